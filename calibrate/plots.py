"""Pictures of a calibration: the posterior's corner plot, the fit's residuals, and the
isolating suites with their steady-state lines.

Written with matplotlib's Agg backend (no display needed), atomically: each
figure is rendered to memory and then written with a temp file and a rename.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from . import calfile
from ._io import atomic_write_bytes
from .fit import predict_batch_times

LABELS = {"t_setup_ns": "T_setup (ns)", "t_step_ns": "T_step (ns)", "t_int_ns": "T_int (ns)",
          "t_sub_ns": "T_sub (ns)", "t_mem_ns": "T_mem (ns)", "t_visit_ns": "T_visit (ns)", "t_hit_ns": "T_hit (ns)",
          "ratio": "r = T_int/T_step"}
#: Figure resolution, dots per inch.
DPI = 110


def _save(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    return path


def corner(cal: dict, path: Path) -> Path:
    """Pairwise scatter and marginal histograms of the posterior samples (constants and r)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = calfile.samples_by_name(cal)
    names = [n for n in ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "t_mem_ns", "t_visit_ns", "t_hit_ns",
                         "ratio") if n in samples]
    k = len(names)
    fig, axes = plt.subplots(k, k, figsize=(2.2 * k, 2.2 * k), squeeze=False)
    for i, yi in enumerate(names):
        for j, xj in enumerate(names):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(samples[xj], bins=40, color="0.4")
                lo, hi = np.percentile(samples[xj], [2.5, 97.5])
                for v in (lo, np.median(samples[xj]), hi):
                    ax.axvline(v, color="tab:red", lw=0.8)
                ax.set_yticks([])
            else:
                ax.plot(samples[xj], samples[yi], ".", ms=1.5, alpha=0.3, color="0.2")
            if i == k - 1:
                ax.set_xlabel(LABELS[xj])
            if j == 0 and i > 0:
                ax.set_ylabel(LABELS[yi])
    fig.suptitle("posterior of the in-context fit (lines: median and 95% interval)")
    out = _save(fig, path)
    plt.close(fig)
    return out


def relative_residuals(cal: dict) -> tuple[list, list, np.ndarray]:
    """(in-context records with values, their ray sets, measured / predicted - 1 of each).

    Each configuration is predicted as the file's predictions are for its ray set:
    by that set's own fit (``by_rays``) when there is one, else by the pooled fit;
    the median over posterior samples against the median of the repeats.
    """
    recs = [m for m in cal["measurements"] if m["kind"] == "in_context" and m["values_ns"]]
    sets = [str(m.get("ray_set") or "") for m in recs]
    rel = np.empty(len(recs))
    for name in sorted(set(sets)):
        idx = [i for i, s in enumerate(sets) if s == name]
        block = calfile.fit_for_rays(cal, name or None)[0]
        design = calfile.design_from_measurements([recs[i] for i in idx], "in_context", include_held_back=True)
        cols = block["samples"]["columns"]
        values = np.asarray(block["samples"]["values"], dtype=float)
        names = [c for c in cols if c != calfile.SCATTER_COLUMN]
        pred = np.median(predict_batch_times(values[:, [cols.index(n) for n in names]], names, design), axis=0)
        rel[idx] = np.array([np.median(recs[i]["values_ns"]) for i in idx]) / pred - 1.0
    return recs, sets, rel


def residuals(cal: dict, path: Path) -> Path:
    """Relative residual of every in-context configuration against its steps and tests per ray."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs, sets, rel = relative_residuals(cal)
    per_set = bool(cal.get("by_rays"))
    held = np.array([bool(m.get("held_back")) for m in recs])
    rays = np.array([m["rays"] for m in recs], dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    colours = dict(zip(sorted(set(sets)), ("tab:blue", "tab:orange", "tab:green", "tab:purple")))
    for ax, key, label in ((axes[0], "steps", "cells stepped per ray"), (axes[1], "tests", "triangle tests per ray")):
        x = np.array([m[key] for m in recs], dtype=float) / rays
        for name, colour in colours.items():
            mine = np.array([s == name for s in sets])
            tag = f"{name} rays" if name else "fitted"
            ax.plot(x[mine & ~held], 100 * rel[mine & ~held], "o", ms=4, color=colour, label=f"{tag}, fitted")
            ax.plot(x[mine & held], 100 * rel[mine & held], "s", ms=5, mfc="none", color=colour,
                    label=f"{tag}, held back")
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel(label)
    axes[0].set_ylabel("measured / predicted - 1 (%)")
    axes[1].legend(fontsize="small")
    fig.suptitle("in-context batch times against " + ("each ray set's own fit" if per_set else "the fitted model"))
    out = _save(fig, path)
    plt.close(fig)
    return out


def _isolated_points(cal: dict, suite: str, per_ray: str):
    """(count per ray, ns per ray, MAD ns per ray, ray set) of one isolating suite's measured records."""
    out = []
    for m in cal["measurements"]:
        if m["kind"] == "isolated" and m.get("suite") == suite and m["values_ns"] and m["rays"] > 0:
            v = np.asarray(m["values_ns"], dtype=float)
            med = float(np.median(v))
            out.append((m[per_ray] / m["rays"], med / m["rays"], float(np.median(np.abs(v - med))) / m["rays"],
                        str(m.get("ray_set") or "")))
    return sorted(out)


def isolated(cal: dict, path: Path) -> Path:
    """The isolating suites per ray: empty grids against steps, one cell against tests.

    Filled points are the steady-state configurations the isolated fit uses (at least
    ``calibrate.run.STEADY_STEPS_PER_RAY`` steps or ``STEADY_TESTS_PER_RAY`` tests a ray),
    open ones the short walks and lists it leaves out.  The line on the left is the fit,
    T_setup + T_step * steps; on the right each ray set's line has the fitted slope T_int
    through the median of its steady points (the intercepts are not part of the file).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .run import STEADY_STEPS_PER_RAY, STEADY_TESTS_PER_RAY

    iso = cal.get("isolated") or {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    panels = ((axes[0], "empty", "steps", STEADY_STEPS_PER_RAY, "cells stepped per ray (empty grids)"),
              (axes[1], "cell", "tests", STEADY_TESTS_PER_RAY, "triangle tests per ray (one cell)"))
    colours = {"isotropic": "tab:blue", "aimed": "tab:orange"}
    for ax, suite, per_ray, threshold, label in panels:
        pts = _isolated_points(cal, suite, per_ray)
        ax.set_xlabel(label)
        if not pts:
            ax.text(0.5, 0.5, "no measurements", ha="center", va="center", transform=ax.transAxes)
            continue
        for ray_set in sorted({p[3] for p in pts}):
            mine = [p for p in pts if p[3] == ray_set]
            x = np.array([p[0] for p in mine])
            y = np.array([p[1] for p in mine])
            err = np.array([p[2] for p in mine])
            steady = x >= threshold
            colour = colours.get(ray_set, "0.3")
            name = "missing rays" if (suite == "cell" and ray_set == "isotropic") else (
                "aimed rays" if ray_set == "aimed" else "isotropic rays")
            ax.errorbar(x[steady], y[steady], yerr=err[steady], fmt="o", ms=4, color=colour,
                        label=f"{name}, fitted")
            ax.errorbar(x[~steady], y[~steady], yerr=err[~steady], fmt="o", ms=4, mfc="none", color=colour,
                        label=f"{name}, short (left out)")
            xs = np.linspace(0.0, float(x.max()), 50)
            if suite == "empty" and iso.get("t_step_ns") and iso.get("t_setup_ns"):
                ax.plot(xs, iso["t_setup_ns"]["median"] + iso["t_step_ns"]["median"] * xs, "-", lw=1, color=colour,
                        label=f"T_setup + T_step x steps, T_step = {iso['t_step_ns']['median']:.3g} ns")
            elif suite == "cell" and iso.get("t_int_ns") and steady.any():
                slope = iso["t_int_ns"]["median"]
                base = float(np.median(y[steady] - slope * x[steady]))
                ax.plot(xs, base + slope * xs, "-", lw=1, color=colour,
                        label=f"slope T_int = {slope:.3g} ns" if ray_set == "isotropic" else None)
        ax.set_xlim(left=0.0)
        ax.set_ylim(bottom=0.0)
        ax.legend(fontsize="x-small")
    axes[0].set_ylabel("ns per ray")
    r = iso.get("ratio")
    fig.suptitle("isolating suites: marginal costs in cache"
                 + (f" (r = {r['median']:.3g}, 95% [{r['ci95'][0]:.3g}, {r['ci95'][1]:.3g}])" if r else ""))
    out = _save(fig, path)
    plt.close(fig)
    return out


def plot_paths(prefix: Path) -> tuple[Path, Path, Path]:
    """The files :func:`calibration_plots` writes for ``prefix``: (corner, residuals, isolated)."""
    prefix = Path(prefix)
    base = prefix.name[:-4] if prefix.suffix == ".png" else prefix.name
    return (prefix.with_name(base + "-corner.png"), prefix.with_name(base + "-residuals.png"),
            prefix.with_name(base + "-isolated.png"))


def calibration_plots(cal: dict, prefix: Path) -> list[Path]:
    """Write PREFIX-corner.png, PREFIX-residuals.png and PREFIX-isolated.png; returns their paths."""
    corner_path, residuals_path, isolated_path = plot_paths(prefix)
    return [corner(cal, corner_path), residuals(cal, residuals_path), isolated(cal, isolated_path)]

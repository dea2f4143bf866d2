"""`calibrate compare`: measured traversal time against resolution, beside the prediction.

For each scene, :func:`compare_scene` predicts the grid (:func:`calibrate.predict.predict`),
then measures real traversal time (:mod:`calibrate.sweep`) over a log-spaced sweep of
resolutions from 1/4 to 4 times the predicted optimum per axis, for each depth it
compares, together with the predicted grid and every baseline heuristic's grid, all in
one interleaved measurement; then the grids that decide the penalties (the predicted one and
those around each curve's minimum) are timed again (REFINE_ROUNDS), their values put on
the sweep's scale (:func:`refine_level`) before they join it.  It reports

- the measured optimum: the vertex of a smooth fit through the points near each
  curve's lowest one (:func:`calibrate.sweep.fit_minimum`), the lowest over depths;
- ``penalty = time(predicted) / time(measured best) - 1``, and the same for each baseline
  (pbrt v2, Manta 8N, Manta's two-level top, Cleary lambda = 5, Kalojanov's two-level grid);
- the predicted curve: the constants times the model's counts per ray (uniform grids:
  the general model with the effects the prediction kept; nested grids: the kernel's
  counts, the model not being defined for scaled subgrids), with the posterior's 95% band;
  with a calibrated T_hit, plus T_hit times the share of the sweep's rays that hit.

Curves (``--levels``): ``1`` sweeps uniform grids, ``2`` two-level grids whose top and
depth-1 subgrid resolutions are both scaled by the square root of the sweep factor (so
the leaf cells' size scales by the factor), ``auto`` both (and the predicted depth when
it is 3).  With ``auto`` the measured best is the best over the depths, so a wrong depth
choice shows as a penalty.
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from pathlib import Path

import numpy as np

from . import predict as _predict
from . import sweep as _sweep
from ._grid import Scene
from ._io import UserError, atomic_write_bytes, check_writable
from .protocol import median_mad
from .sweep import GridSpec

#: Sweep points per curve (log-spaced per-axis factors) and the sweep's span each way.
DEFAULT_POINTS = 13
MIN_POINTS = 3
MAX_POINTS = 64
SWEEP_SPAN = 4.0
#: Rays per batch and their seed (the same rays for every grid of a scene): as many distinct rays
#: as the calibration's in-context batches (calibrate.suites.CONTEXT_RAYS_PER_BATCH), whose
#: comment says why a short batch traced again and again times a grid too fast.
DEFAULT_RAY_COUNT = 16384
#: Most rays per batch on the command line: a batch's rays and hits (64 bytes a ray) stay in memory.
MAX_RAY_COUNT = 2**24
RAY_SEED = 1
LEVEL_CHOICES = ("1", "2", "auto")
#: Baselines built as nested grids: name -> (kernel rule scale, exponents); the rest are uniform.
#: Manta RecursiveGrid (Ize et al. 2007): (8 n)^(3 / (2L + 1 - 2 depth)) cells per subgrid.
#: Kalojanov, Billeter, Slusallek 2011: leaf grids of density 1.2 references per cell.
NESTED_BASELINES = {"manta-L2-top": (8.0, None), "kalojanov-2level": (1.2, (1.0, 1.0))}
#: After the sweep, the grids that decide the penalties -- each curve's points in its minimum's
#: fit window (:func:`calibrate.sweep.fit_minimum`) and the predicted grid -- are built again
#: (REFINE_BUILDS times) and timed REFINE_ROUNDS more times, interleaved, their values joining
#: the sweep's.  On a noisy host a point's median is uncertain by 3-5% after the sweep's
#: values, and the predicted point and the curve's minimum are the two the penalty compares.
REFINE_ROUNDS = 16
REFINE_BUILDS = 2
#: The refinement's values are put on the sweep's scale before they join it: divided by its
#: level, the median over the grids timed again of (their median in the refinement / their
#: median in the sweep), when at least this many grids were timed again (else 1).  Timed
#: apart from the other grids, a few minutes later, the same grids ran at a common level
#: 0.66-0.78 (armadillo), 0.83-0.98 (sphere) and 1.08-1.35 (cylinder1996) times the
#: sweep's (2026-12-03, evening): joined as timed, the refined points sat off the curve
#: of the others and the measured best moved to whichever kind the level favoured.
REFINE_LEVEL_MIN_GRIDS = 3
#: Bootstrap replicates of a penalty's 95% interval, and their seed.  Each replicate draws
#: every measured grid's values again with replacement (independently: values of one grid
#: are taken as exchangeable), takes their median, finds each curve's minimum as the
#: measurement does and forms the penalty; the interval is the central 95% of the
#: replicates.  On a noisy host a penalty of a few per cent can be the noise's.
PENALTY_BOOTSTRAP = 400
PENALTY_BOOTSTRAP_SEED = 12345
#: Plot: figure size per scene panel (inches) and resolution.
PANEL_INCHES = (5.2, 4.6)
DPI = 90
PANEL_COLUMNS = 2


# ---------------------------------------------------------------------------------------
# one scene
# ---------------------------------------------------------------------------------------

def sweep_factors(points: int, span: float = SWEEP_SPAN) -> np.ndarray:
    """``points`` per-axis factors log-spaced from 1/span to span (1 is among them for odd counts)."""
    return span ** np.linspace(-1.0, 1.0, int(points))


def _plan_spec(plan: dict, ratio: float, label: str) -> GridSpec:
    levels = plan["levels"]
    top = tuple(levels[0]["resolution"])
    if len(levels) == 1:
        return GridSpec("uniform", [top], label=label)
    return GridSpec("nested", [top], depth=len(levels), subgrids="model", ratio=ratio, label=label)


def _curve_spec(centre: GridSpec, f: float) -> GridSpec:
    """The centre spec at sweep factor f: uniform axes times f; nested top and subgrids times sqrt(f)."""
    return centre.scaled(f) if centre.kind == "uniform" else centre.scaled(math.sqrt(f))


def _baseline_specs(pred: dict) -> dict:
    out = {}
    for name, d in pred["baselines_detail"].items():
        top = tuple(d["levels"][0])
        if name in NESTED_BASELINES:
            scale, exps = NESTED_BASELINES[name]
            out[name] = GridSpec("nested", [top], depth=2, subgrids="rule", scale=scale, exponents=exps, label=name)
        else:
            out[name] = GridSpec("uniform", [top], label=name)
    return out


def _model_counts(stats, terms, spec: GridSpec, point: dict) -> tuple[float, float, float, float, str]:
    """(steps, tests, subgrids, visits, source) of the predicted curve at one sweep point, the visits
    what T_visit prices: occupied cells entered and changes of occupancy."""
    from models.general import predict_uniform, stopped_tests_per_ray

    if spec.kind == "uniform":
        _, steps, _ = predict_uniform(stats, spec.top, 0.0, 1.0, 1.0, overlap="exact", terms=terms)
        tests = stopped_tests_per_ray(stats, spec.top, terms=terms)
        return steps, tests, 0.0, _predict._priced_visits(stats, spec.top, terms), "model"
    return (point["steps"], point["tests"], point["subgrids"], point.get("visits", 0.0) + point.get("changes", 0.0),
            "kernel")


def compare_scene(scene, *, constants=None, samples=None, ratio=None, levels: str = "auto",
                  fidelity: str = "analytic", rays: str = "isotropic", points: int = DEFAULT_POINTS,
                  ray_count: int = DEFAULT_RAY_COUNT,
                  rounds: int = _sweep.SWEEP_ROUNDS, builds: int = _sweep.SWEEP_BUILDS,
                  min_time: float = _sweep.SWEEP_MIN_VALUE_NS * 1e-9,
                  prime: bool = _sweep.SWEEP_PRIME, seed: int = 0, clock: str = _sweep.DEFAULT_CLOCK,
                  refine_rounds: int = REFINE_ROUNDS, progress=None, status=None) -> dict:
    """Measured sweep, predicted curve and penalties of one scene (module docstring).

    scene : Scene, built-in name or mesh path; constants / samples / ratio : as
    :func:`calibrate.predict.predict`; levels : "1" | "2" | "auto"; fidelity : the
    prediction's ("paper" | "analytic" | "simulated"); rays : "isotropic" |
    "camera"; points : sweep points per curve (>= 3); ray_count : rays per batch;
    rounds, builds, min_time : values per grid, the builds of every grid they are spread
    over (:func:`calibrate.sweep.sweep`) and seconds per value; prime : one untimed
    call before each value (as :func:`calibrate.sweep.sweep`); clock : "thread" (the timing
    thread's CPU time) or "wall" (the kernel's monotonic clock); refine_rounds : values added to
    the grids that decide the penalties (REFINE_ROUNDS; 0: none).

    Returns a JSON-ready dict: ``scene``, ``triangles``, ``units``, ``penalty``,
    ``penalty_ci95`` (its bootstrap 95% interval, :func:`penalty_intervals`),
    ``predicted_resolution`` (top level), ``predicted_levels``, ``predicted_time_ns``,
    ``best_measured_resolution``, ``best_measured_levels``, ``best_measured_time_ns``,
    ``baselines`` (name -> ``resolution``, ``levels``, ``penalty``, ``penalty_ci95``, ``time_ns``,
    ``mad_ns``, ``cells``), ``curves`` (per depth: ``levels``, ``fit``, ``points``),
    ``points`` (every sweep point), ``hits_per_ray`` (the share of the sweep's rays that hit,
    priced at T_hit in the predicted curve; 0 without T_hit), ``notes``.
    """
    levels = _predict._check_choice("levels", levels, LEVEL_CHOICES)
    rays = _predict._check_choice("ray set", rays, _predict.RAY_KINDS)
    points = _check_points(points)
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    k = _predict.resolve_constants(constants, samples, ratio)
    src = dict(constants=constants, samples=samples, ratio=ratio)
    say = status or (lambda text: None)
    say(f"{scene.name}: predicting")
    fidelity = _predict._check_choice("fidelity", fidelity, _predict.FIDELITIES)
    pred = _predict.predict(scene, levels=levels, rays=rays, fidelity=fidelity, **src)
    chosen = _plan_spec(pred, k.ratio, "predicted")
    depths = {"1": [1], "2": [2], "auto": [1, 2]}[levels]
    if len(pred["levels"]) not in depths:
        depths.append(len(pred["levels"]))
    centres = {}
    for L in depths:
        if L == len(pred["levels"]):
            centres[L] = chosen
        else:
            centres[L] = _plan_spec(_predict.predict(scene, levels=str(L), rays=rays, fidelity=fidelity, **src),
                                    k.ratio, f"L={L} plan")
    factors = sweep_factors(points)
    curve_specs = {L: [_curve_spec(c, f) for f in factors] for L, c in centres.items()}
    baselines = _baseline_specs(pred)
    # one measurement of every distinct grid, interleaved; the curves built coarse to fine,
    # the depths side by side, so that the sweep's memory budget
    # (calibrate.sweep.MAX_SWEEP_TOTAL_BYTES) drops the finest (largest) points of every
    # depth, not the last depths' whole curves
    unique: list[GridSpec] = []
    index: dict[GridSpec, int] = {}
    coarse_first = [specs[j] for j in range(len(factors)) for specs in curve_specs.values()]
    for spec in [chosen, *baselines.values(), *coarse_first]:
        if spec not in index:
            index[spec] = len(unique)
            unique.append(spec)
    say(f"{scene.name}: building {len(unique)} grids")
    o, d = _predict._rays(scene, rays, int(ray_count), RAY_SEED)
    try:
        measured = _sweep.sweep(scene, unique, (o, d), rounds=rounds, builds=builds, min_time=min_time, seed=seed,
                                prime=prime, progress=progress, status=lambda text: say(f"{scene.name}: {text}"),
                                required=(index[chosen],), clock=clock)
    except ValueError as exc:
        raise UserError(f"{scene.name}: the predicted grid cannot be measured ({exc})") from None
    level = None
    if refine_rounds:
        deciding = _deciding_grids(factors, curve_specs, index, measured, chosen)
        say(f"{scene.name}: timing the {len(deciding)} grids that decide the penalty again")
        again = _sweep.sweep(scene, [unique[i] for i in deciding], (o, d), rounds=int(refine_rounds),
                             builds=min(REFINE_BUILDS, int(refine_rounds)), min_time=min_time, seed=seed + 1,
                             prime=prime, progress=progress, status=lambda text: say(f"{scene.name}: {text}"),
                             clock=clock)
        level = refine_level([measured[i] for i in deciding], again)
        for i, extra in zip(deciding, again):
            _join_values(measured[i], extra, level)
    stats = _predict.scene_statistics(scene)
    terms = _predict.analytic_uniform_plan(stats, k, False)[0]["terms"]
    notes = list(k.notes)
    extrapolated = _predict.extrapolation_note(k, pred["memory_bytes"])
    if extrapolated:
        notes.append(extrapolated)
    # the share of the sweep's own rays that hit (the same first hits in every grid; the
    # predicted grid's count), priced at T_hit
    hits = float(measured[index[chosen]]["hits"]) if k.t_hit > 0 else 0.0
    curves, all_points = [], []
    for L, specs in curve_specs.items():
        pts = []
        for f, spec in zip(factors, specs):
            m = measured[index[spec]]
            p = dict(levels=L, factor=float(f), resolution=list(spec.top), sub_scale=spec.sub_scale
                     if spec.kind == "nested" else None, **{key: m.get(key) for key in (
                         "median_ns", "mad_ns", "steps", "tests", "subgrids", "visits", "changes", "cells",
                         "memory_bytes", "skipped")},
                     values=len(m.get("values_ns") or []))
            if "median_ns" in m:
                steps, tests, subs, visits, source = _model_counts(stats, terms, spec, m)
                mem = float(m.get("memory_bytes") or 0.0)
                if spec.kind == "uniform":  # the bytes the plan's memory term charges (what rays read)
                    mem = _predict.charged_bytes(stats, spec.top, k, steps, tests, mem)
                band = k.cost_samples(steps, tests, subs, mem, visits, hits)
                p["predicted"] = dict(median=float(np.median(band)), ci95=[float(np.percentile(band, 2.5)),
                                                                         float(np.percentile(band, 97.5))],
                                      counts=source)
            pts.append(p)
        ok = [p for p in pts if p.get("median_ns") is not None]
        if len(ok) < MIN_POINTS:
            notes.append(f"L={L}: only {len(ok)} sweep points measured; no curve minimum")
            curves.append(dict(levels=L, centre=centres[L].to_dict(), points=pts, fit=None))
            all_points.extend(pts)
            continue
        fit = _sweep.fit_minimum([p["factor"] for p in ok], [p["median_ns"] for p in ok],
                                 mads=[p["mad_ns"] for p in ok], counts=[p["values"] for p in ok])
        best_spec = _curve_spec(centres[L], fit["scale"])
        fit = dict(fit, factor=fit.pop("scale"), resolution=list(best_spec.top),
                   sub_scale=best_spec.sub_scale if best_spec.kind == "nested" else None)
        if fit["at_edge"]:
            notes.append(f"L={L}: the lowest measured time is at the sweep's "
                         f"{'coarse' if fit['window'][0] == 0 else 'fine'} end; the true optimum may lie beyond")
        curves.append(dict(levels=L, centre=centres[L].to_dict(), points=pts, fit=fit))
        all_points.extend(pts)
    fitted = [c for c in curves if c["fit"] is not None]
    if not fitted:
        raise UserError(f"{scene.name}: too few grids could be built and measured to locate a minimum")
    best_curve = min(fitted, key=lambda c: c["fit"]["time"])
    t_best = best_curve["fit"]["time"]
    mc = measured[index[chosen]]
    if "median_ns" not in mc:
        raise UserError(f"{scene.name}: the predicted grid could not be built ({mc.get('skipped')})")
    # the penalties' intervals: every measured grid's values drawn again
    boot_curves = [[(f, index[spec]) for f, spec in zip(factors, curve_specs[c["levels"]])
                    if measured[index[spec]].get("values_ns")] for c in fitted]
    boot_choices = {name: index[spec] for name, spec in [("predicted", chosen), *baselines.items()]
                    if measured[index[spec]].get("values_ns")}
    needed = {i for pts in boot_curves for _, i in pts} | set(boot_choices.values())
    intervals = penalty_intervals({i: measured[i]["values_ns"] for i in needed}, boot_curves, boot_choices)
    out_base = {}
    for name, spec in baselines.items():
        m = measured[index[spec]]
        row = dict(resolution=list(spec.top), levels=1 if spec.kind == "uniform" else spec.depth,
                   cells=m.get("cells"))
        if "median_ns" in m:
            row.update(penalty=_sweep.penalty(m["median_ns"], t_best), penalty_ci95=intervals.get(name),
                       time_ns=m["median_ns"], mad_ns=m["mad_ns"])
        else:
            row.update(penalty=None, time_ns=None, mad_ns=None, skipped=m.get("skipped"))
        out_base[name] = row
    units = "ns" if k.units == "ns" else "T_step"
    if units != "ns":
        # ratio mode: the curve is in units of T_step; one scale (the median of measured over
        # predicted) puts it beside the measured points, so only its shape is compared.
        pairs = [(p["median_ns"], p["predicted"]["median"]) for p in all_points if p.get("predicted")]
        t_step_ns = float(np.median([a / b for a, b in pairs]))
        for p in all_points:
            if p.get("predicted"):
                pr = p["predicted"]
                pr.update(median=pr["median"] * t_step_ns, ci95=[x * t_step_ns for x in pr["ci95"]])
        notes.append(f"ratio mode: the predicted curve is in units of T_step, drawn with T_step = {t_step_ns:.3g} ns "
                     "(the median of measured / predicted over the sweep): compare its shape, not its height")
    else:
        t_step_ns = None
    return _predict.json_ready(dict(
        scene=scene.name, triangles=scene.n_triangles, units=units, fidelity=fidelity, rays=rays, clock=clock,
        ray_count=int(ray_count),
        constants=pred["constants"], penalty=_sweep.penalty(mc["median_ns"], t_best),
        penalty_ci95=intervals.get("predicted"),
        predicted_resolution=list(chosen.top), predicted_levels=len(pred["levels"]),
        predicted_level_resolutions=[lv["resolution"] for lv in pred["levels"]],
        predicted_time_ns=mc["median_ns"], predicted_mad_ns=mc["mad_ns"], predicted_cells=mc["cells"],
        best_measured_resolution=best_curve["fit"]["resolution"], best_measured_levels=best_curve["levels"],
        best_measured_time_ns=t_best, best_measured_factor=best_curve["fit"]["factor"],
        baselines=out_base, curves=curves, points=all_points, t_step_scale_ns=t_step_ns, refine_level=level,
        hits_per_ray=hits, notes=notes))


def _deciding_grids(factors, curve_specs: dict, index: dict, measured: list, chosen) -> list[int]:
    """Sweep indices of the grids that decide the penalties: the predicted grid, and each curve's
    points in the fit window of its minimum."""
    out = {index[chosen]}
    for specs in curve_specs.values():
        ok = [(f, index[spec]) for f, spec in zip(factors, specs) if measured[index[spec]].get("median_ns") is not None]
        if len(ok) >= MIN_POINTS:
            rows = [measured[i] for _, i in ok]
            fit = _sweep.fit_minimum([f for f, _ in ok], [m["median_ns"] for m in rows],
                                     mads=[m["mad_ns"] for m in rows], counts=[len(m["values_ns"]) for m in rows])
            lo, hi = fit["window"]
            out.update(i for _, i in ok[lo:hi + 1])
    return sorted(i for i in out if measured[i].get("median_ns") is not None)


def refine_level(rows: list, extras: list) -> float:
    """The refinement's common level against the sweep's (REFINE_LEVEL_MIN_GRIDS): the median
    over grids measured in both of ``extra median / row median``, or 1.0 with fewer grids."""
    ratios = [e["median_ns"] / r["median_ns"] for r, e in zip(rows, extras)
              if r.get("median_ns") and e.get("median_ns")]
    return float(np.median(ratios)) if len(ratios) >= REFINE_LEVEL_MIN_GRIDS else 1.0


def _join_values(row: dict, extra: dict, level: float = 1.0) -> None:
    """Add a second timing's values of one grid to its sweep row, divided by ``level`` (the
    second timing's common level, :func:`refine_level`); median, MAD and builds again.  The
    values as timed join ``raw_values_ns``."""
    if extra.get("median_ns") is None:
        return
    row["values_ns"] = list(row["values_ns"]) + [v / level for v in extra["values_ns"]]
    if "raw_values_ns" in row and "raw_values_ns" in extra:
        row["raw_values_ns"] = list(row["raw_values_ns"]) + list(extra["raw_values_ns"])
    else:
        row.pop("raw_values_ns", None)
    row["median_ns"], row["mad_ns"] = (float(x) for x in median_mad(row["values_ns"]))
    row["builds"] = row.get("builds", 0) + extra.get("builds", 0)
    row["warnings"] = list(row.get("warnings", [])) + [w for w in extra.get("warnings", []) if w not in row.get("warnings", [])]


def penalty_intervals(values: dict, curves: list, choices: dict, *, replicates: int = PENALTY_BOOTSTRAP,
                      seed: int = PENALTY_BOOTSTRAP_SEED) -> dict:
    """Bootstrap 95% intervals of penalties (see PENALTY_BOOTSTRAP).

    values : {grid index: (n,) values, ns per ray}; curves : one list per fitted curve of
    (factor, grid index) for its measured points, in increasing factor; choices : {name:
    grid index} of the grids whose penalty is wanted.  Returns {name: [low, high]}
    ({} when a replicate finds no minimum for any curve)."""
    rng = np.random.default_rng(seed)
    idx = sorted(values)
    arrays = {i: np.asarray(values[i], dtype=np.float64) for i in idx}
    draws = {name: [] for name in choices}
    for _ in range(int(replicates)):
        med, mad = {}, {}
        for i in idx:
            v = arrays[i][rng.integers(0, arrays[i].size, arrays[i].size)]
            med[i] = float(np.median(v))
            mad[i] = float(np.median(np.abs(v - med[i])))
        best = math.inf
        for pts in curves:
            fit = _sweep.fit_minimum([f for f, _ in pts], [med[i] for _, i in pts], mads=[mad[i] for _, i in pts],
                                     counts=[arrays[i].size for _, i in pts])
            best = min(best, fit["time"])
        if not math.isfinite(best):
            return {}
        for name, i in choices.items():
            draws[name].append(med[i] / best - 1.0)
    return {name: [float(np.percentile(d, 2.5)), float(np.percentile(d, 97.5))] for name, d in draws.items() if d}


def _check_points(points) -> int:
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or not (
            MIN_POINTS <= points <= MAX_POINTS):
        raise UserError(f"--points must be a whole number from {MIN_POINTS} to {MAX_POINTS}, got {points!r}")
    return int(points)


def summarise(results: list[dict]) -> dict:
    """Median and worst penalty of the prediction and of each baseline over scenes; for the
    prediction also ``worst_sure``, the highest lower end of a scene's 95% interval, and its
    ``worst_sure_scene`` (None without intervals).

    The worst penalty over many scenes is the largest of many noisy ratios: on this project's
    2-core EPYC host one plan (the teapot's 28x15x17) measured +0.0% to +1.4% in four sweeps and
    +3.6% [-0.6, +7.5] in a fifth (docs/compare.md, "Which cache the plans want").  The lower end
    says how much of the worst the sweep is sure of."""
    def stats(values):
        v = [x for x in values if x is not None]
        return dict(median=float(np.median(v)) if v else None, worst=float(max(v)) if v else None, scenes=len(v))

    names = []
    for r in results:
        names.extend(n for n in r["baselines"] if n not in names)
    predicted = stats([r["penalty"] for r in results])
    lows = [(r["penalty_ci95"][0], r["scene"]) for r in results
            if r.get("penalty") is not None and r.get("penalty_ci95")]
    sure = max(lows) if lows else (None, None)
    predicted.update(worst_sure=None if sure[0] is None else float(sure[0]), worst_sure_scene=sure[1])
    return dict(predicted=predicted,
                baselines={n: stats([r["baselines"].get(n, {}).get("penalty") for r in results]) for n in names})


# ---------------------------------------------------------------------------------------
# plot
# ---------------------------------------------------------------------------------------

CURVE_COLOURS = {1: "tab:blue", 2: "tab:orange", 3: "tab:green"}
BASELINE_MARKERS = {"pbrt-v2": "v", "manta-L1": "s", "manta-L2-top": "D", "cleary-lambda5": "^",
                    "kalojanov-2level": "P"}


def plot(results: list[dict], path) -> Path:
    """One panel per scene: measured points (median, MAD bars) against total cells, the
    predicted curve and its 95% band, and a marker per choice.  Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = min(PANEL_COLUMNS, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(PANEL_INCHES[0] * cols, PANEL_INCHES[1] * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax, r in zip(axes.flat, results):
        for c in r["curves"]:
            colour = CURVE_COLOURS.get(c["levels"], "0.3")
            pts = [p for p in c["points"] if p.get("median_ns") is not None]
            x = np.array([p["cells"] for p in pts], dtype=float)
            y = np.array([p["median_ns"] for p in pts])
            ax.errorbar(x, y, yerr=[p["mad_ns"] for p in pts], fmt="o", ms=3.5, color=colour, capsize=2,
                        label=f"measured, {c['levels']} level{'s' if c['levels'] > 1 else ''}")
            pr = [p["predicted"] for p in pts]
            ax.plot(x, [q["median"] for q in pr], "-", color=colour, lw=1.2, alpha=0.8)
            ax.fill_between(x, [q["ci95"][0] for q in pr], [q["ci95"][1] for q in pr], color=colour, alpha=0.15,
                            lw=0)
            if c["fit"] is not None and c["levels"] == r["best_measured_levels"]:
                f = c["fit"]
                near = min(pts, key=lambda p: abs(math.log(p["factor"] / f["factor"])))
                ax.plot([near["cells"] * (f["factor"] / near["factor"]) ** 3], [f["time"]], "o", ms=11,
                        mfc="none", mec="k", mew=1.5, label="best measured (fit)")
        ax.plot([r["predicted_cells"]], [r["predicted_time_ns"]], "*", ms=14, color="tab:red",
                label=f"predicted ({100 * r['penalty']:+.1f}%)")
        for name, b in r["baselines"].items():
            if b.get("time_ns") is None:
                continue
            ax.plot([b["cells"]], [b["time_ns"]], BASELINE_MARKERS.get(name, "x"), ms=7, color="0.25", mfc="none",
                    label=f"{name} ({100 * b['penalty']:+.0f}%)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cells (all levels)")
        ax.set_ylabel(f"ns per ray ({'thread CPU' if r.get('clock', 'thread') == 'thread' else 'wall'} time)")
        ax.set_title(f"{r['scene']} ({r['triangles']:,} triangles)", fontsize=10)
        ax.legend(fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    fig.suptitle("measured (points, MAD bars) and predicted (lines, 95% band) time per ray", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def _points_arg(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--points must be a whole number, got {text!r}") from None
    if not MIN_POINTS <= n <= MAX_POINTS:
        raise argparse.ArgumentTypeError(f"--points must be from {MIN_POINTS} to {MAX_POINTS}, got {n}")
    return n


def _count_arg(what: str, lo: int, hi: int | None = None):
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a whole number, got {text!r}") from None
        if n < lo:
            raise argparse.ArgumentTypeError(f"{what} must be at least {lo}, got {n}")
        if hi is not None and n > hi:
            raise argparse.ArgumentTypeError(f"{what} must be at most {hi:,}, got {n}")
        return n

    return parse


def add_parser(sub):
    """Register the ``compare`` verb on an argparse subparsers object; returns its parser."""
    from .cli import positive_number

    help_text = "measure traversal time over resolutions around the prediction; penalties of it and the baselines"
    sp = sub.add_parser("compare", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")
    sp.add_argument("meshes", nargs="*", metavar="MESH|SCENE",
                    help="mesh files or built-in scene names (default: every built-in scene)")
    _predict.add_constants_options(sp, "predict from your own T_int/T_step alone")
    sp.add_argument("--levels", default="auto", choices=LEVEL_CHOICES,
                    help="depths to sweep and predict (auto: uniform and two-level, the prediction's own depth)")
    sp.add_argument("--fidelity", default="analytic", choices=_predict.FIDELITIES,
                    help="the prediction's fidelity (as calibrate predict's)")
    sp.add_argument("--rays", default="isotropic", choices=_predict.RAY_KINDS)
    sp.add_argument("--points", type=_points_arg, default=DEFAULT_POINTS, metavar="N",
                    help=f"sweep points per depth, 1/{SWEEP_SPAN:g}x to {SWEEP_SPAN:g}x per axis "
                         f"(default {DEFAULT_POINTS})")
    sp.add_argument("--ray-count", type=_count_arg("--ray-count", 1, MAX_RAY_COUNT), default=DEFAULT_RAY_COUNT, metavar="N",
                    help=f"rays per timed batch (default {DEFAULT_RAY_COUNT})")
    sp.add_argument("--rounds", type=_count_arg("--rounds", 1), default=_sweep.SWEEP_ROUNDS, metavar="N",
                    help=f"timed values per grid (default {_sweep.SWEEP_ROUNDS})")
    sp.add_argument("--builds", type=_count_arg("--builds", 1), default=_sweep.SWEEP_BUILDS, metavar="N",
                    help=f"builds of every grid the values are spread over: where a grid lies in memory moves its "
                         f"time by a few per cent (default {_sweep.SWEEP_BUILDS})")
    sp.add_argument("--refine-rounds", type=_count_arg("--refine-rounds", 0), default=REFINE_ROUNDS, metavar="N",
                    help=f"values added, after the sweep, to the predicted grid and the points around each curve's "
                         f"minimum, the grids the penalties compare (default {REFINE_ROUNDS}; 0: none)")
    sp.add_argument("--min-time", type=positive_number("--min-time"), default=_sweep.SWEEP_MIN_VALUE_NS * 1e-9,
                    metavar="SECONDS", help=f"shortest timed value (default {_sweep.SWEEP_MIN_VALUE_NS * 1e-9:g} s)")
    sp.add_argument("--clock", default=_sweep.DEFAULT_CLOCK, choices=_sweep.CLOCKS,
                    help="thread: the timing thread's CPU time (default; a busy host's waits left out); wall: the "
                         "kernel's wall clock, as calibrate run times")
    sp.add_argument("--plot", metavar="FILE", help="write a PNG: measured points, predicted curve, choices")
    sp.set_defaults(func=cmd_compare)
    return sp


def cmd_compare(args) -> int:
    """Run the ``compare`` verb: JSON on stdout with ``--json``, else rich tables."""
    import json

    from .cli import _Progress
    from .scenes import builtin_names

    src = _predict.constants_from_args(args, rays=args.rays)
    if args.plot:
        plot_path = Path(args.plot)
        if not plot_path.is_dir() and plot_path.suffix.lower() != ".png":
            raise UserError(f"--plot {plot_path}: the plot is a PNG; give a file name ending in .png")
        check_writable(plot_path)  # a directory, a missing or read-only directory, a write-protected file
    names = args.meshes or builtin_names()
    scenes = [Scene.load(name) for name in names]  # every input checked before anything is measured
    results, skipped = [], []
    with _Progress(not args.quiet, "comparing") as bar:
        for i, scene in enumerate(scenes):
            def status(text, i=i):
                bar.status(f"[{i + 1}/{len(scenes)}] {text}")

            try:
                results.append(compare_scene(scene, levels=args.levels, fidelity=args.fidelity, rays=args.rays,
                                             points=args.points, ray_count=args.ray_count, rounds=args.rounds,
                                             builds=args.builds, min_time=args.min_time, clock=args.clock,
                                             refine_rounds=args.refine_rounds, progress=bar,
                                             status=status, **src))
            except UserError as exc:  # a scene whose grids cannot be built: the others still count
                if len(scenes) == 1:
                    raise
                skipped.append(str(exc))
    for reason in skipped:
        print(f"calibrate: warning: skipped {reason}", file=sys.stderr)
    if not results:
        raise UserError("no scene could be measured: " + "; ".join(skipped))
    summary = summarise(results)
    if args.plot:
        plot(results, Path(args.plot))
    if args.json:
        doc = dict(scenes=results, summary=summary, skipped=skipped)
        sys.stdout.write(json.dumps(doc, indent=2, allow_nan=False) + "\n")
        return 0
    _print_human(results, summary, args.plot)
    return 0


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:+.1f}%"


def _pct_ci(x, ci) -> str:
    """A penalty with its 95% interval, in per cent."""
    return _pct(x) if x is None or not ci else f"{100 * x:+.1f}% [{100 * ci[0]:+.1f}, {100 * ci[1]:+.1f}]"


def _fmt_res(res) -> str:
    return "x".join(str(v) for v in res)


def _print_human(results, summary, plot_path) -> None:
    from rich.table import Table

    from .cli import _console

    console = _console()
    names = list(summary["baselines"])
    table = Table(title="penalty = time(choice) / time(measured best) - 1  (measured, ns per ray; "
                        "the prediction's with its bootstrap 95% interval)")
    for col in ("scene", "predicted", "best measured", "penalty", *names):
        table.add_column(col, justify="right")
    for r in results:
        pred = f"{_fmt_res(r['predicted_resolution'])} L{r['predicted_levels']}"
        best = f"{_fmt_res(r['best_measured_resolution'])} L{r['best_measured_levels']}"
        table.add_row(r["scene"], pred, best, _pct_ci(r["penalty"], r.get("penalty_ci95")),
                      *(_pct(r["baselines"][n]["penalty"])
                                                                     if n in r["baselines"] else "-"
                                                                     for n in names))
    if len(results) > 1:
        s = summary["predicted"]
        table.add_row("median", "", "", _pct(s["median"]), *(_pct(summary["baselines"][n]["median"]) for n in names))
        table.add_row("worst", "", "", _pct(s["worst"]), *(_pct(summary["baselines"][n]["worst"]) for n in names))
    console.print(table)
    if len(results) > 1 and summary["predicted"].get("worst_sure") is not None:
        console.print(f"the worst penalty the sweeps are sure of (the highest lower end of a 95% interval): "
                      f"{_pct(summary['predicted']['worst_sure'])} ({summary['predicted']['worst_sure_scene']})")
    for r in results:
        console.print(f"{r['scene']}: predicted {r['predicted_time_ns']:.4g} ns/ray (MAD {r['predicted_mad_ns']:.2g}), "
                      f"measured best {r['best_measured_time_ns']:.4g} ns/ray at "
                      f"{_fmt_res(r['best_measured_resolution'])} (L{r['best_measured_levels']})")
        for note in r["notes"]:
            console.print(f"  note: {note}")
    if plot_path:
        console.print(f"plot written to {plot_path}")

"""`calibrate paper`: the talk's claims, measured on this host, side by side.

The talk ("Grid Creation Strategies for Efficient Ray Tracing", Ize, Shirley and
Parker, RT 2007) makes five measurable claims about its scene classes.  Each is
measured here on the built-in scenes with real traversal times (the un-instrumented
kernel, interleaved repeats, median: :func:`calibrate.sweep.sweep`) on isotropic
random rays through the scene's box (the talk's "all rays hit the grid and are
equally likely"), and judged:

``compact-5pct``
    "Get within 5% of optimal for tested scenes": the points law ``M = 2 N r`` against
    the measured best of a short sweep, on bumpy spheres of several sizes (compact,
    scan-like triangles).
``lines-optimal``
    "O(N^1.5) cells produces grids within 3% of optimal performance" (the lines law
    ``M = (N r)^1.5``), and "extremely large 19,996 tri cylinder within 10% of optimal".
``linear-slowdown``
    "O(N) cells results in a 1.25x - 2x slowdown" on the cylinders of 196, 1,996 and
    19,996 long skinny triangles: time at the points law's O(N) cells over time at the
    lines law's O(N^1.5) cells.
``two-level``
    2-level against 1-level speed-up: "about a 2x speedup" on scanned models (the
    bumpy sphere here), "1.4x faster than 1-level for 1996 tri cylinder", "just 1.04x
    faster ... for 196 tri cylinder".  The 2-level grid is the talk's closed form
    (``m1^3 = (2 k^2 N r)^0.6`` with subgrids of ``2 r n`` cells for points;
    ``m1^3 = k N r`` with ``(r n)^1.5`` for lines) over a few top scales; the 1-level
    grid is the measured best of the 1-level sweep.  The 2-level grid ``calibrate predict``
    recommends (subgrids sized per cell by the general model) is measured beside them and
    the faster 2-level grid counts.
``empirical-exponent``
    "O(N^(7/9)) cells ... for compact triangles, O(N^(4/3)) cells for long skinny
    triangles": the exponent of a least-squares line through log(measured-best cells)
    against log N over a family of spheres and a family of cylinders.

Each judgment is a pure function of the measured numbers (:func:`judge`), so the
table can be checked on planted values; tolerances are named constants below.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from models.closed_forms import cells_to_resolution, lines_cells, points_cells, two_level_lines, two_level_points
from models.portable import paper_k

from ._grid import Scene

# --- the talk's claims ------------------------------------------------------------------


@dataclass(frozen=True)
class Claim:
    """One claim of the talk: what it says, the number(s) it gives and how a measurement is judged.

    kind : "at-most" (ours <= value), "range" (lo <= ours <= hi, widened by ``tol``
    relative), "about" (within ``tol`` relative of value) or "exponent" (within ``tol``
    absolute of value).  value : float, or (lo, hi) for "range".
    """

    key: str
    statement: str
    kind: str
    value: object
    tol: float = 0.0
    what: str = ""


#: A measured factor agrees with the talk's when within this fraction of it (or of its range's ends).
FACTOR_REL_TOL = 0.15
#: A measured exponent agrees with the talk's when within this much of it: half the gap between
#: the talk's empirical exponents and its theory's (7/9 against 1, 4/3 against 3/2).
EXPONENT_ABS_TOL = 0.09

CLAIMS = {
    "compact-5pct": Claim("compact-5pct", "points law M = 2Nr within 5% of optimal (compact scenes)", "at-most",
                          0.05, what="penalty of the points law's grid against the measured best"),
    "lines-3pct": Claim("lines-3pct", "lines law M = (Nr)^1.5 within 3% of optimal (cylinders)", "at-most", 0.03,
                        what="penalty of the lines law's grid against the measured best"),
    "lines-10pct-large": Claim("lines-10pct-large", "19,996-triangle cylinder within 10% of optimal", "at-most",
                               0.10, what="penalty of the lines law's grid against the measured best"),
    "linear-slowdown": Claim("linear-slowdown", "O(N) cells are 1.25x to 2x slower than O(N^1.5)", "range",
                             (1.25, 2.0), FACTOR_REL_TOL,
                             what="time at M = 2Nr over time at M = (Nr)^1.5"),
    "two-level-scan": Claim("two-level-scan", "2-level about 2x faster than 1-level (scanned models)", "about", 2.0,
                            FACTOR_REL_TOL, what="best 1-level time over best 2-level time"),
    "two-level-1996": Claim("two-level-1996", "2-level 1.4x faster than 1-level (1,996-triangle cylinder)", "about",
                            1.4, FACTOR_REL_TOL, what="best 1-level time over best 2-level time"),
    "two-level-196": Claim("two-level-196", "2-level just 1.04x faster than 1-level (196-triangle cylinder)", "about",
                           1.04, FACTOR_REL_TOL, what="best 1-level time over best 2-level time"),
    "exponent-compact": Claim("exponent-compact", "best cells grow as N^(7/9) (compact)", "exponent", 7.0 / 9.0,
                              EXPONENT_ABS_TOL, what="fitted exponent of measured-best cells against N"),
    "exponent-skinny": Claim("exponent-skinny", "best cells grow as N^(4/3) (long skinny)", "exponent", 4.0 / 3.0,
                             EXPONENT_ABS_TOL, what="fitted exponent of measured-best cells against N"),
}


def judge(claim: Claim, ours: float) -> bool:
    """Whether a measured value agrees with a claim (see :class:`Claim` for the kinds)."""
    x = float(ours)
    if not math.isfinite(x):
        return False
    if claim.kind == "at-most":
        return x <= float(claim.value)
    if claim.kind == "range":
        lo, hi = claim.value
        return lo / (1.0 + claim.tol) <= x <= hi * (1.0 + claim.tol)
    if claim.kind == "about":
        v = float(claim.value)
        return v / (1.0 + claim.tol) <= x <= v * (1.0 + claim.tol)
    if claim.kind == "exponent":
        return abs(x - float(claim.value)) <= claim.tol
    raise ValueError(f"unknown claim kind {claim.kind!r}")


def talk_text(claim: Claim) -> str:
    """The talk's number as the table shows it."""
    if claim.kind == "at-most":
        return f"<= {100 * float(claim.value):.0f}%"
    if claim.kind == "range":
        lo, hi = claim.value
        return f"{lo:g}x - {hi:g}x"
    if claim.kind == "about":
        return f"{float(claim.value):g}x"
    return {7.0 / 9.0: "7/9 = 0.778", 4.0 / 3.0: "4/3 = 1.333"}.get(float(claim.value), f"{float(claim.value):.3f}")


def ours_text(claim: Claim, ours: float) -> str:
    """Our measured value as the table shows it."""
    if not math.isfinite(ours):
        return "-"
    if claim.kind == "at-most":
        return f"{100 * ours:+.1f}%"
    if claim.kind in ("range", "about"):
        return f"{ours:.2f}x"
    return f"{ours:.3f}"


def disagreement(claim: Claim, ours: float, scene: str) -> str:
    """The sentence the table prints where we disagree ("" where we agree)."""
    if judge(claim, ours):
        return ""
    if not math.isfinite(ours):
        return f"{scene}: not measured."
    if claim.kind == "at-most":
        return (f"{scene}: the law's grid is {100 * ours:.1f}% slower than the measured best here, more than the "
                f"talk's {100 * float(claim.value):.0f}%.")
    if claim.kind == "range":
        lo, hi = claim.value
        side = f"only {ours:.2f}x" if ours < lo else f"{ours:.2f}x"
        bound = f"below the talk's {lo:g}x" if ours < lo else f"above the talk's {hi:g}x"
        return f"{scene}: O(N) cells are {side} as slow as O(N^1.5) here, {bound}."
    if claim.kind == "about":
        how = "as fast as" if ours >= 1.0 else "the speed of"
        return (f"{scene}: the 2-level grid is {ours:.2f}x {how} the best 1-level grid here, not about "
                f"{float(claim.value):g}x.")
    theory = {"exponent-compact": "1 (the points law)", "exponent-skinny": "1.5 (the lines law)"}.get(claim.key, "")
    return (f"{scene}: the measured-best cells grow as N^{ours:.2f} here, not N^{float(claim.value):.2f}"
            + (f"; the talk's theory gives {theory}." if theory else "."))


def claim_row(key: str, scene: str, ours: float, **detail) -> dict:
    """One row of the table: the claim, the talk's number, ours, agree, and the sentence where we disagree."""
    claim = CLAIMS[key]
    ours = float(ours) if ours is not None else math.nan
    agree = judge(claim, ours) if math.isfinite(ours) else None
    return dict(claim=key, statement=claim.statement, measured=claim.what, scene=scene, talk=talk_text(claim),
                talk_value=list(claim.value) if isinstance(claim.value, tuple) else float(claim.value),
                ours=ours if math.isfinite(ours) else None, ours_text=ours_text(claim, ours), agree=agree,
                note=disagreement(claim, ours, scene) if agree is False else "", **detail)


def fit_exponent(n, cells) -> dict:
    """Least-squares line through (log N, log cells): ``cells = c N^b``.

    n, cells : (J,) positive.  Returns dict ``exponent`` (b), ``constant`` (c),
    ``stderr`` (standard error of b; None with fewer than 3 points), ``points`` (J).
    """
    n = np.asarray(n, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.float64)
    if n.shape != cells.shape or n.ndim != 1 or n.size < 2:
        raise ValueError("fit_exponent needs at least two (N, cells) points of equal length")
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(cells)) and np.all(n > 0) and np.all(cells > 0)):
        raise ValueError("fit_exponent needs finite positive N and cells")
    x, y = np.log(n), np.log(cells)
    if np.ptp(x) == 0:
        raise ValueError("fit_exponent needs at least two different N")
    b, a = np.polyfit(x, y, 1)
    stderr = None
    if x.size >= 3:
        resid = y - (a + b * x)
        stderr = float(math.sqrt(float(resid @ resid) / (x.size - 2) / float(((x - x.mean()) ** 2).sum())))
    return dict(exponent=float(b), constant=float(math.exp(a)), stderr=stderr, points=int(x.size))


# --- what is measured ---------------------------------------------------------------------

#: Per-axis scales of the class law's resolution in a 1-level sweep: 2^(j/2), j = -3..3
#: (cells from 1/23 to 23 times the law's).
SWEEP_AXIS_SCALES = tuple(2.0 ** (j / 2.0) for j in range(-3, 4))
#: Per-axis scales of the talk's 2-level top resolution.
TWO_LEVEL_TOP_SCALES = tuple(2.0 ** (j / 2.0) for j in (-1, 0, 1))
TWO_LEVEL_TOP_SCALES_QUICK = (2.0 ** -0.5, 1.0)
#: Rays per scene (isotropic, seeded), timing rounds per grid and the shortest value (s).
RAYS = 16384
RAYS_QUICK = 4096
ROUNDS = 9
ROUNDS_QUICK = 7
MIN_TIME_S = 0.020
MIN_TIME_S_QUICK = 0.010
SEED = 0
#: Segments of the cylinders (4 s - 4 triangles) and sphere sizes (target triangles) per family.
CYLINDER_SEGMENTS = (50, 125, 250, 500, 1250, 5000)
CYLINDER_SEGMENTS_QUICK = (50, 125, 500)
SPHERE_TRIANGLES = (1280, 2880, 5120, 11520, 20480, 40500)
SPHERE_TRIANGLES_QUICK = (1280, 5120, 20480)


def family_scenes(quick: bool) -> dict:
    """The compact (bumpy spheres) and long-skinny (cylinders) families: name -> list of Scenes."""
    from .scenes import CYLINDER_SEGMENTS as BUILTIN_CYL
    from .scenes import cylinder_mesh, sphere_mesh

    builtin_by_segments = {s: name for name, s in BUILTIN_CYL.items()}
    spheres = []
    for n in (SPHERE_TRIANGLES_QUICK if quick else SPHERE_TRIANGLES):
        v, f = sphere_mesh(n)
        spheres.append(Scene(v, f, name="sphere" if f.shape[0] == 40_500 else f"sphere{f.shape[0]}"))
    cylinders = []
    for s in (CYLINDER_SEGMENTS_QUICK if quick else CYLINDER_SEGMENTS):
        v, f = cylinder_mesh(s)
        cylinders.append(Scene(v, f, name=builtin_by_segments.get(s, f"cylinder{f.shape[0]}")))
    return dict(compact=spheres, skinny=cylinders)


def _two_level_spec(scene: Scene, law: str, r: float, top_scale: float):
    from .sweep import GridSpec

    n = scene.n_triangles
    extent = scene.box_hi - scene.box_lo
    k = paper_k(scene.stats.k)
    if law == "points":
        top_cells = float(two_level_points(n, r, k)[0])
        leaf_scale, leaf_exponent = 2.0 * r, 1.0  # subgrid of n points: 2 r n cells (the talk's m2^3 = 2 N2 r)
    else:
        top_cells = float(two_level_lines(n, r, k)[0])
        leaf_scale, leaf_exponent = r, 1.5  # subgrid of n lines: (r n)^1.5 cells
    res = cells_to_resolution(top_cells * top_scale ** 3, extent)
    return GridSpec("nested", (res,), depth=2, subgrids="rule", scale=leaf_scale,
                    exponents=(1.0, leaf_exponent), label=f"2-level top x{top_scale:.3g}")


def _predicted_two_level_spec(scene: Scene, r: float):
    """The 2-level grid ``calibrate predict --levels 2 --ratio r`` recommends (model-sized subgrids)."""
    from .predict import predict
    from .sweep import GridSpec

    top = tuple(predict(scene, ratio=r, levels="2")["levels"][0]["resolution"])
    return GridSpec("nested", (top,), depth=2, subgrids="model", ratio=r, label="2-level as predicted")


def measure_scene(scene: Scene, law: str, r: float, *, quick: bool, two_level: bool = False,
                  linear: bool = False, progress=None, status=None) -> dict:
    """Sweep one scene: 1-level grids around its class law (and O(N) for ``linear``), the talk's
    2-level grid for ``two_level``; times from :func:`calibrate.sweep.sweep`.

    Returns dict ``scene``, ``triangles``, ``law``, ``law_cells``, ``uniform`` (sweep
    points sorted by cells, each with ``labels``, ``cells``, ``median_ns``...), ``fit``
    (:func:`calibrate.sweep.fit_minimum` over cells^(1/3)), ``best_cells``, ``best_ns``,
    ``law_ns``, ``linear_ns``, ``two_level`` (points) and ``two_level_best_ns``.
    """
    from .rays import isotropic
    from .sweep import GridSpec, fit_minimum, sweep

    n = scene.n_triangles
    extent = scene.box_hi - scene.box_lo
    law_cells = float(points_cells(n, r) if law == "points" else lines_cells(n, r))
    by_res: dict = {}
    for s in SWEEP_AXIS_SCALES:
        res = cells_to_resolution(law_cells * s ** 3, extent)
        by_res.setdefault(res, []).append("law" if s == 1.0 else f"law x{s:.3g}/axis")
    if linear:
        by_res.setdefault(cells_to_resolution(points_cells(n, r), extent), []).append("O(N)")
    # one point per distinct cell count, so the curve over cells is a function
    by_cells: dict = {}
    for res, labels in by_res.items():
        by_cells.setdefault(res[0] * res[1] * res[2], (res, []))[1].extend(labels)
    uniform = [GridSpec("uniform", (res,), label=", ".join(labels)) for _, (res, labels) in sorted(by_cells.items())]
    nested = []
    if two_level:
        nested = [_two_level_spec(scene, law, r, t) for t in (TWO_LEVEL_TOP_SCALES_QUICK if quick
                                                                else TWO_LEVEL_TOP_SCALES)]
        nested.append(_predicted_two_level_spec(scene, r))
    o, d = isotropic(scene.box_lo, scene.box_hi, RAYS_QUICK if quick else RAYS, SEED)
    if status is not None:
        status(f"{scene.name}: {len(uniform) + len(nested)} grids")
    points = sweep(scene, uniform + nested, (o, d), rounds=ROUNDS_QUICK if quick else ROUNDS,
                   min_time=MIN_TIME_S_QUICK if quick else MIN_TIME_S, seed=SEED, progress=progress)
    for p in points:
        p.pop("values_ns", None)
    upts = [p for p in points[:len(uniform)] if p.get("median_ns") is not None]
    if not upts:
        raise RuntimeError(f"{scene.name}: no 1-level grid could be measured")
    for p in upts:
        p["labels"] = p["spec"]["label"].split(", ")
    cube_root = np.array([float(np.prod(p["resolution"])) ** (1.0 / 3.0) for p in upts])
    fit = fit_minimum(cube_root, [p["median_ns"] for p in upts])

    def labelled(label):
        hits = [p["median_ns"] for p in upts if label in p["labels"]]
        return hits[0] if hits else None

    two = [p for p in points[len(uniform):]]
    two_ns = [p["median_ns"] for p in two if p.get("median_ns") is not None]
    return dict(scene=scene.name, triangles=n, law=law, ratio=r, law_cells=law_cells, rays=int(o.shape[0]),
                uniform=upts, fit=fit, best_cells=fit["scale"] ** 3, best_ns=fit["time"],
                best_measured_ns=min(p["median_ns"] for p in upts), law_ns=labelled("law"),
                linear_ns=labelled("O(N)") if linear else None, two_level=two,
                two_level_best_ns=min(two_ns) if two_ns else None)


def _penalty(m: dict) -> float | None:
    """The law's time over the measured best: the lower of the fitted curve's vertex and the lowest point."""
    from .sweep import penalty

    return None if m["law_ns"] is None else penalty(m["law_ns"], min(m["best_ns"], m["best_measured_ns"]))


def build_rows(measured: dict, exponents: dict) -> list[dict]:
    """The table's rows from the per-scene measurements and the exponent fits."""
    rows = []
    for m in measured.values():
        if m["law"] == "points":
            rows.append(claim_row("compact-5pct", m["scene"], _penalty(m), law_ns=m["law_ns"],
                                  best_ns=min(m["best_ns"], m["best_measured_ns"]),
                                  best_cells=m["best_cells"], law_cells=m["law_cells"],
                                  best_at_edge=m["fit"]["at_edge"]))
    for m in measured.values():
        if m["law"] == "lines" and m["linear_ns"] is not None:
            key = "lines-10pct-large" if m["triangles"] > 10_000 else "lines-3pct"
            rows.append(claim_row(key, m["scene"], _penalty(m), law_ns=m["law_ns"],
                                  best_ns=min(m["best_ns"], m["best_measured_ns"]),
                                  best_cells=m["best_cells"], law_cells=m["law_cells"],
                                  best_at_edge=m["fit"]["at_edge"]))
    for m in measured.values():
        if m["law"] == "lines" and m["linear_ns"] is not None and m["law_ns"]:
            rows.append(claim_row("linear-slowdown", m["scene"], m["linear_ns"] / m["law_ns"],
                                  linear_ns=m["linear_ns"], law_ns=m["law_ns"]))
    # the talk's scan claim on the largest compact scene measured with a 2-level grid
    scans = [m for m in measured.values() if m["law"] == "points" and m["two_level_best_ns"]]
    two = [(max(scans, key=lambda m: m["triangles"]), "two-level-scan")] if scans else []
    two += [(measured[name], key) for name, key in (("cylinder1996", "two-level-1996"), ("cylinder196", "two-level-196"))
            if name in measured and measured[name]["two_level_best_ns"]]
    for m, key in two:
        one = min(m["best_ns"], m["best_measured_ns"])
        rows.append(claim_row(key, m["scene"], one / m["two_level_best_ns"], one_level_best_ns=one,
                              two_level_best_ns=m["two_level_best_ns"]))
    for family, key in (("compact", "exponent-compact"), ("skinny", "exponent-skinny")):
        e = exponents.get(family)
        if e is not None:
            rows.append(claim_row(key, e["label"], e["exponent"], stderr=e["stderr"], n=e["n"], cells=e["cells"]))
    return rows


def run_paper(*, ratio: float, quick: bool = False, progress=None, status=None) -> dict:
    """Measure every claim; returns the JSON-ready report (``rows``, ``scenes``, ``exponents``, conditions)."""
    t0 = time.monotonic()
    load0 = _loadavg()
    r = float(ratio)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"ratio must be a finite number > 0, got {ratio!r}")
    families = family_scenes(quick)
    measured = {}
    largest = max(families["compact"], key=lambda s: s.n_triangles)
    talk_cylinders = ("cylinder196", "cylinder1996", "cylinder19996")
    jobs = [(s, "points", dict(two_level=s is largest)) for s in families["compact"]]
    jobs += [(s, "lines", dict(linear=s.name in talk_cylinders, two_level=s.name in talk_cylinders[:2]))
             for s in families["skinny"]]
    for i, (scene, law, opts) in enumerate(jobs):
        if status is not None:
            status(f"{i + 1}/{len(jobs)} {scene.name}")
        measured[scene.name] = measure_scene(scene, law, r, quick=quick, progress=progress, status=status, **opts)
    compact = [measured[s.name] for s in families["compact"]]
    exponents = {}
    for family, members in (("compact", compact), ("skinny", [measured[s.name] for s in families["skinny"]])):
        fit = fit_exponent([m["triangles"] for m in members], [m["best_cells"] for m in members])
        ns = [m["triangles"] for m in members]
        label = "spheres" if family == "compact" else "cylinders"
        exponents[family] = dict(fit, label=f"{label} N={min(ns):,}..{max(ns):,}", n=ns,
                                 cells=[m["best_cells"] for m in members],
                                 at_edge=[bool(m["fit"]["at_edge"]) for m in members])
    rows = build_rows(measured, exponents)
    return _plain(dict(rows=rows, ratio=r, quick=bool(quick), rays="isotropic", seed=SEED,
                       scenes=list(measured.values()), exponents=exponents, load_average=[load0, _loadavg()],
                       wall_s=time.monotonic() - t0,
                       agree=sum(1 for x in rows if x["agree"]), disagree=sum(1 for x in rows if x["agree"] is False)))


def _loadavg():
    try:
        return float(os.getloadavg()[0])
    except (OSError, AttributeError):
        return None


def _plain(x):
    from .predict import json_ready  # imported late: predict is heavy to import

    return json_ready(x)


# --- command line ---------------------------------------------------------------------------

def add_parser(sub):
    """Register the ``paper`` verb on an argparse subparsers object; returns its parser."""
    from .predict import add_constants_options

    help_text = "measure the talk's claims on its own scene classes and print the talk and this host side by side"
    sp = sub.add_parser("paper", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")
    sp.add_argument("--quick", action="store_true",
                    help="fewer scenes (no 19,996-triangle cylinder), rays and repeats: about half a minute")
    add_constants_options(sp, "use your own T_int/T_step for the laws",
                          "calibration file (default ./calibration.json)")
    sp.set_defaults(func=cmd_paper)
    return sp


def cmd_paper(args) -> int:
    """Run the ``paper`` verb."""
    import json

    from .cli import _Progress
    from .predict import constants_from_args, resolve_constants

    src = constants_from_args(args, rays="isotropic")  # the claims are about isotropic lines, which it traces
    r = resolve_constants(**src).ratio
    with _Progress(not args.quiet, "measuring") as bar:
        report = run_paper(ratio=r, quick=args.quick, progress=bar, status=bar.status)
    if args.json:
        sys.stdout.write(json.dumps(report, indent=2, allow_nan=False) + "\n")
        return 0
    print_report(report)
    return 0


def print_report(report: dict) -> None:
    """The side-by-side table, the sentences where we disagree, and the conditions."""
    from rich.table import Table

    from .cli import _console

    console = _console()
    table = Table(title=f"the talk's claims and this host (r = T_int/T_step = {report['ratio']:.3g})")
    for col, just in (("claim (the talk)", "left"), ("scene", "left"), ("talk", "right"), ("here", "right"),
                      ("agree", "center")):
        table.add_column(col, justify=just)
    for row in report["rows"]:
        mark = {True: "yes", False: "[bold]no[/bold]", None: "-"}[row["agree"]]
        here = row["ours_text"] + (f" ± {row['stderr']:.3f}" if row.get("stderr") is not None else "")
        table.add_row(row["statement"], row["scene"], row["talk"], here, mark)
    console.print(table)
    for row in report["rows"]:
        if row["note"]:
            console.print(f"disagree: {row['note']}")
    edges = [s["scene"] for s in report["scenes"] if s["fit"]["at_edge"]]
    if edges:
        console.print(f"note: the measured best lies at the end of the sweep for {', '.join(edges)}; "
                      "the true optimum may lie beyond it")
    load = report["load_average"]
    load_text = "" if None in load else f", load average {load[0]:.2f} at the start and {load[1]:.2f} at the end"
    console.print(f"{report['agree']} agree, {report['disagree']} disagree; {report['rays']} rays, "
                  f"{'quick' if report['quick'] else 'full'} run, wall time {report['wall_s']:.1f} s{load_text}")

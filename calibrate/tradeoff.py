"""`calibrate tradeoff`: what accuracy costs in time, measured in one run.

Three tradeoffs (DESIGN §3.3 and §4), each a table and a panel of one figure:

budget
    One calibration run (:func:`calibrate.run.run_calibration`) measures to the
    largest budget; after each of its stages (``on_stage``) the posterior that a
    run stopping there would have is kept, so one run gives the curve of every
    shorter budget.  Per stage: the wall time spent (the budget that buys it), the
    full width of r's 95% interval over its median, and per scene the *expected
    penalty* of the prediction made from that posterior: the expected relative time
    lost, under the posterior median's cost curve, by using the resolution of a
    posterior sample instead of the median's optimum
    (:func:`models.uncertainty.posterior_optimum`'s ``penalty``; 0 for a point
    mass).  Beside it, the penalty of the stage's median choice on the *last*
    stage's cost curve: what stopping early cost, as far as the longest run knows.
fidelity
    Per scene, the time of each fidelity of :func:`calibrate.predict.predict`
    (paper, analytic, simulated) and of the measured sweep, and the penalty of each
    one's resolution against the measured optimum.
intersector
    T_int of each intersector from the isolating one-cell suite (both measured in
    the same interleaved rounds, fitted like ``calibrate run``'s isolated
    estimates), and leaks per million rays aimed exactly at the vertices and edges
    of closed jittered meshes (:func:`calibrate.rays.aimed_at_edges`).  The kernels
    offer double precision only, so there is no single-precision column.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.effects import select_effects
from models.general import Terms, cost_cubic, optimal_cell_size
from models.uncertainty import posterior_optimum, summarise

from . import calfile, suites
from . import run as _run
from ._grid import Grid, Scene
from ._io import UserError
from .protocol import measure, pin_to_one_core
from .rays import aimed_at_edges
from .scenes import jittered_closed_mesh

#: Scenes of the budget and fidelity tradeoffs when none are named: compact and long skinny.
DEFAULT_SCENES = ("sphere", "cylinder1996")
#: Budget of the one calibration run whose stages give the budget curve, seconds.
DEFAULT_BUDGET_S = 120.0
#: The run measures to its budget: a target width no run reaches.
NEVER_REACHED_REL_WIDTH = 1e-9
INTERSECTORS = ("moller-trumbore", "watertight")
#: Values per configuration of the one-cell suite that measures T_int per intersector.
T_INT_ROUNDS = 7
#: Closed jittered meshes (seeds 0..n-1 of jittered_closed_mesh) the leak count aims at ...
LEAK_MESHES = 20
#: ... and rays per mesh aimed at random edge points (besides every vertex and edge midpoint once).
LEAK_EDGE_POINTS_PER_MESH = 7438
#: Ray origins: uniform in a ball of this radius about the centre of the radius-1 mesh.
LEAK_ORIGIN_RADIUS = 0.1
#: The grid the aimed rays are traced through (grids and brute force agree: tests/test_watertight.py).
LEAK_GRID_RESOLUTION = (16, 16, 16)
#: Central mass of the reported leak-rate interval (Wilson score interval).
LEAK_CI_Z = 1.959963984540054
#: What the kernels offer (kernels/gridcal.h: geometry is double precision throughout).
PRECISION_NOTE = ("the kernels are double precision only (kernels/gridcal.h): scenes scaled by 1e-20 or 1e20 "
                  "must work, and products of two coordinates (1e40) do not fit single precision, so there is "
                  "no single-precision variant to compare")

# --quick: three small scenes in the in-context suite at the coarse resolutions
# (suites.COARSE_CONTEXT_*), the isolating suites' steady state with a
# short walk and list each (29 configurations, not 42), short values, a tiny budget, one small
# scene, few rays.
QUICK_SCENES = ("cylinder196",)
QUICK_BUDGET_S = 20.0
QUICK_SUITES = dict(CONTEXT_SCENES=("cylinder196", "scattered-skinny", "scattered-compact"),
                    CONTEXT_CELLS_PER_TRIANGLE=suites.COARSE_CONTEXT_CELLS_PER_TRIANGLE,
                    CONTEXT_SKINNY_EXTRA=suites.COARSE_CONTEXT_SKINNY_EXTRA,
                    EMPTY_GRID_SIDES=(1, 12, 16, 20, 24, 28, 32),
                    CELL_TRIANGLE_COUNTS=(1, 32, 64, 96, 128, 192, 256))
QUICK_RUN = dict(FIRST_ROUNDS=5, STAGE_ROUNDS=3, FIT_RESERVE_S=1.0, FIT_RESERVE_MARGIN=0.0, POST_FIT_MIN_S=0.0,
                 POST_FIT_PER_POOLED=0.0)
QUICK_LEAK_MESHES = 2
QUICK_LEAK_EDGE_POINTS = 1000
QUICK_T_INT_ROUNDS = 4


# ---------------------------------------------------------------------------------------
# budget -> width of r's interval -> expected penalty
# ---------------------------------------------------------------------------------------

@dataclass
class StagePosterior:
    """One stage of a run: the wall time it took to get there and its posterior samples.

    stage : 1-based; elapsed_s : seconds since the run started; values : timed values so far;
    samples : dict ``t_setup_ns, t_step_ns, t_int_ns`` -> (S,) posterior samples (ns).
    """

    stage: int
    elapsed_s: float
    values: int
    samples: dict


def expected_penalty(stats, t_setup, t_step, t_int, terms: Terms | None = None) -> float:
    """Expected relative time lost by predicting with a posterior sample instead of the median.

    ``E_s[T_med(h_s)] / T_med(h_med) - 1`` over the (S,) samples (ns): the resolution
    chosen from each sample's r is costed on the median constants' curve
    (:func:`models.uncertainty.posterior_optimum`).  0 for a point mass; for a narrow
    posterior it grows as the square of the width (the cost curve is flat at its optimum).
    """
    return float(posterior_optimum(stats, t_setup, t_step, t_int, terms=terms, overlap="exact",
                                   use_jax=False).penalty)


def _optimal_h(stats, terms: Terms, t_step, t_int) -> float:
    return float(optimal_cell_size(stats, t_step, t_int, mailbox=terms.mailbox, overlap="exact", edge=terms.edge,
                                   area=terms.area, traversed_fraction=terms.traversed_fraction))


def penalty_against(stats, terms: Terms, chosen: tuple, truth: tuple) -> float:
    """Relative time lost by the optimum of constants ``chosen`` on the cost curve of ``truth``.

    chosen, truth : (t_setup, t_step, t_int) ns.  0 when both give the same r.
    """
    h = _optimal_h(stats, terms, chosen[1], chosen[2])
    h_true = _optimal_h(stats, terms, truth[1], truth[2])
    return float(cost_cubic(stats, h, *truth, terms=terms) / cost_cubic(stats, h_true, *truth, terms=terms) - 1.0)


def _medians(samples: dict) -> tuple:
    return tuple(float(np.median(samples[k])) for k in ("t_setup_ns", "t_step_ns", "t_int_ns"))


def scene_terms(stats, constants: tuple) -> Terms:
    """The terms ``calibrate predict``'s analytic fidelity selects for a scene (uniform grid)."""
    return select_effects(stats, *constants, mailbox=False, termination=True, overlap="exact", levels=1).terms


def budget_curve(stages: list, scenes: dict) -> list:
    """Rows of the budget curve from a run's stages.

    stages : list of :class:`StagePosterior`, in order; scenes : dict name -> SceneStats.
    The effects (terms) of each scene are selected once with the last stage's medians.
    Returns one dict per stage: ``stage``, ``budget_s``, ``values``, ``ratio`` {median, ci95},
    ``ratio_rel_width``, ``penalty`` {scene: expected penalty}, ``penalty_vs_last`` {scene: ...}.
    """
    if not stages:
        raise ValueError("no stages: the run was not fitted even once")
    last = _medians(stages[-1].samples)
    terms = {name: scene_terms(st, last) for name, st in scenes.items()}
    rows = []
    for sp in stages:
        s = sp.samples
        r = summarise(s["t_int_ns"] / s["t_step_ns"])
        med = _medians(s)
        rows.append(dict(
            stage=sp.stage, budget_s=sp.elapsed_s, values=sp.values,
            ratio=dict(median=r.median, ci95=list(r.ci95)),
            ratio_rel_width=(r.ci95[1] - r.ci95[0]) / r.median,
            penalty={n: expected_penalty(st, s["t_setup_ns"], s["t_step_ns"], s["t_int_ns"], terms[n])
                     for n, st in scenes.items()},
            penalty_vs_last={n: penalty_against(st, terms[n], med, last) for n, st in scenes.items()}))
    return rows


def stage_posterior(stage: "_run.Stage") -> StagePosterior:
    """A run's :class:`calibrate.run.Stage` -> :class:`StagePosterior` (samples by name)."""
    res = stage.result
    samples = {k: np.asarray(res.samples[:, res.names.index(k)], dtype=np.float64).copy()
               for k in ("t_setup_ns", "t_step_ns", "t_int_ns")}
    return StagePosterior(stage=stage.stage, elapsed_s=stage.elapsed_s, values=stage.values, samples=samples)


@contextlib.contextmanager
def _patched(module, values: dict):
    old = {k: getattr(module, k) for k in values}
    try:
        for k, v in values.items():
            setattr(module, k, v)
        yield
    finally:
        for k, v in old.items():
            setattr(module, k, v)


def quick_suites():
    """Context in which ``calibrate run``'s suites are the small ones of ``--quick``."""
    stack = contextlib.ExitStack()
    stack.enter_context(_patched(suites, QUICK_SUITES))
    stack.enter_context(_patched(_run, QUICK_RUN))
    return stack


def measure_budget_curve(budget_s: float, *, seed: int = 0, progress=None, status=None, workdir=None):
    """Run one calibration to ``budget_s`` and keep every stage's posterior.

    Returns (list of :class:`StagePosterior`, :class:`calibrate.run.RunResult`).  The
    calibration file goes to ``workdir`` (a temporary directory when None).
    """
    stages: list = []

    def collect(stage) -> bool:
        # a stage the deadline ended before it timed anything new repeats its predecessor's fit
        if not stages or stage.values > stages[-1].values:
            stages.append(stage_posterior(stage))
        return False

    with contextlib.ExitStack() as stack:
        if workdir is None:
            workdir = stack.enter_context(tempfile.TemporaryDirectory(prefix="gridcal-tradeoff-"))
        result = _run.run_calibration(Path(workdir) / "calibration.json", budget_s=budget_s,
                                      target_rel_width=NEVER_REACHED_REL_WIDTH, seed=seed, progress=progress,
                                      status=status, on_stage=collect)
    return stages, result


# ---------------------------------------------------------------------------------------
# intersector: T_int and leaks
# ---------------------------------------------------------------------------------------

def wilson_interval(k: int, n: int, z: float = LEAK_CI_Z) -> tuple:
    """Wilson score interval of a binomial proportion k / n (both ends in [0, 1])."""
    if n <= 0:
        raise ValueError("no trials")
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (0.0 if k == 0 else max(0.0, centre - half)), (1.0 if k == n else min(1.0, centre + half))


def count_leaks(scene: Scene, origins, directions, kind, intersector: str) -> dict:
    """Misses of rays that must hit (aimed from inside a closed mesh), overall and by target kind."""
    _, prim = Grid.uniform(scene, LEAK_GRID_RESOLUTION, intersector).intersect(origins, directions)
    miss = prim < 0
    return dict(rays=int(miss.size), leaks=int(miss.sum()),
                by_kind={str(k): [int((miss & (kind == k)).sum()), int((kind == k).sum())] for k in np.unique(kind)})


def leak_table(n_meshes: int = LEAK_MESHES, edge_points: int = LEAK_EDGE_POINTS_PER_MESH, seed: int = 0) -> dict:
    """Leaks per million aimed rays per intersector, with a 95% interval, over ``n_meshes`` meshes."""
    totals = {ix: dict(rays=0, leaks=0, by_kind={}) for ix in INTERSECTORS}
    for i in range(n_meshes):
        v, f = jittered_closed_mesh(seed + i)
        scene = Scene(v, f, name=f"jittered{seed + i}")
        o, d, kind = aimed_at_edges(v, f, edge_points, seed + 5000 + i, origin_radius=LEAK_ORIGIN_RADIUS)
        for ix in INTERSECTORS:
            c = count_leaks(scene, o, d, kind, ix)
            t = totals[ix]
            t["rays"] += c["rays"]
            t["leaks"] += c["leaks"]
            for k, (m, n) in c["by_kind"].items():
                a = t["by_kind"].setdefault(k, [0, 0])
                a[0] += m
                a[1] += n
    out = {}
    for ix, t in totals.items():
        lo, hi = wilson_interval(t["leaks"], t["rays"])
        out[ix] = dict(rays=t["rays"], leaks=t["leaks"], per_million=1e6 * t["leaks"] / t["rays"],
                       per_million_ci95=[1e6 * lo, 1e6 * hi],
                       by_kind={k: dict(leaks=m, rays=n, per_million=1e6 * m / n)
                                for k, (m, n) in t["by_kind"].items()})
    return out


def intersector_costs(seed: int = 0, rounds: int = T_INT_ROUNDS, progress=None) -> dict:
    """T_int (ns per test) of each intersector from the one-cell suite, measured in the same rounds.

    Returns dict intersector -> {median, ci68, ci95} (ns), as ``calibrate run``'s isolated T_int,
    or {error: why} when that intersector's measurements cannot be fitted (a busy host).
    """
    from .fit import ConvergenceError

    configs = {ix: [c for c in suites.isolated_configs(ix, seed) if c.suite == "cell"] for ix in INTERSECTORS}
    runs = {f"{ix}: {c.name}": c.run for ix, cs in configs.items() for c in cs}
    with pin_to_one_core():
        timings = measure(runs, rng=np.random.default_rng(seed), rounds=rounds, warmups=_run.WARMUPS,
                          min_value_ns=_run.MIN_VALUE_NS, progress=progress)
    out = {}
    for ix, cs in configs.items():
        mine = {c.name: timings[f"{ix}: {c.name}"] for c in cs if f"{ix}: {c.name}" in timings}
        recs = _run.records(cs, mine, set())
        try:
            res = calfile.constants_json(_run.fit_cell_suite(recs, seed)[0])["t_int_ns"]
        except (ValueError, ConvergenceError) as exc:
            res = dict(error=f"T_int of the {ix} intersector could not be fitted: {exc}")
        out[ix] = res
    return out


# ---------------------------------------------------------------------------------------
# fidelity -> time to predict -> penalty against the measured optimum
# ---------------------------------------------------------------------------------------

#: Measured sweep per scene: uniform grids at the analytic resolution scaled per axis by
#: 2^(j/4), j = -FIDELITY_SWEEP_STEPS..FIDELITY_SWEEP_STEPS (a factor 8 in cells each way),
#: plus each fidelity's own resolution, timed interleaved (calibrate.sweep).
FIDELITY_SWEEP_STEPS = 4
FIDELITY_SWEEP_STEP = 2.0 ** 0.25
#: Isotropic rays per sweep batch (the ray distribution the paper and analytic models assume).
FIDELITY_RAYS = 4096
QUICK_FIDELITY_SWEEP_STEPS = 2
QUICK_FIDELITY_RAYS = 1024
QUICK_SWEEP_ROUNDS = 3


def fidelity_table(scene: Scene, constants: dict, samples: dict, *, steps: int = FIDELITY_SWEEP_STEPS,
                   n_rays: int = FIDELITY_RAYS, rounds: int | None = None, seed: int = 0, progress=None,
                   status=None) -> list:
    """Time to predict and penalty against the measured optimum, per fidelity, for one scene.

    constants, samples : a calibration's medians and posterior samples (``t_*_ns``), as
    :func:`calibrate.predict.predict` takes them.  Each fidelity predicts a uniform grid
    (``levels=1``); the measured sweep times uniform grids around the analytic resolution
    and every fidelity's resolution on the same isotropic rays, interleaved.  The measured
    optimum is the lower of the lowest timed grid and the curve's smooth minimum
    (:func:`calibrate.sweep.fit_minimum`), so no penalty is negative.

    Returns one dict per fidelity (paper, analytic, simulated, measured): ``scene``,
    ``fidelity``, ``time_s`` (to predict; for ``measured`` the sweep's build-and-time
    wall time), ``resolution``, ``ns_per_ray`` (measured at that resolution), ``penalty``.
    """
    from . import sweep as _sweep
    from .predict import FIDELITIES, predict
    from .rays import isotropic

    res, took = {}, {}
    for f in FIDELITIES:
        if status is not None:
            status(f"fidelity: {scene.name}, predicting ({f})")
        t0 = time.perf_counter()
        pred = predict(scene, constants=constants, samples=samples, fidelity=f, levels="1")
        took[f] = time.perf_counter() - t0
        res[f] = tuple(pred["levels"][0]["resolution"])
    factors = [FIDELITY_SWEEP_STEP ** j for j in range(-steps, steps + 1)]
    curve = list(dict.fromkeys(_sweep.scaled_resolutions(res["analytic"], factors)))
    specs = curve + [r for r in dict.fromkeys(res.values()) if r not in curve]
    o, d = isotropic(scene.box_lo, scene.box_hi, n_rays, seed)
    if status is not None:
        status(f"fidelity: {scene.name}, measured sweep of {len(specs)} grids")
    t0 = time.perf_counter()
    kw = {} if rounds is None else dict(rounds=rounds)
    points = _sweep.sweep(scene, [_sweep.GridSpec("uniform", [r]) for r in specs], (o, d), seed=seed,
                          progress=progress, **kw)
    took["measured"] = time.perf_counter() - t0
    ns = {r: p.get("median_ns") for r, p in zip(specs, points)}
    on_curve = [(i, r) for i, r in enumerate(curve) if ns.get(r) is not None]
    if not on_curve:
        raise UserError(f"{scene.name}: no grid of the sweep could be built and timed")
    # the lowest of every timed grid, the fidelities' own included
    lowest = min((r for r in specs if ns.get(r) is not None), key=lambda r: ns[r])
    cells = [float(np.prod(r)) for _, r in on_curve]
    best_t = ns[lowest]
    if len(on_curve) >= 3 and all(b > a for a, b in zip(cells, cells[1:])):
        fit = _sweep.fit_minimum(cells, [ns[r] for _, r in on_curve])
        best_t = min(best_t, float(fit["time"]))
    res["measured"] = lowest
    rows = []
    for f in (*FIDELITIES, "measured"):
        t = ns.get(res[f])
        rows.append(dict(scene=scene.name, fidelity=f, time_s=took[f], resolution=list(res[f]), ns_per_ray=t,
                         penalty=None if t is None else _sweep.penalty(t, best_t)))
    return rows


# ---------------------------------------------------------------------------------------
# the verb
# ---------------------------------------------------------------------------------------

def tradeoff(scenes=None, *, budget_s: float | None = None, quick: bool = False, seed: int = 0,
             progress=None, status=None) -> dict:
    """Measure all three tradeoffs; returns the JSON-ready report (see module docstring).

    scenes : names of built-in scenes or mesh paths (default DEFAULT_SCENES, or
    QUICK_SCENES with ``quick``); budget_s : the calibration run's budget.
    """
    t0 = time.monotonic()
    status = status or (lambda text: None)
    if budget_s is None:
        budget_s = QUICK_BUDGET_S if quick else DEFAULT_BUDGET_S
    if not (isinstance(budget_s, (int, float)) and math.isfinite(budget_s) and budget_s > 0):
        raise UserError(f"--budget must be a positive number of seconds, got {budget_s!r}")
    if budget_s < _run.MIN_BUDGET_S:  # the run would refuse it, but only after the intersector measurements
        raise UserError(f"--budget {budget_s:g} s is too short: a run needs at least {_run.MIN_BUDGET_S:g} s")
    names = list(scenes) if scenes else list(QUICK_SCENES if quick else DEFAULT_SCENES)
    loaded = [Scene.load(s) for s in names]
    if len({sc.name for sc in loaded}) < len(loaded):
        raise UserError(f"scenes must have different names, got {', '.join(sc.name for sc in loaded)}")
    stats = {sc.name: sc.stats for sc in loaded}
    report = dict(quick=bool(quick), seed=seed, scenes=[dict(name=sc.name, triangles=sc.n_triangles) for sc in loaded])

    status("intersectors: leaks of rays aimed at vertices and edges")
    leaks = leak_table(QUICK_LEAK_MESHES if quick else LEAK_MESHES,
                       QUICK_LEAK_EDGE_POINTS if quick else LEAK_EDGE_POINTS_PER_MESH, seed)
    status("intersectors: T_int from the one-cell suite")
    t_int = intersector_costs(seed, QUICK_T_INT_ROUNDS if quick else T_INT_ROUNDS, progress)
    with (quick_suites() if quick else contextlib.nullcontext()):
        status(f"budget: one calibration run of {budget_s:g} s")
        stages, run_result = measure_budget_curve(budget_s, seed=seed, progress=progress, status=status)
    report["intersector"] = dict(
        rows=[dict(intersector=ix, t_int_ns=None if "error" in t_int[ix] else t_int[ix],
                   t_int_error=t_int[ix].get("error"), leaks_per_million=leaks[ix]["per_million"],
                   leaks_per_million_ci95=leaks[ix]["per_million_ci95"], leaks=leaks[ix]["leaks"],
                   rays=leaks[ix]["rays"], by_kind=leaks[ix]["by_kind"]) for ix in INTERSECTORS],
        precision=dict(offered=["double"], note=PRECISION_NOTE))
    report["budget"] = dict(run_budget_s=budget_s, rows=budget_curve(stages, stats))
    cal = run_result.calibration
    samples = {k: v for k, v in calfile.samples_by_name(cal).items() if k.endswith("_ns")}
    medians = {k: v["median"] for k, v in cal["constants"].items() if k.endswith("_ns") and v}
    fid = []
    for sc in loaded:
        with pin_to_one_core():
            fid += fidelity_table(sc, medians, samples, seed=seed, progress=progress, status=status,
                                  steps=QUICK_FIDELITY_SWEEP_STEPS if quick else FIDELITY_SWEEP_STEPS,
                                  n_rays=QUICK_FIDELITY_RAYS if quick else FIDELITY_RAYS,
                                  rounds=QUICK_SWEEP_ROUNDS if quick else None)
    report["fidelity"] = dict(rows=fid, constants="the budget run's last stage (its calibration)")
    report["calibration"] = dict(constants=run_result.calibration["constants"], holdout_mare=run_result.holdout_mare,
                                 warnings=[w for w in run_result.warnings if not w.startswith("budget spent")])
    report["wall_s"] = time.monotonic() - t0
    return _plain(report)


def _plain(x):
    from .predict import json_ready  # imported late: predict is heavy to import

    return json_ready(x)


# ---------------------------------------------------------------------------------------
# figure
# ---------------------------------------------------------------------------------------

#: Figure resolution, dots per inch.
DPI = 90
#: Penalty axes are logarithmic above this many per cent and linear below (0 stays on the axis).
PENALTY_LINEAR_BELOW_PCT = 0.1
INTERSECTOR_COLOURS = {"moller-trumbore": "C3", "watertight": "C2"}


def plot(report: dict, path) -> Path:
    """Write the tradeoff figure (PNG, atomically): budget, fidelity and intersector panels."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ._io import atomic_write_bytes

    path = Path(path)
    has_fid = bool(report.get("fidelity", {}).get("rows"))
    fig, grid = plt.subplots(2, 2, figsize=(9.6, 7.2))
    axes = grid.ravel()
    if not has_fid:
        axes[2].axis("off")
        axes = [axes[0], axes[1], axes[3]]
    rows = report["budget"]["rows"]
    b = [r["budget_s"] for r in rows]
    ax = axes[0]
    ax.plot(b, [100 * r["ratio_rel_width"] for r in rows], "o-", color="k")
    ax.set_xlabel("calibration budget (s)")
    ax.set_ylabel("r: 95% interval width / median (%)")
    ax.set_ylim(bottom=0)
    ax.set_title("budget -> width of r's interval")
    ax = axes[1]
    for i, name in enumerate(rows[0]["penalty"]):
        color = f"C{i}"
        ax.plot(b, [100 * r["penalty"][name] for r in rows], "o-", color=color, label=f"{name}: expected")
        ax.plot(b, [100 * r["penalty_vs_last"][name] for r in rows], "x--", color=color,
                label=f"{name}: vs last stage")
    ax.set_xlabel("calibration budget (s)")
    ax.set_ylabel("time penalty of the prediction (%)")
    ax.set_yscale("symlog", linthresh=PENALTY_LINEAR_BELOW_PCT)
    ax.set_ylim(bottom=0)
    ax.set_title("budget -> penalty")
    ax.legend(fontsize=7)
    if has_fid:
        ax = axes[2]
        fid = report["fidelity"]["rows"]
        for i, name in enumerate(dict.fromkeys(r["scene"] for r in fid)):
            mine = [r for r in fid if r["scene"] == name]
            mine = [r for r in mine if r["penalty"] is not None]
            ax.plot([r["time_s"] for r in mine], [100 * r["penalty"] for r in mine], "o-", color=f"C{i}", label=name)
            for r in mine if i == 0 else []:  # fidelities named once: every scene has them in the same order
                if r["penalty"] is not None:
                    ax.annotate(r["fidelity"], (r["time_s"], 100 * r["penalty"]), fontsize=7,
                                textcoords="offset points", xytext=(3, 3))
        ax.set_xscale("log")
        ax.set_yscale("symlog", linthresh=PENALTY_LINEAR_BELOW_PCT)
        ax.set_ylim(bottom=0)
        ax.set_xlabel("time to predict (s)")
        ax.set_ylabel("penalty vs measured optimum (%)")
        ax.set_title("fidelity -> time and penalty")
        ax.legend(fontsize=7)
    ax = axes[-1]
    ix = report["intersector"]["rows"]
    x = np.arange(len(ix))
    tallest = max([r["t_int_ns"]["ci95"][1] for r in ix if r["t_int_ns"] is not None] or [1.0])
    for xi, r in zip(x, ix):
        c = r["t_int_ns"]
        colour = INTERSECTOR_COLOURS.get(r["intersector"], "C0")
        if c is None:
            ax.annotate("T_int not fitted", (xi, 0.0), ha="center", va="bottom", fontsize=8)
            top = 0.0
        else:
            ax.bar([xi], [c["median"]], yerr=[[c["median"] - c["ci95"][0]], [c["ci95"][1] - c["median"]]],
                   color=colour, capsize=4)
            top = c["median"]
        inside = top > 0.25 * tallest  # a short bar gets its label above it
        ax.annotate(f"{r['leaks_per_million']:,.0f} leaks\nper million",
                    (xi, 0.5 * top if inside else (c["ci95"][1] + 0.03 * tallest if c is not None
                                                  else 0.12 * tallest)),
                    ha="center", va="center" if inside else "bottom", fontsize=8, color="w" if inside else "k")
    ax.set_xlim(-0.6, len(ix) - 0.4)  # room for a label where no bar was drawn
    ax.set_xticks(x, [r["intersector"] for r in ix])
    ax.set_ylabel("T_int (ns per test, 95% interval)")
    ax.set_title("intersector -> T_int and leaks")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def add_parser(sub):
    """Register the ``tradeoff`` verb on an argparse subparsers object; returns its parser."""
    from .cli import positive_number, seed_number

    help_text = ("what accuracy costs in time: calibration budget vs r's interval vs penalty, prediction "
                 "fidelity vs time vs penalty, intersector vs T_int vs leaks")
    sp = sub.add_parser("tradeoff", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")
    sp.add_argument("scenes", nargs="*", metavar="MESH|SCENE",
                    help=f"mesh files or built-in scenes (default {' '.join(DEFAULT_SCENES)})")
    sp.add_argument("--budget", type=positive_number("the budget in seconds"), metavar="SECONDS",
                    help=f"budget of the calibration run whose stages give the curve (default {DEFAULT_BUDGET_S:g}; "
                         f"{QUICK_BUDGET_S:g} with --quick)")
    sp.add_argument("--plot", metavar="FILE", help="write the figure (PNG) here")
    sp.add_argument("--quick", action="store_true",
                    help="small suites, a tiny budget, one small scene, few rays (seconds; for tests and CI)")
    sp.add_argument("--seed", type=seed_number, default=0)
    sp.set_defaults(func=cmd_tradeoff)
    return sp


def cmd_tradeoff(args) -> int:
    """Run the ``tradeoff`` verb: JSON on stdout with ``--json``, else tables."""
    import json
    import sys

    from .cli import _Progress

    if args.plot:
        _check_plot_path(Path(args.plot))
    with _Progress(not args.quiet, "tradeoff") as bar:
        report = tradeoff(args.scenes, budget_s=args.budget, quick=args.quick, seed=args.seed, progress=bar,
                          status=bar.status)
    if args.plot:
        report["plot"] = str(plot(report, Path(args.plot)))
    if args.json:
        sys.stdout.write(json.dumps(report, indent=2, allow_nan=False) + "\n")
        return 0
    print_report(report)
    return 0


def _check_plot_path(path: Path) -> None:
    """Refuse a plot path that cannot be written before spending minutes measuring."""
    from ._io import check_writable

    if not path.is_dir() and path.suffix.lower() != ".png":
        raise UserError(f"{path}: the plot is a PNG; give a file name ending in .png")
    check_writable(path)  # a directory, a missing or read-only directory, a write-protected file


def print_report(report: dict) -> None:
    """The report as tables on stdout."""
    from rich.table import Table

    from .cli import _console

    console = _console()
    rows = report["budget"]["rows"]
    scenes = list(rows[0]["penalty"])
    t = Table(title=f"budget: the stages of one {report['budget']['run_budget_s']:g} s calibration run")
    for col in ("budget (s)", "values", "r median", "r 95% interval", "width / median"):
        t.add_column(col, justify="right")
    for n in scenes:
        t.add_column(f"penalty {n}: expected / vs last", justify="right")
    for r in rows:
        t.add_row(f"{r['budget_s']:.1f}", f"{r['values']:,}", f"{r['ratio']['median']:.3f}",
                  f"[{r['ratio']['ci95'][0]:.3f}, {r['ratio']['ci95'][1]:.3f}]", f"{100 * r['ratio_rel_width']:.1f}%",
                  *[f"{100 * r['penalty'][n]:.3f}% / {100 * r['penalty_vs_last'][n]:.3f}%" for n in scenes])
    console.print(t)
    fid = report.get("fidelity", {}).get("rows")
    if fid:
        t = Table(title="fidelity: time to predict and penalty against the measured optimum")
        for col in ("scene", "fidelity", "time to predict", "resolution", "measured ns/ray", "penalty"):
            t.add_column(col, justify="right")
        for r in fid:
            t.add_row(r["scene"], r["fidelity"], _fmt_s(r["time_s"]), "x".join(str(x) for x in r["resolution"]),
                      f"{r['ns_per_ray']:.4g}", f"{100 * r['penalty']:.1f}%")
        console.print(t)
    t = Table(title="intersector: T_int (one-cell suite) and leaks of rays aimed at vertices and edges")
    for col in ("intersector", "T_int ns (95%)", "leaks per million (95%)", "leaks / rays",
                "vertex / midpoint / edge point per million"):
        t.add_column(col, justify="right")
    for r in report["intersector"]["rows"]:
        k, c = r["by_kind"], r["t_int_ns"]
        t.add_row(r["intersector"], "not fitted" if c is None else
                  f"{c['median']:.3g} [{c['ci95'][0]:.3g}, {c['ci95'][1]:.3g}]",
                  f"{r['leaks_per_million']:,.0f} [{r['leaks_per_million_ci95'][0]:,.0f}, "
                  f"{r['leaks_per_million_ci95'][1]:,.0f}]", f"{r['leaks']:,} / {r['rays']:,}",
                  " / ".join(f"{k[n]['per_million']:,.0f}" if n in k else "-"
                             for n in ("vertex", "midpoint", "edge point")))
    console.print(t)
    for r in report["intersector"]["rows"]:
        if r["t_int_error"]:
            console.print(f"note: {r['t_int_error']}")
    console.print(f"precision: {report['intersector']['precision']['note']}")
    console.print(f"wall time {report['wall_s']:.1f} s" + (f"; figure written to {report['plot']}"
                                                          if report.get("plot") else ""))


def _fmt_s(s: float) -> str:
    if s < 1e-3:
        return f"{1e6 * s:.0f} us"
    if s < 1:
        return f"{1e3 * s:.1f} ms"
    return f"{s:.1f} s"

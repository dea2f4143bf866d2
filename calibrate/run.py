"""`calibrate run`: measure this host's grid costs and fit them.

The run builds every configuration of :mod:`calibrate.suites` (isolating and
in-context, with exact counts from the instrumented twin), times them with
:func:`calibrate.protocol.measure` in interleaved rounds, and fits the
in-context batch times with :func:`calibrate.fit.fit`.  A seeded fifth of the
in-context configurations is held back from the fit; the fitted constants
predict their batch times and the median absolute relative error is reported.

Measuring proceeds in stages of rounds.  After each stage the in-context
measurements are fitted; with a target relative width of r's 95% interval,
measuring stops once the interval is narrower, or when the time budget is
spent.  Every stage's raw values are written to ``<out>.partial`` atomically;
an interrupted run keeps them and ``calibrate run --resume`` continues.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import calfile, suites
from . import fit as _fit
from ._io import UserError, atomic_write_text, check_writable
from ._grid import intersector_code
from models.memory import candidate_cache_sizes, line_weights, lines_beyond_cache
from .host import cache_bytes as host_cache_bytes, fingerprint, last_cache_bytes
from .protocol import REL_SPREAD_WARN, Measurement, MeasurementInterrupted, measure, pin_to_one_core

#: Default wall-clock budget of a run, seconds.
DEFAULT_BUDGET_S = 60.0
#: Default target: full width of r's 95% interval relative to its median.
DEFAULT_TARGET_REL_WIDTH = 0.06
#: Rounds measured before the first fit, and added by each later stage.
FIRST_ROUNDS = 5
STAGE_ROUNDS = 4
#: Minimum duration of one timed value, ns (pyperf uses 100 ms; batches here are uniform).
MIN_VALUE_NS = 10_000_000
#: Warm-up values discarded per configuration, in a run's first stage only: a later stage's
#: values follow the first's in the same process, and each value is primed
#: (PRIME_EACH_VALUE), so a second warm-up bought nothing but time (one value per
#: configuration, 2-3 s of a 60 s run).
WARMUPS = 1
#: One untimed call of a configuration before each of its values (protocol.measure's prime):
#: interleaving leaves the previous configuration's data in the caches, and a value's first loop
#: then waits on memory.  A/B on this host, 2026-12-02, three runs each (docs/calibration.md):
#: T_mem 2.8 against 3.8-4.5 ns (the cold starts had gone into it), cross-validated error
#: 4.7-5.5% against 4.6-6.1%, isotropic r's 95% half-width 19-20% against 22-26%.
PRIME_EACH_VALUE = True
#: Fraction of in-context configurations held back from the fit to test its predictions.
HOLDOUT_FRACTION = 0.2
#: Share of the budget kept for fitting after the last stage (the pooled fit, then one
#: per ray set): the least kept; a slower host keeps more (FIT_RESERVE_MARGIN, below).
#: It is all the first stage keeps, and the first stage is the last where measuring it
#: takes most of the budget: on a slower 2-core EPYC host (2026-12-07, evening) the first
#: stage measured until the budget less this reserve, and the pooled fit took 6.1 s and the
#: ray sets' 6.2 s: with 9 s kept, two default runs of three ended at 63.7 and 64.1 s, their
#: trials of T_visit, T_mem and T_hit cut short (held-back error 13.5-14%, against 3.7%); with
#: 15 s, two runs ended at 54.6-54.9 s with every term fitted (held back 3.0%).
FIT_RESERVE_S = 15.0
#: The time kept after the last stage is estimated from the stage before it, so that a host
#: whose fits are slow (a noisy one: longer chains) still ends within the budget: the next
#: stage's fits take up to FIT_RESERVE_MARGIN times the last stage's (more values, the same
#: chains), and fitting each ray set alone and cross-validating take
#: max(POST_FIT_MIN_S, POST_FIT_PER_POOLED times the last pooled fit) (two fits of half the
#: data each, with their own trials of the optional terms, then CV_FOLDS maxima per set).
#: Their time hardly follows the pooled fit's, whose trials end early or late as its own
#: data decide: on this project's 2-core EPYC host, 2026-12-06, with 154 in-context
#: configurations, they took 5.1-6.8 s in six runs after last pooled fits of 2.1-3.4 s (in
#: an earlier one, 4 times a 1.8 s pooled fit left the isotropic trials 0.7 s short, and they
#: lost T_visit, T_mem and T_hit); with 5 times the pooled fit the first stage's reserve was
#: 14-21 s, and in two runs of five the second stage did not start (the run ended at 42-46 s
#: of its 60 s; docs/calibration.md, "The budget spent on measuring").  A floor of 8 s left
#: one run's isotropic T_hit trial 0.9 s short after a third stage whose fits took 1.5 s
#: more than the second's: 10 s.  The floor covers this host; the multiple follows a slower one.
FIT_RESERVE_MARGIN = 1.2
POST_FIT_MIN_S = 10.0
POST_FIT_PER_POOLED = 2.5
#: The fits' chains keep to the budget too (``calibrate.fit.fit``'s deadline): a trial of an
#: optional term whose chain cannot converge in time ends, and the term is left out with a
#: warning (a pooled trial that ran to its cap took 8.7 s and the run 63.9 s, 2026-12-06).
#: The pooled fit's trials end by the run's deadline less the time kept for the fits after
#: it (:func:`post_fit_reserve` of the stage before's pooled fit); each ray set's trials by
#: the deadline less FINISH_MARGIN_S, kept for the cross-validation (0.5-0.8 s here) and
#: writing the file.
FINISH_MARGIN_S = 1.5
#: Cap on the chain of an isolating suite's fit (two or three constants; a steady design
#: converges in 1,200-1,500 steps): a chain that wants more is an interval the noise has
#: made too wide, and it is reported as not fitted instead of taking the run's budget.
ISOLATED_MAX_STEPS = 8000
#: The isolating fits stop sampling as soon as a constant's 95% interval spans more than
#: fit.MAX_CI95_DECADES (the in-context fit's optional terms do the same).
ISOLATED_FAIL_FAST = ("t_setup_ns", "t_step_ns", "t_int_ns")
#: Shortest budget accepted, seconds: the fitting reserve plus a few seconds of measuring
#: (the first stage times every configuration FIRST_ROUNDS times).
MIN_BUDGET_S = FIT_RESERVE_S + 4.0
#: Constants whose in-context fit borrows a prior from the isolating suites: set-up
#: and subgrid entry are a few per cent of a real batch, too little for the batches
#: alone to pin them; the isolating suites measure them directly.
#: Width (log units) of each prior. Set-up: 0.3, lets the in-context data move it by tens
#: of per cent. Subgrid entry: 0.7 (a factor of two at one sigma), because the isolating
#: suite enters subgrids of one cell, while a real subgrid entry sets up a traversal of
#: n^3 cells; in-context fits put it at 2-4x the isolated value, and a prior of 0.3 held
#: it down (held-back error of isotropic rays 21% with 0.3, 14.5% with 0.7 on the same
#: measurements; docs/calibration.md).
#: Hit: 0.5; the one-cell suite's aimed rays (every one hits) cost 25-30 ns more than its
#: missing ones in six runs, the in-context fits without a prior put T_hit at 35-78 ns,
#: and without one it trades against T_setup (a scene's hits are a fixed share of its
#: rays): the pooled chain ran 4,574 steps instead of 1,326 (docs/calibration.md, "A cost
#: per hit").
PRIOR_FROM_ISOLATED = {"t_setup_ns": 0.3, "t_sub_ns": 0.7, "t_hit_ns": 0.5}
#: The isolating suites' fits take the configurations whose rays are in the steady state.
#: A walk's first steps cost more than its later ones, and a short triangle list's tests
#: more than a long one's (branches that a long loop trains mispredict in a short one):
#: on this host, 2026-12-02, 4^3 and 8^3 empty grids (4 and 8 steps a ray) cost 10% and 3%
#: above the line through 12^3-32^3 (1^3, one step and a predictable exit, 28% below it),
#: and lists of 16 triangles 9% above the line through 32-256;
#: fitted through all of them, the isolated r's 95% half-width was 31-34%
#: (docs/calibration.md, "The isolating suites' steady state").
STEADY_STEPS_PER_RAY = 10.0
STEADY_TESTS_PER_RAY = 32.0
#: Fewest configurations an isolating fit takes (two for each of up to three constants):
#: when fewer are steady, those with the longest walks or lists, and a warning.
MIN_STEADY_CONFIGS = 6
#: Below this share of a core (the run's thread CPU time over its wall time) the host is
#: called busy: other processes took the rest, and every timed value waited for them.
BUSY_SHARE = 0.8
#: Partial-file format marker.
PARTIAL_FORMAT = "gridcal-partial-run"
PARTIAL_VERSION = 1


@dataclass
class Stage:
    """The state of a run after one stage's fit (what :func:`run_calibration` passes ``on_stage``).

    stage : 1-based stage number; rounds : values requested per configuration so far;
    elapsed_s : wall time since the run started (building, measuring and every fit so far);
    values : timed values over all configurations; result : the stage's :class:`calibrate.fit.FitResult`
    (in-context fit); ratio_rel_width : full width of r's 95% interval over its median.
    """

    stage: int
    rounds: int
    elapsed_s: float
    values: int
    result: object
    ratio_rel_width: float


@dataclass
class RunResult:
    calibration: dict
    wall_s: float
    holdout_mare: float
    ratio_rel_width: float
    warnings: list
    holdout_mare_pooled: float = float("nan")
    holdout_mare_by_rays: dict | None = None
    cv_mare: float = float("nan")
    cv_mare_by_rays: dict | None = None


def partial_path(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def _save_partial(path: Path, seed: int, intersector: str, configs, timings: dict) -> None:
    data = dict(format=PARTIAL_FORMAT, version=PARTIAL_VERSION, seed=seed, intersector=intersector,
                configs=[c.name for c in configs],
                measurements={k: m.to_dict() for k, m in timings.items()})
    atomic_write_text(path, json.dumps(data))


def _load_partial(path: Path, seed: int, intersector: str, configs) -> dict:
    if not path.exists():
        raise UserError(f"{path}: no interrupted run to resume (run without --resume to start one)")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: cannot read the interrupted run ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != PARTIAL_FORMAT:
        raise UserError(f"{path}: not a gridcal partial run")
    if data.get("version") != PARTIAL_VERSION:
        raise UserError(f"{path}: partial-run version {data.get('version')!r} is not {PARTIAL_VERSION}")
    if data.get("intersector") != intersector or data.get("seed") != seed:
        raise UserError(f"{path}: was measured with intersector {data.get('intersector')!r} and seed "
                        f"{data.get('seed')!r}; resume with the same --intersector and --seed")
    if data.get("configs") != [c.name for c in configs]:
        raise UserError(f"{path}: its configurations differ from this version's suites; start a new run")
    out = {}
    for name, rec in data.get("measurements", {}).items():
        try:
            out[name] = Measurement.from_dict(rec)
        except ValueError as exc:
            raise UserError(f"{path}: measurement {name!r}: {exc}") from None
    return out


def holdout_names(configs, seed: int) -> set:
    """A seeded fifth of the in-context configurations, held back from the fit."""
    ctx = [c.name for c in configs if c.kind == "in_context"]
    rng = np.random.default_rng(seed + 7919)
    k = max(1, int(round(HOLDOUT_FRACTION * len(ctx))))
    return set(np.array(ctx)[rng.choice(len(ctx), size=k, replace=False)].tolist())


def records(configs, timings: dict, held: set, cache_size: int | None = None) -> list:
    """JSON records of the configurations with their values; with ``cache_size`` (bytes), an
    in-context record also carries ``misses``, the memory effect's count (models/memory.py).

    A series timed with stamps keeps its values as timed in ``raw_values_ns`` and when each
    ended in ``stamps_s``; its ``values_ns``, what every fit reads, are those over the host's
    common slowdown at the time (:func:`calibrate.calfile.apply_drift`).  A series' warnings
    describe its values as timed."""
    out = []
    for c in configs:
        rec = c.record()
        if cache_size is not None and c.kind == "in_context":
            rec["misses"] = _misses(rec, cache_size)
        m = timings.get(c.name)
        rec["values_ns"] = list(m.values_ns) if m else []
        if m and m.values_ns and len(m.stamps_s) == len(m.values_ns) and min(m.values_ns) > 0:
            rec["raw_values_ns"] = list(m.values_ns)
            rec["stamps_s"] = list(m.stamps_s)
        rec["loops"] = int(m.loops) if m else 0
        rec["warnings"] = m.warnings if m else []
        rec["held_back"] = c.name in held
        out.append(rec)
    return calfile.apply_drift(out)


def with_cache(recs, cache_size: int) -> list:
    """The records with every in-context one's ``misses`` counted against ``cache_size`` bytes."""
    return [dict(r, misses=_misses(r, cache_size)) if r["kind"] == "in_context" else r for r in recs]


def _misses(rec, cache_size: int) -> float:
    """An in-context record's lines beyond a cache of ``cache_size`` bytes (models/memory.py),
    its occupied cells entered counted with its changes of occupancy, as T_visit prices them."""
    visits = float(rec.get("visits", 0)) + float(rec.get("changes", 0))
    return float(lines_beyond_cache(rec["steps"], rec["tests"], rec["memory_bytes"], cache_size, visits))


#: Log-posterior margin within which cache sizes count as tied (:func:`select_cache`): the
#: likelihood-ratio margin that gates an optional term (calfile.MEMORY_MIN_GAIN, half the 5%
#: point of chi-square with one degree of freedom).
CACHE_SCORE_MARGIN = calfile.MEMORY_MIN_GAIN


def select_cache(recs, candidates, seed: int = 0, priors=None) -> tuple[int, dict]:
    """(bytes, {bytes: score}): the cache size C among ``candidates`` whose memory term fits the
    in-context timings best (models/memory.py: which cache a traversal runs out of differs by host).

    A candidate's score is the sum over ray sets of the maximum log posterior
    (:func:`calibrate.fit.max_log_posterior`) of that set's fitted configurations (held-back
    ones are not looked at) with every term the design carries and ``misses`` counted against
    C: the same terms and values for every candidate, so the scores compare as log-likelihoods.
    A candidate whose fit fails scores -inf.  Of the candidates within CACHE_SCORE_MARGIN of
    the best score, which the timings do not tell apart, the largest is taken: it charges the
    memory term to the fewest grids.  A smaller one taxes every step and test of the mid-size
    grids, which is what the suite's few grids between the caches cannot tell from T_step and
    T_int: a run whose 4 MiB scored 108.4 against 107.4 for 16 MiB fitted its isotropic rays
    with T_mem 2.0 ns a line beyond 4 MiB and r 0.31 [0.22, 0.52], whose plans were 25-58% a
    side finer than the measured best on the bunny, the armadillo and Sponza (+5.8%, +4.7%,
    +15.3%), where the same timings with C = 16 MiB plan within 4% (docs/calibration.md,
    "Occupancy changes priced, and the cache size").  When every candidate fails, the
    smallest is returned (its fit then says why).
    """
    ctx = [r for r in recs if r["kind"] == "in_context" and r["values_ns"] and not r.get("held_back")]
    sets = sorted({r.get("ray_set") for r in ctx}, key=str)
    scores = {}
    for c in candidates:
        total = 0.0
        for name in sets:
            group = with_cache([r for r in ctx if r.get("ray_set") == name], c)
            try:
                total += _fit.max_log_posterior(calfile.design_from_measurements(group, "in_context"), seed,
                                                priors=priors)
            except (ValueError, _fit.ConvergenceError):
                total = -math.inf
                break
        scores[int(c)] = total
    best = max(scores.values())
    if not math.isfinite(best):
        return min(scores), scores
    return max(c for c, v in scores.items() if v >= best - CACHE_SCORE_MARGIN), scores


def _priors(isolated):
    priors = {}
    for name, sigma_log in PRIOR_FROM_ISOLATED.items():
        est = (isolated or {}).get(name)
        if est:
            priors[name] = (est["median"], sigma_log)
    return priors


def _fit_clock(deadline):
    """The run's ``deadline`` (by this module's clock) on the clock the fits read
    (``calibrate.fit``'s ``time.monotonic``): the same in a run, apart where a test fakes one."""
    return None if deadline is None else _fit.time.monotonic() + (deadline - time.monotonic())


def _fit_stage(recs, seed, isolated, deadline=None):
    design = calfile.design_from_measurements(recs, "in_context")
    return calfile.fit_in_context(design, seed=seed, priors=_priors(isolated), deadline=_fit_clock(deadline))


def _holdout(result, by_rays, recs):
    """Held-back errors: (MARE of the predictions the file gives, pooled fit's MARE, {ray set: MARE}).

    A held-back configuration is predicted by its ray set's own fit when there is
    one (as ``predict --rays`` does), else by the pooled fit.
    """
    held = [r for r in recs if r["held_back"] and r["values_ns"]]
    if not held:
        return float("nan"), float("nan"), {}
    pooled = _fit.holdout_errors(result, calfile.design_from_measurements(held, "in_context",
                                                                          include_held_back=True))
    errors, by_set = [], {}
    for name in sorted({r.get("ray_set") for r in held}, key=str):
        group = [r for r in held if r.get("ray_set") == name]
        fit = by_rays.get(name, result)
        e = _fit.holdout_errors(fit, calfile.design_from_measurements(group, "in_context", include_held_back=True))
        errors.extend(e)
        if name in by_rays:
            by_set[name] = float(np.median(e))
    return float(np.median(errors)), float(np.median(pooled)), by_set


#: Folds of the cross-validated error the run reports beside the held-back one.
CV_FOLDS = 5


def _cross_validated(result, by_rays, recs, seed, priors):
    """(median error over every in-context configuration, {ray set: median}), each configuration
    predicted by the posterior maximum of its ray set's model (with T_mem and T_visit when that
    set's fit has them) fitted to the other CV_FOLDS - 1 folds; (nan, {}) when a fold cannot be fitted."""
    groups = {}
    for r in recs:
        if r["kind"] == "in_context" and r["values_ns"]:
            groups.setdefault(r.get("ray_set") if r.get("ray_set") in by_rays else None, []).append(r)
    errors, by_set = [], {}
    for name, group in sorted(groups.items(), key=lambda kv: str(kv[0])):
        fit = by_rays.get(name, result)
        design = calfile.design_from_measurements(group, "in_context", include_held_back=True)
        for col, constant, _ in calfile.OPTIONAL_TERMS:
            if constant not in fit.names:
                design.pop(col, None)
        try:
            e = _fit.cross_validated_errors(design, min(CV_FOLDS, len(group)), seed, priors=priors)
        except ValueError:
            return float("nan"), {}
        errors.extend(e)
        if name is not None:
            by_set[name] = float(np.median(e))
    return (float(np.median(errors)) if errors else float("nan")), by_set


def _rel_width(result) -> float:
    r = result.constants["ratio"]
    return (r["ci95"][1] - r["ci95"][0]) / r["median"]


def rel_spread(values_ns) -> float:
    """A configuration's scaled MAD over its median (protocol.Measurement.rel_spread)."""
    return Measurement(loops=1, values_ns=list(values_ns)).rel_spread


def spread_summary(spreads, n_configs: int, detrended=None) -> str:
    """One warning for every configuration whose values spread more than the protocol's
    threshold (each keeps its own warning in the file's measurements): on a noisy host
    most do, and a line each would bury the other warnings.  ``detrended``: the same
    configurations' spreads with the host's common slowdown divided out, whose median
    the warning adds."""
    s = np.sort(np.asarray(spreads, dtype=float))
    after = ""
    if detrended is not None and len(detrended):
        after = (f"; {100 * float(np.median(detrended)):.0f}% with the host's common slowdown "
                 "divided out, as the fits see them")
    return (f"large spread in {s.size} of {n_configs} configurations: scaled MAD {100 * s[0]:.0f}-{100 * s[-1]:.0f}% "
            f"of the median (median {100 * float(np.median(s)):.0f}%; threshold {100 * REL_SPREAD_WARN:.0f}%"
            f"{after}); the host may be busy or noisy (each configuration's warnings are in the file's measurements)")


def post_fit_reserve(pooled_fit_s: float) -> float:
    """Seconds to keep for each ray set's fit and the cross-validation after the last pooled
    fit, from the stage before's pooled fit (``pooled_fit_s``)."""
    return max(POST_FIT_MIN_S, POST_FIT_PER_POOLED * pooled_fit_s)


def fit_reserve(stage_fit_s: float, pooled_fit_s: float) -> float:
    """Seconds to keep after the last stage's measuring, from the last stage's fitting time
    (``stage_fit_s``: the isolating suites and the pooled fit) and its pooled fit's alone:
    the next stage's fits, then each ray set's and the cross-validation
    (:func:`post_fit_reserve`); never less than FIT_RESERVE_S."""
    return max(FIT_RESERVE_S, FIT_RESERVE_MARGIN * stage_fit_s + post_fit_reserve(pooled_fit_s))


def _suite_design(recs, suite, per_ray, threshold, aimed_column=False):
    """The design of one isolating suite's steady-state configurations, and a note or None.

    per_ray : the count ("steps" or "tests") whose mean per ray decides the steady state;
    threshold : the least mean a configuration's rays must reach.  When fewer than
    MIN_STEADY_CONFIGS do, the configurations with the most are used and the note says so.
    aimed_column : for the one-cell suite, whose rays step once each (steps duplicate rays):
    the ``steps`` column counts the aimed rays instead, so that a hitting ray's extra
    per-ray cost (filling in its hit) gets its own constant and does not bend T_int.
    """
    chosen = [r for r in recs if r["kind"] == "isolated" and r["suite"] == suite and r["values_ns"]]
    if not chosen:
        raise ValueError(f"no {suite} measurements")
    chosen.sort(key=lambda r: r[per_ray] / r["rays"])
    steady = [r for r in chosen if r[per_ray] / r["rays"] >= threshold]
    note = None
    if len(steady) < MIN_STEADY_CONFIGS:
        n_steady, steady = len(steady), chosen[-MIN_STEADY_CONFIGS:]
        note = (f"{suite} suite: {n_steady} configurations reach {threshold:g} {per_ray} a ray; "
                f"fitted on the {len(steady)} with the most (their rays may not be in the steady state)")
    design = {k: np.array([float(r[k]) for r in steady]) for k in ("rays", "steps", "tests", "subgrids")}
    if aimed_column:
        design["steps"] = np.array([float(r["rays"]) if r.get("ray_set") == "aimed" else 0.0 for r in steady])
    design["times_ns"] = [list(r["values_ns"]) for r in steady]
    return design, note


#: The one-cell suite's designs, tried in turn until one fits: (least tests a ray, aimed
#: rays' extra cost a constant of its own).  The first is the steady state; the others are
#: for an intersector whose steady lists do not draw a line with a positive per-ray cost
#: (Moller-Trumbore on this host: 15 ns a test from 16 to 32 triangles, 17.5 from 128 to
#: 256, so the line through the long lists meets zero tests at -80 ns, and its aimed rays
#: cost no more than its missing ones).
CELL_SUITE_DESIGNS = ((STEADY_TESTS_PER_RAY, True), (STEADY_TESTS_PER_RAY, False), (0.0, True), (0.0, False))


def _first_design_that_fits(tries, seed, required, what):
    """Fit the designs of ``tries``, (design, note, name) each, in turn until one fits (an
    isolating suite's fit: capped at ISOLATED_MAX_STEPS, stopped early on an unidentified
    constant).  Returns (FitResult, note): the design's own note, and when it was not the
    first, which was fitted and why those before it were not.  Raises the first error when
    none fits."""
    first_error, notes = None, []
    for design, note, name in tries:
        try:
            res = _fit.fit(design, seed=seed, required=required, max_steps=ISOLATED_MAX_STEPS,
                           fail_fast=ISOLATED_FAIL_FAST)
        except (ValueError, _fit.ConvergenceError) as exc:
            first_error = first_error or exc
            notes.append(f"{name}: {exc}")
            continue
        if notes:
            note = "; ".join(([note] if note else []) + [f"{what} fitted on {name}, since " + "; ".join(notes)])
        return res, note
    raise first_error


def fit_cell_suite(recs, seed):
    """The one-cell suite's fit: on its steady-state lists with the aimed rays' extra cost
    apart when that fits, else the next of CELL_SUITE_DESIGNS that does (the note says which
    and why).  Returns (:class:`calibrate.fit.FitResult` whose ``t_int_ns`` is T_int, note or
    None); raises the first design's error when none fits."""
    tries = []
    for threshold, aimed in CELL_SUITE_DESIGNS:
        design, note = _suite_design(recs, "cell", "tests", threshold, aimed_column=aimed)
        if not aimed:
            design["steps"] = np.zeros_like(design["steps"])  # each ray steps once: steps are rays
        name = ("every list" if threshold <= 0 else f"lists of {threshold:g}+ triangles") + (
            ", aimed rays apart" if aimed else ", one per-ray cost")
        tries.append((design, note, name))
    return _first_design_that_fits(tries, seed, ("rays", "tests"), "cell suite")


#: The empty-grid suite's designs, tried in turn until one fits (least steps a ray): the
#: steady walks, then every walk.  On a noisy host the steady walks (12 to 39 steps a ray)
#: can leave the per-ray cost unidentified (an AMD EPYC host, 2026-12-03, values spread
#: 10-24%: T_setup's 95% interval [0.09, 108] ns); the short walks pin it, at the price of
#: their transient in T_step.
EMPTY_SUITE_DESIGNS = (STEADY_STEPS_PER_RAY, 0.0)


def fit_empty_suite(recs, seed):
    """The empty-grid suite's fit: on its steady walks when that fits, else on every walk (the
    note says so and why).  Returns (:class:`calibrate.fit.FitResult` with T_setup and T_step,
    note or None); raises the first design's error when none fits."""
    tries = [(*_suite_design(recs, "empty", "steps", threshold),
              "every walk" if threshold <= 0 else f"walks of {threshold:g}+ steps") for threshold in EMPTY_SUITE_DESIGNS]
    return _first_design_that_fits(tries, seed, ("rays", "steps"), "empty-grid suite")


def _isolated_fit(recs, seed):
    """First estimates from the isolating suites, each fitted on its own, in the steady state.

    - empty grids: batch = rays*T_setup + steps*T_step, on the grids whose rays take at least
                   STEADY_STEPS_PER_RAY steps                       -> T_setup, T_step
    - one cell:    batch = rays*a + aimed rays*b + tests*T_int, on the lists of at least
                   STEADY_TESTS_PER_RAY triangles (a: set-up and the one step; b: what a
                   hitting ray adds)                                -> T_int, T_hit = b
    - subgrids:    the same grid with and without a 1x1x1 subgrid in every cell;
                   each entry adds one cell step and one subgrid entry, so
                   T_sub = (time(all) - time(none)) / subgrids - T_step (paired, per side).
    - r = T_int / T_step: the first two fits' posterior samples paired at random (the
                   suites are fitted apart, so their posteriors are independent).
    The isolated constants are marginal costs: what one more step or test costs a ray
    that is already walking or testing.  Returns (constants dict in the calibration's
    form, warning or None).
    """
    out, problems = {}, []
    step_samples = int_samples = None
    try:
        res, note = fit_empty_suite(recs, seed)
        if note:
            problems.append(note)
        out["t_setup_ns"] = calfile.constants_json(res)["t_setup_ns"]
        out["t_step_ns"] = calfile.constants_json(res)["t_step_ns"]
        step_samples = res.samples[:, res.names.index("t_step_ns")]
    except (ValueError, _fit.ConvergenceError) as exc:
        problems.append(f"empty-grid suite: {exc}")
    try:
        res, note = fit_cell_suite(recs, seed)
        if note:
            problems.append(note)
        out["t_int_ns"] = calfile.constants_json(res)["t_int_ns"]
        int_samples = res.samples[:, res.names.index("t_int_ns")]
        if res.constants.get("t_step_ns") is not None:
            # the design with the aimed rays apart: their column's constant is what a hit adds
            out["t_hit_ns"] = calfile.constants_json(res)["t_step_ns"]
    except (ValueError, _fit.ConvergenceError) as exc:
        problems.append(f"one-cell suite: {exc}")
    sub = [r for r in recs if r["kind"] == "isolated" and r["suite"] == "subgrid" and r["values_ns"]]
    t_step = out.get("t_step_ns")
    if t_step and sub:
        by_res = {}
        for r in sub:
            by_res.setdefault(r["resolution"].split(" / ")[0], {})["all" if r["subgrids"] else "none"] = r
        diffs = [(float(np.median(p["all"]["values_ns"])) - float(np.median(p["none"]["values_ns"])))
                 / p["all"]["subgrids"] - t_step["median"] for p in by_res.values() if len(p) == 2]
        d = np.array(diffs)
        if d.size and np.median(d) > 0:
            # The median of the paired differences; a busy host can push single pairs below
            # zero, which bounds the interval at 0 (free) rather than losing the estimate.
            lo, hi = max(float(d.min()), 0.0), float(d.max())
            out["t_sub_ns"] = {"median": float(np.median(d)), "ci68": [lo, hi], "ci95": [lo, hi]}
            if d.min() <= 0:
                problems.append(f"subgrid suite: {int((d <= 0).sum())} of {d.size} paired differences show no "
                                "cost beyond a cell step (a busy host?); their median is used")
        elif d.size:
            problems.append("subgrid suite: entering a subgrid costs no more than a cell step here")
    if step_samples is not None and int_samples is not None:
        # The two suites are fitted apart, so their posteriors are independent: the ratio's
        # posterior pairs their samples at random (both shuffled, the longer cut to the shorter).
        rng = np.random.default_rng(seed)
        n = min(step_samples.size, int_samples.size)
        ratio = rng.permutation(int_samples)[:n] / rng.permutation(step_samples)[:n]
        summary = _fit.summarize(ratio)
        out["ratio"] = {"median": summary["median"], "ci68": list(summary["ci68"]), "ci95": list(summary["ci95"])}
    return out, ("isolated: " + "; ".join(problems)) if problems else None


def _finish(result, recs, seed, priors, warnings, deadline=None):
    """What a run does after its last pooled fit, and ``calibrate fit`` after its re-fit: each
    ray set's fit, the held-back errors ((MARE, pooled MARE, {ray set: MARE})) and the
    cross-validated ones ((median, {ray set: median})).  Ray sets not fitted alone and optional
    terms the pooled fit left out are said in ``warnings``.  ``deadline``: the run's end, which
    the ray sets' trial terms (:func:`calibrate.calfile.fit_in_context`) must leave FINISH_MARGIN_S
    before.  Returns (by_rays, skipped, held-back errors, cross-validated errors)."""
    end = None if deadline is None else deadline - FINISH_MARGIN_S
    by_rays, skipped = calfile.fit_by_rays(recs, seed=seed, priors=priors, deadline=_fit_clock(end))
    for name, why in skipped.items():
        warnings.append(f"ray set {name}: not fitted alone, its predictions use the pooled constants ({why})")
    for _, name, _ in calfile.OPTIONAL_TERMS:
        if f"{name[:-3]}_skipped" in result.diagnostics:
            warnings.append(result.diagnostics[f"{name[:-3]}_skipped"])
    return by_rays, skipped, _holdout(result, by_rays, recs), _cross_validated(result, by_rays, recs, seed, priors)


def checked_cache_bytes(value) -> int:
    """A cache size given by hand (``--cache``; :func:`run_calibration`, :func:`refit_calibration`):
    a whole number of bytes > 0, else UserError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise UserError(f"the cache size must be a whole number of bytes > 0, got {value!r}")
    return int(value)


def refit_calibration(cal, *, seed: int = 0, cache_bytes: int | None = None) -> tuple[dict, list]:
    """``calibrate fit``: a run's fits again on a calibration's stored measurements, by this
    version's code (the in-context records' ``misses`` counted again against the file's cache
    size by this version's memory model): the isolating suites (their constants give the in-context priors; a file
    without their measurements keeps its stored priors), the pooled fit, each ray set's, and
    the held-back and cross-validated errors the file reports (``meta``), so that they describe
    the new fit, not the old one.

    ``cache_bytes`` (``calibrate fit --cache``): count the in-context records' lines beyond a
    cache of that many bytes instead of the file's, and record it (``meta.cache_bytes``,
    ``meta.cache_source``); the run's scores of the sizes it tried stay in ``meta.cache_scores``.
    The cache the suite's timings fit best need not be the one whose plans are best: on this
    project's 2-core EPYC host, three runs that chose 8, 8 and 16 MiB all planned within 3.6% of
    their sweeps' best refitted at 16 MiB, and one of the 8 MiB ones 8.2% off as chosen
    (docs/calibration.md, "Shorter values, half an octave of cache, and r from run to run").
    Returns (validated calibration, warnings)."""
    cal = calfile.validate(calfile._plain(cal))
    recs = calfile.apply_drift(cal["measurements"])
    cache = calfile.cache_bytes_of(cal)
    ctx = [r for r in recs if r["kind"] == "in_context"]
    if cache_bytes is not None:
        cache_bytes = checked_cache_bytes(cache_bytes)
        lacking = sum(1 for r in ctx if "memory_bytes" not in r)
        if not ctx:
            raise UserError("--cache: the file holds no in-context measurements, so no cache lines can be counted "
                            "against another cache")
        if lacking:
            raise UserError(f"--cache: {lacking} of the file's {len(ctx)} in-context measurements do not record their "
                            f"grid's bytes (memory_bytes), so their cache lines cannot be counted against another "
                            f"cache (a file written before the memory term: run `calibrate run` again)")
        cache = cache_bytes
        recs = with_cache(recs, cache)
    elif cache is not None and ctx and all("misses" in r and "memory_bytes" in r for r in ctx):
        # the memory effect's count by this version's model: a file written before the spread of
        # cache sizes (models.memory, 2026-12-06) carries one cache's counts
        recs = with_cache(recs, cache)
    warnings = []
    if any(r["kind"] == "isolated" and r["values_ns"] for r in recs):
        isolated, iso_warning = _isolated_fit(recs, seed)
        if iso_warning:
            warnings.append(iso_warning)
        priors = _priors(isolated)
    else:
        isolated = cal.get("isolated", {})
        priors = calfile.stored_priors(cal)
    result = calfile.fit_in_context(calfile.design_from_measurements(recs, "in_context"), seed=seed, priors=priors)
    by_rays, skipped, (mare, mare_pooled, mare_by_rays), (cv, cv_by_rays) = _finish(result, recs, seed, priors,
                                                                                     warnings)
    meta = {k: v for k, v in cal.get("meta", {}).items() if k != "by_rays_skipped"}
    if any(r.get("held_back") for r in recs):
        meta.update(holdout_mare=None if math.isnan(mare) else mare,
                    holdout_mare_pooled=None if math.isnan(mare_pooled) else mare_pooled,
                    holdout_mare_by_rays=mare_by_rays, cv_mare=None if math.isnan(cv) else cv,
                    cv_mare_by_rays=cv_by_rays)
    meta.update(ratio_rel_width=_rel_width(result), refit_seed=seed, line_weights=line_weights())
    if cache_bytes is not None:
        meta.update(cache_bytes=cache, cache_source=f"set by `calibrate fit --cache` ({cache} bytes)")
    if skipped:
        meta["by_rays_skipped"] = skipped
    new = calfile.from_fit(result, fingerprint=cal["fingerprint"], measurements=recs, isolated=isolated, meta=meta,
                           by_rays=by_rays)
    return new, warnings


def cpu_share(wall_s: float, cpu_s: float) -> float:
    """The share of one core a thread had: its CPU time over the wall time (1 on a quiet host)."""
    return cpu_s / wall_s if wall_s > 0 else 1.0


def busy_note(share: float) -> str:
    """Half a sentence on a busy host, or "" when the run had (nearly) a core of its own."""
    if share >= BUSY_SHARE:
        return ""
    return (f"this run's thread had {100 * share:.0f}% of a core (the host is busy: other processes "
            f"took the rest)")


def not_fitted_message(exc, *, budget_s: float, set_up_s: float, configs, timings: dict, share: float,
                       out: Path, part: Path, seed: int = 0, intersector: str = "watertight",
                       cache_bytes: int | None = None) -> str:
    """Why a run that fitted nothing ends, and how to continue from what it measured (the
    command names the seed and the intersector when they are not the defaults: a partial
    file resumes only with its own; and the run's --cache when it had one)."""
    context = [c.name for c in configs if c.kind == "in_context"]
    measured = sum(1 for name in context if name in timings and len(timings[name].values_ns))
    busy = busy_note(share)
    same = (f" --seed {seed}" if seed != 0 else "") + (f" --intersector {intersector}"
                                                      if intersector != "watertight" else "")
    same += f" --cache {cache_bytes}" if cache_bytes is not None else ""
    return (f"the measurements could not be fitted within the {budget_s:g} s budget ({exc}): building "
            f"the suites took {set_up_s:.0f} s, and {measured} of {len(context)} in-context configurations "
            f"had values when the time kept for fitting began" + (f"; {busy}" if busy else "") +
            f". The values measured are kept in {part}: `calibrate run --resume --out {out}{same} "
            f"--budget {2 * budget_s:g}` continues from them")


def run_calibration(out: Path, *, budget_s: float = DEFAULT_BUDGET_S,
                    target_rel_width: float | None = DEFAULT_TARGET_REL_WIDTH,
                    intersector: str = "watertight", seed: int = 0, resume: bool = False,
                    progress=None, status=None, on_stage=None, started: float | None = None,
                    cache_bytes: int | None = None) -> RunResult:
    """Measure, fit, validate on held-back configurations, and save ``out`` atomically.

    progress(done, total, label) reports measuring; status(text) reports stages.
    on_stage(stage) is called after every stage's fit with a :class:`Stage` (the
    posterior a run stopping there would have); a true return value ends measuring
    there, as a reached target would (``calibrate tradeoff`` reads one long run's
    stages as the runs of shorter budgets).
    started : ``time.monotonic()`` at which the budget began (the command line passes its
    own start, so that the budget covers importing the fitting libraries); now when None.
    cache_bytes : the memory term's cache size (``--cache``), instead of the best fit among the
    sizes from the level-2 to the last-level cache (:func:`select_cache`): the size the suite's
    timings fit best is not always the one whose plans are best (docs/compare.md, "Which cache
    the plans want").
    Raises UserError for bad arguments, MeasurementInterrupted (after saving the
    partial file) on Ctrl-C, and fit errors when the data cannot be fitted.
    """
    if not (isinstance(budget_s, (int, float)) and math.isfinite(budget_s) and budget_s > 0):
        raise UserError(f"--budget must be a positive number of seconds, got {budget_s!r}")
    if budget_s < MIN_BUDGET_S:
        raise UserError(f"--budget {budget_s:g} s is too short: a run needs at least {MIN_BUDGET_S:g} s "
                        f"({FIT_RESERVE_S:g} s of it for fitting)")
    if target_rel_width is not None and not (math.isfinite(target_rel_width) and target_rel_width > 0):
        raise UserError(f"--target-rel-width must be a positive number, got {target_rel_width!r}")
    if not (isinstance(seed, int) and 0 <= seed < 2**32):
        raise UserError(f"--seed must be a whole number from 0 to 2^32 - 1, got {seed!r}")
    intersector_code(intersector)  # validates the name
    # Every input and destination is checked before anything is built or measured.
    out = check_writable(out)
    part = partial_path(out)
    if resume and not part.exists():
        raise UserError(f"{part}: no interrupted run to resume (run without --resume to start one)")
    check_writable(part)
    status = status or (lambda text: None)
    t_start = time.monotonic() if started is None else float(started)
    deadline = t_start + budget_s
    wall_here, cpu_here = time.monotonic(), time.thread_time()

    def share_so_far() -> float:
        return cpu_share(time.monotonic() - wall_here, time.thread_time() - cpu_here)

    warnings: list = []

    if cache_bytes is not None:
        cache_bytes = checked_cache_bytes(cache_bytes)
        cache, candidates = cache_bytes, [cache_bytes]
        cache_source, cache_scores = f"set by `calibrate run --cache` ({cache_bytes} bytes)", None
    else:
        cache, l2_source = host_cache_bytes()
        candidates = candidate_cache_sizes(cache, last_cache_bytes())
        cache_source, cache_scores = l2_source, None
    with pin_to_one_core() as pin:
        status("building grids and counting work with the instrumented twin")
        configs = suites.isolated_configs(intersector, seed) + suites.context_configs(intersector, seed)
        set_up_s = time.monotonic() - wall_here
        timings = _load_partial(part, seed, intersector, configs) if resume else {}
        held = holdout_names(configs, seed)
        runs = {c.name: c.run for c in configs}
        rng = np.random.default_rng(seed)
        rounds = max([FIRST_ROUNDS] + [len(m.values_ns) for m in timings.values()])
        result = None
        last_fit = None  # (stage, records, isolated, warning, result, cache) of the last stage that fitted
        stage = 0
        reserve = FIT_RESERVE_S  # kept for the fits after the last stage; re-estimated by each stage
        post_reserve = FIT_RESERVE_S / 2  # of it, what each ray set's fit and the cross-validation take
        while True:
            stage += 1
            status(f"measuring stage {stage}: {len(configs)} configurations to {rounds} values each")
            try:
                measure(runs, rng=rng, rounds=rounds, warmups=WARMUPS if stage == 1 else 0,
                        min_value_ns=MIN_VALUE_NS,
                        progress=progress, deadline=deadline - reserve, into=timings,
                        prime=PRIME_EACH_VALUE)
            except MeasurementInterrupted:
                _save_partial(part, seed, intersector, configs, timings)
                raise
            _save_partial(part, seed, intersector, configs, timings)
            recs = records(configs, timings, held, cache)
            status("fitting")
            fit_start = time.monotonic()
            isolated, iso_warning = _isolated_fit(recs, seed)
            if len(candidates) > 1:
                cache, cache_scores = select_cache(recs, candidates, seed, _priors(isolated))
                recs = with_cache(recs, cache)
                cache_source = (f"the best fit of the timings among {len(candidates)} sizes from the level-2 "
                                f"cache ({l2_source}) to the last-level one")
            pooled_start = time.monotonic()
            try:
                result = _fit_stage(recs, seed, isolated, deadline - post_reserve)
            except (ValueError, _fit.ConvergenceError) as exc:
                if time.monotonic() < deadline - reserve:
                    rounds += STAGE_ROUNDS
                    continue
                if last_fit is None:
                    raise UserError(not_fitted_message(exc, budget_s=budget_s, set_up_s=set_up_s, configs=configs,
                                                       timings=timings, share=share_so_far(), out=out, part=part,
                                                       seed=seed, intersector=intersector,
                                                       cache_bytes=cache_bytes)) from None
                # A later stage's data can fit worse than an earlier one's (e.g. with many repeats a
                # small misfit makes a constant's interval reach towards 0): keep the last fit that
                # worked, with the measurements it was made from, and say so.
                fitted_stage, recs, isolated, iso_warning, result, (cache, cache_scores, cache_source) = last_fit
                n_kept = sum(len(r["values_ns"]) for r in recs)
                n_all = sum(len(m.values_ns) for m in timings.values())
                warnings.append(f"the last stage's fit failed ({exc}); the calibration is stage {fitted_stage}'s "
                                f"fit and keeps the {n_kept} values it was made from (of {n_all} measured)")
                break
            last_fit = (stage, recs, isolated, iso_warning, result, (cache, cache_scores, cache_source))
            fit_end = time.monotonic()
            reserve = fit_reserve(fit_end - fit_start, fit_end - pooled_start)
            post_reserve = min(reserve, post_fit_reserve(fit_end - pooled_start))
            width = _rel_width(result)
            enough = target_rel_width is None or width <= target_rel_width
            if on_stage is not None and on_stage(Stage(
                    stage=stage, rounds=rounds, elapsed_s=time.monotonic() - t_start, result=result,
                    values=sum(len(m.values_ns) for m in timings.values()), ratio_rel_width=width)):
                enough = True
            if enough or time.monotonic() >= deadline - reserve:
                if not enough:
                    warnings.append(f"budget spent: the pooled fit's r has a 95% interval {100 * width:.1f}% of its "
                                    f"median wide, target {100 * target_rel_width:.1f}%")
                break
            rounds += STAGE_ROUNDS

        status("fitting each ray set alone")
        by_rays, skipped, (mare, mare_pooled, mare_by_rays), (cv, cv_by_rays) = _finish(
            result, recs, seed, _priors(isolated), warnings, deadline)
        if iso_warning:
            warnings.append(iso_warning)
        cut = 0
        spreads, detrended = [], []
        for r in recs:
            for w in r["warnings"]:
                if "stopped early" in w:  # the budget's deadline, reported once below
                    cut += 1
                    continue
                if w.startswith("large spread"):  # one line for all of them, below
                    spreads.append(rel_spread(r.get("raw_values_ns", r["values_ns"])))
                    if "raw_values_ns" in r:
                        detrended.append(rel_spread(r["values_ns"]))
                    continue
                warnings.append(f"{r['name']}: {w}")
        if spreads:
            warnings.append(spread_summary(spreads, len(recs), detrended))
        if cut:
            lengths = sorted(len(r["values_ns"]) for r in recs)
            warnings.append(f"the budget ended the last stage early: {cut} of {len(recs)} configurations have "
                            f"fewer than the {rounds} values it asked for ({lengths[0]}-{lengths[-1]}; all are used)")
        wall = time.monotonic() - t_start
        share = share_so_far()
        busy = busy_note(share)
        if busy:
            warnings.append(f"{busy}: its values waited for them, so the constants are slower and "
                            f"their intervals wider than a quiet host's")
        meta = dict(tool="gridcal", budget_s=budget_s, target_rel_width=target_rel_width, seed=seed,
                    intersector=intersector, wall_s=wall, stages=stage, rounds=rounds,
                    holdout_fraction=HOLDOUT_FRACTION, holdout_mare=mare, holdout_mare_pooled=mare_pooled,
                    holdout_mare_by_rays=mare_by_rays, cv_mare=None if math.isnan(cv) else cv,
                    cv_mare_by_rays=cv_by_rays, cv_folds=CV_FOLDS,
                    ratio_rel_width=_rel_width(result), pinned_core=pin.core, pin_note=pin.note,
                    rays_per_batch=suites.RAYS_PER_BATCH, context_rays_per_batch=suites.CONTEXT_RAYS_PER_BATCH,
                    min_value_ns=MIN_VALUE_NS,
                    cache_bytes=cache, cache_source=cache_source, cache_candidates=candidates,
                    line_weights=line_weights(), cpu_share=share)
        if cache_scores is not None:
            meta["cache_scores"] = {str(c): (v if math.isfinite(v) else None) for c, v in cache_scores.items()}
        if skipped:
            meta["by_rays_skipped"] = skipped
        from ._kernels import CFLAGS, traverse_isa

        cal = calfile.from_fit(result, fingerprint=fingerprint(
            extra={"kernel_build": CFLAGS, "kernel_isa": traverse_isa(),
                   "timing_clock": suites.TIMING_CLOCK}),
                               measurements=recs, isolated=isolated, meta=meta, by_rays=by_rays)
        calfile.save(out, cal)
        if part.exists():
            part.unlink()
    return RunResult(calibration=cal, wall_s=wall, holdout_mare=mare, ratio_rel_width=_rel_width(result),
                     warnings=warnings, holdout_mare_pooled=mare_pooled, holdout_mare_by_rays=mare_by_rays,
                     cv_mare=cv, cv_mare_by_rays=cv_by_rays)

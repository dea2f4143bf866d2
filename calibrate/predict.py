"""`calibrate predict`: the recommended grid for a mesh, its predicted cost and why.

:func:`predict` turns a scene and the host's constants (a calibration's posterior
samples, or a user's own ratio ``r = T_int / T_step``) into the recommended grid per
level, the predicted counts and ns per ray, the effects the prediction used (with
reasons) and the resolutions of today's heuristics beside it.  :func:`add_parser`
registers the ``predict`` verb on the command line (``cmd_predict`` runs it).

Fidelities (DESIGN §3.3):

``paper``
    The talk's closed forms for the scene's class (compact -> points law,
    long-skinny -> lines law, mixed -> points law), and the talk's own cost model
    for the counts (a cube of ``m^3`` cells: ``m`` steps, ``N/m^2`` or ``N/m`` tests;
    a ray enters ``k`` subgrids per level).  Microseconds.
``analytic``
    The general integral-geometry model (:mod:`models.general`) with the effects
    :func:`models.effects.select_effects` keeps; nested grids by Crofton composition
    (:mod:`models.nested`).  One pass over the mesh, and where rays stop on it measured
    with TERMINATION_RAYS lines up to TERMINATION_SAMPLE_MAX_TRIANGLES triangles
    (:func:`sample_termination`); both cached per scene object.
``simulated``
    The instrumented kernel (:meth:`calibrate._grid.Grid.count`) traverses a sample of
    rays through the real scene at a few resolutions around the analytic optimum; the
    measured count curves ``steps(s)``, ``tests(s)`` (``s`` = per-axis scale of the
    resolution) are fitted and minimised.  They include what the analytic terms model
    only approximately or not at all: termination at the first hit, clustering, the
    kernel's own insertion, and camera rays.  Nested grids (L >= 2) are built in the
    kernel as the analytic plan gives them and counted (not re-optimised).

Units: with a calibration every time is ns.  With ``ratio`` alone (no calibration)
``T_setup = 0``, ``T_step = 1``, ``T_int = r`` and ``T_sub = RATIO_MODE_T_SUB_IN_T_STEP``:
every cost is then *in units of T_step*; the result's ``predicted.ns_per_ray`` is
``None`` and ``predicted.cost_t_step`` holds ``{median, ci95}`` in those units.
"""

from __future__ import annotations

import itertools
import math
import time
import weakref
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import nlopt
import numpy as np

from models import baselines as _baselines
from models.closed_forms import MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS, cells_to_resolution, l_level_cells
from models.effects import EFFECT_TOLERANCE, select_effects, termination_fraction
from models.general import (THIN_AXIS_CELLS, Terms, cell_fraction, expected_refs, occupancy_changes,
                            predict_uniform, steps_per_ray, stopped_tests_per_ray, terminated_visits, visits_per_ray)
from models.memory import BITMAP_BYTES_PER_CELL, line_weights, lines_beyond_cache, read_bytes
from models.nested import MAX_LEVELS, TooManyPairs, clustering_change, nested_counts
from models.portable import paper_k, paper_level_cells
from models.stats import TerminationSample, scene_class, triangle_geometry, triangle_sample
from models.uncertainty import discrete_posterior_optimum, posterior_optimum, summarise

from ._grid import Grid, Scene, resolution_for_cells, triangle_box_overlap
from ._io import UserError

FIDELITIES = ("paper", "analytic", "simulated")
LEVEL_CHOICES = ("auto", "1", "2", "3")
RAY_KINDS = ("isotropic", "camera")
DEFAULT_CALIBRATION = "calibration.json"
DEFAULT_SCENE = "sphere"

# --- memory layout of the kernel's grid (kernels/gc_internal.h, kernels/grid.c) ---------
#: gc_cell: begin + count, two uint32.
BYTES_PER_CELL = 8
#: The occupancy bitmap: a bit a cell, in 64-bit words.
CELLS_PER_OCCUPANCY_WORD = 64
BYTES_PER_OCCUPANCY_WORD = 8
#: a lane of a gc_pack: the triangle's 3 x 3 doubles and its int32 face index.
BYTES_PER_REFERENCE = 72 + 4
#: gc_node: one per (sub)grid, the top level included.
BYTES_PER_NODE = 120

# --- ratio mode ------------------------------------------------------------------------
#: T_sub assumed with ``ratio`` alone (and when a calibration has no T_sub), in units of
#: T_step.  Estimate from the kernel's walk(): entering a subgrid repeats the per-axis
#: DDA set-up (entry cell, t_next, dt for 3 axes), about the work of two cell steps.
RATIO_MODE_T_SUB_IN_T_STEP = 2.0
#: T_setup assumed with ``ratio`` alone when a *relative* cost matters (the depth rule's
#: gain, :data:`DEEPEN_MIN_GAIN_RATIO_MODE`), in units of T_step: the reference calibration's
#: 58.8 ns / 22.1 ns (docs/calibration.md).  Costs reported in ratio mode keep T_setup = 0.
RATIO_MODE_T_SETUP_IN_T_STEP = 2.66

# --- nested plans ---------------------------------------------------------------------------
#: Nested plans (L >= 2) come from :func:`models.nested.nested_counts` (Crofton composition
#: over the structure built from the real triangles, analytic leaves), screened over a few
#: per-axis scales of the talk's L-level closed form for the top resolution (a walk from
#: the closed form towards cheaper neighbours, stopping at the first dearer one).
#: ``levels=auto`` stops at the first depth that does not beat the one above it.
#: A deeper grid is chosen only when its predicted cost per ray is at least this fraction
#: below the shallower one's: a small predicted gain is not evidence.  Four
#: ``calibrate compare`` runs of 2026-12-02 (night; T_mem, T_visit, a ray's first cell
#: whole) put the predicted gain of a second level at 6.3-6.9% on cylinder19996 and
#: armadillo (measured: 3.7-25.4% and -0.4-8.2%, the two-level grid faster in 7 of 8),
#: -7.7% to -8.5% on the bunny (measured -10% to -17%) and -16% or less on every other
#: scene; 3% lies in that gap, nearer the positive side, since a second level the model
#: overrates costs little (docs/compare.md, "The depth rule, again").  Earlier: 20% when
#: T_sub was held at a third of its in-context value, 10% when the two scans' predicted
#: gains were 12-13%.
DEEPEN_MIN_GAIN = 0.03
#: A plan holding more than this many times the largest grid the calibration timed gets
#: a note: its cost is extrapolated (measured here: grids past 64 MB cost 1.5-2.7 times
#: what the one-level memory term says; docs/compare.md).
EXTRAPOLATION_FACTOR = 2.0
#: The same with ``ratio`` alone, where T_setup and T_sub are assumed (RATIO_MODE_*), not
#: measured: the wider margin that fixed the room and the over-deep sphere and cylinder1996
#: plans in ratio mode (docs/compare.md).
DEEPEN_MIN_GAIN_RATIO_MODE = 0.20
#: (:func:`models.nested.optimal_nested`'s nlopt search is not used: with exact overlap it
#: takes about 20 s on 40k triangles.)
#: Up to this many triangles the plan uses exact triangle/cell overlap (the kernel's
#: default insertion) and SCREEN_AXIS_SCALES; above it, bounding-box overlap (conservative:
#: more references than the kernel stores) and SCREEN_AXIS_SCALES_LARGE, to bound the time.
NESTED_EXACT_MAX_TRIANGLES = 100_000
#: Per-axis scales of the talk's L-level top resolution screened (2^(j/2), j = -2..2) ...
SCREEN_AXIS_SCALES = tuple(2.0 ** (j / 2.0) for j in range(-2, 3))
#: ... and above NESTED_EXACT_MAX_TRIANGLES (one evaluation: about 1 s for L = 2 and
#: 3 s for L = 3 on 1M triangles).
SCREEN_AXIS_SCALES_LARGE = (1.0,)

# --- simulated fidelity ----------------------------------------------------------------
#: Rays traced per resolution (common random numbers: the same rays at every resolution).
SIM_RAYS = 4096
#: Per-axis scale factors of the analytic optimum that are built and counted
#: (2^(j/2), j = -2..2: a factor 8 in cells each way; the builds at the large end dominate).
SIM_AXIS_SCALES = tuple(2.0 ** (j / 2.0) for j in range(-2, 3))
#: Resolution of the fitted curves' minimisation over the scale (points on a log grid).
SIM_SEARCH_POINTS = 256
#: Seed of the simulated fidelity's rays (a prediction is deterministic).
SIM_SEED = 0
#: Above this many cells a simulated candidate is skipped (build memory and time).
SIM_MAX_CELLS = 2 ** 24

# --- the memory effect (models/memory.py) --------------------------------------------
#: Per-axis scales of the optimum without them searched when a calibration's T_mem or T_visit
#: makes the memory effect or the occupied cells matter (2^(j/8), j = -16..16: 1/4x to 4x per
#: axis, 64x in cells each way).
SEARCH_SCALES = tuple(2.0 ** (j / 8.0) for j in range(-16, 17))

# --- cell shape (_axis_search) -----------------------------------------------------------
#: The one-level plan's cells per axis are searched each on its own (nlopt BOBYQA over the
#: logarithms of the three resolutions), from the plan with cells as near cubes as the box
#: allows, at most this factor more per axis, and down to one cell (a bound below the start
#: kept `cylinder19996` at 7-8 cells along its axis where the model's cheapest has 2-3; the
#: fastest grids measured on its sweeps have 2-5).
AXIS_SEARCH_SPAN = 16.0
#: Cells longer along one axis are probed first, that axis's cells divided by each of these
#: (nine evaluations); the search starts again from the cheapest probe when it beats the
#: start, and may go down to the largest factor along an axis.  The model's cost of a long
#: cylinder has two valleys: near-cubic cells, and cells a few times longer along the axis
#: than across, whose references the rays that stop on the wall read from a small part of
#: the grid (`cylinder19996`: 96x96x12 against 106x106x170, docs/calibration.md, "What rays
#: read of a big grid"); the search from the near-cubic plan alone stays in the first.
AXIS_LONG_CELLS = (4.0, 16.0, 64.0)
#: Evaluations of the model's cost the search may spend (about 0.15 ms each).
AXIS_SEARCH_EVALS = 60
#: The shaped plan is taken only when the model prices it at least this much below the
#: near-cubic one: with a default calibration the scans' and soups' shaped optima are 0.0-0.4%
#: cheaper in the model (four of them timed: within 2% of the near-cubic plan either way),
#: the cylinders' 1.1-12.6% (timed 2.5-31% faster).
AXIS_MIN_GAIN = 0.01
#: Where the cost is flat between two axes (a round cylinder's x and y) the search stops
#: anywhere along the flat: a pair of axes is given equal cells (their geometric mean) when
#: that costs at most this fraction more in the model.
AXIS_EQUAL_CELLS_TOLERANCE = 1e-3

# --- where rays stop (models.effects.termination_fraction) ---------------------------------
#: Isotropic lines traced through the real mesh to measure where rays stop: the traversed
#: fraction's standard error is below 0.01 with 4,096 (each ray's share lies in [0, 1]).
TERMINATION_RAYS = 4096
#: Their seed (a prediction is deterministic).
TERMINATION_SEED = 0
#: Cells per triangle of the grid they are traced through (the first hits do not depend
#: on it; a coarse grid keeps the build small next to the mesh) ...
TERMINATION_CELLS_PER_TRIANGLE = 0.25
#: ... halved while the grid's expected references (models.general.expected_refs) exceed
#: this many: long triangles cross many cells (cylinder19996 at a quarter cell per
#: triangle: 1.0 M references, 76 MB, 116 ms; a 200,000-triangle cylinder would take 22 M),
#: so the sample's memory stays below about 160 MB.  Fewer cells make the trace dearer
#: instead (cylinder19996 in 5 cells: 112 ms, nearly all of it tracing).
TERMINATION_MAX_REFS = 2 ** 21
#: Above this many triangles the fraction is the approximation, not sampled: the grid the
#: lines are traced through costs about 0.1 ms per 1,000 triangles to build whatever its
#: resolution or insertion (31 ms at 10^5, 121 ms at 10^6 here; the trace 3-12 ms), against
#: the analytic prediction's goal of 50 ms for a million triangles.
TERMINATION_SAMPLE_MAX_TRIANGLES = 200_000
#: Per-axis factors on the sample's grid of the other grids whose occupied cells it counts
#: (how a mesh's sheets share cells changes with the cell: models.general.occupancy_scale);
#: a grid whose expected references exceed TERMINATION_MAX_REFS is left out.
OCCUPANCY_AXIS_SCALES = (0.5, 2.0 ** -0.5, 2.0 ** 0.5)
#: Per-axis factors on the sample's grid of the finer grids whose changes of occupancy it also
#: counts (models.general.occupancy_changes): a small mesh's plans have many cells a triangle
#: (`cylinder196` 11x11x23, 14 a triangle, against the sample's 0.25), where its walks change
#: occupancy (0.78 a ray there, none in every grid up to 3x3x16); left out past
#: TERMINATION_MAX_REFS as above, or past CHANGES_MAX_CELLS cells (a big mesh's plans have
#: fewer cells a triangle than the sample's grid at twice its cells an axis).  Their occupied
#: cells are kept too (models.general.occupancy_scale): a flat mesh's sample grids are one cell
#: thick and more than half occupied, which says nothing of how its sheets share cells, and its
#: plans lie among these (the CAD tray: sample 50x1x50, its grids three to five cells thick
#: counted 15-23% too few occupied cells by the even spread, now within 8%; two cells thick,
#: more than half occupied, 20% too few against 31%; docs/compare.md, "The finer grids'
#: occupied cells").
CHANGES_AXIS_SCALES = (2.0, 4.0)
CHANGES_MAX_CELLS = 2 ** 18

_STATS_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_SAMPLED_STATS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


# ---------------------------------------------------------------------------------------
# constants
# ---------------------------------------------------------------------------------------

#: :attr:`Constants.line_weights` of constants not read from a calibration file.
NO_LINE_WEIGHTS = "not from a calibration file"


class Constants:
    """Medians and posterior samples of the hardware constants.

    Attributes: ``t_setup, t_step, t_int, t_sub, t_mem, t_visit, t_hit`` (floats, medians) and
    ``samples`` (dict name -> (S,) float64, same names without ``_ns``);
    ``units`` is ``"ns"`` or ``"T_step"`` (ratio mode); ``notes`` lists assumptions;
    ``fitted_on`` is the ray set the constants were fitted on alone, or None (all of them);
    ``cache_bytes`` is the cache T_mem was measured against (None without a memory term);
    ``largest_grid_bytes`` the largest grid the calibration timed (None when unknown);
    ``line_weights`` the line weights a calibration file recorded for its T_mem (a mapping, or
    None when it does not say), NO_LINE_WEIGHTS for constants not read from a file.
    """

    def __init__(self, t_setup, t_step, t_int, t_sub, samples, units, notes, fitted_on=None, t_mem=0.0,
                 cache_bytes=None, largest_grid_bytes=None, t_visit=0.0, t_hit=0.0, line_weights=NO_LINE_WEIGHTS):
        self.t_setup, self.t_step, self.t_int, self.t_sub = (float(t_setup), float(t_step), float(t_int),
                                                             float(t_sub))
        self.t_mem = float(t_mem)
        self.t_visit = float(t_visit)
        self.t_hit = float(t_hit)
        self.cache_bytes = None if cache_bytes is None else int(cache_bytes)
        self.largest_grid_bytes = None if largest_grid_bytes is None else int(largest_grid_bytes)
        self.samples = samples
        self.units = units
        self.notes = notes
        self.fitted_on = fitted_on
        self.line_weights = line_weights

    @property
    def ratio(self) -> float:
        return self.t_int / self.t_step

    @property
    def has_memory(self) -> bool:
        """The memory effect's term is in the cost (a calibration fitted T_mem)."""
        return self.t_mem > 0 and self.cache_bytes is not None

    def lines(self, steps, tests, memory_bytes, visits=0.0) -> float:
        """Cache lines per ray fetched from beyond the cache (models/memory.py; ``visits``: the
        occupied cells entered and changes of occupancy, what T_visit prices); 0 without T_mem."""
        if not self.has_memory:
            return 0.0
        return float(lines_beyond_cache(steps, tests, memory_bytes, self.cache_bytes, visits))

    @property
    def has_visits(self) -> bool:
        """The occupied-cell term is in the cost (a calibration fitted T_visit)."""
        return self.t_visit > 0

    def cost_samples(self, steps, tests, subgrids=0.0, memory_bytes=0.0, visits=0.0, hits=0.0) -> np.ndarray:
        """(S,) predicted cost per ray for fixed counts (grid bytes, occupied cells entered, the
        share of rays that hit), one per posterior sample."""
        s = self.samples
        out = s["t_setup"] + s["t_step"] * steps + s["t_int"] * tests + s["t_sub"] * subgrids
        if visits > 0:
            out = out + s["t_visit"] * visits
        if hits > 0:
            out = out + s["t_hit"] * hits
        lines = self.lines(steps, tests, memory_bytes, visits)
        return out + s["t_mem"] * lines if lines > 0 else out

    def cost(self, steps, tests, subgrids=0.0, memory_bytes=0.0, visits=0.0, hits=0.0) -> float:
        """Predicted cost per ray under the median constants (the memory term needs the grid's
        bytes, the occupied-cell term the occupied cells a ray enters, the hit term the share of
        rays that hit)."""
        return (self.t_setup + self.t_step * steps + self.t_int * tests + self.t_sub * subgrids
                + self.t_mem * self.lines(steps, tests, memory_bytes, visits) + self.t_visit * visits
                + self.t_hit * hits)


def _median_of(value, name):
    if isinstance(value, dict):
        value = value.get("median")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"constant {name} must be a number (ns), got {value!r}") from None
    if not math.isfinite(x) or x < 0:
        raise ValueError(f"constant {name} must be finite and >= 0 ns, got {value!r}")
    return x


def resolve_constants(constants=None, samples=None, ratio=None) -> Constants:
    """Constants from a calibration's medians/samples or from a ratio alone.

    constants : mapping ``t_setup_ns, t_step_ns, t_int_ns[, t_sub_ns, t_mem_ns, t_visit_ns]`` -> ns (a
        float or a ``{"median": ...}`` block, e.g. a calibration's ``constants``); an optional
        ``fitted_on`` names the ray set they were fitted on alone (a note says so), and
        ``cache_bytes`` the cache T_mem was measured against (required with T_mem), and
        ``largest_grid_bytes`` the largest grid the calibration timed (a plan beyond
        :data:`EXTRAPOLATION_FACTOR` times it gets a note), and ``line_weights`` the cache lines
        a step, an occupied cell and a test were charged when its T_mem was fitted
        (:func:`calibrate.calfile.line_weights_of`; None: the file does not say): other than
        today's (:func:`models.memory.line_weights`), a note says to refit.
    samples : mapping of the same names -> (S,) posterior samples (ns), e.g.
        :func:`calibrate.calfile.samples_by_name`; medians default to theirs.
    ratio : ``T_int / T_step`` > 0 (no calibration; costs in units of T_step).
    """
    notes = []
    if ratio is not None:
        if constants is not None or samples is not None:
            raise ValueError("give either a calibration or a ratio, not both")
        try:
            r = float(ratio)
        except (TypeError, ValueError):
            raise ValueError(f"ratio must be a number (T_int / T_step), got {ratio!r}") from None
        if not (math.isfinite(r) and r > 0):
            raise ValueError(f"ratio must be a finite number > 0 (T_int / T_step), got {ratio!r}")
        one = lambda x: np.array([float(x)])  # noqa: E731
        notes.append(f"ratio mode: T_setup = 0, T_step = 1, T_int = {r:g}, T_sub = "
                     f"{RATIO_MODE_T_SUB_IN_T_STEP:g} (assumed); costs are in units of T_step")
        return Constants(0.0, 1.0, r, RATIO_MODE_T_SUB_IN_T_STEP,
                         dict(t_setup=one(0.0), t_step=one(1.0), t_int=one(r), t_sub=one(RATIO_MODE_T_SUB_IN_T_STEP),
                              t_mem=one(0.0), t_visit=one(0.0), t_hit=one(0.0)),
                         "T_step", notes)
    if constants is None and samples is None:
        raise ValueError("no calibration: run `calibrate run` first, pass a calibration file, or give a ratio "
                         "T_int/T_step")
    names = ("t_setup", "t_step", "t_int", "t_sub", "t_mem", "t_visit", "t_hit")
    arrays = {}
    if samples is not None:
        for n in names:
            a = samples.get(f"{n}_ns")
            if a is None:
                continue
            a = np.asarray(a, dtype=np.float64).reshape(-1)
            if a.size == 0 or not np.all(np.isfinite(a)) or np.any(a < 0):
                raise ValueError(f"samples of {n}_ns must be a non-empty array of finite ns >= 0")
            arrays[n] = a
        sizes = {a.size for a in arrays.values()}
        if len(sizes) > 1:
            raise ValueError(f"posterior sample columns differ in length: {sorted(sizes)}")
    med = {}
    for n in names:
        v = None if constants is None else constants.get(f"{n}_ns")
        if v is not None:
            med[n] = _median_of(v, f"{n}_ns")
        elif n in arrays:
            med[n] = float(np.median(arrays[n]))
    for n in ("t_setup", "t_step", "t_int"):
        if n not in med:
            raise ValueError(f"the calibration lacks {n}_ns")
    if not (med["t_step"] > 0 and med["t_int"] > 0):
        raise ValueError("t_step_ns and t_int_ns must be > 0")
    fitted_on = None if constants is None else constants.get("fitted_on")
    if fitted_on is not None and not (isinstance(fitted_on, str) and fitted_on):
        raise ValueError(f"fitted_on must name a ray set, got {fitted_on!r}")
    if fitted_on is not None:
        notes.append(f"constants fitted on the calibration's {fitted_on} rays alone")
    if "t_sub" not in med:
        med["t_sub"] = RATIO_MODE_T_SUB_IN_T_STEP * med["t_step"]
        notes.append(f"the calibration has no T_sub: assumed {RATIO_MODE_T_SUB_IN_T_STEP:g} x T_step")
    cache = None if constants is None else constants.get("cache_bytes")
    recorded = NO_LINE_WEIGHTS if constants is None else constants.get("line_weights", NO_LINE_WEIGHTS)
    if "t_mem" in med and med["t_mem"] > 0:
        try:
            cache = int(cache)
        except (TypeError, ValueError):
            raise ValueError(f"a calibration with T_mem needs the cache size it was measured against "
                             f"(cache_bytes), got {cache!r}") from None
        if cache <= 0:
            raise ValueError(f"cache_bytes must be > 0, got {cache}")
        notes.append(f"memory effect: T_mem = {med['t_mem']:.3g} ns per cache line fetched from beyond the "
                     f"host's {cache / 2 ** 20:.3g} MiB cache")
        if recorded != NO_LINE_WEIGHTS and recorded != line_weights():
            notes.append(f"the calibration's T_mem was fitted with other cache lines a step, an occupied cell "
                         f"and a test ({_weights_text(recorded)}) than today's "
                         f"({_weights_text(line_weights())}): `calibrate fit FILE` refits it from the file's "
                         "measurements")
    else:
        med["t_mem"] = 0.0
        cache = None
    if med.get("t_visit", 0.0) > 0:
        notes.append(f"occupied cells: T_visit = {med['t_visit']:.3g} ns per occupied cell a ray enters")
    else:
        med["t_visit"] = 0.0
    if med.get("t_hit", 0.0) > 0:
        notes.append(f"hits: T_hit = {med['t_hit']:.3g} ns per ray that finds a hit")
    else:
        med["t_hit"] = 0.0
    size = next(iter(arrays.values())).size if arrays else 1
    for n in names:
        if n not in arrays:
            arrays[n] = np.full(size, med[n])
    if np.any(arrays["t_step"] <= 0) or np.any(arrays["t_int"] <= 0):
        raise ValueError("posterior samples of t_step_ns and t_int_ns must be > 0")
    largest = None if constants is None else constants.get("largest_grid_bytes")
    if largest is not None:
        try:
            largest = int(largest)
        except (TypeError, ValueError):
            raise ValueError(f"largest_grid_bytes must be a whole number of bytes, got {largest!r}") from None
        if largest <= 0:
            raise ValueError(f"largest_grid_bytes must be > 0, got {largest}")
    return Constants(med["t_setup"], med["t_step"], med["t_int"], med["t_sub"], arrays, "ns", notes,
                     fitted_on=fitted_on, t_mem=med["t_mem"], cache_bytes=cache, largest_grid_bytes=largest,
                     t_visit=med["t_visit"], t_hit=med["t_hit"], line_weights=recorded)


def extrapolation_note(k: Constants, memory_bytes) -> str | None:
    """A note when a grid of ``memory_bytes`` is more than :data:`EXTRAPOLATION_FACTOR`
    times the largest grid the calibration timed (None otherwise, or when unknown)."""
    if k.largest_grid_bytes is None or not memory_bytes > EXTRAPOLATION_FACTOR * k.largest_grid_bytes:
        return None
    return (f"extrapolated: the planned grid holds {memory_bytes / 1e6:,.0f} MB, "
            f"{memory_bytes / k.largest_grid_bytes:.0f} times the largest grid the calibration timed "
            f"({k.largest_grid_bytes / 1e6:.0f} MB); the memory term knows one cache level, and grids past "
            "the caches further out cost more than it says (docs/compare.md), so the depth and resolution "
            "may be off")


def load_calibration_constants(path, rays: str | None = None) -> Constants:
    """Constants of a calibration file (medians and posterior samples); UserError naming the file.

    rays : the ray set predicted for; a calibration that fitted that set alone
        (``by_rays``) gives its constants, otherwise the pooled ones.
    """
    from . import calfile

    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such calibration file; run `calibrate run` to create one, or pass --ratio R")
    cal = calfile.load(p)
    block, fitted_on = calfile.fit_for_rays(cal, rays)
    constants = dict(block["constants"], fitted_on=fitted_on) if fitted_on else dict(block["constants"])
    cache = calfile.cache_bytes_of(cal)
    if cache is not None:
        constants["cache_bytes"] = cache
    largest = calfile.largest_grid_bytes(cal)
    if largest is not None:
        constants["largest_grid_bytes"] = largest
    constants["line_weights"] = calfile.line_weights_of(cal)
    return resolve_constants(constants=constants, samples=calfile.samples_by_name(block))


def _weights_text(weights) -> str:
    """A calibration's line weights (:func:`calibrate.calfile.line_weights_of`) as a note says them."""
    if weights is None:
        return "unrecorded: before 2026-12-07 a line a step, none an occupied cell, 72/64 a test"
    show = lambda x: f"{x:g}" if isinstance(x, (int, float)) else "?"  # noqa: E731
    return f"{show(weights.get('step'))} a step, {show(weights.get('visit'))} an occupied cell, " \
           f"{show(weights.get('test'))} a test"


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------

def scene_statistics(scene: Scene):
    """SceneStats of a scene with where rays stop on it sampled (computed once per scene object).

    ``scene.stats`` (one pass over the mesh, in C) with ``termination`` =
    :func:`sample_termination`: the analytic model's counts then scale by the traversed
    fraction measured on the real mesh instead of its approximation (above
    TERMINATION_SAMPLE_MAX_TRIANGLES triangles, the approximation), and ``triangles`` =
    :func:`models.stats.triangle_sample`, what the memory term weighs a uniform grid's
    references by (:func:`models.memory.read_bytes`).
    """
    cached = _SAMPLED_STATS.get(scene)
    if cached is None:
        cached = replace(scene.stats, triangles=triangle_sample(scene.vertices, scene.faces))
        if scene.n_triangles <= TERMINATION_SAMPLE_MAX_TRIANGLES:
            cached = replace(cached, termination=sample_termination(scene))
        _SAMPLED_STATS[scene] = cached
    return cached


def termination_grid_resolution(scene: Scene) -> tuple[int, int, int]:
    """The grid :func:`sample_termination` traces through: TERMINATION_CELLS_PER_TRIANGLE cells
    per triangle, halved while the expected references exceed TERMINATION_MAX_REFS (down to
    one cell)."""
    extent = scene.box_hi - scene.box_lo
    cells = max(1.0, TERMINATION_CELLS_PER_TRIANGLE * scene.n_triangles)
    res = resolution_for_cells(cells, extent)
    while cells > 1.0 and expected_refs(scene.stats, res) > TERMINATION_MAX_REFS:
        cells = max(1.0, cells / 2.0)
        res = resolution_for_cells(cells, extent)
    return res


def sample_termination(scene: Scene, rays: int = TERMINATION_RAYS, seed: int = TERMINATION_SEED):
    """Where isotropic lines through the grid box stop on the mesh: a :class:`models.stats.TerminationSample`.

    ``rays`` lines of :func:`calibrate.rays.isotropic` (the model's ray distribution) are
    traced through the uniform grid of :func:`termination_grid_resolution`; the fraction is
    the box chord covered before the first hit (all of it on a miss), summed over the rays,
    over the chords summed: what scales the expected steps of the count model, whose cells
    along a line are in proportion to its length.  The sample also keeps that grid's
    occupied cells, which :func:`models.general.occupied_cells` is scaled to, and the
    occupied cells the rays enter before their hit (the instrumented kernel), which
    :func:`models.general.surface_visits` takes a surface's count from, and the occupied
    cells of grids at OCCUPANCY_AXIS_SCALES of its cells per axis, between which
    :func:`models.general.occupancy_scale` interpolates (40-60 ms more on the 70,000- to
    86,000-triangle scans, against 9 ms for the one grid), and the changes of occupancy per
    ray on each of those grids and on the finer ones of CHANGES_AXIS_SCALES
    (:func:`models.general.occupancy_changes`; 40-100 ms more on the scans), whose occupied
    cells join the others'.
    """
    from . import rays as _rays_mod

    lo, hi = scene.box_lo, scene.box_hi
    o, d = _rays_mod.isotropic(lo, hi, int(rays), seed)
    t_in, t_out = _rays_mod.box_chords(o, d, lo, hi)
    res = tuple(int(x) for x in termination_grid_resolution(scene))
    grid = Grid.uniform(scene, res)
    t_hit, _ = grid.intersect(o, d)
    chord = np.maximum(t_out - t_in, 0.0)
    covered = np.clip(np.minimum(t_hit, t_out) - t_in, 0.0, chord)
    total = float(chord.sum())
    fraction = min(1.0, float(covered.sum()) / total) if total > 0 else 1.0
    occupied = _occupied_cells(grid)
    _, _, _, n_visits, n_changes = grid.count(o, d, visits=True, changes=True)
    visits = float(n_visits.mean())
    changes = [(res, float(n_changes.mean()))]
    del grid
    occupancy = []
    for s in OCCUPANCY_AXIS_SCALES:
        other = _scaled(res, s)
        if other == res or expected_refs(scene.stats, other) > TERMINATION_MAX_REFS:
            continue
        g = Grid.uniform(scene, other)
        occupancy.append((other, _occupied_cells(g)))
        changes.append((other, float(g.count(o, d, changes=True)[-1].mean())))
        del g
    for s in CHANGES_AXIS_SCALES:
        other = _scaled(res, s)
        if (other == res or other[0] * other[1] * other[2] > CHANGES_MAX_CELLS
                or expected_refs(scene.stats, other) > TERMINATION_MAX_REFS):
            continue
        g = Grid.uniform(scene, other)
        occupancy.append((other, _occupied_cells(g)))
        changes.append((other, float(g.count(o, d, changes=True)[-1].mean())))
        del g
    return TerminationSample(fraction=fraction, p_hit=float(np.mean(np.isfinite(t_hit))), rays=int(rays),
                             resolution=res, occupied=occupied, visits=visits, occupancy=tuple(occupancy),
                             changes=tuple(changes))


def _occupied_cells(grid: Grid) -> int:
    """The cells of a uniform grid that hold a triangle."""
    return int(grid.info["n_cells"]) - int(grid.info["n_empty_cells"])


def _geometry(scene: Scene):
    """(per-triangle geometry, corners (F, 3, 3) or None) for the nested model, cached per scene.

    Corners (exact overlap) only up to NESTED_EXACT_MAX_TRIANGLES triangles.
    """
    cached = _STATS_CACHE.get(scene)
    if cached is None:
        geom = triangle_geometry(scene.vertices, scene.faces)
        corners = scene.vertices[scene.faces] if scene.n_triangles <= NESTED_EXACT_MAX_TRIANGLES else None
        cached = (geom, corners)
        _STATS_CACHE[scene] = cached
    return cached


def _res_list(res):
    return [int(x) for x in res]


def _memory_bytes(cells, refs, nodes) -> int:
    """Bytes of a built grid (kernels/grid.c, gc_grid_get_info), less the fixed gc_grid header:
    the cell records, the occupancy bitmap, the references' triangle copies and the nodes."""
    words = math.ceil(cells / CELLS_PER_OCCUPANCY_WORD)
    return int(BYTES_PER_CELL * cells + BYTES_PER_OCCUPANCY_WORD * words + BYTES_PER_REFERENCE * refs
               + BYTES_PER_NODE * nodes)


def _interval(x: np.ndarray) -> dict:
    iv = summarise(x)
    return dict(median=iv.median, ci95=[iv.ci95[0], iv.ci95[1]])


def _check_choice(name, value, choices):
    if str(value) not in choices:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")
    return str(value)


def _level_dicts_uniform(stats, res, refs):
    cells = res[0] * res[1] * res[2]
    return [dict(level=1, resolution=_res_list(res), grids=1, cells=int(cells), references=float(refs),
                 memory_bytes=_memory_bytes(cells, refs, 1))]


# ---------------------------------------------------------------------------------------
# paper fidelity
# ---------------------------------------------------------------------------------------

def paper_plan(stats, cls, k: Constants, levels):
    """The talk's closed forms and the talk's cost model (pure arithmetic on the statistics).

    stats : SceneStats; cls : scene class ("compact" | "long-skinny" | "mixed"; mixed
    uses the points law); k : :class:`Constants`; levels : "auto" | "1" | "2" | "3".
    Cells per level from :func:`models.portable.paper_level_cells` (the portable form of
    :func:`models.closed_forms.l_level_cells`, so ``calibrate export``'s header gives the
    same resolutions: :func:`models.portable.paper_resolutions`) with the scene's
    ``k = E2 / V^(2/3)``; counts per ray from the talk's cube model with ``m_l = M_l^(1/3)``:
    ``steps = sum_l k^(l-1) m_l``, ``subgrids = sum_{l>=2} k^(l-1)``, leaf tests
    ``k^(L-1) n_L / m_L^2`` (points) or ``/ m_L`` (lines), ``n_{l+1} = n_l / (k m_l^2)``
    (points) or ``n_l / (k m_l)`` (lines).

    Returns (plan, effects): plan is a dict with ``levels`` (list of dicts, top first),
    ``steps``, ``tests``, ``subgrids`` (per ray), ``memory_bytes``; effects a list of dicts.
    """
    kind = "lines" if cls == "long-skinny" else "points"
    kk = paper_k(stats.k)
    n = float(stats.n_triangles)
    r = k.ratio

    def plan(L):
        cells = paper_level_cells(n, r, L, kk, kind=kind)
        m = [float(c) ** (1.0 / 3.0) for c in cells]
        n_l = n
        steps = subgrids = 0.0
        for depth in range(L):
            entered = kk ** depth
            steps += entered * m[depth]
            if depth > 0:
                subgrids += entered
            if depth < L - 1:
                n_l = n_l / (kk * m[depth] ** 2) if kind == "points" else n_l / (kk * m[depth])
        tests = kk ** (L - 1) * (n_l / m[-1] ** 2 if kind == "points" else n_l / m[-1])
        out_levels = []
        extent = np.asarray(stats.extent, dtype=np.float64)
        grids = 1
        for depth, c in enumerate(cells):
            res = cells_to_resolution(c, extent)
            nc = res[0] * res[1] * res[2]
            out_levels.append(dict(level=depth + 1, resolution=_res_list(res), grids=int(round(grids)),
                                   cells=int(round(grids * nc))))
            # occupied cells of this level hold the next level's grids (the talk's k m^2 per grid)
            grids = grids * min(kk * float(c) ** (2.0 / 3.0), nc)
            extent = extent / np.asarray(res, dtype=np.float64)
        refs = n  # the talk's points: one reference per primitive
        total_cells = sum(lv["cells"] for lv in out_levels)
        nodes = sum(lv["grids"] for lv in out_levels)
        for lv in out_levels:
            leaf = lv["level"] == L
            lv["references"] = float(refs) if leaf else 0.0
            lv["memory_bytes"] = _memory_bytes(lv["cells"], refs if leaf else 0, lv["grids"])
        return dict(levels=out_levels, steps=steps, tests=tests, subgrids=subgrids,
                    memory_bytes=_memory_bytes(total_cells, refs, nodes), kind=kind)

    if levels == "auto":
        plans = [plan(L) for L in range(1, MAX_LEVELS + 1)]
        best = min(plans, key=lambda p: k.cost(p["steps"], p["tests"], p["subgrids"]))
    else:
        best = plan(int(levels))
    law = {"points": "M = 2 N r (points)", "lines": "M = (N r)^1.5 (lines)"}[kind]
    effects = [dict(name="paper", used=True, change=0.0,
                    reason=f"the talk's closed form for a {cls} scene: {law}" +
                           (f", {len(best['levels'])}-level recursion with k = {kk:.3g}" if len(best["levels"]) > 1
                            else "") + "; rays never terminate, no edge or area terms")]
    return best, effects


# ---------------------------------------------------------------------------------------
# analytic fidelity
# ---------------------------------------------------------------------------------------

def _effect_dicts(sel):
    return [dict(name=e.name, used=bool(e.used), change=float(e.change), reason=e.reason) for e in sel.effects]


def _priced_visits(stats, res, terms) -> float:
    """What T_visit prices per ray in a uniform grid at ``res``: the occupied cells entered
    (:func:`models.general.visits_per_ray`) and the changes of occupancy
    (:func:`models.general.occupancy_changes`)."""
    return visits_per_ray(stats, res, terms=terms) + occupancy_changes(stats, res)


def _uniform_counts(stats, res, k: Constants, terms):
    """(steps, tests, references, memory bytes, visits, charged bytes) of a uniform grid under
    the general model (the tests of rays that stop: :func:`models.general.stopped_tests_per_ray`);
    the visits are what T_visit prices (:func:`_priced_visits`); the charged bytes are what the
    memory term prices (:func:`charged_bytes`), the memory bytes the grid's."""
    _, steps, _ = predict_uniform(stats, res, k.t_setup, k.t_step, k.t_int, overlap="exact", terms=terms)
    tests = stopped_tests_per_ray(stats, res, terms=terms)
    refs = expected_refs(stats, res, overlap="exact")
    mem = _memory_bytes(res[0] * res[1] * res[2], refs, 1)
    return steps, tests, refs, mem, _priced_visits(stats, res, terms), charged_bytes(stats, res, k, steps, tests, mem)


def charged_bytes(stats, res, k: Constants, steps, tests, memory_bytes) -> float:
    """The bytes of a uniform grid at ``res`` the memory term charges (``Constants.lines``): the
    grid's ``memory_bytes`` weighed by where rays read it, with the scene's triangle sample
    (:func:`models.memory.read_bytes`); the grid's bytes without a memory term or a sample."""
    if not k.has_memory:
        return float(memory_bytes)
    return read_bytes(stats.triangles, stats.extent, res, steps, tests, memory_bytes, k.cache_bytes,
                      BYTES_PER_REFERENCE, BITMAP_BYTES_PER_CELL)


def _term_effect(name: str, share: float, head: str, what: str) -> dict:
    """An optional term's effect entry: *used*, i.e. it moves the resolution, when its share of the
    predicted time is more than EFFECT_TOLERANCE; ``what`` says how it moved it."""
    used = share > EFFECT_TOLERANCE
    return dict(name=name, used=bool(used), change=float(share), reason=(
        f"{head}, {100 * share:.1f}% of the predicted time "
        + (f"({what})" if used else f"(below the {100 * EFFECT_TOLERANCE:g}% tolerance: the resolution "
                                    "ignores it)")))


def _visits_effect(k: Constants, cost: float, visits: float, what: str) -> dict:
    """The occupied-cell effect's entry for a plan of predicted ``cost`` (``change``: the share of
    it the term is)."""
    share = k.t_visit * visits / cost if cost > 0 else 0.0
    return _term_effect("occupied-cells", share, f"{visits:.3g} occupied cells entered and changes of occupancy "
                        "per ray (models.general.visits_per_ray, approximate, and occupancy_changes, sampled) at "
                        f"{k.t_visit:.3g} ns each", what)


def _memory_effect(k: Constants, steps, tests, memory_bytes, what: str, subgrids=0.0, visits=0.0,
                   charged=None) -> dict:
    """The memory effect's entry for a plan (``change``: the share of the predicted time its term
    is).  The term is in every predicted time of a calibration with T_mem; the effect is *used*
    when that share is more than EFFECT_TOLERANCE.  ``charged``: the bytes the term prices where
    they are not the grid's (:func:`charged_bytes`)."""
    priced = memory_bytes if charged is None else charged
    total = k.cost(steps, tests, subgrids, priced, visits)
    lines = k.lines(steps, tests, priced, visits)
    share = k.t_mem * lines / total if total > 0 else 0.0
    weighed = ("" if charged is None or abs(priced - memory_bytes) <= 1e-9 * memory_bytes else
               f", weighed by where rays read it as {priced / 2 ** 20:.3g} MiB (models.memory.read_bytes)")
    return _term_effect("memory", share, f"the grid's {memory_bytes / 2 ** 20:.3g} MiB{weighed} against the host's "
                        f"{k.cache_bytes / 2 ** 20:.3g} MiB cache: {lines:.3g} cache lines per ray from beyond it",
                        what)


def _surface_tests_effect(stats, k: Constants, res, terms, steps, tests, mem, visits) -> dict | None:
    """The entry of the tests counted in the occupied cells (:func:`models.general.stopped_tests_per_ray`)
    at the closed form's optimum ``res``, whose cubic counts the tests by the distance; None when
    rays never stop.  ``change``: the relative change of the predicted time the occupied cells'
    count makes; *used* (the resolution is searched) above EFFECT_TOLERANCE."""
    if terms.traversed_fraction >= 1.0 or terms.mailbox:
        return None
    _, _, by_distance = predict_uniform(stats, res, 0.0, 1.0, 1.0, overlap="exact", terms=terms)
    cost = k.cost(steps, tests, 0.0, mem, visits)
    change = abs(k.cost(steps, by_distance, 0.0, mem, visits) / cost - 1.0) if cost > 0 else 0.0
    used = change > EFFECT_TOLERANCE
    return dict(name="surface-tests", used=bool(used), change=float(change), reason=(
        f"tests counted in the occupied cells a ray enters before it stops (models.general.stopped_tests_per_ray): "
        f"{tests:.3g} per ray against {by_distance:.3g} by the distance it covers, {100 * change:.1f}% of the "
        "predicted time at the closed form's optimum "
        + ("(the resolution is the cheapest by them)" if used else
           f"(below the {100 * EFFECT_TOLERANCE:g}% tolerance: the resolution is the closed form's)")))


def _within_caps(res) -> bool:
    """Whether a resolution keeps to MAX_CELLS_PER_AXIS and MAX_TOTAL_CELLS."""
    return max(res) <= MAX_CELLS_PER_AXIS and res[0] * res[1] * res[2] <= MAX_TOTAL_CELLS


def _priced(stats, res, k: Constants, terms):
    """(the model's cost, :func:`_uniform_counts`) of a uniform grid at ``res``."""
    c = _uniform_counts(stats, res, k, terms)
    return k.cost(c[0], c[1], 0.0, c[5], c[4]), c


def _scaled_candidates(stats, k: Constants, terms, res) -> dict:
    """resolution -> :func:`_priced` of ``res`` scaled by each of SEARCH_SCALES (thin axes floor
    and ceiling, :func:`_scaled_with_thin_axes`), within the caps."""
    cands = {}
    for r in (q for sc in SEARCH_SCALES for q in _scaled_with_thin_axes(res, sc)):
        if r not in cands and _within_caps(r):
            cands[r] = _priced(stats, r, k, terms)
    return cands


def _axis_search(stats, k: Constants, terms, res, cost0):
    """The cheapest resolution under the model with each axis's cells searched on its own, from
    ``res`` (whose cost is ``cost0``): (resolution, its cost, evaluations).

    The near-cubic plans of the closed form and of the scaled search above fit a scene whose
    triangles run every way; a cylinder's walls are long along its axis, so each triangle there
    lies in every cell of a column of cubic cells, and cells longer along the axis hold the same
    triangles a ray meets with a fraction of the references (memory) and of the steps
    (`cylinder19996` at 96x96x12 cells: 0.9 M references and 226 ns a ray, against 5.7 M and
    960 ns at the near-cubic 96x96x474; docs/compare.md, "Cells shaped to the triangles").
    nlopt's BOBYQA minimises the model's cost over the logarithms of the three resolutions
    (down to one cell an axis, up to AXIS_SEARCH_SPAN times the start; AXIS_SEARCH_EVALS
    evaluations; the counts are continuous in the cell sizes), and again from the cheapest of
    the AXIS_LONG_CELLS probes (one axis's cells fewer) when that beats the first search; then the floors and ceilings of the result
    are priced and the cheapest kept, and where two axes' cells can be made equal for at most AXIS_EQUAL_CELLS_TOLERANCE
    more, they are (the search stops anywhere along a flat direction; a round cylinder gets
    square cells across)."""

    def cost(r):
        return _priced(stats, r, k, terms)[0]

    res = tuple(int(x) for x in res)
    x0 = np.log(np.asarray(res, dtype=np.float64))
    lo = np.zeros(3)  # down to one cell an axis
    hi = np.maximum(lo, np.minimum(math.log(MAX_CELLS_PER_AXIS), x0 + math.log(AXIS_SEARCH_SPAN)))
    evals = [0]

    def objective(x, grad):
        evals[0] += 1
        over = float(np.sum(x)) - math.log(MAX_TOTAL_CELLS)  # past the cap on cells: steeply dearer
        return cost(tuple(np.exp(x))) * (1.0 + 1e3 * max(over, 0.0) ** 2)

    def search(start):
        opt = nlopt.opt(nlopt.LN_BOBYQA, 3)
        opt.set_lower_bounds(lo)
        opt.set_upper_bounds(hi)
        opt.set_min_objective(objective)
        opt.set_maxeval(AXIS_SEARCH_EVALS)
        opt.set_xtol_rel(1e-3)
        opt.set_initial_step(math.log(2.0))
        try:
            x = opt.optimize(np.clip(start, lo, hi))
            return x, opt.last_optimum_value()
        except (nlopt.RoundoffLimited, RuntimeError):  # as models.nested's search: keep the start
            return start, objective(start, None)

    x, best_value = search(x0)
    probes = [np.maximum(lo, x0 - math.log(f) * np.eye(3)[i]) for f in AXIS_LONG_CELLS for i in range(3)]
    value, i_probe = min((objective(p, None), i) for i, p in enumerate(probes))
    if value < best_value:
        x_long, long_value = search(probes[i_probe])
        if long_value < best_value:
            x = x_long
    r = np.exp(x)
    cands = {tuple(max(1, int(v)) for v in c) for c in itertools.product(*[(math.floor(v), math.ceil(v)) for v in r])}
    cands = [c for c in cands if _within_caps(c)]
    if not cands:
        return res, cost0, evals[0]
    best_cost, best = min((cost(c), c) for c in cands)
    ext = np.asarray(stats.extent, dtype=np.float64)
    for i, j in ((0, 1), (1, 2), (0, 2)):
        cell = math.sqrt(ext[i] / best[i] * ext[j] / best[j])  # the pair's geometric mean
        if not cell > 0:
            continue
        eq = list(best)
        eq[i], eq[j] = (max(1, int(round(ext[a] / cell))) for a in (i, j))
        eq = tuple(eq)
        if eq != best and _within_caps(eq):
            c_eq = cost(eq)
            if c_eq <= best_cost * (1.0 + AXIS_EQUAL_CELLS_TOLERANCE):
                best, best_cost = eq, c_eq
    if best_cost >= cost0:
        return res, cost0, evals[0]
    return best, best_cost, evals[0]


def analytic_uniform_plan(stats, k: Constants, mailbox):
    """Single-level plan of the general model with the effects :func:`models.effects.select_effects` keeps.

    Rays terminate at the first hit (the kernel's behaviour), exact overlap (the kernel's
    default insertion).  With a calibration's T_mem or T_visit, when the memory effect's
    term (models/memory.py) or the occupied cells' (models.general.visits_per_ray) is more
    than EFFECT_TOLERANCE of the predicted time at the optimum, the resolution is the
    cheapest of SEARCH_SCALES around the optimum without them; so too when the tests counted
    in the occupied cells (:func:`models.general.stopped_tests_per_ray`) change the time at
    the closed form's optimum, which counts them by the distance, by more than that.  Then
    each axis's cells are searched on their own (:func:`_axis_search`), and the shaped
    resolution is taken when the model prices it at least AXIS_MIN_GAIN below (the
    "cell-shape" effect).
    Returns (plan, effects) like :func:`paper_plan`; plan also holds ``terms`` (the
    selected :class:`models.general.Terms`).
    """
    sel = select_effects(stats, k.t_setup, k.t_step, k.t_int, mailbox=mailbox, termination=True, overlap="exact",
                         levels=1)
    res = sel.resolution
    steps, tests, refs, mem, visits, charged = _uniform_counts(stats, res, k, sel.terms)
    effects = _effect_dicts(sel)
    candidates = None
    surface = _surface_tests_effect(stats, k, res, sel.terms, steps, tests, charged, visits)
    if surface is not None:
        effects.append(surface)
    if k.has_memory or k.has_visits or (surface is not None and surface["used"]):
        cands = _scaled_candidates(stats, k, sel.terms, res)
        best = min(cands, key=lambda r: cands[r][0])
        cost, c = cands[best]
        what = (f"resolution searched from 1/4x to 4x per axis of the optimum without it "
                f"{_fmt_res(res)}: {_fmt_res(best)}")
        new = []
        if k.has_memory:
            new.append(_memory_effect(k, c[0], c[1], c[3], what, visits=c[4], charged=c[5]))
        if k.has_visits:
            new.append(_visits_effect(k, cost, c[4], what))
        effects.extend(new)
        if surface is not None and surface["used"]:
            surface["reason"] = surface["reason"][:-1] + f"; {what})"
        if any(e["used"] for e in new) or (surface is not None and surface["used"]):
            res = best
            steps, tests, refs, mem, visits, charged = c
            candidates = [(r, cc[1]) for r, cc in cands.items()]
    cost_cubic = k.cost(steps, tests, 0.0, charged, visits)
    shaped, cost_shaped, evals = _axis_search(stats, k, sel.terms, res, cost_cubic)
    gain = 1.0 - cost_shaped / cost_cubic if cost_cubic > 0 else 0.0
    shape_used = shaped != tuple(int(x) for x in res) and gain >= AXIS_MIN_GAIN
    effects.append(dict(name="cell-shape", used=bool(shape_used), change=float(gain), reason=(
        f"each axis's cells searched on its own ({evals} evaluations): {_fmt_res(shaped)} is "
        f"{100 * gain:.1f}% cheaper in the model than {_fmt_res(res)} "
        + ("(taken: cells longer along the triangles' common direction)" if shape_used else
           f"(below the {100 * AXIS_MIN_GAIN:g}% the shape must gain: the cells stay near cubes)"))))
    if shape_used:
        res = shaped
        # the posterior's choice runs along the shape taken (not the closed form's cubes)
        shaped_cands = _scaled_candidates(stats, k, sel.terms, res)
        shaped_cands.setdefault(res, _priced(stats, res, k, sel.terms))
        steps, tests, refs, mem, visits, charged = shaped_cands[res][1]
        candidates = [(q, shaped_cands[q][1]) for q in sorted(shaped_cands)]
    plan = dict(levels=_level_dicts_uniform(stats, res, refs), steps=steps, tests=tests, subgrids=0.0,
                memory_bytes=mem, charged_bytes=charged, visits=visits, changes=occupancy_changes(stats, res),
                terms=sel.terms, selection=sel)
    if candidates is not None:
        plan["candidates"] = candidates
    return plan, effects


def _nested_plan(scene, stats, k: Constants, L):
    """An L-level structure from models.nested (counts without termination) and how it was found.

    Analytic-leaf counts at the talk's L-level closed form for the top resolution scaled
    per axis by ``SCREEN_AXIS_SCALES`` (or ``SCREEN_AXIS_SCALES_LARGE``); the cheapest is kept.
    Returns (NestedCounts, overlap, description).
    """
    geom, corners = _geometry(scene)
    overlap = "exact" if corners is not None else "bbox"
    scales = SCREEN_AXIS_SCALES if corners is not None else SCREEN_AXIS_SCALES_LARGE
    kk = max(float(stats.k), 1e-3)
    centre = cells_to_resolution(float(l_level_cells(stats.n_triangles, k.ratio, L, kk, kind="points")[0]),
                                 stats.extent)
    memo = {}

    def evaluate(i):
        if i not in memo:
            try:
                c = nested_counts(geom, stats.box_lo, stats.box_hi, _scaled(centre, scales[i]), L, k.ratio,
                                  overlap=overlap, corners=corners, leaves="analytic",
                                  overlap_test=triangle_box_overlap, separate_fraction=stats.separate_fraction)
                memo[i] = (k.cost(c.steps, c.tests, c.subgrids, _nested_memory_bytes(c), c.visits), c)
            except TooManyPairs:
                memo[i] = (math.inf, None)
        return memo[i][0]

    # Walk from the closed form (scale 1) towards cheaper neighbours; stop when one is dearer.
    i = scales.index(1.0)
    evaluate(i)
    for step in (-1, 1):
        j = i
        while 0 <= j + step < len(scales) and evaluate(j + step) < evaluate(j):
            j += step
        if j != i:
            break
    ns, best = min(memo.values(), key=lambda v: v[0])
    if best is None:
        raise TooManyPairs(f"every screened {L}-level top resolution exceeds the pair budget")
    how = (f"{overlap} overlap; top by a walk over {len(memo)} of {len(scales)} scales of the talk's L-level "
           "law, analytic leaves"
           + ("" if corners is not None else
              f"; above {NESTED_EXACT_MAX_TRIANGLES:,} triangles: conservative bounding-box overlap"))
    return best, overlap, how


def _nested_memory_bytes(counts) -> int:
    """Bytes of a nested structure from models.nested (as the kernel stores it)."""
    nodes = sum(info.grids for info in counts.per_level)
    return _memory_bytes(counts.cells, counts.refs, nodes)


def _nested_levels(counts):
    out = []
    for depth, info in enumerate(counts.per_level):
        res = np.asarray(info.resolutions).reshape(-1, 3)
        leaf = depth == counts.levels - 1
        lv = dict(level=depth + 1, resolution=_res_list(np.median(res, axis=0).round().astype(int)),
                  grids=int(info.grids), cells=int(info.cells),
                  references=float(counts.refs) if leaf else float(info.refs),
                  memory_bytes=_memory_bytes(info.cells, counts.refs if leaf else 0, info.grids))
        if res.shape[0] > 1:
            lv["resolution_is"] = "median over subgrids"
            lv["resolution_min"] = _res_list(res.min(axis=0))
            lv["resolution_max"] = _res_list(res.max(axis=0))
        out.append(lv)
    return out


def _terminated_nested(counts, stats, traversed_fraction):
    """(steps, tests, subgrids, occupied cells entered) per ray of a nested plan's model counts
    (:func:`models.nested.nested_counts`, no termination) for rays covering ``traversed_fraction``
    of the distance: the steps scaled by :func:`models.general.cell_fraction`, the occupied
    leaf cells entered by :func:`models.general.terminated_visits`, and the tests as those
    cells hold them.

    Tests: every test is made in an occupied leaf cell, and by Crofton a ray entering one
    meets the structure's tests per occupied leaf cell entered (``tests / visits`` without
    termination); rays that stop keep that figure, so the tests are that times the leaf
    cells entered.  For separate triangles this is the distance's scaling again; on a
    surface it counts the tests where the rays stop, which the distance does not: on the
    cylinders, whose wall runs along the box, a ray that hits stops in the first wall cell
    it enters and makes half the tests of a line that crosses the box, where the distance
    (14% of it covered) has it make a seventh (`cylinder19996`'s three-level plan at
    11x11x56: 18.5 tests a ray by the distance, 36.7 so, 48.8 by the kernel).  Over the
    nested plans of the 18 scenes of ``compare_all.py`` (docs/compare.md, "Nested grids'
    tests where rays stop") the median error against the kernel's count is 28% so and 36%
    by the distance, the worst undercount -25% against -62%; it counts too many where rays
    stop in cells holding few of the triangles (Sponza's three levels +343%, the tray's
    +244%), whose nested plans cost more than one level either way.

    Subgrids: in a two-level grid a subgrid is an occupied top cell, so the subgrids a ray
    enters stop as occupied cells do (:func:`models.general.terminated_visits` of the
    subgrids) where that stops them sooner than the distance does: on a closed scan a ray
    that hits stops in about the first subgrid it enters, where the distance alone would
    have it enter a second on the way out (armadillo at 12x14x11 over 5^3: the kernel's 1.47
    subgrids a ray, 2.12 by the distance, 1.50 so).  Deeper grids keep the distance's
    scaling: their count mixes the subgrids of every level, which a ray enters one inside
    another (with the surface's count applied to all of them, armadillo's three-level plan
    was priced at 461 ns a ray and measured at 783)."""
    g = cell_fraction(traversed_fraction, counts.steps)
    subgrids = g * counts.subgrids
    visits = terminated_visits(counts.visits, stats.separate_fraction, g)
    tests = counts.tests / counts.visits * visits if counts.visits > 0 else g * counts.tests
    if counts.levels == 2 and counts.subgrids > 0:
        by_surface = float(terminated_visits(counts.subgrids, stats.separate_fraction, g))
        if by_surface < subgrids:
            subgrids = by_surface
    return g * counts.steps, tests, subgrids, visits


def _analytic_nested(scene, stats, k: Constants, L, mailbox):
    counts, overlap, how = _nested_plan(scene, stats, k, L)
    frac, _ = termination_fraction(stats)
    ns0 = k.cost(counts.steps, counts.tests, counts.subgrids, _nested_memory_bytes(counts), counts.visits)
    sel = select_effects(stats, k.t_setup, k.t_step, k.t_int, mailbox=mailbox, termination=True, overlap="exact",
                         levels=L, subgrid_ns=k.t_sub * counts.subgrids * cell_fraction(frac, counts.steps),
                         clustering_change=clustering_change(counts, stats, k.t_step, k.t_int, ns0))
    f = sel.terms.traversed_fraction
    g = cell_fraction(f, counts.steps)
    steps, tests, subgrids, visits = _terminated_nested(counts, stats, f)
    levels = _nested_levels(counts)
    # the changes of occupancy along the top grid's walks (a cell holding a subgrid is occupied),
    # as a uniform grid of its resolution has them; the subgrids' own walks are not counted
    changes = occupancy_changes(stats, levels[0]["resolution"])
    plan = dict(levels=levels, steps=steps, tests=tests, subgrids=subgrids,
                memory_bytes=_nested_memory_bytes(counts), visits=visits + changes, changes=changes,
                terms=sel.terms, counts=counts, overlap=overlap)
    effects = _effect_dicts(sel)
    if k.has_memory:
        effects.append(_memory_effect(k, plan["steps"], plan["tests"], plan["memory_bytes"],
                                      "in the cost of every screened top resolution", plan["subgrids"],
                                      plan["visits"]))
    effects.append(dict(name="nested-model", used=True, change=0.0,
                        reason=(f"{L}-level Crofton composition over the built structure ({how}); "
                                f"termination scales its counts by {100 * g:.0f}% (rays cover {100 * f:.0f}% "
                                "of the distance, their first cell whole)")))
    return plan, effects


def _plan_ns(k: Constants, plan: Mapping) -> float:
    """A plan's predicted cost per ray (T_hit aside: the same at every depth), its memory term on
    the bytes the plan charges (``charged_bytes``, a uniform plan's read-weighted bytes) where it
    has them, else on its grid's: what :func:`predict` reports for it.  Pricing a uniform plan on
    its whole grid here while its prediction charges what rays read put ``cylinder19996``'s
    151x113x7 at 1,251 ns a ray against its own 403, and a 3-level grid at 993 won the depth; it
    measured 5.4 times the best uniform grid's time (docs/compare.md)."""
    return k.cost(plan["steps"], plan["tests"], plan.get("subgrids", 0.0),
                  plan.get("charged_bytes", plan.get("memory_bytes", 0.0)), plan.get("visits", 0.0))


def _deepen(k: Constants, uniform, nested, stops, how: str, min_gain: float | None = None):
    """Depth by predicted cost per ray incl. T_sub, stopping at the first depth that does not
    improve on the one above it by at least ``min_gain`` (a fraction of its cost; default
    DEEPEN_MIN_GAIN with a calibration, DEEPEN_MIN_GAIN_RATIO_MODE with a ratio alone).

    uniform() gives the single-level (plan, effects); nested(L) an L-level one,
    raising one of ``stops`` when that depth cannot be modelled or built.  Each plan is priced
    as its own prediction is (:func:`_plan_ns`)."""
    if min_gain is None:
        min_gain = DEEPEN_MIN_GAIN if k.units == "ns" else DEEPEN_MIN_GAIN_RATIO_MODE
    best = uniform()
    best_ns = _plan_ns(k, best[0])
    tried = [f"L=1: {best_ns:.4g}"]
    # the gain is relative to the whole cost of a ray, set-up included (unknown in ratio mode)
    setup = RATIO_MODE_T_SETUP_IN_T_STEP * k.t_step if k.units != "ns" else 0.0
    for L in range(2, MAX_LEVELS + 1):
        try:
            cand = nested(L)
        except stops as exc:
            tried.append(f"L={L}: not modelled ({exc})")
            break
        ns = _plan_ns(k, cand[0])
        tried.append(f"L={L}: {ns:.4g}")
        if ns + setup >= (best_ns + setup) * (1.0 - min_gain):
            break
        best, best_ns = cand, ns
    best[1].append(dict(name="levels", used=True, change=0.0,
                        reason=(f"depth by {how} cost per ray incl. T_sub ({k.units}), stopping at the first "
                                f"depth that does not improve by {100 * min_gain:.0f}% (the model's misfit on real "
                                "traversals)" + (f", T_setup taken as {RATIO_MODE_T_SETUP_IN_T_STEP:g} T_step for the "
                                                 "gain" if setup else "") + ": " + ", ".join(tried))))
    return best


def _analytic_plan(scene, stats, k: Constants, levels, mailbox):
    if levels != "auto":
        L = int(levels)
        if L == 1:
            return analytic_uniform_plan(stats, k, mailbox)
        return _analytic_nested(scene, stats, k, L, mailbox)
    return _deepen(k, lambda: analytic_uniform_plan(stats, k, mailbox),
                   lambda L: _analytic_nested(scene, stats, k, L, mailbox), (TooManyPairs,), "predicted")


# ---------------------------------------------------------------------------------------
# simulated fidelity
# ---------------------------------------------------------------------------------------

def _rays(scene, kind, n, seed):
    from . import rays as _rays_mod

    if kind == "camera":
        return _rays_mod.camera(scene.box_lo, scene.box_hi, n, seed)
    return _rays_mod.isotropic(scene.box_lo, scene.box_hi, n, seed)


def _scaled(res, s):
    return tuple(max(1, int(round(x * s))) for x in res)


def _scaled_with_thin_axes(res, s):
    """:func:`_scaled`, and where an axis scales to fewer than THIN_AXIS_CELLS cells, its floor and
    ceiling each (a slab 1.4 cells deep is tried 1 and 2 deep: rounding alone would skip one)."""
    base = _scaled(res, s)
    options = [sorted({max(1, math.floor(x * s)), max(1, math.ceil(x * s))}) if x * s < THIN_AXIS_CELLS else [b]
               for x, b in zip(res, base)]
    return [base] + [r for r in itertools.product(*options) if r != base]


def fit_count_curves(scales, steps, tests):
    """Least-squares count curves over the per-axis scale s of a resolution.

    ``steps(s) = a0 + a1 s`` and ``tests(s) = b0 + b1 / s + b2 / s^2`` (the general
    model's shapes: steps grow with cells per axis; tests are N, E1/h, E2/h^2 terms
    times the cell surface h^2).  Coefficients are clipped at 0 after the fit.

    scales, steps, tests : (J,) float64.  Returns (a (2,), b (3,)).
    """
    s = np.asarray(scales, dtype=np.float64)
    a = np.linalg.lstsq(np.stack([np.ones_like(s), s], axis=1), np.asarray(steps, float), rcond=None)[0]
    b = np.linalg.lstsq(np.stack([np.ones_like(s), 1.0 / s, 1.0 / s ** 2], axis=1), np.asarray(tests, float),
                        rcond=None)[0]
    return np.maximum(a, 0.0), np.maximum(b, 0.0)


def _count(grid, o, d):
    """Per-ray means from the instrumented twin: (steps, tests, subgrids, visits, changes, grid info), the
    visits what T_visit prices: the occupied cells entered and the changes of occupancy (of them)."""
    steps, tests, sub, visits, changes = grid.count(o, d, visits=True, changes=True)
    return (float(steps.mean()), float(tests.mean()), float(sub.mean()), float(visits.mean() + changes.mean()),
            float(changes.mean()), grid.info)


def _simulated_uniform(scene, stats, k: Constants, rays, mailbox):
    base_plan, effects = analytic_uniform_plan(stats, k, mailbox)
    base = tuple(base_plan["levels"][0]["resolution"])
    o, d = _rays(scene, rays, SIM_RAYS, SIM_SEED)
    # Keep every build within SIM_MAX_CELLS: shift the whole scale set down when its top end
    # would exceed the budget (then the recommendation is bounded by the budget; said below).
    base_cells = float(base[0]) * base[1] * base[2]
    shift = min(1.0, (SIM_MAX_CELLS / (base_cells * max(SIM_AXIS_SCALES) ** 3)) ** (1.0 / 3.0))
    rows = []
    for s in SIM_AXIS_SCALES:
        res = _scaled(base, s * shift)
        if res[0] * res[1] * res[2] > SIM_MAX_CELLS or any(r[1] == res for r in rows):
            continue
        st, te, _, vi, _, _ = _count(Grid.uniform(scene, res, mailbox=mailbox), o, d)
        rows.append((s * shift, res, st, te, vi))
    sc = np.array([r[0] for r in rows])
    st = np.array([r[2] for r in rows])
    te = np.array([r[3] for r in rows])
    vi = np.array([r[4] for r in rows])
    def mem(scales):  # the bytes the memory term charges at each scale (the model's references and counts)
        if not k.has_memory:
            return np.zeros(len(scales))
        return np.array([float(_uniform_counts(stats, _scaled(base, x), k, Terms(mailbox=mailbox))[5])
                         for x in scales])

    def visits(scales):  # occupied cells entered: the kernel's counts, interpolated in log scale
        return np.interp(np.log(scales), np.log(sc), vi)

    def cost_of(scales, steps_s, tests_s):
        return np.array([k.cost(a_, b_, 0.0, m_, v_)
                         for a_, b_, m_, v_ in zip(steps_s, tests_s, mem(scales), visits(scales))])

    measured_cost = cost_of(sc, st, te)
    if len(rows) >= 3:  # enough distinct resolutions to fit the three test terms
        a, b = fit_count_curves(sc, st, te)
        grid_s = np.exp(np.linspace(np.log(sc.min()), np.log(sc.max()), SIM_SEARCH_POINTS))
        cost = cost_of(grid_s, a[0] + a[1] * grid_s, b[0] + b[1] / grid_s + b[2] / grid_s ** 2)
        s_best = float(grid_s[int(np.argmin(cost))])
    else:  # tiny grids: rounding merges the scales; take the cheapest measured one
        a, b = np.full(2, np.nan), np.full(3, np.nan)
        s_best = float(sc[int(np.argmin(measured_cost))])
    at_edge = len(rows) >= 3 and s_best >= sc.max() * (1.0 - 1e-9)
    edge_note = ""
    if at_edge:
        edge_note = (f"; bounded by the simulation's {SIM_MAX_CELLS:,}-cell budget: the optimum may be finer"
                     if shift < 1.0 else "; at the finest simulated resolution: the optimum may be finer")
    res = _scaled(base, s_best)
    steps, tests, _, n_visits, n_changes, info = _count(Grid.uniform(scene, res, mailbox=mailbox), o, d)
    refs = float(info["n_refs"])
    model_steps = steps_per_ray(stats.extent, res)
    _, _, model_tests = predict_uniform(stats, res, 0.0, 1.0, 1.0, overlap="exact", terms=Terms(mailbox=mailbox))
    cells = res[0] * res[1] * res[2]
    plan = dict(levels=[dict(level=1, resolution=_res_list(res), grids=1, cells=int(cells), references=refs,
                             memory_bytes=int(info["memory_bytes"]))],
                steps=steps, tests=tests, subgrids=0.0, memory_bytes=int(info["memory_bytes"]), visits=n_visits,
                changes=n_changes, charged_bytes=charged_bytes(stats, res, k, steps, tests, int(info["memory_bytes"])),
                simulation=dict(rays=SIM_RAYS, ray_set=rays, scales=sc.tolist(), steps=st.tolist(),
                                tests=te.tolist(), visits=vi.tolist(), steps_fit=a.tolist(), tests_fit=b.tolist(),
                                best_scale=s_best, analytic_resolution=_res_list(base)))
    effects.append(dict(
        name="simulated", used=True, change=float(abs(tests / model_tests - 1.0)) if model_tests > 0 else 0.0,
        reason=(f"instrumented kernel on {SIM_RAYS} {rays} rays at {len(rows)} resolutions: at the optimum the "
                f"kernel takes {steps:.3g} steps and {tests:.3g} tests per ray, {100 * steps / model_steps:.0f}% "
                f"and {100 * tests / model_tests:.0f}% of the no-termination model (termination at the first hit, "
                "clustering, ray distribution)" + edge_note)))
    return plan, effects


def _kernel_subgrid_resolutions(scene, stats, counts, overlap):
    """(cells, 3) int32 depth-1 subgrid resolutions of a models.nested structure, x fastest.

    The non-empty top cells are recomputed exactly as :func:`models.nested.nested_counts`
    enumerates them (bounding-box candidates, then the separating-axis test for exact
    overlap); their order is the flat cell index, the order of the plan's subgrids.
    """
    from models.nested import _enumerate_pairs  # the same enumeration: rows line up

    geom, corners = _geometry(scene)
    top = np.asarray(counts.top_resolution, dtype=np.int64)
    lo = np.asarray(stats.box_lo)
    cell = np.asarray(stats.extent) / top
    src, ijk = _enumerate_pairs(geom.lo, geom.hi, lo[None, :], cell[None, :], top[None, :])
    if overlap == "exact":
        c_lo = lo[None, :] + ijk * cell[None, :]
        keep = triangle_box_overlap(corners[src], c_lo, c_lo + cell[None, :])
        ijk = ijk[keep]
    flat = ijk[:, 0] + top[0] * (ijk[:, 1] + top[1] * ijk[:, 2])
    n_cells = int(np.prod(top))
    nonempty = np.flatnonzero(np.bincount(flat, minlength=n_cells))
    sub = np.zeros((n_cells, 3), dtype=np.int32)
    child = np.asarray(counts.per_level[1].resolutions).reshape(-1, 3)
    if child.shape[0] != nonempty.size:
        raise ValueError(f"the nested plan has {child.shape[0]} subgrids but {nonempty.size} non-empty top cells")
    sub[nonempty] = child
    return sub


def _kernel_subgrid_tables(scene, stats, counts, overlap):
    """The depth-1 table of :func:`_kernel_subgrid_resolutions` and, for three levels, the
    depth-2 table (one row per cell of the depth-1 subgrids, as ``Grid.nested``'s
    ``subgrid_resolutions2`` takes it; None for two levels), so the kernel builds every
    level of the plan.

    The plan's depth-1 subgrids are the non-zero rows of the first table in the order of
    their top cells, the kernel's order; the plan's second-level cells are numbered the
    same way (each subgrid's cells x fastest), so a leaf grid goes to the row of the
    non-empty cell it subdivides.
    """
    sub = _kernel_subgrid_resolutions(scene, stats, counts, overlap)
    if counts.levels < 3:
        return sub, None
    mid, leaf = counts.per_level[1], counts.per_level[2]
    res = np.asarray(mid.resolutions, dtype=np.int64).reshape(-1, 3)
    child = np.asarray(leaf.resolutions).reshape(-1, 3)
    cells = np.asarray(mid.nonempty_cells)
    if child.shape[0] != cells.size:
        raise ValueError(f"the nested plan has {child.shape[0]} leaf grids but {cells.size} non-empty second-level "
                         "cells")
    sub2 = np.zeros((int(np.prod(res, axis=1).sum()), 3), dtype=np.int32)
    sub2[cells] = child
    return sub, sub2


def _simulated_nested(scene, stats, k: Constants, L, rays, mailbox):
    plan, effects = _analytic_nested(scene, stats, k, L, mailbox)
    counts = plan["counts"]
    sub, sub2 = _kernel_subgrid_tables(scene, stats, counts, plan["overlap"])
    grid = Grid.nested(scene, levels=L, resolution=counts.top_resolution, subgrid_resolutions=sub,
                       subgrid_resolutions2=sub2, mailbox=mailbox)
    o, d = _rays(scene, rays, SIM_RAYS, SIM_SEED)
    steps, tests, subgrids, n_visits, n_changes, info = _count(grid, o, d)
    plan = dict(plan, steps=steps, tests=tests, subgrids=subgrids, memory_bytes=int(info["memory_bytes"]),
                visits=n_visits, changes=n_changes)
    plan["levels"] = [dict(lv) for lv in plan["levels"]]
    plan["levels"][-1]["references"] = float(info["n_refs"])
    effects.append(dict(name="simulated", used=True, change=0.0,
                        reason=(f"instrumented kernel on {SIM_RAYS} {rays} rays through the {L}-level plan built "
                                f"in the kernel ({steps:.3g} steps, {tests:.3g} tests, {subgrids:.3g} subgrids per "
                                "ray); top resolution from the analytic plan, not re-optimised")))
    return plan, effects


def _simulated_plan(scene, stats, k: Constants, levels, rays, mailbox):
    if levels != "auto":
        L = int(levels)
        if L == 1:
            return _simulated_uniform(scene, stats, k, rays, mailbox)
        return _simulated_nested(scene, stats, k, L, rays, mailbox)
    return _deepen(k, lambda: _simulated_uniform(scene, stats, k, rays, mailbox),
                   lambda L: _simulated_nested(scene, stats, k, L, rays, mailbox), (TooManyPairs, ValueError),
                   "simulated")


# ---------------------------------------------------------------------------------------
# the prediction
# ---------------------------------------------------------------------------------------

def _baseline_table(stats, k: Constants, terms, hits: float = 0.0):
    """Each baseline's top resolution, and for the uniform ones their model counts and cost (the
    prediction's terms; ``hits``: the share of rays that hit, priced at T_hit as the prediction's)."""
    out, detail = {}, {}
    for name, levels in _baselines.all_baselines(stats).items():
        out[name] = _res_list(levels[0])
        d = dict(levels=[_res_list(x) for x in levels])
        if len(levels) == 1:
            steps, tests, _, _, visits, mem = _uniform_counts(stats, levels[0], k, terms)
            d.update(steps_per_ray=steps, tests_per_ray=tests,
                     cost_per_ray=k.cost(steps, tests, 0.0, mem, visits, hits))
        detail[name] = d
    return out, detail


def predict(scene, *, constants=None, samples=None, ratio=None, fidelity="analytic", levels="auto",
            rays="isotropic", mailbox=False) -> dict:
    """Recommended grid, predicted cost and the effects used, for one scene.

    Parameters
    ----------
    scene : :class:`calibrate._grid.Scene`, a built-in scene's name or a mesh file's path.
    constants, samples, ratio : see :func:`resolve_constants` (a calibration's medians and
        posterior samples in ns, or ``ratio = T_int / T_step`` alone).
    fidelity : "paper" | "analytic" | "simulated" (module docstring).
    levels : "auto" (choose 1..3 by predicted cost incl. T_sub) or 1, 2, 3.
    rays : "isotropic" | "camera" (the ray set the simulated fidelity counts; the
        analytic models assume isotropic lines and say so for camera rays).
    mailbox : the kernel mailboxes (tests each triangle once per ray).

    Returns
    -------
    dict (JSON-ready): ``scene``, ``triangles``, ``scene_class``, ``scene_class_reason``,
    ``fidelity``, ``units`` ("ns" or "T_step"), ``levels`` (top first, each with
    ``resolution`` [nx, ny, nz], ``grids``, ``cells``, ``references``), ``memory_bytes``,
    ``predicted`` (``ns_per_ray`` {median, ci95} or None in ratio mode, ``cost_t_step``
    in ratio mode, ``steps_per_ray``, ``tests_per_ray``, ``subgrids_per_ray``, ``visits_per_ray``:
    what T_visit prices, the occupied cells entered and the changes of occupancy, ``changes_per_ray``:
    the changes of them, ``hits_per_ray``: the share of rays that hit, priced at T_hit; 0 without T_hit),
    ``effects`` (list of {name, used, change, reason}), ``baselines`` (name ->
    top-level [nx, ny, nz]), ``baselines_detail``, ``notes``, ``timing_s``.
    """
    t0 = time.perf_counter()
    fidelity = _check_choice("fidelity", fidelity, FIDELITIES)
    levels = _check_choice("levels", levels, LEVEL_CHOICES)
    rays = _check_choice("ray set", rays, RAY_KINDS)
    if not isinstance(mailbox, (bool, np.bool_)):
        raise ValueError(f"mailbox must be True or False, got {mailbox!r}")
    mailbox = bool(mailbox)
    k = resolve_constants(constants, samples, ratio)
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    # the paper fidelity is the talk's model, without termination: where rays stop is not sampled for it
    stats = scene.stats if fidelity == "paper" else scene_statistics(scene)
    cls, cls_reason = scene_class(stats)
    notes = list(k.notes)
    if fidelity == "paper":
        plan, effects = paper_plan(stats, cls, k, levels)
    elif fidelity == "analytic":
        plan, effects = _analytic_plan(scene, stats, k, levels, mailbox)
    else:
        plan, effects = _simulated_plan(scene, stats, k, levels, rays, mailbox)
    if rays == "camera" and fidelity != "simulated":
        notes.append("camera rays: the paper and analytic models assume isotropic lines; use --fidelity simulated "
                     "to count camera rays")
    note = extrapolation_note(k, plan["memory_bytes"])
    if note:
        notes.append(note)
    steps, tests, subgrids = float(plan["steps"]), float(plan["tests"]), float(plan["subgrids"])
    # the paper fidelity is the talk's model: no memory term, no occupied cells
    plan_bytes = float(plan.get("charged_bytes", plan["memory_bytes"])) if fidelity != "paper" else 0.0
    visits = float(plan.get("visits", 0.0)) if fidelity != "paper" else 0.0
    changes = float(plan.get("changes", 0.0)) if fidelity != "paper" else 0.0
    # a ray that hits costs T_hit more: the share of isotropic lines that hit the mesh (sampled
    # where the traversed fraction is); the same at every resolution, so no plan depends on it
    hits = float(termination_fraction(stats)[1]) if fidelity != "paper" and k.t_hit > 0 else 0.0
    if hits and rays == "camera":
        notes.append(f"hits: T_hit is priced for the share of isotropic lines that hit the mesh ({hits:.3g}); "
                     "camera rays hit as their view has it")
    cost = _interval(k.cost_samples(steps, tests, subgrids, plan_bytes, visits, hits))
    predicted = dict(ns_per_ray=cost if k.units == "ns" else None, steps_per_ray=steps, tests_per_ray=tests,
                     subgrids_per_ray=subgrids, visits_per_ray=visits, changes_per_ray=changes, hits_per_ray=hits)
    if k.has_memory and fidelity != "paper":
        predicted["lines_per_ray"] = k.lines(steps, tests, plan_bytes, visits)
    if k.units != "ns":
        predicted["cost_t_step"] = cost
    terms = plan.get("terms") or Terms(mailbox=mailbox)
    if fidelity == "analytic" and "candidates" in plan and k.samples["t_step"].size > 1:
        # the memory and occupied-cell terms have no closed-form optimum: each posterior sample
        # picks among the searched candidates
        res_c = [r for r, _ in plan["candidates"]]
        cnt = np.array([c for _, c in plan["candidates"]], dtype=np.float64)  # :func:`_uniform_counts`
        costs = np.stack([k.cost_samples(c[0], c[1], 0.0, c[5], c[4]) for c in cnt], axis=1)
        med = np.array([k.cost(c[0], c[1], 0.0, c[5], c[4]) for c in cnt])
        (i_lo, i_hi), pen = discrete_posterior_optimum(costs, med, [r[0] * r[1] * r[2] for r in res_c])
        predicted["resolution_ci95"] = [_res_list(res_c[i_lo]), _res_list(res_c[i_hi])]
        predicted["uncertainty_penalty"] = pen
    elif fidelity == "analytic" and len(plan["levels"]) == 1 and k.samples["t_step"].size > 1:
        post = posterior_optimum(stats, k.samples["t_setup"], k.samples["t_step"], k.samples["t_int"], terms=terms,
                                 overlap="exact", use_jax=False)
        predicted["resolution_ci95"] = [_res_list(post.resolution_ci95[0]), _res_list(post.resolution_ci95[1])]
        predicted["uncertainty_penalty"] = post.penalty
    # The recommendation under the same model as the baselines (general model, selected terms).
    if len(plan["levels"]) == 1:
        res1 = plan["levels"][0]["resolution"]
        _, m_steps, _ = predict_uniform(stats, res1, 0.0, 1.0, 1.0, overlap="exact", terms=terms)
        m_tests = stopped_tests_per_ray(stats, res1, terms=terms)
        predicted["model_cost_per_ray"] = k.cost(m_steps, m_tests, 0.0, plan_bytes,
                                                 _priced_visits(stats, res1, terms), hits)
    elif "counts" in plan:
        # the model's counts, also for a simulated plan (whose steps and tests are the kernel's)
        steps, tests, subgrids, visits = _terminated_nested(plan["counts"], stats, terms.traversed_fraction)
        visits += occupancy_changes(stats, plan["levels"][0]["resolution"])
        predicted["model_cost_per_ray"] = k.cost(steps, tests, subgrids, plan_bytes, visits, hits)
    else:
        predicted["model_cost_per_ray"] = None
    base, base_detail = _baseline_table(stats, k, terms, hits)
    out = dict(scene=scene.name, triangles=int(stats.n_triangles), scene_class=cls, scene_class_reason=cls_reason,
               fidelity=fidelity, units=k.units, rays=rays, mailbox=mailbox,
               constants=dict(t_setup=k.t_setup, t_step=k.t_step, t_int=k.t_int, t_sub=k.t_sub, ratio=k.ratio,
                              fitted_on=k.fitted_on, t_mem=k.t_mem, cache_bytes=k.cache_bytes, t_visit=k.t_visit,
                              t_hit=k.t_hit),
               levels=plan["levels"], memory_bytes=int(plan["memory_bytes"]), predicted=predicted,
               effects=effects, baselines=base, baselines_detail=base_detail, notes=notes)
    if "simulation" in plan:
        out["simulation"] = plan["simulation"]
    out["timing_s"] = time.perf_counter() - t0
    return json_ready(out)


def recommended_grid(scene, *, constants=None, samples=None, ratio=None, levels="auto", mailbox=False):
    """The analytic fidelity's recommended grid, built in the kernel.

    Same plan as :func:`predict` with ``fidelity="analytic"`` (and the same arguments):
    ``levels="1"`` gives the uniform recommendation, ``"auto"`` the nested one (which may
    be a single level when no deeper grid is predicted to pay).  A nested plan is built
    with its top resolution and its per-cell subgrid resolutions at every level
    (:func:`_kernel_subgrid_tables`).

    Returns ``(grid, plan)``: a :class:`calibrate._grid.Grid` and a dict with ``levels``
    (the number of levels), ``resolution`` (top [nx, ny, nz]), ``level_plans`` (the plan's
    dict per level, as :func:`predict` reports them), ``predict_s`` (seconds to plan, scene
    statistics included unless already cached) and ``build_s`` (seconds to build).
    """
    levels = _check_choice("levels", levels, LEVEL_CHOICES)
    if not isinstance(mailbox, (bool, np.bool_)):
        raise ValueError(f"mailbox must be True or False, got {mailbox!r}")
    k = resolve_constants(constants, samples, ratio)
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    t0 = time.perf_counter()
    stats = scene_statistics(scene)
    plan, _ = _analytic_plan(scene, stats, k, levels, bool(mailbox))
    n_levels = len(plan["levels"])
    sub = sub2 = None
    if n_levels > 1:
        counts = plan["counts"]
        sub, sub2 = _kernel_subgrid_tables(scene, stats, counts, plan["overlap"])
        top = _res_list(counts.top_resolution)
    else:
        top = _res_list(plan["levels"][0]["resolution"])
    t1 = time.perf_counter()
    if n_levels > 1:
        grid = Grid.nested(scene, levels=n_levels, resolution=top, subgrid_resolutions=sub,
                           subgrid_resolutions2=sub2, mailbox=bool(mailbox))
    else:
        grid = Grid.uniform(scene, top, mailbox=bool(mailbox))
    t2 = time.perf_counter()
    return grid, dict(levels=n_levels, resolution=top, level_plans=plan["levels"], predict_s=t1 - t0,
                      build_s=t2 - t1)


def json_ready(x):
    """numpy scalars/arrays and tuples -> JSON types; non-finite floats -> None."""
    if isinstance(x, dict):
        return {str(key): json_ready(v) for key, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_ready(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_ready(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        f = float(x)
        return f if math.isfinite(f) else None
    return x


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def add_constants_options(sp, ratio_help: str, calibration_help: str | None = None) -> None:
    """The ``--calibration FILE | --ratio R`` pair every verb that predicts takes
    (read back by :func:`constants_from_args`)."""
    from .cli import positive_number

    src = sp.add_mutually_exclusive_group()
    src.add_argument("--calibration", metavar="FILE",
                     help=calibration_help or f"calibration file (default ./{DEFAULT_CALIBRATION} when it exists)")
    src.add_argument("--ratio", type=positive_number("the ratio T_int/T_step"), metavar="R", help=ratio_help)


def add_parser(sub):
    """Register the ``predict`` verb on an argparse subparsers object; returns its parser."""
    help_text = "predict the optimal uniform or nested grid for a mesh and its cost per ray"
    sp = sub.add_parser("predict", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")
    sp.add_argument("mesh", nargs="?", default=DEFAULT_SCENE, metavar="MESH|SCENE",
                    help=f"a mesh file or a built-in scene's name (default {DEFAULT_SCENE})")
    add_constants_options(sp, "predict from your own T_int/T_step alone; costs then in units of T_step")
    sp.add_argument("--fidelity", default="analytic", choices=FIDELITIES)
    sp.add_argument("--levels", default="auto", choices=LEVEL_CHOICES)
    sp.add_argument("--rays", default="isotropic", choices=RAY_KINDS)
    sp.add_argument("--mailbox", action="store_true", help="the kernel mailboxes (tests each triangle once per ray)")
    sp.set_defaults(func=cmd_predict)
    return sp


def constants_from_args(args, rays: str | None = None) -> dict:
    """The constants source of a verb's ``--ratio`` / ``--calibration`` arguments (``ratio=`` or
    ``samples=`` and ``constants=`` for :func:`predict`); no calibration file raises UserError.
    ``rays`` picks the calibration's fit of that ray set alone when it has one."""
    if getattr(args, "ratio", None) is not None:
        return dict(ratio=args.ratio)
    path = Path(args.calibration) if getattr(args, "calibration", None) else Path(DEFAULT_CALIBRATION)
    if not path.exists():
        if getattr(args, "calibration", None):
            raise UserError(f"{path}: no such calibration file; run `calibrate run` to create one, or pass --ratio R")
        raise UserError(f"no calibration: ./{DEFAULT_CALIBRATION} does not exist; run `calibrate run` first, "
                        "pass --calibration FILE, or give your own ratio with --ratio R")
    k = load_calibration_constants(path, rays)
    s = k.samples
    names = ("t_setup", "t_step", "t_int", "t_sub", "t_mem", "t_visit", "t_hit")
    constants = {f"{n}_ns": getattr(k, n) for n in names}
    if k.fitted_on:
        constants["fitted_on"] = k.fitted_on
    if k.cache_bytes is not None:
        constants["cache_bytes"] = k.cache_bytes
    if k.largest_grid_bytes is not None:
        constants["largest_grid_bytes"] = k.largest_grid_bytes
    if k.line_weights != NO_LINE_WEIGHTS:
        constants["line_weights"] = k.line_weights
    return dict(samples={f"{n}_ns": s[n] for n in names}, constants=constants)




def cmd_predict(args) -> int:
    """Run the ``predict`` verb: JSON on stdout with ``--json``, else rich tables."""
    import json
    import sys

    from .cli import _stderr_is_tty

    src = constants_from_args(args, rays=args.rays)
    scene = Scene.load(args.mesh)
    try:  # a scene the statistics reject fails here, naming the file, before any progress line
        scene.stats  # noqa: B018
    except ValueError as exc:
        raise UserError(f"{scene.name}: {exc}") from None
    slow = args.fidelity == "simulated" or (args.levels != "1" and args.fidelity == "analytic")
    if slow and not args.quiet and not args.json and _stderr_is_tty():
        print(f"predicting ({args.fidelity}) for {scene.name} ({scene.n_triangles:,} triangles) ...",
              file=sys.stderr)
    result = predict(scene, fidelity=args.fidelity, levels=args.levels, rays=args.rays, mailbox=args.mailbox, **src)
    if args.json:
        sys.stdout.write(json.dumps(result, indent=2, allow_nan=False) + "\n")
        return 0
    _print_human(result)
    return 0


def _fmt_res(res):
    return "x".join(str(x) for x in res)


def _fmt_bytes(n):
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return str(n)


def _print_human(result: dict) -> None:
    from rich.table import Table

    from .cli import _console

    console = _console()
    unit = "ns/ray" if result["units"] == "ns" else "T_step/ray"
    cost = result["predicted"]["ns_per_ray"] or result["predicted"].get("cost_t_step")
    console.print(f"[bold]{result['scene']}[/bold]: {result['triangles']:,} triangles, class "
                  f"[bold]{result['scene_class']}[/bold] ({result['scene_class_reason']}); fidelity "
                  f"{result['fidelity']}, {result['rays']} rays")
    grid = Table(title="recommended grid")
    for col in ("level", "resolution", "grids", "cells", "references", "memory"):
        grid.add_column(col, justify="right")
    for lv in result["levels"]:
        res = _fmt_res(lv["resolution"]) + (" (median)" if lv.get("resolution_is") else "")
        grid.add_row(str(lv["level"]), res, f"{lv['grids']:,}", f"{lv['cells']:,}", f"{lv['references']:,.0f}",
                     _fmt_bytes(lv["memory_bytes"]) if "memory_bytes" in lv else "")
    console.print(grid)
    p = result["predicted"]
    interval = (f"95% interval [{cost['ci95'][0]:.4g}, {cost['ci95'][1]:.4g}]" if result["units"] == "ns"
                else "no interval without a calibration's posterior")
    console.print(f"predicted {cost['median']:.4g} {unit}, {interval}; "
                  f"{p['steps_per_ray']:.4g} steps, {p['tests_per_ray']:.4g} tests, "
                  f"{p['subgrids_per_ray']:.3g} subgrids per ray; memory {_fmt_bytes(result['memory_bytes'])}")
    eff = Table(title="effects")
    eff.add_column("effect")
    eff.add_column("used")
    eff.add_column("why")
    for e in result["effects"]:
        eff.add_row(e["name"], "yes" if e["used"] else "no", e["reason"])
    console.print(eff)
    base = Table(title="baselines (general-model cost, same terms)")
    base.add_column("heuristic")
    base.add_column("resolution (per level)")
    base.add_column(f"model {unit}", justify="right")
    ours = " / ".join(_fmt_res(lv["resolution"]) for lv in result["levels"])
    mc = p.get("model_cost_per_ray")
    base.add_row("[bold]this prediction[/bold]", ours, "-" if mc is None else f"{mc:.4g}")
    for name, d in result["baselines_detail"].items():
        c = d.get("cost_per_ray")
        base.add_row(name, " / ".join(_fmt_res(r) for r in d["levels"]), "-" if c is None else f"{c:.4g}")
    console.print(base)
    for n in result["notes"]:
        console.print(f"note: {n}")
    console.print(f"prediction time {1000 * result['timing_s']:.1f} ms")

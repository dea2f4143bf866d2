"""The general cost model (DESIGN §3.2): expected counts per ray from integral geometry.

Setting: a grid box with extents ``d`` (3,), volume ``V``, surface ``S``; resolution
``n = (nx, ny, nz)``; cell sizes ``c_i = d_i / n_i``; cell surface
``S_c = 2 (cx cy + cy cz + cz cx)``.  Rays are isotropic uniform random lines that hit
the box (the talk's "all rays hit the grid and are equally likely"), no termination.

Crofton (Cauchy) formula: for convex ``K`` inside the box,
``P(line hits K | line hits box) = S(K) / S``.

Steps (cells visited per ray; exact)
    ``steps = sum_cells S_c / S = nx ny nz S_c / S
            = 2 (nz dx dy + nx dy dz + ny dz dx) / S``
    (``= m`` for an m^3 grid of a cube; ``= 6 V / (S h)`` for cubic cells of side h).

Tests without mailboxing (exact given the per-cell reference counts)
    ``tests = sum_cells refs(c) S_c / S = R S_c / S``.

Expected references ``R`` (average over the grid offset, exact for that average)
    A triangle T overlaps the cell ``C + z`` iff the lattice point ``z`` lies in
    ``T (+) (-C)``; with a uniformly random offset the expected count is
    ``vol(T (+) C) / vol(C)``.  For the box ``C = sum_i [0, c_i] e_i`` (a sum of
    orthogonal segments), adding one segment adds ``c_i`` times the measure of the
    projection along ``e_i``, so for a planar T (zero volume):
    ``vol(T (+) C) = sum_i c_i A|n_i| + sum_i c_j c_k ext_i + cx cy cz``
    ((i, j, k) a cyclic permutation).  Dividing by ``cx cy cz``:
    ``E[cells(T)] = 1 + sum_i ext_i / c_i + sum_i A|n_i| / (c_j c_k)``,
    hence ``R = N + sum_i E1_i / c_i + sum_i E2_i / (c_j c_k)``
    (cubic: ``N + E1/h + E2/h^2``).
    A build that assigns by *bounding-box* overlap instead has
    ``E[cells] = prod_i (1 + ext_i / c_i)``, i.e.
    ``R_bbox = N + sum_i E1_i / c_i + sum_i B_jk / (c_j c_k) + B_xyz / (cx cy cz)``
    with ``B_jk = sum ext_j ext_k`` and ``B_xyz = sum ext_x ext_y ext_z``.

Tests with mailboxing (each triangle tested once per ray)
    A ray tests T iff it meets the union U of T's cells.
    - exact overlap: U is approximated by ``T (+) C`` (the DESIGN's "hull"); by the
      mixed-volume identity ``S(K + L) = S(K) + S(L) + 6 V(K, L, B)`` and
      ``V(T, segment c_i e_i, B) = c_i P_i(T) / 6`` (P_i the perimeter of T projected
      along e_i), ``S(T (+) C) = 2A + sum_i c_i P_i + S_c``, so
      ``tests_mb = (2 A_tot + sum_i c_i P_i + N S_c) / S``
      (cubic: ``2A + h (Px+Py+Pz) + 6 h^2`` per triangle).  Approximate: U is a
      polycube, not convex, and a line through ``T (+) C`` can miss U.
    - bounding-box overlap: U is the box of the cell range, convex, with expected side
      ``ext_i + c_i`` (independent per axis over the offset), so exactly
      ``tests_mb = 2 sum_i (B_jk + c_j E1_k + c_k E1_j + N c_j c_k) / S``.

Single-level optimum (cubic cells of side h, rays never terminate)
    ``T(h) = T_setup + T_step 6V/(S h) + T_int 6 (N h^2 + E1 h + E2) / S`` is convex in
    h > 0; ``dT/dh = 0`` is ``2 N r h^3 + E1 r h^2 - V = 0`` (r = T_int / T_step), whose
    left side increases on h > 0 from ``-V``: one positive root, the minimum.  Every
    variant above gives the same cubic ``a h^3 + b h^2 - c = 0`` with ``a = 2 N r`` and
    (exact, no mailbox) ``b = r E1, c = V``; (exact, mailbox) ``b = r P / 6, c = V``;
    (bbox, no mailbox) ``b = r E1, c = V + r B_xyz``; (bbox, mailbox) ``b = 2 r E1 / 3, c = V``.

Rays that stop at their first hit (:func:`cell_fraction`): a ray enters its first cell
whole and a fraction f of the rest, so the counts scale by ``f + (1 - f) / S0`` and the
optimum solves a quartic (:func:`termination_coefficients`, :func:`solve_cell_quartic`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .closed_forms import MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS, cells_to_resolution
from .stats import SceneStats

#: Newton iterations for the scaled cubic; from a start within a factor sqrt(2) of the
#: root, Newton on this convex increasing function converges monotonically and
#: quadratically, so 40 is far more than float64 needs (kept fixed for jax tracing).
CUBIC_NEWTON_ITERATIONS = 40

OVERLAP_MODES = ("exact", "bbox")
#: An axis with fewer cells than this at the continuous optimum is *thin*: the integer
#: search tries one cell more and one fewer than its floor and ceiling.
THIN_AXIS_CELLS = 4
#: Occupied cells a ray enters on a connected surface when rays stop at their first hit
#: (:func:`visits_per_ray`): measured 0.9 to 2.0 per ray on the built-in surfaces and the
#: meshes of ../shared/meshes at 1/8 to 8 cells per triangle, nearly the same at every
#: resolution (docs/calibration.md, "Occupied cells").
VISITS_SURFACE = 1.5


@dataclass(frozen=True)
class Terms:
    """Which terms of the count model are switched on (see :mod:`models.effects`).

    edge : the E1 / perimeter terms (triangles spanning cells along their extent).
    area : the E2 / 2A / bbox-area terms (large triangles).
    mailbox : tests counted once per ray per triangle.
    traversed_fraction : fraction (0, 1] of its no-termination *distance* a ray covers
        (1.0 = rays never stop; :func:`models.effects.termination_fraction`); the counts
        scale by :func:`cell_fraction` of it (a ray enters its first cell whatever it hits).
    """

    edge: bool = True
    area: bool = True
    mailbox: bool = False
    traversed_fraction: float = 1.0


def _resolution(resolution) -> np.ndarray:
    if type(resolution) is tuple and len(resolution) == 3 and all(type(x) is int and x >= 1 for x in resolution):
        return np.array(resolution, dtype=np.float64)  # the planners' own tuples: no array checks needed
    n = np.asarray(resolution)
    if n.shape != (3,):
        raise ValueError(f"resolution must be (nx, ny, nz), got shape {n.shape}")
    if not np.all(np.isfinite(n)) or np.any(n < 1):
        raise ValueError(f"resolution entries must be finite and >= 1, got {resolution!r}")
    return n.astype(np.float64)


def _check_overlap(overlap):
    if overlap not in OVERLAP_MODES:
        raise ValueError(f"overlap must be one of {OVERLAP_MODES}, got {overlap!r}")


def cell_sizes(extent, resolution) -> np.ndarray:
    """(3,) cell sizes ``d_i / n_i`` (scene units)."""
    return np.asarray(extent, dtype=np.float64) / _resolution(resolution)


def steps_per_ray(extent, resolution) -> float:
    """Expected cells visited per isotropic line hitting the box: ``2 (nz dx dy + nx dy dz + ny dz dx) / S``."""
    d = np.asarray(extent, dtype=np.float64)
    n = _resolution(resolution)
    s = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    return float(2.0 * (n[2] * d[0] * d[1] + n[0] * d[1] * d[2] + n[1] * d[2] * d[0]) / s)


def expected_refs(stats: SceneStats, resolution, *, overlap="exact", edge=True, area=True) -> float:
    """Expected total cell references R (offset average) at this resolution.

    ``exact``: ``N + sum_i E1_i/c_i + sum_i E2_i/(c_j c_k)``;
    ``bbox``:  ``N + sum_i E1_i/c_i + sum_i B_jk/(c_j c_k) + B_xyz/(cx cy cz)``.
    """
    _check_overlap(overlap)
    c = cell_sizes(stats.extent, resolution)
    cc = np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])  # c_j c_k for i = x, y, z
    r = float(stats.n_triangles)
    if edge:
        r += float(np.sum(stats.e1_axes / c))
    if area:
        if overlap == "exact":
            r += float(np.sum(stats.e2_axes / cc))
        else:
            r += float(np.sum(stats.bbox_pair_sums / cc)) + stats.bbox_triple_sum / float(np.prod(c))
    return r


def occupied_cells(stats: SceneStats, resolution) -> float:
    """Expected cells holding at least one triangle (exact overlap), the *occupied* cells.

    A cell is occupied when the union U of the triangles meets it, so (the argument of
    :func:`expected_refs`, for U instead of one triangle) the offset-averaged count is
    ``vol(U (+) C) / vol(C)``.  For a connected surface the union's first-order term is
    its projected area, ``sum_i E2_i / (c_j c_k)``: the ``N`` and ``E1`` terms of R count
    cells that neighbouring triangles share.  For separate triangles nothing is shared
    and every term of R counts.  The model takes

        ``R_occ = sum_i E2_i / (c_j c_k) + f_sep (N + sum_i E1_i / c_i)``

    (``f_sep`` = :attr:`models.stats.SceneStats.separate_fraction`), and spreads R_occ
    over the ``n`` cells at random (Poisson): ``occupied = n (1 - exp(-R_occ / n))``,
    which saturates at n for coarse grids.  With a sampled grid's occupied cells
    (:func:`occupancy_scale`) R_occ is scaled to match them.  APPROXIMATE: measured
    against the kernel's grids within about 15% on closed and open surfaces and on
    separate triangles, a thin shell apart (docs/calibration.md, "Occupied cells").
    """
    n = float(np.prod(_resolution(resolution)))
    return float(-n * np.expm1(-occupancy_scale(stats, resolution) * _r_occ(stats, resolution) / n))


def _r_occ(stats: SceneStats, resolution) -> float:
    c = cell_sizes(stats.extent, resolution)
    cc = np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])
    r_occ = float(np.sum(stats.e2_axes / cc))
    return r_occ + stats.separate_fraction * (float(stats.n_triangles) + float(np.sum(stats.e1_axes / c)))


def _scale_at(stats: SceneStats, res, occupied) -> float | None:
    """The factor on R_occ that gives ``occupied`` cells at ``res``, None from a grid more than
    half occupied or empty (near saturation any R_occ fits)."""
    n = float(res[0] * res[1] * res[2])
    r_occ = _r_occ(stats, res)
    if not (0 < occupied <= 0.5 * n) or not r_occ > 0.0:
        return None
    return float(-n * np.log1p(-occupied / n) / r_occ)


def occupancy_scale(stats: SceneStats, resolution=None) -> float:
    """The factor on R_occ that gives the occupied cells counted in the sampled grids
    (:attr:`models.stats.TerminationSample.occupied` and ``occupancy``), 1 without one.

    At each sampled grid, solves ``n (1 - exp(-s R_occ / n)) = occupied``.  The projected
    area counts each sheet of a surface on its own; where two sheets lie closer than a
    cell (a thin shell: the CAD chair's slats and legs) they share cells, and the kernel's
    grids hold 0.46-0.49 of the model's occupied cells at every resolution from 1/4 to 4
    cells a triangle; elsewhere 0.75-1.17 (docs/compare.md, "Tests counted in the occupied
    cells, and the occupied cells sampled").  How far the sheets share cells changes with
    the cell: on the bunny one scale, fitted at the sample's grid, counts 40-60% too many
    occupied cells at a half and a third of its cells per axis and 12% too few at twice
    them (docs/compare.md, "The occupied cells sampled at three sizes").  With grids
    sampled at several sizes, ``log s`` is interpolated linearly in the log of the cells
    at ``resolution`` between theirs (the nearest one's beyond them); without
    ``resolution``, the sample's own grid's.  A grid more than half occupied says little
    about how triangles share cells (near saturation any R_occ fits) and is left out.
    """
    ts = stats.termination
    if ts is None or ts.resolution is None:
        return 1.0
    own = _scale_at(stats, ts.resolution, ts.occupied)
    if resolution is None:
        return 1.0 if own is None else own
    points = [(ts.resolution, own)] + [(r, _scale_at(stats, r, occ)) for r, occ in ts.occupancy]
    points = sorted((math.log(float(r[0] * r[1] * r[2])), math.log(s)) for r, s in points if s is not None)
    if not points:
        return 1.0
    x = math.log(float(np.prod(_resolution(resolution))))
    return float(math.exp(np.interp(x, [p[0] for p in points], [p[1] for p in points])))


def occupancy_changes(stats: SceneStats, resolution) -> float:
    """Changes of occupancy per ray at ``resolution``: the cells of a ray's walk that are empty
    after an occupied one or occupied after an empty one (the cell before the first counting
    as occupied), what the instrumented kernel counts (``Grid.count(..., changes=True)``).

    Each is the branch that decides whether a cell is tested going the other way from the
    cell before, mispredicted about once a change (callgrind: 1.83 a ray on the sphere,
    docs/calibration.md, "One T_step for every scene"); T_visit prices them with the occupied
    cells entered.  How many a ray makes depends on the mesh and the cell, not on a law the
    statistics give: on a scan about 2 for every ray that enters the box in an empty cell,
    nearly constant over the resolution; on a cylinder none while every cell a ray enters is
    occupied and about 1 once the grid has empty cells around the wall; on separate
    triangles about 2 S p (1 - p) for S steps of which a share p occupied.  So they are taken
    from the termination sample's grids (:attr:`models.stats.TerminationSample.changes`),
    linearly in the log of the cells between them and the nearest one's beyond them;
    0 without a sample (a mesh too large to sample: the plan is then priced without them).
    """
    ts = stats.termination
    if ts is None or not ts.changes:
        return 0.0
    points = sorted((math.log(float(r[0] * r[1] * r[2])), float(c)) for r, c in ts.changes)
    x = math.log(float(np.prod(_resolution(resolution))))
    return float(np.interp(x, [p[0] for p in points], [p[1] for p in points]))


def terminated_visits(visits, separate_fraction, traversed_fraction, surface=VISITS_SURFACE):
    """Occupied cells a ray enters when rays stop at their first hit, from the count without
    termination ``visits`` (broadcasts over arrays).

    Two kinds of scene, mixed by ``separate_fraction`` (:attr:`models.stats.SceneStats.separate_fraction`):

    - separate triangles: a ray's work is in proportion to the distance it covers,
      so ``traversed_fraction * visits`` (as for steps and tests);
    - a connected surface: a ray that meets it stops within the first occupied cells
      it enters, about VISITS_SURFACE of them whatever the resolution; no more rays
      meet them than the count without termination allows, so
      ``VISITS_SURFACE * min(visits, 1)``.  (Constant over resolution on purpose: on a
      thin slab one cell thick the count without termination grows with the cells
      across it, but the kernel's rays stop in the first one, 0.9 per ray at every
      resolution on the CAD tray.)

    ``surface`` is that count (VISITS_SURFACE, or a scene's own from :func:`surface_visits`).
    ``traversed_fraction >= 1`` (rays never stop) returns ``visits`` unchanged.
    """
    v = np.asarray(visits, dtype=np.float64)
    if traversed_fraction >= 1.0:
        return v if v.ndim else float(v)
    f = float(separate_fraction)
    out = f * traversed_fraction * v + (1.0 - f) * surface * np.minimum(v, 1.0)
    return out if out.ndim else float(out)


def _open_visits(stats: SceneStats, resolution) -> float:
    """Occupied cells a ray enters when rays never stop: Crofton as in :func:`steps_per_ray`,
    for the occupied cells only, ``occupied_cells * S_c / S``."""
    c = cell_sizes(stats.extent, resolution)
    s_c = 2.0 * (c[0] * c[1] + c[1] * c[2] + c[2] * c[0])
    return float(occupied_cells(stats, resolution) * s_c / stats.surface)


def surface_visits(stats: SceneStats) -> float:
    """Occupied cells a ray enters on a connected surface before it stops: the termination
    sample's own count (:attr:`models.stats.TerminationSample.visits`, the kernel's in the
    sample's grid, less the separate triangles' share as :func:`terminated_visits` counts
    it), VISITS_SURFACE without one.  The kernel's count moves slowly with the resolution
    (the bunny 1.70 a ray at 8x8x6, 1.43 at 27x25x21, 1.21 at 136x128x104); the sample's
    grid, a quarter cell a triangle, is near the plans.  Kept within [0.5, 4] of a cell
    (a sample of a scene that is nearly all separate triangles leaves little to divide)."""
    ts = stats.termination
    if ts is None or ts.visits is None or stats.separate_fraction >= 1.0:
        return VISITS_SURFACE
    v0 = _open_visits(stats, ts.resolution)
    if not v0 > 0.0:
        return VISITS_SURFACE
    g = float(cell_fraction(ts.fraction, steps_per_ray(stats.extent, ts.resolution)))
    f = stats.separate_fraction
    surface = (ts.visits - f * g * v0) / ((1.0 - f) * min(v0, 1.0))
    return float(min(max(surface, 0.5), 4.0))


def cell_fraction(traversed_fraction, steps, xp=np):
    """Fraction of a ray's no-termination cells it enters when it stops at its first hit.

    ``traversed_fraction`` ``f`` is the fraction of the *distance* a ray covers
    (:func:`models.effects.termination_fraction`); ``steps`` ``S0`` the cells it enters
    without termination, ``1 + X`` with X the cell boundaries its chord crosses.  A ray
    enters its first cell whatever it hits, then crosses ``f X`` boundaries on average,
    so it enters ``1 + f (S0 - 1)`` cells, the fraction ``f + (1 - f) / S0`` of S0.  Its
    tests and occupied cells are those of the cells it enters: a ray that stops in a cell
    has tested every triangle of it (the tests per cell entered are taken as the
    no-termination average, ``T0 / S0``).  On a grid one or two cells across the
    distance alone would count a small part of the first cell's tests (the CAD tray,
    docs/compare.md, "Rays stop at the end of a cell").  ``S0`` is clipped at 1
    (broadcasts; ``xp`` may be ``jax.numpy``).  ``f = 1`` (rays never stop) gives 1.
    """
    f = traversed_fraction
    return f + (1.0 - f) / xp.maximum(steps, 1.0)


def visits_per_ray(stats: SceneStats, resolution, *, terms: Terms | None = None) -> float:
    """Expected occupied cells a ray enters, with termination as ``terms`` says.

    Without termination, Crofton as in :func:`steps_per_ray`, for the occupied cells
    only: ``occupied_cells * S_c / S``; with it, :func:`terminated_visits`.

    APPROXIMATE (docs/calibration.md, "Occupied cells"): on separate triangles within
    about 5% of the kernel's counts at coarse grids and 40% at fine ones; on surfaces
    the kernel enters 0.9 to 2 occupied cells per ray, against the model's 1.5.
    """
    terms = terms or Terms()
    v = _open_visits(stats, resolution)
    if terms.traversed_fraction >= 1.0:
        return v
    g = cell_fraction(terms.traversed_fraction, steps_per_ray(stats.extent, resolution))
    return terminated_visits(v, stats.separate_fraction, g, surface_visits(stats))


def stopped_tests_per_ray(stats: SceneStats, resolution, *, terms: Terms | None = None) -> float:
    """Triangle tests per ray (exact overlap) when rays stop at their first hit: the smaller
    of two counts.

    - By the distance (:func:`predict_uniform`): the no-termination tests ``T0`` scaled by
      :func:`cell_fraction`, as if a ray's tests were spread evenly along it.
    - By the occupied cells: every test is made in an occupied cell, and by Crofton a ray
      entering one meets ``R / occupied`` references on average (``T0 / V0``, ``V0`` the
      occupied cells entered without termination); rays that stop keep that figure, so the
      tests are ``T0 * visits / V0`` with ``visits`` from :func:`visits_per_ray`.  On a
      connected surface a ray stops within its first occupied cells, where the distance
      has it test every cell it would cross on the way out.

    The smaller is taken as :func:`calibrate.predict` takes it for a two-level grid's
    subgrids (a surface stops rays sooner than the distance does, never later).
    APPROXIMATE: with the termination sample's occupied cells and visits
    (:func:`occupancy_scale`, :func:`surface_visits`), against the kernel's counts at the
    plans within 0-17% on the scans of ../shared/meshes, where the distance alone is
    25-110% over (docs/compare.md, "Tests counted in the occupied cells, and the occupied
    cells sampled"); where the occupied-cell count is off it is off with it.
    ``terms.traversed_fraction >= 1`` (rays never stop) gives ``T0``; with
    ``terms.mailbox``, the count by the distance (a mailbox's tests per cell are not
    R / occupied).
    """
    terms = terms or Terms()
    if terms.traversed_fraction >= 1.0 or terms.mailbox:
        return float(predict_uniform(stats, resolution, 0.0, 1.0, 1.0, overlap="exact", terms=terms)[2])
    tests0 = triangle_tests_per_ray(stats, resolution, overlap="exact", edge=terms.edge, area=terms.area)
    g = float(cell_fraction(terms.traversed_fraction, steps_per_ray(stats.extent, resolution)))
    by_distance = g * tests0
    v0 = _open_visits(stats, resolution)
    if not v0 > 0.0:
        return float(by_distance)
    visits = terminated_visits(v0, stats.separate_fraction, g, surface_visits(stats))
    return float(min(by_distance, tests0 * visits / v0))


def triangle_tests_per_ray(stats: SceneStats, resolution, *, mailbox=False, overlap="exact",
                  edge=True, area=True) -> float:
    """Expected triangle tests per isotropic line hitting the box (no termination).

    See the module docstring for the four formulas (mailbox x overlap).
    """
    _check_overlap(overlap)
    c = cell_sizes(stats.extent, resolution)
    s_cell = 2.0 * (c[0] * c[1] + c[1] * c[2] + c[2] * c[0])
    if not mailbox:
        return expected_refs(stats, resolution, overlap=overlap, edge=edge, area=area) * s_cell / stats.surface
    total = stats.n_triangles * s_cell
    if overlap == "exact":
        if edge:
            total += float(np.dot(c, stats.perimeters))
        if area:
            total += 2.0 * stats.area
    else:
        e1 = stats.e1_axes
        if edge:  # 2 sum_i (c_j E1_k + c_k E1_j)
            total += 2.0 * float(c[1] * e1[2] + c[2] * e1[1] + c[2] * e1[0]
                                 + c[0] * e1[2] + c[0] * e1[1] + c[1] * e1[0])
        if area:
            total += 2.0 * float(np.sum(stats.bbox_pair_sums))
    return total / stats.surface


def predict_uniform(stats: SceneStats, resolution, t_setup, t_step, t_int, mailbox=False, *,
                    overlap="exact", terms: Terms | None = None) -> tuple[float, float, float]:
    """Predicted cost of a uniform grid at a resolution.

    Parameters
    ----------
    stats : SceneStats.
    resolution : (3,) ints (nx, ny, nz), each >= 1.
    t_setup, t_step, t_int : ns per ray, ns per cell step, ns per triangle test.
    mailbox : kernel tests each triangle once per ray (ignored when ``terms`` is given).
    overlap : "exact" (triangle/cell overlap) or "bbox" (bounding-box overlap).
    terms : which terms to include (default: all, ``mailbox`` as given, no termination).

    Returns
    -------
    (ns_per_ray, steps, tests) : ns per ray, cells visited per ray, triangle tests per ray.
    """
    if terms is None:
        terms = Terms(mailbox=bool(mailbox))
    f = float(terms.traversed_fraction)
    if not 0.0 < f <= 1.0:
        raise ValueError(f"traversed_fraction must be in (0, 1], got {f}")
    for name, t in (("t_setup", t_setup), ("t_step", t_step), ("t_int", t_int)):
        if not np.isfinite(t) or t < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {t!r}")
    steps0 = steps_per_ray(stats.extent, resolution)
    g = cell_fraction(f, steps0)
    steps = g * steps0
    tests = g * triangle_tests_per_ray(stats, resolution, mailbox=terms.mailbox, overlap=overlap,
                                       edge=terms.edge, area=terms.area)
    return float(t_setup + t_step * steps + t_int * tests), steps, tests


def tests_polynomial(stats: SceneStats, *, mailbox=False, overlap="exact", edge=True, area=True):
    """``(alpha, beta, gamma, delta)`` with tests per ray (cubic cells of side h, no termination)
    ``6 (alpha h^2 + beta h + gamma + delta / h) / S`` (the module docstring's four formulas):
    exact ``(N, E1, E2, 0)``, bbox ``(N, E1, sum B_jk, B_xyz)``, exact mailbox
    ``(N, P/6, A/3, 0)``, bbox mailbox ``(N, 2 E1/3, sum B_jk / 3, 0)``; ``edge`` and
    ``area`` switch off beta and gamma/delta."""
    _check_overlap(overlap)
    n = float(stats.n_triangles)
    if overlap == "exact":
        beta = float(np.sum(stats.perimeters)) / 6.0 if mailbox else stats.e1
        gamma = stats.area / 3.0 if mailbox else stats.e2
        delta = 0.0
    else:
        beta = (2.0 / 3.0) * stats.e1 if mailbox else stats.e1
        gamma = float(np.sum(stats.bbox_pair_sums)) / (3.0 if mailbox else 1.0)
        delta = 0.0 if mailbox else stats.bbox_triple_sum
    return n, float(beta) if edge else 0.0, float(gamma) if area else 0.0, float(delta) if area else 0.0


def cubic_coefficients(stats: SceneStats, r, *, mailbox=False, overlap="exact", edge=True,
                       area=True):
    """``(a, b, c)`` of ``a h^3 + b h^2 - c = 0`` whose positive root is the optimal cubic cell size.

    ``r`` may be a scalar or an array (T_int / T_step); the result broadcasts.  With
    :func:`tests_polynomial`'s coefficients: ``a = 2 alpha r``, ``b = beta r``,
    ``c = V + delta r``.
    """
    _check_overlap(overlap)
    r = np.asarray(r, dtype=np.float64)
    a = 2.0 * stats.n_triangles * r
    if not edge:
        b = 0.0 * r
    elif overlap == "exact":
        b = r * (float(np.sum(stats.perimeters)) / 6.0 if mailbox else stats.e1)
    else:
        b = r * ((2.0 / 3.0) * stats.e1 if mailbox else stats.e1)
    c = stats.volume + (r * stats.bbox_triple_sum if (overlap == "bbox" and area and not mailbox) else 0.0 * r)
    return a, b, c


def termination_coefficients(stats: SceneStats, r, traversed_fraction, *, mailbox=False, overlap="exact",
                             edge=True, area=True):
    """``(k4, k3, k2)`` that termination adds to the optimum's equation:
    ``k4 h^4 + (a + k3) h^3 + (b + k2) h^2 - c = 0`` (``a, b, c`` of :func:`cubic_coefficients`).

    With :func:`cell_fraction` ``g = f + (1 - f) / S0`` and ``S0 = 6V/(S h)``, the cost is
    ``T_setup + f (T_step S0 + T_int T0) + (1 - f) (T_step + T_int T0 / S0)`` with
    ``T0 / S0 = (alpha h^3 + beta h^2 + gamma h + delta) / V``; setting its derivative to 0
    and multiplying by ``S h^2 / (6 f T_step)`` gives the equation with
    ``kappa = (1 - f) S / (6 f V)``: ``k4 = 3 alpha kappa r``, ``k3 = 2 beta kappa r``,
    ``k2 = gamma kappa r``, all 0 for ``f = 1``.  The left side is convex and increasing on
    h > 0 (every coefficient but ``-c`` is >= 0): one positive root, the minimum, at or
    below the cubic's (a ray's first cell is paid in full, so fuller cells cost more).
    """
    r = np.asarray(r, dtype=np.float64)
    f = float(traversed_fraction)
    if not 0.0 < f <= 1.0:
        raise ValueError(f"traversed_fraction must be in (0, 1], got {f}")
    alpha, beta, gamma, _ = tests_polynomial(stats, mailbox=mailbox, overlap=overlap, edge=edge, area=area)
    kappa = (1.0 - f) * stats.surface / (6.0 * f * stats.volume)
    return 3.0 * alpha * kappa * r, 2.0 * beta * kappa * r, gamma * kappa * r


def solve_cell_cubic(a, b, c, xp=np):
    """Positive root h of ``a h^3 + b h^2 - c = 0`` (a, c > 0, b >= 0), vectorised.

    Works with ``xp = numpy`` or ``jax.numpy`` (fixed iteration count, no branches).
    Scaled to ``x = h / h_a`` with ``h_a = (c/a)^(1/3)`` (computed in log space):
    ``x^3 + beta x^2 - 1 = 0``, ``beta = b h_a^2 / c``.  The root lies in
    ``[x0 / sqrt(2), x0]`` with ``x0 = min(1, beta^(-1/2))``; Newton from x0 decreases
    monotonically to it (the function is convex and increasing for x > 0).
    """
    log_ha = (xp.log(c) - xp.log(a)) / 3.0
    beta = b * xp.exp(2.0 * log_ha - xp.log(c))
    x = xp.minimum(1.0, 1.0 / xp.sqrt(xp.maximum(beta, 1e-300)))
    for _ in range(CUBIC_NEWTON_ITERATIONS):
        fx = x * x * (x + beta) - 1.0
        dfx = x * (3.0 * x + 2.0 * beta)
        x = x - fx / dfx
    return x * xp.exp(log_ha)


def solve_cell_quartic(a, b, c, k4, k3, k2, xp=np):
    """Positive root h of ``k4 h^4 + (a + k3) h^3 + (b + k2) h^2 - c = 0`` (a, c > 0; b, k's >= 0),
    vectorised (``xp`` numpy or jax.numpy, fixed iterations).

    Starts at the cubic's root h_c (:func:`solve_cell_cubic`; the k's are 0 without
    termination and h_c is returned unchanged), where the left side is >= 0; the function
    is convex and increasing on h > 0, so Newton from h_c never passes the root and
    decreases monotonically to it (h stays positive).  Far above the root each step
    takes at least a quarter off h (the quartic term dominating), near it Newton
    converges quadratically: the fixed iterations reach roots 10^3 below h_c and more
    (rays stopping at once, f = 1e-6, put it 30-70 times below; tested to rounding).
    """
    h = solve_cell_cubic(a, b, c, xp=xp)
    for _ in range(CUBIC_NEWTON_ITERATIONS):
        h2 = h * h
        fx = h2 * (k4 * h2 + (a + k3) * h + (b + k2)) - c
        dfx = h * (4.0 * k4 * h2 + 3.0 * (a + k3) * h + 2.0 * (b + k2))
        h = h - fx / dfx
    return h


def optimal_cell_size(stats: SceneStats, t_step, t_int, *, mailbox=False, overlap="exact",
                      edge=True, area=True, traversed_fraction=1.0):
    """Optimal cubic cell side h* (scene units) of a single-level grid; with
    ``traversed_fraction < 1`` rays stop at their first hit (:func:`termination_coefficients`)."""
    if not (np.all(np.asarray(t_step) > 0) and np.all(np.asarray(t_int) > 0)):
        raise ValueError("t_step and t_int must be > 0")
    r = np.asarray(t_int, dtype=np.float64) / np.asarray(t_step, dtype=np.float64)
    kw = dict(mailbox=mailbox, overlap=overlap, edge=edge, area=area)
    a, b, c = cubic_coefficients(stats, r, **kw)
    if traversed_fraction >= 1.0:
        h = solve_cell_cubic(a, b, c)
    else:
        h = solve_cell_quartic(a, b, c, *termination_coefficients(stats, r, traversed_fraction, **kw))
    return float(h) if np.ndim(h) == 0 else h


def optimal_uniform(stats: SceneStats, t_setup, t_step, t_int, *, mailbox=False, overlap="exact",
                    terms: Terms | None = None, max_per_axis=MAX_CELLS_PER_AXIS,
                    max_total=MAX_TOTAL_CELLS) -> tuple[tuple[int, int, int], float]:
    """Best integer resolution of a single-level grid and its optimal cubic cell size.

    The continuous optimum h* (cubic root; with termination, the quartic's) gives
    ``d_i / h*`` per axis; every floor/ceil combination (clamped like
    :func:`cells_to_resolution`; on a thin axis, fewer than THIN_AXIS_CELLS cells at h*,
    the integers from one below the floor to one above the ceiling) and the clamped talk
    rule are scored with :func:`predict_uniform`, and the cheapest is returned.  A box
    0.9 cells deep at h* may be cheapest 2 cells deep (non-cubic cells; the CAD tray,
    docs/compare.md), which floor/ceil alone never tries.

    Returns
    -------
    ((nx, ny, nz), h_star) : resolution (Python ints) and h* (scene units).
    """
    if terms is None:
        terms = Terms(mailbox=bool(mailbox))
    h = optimal_cell_size(stats, t_step, t_int, mailbox=terms.mailbox, overlap=overlap,
                          edge=terms.edge, area=terms.area, traversed_fraction=terms.traversed_fraction)
    base = cells_to_resolution(stats.volume / h ** 3, stats.extent, max_per_axis=max_per_axis,
                               max_total=max_total)
    cont = np.minimum(stats.extent / h, float(max_per_axis))
    options = [sorted({np.floor(x) - 1, np.floor(x), np.ceil(x), np.ceil(x) + 1}) if x < THIN_AXIS_CELLS
               else (np.floor(x), np.ceil(x)) for x in cont]
    best, best_t = base, predict_uniform(stats, base, t_setup, t_step, t_int, overlap=overlap, terms=terms)[0]
    for cand in itertools.product(*options):
        n = tuple(int(min(max(v, 1), max_per_axis)) for v in cand)
        if n[0] * n[1] * n[2] > max_total:
            continue
        t = predict_uniform(stats, n, t_setup, t_step, t_int, overlap=overlap, terms=terms)[0]
        if t < best_t:
            best, best_t = n, t
    return best, h


def cost_cubic(stats: SceneStats, h, t_setup, t_step, t_int, *, terms: Terms | None = None,
               overlap="exact", xp=np):
    """Predicted ns per ray for cubic cells of continuous side h (no rounding, no clamps).

    The smooth form used by optimisers and by posterior propagation (``xp`` may be
    ``jax.numpy``; every argument broadcasts).  ``steps = 6V/(S h)`` and the tests of
    :func:`tests_polynomial`, both scaled by :func:`cell_fraction` of ``terms.traversed_fraction``.
    """
    if terms is None:
        terms = Terms()
    alpha, beta, gamma, delta = tests_polynomial(stats, mailbox=terms.mailbox, overlap=overlap, edge=terms.edge,
                                                 area=terms.area)
    s = stats.surface
    steps = 6.0 * stats.volume / (s * h)
    tests = 6.0 * (alpha * h * h + beta * h + gamma + delta / h) / s
    g = cell_fraction(terms.traversed_fraction, steps, xp=xp)
    return t_setup + g * (t_step * steps + t_int * tests)

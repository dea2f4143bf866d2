"""Nested (L-level) grids by Crofton composition (DESIGN §3.2).

A line conditioned on hitting a cell is an isotropic uniform line of that cell, so
for a grid whose non-empty cells hold subgrids,

    T = T_setup + T_step * steps_top
        + sum_{non-empty cells c} (S_c / S) * (T_sub + T_c),

where ``T_c`` is the same model applied to the cell's own triangles in the cell's
box.  Unrolled over all levels, the expected counts per ray are

- ``steps    = sum_{grids g} 2 (nz dx dy + nx dy dz + ny dz dx)_g / S``
  (each grid g is reached with probability ``S_g / S`` and then takes its own
  ``2(...)_g / S_g`` steps; the root has ``S_g = S``);
- ``subgrids = sum_{grids g below the root} S_g / S``;
- ``tests    = sum_{leaf cells c} refs(c) S_c / S`` (no mailboxing in subgrids);

and ``T = T_setup + T_step steps + T_int tests + T_sub subgrids``.  These counts are
exact expectations for isotropic lines *given the built structure*; the structure is
built here from the real triangles (no offset averaging), level by level, vectorised
over (triangle, cell) pairs.

Per-cell sub-scenes (approximation, documented): the triangles of a cell are those
whose bounding box overlaps it (``overlap="bbox"``, conservative like a counting-sort
build) or that truly overlap it (``overlap="exact"``, separating-axis test).  Their
statistics restricted to the cell use the bounding-box clip: ``ext`` is the extent
of ``bbox(T) ∩ cell``; the area inside the cell is ``A`` times the fraction of the
bounding box's footprint that survives the clip in T's dominant projection plane.
Each subgrid's resolution comes from its own sub-scene: the last level uses the
general model's cubic optimum ``2 n r h^3 + E1 r h^2 - V = 0`` of the cell;
intermediate levels use the talk's L-level recursion
(:func:`models.closed_forms.l_level_cells`) with the cell's own ``k = E2 / V^(2/3)``.
The top resolution is optimised with nlopt (bounded global DIRECT-L, then a local
BOBYQA polish) on ``log(total cells)``, scoring candidates with analytic leaf counts
(offset-averaged references of each leaf subgrid's sub-scene); the best few are then
re-counted with enumerated leaves.  The objective is piecewise constant in the
resolution (integer cells), so gradients do not help there and none are used.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import nlopt
import numpy as np

from .closed_forms import cells_to_resolution, l_level_cells
from .general import optimal_uniform, solve_cell_cubic
from .stats import SceneStats, TriangleGeometry, grid_box, triangle_geometry

#: Largest number of (triangle, cell) pairs one level may enumerate (memory guard:
#: about 0.5 GiB of temporary index arrays).
MAX_PAIRS = 2 ** 23
#: Clamp on cells per axis of a subgrid (a subgrid fills one parent cell).
MAX_SUBGRID_CELLS_PER_AXIS = 256
#: Clamp on the top-level total cells of a nested grid during the search.
MAX_NESTED_TOP_CELLS = 2 ** 22
#: The search for the top resolution spans 1 cell up to this factor above the talk's
#: L-level closed form (in total cells).
TOP_SEARCH_FACTOR = 64.0
#: nlopt evaluation budgets of the global (DIRECT-L) and local (BOBYQA) stages.
GLOBAL_EVALS = 16
LOCAL_EVALS = 12
#: Candidates re-counted with enumerated leaves after the analytic-leaf search.
FINAL_CANDIDATES = 3
#: Deepest nested grid considered by :func:`choose_levels`.
MAX_LEVELS = 3


class TooManyPairs(ValueError):
    """A level would enumerate more than MAX_PAIRS (triangle, cell) pairs."""


def triangle_box_overlap(tri, lo, hi) -> np.ndarray:
    """Separating-axis test (Akenine-Moller 2001) of triangles against boxes, vectorised.

    Parameters
    ----------
    tri : (P, 3, 3) float64 corners; lo, hi : (P, 3) float64 box corners.

    Returns
    -------
    (P,) bool, True when the closed triangle and the closed box intersect.
    """
    c = 0.5 * (lo + hi)
    hs = 0.5 * (hi - lo)
    v = tri - c[:, None, :]
    ok = np.all(v.min(axis=1) <= hs, axis=1) & np.all(v.max(axis=1) >= -hs, axis=1)
    e = [v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]]
    axes = [np.cross(e[0], v[:, 2] - v[:, 0])]
    for ej in e:
        zero = np.zeros_like(ej[:, 0])
        axes.append(np.stack([zero, -ej[:, 2], ej[:, 1]], axis=1))  # e_x cross ej
        axes.append(np.stack([ej[:, 2], zero, -ej[:, 0]], axis=1))  # e_y cross ej
        axes.append(np.stack([-ej[:, 1], ej[:, 0], zero], axis=1))  # e_z cross ej
    for a in axes:
        p = np.einsum("pkj,pj->pk", v, a)
        rad = np.sum(hs * np.abs(a), axis=1)
        ok &= (p.min(axis=1) <= rad) & (p.max(axis=1) >= -rad)
    return ok


@dataclass(frozen=True)
class LevelInfo:
    """One level of a built nested grid.

    grids : number of (sub)grids at this level; cells : their total cells;
    nonempty : cells holding >= 1 triangle; refs : (triangle, cell) references;
    resolutions : (grids, 3) int64 per-grid resolutions; dispersion : variance/mean
    of per-cell reference counts over all cells of the level (1 for Poisson).
    sub_n, sub_e1, sub_e2 : (nonempty,) sub-scene statistics of the non-empty cells
    (references, clipped E1, clipped E2) when a level below exists, else None;
    sub_extent : (nonempty, 3) their cell extents.
    nonempty_cells : (nonempty,) flat indices of the non-empty cells over the level's
    grids (each grid's cells x fastest, the grids in order) when a level below exists:
    the next level's grids, in order, are these cells' subgrids.
    """

    grids: int
    cells: int
    nonempty: int
    refs: int
    resolutions: np.ndarray
    dispersion: float
    sub_n: np.ndarray | None = None
    sub_e1: np.ndarray | None = None
    sub_e2: np.ndarray | None = None
    sub_extent: np.ndarray | None = None
    nonempty_cells: np.ndarray | None = None


@dataclass(frozen=True)
class NestedCounts:
    """Expected counts per isotropic line hitting the box, and the structure's size."""

    levels: int
    top_resolution: tuple
    steps: float
    tests: float
    subgrids: float
    cells: int
    refs: int
    per_level: list = field(default_factory=list)
    visits: float = 0.0  # occupied leaf cells entered (models.general.occupied_cells at analytic leaves)

    def ns_per_ray(self, t_setup, t_step, t_int, t_sub):
        """``T_setup + T_step steps + T_int tests + T_sub subgrids`` (ns); broadcasts over arrays."""
        return t_setup + t_step * self.steps + t_int * self.tests + t_sub * self.subgrids


def _enumerate_pairs(tri_lo, tri_hi, node_lo, node_cell, node_res):
    """All (pair, cell index) combinations of bbox overlap; arrays per pair (P, 3)."""
    i0 = np.clip(np.floor((tri_lo - node_lo) / node_cell), 0, node_res - 1).astype(np.int64)
    i1 = np.clip(np.floor((tri_hi - node_lo) / node_cell), 0, node_res - 1).astype(np.int64)
    span = i1 - i0 + 1
    cnt = span[:, 0] * span[:, 1] * span[:, 2]
    total = int(cnt.sum())
    if total > MAX_PAIRS:
        raise TooManyPairs(f"{total} triangle-cell pairs exceed MAX_PAIRS={MAX_PAIRS}; lower the resolution")
    src = np.repeat(np.arange(cnt.shape[0]), cnt)
    local = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    sp = span[src]
    ijk = i0[src] + np.stack([local % sp[:, 0], (local // sp[:, 0]) % sp[:, 1],
                              local // (sp[:, 0] * sp[:, 1])], axis=1)
    return src, ijk


def _vector_resolution(total_cells, extent, max_axis):
    """Vectorised cells -> resolution (talk's rule), extents (G, 3), totals (G,)."""
    logd = np.log(extent)
    log_n = logd + ((np.log(np.maximum(total_cells, 1.0)) - logd.sum(axis=1)) / 3.0)[:, None]
    return np.clip(np.rint(np.exp(np.minimum(log_n, np.log(max_axis) + 1.0))), 1, max_axis).astype(np.int64)


def nested_counts(geom: TriangleGeometry, box_lo, box_hi, top_resolution, levels, r, *,
                  overlap="bbox", corners=None, leaves="enumerate", overlap_test=None,
                  separate_fraction=0.0, child_scale=1.0) -> NestedCounts:
    """Build an L-level grid structure from the triangles and return its expected counts.

    Parameters
    ----------
    geom : per-triangle geometry (:func:`models.stats.triangle_geometry`).
    box_lo, box_hi : (3,) the root grid box (use :func:`models.stats.grid_box`).
    top_resolution : (3,) ints.
    levels : L >= 1.  L = 1 is a uniform grid with its *actual* references.
    r : T_int / T_step used to size the subgrids.
    overlap : "bbox" or "exact" (then ``corners`` (F, 3, 3) is required).
    leaves : "enumerate" counts the leaf level's references exactly; "analytic" (L >= 2)
        uses the offset-averaged references of each leaf subgrid's clipped sub-scene
        (:func:`models.general.expected_refs` per subgrid) -- much faster, used while
        searching; ``refs`` is then the expected count.
    overlap_test : optional drop-in for :func:`triangle_box_overlap` (same arguments and
        result), e.g. a compiled one; this module stays free of any kernel.
    separate_fraction : :attr:`models.stats.SceneStats.separate_fraction`, for the occupied
        cells of analytic leaves (:func:`models.general.occupied_cells`, per subgrid).
    child_scale : per-axis factor on the depth-1 subgrids' resolutions (rounded, >= 1),
        for sweeps around a plan; deeper levels are sized for the cells they then get.

    ``visits`` counts the occupied leaf cells a line enters (no termination): exactly the
    non-empty leaf cells' ``S_cell / S`` when the leaves are enumerated, the occupied-cell
    model per subgrid when they are analytic.
    """
    if leaves not in ("enumerate", "analytic"):
        raise ValueError(f"leaves must be 'enumerate' or 'analytic', got {leaves!r}")
    if overlap not in ("bbox", "exact"):
        raise ValueError(f"overlap must be 'bbox' or 'exact', got {overlap!r}")
    if overlap == "exact" and corners is None:
        raise ValueError("overlap='exact' needs the triangle corners (F, 3, 3)")
    if int(levels) != levels or levels < 1:
        raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
    if not r > 0:
        raise ValueError(f"r must be > 0, got {r!r}")
    if not (np.isfinite(child_scale) and child_scale > 0):
        raise ValueError(f"child_scale must be finite and > 0, got {child_scale!r}")
    lo, hi = grid_box(box_lo, box_hi)
    ext_root = hi - lo
    s_root = 2.0 * (ext_root[0] * ext_root[1] + ext_root[1] * ext_root[2] + ext_root[2] * ext_root[0])
    node_lo = lo[None, :]
    node_ext = ext_root[None, :]
    node_res = np.asarray(top_resolution, dtype=np.int64).reshape(1, 3)
    if np.any(node_res < 1):
        raise ValueError(f"top_resolution must be >= 1, got {top_resolution!r}")
    pair_tri = np.arange(geom.area.shape[0])
    pair_node = np.zeros_like(pair_tri)
    sub = None
    steps = subgrids = tests = visits = 0.0
    cells_total = refs_total = 0
    per_level = []
    dominant = np.argmax(geom.proj_area, axis=1)
    for depth in range(int(levels)):
        cell = node_ext / node_res  # (G, 3)
        d = node_ext
        steps += float(np.sum(2.0 * (node_res[:, 2] * d[:, 0] * d[:, 1] + node_res[:, 0] * d[:, 1] * d[:, 2]
                                     + node_res[:, 1] * d[:, 2] * d[:, 0]))) / s_root
        if depth > 0:
            subgrids += float(np.sum(2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]))) / s_root
        ncell = np.prod(node_res, axis=1)
        if depth == levels - 1 and depth > 0 and leaves == "analytic":
            # Offset-averaged references of each leaf grid's sub-scene (models.general), with
            # the per-axis count ``a_i + clip_i / c_i``, ``a_i = 1 - (faces of the cell the
            # clipped box touches on axis i) / 2``: a clipped box starting on a cell face
            # starts on a subgrid plane, so it spans ceil(clip/c) cells, clip/c + 1/2 on average.
            # bbox: sum prod_i (a_i + clip_i / c_i), expanded into the per-subgrid sums ``sub``.
            # exact: the same linear terms plus the clipped projected areas (no corner terms).
            s0, s1, s2, s3, e2_s = sub
            inv = 1.0 / cell
            if overlap == "bbox":
                refs = (s0 + np.sum(s1 * inv, axis=1)
                        + np.sum(s2 * inv[:, [1, 2, 0]] * inv[:, [2, 0, 1]], axis=1) + s3 * np.prod(inv, axis=1))
            else:
                cc = np.stack([cell[:, 1] * cell[:, 2], cell[:, 2] * cell[:, 0], cell[:, 0] * cell[:, 1]], axis=1)
                refs = s0 + np.sum(s1 * inv, axis=1) + np.sum(e2_s / cc, axis=1)
            cc = np.stack([cell[:, 1] * cell[:, 2], cell[:, 2] * cell[:, 0], cell[:, 0] * cell[:, 1]], axis=1)
            s_cell = 2.0 * cc.sum(axis=1)
            tests += float(np.sum(refs * s_cell)) / s_root
            # occupied cells of each leaf grid: its sub-scene's projected area, plus the
            # linear terms as far as its triangles are separate (models.general.occupied_cells)
            r_occ = np.sum(e2_s / cc, axis=1) + float(separate_fraction) * (s0 + np.sum(s1 * inv, axis=1))
            n_cells = ncell.astype(np.float64)
            visits += float(np.sum(-n_cells * np.expm1(-r_occ / n_cells) * s_cell)) / s_root
            refs_total = int(round(float(refs.sum())))
            cells_total += int(ncell.sum())
            per_level.append(LevelInfo(grids=int(node_res.shape[0]), cells=int(ncell.sum()), nonempty=-1,
                                       refs=refs_total, resolutions=node_res.copy(), dispersion=float("nan")))
            break
        offset = np.concatenate([[0], np.cumsum(ncell)[:-1]])
        src, ijk = _enumerate_pairs(geom.lo[pair_tri], geom.hi[pair_tri], node_lo[pair_node],
                                    cell[pair_node], node_res[pair_node])
        tri = pair_tri[src]
        node = pair_node[src]
        c_lo = node_lo[node] + ijk * cell[node]
        c_hi = c_lo + cell[node]
        if overlap == "exact":
            keep = (overlap_test or triangle_box_overlap)(corners[tri], c_lo, c_hi)
            tri, node, ijk, c_lo, c_hi = tri[keep], node[keep], ijk[keep], c_lo[keep], c_hi[keep]
        res_n = node_res[node]
        flat = offset[node] + ijk[:, 0] + res_n[:, 0] * (ijk[:, 1] + res_n[:, 1] * ijk[:, 2])
        n_cells = int(ncell.sum())
        counts = np.bincount(flat, minlength=n_cells)
        mean = counts.mean()
        dispersion = float(counts.var() / mean) if mean > 0 else 0.0
        cells_total += n_cells
        nonempty_ids = np.flatnonzero(counts)
        info = LevelInfo(grids=int(node_res.shape[0]), cells=n_cells, nonempty=int(nonempty_ids.size),
                         refs=int(tri.size), resolutions=node_res.copy(), dispersion=dispersion)
        if depth == levels - 1:
            per_level.append(info)
            s_cell_of_pair = 2.0 * (cell[node, 0] * cell[node, 1] + cell[node, 1] * cell[node, 2]
                                    + cell[node, 2] * cell[node, 0])
            tests += float(np.sum(s_cell_of_pair)) / s_root
            refs_total = int(tri.size)
            occ_cell = np.searchsorted(offset, nonempty_ids, side="right") - 1  # the grid of each occupied cell
            c_occ = cell[occ_cell]
            visits += float(np.sum(2.0 * (c_occ[:, 0] * c_occ[:, 1] + c_occ[:, 1] * c_occ[:, 2]
                                          + c_occ[:, 2] * c_occ[:, 0]))) / s_root
            break
        # Sub-scenes of the non-empty cells (bounding-box clip, see module docstring).
        clip = np.maximum(np.minimum(geom.hi[tri], c_hi) - np.maximum(geom.lo[tri], c_lo), 0.0)
        ext_t = geom.ext[tri]
        ratio = np.where(ext_t > 0, clip / np.where(ext_t > 0, ext_t, 1.0), 1.0)
        dom = dominant[tri]
        a1, a2 = (dom + 1) % 3, (dom + 2) % 3
        idx = np.arange(tri.size)
        frac = ratio[idx, a1] * ratio[idx, a2]
        child_of_cell = np.full(n_cells, -1, dtype=np.int64)
        child_of_cell[nonempty_ids] = np.arange(nonempty_ids.size)
        child = child_of_cell[flat]
        g = nonempty_ids.size
        n_c = counts[nonempty_ids].astype(np.float64)
        e1_ax = np.stack([np.bincount(child, weights=clip[:, i], minlength=g) for i in range(3)], axis=1)
        e2_ax = np.stack([np.bincount(child, weights=geom.proj_area[tri, i] * frac, minlength=g)
                          for i in range(3)], axis=1)
        e1_c, e2_c = e1_ax.sum(axis=1), e2_ax.sum(axis=1)
        if leaves == "analytic" and depth == levels - 2:
            # faces of its cell each clipped box touches, per axis (0, 1 or 2)
            touch = ((geom.lo[tri] <= c_lo).astype(np.float64) + (geom.hi[tri] >= c_hi).astype(np.float64))
            a = 1.0 - 0.5 * touch  # (P, 3)
            if overlap == "exact":  # linear correction only
                s0 = np.bincount(child, weights=1.0 + np.sum(a - 1.0, axis=1), minlength=g)
                s1 = e1_ax
                s2 = s3 = None
            else:  # sums of the expanded product prod_i (a_i + clip_i / c_i)
                j, k = [1, 2, 0], [2, 0, 1]
                s0 = np.bincount(child, weights=np.prod(a, axis=1), minlength=g)
                s1 = np.stack([np.bincount(child, weights=clip[:, i] * a[:, j[i]] * a[:, k[i]], minlength=g)
                               for i in range(3)], axis=1)
                s2 = np.stack([np.bincount(child, weights=clip[:, j[i]] * clip[:, k[i]] * a[:, i], minlength=g)
                               for i in range(3)], axis=1)
                s3 = np.bincount(child, weights=np.prod(clip, axis=1), minlength=g)
            sub = (s0, s1, s2, s3, e2_ax)
        # Child boxes: the parent cells.
        cell_node = np.searchsorted(offset, nonempty_ids, side="right") - 1
        local = nonempty_ids - offset[cell_node]
        rn = node_res[cell_node]
        cijk = np.stack([local % rn[:, 0], (local // rn[:, 0]) % rn[:, 1], local // (rn[:, 0] * rn[:, 1])], axis=1)
        child_ext = cell[cell_node]
        child_lo = node_lo[cell_node] + cijk * child_ext
        v_c = np.prod(child_ext, axis=1)
        per_level.append(replace(info, sub_n=n_c, sub_e1=e1_c, sub_e2=e2_c, sub_extent=child_ext,
                                 nonempty_cells=nonempty_ids))
        remaining = levels - depth - 1
        if remaining == 1:
            h = solve_cell_cubic(2.0 * n_c * r, r * e1_c, v_c)
            child_res = np.clip(np.rint(child_ext / h[:, None]), 1, MAX_SUBGRID_CELLS_PER_AXIS).astype(np.int64)
        else:
            k_c = np.maximum(e2_c / v_c ** (2.0 / 3.0), 1e-3)
            m3 = l_level_cells(n_c, r, remaining, k_c, kind="points")[0]
            child_res = _vector_resolution(m3, child_ext, MAX_SUBGRID_CELLS_PER_AXIS)
        if depth == 0 and child_scale != 1.0:  # as calibrate.sweep.GridSpec scales a plan's subgrids
            child_res = np.clip(np.rint(child_res * float(child_scale)), 1, 2**31 - 1).astype(np.int64)
        node_lo, node_ext, node_res = child_lo, child_ext, child_res
        pair_tri, pair_node = tri, child
    return NestedCounts(levels=int(levels), top_resolution=tuple(int(x) for x in np.asarray(top_resolution)),
                        steps=steps, tests=tests, subgrids=subgrids, cells=cells_total, refs=refs_total,
                        per_level=per_level, visits=visits)


@dataclass(frozen=True)
class NestedPlan:
    """Result of :func:`optimal_nested`: the best top resolution for L levels."""

    levels: int
    top_resolution: tuple
    ns_per_ray: float
    counts: NestedCounts
    evaluations: int


def optimal_nested(vertices, faces, stats: SceneStats, t_setup, t_step, t_int, t_sub, levels, *,
                   overlap="bbox", seed=0, geom: TriangleGeometry | None = None) -> NestedPlan:
    """Optimise the top resolution of an L-level grid (nlopt on log total cells).

    Parameters
    ----------
    vertices (V, 3) float64, faces (F, 3) int64 : the mesh (``geom`` may be passed instead
        of recomputing per-triangle geometry; ``vertices``/``faces`` are still needed for
        ``overlap="exact"``).
    stats : its SceneStats (box, N, k).
    t_setup, t_step, t_int, t_sub : ns.
    levels : L >= 1.  L = 1 uses the analytic uniform optimum (no enumeration).
    seed : nlopt's random seed (DIRECT-L is deterministic; kept for reproducibility).
    """
    if not (t_step > 0 and t_int > 0 and t_setup >= 0 and t_sub >= 0):
        raise ValueError("need t_step > 0, t_int > 0, t_setup >= 0, t_sub >= 0")
    if geom is None:
        geom = triangle_geometry(vertices, faces)
    corners = None
    if overlap == "exact":
        corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    r = t_int / t_step
    if levels == 1:
        res, _ = optimal_uniform(stats, t_setup, t_step, t_int)
        counts = nested_counts(geom, stats.box_lo, stats.box_hi, res, 1, r, overlap=overlap, corners=corners)
        return NestedPlan(1, res, float(counts.ns_per_ray(t_setup, t_step, t_int, t_sub)), counts, 1)
    k = max(stats.k, 1e-3)
    centre = float(l_level_cells(stats.n_triangles, r, levels, k, kind="points")[0])
    lo_m = 1.0  # a 1x1x1 top grid is a single-level grid behind one subgrid entry
    hi_m = max(min(centre * TOP_SEARCH_FACTOR, MAX_NESTED_TOP_CELLS), lo_m * 2.0)
    cache: dict = {}

    def evaluate(log_m):
        res = cells_to_resolution(np.exp(log_m), stats.extent, max_total=MAX_NESTED_TOP_CELLS)
        if res not in cache:
            try:
                c = nested_counts(geom, stats.box_lo, stats.box_hi, res, levels, r, overlap=overlap,
                                  corners=corners, leaves="analytic")
                cache[res] = (float(c.ns_per_ray(t_setup, t_step, t_int, t_sub)), c)
            except TooManyPairs:
                cache[res] = (np.inf, None)
        return cache[res][0]

    def objective(x, grad):
        t = evaluate(float(x[0]))
        return t if np.isfinite(t) else 1e300

    nlopt.srand(int(seed))
    bounds = (np.log(lo_m), np.log(hi_m))
    x0 = float(np.clip(np.log(centre), *bounds))
    best_x = x0
    for alg, evals in ((nlopt.GN_DIRECT_L, GLOBAL_EVALS), (nlopt.LN_BOBYQA, LOCAL_EVALS)):
        opt = nlopt.opt(alg, 1)
        opt.set_lower_bounds([bounds[0]])
        opt.set_upper_bounds([bounds[1]])
        opt.set_min_objective(objective)
        opt.set_maxeval(evals)
        opt.set_xtol_abs(1e-3)
        if alg == nlopt.LN_BOBYQA:
            opt.set_initial_step([0.25])
        try:
            best_x = float(opt.optimize([best_x])[0])
        except (nlopt.RoundoffLimited, RuntimeError):
            pass
    finite = sorted((v[0], res) for res, v in cache.items() if np.isfinite(v[0]))
    if not finite:
        raise ValueError("no candidate top resolution fits within MAX_PAIRS; scene too large for nested search")
    # Re-count the best few candidates with enumerated leaves (exact for the built structure).
    best = None
    for _, res in finite[:FINAL_CANDIDATES]:
        try:
            c = nested_counts(geom, stats.box_lo, stats.box_hi, res, levels, r, overlap=overlap, corners=corners)
        except TooManyPairs:
            continue
        t = float(c.ns_per_ray(t_setup, t_step, t_int, t_sub))
        if best is None or t < best[0]:
            best = (t, res, c)
    if best is None:  # leaves too many to enumerate: keep the analytic leaf counts
        t, res = finite[0]
        best = (t, res, cache[res][1])
    t, res, counts = best
    return NestedPlan(int(levels), res, t, counts, len(cache))


def choose_levels(vertices, faces, stats: SceneStats, t_setup, t_step, t_int, t_sub, *,
                  max_levels=MAX_LEVELS, overlap="bbox") -> tuple[NestedPlan, list]:
    """Depth L in 1..max_levels minimising predicted ns per ray (T_sub included).

    Returns ``(best_plan, all_plans)``.
    """
    geom = triangle_geometry(vertices, faces)
    plans = [optimal_nested(vertices, faces, stats, t_setup, t_step, t_int, t_sub, L, overlap=overlap, geom=geom)
             for L in range(1, int(max_levels) + 1)]
    return min(plans, key=lambda p: p.ns_per_ray), plans


def _child_cost_ns(n, e1, e2, extent, t_step, t_int):
    """Analytic cost (ns, setup excluded) of single-level subgrids at their continuous optimum.

    Cubic cells of side h (the cubic root), ``steps = 6 V/(S h)``,
    ``tests = 6 (n h^2 + E1 h + E2) / S`` per line hitting the cell; arrays (G,).
    """
    r = t_int / t_step
    v = np.prod(extent, axis=-1)
    s = 2.0 * (extent[..., 0] * extent[..., 1] + extent[..., 1] * extent[..., 2] + extent[..., 2] * extent[..., 0])
    h = np.minimum(solve_cell_cubic(2.0 * n * r, r * e1, v), np.max(extent, axis=-1))
    return t_step * 6.0 * v / (s * h) + t_int * 6.0 * (n * h * h + e1 * h + e2) / s


def clustering_change(counts: NestedCounts, stats: SceneStats, t_step, t_int, total_ns) -> float | None:
    """Relative change of a 2-level prediction if every subgrid held the *mean* sub-scene.

    The talk's 2-level law assumes equal cells; the composition uses each cell's own
    triangles.  Both sides use the analytic single-level subgrid cost
    (:func:`_child_cost_ns`), so the difference is the clustering (Jensen) effect alone.
    Returns None for L = 1 (no subgrids) or when the top level has no sub-scenes.
    """
    if counts.levels < 2:
        return None
    top = counts.per_level[0]
    if top.sub_n is None or top.sub_n.size == 0:
        return None
    ext = top.sub_extent
    s_c = 2.0 * (ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0])
    w = s_c / stats.surface
    own = float(np.sum(w * _child_cost_ns(top.sub_n, top.sub_e1, top.sub_e2, ext, t_step, t_int)))
    mean = float(np.sum(w) * _child_cost_ns(top.sub_n.mean(), top.sub_e1.mean(), top.sub_e2.mean(),
                                            ext.mean(axis=0), t_step, t_int))
    return abs(own - mean) / float(total_ns)


def manta_level_resolution(n, extent, levels, depth, scale=8.0) -> tuple[int, int, int]:
    """Per-level rule used by the kernels (Manta RecursiveGrid): per axis
    ``m = (scale n)^(1/(2L+1-2 depth))``, i.e. ``(scale n)^(3/(2L+1-2 depth))`` cells,
    turned into a resolution for ``extent`` (3,)."""
    from .baselines import manta_level_cells

    return cells_to_resolution(manta_level_cells(n, levels, depth, scale), extent)


"""Nested grids: the separating-axis test, the Crofton composition against Monte Carlo, the search."""

from __future__ import annotations

import numpy as np
import pytest
from test_models_general import cell_boxes, mesh_of, random_triangles, sample_lines, visited_cells

from models.closed_forms import cells_to_resolution
from models.general import optimal_uniform, steps_per_ray
from models.nested import (choose_levels, clustering_change, nested_counts, optimal_nested,
                           triangle_box_overlap)
from models.stats import grid_box, scene_stats, stats_from_geometry, triangle_geometry


@pytest.mark.parametrize("i", range(3))
def test_separating_axis_against_sampling(i):
    """No false negatives (a sampled triangle point inside the box) and no false positives
    (every accepted pair has a sampled triangle point within the sampling spacing of the box)."""
    rng = np.random.default_rng(5000 + i)
    n = 3000
    tri = rng.normal(size=(n, 3, 3)) * rng.uniform(0.1, 1.0, (n, 1, 1))
    lo = rng.uniform(-1, 0.5, (n, 3))
    hi = lo + rng.uniform(0.05, 1.0, (n, 3))
    got = triangle_box_overlap(tri, lo, hi)
    k = 60  # barycentric samples per edge
    a, b = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
    keep = a + b <= k
    u, v = a[keep] / k, b[keep] / k
    pts = tri[:, 0, None] + u[None, :, None] * (tri[:, 1] - tri[:, 0])[:, None] + v[None, :, None] * (
        tri[:, 2] - tri[:, 0])[:, None]
    gap = np.maximum(np.maximum(lo[:, None] - pts, pts - hi[:, None]), 0)
    dist = np.sqrt((gap ** 2).sum(axis=2)).min(axis=1)
    spacing = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1) / k
    assert not np.any(~got & (dist == 0))  # no false negatives
    assert not np.any(got & (dist > spacing))  # no false positives beyond sampling resolution
    assert 0.1 < got.mean() < 0.9


def test_separating_axis_edge_case():
    """A triangle beside a box corner, separated only by an edge-cross-product axis."""
    lo, hi = np.zeros((1, 3)), np.ones((1, 3))
    tri = np.array([[[1.6, 0.5, -1.0], [0.5, 1.6, -1.0], [1.05, 1.05, 3.0]]])
    # all three box-axis tests pass (bboxes overlap) but the triangle misses the corner edge x=y=1
    assert not triangle_box_overlap(tri, lo, hi)[0]
    assert triangle_box_overlap(tri - 0.2, lo, hi)[0]


def test_single_level_counts_match_the_identity():
    rng = np.random.default_rng(5100)
    extent = np.array([2.0, 1.0, 3.0])
    tri = random_triangles(rng, 200, extent, 0.1)
    g = triangle_geometry(*mesh_of(tri))
    res = (6, 3, 9)
    c = nested_counts(g, [0, 0, 0], extent, res, 1, 4.0)
    assert c.steps == pytest.approx(steps_per_ray(extent, res), rel=1e-12)
    lo, hi = cell_boxes(extent, res)
    occ = np.all((g.lo[None] <= hi[:, None]) & (g.hi[None] >= lo[:, None]), axis=2)
    cell = extent / np.array(res)
    s_cell = 2 * (cell[0] * cell[1] + cell[1] * cell[2] + cell[2] * cell[0])
    s_box = 2 * (2 + 3 + 6.0)
    assert c.refs == occ.sum()
    assert c.tests == pytest.approx(occ.sum() * s_cell / s_box, rel=1e-12)
    assert c.subgrids == 0.0


def _entry_point(o, w, lo, hi):
    """Entry parameter of lines into boxes (per line), assuming they hit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / w, (hi - o) / w
    return np.nanmax(np.minimum(t1, t2), axis=1)


@pytest.mark.parametrize("i, overlap", [(0, "bbox"), (1, "exact")])
def test_two_level_crofton_composition_matches_monte_carlo(i, overlap):
    """Traverse the built 2-level structure with random lines; compare steps, tests, subgrids."""
    rng = np.random.default_rng(5200 + i)
    extent = np.array([2.0, 2.0, 1.0])
    tri = random_triangles(rng, 150, extent, 0.12)
    v, f = mesh_of(tri)
    g = triangle_geometry(v, f)
    top = (3, 3, 2)
    counts = nested_counts(g, [0, 0, 0], extent, top, 2, 6.0, overlap=overlap, corners=tri)
    lvl0, lvl1 = counts.per_level
    # rebuild the top-level occupancy independently
    lo, hi = cell_boxes(extent, top)
    occ = np.all((g.lo[None] <= hi[:, None]) & (g.hi[None] >= lo[:, None]), axis=2)
    if overlap == "exact":
        nc, t = lo.shape[0], tri.shape[0]
        occ &= triangle_box_overlap(np.repeat(tri, nc, 0), np.tile(lo, (t, 1)), np.tile(hi, (t, 1))).reshape(t, nc).T
    nonempty = np.flatnonzero(occ.any(axis=1))
    assert lvl0.nonempty == nonempty.size and lvl1.grids == nonempty.size
    n_rays = 40_000
    o, w = sample_lines(rng, extent, n_rays)
    cells, top_steps = visited_cells(o, w, extent, top)
    steps = top_steps.astype(float)
    tests = np.zeros(n_rays)
    subgrids = np.zeros(n_rays)
    for gi, cid in enumerate(nonempty):
        res = lvl1.resolutions[gi]
        through = np.any(cells == cid, axis=1)
        oo, ww = o[through], w[through]
        t_in = _entry_point(oo, ww, lo[cid], hi[cid])
        local = np.clip(oo + t_in[:, None] * ww - lo[cid], 0, hi[cid] - lo[cid])
        sub_cells, sub_steps = visited_cells(local, ww, hi[cid] - lo[cid], res)
        slo, shi = cell_boxes(hi[cid] - lo[cid], res)
        slo, shi = slo + lo[cid], shi + lo[cid]
        mine = np.flatnonzero(occ[cid])
        socc = np.all((g.lo[mine][None] <= shi[:, None]) & (g.hi[mine][None] >= slo[:, None]), axis=2)
        if overlap == "exact":
            ns, t = slo.shape[0], mine.size
            socc &= triangle_box_overlap(np.repeat(tri[mine], ns, 0), np.tile(slo, (t, 1)),
                                         np.tile(shi, (t, 1))).reshape(t, ns).T
        refs = socc.sum(axis=1)
        steps[through] += sub_steps
        subgrids[through] += 1
        tests[through] += np.where(sub_cells >= 0, refs[np.maximum(sub_cells, 0)], 0).sum(axis=1)
    assert subgrids.mean() == pytest.approx(counts.subgrids, rel=0.02)
    assert steps.mean() == pytest.approx(counts.steps, rel=0.02)
    assert tests.mean() == pytest.approx(counts.tests, rel=0.03)


def _sphere(subdivisions=4):
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def test_optimal_nested_matches_a_scan():
    v, f = _sphere(3)
    s = scene_stats(v, f)
    g = triangle_geometry(v, f)
    t = dict(t_setup=20.0, t_step=2.0, t_int=8.0, t_sub=10.0)
    plan = optimal_nested(v, f, s, *t.values(), 2, geom=g)
    scan = []
    for m in np.exp(np.linspace(0.0, np.log(8000), 30)):
        res = cells_to_resolution(m, s.extent)
        c = nested_counts(g, s.box_lo, s.box_hi, res, 2, t["t_int"] / t["t_step"])
        scan.append(c.ns_per_ray(*t.values()))
    assert plan.ns_per_ray <= min(scan) * 1.01
    assert plan.evaluations <= 40


def test_choose_levels_by_predicted_cost():
    v, f = _sphere(4)
    s = scene_stats(v, f)
    best, plans = choose_levels(v, f, s, 20.0, 2.0, 8.0, 1e6, max_levels=2)
    assert best.levels == 1  # a subgrid entry of 1 ms never pays
    best, plans = choose_levels(v, f, s, 20.0, 2.0, 8.0, 0.0, max_levels=2)
    assert best.levels == 2  # free subgrids on a manifold: the talk's 2-level gain (small at N = 5k)
    assert plans[1].ns_per_ray < plans[0].ns_per_ray


def test_clustering_change_zero_for_identical_cells_positive_for_clusters():
    # identical cells: one small triangle at the same place in every cell of a 4^3 top grid
    base = np.array([[0.1, 0.1, 0.1], [0.15, 0.1, 0.1], [0.1, 0.15, 0.12]])
    tri = np.array([base + np.array(ijk) for ijk in np.ndindex(4, 4, 4)])
    v, f = mesh_of(tri)
    s = stats_from_geometry(triangle_geometry(v, f), [0, 0, 0], [4, 4, 4])
    c = nested_counts(triangle_geometry(v, f), s.box_lo, s.box_hi, (4, 4, 4), 2, 5.0)
    assert clustering_change(c, s, 1.0, 5.0, 100.0) == pytest.approx(0.0, abs=1e-12)
    # clustered: 500 triangles in one cell, 1 in each of three others
    rng = np.random.default_rng(5300)
    dense = 0.2 + rng.uniform(0, 0.5, (500, 1, 3)) + rng.normal(size=(500, 3, 3)) * 0.02
    sparse = np.array([base + np.array([3, 3, 3]), base + np.array([0, 3, 0]), base + np.array([3, 0, 0])])
    tri = np.concatenate([dense, sparse])
    v, f = mesh_of(tri)
    g = triangle_geometry(v, f)
    s = stats_from_geometry(g, [0, 0, 0], [4, 4, 4])
    c = nested_counts(g, s.box_lo, s.box_hi, (4, 4, 4), 2, 5.0)
    assert clustering_change(c, s, 1.0, 5.0, c.ns_per_ray(10, 1, 5, 5)) > 0.05
    assert c.per_level[0].dispersion > 10


def test_uniform_single_level_plan_agrees_with_analytic_optimum():
    v, f = _sphere(3)
    s = scene_stats(v, f)
    plan = optimal_nested(v, f, s, 20.0, 2.0, 8.0, 5.0, 1)
    assert plan.top_resolution == optimal_uniform(s, 20.0, 2.0, 8.0)[0]
    assert plan.counts.subgrids == 0.0


def test_bad_nested_input():
    v, f = _sphere(1)
    s = scene_stats(v, f)
    g = triangle_geometry(v, f)
    lo, hi = grid_box(s.box_lo, s.box_hi)
    with pytest.raises(ValueError):
        nested_counts(g, lo, hi, (2, 2, 2), 0, 1.0)
    with pytest.raises(ValueError):
        nested_counts(g, lo, hi, (2, 2, 2), 2, 1.0, overlap="exact")  # corners missing
    with pytest.raises(ValueError):
        optimal_nested(v, f, s, 1.0, 0.0, 1.0, 1.0, 2)

"""The general model: Monte Carlo checks of the counts, reductions to the talk's laws, optimum, limits.

The Monte Carlo helpers sample isotropic uniform random lines hitting a box (a uniform
point on the surface, a cosine-weighted inward direction) and find the cells each line
visits by exact geometry; ``tests/test_models_nested.py`` imports them.
"""

from __future__ import annotations

import itertools

from dataclasses import replace

import numpy as np
import pytest

from models.closed_forms import MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS, lines_cells, points_cells
from models.general import (Terms, cell_fraction, cost_cubic, cubic_coefficients, expected_refs, optimal_cell_size,
                            optimal_uniform, predict_uniform, solve_cell_cubic, steps_per_ray, termination_coefficients,
                            triangle_tests_per_ray)
from models.nested import triangle_box_overlap
from models.stats import scene_stats, stats_from_geometry, triangle_geometry


# --- Monte Carlo helpers ----------------------------------------------------------------

def sample_lines(rng, extent, n):
    """Isotropic uniform random lines hitting the box [0, extent].

    Returns origins (n, 3) on the box surface and unit inward directions (n, 3).
    """
    d = np.asarray(extent, dtype=np.float64)
    face_area = np.array([d[1] * d[2], d[2] * d[0], d[0] * d[1]])
    axis = rng.choice(3, size=n, p=face_area / face_area.sum())
    side = rng.integers(0, 2, size=n)
    o = rng.uniform(0, 1, (n, 3)) * d
    rows = np.arange(n)
    o[rows, axis] = side * d[axis]
    u1, u2 = rng.uniform(size=n), rng.uniform(size=n)
    cos_t, sin_t, phi = np.sqrt(u1), np.sqrt(1 - u1), 2 * np.pi * u2
    w = np.empty((n, 3))
    w[rows, axis] = np.where(side == 0, cos_t, -cos_t)
    w[rows, (axis + 1) % 3] = sin_t * np.cos(phi)
    w[rows, (axis + 2) % 3] = sin_t * np.sin(phi)
    return o, w


def chord_end(o, w, extent):
    """Parameter t at which each line leaves the box (n,)."""
    d = np.asarray(extent, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(w > 0, (d - o) / w, np.where(w < 0, -o / w, np.inf))
    return t.min(axis=1)


def visited_cells(o, w, extent, res):
    """Cells each line visits: (n, K) flat ids ``i + nx (j + ny k)`` (-1 padding), and (n,) counts.

    Sorts the line's crossings of interior cell planes; the midpoint of each segment
    names a visited cell.
    """
    d = np.asarray(extent, dtype=np.float64)
    res = np.asarray(res)
    c = d / res
    t_out = chord_end(o, w, d)
    ts = [np.zeros((o.shape[0], 1))]
    for i in range(3):
        k = np.arange(1, res[i])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (k[None, :] * c[i] - o[:, i:i + 1]) / w[:, i:i + 1]
        ts.append(np.where((t > 0) & (t < t_out[:, None]), t, np.inf))
    t = np.sort(np.concatenate(ts, axis=1), axis=1)
    t_next = np.minimum(np.concatenate([t[:, 1:], np.full((o.shape[0], 1), np.inf)], axis=1), t_out[:, None])
    valid = np.isfinite(t) & (t < t_out[:, None])
    mid = 0.5 * (np.where(valid, t, 0) + np.where(valid, t_next, 0))
    p = o[:, None, :] + mid[:, :, None] * w[:, None, :]
    ijk = np.clip(np.floor(p / c).astype(np.int64), 0, res - 1)
    flat = ijk[..., 0] + res[0] * (ijk[..., 1] + res[1] * ijk[..., 2])
    return np.where(valid, flat, -1), valid.sum(axis=1)


def cell_boxes(extent, res):
    """(C, 3) lo and hi of every cell, flat order ``i + nx (j + ny k)``."""
    c = np.asarray(extent, dtype=np.float64) / np.asarray(res)
    idx = np.arange(int(np.prod(res)))
    ijk = np.stack([idx % res[0], (idx // res[0]) % res[1], idx // (res[0] * res[1])], axis=1)
    return ijk * c, ijk * c + c


def random_triangles(rng, n, extent, scale, skinny=False, margin=0.25):
    """n triangles with centres in the box's inner region and corners kept inside the box."""
    d = np.asarray(extent, dtype=np.float64)
    cen = rng.uniform(margin, 1 - margin, (n, 3)) * d
    off = rng.normal(size=(n, 3, 3)) * scale
    if skinny:
        off[:, :, 1:] *= 0.05
    return np.clip(cen[:, None, :] + off, 0, d)


def mesh_of(tri):
    return tri.reshape(-1, 3), np.arange(tri.shape[0] * 3).reshape(-1, 3)


# --- steps ------------------------------------------------------------------------------------

@pytest.mark.parametrize("i, extent, res", [
    (0, (1, 1, 1), (4, 4, 4)),
    (1, (1.0, 2.0, 3.0), (4, 5, 6)),
    (2, (1, 10, 100), (2, 5, 30)),
    (3, (1, 1, 0.01), (8, 8, 1)),
    (4, (3, 1, 1), (1, 1, 1)),
])
def test_steps_match_monte_carlo(i, extent, res):
    rng = np.random.default_rng(3000 + i)
    o, w = sample_lines(rng, extent, 100_000)
    _, count = visited_cells(o, w, extent, res)
    assert count.mean() == pytest.approx(steps_per_ray(extent, res), rel=0.01)


def test_steps_cube_is_m():
    for m in (1, 3, 17, 1000):
        assert steps_per_ray([2.5] * 3, (m, m, m)) == pytest.approx(m)


# --- tests per ray ------------------------------------------------------------------------------

@pytest.mark.parametrize("i", range(3))
def test_tests_identity_on_a_fixed_grid(i):
    """tests = sum_cells refs(c) S_c / S for the actual per-cell references (exact and bbox)."""
    rng = np.random.default_rng(3100 + i)
    extent, res = np.array([1.0, 2.0, 1.5]), (4, 6, 5)
    tri = random_triangles(rng, 60, extent, 0.15, skinny=(i == 2))
    lo, hi = cell_boxes(extent, res)
    nc, t = lo.shape[0], tri.shape[0]
    exact = triangle_box_overlap(np.repeat(tri, nc, 0), np.tile(lo, (t, 1)), np.tile(hi, (t, 1))).reshape(t, nc).T
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    bbox = np.all((tlo[None] <= hi[:, None]) & (thi[None] >= lo[:, None]), axis=2)
    o, w = sample_lines(rng, extent, 60_000)
    cells, _ = visited_cells(o, w, extent, res)
    c = extent / np.array(res)
    s_cell = 2 * (c[0] * c[1] + c[1] * c[2] + c[2] * c[0])
    s_box = 2 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    for occ in (exact, bbox):
        refs = occ.sum(axis=1)
        mc = np.where(cells >= 0, refs[np.maximum(cells, 0)], 0).sum(axis=1).mean()
        assert mc == pytest.approx(refs.sum() * s_cell / s_box, rel=0.02)
    assert np.all(bbox >= exact)  # the separating-axis test never adds a cell bbox overlap rejects


def _lattice_cells(tri, c, offset):
    """Cells of the infinite lattice ``offset + k c`` that the triangle truly overlaps."""
    lo = np.floor((tri.min(axis=0) - offset) / c).astype(int)
    hi = np.floor((tri.max(axis=0) - offset) / c).astype(int)
    k = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    box_lo = offset + k * c
    return int(triangle_box_overlap(np.repeat(tri[None], len(k), 0), box_lo, box_lo + c).sum()), int(len(k))


@pytest.mark.parametrize("i, scale, skinny, cells", [
    (0, 0.3, False, (1.0, 1.0, 1.0)),
    (1, 1.5, False, (1.0, 1.0, 1.0)),
    (2, 2.0, True, (1.0, 1.0, 1.0)),
    (3, 1.0, False, (0.5, 1.0, 2.0)),
])
def test_expected_cells_per_triangle_offset_average(i, scale, skinny, cells):
    """E[cells(T)] over a random grid offset: exact 1 + sum ext/c + sum A|n_i|/(c_j c_k); bbox prod(1 + ext/c)."""
    rng = np.random.default_rng(3200 + i)
    c = np.array(cells)
    got_exact, got_bbox, want_exact, want_bbox = [], [], [], []
    for _ in range(1000):
        tri = rng.normal(size=(3, 3)) * scale
        if skinny:
            tri[:, 1:] *= 0.05
        tri = tri @ np.linalg.qr(rng.normal(size=(3, 3)))[0] if skinny else tri
        ne, nb = _lattice_cells(tri, c, rng.uniform(0, 1, 3) * c)
        got_exact.append(ne)
        got_bbox.append(nb)
        g = triangle_geometry(*mesh_of(tri[None]))
        ext = g.ext[0]
        cc = np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])
        want_exact.append(1 + np.sum(ext / c) + np.sum(g.proj_area[0] / cc))
        want_bbox.append(np.prod(1 + ext / c))
    # paired differences: the mean must vanish within 4 standard errors (and 3%)
    for got, want in ((got_exact, want_exact), (got_bbox, want_bbox)):
        diff = np.asarray(got) - np.asarray(want)
        se = diff.std(ddof=1) / np.sqrt(diff.size)
        assert abs(diff.mean()) < 4 * se
        assert abs(diff.mean()) < 0.03 * np.mean(want)


def test_expected_refs_formula_matches_stats():
    rng = np.random.default_rng(3300)
    tri = random_triangles(rng, 50, (2, 2, 2), 0.2)
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], [2, 2, 2])
    g = triangle_geometry(*mesh_of(tri))
    res = (5, 7, 9)
    c = 2.0 / np.array(res)
    cc = np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])
    want = np.sum(1 + (g.ext / c).sum(axis=1) + (g.proj_area / cc).sum(axis=1))
    assert expected_refs(s, res) == pytest.approx(want, rel=1e-12)
    assert expected_refs(s, res, overlap="bbox") == pytest.approx(np.sum(np.prod(1 + g.ext / c, axis=1)), rel=1e-12)


def _mailbox_mc(rng, tri, extent, res, occ, n_rays):
    o, w = sample_lines(rng, extent, n_rays)
    cells, _ = visited_cells(o, w, extent, res)
    hit = np.zeros((n_rays, tri.shape[0]), dtype=bool)
    for k in range(cells.shape[1]):
        cc = cells[:, k]
        m = cc >= 0
        hit[m] |= occ[cc[m]]
    return hit.sum(axis=1).mean()


@pytest.mark.parametrize("i", range(2))
def test_mailbox_bbox_is_exact_on_a_fixed_grid(i):
    """Bounding-box assignment: the cells of a triangle form a box, so tests_mb = sum S(box)/S exactly."""
    rng = np.random.default_rng(3400 + i)
    extent, res = np.array([2.0, 2.0, 2.0]), (5, 6, 7)
    tri = random_triangles(rng, 80, extent, 0.2)
    lo, hi = cell_boxes(extent, res)
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    occ = np.all((tlo[None] <= hi[:, None]) & (thi[None] >= lo[:, None]), axis=2)
    c = extent / np.array(res)
    i0, i1 = np.floor(tlo / c), np.minimum(np.floor(thi / c), np.array(res) - 1)
    box = (i1 - i0 + 1) * c
    s_union = 2 * (box[:, 0] * box[:, 1] + box[:, 1] * box[:, 2] + box[:, 2] * box[:, 0])
    want = s_union.sum() / (2 * 3 * 4.0)
    assert _mailbox_mc(rng, tri, extent, res, occ, 40_000) == pytest.approx(want, rel=0.02)


def test_mailbox_bbox_offset_average_formula():
    """E over the grid offset of the union box's surface is the bbox mailbox formula (exact)."""
    rng = np.random.default_rng(3500)
    tri = random_triangles(rng, 1, (3, 3, 3), 0.6)
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], [3, 3, 3])
    c = np.array([0.4, 0.5, 0.3])
    res = 3.0 / c
    lo, hi = tri[0].min(axis=0), tri[0].max(axis=0)
    off = rng.uniform(0, 1, (200_000, 3)) * c
    n = np.floor((hi - off) / c) - np.floor((lo - off) / c) + 1
    box = n * c
    mc = np.mean(2 * (box[:, 0] * box[:, 1] + box[:, 1] * box[:, 2] + box[:, 2] * box[:, 0])) / s.surface
    assert mc == pytest.approx(triangle_tests_per_ray(s, res, mailbox=True, overlap="bbox"), rel=0.005)


@pytest.mark.parametrize("i, scale, skinny", [(0, 0.1, False), (1, 0.25, True)])
def test_mailbox_exact_overlap_is_an_approximation(i, scale, skinny):
    """Exact assignment with mailboxing: S(T (+) C) under-estimates the polycube of cells.

    Measured with 300 triangles placed uniformly (position averages stand in for the
    offset average): the formula is low by 1-13% depending on shape.  The tolerance
    states that (a documented approximation, see models.general).
    """
    rng = np.random.default_rng(3600 + i)
    extent, res = np.array([2.0, 2.0, 2.0]), (6, 6, 6)
    tri = random_triangles(rng, 300, extent, scale, skinny=skinny)
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], extent)
    lo, hi = cell_boxes(extent, res)
    nc, t = lo.shape[0], tri.shape[0]
    occ = triangle_box_overlap(np.repeat(tri, nc, 0), np.tile(lo, (t, 1)), np.tile(hi, (t, 1))).reshape(t, nc).T
    mc = _mailbox_mc(rng, tri, extent, res, occ, 30_000)
    model = triangle_tests_per_ray(s, res, mailbox=True)
    assert 0.97 < mc / model < 1.15
    assert model < triangle_tests_per_ray(s, res)  # mailboxing never adds tests


# --- reductions to the talk's laws ------------------------------------------------------------

def _cube_stats(n, e1=0.0, e2=0.0, side=1.0):
    v = np.array([[0, 0, 0], [side, 0, 0], [0, side, side]], dtype=np.float64)
    s = scene_stats(v, np.array([[0, 1, 2]]))
    z = np.zeros(3)
    return replace(s, n_triangles=int(n), e1=e1, e1_axes=z + e1 / 3, e2=e2, e2_axes=z + e2 / 3,
                   perimeters=z, bbox_pair_sums=z, bbox_triple_sum=0.0, area=0.0)


@pytest.mark.parametrize("i", range(3))
def test_reduces_to_points_law(i):
    rng = np.random.default_rng(3700 + i)
    n, r, side = int(rng.integers(1, 10 ** 7)), rng.uniform(0.3, 30), rng.uniform(1e-3, 1e3)
    s = _cube_stats(n, side=side)
    h = optimal_cell_size(s, 1.0, r)
    assert s.volume / h ** 3 == pytest.approx(points_cells(n, r), rel=1e-12)
    # and the model's tests per ray at an m^3 grid are the talk's N / m^2
    m = 7
    assert triangle_tests_per_ray(s, (m, m, m)) == pytest.approx(n / m ** 2, rel=1e-12)


def test_reduces_to_line_law():
    """Lines crossing the box (|ext|_1 = side each): E1 = N side dominates, M -> (N r)^1.5."""
    r, side = 4.0, 2.0
    for n in (1e6, 1e9, 1e12):
        s = _cube_stats(n, e1=n * side, side=side)
        h = optimal_cell_size(s, 1.0, r)
        ratio = (s.volume / h ** 3) / lines_cells(n, r)
        assert abs(ratio - 1) < 5 / np.sqrt(n * r)  # 2 N r h^3 / (E1 r h^2) = 2 h / side -> 0
    # tests per ray of such lines at m^3: N m^2 (1/m ... ) -> the talk's N/m (+ the point term)
    m = 10
    s = _cube_stats(1000, e1=1000 * side, side=side)
    assert triangle_tests_per_ray(s, (m, m, m)) == pytest.approx(1000 / m + 1000 / m ** 2, rel=1e-12)


# --- optimum -------------------------------------------------------------------------------------

@pytest.mark.parametrize("i", range(4))
def test_cubic_root_is_the_brute_force_minimum(i):
    rng = np.random.default_rng(3800 + i)
    tri = random_triangles(rng, 200, rng.uniform(0.5, 5, 3), rng.uniform(0.01, 0.5), skinny=bool(i % 2))
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0))
    t_setup, t_step, t_int = 10.0, rng.uniform(0.5, 3), rng.uniform(1, 20)
    for mailbox in (False, True):
        for overlap in ("exact", "bbox"):
            terms = Terms(mailbox=mailbox)
            h = optimal_cell_size(s, t_step, t_int, mailbox=mailbox, overlap=overlap)
            grid = np.exp(np.linspace(np.log(h / 20), np.log(h * 20), 400001))
            cost = cost_cubic(s, grid, t_setup, t_step, t_int, terms=terms, overlap=overlap)
            assert grid[np.argmin(cost)] == pytest.approx(h, rel=1e-3)


@pytest.mark.parametrize("i", range(4))
def test_terminated_optimum_is_the_brute_force_minimum(i):
    """With rays stopping at their first hit (traversed fraction f < 1) the optimum solves the
    quartic of termination_coefficients: it is the minimum of cost_cubic under the same terms,
    found by a dense scan, and it lies at or below the cubic's (no-termination) root."""
    rng = np.random.default_rng(3850 + i)
    tri = random_triangles(rng, 200, rng.uniform(0.5, 5, 3), rng.uniform(0.01, 0.5), skinny=bool(i % 2))
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0))
    t_setup, t_step, t_int = 10.0, rng.uniform(0.5, 3), rng.uniform(1, 20)
    for f in (0.9, 0.4, 0.05):
        for mailbox in (False, True):
            for overlap in ("exact", "bbox"):
                terms = Terms(mailbox=mailbox, traversed_fraction=f)
                h = optimal_cell_size(s, t_step, t_int, mailbox=mailbox, overlap=overlap, traversed_fraction=f)
                h_free = optimal_cell_size(s, t_step, t_int, mailbox=mailbox, overlap=overlap)
                assert h < h_free
                grid = np.exp(np.linspace(np.log(h / 20), np.log(h * 20), 400001))
                grid = grid[6 * s.volume / (s.surface * grid) >= 1]  # S0 >= 1: the cell fraction's clip
                cost = cost_cubic(s, grid, t_setup, t_step, t_int, terms=terms, overlap=overlap)
                assert grid[np.argmin(cost)] == pytest.approx(h, rel=1e-3)


@pytest.mark.parametrize("n", [10, 10 ** 4, 10 ** 7])
def test_quartic_solver_reaches_far_roots(n):
    """Rays that stop at once (the distance fraction's floor, 1e-6) put the optimum 30-70 times
    below the cubic's; the fixed Newton iterations still solve the quartic to rounding."""
    s = _cube_stats(n, e1=n * 0.01, e2=n * 1e-4)
    for f in (1e-6, 1e-3, 0.1, 0.9):
        h = optimal_cell_size(s, 1.0, 0.2, traversed_fraction=f)
        a, b, c = cubic_coefficients(s, 0.2)
        k4, k3, k2 = termination_coefficients(s, 0.2, f)
        assert abs(k4 * h ** 4 + (a + k3) * h ** 3 + (b + k2) * h ** 2 - c) <= 1e-12 * c
        assert 0 < h <= optimal_cell_size(s, 1.0, 0.2)


def test_cell_fraction_counts_the_first_cell():
    """A ray enters its first cell whatever it hits: 1 + f (S0 - 1) cells of S0."""
    assert cell_fraction(0.25, 9.0) * 9.0 == pytest.approx(1 + 0.25 * 8)
    assert cell_fraction(0.25, 1.0) == 1.0  # one cell across: the whole of it
    assert cell_fraction(0.25, 0.5) == 1.0  # clipped at S0 = 1
    assert cell_fraction(1.0, 7.0) == 1.0  # rays never stop
    np.testing.assert_allclose(cell_fraction(0.5, np.array([1.0, 2.0, 1e9])), [1.0, 0.75, 0.5])
    # predict_uniform's counts are that fraction of the no-termination ones
    s = _cube_stats(1000, e1=50.0, e2=3.0)
    _, st0, te0 = predict_uniform(s, (4, 4, 4), 0.0, 1.0, 1.0, terms=Terms())
    _, st, te = predict_uniform(s, (4, 4, 4), 0.0, 1.0, 1.0, terms=Terms(traversed_fraction=0.2))
    assert st0 == pytest.approx(4.0) and st == pytest.approx(1 + 0.2 * 3)
    assert te == pytest.approx(te0 * st / st0)


def test_cubic_solver_extremes():
    a = np.array([1e-300, 1.0, 1e300, 2.0, 5.0])
    b = np.array([0.0, 1e300, 1.0, 1e-300, 3.0])
    c = np.array([1.0, 1.0, 1e-300, 1e300, 7.0])
    h = solve_cell_cubic(a, b, c)
    assert np.all(np.isfinite(h)) and np.all(h > 0)
    lh = np.log(h)  # residual in log space: a h^3 and b h^2 over- or underflow here
    with np.errstate(divide="ignore"):
        resid = np.exp(np.log(a) + 3 * lh - np.log(c)) + np.exp(np.log(b) + 2 * lh - np.log(c)) - 1
    np.testing.assert_allclose(resid, 0, atol=1e-12)


def test_optimal_uniform_beats_its_integer_neighbours():
    rng = np.random.default_rng(3900)
    tri = random_triangles(rng, 500, (3, 1, 2), 0.05)
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], [3, 1, 2])
    res, _ = optimal_uniform(s, 10, 1.0, 4.0)
    best = predict_uniform(s, res, 10, 1.0, 4.0)[0]
    for d in np.ndindex(3, 3, 3):
        n = tuple(max(1, x + y - 1) for x, y in zip(res, d))
        assert predict_uniform(s, n, 10, 1.0, 4.0)[0] >= best - 1e-12


def _tray_stats():
    """The statistics of ../shared/meshes/cad_tray_bottom_4k.stl (a closed plate 356 x 3.2 x 356),
    written out so the test runs without the mesh."""
    from models.stats import SceneStats

    lo, hi = np.array([0.0, 0.0, -355.6]), np.array([355.6, 3.175, 0.0])
    return SceneStats(n_triangles=4520, box_lo=lo, box_hi=hi, extent=hi - lo, volume=401483.068,
                      surface=257418.84, e1=89899.25, e1_axes=np.array([44686.69, 6032.5, 39180.06]), e2=225393.27,
                      e2_axes=np.array([3233.38, 219128.12, 3031.77]),
                      perimeters=np.array([89708.49, 139841.07, 100735.37]),
                      bbox_pair_sums=np.array([6466.76, 689424.98, 6063.53]), bbox_triple_sum=33388.11,
                      area=224414.73, k=41.415, aspect_median=11.56, aspect_p95=157.66, n_degenerate=0,
                      watertight=True, enclosed_volume=347865.90, positions=2216)


def test_the_cad_tray_is_planned_two_cells_deep():
    """The CAD tray: under a cell deep at the continuous optimum, cheapest two deep in the model
    (and measured so: docs/compare.md, "Rays stop at the end of a cell"), which floor/ceil alone
    never tries; the result beats every resolution with the floor or ceiling on the wide axes
    and 1 to 3 cells on the thin one."""
    from models.effects import select_effects, termination_fraction

    st = _tray_stats()
    t = (79.0, 8.3, 1.03)
    sel = select_effects(st, *t, termination=True)
    assert sel.resolution[1] == 2
    terms = sel.terms
    assert terms.traversed_fraction == termination_fraction(st)[0] < 0.2
    h = optimal_cell_size(st, t[1], t[2], edge=terms.edge, area=terms.area,
                          traversed_fraction=terms.traversed_fraction)
    cont = st.extent / h
    assert cont[1] < 1
    cost = predict_uniform(st, sel.resolution, *t, terms=terms)[0]
    wide = [(int(np.floor(x)), int(np.ceil(x))) for x in cont]
    for q in itertools.product(wide[0], (1, 2, 3), wide[2]):
        assert predict_uniform(st, q, *t, terms=terms)[0] >= cost - 1e-12


@pytest.mark.parametrize("n", [1, 10 ** 7])
@pytest.mark.parametrize("extent", [(1, 1, 1), (356, 3.2, 356), (1, 1e-9, 1e-9), (1e20, 1, 1e-20)])
def test_limits_finite_and_clamped(n, extent):
    rng = np.random.default_rng(4000 + n % 97)
    tri = random_triangles(rng, 20, extent, 0.01 * np.array(extent))
    s = stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], extent)
    k = n / s.n_triangles  # scale every sum to n triangles of the same shape
    s = replace(s, n_triangles=n, e1=s.e1 * k, e1_axes=s.e1_axes * k, e2=s.e2 * k, e2_axes=s.e2_axes * k,
                perimeters=s.perimeters * k, bbox_pair_sums=s.bbox_pair_sums * k,
                bbox_triple_sum=s.bbox_triple_sum * k, area=s.area * k)
    for mailbox in (False, True):
        res, h = optimal_uniform(s, 10.0, 1.0, 5.0, mailbox=mailbox)
        assert np.isfinite(h) and h > 0
        assert all(1 <= x <= MAX_CELLS_PER_AXIS for x in res) and np.prod(res) <= MAX_TOTAL_CELLS
        t, steps, tests = predict_uniform(s, res, 10.0, 1.0, 5.0, mailbox=mailbox)
        assert np.isfinite(t) and np.isfinite(steps) and np.isfinite(tests) and t > 0


def test_bad_input_raises():
    s = _cube_stats(10)
    for res in ((0, 1, 1), (1, 1), (np.nan, 1, 1)):
        with pytest.raises(ValueError):
            predict_uniform(s, res, 1, 1, 1)
    with pytest.raises(ValueError):
        predict_uniform(s, (1, 1, 1), 1, -1, 1)
    with pytest.raises(ValueError):
        triangle_tests_per_ray(s, (1, 1, 1), overlap="sat")
    with pytest.raises(ValueError):
        optimal_cell_size(s, 0.0, 1.0)


@pytest.mark.parametrize("scale", [1e-20, 1e-5, 1.0, 1e7, 1e20])
def test_scale_invariance_over_forty_decades(scale):
    """Scaling a scene by s scales h* by s and leaves the resolution and counts unchanged."""
    rng = np.random.default_rng(4100)
    tri = random_triangles(rng, 300, (2, 1, 3), 0.05)
    base = scene_stats(*mesh_of(tri))
    s = scene_stats(*mesh_of(tri * scale))
    assert s.k == pytest.approx(base.k, rel=1e-9)
    for mailbox in (False, True):
        res0, h0 = optimal_uniform(base, 10.0, 1.0, 5.0, mailbox=mailbox)
        res, h = optimal_uniform(s, 10.0, 1.0, 5.0, mailbox=mailbox)
        assert res == res0 and h == pytest.approx(h0 * scale, rel=1e-9)
        assert predict_uniform(s, res, 10, 1, 5, mailbox=mailbox)[0] == pytest.approx(
            predict_uniform(base, res0, 10, 1, 5, mailbox=mailbox)[0], rel=1e-9)


def test_single_triangle_scene():
    s = scene_stats(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64), np.array([[0, 1, 2]]))
    res, h = optimal_uniform(s, 10.0, 1.0, 5.0)
    t, steps, tests = predict_uniform(s, res, 10.0, 1.0, 5.0)
    assert all(n >= 1 for n in res) and np.isfinite(t) and 1.0 <= steps and 0 < tests

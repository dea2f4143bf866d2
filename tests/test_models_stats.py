"""Scene statistics: hand-computed values, watertightness, the grid box rule, real meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.stats import (AR_SAMPLE_TRIANGLES, MIN_EXTENT_FRACTION, enclosed_volume, grid_box,
                          is_watertight, scene_class, scene_stats, triangle_geometry)

MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"

# Unit cube [0,1]^3, 12 outward-oriented triangles.
CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                   [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [3, 7, 6], [3, 6, 2], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]], dtype=np.int64)


def test_unit_cube_hand_values():
    s = scene_stats(CUBE_V, CUBE_F)
    assert s.n_triangles == 12
    np.testing.assert_allclose(s.extent, [1, 1, 1])
    assert s.volume == pytest.approx(1.0) and s.surface == pytest.approx(6.0)
    # Each triangle is half a unit face: bbox extent (1, 1, 0) -> |ext|_1 = 2; 12 * 2 = 24.
    assert s.e1 == pytest.approx(24.0)
    np.testing.assert_allclose(s.e1_axes, [8, 8, 8])
    # A |n|_1 = 1/2 per triangle -> E2 = 6 = total area; k = E2 / V^(2/3) = 6 (the talk's cube).
    assert s.e2 == pytest.approx(6.0) and s.area == pytest.approx(6.0)
    assert s.k == pytest.approx(6.0)
    # Along x: the 4 x-facing triangles project to right triangles (perimeter 2 + sqrt 2),
    # the 8 others to unit segments (perimeter 2): P_x = 4 (2 + sqrt 2) + 16 = 24 + 4 sqrt 2.
    np.testing.assert_allclose(s.perimeters, [24 + 4 * np.sqrt(2)] * 3)
    # bbox pair sums: sum ext_y ext_z = 4 x-facing triangles * 1 = 4 per axis; triple 0.
    np.testing.assert_allclose(s.bbox_pair_sums, [4, 4, 4])
    assert s.bbox_triple_sum == 0.0
    assert s.aspect_median == pytest.approx(2.0) and s.aspect_p95 == pytest.approx(2.0)
    assert s.n_degenerate == 0
    assert s.watertight and s.enclosed_volume == pytest.approx(1.0)
    assert scene_class(s)[0] == "compact"


def test_single_triangle_hand_values():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0]], dtype=np.float64)
    s = scene_stats(v, np.array([[0, 1, 2]]))
    assert s.e1 == pytest.approx(3.0)  # extents (1, 2, 0)
    np.testing.assert_allclose(s.e2_axes, [0, 0, 1])  # area 1, normal z
    # projected perimeters: along x a segment of length 2 (4), along y length 1 (2),
    # along z the triangle itself 1 + 2 + sqrt 5.
    np.testing.assert_allclose(s.perimeters, [4, 2, 3 + np.sqrt(5)])
    assert s.aspect_median == pytest.approx(5.0 / 2.0)  # longest^2 = 5, area 1
    # flat in z: widened to MIN_EXTENT_FRACTION * 2, symmetric about z = 0
    np.testing.assert_allclose(s.box_lo, [0, 0, -MIN_EXTENT_FRACTION])
    np.testing.assert_allclose(s.box_hi, [1, 2, MIN_EXTENT_FRACTION])
    assert not s.watertight


def test_watertight_detection():
    assert is_watertight(CUBE_V, CUBE_F)
    assert not is_watertight(CUBE_V, CUBE_F[:-1])  # one face missing: 3 boundary edges
    # Split vertices (one copy per face corner) still merge to a closed cube.
    v_split = CUBE_V[CUBE_F.reshape(-1)]
    f_split = np.arange(36).reshape(12, 3)
    assert is_watertight(v_split, f_split)
    # -0.0 and +0.0 are the same position.
    v_neg = v_split.copy()
    v_neg[v_neg == 0.0] = -0.0
    v_mixed = np.where(np.arange(36)[:, None] % 2 == 0, v_split, v_neg)
    assert is_watertight(v_mixed, f_split)
    # A duplicated face makes its edges shared by 3+ faces.
    assert not is_watertight(CUBE_V, np.vstack([CUBE_F, CUBE_F[:1]]))
    # A slightly moved copy of a vertex is a different position: crack.
    v_crack = v_split.copy()
    v_crack[0, 0] += 1e-12
    assert not is_watertight(v_crack, f_split)


def test_enclosed_volume_translation_invariant():
    for i in range(3):
        rng = np.random.default_rng(1000 + i)
        shift = rng.uniform(-1e6, 1e6, 3)
        assert enclosed_volume(CUBE_V * 2.5 + shift, CUBE_F) == pytest.approx(2.5 ** 3, rel=1e-9)


def test_degenerate_triangles_counted():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 0, 0], [0, 1, 3]])  # collinear, zero-size, fine
    s = scene_stats(v, f)
    assert s.n_degenerate == 2
    assert s.aspect_median == pytest.approx(2.0)
    assert scene_class(s)[0] == "long-skinny"  # 2/3 degenerate > 50%
    geom = triangle_geometry(v, f)
    assert geom.degenerate.tolist() == [True, True, False]


def test_grid_box_rule():
    lo, hi = grid_box([0, 0, 0], [10, 0, 5])
    np.testing.assert_allclose(hi - lo, [10, 10 * MIN_EXTENT_FRACTION, 5])
    assert lo[1] == pytest.approx(-5 * MIN_EXTENT_FRACTION)
    # one point, at the origin and far away
    for p in (0.0, 1e20, -3e-20):
        lo, hi = grid_box([p] * 3, [p] * 3)
        assert np.all(hi - lo > 0) and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))
        assert lo[0] <= p <= hi[0]
    # near the float64 limit: still finite with positive extents
    lo, hi = grid_box([1.7e308, 0, 0], [1.7e308, 1, 1])
    assert np.all(hi - lo > 0) and np.all(np.isfinite(hi))


@pytest.mark.parametrize("bad", [
    (np.zeros((3, 2)), np.array([[0, 1, 2]])),
    (np.zeros((3, 3)), np.array([[0, 1, 3]])),
    (np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64)),
    (np.array([[0, 0, 0], [1, np.nan, 0], [0, 1, 0]]), np.array([[0, 1, 2]])),
    (np.zeros((3, 3)), np.array([[0.0, 1.0, 2.0]])),
])
def test_bad_input_raises(bad):
    with pytest.raises(ValueError):
        scene_stats(*bad)
    with pytest.raises(ValueError):
        grid_box([0, 0, 1], [1, 1, 0])


def test_stats_are_sums_over_triangles():
    """Splitting a mesh in two: every sum is additive (vectorised pass vs. per-part)."""
    for i in range(3):
        rng = np.random.default_rng(1100 + i)
        v = rng.normal(size=(300, 3)) * rng.uniform(0.1, 10, 3)
        f = rng.integers(0, 300, size=(5000, 3))
        whole = scene_stats(v, f, topology=False)
        a = scene_stats(v, f[:1234], topology=False)
        b = scene_stats(v, f[1234:], topology=False)
        for name in ("e1", "e2", "area", "bbox_triple_sum"):
            assert getattr(whole, name) == pytest.approx(getattr(a, name) + getattr(b, name), rel=1e-12)
        for name in ("e1_axes", "e2_axes", "perimeters", "bbox_pair_sums"):
            np.testing.assert_allclose(getattr(whole, name), getattr(a, name) + getattr(b, name), rtol=1e-12)
        # and the per-triangle arrays agree with the one-pass sums
        g = triangle_geometry(v, f)
        np.testing.assert_allclose(whole.perimeters, g.proj_perimeter.sum(axis=0), rtol=1e-12)
        np.testing.assert_allclose(whole.e2_axes, g.proj_area.sum(axis=0), rtol=1e-12)


def test_aspect_sample_matches_exact_percentiles():
    rng = np.random.default_rng(1200)
    n = 3 * AR_SAMPLE_TRIANGLES
    v = rng.normal(size=(3 * n, 3))
    f = np.arange(3 * n).reshape(n, 3)
    s = scene_stats(v, f, topology=False)
    g = triangle_geometry(v, f)
    ar = g.longest_edge_sq / (2 * g.area)
    med, p95 = np.percentile(ar, [50, 95])
    assert s.aspect_median == pytest.approx(med, rel=0.02)
    assert s.aspect_p95 == pytest.approx(p95, rel=0.05)


# README of the shared meshes: AR median / p95 and watertightness (cornell_box_36 is
# left out: its TAB-separated `v` lines need the project's own loader).
README_TABLE = {
    "spot_6k.obj": (1.9, 3.0, True, "compact"),
    "utah_teapot_6k.obj": (2.9, 10.8, False, "compact"),
    "fertility_9k.off": (2.1, 4.1, True, "compact"),
    "stanford_bunny_69k.obj": (2.0, 2.4, False, "compact"),
    "armadillo_86k.obj": (1.7, 3.1, True, "compact"),
    "sponza_dabrovic_66k.obj": (7.6, 58, False, "mixed"),
    "cad_round_cylinder_1k.stl": (19.7, 21.2, True, "long-skinny"),
    "cad_tray_bottom_4k.stl": (11.6, 158, True, "long-skinny"),
    "cad_fandisk_13k.obj": (2.0, 2.1, True, "compact"),
    "cad_chair_soup_13k.obj": (42, 121, False, "long-skinny"),
}


@pytest.mark.parametrize("name", sorted(README_TABLE))
def test_real_meshes_match_readme(name):
    if not MESHES.is_dir():
        pytest.skip(f"shared meshes folder {MESHES} is absent")
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.load(MESHES / name, force="mesh", process=False)
    s = scene_stats(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64))
    med, p95, wt, cls = README_TABLE[name]
    assert s.aspect_median == pytest.approx(med, abs=0.051 * max(1.0, med / 10) + 1e-9, rel=0.01)
    assert s.aspect_p95 == pytest.approx(p95, rel=0.01, abs=0.051)
    assert s.watertight == wt
    assert scene_class(s)[0] == cls


def test_unreferenced_vertices_do_not_change_the_box():
    v = np.vstack([CUBE_V, [[100.0, -50.0, 7.0]] * 20])
    s = scene_stats(v, CUBE_F)
    np.testing.assert_allclose(s.box_lo, [0, 0, 0])
    np.testing.assert_allclose(s.box_hi, [1, 1, 1])

"""The compiled scene-statistics pass (kernels/stats.c) against the numpy reference (models.stats)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibrate import Scene, _kernels
from calibrate._grid import compiled_scene_stats
from calibrate.scenes import builtin_names, load_builtin
from models.stats import AR_SAMPLE_TRIANGLES, is_watertight, mesh_topology, scene_stats

# Sums over triangles are accumulated in another order (one pass in C, numpy's
# chunked pairwise sums): they agree to rounding, not bit for bit.
RTOL = 1e-11


def assert_same_stats(a, b):
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, (bool, np.bool_, int, np.integer)):
            assert x == y, field.name
        else:
            np.testing.assert_allclose(np.asarray(y, dtype=float), np.asarray(x, dtype=float), rtol=RTOL, atol=0,
                                       err_msg=field.name)


@pytest.mark.parametrize("name", builtin_names())
def test_builtin_scenes_match_the_reference(name):
    mesh = load_builtin(name)
    v, f = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64)
    assert_same_stats(scene_stats(v, f), compiled_scene_stats(v, f))


@pytest.mark.parametrize("i", range(6))
def test_random_soups_with_degenerate_and_duplicate_triangles_match(i):
    rng = np.random.default_rng(i)
    n = int(rng.integers(1, 400))
    v = rng.normal(size=(3 * n, 3)) * 10.0 ** rng.uniform(-20, 20)
    f = rng.integers(0, v.shape[0], size=(n, 3))
    f[: n // 5, 1] = f[: n // 5, 0]  # repeated corners: zero-area triangles
    v[rng.integers(0, v.shape[0], size=n // 7)] *= -0.0  # signed zeros
    f = np.concatenate([f, f[: n // 3]])  # duplicate triangles
    assert_same_stats(scene_stats(v, f), compiled_scene_stats(v, f))


def test_aspect_percentiles_use_the_same_sample_above_the_sampling_size():
    n = AR_SAMPLE_TRIANGLES * 2 + 17
    rng = np.random.default_rng(7)
    v = rng.uniform(size=(3 * n, 3))
    f = np.arange(3 * n).reshape(n, 3)
    a, b = scene_stats(v, f, topology=False), compiled_scene_stats(v, f)
    assert (a.aspect_median, a.aspect_p95) == (b.aspect_median, b.aspect_p95)


@pytest.mark.parametrize("i", range(4))
def test_watertightness_agrees_on_closed_opened_and_split_meshes(i):
    mesh = load_builtin("sphere")  # a closed displaced icosphere
    v, f = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64)
    rng = np.random.default_rng(i)
    if i == 1:  # one face removed: open
        f = np.delete(f, int(rng.integers(len(f))), axis=0)
    elif i == 2:  # split vertices: every face its own corners, still closed
        v, f = v[f.reshape(-1)], np.arange(3 * len(f)).reshape(-1, 3)
    elif i == 3:  # one face twice: an edge shared by four faces
        f = np.concatenate([f, f[:1]])
    want = i in (0, 2)
    assert is_watertight(v, f) == want
    assert compiled_scene_stats(v, f).watertight == want


def test_scene_stats_property_uses_the_compiled_pass():
    mesh = load_builtin(builtin_names()[0])
    scene = Scene(mesh[0], mesh[1])
    assert_same_stats(scene_stats(scene.vertices, scene.faces), scene.stats)


def test_out_of_range_faces_are_refused():
    v = np.zeros((3, 3))
    with pytest.raises(ValueError, match="out of range"):
        compiled_scene_stats(v, np.array([[0, 1, 3]]))


# --- watertightness: the compiled edge grouping against the numpy reference -----------------


def _closed_mesh(i):
    """A closed mesh picked by i: a small displaced icosphere or a cylinder (fans of long
    triangles: a cap's first vertex has an edge to every other ring vertex)."""
    from calibrate.scenes import cylinder_mesh, sphere_mesh

    v, f = sphere_mesh(80 * (1 + i % 4)) if i % 2 == 0 else cylinder_mesh(5 + 3 * i)
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def _variant(v, f, kind, rng):
    """(vertices, faces, watertight as known by construction or None) of one variant."""
    n = len(f)
    if kind == "closed":
        return v, f, True
    if kind == "shuffled":  # faces and vertices renumbered: still closed
        perm = rng.permutation(len(v))
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(v))
        return v[perm], inv[f][rng.permutation(n)], True
    if kind == "split":  # every face its own corners (merged again by position), some at -0.0
        vs = v[f.reshape(-1)].copy()
        vs[vs == 0.0] = -0.0
        return vs, np.arange(3 * n).reshape(-1, 3), True
    if kind == "open":  # faces removed: their edges occur once
        return v, np.delete(f, rng.choice(n, size=int(rng.integers(1, 4)), replace=False), axis=0), False
    if kind == "doubled face":  # a face twice: its edges are shared by four faces... or three
        return v, np.concatenate([f, f[rng.integers(n)][None]]), False
    if kind == "two copies":  # a second copy at the same positions, own indices: four faces per edge
        return np.concatenate([v, v]), np.concatenate([f, f + len(v)]), False
    if kind == "moved corner":  # one corner moved to another vertex: edges once and three times
        g = f.copy()
        t = int(rng.integers(n))
        g[t, int(rng.integers(3))] = int(rng.integers(len(v)))
        return v, g, None  # the reference decides (the new corner may repeat one: degenerate)
    if kind == "degenerate":  # new vertices p, q, r and faces (p, p, q), (p, p, r): every edge twice
        p = len(v)
        extra = v.max(axis=0) + np.arange(1.0, 4.0)[:, None]
        return np.concatenate([v, extra]), np.concatenate([f, [[p, p, p + 1], [p, p, p + 2]]]), True
    raise AssertionError(kind)


VARIANTS = ["closed", "shuffled", "split", "open", "doubled face", "two copies", "moved corner", "degenerate"]


@pytest.mark.parametrize("kind", VARIANTS)
@pytest.mark.parametrize("i", range(4))
def test_topology_matches_the_reference_on_seeded_variants(kind, i):
    rng = np.random.default_rng(i)
    v, f, known = _variant(*_closed_mesh(i), kind, rng)
    want = is_watertight(v, f)
    if known is not None:
        assert want == known  # the reference itself recovers the constructed answer
    vc, fc = np.ascontiguousarray(v), np.ascontiguousarray(f)
    assert _kernels.mesh_watertight(vc, fc) == want
    # the distinct positions too; the reference recovers a count made by hand: rows that
    # differ in any bit (-0.0 is +0.0)
    topology = mesh_topology(v, f)
    assert topology[0] == want and _kernels.mesh_topology(vc, fc) == topology
    assert topology[1] == len({tuple(r) for r in (np.asarray(v, dtype=np.float64) + 0.0).tolist()})


def test_distinct_positions_of_split_and_separate_triangles():
    mesh = load_builtin("sphere")  # closed: about half as many positions as faces
    v, f = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64)
    split_v, split_f = v[f.reshape(-1)], np.arange(3 * len(f)).reshape(-1, 3)
    closed = compiled_scene_stats(v, f)
    split = compiled_scene_stats(split_v, split_f)
    assert closed.positions == split.positions == len(np.unique(v, axis=0))
    assert closed.separate_fraction == split.separate_fraction < 0.01
    # the same triangles moved apart: no corner shared
    moved = split_v + np.repeat(np.arange(len(f))[:, None] * 10.0, 3, axis=0)
    apart = compiled_scene_stats(moved, split_f)
    assert apart.positions == 3 * len(f) and apart.separate_fraction == 1.0
    assert scene_stats(moved, split_f).positions == apart.positions
    assert scene_stats(moved, split_f, topology=False).separate_fraction == 0.0  # not computed: connected


@pytest.mark.parametrize("i", range(6))
def test_watertightness_matches_the_reference_on_random_small_meshes(i):
    # Few vertices, many faces: groups of every size, edges occurring 1..many times.
    rng = np.random.default_rng(100 + i)
    nv = int(rng.integers(3, 9))
    v = rng.integers(-2, 3, size=(nv, 3)).astype(np.float64)  # coincident positions likely
    half = rng.integers(0, nv, size=(int(rng.integers(1, 12)), 3))
    f = np.concatenate([half, half[rng.permutation(len(half))]]) if i % 2 else half
    assert _kernels.mesh_watertight(v, f) == is_watertight(v, f)


def test_watertightness_of_a_tetrahedron_and_its_broken_forms():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    assert _kernels.mesh_watertight(v, f)
    # vertex 0's edges: partner 1 three times and partner 2 once (an even count that does not pair)
    g = f.copy()
    g[3] = [0, 1, 3]
    assert not is_watertight(v, g) and not _kernels.mesh_watertight(v, g)
    assert not _kernels.mesh_watertight(v, f[:3])
    # two triangles on one edge: vertex 0's edges, to 2 and to 3, are even in number but unpaired
    hinge = np.array([[2, 3, 0], [2, 3, 1]])
    assert not is_watertight(v, hinge) and not _kernels.mesh_watertight(v, hinge)


@pytest.mark.parametrize("bad", [-1, 60])
def test_a_bad_index_far_into_the_faces_is_named_by_both_passes(bad):
    # Face 37 is reached after the passes have looked ahead at it (prefetching).
    rng = np.random.default_rng(3)
    v = rng.normal(size=(60, 3))
    f = rng.integers(0, 60, size=(50, 3))
    f[37, 1] = bad
    for call in (lambda: _kernels.mesh_sums(v, f, 1), lambda: _kernels.mesh_watertight(v, f)):
        with pytest.raises(ValueError, match="face 37 has a vertex index out of range"):
            call()


def test_one_thread_and_two_give_the_same_statistics():
    mesh = load_builtin("sphere")
    v, f = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64)
    one, two = compiled_scene_stats(v, f, threads=1), compiled_scene_stats(v, f, threads=2)
    for field in dataclasses.fields(one):  # bit for bit: the same passes, only run side by side
        assert np.array_equal(getattr(one, field.name), getattr(two, field.name)), field.name
    with pytest.raises(ValueError, match="threads must be 1 or 2"):
        compiled_scene_stats(v, f, threads=3)

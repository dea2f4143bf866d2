"""The compiled scene-statistics pass (kernels/stats.c) against the numpy reference (models.stats)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibrate import Scene
from calibrate._grid import compiled_scene_stats
from calibrate.scenes import builtin_names, load_builtin
from models.stats import AR_SAMPLE_TRIANGLES, is_watertight, scene_stats

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

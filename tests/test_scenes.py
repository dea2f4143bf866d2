"""Built-in procedural scenes: exact counts, closedness, shapes of triangles, determinism."""

import numpy as np
import pytest

from calibrate import scenes

EXPECTED_NAMES = [
    "sphere",
    "cylinder196",
    "cylinder1996",
    "cylinder19996",
    "scattered-compact",
    "scattered-skinny",
    "room",
]
# A triangle is degenerate when 2 area / longest edge^2 (= 1 / aspect ratio) falls
# below this; the skinniest intended triangles (cylinder19996 cap fans) sit near 6e-4.
DEGENERATE_INVERSE_ASPECT = 1e-7
EQUILATERAL_ASPECT = 2.0 / np.sqrt(3.0)  # longest edge^2 / (2 area) of an equilateral triangle
Z_TOLERANCE = 5.0  # Monte Carlo checks: |estimate - truth| < 5 standard errors


def triangle_stats(v, f):
    """Per-triangle area (F,), aspect ratio longest edge^2 / (2 area) (F,), unit normal (F, 3)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    e2 = np.stack([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=1)
    aspect = e2.max(axis=1) / double_area
    return 0.5 * double_area, aspect, cross / double_area[:, None]


def closed_and_oriented(f, n_vertices):
    """True when every directed edge occurs once and its reverse occurs once.

    That is: every edge is shared by exactly two triangles through shared
    vertex indices, and the two use it in opposite directions (consistent
    orientation) -- a watertight, orientable surface.
    """
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = e[:, 0] * n_vertices + e[:, 1]
    reverse = e[:, 1] * n_vertices + e[:, 0]
    return np.unique(key).size == key.size and bool(np.all(np.isin(reverse, key)))


def signed_volume(v, f):
    """Enclosed volume by the divergence theorem (positive for outward orientation)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


# ------------------------------------------------------------------------------
# registry
# ------------------------------------------------------------------------------

def test_registry_names_in_order_with_descriptions():
    assert scenes.builtin_names() == EXPECTED_NAMES
    assert list(scenes.BUILTIN) == EXPECTED_NAMES
    for name, (description, generator) in scenes.BUILTIN.items():
        assert isinstance(description, str) and description
        assert callable(generator)


@pytest.mark.parametrize("bad", ["", "Sphere", "cylinder", "bunny.ply", None, 3])
def test_unknown_name_lists_valid_names(bad):
    with pytest.raises(ValueError) as err:
        scenes.load_builtin(bad)
    for name in EXPECTED_NAMES:
        assert name in str(err.value)


@pytest.mark.parametrize("name", EXPECTED_NAMES)
def test_builtin_arrays_valid_deterministic_nondegenerate(name):
    v, f = scenes.load_builtin(name)
    assert v.dtype == np.float64 and v.ndim == 2 and v.shape[1] == 3
    assert f.dtype == np.int64 and f.ndim == 2 and f.shape[1] == 3
    assert v.flags.c_contiguous and f.flags.c_contiguous
    assert np.all(np.isfinite(v))
    assert f.min() >= 0 and f.max() < v.shape[0]
    # every vertex is used
    assert np.unique(f).size == v.shape[0]
    # no repeated index inside a triangle, no degenerate triangle
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    _, aspect, _ = triangle_stats(v, f)
    assert np.all(1.0 / aspect > DEGENERATE_INVERSE_ASPECT)
    # bit-identical on a second call
    v2, f2 = scenes.load_builtin(name)
    assert v.tobytes() == v2.tobytes() and f.tobytes() == f2.tobytes()


# ------------------------------------------------------------------------------
# cylinders
# ------------------------------------------------------------------------------

@pytest.mark.parametrize(
    "name, segments, triangles",
    [("cylinder196", 50, 196), ("cylinder1996", 500, 1996), ("cylinder19996", 5000, 19996)],
)
def test_cylinder_counts_closed_volume_and_skinny_sides(name, segments, triangles):
    v, f = scenes.load_builtin(name)
    assert f.shape[0] == triangles == 4 * segments - 4
    assert v.shape[0] == 2 * segments
    assert closed_and_oriented(f, v.shape[0])
    r, length = scenes.CYLINDER_RADIUS, scenes.CYLINDER_LENGTH
    # enclosed volume = inscribed regular n-gon area * length, exactly
    polygon_area = 0.5 * segments * r * r * np.sin(2.0 * np.pi / segments)
    assert signed_volume(v, f) == pytest.approx(polygon_area * length, rel=1e-9)
    # side triangles: span the full length; aspect ratio (L^2 + c^2) / (c L), c = chord
    area, aspect, normal = triangle_stats(v, f)
    z = v[f][:, :, 2]
    side = np.abs(normal[:, 2]) < 0.5
    assert side.sum() == 2 * segments
    assert np.all(z[side].max(axis=1) - z[side].min(axis=1) == length)
    chord = 2.0 * r * np.sin(np.pi / segments)
    expected_aspect = (length**2 + chord**2) / (chord * length)
    assert np.allclose(aspect[side], expected_aspect, rtol=1e-6)
    assert aspect[side].min() > 50.0  # long and skinny at every size
    # caps: fans of n - 2 triangles each, in the planes z = 0 and z = L
    caps = ~side
    assert np.sum(caps & (z.max(axis=1) == 0.0)) == segments - 2
    assert np.sum(caps & (z.min(axis=1) == length)) == segments - 2


def test_cylinder_mesh_general_count_and_bad_input():
    for i, segments in enumerate([3, 4, 7, 64]):
        v, f = scenes.cylinder_mesh(segments)
        assert f.shape[0] == 4 * segments - 4, i
        assert closed_and_oriented(f, v.shape[0]), i
    with pytest.raises(ValueError, match="segments"):
        scenes.cylinder_mesh(2)
    with pytest.raises(ValueError, match="radius"):
        scenes.cylinder_mesh(8, radius=0.0)


# ------------------------------------------------------------------------------
# sphere
# ------------------------------------------------------------------------------

@pytest.mark.parametrize("frequency", [1, 2, 3, 5, 8, 13])
def test_icosphere_shares_every_vertex_exactly(frequency):
    v, f = scenes.icosphere(frequency)
    assert f.shape[0] == 20 * frequency**2
    assert v.shape[0] == 10 * frequency**2 + 2  # Euler: V - E + F = 2 with E = 3F/2
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0, rtol=0.0, atol=4e-16)
    # no two vertices at the same position: merging was exact, nothing duplicated
    assert np.unique(v, axis=0).shape[0] == v.shape[0]
    assert closed_and_oriented(f, v.shape[0])
    assert signed_volume(v, f) > 0


def test_sphere_scene_compact_closed_outward():
    v, f = scenes.load_builtin("sphere")
    assert f.shape[0] == 40_500  # 20 * 45^2, nearest to SPHERE_DEFAULT_TRIANGLES
    assert closed_and_oriented(f, v.shape[0])
    r = np.linalg.norm(v, axis=1)
    amp = scenes.SPHERE_BUMP_AMPLITUDE_FRACTION
    assert r.min() >= 1.0 - amp - 1e-12 and r.max() <= 1.0 + amp + 1e-12
    assert r.std() > 0.1 * amp  # it is bumpy, not a plain sphere
    vol = signed_volume(v, f)
    assert 4.0 / 3.0 * np.pi * (1 - amp) ** 3 < vol < 4.0 / 3.0 * np.pi * (1 + amp) ** 3
    # near-equilateral: median aspect within 6% of equilateral, worst within 30%
    area, aspect, normal = triangle_stats(v, f)
    assert np.median(aspect) < 1.06 * EQUILATERAL_ASPECT
    assert aspect.max() < 1.3 * EQUILATERAL_ASPECT
    # sizes are uniform too (compact "points"): largest/smallest area below 3
    assert area.max() / area.min() < 3.0
    # outward: triangle normals point away from the centre
    centroid = v[f].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normal, centroid) > 0)


@pytest.mark.parametrize("n_target", [1, 20, 100, 12_345, 80_000])
def test_sphere_mesh_count_is_nearest_20f2(n_target):
    v, f = scenes.sphere_mesh(n_target)
    freq = int(round(np.sqrt(f.shape[0] / 20)))
    assert f.shape[0] == 20 * freq**2 and v.shape[0] == 10 * freq**2 + 2
    # the frequency is the integer nearest to sqrt(n_target / 20), at least 1
    assert freq == 1 or abs(freq - np.sqrt(n_target / 20)) <= 0.5 + 1e-12
    assert freq >= 1 and abs(freq - np.sqrt(n_target / 20)) < abs(freq + 1 - np.sqrt(n_target / 20))
    assert closed_and_oriented(f, v.shape[0])


def test_sphere_mesh_reaches_five_million_triangles():
    v, f = scenes.sphere_mesh(5_000_000)
    assert f.shape == (5_000_000, 3)  # frequency 500
    assert v.shape == (10 * 500**2 + 2, 3)
    assert f.min() == 0 and f.max() == v.shape[0] - 1
    assert np.all(np.isfinite(v))


def test_sphere_mesh_bad_input():
    for bad in [0, -5, 2.5, True]:
        with pytest.raises(ValueError, match="n_target"):
            scenes.sphere_mesh(bad)
    with pytest.raises(ValueError, match="radius"):
        scenes.sphere_mesh(100, radius=-1.0)
    with pytest.raises(ValueError, match="bump_amplitude_fraction"):
        scenes.sphere_mesh(100, bump_amplitude_fraction=float("nan"))


# ------------------------------------------------------------------------------
# jittered closed mesh
# ------------------------------------------------------------------------------

@pytest.mark.parametrize("i", range(5))
def test_jittered_closed_mesh_watertight_star_shaped(i):
    seed = 1000 + i
    v, f = scenes.jittered_closed_mesh(seed)
    assert f.shape[0] == 20 * scenes.JITTER_MESH_FREQUENCY**2
    assert closed_and_oriented(f, v.shape[0])
    assert np.unique(v, axis=0).shape[0] == v.shape[0]  # shared, not duplicated
    # vertices really moved off the sphere
    assert np.abs(np.linalg.norm(v, axis=1) - 1.0).max() > 1e-3
    # every triangle sees the origin from its back: a ray from the origin
    # crosses the surface exactly once (star-shaped around the origin)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    assert np.all(np.einsum("ij,ij->i", a, np.cross(b, c)) > 0)
    _, aspect, _ = triangle_stats(v, f)
    assert aspect.max() < 2.0 * EQUILATERAL_ASPECT
    v2, f2 = scenes.jittered_closed_mesh(seed)
    assert v.tobytes() == v2.tobytes() and np.array_equal(f, f2)
    v3, _ = scenes.jittered_closed_mesh(seed + 100)
    assert not np.array_equal(v, v3)


def test_jittered_closed_mesh_bad_seed():
    for bad in [-1, 1.5, "x", None]:
        with pytest.raises(ValueError, match="seed"):
            scenes.jittered_closed_mesh(bad)


# ------------------------------------------------------------------------------
# scattered triangles
# ------------------------------------------------------------------------------

def test_scattered_compact_equilateral_uniform_isotropic():
    v, f = scenes.load_builtin("scattered-compact")
    n = scenes.SCATTERED_COMPACT_DEFAULT_COUNT
    assert f.shape[0] == n and v.shape[0] == 3 * n
    area, aspect, normal = triangle_stats(v, f)
    assert np.allclose(aspect, EQUILATERAL_ASPECT, rtol=1e-9)
    edge = scenes.COMPACT_EDGE_FRACTION_OF_SPACING / np.cbrt(n)
    assert np.allclose(area, np.sqrt(3.0) / 4.0 * edge**2, rtol=1e-9)
    centroid = v[f].mean(axis=1)
    assert centroid.min() >= 0.0 and centroid.max() <= 1.0
    # centroids uniform in the unit cube: mean 1/2, variance 1/12 per axis
    se = np.sqrt(1.0 / 12.0 / n)
    assert np.all(np.abs(centroid.mean(axis=0) - 0.5) < Z_TOLERANCE * se)
    # orientations isotropic: |n_axis| uniform on [0, 1] (Archimedes), mean 1/2
    assert np.all(np.abs(np.abs(normal).mean(axis=0) - 0.5) < Z_TOLERANCE * se)


def test_scattered_skinny_lengths_aspect_isotropic():
    v, f = scenes.load_builtin("scattered-skinny")
    n = scenes.SCATTERED_SKINNY_DEFAULT_COUNT
    assert f.shape[0] == n
    _, aspect, _ = triangle_stats(v, f)
    assert np.allclose(aspect, scenes.SKINNY_ASPECT_RATIO, rtol=1e-9)
    long_edge = v[f[:, 1]] - v[f[:, 0]]
    length = np.linalg.norm(long_edge, axis=1)
    assert np.allclose(length, scenes.SKINNY_LENGTH_FRACTION_OF_BOX, rtol=1e-12)
    u = long_edge / length[:, None]
    se = np.sqrt(1.0 / 12.0 / n)
    assert np.all(np.abs(np.abs(u).mean(axis=0) - 0.5) < Z_TOLERANCE * se)
    # long relative to the box: each spans a quarter of the box side
    assert np.all(np.ptp(v[f], axis=1).max(axis=1) > 0.25 / np.sqrt(3.0) - 1e-12)


@pytest.mark.parametrize("i", range(3))
def test_scattered_seed_and_count_parameters(i):
    seed = 1000 + i
    for gen in (scenes.scattered_compact, scenes.scattered_skinny):
        v, f = gen(n=17 + i, seed=seed)
        assert f.shape[0] == 17 + i
        v2, _ = gen(n=17 + i, seed=seed)
        v3, _ = gen(n=17 + i, seed=seed + 1)
        assert v.tobytes() == v2.tobytes()
        assert not np.array_equal(v, v3)
    with pytest.raises(ValueError, match="n"):
        scenes.scattered_compact(n=0)


# ------------------------------------------------------------------------------
# room
# ------------------------------------------------------------------------------

def test_room_mixed_sizes_inward_walls_closed_parts():
    v, f = scenes.load_builtin("room")
    assert 10_000 <= f.shape[0] <= 50_000
    size = np.array(scenes.ROOM_SIZE_UNITS)
    assert np.all(v >= 0.0) and np.all(v <= size)
    area, aspect, normal = triangle_stats(v, f)
    # walls, floor and ceiling: the first 12 triangles, covering the whole shell, facing in
    shell = slice(0, 12)
    sx, sy, sz = size
    assert area[shell].sum() == pytest.approx(2 * (sx * sy + sx * sz + sy * sz), rel=1e-12)
    to_centre = 0.5 * size - v[f[shell]].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normal[shell], to_centre) > 0)
    # the rest is a union of closed, outward parts
    rest = f[12:]
    assert closed_and_oriented(rest, v.shape[0])
    assert signed_volume(v, rest) > 0
    # mixed: big quads, many compact triangles, and long skinny ones
    assert np.sum(area > 1.0) >= 12
    assert np.sum(aspect < 1.2 * EQUILATERAL_ASPECT) >= 10_000
    assert np.sum(aspect > 50.0) >= 50


def test_room_object_size_parameter():
    _, f_small = scenes.room_mesh(object_triangles=500)
    _, f_default = scenes.room_mesh()
    default_freq = round(np.sqrt(scenes.ROOM_OBJECT_TRIANGLES / 20))
    assert f_default.shape[0] - f_small.shape[0] == 20 * default_freq**2 - 20 * 5**2

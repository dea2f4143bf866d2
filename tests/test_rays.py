"""Ray sets: exactness of the isotropic sampler by Crofton's formulas, camera and surface rays.

Monte Carlo checks compare an estimate with its exact value within Z_TOLERANCE
standard errors computed from the sample itself; every random case is seeded by
its index so a failure names its own reproduction.
"""

import numpy as np
import pytest

from calibrate import rays, scenes

Z_TOLERANCE = 5.0  # |estimate - truth| < 5 standard errors
UNIT_TOLERANCE = 1e-12  # | |d| - 1 |
# Boxes of different aspect (lo, hi); the last is a long thin slab.
BOXES = [
    ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    ((-1.0, 0.5, 2.0), (2.0, 1.5, 2.5)),
    ((10.0, -3.0, 7.0), (10.5, 2.0, 9.0)),
    ((0.0, 0.0, 0.0), (1.0, 10.0, 100.0)),
]


def box_volume_area(lo, hi):
    d = np.asarray(hi, float) - np.asarray(lo, float)
    return float(np.prod(d)), float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[0] * d[2]))


def mean_and_se(x):
    x = np.asarray(x, dtype=np.float64)
    return x.mean(), x.std(ddof=1) / np.sqrt(x.size)


def uniform_hemisphere_lines(lo, hi, n, rng):
    """A WRONG sampler for the negative control: uniform (not cosine) directions."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = hi - lo
    areas = np.array([d[1] * d[2], d[0] * d[2], d[0] * d[1]])
    face = rng.choice(6, size=n, p=np.repeat(areas, 2) / (2 * areas.sum()))
    axis, on_hi = face // 2, face % 2 == 1
    p = lo + rng.random((n, 3)) * d
    rows = np.arange(n)
    p[rows, axis] = np.where(on_hi, hi[axis], lo[axis])
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    inward = np.where(on_hi, -1.0, 1.0)
    v[rows, axis] = np.abs(v[rows, axis]) * inward
    return p - 1e-3 * v, v


# ------------------------------------------------------------------------------
# isotropic: basic properties
# ------------------------------------------------------------------------------

@pytest.mark.parametrize("i", range(len(BOXES)))
def test_isotropic_unit_finite_outside_deterministic(i):
    lo, hi = BOXES[i]
    o, d = rays.isotropic(lo, hi, 20_000, 1000 + i)
    assert o.shape == d.shape == (20_000, 3)
    assert o.dtype == d.dtype == np.float64
    assert np.all(np.isfinite(o)) and np.all(np.isfinite(d))
    assert np.abs(np.linalg.norm(d, axis=1) - 1.0).max() < UNIT_TOLERANCE
    # origins strictly outside the box
    outside = np.any((o < np.asarray(lo)) | (o > np.asarray(hi)), axis=1)
    assert np.all(outside)
    # every line hits the box, entering exactly `margin` along the ray
    t_in, t_out = rays.box_chords(o, d, lo, hi)
    assert np.all(t_in < t_out)
    margin = rays.ISOTROPIC_MARGIN_FRACTION_OF_DIAGONAL * np.linalg.norm(np.subtract(hi, lo))
    assert np.allclose(t_in, margin, rtol=1e-9, atol=1e-12 * np.abs(o).max())
    o2, d2 = rays.isotropic(lo, hi, 20_000, 1000 + i)
    assert o.tobytes() == o2.tobytes() and d.tobytes() == d2.tobytes()
    o3, _ = rays.isotropic(lo, hi, 20_000, 2000 + i)
    assert not np.array_equal(o, o3)


def test_isotropic_flat_box():
    lo, hi = (0.0, 0.0, 1.0), (2.0, 3.0, 1.0)  # a rectangle in the plane z = 1
    o, d = rays.isotropic(lo, hi, 5_000, 1000)
    assert np.all(np.isfinite(o)) and np.all(d[:, 2] != 0.0)
    t = (1.0 - o[:, 2]) / d[:, 2]
    assert np.all(t > 0)
    hit = o + t[:, None] * d
    assert np.all((hit[:, 0] >= -1e-12) & (hit[:, 0] <= 2 + 1e-12))
    assert np.all((hit[:, 1] >= -1e-12) & (hit[:, 1] <= 3 + 1e-12))


# ------------------------------------------------------------------------------
# isotropic: Crofton's formulas (exactness of the line measure)
# ------------------------------------------------------------------------------

@pytest.mark.parametrize("i", range(len(BOXES)))
def test_isotropic_mean_chord_is_4V_over_S(i):
    lo, hi = BOXES[i]
    o, d = rays.isotropic(lo, hi, 200_000, 1000 + i)
    t_in, t_out = rays.box_chords(o, d, lo, hi)
    mean, se = mean_and_se(t_out - t_in)
    vol, area = box_volume_area(lo, hi)
    exact = 4.0 * vol / area
    assert se < 0.01 * exact  # the check is sharp enough to mean something
    assert abs(mean - exact) < Z_TOLERANCE * se, (mean, exact, se)


@pytest.mark.parametrize("i", range(len(BOXES)))
def test_negative_control_uniform_directions_fail_chord_check(i):
    """The chord check has power: a sampler with uniform directions fails it on every box."""
    lo, hi = BOXES[i]
    o, d = uniform_hemisphere_lines(lo, hi, 200_000, np.random.default_rng(1000 + i))
    t_in, t_out = rays.box_chords(o, d, lo, hi)
    mean, se = mean_and_se(t_out - t_in)
    vol, area = box_volume_area(lo, hi)
    assert abs(mean - 4.0 * vol / area) > Z_TOLERANCE * se


@pytest.mark.parametrize("i", range(3))
def test_isotropic_hit_fraction_of_inner_sphere_is_area_ratio(i):
    lo, hi = BOXES[i]
    lo_a, hi_a = np.asarray(lo), np.asarray(hi)
    rng = np.random.default_rng(1000 + i)
    radius = 0.4 * 0.5 * (hi_a - lo_a).min()
    centre = lo_a + radius + rng.random(3) * (hi_a - lo_a - 2 * radius)
    o, d = rays.isotropic(lo, hi, 200_000, 1000 + i)
    w = centre - o
    dist2 = (w * w).sum(axis=1) - np.einsum("ij,ij->i", w, d) ** 2
    hit = dist2 < radius**2
    _, area = box_volume_area(lo, hi)
    p = 4.0 * np.pi * radius**2 / area
    se = np.sqrt(p * (1 - p) / hit.size)
    assert abs(hit.mean() - p) < Z_TOLERANCE * se, (hit.mean(), p, se)


@pytest.mark.parametrize("i", range(3))
def test_isotropic_hit_fraction_of_inner_box_is_area_ratio(i):
    lo, hi = BOXES[i]
    lo_a, hi_a = np.asarray(lo), np.asarray(hi)
    rng = np.random.default_rng(1000 + i)
    a, b = rng.random((2, 3))
    k_lo = lo_a + np.minimum(a, b) * (hi_a - lo_a)
    k_hi = lo_a + np.maximum(a, b) * (hi_a - lo_a)
    o, d = rays.isotropic(lo, hi, 200_000, 1000 + i)
    t_in, t_out = rays.box_chords(o, d, k_lo, k_hi)
    hit = t_in < t_out
    p = box_volume_area(k_lo, k_hi)[1] / box_volume_area(lo, hi)[1]
    se = np.sqrt(p * (1 - p) / hit.size)
    assert abs(hit.mean() - p) < Z_TOLERANCE * se, (hit.mean(), p, se)


def cells_visited(o, d, lo, counts, h):
    """Cells of a grid (counts (3,) cells of side h from lo) each line passes through, (n,).

    Brute force: a slab test of every line against every cell; a cell counts
    when the line's chord inside it has positive length.
    """
    ix, iy, iz = np.meshgrid(*(np.arange(c) for c in counts), indexing="ij")
    cell_lo = np.asarray(lo, float) + h * np.stack([ix, iy, iz], axis=-1).reshape(-1, 3)
    total = np.zeros(o.shape[0], dtype=np.int64)
    for c_lo in cell_lo:
        t_in, t_out = rays.box_chords(o, d, c_lo, c_lo + h)
        total += t_in < t_out
    return total


@pytest.mark.parametrize(
    "i, lo, counts, h",
    [
        (0, (0.0, 0.0, 0.0), (4, 4, 4), 0.25),  # cube: exactly m = 4 cells per line
        (1, (1.0, -2.0, 0.5), (2, 4, 6), 0.5),  # 1 x 2 x 3 box: 6V/(S h) = 36/11
        (2, (0.0, 0.0, 0.0), (1, 3, 9), 1.0 / 3.0),  # 1/3 x 1 x 3 slab
    ],
)
def test_isotropic_cells_visited_is_6V_over_Sh(i, lo, counts, h):
    hi = tuple(np.asarray(lo) + h * np.asarray(counts))
    o, d = rays.isotropic(lo, hi, 40_000, 1000 + i)
    visited = cells_visited(o, d, lo, counts, h)
    assert visited.min() >= 1
    vol, area = box_volume_area(lo, hi)
    exact = 6.0 * vol / (area * h)
    if counts == (4, 4, 4):
        assert exact == pytest.approx(4.0, rel=1e-12)
    mean, se = mean_and_se(visited)
    assert se < 0.01 * exact
    assert abs(mean - exact) < Z_TOLERANCE * se, (mean, exact, se)


@pytest.mark.parametrize("i", range(len(BOXES)))
def test_isotropic_direction_second_moment_is_projected_area_weighted(i):
    """Direction density is proportional to the box's projected area |u_x| A_x + |u_y| A_y + |u_z| A_z.

    Integrating u_a^2 against it over the sphere gives E[u_a^2] = (1 + A_a / sum A) / 4
    (A_a = area of a face perpendicular to axis a); uniform directions give 1/3.
    """
    lo, hi = BOXES[i]
    o, d = rays.isotropic(lo, hi, 200_000, 1000 + i)
    dims = np.subtract(hi, lo)
    areas = np.array([dims[1] * dims[2], dims[0] * dims[2], dims[0] * dims[1]])
    exact = (1.0 + areas / areas.sum()) / 4.0
    for a in range(3):
        mean, se = mean_and_se(d[:, a] ** 2)
        assert abs(mean - exact[a]) < Z_TOLERANCE * se, (a, mean, exact[a], se)
    if i == len(BOXES) - 1:  # the slab: far from uniform, visibly
        mean_z, se_z = mean_and_se(d[:, 2] ** 2)
        assert abs(mean_z - 1.0 / 3.0) > 10 * Z_TOLERANCE * se_z


# ------------------------------------------------------------------------------
# camera
# ------------------------------------------------------------------------------

def camera_axes(view=rays.DEFAULT_VIEW_DIRECTION):
    fwd = np.asarray(view, float) / np.linalg.norm(view)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return fwd, right, np.cross(right, fwd)


@pytest.mark.parametrize("i", range(len(BOXES)))
def test_camera_grid_frames_box_from_outside(i):
    lo, hi = BOXES[i]
    lo_a, hi_a = np.asarray(lo), np.asarray(hi)
    o, d = rays.camera_grid(lo, hi, 33, 21)
    assert o.shape == d.shape == (33 * 21, 3)
    assert np.abs(np.linalg.norm(d, axis=1) - 1.0).max() < UNIT_TOLERANCE
    eye = o[0]
    assert np.all(o == eye)
    assert np.any((eye < lo_a) | (eye > hi_a))
    centre = 0.5 * (lo_a + hi_a)
    radius = 0.5 * np.linalg.norm(hi_a - lo_a)
    half = np.radians(rays.DEFAULT_FOV_DEG) / 2
    assert np.linalg.norm(centre - eye) == pytest.approx(radius / np.sin(half), rel=1e-12)
    # the centre pixel of an odd-sized image looks exactly at the box centre
    mid = 10 * 33 + 16
    to_centre = (centre - eye) / np.linalg.norm(centre - eye)
    assert np.allclose(d[mid], to_centre, atol=1e-12)
    # every box corner is within the half field of view of the centre line
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    to_corner = corners - eye
    cos = to_corner @ to_centre / np.linalg.norm(to_corner, axis=1)
    assert np.all(cos >= np.cos(half) - 1e-12)


def test_camera_grid_row_major_pixel_mapping():
    lo, hi = BOXES[1]
    width, height = 16, 9
    fwd, right, up = camera_axes()
    tan_half = np.tan(np.radians(rays.DEFAULT_FOV_DEG) / 2)
    short = min(width, height)
    for k, seed in enumerate([None, 1000, 1001]):
        o, d = rays.camera_grid(lo, hi, width, height, seed=seed)
        # image-plane coordinates back to continuous pixel coordinates
        x = (d @ right) / (d @ fwd) / (tan_half * width / short)
        y = (d @ up) / (d @ fwd) / (tan_half * height / short)
        col_f = (x + 1.0) / 2.0 * width
        row_f = (1.0 - y) / 2.0 * height
        row, col = np.divmod(np.arange(width * height), width)
        if seed is None:
            assert np.allclose(col_f, col + 0.5, atol=1e-9), k
            assert np.allclose(row_f, row + 0.5, atol=1e-9), k
        else:
            assert np.all((col_f > col - 1e-9) & (col_f < col + 1 + 1e-9)), k
            assert np.all((row_f > row - 1e-9) & (row_f < row + 1 + 1e-9)), k
            assert not np.allclose(col_f, col + 0.5), k


@pytest.mark.parametrize("i, n", [(0, 1), (1, 17), (2, 10_000), (3, 4_321)])
def test_camera_rays_count_jitter_determinism(i, n):
    lo, hi = BOXES[i % len(BOXES)]
    o, d = rays.camera(lo, hi, n, 1000 + i)
    assert o.shape == d.shape == (n, 3)
    assert np.all(np.isfinite(d)) and np.abs(np.linalg.norm(d, axis=1) - 1.0).max() < UNIT_TOLERANCE
    o2, d2 = rays.camera(lo, hi, n, 1000 + i)
    assert o.tobytes() == o2.tobytes() and d.tobytes() == d2.tobytes()
    _, d3 = rays.camera(lo, hi, n, 2000 + i)
    assert not np.array_equal(d, d3)
    # all inside the field of view
    fwd, right, up = camera_axes()
    tan_half = np.tan(np.radians(rays.DEFAULT_FOV_DEG) / 2)
    assert np.all(np.abs(d @ right) / (d @ fwd) <= tan_half * (1 + 1e-12))
    assert np.all(np.abs(d @ up) / (d @ fwd) <= tan_half * (1 + 1e-12))
    if n >= 1000:
        # pixels cover the square image uniformly: image-plane x has mean 0, variance 1/3
        x = (d @ right) / (d @ fwd) / tan_half
        mean, se = mean_and_se(x)
        assert abs(mean) < Z_TOLERANCE * se
        assert abs(x.var() - 1.0 / 3.0) < 0.02
        # the image frames the box: a good share of rays hit it, not all
        t_in, t_out = rays.box_chords(o, d, lo, hi)
        hit = (t_in < t_out) & (t_out > 0)
        assert 0.05 < hit.mean() < 1.0


# ------------------------------------------------------------------------------
# surface
# ------------------------------------------------------------------------------

TRIANGLE = (np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.5], [0.3, 1.5, 1.0]]), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("i, side", [(0, "front"), (1, "back"), (2, "random")])
def test_surface_rays_on_one_triangle(i, side):
    v, f = TRIANGLE
    n_rays = 100_000
    o, d = rays.surface(v, f, n_rays, 1000 + i, side=side)
    assert np.abs(np.linalg.norm(d, axis=1) - 1.0).max() < UNIT_TOLERANCE
    a, b, c = v
    nrm = np.cross(b - a, c - a)
    nrm /= np.linalg.norm(nrm)
    eps = rays.SURFACE_OFFSET_FRACTION_OF_DIAGONAL * np.linalg.norm(np.ptp(v, axis=0))
    height = (o - a) @ nrm
    assert np.allclose(np.abs(height), eps, rtol=1e-6)
    sign = np.sign(height)
    if side == "front":
        assert np.all(sign > 0)
    elif side == "back":
        assert np.all(sign < 0)
    else:
        frac = (sign > 0).mean()
        assert abs(frac - 0.5) < Z_TOLERANCE * np.sqrt(0.25 / n_rays)
    # foot points inside the triangle, uniform: mean is the centroid
    foot = o - height[:, None] * nrm
    m = np.stack([b - a, c - a], axis=1)
    uv = np.linalg.lstsq(m, (foot - a).T, rcond=None)[0].T
    assert np.all(uv >= -1e-9) and np.all(uv.sum(axis=1) <= 1 + 1e-9)
    for axis in range(3):
        mean, se = mean_and_se(foot[:, axis])
        assert abs(mean - v[:, axis].mean()) < Z_TOLERANCE * se
    # directions leave on the origin's side, cosine-weighted: E[cos] = 2/3, E[cos^2] = 1/2
    cos = (d @ nrm) * sign
    assert np.all(cos > 0)
    for power, exact in ((1, 2.0 / 3.0), (2, 0.5)):
        mean, se = mean_and_se(cos**power)
        assert abs(mean - exact) < Z_TOLERANCE * se, (power, mean, se)
    # azimuth is uniform: the tangential mean is zero
    tangential = d - (d @ nrm)[:, None] * nrm
    for axis in range(3):
        mean, se = mean_and_se(tangential[:, axis])
        assert abs(mean) < Z_TOLERANCE * se


@pytest.mark.parametrize("i", range(3))
def test_surface_area_weighting_and_degenerate_triangles_skipped(i):
    # triangle 0: area 1/2 at z = 0; triangle 1: degenerate; triangle 2: area 3/2 at z = 5
    v = np.array(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2], [3, 3, 3], [4, 4, 4], [0, 0, 5], [3, 0, 5], [0, 1, 5]],
        dtype=np.float64,
    )
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    n_rays = 50_000
    o, _ = rays.surface(v, f, n_rays, 1000 + i, side="front")
    on_first = np.abs(o[:, 2]) < 1.0
    on_last = np.abs(o[:, 2] - 5.0) < 1.0
    assert np.all(on_first | on_last)  # never on the degenerate one
    p = 0.25
    assert abs(on_first.mean() - p) < Z_TOLERANCE * np.sqrt(p * (1 - p) / n_rays)


@pytest.mark.parametrize("i, side, sign", [(0, "front", 1.0), (1, "back", -1.0)])
def test_surface_sides_on_closed_sphere(i, side, sign):
    """Front rays of an outward icosphere leave outward, back rays inward.

    Facet normals are within a few degrees of the radial direction, so
    cos(angle to radial) averages close to the cosine-weighted 2/3.
    """
    v, f = scenes.icosphere(16)
    o, d = rays.surface(v, f, 20_000, 1000 + i, side=side)
    radial = o / np.linalg.norm(o, axis=1, keepdims=True)
    cos = sign * np.einsum("ij,ij->i", d, radial)
    assert (cos > 0).mean() > 0.99
    assert abs(cos.mean() - 2.0 / 3.0) < 0.01
    o2, d2 = rays.surface(v, f, 20_000, 1000 + i, side=side)
    assert o.tobytes() == o2.tobytes() and d.tobytes() == d2.tobytes()


# ------------------------------------------------------------------------------
# registry and bad input
# ------------------------------------------------------------------------------

@pytest.mark.parametrize("i, name", list(enumerate(["isotropic", "camera", "surface"])))
def test_ray_set_registry(i, name):
    assert rays.ray_set_names() == ["isotropic", "camera", "surface"]
    v, f = scenes.load_builtin("cylinder196")
    o, d = rays.make_rays(name, v, f, 1_000, 1000 + i)
    assert o.shape == d.shape == (1_000, 3)
    assert np.all(np.isfinite(o)) and np.abs(np.linalg.norm(d, axis=1) - 1.0).max() < UNIT_TOLERANCE
    o2, d2 = rays.RAY_SETS[name](v, f, 1_000, 1000 + i)
    assert o.tobytes() == o2.tobytes() and d.tobytes() == d2.tobytes()


def test_unknown_ray_set_lists_names():
    v, f = TRIANGLE
    with pytest.raises(ValueError) as err:
        rays.make_rays("primary", v, f, 10, 0)
    for name in ("isotropic", "camera", "surface"):
        assert name in str(err.value)


GOOD_LO, GOOD_HI = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n=0), "n"),
        (dict(n=-3), "n"),
        (dict(n=2.5), "n"),
        (dict(n=True), "n"),
        (dict(lo=(0.0, 2.0, 0.0)), "lo <= hi"),
        (dict(lo=(0.0, float("nan"), 0.0)), "finite"),
        (dict(hi=(1.0, float("inf"), 1.0)), "finite"),
        (dict(lo=(0.0, 0.0)), "shape"),
        (dict(lo=(1.0, 1.0, 1.0)), "zero surface area|single point"),
        (dict(seed=-1), "seed"),
        (dict(seed=0.5), "seed"),
    ],
)
@pytest.mark.parametrize("generator", ["isotropic", "camera"])
def test_box_ray_sets_reject_bad_input(generator, kwargs, match):
    args = dict(lo=GOOD_LO, hi=GOOD_HI, n=10, seed=0)
    args.update(kwargs)
    if generator == "isotropic" and "lo" in kwargs and kwargs["lo"] == (1.0, 1.0, 1.0):
        match = "zero surface area"
    with pytest.raises(ValueError, match=match):
        getattr(rays, generator)(args["lo"], args["hi"], args["n"], args["seed"])


def test_isotropic_rejects_bad_margin_and_line_box():
    with pytest.raises(ValueError, match="margin"):
        rays.isotropic(GOOD_LO, GOOD_HI, 10, 0, margin_fraction=0.0)
    with pytest.raises(ValueError, match="zero surface area"):
        rays.isotropic((0.0, 0.0, 0.0), (0.0, 0.0, 5.0), 10, 0)  # a segment


def test_camera_rejects_bad_view_and_fov():
    with pytest.raises(ValueError, match="view_direction"):
        rays.camera(GOOD_LO, GOOD_HI, 10, 0, view_direction=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="fov"):
        rays.camera(GOOD_LO, GOOD_HI, 10, 0, fov_deg=180.0)
    with pytest.raises(ValueError, match="n"):
        rays.camera_grid(GOOD_LO, GOOD_HI, 0, 10)


def test_camera_looking_straight_down_is_well_defined():
    o, d = rays.camera_grid(GOOD_LO, GOOD_HI, 5, 5, view_direction=(0.0, 0.0, -1.0))
    assert np.all(np.isfinite(d))
    assert np.allclose(d[12], (0.0, 0.0, -1.0))


@pytest.mark.parametrize(
    "vertices, faces, kwargs, match",
    [
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), {}, "vertices"),
        (TRIANGLE[0], np.array([[0, 1, 3]]), {}, "face indices"),
        (TRIANGLE[0], np.array([[0.0, 1.0, 2.0]]), {}, "integer"),
        (np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), {}, "NaN"),
        (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]), np.array([[0, 1, 2]]), {}, "zero total area"),
        (TRIANGLE[0], TRIANGLE[1], {"side": "inside"}, "side"),
        (TRIANGLE[0], TRIANGLE[1], {"n": 0}, "n"),
    ],
)
def test_surface_rejects_bad_input(vertices, faces, kwargs, match):
    n = kwargs.pop("n", 10)
    with pytest.raises(ValueError, match=match):
        rays.surface(vertices, faces, n, 0, **kwargs)


@pytest.mark.parametrize("exponent", [-200, -20, 20, 200])
def test_ray_sets_on_boxes_of_extreme_scale(exponent):
    """Boxes of 1e-200 to 1e200: areas and diagonals neither overflow nor underflow (a fuzzing find)."""
    scale = 10.0 ** exponent
    lo, hi = np.array([-1.0, 0.0, 2.0]) * scale, np.array([3.0, 0.5, 2.25]) * scale
    o, d = rays.isotropic(lo, hi, 512, seed=exponent + 1000)
    assert np.all(np.isfinite(o)) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    diag = np.linalg.norm((hi - lo) / scale) * scale
    entry = o + (rays.ISOTROPIC_MARGIN_FRACTION_OF_DIAGONAL * diag) * d
    inside = np.all((entry >= lo - 1e-9 * scale) & (entry <= hi + 1e-9 * scale), axis=1)
    assert inside.all(), f"{(~inside).sum()} rays do not enter the box where they should"
    o, d = rays.camera(lo, hi, 64, seed=exponent + 2000)
    assert np.all(np.isfinite(o)) and np.allclose(np.linalg.norm(d, axis=1), 1.0)


def test_isotropic_rejects_a_box_too_wide_for_float64():
    with pytest.raises(ValueError, match="too wide for float64"):
        rays.isotropic([-1e308, 0, 0], [1e308, 1, 1], 8, seed=0)


def test_isotropic_refuses_origins_beyond_float64():
    """Rays start outside the box; for a box at float64's limit they cannot (a fuzzing find)."""
    with pytest.raises(ValueError, match="too close to float64's limit"):
        rays.isotropic([0.2e308, 0, 0], [1.79e308, 1e307, 1e307], 512, seed=0)

"""Ray sets for timing and counting, deterministic by seed.

Every generator returns

    origins    : (n, 3) float64, scene units
    directions : (n, 3) float64, unit length

and raises ValueError on bad arguments (n <= 0, non-finite or inverted box,
empty mesh, ...). The same arguments give bit-identical arrays.

``isotropic``
    Isotropic uniform random lines that hit the box, sampled exactly: the
    measure of lines invariant under rigid motions, conditioned on hitting the
    box (DESIGN section 3.2). Under it Crofton's formulas hold exactly:
    P(line hits convex K inside the box) = S(K) / S, mean chord = 4 V / S,
    mean cells visited = 6 V / (S h). This is the ray distribution of the cost
    model, so counts measured on it can be compared with the model exactly.
``camera``, ``camera_grid``
    Pinhole-camera primary rays looking at the box centre from outside.
``surface``
    Ambient-occlusion-style rays leaving area-uniform points of a mesh.
``aimed_at_edges``
    Rays from inside a closed mesh aimed exactly at its vertices and edges,
    where a non-watertight triangle test lets rays slip through (these
    directions are ``target - origin``, not unit length, so t = 1 at the target).

``RAY_SETS`` maps a name to a generator with the common signature
``(vertices, faces, n, seed) -> (origins, directions)`` (the box is the
mesh's bounding box), for the command line.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = [
    "ISOTROPIC_MARGIN_FRACTION_OF_DIAGONAL",
    "SURFACE_OFFSET_FRACTION_OF_DIAGONAL",
    "DEFAULT_VIEW_DIRECTION",
    "DEFAULT_FOV_DEG",
    "RAY_SETS",
    "ray_set_names",
    "make_rays",
    "isotropic",
    "camera",
    "camera_grid",
    "surface",
    "aimed_at_edges",
    "unique_edges",
    "mesh_bounds",
    "box_chords",
]

Rays = tuple[np.ndarray, np.ndarray]

# isotropic: origins start this far (along the ray, as a fraction of the box
# diagonal) before the point where the line enters the box.
ISOTROPIC_MARGIN_FRACTION_OF_DIAGONAL = 0.01
# surface: origins are lifted off the surface along the geometric normal by
# this fraction of the mesh's bounding-box diagonal (self-intersection epsilon).
SURFACE_OFFSET_FRACTION_OF_DIAGONAL = 1e-4
# camera: direction the camera looks along (towards the box centre); generic,
# so no image row or column lines up with a grid axis or a box diagonal.
DEFAULT_VIEW_DIRECTION = (0.55, 0.75, -0.37)
DEFAULT_FOV_DEG = 40.0  # full field of view across the narrower image side
# camera: distance = bounding-sphere radius / sin(fov / 2) * this factor; 1 makes
# the sphere around the box exactly touch the narrower image edges.
CAMERA_FRAMING_FACTOR = 1.0
# camera: "up" hint; replaced by +y when the view direction is within this
# angle's sine of it (nearly vertical view).
_UP_HINT = np.array([0.0, 0.0, 1.0])
_UP_PARALLEL_SINE = 1e-3
SURFACE_SIDES = ("random", "front", "back")


# ----------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------

def _check_n(n) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"number of rays n must be an integer, got {n!r}")
    if n <= 0:
        raise ValueError(f"number of rays n must be > 0, got {n}")
    return int(n)


def _rng(seed) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer or a numpy Generator, got {seed!r}")
    return np.random.default_rng(int(seed))


def _check_box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,):
        raise ValueError(f"box corners lo and hi must have shape (3,), got {lo.shape} and {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"box corners must be finite, got lo={lo.tolist()} hi={hi.tolist()}")
    if not np.all(lo <= hi):
        raise ValueError(f"box must have lo <= hi on every axis, got lo={lo.tolist()} hi={hi.tolist()}")
    return lo, hi


def _extent(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """hi - lo, (3,); a box wider than float64 can hold raises ValueError."""
    with np.errstate(over="ignore"):
        d = hi - lo
    if not np.all(np.isfinite(d)):
        raise ValueError(f"box is too wide for float64: lo={lo.tolist()}, hi={hi.tolist()}")
    return d


def _diagonal(lo: np.ndarray, hi: np.ndarray) -> float:
    """|hi - lo| without overflow or underflow of the squares (any finite box)."""
    d = np.abs(_extent(lo, hi))
    scale = float(d.max())
    return scale * float(np.linalg.norm(d / scale)) if scale > 0 else 0.0


def _face_areas(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Area of one box face perpendicular to each axis, (3,), in units of the largest extent squared.

    Relative, so the areas (and the face probabilities made from them) neither
    overflow for boxes of 1e200 nor underflow for boxes of 1e-200.
    """
    d = _extent(lo, hi)
    scale = float(d.max())
    if scale > 0:
        d = d / scale
    return np.array([d[1] * d[2], d[0] * d[2], d[0] * d[1]])


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F >= 1, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integer indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(f"face indices must be in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices contain NaN or Inf")
    return v, f.astype(np.int64, copy=False)


def mesh_bounds(vertices) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of vertices (V, 3): lo (3,), hi (3,) float64."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices contain NaN or Inf")
    return v.min(axis=0), v.max(axis=0)


# ----------------------------------------------------------------------------------
# sampling helpers
# ----------------------------------------------------------------------------------

def _cosine_local(rng: np.random.Generator, n: int) -> np.ndarray:
    """Cosine-weighted directions about +z, (n, 3): density cos(theta) / pi.

    Malley's method: a uniform point in the unit disc lifted to the hemisphere.
    z = sqrt(1 - u1) > 0 since u1 < 1.
    """
    u = rng.random((n, 2))
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u[:, 0])], axis=1)


def _orthonormal_basis(nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangents t, b (n, 3) with (t, b, nrm) right-handed orthonormal, for unit nrm (n, 3).

    Branchless construction of Duff et al., "Building an Orthonormal Basis,
    Revisited", JCGT 2017.
    """
    x, y, z = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    bt = np.stack([b, sign + y * y * a, -y], axis=1)
    return t, bt


def _normalise(d: np.ndarray) -> np.ndarray:
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------
# ray sets
# ----------------------------------------------------------------------------------

def box_chords(origins, directions, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Where lines enter and leave the box [lo, hi]: ``(t_in, t_out)``, each (n,).

    The slab test per axis; a direction component of zero leaves that axis's slab out
    when the origin lies strictly inside it (its quotients are -inf and +inf), and makes
    the line miss when the origin lies on one of its planes (``fmin``/``fmax`` take the
    infinite quotient over the NaN one).  A line that misses the box has ``t_in > t_out``.
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (np.asarray(lo, dtype=np.float64) - o) * inv
        t1 = (np.asarray(hi, dtype=np.float64) - o) * inv
    return np.fmin(t0, t1).max(axis=1), np.fmax(t0, t1).min(axis=1)


def isotropic(
    lo, hi, n: int, seed, margin_fraction: float = ISOTROPIC_MARGIN_FRACTION_OF_DIAGONAL
) -> Rays:
    """Isotropic uniform random lines through the box [lo, hi], sampled exactly.

    The rigid-motion-invariant measure of lines, restricted to lines that hit
    a convex body, is the same as: a point uniform (by area) on the body's
    surface, and a direction into the body with density proportional to
    cos(angle to the inward normal) (Santalo, "Integral Geometry and
    Geometric Probability", the density of lines dG = |cos theta| dA dw).
    For the box: a face chosen with probability area / S, a uniform point on
    it, and a cosine-weighted direction about its inward normal. Each line
    crosses the box surface twice but is generated from its entry point only,
    which is exactly the line measure (a line hitting the box has one entry).

    The origin is then moved back along -direction by ``margin_fraction`` of
    the box diagonal, so every ray starts outside the box and enters it at
    parameter t = margin_fraction * |hi - lo| exactly. Directions are not
    uniform on the sphere: their density is proportional to the box's
    projected area along them.

    lo, hi : (3,) box corners, lo <= hi, finite; one extent may be zero (a flat
        box), but the surface area must be positive.
    n : number of rays (> 0). seed : non-negative int (or a numpy Generator).
    Returns origins (n, 3) float64 and unit directions (n, 3) float64.
    """
    lo, hi = _check_box(lo, hi)
    n = _check_n(n)
    if not (np.isfinite(margin_fraction) and margin_fraction > 0):
        raise ValueError(f"margin_fraction must be finite and > 0, got {margin_fraction}")
    areas = _face_areas(lo, hi)
    total = 2.0 * areas.sum()
    if not total > 0:
        raise ValueError(f"box has zero surface area (lo={lo.tolist()}, hi={hi.tolist()})")
    rng = _rng(seed)
    # face k: axis k // 2, side k % 2 (0: the lo face, inward normal +e_axis)
    p_face = np.repeat(areas, 2) / total
    face = rng.choice(6, size=n, p=p_face)
    axis = face // 2
    on_hi = (face % 2).astype(bool)
    points = lo + rng.random((n, 3)) * (hi - lo)
    rows = np.arange(n)
    points[rows, axis] = np.where(on_hi, hi[axis], lo[axis])
    local = _cosine_local(rng, n)
    # map local (x, y, z) so that z lies along the inward normal of the chosen face
    inward = np.where(on_hi, -1.0, 1.0)
    directions = np.empty((n, 3))
    directions[rows, axis] = local[:, 2] * inward
    directions[rows, (axis + 1) % 3] = local[:, 0]
    directions[rows, (axis + 2) % 3] = local[:, 1]
    directions = _normalise(directions)
    margin = margin_fraction * _diagonal(lo, hi)
    with np.errstate(over="ignore", invalid="ignore"):
        origins = points - margin * directions
    if not np.all(np.isfinite(origins)):
        raise ValueError(f"box is too close to float64's limit for rays from outside it: lo={lo.tolist()}, "
                         f"hi={hi.tolist()}")
    return np.ascontiguousarray(origins), np.ascontiguousarray(directions)


def _camera_frame(lo, hi, view_direction, fov_deg):
    """Eye (3,), forward, right, up (3,) unit vectors and tan(fov / 2) for the box."""
    lo, hi = _check_box(lo, hi)
    fwd = np.asarray(view_direction, dtype=np.float64)
    if fwd.shape != (3,) or not np.all(np.isfinite(fwd)) or not np.linalg.norm(fwd) > 0:
        raise ValueError(f"view_direction must be a finite non-zero 3-vector, got {view_direction!r}")
    if not (np.isfinite(fov_deg) and 0 < fov_deg < 180):
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    fwd = fwd / np.linalg.norm(fwd)
    radius = 0.5 * _diagonal(lo, hi)
    if not radius > 0:
        raise ValueError(f"box is a single point (lo = hi = {lo.tolist()}); a camera cannot frame it")
    half = np.radians(fov_deg) / 2.0
    distance = CAMERA_FRAMING_FACTOR * radius / np.sin(half)
    centre = 0.5 * (lo + hi)
    eye = centre - distance * fwd
    up_hint = _UP_HINT
    if not np.linalg.norm(np.cross(fwd, _UP_HINT)) > _UP_PARALLEL_SINE:
        up_hint = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up_hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return eye, fwd, right, up, np.tan(half)


def _pixel_rays(frame, width, height, col, row, jitter) -> Rays:
    """Rays through image points (col + jitter_x, row + jitter_y), pixel units, row 0 at the top."""
    eye, fwd, right, up, tan_half = frame
    short = min(width, height)
    x = (2.0 * (col + jitter[:, 0]) / width - 1.0) * tan_half * (width / short)
    y = (1.0 - 2.0 * (row + jitter[:, 1]) / height) * tan_half * (height / short)
    d = _normalise(fwd[None, :] + x[:, None] * right[None, :] + y[:, None] * up[None, :])
    origins = np.broadcast_to(eye, d.shape).copy()
    return np.ascontiguousarray(origins), np.ascontiguousarray(d)


def camera_grid(
    lo,
    hi,
    width: int,
    height: int,
    view_direction=DEFAULT_VIEW_DIRECTION,
    fov_deg: float = DEFAULT_FOV_DEG,
    seed=None,
) -> Rays:
    """Primary rays of a width x height pinhole image of the box, in row-major pixel order.

    Ray ``row * width + col`` goes through the centre of pixel (col, row)
    (row 0 at the top), or a uniformly jittered point of it when ``seed`` is
    given. The camera looks along ``view_direction`` at the box centre from
    outside, at distance ``radius / sin(fov / 2)`` where radius is half the
    box diagonal, so the whole box is in view; ``fov_deg`` spans the narrower
    image side. Up is +z (or +y when looking nearly vertically).

    Returns origins (width*height, 3) float64 (all the eye point) and unit
    directions (width*height, 3) float64.
    """
    width = _check_n(width)
    height = _check_n(height)
    frame = _camera_frame(lo, hi, view_direction, fov_deg)
    idx = np.arange(width * height)
    row, col = np.divmod(idx, width)
    if seed is None:
        jitter = np.full((idx.size, 2), 0.5)
    else:
        jitter = _rng(seed).random((idx.size, 2))
    return _pixel_rays(frame, width, height, col.astype(np.float64), row.astype(np.float64), jitter)


def camera(
    lo,
    hi,
    n: int,
    seed,
    view_direction=DEFAULT_VIEW_DIRECTION,
    fov_deg: float = DEFAULT_FOV_DEG,
) -> Rays:
    """n jittered pinhole-camera primary rays looking at the box centre from outside.

    The image is the smallest square of w x w >= n pixels; n distinct pixels
    are drawn at random (all of them when n = w^2), kept in row-major order
    (coherent, like a renderer's primary rays), and each ray passes through a
    uniformly jittered point of its pixel. Camera placement as ``camera_grid``.

    Returns origins (n, 3) float64 (all the eye point) and unit directions (n, 3).
    """
    n = _check_n(n)
    rng = _rng(seed)
    frame = _camera_frame(lo, hi, view_direction, fov_deg)
    w = int(np.ceil(np.sqrt(n)))
    while w * w < n:  # guard against sqrt rounding
        w += 1
    pixels = np.sort(rng.permutation(w * w)[:n]) if w * w > n else np.arange(n)
    row, col = np.divmod(pixels, w)
    jitter = rng.random((n, 2))
    return _pixel_rays(frame, w, w, col.astype(np.float64), row.astype(np.float64), jitter)


def surface(vertices, faces, n: int, seed, side: str = "random") -> Rays:
    """Rays leaving uniformly random points of a mesh surface (ambient-occlusion style).

    Points are uniform by area over the mesh (a triangle chosen with
    probability area / total area, then a uniform point in it). Each ray
    leaves along the geometric normal's side given by ``side``:

    - ``"random"`` (default): front or back with probability 1/2 each, per ray;
      right for open meshes and triangle soups, whose back faces are visible too;
    - ``"front"``: the side of normal (b - a) x (c - a) (outside of a closed,
      outward-oriented mesh); ``"back"``: the other side.

    The origin is offset from the surface along the chosen normal by
    ``SURFACE_OFFSET_FRACTION_OF_DIAGONAL`` times the mesh's bounding-box
    diagonal; the direction is cosine-weighted about that normal (density
    cos(theta) / pi). Zero-area triangles are never chosen.

    vertices (V, 3) float, faces (F, 3) int. Returns origins (n, 3) float64
    and unit directions (n, 3) float64.
    """
    v, f = _check_mesh(vertices, faces)
    n = _check_n(n)
    if side not in SURFACE_SIDES:
        raise ValueError(f"side must be one of {SURFACE_SIDES}, got {side!r}")
    rng = _rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    cdf = np.cumsum(double_area)
    total = cdf[-1]
    if not (np.isfinite(total) and total > 0):
        raise ValueError("mesh has zero total area; no surface to sample")
    tri = np.searchsorted(cdf, rng.random(n) * total, side="right")
    tri = np.minimum(tri, f.shape[0] - 1)  # guard the top end against rounding
    uv = rng.random((n, 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    at, bt, ct = a[tri], b[tri], c[tri]
    points = at + uv[:, 0:1] * (bt - at) + uv[:, 1:2] * (ct - at)
    normal = cross[tri] / double_area[tri, None]
    if side == "random":
        sign = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    else:
        sign = np.full(n, 1.0 if side == "front" else -1.0)
    normal = normal * sign[:, None]
    local = _cosine_local(rng, n)
    t, bt_ = _orthonormal_basis(normal)
    directions = _normalise(local[:, 0:1] * t + local[:, 1:2] * bt_ + local[:, 2:3] * normal)
    lo, hi = v.min(axis=0), v.max(axis=0)
    offset = SURFACE_OFFSET_FRACTION_OF_DIAGONAL * _diagonal(lo, hi)
    origins = points + offset * normal
    return np.ascontiguousarray(origins), np.ascontiguousarray(directions)


def unique_edges(faces) -> np.ndarray:
    """(E, 2) int64 undirected edges of a triangle mesh, each once (smaller index first)."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def aimed_at_edges(vertices, faces, n_edge_points: int, seed, origin_radius: float = 0.1, centre=(0.0, 0.0, 0.0)):
    """Rays from inside a closed mesh aimed exactly at every vertex, every edge midpoint and random edge points.

    After pbrt-v4's ``Triangle.Watertight`` test.  Origins are uniform in the ball of
    ``origin_radius`` about ``centre``, which must lie inside the (star-shaped) mesh;
    targets are every vertex once, every edge's midpoint once and ``n_edge_points``
    uniformly random points on uniformly random edges -- the places where a
    non-watertight ray/triangle test lets a ray slip between two triangles.  A ray
    that hits nothing has leaked.

    Parameters
    ----------
    vertices : (V, 3) float64; faces : (F, 3) int64, a closed mesh around ``centre``.
    n_edge_points : int >= 0; seed : int >= 0 or a numpy Generator.

    Returns
    -------
    origins : (n, 3) float64; directions : (n, 3) float64 = target - origin (not unit
    length: t = 1 at the target); kind : (n,) str array, 'vertex', 'midpoint' or 'edge point'.
    n = V + E + n_edge_points.
    """
    v, f = _check_mesh(vertices, faces)
    if isinstance(n_edge_points, (bool, np.bool_)) or not isinstance(n_edge_points, (int, np.integer)) \
            or n_edge_points < 0:
        raise ValueError(f"n_edge_points must be a non-negative integer, got {n_edge_points!r}")
    if not (np.isfinite(origin_radius) and origin_radius >= 0):
        raise ValueError(f"origin_radius must be a finite number >= 0, got {origin_radius!r}")
    rng = _rng(seed)
    edges = unique_edges(f)
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    pick = rng.integers(0, len(edges), int(n_edge_points))
    s = rng.random((int(n_edge_points), 1))
    targets = np.concatenate([v, 0.5 * (a + b), a[pick] + s * (b[pick] - a[pick])])
    kind = np.array(["vertex"] * len(v) + ["midpoint"] * len(edges) + ["edge point"] * len(pick))
    n = len(targets)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    origins = np.asarray(centre, dtype=np.float64) + origin_radius * np.cbrt(rng.random((n, 1))) * u
    return np.ascontiguousarray(origins), np.ascontiguousarray(targets - origins), kind


# ----------------------------------------------------------------------------------
# registry (common signature for the command line)
# ----------------------------------------------------------------------------------

def _isotropic_mesh(vertices, faces, n, seed) -> Rays:
    _check_mesh(vertices, faces)
    return isotropic(*mesh_bounds(vertices), n, seed)


def _camera_mesh(vertices, faces, n, seed) -> Rays:
    _check_mesh(vertices, faces)
    return camera(*mesh_bounds(vertices), n, seed)


RAY_SETS: dict[str, Callable[..., Rays]] = {
    "isotropic": _isotropic_mesh,
    "camera": _camera_mesh,
    "surface": surface,
}


def ray_set_names() -> list[str]:
    """Names of the ray sets, in registry order."""
    return list(RAY_SETS)


def make_rays(name: str, vertices, faces, n: int, seed) -> Rays:
    """Generate ray set ``name`` for a mesh (its bounding box for isotropic and camera).

    vertices (V, 3) float, faces (F, 3) int. Returns origins (n, 3) float64
    and unit directions (n, 3) float64. Raises ValueError naming the valid
    ray sets when ``name`` is unknown.
    """
    try:
        generator = RAY_SETS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown ray set {name!r}; valid names: {', '.join(RAY_SETS)}") from None
    return generator(vertices, faces, n, seed)

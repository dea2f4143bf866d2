"""Built-in procedural scenes.

Every verb that takes a mesh file also takes one of these names, so the tool
works with no input files at all. Each generator is a pure, deterministic
function: the same arguments give bit-identical arrays.

Every scene is returned as

    vertices : (V, 3) float64, scene units (arbitrary length unit)
    faces    : (F, 3) int64, indices into ``vertices``, counter-clockwise seen
               from the outside for closed surfaces (outward normals)

Scenes (the ``BUILTIN`` registry, in order):

``sphere``
    A compact, scanned-like closed surface: a geodesic icosphere of roughly
    equilateral triangles with a smooth deterministic radial displacement
    ("bumps"). ``sphere_mesh(n_target)`` scales it to millions of triangles in
    seconds (fully vectorised).
``cylinder196``, ``cylinder1996``, ``cylinder19996``
    The talk's long-skinny-triangle cylinders (Ize, Shirley, Parker, RT 2007):
    ``n`` segments around, each side quad split into two triangles that run the
    full length, both caps triangulated as fans of ``n - 2`` triangles:
    ``4 n - 4`` triangles, so ``n`` = 50, 500, 5000 give exactly 196, 1,996 and
    19,996. Radius ``CYLINDER_RADIUS`` = 1, length ``CYLINDER_LENGTH`` = 10
    along +z, so a side triangle is 10 long and ``2 sin(pi/n)`` wide
    (longest-edge^2 / (2 area) = 80, 796, 7958).
``scattered-compact``
    N small, randomly oriented equilateral triangles ("points") with centres
    uniform in the unit cube.
``scattered-skinny``
    N long, thin, randomly oriented triangles ("lines") with centres uniform
    in the unit cube.
``room``
    A room with mixed triangle sizes: big floor/ceiling/wall quads, boxes as
    furniture, a dense small-triangle object on the table (a bumpy sphere) and
    long thin elements (table legs, ceiling pipes).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = [
    "BUILTIN",
    "builtin_names",
    "load_builtin",
    "sphere_mesh",
    "cylinder_mesh",
    "scattered_compact",
    "scattered_skinny",
    "room_mesh",
    "jittered_closed_mesh",
    "icosphere",
]

Mesh = tuple[np.ndarray, np.ndarray]

# --- sphere -------------------------------------------------------------------
SPHERE_DEFAULT_TRIANGLES = 40_000  # target; actual count is 20 f^2 = 40,500
SPHERE_RADIUS_UNITS = 1.0
# Smooth radial displacement: sum of SPHERE_BUMP_WAVES sine waves along fixed
# random directions; total amplitude as a fraction of the radius.
SPHERE_BUMP_AMPLITUDE_FRACTION = 0.06
SPHERE_BUMP_WAVES = 12
SPHERE_BUMP_MIN_FREQUENCY_PER_RADIUS = 2.0  # angular frequency of the waves
SPHERE_BUMP_MAX_FREQUENCY_PER_RADIUS = 9.0
SPHERE_BUMP_SEED = 20070910  # fixed: the displacement is part of the scene
# Bit budget of the lattice-point key (see _icosphere_lattice): 12 icosahedron
# vertex ids (+ a sentinel) fit in 4 bits, each barycentric weight in 21 bits.
_VERTEX_ID_BITS = 4
_WEIGHT_BITS = 21
_MAX_FREQUENCY = (1 << _WEIGHT_BITS) - 1

# --- cylinders (the talk's long skinny triangle scenes) -------------------------
CYLINDER_RADIUS = 1.0  # scene units
CYLINDER_LENGTH = 10.0  # scene units, along +z from z = 0
CYLINDER_SEGMENTS = {"cylinder196": 50, "cylinder1996": 500, "cylinder19996": 5000}

# --- scattered triangles --------------------------------------------------------
SCATTERED_COMPACT_DEFAULT_COUNT = 20_000
SCATTERED_COMPACT_SEED = 1
# Edge length of a compact triangle, as a fraction of the mean centre spacing
# (box side / N^(1/3)): small against any sensible grid cell, i.e. a "point".
COMPACT_EDGE_FRACTION_OF_SPACING = 0.25
SCATTERED_SKINNY_DEFAULT_COUNT = 5_000
SCATTERED_SKINNY_SEED = 2
SKINNY_LENGTH_FRACTION_OF_BOX = 0.25  # triangle length / box side
SKINNY_ASPECT_RATIO = 100.0  # length / width = longest edge^2 / (2 area)
SCATTERED_BOX_SIDE_UNITS = 1.0  # centres uniform in [0, side]^3

# --- room -------------------------------------------------------------------------
ROOM_SIZE_UNITS = (10.0, 8.0, 3.0)  # x, y, z (z up), e.g. metres
ROOM_OBJECT_TRIANGLES = 20_000  # target for the dense bumpy sphere on the table
ROOM_LEG_SEGMENTS = 16
ROOM_PIPE_SEGMENTS = 12

# --- jittered closed mesh (watertightness tests) ---------------------------------
JITTER_MESH_FREQUENCY = 8  # 20 * 8^2 = 1,280 triangles, 642 vertices
# Each vertex moves by a uniform vector in a cube of this half-side, as a
# fraction of the shortest edge, so no triangle can fold over.
JITTER_FRACTION_OF_MIN_EDGE = 0.1


# ----------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------

def _icosahedron() -> Mesh:
    """Regular icosahedron on the unit sphere: (12, 3) float64, (20, 3) int64, outward."""
    phi = (1.0 + np.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0],
            [0, -1, phi], [0, 1, phi], [0, -1, -phi], [0, 1, -phi],
            [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1],
        ],
        dtype=np.float64,
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )
    return v, f


def _icosphere_lattice(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic (class I) subdivision of the icosahedron, projected to the unit sphere.

    Each of the 20 faces (A, B, C) is cut into ``frequency^2`` triangles by the
    lattice points ``(wA A + wB B + wC C) / f`` with integer weights summing to f.
    Points shared between faces are merged exactly: a point's key is its sorted
    list of (icosahedron vertex, weight) pairs, so no floating-point tolerance
    is involved and every shared vertex is stored once.

    Returns vertices (10 f^2 + 2, 3) float64 on the unit sphere and faces
    (20 f^2, 3) int64, outward (counter-clockwise seen from outside).
    """
    f = int(frequency)
    if f < 1 or f > _MAX_FREQUENCY:
        raise ValueError(f"icosphere frequency must be in [1, {_MAX_FREQUENCY}], got {frequency}")
    ico_v, ico_f = _icosahedron()

    # local lattice points (i, j) with i + j <= f; weights (f - i - j, i, j)
    ii, jj = np.meshgrid(np.arange(f + 1), np.arange(f + 1), indexing="ij")
    valid = ii + jj <= f
    i_pts = ii[valid].astype(np.int64)
    j_pts = jj[valid].astype(np.int64)
    n_local = i_pts.size  # (f + 1)(f + 2) / 2
    local_id = np.full((f + 2, f + 2), -1, dtype=np.int64)
    local_id[i_pts, j_pts] = np.arange(n_local)

    # local triangles: "up" (i,j),(i+1,j),(i,j+1) for i+j <= f-1,
    # "down" (i+1,j),(i+1,j+1),(i,j+1) for i+j <= f-2; same orientation as (A,B,C)
    up = i_pts + j_pts <= f - 1
    iu, ju = i_pts[up], j_pts[up]
    tri_up = np.stack([local_id[iu, ju], local_id[iu + 1, ju], local_id[iu, ju + 1]], axis=1)
    down = i_pts + j_pts <= f - 2
    idn, jdn = i_pts[down], j_pts[down]
    tri_down = np.stack(
        [local_id[idn + 1, jdn], local_id[idn + 1, jdn + 1], local_id[idn, jdn + 1]], axis=1
    )
    local_tris = np.concatenate([tri_up, tri_down], axis=0)  # (f^2, 3)

    # canonical integer key per (face, lattice point)
    weights = np.stack([f - i_pts - j_pts, i_pts, j_pts], axis=1)  # (n_local, 3)
    w = np.broadcast_to(weights[None, :, :], (20, n_local, 3))
    vid = np.broadcast_to(ico_f[:, None, :], (20, n_local, 3))
    sentinel = 12
    vid_eff = np.where(w == 0, sentinel, vid)
    order = np.argsort(vid_eff, axis=2, kind="stable")
    vid_s = np.take_along_axis(vid_eff, order, axis=2)
    w_s = np.take_along_axis(w, order, axis=2)
    key = (
        vid_s[..., 0]
        | (vid_s[..., 1] << _VERTEX_ID_BITS)
        | (vid_s[..., 2] << (2 * _VERTEX_ID_BITS))
        | (w_s[..., 0] << (3 * _VERTEX_ID_BITS))
        | (w_s[..., 1] << (3 * _VERTEX_ID_BITS + _WEIGHT_BITS))
    ).reshape(-1)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1).astype(np.int64)

    # one representative (face, point) per unique key -> position
    face_of = first // n_local
    pt_of = first % n_local
    wr = weights[pt_of].astype(np.float64)  # (V, 3)
    corners = ico_v[ico_f[face_of]]  # (V, 3, 3)
    pos = (wr[:, 0:1] * corners[:, 0] + wr[:, 1:2] * corners[:, 1] + wr[:, 2:3] * corners[:, 2])
    pos /= np.linalg.norm(pos, axis=1, keepdims=True)

    global_tris = local_tris[None, :, :] + (np.arange(20, dtype=np.int64) * n_local)[:, None, None]
    faces = inverse[global_tris.reshape(-1, 3)]
    return np.ascontiguousarray(pos), np.ascontiguousarray(faces, dtype=np.int64)


def _frequency_for(n_target: int) -> int:
    """Geodesic frequency f whose 20 f^2 triangles are nearest to ``n_target``."""
    return max(1, int(round(np.sqrt(n_target / 20.0))))


def _bump_factor(unit: np.ndarray, amplitude_fraction: float) -> np.ndarray:
    """Radial scale factor (V,) for unit directions (V, 3): 1 + smooth deterministic noise.

    Sum of ``SPHERE_BUMP_WAVES`` sine waves sin(k (u . d) + phase) along fixed
    random unit directions d, normalised so |factor - 1| <= amplitude_fraction.
    """
    rng = np.random.default_rng(SPHERE_BUMP_SEED)
    dirs = rng.normal(size=(SPHERE_BUMP_WAVES, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    freq = rng.uniform(
        SPHERE_BUMP_MIN_FREQUENCY_PER_RADIUS, SPHERE_BUMP_MAX_FREQUENCY_PER_RADIUS, SPHERE_BUMP_WAVES
    )
    phase = rng.uniform(0.0, 2.0 * np.pi, SPHERE_BUMP_WAVES)
    weight = 1.0 / freq  # rougher waves are weaker, like a natural surface
    weight /= weight.sum()
    noise = np.sin((unit @ dirs.T) * freq + phase) @ weight  # in [-1, 1]
    return 1.0 + amplitude_fraction * noise


def _box_mesh(lo, hi) -> Mesh:
    """Closed axis-aligned box, 8 vertices, 12 outward triangles."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    v = lo + corners * (hi - lo)
    # vertex index = x + 2 y + 4 z
    f = np.array(
        [
            [0, 2, 3], [0, 3, 1],  # z = lo (normal -z)
            [4, 5, 7], [4, 7, 6],  # z = hi (+z)
            [0, 1, 5], [0, 5, 4],  # y = lo (-y)
            [2, 6, 7], [2, 7, 3],  # y = hi (+y)
            [0, 4, 6], [0, 6, 2],  # x = lo (-x)
            [1, 3, 7], [1, 7, 5],  # x = hi (+x)
        ],
        dtype=np.int64,
    )
    return v, f


def _quad(p0, p1, p2, p3, facing) -> Mesh:
    """Planar quad p0 p1 p2 p3 (in order around its boundary) as 2 triangles.

    The triangles are wound so their normal points along ``facing`` (3,).
    """
    v = np.array([p0, p1, p2, p3], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    if np.dot(np.cross(v[1] - v[0], v[2] - v[0]), np.asarray(facing, dtype=np.float64)) < 0:
        f = f[:, ::-1].copy()
    return v, f


def _concat(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes, offsetting face indices."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(f + offset)
        offset += v.shape[0]
    return (
        np.ascontiguousarray(np.concatenate(verts, axis=0), dtype=np.float64),
        np.ascontiguousarray(np.concatenate(faces, axis=0), dtype=np.int64),
    )


def _cylinder_between(p0, p1, radius: float, segments: int) -> Mesh:
    """Closed cylinder from p0 to p1: side quads split full-length, fan caps; 4n-4 triangles.

    Vertices: bottom ring 0..n-1 around p0, top ring n..2n-1 around p1.
    """
    n = int(segments)
    if n < 3:
        raise ValueError(f"a cylinder needs at least 3 segments, got {segments}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"cylinder radius must be finite and > 0, got {radius}")
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    if not (np.isfinite(length) and length > 0):
        raise ValueError("cylinder end points must be finite and distinct")
    w = axis / length
    # orthonormal (u, v, w); u x v = w so increasing angle is counter-clockwise about w
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    theta = 2.0 * np.pi * np.arange(n) / n
    ring = radius * (np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v)  # (n, 3)
    verts = np.concatenate([p0 + ring, p1 + ring], axis=0)
    i = np.arange(n, dtype=np.int64)
    j = (i + 1) % n
    b_i, b_j, t_i, t_j = i, j, i + n, j + n
    side = np.concatenate(
        [np.stack([b_i, b_j, t_j], axis=1), np.stack([b_i, t_j, t_i], axis=1)], axis=0
    )
    k = np.arange(1, n - 1, dtype=np.int64)
    zero = np.zeros_like(k)
    bottom = np.stack([zero, k + 1, k], axis=1)  # normal -w
    top = np.stack([zero + n, k + n, k + 1 + n], axis=1)  # normal +w
    faces = np.concatenate([side, bottom, top], axis=0)
    return np.ascontiguousarray(verts), np.ascontiguousarray(faces, dtype=np.int64)


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """n uniformly distributed rotation matrices (n, 3, 3) from unit quaternions (Shoemake 1992)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    a, b, c, d = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (c * c + d * d), 2 * (b * c - a * d), 2 * (b * d + a * c)], axis=1),
            np.stack([2 * (b * c + a * d), 1 - 2 * (b * b + d * d), 2 * (c * d - a * b)], axis=1),
            np.stack([2 * (b * d - a * c), 2 * (c * d + a * b), 1 - 2 * (b * b + c * c)], axis=1),
        ],
        axis=1,
    )


def _check_count(n, what: str) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"{what} must be an integer, got {n!r}")
    if n < 1:
        raise ValueError(f"{what} must be >= 1, got {n}")
    return int(n)


# ----------------------------------------------------------------------------------
# public generators
# ----------------------------------------------------------------------------------

def icosphere(frequency: int, radius: float = 1.0) -> Mesh:
    """Geodesic icosphere of ``20 frequency^2`` triangles and ``10 frequency^2 + 2`` vertices.

    Returns vertices (V, 3) float64 at distance ``radius`` (scene units) from the
    origin and faces (F, 3) int64, closed, outward, shared vertices indexed once.
    """
    v, f = _icosphere_lattice(_check_count(frequency, "frequency"))
    return v * float(radius), f


def sphere_mesh(
    n_target: int = SPHERE_DEFAULT_TRIANGLES,
    radius: float = SPHERE_RADIUS_UNITS,
    bump_amplitude_fraction: float = SPHERE_BUMP_AMPLITUDE_FRACTION,
) -> Mesh:
    """Bumpy closed sphere of roughly equilateral triangles (the compact, scan-like scene).

    A geodesic icosphere of frequency f = round(sqrt(n_target / 20)) (so the
    triangle count is ``20 f^2``, the nearest such count to ``n_target``),
    displaced radially by smooth deterministic noise of relative amplitude
    ``bump_amplitude_fraction``. Vectorised: 5e6 triangles take a few seconds.

    Returns vertices (10 f^2 + 2, 3) float64 (scene units, centred on the
    origin, radius within ``radius * (1 +- bump_amplitude_fraction)``) and
    faces (20 f^2, 3) int64, closed and outward.
    """
    n_target = _check_count(n_target, "n_target")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be finite and > 0, got {radius}")
    if not (np.isfinite(bump_amplitude_fraction) and 0 <= bump_amplitude_fraction < 0.5):
        raise ValueError(f"bump_amplitude_fraction must be in [0, 0.5), got {bump_amplitude_fraction}")
    unit, faces = _icosphere_lattice(_frequency_for(n_target))
    scale = radius * _bump_factor(unit, bump_amplitude_fraction)
    return np.ascontiguousarray(unit * scale[:, None]), faces


def cylinder_mesh(
    segments: int, radius: float = CYLINDER_RADIUS, length: float = CYLINDER_LENGTH
) -> Mesh:
    """The talk's closed cylinder of long skinny triangles: ``4 segments - 4`` triangles.

    Axis +z from z = 0 to z = ``length``; ``segments`` vertices per ring.
    Each side quad is split into two triangles spanning the full length; both
    caps are fans of ``segments - 2`` triangles from ring vertex 0.

    Returns vertices (2 segments, 3) float64 and faces (4 segments - 4, 3)
    int64, closed and outward.
    """
    segments = _check_count(segments, "segments")
    return _cylinder_between((0.0, 0.0, 0.0), (0.0, 0.0, float(length)), radius, segments)


def scattered_compact(
    n: int = SCATTERED_COMPACT_DEFAULT_COUNT,
    seed: int = SCATTERED_COMPACT_SEED,
    box_side: float = SCATTERED_BOX_SIDE_UNITS,
) -> Mesh:
    """``n`` small compact triangles ("points") scattered uniformly in a cube.

    Equilateral triangles of edge ``COMPACT_EDGE_FRACTION_OF_SPACING * box_side
    / n^(1/3)``, uniformly random orientation, centroids uniform in
    ``[0, box_side]^3``. A triangle soup: 3 own vertices per triangle.

    Returns vertices (3 n, 3) float64 and faces (n, 3) int64.
    """
    n = _check_count(n, "n")
    rng = np.random.default_rng(seed)
    edge = COMPACT_EDGE_FRACTION_OF_SPACING * box_side / np.cbrt(n)
    circumradius = edge / np.sqrt(3.0)
    ang = 2.0 * np.pi * np.arange(3) / 3.0
    canonical = circumradius * np.stack([np.cos(ang), np.sin(ang), np.zeros(3)], axis=1)  # (3, 3)
    centres = rng.uniform(0.0, box_side, size=(n, 3))
    rot = _random_rotations(rng, n)
    verts = centres[:, None, :] + np.einsum("nij,kj->nki", rot, canonical)
    faces = np.arange(3 * n, dtype=np.int64).reshape(n, 3)
    return np.ascontiguousarray(verts.reshape(-1, 3)), faces


def scattered_skinny(
    n: int = SCATTERED_SKINNY_DEFAULT_COUNT,
    seed: int = SCATTERED_SKINNY_SEED,
    box_side: float = SCATTERED_BOX_SIDE_UNITS,
) -> Mesh:
    """``n`` long thin triangles ("lines") scattered uniformly in a cube.

    Each triangle has a long edge of length ``L = SKINNY_LENGTH_FRACTION_OF_BOX
    * box_side`` along a uniformly random direction u, centred on a point
    uniform in ``[0, box_side]^3``, and an apex at height ``L /
    SKINNY_ASPECT_RATIO`` above the long edge's midpoint along a random
    direction perpendicular to u: longest edge^2 / (2 area) = SKINNY_ASPECT_RATIO.

    Returns vertices (3 n, 3) float64 and faces (n, 3) int64.
    """
    n = _check_count(n, "n")
    rng = np.random.default_rng(seed)
    length = SKINNY_LENGTH_FRACTION_OF_BOX * box_side
    width = length / SKINNY_ASPECT_RATIO
    centres = rng.uniform(0.0, box_side, size=(n, 3))
    rot = _random_rotations(rng, n)  # columns: random orthonormal frame
    u = rot[:, :, 0]
    v = rot[:, :, 1]
    a = centres - 0.5 * length * u
    b = centres + 0.5 * length * u
    c = centres + width * v
    verts = np.stack([a, b, c], axis=1).reshape(-1, 3)
    faces = np.arange(3 * n, dtype=np.int64).reshape(n, 3)
    return np.ascontiguousarray(verts), faces


def room_mesh(object_triangles: int = ROOM_OBJECT_TRIANGLES) -> Mesh:
    """A furnished room with mixed triangle sizes (about 20k triangles by default).

    - floor, ceiling and four walls: one quad (2 triangles) each, facing inward;
    - furniture: a table top, a cabinet, two crates and a bed (closed boxes);
    - four table legs and three ceiling pipes: thin closed cylinders of long
      skinny side triangles;
    - on the table, a dense bumpy sphere of about ``object_triangles`` compact
      triangles (``sphere_mesh``).

    Room spans ``[0, ROOM_SIZE_UNITS]`` (z up). The first 12 triangles are the
    floor, ceiling and walls (normals into the room); everything after them is
    a union of closed, outward-oriented parts. Returns vertices (V, 3) float64
    and faces (F, 3) int64.
    """
    object_triangles = _check_count(object_triangles, "object_triangles")
    sx, sy, sz = ROOM_SIZE_UNITS
    parts: list[Mesh] = [
        _quad((0, 0, 0), (sx, 0, 0), (sx, sy, 0), (0, sy, 0), (0, 0, 1)),  # floor
        _quad((0, 0, sz), (sx, 0, sz), (sx, sy, sz), (0, sy, sz), (0, 0, -1)),  # ceiling
        _quad((0, 0, 0), (sx, 0, 0), (sx, 0, sz), (0, 0, sz), (0, 1, 0)),  # wall y = 0
        _quad((0, sy, 0), (sx, sy, 0), (sx, sy, sz), (0, sy, sz), (0, -1, 0)),  # wall y = sy
        _quad((0, 0, 0), (0, sy, 0), (0, sy, sz), (0, 0, sz), (1, 0, 0)),  # wall x = 0
        _quad((sx, 0, 0), (sx, sy, 0), (sx, sy, sz), (sx, 0, sz), (-1, 0, 0)),  # wall x = sx
    ]
    # table: top 2.0 x 1.0 x 0.05 at height 0.75, legs radius 0.03
    t_lo, t_hi, t_top = np.array([4.0, 3.5]), np.array([6.0, 4.5]), 0.75
    parts.append(_box_mesh((t_lo[0], t_lo[1], t_top - 0.05), (t_hi[0], t_hi[1], t_top)))
    inset = 0.1
    for x in (t_lo[0] + inset, t_hi[0] - inset):
        for y in (t_lo[1] + inset, t_hi[1] - inset):
            parts.append(_cylinder_between((x, y, 0.0), (x, y, t_top - 0.05), 0.03, ROOM_LEG_SEGMENTS))
    # other furniture
    parts.append(_box_mesh((0.2, 6.0, 0.0), (1.2, 7.8, 2.0)))  # cabinet
    parts.append(_box_mesh((8.0, 0.5, 0.0), (8.6, 1.1, 0.6)))  # crate
    parts.append(_box_mesh((8.1, 0.6, 0.6), (8.5, 1.0, 1.0)))  # crate on the crate
    parts.append(_box_mesh((7.0, 5.5, 0.0), (9.0, 7.5, 0.5)))  # bed
    # ceiling pipes along x, radius 0.05, 0.2 below the ceiling
    for y in (2.0, 4.0, 6.0):
        parts.append(_cylinder_between((0.1, y, sz - 0.2), (sx - 0.1, y, sz - 0.2), 0.05, ROOM_PIPE_SEGMENTS))
    # dense object: bumpy sphere of radius 0.3 resting on the table
    obj_v, obj_f = sphere_mesh(object_triangles, radius=0.3)
    obj_v = obj_v + np.array([5.0, 4.0, t_top + 0.3 * (1.0 + SPHERE_BUMP_AMPLITUDE_FRACTION)])
    parts.append((obj_v, obj_f))
    return _concat(parts)


def jittered_closed_mesh(seed: int, frequency: int = JITTER_MESH_FREQUENCY) -> Mesh:
    """Closed icosphere (radius 1, centred on the origin) with randomly jittered vertices.

    For watertightness tests: every edge is shared by exactly two triangles
    through shared vertex indices (never duplicated positions), so a ray from
    the origin (strictly inside) must hit it. Each vertex moves by a uniform
    random vector in a cube of half-side ``JITTER_FRACTION_OF_MIN_EDGE`` times
    the shortest edge, so vertex positions are irregular floats while no
    triangle folds over.

    Returns vertices (10 f^2 + 2, 3) float64 and faces (20 f^2, 3) int64, outward.
    """
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    v, f = _icosphere_lattice(_check_count(frequency, "frequency"))
    edges = v[f] - v[np.roll(f, -1, axis=1)]
    min_edge = np.sqrt((edges**2).sum(axis=2)).min()
    rng = np.random.default_rng(seed)
    half = JITTER_FRACTION_OF_MIN_EDGE * min_edge
    return np.ascontiguousarray(v + rng.uniform(-half, half, size=v.shape)), f


# ----------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------

def _cyl(name: str) -> Callable[[], Mesh]:
    return lambda: cylinder_mesh(CYLINDER_SEGMENTS[name])


BUILTIN: dict[str, tuple[str, Callable[[], Mesh]]] = {
    "sphere": (
        "bumpy closed sphere, 40,500 near-equilateral triangles (compact, scan-like)",
        sphere_mesh,
    ),
    "cylinder196": (
        "closed cylinder r=1 l=10, 50 segments: 196 long skinny triangles (talk)",
        _cyl("cylinder196"),
    ),
    "cylinder1996": (
        "closed cylinder r=1 l=10, 500 segments: 1,996 long skinny triangles (talk)",
        _cyl("cylinder1996"),
    ),
    "cylinder19996": (
        "closed cylinder r=1 l=10, 5000 segments: 19,996 long skinny triangles (talk)",
        _cyl("cylinder19996"),
    ),
    "scattered-compact": (
        "20,000 small compact triangles scattered in the unit cube (points)",
        scattered_compact,
    ),
    "scattered-skinny": (
        "5,000 long thin triangles (length 1/4 box, aspect 100) scattered in the unit cube (lines)",
        scattered_skinny,
    ),
    "room": (
        "10x8x3 room: wall quads, box furniture, thin legs and pipes, dense sphere (mixed)",
        room_mesh,
    ),
}


def builtin_names() -> list[str]:
    """Names of the built-in scenes, in registry order."""
    return list(BUILTIN)


def load_builtin(name: str) -> Mesh:
    """Generate built-in scene ``name``: vertices (V, 3) float64, faces (F, 3) int64.

    Raises ValueError naming the valid scenes when ``name`` is unknown.
    """
    try:
        _, generator = BUILTIN[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown built-in scene {name!r}; valid names: {', '.join(BUILTIN)}"
        ) from None
    return generator()

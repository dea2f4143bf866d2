"""DESIGN section 6 hard cases: grid first hits equal brute force where rounding bites.

Every case traces seeded rays by brute force (the reference, same intersector)
and through uniform grids and nested grids of depth 2 and 3, with and without
mailboxing, with both intersectors and both twins (timed and instrumented).
A ray agrees when both miss, or both hit at t within ``REL_T_TOLERANCE`` and on
the same triangle, or on different triangles at the same t (a tie: a shared
edge or a duplicated triangle; ties are counted and reported).

Cases: axis-parallel rays with +0.0 and -0.0 components; rays exactly along
cell faces, cell edges and through cell corners of the grid under test;
origins inside the grid, on its boundary faces/edges/corners and 1e6 or 1e12
box sizes away; the scene scaled by 1e-20 and 1e20 and translated far; flat
scenes (a plane, a line, a point); degenerate and duplicated triangles; a
single triangle; resolutions that overflow 32-bit offsets or pass the memory
limit (refused with a ValueError, also in a fresh interpreter).

Defects these cases found (rays lost at box edges and corners, zero-area
triangles and rays in a triangle's plane hit at a t made of rounding noise)
are fixed in the kernels; their minimal reproductions stay here as tests.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from calibrate import Grid, Scene, brute_force
from calibrate.scenes import jittered_closed_mesh, room_mesh

from conftest import first_hit_disagreements

#: |t_grid - t_brute| <= this * |t_brute| counts as the same hit distance (task's tie rule).
REL_T_TOLERANCE = 1e-9
INTERSECTOR_NAMES = ("watertight", "moller-trumbore")
NESTED_LEVELS = (2, 3)
#: Far origins: this many box diagonals away from the box centre.
FAR_DISTANCES_IN_DIAGONALS = (1e6, 1e12)
#: Scale factors of the scaled-scene test (coordinates from 1e-20 to 1e20, DESIGN section 6).
SCENE_SCALES = (1e-20, 1e20)
#: Far translation of the scaled scene, in box sizes.
FAR_OFFSET_IN_BOX_SIZES = 1e6
#: Relative t tolerance between a transformed scene and the original.  Pure scaling
#: rounds every coordinate once (relative 2^-53), so t moves by a few ulps; a translation
#: by k box sizes rounds coordinates to k * 2^-53 of the box, so the bound grows with k.
SCALED_T_REL_TOLERANCE = 1e-12
TRANSLATED_T_REL_TOLERANCE_PER_BOX_SIZE = 1e-14
#: A memory limit this many times a grid's final size must let the same grid build (build
#: scratch: the triangle copy and per-level counting-sort arrays, measured near 1.7x).
BUILD_PEAK_ALLOWANCE_FACTOR = 4
#: Lattice of the hand-made "lattice" scene: vertices at multiples of 1/LATTICE_DIVISIONS.
LATTICE_DIVISIONS = 4
LATTICE_RANDOM_TRIANGLES = 40
#: A small room (the room built-in with a light table object): walls lie exactly on the box faces.
SMALL_ROOM_OBJECT_TRIANGLES = 320


# ---------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------

def grid_variants(scene: Scene, resolution, mailboxes=(False, True), intersectors=INTERSECTOR_NAMES):
    """Yield (label, grid): uniform and nested (levels 2, 3) at top ``resolution`` (nx, ny, nz)."""
    for intersector in intersectors:
        for mailbox in mailboxes:
            yield (f"uniform {tuple(resolution)} {intersector} mailbox={mailbox}",
                   Grid.uniform(scene, resolution, intersector=intersector, mailbox=mailbox))
            for levels in NESTED_LEVELS:
                yield (f"nested L={levels} top {tuple(resolution)} {intersector} mailbox={mailbox}",
                       Grid.nested(scene, levels, resolution, intersector=intersector, mailbox=mailbox))


def check_grid(grid: Grid, origins, directions, t_ref, prim_ref, where: str) -> int:
    """Assert both twins of ``grid`` agree with the reference hits; return the tie count.

    origins, directions : (n, 3) float64 rays; t_ref (n,) float64, prim_ref (n,) int32.
    """
    t, prim = grid.intersect(origins, directions)
    bad, ties = first_hit_disagreements(t, prim, t_ref, prim_ref, REL_T_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise AssertionError(
            f"{where}: {bad.size} of {len(t)} first hits differ from brute force (ties {ties}); "
            f"first ray {i}: origin {origins[i].tolist()!r} direction {directions[i].tolist()!r}: "
            f"grid t={t[i]!r} prim={prim[i]}, brute t={t_ref[i]!r} prim={prim_ref[i]}")
    tc, pc, steps, tests, subgrids = grid.count(origins, directions, hits=True)
    same = (np.array_equal(tc, t) and np.array_equal(pc, prim))
    assert same, f"{where}: timed and instrumented twins return different hits"
    miss = prim < 0
    assert np.all(np.isinf(t[miss])) and np.all(np.isfinite(t[~miss]) & (t[~miss] > 0)), (
        f"{where}: a miss must be t=+inf, prim=-1 and a hit t > 0 finite")
    return ties


def check_all(scene: Scene, origins, directions, resolution, what: str, **variant_kw) -> dict:
    """Compare every grid variant with brute force on the rays; return {label: ties}."""
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    refs = {name: brute_force(scene, origins, directions, name) for name in INTERSECTOR_NAMES}
    ties = {}
    for label, grid in grid_variants(scene, resolution, **variant_kw):
        intersector = grid.options["intersector"]
        t_ref, p_ref = refs[intersector]
        ties[label] = check_grid(grid, origins, directions, t_ref, p_ref, f"{what}: {label}")
    return ties


def lattice_planes(grid: Grid) -> list[np.ndarray]:
    """Cell-boundary coordinates of the top level: three arrays (n_i + 1,), scene units.

    Both ways of computing a plane, lo + i * (hi - lo) / n and lo + (hi - lo) * i / n,
    are included (they can differ by an ulp), so some rays sit exactly on the kernel's plane.
    """
    info = grid.info
    lo = np.array(info["box_lo"])
    hi = np.array(info["box_hi"])
    res = np.array(info["resolution"])
    planes = []
    for a in range(3):
        i = np.arange(res[a] + 1, dtype=np.float64)
        p = np.concatenate([lo[a] + i * ((hi[a] - lo[a]) / res[a]), lo[a] + (hi[a] - lo[a]) * i / res[a]])
        p[0], p[res[a]] = lo[a], hi[a]
        planes.append(np.unique(p))
    return planes


def signed_zero_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) axis-parallel directions: main axis +-1, other components +0.0 or -0.0 at random."""
    axis = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    d = np.where(rng.random((n, 3)) < 0.5, 0.0, -0.0)
    d[np.arange(n), axis] = sign
    return d


def axis_origins(lo, hi, directions, rng: np.random.Generator, inside_fraction: float = 0.5):
    """(n, 3) origins for axis-parallel directions: before the box on the main axis, or inside.

    The two off-axis coordinates are uniform in the box (scene units).
    """
    n = directions.shape[0]
    ext = hi - lo
    o = lo + rng.random((n, 3)) * ext
    main = np.argmax(np.abs(directions), axis=1)
    outside = rng.random(n) >= inside_fraction
    rows = np.flatnonzero(outside)
    a = main[rows]
    start = np.where(directions[rows, a] > 0, lo[a] - 0.25 * ext[a], hi[a] + 0.25 * ext[a])
    o[rows, a] = start
    return o


def unit_box_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The surface of [0, 1]^3: vertices (8, 3) float64 (index x + 2 y + 4 z), faces (12, 3) int64."""
    v = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    f = np.array([[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4],
                  [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]], dtype=np.int64)
    return v, f


def lattice_scene(seed: int) -> Scene:
    """Unit-box surface plus random triangles whose vertices are lattice points k / LATTICE_DIVISIONS.

    The grid box is exactly [0, 1]^3, so with LATTICE_DIVISIONS cells per axis every
    triangle vertex is a cell corner and many edges run along cell faces and edges.
    """
    rng = np.random.default_rng(seed)
    bv, bf = unit_box_mesh()
    pts = rng.integers(0, LATTICE_DIVISIONS + 1, size=(4 * LATTICE_RANDOM_TRIANGLES, 3, 3)) / LATTICE_DIVISIONS
    area2 = np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1)
    pts = pts[area2 > 0][:LATTICE_RANDOM_TRIANGLES]
    v = np.concatenate([bv, pts.reshape(-1, 3)])
    f = np.concatenate([bf, len(bv) + np.arange(pts.shape[0] * 3).reshape(-1, 3)])
    return Scene(v, f, name=f"lattice{seed}")


def small_room() -> Scene:
    v, f = room_mesh(SMALL_ROOM_OBJECT_TRIANGLES)
    return Scene(v, f, name="small room")


def jittered_scene(seed: int) -> Scene:
    v, f = jittered_closed_mesh(seed)
    return Scene(v, f, name=f"jittered{seed}")


def random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) unit vectors uniform on the sphere."""
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def lattice_rays(grid: Grid, rng: np.random.Generator, n_each: int):
    """Rays exactly along cell faces, along cell edges and through cell corners of ``grid``.

    Returns origins, directions (m, 3) float64:
    - face rays: axis-parallel (+-0.0 off-axis) with one off-axis coordinate on a plane;
    - in-face diagonal rays: lying in a lattice plane, random direction within it;
    - edge rays: axis-parallel with both off-axis coordinates on planes;
    - corner rays: along the cell diagonal (hx, hy, hz) (signs at random) from a lattice
      corner, from inside the grid and from two cells before the box;
    - rays from random lattice corners in random directions.
    """
    info = grid.info
    lo, hi = np.array(info["box_lo"]), np.array(info["box_hi"])
    res = np.array(info["resolution"])
    h = (hi - lo) / res
    planes = lattice_planes(grid)

    def pick(axis: int, n: int) -> np.ndarray:
        return planes[axis][rng.integers(0, len(planes[axis]), n)]

    origins, directions = [], []

    # faces and edges, axis-parallel
    for on_edge in (False, True):
        d = signed_zero_directions(rng, n_each)
        o = axis_origins(lo, hi, d, rng)
        main = np.argmax(np.abs(d), axis=1)
        for k in range(n_each):
            others = [a for a in range(3) if a != main[k]]
            fixed = others if on_edge else [others[rng.integers(0, 2)]]
            for a in fixed:
                o[k, a] = pick(a, 1)[0]
        origins.append(o)
        directions.append(d)

    # in-face diagonals: coordinate a on a plane, direction component a = +-0.0
    a = rng.integers(0, 3, n_each)
    o = lo + rng.random((n_each, 3)) * (hi - lo)
    d = random_unit(rng, n_each)
    for k in range(n_each):
        o[k, a[k]] = pick(a[k], 1)[0]
        d[k, a[k]] = 0.0 if rng.random() < 0.5 else -0.0
    outside = rng.random(n_each) < 0.5  # half start outside: back off along -d (stays in the plane)
    o[outside] -= 2.0 * np.linalg.norm(hi - lo) * d[outside]
    for k in np.flatnonzero(outside):
        o[k, a[k]] = pick(a[k], 1)[0]
    origins.append(o)
    directions.append(d)

    # corners: along the cell diagonal through lattice corners
    idx = np.stack([rng.integers(0, res[i] + 1, n_each) for i in range(3)], axis=1)
    corner = lo + idx * h
    signs = rng.choice([-1.0, 1.0], (n_each, 3))
    d = signs * h
    back = rng.random(n_each) < 0.5
    # or backed off along the diagonal by whole cells until two cells before the box, so
    # the ray crosses the extended lattice's corners on its way in.  Those rays go through
    # an interior corner (where an axis has one) so they cross the box's interior: a ray
    # touching the box only along an edge is test_hit_on_box_corner_is_not_lost.
    interior = np.stack([rng.integers(min(1, res[i] - 1), max(res[i], 2), n_each) for i in range(3)], axis=1)
    idx = np.where(back[:, None], np.minimum(interior, res), idx)
    corner = lo + idx * h
    cells_back = 2 + np.max(np.where(signs > 0, idx, res - idx), axis=1)
    start = corner - cells_back[:, None] * d
    o = np.where(back[:, None], start, corner)
    origins.append(o)
    directions.append(d)
    # unit-cube diagonal (1, 1, 1) in the direction of the corner rays, through cubic cells when they are cubic
    origins.append(corner)
    directions.append(signs)

    # random directions from lattice corners
    origins.append(lo + np.stack([rng.integers(0, res[i] + 1, n_each) for i in range(3)], axis=1) * h)
    directions.append(random_unit(rng, n_each))
    return np.concatenate(origins), np.concatenate(directions)


def boundary_rays(lo, hi, rng: np.random.Generator, n_each: int):
    """Origins exactly on the box's faces, edges and corners; random and axis-parallel directions.

    Returns origins, directions (m, 3) float64 (both inward and outward directions).
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    origins, directions = [], []
    for n_fixed in (1, 2, 3):  # face, edge, corner
        o = lo + rng.random((n_each, 3)) * (hi - lo)
        for k in range(n_each):
            axes = rng.permutation(3)[:n_fixed]
            side = rng.integers(0, 2, n_fixed)
            o[k, axes] = np.where(side == 0, lo[axes], hi[axes])
        for d in (random_unit(rng, n_each), signed_zero_directions(rng, n_each)):
            origins.append(o)
            directions.append(d)
        # aimed at random points inside the box
        target = lo + rng.random((n_each, 3)) * (hi - lo)
        d = target - o
        ok = np.any(d != 0, axis=1)
        origins.append(o[ok])
        directions.append(d[ok])
    return np.concatenate(origins), np.concatenate(directions)


def far_rays(lo, hi, distance_in_diagonals: float, rng: np.random.Generator, n: int):
    """Rays from ``distance_in_diagonals`` box diagonals away, aimed at random points in the box.

    Half the directions are (target - origin) unscaled (t near 1 at the target), half
    unit length; a quarter of the rays are axis-parallel with +-0.0 components.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    diag = np.linalg.norm(hi - lo)
    centre = 0.5 * (lo + hi)
    target = lo + rng.random((n, 3)) * (hi - lo)
    o = centre + distance_in_diagonals * diag * random_unit(rng, n)
    d = target - o
    unit = rng.random(n) < 0.5
    d[unit] /= np.linalg.norm(d[unit], axis=1, keepdims=True)
    axis_rows = rng.random(n) < 0.25
    da = signed_zero_directions(rng, int(axis_rows.sum()))
    oa = target[axis_rows].copy()
    main = np.argmax(np.abs(da), axis=1)
    rows = np.arange(len(main))
    oa[rows, main] -= da[rows, main] * distance_in_diagonals * diag
    o[axis_rows], d[axis_rows] = oa, da
    return o, d


# ---------------------------------------------------------------------------------
# axis-parallel rays with signed zeros
# ---------------------------------------------------------------------------------

@pytest.mark.parametrize("case", range(3))
def test_axis_parallel_signed_zero_rays(case):
    rng = np.random.default_rng(1000 + case)
    scene = [jittered_scene(case), lattice_scene(case), small_room()][case]
    d = signed_zero_directions(rng, 1500)
    # every sign pattern explicitly too: (+-1, +-0, +-0) along each axis
    patterns = []
    for axis in range(3):
        for s in (1.0, -1.0):
            for z1 in (0.0, -0.0):
                for z2 in (0.0, -0.0):
                    v = [z1, z2]
                    v.insert(axis, s)
                    patterns.append(v)
    patterns = np.array(patterns)
    assert np.signbit(patterns).any() and (patterns == 0).any()
    d = np.concatenate([d, np.repeat(patterns, 20, axis=0)])
    o = axis_origins(scene.box_lo, scene.box_hi, d, rng)
    res = (5, 4, 6) if case != 1 else (LATTICE_DIVISIONS,) * 3
    ties = check_all(scene, o, d, res, f"axis-parallel signed zeros ({scene.name})")
    print(f"{scene.name}: ties per grid {ties}")


def test_negative_zero_equals_positive_zero_direction():
    """A -0.0 component must not change any hit: same rays with +0.0 give identical results."""
    rng = np.random.default_rng(1100)
    scene = lattice_scene(7)
    d_neg = signed_zero_directions(rng, 800)
    d_neg[d_neg == 0] = -0.0
    d_pos = np.where(d_neg == 0, 0.0, d_neg)
    assert np.signbit(d_neg[d_neg == 0]).all() and not np.signbit(d_pos[d_pos == 0]).any()
    o = axis_origins(scene.box_lo, scene.box_hi, d_neg, rng)
    planes = np.arange(LATTICE_DIVISIONS + 1) / LATTICE_DIVISIONS
    snap = rng.random(o.shape) < 0.5  # half the off-axis coordinates exactly on lattice planes
    o = np.where(snap & (d_neg == 0), planes[rng.integers(0, len(planes), o.shape)], o)
    for label, grid in grid_variants(scene, (LATTICE_DIVISIONS,) * 3):
        t_n, p_n = grid.intersect(o, d_neg)
        t_p, p_p = grid.intersect(o, d_pos)
        bad, ties = first_hit_disagreements(t_n, p_n, t_p, p_p, REL_T_TOLERANCE)
        assert bad.size == 0, f"{label}: -0.0 and +0.0 directions give different hits on {bad.size} rays"


# ---------------------------------------------------------------------------------
# rays along cell faces, edges and corners
# ---------------------------------------------------------------------------------

LATTICE_CASES = [
    ("lattice", 0, (LATTICE_DIVISIONS,) * 3),
    ("lattice", 1, (2 * LATTICE_DIVISIONS, LATTICE_DIVISIONS, 1)),
    ("lattice", 2, (3, 5, 7)),
    ("jittered", 3, (6, 6, 6)),
    ("room", 4, (10, 8, 3)),
]


@pytest.mark.parametrize("kind,case,resolution", LATTICE_CASES)
def test_rays_along_cell_faces_edges_corners(kind, case, resolution):
    rng = np.random.default_rng(1200 + case)
    scene = {"lattice": lambda: lattice_scene(case), "jittered": lambda: jittered_scene(case),
             "room": small_room}[kind]()
    probe = Grid.uniform(scene, resolution)
    o, d = lattice_rays(probe, rng, 150)
    ties = check_all(scene, o, d, resolution, f"lattice rays ({scene.name}, {resolution})")
    print(f"{scene.name} {resolution}: ties per grid {ties}")


@pytest.mark.parametrize("case", range(2))
def test_rays_along_subgrid_cell_faces_edges_corners(case):
    """Nested grids whose subgrids split every top cell 2x2x2: the fine lattice is the
    uniform (8, 8, 8) lattice, so rays built on it run along subgrid faces, edges, corners."""
    rng = np.random.default_rng(1250 + case)
    scene = lattice_scene(10 + case)
    top = (LATTICE_DIVISIONS,) * 3
    fine = tuple(2 * n for n in top)
    o, d = lattice_rays(Grid.uniform(scene, fine), rng, 150)
    refs = {name: brute_force(scene, o, d, name) for name in INTERSECTOR_NAMES}
    sub = np.full((int(np.prod(top)), 3), 2, dtype=np.int32)
    for intersector in INTERSECTOR_NAMES:
        for mailbox in (False, True):
            for levels in NESTED_LEVELS:
                g = Grid.nested(scene, levels, top, subgrid_resolutions=sub, intersector=intersector,
                                mailbox=mailbox)
                assert g.info["levels"] >= 2
                check_grid(g, o, d, *refs[intersector],
                           f"subgrid lattice rays ({scene.name}) L={levels} {intersector} mailbox={mailbox}")


def test_cubic_cells_diagonal_passes_exact_corners():
    """Along (1, 1, 1) through a 4x4x4 grid of the unit cube, the ray meets corners exactly.

    A diagonal through (k/4, k/4, k/4) crosses three planes at once at every corner:
    the DDA must step all three axes without skipping or repeating cells.  The box
    diagonal carries one triangle per crossed cell, placed off the diagonal plane so
    only the corner-crossing logic decides which cells are visited.
    """
    rng = np.random.default_rng(1300)
    bv, bf = unit_box_mesh()
    # small triangles perpendicular to (1, 1, 1) centred at (k + 0.5) / 4 on the diagonal
    centres = (np.arange(LATTICE_DIVISIONS) + 0.5) / LATTICE_DIVISIONS
    u = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    w = np.array([1.0, 1.0, -2.0]) / np.sqrt(6.0)
    r = 0.05
    tris = np.stack([c + r * np.stack([u, -0.5 * u + 0.866 * w, -0.5 * u - 0.866 * w]) for c in centres])
    v = np.concatenate([bv, tris.reshape(-1, 3)])
    f = np.concatenate([bf, len(bv) + np.arange(tris.size // 3).reshape(-1, 3)])
    scene = Scene(v, f, name="diagonal targets")
    n = 64
    signs = rng.choice([-1.0, 1.0], (n, 3))
    start = np.where(signs > 0, 0.0, 1.0)
    o = np.concatenate([start, start - 0.5 * signs])  # on a box corner, and before it on the diagonal
    d = np.concatenate([signs, signs])
    check_all(scene, o, d, (LATTICE_DIVISIONS,) * 3, "corner diagonals")
    # the main diagonal (+,+,+) from the box corner (0, 0, 0) (where the box's own triangles
    # meet the ray at t = 0, which does not count) hits the first target at t = 0.5 / 4
    first_target = len(bf)
    for label, g in grid_variants(scene, (LATTICE_DIVISIONS,) * 3):
        t, prim = g.intersect([[0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]])
        assert prim[0] == first_target and t[0] == pytest.approx(0.5 / LATTICE_DIVISIONS, rel=1e-12), label


# ---------------------------------------------------------------------------------
# origins inside, on the boundary, far away
# ---------------------------------------------------------------------------------

@pytest.mark.parametrize("case", range(3))
def test_origins_inside_and_on_the_boundary(case):
    rng = np.random.default_rng(1400 + case)
    scene = [jittered_scene(case), lattice_scene(case), small_room()][case]
    lo, hi = scene.box_lo, scene.box_hi
    ob, db = boundary_rays(lo, hi, rng, 200)
    oi = lo + rng.random((600, 3)) * (hi - lo)
    di = np.concatenate([random_unit(rng, 400), signed_zero_directions(rng, 200)])
    o, d = np.concatenate([ob, oi]), np.concatenate([db, di])
    res = (LATTICE_DIVISIONS,) * 3 if case == 1 else (7, 5, 6)
    ties = check_all(scene, o, d, res, f"inside/boundary origins ({scene.name})")
    print(f"{scene.name}: ties per grid {ties}")


@pytest.mark.parametrize("case,distance", list(enumerate(FAR_DISTANCES_IN_DIAGONALS * 2)))
def test_far_origins(case, distance):
    rng = np.random.default_rng(1500 + case)
    scene = jittered_scene(case) if case < 2 else lattice_scene(case)
    o, d = far_rays(scene.box_lo, scene.box_hi, distance, rng, 800)
    res = (6, 6, 6) if case < 2 else (LATTICE_DIVISIONS,) * 3
    ties = check_all(scene, o, d, res, f"origins {distance:g} diagonals away ({scene.name})")
    t, _ = brute_force(scene, o, d)
    # a ray aimed at a point of the closed sphere's box: most of them must hit something
    assert np.isfinite(t).mean() > 0.3, "far rays aimed at the box should mostly hit"
    print(f"{scene.name} at {distance:g}: ties per grid {ties}")


# ---------------------------------------------------------------------------------
# scaled and translated scenes
# ---------------------------------------------------------------------------------

def sphere_rays(rng: np.random.Generator, n: int):
    """Rays that hit the unit jittered sphere well inside its silhouette.

    Half start within 0.3 of the centre (inside: every ray must hit); half start
    3 radii away aimed at points within 0.5 of the centre.  Returns (n, 3) arrays.
    """
    n_in = n // 2
    o_in = 0.3 * random_unit(rng, n_in) * rng.random((n_in, 1))
    d_in = random_unit(rng, n_in)
    o_out = 3.0 * random_unit(rng, n - n_in)
    d_out = 0.5 * random_unit(rng, n - n_in) * rng.random((n - n_in, 1)) - o_out
    return np.concatenate([o_in, o_out]), np.concatenate([d_in, d_out])


def adjacent(faces: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) bool: triangles a[i] and b[i] share at least one vertex (or are the same)."""
    fa, fb = faces[a], faces[b]
    return (fa[:, :, None] == fb[:, None, :]).any(axis=(1, 2))


#: (scale factor, translation in box sizes): pure scaling, pure translation, both.
SCALE_CASES = ([(scale, 0.0) for scale in SCENE_SCALES] + [(1.0, FAR_OFFSET_IN_BOX_SIZES)]
               + [(scale, FAR_OFFSET_IN_BOX_SIZES) for scale in SCENE_SCALES])


@pytest.mark.parametrize("case", range(len(SCALE_CASES)))
def test_scaled_and_translated_scene(case):
    scale, offset_boxes = SCALE_CASES[case]
    rng = np.random.default_rng(1600 + case)
    v, f = jittered_closed_mesh(case)
    base = Scene(v, f, name="unit")
    o, d = sphere_rays(rng, 600)
    offset = np.array([1.0, -0.5, 0.25]) * offset_boxes * scale * 2.0  # box side is 2
    scaled = Scene(v * scale + offset, f, name=f"x{scale:g}+{offset_boxes:g}")
    so, sd = o * scale + offset, d * scale
    rel = SCALED_T_REL_TOLERANCE + TRANSLATED_T_REL_TOLERANCE_PER_BOX_SIZE * offset_boxes
    t0, p0 = brute_force(base, o, d)
    assert np.all(p0 >= 0)
    for label, grid in grid_variants(scaled, (5, 5, 5)):
        isect = grid.options["intersector"]
        t_ref, p_ref = brute_force(scaled, so, sd, isect)
        ties = check_grid(grid, so, sd, t_ref, p_ref, f"{scaled.name}: {label}")
        t, prim = grid.intersect(so, sd)
        base_t, base_p = brute_force(base, o, d, isect)
        assert np.all(prim >= 0), f"{scaled.name} {label}: {int((prim < 0).sum())} rays lost their hit"
        err = np.abs(t - base_t) / base_t
        assert err.max() <= rel, (
            f"{scaled.name} {label}: t differs from the unscaled scene by {err.max():.3g} relative "
            f"(tolerance {rel:g}) at ray {int(np.argmax(err))}")
        moved = prim != base_p
        assert adjacent(f, prim[moved], base_p[moved]).all(), (
            f"{scaled.name} {label}: {int(moved.sum())} rays changed triangle to a non-neighbour")
        print(f"{scaled.name} {label}: ties {ties}, max rel t error {err.max():.2e}, prim changes {moved.sum()}")


# ---------------------------------------------------------------------------------
# flat and degenerate scenes
# ---------------------------------------------------------------------------------

def planar_patch(seed: int, z: float = 0.0, k: int = 9) -> Scene:
    """A k x k vertex patch in the plane z (jittered x, y), 2 (k - 1)^2 triangles."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(k, dtype=np.float64), np.arange(k, dtype=np.float64), indexing="ij")
    jitter = 0.2 * (rng.random((k, k, 2)) - 0.5)
    jitter[[0, -1], :, 0] = 0.0  # keep the border straight so the box is [0, k-1]^2
    jitter[:, [0, -1], 1] = 0.0
    v = np.stack([x + jitter[..., 0], y + jitter[..., 1], np.full_like(x, z)], axis=-1).reshape(-1, 3)
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, e = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, e], 1)])
    return Scene(v, f, name=f"plane z={z:g}")


@pytest.mark.parametrize("case,z", [(0, 0.0), (1, -0.0), (2, 5.0), (3, 1e8)])
def test_flat_planar_scene(case, z):
    rng = np.random.default_rng(1700 + case)
    scene = planar_patch(case, z)
    assert np.all(scene.box_hi > scene.box_lo), "the grid box of a flat scene must be widened"
    n = 500
    target = np.concatenate([scene.box_lo[:2] + rng.random((n, 2)) * (scene.box_hi - scene.box_lo)[:2],
                             np.full((n, 1), z)], axis=1)
    o_above = target + random_unit(rng, n) * 3.0
    d_above = target - o_above
    # in the plane (direction z = +-0.0): grazing rays, all must miss
    o_in = np.concatenate([scene.box_lo[:2] - 1.0 + rng.random((n, 2)) * 10.0, np.full((n, 1), z)], axis=1)
    d_in = random_unit(rng, n)
    d_in[:, 2] = np.where(rng.random(n) < 0.5, 0.0, -0.0)
    # straight down/up through lattice-aligned x, y (integer coordinates are patch vertices or edges)
    o_ax = np.concatenate([rng.integers(0, 9, (n, 2)).astype(np.float64), np.full((n, 1), z + 1.0)], axis=1)
    d_ax = np.zeros((n, 3))
    d_ax[:, 2] = -1.0
    d_ax[:, :2] = np.where(rng.random((n, 2)) < 0.5, 0.0, -0.0)
    o = np.concatenate([o_above, o_in, o_ax])
    d = np.concatenate([d_above, d_in, d_ax])
    ties = check_all(scene, o, d, (8, 8, 1), f"flat scene z={z}")
    check_all(scene, o, d, (3, 5, 4), f"flat scene z={z}", mailboxes=(False,))
    t, prim = Grid.uniform(scene, (8, 8, 1)).intersect(o, d)
    assert np.all(prim[n:2 * n] < 0), "rays lying in the plane of every triangle must miss"
    if abs(z) < 1e3:  # far from the origin the down rays' lattice points are no longer exact
        assert np.all(prim[:n] >= 0), "rays aimed at points of the patch must hit it"
    print(f"flat z={z}: ties per grid {ties}")


#: Exactly collinear vertices: dyadic steps along a dyadic direction, so every coordinate is exact.
LINE_BASE = np.array([1.0, 2.0, -3.0])
LINE_DIRECTION = np.array([0.5, -1.0, 2.0])
LINE_STEPS = 64


def collapsed_vertices(shape: str, rng: np.random.Generator, n_vertices: int) -> np.ndarray:
    """(n_vertices, 3) float64 points on one line (exactly) or all at one point."""
    if shape == "line":
        s = rng.integers(0, LINE_STEPS + 1, n_vertices) / LINE_STEPS
        return LINE_BASE + s[:, None] * LINE_DIRECTION
    point = {"point": [1.0, 2.0, -3.0], "origin point": [0.0, 0.0, 0.0], "far point": [1e15, -1e15, 3.0]}[shape]
    return np.tile(point, (n_vertices, 1))


@pytest.mark.parametrize("case,shape", [(0, "line"), (1, "point"), (2, "origin point"), (3, "far point")])
def test_collapsed_scene_builds_and_agrees(case, shape):
    """Every triangle degenerate (a line or a point): the grid builds, traces, agrees with brute force.

    A scene collapsed onto a point is never hit (all three vertices coincide, so every
    edge function is exactly zero).  On the line, zero-area triangles are refused by the
    intersectors' determinant bound (``test_collinear_triangle_is_never_hit``).
    """
    rng = np.random.default_rng(1800 + case)
    n_tri = 30
    v = collapsed_vertices(shape, rng, 3 * n_tri)
    f = np.arange(3 * n_tri).reshape(-1, 3)
    scene = Scene(v, f, name=shape)
    assert np.all(scene.box_hi > scene.box_lo), f"{shape}: the grid box must be widened to positive extents"
    # rays aimed exactly at the collapsed geometry's points, plus axis-parallel through them
    n = 400
    # the line's two end points are box corners: rays from outside that touch the box only
    # there are test_hit_on_box_corner_is_not_lost, so aim at the other points
    inner = v[~np.all((v == v.min(axis=0)) | (v == v.max(axis=0)), axis=1)] if shape == "line" else v
    target = inner[rng.integers(0, len(inner), n)]
    o = target + random_unit(rng, n)
    d = target - o
    da = signed_zero_directions(rng, n)
    oa = target - da
    o, d = np.concatenate([o, oa]), np.concatenate([d, da])
    for res in [(1, 1, 1), (4, 4, 4), (16, 2, 7)]:
        check_all(scene, o, d, res, f"collapsed onto a {shape}")
        for label, grid in grid_variants(scene, res, mailboxes=(False,)):
            assert grid.info["n_triangles"] == n_tri
            steps, tests, subgrids = grid.count(o, d)
            assert steps.shape == tests.shape == subgrids.shape == (2 * n,)
            if shape != "line":
                t, prim = grid.intersect(o, d)
                assert np.all(prim == -1) and np.all(np.isinf(t)), f"{shape} {label}: a point triangle was hit"


#: An exactly collinear triangle (s = 1/32, 13/32, 22/32 on the dyadic line) and a ray crossing
#: it at t = 1 (at s = 3/32) that the watertight intersector hits at t = 0.99327928.
COLLINEAR_TRIANGLE = [[1.015625, 1.96875, -2.9375], [1.2109375, 1.578125, -2.15625], [1.3515625, 1.296875, -1.59375]]
COLLINEAR_RAY_ORIGIN = [[1.1348762388425309, 2.3656747110178387, -3.6963465459956018]]
COLLINEAR_RAY_DIRECTION = [[-0.08800123884253086, -0.45942471101783866, 0.8838465459956018]]


@pytest.mark.parametrize("intersector", ["watertight", "moller-trumbore"])
def test_collinear_triangle_is_never_hit(intersector):
    """Minimal case: the triangle (0,0,0), (1,0,0), (3,0,0) lies on the x axis (zero area).

    The watertight ray from (1.5, 0.3, 0.1) along (-0.75, -0.3, -0.1) passes through
    (0.75, 0, 0) at t = 1 and was reported as a hit at t = 0.9333; the Moller-Trumbore
    case uses the dyadic line scene (exactly collinear), where hits come back with t
    anywhere from 0.1 to 5 for rays crossing the line at t = 1.  ``COLLINEAR_TRIANGLE``
    is one triangle of that line scene with a ray the watertight test hit at t = 0.9933.
    """
    rng = np.random.default_rng(1850)
    tiny = Scene([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]], [[0, 1, 2]], name="x-axis segment")
    o1, d1 = np.array([[1.5, 0.3, 0.1]]), np.array([[-0.75, -0.3, -0.1]])
    n_tri, n = 30, 2000
    v = collapsed_vertices("line", rng, 3 * n_tri)
    line = Scene(v, np.arange(3 * n_tri).reshape(-1, 3), name="line")
    target = v[rng.integers(0, len(v), n)]
    o = target + random_unit(rng, n)
    d = target - o
    one = Scene(COLLINEAR_TRIANGLE, [[0, 1, 2]], name="collinear triangle")
    o2, d2 = np.array(COLLINEAR_RAY_ORIGIN), np.array(COLLINEAR_RAY_DIRECTION)
    hits = {}
    for scene, oo, dd in ((tiny, o1, d1), (line, o, d), (one, o2, d2)):
        t, prim = brute_force(scene, oo, dd, intersector)
        t_g, prim_g = Grid.uniform(scene, (4, 4, 4), intersector=intersector).intersect(oo, dd)
        hits[scene.name] = (int((prim >= 0).sum()), int((prim_g >= 0).sum()))
    assert all(b == 0 and g == 0 for b, g in hits.values()), f"(brute, grid) hits on zero-area triangles: {hits}"


#: A far-translated, 1e20-scaled triangle whose plane contains the z axis through its vertex 2.
PLANE_RAY_SCALE = 1e20
PLANE_RAY_OFFSET = np.array([1.4216918615556861e20, -1.5122111237799127e19, 4.609995254663515e19])
PLANE_RAY_TRIANGLE = np.array([[0.5, 1.0, 0.25], [0.25, 0.5, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("intersector", [
    "watertight",
    "moller-trumbore",
])
def test_ray_in_triangle_plane_gets_no_wrong_t(intersector):
    """A ray in the plane of a triangle meets it only at its vertex: a hit must be at t = 1.

    The triangle (0.5, 1, 0.25), (0.25, 0.5, 0), (0, 0, 1) has normal (-0.625, 0.3125, 0),
    so the line x = y = 0 lies in its plane and touches the triangle only at (0, 0, 1).
    Scaled by 1e20 and translated by ~1e20, the ray from (0, 0, 0) along +z (same map)
    must either miss or hit at t = 1e20 (the vertex).
    """
    v = PLANE_RAY_TRIANGLE * PLANE_RAY_SCALE + PLANE_RAY_OFFSET
    scene = Scene(v, [[0, 1, 2]], name="plane ray")
    o = PLANE_RAY_OFFSET[None, :].copy()
    d = np.array([[0.0, 0.0, 1.0]])
    t, prim = brute_force(scene, o, d, intersector)
    t_vertex = 1.0 * PLANE_RAY_SCALE
    assert prim[0] < 0 or abs(t[0] - t_vertex) <= REL_T_TOLERANCE * t_vertex, (
        f"{intersector}: hit at t = {t[0] / PLANE_RAY_SCALE:.6g} (scaled), the triangle is only at 1")


def test_degenerate_triangles_mixed_into_a_mesh():
    """Collinear and repeated-vertex triangles inside a closed mesh: grids agree with brute force.

    Repeated-vertex triangles (a, a, b) along mesh edges and (a, a, a) at mesh vertices
    are never the first hit; every ray from inside still hits the closed mesh (watertight).
    """
    rng = np.random.default_rng(1900)
    v, f = jittered_closed_mesh(9)
    n_deg = 60
    # repeated vertex: (a, a, b) along a mesh edge, and (a, a, a)
    edges = f[rng.integers(0, len(f), n_deg), :2]
    rep = np.stack([edges[:, 0], edges[:, 0], edges[:, 1]], axis=1)
    same = np.repeat(f[rng.integers(0, len(f), n_deg // 3), :1], 3, axis=1)
    # collinear: three points on a chord through the sphere's interior; dyadic end points
    # and steps keep them exactly collinear
    a = np.round(0.6 * random_unit(rng, n_deg) * 64) / 64
    b = np.round(0.6 * random_unit(rng, n_deg) * 64) / 64
    s = np.sort(rng.integers(0, 17, (n_deg, 3)), axis=1) / 16
    col_v = a[:, None, :] + s[:, :, None] * (b - a)[:, None, :]
    # collinear on a mesh edge: the edge's end points and its midpoint
    mid = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
    nv = len(v)
    v2 = np.concatenate([v, col_v.reshape(-1, 3), mid])
    col = nv + np.arange(3 * n_deg).reshape(-1, 3)
    on_edge = np.stack([edges[:, 0], nv + 3 * n_deg + np.arange(n_deg), edges[:, 1]], axis=1)
    deg = np.concatenate([rep, same, col, on_edge])
    faces = np.concatenate([f, deg])
    order = rng.permutation(len(faces))  # interleave degenerate triangles with the real ones
    faces = faces[order]
    is_deg = order >= len(f)
    # two identical vertices make every edge function pair come from identical operands,
    # so these can never be hit (collinear ones can: test_collinear_triangle_is_never_hit)
    is_repeated = is_deg & (order < len(f) + len(rep) + len(same))
    scene = Scene(v2, faces, name="mesh with degenerate triangles")
    # rays from inside at mesh vertices, edge midpoints and the collinear points; plus random
    n = 300
    o = 0.2 * random_unit(rng, 4 * n) * rng.random((4 * n, 1))
    targets = np.concatenate([v[edges[:, 0]], mid, col_v.reshape(-1, 3)])
    targets = targets[rng.integers(0, len(targets), 3 * n)]
    d = np.concatenate([targets - o[:3 * n], random_unit(rng, n)])
    ties = check_all(scene, o, d, (6, 6, 6), "degenerate triangles mixed in")
    for label, grid in grid_variants(scene, (6, 6, 6)):
        t, prim = grid.intersect(o, d)
        assert not is_repeated[prim[prim >= 0]].any(), f"{label}: a repeated-vertex triangle was the hit"
        if grid.options["intersector"] == "watertight":
            assert np.all(prim >= 0), f"{label}: a ray from inside the closed mesh escaped"
    print(f"degenerate mix: ties per grid {ties}; {int(is_deg.sum())} degenerate triangles")


@pytest.mark.parametrize("case,flip", [(0, False), (1, True)])
def test_duplicated_triangles_tie(case, flip):
    """Every triangle twice (same or reversed winding): the hit t is unchanged, the prim is either copy."""
    rng = np.random.default_rng(2000 + case)
    v, f = jittered_closed_mesh(case)
    n_f = len(f)
    dup = f[:, ::-1] if flip else f
    scene = Scene(v, np.concatenate([f, dup]), name=f"duplicated flip={flip}")
    base = Scene(v, f)
    o, d = sphere_rays(rng, 600)
    ties = check_all(scene, o, d, (5, 5, 5), f"duplicated triangles flip={flip}")
    for isect in INTERSECTOR_NAMES:
        t_b, p_b = brute_force(base, o, d, isect)
        for label, grid in grid_variants(scene, (5, 5, 5), intersectors=(isect,), mailboxes=(True,)):
            t, prim = grid.intersect(o, d)
            hit = prim >= 0
            assert np.array_equal(hit, p_b >= 0), f"{label}: duplicates changed which rays hit"
            assert np.allclose(t[hit], t_b[hit], rtol=REL_T_TOLERANCE, atol=0), f"{label}: t changed"
            original = prim[hit] % n_f  # copy i + n_f is triangle i again
            assert adjacent(f, original, p_b[hit]).all(), f"{label}: a hit moved off the base mesh's triangle"
    print(f"duplicated flip={flip}: ties per grid {ties}")


# ---------------------------------------------------------------------------------
# a single triangle
# ---------------------------------------------------------------------------------

def single_triangle(case: int, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) float64 vertices: flat in z on the axes; random; lying on a box diagonal plane."""
    return [np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
            rng.normal(size=(3, 3)),
            np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 1.0]])][case]


@pytest.mark.parametrize("case", range(3))
def test_single_triangle(case):
    """N = 1: rays at interior points from anywhere; at vertices and edge points from inside the box.

    (A ray from outside that touches the box only at a vertex or along an edge of the
    triangle lying on the box boundary is ``test_hit_on_box_corner_is_not_lost``.)
    """
    rng = np.random.default_rng(2100 + case)
    tri = single_triangle(case, rng)
    scene = Scene(tri, [[0, 1, 2]], name=f"single triangle {case}")
    lo, hi = scene.box_lo, scene.box_hi
    n = 300
    bary = rng.dirichlet(np.ones(3), n)
    interior = bary @ tri
    o_int = interior + 2.0 * random_unit(rng, n)
    # vertices and random edge points, aimed at from random points strictly inside the box
    s = rng.random((n, 1))
    k = rng.integers(0, 3, n)
    boundary = np.concatenate([tri[k[: n // 2]], (tri[k] + s * (tri[(k + 1) % 3] - tri[k]))[n // 2:]])
    o_box = lo + (0.05 + 0.9 * rng.random((n, 3))) * (hi - lo)
    da = signed_zero_directions(rng, n)
    oa = interior - 2.0 * da
    o = np.concatenate([o_int, o_box, oa])
    d = np.concatenate([interior - o_int, boundary - o_box, da])
    for res in [(1, 1, 1), (3, 3, 3), (2, 5, 1)]:
        check_all(scene, o, d, res, f"single triangle {case} {res}")
    for isect in INTERSECTOR_NAMES:
        t, prim = brute_force(scene, o, d, isect)
        assert set(np.unique(prim)) <= {-1, 0}
        assert np.all(prim[:n] == 0), f"{isect}: rays aimed at interior points of the triangle must hit it"
        assert np.allclose(t[:n], 1.0, rtol=1e-9), f"{isect}: the interior target lies at t = 1"


@pytest.mark.parametrize("intersector", INTERSECTOR_NAMES)
def test_hit_on_box_corner_is_not_lost(intersector):
    """Minimal case: triangle (0,0,0), (1,0,0), (0,1,0), ray aimed from outside at the vertex (0,0,0).

    The box is [0,1] x [0,1] x [-5e-4, 5e-4]; the ray from (0.23528351998403452,
    -1.152032301863296, 1.6178576082855618) along minus that vector reaches x = 0 at
    t = 0.9999999999999999 and y = 0 at t = 1.0, so the slab test rejects it; brute
    force hits at t = 1.  Of 10,000 rays from random points aimed at that vertex,
    about 5% are lost (both intersectors).  The same happens along a box edge: in
    ``lattice_scene(2)`` with a (3, 5, 7) grid, the ray from (-1, 2.2, -2/7) along
    (1/3, -1/5, 1/7) touches the box only on its edge x = 1, y = 1 at t = 6, where brute
    force hits triangle 7 and the grid reports a miss.
    """
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    scene = Scene(tri, [[0, 1, 2]], name="single triangle")
    o1 = np.array([[0.23528351998403452, -1.152032301863296, 1.6178576082855618]])
    rng = np.random.default_rng(2150)
    o = np.concatenate([o1, rng.normal(size=(2000, 3))])
    d = -o
    t_ref, p_ref = brute_force(scene, o, d, intersector)
    for label, grid in grid_variants(scene, (1, 1, 1), intersectors=(intersector,), mailboxes=(False,)):
        t, prim = grid.intersect(o, d)
        lost = (prim < 0) & (p_ref >= 0)
        assert not lost.any(), f"{label}: {int(lost.sum())} of {int((p_ref >= 0).sum())} vertex hits lost"


# ---------------------------------------------------------------------------------
# resolutions that cannot be built
# ---------------------------------------------------------------------------------

#: (65536, 65536, 2) = 2^33 cells: the product overflows 32 bits.
OVERFLOW_RESOLUTIONS = [(65536, 65536, 2), (65536, 65536, 1), (2**31 - 1, 2**31 - 1, 2**31 - 1)]


@pytest.mark.parametrize("resolution", OVERFLOW_RESOLUTIONS)
def test_resolution_overflowing_32_bits_is_refused(resolution):
    scene = jittered_scene(0)
    with pytest.raises(ValueError, match=r"overflow.*32-bit"):
        Grid.uniform(scene, resolution)
    with pytest.raises(ValueError, match=r"overflow.*32-bit"):
        Grid.nested(scene, 2, resolution)


def test_memory_limit_is_refused():
    scene = jittered_scene(0)
    small = Grid.uniform(scene, (4, 4, 4))
    limit = small.info["memory_bytes"] // 2
    with pytest.raises(ValueError, match="memory limit"):
        Grid.uniform(scene, (4, 4, 4), memory_limit=int(limit))
    with pytest.raises(ValueError, match="memory limit"):
        Grid.nested(scene, 3, (4, 4, 4), memory_limit=int(limit))
    # a cell count that fits 32 bits but not the default limit (8 GiB)
    with pytest.raises(ValueError, match="memory limit"):
        Grid.uniform(scene, (1, 1, 2**31 - 1))
    # a generous limit is accepted and builds the same grid (the limit also counts build
    # scratch, so the final size alone is not always enough)
    ok = Grid.uniform(scene, (4, 4, 4), memory_limit=int(BUILD_PEAK_ALLOWANCE_FACTOR * small.info["memory_bytes"]))
    assert ok.info["memory_bytes"] == small.info["memory_bytes"]


def test_overflow_refused_cleanly_in_a_fresh_interpreter():
    """In a fresh process the overflowing build raises a ValueError and exits without a signal."""
    repo = Path(__file__).resolve().parents[1]
    code = textwrap.dedent("""
        import sys
        from calibrate._grid import Grid, Scene
        from calibrate.scenes import jittered_closed_mesh
        scene = Scene(*jittered_closed_mesh(0))
        for build in (lambda: Grid.uniform(scene, (65536, 65536, 2)),
                      lambda: Grid.nested(scene, 2, (65536, 65536, 2))):
            try:
                build()
            except ValueError as exc:
                print("refused:", exc)
            else:
                sys.exit("built a grid of 2^33 cells")
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, f"exit status {proc.returncode} (negative: killed by a signal): {proc.stderr}"
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("refused:")]
    assert len(lines) == 2 and all("overflow" in ln and "65536x65536x2" in ln for ln in lines), proc.stdout

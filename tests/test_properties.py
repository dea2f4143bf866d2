"""Property tests of the kernels (hypothesis): random meshes and rays, degenerate ones included.

Meshes are small (1 to 40 triangles) and drawn to be awkward: coordinates from
1e-20 to 1e20, triangles of zero area (a repeated vertex, collinear corners),
duplicate triangles, flat and line-like scenes, vertices snapped to a lattice
(rays then run along cell faces and through edges and corners).  Rays start
inside, on and far outside the box, run parallel to axes (with +0 and -0
components) and aim exactly at vertices.

Properties:

- the first hit through uniform and nested grids, both intersectors, with and
  without mailboxing, equals brute force (the tie rule of tests/conftest.py: same
  t within 1e-9 relative on another triangle is a tie, e.g. a shared edge), and
  never comes before it.  One exception, stated and bounded: Moller-Trumbore on a
  sliver triangle can report a hit whose point lies outside the triangle's
  bounding box (see :func:`off_triangle_hits`); a grid may miss such a hit, so
  those rays are not compared for that intersector;
- building never crashes: a grid builds, or a resolution past the kernel's limits
  raises ``ValueError``;
- counts are consistent.  ``Grid.count`` gives per-ray totals, not the cells
  visited, so the bound "tests <= references in the visited cells" is checked
  through bounds implied by it: a ray visits a cell at most once, so
  tests <= steps * (most references in one top-level cell, whole subtree) and
  tests <= all references; with mailboxing tests <= triangles; in a uniform grid a
  ray crosses each of the nx-1 + ny-1 + nz-1 inner cell planes at most once, so
  steps <= nx + ny + nz - 2; a uniform grid enters no subgrid, and a nested grid
  enters at most one per cell step.

Settings are derandomized (the same examples every run, no example database).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibrate import Grid, Scene, brute_force

from conftest import first_hit_disagreements

PROPERTY_SETTINGS = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                             suppress_health_check=[HealthCheck.too_slow])
INTERSECTORS = ("watertight", "moller-trumbore")
MAX_TRIANGLES = 40
N_RAYS = 160


@st.composite
def meshes(draw):
    """(vertices (V, 3) float64, faces (F, 3) int64): small, often degenerate."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n_tri = draw(st.integers(1, MAX_TRIANGLES))
    scale = 10.0 ** draw(st.integers(-20, 20))
    offset = draw(st.sampled_from([0.0, 1.0, -3.5, 1e3]))
    shape = draw(st.sampled_from(["cloud", "flat", "line", "lattice", "point-like"]))
    n_v = draw(st.integers(3, 3 * n_tri))
    v = rng.uniform(-1.0, 1.0, (n_v, 3))
    if shape == "flat":
        v[:, rng.integers(3)] = rng.uniform(-1, 1)
    elif shape == "line":
        v = np.outer(rng.uniform(-1, 1, n_v), rng.normal(size=3))
    elif shape == "lattice":
        v = np.round(v * 4.0) / 4.0
    elif shape == "point-like":
        v = v * 1e-9 + rng.uniform(-1, 1, 3)
    v = (v + offset) * scale
    f = rng.integers(0, n_v, (n_tri, 3))
    k = draw(st.integers(0, n_tri))  # triangles made degenerate
    if k:
        rows = rng.choice(n_tri, k, replace=False)
        kinds = rng.integers(0, 3, k)
        for row, kind in zip(rows, kinds):
            if kind == 0:  # a repeated vertex: zero area
                f[row, 2] = f[row, 0]
            elif kind == 1:  # all three the same vertex
                f[row] = f[row, 0]
            else:  # a duplicate of another triangle
                f[row] = f[rng.integers(n_tri)]
    return v, f


def rays_for(scene: Scene, seed: int):
    """(origins, directions): inside, boundary and far origins; axis-parallel and vertex-aimed directions."""
    rng = np.random.default_rng(seed)
    lo, hi = scene.box_lo, scene.box_hi
    ext = hi - lo
    n = N_RAYS
    kind = rng.integers(0, 4, n)
    o = lo + rng.uniform(-0.5, 1.5, (n, 3)) * ext
    far = kind == 1
    o[far] = lo + (rng.uniform(-1, 1, (int(far.sum()), 3)) * 1e3 + 0.5) * ext
    on = kind == 2  # on a face of the box
    o[on] = lo + rng.uniform(0, 1, (int(on.sum()), 3)) * ext
    axis = rng.integers(0, 3, int(on.sum()))
    o[on, axis] = np.where(rng.random(axis.size) < 0.5, lo[axis], hi[axis])
    d = rng.normal(size=(n, 3))
    aimed = (kind == 3) | (rng.random(n) < 0.3)  # exactly at a vertex of the mesh
    targets = scene.vertices[scene.faces[rng.integers(0, scene.n_triangles, int(aimed.sum())), rng.integers(0, 3, int(aimed.sum()))]]
    d[aimed] = targets - o[aimed]
    parallel = rng.random(n) < 0.25  # along an axis, with a signed zero in the others
    ax = rng.integers(0, 3, int(parallel.sum()))
    dp = np.where(rng.random((ax.size, 3)) < 0.5, 0.0, -0.0)
    dp[np.arange(ax.size), ax] = np.where(rng.random(ax.size) < 0.5, 1.0, -1.0)
    d[parallel] = dp
    zero = ~(d != 0).any(axis=1)  # an origin exactly on its target vertex
    d[zero] = (1.0, 0.0, 0.0)
    return o, d


resolutions = st.tuples(st.integers(1, 12), st.integers(1, 12), st.integers(1, 12))


def _check_counts(grid: Grid, scene: Scene, o, d, t, prim, where: str, mailbox: bool):
    tc, pc, steps, tests, subgrids = grid.count(o, d, hits=True)
    assert np.array_equal(tc, t, equal_nan=True) and np.array_equal(pc, prim), f"{where}: twins disagree"
    for name, a in (("steps", steps), ("tests", tests), ("subgrids", subgrids)):
        assert a.shape == (o.shape[0],) and np.issubdtype(a.dtype, np.unsignedinteger), f"{where}: {name} {a.dtype}"
        assert int(a.max(initial=0)) < 2**31, f"{where}: {name} wrapped around: {a.max()}"
    info = grid.info
    most_in_a_cell = int(grid.top_counts().max())
    assert np.all(tests.astype(np.int64) <= steps.astype(np.int64) * most_in_a_cell), (
        f"{where}: more tests than the visited cells can hold")
    assert np.all(tests <= info["n_refs"]), f"{where}: more tests than references"
    if mailbox:
        assert np.all(tests <= scene.n_triangles), f"{where}: a mailboxed ray tested a triangle twice"
    if info["levels"] == 1:
        nx, ny, nz = info["resolution"]
        assert np.all(steps <= nx + ny + nz - 2), f"{where}: {steps.max()} steps in {nx}x{ny}x{nz} cells"
        assert not subgrids.any(), f"{where}: a uniform grid entered a subgrid"
    else:
        assert np.all(subgrids <= steps), f"{where}: more subgrids entered than cells stepped"
    # a ray that never meets the box steps nowhere and tests nothing
    missed = np.isinf(t)
    assert np.all((steps[missed] > 0) | (tests[missed] == 0)), f"{where}: tests without a cell"


#: Relative difference in t within which two hits are a tie (as tests/conftest.py).
TIE_REL = 1e-9
#: A hit point farther than this (relative to the coordinates' magnitude) outside its triangle's
#: bounding box is rounding noise, not a point of the triangle.
OFF_TRIANGLE_REL = 1e-6


def off_triangle_hits(scene: Scene, o, d, t, prim) -> np.ndarray:
    """(n,) bool: a hit whose point o + t d lies outside its triangle's bounding box beyond rounding.

    Moller-Trumbore on a sliver (a triangle whose area is rounding noise beside its
    edges, but above the determinant bound) computes barycentrics of the same size
    as their rounding errors and can report a hit far from the triangle.  Brute
    force reports it; a grid, which tests a triangle only in the cells it overlaps
    and accepts a hit only inside the cell being walked, may not.  Such rays are
    the intersector's noise, not the grid's; the watertight intersector has none.
    """
    hit = prim >= 0
    out = np.zeros(t.shape, dtype=bool)
    if not hit.any():
        return out
    tri = scene.vertices[scene.faces[prim[hit]]]  # (h, 3, 3)
    point = o[hit] + t[hit, None] * d[hit]
    size = np.abs(o[hit]) + np.abs(t[hit, None] * d[hit]) + np.abs(tri).max(axis=1)
    margin = OFF_TRIANGLE_REL * size
    out[hit] = ((point < tri.min(axis=1) - margin) | (point > tri.max(axis=1) + margin)).any(axis=1)
    return out


def _check_grid(grid: Grid, scene: Scene, o, d, refs, where: str, mailbox: bool):
    t, prim = grid.intersect(o, d)
    t_ref, p_ref = refs
    # brute force takes the nearest hit of all: a grid's comes no earlier (but for a tie's rounding)
    assert np.all(t >= t_ref * (1.0 - TIE_REL)), f"{where}: a grid hit comes before brute force's first hit"
    bad, _ = first_hit_disagreements(t, prim, t_ref, p_ref)
    if grid.options["intersector"] == "moller-trumbore":
        bad = bad[~off_triangle_hits(scene, o, d, t_ref, p_ref)[bad]]
    else:
        assert not off_triangle_hits(scene, o, d, t_ref, p_ref).any(), f"{where}: watertight hit off its triangle"
    assert bad.size == 0, (f"{where}: {bad.size} first hits differ from brute force (ray {bad[0]}: "
                           f"o={o[bad[0]].tolist()} d={d[bad[0]].tolist()} grid t={t[bad[0]]!r} prim={prim[bad[0]]}, "
                           f"brute t={t_ref[bad[0]]!r} prim={p_ref[bad[0]]})")
    _check_counts(grid, scene, o, d, t, prim, where, mailbox)


@PROPERTY_SETTINGS
@given(mesh=meshes(), res=resolutions, ray_seed=st.integers(0, 2**32 - 1), mailbox=st.booleans(),
       insertion=st.sampled_from(["exact", "bounds"]))
def test_uniform_first_hits_equal_brute_force(mesh, res, ray_seed, mailbox, insertion):
    scene = Scene(*mesh)
    o, d = rays_for(scene, ray_seed)
    for intersector in INTERSECTORS:
        refs = brute_force(scene, o, d, intersector)
        grid = Grid.uniform(scene, res, intersector, mailbox=mailbox, insertion=insertion)
        _check_grid(grid, scene, o, d, refs, f"uniform {res} {intersector} {insertion} mailbox={mailbox}", mailbox)


@PROPERTY_SETTINGS
@given(mesh=meshes(), levels=st.integers(2, 3), threshold=st.integers(0, 4), scale=st.sampled_from([0.5, 2.0, 8.0]),
       ray_seed=st.integers(0, 2**32 - 1), mailbox=st.booleans())
def test_nested_first_hits_equal_brute_force(mesh, levels, threshold, scale, ray_seed, mailbox):
    scene = Scene(*mesh)
    o, d = rays_for(scene, ray_seed)
    for intersector in INTERSECTORS:
        refs = brute_force(scene, o, d, intersector)
        grid = Grid.nested(scene, levels=levels, threshold=threshold, scale=scale, intersector=intersector,
                           mailbox=mailbox)
        _check_grid(grid, scene, o, d, refs, f"nested L={levels} threshold={threshold} scale={scale} "
                    f"{intersector} mailbox={mailbox}", mailbox)


#: Per-axis cell counts from one to past the kernel's limits (2^31 - 1 per axis, 2^32 - 2 in all).
axis_cells = st.one_of(st.integers(1, 8), st.integers(1, 2**16), st.sampled_from([2**31 - 1, 2**31, 2**40]),
                       st.integers(-3, 0))


#: Memory limits (bytes) for the builds below: small enough that no example allocates much.
BUILD_MEMORY_LIMITS = (2**24, 2**20, 10_000, 1)
REFUSALS = ("at least 1 cell", "exceeds 2^31 - 1", "overflows", "memory limit")


@PROPERTY_SETTINGS
@given(mesh=meshes(), res=st.tuples(axis_cells, axis_cells, axis_cells), levels=st.integers(1, 3),
       memory_limit=st.sampled_from(BUILD_MEMORY_LIMITS))
def test_building_never_crashes(mesh, res, levels, memory_limit):
    """A grid builds, or the resolution is refused with a one-line ValueError naming why."""
    scene = Scene(*mesh)
    try:
        if levels == 1:
            grid = Grid.uniform(scene, res, memory_limit=memory_limit)
        else:
            grid = Grid.nested(scene, levels=levels, resolution=res, memory_limit=memory_limit)
    except ValueError as exc:
        text = str(exc)
        assert "\n" not in text and any(r in text for r in REFUSALS), f"{res} refused: {text}"
        if "memory limit" not in text:
            cells = int(np.prod([int(x) for x in res], dtype=object))
            assert min(res) < 1 or max(res) > 2**31 - 1 or cells > 2**32 - 2, f"{res} refused: {text}"
        return
    info = grid.info
    assert tuple(info["resolution"]) == tuple(res)
    assert info["n_cells"] >= int(np.prod(res)) and info["n_refs"] >= 0
    assert info["memory_bytes"] <= memory_limit
    counts = grid.top_counts()
    assert counts.shape == (res[2], res[1], res[0]) and counts.min() >= 0
    if levels == 1:
        assert int(counts.sum()) == info["n_refs"]


@pytest.mark.xfail(strict=True, reason="known: a direction whose components differ by 1e600 (1e300 and 1e-300) "
                                       "touching the box only at a vertex on its edge misses in the grid; brute "
                                       "force hits the vertex at t = 2.5e-301. Moderate directions agree.")
def test_extreme_direction_through_a_box_edge_vertex():
    scene = Scene([(0.0, 0, 0), (1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)], [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)])
    o, d = np.array([[0.25, 0.25, 1.0]]), np.array([[-1e300, -1e300, 1e-300]])
    t_ref, p_ref = brute_force(scene, o, d)
    assert np.isfinite(t_ref[0])
    t, prim = Grid.uniform(scene, (3, 4, 5)).intersect(o, d)
    bad, _ = first_hit_disagreements(t, prim, t_ref, p_ref)
    assert bad.size == 0

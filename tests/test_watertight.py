"""Watertightness: rays from inside a closed jittered mesh aimed at its vertices and edges all hit.

After pbrt-v4's ``Triangle.Watertight`` test: a closed icosphere with jittered
vertices (``jittered_closed_mesh``), seeded rays from random points near its
centre aimed exactly at mesh vertices, edge midpoints and random points on
edges -- the places where a non-watertight test lets a ray slip between two
triangles.  With the watertight intersector (Woop, Benthin and Wald 2013) every
ray must hit, by brute force and through uniform and nested grids.  The
Moller-Trumbore leak count is measured and printed beside it; it is a property
of that intersector, not something the kernels promise, so it is only checked to
be a count (the test does not require Moller-Trumbore to leak at all).  The timed
and instrumented twins must return bit-identical (t, prim) on these rays.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibrate import Grid, Scene, brute_force
from calibrate.rays import aimed_at_edges
from calibrate.scenes import jittered_closed_mesh

from conftest import first_hit_disagreements

#: Meshes (seeds of jittered_closed_mesh) in the sweep.
MESH_SEEDS = range(4)
#: Ray origins are uniform in a ball of this radius (scene units) about the centre; the
#: mesh has radius 1, so they are strictly inside.
ORIGIN_BALL_RADIUS = 0.1
#: Rays per mesh aimed at random points on random edges (besides every vertex and every
#: edge midpoint once).
RANDOM_EDGE_POINT_RAYS = 3000
#: Uniform grid resolutions in the sweep (cells per axis), plus nested depths.
UNIFORM_RESOLUTIONS = [(1, 1, 1), (4, 4, 4), (16, 16, 16), (37, 23, 11)]
NESTED_LEVELS = (2, 3)
#: A ray aimed at a target point from inside a star-shaped mesh crosses the surface once,
#: at the target (t = 1 for direction = target - origin); rounding of the direction moves
#: the crossing by a few ulps of the unit radius.
TARGET_T_REL_TOLERANCE = 1e-9


def watertight_rays(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator):
    """Rays from inside aimed at every vertex, every edge midpoint and random edge points
    (:func:`calibrate.rays.aimed_at_edges`); returns origins, directions (t = 1 at the target), kind."""
    return aimed_at_edges(vertices, faces, RANDOM_EDGE_POINT_RAYS, rng, origin_radius=ORIGIN_BALL_RADIUS)


def star_shaped_from_ball(vertices: np.ndarray, faces: np.ndarray, radius: float) -> bool:
    """True when every triangle's plane passes farther than ``radius`` from the centre, facing outward.

    Then every ray from the ball crosses the surface exactly once.
    """
    v0, v1, v2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    n = np.cross(v1 - v0, v2 - v0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return bool(np.all(np.einsum("ij,ij->i", n, v0) > radius))


def grids(scene: Scene, intersector: str):
    """Yield (label, grid) over every grid kind in the sweep, mailbox off and on."""
    for mailbox in (False, True):
        for res in UNIFORM_RESOLUTIONS:
            yield f"uniform {res} mailbox={mailbox}", Grid.uniform(scene, res, intersector, mailbox=mailbox)
        for levels in NESTED_LEVELS:
            yield f"nested L={levels} mailbox={mailbox}", Grid.nested(
                scene, levels, intersector=intersector, mailbox=mailbox)
        yield f"nested L=2 top (3, 3, 3) mailbox={mailbox}", Grid.nested(
            scene, 2, (3, 3, 3), intersector=intersector, mailbox=mailbox)


def miss_summary(prim: np.ndarray, kind: np.ndarray) -> dict:
    """{kind: misses} for the rays that returned no hit."""
    return {str(k): int(((prim < 0) & (kind == k)).sum()) for k in np.unique(kind)}


@pytest.mark.parametrize("seed", MESH_SEEDS)
def test_watertight_never_leaks(seed):
    rng = np.random.default_rng(3000 + seed)
    v, f = jittered_closed_mesh(seed)
    scene = Scene(v, f, name=f"jittered{seed}")
    o, d, kind = watertight_rays(v, f, rng)
    assert star_shaped_from_ball(v, f, ORIGIN_BALL_RADIUS), "the test needs rays that cross the mesh once"

    t_ref, p_ref = brute_force(scene, o, d, "watertight")
    assert np.all(p_ref >= 0), f"brute force leaked: misses {miss_summary(p_ref, kind)} of {len(o)} rays"
    err = np.abs(t_ref - 1.0)
    assert err.max() <= TARGET_T_REL_TOLERANCE, f"hit not at the target: |t - 1| = {err.max():.3g}"

    for label, grid in grids(scene, "watertight"):
        t, prim = grid.intersect(o, d)
        assert np.all(prim >= 0), f"{label}: leaked, misses {miss_summary(prim, kind)} of {len(o)} rays"
        bad, ties = first_hit_disagreements(t, prim, t_ref, p_ref)
        assert bad.size == 0, f"{label}: {bad.size} rays differ from brute force (ties {ties})"
        tc, pc, steps, tests, subgrids = grid.count(o, d, hits=True)
        assert np.array_equal(tc, t) and np.array_equal(pc, prim), f"{label}: twins return different hits"


@pytest.mark.parametrize("seed", MESH_SEEDS)
def test_moller_trumbore_leak_count(seed):
    """Moller-Trumbore: its leaks are counted and printed; grids leak exactly where brute force does.

    Only the count is checked (an integer >= 0): Moller-Trumbore is not watertight,
    but nothing requires it to leak on these rays.  Grid and brute force run the same
    triangle tests, so they agree ray by ray (a hit's triangle may differ at a tie).
    """
    rng = np.random.default_rng(3000 + seed)  # the same rays as the watertight test
    v, f = jittered_closed_mesh(seed)
    scene = Scene(v, f, name=f"jittered{seed}")
    o, d, kind = watertight_rays(v, f, rng)
    t_ref, p_ref = brute_force(scene, o, d, "moller-trumbore")
    leaks = int((p_ref < 0).sum())
    assert isinstance(leaks, int) and leaks >= 0
    print(f"seed {seed}: Moller-Trumbore leaks {leaks} of {len(o)} rays by brute force "
          f"({miss_summary(p_ref, kind)}); watertight leaks 0")
    for label, grid in grids(scene, "moller-trumbore"):
        t, prim = grid.intersect(o, d)
        bad, ties = first_hit_disagreements(t, prim, t_ref, p_ref)
        assert bad.size == 0, f"{label}: {bad.size} rays differ from brute force (ties {ties})"
        tc, pc, steps, tests, subgrids = grid.count(o, d, hits=True)
        assert np.array_equal(tc, t) and np.array_equal(pc, prim), f"{label}: twins return different hits"


def test_watertight_shared_vertex_of_many_triangles():
    """Rays aimed exactly at a vertex shared by a fan of 3 to 12 triangles all hit (pbrt's case).

    A fan around a dyadic vertex at the apex of a shallow cone; rays from below
    aimed at the apex from random directions; brute force and a grid hit every ray.
    """
    rng = np.random.default_rng(3100)
    for n_fan in range(3, 13):
        theta = 2.0 * np.pi * (np.arange(n_fan) + rng.random(n_fan) * 0.5) / n_fan
        ring = np.stack([np.cos(theta), np.sin(theta), np.full(n_fan, -0.25)], axis=1)
        apex = np.array([[0.125, -0.375, 0.0]])
        v = np.concatenate([apex, apex + ring])
        f = np.stack([np.zeros(n_fan, dtype=np.int64), 1 + np.arange(n_fan), 1 + (np.arange(n_fan) + 1) % n_fan], 1)
        scene = Scene(v, f, name=f"fan{n_fan}")
        n = 500
        # origins below the fan, inside the cone under the apex
        origins = apex + np.concatenate([0.3 * (rng.random((n, 2)) - 0.5), -0.5 - rng.random((n, 1))], axis=1)
        d = apex - origins
        t_ref, p_ref = brute_force(scene, origins, d, "watertight")
        assert np.all(p_ref >= 0), f"fan of {n_fan}: {int((p_ref < 0).sum())} of {n} rays leaked through the apex"
        for res in [(1, 1, 1), (4, 4, 2)]:
            t, prim = Grid.uniform(scene, res, "watertight").intersect(origins, d)
            assert np.all(prim >= 0), f"fan of {n_fan}, grid {res}: rays leaked through the apex"

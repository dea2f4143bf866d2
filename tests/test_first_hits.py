"""First hits through every kind of grid equal brute force (issue: kernels).

For every built-in scene and several real meshes, 10^5 seeded rays (isotropic
lines through the box, camera rays, rays leaving the surface) are traced by
brute force once per intersector; then through uniform grids from 1x1x1 to
fine and nested grids of depth 2 and 3 (by the kernel's rule and by explicit
tables), with and without mailboxing.  Every
ray's first hit must agree, and the timed and instrumented twins must return
identical hits, on every sign stage (SSE2, AVX2) the host's CPU runs.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibrate import Grid, Scene, brute_force
from calibrate._grid import resolution_for_cells
from calibrate.rays import camera, isotropic, surface
from calibrate.scenes import builtin_names

from conftest import first_hit_disagreements, shared_mesh, traverse_isa, traverse_isas

N_RAYS = 100_000
#: real meshes in the sweep: a compact organic surface, a CAD part, a long-skinny soup, a room
REAL_MESHES = ["spot_6k.obj", "cad_fandisk_13k.obj", "cad_chair_soup_13k.obj", "cornell_box_36.obj"]


def ray_mix(scene: Scene, seed: int):
    """(origins, directions): 40% isotropic lines, 30% camera rays, 30% rays leaving the surface."""
    n_iso, n_cam = int(0.4 * N_RAYS), int(0.3 * N_RAYS)
    o1, d1 = isotropic(scene.box_lo, scene.box_hi, n_iso, seed)
    o2, d2 = camera(scene.box_lo, scene.box_hi, n_cam, seed + 1)
    o3, d3 = surface(scene.vertices, scene.faces, N_RAYS - n_iso - n_cam, seed + 2)
    return np.concatenate([o1, o2, o3]), np.concatenate([d1, d2, d3])


def grid_cases(scene: Scene):
    """(label, builder) pairs: uniform from 1x1x1 to fine, nested of depth 2 and 3."""
    ext = scene.box_hi - scene.box_lo
    n = scene.n_triangles
    coarse = resolution_for_cells(max(n / 8, 8), ext)
    medium = resolution_for_cells(2 * n, ext)
    fine = resolution_for_cells(min(16 * n, 4e6), ext)
    cases = [("1x1x1", lambda isect, mb: Grid.uniform(scene, (1, 1, 1), isect, mailbox=mb)),
             ("bounds insertion", lambda isect, mb: Grid.uniform(scene, medium, isect, mb, insertion="bounds"))]
    for label, res in (("coarse", coarse), ("medium", medium), ("fine", fine)):
        cases.append((f"uniform {label} {res}", lambda isect, mb, res=res: Grid.uniform(scene, res, isect, mailbox=mb)))
    for levels in (2, 3):
        cases.append((f"nested L={levels}", lambda isect, mb, levels=levels: Grid.nested(
            scene, levels=levels, intersector=isect, mailbox=mb)))
    cases.append(("nested L=2 explicit", lambda isect, mb: Grid.nested(
        scene, levels=2, resolution=coarse, intersector=isect, mailbox=mb,
        subgrid_resolutions=np.tile(np.array([[3, 2, 4]], dtype=np.int32), (int(np.prod(coarse)), 1)))))
    # three levels from both tables: every top cell 2x2x2, every second-level cell 2x3x1 but
    # every fifth (a leaf list)
    rows2 = 8 * int(np.prod(coarse))
    sub2 = np.tile(np.array([[2, 3, 1]], dtype=np.int32), (rows2, 1))
    sub2[::5] = 0
    cases.append(("nested L=3 explicit", lambda isect, mb: Grid.nested(
        scene, levels=3, resolution=coarse, intersector=isect, mailbox=mb,
        subgrid_resolutions=np.full((int(np.prod(coarse)), 3), 2, dtype=np.int32), subgrid_resolutions2=sub2)))
    return cases


def check_scene(scene: Scene, seed: int):
    o, d = ray_mix(scene, seed)
    for intersector in ("watertight", "moller-trumbore"):
        t_ref, p_ref = brute_force(scene, o, d, intersector)
        assert np.isfinite(t_ref).mean() > 0.05, "the ray mix should hit the scene"
        for label, build in grid_cases(scene):
            for mailbox in (False, True):
                if label == "1x1x1" and mailbox:
                    continue  # one cell: the mailbox never fires; the brute-force cost is spent once
                grid = build(intersector, mailbox)
                t, prim = grid.intersect(o, d)
                bad, ties = first_hit_disagreements(t, prim, t_ref, p_ref)
                where = f"{scene.name} {label} {intersector} mailbox={mailbox}"
                assert bad.size == 0, (
                    f"{where}: {bad.size} of {N_RAYS} first hits differ from brute force "
                    f"(first ray {bad[0]}: grid t={t[bad[0]]!r} prim={prim[bad[0]]}, "
                    f"brute t={t_ref[bad[0]]!r} prim={p_ref[bad[0]]}); ties {ties}")
                if label == "1x1x1":
                    continue  # one cell is brute force again: the twins are compared on every other grid
                tc, pc, steps, tests, subgrids = grid.count(o, d, hits=True)
                assert np.array_equal(tc, t) and np.array_equal(pc, prim), f"{where}: twins disagree"
                for isa in traverse_isas():
                    with traverse_isa(isa):
                        ti, pi = grid.intersect(o, d)
                    assert np.array_equal(ti, t) and np.array_equal(pi, prim), f"{where}: {isa} disagrees"
                if grid.info["levels"] == 1:
                    assert not subgrids.any(), f"{where}: a uniform grid entered subgrids"
                if mailbox:
                    assert tests.max() <= scene.n_triangles, f"{where}: mailbox tested a triangle twice"


@pytest.mark.slow
@pytest.mark.parametrize("index,name", list(enumerate(builtin_names())))
def test_builtin_scene_first_hits_equal_brute_force(index, name):
    check_scene(Scene.builtin(name), seed=1000 + 10 * index)


@pytest.mark.slow
@pytest.mark.parametrize("index,name", list(enumerate(REAL_MESHES)))
def test_real_mesh_first_hits_equal_brute_force(index, name):
    check_scene(Scene.from_file(shared_mesh(name)), seed=2000 + 10 * index)


@pytest.mark.parametrize("index,name", list(enumerate(["sphere", "cylinder1996"])))
def test_every_sign_stage_gives_the_same_hits(index, name):
    """The timed twin's SSE2 and AVX2 sign stages (where the CPU has AVX2) and the
    instrumented twin return the same hits, bit for bit, on uniform and nested grids."""
    from calibrate import _kernels

    scene = Scene.builtin(name)
    o, d = ray_mix(scene, seed=3000 + 10 * index)
    isas = traverse_isas()
    assert "sse2" in isas and _kernels.traverse_isa() == isas[-1], (isas, _kernels.traverse_isa())
    for grid in (Grid.uniform(scene, resolution_for_cells(scene.n_triangles, scene.box_hi - scene.box_lo)),
                 Grid.nested(scene, levels=2)):
        tc, pc, _, _, _ = grid.count(o, d, hits=True)
        assert np.isfinite(tc).mean() > 0.05
        for isa in isas:
            with traverse_isa(isa):
                t, prim = grid.intersect(o, d)
            assert np.array_equal(t, tc) and np.array_equal(prim, pc), f"{name} {grid.info['levels']} levels: {isa}"


def test_sign_stage_switch_refuses_unknown_names():
    from calibrate import _kernels

    with pytest.raises(ValueError, match="unknown instruction set 'neon'"):
        _kernels.set_traverse_isa("neon")
    assert _kernels.traverse_isa() in ("avx2", "sse2")

"""The general model (models.general) against the instrumented kernel (issue 4's key check).

Steps: the model's expected cells per isotropic line, ``2 (nz dx dy + nx dy dz + ny dz dx) / S``
for the grid's actual per-axis resolution, must match the mean steps the instrumented
twin counts within 1%.  Steps are measured on an *empty* grid over the scene's box
(``calibrate._grid.empty_grid``): nothing is hit, so no ray terminates, and the DDA is
the same walk the scene's grid does.

Tests without termination: the kernel stops at the first hit, so its raw test count on
a real scene is not the no-termination count the model predicts.  The sound comparison
is Crofton's formula applied to the *built* grid: a line conditioned on hitting the box
meets cell c with probability ``S(c) / S``, so the expected tests per ray without
termination (no mailbox) are exactly ``sum_c refs(c) S(c) / S`` with ``refs(c)`` from
``Grid.top_counts()`` of a grid built with exact insertion.  That sum is compared with
the model's ``R(h) S_c / S`` (offset-averaged references) within 5%.  The Crofton sum
itself is checked against the instrumented twin on a scene that no ray can hit
(zero-area triangles: the intersector rejects a zero determinant, yet exact insertion
stores them in every cell their segment crosses), where the kernel's count *is* the
no-termination count.

Scenes: every built-in scene and real meshes from ../shared/meshes (skipped, with the
reason, when that folder is absent).  Resolutions: the model's single-level optimum at
``r = PLANTED_RATIO``, clamped to ``MAX_TEST_CELLS`` so every build stays fast.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from calibrate import rays
from calibrate._grid import Grid, Scene, empty_grid
from calibrate.predict import analytic_uniform_plan, paper_plan, predict, resolve_constants
from calibrate.scenes import builtin_names
from conftest import shared_mesh
from models.closed_forms import MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS
from models.general import optimal_uniform, steps_per_ray, triangle_tests_per_ray
from models.stats import MIN_EXTENT_FRACTION, scene_class

STEPS_REL_TOL = 0.01
TESTS_REL_TOL = 0.05
#: Rays for the steps check: the standard error of the mean steps is below 0.35% of
#: the mean on every scene here (0.25% on the flattest), so 1% is about 3+ sigma.
STEPS_RAYS = 200_000
#: Rays for the Crofton-vs-kernel check on the unhittable scene.
CROFTON_RAYS = 100_000
#: Planted constants (ns) for the resolutions under test; r = T_int / T_step = 5.
T_SETUP_NS, T_STEP_NS, T_INT_NS = 10.0, 3.0, 15.0
PLANTED_RATIO = T_INT_NS / T_STEP_NS
#: Largest grid built by these tests (cells): keeps each build well under a second.
MAX_TEST_CELLS = 2 ** 21
#: Real meshes checked (at least two are required by the issue).
REAL_MESHES = ("spot_6k.obj", "cad_fandisk_13k.obj", "cad_round_cylinder_1k.stl", "stanford_bunny_69k.obj",
               "cad_tray_bottom_4k.stl")
SCENE_IDS = [f"builtin:{n}" for n in builtin_names()] + [f"mesh:{m}" for m in REAL_MESHES]


def _scene(scene_id: str) -> Scene:
    kind, name = scene_id.split(":", 1)
    if kind == "builtin":
        return Scene.builtin(name)
    return Scene.from_file(shared_mesh(name))


def _resolution(stats):
    res, _ = optimal_uniform(stats, T_SETUP_NS, T_STEP_NS, T_INT_NS, max_total=MAX_TEST_CELLS)
    return res


def _crofton_tests(grid: Grid, scene: Scene) -> float:
    """Expected tests per isotropic line without termination: sum_c refs(c) S(c) / S."""
    counts = grid.top_counts()  # (nz, ny, nx) references per cell
    d = scene.box_hi - scene.box_lo
    c = d / np.asarray(grid.resolution, dtype=np.float64)
    s_cell = 2.0 * (c[0] * c[1] + c[1] * c[2] + c[2] * c[0])  # every cell of a uniform grid alike
    s_box = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    return float(counts.sum()) * s_cell / s_box


@pytest.mark.parametrize("i, scene_id", list(enumerate(SCENE_IDS)), ids=SCENE_IDS)
def test_steps_match_instrumented_kernel(i, scene_id):
    scene = _scene(scene_id)
    stats = scene.stats
    res = _resolution(stats)
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, STEPS_RAYS, 1000 + i)
    steps, tests, subgrids = empty_grid(scene.box_lo, scene.box_hi, res).count(o, d)
    assert tests.max() == 0 and subgrids.max() == 0
    model = steps_per_ray(stats.extent, res)
    measured = float(steps.mean())
    assert abs(measured / model - 1.0) < STEPS_REL_TOL, (scene_id, res, measured, model)


@pytest.mark.parametrize("scene_id", SCENE_IDS, ids=SCENE_IDS)
def test_tests_without_termination_match_crofton_sum(scene_id):
    scene = _scene(scene_id)
    stats = scene.stats
    res = _resolution(stats)
    grid = Grid.uniform(scene, res, insertion="exact")
    exact = _crofton_tests(grid, scene)
    model = triangle_tests_per_ray(stats, res, mailbox=False, overlap="exact")
    assert abs(model / exact - 1.0) < TESTS_REL_TOL, (scene_id, res, model, exact)


def _unhittable_segments(rng: np.random.Generator, n: int) -> Scene:
    """n zero-area triangles (the third corner on the segment of the first two) in a unit cube."""
    a = rng.random((n, 3))
    b = a + 0.1 * rng.standard_normal((n, 3))
    m = a + rng.random((n, 1)) * (b - a)
    v = np.concatenate([a, b, m])
    f = np.stack([np.arange(n), np.arange(n) + n, np.arange(n) + 2 * n], axis=1)
    return Scene(v, f, name="segments")


@pytest.mark.parametrize("i, res", list(enumerate([(10, 10, 10), (31, 29, 30), (7, 13, 21)])))
def test_crofton_sum_is_the_kernels_count_when_no_ray_terminates(i, res):
    rng = np.random.default_rng(1000 + i)
    scene = _unhittable_segments(rng, 3000)
    grid = Grid.uniform(scene, res, insertion="exact")
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, CROFTON_RAYS, 2000 + i)
    t, prim, steps, tests, _ = grid.count(o, d, hits=True)
    assert np.all(prim < 0), "a zero-area triangle was hit: rays would terminate"
    exact = _crofton_tests(grid, scene)
    se = float(tests.std()) / math.sqrt(tests.size)
    assert abs(float(tests.mean()) - exact) < 4.0 * se + 1e-12, (tests.mean(), exact, se)
    # and the model (E2 = 0: segments are the talk's lines) within the tests tolerance
    model = triangle_tests_per_ray(scene.stats, res, mailbox=False, overlap="exact")
    assert abs(model / exact - 1.0) < TESTS_REL_TOL
    # the model's steps hold on this scene's own grid too (no hits: the walk never stops early)
    assert abs(float(steps.mean()) / steps_per_ray(scene.stats.extent, res) - 1.0) < STEPS_REL_TOL


# --- tolerance: N = 1, flat boxes, N = 1e7 --------------------------------------------


def _finite_clamped(result_levels):
    for lv in result_levels:
        res = lv["resolution"]
        assert len(res) == 3 and all(isinstance(x, int) and 1 <= x <= MAX_CELLS_PER_AXIS for x in res)
        assert res[0] * res[1] * res[2] <= MAX_TOTAL_CELLS


def _plate_scene():
    """A closed plate 10 x 0.3 x 10 in a box 11 x 0.6 x 11 (pinned by two tiny corner triangles)."""
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.box(extents=(10.0, 0.3, 10.0)).subdivide().subdivide()
    v, f = np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64)
    lo, hi = np.array([-5.5, -0.3, -5.5]), np.array([5.5, 0.3, 5.5])
    pins = np.array([lo, lo + [1e-3, 0, 0], lo + [0, 0, 1e-3], hi, hi - [1e-3, 0, 0], hi - [0, 0, 1e-3]])
    n = len(v)
    return Scene(np.vstack([v, pins]), np.vstack([f, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5]]]))


def test_a_ray_enters_its_first_cell_whole():
    """models.general.cell_fraction against the kernel on a grid one cell deep: with the distance
    fraction f the rays actually cover (from the kernel's own hits), a ray enters
    ``1 + f (S0 - 1)`` cells; the distance alone (``f S0``) misses most of the first cell."""
    from test_models_general import chord_end, sample_lines

    from models.general import cell_fraction

    scene = _plate_scene()
    lo, ext = np.asarray(scene.box_lo), np.asarray(scene.box_hi) - np.asarray(scene.box_lo)
    o, w = sample_lines(np.random.default_rng(4400), ext, 100_000)
    o = o + lo
    t_out = chord_end(o - lo, w, ext)
    for res in ((1, 1, 1), (4, 1, 4), (8, 1, 8), (16, 1, 16)):
        t, prim, steps, _, _ = Grid.uniform(scene, res).count(o, w, hits=True)
        f = np.where(prim >= 0, t, t_out).mean() / t_out.mean()
        assert 0.2 < f < 0.6  # most rays stop at the plate, well inside the box
        s0 = steps_per_ray(ext, res)
        kernel = steps.mean()
        assert cell_fraction(f, s0) * s0 == pytest.approx(kernel, rel=0.05), res
        assert f * s0 < 0.65 * kernel, res



#: Scenes whose steps with termination are checked: every built-in scene but the room (whose rays
#: stop where they enter: counted without termination, checked on its own below) and the two
#: real meshes the approximate fraction got most wrong (they enclose their box).
TERMINATION_IDS = ([f"builtin:{n}" for n in builtin_names() if n != "room"]
                   + ["mesh:sponza_dabrovic_66k.obj", "mesh:cornell_box_36.obj"])
#: The sampled model's steps against the kernel's at the resolutions of this file (the model's
#: optimum without termination for r = 5, finer than a host's): measured within 10.5% (Sponza,
#: 3.3 steps a ray) and 7.1% (cylinder196), within 3% on the rest; at the plans for r = 0.2,
#: within 12.5% (cylinder196) and 3% (docs/compare.md, "Where rays stop, sampled").
TERMINATED_STEPS_REL_TOL = 0.15


@pytest.mark.parametrize("i, scene_id", list(enumerate(TERMINATION_IDS)), ids=TERMINATION_IDS)
def test_steps_with_termination_sampled_match_the_kernel(i, scene_id):
    """Rays that stop at their first hit: the count model scaled by the traversed fraction
    sampled on the real mesh (``calibrate.predict.scene_statistics``) against the kernel's steps
    on other rays of the same distribution, at this file's resolution for the scene; nearer
    than the approximate fraction's on every scene."""
    from calibrate.predict import scene_statistics
    from models.effects import termination_fraction
    from models.general import Terms, predict_uniform

    scene = _scene(scene_id)
    sampled, approx = scene_statistics(scene), scene.stats
    res = _resolution(sampled)
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, 8192, 4500 + i)
    kernel = float(Grid.uniform(scene, res).count(o, d)[0].mean())

    def model(st):
        return predict_uniform(st, res, 0.0, 1.0, 1.0, terms=Terms(traversed_fraction=termination_fraction(st)[0]))[1]

    assert model(sampled) == pytest.approx(kernel, rel=TERMINATED_STEPS_REL_TOL)
    assert abs(model(sampled) - kernel) < abs(model(approx) - kernel)


def test_the_rooms_rays_take_one_step():
    """What the room's fallback rests on: every isotropic ray stops in the cell where it enters."""
    scene = Scene.builtin("room")
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, 8192, 4600)
    for res in ((8, 6, 3), (34, 27, 11), (96, 77, 29)):
        assert np.all(Grid.uniform(scene, res).count(o, d)[0] == 1), res


@pytest.mark.parametrize("fidelity", ["paper", "analytic", "simulated"])
def test_single_triangle_gives_finite_clamped_answers(fidelity):
    # One triangle in the plane z = 0: N = 1 and a flat box (z widened by models.stats.grid_box).
    scene = Scene(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]), name="one")
    out = predict(scene, ratio=PLANTED_RATIO, fidelity=fidelity, levels="auto")
    _finite_clamped(out["levels"])
    for key in ("steps_per_ray", "tests_per_ray"):
        assert math.isfinite(out["predicted"][key]) and out["predicted"][key] >= 0
    assert math.isfinite(out["predicted"]["cost_t_step"]["median"])
    assert out["memory_bytes"] > 0


def _sheet(i: int) -> Scene:
    """A triangulated sheet of aspect up to 1:1e-6 (a tray bottom, a floor): flat z extent."""
    rng = np.random.default_rng(1000 + i)
    n = 40
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 10.0 ** i, n))
    z = 1e-6 * rng.random(x.shape)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    q = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([q, q + 1, q + n], 1), np.stack([q + 1, q + n + 1, q + n], 1)])
    return Scene(v, f, name=f"sheet{i}")


@pytest.mark.parametrize("i", range(3))
def test_flat_boxes_give_finite_clamped_answers(i, monkeypatch):
    scene = _sheet(i)
    for fidelity in ("paper", "analytic"):
        out = predict(scene, ratio=PLANTED_RATIO, fidelity=fidelity, levels="1")
        _finite_clamped(out["levels"])
        assert math.isfinite(out["predicted"]["cost_t_step"]["median"])
    # the closed form (cells as near cubes as the box allows): the thin axis gets no cells
    # flatter than half the others' size (rounding to whole cells); its extent is the widened
    # thickness of models.stats.grid_box.  The cell-shape search may flatten them further
    # where the model prices that cheaper (test_cell_shape_of_a_sheet_is_cheaper_in_kernel_counts).
    monkeypatch.setattr("calibrate.predict.AXIS_MIN_GAIN", math.inf)
    for fidelity in ("paper", "analytic"):
        out = predict(scene, ratio=PLANTED_RATIO, fidelity=fidelity, levels="1")
        res = out["levels"][0]["resolution"]
        cell = scene.stats.extent / np.asarray(res, dtype=np.float64)
        assert scene.stats.extent[2] == pytest.approx(MIN_EXTENT_FRACTION * scene.stats.extent.max())
        assert res[2] == 1 or cell[2] >= 0.5 * min(cell[0], cell[1]), (res, cell)


@pytest.mark.parametrize("ratio", [1e-6, PLANTED_RATIO, 1e6])
def test_ten_million_triangles_via_stats_only(ratio):
    # The sphere's statistics scaled to N = 1e7 as a finer tessellation of the same surface:
    # edge sums grow like sqrt(N), areas stay.
    base = Scene.builtin("sphere").stats
    f = 1e7 / base.n_triangles
    g = math.sqrt(f)
    stats = dataclasses.replace(base, n_triangles=10 ** 7, e1=base.e1 * g, e1_axes=base.e1_axes * g,
                                perimeters=base.perimeters * g, bbox_pair_sums=base.bbox_pair_sums,
                                bbox_triple_sum=base.bbox_triple_sum / g)
    k = resolve_constants(ratio=ratio)
    for plan, _ in (paper_plan(stats, scene_class(stats)[0], k, "auto"), paper_plan(stats, "compact", k, "1"),
                    analytic_uniform_plan(stats, k, False)):
        _finite_clamped(plan["levels"])
        for key in ("steps", "tests", "subgrids"):
            assert math.isfinite(plan[key]) and plan[key] >= 0
        assert 0 < plan["memory_bytes"] < 2 ** 63


#: Closed scans whose two-level plans put the surface's stop on the subgrid count.
NESTED_SURFACE_IDS = ["builtin:sphere", "mesh:stanford_bunny_69k.obj", "mesh:armadillo_86k.obj"]
#: The model's subgrids a ray against the kernel's at r = 0.2: 1.50 against the bunny's 1.54,
#: armadillo's 1.49 and the sphere's 1.88 (by the distance alone 2.13, 2.05 and 1.69: a ray that
#: meets the sphere near its rim enters several subgrids before it hits); tests, by the leaf
#: cells entered, 19.2, 25.9 and 18.0 against the kernel's 15.6, 17.4 and 17.2 (by the distance
#: alone 28.5, 38.0 and 18.8).
NESTED_SUBGRIDS_REL_TOL = 0.25


def _nested_plan_and_kernel(scene_id: str, levels: int, seed: int):
    """A scene's analytic ``levels``-level plan at r = 0.2, its model counts without termination,
    the traversed fraction, and the kernel's tests and subgrids a ray through the same structure."""
    from calibrate import predict as P

    scene = _scene(scene_id)
    stats = P.scene_statistics(scene)
    k = resolve_constants(ratio=0.2)
    plan, _ = P._analytic_plan(scene, stats, k, str(levels), False)
    counts, f = plan["counts"], plan["terms"].traversed_fraction
    assert counts.levels == levels and f < 1.0
    grid, built = P.recommended_grid(scene, ratio=0.2, levels=str(levels))
    assert built["levels"] == levels and built["resolution"] == list(counts.top_resolution)
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, 8192, seed)
    _, tests, subgrids = grid.count(o, d)
    return stats, counts, f, float(tests.mean()), float(subgrids.mean())


@pytest.mark.parametrize("i, scene_id", list(enumerate(NESTED_SURFACE_IDS)), ids=NESTED_SURFACE_IDS)
def test_two_level_counts_stop_at_the_surface(i, scene_id):
    """A closed scan's two-level plan: rays that hit stop in about the first subgrid they enter,
    so the model's subgrids a ray meet the kernel's within 25% and its tests are nearer the
    kernel's than the distance's scaling alone gives (``predict._terminated_nested``)."""
    from calibrate import predict as P
    from models.general import cell_fraction

    stats, counts, f, k_tests, k_sub = _nested_plan_and_kernel(scene_id, 2, 4700 + i)
    _, m_tests, m_sub, _ = P._terminated_nested(counts, stats, f)
    g = cell_fraction(f, counts.steps)
    assert m_sub == pytest.approx(k_sub, rel=NESTED_SUBGRIDS_REL_TOL)
    assert m_sub < g * counts.subgrids  # the surface stopped them sooner than the distance
    assert abs(m_tests - k_tests) < abs(g * counts.tests - k_tests)
    # deeper grids keep the distance's scaling for the subgrids (their count mixes every level's)
    deeper = P._terminated_nested(dataclasses.replace(counts, levels=3), stats, f)
    assert deeper[2] == pytest.approx(g * counts.subgrids)
    assert deeper[1] == pytest.approx(m_tests)  # the tests go by the leaf cells entered at any depth


#: Scenes whose wall runs along the box: a ray that hits stops in the first wall cell it enters,
#: having made about half the tests of a line across the box, where the distance it covers
#: (14% of it) would give a seventh.  At r = 0.2 the kernel's tests a ray and the model's
#: (by the occupied leaf cells entered; by the distance in brackets): `cylinder1996` two levels
#: 26.6 against 24.5 (13.4), three levels 19.1 against 18.8 (9.9); `cylinder196` two levels
#: 10.1 against 11.7 (7.3), three levels 8.3 against 10.7 (5.1).
NESTED_WALL_IDS = ["builtin:cylinder1996", "builtin:cylinder196"]
#: Tolerance on the tests a ray counted by the leaf cells entered, against the kernel's
#: (`cylinder196`'s three levels are the farthest, +29%).
NESTED_WALL_TESTS_REL_TOL = 0.35


@pytest.mark.parametrize("i, case", list(enumerate([(s, L) for s in NESTED_WALL_IDS for L in (2, 3)])),
                         ids=[f"{s}-L{L}" for s in NESTED_WALL_IDS for L in (2, 3)])
def test_nested_tests_where_rays_stop_on_a_wall(i, case):
    """On a cylinder the nested plans' tests a ray, counted in the occupied leaf cells a ray
    enters, meet the kernel's within 35%, where the distance's scaling counts 50-72% of
    them (what made `cylinder19996` plan three levels, 17-26% slower than one level)."""
    from calibrate import predict as P
    from models.general import cell_fraction

    scene_id, levels = case
    stats, counts, f, k_tests, _ = _nested_plan_and_kernel(scene_id, levels, 4800 + i)
    _, m_tests, _, _ = P._terminated_nested(counts, stats, f)
    g = cell_fraction(f, counts.steps)
    assert m_tests == pytest.approx(k_tests, rel=NESTED_WALL_TESTS_REL_TOL)
    assert g * counts.tests < 0.75 * k_tests  # the distance's count, for contrast


def test_nested_tests_of_separate_triangles_scale_with_the_distance():
    """For separate triangles the leaf cells a ray enters scale with the distance it covers, so
    the tests by the leaf cells entered are the distance's: nothing changes for a soup."""
    from calibrate import predict as P
    from models.general import cell_fraction

    scene = Scene.builtin("scattered-compact")
    stats = P.scene_statistics(scene)
    assert stats.separate_fraction == pytest.approx(1.0)
    plan, _ = P._analytic_plan(scene, stats, resolve_constants(ratio=0.2), "2", False)
    counts = plan["counts"]
    for f in (0.2, 0.5, 0.9):
        _, m_tests, _, _ = P._terminated_nested(counts, stats, f)
        assert m_tests == pytest.approx(cell_fraction(f, counts.steps) * counts.tests, rel=1e-12)


# --- the cell shape (predict._axis_search) -------------------------------------------------------


def _closed_form_and_shaped(scene: Scene, monkeypatch):
    """The analytic one-level plan (ratio mode, PLANTED_RATIO) with the cells as near cubes as the
    box allows, and with each axis searched on its own; and the shaped plan's cell-shape effect."""
    with monkeypatch.context() as m:
        m.setattr("calibrate.predict.AXIS_MIN_GAIN", math.inf)
        cubic = predict(scene, ratio=PLANTED_RATIO, fidelity="analytic", levels="1")
    shaped = predict(scene, ratio=PLANTED_RATIO, fidelity="analytic", levels="1")
    effect = [e for e in shaped["effects"] if e["name"] == "cell-shape"]
    assert len(effect) == 1
    return tuple(cubic["levels"][0]["resolution"]), tuple(shaped["levels"][0]["resolution"]), effect[0]


def _kernel_cost(scene: Scene, res, seed: int) -> tuple[float, int]:
    """(steps + r tests a ray, references) of the kernel's grid at ``res`` on seeded isotropic rays."""
    grid = Grid.uniform(scene, res)
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, 8192, seed)
    steps, tests, _ = grid.count(o, d)
    return float(steps.mean() + PLANTED_RATIO * tests.mean()), int(grid.info["n_refs"])


#: Cylinders whose walls run along z: the search makes their cells longer along z than across,
#: equal across, and the kernel's counts agree that the shape is cheaper (steps + r tests a ray
#: at r = 5 on 8,192 isotropic rays: `cylinder1996` at 91x91x171 45.7 against 54.2 at the
#: closed form's 82x82x407, with 321 k references against 620 k; `cylinder196` at 34x35x68
#: 20.0 against 23.9 at 30x30x149, 21 k against 37 k).
SHAPED_CYLINDER_IDS = ["builtin:cylinder196", "builtin:cylinder1996"]


@pytest.mark.parametrize("i, scene_id", list(enumerate(SHAPED_CYLINDER_IDS)), ids=SHAPED_CYLINDER_IDS)
def test_cell_shape_of_a_cylinder_follows_its_walls(i, scene_id, monkeypatch):
    scene = _scene(scene_id)
    cubic, shaped, effect = _closed_form_and_shaped(scene, monkeypatch)
    assert effect["used"] and shaped != cubic and effect["change"] >= 0.01
    cell = scene.stats.extent / np.asarray(shaped, dtype=np.float64)
    assert cell[2] > 1.5 * max(cell[0], cell[1])  # longer along the walls
    assert cell[0] == pytest.approx(cell[1], rel=0.05)  # square across (a round cylinder)
    k_cubic, refs_cubic = _kernel_cost(scene, cubic, 4900 + i)
    k_shaped, refs_shaped = _kernel_cost(scene, shaped, 4900 + i)
    assert refs_shaped < refs_cubic
    assert k_shaped < k_cubic


@pytest.mark.parametrize("i", range(3))
def test_cell_shape_of_a_sheet_is_cheaper_in_kernel_counts(i, monkeypatch):
    """A flat sheet in a flat box: where the search changes the shape, the kernel's counts agree
    (steps + r tests a ray: 10.8 at 477x477x4 against 12.1 at the closed form's 1663x1663x3;
    14.6 at 160x546x5 against 16.5 at 267x2674x4; 25.1 at 56x704x10 against 26.6 at 67x4096x7)."""
    scene = _sheet(i)
    cubic, shaped, effect = _closed_form_and_shaped(scene, monkeypatch)
    if not effect["used"]:
        assert shaped == cubic
        return
    assert _kernel_cost(scene, shaped, 4950 + i)[0] < _kernel_cost(scene, cubic, 4950 + i)[0]


def test_cell_shape_turns_with_the_scene(monkeypatch):
    """The cylinder laid along x instead of z gets the same cells with the axes permuted."""
    scene = Scene.builtin("cylinder1996")
    turned = Scene(scene.vertices[:, [2, 0, 1]].copy(), scene.faces, name="cylinder1996-along-x")
    _, shaped, _ = _closed_form_and_shaped(scene, monkeypatch)
    _, shaped_x, _ = _closed_form_and_shaped(turned, monkeypatch)
    assert shaped_x == (shaped[2], shaped[0], shaped[1])


@pytest.mark.parametrize("name", ["sphere", "scattered-skinny"])
def test_cell_shape_leaves_scenes_without_a_direction(name, monkeypatch):
    """Triangles running every way: the search finds nothing worth a shape and the cells stay cubes."""
    cubic, shaped, effect = _closed_form_and_shaped(Scene.builtin(name), monkeypatch)
    assert not effect["used"] and shaped == cubic and effect["change"] < 0.01

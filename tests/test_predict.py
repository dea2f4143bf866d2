"""`calibrate predict`: the JSON contract, the constants' sources, bad inputs, and each fidelity.

The verb is exercised through its own parser (``calibrate.predict.add_parser`` on a
``calibrate.cli._Parser``), as ``calibrate.cli.build_parser`` will register it.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrate import calfile, rays
from calibrate._grid import Grid, Scene
from calibrate._io import UserError
from calibrate.cli import _Parser
from calibrate.predict import (DEFAULT_CALIBRATION, EXTRAPOLATION_FACTOR, SIM_RAYS, SIM_SEED, add_parser,
                               TERMINATION_RAYS, TERMINATION_SEED, cmd_predict, fit_count_curves, predict,
                               resolve_constants, sample_termination, scene_statistics)
from models.closed_forms import cells_to_resolution, lines_cells, points_cells, two_level_points
from models.effects import rays_stop_on_entry, select_effects
from models.general import predict_uniform

#: Planted constants (ns) of the synthetic calibration, and its posterior's relative spread.
PLANTED_NS = dict(t_setup_ns=20.0, t_step_ns=3.0, t_int_ns=15.0, t_sub_ns=10.0)
POSTERIOR_REL_SD = 0.05
N_SAMPLES = 400
RATIO = 5.0
REQUIRED_KEYS = ("levels", "predicted", "effects", "baselines", "scene_class", "fidelity", "timing_s")


def _parser():
    p = _Parser(prog="calibrate")
    sub = p.add_subparsers(dest="verb", parser_class=_Parser)
    add_parser(sub)
    return p


def _run_json(argv, capsys) -> dict:
    args = _parser().parse_args(["predict", *argv, "--json"])
    assert cmd_predict(args) == 0
    return json.loads(capsys.readouterr().out)


def synthetic_calibration(rng: np.random.Generator) -> dict:
    """A valid calibration whose posterior is lognormal about PLANTED_NS (no fit needed)."""
    names = list(PLANTED_NS)
    values = np.stack([PLANTED_NS[n] * np.exp(POSTERIOR_REL_SD * rng.standard_normal(N_SAMPLES)) for n in names]
                      + [np.full(N_SAMPLES, 0.01)], axis=1)

    def est(x):
        q = np.percentile(x, [50, 16, 84, 2.5, 97.5])
        return {"median": float(q[0]), "ci68": [float(q[1]), float(q[2])], "ci95": [float(q[3]), float(q[4])]}

    constants = {n: est(values[:, j]) for j, n in enumerate(names)}
    constants["ratio"] = est(values[:, 2] / values[:, 1])
    cal = {"schema_version": calfile.SCHEMA_VERSION, "fingerprint": {"cpu_model": "test"}, "constants": constants,
           "isolated": {}, "samples": {"columns": names + ["extra_scatter"], "values": values.tolist()},
           "diagnostics": {"converged": True}, "measurements": [], "meta": {}}
    return calfile.validate(cal)


@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "calibration.json"
    calfile.save(path, synthetic_calibration(np.random.default_rng(1000)))
    return path


# --- the JSON contract -------------------------------------------------------------------


def _check_contract(out: dict):
    for key in REQUIRED_KEYS:
        assert key in out, key
    assert isinstance(out["levels"], list) and out["levels"]
    for lv in out["levels"]:
        res = lv["resolution"]
        assert len(res) == 3 and all(isinstance(x, int) and x >= 1 for x in res)
        assert lv["cells"] >= res[0] * res[1] * res[2] and lv["references"] >= 0
    p = out["predicted"]
    for key in ("steps_per_ray", "tests_per_ray"):
        assert math.isfinite(p[key]) and p[key] > 0
    assert isinstance(out["effects"], list) and out["effects"]
    for e in out["effects"]:
        assert isinstance(e["name"], str) and isinstance(e["reason"], str) and e["reason"]
        assert isinstance(e["used"], bool)
    assert {"pbrt-v2", "manta-L1", "cleary-lambda5", "kalojanov-2level"} <= set(out["baselines"])
    for res in out["baselines"].values():
        assert len(res) == 3 and all(isinstance(x, int) and x >= 1 for x in res)
    assert out["timing_s"] > 0 and out["memory_bytes"] > 0


@pytest.mark.parametrize("fidelity", ["paper", "analytic"])
def test_json_has_every_field_with_a_calibration(fidelity, cal_path, capsys):
    out = _run_json(["sphere", "--calibration", str(cal_path), "--fidelity", fidelity, "--levels", "1"], capsys)
    _check_contract(out)
    ns = out["predicted"]["ns_per_ray"]
    assert ns["ci95"][0] < ns["median"] < ns["ci95"][1]
    assert out["fidelity"] == fidelity and out["units"] == "ns" and out["scene_class"] == "compact"


def test_ratio_path_needs_no_calibration(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no ./calibration.json here
    out = _run_json(["sphere", "--ratio", str(RATIO), "--levels", "1"], capsys)
    _check_contract(out)
    p = out["predicted"]
    assert p["ns_per_ray"] is None and out["units"] == "T_step"
    # in units of T_step: cost = steps + r * tests (T_setup = 0)
    assert p["cost_t_step"]["median"] == pytest.approx(p["steps_per_ray"] + RATIO * p["tests_per_ray"], rel=1e-12)


def test_synthetic_calibration_flows_through(cal_path, capsys, monkeypatch):
    # the closed form's plan: the cell-shape search is tested on its own (test_cell_shape_*)
    monkeypatch.setattr("calibrate.predict.AXIS_MIN_GAIN", math.inf)
    out = _run_json(["cylinder1996", "--calibration", str(cal_path), "--levels", "1"], capsys)
    samples = calfile.samples_by_name(calfile.load(cal_path))
    p = out["predicted"]
    # the interval is the posterior of T_setup + T_step steps + T_int tests, sample by sample
    t = samples["t_setup_ns"] + samples["t_step_ns"] * p["steps_per_ray"] + samples["t_int_ns"] * p["tests_per_ray"]
    assert p["ns_per_ray"]["median"] == pytest.approx(float(np.median(t)), rel=1e-12)
    assert p["ns_per_ray"]["ci95"] == pytest.approx(list(np.percentile(t, [2.5, 97.5])), rel=1e-12)
    # the resolution is the models' optimum for the calibration's median constants
    med = {n: float(np.median(samples[n])) for n in PLANTED_NS}
    sel = select_effects(scene_statistics(Scene.builtin("cylinder1996")), med["t_setup_ns"], med["t_step_ns"], med["t_int_ns"])
    assert tuple(out["levels"][0]["resolution"]) == tuple(sel.resolution)
    assert out["constants"]["ratio"] == pytest.approx(med["t_int_ns"] / med["t_step_ns"])
    assert len(p["resolution_ci95"]) == 2


def test_default_calibration_is_read_from_the_working_directory(cal_path, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / DEFAULT_CALIBRATION).write_bytes(cal_path.read_bytes())
    out = _run_json(["--levels", "1"], capsys)  # default scene: sphere
    assert out["scene"] == "sphere" and out["units"] == "ns"


def test_human_output_shows_grid_effects_and_baselines(cal_path, capsys):
    args = _parser().parse_args(["predict", "room", "--calibration", str(cal_path), "--levels", "1"])
    assert cmd_predict(args) == 0
    text = capsys.readouterr().out
    for word in ("recommended grid", "effects", "baselines", "pbrt-v2", "ns/ray", "class"):
        assert word in text, word


# --- bad inputs ----------------------------------------------------------------------------


def test_missing_default_calibration_says_what_to_do(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = _parser().parse_args(["predict", "sphere"])
    with pytest.raises(ValueError, match=r"calibrate run.*--ratio"):
        cmd_predict(args)


def test_missing_calibration_file_is_named(tmp_path):
    args = _parser().parse_args(["predict", "--calibration", str(tmp_path / "nope.json")])
    with pytest.raises(ValueError, match=r"nope\.json: no such calibration file"):
        cmd_predict(args)


@pytest.mark.parametrize("argv, message", [
    (["--ratio", "-2"], "positive"),
    (["--ratio", "nan"], "positive"),
    (["--ratio", "abc"], "number"),
    (["--fidelity", "exact"], "invalid choice"),
    (["--levels", "4"], "invalid choice"),
    (["--rays", "surface"], "invalid choice"),
    (["--ratio", "5", "--calibration", "x.json"], "not allowed with"),
])
def test_bad_command_lines_are_one_line_errors(argv, message):
    with pytest.raises(UserError, match=message):
        _parser().parse_args(["predict", *argv])


@pytest.mark.parametrize("kwargs, message", [
    (dict(ratio=RATIO, fidelity="exact"), "unknown fidelity 'exact'"),
    (dict(ratio=RATIO, levels=4), "unknown levels 4"),
    (dict(ratio=RATIO, rays="surface"), "unknown ray set"),
    (dict(ratio=-1.0), "ratio must be a finite number > 0"),
    (dict(ratio=0.0), "ratio must be a finite number > 0"),
    (dict(ratio=float("inf")), "ratio must be a finite number > 0"),
    (dict(), "no calibration"),
    (dict(ratio=RATIO, constants=PLANTED_NS), "not both"),
    (dict(constants=dict(t_step_ns=3.0, t_int_ns=15.0)), "lacks t_setup_ns"),
    (dict(constants=dict(PLANTED_NS, t_step_ns=-3.0)), "t_step_ns must be finite and >= 0"),
    (dict(ratio=RATIO, mailbox="yes"), "mailbox must be True or False"),
    (dict(constants=dict(PLANTED_NS, largest_grid_bytes=0)), "largest_grid_bytes must be > 0"),
    (dict(constants=dict(PLANTED_NS, largest_grid_bytes="big")), "largest_grid_bytes must be a whole number"),
])
def test_bad_arguments_raise_value_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        predict("cylinder196", **kwargs)


@pytest.mark.parametrize("i", range(2))
def test_a_plan_far_beyond_the_largest_calibrated_grid_says_it_is_extrapolated(i, cal_path):
    """The note appears once the planned grid holds more than EXTRAPOLATION_FACTOR times
    the largest grid the calibration timed, and not below; a calibration file gives its
    largest in-context grid."""
    plan_bytes = predict("sphere", constants=PLANTED_NS, levels="1")["memory_bytes"]
    limit = plan_bytes / EXTRAPOLATION_FACTOR
    for largest, noted in ((limit * (0.9 - 0.3 * i), True), (limit * (1.05 + i), False)):
        out = predict("sphere", constants=dict(PLANTED_NS, largest_grid_bytes=int(largest)), levels="1")
        notes = [n for n in out["notes"] if n.startswith("extrapolated")]
        assert len(notes) == int(noted), (largest, out["notes"])
        if noted:
            assert f"{plan_bytes / 1e6:,.0f} MB" in notes[0] and f"{plan_bytes / int(largest):.0f} times" in notes[0]
    assert not any(n.startswith("extrapolated") for n in predict("sphere", constants=PLANTED_NS)["notes"])
    cal = calfile.load(cal_path)
    assert calfile.largest_grid_bytes(cal) is None  # no measurements in the synthetic file
    cal["measurements"] = [dict(kind="in_context", memory_bytes=5_000 * (j + 1), values_ns=[1.0]) for j in range(3)]
    cal["measurements"] += [dict(kind="isolated", memory_bytes=10**9, values_ns=[1.0]),
                            dict(kind="in_context", memory_bytes=10**9, values_ns=[])]
    assert calfile.largest_grid_bytes(cal) == 15_000


def test_unknown_scene_is_named():
    with pytest.raises(ValueError, match="neither a mesh file nor a built-in scene"):
        predict("teapot", ratio=RATIO)


# --- fidelities ------------------------------------------------------------------------------


@pytest.mark.parametrize("i, r", list(enumerate([0.5, RATIO, 40.0])))
def test_paper_fidelity_reproduces_the_closed_forms(i, r):
    sphere = Scene.builtin("sphere")  # compact: the points law
    st = sphere.stats
    out = predict(sphere, ratio=r, fidelity="paper", levels="1")
    m3 = float(points_cells(st.n_triangles, r))
    assert out["levels"][0]["resolution"] == list(cells_to_resolution(m3, st.extent))
    m = m3 ** (1.0 / 3.0)  # the talk's cost: m steps and N / m^2 tests
    assert out["predicted"]["steps_per_ray"] == pytest.approx(m, rel=1e-12)
    assert out["predicted"]["tests_per_ray"] == pytest.approx(st.n_triangles / m ** 2, rel=1e-12)
    # two levels: m1^3 = (2 k^2 N r)^0.6 and m2^3 = (2 N r / k^3)^0.6 with the scene's k
    out2 = predict(sphere, ratio=r, fidelity="paper", levels="2")
    m1, m2 = two_level_points(st.n_triangles, r, st.k)
    assert out2["levels"][0]["resolution"] == list(cells_to_resolution(float(m1), st.extent))
    sub_extent = st.extent / np.asarray(out2["levels"][0]["resolution"], dtype=np.float64)
    assert out2["levels"][1]["resolution"] == list(cells_to_resolution(float(m2), sub_extent))
    assert out2["predicted"]["subgrids_per_ray"] == pytest.approx(st.k, rel=1e-12)  # a ray enters k subgrids
    # long skinny triangles: the lines law
    cyl = Scene.builtin("cylinder1996")
    out3 = predict(cyl, ratio=r, fidelity="paper", levels="1")
    assert out3["scene_class"] == "long-skinny"
    assert out3["levels"][0]["resolution"] == list(cells_to_resolution(float(lines_cells(1996, r)),
                                                                         cyl.stats.extent))


def test_a_shaped_plans_interval_keeps_its_shape(cal_path, capsys):
    """A cylinder's plan with cells long along its walls: the posterior's resolution interval is
    picked among that shape's scalings (the closed form's cubes would not contain the plan)."""
    out = _run_json(["cylinder1996", "--calibration", str(cal_path), "--levels", "1"], capsys)
    shape = [e for e in out["effects"] if e["name"] == "cell-shape"]
    assert len(shape) == 1 and shape[0]["used"]
    res = np.asarray(out["levels"][0]["resolution"], dtype=np.float64)
    lo, hi = (np.asarray(r, dtype=np.float64) for r in out["predicted"]["resolution_ci95"])
    assert np.prod(lo) <= np.prod(res) <= np.prod(hi)
    for bound in (lo, hi):  # the same per-axis proportions, up to whole cells
        s = bound / res
        assert np.all(np.abs(s / s.mean() - 1.0) <= 1.0 / np.minimum(bound, res) + 1e-9), (bound, res)


def test_analytic_single_level_is_the_models_prediction(monkeypatch):
    monkeypatch.setattr("calibrate.predict.AXIS_MIN_GAIN", math.inf)  # the closed form's plan
    scene = Scene.builtin("room")
    k = resolve_constants(constants=PLANTED_NS)
    out = predict(scene, constants=PLANTED_NS, fidelity="analytic", levels="1")
    stats = scene_statistics(scene)  # where rays stop sampled on the mesh
    sel = select_effects(stats, k.t_setup, k.t_step, k.t_int, termination=True)
    assert tuple(out["levels"][0]["resolution"]) == tuple(sel.resolution)
    t, steps, tests = predict_uniform(stats, sel.resolution, k.t_setup, k.t_step, k.t_int, terms=sel.terms)
    assert out["predicted"]["ns_per_ray"]["median"] == pytest.approx(t, rel=1e-12)
    assert out["predicted"]["steps_per_ray"] == pytest.approx(steps, rel=1e-12)
    assert out["predicted"]["model_cost_per_ray"] == pytest.approx(t, rel=1e-12)
    pbrt = out["baselines_detail"]["pbrt-v2"]
    assert pbrt["cost_per_ray"] == pytest.approx(
        predict_uniform(stats, pbrt["levels"][0], k.t_setup, k.t_step, k.t_int, terms=sel.terms)[0], rel=1e-12)
    assert {e["name"] for e in out["effects"]} >= {"edge", "area", "mailbox", "termination", "clustering", "subgrid"}
    assert [e["used"] for e in out["effects"] if e["name"] == "mailbox"] == [False]


def test_analytic_auto_levels_reports_the_depths_it_compared():
    out = predict("scattered-compact", constants=PLANTED_NS, fidelity="analytic", levels="auto")
    why = [e["reason"] for e in out["effects"] if e["name"] == "levels"]
    assert len(why) == 1 and "L=1" in why[0] and "L=2" in why[0]
    assert 1 <= len(out["levels"]) <= 3


def test_fit_count_curves_recovers_planted_coefficients():
    s = np.array([0.5, 0.7, 1.0, 1.4, 2.0])
    a, b = fit_count_curves(s, 2.0 + 30.0 * s, 1.0 + 4.0 / s + 9.0 / s ** 2)
    assert a == pytest.approx([2.0, 30.0], rel=1e-9)
    assert b == pytest.approx([1.0, 4.0, 9.0], rel=1e-9)


@pytest.mark.parametrize("ray_set", ["isotropic", "camera"])
def test_simulated_counts_are_the_kernels_counts(ray_set):
    scene = Scene.builtin("scattered-skinny")
    out = predict(scene, constants=PLANTED_NS, fidelity="simulated", levels="1", rays=ray_set)
    res = out["levels"][0]["resolution"]
    gen = rays.camera if ray_set == "camera" else rays.isotropic
    o, d = gen(scene.box_lo, scene.box_hi, SIM_RAYS, SIM_SEED)
    steps, tests, _ = Grid.uniform(scene, res).count(o, d)
    assert out["predicted"]["steps_per_ray"] == pytest.approx(float(steps.mean()), rel=1e-12)
    assert out["predicted"]["tests_per_ray"] == pytest.approx(float(tests.mean()), rel=1e-12)
    sim = out["simulation"]
    assert sim["ray_set"] == ray_set and len(sim["scales"]) >= 3
    # the chosen scale minimises the fitted curves' cost within the measured range
    a, b = np.array(sim["steps_fit"]), np.array(sim["tests_fit"])
    k = resolve_constants(constants=PLANTED_NS)
    s = np.array(sim["scales"])
    cost = lambda x: k.t_step * (a[0] + a[1] * x) + k.t_int * (b[0] + b[1] / x + b[2] / x ** 2)  # noqa: E731
    assert cost(sim["best_scale"]) <= cost(s).min() + 1e-9


def test_camera_rays_with_the_analytic_model_say_so():
    out = predict("cylinder196", ratio=RATIO, fidelity="analytic", levels="1", rays="camera")
    assert any("camera rays" in n for n in out["notes"])


def test_scene_statistics_are_cached_per_scene_object():
    scene = Scene.builtin("scattered-compact")
    first = predict(scene, ratio=RATIO, fidelity="analytic", levels="1")
    stats, sampled = scene.stats, scene_statistics(scene)
    second = predict(scene, ratio=RATIO, fidelity="analytic", levels="1")
    assert scene.stats is stats and scene_statistics(scene) is sampled and first["levels"] == second["levels"]
    assert sampled.termination is not None and stats.termination is None



def test_sampled_termination_recovers_a_centred_sphere():
    """Where rays stop, measured: the hit probability is Crofton's A / S for a convex surface, and
    the traversed fraction is the exact sphere's on the same lines (the mesh is inscribed in it)."""
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    v = np.asarray(m.vertices) + 1.0  # centred in [0, 2]^3, which two specks at the corners span
    f = np.asarray(m.faces, dtype=np.int64)
    specks = np.array([[0, 0, 0], [1e-7, 0, 0], [0, 1e-7, 0], [2, 2, 2], [2 - 1e-7, 2, 2], [2, 2 - 1e-7, 2]])
    n = len(v)
    scene = Scene(np.vstack([v, specks]), np.vstack([f, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5]]]), name="ball")
    assert np.allclose(scene.box_lo, 0.0) and np.allclose(scene.box_hi, 2.0)
    ts = sample_termination(scene)
    assert ts.rays == TERMINATION_RAYS
    o, d = rays.isotropic(scene.box_lo, scene.box_hi, TERMINATION_RAYS, TERMINATION_SEED)
    t_in, t_out = rays.box_chords(o, d, scene.box_lo, scene.box_hi)
    oc = o - 1.0
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - 0.09)
    hit = disc > 0
    t_hit = np.where(hit, -b - np.sqrt(np.maximum(disc, 0.0)), t_out)
    exact = float(np.sum(t_hit - t_in) / np.sum(t_out - t_in))
    assert ts.fraction == pytest.approx(exact, abs=0.003)
    assert ts.p_hit == pytest.approx(hit.mean(), abs=0.003)  # rays grazing the facets may differ
    crofton = 4.0 * math.pi * 0.09 / 24.0
    assert abs(ts.p_hit - crofton) < 4.0 * math.sqrt(crofton * (1 - crofton) / TERMINATION_RAYS)
    # the analytic fidelity's counts scale by it
    out = predict(scene, ratio=RATIO, fidelity="analytic", levels="1")
    why = [e["reason"] for e in out["effects"] if e["name"] == "termination"][0]
    assert f"sampled, {TERMINATION_RAYS} rays" in why and f"{100 * ts.fraction:.1f}% of the no-hit distance" in why


def test_a_large_mesh_keeps_the_approximate_fraction(monkeypatch):
    """Above TERMINATION_SAMPLE_MAX_TRIANGLES the sample's grid would cost more than the analytic
    prediction's time goal: no termination sample, the reason says approximate."""
    import calibrate.predict as P

    scene = Scene.builtin("cylinder1996")
    monkeypatch.setattr(P, "TERMINATION_SAMPLE_MAX_TRIANGLES", scene.n_triangles - 1)
    sampled = scene_statistics(scene)
    assert sampled.termination is None and sampled.n_triangles == scene.stats.n_triangles
    assert sampled.triangles is not None  # the triangle sample is a strided read, cheap at any size
    out = predict(scene, ratio=RATIO, fidelity="analytic", levels="1")
    assert "termination (approximate)" in [e["reason"] for e in out["effects"] if e["name"] == "termination"][0]


def test_rays_stopping_where_they_enter_the_room_are_counted_without_termination(monkeypatch):
    """The room's walls are its box's faces: every sampled ray stops where it enters, and the plan
    is the one of rays that never stop (the count model alone would refine without bound)."""
    monkeypatch.setattr("calibrate.predict.AXIS_MIN_GAIN", math.inf)  # the closed form's plan
    scene = Scene.builtin("room")
    st = scene_statistics(scene)
    assert rays_stop_on_entry(st) and st.termination.p_hit == 1.0 and st.termination.fraction < 1e-9
    k = resolve_constants(constants=PLANTED_NS)
    out = predict(scene, constants=PLANTED_NS, fidelity="analytic", levels="1")
    never = select_effects(scene.stats, k.t_setup, k.t_step, k.t_int, termination=False)
    assert tuple(out["levels"][0]["resolution"]) == tuple(never.resolution)
    why = [e for e in out["effects"] if e["name"] == "termination"][0]
    assert not why["used"] and "where it enters the box" in why["reason"]


@pytest.mark.parametrize("i, res", list(enumerate([(8, 9, 10), (40, 40, 40)])))
def test_memory_estimate_uses_the_kernels_layout(i, res):
    from calibrate.predict import _memory_bytes

    scene = Scene.builtin("scattered-compact")
    info = Grid.uniform(scene, res).info
    est = _memory_bytes(res[0] * res[1] * res[2], info["n_refs"], 1)
    # the kernel adds only its fixed-size gc_grid header and the last pack's unused lanes
    assert 0 <= info["memory_bytes"] - est < 1024, (info["memory_bytes"], est)


@pytest.mark.parametrize("l2, l3, depth", [(98.0, 60.0, 1), (96.0, 94.0, 2), (96.0, 90.0, 3), (120.0, 10.0, 1)])
def test_deeper_grids_need_a_gain_beyond_the_models_misfit(l2, l3, depth):
    """The depth rule on planted costs: L=1 costs 100; deeper only for a gain of DEEPEN_MIN_GAIN."""
    from calibrate.predict import DEEPEN_MIN_GAIN, _deepen

    assert DEEPEN_MIN_GAIN == pytest.approx(0.03)
    k = resolve_constants(constants=dict(t_setup_ns=0.0, t_step_ns=1.0, t_int_ns=1.0, t_sub_ns=1.0))
    plan = lambda steps, L: (dict(steps=steps, tests=0.0, subgrids=0.0, levels=[{}] * L), [])  # noqa: E731
    cost = {2: l2, 3: l3}
    best, effects = _deepen(k, lambda: plan(100.0, 1), lambda L: plan(cost[L], L), (ValueError,), "planted")
    assert len(best["levels"]) == depth
    assert "3%" in effects[-1]["reason"]


def test_the_depth_rule_prices_a_plan_on_the_bytes_it_charges(one_capacity):
    """A uniform plan whose memory term charges fewer bytes than its grid holds (what rays read,
    models.memory.read_bytes) is priced on those in the depth rule, as its own prediction is: planted,
    a 64 MiB grid charged as 8 MiB against a 16 MiB cache costs its steps alone and beats a nested
    plan 10% cheaper than the whole grid's price."""
    from calibrate.predict import _deepen

    k = resolve_constants(constants=dict(t_setup_ns=0.0, t_step_ns=1.0, t_int_ns=1.0, t_sub_ns=1.0, t_mem_ns=1.0,
                                         cache_bytes=16 * 2 ** 20))
    mib = 2 ** 20
    uniform = dict(steps=100.0, tests=0.0, subgrids=0.0, levels=[{}], memory_bytes=64 * mib, charged_bytes=8 * mib)
    whole = k.cost(100.0, 0.0, 0.0, 64 * mib)
    assert whole == pytest.approx(100.0 + 0.75 * 100.0)  # 3/4 of the lines beyond the cache
    nested = dict(steps=0.9 * whole, tests=0.0, subgrids=0.0, levels=[{}, {}], memory_bytes=8 * mib)
    best, effects = _deepen(k, lambda: (dict(uniform), []), lambda L: (dict(nested), []), (ValueError,), "planted")
    assert len(best["levels"]) == 1
    assert "L=1: 100," in effects[-1]["reason"]


def test_auto_depth_prices_the_uniform_plan_as_levels_1_does():
    """``predict --levels auto``'s L=1 cost is the one ``--levels 1`` predicts: on ``cylinder19996``
    (shaped cells whose end caps rays seldom read) with a memory term the two differed 3-fold."""
    from calibrate import predict as P

    k = dict(t_setup_ns=50.0, t_step_ns=7.0, t_int_ns=1.0, t_sub_ns=40.0, t_mem_ns=16.0, t_visit_ns=5.0,
             cache_bytes=16 * 2 ** 20)
    one = P.predict("cylinder19996", constants=k, levels=1)
    auto = P.predict("cylinder19996", constants=k, levels="auto")
    reason = next(e["reason"] for e in auto["effects"] if e["name"] == "levels")
    l1 = float(reason.split("L=1: ")[1].split(",")[0])
    assert l1 == pytest.approx(one["predicted"]["ns_per_ray"]["median"], rel=1e-3)


@pytest.mark.parametrize("l2, depth", [(79.9, 1), (None, 2)])  # 79.9 would pass without the set-up
def test_ratio_mode_gain_counts_an_assumed_set_up(l2, depth):
    """With a ratio alone T_setup is unknown: the gain is taken on cost + RATIO_MODE_T_SETUP_IN_T_STEP,
    so L=1 at 100 + s and L=2 at l2 + s (s = 2.66) must differ by 20% of 102.66: L=2 below 82.13."""
    from calibrate.predict import RATIO_MODE_T_SETUP_IN_T_STEP, _deepen

    k = resolve_constants(ratio=1.0)  # T_setup 0, T_step 1
    s = RATIO_MODE_T_SETUP_IN_T_STEP
    from calibrate.predict import DEEPEN_MIN_GAIN_RATIO_MODE

    assert DEEPEN_MIN_GAIN_RATIO_MODE == pytest.approx(0.20)
    l2 = l2 if depth == 1 else 0.8 * (100.0 + s) - s - 0.01  # just inside the margin
    plan = lambda steps, L: (dict(steps=steps, tests=0.0, subgrids=0.0, levels=[{}] * L), [])  # noqa: E731
    best, effects = _deepen(k, lambda: plan(100.0, 1), lambda L: plan(l2 if L == 2 else 1e9, L), (ValueError,),
                            "planted")
    assert len(best["levels"]) == depth
    assert "T_setup taken as" in effects[-1]["reason"]


def test_the_search_tries_thin_axes_one_and_two_deep():
    """The memory/occupied-cell search scales every axis; one that scales to fewer than
    THIN_AXIS_CELLS cells gets its floor and ceiling both (the CAD tray: 106x2x106 at 0.55x is
    58x1x58 by rounding, and 58x2x58 is the one measured faster)."""
    from calibrate.predict import _scaled_with_thin_axes

    out = _scaled_with_thin_axes((106, 2, 106), 0.55)
    assert out[0] == (58, 1, 58) and set(out) == {(58, 1, 58), (58, 2, 58)}
    assert _scaled_with_thin_axes((40, 40, 40), 0.5) == [(20, 20, 20)]  # no thin axis
    assert set(_scaled_with_thin_axes((3, 3, 50), 0.7)) == {(2, 2, 35), (2, 3, 35), (3, 2, 35), (3, 3, 35)}
    assert _scaled_with_thin_axes((1, 1, 1), 0.25) == [(1, 1, 1)]  # never below one cell


def test_the_samples_grid_bounds_its_references(monkeypatch):
    """Long triangles cross many cells: the sample's grid is coarsened until its expected
    references fit TERMINATION_MAX_REFS, and the fraction it measures does not change."""
    import calibrate.predict as P
    from models.general import expected_refs

    scene = Scene.builtin("cylinder1996")
    full = P.termination_grid_resolution(scene)
    assert full == P.resolution_for_cells(P.TERMINATION_CELLS_PER_TRIANGLE * scene.n_triangles,
                                          scene.box_hi - scene.box_lo)
    refs = expected_refs(scene.stats, full)
    monkeypatch.setattr(P, "TERMINATION_MAX_REFS", refs / 3.0)
    small = P.termination_grid_resolution(scene)
    assert np.prod(small) < np.prod(full) and expected_refs(scene.stats, small) <= refs / 3.0
    # first hits do not depend on the grid
    coarse = P.sample_termination(scene)
    monkeypatch.undo()
    fine = P.sample_termination(scene)
    assert (coarse.fraction, coarse.p_hit, coarse.rays) == (fine.fraction, fine.p_hit, fine.rays)
    assert coarse.resolution == small and fine.resolution == full  # each keeps its own grid's occupied cells


@pytest.mark.parametrize("levels", ["1", "2"])
def test_the_json_constants_price_the_predicted_counts(levels):
    """Every constant the predicted cost uses is in the output's ``constants``: with them a
    reader recomputes ``model_cost_per_ray`` from the predicted counts per ray (T_visit
    among them: it was left out once)."""
    planted = dict(PLANTED_NS, t_visit_ns=7.0)
    out = predict(Scene.builtin("sphere"), constants=planted, fidelity="analytic", levels=levels)
    c, p = out["constants"], out["predicted"]
    assert c["t_visit"] == pytest.approx(7.0) and c["t_mem"] == 0.0
    assert p["visits_per_ray"] > 0
    if levels == "2":
        assert p["subgrids_per_ray"] > 0
    priced = (c["t_setup"] + c["t_step"] * p["steps_per_ray"] + c["t_int"] * p["tests_per_ray"]
              + c["t_sub"] * p["subgrids_per_ray"] + c["t_visit"] * p["visits_per_ray"])
    assert p["model_cost_per_ray"] == pytest.approx(priced, rel=1e-9)


def test_the_axis_search_goes_down_to_one_cell_an_axis():
    """Planted constants of an isotropic fit with the memory term (T_mem 33.6 ns a line beyond a
    16 MiB cache): the model's cheapest grid for ``cylinder19996`` has 2-3 cells along its axis,
    far below the 1/64 of the near-cubic start (106x106x525) the search was once bounded by,
    which stopped it at 8 (the fastest grids measured on its sweeps have 2-5)."""
    from calibrate.predict import _axis_search, _priced

    k = resolve_constants(constants=dict(t_setup_ns=44.5, t_step_ns=6.42, t_int_ns=1.54, t_sub_ns=54.2,
                                         t_mem_ns=33.6, t_visit_ns=9.47, cache_bytes=16 * 2 ** 20))
    stats = scene_statistics(Scene.builtin("cylinder19996"))
    terms = select_effects(stats, k.t_setup, k.t_step, k.t_int, mailbox=False, termination=True,
                           overlap="exact", levels=1).terms
    start = (106, 106, 525)
    got, cost, _ = _axis_search(stats, k, terms, start, _priced(stats, start, k, terms)[0])
    assert got[2] <= 4 < 525 / 64
    bounded = min(_priced(stats, (x, y, 8), k, terms)[0] for x, y in ((got[0], got[1]), (182, 133)))
    assert cost < 0.97 * bounded

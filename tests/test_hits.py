"""A ray's hit: what a ray does when it finds one costs something no other count carries.

The winning test's last stage, the hit recorded and the walk's exit on a hit are paid
once per ray that hits; a scene's share of such rays is fixed at every resolution.
``calibrate run`` records the rays that hit in each in-context configuration and fits
``T_hit`` when the timings call for it, with a prior from the one-cell suite (whose aimed
rays all hit); ``predict`` adds ``T_hit`` times the share of isotropic lines that hit the
mesh (sampled on the mesh) and ``compare`` the share of its own rays.  These tests check
a planted T_hit against the fit, its absence, the file's checks, the suites' count, the
prediction's arithmetic and the header.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrate import calfile
from calibrate import run as R
from calibrate._grid import Grid, Scene
from calibrate.predict import predict, resolve_constants, scene_statistics
from calibrate.suites import _config, _rays
from conftest import assert_planted_recovered, exported_header, planted_calibration, planted_counts
from models.effects import termination_fraction

RAYS = 2048
TRUTH = {"t_setup_ns": 60.0, "t_step_ns": 10.0, "t_int_ns": 1.3, "t_sub_ns": 60.0, "t_visit_ns": 5.0,
         "t_hit_ns": 40.0}
PRIORS = {"t_setup_ns": (70.0, 0.3), "t_sub_ns": (60.0, 0.7), "t_hit_ns": (30.0, 0.5)}
NOISE_REL = 0.02
N_CONFIGS = 40
N_REPEATS = 5
ALL = calfile.OPTIONAL_COUNT_FIELDS


def _records(seed: int, truth=TRUTH) -> list[dict]:
    """In-context records of ten scenes x two ray sets, each (scene, ray set) with its own share of
    rays that hit (10-95%, the same at every resolution, as in a real suite); values from ``truth``."""
    rng = np.random.default_rng(seed)
    share = {(s, rs): rng.uniform(0.1, 0.95) for s in range(10) for rs in ("camera", "isotropic")}
    recs = []
    for j in range(N_CONFIGS):
        counts = planted_counts(rng, j, RAYS)
        counts["visits"] = int(counts["steps"] * rng.uniform(0.05, 1.0))
        scene, ray_set = j % 10, ("camera", "isotropic")[(j // 10) % 2]
        counts["hits"] = int(RAYS * share[scene, ray_set])
        mu = sum(counts.get(k, RAYS) * truth[name] for k, name in (
            ("rays", "t_setup_ns"), ("steps", "t_step_ns"), ("tests", "t_int_ns"), ("subgrids", "t_sub_ns"),
            ("visits", "t_visit_ns"), ("hits", "t_hit_ns")))
        recs.append(dict(kind="in_context", scene=f"scene{scene}", resolution=[j + 1] * 3, intersector="watertight",
                         name=f"scene{scene} #{j}", ray_set=ray_set, rays=RAYS, **counts, held_back=False,
                         warnings=[],
                         values_ns=[float(v) for v in mu * np.exp(NOISE_REL * rng.standard_normal(N_REPEATS))]))
    return recs


def _design(recs):
    return calfile.design_from_measurements(recs, "in_context", optional=ALL)


@pytest.fixture(scope="module")
def planted():
    recs = _records(0)
    return (recs, *planted_calibration(recs, PRIORS))


def test_the_fit_recovers_a_planted_t_hit(planted):
    _, result, _ = planted
    assert "t_hit_ns" in result.names and "t_hit_skipped" not in result.diagnostics
    assert_planted_recovered(result, TRUTH, ("t_step_ns", "t_int_ns", "t_visit_ns"))
    assert_planted_recovered(result, TRUTH, ("t_hit_ns", "t_setup_ns"), rel=0.15)


def test_an_absent_t_hit_is_left_out_and_the_fit_says_why():
    recs = _records(1, truth=dict(TRUTH, t_hit_ns=0.0))
    result = calfile.fit_in_context(_design(recs), seed=0, priors=PRIORS)
    assert "t_hit_ns" not in result.names
    assert result.diagnostics["t_hit_skipped"].startswith("T_hit not fitted")
    assert result.constants["t_step_ns"]["median"] == pytest.approx(TRUTH["t_step_ns"], rel=0.05)


def test_t_hit_round_trips_and_bad_hit_counts_are_rejected(planted, tmp_path):
    _, result, cal = planted
    path = tmp_path / "cal.json"
    calfile.save(path, cal)
    back = calfile.load(path)
    assert back["constants"]["t_hit_ns"]["median"] == pytest.approx(result.constants["t_hit_ns"]["median"])
    assert "t_hit_ns" in back["samples"]["columns"]
    assert calfile.refit(back, seed=0, optional=("misses", "visits"))["constants"].get("t_hit_ns") is None
    for value, message in ((-1, "whole number of rays"), (2.5, "whole number of rays"),
                           (RAYS + 1, "rays hit but the batch traced only")):
        bad = json.loads(json.dumps(cal))
        bad["measurements"][0]["hits"] = value
        with pytest.raises(ValueError, match=r"measurements\[0\]\.hits: .*" + message):
            calfile.validate(bad)


def test_a_suite_configuration_counts_the_rays_that_hit():
    scene = Scene.builtin("cylinder196")
    o, d = _rays(scene, "isotropic", 3)
    grid = Grid.uniform(scene, (4, 4, 16))
    cfg = _config("c", "in_context", "context", scene.name, "4x4x16", "watertight", grid, o, d, "isotropic")
    t, _ = Grid.uniform(scene, (1, 1, 1)).intersect(o, d)  # another grid, the same first hits
    assert 0 < cfg.hits < cfg.rays
    assert cfg.hits == int(np.isfinite(t).sum())
    assert cfg.record()["hits"] == cfg.hits


def test_the_isolating_cell_suite_gives_the_prior_of_t_hit():
    recs = []
    rng = np.random.default_rng(5)
    for k in (32, 48, 64, 96, 128, 160, 192, 256):
        for aimed in (False, True):
            mu = RAYS * (70.0 + (25.0 if aimed else 0.0)) + RAYS * k * 1.5
            recs.append(dict(kind="isolated", suite="cell", ray_set="aimed" if aimed else "isotropic", rays=RAYS,
                             steps=RAYS, tests=RAYS * k, subgrids=0,
                             values_ns=[float(v) for v in mu * np.exp(0.01 * rng.standard_normal(5))]))
    iso, _ = R._isolated_fit(recs, 0)
    assert iso["t_hit_ns"]["median"] == pytest.approx(25.0, rel=0.1)
    assert iso["t_int_ns"]["median"] == pytest.approx(1.5, rel=0.05)
    assert R._priors(iso)["t_hit_ns"] == (iso["t_hit_ns"]["median"], R.PRIOR_FROM_ISOLATED["t_hit_ns"])


def test_predict_adds_t_hit_for_the_share_of_lines_that_hit():
    plain = dict(t_setup_ns=60.0, t_step_ns=10.0, t_int_ns=1.2, t_sub_ns=60.0)
    hit = dict(plain, t_hit_ns=40.0)
    p0 = predict("sphere", constants=plain, levels="1")
    p1 = predict("sphere", constants=hit, levels="1")
    share = termination_fraction(scene_statistics(Scene.builtin("sphere")))[1]
    assert 0.3 < share < 0.8  # a sphere in its cube: about pi/6 of the lines
    q0, q1 = p0["predicted"], p1["predicted"]
    assert q1["hits_per_ray"] == pytest.approx(share) and q0["hits_per_ray"] == 0.0
    assert q1["ns_per_ray"]["median"] == pytest.approx(q0["ns_per_ray"]["median"] + 40.0 * share, rel=1e-9)
    assert q1["model_cost_per_ray"] == pytest.approx(q0["model_cost_per_ray"] + 40.0 * share, rel=1e-9)
    assert p1["levels"] == p0["levels"]  # the same at every resolution: no plan moves
    for name, d in p1["baselines_detail"].items():  # the baselines priced with the same terms
        if d.get("cost_per_ray") is not None:
            assert d["cost_per_ray"] == pytest.approx(p0["baselines_detail"][name]["cost_per_ray"] + 40.0 * share)
    assert p1["constants"]["t_hit"] == 40.0
    assert resolve_constants(constants=hit).t_hit == 40.0 and resolve_constants(constants=plain).t_hit == 0.0
    # the talk's model (paper fidelity) has no hit cost
    assert predict("sphere", constants=hit, levels="1", fidelity="paper")["predicted"]["hits_per_ray"] == 0.0


def test_the_header_carries_t_hit_and_compiles(planted, tmp_path):
    _, result, cal = planted
    text = exported_header(cal, tmp_path, "GRIDCAL_T_HIT_NS > 0.0")
    assert f"#define GRIDCAL_T_HIT_NS {result.constants['t_hit_ns']['median']!r}" in text

"""A calibration per ray set (``by_rays``): each ray set's in-context batches fitted alone.

Camera rays step through neighbouring cells in lockstep and isotropic rays do not,
so on real hosts a cell step of an isotropic ray costs about twice as much
(docs/calibration.md). These tests plant different constants per ray set in
synthetic timings and check that each set's fit recovers its own, that the file
keeps them, and that predict and export use the set asked for.
"""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import pytest

from calibrate import calfile
from calibrate import fit as F
from calibrate import run
from calibrate.export import export
from calibrate.plots import relative_residuals
from calibrate.predict import load_calibration_constants, predict
from conftest import planted_counts

RAYS = 2048
# Constants of the same order as a measured host's (docs/calibration.md), ns.
TRUTH = {
    "camera": {"t_setup_ns": 36.0, "t_step_ns": 10.0, "t_int_ns": 3.8, "t_sub_ns": 38.0},
    "isotropic": {"t_setup_ns": 55.0, "t_step_ns": 23.0, "t_int_ns": 4.8, "t_sub_ns": 30.0},
}
NOISE_REL = 0.02
N_PER_SET = 30
N_REPEATS = 5
HOLD_EVERY = 5  # every fifth configuration of a set is held back
# As `calibrate run` does, set-up and subgrid entry borrow a prior from the isolating
# suites (their share of a batch is small); here one prior between the two sets' truths.
PRIORS = {"t_setup_ns": (45.0, 0.3), "t_sub_ns": (34.0, 0.3)}


def _records(seed: int) -> list[dict]:
    """In-context records of both ray sets (same count design), values from each set's truth."""
    rng = np.random.default_rng(seed)
    recs = []
    for j in range(N_PER_SET):
        counts = planted_counts(rng, j, RAYS)
        for ray_set, t in TRUTH.items():
            mu = (RAYS * t["t_setup_ns"] + counts["steps"] * t["t_step_ns"] + counts["tests"] * t["t_int_ns"]
                  + counts["subgrids"] * t["t_sub_ns"])
            recs.append(dict(kind="in_context", scene=f"scene{j % 5}", resolution=[j + 1] * 3, intersector="watertight",
                             name=f"scene{j % 5} #{j} {ray_set}", ray_set=ray_set, rays=RAYS, **counts,
                             values_ns=[float(v) for v in mu * np.exp(NOISE_REL * rng.standard_normal(N_REPEATS))],
                             held_back=j % HOLD_EVERY == 0, warnings=[]))
    return recs


@pytest.fixture(scope="module")
def planted():
    recs = _records(0)
    pooled = F.fit(calfile.design_from_measurements(recs, "in_context"), seed=0, priors=PRIORS)
    by_rays, skipped = calfile.fit_by_rays(recs, seed=0, priors=PRIORS)
    cal = calfile.from_fit(pooled, fingerprint={"cpu_model": "Test CPU"}, measurements=recs, meta={},
                           by_rays=by_rays)
    return recs, pooled, by_rays, skipped, cal


def test_each_ray_set_recovers_its_own_planted_constants(planted):
    _, pooled, by_rays, skipped, _ = planted
    assert not skipped and set(by_rays) == {"camera", "isotropic"}
    for ray_set, truth in TRUTH.items():
        c = by_rays[ray_set].constants
        for name in ("t_step_ns", "t_int_ns"):
            assert c[name]["median"] == pytest.approx(truth[name], rel=0.03), (ray_set, name)
        r_true = truth["t_int_ns"] / truth["t_step_ns"]
        assert c["ratio"]["ci95"][0] <= r_true <= c["ratio"]["ci95"][1], ray_set
    # one set of constants for both cannot hold either ratio
    r_pooled = pooled.constants["ratio"]["median"]
    assert not any(abs(r_pooled / (t["t_int_ns"] / t["t_step_ns"]) - 1) < 0.1 for t in TRUTH.values())


def test_held_back_batches_are_predicted_by_their_own_ray_set(planted):
    recs, pooled, by_rays, _, _ = planted
    mare, mare_pooled, per_set = run._holdout(pooled, by_rays, recs)
    assert set(per_set) == {"camera", "isotropic"}
    assert mare < 0.03, "with the planted noise of 2% each set predicts its own batches to a few per cent"
    assert mare_pooled > 3 * mare
    # without per-set fits the file's predictions are the pooled ones
    assert run._holdout(pooled, {}, recs)[0] == pytest.approx(mare_pooled)


def test_by_rays_round_trips_and_is_chosen_by_ray_set(planted, tmp_path):
    *_, cal = planted
    path = calfile.save(tmp_path / "cal.json", cal)
    loaded = calfile.load(path)
    assert loaded == cal
    for ray_set in TRUTH:
        block, fitted_on = calfile.fit_for_rays(loaded, ray_set)
        assert fitted_on == ray_set and block is loaded["by_rays"][ray_set]
        s = calfile.samples_by_name(block)
        assert np.median(s["ratio"]) == pytest.approx(block["constants"]["ratio"]["median"], rel=0.02)
    assert calfile.fit_for_rays(loaded, "isotropic-wide") == (loaded, None)
    assert calfile.fit_for_rays(loaded, None) == (loaded, None)


def test_refit_fits_each_ray_set_again(planted):
    *_, cal = planted
    again = calfile.refit(cal, seed=0)
    assert set(again["by_rays"]) == set(cal["by_rays"])
    for ray_set in TRUTH:
        assert again["by_rays"][ray_set]["constants"] == cal["by_rays"][ray_set]["constants"]


def test_one_ray_set_alone_gives_no_by_rays():
    recs = [r for r in _records(1) if r["ray_set"] == "camera"]
    assert calfile.fit_by_rays(recs, seed=0, priors=PRIORS) == ({}, {})


def test_a_ray_set_that_cannot_be_fitted_alone_is_skipped_with_its_reason():
    recs = _records(2)
    camera = [r for r in recs if r["ray_set"] == "camera"]
    for r in camera[1:]:  # one configuration left: nothing to fit
        r["values_ns"] = []
    fits, skipped = calfile.fit_by_rays(recs, seed=0, priors=PRIORS)
    assert set(fits) == {"isotropic"} and set(skipped) == {"camera"}
    assert skipped["camera"]


def test_predict_uses_the_ray_sets_constants(planted, tmp_path):
    *_, cal = planted
    path = calfile.save(tmp_path / "cal.json", cal)
    seen = set()
    for ray_set in TRUTH:
        k = load_calibration_constants(path, ray_set)
        assert k.fitted_on == ray_set
        assert k.t_step == pytest.approx(cal["by_rays"][ray_set]["constants"]["t_step_ns"]["median"])
        # a single level's optimum depends on r alone
        got = predict("sphere", constants=dict(t_setup_ns=k.t_setup, t_step_ns=k.t_step, t_int_ns=k.t_int,
                                               t_sub_ns=k.t_sub, fitted_on=k.fitted_on),
                      samples={f"{n}_ns": k.samples[n] for n in ("t_setup", "t_step", "t_int", "t_sub")},
                      levels="1", rays=ray_set)
        assert got["levels"][0]["resolution"] == predict("sphere", ratio=k.ratio, levels="1")["levels"][0]["resolution"]
        assert got["constants"]["fitted_on"] == ray_set
        assert any(f"{ray_set} rays alone" in n for n in got["notes"])
        seen.add(tuple(got["levels"][0]["resolution"]))
    assert len(seen) == 2, "camera and isotropic constants recommend different grids here"
    pooled = load_calibration_constants(path)
    assert pooled.fitted_on is None and pooled.t_step == pytest.approx(cal["constants"]["t_step_ns"]["median"])


def test_predict_rejects_a_bad_fitted_on():
    with pytest.raises(ValueError, match="fitted_on must name a ray set"):
        predict("sphere", constants=dict(t_setup_ns=1.0, t_step_ns=1.0, t_int_ns=1.0, fitted_on=3), levels="1")


def _header_ratio(path) -> float:
    return float(re.search(r"#define GRIDCAL_RATIO (\S+)", path.read_text()).group(1))


def test_export_writes_the_ray_sets_constants(planted, tmp_path):
    *_, cal = planted
    path = calfile.save(tmp_path / "cal.json", cal)
    for ray_set in TRUTH:
        out = tmp_path / f"{ray_set}.h"
        result = export(out, calibration=path, rays=ray_set)
        assert result["fitted_on"] == ray_set
        assert _header_ratio(out) == pytest.approx(cal["by_rays"][ray_set]["constants"]["ratio"]["median"], rel=1e-12)
        assert f"constants fitted on: {ray_set} rays alone" in out.read_text()
    plain = copy.deepcopy(cal)
    del plain["by_rays"]
    path2 = calfile.save(tmp_path / "plain.json", plain)
    result = export(tmp_path / "plain.h", calibration=path2, rays="camera")
    assert result["fitted_on"] is None
    assert _header_ratio(tmp_path / "plain.h") == pytest.approx(cal["constants"]["ratio"]["median"], rel=1e-12)
    assert "constants fitted on: all ray sets" in (tmp_path / "plain.h").read_text()


def _mutate(path, value):
    def f(cal):
        obj = cal
        keys = path.split(".")
        for k in keys[:-1]:
            obj = obj[int(k)] if isinstance(obj, list) else obj[k]
        last = int(keys[-1]) if isinstance(obj, list) else keys[-1]
        if value is None:
            del obj[last]
        else:
            obj[last] = value
        return cal
    return f


BAD_BY_RAYS = [
    ("not an object", _mutate("by_rays", [1, 2]), r"by_rays: must be a JSON object, got array"),
    ("entry not an object", _mutate("by_rays.camera", "fast"), r"by_rays\.camera: must be a JSON object, got string"),
    ("missing samples", _mutate("by_rays.camera.samples", None), r"by_rays\.camera: missing key 'samples'"),
    ("unknown key", _mutate("by_rays.camera.measurements", []), r"by_rays\.camera: unknown key 'measurements'"),
    ("ci misses median", _mutate("by_rays.isotropic.constants.t_step_ns.ci95", [1.0, 2.0]),
     r"by_rays\.isotropic\.constants\.t_step_ns\.ci95: interval \[1, 2\] does not contain the median"),
    ("sample not positive", _mutate("by_rays.camera.samples.values.0.1", -1.0),
     r"by_rays\.camera\.samples\.values\[0\]\[1\]: t_step_ns must be positive"),
    ("not converged", _mutate("by_rays.camera.diagnostics.converged", False),
     r"by_rays\.camera\.diagnostics\.converged: is not true"),
    ("empty name", lambda cal: cal["by_rays"].update({"": cal["by_rays"]["camera"]}) or cal,
     r"by_rays: a ray set's name must not be empty"),
]


@pytest.mark.parametrize("label, mutate, message", BAD_BY_RAYS, ids=[b[0] for b in BAD_BY_RAYS])
def test_bad_by_rays_blocks_are_rejected(planted, tmp_path, label, mutate, message):
    *_, cal = planted
    text = calfile.dumps(cal)
    bad = mutate(copy.deepcopy(cal))
    path = tmp_path / "calibration.json"
    path.write_text(__import__("json").dumps(bad))
    with pytest.raises(calfile.UserError, match=message):
        calfile.load(path)
    assert calfile.dumps(cal) == text, "the fixture is untouched"


def test_residuals_are_taken_against_each_ray_sets_fit(planted):
    *_, cal = planted
    recs, sets, rel = relative_residuals(cal)
    assert sorted(set(sets)) == ["camera", "isotropic"] and len(rel) == len(recs) == 2 * N_PER_SET
    assert np.median(np.abs(rel)) < 0.03, "each set's own fit leaves the planted 2% noise"
    pooled = {k: v for k, v in cal.items() if k != "by_rays"}
    assert np.median(np.abs(relative_residuals(pooled)[2])) > 3 * np.median(np.abs(rel))


def test_bench_plans_with_the_fit_it_is_asked_for(planted, tmp_path, capsys):
    """`bench --fit`: the isotropic fit by default (the grids `predict` recommends), another ray set's
    or the pooled fit when asked; the JSON says which."""
    from calibrate.cli import main

    *_, cal = planted
    path = calfile.save(tmp_path / "cal.json", cal)
    grids = {}
    for fit in ("pooled", "isotropic", "camera", None):
        code = main(["bench", "sphere", "--json", "--batch", "64", "--repeats", "1", "--rays", "camera",
                     "--no-trimesh", "--calibration", str(path), "--quiet"] + (["--fit", fit] if fit else []))
        assert code == 0
        out = json.loads(capsys.readouterr().out)
        named = fit or "isotropic"
        assert ("every ray set" in out["constants"]) == (named == "pooled")
        assert (f"{named} rays' fit" in out["constants"]) == (named != "pooled")
        fit = fit or "default"
        grids[fit] = tuple(out["scenes"][0]["grids"]["gridcal-uniform"]["resolution"])
    for fit in ("isotropic", "camera"):
        k = load_calibration_constants(path, fit)
        assert grids[fit] == tuple(predict("sphere", ratio=k.ratio, levels="1")["levels"][0]["resolution"])
    assert grids["isotropic"] != grids["camera"] and grids["default"] == grids["isotropic"]

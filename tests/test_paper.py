"""`calibrate paper`: the exponent fit, the agree/disagree judgments, the JSON report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrate import Scene
from calibrate.cli import main
from calibrate.paper import (CLAIMS, EXPONENT_ABS_TOL, FACTOR_REL_TOL, build_rows, claim_row, fit_exponent, judge,
                             measure_scene)
from calibrate.scenes import cylinder_mesh


@pytest.mark.parametrize("case", range(6))
def test_fit_exponent_recovers_planted_exponent(case):
    rng = np.random.default_rng(case)
    b = rng.uniform(0.4, 1.7)
    c = rng.uniform(0.5, 50.0)
    n = np.geomspace(100, 100_000, 3 + case)
    exact = fit_exponent(n, c * n ** b)
    assert exact["exponent"] == pytest.approx(b, abs=1e-10)
    assert exact["constant"] == pytest.approx(c, rel=1e-8)
    noisy = fit_exponent(n, c * n ** b * np.exp(rng.normal(0.0, 0.02, n.size)))
    assert abs(noisy["exponent"] - b) < 0.05
    assert noisy["stderr"] is not None and noisy["points"] == n.size


def test_fit_exponent_stderr_matches_scatter():
    # residuals +e, -e, +e, -e about an exact line in log-log: known least-squares slope error
    n = np.array([10.0, 100.0, 1000.0, 10000.0])
    e = 0.1
    cells = 3.0 * n ** 0.8 * np.exp(e * np.array([1, -1, -1, 1]))  # symmetric: slope unchanged
    fit = fit_exponent(n, cells)
    assert fit["exponent"] == pytest.approx(0.8, abs=1e-12)
    x = np.log(n)
    expected = math.sqrt(4 * e * e / 2 / ((x - x.mean()) ** 2).sum())
    assert fit["stderr"] == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("n,cells", [([100], [5]), ([10, 10], [1, 2]), ([10, 100], [1, -1]), ([1, 2], [1])])
def test_fit_exponent_rejects_bad_points(n, cells):
    with pytest.raises(ValueError):
        fit_exponent(n, cells)


@pytest.mark.parametrize("key,inside,outside", [
    ("compact-5pct", 0.049, 0.051),
    ("lines-3pct", -0.01, 0.031),
    ("lines-10pct-large", 0.099, 0.101),
    ("linear-slowdown", 1.25 / (1 + FACTOR_REL_TOL) + 1e-9, 1.25 / (1 + FACTOR_REL_TOL) - 1e-3),
    ("linear-slowdown", 2.0 * (1 + FACTOR_REL_TOL) - 1e-9, 2.0 * (1 + FACTOR_REL_TOL) + 1e-3),
    ("two-level-scan", 2.0 * (1 + FACTOR_REL_TOL) - 1e-9, 2.0 / (1 + FACTOR_REL_TOL) - 1e-3),
    ("two-level-196", 1.04, 0.8),
    ("two-level-1996", 1.4, 1.0),
    ("exponent-compact", 7 / 9 + EXPONENT_ABS_TOL - 1e-9, 1.0),
    ("exponent-skinny", 4 / 3 - EXPONENT_ABS_TOL + 1e-9, 1.5),
])
def test_planted_values_are_marked_agree_or_disagree(key, inside, outside):
    assert judge(CLAIMS[key], inside) and not judge(CLAIMS[key], outside)
    agree = claim_row(key, "scene", inside)
    disagree = claim_row(key, "scene", outside)
    assert agree["agree"] is True and agree["note"] == ""
    assert disagree["agree"] is False and disagree["note"].startswith("scene: ")
    assert disagree["claim"] == key and disagree["talk"] and disagree["ours"] == pytest.approx(outside)
    assert claim_row(key, "scene", None)["agree"] is None  # not measured: neither


def _planted_scene(name, law, n, law_ns, best_ns, linear_ns=None, two_ns=None):
    return dict(scene=name, triangles=n, law=law, law_ns=law_ns, best_ns=best_ns, best_measured_ns=best_ns,
                best_cells=1000.0, law_cells=900.0, fit=dict(at_edge=False), linear_ns=linear_ns,
                two_level_best_ns=two_ns)


def test_rows_from_planted_measurements():
    measured = {
        "sphereA": _planted_scene("sphereA", "points", 5000, law_ns=104.0, best_ns=100.0),  # +4%: agree
        "sphereB": _planted_scene("sphereB", "points", 40000, law_ns=110.0, best_ns=100.0, two_ns=50.0),  # +10%, 2x
        "cylinder196": _planted_scene("cylinder196", "lines", 196, law_ns=100.0, best_ns=100.0, linear_ns=130.0,
                                      two_ns=100.0),  # 0%, 1.3x, 1.0x
        "cylinder1996": _planted_scene("cylinder1996", "lines", 1996, law_ns=110.0, best_ns=100.0, linear_ns=110.0,
                                       two_ns=110.0),  # +10%, 1.0x: disagree; 1.0x speed-up: disagree
        "cylinder19996": _planted_scene("cylinder19996", "lines", 19996, law_ns=108.0, best_ns=100.0,
                                        linear_ns=432.0),  # +8% (<= 10%), 4x: disagree
    }
    exponents = dict(compact=dict(label="spheres", exponent=0.8, stderr=0.01, n=[1, 2], cells=[1, 2]),
                     skinny=dict(label="cylinders", exponent=0.5, stderr=0.01, n=[1, 2], cells=[1, 2]))
    rows = {(r["claim"], r["scene"]): r for r in build_rows(measured, exponents)}
    expected = {("compact-5pct", "sphereA"): True, ("compact-5pct", "sphereB"): False,
                ("lines-3pct", "cylinder196"): True, ("lines-3pct", "cylinder1996"): False,
                ("lines-10pct-large", "cylinder19996"): True,
                ("linear-slowdown", "cylinder196"): True, ("linear-slowdown", "cylinder1996"): False,
                ("linear-slowdown", "cylinder19996"): False,
                ("two-level-scan", "sphereB"): True, ("two-level-196", "cylinder196"): True,
                ("two-level-1996", "cylinder1996"): False,
                ("exponent-compact", "spheres"): True, ("exponent-skinny", "cylinders"): False}
    assert {k: r["agree"] for k, r in rows.items()} == expected
    assert rows[("compact-5pct", "sphereB")]["ours"] == pytest.approx(0.10)
    assert rows[("linear-slowdown", "cylinder19996")]["ours"] == pytest.approx(4.0)
    assert rows[("two-level-scan", "sphereB")]["ours"] == pytest.approx(2.0)
    for r in rows.values():
        assert (r["note"] != "") == (r["agree"] is False)


def test_measure_scene_small_cylinder():
    v, f = cylinder_mesh(12)
    scene = Scene(v, f, name="cyl44")
    m = measure_scene(scene, "lines", 1.0, quick=True, linear=True, two_level=True)
    cells = [p["cells"] for p in m["uniform"]]
    assert cells == sorted(cells) and len(set(cells)) == len(cells)
    assert m["law_ns"] is not None and m["linear_ns"] is not None and m["law_ns"] > 0
    assert any("law" in p["labels"] for p in m["uniform"]) and any("O(N)" in p["labels"] for p in m["uniform"])
    assert min(cells) <= m["best_cells"] * (1 + 1e-9) and m["best_cells"] <= max(cells) * (1 + 1e-9)
    assert m["best_measured_ns"] == min(p["median_ns"] for p in m["uniform"])
    assert len(m["two_level"]) == 3 and m["two_level_best_ns"] > 0
    # the counts come from the instrumented twin: at least one cell per ray that meets the box
    assert all(p["steps"] > 0 for p in m["uniform"])


@pytest.mark.slow
def test_quick_run_json(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["paper", "--quick", "--ratio", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("rows", "ratio", "quick", "scenes", "exponents", "load_average", "wall_s", "agree", "disagree"):
        assert key in out
    assert out["quick"] is True and out["ratio"] == 1.0
    claims = {r["claim"] for r in out["rows"]}
    assert claims == set(CLAIMS) - {"lines-10pct-large"}  # quick: no 19,996-triangle cylinder
    for r in out["rows"]:
        assert set(r) >= {"claim", "statement", "scene", "talk", "talk_value", "ours", "ours_text", "agree", "note"}
        assert r["agree"] is judge(CLAIMS[r["claim"]], r["ours"])
        assert (r["note"] != "") == (r["agree"] is False)
    assert out["agree"] + out["disagree"] == len(out["rows"])
    assert not any(s["scene"] == "cylinder19996" for s in out["scenes"])


def test_no_calibration_is_a_user_error(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["paper", "--quick"]) == 2
    assert "no calibration" in capsys.readouterr().err
    assert main(["paper", "--ratio", "-1"]) == 2
    assert "positive" in capsys.readouterr().err

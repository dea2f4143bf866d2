"""calibrate bench: the first-hit agreement check, the exponent fit, the JSON it prints, skips and errors."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from calibrate import Grid, Scene, brute_force
from calibrate.bench import (MIN_AGREEMENT, T_REL_TOL, bench_scene, embree_unavailable, first_hit_agreement,
                             fit_exponent, make_rays, scale_bench, trimesh_unavailable)
from calibrate.cli import main

TINY = dict(batch=256, repeats=2, ray_sets=("isotropic",), trimesh=False)


def _hits(scene, kind="isotropic", n=512, seed=0):
    o, d = make_rays(scene, kind, n, seed=seed)
    t, prim = Grid.uniform(scene, (8, 8, 8)).intersect(o, d)
    return o, d, t, prim


def test_agreement_catches_planted_disagreements():
    scene = Scene.builtin("cylinder196")
    o, d, t, prim = _hits(scene)
    t_ref, prim_ref = brute_force(scene, o, d)
    same = first_hit_agreement(t, prim, t_ref, prim_ref, scene, o, d)
    assert same["agree"] == 1.0 and same["ok"]
    hit = np.flatnonzero(np.isfinite(t_ref))
    assert hit.size >= 3
    t2, prim2 = t.copy(), prim.copy()
    t2[hit[0]], prim2[hit[0]] = np.inf, -1                   # a hit reported as a miss
    t2[hit[1]] *= 1.0 + 100 * T_REL_TOL                        # t off by 1%
    far = (prim2[hit[2]] + scene.n_triangles // 2) % scene.n_triangles
    prim2[hit[2]] = far                                        # a triangle the ray does not meet there
    got = first_hit_agreement(t2, prim2, t_ref, prim_ref, scene, o, d)
    assert (got["hit_miss"], got["t_differs"], got["triangle_differs"]) == (1, 1, 1)
    assert got["agree"] == pytest.approx(1.0 - 3.0 / t.size)
    assert got["ok"] == (got["agree"] >= MIN_AGREEMENT)
    assert not got["ok"]  # 3 of 512 is 0.6%: more than the 0.1% allowed


def test_agreement_counts_a_shared_edge_as_a_tie():
    # two triangles sharing the diagonal of the unit square; the ray hits that edge at t = 1
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    scene = Scene(v, np.array([[0, 1, 2], [0, 2, 3]]))
    o, d = np.array([[0.5, 0.5, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    got = first_hit_agreement(np.array([1.0]), np.array([0]), np.array([1.0]), np.array([1]), scene, o, d)
    assert got["ties"] == 1 and got["agree"] == 1.0
    # off the edge only one triangle is met: a different id is a disagreement
    o = np.array([[0.8, 0.2, 1.0]])
    got = first_hit_agreement(np.array([1.0]), np.array([1]), np.array([1.0]), np.array([0]), scene, o, d)
    assert got["ties"] == 0 and got["triangle_differs"] == 1 and got["agree"] == 0.0


@pytest.mark.parametrize("case", range(3))
def test_exponent_fit_recovers_a_planted_exponent(case):
    rng = np.random.default_rng(case)
    b, a = rng.uniform(-1.0, 2.0), rng.uniform(0.1, 10.0)
    x = np.logspace(3, 6.7, 6)
    y = a * x ** b * np.exp(rng.normal(0.0, 0.01, x.size))
    fit = fit_exponent(x, y)
    assert fit["exponent"] == pytest.approx(b, abs=0.02)
    assert fit["prefactor"] == pytest.approx(a, rel=0.2)
    assert fit["r2"] > 0.99 or abs(b) < 0.05


@pytest.mark.parametrize("x, y", [([1.0], [2.0]), ([1.0, 2.0], [1.0, -1.0]), ([2.0, 2.0], [1.0, 3.0]),
                                  ([1.0, 2.0], [1.0])])
def test_exponent_fit_rejects_bad_input(x, y):
    with pytest.raises(ValueError):
        fit_exponent(x, y)


def test_json_fields_for_a_small_scene(capsys):
    code = main(["bench", "cylinder196", "--json", "--batch", "256", "--repeats", "3", "--rays", "camera",
                 "--no-trimesh", "--ratio", "1"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kernel_isa"] in ("avx2", "sse2", "scalar")
    (s,) = out["scenes"]
    assert s["scene"] == "cylinder196" and s["triangles"] == 196
    assert set(s["ray_sets"]) == {"camera"}
    rates = s["ray_sets"]["camera"]["rates"]
    for name in ("gridcal-uniform", "gridcal-nested"):
        assert s["mrays_per_s"][name] == pytest.approx(rates[name]["mrays_per_s"])  # one ray set
        assert rates[name]["min"] <= rates[name]["mrays_per_s"] <= rates[name]["max"]
        assert s["grids"][name]["references"] > 0
    if embree_unavailable() is None:
        e = rates["embree"]
        for name in ("gridcal-uniform", "gridcal-nested"):
            r, g = s["ratio_vs_embree"][name], rates[name]
            assert r == pytest.approx(s["ray_sets"]["camera"]["ratio_vs_embree"][name])
            assert g["min"] / e["max"] * (1 - 1e-12) <= r <= g["max"] / e["min"] * (1 + 1e-12)
            lo, hi = s["ratio_vs_embree_ci95"][name]
            assert lo <= r <= hi
            assert s["ray_sets"]["camera"]["ratio_vs_embree_ci95"][name] == pytest.approx([lo, hi])
    else:
        assert "embree" in s["skipped"] and s["ratio_vs_embree"] == {}


def test_embree_agrees_with_gridcal_on_first_hits():
    reason = embree_unavailable()
    if reason:
        pytest.skip(reason)
    r = bench_scene(Scene.builtin("cylinder196"), ratio=1.0, **dict(TINY, ray_sets=("isotropic", "camera")))
    for rs in r["ray_sets"].values():
        a = rs["agreement"]["embree"]
        assert a["rays"] == 256 and a["agree"] >= MIN_AGREEMENT
    assert r["agreement_ok"]


def test_trimesh_agrees_with_gridcal_on_first_hits():
    reason = trimesh_unavailable()
    if reason:
        pytest.skip(reason)
    r = bench_scene(Scene.builtin("cylinder196"), ratio=1.0, **dict(TINY, trimesh=True))
    assert r["ray_sets"]["isotropic"]["agreement"]["trimesh"]["agree"] >= MIN_AGREEMENT
    assert r["mrays_per_s"]["trimesh"] > 0


def test_skip_reasons_when_embreex_and_rtree_are_absent(monkeypatch):
    for mod in ("embreex", "embreex.rtcore_scene", "embreex.mesh_construction", "rtree"):
        monkeypatch.setitem(sys.modules, mod, None)  # import of these now raises ImportError
    assert "embreex" in embree_unavailable()
    assert "rtree" in trimesh_unavailable()
    r = bench_scene(Scene.builtin("cylinder196"), ratio=1.0, **dict(TINY, trimesh=True))
    assert "embreex" in r["skipped"]["embree"] and "rtree" in r["skipped"]["trimesh"]
    assert set(r["mrays_per_s"]) == {"gridcal-uniform", "gridcal-nested"}
    assert r["ratio_vs_embree"] == {}


def test_scale_rows_and_exponents():
    r = scale_bench(max_triangles=2_000, sizes=(200, 800), ratio=1.0, batch=128, repeats=1)
    rows = r["rows"]
    assert [row["triangles"] for row in rows] == [180, 720, 2000]  # 20 f^2 nearest each target
    for row in rows:
        assert row["references"] >= row["triangles"] and row["memory_bytes"] > 0 and row["mrays_per_s"] > 0
    ours = {"build_s", "predict_s", "references", "memory_bytes", "ns_per_ray"}
    theirs = set() if embree_unavailable() else {"embree_ns_per_ray", "embree_build_s"}
    assert set(r["exponents"]) == ours | theirs
    assert all(row["nested"]["levels"] >= 1 for row in rows)  # below the nested cap every row has one
    refs = fit_exponent([row["triangles"] for row in rows], [row["references"] for row in rows])
    assert r["exponents"]["references"]["exponent"] == pytest.approx(refs["exponent"])


@pytest.mark.parametrize("argv, words", [
    (["bench", "--batch", "0"], "--batch"),
    (["bench", "--rays", "sideways"], "sideways"),
    (["bench", "no-such-scene"], "no-such-scene"),
    (["bench", "--scale", "--max-triangles", "1500.5"], "whole number"),
    (["bench", "--ratio", "-1"], "ratio"),
    (["bench", "--clock", "sundial"], "sundial"),
])
def test_bad_input_is_one_line_and_exit_2(argv, words, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("calibrate: error:") and words in err and "\n" not in err


@pytest.mark.parametrize("name", ["room"])  # its auto plan has 2 levels
def test_recommended_grid_is_what_predict_recommends(name):
    from calibrate.predict import predict, recommended_grid

    scene = Scene.builtin(name)
    for levels in ("1", "auto"):
        p = predict(scene, ratio=1.0, levels=levels)
        grid, plan = recommended_grid(scene, ratio=1.0, levels=levels)
        assert plan["levels"] == len(p["levels"]) == grid.info["levels"]
        assert plan["resolution"] == p["levels"][0]["resolution"] == list(grid.resolution)


def test_thread_clock_leaves_out_waiting_and_wall_clock_does_not():
    import time

    from calibrate.bench import interleaved

    calls = {"waits": lambda: time.sleep(0.02)}
    wall = interleaved(calls, repeats=2, warmups=0, clock="wall")["waits"]
    thread = interleaved(calls, repeats=2, warmups=0, clock="thread")["waits"]
    assert min(wall) >= 20_000_000 and max(thread) < 10_000_000
    with pytest.raises(ValueError, match="clock"):
        interleaved(calls, repeats=1, clock="sundial")


def test_ratio_interval_holds_a_planted_ratio_and_widens_with_noise():
    """Two ray sets whose contender runs at 0.5 and 0.8 of Embree, times drawn with 2% and
    20% noise over 15 paired rounds: the combined ratio (weights 1 and 3: 0.5 and 0.8
    combined as 4 / (1 / 0.5 + 3 / 0.8) = 0.696) lies in the interval, which is narrow at 2%
    and several times wider at 20%."""
    from calibrate.bench import ratio_interval

    truth = 4.0 / (1.0 / 0.5 + 3.0 / 0.8)
    widths = []
    for noise in (0.02, 0.20):
        rng = np.random.default_rng(11)
        rounds = []
        for weight, ratio in ((1.0, 0.5), (3.0, 0.8)):
            e = 100.0 * np.exp(noise * rng.standard_normal(15))
            c = 100.0 / ratio * np.exp(noise * rng.standard_normal(15))
            rounds.append((weight, e, c))
        lo, hi = ratio_interval(rounds)
        assert lo < truth < hi
        widths.append(hi - lo)
    assert widths[0] < 0.05 and widths[1] > 4 * widths[0]

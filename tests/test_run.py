"""`calibrate run` end to end on a small suite: the calibration file, interruption and resume.

The suites are shrunk (one small scene, few rays, 2 ms values) so a run takes
seconds; the timings are real, so only the shape of the output is asserted,
never a speed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibrate import calfile, run, suites
from calibrate._io import UserError
from calibrate.cli import main
from calibrate.protocol import Copies, MeasurementInterrupted
from models.memory import lines_beyond_cache


@pytest.fixture
def small_suite(monkeypatch):
    monkeypatch.setattr(suites, "RAYS_PER_BATCH", 256)
    monkeypatch.setattr(suites, "CONTEXT_RAYS_PER_BATCH", 320)
    monkeypatch.setattr(suites, "EMPTY_GRID_SIDES", (1, 12, 16, 20, 24, 28, 32))
    monkeypatch.setattr(suites, "CELL_TRIANGLE_COUNTS", (1, 32, 64, 128))
    monkeypatch.setattr(suites, "SUBGRID_SIDES", (2, 4, 8))
    monkeypatch.setattr(suites, "CONTEXT_SCENES", ("cylinder196", "scattered-skinny"))
    monkeypatch.setattr(suites, "CONTEXT_CELLS_PER_TRIANGLE", suites.COARSE_CONTEXT_CELLS_PER_TRIANGLE)
    monkeypatch.setattr(suites, "CONTEXT_SKINNY_EXTRA", suites.COARSE_CONTEXT_SKINNY_EXTRA)
    monkeypatch.setattr(run, "MIN_VALUE_NS", 2_000_000)
    monkeypatch.setattr(run, "FIRST_ROUNDS", 4)


def _interrupt_after(n_values: int):
    seen = {"n": 0}

    def progress(done, total, label):
        if total and not label.startswith("warm-up"):
            seen["n"] += 1
            if seen["n"] >= n_values:
                raise KeyboardInterrupt

    return progress


def test_in_context_grids_are_timed_on_copies(small_suite, monkeypatch):
    """Each in-context configuration times CONTEXT_COPIES separate builds of its grid in
    turn (equal in every count and byte total, the same first hits), counted once."""
    from calibrate._grid import Grid

    timed, original = [], Grid.timed_batch

    def tracked(self, *a, **kw):
        timed.append((id(self), self.info))
        return original(self, *a, **kw)

    monkeypatch.setattr(Grid, "timed_batch", tracked)
    k = suites.CONTEXT_COPIES
    configs = suites.context_configs("watertight", 0, scenes=("cylinder196",))
    assert configs and k > 1 and len(timed) == k * len(configs)
    for j, c in enumerate(configs):
        assert isinstance(c.run, Copies) and len(c.run.runs) == k
        group = timed[j * k:(j + 1) * k]
        assert len({i for i, _ in group}) == k  # separate grids
        assert all(info == group[0][1] for _, info in group), c.name
        assert group[0][1]["memory_bytes"] == c.memory_bytes
        assert len({r(1)[1] for r in c.run.runs}) == 1  # the same checksum of first hits
    single = suites.context_configs("watertight", 0, scenes=("cylinder196",), copies=1)
    assert [c.record() for c in single] == [c.record() for c in configs]
    assert not any(isinstance(c.run, Copies) for c in single)
    with pytest.raises(ValueError, match="copies"):
        suites.context_configs("watertight", 0, scenes=("cylinder196",), copies=0)


@pytest.mark.parametrize("name", suites.BARE_CONTEXT_SCENES)
def test_padded_scenes_add_empty_space_and_steps_apart_from_visits(name, monkeypatch):
    """Each in-context scene padded is the built-in scene, unchanged, in a box PADDED_SCALE
    times its own about the same centre; the suite times it with uniform grids only, and a
    grid of as many cells per triangle steps through more cells per occupied cell entered
    than the bare scene's (what separates T_step from T_visit)."""
    from calibrate._grid import Grid, Scene, resolution_for_cells

    padded_name = name + suites.PADDED_SUFFIX
    assert padded_name in suites.CONTEXT_SCENES and name in suites.CONTEXT_SCENES
    bare, padded = Scene.builtin(name), suites.context_scene(padded_name)
    assert padded.name == padded_name and padded.n_triangles == bare.n_triangles + 2
    np.testing.assert_array_equal(padded.vertices[: len(bare.vertices)], bare.vertices)
    np.testing.assert_array_equal(padded.faces[: bare.n_triangles], bare.faces)
    centre, half = 0.5 * (bare.box_lo + bare.box_hi), 0.5 * (bare.box_hi - bare.box_lo)
    atol = 1e-12 * float(np.abs(bare.box_hi - bare.box_lo).max())
    np.testing.assert_allclose(padded.box_lo, centre - suites.PADDED_SCALE * half, rtol=0, atol=atol)
    np.testing.assert_allclose(padded.box_hi, centre + suites.PADDED_SCALE * half, rtol=0, atol=atol)
    ratios = {}
    for scene in (bare, padded):
        o, d = suites._rays(scene, "isotropic", 5)
        o, d = o[:2048], d[:2048]
        res = resolution_for_cells(scene.n_triangles, scene.box_hi - scene.box_lo)
        steps, _, _, visits = Grid.uniform(scene, res).count(o, d, visits=True)
        ratios[scene.name] = steps.sum() / max(int(visits.sum()), 1)
    assert ratios[padded_name] > 1.5 * ratios[name], ratios
    monkeypatch.setattr(suites, "CONTEXT_CELLS_PER_TRIANGLE", (1 / 8, 1 / 4))
    monkeypatch.setattr(suites, "CONTEXT_SKINNY_EXTRA", ())
    monkeypatch.setattr(suites, "CONTEXT_RAYS_PER_BATCH", 64)
    configs = suites.context_configs("watertight", 0, scenes=(padded_name,), copies=1)
    assert len(configs) == 2 * len(suites.CONTEXT_RAY_SETS)
    assert all(c.scene == padded_name and c.subgrids == 0 and "L" not in c.resolution for c in configs)
    bare_configs = suites.context_configs("watertight", 0, scenes=(name,), copies=1)
    assert len(bare_configs) == (2 + len(suites.CONTEXT_LEVELS)) * len(suites.CONTEXT_RAY_SETS)


def test_padded_scene_refuses_a_box_smaller_than_the_scene():
    for bad in (0.5, float("nan"), float("inf"), "2", True):
        with pytest.raises(ValueError, match="scale"):
            suites.padded_scene("cylinder196", bad)


def test_run_writes_a_valid_calibration(small_suite, tmp_path):
    out = tmp_path / "cal.json"
    result = run.run_calibration(out, budget_s=120, target_rel_width=None, seed=3)
    cal = calfile.load(out)
    for key in ("t_setup_ns", "t_step_ns", "t_int_ns", "ratio"):
        est = cal["constants"][key]
        assert est["ci95"][0] <= est["median"] <= est["ci95"][1]
    assert cal["diagnostics"]["converged"] is True
    kinds = {m["kind"] for m in cal["measurements"]}
    assert kinds == {"isolated", "in_context"}
    held = [m for m in cal["measurements"] if m["held_back"]]
    assert held and all(m["kind"] == "in_context" for m in held)
    assert np.isfinite(result.holdout_mare) and result.holdout_mare >= 0
    # each ray set is fitted alone, or the file says why not
    fitted, skipped = set(cal.get("by_rays", {})), set(cal["meta"].get("by_rays_skipped", {}))
    assert fitted | skipped == {"isotropic", "camera"} and not fitted & skipped
    assert set(cal["meta"]["holdout_mare_by_rays"]) <= fitted
    # every in-context configuration is also predicted by a fit to the other folds
    assert cal["meta"]["cv_folds"] == run.CV_FOLDS and 0 <= cal["meta"]["cv_mare"] == result.cv_mare
    assert set(cal["meta"]["cv_mare_by_rays"]) == fitted
    # every in-context record carries its grid's bytes and its lines beyond the cache
    ctx = [m for m in cal["measurements"] if m["kind"] == "in_context"]
    assert all(m["memory_bytes"] > 0 and m["misses"] >= 0 for m in ctx)
    # and its walks' occupancy changes, recorded for analysis (not a term of the fit)
    assert all(0 <= m["changes"] <= m["steps"] for m in cal["measurements"]) and sum(m["changes"] for m in ctx) > 0
    assert cal["meta"]["cache_bytes"] > 0
    # the cache the memory effect is counted against: one of the sizes tried, the largest of
    # those scored within CACHE_SCORE_MARGIN of the best (run.select_cache)
    tried = cal["meta"]["cache_candidates"]
    assert cal["meta"]["cache_bytes"] in tried and tried == sorted(tried)
    if len(tried) > 1:
        scores = {int(k): v for k, v in cal["meta"]["cache_scores"].items() if v is not None}
        best = max(scores.values())
        assert cal["meta"]["cache_bytes"] == max(c for c, v in scores.items() if v >= best - run.CACHE_SCORE_MARGIN)
    # the in-context batches are long streams of distinct rays, the isolating ones short
    assert {m["rays"] for m in ctx if m["ray_set"] == "isotropic"} == {suites.CONTEXT_RAYS_PER_BATCH}
    assert {m["rays"] for m in cal["measurements"] if m["kind"] == "isolated"} == {suites.RAYS_PER_BATCH}
    assert cal["meta"]["context_rays_per_batch"] == suites.CONTEXT_RAYS_PER_BATCH
    for ray_set in fitted:
        assert cal["by_rays"][ray_set]["diagnostics"]["converged"] is True
    assert not run.partial_path(out).exists(), "a finished run leaves no partial file"
    # every series keeps its values as timed and when; what the fits read is those over the host's
    # common slowdown, which the file's raw values and stamps give again
    timed = [m for m in cal["measurements"] if m["values_ns"]]
    assert timed and all(len(m["raw_values_ns"]) == len(m["stamps_s"]) == len(m["values_ns"]) for m in timed)
    stamps = sorted(t for m in timed for t in m["stamps_s"])
    assert len(set(stamps)) == len(stamps)
    again_values = calfile.apply_drift(json.loads(json.dumps(cal))["measurements"])
    flat = lambda recs: [v for m in recs for v in m["values_ns"]]
    assert flat(again_values) == pytest.approx(flat(cal["measurements"]))
    assert any(m["values_ns"] != m["raw_values_ns"] for m in timed)
    # the stored measurements re-fit without measuring again
    again = calfile.refit(cal, seed=3)
    assert again["constants"]["ratio"]["median"] > 0
    # `calibrate fit` re-fits the isolating suites too and reports the new fit's errors, not the stored ones
    stale = json.loads(json.dumps(cal))
    stale["meta"].update(holdout_mare=0.999, cv_mare=0.999)
    stale["isolated"] = {}
    for m in stale["measurements"]:  # values_ns are derived: a re-fit derives them again
        m["values_ns"] = [1.0] * len(m["values_ns"])
        if m["kind"] == "in_context":  # and so are the misses, by this version's memory model
            m["misses"] = 0.0
    new, warnings = run.refit_calibration(stale, seed=3)
    assert flat(new["measurements"]) == pytest.approx(flat(cal["measurements"]))
    cache = calfile.cache_bytes_of(cal)
    assert [m["misses"] for m in new["measurements"] if m["kind"] == "in_context"] == pytest.approx(
        [m["misses"] for m in cal["measurements"] if m["kind"] == "in_context"])
    assert all(m["misses"] == pytest.approx(float(lines_beyond_cache(m["steps"], m["tests"], m["memory_bytes"], cache,
                                                                      m["visits"] + m["changes"])))
               for m in new["measurements"] if m["kind"] == "in_context")
    assert new["meta"]["holdout_mare"] == pytest.approx(cal["meta"]["holdout_mare"], rel=0.5, abs=0.02)
    assert new["meta"]["cv_mare"] == pytest.approx(cal["meta"]["cv_mare"], rel=0.5, abs=0.02)
    assert set(new["isolated"]) == set(cal["isolated"])
    assert all(isinstance(w, str) for w in warnings)
    # a file without isolating measurements keeps the priors it was fitted with
    bare = json.loads(json.dumps(cal))
    bare["measurements"] = [m for m in bare["measurements"] if m["kind"] == "in_context"]
    new, _ = run.refit_calibration(bare, seed=3)
    assert new["diagnostics"]["priors"] == cal["diagnostics"]["priors"]
    assert new["isolated"] == cal["isolated"]


def test_interrupted_run_resumes_to_the_same_kind_of_data(small_suite, tmp_path):
    out = tmp_path / "cal.json"
    with pytest.raises(MeasurementInterrupted):
        run.run_calibration(out, budget_s=120, target_rel_width=None, seed=5, progress=_interrupt_after(40))
    part = run.partial_path(out)
    assert part.exists() and not out.exists(), "an interrupted run keeps its values and writes no calibration"
    saved = json.loads(part.read_text())
    n_values = sum(len(m["values_ns"]) for m in saved["measurements"].values())
    assert 0 < n_values <= 40, n_values

    run.run_calibration(out, budget_s=120, target_rel_width=None, seed=5, resume=True)
    resumed = calfile.load(out)
    fresh_out = tmp_path / "fresh.json"
    run.run_calibration(fresh_out, budget_s=120, target_rel_width=None, seed=5)
    fresh = calfile.load(fresh_out)

    def shape(cal):
        return sorted((m["name"], m["kind"], m["rays"], m["steps"], m["tests"], m["subgrids"], m["held_back"],
                       len(m["values_ns"]) >= run.FIRST_ROUNDS) for m in cal["measurements"])

    assert shape(resumed) == shape(fresh)
    assert not part.exists()


def test_resume_without_a_partial_file_is_a_clear_error(small_suite, tmp_path, capsys):
    code = main(["run", "--resume", "--quiet", "--out", str(tmp_path / "cal.json")])
    err = capsys.readouterr().err
    assert code == 2 and "no interrupted run to resume" in err and "Traceback" not in err


@pytest.mark.parametrize("argv,needle", [
    (["run", "--budget", "0"], "positive"),
    (["run", "--budget", "abc"], "must be a number"),
    (["run", "--target-rel-width", "-1"], "positive"),
    (["run", "--intersector", "nope"], "invalid choice"),
    (["fit", "missing.json"], "missing.json"),
    (["show", "missing.json"], "missing.json"),
    (["frobnicate"], "invalid choice"),
])
def test_cli_user_mistakes_are_one_line(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err
    assert err.count("\n") == 1 and err.startswith("calibrate: error:"), err


def test_run_json_and_show(small_suite, tmp_path, capsys):
    out = tmp_path / "cal.json"
    code = main(["run", "--json", "--quiet", "--budget", "120", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    printed = json.loads(captured.out)
    for key in ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "ratio"):
        assert key in printed["constants"]
    assert printed["wall_s"] > 0
    assert printed["cache_bytes"] == calfile.load(out)["meta"]["cache_bytes"] > 0
    # the run's warnings are in the JSON and, as without --json, on stderr
    assert isinstance(printed["warnings"], list) and all(isinstance(w, str) for w in printed["warnings"])
    err = " ".join(captured.err.split())
    for w in printed["warnings"][:10]:
        assert " ".join(w.split())[:60] in err, (w, captured.err)
    assert main(["show", str(out), "--json", "--plot", str(tmp_path / "fig")]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["constants"] == calfile.load(out)["constants"]
    assert [Path(p).name for p in shown["plots"]] == ["fig-corner.png", "fig-residuals.png", "fig-isolated.png"]
    for p in shown["plots"]:
        assert Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_run_summary_says_the_cache_and_the_sizes_close_to_it():
    """The closing summary's cache line: the size, and the sizes within ten log units of the best
    score (so a user sees when the choice was close); or how a size given by hand was set."""
    from calibrate.cli import _cache_line

    mib = 1 << 20
    meta = dict(cache_bytes=8 * mib, cache_scores={str(4 * mib): 353.2, str(8 * mib): 370.3,
                                                  str(16 * mib): 368.3, str(32 * mib): None})
    line = _cache_line(meta)
    assert line.startswith("memory term counted against a 8 MiB cache, chosen by the fit among 4 sizes"), line
    assert "8 MiB +0.0, 16 MiB -2.0)" in line and "4 MiB" not in line, line
    line = _cache_line(dict(cache_bytes=16 * mib, cache_source="set by `calibrate run --cache` (16777216 bytes)"))
    assert line == "memory term counted against a 16 MiB cache: set by `calibrate run --cache` (16777216 bytes)"


def _planted_isolated_records(sub_diffs, t_setup=50.0, t_step=10.0, seed=0, transient=0.0):
    """Isolating-suite records with planted times: empty grids (about 1.5 side steps a ray; a
    walk of fewer than 10 steps costs ``transient`` ns more, as short walks do), subgrid pairs given."""
    rng = np.random.default_rng(seed)
    recs = []
    for side in (1, 2, 4, 8, 12, 16, 20, 24, 28):
        rays, steps = 2048, int(2048 * 1.5 * side)
        t = rays * t_setup + steps * t_step + (rays * transient if steps < 10 * rays else 0.0)
        recs.append(dict(kind="isolated", suite="empty", rays=rays, steps=steps, tests=0, subgrids=0,
                         values_ns=list(t * (1 + 0.002 * rng.standard_normal(5)))))
    for side, diff in zip((2, 4, 8, 16), sub_diffs, strict=True):
        subs = 2000 * side
        none = 1e6
        recs.append(dict(kind="isolated", suite="subgrid", resolution=f"{side}x{side}x{side}", rays=2048,
                         steps=subs, tests=0, subgrids=0, values_ns=[none] * 5))
        recs.append(dict(kind="isolated", suite="subgrid", resolution=f"{side}x{side}x{side} / 1x1x1",
                         rays=2048, steps=2 * subs, tests=0, subgrids=subs,
                         values_ns=[none + subs * (diff + t_step)] * 5))
    return recs


def _planted_cell_records(t_int=2.0, per_ray=60.0, aimed_extra=25.0, short_list_extra=0.0, seed=5,
                          counts=(1, 16, 32, 64, 128, 256)):
    """One-cell records: rays that miss and rays aimed at a triangle (``aimed_extra`` ns more a
    ray), k tests a ray; a list shorter than 32 costs ``short_list_extra`` ns a test more."""
    rng = np.random.default_rng(seed)
    recs = []
    for k in counts:
        for ray_set, extra in (("isotropic", 0.0), ("aimed", aimed_extra)):
            rays = 2048
            t = rays * (per_ray + extra) + rays * k * (t_int + (short_list_extra if k < 32 else 0.0))
            recs.append(dict(kind="isolated", suite="cell", rays=rays, steps=rays, tests=rays * k, subgrids=0,
                             ray_set=ray_set, values_ns=list(t * (1 + 0.01 * rng.standard_normal(5)))))
    return recs


def test_isolated_ratio_is_the_ratio_of_the_two_posteriors():
    """r from the empty-grid and one-cell suites: planted T_step = 10 and T_int = 2 ns are
    recovered, and the 95% interval is that of the ratio of the two posteriors, inside the
    product of the two intervals' ends (which is wider than 95%)."""
    recs = _planted_isolated_records([30.0, 40.0, 50.0, 60.0]) + _planted_cell_records()
    iso, warning = run._isolated_fit(recs, seed=0)
    assert warning is None
    r = iso["ratio"]
    assert r["median"] == pytest.approx(0.2, rel=0.03)
    assert r["ci95"][0] < 0.2 < r["ci95"][1]
    assert r["ci68"][0] > r["ci95"][0] and r["ci68"][1] < r["ci95"][1]
    lo = iso["t_int_ns"]["ci95"][0] / iso["t_step_ns"]["ci95"][1]
    hi = iso["t_int_ns"]["ci95"][1] / iso["t_step_ns"]["ci95"][0]
    assert lo < r["ci95"][0] and r["ci95"][1] < hi


def test_isolated_constants_are_the_steady_states_marginal_costs():
    """Short walks and short lists cost more per step and test (planted: 30 ns a ray on walks of
    fewer than 10 steps, 1 ns a test on lists of fewer than 32), and aimed rays 25 ns more a ray:
    the isolated fit recovers the planted marginal costs (T_step 10, T_int 2, r 0.2) within 2%,
    with r's 95% interval covering 0.2 and narrower than 10% either side. Fitted through every
    configuration with one intercept, as before, T_step came out 8.8 [8.1, 9.6] (the truth outside
    its interval), T_setup 82 and r 0.222 [0.190, 0.260]."""
    recs = (_planted_isolated_records([30.0, 40.0, 50.0, 60.0], transient=30.0)
            + _planted_cell_records(short_list_extra=1.0))
    iso, warning = run._isolated_fit(recs, seed=0)
    assert warning is None
    assert iso["t_step_ns"]["median"] == pytest.approx(10.0, rel=0.02)
    assert iso["t_setup_ns"]["median"] == pytest.approx(50.0, rel=0.05)
    assert iso["t_int_ns"]["median"] == pytest.approx(2.0, rel=0.02)
    r = iso["ratio"]
    assert r["ci95"][0] < 0.2 < r["ci95"][1]
    assert r["ci95"][1] - r["ci95"][0] < 0.2 * r["median"]


def test_isolated_plot_draws_the_suites_and_copes_without_them(tmp_path):
    from calibrate import plots

    recs = _planted_isolated_records([30.0, 40.0, 50.0, 60.0]) + _planted_cell_records()
    iso, _ = run._isolated_fit(recs, seed=0)
    for name, cal in (("with", dict(measurements=recs, isolated=iso)),
                      ("without", dict(measurements=[], isolated={}))):
        out = plots.isolated(cal, tmp_path / f"{name}.png")
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_cell_suite_whose_steady_line_meets_zero_below_zero_falls_back_and_says_so():
    """Moller-Trumbore-like timings: a test costs 15 ns in short lists and up to 17 in long
    ones, aimed rays cost no more than missing ones, so the line through the long lists has
    a negative per-ray cost and no aimed-ray constant; the fit falls back to every list with
    one per-ray cost, says so, and T_int lies within the planted per-test costs."""
    rng = np.random.default_rng(7)
    recs = []
    for k in (1, 16, 32, 64, 128, 256):
        for ray_set in ("isotropic", "aimed"):
            t = 2048 * (60.0 + k * (15.0 + 2.0 * k / 256))
            recs.append(dict(kind="isolated", suite="cell", rays=2048, steps=2048, tests=2048 * k, subgrids=0,
                             ray_set=ray_set, values_ns=list(t * (1 + 0.005 * rng.standard_normal(5)))))
    res, note = run.fit_cell_suite(recs, seed=0)
    assert 15.0 < res.constants["t_int_ns"]["median"] < 17.0
    assert "cell suite fitted on every list, one per-ray cost" in note
    assert "lists of 32+ triangles, aimed rays apart" in note
    # the watertight-like planted suite fits its steady state at once
    res, note = run.fit_cell_suite(_planted_cell_records(short_list_extra=1.0), seed=0)
    assert note is None and res.constants["t_int_ns"]["median"] == pytest.approx(2.0, rel=0.02)


def test_too_few_steady_configurations_fit_the_longest_and_say_so():
    recs = _planted_isolated_records([30.0, 40.0, 50.0, 60.0])
    recs = [r for r in recs if r["suite"] != "empty" or r["steps"] < 20 * r["rays"]]  # longest walk: 18 steps
    recs += _planted_cell_records(counts=(1, 4, 8, 16, 32))  # two lists of 32: one hit, one miss
    iso, warning = run._isolated_fit(recs, seed=0)
    assert "t_step_ns" in iso and "t_int_ns" in iso
    assert "empty suite: 2 configurations reach 10 steps a ray" in warning
    assert "cell suite: 2 configurations reach 32 tests a ray" in warning


def test_isolated_subgrid_cost_is_the_median_of_the_paired_differences():
    iso, warning = run._isolated_fit(_planted_isolated_records([30.0, 40.0, 50.0, 60.0]), seed=0)
    assert iso["t_step_ns"]["median"] == pytest.approx(10.0, rel=0.02)
    assert iso["t_sub_ns"]["median"] == pytest.approx(45.0, rel=0.05)
    assert "subgrid" not in (warning or "")


def test_one_noisy_subgrid_pair_does_not_lose_the_estimate():
    # a busy host: one pair shows no cost beyond a cell step
    iso, warning = run._isolated_fit(_planted_isolated_records([-5.0, 40.0, 50.0, 60.0]), seed=0)
    assert iso["t_sub_ns"]["median"] == pytest.approx(45.0, rel=0.05)
    assert iso["t_sub_ns"]["ci95"][0] == 0.0
    assert "1 of 4 paired differences" in warning


def test_subgrids_that_cost_nothing_give_no_estimate_and_say_so():
    iso, warning = run._isolated_fit(_planted_isolated_records([-5.0, -4.0, 1.0, -2.0]), seed=0)
    assert "t_sub_ns" not in iso
    assert "costs no more than a cell step" in warning


def fake_time(clock: dict, cpu=lambda c: c["t"]):
    """A stand-in for calibrate.run's time module: the wall clock is clock["t"], the run's
    thread clock cpu(clock) (the same: a quiet host)."""

    class FakeTime:
        @staticmethod
        def monotonic():
            return clock["t"]

        @staticmethod
        def thread_time():
            return cpu(clock)

    return FakeTime


def test_a_failed_last_stage_keeps_the_last_fit_that_worked(small_suite, tmp_path, monkeypatch):
    """The budget ends on a stage whose fit fails: the run keeps the previous stage's fit and data."""
    from calibrate.protocol import Measurement

    configs = suites.isolated_configs("watertight", 0) + suites.context_configs("watertight", 0)
    planted = {"rays": 50.0, "steps": 10.0, "tests": 4.0, "subgrids": 30.0}
    truth = {c.name: sum(planted[k] * c.record()[k] for k in planted) for c in configs}
    rng = np.random.default_rng(0)
    clock = {"t": 0.0}

    def fake_measure(runs, *, rounds, into, **_):
        for name in runs:
            m = into.setdefault(name, Measurement(loops=1))
            m.target_values = rounds
            while len(m.values_ns) < rounds:
                m.values_ns.append(float(truth[name] * np.exp(0.02 * rng.standard_normal())))
        clock["t"] += 1.0 if rounds == run.FIRST_ROUNDS else 1e6  # the second stage spends the budget

    real_fit_stage = run._fit_stage
    calls = {"n": 0}

    def fit_stage(recs, seed, isolated, deadline=None):
        calls["n"] += 1
        if calls["n"] > 1:
            raise ValueError("planted failure")
        return real_fit_stage(recs, seed, isolated, deadline)

    monkeypatch.setattr(run, "time", fake_time(clock))
    monkeypatch.setattr(run, "measure", fake_measure)
    monkeypatch.setattr(run, "_fit_stage", fit_stage)
    out = tmp_path / "cal.json"
    result = run.run_calibration(out, budget_s=120, target_rel_width=1e-9, seed=0)
    assert calls["n"] == 2
    assert any("the last stage's fit failed (planted failure)" in w and "stage 1's fit" in w
               for w in result.warnings), result.warnings
    cal = calfile.load(out)
    assert {len(m["values_ns"]) for m in cal["measurements"]} == {run.FIRST_ROUNDS}, \
        "the file keeps the values the kept fit was made from"
    r_true = planted["tests"] / planted["steps"]
    assert cal["constants"]["ratio"]["ci95"][0] <= r_true <= cal["constants"]["ratio"]["ci95"][1]


def test_an_empty_suite_too_noisy_for_its_steady_walks_falls_back_to_every_walk():
    """Steady walks of 18 to 42 steps with 25% noise leave the per-ray cost unidentified (the
    intercept is a small part of every such batch); the fit then takes the short walks too,
    says why, and recovers the planted T_step = 10 and T_setup = 50 ns."""
    rng = np.random.default_rng(3)
    recs = []
    for side in (1, 2, 4, 8, 12, 16, 20, 24, 28):
        rays, steps = 2048, int(2048 * 1.5 * side)
        t = rays * 50.0 + steps * 10.0
        noise = 0.25 if steps >= 10 * rays else 0.005
        recs.append(dict(kind="isolated", suite="empty", rays=rays, steps=steps, tests=0, subgrids=0,
                         values_ns=list(t * np.exp(noise * rng.standard_normal(5)))))
    with pytest.raises(ValueError, match="T_setup is not identified"):
        design, _ = run._suite_design(recs, "empty", "steps", run.STEADY_STEPS_PER_RAY)
        run._fit.fit(design, seed=0, required=("rays", "steps"), max_steps=run.ISOLATED_MAX_STEPS,
                     fail_fast=run.ISOLATED_FAIL_FAST)
    res, note = run.fit_empty_suite(recs, seed=0)
    assert "empty-grid suite fitted on every walk, since walks of 10+ steps: T_setup is not identified" in note
    assert res.constants["t_step_ns"]["median"] == pytest.approx(10.0, rel=0.05)
    assert res.constants["t_setup_ns"]["median"] == pytest.approx(50.0, rel=0.1)
    # quiet steady walks fit at once
    res, note = run.fit_empty_suite(_planted_isolated_records([30.0, 40.0, 50.0, 60.0]), seed=0)
    assert note is None and res.constants["t_step_ns"]["median"] == pytest.approx(10.0, rel=0.02)


def test_fit_reserve_grows_with_the_last_stages_fitting_time():
    assert run.fit_reserve(0.0, 0.0) >= run.FIT_RESERVE_S
    # the ray sets' fits keep their floor after a quick pooled fit, and follow a slow one
    assert run.fit_reserve(10.0, 2.0) == pytest.approx(run.FIT_RESERVE_MARGIN * 10.0 + run.POST_FIT_MIN_S)
    assert run.fit_reserve(10.0, 8.0) == pytest.approx(run.FIT_RESERVE_MARGIN * 10.0 + run.POST_FIT_PER_POOLED * 8.0)
    assert run.post_fit_reserve(8.0) > run.POST_FIT_MIN_S


def test_busy_host_share_and_note():
    assert run.cpu_share(10.0, 9.9) == pytest.approx(0.99)
    assert run.cpu_share(0.0, 0.0) == 1.0
    assert run.busy_note(run.BUSY_SHARE) == ""
    assert "had 50% of a core (the host is busy" in run.busy_note(0.5)


def test_a_run_that_measures_no_context_configuration_says_why_and_how_to_go_on(small_suite, tmp_path,
                                                                                   monkeypatch):
    """A host so busy that the budget ends before the in-context suite is measured: the run
    ends with one message naming the in-context configurations measured (none), the share of
    a core the run had and the command that continues it; the partial file keeps the values."""
    from calibrate.protocol import Measurement

    isolated = {c.name for c in suites.isolated_configs("watertight", 0)}
    clock = {"t": 0.0, "cpu": 0.0}

    def fake_measure(runs, *, rounds, into, deadline, **_):
        for name in runs:
            if name in isolated:  # the isolating suites are all the budget allowed
                m = into.setdefault(name, Measurement(loops=1))
                m.values_ns.extend([1e6] * rounds)
        clock["cpu"] += 0.4 * (deadline - clock["t"])  # other processes took the rest of the core
        clock["t"] = deadline

    monkeypatch.setattr(run, "time", fake_time(clock, lambda c: c["cpu"]))
    monkeypatch.setattr(run, "measure", fake_measure)
    out = tmp_path / "cal.json"
    with pytest.raises(UserError) as err:
        run.run_calibration(out, budget_s=60, seed=0)
    text = str(err.value)
    n_context = len(suites.context_configs("watertight", 0))
    assert "within the 60 s budget" in text and f"0 of {n_context} in-context configurations" in text, text
    assert "had 40% of a core (the host is busy" in text, text
    assert f"calibrate run --resume --out {out} --budget 120" in text, text
    assert run.partial_path(out).exists() and not out.exists()


def test_the_resume_command_names_a_runs_own_seed_and_intersector():
    from types import SimpleNamespace

    from calibrate.protocol import Measurement

    configs = [SimpleNamespace(name="a", kind="in_context"), SimpleNamespace(name="b", kind="in_context"),
               SimpleNamespace(name="c", kind="isolated")]
    timings = {"a": Measurement(loops=1), "c": Measurement(loops=1)}
    timings["a"].values_ns.append(1e6)
    common = dict(budget_s=30, set_up_s=3.2, configs=configs, timings=timings, share=0.99,
                  out=Path("o.json"), part=Path("o.json.partial"))
    text = run.not_fitted_message("nothing to fit", **common, seed=7, intersector="moller-trumbore")
    assert "1 of 2 in-context configurations" in text and "busy" not in text
    assert "`calibrate run --resume --out o.json --seed 7 --intersector moller-trumbore --budget 60`" in text
    assert "`calibrate run --resume --out o.json --budget 60`" in run.not_fitted_message("x", **common)
    text = run.not_fitted_message("x", **common, cache_bytes=16 << 20)
    assert "`calibrate run --resume --out o.json --cache 16777216 --budget 60`" in text


def test_a_run_given_a_cache_size_counts_against_it_and_tries_no_other(small_suite, tmp_path, monkeypatch):
    """`calibrate run --cache SIZE`: no cache size is chosen by the fit (select_cache is not
    called), every in-context record's lines are counted against SIZE, and the file says so."""
    def no_choice(*args, **kwargs):
        raise AssertionError("select_cache called for a run given its cache size")

    monkeypatch.setattr(run, "select_cache", no_choice)
    out = tmp_path / "cal.json"
    run.run_calibration(out, budget_s=60, target_rel_width=None, seed=2, cache_bytes=3 << 20)
    cal = calfile.load(out)
    assert calfile.cache_bytes_of(cal) == 3 << 20 and cal["meta"]["cache_candidates"] == [3 << 20]
    assert "calibrate run --cache" in cal["meta"]["cache_source"] and "cache_scores" not in cal["meta"]
    ctx = [m for m in cal["measurements"] if m["kind"] == "in_context"]
    assert ctx and all(m["misses"] == pytest.approx(float(lines_beyond_cache(
        m["steps"], m["tests"], m["memory_bytes"], 3 << 20, m["visits"] + m["changes"]))) for m in ctx)
    for bad in (0, -5, 2.5, True):
        with pytest.raises(UserError, match="cache size"):
            run.run_calibration(tmp_path / "bad.json", budget_s=60, cache_bytes=bad)


def test_slow_fits_end_measuring_earlier(small_suite, tmp_path, monkeypatch):
    """A host whose fits are slow keeps more of the budget for them: the second stage stops
    measuring at the budget less the reserve estimated from the first stage's fitting time.
    A busy host is said so, with the share of a core the run had."""
    from calibrate.protocol import Measurement

    configs = suites.isolated_configs("watertight", 0) + suites.context_configs("watertight", 0)
    planted = {"rays": 50.0, "steps": 10.0, "tests": 4.0, "subgrids": 30.0}
    truth = {c.name: sum(planted[k] * c.record()[k] for k in planted) for c in configs}
    rng = np.random.default_rng(1)
    clock = {"t": 0.0}
    deadlines = []

    def fake_measure(runs, *, rounds, into, deadline, **_):
        deadlines.append(deadline)
        for name in runs:
            m = into.setdefault(name, Measurement(loops=1))
            m.target_values = rounds
            while len(m.values_ns) < rounds:
                m.values_ns.append(float(truth[name] * np.exp(0.02 * rng.standard_normal())))
        clock["t"] = 1.0 if len(deadlines) == 1 else deadline  # a later stage measures to its deadline

    real_fit_stage = run._fit_stage

    def slow_fit_stage(recs, seed, isolated, deadline=None):
        clock["t"] += 10.0  # a pooled fit that takes 10 s
        return real_fit_stage(recs, seed, isolated, deadline)

    monkeypatch.setattr(run, "time", fake_time(clock, lambda c: 0.5 * c["t"]))  # and a busy host: half a core
    monkeypatch.setattr(run, "measure", fake_measure)
    monkeypatch.setattr(run, "_fit_stage", slow_fit_stage)
    result = run.run_calibration(tmp_path / "cal.json", budget_s=120, target_rel_width=1e-9, seed=0)
    assert any(w.startswith("this run's thread had 50% of a core (the host is busy") for w in result.warnings)
    assert calfile.load(tmp_path / "cal.json")["meta"]["cpu_share"] == pytest.approx(0.5)
    reserve = run.fit_reserve(10.0, 10.0)
    assert reserve > run.FIT_RESERVE_S
    assert deadlines == [pytest.approx(120 - run.FIT_RESERVE_S), pytest.approx(120 - reserve)]


def test_large_spreads_are_one_warning():
    line = run.spread_summary([0.12, 0.30, 0.16], 40)
    assert line.startswith("large spread in 3 of 40 configurations: scaled MAD 12-30% of the median (median 16%")
    assert "; 6% with the host's common slowdown divided out" in run.spread_summary([0.12, 0.30], 40, [0.05, 0.07])
    values = [100.0, 100.0, 130.0, 70.0, 100.0]  # MAD 0 about the median: spread 0
    assert run.rel_spread(values) == 0.0
    assert run.rel_spread([90.0, 100.0, 110.0]) == pytest.approx(1.482602218505602 * 10 / 100)

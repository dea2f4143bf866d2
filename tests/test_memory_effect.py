"""The memory effect (models/memory.py): T_mem per cache line fetched from beyond the cache.

A grid larger than the host's cache makes its steps and tests fetch lines from
further out; ``calibrate run`` records each batch's grid bytes and its expected
lines from beyond the cache (``misses``), the fit adds ``T_mem`` for them, and
predictions add ``T_mem * lines`` per ray.  These tests plant T_mem in
synthetic timings and check that the fit recovers it, that the calibration file
keeps and checks it, that a design which cannot tell it apart falls back to the
four constants and says why, and that predict moves the resolution only when
the effect matters.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrate import calfile, host
from calibrate import fit as F
from calibrate._grid import Scene
from calibrate.predict import _uniform_counts, predict, resolve_constants, scene_statistics
from conftest import assert_planted_recovered, exported_header, planted_counts
from models.effects import select_effects
from models.memory import (LINE_BYTES, STEP_LINES, TEST_LINES, VISIT_LINES, candidate_cache_sizes, lines_beyond_cache,
                           miss_fraction, weighted_miss_fraction)
from models.uncertainty import discrete_posterior_optimum

RAYS = 2048
CACHE = 2 << 20
# Constants of the same order as a measured host's isotropic fit (docs/calibration.md), ns.
TRUTH = {"t_setup_ns": 80.0, "t_step_ns": 11.5, "t_int_ns": 1.9, "t_sub_ns": 70.0, "t_mem_ns": 2.8}
PRIORS = {"t_setup_ns": (70.0, 0.3), "t_sub_ns": (60.0, 0.7)}
NOISE_REL = 0.02
N_CONFIGS = 40
N_REPEATS = 5


# -- the model ---------------------------------------------------------------------------

def test_miss_fraction_is_zero_while_the_grid_fits_and_one_minus_c_over_f_beyond(one_capacity):
    f = np.array([0.0, 1.0, CACHE / 2, CACHE, 2.0 * CACHE, 8.0 * CACHE, 1e15])
    got = miss_fraction(f, CACHE)
    want = np.where(f > CACHE, 1.0 - CACHE / np.maximum(f, 1.0), 0.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
    assert got[4] == pytest.approx(0.5) and got[5] == pytest.approx(7 / 8)
    assert np.all(np.diff(got) >= 0) and np.all(got < 1.0)
    np.testing.assert_array_equal(miss_fraction(f, None), np.zeros_like(f))


@pytest.mark.parametrize("cache, memory", [(0, 1.0), (-1, 1.0), (float("nan"), 1.0), (CACHE, -1.0),
                                           (CACHE, float("inf"))])
def test_miss_fraction_rejects_bad_sizes(cache, memory):
    with pytest.raises(ValueError):
        miss_fraction(memory, cache)


def _spread(cache):
    """The spread of capacities as docs/calibration.md states it: C 2^(j/2), j = -6..6, weighted by
    a normal law in log2 of the capacity, one octave wide."""
    j = np.arange(-6, 7)
    w = np.exp(-0.5 * (j / 2.0) ** 2)
    return w / w.sum(), cache * 2.0 ** (j / 2.0)


def test_the_miss_fraction_is_the_mean_of_one_cache_law_over_the_spread():
    import models.memory as mm

    assert mm.CACHE_SPREAD_OCTAVES == 1.0 and mm.CACHE_SPREAD_STEPS == 6
    f = np.array([0.0, 1.0, CACHE / 8, CACHE / 2, CACHE, 1.5 * CACHE, 4.0 * CACHE, 1e15])
    w, caps = _spread(CACHE)
    want = np.array([sum(wj * max(0.0, 1.0 - cj / x) for wj, cj in zip(w, caps)) if x > 0 else 0.0 for x in f])
    np.testing.assert_allclose(miss_fraction(f, CACHE), want, rtol=1e-12, atol=1e-15)
    # nothing below the smallest capacity, less than one cache's law beyond the largest
    assert miss_fraction(caps[0], CACHE) == 0.0
    assert 0.0 < miss_fraction(8 * CACHE, CACHE) < 1.0 - CACHE / (8 * CACHE)


def test_the_spread_puts_no_cliff_at_the_cache(monkeypatch):
    """With one capacity the share's slope in log F leaps from 0 to 1 at the cache size (a grid
    just under it pays nothing, one 15% over 13% of its lines); with the spread it turns in
    thirteen steps of at most a fifth (each capacity's weight), and stays below a half."""
    import models.memory as mm

    x = np.linspace(-4.0, 4.0, 4001)
    f = CACHE * np.exp(x)

    def slopes():
        m = miss_fraction(f, CACHE)
        return np.diff(m) / np.diff(x)

    spread = slopes()
    monkeypatch.setattr(mm, "CACHE_SPREAD_OCTAVES", 0.0)
    one = slopes()
    assert float(np.max(np.abs(np.diff(one)))) > 0.9  # the cliff: 0 -> 1 between neighbours
    assert np.all(spread >= 0.0) and float(np.max(np.abs(np.diff(spread)))) < 0.21
    assert float(np.max(spread)) < 0.5


def test_the_weighted_share_is_the_mean_over_the_spread(monkeypatch):
    import models.memory as mm

    rng = np.random.default_rng(7)
    rates = rng.pareto(1.5, 300) + 1e-3
    sizes = rng.integers(1, 8, 300).astype(float) * 64.0
    cache = 0.3 * float(sizes.sum())
    got = weighted_miss_fraction(rates, sizes, cache)
    w, caps = _spread(cache)
    monkeypatch.setattr(mm, "CACHE_SPREAD_OCTAVES", 0.0)
    want = sum(wj * weighted_miss_fraction(rates, sizes, cj) for wj, cj in zip(w, caps))
    assert got == pytest.approx(want, rel=1e-9)
    assert 0.0 < got < 1.0


def test_lines_count_a_line_a_step_two_an_occupied_cell_and_a_triangle_copy_a_test(one_capacity):
    assert (STEP_LINES, VISIT_LINES, TEST_LINES) == (1.0, 2.0, 72.0 / LINE_BYTES)
    f = 4.0 * CACHE  # three quarters of the grid is beyond the cache
    assert lines_beyond_cache(10, 8, f, CACHE, 3) == pytest.approx(0.75 * (10 + 3 * 2 + 8 * 72 / 64))
    assert lines_beyond_cache(10, 8, f, CACHE) == pytest.approx(0.75 * (10 + 8 * 72 / 64))  # no visits given: none
    # linear: batch totals are rays times per-ray values
    per_ray = lines_beyond_cache(10, 8, f, CACHE, 3)
    assert lines_beyond_cache(RAYS * 10, RAYS * 8, f, CACHE, RAYS * 3) == pytest.approx(RAYS * per_ray)
    assert lines_beyond_cache(10, 8, CACHE, CACHE, 3) == 0.0


# -- the host's cache ------------------------------------------------------------------------

def _cache_dir(tmp_path, entries):
    for i, (level, kind, size) in enumerate(entries):
        d = tmp_path / f"index{i}"
        d.mkdir()
        (d / "level").write_text(f"{level}\n")
        (d / "type").write_text(f"{kind}\n")
        (d / "size").write_text(f"{size}\n")
    return tmp_path


@pytest.mark.parametrize("entries, want", [
    ([(1, "Data", "48K"), (1, "Instruction", "64K"), (2, "Unified", "2048K"), (3, "Unified", "491520K")], 2 << 20),
    ([(1, "Data", "32K"), (2, "Unified", "1M")], 1 << 20),
    ([(2, "Instruction", "4M"), (2, "Data", "512K")], 512 << 10),
])
def test_cache_bytes_reads_the_level_two_data_or_unified_cache(tmp_path, entries, want):
    size, source = host.cache_bytes(cache_dir=_cache_dir(tmp_path, entries))
    assert size == want and source.endswith("size")


@pytest.mark.parametrize("entries", [[], [(1, "Data", "48K")], [(2, "Unified", "lots")], [(2, "Unified", "0K")]])
def test_cache_bytes_is_assumed_when_the_system_does_not_say(tmp_path, entries):
    size, source = host.cache_bytes(cache_dir=_cache_dir(tmp_path, entries))
    assert (size, source) == (host.DEFAULT_CACHE_BYTES, "assumed")
    assert host.cache_bytes(cache_dir=tmp_path / "absent") == (host.DEFAULT_CACHE_BYTES, "assumed")


@pytest.mark.parametrize("entries, want", [
    ([(1, "Data", "48K"), (2, "Unified", "2048K"), (3, "Unified", "491520K")], 491520 << 10),
    ([(2, "Unified", "1M"), (3, "Unified", "32M")], 32 << 20),
    ([(1, "Data", "32K"), (2, "Unified", "1M")], None),
    ([(3, "Unified", "lots")], None),
])
def test_last_cache_bytes_reads_the_level_three_cache_or_says_none(tmp_path, entries, want):
    assert host.last_cache_bytes(cache_dir=_cache_dir(tmp_path, entries)) == want
    assert host.last_cache_bytes(cache_dir=tmp_path / "absent") is None


def test_candidate_cache_sizes_double_from_the_level_two_to_the_last_level():
    mib = 1 << 20
    assert candidate_cache_sizes(mib, 32 * mib) == [mib, 2 * mib, 4 * mib, 8 * mib, 16 * mib, 32 * mib]
    assert candidate_cache_sizes(2 * mib, 480 * mib) == [2 * mib * 2 ** k for k in range(8)] + [480 * mib]
    assert candidate_cache_sizes(mib, 3 * mib) == [mib, 2 * mib, 3 * mib]
    assert candidate_cache_sizes(mib, None) == [mib] == candidate_cache_sizes(mib, mib // 2)
    with pytest.raises(ValueError, match="> 0"):
        candidate_cache_sizes(0, mib)


def test_the_fingerprint_records_the_cache():
    fp = host.fingerprint()
    assert isinstance(fp["cache_bytes"], int) and fp["cache_bytes"] > 0 and fp["cache_source"]


# -- the fit ------------------------------------------------------------------------------------

def _records(seed: int, truth=TRUTH, memory_scale=1.0, cache=CACHE) -> list[dict]:
    """In-context records over grids from 0.1 to 40 MB, values from ``truth`` (lines beyond a
    cache of ``cache`` bytes) with 2% noise."""
    rng = np.random.default_rng(seed)
    recs = []
    for j in range(N_CONFIGS):
        counts = planted_counts(rng, j, RAYS)
        memory = int(memory_scale * np.exp(rng.uniform(np.log(1e5), np.log(4e7))))
        misses = float(lines_beyond_cache(counts["steps"], counts["tests"], memory, cache))
        mu = (RAYS * truth["t_setup_ns"] + counts["steps"] * truth["t_step_ns"] + counts["tests"] * truth["t_int_ns"]
              + counts["subgrids"] * truth["t_sub_ns"] + misses * truth["t_mem_ns"])
        recs.append(dict(kind="in_context", scene=f"scene{j % 5}", resolution=[j + 1] * 3, intersector="watertight",
                         name=f"scene{j % 5} #{j}", ray_set="isotropic", rays=RAYS, **counts, memory_bytes=memory,
                         misses=misses, held_back=False, warnings=[],
                         values_ns=[float(v) for v in mu * np.exp(NOISE_REL * rng.standard_normal(N_REPEATS))]))
    return recs


@pytest.fixture(scope="module")
def planted():
    recs = _records(0)
    result = calfile.fit_in_context(calfile.design_from_measurements(recs, "in_context"), seed=0, priors=PRIORS)
    cal = calfile.from_fit(result, fingerprint={"cpu_model": "Test CPU", "cache_bytes": CACHE}, measurements=recs,
                           meta={"cache_bytes": CACHE})
    return recs, result, cal


@pytest.mark.parametrize("i, planted_cache", [(0, 1 << 20), (1, 4 << 20), (2, 8 << 20), (3, 16 << 20)])
def test_the_run_picks_the_cache_size_planted_in_the_timings(i, planted_cache):
    """Timings made with the memory effect beyond a cache of C bytes: among the sizes from the
    level-2 to the last-level cache, calibrate run keeps C (the best fit), and the fit with the
    misses counted against it recovers T_mem.  Held-back records are not looked at."""
    from calibrate import run

    truth = dict(TRUTH, t_mem_ns=12.0)
    recs = _records(2100 + i, truth, cache=planted_cache)
    candidates = candidate_cache_sizes(1 << 20, 32 << 20)
    # a held-back record with absurd times must not move the choice
    recs.append(dict(recs[0], name="held", held_back=True, values_ns=[v * 50 for v in recs[0]["values_ns"]]))
    wrong = run.with_cache(recs, 32 << 20 if planted_cache != 32 << 20 else 1 << 20)
    chosen, scores = run.select_cache(wrong, candidates, seed=0, priors=PRIORS)
    assert chosen == planted_cache, {c >> 20: round(v, 1) for c, v in scores.items()}
    assert set(scores) == set(candidates) and max(scores.values()) == scores[chosen]
    fitted = run.with_cache(wrong, chosen)
    result = calfile.fit_in_context(calfile.design_from_measurements(fitted, "in_context"), seed=0, priors=PRIORS)
    assert_planted_recovered(result, truth, ("t_step_ns", "t_int_ns", "t_mem_ns"), rel=0.1)


@pytest.mark.parametrize("at_16, chosen", [(107.4, 16 << 20), (106.6, 16 << 20), (106.4, 4 << 20)])
def test_cache_sizes_the_timings_do_not_tell_apart_go_to_the_largest(monkeypatch, at_16, chosen):
    """Planted scores (a run's: 4 MiB best at 108.4): a larger cache within CACHE_SCORE_MARGIN
    (1.92) of the best is taken; 2 points below it is not."""
    from calibrate import run

    assert run.CACHE_SCORE_MARGIN == pytest.approx(1.92)
    planted = {1 << 20: 98.3, 2 << 20: 99.0, 4 << 20: 108.4, 8 << 20: 104.3, 16 << 20: at_16, 32 << 20: 103.6}
    monkeypatch.setattr(run, "with_cache", lambda recs, c: [dict(r, cache=c) for r in recs])
    monkeypatch.setattr(run.calfile, "design_from_measurements", lambda group, kind: {"cache": group[0]["cache"]})
    monkeypatch.setattr(run._fit, "max_log_posterior", lambda design, seed, priors=None: planted[design["cache"]])
    recs = [dict(kind="in_context", ray_set="isotropic", values_ns=[1.0], held_back=False)]
    got, scores = run.select_cache(recs, sorted(planted), seed=0)
    assert got == chosen and scores == planted
    planted = dict.fromkeys(planted, -math.inf)  # every fit failed: the smallest, as before
    assert run.select_cache(recs, sorted(planted), seed=0)[0] == 1 << 20


def test_with_cache_counts_the_misses_of_in_context_records_only():
    from calibrate import run

    recs = _records(5)[:3] + [dict(kind="isolated", suite="empty", steps=10, tests=0, memory_bytes=1 << 30)]
    out = run.with_cache(recs, 4 << 20)
    for r, o in zip(recs[:3], out[:3]):
        assert o["misses"] == pytest.approx(float(lines_beyond_cache(r["steps"], r["tests"], r["memory_bytes"],
                                                                      4 << 20)))
    assert out[3] is recs[3] and "misses" not in out[3]
    assert recs[0]["misses"] == pytest.approx(float(lines_beyond_cache(recs[0]["steps"], recs[0]["tests"],
                                                                       recs[0]["memory_bytes"], CACHE)))


def test_the_fit_recovers_a_planted_t_mem(planted):
    _, result, _ = planted
    assert "t_mem_ns" in result.names and "t_mem_skipped" not in result.diagnostics
    assert_planted_recovered(result, TRUTH, ("t_step_ns", "t_int_ns", "t_mem_ns"))


def test_without_the_memory_term_the_same_timings_fit_worse(planted):
    recs, result, _ = planted
    design = calfile.design_from_measurements(recs, "in_context")
    del design["misses"]
    four = calfile.fit_in_context(design, seed=0, priors=PRIORS)
    tau = lambda r: r.diagnostics["extra_scatter"]["median"]  # noqa: E731
    assert tau(four) > 3 * tau(result)


def test_a_design_that_cannot_tell_t_mem_apart_falls_back_and_says_why():
    # every grid but one fits the cache: T_mem shows in one batch by a hair
    recs = _records(1, memory_scale=1e-3)
    recs[0]["memory_bytes"] = CACHE + 1
    recs[0]["misses"] = float(lines_beyond_cache(recs[0]["steps"], recs[0]["tests"], CACHE + 1, CACHE))
    result = calfile.fit_in_context(calfile.design_from_measurements(recs, "in_context"), seed=0, priors=PRIORS)
    assert "t_mem_ns" not in result.names
    assert "T_mem not fitted" in result.diagnostics["t_mem_skipped"]
    assert result.constants["t_int_ns"]["median"] == pytest.approx(TRUTH["t_int_ns"], rel=0.05)


@pytest.mark.parametrize("i", range(3))
def test_the_likelihood_ratio_gate_sees_a_planted_t_mem_and_not_an_absent_one(i):
    with_mem = calfile.design_from_measurements(_records(10 + i), "in_context")
    without = calfile.design_from_measurements(_records(10 + i, truth=dict(TRUTH, t_mem_ns=0.0)), "in_context")
    g_with = F.log_posterior_gain(with_mem, "misses", seed=i, priors=PRIORS)
    g_without = F.log_posterior_gain(without, "misses", seed=i, priors=PRIORS)
    assert g_with > 20 * calfile.MEMORY_MIN_GAIN
    assert g_without < calfile.MEMORY_MIN_GAIN < g_with


def test_fail_fast_stops_a_fit_whose_optional_term_is_not_identified():
    recs = _records(3, truth=dict(TRUTH, t_mem_ns=0.0))
    design = calfile.design_from_measurements(recs, "in_context")
    with pytest.raises(ValueError, match="T_mem is not identified"):
        F.fit(design, seed=0, priors=PRIORS, fail_fast=("t_mem_ns",))
    result = calfile.fit_in_context(design, seed=0, priors=PRIORS)
    assert "t_mem_ns" not in result.names and "T_mem not fitted" in result.diagnostics["t_mem_skipped"]


def test_cross_validation_predicts_every_configuration_once_and_sees_the_missing_term():
    design = calfile.design_from_measurements(_records(4), "in_context")
    with_mem = F.cross_validated_errors(design, 5, seed=4, priors=PRIORS)
    assert with_mem.shape == (N_CONFIGS,) and np.all(np.isfinite(with_mem))
    # the model that planted the timings predicts unseen batches to about the noise (2%)
    assert np.median(with_mem) < 0.03
    without = F.cross_validated_errors({k: v for k, v in design.items() if k != "misses"}, 5, seed=4,
                                       priors=PRIORS)
    assert np.median(without) > 2 * np.median(with_mem)
    with pytest.raises(ValueError, match="folds"):
        F.cross_validated_errors(design, 1)


def test_records_without_misses_fit_four_constants():
    recs = _records(2)
    for r in recs[:3]:
        del r["misses"]
    design = calfile.design_from_measurements(recs, "in_context")
    assert "misses" not in design


# -- the file -------------------------------------------------------------------------------------

def test_t_mem_round_trips(planted, tmp_path):
    _, result, cal = planted
    path = tmp_path / "cal.json"
    calfile.save(path, cal)
    back = calfile.load(path)
    assert back["constants"]["t_mem_ns"]["median"] == pytest.approx(result.constants["t_mem_ns"]["median"])
    assert "t_mem_ns" in back["samples"]["columns"] and calfile.cache_bytes_of(back) == CACHE
    again = calfile.refit(back, seed=0)
    assert again["constants"]["t_mem_ns"]["median"] == pytest.approx(TRUTH["t_mem_ns"], rel=0.05)


def test_a_t_mem_fitted_with_other_line_weights_is_said_to_need_a_refit(planted, tmp_path):
    import argparse

    from calibrate import predict as P
    from models.memory import line_weights

    def notes(path):
        """The notes of the file's constants, and of a prediction from it as the verbs load it."""
        src = P.constants_from_args(argparse.Namespace(calibration=str(path), ratio=None))
        return P.load_calibration_constants(path).notes, P.predict("cylinder196", levels="1", **src)["notes"]

    _, _, cal = planted
    old = tmp_path / "old.json"  # no meta.line_weights: fitted before they were recorded
    calfile.save(old, cal)
    for said in notes(old):
        assert any("was fitted with other cache lines" in n and "unrecorded" in n and "calibrate fit FILE" in n
                   for n in said), said
    other = tmp_path / "other.json"
    calfile.save(other, dict(cal, meta=dict(cal["meta"], line_weights={"step": 1.0, "visit": 0.0, "test": 1.125})))
    for said in notes(other):
        assert any("(1 a step, 0 an occupied cell, 1.125 a test)" in n for n in said), said
    today = tmp_path / "today.json"
    calfile.save(today, dict(cal, meta=dict(cal["meta"], line_weights=line_weights())))
    for said in notes(today):
        assert not any("other cache lines" in n for n in said), said
    # constants given by hand say nothing of line weights
    assert not any("other cache lines" in n for n in P.resolve_constants(constants=_constants(6.0, 3 << 20)).notes)


def test_a_refit_records_the_line_weights_it_fitted_with(planted):
    from calibrate import run
    from models.memory import line_weights

    _, _, cal = planted
    new, _ = run.refit_calibration(cal, seed=0)
    assert calfile.line_weights_of(new) == line_weights() == {"step": 1.0, "visit": 2.0, "test": 1.125}
    assert calfile.line_weights_of(cal) is None


def test_calibrate_fit_counts_the_lines_against_a_cache_given_by_hand(planted):
    """`calibrate fit --cache SIZE`: the in-context records' lines beyond the cache are counted
    against SIZE, the file says so, and refitting at the planted cache after a wrong one
    recovers the planted constants (the size given is the one the fit used)."""
    from calibrate import run
    from calibrate._io import UserError

    recs, _, cal = planted
    wrong, _ = run.refit_calibration(cal, seed=0, cache_bytes=8 * CACHE)
    assert calfile.cache_bytes_of(wrong) == 8 * CACHE and "calibrate fit --cache" in wrong["meta"]["cache_source"]
    ctx = [m for m in wrong["measurements"] if m["kind"] == "in_context"]
    assert [m["misses"] for m in ctx] == pytest.approx(
        [float(lines_beyond_cache(r["steps"], r["tests"], r["memory_bytes"], 8 * CACHE)) for r in recs])
    assert [m["misses"] for m in ctx] != pytest.approx([r["misses"] for r in recs])
    right, _ = run.refit_calibration(wrong, seed=0, cache_bytes=CACHE)
    assert calfile.cache_bytes_of(right) == CACHE
    assert [m["misses"] for m in right["measurements"] if m["kind"] == "in_context"] == pytest.approx(
        [r["misses"] for r in recs])
    for name in ("t_step_ns", "t_int_ns", "t_mem_ns"):
        c = right["constants"][name]
        assert c["median"] == pytest.approx(TRUTH[name], rel=0.1) and c["ci95"][0] <= TRUTH[name] <= c["ci95"][1]
    # a file whose records do not say their grid's bytes cannot be counted against another cache
    old = json.loads(json.dumps(cal))
    for m in old["measurements"]:
        m.pop("memory_bytes", None)
        m.pop("misses", None)
    old["constants"].pop("t_mem_ns", None)
    with pytest.raises(UserError, match="memory_bytes"):
        run.refit_calibration(old, seed=0, cache_bytes=CACHE)
    for bad in (0, -5, 2.5, True):  # the same check as a run's (run.checked_cache_bytes)
        with pytest.raises(UserError, match="cache size"):
            run.refit_calibration(cal, seed=0, cache_bytes=bad)


def test_calibrate_fit_cache_on_the_command_line(planted, tmp_path, capsys):
    """`calibrate fit FILE --cache 3MiB --out NEW --json`: NEW counts the lines against 3 MiB and
    the JSON says so; FILE is left as it was."""
    from calibrate.cli import main

    _, _, cal = planted
    src, out = tmp_path / "cal.json", tmp_path / "c3.json"
    calfile.save(src, cal)
    before = src.read_bytes()
    assert main(["fit", str(src), "--cache", "3MiB", "--out", str(out), "--json", "--quiet"]) == 0
    said = json.loads(capsys.readouterr().out)
    assert said["cache_bytes"] == 3 << 20 == calfile.cache_bytes_of(calfile.load(out))
    assert src.read_bytes() == before and calfile.cache_bytes_of(calfile.load(src)) == CACHE


@pytest.mark.parametrize("text, want", [("16MiB", 16 << 20), ("16M", 16 << 20), ("11.3 MiB", round(11.3 * 2**20)),
                                        ("512k", 512 << 10), ("1GiB", 1 << 30), ("4096", 4096), ("64b", 64)])
def test_cache_sizes_are_read_in_bytes_or_binary_units(text, want):
    from calibrate.cli import byte_size

    assert byte_size(text) == want


@pytest.mark.parametrize("text, said", [("16XB", "unit"), ("MiB", "number"), ("-1MiB", "from 64 bytes"),
                                        ("0", "from 64 bytes"), ("nanM", "unit"), ("1e400", "from 64 bytes"),
                                        ("2e20", "from 64 bytes")])
def test_bad_cache_sizes_are_refused_with_a_reason(text, said):
    import argparse

    from calibrate.cli import byte_size

    with pytest.raises(argparse.ArgumentTypeError, match=said):
        byte_size(text)


def _mutated(cal, fn):
    bad = json.loads(json.dumps(cal))
    fn(bad)
    return bad


@pytest.mark.parametrize("label, mutate, message", [
    ("no cache size", lambda c: (c["meta"].pop("cache_bytes"), c["fingerprint"].pop("cache_bytes")),
     "meta.cache_bytes: missing"),
    ("cache size zero", lambda c: c["meta"].__setitem__("cache_bytes", 0), "meta.cache_bytes: must be a whole"),
    ("fractional grid bytes", lambda c: c["measurements"][0].__setitem__("memory_bytes", 1.5),
     "measurements[0].memory_bytes"),
    ("negative misses", lambda c: c["measurements"][1].__setitem__("misses", -3.0), "measurements[1].misses"),
    ("t_mem without its samples", lambda c: (c["samples"]["columns"].remove("t_mem_ns"),
                                             [row.pop(c["samples"]["columns"].index("t_int_ns") + 2)
                                              for row in c["samples"]["values"]]),
     "missing column 't_mem_ns'"),
])
def test_bad_memory_fields_are_rejected(planted, label, mutate, message):
    _, _, cal = planted
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        calfile.validate(_mutated(cal, mutate))


# -- predictions -----------------------------------------------------------------------------------

def _constants(t_mem, cache):
    c = {k: v for k, v in TRUTH.items() if k != "t_mem_ns"}
    return dict(c, t_mem_ns=t_mem, cache_bytes=cache)


def _effect(result, name):
    return next(e for e in result["effects"] if e["name"] == name)


def _cost_at(res, t_mem, cache):
    k = resolve_constants(constants=_constants(t_mem, cache))
    stats = scene_statistics(Scene.builtin("sphere"))
    terms = select_effects(stats, k.t_setup, k.t_step, k.t_int, termination=True, overlap="exact", levels=1).terms
    # the bytes the term prices, and the occupied cells entered (their lines, as the planner counts them)
    steps, tests, _, _, visits, charged = _uniform_counts(stats, tuple(res), k, terms)
    return k.cost(steps, tests, 0.0, charged, visits)


@pytest.mark.parametrize("t_mem, cache", [(40.0, 4096), (6.0, 3 << 20), (20.0, 1 << 20)])
def test_a_grid_beyond_the_cache_gets_the_resolution_cheapest_with_the_memory_term(t_mem, cache):
    plain = predict("sphere", constants=_constants(0.0, None), levels="1")
    costly = predict("sphere", constants=_constants(t_mem, cache), levels="1")
    assert not any(e["name"] == "memory" for e in plain["effects"])
    mem = _effect(costly, "memory")
    assert mem["used"] and mem["change"] > 0.02
    res, res0 = costly["levels"][0]["resolution"], plain["levels"][0]["resolution"]
    assert res != res0
    best = _cost_at(res, t_mem, cache)
    assert best < _cost_at(res0, t_mem, cache)
    for f in (0.9, 1.1):  # no cheaper neighbour (the search's step is 2^(1/8) per axis)
        assert best <= _cost_at([max(1, round(x * f)) for x in res], t_mem, cache) * (1 + 1e-12)
    # the predicted time carries T_mem times the lines per ray
    p = costly["predicted"]
    assert p["lines_per_ray"] > 0
    base = (TRUTH["t_setup_ns"] + TRUTH["t_step_ns"] * p["steps_per_ray"] + TRUTH["t_int_ns"] * p["tests_per_ray"])
    assert p["ns_per_ray"]["median"] == pytest.approx(base + t_mem * p["lines_per_ray"], rel=1e-9)


def test_a_grid_that_fits_the_cache_leaves_the_resolution_alone():
    plain = predict("sphere", constants=_constants(0.0, None), levels="1")
    roomy = predict("sphere", constants=_constants(40.0, 1 << 40), levels="1")
    mem = _effect(roomy, "memory")
    assert not mem["used"] and mem["change"] == 0.0 and "tolerance" in mem["reason"]
    assert roomy["levels"][0]["resolution"] == plain["levels"][0]["resolution"]
    assert roomy["predicted"]["ns_per_ray"]["median"] == pytest.approx(plain["predicted"]["ns_per_ray"]["median"])


def test_t_mem_without_a_cache_size_is_an_error():
    with pytest.raises(ValueError, match="cache"):
        predict("sphere", constants=_constants(3.0, None), levels="1")


def test_the_header_carries_t_mem_and_the_cache(planted, tmp_path):
    _, _, cal = planted
    text = exported_header(cal, tmp_path, "GRIDCAL_T_MEM_NS > 0.0 && GRIDCAL_CACHE_BYTES > 0.0")
    assert "#define GRIDCAL_T_MEM_NS" in text and f"#define GRIDCAL_CACHE_BYTES {CACHE}.0" in text


def test_discrete_posterior_optimum_recovers_a_planted_split():
    # three candidates; 30 samples prefer the first, 70 the third; the median prefers the second
    costs = np.array([[1.0, 2.0, 3.0]] * 30 + [[3.0, 2.0, 1.0]] * 70)
    median = np.array([1.5, 1.0, 1.2])
    (lo, hi), penalty = discrete_posterior_optimum(costs, median, [10, 100, 1000])
    assert (lo, hi) == (0, 2)
    assert penalty == pytest.approx((0.3 * 1.5 + 0.7 * 1.2) / 1.0 - 1.0)
    with pytest.raises(ValueError):
        discrete_posterior_optimum(costs, median[:2], [10, 100])


def test_the_resolution_interval_comes_from_the_memory_search_over_posterior_samples():
    rng = np.random.default_rng(0)
    n = 400
    samples = {k: v * np.exp(0.1 * rng.standard_normal(n)) for k, v in TRUTH.items()}
    samples["t_mem_ns"] = 20.0 * np.exp(0.3 * rng.standard_normal(n))
    constants = dict(_constants(20.0, 1 << 20))
    result = predict("sphere", constants=constants, samples=samples, levels="1")
    assert _effect(result, "memory")["used"]
    cells = lambda r: int(np.prod(r))  # noqa: E731
    lo, hi = result["predicted"]["resolution_ci95"]
    chosen = result["levels"][0]["resolution"]
    assert cells(lo) <= cells(chosen) <= cells(hi) and cells(lo) < cells(hi)
    assert 0.0 <= result["predicted"]["uncertainty_penalty"] < 0.1


def _chain_steps(monkeypatch):
    """A list that collects the steps of every emcee chunk sampled from now on."""
    import emcee

    steps = []
    run_mcmc = emcee.EnsembleSampler.run_mcmc

    def counting(self, state, nsteps, **kw):
        steps.append(int(nsteps))
        return run_mcmc(self, state, nsteps, **kw)

    monkeypatch.setattr(emcee.EnsembleSampler, "run_mcmc", counting)
    return steps


def test_a_fit_with_an_optional_term_stops_as_soon_as_a_required_constant_is_not_identified(monkeypatch):
    """With a trial term in, any constant may be the one the data cannot place (measured: the pooled
    fit of both ray sets with T_mem leaves T_step on a ridge down to 1e-6 ns).  Such a trial ends in
    the first chunk of the chain, not after a full one: a run's budget goes to measuring."""
    recs = _records(7, truth=dict(TRUTH, t_step_ns=1e-3, t_mem_ns=12.0))  # steps cost nothing: T_step unplaced
    design = calfile.design_from_measurements(recs, "in_context")
    steps = _chain_steps(monkeypatch)
    with pytest.raises(ValueError, match="T_step is not identified"):
        F.fit(design, seed=0, priors=PRIORS)
    full = sum(steps)
    steps.clear()
    with pytest.raises(ValueError, match="T_step is not identified"):
        F.fit(design, seed=0, priors=PRIORS, fail_fast=F.CONSTANT_NAMES)
    assert sum(steps) == F.FIRST_CHUNK_STEPS < full
    # fit_in_context tries T_mem that way (one chunk), then fits without it, where T_step's term is
    # nothing at the posterior maximum: refused before any sampling
    steps.clear()
    with pytest.raises(ValueError, match="T_step is not identified"):
        calfile.fit_in_context(design, seed=0, priors=PRIORS)
    assert sum(steps) == F.FIRST_CHUNK_STEPS


def test_a_trial_term_whose_chain_cannot_converge_by_the_deadline_is_left_out(monkeypatch):
    """A run's fits keep to its budget: with no time left, the trial of T_mem ends after its first
    chunk and the term is left out, saying why; the fit without trial terms has no deadline and
    still recovers the other constants."""
    import time

    recs = _records(8, truth=dict(TRUTH, t_mem_ns=12.0))
    design = calfile.design_from_measurements(recs, "in_context")
    steps = _chain_steps(monkeypatch)
    with pytest.raises(F.ConvergenceError, match="time left for fitting"):
        F.fit(design, seed=0, priors=PRIORS, deadline=time.monotonic())
    assert steps == [F.FIRST_CHUNK_STEPS]
    steps.clear()
    result = calfile.fit_in_context(design, seed=0, priors=PRIORS, deadline=time.monotonic())
    assert "t_mem_ns" not in result.names
    assert "time left for fitting" in result.diagnostics["t_mem_skipped"]
    assert steps[0] == F.FIRST_CHUNK_STEPS and sum(steps) > F.FIRST_CHUNK_STEPS  # the trial, then a full fit
    # and with time enough the same design keeps T_mem and recovers it
    kept = calfile.fit_in_context(design, seed=0, priors=PRIORS, deadline=time.monotonic() + 3600)
    assert kept.constants["t_mem_ns"]["median"] == pytest.approx(12.0, rel=0.15)

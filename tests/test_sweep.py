"""calibrate.sweep: spec arithmetic, the counts a sweep reports, and the smooth minimum."""

from __future__ import annotations

import math
import weakref

import numpy as np
import pytest

from calibrate import rays
from calibrate._grid import Grid, Scene
from calibrate.sweep import (MAX_SWEEP_CELLS, GridSpec, best_point, fit_minimum, measure_time_per_ray,
                             model_subgrid_resolutions, model_subgrid_tables, penalty, scaled_resolutions,
                             split_rounds, sweep)

#: Short timings: these tests check counts and bookkeeping, never speed.
FAST = dict(rounds=2, min_time=1e-4)
N_RAYS = 256


@pytest.fixture(scope="module")
def cylinder():
    return Scene.builtin("cylinder196")


def _rays(scene, seed=0, n=N_RAYS):
    return rays.isotropic(scene.box_lo, scene.box_hi, n, seed)


def test_penalty_arithmetic():
    assert penalty(110.0, 100.0) == pytest.approx(0.10)
    assert penalty(100.0, 100.0) == 0.0
    assert penalty(90.0, 100.0) == pytest.approx(-0.10)  # a choice measured below the fitted best: noise
    for bad in ((1.0, 0.0), (math.nan, 1.0), (1.0, math.inf), (-1.0, 1.0)):
        with pytest.raises(ValueError):
            penalty(*bad)


def test_scaled_resolutions_round_and_clamp():
    assert scaled_resolutions((3, 1, 8), [0.1, 1.0, 2.5]) == [(1, 1, 1), (3, 1, 8), (8, 2, 20)]
    assert scaled_resolutions((100, 50, 10), [0.01]) == [(1, 1, 1)]
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError):
            scaled_resolutions((2, 2, 2), [bad])
    with pytest.raises(ValueError):
        scaled_resolutions((0, 2, 2), [1.0])


def test_spec_scaled_scales_every_level():
    spec = GridSpec("nested", [(4, 4, 10), (3, 3, 3)], subgrids="fixed")
    s2 = spec.scaled(2.0)
    assert s2.levels == ((8, 8, 20), (6, 6, 6))
    assert s2.sub_scale == 2.0
    assert GridSpec("uniform", [(5, 1, 2)]).scaled(0.1).levels == ((1, 1, 1),)
    with pytest.raises(ValueError):
        GridSpec("nested", [(4, 4, 4)], subgrids="model")  # no ratio
    with pytest.raises(ValueError):
        GridSpec("pyramid", [(4, 4, 4)])


@pytest.mark.parametrize("index", range(2))
def test_sweep_counts_equal_grid_count(cylinder, index):
    """The counts a sweep reports are the instrumented twin's on the same rays."""
    o, d = _rays(cylinder, seed=index)
    specs = [GridSpec("uniform", [(5, 5, 20)]),
             GridSpec("nested", [(3, 3, 6)], ratio=0.926),
             GridSpec("nested", [(3, 3, 6)], subgrids="rule", scale=2.0)]
    points = sweep(cylinder, specs, (o, d), seed=index, **FAST)
    for spec, p in zip(specs, points):
        steps, tests, subgrids = spec.build(cylinder).count(o, d)
        assert p["steps"] == pytest.approx(float(steps.mean()), rel=1e-12)
        assert p["tests"] == pytest.approx(float(tests.mean()), rel=1e-12)
        assert p["subgrids"] == pytest.approx(float(subgrids.mean()), rel=1e-12)
        assert p["median_ns"] > 0 and p["mad_ns"] >= 0 and len(p["values_ns"]) == FAST["rounds"]
    assert points[0]["subgrids"] == 0.0 and points[1]["subgrids"] > 0


def test_split_rounds_spreads_the_values_over_the_builds():
    assert split_rounds(8, 4) == [2, 2, 2, 2]
    assert split_rounds(7, 3) == [3, 2, 2]
    assert split_rounds(2, 5) == [1, 1]  # no build without a value
    assert split_rounds(5, 1) == [5]
    for bad in ((0, 1), (3, 0)):
        with pytest.raises(ValueError):
            split_rounds(*bad)


@pytest.mark.parametrize("index", range(2))
def test_sweep_builds_every_spec_again_for_each_share_of_values(cylinder, monkeypatch, index):
    """Each build makes a fresh grid of every spec (a grid passed in is reused), times it
    for its share of the values, and frees it; the values pool into one series."""
    rounds, builds = 5, 3
    made, timed = [], []
    original_build, original_timed = GridSpec.build, Grid.timed_batch

    def counting_build(self, scene, **kw):
        # the same spec's grid of the build before, and its timed batch (which holds the
        # kernel's grid), are freed by now
        assert all(ref() is None for top, ref in made + timed if top == self.top)
        grid = original_build(self, scene, **kw)
        made.append((self.top, weakref.ref(grid)))
        return grid

    def tracked_timed_batch(self, *a, **kw):
        run = original_timed(self, *a, **kw)
        timed.append((tuple(self.resolution), weakref.ref(run)))
        return run

    monkeypatch.setattr(GridSpec, "build", counting_build)
    monkeypatch.setattr(Grid, "timed_batch", tracked_timed_batch)
    o, d = _rays(cylinder, seed=index)
    given = Grid.uniform(cylinder, (2, 2, 8))
    specs = [GridSpec("uniform", [(5, 5, 20)]), GridSpec("nested", [(3, 3, 6)], ratio=0.926), given]
    ticks = []
    points = sweep(cylinder, specs, (o, d), seed=index, rounds=rounds, builds=builds, min_time=1e-4,
                   progress=lambda done, total, label: total and ticks.append((done, total)))
    assert [top for top, _ in made] == [(5, 5, 20), (3, 3, 6)] * builds
    # one progress count over every build: rising by one a value (the warm-up, on the first
    # build, is the loop calibration's last call: not counted)
    assert [t for _, t in ticks] == [len(specs) * rounds] * len(ticks)
    assert [dn for dn, _ in ticks] == list(range(1, len(ticks) + 1)) and len(ticks) == ticks[0][1]
    for p in points:
        assert len(p["values_ns"]) == rounds and p["builds"] == builds
    one = sweep(cylinder, specs[:1], (o, d), seed=index, rounds=rounds, builds=1, min_time=1e-4)[0]
    assert one["builds"] == 1 and len(one["values_ns"]) == rounds
    assert one["steps"] == points[0]["steps"] and one["tests"] == points[0]["tests"]
    with pytest.raises(ValueError, match="builds"):
        sweep(cylinder, specs[:1], (o, d), builds=0, min_time=1e-4)


def test_measure_time_per_ray_on_a_built_grid(cylinder):
    o, d = _rays(cylinder)
    grid = Grid.uniform(cylinder, (4, 4, 16))
    for clock in ("thread", "wall"):
        m = measure_time_per_ray(cylinder, grid, o, d, clock=clock, **FAST)
        steps, tests, _ = grid.count(o, d)
        assert m["tests"] == pytest.approx(float(tests.mean()))
        assert m["median_ns"] > 0
    with pytest.raises(ValueError):
        measure_time_per_ray(cylinder, grid, o, d, clock="sundial", **FAST)


def test_fixed_subgrids_give_every_subdivided_cell_that_resolution(cylinder):
    top, sub = (3, 3, 5), (2, 3, 4)
    spec = GridSpec("nested", [top, sub], subgrids="fixed")
    grid = spec.build(cylinder)
    counts = Grid.uniform(cylinder, top).top_counts()
    subdivided = int((counts > spec.threshold).sum())
    assert subdivided > 0
    assert grid.info["n_cells"] == top[0] * top[1] * top[2] + subdivided * sub[0] * sub[1] * sub[2]


def test_model_subgrids_scale_per_axis(cylinder):
    top = (3, 3, 6)
    base = model_subgrid_resolutions(cylinder, top, 2, 0.926)
    spec = GridSpec("nested", [top], ratio=0.926, sub_scale=2.0)
    n_cells = spec.build(cylinder).info["n_cells"]
    rows = base[base[:, 0] > 0]
    doubled = np.maximum(1, np.rint(rows * 2.0)).prod(axis=1).sum()
    # cells with at most `threshold` references keep their list even when a row is given
    counts = Grid.uniform(cylinder, top).top_counts().reshape(-1)
    kept = (base[:, 0] > 0) & (counts <= spec.threshold)
    expected = top[0] * top[1] * top[2] + doubled - np.maximum(1, np.rint(base[kept] * 2.0)).prod(axis=1).sum()
    assert n_cells == expected


@pytest.mark.parametrize("sub_scale", [1.0, 2.0, 0.5])
def test_three_level_model_specs_are_built_level_for_level(cylinder, sub_scale):
    """The kernel builds the nested model's three levels: its grids and cells, level by level."""
    from models.nested import nested_counts

    from calibrate._grid import triangle_box_overlap
    from calibrate.predict import _geometry

    top, ratio = (3, 3, 8), 0.15
    geom, corners = _geometry(cylinder)
    counts = nested_counts(geom, cylinder.stats.box_lo, cylinder.stats.box_hi, top, 3, ratio, overlap="exact",
                           corners=corners, leaves="analytic", overlap_test=triangle_box_overlap,
                           child_scale=sub_scale)
    info = GridSpec("nested", [top], depth=3, ratio=ratio, sub_scale=sub_scale).build(cylinder).info
    assert info["levels"] == 3
    assert info["n_nodes"] == 1 + sum(lv.grids for lv in counts.per_level[1:])
    assert info["n_cells"] == counts.cells
    sub, sub2 = model_subgrid_tables(cylinder, top, 3, ratio, sub_scale)
    leaves = sub2[sub2[:, 0] > 0]
    assert leaves.shape[0] == counts.per_level[2].grids and (leaves.prod(axis=1) > 1).sum() > 50
    if sub_scale == 1.0:  # the two-level table is the same function's
        assert np.array_equal(sub, model_subgrid_resolutions(cylinder, top, 3, ratio))


def test_sweep_skips_specs_over_the_cell_budget(cylinder):
    side = int(round(MAX_SWEEP_CELLS ** (1 / 3))) + 2
    points = sweep(cylinder, [GridSpec("uniform", [(side, side, side)]), GridSpec("uniform", [(2, 2, 2)])],
                   _rays(cylinder), **FAST)
    assert "skipped" in points[0] and "median_ns" not in points[0]
    assert best_point(points) == 1


@pytest.mark.parametrize("index", range(5))
def test_fit_minimum_recovers_a_planted_vertex(index):
    """log t = a (log s - log s0)^2 + c with 1% noise: the vertex within 15% in scale."""
    rng = np.random.default_rng(index)
    s0 = float(np.exp(rng.uniform(-0.8, 0.8)))
    a, c = rng.uniform(0.6, 1.5), math.log(500.0)
    scales = 4.0 ** np.linspace(-1.0, 1.0, 13)
    times = np.exp(a * (np.log(scales) - math.log(s0)) ** 2 + c + rng.normal(0.0, 0.01, scales.size))
    fit = fit_minimum(scales, times)
    assert fit["fitted"]
    assert abs(math.log(fit["scale"] / s0)) < math.log(1.15)
    assert fit["time"] == pytest.approx(500.0, rel=0.03)
    # the curve's minimum is no higher than the lowest point's neighbourhood allows
    assert fit["time"] <= times.min() * 1.03


def test_fit_minimum_at_the_edge_keeps_the_lowest_point():
    scales = np.array([1.0, 2.0, 4.0, 8.0])
    times = np.array([100.0, 80.0, 60.0, 50.0])  # still falling at the end
    fit = fit_minimum(scales, times)
    assert fit["at_edge"] and not fit["fitted"]
    assert fit["scale"] == 8.0 and fit["time"] == 50.0
    with pytest.raises(ValueError):
        fit_minimum([2.0, 1.0], [1.0, 1.0])


def test_fit_minimum_keeps_the_lowest_point_at_a_kink():
    """A curve that jumps right after its minimum (a cache level) is no parabola there."""
    scales = 4.0 ** np.linspace(-1.0, 1.0, 7)
    times = np.array([2834.0, 2000.0, 1853.0, 1639.0, 3512.0, 4317.0, 6492.0])
    fit = fit_minimum(scales, times, mads=np.full(7, 10.0))
    assert not fit["fitted"]
    assert fit["scale"] == scales[3] and fit["time"] == 1639.0


@pytest.mark.parametrize("i", range(3))
def test_fit_minimum_judges_a_dip_by_the_medians_standard_error(i):
    """A point 15% under a smooth curve (a resolution that suits the scene) lies within
    3 sigma of its values' spread, but far outside 3 standard errors of a median of 8
    values: with ``counts`` the dip is no parabola and the lowest point is kept, and the
    fitted best is never above a measured point by more than the medians' noise."""
    rng = np.random.default_rng(1300 + i)
    scales = 4.0 ** np.linspace(-1.0, 1.0, 13)
    times = 100.0 * (1.0 + rng.uniform(0.3, 0.7) * np.log(scales) ** 2)
    times[6] *= 0.85
    mads = 0.04 * times
    loose = fit_minimum(scales, times, mads=mads)
    assert loose["fitted"] and loose["time"] > 1.05 * times[6]
    strict = fit_minimum(scales, times, mads=mads, counts=np.full(13, 8))
    assert not strict["fitted"] and strict["time"] == times[6]
    smooth = 100.0 * (1.0 + 0.5 * np.log(scales) ** 2)  # no dip: the vertex is still fitted
    assert fit_minimum(scales, smooth, mads=0.04 * smooth, counts=np.full(13, 8))["fitted"]


def test_a_required_grid_that_cannot_be_built_stops_the_sweep_at_once(cylinder):
    side = int(round(MAX_SWEEP_CELLS ** (1 / 3))) + 2
    with pytest.raises(ValueError, match="cannot be measured"):
        sweep(cylinder, [GridSpec("uniform", [(side, side, side)]), GridSpec("uniform", [(2, 2, 2)])],
              _rays(cylinder), required=(0,), **FAST)


def test_a_sweeps_values_have_the_common_slowdown_divided_out(cylinder, monkeypatch):
    """Each value is the one timed over the drift factor protocol.drift_factors gives for
    the sweep's series (kept as raw_values_ns); with drift_out=False the values are as timed."""
    from calibrate import protocol

    seen = {}
    real = protocol.drift_factors

    def spy(series):
        seen.update(series)
        return real(series)

    monkeypatch.setattr(protocol, "drift_factors", spy)
    o, d = _rays(cylinder, seed=1)
    specs = [GridSpec("uniform", [(s, s, 4 * s)]) for s in (2, 3, 4, 5)]
    points = sweep(cylinder, specs, (o, d), seed=1, rounds=4, min_time=1e-4)
    factors = real(seen)
    assert len(seen) == len(specs)
    for key, p in zip(sorted(seen, key=int), points):
        raw = np.asarray(p["raw_values_ns"])
        assert raw * N_RAYS == pytest.approx(np.asarray(seen[key][0]))
        assert np.asarray(p["values_ns"]) == pytest.approx(raw / factors[key])
        assert p["median_ns"] == pytest.approx(float(np.median(p["values_ns"])))
    plain = sweep(cylinder, specs, (o, d), seed=1, rounds=4, min_time=1e-4, drift_out=False)
    assert all("raw_values_ns" not in p for p in plain)

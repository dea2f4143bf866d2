"""The per-scene fit of tests/benchmarks/scene_constants.py recovers planted costs.

The benchmark reads a calibration's stored in-context timings and fits each scene's
uniform grids alone; these tests plant a step's and a test's cost in per-ray times
(coarse-to-fine counts like one scene's series) and check the fit returns them, and
that it reads a calibration's records scene by scene with the calibration's residuals.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "benchmarks"))
import scene_constants as SC  # noqa: E402


def _series(rng, n=8):
    """Steps rise and tests fall from coarse to fine, as along one scene's resolutions."""
    steps = np.geomspace(1.5, 40.0, n) * rng.uniform(0.9, 1.1, n)
    tests = np.geomspace(150.0, 10.0, n) * rng.uniform(0.9, 1.1, n)
    return steps, tests


@pytest.mark.parametrize("i", range(5))
def test_local_fit_recovers_planted_step_and_test_costs(i):
    rng = np.random.default_rng(i)
    a, t_step, t_int = rng.uniform(30, 80), rng.uniform(3, 14), rng.uniform(0.5, 1.5)
    steps, tests = _series(rng)
    time = (a + t_step * steps + t_int * tests) * np.exp(0.003 * rng.standard_normal(steps.size))
    got = SC.local_fit(steps, tests, time)
    assert got["t_step_ns"] == pytest.approx(t_step, rel=0.03)
    assert got["t_int_ns"] == pytest.approx(t_int, rel=0.05)
    assert got["ratio"] == pytest.approx(t_int / t_step, rel=0.08)
    assert 0 < got["rms"] < 0.01


def test_local_fit_needs_enough_grids():
    with pytest.raises(ValueError, match="at least"):
        SC.local_fit([1, 2, 3], [9, 5, 3], [50, 60, 70])


def test_scene_rows_fit_each_scene_alone_and_report_the_calibrations_residuals():
    rng = np.random.default_rng(7)
    truth = {"sphere": (5.0, 1.0), "cylinder": (12.0, 0.8)}
    consts = {"t_setup_ns": {"median": 40.0}, "t_step_ns": {"median": 5.0}, "t_int_ns": {"median": 1.0},
              "t_mem_ns": None, "ratio": {"median": 0.2}}
    recs = []
    for scene, (t_step, t_int) in truth.items():
        steps, tests = _series(rng, 6)
        for j, (s, t) in enumerate(zip(steps, tests)):
            rays = 1000
            ns = rays * (40.0 + t_step * s + t_int * t)
            recs.append(dict(kind="in_context", ray_set="isotropic", scene=scene, resolution=f"{j + 2}x{j + 2}x{j + 2}",
                             rays=rays, steps=int(rays * s), tests=int(rays * t), subgrids=0, values_ns=[ns] * 3,
                             changes=rays * j))
    # a nested grid and another ray set are left out
    recs.append(dict(recs[0], resolution="L2 3x3x3"))
    recs.append(dict(recs[0], ray_set="camera"))
    cal = {"constants": consts, "by_rays": {"isotropic": {"constants": consts}}, "measurements": recs}
    rows = {r["scene"]: r for r in SC.scene_rows(cal, "isotropic")}
    assert set(rows) == set(truth)
    for scene, (t_step, t_int) in truth.items():
        row = rows[scene]
        assert row["grids"] == 6 and row["local"]["t_step_ns"] == pytest.approx(t_step, rel=0.01)
        assert row["local"]["t_int_ns"] == pytest.approx(t_int, rel=0.02)
        assert np.all(np.diff(row["steps_per_ray"]) > 0)  # coarse to fine
        assert row["changes_per_ray"] == pytest.approx(list(range(6)))
    # the sphere is the calibration's own: no residual; the cylinder's residuals rise with its steps
    assert max(abs(x) for x in rows["sphere"]["residuals"]) < 0.01
    res = rows["cylinder"]["residuals"]
    assert res[-1] > 0.1 and res[-1] > res[0]  # dear steps: under-priced most at the finest grid

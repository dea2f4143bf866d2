"""Tests of calibrate.fit: planted constants recovered, honest intervals, ill-posed designs.

Synthetic timings follow the fit's model with planted constants: batches of
RAYS_PER_BATCH rays, steps per ray 10..2000 and tests per ray 1..500
(log-uniform, as a coarse-to-fine resolution sweep gives), some empty-grid
batches (no tests, few steps) like the isolating microbenchmarks, and 5%
multiplicative log-normal noise per value. Every dataset is seeded by its index.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from calibrate import fit as F

TRUE_NS = {"t_setup_ns": 40.0, "t_step_ns": 3.0, "t_int_ns": 7.5, "t_sub_ns": 15.0}
TRUE_RATIO = TRUE_NS["t_int_ns"] / TRUE_NS["t_step_ns"]
RAYS_PER_BATCH = 10_000
NOISE_REL = 0.05
STEPS_PER_RAY = (10.0, 2000.0)
TESTS_PER_RAY = (1.0, 500.0)
EMPTY_STEPS_PER_RAY = (1.0, 50.0)
SUBGRIDS_PER_RAY = (5.0, 50.0)
RECOVERY_REL_TOL = 0.02
COVERAGE_DATASETS = 50
COVERAGE_MIN = 0.90
# Chain length for the coverage sweep, in autocorrelation times: half the
# default, still converged (emcee's estimate is trusted from ~20 tau). Shorter
# chains give noisier interval ends, so coverage passing here implies it at 50.
COVERAGE_AUTOCORR_TOL = 25.0


def synthetic_design(
    rng: np.random.Generator,
    n_configs: int = 40,
    n_repeats: int = 5,
    n_empty: int = 10,
    nested_share: float = 0.0,
    true_ns: dict = TRUE_NS,
    noise_rel: float = NOISE_REL,
    misfit_rel: float = 0.0,
) -> dict:
    """A design with planted constants; counts are batch totals, times in ns."""
    rays = np.full(n_configs, float(RAYS_PER_BATCH))
    log_uniform = lambda lo_hi, n: np.exp(rng.uniform(np.log(lo_hi[0]), np.log(lo_hi[1]), n))  # noqa: E731
    steps_pr = log_uniform(STEPS_PER_RAY, n_configs)
    tests_pr = log_uniform(TESTS_PER_RAY, n_configs)
    steps_pr[:n_empty] = log_uniform(EMPTY_STEPS_PER_RAY, n_empty)
    tests_pr[:n_empty] = 0.0
    nested = rng.random(n_configs) < nested_share
    nested[:n_empty] = False
    sub_pr = np.where(nested, rng.uniform(*SUBGRIDS_PER_RAY, n_configs), 0.0)
    steps, tests, subgrids = (np.round(rays * v) for v in (steps_pr, tests_pr, sub_pr))
    mu = (
        rays * true_ns["t_setup_ns"]
        + steps * true_ns["t_step_ns"]
        + tests * true_ns["t_int_ns"]
        + subgrids * true_ns["t_sub_ns"]
    )
    misfit = misfit_rel * rng.standard_normal(n_configs)
    times = mu[:, None] * np.exp(misfit[:, None] + noise_rel * rng.standard_normal((n_configs, n_repeats)))
    return {"rays": rays, "steps": steps, "tests": tests, "subgrids": subgrids, "times_ns": times}


def truth_of(name: str) -> float:
    return TRUE_RATIO if name == "ratio" else TRUE_NS[name]


# --- recovery and honesty ------------------------------------------------------


@pytest.mark.parametrize("i", range(3))
def test_recovers_planted_constants_within_2_percent(i):
    design = synthetic_design(
        np.random.default_rng(100 + i), n_configs=120, n_repeats=10, n_empty=24, nested_share=0.5
    )
    t0 = time.perf_counter()
    res = F.fit(design, seed=i)
    elapsed = time.perf_counter() - t0
    assert res.names == ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns")
    for name in ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "ratio"):
        c = res.constants[name]
        assert abs(c["median"] / truth_of(name) - 1) < RECOVERY_REL_TOL, (name, c)
        assert c["ci95"][0] <= c["ci68"][0] <= c["median"] <= c["ci68"][1] <= c["ci95"][1]
    d = res.diagnostics
    assert d["converged"] is True
    assert d["n_steps"] - d["burn_in"] >= F.AUTOCORR_TOL * max(d["tau_steps"])
    assert F.ACCEPTANCE_RANGE[0] <= d["acceptance"] <= F.ACCEPTANCE_RANGE[1]
    assert elapsed < 10.0  # a typical fit takes about a second


def test_95_percent_intervals_cover_truth_in_90_percent_of_datasets():
    hits = {name: 0 for name in ("t_setup_ns", "t_step_ns", "t_int_ns", "ratio")}
    for i in range(COVERAGE_DATASETS):
        design = synthetic_design(np.random.default_rng(2000 + i), n_configs=24, n_repeats=5, n_empty=6)
        res = F.fit(design, seed=i, autocorr_tol=COVERAGE_AUTOCORR_TOL)
        assert res.diagnostics["n_steps"] - res.diagnostics["burn_in"] >= 25 * max(res.diagnostics["tau_steps"])
        for name in hits:
            lo, hi = res.constants[name]["ci95"]
            hits[name] += lo <= truth_of(name) <= hi
    for name, n in hits.items():
        assert n >= COVERAGE_MIN * COVERAGE_DATASETS, (name, n)


@pytest.mark.parametrize("i", range(2))
def test_model_misfit_widens_intervals_instead_of_lying(i):
    # 4% per-configuration misfit that repeats cannot average away, tiny repeat
    # noise: a repeat-only noise model would give confidently wrong intervals.
    design = synthetic_design(
        np.random.default_rng(300 + i), n_configs=40, n_repeats=10, noise_rel=0.002, misfit_rel=0.04
    )
    res = F.fit(design, seed=i)
    for name in ("t_setup_ns", "t_step_ns", "t_int_ns", "ratio"):
        lo, hi = res.constants[name]["ci95"]
        assert lo <= truth_of(name) <= hi, (name, lo, hi)
    lo, hi = res.diagnostics["extra_scatter"]["ci95"]
    assert lo <= 0.04 <= hi


def test_without_subgrids_t_sub_is_none():
    design = synthetic_design(np.random.default_rng(400), n_configs=30)
    del design["subgrids"]
    res = F.fit(design, seed=0)
    assert res.constants["t_sub_ns"] is None
    assert res.names == ("t_setup_ns", "t_step_ns", "t_int_ns")
    assert res.samples.shape[1] == 3
    assert res.tau_samples.shape == (res.samples.shape[0],)


def test_deterministic_given_seed():
    design = synthetic_design(np.random.default_rng(500), n_configs=20)
    quick = {"autocorr_tol": COVERAGE_AUTOCORR_TOL}
    a = F.fit(design, seed=7, **quick)
    b = F.fit(design, seed=7, **quick)
    np.testing.assert_array_equal(a.samples, b.samples)
    assert a.constants == b.constants
    c = F.fit(design, seed=8, **quick)
    assert not np.array_equal(a.samples, c.samples)
    # A different seed moves the summary by Monte Carlo error only.
    assert abs(c.constants["ratio"]["median"] / a.constants["ratio"]["median"] - 1) < 0.01


def test_held_back_configurations_predicted_within_5_percent():
    design = synthetic_design(np.random.default_rng(600), n_configs=50, nested_share=0.4)
    train, held = F.split_design(design, 0.25, np.random.default_rng(601))
    assert len(train["rays"]) + len(held["rays"]) == 50 and len(held["rays"]) >= 12
    res = F.fit(train, seed=0)
    pred = F.predict_batch_times(res.samples, res.names, held)
    assert pred.shape == (res.samples.shape[0], len(held["rays"]))
    err = F.holdout_error(res, held)
    # Measured medians carry ~5%/sqrt(5) noise, so the error is about 2%.
    assert err < 0.05
    # Against noise-free truth the prediction is better still.
    truth = F.predict_batch_times(
        np.array([[TRUE_NS[n] for n in res.names]]), res.names, held
    )[0]
    assert np.median(np.abs(np.median(pred, axis=0) / truth - 1)) < 0.02


def test_posterior_gradient_matches_finite_differences():
    prep = F.prepare_design(synthetic_design(np.random.default_rng(700), n_configs=15, nested_share=0.5))
    post = F._LogPosterior(prep)
    theta = np.append(np.log([TRUE_NS[n] for n in prep.names]), 0.03)
    val, grad = post.value_and_grad(theta)
    assert val == pytest.approx(post(theta[None, :])[0], rel=1e-12)
    step = 1e-6
    for p in range(theta.size):
        e = np.zeros_like(theta)
        e[p] = step
        fd = (post.value_and_grad(theta + e)[0] - post.value_and_grad(theta - e)[0]) / (2 * step)
        assert grad[p] == pytest.approx(fd, rel=1e-5, abs=1e-4), p
    outside = theta.copy()
    outside[-1] = -0.1  # negative scatter is outside the support
    assert post(outside[None, :])[0] == -np.inf


# --- ill-posed designs -----------------------------------------------------------


def test_collinear_steps_and_tests_rejected():
    design = synthetic_design(np.random.default_rng(800), n_configs=30, n_empty=0)
    design["tests"] = design["steps"] / 4.0
    with pytest.raises(ValueError, match=r"collinear counts: steps and tests"):
        F.fit(design, seed=0)


def test_nearly_collinear_counts_error_or_honest_interval():
    rng = np.random.default_rng(801)
    for jitter_rel in (1e-3, 1e-1):
        design = synthetic_design(rng, n_configs=30, n_empty=0)
        design["tests"] = np.round(design["steps"] / 4.0 * (1 + jitter_rel * rng.standard_normal(30)))
        mu = (
            design["rays"] * TRUE_NS["t_setup_ns"]
            + design["steps"] * TRUE_NS["t_step_ns"]
            + design["tests"] * TRUE_NS["t_int_ns"]
        )
        design["times_ns"] = mu[:, None] * np.exp(NOISE_REL * rng.standard_normal((30, 5)))
        try:
            res = F.fit(design, seed=0, autocorr_tol=COVERAGE_AUTOCORR_TOL)
        except (ValueError, F.ConvergenceError) as exc:
            assert "collinear" in str(exc) or "not identified" in str(exc)
            continue
        lo, hi = res.constants["ratio"]["ci95"]
        assert lo <= TRUE_RATIO <= hi
        assert hi / lo > 1.5  # honestly wide: steps and tests barely separable


def test_single_configuration_rejected():
    design = synthetic_design(np.random.default_rng(802), n_configs=1, n_empty=0)
    with pytest.raises(ValueError, match="single configuration"):
        F.fit(design)


def test_too_few_configurations_rejected():
    design = synthetic_design(np.random.default_rng(803), n_configs=3, n_empty=1)
    with pytest.raises(ValueError, match="at least 4 configurations"):
        F.fit(design)


def test_zero_variance_repeats_rejected():
    design = synthetic_design(np.random.default_rng(804), n_configs=20)
    design["times_ns"][7, :] = design["times_ns"][7, 0]
    with pytest.raises(ValueError, match=r"zero variance: repeats of configuration\(s\) 7"):
        F.fit(design)


@pytest.mark.parametrize("t_step_ns", [1e-6, 1e-3])
def test_t_step_near_zero_error_or_honest_interval(t_step_ns):
    true_ns = dict(TRUE_NS, t_step_ns=t_step_ns)
    design = synthetic_design(np.random.default_rng(805), n_configs=30, true_ns=true_ns)
    try:
        res = F.fit(design, seed=0)
    except ValueError as exc:
        assert "T_step is not identified" in str(exc)
        return
    lo, hi = res.constants["t_step_ns"]["ci95"]
    assert lo <= t_step_ns <= hi and hi / lo > 10


def test_small_t_step_that_the_data_do_resolve_is_recovered():
    # 0.03 ns/step is 1% of the real one but still several % of long batches.
    true_ns = dict(TRUE_NS, t_step_ns=0.03)
    res = F.fit(synthetic_design(np.random.default_rng(806), n_configs=30, true_ns=true_ns), seed=0)
    lo, hi = res.constants["t_step_ns"]["ci95"]
    assert lo <= 0.03 <= hi and hi / lo < 1.5


def test_unconverged_chain_raises_with_estimate():
    design = synthetic_design(np.random.default_rng(807), n_configs=20)
    with pytest.raises(F.ConvergenceError, match="autocorrelation times") as info:
        F.fit(design, seed=0, max_steps=300)
    assert info.value.tau.shape == (4,) and np.all(info.value.tau > 0)
    assert info.value.n_steps <= 300


# --- malformed input ---------------------------------------------------------------


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("tests"), "missing 'tests'"),
        (lambda d: d["steps"].__setitem__(3, -5.0), "negative count"),
        (lambda d: d["times_ns"].__setitem__((2, 1), np.nan), "row 2 contains NaN"),
        (lambda d: d["times_ns"].__setitem__((4, 0), 0.0), "non-positive time"),
        (lambda d: d.__setitem__("rays", d["rays"][:-1]), "'rays' has 19"),
        (lambda d: d.__setitem__("tests", np.zeros(20)), "zero in every configuration"),
    ],
)
def test_malformed_designs_rejected(mutate, message):
    design = synthetic_design(np.random.default_rng(900), n_configs=20)
    mutate(design)
    with pytest.raises(ValueError, match=message):
        F.fit(design)


def test_ragged_repeats_accepted():
    design = synthetic_design(np.random.default_rng(901), n_configs=25)
    design["times_ns"] = [row[: 2 + j % 4] for j, row in enumerate(design["times_ns"])]
    prep = F.prepare_design(design)
    np.testing.assert_array_equal(prep.n_repeats, [2 + j % 4 for j in range(25)])
    res = F.fit(design, seed=0)
    lo, hi = res.constants["ratio"]["ci95"]
    assert lo <= TRUE_RATIO <= hi


def test_isolating_suite_fits_a_subset_of_constants():
    # Empty grids of growing m: no tests, no subgrids -> T_setup and T_step only.
    design = synthetic_design(np.random.default_rng(902), n_configs=20, n_empty=20)
    assert not np.any(design["tests"])
    with pytest.raises(ValueError, match="'tests' is zero in every configuration"):
        F.prepare_design(design)
    res = F.fit(design, seed=0, required=("rays", "steps"))
    assert res.names == ("t_setup_ns", "t_step_ns")
    assert res.constants["t_int_ns"] is None and res.constants["ratio"] is None
    for name in res.names:
        lo, hi = res.constants[name]["ci95"]
        assert lo <= TRUE_NS[name] <= hi and hi / lo < 1.2


def test_repeated_configuration_is_one_configuration():
    design = synthetic_design(np.random.default_rng(904), n_configs=10, n_empty=0)
    for key in ("rays", "steps", "tests", "subgrids"):
        design[key] = np.repeat(design[key][:1], 10)
    with pytest.raises(ValueError, match="collinear counts: rays, steps and tests"):
        F.fit(design)


def test_single_values_without_repeats_put_all_noise_in_the_scatter():
    design = synthetic_design(np.random.default_rng(903), n_configs=40, n_repeats=1)
    res = F.fit(design, seed=0)
    assert res.diagnostics["pooled_repeat_sd"] is None
    lo, hi = res.diagnostics["extra_scatter"]["ci95"]
    assert lo <= NOISE_REL <= hi
    for name in ("t_setup_ns", "t_step_ns", "t_int_ns", "ratio"):
        lo, hi = res.constants[name]["ci95"]
        assert lo <= truth_of(name) <= hi, name

"""Posterior propagation: known transforms of the samples, jax = numpy, penalty scaling."""

from __future__ import annotations

import numpy as np
import pytest
from test_models_general import mesh_of, random_triangles

from models.general import Terms, optimal_cell_size
from models.stats import stats_from_geometry, triangle_geometry
from models.uncertainty import posterior_ns, posterior_optimum, summarise


def _stats(i=0):
    rng = np.random.default_rng(7000 + i)
    tri = random_triangles(rng, 3000, (2, 1, 1), 0.02)
    return stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], [2, 1, 1])


def _samples(i, n, sigma):
    rng = np.random.default_rng(7100 + i)
    return (20 * np.exp(sigma * rng.standard_normal(n)), 2 * np.exp(sigma * rng.standard_normal(n)),
            8 * np.exp(sigma * rng.standard_normal(n)))


def test_point_posterior_collapses():
    s = _stats()
    p = posterior_optimum(s, np.full(9, 20.0), np.full(9, 2.0), np.full(9, 8.0), use_jax=False)
    h = optimal_cell_size(s, 2.0, 8.0)
    assert p.cell_size.median == pytest.approx(h, rel=1e-12)
    assert p.cell_size.ci95 == (pytest.approx(h, rel=1e-12), pytest.approx(h, rel=1e-12))
    assert p.penalty == pytest.approx(0.0, abs=1e-12) and p.regret == pytest.approx(0.0, abs=1e-12)
    assert p.resolution_ci95[0] == p.resolution_ci95[1] == p.resolution


def test_median_cell_size_is_the_optimum_at_the_median_ratio():
    """h* is monotone in r, so with an odd sample count the median h* is h*(median r)."""
    s = _stats(1)
    rng = np.random.default_rng(7200)
    t_int = 8 * np.exp(0.3 * rng.standard_normal(2001))
    p = posterior_optimum(s, np.full(2001, 20.0), np.full(2001, 2.0), t_int, use_jax=False)
    assert p.cell_size.median == pytest.approx(optimal_cell_size(s, 2.0, float(np.median(t_int))), rel=1e-12)
    lo, hi = p.resolution_ci95
    assert all(a <= m <= b for a, m, b in zip(lo, p.resolution, hi))


@pytest.mark.parametrize("mailbox", [False, True])
def test_jax_and_numpy_agree(mailbox):
    s = _stats(2)
    ts, tt, ti = _samples(0, 501, 0.2)
    terms = Terms(mailbox=mailbox, traversed_fraction=0.7)
    a = posterior_optimum(s, ts, tt, ti, terms=terms, use_jax=True)
    b = posterior_optimum(s, ts, tt, ti, terms=terms, use_jax=False)
    assert a.cell_size.median == pytest.approx(b.cell_size.median, rel=1e-10)
    assert a.penalty == pytest.approx(b.penalty, rel=1e-8, abs=1e-14)
    assert a.regret == pytest.approx(b.regret, rel=1e-8, abs=1e-14)
    assert a.ns_per_ray.ci95 == pytest.approx(b.ns_per_ray.ci95, rel=1e-12)


def test_penalty_is_second_order_in_the_spread():
    """Near the optimum the expected penalty grows as the variance: doubling sigma ~ x4."""
    s = _stats(3)
    p1 = posterior_optimum(s, *_samples(1, 4001, 0.02), use_jax=False).penalty
    p2 = posterior_optimum(s, *_samples(1, 4001, 0.04), use_jax=False).penalty
    assert p1 > 0 and p2 > 0
    assert p2 / p1 == pytest.approx(4.0, rel=0.1)


def test_posterior_ns_is_the_linear_combination():
    ts, tt, ti = _samples(2, 1001, 0.1)
    sub = np.full(1001, 5.0)
    iv = posterior_ns(10.0, 3.0, ts, tt, ti, subgrids=2.0, t_sub=sub)
    want = summarise(ts + 10 * tt + 3 * ti + 10.0)
    assert iv.median == pytest.approx(want.median) and iv.ci68 == pytest.approx(want.ci68)


def test_bad_samples_raise():
    s = _stats()
    with pytest.raises(ValueError):
        posterior_optimum(s, [1.0, 2.0], [1.0], [1.0, 1.0])
    with pytest.raises(ValueError):
        posterior_optimum(s, [1.0], [0.0], [1.0])
    with pytest.raises(ValueError):
        posterior_optimum(s, [1.0], [1.0], [np.nan])

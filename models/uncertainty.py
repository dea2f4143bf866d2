"""Posterior samples of the hardware constants -> uncertainty of the optimal grid.

Given S posterior samples of ``(t_setup, t_step, t_int[, t_sub])`` (ns), the single-level
optimum is evaluated per sample (the cubic root of :mod:`models.general`, vectorised
with ``jax.vmap`` under float64), giving the optimal cell size's distribution, its
credible intervals, and the time penalty the uncertainty causes under the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .closed_forms import cells_to_resolution
from .general import (Terms, cost_cubic, cubic_coefficients, predict_uniform, solve_cell_quartic,
                      termination_coefficients)
from .stats import SceneStats

#: Central credible intervals reported (fractions of posterior mass).
CREDIBLE_MASSES = (0.68, 0.95)


@dataclass(frozen=True)
class Interval:
    """median and central credible intervals ``ci68 = (lo, hi)``, ``ci95 = (lo, hi)``."""

    median: float
    ci68: tuple
    ci95: tuple


def summarise(samples) -> Interval:
    """Median and central 68% / 95% intervals of a 1-D array of samples."""
    x = np.asarray(samples, dtype=np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("no samples to summarise")
    q = [50.0]
    for m in CREDIBLE_MASSES:
        q += [50.0 * (1.0 - m), 50.0 * (1.0 + m)]
    p = np.percentile(x, q)
    return Interval(float(p[0]), (float(p[1]), float(p[2])), (float(p[3]), float(p[4])))


@dataclass(frozen=True)
class PosteriorOptimum:
    """Uncertainty of the single-level optimum over posterior samples.

    cell_size : Interval of the optimal cubic cell side h* (scene units).
    total_cells : Interval of ``V / h*^3``.
    resolution : (3,) ints at the median h*; resolution_ci68 / resolution_ci95 :
        ``(low, high)`` resolutions at the interval ends of h*.
    ns_per_ray : Interval of the predicted time at ``resolution`` over the samples (ns).
    penalty : ``E_s[T_med(h_s)] / T_med(h_med) - 1``: expected relative cost, under the
        median constants, of using a resolution drawn from the posterior.
    regret : ``E_s[T_s(h_med) / T_s(h_s)] - 1``: expected relative loss of the median
        choice when a sample is the truth.
    """

    n_samples: int
    cell_size: Interval
    total_cells: Interval
    resolution: tuple
    resolution_ci68: tuple
    resolution_ci95: tuple
    ns_per_ray: Interval
    penalty: float
    regret: float


def _check_samples(**arrays):
    out = {}
    size = None
    for name, a in arrays.items():
        x = np.asarray(a, dtype=np.float64).reshape(-1)
        if x.size == 0 or not np.all(np.isfinite(x)):
            raise ValueError(f"{name} samples must be a non-empty finite array")
        if size is not None and x.size != size:
            raise ValueError(f"{name} has {x.size} samples, expected {size}")
        size = x.size
        out[name] = x
    if np.any(out["t_step"] <= 0) or np.any(out["t_int"] <= 0):
        raise ValueError("t_step and t_int samples must be > 0")
    if np.any(out["t_setup"] < 0):
        raise ValueError("t_setup samples must be >= 0")
    return out


def posterior_optimum(stats: SceneStats, t_setup, t_step, t_int, *, terms: Terms | None = None,
                      overlap="exact", use_jax=True) -> PosteriorOptimum:
    """Evaluate the single-level optimum over posterior samples.

    Parameters
    ----------
    stats : SceneStats.
    t_setup, t_step, t_int : (S,) float64 posterior samples (ns).
    terms : model terms (from :func:`models.effects.select_effects`); default all, no mailbox.
    overlap : "exact" or "bbox".
    use_jax : vectorise with ``jax.vmap`` (float64); False uses numpy broadcasting.
    """
    if terms is None:
        terms = Terms()
    s = _check_samples(t_setup=t_setup, t_step=t_step, t_int=t_int)
    ts, tt, ti = s["t_setup"], s["t_step"], s["t_int"]
    med = (float(np.median(ts)), float(np.median(tt)), float(np.median(ti)))
    kw = dict(terms=terms, overlap=overlap)
    kw_poly = dict(mailbox=terms.mailbox, overlap=overlap, edge=terms.edge, area=terms.area)
    a0, b0, c0 = cubic_coefficients(stats, 1.0, **kw_poly)
    a0, b0, c_vol = float(a0), float(b0), float(stats.volume)
    c_r = float(c0) - c_vol  # the part of c proportional to r (bbox volume term)
    # termination's coefficients, each proportional to r (zero when rays never stop)
    k4, k3, k2 = (float(x) for x in termination_coefficients(stats, 1.0, terms.traversed_fraction, **kw_poly))

    def optimum(r, xp=np):
        return solve_cell_quartic(a0 * r, b0 * r, c_vol + c_r * r, k4 * r, k3 * r, k2 * r, xp=xp)

    h_med = float(optimum(med[2] / med[1]))

    def per_sample(xp, t0, t1, t2):
        r = t2 / t1
        h = optimum(r, xp=xp)
        t_own = cost_cubic(stats, h, t0, t1, t2, xp=xp, **kw)  # sample truth, own optimum
        t_at_med = cost_cubic(stats, h_med, t0, t1, t2, xp=xp, **kw)  # sample truth, median choice
        t_med_at_h = cost_cubic(stats, h, med[0], med[1], med[2], xp=xp, **kw)  # median truth, sample choice
        return h, t_own, t_at_med, t_med_at_h

    if use_jax:
        import jax
        import jax.numpy as jnp

        with jax.enable_x64(True):
            f = jax.jit(jax.vmap(lambda a, b, c: per_sample(jnp, a, b, c)))
            h, t_own, t_at_med, t_med_at_h = (np.asarray(x) for x in f(ts, tt, ti))
    else:
        h, t_own, t_at_med, t_med_at_h = per_sample(np, ts, tt, ti)
    t_med_best = float(cost_cubic(stats, h_med, *med, **kw))
    cell = summarise(h)
    cells = summarise(stats.volume / h ** 3)

    def res(hh):
        return cells_to_resolution(stats.volume / hh ** 3, stats.extent)

    resolution = res(h_med)
    # Larger h -> fewer cells: the low-resolution end is the high end of h.
    ci68 = (res(cell.ci68[1]), res(cell.ci68[0]))
    ci95 = (res(cell.ci95[1]), res(cell.ci95[0]))
    ns = _predict_many(stats, resolution, ts, tt, ti, terms, overlap)
    return PosteriorOptimum(
        n_samples=int(ts.size), cell_size=cell, total_cells=cells, resolution=resolution,
        resolution_ci68=ci68, resolution_ci95=ci95, ns_per_ray=summarise(ns),
        penalty=float(np.mean(t_med_at_h) / t_med_best - 1.0),
        regret=float(np.mean(t_at_med / t_own) - 1.0))


def discrete_posterior_optimum(costs, median_costs, cells) -> tuple[tuple[int, int], float]:
    """The optimum over a fixed set of K candidate grids, under posterior uncertainty.

    For a cost with no closed-form optimum (e.g. with the memory effect): each
    posterior sample picks its cheapest candidate.

    costs : (S, K) cost per ray of candidate k under sample s; median_costs : (K,) the
    same under the median constants; cells : (K,) each candidate's cell count.
    Returns ((k_low, k_high), penalty): the candidates at the 2.5th and 97.5th
    percentiles of the samples' chosen cell counts (nearest in cells), and the
    expected relative excess of a sample's choice under the median constants, as
    :func:`posterior_optimum`'s ``penalty``.
    """
    costs = np.atleast_2d(np.asarray(costs, dtype=np.float64))
    med = np.asarray(median_costs, dtype=np.float64).reshape(-1)
    cells = np.asarray(cells, dtype=np.float64).reshape(-1)
    if costs.shape[1] != med.size or med.size != cells.size or med.size == 0:
        raise ValueError(f"costs {costs.shape}, median_costs {med.shape} and cells {cells.shape} disagree")
    if not (np.all(np.isfinite(costs)) and np.all(np.isfinite(med)) and np.all(cells > 0)):
        raise ValueError("costs must be finite and cells > 0")
    best = np.argmin(costs, axis=1)
    lo, hi = np.percentile(cells[best], [2.5, 97.5])
    pick = lambda c: int(np.argmin(np.abs(np.log(cells) - np.log(c))))  # noqa: E731
    penalty = float(np.mean(med[best]) / float(np.min(med)) - 1.0)
    return (pick(lo), pick(hi)), penalty


def _predict_many(stats, resolution, ts, tt, ti, terms, overlap):
    """predict_uniform over many samples: the counts do not depend on the constants."""
    _, steps, tests = predict_uniform(stats, resolution, 0.0, 1.0, 1.0, overlap=overlap, terms=terms)
    return ts + tt * steps + ti * tests


def posterior_ns(steps, tests, t_setup, t_step, t_int, subgrids=0.0, t_sub=None) -> Interval:
    """Interval of predicted ns per ray for fixed expected counts (e.g. a nested plan's counts).

    steps, tests, subgrids : floats per ray; t_* : (S,) samples (t_sub optional).
    """
    s = _check_samples(t_setup=t_setup, t_step=t_step, t_int=t_int)
    t = s["t_setup"] + s["t_step"] * steps + s["t_int"] * tests
    if t_sub is not None:
        sub = np.asarray(t_sub, dtype=np.float64).reshape(-1)
        if sub.size != t.size or not np.all(np.isfinite(sub)):
            raise ValueError("t_sub samples must be finite and match the other samples")
        t = t + sub * subgrids
    return summarise(t)

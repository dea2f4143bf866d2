"""Fit per-operation costs to batch timings: nlopt maximum a posteriori, then emcee.

Model
-----
Configuration j (a scene, a resolution, a ray set) is a batch with exact counts
from the instrumented kernel: ``rays_j``, ``steps_j`` (cells stepped),
``tests_j`` (ray/triangle tests) and ``subgrids_j`` (subgrids entered), all
batch totals. Its median batch time is

    mu_j = rays_j*T_setup + steps_j*T_step + tests_j*T_int + subgrids_j*T_sub   (ns)

(plus ``misses_j*T_mem``, ``visits_j*T_visit`` and ``hits_j*T_hit`` when the design carries
those counts: cache lines fetched from beyond the cache, occupied cells entered, rays that
found a hit), and repeat k is ``y_jk = mu_j * exp(u_j + e_jk)``: multiplicative noise, so
every constant is fitted as its logarithm (positive by construction) and
residuals are relative. Two noise terms:

- ``e_jk``, repeat-to-repeat noise, variance ``sigma_j^2`` per configuration.
  The per-configuration sample variance ``s_j^2`` of ``log y_jk`` is shrunk
  toward the pooled variance with ``NOISE_PRIOR_DOF`` pseudo-repeats (a
  scaled-inverse-chi^2 prior; Gelman et al., *Bayesian Data Analysis*, 3rd ed.,
  sec. 3.3), and ``sigma_j`` is integrated out: the mean log time of
  configuration j then follows a Student-t with ``K_j - 1 + NOISE_PRIOR_DOF``
  degrees of freedom and scale ``sqrt(s_shrunk_j^2 / K_j)``. Configurations
  with few repeats thus weigh less and have heavier tails.
- ``u_j``, model misfit shared by all repeats of a configuration (cache
  effects, branch prediction: anything the four counts do not explain), with
  one fitted scale ``tau`` (log units, i.e. relative). It is added in
  quadrature to the t scale: ``scale_j^2 = s_shrunk_j^2 / K_j + tau^2``.
  Without ``tau`` many repeats of badly modelled batches would give confident
  wrong intervals; with it, intervals widen as the model fits worse.

Priors: each ``log T`` uniform on a box set by the data (no term may exceed
``PRIOR_UPPER_FACTOR`` times the fastest batch it appears in, and the box spans
``PRIOR_RANGE_DECADES`` decades below that), except the optional terms T_visit and T_hit,
flat in ``T`` on the same box (``FLAT_PRIOR_NAMES``); ``tau`` half-normal
with scale ``TAU_PRIOR_SCALE``. ``mu_j`` is the *median* batch time (``exp`` of the mean
log time), which is what the protocol reports.

Procedure
---------
1. Validate the design and detect ill-posed ones: too few configurations,
   collinear count columns, repeats with zero spread (``ValueError``).
2. nlopt: a bounded global search (CRS2 with local mutation, seeded with
   ``nlopt.srand``) from a weighted-least-squares start, then a local L-BFGS
   polish with the analytic gradient. A term whose share of every batch time
   is negligible at the optimum is reported as not identified (``ValueError``).
3. emcee from the optimum: walkers in a small ball, differential-evolution
   moves, a vectorised numpy log-probability, run in chunks until the chain is at least
   ``AUTOCORR_TOL`` integrated autocorrelation times long (emcee's
   ``get_autocorr_time(tol=...)``) and the acceptance fraction is in
   ``ACCEPTANCE_RANGE``; past ``max_steps`` a :class:`ConvergenceError`
   carrying the estimate is raised. An unconverged posterior is never returned.
4. A constant whose 95% interval spans more than ``MAX_CI95_DECADES`` decades
   is reported as not identified (``ValueError``): such an interval is the
   prior's box, not a measurement (e.g. T_step near 0).
5. Summaries of each constant and ``r = T_int / T_step``: median, central 68%
   and 95% intervals of the thinned posterior.

Everything is deterministic given ``seed``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import emcee
import nlopt
import numpy as np

__all__ = [
    "AUTOCORR_TOL",
    "COUNT_KEYS",
    "CONSTANT_NAMES",
    "ConvergenceError",
    "FitResult",
    "fit",
    "holdout_error",
    "cross_validated_errors",
    "log_posterior_gain",
    "maximum_a_posteriori",
    "predict_batch_times",
    "prepare_design",
    "split_design",
    "summarize",
]

# Count column in a design -> the constant (ns per unit) it multiplies.
# ``misses`` is the memory effect's count (models/memory.py): cache lines fetched from
# beyond the cache; ``visits`` the occupied cells entered (cells holding triangles, part
# of ``steps``), whose tests start a new run of packs; ``hits`` the rays that found a hit
# (what a ray does when it finds one: the winning test's last stage, the hit recorded).
# Each is fitted only when a design carries it.
COUNT_KEYS = ("rays", "steps", "tests", "subgrids", "misses", "visits", "hits")
CONSTANT_NAMES = ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "t_mem_ns", "t_visit_ns", "t_hit_ns")
RATIO_NAME = "ratio"
CONSTANT_LABELS = {
    "t_setup_ns": "T_setup",
    "t_step_ns": "T_step",
    "t_int_ns": "T_int",
    "t_sub_ns": "T_sub",
    "t_mem_ns": "T_mem",
    "t_visit_ns": "T_visit",
    "t_hit_ns": "T_hit",
}
# Columns that must be present; subgrids is optional (uniform grids only).
REQUIRED_COUNT_KEYS = ("rays", "steps", "tests")

# --- noise model -----------------------------------------------------------
# Pseudo-repeats of the pooled variance added to each configuration's own
# (scaled-inverse-chi^2 prior, Gelman et al. BDA3 sec. 3.3). 4 keeps a
# configuration with 3 repeats from being trusted blindly.
NOISE_PRIOR_DOF = 4.0
# Degrees of freedom standing for "Gaussian" when no repeat variance exists.
GAUSSIAN_DOF = 1e9
# Half-normal prior scale of the misfit scatter tau (log units = relative):
# 0.2 allows 20% unexplained per-configuration error without favouring it.
TAU_PRIOR_SCALE = 0.2
# Hard upper bound of tau (log units): a factor e of misfit is a broken model.
TAU_MAX = 1.0

# --- priors on the constants -------------------------------------------------
# Upper bound of T_p: this factor times min_j(median time_j / count_jp), i.e.
# no term may exceed the whole batch it appears in by more than this factor.
PRIOR_UPPER_FACTOR = 10.0
# The log-uniform prior spans this many decades below the upper bound.
PRIOR_RANGE_DECADES = 8.0
# Terms whose cost may be 0 with a prior flat in T itself (on the same box), not in log T.
# A log-uniform prior gives every decade below the data's reach the same mass, so a term
# the data put at a few ns but cannot tell from 0 at the 5% level gets most of its
# posterior at 1e-5 ns; flat in T, it keeps the data's shape.  (T_mem keeps the
# log-uniform prior it was validated with.)
FLAT_PRIOR_NAMES = ("t_visit_ns", "t_hit_ns")

# --- ill-posed designs -------------------------------------------------------
# Condition number of the column-normalised relative design matrix above
# which count columns are treated as collinear (double precision leaves ~1e-8
# relative accuracy after squaring; 1e7 flags near-exact proportionality).
COLLINEAR_CONDITION_MAX = 1e7
# A term explaining less than this share of every batch time at the optimum
# is not identified by the design (T near 0, or its count too small).
MIN_TERM_SHARE = 1e-3
# Condition number above which error messages point at near-collinear counts.
CONDITION_HINT = 1e2
# A constant whose 95% interval spans more than this many decades is not
# identified: the posterior is the prior's box, not a measurement.
MAX_CI95_DECADES = 2.0
# Relative spread (sd of log time) under which repeats count as identical.
ZERO_SPREAD_REL = 1e-12

# A column takes part in a collinearity when its weight in the smallest
# singular vector exceeds this fraction of the largest weight.
INVOLVED_COMPONENT_FRACTION = 0.1

# --- optimiser ---------------------------------------------------------------
# Range of the least-squares start of tau (log units).
START_TAU_MIN = 1e-3
START_TAU_MAX = 0.5
# An optimum within this fraction of the prior box from its lower end counts
# as "at the bound" (the constant wants to be smaller than the prior allows).
AT_BOUND_FRACTION = 1e-6
GLOBAL_MAXEVAL = 1000
LOCAL_MAXEVAL = 2000
LOCAL_FTOL_REL = 1e-12

# --- sampler -------------------------------------------------------------------
N_WALKERS = 32
# Initial ball radius around the optimum, log units (relative).
BALL_SCALE = 1e-3
# Chain must be this many integrated autocorrelation times long (emcee docs:
# "Autocorrelation analysis & convergence" recommend N > 50 tau).
AUTOCORR_TOL = 50.0
# Shortest chain accepted at all, in tau (emcee's integrated_time documents
# estimates from shorter chains as unreliable; quick checks only).
MIN_AUTOCORR_TOL = 20.0
# Burn-in discarded, in autocorrelation times (emcee docs suggest a few tau).
BURN_IN_TAU = 5.0
# Thinning, in autocorrelation times (emcee docs: about tau / 2).
THIN_TAU = 0.5
DE_MOVE_WEIGHT = 0.8
FIRST_CHUNK_STEPS = 600
MIN_CHUNK_STEPS = 200
# Safety factor on the chain length the current tau estimate asks for.
CHUNK_MARGIN = 1.15
MAX_STEPS_DEFAULT = 20000
# Sane mean acceptance fraction (Foreman-Mackey et al. 2013, sec. 4: "between
# 0.2 and 0.5"; widened since bounded posteriors reject more).
ACCEPTANCE_RANGE = (0.1, 0.8)

# Central interval probabilities (percent).
CI68_PERCENT = (15.865525393145708, 84.13447460685429)
CI95_PERCENT = (2.5, 97.5)


class ConvergenceError(RuntimeError):
    """The MCMC chain did not converge within the step cap.

    tau : (P+1,) float, last integrated autocorrelation time estimate (steps)
    n_steps : int, chain length reached
    acceptance : float, mean acceptance fraction
    """

    def __init__(self, message: str, tau, n_steps: int, acceptance: float):
        super().__init__(message)
        self.tau = np.asarray(tau, dtype=float)
        self.n_steps = int(n_steps)
        self.acceptance = float(acceptance)


@dataclass
class FitResult:
    """Posterior summary of a fit.

    constants : dict name -> {"median": float, "ci68": (lo, hi), "ci95": (lo, hi)},
        names ``t_setup_ns``, ``t_step_ns``, ``t_int_ns``, ``t_sub_ns``, ``t_mem_ns``,
        ``t_visit_ns``, ``t_hit_ns`` (ns per ray, step, test, subgrid entry, cache line
        beyond the cache, occupied cell entered, ray that hits) and
        ``ratio`` (T_int / T_step, dimensionless). ``t_sub_ns`` is None when the
        design has no subgrids, ``t_mem_ns`` when it has no ``misses``, ``t_visit_ns``
        when it has no ``visits``, ``t_hit_ns`` when it has no ``hits``
        (and any constant not fitted, see ``fit(required=...)``, is None).
    names : tuple of str, the fitted constants, columns of ``samples``.
    samples : (S, P) float, thinned posterior samples of the fitted constants, ns.
    tau_samples : (S,) float, posterior samples of the misfit scatter (log units).
    diagnostics : dict, JSON-ready: acceptance, autocorrelation times, chain
        length, burn-in, thinning, converged (always True), scatter summary, ...
    mle : dict name -> float, the optimum (ns; ``extra_scatter`` in log units).
    """

    constants: dict
    names: tuple
    samples: np.ndarray
    tau_samples: np.ndarray
    diagnostics: dict
    mle: dict
    seed: int = 0
    n_configs: int = 0

    def ratio_samples(self) -> np.ndarray:
        """(S,) posterior samples of r = T_int / T_step."""
        i_int = self.names.index("t_int_ns")
        i_step = self.names.index("t_step_ns")
        return self.samples[:, i_int] / self.samples[:, i_step]


# ---------------------------------------------------------------------------
# Design preparation
# ---------------------------------------------------------------------------


@dataclass
class PreparedDesign:
    """Validated design and its sufficient statistics.

    names : tuple of str, fitted constants (P,).
    counts : (J, P) float, batch-total counts for the fitted constants.
    log_mean : (J,) float, mean of log batch time (ns) per configuration.
    scale2 : (J,) float, squared t scale of log_mean from repeat noise.
    dof : (J,) float, t degrees of freedom per configuration.
    n_repeats : (J,) int.
    pooled_sd : float or None, pooled within-configuration sd of log time.
    condition : float, condition number of the column-normalised relative design.
    """

    names: tuple
    counts: np.ndarray
    log_mean: np.ndarray
    scale2: np.ndarray
    dof: np.ndarray
    n_repeats: np.ndarray
    pooled_sd: float | None
    condition: float


def _as_times(times, n_configs: int) -> list[np.ndarray]:
    """times_ns -> list of J 1-D float arrays (rows may differ in length)."""
    if isinstance(times, np.ndarray) and times.ndim == 2:
        rows = [times[j] for j in range(times.shape[0])]
    else:
        try:
            rows = [np.atleast_1d(np.asarray(r, dtype=float)) for r in times]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"times_ns must be a (J, K) array or J sequences of numbers: {exc}") from exc
    if len(rows) != n_configs:
        raise ValueError(f"times_ns has {len(rows)} rows but the counts have {n_configs} configurations")
    out = []
    for j, r in enumerate(rows):
        r = np.asarray(r, dtype=float)
        if r.ndim != 1 or r.size == 0:
            raise ValueError(f"times_ns row {j} must be a non-empty 1-D list of values")
        if not np.all(np.isfinite(r)):
            raise ValueError(f"times_ns row {j} contains NaN or infinity")
        if np.any(r <= 0):
            raise ValueError(f"times_ns row {j} contains a non-positive time (times must be > 0 ns)")
        out.append(r)
    return out


def _count_column(design: Mapping, key: str) -> np.ndarray:
    try:
        col = np.asarray(design[key], dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"count column {key!r} is not numeric: {exc}") from exc
    if col.ndim != 1:
        raise ValueError(f"count column {key!r} must be 1-D, got shape {col.shape}")
    if not np.all(np.isfinite(col)):
        raise ValueError(f"count column {key!r} contains NaN or infinity")
    if np.any(col < 0):
        j = int(np.flatnonzero(col < 0)[0])
        raise ValueError(f"count column {key!r} has a negative count ({col[j]:g}) in configuration {j}")
    return col


def prepare_design(design: Mapping, required: Sequence[str] = REQUIRED_COUNT_KEYS) -> PreparedDesign:
    """Validate a design and reduce it to per-configuration statistics.

    design : mapping with ``rays``, ``steps``, ``tests`` (J,) batch totals,
        optional ``subgrids``, ``misses``, ``visits`` and ``hits`` (J,), and ``times_ns``: a (J, K) array or J
        sequences of repeat values (ns per batch, > 0).

    required : count columns that must be present and non-zero somewhere
        (``rays`` always is). Any other column is fitted only when some
        configuration has a non-zero count: by default T_sub only when a
        subgrid is entered; an isolating suite passes ``required=("rays",)``
        to fit e.g. T_setup and T_step from empty grids alone.
    Raises ValueError naming the problem for malformed or ill-posed designs.
    """
    if not isinstance(design, Mapping):
        raise ValueError("design must be a mapping of count columns and times_ns")
    required = tuple(dict.fromkeys(("rays",) + tuple(required)))
    for key in required:
        if key not in COUNT_KEYS:
            raise ValueError(f"unknown count column {key!r} (known: {', '.join(COUNT_KEYS)})")
    for key in required + ("times_ns",):
        if key not in design:
            raise ValueError(f"design is missing {key!r}")
    cols = {k: _count_column(design, k) for k in COUNT_KEYS if k in design and design[k] is not None}
    n_configs = cols["rays"].shape[0]
    for k, c in cols.items():
        if c.shape[0] != n_configs:
            raise ValueError(f"count column {k!r} has {c.shape[0]} entries, 'rays' has {n_configs}")
    if np.any(cols["rays"] <= 0):
        j = int(np.flatnonzero(cols["rays"] <= 0)[0])
        raise ValueError(f"configuration {j} has no rays; every batch must trace at least one ray")
    times = _as_times(design["times_ns"], n_configs)

    keys = [k for k in COUNT_KEYS if k in cols and (k in required or np.any(cols[k] > 0))]
    names = tuple(CONSTANT_NAMES[COUNT_KEYS.index(k)] for k in keys)
    counts = np.stack([cols[k] for k in keys], axis=1)
    n_params = len(names)

    for k, name in zip(keys, names):
        if not np.any(cols[k] > 0):
            raise ValueError(f"count column {k!r} is zero in every configuration: {CONSTANT_LABELS[name]} cannot be fitted")
    if n_configs == 1:
        raise ValueError(
            f"a single configuration cannot separate {n_params} constants; "
            f"measure at least {n_params + 1} configurations with different counts"
        )
    if n_configs < n_params + 1:
        raise ValueError(
            f"{n_configs} configurations cannot fit {n_params} constants and a scatter term; "
            f"measure at least {n_params + 1} configurations with different counts"
        )

    log_rows = [np.log(r) for r in times]
    n_rep = np.array([r.size for r in log_rows])
    log_mean = np.array([r.mean() for r in log_rows])
    var = np.array([r.var(ddof=1) if r.size > 1 else np.nan for r in log_rows])
    zero = np.flatnonzero((n_rep > 1) & (np.sqrt(np.nan_to_num(var, nan=1.0)) < ZERO_SPREAD_REL))
    if zero.size:
        listed = ", ".join(str(int(j)) for j in zero[:5]) + (" ..." if zero.size > 5 else "")
        raise ValueError(
            f"zero variance: repeats of configuration(s) {listed} are identical; "
            "the timer is too coarse or values were copied, so the noise cannot be estimated"
        )

    condition = _check_collinear(counts / np.exp(log_mean)[:, None], keys)

    has_rep = n_rep > 1
    if np.any(has_rep):
        dof_within = n_rep[has_rep] - 1
        pooled_var = float(np.sum(dof_within * var[has_rep]) / np.sum(dof_within))
        own = np.where(has_rep, (n_rep - 1) * np.nan_to_num(var), 0.0)
        shrunk = (own + NOISE_PRIOR_DOF * pooled_var) / (n_rep - 1 + NOISE_PRIOR_DOF)
        scale2 = shrunk / n_rep
        dof = n_rep - 1 + NOISE_PRIOR_DOF
        pooled_sd = math.sqrt(pooled_var)
    else:
        # No repeats anywhere: all noise goes into tau.
        scale2 = np.zeros(n_configs)
        dof = np.full(n_configs, GAUSSIAN_DOF)
        pooled_sd = None
    return PreparedDesign(names, counts, log_mean, scale2, dof.astype(float), n_rep, pooled_sd, condition)


def _check_collinear(rel_counts: np.ndarray, keys: Sequence[str]) -> float:
    """Raise ValueError when count columns are (nearly) linearly dependent.

    rel_counts : (J, P) counts divided by each configuration's median time, so
        rows are weighted as the multiplicative noise weighs them.
    """
    norms = np.linalg.norm(rel_counts, axis=0)
    a = rel_counts / norms
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    cond = sv[0] / sv[-1] if sv[-1] > 0 else math.inf
    if cond > COLLINEAR_CONDITION_MAX:
        v = np.abs(vt[-1])
        involved = [keys[i] for i in np.flatnonzero(v > INVOLVED_COMPONENT_FRACTION * v.max())]
        what = ", ".join(involved[:-1]) + " and " + involved[-1] if len(involved) > 1 else involved[0]
        consts = ", ".join(CONSTANT_LABELS[CONSTANT_NAMES[COUNT_KEYS.index(k)]] for k in involved)
        raise ValueError(
            f"collinear counts: {what} are (nearly) proportional across configurations "
            f"(condition number {cond:.3g}), so {consts} cannot be separated; "
            "add configurations in which these counts vary independently"
        )
    return float(cond)


def _condition_hint(prep: PreparedDesign) -> str:
    if prep.condition > CONDITION_HINT:
        return (
            f" (the count columns are nearly collinear: condition number {prep.condition:.3g}; "
            "vary steps and tests per ray independently)"
        )
    return ""


# ---------------------------------------------------------------------------
# Log posterior
# ---------------------------------------------------------------------------


def _bounds(prep: PreparedDesign) -> tuple[np.ndarray, np.ndarray]:
    """Box of the log-uniform priors, (P,) lower and upper log(ns)."""
    med = np.exp(prep.log_mean)[:, None]
    with np.errstate(divide="ignore"):
        per_unit = np.where(prep.counts > 0, med / prep.counts, np.inf)
    hi = np.log(PRIOR_UPPER_FACTOR * per_unit.min(axis=0))
    lo = hi - PRIOR_RANGE_DECADES * math.log(10.0)
    return lo, hi


class _LogPosterior:
    """Vectorised log posterior over theta = (log T_1..log T_P, tau).

    Called on (W, P+1) arrays, returns (W,) log densities (-inf outside the
    support). ``value_and_grad`` serves nlopt on a single (P+1,) point.
    """

    def __init__(self, prep: PreparedDesign, priors: Mapping | None = None):
        self.x = prep.counts
        self.ybar = prep.log_mean
        self.v = prep.scale2
        self.nu = prep.dof
        self.lo, self.hi = _bounds(prep)
        self.n_params = prep.counts.shape[1]
        self.xt = np.ascontiguousarray(prep.counts.T)
        self.half_nu1 = 0.5 * (self.nu + 1.0)
        self.half_inv_tau_prior2 = 0.5 / TAU_PRIOR_SCALE**2
        self.lower = np.append(self.lo, 0.0)
        self.upper = np.append(self.hi, TAU_MAX)
        self.norm = np.sum(
            _lgamma_half(self.nu + 1.0) - _lgamma_half(self.nu) - 0.5 * np.log(np.pi * self.nu)
        )
        # Optional log-normal priors: (P,) centres (log ns) and inverse variances (0: none).
        self.prior_mu = np.zeros(self.n_params)
        self.prior_prec = np.zeros(self.n_params)
        for name, (median_ns, sigma_log) in (priors or {}).items():
            if name not in prep.names:
                continue
            p = list(prep.names).index(name)
            self.prior_mu[p] = math.log(median_ns)
            self.prior_prec[p] = 1.0 / sigma_log**2
        self.has_priors = bool(self.prior_prec.any())
        # Optional terms: prior flat in T itself, i.e. + log T in log-parameters.
        self.flat = np.array([1.0 if name in FLAT_PRIOR_NAMES else 0.0 for name in prep.names])
        self.has_flat = bool(self.flat.any())

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(theta)
        # Outside the box iff some coordinate is below its lower or above its upper bound.
        ok = np.maximum(self.lower - theta, theta - self.upper).max(axis=1) <= 0.0
        all_ok = bool(ok.all())
        if not all_ok:
            if not ok.any():
                return np.full(theta.shape[0], -np.inf)
            theta = theta[ok]
        tau2 = theta[:, -1] * theta[:, -1]
        r = self.ybar - np.log(np.exp(theta[:, :-1]) @ self.xt)  # (W, J) log residuals
        s2 = self.v + tau2[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):  # s2 = 0: -inf below
            ll = self.half_nu1 * np.log1p(r * r / (self.nu * s2)) + 0.5 * np.log(s2)
        val = self.norm - ll.sum(axis=1) - self.half_inv_tau_prior2 * tau2
        if self.has_priors:
            dev = theta[:, :-1] - self.prior_mu
            val = val - 0.5 * (dev * dev * self.prior_prec).sum(axis=1)
        if self.has_flat:
            val = val + theta[:, :-1] @ self.flat
        if all_ok:
            out = val
        else:
            out = np.full(ok.shape[0], -np.inf)
            out[ok] = val
        out[~np.isfinite(out)] = -np.inf
        return out

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """Log posterior and its gradient at one point (inside the box)."""
        log_t = theta[: self.n_params]
        tau = theta[self.n_params]
        t = np.exp(log_t)
        terms = self.x * t  # (J, P)
        mu = terms.sum(axis=1)
        r = self.ybar - np.log(mu)
        s2 = self.v + tau * tau
        if np.any(s2 <= 0.0):
            # No repeat noise and no scatter: the density is degenerate here.
            return -np.inf, np.zeros(theta.size)
        q = self.nu * s2 + r * r
        ll = -0.5 * (self.nu + 1.0) * np.log1p(r * r / (self.nu * s2)) - 0.5 * np.log(s2)
        val = ll.sum() + self.norm - 0.5 * (tau / TAU_PRIOR_SCALE) ** 2
        dll_dr = -(self.nu + 1.0) * r / q
        # dr/dlogT_p = -terms_jp / mu_j
        g_t = -(dll_dr[:, None] * terms / mu[:, None]).sum(axis=0)
        dll_ds2 = 0.5 * (self.nu + 1.0) * r * r / (s2 * q) - 0.5 / s2
        g_tau = np.sum(dll_ds2 * 2.0 * tau) - tau / TAU_PRIOR_SCALE**2
        if self.has_priors:
            dev = log_t - self.prior_mu
            val -= 0.5 * float((dev * dev * self.prior_prec).sum())
            g_t = g_t - dev * self.prior_prec
        if self.has_flat:
            val += float(log_t @ self.flat)
            g_t = g_t + self.flat
        return float(val), np.append(g_t, g_tau)


def _lgamma_half(x: np.ndarray) -> np.ndarray:
    """log Gamma(x / 2), elementwise, via math.lgamma."""
    return np.array([math.lgamma(0.5 * float(v)) for v in np.ravel(x)]).reshape(np.shape(x))


# ---------------------------------------------------------------------------
# Maximum a posteriori (nlopt)
# ---------------------------------------------------------------------------


def _least_squares_start(prep: PreparedDesign, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Relative least squares start: min sum_j (x_j . T / y_j - 1)^2, clipped into the box."""
    y = np.exp(prep.log_mean)
    a = prep.counts / y[:, None]
    t, *_ = np.linalg.lstsq(a, np.ones_like(y), rcond=None)
    floor = np.exp(0.5 * (lo + hi))
    t = np.where(t > 0, t, floor)
    log_t = np.clip(np.log(t), lo, hi)
    mu = prep.counts @ np.exp(log_t)
    resid_sd = float(np.std(prep.log_mean - np.log(mu)))
    tau = min(max(resid_sd, START_TAU_MIN), START_TAU_MAX)
    return np.append(log_t, tau)


#: What an nlopt run may raise when it stops early (the best point seen is kept):
#: roundoff, its generic failure (not a Python RuntimeError in every nlopt build).
NLOPT_STOPS = tuple({nlopt.RoundoffLimited, RuntimeError, getattr(nlopt, "runtime_error", RuntimeError)})


def _maximise(post: _LogPosterior, prep: PreparedDesign, seed: int) -> np.ndarray:
    """nlopt: bounded global search (GN_CRS2_LM) then L-BFGS polish; returns theta."""
    n = post.n_params + 1
    lower = np.append(post.lo, 0.0)
    upper = np.append(post.hi, TAU_MAX)
    best = {"f": -np.inf, "x": None}

    def objective(x, grad):
        x = np.clip(x, lower, upper)
        val, g = post.value_and_grad(x)
        if not np.isfinite(val):
            val, g = -np.finfo(float).max, np.zeros(n)
        if grad.size > 0:
            grad[:] = -g
        if val > best["f"]:
            best["f"], best["x"] = val, x.copy()
        return -val

    start = np.clip(_least_squares_start(prep, post.lo, post.hi), lower, upper)
    nlopt.srand(int(seed))
    glob = nlopt.opt(nlopt.GN_CRS2_LM, n)
    glob.set_lower_bounds(lower)
    glob.set_upper_bounds(upper)
    glob.set_min_objective(objective)
    glob.set_maxeval(GLOBAL_MAXEVAL)
    glob.set_ftol_rel(LOCAL_FTOL_REL)
    try:
        glob.optimize(start)
    except NLOPT_STOPS:
        pass
    for x0 in (best["x"], start):
        loc = nlopt.opt(nlopt.LD_LBFGS, n)
        loc.set_lower_bounds(lower)
        loc.set_upper_bounds(upper)
        loc.set_min_objective(objective)
        loc.set_maxeval(LOCAL_MAXEVAL)
        loc.set_ftol_rel(LOCAL_FTOL_REL)
        try:
            loc.optimize(np.asarray(x0, dtype=float))
        except NLOPT_STOPS:
            pass  # the best point seen so far is kept by the objective
    if best["x"] is None or not np.isfinite(best["f"]):
        raise ValueError("the likelihood has no finite maximum for this design")
    return best["x"]


def _check_identified(theta: np.ndarray, post: _LogPosterior, prep: PreparedDesign) -> None:
    """Raise ValueError for a constant the design cannot determine at the optimum."""
    t = np.exp(theta[: post.n_params])
    terms = post.x * t
    share = (terms / terms.sum(axis=1, keepdims=True)).max(axis=0)
    for p, name in enumerate(prep.names):
        if post.prior_prec[p] > 0:
            continue  # an informative prior identifies it
        label = CONSTANT_LABELS[name]
        at_floor = theta[p] <= post.lo[p] + AT_BOUND_FRACTION * (post.hi[p] - post.lo[p])
        if share[p] < MIN_TERM_SHARE or at_floor:
            raise ValueError(
                f"{label} is not identified: at the best fit its term is at most "
                f"{100 * share[p]:.2g}% of any batch time (threshold {100 * MIN_TERM_SHARE:.2g}%), "
                f"i.e. {label} is near 0 or its count too small in every configuration; "
                "add configurations where this term is a visible part of the time" + _condition_hint(prep)
            )


def _check_width(samples: np.ndarray, prep: PreparedDesign, names: Sequence[str] | None = None) -> None:
    """Raise ValueError for a constant whose 95% interval spans too many decades.

    samples : (S, P) of the constants ``names`` (default: all of ``prep.names``)."""
    lo, hi = np.percentile(samples, CI95_PERCENT, axis=0)
    decades = np.log10(hi / lo)
    for p, name in enumerate(prep.names if names is None else names):
        if decades[p] > MAX_CI95_DECADES:
            label = CONSTANT_LABELS[name]
            raise ValueError(
                f"{label} is not identified: its 95% interval [{lo[p]:.3g}, {hi[p]:.3g}] ns spans "
                f"{decades[p]:.1f} decades (limit {MAX_CI95_DECADES:g}), so the data say little beyond "
                f"'{label} is small'; add configurations where this term is a visible part of the time"
                + _condition_hint(prep)
            )


# ---------------------------------------------------------------------------
# Sampling (emcee)
# ---------------------------------------------------------------------------


def _sample(
    post: _LogPosterior, theta0: np.ndarray, seed: int, max_steps: int, n_walkers: int, autocorr_tol: float,
    prep: PreparedDesign | None = None, fail_fast: Sequence[int] = (), deadline: float | None = None,
):
    """Run emcee from a ball around theta0 until converged; returns (chain, info).

    fail_fast : parameter indices checked after every chunk: when the second half of the
    chain so far already gives one a 95% interval wider than MAX_CI95_DECADES, sampling
    stops with :func:`_check_width`'s ValueError instead of running on to a result that
    would be rejected.
    deadline : ``time.monotonic()`` by which the chain must have converged: after every
    chunk, a chain that the steps its tau estimate still asks for (at the pace of the steps
    so far) would take past it stops with ConvergenceError.
    """
    started = time.monotonic()
    n_dim = theta0.size
    rng = np.random.default_rng(seed)
    lower = np.append(post.lo, 0.0)
    upper = np.append(post.hi, TAU_MAX)
    ball = theta0 + BALL_SCALE * rng.standard_normal((n_walkers, n_dim))
    ball[:, -1] = np.abs(ball[:, -1])
    ball = np.clip(ball, lower, upper)
    # Differential-evolution moves (ter Braak 2006; ter Braak & Vrugt 2008 for
    # the snooker update), mixed as in emcee's "Moves" tutorial: on these
    # near-Gaussian posteriors tau is ~3x shorter than with the stretch move.
    moves = [(emcee.moves.DEMove(), DE_MOVE_WEIGHT), (emcee.moves.StretchMove(), 1.0 - DE_MOVE_WEIGHT)]
    sampler = emcee.EnsembleSampler(n_walkers, n_dim, post, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    state = ball
    n_steps = 0
    chunk = min(FIRST_CHUNK_STEPS, max_steps)
    tau = np.full(n_dim, np.nan)
    while True:
        state = sampler.run_mcmc(state, chunk, progress=False)
        n_steps += chunk
        if fail_fast:
            half = np.exp(sampler.get_chain(discard=n_steps // 2, flat=True)[:, list(fail_fast)])
            _check_width(half, prep, names=[prep.names[p] for p in fail_fast])
        acceptance = float(np.mean(sampler.acceptance_fraction))
        tau_all = sampler.get_autocorr_time(tol=0)
        burn = int(math.ceil(BURN_IN_TAU * np.max(tau_all)))
        converged = False
        if burn < n_steps:
            try:
                tau = sampler.get_autocorr_time(discard=burn, tol=autocorr_tol)
                converged = True
            except emcee.autocorr.AutocorrError as exc:
                tau = np.asarray(exc.tau)
        else:
            tau = tau_all
        acc_ok = ACCEPTANCE_RANGE[0] <= acceptance <= ACCEPTANCE_RANGE[1]
        if converged and acc_ok:
            break
        # Total length the current tau estimate asks for. Short chains tend
        # to underestimate tau, so exceeding the cap already is conclusive.
        wanted = burn + int(math.ceil(autocorr_tol * np.max(tau) * CHUNK_MARGIN))
        if converged or n_steps >= max_steps or wanted > max_steps:
            why = []
            if not converged:
                why.append(
                    f"after {n_steps} steps (burn-in {burn}) the chain is shorter than "
                    f"{autocorr_tol:g} autocorrelation times (tau = "
                    f"{np.array2string(np.asarray(tau), precision=1)} steps, so about {wanted} steps "
                    f"are needed, cap {max_steps})"
                )
            if not acc_ok:
                why.append(
                    f"the acceptance fraction {acceptance:.3f} is outside "
                    f"{ACCEPTANCE_RANGE[0]}..{ACCEPTANCE_RANGE[1]}"
                )
            raise ConvergenceError(
                "posterior not converged: " + "; ".join(why)
                + ". The design may be ill-posed (a wide, ridge-shaped posterior); "
                "add configurations or raise max_steps",
                tau,
                n_steps,
                acceptance,
            )
        if deadline is not None:  # the steps still wanted, at the pace of those so far
            left = deadline - time.monotonic()
            more = (time.monotonic() - started) / n_steps * max(wanted - n_steps, MIN_CHUNK_STEPS)
            if more > left:
                raise ConvergenceError(
                    f"posterior not converged in the time left for fitting: after {n_steps} steps "
                    f"(burn-in {burn}) about {wanted} are needed (tau = "
                    f"{np.array2string(np.asarray(tau), precision=1)} steps), {more:.1f} s more at "
                    f"this pace, {max(left, 0.0):.1f} s left",
                    tau,
                    n_steps,
                    acceptance,
                )
        chunk = int(min(max(wanted - n_steps, MIN_CHUNK_STEPS), max_steps - n_steps))
    thin = max(1, int(THIN_TAU * np.min(tau)))
    chain = sampler.get_chain(discard=burn, thin=thin, flat=True)
    info = {
        "acceptance": acceptance,
        "acceptance_min": float(np.min(sampler.acceptance_fraction)),
        "tau_steps": [float(v) for v in tau],
        "n_steps": n_steps,
        "n_walkers": n_walkers,
        "burn_in": burn,
        "thin": thin,
        "n_samples": int(chain.shape[0]),
        "autocorr_tol": float(autocorr_tol),
        "converged": True,
    }
    return chain, info


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------


def summarize(values: np.ndarray) -> dict:
    """Median and central 68% / 95% intervals of (S,) samples (floats)."""
    v = np.asarray(values, dtype=float)
    q = np.percentile(v, [50.0, *CI68_PERCENT, *CI95_PERCENT])
    return {
        "median": float(q[0]),
        "ci68": (float(q[1]), float(q[2])),
        "ci95": (float(q[3]), float(q[4])),
    }


def fit(
    design: Mapping,
    seed: int = 0,
    *,
    max_steps: int = MAX_STEPS_DEFAULT,
    n_walkers: int = N_WALKERS,
    autocorr_tol: float = AUTOCORR_TOL,
    required: Sequence[str] = REQUIRED_COUNT_KEYS,
    priors: Mapping | None = None,
    fail_fast: Sequence[str] = (),
    deadline: float | None = None,
) -> FitResult:
    """Fit T_setup, T_step, T_int (and T_sub, T_mem) to batch timings.

    design : mapping, see :func:`prepare_design`. Counts are batch totals,
        ``times_ns`` repeat times of each batch in ns.
    seed : int, seeds nlopt (``nlopt.srand``), the walker ball and emcee.
    max_steps : int, cap on the chain length; past it ConvergenceError.
    n_walkers : int, emcee walkers (>= 2 * (P + 1)).
    autocorr_tol : float, required chain length after burn-in in integrated
        autocorrelation times (emcee's ``tol``); at least MIN_AUTOCORR_TOL.
    required : count columns that must be fitted (see :func:`prepare_design`);
        constants of other all-zero columns, and ``ratio`` without both
        T_step and T_int, are None in ``constants``.
    priors : optional ``{name: (median_ns, sigma_log)}``: a log-normal prior on
        that constant (e.g. from an isolating microbenchmark), for a term that
        is too small a part of every batch to be identified by the batches alone.
    fail_fast : constants (e.g. an optional term) whose 95% interval is checked while
        sampling: one already too wide ends the fit early with the same ValueError.
    deadline : ``time.monotonic()`` by which the chain must converge; a chain whose
        remaining steps would run past it ends early with ConvergenceError (None: no limit).

    Returns a :class:`FitResult`. Raises ValueError for malformed or ill-posed
    designs (naming the problem) and ConvergenceError when the posterior does
    not converge within ``max_steps`` (or by ``deadline``).
    """
    prep = prepare_design(design, required)
    for name, spec in (priors or {}).items():
        if name not in CONSTANT_NAMES:
            raise ValueError(f"prior for unknown constant {name!r}")
        median_ns, sigma_log = spec
        if not (median_ns > 0 and math.isfinite(median_ns) and sigma_log > 0 and math.isfinite(sigma_log)):
            raise ValueError(f"prior for {name} needs a positive median and log-scale, got {spec!r}")
    post = _LogPosterior(prep, priors)
    n_dim = post.n_params + 1
    if not autocorr_tol >= MIN_AUTOCORR_TOL:
        raise ValueError(f"autocorr_tol = {autocorr_tol} is below {MIN_AUTOCORR_TOL}: the tau estimate itself is unreliable")
    if n_walkers < 2 * n_dim:
        raise ValueError(f"n_walkers = {n_walkers} must be at least {2 * n_dim} for {n_dim} parameters")
    theta = _maximise(post, prep, seed)
    _check_identified(theta, post, prep)
    try:
        chain, info = _sample(post, theta, seed, int(max_steps), int(n_walkers), float(autocorr_tol), prep,
                              [p for p, name in enumerate(prep.names) if name in fail_fast], deadline)
    except ConvergenceError as exc:
        exc.args = (exc.args[0] + _condition_hint(prep),)
        raise
    samples = np.exp(chain[:, : post.n_params])
    _check_width(samples, prep)
    tau_samples = chain[:, post.n_params]
    constants: dict = {name: None for name in CONSTANT_NAMES}
    for p, name in enumerate(prep.names):
        constants[name] = summarize(samples[:, p])
    result = FitResult(
        constants=constants,
        names=tuple(prep.names),
        samples=samples,
        tau_samples=tau_samples,
        diagnostics={},
        mle={name: float(np.exp(theta[p])) for p, name in enumerate(prep.names)},
        seed=int(seed),
        n_configs=int(prep.counts.shape[0]),
    )
    result.mle["extra_scatter"] = float(theta[-1])
    has_ratio = "t_int_ns" in prep.names and "t_step_ns" in prep.names
    constants[RATIO_NAME] = summarize(result.ratio_samples()) if has_ratio else None
    info.update(
        {
            "parameters": list(prep.names) + ["extra_scatter"],
            "extra_scatter": summarize(tau_samples),
            "pooled_repeat_sd": prep.pooled_sd,
            "design_condition": prep.condition,
            "n_configs": int(prep.counts.shape[0]),
            "n_values": int(prep.n_repeats.sum()),
            "seed": int(seed),
            "noise_model": "lognormal repeats (per-config variance shrunk to pooled, t marginal) + shared misfit scatter",
            "priors": {k: [float(v[0]), float(v[1])] for k, v in (priors or {}).items()},
        }
    )
    result.diagnostics = info
    return result


def maximum_a_posteriori(design: Mapping, seed: int = 0, *, required: Sequence[str] = REQUIRED_COUNT_KEYS,
                         priors: Mapping | None = None) -> tuple[dict, float]:
    """The posterior's maximum alone (the nlopt search of :func:`fit`, no sampling).

    Returns ({constant name: ns}, the maximum log posterior); cheap enough for
    leave-one-out cross-validation and for deciding whether a term is needed.
    """
    prep = prepare_design(design, required)
    post = _LogPosterior(prep, priors)
    theta = _maximise(post, prep, seed)
    return ({name: float(np.exp(theta[p])) for p, name in enumerate(prep.names)},
            float(post.value_and_grad(theta)[0]))


def log_posterior_gain(design: Mapping, column: str, seed: int = 0, *,
                       required: Sequence[str] = REQUIRED_COUNT_KEYS, priors: Mapping | None = None) -> float:
    """How much a count column's term raises the maximum of the log posterior.

    The maximum with ``column`` in the design minus the maximum without it
    (:func:`maximum_a_posteriori`), each without the ``log T`` of the flat priors
    (``FLAT_PRIOR_NAMES``; a log-uniform prior adds nothing over its box).  Twice the
    gain is then the likelihood-ratio statistic of the term, so a gain below 1.92
    means the timings do not reject the term's absence at the 5% level (chi-square
    with one degree of freedom).
    """
    if column not in design:
        raise ValueError(f"design has no column {column!r}")
    best = max_log_posterior(design, seed, required=required, priors=priors)
    return best - max_log_posterior({k: v for k, v in design.items() if k != column}, seed, required=required,
                                    priors=priors)


def max_log_posterior(design: Mapping, seed: int = 0, *, required: Sequence[str] = REQUIRED_COUNT_KEYS,
                      priors: Mapping | None = None) -> float:
    """The maximum of the log posterior (:func:`maximum_a_posteriori`) without the ``log T`` of
    the flat priors (``FLAT_PRIOR_NAMES``): a log-likelihood (plus the informative priors) that
    designs with the same terms and values can be compared by."""
    consts, value = maximum_a_posteriori(design, seed, required=required, priors=priors)
    return value - sum(math.log(v) for name, v in consts.items() if name in FLAT_PRIOR_NAMES)


def predict_batch_times(samples: np.ndarray, names: Sequence[str], design: Mapping) -> np.ndarray:
    """Median batch time for every posterior sample and configuration.

    samples : (S, P) float, constants in ns (columns ``names``).
    names : P constant names from CONSTANT_NAMES.
    design : mapping with the count columns of ``names`` ((J,) batch totals);
        a missing ``subgrids`` column counts as zero.
    Returns (S, J) predicted batch times, ns.
    """
    samples = np.atleast_2d(np.asarray(samples, dtype=float))
    if samples.shape[1] != len(names):
        raise ValueError(f"samples have {samples.shape[1]} columns but {len(names)} names")
    cols = []
    for name in names:
        if name not in CONSTANT_NAMES:
            raise ValueError(f"unknown constant {name!r}")
        key = COUNT_KEYS[CONSTANT_NAMES.index(name)]
        if key in design and design[key] is not None:
            cols.append(_count_column(design, key))
        elif key == "subgrids":
            cols.append(None)
        else:
            raise ValueError(f"design is missing {key!r}")
    n_configs = next(c.shape[0] for c in cols if c is not None)
    x = np.stack([c if c is not None else np.zeros(n_configs) for c in cols], axis=1)
    return samples @ x.T


def holdout_error(result: FitResult, design: Mapping) -> float:
    """Median absolute relative error of predicted vs measured batch times.

    result : a FitResult (fitted without these configurations).
    design : held-back configurations (counts and ``times_ns``).
    Prediction: median over posterior samples; measurement: median of repeats.
    Returns a float, e.g. 0.03 for 3%.
    """
    return float(np.median(holdout_errors(result, design)))


def holdout_errors(result: FitResult, design: Mapping) -> np.ndarray:
    """Absolute relative error of each held-back configuration, (J,) (see :func:`holdout_error`)."""
    pred = np.median(predict_batch_times(result.samples, result.names, design), axis=0)
    if "subgrids" in design and design["subgrids"] is not None and "t_sub_ns" not in result.names:
        if np.any(np.asarray(design["subgrids"]) > 0):
            raise ValueError("held-back configurations enter subgrids but T_sub was not fitted")
    times = _as_times(design["times_ns"], pred.shape[0])
    measured = np.array([np.median(r) for r in times])
    return np.abs(pred / measured - 1.0)


def _take(design: Mapping, idx) -> dict:
    """The configurations ``idx`` of a design (count columns and times; other keys as they are)."""
    out = {}
    for k, v in design.items():
        if k == "times_ns":
            out[k] = [np.asarray(design[k][int(i)], dtype=float) for i in idx]
        elif k in COUNT_KEYS and v is not None:
            out[k] = np.asarray(v)[idx]
        else:
            out[k] = v
    return out


def cross_validated_errors(design: Mapping, folds: int = 5, seed: int = 0, *,
                           required: Sequence[str] = REQUIRED_COUNT_KEYS, priors: Mapping | None = None) -> np.ndarray:
    """|predicted / measured - 1| of every configuration, each predicted by the posterior's
    maximum (:func:`maximum_a_posteriori`) fitted to the other folds.

    folds : number of folds (2 .. J); configurations are dealt to folds in a random
    order drawn from ``seed``.  Measured: the median of each configuration's repeats.
    Returns (J,) errors in configuration order.  Steadier than one held-back set: every
    configuration is predicted once, by a fit that did not see it.
    """
    n = len(np.asarray(design["rays"]))
    if not 2 <= int(folds) <= n:
        raise ValueError(f"folds must be from 2 to the {n} configurations, got {folds!r}")
    fold = np.empty(n, dtype=int)
    fold[np.random.default_rng(seed).permutation(n)] = np.arange(n) % int(folds)
    times = _as_times(design["times_ns"], n)
    errors = np.empty(n)
    for f in range(int(folds)):
        test = np.flatnonzero(fold == f)
        consts, _ = maximum_a_posteriori(_take(design, np.flatnonzero(fold != f)), seed, required=required,
                                         priors=priors)
        held = _take(design, test)
        pred = sum(v * _count_column(held, COUNT_KEYS[CONSTANT_NAMES.index(name)]) for name, v in consts.items())
        errors[test] = np.abs(pred / np.array([np.median(times[i]) for i in test]) - 1.0)
    return errors


def split_design(design: Mapping, holdout_fraction: float, rng: np.random.Generator):
    """Split a design's configurations into (fit_design, holdout_design).

    holdout_fraction : float in (0, 1), share of configurations held back
        (at least one, and at least one kept).
    rng : np.random.Generator choosing which.
    """
    if not 0.0 < holdout_fraction < 1.0:
        raise ValueError(f"holdout_fraction must be in (0, 1), got {holdout_fraction}")
    n = len(np.asarray(design["rays"]))
    n_hold = min(max(1, int(round(holdout_fraction * n))), n - 1)
    perm = rng.permutation(n)
    hold = np.sort(perm[:n_hold])
    keep = np.sort(perm[n_hold:])

    return _take(design, keep), _take(design, hold)

"""Measured sweeps of real traversal time over grid resolutions.

A :class:`GridSpec` names a grid without building it: a uniform grid's resolution, or
a nested grid's top resolution and how its subgrids are sized.  :func:`sweep` builds
several specs over one scene, counts their work on a ray batch with the instrumented
twin (:meth:`calibrate._grid.Grid.count`) and times the un-instrumented twin on the
same rays with :func:`calibrate.protocol.measure` (loop calibration, discarded
warm-ups, rounds in a random order so drift hits every spec alike).  The result per
spec is the median and MAD of ns per ray beside the counts per ray.

:func:`fit_minimum` puts a smooth curve (a quadratic in log time against log scale)
through the points near the lowest measured one, so the "measured best" of a sweep is
the curve's vertex, not merely the luckiest noisy point; :func:`penalty` is the
relative excess ``time(choice) / time(best) - 1``.

Subgrid sizing of a nested spec (``subgrids``):

``model``
    As ``calibrate predict`` plans it: :func:`models.nested.nested_counts` sizes each
    depth-1 subgrid from its own sub-scene for the ratio ``ratio`` (the general
    model's cubic optimum per cell) at the spec's top resolution, and with three levels
    each second-level cell's leaf grid the same way.  ``sub_scale`` multiplies every
    depth-1 subgrid's axes; the leaf grids of three levels are then sized by the model
    for the cells they get.
``rule``
    The kernel's rule: a cell with ``n > threshold`` references gets
    ``(scale n)^exponent`` cells (Manta's exponents unless ``exponents`` is given).
``fixed``
    Every subdivided cell gets ``levels[1]`` (only with 2 levels).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from . import protocol
from ._grid import DEFAULT_SUBDIVIDE_THRESHOLD, MANTA_SCALE, Grid, Scene, triangle_box_overlap

__all__ = [
    "GridSpec",
    "SWEEP_ROUNDS",
    "SWEEP_MIN_VALUE_NS",
    "SWEEP_BUILDS",
    "split_rounds",
    "MAX_SWEEP_CELLS",
    "scaled_resolutions",
    "measure_time_per_ray",
    "sweep",
    "best_point",
    "penalty",
    "fit_minimum",
]

#: Values (rounds) per spec and the minimum duration of one value (ns): shorter than a
#: calibration's (protocol.MIN_VALUE_NS_DEFAULT) since a sweep times many specs.
SWEEP_ROUNDS = 8
SWEEP_MIN_VALUE_NS = 10_000_000
SWEEP_WARMUPS = 1
#: Builds of every grid the values are spread over (see :func:`sweep`), and whether each
#: value is primed with one untimed call (see :func:`calibrate.protocol.measure`).
SWEEP_BUILDS = 4
SWEEP_PRIME = True
#: Whether a sweep's values have the host's common slowdown divided out (see :func:`sweep`).
SWEEP_DRIFT_OUT = True
#: A spec whose top level would exceed this many cells is not built (memory and time).
MAX_SWEEP_CELLS = 2 ** 25
#: A grid whose build would take more memory than this (bytes) is not built, and a sweep
#: stops building once its grids together hold MAX_SWEEP_TOTAL_BYTES (they are all kept
#: in memory to be timed interleaved).
MAX_SWEEP_MEMORY_BYTES = 2 ** 31
MAX_SWEEP_TOTAL_BYTES = 6 * 2 ** 30
#: fit_minimum: the quadratic goes through the points within this factor in scale of the
#: lowest one, and must agree with the lowest point within this relative difference (or
#: its noise, if larger).
FIT_HALF_SPAN = 2.0
FIT_AGREEMENT = 0.02
FIT_MIN_NEIGHBOURS = 2
#: The standard error of a median of n normal values is about this times sigma / sqrt(n).
MEDIAN_SE_FACTOR = math.sqrt(math.pi / 2.0)
#: Clocks a value may be read with (see Grid.timed_batch): the timing thread's CPU time leaves out
#: the time the thread waited for a core, so a busy host disturbs the values less.
CLOCKS = ("thread", "wall")
DEFAULT_CLOCK = "thread"
SUBGRID_MODES = ("model", "rule", "fixed")

_MODEL_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _res3(res) -> tuple[int, int, int]:
    r = tuple(int(x) for x in res)
    if len(r) != 3 or min(r) < 1:
        raise ValueError(f"a resolution needs three whole numbers >= 1, got {res!r}")
    return r


def scaled_resolutions(res, factors) -> list[tuple[int, int, int]]:
    """``res`` (nx, ny, nz) scaled per axis by each factor, rounded, every axis >= 1.

    res : three positive whole numbers; factors : iterable of positive numbers.
    Returns one resolution per factor, in the order given (duplicates kept).
    """
    base = np.asarray(_res3(res), dtype=np.float64)
    out = []
    for f in factors:
        f = float(f)
        if not (math.isfinite(f) and f > 0):
            raise ValueError(f"scale factors must be finite and > 0, got {f!r}")
        out.append(tuple(int(max(1, round(x * f))) for x in base))
    return out


@dataclass(frozen=True)
class GridSpec:
    """A grid to build: kind ``uniform`` or ``nested``.

    levels : per-axis resolutions, top first (a uniform grid has one; a nested grid
        has the top and, with ``subgrids='fixed'``, the subgrids' resolution; with
        ``model`` or ``rule`` a second entry is informative only, e.g. the median).
    depth : levels of a nested grid (>= 2; default ``len(levels)``, at least 2).
    subgrids : "model" | "rule" | "fixed" (module docstring); nested only.
    ratio : T_int / T_step the ``model`` subgrids are sized for.
    sub_scale : per-axis factor on the depth-1 subgrids (``model``) or their cells
        (``rule``: total cells times ``sub_scale^3``).
    scale, exponents, threshold : the kernel rule's constant, per-level exponents
        and the references a cell holds before it subdivides.
    label : a name for reports (not part of the spec's identity: equal specs are one grid).
    """

    kind: str
    levels: tuple
    depth: int | None = None
    subgrids: str = "model"
    ratio: float | None = None
    sub_scale: float = 1.0
    scale: float = MANTA_SCALE
    exponents: tuple | None = None
    threshold: int = DEFAULT_SUBDIVIDE_THRESHOLD
    label: str = field(default="", compare=False)

    def __post_init__(self):
        if self.kind not in ("uniform", "nested"):
            raise ValueError(f"GridSpec kind must be 'uniform' or 'nested', got {self.kind!r}")
        levels = tuple(_res3(r) for r in self.levels)
        if not levels:
            raise ValueError("GridSpec needs at least the top resolution in levels")
        object.__setattr__(self, "levels", levels)
        if self.exponents is not None:
            object.__setattr__(self, "exponents", tuple(float(e) for e in self.exponents))
        if self.kind == "uniform":
            if len(levels) != 1:
                raise ValueError(f"a uniform GridSpec has one resolution, got {len(levels)}")
            return
        depth = self.depth if self.depth is not None else max(2, len(levels))
        object.__setattr__(self, "depth", int(depth))
        if self.depth < 2:
            raise ValueError(f"a nested GridSpec needs depth >= 2, got {self.depth}")
        if self.subgrids not in SUBGRID_MODES:
            raise ValueError(f"unknown subgrids {self.subgrids!r}; choose one of {', '.join(SUBGRID_MODES)}")
        if self.subgrids == "model" and not (self.ratio is not None and self.ratio > 0):
            raise ValueError("subgrids='model' needs ratio = T_int / T_step > 0")
        if self.subgrids == "fixed" and (len(levels) != 2 or self.depth != 2):
            raise ValueError("subgrids='fixed' needs exactly two levels (top and subgrid resolution)")
        if not (math.isfinite(self.sub_scale) and self.sub_scale > 0):
            raise ValueError(f"sub_scale must be finite and > 0, got {self.sub_scale!r}")

    @property
    def top(self) -> tuple[int, int, int]:
        return self.levels[0]

    @property
    def top_cells(self) -> int:
        return self.top[0] * self.top[1] * self.top[2]

    def scaled(self, factor: float) -> "GridSpec":
        """Every level's per-axis resolution times ``factor`` (rounded, >= 1)."""
        levels = tuple(scaled_resolutions(r, [factor])[0] for r in self.levels)
        if self.kind == "uniform":
            return replace(self, levels=levels)
        return replace(self, levels=levels, sub_scale=self.sub_scale * float(factor))

    def to_dict(self) -> dict:
        d = dict(kind=self.kind, levels=[list(r) for r in self.levels], label=self.label)
        if self.kind == "nested":
            d.update(depth=self.depth, subgrids=self.subgrids, sub_scale=self.sub_scale, threshold=self.threshold)
            if self.subgrids == "model":
                d["ratio"] = self.ratio
            if self.subgrids == "rule":
                d.update(scale=self.scale, exponents=None if self.exponents is None else list(self.exponents))
        return d

    def build(self, scene: Scene, *, mailbox: bool = False, memory_limit: int | None = None) -> Grid:
        """The grid over ``scene`` (a :class:`calibrate._grid.Grid`); ``memory_limit`` in bytes."""
        if self.kind == "uniform":
            return Grid.uniform(scene, self.top, mailbox=mailbox, memory_limit=memory_limit)
        if self.subgrids == "fixed":
            sub = np.zeros((self.top_cells, 3), dtype=np.int64)
            occupied = self._occupied(scene).reshape(-1) > self.threshold
            sub[occupied] = self.levels[1]
            return Grid.nested(scene, levels=2, resolution=self.top, subgrid_resolutions=sub,
                               threshold=self.threshold, mailbox=mailbox, memory_limit=memory_limit)
        if self.subgrids == "rule":
            from ._grid import manta_rule

            _, exps = manta_rule(self.depth, self.scale)
            exps = list(self.exponents) if self.exponents is not None else exps[:self.depth]
            # (scale n)^e cells times sub_scale^3  <=>  scale' = scale * sub_scale^(3 / e) at depth 1
            scale = self.scale * self.sub_scale ** (3.0 / exps[1])
            return Grid.nested(scene, levels=self.depth, resolution=self.top, scale=scale, exponents=exps,
                               threshold=self.threshold, mailbox=mailbox, memory_limit=memory_limit)
        if self.depth >= 3:  # the leaf table depends on the depth-1 subgrids: the model sizes both
            sub, sub2 = model_subgrid_tables(scene, self.top, self.depth, self.ratio, self.sub_scale)
        else:
            sub, sub2 = model_subgrid_resolutions(scene, self.top, self.depth, self.ratio), None
            if self.sub_scale != 1.0:
                nz = sub[:, 0] > 0
                sub = sub.copy()
                sub[nz] = np.clip(np.rint(sub[nz] * self.sub_scale), 1, 2 ** 31 - 1).astype(sub.dtype)
        return Grid.nested(scene, levels=self.depth, resolution=self.top, subgrid_resolutions=sub,
                           subgrid_resolutions2=sub2, threshold=self.threshold, mailbox=mailbox,
                           memory_limit=memory_limit)

    def _occupied(self, scene: Scene) -> np.ndarray:
        return Grid.uniform(scene, self.top).top_counts()


def model_subgrid_resolutions(scene: Scene, top, depth: int, ratio: float) -> np.ndarray:
    """(cells, 3) depth-1 subgrid resolutions the nested model gives at top resolution ``top``.

    The plan of ``calibrate predict`` (:func:`models.nested.nested_counts`, analytic
    leaves) for ``depth`` levels and ``T_int / T_step = ratio``, laid out per top cell
    as the kernel takes them (x fastest; zero rows for empty cells).  Cached per scene.
    """
    return model_subgrid_tables(scene, top, depth, ratio)[0]


def model_subgrid_tables(scene: Scene, top, depth: int, ratio: float, sub_scale: float = 1.0):
    """The nested model's subgrid tables at top resolution ``top``: ``(sub, sub2)``.

    ``sub`` as :func:`model_subgrid_resolutions` gives it (its axes times ``sub_scale``,
    rounded), ``sub2`` the leaf grids of three levels, one row per cell of the depth-1
    subgrids (``Grid.nested``'s ``subgrid_resolutions2``), sized by the model for the
    scaled depth-1 cells; None for two levels.  Cached per scene.
    """
    from models.nested import nested_counts

    from .predict import _geometry, _kernel_subgrid_tables

    top = _res3(top)
    cache = _MODEL_CACHE.setdefault(scene, {})
    key = (top, int(depth), float(ratio), float(sub_scale))
    if key not in cache:
        stats = scene.stats
        geom, corners = _geometry(scene)
        overlap = "exact" if corners is not None else "bbox"
        counts = nested_counts(geom, stats.box_lo, stats.box_hi, top, int(depth), float(ratio), overlap=overlap,
                               corners=corners, leaves="analytic", overlap_test=triangle_box_overlap,
                               child_scale=float(sub_scale))
        cache[key] = _kernel_subgrid_tables(scene, stats, counts, overlap)
    return cache[key]


# ---------------------------------------------------------------------------------------
# measuring
# ---------------------------------------------------------------------------------------

def _as_grid(scene, spec_or_grid, mailbox=False):
    if isinstance(spec_or_grid, Grid):
        return spec_or_grid
    if isinstance(spec_or_grid, GridSpec):
        return spec_or_grid.build(scene, mailbox=mailbox, memory_limit=MAX_SWEEP_MEMORY_BYTES)
    raise ValueError(f"expected a GridSpec or a Grid, got {type(spec_or_grid).__name__}")


def _counts(grid: Grid, origins, directions) -> dict:
    t, _, steps, tests, subgrids, visits, changes = grid.count(origins, directions, hits=True, visits=True,
                                                               changes=True)
    info = grid.info
    return dict(steps=float(steps.mean()), tests=float(tests.mean()), subgrids=float(subgrids.mean()),
                visits=float(visits.mean()), changes=float(changes.mean()), hits=float(np.isfinite(t).mean()),
                cells=int(info["n_cells"]), references=int(info["n_refs"]),
                memory_bytes=int(info["memory_bytes"]))


def _summary(m: protocol.Measurement, n_rays: int, drift=None) -> dict:
    """A grid's values per ray, median and MAD; with ``drift`` (the factors of
    :func:`calibrate.protocol.drift_factors`), ``values_ns`` are those over the host's common
    slowdown at their time, and the values as timed are kept in ``raw_values_ns``."""
    raw = np.asarray(m.values_ns, dtype=np.float64) / n_rays
    values = raw if drift is None else raw / np.asarray(drift, dtype=np.float64)
    med, mad = protocol.median_mad(values)
    out = dict(median_ns=med, mad_ns=mad, values_ns=values.tolist(), loops=int(m.loops), warnings=m.warnings)
    if drift is not None:
        out["raw_values_ns"] = raw.tolist()
    return out


def measure_time_per_ray(scene: Scene, spec_or_grid, origins, directions, *, rounds: int = SWEEP_ROUNDS,
                         builds: int = SWEEP_BUILDS, min_time: float = SWEEP_MIN_VALUE_NS * 1e-9, seed: int = 0,
                         mailbox: bool = False, clock: str = DEFAULT_CLOCK) -> dict:
    """Time and count one grid on a ray batch.

    Returns a dict: ``median_ns``, ``mad_ns`` (ns per ray, over ``rounds`` values of the
    un-instrumented kernel spread over ``builds`` builds of the grid (a built Grid is
    timed as it is), each value primed and lasting at least ``min_time`` seconds, one
    warm-up discarded; ``clock`` "thread" (default: the timing thread's CPU time) or
    "wall" (the kernel's own monotonic clock)), ``values_ns`` (per ray), ``steps``,
    ``tests``, ``subgrids``, ``visits`` (mean per ray, from the instrumented twin on the same
    rays), ``hits`` (the share of the rays that hit), ``cells``, ``references``,
    ``memory_bytes``, ``builds``.
    """
    return sweep(scene, [spec_or_grid], (origins, directions), rounds=rounds, builds=builds, min_time=min_time,
                 seed=seed, mailbox=mailbox, clock=clock)[0]


def _skip(out: list, row: dict, i: int, required) -> None:
    if i in required:
        raise ValueError(f"grid {i + 1} cannot be measured: {row['skipped']}")
    out.append(row)


def split_rounds(rounds: int, builds: int) -> list[int]:
    """Values per build when ``rounds`` values per grid are spread over ``builds`` builds.

    As even as can be, the first builds taking one more; never a build without a value
    (``builds`` above ``rounds`` gives ``rounds`` builds of one value each).
    """
    rounds, builds = int(rounds), int(builds)
    if rounds < 1 or builds < 1:
        raise ValueError(f"rounds and builds must be >= 1, got {rounds!r} and {builds!r}")
    builds = min(builds, rounds)
    return [rounds // builds + (1 if b < rounds % builds else 0) for b in range(builds)]


def sweep(scene: Scene, specs: Sequence, rays, *, rounds: int = SWEEP_ROUNDS, builds: int = SWEEP_BUILDS,
          min_time: float = SWEEP_MIN_VALUE_NS * 1e-9, seed: int = 0, mailbox: bool = False,
          clock: str = DEFAULT_CLOCK, prime: bool = SWEEP_PRIME,
          progress: Callable[[int, int, str], None] | None = None,
          status: Callable[[str], None] | None = None, required: Sequence[int] = (),
          drift_out: bool = SWEEP_DRIFT_OUT) -> list[dict]:
    """Build, count and time several grids on one ray batch, interleaved.

    specs : GridSpecs or built Grids; rays : (origins, directions), (n, 3) each.
    Every grid is built and its work counted; then all are timed together by
    :func:`calibrate.protocol.measure`, each round in a fresh random order drawn from
    ``seed``.  A spec whose top level exceeds :data:`MAX_SWEEP_CELLS` cells, or whose
    build fails (more than :data:`MAX_SWEEP_MEMORY_BYTES`), gives a dict with ``skipped`` (the reason) and no times.

    ``rounds`` values per grid are spread over ``builds`` builds of every spec
    (:func:`split_rounds`): the grids are built, timed for their share of the values,
    freed, and built again.  Where a grid's memory lies decides a few per cent of its
    time (which cache sets and pages its cells fall on), the same for every value of
    one build and different for the next, so one build's values alone cannot show it;
    pooled over builds, it is part of each grid's median and spread.  The loop count
    is calibrated on the first build and kept.  A Grid passed in (not a spec) is timed
    as it is in every build.  ``prime`` calls a grid once, untimed, before each of its
    values (:func:`calibrate.protocol.measure`), as ``calibrate run`` does; primed, the
    warm-ups are run on the first build only, else on every build.

    ``drift_out`` : divide the host's common slowdown out of each value
    (:func:`calibrate.protocol.drift_factors`: the grids timed just before and after a
    value estimate it); the values as timed stay in ``raw_values_ns``.

    ``required`` : indices of specs that must be built: when one is skipped the sweep
    raises ``ValueError`` at once (before building the rest).

    Returns one dict per spec, in order (see :func:`measure_time_per_ray`), each with
    ``spec`` (its :meth:`GridSpec.to_dict`, or None for a Grid) and ``builds`` (how
    many builds it was timed in).
    """
    if clock not in CLOCKS:
        raise ValueError(f"unknown clock {clock!r}; choose one of {', '.join(CLOCKS)}")
    o, d = rays
    o = np.ascontiguousarray(o, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    n_rays = int(o.shape[0])
    if n_rays < 1:
        raise ValueError("sweep needs at least one ray")
    if isinstance(rounds, bool) or int(rounds) < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds!r}")
    if isinstance(builds, bool) or int(builds) < 1:
        raise ValueError(f"builds must be >= 1, got {builds!r}")
    if not (min_time > 0):
        raise ValueError(f"min_time must be > 0 s, got {min_time!r}")
    shares = split_rounds(rounds, builds)
    out: list[dict] = []
    measured: dict[str, protocol.Measurement] = {}
    rng = np.random.default_rng(seed)
    ticks = [0, 0]  # progress ticks of the builds before this one, and of this one so far

    def build_all(b: int) -> dict:
        configs, held = {}, 0
        for i, spec in enumerate(specs):
            if b > 0 and "skipped" in out[i]:
                continue
            if status is not None:
                status(f"building {i + 1}/{len(specs)}" + (f" (build {b + 1}/{len(shares)})" if b else ""))
            row = out[i] if b > 0 else dict(spec=spec.to_dict() if isinstance(spec, GridSpec) else None)
            if b == 0 and isinstance(spec, GridSpec) and spec.top_cells > MAX_SWEEP_CELLS:
                row["skipped"] = f"{spec.top_cells:,} top-level cells exceed the sweep's {MAX_SWEEP_CELLS:,}"
                _skip(out, row, i, required)
                continue
            if held > MAX_SWEEP_TOTAL_BYTES:
                if b == 0:
                    row["skipped"] = f"the sweep's grids already hold {held / 2**30:.1f} GiB"
                    _skip(out, row, i, required)
                continue
            try:
                grid = _as_grid(scene, spec, mailbox)
            except (ValueError, MemoryError) as exc:
                if b == 0:
                    row["skipped"] = f"not built: {exc}"
                    _skip(out, row, i, required)
                continue
            if b == 0:
                row["resolution"] = list(grid.resolution)
                row.update(_counts(grid, o, d))
                out.append(row)
            held += row["memory_bytes"]
            row["builds"] = row.get("builds", 0) + 1
            configs[str(i)] = grid.timed_batch(o, d, clock=clock)
            if progress is not None:
                progress(0, 0, f"built {i + 1}/{len(specs)}")
        return configs

    def report(done: int, total: int, label: str) -> None:
        if total:
            ticks[1] = done
        if progress is not None:
            progress(ticks[0] + done if total else 0, total and grand_total, label)

    grand_total = 0
    for b in range(len(shares)):
        configs = build_all(b)
        if not configs:
            break
        if b == 0:
            # the first build's first warm-up is each loop calibration's last call (protocol.measure)
            grand_total = len(configs) * (rounds + SWEEP_WARMUPS * (1 if prime else len(shares))
                                          - min(SWEEP_WARMUPS, 1))
        if status is not None:
            status("timing" + (f" (build {b + 1}/{len(shares)})" if len(shares) > 1 else ""))
        # primed, the warm-ups on the first build only: a grid built again was just written
        # (its pages are mapped), and each value starts from its own call
        warmups = SWEEP_WARMUPS if b == 0 or not prime else 0
        protocol.measure(configs, rng=rng, rounds=sum(shares[:b + 1]), warmups=warmups,
                         min_value_ns=max(1, int(min_time * 1e9)), progress=report, into=measured, prime=prime)
        ticks[:] = [ticks[0] + ticks[1], 0]
        del configs  # the grids are freed before the next build
    drift = protocol.drift_factors({k: (m.values_ns, m.stamps_s) for k, m in measured.items()
                                    if m.values_ns and min(m.values_ns) > 0}) if drift_out else {}
    for key, m in measured.items():
        out[int(key)].update(_summary(m, n_rays, drift.get(key)))
    return out


# ---------------------------------------------------------------------------------------
# reading a sweep
# ---------------------------------------------------------------------------------------

def penalty(time_choice: float, time_best: float) -> float:
    """Relative excess time of a choice over the best: ``time_choice / time_best - 1``."""
    tc, tb = float(time_choice), float(time_best)
    if not (math.isfinite(tc) and math.isfinite(tb) and tb > 0 and tc >= 0):
        raise ValueError(f"penalty needs finite times, the best > 0; got {time_choice!r} and {time_best!r}")
    return tc / tb - 1.0


def best_point(points: Sequence[dict], key: str = "median_ns") -> int:
    """Index of the point with the lowest measured ``key`` (skipped points ignored)."""
    best, best_t = -1, math.inf
    for i, p in enumerate(points):
        t = p.get(key)
        if t is not None and math.isfinite(t) and t < best_t:
            best, best_t = i, t
    if best < 0:
        raise ValueError("no measured point in the sweep")
    return best


def fit_minimum(scales, times, *, mads=None, counts=None, half_span: float = FIT_HALF_SPAN) -> dict:
    """Smooth minimum of a measured curve ``times(scales)``.

    A least-squares quadratic in ``log time`` against ``log scale`` through the lowest
    measured point and its neighbours within a factor ``half_span`` in scale each side
    (at least ``FIT_MIN_NEIGHBOURS`` each side where the sweep has them, so the fit has
    points to disagree with).  Its vertex is the minimum when
    the parabola opens upwards, the vertex lies within the fitted points' span, and the
    curve at the lowest point agrees with it within the noise (3 standard errors of
    that point, at least ``FIT_AGREEMENT`` relative): a curve with a kink there (a cache
    level, say, or a resolution that fits the scene's own structure) is not a parabola,
    and the lowest measured point is kept instead.  The standard error is the scaled MAD
    from ``mads``; with ``counts`` (values behind each point) it is that of the point's
    median, 1.2533 sigma / sqrt(count), since a point is the median of its values.

    scales : (J,) positive, increasing; times : (J,) positive (ns); mads, counts : (J,) or None.
    Returns dict ``scale``, ``time`` (the curve's value there), ``fitted`` (bool),
    ``at_edge`` (the lowest point is the first or last of the sweep), ``window``
    ([first, last] index used), ``coef`` (quadratic coefficients, highest first).
    """
    s = np.asarray(scales, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if s.shape != t.shape or s.ndim != 1 or s.size == 0:
        raise ValueError("fit_minimum needs scales and times of one equal, non-zero length")
    if np.any(~np.isfinite(s)) or np.any(s <= 0) or np.any(~np.isfinite(t)) or np.any(t <= 0):
        raise ValueError("fit_minimum needs finite positive scales and times")
    if np.any(np.diff(s) <= 0):
        raise ValueError("fit_minimum needs increasing scales")
    if not half_span > 1:
        raise ValueError(f"half_span must be > 1, got {half_span!r}")
    j = int(np.argmin(t))
    at_edge = j == 0 or j == s.size - 1
    near = np.flatnonzero(np.abs(np.log(s / s[j])) <= math.log(half_span) * (1 + 1e-12))
    lo = min(int(near.min()), max(0, j - FIT_MIN_NEIGHBOURS))
    hi = max(int(near.max()), min(s.size - 1, j + FIT_MIN_NEIGHBOURS)) + 1
    x, y = np.log(s[lo:hi]), np.log(t[lo:hi])
    out = dict(scale=float(s[j]), time=float(t[j]), fitted=False, at_edge=bool(at_edge), window=[lo, hi - 1],
               coef=None)
    if x.size >= 3:
        coef = np.polyfit(x, y, 2)
        a, b, _ = coef
        se = 1.0 if counts is None else MEDIAN_SE_FACTOR / math.sqrt(max(1, int(counts[j])))
        noise = FIT_AGREEMENT if mads is None else max(FIT_AGREEMENT,
                                                       3.0 * protocol.MAD_TO_SIGMA * float(mads[j]) * se / t[j])
        agrees = abs(math.exp(np.polyval(coef, math.log(s[j]))) / t[j] - 1.0) <= noise
        if a > 0 and agrees:
            xv = -b / (2.0 * a)
            if x[0] <= xv <= x[-1]:
                out.update(scale=float(math.exp(xv)), time=float(math.exp(np.polyval(coef, xv))), fitted=True,
                           coef=[float(c) for c in coef])
    return out

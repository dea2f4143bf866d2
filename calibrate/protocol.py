"""Measurement protocol around timed batch loops.

A *run callable* times a whole batch inside C::

    run(loops: int) -> (elapsed_ns: int, checksum: float)

runs the batch ``loops`` times between two ``clock_gettime`` reads and returns
the elapsed wall time in ns and a checksum that keeps the work observable.
This module turns such callables into robust per-loop timings, following
pyperf's protocol (Victor Stinner, pyperf ``--min-time``, ``--warmups``,
``--loops``; its ``check`` warnings):

1. loop calibration: the smallest power of two for which one value lasts at
   least ``min_value_ns`` (capped at ``max_loops``), from one loop's time and
   then each try's, at least doubling (:func:`calibrate_loops`);
2. warm-ups: ``warmups`` values per configuration, in random order, discarded
   (kept in ``Measurement.warmups_ns`` for inspection only); the loop
   calibration's last call, a value of the count it found, is the first;
3. rounds: each round times every configuration once, in an order drawn from
   the caller's ``np.random.Generator``, so slow drift (thermal, frequency,
   neighbours) affects all configurations alike;
4. summary: per configuration the median and MAD of the per-loop values, and
   warnings (a list of strings, never printed here) for a large spread, a value
   too short for the timer, an incomplete series or a capped loop count.

Partial results and resuming
----------------------------
``measure`` accumulates into a caller-owned dict (``into``), appending each
value as soon as it is timed, so the dict is always consistent:

- ``deadline`` (a ``time.monotonic()`` value) or ``should_stop`` ends the
  measurement cleanly *between* values; ``measure`` returns what it has, and
  the incomplete series carry a warning.
- ``KeyboardInterrupt`` raised anywhere inside ``measure`` (in a run callable,
  the progress callback, ...) is re-raised as :class:`MeasurementInterrupted`
  (a ``KeyboardInterrupt`` subclass, so uncaught it still behaves like Ctrl-C)
  whose ``measurements`` attribute is the partial dict (``into`` itself when
  given). The value being timed at the moment of the interrupt is lost.
- To resume, pass the saved measurements back as ``into`` (rebuilt with
  :meth:`Measurement.from_dict`): their loop counts are reused (no
  recalibration, so old and new values are comparable), warm-ups are run
  again (a fresh process is cold), and each series is filled up to ``rounds``.

A configuration whose loop calibration has not finished when the measurement
stops is absent from the result.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, MutableMapping

import numpy as np

__all__ = [
    "MIN_VALUE_NS_DEFAULT",
    "MAX_LOOPS_DEFAULT",
    "ROUNDS_DEFAULT",
    "WARMUPS_DEFAULT",
    "REL_SPREAD_WARN",
    "TIMER_RESOLUTION_FACTOR",
    "MAD_TO_SIGMA",
    "DRIFT_NEIGHBOURS",
    "DRIFT_MAX_GAP_S",
    "DRIFT_ITERATIONS",
    "DRIFT_MIN_SERIES",
    "Copies",
    "Measurement",
    "MeasurementInterrupted",
    "Pinning",
    "calibrate_loops",
    "drift_factors",
    "measure",
    "median_mad",
    "pin_to_one_core",
    "idlest_cpu",
    "cpu_times",
    "timer_info",
    "timer_resolution_ns",
]

RunCallable = Callable[[int], "tuple[int, float]"]
ProgressCallback = Callable[[int, int, str], None]

# Minimum duration of one value (one call of a run callable), ns. pyperf's
# default --min-time is 100 ms per value; batches here are tight C loops with
# no interpreter in between, so 20 ms is ample and keeps `calibrate run` short.
MIN_VALUE_NS_DEFAULT = 20_000_000
# Cap on the loop count found by calibration; the C loop counter is at least
# 32-bit signed, and 2**30 loops of even a 1 ns batch already last ~1 s.
MAX_LOOPS_DEFAULT = 2**30
#: A timed call shorter than this share of the minimum value is not used to predict the loop
#: count (:func:`calibrate_loops`): at 1/1000 of 10 ms, 10 us, a clock's steps of up to 100 ns
#: err by at most 1%; shorter calls double the loops as pyperf does.
LOOP_ESTIMATE_MIN_SHARE = 1e-3
# Values per configuration (rounds) and discarded warm-ups per configuration.
# pyperf's defaults are 20 processes x 3 values and 1 warm-up per process.
ROUNDS_DEFAULT = 10
WARMUPS_DEFAULT = 1
# Relative spread (scaled MAD / median) above which a series is flagged.
# pyperf warns when the standard deviation exceeds 10% of the mean.
REL_SPREAD_WARN = 0.10
# A value must last at least this many timer resolutions (the task's "~1000x
# timer resolution"; pyperf's analogous check flags values shorter than 1 ms).
TIMER_RESOLUTION_FACTOR = 1000
# Fewer values than this and no spread is estimated.
MIN_VALUES_FOR_SPREAD = 3
# Consistency constant: MAD * 1.4826 estimates sigma for normal data
# (1 / Phi^-1(3/4); Rousseeuw & Croux 1993).
MAD_TO_SIGMA = 1.482602218505602
# Successive perf_counter_ns reads taken to estimate the timer step empirically.
TIMER_PROBE_READS = 2000
# drift_factors: values on each side of a value whose residuals estimate the host's
# common slowdown at its time, the longest gap to such a neighbour (a fit or a stage in
# between and the neighbour says nothing), and the refinements of medians and slowdown.
# On the AMD EPYC host (2026-12-03) 2 on each side with 3 refinements reproduced the
# configurations' medians best among 1-10 a side and 1 or 3 refinements (docs/calibration.md).
DRIFT_NEIGHBOURS = 2
DRIFT_MAX_GAP_S = 1.0
DRIFT_ITERATIONS = 3
# Fewest stamped configurations drift_factors corrects: with fewer, a value's neighbours
# are mostly its own configuration's, and the slowdown cannot be told from its noise.
DRIFT_MIN_SERIES = 3


# ---------------------------------------------------------------------------
# statistics


def median_mad(values_ns) -> tuple[float, float]:
    """Median and (raw, unscaled) median absolute deviation.

    values_ns : (n,) float, any unit (ns per loop here); n >= 1.
    Returns (median, mad) in the same unit; multiply mad by ``MAD_TO_SIGMA``
    for a robust estimate of the standard deviation.
    """
    v = np.asarray(values_ns, dtype=np.float64)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"median_mad needs a non-empty 1-D sequence, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("median_mad: values contain NaN or Inf")
    med = float(np.median(v))
    return med, float(np.median(np.abs(v - med)))


def drift_factors(series: Mapping[str, tuple]) -> dict[str, np.ndarray]:
    """The host's common slowdown at the time of each value, estimated from its neighbours.

    series : name -> (values, stamps_s), one configuration's values (any positive unit) and
        when each was timed (seconds, one clock for all); stamps empty or None for a series
        measured without them, whose factors are 1 and whose values inform no other.
    Returns name -> (n,) positive factors; ``values / factors`` are the values with the
    slowdown divided out.  With fewer than DRIFT_MIN_SERIES stamped series every factor is 1.

    Configurations are timed interleaved in random order, so the values timed just before
    and after one are of other configurations.  On a shared host a slow spell (a
    neighbour's memory traffic, a busy sibling thread) outlasts a value and slows the
    values around it alike: the model is ``log v = m_config + z(t) + e``.  z at a value is
    the median of the log-residuals ``log v - m`` of the DRIFT_NEIGHBOURS values on each
    side in time (those within DRIFT_MAX_GAP_S, of other configurations), and m is each
    configuration's median of ``log v - z``, the two refined in turn DRIFT_ITERATIONS
    times.  On a noisy AMD EPYC host (2026-12-03), 69 configurations x 12 values: lag-1
    correlation of the residuals 0.63; the medians of two halves of each series differ
    by 3.0% instead of 7.3% (alternate values) and 4.9% instead of 11.0% (first and
    second half) with the factors divided out.
    """
    names = list(series)
    stamped, logs, ids, times = [], [], [], []
    out = {}
    for k, name in enumerate(names):
        values, stamps = series[name]
        v = np.asarray(values, dtype=np.float64)
        out[name] = np.ones(v.shape[0])
        if stamps is None or len(stamps) == 0 or v.shape[0] == 0:
            continue
        t = np.asarray(stamps, dtype=np.float64)
        if t.shape != v.shape:
            raise ValueError(f"drift_factors: {name!r} has {v.shape[0]} values and {t.shape[0]} stamps")
        if not (np.all(np.isfinite(v)) and np.all(v > 0) and np.all(np.isfinite(t))):
            raise ValueError(f"drift_factors: {name!r} needs positive finite values and finite stamps")
        stamped.append(name)
        logs.append(np.log(v))
        ids.append(np.full(v.shape[0], k))
        times.append(t)
    if len(logs) < DRIFT_MIN_SERIES:
        return out
    lv, cid, ts = np.concatenate(logs), np.concatenate(ids), np.concatenate(times)
    order = np.argsort(ts, kind="stable")
    lv, cid, ts = lv[order], cid[order], ts[order]
    n = lv.shape[0]
    # neighbours of each value in time: offsets -w..w but 0, within the gap
    w = DRIFT_NEIGHBOURS
    pos = np.arange(n)[:, None] + np.array([o for o in range(-w, w + 1) if o != 0])[None, :]
    valid = (pos >= 0) & (pos < n)
    pos = np.clip(pos, 0, n - 1)
    valid &= np.abs(ts[pos] - ts[:, None]) <= DRIFT_MAX_GAP_S
    valid &= cid[pos] != cid[:, None]  # other configurations only
    has = valid.any(axis=1)  # a value without such neighbours keeps z = 0
    z = np.zeros(n)
    for _ in range(DRIFT_ITERATIONS):
        m = np.zeros(int(cid.max()) + 1)
        for k in np.unique(cid):
            m[k] = np.median((lv - z)[cid == k])
        res = np.where(valid, (lv - m[cid])[pos], np.nan)
        z = np.zeros(n)
        z[has] = np.nanmedian(res[has], axis=1)
    back = np.empty(n)  # the factors in the order the series were concatenated
    back[order] = np.exp(z)
    for name, part in zip(stamped, np.split(back, np.cumsum([a.size for a in logs])[:-1])):
        out[name] = part
    return out


@dataclass
class Measurement:
    """Timings of one configuration.

    loops : int, batch repetitions per value (fixed by calibration).
    values_ns : list of float, one per value in measurement order, ns per loop
        (elapsed_ns / loops); warm-ups excluded.
    target_values : int, number of values requested (``rounds``).
    timer_resolution_ns : float, effective timer resolution used for checks.
    warmups_ns : list of float, discarded warm-up values, ns per loop.
    notes : list of str, events recorded while measuring (e.g. loop cap hit).
    stamps_s : list of float, when each value ended (seconds of ``time.time()``), one per
        value; empty for values measured without stamps.  :func:`drift_factors` reads them.

    Derived (properties): ``median`` and ``mad`` (ns per loop), ``sigma``
    (= MAD_TO_SIGMA * mad), ``rel_spread`` (= sigma / median), ``complete``,
    ``warnings`` (list of str).
    """

    loops: int
    values_ns: list[float] = field(default_factory=list)
    target_values: int = 0
    timer_resolution_ns: float = 1.0
    warmups_ns: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    stamps_s: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        """Median ns per loop (NaN with no values)."""
        return median_mad(self.values_ns)[0] if self.values_ns else math.nan

    @property
    def mad(self) -> float:
        """Raw median absolute deviation, ns per loop (NaN with no values)."""
        return median_mad(self.values_ns)[1] if self.values_ns else math.nan

    @property
    def sigma(self) -> float:
        """Scaled MAD, a robust standard deviation, ns per loop."""
        return MAD_TO_SIGMA * self.mad

    @property
    def rel_spread(self) -> float:
        """sigma / median (dimensionless); NaN with fewer than 3 values."""
        if len(self.values_ns) < MIN_VALUES_FOR_SPREAD:
            return math.nan
        med = self.median
        return self.sigma / med if med > 0 else math.inf

    @property
    def complete(self) -> bool:
        return len(self.values_ns) >= self.target_values

    @property
    def warnings(self) -> list[str]:
        """Problems with this series, as sentences; empty when none."""
        out = list(self.notes)
        n = len(self.values_ns)
        if n < self.target_values:
            out.append(f"only {n} of {self.target_values} values measured (stopped early)")
        if n == 0:
            return out
        if n < MIN_VALUES_FOR_SPREAD:
            out.append(f"only {n} values: spread not estimated")
        else:
            rs = self.rel_spread
            if rs > REL_SPREAD_WARN:
                out.append(
                    f"large spread: scaled MAD is {100 * rs:.1f}% of the median "
                    f"(threshold {100 * REL_SPREAD_WARN:.0f}%); the host may be busy"
                )
        shortest_ns = min(self.values_ns) * self.loops
        floor_ns = TIMER_RESOLUTION_FACTOR * self.timer_resolution_ns
        if shortest_ns < floor_ns:
            out.append(
                f"value too short: shortest value lasts {shortest_ns:.0f} ns, under "
                f"{TIMER_RESOLUTION_FACTOR} x timer resolution ({floor_ns:.0f} ns); "
                "raise min_value_ns"
            )
        return out

    def to_dict(self) -> dict:
        """JSON-serialisable form (derived statistics included for readers)."""
        n = len(self.values_ns)
        return {
            "loops": int(self.loops),
            "values_ns": [float(v) for v in self.values_ns],
            "target_values": int(self.target_values),
            "timer_resolution_ns": float(self.timer_resolution_ns),
            "warmups_ns": [float(v) for v in self.warmups_ns],
            "notes": list(self.notes),
            "stamps_s": [float(t) for t in self.stamps_s],
            "median_ns": self.median if n else None,
            "mad_ns": self.mad if n else None,
            "warnings": self.warnings,
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> "Measurement":
        """Inverse of :meth:`to_dict` (derived fields are ignored)."""
        try:
            loops = int(d["loops"])
            values = [float(v) for v in d["values_ns"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"bad measurement record: {exc!r}") from exc
        if loops < 1:
            raise ValueError(f"bad measurement record: loops = {loops} < 1")
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError("bad measurement record: values_ns must be finite and >= 0")
        try:
            stamps = [float(t) for t in d.get("stamps_s", [])]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"bad measurement record: stamps_s: {exc!r}") from exc
        if stamps and (len(stamps) != len(values) or not all(math.isfinite(t) for t in stamps)):
            raise ValueError("bad measurement record: stamps_s must hold one finite time per value")
        return cls(
            loops=loops,
            values_ns=values,
            target_values=int(d.get("target_values", len(values))),
            timer_resolution_ns=float(d.get("timer_resolution_ns", 1.0)),
            warmups_ns=[float(v) for v in d.get("warmups_ns", [])],
            notes=[str(s) for s in d.get("notes", [])],
            stamps_s=stamps,
        )


class MeasurementInterrupted(KeyboardInterrupt):
    """KeyboardInterrupt during :func:`measure`, carrying the partial results.

    measurements : dict name -> Measurement, every value timed so far (the
        caller's ``into`` dict when one was given).
    """

    def __init__(self, measurements: dict):
        super().__init__("measurement interrupted; partial results in .measurements")
        self.measurements = measurements


class Copies:
    """One configuration timed on several copies of its data, a copy per value in turn.

    runs : run callables of equal work (e.g. the same grid built several times).  A
    value's time depends a little on where its data lies in memory (which cache sets
    and pages it falls on): the same for every value of one copy, different for
    another, so values of one copy alone hide it.  :func:`measure` calls
    :meth:`next_value` before each value, so the values cycle through the copies and
    their median and spread include it.
    """

    def __init__(self, runs):
        self.runs = list(runs)
        if not self.runs or not all(callable(r) for r in self.runs):
            raise ValueError("Copies needs at least one run callable")
        self.current = 0
        self._started = False

    def next_value(self) -> None:
        """Move to the next copy (the first value stays on the first copy)."""
        if self._started:
            self.current = (self.current + 1) % len(self.runs)
        self._started = True

    def __call__(self, loops: int):
        return self.runs[self.current](loops)

    def prime(self) -> None:
        """Prime the current copy: its own ``prime()`` when it has one, else one untimed loop."""
        run = self.runs[self.current]
        primer = getattr(run, "prime", None)
        if primer is not None:
            primer()
        else:
            run(1)


# ---------------------------------------------------------------------------
# timer


def timer_info() -> dict:
    """Resolution of the clocks a measurement depends on, ns.

    Returns a JSON-serialisable dict:
      clock_getres_ns : CLOCK_MONOTONIC resolution reported by the OS
          (the clock the C loops read), or None where unavailable;
      perf_counter_step_ns : smallest positive difference between successive
          ``time.perf_counter_ns()`` reads (an empirical upper bound on the
          granularity; it includes the interpreter's call overhead);
      perf_counter_impl : the implementation Python reports for perf_counter;
      thread_clock_getres_ns : CLOCK_THREAD_CPUTIME_ID resolution (the clock of
          timing_clock "thread"), or None where unavailable;
      resolution_ns : the larger of the two, used for the too-short check.
    """
    getres_ns = None
    if hasattr(time, "clock_getres") and hasattr(time, "CLOCK_MONOTONIC"):
        try:
            getres_ns = float(time.clock_getres(time.CLOCK_MONOTONIC) * 1e9)
        except OSError:
            getres_ns = None
    thread_ns = None
    if hasattr(time, "clock_getres") and hasattr(time, "CLOCK_THREAD_CPUTIME_ID"):
        try:
            thread_ns = float(time.clock_getres(time.CLOCK_THREAD_CPUTIME_ID) * 1e9)
        except OSError:
            thread_ns = None
    read = time.perf_counter_ns
    stamps = [read() for _ in range(TIMER_PROBE_READS)]
    deltas = [b - a for a, b in zip(stamps, stamps[1:]) if b > a]
    step_ns = float(min(deltas)) if deltas else None
    info = time.get_clock_info("perf_counter")
    known = [x for x in (getres_ns, step_ns, info.resolution * 1e9) if x is not None]
    return {
        "clock_getres_ns": getres_ns,
        "perf_counter_step_ns": step_ns,
        "perf_counter_impl": info.implementation,
        "thread_clock_getres_ns": thread_ns,
        "resolution_ns": max(max(known), 1.0),
    }


def timer_resolution_ns() -> float:
    """Effective timer resolution, ns (``timer_info()["resolution_ns"]``)."""
    return timer_info()["resolution_ns"]


# ---------------------------------------------------------------------------
# core pinning


@dataclass
class Pinning:
    """Result of :func:`pin_to_one_core`.

    core : the CPU the process is now pinned to, or None when not pinned.
    previous : the affinity set before pinning (None when unsupported).
    note : one sentence for the report.
    Use ``restore()`` (or the object as a context manager) to undo.
    """

    core: int | None
    previous: frozenset | None
    note: str

    def restore(self) -> None:
        """Give the process back its previous affinity (no-op if not pinned)."""
        if self.core is not None and self.previous:
            os.sched_setaffinity(0, self.previous)

    def __enter__(self) -> "Pinning":
        return self

    def __exit__(self, *exc) -> None:
        self.restore()


#: Seconds over which the CPUs' idle time is sampled before choosing one to pin to, and
#: the idle share (0..1) within which CPUs count as equally idle.
IDLE_SAMPLE_S = 0.1
IDLE_TIE = 0.1


def _read_proc_stat() -> str:
    with open("/proc/stat", encoding="ascii") as f:
        return f.read()


def cpu_times(text: str) -> dict[int, tuple[int, int]]:
    """Per-CPU (idle, total) jiffies from the text of /proc/stat (idle includes iowait)."""
    out = {}
    for line in text.splitlines():
        name, _, rest = line.partition(" ")
        if not (name.startswith("cpu") and name[3:].isdigit()):
            continue
        fields = [int(x) for x in rest.split()]
        if len(fields) < 4:
            continue
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
        out[int(name[3:])] = (idle, sum(fields[:8]))
    return out


def idlest_cpu(cpus, *, interval: float = IDLE_SAMPLE_S, read=_read_proc_stat, sleep=time.sleep,
               pid: int | None = None) -> tuple[int | None, str]:
    """The CPU of ``cpus`` that was idlest over ``interval`` seconds, and a note.

    CPUs within :data:`IDLE_TIE` of the idlest count as tied, and the process id picks
    among them (highest-numbered first), so calibrations started together, each
    sampling the same idle CPUs, spread over them instead of sharing one.  Returns
    (None, reason) when /proc/stat cannot be read or names none of ``cpus``.
    """
    cpus = sorted(cpus, reverse=True)
    try:
        first = cpu_times(read())
        sleep(interval)
        second = cpu_times(read())
    except (OSError, ValueError) as exc:
        return None, f"CPU load unknown ({exc})"
    share = {}
    for c in cpus:
        if c in first and c in second:
            d_idle, d_total = second[c][0] - first[c][0], second[c][1] - first[c][1]
            share[c] = d_idle / d_total if d_total > 0 else 1.0
    if not share:
        return None, "CPU load unknown (no CPU of the affinity set in /proc/stat)"
    best = max(share.values())
    tied = [c for c in cpus if c in share and share[c] >= best - IDLE_TIE]
    chosen = tied[(os.getpid() if pid is None else pid) % len(tied)]
    return chosen, f"idle {100 * share[chosen]:.0f}% over {interval:g} s"


def pin_to_one_core(core: int | None = None) -> Pinning:
    """Pin this process to one CPU where the OS allows it.

    core : CPU index, or None to take the idlest CPU of the current affinity set
        (:func:`idlest_cpu`: another process busy on a CPU, a second calibration say,
        would share it and evict its caches at every switch), else the
        highest-numbered one (CPU 0 usually services most interrupts on Linux;
        pyperf's tuning docs likewise advise benchmarking away from it).
    Never raises on an unsupported platform or a refused request: the returned
    :class:`Pinning` has ``core=None`` and says why in ``note``.
    """
    if not (hasattr(os, "sched_getaffinity") and hasattr(os, "sched_setaffinity")):
        return Pinning(None, None, "not pinned: this platform has no sched_setaffinity")
    try:
        previous = frozenset(os.sched_getaffinity(0))
    except OSError as exc:
        return Pinning(None, None, f"not pinned: cannot read affinity ({exc})")
    why = ""
    if core is None:
        if not previous:
            return Pinning(None, previous, "not pinned: empty affinity set")
        core, why = idlest_cpu(previous) if len(previous) > 1 else (None, "")
        if core is None:
            core = max(previous)
    elif core not in previous:
        raise ValueError(f"core {core} is not in this process's affinity set {sorted(previous)}")
    try:
        os.sched_setaffinity(0, {core})
    except OSError as exc:
        return Pinning(None, previous, f"not pinned: sched_setaffinity refused ({exc})")
    return Pinning(core, previous, f"pinned to CPU {core} of {sorted(previous)}" + (f" ({why})" if why else ""))


# ---------------------------------------------------------------------------
# measuring


def _call(name: str, run: RunCallable, loops: int) -> int:
    """Call ``run(loops)`` and return its elapsed ns, validated."""
    result = run(loops)
    try:
        elapsed_ns, _checksum = result
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"run callable {name!r} must return (elapsed_ns, checksum), got {result!r}"
        ) from exc
    if isinstance(elapsed_ns, float) and not math.isfinite(elapsed_ns):
        raise ValueError(f"run callable {name!r} returned elapsed_ns = {elapsed_ns}")
    elapsed_ns = int(elapsed_ns)
    if elapsed_ns < 0:
        raise ValueError(f"run callable {name!r} returned a negative time ({elapsed_ns} ns)")
    return elapsed_ns


def calibrate_loops(
    run: RunCallable,
    *,
    min_value_ns: int = MIN_VALUE_NS_DEFAULT,
    max_loops: int = MAX_LOOPS_DEFAULT,
    name: str = "run",
    stop: Callable[[], bool] | None = None,
    calls: list | None = None,
) -> tuple[int | None, list[str]]:
    """Smallest power-of-two loop count whose value lasts >= min_value_ns.

    One call is made and discarded first: the first call of a configuration finds
    its data out of the caches (other configurations ran since it was built) and can
    last many times a warm call, which would settle on a loop count too small, and
    then every value of the configuration would be one cold call.  Then one loop is
    timed, and each next try is the smallest power of two that the time a loop took
    so far says will reach the minimum (at least twice the last try: pyperf's doubling
    when the estimate is no help), until a call reaches it.  Where pyperf's doubling
    from 1 makes a call for every power of two below the count (a value of 10 ms from
    loops of 2 ms: 1, 2, 4 and 8 loops, 30 ms), this makes two (1 and 8 loops, 18 ms)
    and finds the same count; :func:`measure` keeps the last as a warm-up.  A one-loop time
    under :data:`LOOP_ESTIMATE_MIN_SHARE` of the minimum (a timer too coarse for it)
    is not used for an estimate: the loops double instead.  Returns (loops, notes):
    ``loops`` is None when ``stop()`` turned true before calibration finished;
    ``notes`` reports a cap hit (loops = max_loops with a value still short).
    ``calls``, when given, gets ``(loops, elapsed_ns)`` of each timed call appended (the
    discarded cold call is not one).
    """
    if min_value_ns <= 0:
        raise ValueError(f"min_value_ns must be > 0, got {min_value_ns}")
    if max_loops < 1:
        raise ValueError(f"max_loops must be >= 1, got {max_loops}")
    if stop is not None and stop():
        return None, []
    _call(name, run, 1)  # the cold first call
    loops = 1
    while True:
        if stop is not None and stop():
            return None, []
        elapsed_ns = _call(name, run, loops)
        if calls is not None:
            calls.append((loops, elapsed_ns))
        if elapsed_ns >= min_value_ns:
            return loops, []
        if loops >= max_loops:
            return loops, [
                f"loop count capped at {max_loops}: a value lasts only {elapsed_ns} ns "
                f"(< min_value_ns = {min_value_ns})"
            ]
        if elapsed_ns >= LOOP_ESTIMATE_MIN_SHARE * min_value_ns:
            loops = min(max(2 * loops, _loops_reaching(min_value_ns, elapsed_ns, loops)), max_loops)
        else:
            loops = min(2 * loops, max_loops)


def _loops_reaching(min_value_ns: int, elapsed_ns: int, loops: int) -> int:
    """The smallest power of two whose value lasts >= min_value_ns at elapsed_ns / loops a loop."""
    want = -(-min_value_ns * loops // elapsed_ns)  # ceil(min_value_ns / (elapsed_ns / loops)), in integers
    return 1 << max(int(want) - 1, 0).bit_length()


def measure(
    configs: Mapping[str, RunCallable],
    *,
    rng: np.random.Generator,
    rounds: int = ROUNDS_DEFAULT,
    warmups: int = WARMUPS_DEFAULT,
    min_value_ns: int = MIN_VALUE_NS_DEFAULT,
    max_loops: int = MAX_LOOPS_DEFAULT,
    progress: ProgressCallback | None = None,
    deadline: float | None = None,
    should_stop: Callable[[dict], bool] | None = None,
    into: MutableMapping[str, Measurement] | None = None,
    timer_resolution_ns: float | None = None,
    clock: Callable[[], float] = time.monotonic,
    prime: bool = False,
    stamp: Callable[[], float] = time.time,
) -> dict[str, Measurement]:
    """Time every configuration with calibrated loops, warm-ups and interleaved rounds.

    configs : dict name -> run callable, ``run(loops) -> (elapsed_ns, checksum)``.
    rng : np.random.Generator drawing the order of configurations in each round.
    rounds : values wanted per configuration (>= 1); one round times each
        configuration still short of ``rounds`` values once.
    warmups : discarded values per configuration before the first round (>= 0).  A
        configuration calibrated here has its calibration's last call, made with the count
        found, as its first warm-up (a discarded value of that count, warm from the calls
        before it), so the warm-up pass skips it once.
    min_value_ns : minimum duration of one value for loop calibration, ns.
    max_loops : cap on the calibrated loop count.
    progress : optional ``progress(done, total, label)`` called after each
        warm-up or value; ``total`` counts the warm-ups timed (not the loop
        calibration's last calls, kept as warm-ups) plus values. During loop
        calibration it is called as ``progress(0, 0, "calibrating <name>")``
        (total 0: not yet known).
    deadline : ``clock()`` value (default ``time.monotonic()``) after which the
        measurement stops cleanly between values, keeping what was measured.
    should_stop : optional ``should_stop(measurements) -> bool`` consulted
        between values with the dict built so far (an adaptive budget).
    into : caller-owned dict updated in place as values arrive; existing
        entries are resumed (see module docstring). A new dict when None.
    timer_resolution_ns : effective timer resolution for the too-short check;
        measured with :func:`timer_info` when None.
    clock : monotonic clock in seconds used for ``deadline`` (injectable).
    prime : call a configuration once (one loop, untimed) before each of its values,
        so that a value starts from the caches as the configuration's own calls leave
        them, not as the configuration timed before it left them (interleaving makes
        every value's first loop cold otherwise).  A run callable with a ``prime()``
        method has that called instead (:meth:`calibrate.Grid.timed_batch`'s traces the
        first rays of its batch: a long batch of distinct rays is not traced twice).
    stamp : the clock whose reading after each value goes into ``Measurement.stamps_s``
        (seconds; the wall clock by default, so that the values of a resumed run, in
        another process, are placed in time with the earlier ones).

    A run callable with a ``next_value()`` method has it called before each of its
    values and warm-ups (before the priming call): :class:`Copies` moves to its next
    copy of the configuration there.

    Returns the dict name -> :class:`Measurement` (``into`` when given).
    Raises :class:`MeasurementInterrupted` on KeyboardInterrupt, carrying it.
    """
    if not configs:
        raise ValueError("measure: no configurations given")
    for name, run in configs.items():
        if not callable(run):
            raise ValueError(f"measure: configuration {name!r} is not callable")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"measure: rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if rounds < 1:
        raise ValueError(f"measure: rounds must be >= 1, got {rounds}")
    if warmups < 0:
        raise ValueError(f"measure: warmups must be >= 0, got {warmups}")
    if min_value_ns <= 0:
        raise ValueError(f"measure: min_value_ns must be > 0, got {min_value_ns}")
    if timer_resolution_ns is None:
        timer_resolution_ns = timer_info()["resolution_ns"]
    if not timer_resolution_ns > 0:
        raise ValueError(f"measure: timer_resolution_ns must be > 0, got {timer_resolution_ns}")

    results = {} if into is None else into

    def stop() -> bool:
        if deadline is not None and clock() >= deadline:
            return True
        return should_stop is not None and bool(should_stop(results))

    def report(done: int, total: int, label: str) -> None:
        if progress is not None:
            progress(done, total, label)

    names = list(configs)
    try:
        # 1. loop calibration, for configurations not resumed
        last_call = {}  # name -> ns a loop of the calibration's last call (made with the count found)
        for name in names:
            if name in results:
                continue
            report(0, 0, f"calibrating {name}")
            calls = []
            loops, notes = calibrate_loops(
                configs[name], min_value_ns=min_value_ns, max_loops=max_loops,
                name=name, stop=stop, calls=calls,
            )
            if loops is None:
                break
            results[name] = Measurement(loops=loops, notes=notes)
            last_call[name] = calls[-1][1] / loops  # calibrate_loops ends on a call with its count
        ready = [n for n in names if n in results]
        for name in ready:
            m = results[name]
            m.target_values = max(m.target_values, rounds)
            m.timer_resolution_ns = float(timer_resolution_ns)
            m.warmups_ns = [last_call[name]] if warmups > 0 and name in last_call else []
        need = {n: max(rounds - len(results[n].values_ns), 0) for n in ready}
        total = sum(warmups - len(results[n].warmups_ns) for n in ready) + sum(need.values())
        done = 0

        def one(name: str, sink: list[float], label: str, stamps: list | None = None) -> bool:
            nonlocal done
            if stop():
                return False
            m = results[name]
            advance = getattr(configs[name], "next_value", None)
            if advance is not None:
                advance()
            if prime:
                primer = getattr(configs[name], "prime", None)
                if primer is not None:
                    primer()
                else:
                    _call(name, configs[name], 1)
            elapsed_ns = _call(name, configs[name], m.loops)
            sink.append(elapsed_ns / m.loops)
            if stamps is not None:
                stamps.append(float(stamp()))
            done += 1
            report(done, total, label)
            return True

        # 2. warm-ups, interleaved like the rounds
        for w in range(warmups):
            for i in rng.permutation(len(ready)):
                name = ready[i]
                if len(results[name].warmups_ns) > w:
                    continue  # the calibration's last call
                if not one(name, results[name].warmups_ns, f"warm-up {w + 1}/{warmups} {name}"):
                    return results
        # 3. rounds in random order; drift then hits every configuration alike
        for r in range(max(need.values(), default=0)):
            todo = [n for n in ready if need[n] > r]
            for i in rng.permutation(len(todo)):
                name = todo[i]
                m = results[name]
                label = f"value {len(m.values_ns) + 1}/{m.target_values} {name}"
                # values resumed from a record without stamps cannot be placed in time: none get stamps
                stamps = m.stamps_s if len(m.stamps_s) == len(m.values_ns) else None
                if not one(name, m.values_ns, label, stamps):
                    return results
    except KeyboardInterrupt as exc:
        if isinstance(exc, MeasurementInterrupted):
            raise
        raise MeasurementInterrupted(results) from exc
    return results

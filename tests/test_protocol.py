"""Measurement protocol, tested with fake run callables (no kernels, no sleeping)."""

import json
import math
import os

import numpy as np
import pytest

from calibrate.protocol import (
    MAD_TO_SIGMA,
    Copies,
    REL_SPREAD_WARN,
    TIMER_RESOLUTION_FACTOR,
    Measurement,
    MeasurementInterrupted,
    LOOP_ESTIMATE_MIN_SHARE,
    calibrate_loops,
    cpu_times,
    drift_factors,
    idlest_cpu,
    measure,
    median_mad,
    pin_to_one_core,
    timer_info,
)

# Planted cost of one loop of a fake batch, ns.
NS_PER_LOOP = 1234.5
# A small minimum value keeps loop counts (and the fakes' bookkeeping) small.
MIN_VALUE_NS = 100_000
# Planted timer resolution for tests that must not depend on the host's.
RES_NS = 1.0


class FakeRun:
    """run(loops) -> (elapsed_ns, checksum) with planted cost and noise.

    ns_per_loop : planted cost, ns. noise_sigma : log-normal multiplicative
    noise per value. slow_first / slow_factor : the first `slow_first` calls
    take `slow_factor` times longer (a cold cache). log : shared list that
    records (name, loops) of every call. clock : optional FakeClock advanced by
    each call's elapsed time. fail_at : raise KeyboardInterrupt on this call.
    """

    def __init__(self, name, ns_per_loop=NS_PER_LOOP, *, rng=None, noise_sigma=0.0,
                 slow_first=0, slow_factor=1.0, log=None, clock=None, fail_at=None):
        self.name, self.ns_per_loop = name, ns_per_loop
        self.rng, self.noise_sigma = rng, noise_sigma
        self.slow_first, self.slow_factor = slow_first, slow_factor
        self.log = [] if log is None else log
        self.clock, self.fail_at = clock, fail_at
        self.calls = 0

    def __call__(self, loops):
        self.calls += 1
        if self.fail_at is not None and self.calls == self.fail_at:
            raise KeyboardInterrupt
        self.log.append((self.name, loops))
        factor = self.slow_factor if self.calls <= self.slow_first else 1.0
        if self.noise_sigma:
            factor *= math.exp(self.noise_sigma * self.rng.standard_normal())
        elapsed = int(loops * self.ns_per_loop * factor)
        if self.clock is not None:
            self.clock.t += elapsed * 1e-9
        return elapsed, float(loops)


class FakeClock:
    """Monotonic seconds, advanced only by fake runs."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def preset(names, loops, rounds=0):
    """Measurements as if calibrated earlier (the resume path): no calibration calls."""
    return {n: Measurement(loops=loops, target_values=rounds) for n in names}


# -- loop calibration ---------------------------------------------------------------


@pytest.mark.parametrize("i", range(6))
def test_calibrate_loops_is_smallest_power_of_two_reaching_minimum(i):
    rng = np.random.default_rng(1000 + i)
    ns = float(rng.uniform(10.0, 50_000.0))
    run = FakeRun("a", ns)
    loops, notes = calibrate_loops(run, min_value_ns=MIN_VALUE_NS)
    assert notes == []
    assert loops & (loops - 1) == 0  # power of two
    assert int(loops * ns) >= MIN_VALUE_NS
    assert loops == 1 or int(loops // 2 * ns) < MIN_VALUE_NS
    # one discarded call, one loop timed, then the count that loop's time predicts; a loop
    # too short for the clock to estimate from doubles until a call is long enough
    calls = [l for _, l in run.log]
    if ns >= LOOP_ESTIMATE_MIN_SHARE * MIN_VALUE_NS:
        assert calls == ([1, 1] if loops == 1 else [1, 1, loops])
    else:
        assert calls[:3] == [1, 1, 2] and calls[-1] == loops
        assert all(b > a and b & (b - 1) == 0 for a, b in zip(calls[1:], calls[2:]))


@pytest.mark.parametrize("i", range(6))
def test_calibrate_loops_matches_doubling_under_noise(i):
    """With noisy values (a slow or fast one-loop call among them) the predicted jumps find
    a count within a factor of two of pyperf's doubling on the same planted cost, in fewer
    and shorter calls; every count is a power of two."""
    rng = np.random.default_rng(1020 + i)
    ns = float(rng.uniform(1_000.0, 30_000.0))

    def doubling(run):
        run(1)
        loops = 1
        while run(loops)[0] < MIN_VALUE_NS:
            loops *= 2
        return loops

    ref = doubling(FakeRun("ref", ns))
    for j in range(5):
        slow_one = float(rng.uniform(0.5, 3.0))  # the one-loop call's time off by this factor
        run = FakeRun("a", ns, rng=np.random.default_rng(1030 + 10 * i + j), noise_sigma=0.05,
                      slow_first=2, slow_factor=slow_one)
        loops, notes = calibrate_loops(run, min_value_ns=MIN_VALUE_NS)
        assert notes == [] and loops & (loops - 1) == 0
        assert ref // 2 <= loops <= 2 * ref
        assert len(run.log) <= 2 + ref.bit_length()  # doubling's calls: 1 + ref.bit_length()
        assert sum(l for _, l in run.log[2:]) <= sum(2**k for k in range(ref.bit_length())) + 2 * ref


def test_calibrate_loops_doubles_when_one_loop_is_below_the_clock():
    """A one-loop call too short to estimate from (a coarse clock reads 0) doubles the loops."""
    run = FakeRun("a", 0.4)  # int(loops * 0.4) ns: 0 for one loop
    loops, _ = calibrate_loops(run, min_value_ns=MIN_VALUE_NS)
    calls = [l for _, l in run.log]
    assert calls[:4] == [1, 1, 2, 4]
    assert int(loops * 0.4) >= MIN_VALUE_NS and int(loops // 2 * 0.4) < MIN_VALUE_NS * 1.01


def test_calibrate_loops_jumps_again_after_a_slow_first_loop():
    """A one-loop call three times slow (still cold) predicts too few loops; the call with
    them, warm, predicts the right count, which is the answer."""
    ns = 1_000.0  # 100 loops reach MIN_VALUE_NS: the answer is 128
    run = FakeRun("a", ns, slow_first=2, slow_factor=3.0)  # the one-loop call reads 3,000 ns
    loops, _ = calibrate_loops(run, min_value_ns=MIN_VALUE_NS)
    assert [l for _, l in run.log] == [1, 1, 64, 128]  # 100_000 / 3_000 = 34 -> 64, then 100 -> 128
    assert loops == 128


@pytest.mark.parametrize("i", range(4))
def test_a_cold_first_call_does_not_set_the_loop_count(i):
    """A first call so slow (the configuration's data out of the caches) that it alone
    lasts the minimum value is discarded: the loop count is the one warm calls need."""
    rng = np.random.default_rng(1050 + i)
    ns = float(rng.uniform(2_000.0, 20_000.0))
    slow = float(rng.uniform(1.2, 4.0)) * MIN_VALUE_NS / ns  # the cold call alone reaches the minimum
    loops_cold, _ = calibrate_loops(FakeRun("a", ns, slow_first=1, slow_factor=slow), min_value_ns=MIN_VALUE_NS)
    loops_warm, _ = calibrate_loops(FakeRun("b", ns), min_value_ns=MIN_VALUE_NS)
    assert loops_warm > 1 and loops_cold == loops_warm


class ColdAfterOthers(FakeRun):
    """A fake whose first loop after another configuration's call takes ``cold_ns`` more
    (its data out of the caches); the log shared by all fakes says who ran last."""

    def __init__(self, name, ns_per_loop, cold_ns, log):
        super().__init__(name, ns_per_loop, log=log)
        self.cold_ns = cold_ns

    def __call__(self, loops):
        cold = bool(self.log) and self.log[-1][0] != self.name
        elapsed, checksum = super().__call__(loops)
        return elapsed + (int(self.cold_ns) if cold else 0), checksum


@pytest.mark.parametrize("i", range(3))
def test_prime_takes_each_value_warm(i):
    """Interleaved values start cold: without prime most values carry the planted cold
    start (spread over their loops); with prime each value is the warm cost exactly."""
    rng = np.random.default_rng(1150 + i)
    ns = {n: float(rng.uniform(500.0, 5_000.0)) for n in "abc"}
    cold = float(rng.uniform(20_000.0, 60_000.0))
    for prime in (False, True):
        log = []
        runs = {n: ColdAfterOthers(n, ns[n], cold, log) for n in "abc"}
        out = measure(runs, rng=np.random.default_rng(1160 + i), rounds=5, warmups=1,
                      min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS, prime=prime)
        for n in "abc":
            values = np.array(out[n].values_ns)
            warm = int(out[n].loops * ns[n]) / out[n].loops
            if prime:
                assert np.allclose(values, warm), (n, values, warm)
            else:  # a value right after the same configuration's last one (across rounds) is warm
                assert np.sum(values >= warm + 0.9 * cold / out[n].loops) >= 3, (n, values, warm)


@pytest.mark.parametrize("i", range(3))
def test_copies_take_the_values_in_turn(i):
    """Each value (its priming call and its warm-up too) runs on one copy, the next
    value on the next copy: the values carry every copy's planted cost, and their
    median lies among them, where one copy alone shows only its own."""
    rng = np.random.default_rng(1170 + i)
    base = float(rng.uniform(500.0, 5_000.0))
    costs = base * (1.0 + rng.uniform(0.02, 0.10, size=3).cumsum())
    log = []
    copies = Copies([FakeRun(f"copy{k}", c, log=log) for k, c in enumerate(costs)])
    rounds = 9
    out = measure({"a": copies, "b": FakeRun("b", base, log=log)}, rng=np.random.default_rng(1180 + i),
                  rounds=rounds, warmups=1, min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS, prime=True)
    loops = out["a"].loops
    values = np.array(out["a"].values_ns)
    per_copy = [int(loops * c) / loops for c in costs]
    # warm-up on copy 0, then the values on copies 1, 2, 0, 1, ... : three of each
    for k, v in enumerate(per_copy):
        assert np.sum(np.isclose(values, v)) == rounds // 3, (k, values, per_copy)
    assert out["a"].median == pytest.approx(per_copy[1])
    # after the loop calibration (copy 0: one discarded call, one loop, then the count that
    # loop predicts, the warm-up), each value is a priming call and a timed call on one
    # copy: copies 0, 1, 2, 0, 1, ...
    calls = [(n, l) for n, l in log if n.startswith("copy")]
    calibration = 3 if loops > 1 else 2
    assert calls[:calibration] == [("copy0", 1), ("copy0", 1), ("copy0", loops)][:calibration]
    assert len(out["a"].warmups_ns) == 1
    pairs = [calls[j:j + 2] for j in range(calibration, len(calls), 2)]
    assert len(pairs) == rounds
    for v, pair in enumerate(pairs):
        assert pair == [(f"copy{v % 3}", 1), (f"copy{v % 3}", loops)], (v, pair)


class PrimedRun(FakeRun):
    """A FakeRun with its own ``prime()`` (a short untimed call, as Grid.timed_batch's), logged as
    (name, "prime")."""

    def prime(self):
        self.log.append((self.name, "prime"))


@pytest.mark.parametrize("i", range(3))
def test_a_run_with_its_own_prime_is_primed_by_it(i):
    """measure(prime=True) calls a run callable's prime() before each warm-up and value instead
    of one loop of the whole batch; Copies primes its current copy the same way, and a copy
    without prime() by one loop."""
    rng = np.random.default_rng(1190 + i)
    log = []
    runs = {"a": PrimedRun("a", float(rng.uniform(500.0, 5_000.0)), log=log),
            "b": Copies([PrimedRun("b0", 900.0, log=log), FakeRun("b1", 950.0, log=log)])}
    rounds = 4
    out = measure(runs, rng=np.random.default_rng(1200 + i), rounds=rounds, warmups=1,
                  min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS, prime=True)
    assert len(out["a"].values_ns) == rounds
    calls_a = [c for n, c in log if n == "a"]
    after_calibration = calls_a[calls_a.index("prime"):]
    assert after_calibration == ["prime", out["a"].loops] * rounds  # each value (the warm-up: the calibration's)
    # copy b0 (values 1 and 3) primes itself; b1 (values 2 and 4) by one loop
    b = [(n, c) for n, c in log if n.startswith("b")]
    b_after = b[[k for k, e in enumerate(b) if e[1] == "prime"][0]:]
    loops = out["b"].loops
    assert b_after == [("b0", "prime"), ("b0", loops), ("b1", 1), ("b1", loops)] * 2


def test_copies_needs_run_callables():
    with pytest.raises(ValueError, match="at least one run callable"):
        Copies([])
    with pytest.raises(ValueError, match="at least one run callable"):
        Copies([1, 2])


def test_measure_values_last_at_least_min_value():
    out = measure({"a": FakeRun("a", 37.0), "b": FakeRun("b", 5000.0)},
                  rng=np.random.default_rng(1100), rounds=4, warmups=1,
                  min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS)
    for name, ns in (("a", 37.0), ("b", 5000.0)):
        m = out[name]
        assert len(m.values_ns) == 4
        assert all(v * m.loops >= MIN_VALUE_NS - 1 for v in m.values_ns)
        assert m.median == pytest.approx(ns, rel=1e-3)
        assert m.warnings == []


def test_loop_cap_is_reported():
    out = measure({"a": FakeRun("a", 1.0)}, rng=np.random.default_rng(1200), rounds=3,
                  warmups=0, min_value_ns=MIN_VALUE_NS, max_loops=64,
                  timer_resolution_ns=RES_NS)
    assert out["a"].loops == 64
    assert any("capped at 64" in w for w in out["a"].warnings)


# -- warm-ups ------------------------------------------------------------------------


@pytest.mark.parametrize("warmups", [1, 3])
def test_warmups_are_discarded(warmups):
    slow = 10.0
    runs = {n: FakeRun(n, slow_first=warmups, slow_factor=slow) for n in "abc"}
    out = measure(runs, rng=np.random.default_rng(1300 + warmups), rounds=5,
                  warmups=warmups, into=preset(runs, 128), timer_resolution_ns=RES_NS)
    for m in out.values():
        assert len(m.warmups_ns) == warmups
        assert all(v == pytest.approx(slow * NS_PER_LOOP, rel=1e-3) for v in m.warmups_ns)
        assert all(v == pytest.approx(NS_PER_LOOP, rel=1e-3) for v in m.values_ns)


def test_without_warmups_the_slow_first_call_pollutes_values():
    # the same fake with warmups=0: the planted slow call lands in the values
    runs = {"a": FakeRun("a", slow_first=1, slow_factor=10.0)}
    out = measure(runs, rng=np.random.default_rng(1310), rounds=5, warmups=0,
                  into=preset(runs, 128), timer_resolution_ns=RES_NS)
    assert max(out["a"].values_ns) == pytest.approx(10.0 * NS_PER_LOOP, rel=1e-3)


# -- interleaving ----------------------------------------------------------------------


def _round_orders(seed, names="abcde", rounds=8):
    log = []
    runs = {n: FakeRun(n, log=log) for n in names}
    measure(runs, rng=np.random.default_rng(seed), rounds=rounds, warmups=0,
            into=preset(runs, 64), timer_resolution_ns=RES_NS)
    k = len(names)
    return [tuple(n for n, _ in log[r * k:(r + 1) * k]) for r in range(rounds)]


def test_rounds_are_random_permutations_reproducible_by_seed():
    orders = _round_orders(1400)
    assert all(sorted(o) == list("abcde") for o in orders)  # each round times all once
    assert len(set(orders)) > 1  # order differs between rounds
    assert orders == _round_orders(1400)  # same seed, same schedule
    assert orders != _round_orders(1401)


# -- statistics ------------------------------------------------------------------------


def test_median_mad_planted():
    med, mad = median_mad([1.0, 2.0, 3.0, 4.0, 100.0])
    assert (med, mad) == (3.0, 1.0)  # deviations 2,1,0,1,97
    med, mad = median_mad([4.0, 1.0, 3.0, 2.0])
    assert (med, mad) == (2.5, 1.0)  # deviations 1.5,1.5,0.5,0.5


@pytest.mark.parametrize("i", range(4))
def test_median_mad_matches_brute_force(i):
    rng = np.random.default_rng(1500 + i)
    v = rng.lognormal(7.0, 0.5, size=int(rng.integers(1, 40)))

    def brute_median(x):
        s = sorted(x)
        n = len(s)
        return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])

    med, mad = median_mad(v)
    assert med == pytest.approx(brute_median(v), rel=1e-12)
    assert mad == pytest.approx(brute_median([abs(x - med) for x in v]), rel=1e-12)


def test_scaled_mad_estimates_sigma():
    sigma = 5.0
    v = np.random.default_rng(1600).normal(100.0, sigma, size=20_000)
    assert MAD_TO_SIGMA * median_mad(v)[1] == pytest.approx(sigma, rel=0.03)


def test_measurement_reports_planted_values():
    planted = [1000.0, 1010.0, 990.0, 1500.0, 1005.0]  # deviations 5, 5, 15, 495, 0
    it = iter(planted)
    runs = {"a": lambda loops: (int(next(it) * loops), 0.0)}
    out = measure(runs, rng=np.random.default_rng(1700), rounds=5, warmups=0,
                  into=preset(runs, 1000), timer_resolution_ns=RES_NS)
    m = out["a"]
    assert m.values_ns == planted
    assert m.median == 1005.0 and m.mad == 5.0
    assert m.rel_spread == pytest.approx(MAD_TO_SIGMA * 5.0 / 1005.0)


# -- warnings --------------------------------------------------------------------------


@pytest.mark.parametrize("i", range(3))
def test_spread_warning_fires_on_noisy_not_on_quiet(i):
    rng = np.random.default_rng(1800 + i)
    runs = {"noisy": FakeRun("noisy", rng=rng, noise_sigma=0.4),
            "quiet": FakeRun("quiet", rng=rng, noise_sigma=0.002)}
    out = measure(runs, rng=rng, rounds=15, warmups=1, min_value_ns=MIN_VALUE_NS,
                  timer_resolution_ns=RES_NS)
    assert out["noisy"].rel_spread > REL_SPREAD_WARN
    assert any("large spread" in w for w in out["noisy"].warnings)
    assert out["quiet"].rel_spread < REL_SPREAD_WARN
    assert out["quiet"].warnings == []


def test_too_short_warning_relative_to_timer_resolution():
    res_ns = 1000.0  # planted: values of ~100 us are under 1000 x 1 us
    out = measure({"a": FakeRun("a")}, rng=np.random.default_rng(1900), rounds=3,
                  warmups=0, min_value_ns=MIN_VALUE_NS, timer_resolution_ns=res_ns)
    m = out["a"]
    assert min(m.values_ns) * m.loops < TIMER_RESOLUTION_FACTOR * res_ns
    assert any("too short" in w for w in m.warnings)
    out = measure({"a": FakeRun("a")}, rng=np.random.default_rng(1901), rounds=3,
                  warmups=0, min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS)
    assert not any("too short" in w for w in out["a"].warnings)


# -- stopping, interrupting, resuming ------------------------------------------------


def test_deadline_stops_between_values_keeping_partial_data():
    clock = FakeClock()
    starts = []
    runs = {}
    for n in "ab":
        fake = FakeRun(n, clock=clock)
        runs[n] = (lambda f: lambda loops: (starts.append(clock()), f(loops))[1])(fake)
    rounds = 20
    # calibration ~0.2 ms per config; each value ~0.16 ms: the deadline falls mid-rounds
    deadline = 2.0e-3
    out = measure(runs, rng=np.random.default_rng(2000), rounds=rounds, warmups=1,
                  min_value_ns=MIN_VALUE_NS, deadline=deadline, clock=clock,
                  timer_resolution_ns=RES_NS)
    counts = [len(m.values_ns) for m in out.values()]
    assert all(0 < c < rounds for c in counts)
    assert abs(counts[0] - counts[1]) <= 1  # interleaved: both stopped in the same round
    assert all(s < deadline for s in starts)  # no value started after the deadline
    assert all(any("stopped early" in w for w in m.warnings) for m in out.values())
    assert all(not m.complete for m in out.values())


def test_should_stop_sees_partial_results():
    seen = []

    def enough(results):
        seen.append(sum(len(m.values_ns) for m in results.values()))
        return seen[-1] >= 5

    runs = {n: FakeRun(n) for n in "abc"}
    out = measure(runs, rng=np.random.default_rng(2100), rounds=10, warmups=0,
                  into=preset(runs, 64), should_stop=enough, timer_resolution_ns=RES_NS)
    assert sum(len(m.values_ns) for m in out.values()) == 5


def test_interrupt_keeps_partial_data_and_resume_completes():
    log = []
    runs = {n: FakeRun(n, log=log) for n in "abc"}
    # calibration of NS_PER_LOOP to 100 us takes 3 calls (a discarded one, 1 loop, 128 loops,
    # the last of them the warm-up)
    runs["b"].fail_at = 3 + 4  # calibration, then the 4th value of b
    into = {}
    with pytest.raises(MeasurementInterrupted) as info:
        measure(runs, rng=np.random.default_rng(2200), rounds=6, warmups=1,
                min_value_ns=MIN_VALUE_NS, into=into, timer_resolution_ns=RES_NS)
    assert isinstance(info.value, KeyboardInterrupt)
    assert info.value.measurements is into
    assert len(into["b"].values_ns) == 3
    assert all(3 <= len(into[n].values_ns) <= 4 for n in "ac")
    loops = {n: m.loops for n, m in into.items()}

    # save and reload as the CLI would, then resume with healthy callables
    saved = json.loads(json.dumps({n: m.to_dict() for n, m in into.items()}))
    resumed = {n: Measurement.from_dict(d) for n, d in saved.items()}
    log2 = []
    runs2 = {n: FakeRun(n, log=log2) for n in "abc"}
    out = measure(runs2, rng=np.random.default_rng(2201), rounds=6, warmups=1,
                  min_value_ns=MIN_VALUE_NS, into=resumed, timer_resolution_ns=RES_NS)
    assert out is resumed
    assert all(len(m.values_ns) == 6 and m.complete and m.warnings == [] for m in out.values())
    assert {n: m.loops for n, m in out.items()} == loops
    assert {l for _, l in log2} == set(loops.values())  # no recalibration


def test_interrupt_during_calibration_keeps_calibrated_configs():
    runs = {"a": FakeRun("a"), "b": FakeRun("b", fail_at=3)}
    into = {}
    with pytest.raises(MeasurementInterrupted):
        measure(runs, rng=np.random.default_rng(2300), rounds=3, warmups=0,
                min_value_ns=MIN_VALUE_NS, into=into, timer_resolution_ns=RES_NS)
    assert list(into) == ["a"] and into["a"].loops == 128


def test_progress_counts_every_warmup_and_value():
    calls = []
    runs = {n: FakeRun(n) for n in "ab"}
    measure(runs, rng=np.random.default_rng(2400), rounds=4, warmups=2,
            min_value_ns=MIN_VALUE_NS, progress=lambda d, t, s: calls.append((d, t, s)),
            timer_resolution_ns=RES_NS)
    # two warm-ups a configuration, the first the calibration's last call (not counted)
    counted = [(d, t) for d, t, _ in calls if t > 0]
    assert counted == [(k, 10) for k in range(1, 11)]
    assert sum(s.startswith("calibrating") for _, _, s in calls) == 2
    assert sum(s.startswith("warm-up 1/") for _, _, s in calls) == 0
    assert sum(s.startswith("warm-up 2/") for _, _, s in calls) == 2


@pytest.mark.parametrize("i", range(3))
def test_the_calibrations_last_call_is_the_first_warmup(i):
    """Each configuration calibrated in the run keeps ``warmups`` warm-ups, the first the
    calibration's last call (a value of the count found); the pass times only the rest.
    Resumed configurations, not calibrated again, get every warm-up timed."""
    rng = np.random.default_rng(2410 + i)
    log = []
    runs = {n: FakeRun(n, float(rng.uniform(500.0, 5_000.0)), log=log) for n in "abc"}
    warmups = 1 + i
    out = measure(runs, rng=np.random.default_rng(2420 + i), rounds=3, warmups=warmups,
                  min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS)
    for n, m in out.items():
        assert len(m.warmups_ns) == warmups
        assert m.warmups_ns[0] == int(m.loops * runs[n].ns_per_loop) / m.loops
        # calls at the count found: the calibration's last, the other warm-ups, the values
        assert sum(1 for name, l in log if name == n and l == m.loops) == 1 + (warmups - 1) + 3
    resumed = {n: Measurement.from_dict(json.loads(json.dumps(m.to_dict()))) for n, m in out.items()}
    log2 = []
    runs2 = {n: FakeRun(n, runs[n].ns_per_loop, log=log2) for n in "abc"}
    out2 = measure(runs2, rng=np.random.default_rng(2430 + i), rounds=4, warmups=warmups,
                   min_value_ns=MIN_VALUE_NS, into=resumed, timer_resolution_ns=RES_NS)
    for n, m in out2.items():
        assert len(m.warmups_ns) == warmups and len(m.values_ns) == 4
        assert sum(1 for name, _ in log2 if name == n) == warmups + 1


# -- input validation and serialisation ----------------------------------------------


def test_bad_input_raises_value_error():
    rng = np.random.default_rng(2500)
    with pytest.raises(ValueError, match="no configurations"):
        measure({}, rng=rng)
    with pytest.raises(ValueError, match="rounds"):
        measure({"a": FakeRun("a")}, rng=rng, rounds=0)
    with pytest.raises(ValueError, match="Generator"):
        measure({"a": FakeRun("a")}, rng=np.random.RandomState(0))
    with pytest.raises(ValueError, match="not callable"):
        measure({"a": 3}, rng=rng)
    with pytest.raises(ValueError, match="negative"):
        measure({"a": lambda loops: (-5, 0.0)}, rng=rng, timer_resolution_ns=RES_NS)
    with pytest.raises(ValueError, match="elapsed_ns, checksum"):
        measure({"a": lambda loops: 5}, rng=rng, timer_resolution_ns=RES_NS)
    with pytest.raises(ValueError, match="loops"):
        Measurement.from_dict({"loops": 0, "values_ns": []})


def test_measurement_round_trips_through_json():
    m = Measurement(loops=64, values_ns=[10.0, 11.0, 12.5], target_values=4,
                    timer_resolution_ns=20.0, warmups_ns=[30.0], notes=["n"])
    d = json.loads(json.dumps(m.to_dict()))
    assert d["median_ns"] == 11.0
    assert Measurement.from_dict(d) == m


# -- host helpers -----------------------------------------------------------------------


def test_timer_info_reports_a_positive_resolution():
    info = timer_info()
    json.dumps(info)
    assert math.isfinite(info["resolution_ns"]) and info["resolution_ns"] >= 1.0
    if info["clock_getres_ns"] is not None:
        assert info["resolution_ns"] >= info["clock_getres_ns"]


def test_pin_to_one_core_and_restore():
    if not hasattr(os, "sched_setaffinity"):
        assert pin_to_one_core().core is None
        return
    before = os.sched_getaffinity(0)
    with pin_to_one_core() as pin:
        if pin.core is not None:
            assert os.sched_getaffinity(0) == {pin.core} and pin.core in before
    assert os.sched_getaffinity(0) == before
    with pytest.raises(ValueError, match="affinity set"):
        pin_to_one_core(core=max(before) + 1000)


PROC_STAT = """cpu  {a} 0 {b} {c} 5 0 1 0 0 0
cpu0 {u0} 0 10 {i0} 2 0 1 0 0 0
cpu1 {u1} 0 10 {i1} 3 0 0 0 0 0
intr 12345 0 0
ctxt 999
"""


def _stat(u0, i0, u1, i1):
    return PROC_STAT.format(a=u0 + u1, b=20, c=i0 + i1, u0=u0, i0=i0, u1=u1, i1=i1)


def test_cpu_times_reads_idle_and_total_per_cpu():
    t = cpu_times(_stat(100, 900, 400, 600))
    assert t == {0: (902, 1013), 1: (603, 1013)}


@pytest.mark.parametrize("i", range(4))
def test_idlest_cpu_avoids_a_busy_cpu_and_spreads_ties(i):
    """A CPU another process keeps busy is avoided whatever the process id; between CPUs
    equally idle the process id decides, so two processes with neighbouring ids part."""
    rng = np.random.default_rng(1400 + i)
    busy = int(rng.integers(0, 2))
    before = _stat(100, 900, 100, 900)
    spent = [(95, 5), (5, 95)] if busy == 0 else [(5, 95), (95, 5)]  # (user, idle) jiffies per CPU
    after = _stat(100 + spent[0][0], 900 + spent[0][1], 100 + spent[1][0], 900 + spent[1][1])
    for pid in (1000 + i, 1001 + i):
        reads = iter([before, after])
        cpu, note = idlest_cpu({0, 1}, read=lambda: next(reads), sleep=lambda s: None, pid=pid)
        assert cpu == 1 - busy and "idle 95%" in note
    tied = _stat(150, 950, 152, 948)
    chosen = set()
    for pid in (2000 + i, 2001 + i):
        reads = iter([before, tied])
        chosen.add(idlest_cpu({0, 1}, read=lambda: next(reads), sleep=lambda s: None, pid=pid)[0])
    assert chosen == {0, 1}


def test_idlest_cpu_without_proc_stat_says_so():
    def unreadable():
        raise OSError("no /proc here")

    cpu, note = idlest_cpu({0, 1}, read=unreadable, sleep=lambda s: None)
    assert cpu is None and "no /proc here" in note
    cpu, note = idlest_cpu({5, 6}, read=lambda: _stat(1, 1, 1, 1), sleep=lambda s: None)
    assert cpu is None and "no CPU of the affinity set" in note


def test_pin_is_a_noop_without_affinity_support(monkeypatch):
    monkeypatch.delattr(os, "sched_setaffinity", raising=False)
    pin = pin_to_one_core()
    assert pin.core is None and "not pinned" in pin.note
    pin.restore()  # harmless


# -- the host's common slowdown (drift_factors) ----------------------------------------


def _drifting_host(seed, n_configs=40, rounds=10, noise=0.02, spell=0.25):
    """Interleaved values of n_configs configurations on a host whose slowdown z(t) is an
    AR(1) process (slow spells of some 20 values), plus iid noise; returns
    (series {name: (values, stamps)}, planted medians, planted slowdown per value)."""
    rng = np.random.default_rng(seed)
    med = {f"c{k}": float(np.exp(rng.uniform(np.log(1e4), np.log(1e7)))) for k in range(n_configs)}
    names = list(med)
    vals = {n: [] for n in names}
    stamps = {n: [] for n in names}
    slow = {n: [] for n in names}
    z, t = 0.0, 0.0
    for _ in range(rounds):
        for i in rng.permutation(n_configs):
            z = 0.95 * z + spell * np.sqrt(1 - 0.95**2) * rng.standard_normal()
            t += 0.02
            n = names[i]
            vals[n].append(med[n] * np.exp(z + noise * rng.standard_normal()))
            stamps[n].append(t)
            slow[n].append(np.exp(z))
    return {n: (vals[n], stamps[n]) for n in names}, med, slow


@pytest.mark.parametrize("i", range(6))
def test_drift_factors_recover_a_planted_common_slowdown(i):
    """Slow spells of 25% (log sd) lasting ~20 values, 2% noise of each value's own: the
    factors follow the planted slowdown and the corrected medians sit near the truth."""
    series, med, slow = _drifting_host(2000 + i)
    f = drift_factors(series)
    planted = np.concatenate([np.log(slow[n]) for n in series])
    got = np.concatenate([np.log(f[n]) for n in series])
    assert np.corrcoef(planted, got)[0, 1] > 0.9
    # each median's error, centred: the slowdown is known up to a constant factor
    def errors(values):
        e = np.array([np.log(np.median(values(n)) / med[n]) for n in series])
        return np.abs(e - np.median(e))
    raw_err = errors(lambda n: series[n][0])
    cor_err = errors(lambda n: np.asarray(series[n][0]) / f[n])
    assert np.median(cor_err) < 0.7 * np.median(raw_err)
    spread = lambda v: MAD_TO_SIGMA * median_mad(np.log(v))[1]
    assert np.median([spread(np.asarray(series[n][0]) / f[n]) for n in series]) < 0.08
    assert np.median([spread(series[n][0]) for n in series]) > 0.12


def test_drift_factors_leave_a_quiet_host_alone():
    series, med, slow = _drifting_host(2010, spell=0.0)
    f = drift_factors(series)
    assert max(abs(np.log(f[n])).max() for n in f) < 0.05


def test_drift_factors_need_three_stamped_series_and_near_neighbours():
    series, _, _ = _drifting_host(2020, n_configs=5)
    names = list(series)
    two = {n: series[n] for n in names[:2]}
    assert all(np.all(f == 1.0) for f in drift_factors(two).values())
    # series without stamps get ones and inform no other
    partial = {n: (series[n][0], [] if k >= 2 else series[n][1]) for k, n in enumerate(names)}
    assert all(np.all(f == 1.0) for f in drift_factors(partial).values())
    # a value far in time from every other has no neighbour: factor 1
    lone = dict(series)
    v, t = list(series[names[0]][0]), list(series[names[0]][1])
    lone[names[0]] = (v + [v[0] * 3], t + [t[-1] + 100.0])
    f = drift_factors(lone)
    assert f[names[0]][-1] == 1.0 and f[names[0]].shape == (len(v) + 1,)


def test_drift_factors_reject_mismatched_or_bad_input():
    series, _, _ = _drifting_host(2030, n_configs=4)
    n = next(iter(series))
    bad = dict(series)
    bad[n] = (series[n][0], series[n][1][:-1])
    with pytest.raises(ValueError, match="stamps"):
        drift_factors(bad)
    bad[n] = ([0.0] + list(series[n][0][1:]), series[n][1])
    with pytest.raises(ValueError, match="positive"):
        drift_factors(bad)


def test_measure_stamps_each_value_and_round_trips_them():
    stamps = iter(range(10_000))
    runs = {n: FakeRun(n) for n in "abc"}
    got = measure(runs, rng=np.random.default_rng(3), rounds=4, warmups=1, min_value_ns=MIN_VALUE_NS,
                  timer_resolution_ns=RES_NS, stamp=lambda: float(next(stamps)))
    every = sorted(t for m in got.values() for t in m.stamps_s)
    assert all(len(m.stamps_s) == len(m.values_ns) == 4 for m in got.values())
    assert every == sorted(set(every)) and all(np.all(np.diff(m.stamps_s) > 0) for m in got.values())
    back = Measurement.from_dict(json.loads(json.dumps(got["a"].to_dict())))
    assert back.stamps_s == got["a"].stamps_s
    with pytest.raises(ValueError, match="stamps_s"):
        Measurement.from_dict(dict(got["a"].to_dict(), stamps_s=[1.0]))


def test_values_resumed_without_stamps_stay_unstamped():
    """A series resumed from a record without stamps cannot be placed in time: it takes no
    stamps for its new values either (a partial series of stamps would misplace them)."""
    into = {"a": Measurement(loops=1, values_ns=[5.0, 6.0], target_values=2)}
    got = measure({"a": FakeRun("a"), "b": FakeRun("b")}, rng=np.random.default_rng(4), rounds=4, warmups=0,
                  min_value_ns=MIN_VALUE_NS, timer_resolution_ns=RES_NS, into=into)
    assert len(got["a"].values_ns) == 4 and got["a"].stamps_s == []
    assert len(got["b"].stamps_s) == 4

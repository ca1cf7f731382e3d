"""Tests for rt_ident.loop.scheduler: absolute-deadline ticks, overrun skipping, lateness histogram, RT setup."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from rt_ident.errors import ConfigError
from rt_ident.loop import scheduler
from rt_ident.loop.scheduler import LatenessHistogram, Ticker, apply_realtime

P = 1e-3


class FakeClock:
    """A clock that advances ``step`` per reading (so spinning terminates) and by what the sleeper sleeps."""

    def __init__(self, t: float = 100.0, step: float = 1e-6, oversleep: float = 0.0, seed: int = 0) -> None:
        self.t = t
        self.step = step
        self.oversleep = oversleep
        self.rng = np.random.default_rng(seed)
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        self.t += self.step
        return self.t

    def sleep(self, dt: float) -> None:
        assert dt > 0
        self.sleeps.append(dt)
        self.t += dt + (self.rng.uniform(0, self.oversleep) if self.oversleep else 0.0)


def test_ticks_land_on_deadlines_and_sleep_stops_spin_s_early() -> None:
    clk = FakeClock()
    tk = Ticker(P, clock=clk, sleeper=clk.sleep, spin_s=150e-6, max_sleep_s=None)
    t0 = tk.start()
    for k in range(1, 6):
        info = tk.wait_next()
        assert info.index == k and info.skipped == 0
        assert info.deadline == t0 + k * P
        assert 0.0 <= info.lateness_s <= 2 * clk.step
    # every sleep ended ~150 us before its deadline, the rest was spun
    assert all(abs(s - (P - 150e-6)) < 20e-6 for s in clk.sleeps)


def test_wait_is_cut_into_sleeps_no_longer_than_max_sleep_s() -> None:
    clk = FakeClock()
    tk = Ticker(P, clock=clk, sleeper=clk.sleep, spin_s=150e-6, max_sleep_s=100e-6)
    t0 = tk.start()
    for k in range(1, 4):
        info = tk.wait_next()
        assert info.deadline == t0 + k * P and 0.0 <= info.lateness_s <= 2 * clk.step
    assert max(clk.sleeps) <= 100e-6 + 1e-12
    # ~850 us of sleep per tick in chunks of <= 100 us: 9 sleeps per tick
    assert 3 * 8 <= len(clk.sleeps) <= 3 * 10


def test_max_sleep_s_must_be_positive() -> None:
    with pytest.raises(ConfigError):
        Ticker(1e-3, max_sleep_s=0.0)
    with pytest.raises(ConfigError):
        Ticker(1e-3, max_sleep_s=float("nan"))


def test_injected_slow_tick_is_one_overrun_and_whole_periods_are_skipped() -> None:
    clk = FakeClock()
    tk = Ticker(P, clock=clk, sleeper=clk.sleep, spin_s=50e-6)
    tk.start()
    first = tk.wait_next()
    assert first.index == 1
    clk.t += 3.5 * P                 # the loop body took 3.5 periods
    late = tk.wait_next()
    # deadlines 2 and 3 are skipped; tick 4 (already passed by 0.5 P) is returned at once, no burst
    assert late.skipped == 2 and late.index == 4
    assert late.deadline == pytest.approx(tk.t0 + 4 * P, abs=1e-12)
    assert 0.0 < late.lateness_s < P
    assert tk.overruns == 1 and tk.skipped_total == 2
    nxt = tk.wait_next()             # back on the grid, waits normally
    assert nxt.index == 5 and nxt.skipped == 0 and nxt.lateness_s < 10e-6
    assert tk.overruns == 1


def test_late_by_less_than_a_period_is_not_an_overrun() -> None:
    clk = FakeClock()
    tk = Ticker(P, clock=clk, sleeper=clk.sleep, spin_s=50e-6)
    tk.start()
    tk.wait_next()
    clk.t += 1.6 * P                 # next deadline missed by 0.6 P
    info = tk.wait_next()
    assert info.index == 2 and info.skipped == 0
    assert info.lateness_s == pytest.approx(0.6 * P, abs=5e-6)
    assert tk.overruns == 0


def test_deadlines_do_not_drift_with_jittery_sleeps_and_work() -> None:
    clk = FakeClock(oversleep=80e-6, step=2e-6, seed=1)
    rng = np.random.default_rng(2)
    tk = Ticker(P, clock=clk, sleeper=clk.sleep, spin_s=20e-6)
    t0 = tk.start()
    n = 5000
    for _ in range(n):
        info = tk.wait_next()
        clk.t += rng.uniform(0, 0.3 * P)   # work in the loop body
    assert info.index == n and tk.overruns == 0
    assert info.deadline == pytest.approx(t0 + n * P, abs=1e-9)
    # the achieved rate is the nominal one: a relative-sleep loop would be ~(1 + 0.19) periods per tick here
    assert abs((clk.t - t0) - n * P) < P


def test_real_clock_ticks_are_consecutive_or_counted_as_skipped() -> None:
    tk = Ticker(2e-3, spin_s=100e-6)
    prev = 0
    for _ in range(10):
        info = tk.wait_next()
        assert info.index == prev + 1 + info.skipped
        assert info.lateness_s >= 0.0
        prev = info.index
    assert tk.ticks == 10


def test_ticker_rejects_bad_period_and_whole_period_spin() -> None:
    with pytest.raises(ConfigError, match="period_s"):
        Ticker(0.0)
    with pytest.raises(ConfigError, match="spin_s"):
        Ticker(1e-3, spin_s=1e-3)   # would busy-wait the whole period


def test_histogram_percentiles_match_numpy_within_one_bin() -> None:
    rng = np.random.default_rng(5)
    data_s = rng.lognormal(mean=np.log(40e-6), sigma=0.8, size=20_000)
    h = LatenessHistogram()
    n_bins_before = len(h.counts())
    for v in data_s:
        h.record(float(v))
    assert len(h.counts()) == n_bins_before and h.counts().sum() == data_s.size
    us = data_s * 1e6
    width = 10 ** (1 / h.bins_per_decade) - 1
    for q in (1, 50, 90, 99, 99.9):
        assert h.percentile(q) == pytest.approx(np.percentile(us, q), rel=width)
    s = h.summary()
    assert s["max"] == us.max() and h.percentile(100) == us.max()
    assert s["count"] == data_s.size and s["mean"] == pytest.approx(us.mean(), rel=1e-9)
    assert s["p99"] == h.percentile(99) and s["p50"] == h.percentile(50)


def test_histogram_handles_underflow_overflow_and_empty() -> None:
    h = LatenessHistogram(lo_us=1.0, hi_us=1e4)
    assert np.isnan(h.percentile(50))
    h.record_many([-5e-6, 0.0, 0.5e-6, 20e-6, 0.5])   # early/zero, below lo, one in range, 500 ms
    c = h.counts()
    assert c[0] == 3 and c[-1] == 1 and c[1:-1].sum() == 1
    assert h.percentile(100) == pytest.approx(0.5e6) and h.percentile(0) == pytest.approx(-5.0)
    h.reset()
    assert h.count == 0 and h.counts().sum() == 0


def test_apply_realtime_reports_denials_without_raising(monkeypatch: pytest.MonkeyPatch) -> None:
    def deny(*_a, **_k):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(scheduler.os, "sched_setscheduler", deny)
    monkeypatch.setattr(scheduler.os, "sched_setaffinity", deny)
    monkeypatch.setattr(scheduler, "_mlockall", lambda: "mlockall failed: [Errno 1] nope")
    monkeypatch.setattr(scheduler.gc, "freeze", deny)
    report = apply_realtime(priority=50, cpus=[0], lock_memory=True, freeze_gc=True)
    assert set(report) == {"sched_fifo", "affinity", "mlockall", "gc_freeze"}
    assert all(isinstance(v, str) for v in report.values())
    assert "not permitted" in report["sched_fifo"] and "not permitted" in report["affinity"]
    assert apply_realtime(priority=None, cpus=None, lock_memory=False, freeze_gc=False) == {
        k: "not requested" for k in report
    }


def test_apply_realtime_in_a_child_process_returns_a_full_report() -> None:
    # Run in a short-lived child: SCHED_FIFO / mlockall must not leak into the test process.
    code = (
        "import json; from rt_ident.loop.scheduler import apply_realtime;"
        "print(json.dumps(apply_realtime(priority=10, cpus=[0])))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(report) == {"sched_fifo", "affinity", "mlockall", "gc_freeze"}
    assert all(v is True or isinstance(v, str) and v for v in report.values())
    assert report["gc_freeze"] is True and report["affinity"] is True


def test_locking_and_unlocking_memory_start_no_process() -> None:
    # in a child: the lock must not leak into the test process; a process started would be forked from a
    # run's whole heap at its start and end
    code = (
        "import json, os, subprocess\n"
        "def refuse(*a, **k):\n"
        "    raise AssertionError('a process was started')\n"
        "subprocess.Popen = os.fork = os.posix_spawn = refuse\n"
        "from rt_ident.loop import scheduler\n"
        "print(json.dumps([scheduler._mlockall(), scheduler.unlock_memory()]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-500:]
    locked, unlocked = json.loads(out.stdout.strip().splitlines()[-1])
    assert unlocked is True and (locked is True or "CAP_IPC_LOCK" in locked), (locked, unlocked)


def test_apply_realtime_locks_memory_and_collects_before_it_turns_sched_fifo(restore_scheduling, monkeypatch):
    # both take tenths of a second of CPU: not at SCHED_FIFO, ahead of everything else on the loop's CPU
    import gc

    import rt_ident.loop.scheduler as sched

    seen = {}

    def mlockall():
        seen["mlockall"] = os.sched_getscheduler(0)
        return True

    monkeypatch.setattr(sched, "_mlockall", mlockall)

    def on_gc(phase, info):
        if phase == "start":
            seen.setdefault("gc", os.sched_getscheduler(0))

    gc.callbacks.append(on_gc)
    try:
        report = apply_realtime(priority=10, cpus=None, lock_memory=True, freeze_gc=True)
    finally:
        gc.callbacks.remove(on_gc)
    if report["sched_fifo"] is not True:
        pytest.skip(f"SCHED_FIFO not granted here: {report['sched_fifo']}")
    fifo = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    assert seen["mlockall"] not in (os.SCHED_FIFO, fifo) and seen["gc"] not in (os.SCHED_FIFO, fifo)
    assert os.sched_getscheduler(0) in (os.SCHED_FIFO, fifo)
    assert list(report) == ["sched_fifo", "affinity", "mlockall", "gc_freeze"]


_ARROW_CHILD = (
    "import json, rt_ident, numpy as np, pyarrow as pa, pyarrow.parquet as pq, sys\n"
    "def vm():\n"
    "    return next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmSize'))\n"
    "before = vm()\n"
    "pq.write_table(pa.table({'t': np.arange(1e5)}), sys.argv[1]); pq.read_table(sys.argv[1])\n"
    "print(json.dumps({'pool': pa.default_memory_pool().backend_name, 'grew_mb': (vm() - before) / 1024}))\n"
)


@pytest.mark.parametrize("env", [None, "jemalloc"], ids=["default", "users-own"])
def test_a_recording_written_and_read_in_process_maps_no_arena_a_real_time_lock_would_pin(tmp_path, env):
    """mlockall faults in every page a process maps: Arrow's mimalloc arena (1 GiB at its first
    allocation) would be pinned by the next real-time run in the same process. A user's own pool stays."""
    environ = {k: v for k, v in os.environ.items() if k != "ARROW_DEFAULT_MEMORY_POOL"}
    if env is not None:
        environ["ARROW_DEFAULT_MEMORY_POOL"] = env
    out = subprocess.run([sys.executable, "-c", _ARROW_CHILD, str(tmp_path / "r.parquet")], env=environ,
                         capture_output=True, text=True, timeout=120, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    if env is None:
        assert got["pool"] == "system" and got["grew_mb"] < 256, got
    else:
        assert got["pool"] == env, got

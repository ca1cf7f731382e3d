"""Fixed-rate ticks on absolute deadlines, lateness statistics, real-time setup.

The loop (as in ros2_control's controller manager) is read, update, write,
then sleep until the next *absolute* deadline ``t0 + k * period``. Deadlines
are computed from the start time and the tick index, never by adding a sleep
to "now", so errors do not accumulate (relative sleeps can tick at 893 Hz
instead of 1 kHz on a VM: docs/measurements.md).

Waiting is done in two phases: ``time.sleep`` until ``spin_s`` before the
deadline (on CPython >= 3.11 / Linux ``time.sleep`` is implemented with
``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`` on ``now + secs``, and
``time.perf_counter`` reads the same CLOCK_MONOTONIC), then a short spin on
the clock. The spin is capped at half a period: under SCHED_FIFO a thread
that busy-waits whole periods is paused by the kernel's RT throttle.

The sleep itself is cut into chunks of at most ``max_sleep_s`` (default
100 us). On a KVM guest a thread that sleeps most of a tick lets the vCPU
halt, and the host now and then takes milliseconds to run it again. Halts
shorter than the host's KVM halt-polling window (``halt_poll_ns``, 200 us by
default) are resumed by polling, without a trip through the host scheduler,
so a sleeper cut into 100-200 us sleeps is not late that way (figures:
docs/measurements.md, "Host facts behind the loop's design"). On bare metal
the chunks only cost a few extra wake-ups per tick; ``max_sleep_s=None``
sleeps in one piece.

When a deadline is missed by more than one period, the ticker counts an
overrun and *skips* whole periods, so the loop resumes on the original grid
instead of bursting through the missed ticks to catch up.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import math
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)

Clock = Callable[[], float]
Sleeper = Callable[[float], None]


@dataclass(frozen=True, slots=True)
class TickInfo:
    """What :meth:`Ticker.wait_next` returns.

    index : tick number k; its deadline is ``t0 + k * period`` (k counts skipped ticks too)
    deadline : absolute deadline of this tick on the ticker's clock [s]
    lateness_s : clock reading after the wait minus ``deadline`` (>= 0 with a monotonic clock)
    skipped : whole periods skipped before this tick because of an overrun (0 normally)
    """

    index: int
    deadline: float
    lateness_s: float
    skipped: int


class Ticker:
    """Fixed-rate ticks on absolute deadlines ``t0 + k * period``.

    Parameters
    ----------
    period_s : tick period [s], > 0
    clock : monotonic clock in seconds (injected in tests)
    sleeper : ``sleeper(seconds)`` blocks for about that long; default ``time.sleep``
    spin_s : how long before the deadline to stop sleeping and spin; ``0 <= spin_s <= period_s / 2``
    max_sleep_s : longest single sleep (the wait is cut into sleeps of at most this); None: one sleep
    """

    def __init__(
        self,
        period_s: float,
        *,
        clock: Clock = time.perf_counter,
        sleeper: Sleeper | None = None,
        spin_s: float = 150e-6,
        max_sleep_s: float | None = 100e-6,
    ) -> None:
        try:
            period_s = float(period_s)
            spin_s = float(spin_s)
        except (TypeError, ValueError):
            raise ConfigError("period_s", f"period_s and spin_s must be numbers, got {period_s!r}, "
                                          f"{spin_s!r}") from None
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigError("period_s", f"must be a finite number > 0, got {period_s!r}")
        if not (math.isfinite(spin_s) and 0.0 <= spin_s <= 0.5 * period_s):
            # Never busy-wait (close to) a whole period: under SCHED_FIFO the RT throttle pauses the thread.
            raise ConfigError("spin_s", f"must be in [0, period_s/2 = {0.5 * period_s!r}], got {spin_s!r}")
        if max_sleep_s is not None:
            try:
                max_sleep_s = float(max_sleep_s)
            except (TypeError, ValueError):
                raise ConfigError("max_sleep_s", f"must be a number or None, got {max_sleep_s!r}") from None
            if not (math.isfinite(max_sleep_s) and max_sleep_s > 0.0):
                raise ConfigError("max_sleep_s", f"must be a finite number > 0 (or None), got {max_sleep_s!r}")
        self.period_s = period_s
        self.spin_s = spin_s
        self.max_sleep_s = max_sleep_s
        self._clock = clock
        self._sleep = sleeper if sleeper is not None else time.sleep
        self._t0: float | None = None
        self._index = 0
        self.overruns = 0        # ticks on which at least one whole period was skipped
        self.skipped_total = 0   # whole periods skipped in total
        self.ticks = 0           # ticks returned by wait_next()

    @property
    def t0(self) -> float | None:
        """Start time (deadline of tick 0), or None before :meth:`start`."""
        return self._t0

    @property
    def started(self) -> bool:
        return self._t0 is not None

    def next_deadline(self) -> float:
        """The deadline the next :meth:`wait_next` waits for (if it is not missed), on the ticker's clock."""
        if self._t0 is None:
            raise RuntimeError("next_deadline() before start()")
        return self._t0 + (self._index + 1) * self.period_s

    def start(self, t0: float | None = None) -> float:
        """Anchor the grid: tick k has deadline ``t0 + k * period``. Returns t0.

        ``wait_next()`` calls this with the current time when not started.
        """
        self._t0 = float(self._clock() if t0 is None else t0)
        self._index = 0
        return self._t0

    def deadline(self, index: int) -> float:
        """Absolute deadline of tick ``index`` (computed from t0, so it never drifts)."""
        if self._t0 is None:
            raise ConfigError("t0", "ticker not started; call start() or wait_next() first")
        return self._t0 + index * self.period_s

    def wait_next(self) -> TickInfo:
        """Block until the next tick's absolute deadline and return its :class:`TickInfo`.

        If the next deadline has already passed by more than one period, the
        missed periods are skipped (``skipped`` > 0, ``overruns`` incremented)
        and the tick on the grid just before "now" is returned at once.
        """
        t0 = self.start() if self._t0 is None else self._t0
        clock = self._clock
        period = self.period_s
        k = self._index + 1
        deadline = t0 + k * period
        now = clock()
        skipped = 0
        late = now - deadline
        if late > period:
            # Overrun: skip whole periods (never burst to catch up), as ros2_control does.
            skipped = int(late // period)
            k += skipped
            deadline = t0 + k * period
            if deadline > now:  # floating-point edge: stay on a deadline that has passed
                k -= 1
                skipped -= 1
                deadline = t0 + k * period
            if skipped > 0:
                self.overruns += 1
                self.skipped_total += skipped
        else:
            wake = deadline - self.spin_s
            chunk = self.max_sleep_s
            remaining = wake - now
            if chunk is None:
                if remaining > 0.0:
                    self._sleep(remaining)
            else:
                while remaining > 0.0:  # short sleeps: the vCPU never halts long (module docstring)
                    self._sleep(remaining if remaining < chunk else chunk)
                    remaining = wake - clock()
            now = clock()
            while now < deadline:  # short spin; at most spin_s (plus sleep undershoot)
                now = clock()
        self._index = k
        self.ticks += 1
        return TickInfo(k, deadline, now - deadline, skipped)


class LatenessHistogram:
    """Fixed-memory histogram of tick lateness with log-spaced bins in microseconds.

    Bins cover ``[lo_us, hi_us)`` with ``bins_per_decade`` bins per decade;
    values below ``lo_us`` (including 0 and negative lateness) go to an
    underflow bin, values at or above ``hi_us`` to an overflow bin. Exact
    count, sum, min and max are kept. :meth:`record` allocates nothing beyond
    Python floats. Percentiles interpolate log-linearly inside the bin and are
    clamped to the exact observed min/max, so their relative error is at most
    one bin width (``10**(1/bins_per_decade) - 1``, 4.7 % by default).
    """

    def __init__(self, lo_us: float = 0.1, hi_us: float = 1e6, bins_per_decade: int = 50) -> None:
        if not (0.0 < lo_us < hi_us) or not math.isfinite(hi_us):
            raise ConfigError("lo_us", f"need 0 < lo_us < hi_us < inf, got {lo_us!r}, {hi_us!r}")
        if int(bins_per_decade) < 1:
            raise ConfigError("bins_per_decade", f"must be >= 1, got {bins_per_decade!r}")
        self.lo_us = float(lo_us)
        self.hi_us = float(hi_us)
        self.bins_per_decade = int(bins_per_decade)
        self._log_lo = math.log10(self.lo_us)
        self.n_bins = int(math.ceil((math.log10(self.hi_us) - self._log_lo) * self.bins_per_decade))
        # counts[0] underflow, counts[1..n_bins] log bins, counts[n_bins+1] overflow
        self._counts = [0] * (self.n_bins + 2)
        self.count = 0
        self.sum_us = 0.0
        self.min_us = math.inf
        self.max_us = -math.inf

    def reset(self) -> None:
        for i in range(len(self._counts)):
            self._counts[i] = 0
        self.count = 0
        self.sum_us = 0.0
        self.min_us = math.inf
        self.max_us = -math.inf

    def record(self, lateness_s: float) -> None:
        """Add one lateness sample given in seconds."""
        us = lateness_s * 1e6
        self.count += 1
        self.sum_us += us
        if us < self.min_us:
            self.min_us = us
        if us > self.max_us:
            self.max_us = us
        if us < self.lo_us:
            self._counts[0] += 1
        elif us >= self.hi_us:
            self._counts[-1] += 1
        else:
            i = int((math.log10(us) - self._log_lo) * self.bins_per_decade)
            if i >= self.n_bins:
                i = self.n_bins - 1
            self._counts[i + 1] += 1

    def record_many(self, lateness_s: Iterable[float]) -> None:
        for v in lateness_s:
            self.record(float(v))

    def counts(self) -> np.ndarray:
        """Copy of the counts: [underflow, bins..., overflow]."""
        return np.asarray(self._counts, dtype=np.int64)

    def bin_edges_us(self) -> np.ndarray:
        """Edges of the log bins (n_bins + 1 values, the last clipped to hi_us)."""
        e = 10.0 ** (self._log_lo + np.arange(self.n_bins + 1) / self.bins_per_decade)
        e[-1] = min(e[-1], self.hi_us)
        return e

    def percentile(self, q: float) -> float:
        """Approximate q-th percentile (0..100) in µs; NaN when empty."""
        if not 0.0 <= q <= 100.0:
            raise ConfigError("q", f"must be in [0, 100], got {q!r}")
        if self.count == 0:
            return math.nan
        target = q / 100.0 * self.count
        cum = 0
        nb = self.n_bins
        for j, c in enumerate(self._counts):
            if c == 0 or cum + c < target:
                cum += c
                continue
            frac = (target - cum) / c
            if j == 0:
                lo, hi = self.min_us, min(self.lo_us, self.max_us)
                value = lo + frac * (hi - lo)
            elif j == nb + 1:
                lo, hi = max(self.hi_us, self.min_us), self.max_us
                value = lo + frac * (hi - lo)
            else:
                a = self._log_lo + (j - 1) / self.bins_per_decade
                value = 10.0 ** (a + frac / self.bins_per_decade)
            return min(max(value, self.min_us), self.max_us)
        return self.max_us

    def summary(self) -> dict[str, float]:
        """``count`` and, in µs, ``mean``, ``p50``, ``p99``, ``max`` (NaN when empty)."""
        return {
            "count": float(self.count),
            "mean": self.sum_us / self.count if self.count else math.nan,
            "p50": self.percentile(50.0),
            "p99": self.percentile(99.0),
            "max": self.max_us if self.count else math.nan,
        }


# --- real-time setup -------------------------------------------------------------

_MCL_CURRENT = 1
_MCL_FUTURE = 2


def _libc() -> ctypes.CDLL | str:
    """The C library (errno kept), or why it does not load. From the process's own symbols first: a
    dynamically linked Python has it loaded, and ``find_library`` runs ``ldconfig`` in a child process."""
    try:
        own = ctypes.CDLL(None, use_errno=True)
        if hasattr(own, "mlockall") and hasattr(own, "munlockall"):
            return own
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError as exc:
        return f"libc not loadable: {exc}"


def _mlockall() -> bool | str:
    libc = _libc()
    if isinstance(libc, str):
        return libc
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        return f"mlockall failed: [Errno {err}] {os.strerror(err)} (needs CAP_IPC_LOCK or a memlock rlimit)"
    return True


def locked_memory_kb() -> int | None:
    """This process's locked memory (``VmLck``), in kB; None where ``/proc`` does not say."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmLck:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def unlock_memory() -> bool | str:
    """``munlockall()``: the process's pages unlocked and new mappings no longer locked (``MCL_FUTURE``
    ends with it). Without it, a process that goes on after its run (a commissioning's next stage, the
    final fit, a caller's own work) faults in and pins every page it maps from then on."""
    libc = _libc()
    if isinstance(libc, str):
        return libc
    if libc.munlockall() != 0:
        err = ctypes.get_errno()
        return f"munlockall failed: [Errno {err}] {os.strerror(err)}"
    return True


def apply_realtime(
    priority: int | None = 50,
    cpus: Iterable[int] | None = None,
    lock_memory: bool = True,
    freeze_gc: bool = True,
) -> dict[str, bool | str]:
    """Ask for real-time treatment of the calling process; never raises.

    Tries, independently and in this order: CPU affinity to ``cpus`` (``None``
    skips), ``mlockall(MCL_CURRENT | MCL_FUTURE)``, ``gc.collect(); gc.freeze();
    gc.disable()`` (the caller may ``gc.collect()`` outside the hot path or
    ``gc.enable()`` afterwards), and SCHED_FIFO at ``priority`` (``None`` skips).

    Returns ``{"sched_fifo": ..., "affinity": ..., "mlockall": ..., "gc_freeze": ...}``
    where each value is ``True`` when granted, else a string saying why not
    (``"not requested"`` when skipped).
    """
    # SCHED_FIFO last: locking the memory (faulting every page in) and collecting a large heap take
    # tenths of a second of CPU, which need not run ahead of everything else on the loop's CPU
    report: dict[str, bool | str] = dict.fromkeys(("sched_fifo", "affinity", "mlockall", "gc_freeze"), "")

    if cpus is None:
        report["affinity"] = "not requested"
    else:
        try:
            os.sched_setaffinity(0, set(int(c) for c in cpus))
            report["affinity"] = True
        except AttributeError:
            report["affinity"] = "sched_setaffinity not available on this platform"
        except Exception as exc:  # noqa: BLE001
            report["affinity"] = f"denied: {exc}"

    if not lock_memory:
        report["mlockall"] = "not requested"
    else:
        try:
            report["mlockall"] = _mlockall()
        except Exception as exc:  # noqa: BLE001
            report["mlockall"] = f"failed: {exc}"

    if not freeze_gc:
        report["gc_freeze"] = "not requested"
    else:
        try:
            gc.collect()
            gc.freeze()
            gc.disable()
            report["gc_freeze"] = True
        except Exception as exc:  # noqa: BLE001
            report["gc_freeze"] = f"failed: {exc}"

    if priority is None:
        report["sched_fifo"] = "not requested"
    else:
        try:
            lo = os.sched_get_priority_min(os.SCHED_FIFO)
            hi = os.sched_get_priority_max(os.SCHED_FIFO)
            prio = min(max(int(priority), lo), hi)
            # RESET_ON_FORK: a helper restarted from the loop thread (rt_ident.processes.guard) must
            # not inherit SCHED_FIFO - importing numpy at FIFO 50 on the loop's CPU starves the loop for
            # seconds, and a torque-mode axis runs away
            os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(prio))
            report["sched_fifo"] = True
            if prio != priority:
                log.info("SCHED_FIFO priority %s clamped to %s", priority, prio)
        except AttributeError:
            report["sched_fifo"] = "SCHED_FIFO not available on this platform"
        except Exception as exc:  # noqa: BLE001 - the report carries the reason
            report["sched_fifo"] = f"denied: {exc}"

    granted = [k for k, v in report.items() if v is True]
    refused = {k: v for k, v in report.items() if v is not True and v != "not requested"}
    if refused:
        log.warning("real-time setup: granted %s; not granted %s", granted, refused)
    else:
        log.info("real-time setup: granted %s", granted)
    return report


__all__ = ["TickInfo", "Ticker", "LatenessHistogram", "apply_realtime"]

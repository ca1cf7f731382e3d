"""One real-time loop per CPU on a host: an exclusive claim on the loop's CPU for the length of a run.

Every real-time loop takes the host's last CPU at SCHED_FIFO (rt_ident.loop.host). Two of them there
(a second ``rt-ident`` started while one runs) are never time-sliced against each other: each one's
cycle waits for the other's, and their spins together pass the kernel's RT budget (95 % of each second),
after which both are paused for the rest of the second, up to 50 ms. A drive watching its RPDOs then
faults, and an axis coasts. So a loop claims its CPU before it turns real-time: an ``flock`` on a file
named after the CPU (:mod:`rt_ident.hostlock`), which the kernel drops when the process ends, however it
ends. A second loop waits for the first to end (``[loop] cpu_wait_s``), saying once whom it
waits for, and then refuses to start, before anything is energized.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

from rt_ident.errors import ConfigError, RtIdentError
from rt_ident.hostlock import holder, lock_dir, try_flock

log = logging.getLogger(__name__)

#: How often a waiting loop tries the claim again [s].
POLL_S = 0.01


class CpuWaitInterrupted(RtIdentError):
    """Stopped (a signal) while waiting for the CPU: nothing was energized, the run ends as asked."""

    cause = None


def claim_path(cpu: int, directory: str | os.PathLike[str] | None = None) -> Path:
    """The file whose lock is the claim on ``cpu``: in ``directory``, else the host's lock directory."""
    return lock_dir(directory) / f"rt-ident-loop-cpu{int(cpu)}.lock"


class CpuClaim:
    """The claim on one CPU: :meth:`acquire` (waits up to ``wait_s``), :meth:`release` (idempotent).

    Within one process the claim is counted, not locked twice: a real-time section started before
    another of the same process has ended shares its claim instead of waiting on itself.
    """

    _held: dict[Path, tuple[int, int]] = {}          # path -> (fd, count), this process's claims
    _lock = threading.Lock()

    def __init__(self, cpu: int, wait_s: float, stop: threading.Event | None = None,
                 directory: str | os.PathLike[str] | None = None) -> None:
        self.cpu = int(cpu)
        self.wait_s = float(wait_s)
        self.stop = stop
        self.path = claim_path(cpu, directory)
        self.waited_s = 0.0
        self._mine = False

    def _try(self) -> bool:
        with CpuClaim._lock:
            held = CpuClaim._held.get(self.path)
            if held is not None:
                CpuClaim._held[self.path] = (held[0], held[1] + 1)
                return True
            fd = try_flock(self.path)
            if fd is None:
                return False
            CpuClaim._held[self.path] = (fd, 1)
            return True

    def _who(self) -> str:
        return holder(self.path) or "another process"

    def acquire(self) -> None:
        """Hold the CPU, or raise: :class:`ConfigError` (``loop.cpu_wait_s``) after ``wait_s``,
        :class:`CpuWaitInterrupted` when ``stop`` is set while waiting."""
        if self._mine:
            return
        t0 = time.monotonic()
        said = False
        while not self._try():
            waited = time.monotonic() - t0
            if self.stop is not None and self.stop.is_set():
                raise CpuWaitInterrupted(f"stopped while waiting for CPU {self.cpu}, which {self._who()} holds "
                                         "for its real-time loop; nothing was energized")
            if waited >= self.wait_s:
                raise ConfigError("loop.cpu_wait_s", f"CPU {self.cpu} is still held by the real-time loop of "
                                  f"{self._who()} after {waited:.1f} s: let that run end first, give this one longer "
                                  "(loop.cpu_wait_s) or run it without real time (loop.realtime = false)")
            if not said:
                log.warning("CPU %d is held by the real-time loop of %s: waiting up to %g s for it "
                            "(loop.cpu_wait_s)", self.cpu, self._who(), self.wait_s)
                said = True
            time.sleep(POLL_S)
        self.waited_s = time.monotonic() - t0
        self._mine = True

    def release(self) -> None:
        if not self._mine:
            return
        self._mine = False
        with CpuClaim._lock:
            fd, count = CpuClaim._held[self.path]
            if count > 1:
                CpuClaim._held[self.path] = (fd, count - 1)
                return
            del CpuClaim._held[self.path]
        os.close(fd)                                  # closing the only descriptor drops the lock


__all__ = ["CpuClaim", "CpuWaitInterrupted", "claim_path"]

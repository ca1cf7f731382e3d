"""Keep the loop's CPU busy while the loop sleeps, at the lowest priority there is.

On a KVM guest every tick that follows a sleep runs slow: the loop thread sleeps ~0.8 ms of each
1 ms tick, and the tick after it spends ~35 % longer in every part (read, filters, estimators, plan)
than the same code run back to back, most of it in whichever axis goes first; a loop that never
sleeps runs the same tick markedly faster (figures: docs/measurements.md, "Host facts behind the
loop's design"). The likely cause is the vCPU going idle (the guest halts it, the host runs something
else, the timer's wake-up goes through the hypervisor) and the interpreter's caches and branch
predictors going cold with it; the mechanism is not proven, the effect is. Spinning in the loop
thread itself is not an option: under SCHED_FIFO a thread that never sleeps is paused for 50 ms of
every second by the kernel's RT throttle (overruns), and a spinning Python thread holds the GIL that
a CANopen backend's SYNC and receive threads need.

:class:`IdlePoller` is a thread pinned to the loop's CPU under ``SCHED_IDLE``: it runs only when
nothing else on that CPU wants to, so the loop (SCHED_FIFO) and any other thread preempt it at
once, and the RT throttle never counts it. It spins inside one compiled call
(``numba.njit(nogil=True)``) from start to stop, so it never holds the GIL while it spins. With it
the vCPU does not halt, and rt_ident.compose.run lets the ticker sleep in one piece instead of
100 us pieces. What it buys depends on the machine: ``rt-ident bench xy`` runs the two-axis tick with
and without it side by side (docs/measurements.md). The cost is the loop's CPU at 100 % for the
length of the run (the loop has that CPU to itself already: rt_ident.compose.run keeps every helper
off it). ``[loop] idle_poll = false`` turns it off.

The thread is at ``SCHED_IDLE`` only inside the compiled call, where it holds no GIL: it enters and
leaves the call as an ordinary thread. A ``SCHED_IDLE`` thread holding or waiting for the GIL stalls
the real-time threads of this process: CPython makes a thread that hands over the GIL on request
wait until the requester has taken it, and beside any other busy thread on that CPU a ``SCHED_IDLE``
requester may not run for hundreds of milliseconds. Callers compile the spin (:meth:`IdlePoller.prepare`)
before they turn real-time, and stop the poller once the threads it could stall (a SYNC sender) have
stopped.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any

import numba
import numpy as np
from numba.core import types

log = logging.getLogger(__name__)

# libc by symbol name, resolved in the process when the code is loaded: no address of this process's is
# compiled in, so numba caches the spin beside the package (pointers pass as pointer-sized integers;
# callable only from compiled code, hence Any)
_clock_gettime: Any = types.ExternalFunction("clock_gettime", types.intc(types.intc, types.uintp))
_setscheduler: Any = types.ExternalFunction("sched_setscheduler", types.intc(types.intc, types.intc, types.uintp))
_MONOTONIC, _IDLE, _OTHER = time.CLOCK_MONOTONIC, os.SCHED_IDLE, os.SCHED_OTHER


@numba.njit(nogil=True, cache=True)
def _spin(stop, ts, state):
    """Runs without the GIL from the first iteration to the last: a thread that came back to Python between
    chunks could be preempted holding the GIL, and at SCHED_IDLE beside a busy process it might not run again
    for many milliseconds while the loop waited for the GIL. SCHED_IDLE is taken here and left here (pid 0:
    this thread), so that the thread holds and takes the GIL only as an ordinary thread. state[0]: 1 once
    idle, -1 if refused; state[1]: 0 if the policy was given back on the way out. The call to clock_gettime
    (vDSO, no system call) is opaque to the compiler, so stop[0] is read again on every iteration."""
    param = state[2:].ctypes.data                  # struct sched_param {int priority}: zeros
    if _setscheduler(0, _IDLE, param) != 0:
        state[0] = -1
        return 0
    state[0] = 1
    n = 0
    where = ts.ctypes.data
    while stop[0] == 0:
        _clock_gettime(_MONOTONIC, where)
        n += 1
    state[1] = _setscheduler(0, _OTHER, param)
    return n


class IdlePoller:
    """A thread that keeps ``cpu`` busy at ``SCHED_IDLE`` until :meth:`stop` (a context manager too).

    :meth:`prepare` compiles the spin (call it before the caller turns real-time); :meth:`start`
    returns once the thread spins at ``SCHED_IDLE`` on its CPU, with a report: ``{"running": True,
    "cpu": ..., "policy": "SCHED_IDLE"}``, or ``{"running": False, "reason": ...}`` when it could not
    be placed (the thread has ended then). ``iterations`` is the spin's count once stopped;
    ``exit_policy`` the policy the thread had when it took the GIL back (``os.SCHED_OTHER`` unless
    the kernel refused to give ``SCHED_IDLE`` up).
    """

    def __init__(self, cpu: int) -> None:
        self.cpu = int(cpu)
        self.iterations = 0
        self.exit_policy: int | None = None
        self._stop = np.zeros(1, dtype=np.int64)
        self._ts = np.zeros(2, dtype=np.int64)
        self._state = np.zeros(4, dtype=np.int32)     # [idle?, exit setscheduler result, sched_param...]
        self._spin: Any = None                        # the compiled spin (a numba dispatcher), by prepare()
        self._thread: threading.Thread | None = None
        self._placed = threading.Event()
        self._report: dict[str, Any] = {}

    def prepare(self) -> None:
        """Compile the spin (idempotent; raises what the compiler raises)."""
        if self._spin is None:
            # compiled for these arrays without running it (a run would switch the caller to SCHED_IDLE)
            _spin.compile(tuple(numba.typeof(a) for a in (self._stop, self._ts, self._state)))
            self._spin = _spin

    def start(self, timeout: float = 10.0) -> dict[str, Any]:
        self.prepare()
        self._state[:2] = 0
        self._thread = threading.Thread(target=self._run, name="rt_ident-idle-poll", daemon=True)
        self._thread.start()
        end = time.monotonic() + timeout
        if not self._placed.wait(timeout):
            self.stop()
            return {"running": False, "reason": f"the thread did not start within {timeout:g} s"}
        if not self._report.get("running"):
            self._thread.join(timeout)
            return dict(self._report)
        while self._state[0] == 0 and self._thread.is_alive() and time.monotonic() < end:
            time.sleep(1e-3)                           # the thread is on its way into the spin
        if self._state[0] != 1:
            self.stop()
            why = ("the kernel refused SCHED_IDLE" if self._state[0] == -1
                   else f"it did not reach SCHED_IDLE within {timeout:g} s")
            return {"running": False, "reason": f"cannot place the poller on CPU {self.cpu}: {why}"}
        return dict(self._report)

    def _run(self) -> None:
        try:
            os.sched_setaffinity(0, {self.cpu})          # this thread only (Linux: 0 is the caller)
        except (AttributeError, OSError, ValueError) as exc:
            self._report = {"running": False, "reason": f"cannot place the poller on CPU {self.cpu}: {exc}"}
            self._placed.set()
            return
        self._report = {"running": True, "cpu": self.cpu, "policy": "SCHED_IDLE"}
        self._placed.set()
        self.iterations = int(self._spin(self._stop, self._ts, self._state))
        self.exit_policy = os.sched_getscheduler(0)

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and wait for it (idempotent)."""
        self._stop[0] = 1
        th = self._thread
        if th is not None and th.is_alive() and th is not threading.current_thread():
            th.join(timeout)
            if th.is_alive():                            # daemon: it cannot keep the process alive
                log.warning("idle poller did not stop within %g s", timeout)

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> IdlePoller:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = ["IdlePoller"]

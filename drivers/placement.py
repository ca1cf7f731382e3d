"""Where an emulated device runs: its CPU set and scheduling, so the real-time loop cannot starve it.

A real drive or encoder board has its own processor and clock. An emulated one shares this
host's CPUs with the loop, which (when real-time) runs SCHED_FIFO on the last CPU and barely
yields it. An emulator on that CPU then answers late and the loop sees stale data. Both ways of
starting an emulator use the same placement: the loop's own child process
(:class:`rt_ident.processes.emulation.EmulatorProcess`) and the command line
(``python -m drivers.cia402.emulator``, ``python -m drivers.encoder_board.emulator``).
"""

from __future__ import annotations

import gc
import os
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

#: SCHED_FIFO priority of an emulated device when the loop is real-time (the loop has 50).
EMULATOR_FIFO_PRIORITY = 40


def helper_cpus(realtime: bool) -> list[int] | None:
    """Every CPU but the loop's (the last one, see rt_ident.compose.run) when the loop is real-time."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None
    return cpus[:-1] if realtime and len(cpus) >= 2 else None


def device_placement(realtime: bool = True) -> dict[str, Any]:
    """The placement of an emulated device beside a (real-time) loop."""
    return {"cpus": helper_cpus(realtime), "fifo_priority": EMULATOR_FIFO_PRIORITY if realtime else None}


def keep_to(cpus: list[int] | None) -> dict[str, Any]:
    """Keep the calling thread to ``cpus`` (call it before starting any other thread: new threads
    inherit it). Returns what was applied, or why not ("denied: ...")."""
    if not cpus:
        return {}
    try:
        os.sched_setaffinity(0, set(cpus))
    except (AttributeError, OSError) as exc:
        return {"cpus": f"denied: {exc}"}
    return {"cpus": sorted(cpus)}


def _threads() -> set[int]:
    """The native ids of this process's threads now."""
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def start_realtime(start: Callable[[], T], priority: int | None) -> tuple[T, dict[str, Any]]:
    """``start()`` (which builds a device and starts its threads) at ordinary scheduling, then
    SCHED_FIFO at ``priority`` for the threads it started. Returns the device and what was applied, or
    why not ("denied: ...").

    Only the device's streaming is real-time. Building the device (its object dictionary, its plant, the
    first calls of its compiled kernels: tens of ms of CPU, more on a busy host), its report and
    the interpreter's exit stay in the calling thread at ordinary scheduling: at SCHED_FIFO they would
    hold the CPU against the other emulated devices there, which share the priority and are never
    time-sliced against it. Threads started before (numpy's BLAS pool, spinning when it works) keep
    theirs too."""
    before = _threads()
    device = start()
    if not priority:
        return device, {}
    threads = _threads() - before
    if not threads:
        return device, {"sched_fifo": "no device thread"}
    try:
        for tid in sorted(threads):
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(int(priority)))
            except ProcessLookupError:                # the thread ended meanwhile
                pass
    except (AttributeError, OSError) as exc:
        return device, {"sched_fifo": f"denied: {exc}"}
    return device, {"sched_fifo": int(priority)}


def clear_heap() -> None:
    """Collect once, before the device starts its threads (call it before :func:`place` too).

    Importing numba, canopen and the plant leaves a few hundred thousand long-lived objects; the
    collector's first full pass over them takes ~60 ms and holds the GIL: with the device's threads
    running, a drive could not answer a SYNC or send a heartbeat for that long, a pause a real drive's
    firmware never takes. Before they start, nothing waits on it."""
    gc.collect()


def settle_heap() -> None:
    """Once the device is up: put every object alive now out of the cyclic collector's reach
    (``gc.freeze``) without a collection: a full pass then would hold the GIL for 20-50 ms against the
    device's threads. What starting the device left for garbage (~2 300 objects for the CiA 402 drive)
    stays. The collector stays on for what the device allocates later: those passes are short."""
    gc.freeze()

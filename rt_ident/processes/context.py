"""The multiprocessing context every helper process and emulated device is started from.

A spawned child imports numpy, numba, scipy, rerun and pyarrow again (seconds of CPU
per run on a small machine, and the imports of several helpers compete with the loop's start). On
Linux the helpers are forked instead from one forkserver per main process that has imported those
modules once (:data:`PRELOAD`). Each child still starts from a clean, single-threaded process: the
forkserver runs no threads (a test checks) and holds nothing of the run.

What spawned children got from their parent at ``start()`` they get from the forkserver, so the
forkserver is started the way helpers must be born: the group's signals ignored (SIGINT, SIGTERM, SIGHUP;
its children inherit that, with no window before :func:`rt_ident.processes.guard.become_helper`, and so
does multiprocessing's resource tracker, started with it: one killed by a closed terminal's SIGHUP
would leave the run's semaphores in /dev/shm) and
:data:`~rt_ident.processes.guard.HELPER_ENV` in its environment (one BLAS thread; it is read at
numpy's import, which the forkserver does). Each child takes its starter's current stdout, stderr and
environment as it starts (:func:`rt_ident.processes.guard.start_with_helper_env`). The forkserver exits
once the main process and every child have ended. ``RT_IDENT_START_METHOD=spawn`` spawns the helpers
instead (the default where the platform has no forkserver).
"""

from __future__ import annotations

import _thread
import atexit
import multiprocessing as mp
import multiprocessing.util  # noqa: F401 - its exit handler is registered before this module's (below)
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from multiprocessing.context import ForkServerContext, SpawnContext
from typing import Any, TypeVar

T = TypeVar("T")

#: modules the forkserver imports once (one missing is skipped by multiprocessing). Not rerun nor pyarrow:
#: they start threads at import (tokio's workers, jemalloc's), and a process with threads must not fork. Nor
#: scipy.signal: about a second of CPU per run, for the few helpers that import it themselves when they need it
PRELOAD = ("numpy", "scipy.linalg", "numba", "can", "canopen", "serial",
           "rt_ident.processes.jobs", "rt_ident.processes.recorder", "rt_ident.processes.telemetry",
           "rt_ident.processes.emulation", "rt_ident.estimators.streaming", "rt_ident.control.design")

_lock = threading.Lock()


def start_method() -> str:
    """``forkserver`` where the platform has it, unless ``RT_IDENT_START_METHOD=spawn``."""
    wanted = os.environ.get("RT_IDENT_START_METHOD", "").strip().lower()
    usable = [m for m in ("forkserver", "spawn") if m in mp.get_all_start_methods()]
    if wanted:
        if wanted not in usable:
            raise ValueError(f"RT_IDENT_START_METHOD={wanted!r}: use one of {', '.join(usable)}")
        return wanted
    return usable[0]


def helper_context() -> ForkServerContext | SpawnContext:
    """The context to create helper processes and their shared memory from (started on first use)."""
    method = start_method()
    if method == "forkserver":
        fs = mp.get_context("forkserver")
        _ensure_forkserver(fs)
        return fs
    return mp.get_context("spawn")


class Prestart:
    """The forkserver started ahead of need (:func:`prestart`); :meth:`discard` ends it again, unused."""

    def __init__(self, started: bool) -> None:
        self.started = started

    def discard(self) -> None:
        """End the forkserver this started, at once: only while no helper has been started from it (a start
        refused before any process). It ignores SIGTERM and may still be importing, so it is killed."""
        if not self.started:
            return
        self.started = False
        end_forkserver(0.0)


def end_forkserver(wait_s: float) -> None:
    """End the forkserver this process started and reap it: its pipe closed, then ``wait_s`` for it to exit
    (it reads the pipe only once its preloads are imported), then SIGKILL (it ignores SIGTERM)."""
    from multiprocessing import forkserver, util

    server: Any = forkserver._forkserver                # multiprocessing keeps no public handle on it
    with _lock:
        pid = getattr(server, "_forkserver_pid", None)
        if pid is None:
            return
        fd = getattr(server, "_forkserver_alive_fd", None)
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass
        deadline = time.monotonic() + wait_s
        try:
            while os.waitpid(pid, os.WNOHANG)[0] == 0:
                if time.monotonic() >= deadline:
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                    break
                time.sleep(0.002)
        except (ChildProcessError, ProcessLookupError):
            pass
        address = getattr(server, "_forkserver_address", None)
        if address and not util.is_abstract_socket_namespace(address):
            try:
                os.unlink(address)
            except OSError:
                pass
        server._forkserver_pid = server._forkserver_alive_fd = server._forkserver_address = None


def _at_exit() -> None:
    """At this process's exit: the helpers its starters never closed, then the forkserver, which would end by
    itself a moment after this process, as an orphan. The forkserver goes last and only with no child left:
    a forked child's exit status comes through it."""
    from rt_ident.processes.guard import end_left_helpers

    end_left_helpers()
    if not mp.active_children():
        end_forkserver(1.0)


# after multiprocessing.util's import registered its exit handler: handlers run last-registered first
atexit.register(_at_exit)


def prestart() -> Prestart:
    """Start the forkserver now, unless it runs: its preloads (about a second of CPU) then run beside the
    caller's own imports and checks instead of before its first helper. Nothing else is started."""
    if start_method() != "forkserver":
        return Prestart(False)
    from multiprocessing import forkserver

    running = getattr(forkserver._forkserver, "_forkserver_pid", None) is not None
    helper_context()
    return Prestart(not running)


def _ensure_forkserver(ctx: ForkServerContext) -> None:
    """Start the forkserver (or start it again, if it died) as helpers must be born; a no-op while it runs."""
    with _lock:
        from multiprocessing import forkserver

        from rt_ident.processes.guard import GROUP_SIGNALS, HELPER_ENV

        ctx.set_forkserver_preload(list(PRELOAD))
        added = [k for k in HELPER_ENV if k not in os.environ]
        for k in added:
            os.environ[k] = HELPER_ENV[k]
        main = threading.current_thread() is threading.main_thread()
        old = {s: signal.signal(s, signal.SIG_IGN) for s in GROUP_SIGNALS} if main else {}
        sched = _ordinary_scheduling()
        try:
            forkserver.ensure_running()
        finally:
            _restore_scheduling(sched)
            for s, h in old.items():
                signal.signal(s, h)
            for k in added:
                os.environ.pop(k, None)


def beside_the_loop(fn: Callable[[], T]) -> Future[T]:
    """``fn()`` on a thread of its own at SCHED_OTHER on every CPU, for work the loop's tick must not wait
    for (a helper's restart: the kill, new shared memory, the fork, each waiting on other processes that
    a busy host may not run for a long time). The thread does not inherit the loop's CPU or priority. The
    future holds what ``fn`` returned or raised."""
    fut: Future[T] = Future()

    def run() -> None:
        _ordinary_scheduling()
        fut.set_running_or_notify_cancel()
        try:
            fut.set_result(fn())
        except BaseException as exc:  # noqa: BLE001 - handed to whoever takes the result
            fut.set_exception(exc)

    # not threading.Thread.start(), which waits until the new thread runs: on the loop's CPU that is a few ms
    _thread.start_new_thread(run, ())
    return fut


def _ordinary_scheduling() -> tuple | None:
    """The calling thread on every CPU at SCHED_OTHER (a thread beside the loop; or while it starts the
    forkserver, which inherits both and passes them to every helper: a loop thread on its own CPU at
    SCHED_FIFO would otherwise start the helpers and emulated devices of every later run there). Returns
    what to restore."""
    try:
        saved = (os.sched_getscheduler(0), os.sched_getparam(0), os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None
    try:
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
        if saved[0] != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass
    return saved


def _restore_scheduling(saved: tuple | None) -> None:
    if saved is None:
        return
    policy, param, cpus = saved
    try:
        if policy != os.SCHED_OTHER:
            os.sched_setscheduler(0, policy, param)
        os.sched_setaffinity(0, cpus)
    except OSError:
        pass


__all__ = ["PRELOAD", "Prestart", "beside_the_loop", "end_forkserver", "helper_context", "prestart", "start_method"]

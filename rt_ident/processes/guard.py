"""How a run's helper processes (recorder, telemetry, fit and control processes) live and die.

* **Signals go to the main process only.** Ctrl-C in a terminal sends SIGINT to the whole process
  group, systemd's stop sends SIGTERM to the whole group, a closed terminal or a dropped ssh session
  SIGHUP (the shell passes it to its jobs). A helper that took them would die in the
  middle of its work (the recorder with samples still in its ring) or print a KeyboardInterrupt
  traceback; the main process would die without stopping the device. So the main process takes all
  three as a request to stop, and helpers are started with them *ignored* (:func:`start_ignoring_signals`:
  the disposition is inherited through the spawn's exec, and Python keeps an inherited SIG_IGN, so
  there is no window during the child's start-up), and set them ignored again first thing
  (:func:`become_helper`). The main process stops them in order: loop, then recorder (drains every
  sample, closes the file), telemetry, workers.
* **A helper notices its parent's death** (kill -9 of the main process) within ~0.2 s
  (:class:`ParentWatch`: the parent pid changes when the helper is re-parented) and then finishes
  what it holds (the recorder writes the Parquet file from every sample it received) and exits:
  no orphan keeps files open.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_log = logging.getLogger("rt_ident.processes.guard")


#: A helper's BLAS runs on one thread unless the user set otherwise. Its matrices are tiny (the control
#: process's 10-state loops, the fit process's 4-parameter normal equations): extra OpenBLAS threads only
#: spin between calls: with two threads on a 2-CPU machine a redesign costs the control process several
#: times the CPU of one thread, the helpers' CPU is full and a redesign answers seconds late
#: (docs/measurements.md, "After a load change on Y"). ``rt-ident`` sets the same in its own process
#: (rt_ident.cli); this covers helpers started by any other caller too.
HELPER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def start_with_helper_env(proc: Any) -> None:
    """``proc.start()`` with :data:`HELPER_ENV` in the environment the child is spawned with (a
    variable the user set is kept); this process's environment is restored afterwards. A child forked
    by the forkserver gets this process's stdout, stderr and environment too (:class:`_StartersStdio`)."""
    added = [k for k in HELPER_ENV if k not in os.environ]
    for k in added:
        os.environ[k] = HELPER_ENV[k]
    if getattr(proc, "_start_method", None) == "forkserver":
        proc._starters_stdio = _StartersStdio()
    try:
        proc.start()
    finally:
        for k in added:
            os.environ.pop(k, None)


def end_left_helpers() -> None:
    """End every helper its starter never closed (at this process's exit, :mod:`rt_ident.processes.context`).
    multiprocessing's exit handler sends its daemonic children SIGTERM, which helpers ignore, then joins them
    without a timeout: one left running would hold the exit for ever (it ends itself only once this process
    is gone)."""
    import multiprocessing

    for proc in multiprocessing.active_children():
        if proc.name.startswith("rt_ident-"):
            _log.warning("%s (pid %s) was still running at exit (never closed by what started it): ended",
                         proc.name, proc.pid)
            end_helper(proc, term_wait_s=0.2)


class _StartersStdio:
    """Carries the starting process's stdout, stderr and environment to a child of the forkserver.

    A forked child inherits the forkserver's fds 1 and 2 and environment, from whenever the forkserver
    was started: a later redirection (a log file, pytest's capture) or variable would not reach it, as
    it reaches a spawned child. Pickled with the process object, this sends the current fds 1 and 2
    (``multiprocessing.reduction.DupFd``: passed over the forkserver's socket) and ``os.environ``, and
    the child installs them as it unpickles its process object, before the helper's code runs.
    Variables read at import (BLAS threads, numba's) keep the forkserver's values: it preloaded them."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        from multiprocessing import reduction

        fds: list[Any] = []
        for fd in (1, 2):
            try:
                os.fstat(fd)
            except OSError:             # closed here: the child keeps the forkserver's
                fds.append(None)
                continue
            fds.append(reduction.DupFd(fd))
        return _adopt_starters_stdio, (fds[0], fds[1], dict(os.environ))


def _adopt_starters_stdio(out: Any, err: Any, env: dict[str, str]) -> None:
    for fd, dup in ((1, out), (2, err)):
        if dup is None:
            continue
        got = dup.detach()
        if got != fd:
            os.dup2(got, fd)
            os.close(got)
    os.environ.clear()
    os.environ.update(env)


def end_helper(proc: Any, term_wait_s: float = 1.0, kill_wait_s: float = 1.0) -> None:
    """End a helper process that is still alive: SIGTERM, then SIGKILL if it is there after
    ``term_wait_s``. Helpers are born ignoring SIGTERM (:func:`start_ignoring_signals`), so without
    the SIGKILL one lives on - and writes into shared memory a later helper may reuse."""
    if proc is None or not proc.is_alive():
        return
    proc.terminate()
    proc.join(term_wait_s)
    if proc.is_alive():
        proc.kill()
        proc.join(kill_wait_s)


def quick_exit(code: int = 0) -> None:
    """End a helper that has handed over everything it holds, skipping the interpreter's teardown
    (a few hundred ms with numba, scipy and python-control loaded, which the run's end would wait for)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    logging.shutdown()
    os._exit(code)


def start_ignoring_signals(proc: Any) -> None:
    """``proc.start()`` with the child born ignoring :data:`GROUP_SIGNALS` (and with :data:`HELPER_ENV`).

    A child of the forkserver inherits that from the forkserver (rt_ident.processes.context), so this
    process's own handlers stay in place: its start waits for the forkserver's preloads (up to a second
    after the forkserver itself started), and a Ctrl-C ignored meanwhile would be lost. A spawned child
    inherits this process's dispositions, ignored for the moment its start takes."""
    if (threading.current_thread() is not threading.main_thread()
            or getattr(proc, "_start_method", None) == "forkserver"):
        start_with_helper_env(proc)  # off the main thread dispositions cannot change; become_helper() covers it
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in GROUP_SIGNALS}
    try:
        start_with_helper_env(proc)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def stop_signals() -> tuple[int, ...]:
    """The signals a command's main process stops on: SIGINT and SIGTERM whatever their disposition (an
    inherited SIG_IGN included: a shell script's background job), SIGHUP unless it is ignored (``nohup``
    asked the command to outlive its terminal)."""
    return tuple(s for s in GROUP_SIGNALS if s != signal.SIGHUP or signal.getsignal(s) != signal.SIG_IGN)


def install_stop_signals(stop: threading.Event) -> dict[int, Any]:
    """:func:`stop_signals` set ``stop`` (in the main thread): the main process of a run that energizes a
    device, or of any long command, ends on them at a point of its choosing. Returns the handlers they had."""
    old: dict[int, Any] = {}
    if threading.current_thread() is not threading.main_thread():
        return old

    def handler(signum: int, frame: Any) -> None:  # noqa: ARG001
        stop.set()

    for sig in stop_signals():
        old[sig] = signal.signal(sig, handler)
    return old


def name_process(name: str) -> None:
    """Set the calling thread's kernel name (``/proc/PID/comm``, at most 15 bytes; threads it starts
    inherit it) on Linux, so that ps, top and pgrep tell a run's helpers apart: forked by the forkserver,
    they all carry its command line. Nothing elsewhere, and never raises."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)        # PR_SET_NAME
    except (OSError, AttributeError, UnicodeError):
        pass


#: Nice value of each helper role (any other helper: 10). The control process answers a redesign
#: request, rare and urgent: its latency is the time from a load change to the controller that fits
#: it. At the nice value of the fit processes, which refit without pause, it gets a fifth of the
#: helpers' CPU, and a 0.2 s redesign answers seconds late while the axis runs a controller that no
#: longer fits it (docs/measurements.md, "After a load change on Y"). A fit process's fit only waits
#: longer; its next fit starts when it is done anyway.
HELPER_NICE = {"control": 5, "telemetry": 10, "recorder": 10, "fit": 15}


def helper_comm(process_name: str) -> str:
    """The kernel name of the helper whose process is named ``process_name`` (``rt_ident-fit`` -> ``rt-fit``)."""
    return ("rt-" + process_name.removeprefix("rt_ident-"))[:15]


#: attribute of a helper's ``multiprocessing.Process``: ``{"nice": int | None, "cpus": list[int] | None}``, how the run
#: placed the process it replaces (:func:`become_helper` applies it in the child, before any thread starts)
PLACEMENT_ATTR = "rt_placement"


def _place_self(nice: int | None, cpus: list[int] | None, tid: int = 0) -> None:
    """A thread of this process (0: the calling one) on ``cpus`` at ``nice``, each where given and permitted."""
    try:
        if cpus:
            os.sched_setaffinity(tid, set(cpus))
    except (AttributeError, OSError, ValueError):
        pass
    try:
        if nice is not None:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (AttributeError, OSError):
        pass


def threads_of(pid: int) -> list[int]:
    """Every thread of a process (Linux: priority and affinity calls on a pid reach one thread only)."""
    try:
        return [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        return [pid]


def take_placement() -> None:
    """A helper that deferred it (:func:`become_helper`), once ready: the recorded placement on every thread it has.
    The run placed the first helpers the same way, once they were ready: their imports ran at the run's priority."""
    import multiprocessing

    placed = getattr(multiprocessing.current_process(), PLACEMENT_ATTR, None)
    if not placed:
        return
    for tid in threads_of(os.getpid()):
        _place_self(placed.get("nice"), placed.get("cpus"), tid)


def become_helper(defer_placement: bool = False) -> ParentWatch:
    """First call in a helper's main: ignore the group's signals (:data:`GROUP_SIGNALS`), name it
    (:func:`name_process`), leave the loop's CPU; returns the parent watch.

    A helper started during the run (a restart) places itself as the run placed the one it replaces
    (:data:`PLACEMENT_ATTR`), here or, with ``defer_placement``, at :func:`take_placement` (a helper that
    imports or opens files before it is ready); without that record, while the parent's loop runs real-time,
    off the loop's CPU and at its role's nice value (:data:`HELPER_NICE`). It would otherwise keep the
    forkserver's CPUs and nice value, or, started from the loop thread, the loop's single CPU (its scheduling
    policy is reset: the loop sets SCHED_RESET_ON_FORK). It is still single-threaded here, so the threads it
    starts later inherit both."""
    import multiprocessing

    for s in GROUP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    me = multiprocessing.current_process()
    name_process(helper_comm(me.name))
    placed = getattr(me, PLACEMENT_ATTR, None)
    if placed:
        if not defer_placement:
            _place_self(placed.get("nice"), placed.get("cpus"))
        return ParentWatch()
    name = me.name
    try:
        parent = multiprocessing.parent_process()
        ppid = parent.pid if parent is not None and parent.pid is not None else os.getppid()
        # the parent's main thread: the loop, when it runs (SCHED_RESET_ON_FORK is or-ed into what it reads)
        if os.sched_getscheduler(ppid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO:
            loop_cpus = os.sched_getaffinity(ppid)
            every = set(range(os.cpu_count() or 1))
            cpus = ((os.sched_getaffinity(0) - loop_cpus) or (every - loop_cpus)) if len(loop_cpus) < len(every) \
                else None
            _place_self(HELPER_NICE.get(name.removeprefix("rt_ident-").split("-", 1)[0]),
                        sorted(cpus) if cpus else None)
    except (AttributeError, OSError):
        pass
    return ParentWatch()


class ParentWatch:
    """``gone`` becomes True once the process that started this helper has died.

    multiprocessing hands a child a pipe end that reaches EOF when that process ends, whether the child
    was spawned or forked by the forkserver (whose own life does not follow the main process's: it
    lasts while any child holds its socket). Outside multiprocessing: the parent pid changes."""

    def __init__(self, every_s: float = 0.2) -> None:
        import multiprocessing

        self.ppid = os.getppid()
        self._parent = multiprocessing.parent_process()
        self.every_s = every_s
        self._next = 0.0
        self._gone = False

    @property
    def gone(self) -> bool:
        if self._gone:
            return True
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.every_s
            self._gone = (not self._parent.is_alive()) if self._parent is not None else os.getppid() != self.ppid
        return self._gone


#: a job process (fit, control) that has not answered for this long is taken as hung [s]
HANG_S = 10.0
#: a gap this long between two looks means the watch itself was held up (a stalled loop): its time is not counted
_LOOK_GAP_S = 1.0


class HelperWatch:
    """Notices, within ``every_ticks`` ticks, a helper process that died, or a job process (one with
    ``progress``) that has made no progress on waiting work for ``hang_s`` seconds of watching (stopped,
    deadlocked, starved); says so at once (one log line, and the run summary's ``helpers``), and restarts
    it once where that is safe (the fit and control processes; telemetry, which then writes a new file).
    A hung process that cannot be restarted is left running and reported. The recorder is watched by the
    loop itself: its death stops the run (samples could no longer be recorded)."""

    def __init__(self, helpers: dict[str, Any], *, restartable: tuple[str, ...] = (), max_restarts: int = 1,
                 every_ticks: int = 100, hang_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.helpers = {k: v for k, v in helpers.items() if v is not None}
        self.restartable = set(restartable)
        self.max_restarts = max_restarts
        self.every_ticks = every_ticks
        self.hang_s = HANG_S if hang_s is None else hang_s
        self._clock = clock
        self._waiting: dict[str, tuple[float, Any]] = {}   # name -> (since, progress then)
        self._last_look = -math.inf
        self.status: dict[str, dict[str, Any]] = {
            k: {"pid": getattr(v, "pid", None), "deaths": 0, "hangs": 0, "restarts": 0, "alive": True,
                "exitcodes": []}
            for k, v in self.helpers.items()}

    def __call__(self, tick: int) -> None:
        if tick % self.every_ticks:
            return
        now = self._clock()
        if now - self._last_look > _LOOK_GAP_S:
            self._waiting.clear()                    # not watched meanwhile: start timing again
        self._last_look = now
        for name, h in self.helpers.items():
            st = self.status[name]
            if not st["alive"]:
                continue
            if not h.alive:
                code = h.exitcode
                st["deaths"] += 1
                st["exitcodes"].append(code)
                self._restart(name, h, f"died (exit code {code})")
            elif (progress := getattr(h, "progress", None)) is not None:
                since, then = self._waiting.get(name, (now, None))
                if progress != then:
                    self._waiting[name] = (now, progress)
                elif now - since >= self.hang_s and not st.get("hung"):
                    st["hangs"] += 1
                    st["hang_s"] = self.hang_s
                    self._waiting.pop(name)
                    self._restart(name, h, f"gave no answer for {now - since:.0f} s (hung, or starved by the host)",
                                  alive=True)
            else:
                self._waiting.pop(name, None)

    def _restart(self, name: str, h: Any, what: str, alive: bool = False) -> None:
        st = self.status[name]
        if name in self.restartable and st["restarts"] < self.max_restarts:
            st["restarts"] += 1
            old = getattr(h, "pid", None)
            h.restart()
            _log.error("helper %s %s; restarting it (the old pid %s)", name, what, old)
        else:
            if alive:
                st["hung"] = True                    # left as it is: reported, not timed again
            else:
                st["alive"] = False
            _log.error("helper %s %s; not restarted", name, what)

    def freeze(self) -> None:
        """Take the status when the loop ends (the helpers are closed after that)."""
        for name, h in self.helpers.items():
            st = self.status[name]
            st["alive"] = st["alive"] and bool(h.alive)
            st["pid"] = getattr(h, "pid", None)
            if hasattr(h, "fits") and st["restarts"]:
                st["results_since_restart"] = h.fits - h.fits_at_restart
        self._frozen = True

    def summary(self) -> dict[str, dict[str, Any]]:
        if not getattr(self, "_frozen", False):
            self.freeze()
        return self.status

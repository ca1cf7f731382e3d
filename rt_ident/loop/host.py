"""The host under the loop: which CPU the loop gets, the real-time treatment it asks for, the idle
poller on that CPU, the helpers kept off it, and what the host did meanwhile (steal time, device
interrupts on the loop's CPU), for the run summary. Used by ``rt-ident run`` for one axis
(:mod:`rt_ident.compose.run`, one axis or several)."""

from __future__ import annotations

import gc
import logging
import os
import threading
from typing import Any

from rt_ident.config import RunConfig
from rt_ident.loop.cpu_claim import CpuClaim
from rt_ident.processes.guard import HELPER_NICE, threads_of

log = logging.getLogger(__name__)


def loop_cpu() -> int | None:
    """The CPU the loop gets to itself: the last one, when there are at least two."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None
    return cpus[-1] if len(cpus) >= 2 else None


class HostSteal:
    """Time the hypervisor ran something else while this guest's loop CPU wanted to run.

    ``/proc/stat``'s steal column (USER_HZ ticks, usually 10 ms) for the CPU the loop is pinned
    to (the whole machine when it is not pinned). On a VM, a late tick with no context switch
    and no page fault in the loop thread, while steal grows, was the host's doing.
    """

    def __init__(self) -> None:
        try:
            cpus = os.sched_getaffinity(0)
        except (AttributeError, OSError):
            cpus = set()
        self.cpu: int | None = next(iter(cpus)) if len(cpus) == 1 else None
        self._start = self._read()

    def _read(self) -> int | None:
        key = "cpu" if self.cpu is None else f"cpu{self.cpu}"
        try:
            with open("/proc/stat") as fh:
                for line in fh:
                    fields = line.split()
                    if fields and fields[0] == key and len(fields) > 8:
                        return int(fields[8])
        except OSError:
            pass
        return None

    def elapsed_ms(self) -> float | None:
        end = self._read()
        if end is None or self._start is None:
            return None
        return (end - self._start) * 1000.0 / os.sysconf("SC_CLK_TCK")


def read_interrupts(path: str = "/proc/interrupts") -> tuple[list[int], dict[str, list[int]]] | None:
    """(the CPU numbers of the columns, device interrupt name -> count per column) from
    ``/proc/interrupts``: numbered lines only (devices), not the per-CPU timer or IPI lines."""
    try:
        with open(path) as fh:
            head = fh.readline().split()
            cpus = [int(c[3:]) for c in head if c.startswith("CPU")]
            out: dict[str, list[int]] = {}
            for line in fh:
                parts = line.split()
                if not parts or not parts[0].rstrip(":").isdigit() or len(parts) < len(cpus) + 1:
                    continue
                counts = [int(x) for x in parts[1:1 + len(cpus)]]
                name = parts[-1] if len(parts) > len(cpus) + 1 else parts[0].rstrip(":")
                out[f"{parts[0].rstrip(':')} {name}"] = counts
            return cpus, out
    except (OSError, ValueError):
        return None


class LoopCpuInterrupts:
    """Device interrupts the loop's CPU served during the loop. With the kernel's IRQ time accounting
    off (common on VMs), the time a CPU spends in an interrupt and its softirq is charged to whatever
    thread it interrupted: on the loop's CPU, to the loop's tick, as milliseconds of the loop thread's
    own CPU time. A managed IRQ (a VM's virtio-blk disk, say) cannot be moved; reported so that a bench
    PC's setup can be checked: move movable IRQs off the loop's CPU."""

    def __init__(self, cpu: int | None) -> None:
        self.cpu = cpu
        self._start = read_interrupts() if cpu is not None else None

    def summary(self) -> dict[str, Any] | None:
        if self._start is None:
            return None
        end = read_interrupts()
        cpus, before = self._start
        if end is None or end[0] != cpus or self.cpu not in cpus:
            return None
        col = cpus.index(self.cpu)
        delta = {name: counts[col] - before.get(name, [0] * len(cpus))[col] for name, counts in end[1].items()}
        busy = sorted(((n, d) for n, d in delta.items() if d > 0), key=lambda nd: -nd[1])
        return {"cpu": self.cpu, "total": sum(d for _, d in busy), "top": dict(busy[:3])}


def helper_role(name: str) -> str:
    """"fit-x" -> "fit": a helper's role from its name (the part before an axis suffix)."""
    return name.split("-", 1)[0]


def keep_off_loop_cpu(pids: list[int], realtime: bool, *, device: int | None = None,
                      roles: dict[int, str] | None = None) -> dict[str, Any]:
    """Recorder, telemetry, fit and control processes: lower priority, and off the loop's CPU.

    ``roles`` (pid -> "fit", "control", ...) sets each one's nice value from :data:`HELPER_NICE`
    (10 when not given). Applied to every thread each process has started so far (rerun's and
    pyarrow's threads exist by now); threads started later inherit it from the thread that creates
    them. An emulated ``device`` (its pid) only leaves the loop's CPU: it stands for hardware that
    runs on its own, so it keeps its priority (niced, beside the fit process's 90 ms bursts, the
    serial board can miss the host's 20-tick watchdog).
    """
    cpu = loop_cpu() if realtime else None
    roles = roles or {}
    report: dict[str, Any] = {"pids": pids, "niced": True, "cpus": None, "threads": 0, "device_pid": device,
                              "nice": {}}
    for pid in pids + ([device] if device else []):
        nice = HELPER_NICE.get(roles.get(pid, ""), 10)
        for tid in threads_of(pid):
            report["threads"] += 1
            if pid != device:
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                    report["nice"][str(pid)] = nice
                except OSError:
                    report["niced"] = False
            if cpu is not None:
                try:
                    others = set(os.sched_getaffinity(tid)) - {cpu}
                    if others:
                        os.sched_setaffinity(tid, others)
                        report["cpus"] = sorted(others)
                except OSError:
                    pass
    return report


def apply_run_realtime(cfg: RunConfig) -> dict[str, Any]:
    if not cfg.loop.realtime:
        return {"requested": False}
    from rt_ident.loop.scheduler import apply_realtime

    cpu = loop_cpu()
    return apply_realtime(priority=50, cpus=None if cpu is None else [cpu], lock_memory=True, freeze_gc=True)


class LoopRealtime:
    """The loop thread's real-time treatment for one run, from :meth:`begin` (before the device is
    activated) to :meth:`end` (once the device is stopped).

    SCHED_FIFO is for the loop's cycle only. CPU-bound work at SCHED_FIFO (compiling the idle poller,
    the final fit, closing the files, whatever the caller does next) is paused by the kernel's RT
    throttle for 50 ms once it has had 950 ms of a second, and starves every other thread of its
    CPU (per-CPU kernel workers too) until then. So :meth:`prepare` compiles the idle poller and
    collects and freezes the heap while the thread is an ordinary one and before the device is
    opened (a collection holds the GIL for tenths of a second: the thread that sends the host's
    heartbeat until the SYNC runs would wait that long, and a drive watching it faults); :meth:`begin`
    is then quick; :meth:`end` stops the poller, gives the thread back the policy and CPUs it had
    before, unlocks the memory the run locked and unfreezes the heap it froze. Register :meth:`end`
    before the backend's context, so that on an error it runs after the backend's safe stop (the SYNC
    sender the poller could stall is gone by then: see rt_ident.loop.idle_poll); on a normal end call
    it after ``safe_stop()``.
    """

    def __init__(self, cfg: RunConfig, stop: threading.Event | None = None) -> None:
        self.cfg = cfg
        self.stop = stop
        self.report: dict[str, Any] = {"requested": False}
        self.poller: Any = None
        self._prepared: tuple[Any, str | None] | None = None     # (idle poller, why it failed)
        self._saved: tuple[int, Any, set[int]] | None = None
        self._claim: CpuClaim | None = None
        self._unlock = False                       # end() unlocks the memory this run locked
        self._unfreeze = False                     # end() unfreezes the heap this run froze

    def prepare(self) -> None:
        """The slow part, as an ordinary thread and before the device is opened (idempotent). First the
        claim on the loop's CPU (rt_ident.loop.cpu_claim): it may wait for another loop, and may refuse."""
        if self._prepared is not None:
            return
        # objects frozen stay out of every collection: the run's own cycles (its helpers and their
        # shared-memory rings) would outlive it in a process that goes on. A heap the caller froze
        # before stays frozen.
        self._unfreeze = gc.get_freeze_count() == 0
        if not self.cfg.loop.realtime:
            # no collector pause in the loop of an ordinary process either (a gen-1 pass of tens of ms
            # is a stall): collected and frozen here, turned off by begin(), back on after the run
            gc.collect()
            gc.freeze()
            self._prepared = (None, None)
            return
        poller, failed = None, None
        cpu = loop_cpu()
        if cpu is not None and self._claim is None:
            claim = CpuClaim(cpu, self.cfg.loop.cpu_wait_s, self.stop)
            claim.acquire()
            self._claim = claim
        if self.cfg.loop.idle_poll and cpu is not None:
            from rt_ident.loop.idle_poll import IdlePoller

            poller = IdlePoller(cpu)
            try:
                poller.prepare()
            except Exception as exc:  # noqa: BLE001 - an optional aid: the run goes on without it, and says why
                log.warning("idle poller not started: %s", exc)
                poller, failed = None, f"failed to start: {type(exc).__name__}: {exc}"
        gc.collect()                                   # apply_realtime's collection is then a short one
        gc.freeze()
        self._prepared = (poller, failed)

    def begin(self, tickers: list) -> dict[str, Any]:
        """Real-time treatment for the calling thread (the loop) and the idle poller; returns the report
        (``idle_poll`` in it when the run is real time)."""
        cfg = self.cfg
        self.prepare()
        if not cfg.loop.realtime:
            gc.disable()                               # the caller turns it back on after the run
            self.report = {**apply_run_realtime(cfg), "gc_freeze": True}
            return self.report
        assert self._prepared is not None             # made by prepare() for a real-time run
        poller, failed = self._prepared
        try:
            self._saved = (os.sched_getscheduler(0), os.sched_getparam(0), os.sched_getaffinity(0))
        except (AttributeError, OSError):
            self._saved = None
        from rt_ident.loop.scheduler import locked_memory_kb

        unlocked_before = locked_memory_kb() == 0       # memory the process locked itself stays locked
        self.report = apply_run_realtime(cfg)
        self._unlock = unlocked_before and self.report.get("mlockall") is True
        if self._claim is not None:
            self.report["cpu_claim"] = {"cpu": self._claim.cpu, "waited_s": round(self._claim.waited_s, 3)}
        self.poller = start_idle_poll(cfg, self.report, tickers, poller=poller, failed=failed)
        return self.report

    def end(self) -> None:
        """Stop the idle poller, leave real time, free the CPU and unfreeze the heap the run froze
        (idempotent; never raises)."""
        poller, self.poller = self.poller, None
        if poller is not None:
            poller.stop()
        saved, self._saved = self._saved, None
        if saved is not None:
            policy, param, cpus = saved
            try:
                os.sched_setscheduler(0, policy, param)
            except (AttributeError, OSError) as exc:
                log.warning("the loop thread could not leave SCHED_FIFO: %s", exc)
            try:
                os.sched_setaffinity(0, cpus)
            except (AttributeError, OSError) as exc:
                log.warning("the loop thread could not leave its CPU: %s", exc)
        if self._unlock:
            from rt_ident.loop.scheduler import unlock_memory

            self._unlock = False
            unlocked = unlock_memory()
            if unlocked is not True:
                log.warning("the memory locked for the loop stays locked: %s", unlocked)
        claim, self._claim = self._claim, None
        if claim is not None:
            claim.release()
        if self._unfreeze:
            self._unfreeze = False
            gc.unfreeze()                              # collectable again once the caller enables the collector


def start_idle_poll(cfg: RunConfig, realtime: dict[str, Any], tickers: list, *, poller: Any = None,
                    failed: str | None = None) -> Any:
    """Start the idle poller (rt_ident.loop.idle_poll) on the loop's CPU when the run is real time,
    the loop got that CPU to itself and ``[loop] idle_poll`` is on; its report goes into ``realtime``
    as ``idle_poll``. With it running the vCPU cannot halt, so the tickers sleep in one piece (unless
    the config sets ``max_sleep_us``). ``poller``: one already prepared for that CPU (else one is made
    here); ``failed``: why preparing it failed. Returns the running poller (the caller stops it) or None."""
    if not cfg.loop.realtime:
        return None
    if not cfg.loop.idle_poll:
        realtime["idle_poll"] = {"running": False, "reason": "[loop] idle_poll = false"}
        return None
    cpus = os.sched_getaffinity(0) if realtime.get("affinity") is True else set()   # pinned by apply_run_realtime
    cpu = next(iter(cpus)) if len(cpus) == 1 else None
    if cpu is None:
        realtime["idle_poll"] = {"running": False, "reason": "the loop has no CPU of its own"}
        return None
    if failed is not None:
        realtime["idle_poll"] = {"running": False, "reason": failed}
        return None
    from rt_ident.loop.idle_poll import IdlePoller

    if poller is None or poller.cpu != cpu:
        poller = IdlePoller(cpu)
    try:
        report = poller.start()
    except Exception as exc:  # noqa: BLE001 - an optional aid: the run goes on without it, and says why
        log.warning("idle poller not started: %s", exc)
        poller.stop()
        report = {"running": False, "reason": f"failed to start: {type(exc).__name__}: {exc}"}
    realtime["idle_poll"] = report
    if report.get("running") and "max_sleep_us" not in cfg.loop.model_fields_set:
        for ticker in tickers:
            ticker.max_sleep_s = None
        report["ticker_sleep"] = "one piece"
    return poller if report.get("running") else None

"""The process that fits streaming-estimator snapshots, so that no fit ever runs in the tick.

The per-sample halves (:mod:`rt_ident.estimators.streaming`) run in the loop and hand over a
small snapshot now and then; :func:`make_fit_process` fits it with
:func:`rt_ident.estimators.streaming.fit_snapshot` in its own process and hands the result back,
both ways through shared-memory rings (:mod:`rt_ident.processes.shm_ring`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from rt_ident.estimators.streaming import fit_snapshot
from rt_ident.processes.context import beside_the_loop, helper_context
from rt_ident.processes.guard import PLACEMENT_ATTR, become_helper, end_helper, quick_exit, start_ignoring_signals
from rt_ident.processes.shm_ring import MessageRing, RingReused

log = logging.getLogger(__name__)

_WORKER_POLL_S = 0.002  # fit process: sleep between polls of an empty inbox
_RESTART_WAIT_S = 10.0  # close: how long a restart under way is waited for


def _job_main(job: Callable[[Any], Any], inbox: MessageRing, outbox: MessageRing, min_interval: float,
                 view_interval: float = 0.0) -> None:
    import dataclasses
    import time

    watch = become_helper()
    last_view = -math.inf
    inbox.flag = 1                                   # ready for a snapshot
    while True:
        if watch.gone:                               # the run's main process died: nobody to answer
            return
        closed = inbox.writer_closed
        if not inbox.pending_messages:
            if closed:
                return
            time.sleep(_WORKER_POLL_S)
            continue
        inbox.flag = 0                               # busy: the loop keeps its snapshots
        snap = _decode(inbox.get(1)[0])
        t0 = time.monotonic()
        try:
            result: Any = job(snap)
        except Exception as exc:  # noqa: BLE001 - reported to the parent, never fatal here
            result = exc
        if getattr(result, "frf", None) is not None and dataclasses.is_dataclass(result) \
                and not isinstance(result, type):
            # the dashboard's FRF view is 16 of a result's 17 kB: unpickling it costs the loop's tick
            # ~100 us, and the dashboard draws one at most every few seconds - send one that often
            if time.monotonic() - last_view < view_interval:
                result = dataclasses.replace(result, frf=None)
            else:
                last_view = time.monotonic()
        try:
            ok = outbox.put_object(result)
        except Exception as exc:  # noqa: BLE001 - e.g. an exception that does not pickle
            ok = outbox.put_object(RuntimeError(f"{type(result).__name__}: {exc}"))
        if not ok:
            log.warning("fit process: result ring full, result dropped")
        # duty-cycle limit: a fit takes ~25 ms; a few per second are plenty for a live view, and
        # the CPU left over belongs to the loop (meanwhile the loop keeps its newer snapshots)
        while time.monotonic() - t0 < min_interval and not inbox.writer_closed:
            time.sleep(0.01)
        inbox.flag = 1


def _job_process(*args: Any) -> None:
    """The job process: :func:`_job_main`, then out at once (its results are in the ring already)."""
    try:
        _job_main(*args)
    except RingReused as exc:               # its parent let go of the rings: nobody to answer
        log.warning("fit process: %s", exc)
        quick_exit(1)
    quick_exit()


_CODEC = "codec"     # ring key naming the class of a snapshot sent as its fields (see JobProcess.submit)


def _decoders() -> dict[str, Callable[[dict], Any]]:
    """Snapshot classes sent as their fields (``to_fields`` here, ``from_fields`` in the job process), by name."""
    from rt_ident.estimators.spectra import Spectra, SpectraSums

    return {"Spectra": Spectra.from_fields, "SpectraSums": SpectraSums.from_fields}


def _decode(msg: dict) -> Any:
    """A snapshot from its ring message: pickled, or as the fields of a class with ``from_fields``."""
    if MessageRing.is_object(msg):
        return MessageRing.unpickle(msg)
    name = bytes(msg.pop(_CODEC)).decode("ascii")
    return _decoders()[name](msg)


@dataclass
class JobProcess:
    """Runs ``job(request)`` in a separate process. ``submit`` and ``poll`` never block the caller.

    Snapshots and results travel through shared-memory rings (:mod:`rt_ident.processes.shm_ring`: no
    feeder thread in the loop's process). The job process says when it is ready for the next
    snapshot; ``submit`` sends one only then, so a snapshot is pickled at most a few times
    per second (``skipped`` counts the ones not sent because a fit was running).
    """

    job: Callable[[Any], Any]       # picklable (a module-level function or a partial of one)
    name: str = "rt_ident-job"
    min_interval: float = 0.25      # s between jobs
    view_interval: float = 0.0      # s between results that keep their ``frf`` view (others: frf=None)
    ring_bytes: int = 4 << 20       # per direction; a snapshot is a few kB

    def __post_init__(self) -> None:
        self._in, self._out, self._proc = self._parts()
        self._replacing: Future[tuple[MessageRing, MessageRing, Any]] | None = None    # restart() under way
        self.skipped = 0
        self.generation = 0             # restarts so far: a request sent to an earlier process gets no answer
        self._was_ready = False         # this process has said it is ready at least once (its imports are done)
        self.fits_at_restart = 0        # results before the last restart (see restart)
        self.fits = 0
        self.errors = 0
        self.last_error: str | None = None
        self.placement: dict[str, Any] | None = None    # how the run placed it: a replacement takes the same

    def _parts(self) -> tuple[MessageRing, MessageRing, Any]:
        """New rings (in, out) and the process that will serve them, not started."""
        ctx = helper_context()
        inbox = MessageRing(self.ring_bytes, max_messages=1, ctx=ctx)
        outbox = MessageRing(self.ring_bytes, ctx=ctx)
        proc = ctx.Process(target=_job_process, args=(self.job, inbox, outbox, self.min_interval, self.view_interval),
                           name=self.name, daemon=True)
        return inbox, outbox, proc

    def start(self) -> JobProcess:
        start_ignoring_signals(self._proc)
        return self

    @property
    def alive(self) -> bool:
        """The process lives, or its replacement is under way."""
        return not self._current() or self._proc.is_alive()

    @property
    def exitcode(self) -> int | None:
        return self._proc.exitcode

    def restart(self) -> JobProcess:
        """A new job process (and rings) in place of a dead or hung one; results in flight are lost. Returns
        at once: the old process is killed (it ignores SIGTERM) and the new one made and started beside the
        loop (:func:`~rt_ident.processes.context.beside_the_loop`); until it is in, the job is busy
        (``submit`` skips, ``poll`` has nothing)."""
        if self._replacing is not None:
            return self
        old = self._proc
        self._was_ready = False
        self.generation += 1
        self.fits_at_restart = self.fits
        self._replacing = beside_the_loop(lambda: self._replacement(old))
        return self

    def _replacement(self, old: Any) -> tuple[MessageRing, MessageRing, Any]:
        end_helper(old, term_wait_s=0.0)
        parts = self._parts()
        setattr(parts[2], PLACEMENT_ATTR, self.placement)
        start_ignoring_signals(parts[2])
        return parts

    def _current(self, wait_s: float = 0.0) -> bool:
        """True once no restart is under way (waiting up to ``wait_s`` for one): a finished one's rings and
        process are taken in here, on the caller's thread. One that failed leaves the killed process in
        place, to be found dead."""
        fut = self._replacing
        if fut is None:
            return True
        try:
            self._in, self._out, self._proc = fut.result(timeout=wait_s)
        except TimeoutError:
            return False
        except Exception as exc:  # noqa: BLE001 - said, and the process is then found dead
            log.error("%s: restart failed: %s", self.name, exc)
        self._replacing = None
        return True

    def wait_ready(self, timeout: float = 30.0) -> bool:
        """Block (before the loop starts) until the job process has imported everything and waits for
        its first job; False on timeout. On a 2-CPU machine the job process shares the non-loop CPU with
        an emulated device's real-time threads, and its imports alone take seconds there."""
        import time

        end = time.monotonic() + timeout
        if not self._current(timeout):
            return False
        while time.monotonic() < end:
            if self._in.flag:
                return True
            if not self._proc.is_alive():
                return False
            time.sleep(0.01)
        return False

    @property
    def pid(self) -> int | None:
        """The process's pid (the old one's while a restart is under way)."""
        self._current()
        return self._proc.pid

    @property
    def ready(self) -> bool:
        """True when the job process waits for a snapshot (and none is on its way)."""
        return self._current() and bool(self._in.flag) and not self._in.pending_messages

    @property
    def progress(self) -> tuple[int, int] | None:
        """While work waits for the process (a snapshot in its inbox, or one it is on): how far it has got,
        as (snapshots taken, results returned); None while it waits for work or has not started yet (its
        imports). A process whose progress does not move is found hung by
        :class:`rt_ident.processes.guard.HelperWatch`."""
        if not self._current():
            return None
        inbox = self._in
        self._was_ready = self._was_ready or bool(inbox.flag) or inbox.messages_read > 0
        if not self._was_ready or (inbox.flag and not inbox.pending_messages):
            return None
        return inbox.messages_read, self._out.messages_written

    def submit(self, snap: Any) -> bool:
        """Send ``snap`` if the job process is ready for it (True), else count it as skipped."""
        if snap is None:
            return False
        if not self.ready or not self._put(snap):
            self.skipped += 1
            return False
        return True

    def _put(self, snap: Any) -> bool:
        # a snapshot class the job process knows goes as flat arrays: pickling a Spectra costs the loop's
        # tick ~100 us (its arrays through pickle's reduce machinery), its fields a few
        name = type(snap).__name__
        if name in _decoders():
            fields = snap.to_fields()
            fields[_CODEC] = np.frombuffer(name.encode("ascii"), dtype=np.uint8)
            return self._in.put(fields)
        return self._in.put_object(snap)

    def poll(self) -> Any:
        """The newest result the job process has returned since the last poll, or None."""
        return self.unpack(self.take())

    def take(self) -> list:
        """The results returned since the last call, still packed (:meth:`unpack` opens them): the
        loop takes them on one tick and unpickles them on the next, each step tens of microseconds."""
        if not self._current() or not self._out.pending_messages:
            return []
        return self._out.get()

    def unpack(self, msgs: list) -> Any:
        """The newest result of ``msgs`` (from :meth:`take`), or None; counts fits and errors."""
        if not msgs:
            return None
        return newest_result(self, (MessageRing.unpickle(msg) for msg in msgs))

    def begin_close(self) -> None:
        """Tell the process to finish (idempotent); :meth:`close` then waits for it. Several helpers
        told first end side by side: each takes a few hundred ms to exit. A restart under way is waited
        for first (its process is then told too)."""
        self._current(_RESTART_WAIT_S)
        self._in.close_writer()

    def close(self, timeout: float = 5.0) -> None:
        self.begin_close()
        self._proc.join(timeout)
        end_helper(self._proc)          # born ignoring SIGTERM: a job still running is killed, not left behind


def newest_result(jobs: Any, items: Any) -> Any:
    """The last non-exception of ``items`` (None if none); counts ``jobs.fits`` and ``jobs.errors``
    (and keeps ``jobs.last_error``) on the way. Shared by the job process and its in-process stand-in."""
    latest = None
    for item in items:
        if isinstance(item, Exception):
            jobs.errors += 1
            jobs.last_error = str(item)
        else:
            jobs.fits += 1
            latest = item
    return latest


def make_fit_process(method: str, hold: str = "zoh", lead: float = 7.96e-4, min_interval: float = 0.25,
              ring_bytes: int = 4 << 20, view_interval: float = 2.0) -> JobProcess:
    """The fit process: :func:`rt_ident.estimators.streaming.fit_snapshot` of one method, per snapshot.
    A fit's FRF view (for the dashboard) comes back at most every ``view_interval`` seconds."""
    return JobProcess(partial(fit_snapshot, method, hold=hold, lead=lead), name="rt_ident-fit",
                     min_interval=min_interval, ring_bytes=ring_bytes, view_interval=view_interval)

"""The cyclic part of the CANopen backend: per-sample torque plan, SYNC sender, sample assembly.

Threads and hand-offs:

* the **SYNC sender** (own thread, absolute deadlines at ``sync_rate_hz``) takes the
  torque for SYNC index ``k`` from the :class:`TorquePlan`, appends a marker
  ``(MARK, k, t, torque)`` to the shared deque, then sends RPDO1 (controlword +
  target torque) and the SYNC. The drive applies RPDO data at the next SYNC
  (synchronous RPDO) and answers with its TPDOs;
* the frame reader (:class:`drivers.cia402.frames.FrameIO`) runs a light callback that
  only appends ``(cob_id, t_arrival, bytes)`` to the same deque (``deque.append`` is
  atomic). It is a receive thread, except while the backend is active with ``echo`` or
  ``timed`` markers: then the loop thread reads the bus itself at the start of ``read()``
  (no thread competes with the loop for the GIL; the frames wait in the socket);
* the **loop thread** drains the deque in ``read()`` through :class:`SampleAssembler`.

The frames between two window markers form the window of one sample (CiA 301's
synchronous window, here one SYNC period). A window without a valid frame of every
TPDO is *stale* (the sample is dropped; ``SampleBlock.lost`` shows the gap); extra
frames in a window are *late* (the newest is used); frames of the wrong length are
*corrupt*. The window markers are:

* ``timed`` (the bus stamps each frame with its time on the bus: the kernel's receive time
  on ``udp_multicast`` and SocketCAN, the send time on python-can's ``virtual`` bus; see
  :attr:`drivers.cia402.frames.FrameIO.timed`): the sender's marker **time**, taken just
  before SYNC ``k`` is sent. A frame stamped at or after it and before SYNC ``k+1``'s marker
  time belongs to window ``k``, however late a thread read it; a window closes once the
  reader has read everything up to the next marker's time (``FrameIO.read_until``). A real
  CAN adapter does not hand a node its own frames, so this does not need them;
* with ``echo`` (python-can's ``udp_multicast`` open to the network: the bus hands this host's
  own frames back, in bus order; not CAN, not the loopback-confined bus): the **echo of SYNC k**
  ``(ECHO, t)``. The sender's marker only records ``k``, time and torque. Attribution is then
  exact whatever the host's scheduling: a TPDO read after SYNC k's echo and before SYNC k+1's
  was on the bus between them;
* otherwise (an interface whose frame times are not on this host's clock) the sender's marker
  itself, by deque order: it enters the deque before SYNC ``k`` is on the bus, so every TPDO
  answering SYNC ``k`` follows it, but a TPDO the receive thread handles after the sender's
  *next* marker (a late receive thread, not a late drive) lands in the next window.

TPDOs carry no SYNC counter. A drive does not send an answer once the next SYNC has
arrived (CiA 301 synchronous window; the emulated drive checks), but an answer sent just
as the next SYNC goes on the bus lands in the next window. So a window holding a single
answer right after a window without one is *ambiguous* (it may be the late answer) and
dropped (counted in ``stale`` and ``ambiguous``); two answers in a window mean the drive
caught up, and the newest is this SYNC's. A drive late by a whole period for several
periods in a row would still shift its data by one sample.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import struct
import threading
import time
from collections.abc import Callable

import numpy as np

from drivers.base import SAME_TORQUE
from drivers.cia402.bus import error_code
from drivers.errors import ProtocolError, WatchdogTrip, stuck_encoder_fix
from rt_ident.errors import ask_realtime

log = logging.getLogger(__name__)

MARK = -1                      # first element of a SYNC marker in the deque: (MARK, k, t_sent, torque)
ECHO = -2                      # this host's SYNC read back from the bus: (ECHO, t_arrival[, ordinal])
CANCEL = -3                    # SYNC k was not sent after all (bus error): (CANCEL, k)
SKIP = -4                      # (SKIP, n): this deque's markers start after the n-th SYNC of its bus connection
_MAX_PENDING = 4096            # SYNC records waiting for their echo before echoes count as missing
_ZERO = np.zeros(1)            # a lease's end: one value of 0
_RPDO = struct.Struct("<Hh")   # controlword (UNSIGNED16), target torque (INTEGER16, per mille)


def wrap32(delta: int) -> int:
    """A difference of two INTEGER32 readings, wrapped into [-2^31, 2^31)."""
    return ((delta + 0x80000000) & 0xFFFFFFFF) - 0x80000000


class TorquePlan:
    """Per-sample torque commands keyed by SYNC index; written by the loop, read by the sender.

    Semantics of :mod:`drivers.base`: ``hold(v)`` holds ``v`` from now on; ``plan(values, k0)``
    asks for ``values[i]`` at SYNC ``k0 + i`` and replaces the rest of an older plan; indices not
    covered hold the last value taken. Values for SYNCs already sent are counted in ``late``; those
    of them that differ from the torque sent (a torque that lands a SYNC late) in ``late_changed``.
    """

    SENT = 64                     # the torques of the last SENT SYNCs, for late_changed

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values = np.empty(0)
        self._start = 0
        self._last = 0.0
        self._next = 0            # the next SYNC index the sender will take
        self.late = 0
        self.late_changed = 0
        self._sent_k = [-1] * self.SENT
        self._sent_v = [0.0] * self.SENT

    def hold(self, torque: float) -> None:
        with self._lock:
            self._values = self._values[:0]
            self._last = float(torque)

    def plan(self, values: np.ndarray, start: int, lease: int | None = None) -> None:
        """``lease``: the torque drops to 0 that many SYNCs after the plan ends (one lock with the plan:
        the sender never takes a plan without its end)."""
        vals = np.asarray(values, dtype=float)
        if vals.size == 0:
            return
        with self._lock:
            self._plan(vals, start)
            if lease is not None:
                self._plan(_ZERO, start + vals.size + lease)

    def _plan(self, vals: np.ndarray, start: int) -> None:
        """Under the lock: ``vals`` from SYNC ``start`` on, replacing the rest of an older plan."""
        nxt = self._next
        if start < nxt:
            late = min(nxt - start, vals.size)
            self.late += late
            sk, sv, n = self._sent_k, self._sent_v, self.SENT
            for i in range(late):
                j = (start + i) % n
                if sk[j] == start + i and abs(sv[j] - vals[i]) > SAME_TORQUE:
                    self.late_changed += 1
            if late == vals.size:
                self._values = self._values[:0]
                self._last = float(vals[-1])
                return
            vals, start = vals[late:], nxt
        old, os_ = self._values, self._start
        if old.size and os_ < start:
            keep = old[: max(0, min(old.size, start - os_))]
            gap = start - (os_ + keep.size)
            self._values = np.concatenate((keep, np.full(gap, old[-1]), vals))
        else:
            self._values, os_ = vals.copy(), start
        self._start = os_

    def take(self, k: int) -> float:
        """The torque for SYNC ``k`` (called by the sender, with increasing ``k``)."""
        with self._lock:
            self._next = k + 1
            v = self._values
            if v.size:
                i = k - self._start
                if i >= v.size:
                    self._last = float(v[-1])
                    self._values = v[:0]
                elif i >= 0:
                    self._last = float(v[i])
                    self._values = v[i + 1:]
                    self._start = k + 1
            j = k % self.SENT
            self._sent_k[j], self._sent_v[j] = k, self._last
            return self._last


class RpdoChannel:
    """One drive's share of the SYNC cycle: its RPDO1 (COB-ID, controlword), its torque plan, its deque.

    ``controlword`` is read by the sender every cycle (the backend walks the 402 state machine
    by setting it); ``encode(T) -> (int per mille, T_quantized)``.
    """

    __slots__ = ("rpdo_cob", "plan", "encode", "sink", "controlword")

    def __init__(self, rpdo_cob: int, plan: TorquePlan, encode: Callable[[float], tuple[int, float]],
                 sink: collections.deque, controlword: int = 0) -> None:
        self.rpdo_cob = rpdo_cob
        self.plan = plan
        self.encode = encode
        self.sink = sink
        self.controlword = controlword


class SyncSender:
    """Sends every channel's RPDO1, then one SYNC, every ``period`` seconds on absolute deadlines, in its own thread.

    One SYNC producer per bus: several drives on one bus (an XY table's two axes) are several
    :class:`RpdoChannel` of one sender, so both drives sample and apply torque at the same SYNC.
    The constructor makes the first channel (``sink``, ``plan``, ``torque_to_permille``,
    ``rpdo_cob``; its ``controlword`` is this object's); :meth:`join` / :meth:`leave` add and
    remove others at a period boundary. Each channel's deque gets ``(SKIP, n)`` when it joins:
    its first marker belongs to the SYNC after the ``n``-th this bus connection has sent
    (``sent_before`` counts those of earlier senders), so echoes of earlier SYNCs are not its own.

    ``send(cob_id, data)`` must be thread-safe (``canopen.Network.send_message`` is).
    On overrun whole periods are skipped (counted in ``overruns``), never sent in a burst.
    The thread needs the GIL at each deadline: its jitter is bounded by the interpreter's
    switch interval while the loop thread computes (``sys.setswitchinterval``).
    Send errors are counted and kept in ``last_error``, never raised in the thread.
    """

    def __init__(self, send: Callable[[int, bytes], None], period: float, sink: collections.deque,
                 plan: TorquePlan, torque_to_permille: Callable[[float], tuple[int, float]],
                 rpdo_cob: int, sync_cob: int = 0x80, clock: Callable[[], float] = time.monotonic,
                 sent_before: int = 0, heartbeat: tuple[int, int] | None = None) -> None:
        self._send = send
        self.period = float(period)
        self.primary = RpdoChannel(rpdo_cob, plan, torque_to_permille, sink)
        self._channels: list[RpdoChannel] = [self.primary]
        self._changes: list[tuple[bool, RpdoChannel]] = []     # (join?, channel), applied by the thread
        self._lock = threading.Lock()
        self._sync_cob = sync_cob
        self._clock = clock
        self.sent_before = int(sent_before)
        self.heartbeat = heartbeat    # (COB-ID, every n SYNC periods): the host's heartbeat, sent by this thread
        self.heartbeats = 0
        self.next_index = 0          # SYNC index of the next cycle
        self.next_at: float | None = None    # its deadline, on ``clock`` (None: not running)
        self.sent = 0
        self.overruns = 0
        self.send_errors = 0
        self.consecutive_errors = 0
        self.last_error: str | None = None
        self.last_errno: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._creator: tuple[int, int] | None = None

    @classmethod
    def for_channel(cls, send: Callable[[int, bytes], None], period: float, channel: RpdoChannel,
                    sent_before: int = 0, heartbeat: tuple[int, int] | None = None) -> SyncSender:
        sender = cls(send, period, channel.sink, channel.plan, channel.encode, channel.rpdo_cob,
                     sent_before=sent_before, heartbeat=heartbeat)
        sender.primary = channel
        sender._channels = [channel]
        return sender

    @property
    def controlword(self) -> int:
        return self.primary.controlword

    @controlword.setter
    def controlword(self, value: int) -> None:
        self.primary.controlword = value

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def channels(self) -> int:
        """Channels sending now or about to (joins and leaves not yet applied counted)."""
        with self._lock:
            return len(self._members())

    def _members(self) -> list[RpdoChannel]:
        """Under the lock: the channels once the pending joins and leaves are applied, as the thread applies
        them (a second leave of a channel removes nothing: it must not count as another channel's leave)."""
        members = list(self._channels)
        for join, ch in self._changes:
            if join and ch not in members:
                members.append(ch)
            elif not join and ch in members:
                members.remove(ch)
        return members

    def join(self, channel: RpdoChannel) -> None:
        """Add a drive's channel from the next period on (a no-op if it sends already)."""
        with self._lock:
            if self.running:
                if channel not in self._members():
                    self._changes.append((True, channel))
            elif channel not in self._channels:
                self._channels.append(channel)

    def leave(self, channel: RpdoChannel) -> None:
        """Stop sending this channel's RPDO from the next period on (idempotent)."""
        with self._lock:
            if self.running:
                if channel in self._members():
                    self._changes.append((False, channel))
            elif channel in self._channels:
                self._channels.remove(channel)

    def start(self) -> None:
        if self.running:
            return
        self._stop.clear()
        self._creator = _scheduling()          # the loop thread's: the sender runs one step above it
        for ch in self._channels:
            ch.sink.append((SKIP, self.sent_before + self.sent))
        self._thread = threading.Thread(target=self._run, name="canopen-sync", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        self.next_at = None
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("SYNC sender thread did not stop within %.2f s", timeout)
            self._thread = None
        with self._lock:                        # joins and leaves the thread did not get to
            for join, ch in self._changes:
                if join and ch not in self._channels:
                    self._channels.append(ch)
                elif not join and ch in self._channels:
                    self._channels.remove(ch)
            self._changes = []

    def _apply_changes(self, channels: list[RpdoChannel]) -> None:
        with self._lock:
            changes, self._changes = self._changes, []
            for join, ch in changes:
                if join and ch not in channels:
                    ch.sink.append((SKIP, self.sent_before + self.sent))
                    channels.append(ch)
                elif not join and ch in channels:
                    channels.remove(ch)

    def _run(self) -> None:
        _preempt_creator(self._creator)
        period, clock, stop = self.period, self._clock, self._stop
        channels, send, pack, sync_cob = self._channels, self._send, _RPDO.pack, self._sync_cob
        deadline = clock()
        self.next_at = deadline
        k = self.next_index
        next_hb = k
        while not stop.is_set():
            now = clock()
            if now < deadline:
                stop.wait(deadline - now)
                continue
            late = now - deadline
            if late >= period:                      # overrun: skip whole periods, never burst
                skip = int(late // period)
                k += skip
                deadline += skip * period
                self.next_at = deadline
                self.overruns += skip
            if self._changes:
                self._apply_changes(channels)
            cycle = []
            for ch in channels:
                permille, torque = ch.encode(ch.plan.take(k))
                cycle.append((ch, torque, pack(ch.controlword & 0xFFFF, permille)))
            marked = False
            try:
                for ch, _, data in cycle:
                    send(ch.rpdo_cob, data)
                # the marker's time as close before the SYNC as it can be: a frame stamped after it
                # answers this SYNC or a later one (timed window markers, see SampleAssembler)
                t = clock()
                for ch, torque, _ in cycle:
                    ch.sink.append((MARK, k, t, torque))
                marked = True
                send(sync_cob, b"")
                self.sent += 1
                self.consecutive_errors = 0
            except Exception as exc:  # noqa: BLE001 - a sender thread must not die on a bus error
                for ch in channels if marked else ():
                    ch.sink.append((CANCEL, k))
                self.send_errors += 1
                self.consecutive_errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                self.last_errno = error_code(exc)
            if k >= next_hb and self.heartbeat is not None:   # (set to None: the heartbeat stops)
                hb_cob, hb_every = self.heartbeat
                # The host's heartbeat from this thread (real-time, one step above the loop) while the
                # SYNC runs: from an ordinary thread it can wait behind the real-time threads of a loaded
                # host for longer than the drives' heartbeat timeout, and they fault (EMCY 0x8130).
                next_hb = k + hb_every
                try:
                    send(hb_cob, b"\x05")
                    self.heartbeats += 1
                except Exception:  # noqa: BLE001 - counted with the SYNC's errors on the next cycle
                    pass
            k += 1
            self.next_index = k
            deadline += period
            self.next_at = deadline


def _scheduling() -> tuple[int, int] | None:
    """(policy, priority) of the calling thread, without the reset-on-fork flag; None if unknown."""
    try:
        return os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return None


def _preempt_creator(creator: tuple[int, int] | None) -> None:
    """Under SCHED_FIFO (the loop thread's, read when it started the sender), run one step above it.

    Threads of equal FIFO priority on one CPU do not preempt each other: the SYNC would wait
    for the loop's spin and computation. One step higher, it waits at most for the GIL.
    The policy is set here explicitly, not inherited: the loop thread runs with
    SCHED_RESET_ON_FORK (a helper it restarts must not be real-time), and that flag makes
    every new thread it starts SCHED_OTHER too - a sender on the loop's CPU then runs only
    while the loop sleeps (about half of the SYNCs late by whole periods, even on an idle host).
    """
    if creator is None or creator[0] != os.SCHED_FIFO:
        return
    try:
        prio = min(creator[1] + 1, os.sched_get_priority_max(os.SCHED_FIFO))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (AttributeError, OSError) as exc:
        log.warning("SYNC sender cannot run real-time above the loop (%s): SYNCs will be late", exc)


class SampleAssembler:
    """Turns the deque items into samples: one window of TPDO frames per SYNC marker.

    ``layouts``: ``(cob_id, struct)`` of TPDO1 = (statusword, position counts, torque per mille)
    and TPDO2 = (scale counts,). Positions are unwrapped across INTEGER32 overflow.
    Raises :class:`WatchdogTrip` (missing data, or a motor encoder frozen while the drive
    reports at least ``stuck_permille`` of torque: a free-free axis must move) or
    :class:`ProtocolError` (wrong-length frames) after more than ``stale_limit`` bad samples
    in a row - only when ``deliver`` is true.
    """

    def __init__(self, layouts: list[tuple[int, struct.Struct]], stale_limit: int, stuck_permille: float,
                 echo: bool = False, timed: bool = False) -> None:
        self.layouts = layouts
        self.stale_limit = stale_limit
        self.stuck_permille = stuck_permille
        self.echo = echo
        self.timed = timed and not echo
        self._open: collections.deque = collections.deque()   # timed mode: [(marker, frames)], oldest first
        self._records: collections.deque = collections.deque()   # echo mode: SYNCs sent, echo not yet read
        self.echoes = 0
        self._echo_floor = 0                  # echoes with an ordinal up to this are older than our markers
        self._marker: tuple | None = None
        self._frames: dict[int, list[tuple]] = {}     # cob -> [(cob, t_received, data)]
        self.statusword: int | None = None   # latest valid statusword
        self.first_k = 0                      # SYNC index of the first sample to deliver
        self.frames_seen = 0
        self.stale = 0
        self.ambiguous = 0                   # stale because attribution was ambiguous (in ``stale`` too)
        self.late = 0
        self.corrupt = 0
        self.unchanged = 0
        self.max_latency = 0.0               # s, SYNC sent -> TPDO received (host clock)
        self._prev_complete = True           # no earlier SYNC whose answer could still come
        self._bad_run = 0
        self._bad_corrupt = False
        self._last_corrupt = ""
        self._pos: int | None = None
        self._pos_raw = 0
        self._scale: int | None = None
        self._scale_raw = 0
        self._stuck_run = 0
        self.rows: dict[str, list] = {k: [] for k in ("k", "t", "sw", "pos", "tq", "scale", "cmd")}
        # SYNC periods the host's sender has skipped so far (drive.py wires it): a stale run during
        # which the host itself fell behind is the host's fault, not the drive's, and the trip says so
        self.host_missed: Callable[[], int] | None = None
        self._run_missed0 = 0
        self._run_latency = 0.0

    def _which(self) -> tuple[str, bool]:
        """Whose fault a stale run was, and whether it was the host's: the host's when its SYNC sender
        skipped periods meanwhile (a busy host that was late, the drive may well have answered), else the
        drive's (the host kept time and no valid answer came: stale data)."""
        missed = (self.host_missed() - self._run_missed0) if self.host_missed is not None else 0
        if missed > 0:
            return (f"the host fell behind meanwhile ({missed} SYNC periods skipped by its sender): "
                    "a busy host, not a silent drive"), True
        return "the host kept time (0 SYNC periods skipped): the drive sent no fresh data", False

    def reset_counters(self) -> None:
        self.stale = self.ambiguous = self.late = self.corrupt = self.unchanged = 0
        self.max_latency = 0.0
        self._bad_run = self._stuck_run = 0
        self._bad_corrupt = False

    def take_rows(self) -> dict[str, list]:
        rows = self.rows
        self.rows = {k: [] for k in rows}
        return rows

    def feed(self, dq: collections.deque, deliver: bool, read_until: float | None = None) -> None:
        """Consume every item now in ``dq``; rows of delivered samples accumulate in ``rows``.

        A window closes at the next marker, taking the newest valid frame of each TPDO (so a
        frame one period late next to the on-time one is attributed right). It closes early,
        as soon as it is complete, only when the previous window was complete: then no frame
        of an older SYNC can still be on its way, and the sample is delivered without waiting
        for the next SYNC.

        ``timed``: ``read_until`` is the bus reader's :attr:`~drivers.cia402.frames.FrameIO.read_until`
        (every frame stamped before it is in ``dq``); see :meth:`_feed_timed`.
        """
        if self.timed:
            self._feed_timed(dq, deliver, read_until)
            return
        pop = dq.popleft
        echo = self.echo
        for _ in range(len(dq)):
            item = pop()
            kind = item[0]
            if kind == MARK and echo:
                self._records.append(item)
                if len(self._records) > _MAX_PENDING:
                    raise ProtocolError(f"{len(self._records)} SYNCs sent without reading them back from the "
                                        f"bus ({self.echoes} read so far); window markers are missing")
            elif kind == ECHO:
                if len(item) > 2 and item[2] <= self._echo_floor:
                    continue                   # a SYNC sent before this drive's channel joined the sender
                if not self._records:          # a SYNC of an earlier session
                    continue
                self.echoes += 1
                if self._marker is not None:
                    self._close(self._marker, self._frames, deliver)
                self._marker = self._records.popleft()
                self._frames = {}
            elif kind == SKIP:
                self._echo_floor = item[1]
            elif kind == CANCEL:
                if echo and self._records and self._records[-1][1] == item[1]:
                    self._records.pop()        # never on the bus: no echo will come
            elif kind == MARK:
                if self._marker is not None:
                    self._close(self._marker, self._frames, deliver)
                self._marker = item
                self._frames = {}
            else:
                self.frames_seen += 1
                if self._marker is None:      # after an early close: a frame answering an older SYNC
                    self.late += 1
                    continue
                self._frames.setdefault(item[0], []).append(item)
        if self._marker is not None and self._prev_complete and self._complete(self._frames):
            self._close(self._marker, self._frames, deliver)
            self._marker = None

    def _complete(self, frames: dict[int, list[tuple]]) -> bool:
        """A valid frame of every TPDO is in the window."""
        return all(any(len(f[2]) == st.size for f in frames.get(cob, ())) for cob, st in self.layouts)

    def _feed_timed(self, dq: collections.deque, deliver: bool, read_until: float | None) -> None:
        """Windows by time: a frame belongs to the newest SYNC whose marker time is not after the frame's
        time on the bus, whenever the frame was read. The sender's marker enters the deque before its
        SYNC is sent, so it precedes every answer to that SYNC there; a frame stamped before the oldest
        open window answers a window already closed (``late``). The oldest window closes once the next
        SYNC's marker time is at or before ``read_until`` (every frame of the window has been read), or
        early as in :meth:`feed`. Without ``read_until`` a window closes when the next marker is in."""
        pop, wins = dq.popleft, self._open
        for _ in range(len(dq)):
            item = pop()
            kind = item[0]
            if kind == MARK:
                wins.append((item, {}))
            elif kind == CANCEL:
                if wins and wins[-1][0][1] == item[1]:          # never on the bus: no window of its own
                    _, frames = wins.pop()
                    for cob, got in frames.items():
                        if wins:
                            wins[-1][1].setdefault(cob, []).extend(got)
            elif kind in (ECHO, SKIP):
                continue
            else:
                self.frames_seen += 1
                t = item[1]
                for marker, frames in reversed(wins):
                    if marker[2] <= t:
                        frames.setdefault(item[0], []).append(item)
                        break
                else:
                    self.late += 1                 # answers a SYNC whose window has closed
        horizon = math.inf if read_until is None else read_until
        while wins:
            marker, frames = wins[0]
            ended = len(wins) > 1 and (wins[1][0][2] <= horizon or len(wins) > _MAX_PENDING)
            if not (ended or (self._prev_complete and self._complete(frames))):
                break
            wins.popleft()
            self._close(marker, frames, deliver)

    def _close(self, marker: tuple, window: dict[int, list[tuple]], deliver: bool) -> None:
        _, k, t, cmd = marker
        values: list = []
        bad = None
        lone = True                      # exactly one valid frame of every TPDO
        for cob, st in self.layouts:
            frames = window.get(cob)
            if not frames:
                bad = bad or "missing"
                continue
            if len(frames) > 1:
                self.late += len(frames) - 1
            good = [f for f in frames if len(f[2]) == st.size]
            if len(good) < len(frames):
                self.corrupt += len(frames) - len(good)
                self._last_corrupt = (f"TPDO 0x{cob:03X} with {len(frames[-1][2])} bytes, "
                                      f"{st.size} mapped")
            if not good:
                bad = "corrupt"
                continue
            lone = lone and len(good) == 1
            latency = good[-1][1] - t
            if latency > self.max_latency:
                self.max_latency = latency
            values.extend(st.unpack(good[-1][2]))
        if bad is None and lone and not self._prev_complete:
            # One answer right after a window without one: it may be the previous SYNC's answer,
            # sent just as this SYNC went on the bus (the drive cannot see that race). Dropped.
            bad = "ambiguous"
            self.ambiguous += 1
            sw = values[0]
            self.statusword = sw
        self._prev_complete = bad is None or bad == "ambiguous"
        if bad is not None:
            self.stale += 1
            if self._bad_run == 0:
                self._run_missed0 = self.host_missed() if self.host_missed is not None else 0
                self._run_latency = 0.0
            self._bad_run += 1
            self._bad_corrupt = self._bad_corrupt or bad == "corrupt"
            if deliver and self._bad_run > self.stale_limit:
                if self._bad_corrupt:
                    raise ProtocolError(f"{self._bad_run} samples in a row without a valid TPDO set "
                                        f"(last bad frame: {self._last_corrupt}); {self.corrupt} corrupt "
                                        f"frames in total")
                whose, host = self._which()
                raise WatchdogTrip(f"no fresh TPDO data for {self._bad_run} SYNCs in a row "
                                   f"(stale_limit {self.stale_limit}, {self.stale} stale samples in total); {whose}",
                                   fix=ask_realtime("the host's SYNCs were late, not the drive's answers",
                                                    "a larger backend.stale_limit") if host else None)
            return
        self._bad_run = 0
        self._bad_corrupt = False
        sw, pos_raw, tq, scale_raw = values
        self.statusword = sw
        if self._pos is None or self._scale is None:     # (both set on the first sample)
            self._pos, self._scale = pos_raw, scale_raw
            moved = True
        else:
            moved = pos_raw != self._pos_raw
            self._pos += wrap32(pos_raw - self._pos_raw)
            self._scale += wrap32(scale_raw - self._scale_raw)
        self._pos_raw, self._scale_raw = pos_raw, scale_raw
        if not deliver or k < self.first_k:
            return
        # watchdog: a free-free axis must move under applied torque (the drive's torque actual,
        # not the command: a drive-side position loop may cancel the command at standstill).
        # Count the samples with torque since the encoder last changed; standstill without
        # torque does not count, any movement resets.
        if moved:
            self._stuck_run = 0
        elif abs(tq) >= self.stuck_permille > 0.0:
            self.unchanged += 1
            self._stuck_run += 1
            if self._stuck_run > self.stale_limit:
                raise WatchdogTrip(f"motor encoder 0x6064 unchanged at {pos_raw} counts through {self._stuck_run} "
                                   f"samples with torque applied (last {tq} per mille of rated torque; "
                                   f"stale_limit {self.stale_limit}): stuck encoder or frozen drive data",
                                   fix=stuck_encoder_fix("backend.stuck_torque_min"))
        r = self.rows
        r["k"].append(k)
        r["t"].append(t)
        r["sw"].append(sw)
        r["pos"].append(self._pos)
        r["tq"].append(tq)
        r["scale"].append(self._scale)
        r["cmd"].append(cmd)

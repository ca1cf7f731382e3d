"""Reading and writing CAN frames for the CiA 402 backend and the emulated drive.

:class:`FrameIO` receives the frames of a python-can bus - in a thread, or when its
owner calls :meth:`FrameIO.pump` - and sends them. On ``udp_multicast`` (the emulated
drive's transport across processes) it reads and writes the socket itself in
python-can's wire format (one msgpack map per datagram), at about a quarter of
python-can's cost per frame; on every other interface (SocketCAN, PCAN, ...) it uses
``bus.recv()`` / ``bus.send()``. As on CAN, a bus's own frames are not received, except on
a ``udp_multicast`` bus open to the network (python-can's own socket: multicast loopback
hands them back, in bus order; :attr:`FrameIO.own_frames_back`).

Where the frames carry the time they were on the bus (:attr:`FrameIO.timed`: the kernel's receive
time on ``udp_multicast`` and SocketCAN, the send time on python-can's ``virtual`` bus), that time
is handed over on this host's monotonic clock, and :attr:`FrameIO.read_until` tells a reader that
every frame on the bus before it has been handed over: a frame's place among the SYNCs then does
not depend on when a thread got to read it.
"""

from __future__ import annotations

import logging
import math
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import can

from drivers.cia402.bus import confined

log = logging.getLogger(__name__)

_OFFSET_EVERY_S = 1.0    # s; how often the realtime -> monotonic offset of frame times is measured again
_IDLE_S = 0.05           # s; a blocking receive thread wakes at least this often (stop() waits at most this)
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)   # Linux: cumulative drop count of the receive queue
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_RCVBUF = 1 << 22        # bytes asked for the receive buffer (~5000 frames; capped by net.core.rmem_max)
_DATA_KEY = b"\xa4data\xc4"   # msgpack: the key "data" followed by a bin8 header
_TIMESPEC = struct.Struct("@ll")
UDP_DEFAULT_PORT = 43113  # python-can's default port of the udp_multicast interface

Frame = tuple[int, bytes, float]   # (COB-ID, data, host monotonic time of arrival)


def stop_periodic(task: Any) -> None:
    """Stop a canopen / python-can periodic send task and wait for its thread, so that no send races
    the bus shutdown (python-can's thread dies with a traceback when its socket closes under it)."""
    if task is None:
        return
    task.stop()
    thread = getattr(getattr(task, "_task", task), "thread", None)
    if isinstance(thread, threading.Thread) and thread is not threading.current_thread():
        thread.join(1.0)


def _clock_offset() -> float | None:
    """``time.time() - time.monotonic()`` from the tightest of three readings (None if every one was
    interrupted for more than 20 us: a preempted reading would shift every frame's time)."""
    best: tuple[float, float] | None = None
    for _ in range(3):
        a = time.monotonic()
        r = time.time()
        b = time.monotonic()
        if b - a < 20e-6 and (best is None or b - a < best[0]):
            best = (b - a, r - 0.5 * (a + b))
    return best[1] if best is not None else None


def _udp_template(cob: int, n: int) -> tuple[bytes, bytes]:
    """python-can's udp_multicast datagram of a classic 11-bit data frame, split around its ``n`` data bytes."""
    from can.interfaces.udp_multicast.utils import pack_message

    blob = pack_message(can.Message(arbitration_id=cob, data=bytes(n), is_extended_id=False))
    i = blob.index(_DATA_KEY + bytes([n])) + len(_DATA_KEY) + 1
    return blob[:i], blob[i + n:]


class FrameIO:
    """Receives the frames of a python-can bus - in a thread, or when its owner calls :meth:`pump` - and sends.

    ``handler(frames)`` gets the frames read in one go, ``[(cob_id, data, t_arrival), ...]``
    in bus order (exceptions are logged, never raised). Only one reader at a time: the
    thread (:meth:`start` / :meth:`stop`) or :meth:`pump`.
    ``poll_s``: ``None`` - the thread blocks until a frame arrives (waking every ``_IDLE_S``);
    a number - it never blocks longer: an empty read is followed by ``on_idle()`` (if given:
    periodic work without another thread competing for the GIL) and ``time.sleep(poll_s)``.
    On a KVM guest a thread that blocks longer than ~200 us (the halt-polling window) lets its
    vCPU halt, and waking it costs 0.5-50 ms now and then; a drive must answer within one SYNC
    period, so the emulated drive polls.

    ``udp_multicast``: the bus's socket is read and written directly (a duplicate of its
    file descriptor) in python-can's wire format (one msgpack map per frame): reading,
    decoding and dispatching a frame costs ~15 us instead of ~40 us through ``bus.recv()``;
    ``t_arrival`` is the kernel's receive time. On the loopback-confined bus
    (:class:`drivers.cia402.bus.LoopbackUdpMulticastBus`) frames go out through the bus's send
    socket and those from its address are dropped (a node does not receive its own frames);
    on python-can's own ``udp_multicast`` bus they come back, in bus order. Frames the kernel
    dropped because the receive buffer was full are counted in :attr:`dropped`. Other
    interfaces: ``bus.recv()``.

    ``timed`` (``udp_multicast``, ``socketcan``, ``virtual``): ``t_arrival`` is the frame's
    time on the bus (kernel receive time; the virtual bus's send time) converted to
    ``time.monotonic()``, not the time this process read it; :attr:`read_until` is the
    monotonic time at which the last completed read began (every frame stamped before it has
    been handed over by then). Elsewhere ``t_arrival`` is the time of reading.
    """

    def __init__(self, bus: can.BusABC, handler: Callable[[list[Frame]], None], *,
                 bus_kwargs: Mapping[str, Any], poll_s: float | None = None, name: str = "canopen-rx",
                 send_lock: Any = None, on_idle: Callable[[], None] | None = None) -> None:
        self.bus = bus
        self._handler = handler
        self._on_idle = on_idle
        self.poll_s = poll_s
        self.name = name
        self._lock = send_lock if send_lock is not None else threading.Lock()
        self.udp = bus_kwargs.get("interface") == "udp_multicast"
        # frames stamped with their time on the bus, on the realtime clock (python-can: SocketCAN's kernel
        # receive time, the virtual bus's send time; udp_multicast: the kernel's, read here)
        self.timed = self.udp or bus_kwargs.get("interface") in ("socketcan", "virtual")
        self.read_until = -math.inf   # monotonic time at which the last completed read began
        self.local_only = confined(bus_kwargs)   # drop datagrams from anywhere but this host (drivers.cia402.bus)
        self.foreign = 0          # datagrams dropped because they came from another address
        self._dest = (str(bus_kwargs.get("channel")), int(bus_kwargs.get("port") or UDP_DEFAULT_PORT))
        self._sock: socket.socket | None = None
        self._tx: socket.socket | None = None
        self._own: tuple[str, int] | None = getattr(bus, "own_address", None)   # our frames' source: dropped
        self._templates: dict[tuple[int, int], tuple[bytes, bytes]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._unpack: Callable | None = None
        self._mono_offset = _clock_offset() or time.time() - time.monotonic()   # realtime stamps -> monotonic
        self._offset_at = time.monotonic()
        self.frames = 0           # frames handed to the handler
        self.malformed = 0        # datagrams that are not python-can frames
        self.dropped = 0          # frames the kernel dropped (receive buffer full)
        self.errors = 0           # handler exceptions
        self.failure: str | None = None   # why reading stopped (the bus broke)

    @property
    def own_frames_back(self) -> bool:
        """True when this bus hands its own frames back in bus order (python-can's ``udp_multicast``
        bus open to the network); never on CAN or the loopback-confined bus."""
        return self.udp and self._own is None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def open(self) -> FrameIO:
        """The duplicate socket (udp_multicast; idempotent). :meth:`start` and :meth:`pump` call it."""
        if self.udp and self._sock is None:
            import msgpack

            self._unpack = msgpack.unpackb
            sock = socket.socket(fileno=os.dup(self.bus.fileno()))
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
                sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            except OSError as exc:
                log.warning("canopen: receive buffer / drop counter not available: %s", exc)
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            except OSError as exc:              # then a frame's time is when it was read: not timed
                self.timed = False
                log.warning("canopen: kernel receive times not available (%s): frames are placed among the "
                            "SYNCs in the order a thread reads them", exc)
            tx_fileno = getattr(self.bus, "tx_fileno", None)
            self._tx = socket.socket(fileno=os.dup(tx_fileno())) if tx_fileno is not None else sock
            self._sock = sock
        return self

    def start(self) -> FrameIO:
        """Read in a thread (it inherits the creating thread's CPU set and scheduling)."""
        if self.running:
            return self
        self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the thread (idempotent); frames keep queueing in the socket until read."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("%s: receive thread did not stop within %.2f s", self.name, timeout)
            self._thread = None

    def close(self) -> None:
        """Stop, and close the duplicate socket (the bus itself stays open)."""
        self.stop()
        if self._tx is not None and self._tx is not self._sock:
            self._tx.close()
        self._tx = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # ----- sending ----------------------------------------------------------------------
    def send(self, cob_id: int, data: bytes) -> None:
        """Send one 11-bit data frame (thread-safe). Raises python-can's or the socket's error."""
        sock = self._tx
        if sock is not None:
            key = (cob_id, len(data))
            tpl = self._templates.get(key)
            if tpl is None:
                tpl = self._templates[key] = _udp_template(cob_id, len(data))
            sock.sendto(tpl[0] + data + tpl[1], self._dest)
            return
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
        with self._lock:
            self.bus.send(msg)

    # ----- receiving --------------------------------------------------------------------
    def pump(self, limit: int = 4096) -> int:
        """Read every frame waiting now (at most ``limit``) and hand them over; returns how many.
        A read that got every waiting frame moves :attr:`read_until` to the time it began.

        Raises :class:`OSError` / ``can.CanError`` if the bus broke.
        """
        began = time.monotonic()
        frames = self.read_now(limit)
        self._deliver(frames)
        if len(frames) < limit:
            self.read_until = began
        return len(frames)

    def read_now(self, limit: int = 4096) -> list[Frame]:
        """The frames waiting now, not handed over (for a handler that looks ahead; same thread only)."""
        self.open()
        sock = self._sock
        return self._read_udp(sock, limit) if sock is not None else self._read_bus(limit)

    def _deliver(self, frames: list[Frame]) -> None:
        if not frames:
            return
        self.frames += len(frames)
        try:
            self._handler(frames)
        except Exception:  # noqa: BLE001 - a reader must survive its handler
            self.errors += 1
            log.exception("%s: frame handler failed", self.name)

    def _follow_clock(self) -> float:
        """The realtime -> monotonic offset of frame times, measured again every ``_OFFSET_EVERY_S``
        (the realtime clock is slewed by NTP; the monotonic one is not stepped)."""
        if time.monotonic() - self._offset_at > _OFFSET_EVERY_S:
            self._offset_at = time.monotonic()
            self._mono_offset = _clock_offset() or self._mono_offset
        return self._mono_offset

    def _read_udp(self, sock: socket.socket, limit: int) -> list[Frame]:
        recvmsg, unpack, offset, own = sock.recvmsg, self._unpack, self._follow_clock(), self._own
        assert unpack is not None               # open() set it with the socket
        frames: list[Frame] = []
        while len(frames) < limit:
            try:
                raw, anc, _, src = recvmsg(4096, 256, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            if self.local_only and not (src and str(src[0]).startswith("127.")):
                self.foreign += 1
                continue
            if own is not None and src is not None and tuple(src[:2]) == own:
                continue                        # our own frame: a CAN node does not receive it
            t = 0.0
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET:
                    if kind == _SO_TIMESTAMPNS and len(value) >= _TIMESPEC.size:
                        sec, nsec = _TIMESPEC.unpack_from(value)
                        t = sec + 1e-9 * nsec - offset
                    elif kind == _SO_RXQ_OVFL and len(value) >= 4:
                        self.dropped = struct.unpack_from("I", value)[0]
            try:
                d = unpack(raw, raw=True)
                if d.get(b"is_error_frame") or d.get(b"is_remote_frame"):
                    continue
                frames.append((d[b"arbitration_id"], d[b"data"], t or time.monotonic()))
            except Exception:  # noqa: BLE001 - not a python-can frame
                self.malformed += 1
        return frames

    def _read_bus(self, limit: int, timeout: float = 0.0) -> list[Frame]:
        frames: list[Frame] = []
        msg = self.bus.recv(timeout)
        offset = self._follow_clock() if self.timed else None
        while msg is not None:
            if not (msg.is_error_frame or msg.is_remote_frame):
                now = time.monotonic()
                t = msg.timestamp - offset if offset is not None and msg.timestamp else now
                frames.append((msg.arbitration_id, bytes(msg.data), min(t, now)))
            if len(frames) >= limit:
                break
            msg = self.bus.recv(0.0)
        return frames

    def _run(self) -> None:
        stop, poll_s = self._stop, self.poll_s
        poller = None
        if self._sock is not None and poll_s is None:
            poller = select.poll()
            poller.register(self._sock.fileno(), select.POLLIN)
        while not stop.is_set():
            try:
                if self._sock is None and poll_s is None:       # block in python-can's recv
                    began = time.monotonic()
                    frames = self._read_bus(512, _IDLE_S)
                    self._deliver(frames)
                    if len(frames) < 512:
                        self.read_until = began
                    continue
                if self.pump(512):
                    continue
            except Exception as exc:  # noqa: BLE001 - the bus is closing or broken
                if not stop.is_set():
                    self.failure = f"{type(exc).__name__}: {exc}"
                    log.error("%s: reading the bus failed: %s", self.name, exc)
                return
            if poller is not None:
                poller.poll(int(_IDLE_S * 1000))
                continue
            if self._on_idle is not None:
                try:
                    self._on_idle()
                except Exception:  # noqa: BLE001
                    self.errors += 1
                    log.exception("%s: idle work failed", self.name)
            assert poll_s is not None           # else the socket's poller or python-can's recv waited above
            time.sleep(poll_s)

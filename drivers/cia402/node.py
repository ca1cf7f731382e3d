"""Connection and SDO configuration of one CiA 402 node (the blocking, non-cyclic part of the backend).

Everything here runs in ``open()``/``activate()``/``close()``, never in ``read()``:
canopen's blocking SDO helpers are fine at start-up and must stay out of the loop.
Errors: no answer -> :class:`DeviceConnectionError` (node id and time waited); an
object missing from the EDS or refused by the drive -> :class:`ProtocolError` naming
the object; an SDO timeout in the middle of the set-up -> :class:`DeviceTimeout`.

Frames are received by :class:`~drivers.cia402.frames.FrameIO` (shared with the emulated drive), not by
canopen's ``Network.connect()`` notifier: on ``udp_multicast`` it reads the socket
itself at about a quarter of python-can's cost per frame. Only where the bus hands this
host's own SYNCs back in bus order (python-can's ``udp_multicast`` open to the network) does
the sample assembly use them as window markers; on CAN and the loopback-confined bus the
SYNC sender's marker times do, compared with each frame's time on the bus (see
:mod:`drivers.cia402.stream`).
"""

from __future__ import annotations

import logging
import math
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.cia402 import profile as p402
from drivers.cia402.bus import open_bus
from drivers.cia402.config import Cia402Config
from drivers.cia402.frames import FrameIO, stop_periodic
from drivers.cia402.stream import RpdoChannel, SyncSender
from drivers.cia402.variants import interpolation_period
from drivers.errors import DeviceConnectionError, DeviceTimeout, ProtocolError
from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)


class _SdoTimeoutAbortFilter(logging.Filter):
    """canopen logs an ERROR for the abort (0x05040000) it sends on every SDO timeout; this module raises
    its own error for each such timeout, naming the object and sdo_timeout, so the library's line goes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (isinstance(record.msg, str) and record.msg.startswith("Transfer aborted by client")
                    and record.args == (0x05040000,))


logging.getLogger("canopen.sdo.client").addFilter(_SdoTimeoutAbortFilter())


def _best_effort(what: str, steps: Iterable[Callable[[], object]]) -> None:
    """Run every step of a stop path; a failing one is logged and the next still runs."""
    for step in steps:
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - a stop path must reach its end
            log.warning("canopen: %s step failed: %s", what, exc)


class SdoRefused(ProtocolError):
    """The drive aborted an SDO transfer; ``code`` is its abort code."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


#: Aborts that say a PDO's mapping record has no room for another entry.
_NO_ROOM = (0x06090011, 0x06040042)
#: Aborts that say a drive does not take an optional object (absent, read-only, value refused).
_NOT_TAKEN = (0x06020000, 0x06010002, 0x06090030, 0x06090011)


class _NoRoom(Exception):
    """A PDO's mapping takes only ``entries`` objects (``cause``: the drive's abort)."""

    def __init__(self, entries: int, cause: str) -> None:
        super().__init__(cause)
        self.entries = entries
        self.cause = cause


class BusConnection:
    """One CAN interface, opened once per process and shared by every drive on it.

    A bus has one SYNC producer and one host heartbeat, whatever the number of drives: the
    two axes of an XY table on one bus are two :class:`NodeSetup` (and two backends) on one
    connection. It owns the python-can bus, the ``canopen.Network`` (each drive adds its
    ``RemoteNode``), the :class:`~drivers.cia402.frames.FrameIO` reading it (whichever backend
    pumps it delivers every drive's frames), the host heartbeat and the
    :class:`~drivers.cia402.stream.SyncSender`: the first drive to activate starts it, the
    others join it (:meth:`join_sync`), the last to leave stops it (:meth:`leave_sync`).
    Connections are keyed by interface, channel and port, and counted: the last
    :meth:`release` closes the bus.

    Echoes of this host's SYNCs (where the bus hands them back: :attr:`FrameIO.own_frames_back`) are
    counted here, so that each drive's deque can tell the SYNCs sent before its channel joined from its
    own (``(ECHO, t, n)``).
    """

    _open: dict[tuple, BusConnection] = {}
    _registry = threading.Lock()

    def __init__(self, cfg: Cia402Config) -> None:
        self.cfg = cfg
        self.key = self.key_of(cfg)
        self.refs = 0
        self.network: canopen.Network | None = None
        self.io: FrameIO | None = None
        self.sender: SyncSender | None = None
        self.syncs_sent = 0                    # by senders that have stopped
        self.syncs_seen = 0                    # SYNC echoes read back
        self._echo_subscribers: list[Callable] = []
        self._hb_task: Any = None
        self._lock = threading.Lock()
        self._switch_interval: float | None = None

    @staticmethod
    def key_of(cfg: Cia402Config) -> tuple:
        kw = cfg.bus_kwargs()
        return (kw.get("interface"), str(kw.get("channel")), kw.get("port"))

    @classmethod
    def acquire(cls, cfg: Cia402Config) -> BusConnection:
        """The open connection to ``cfg``'s bus, opened now if it is not; one reference more."""
        with cls._registry:
            conn = cls._open.get(cls.key_of(cfg))
            if conn is None:
                conn = cls(cfg)
                conn._connect()
                cls._open[conn.key] = conn
            else:
                conn._check_compatible(cfg)
            conn.refs += 1
            return conn

    def release(self) -> None:
        """One reference less; the last closes the bus (never raises)."""
        with self._registry:
            self.refs -= 1
            if self.refs > 0:
                return
            if self._open.get(self.key) is self:
                del self._open[self.key]
        self._shutdown()

    def _check_compatible(self, cfg: Cia402Config) -> None:
        mine = self.cfg
        for field in ("bitrate", "sync_rate_hz", "master_node_id", "heartbeat_ms"):
            if getattr(cfg, field) != getattr(mine, field):
                raise ConfigError(f"backend.{field}", f"node {cfg.node_id} asks for {getattr(cfg, field)} on "
                                  f"{mine.interface}:{mine.channel}, where node {mine.node_id} already runs "
                                  f"{getattr(mine, field)}; drives on one bus share it")

    def _connect(self) -> None:
        cfg = self.cfg
        try:
            bus = open_bus(cfg.bus_kwargs())
        except Exception as exc:  # noqa: BLE001 - python-can raises many types here
            raise DeviceConnectionError(f"cannot open CAN interface {cfg.interface!r} channel {cfg.channel!r}: "
                                        f"{type(exc).__name__}: {exc}") from exc
        net = canopen.Network(bus)
        self.network = net
        self.io = FrameIO(bus, self._dispatch, bus_kwargs=cfg.bus_kwargs(), send_lock=net.send_lock,
                          name=f"canopen-rx-{cfg.channel}").start()
        if self.io.own_frames_back:
            net.subscribe(0x80, self._on_sync_echo)
        self._hb_task = net.send_periodic(0x700 + cfg.master_node_id, bytes([0x05]), cfg.heartbeat_ms / 1000.0)

    def _dispatch(self, frames: list) -> None:
        net = self.network
        assert net is not None                  # FrameIO runs between _connect and _shutdown
        notify = net.notify
        for cob, data, t in frames:
            notify(cob, data, t)

    def _on_sync_echo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.syncs_seen += 1
        n = self.syncs_seen
        for cb in self._echo_subscribers:
            cb(timestamp, n)

    def subscribe_echo(self, callback: Callable[[float, int], None]) -> None:
        self._echo_subscribers.append(callback)

    def unsubscribe_echo(self, callback: Callable[[float, int], None] | None) -> None:
        if callback in self._echo_subscribers:
            self._echo_subscribers.remove(callback)

    # ----- the one SYNC producer --------------------------------------------------------
    def join_sync(self, channel: RpdoChannel, gil_switch_interval_us: float | None) -> SyncSender:
        """Start the bus's SYNC sender with this channel, or add the channel to the running one."""
        with self._lock:
            sender = self.sender
            if sender is not None and sender.running:
                sender.join(channel)
                return sender
            if sender is not None:
                self.syncs_sent += sender.sent
            cfg = self.cfg
            every = max(1, int(round(cfg.heartbeat_ms / 1000.0 / cfg.sample_period)))
            assert self.io is not None              # connected (acquire)
            sender = SyncSender.for_channel(self.io.send, cfg.sample_period, channel, sent_before=self.syncs_sent,
                                            heartbeat=(0x700 + cfg.master_node_id, every))
            self.sender = sender
            self._heartbeat_task(False)         # the sender's thread sends the host's heartbeat now
            if gil_switch_interval_us is not None and self._switch_interval is None:
                self._switch_interval = sys.getswitchinterval()
                sys.setswitchinterval(min(self._switch_interval, 1e-6 * gil_switch_interval_us))
            sender.start()
            return sender

    def leave_sync(self, channel: RpdoChannel) -> None:
        """Stop sending this channel; the last channel's leave stops the SYNC (idempotent, never raises)."""
        with self._lock:
            sender = self.sender
            if sender is None:
                return
            sender.leave(channel)
            if sender.channels > 0 and sender.running:
                return
            sender.stop()
            self._heartbeat_task(True)
            if self._switch_interval is not None:
                sys.setswitchinterval(self._switch_interval)
                self._switch_interval = None

    def _heartbeat_task(self, run: bool) -> None:
        """The host's heartbeat from canopen's periodic task (while no SYNC runs), or not (never raises)."""
        try:
            if run and self._hb_task is None and self.network is not None:
                cfg = self.cfg
                self._hb_task = self.network.send_periodic(0x700 + cfg.master_node_id, bytes([0x05]),
                                                           cfg.heartbeat_ms / 1000.0)
            elif not run and self._hb_task is not None:
                stop_periodic(self._hb_task)
                self._hb_task = None
        except Exception as exc:  # noqa: BLE001
            log.warning("canopen: host heartbeat task: %s", exc)

    def _shutdown(self) -> None:
        if self.sender is not None:
            self.sender.stop()
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None
        net = self.network
        if net is None:
            return
        _best_effort("closing the bus", (lambda: stop_periodic(self._hb_task),
                                         lambda: self.io.close() if self.io is not None else None,
                                         net.disconnect))
        self._hb_task = None
        self.io = None
        self.network = None


class NodeSetup:
    """Owns the ``RemoteNode`` of one drive and its SDO set-up, on a shared :class:`BusConnection`."""

    def __init__(self, cfg: Cia402Config, *, on_tpdo: Callable, on_heartbeat: Callable,
                 on_emcy: Callable, on_sync_echo: Callable | None = None) -> None:
        self.cfg = cfg
        self._on_tpdo = on_tpdo
        self._on_heartbeat = on_heartbeat
        self._on_emcy = on_emcy
        self._on_sync_echo = on_sync_echo
        self.conn: BusConnection | None = None
        self.network: canopen.Network | None = None
        self.io: FrameIO | None = None
        self.node: canopen.RemoteNode | None = None
        self.rpdo_cob = 0x200 + cfg.node_id
        self.tpdo_cobs: list[int] = []
        self.tpdo_layouts: list[tuple[int, struct.Struct]] = []
        self._od: canopen.ObjectDictionary | None = None
        self.device_type = 0                    # 0x1000, read by connect()
        self.drive_rated_torque: float | None = None    # 0x6076 [N m]; None: the drive has none
        self.identity: dict[str, Any] = {}      # read by configure(); see identity_objects()

    # ----- objects ----------------------------------------------------------------------
    @property
    def od(self) -> canopen.ObjectDictionary:
        """The EDS's object dictionary (read first thing by :meth:`connect`)."""
        assert self._od is not None, "NodeSetup.connect() reads the EDS first"
        return self._od

    def _var(self, index: int, subindex: int = 0) -> canopen.objectdictionary.ODVariable:
        var = self.od.get_variable(index, subindex)
        if var is None:
            raise ProtocolError(f"EDS {self.cfg.eds_path().name} lacks {p402.object_label(index, subindex or None)}; "
                                f"the backend needs it for a CiA 402 drive in CST mode")
        return var

    def _data_type(self, index: int, subindex: int = 0) -> int:
        """The object's CANopen data type code (the EDS states one for every object it defines)."""
        code = self._var(index, subindex).data_type
        if code is None:
            raise ProtocolError(f"EDS {self.cfg.eds_path().name} gives {p402.object_label(index, subindex or None)} "
                                f"no data type")
        return code

    def _check_od(self) -> None:
        cfg = self.cfg
        mapped = [(p402.CONTROLWORD, 0), (p402.TARGET_TORQUE, 0), (p402.STATUSWORD, 0),
                  (p402.POSITION_ACTUAL, 0), (p402.TORQUE_ACTUAL, 0), (cfg.scale_index, cfg.scale_subindex)]
        for index, sub in mapped:
            if not self._var(index, sub).pdo_mappable:
                raise ProtocolError(f"EDS {cfg.eds_path().name} marks {p402.object_label(index, sub)} as not "
                                    f"PDO-mappable")
        for index, sub in [(p402.MODES_OF_OPERATION, 0), (p402.MODES_DISPLAY, 0), (p402.MAX_TORQUE, 0),
                           (p402.PRODUCER_HEARTBEAT, 0), (p402.CONSUMER_HEARTBEAT, 1), (0x1400, 1),
                           (0x1600, 1), (0x1800, 1), (0x1801, 1), (0x1A00, 1), (0x1A01, 1)]:
            self._var(index, sub)
        scale_type = self._data_type(cfg.scale_index, cfg.scale_subindex)
        if scale_type not in (0x04, 0x07):
            raise ProtocolError(f"table scale object {p402.object_label(cfg.scale_index, cfg.scale_subindex)} "
                                f"has data type 0x{scale_type:04X}; a 32-bit integer is required")

    # ----- SDO with errors that name the object -----------------------------------------
    def upload(self, index: int, subindex: int, what: str = "") -> int:
        try:
            return self._read(index, subindex, self._data_type(index, subindex))
        except SdoAbortedError as exc:
            raise ProtocolError(f"node {self.cfg.node_id} refused reading {p402.object_label(index, subindex)}"
                                f"{what}: {p402.abort_text(exc.code)}") from exc

    def _read(self, index: int, subindex: int, code: int) -> int:
        """One SDO read decoded as data type ``code``; an abort propagates, a silence is DeviceTimeout."""
        assert self.node is not None            # connected
        try:
            data = self.node.sdo.upload(index, subindex)
        except SdoCommunicationError as exc:
            raise DeviceTimeout(f"node {self.cfg.node_id} did not answer reading "
                                f"{p402.object_label(index, subindex)} within sdo_timeout "
                                f"{self.cfg.sdo_timeout:g} s") from exc
        st = struct.Struct("<" + p402.STRUCT_CODE[code])
        return st.unpack_from(bytes(data).ljust(st.size, b"\0"))[0]

    def download(self, index: int, subindex: int, value: int, what: str = "", code: int | None = None) -> None:
        """Write an object by SDO (its data type from the EDS, or ``code`` for one the EDS lacks).
        A refusal raises :class:`SdoRefused` (a :class:`ProtocolError` naming the object and the abort)."""
        code = self._data_type(index, subindex) if code is None else code
        data = struct.pack("<" + p402.STRUCT_CODE[code], value)
        assert self.node is not None            # connected
        try:
            self.node.sdo.download(index, subindex, data)
        except SdoAbortedError as exc:
            raise SdoRefused(exc.code, f"node {self.cfg.node_id} refused writing {p402.object_label(index, subindex)} "
                             f"= 0x{value & 0xFFFFFFFF:X}{what}: {p402.abort_text(exc.code)}") from exc
        except SdoCommunicationError as exc:
            raise DeviceTimeout(f"node {self.cfg.node_id} did not answer writing "
                                f"{p402.object_label(index, subindex)} within sdo_timeout "
                                f"{self.cfg.sdo_timeout:g} s") from exc

    def try_download(self, index: int, subindex: int, data: bytes) -> bool:
        """Best effort (stop paths): log failures, never raise."""
        try:
            if self.node is not None and self.network is not None and self.network.bus is not None:
                self.node.sdo.download(index, subindex, data)
                return True
        except Exception as exc:  # noqa: BLE001
            log.warning("canopen: writing 0x%04X:%02X failed: %s", index, subindex, exc)
        return False

    def try_upload(self, index: int, subindex: int) -> int | None:
        """Best effort (stop paths): the object's value, or None (logged); never raises."""
        try:
            if self.node is not None and self.network is not None and self.network.bus is not None:
                return self._read(index, subindex, self._data_type(index, subindex))
        except Exception as exc:  # noqa: BLE001
            log.warning("canopen: reading 0x%04X:%02X failed: %s", index, subindex, exc)
        return None

    @property
    def echo(self) -> bool:
        """True when this host's own frames come back in bus order (python-can's ``udp_multicast``
        open to the network): then the echoed SYNCs, not the sender's clock, mark the sample windows."""
        return self.io is not None and self.io.own_frames_back and self._on_sync_echo is not None

    @property
    def timed(self) -> bool:
        """True when the frames carry their time on the bus on this host's clock and this host's own
        frames do not come back: the sender's marker times mark the sample windows."""
        return self.io is not None and self.io.timed and not self.echo

    @property
    def read_until(self) -> float:
        """Every frame on the bus before this monotonic time has been handed over (timed buses)."""
        return self.io.read_until if self.io is not None else -math.inf

    def send(self, cob_id: int, data: bytes) -> None:
        """Send one frame (thread-safe; a fraction of the cost of ``Network.send_message``, used per SYNC)."""
        assert self.io is not None              # connected
        self.io.send(cob_id, data)

    def receive_in_caller(self) -> None:
        """Stop the receive thread: from now on the caller reads the bus with :meth:`pump` (echo mode)."""
        assert self.io is not None              # connected
        self.io.stop()

    def receive_in_thread(self) -> None:
        """Read the bus in a thread again (SDO needs it); a no-op if it runs. Never raises (stop paths)."""
        if self.io is not None and not self.io.running:
            try:
                self.io.start()
            except Exception as exc:  # noqa: BLE001
                log.warning("canopen: receive thread not restarted: %s", exc)

    def pump(self) -> None:
        """Read and dispatch every frame waiting now (only while the receive thread is stopped)."""
        io = self.io
        if io is not None and not io.running:
            try:
                io.pump()
            except Exception as exc:  # noqa: BLE001 - python-can / socket errors
                raise DeviceConnectionError(f"reading CAN interface {self.cfg.interface!r} channel "
                                            f"{self.cfg.channel!r} failed: {type(exc).__name__}: {exc}") from exc

    # ----- start-up ---------------------------------------------------------------------
    def connect(self) -> None:
        """Bus, network, node, heartbeat producer, NMT PRE-OPERATIONAL, probe of 0x1000."""
        cfg = self.cfg
        path = cfg.eds_path()
        try:
            self._od = canopen.import_od(str(path), cfg.node_id)
        except Exception as exc:  # noqa: BLE001 - any parse failure is a config error
            # the parser's message can quote the file's lines: name the file and the kind of error only
            raise ConfigError("backend.eds", f"cannot read EDS {path}: not a valid EDS file "
                                             f"({type(exc).__name__})") from None
        self._check_od()
        conn = BusConnection.acquire(cfg)        # shared with any other drive on this bus
        self.conn = conn
        net = self.network = conn.network
        self.io = conn.io
        assert net is not None                  # acquire() connected it
        if net.nodes.get(cfg.node_id) is not None:
            raise ConfigError("backend.node_id", f"node {cfg.node_id} is configured twice on "
                                                 f"{cfg.interface}:{cfg.channel}")
        if self.echo and self._on_sync_echo is not None:      # (echo implies the callback)
            conn.subscribe_echo(self._on_sync_echo)
        node = canopen.RemoteNode(cfg.node_id, self._od)
        net.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = cfg.sdo_timeout
        self.node = node
        net.subscribe(0x700 + cfg.node_id, self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        node.nmt.send_command(0x80)                       # PRE-OPERATIONAL: SDO on, PDOs off
        t0 = time.monotonic()
        try:
            device_type = node.sdo.upload(p402.DEVICE_TYPE, 0)
        except SdoCommunicationError:
            raise DeviceConnectionError(
                f"no answer from CANopen node {cfg.node_id} on {cfg.interface}:{cfg.channel} within "
                f"{time.monotonic() - t0:.2f} s (SDO read of 0x1000 device type, sdo_timeout "
                f"{cfg.sdo_timeout:g} s): is the drive powered and on this bus, and do backend.node_id, "
                f"backend.interface and backend.channel name it?") from None
        except SdoAbortedError as exc:
            raise ProtocolError(f"node {cfg.node_id} refused reading 0x1000 device type: "
                                f"{p402.abort_text(exc.code)}") from exc
        self.device_type = struct.unpack_from("<I", bytes(device_type).ljust(4, b"\0"))[0]
        profile = self.device_type & 0xFFFF
        if profile != 402:
            raise ProtocolError(f"node {cfg.node_id} reports device profile {profile} in 0x1000, not 402 (drive)")

    def configure(self) -> float:
        """PDO mapping, mode 10 verified, torque limit, cycle period, heartbeats. Returns the rated torque [N m]."""
        cfg = self.cfg
        rated = self._rated_torque()
        self._probe_streamed()
        # RPDO1: controlword + target torque, applied at each SYNC
        self.rpdo_cob = self._map_pdo(0x1400, 0x1600, [(p402.CONTROLWORD, 0), (p402.TARGET_TORQUE, 0)],
                                      0x200 + cfg.node_id, "RPDO1")
        streamed = [(p402.STATUSWORD, 0), (p402.POSITION_ACTUAL, 0), (p402.TORQUE_ACTUAL, 0),
                    (cfg.scale_index, cfg.scale_subindex)]
        tpdos = self._map_tpdos(streamed)
        self._disable_unused(0x1400, used=1)
        self._disable_unused(0x1800, used=len(tpdos))
        self.tpdo_cobs = [cob for cob, _ in tpdos]
        self.tpdo_layouts = [(cob, p402.pdo_struct([self._data_type(i, s) for i, s in entries]))
                             for cob, entries in tpdos]
        assert self.network is not None         # connected
        for cob in self.tpdo_cobs:
            self.network.subscribe(cob, self._on_tpdo)
        self._set_cycle_time()
        self._set_mode_cst()
        permille = cfg.max_torque_permille or min(65535, int(round(cfg.torque_limit * 1000.0 / rated)))
        self.download(p402.MAX_TORQUE, 0, permille, " (drive-side torque limit, per mille of rated torque)")
        self.download(p402.PRODUCER_HEARTBEAT, 0, cfg.heartbeat_ms)
        self.download(p402.CONSUMER_HEARTBEAT, 1, (cfg.master_node_id << 16) | cfg.consumer_ms)
        deadline_note = self._set_rpdo_deadline()
        self.identity = self.identity_objects()
        self.identity["rpdo_deadline_ms"] = self.rpdo_deadline_ms
        if deadline_note:
            self.identity["notes"].append(deadline_note)
        return rated

    def _set_rpdo_deadline(self) -> str | None:
        """RPDO1's deadline monitoring (0x1400:05), so the drive itself ends a silence of the host's
        torques. A drive that refuses it: a note (an error when the config asked for it), and
        :attr:`rpdo_deadline_ms` None."""
        cfg = self.cfg
        self.rpdo_deadline_ms: int | None = cfg.rpdo_deadline_ms
        if not cfg.rpdo_deadline_ms:
            return None
        try:
            self.download(0x1400, 5, cfg.rpdo_deadline_ms, " (RPDO1 deadline monitoring)", code=0x06)
        except SdoRefused as exc:
            if "rpdo_deadline_ms" in cfg.model_fields_set:
                raise ConfigError("backend.rpdo_deadline_ms", f"{exc}; set 0 to run without it") from exc
            self.rpdo_deadline_ms = None
            note = (f"0x1400:05: no RPDO deadline ({p402.abort_text(exc.code)}): a stalled host's last torque "
                    f"stays until the heartbeat consumer trips ({cfg.consumer_ms} ms)")
            log.warning("canopen: node %d: %s", cfg.node_id, note)
            return note
        return None

    def optional_upload(self, index: int, subindex: int = 0, code: int = 0x07) -> int | None:
        """An object the drive may lack, read by SDO whether or not the EDS lists it (its data type from
        the EDS if listed, else ``code``): None when the drive aborts the read (no such object)."""
        var = self.od.get_variable(index, subindex)
        if var is not None and var.data_type in p402.STRUCT_CODE:
            code = var.data_type
        try:
            return self._read(index, subindex, code)
        except SdoAbortedError:
            return None

    def identity_objects(self) -> dict[str, Any]:
        """What the drive says it is, by SDO (start-up only): 0x1000, 0x6502, 0x6076, 0x6072, 0x607E, the
        identity object 0x1018 (vendor, product, revision, serial number) and the node id. An object the
        drive lacks is None and named in ``notes``."""
        modes = self.optional_upload(p402.SUPPORTED_MODES, 0, 0x07)
        polarity = self.optional_upload(p402.POLARITY, 0, 0x05)
        notes = [f"0x{index:04X}: not present" for index, v in ((p402.SUPPORTED_MODES, modes),
                                                                (p402.RATED_TORQUE, self.drive_rated_torque),
                                                                (p402.POLARITY, polarity)) if v is None]
        unit = {k: self.optional_upload(p402.IDENTITY, sub, 0x07)
                for k, sub in (("vendor_id", 1), ("product_code", 2), ("revision", 3), ("serial_number", 4))}
        if unit["serial_number"] is None:
            notes.append("0x1018:04 (serial number): not present")
        return {"node_id": self.cfg.node_id, "device_type": self.device_type, "supported_drive_modes": modes,
                "rated_torque_nm": self.drive_rated_torque, "max_torque_permille": self.upload(p402.MAX_TORQUE, 0),
                "polarity": polarity, **unit, "notes": notes}

    def _rated_torque(self) -> float:
        cfg = self.cfg
        milli = self.optional_upload(p402.RATED_TORQUE, 0, 0x07)       # mN m
        drive = milli / 1000.0 if milli else None
        self.drive_rated_torque = drive
        if cfg.rated_torque is None:
            if not drive:
                raise ConfigError("backend.rated_torque", f"not given and node {cfg.node_id} reports no "
                                  f"motor rated torque (0x6076)")
            return drive
        if drive and abs(drive - cfg.rated_torque) > 0.01 * drive:
            raise ConfigError("backend.rated_torque", f"{cfg.rated_torque:g} N m in the config but node "
                              f"{cfg.node_id} reports {drive:g} N m in 0x6076 (motor rated torque); torques would "
                              f"be scaled wrongly (leave backend.rated_torque unset to use the drive's)")
        return cfg.rated_torque

    def _probe_streamed(self) -> None:
        """Read every object the TPDOs will carry once by SDO: a drive without one is refused here, in one
        line naming the object and the drive's abort (the table scale's says where else it can come from)."""
        cfg = self.cfg
        for index, sub in ((p402.STATUSWORD, 0), (p402.POSITION_ACTUAL, 0), (p402.TORQUE_ACTUAL, 0)):
            self.upload(index, sub, " (streamed in every sample)")
        try:
            self.upload(cfg.scale_index, cfg.scale_subindex)
        except ProtocolError as exc:
            raise ProtocolError(f"{exc} - the table scale (backend.scale_index / scale_subindex); a drive without "
                                f"0x60E4 needs the object its second encoder input is read from, named there "
                                f"with that drive's EDS") from None

    def _map_tpdos(self, entries: list[tuple[int, int]]) -> list[tuple[int, list[tuple[int, int]]]]:
        """The streamed objects in TPDO1 (statusword, position, torque) and TPDO2 (scale); on a drive that
        takes fewer entries per PDO, across TPDOs in the same order (at least 2 per PDO: the set stays
        two frames per SYNC). Returns ``[(cob, entries)]``."""
        cfg = self.cfg
        chunks = [entries[:3], entries[3:]]
        while True:
            try:
                return [(self._map_pdo(0x1800 + n, 0x1A00 + n, chunk, (0x180, 0x280, 0x380, 0x480)[n] + cfg.node_id,
                                       f"TPDO{n + 1}"), chunk) for n, chunk in enumerate(chunks)]
            except _NoRoom as room:
                size = max(len(c) for c in chunks)
                if room.entries >= size or room.entries < 2:
                    raise ProtocolError(f"node {cfg.node_id} maps at most {room.entries} objects into a PDO "
                                        f"({room.cause}); the backend needs at least 2") from None
                log.info("canopen: node %d maps at most %d objects per PDO: the streamed objects go across "
                         "TPDOs", cfg.node_id, room.entries)
                n = room.entries
                chunks = [entries[i:i + n] for i in range(0, len(entries), n)]

    def _map_pdo(self, comm: int, mapping: int, entries: list[tuple[int, int]], default_cob: int,
                 label: str) -> int:
        """CiA 301 sequence: invalidate, transmission type 1, count 0, entries, count, validate.
        An entry the drive has no room for raises :class:`_NoRoom`; one it cannot map, a one-line
        :class:`ProtocolError` naming the object and the abort."""
        cob = self.upload(comm, 1) & 0x7FF or default_cob
        self.download(comm, 1, cob | p402.PDO_INVALID, f" (disable {label} to map it)")
        self.download(comm, 2, p402.TRANS_SYNC_EVERY, f" ({label} transmission type: every SYNC)")
        self.download(mapping, 0, 0, f" (clear {label} mapping)")
        for i, (index, sub) in enumerate(entries, start=1):
            bits = len(self._var(index, sub))
            try:
                self.download(mapping, i, p402.mapping_entry(index, sub, bits),
                              f" (mapping {p402.object_label(index, sub)} into {label})")
            except SdoRefused as exc:
                if exc.code in _NO_ROOM and i > 1:
                    raise _NoRoom(i - 1, p402.abort_text(exc.code)) from None
                raise ProtocolError(f"node {self.cfg.node_id} cannot map {p402.object_label(index, sub)} into "
                                    f"{label}: {p402.abort_text(exc.code)}; the backend needs it in every "
                                    f"sample") from None
        try:
            self.download(mapping, 0, len(entries), f" ({label} mapping count)")
        except SdoRefused as exc:
            if exc.code in _NO_ROOM and len(entries) > 1:
                raise _NoRoom(len(entries) - 1, p402.abort_text(exc.code)) from None
            raise
        self.download(comm, 1, cob, f" (enable {label})")
        return cob

    def _set_cycle_time(self) -> None:
        """The SYNC period in 0x1006 (if the drive takes it: some keep it read-only) and in 0x60C2, the
        interpolation time period, where the drive has one (some need it for cyclic synchronous modes)."""
        cfg = self.cfg
        period = 1.0 / cfg.sync_rate_hz
        self._sync_counter_off()
        if self.od.get_variable(p402.CYCLE_PERIOD) is not None:
            try:
                self.download(p402.CYCLE_PERIOD, 0, int(round(1e6 * period)), " (SYNC period in us)")
            except SdoRefused as exc:
                if exc.code not in _NOT_TAKEN:
                    raise
                log.info("canopen: node %d does not take 0x1006 (%s); the SYNC sets its cycle",
                         cfg.node_id, p402.abort_text(exc.code))
        if self.optional_upload(p402.INTERPOLATION_PERIOD, 1, 0x05) is None:
            return                              # no such object: the drive follows the SYNC
        value, power = interpolation_period(period)
        self.download(p402.INTERPOLATION_PERIOD, 2, power, " (interpolation time index, power of ten)", code=0x02)
        self.download(p402.INTERPOLATION_PERIOD, 1, value, f" (interpolation time period: {value} x 10^{power} s)",
                      code=0x05)

    def _sync_counter_off(self) -> None:
        """0x1019 = 0 on a drive that expects a counter in every SYNC (ours carry none: it would ignore
        them). CiA 301 lets it change only while 0x1006 is 0, so that goes first where the drive takes it."""
        overflow = self.optional_upload(p402.SYNC_OVERFLOW, 0, 0x05)
        if not overflow:
            return
        if self.od.get_variable(p402.CYCLE_PERIOD) is not None:
            try:
                self.download(p402.CYCLE_PERIOD, 0, 0, " (0 before 0x1019 can change)")
            except SdoRefused as exc:
                if exc.code not in _NOT_TAKEN:
                    raise
        self.download(p402.SYNC_OVERFLOW, 0, 0, f" (was {overflow}: this master's SYNCs carry no counter)",
                      code=0x05)
        log.info("canopen: node %d expected a SYNC counter (0x1019 = %d); set to 0", self.cfg.node_id, overflow)

    def _disable_unused(self, comm_base: int, used: int) -> None:
        n = used
        while n < 512 and self.od.get_variable(comm_base + n, 1) is not None:
            try:
                cob = self.upload(comm_base + n, 1)
                if not cob & p402.PDO_INVALID:
                    self.download(comm_base + n, 1, cob | p402.PDO_INVALID)
            except ProtocolError as exc:
                log.warning("canopen: cannot disable unused PDO 0x%04X: %s", comm_base + n, exc)
            n += 1

    def _set_mode_cst(self) -> None:
        """0x6060 = 10 and check 0x6061 ourselves (canopen's op_mode setter only warns)."""
        cfg = self.cfg
        self.download(p402.MODES_OF_OPERATION, 0, p402.MODE_CST, " (cyclic synchronous torque)")
        deadline = time.monotonic() + max(cfg.sdo_timeout, 0.1)
        while True:
            shown = self.upload(p402.MODES_DISPLAY, 0)
            if shown == p402.MODE_CST:
                return
            if time.monotonic() > deadline:
                raise ProtocolError(f"node {cfg.node_id}: 0x6061 (modes of operation display) reads {shown} after "
                                    f"writing 0x6060 = 10; the drive does not run cyclic synchronous torque")
            time.sleep(0.01)

    def nmt_operational(self) -> None:
        assert self.node is not None            # connected
        self.node.nmt.send_command(0x01)

    # ----- shutdown ---------------------------------------------------------------------
    def teardown(self, drive_consumer_off: bool) -> None:
        """Consumer heartbeat off (so the drive does not fault when ours stops), NMT PRE-OPERATIONAL,
        this node off the shared network, then the bus connection released (the last drive's release
        stops the host heartbeat and closes the bus). Idempotent; never raises."""
        net, node, conn = self.network, self.node, self.conn
        if net is None or conn is None:
            return
        self.receive_in_thread()
        if drive_consumer_off and node is not None:
            self.try_download(p402.CONSUMER_HEARTBEAT, 1, struct.pack("<I", 0))
        cfg = self.cfg
        _best_effort("teardown", (
            lambda: node.nmt.send_command(0x80) if node is not None else None,
            lambda: conn.unsubscribe_echo(self._on_sync_echo),
            lambda: net.unsubscribe(0x700 + cfg.node_id, self._on_heartbeat),
            *[(lambda c=cob: net.unsubscribe(c, self._on_tpdo)) for cob in self.tpdo_cobs],
            lambda: net.__delitem__(cfg.node_id) if node is not None and cfg.node_id in net.nodes else None))
        self.io = None
        self.network = None
        self.node = None
        self.conn = None
        conn.release()

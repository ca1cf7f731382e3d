"""CiA 402 servo drive over CANopen in cyclic synchronous torque mode (registry name ``"canopen"``).

Start-up (``open()``): python-can bus + ``canopen.Network``, a ``RemoteNode`` with the
EDS, NMT PRE-OPERATIONAL, probe 0x1000 (no answer -> :class:`DeviceConnectionError`),
PDO mapping by SDO (RPDO1 = controlword 0x6040 + target torque 0x6071; TPDO1 =
statusword 0x6041 + position actual 0x6064 + torque actual 0x6077; TPDO2 = the table
scale object, default 0x60E4:01; transmission type 1 = every SYNC), modes of operation
0x6060 = 10 verified on 0x6061, drive torque limit 0x6072, heartbeats 0x1017/0x1016, and the
identity objects 0x1000, 0x6502, 0x6076, 0x6072, 0x607E read once (:meth:`Cia402Backend.identity`).
``activate()``: NMT OPERATIONAL, SYNC sender running, controlword walks the 402 state
machine to OPERATION ENABLED, confirmed by the statusword within ``startup_timeout``.

Every ``read()`` returns the samples of the SYNCs since the last call (see
:mod:`drivers.cia402.stream`), after checking EMCY, heartbeat age and the sender.
Units: theta1 = counts 2 pi / counts_per_rev; theta2 = (scale counts * scale_resolution)
/ lead; torques per mille of the rated torque. ``t`` is the host's monotonic time of the
SYNC that sampled the data, relative to the first delivered sample (the drive has no
clock in its PDOs); ``seq`` counts SYNC periods from 0 at activation.

Polarity: ``torque_sign``, ``motor_encoder_sign`` and ``scale_sign`` are applied by
:mod:`drivers.base`. A drive with position polarity set (0x607E bit 7) reverses motor torque and
motor position together, so it stays consistent in its own frame while the external scale now runs
against the motor: the host then reverses the scale (see :class:`Cia402Backend`).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import struct
import time
from collections.abc import Iterator, Mapping
from typing import Any

import can
import numpy as np
from canopen.emcy import EmcyError

from drivers.base import Backend, SampleBlock
from drivers.cia402 import profile as p402
from drivers.cia402.bus import bus_error_hint, error_code
from drivers.cia402.config import Cia402Config, answer_time, validate
from drivers.cia402.node import NodeSetup
from drivers.cia402.stream import ECHO, RpdoChannel, SampleAssembler, SyncSender, TorquePlan
from drivers.errors import (
    DeviceConnectionError,
    DeviceFault,
    DeviceTimeout,
    DriveNotReady,
    DriverError,
    HeartbeatLost,
    ProtocolError,
    RpdoTimeout,
)
from rt_ident.hostlock import NamedLock

log = logging.getLogger(__name__)

_TWO_PI = 2.0 * math.pi
_SDO_REREAD_S = 0.005       # between statusword reads by SDO after a disable written by SDO

#: the NMT states a heartbeat reports (CiA 301), other than OPERATIONAL (5) and the boot-up message (0)
NMT_STATES = {4: "STOPPED", 127: "PRE-OPERATIONAL"}


class Cia402Backend(Backend):
    """A CiA 402 drive streaming motor encoder, table scale and torque at the SYNC rate.

    The effective scale sign (``self.scale_sign`` once open) = configured ``scale_sign`` x (-1 if the
    drive's 0x607E bit 7 is set): the drive reverses motor torque and 0x6064 but not the table scale.
    ``torque_sign`` and ``motor_encoder_sign`` describe the wiring in the drive's own frame.
    """

    name = "canopen"

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg: Cia402Config = validate(config)
        super().__init__({"torque_limit": cfg.torque_limit, "torque_sign": cfg.torque_sign,
                          "motor_encoder_sign": cfg.motor_encoder_sign, "scale_sign": cfg.scale_sign})
        self.config = cfg
        self._setup: NodeSetup | None = None
        self._deque: collections.deque = collections.deque(maxlen=max(8192, int(8 * cfg.sync_rate_hz)))
        self._plan = TorquePlan()
        self._sender: SyncSender | None = None    # the bus's (shared with the other drives on it)
        self._channel: RpdoChannel | None = None  # this drive's RPDO in the sender's cycle
        # the outcome of a stop made over the SYNC (what was not confirmed, or None); after it the drive's
        # RPDO has left the cycle, and its answers can no longer be matched to SYNCs
        self._sync_stop: tuple[str | None] | None = None
        self._asm: SampleAssembler | None = None
        self.rated_torque = cfg.rated_torque or math.nan
        self._k0 = 0                  # SYNC index of seq 0
        self._t0 = 0.0
        self._next_seq = 0            # seq expected next (for the lost count)
        self._emcy: tuple[int, int] | None = None
        self._hb_time = 0.0           # monotonic time of the last heartbeat of the drive
        self._hb_state = 0
        self._hb_operational = False  # a heartbeat reported OPERATIONAL since NMT start was sent
        self._hb_not_operational = 0  # heartbeats not reporting OPERATIONAL after one that did
        self._hb_rebooted = False     # one of them a boot-up message
        self.warning_samples = 0      # samples whose statusword had its warning bit set
        self.limited_samples = 0      # ... its internal-limit bit: the drive cut the torque
        self._fault_code: int | None = None   # 0x603F read after the stop of a drive in FAULT that sent no EMCY
        self.statusword = 0
        self._ident: dict[str, Any] = {}
        # one master per drive on this host: a second program commanding the node would each send it torque
        kw = cfg.bus_kwargs()
        self._node_lock = NamedLock("can-node", f"{kw.get('interface')}:{kw.get('channel')}:{kw.get('port')}:"
                                                f"{cfg.node_id}")

    # ----- properties -------------------------------------------------------------------
    @property
    def sample_period(self) -> float:
        return self.config.sample_period

    @property
    def has_measured_torque(self) -> bool:
        return True

    @property
    def counters(self) -> dict[str, int]:
        """Stale/late/corrupt samples and frames, unchanged encoder samples, SYNC overruns, late plan values
        (late_torques: those that differed from the torque sent, so it landed a SYNC late), samples with the
        statusword's warning (bit 7) and internal limit (bit 11) set."""
        a, s = self._asm, self._sender
        io = self._setup.io if self._setup is not None else None
        return {"stale": a.stale if a else 0, "ambiguous": a.ambiguous if a else 0,
                "late": a.late if a else 0, "corrupt": a.corrupt if a else 0,
                "unchanged": a.unchanged if a else 0, "sync_sent": s.sent if s else 0,
                "sync_echoes": a.echoes if a else 0, "sync_overruns": s.overruns if s else 0,
                "send_errors": s.send_errors if s else 0, "late_plan_samples": self._plan.late,
                "late_torques": self._plan.late_changed, "warning": self.warning_samples,
                "internal_limit": self.limited_samples,
                "rx_dropped": io.dropped if io else 0,
                "max_latency_us": int(1e6 * a.max_latency) if a else 0}

    def read_phase(self) -> float | None:
        """The next SYNC's time plus the time its answers need (answer_time, every drive on the bus)."""
        s = self._sender
        if s is None or not s.running or s.next_at is None:
            return None
        return s.next_at - time.monotonic() + answer_time(self.config, s.channels)

    # ----- light callbacks (python-can's receive thread: no work, never raise) ----------
    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._deque.append((can_id, timestamp, bytes(data)))      # FrameIO: host monotonic arrival time

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._hb_time = time.monotonic()
        state = data[0] & 0x7F if data else 0
        self._hb_state = state
        if state == 5:
            self._hb_operational = True
            self._hb_not_operational = 0
        elif self._hb_operational:
            self._hb_not_operational += 1
            self._hb_rebooted |= state == 0

    def _on_sync_echo(self, timestamp: float, ordinal: int) -> None:
        self._deque.append((ECHO, timestamp, ordinal))

    def _on_emcy(self, entry: EmcyError) -> None:
        if entry.code & 0xFF00 and self._emcy is None:
            self._emcy = (entry.code, entry.register)

    # ----- unit conversions -------------------------------------------------------------
    def _torque_to_permille(self, torque: float) -> tuple[int, float]:
        pm = int(round(torque * 1000.0 / self.rated_torque))
        pm = max(-32768, min(32767, pm))
        return pm, pm * self.rated_torque / 1000.0

    # ----- lifecycle hooks --------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        if not self._node_lock.try_acquire():
            raise DeviceConnectionError(f"node {cfg.node_id} on {cfg.interface} {cfg.channel} is in use: "
                                        f"{self._node_lock.who()} is its master; let it end first (two masters "
                                        "would each send the drive torque)")
        try:
            self._connect()
        except BaseException:
            self._node_lock.release()
            raise

    def _connect(self) -> None:
        cfg = self.config
        setup = NodeSetup(cfg, on_tpdo=self._on_tpdo, on_heartbeat=self._on_heartbeat, on_emcy=self._on_emcy,
                          on_sync_echo=self._on_sync_echo)
        self._setup = setup
        try:
            with self._bus_errors("opening the drive"):
                setup.connect()
                self.rated_torque = setup.configure()
        except BaseException:
            setup.teardown(drive_consumer_off=False)
            self._setup = None
            raise
        self._ident = dict(setup.identity)
        polarity = self._ident.get("polarity") or 0         # absent (SDO abort): as 0
        self.scale_sign = cfg.scale_sign * (-1 if polarity & p402.POLARITY_POSITION else 1)
        if polarity & p402.POLARITY_POSITION:
            log.info("canopen: node %d has 0x607E = 0x%02X (position polarity: the drive reverses motor torque "
                     "and position); the table scale is reversed on the host (effective scale_sign %d)",
                     cfg.node_id, polarity, self.scale_sign)
        self._asm = SampleAssembler(setup.tpdo_layouts, cfg.stale_limit,
                                    cfg.stuck_torque * 1000.0 / self.rated_torque, echo=setup.echo,
                                    timed=setup.timed)
        self._hb_time = time.monotonic()

    def fault_detail(self) -> str:
        code = self._fault_code
        if not code:
            return ""
        return (f"; node {self.config.node_id}'s error code 0x603F, read after the stop: "
                f"{p402.emcy_text(code).removeprefix('EMCY ')} (no EMCY reached this host: the drive's 0x1014 may "
                f"have it off)")

    def _link_trouble(self) -> str:
        s, cfg = self._sender, self.config
        if s is None or not s.consecutive_errors:
            return ""
        return (f"; meanwhile the last {s.consecutive_errors} SYNC cycles failed to send on "
                f"{cfg.interface}:{cfg.channel} ({s.last_error}): the drive held its last torque up to its "
                f"RPDO deadline")

    @contextlib.contextmanager
    def _bus_errors(self, doing: str) -> Iterator[None]:
        """A python-can error while ``doing``: a one-line :class:`DeviceConnectionError` with what it means."""
        try:
            yield
        except can.CanError as exc:
            cfg = self.config
            hint = bus_error_hint(error_code(exc), cfg.interface, cfg.channel, cfg.bitrate)
            raise DeviceConnectionError(f"{doing} on CAN interface {cfg.interface}:{cfg.channel} failed: "
                                        f"{type(exc).__name__}: {exc}" + (f": {hint}" if hint else "")) from exc

    def _identity(self) -> dict[str, Any]:
        """0x1000 device type, 0x6502 supported drive modes, 0x6076 rated torque [N m], 0x6072 max torque
        [per mille], 0x607E polarity, node id; read by SDO during open (None: the drive lacks it, named
        in ``notes``)."""
        ident = dict(self._ident)
        ident["notes"] = list(ident.get("notes", []))
        return ident

    def _read_position(self) -> tuple[float, float]:
        """0x6064 and the table scale object, by SDO (the drive reports them whatever its state)."""
        cfg, setup = self.config, self._setup
        assert setup is not None
        counts = setup.upload(p402.POSITION_ACTUAL, 0, " (the motor position before enabling)")
        scale = setup.upload(cfg.scale_index, cfg.scale_subindex, " (the table position before enabling)")
        return counts * (_TWO_PI / cfg.counts_per_rev), scale * (cfg.scale_resolution / cfg.lead)

    def _activate(self) -> None:
        cfg, setup = self.config, self._setup
        assert setup is not None and setup.conn is not None and self._asm is not None
        self._plan.hold(0.0)
        channel = RpdoChannel(setup.rpdo_cob, self._plan, self._torque_to_permille, self._deque, p402.CW_SHUTDOWN)
        self._channel = channel
        self._sync_stop = None
        try:
            # Heartbeats sent before the drive saw NMT start may still be queued (python-can's cyclic
            # sender also sends missed heartbeats in a burst after a stall, e.g. while this process
            # was being locked in memory): only a heartbeat after one reporting OPERATIONAL counts.
            self._hb_operational = False
            self._hb_not_operational = 0
            self._hb_rebooted = False
            if setup.echo or setup.timed:   # bus order or bus times are in the frames: read them in this
                setup.receive_in_caller()      # thread, no receive thread competing for the GIL
            setup.nmt_operational()
            self._hb_time = time.monotonic()
            # one SYNC producer per bus: started by the first drive, joined by the others
            sender = self._sender = setup.conn.join_sync(channel, cfg.gil_switch_interval_us)
            self._asm.host_missed = lambda: sender.overruns
            with self._bus_errors("enabling the drive"):
                self._enable(sender)
        except BaseException:
            self._stop_drive()
            raise
        # samples from here on are delivered; seq 0 is the next SYNC
        self._asm.reset_counters()
        self._asm.take_rows()
        self._k0 = sender.next_index
        self._asm.first_k = self._k0
        self._next_seq = 0
        self._t0 = time.monotonic()

    def _enable(self, sender: SyncSender) -> None:
        """Walk the 402 state machine by controlword until the statusword says OPERATION ENABLED."""
        cfg, setup, asm, ch = self.config, self._setup, self._asm, self._channel
        assert setup is not None and asm is not None and ch is not None     # _activate made them
        deadline = time.monotonic() + cfg.startup_timeout
        resets, toggle_at = 0, 0.0
        hold = max(0.02, 10 * cfg.sample_period)    # each controlword long enough for several SYNCs
        while True:
            setup.pump()
            asm.feed(self._deque, deliver=False, read_until=setup.read_until)
            self._check_emcy_heartbeat(startup=True)
            sw = asm.statusword
            state = p402.decode_state(sw) if sw is not None else None
            if state == p402.OPERATION_ENABLED and self._hb_operational and sw is not None:
                self.statusword = sw
                log.info("canopen: node %d in OPERATION ENABLED (statusword 0x%04X)", cfg.node_id, sw)
                return
            if state == p402.FAULT:
                # fault reset = rising edge of bit 7: hold 0x80, then 0x00, each for `hold` seconds
                if time.monotonic() >= toggle_at:
                    toggle_at = time.monotonic() + hold
                    if ch.controlword & p402.CW_FAULT_RESET:
                        ch.controlword = p402.CW_DISABLE_VOLTAGE
                    else:
                        resets += 1
                        if resets > 3:
                            raise DeviceFault(f"node {cfg.node_id} stays in FAULT after {resets - 1} fault resets "
                                              f"(statusword 0x{sw:04X})")
                        log.warning("canopen: node %d in FAULT at start-up; sending fault reset", cfg.node_id)
                        ch.controlword = p402.CW_FAULT_RESET
            elif state is not None:
                ch.controlword = p402.next_controlword(state, ch.controlword)
            if time.monotonic() > deadline:
                if sw is None:
                    raise DeviceTimeout(
                        f"no TPDO from node {cfg.node_id} within startup_timeout {cfg.startup_timeout:g} s after "
                        f"NMT OPERATIONAL ({sender.sent} SYNCs sent, {asm.frames_seen} TPDO frames received)")
                if state == p402.OPERATION_ENABLED:
                    raise DeviceTimeout(
                        f"node {cfg.node_id} is in OPERATION ENABLED but its heartbeat did not report NMT "
                        f"OPERATIONAL within startup_timeout {cfg.startup_timeout:g} s (last state "
                        f"{self._hb_state})")
                blocker = p402.enable_blocker(sw)
                if blocker is not None:
                    raise DriveNotReady(f"node {cfg.node_id} does not enable: state {state} (statusword "
                                        f"0x{sw:04X}); {blocker[0]}", fix=blocker[1])
                raise DeviceTimeout(
                    f"node {cfg.node_id} did not reach OPERATION ENABLED within startup_timeout "
                    f"{cfg.startup_timeout:g} s: state {state} (statusword 0x{sw:04X})")
            time.sleep(cfg.sample_period)

    def _check_emcy_heartbeat(self, startup: bool = False) -> None:
        cfg = self.config
        if self._emcy is not None:
            code, reg = self._emcy
            fault = {p402.EMCY_RPDO_TIMEOUT: RpdoTimeout, p402.EMCY_HEARTBEAT: HeartbeatLost}.get(code, DeviceFault)
            raise fault(f"node {cfg.node_id} sent {p402.emcy_text(code)}, error register 0x{reg:02X}")
        io = self._setup.io if self._setup is not None else None
        if io is not None and io.dropped:       # the drive's heartbeats may be among them: no silence to judge
            raise ProtocolError(f"{io.dropped} frames dropped by this host's receive buffer on "
                                f"{cfg.interface}:{cfg.channel}; samples can no longer be matched to SYNCs")
        age = time.monotonic() - self._hb_time
        if age > cfg.consumer_ms / 1000.0:
            raise DeviceFault(f"no heartbeat from node {cfg.node_id} for {age:.3f} s (consumer time "
                              f"{cfg.consumer_ms} ms, producer {cfg.heartbeat_ms} ms)")
        if not startup and self._hb_not_operational:
            raise DeviceFault(f"node {cfg.node_id} left NMT OPERATIONAL: " + (
                "it sent a boot-up message, so it restarted (its logic supply dipped, its own watchdog, or an "
                "NMT reset from another master on the bus)" if self._hb_rebooted else
                f"its heartbeat reports {NMT_STATES.get(self._hb_state, f'state {self._hb_state}')} (an NMT "
                "command from another master on the bus, or the drive's own error behaviour, 0x1029)"))
        s = self._sender
        if s is not None and s.consecutive_errors >= 10:
            hint = bus_error_hint(s.last_errno, cfg.interface, cfg.channel, cfg.bitrate)
            raise DeviceConnectionError(f"CAN send failing on {cfg.interface}:{cfg.channel}: {s.last_error} "
                                        f"({s.send_errors} errors)" + (f": {hint}" if hint else ""))

    def _read(self) -> SampleBlock:
        asm, setup = self._asm, self._setup
        assert asm is not None and setup is not None      # opened
        setup.pump()
        self._check_emcy_heartbeat()
        asm.feed(self._deque, deliver=True, read_until=setup.read_until)
        rows = asm.take_rows()
        n = len(rows["k"])
        if n == 0:
            return SampleBlock.empty(with_measured=True)
        sw = rows["sw"]
        flags = 0
        for word in sw:
            if p402.decode_state(word) != p402.OPERATION_ENABLED:
                self.statusword = word
                raise DeviceFault(f"node {self.config.node_id} left OPERATION ENABLED: state "
                                  f"{p402.decode_state(word)} (statusword 0x{word:04X})")
            flags |= word
        if flags & (p402.SW_WARNING | p402.SW_INTERNAL_LIMIT):
            self.warning_samples += sum(1 for word in sw if word & p402.SW_WARNING)
            self.limited_samples += sum(1 for word in sw if word & p402.SW_INTERNAL_LIMIT)
        self.statusword = sw[-1]
        cfg = self.config
        seq = np.asarray(rows["k"], dtype=np.int64) - self._k0
        lost = int(seq[-1] - self._next_seq + 1 - n)
        self._next_seq = int(seq[-1]) + 1
        theta1 = np.asarray(rows["pos"], dtype=float) * (_TWO_PI / cfg.counts_per_rev)
        theta2 = np.asarray(rows["scale"], dtype=float) * (cfg.scale_resolution / cfg.lead)
        tq = np.asarray(rows["tq"], dtype=float) * (self.rated_torque / 1000.0)
        t = np.asarray(rows["t"]) - self._t0
        return SampleBlock(t, seq, theta1, theta2, np.asarray(rows["cmd"], dtype=float), tq, lost=max(lost, 0))

    def _write_hold(self, torque: float) -> None:
        self._plan.hold(torque)

    def _write_plan(self, torques: np.ndarray, start_seq: int) -> None:
        self._plan.plan(torques, start_seq + self._k0)

    def _write_leased_plan(self, torques: np.ndarray, start_seq: int, lease: int) -> None:
        self._plan.plan(torques, start_seq + self._k0, lease)

    def _wait_state(self, accept: tuple[str, ...], timeout: float) -> bool:
        """Poll the TPDO stream (not delivering samples) until the drive reports one of ``accept``."""
        end = time.monotonic() + timeout
        asm, setup = self._asm, self._setup
        assert asm is not None and setup is not None      # opened
        while True:
            try:
                setup.pump()
                asm.feed(self._deque, deliver=False, read_until=setup.read_until)
            except DriverError:
                pass
            sw = asm.statusword
            if sw is not None and p402.decode_state(sw) in accept:
                self.statusword = sw
                return True
            if time.monotonic() > end:
                return False
            time.sleep(self.config.sample_period)

    def _stop_drive(self) -> str | None:
        """Quick stop, torque 0, disable voltage, stop SYNC. Bounded in time; never raises. Returns what the
        drive did not confirm (None: disabled, or never enabled by this host)."""
        cfg, sender, ch = self.config, self._sender, self._channel
        self._plan.hold(0.0)
        if sender is None or ch is None:          # never activated: the drive was not enabled by us
            return None
        if self._sync_stop is not None and self._sync_stop[0] is None:
            return None                           # stopped and confirmed before (a failed enable, then the run's stop)
        if not sender.running or self._sync_stop is not None:
            if self._sdo_disable():
                return None
            return f"the drive did not acknowledge the disable written by SDO (no SYNC cycle left to send it in); " \
                   f"{self._on_its_own()}"
        unconfirmed = None
        try:
            asm = self._asm
            if asm is not None:
                asm.statusword = None   # only answers to the stop commands count
            ch.controlword = p402.CW_QUICK_STOP
            if not self._wait_state((p402.QUICK_STOP_ACTIVE, p402.SWITCH_ON_DISABLED, p402.FAULT),
                                    cfg.stop_timeout):
                log.warning("canopen: node %d did not confirm quick stop within %.3f s",
                            cfg.node_id, cfg.stop_timeout)
            ch.controlword = p402.CW_DISABLE_VOLTAGE
            if not self._wait_state((p402.SWITCH_ON_DISABLED, p402.FAULT), cfg.stop_timeout):
                unconfirmed = (f"node {cfg.node_id} did not report itself disabled within {cfg.stop_timeout:g} s; "
                               f"{self._on_its_own()}")
        finally:
            self._leave_sync()
            if self._setup is not None:
                self._setup.receive_in_thread()     # SDO (close) needs a receiver again
            if self._setup is not None and self._emcy is None and p402.decode_state(self.statusword) == p402.FAULT:
                self._fault_code = self._setup.try_upload(p402.ERROR_CODE, 0)
            if unconfirmed is not None and self._sdo_confirms_disabled():
                log.warning("canopen: node %d sent no PDO after the disable; its statusword read by SDO "
                            "confirms it", cfg.node_id)
                unconfirmed = None
            self._deque.clear()
            self._sync_stop = (unconfirmed,)
        return unconfirmed

    def _sdo_confirms_disabled(self) -> bool:
        """Whether the statusword read by SDO shows the power stage off. A drive that left NMT OPERATIONAL (a
        restart, another master's NMT command) sends no PDO but answers SDO in PRE-OPERATIONAL. One still
        enabled is sent the disable by SDO and read again for up to stop_timeout: a drive acts on a
        controlword in its own cycle, after it has answered the write. A drive that does not answer costs
        one sdo_timeout."""
        setup = self._setup
        if setup is None:
            return False
        sent_at = None
        while True:
            sw = setup.try_upload(p402.STATUSWORD, 0)
            if sw is None:
                return False
            if p402.decode_state(sw) in (p402.SWITCH_ON_DISABLED, p402.NOT_READY, p402.FAULT):
                self.statusword = sw
                return True
            if sent_at is None:
                if not setup.try_download(p402.CONTROLWORD, 0, struct.pack("<H", p402.CW_DISABLE_VOLTAGE)):
                    return False
                sent_at = time.monotonic()
            elif time.monotonic() - sent_at > self.config.stop_timeout:
                return False
            else:
                time.sleep(_SDO_REREAD_S)

    def _on_its_own(self) -> str:
        """What this drive does by itself once the host falls silent, as this host set it up."""
        deadline = self._setup.rpdo_deadline_ms if self._setup is not None else None
        watch = f"at its heartbeat consumer time ({self.config.consumer_ms} ms without this host's heartbeat, " \
                "left on for that reason)"
        if deadline:
            return f"the drive faults at its RPDO deadline ({deadline} ms without a torque write) or {watch}"
        return f"the drive faults {watch}"

    def _leave_sync(self) -> None:
        """This drive's RPDO out of the SYNC cycle (the last drive's leave stops the SYNC)."""
        if self._setup is not None and self._setup.conn is not None and self._channel is not None:
            self._setup.conn.leave_sync(self._channel)

    def _sdo_disable(self) -> bool:
        """Without a running SYNC stream, write the controlword by SDO (best effort). True: the drive took it."""
        if self._setup is None:
            return False
        self._leave_sync()
        self._setup.receive_in_thread()     # SDO needs a receiver
        return self._setup.try_download(p402.CONTROLWORD, 0, struct.pack("<H", p402.CW_DISABLE_VOLTAGE))

    def _safe_stop(self) -> str | None:
        return self._stop_drive()

    def _close(self) -> None:
        self._leave_sync()
        if self._setup is not None:
            # a drive that did not confirm its disable keeps watching this host's heartbeat, which stops now
            self._setup.teardown(drive_consumer_off=self.stop_unconfirmed is None)
            self._setup = None
        self._node_lock.release()


__all__ = ["Cia402Backend"]

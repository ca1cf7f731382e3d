"""An emulated CiA 402 servo drive on a python-can bus, built on ``canopen.LocalNode``.

The drive answers SDO and NMT through ``LocalNode``; everything ``LocalNode`` does
not do is done here: the 402 power state machine driven by the controlword, PDOs as
CiA 301 transmits them (below), the heartbeat consumer (loss of the master's heartbeat
-> fault, torque 0, EMCY 0x8130) and EMCY on faults.

PDO transmission types (0x14xx:02 / 0x18xx:02, CiA 301), in NMT OPERATIONAL only:
RPDOs 0-240 are applied at the next SYNC, 254/255 on receipt (a controlword steps the
state machine at once, as does one written by SDO). TPDO 0 is sent at the SYNC after its data changed, 1-240 at every
n-th SYNC, 254/255 when its data change, not sooner than the inhibit time (0x18xx:03)
after the previous one and at the latest the event timer (0x18xx:05) after it (checked
with the housekeeping, every 2 ms or when due). Out of the box (the EDS) TPDO1 is the
statusword and RPDO1 the controlword, both event-driven (255), as drives ship; a master
maps and sets transmission types itself. The SYNC counter (0x1019 = 2..240, set only while
0x1006 is 0): every SYNC then carries a counter byte, a TPDO of type 1-240 with a start value
(0x18xx:06) first goes out at the SYNC whose counter equals it; a SYNC of the wrong length is
ignored (EMCY 0x8240, once until a right one comes).
On each SYNC in NMT OPERATIONAL the plant (:class:`rt_ident.axis.plant.PlantSimulator`)
advances one sample with the last target torque if OPERATION ENABLED, else with zero. When the
SYNCs stop (a stalled master), time does not: the next SYNC, or a fault (the heartbeat consumer's),
first runs the plant through the silence with the torque in force, as a real drive holds its last
target torque while the table moves on (``silent_samples`` counts those samples). Time the emulator
itself was not run (a paused VM: the master paused with it) is no silence: the emulated world stood
still (``paused_s``). A silence is counted in the SYNC period the master set (0x1006, else 0x60C2).
RPDO deadline monitoring (CiA 301: an RPDO's event timer 0x14xx:05, in ms, from its first reception
on): an RPDO not received within it while OPERATION ENABLED is a fault (EMCY 0x8250, torque 0 from
that instant; the table coasts on). Checked on each RPDO's arrival, and by the housekeeping up to
where the receive thread has read the bus.
TPDOs carry the measurement taken at that SYNC (the plant measures at the start of
the sample) and the torque applied from that SYNC on.

Threads: the receive thread (:class:`drivers.cia402.frames.FrameIO`) runs the SDO
server, stores RPDO data and does the per-SYNC work (like a drive's SYNC interrupt: the
shortest answer latency); housekeeping (delayed frames, heartbeat watch) runs every 2 ms,
in a worker thread or - when the receive thread polls - between its polls. One lock
guards the state. On ``udp_multicast`` the receive thread polls every ``poll_s`` (100 us)
instead of blocking: see :class:`~drivers.cia402.frames.FrameIO`.

Synchronous window (CiA 301): TPDOs answering a SYNC are sent only if no later SYNC
was read with it - a late answer would land in the next SYNC's window and be taken
for that sample. The plant still advances; the master sees a stale sample
(:attr:`late_syncs` counts them).

The device as it truly is: the plant carries the true lead and the true encoder resolutions
(``counts_per_rev``, ``scale_resolution`` here); ``torque_sign`` (motor wired the other way),
``torque_scale`` (a wrong torque constant: physical torque per torque the drive believes it applies),
``motor_encoder_sign`` (0x6064 counts the other way) and ``scale_sign`` (the scale object counts the
other way) act between the drive and the plant. 0x6077 reports the torque the drive believes it
applies. Position polarity (0x607E bit 7) reverses the applied torque, 0x6064 and 0x6077 inside the
drive, not the scale. The travel window (fault 0x8612), the hold loop and ``x0`` act on the true axis.

Works on the ``virtual`` bus (in-process) and ``udp_multicast`` (across processes;
needs msgpack). CLI: ``python -m drivers.cia402.emulator --config configs/canopen-virtual.toml``;
:class:`rt_ident.processes.emulation.EmulatorProcess` runs it in a child process.
"""

from __future__ import annotations

import collections
import heapq
import logging
import math
import random
import struct
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import canopen
import numpy as np
from canopen.sdo import SdoAbortedError

from drivers.cia402 import profile as p402
from drivers.cia402.bus import open_bus
from drivers.cia402.faults import FaultConfig
from drivers.cia402.frames import FrameIO, stop_periodic
from drivers.cia402.local_pdo import PdoLayout, check_mapping_write, od_value, pdo_layouts
from drivers.cia402.variants import INTERPOLATION_PERIOD, PARAMETER_ERROR, DriveProfile, drive_profile
from rt_ident.axis.plant import PlantSimulator
from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)

_QUICK_STOP_OPTION = 0x605A
SYNC_LENGTH = 0x8240           # EMCY: unexpected SYNC data length
_ANSWER_BINS_US = (100, 200, 300, 500, 1000, 2000, float("inf"))   # upper edges of the answer-time bins
_PROCESS = (p402.CONTROLWORD, p402.TARGET_TORQUE, p402.MAX_TORQUE, p402.MODES_OF_OPERATION, 0x60B2,
            _QUICK_STOP_OPTION, p402.POLARITY)
_POWERED = (p402.OPERATION_ENABLED, p402.QUICK_STOP_ACTIVE)


def _count(hist: list[int], seconds: float) -> None:
    us = 1e6 * seconds
    hist[next(i for i, edge in enumerate(_ANSWER_BINS_US) if us < edge)] += 1


def _int32(v: int) -> int:
    return ((v + 0x80000000) & 0xFFFFFFFF) - 0x80000000


def _int8(v: int) -> int:
    return ((v + 0x80) & 0xFF) - 0x80


def _int16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))


#: the longest silence of a master the table is stepped through [s]
SILENCE_MAX_S = 1.0
#: the emulator itself not run for this long (its housekeeping runs every 2 ms): it was paused with its host
OWN_PAUSE_S = 0.010


class EmulatedCia402Drive:
    """A CiA 402 drive in cyclic synchronous torque mode around a simulated axis.

    ``bus``: ``can.Bus`` keyword arguments (``interface``, ``channel``, ``bitrate``, ``port``...).
    ``poll_s``: receive-thread poll period (:class:`~drivers.cia402.frames.FrameIO`); ``"auto"``:
    100 us on ``udp_multicast``, blocking otherwise.
    Constructing does no I/O; :meth:`start` goes on the bus, :meth:`stop` leaves it
    (also a context manager). For tests: :attr:`state` (402 state name),
    :attr:`applied_torque` [N m], :attr:`enabled`, :attr:`samples` (SYNCs in OPERATION ENABLED),
    :attr:`emcy_codes` (EMCYs sent).

    ``counts_per_rev``, ``scale_resolution``, ``rated_torque`` (0x6076): the drive's true values;
    ``torque_sign``, ``motor_encoder_sign``, ``scale_sign`` (+-1), ``torque_scale`` (> 0): how the
    motor and the encoders are truly wired (see the module docstring); ``polarity``: 0x607E at power-up
    (0: the profile's); ``profile``: the vendor variant (:mod:`drivers.cia402.variants`);
    ``run_through_silence``: False steps the table on SYNCs only (a silent master freezes it).
    """

    def __init__(self, node_id: int, eds_path: str | Path, bus: Mapping[str, Any], plant: PlantSimulator,
                 faults: FaultConfig | None = None, *, counts_per_rev: int = 2**17,
                 scale_resolution: float = 1e-7, scale_index: int = 0x60E4, scale_subindex: int = 1,
                 rated_torque: float | None = None, poll_s: float | None | Literal["auto"] = "auto",
                 torque_sign: int = 1, motor_encoder_sign: int = 1, scale_sign: int = 1, torque_scale: float = 1.0,
                 polarity: int = 0, profile: str | DriveProfile = "generic",
                 run_through_silence: bool = True, serial_number: int | None = None) -> None:
        if not 1 <= int(node_id) <= 127:
            raise ValueError(f"node_id must be 1..127, got {node_id!r}")
        self.node_id = int(node_id)
        self.eds_path = Path(eds_path)
        self.bus_kwargs = dict(bus)
        self.plant = plant
        self.faults = faults if faults is not None else FaultConfig()
        self.counts_per_rev = int(counts_per_rev)
        self.scale_resolution = float(scale_resolution)
        self.scale_key = (int(scale_index), int(scale_subindex))
        for name, sign in (("torque_sign", torque_sign), ("motor_encoder_sign", motor_encoder_sign),
                           ("scale_sign", scale_sign)):
            if isinstance(sign, bool) or sign not in (1, -1):
                raise ValueError(f"{name} must be 1 or -1, got {sign!r}")
        if not (isinstance(torque_scale, (int, float)) and math.isfinite(torque_scale) and torque_scale > 0):
            raise ValueError(f"torque_scale must be > 0, got {torque_scale!r}")
        if not 0 <= int(polarity) <= 255:
            raise ValueError(f"polarity (0x607E, UNSIGNED8) must be 0..255, got {polarity!r}")
        self.torque_sign, self.motor_encoder_sign, self.scale_sign = int(torque_sign), int(motor_encoder_sign), \
            int(scale_sign)
        self.torque_scale = float(torque_scale)
        self.profile = drive_profile(profile)
        self._polarity0 = int(polarity) or (self.profile.polarity or 0)
        self._rated_override = rated_torque
        self._serial_number = serial_number
        self.rated_torque = rated_torque or 0.0
        self._controller = plant.controller
        # receive thread: poll on udp_multicast (another process: keep its vCPU awake), block in-process
        if poll_s == "auto":
            poll_s = 1e-4 if self.bus_kwargs.get("interface") == "udp_multicast" else None
        self.poll_s: float | None = poll_s
        self._io: FrameIO | None = None
        self._in_window = True        # the SYNC being handled is the last one read (its answer is on time)
        self._pending: collections.deque = collections.deque()   # frames read, not yet handled
        self._next_housekeeping = 0.0
        self._net: canopen.Network | None = None
        self._node: canopen.LocalNode | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rng = random.Random(self.faults.seed)
        # drive state (guarded by _lock: the receive thread and the worker both touch it)
        self._state = p402.NOT_READY
        self._prev_cw = 0
        self._values: dict[tuple[int, int], int] = {}
        self._rpdo_data: dict[int, bytes] = {}
        self._rpdos: list[PdoLayout] = []
        self._tpdos: list[PdoLayout] = []
        self._pdo_dirty = True
        self._rpdo_by_cob: dict[int, PdoLayout] = {}
        self._tpdo_sent: dict[int, bytes] = {}       # TPDO COB-ID -> data last sent (types 0, 254, 255)
        self._tpdo_sent_t: dict[int, float] = {}     # TPDO COB-ID -> when (inhibit time, event timer)
        self._event_due = math.inf                   # next inhibit / event timer expiry
        self._syncs = 0
        self._sync_overflow = 0                      # 0x1019: 0 no counter in the SYNC, else 2..240
        self._sync_counter = 0                       # the counter the SYNC being handled carried
        self._sync_bad = False                       # SYNCs of the wrong length since the last good one
        self._tpdo_started: dict[int, int] = {}      # TPDO COB-ID -> the SYNC it started at (0x18xx:06)
        self._qs_samples = 0
        self._limited = False                        # the torque in force was cut at a limit (statusword bit 11)
        self._delayed: list[tuple[float, int, int, bytes]] = []
        self._delay_n = 0
        self._stuck_counts: int | None = None
        self._t_enabled: float | None = None
        self._hb_stopped = False
        self._master: tuple[int, int] = (0, 0)    # (node id, consumer time ms)
        self._master_hb: float | None = None
        self._master_lost = False
        self.applied_torque = 0.0
        self.samples = 0
        self.emcy_codes: list[int] = []
        self.frames_sent = 0
        self.garbage_frames = 0
        self.rpdo_length_errors = 0
        self.sync_length_errors = 0   # SYNCs ignored: a counter where 0x1019 is 0, or none where it is set
        self.late_syncs = 0           # SYNCs answered by no TPDO: a later SYNC had already arrived
        self._sync_t = 0.0            # arrival time of the SYNC being handled
        self._sync_period: float | None = None   # the SYNC period the master set (0x1006 or 0x60C2) [s]
        self._ip = [0, 0]                        # 0x60C2 as written: period value, index (power of ten)
        self._plant_wall: float | None = None    # monotonic time the plant has been advanced to
        self.silent_samples = 0       # samples the plant ran with no SYNC (a stalled master)
        self.run_through_silence = bool(run_through_silence)   # False: the table steps on SYNCs only
        self.longest_silence_s = 0.0             # the longest interval between two SYNCs [s]
        self.paused_s = 0.0                      # time the emulator itself was not run (not the master's silence)
        self._alive_t: float | None = None       # when the emulator last ran (housekeeping, SYNC, RPDO)
        self._rpdo_t: float | None = None        # arrival of the newest RPDO with a deadline (monotonic)
        self._deadline_s = 0.0                   # the shortest RPDO deadline (0x14xx:05) set, 0: none
        self._last_sample = (0.0, 0.0, 0.0, 0.0)   # the plant's newest (theta1, theta2, applied, measured)
        self.answer_us = [0] * len(_ANSWER_BINS_US)   # SYNC arrival -> TPDOs sent, histogram
        self.pickup_us = [0] * len(_ANSWER_BINS_US)   # SYNC arrival -> its handling starts, histogram

    # ----- public view ------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @property
    def enabled(self) -> bool:
        return self._state == p402.OPERATION_ENABLED

    @property
    def polarity_sign(self) -> int:
        """-1 while position polarity (0x607E bit 7) reverses the torque at the motor and 0x6064."""
        return self._position_polarity()

    @property
    def nmt_state(self) -> str:
        return self._node.nmt.state if self._node is not None else "INITIALISING"

    def stats(self) -> dict[str, Any]:
        """State and counters for a report: 402 state, applied torque, samples, late SYNCs, answer times
        (SYNC arrival -> TPDOs sent)."""
        edges = [f"<{e:g}us" for e in _ANSWER_BINS_US[:-1]] + [f">={_ANSWER_BINS_US[-2]:g}us"]
        with self._lock:
            return {"state": self._state, "enabled": self.enabled, "applied_torque": self.applied_torque,
                    "nmt_state": self.nmt_state, "samples": self.samples, "syncs": self._syncs,
                    "late_syncs": self.late_syncs, "silent_samples": self.silent_samples,
                    "longest_silence_s": self.longest_silence_s, "paused_s": self.paused_s,
                    "frames_sent": self.frames_sent,
                    "emcy_codes": list(self.emcy_codes), "pickup_time": dict(zip(edges, self.pickup_us)),
                    "answer_time": dict(zip(edges, self.answer_us))}

    # ----- lifecycle --------------------------------------------------------------------
    def start(self) -> EmulatedCia402Drive:
        if self._net is not None:
            return self
        self._warm_plant()
        od = canopen.import_od(str(self.eds_path), self.node_id)
        self.profile.apply(od)                            # the vendor's variant of the EDS's drive
        bus = open_bus(self.bus_kwargs)
        net = canopen.Network(bus)
        node = canopen.LocalNode(self.node_id, od)
        if self._rated_override:
            node.data_store.setdefault(p402.RATED_TORQUE, {})[0] = struct.pack(
                "<I", int(round(self._rated_override * 1000)))
        self.rated_torque = od_value(node, p402.RATED_TORQUE) / 1000.0
        self._supported = od_value(node, p402.SUPPORTED_MODES)
        for key in ((p402.MAX_TORQUE, 0), (p402.MODES_OF_OPERATION, 0), (_QUICK_STOP_OPTION, 0)):
            self._values[key] = od_value(node, *key)
        if od.get_variable(p402.SYNC_OVERFLOW) is not None:
            self._sync_overflow = self.profile.sync_overflow
            self._values[(p402.SYNC_OVERFLOW, 0)] = self._sync_overflow
        if self._serial_number is not None:
            self._values[(p402.IDENTITY, 4)] = self._serial_number
        if od.get_variable(p402.POLARITY) is not None:
            self._values[(p402.POLARITY, 0)] = self._polarity0
        elif self._polarity0:
            raise ConfigError("emulator.polarity", f"0x{self._polarity0:02X} set, but the drive's EDS "
                              f"{self.eds_path.name} (profile {self.profile.name}) has no 0x607E")
        counts, scale = self._encoders(float(self.plant.state[0]), float(self.plant.state[2]))
        self._values.update({(p402.CONTROLWORD, 0): 0, (p402.TARGET_TORQUE, 0): 0, (0x60B2, 0): 0,
                             (p402.MODES_DISPLAY, 0): 0, (p402.ERROR_CODE, 0): 0, (p402.ERROR_REGISTER, 0): 0,
                             (p402.POSITION_ACTUAL, 0): counts, (p402.TORQUE_ACTUAL, 0): 0,
                             self.scale_key: scale})      # the encoders read from power-up on
        node.add_write_callback(self._on_write)
        node.add_read_callback(self._on_read)
        self._node = node
        self._net = net
        net.add_node(node)
        polling = self.poll_s is not None            # then the receive thread also does the housekeeping
        self._io = FrameIO(bus, self._on_frames, bus_kwargs=self.bus_kwargs, poll_s=self.poll_s,
                           send_lock=net.send_lock, name=f"emulated-drive-rx-{self.node_id}",
                           on_idle=self._idle if polling else None)
        net.subscribe(0x80, self._on_sync)
        self._rebuild_pdos()                              # RPDOs heard from now on
        self._set_state(p402.SWITCH_ON_DISABLED)          # transition 1 after initialisation
        self._stop.clear()
        self._io.start()
        if not polling:
            self._thread = threading.Thread(target=self._run, name=f"emulated-drive-{self.node_id}",
                                            daemon=True)
            self._thread.start()
        node.nmt.send_command(0x81)                       # reset: boot-up message
        node.nmt.send_command(0x80)                       # PRE-OPERATIONAL
        log.info("emulated drive: node %d on %s", self.node_id, self.bus_kwargs)
        return self

    def stop(self) -> None:
        """Leave the bus: worker stopped, heartbeat off, network down, torque 0, disabled. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
            self._thread = None
        net, node, io = self._net, self._node, self._io
        if net is not None:
            try:
                assert node is not None and io is not None    # started with the network
                task = getattr(node.nmt, "_send_task", None)
                node.nmt.stop_heartbeat()
                stop_periodic(task)
                io.close()                                # no more callbacks after this
                net.disconnect()
            except Exception as exc:  # noqa: BLE001
                log.warning("emulated drive: disconnect failed: %s", exc)
            self._net = None
        with self._lock:
            self.applied_torque = 0.0
            if self._state in (p402.OPERATION_ENABLED, p402.QUICK_STOP_ACTIVE, p402.SWITCHED_ON):
                self._set_state(p402.SWITCH_ON_DISABLED)

    def __enter__(self) -> EmulatedCia402Drive:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # ----- object dictionary ------------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od: Any) -> int | None:
        return self._values.get((index, subindex))

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        """SDO writes (receive thread): refuse bad PDO mappings, track process values."""
        with self._lock:
            self._written(index, subindex, od.decode_raw(data))
            if 0x1400 <= index < 0x1C00:             # stored now (LocalNode stores after the callbacks): a
                assert self._node is not None        # rebuild by the housekeeping thread must see it
                self._node.data_store.setdefault(index, {})[subindex] = bytes(data)

    def _written(self, index: int, subindex: int, value: int) -> None:
        if index == p402.POLARITY and self._state in _POWERED:
            raise SdoAbortedError(0x08000022)       # as drives do: polarity only with the power stage off
        if 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00:
            assert self._node is not None            # SDO writes come after start()
            check_mapping_write(self._node, index, subindex, value)
        if 0x1400 <= index < 0x1C00:
            self._pdo_dirty = True
        elif index == p402.SYNC_OVERFLOW:
            if value == 1 or value > 240:
                raise SdoAbortedError(0x06090030)   # CiA 301: 0, or 2..240
            assert self._node is not None
            if self._node.object_dictionary.get_variable(p402.CYCLE_PERIOD) is not None and \
                    od_value(self._node, p402.CYCLE_PERIOD):
                raise SdoAbortedError(0x08000022)   # CiA 301: only while 0x1006 is 0
            self._values[(index, 0)] = self._sync_overflow = value
            self._tpdo_started.clear()
        elif index == INTERPOLATION_PERIOD and subindex == 2 and not -6 <= _int8(value) <= 0:
            raise SdoAbortedError(0x06090030)       # a time index this drive does not take (1 us .. 1 s)
        elif index == p402.CYCLE_PERIOD:
            self._sync_period = 1e-6 * value if value else None
        elif index == INTERPOLATION_PERIOD and subindex in (1, 2):
            self._ip[subindex - 1] = value if subindex == 1 else _int8(value)
            if self._ip[0] and (self._sync_period is None or not self._cycle_set_directly()):
                self._sync_period = self._ip[0] * 10.0 ** self._ip[1]
        elif index == p402.MODES_OF_OPERATION:
            self._values[(index, 0)] = value
            bit = p402.MODE_BITS.get(value)
            if bit is not None and self._supported >> bit & 1:
                self._values[(p402.MODES_DISPLAY, 0)] = value
            else:
                log.warning("emulated drive: mode %d not supported (0x6502 = 0x%08X); display unchanged",
                            value, self._supported)
        elif index == p402.CONSUMER_HEARTBEAT and subindex == 1:
            self._set_consumer((value >> 16) & 0x7F, value & 0xFFFF)
        elif index in _PROCESS:
            self._values[(index, subindex)] = value
            if index == p402.CONTROLWORD:           # acted on in the drive's own cycle, SYNC or not
                self._step_state_machine(value, sample=False)
                self._event_tpdos()

    def _set_consumer(self, master_id: int, ms: int) -> None:
        old, net = self._master[0], self._net
        assert net is not None                       # an SDO write: on the bus
        if old and old != master_id:
            try:
                net.unsubscribe(0x700 + old, self._on_master_heartbeat)
            except (KeyError, ValueError):
                pass
        self._master = (master_id, ms)
        self._master_hb = None
        if master_id and ms:
            net.subscribe(0x700 + master_id, self._on_master_heartbeat)

    def _rebuild_pdos(self) -> None:
        node, net = self._node, self._net
        assert node is not None and net is not None   # on the bus
        rpdos, tpdos = pdo_layouts(node)
        for lay in self._rpdos:
            net.unsubscribe(lay.cob, self._on_rpdo)
        for lay in rpdos:
            net.subscribe(lay.cob, self._on_rpdo)
        self._rpdos, self._tpdos = rpdos, tpdos
        self._rpdo_by_cob = {lay.cob: lay for lay in rpdos}
        deadlines = [lay.event_s for lay in rpdos if lay.event_s > 0.0]
        self._deadline_s = min(deadlines) if deadlines else 0.0
        self._rpdo_t = None                               # monitoring starts at the next reception
        self._tpdo_sent.clear()                           # a changed PDO set: event TPDOs go out afresh
        self._tpdo_started.clear()
        self._tpdo_sent_t.clear()
        self._pdo_dirty = False

    # ----- receive-thread callbacks (light) ---------------------------------------------
    def _on_frames(self, frames: list) -> None:
        """Frames read in one go, in bus order; a SYNC followed by another one is answered late."""
        net, pending = self._net, self._pending
        assert net is not None                       # FrameIO delivers between start() and stop()
        notify = net.notify
        pending.extend(frames)
        while pending:
            cob, data, t = pending.popleft()
            if cob == 0x80:
                self._in_window = not any(f[0] == 0x80 for f in pending)
            notify(cob, data, t)

    def _still_in_window(self) -> bool:
        """Last look before answering a SYNC: has the next one arrived meanwhile? (receive thread only)"""
        if not self._in_window:
            return False
        assert self._io is not None                  # the receive thread asks: started
        new = self._io.read_now()
        self._pending.extend(new)
        self._in_window = not any(f[0] == 0x80 for f in new)
        return self._in_window

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != (1 if self._sync_overflow else 0):
            self._sync_length_error(len(data))            # as drives do: not a SYNC this drive acts on
            return
        self._sync_bad = False
        self._sync_counter = data[0] if data else 0
        self._sync_t = timestamp
        _count(self.pickup_us, time.monotonic() - timestamp)
        with self._lock:
            try:
                self._on_sync_work()
            except Exception:  # noqa: BLE001 - an emulator must survive its own bugs, visibly
                log.exception("emulated drive: SYNC processing failed")

    def _sync_length_error(self, n: int) -> None:
        """A SYNC of the wrong length (CiA 301: one data byte, the counter, where 0x1019 is set; none
        where it is 0): ignored, and EMCY 0x8240 once until a SYNC of the right length comes."""
        self.sync_length_errors += 1
        if self._sync_bad:
            return
        self._sync_bad = True
        log.warning("emulated drive %d: SYNC with %d data bytes ignored (0x1019 = %d)", self.node_id, n,
                    self._sync_overflow)
        self.emcy_codes.append(SYNC_LENGTH)
        try:
            assert self._node is not None
            self._node.emcy.send(SYNC_LENGTH, 0x10)      # error register: communication error
        except Exception as exc:  # noqa: BLE001 - the bus may be closing
            log.warning("emulated drive: EMCY send failed: %s", exc)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        lay = self._rpdo_by_cob.get(can_id)
        if lay is not None and lay.event_s > 0.0:
            with self._lock:
                self._note_alive(time.monotonic())
                self._check_deadline(timestamp, "next RPDO")   # the silence before this one, if too long
                self._rpdo_t = timestamp
        if lay is None or lay.trans_type <= 240:          # synchronous: applied at the next SYNC
            self._rpdo_data[can_id] = bytes(data)
            return
        with self._lock:                                  # event-driven (254/255): applied on receipt
            assert self._node is not None                 # subscribed while on the bus
            if self._node.nmt.state != "OPERATIONAL":
                return
            if len(data) != lay.struct.size:
                self.rpdo_length_errors += 1
                return
            v = self._values
            for key, value in zip(lay.keys, lay.struct.unpack(data)):
                v[key] = value
            if (p402.CONTROLWORD, 0) in lay.keys:
                self._step_state_machine(v[(p402.CONTROLWORD, 0)], sample=False)
            self._event_tpdos()

    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._master_hb = time.monotonic()

    # ----- worker -----------------------------------------------------------------------
    def _idle(self) -> None:
        """Housekeeping from the polling receive thread: every 2 ms, or when a delayed frame is due."""
        now = time.monotonic()
        if now < self._next_housekeeping and now < self._event_due and not (
                self._delayed and self._delayed[0][0] <= now):
            return
        self._next_housekeeping = now + 0.002
        with self._lock:
            self._housekeeping()

    def _run(self) -> None:
        while not self._stop.is_set():
            timeout = 0.002
            with self._lock:
                if self._delayed:
                    timeout = min(timeout, max(0.0, self._delayed[0][0] - time.monotonic()))
                timeout = min(timeout, max(0.0, self._event_due - time.monotonic()))
            if self._stop.wait(timeout):
                break
            with self._lock:
                try:
                    self._housekeeping()
                except Exception:  # noqa: BLE001
                    log.exception("emulated drive: housekeeping failed")

    def _set_state(self, state: str) -> None:
        if state != self._state:
            log.debug("emulated drive %d: %s -> %s", self.node_id, self._state, state)
            if self._state == p402.FAULT and self._node is not None:
                self._values[(p402.ERROR_CODE, 0)] = 0
                self._values[(p402.ERROR_REGISTER, 0)] = 0
                self._node.emcy.reset()
            if state == p402.QUICK_STOP_ACTIVE:
                self._qs_samples = 0
            if state == p402.OPERATION_ENABLED and self._t_enabled is None:
                self._t_enabled = time.monotonic()
            self._state = state
        sw = p402.STATUSWORD_OF[state]
        if self.faults.main_power_off:
            sw &= ~p402.SW_VOLTAGE_ENABLED
        if self.faults.local_control:
            sw &= ~p402.SW_REMOTE
        if state == p402.OPERATION_ENABLED and self._limited:
            sw |= p402.SW_INTERNAL_LIMIT
        warn = self.faults.warning_at_sample
        if warn is not None and self.samples >= warn:
            sw |= p402.SW_WARNING
        self._values[(p402.STATUSWORD, 0)] = sw
        if state != p402.OPERATION_ENABLED:
            self.applied_torque = 0.0

    def _fault(self, code: int, reason: str, at: float | None = None) -> None:
        """Into FAULT (torque off) with EMCY ``code``; the plant first runs through a silence of the master
        up to ``at`` (default now) with the torque in force until then."""
        if self._state == p402.FAULT:
            return
        self._run_through_silence(time.monotonic() if at is None else at)
        st, lead = self.plant.state, self.plant.params.lead
        log.warning("emulated drive %d: fault %s: %s (table at x = %.3f mm, %.1f mm/s)", self.node_id,
                    p402.emcy_text(code), reason, 1e3 * lead * st[2], 1e3 * lead * st[3])
        register = 0x01 | (0x10 if code & 0xFF00 == 0x8100 else 0x02 if code & 0xF000 == 0x2000 else 0)
        self._values[(p402.ERROR_CODE, 0)] = code
        self._values[(p402.ERROR_REGISTER, 0)] = register
        self._set_state(p402.FAULT)
        self.emcy_codes.append(code)
        if self.faults.emcy_off:
            return
        try:
            assert self._node is not None            # a fault is raised only while on the bus
            self._node.emcy.send(code, register)
        except Exception as exc:  # noqa: BLE001
            log.warning("emulated drive: EMCY send failed: %s", exc)

    def _restart(self, sample: int) -> None:
        """A restart (fault injection): the power stage off, then NMT as at power-up, the boot-up message
        and PRE-OPERATIONAL (no PDOs until a master starts the node again)."""
        node = self._node
        assert node is not None                      # SYNCs arrive after start()
        log.warning("emulated drive %d: restarting at sample %d (fault injection)", self.node_id, sample)
        self._set_state(p402.SWITCH_ON_DISABLED)
        node.nmt.send_command(0x81)                  # reset: boot-up message
        node.nmt.send_command(0x80)

    def _housekeeping(self) -> None:
        node = self._node
        assert node is not None                      # the worker runs after start()
        now = time.monotonic()
        self._note_alive(now)
        while self._delayed and self._delayed[0][0] <= now:
            _, _, cob, data = heapq.heappop(self._delayed)
            self._send(cob, data)
        # a silence is known only as far as the receive thread has read the bus: frames that arrived on
        # time but wait in this process's socket (its receive thread starved) are not a silence
        heard = min(now, self._io.read_until) if self._io is not None else now
        master, ms = self._master
        if master and ms and self._master_hb is not None and not self._master_lost:
            if heard - self._master_hb > ms / 1000.0:
                self._master_lost = True
                self._fault(0x8130, f"no heartbeat from node {master} for {heard - self._master_hb:.3f} s")
        elif self._master_lost and self._master_hb is not None and now - self._master_hb < ms / 1000.0:
            self._master_lost = False
        self._check_deadline(heard)
        f = self.faults
        if (f.heartbeat_stop_at_s is not None and not self._hb_stopped and self._t_enabled is not None
                and now - self._t_enabled >= f.heartbeat_stop_at_s):
            self._hb_stopped = True
            node.nmt.stop_heartbeat()
            log.warning("emulated drive %d: heartbeat stopped (fault injection)", self.node_id)
        if node.nmt.state != "OPERATIONAL" and self._state in (
                p402.OPERATION_ENABLED, p402.QUICK_STOP_ACTIVE, p402.SWITCHED_ON):
            self._set_state(p402.SWITCH_ON_DISABLED)      # communication ended: power stage off
        if self._pdo_dirty:
            self._rebuild_pdos()
        self._event_tpdos()

    def _event_tpdos(self) -> None:
        """Send the event-driven TPDOs (254/255, CiA 301) that are due: data changed and the inhibit time
        (0x18xx:03) since the last one over, or the event timer (0x18xx:05) expired. Only in OPERATIONAL;
        entering it sends each once. PDO parameters written since the last look take effect first, as a
        drive applies them when written (an inhibit time just set holds for the next change already)."""
        node = self._node
        assert node is not None                      # on the bus
        if self._pdo_dirty:
            self._rebuild_pdos()
        if node.nmt.state != "OPERATIONAL":
            self._tpdo_sent.clear()
            self._tpdo_sent_t.clear()
            self._event_due = math.inf
            return
        now, v, due = time.monotonic(), self._values, math.inf
        for lay in self._tpdos:
            if lay.trans_type < 254:
                continue
            data = lay.struct.pack(*(v.get(k, 0) for k in lay.keys))
            last = self._tpdo_sent_t.get(lay.cob)
            timer_due = last + lay.event_s if last is not None and lay.event_s > 0 else math.inf
            if self._tpdo_sent.get(lay.cob) == data and now < timer_due:
                due = min(due, timer_due)
                continue
            if last is not None and now < last + lay.inhibit_s:
                due = min(due, last + lay.inhibit_s)     # changed, but inhibited: sent when it ends
                continue
            self._send(lay.cob, data)
            sent = time.monotonic()                  # the timers run from the frame on the bus, not from `now`
            self._tpdo_sent[lay.cob], self._tpdo_sent_t[lay.cob] = data, sent
            if lay.event_s > 0:
                due = min(due, sent + lay.event_s)
        self._event_due = due

    def _on_sync_work(self) -> None:
        assert self._node is not None                # SYNCs arrive after start()
        if self._node.nmt.state != "OPERATIONAL":
            return
        if self._pdo_dirty:
            self._rebuild_pdos()
        self._syncs += 1
        self._note_alive(time.monotonic())
        self._note_sync_time(self._sync_t or time.monotonic())    # when it came, not when it was handled
        v = self._values
        for lay in self._rpdos:                           # synchronous RPDOs take effect now
            data = self._rpdo_data.pop(lay.cob, None)
            if data is None:
                continue
            if len(data) != lay.struct.size:
                self.rpdo_length_errors += 1
                continue
            for key, value in zip(lay.keys, lay.struct.unpack(data)):
                v[key] = value
        self._step_state_machine(v[(p402.CONTROLWORD, 0)])
        enabled, torque = self._torque_in_force()
        if enabled:
            self.samples += 1
        gain = self._torque_gain()
        self._use_controller(enabled)
        self._step(np.array([gain * torque]))
        theta1, theta2, applied, meas = self._last_sample
        self.applied_torque = applied if enabled else 0.0
        counts, scale = self._encoders(theta1, theta2)
        f, n = self.faults, self.samples
        if f.stuck_encoder_at_sample is not None and n >= f.stuck_encoder_at_sample:
            if self._stuck_counts is None:
                self._stuck_counts = v[(p402.POSITION_ACTUAL, 0)]
            counts = self._stuck_counts
        v[(p402.POSITION_ACTUAL, 0)] = counts
        v[self.scale_key] = scale
        meas = meas / gain if enabled else 0.0                          # 0x6077: the believed torque
        v[(p402.TORQUE_ACTUAL, 0)] = _int16(meas * 1000.0 / self.rated_torque)
        if enabled and f.emcy_at_sample is not None and n == f.emcy_at_sample:
            self._fault(f.emcy_code, f"injected at sample {n}")
        if enabled and f.restart_at_sample is not None and n == f.restart_at_sample:
            self._restart(n)
            return
        if enabled and self.plant.travel_exceeded:
            self._fault(0x8612, "table outside its travel")
        self._set_state(self._state)                      # refresh the statusword
        self._send_tpdos(enabled, n)
        self._event_tpdos()

    def _note_alive(self, now: float) -> None:
        """The emulator runs at ``now``. Not run for longer than OWN_PAUSE_S before: it was paused itself (a
        paused VM, a starved process), and the emulated world with it - a drive has a processor of its own.
        That time is taken out of the master's silence and the RPDO deadline (``paused_s`` counts it)."""
        last, self._alive_t = self._alive_t, now
        if last is None or now - last <= OWN_PAUSE_S:
            return
        gap = now - last
        self.paused_s += gap
        if self._plant_wall is not None:
            self._plant_wall += gap
        if self._rpdo_t is not None:
            self._rpdo_t += gap

    def _check_deadline(self, now: float, seen_by: str = "housekeeping") -> None:
        """An RPDO deadline passed by ``now`` while OPERATION ENABLED: the plant first runs through the
        silence with the torque held up to the deadline, then the fault (the torque off from there on).
        ``seen_by`` goes into the fault's text (which check found the silence)."""
        d, t = self._deadline_s, self._rpdo_t
        if not d or t is None or now - t <= d or self._state != p402.OPERATION_ENABLED:
            return
        self._fault(p402.EMCY_RPDO_TIMEOUT, f"no RPDO for {1e3 * (now - t):.0f} ms (deadline 0x1400:05 = "
                                            f"{1e3 * d:.0f} ms; seen by the {seen_by})", at=t + d)

    def _torque_in_force(self) -> tuple[bool, float]:
        """(enabled, the torque the drive believes it applies [N m], its own frame): the last target torque
        plus the offset 0x60B2 within 0x6072 (and an injected derating) while OPERATION ENABLED, else 0."""
        if self._state != p402.OPERATION_ENABLED:
            self._limited = False
            return False, 0.0
        v, f = self._values, self.faults
        limit = v[(p402.MAX_TORQUE, 0)]
        if f.derate_at_sample is not None and self.samples >= f.derate_at_sample:
            limit = min(limit, f.derate_permille)
        want = v[(p402.TARGET_TORQUE, 0)] + v[(0x60B2, 0)]
        permille = max(-limit, min(limit, want))
        self._limited = permille != want
        return True, permille * self.rated_torque / 1000.0

    def _step(self, torques: np.ndarray) -> None:
        blk = self.plant.step_block(torques)
        self._last_sample = (float(blk.theta1[-1]), float(blk.theta2[-1]), float(blk.torque_applied[-1]),
                             float(blk.torque_meas[-1]))

    def _cycle_set_directly(self) -> bool:
        """0x1006 holds a period (it takes precedence over 0x60C2)."""
        node = self._node
        return node is not None and node.object_dictionary.get_variable(p402.CYCLE_PERIOD) is not None and \
            bool(od_value(node, p402.CYCLE_PERIOD))

    def _note_sync_time(self, t: float) -> None:
        """A SYNC that came at ``t``: the plant first runs through the time since the last one beyond
        this SYNC's own sample (a master that went silent), counted in the SYNC period the master set (no
        period set: nothing is run through). By arrival times: SYNCs that waited in this drive's queue are
        no silence."""
        last = self._plant_wall
        if last is not None and self._syncs > 1:
            self.longest_silence_s = max(self.longest_silence_s, t - last)
        self._run_through_silence(t, pending=1)
        self._plant_wall = t if self._plant_wall is None else max(t, self._plant_wall)

    def _run_through_silence(self, now: float, pending: int = 0) -> None:
        """The plant advances through the samples since the last SYNC up to ``now`` (less the ``pending``
        ones a SYNC steps itself) with the torque in force then, when they are two or more: a drive
        holds its last target torque while its master is silent, and the table moves on."""
        p, last = self._sync_period, self._plant_wall
        if p is None or last is None or self._node is None or self._node.nmt.state != "OPERATIONAL" or \
                not self.run_through_silence:
            return
        k = int((now - last) / p + 0.5) - pending
        if k < 2:
            return
        enabled, torque = self._torque_in_force()
        k = min(k, int(SILENCE_MAX_S / p))   # a deadline or the heartbeat consumer has ended it long before
        self._use_controller(enabled)
        self._step(np.full(k, self._torque_gain() * torque) if enabled else np.zeros(k))   # disabled: it coasts
        self.applied_torque = self._last_sample[2] if enabled else 0.0
        self._plant_wall = max(last + k * p, now - p)
        self.silent_samples += k

    def _position_polarity(self) -> int:
        """-1 while 0x607E bit 7 (position polarity) is set. Bit 6 (velocity polarity) is stored only:
        it reverses velocity values, and cyclic synchronous torque has none."""
        return -1 if self._values.get((p402.POLARITY, 0), 0) & p402.POLARITY_POSITION else 1

    def _torque_gain(self) -> float:
        """Physical motor torque per N m the drive believes it applies (in its own frame): position
        polarity, the motor's wiring and the torque constant's error."""
        return self._position_polarity() * self.torque_sign * self.torque_scale

    def _encoders(self, theta1: float, theta2: float) -> tuple[int, int]:
        """The motor encoder's counts and the table scale's steps (0x6064 and the scale object) at the
        quantized true angles the plant's sensors report: 0x6064 with the encoder's wiring and the
        drive's position polarity, the scale with its own wiring only (0x607E does not act on it)."""
        counts = int(math.floor(theta1 * self.counts_per_rev / (2.0 * math.pi) + 0.5))
        counts *= self._position_polarity() * self.motor_encoder_sign
        x = theta2 * self.plant.params.lead
        steps = self.scale_sign * int(math.floor(x / self.scale_resolution + 0.5))
        return _int32(counts), _int32(steps)

    def _step_state_machine(self, controlword: int, sample: bool = True) -> None:
        """``sample``: called at a SYNC (a quick stop ends after two); else on an event-driven RPDO."""
        state = self._state
        if state == p402.QUICK_STOP_ACTIVE and sample:
            self._qs_samples += 1
            if self._qs_samples > 1 and self._values[(_QUICK_STOP_OPTION, 0)] in (0, 1, 2, 3, 4):
                state = p402.SWITCH_ON_DISABLED           # 12: quick stop done (torque already 0)
        if self.faults.local_control:           # the bus's controlword is not obeyed
            self._prev_cw = controlword
            if state != self._state:
                self._set_state(state)
            return
        new = p402.drive_transition(state, controlword, self._prev_cw, self._values[(_QUICK_STOP_OPTION, 0)])
        self._prev_cw = controlword
        if self.faults.main_power_off and new in (p402.SWITCHED_ON, p402.OPERATION_ENABLED):
            new = state                          # no voltage at the power stage: it does not switch on
        if new == p402.OPERATION_ENABLED and state != new and not self._cycle_time_set():
            self._fault(PARAMETER_ERROR, "cyclic synchronous mode without an interpolation time period (0x60C2)")
            return
        self._set_state(new)

    def _cycle_time_set(self) -> bool:
        """False for a drive that needs 0x60C2 for a cyclic synchronous mode and has 0 in it."""
        if not self.profile.interpolation_period or self._values.get((p402.MODES_DISPLAY, 0)) not in (8, 9, 10):
            return True
        assert self._node is not None                # the state machine steps while on the bus
        return od_value(self._node, INTERPOLATION_PERIOD, 1) != 0

    def _use_controller(self, enabled: bool) -> None:
        """The drive's own position loop (if the plant has one) runs only when enabled."""
        want = self._controller if enabled else None
        if self.plant.controller is not want:
            self.plant = self._plant_with(want)

    def _plant_with(self, controller: Any) -> PlantSimulator:
        """The plant as it is now (state, parameters, sensors), with ``controller`` as its hold loop."""
        p = self.plant
        return PlantSimulator(p.params, p.dt, sensors=p.sensors, controller=controller,
                              torque_limit=p.torque_limit, travel=p.travel, integrator=p.integrator,
                              seed=p.seed + p.sample_index, x0=p.state, friction=p.friction)

    def _warm_plant(self) -> None:
        """Step a copy of the plant one sample before going on the bus: the first call of each compiled
        kernel a SYNC runs loads or compiles it (milliseconds), and that SYNC would go unanswered.
        The axis itself does not move. A silent master's samples (several at once) are warmed too."""
        for controller in {id(c): c for c in (self.plant.controller, self._controller)}.values():
            for n in (1, 3):
                self._plant_with(controller).step_block(np.zeros(n))

    def _send_tpdos(self, enabled: bool, n: int) -> None:
        f, v = self.faults, self._values
        frames, acyclic = [], []
        for lay in self._tpdos:                           # 0: at the SYNC after a change; n: every n-th SYNC
            if lay.trans_type > 240 or (lay.trans_type and self._sync_skip(lay)):
                continue
            data = lay.struct.pack(*(v.get(k, 0) for k in lay.keys))
            if lay.trans_type == 0:
                if self._tpdo_sent.get(lay.cob) == data:
                    continue
                acyclic.append((lay.cob, data))
            frames.append((lay.cob, data))
        if not self._still_in_window():                   # outside the synchronous window: not sent
            self.late_syncs += 1
            return
        self._tpdo_sent.update(acyclic)
        frames = f.tpdo_frames(frames, n, enabled)
        delay = f.tpdo_delay(n, enabled)
        if delay > 0:
            for cob, data in frames:
                self._delay_n += 1
                heapq.heappush(self._delayed, (time.monotonic() + delay, self._delay_n, cob, data))
        else:
            for cob, data in frames:
                self._send(cob, data)
            _count(self.answer_us, time.monotonic() - self._sync_t)
        for cob, data in f.garbage(self._rng):
            self._send(cob, data)
            self.garbage_frames += 1

    def _sync_skip(self, lay: PdoLayout) -> bool:
        """A TPDO of type 1..240 is not due at this SYNC. With the SYNC counter on and a start value
        (0x18xx:06) it starts at the SYNC whose counter equals it, then every n-th SYNC."""
        since = self._syncs
        if self._sync_overflow and lay.sync_start:
            began = self._tpdo_started.get(lay.cob)
            if began is None:
                if self._sync_counter != lay.sync_start:
                    return True
                began = self._tpdo_started[lay.cob] = self._syncs
            since = self._syncs - began
        return bool(since % lay.trans_type)

    def _send(self, cob: int, data: bytes) -> None:
        try:
            assert self._io is not None              # on the bus
            self._io.send(cob, data)
            self.frames_sent += 1
        except Exception as exc:  # noqa: BLE001 - the bus may be closing
            log.debug("emulated drive: send 0x%03X failed: %s", cob, exc)


__all__ = ["EmulatedCia402Drive"]

"""An emulated serial encoder board on a pseudo-terminal, with fault injection.

The board end of ``docs/serial-protocol.md``: a thread wakes every
``burst_period`` (1 ms), emits the data frames due at ``sample_rate_hz`` since
the last burst (about 20), stepping :class:`rt_ident.axis.plant.PlantSimulator` with
the commanded torque (zero when disabled), and parses the host's frames. The
host opens :attr:`EmulatedBoard.port` (the pty slave) like a real device.

Faults (set on :attr:`EmulatedBoard.faults` while running, or one-shot methods):
dropped frames, corrupted bytes (CRC errors), garbage bytes, delayed frames
(:meth:`delay`), a stuck motor encoder, board silence and host-heartbeat loss
(``deaf``: host frames are ignored, so the board's watchdog disables it and
zeroes the torque).

The device may differ from what the host is told (``[emulator] actual``,
:class:`~drivers.encoder_board.config.BoardTruth`): a motor wired the other way, encoders counting the
other way or at another resolution, another screw lead, another torque per commanded N m. The board
reports what it believes it drives (the command, the current); the plant, its travel and ``x0`` are the
true ones. The board answers INFO_REQUEST with :meth:`EmulatedBoard.info`.

``python -m drivers.encoder_board.emulator`` prints the pty path and runs until Ctrl-C.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drivers.encoder_board import protocol as sp
from drivers.encoder_board.config import (
    MAX_CURRENT_A,
    EmulatorConfig,
    SerialBoardConfig,
    parse_emulator,
    parse_serial,
)
from rt_ident.axis.friction import Friction
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig, rest_at

log = logging.getLogger(__name__)

MODEL = "emulated-board"       # what the emulated board's INFO frame says it is
FIRMWARE = (1, 0, 0)
#: the board's loop not run for this many bursts: it was paused with its host (a starved process, a paused
#: VM), which a real board, on a processor of its own, never is; that time is no silence of the host
OWN_PAUSE_BURSTS = 10


@dataclass
class Faults:
    """Continuous fault settings (mutable on purpose: tests change them while the board runs)."""

    drop_probability: float = 0.0     # per frame: not sent (seq still advances -> host sees a gap)
    corrupt_probability: float = 0.0  # per frame: one payload byte flipped (a CRC error)
    garbage_probability: float = 0.0  # per frame: 1..garbage_max random bytes sent before it
    garbage_max: int = 16
    stuck_encoder: bool = False       # motor counts frozen at their value when this was set
    silent: bool = False              # board -> host link down: nothing is sent
    deaf: bool = False                # host -> board link down: host frames (and heartbeats) lost


class EmulatedBoard:
    """The board: plant + protocol + pty. Construct (no I/O), :meth:`start`, :meth:`stop`.

    Observable state for tests: :attr:`enabled`, :attr:`applied_torque` (the
    command in force on the last sample, 0 when disabled), :attr:`motor_torque`,
    :attr:`status`, and counters (``frames_sent``, ``frames_dropped``,
    ``frames_corrupted``, ``garbage_sent``, ``tx_overflow_frames``,
    ``host_frames``, ``plan_late_samples``, ``ignored_commands``).

    The keyword arguments are the device as the host is told (its ``[backend]``: resolutions, polarity;
    ``params``: the plant and its lead); ``emulator.actual`` overrides them with the truth.
    """

    def __init__(self, params: AxisParams | None = None, *, sample_rate_hz: float = 20000.0,
                 counts_per_rev: int = 2**17, scale_resolution: float = 1e-7,
                 torque_constant: float = 0.1, torque_limit: float = 1.0,
                 torque_sign: int = 1, motor_encoder_sign: int = 1, scale_sign: int = 1,
                 emulator: EmulatorConfig | None = None, plan_capacity: int = 4096,
                 clock: Callable[[], float] = time.monotonic, friction: Friction | None = None) -> None:
        self.cfg = emulator if emulator is not None else EmulatorConfig()
        a = self.cfg.actual
        params = params if params is not None else thomson_x()
        self.params = params if a.lead is None else replace(params, lead=a.lead)   # the true plant
        self.friction = friction          # friction to ground / backlash of the plant (rt_ident.axis.friction)
        self.sample_rate_hz = float(sample_rate_hz)
        self.dt = 1.0 / self.sample_rate_hz
        # the truth: what the encoders count, which way the motor turns, its torque per N m the board drives
        self.counts_per_rev = int(a.counts_per_rev or counts_per_rev)
        self.scale_resolution = float(a.scale_resolution or scale_resolution)
        self.torque_sign = a.torque_sign or torque_sign
        self.motor_encoder_sign = a.motor_encoder_sign or motor_encoder_sign
        self.scale_sign = a.scale_sign or scale_sign
        self.torque_scale = float(a.torque_scale or 1.0)
        self.sensors = SensorConfig(counts_per_rev=self.counts_per_rev, scale_resolution=self.scale_resolution,
                                    angle_noise=self.cfg.angle_noise,
                                    torque_meas_noise=self.cfg.torque_meas_noise,
                                    torque_process_noise=self.cfg.torque_process_noise)
        self.torque_constant = float(torque_constant)
        self.torque_limit = float(torque_limit)
        self.plan_capacity = int(plan_capacity)
        self.clock = clock
        self.paused_s = 0.0            # time the board's own loop was not run (not counted as the host's silence)
        c = self.cfg
        self.faults = Faults(c.drop_probability, c.corrupt_probability, c.garbage_probability,
                             16, c.stuck_encoder, c.silent, c.deaf)
        self._rng = np.random.default_rng(c.seed + 7919)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self.port: str | None = None
        # board state
        self.enabled = False
        self.applied_torque = 0.0
        self.motor_torque = 0.0
        self.status = 0
        self._latched = 0
        self._hold = 0.0
        self._plan_start = 0
        self._plan: np.ndarray | None = None
        self._k = 0                      # samples produced (wire seq = seq0 + k)
        self._rebuilds = 0
        self._plant = self._make_plant(controller=None, x0=rest_at(self.cfg.x0, self.params.lead))
        self._last_theta1 = 0.0
        self._stuck_counts: int | None = None
        self._decoder = sp.FrameDecoder()
        self._out = bytearray()          # the board's transmit FIFO
        self._transit = bytearray()      # bytes past the FIFO: held up by delay(), or made in a pause of this loop
        self._delay_until = -math.inf
        self._drop_next = self._corrupt_next = 0
        self._garbage_next = b""
        self._last_host = 0.0
        self._rx_idle = 0
        self._plan_late_flag = False
        self._overflowed = False
        self.frames_sent = self.frames_dropped = self.frames_corrupted = 0
        self.garbage_sent = self.tx_overflow_frames = self.host_frames = 0
        self.plan_late_samples = self.ignored_commands = 0
        self.tx_buffer = c.tx_buffer     # bytes the board queues before dropping whole frames
        self.tx_refused_longest_s = 0.0  # longest time the pty took no byte of what the board had to send
        self._refused_since: float | None = None
        self.cpu_seconds = 0.0           # CPU time used by the board thread (emulation cost)

    # ----- lifecycle ---------------------------------------------------------------------
    def start(self) -> EmulatedBoard:
        """Open the pty (raw, slave kept open) and start streaming."""
        if self._thread is not None:
            return self
        self._plant.step_block(np.empty(0))     # load the compiled plant kernel now, not at the first frame
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)                 # raw before anything is written
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="emulated-board", daemon=True)
        self._thread.start()
        log.info("emulated board on %s at %.0f Hz", self.port, self.sample_rate_hz)
        return self

    def stop(self) -> None:
        """Stop the thread and close the pty. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def __enter__(self) -> EmulatedBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> dict[str, Any]:
        """State and counters for a report (what the emulator process sends its parent at close)."""
        with self._lock:
            return {"enabled": self.enabled, "applied_torque": self.applied_torque, "status": self.status,
                    "samples": self._k, "frames_sent": self.frames_sent, "frames_dropped": self.frames_dropped,
                    "frames_corrupted": self.frames_corrupted, "host_frames": self.host_frames,
                    "tx_overflow_frames": self.tx_overflow_frames, "paused_s": self.paused_s,
                    "tx_refused_longest_s": max(self.tx_refused_longest_s, 0.0 if self._refused_since is None
                                                else self.clock() - self._refused_since),
                    "queued_bytes": len(self._out) + len(self._transit)}

    # ----- one-shot faults -----------------------------------------------------------------
    def drop_next(self, n: int) -> None:
        """Do not send the next ``n`` frames (their sequence numbers are skipped)."""
        with self._lock:
            self._drop_next += int(n)

    def corrupt_next(self, n: int) -> None:
        """Flip one payload byte in each of the next ``n`` frames sent."""
        with self._lock:
            self._corrupt_next += int(n)

    def inject_garbage(self, data: bytes | int) -> None:
        """Send these bytes (or that many random bytes) before the next frame."""
        if isinstance(data, int):
            data = self._rng.integers(0, 256, data, dtype=np.uint8).tobytes()
        with self._lock:
            self._garbage_next += bytes(data)

    def delay(self, seconds: float) -> None:
        """Hold all output for ``seconds`` (frames keep being produced and queue up)."""
        with self._lock:
            self._delay_until = self.clock() + float(seconds)

    # ----- the board loop -------------------------------------------------------------------
    def _make_plant(self, controller: HoldController | None, x0: np.ndarray | None) -> PlantSimulator:
        self._rebuilds += 1
        # a disabled power stage applies nothing: no process noise either
        sensors = self.sensors if self.enabled else replace(self.sensors, torque_process_noise=0.0)
        # the plant saturates the physical torque: the board's limit as the motor truly delivers it
        return PlantSimulator(self.params, self.dt, sensors=sensors, controller=controller,
                              torque_limit=self.torque_limit * self.torque_scale, travel=self.cfg.travel,
                              seed=self.cfg.seed * 1000 + self._rebuilds, x0=x0, friction=self.friction)

    def _set_enabled(self, on: bool) -> None:
        """Power stage on/off. The drive's hold loop (``hold``) only acts while enabled."""
        self.enabled = on
        self._hold = 0.0
        self._plan = None
        ctrl = HoldController(reference=self._last_theta1) if (on and self.cfg.hold) else None
        self._plant = self._make_plant(ctrl, self._plant.state)

    def _run(self) -> None:
        try:
            origin = self.clock()
            self._last_host = origin
            next_wake = prev = origin
            while not self._stop.is_set():
                now = self.clock()
                paused = now - prev > OWN_PAUSE_BURSTS * self.cfg.burst_period
                if paused:
                    self.paused_s += now - prev
                    self._last_host += now - prev
                prev = now
                self._service_host(now)
                due = int((now - origin) * self.sample_rate_hz) - self._k
                if due > 0:
                    self._produce(due, sent_meanwhile=paused)
                self._flush(now)
                self.cpu_seconds = time.thread_time()
                next_wake += self.cfg.burst_period
                if next_wake < now - 10 * self.cfg.burst_period:   # starved: do not try to catch up
                    next_wake = now
                self._stop.wait(max(0.0, next_wake - self.clock()))
        except Exception:  # noqa: BLE001 - a dying board thread must say why
            log.exception("emulated board thread failed")
            self.enabled = False
            self.applied_torque = 0.0

    def _service_host(self, now: float) -> None:
        data = bytearray()
        while True:
            try:
                chunk = os.read(self._master, 65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            if not chunk:
                break
            data += chunk
        if self.faults.deaf:
            data = bytearray()
        # a partial frame with no further byte for two bursts is final (an inter-frame timeout)
        self._rx_idle = 0 if data else self._rx_idle + 1
        frames = self._decoder.feed(bytes(data)) if data else (
            self._decoder.flush() if self._rx_idle >= 2 and self._decoder.buffered else [])
        for frame in frames:
            self._handle(frame)
            self._last_host = now
        if self.enabled and now - self._last_host > self.cfg.heartbeat_timeout:
            log.warning("emulated board: no host frame for %.3f s: disabling", now - self._last_host)
            self._set_enabled(False)
            self._latched |= sp.ST_FAULT | sp.ST_HEARTBEAT_LOST

    def _handle(self, frame: sp.Frame) -> None:
        self.host_frames += 1
        if isinstance(frame, sp.Enable):
            self._latched = 0
            if not self.enabled:
                self._set_enabled(True)
        elif isinstance(frame, sp.Disable):
            if self.enabled:
                self._set_enabled(False)
        elif isinstance(frame, sp.QuickStop):
            if self.enabled:
                self._set_enabled(False)
            self._latched |= sp.ST_QUICK_STOPPED
        elif isinstance(frame, sp.InfoRequest):
            if self.cfg.answer_info and not self.faults.silent:
                self._out += self.info().encode()      # ahead of this burst's data frames
        elif isinstance(frame, (sp.TorqueHold, sp.TorquePlan)):
            if not self.enabled:
                self.ignored_commands += 1
            elif isinstance(frame, sp.TorqueHold):
                self._hold = float(frame.torque)
                self._plan = None
            else:
                self._merge_plan(frame)

    def _merge_plan(self, frame: sp.TorquePlan) -> None:
        """Queue a plan frame: it replaces every queued value for samples >= its start."""
        nxt = self.cfg.seq0 + self._k                       # next sample to be produced
        d = (frame.start_seq - nxt) & 0xFFFFFFFF            # uint32 start -> int32 distance
        start = nxt + (d - (1 << 32) if d >= (1 << 31) else d)
        vals = np.asarray(frame.torques, dtype=float)
        late = min(max(0, nxt - start), vals.size)
        if late:
            self.plan_late_samples += late
            self._plan_late_flag = True
        if self._plan is not None and start > self._plan_start:
            keep = self._plan[:start - self._plan_start]
            gap = start - self._plan_start - keep.size       # the new plan starts after the old one ends
            vals = np.concatenate([keep, np.full(gap, keep[-1]), vals])
            start = self._plan_start
        if start < nxt:                                      # drop what is already past
            if nxt - start >= vals.size:
                self._hold, self._plan = float(vals[-1]), None
                return
            vals, start = vals[nxt - start:], nxt
        self._plan, self._plan_start = vals[:self.plan_capacity], start

    def info(self) -> sp.Info:
        """The INFO frame: what the board is configured for (its encoders as they truly are)."""
        return sp.Info(sp.PROTOCOL_VERSION, FIRMWARE, self.cfg.serial_number, MODEL, self.sample_rate_hz,
                       min(self.torque_limit / self.torque_constant, MAX_CURRENT_A), self.torque_constant,
                       self.counts_per_rev, self.scale_resolution)

    def _commands(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Torque in force for the next n samples and a per-sample plan-active mask."""
        cmd = np.full(n, self._hold)
        active = np.zeros(n, dtype=bool)
        if self.enabled and self._plan is not None:
            k0 = self.cfg.seq0 + self._k
            a = max(0, self._plan_start - k0)                # first sample of the block in the plan
            if a < n:
                lo = k0 + a - self._plan_start                # its index in the plan
                take = self._plan[lo:lo + n - a]
                cmd[a:a + take.size] = take
                active[a:a + take.size] = True
                rest = self._plan[lo + take.size:]
                if rest.size == 0:                            # plan finished: hold its last value
                    self._hold = float(self._plan[-1])
                    cmd[a + take.size:] = self._hold
                    self._plan = None
                else:
                    self._plan, self._plan_start = rest, k0 + n
        if not self.enabled:
            cmd[:] = 0.0
        return cmd, active

    def _produce(self, n: int, sent_meanwhile: bool = False) -> None:
        """The next ``n`` samples, encoded and queued. ``sent_meanwhile``: they fell due while this loop was
        not run, a pause a board with a processor of its own never takes; it would have sent them during it."""
        cmd, plan_active = self._commands(n)
        lim = self.torque_limit
        limited = np.abs(cmd) > lim
        cmd = np.clip(cmd, -lim, lim)
        gain = self.torque_sign * self.torque_scale      # physical torque per N m the board believes it drives
        blk = self._plant.step_block(cmd if gain == 1.0 else gain * cmd)
        q1 = self.sensors.theta1_quantum
        enc = np.rint(blk.theta1 / q1).astype(np.int64)
        scale = np.rint(blk.theta2 * self.params.lead / self.sensors.scale_resolution).astype(np.int64)
        if self.motor_encoder_sign != 1:
            enc = -enc
        if self.scale_sign != 1:
            scale = -scale
        self._last_theta1 = float(blk.theta1[-1])
        if self.faults.stuck_encoder:
            if self._stuck_counts is None:
                self._stuck_counts = int(enc[0])
            enc[:] = self._stuck_counts
        else:
            self._stuck_counts = None
        meas = blk.torque_meas        # the current the board believes it drives (+ its measurement noise)
        if gain != 1.0:
            meas = blk.torque_applied / gain + (blk.torque_meas - blk.torque_applied)
        current = np.clip(np.rint(meas / self.torque_constant * 1000.0), -32768, 32767)
        status = np.full(n, self._latched | (sp.ST_ENABLED if self.enabled else 0), dtype=np.uint16)
        status[limited] |= sp.ST_TORQUE_LIMITED
        status[plan_active] |= sp.ST_PLAN_ACTIVE
        if self._plan_late_flag:
            status[0] |= sp.ST_PLAN_LATE
            self._plan_late_flag = False
        if self._overflowed:
            status[0] |= sp.ST_TX_OVERFLOW
            self._overflowed = False
        k = np.arange(self._k, self._k + n, dtype=np.int64)
        t_us = self.cfg.t0_us + np.rint(k * (1e6 / self.sample_rate_hz)).astype(np.int64)
        raw = sp.encode_data_block(self.cfg.seq0 + k, t_us, enc, scale, cmd.astype(np.float32),
                                   current.astype(np.int16), status)
        self._k += n
        self.applied_torque = float(cmd[-1])
        self.motor_torque = float(blk.torque_applied[-1])
        self.status = int(status[-1])
        if self._plant.travel_exceeded and self.enabled:
            log.warning("emulated board: table outside its travel: disabling")
            self._set_enabled(False)
            self._latched |= sp.ST_FAULT | sp.ST_LIMIT_SWITCH
        self._emit(raw, n, sent_meanwhile)

    def _faulty(self, frames: np.ndarray) -> tuple[int, bytes]:
        """Drop, corrupt and pad (n, 30) frames; returns (frames sent, bytes)."""
        f, rng, n = self.faults, self._rng, frames.shape[0]
        keep = np.ones(n, dtype=bool)
        nd = min(self._drop_next, n)
        keep[:nd] = False
        self._drop_next -= nd
        if f.drop_probability > 0:
            keep &= rng.random(n) >= f.drop_probability
        if f.silent:
            keep[:] = False
        self.frames_dropped += int(n - keep.sum())
        frames = frames[keep]                          # a copy: safe to corrupt
        m = int(frames.shape[0])
        bad = np.zeros(m, dtype=bool)
        nc = min(self._corrupt_next, m)
        bad[:nc] = True
        self._corrupt_next -= nc
        if f.corrupt_probability > 0:
            bad |= rng.random(m) < f.corrupt_probability
        idx = np.flatnonzero(bad)
        if idx.size:   # a payload byte XOR a non-zero value: always a CRC error
            cols = rng.integers(sp.HEADER_SIZE, sp.DATA_FRAME_SIZE - 2, idx.size)
            frames[idx, cols] ^= rng.integers(1, 256, idx.size).astype(np.uint8)
            self.frames_corrupted += int(idx.size)
        garbage, self._garbage_next = self._garbage_next, b""
        self.garbage_sent += len(garbage)
        if not (f.garbage_probability > 0 and m):
            return m, garbage + frames.tobytes()
        pieces = [garbage]
        for i, g in enumerate(rng.random(m) < f.garbage_probability):
            if g:
                junk = rng.integers(0, 256, int(rng.integers(1, f.garbage_max + 1)), dtype=np.uint8)
                pieces.append(junk.tobytes())
                self.garbage_sent += junk.size
            pieces.append(frames[i].tobytes())
        return m, b"".join(pieces)

    def _emit(self, raw: bytes, n: int, sent_meanwhile: bool = False) -> None:
        """Apply the transmit faults to n encoded frames and queue what is sent. ``sent_meanwhile``: frames
        the board would already have sent, now waiting on the host's side, past its FIFO."""
        f = self.faults
        m, data = n, raw
        if (f.drop_probability or f.corrupt_probability or f.garbage_probability or f.silent
                or self._drop_next or self._corrupt_next or self._garbage_next):
            with self._lock:
                m, data = self._faulty(np.frombuffer(raw, dtype=np.uint8).reshape(n, sp.DATA_FRAME_SIZE))
        if sent_meanwhile or self.clock() < self._delay_until:   # delay(): held up in transit, not the FIFO
            if self._out:                      # behind what the FIFO held when the hold began: in order
                self._transit += self._out
                self._out.clear()
            self.frames_sent += m
            self._transit += data
            return
        if m and len(self._out) + len(data) > self.tx_buffer:
            self.tx_overflow_frames += m       # a full transmit FIFO drops whole frames
            self._overflowed = True
            return
        self.frames_sent += m
        self._out += data

    def _flush(self, now: float) -> None:
        if now < self._delay_until:
            return
        for buf in (self._transit, self._out):
            if not buf:
                continue
            try:
                written = os.write(self._master, buf)
            except (BlockingIOError, InterruptedError):
                written = 0
            except OSError:
                log.debug("emulated board: write failed", exc_info=True)
                return
            self._note_refusal(now, written == 0)
            del buf[:written]
            if buf:
                return
        self._note_refusal(now, False)

    def _note_refusal(self, now: float, refused: bool) -> None:
        """Times the pseudo-terminal took no byte while the board, enabled, had some to send: the host's side of
        it full (the host not reading, or its kernel's tty worker not moving bytes) - ``tx_refused_longest_s``.
        Not counted while disabled: before its run and after it, a host need not read."""
        if refused and self.enabled:
            if self._refused_since is None:
                self._refused_since = now
        elif self._refused_since is not None:
            self.tx_refused_longest_s = max(self.tx_refused_longest_s, now - self._refused_since)
            self._refused_since = None


def start_emulator_for(config: Any) -> EmulatedBoard:
    """Start the board a serial config describes; returns it running (use ``.port``).

    ``config`` is a :class:`rt_ident.config.RunConfig`, a whole run mapping
    (``{"axis":…, "backend":…, "emulator":…}``) or a flat ``[backend]`` mapping
    whose ``emulator`` key holds the emulator options.
    """
    if hasattr(config, "backend") and hasattr(config, "axis_params"):
        backend = {**dict(getattr(config.backend, "model_extra", None) or {})}
        emu = dict(getattr(config, "emulator", None) or {})
        params = config.axis_params()
    else:
        data = dict(config or {})
        if "backend" in data:
            backend = dict(data.get("backend") or {})
            emu = dict(data.get("emulator") or {})
            params = AxisParams.from_mapping(data["axis"], where="axis") if data.get("axis") else None
        else:
            backend, emu, params = data, dict(data.get("emulator") or {}), None
    emu = emu or dict(backend.get("emulator") or {})
    bcfg: SerialBoardConfig = parse_serial({**backend, "emulate": True, "emulator": emu})
    ecfg = parse_emulator(emu)
    return board_for(bcfg, ecfg, params).start()


def board_for(bcfg: SerialBoardConfig, ecfg: EmulatorConfig, params: AxisParams | None = None,
              **kwargs: Any) -> EmulatedBoard:
    """A (not started) board matching a validated serial backend config."""
    if ecfg.friction is not None and "friction" not in kwargs:
        kwargs["friction"] = Friction.from_mapping(ecfg.friction, where="emulator.friction")
    return EmulatedBoard(params, sample_rate_hz=bcfg.sample_rate_hz, counts_per_rev=bcfg.counts_per_rev,
                         scale_resolution=bcfg.scale_resolution, torque_constant=bcfg.torque_constant,
                         torque_limit=bcfg.torque_limit, torque_sign=bcfg.torque_sign,
                         motor_encoder_sign=bcfg.motor_encoder_sign, scale_sign=bcfg.scale_sign,
                         emulator=ecfg, plan_capacity=bcfg.plan_capacity, **kwargs)


def main(argv: list[str] | None = None) -> int:
    """``python -m drivers.encoder_board.emulator [--config run.toml]``: print the pty path, run until Ctrl-C."""
    import tomllib

    ap = argparse.ArgumentParser(description="Emulated serial encoder board on a pseudo-terminal")
    ap.add_argument("--config", help="run TOML with [backend] (serial), [emulator], [axis]")
    ap.add_argument("--rate", type=float, help="sample rate [Hz] (default 20000)")
    ap.add_argument("--seed", type=int, help="noise / fault seed")
    ap.add_argument("--no-realtime", action="store_true",
                    help="do not keep off the loop's CPU / ask for SCHED_FIFO (see drivers.placement)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    data: dict[str, Any] = {}
    if args.config:
        with open(args.config, "rb") as fh:
            data = tomllib.load(fh)
    data.setdefault("backend", {})
    data.setdefault("emulator", {})
    if args.rate is not None:
        data["backend"]["sample_rate_hz"] = args.rate
    if args.seed is not None:
        data["emulator"]["seed"] = args.seed
    from drivers.placement import clear_heap, device_placement, keep_to, settle_heap, start_realtime

    clear_heap()
    placement = device_placement(not args.no_realtime)       # as the loop places its own emulator child
    placed = keep_to(placement["cpus"])
    board, rt = start_realtime(lambda: start_emulator_for(data), placement["fifo_priority"])
    placed.update(rt)
    logging.getLogger(__name__).info("placement: %s", placed or "none")
    settle_heap()
    print(board.port, flush=True)   # the one line a caller reads (CLI output, not logging)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        board.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Backend for the serial encoder board (``docs/serial-protocol.md``), registry name ``"serial"``.

The board streams one numbered, time-stamped data frame per sample (default
20 kHz); :meth:`SerialBoardBackend.read` drains whatever arrived (``in_waiting``
bytes, never a blocking ``read(n)``), decodes it with
:class:`drivers.encoder_board.protocol.FrameDecoder` and returns one
:class:`~drivers.base.SampleBlock`. Torque goes out as hold or sequence-tagged
plan frames; a heartbeat is sent whenever nothing else was sent for
``heartbeat_period``. Any fatal condition (CRC storm, silence, board fault,
encoder mismatch) first sends quick-stop / zero-torque / disable frames, then
raises the matching :class:`~drivers.errors.DriverError`.

At open the host asks the board what it is (INFO_REQUEST); :meth:`~drivers.base.Backend.identity`
returns the answer, or ``{"info": "not available"}`` when the board did not answer within
``info_timeout`` (a version 1 board). Polarity (``torque_sign``, ``motor_encoder_sign``,
``scale_sign``) is applied by :class:`~drivers.base.Backend`.

With ``emulate = true`` the backend starts its own
:class:`drivers.encoder_board.emulator.EmulatedBoard` on a pty in ``open()`` and stops
it in ``close()``.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import serial

from drivers.base import SAME_TORQUE, Backend, SampleBlock, settings_differ
from drivers.encoder_board import protocol as sp
from drivers.encoder_board.config import EmulatorConfig, parse_emulator, parse_serial
from drivers.errors import DeviceConnectionError, DeviceFault, DeviceTimeout, DriverError, ProtocolError
from rt_ident.hostlock import holder

log = logging.getLogger(__name__)

_MAX_READ = 1 << 16  # bytes drained per read() at most (~109 ms of frames at 20 kHz)
_TTY_PIECE = 4095    # bytes a tty read returns at most (Linux N_TTY's 4 KiB buffer, raw mode)
_REFILL_LOOK_S = 5e-5  # [s] between looks at ``in_waiting`` while the kernel refills the tty's buffer

#: errnos of a tty whose device went away under an open port (EIO, ENXIO, ENODEV)
_GONE_ERRNOS = (5, 6, 19)


#: relative spacing of float32 values: the board's copy of a planned torque is the host's value rounded to it
F32_EPS = float(np.finfo(np.float32).eps)

#: where Linux lists USB serial converters (FTDI, CP210x, ...), each with its latency timer [ms]
USB_SERIAL_SYSFS = Path("/sys/bus/usb-serial/devices")


def usb_latency_note(port: str, sysfs: Path | None = None) -> str | None:
    """A USB serial converter hands received bytes over only when its buffer fills or its latency timer runs out
    (16 ms by default for FTDI chips): a 1 kHz loop then reads in bursts that far apart and runs its control on
    samples that old. The warning naming the fix, or None (a timer of 1 ms, a CDC-ACM board, not a converter)."""
    timer = (sysfs or USB_SERIAL_SYSFS) / Path(os.path.realpath(port)).name / "latency_timer"
    try:
        ms = int(timer.read_text().strip())
    except (OSError, ValueError):
        return None
    if ms <= 1:
        return None
    return (f"serial port {port!r} is a USB serial converter that holds received bytes up to {ms} ms (its latency "
            f"timer): the loop reads the board in {ms} ms bursts; set it to 1 ms: echo 1 | sudo tee {timer}")


def _gone(exc: BaseException) -> str:
    """What an I/O error of an open port means for the user, where it means the board went away."""
    text = str(exc)                     # pyserial re-raises some OSErrors as text: "read failed: [Errno 5] ..."
    if getattr(exc, "errno", None) in _GONE_ERRNOS or "device disconnected" in text \
            or any(f"[Errno {n}]" in text for n in _GONE_ERRNOS):
        return " (the board's link went away: unplugged, powered off or reset)"
    return ""


class SerialBoardBackend(Backend):
    """The serial encoder board. Constructor validates only (no I/O)."""

    name = "serial"

    def __init__(self, config: Mapping[str, Any] | None = None, *,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = cfg = parse_serial(config or {})
        super().__init__({"torque_limit": cfg.torque_limit, "torque_sign": cfg.torque_sign,
                          "motor_encoder_sign": cfg.motor_encoder_sign, "scale_sign": cfg.scale_sign})
        self.emulator_config: EmulatorConfig | None = None
        if cfg.emulate:
            self.emulator_config = parse_emulator(cfg.emulator, where="backend.emulator")
        self.clock = clock
        self.emulator: Any = None
        self.port: str | None = cfg.port
        self._ser: Any = None
        self._direct: tuple[Any, int | None] = (None, None)   # (port, its descriptor for direct writes)
        self._decoder = sp.FrameDecoder()
        self._unwrap = sp.StreamUnwrapper()
        self._pending = np.empty(0, dtype=sp.DATA_DTYPE)
        self._rad_per_count = 2.0 * math.pi / cfg.counts_per_rev
        self._rad_per_scale = cfg.scale_resolution / cfg.lead
        self._nm_per_ma = cfg.torque_constant * 1e-3
        self._last_frame = 0.0
        self._last_tx = -math.inf
        self._heartbeats = 0
        self._twist0: float | None = None
        self._last_seq: int | None = None
        self._info: dict[str, Any] | None = None    # the board's INFO answer (cached at open)
        self.bytes_read = 0
        self.plan_late = 0
        self.late_torques = 0
        # the torque last planned for each sample (seq modulo the size; -1: none), to tell which samples the
        # board ran on an older plan because the newer one came after them
        size = 1 << max(16, (2 * cfg.plan_capacity).bit_length())
        self._intent_seq = np.full(size, -1, dtype=np.int64)
        self._intent = np.zeros(size, dtype=np.float32)
        self.torque_limited = 0
        self.tx_overflow = 0
        self.write_retries = 0     # writes sent once more after a timeout (_send)

    # ----- properties ---------------------------------------------------------------------
    @property
    def sample_period(self) -> float:
        return 1.0 / self.config.sample_rate_hz

    @property
    def has_measured_torque(self) -> bool:
        return True

    def stats(self) -> dict[str, int]:
        """Link health counters (cumulative)."""
        d = self._decoder
        return {"frames": d.frames, "crc_errors": d.crc_errors, "header_errors": d.header_errors,
                "garbage_bytes": d.garbage_bytes, "resyncs": d.resyncs, "lost": self._unwrap.lost,
                "backsteps": self._unwrap.backsteps, "bytes_read": self.bytes_read,
                "heartbeats": self._heartbeats, "plan_late": self.plan_late, "late_torques": self.late_torques,
                "torque_limited": self.torque_limited, "tx_overflow": self.tx_overflow,
                "clamped": self.clamped, "write_retries": self.write_retries}

    # ----- I/O helpers --------------------------------------------------------------------
    def _send(self, data: bytes) -> None:
        # pyserial checks its deadline after each os.write: a host stalled inside write() reads as a
        # timeout though every byte went out. So a timeout is written once more (frames are whole and
        # idempotent; a partial one is garbage the board skips); a board that does not read times out twice.
        for retry in (False, True):
            try:
                self._write(data)
                break
            except serial.SerialTimeoutException as exc:
                if retry:
                    raise DeviceTimeout(f"serial port {self.port!r}: write timed out after "
                                        f"{self.config.write_timeout} s, twice") from exc
                self.write_retries += 1
            except (serial.SerialException, OSError) as exc:
                raise DeviceConnectionError(f"serial port {self.port!r}: write failed: {exc}{_gone(exc)}") from exc
        self._last_tx = self.clock()

    def _write(self, data: bytes) -> None:
        """``data`` out. pyserial polls the port after every write, and a poll of a tty with no input waits
        inside the kernel for its tty worker (see :meth:`_recv`): a write the port takes whole is made
        directly; only one it cannot take waits, for ``write_timeout`` at most, as pyserial waits."""
        ser = self._ser
        if self._direct[0] is not ser:           # once per port: a pyserial URL (loop://...) has no descriptor,
            fd = getattr(ser, "fd", None)        # and a port class whose descriptor blocks keeps its own write
            self._direct = (ser, fd if isinstance(fd, int) and not os.get_blocking(fd) else None)
        fd = self._direct[1]
        if fd is None:
            ser.write(data)
            return
        try:
            n = os.write(fd, data)
        except BlockingIOError:
            n = 0
        if n < len(data):
            ser.write(data[n:])

    def _recv(self) -> bytes:
        """Everything that has arrived, without ever waiting inside the kernel.

        Serial input reaches the line discipline through the kernel's tty work, run by an ordinary-priority
        worker thread; a read or poll finding the line discipline empty waits, uninterruptibly, for pending
        work to finish, and a real-time loop waits with it, however long a busy CPU holds the worker off. So
        this reads only what ``in_waiting`` says is there. The line discipline holds at most
        :data:`_TTY_PIECE` and is refilled a moment after each read: a read that found a backlog (a piece's
        worth or more) looks again until nothing has come for ``poll_timeout``; a read of less (the board's
        few frames per tick) pays no wait. With nothing there, it looks for ``poll_timeout`` at most."""
        ser, data = self._ser, bytearray()
        quiet_s = self.config.poll_timeout
        try:
            until = time.monotonic() + quiet_s
            while len(data) < _MAX_READ:
                n = ser.in_waiting
                if n:
                    data += ser.read(min(n, _MAX_READ - len(data)))
                    until = time.monotonic() + quiet_s
                    continue
                if (data and len(data) < _TTY_PIECE) or time.monotonic() >= until:
                    break
                time.sleep(_REFILL_LOOK_S)       # the tty worker may need this CPU to refill the buffer
        except (serial.SerialException, OSError) as exc:
            raise DeviceConnectionError(f"serial port {self.port!r}: read failed: {exc}{_gone(exc)}") from exc
        self.bytes_read += len(data)
        return bytes(data)

    def _stop_frames(self) -> bool:
        """Quick stop, zero torque, disable: best effort, never raises. False when they could not be sent."""
        if self._ser is None:
            return False
        for frame in (sp.encode_quick_stop(), sp.encode_torque_hold(0.0), sp.encode_disable()):
            try:
                self._send(frame)
            except Exception as exc:  # noqa: BLE001 - a stop path must not raise
                # once: the link's failure is the stop's cause, and safe_stop() reports the disable unconfirmed
                if not getattr(self, "_stop_unsent", False):
                    self._stop_unsent = True
                    log.info("serial board %s: stop frames not sent (%s); the board disables itself when the "
                             "host's heartbeats stop", self.port, type(exc).__name__)
                log.debug("serial board %s: stop frame failed", self.port, exc_info=True)
                return False
        return True

    def _fail(self, exc: DriverError) -> DriverError:
        """De-energize first, then hand the error back to be raised (the caller reports it)."""
        log.info("serial board %s: %s", self.port, exc)
        self._stop_frames()
        return exc

    def _wait_for(self, predicate: Callable[[np.ndarray], int], timeout: float) -> np.ndarray | None:
        """Read until ``predicate(samples)`` gives an index >= 0; return the samples from there."""
        deadline = self.clock() + timeout
        while True:
            samples, others = self._decoder.feed_samples(self._recv())
            if others:
                self._note(others)
            if samples.shape[0]:
                self._last_frame = self.clock()
                i = predicate(samples)
                if i >= 0:
                    return samples[i:]
            if self.clock() >= deadline:
                return None

    def _note(self, frames: list[sp.Frame]) -> None:
        """Keep an INFO answer (one may also arrive after open gave up on it)."""
        for f in frames:
            if isinstance(f, sp.Info):
                self._info = f.as_dict()

    def _request_info(self) -> None:
        """Ask the board what it is; wait at most ``info_timeout`` for the answer (a board that does not
        know the request never answers: open goes on without it)."""
        self._send(sp.encode_info_request())
        deadline = self.clock() + self.config.info_timeout
        while self._info is None and self.clock() < deadline:
            samples, others = self._decoder.feed_samples(self._recv())
            if others:
                self._note(others)
            if samples.shape[0]:
                self._last_frame = self.clock()
                self._opened_at = self._position(samples[-1])
        info = self._info
        if info is None:
            log.info("serial board on %s: no answer to INFO_REQUEST within %g s: identity not available",
                     self.port, self.config.info_timeout)
            return
        cfg = self.config
        told = {"sample_rate_hz": cfg.sample_rate_hz, "counts_per_rev": cfg.counts_per_rev,
                "scale_resolution": cfg.scale_resolution}
        differ = settings_differ(info, told)
        if differ:                             # the run refuses it, commissioning fails its check: said there
            log.info("serial board on %s is configured for %s", self.port,
                     ", ".join(f"{k} = {dev:g} ([backend]: {v:g})" for k, (dev, v) in differ.items()))

    def _position(self, sample: np.ndarray) -> tuple[float, float]:
        return float(sample["enc"]) * self._rad_per_count, float(sample["scale"]) * self._rad_per_scale

    def _identity(self) -> dict[str, Any]:
        return dict(self._info) if self._info is not None else {"info": "not available"}

    # ----- lifecycle hooks -----------------------------------------------------------------
    def _open(self) -> None:
        cfg, ecfg = self.config, self.emulator_config
        if ecfg is not None:                  # (set exactly when the config says emulate)
            from drivers.encoder_board.emulator import board_for
            self.emulator = board_for(cfg, ecfg).start()
            self.port = self.emulator.port
        try:
            # exclusive: an flock on the port, so a second program that asks for one (another run) is refused
            # instead of reading half the frames and sending torque frames of its own
            self._ser = serial.serial_for_url(self.port, baudrate=cfg.baudrate, timeout=cfg.poll_timeout,
                                              write_timeout=cfg.write_timeout, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._stop_emulator()
            hint = ""
            if getattr(exc, "errno", None) == 13 or "Permission denied" in str(exc):
                hint = " (no permission: add your user to the group that owns the port, e.g. dialout, and log in again)"
            elif getattr(exc, "errno", None) == 2 or "No such file" in str(exc):
                hint = " (no such device: is the board plugged in? backend.port names it, e.g. /dev/ttyACM0)"
            elif getattr(exc, "errno", None) == errno.EBUSY or "Device or resource busy" in str(exc):
                hint = (" (busy: another program opened it for itself alone; on a desktop Linux often ModemManager "
                        "probing a newly plugged /dev/ttyACM board for a few seconds: try again, or keep it off "
                        "with a udev rule setting ENV{ID_MM_DEVICE_IGNORE}=\"1\" for the board)")
            elif getattr(exc, "errno", None) == errno.EAGAIN or "exclusively lock" in str(exc):
                hint = (f" (in use: {holder(self.port or '') or 'another program'} has the port: let it end first; "
                        "two programs on one board would each send it torque)")
            elif "Inappropriate ioctl" in str(exc):
                hint = " (not a serial device: backend.port names the board's tty, e.g. /dev/ttyACM0)"
            raise DeviceConnectionError(f"cannot open serial port {self.port!r}: {exc}{hint}") from exc
        note = usb_latency_note(self.port or "") if ecfg is None else None
        if note:
            log.warning("%s", note)
        try:
            self._send(sp.encode_disable())          # a known, de-energized state
            got = self._wait_for(lambda _s: 0, cfg.startup_timeout)
        except DriverError:
            self._close()
            raise
        if got is None:
            d = self._decoder
            self._close()
            raise DeviceTimeout(f"serial port {self.port!r}: no valid data frame within "
                                f"{cfg.startup_timeout} s ({self.bytes_read} bytes, {d.crc_errors} CRC errors, "
                                f"{d.garbage_bytes} garbage bytes)")
        log.info("serial board on %s: streaming (seq %d)", self.port, int(got["seq"][0]))
        self._opened_at = self._position(got[-1])
        try:
            self._request_info()
        except DriverError:
            self._close()
            raise

    def _link_trouble(self) -> str:
        """The port gone under the run (a board unplugged, powered off or reset): its silence was the link's.
        The kernel hangs a tty up a moment after its device goes, so the read before a watchdog trip may
        not have seen it yet; this looks again, without waiting."""
        ser = self._ser
        if ser is None:
            return ""
        try:
            _waiting = ser.in_waiting                   # the ioctl fails (EIO) on a hung-up tty
        except (serial.SerialException, OSError) as exc:
            return f"; serial port {self.port!r} then failed: {exc}{_gone(exc)}"
        return ""

    def _read_position(self) -> tuple[float, float]:
        return self._opened_at

    def _activate(self) -> None:
        self._send(sp.encode_enable())
        got = self._wait_for(lambda s: int(np.argmax((s["status"] & sp.ST_ENABLED) != 0))
                             if np.any(s["status"] & sp.ST_ENABLED) else -1, self.config.startup_timeout)
        if got is None:
            raise self._fail(DeviceTimeout(f"serial port {self.port!r}: board did not report enabled "
                                           f"within {self.config.startup_timeout} s"))
        self._pending = got            # the stream starts at the first enabled sample
        self._unwrap = sp.StreamUnwrapper()
        self._twist0 = None

    def _read(self) -> SampleBlock:
        cfg = self.config
        now = self.clock()
        prev_read, self._last_read = getattr(self, "_last_read", now), now
        if now - self._last_tx >= cfg.heartbeat_period:
            self._send(sp.encode_heartbeat(self._heartbeats))
            self._heartbeats += 1
        d = self._decoder
        crc0, hdr0, garbage0 = d.crc_errors, d.header_errors, d.garbage_bytes
        samples, others = d.feed_samples(self._recv())
        if others:
            self._note(others)
        if self._pending.shape[0]:
            samples = np.concatenate([self._pending, samples]) if samples.shape[0] else self._pending
            self._pending = np.empty(0, dtype=sp.DATA_DTYPE)
        errors = (d.crc_errors - crc0) + (d.header_errors - hdr0)
        if errors > cfg.crc_storm_limit:
            raise self._fail(ProtocolError(f"serial port {self.port!r}: CRC storm: {errors} bad frames in one "
                                           f"read (crc_storm_limit={cfg.crc_storm_limit})"))
        if d.garbage_bytes - garbage0 > cfg.garbage_storm_limit:
            raise self._fail(ProtocolError(f"serial port {self.port!r}: {d.garbage_bytes - garbage0} garbage "
                                           f"bytes in one read (garbage_storm_limit={cfg.garbage_storm_limit})"))
        if samples.shape[0] == 0:
            if now - self._last_frame > cfg.read_timeout:
                # whose silence: the host's (it had not read for most of the timeout: a busy host; the
                # frames would be in the buffer had the board sent them, so the board was silent too,
                # but the host cannot tell how long) or, the host reading on, the board's - or the kernel's
                # tty worker's, which the host does not wait for (_recv) and cannot see
                gap = now - prev_read
                who = (f"the host itself had not read for {gap:.3f} s: a busy host" if gap > 0.5 * cfg.read_timeout
                       else f"the host kept reading (last read {1e3 * gap:.1f} ms before): the board sent nothing, "
                            "or this host's kernel held its bytes back (a CPU too busy for its tty worker)")
                raise self._fail(DeviceTimeout(f"serial port {self.port!r}: no valid frame for "
                                               f"{now - self._last_frame:.3f} s (read_timeout={cfg.read_timeout}); "
                                               + who))
            return SampleBlock.empty(with_measured=True)
        self._last_frame = now
        u = self._unwrap.update(samples)
        if u.backsteps:
            raise self._fail(DeviceFault(f"serial port {self.port!r}: sequence number repeated or went back "
                                         f"({u.backsteps} frames): board restarted?"))
        status = samples["status"]
        any_set = int(np.bitwise_or.reduce(status))
        if not int(np.bitwise_and.reduce(status)) & sp.ST_ENABLED or any_set & sp.ST_FAULT:
            bad = ((status & sp.ST_ENABLED) == 0) | ((status & sp.ST_FAULT) != 0)
            i = int(np.argmax(bad))
            raise self._fail(DeviceFault(f"serial port {self.port!r}: board reported "
                                         f"{sp.status_text(int(status[i]))} at seq {int(u.seq[i])}"))
        theta1 = u.enc * self._rad_per_count
        theta2 = u.scale * self._rad_per_scale           # x / lead
        if self.config.encoder_mismatch_limit is not None:
            self._check_encoders(theta1, theta2, u.seq)
        if any_set & (sp.ST_PLAN_LATE | sp.ST_TORQUE_LIMITED | sp.ST_TX_OVERFLOW):
            self.plan_late += int(np.count_nonzero(status & sp.ST_PLAN_LATE))
            self.torque_limited += int(np.count_nonzero(status & sp.ST_TORQUE_LIMITED))
            self.tx_overflow += int(np.count_nonzero(status & sp.ST_TX_OVERFLOW))
        self._count_late(u.seq, samples["cmd"], status)
        self._last_seq = int(u.seq[-1])
        return SampleBlock(t=u.t, seq=u.seq, theta1=theta1, theta2=theta2,
                           torque_cmd=samples["cmd"].astype(np.float64),
                           torque_meas=samples["current"] * self._nm_per_ma, lost=u.lost)

    def _check_encoders(self, theta1: np.ndarray, theta2: np.ndarray, seq: np.ndarray) -> None:
        """The shaft twist theta1 - theta2 is physically small (|T|/K): a drift means a bad sensor."""
        limit = self.config.encoder_mismatch_limit
        # in the host's convention (the device's may count one of them the other way)
        twist = ((theta1 if self.motor_encoder_sign == 1 else -theta1)
                 - (theta2 if self.scale_sign == 1 else -theta2))
        if self._twist0 is None:
            self._twist0 = float(twist[0])
        if twist.max() - self._twist0 > limit or self._twist0 - twist.min() > limit:
            drift = np.abs(twist - self._twist0)
            i = int(np.argmax(drift > limit))
            raise self._fail(DeviceFault(
                f"serial port {self.port!r}: motor encoder and linear scale disagree by {drift[i]:.3f} rad "
                f"at seq {int(seq[i])} (encoder_mismatch_limit={limit}): encoder stuck or slipping?"))

    def _count_late(self, seq: np.ndarray, cmd: np.ndarray, status: np.ndarray) -> None:
        """late_torques: samples whose torque in force (not clamped by the board) is not the one last planned
        for them; the plan for them reached the board after they were taken."""
        idx = seq & (self._intent.size - 1)
        known = (self._intent_seq[idx] == seq) & ((status & sp.ST_TORQUE_LIMITED) == 0)
        if known.any():
            want = self._intent[idx[known]].astype(np.float64)
            off = np.abs(cmd[known].astype(np.float64) - want) > SAME_TORQUE + F32_EPS * np.abs(want)
            self.late_torques += int(np.count_nonzero(off))

    def _remember(self, start_seq: int, torques: np.ndarray) -> None:
        seq = start_seq + np.arange(torques.size, dtype=np.int64)
        idx = seq & (self._intent.size - 1)
        self._intent_seq[idx] = seq
        self._intent[idx] = torques

    def _write_hold(self, torque: float) -> None:
        self._send(sp.encode_torque_hold(torque))
        self._intent_seq.fill(-1)                         # a hold replaces every plan the board queued

    def _write_plan(self, torques: np.ndarray, start_seq: int) -> None:
        if torques.size:
            self._send(self._plan_frames(torques, start_seq, int(torques.size)))
            self._remember(start_seq, torques)

    def _write_leased_plan(self, torques: np.ndarray, start_seq: int, lease: int) -> None:
        """The plan and its lease's zero in one write: a host stalled between two writes would leave
        the board holding the plan's last value with no end."""
        n = int(torques.size)
        if n:
            self._send(self._plan_frames(torques, start_seq, n + lease + 1)
                       + sp.encode_torque_plan(start_seq + n + lease, (0.0,)))
            self._remember(start_seq, np.concatenate([torques, np.full(lease, torques[-1]), np.zeros(1)]))

    def _plan_frames(self, torques: np.ndarray, start_seq: int, span: int) -> bytes:
        cap = self.config.plan_capacity
        ahead = start_seq + span - (self._last_seq if self._last_seq is not None else start_seq)
        if ahead > cap:
            raise DriverError(f"torques: plan reaches {ahead} samples past the last one read; "
                              f"the board queues at most plan_capacity={cap}")
        return sp.encode_torque_plan(start_seq, torques)

    def _safe_stop(self) -> str | None:
        on_its_own = "the board's firmware disables it when the host's frames stop (its heartbeat timeout)"
        if not self._stop_frames():
            return f"the stop frames could not be sent (the link had failed); {on_its_own}"
        if self.config.stop_timeout <= 0:
            return f"not awaited (backend.stop_timeout = 0); {on_its_own}"
        try:
            got = self._wait_for(lambda s: int(np.argmax((s["status"] & sp.ST_ENABLED) == 0))
                                 if np.any((s["status"] & sp.ST_ENABLED) == 0) else -1,
                                 self.config.stop_timeout)
        except Exception:  # noqa: BLE001
            got = None
        if got is None:
            return f"the board did not report itself disabled within {self.config.stop_timeout:g} s; {on_its_own}"
        return None

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("serial: closing %s failed: %s", self.port, exc)
                log.debug("serial: closing %s failed", self.port, exc_info=True)
        self._stop_emulator()

    def _stop_emulator(self) -> None:
        emu, self.emulator = self.emulator, None
        if emu is not None:
            emu.stop()

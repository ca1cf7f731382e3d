"""Wire codec of the serial encoder board (pure: no I/O, no clock).

Specified in ``docs/serial-protocol.md``. Every frame, in both directions::

    A5 5A | type u8 | len u8 | payload (len bytes) | crc u16

little-endian; ``crc = binascii.crc_hqx(type..payload, 0xFFFF)`` (CRC-16/CCITT,
polynomial 0x1021, init 0xFFFF). The board streams one :class:`DataFrame` per
sample and answers an :class:`InfoRequest` with one :class:`Info` frame; the host
sends enable/disable/quick-stop/heartbeat/torque frames.

:class:`FrameDecoder` resynchronizes on garbage, partial frames and CRC errors
(on a bad CRC or an impossible header it drops one byte and hunts for the next
sync) and counts what it discarded. Runs of back-to-back data frames are
validated and unpacked with numpy in one go, so a 20 kHz stream costs one
``crc_hqx`` call (~0.3 us) per frame and a handful of numpy calls per read.
:class:`StreamUnwrapper` turns the wrapping 32-bit sequence numbers, microsecond
time stamps and encoder counters into int64 / seconds and counts sequence gaps.
"""

from __future__ import annotations

import struct
from binascii import crc_hqx
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

SYNC = b"\xa5\x5a"
SYNC_U16 = 0x5AA5              # the two sync bytes read as a little-endian uint16
CRC_INIT = 0xFFFF
HEADER_SIZE = 4                # sync (2) + type + len
OVERHEAD = HEADER_SIZE + 2     # + crc
MAX_PAYLOAD = 252

PROTOCOL_VERSION = 2           # 2: INFO_REQUEST / INFO added (a version 1 board ignores the request)

# frame types
T_DATA = 0x01
T_INFO = 0x02
T_ENABLE = 0x10
T_DISABLE = 0x11
T_QUICK_STOP = 0x12
T_HEARTBEAT = 0x13
T_TORQUE_HOLD = 0x14
T_TORQUE_PLAN = 0x15
T_INFO_REQUEST = 0x16

PLAN_MAX_VALUES = (MAX_PAYLOAD - 4) // 4   # 62 float32 values per plan frame

# status flags of a data frame
ST_ENABLED = 0x0001         # power stage on, torque commands applied
ST_FAULT = 0x0002           # latched fault (cleared by ENABLE); the board is disabled
ST_QUICK_STOPPED = 0x0004   # a quick stop was executed (cleared by ENABLE)
ST_HEARTBEAT_LOST = 0x0008  # host frames stopped arriving while enabled (with ST_FAULT)
ST_TORQUE_LIMITED = 0x0010  # the command was clamped to the board's torque limit
ST_PLAN_ACTIVE = 0x0020     # this sample's command came from a plan
ST_PLAN_LATE = 0x0040       # a plan frame arrived after some of its samples were due
ST_LIMIT_SWITCH = 0x0080    # the table left its travel (with ST_FAULT)
ST_TX_OVERFLOW = 0x0100     # the board dropped frames because its transmit buffer was full

STATUS_NAMES = {
    ST_ENABLED: "enabled", ST_FAULT: "fault", ST_QUICK_STOPPED: "quick-stopped",
    ST_HEARTBEAT_LOST: "heartbeat-lost", ST_TORQUE_LIMITED: "torque-limited",
    ST_PLAN_ACTIVE: "plan-active", ST_PLAN_LATE: "plan-late", ST_LIMIT_SWITCH: "limit-switch",
    ST_TX_OVERFLOW: "tx-overflow",
}

#: One data frame on the wire, including sync, header and CRC (30 bytes).
DATA_DTYPE = np.dtype([
    ("sync", "<u2"), ("type", "u1"), ("len", "u1"),
    ("seq", "<u4"), ("t_us", "<u4"), ("enc", "<i4"), ("scale", "<i4"),
    ("cmd", "<f4"), ("current", "<i2"), ("status", "<u2"), ("crc", "<u2"),
])
DATA_FRAME_SIZE = DATA_DTYPE.itemsize
DATA_LEN = DATA_FRAME_SIZE - OVERHEAD          # 24 payload bytes
#: The sample fields of a data frame (in the arrays :meth:`FrameDecoder.feed_samples` returns).
SAMPLE_FIELDS = ("seq", "t_us", "enc", "scale", "cmd", "current", "status")
_DATA_PAYLOAD = struct.Struct("<IIiifhH")
assert _DATA_PAYLOAD.size == DATA_LEN and DATA_FRAME_SIZE == 30

# header (sync, type, len) as one uint32, and the CRC, of a data frame: one comparison per frame
_HDR_DTYPE = np.dtype({"names": ["hdr", "crc"], "formats": ["<u4", "<u2"],
                       "offsets": [0, DATA_FRAME_SIZE - 2], "itemsize": DATA_FRAME_SIZE})
_DATA_HDR_U32 = SYNC_U16 | (T_DATA << 16) | (DATA_LEN << 24)

# INFO: protocol version, firmware major/minor/patch, serial number, model (ASCII, NUL-padded),
# sample rate [Hz], current limit [A], torque constant [N m/A], counts per rev, scale resolution [m]
_INFO_PAYLOAD = struct.Struct("<4BI16sfffId")
INFO_LEN = _INFO_PAYLOAD.size                 # 48 payload bytes

_FIXED_LEN = {T_DATA: DATA_LEN, T_INFO: INFO_LEN, T_ENABLE: 0, T_DISABLE: 0, T_QUICK_STOP: 0, T_HEARTBEAT: 4,
              T_TORQUE_HOLD: 4, T_INFO_REQUEST: 0}


def status_text(status: int) -> str:
    """Human-readable flag names, e.g. ``"fault|heartbeat-lost"``."""
    names = [name for bit, name in STATUS_NAMES.items() if status & bit]
    return "|".join(names) if names else "none"


# ----- frames (values) ----------------------------------------------------------------
@dataclass(frozen=True)
class DataFrame:
    """Board -> host: one sample. Raw wire values (wrapping counters, device units)."""

    seq: int        # uint32, +1 per sample, wraps
    t_us: int       # uint32 board time [us], wraps every 71.6 min
    enc: int        # int32 motor encoder counts
    scale: int      # int32 linear-scale counts
    cmd: float      # float32 torque command in force for this sample [N m]
    current: int    # int16 measured motor current [mA]
    status: int     # uint16 ST_* flags

    def encode(self) -> bytes:
        return encode_frame(T_DATA, _DATA_PAYLOAD.pack(
            self.seq & 0xFFFFFFFF, self.t_us & 0xFFFFFFFF, self.enc, self.scale,
            self.cmd, self.current, self.status))


@dataclass(frozen=True)
class Enable:
    """Host -> board: power on (clears latched faults, torque starts at 0)."""

    def encode(self) -> bytes:
        return encode_frame(T_ENABLE, b"")


@dataclass(frozen=True)
class Disable:
    """Host -> board: torque 0, power stage off, plan discarded."""

    def encode(self) -> bytes:
        return encode_frame(T_DISABLE, b"")


@dataclass(frozen=True)
class QuickStop:
    """Host -> board: immediate torque 0 and disable; sets ST_QUICK_STOPPED."""

    def encode(self) -> bytes:
        return encode_frame(T_QUICK_STOP, b"")


@dataclass(frozen=True)
class Heartbeat:
    """Host -> board: keep-alive (any valid host frame also feeds the board's watchdog)."""

    counter: int = 0

    def encode(self) -> bytes:
        return encode_frame(T_HEARTBEAT, struct.pack("<I", self.counter & 0xFFFFFFFF))


@dataclass(frozen=True)
class TorqueHold:
    """Host -> board: hold this torque [N m] from the next sample on; discards any plan."""

    torque: float

    def encode(self) -> bytes:
        return encode_frame(T_TORQUE_HOLD, struct.pack("<f", self.torque))


@dataclass(frozen=True)
class TorquePlan:
    """Host -> board: ``torques[i]`` for the sample whose uint32 seq is ``start_seq + i``.

    Replaces every queued value for samples >= ``start_seq``; after the last
    value the board holds it. At most :data:`PLAN_MAX_VALUES` values per frame.
    """

    start_seq: int
    torques: tuple[float, ...]

    def encode(self) -> bytes:
        n = len(self.torques)
        if not 1 <= n <= PLAN_MAX_VALUES:
            raise ValueError(f"torques: 1..{PLAN_MAX_VALUES} values per plan frame, got {n}")
        return encode_frame(T_TORQUE_PLAN, struct.pack(f"<I{n}f", self.start_seq & 0xFFFFFFFF,
                                                       *self.torques))


@dataclass(frozen=True)
class InfoRequest:
    """Host -> board: send one INFO frame (no effect on the power stage)."""

    def encode(self) -> bytes:
        return encode_frame(T_INFO_REQUEST, b"")


@dataclass(frozen=True)
class Info:
    """Board -> host: what the board is and what it is configured for (the answer to INFO_REQUEST)."""

    protocol_version: int            # uint8
    firmware: tuple[int, int, int]   # uint8 major, minor, patch
    serial_number: int               # uint32
    model: str                       # ASCII, at most 16 bytes
    sample_rate_hz: float            # float32
    current_limit_a: float           # float32: the board clamps the motor current to this
    torque_constant: float           # float32 [N m/A] the board converts torque commands with
    counts_per_rev: int              # uint32 motor encoder counts per revolution (0: not configured)
    scale_resolution: float          # float64 [m per scale count] (0: not configured)

    def encode(self) -> bytes:
        model = self.model.encode("ascii")
        if len(model) > 16:
            raise ValueError(f"model: at most 16 ASCII bytes, got {self.model!r}")
        return encode_frame(T_INFO, _INFO_PAYLOAD.pack(
            self.protocol_version, *self.firmware, self.serial_number & 0xFFFFFFFF, model,
            self.sample_rate_hz, self.current_limit_a, self.torque_constant, self.counts_per_rev,
            self.scale_resolution))

    def as_dict(self) -> dict[str, object]:
        return {"model": self.model, "firmware": ".".join(map(str, self.firmware)),
                "serial_number": self.serial_number, "protocol_version": self.protocol_version,
                "sample_rate_hz": self.sample_rate_hz, "current_limit_a": self.current_limit_a,
                "torque_constant": self.torque_constant, "counts_per_rev": self.counts_per_rev,
                "scale_resolution": self.scale_resolution}


Frame = DataFrame | Info | Enable | Disable | QuickStop | Heartbeat | TorqueHold | TorquePlan | InfoRequest


# ----- encoders (pure) ----------------------------------------------------------------
def encode_frame(ftype: int, payload: bytes) -> bytes:
    """Wrap a payload: sync, type, len, payload, CRC-16 over type..payload."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload: at most {MAX_PAYLOAD} bytes, got {len(payload)}")
    body = bytes((ftype, len(payload))) + payload
    return SYNC + body + crc_hqx(body, CRC_INIT).to_bytes(2, "little")


def encode_enable() -> bytes:
    return Enable().encode()


def encode_disable() -> bytes:
    return Disable().encode()


def encode_quick_stop() -> bytes:
    return QuickStop().encode()


def encode_info_request() -> bytes:
    return InfoRequest().encode()


def encode_heartbeat(counter: int) -> bytes:
    return Heartbeat(counter).encode()


def encode_torque_hold(torque: float) -> bytes:
    return TorqueHold(float(torque)).encode()


def encode_torque_plan(start_seq: int, torques: Iterable[float]) -> bytes:
    """A plan of any length as consecutive frames of up to 62 values each."""
    values = np.asarray(list(torques) if not isinstance(torques, np.ndarray) else torques,
                        dtype=np.float32).ravel()
    if values.size == 0:
        raise ValueError("torques: a plan needs at least one value")
    out = []
    for i in range(0, values.size, PLAN_MAX_VALUES):
        chunk = values[i:i + PLAN_MAX_VALUES]
        payload = struct.pack("<I", (start_seq + i) & 0xFFFFFFFF) + chunk.astype("<f4").tobytes()
        out.append(encode_frame(T_TORQUE_PLAN, payload))
    return b"".join(out)


def encode_data_block(seq: np.ndarray, t_us: np.ndarray, enc: np.ndarray, scale: np.ndarray,
                      cmd: np.ndarray, current: np.ndarray, status: np.ndarray) -> bytes:
    """Many data frames at once (vectorized; counters are reduced modulo 2^32)."""
    n = int(np.shape(seq)[0])
    a = np.empty(n, dtype=DATA_DTYPE)
    a["sync"] = SYNC_U16
    a["type"] = T_DATA
    a["len"] = DATA_LEN
    a["seq"] = np.asarray(seq, dtype=np.int64) & 0xFFFFFFFF
    a["t_us"] = np.asarray(t_us, dtype=np.int64) & 0xFFFFFFFF
    a["enc"] = (np.asarray(enc, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint32).view(np.int32)
    a["scale"] = (np.asarray(scale, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint32).view(np.int32)
    a["cmd"] = cmd
    a["current"] = current
    a["status"] = status
    raw = a.view(np.uint8).data                 # a memoryview of the frames' bytes
    size = DATA_FRAME_SIZE
    a["crc"] = np.fromiter((crc_hqx(raw[o + 2:o + size - 2], CRC_INIT) for o in range(0, n * size, size)),
                           dtype=np.uint16, count=n)
    return a.tobytes()


# ----- decoder --------------------------------------------------------------------------
def _length_ok(ftype: int, length: int) -> bool:
    fixed = _FIXED_LEN.get(ftype)
    if fixed is not None:
        return length == fixed
    if ftype == T_TORQUE_PLAN:
        return 8 <= length <= MAX_PAYLOAD and length % 4 == 0
    return False


def _parse_info(payload: bytes) -> Info:
    ver, major, minor, patch, serial_no, model, rate, ilim, kt, cpr, res = _INFO_PAYLOAD.unpack(payload)
    rate, ilim, kt = (float(f"{v:.7g}") for v in (rate, ilim, kt))   # float32: the decimal value it was sent as
    return Info(ver, (major, minor, patch), serial_no, model.rstrip(b"\0").decode("ascii", "replace"),
                rate, ilim, kt, cpr, res)


def _parse_other(ftype: int, payload: bytes) -> Frame:
    if ftype == T_INFO:
        return _parse_info(payload)
    if ftype == T_INFO_REQUEST:
        return InfoRequest()
    if ftype == T_ENABLE:
        return Enable()
    if ftype == T_DISABLE:
        return Disable()
    if ftype == T_QUICK_STOP:
        return QuickStop()
    if ftype == T_HEARTBEAT:
        return Heartbeat(struct.unpack("<I", payload)[0])
    if ftype == T_TORQUE_HOLD:
        return TorqueHold(struct.unpack("<f", payload)[0])
    n = (len(payload) - 4) // 4
    start, *values = struct.unpack(f"<I{n}f", payload)
    return TorquePlan(start, tuple(values))


class FrameDecoder:
    """Incremental decoder: feed arbitrary byte chunks, get whole validated frames.

    Counters (cumulative): ``frames`` accepted, ``crc_errors`` (well-formed
    header, CRC mismatch), ``header_errors`` (sync followed by an unknown type
    or an impossible length), ``garbage_bytes`` (every byte discarded),
    ``resyncs`` (episodes of lost synchronization, each ending at the next
    valid frame), ``incomplete`` (partial frames abandoned by :meth:`flush`).
    Only known frame types with their exact lengths are accepted,
    so a corrupted length byte is rejected without waiting for its CRC.
    """

    def __init__(self) -> None:
        self._tail = b""
        self._hunting = False
        self.frames = 0
        self.incomplete = 0
        self.crc_errors = 0
        self.header_errors = 0
        self.garbage_bytes = 0
        self.resyncs = 0

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._tail)

    def reset(self) -> None:
        """Forget buffered bytes (counters are kept)."""
        self._tail = b""

    def feed(self, data: bytes) -> list[Frame]:
        """All complete frames in order, as frame objects (convenient, ~1 us per frame)."""
        out: list[Frame] = []
        for item in self._scan(data):
            if isinstance(item, np.ndarray):
                out.extend(DataFrame(*row) for row in item[list(SAMPLE_FIELDS)].tolist())
            else:
                out.append(item)
        return out

    def feed_samples(self, data: bytes) -> tuple[np.ndarray, list[Frame]]:
        """Fast path: (data frames as a read-only :data:`DATA_DTYPE` array, other frames in order).

        Use the fields named in :data:`SAMPLE_FIELDS` (``seq``, ``t_us``, ``enc``,
        ``scale``, ``cmd``, ``current``, ``status``).
        """
        runs: list[np.ndarray] = []
        others: list[Frame] = []
        for item in self._scan(data):
            if isinstance(item, np.ndarray):
                runs.append(item)
            else:
                others.append(item)
        if not runs:
            return np.empty(0, dtype=DATA_DTYPE), others
        return (runs[0] if len(runs) == 1 else np.concatenate(runs)), others

    def flush(self) -> list[Frame]:
        """The stream paused (e.g. no byte for an inter-frame timeout): buffered bytes are final.

        A partial frame at the head cannot complete any more; it is counted in
        ``incomplete`` and resynchronization continues one byte later, so a
        truncated frame does not hold back a whole frame behind it.
        """
        out: list[Frame] = []
        while self._tail:
            tail, self._tail = self._tail, b""
            if tail.startswith(SYNC) and len(tail) > 2:
                self.incomplete += 1
            self._discard(1)
            out += self.feed(tail[1:])
        return out

    # -- core -----------------------------------------------------------------------------
    def _discard(self, nbytes: int) -> None:
        if nbytes > 0:
            self.garbage_bytes += nbytes
            if not self._hunting:
                self._hunting = True
                self.resyncs += 1

    def _scan(self, data: bytes) -> list[np.ndarray | Frame]:
        buf = self._tail + bytes(data)
        mv = memoryview(buf)
        n = len(buf)
        pos = 0
        items: list[np.ndarray | Frame] = []
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                # keep a trailing first sync byte: its partner may come in the next chunk
                keep = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                self._discard(keep - pos)
                pos = keep
                break
            self._discard(i - pos)
            pos = i
            if n - pos < HEADER_SIZE:
                break
            ftype, length = buf[pos + 2], buf[pos + 3]
            if not _length_ok(ftype, length):
                self.header_errors += 1
                self._discard(1)
                pos += 1
                continue
            if ftype == T_DATA:
                k = (n - pos) // DATA_FRAME_SIZE
                if k == 0:
                    break
                hdr = np.frombuffer(buf, dtype=_HDR_DTYPE, count=k, offset=pos)
                ok = hdr["hdr"] == _DATA_HDR_U32
                m = k if ok.all() else int(np.argmin(ok))      # ok[0] is True: header checked above
                want = hdr["crc"][:m].tolist()
                g = 0
                for o in range(pos + 2, pos + 2 + m * DATA_FRAME_SIZE, DATA_FRAME_SIZE):
                    if crc_hqx(mv[o:o + DATA_FRAME_SIZE - 4], CRC_INIT) != want[g]:
                        break
                    g += 1
                if g:
                    items.append(np.frombuffer(buf, dtype=DATA_DTYPE, count=g, offset=pos))
                    self.frames += g
                    self._hunting = False
                    pos += g * DATA_FRAME_SIZE
                if g < m:                                      # CRC error: drop one byte, hunt
                    self.crc_errors += 1
                    self._discard(1)
                    pos += 1
                continue
            end = pos + HEADER_SIZE + length
            if n - end < 2:
                break
            if crc_hqx(mv[pos + 2:end], CRC_INIT) != buf[end] | (buf[end + 1] << 8):
                self.crc_errors += 1
                self._discard(1)
                pos += 1
                continue
            items.append(_parse_other(ftype, bytes(mv[pos + HEADER_SIZE:end])))
            self.frames += 1
            self._hunting = False
            pos = end + 2
        self._tail = buf[pos:]
        return items


# ----- unwrapping -------------------------------------------------------------------------
# seq, t_us, enc, scale: four consecutive 32-bit words at payload offset 0 of every data frame
_COUNTERS_DTYPE = np.dtype({"names": ["c"], "formats": [("<u4", (4,))], "offsets": [HEADER_SIZE],
                            "itemsize": DATA_FRAME_SIZE})


@dataclass(frozen=True)
class Unwrapped:
    """One block of samples on continuous axes."""

    seq: np.ndarray     # int64, continuous sequence numbers
    t: np.ndarray       # float64 board time [s] (the unwrapped µs counter * 1e-6)
    enc: np.ndarray     # int64 motor counts (int32 wrap removed)
    scale: np.ndarray   # int64 scale counts (int32 wrap removed)
    lost: int           # samples missing in the sequence (gaps), including before this block
    backsteps: int      # frames whose seq did not advance (repeat or reset of the board)


class StreamUnwrapper:
    """Carries the 32-bit counters of a data stream across blocks (stateful, pure).

    Each counter step is taken modulo 2^32 and accumulated in int64: read as
    int32 for seq, enc and scale, as uint32 for time (the board clock never runs
    back). A sequence step ``d`` of 1 is normal; ``d > 1`` means ``d - 1`` lost
    samples; ``d <= 0`` is a backstep (the board repeated or restarted).
    """

    def __init__(self) -> None:
        self._last_raw: np.ndarray | None = None    # (4,) uint32 raw words of the last sample
        self._last_full: np.ndarray | None = None   # (4,) int64 unwrapped values of the last sample
        self.lost = 0
        self.backsteps = 0

    def update(self, samples: np.ndarray) -> Unwrapped:
        """Unwrap a :data:`DATA_DTYPE` array (as returned by :meth:`FrameDecoder.feed_samples`)."""
        n = samples.shape[0]
        if n == 0:
            e = np.empty(0, dtype=np.int64)
            return Unwrapped(e, np.empty(0), e, e, 0, 0)
        words = np.empty((n + 1, 4), dtype=np.uint32)
        words[1:] = samples.view(_COUNTERS_DTYPE)["c"]
        last_raw, last_full = self._last_raw, self._last_full     # both set once a block was seen
        first_block = last_raw is None or last_full is None
        if last_raw is None or last_full is None:
            words[0] = words[1]
            last_full = np.array([int(samples["seq"][0]), int(samples["t_us"][0]),
                                  int(samples["enc"][0]), int(samples["scale"][0])], dtype=np.int64)
        else:
            words[0] = last_raw
        du = words[1:] - words[:-1]                        # uint32 arithmetic: steps modulo 2^32
        d = du.view(np.int32).astype(np.int64)             # as int32 (seq, enc, scale)
        d[:, 1] = du[:, 1]                                 # time: unsigned
        steps = d[:, 0]
        if first_block:
            steps = steps.copy()
            steps[0] = 1                                   # nothing precedes the very first sample
        full = np.cumsum(d, axis=0)
        full += last_full
        if steps.min() >= 1:
            lost, back = int(steps.sum()) - n, 0
        else:
            lost = int(np.sum(steps[steps > 1] - 1))
            back = int(np.count_nonzero(steps <= 0))
        self.lost += lost
        self.backsteps += back
        self._last_raw, self._last_full = words[-1].copy(), full[-1].copy()
        return Unwrapped(full[:, 0], full[:, 1] * 1e-6, full[:, 2], full[:, 3], lost, back)

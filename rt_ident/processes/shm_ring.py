"""A single-producer, single-consumer message ring in shared memory.

The real-time loop hands samples to the recorder, decimated blocks to the
telemetry process and snapshots to the fit process. ``multiprocessing.Queue``
does that with a *feeder thread* in the producer's process: every ``put``
wakes it, it pickles and writes to a pipe, and it competes with the loop for
the GIL and (inheriting SCHED_FIFO and the loop's CPU) for the CPU: in the
loop (1 kHz, 34 samples per tick) the three queues cost 45-250 us per tick and
single puts up to 5 ms (docs/measurements.md). This ring has no thread, no
lock and no system call on either side: ``put`` copies the arrays into shared memory and then
advances a write counter; the consumer polls the counter, copies out, and
advances a read counter. A full ring makes ``put`` return False at once; the
caller decides to drop (telemetry) or wait (recording).

Memory: ``multiprocessing`` ``RawArray``s of the helpers' context (an unlinked file
mapped in both processes: nothing is left in ``/dev/shm`` when a process is
killed). The objects are handed to the child as ``Process`` arguments. Once the
parent lets go of a ring, ``multiprocessing`` hands the same memory to the next
ring it makes; a helper still running on the old one (its parent's object gone
without closing it) would then read and advance another ring's counters. So each
ring writes a random token into its header and both sides check it before they
touch the ring: a side whose token is no longer there raises :class:`RingReused`.

Ordering: the producer writes the data, then the counter; the consumer reads
the counter, then the data. That relies on stores becoming visible in program
order, which x86-64 guarantees (total store order). Weakly ordered CPUs
(aarch64) give no such guarantee for plain stores; see :data:`STRONG_ORDERING`.

Message format (frames start 16-byte aligned, fields 8-byte aligned): ``int64 length`` (bytes of the
whole frame; ``-1`` marks "wrapped: continue at offset 0"), ``int64 n_fields``,
then per field a 16-byte ASCII key, ``int64 dtype code``, ``int64 count`` and
the data padded to 8 bytes. A message maps field names to 1-D arrays of
float64, int64 or uint8 (the latter for pickled objects, see
:meth:`MessageRing.put_object`).
"""

from __future__ import annotations

import mmap
import os
import pickle
import platform
import struct
from collections.abc import Mapping
from typing import Any

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from rt_ident.errors import ConfigError, DataError
from rt_ident.processes.context import helper_context

__all__ = ["MessageRing", "RingReused", "STRONG_ORDERING", "key_words", "consumer_waits", "put_rows", "put_seq_floats",
           "put_sums"]

#: True where plain stores are seen by other cores in program order (x86-64 / i686).
STRONG_ORDERING: bool = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")

_DTYPES: tuple[np.dtype, ...] = (np.dtype(np.float64), np.dtype(np.int64), np.dtype(np.uint8))
_CODE = {dt: i for i, dt in enumerate(_DTYPES)}
_HEAD = struct.Struct("<qq")                 # frame length, number of fields
_FIELD = struct.Struct("<16sqq")             # key, dtype code, count
_WRAP = -1
_OBJECT_KEY = "__pickle__"

# header slots (int64): written by the producer ...
_W_POS, _W_MSGS, _W_CLOSED = 0, 1, 2
# ... at creation: whose memory this is
_TOKEN = 3
# ... and by the consumer
_R_POS, _R_MSGS, _R_FLAG = 4, 5, 6
_HEADER_SLOTS = 8


class RingReused(DataError):
    """This side's ring memory now belongs to another ring (see the module docstring)."""


def _pad8(n: int) -> int:
    return (n + 7) & ~7


def _pad16(n: int) -> int:
    return (n + 15) & ~15


class MessageRing:
    """SPSC ring of messages (``dict[str, 1-D array]``) in shared memory.

    capacity_bytes : size of the data area (rounded up to a multiple of 8)
    max_messages : at most this many unread messages (a second limit besides the bytes)
    ctx : multiprocessing context whose ``RawArray`` allocates the memory
        (default: :func:`~rt_ident.processes.context.helper_context`)

    Exactly one process calls the producer methods (:meth:`put`, :meth:`put_object`,
    :meth:`close_writer`) and one the consumer methods (:meth:`get`, :meth:`get_object`,
    :attr:`flag` setter). Pass the ring itself to the child process as an argument.
    """

    def __init__(self, capacity_bytes: int, *, max_messages: int = 1 << 30, ctx: Any = None) -> None:
        if isinstance(capacity_bytes, bool) or not isinstance(capacity_bytes, int) or capacity_bytes < 1024:
            raise ConfigError("capacity_bytes", f"must be an integer >= 1024, got {capacity_bytes!r}")
        if isinstance(max_messages, bool) or not isinstance(max_messages, int) or max_messages < 1:
            raise ConfigError("max_messages", f"must be an integer >= 1, got {max_messages!r}")
        ctx = ctx if ctx is not None else helper_context()
        self.capacity = _pad16(capacity_bytes)
        self.max_messages = max_messages
        self._header = ctx.RawArray("q", _HEADER_SLOTS)
        self._data = ctx.RawArray("b", self.capacity)
        self._token = int.from_bytes(os.urandom(8), "little") >> 1 | 1
        self._header[_TOKEN] = self._token
        self._bind()

    def _bind(self) -> None:
        self._mv = memoryview(self._data).cast("B")
        self._buf = np.frombuffer(self._mv, dtype=np.uint8)
        # typed views of the same bytes, indexed by dtype code (fields are 8-byte aligned)
        self._views = tuple(np.frombuffer(self._mv, dtype=dt) for dt in _DTYPES)
        self._keys: dict[str, bytes] = {}
        self._h = self._header
        self._compiled = (np.frombuffer(self._header, dtype=np.int64), self._views[1], self._views[0])

    def __getstate__(self) -> dict[str, Any]:
        return {"capacity": self.capacity, "max_messages": self.max_messages,
                "header": self._header, "data": self._data, "token": self._token}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.capacity = state["capacity"]
        self.max_messages = state["max_messages"]
        self._header = state["header"]
        self._data = state["data"]
        self._token = state["token"]
        self._bind()
        # Map every page of the ring now (a read per page). Otherwise the child process's resident
        # set grows by a page each time the ring's position first reaches one (a fit process by 8 MB
        # as its two 4-MB rings fill), which reads as a leak in a soak although it stops at the rings'
        # size. The pages exist already (RawArray zeroes
        # them in the parent), so this allocates nothing; it also spares the child those faults.
        int(self._buf[::mmap.PAGESIZE].sum())

    # ------------------------------------------------------------ both sides
    def _mine(self) -> None:
        """Raise :class:`RingReused` when the memory holds another ring's token now."""
        if self._h[_TOKEN] != self._token:
            raise RingReused("this ring's shared memory was given to another ring (the side that made it "
                             "let go of it): stopping instead of touching it")

    @property
    def pending_messages(self) -> int:
        """Messages written and not yet consumed."""
        h = self._h
        return h[_W_MSGS] - h[_R_MSGS]

    @property
    def messages_read(self) -> int:
        """Messages consumed since the ring was made."""
        return int(self._h[_R_MSGS])

    @property
    def messages_written(self) -> int:
        """Messages written since the ring was made."""
        return int(self._h[_W_MSGS])

    @property
    def used_bytes(self) -> int:
        h = self._h
        return h[_W_POS] - h[_R_POS]

    @property
    def writer_closed(self) -> bool:
        return bool(self._h[_W_CLOSED])

    @property
    def flag(self) -> int:
        """A value the consumer publishes to the producer (e.g. "ready for the next one")."""
        return self._h[_R_FLAG]

    @flag.setter
    def flag(self, value: int) -> None:
        self._mine()
        self._h[_R_FLAG] = int(value)

    # --------------------------------------------------------------- producer
    def put(self, fields: Mapping[str, Any]) -> bool:
        """Copy one message into the ring. False (nothing written) if it does not fit now.

        Values are 1-D arrays (or anything ``np.asarray`` makes one of); float64, int64 and
        uint8 keep their type, other numeric types become float64. Raises
        :class:`DataError` for a message that could never fit, a key longer than 16 ASCII
        bytes, or non-numeric data.
        """
        h = self._h
        self._mine()
        if h[_W_CLOSED]:
            raise DataError("MessageRing.put(): the writer side is closed")
        items = []
        size = _HEAD.size
        keys = self._keys
        for key, a in fields.items():
            if type(a) is not np.ndarray or a.ndim != 1 or not a.flags.c_contiguous:
                a = np.ascontiguousarray(a).reshape(-1)
            code = _CODE.get(a.dtype)
            if code is None:
                if a.dtype.kind not in "fiub":
                    raise DataError(f"MessageRing.put(): field {key!r} has dtype {a.dtype}")
                a, code = a.astype(np.float64), 0
            k = keys.get(key)
            if k is None:
                k = key.encode("ascii")
                if len(k) > 16:
                    raise DataError(f"MessageRing.put(): key {key!r} longer than 16 bytes")
                keys[key] = k
            items.append((k, code, a))
            size += _FIELD.size + _pad8(a.nbytes)
        size = _pad16(size)          # so that a 16-byte wrap marker always fits before the end
        cap = self.capacity
        if size > cap // 2:
            raise DataError(f"MessageRing.put(): a {size}-byte message does not fit a {cap}-byte ring")
        if h[_W_MSGS] - h[_R_MSGS] >= self.max_messages:
            return False
        w = h[_W_POS]
        pos = w % cap
        skip = cap - pos if pos + size > cap else 0
        if cap - (w - h[_R_POS]) < skip + size:
            return False
        mv = self._mv
        if skip:
            _HEAD.pack_into(mv, pos, _WRAP, 0)
            w += skip
            pos = 0
        _HEAD.pack_into(mv, pos, size, len(items))
        off = pos + _HEAD.size
        views = self._views
        for k, code, a in items:
            n = a.shape[0]
            _FIELD.pack_into(mv, off, k, code, n)
            off += _FIELD.size
            if code == 2:
                views[2][off:off + n] = a
                off += _pad8(n)
            else:
                o = off >> 3
                views[code][o:o + n] = a
                off += 8 * n
        # publish: data first, then the counters (see the module docstring on ordering)
        self._mine()
        h[_W_POS] = w + size
        h[_W_MSGS] = h[_W_MSGS] + 1
        return True

    def put_object(self, obj: Any) -> bool:
        """Pickle ``obj`` into one message (for rare, irregular payloads). False if it does not fit now."""
        raw = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        return self.put({_OBJECT_KEY: np.frombuffer(raw, dtype=np.uint8)})

    def compiled_views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The header and the data area as int64 and float64 arrays, for :func:`put_seq_floats`
        (the producer side of a compiled caller; the same memory :meth:`put` writes)."""
        return self._compiled

    def close_writer(self) -> None:
        """Tell the consumer that nothing more will come (it drains what is there, then stops)."""
        self._mine()
        self._h[_W_CLOSED] = 1

    # --------------------------------------------------------------- consumer
    def get(self, max_messages: int | None = None) -> list[dict[str, np.ndarray]]:
        """Copy out and consume up to ``max_messages`` messages (all pending by default)."""
        h = self._h
        self._mine()
        w = h[_W_POS]
        n_avail = h[_W_MSGS] - h[_R_MSGS]
        if max_messages is not None:
            n_avail = min(n_avail, max_messages)
        r = h[_R_POS]
        cap, mv, buf = self.capacity, self._mv, self._buf
        out: list[dict[str, np.ndarray]] = []
        while len(out) < n_avail and r < w:
            pos = r % cap
            size, n_fields = _HEAD.unpack_from(mv, pos)
            if size == _WRAP:
                r += cap - pos
                continue
            off = pos + _HEAD.size
            msg: dict[str, np.ndarray] = {}
            for _ in range(n_fields):
                k, code, count = _FIELD.unpack_from(mv, off)
                off += _FIELD.size
                dt = _DTYPES[code]
                nb = count * dt.itemsize
                msg[k.rstrip(b"\0").decode("ascii")] = buf[off:off + nb].view(dt).copy()
                off += _pad8(nb)
            out.append(msg)
            r += size
        if out:
            self._mine()
            h[_R_POS] = r
            h[_R_MSGS] = h[_R_MSGS] + len(out)
        return out

    @staticmethod
    def is_object(msg: Mapping[str, np.ndarray]) -> bool:
        """Whether ``msg`` was sent with :meth:`put_object`."""
        return _OBJECT_KEY in msg

    @staticmethod
    def unpickle(msg: Mapping[str, np.ndarray]) -> Any:
        """The object of a :meth:`put_object` message."""
        return pickle.loads(msg[_OBJECT_KEY].tobytes())

    def get_object(self) -> tuple[bool, Any]:
        """Consume one message sent with :meth:`put_object`: ``(True, obj)``, or ``(False, None)`` if none."""
        msgs = self.get(1)
        if not msgs:
            return False, None
        return True, self.unpickle(msgs[0])


# ---------------------------------------------------------------- a compiled producer
def key_words(key: str) -> np.ndarray:
    """A field key as the two int64 words a frame stores it in (16 ASCII bytes, zero padded)."""
    k = key.encode("ascii")
    if len(k) > 16:
        raise DataError(f"key {key!r} longer than 16 bytes")
    return np.frombuffer(k.ljust(16, b"\0"), dtype="<i8").copy()


@intrinsic
def _release_fence(typingctx):  # noqa: ARG001 - numba's intrinsic signature
    """A release fence: the stores before it are not moved after it by the compiler (x86-64 needs no
    instruction for it: total store order; see the module docstring on ordering)."""
    def codegen(context, builder, signature, args):  # noqa: ARG001 - numba's codegen signature
        builder.fence("release")
        return context.get_dummy_value()
    return types.none(), codegen


@numba.njit(cache=True)
def _reserve(h, di, cap, max_messages, size):
    """Room in the ring for a frame of ``size`` bytes (a multiple of 16), as :meth:`MessageRing.put`
    makes it: ``(1, w, p)`` with the write position ``w`` (past a wrap marker, written when the frame
    does not fit before the end) and the frame's first int64 word ``p``; ``(0, 0, 0)`` when it does not
    fit now (ring or message count full), ``(-1, 0, 0)`` when it never can (over half the ring)."""
    if size > cap // 2:
        return -1, 0, 0
    if h[_W_MSGS] - h[_R_MSGS] >= max_messages:
        return 0, 0, 0
    w = h[_W_POS]
    pos = w % cap
    skip = cap - pos if pos + size > cap else 0
    if cap - (w - h[_R_POS]) < skip + size:
        return 0, 0, 0
    if skip:
        di[pos >> 3] = _WRAP
        di[(pos >> 3) + 1] = 0
        w += skip
        pos = 0
    return 1, w, pos >> 3


@numba.njit(cache=True)
def _commit(h, w, size):
    """Publish the frame written at ``w``: its data first (a release fence), then the counters."""
    _release_fence()  # type: ignore[call-arg]  # an intrinsic: numba passes typingctx itself
    h[_W_POS] = w + size
    h[_W_MSGS] = h[_W_MSGS] + 1


@numba.njit(cache=True)
def put_seq_floats(h, di, df, cap, max_messages, keys, seq, c0, c1, c2, c3, c4, ncols) -> int:
    """:meth:`MessageRing.put` of ``{key0: seq, key1: concatenate(c0 .. c<ncols-1>)}`` (int64 ``seq``,
    float64 columns of its length, ``keys`` the four words of :func:`key_words` of both keys), compiled:
    the same frame, byte for byte. ``h``, ``di``, ``df``: :meth:`MessageRing.compiled_views`; ``cap`` the
    ring's capacity in bytes. Returns 1 when written, 0 when it does not fit now, -1 when it never can
    (the caller then goes through :meth:`MessageRing.put`, which says why)."""
    n = seq.shape[0]
    size = 16 + 32 + 8 * n + 32 + 8 * ncols * n
    size = (size + 15) & ~15
    ok, w, p = _reserve(h, di, cap, max_messages, size)
    if ok != 1:
        return ok
    di[p] = size
    di[p + 1] = 2
    di[p + 2] = keys[0]
    di[p + 3] = keys[1]
    di[p + 4] = 1                       # int64
    di[p + 5] = n
    for i in range(n):
        di[p + 6 + i] = seq[i]
    q = p + 6 + n
    di[q] = keys[2]
    di[q + 1] = keys[3]
    di[q + 2] = 0                       # float64
    di[q + 3] = ncols * n
    o = q + 4
    for j in range(ncols):
        c = c0 if j == 0 else c1 if j == 1 else c2 if j == 2 else c3 if j == 3 else c4
        for i in range(n):
            df[o + i] = c[i]
        o += n
    _commit(h, w, size)
    return 1


@numba.njit(cache=True)
def put_rows(h, di, df, cap, max_messages, keys, index, rows, n, tail_keys, tail_id, tail_values, tail) -> int:
    """:meth:`MessageRing.put` of ``{key_i: rows[index[i], :n]}`` (float64; ``keys`` two words a key, from
    :func:`key_words`), followed, when ``tail``, by ``{tail_key0: [tail_id] (int64), tail_key1:
    tail_values (float64)}``, compiled: the same frame, byte for byte. Returns as :func:`put_seq_floats`."""
    m = index.shape[0]
    nv = tail_values.shape[0]
    size = 16 + m * (32 + 8 * n)
    if tail:
        size += 32 + 8 + 32 + 8 * nv
    size = (size + 15) & ~15
    ok, w, p = _reserve(h, di, cap, max_messages, size)
    if ok != 1:
        return ok
    di[p] = size
    di[p + 1] = m + 2 if tail else m
    q = p + 2
    for i in range(m):
        di[q] = keys[2 * i]
        di[q + 1] = keys[2 * i + 1]
        di[q + 2] = 0                   # float64
        di[q + 3] = n
        r = index[i]
        for j in range(n):
            df[q + 4 + j] = rows[r, j]
        q += 4 + n
    if tail:
        di[q] = tail_keys[0]
        di[q + 1] = tail_keys[1]
        di[q + 2] = 1                   # int64
        di[q + 3] = 1
        di[q + 4] = tail_id
        q += 5
        di[q] = tail_keys[2]
        di[q + 1] = tail_keys[3]
        di[q + 2] = 0
        di[q + 3] = nv
        for j in range(nv):
            df[q + 4 + j] = tail_values[j]
    _commit(h, w, size)
    return 1


@numba.njit(cache=True)
def put_sums(h, di, df, cap, max_messages, keys, harmonics, S1, S2, quantum, scalars, codec, codec_len) -> int:
    """:meth:`MessageRing.put` of a streaming estimator's running sums as
    :meth:`rt_ident.estimators.spectra.SpectraSums.to_fields` lays them out, with the codec field the
    fit process decodes them by (``{harmonics, sums, quantum, scalars, codec}``; ``keys`` their ten words,
    ``codec`` the name's bytes as int64 words, ``codec_len`` its length), compiled. Returns as
    :func:`put_seq_floats`. The codec field's padding bytes are zeros here (MessageRing.put leaves what
    was in the ring); nobody reads them."""
    H = harmonics.shape[0]
    ns = 2 * (S1.shape[0] + S2.shape[0])
    nq, nsc = quantum.shape[0], scalars.shape[0]
    size = 16 + (32 + 8 * H) + (32 + 8 * ns) + (32 + 8 * nq) + (32 + 8 * nsc) + (32 + ((codec_len + 7) & ~7))
    size = (size + 15) & ~15
    ok, w, p = _reserve(h, di, cap, max_messages, size)
    if ok != 1:
        return ok
    di[p] = size
    di[p + 1] = 5
    q = p + 2
    di[q], di[q + 1], di[q + 2], di[q + 3] = keys[0], keys[1], 1, H          # harmonics: int64
    for i in range(H):
        di[q + 4 + i] = harmonics[i]
    q += 4 + H
    di[q], di[q + 1], di[q + 2], di[q + 3] = keys[2], keys[3], 0, ns         # sums: S1 then S2, re and im
    o = q + 4
    for i in range(S1.shape[0]):
        df[o] = S1[i].real
        df[o + 1] = S1[i].imag
        o += 2
    for i in range(S2.shape[0]):
        df[o] = S2[i].real
        df[o + 1] = S2[i].imag
        o += 2
    q = o
    di[q], di[q + 1], di[q + 2], di[q + 3] = keys[4], keys[5], 0, nq         # quantum
    for i in range(nq):
        df[q + 4 + i] = quantum[i]
    q += 4 + nq
    di[q], di[q + 1], di[q + 2], di[q + 3] = keys[6], keys[7], 0, nsc        # scalars
    for i in range(nsc):
        df[q + 4 + i] = scalars[i]
    q += 4 + nsc
    di[q], di[q + 1], di[q + 2], di[q + 3] = keys[8], keys[9], 2, codec_len  # codec: uint8
    for i in range((codec_len + 7) >> 3):
        di[q + 4 + i] = codec[i]
    _commit(h, w, size)
    return 1


@numba.njit(cache=True)
def consumer_waits(h) -> bool:
    """The consumer says it waits for a message (its flag) and none is pending (rt_ident.processes.jobs's
    ``JobProcess.ready``), compiled."""
    return h[_R_FLAG] != 0 and h[_W_MSGS] - h[_R_MSGS] == 0

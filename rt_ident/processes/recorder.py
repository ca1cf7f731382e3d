"""Crash-safe raw-sample recordings: write (Recorder, RecorderProcess) and read (read_recording).

On-disk layout of a recording named ``run.parquet`` (the "documented equivalent" of appending
row groups to one Parquet file):

* ``run.parquet.arrows`` - the crash-safe journal: an Arrow IPC *stream*
  (``pyarrow.ipc.new_stream``) written through an unbuffered file, one record batch per flush. The
  schema message (which carries the metadata) precedes the first batch. After ``kill -9`` every
  batch whose bytes reached the OS is intact; a batch cut short by the kill is detected by the
  reader (truncated message) and discarded whole, so no partial row is ever returned.
* ``run.parquet.part`` - the same batches appended as one Parquet row group per flush with
  ``pyarrow.parquet.ParquetWriter``. It has no footer until ``close()``, so it is never read.
* ``run.parquet`` - appears only on ``close()``: the footer is written to ``.part``, which is then
  atomically renamed (``os.replace``), and the journal is deleted. "``run.parquet`` exists"
  therefore means "complete"; otherwise :func:`read_recording` recovers from the journal.

Columns: ``t`` [s] float64, ``seq`` int64, ``theta1``, ``theta2`` [rad], ``torque_cmd`` [N m],
``torque_meas`` [N m] (NaN where the hardware has no measured torque). The caller's metadata is
stored as JSON under the schema key ``rt_ident.metadata`` in both files, so it is recoverable from
the journal without any Parquet footer.

:class:`RecorderProcess` runs a :class:`Recorder` in a separate process fed through a
shared-memory ring, so compression and disk I/O never share the real-time loop's GIL.
Reading (Parquet, journal, CSV) lives in :mod:`rt_ident.outputs.recording_reader`; ``Recording`` and
``read_recording`` are re-exported here.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.errors import ConfigError, DataError, RtIdentError
from rt_ident.outputs.recording_reader import (
    COLUMNS,
    FORMAT_KEY,
    FORMAT_VERSION,
    METADATA_KEY,
    Recording,
    journal_path,
    part_path,
    read_recording,
)
from rt_ident.processes.context import helper_context
from rt_ident.processes.guard import become_helper, end_helper, quick_exit, start_ignoring_signals
from rt_ident.processes.shm_ring import MessageRing, RingReused

log = logging.getLogger(__name__)

__all__ = ["Recorder", "RecorderProcess", "Recording", "read_recording", "journal_path", "part_path"]


def _json_default(obj: Any) -> Any:
    if is_dataclass(obj) and not isinstance(obj, type):
        return asdict(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def encode_metadata(metadata: Mapping[str, Any]) -> bytes:
    """JSON-encode the caller's metadata (dataclasses, numpy values and paths allowed)."""
    if not isinstance(metadata, Mapping):
        raise ConfigError("metadata", f"must be a mapping, got {type(metadata).__name__}")
    try:
        return json.dumps(dict(metadata), default=_json_default, allow_nan=True).encode()
    except (TypeError, ValueError) as e:
        raise ConfigError("metadata", f"cannot be stored as JSON: {e}") from e


def _schema(metadata_json: bytes) -> Any:
    import pyarrow as pa

    fields: list[tuple[str, pa.DataType]] = [("t", pa.float64()), ("seq", pa.int64())]
    fields += [(name, pa.float64()) for name in COLUMNS[2:]]
    return pa.schema(fields, metadata={METADATA_KEY: metadata_json, FORMAT_KEY: FORMAT_VERSION})


class Recorder:
    """Append raw samples in memory; write them to disk at most every ``flush_interval`` seconds.

    ``append`` only copies arrays into a list (cheap); ``flush`` turns the buffer into one Arrow
    record batch, appends it to the journal (crash-safe) and as one row group to the Parquet part
    file. ``close`` finalizes ``path`` (see the module docstring) and is idempotent. The
    constructor does no I/O; the files are created by ``open()`` (called by ``__enter__`` and by
    the first flush). An existing recording is never overwritten unless ``overwrite=True``.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        metadata: Mapping[str, Any],
        flush_interval: float = 0.5,
        *,
        overwrite: bool = False,
        fsync: bool = False,
    ) -> None:
        if not math.isfinite(flush_interval) or flush_interval <= 0.0:
            raise ConfigError("flush_interval", f"must be a positive number of seconds, got {flush_interval!r}")
        self.path = Path(path)
        if self.path.suffix != ".parquet":
            raise ConfigError("path", f"a recording must end in .parquet, got {self.path.name!r}")
        self.flush_interval = float(flush_interval)
        self.overwrite = overwrite
        self.fsync = fsync
        self._metadata_json = encode_metadata(metadata)
        self._buffer: list[tuple[np.ndarray, ...]] = []
        self._buffered_rows = 0
        self._rows_written = 0
        self._last_flush: float | None = None
        self._journal_file: Any = None
        self._journal: Any = None
        self._parquet: Any = None
        self._schema: Any = None
        self._closed = False

    @property
    def rows_written(self) -> int:
        """Rows on disk (flushed); buffered rows are not counted."""
        return self._rows_written

    @property
    def closed(self) -> bool:
        return self._closed

    def open(self) -> None:
        """Create the journal and the Parquet part file (no-op if already open)."""
        if self._journal is not None:
            return
        if self._closed:
            raise RtIdentError(f"recorder for {self.path} is closed")
        import pyarrow.ipc as ipc
        import pyarrow.parquet as pq

        jpath, ppath = journal_path(self.path), part_path(self.path)
        for p in (self.path, jpath):
            if p.exists() and not self.overwrite:
                raise ConfigError("path", f"{p} already exists (pass overwrite=True to replace it)")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            self.path.unlink()
        self._schema = _schema(self._metadata_json)
        # Unbuffered: every batch goes to the OS in the write() calls of write_batch, so a
        # kill -9 after a flush loses nothing that flush wrote.
        self._journal_file = open(jpath, "wb", buffering=0)  # noqa: SIM115 - closed in close()
        self._journal = ipc.new_stream(self._journal_file, self._schema)
        self._parquet = pq.ParquetWriter(ppath, self._schema, compression="zstd")
        log.info("recording to %s (journal %s)", self.path, jpath.name)

    def append(
        self,
        t: Any,
        seq: Any,
        theta1: Any,
        theta2: Any,
        torque_cmd: Any,
        torque_meas: Any | None = None,
    ) -> None:
        """Buffer one block of samples (1-D arrays of one length; ``torque_meas=None`` -> NaN)."""
        if self._closed:
            raise RtIdentError(f"append() on closed recorder for {self.path}")
        cols = [np.array(t, dtype=np.float64, ndmin=1), np.array(seq, dtype=np.int64, ndmin=1)]
        cols += [np.array(x, dtype=np.float64, ndmin=1) for x in (theta1, theta2, torque_cmd)]
        n = cols[0].shape[0]
        cols.append(
            np.full(n, np.nan) if torque_meas is None else np.array(torque_meas, dtype=np.float64, ndmin=1)
        )
        for name, c in zip(COLUMNS, cols):
            if c.ndim != 1 or c.shape[0] != n:
                raise DataError(f"append(): {name!r} has shape {c.shape}, expected ({n},) like 't'")
        if n:
            self._buffer.append(tuple(cols))
            self._buffered_rows += n

    def flush_if_due(self, now: float) -> bool:
        """Flush when ``flush_interval`` has passed since the last flush (``now`` from any clock)."""
        if self._last_flush is None:
            self._last_flush = now
            return False
        if now - self._last_flush < self.flush_interval:
            return False
        self._last_flush = now
        return self.flush()

    def flush(self) -> bool:
        """Write the buffered rows (one journal batch + one Parquet row group). True if rows written."""
        if not self._buffer:
            return False
        import pyarrow as pa

        self.open()
        cols = [np.concatenate([b[i] for b in self._buffer]) for i in range(len(COLUMNS))]
        batch = pa.record_batch([pa.array(c) for c in cols], schema=self._schema)
        journaled = False
        try:
            self._journal.write_batch(batch)  # the crash-safe copy first
            if self.fsync:
                os.fsync(self._journal_file.fileno())
            journaled = True
            self._parquet.write_table(pa.Table.from_batches([batch]), row_group_size=batch.num_rows)
        except BaseException:
            if journaled:                     # on disk in the journal, which is the recording from now on
                self._written_out(batch.num_rows)
            self._stop_writing()
            raise
        self._written_out(batch.num_rows)
        return True

    def _written_out(self, rows: int) -> None:
        self._rows_written += rows
        self._buffer.clear()
        self._buffered_rows = 0

    def close(self) -> None:
        """Flush, finalize ``path`` and delete the journal. Safe to call twice."""
        if self._closed:
            return
        try:
            self.flush()
            if self._parquet is None:  # nothing was ever written: still leave a valid empty file
                self.open()
            self._parquet.close()
            os.replace(part_path(self.path), self.path)
            self._journal.close()
            self._journal_file.close()
            journal_path(self.path).unlink(missing_ok=True)
            log.info("recording %s closed: %d rows", self.path, self._rows_written)
        except BaseException:
            self._stop_writing()
            raise
        finally:
            self._closed = True

    def _stop_writing(self) -> None:
        """After a failed write or close: the journal, as far as it was written, is the recording. Nothing
        more is written to it (a batch after one cut short by a full disk would be read as that batch's
        body), and the footerless ``.part``, which no reader opens, is deleted to give its space back.
        The Parquet writer is closed here, where its failure is expected, and not by the garbage
        collector, which would print the same error (a full disk) again as a traceback."""
        self._closed = True
        writer, self._parquet = self._parquet, None
        if writer is not None:
            try:
                writer.close()
            except OSError:
                writer.is_open = False      # what pyarrow's __del__ checks before closing again
        part_path(self.path).unlink(missing_ok=True)
        journal, self._journal_file = self._journal_file, None
        self._journal = None                # its stream is not closed: that would append an end marker
        if journal is not None:
            journal.close()

    def __enter__(self) -> Recorder:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _block_message(block: Any) -> dict[str, np.ndarray]:
    """A SampleBlock or a mapping as one ring message: ``seq`` (int64) and ``floats``, the float
    columns of ``COLUMNS`` back to back (``torque_meas`` left out when None). Two fields instead of
    six: each field of a message is a few microseconds of the loop's tick (:func:`_message_columns`
    undoes it in the recorder)."""
    # a dict or another mapping, else a SampleBlock (checked in this order: for a SampleBlock, typing's
    # isinstance(block, Mapping) alone cost microseconds of the tick)
    if isinstance(block, dict) or (not hasattr(block, "seq") and isinstance(block, Mapping)):
        get = block.get
    else:
        def get(name: str, _d: Any = None) -> Any:
            return (getattr(block, name, None))
    seq = get("seq", None)
    if seq is None:
        raise DataError("RecorderProcess.put(): block has no 'seq'")
    seq = np.asarray(seq, dtype=np.int64)
    parts = []
    for name in _FLOAT_COLUMNS:
        v = get(name, None)
        if v is None:
            if name != COLUMNS[-1]:
                raise DataError(f"RecorderProcess.put(): block has no {name!r}")
            continue
        a = np.asarray(v, dtype=np.float64)
        if a.shape != seq.shape:  # checked here so that a bad block fails in the caller, not in the recorder
            raise DataError(f"RecorderProcess.put(): {name!r} has shape {a.shape}, 'seq' has {seq.shape}")
        parts.append(a)
    return {"seq": seq, "floats": np.concatenate(parts)}


_FLOAT_COLUMNS = tuple(c for c in COLUMNS if c != "seq")


def _message_columns(m: Mapping[str, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(t, seq, theta1, theta2, torque_cmd, torque_meas or None) of a :func:`_block_message`."""
    seq = m["seq"]
    f = m["floats"].reshape(-1, seq.shape[0]) if seq.shape[0] else np.empty((len(_FLOAT_COLUMNS) - 1, 0))
    return f[0], seq, f[1], f[2], f[3], (f[4] if f.shape[0] > 4 else None)


def _os_reason(exc: OSError, path: str) -> str:
    import errno as _errno

    where = exc.filename or path
    if exc.errno == _errno.ENOSPC:
        return f"{where}: no space left on the device (ENOSPC); recording stopped"
    return f"{where}: {exc.strerror or exc} ({_errno.errorcode.get(exc.errno or 0, 'OSError')}); recording stopped"


def _recorder_main(
    path: str,
    metadata_json: bytes,
    flush_interval: float,
    overwrite: bool,
    ring: MessageRing,
    rows_written: Any,
    failed: Any,
    ready: Any = None,
    reason: Any = None,
) -> None:
    """Body of the recorder process: drain the ring, flush on time, finish when the writer closes
    or the parent dies (kill -9: the file is then finished from every sample the ring holds).

    A failure is reported to the parent in one line (``reason``): for an OS error (a full disk,
    a file that cannot be written) the file and the cause, without a traceback."""
    watch = become_helper()
    rec = Recorder(path, json.loads(metadata_json), flush_interval, overwrite=overwrite)
    poll = min(0.02, flush_interval / 4.0)
    try:
        rec.open()
        if ready is not None:
            ready.value = 1
        while True:
            # read before draining: nothing can follow a close (or the writer's death)
            closed = ring.writer_closed or watch.gone
            msgs = ring.get()
            for m in msgs:
                rec.append(*_message_columns(m))
            if rec.flush_if_due(time.monotonic()):
                rows_written.value = rec.rows_written
            if closed and not msgs:
                break
            if not msgs:
                time.sleep(poll)
        rec.close()
        rows_written.value = rec.rows_written
        if watch.gone:
            log.warning("recorder: the run's main process died; %s finished with %d rows", path, rec.rows_written)
    except OSError as exc:                       # a full disk, a file that cannot be written
        why = _os_reason(exc, path)
        log.info("recorder: %s", why)          # the parent names it in the run's stop (one line)
        _end_failed(rec, why, failed, reason)
        rows_written.value = rec.rows_written    # with the rows of a batch only the journal took
        raise SystemExit(1) from None
    except RingReused as exc:                    # its parent let go of the ring: nothing more can come
        _end_failed(rec, str(exc), failed, reason)
        rows_written.value = rec.rows_written
        log.warning("recorder: %s; %s finished with %d rows", exc, path, rec.rows_written)
        raise SystemExit(1) from None
    except BaseException as exc:
        if reason is not None:
            reason.value = f"{type(exc).__name__}: {exc}".encode("utf-8", "replace")[: len(reason) - 1]
        failed.value = 1
        log.exception("recorder process for %s failed", path)
        try:
            rec.close()  # keep whatever was buffered
        except Exception:  # noqa: BLE001 - already failing; the journal holds the flushed rows
            log.exception("recorder close after failure")
        raise


def _end_failed(rec: Recorder, why: str, failed: Any, reason: Any) -> None:
    """A failure the parent reports in one line: its reason and the flag set, whatever can still be
    written kept."""
    if reason is not None:
        reason.value = why.encode("utf-8", "replace")[: len(reason) - 1]
    failed.value = 1
    try:
        rec.close()
    except Exception:  # noqa: BLE001 - already failing; the journal holds the flushed rows
        pass


def _recorder_process(*args: Any) -> None:
    """The recorder process: :func:`_recorder_main`, then out at once once the file is closed (a
    failure takes the usual way out, with its exit code)."""
    _recorder_main(*args)
    quick_exit()


class RecorderProcess:
    """A :class:`Recorder` in its own process, fed by ``put(block)`` from the real-time loop.

    Blocks travel through a shared-memory :class:`~rt_ident.processes.shm_ring.MessageRing` (no feeder
    thread, no pickling, no system call in the loop). ``queue_size`` bounds the blocks in
    flight and ``ring_bytes`` the bytes: the defaults (65536 blocks, 64 MiB) hold > 30 s at
    34 k samples/s (~50 bytes per sample) and > 6 s at 200 k samples/s: far longer than the
    recorder's flushes take. A full ring is a recorder a whole ring behind (its disk or its
    process stalled): ``put`` then waits at most ``put_timeout`` seconds (default 0: the caller is the
    real-time loop, which a wait would stall with the device under its last torque; counted in
    ``full_waits``) and raises :class:`RtIdentError`, as it does when the recorder process has
    failed or died. The samples of a block it refused are counted (``samples_refused``): the
    recording is then not complete. The recorder flushes every ``flush_interval`` (<= 1 s) seconds.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        metadata: Mapping[str, Any],
        queue_size: int = 65536,
        *,
        ring_bytes: int = 64 << 20,
        flush_interval: float = 0.5,
        put_timeout: float = 0.0,
        overwrite: bool = False,
    ) -> None:
        if not 0.0 < flush_interval <= 1.0:
            raise ConfigError("flush_interval", f"must be in (0, 1] s, got {flush_interval!r}")
        if queue_size < 1:
            raise ConfigError("queue_size", f"must be >= 1, got {queue_size!r}")
        if ring_bytes < 1 << 16:
            raise ConfigError("ring_bytes", f"must be >= 65536, got {ring_bytes!r}")
        self.path = Path(path)
        self._metadata_json = encode_metadata(metadata)
        self.flush_interval = float(flush_interval)
        self.put_timeout = float(put_timeout)
        self.overwrite = overwrite
        self.queue_size = int(queue_size)
        self.ring_bytes = int(ring_bytes)
        self._ctx: Any = None        # helper_context(), at start(): the constructor starts no process
        self._ring: MessageRing | None = None
        self._proc: Any = None
        self._rows_written: Any = None
        self._failed: Any = None
        self._ready: Any = None
        self._reason: Any = None
        self.full_waits = 0
        self.samples_refused = 0
        self.refusal: str | None = None            # why the first block was refused
        # blocks and samples handed over, in place: the compiled tick (rt_ident.loop.tick_core),
        # which puts into the ring itself, counts into a view of it
        self.put_counts = np.zeros(2, dtype=np.int64)
        self._last_alive_check = -math.inf
        self._exited = False
        self._closed = False

    def start(self) -> RecorderProcess:
        if self._proc is not None:
            return self
        self._ctx = helper_context()
        self._ring = MessageRing(self.ring_bytes, max_messages=self.queue_size, ctx=self._ctx)
        # Lock-free: one writer (the child); a child killed while holding a lock would hang us.
        self._rows_written = self._ctx.Value("q", 0, lock=False)
        self._failed = self._ctx.Value("b", 0, lock=False)
        self._ready = self._ctx.Value("b", 0, lock=False)
        self._reason = self._ctx.Array("c", 512, lock=False)
        self._proc = self._ctx.Process(
            target=_recorder_process,
            args=(str(self.path), self._metadata_json, self.flush_interval, self.overwrite,
                  self._ring, self._rows_written, self._failed, self._ready, self._reason),
            name="rt_ident-recorder",
            daemon=True,
        )
        start_ignoring_signals(self._proc)
        return self

    blocks_put = property(lambda self: int(self.put_counts[0]))
    samples_put = property(lambda self: int(self.put_counts[1]))

    def compiled_target(self) -> tuple[MessageRing, np.ndarray] | None:
        """For a compiled producer (rt_ident.loop.tick_core, which writes :meth:`put`'s message with
        rt_ident.processes.shm_ring.put_seq_floats and counts into ``put_counts``): the ring and the
        counters, or None before :meth:`start` or after :meth:`close`. A full ring or a dead recorder
        stay the Python :meth:`put`'s (and :meth:`check_alive`'s) to handle."""
        if self._ring is None or self._closed:
            return None
        return self._ring, self.put_counts

    def check_alive(self) -> None:
        """Raise :class:`RtIdentError` if the recorder process is gone (rate-limited, as in :meth:`put`)."""
        self._check_alive()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def failure(self) -> str | None:
        """The recorder's own one-line reason for failing (None while it works)."""
        if self._reason is None or not self._reason.value:
            return None
        return self._reason.value.decode("utf-8", "replace")

    def wait_ready(self, timeout: float = 30.0) -> None:
        """Block (before the device is enabled) until the recorder has created its files; raise
        :class:`RtIdentError` with the recorder's reason if it could not."""
        end = time.monotonic() + timeout
        while not self._ready.value:
            if self._failed.value or self._proc.exitcode is not None:
                self._proc.join(1.0)
                raise RtIdentError(self.failure or f"recorder for {self.path} exited ({self._proc.exitcode})")
            if time.monotonic() > end:
                raise RtIdentError(f"recorder for {self.path} did not open its files within {timeout:g} s")
            time.sleep(0.01)

    @property
    def rows_written(self) -> int:
        """Rows the recorder process has flushed to disk so far."""
        return 0 if self._rows_written is None else int(self._rows_written.value)

    def _check_alive(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_alive_check >= 0.1:  # waitpid() at most 10x per second
            self._last_alive_check = now
            self._exited = self._proc.exitcode is not None
        if self._failed.value or self._exited:
            if self.failure:
                raise RtIdentError(self.failure)
            raise RtIdentError(
                f"recorder process for {self.path} is not running (exitcode {self._proc.exitcode}); "
                "samples can no longer be recorded"
            )

    def put(self, block: Any) -> None:
        """Hand one block (``SampleBlock`` or mapping with the recording columns) to the recorder."""
        cols = _block_message(block)
        if self._closed or self._ring is None:
            raise RtIdentError("RecorderProcess.put(): not started or already closed")
        try:
            self._check_alive()
            if not self._ring.put(cols):
                self._wait_for_room(cols)
        except RtIdentError as exc:
            self.samples_refused += len(cols["seq"])
            self.refusal = self.refusal or str(exc)
            raise
        self.put_counts[0] += 1
        self.put_counts[1] += len(cols["seq"])

    def _wait_for_room(self, cols: Mapping[str, Any]) -> None:
        assert self._ring is not None
        self.full_waits += 1
        behind = (f"{self._ring.pending_messages} blocks, {self._ring.used_bytes / 2**20:.0f} MiB not yet "
                  "written")
        deadline = time.monotonic() + self.put_timeout
        while not self._ring.put(cols):
            self._check_alive(force=True)
            if time.monotonic() >= deadline:
                raise RtIdentError(f"the recorder of {self.path} fell a whole ring behind ({behind}): its disk "
                                   "or its process stalled; recording stopped")
            time.sleep(1e-4)

    def close(self, timeout: float = 10.0) -> dict[str, Any]:
        """Let the recorder drain the ring, finalize the file and join. Terminates it after ``timeout``."""
        summary: dict[str, Any] = {"path": str(self.path), "blocks_put": self.blocks_put,
                                   "samples_put": self.samples_put, "samples_refused": self.samples_refused,
                                   "refusal": self.refusal, "full_waits": self.full_waits, "terminated": False}
        if self._proc is None or self._ring is None or self._closed:     # (started: both)
            self._closed = True
            summary.update(rows_written=self.rows_written, exitcode=getattr(self._proc, "exitcode", None))
            summary["complete"] = self._complete(summary)
            return summary
        self._closed = True
        self._ring.close_writer()
        self._proc.join(timeout)
        if self._proc.is_alive():
            log.error("recorder process did not finish within %.1f s; terminating", timeout)
            end_helper(self._proc, 2.0)     # born ignoring SIGTERM: SIGKILL after 2 s (the journal keeps the rows)
            summary["terminated"] = True
        summary.update(rows_written=self.rows_written, exitcode=self._proc.exitcode, failure=self.failure)
        summary["complete"] = self._complete(summary)
        if not summary["complete"]:
            log.info("recording %s is incomplete: %d of %d samples written (recorder exit code %s)",
                      self.path, summary["rows_written"], self.samples_put, summary["exitcode"])
        return summary

    def _complete(self, summary: Mapping[str, Any]) -> bool:
        """Every sample the loop had for it is in the finished file, and the recorder exited cleanly."""
        return (summary.get("exitcode") == 0 and not summary.get("terminated") and not self.samples_refused
                and summary.get("rows_written") == self.samples_put and self.path.exists())

    def __enter__(self) -> RecorderProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

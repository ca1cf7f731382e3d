"""``rt-ident fleet identify``: every recording of a manifest identified as one Dask task, results appended
to a Parquet history partitioned by machine.

* One task per recording (:func:`identify_recording`): it hashes the file (SHA-256 of its bytes, read in
  1 MiB pieces) and returns at once when the hash is already in the history; otherwise it identifies the
  recording with :func:`rt_ident.reports.identify.identify_file` (a recording made by ``rt-ident run`` is
  replayed through the loop's streaming estimator in record batches: memory does not grow with length).
  A remote recording (an fsspec URL) is copied to the worker's temporary folder first.
* A task never raises: a bad recording comes back as a row with ``status = "failed"`` and its error, and the
  others go on. Failed rows are reported, not stored (a fixed file is identified on the next run). A local
  recording must be a regular file (a device such as ``/dev/zero`` or a pipe would be read forever); a
  task that runs longer than its timeout comes back failed ("timed out") and the run goes on.
* Results are written as they arrive, at least every ``flush_every`` seconds, and on Ctrl-C, SIGTERM or SIGHUP
  before the run ends; each write takes the history's lock and drops the rows whose recording (content
  hash) the history already holds, so concurrent runs and a recording listed twice give one row each
  (:mod:`rt_ident.fleet.store`: the lock, the atomic writes).
* Every stored row carries its verdict: ``trusted``, ``reasons`` (why not, in words) and ``trust_criteria``
  (JSON: each criterion with its value, limit and result). Drift uses trusted rows only.
* The cluster: the scheduler the user names (``--scheduler tcp://host:8786``), else a ``LocalCluster`` of
  ``workers`` single-threaded processes bound to 127.0.0.1, its dashboard on 127.0.0.1 (a free port) -
  nothing listens beyond this host unless the user points at a cluster.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import queue
import shutil
import signal
import stat
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_ident import __version__
from rt_ident.errors import DataError
from rt_ident.fleet.manifest import Entry
from rt_ident.fleet.store import HashIndex, history_lock, write_rows
from rt_ident.outputs.recording_reader import journal_path
from rt_ident.processes.guard import install_stop_signals, stop_signals

if TYPE_CHECKING:
    import pyarrow as pa

log = logging.getLogger(__name__)

PARAMS = ("I1", "I2", "B", "K", "wn", "wd", "zeta")
_CHUNK = 1 << 20
#: seconds a task may run before it is reported as timed out
TASK_TIMEOUT = 600.0
#: seconds between writes of finished results
FLUSH_EVERY = 2.0
_STOP_POLL_S = 0.05          # the longest a stop request waits for the run to see it


def _hash_local(path: str, stop: threading.Event) -> str:
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        journal = journal_path(path)
        if path.endswith(".parquet") and journal.is_file():
            raise DataError(f"not closed: only its journal {journal.name} is there (a run that crashed, or one still "
                            f"recording); list {journal.name} in the manifest to identify what it flushed") from None
        raise DataError("no such file") from None
    if not stat.S_ISREG(mode):                        # a device or pipe would be read forever
        raise ValueError(f"{path} is not a regular file")
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for piece in iter(lambda: fh.read(_CHUNK), b""):
            if stop.is_set():                          # the task timed out: stop reading
                raise TimeoutError(path)
            h.update(piece)
    return h.hexdigest()


def _fetch(url: str, folder: str, stop: threading.Event) -> tuple[str, str]:
    """Copy an fsspec URL to ``folder``; returns (local path, hash of the bytes)."""
    import fsspec

    h = hashlib.sha256()
    local = os.path.join(folder, os.path.basename(url.rstrip("/")) or "recording")
    with fsspec.open(url, "rb") as src, open(local, "wb") as dst:
        for piece in iter(lambda: src.read(_CHUNK), b""):
            if stop.is_set():
                raise TimeoutError(url)
            h.update(piece)
            dst.write(piece)
    return local, h.hexdigest()


def identify_recording(entry: dict[str, Any], known: frozenset[str] = frozenset(),
                       method: str | None = None, timeout: float | None = None) -> dict[str, Any]:
    """One recording -> one history row (runs on a worker; never raises).

    ``entry``: ``path, machine, axis, time`` (time as a timezone-aware datetime). ``status`` is ``ok``,
    ``skipped`` (its hash is in ``known``) or ``failed`` (``error`` says why). With ``timeout`` (seconds)
    the work runs in a thread of its own and the task returns ``failed`` ("timed out") when it has not
    finished by then. Hashing or copying the file stops then; the identification itself cannot be
    stopped: its thread ends with its work or its process.
    """
    stop = threading.Event()
    if not timeout:
        return _identify(entry, known, method, stop)
    box: dict[str, dict[str, Any]] = {}
    worker = threading.Thread(target=lambda: box.update(row=_identify(entry, known, method, stop)), daemon=True,
                              name=f"identify {os.path.basename(str(entry.get('path')))}")
    worker.start()
    worker.join(timeout)
    if "row" in box:
        return box["row"]
    stop.set()
    return {**_blank_row(entry, method), "status": "failed",
            "error": f"timed out after {timeout:g} s (--task-timeout); the recording is left unidentified"}


def _blank_row(entry: dict[str, Any], method: str | None) -> dict[str, Any]:
    return {**entry, "hash": None, "method": method, "version": __version__, "samples": None, "trusted": None,
            "reasons": None, "trust_criteria": None, "status": "ok", "error": None}


def _identify(entry: dict[str, Any], known: frozenset[str], method: str | None,
              stop: threading.Event) -> dict[str, Any]:
    from rt_ident.reports.identify import identify_file

    row = _blank_row(entry, method)
    tmp = None
    try:
        path = entry["path"]
        if "://" in path and not path.startswith("file://"):
            tmp = tempfile.mkdtemp(prefix="rt-ident-fleet-")
            local, digest = _fetch(path, tmp, stop)
        else:
            local = path[len("file://"):] if path.startswith("file://") else path
            digest = _hash_local(local, stop)
        row["hash"] = digest
        if digest in known:
            row["status"] = "skipped"
            return row
        ident, info = identify_file(local, method)
        d = ident.as_dict()
        row["method"] = d["method"]
        row["samples"] = int(info["samples"])
        trust = d.get("trust") or {}
        row["trusted"] = bool(d["trusted"]) and bool(trust.get("criteria"))   # no criteria: never trusted
        row["reasons"] = [str(w) for w in trust.get("reasons") or ([] if row["trusted"] else ["no criteria stated"])]
        row["trust_criteria"] = json.dumps(trust.get("criteria") or [], default=float)
        for k in PARAMS:
            row[k] = d["parameters"].get(k)
            lo, hi = (d["ci95"] or {}).get(k) or (None, None)
            row[f"{k}_lo"], row[f"{k}_hi"] = lo, hi
        diag = d.get("diagnostics") or {}
        row["fit_chi2_dof"] = diag.get("chi2_dof")
        row["snr_median_db"] = diag.get("snr_median_db")
    except Exception as exc:  # noqa: BLE001 - a bad recording is a result, not the end of the fleet
        row["status"] = "failed"
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return row


def _schema() -> pa.Schema:
    import pyarrow as pa

    fields: list[tuple[str, pa.DataType]] = [
        ("path", pa.string()), ("machine", pa.string()), ("axis", pa.string()),
        ("time", pa.timestamp("us", tz="UTC")), ("hash", pa.string()), ("method", pa.string()),
        ("version", pa.string()), ("samples", pa.int64()), ("trusted", pa.bool_()),
        ("reasons", pa.list_(pa.string())), ("trust_criteria", pa.string())]
    for k in PARAMS:
        fields += [(k, pa.float64()), (f"{k}_lo", pa.float64()), (f"{k}_hi", pa.float64())]
    fields += [("fit_chi2_dof", pa.float64()), ("snr_median_db", pa.float64())]
    return pa.schema(fields)


def append_history(history: str | Path, rows: list[dict[str, Any]], index: HashIndex | None = None) -> int:
    """Write the ``ok`` rows of ``rows`` to the Parquet dataset under ``history`` (hive-partitioned by
    machine); returns how many were written. Under the history's lock, rows whose recording (hash) the
    history already holds with a verdict are dropped, and so are repeats within ``rows``: one row per
    recording, whoever writes at the same time. Each file appears whole (temporary name, renamed); nothing
    written before is rewritten. ``index``: the caller's :class:`~rt_ident.fleet.store.HashIndex` of
    this history (kept up to date), to read each file once over many calls."""
    return len(_append(history, rows, index or HashIndex(history)))


def _append(history: str | Path, rows: list[dict[str, Any]], index: HashIndex) -> list[dict[str, Any]]:
    """:func:`append_history`; returns the rows written."""
    import pyarrow as pa

    ok = [r for r in rows if r.get("status") == "ok"]
    if not ok:
        return []
    with history_lock(history):
        stored = set(index.refresh())
        fresh = []
        for r in ok:
            if r["hash"] not in stored:
                stored.add(r["hash"])
                fresh.append(r)
        if not fresh:
            return []
        schema = _schema()
        table = pa.Table.from_pylist([{f.name: r.get(f.name) for f in schema} for r in fresh], schema=schema)
        index.add(write_rows(history, table), [r["hash"] for r in fresh])
    return fresh


def known_hashes(history: str | Path) -> frozenset[str]:
    """Hashes already identified *with a recorded verdict*: a row from before verdicts were recorded is
    identified again (a new row; :func:`rt_ident.fleet.drift.series` prefers it)."""
    return HashIndex(history).refresh()


class _Cluster:
    """A Dask client: on ``scheduler`` if given, else on a LocalCluster confined to 127.0.0.1."""

    def __init__(self, scheduler: str | None, workers: int) -> None:
        from distributed import Client, LocalCluster

        self.cluster = None
        if scheduler:
            self.client = Client(scheduler, timeout="20s")
        else:
            # the scheduler runs in this process: its INFO lines (addresses, workers coming and going) are
            # not the user's business unless they ask (-v); warnings still show
            logging.getLogger("distributed").setLevel(max(logging.WARNING, logging.getLogger().level))
            # processes, one thread each: numba kernels and numpy hold the GIL for whole recordings
            try:
                with _children_ignore_ctrl_c():
                    # the workers' own log lines stay quiet: a task's failure is reported per recording here, and
                    # a worker losing its scheduler while the cluster closes after Ctrl-C logs an ERROR with a
                    # traceback
                    self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                                silence_logs=logging.CRITICAL)
                self.client = Client(self.cluster)
            except BaseException:                # Ctrl-C or a failure before the client: nothing was submitted
                if self.cluster is not None:
                    self.cluster.close()
                raise
        self.dashboard = self.client.dashboard_link if self._has_dashboard() else None

    def _has_dashboard(self) -> bool:
        try:
            import bokeh  # noqa: F401 - the dashboard needs it
        except ImportError:
            return False
        return True

    def close(self) -> None:
        # the results are in hand: what the scheduler says while it and its workers go down is noise
        if self.cluster is not None:
            logging.getLogger("distributed").setLevel(logging.CRITICAL)
        self.client.close()
        if self.cluster is not None:
            # a worker still running a timed-out or interrupted task is killed after a grace period;
            # distributed's warning about it says nothing the run's result does not
            nanny = logging.getLogger("distributed.nanny")
            level = nanny.level
            nanny.setLevel(max(logging.ERROR, level))
            try:
                self.cluster.close()
            finally:
                nanny.setLevel(level)


@contextmanager
def _children_ignore_ctrl_c() -> Iterator[None]:
    """SIGINT and SIGHUP ignored while the LocalCluster starts its worker processes, which inherit that: Ctrl-C
    in a terminal (or its closing) reaches the whole process group, and only this process is to handle it (it
    ends the run and the cluster). A Ctrl-C during those seconds is lost (blocking it in this thread would not
    hold it: a thread that libraries imported before had started takes it, and ignores it)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def identify_fleet(entries: Iterable[Entry], history: str | Path, *, scheduler: str | None = None,
                   workers: int = 2, method: str | None = None, flush_every: float = FLUSH_EVERY,
                   task_timeout: float | None = TASK_TIMEOUT,
                   on_start: Callable[[int, str | None], None] | None = None,
                   on_result: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Identify every entry on Dask; append new results to ``history``. Returns counts and failures.

    ``on_start(n_tasks, dashboard_url)`` once the cluster is up; ``on_result(row)`` per finished task
    (progress). Finished results are written at least every ``flush_every`` seconds and when the run is
    interrupted (Ctrl-C, or SIGTERM or SIGHUP in the main thread): then ``interrupted`` is True and what finished is
    in the history. ``task_timeout`` (seconds; None or 0: none) per task. An entry listed twice (same
    path) is run once (``duplicates``); a row another run wrote meanwhile counts as ``skipped``. A write
    the history refuses (a full disk, no permission) ends the run: ``write_error`` says why, ``unwritten``
    counts the results it could not keep; what was written before stays.
    """
    items: list[dict[str, Any]] = []
    paths: set[str] = set()
    duplicates = 0
    for e in entries:
        if e.path in paths:
            duplicates += 1
            continue
        paths.add(e.path)
        items.append({"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time})
    index = HashIndex(history)
    known = index.refresh()
    counts = {"tasks": len(items), "identified": 0, "untrusted": 0, "skipped": 0, "failed": 0,
              "duplicates": duplicates, "unwritten": 0}
    write_error: list[str] = []                   # why the history refused a write (the run then ends)
    failures: list[dict[str, Any]] = []
    pending: list[dict[str, Any]] = []
    oldest = 0.0                                  # when the oldest unwritten result arrived

    def write() -> list[dict[str, Any]] | None:
        """The rows written; None once the history has refused a write (the run then ends)."""
        if write_error:
            return None
        try:
            return _append(history, pending, index)
        except OSError as exc:
            write_error.append(f"{exc.filename or history}: {exc.strerror or exc}")
            stop.set()
            return None

    def flush() -> None:
        with _signals_deferred():
            written = write()
            if written is None:
                counts["unwritten"] += len(pending)
            else:
                counts["identified"] += len(written)
                counts["untrusted"] += sum(not r["trusted"] for r in written)
                counts["skipped"] += len(pending) - len(written)      # another run (or another path) had it
            pending.clear()

    def take(fut: Any) -> None:
        nonlocal oldest
        row = _result(fut, futures[fut.key])
        status = row["status"]
        if status == "failed":
            counts["failed"] += 1
            failures.append({"path": row["path"], "machine": row["machine"], "axis": row["axis"],
                             "error": row["error"]})
        elif status == "skipped":
            counts["skipped"] += 1
        else:
            if not pending:
                oldest = time.monotonic()
            pending.append(row)
        if on_result is not None:
            on_result(row)

    interrupted = False
    done: queue.Queue[Any] = queue.Queue()       # futures, as they finish (filled from Dask's thread)
    futures: dict[Any, dict[str, Any]] = {}      # Dask key -> its entry
    cluster = _Cluster(scheduler, workers)
    # the run checks the flag between results: no KeyboardInterrupt lands inside a Dask call
    stop = threading.Event()
    old_signals = install_stop_signals(stop)
    try:
        try:
            if on_start is not None:
                on_start(len(items), cluster.dashboard)
            client = cluster.client
            # one copy per worker of the known hashes (a list of one: scatter splits a collection into elements)
            seen = client.scatter([known], broadcast=True)[0] if known else known
            for it in items:
                fut = client.submit(identify_recording, it, seen, method, task_timeout or None, pure=False)
                futures[fut.key] = it
                fut.add_done_callback(done.put)
            left = len(futures)
            while left and not stop.is_set():
                wait = oldest + flush_every - time.monotonic() if pending else flush_every
                try:
                    take(done.get(timeout=min(max(wait, 0.01), _STOP_POLL_S)))
                    left -= 1
                except queue.Empty:
                    pass
                if pending and time.monotonic() - oldest >= flush_every:
                    flush()
        except KeyboardInterrupt:                 # from a callback, or a signal held through a write
            stop.set()
        if stop.is_set():
            interrupted = not write_error
            while not done.empty():               # what finished before the interrupt is kept too
                take(done.get_nowait())
        try:
            flush()
        except KeyboardInterrupt:                 # during the last write, which finished first
            interrupted = True
    finally:
        try:
            with _signals_deferred():             # a close cut short leaves workers to distributed's exit hooks
                cluster.close()
        except KeyboardInterrupt:
            interrupted = True
        for sig, handler in old_signals.items():
            signal.signal(sig, handler)
    return {**counts, "interrupted": interrupted, "write_error": write_error[0] if write_error else None,
            "failures": failures, "history": str(history),
            "dashboard": cluster.dashboard, "scheduler": scheduler or "LocalCluster on 127.0.0.1"}


def _result(fut: Any, item: dict[str, Any]) -> dict[str, Any]:
    """A finished future's row; a task lost with its worker (or cancelled) is a failed row."""
    try:
        row = fut.result()
    except Exception as exc:  # noqa: BLE001 - KilledWorker, CancelledError ...: this recording failed
        row = {**_blank_row(item, None), "status": "failed", "error": f"{type(exc).__name__}: {exc}"}
    fut.release()
    return row


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Ctrl-C, SIGTERM and SIGHUP during a write take effect once it is done (as KeyboardInterrupt): a write is
    never cut between its files and the count of what it wrote."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []

    def note(signum: int, frame: Any) -> None:  # noqa: ARG001
        got.append(signum)

    old = {sig: signal.signal(sig, note) for sig in stop_signals()}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if got:
        raise KeyboardInterrupt


__all__ = ["FLUSH_EVERY", "PARAMS", "TASK_TIMEOUT", "append_history", "identify_fleet", "identify_recording",
           "known_hashes"]

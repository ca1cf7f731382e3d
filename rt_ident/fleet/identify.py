"""``rt-ident fleet identify``: every recording of a manifest identified as one Dask task, results appended
to a Parquet history partitioned by machine.

* One task per recording (:func:`identify_recording`): it hashes the file (SHA-256 of its bytes, read in
  1 MiB pieces) and returns at once when the hash is already in the history; otherwise it identifies the
  recording with :func:`rt_ident.reports.identify.identify_file` (a recording made by ``rt-ident run`` is
  replayed through the loop's streaming estimator in record batches: memory does not grow with length).
  A remote recording (an fsspec URL) is copied to the worker's temporary folder first.
* A task never raises: a bad recording comes back as a row with ``status = "failed"`` and its error, and the
  others go on. Failed rows are reported, not stored (a fixed file is identified on the next run). A local
  recording must be a regular file (a device such as ``/dev/zero`` or a pipe would be read forever).
* Each write takes the history's lock and drops the rows whose recording (content hash) the history
  already holds, so concurrent runs and a recording listed twice give one row each
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
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_ident import __version__
from rt_ident.fleet.manifest import Entry
from rt_ident.fleet.store import HashIndex, history_lock, write_rows

if TYPE_CHECKING:
    import pyarrow as pa

log = logging.getLogger(__name__)

PARAMS = ("I1", "I2", "B", "K", "wn", "wd", "zeta")
_CHUNK = 1 << 20


def _hash_local(path: str) -> str:
    if not stat.S_ISREG(os.stat(path).st_mode):       # a device or pipe would be read forever
        raise ValueError(f"{path} is not a regular file")
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for piece in iter(lambda: fh.read(_CHUNK), b""):
            h.update(piece)
    return h.hexdigest()


def _fetch(url: str, folder: str) -> tuple[str, str]:
    """Copy an fsspec URL to ``folder``; returns (local path, hash of the bytes)."""
    import fsspec

    h = hashlib.sha256()
    local = os.path.join(folder, os.path.basename(url.rstrip("/")) or "recording")
    with fsspec.open(url, "rb") as src, open(local, "wb") as dst:
        for piece in iter(lambda: src.read(_CHUNK), b""):
            h.update(piece)
            dst.write(piece)
    return local, h.hexdigest()


def identify_recording(entry: dict[str, Any], known: frozenset[str] = frozenset(),
                       method: str | None = None) -> dict[str, Any]:
    """One recording -> one history row (runs on a worker; never raises).

    ``entry``: ``path, machine, axis, time`` (time as a timezone-aware datetime). ``status`` is ``ok``,
    ``skipped`` (its hash is in ``known``) or ``failed`` (``error`` says why).
    """
    from rt_ident.reports.identify import identify_file

    row: dict[str, Any] = {**entry, "hash": None, "method": method, "version": __version__,
                           "samples": None, "trusted": None, "reasons": None, "trust_criteria": None,
                           "status": "ok", "error": None}
    tmp = None
    try:
        path = entry["path"]
        if "://" in path and not path.startswith("file://"):
            tmp = tempfile.mkdtemp(prefix="rt-ident-fleet-")
            local, digest = _fetch(path, tmp)
        else:
            local = path[len("file://"):] if path.startswith("file://") else path
            digest = _hash_local(local)
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
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                        host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                        silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        self.dashboard = self.client.dashboard_link if self._has_dashboard() else None

    def _has_dashboard(self) -> bool:
        try:
            import bokeh  # noqa: F401 - the dashboard needs it
        except ImportError:
            return False
        return True

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def identify_fleet(entries: Iterable[Entry], history: str | Path, *, scheduler: str | None = None,
                   workers: int = 2, method: str | None = None,
                   on_start: Callable[[int, str | None], None] | None = None,
                   on_result: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Identify every entry on Dask; append new results to ``history``. Returns counts and failures.

    ``on_start(n_tasks, dashboard_url)`` once the cluster is up; ``on_result(row)`` per finished task
    (progress). Results are appended as they arrive, in batches, so an interrupted run keeps what it did.
    An entry listed twice (same path) is run once (``duplicates``); a row another run wrote meanwhile
    counts as ``skipped``.
    """
    from distributed import as_completed

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
              "duplicates": duplicates}
    failures: list[dict[str, Any]] = []
    batch: list[dict[str, Any]] = []

    def flush() -> None:
        written = _append(history, batch, index)
        counts["identified"] += len(written)
        counts["untrusted"] += sum(not r["trusted"] for r in written)
        counts["skipped"] += len(batch) - len(written)      # another run (or another path) had it
        batch.clear()

    cluster = _Cluster(scheduler, workers)
    try:
        if on_start is not None:
            on_start(len(items), cluster.dashboard)
        client = cluster.client
        # one copy per worker of the known hashes (a list of one: scatter splits a collection into elements)
        seen = client.scatter([known], broadcast=True)[0] if known else known
        futures = [client.submit(identify_recording, it, seen, method, pure=False) for it in items]
        for fut in as_completed(futures):
            row = fut.result()
            fut.release()
            status = row["status"]
            if status == "failed":
                counts["failed"] += 1
                failures.append({"path": row["path"], "machine": row["machine"], "axis": row["axis"],
                                 "error": row["error"]})
            elif status == "skipped":
                counts["skipped"] += 1
            else:
                batch.append(row)
                if len(batch) >= 64:
                    flush()
            if on_result is not None:
                on_result(row)
        flush()
    finally:
        cluster.close()
    return {**counts, "failures": failures, "history": str(history), "dashboard": cluster.dashboard,
            "scheduler": scheduler or "LocalCluster on 127.0.0.1"}


__all__ = ["identify_recording", "identify_fleet", "append_history", "known_hashes", "PARAMS"]

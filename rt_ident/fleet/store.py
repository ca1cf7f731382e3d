"""The history's files: where they are, which can be read, how new ones are written.

The history is a folder, or an fsspec URL (``s3://bucket/fleet``) the installed filesystems understand.
It holds Parquet files ``machine=<name, URL-quoted>/batch-<uuid>.parquet`` (hive partitioning).

* :func:`parquet_files` lists them; a file whose footer cannot be read (truncated, not Parquet) is
  :func:`damaged` and left out by :func:`usable_files` with one warning naming it.
* :func:`write_rows` writes each batch to a hidden temporary name in its partition folder, fsyncs it and
  renames it into place (``os.replace``; on object storage the upload appears whole): a reader never
  sees half a file.
* :func:`history_lock` serializes writers: an exclusive ``flock`` on ``<history>/.rt-ident.lock``; for a
  URL history, on a lock file in this host's temporary folder (it covers the runs of this host only).
* :class:`HashIndex` knows which recordings (content hashes) the history holds with a verdict, reading
  each file's ``hash`` column once.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote, unquote

from rt_ident.errors import ConfigError

if TYPE_CHECKING:
    import pyarrow as pa
    from fsspec import AbstractFileSystem

log = logging.getLogger(__name__)

LOCK_NAME = ".rt-ident.lock"
PARTITION = "machine"


def is_url(history: str | Path) -> bool:
    return "://" in str(history)


def filesystem(history: str | Path) -> tuple[AbstractFileSystem | None, str]:
    """(fsspec filesystem or None for a local folder, root): a local root is absolute and resolved."""
    if is_url(history):
        import fsspec

        fs, root = fsspec.core.url_to_fs(str(history))
        return fs, root.rstrip("/")
    return None, str(Path(history).resolve())


def parquet_files(history: str | Path) -> list[str]:
    """Every ``*.parquet`` file under the history (not hidden ones: those are writes in progress), sorted."""
    fs, root = filesystem(history)
    if fs is None:
        base = Path(root)
        if not base.is_dir():
            return []
        found = [str(p) for p in base.rglob("*.parquet") if p.is_file() and not p.name.startswith(".")]
    else:
        if not fs.exists(root):
            return []
        found = [f for f in fs.glob(root + "/**/*.parquet") if not f.rsplit("/", 1)[-1].startswith(".")]
    return sorted(found)


def damaged(path: str, fs: AbstractFileSystem | None = None) -> str | None:
    """Why ``path`` cannot be read as Parquet (its footer and schema), or None when it can."""
    import pyarrow.parquet as pq

    try:
        if fs is None:
            pq.read_metadata(path)
        else:
            with fs.open(path, "rb") as fh:
                pq.read_metadata(fh)
    except Exception as exc:  # noqa: BLE001 - pyarrow raises ArrowInvalid, OSError ...: all mean unreadable
        return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return None


def warn_damaged(path: str, why: str) -> None:
    log.warning("skipped damaged history file %s (%s)", path, why)


def usable_files(history: str | Path) -> list[str]:
    """:func:`parquet_files` without the damaged ones (each named in one warning)."""
    fs, _ = filesystem(history)
    good = []
    for f in parquet_files(history):
        why = damaged(f, fs)
        if why is None:
            good.append(f)
        else:
            warn_damaged(f, why)
    return good


def partition_value(path: str) -> str | None:
    """The machine of a file ``…/machine=<quoted>/…`` (None if not partitioned so)."""
    for part in reversed(path.replace("\\", "/").split("/")[:-1]):
        if part.startswith(PARTITION + "="):
            return unquote(part[len(PARTITION) + 1:])
    return None


def read_table(history: str | Path, files: list[str]) -> pa.Table:
    """The rows of ``files`` as one Arrow table, ``machine`` from each file's partition folder; files
    with fewer columns (older ones) get NULL in the columns they lack."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    fs, _ = filesystem(history)
    tables = []
    for f in files:
        t = pq.read_table(f, filesystem=fs)
        machine = partition_value(f)
        if machine is not None and PARTITION not in t.column_names:
            t = t.append_column(PARTITION, pa.array([machine] * t.num_rows, pa.string()))
        tables.append(t)
    return pa.concat_tables(tables, promote_options="default")


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_local(folder: Path, table: pa.Table) -> str:
    import pyarrow.parquet as pq

    folder.mkdir(parents=True, exist_ok=True)
    final = folder / f"batch-{uuid.uuid4().hex}.parquet"
    tmp = folder / f".{final.name}.tmp"
    try:
        with open(tmp, "wb") as fh:
            pq.write_table(table, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(folder)           # the rename itself survives a power loss
    return str(final)


def _write_fs(fs: AbstractFileSystem, folder: str, table: pa.Table) -> str:
    import pyarrow.parquet as pq

    fs.makedirs(folder, exist_ok=True)
    final = f"{folder}/batch-{uuid.uuid4().hex}.parquet"
    tmp = f"{folder}/.{final.rsplit('/', 1)[-1]}.tmp"
    try:
        with fs.open(tmp, "wb") as fh:
            pq.write_table(table, fh)
        fs.mv(tmp, final)
    except BaseException:
        if fs.exists(tmp):
            fs.rm(tmp)
        raise
    return final


def write_rows(history: str | Path, table: pa.Table) -> list[str]:
    """Write ``table`` (with a ``machine`` column) under the history, one new file per machine, each
    renamed into place whole. Returns the files written."""
    import pyarrow as pa
    import pyarrow.compute as pc

    fs, root = filesystem(history)
    written = []
    for machine in sorted({str(m) for m in table.column(PARTITION).to_pylist()}):
        rows = table.filter(pc.equal(table.column(PARTITION), pa.scalar(machine))).drop_columns([PARTITION])
        sub = f"{PARTITION}={quote(machine, safe='')}"     # quoted: no name becomes a path
        if fs is None:
            written.append(_write_local(Path(root) / sub, rows))
        else:
            written.append(_write_fs(fs, f"{root}/{sub}", rows))
    return written


def _lock_file(history: str | Path) -> Path:
    fs, root = filesystem(history)
    if fs is None:
        Path(root).mkdir(parents=True, exist_ok=True)
        return Path(root) / LOCK_NAME
    key = hashlib.sha256(str(history).rstrip("/").encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"rt-ident-fleet-{key}.lock"


@contextmanager
def history_lock(history: str | Path, timeout: float = 120.0) -> Iterator[None]:
    """Hold the history's write lock (exclusive ``flock``), waiting at most ``timeout`` seconds for it."""
    path = _lock_file(history)
    # read-only is enough for flock, and lets another user share the lock file
    fd = os.open(path, os.O_RDONLY | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise ConfigError("--history", f"{history} stayed locked by another writer for {timeout:g} s "
                                                   f"(lock file {path})") from None
                time.sleep(0.02)
        yield
    finally:
        os.close(fd)             # releases the lock


class HashIndex:
    """The content hashes the history holds *with a recorded verdict* (``trusted`` and
    ``trust_criteria`` not NULL): a row from before verdicts were recorded does not count, so its
    recording is identified again. Each file is read once (its hash and verdict columns only);
    :meth:`refresh` reads the files added since."""

    def __init__(self, history: str | Path) -> None:
        self.history = history
        self.files: set[str] = set()
        self.hashes: set[str] = set()

    def refresh(self) -> frozenset[str]:
        import pyarrow.parquet as pq

        fs, _ = filesystem(self.history)
        for f in parquet_files(self.history):
            if f in self.files:
                continue
            self.files.add(f)
            try:
                pf = pq.ParquetFile(f, filesystem=fs)
                names = set(pf.schema_arrow.names)
                if not {"hash", "trusted", "trust_criteria"} <= names:
                    continue                        # written before verdicts: no row counts
                cols = pf.read(columns=["hash", "trusted", "trust_criteria"]).to_pydict()
            except Exception as exc:  # noqa: BLE001 - any read error: the file is damaged
                warn_damaged(f, (str(exc).strip().splitlines() or [type(exc).__name__])[0])
                continue
            self.hashes.update(h for h, t, c in zip(cols["hash"], cols["trusted"], cols["trust_criteria"])
                               if h is not None and t is not None and c is not None)
        return frozenset(self.hashes)

    def add(self, files: list[str], hashes: list[Any]) -> None:
        """Files this process wrote (not read again) and the hashes they hold."""
        self.files.update(files)
        self.hashes.update(h for h in hashes if h is not None)


__all__ = ["HashIndex", "damaged", "filesystem", "history_lock", "is_url", "parquet_files", "read_table",
           "usable_files", "write_rows"]

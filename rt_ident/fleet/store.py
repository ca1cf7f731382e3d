"""The history's files: where they are, which can be read.

The history is a folder, or an fsspec URL (``s3://bucket/fleet``) the installed filesystems understand.
It holds Parquet files ``machine=<name, URL-quoted>/batch-<uuid>.parquet`` (hive partitioning).

* :func:`parquet_files` lists them; a file whose footer cannot be read (truncated, not Parquet) is
  :func:`damaged` and left out by :func:`usable_files` with one warning naming it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import unquote

if TYPE_CHECKING:
    import pyarrow as pa
    from fsspec import AbstractFileSystem

log = logging.getLogger(__name__)

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


__all__ = ["damaged", "filesystem", "is_url", "parquet_files", "read_table", "usable_files"]

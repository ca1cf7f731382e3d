"""The fleet's history, queried with DuckDB straight over its Parquet files (no scans of our own).

The history is a local folder or any fsspec URL (``s3://bucket/fleet``: object storage, with the
filesystem installed, e.g. ``s3fs``); DuckDB reads a URL through the registered fsspec filesystem.

:func:`connect` gives an in-memory DuckDB connection with one view, ``history``: every row ever
identified (hive partition ``machine`` included), with its verdict (``trusted``, ``reasons``,
``trust_criteria`` as JSON). Files written before verdicts were recorded lack those columns: their
rows read as NULL there, an unknown verdict (:func:`verdict_sql`). ``rt-ident fleet query "SQL"`` runs
the user's SQL on it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_ident.errors import ConfigError

if TYPE_CHECKING:
    from duckdb import DuckDBPyConnection


def is_url(history: str | Path) -> bool:
    return "://" in str(history)


def has_history(history: str | Path) -> bool:
    """Whether ``history`` (a folder, or an fsspec URL: ``s3://bucket/fleet``) holds any Parquet file."""
    if is_url(history):
        import fsspec

        fs, root = fsspec.core.url_to_fs(str(history))
        return bool(fs.glob(root.rstrip("/") + "/**/*.parquet"))
    root = Path(history)
    return root.is_dir() and any(root.glob("**/*.parquet"))


def connect(history: str | Path) -> DuckDBPyConnection:
    import duckdb

    if not has_history(history):
        raise ConfigError("--history", f"{history} holds no fleet history (run `rt-ident fleet identify` first)")
    con = duckdb.connect(":memory:")
    if is_url(history):          # DuckDB reads it through the fsspec filesystem (s3fs, gcsfs ... installed)
        import fsspec

        con.register_filesystem(fsspec.core.url_to_fs(str(history))[0])
        pattern = str(history).rstrip("/") + "/**/*.parquet"
    else:
        pattern = str(Path(history) / "**" / "*.parquet")
    pattern = pattern.replace("'", "''")
    con.execute(f"CREATE VIEW history AS SELECT * FROM read_parquet('{pattern}', hive_partitioning = true, "
                "union_by_name = true)")
    return con


def columns(con: DuckDBPyConnection) -> set[str]:
    """The columns of the ``history`` view (an old history may lack the newer ones)."""
    return {r[0] for r in con.execute("DESCRIBE history").fetchall()}


def verdict_sql(cols: set[str]) -> str:
    """Select-list items ``trusted`` and ``has_verdict`` for a history with columns ``cols``: a row has a
    verdict when it records both ``trusted`` and the criteria behind it (``trust_criteria``); rows written
    before verdicts were recorded have NULL there (or no such column) and count as unknown, not trusted."""
    trusted = "trusted" if "trusted" in cols else "CAST(NULL AS BOOLEAN)"
    crit = "trust_criteria IS NOT NULL" if "trust_criteria" in cols else "FALSE"
    return f"{trusted} AS trusted, ({trusted} IS NOT NULL AND {crit}) AS has_verdict"


def query(history: str | Path, sql: str) -> tuple[list[str], list[tuple[Any, ...]]]:
    """Run ``sql`` against the ``history`` view; returns (column names, rows). Errors are one line."""
    import duckdb

    con = connect(history)
    try:
        cur = con.execute(sql)
    except duckdb.Error as exc:
        raise ConfigError("SQL", str(exc).splitlines()[0]) from None
    if cur.description is None:
        return [], []
    return [d[0] for d in cur.description], cur.fetchall()


__all__ = ["columns", "connect", "query", "verdict_sql"]

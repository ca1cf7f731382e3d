"""The fleet's history, queried with DuckDB straight over its Parquet files (no scans of our own).

:func:`connect` gives an in-memory DuckDB connection with one view, ``history``: every row ever
identified (hive partition ``machine`` included). ``rt-ident fleet query "SQL"`` runs the user's SQL on it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rt_ident.errors import ConfigError


def connect(history: str | Path):
    import duckdb

    root = Path(history)
    if not root.is_dir() or not any(root.glob("**/*.parquet")):
        raise ConfigError("--history", f"{root} holds no fleet history (run `rt-ident fleet identify` first)")
    con = duckdb.connect(":memory:")
    pattern = str(root / "**" / "*.parquet").replace("'", "''")
    con.execute(f"CREATE VIEW history AS SELECT * FROM read_parquet('{pattern}', hive_partitioning = true, "
                "union_by_name = true)")
    return con


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


__all__ = ["connect", "query"]

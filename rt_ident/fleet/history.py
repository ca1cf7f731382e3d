"""The fleet's history, queried with DuckDB straight over its Parquet files (no scans of our own).

The history is a local folder or any fsspec URL (``s3://bucket/fleet``: object storage, with the
filesystem installed, e.g. ``s3fs``); its files are listed by :mod:`rt_ident.fleet.store`, which leaves
out (and names) a damaged one.

:func:`connect` gives an in-memory DuckDB connection with one view, ``history``: every row ever
identified (hive partition ``machine`` included), with its verdict (``trusted``, ``reasons``,
``trust_criteria`` as JSON). Files written before verdicts were recorded lack those columns: their
rows read as NULL there, an unknown verdict (:func:`verdict_sql`).

The connection reads nothing but the history: a local history is read in place with the history's
folder as DuckDB's only allowed directory; a URL history is read through fsspec into Arrow first, and
DuckDB gets no directory at all. Then external access is switched off and the configuration locked
(no file, network, extension or ATTACH outside that folder; no way to switch it back).
``rt-ident fleet query "SQL"`` runs one SELECT on it (:func:`query`); anything else is refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_ident.errors import ConfigError
from rt_ident.fleet.store import filesystem, is_url, parquet_files, read_table, usable_files

if TYPE_CHECKING:
    from duckdb import DuckDBPyConnection


def has_history(history: str | Path) -> bool:
    """Whether ``history`` (a folder, or an fsspec URL: ``s3://bucket/fleet``) holds any Parquet file."""
    return bool(parquet_files(history))


def _sql_text(s: str) -> str:
    return "'" + s.replace("'", "''") + "'"


def _lock_down(con: DuckDBPyConnection, allowed: list[str]) -> None:
    """Only ``allowed`` folders readable, no external access, settings frozen (this order: the folders
    cannot be set once access is off). No spill folder either: it would be one more allowed directory."""
    con.execute("SET temp_directory = ''")
    con.execute(f"SET allowed_directories = [{', '.join(_sql_text(a) for a in allowed)}]")
    con.execute("SET enable_external_access = false")
    con.execute("SET lock_configuration = true")


def connect(history: str | Path) -> DuckDBPyConnection:
    """A locked-down in-memory DuckDB connection with the view ``history`` (see the module docstring)."""
    import duckdb

    files = usable_files(history)
    if not files:
        damaged = len(parquet_files(history))
        raise ConfigError("--history", f"{history} holds no readable fleet history: its {damaged} Parquet files "
                          "are damaged (named above)" if damaged else
                          f"{history} holds no fleet history (run `rt-ident fleet identify` first)")
    con = duckdb.connect(":memory:")
    if is_url(history):
        con.register("history", read_table(history, files))
        allowed: list[str] = []
    else:
        root = filesystem(history)[1]
        listing = ", ".join(_sql_text(f) for f in files)
        con.execute(f"CREATE VIEW history AS SELECT * FROM read_parquet([{listing}], hive_partitioning = true, "
                    "union_by_name = true, hive_types = {'machine': VARCHAR})")
        allowed = [root.rstrip("/") + "/"]
    _lock_down(con, allowed)
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
    """Run ``sql`` - exactly one SELECT - against the ``history`` view; returns (column names, rows).
    Anything else (another statement type, several statements, a file outside the history) is refused
    with a one-line :class:`~rt_ident.errors.ConfigError`."""
    import duckdb

    con = connect(history)
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as exc:
        raise ConfigError("SQL", _first_line(exc)) from None
    if len(statements) != 1:
        raise ConfigError("SQL", f"refused: {len(statements)} statements; fleet query runs exactly one SELECT")
    kind = statements[0].type
    if kind != duckdb.StatementType.SELECT:
        raise ConfigError("SQL", f"refused: statement type {kind.name}; fleet query runs one SELECT and nothing "
                                 "else (it only reads the history)")
    try:
        cur = con.execute(statements[0])
    except duckdb.PermissionException as exc:
        raise ConfigError("SQL", f"refused: {_first_line(exc)} (fleet query reads the history only)") from None
    except duckdb.Error as exc:
        raise ConfigError("SQL", _first_line(exc)) from None
    if cur.description is None:
        return [], []
    return [d[0] for d in cur.description], cur.fetchall()


def _first_line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


__all__ = ["columns", "connect", "has_history", "is_url", "query", "verdict_sql"]

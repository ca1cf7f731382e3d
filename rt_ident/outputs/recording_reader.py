"""Read a recording back: a closed Parquet file, a crashed recorder's journal, or a CSV.

The on-disk format is described in :mod:`rt_ident.processes.recorder` (which re-exports
:class:`Recording` and :func:`read_recording`). The format constants live here so that the reader
does not depend on the writer.

CSV input: a header row naming at least ``t, theta1, theta2, torque`` (SI units: s, rad, rad,
N m), optionally ``omega1, omega2`` [rad/s]; any column order; other columns are ignored; ``#``
starts a comment. A recording's own torque columns (``torque_cmd``, and ``torque_meas`` where present)
stand in for ``torque``, so a recording exported to CSV reads as the recording does. With
``require_theta2=False`` (the ``rigid-friction`` model: one position sensor) ``theta2`` may be missing
(``Recording.theta2`` is then None) and the units are the file's own (rad and N m, or m and N). A CSV
carries no metadata (``metadata == {}``) and its ``torque`` is taken as both the applied and the commanded
torque.

Torque used for identification (:attr:`Recording.torque`): ``torque_meas`` where it is present and
finite, else ``torque_cmd`` (per sample; a mix is logged as a warning).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.errors import DataError

log = logging.getLogger(__name__)

COLUMNS: tuple[str, ...] = ("t", "seq", "theta1", "theta2", "torque_cmd", "torque_meas")
METADATA_KEY = b"rt_ident.metadata"
FORMAT_KEY = b"rt_ident.format"
FORMAT_VERSION = b"1"
JOURNAL_SUFFIX = ".arrows"
PART_SUFFIX = ".part"
MIN_ROWS = 10
CSV_REQUIRED: tuple[str, ...] = ("t", "theta1", "theta2", "torque")
CSV_OPTIONAL: tuple[str, ...] = ("omega1", "omega2")


def journal_path(path: str | os.PathLike[str]) -> Path:
    """The crash-safe Arrow IPC journal that belongs to recording ``path``."""
    return Path(str(path) + JOURNAL_SUFFIX)


def part_path(path: str | os.PathLike[str]) -> Path:
    """The in-progress Parquet file (no footer yet) that belongs to recording ``path``."""
    return Path(str(path) + PART_SUFFIX)


@dataclass(frozen=True)
class Recording:
    """Samples ready for identification. Arrays share one length; units SI.

    ``torque`` is the signal to identify with (see module docstring). ``source`` is ``"parquet"``
    (a closed recording), ``"journal"`` (recovered after a crash, up to the last flush) or
    ``"csv"``.
    """

    t: np.ndarray
    theta1: np.ndarray
    theta2: np.ndarray | None           # None only when read with require_theta2=False and absent
    torque: np.ndarray
    torque_cmd: np.ndarray
    torque_meas: np.ndarray | None
    omega1: np.ndarray | None
    omega2: np.ndarray | None
    seq: np.ndarray | None
    metadata: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    def __len__(self) -> int:
        return int(self.t.shape[0])


def _decode_metadata(schema_metadata: dict[bytes, bytes] | None, where: Path) -> dict[str, Any]:
    raw = (schema_metadata or {}).get(METADATA_KEY)
    if raw is None:
        return {}
    try:
        meta = json.loads(raw)
    except ValueError as e:
        raise DataError(f"{where}: metadata is not valid JSON ({e})") from e
    return meta if isinstance(meta, dict) else {"value": meta}


def _check_finite(name: str, x: np.ndarray, where: Path) -> None:
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise DataError(f"{where}: column {name!r} has a non-finite value {float(x[bad[0]])} at data row {bad[0] + 1}")


#: magnitudes no axis of this kind reaches (the numerics overflow long before a fit means anything)
PLAUSIBLE_MAX = {"t": 1e9, "theta1": 1e9, "theta2": 1e9, "torque": 1e6}   # s, rad, rad, N m


def _check_plausible(name: str, x: np.ndarray, where: Path) -> None:
    big = np.flatnonzero(np.abs(x) > PLAUSIBLE_MAX[name])
    if big.size:
        unit = {"t": "s", "torque": "N m"}.get(name, "rad")
        raise DataError(f"{where}: column {name!r} reaches {x[big[0]]:.3g} {unit} at data row {big[0] + 1}, beyond "
                        f"any plausible value (|{name}| <= {PLAUSIBLE_MAX[name]:g} {unit}); check the units")


def _build(cols: dict[str, np.ndarray], metadata: dict[str, Any], source: str, where: Path,
           require_theta2: bool = True) -> Recording:
    """Validate columns (names, length, finiteness, monotonic t) and pick the torque signal."""
    has_torque = any(k in cols for k in ("torque", "torque_cmd", "torque_meas"))
    needed = ("t", "theta1", "theta2") if require_theta2 else ("t", "theta1")
    missing = [k for k in needed if k not in cols] + ([] if has_torque else ["torque"])
    if missing:
        raise DataError(f"{where}: missing column(s) {', '.join(missing)} (found: {', '.join(cols) or 'none'})")
    t = np.asarray(cols["t"], dtype=np.float64)
    n = t.shape[0]
    if n < MIN_ROWS:
        raise DataError(f"{where}: only {n} data rows; at least {MIN_ROWS} are needed")
    get = {k: np.asarray(v, dtype=np.float64) for k, v in cols.items() if k != "seq"}
    meas = get.get("torque_meas")
    if "torque" in get:
        torque = cmd = get["torque"]
        meas = None
    else:
        cmd = get["torque_cmd"] if "torque_cmd" in get else get["torque_meas"]   # one of them, or has_torque failed
        if meas is None or not (finite := np.isfinite(meas)).any():
            torque, meas = cmd, None
        else:
            if not finite.all():
                log.warning("%s: torque_meas missing for %d samples; using torque_cmd there",
                            where, int(n - finite.sum()))
            torque = np.where(finite, meas, cmd)
    for name, x in (("t", t), ("theta1", get["theta1"]), ("theta2", get.get("theta2")), ("torque", torque)):
        if x is None:
            continue
        _check_finite(name, x, where)
        _check_plausible(name, x, where)
    for name in CSV_OPTIONAL:
        if name in get:
            _check_finite(name, get[name], where)
    steps = np.flatnonzero(np.diff(t) <= 0.0)
    if steps.size:
        i = int(steps[0]) + 1
        raise DataError(
            f"{where}: t is not strictly increasing at data row {i + 1} (t={float(t[i])!r} after {float(t[i - 1])!r})"
        )
    seq = cols.get("seq")
    return Recording(
        t=t, theta1=get["theta1"], theta2=get.get("theta2"), torque=torque, torque_cmd=cmd,
        torque_meas=meas, omega1=get.get("omega1"), omega2=get.get("omega2"),
        seq=None if seq is None else np.asarray(seq, dtype=np.int64),
        metadata=metadata, source=source,
    )


def _check_types(schema: Any, where: Path) -> None:
    """The columns read as numbers (``seq`` an integer) hold numbers: a text or nested column is named
    in one line, not met as a TypeError in the first arithmetic on it."""
    import pyarrow as pa

    for name in (*COLUMNS, *CSV_REQUIRED, *CSV_OPTIONAL):
        i = schema.get_field_index(name)
        if i < 0:
            continue
        typ = schema.field(i).type
        ok = pa.types.is_integer(typ) if name == "seq" else (pa.types.is_floating(typ) or pa.types.is_integer(typ))
        if not ok:
            raise DataError(f"{where}: column {name!r} holds {typ}, not {'integers' if name == 'seq' else 'numbers'}")


def _check_seq(table: Any, where: Path, row0: int = 0) -> None:
    if "seq" in table.column_names and table.column("seq").null_count:
        i = int(np.flatnonzero(table.column("seq").is_null().to_numpy(zero_copy_only=False))[0])
        raise DataError(f"{where}: column 'seq' has no value at data row {row0 + i + 1}")


def _table_columns(table: Any, where: Path) -> dict[str, np.ndarray]:
    _check_types(table.schema, where)
    _check_seq(table, where)
    return {name: table.column(name).to_numpy() for name in table.column_names}


def _read_journal(path: Path) -> tuple[Any, dict[str, Any]]:
    """All complete batches of an Arrow IPC journal; a torn last batch is dropped whole."""
    import pyarrow as pa
    import pyarrow.ipc as ipc

    batches = []
    try:
        with pa.OSFile(str(path), mode="r") as f:
            reader = ipc.open_stream(f)
            schema = reader.schema
            while True:
                try:
                    batches.append(reader.read_next_batch())
                except StopIteration:
                    break
                except (OSError, pa.ArrowInvalid) as e:
                    log.warning("%s: ignoring a truncated final batch (%s)", path, e)
                    break
    except (OSError, pa.ArrowInvalid) as e:
        raise DataError(f"{path}: journal holds no complete data ({e})") from e
    return pa.Table.from_batches(batches, schema=schema), _decode_metadata(schema.metadata, path)


def _read_parquet(path: Path) -> tuple[Any, dict[str, Any]]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as e:
        raise DataError(f"{path}: not a readable Parquet file ({e})") from e
    return table, _decode_metadata(table.schema.metadata, path)


def _csv_scan(path: Path, names: list[str], idx: list[int]) -> np.ndarray:
    """Slow path: parse row by row, naming the first malformed row."""
    out = []
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        next(reader)
        row_no = 0
        for row in reader:
            if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                continue
            row_no += 1
            vals = []
            for name, i in zip(names, idx):
                if i >= len(row):
                    raise DataError(f"{path}: data row {row_no} (line {reader.line_num}) has no {name!r} value")
                try:
                    vals.append(float(row[i]))
                except ValueError:
                    raise DataError(
                        f"{path}: non-numeric {name!r} value {row[i]!r} at data row {row_no} (line {reader.line_num})"
                    ) from None
            out.append(vals)
    return np.array(out, dtype=np.float64).reshape(-1, len(names))


def _read_csv(path: Path, require_theta2: bool = True) -> dict[str, np.ndarray]:
    try:
        return _read_csv_utf8(path, require_theta2)
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start}); "
                        "save the CSV as UTF-8 or ASCII") from None


def _read_csv_utf8(path: Path, require_theta2: bool = True) -> dict[str, np.ndarray]:
    with open(path, newline="", encoding="utf-8") as f:
        header = next(csv.reader(f), None)
    if not header:
        raise DataError(f"{path}: empty CSV (no header row)")
    header = [h.strip() for h in header]
    required = CSV_REQUIRED if require_theta2 else tuple(c for c in CSV_REQUIRED if c != "theta2")
    exported = "torque" not in header and "torque_cmd" in header
    if exported:
        required = tuple("torque_cmd" if c == "torque" else c for c in required)
    missing = [c for c in required if c not in header]
    if missing:
        hint = ""
        if require_theta2 and missing == ["theta2"]:
            hint = " (a one-sensor recording t,theta1,torque needs --model rigid-friction)"
        elif "torque" in missing:
            hint = " (torque: the applied torque in N m; a recording's torque_cmd and torque_meas also do)"
        raise DataError(f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(header)}){hint}")
    wanted = (*required, *(("torque_meas",) if exported else ()), *CSV_OPTIONAL)
    names = [c for c in wanted if c in header]
    idx = [header.index(c) for c in names]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": reported below
            data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=idx, ndmin=2, dtype=np.float64, comments="#",
                              encoding="utf-8")
    except ValueError:
        data = _csv_scan(path, names, idx)  # names the bad row, or parses what loadtxt could not
    return {name: data[:, k] for k, name in enumerate(names)}


def read_recording(path: str | os.PathLike[str], *, require_theta2: bool = True) -> Recording:
    """Read ``.parquet`` (closed, or recovered from its journal after a crash), ``.arrows``, ``.csv``.

    Raises :class:`DataError` naming the problem: missing file, unknown extension, missing columns,
    non-numeric values (with the row), non-finite or non-monotonic ``t``, fewer than 10 rows.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if p.is_dir():
        raise DataError(f"{p}: a folder, not a recording (one .parquet, .arrows or .csv file)")
    if ext == ".csv":
        if not p.is_file():
            raise DataError(f"{p}: no such file")
        return _build(_read_csv(p, require_theta2), {}, "csv", p, require_theta2)
    if ext == ".parquet":
        journal = journal_path(p)
        if p.is_file():
            table, meta = _read_parquet(p)
            return _build(_table_columns(table, p), meta, "parquet", p)
        if journal.is_file():
            log.warning("%s was not closed; recovering up to the last flush from %s", p, journal.name)
            table, meta = _read_journal(journal)
            return _build(_table_columns(table, p), meta, "journal", p)
        raise DataError(f"{p}: no such file (and no journal {journal.name} to recover from)")
    if ext == JOURNAL_SUFFIX:
        if not p.is_file():
            raise DataError(f"{p}: no such file")
        table, meta = _read_journal(p)
        return _build(_table_columns(table, p), meta, "journal", p)
    raise DataError(f"{p}: unknown extension {p.suffix!r} (expected .parquet, .arrows or .csv)")


def parquet_metadata(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The run metadata of a finished ``.parquet`` recording (schema only: no data is read), or None
    when ``path`` is not one."""
    p = Path(path)
    if p.suffix.lower() != ".parquet" or not p.is_file():
        return None
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(str(p))
    except Exception as e:  # noqa: BLE001 - pyarrow raises several types for a bad file
        raise DataError(f"{p}: not a readable Parquet file ({e})") from e
    if not {"t", "theta1", "theta2", "torque_cmd"} <= set(schema.names):
        return None
    return _decode_metadata(schema.metadata, p)


def iter_parquet_blocks(path: str | os.PathLike[str], rows: int = 1 << 16
                        ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]]:
    """Yield ``(theta1, theta2, torque, seq)`` blocks of a finished recording, ``rows`` at a time
    (Parquet record batches): memory does not grow with the recording's length. Every block is
    checked as :func:`read_recording` checks the whole (finite, plausible, t strictly increasing,
    across block edges too); the torque is the measured one where present, else the command."""
    import pyarrow.parquet as pq

    p = Path(path)
    # row group by row group, without pre-buffering: ParquetFile.iter_batches grows by ~18 B per sample
    # read (~2.5 GB for an hour at 34 k samples/s); this stays flat (a recording's row groups are its
    # 0.5 s flushes)
    f = pq.ParquetFile(str(p), pre_buffer=False, buffer_size=1 << 20)
    _check_types(f.schema_arrow, p)
    names = [c for c in COLUMNS if c in f.schema_arrow.names]
    last_t = -math.inf
    row0 = 0
    for batch in _row_group_slices(f, names, rows):
        _check_seq(batch, p, row0)
        cols = {n: batch.column(n).to_numpy(zero_copy_only=False) for n in names}
        t = np.asarray(cols["t"], dtype=np.float64)
        cmd = np.asarray(cols["torque_cmd"], dtype=np.float64)
        meas = cols.get("torque_meas")
        torque = cmd if meas is None else np.where(np.isfinite(meas), meas, cmd)
        for name, x in (("t", t), ("theta1", cols["theta1"]), ("theta2", cols["theta2"]), ("torque", torque)):
            bad = np.flatnonzero(~np.isfinite(x))
            if bad.size:
                raise DataError(f"{p}: column {name!r} has a non-finite value at data row {row0 + bad[0] + 1}")
            big = np.flatnonzero(np.abs(x) > PLAUSIBLE_MAX[name])
            if big.size:
                raise DataError(f"{p}: column {name!r} reaches {x[big[0]]:.3g} at data row {row0 + big[0] + 1}, "
                                f"beyond any plausible value (|{name}| <= {PLAUSIBLE_MAX[name]:g}); check the units")
        steps = np.flatnonzero(np.diff(np.concatenate(([last_t], t))) <= 0.0)
        if steps.size:
            raise DataError(f"{p}: t is not strictly increasing at data row {row0 + steps[0] + 1}")
        last_t = float(t[-1]) if t.size else last_t
        seq = cols.get("seq")
        yield (np.asarray(cols["theta1"], dtype=np.float64), np.asarray(cols["theta2"], dtype=np.float64),
               torque, None if seq is None else np.asarray(seq, dtype=np.int64))
        row0 += t.shape[0]


def _row_group_slices(f: Any, names: list[str], rows: int) -> Iterator[Any]:
    for i in range(f.num_row_groups):
        table = f.read_row_group(i, columns=names)
        for k in range(0, table.num_rows, rows):
            yield table.slice(k, rows)
        del table

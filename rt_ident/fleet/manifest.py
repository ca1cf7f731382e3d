"""A fleet manifest: which recording belongs to which machine and axis, and when it was made.

CSV with a header and the columns ``path, machine, axis, time`` (more columns are ignored); ``time`` is
ISO 8601 (a date, or a date and time; no zone means UTC). ``path`` is a local path (relative ones are
taken from the manifest's folder) or an fsspec URL (``s3://``, ``gs://``, ``file://``...) the installed
filesystems understand.
"""

from __future__ import annotations

import csv
import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

from rt_ident.errors import ConfigError

COLUMNS = ("path", "machine", "axis", "time")


@dataclass(frozen=True)
class Entry:
    path: str
    machine: str
    axis: str
    time: _dt.datetime      # UTC, timezone-aware


def _is_url(path: str) -> bool:
    return "://" in path


def parse_time(text: str, where: str) -> _dt.datetime:
    try:
        t = _dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise ConfigError(where, f"time {text!r} is not ISO 8601 (e.g. 2026-11-24 or 2026-11-24T06:00:00)") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.UTC)
    return t.astimezone(_dt.UTC)


def read_manifest(path: str | Path) -> list[Entry]:
    """The manifest's entries, in file order. One clear error names the line of any bad row."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("MANIFEST", f"{p} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("MANIFEST", f"cannot read {p}: {exc}") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise ConfigError("MANIFEST", f"{p} is empty (expected a header: {', '.join(COLUMNS)})")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise ConfigError("MANIFEST", f"{p}: header lacks {', '.join(missing)} (has {', '.join(header)})")
    idx = {c: header.index(c) for c in COLUMNS}
    out: list[Entry] = []
    for n, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) < len(header):
            raise ConfigError("MANIFEST", f"{p} line {n}: {len(row)} fields, the header has {len(header)}")
        vals = {c: row[i].strip() for c, i in idx.items()}
        for c in ("path", "machine", "axis"):
            if not vals[c]:
                raise ConfigError("MANIFEST", f"{p} line {n}: empty {c}")
        rec = vals["path"]
        if not _is_url(rec) and not Path(rec).is_absolute():
            rec = str((p.parent / rec).resolve())
        out.append(Entry(rec, vals["machine"], vals["axis"], parse_time(vals["time"], f"MANIFEST line {n}")))
    if not out:
        raise ConfigError("MANIFEST", f"{p} lists no recordings")
    return out


def write_manifest(path: str | Path, entries: list[Entry]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for e in entries:
            w.writerow((e.path, e.machine, e.axis, e.time.isoformat()))


__all__ = ["COLUMNS", "Entry", "read_manifest", "write_manifest", "parse_time"]

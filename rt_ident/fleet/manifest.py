"""A fleet manifest: which recording belongs to which machine and axis, and when it was made.

CSV with a header and the columns ``path, machine, axis, time`` (more columns are ignored); ``time`` is
ISO 8601 (a date, or a date and time; no zone means UTC).

``path`` is a local path (relative ones are taken from the manifest's folder; ``file://`` URLs are local
paths too) or a URL of a remote filesystem fsspec understands (:data:`REMOTE`: ``s3://``, ``gs://``,
``az://``...). Whoever writes a manifest chooses what the identifying process reads, so a local path is
resolved (links followed) and must lie under the manifest's folder, and anything there must be a regular
file (not ``/dev/zero``, a folder or a pipe); other URLs (``http://``, chained ``a::b`` URLs, ``local://``
...) are refused too. ``allow_outside`` lifts both limits but the regular-file one. A path that does not
exist yet is kept: its task reports it.
"""

from __future__ import annotations

import csv
import datetime as _dt
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from rt_ident.errors import ConfigError

COLUMNS = ("path", "machine", "axis", "time")
#: URL schemes of remote filesystems a manifest may name without ``allow_outside`` (none reaches this host's files)
REMOTE = ("s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "hdfs", "webhdfs", "sftp", "ssh", "memory")


@dataclass(frozen=True)
class Entry:
    path: str
    machine: str
    axis: str
    time: _dt.datetime      # UTC, timezone-aware


def _is_url(path: str) -> bool:
    return "://" in path


def recording_path(text: str, folder: Path, allow_outside: bool = False) -> str:
    """The recording ``text`` names, checked (see the module docstring): a local path comes back absolute and
    resolved, a remote URL as written. Raises ValueError saying why it is refused."""
    local = text[len("file://"):] if text.startswith("file://") else text
    if _is_url(local) or "::" in local:
        scheme = local.split("://", 1)[0].lower()
        if allow_outside or ("::" not in local and scheme in REMOTE):
            return local
        raise ValueError(f"{text}: a {scheme}:// URL is not one of the remote filesystems read without "
                         f"--allow-outside ({', '.join(REMOTE)})")
    base = folder.resolve()
    path = (base / local).resolve()               # an absolute path stays itself; links are followed
    if not allow_outside and not path.is_relative_to(base):
        via = "" if Path(os.path.normpath(base / local)) == path else f" (a link to {path})"
        raise ValueError(f"{text}{via} is outside the manifest's folder {base} (--allow-outside reads it)")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return str(path)                          # its task reports it missing, the others go on
    except OSError as exc:
        raise ValueError(f"{text}: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{text} is not a regular file (a device, folder or pipe is never read)")
    return str(path)


def parse_time(text: str, where: str) -> _dt.datetime:
    try:
        t = _dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise ConfigError(where, f"{text!r} is not ISO 8601 (e.g. 2026-11-24 or 2026-11-24T06:00:00)") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.UTC)
    return t.astimezone(_dt.UTC)


def read_manifest(path: str | Path, allow_outside: bool = False) -> list[Entry]:
    """The manifest's entries, in file order. One clear error names the line of any bad row, and of any
    recording path refused (:func:`recording_path`; ``allow_outside``: read paths outside the manifest's
    folder and any URL)."""
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
        try:
            rec = recording_path(vals["path"], p.parent, allow_outside)
            when = parse_time(vals["time"], "time")
        except ValueError as exc:
            raise ConfigError("MANIFEST", f"{p} line {n}: {exc}") from None
        out.append(Entry(rec, vals["machine"], vals["axis"], when))
    if not out:
        raise ConfigError("MANIFEST", f"{p} lists no recordings")
    return out


def write_manifest(path: str | Path, entries: list[Entry]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for e in entries:
            w.writerow((e.path, e.machine, e.axis, e.time.isoformat()))


__all__ = ["COLUMNS", "REMOTE", "Entry", "parse_time", "read_manifest", "recording_path", "write_manifest"]

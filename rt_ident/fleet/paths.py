"""File names made from fleet data (machine and axis names), kept inside the folder they are written to.

A machine or axis name comes from a manifest anyone may write: ``../../tmp/x``, ``/etc/cron.d/job`` or a
name with control characters must not become a path. :func:`safe_name` makes one file-name component
from such names; :func:`output_path` puts it under an output folder and checks it stays there.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

from rt_ident.errors import ConfigError

_KEEP = re.compile(r"[A-Za-z0-9][A-Za-z0-9._]*")     # a part kept as written: no separator, no leading dot
_OTHER = re.compile(r"[^A-Za-z0-9._]")
_SUFFIX = re.compile(r"(\.[A-Za-z0-9]+)*")
MAX_PART = 60


def safe_name(*parts: str) -> str:
    """One file-name component from ``parts``, joined by ``-``.

    Parts made of letters, digits, ``.`` and ``_`` (not starting with ``.``) are kept as written:
    ``safe_name("m01", "x") == "m01-x"``. Anything else - a ``/``, ``-``, a leading dot, a space, a
    non-ASCII letter, a part longer than 60 characters - is replaced by ``_`` (or cut) and a hash of
    the original parts is appended, so two different name tuples never give the same file name:
    ``safe_name("../../tmp/escaped", "x") == "_.._tmp_escaped-x-<10 hex digits>"``.
    """
    if not parts:
        raise ValueError("safe_name needs at least one part")
    if all(_KEEP.fullmatch(p) and len(p) <= MAX_PART for p in parts):
        return "-".join(parts)
    cleaned = [(_OTHER.sub("_", p).lstrip(".") or "_")[:MAX_PART] for p in parts]
    digest = hashlib.sha256(json.dumps(list(parts)).encode()).hexdigest()[:10]
    return "-".join([*cleaned, digest])


def output_path(out_dir: str | Path, *parts: str, suffix: str) -> Path:
    """``out_dir / (safe_name(*parts) + suffix)``, checked to resolve inside ``out_dir``.

    ``suffix`` is a file extension such as ``".png"`` or ``".trend.csv"``. A file already there that is
    a symbolic link out of ``out_dir`` is refused (:class:`~rt_ident.errors.ConfigError` naming ``--out``)
    rather than written through.
    """
    if not _SUFFIX.fullmatch(suffix):
        raise ValueError(f"suffix {suffix!r} is not a file extension such as '.png'")
    folder = Path(out_dir).resolve()
    path = folder / (safe_name(*parts) + suffix)
    if path.resolve().parent != folder:
        raise ConfigError("--out", f"{path} leads out of {folder} (a link there?); remove it or choose another --out")
    return path


__all__ = ["output_path", "safe_name"]

"""A run's output files, decided before anything starts: names, suffixes, no silent overwrite, a
writable directory with room, no file another run is writing; and no empty file left by a run that
read nothing."""

from __future__ import annotations

import contextlib
import datetime as _dt
import os
import shutil
from pathlib import Path
from typing import Any

from rt_ident.config import RunConfig
from rt_ident.errors import ConfigError
from rt_ident.estimators.streaming import STREAMING_METHODS
from rt_ident.hostlock import NamedLock


def default_paths(stamp: str | None = None) -> tuple[Path, Path]:
    """``runs/run-<date>-<time>-<pid>.{rrd,parquet}``: the pid keeps two runs started in the same
    second apart (and :func:`prepare_outputs` still refuses a name that exists)."""
    stamp = stamp or f"{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    for n in range(1, 1000):
        base = Path("runs") / (f"run-{stamp}" if n == 1 else f"run-{stamp}-{n}")
        names = (".rrd", ".parquet", ".parquet.part", ".parquet.arrows")
        if not any(base.with_name(base.name + x).exists() for x in names):
            break
    return base.with_suffix(".rrd"), base.with_suffix(".parquet")


#: free space an output directory must have before the device is enabled (a few seconds of data)
MIN_FREE_BYTES = 32 << 20


class OutputClaims:
    """The files a run writes, each locked host-wide (:class:`~rt_ident.hostlock.NamedLock` on its
    resolved path) from its check to the run's end: a second run given the same file is refused before
    anything starts, instead of writing into the first one's files or removing them as its own."""

    def __init__(self, directory: str | os.PathLike[str] | None = None) -> None:
        self.directory = directory
        self._locks: list[NamedLock] = []

    def claim(self, path: str | os.PathLike[str], what: str, by: str = "run") -> None:
        lock = NamedLock("out", str(Path(path).resolve()), self.directory)
        if not lock.try_acquire():
            raise ConfigError(what, f"{path} is being written by another {by} ({lock.who()}): choose another "
                                    "path, or let that one end first")
        self._locks.append(lock)

    def release(self) -> None:
        """Drop every claim (idempotent)."""
        for lock in self._locks:
            lock.release()
        self._locks.clear()


def check_output(path: str | None, suffix: str, what: str, overwrite: bool,
                 claims: OutputClaims | None = None) -> None:
    """One line, before anything is energized: the suffix, not another run's file (claimed in
    ``claims`` for this run), no silent overwrite, a writable directory with room."""
    if not path:
        return
    p = Path(path)
    if p.suffix != suffix:
        raise ConfigError(what, f"{path!r} must end in {suffix}")
    if claims is not None:
        claims.claim(p, what)
    siblings = [p, p.with_name(p.name + ".part"), p.with_name(p.name + ".arrows")]
    existing = [str(x) for x in siblings if x.exists()]
    if existing and not overwrite:
        raise ConfigError(what, f"{existing[0]} exists; choose another path or pass --overwrite")
    if p.exists() and not p.is_file():
        raise ConfigError(what, f"{path} exists and is not a file")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(what, f"cannot create the directory {p.parent}: {exc.strerror or exc}") from None
    if not os.access(p.parent, os.W_OK | os.X_OK):
        raise ConfigError(what, f"the directory {p.parent} is not writable")
    free = shutil.disk_usage(p.parent).free
    if free < MIN_FREE_BYTES:
        raise ConfigError(what, f"only {free >> 20} MiB free in {p.parent} (needs {MIN_FREE_BYTES >> 20} MiB "
                                "for the first seconds of the run)")


def prepare_outputs(cfg: RunConfig, rrd: str | None, record: str | None, sink: str,
                    overwrite: bool, claims: OutputClaims | None = None) -> tuple[str | None, str | None]:
    """(rrd path, recording path) of a run, checked (and claimed in ``claims``) before any device or
    helper starts."""
    rrd_default, rec_default = default_paths()
    rrd_path = rrd or cfg.telemetry.rrd or (str(rrd_default) if sink == "rrd" else None)
    if sink != "rrd":
        rrd_path = None
    rec_path = record or cfg.recording.path or (str(rec_default) if cfg.recording.enabled else None)
    check_output(rrd_path, ".rrd", "--rrd / telemetry.rrd", overwrite, claims)
    check_output(rec_path, ".parquet", "--record / recording.path", overwrite, claims)
    if rrd_path and rec_path and Path(rrd_path).resolve() == Path(rec_path).resolve():
        raise ConfigError("--rrd", "the dashboard and the recording cannot be the same file")
    return rrd_path, rec_path


def check_methods(cfg: RunConfig) -> None:
    """The estimator method has a streaming form (checked before anything starts)."""
    if cfg.estimator.method not in STREAMING_METHODS:
        raise ConfigError("estimator.method", f"{cfg.estimator.method!r} has no streaming form for the loop; "
                          f"use one of {', '.join(STREAMING_METHODS)} (rt-ident identify runs the others offline)")


def drop_unwritten(files: dict[str, Any]) -> None:
    """Name only files that exist: a path whose file was never written (a telemetry restarted too late to
    open its file, a recorder that failed before its first batch) moves to ``not_written``; what it lost
    is in the run's ``data_lost``."""
    missing = []
    for key in ("rrd", "recording"):
        if files.get(key) and not Path(files[key]).exists():
            missing.append(str(files[key]))
            files[key] = None
    if files.get("rrd_earlier"):
        missing += [f for f in files["rrd_earlier"] if not Path(f).exists()]
        files["rrd_earlier"] = [f for f in files["rrd_earlier"] if f not in missing]
    if missing:
        files["not_written"] = missing


def remove_empty_outputs(summary: dict[str, Any], files: dict[str, Any]) -> None:
    """A run that read no sample leaves no file: an empty recording and a dashboard with nothing
    on it would only look like data."""
    for key in ("rrd", "recording"):
        path = files.get(key)
        if not path:
            continue
        p = Path(path)
        for f in (p, p.with_name(p.name + ".part"), p.with_name(p.name + ".arrows")):
            with contextlib.suppress(FileNotFoundError):
                f.unlink()
        files[key] = None
    if "recording" in summary:
        summary["recording"]["removed_empty"] = True

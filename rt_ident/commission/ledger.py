"""The record of commissioning ``run`` consults: one JSON file per device configuration, named by the
hash of what commissioning checks (the backend's options and ``[plant.actual]``), in the user's state
directory (``$RT_IDENT_STATE_DIR``, else ``$XDG_STATE_HOME/rt_ident``, else ``~/.local/state/rt_ident``).
The file names are hashes: nothing the user types becomes a path. An entry keeps the unit the device said
it was (its serial number), so that a run can tell the commissioned unit from another one put in its place,
and the settings it was commissioned with, so that a run can name what changed in the config file since."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from drivers.base import unit_of
from rt_ident.config import RunConfig


def state_dir() -> Path:
    env = os.environ.get("RT_IDENT_STATE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "rt_ident"


def _settings(cfg: RunConfig) -> dict[str, Any]:
    """What commissioning checks: the backend's options (but where an emulator listens) and the simulated
    device's truth, as JSON values."""
    opts = {k: v for k, v in cfg.backend.options().items() if k not in ("port",)}
    actual = cfg.plant.actual.model_dump() if cfg.plant.actual is not None else None
    blob = json.dumps({"backend": cfg.backend.name, "emulate": cfg.backend.emulate, "options": opts,
                       "actual": actual, "axis_lead": cfg.axis_params().lead}, sort_keys=True, default=str)
    settings: dict[str, Any] = json.loads(blob)
    return settings


def device_key(cfg: RunConfig) -> str:
    """The hash of :func:`_settings`."""
    blob = json.dumps(_settings(cfg), sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


#: the settings' names as a user writes them in the config
_KEYS = {"options": "backend", "actual": "plant.actual", "axis_lead": "axis.lead", "backend": "backend.name",
         "emulate": "backend.emulate"}


def _flat(d: Any, key: str) -> dict[str, Any]:
    if not isinstance(d, dict):
        return {key: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{key}.{k}" if key else _KEYS.get(str(k), str(k))))
    return out


def _file_of(cfg: RunConfig) -> str | None:
    return None if not cfg.source else str(Path(cfg.source).resolve())


def changed_since_commissioned(cfg: RunConfig) -> str | None:
    """For a config file commissioned (passed) with other device settings than it has now: the settings that
    changed since, newest commissioning first ("backend.torque_constant 0.1 -> 0.2"). None when the file
    was never commissioned."""
    file = _file_of(cfg)
    if file is None:
        return None
    best: tuple[float, dict[str, Any]] | None = None
    try:
        entries = list(state_dir().glob("*.json"))
    except OSError:
        return None
    for path in entries:
        try:
            entry = json.loads(path.read_text())
            when = path.stat().st_mtime
        except (OSError, ValueError):
            continue
        if (isinstance(entry, dict) and entry.get("config_file") == file and entry.get("verdict") == "pass"
                and isinstance(entry.get("settings"), dict) and (best is None or when > best[0])):
            best = (when, entry["settings"])
    if best is None:
        return None
    then, now = _flat(best[1], ""), _flat(_settings(cfg), "")
    changed = [f"{k} {then.get(k, '(unset)')} -> {now.get(k, '(unset)')}" for k in sorted(set(then) | set(now))
               if then.get(k) != now.get(k)]
    return ", ".join(changed) or None


def record(cfg: RunConfig, result: dict[str, Any]) -> Path | None:
    """Keep the verdict for ``cfg``'s device (atomically: a reader never sees half a file)."""
    d = state_dir()
    try:
        d.mkdir(parents=True, exist_ok=True)
        entry = {"verdict": result.get("verdict"), "failed": result.get("failed"), "config": cfg.source,
                 "report": result.get("report"), "stage_reached": result.get("stage_reached"),
                 "unit": unit_of(result.get("identity") or {}), "settings": _settings(cfg),
                 "config_file": _file_of(cfg)}
        fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(entry, f)
        path = d / f"{device_key(cfg)}.json"
        os.replace(tmp, path)
        return path
    except OSError:
        return None


def lookup(cfg: RunConfig) -> dict[str, Any] | None:
    """The last commissioning verdict for ``cfg``'s device, or None when it was never commissioned."""
    try:
        return json.loads((state_dir() / f"{device_key(cfg)}.json").read_text())
    except (OSError, ValueError):
        return None


def needs_commissioning(cfg: RunConfig) -> bool:
    """A closed-loop run on a device whose picture the host may have wrong: any device but the plain sim
    (whose plant is the config itself)."""
    if cfg.control.mode == "off" or cfg.axes:
        return False
    return cfg.backend.name != "sim" or bool(cfg.plant.actual is not None and cfg.plant.actual.device_truth())

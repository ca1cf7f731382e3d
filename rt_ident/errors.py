"""One exception hierarchy for the whole product.

Every error raised on purpose by :mod:`rt_ident` or :mod:`drivers` derives from
:class:`RtIdentError`, so a caller (the CLI, the loop) can handle "our" errors in
one place and let genuine bugs propagate.
"""

from __future__ import annotations

import difflib
import typing
from collections.abc import Mapping
from typing import Any


class RtIdentError(Exception):
    """Root of every error this package raises on purpose."""


class ConfigError(RtIdentError, ValueError):
    """Invalid configuration or parameter value. The message names the field."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


class EstimationError(RtIdentError):
    """An estimator cannot produce an answer from the data it was given."""


class DataError(RtIdentError, ValueError):
    """Input data (a recording, a CSV, arrays) is malformed."""


class MissingExtra(RtIdentError):
    """A feature needs a package the core install leaves out (an optional extra of the project)."""


def require(module: str, extra: str, what: str) -> None:
    """Raise :class:`MissingExtra` in one line when ``module`` cannot be imported: ``what`` needs the
    ``extra`` of ``pip install 'rt-ident[extra]'``."""
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise MissingExtra(f"{what} needs {module}: pip install 'rt-ident[{extra}]' (or -e '.[{extra}]' in a checkout)")


#: how a fix begins that puts a failure on the host's load (a drive, a device or the loop itself starved);
#: :func:`ask_realtime` writes it, :func:`host_fix` says it as it applies to the run
HOST_FIX = "loop.realtime = true (or a less busy host"


def ask_realtime(why: str, otherwise: str | None = None) -> str:
    """The fix for a failure the host's load caused: ``loop.realtime = true (or a less busy host[; else
    OTHERWISE]): WHY``."""
    return f"{HOST_FIX}{f'; else {otherwise}' if otherwise else ''}): {why}"


def host_fix(fix: str | None, realtime: dict | bool | None) -> str | None:
    """``fix`` as it applies to a run: one that asks for ``loop.realtime = true`` (:data:`HOST_FIX`) says,
    where the run had it on, what is left to change. ``realtime``: the run's real-time report (its
    ``sched_fifo`` is True where the loop got SCHED_FIFO, else why not), or False where the run was not
    real-time. The result still begins with ``loop.realtime``, the mark of a failure put on the host."""
    if not fix or not fix.startswith(HOST_FIX) or not isinstance(realtime, dict):
        return fix
    rest = fix[len(HOST_FIX):]                   # ")..." or "; else <another setting>)..."
    close = rest.find(")")
    if close < 0:
        return fix
    other, tail = rest[:close].removeprefix(";").strip(), rest[close + 1:]
    host = f"a less busy host ({other})" if other else "a less busy host"
    granted = realtime.get("sched_fifo")
    if granted is True:
        return f"loop.realtime is on and the loop ran at SCHED_FIFO: {host}{tail}"
    return (f"loop.realtime is on but the loop ran without SCHED_FIFO ({granted}): real-time privileges for it "
            f"(an rtprio and memlock limit, or root; see docs/operation/loop.md), or {host}{tail}")


def validation_error(model: Any, exc: Any) -> tuple[Mapping[str, Any], str]:
    """The error of a pydantic ``ValidationError`` of a config section (``model``) to report, and its message
    as the config's line says it. A mistyped key comes first (the field it was meant to be is then missing
    too): it is called unknown and the nearest keys the section has are named. Any other message comes
    without pydantic's "Value error, "."""
    errors = exc.errors()
    err = next((e for e in errors if e.get("type") == "extra_forbidden"), errors[0])
    msg = str(err["msg"]).removeprefix("Value error, ")
    if err.get("type") != "extra_forbidden" or not err.get("loc"):
        return err, msg
    *path, key = err["loc"]
    for part in path:
        model = _step(model, part)
    found = _models(model)
    if len(found) != 1:
        return err, msg
    keys = [k for k in found[0].model_fields if k != "source"]
    near = difflib.get_close_matches(str(key), keys, n=2, cutoff=0.6)
    return err, "unknown key" + (f" (did you mean {' or '.join(near)}?)" if near else
                                 f"; the keys here: {', '.join(keys)}")


def _models(tp: Any) -> list[Any]:
    """The pydantic models a type stands for: itself, or the models of a union (``X | None``, a tagged union)."""
    if hasattr(tp, "model_fields"):
        return [tp]
    return [m for m in typing.get_args(tp) if hasattr(m, "model_fields")]


def _step(tp: Any, part: int | str) -> Any:
    """What stands at ``part`` below ``tp``: a field's type, or the member of a union of models that the tag
    ``part`` picks (pydantic puts a tagged union's tag in the error's place); None if neither."""
    found = _models(tp)
    if len(found) == 1 and part in found[0].model_fields:
        return found[0].model_fields[part].annotation
    tagged = [m for m in found if any(part in typing.get_args(f.annotation) for f in m.model_fields.values())]
    return tagged[0] if tagged else None

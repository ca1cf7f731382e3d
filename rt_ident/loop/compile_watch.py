"""Compiled code the loop reaches for the first time while it runs.

A numba dispatcher's first call with a new argument type compiles it (hundreds of milliseconds) or
loads it from numba's cache (milliseconds: the cache is read and the types resolved). In a tick,
either is an overrun. Everything the tick can reach, its rare paths included, is warmed up before the
first tick (:func:`rt_ident.loop.tick_kernel.warm_up`, the components' own warm-ups); this watch proves
it: it notes every dispatcher's signatures of :mod:`rt_ident` and :mod:`drivers` before the loop and
reports the ones added while it ran.
"""

from __future__ import annotations

import sys
from typing import Any

_PACKAGES = ("rt_ident.", "drivers.")


def _dispatchers() -> dict[str, Any]:
    """Every numba dispatcher a module of ours holds, by ``module.name``."""
    from numba.core.dispatcher import Dispatcher

    found: dict[str, Any] = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith(_PACKAGES) or module is None:
            continue
        for attr, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                found.setdefault(f"{name}.{attr}", value)
    return found


class CompileWatch:
    """``start()`` before the loop, ``stop()`` after it: the signatures compiled or loaded in between."""

    def __init__(self) -> None:
        self._before: dict[str, int] = {}
        self.late: list[str] = []

    def start(self) -> None:
        self._before = {k: len(d.signatures) for k, d in _dispatchers().items()}

    def stop(self) -> list[str]:
        late = []
        for key, d in _dispatchers().items():
            sigs = list(d.signatures)
            for sig in sigs[self._before.get(key, 0):]:
                late.append(f"{key}{tuple(str(t) for t in sig)}")
        self.late = late
        return late

    def as_dict(self) -> dict[str, Any]:
        return {"count": len(self.late), "functions": self.late[:20]}


__all__ = ["CompileWatch"]

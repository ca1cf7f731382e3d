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


def _dispatchers(skip: frozenset[str] = frozenset()) -> dict[str, Any]:
    """Every numba dispatcher a module of ours (other than those named in ``skip``) holds, by ``module.name``."""
    from numba.core.dispatcher import Dispatcher

    found: dict[str, Any] = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith(_PACKAGES) or module is None or name in skip:
            continue
        for attr, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                found.setdefault(f"{name}.{attr}", value)
    return found


class CompileWatch:
    """``start()`` before the loop, ``stop()`` after it: the signatures compiled or loaded in between.

    ``stop()`` runs while the devices still stream (on an error, before their safe stop), beside I/O
    threads that need the GIL and the CPU every period: it only counts the signatures of the dispatchers
    found at ``start()``. The modules imported during the run (rarely any) are scanned when the result is
    read (:meth:`as_dict`), after the run: a scan of every module there, memory the run has not touched
    since its start, holds the loop's CPU and the GIL for milliseconds.
    """

    def __init__(self) -> None:
        self._found: dict[str, Any] = {}
        self._before: dict[str, int] = {}
        self._after: dict[str, int] = {}
        self._modules: frozenset[str] = frozenset()
        self._new_modules = False
        self._late: list[str] | None = None

    def start(self) -> None:
        self._modules = frozenset(sys.modules)
        self._found = _dispatchers()
        self._before = {k: len(d.signatures) for k, d in self._found.items()}
        self._after, self._new_modules, self._late = {}, False, None

    def stop(self) -> None:
        self._after = {k: len(d.signatures) for k, d in self._found.items()}
        self._new_modules = len(sys.modules) != len(self._modules)

    @property
    def late(self) -> list[str]:
        """``module.function(argument types)`` of every signature added between ``start()`` and ``stop()``."""
        if self._late is None:
            late = []
            for key, d in self._found.items():
                for sig in list(d.signatures)[self._before[key]:self._after.get(key, self._before[key])]:
                    late.append(f"{key}{tuple(str(t) for t in sig)}")
            if self._new_modules:
                for key, d in _dispatchers(self._modules).items():
                    late.extend(f"{key}{tuple(str(t) for t in sig)}" for sig in d.signatures)
            self._late = late
        return self._late

    def as_dict(self) -> dict[str, Any]:
        late = self.late
        return {"count": len(late), "functions": late[:20]}


__all__ = ["CompileWatch"]

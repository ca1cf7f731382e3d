"""Backends for rt_ident: the sim plant, a CiA 402 CANopen drive, a serial encoder board.

Backends are named in a registry as strings and imported only when chosen,
so a missing vendor package fails only for the backend that needs it.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

# rt_ident's import brings numba's cache in step with the sources (rt_ident.kernel_cache) before a backend's
# compiled kernels load from it
import rt_ident  # noqa: F401
from drivers.base import Backend, SampleBlock
from drivers.errors import BackendNotFound, DriverError

BACKENDS: dict[str, str] = {
    "sim": "drivers.sim:SimBackend",
    "canopen": "drivers.cia402.drive:Cia402Backend",
    "serial": "drivers.encoder_board.board:SerialBoardBackend",
}


def backend_class(name: str) -> type[Backend]:
    try:
        target = BACKENDS[name]
    except KeyError:
        raise BackendNotFound(f"unknown backend {name!r}; known: {', '.join(sorted(BACKENDS))}") from None
    module_name, _, cls_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendNotFound(f"backend {name!r} cannot be imported: {exc}") from exc
    return getattr(module, cls_name)


def make_backend(name: str, config: Mapping[str, Any] | None = None) -> Backend:
    """Construct (not open) the backend registered as ``name``."""
    return backend_class(name)(config)


__all__ = ["BACKENDS", "Backend", "SampleBlock", "BackendNotFound", "DriverError", "backend_class", "make_backend"]

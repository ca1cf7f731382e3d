"""Start an emulated device for ``[backend] emulate = true``.

The serial board streams at 20 kHz from a Python thread; inside the loop's
process it would compete with the loop for the GIL (and starve under the
loop's SCHED_FIFO), so it runs in its own process and hands back its
pseudo-terminal path. The CANopen drive on python-can's ``virtual`` bus can
only live in the same process (that bus does not cross processes).
"""

from __future__ import annotations

import importlib
import multiprocessing as mp
from typing import Any

from rt_ident.errors import RtIdentError

EMULATORS = {"canopen": "drivers.emulated_drive", "serial": "drivers.emulated_board"}


def _serve(module: str, config: dict[str, Any], conn, stop) -> None:
    try:
        dev = importlib.import_module(module).start_emulator_for(config)
    except Exception as exc:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("port", dev.port))
    try:
        stop.wait()
    finally:
        dev.stop()


class EmulatorProcess:
    """An emulated serial board in a child process; ``.port`` is its pseudo-terminal."""

    def __init__(self, module: str, config: dict[str, Any], timeout: float = 20.0) -> None:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        self._stop = ctx.Event()
        self._proc = ctx.Process(target=_serve, args=(module, config, child, self._stop),
                                 name="rt_ident-emulator", daemon=True)
        self._proc.start()
        if not parent.poll(timeout):
            self.close()
            raise RtIdentError(f"emulator {module} did not start within {timeout:g} s")
        kind, value = parent.recv()
        if kind == "error":
            self.close()
            raise RtIdentError(f"emulator {module} failed to start: {value}")
        self.port: str = value

    def close(self) -> None:
        self._stop.set()
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)


def start_emulator(cfg) -> Any:
    """The emulated device for ``cfg.backend.name``; call ``.close()`` (or ``.stop()``) when done."""
    module = EMULATORS.get(cfg.backend.name)
    if module is None:
        raise RtIdentError(f"backend.emulate: no emulator for backend {cfg.backend.name!r}")
    if cfg.backend.name == "serial":
        return EmulatorProcess(module, cfg.model_dump())
    return importlib.import_module(module).start_emulator_for(cfg)

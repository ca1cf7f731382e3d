"""Start an emulated device for ``[backend] emulate = true``.

An emulated device that streams at kHz rates from Python threads must not share the
loop's process: it would compete with the loop for the GIL (and starve under the loop's
SCHED_FIFO). So it runs in a child process (:class:`EmulatorProcess`, :mod:`rt_ident.processes.context`)
and the loop reaches it like a real device:

* ``serial``: the board on a pseudo-terminal; ``.port`` is its path;
* ``canopen`` on ``udp_multicast``: the CiA 402 drive on the same multicast group;
  ``.port`` is the UDP port (a free one is picked when ``[backend] port`` is not set, so
  that concurrent runs and tests do not share a bus). The drive answers every SYNC within
  one period, so it gets a CPU other than the loop's and, when the loop is real-time,
  SCHED_FIFO below the loop's priority - it stands in for hardware with its own clock;
* ``canopen`` on python-can's ``virtual`` bus: that bus does not cross processes, so the
  drive runs in this process (tests use this; the loop's timing suffers).

The child applies its CPU set and priority to itself before it starts any thread (on
Linux both are per thread, and threads inherit them only when they are created). It
stops when :meth:`EmulatorProcess.close` asks, and by itself when the parent process
goes away (its end of the pipe closes), so a crashed or killed run leaves no emulator.
"""

from __future__ import annotations

import importlib
import logging
import socket
from multiprocessing import current_process
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from drivers.placement import clear_heap, device_placement, keep_to, settle_heap, start_realtime
from rt_ident.errors import RtIdentError
from rt_ident.processes.context import helper_context
from rt_ident.processes.guard import ParentWatch, helper_comm, name_process, start_with_helper_env

if TYPE_CHECKING:
    from rt_ident.config import RunConfig

log = logging.getLogger(__name__)

EMULATORS = {"canopen": "drivers.cia402.emulator", "serial": "drivers.encoder_board.emulator"}
#: what the device process is called (its process name, and its kernel name without "_ident")
DEVICE_NAMES = {"drivers.cia402.emulator": "rt_ident-drive", "drivers.encoder_board.emulator": "rt_ident-board"}


def _serve(module: str, config: dict[str, Any], conn: Connection, placement: dict[str, Any] | None) -> None:
    """Child process: leave the loop's CPU, import the device's code, start the device, turn its threads
    real-time, report, wait for "stop" (or the parent's end), stop.

    Only the device's threads run at SCHED_FIFO (drivers.placement.start_realtime). The import (numba,
    canopen, the plant: most of the start-up's CPU time), building the device, its report and the exit
    run in this thread at ordinary scheduling: at SCHED_FIFO they would hold the CPU against every other
    thread there, other emulated devices at the same priority included.
    """
    name_process(helper_comm(current_process().name))
    placement = placement or {}
    placed = keep_to(placement.get("cpus"))
    parent = ParentWatch(every_s=0.0)
    try:
        mod = importlib.import_module(module)
        clear_heap()
        dev, rt = start_realtime(lambda: mod.start_emulator_for(config), placement.get("fifo_priority"))
    except Exception as exc:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    placed.update(rt)
    settle_heap()                            # no full pass of the collector stalls the device later
    try:
        conn.send(("ready", {"port": getattr(dev, "port", None), "placement": placed}))
        while True:
            if conn.poll(0.25):              # "stop", or EOF: the parent closed its end or died
                break
            if parent.gone:                  # the parent is gone (its pipe end closed)
                break
    except (OSError, EOFError):
        pass
    finally:
        report: dict[str, Any] = {}
        try:                                 # as the host left the device, before its own stop
            stats = getattr(dev, "stats", None)
            report = stats() if callable(stats) else {}
        except Exception as exc:  # noqa: BLE001
            report = {"error": f"{type(exc).__name__}: {exc}"}
        dev.stop()
    try:
        conn.send(("stopped", report))
    except (OSError, ValueError):
        pass


def free_udp_port() -> int:
    """A UDP port no socket is bound to right now (the kernel's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


class EmulatorProcess:
    """An emulated device in a child process.

    ``module.start_emulator_for(config)`` runs in the child; ``port`` is what the device
    reports as its ``.port`` (serial: the pseudo-terminal) unless given (canopen: the UDP
    port). ``placement``: ``{"cpus": [...], "fifo_priority": n}`` applied by the child to
    itself first. ``pid``, ``placement`` (what the child got) are set once it is ready.
    """

    def __init__(self, module: str, config: dict[str, Any], *, timeout: float = 20.0,
                 placement: dict[str, Any] | None = None, port: Any = None) -> None:
        ctx = helper_context()
        self._conn, child = ctx.Pipe()
        self.module = module
        self._proc = ctx.Process(target=_serve, args=(module, config, child, placement),
                                 name=DEVICE_NAMES.get(module, "rt_ident-device"), daemon=True)
        # one BLAS thread: a device thread under SCHED_FIFO that calls a multithreaded BLAS (the plant's
        # matrix exponential at enable) spins on its CPU waiting for a BLAS worker that cannot run there
        # until the RT throttle lets it, up to 1 s later - long enough to trip the board's heartbeat watchdog
        start_with_helper_env(self._proc)
        child.close()                        # only the child holds its end: EOF reaches it if we die
        self.pid: int | None = self._proc.pid
        try:
            if not self._conn.poll(timeout):
                raise RtIdentError(f"emulator {module} did not start within {timeout:g} s")
            kind, value = self._conn.recv()
        except (EOFError, OSError):
            self.close()
            raise RtIdentError(f"emulator {module} exited during start-up (exit code "
                               f"{self._proc.exitcode})") from None
        except RtIdentError:
            self.close()
            raise
        if kind == "error":
            self.close()
            raise RtIdentError(f"emulator {module} failed to start: {value}")
        self.port: Any = port if port is not None else value["port"]
        self.placement: dict[str, Any] = value["placement"]
        self.stats: dict[str, Any] | None = None     # the device's report (state, counters) at close

    @property
    def alive(self) -> bool:
        return self._proc.is_alive()

    def close(self) -> None:
        """Stop the device and reap the child (idempotent; terminates it if it does not stop)."""
        try:
            self._conn.send("stop")
            if self._conn.poll(5.0):
                kind, value = self._conn.recv()
                if kind == "stopped":
                    self.stats = value
                    log.info("emulator %s stopped: %s", self.module, value)
        except (OSError, ValueError, EOFError):
            pass
        self._proc.join(5.0)
        if self._proc.is_alive():
            log.warning("emulator %s did not stop; terminating it", self.module)
            self._proc.terminate()
            self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2.0)
        self._conn.close()

    stop = close

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def start_emulator(cfg: RunConfig) -> Any:
    """The emulated device for ``cfg.backend.name``; call ``.close()`` (or ``.stop()``) when done."""
    name = cfg.backend.name
    module = EMULATORS.get(name)
    if module is None:
        raise RtIdentError(f"backend.emulate: no emulator for backend {name!r}")
    realtime = bool(cfg.loop.realtime)
    placement = device_placement(realtime)
    if name == "serial":
        # a real board runs on its own hardware: the emulated one must not be starved by a busy host either
        return EmulatorProcess(module, cfg.model_dump(), placement=placement)
    opts = cfg.backend.options()
    if opts.get("interface") != "udp_multicast":
        log.warning("emulated drive on %r runs in the loop's process (only udp_multicast reaches a child "
                    "process); expect late samples", opts.get("interface"))
        return importlib.import_module(module).start_emulator_for(cfg)
    port = opts.get("port") or free_udp_port()
    config = {"backend": {**opts, "port": port}, "emulator": dict(cfg.emulator),
              "axis": cfg.axis_params().as_dict()}
    return EmulatorProcess(module, config, placement=placement, port=port)


def start_bus_emulator(cfgs: list, realtime: bool) -> Any:
    """One emulated device process for several CiA 402 drives on one bus (an XY table's axes):
    ``cfgs`` are the axes' run configs, on one ``udp_multicast`` group and port (picked here when
    unset: the caller passes ``.port`` to every backend). Each drive keeps its node id, plant,
    emulator options and faults. On an in-process bus (``virtual``) they run in this process."""
    module = EMULATORS["canopen"]
    opts = [c.backend.options() for c in cfgs]
    drives = [{"backend": o, "emulator": dict(c.emulator), "axis": c.axis_params().as_dict()}
              for o, c in zip(opts, cfgs)]
    if opts[0].get("interface") != "udp_multicast":
        log.warning("emulated drives on %r run in the loop's process (only udp_multicast reaches a child "
                    "process); expect late samples", opts[0].get("interface"))
        return importlib.import_module(module).start_emulator_for({"drives": drives})
    port = opts[0].get("port") or free_udp_port()
    for d in drives:
        d["backend"] = {**d["backend"], "port": port}
    return EmulatorProcess(module, {"drives": drives}, placement=device_placement(realtime), port=port)

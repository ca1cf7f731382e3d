"""``rt-ident run``: build everything from a config, run the loop, always stop safely - one axis, or
every ``[axes.NAME]`` of an XY table in one loop.

Each axis gets its backend, state estimator, streaming estimator and fit process, controller and
redesign process, safety monitor, recorder and telemetry (:func:`_build_axis`); a one-axis run ticks
its :class:`~rt_ident.loop.loop.IdentificationLoop`, several axes one
:class:`~rt_ident.loop.loop.MultiAxisLoop` (every axis's block read, then each axis estimated and
controlled, then every plan written). Order matters: the helper processes are spawned first (so they
do not inherit real-time scheduling), compiled kernels are warmed up, the devices are opened and their
position checked, then real-time treatment is requested for this process, the devices are activated
and the loop ticks. Whatever ends the loop (duration, Ctrl-C, SIGTERM, SIGHUP, a safety trip or device error
on any axis, any exception), every backend's context manager stops it: zero torque, drive disabled.
Files are then closed and one summary is returned (for several axes, each axis's part under ``axes``
and the axis that stopped the run named).

Several axes: every axis ``sim``, or every axis a CiA 402 drive (``canopen``) on one bus, sharing one
bus connection and one SYNC producer (:class:`drivers.cia402.node.BusConnection`); with ``emulate =
true`` one emulator process runs every drive (:func:`rt_ident.processes.emulation.start_bus_emulator`).
Serial encoder boards for several axes are not built: refused in one line.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import re
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers import make_backend
from drivers.errors import SafetyTrip
from rt_ident.axis.modal import modal_parameters
from rt_ident.compose import preflight
from rt_ident.compose.build import (
    backend_counters,
    backend_options,
    check_axes,
    final_fit,
    friction_summary,
    ident_summary,
    identification_loop,
    recording_metadata,
    safety_monitor,
    stall_policy,
    start_controller,
    state_and_streaming,
    warmup,
)
from rt_ident.compose.contour import ContourTrace
from rt_ident.compose.helpers import AxisHelpers, Helpers
from rt_ident.config import RunConfig
from rt_ident.errors import ConfigError, RtIdentError, ask_realtime, host_fix
from rt_ident.loop.host import HostSteal, LoopCpuInterrupts, LoopRealtime
from rt_ident.loop.loop import IdentificationLoop, MultiAxisLoop
from rt_ident.outputs.paths import (
    OutputClaims,
    check_methods,
    check_output,
    drop_unwritten,
    prepare_outputs,
    remove_empty_outputs,
)
from rt_ident.processes.guard import install_stop_signals
from rt_ident.processes.jobs import make_fit_process

log = logging.getLogger(__name__)


#: how long, in all, the final fit's hand-offs to a telemetry process may wait for room in its ring [s]
FINAL_HANDOFF_WAIT_S = 2.0


@dataclass
class _Axis:
    """One axis of a run: its config, device, helpers, loop and output files."""

    name: str
    cfg: RunConfig
    backend: Any
    rrd: str | None
    recording: str | None
    helpers: AxisHelpers
    loop: IdentificationLoop | None = None
    final_fit_error: str | None = None


def run(cfg: RunConfig, *, rrd: str | None = None, record: str | None = None, sink: str | None = None,
        connect_url: str | None = None, stop_event: threading.Event | None = None,
        tick_hook=None, overwrite: bool = False, commissioned_units: dict[str, dict[str, Any] | None] | None = None,
        require_commissioned: bool = False) -> dict[str, Any]:
    """Run the loop described by ``cfg``; returns the summary (also on a safety stop).

    ``summary["stop"]["cause"]`` is ``None`` for a normal end (duration reached, Ctrl-C, SIGTERM, SIGHUP)
    and a cause tag (``"watchdog"``, ``"travel-limit"``, ``"device-fault"``, ...) otherwise. A config
    refused before any device is enabled raises its :class:`~rt_ident.errors.ConfigError`.
    Its output files are claimed host-wide from their check to the end (:class:`OutputClaims`).
    ``commissioned_units``: per axis (``""`` for a run of one), the unit its device's commissioning was of
    (:func:`drivers.base.unit_of`), checked once the device is open and before it is enabled
    (:func:`~rt_ident.compose.preflight.check_unit`).
    """
    claims = OutputClaims()
    try:
        return _run(cfg, claims, rrd=rrd, record=record, sink=sink, connect_url=connect_url, stop_event=stop_event,
                    tick_hook=tick_hook, overwrite=overwrite, units=(commissioned_units or {}, require_commissioned))
    finally:
        claims.release()


def _run(cfg: RunConfig, claims: OutputClaims, *, rrd: str | None, record: str | None, sink: str | None,
         connect_url: str | None, stop_event: threading.Event | None, tick_hook, overwrite: bool,
         units: tuple[dict[str, dict[str, Any] | None], bool]) -> dict[str, Any]:
    from rt_ident.outputs.sinks import DEFAULT_PORT, TelemetryConfig, serve_port

    stop = stop_event or threading.Event()
    several = bool(cfg.axes)
    axes_cfg = check_axes(cfg) if several else {"": cfg}
    if not several:
        check_methods(cfg)
    sink = sink or cfg.telemetry.sink
    live_url = connect_url or cfg.telemetry.connect_url
    if several and sink == "serve":
        raise ConfigError("telemetry.sink", "a run with several axes writes .rrd files (one per axis), streams "
                                            "to one viewer (--spawn, --connect URL) or sends nothing; --serve would "
                                            "need a server per axis")
    if several and sink == "connect":
        if not live_url:
            raise ConfigError("telemetry.connect_url", "--connect needs the viewer's URL (rerun+http://HOST:PORT/proxy)")
        TelemetryConfig(sink="connect", connect_url=live_url)          # the URL's form, checked before anything starts
    rrd_base, rec_base = prepare_outputs(cfg, rrd, record, sink, overwrite, claims)
    contour_rrd = contour_png = None
    if several:
        for name, acfg in axes_cfg.items():                # the per-axis files must not exist either
            prepare_outputs(acfg, _axis_path(rrd_base, name), _axis_path(rec_base, name), sink, overwrite, claims)
        contour_rrd = _sibling(rrd_base, "-contour.rrd")      # the circular test's dashboard, both axes
        contour_png = _sibling(rec_base or rrd_base, "-contour.png")
        check_output(contour_rrd, ".rrd", "--rrd / telemetry.rrd (the contour dashboard beside it)", overwrite,
                     claims)
        check_output(contour_png, ".png", "the contour plot beside the recording", overwrite, claims)
    port = serve_port(cfg.telemetry.bind_ip, cfg.telemetry.port) if sink == "serve" else \
        (cfg.telemetry.port or DEFAULT_PORT)

    summary: dict[str, Any] = {"config": cfg.source}
    if not several:
        summary.update({"backend": cfg.backend.name, "method": cfg.estimator.method})
    axes: dict[str, _Axis] = {}
    helpers = Helpers()
    host: dict[str, Any] = {"steal_ms": None, "steal_cpu": None, "interrupts": None}   # filled around the loop
    stop_cause = stop_message = stop_axis = stop_fix = None
    enabled = False
    refused: ConfigError | None = None
    runner: IdentificationLoop | MultiAxisLoop | None = None
    trace: ContourTrace | None = None
    emulator = None
    old_signals = install_stop_signals(stop)
    try:
        with contextlib.ExitStack() as stack:
            emulator = _start_emulator(cfg, axes_cfg, several)
            if emulator is not None:
                stack.callback(getattr(emulator, "close", None) or emulator.stop)   # after every backend's stop
            if several and sink == "spawn":
                from rt_ident.outputs.sinks import ensure_viewer

                live_url = ensure_viewer(TelemetryConfig(sink="spawn", bind_ip=cfg.telemetry.bind_ip,
                                                         port=cfg.telemetry.port or DEFAULT_PORT))
            if several and live_url and sink in ("spawn", "connect"):
                summary["live_url"] = live_url
            if sink == "serve":
                summary["serve_url"] = f"rerun+http://{_url_host(cfg.telemetry.bind_ip)}:{port}/proxy"
                log.warning("dashboard served at %s (open with: rerun --connect %s)", summary["serve_url"],
                            summary["serve_url"])
            for name, acfg in axes_cfg.items():
                opts = backend_options(acfg)
                if getattr(emulator, "port", None):          # the board's pseudo-terminal, the bus's UDP port
                    opts["port"] = emulator.port
                backend = make_backend(acfg.backend.name, opts)
                _named(name, preflight.check_config, acfg, backend.torque_limit)
                axes[name] = _Axis(name, acfg, backend, _axis_path(rrd_base, name) if several else rrd_base,
                                   _axis_path(rec_base, name) if several else rec_base, AxisHelpers())
                helpers.axes[name] = axes[name].helpers
            loops: dict[str, IdentificationLoop] = {}
            for name, ax in axes.items():
                loops[name] = _build_axis(ax, cfg, sink, live_url, port, several, stop, stack, overwrite)
            watch = helpers.start_watch(cfg.loop.tick_hz)
            trace = ContourTrace(loops, int(round(cfg.loop.duration * cfg.loop.tick_hz))) if several else None

            def hooks(n: int) -> None:
                if trace is not None:
                    trace()
                watch(n)
                if tick_hook is not None:
                    tick_hook(n)

            if several:
                runner = MultiAxisLoop(loops, tick_hz=cfg.loop.tick_hz,
                                       duration=cfg.loop.duration, stop_event=stop, tick_hook=hooks,
                                       max_sleep_s=None if cfg.loop.max_sleep_us is None
                                       else cfg.loop.max_sleep_us * 1e-6, stall=stall_policy(cfg))
            else:
                runner = loops[""]
                runner.tick_hook = hooks
            helpers.ready()                              # files exist, rings mapped: before the devices move
            summary["helper_processes"] = helpers.place(cfg.loop.realtime, getattr(emulator, "pid", None))
            realtime = LoopRealtime(cfg, stop)
            stack.callback(realtime.end)                 # on an error: after every backend's safe stop and close
            realtime.prepare()                           # slow, and before the devices watch our heartbeat
            # restored after every backend's exit: an error's safe stop needs the short switch interval too
            stack.callback(sys.setswitchinterval, sys.getswitchinterval())
            for ax in axes.values():                     # open as late as possible: a device streams from open()
                stack.enter_context(ax.backend)          # on exit (any axis's error too): safe stop, close
            expected_units, unit_required = units
            for name, ax in axes.items():                # the unit commissioned, before it is enabled
                expected_unit = expected_units.get(name)
                if expected_unit is not None:
                    preflight.check_unit(ax.backend, expected_unit, unit_required, summary, name)
            for name, ax in axes.items():                # what the device says it is set to, before enabling it
                _named(name, preflight.check_settings, ax.backend, ax.cfg)
            for name, ax in axes.items():                # nothing energized that would trip on its first ticks
                start = ax.backend.read_position()
                if start is not None:
                    x0 = ax.cfg.axis_params().lead * start[1]
                    preflight.check_start(ax.cfg, x0, ax.backend.sample_period, where=name)
                    if not several:
                        summary["start_position_m"] = x0
            summary["realtime"] = realtime.begin([runner.ticker])
            # a backend's I/O threads (python-can's receiver, a SYNC sender) share this process's GIL: hand
            # it back within 50 us, not 5 ms (the hand-offs to helper processes use no thread: shared rings)
            sys.setswitchinterval(5e-5)
            enabled = True
            for ax in axes.values():
                ax.backend.activate()
            steal = HostSteal()
            irqs = LoopCpuInterrupts(steal.cpu)
            try:
                runner.run()
            finally:
                host["steal_ms"], host["steal_cpu"] = steal.elapsed_ms(), steal.cpu
                host["interrupts"] = irqs.summary()
                watch.freeze()
            for ax in axes.values():
                ax.backend.safe_stop()                   # every axis at zero torque before the (slower) final fits
            realtime.end()                               # the final fits and the files are no real-time work
            for ax in axes.values():
                ax.final_fit_error = _final_fit(ax)
    except RtIdentError as exc:
        if isinstance(exc, ConfigError) and not enabled:
            refused = exc                                # refused before enabling: a one-line error, exit 2
        stop_cause = getattr(exc, "cause", "error")
        stop_message = str(exc) + getattr(exc, "after_stall", "")
        if isinstance(exc, SafetyTrip):                  # a host-side check: was the link going too?
            stop_message += "".join(ax.backend.link_trouble() for ax in axes.values())
        stop_message += "".join(ax.backend.fault_detail() for ax in axes.values())
        stop_fix = getattr(exc, "fix", None)
        if several:
            failed = runner.failed_axis if isinstance(runner, MultiAxisLoop) else None
            stop_axis = failed or next((n for n, ax in axes.items() if ax.loop is not None and _tripped(ax.loop, exc)),
                                       None)
        log.info("run stopped: %s", exc)                 # the summary carries it (the CLI prints it once)
        for ax in axes.values():                         # nothing lost: still fit what was measured
            if ax.loop is not None:
                ax.final_fit_error = _final_fit(ax)
    finally:
        for sig, handler in old_signals.items():
            signal.signal(sig, handler)
        gc.enable()                                      # the loop froze and disabled it (real time)
        reports, lost = helpers.close()
        files: dict[str, Any] = {}
        for name, ax in axes.items():
            files[name] = {"rrd": ax.rrd if sink == "rrd" else None, "recording": ax.recording}
            tel = ax.helpers.telemetry
            if tel is not None and tel.earlier_rrd:      # a telemetry restarted into a new file
                files[name]["rrd_earlier"] = list(tel.earlier_rrd)
                files[name]["rrd"] = tel.config.rrd_path
            read = runner.stats.samples if isinstance(runner, MultiAxisLoop) else \
                (ax.loop.stats.samples if ax.loop is not None else 0)
            if not read:                                 # read nothing: leave no empty files behind
                remove_empty_outputs(reports[name], files[name])
            drop_unwritten(files[name])
        if lost:
            summary["data_lost"] = lost
        summary["helpers"] = helpers.summary()
    if refused is not None:
        raise refused
    backends = {n: ax.backend for n, ax in axes.items()}
    emulated = _emulator_stats(emulator)
    starved = starved_emulator(stop_cause, stop_message, emulated)
    if starved:
        stop_message = f"{stop_message}; {starved}"
        stop_fix = ask_realtime("the emulated drive's process was starved")
    summary["stop"] = {"cause": stop_cause, "message": stop_message, "interrupted": stop.is_set()}
    if stop_fix:
        summary["stop"]["fix"] = host_fix(stop_fix, summary.get("realtime") if cfg.loop.realtime else False)
    if several:
        summary["stop"].update({"axis": stop_axis, "final_torque": {n: b.last_torque for n, b in backends.items()},
                                "backend_state": {n: b.state.value for n, b in backends.items()}})
        unconfirmed = {n: b.stop_unconfirmed for n, b in backends.items() if b.stop_unconfirmed}
        if unconfirmed:
            summary["stop"]["disable_unconfirmed"] = unconfirmed
        summary["files"] = files
        summary["axes"] = {n: {**reports[n], "files": files[n], **_axis_summary(ax)} for n, ax in axes.items()}
        if isinstance(runner, MultiAxisLoop):
            summary["loop"] = {**runner.stats.as_dict(), "host": host}
        if emulated is not None:
            summary["emulator"] = emulated
        contour = trace.result(contour_png, contour_rrd, summary.get("live_url")) if trace is not None else None
        if contour is not None:
            summary["contour"] = contour
    elif axes:
        ax = axes[""]
        summary["stop"].update({"final_torque": ax.backend.last_torque, "backend_state": ax.backend.state.value})
        if ax.backend.stop_unconfirmed:
            summary["stop"]["disable_unconfirmed"] = ax.backend.stop_unconfirmed
        summary.update(reports[""])
        summary["files"] = files[""]
        summary.update(_axis_summary(ax, host))
        if emulated is not None:
            summary["emulator"] = emulated
    return summary


def _build_axis(ax: _Axis, cfg: RunConfig, sink: str, live_url: str | None, port: int, several: bool,
                stop: threading.Event, stack: contextlib.ExitStack, overwrite: bool) -> IdentificationLoop:
    """One axis's helpers (telemetry, recorder, fit and redesign processes), estimators, controller,
    safety monitor and loop (``ax.loop``, returned), warmed up."""
    from rt_ident.outputs.sinks import TelemetryConfig
    from rt_ident.processes.recorder import RecorderProcess
    from rt_ident.processes.telemetry import TelemetryProcess

    acfg, h, name = ax.cfg, ax.helpers, ax.name
    truth = acfg.axis_params()
    dt = ax.backend.sample_period                        # known from the config, before any I/O
    if sink != "off":
        if not several:
            tel_cfg = TelemetryConfig(sink=sink, rrd_path=ax.rrd, connect_url=live_url, bind_ip=cfg.telemetry.bind_ip,
                                      port=port)
        elif sink == "rrd":            # each axis its own recording (rt_ident-x, rt_ident-y): a file, or the viewer
            tel_cfg = TelemetryConfig(sink="rrd", rrd_path=ax.rrd, application_id=f"rt_ident-{name}")
        else:
            tel_cfg = TelemetryConfig(sink="connect", connect_url=live_url, application_id=f"rt_ident-{name}")
        h.telemetry = TelemetryProcess(tel_cfg).start()
        if acfg.backend.name == "sim" or acfg.backend.emulate or several:
            h.telemetry.set_truth({"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K,
                                   **modal_parameters(truth)})
    if ax.recording:
        meta = {**recording_metadata(acfg, dt), **({"axis_name": name} if several else {})}
        h.recorder = RecorderProcess(ax.recording, meta, overwrite=overwrite).start()
    kf, est = state_and_streaming(acfg, dt)
    if acfg.excitation.kind != "none":                   # without the probing multisine there is nothing to fit
        h.fit = make_fit_process(acfg.estimator.method, lead=truth.lead).start()
        stack.callback(h.fit.close)
    warmup(kf, est, (acfg.loop.warmup_periods + 2) * acfg.excitation.period_samples)
    control, h.control = start_controller(acfg, ax.backend, stack)
    tel, rec = h.telemetry, h.recorder
    ax.loop = identification_loop(
        acfg, ax.backend, kf, est, safety_monitor(acfg, dt), control, fit_process=h.fit,
        on_block=rec.put if rec else None, on_telemetry=tel.publish if tel else None,
        on_fit=tel.publish_fit if tel else None, on_loop_gain=tel.publish_loop_gain if tel else None,
        stop_event=stop, tick_hz=cfg.loop.tick_hz, duration=cfg.loop.duration)
    return ax.loop


def _final_fit(ax: _Axis) -> str | None:
    """The final fit of what the axis measured: None, or why there is no estimate."""
    if ax.cfg.excitation.kind == "none":
        return "nothing to identify: no probing excitation (excitation.kind = \"none\")"
    assert ax.loop is not None                           # built before any run ends with a fit
    if ax.helpers.telemetry is not None:                 # the dashboard ends on the values the summary reports
        ax.helpers.telemetry.wait_for_room(FINAL_HANDOFF_WAIT_S)
    return final_fit(ax.loop, ax.loop.est)


def _emulator_stats(emulator: Any) -> dict[str, Any] | None:
    """What the emulator process reported when it was closed (per node for a bus of drives), or None."""
    if emulator is None or getattr(emulator, "stats", None) is None:
        return None
    stats = emulator.stats() if callable(emulator.stats) else emulator.stats
    return stats if isinstance(stats, dict) else None


def emulator_nodes(stats: dict[str, Any]) -> list[dict[str, Any]]:
    """The emulator's stats per drive: one drive's are flat, a bus's are per ``node N``."""
    return [v for k, v in stats.items() if k.startswith("node ") and isinstance(v, dict)] or [stats]


def starved_emulator(cause: str | None, message: str | None, stats: dict[str, Any] | None) -> str | None:
    """A watchdog stop on stale data while the emulated drive itself answered at least that many SYNCs too late
    to send (its process starved: the host's doing, which a drive with a processor of its own would not show):
    the note that says so, else None."""
    stale = re.search(r"for (\d+) SYNCs in a row", message or "") if cause == "watchdog" else None
    if stale is None or not stats:
        return None
    late = max(int(n.get("late_syncs") or 0) for n in emulator_nodes(stats))
    if late < int(stale.group(1)):
        return None
    return (f"the emulated drive answered {late} SYNCs too late to send: its process was starved (a busy host, "
            "not the device)")


def _start_emulator(cfg: RunConfig, axes_cfg: dict[str, RunConfig], several: bool) -> Any:
    """The emulated device(s) of ``[backend] emulate = true`` (one process for every drive on a bus)."""
    if not any(acfg.backend.emulate for acfg in axes_cfg.values()):
        return None
    from rt_ident.processes.emulation import start_bus_emulator, start_emulator

    if several:
        return start_bus_emulator(list(axes_cfg.values()), cfg.loop.realtime)
    return start_emulator(cfg)


def _axis_summary(ax: _Axis, host: dict[str, Any] | None = None) -> dict[str, Any]:
    """An axis's part of the summary: its loop, controller, estimate, device counters and, for a
    simulated device, the truth and the estimate's error."""
    acfg, loop, backend = ax.cfg, ax.loop, ax.backend
    out: dict[str, Any] = {"backend": acfg.backend.name, "method": acfg.estimator.method,
                           "final_fit_error": ax.final_fit_error, "backend_counters": backend_counters(backend)}
    if loop is not None:
        out["loop"] = {**loop.stats.as_dict(), **({"host": host} if host is not None else {}),
                       "compiled_tick": loop.compiled_ticks}
        out["control"] = loop.control.summary() if loop.control is not None else {"mode": "off"}
        late = late_torques(out["backend_counters"], loop.stats.samples, acfg.control.delay_ticks, acfg.backend.name)
        if late is not None and loop.control is not None:
            out["control"]["late_torques"] = late
        notes = device_notes(out["backend_counters"], loop.stats.samples, acfg.backend.name)
        if notes:
            out["device_notes"] = notes
        out["torque_estimate"] = loop.torque_estimate()
        fr = friction_summary(loop)
        if fr is not None:
            out["friction"] = fr
        if loop.identification is not None:
            out.update(ident_summary(loop.identification))
    out.setdefault("parameters", None)
    if acfg.backend.name == "sim" or acfg.backend.emulate:
        truth = getattr(backend, "current_params", None) or acfg.axis_params()   # after the last [[plant.change]]
        tr = {"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K, **modal_parameters(truth)}
        out["truth"] = tr
        if out["parameters"]:
            out["error_pct"] = {k: 100.0 * (out["parameters"][k] - v) / v for k, v in tr.items()}
    return out


#: the mean extra delay of the control torques [ticks] from which a run's summary reports it
LATE_TORQUE_SHARE = 0.05
#: ... and from which the design's delay is the wrong one: the loop's delay is nearer the next whole tick
LATE_REDESIGN_TICKS = 0.5


def late_torques(counters: dict[str, Any] | None, samples: int, delay: int,
                 backend: str = "canopen") -> dict[str, Any] | None:
    """What the device's ``late_torques`` count (samples that ran on an older torque than the one planned for
    them) means for the controller, or None while it is small.

    Each such sample is a plan landing one sample later than designed, so their share of the samples is the
    torques' mean delay past the design's, in ticks. From half a tick on, a design for one tick more describes
    the loop better; below that, one tick more would add more delay than it accounts for, and the fix is the
    host's timing."""
    n = (counters or {}).get("late_torques") or 0
    extra = n / samples if samples else 0.0
    if extra < LATE_TORQUE_SHARE:
        return None
    what = (f"{n} samples ran on an older plan: the torque planned for them reached the board after them"
            if backend == "serial" else f"{n} planned torques missed their SYNC and acted a SYNC late")
    host = ("a less busy host (a USB serial converter: its latency timer at 1 ms)" if backend == "serial" else
            "backend.answer_us if the drives answer sooner than the bus time assumed, or a less busy host")
    fix = f"control.delay_ticks = {delay + 1} (a design for the delay the loop has), or {host}" \
        if extra >= LATE_REDESIGN_TICKS else host
    return {"count": n, "samples": samples, "extra_delay_ticks": round(extra, 3),
            "message": f"in {samples} samples, {what}: the torques acted {extra:.2f} tick later on average than "
                       f"the {delay} tick(s) the controller was designed for",
            "fix": fix}


def device_notes(counters: dict[str, Any] | None, samples: int, backend: str = "canopen") -> list[dict[str, str]]:
    """What the device flagged in its samples: a torque it cut below the command (the loop's model of the
    actuator did not hold there) and warnings, each with what to look at."""
    c = counters or {}
    notes = []
    limited = c.get("internal_limit") or c.get("torque_limited") or 0
    if limited:
        who, how = (("the board", "its status flag") if backend == "serial" else
                    ("the drive", "statusword bit 11, internal limit active"))
        notes.append({"message": f"{who} limited the torque below the command on {limited} of {samples} samples "
                                 f"({how}): there the loop's model of the actuator did not hold",
                      "fix": f"{who}'s own torque, current and thermal limits above backend.torque_limit, or a "
                             "smaller backend.torque_limit or excitation.peak"})
    if c.get("warning"):
        notes.append({"message": f"the drive reported a warning on {c['warning']} of {samples} samples "
                                 "(statusword bit 7)",
                      "fix": "the drive's warning objects or its setup software (vendor-specific), which say which"})
    return notes


def _named(axis: str, check, *args) -> None:
    """``check(*args)``, its ConfigError naming ``axes.AXIS.field`` for an axis of several."""
    try:
        check(*args)
    except ConfigError as exc:
        if not axis:
            raise
        raise ConfigError(f"axes.{axis}.{exc.field}", str(exc)[len(exc.field) + 2:]) from None


def _tripped(loop: IdentificationLoop, exc: Exception) -> bool:
    """Whether ``exc``, raised outside the loop's ticks (a backend's open or activation), came from this
    axis: one of its frames belongs to the axis's loop, safety monitor or backend (by identity: the
    components hold arrays, and two axes' monitors may hold equal values)."""
    own = (loop, loop.safety, loop.backend)
    tb = exc.__traceback__
    while tb is not None:
        obj = tb.tb_frame.f_locals.get("self")
        if obj is not None and any(obj is o for o in own):
            return True
        tb = tb.tb_next
    return False


def _sibling(path: str | None, suffix: str) -> str | None:
    """``runs/run-X.parquet`` -> ``runs/run-X-contour.png``: a file of the whole run beside its outputs."""
    return str(Path(path).with_name(Path(path).stem + suffix)) if path else None


def _axis_path(path: str | None, axis: str) -> str | None:
    """``runs/run-X.rrd`` -> ``runs/run-X-x.rrd``: one file per axis."""
    if not path:
        return None
    p = Path(path)
    return str(p.with_name(f"{p.stem}-{axis}{p.suffix}"))


def _url_host(ip: str) -> str:
    return f"[{ip}]" if ":" in ip else ip


def exit_code(summary: dict[str, Any]) -> int:
    """0: ended as asked (duration, or a signal) with every sample recorded; 3: stopped by a fault,
    trip or error (safe stop); 4: ended, but samples were lost from the recording."""
    if summary["stop"]["cause"] is not None:
        return 3
    return 4 if summary.get("data_lost") else 0


__all__ = ["emulator_nodes", "exit_code", "run", "starved_emulator"]

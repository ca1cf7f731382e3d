"""Several axes in one run (an XY table): the composition root for a config with ``[axes.NAME]``.

Each axis gets what a one-axis run has (:func:`rt_ident.runtime.run.run`): its backend, state
estimator, streaming estimator and fit worker, controller and redesign worker, safety monitor,
recorder (``<name>-<axis>.parquet``) and telemetry (``<name>-<axis>.rrd``). One
:class:`~rt_ident.runtime.loop.MultiAxisLoop` ticks them all: every axis's block is read, then each
axis is estimated and controlled, then every plan is written. A trip or a device error on any axis
stops every axis (zero torque, disabled), and the summary says which axis it came from.

Backends: every axis ``sim``, or every axis a CiA 402 drive (``canopen``) on one bus. The drives
share one bus connection and one SYNC producer (:class:`drivers.cia402.setup.BusConnection`): both
sample at the same SYNC and apply their torques at the same SYNC, and the bus budget counts every
drive's PDOs (:func:`drivers.cia402.config.check_shared_bus`; at 1 Mbit/s two drives allow 1129 Hz
against 2098 Hz for one). With ``emulate = true`` one emulator process runs every drive
(:func:`rt_ident.runtime.emulation.start_bus_emulator`). Serial encoder boards for several axes are
not built: refused in one line.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from drivers import make_backend
from rt_ident.axis.modal import modal_parameters
from rt_ident.config import RunConfig
from rt_ident.errors import ConfigError, RtIdentError
from rt_ident.estimators import make_streaming
from rt_ident.estimators.state_estimation import AxisStateEstimator
from rt_ident.runtime.fit_worker import make_fit_worker
from rt_ident.runtime.helper_guard import HelperWatch
from rt_ident.runtime.loop import IdentificationLoop, MultiAxisLoop
from rt_ident.runtime.outputs import check_output, prepare_outputs, remove_empty_outputs
from rt_ident.runtime.host import HostSteal, LoopCpuInterrupts, LoopRealtime, helper_role, keep_off_loop_cpu
from rt_ident.runtime.build import (backend_counters, backend_options, check_axes, final_fit, friction_estimator,
                                    friction_summary, ident_summary, install_stop_signals, make_excitation, sensor_quanta,
                                    recording_metadata, start_controller, warmup)
from rt_ident.runtime import preflight

log = logging.getLogger(__name__)


def _sibling(path: str | None, suffix: str) -> str | None:
    """``runs/run-X.parquet`` -> ``runs/run-X-contour.png``: a file of the whole run beside its outputs."""
    return str(Path(path).with_name(Path(path).stem + suffix)) if path else None


def _axis_path(path: str | None, axis: str) -> str | None:
    """``runs/run-X.rrd`` -> ``runs/run-X-x.rrd``: one file per axis."""
    if not path:
        return None
    p = Path(path)
    return str(p.with_name(f"{p.stem}-{axis}{p.suffix}"))


class ContourTrace:
    """The table's path on X and Y, one point per tick, when both axes follow a :class:`Circle` reference
    (``kind = "circle"``, ``axis = "x"`` / ``"y"``): afterwards, the circular test's figures (ISO 230-4 G,
    F, H: :mod:`rt_ident.control.contour`) and its polar plot. Preallocated; a tick stores three floats."""

    def __init__(self, loops: dict[str, IdentificationLoop], n_ticks: int) -> None:
        from rt_ident.control.reference import Circle

        self.ctl = {}
        refs = {}
        for name in ("x", "y"):
            lp = loops.get(name)
            ref = getattr(getattr(lp, "control", None), "reference", None)
            if isinstance(ref, Circle) and ref.axis == name:
                self.ctl[name], refs[name] = lp.control, ref
        self.active = len(self.ctl) == 2 and refs["x"].radius == refs["y"].radius and \
            refs["x"].windows() == refs["y"].windows()
        self.ref = refs.get("x")
        n = n_ticks + 8 if self.active else 0
        self.buf = np.full((n, 5), np.nan)        # t, x, y of the table, x, y of the reference
        self.n = 0

    def __call__(self) -> None:
        if not self.active or self.n >= self.buf.shape[0]:
            return
        cx, cy = self.ctl["x"], self.ctl["y"]           # relative to each axis's origin: the circle's frame
        ox, oy = cx.anchor.origin, cy.anchor.origin
        self.buf[self.n] = (cx.t, cx.x_ref + cx.error - ox, cy.x_ref + cy.error - oy, cx.x_ref - ox, cy.x_ref - oy)
        self.n += 1

    def result(self, png: str | None, rrd: str | None = None, live_url: str | None = None) -> dict[str, Any] | None:
        if not self.active or self.n < 16:
            return None
        from rt_ident.control.contour import circle_figures, polar_plot

        t, x, y, xr, yr = self.buf[:self.n].T
        R = self.ref.radius
        paths = {}
        for d, (t0, t1) in self.ref.measured().items():          # constant feed: overshoot arcs excluded
            sel = (t >= t0) & (t <= t1) & np.isfinite(x) & np.isfinite(y)
            if sel.sum() >= 16:
                paths[d] = (x[sel], y[sel])
        if not paths:
            return {"note": "the run ended before the circle began"}
        fig = circle_figures(paths, R, (0.0, -R))
        fig["feed_mm_min"] = 60e3 * 2 * math.pi * R * self.ref.frequency_hz
        stalls = [t for c in self.ctl.values() for t, kind, _ in c.stats.events if kind == "stall"]
        for d, (t0, t1) in self.ref.measured().items():
            hit = [t for t in stalls if t0 - 0.5 <= t <= t1]     # the rejoin after a stall lasts up to ~0.5 s
            if d in fig and hit:                                 # the host, not the axis, made that turn
                fig[d]["disturbed_by_stall_at_s"] = round(hit[0], 3)
        fig["complete"] = {d: d in paths and float(t[-1]) >= self.ref.measured()[d][1] for d in ("ccw", "cw")}
        fig["overshoot_deg"] = self.ref.overshoot_deg
        if png:
            fig["polar_png"] = polar_plot(paths, R, (0.0, -R), fig, png, title="XY circular test (table scale)")
        if rrd or live_url:
            from rt_ident.runtime.dashboard import write_contour_rrd

            try:
                fig["rrd"] = write_contour_rrd(rrd, (xr, yr), paths, R, (0.0, -R), fig, connect_url=live_url)
            except Exception as exc:  # noqa: BLE001 - the figures are in hand; the dashboard is extra
                log.warning("contour dashboard %s not written: %s", rrd or live_url, exc)
                fig["rrd_error"] = f"{type(exc).__name__}: {exc}"
        return fig


def run_axes(cfg: RunConfig, *, rrd: str | None = None, record: str | None = None, sink: str | None = None,
             connect_url: str | None = None, stop_event: threading.Event | None = None, tick_hook=None,
             overwrite: bool = False) -> dict[str, Any]:
    """Run every ``[axes.NAME]`` of ``cfg`` in one loop; returns ``{"axes": {name: summary}, "loop",
    "stop", "files", ...}`` (each axis's summary has the fields of a one-axis run)."""
    from rt_ident.runtime.recording import RecorderProcess
    from rt_ident.runtime.telemetry import TelemetryConfig, TelemetryProcess

    stop = stop_event or threading.Event()
    axes_cfg = check_axes(cfg)
    sink = sink or cfg.telemetry.sink
    if sink not in ("rrd", "off", "connect", "spawn"):
        raise ConfigError("telemetry.sink", "a run with several axes writes .rrd files (one per axis), streams "
                                            "to one viewer (--spawn, --connect URL) or sends nothing; --serve would "
                                            "need a server per axis")
    live_url = None             # --spawn / --connect: every axis's recording (and the contour's) goes to one viewer
    if sink == "connect":
        live_url = connect_url or cfg.telemetry.connect_url
        if not live_url:
            raise ConfigError("telemetry.connect_url", "--connect needs the viewer's URL (rerun+http://HOST:PORT/proxy)")
        TelemetryConfig(sink="connect", connect_url=live_url)          # the URL's form, checked before anything starts
    rrd_base, rec_base = prepare_outputs(cfg, rrd, record, sink, overwrite)
    paths = {name: (_axis_path(rrd_base, name), _axis_path(rec_base, name)) for name in axes_cfg}
    for name, (r, p) in paths.items():              # the per-axis files must not exist either
        prepare_outputs(axes_cfg[name], r, p, sink, overwrite)
    contour_rrd = _sibling(rrd_base, "-contour.rrd")          # the circular test's dashboard, both axes
    contour_png = _sibling(rec_base or rrd_base, "-contour.png")
    check_output(contour_rrd, ".rrd", "--rrd / telemetry.rrd (the contour dashboard beside it)", overwrite)
    check_output(contour_png, ".png", "the contour plot beside the recording", overwrite)
    opts = {name: backend_options(acfg) for name, acfg in axes_cfg.items()}
    backends: dict[str, Any] = {}
    emulator = None
    summary: dict[str, Any] = {"config": cfg.source, "axes": {}}
    loops: dict[str, IdentificationLoop] = {}
    parts: dict[str, dict[str, Any]] = {name: {} for name in axes_cfg}
    host: dict[str, Any] = {"steal_ms": None, "steal_cpu": None, "interrupts": None}
    stop_cause = stop_message = stop_axis = None
    enabled = False
    refused: ConfigError | None = None
    multi = None
    trace: ContourTrace | None = None
    old_signals = install_stop_signals(stop)
    try:
        with contextlib.ExitStack() as stack:
            if sink == "spawn":
                from rt_ident.runtime.telemetry import DEFAULT_PORT, ensure_viewer

                live_url = ensure_viewer(TelemetryConfig(sink="spawn", bind_ip=cfg.telemetry.bind_ip,
                                                         port=cfg.telemetry.port or DEFAULT_PORT))
            if live_url:
                summary["live_url"] = live_url
            if any(acfg.backend.emulate for acfg in axes_cfg.values()):
                from rt_ident.runtime.emulation import start_bus_emulator

                emulator = start_bus_emulator(list(axes_cfg.values()), cfg.loop.realtime)
                stack.callback(getattr(emulator, "close", None) or emulator.stop)   # after every backend's stop
                if getattr(emulator, "port", None):
                    for o in opts.values():
                        o["port"] = emulator.port
            for name, acfg in axes_cfg.items():
                backends[name] = make_backend(acfg.backend.name, opts[name])
                try:
                    preflight.check_config(acfg, backends[name].torque_limit)
                except ConfigError as exc:
                    raise ConfigError(f"axes.{name}.{exc.field}", str(exc)[len(exc.field) + 2:]) from None
            helpers: dict[str, Any] = {}
            for name, acfg in axes_cfg.items():
                backend, part = backends[name], parts[name]
                truth = acfg.axis_params()
                ex = acfg.excitation
                dt = backend.sample_period
                rrd_path, rec_path = paths[name]
                if sink != "off":       # each axis its own recording (rt_ident-x, rt_ident-y): a file, or the viewer
                    tel_cfg = (TelemetryConfig(sink="rrd", rrd_path=rrd_path, application_id=f"rt_ident-{name}")
                               if sink == "rrd" else
                               TelemetryConfig(sink="connect", connect_url=live_url, application_id=f"rt_ident-{name}"))
                    tel = TelemetryProcess(tel_cfg).start()
                    tel.set_truth({"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K,
                                   **modal_parameters(truth)})
                    part["telemetry"] = tel
                    helpers[f"telemetry-{name}"] = tel
                if rec_path:
                    meta = {**recording_metadata(acfg, dt), "axis_name": name}
                    part["recorder"] = RecorderProcess(rec_path, meta, overwrite=overwrite).start()
                q1, q2 = sensor_quanta(acfg)
                kf = AxisStateEstimator(dt, q1, q2, acfg.estimator.kalman_process_noise)
                est = make_streaming(acfg.estimator.method, dt=dt, period=ex.period_samples, band=ex.band,
                                     warmup_periods=acfg.loop.warmup_periods, forgetting=acfg.estimator.forgetting,
                                     lead=truth.lead, quanta=(q1, q2),
                                     process_noise=acfg.estimator.kalman_process_noise)
                worker = make_fit_worker(acfg.estimator.method, lead=truth.lead).start()
                stack.callback(worker.close)
                helpers[f"fit-{name}"] = worker
                warmup(kf, est, (acfg.loop.warmup_periods + 2) * ex.period_samples)
                control, ctl_worker = start_controller(acfg, backend, stack, (q1, q2))
                if ctl_worker is not None:
                    helpers[f"control-{name}"] = ctl_worker
                safety = preflight.safety_monitor(acfg, dt)
                tel, rec = part.get("telemetry"), part.get("recorder")
                loops[name] = IdentificationLoop(
                    backend, tick_hz=cfg.loop.tick_hz, excitation=make_excitation(acfg), state_estimator=kf,
                    estimator=est, safety=safety, duration=cfg.loop.duration, fit_worker=worker,
                    on_block=rec.put if rec else None, on_telemetry=tel.publish if tel else None,
                    on_fit=tel.publish_fit if tel else None, on_loop_gain=tel.publish_loop_gain if tel else None,
                    publish_every=cfg.telemetry.publish_every_ticks,
                    telemetry_stride=max(1, int(round(1.0 / (cfg.telemetry.rate_hz * dt)))),
                    stop_event=stop, control=control, probe_period=ex.period_samples,
                    friction=friction_estimator(acfg, dt, (q1, q2)),
                    friction_feedforward=acfg.control.friction_feedforward, compiled_tick=cfg.loop.compiled_tick)
            watch = HelperWatch(helpers, restartable=tuple(k for k in helpers if not k.startswith("recorder")))
            summary["_watch"] = watch

            trace = ContourTrace(loops, int(round(cfg.loop.duration * cfg.loop.tick_hz)))

            def hooks(n: int) -> None:
                trace()
                watch(n)
                if tick_hook is not None:
                    tick_hook(n)

            multi = MultiAxisLoop(loops, tick_hz=cfg.loop.tick_hz, duration=cfg.loop.duration, stop_event=stop,
                                  max_sleep_s=None if cfg.loop.max_sleep_us is None else cfg.loop.max_sleep_us * 1e-6,
                                  tick_hook=hooks, stall=preflight.stall_policy(cfg))
            for part in parts.values():
                if part.get("recorder") is not None:
                    part["recorder"].wait_ready(30.0)
                if part.get("telemetry") is not None:
                    part["telemetry"].wait_ready(10.0)
            for w in helpers.values():
                if hasattr(w, "wait_ready") and not isinstance(w, TelemetryProcess):
                    w.wait_ready(30.0)
            roles = {getattr(x, "pid", None): helper_role(n) for n, x in helpers.items()}
            roles.update({getattr(p.get("recorder"), "pid", None): "recorder" for p in parts.values()})
            roles.pop(None, None)
            summary["helper_processes"] = keep_off_loop_cpu(list(roles), cfg.loop.realtime,
                                                            device=getattr(emulator, "pid", None), roles=roles)
            realtime = LoopRealtime(cfg)
            stack.callback(realtime.end)               # on an error: after every backend's safe stop and close
            realtime.prepare()                         # slow, and before the devices watch our heartbeat
            for backend in backends.values():
                stack.enter_context(backend)           # open(); on exit (any axis's error too): safe stop, close
            for name, backend in backends.items():     # nothing energized that would trip on its first ticks
                start = backend.read_position()
                if start is not None:
                    preflight.check_start(axes_cfg[name], axes_cfg[name].axis_params().lead * start[1],
                                          backend.sample_period, where=name)
            summary["realtime"] = realtime.begin([multi.ticker])
            switch_interval = sys.getswitchinterval()
            stack.callback(sys.setswitchinterval, switch_interval)
            sys.setswitchinterval(5e-5)
            enabled = True
            for backend in backends.values():
                backend.activate()
            steal = HostSteal()
            irqs = LoopCpuInterrupts(steal.cpu)
            try:
                multi.run()
            finally:
                host["steal_ms"], host["steal_cpu"] = steal.elapsed_ms(), steal.cpu
                host["interrupts"] = irqs.summary()
                watch.freeze()
            for backend in backends.values():
                backend.safe_stop()                    # every axis at zero torque before the final fits
            realtime.end()                             # the final fits and the files are no real-time work
            for name, loop in loops.items():
                parts[name]["final_fit_error"] = final_fit(loop, loop.est)
    except RtIdentError as exc:
        if isinstance(exc, ConfigError) and not enabled:
            refused = exc                                  # refused before enabling: a one-line error, exit 2
        stop_cause = getattr(exc, "cause", "error")
        stop_axis = multi.failed_axis if multi is not None and multi.failed_axis is not None else \
            next((n for n, lp in loops.items() if _tripped(lp, exc)), None)
        stop_message = str(exc) + getattr(exc, "after_stall", "")
        log.info("run stopped: %s", exc)
        for name, loop in loops.items():
            parts[name]["final_fit_error"] = final_fit(loop, loop.est)
    finally:
        for sig, handler in old_signals.items():
            signal.signal(sig, handler)
        gc.enable()                                    # the loop froze and disabled it (real time)
        watch = summary.pop("_watch", None)
        files: dict[str, Any] = {}
        for name, part in parts.items():
            ax: dict[str, Any] = {}
            if part.get("recorder") is not None:
                ax["recording"] = part["recorder"].close()
                if not ax["recording"]["complete"]:
                    r = ax["recording"]
                    ax["data_lost"] = f"recording {r['path']} incomplete: {r['rows_written']} of {r['samples_put']}"
                    summary["data_lost"] = "; ".join(filter(None, [summary.get("data_lost"), f"{name}: {ax['data_lost']}"]))
            tel = part.get("telemetry")
            if tel is not None:
                t = tel.close()
                ax["telemetry"] = {"dropped": tel.dropped, "sent": tel.sent, **t}
                if t.get("write_error"):
                    summary["data_lost"] = "; ".join(filter(None, [summary.get("data_lost"),
                                                                  f"{name} dashboard: {t['write_error']}"]))
            else:
                ax["telemetry"] = {"dropped": 0, "sent": 0, "sink": "off"}
            files[name] = {"rrd": paths[name][0] if sink == "rrd" else None, "recording": paths[name][1]}
            ax["files"] = files[name]
            summary["axes"][name] = ax
        summary["files"] = files
        if watch is not None:
            summary["helpers"] = watch.summary()
        if multi is None or multi.stats.samples == 0:      # read nothing: leave no empty files behind
            for name in files:
                remove_empty_outputs(summary["axes"][name], files[name])
    if refused is not None:
        raise refused
    summary["stop"] = {"cause": stop_cause, "message": stop_message, "axis": stop_axis,
                       "interrupted": stop.is_set(),
                       "final_torque": {n: b.last_torque for n, b in backends.items()},
                       "backend_state": {n: b.state.value for n, b in backends.items()}}
    if emulator is not None and getattr(emulator, "stats", None) is not None:
        summary["emulator"] = emulator.stats if not callable(emulator.stats) else emulator.stats()
    if multi is not None:
        summary["loop"] = {**multi.stats.as_dict(), "host": host}
    if trace is not None:
        contour = trace.result(contour_png, contour_rrd, live_url)
        if contour is not None:
            summary["contour"] = contour
    for name, loop in loops.items():
        ax = summary["axes"][name]
        acfg = axes_cfg[name]
        ax.update({"backend": acfg.backend.name, "method": acfg.estimator.method,
                   "loop": {**loop.stats.as_dict(), "compiled_tick": loop.compiled_ticks},
                   "final_fit_error": parts[name].get("final_fit_error"),
                   "backend_counters": backend_counters(backends[name]),
                   "control": loop.control.summary() if loop.control is not None else {"mode": "off"}})
        fr = friction_summary(loop)
        if fr is not None:
            ax["friction"] = fr
        if loop.identification is not None:
            ax.update(ident_summary(loop.identification))
        ax.setdefault("parameters", None)
        truth = getattr(backends[name], "current_params", None) or acfg.axis_params()
        tr = {"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K, **modal_parameters(truth)}
        ax["truth"] = tr
        if ax["parameters"]:
            ax["error_pct"] = {k: 100.0 * (ax["parameters"][k] - v) / v for k, v in tr.items()}
    return summary


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

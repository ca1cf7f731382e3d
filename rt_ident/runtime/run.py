"""``rt-ident run``: build everything from a config, run the loop, always stop safely.

Order matters: the recorder and telemetry processes are spawned first (so
they do not inherit real-time scheduling), compiled kernels are warmed up,
then real-time treatment is requested for this process, the backend is
activated and the loop ticks. Whatever ends the loop (duration, Ctrl-C,
SIGTERM, a safety trip, a device fault, any exception) the backend's context
manager stops it: zero torque, drive disabled. Files are then closed and a
summary is returned.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from typing import Any


from drivers import make_backend
from rt_ident.axis.modal import modal_parameters
from rt_ident.config import RunConfig
from rt_ident.errors import ConfigError, RtIdentError
from rt_ident.estimators import make_streaming
from rt_ident.estimators.state_estimation import AxisStateEstimator
from rt_ident.runtime.emulation import start_emulator
from rt_ident.runtime.fit_worker import make_fit_worker
from rt_ident.runtime.helper_guard import HelperWatch
from rt_ident.runtime.host import HostSteal, LoopCpuInterrupts, LoopRealtime, keep_off_loop_cpu
from rt_ident.runtime.loop import IdentificationLoop
from rt_ident.runtime import preflight
from rt_ident.runtime.build import (backend_counters, backend_options, final_fit, friction_estimator, friction_summary,
                                    ident_summary, install_stop_signals, make_excitation, sensor_quanta, recording_metadata,
                                    start_controller, warmup)
from rt_ident.runtime.outputs import check_methods, prepare_outputs, remove_empty_outputs

log = logging.getLogger(__name__)


def run(cfg: RunConfig, *, rrd: str | None = None, record: str | None = None, sink: str | None = None,
        connect_url: str | None = None, stop_event: threading.Event | None = None,
        tick_hook=None, overwrite: bool = False) -> dict[str, Any]:
    """Run the loop described by ``cfg``; returns the summary (also on a safety stop).

    ``summary["stop"]["cause"]`` is ``None`` for a normal end (duration reached or Ctrl-C/SIGTERM)
    and a cause tag (``"watchdog"``, ``"travel-limit"``, ``"device-fault"``, ...) otherwise.
    """
    if cfg.axes:
        raise ConfigError("axes", "a config with several axes runs with rt_ident.runtime.multi.run_axes")
    from rt_ident.runtime.recording import RecorderProcess
    from rt_ident.runtime.telemetry import DEFAULT_PORT, TelemetryConfig, TelemetryProcess, serve_port

    stop = stop_event or threading.Event()
    truth = cfg.axis_params()
    sink = sink or cfg.telemetry.sink
    check_methods(cfg)
    rrd_path, rec_path = prepare_outputs(cfg, rrd, record, sink, overwrite)
    port = serve_port(cfg.telemetry.bind_ip, cfg.telemetry.port) if sink == "serve" else \
        (cfg.telemetry.port or DEFAULT_PORT)

    emulator = None
    opts = backend_options(cfg)
    if cfg.backend.emulate:
        emulator = start_emulator(cfg)
        if getattr(emulator, "port", None):          # serial: the board's pseudo-terminal
            opts["port"] = emulator.port
    backend = make_backend(cfg.backend.name, opts)
    ex = cfg.excitation
    summary: dict[str, Any] = {"backend": cfg.backend.name, "config": cfg.source, "method": cfg.estimator.method}
    host: dict[str, Any] = {"steal_ms": None, "steal_cpu": None, "interrupts": None}   # filled around loop.run()
    stop_cause = None
    stop_message = None
    enabled = False
    refused: ConfigError | None = None
    loop = None
    telemetry = recorder = watch = None
    old_signals = install_stop_signals(stop)
    try:
        with contextlib.ExitStack() as stack:
            if emulator is not None:
                stack.callback(getattr(emulator, "close", None) or emulator.stop)
            preflight.check_config(cfg, backend.torque_limit)
            if sink != "off":
                telemetry = TelemetryProcess(TelemetryConfig(sink=sink, rrd_path=rrd_path, connect_url=connect_url
                                                             or cfg.telemetry.connect_url,
                                                             bind_ip=cfg.telemetry.bind_ip, port=port))
                telemetry.start()
                if sink == "serve":
                    summary["serve_url"] = f"rerun+http://{_url_host(cfg.telemetry.bind_ip)}:{port}/proxy"
                    log.warning("dashboard served at %s (open with: rerun --connect %s)", summary["serve_url"],
                                summary["serve_url"])
                if cfg.backend.name == "sim":
                    telemetry.set_truth({"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K,
                                         **modal_parameters(truth)})
            dt = backend.sample_period                 # known from the config, before any I/O
            meta = recording_metadata(cfg, dt)
            if rec_path:
                recorder = RecorderProcess(rec_path, meta, overwrite=overwrite).start()
            q1, q2 = sensor_quanta(cfg)
            kf = AxisStateEstimator(dt, q1, q2, cfg.estimator.kalman_process_noise)
            est = make_streaming(cfg.estimator.method, dt=dt, period=ex.period_samples, band=ex.band,
                                           warmup_periods=cfg.loop.warmup_periods,
                                           forgetting=cfg.estimator.forgetting, lead=truth.lead, quanta=(q1, q2),
                                           process_noise=cfg.estimator.kalman_process_noise)
            worker = make_fit_worker(cfg.estimator.method, lead=truth.lead).start()
            stack.callback(worker.close)
            warmup(kf, est, (cfg.loop.warmup_periods + 2) * ex.period_samples)
            control, ctl_worker = start_controller(cfg, backend, stack, (q1, q2))
            safety = preflight.safety_monitor(cfg, dt)
            watch = HelperWatch({"telemetry": telemetry, "fit": worker, "control": ctl_worker},
                                restartable=("telemetry", "fit", "control"))
            user_hook = tick_hook

            def hooks(n: int) -> None:
                watch(n)
                if user_hook is not None:
                    user_hook(n)

            loop = IdentificationLoop(
                backend, tick_hz=cfg.loop.tick_hz, excitation=make_excitation(cfg), state_estimator=kf, estimator=est,
                safety=safety, duration=cfg.loop.duration, fit_worker=worker,
                on_block=recorder.put if recorder else None,
                on_telemetry=telemetry.publish if telemetry else None,
                on_fit=telemetry.publish_fit if telemetry else None,
                on_loop_gain=telemetry.publish_loop_gain if telemetry else None,
                publish_every=cfg.telemetry.publish_every_ticks,
                telemetry_stride=max(1, int(round(1.0 / (cfg.telemetry.rate_hz * dt)))),
                stop_event=stop, tick_hook=hooks,
                max_sleep_s=None if cfg.loop.max_sleep_us is None else cfg.loop.max_sleep_us * 1e-6,
                control=control, probe_period=ex.period_samples,
                friction=friction_estimator(cfg, dt, sensor_quanta(cfg)),
                friction_feedforward=cfg.control.friction_feedforward, compiled_tick=cfg.loop.compiled_tick,
                stall=preflight.stall_policy(cfg))
            if recorder is not None:
                recorder.wait_ready(30.0)               # its files exist and take bytes before the device moves
            if telemetry is not None:
                telemetry.wait_ready(5.0)
            for w in (worker, ctl_worker):               # imported and waiting before the device is active
                if w is not None and not w.wait_ready(30.0):
                    log.warning("%s not ready after 30 s: live estimates/redesigns will start late", w.name)
            named = [(n, getattr(x, "pid", None)) for n, x in (("telemetry", telemetry), ("recorder", recorder),
                                                               ("fit", worker), ("control", ctl_worker)) if x is not None]
            device = getattr(emulator, "pid", None)
            summary["helper_processes"] = keep_off_loop_cpu([p for _, p in named if p], cfg.loop.realtime,
                                                            device=device, roles={p: n for n, p in named if p})
            # pid -> helper, so that a report never names them by position (there is no recorder without recording)
            summary["helper_processes"]["names"] = {str(p): n for n, p in named if p}
            realtime = LoopRealtime(cfg)
            stack.callback(realtime.end)             # on an error: after the backend's safe stop and close
            realtime.prepare()                       # slow, and before the device watches our heartbeat
            # open as late as possible: a device streams from open() on and nobody reads it until the loop
            stack.enter_context(backend)             # open(); on exit: safe_stop() + close()
            start = backend.read_position()
            if start is not None:                    # nothing energized that would trip on its first ticks
                preflight.check_start(cfg, truth.lead * start[1], dt)
                summary["start_position_m"] = truth.lead * start[1]
            summary["realtime"] = realtime.begin([loop.ticker])
            # a backend's I/O threads (python-can's receiver, a SYNC sender) share this process's GIL:
            # hand it back within 50 us, not 5 ms (the hand-offs to helper processes use no thread: rt_ident.runtime.shm_ring)
            switch_interval = sys.getswitchinterval()
            stack.callback(sys.setswitchinterval, switch_interval)
            sys.setswitchinterval(5e-5)
            enabled = True
            backend.activate()
            steal = HostSteal()
            irqs = LoopCpuInterrupts(steal.cpu)
            try:
                loop.run()
            finally:
                host["steal_ms"], host["steal_cpu"] = steal.elapsed_ms(), steal.cpu
                host["interrupts"] = irqs.summary()
                watch.freeze()
            backend.safe_stop()                      # zero torque before the (slower) final fit
            realtime.end()                           # the final fit and the files are no real-time work
            summary["final_fit_error"] = final_fit(loop, est)
    except RtIdentError as exc:
        if isinstance(exc, ConfigError) and not enabled:
            refused = exc                            # refused before enabling: a one-line error, exit 2
        stop_cause = getattr(exc, "cause", "error")
        stop_message = str(exc) + getattr(exc, "after_stall", "")
        log.info("run stopped: %s", exc)        # the summary carries it (the CLI prints it once)
        if loop is not None:                         # nothing lost: still fit what was measured
            summary["final_fit_error"] = final_fit(loop, loop.est)
    finally:
        for sig, handler in old_signals.items():
            signal.signal(sig, handler)
        import gc

        gc.enable()
        files = {"rrd": rrd_path if sink == "rrd" else None, "recording": rec_path}
        if recorder is not None:
            summary["recording"] = recorder.close()
            if not summary["recording"]["complete"]:
                r = summary["recording"]
                summary["data_lost"] = (f"recording {r['path']} incomplete: {r['rows_written']} of "
                                        f"{r['samples_put']} samples written" +
                                        (f": {r['failure']}" if r.get("failure") else
                                         f" (recorder exit code {r['exitcode']})"))
        if telemetry is not None:
            tel = telemetry.close()
            summary["telemetry"] = {"dropped": telemetry.dropped, "sent": telemetry.sent, **tel}
            if tel.get("write_error"):
                lost = f"dashboard: {tel['write_error']}"
                summary["data_lost"] = f"{summary['data_lost']}; {lost}" if summary.get("data_lost") else lost
        else:
            summary["telemetry"] = {"dropped": 0, "sent": 0, "sink": "off"}
        summary["files"] = files
        if watch is not None:
            summary["helpers"] = watch.summary()
            if telemetry is not None and telemetry.earlier_rrd:
                files["rrd_earlier"] = list(telemetry.earlier_rrd)
                files["rrd"] = telemetry.config.rrd_path
        if loop is None or loop.stats.samples == 0:
            remove_empty_outputs(summary, files)
    if refused is not None:
        raise refused
    summary["stop"] = {"cause": stop_cause, "message": stop_message, "interrupted": stop.is_set(),
                       "final_torque": backend.last_torque, "backend_state": backend.state.value}
    summary["backend_counters"] = backend_counters(backend)
    if loop is not None:
        summary["loop"] = {**loop.stats.as_dict(), "host": host, "compiled_tick": loop.compiled_ticks}
        summary["control"] = loop.control.summary() if loop.control is not None else {"mode": "off"}
        fr = friction_summary(loop)
        if fr is not None:
            summary["friction"] = fr
        ident = loop.identification
        if ident is not None:
            summary.update(ident_summary(ident))
    summary.setdefault("parameters", None)
    if cfg.backend.name == "sim" or cfg.backend.emulate:
        truth = getattr(backend, "current_params", None) or truth    # after the last [[plant.change]]
        tr = {"I1": truth.I1, "I2": truth.I2, "B": truth.B, "K": truth.K, **modal_parameters(truth)}
        summary["truth"] = tr
        if summary["parameters"]:
            summary["error_pct"] = {k: 100.0 * (summary["parameters"][k] - v) / v for k, v in tr.items()}
    return summary


def _url_host(ip: str) -> str:
    return f"[{ip}]" if ":" in ip else ip


def exit_code(summary: dict[str, Any]) -> int:
    """0: ended as asked (duration, or a signal) with every sample recorded; 3: stopped by a fault,
    trip or error (safe stop); 4: ended, but samples were lost from the recording."""
    if summary["stop"]["cause"] is not None:
        return 3
    return 4 if summary.get("data_lost") else 0



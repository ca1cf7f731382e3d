"""What a run builds for each axis, shared by every way of running the loop (:mod:`rt_ident.compose.run`,
:mod:`rt_ident.compose.offline`) and by the checks before a start
(:mod:`rt_ident.compose.preflight`): the backend's options, the estimators, the controller, the probe,
the quantization steps, the recording's metadata, the warm-up of the compiled kernels, the signals that
stop a run and the summary's parts.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.config import RunConfig
from rt_ident.control import make_controller, redesign
from rt_ident.control.anchor import path_samples, split_reference_table
from rt_ident.errors import ConfigError, RtIdentError
from rt_ident.estimators import make_streaming
from rt_ident.estimators.state_estimation import AxisStateEstimator, encoder_quanta
from rt_ident.estimators.svf import make_svf
from rt_ident.loop.loop import IdentificationLoop
from rt_ident.loop.safety import SafetyMonitor
from rt_ident.loop.stall import StallPolicy
from rt_ident.outputs.paths import check_methods
from rt_ident.processes.jobs import JobProcess

log = logging.getLogger(__name__)

#: the sized speed limit is this multiple of the fastest motion the run asks for (a runaway at the
#: torque limit passes it within milliseconds; the probe's motion near the loop's crossover is
#: amplified above its rigid-body value)
SPEED_MARGIN = 2.0


def backend_options(cfg: RunConfig) -> dict[str, Any]:
    opts = cfg.backend.options()
    if cfg.backend.name == "sim":
        opts.setdefault("axis", cfg.axis_params().as_dict())
        if cfg.plant.change:
            opts.setdefault("changes", [dict(c) for c in cfg.plant.change])
    elif cfg.plant.change:
        raise ConfigError("plant.change", f"only the sim backend can change its plant mid-run "
                          f"(backend is {cfg.backend.name!r})")
    return opts

def per_sample_estimator(cfg: RunConfig, dt: float, quanta: tuple[float, float]):
    """The recursive estimator the adaptive controller follows (``[estimator] per_sample``), or None
    (not adaptive, switched off, or a sample rate too low for it: logged, the controller then
    follows the frequency fit)."""
    e = cfg.estimator
    if cfg.control.mode != "adaptive" or e.per_sample == "none":
        return None
    q = e.svf_quanta if e.svf_quanta is not None else quanta
    est, why = make_svf(dt, cfg.axis_params(), filter_hz=e.svf_hz, memory_s=e.svf_memory_s, quanta=q)
    if est is None:
        log.warning("per-sample estimator off (%s): the adaptive controller follows the frequency fit", why)
    return est

def friction_estimator(cfg: RunConfig, dt: float, quanta: tuple[float, float]):
    """The per-sample friction-model estimator of ``[estimator] model`` (None for ``two-inertia``)."""
    e = cfg.estimator
    if e.model == "two-inertia":
        return None
    from rt_ident.estimators.friction_stream import RecursiveFrictionEstimator

    hz = e.friction_hz or (800.0 if e.model == "two-inertia-friction" else 100.0)
    hz = min(hz, 0.25 / dt)
    return RecursiveFrictionEstimator(dt, e.model, filter_hz=hz, memory_s=e.friction_memory_s, quanta=quanta)

def friction_summary(loop) -> dict[str, Any] | None:
    """``{"model", "parameters", "feedforward"}`` of the loop's friction-model estimate, or None."""
    est = getattr(loop, "friction", None)
    if est is None:
        return None
    p = est.estimate()
    ff = getattr(getattr(loop.control, "law", None), "friction", None) if loop.control is not None else None
    return {"model": est.model, "parameters": p,
            "feedforward": None if ff is None else {"Fc": ff.Fc, "Fv": ff.Fv}}

def controller_for(cfg: RunConfig, backend, jobs, quanta: tuple[float, float] | None = None,
                   error_after_s: float | None = None):
    """The host's position controller for ``cfg`` (None with ``control.mode = "off"``), redesigning
    through ``jobs`` (a job process here, in-process jobs in :mod:`rt_ident.compose.offline`).
    ``error_after_s``: where the "after the change" error statistics start (default: 0.5 s after
    the last plant change)."""
    settings = cfg.control.settings()
    if settings.mode == "off":
        return None
    from rt_ident.control.anchor import split_reference_table
    from rt_ident.control.reference import make_reference

    table, options = split_reference_table(cfg.reference)
    last = cfg.plant.last_change_s()
    return make_controller(settings, cfg.axis_params(), tick=1.0 / cfg.loop.tick_hz,
                           torque_limit=backend.torque_limit, reference=make_reference(table),
                           jobs=jobs, error_after_s=error_after_s if error_after_s is not None
                           else None if last is None else last + 0.5,
                           per_sample=per_sample_estimator(cfg, backend.sample_period,
                                                           quanta or sensor_quanta(cfg)),
                           reference_options=options)

def start_controller(cfg: RunConfig, backend, stack: contextlib.ExitStack,
                     quanta: tuple[float, float] | None = None):
    """The host's position controller (None with ``control.mode = "off"``) and its redesign process."""
    jobs = None
    if cfg.control.mode == "adaptive":
        jobs = JobProcess(redesign, name="rt_ident-control", min_interval=0.0).start()
        stack.callback(jobs.close)
    return controller_for(cfg, backend, jobs, quanta), jobs

def state_and_streaming(cfg: RunConfig, dt: float):
    """The loop's state estimator (the Kalman filters of both angles) and its streaming estimator
    (``[estimator] method``) for samples ``dt`` apart."""
    truth, ex, e = cfg.axis_params(), cfg.excitation, cfg.estimator
    q1, q2 = sensor_quanta(cfg)
    kf = AxisStateEstimator(dt, q1, q2, e.kalman_process_noise)
    est = make_streaming(e.method, dt=dt, period=ex.period_samples, band=ex.band,
                         warmup_periods=cfg.loop.warmup_periods, forgetting=e.forgetting, lead=truth.lead,
                         quanta=(q1, q2), process_noise=e.kalman_process_noise)
    return kf, est


def identification_loop(cfg: RunConfig, backend, kf, est, safety, control, **extra: Any) -> IdentificationLoop:
    """The axis's :class:`IdentificationLoop` with everything its config sets (tick, duration, probe,
    telemetry windows, friction model, compiled tick, stall policy); ``extra``: the hand-offs, the
    clock, the ticker, or a tick rate and duration of the run's own."""
    dt = backend.sample_period
    opts: dict[str, Any] = dict(
        tick_hz=cfg.loop.tick_hz, duration=cfg.loop.duration, excitation=make_excitation(cfg),
        publish_every=cfg.telemetry.publish_every_ticks,
        telemetry_stride=max(1, int(round(1.0 / (cfg.telemetry.rate_hz * dt)))),
        max_sleep_s=None if cfg.loop.max_sleep_us is None else cfg.loop.max_sleep_us * 1e-6,
        probe_period=cfg.excitation.period_samples, friction=friction_estimator(cfg, dt, sensor_quanta(cfg)),
        friction_feedforward=cfg.control.friction_feedforward, compiled_tick=cfg.loop.compiled_tick,
        stall=stall_policy(cfg))
    opts.update(extra)
    return IdentificationLoop(backend, state_estimator=kf, estimator=est, safety=safety, control=control, **opts)


def make_excitation(cfg: RunConfig):
    ex = cfg.excitation
    if ex.kind == "none":
        return lambda seq: np.zeros(seq.shape)
    if ex.kind not in ("schroeder", "random"):
        raise RtIdentError(f"excitation.kind: the loop needs a periodic multisine ('schroeder' or 'random'), "
                           f"got {ex.kind!r}")
    ms = schroeder_multisine(ex.period_samples, ex.band, peak=ex.peak,
                             phases="schroeder" if ex.kind == "schroeder" else "random", seed=ex.seed)
    return ms.at

def final_fit(loop: IdentificationLoop, est) -> str | None:
    """Cold fit of everything seen (what `identify` replays); an error is reported, not raised."""
    try:
        final = est.final()
    except RtIdentError as exc:
        log.warning("final fit failed: %s", exc)
        return str(exc)
    if final is not None:
        loop.identification = final
        # the dashboard ends on the final fit's FRF: during a short run (or beside a busy machine) the
        # fit process may not have sent one, and the last it sent was of fewer samples
        try:
            if loop.on_fit is not None and getattr(final, "frf", None) is not None:
                loop.on_fit(max(loop._next_seq - 1, 0) * loop.backend.sample_period, final.frf)
            loop.publish_final()                     # ... and its estimate lines on the final values
        except RtIdentError as exc:
            log.warning("final estimate not sent to the dashboard: %s", exc)
    return None

def ident_summary(ident) -> dict[str, Any]:
    d = ident.as_dict()
    return {"parameters": d["parameters"], "ci95": d.get("ci95"), "trusted": d.get("trusted"),
            "trust": d.get("trust"), "method": d.get("method")}

def sensor_quanta(cfg: RunConfig) -> tuple[float, float]:
    opts = cfg.backend.options()
    lead = cfg.axis_params().lead
    cpr = int(opts.get("counts_per_rev", 2**17) or 2**17)
    res = float(opts.get("scale_resolution", 1e-7) or 1e-7)
    return encoder_quanta(cpr, res, lead)

def recording_metadata(cfg, dt: float) -> dict[str, Any]:
    """What a recording carries about its run: enough for ``rt-ident identify`` to replay the loop's estimator."""
    return {"backend": cfg.backend.name, "sample_period": dt, "axis": cfg.axis_params().as_dict(),
            "excitation": cfg.excitation.model_dump(), "method": cfg.estimator.method,
            "warmup_periods": cfg.loop.warmup_periods, "forgetting": cfg.estimator.forgetting}

def warmup(kf, est, n: int) -> None:
    """Compile/load every kernel before the first tick, on clones (the real state stays untouched).

    ``n`` covers the warm-up periods and one completed period, so the period-completion path of the
    streaming estimator is loaded here too, not at the first full period of the run.
    """
    import copy

    z = np.zeros(8)
    copy.deepcopy(kf).filter_block(z, z)
    w = copy.deepcopy(est)
    t = np.arange(n, dtype=float)
    w.update_block(np.sin(t * 0.1), np.sin(t * 0.1), np.cos(t * 0.1), np.arange(n))
    w.snapshot()

def backend_counters(backend) -> dict[str, Any] | None:
    """The link-health counters a backend keeps (CANopen: ``counters``; serial board: ``stats()``)."""
    for name in ("counters", "stats"):
        value = getattr(backend, name, None)
        try:
            value = value() if callable(value) else value
        except Exception:  # noqa: BLE001 - a summary must not fail on a closed device
            continue
        if isinstance(value, dict):
            return value
    return None


def check_axes(cfg: RunConfig) -> dict[str, RunConfig]:
    """The per-axis configs, refused in one line before anything starts when they cannot run."""
    axes = cfg.axis_configs()
    if len(axes) < 1:
        raise ConfigError("axes", "no axis configured")
    kinds = {acfg.backend.name for acfg in axes.values()}
    if len(axes) > 1 and (len(kinds) > 1 or not kinds <= {"sim", "canopen"}):
        name = next(n for n, a in axes.items() if a.backend.name != "sim")
        raise ConfigError(f"axes.{name}.backend.name", "several axes in one run need every axis on the sim backend, "
                          "or every axis a CiA 402 drive on one CAN bus (serial boards for several axes are not "
                          f"built); got {', '.join(sorted(kinds))}")
    if kinds == {"canopen"}:
        from drivers.cia402.config import check_shared_bus, validate

        if len({acfg.backend.emulate for acfg in axes.values()}) > 1:
            raise ConfigError("backend.emulate", "the drives on one bus are all emulated or all real")
        check_shared_bus([validate(acfg.backend.options()) for acfg in axes.values()])
    for name, acfg in axes.items():
        check_methods(acfg)
        from rt_ident.control.anchor import split_reference_table
        from rt_ident.control.reference import make_reference

        try:
            make_reference(split_reference_table(acfg.reference)[0])   # a bad reference is refused now
        except ConfigError as exc:
            raise ConfigError(f"axes.{name}.{exc.field}", str(exc)[len(exc.field) + 2:]) from None
    return axes


def probe_motion(cfg: RunConfig, sample_period: float) -> tuple[float, float]:
    """(peak speed [m/s], peak displacement [m]) the probing multisine alone gives the rigid axis,
    (I1 + I2) d2x/dt2 = lead T: the peaks of its periodic motion (the position loop removes the mean)."""
    ex = cfg.excitation
    if ex.kind == "none":
        return 0.0, 0.0
    from rt_ident.axis.excitation import schroeder_multisine

    ms = schroeder_multisine(ex.period_samples, ex.band, peak=ex.peak,
                             phases="schroeder" if ex.kind == "schroeder" else "random", seed=ex.seed)
    torque = np.asarray(ms.at(np.arange(ex.period_samples)), dtype=float)
    p = cfg.axis_params()
    v = np.cumsum(torque - torque.mean()) * sample_period * p.lead / (p.I1 + p.I2)
    v -= v.mean()
    x = np.cumsum(v) * sample_period
    return float(np.max(np.abs(v))), float(np.max(np.abs(x - x.mean())))

def reference_path(cfg: RunConfig):
    from rt_ident.control.reference import make_reference

    table, opts = split_reference_table(cfg.reference)
    return make_reference(table), opts

def max_speed(cfg: RunConfig, sample_period: float) -> float:
    """``[safety] max_speed_m_s``, or :data:`SPEED_MARGIN` x (the path's peak speed + its rejoin speed +
    the probe's own speed)."""
    if cfg.safety.max_speed_m_s is not None:
        return float(cfg.safety.max_speed_m_s)
    path, opts = reference_path(cfg)
    path_v = float(np.max(np.abs(path_samples(path)[1]))) if cfg.control.mode != "off" else 0.0
    return SPEED_MARGIN * (path_v + opts.limits.v_max + probe_motion(cfg, sample_period)[0])

def safety_monitor(cfg: RunConfig, sample_period: float) -> SafetyMonitor:
    """The host-side safety checks of ``cfg`` (:class:`SafetyMonitor`)."""
    s = cfg.safety
    p = cfg.axis_params()
    return SafetyMonitor(lead=p.lead, window=s.window, max_decel=s.max_decel,
                         watchdog_ticks=s.watchdog_ticks, stuck_torque=cfg.stuck_torque(), torque_hold=s.torque_hold,
                         max_speed=max_speed(cfg, sample_period), inertia=p.I1 + p.I2)

def stall_policy(cfg: RunConfig) -> StallPolicy:
    s = cfg.safety
    after = s.stall_after(cfg.loop.tick_hz)
    return StallPolicy(after, s.on_stall, max(s.max_stall_stop_s, after))

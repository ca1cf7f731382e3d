"""What a run checks and sizes from its config before any device is enabled.

* :func:`preflight`: builds what the run builds (the backend without I/O, the emulated device's
  model, the estimators, the excitation, the controller, the safety monitor, the ticker) and drops
  it, before a process is started or a device opened: a setting they refuse surfaces as one
  :class:`~rt_ident.errors.ConfigError` naming it (the CLI's exit 2), not as a stop halfway through a
  start. Cheap: no kernel compiled, no process started, no file written;
* :func:`safety_monitor` and :func:`stall_policy`: the host-side checks of ``[safety]``, with the
  speed limit sized from what the axis is asked to do when the config leaves it open;
* :func:`check_config`: the probing multisine against the torque limit, the reference against the speed
  limit and the torque it takes (:func:`check_reference`), and no host control only where something else
  holds the axis;
* :func:`check_start`: the table's position when the device is opened, against the window, the
  reference and the probe's own motion, so that nothing is energized that would trip on its first
  ticks; :func:`check_settings` and :func:`check_unit`: what the opened device reports of its settings
  and which unit it is, against ``[backend]`` and the commissioning on record.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from drivers import BackendNotFound, make_backend
from drivers.base import describe_unit, settings_differ, unit_of
from rt_ident.compose.build import (
    backend_options,
    check_axes,
    controller_for,
    friction_estimator,
    make_excitation,
    probe_motion,
    reference_path,
    safety_monitor,
    sensor_quanta,
)
from rt_ident.config import RunConfig
from rt_ident.control.anchor import path_samples
from rt_ident.errors import ConfigError
from rt_ident.estimators import make_streaming
from rt_ident.estimators.state_estimation import AxisStateEstimator
from rt_ident.loop.scheduler import Ticker
from rt_ident.outputs.paths import check_methods

log = logging.getLogger(__name__)

#: the probe may take at most this share of the torque limit: the position loop needs the rest
PROBE_SHARE = 0.5


def drive_holds(cfg: RunConfig) -> bool:
    """Whether something besides the host holds the axis: the sim's or an emulator's drive-side
    position loop, or a real drive the user declares in a position mode (``[control] drive_holds``)."""
    if cfg.control.drive_holds:
        return True
    if cfg.backend.name == "sim":
        return bool(cfg.backend.options().get("position_hold", False))
    if cfg.backend.emulate:
        emu = cfg.emulator or {}
        return bool(emu.get("position_hold" if cfg.backend.name == "canopen" else "hold", False))
    return False


def check_config(cfg: RunConfig, torque_limit: float) -> None:
    """What the config gets wrong whatever the axis does: the probe's peak above :data:`PROBE_SHARE` of the
    torque limit (the clamped sum is no longer the multisine, and what is left does not hold the table);
    a stall threshold inside the time the drive holds the last plan; no host control on an axis nothing
    else holds (a torque-mode axis walks off under the probe)."""
    ex = cfg.excitation
    if ex.kind != "none" and ex.peak > PROBE_SHARE * torque_limit:
        raise ConfigError("excitation.peak", f"{ex.peak:g} N m is more than {PROBE_SHARE:g} x the torque limit "
                          f"({torque_limit:g} N m): the position loop needs the rest; lower the peak")
    held = cfg.safety.torque_hold + 2.0 / cfg.loop.tick_hz      # the plan (two ticks) and its lease
    after = cfg.safety.stall_after(cfg.loop.tick_hz)
    if after <= held:
        raise ConfigError("safety.max_stall_s", f"{after:g} s is within the {held:g} s the drive holds the last plan "
                          "(torque_hold + 2 ticks): a resume would assume the torque dropped while the drive still "
                          "applies it; make it longer")
    if cfg.control.mode != "off":
        check_reference(cfg, torque_limit)
    if cfg.control.mode == "off" and not drive_holds(cfg):
        raise ConfigError("control.mode", "'off' leaves a torque-mode axis with nothing holding it; run with "
                          "control, or give it a drive-side hold ([control] drive_holds = true for a real drive "
                          "in a position mode, position_hold / hold for the sim and the emulators)")


def check_reference(cfg: RunConfig, torque_limit: float) -> None:
    """The reference within what the safety limits allow and the axis can do: its peak speed within a set
    ``[safety] max_speed_m_s`` (else the run trips on it; unset, the limit is sized from the reference), and the
    torque its peak acceleration takes at ``[axis]`` I1 + I2 within what the torque limit leaves beside the
    probe (else the loop saturates and the table lags the path by millimetres, a typo such as
    ``frequency_hz = 20`` for 2 asking for g's of the table)."""
    path, _ = reference_path(cfg)
    # ~7 samples a tick on a grid no tick or common frequency divides: a path at a multiple of the tick rate
    # (a 1 kHz circle on a 1 kHz tick) does not hide its peaks between the samples
    _, v, a = path_samples(path, step_s=1.0 / (7.31 * cfg.loop.tick_hz))
    v_peak = float(np.max(np.abs(v))) if v.size else 0.0
    a_peak = float(np.max(np.abs(a))) if a.size else 0.0
    limit = cfg.safety.max_speed_m_s
    if limit is not None and v_peak > limit:
        raise ConfigError("reference", f"its peak speed {v_peak * 1e3:.4g} mm/s is above safety.max_speed_m_s "
                          f"({limit * 1e3:.4g} mm/s): the run would trip on it; slow the reference or raise the limit")
    p = cfg.axis_params()
    need = (p.I1 + p.I2) * a_peak / p.lead
    room = torque_limit - (cfg.excitation.peak if cfg.excitation.kind != "none" else 0.0)
    if not need <= room:
        raise ConfigError("reference", f"its peak acceleration {a_peak:.4g} m/s^2 takes {need:.4g} N m at [axis] "
                          f"I1 + I2, more than the {room:.4g} N m the torque limit ({torque_limit:g} N m) leaves "
                          "beside the probe: the table would lag the path; slow the reference (its speed, "
                          "frequency or size)")


def check_start(cfg: RunConfig, x: float, sample_period: float, where: str = "") -> None:
    """Refuse to enable a device whose table at ``x`` [m] is outside the safety window, or whose run
    would leave it: the reference (from where the table is, or from the scale's origin with
    ``origin = "scale"``) and the probe's own motion must stay inside."""
    lo, hi = cfg.safety.window
    name = f"axis {where}: " if where else ""
    span = f"safety.window [{lo * 1e3:.3f}, {hi * 1e3:.3f}] mm"
    if not math.isfinite(x):
        raise ConfigError("safety.window", f"{name}the table's position reads {float(x)}; check the scale")
    if not lo <= x <= hi:
        raise ConfigError("safety.window", f"{name}the table is at {x * 1e3:.3f} mm, outside {span}: move it inside "
                          "before enabling, or widen the window")
    shake = probe_motion(cfg, sample_period)[1]
    low = high = x
    if cfg.control.mode != "off":
        path, opts = reference_path(cfg)
        xs = path_samples(path)[0]
        origin = x - float(path.point(0.0)[0]) if opts.origin == "enable" else 0.0
        low, high = min(x, origin + float(xs.min())), max(x, origin + float(xs.max()))
    if low - shake < lo or high + shake > hi:
        raise ConfigError("reference", f"{name}the run would take the table over [{(low - shake) * 1e3:.3f}, "
                          f"{(high + shake) * 1e3:.3f}] mm (the table at {x * 1e3:.3f} mm, the reference with "
                          f"origin = {opts.origin if cfg.control.mode != 'off' else '-'}, the probe's "
                          f"+-{shake * 1e6:.1f} um), outside {span}")


def preflight(cfg: RunConfig, *, sink: str | None = None, connect_url: str | None = None) -> None:
    """Raise the first :class:`ConfigError` a run of ``cfg`` would meet while starting (``sink``,
    ``connect_url``: the command line's, as :func:`rt_ident.compose.run.run` takes them)."""
    _telemetry(cfg, sink or cfg.telemetry.sink, connect_url or cfg.telemetry.connect_url)
    if not cfg.axes:
        _axis(cfg)
        return
    for name, acfg in check_axes(cfg).items():
        try:
            _axis(acfg)
        except ConfigError as exc:
            msg = str(exc)[len(exc.field) + 2:] if str(exc).startswith(f"{exc.field}: ") else str(exc)
            raise ConfigError(f"axes.{name}.{exc.field}", msg) from None


def _axis(cfg: RunConfig) -> None:
    check_methods(cfg)
    truth = cfg.axis_params()
    opts = backend_options(cfg)
    if cfg.backend.emulate:
        _emulator(cfg)
        if cfg.backend.name == "serial":
            opts.setdefault("port", "emulated")        # the run hands the emulated board's pty over
    try:
        backend = make_backend(cfg.backend.name, opts)    # validates its options, opens nothing
    except BackendNotFound as exc:
        raise ConfigError("backend.name", str(exc)) from None
    dt = backend.sample_period
    q = sensor_quanta(cfg)
    AxisStateEstimator(dt, *q, cfg.estimator.kalman_process_noise)
    ex = cfg.excitation
    make_streaming(cfg.estimator.method, dt=dt, period=ex.period_samples, band=ex.band,
                   warmup_periods=cfg.loop.warmup_periods, forgetting=cfg.estimator.forgetting, lead=truth.lead,
                   quanta=q, process_noise=cfg.estimator.kalman_process_noise)
    make_excitation(cfg)
    controller_for(cfg, backend, None, q)
    friction_estimator(cfg, dt, q)
    safety_monitor(cfg, dt)
    check_config(cfg, backend.torque_limit)
    Ticker(1.0 / cfg.loop.tick_hz, max_sleep_s=None if cfg.loop.max_sleep_us is None else cfg.loop.max_sleep_us * 1e-6)


def _telemetry(cfg: RunConfig, sink: str, connect_url: str | None) -> None:
    from rt_ident.outputs.sinks import DEFAULT_PORT, TelemetryConfig, spawn_refusal

    try:
        tel = TelemetryConfig(sink=sink, rrd_path="check.rrd", connect_url=connect_url,
                              bind_ip=cfg.telemetry.bind_ip, port=cfg.telemetry.port or DEFAULT_PORT)
    except ConfigError as exc:
        field = {"connect_url": "--connect / telemetry.connect_url"}.get(exc.field, f"telemetry.{exc.field}")
        raise ConfigError(field, str(exc)[len(exc.field) + 2:]) from None
    why = spawn_refusal(tel)
    if why:
        raise ConfigError("--spawn / telemetry.sink", why)


def _emulator(cfg: RunConfig) -> None:
    """The emulated device's own options (``[emulator]``), as the emulator will read them."""
    if cfg.backend.name == "serial":
        from drivers.encoder_board.config import parse_emulator

        parse_emulator(dict(cfg.emulator))
    elif cfg.backend.name == "canopen":
        from drivers.cia402.emulator import build_emulator_for

        build_emulator_for(cfg)                       # the drive's model, not started: no bus opened


def check_settings(backend: Any, cfg: RunConfig) -> None:
    """A device that reports its angles' scales or its sample rate unlike ``[backend]`` is refused before it
    is enabled: the position loop would close on angles off by that factor."""
    differ = settings_differ(backend.identity(), cfg.backend.options())
    if differ:
        key, (dev, told) = next(iter(differ.items()))
        raise ConfigError(f"backend.{key}", f"the device reports {dev:g}, the config says {told:g}: correct "
                                            f"backend.{key} (rt-ident commission checks every such setting)")


def check_unit(backend: Any, expected: dict[str, Any], required: bool, summary: dict[str, Any], axis: str) -> None:
    """The device opened is the unit its commissioning was of. Another unit in its place (or one that no
    longer says which it is) is refused with ``--require-commissioned``; else named at once and in the summary
    (``commissioned_unit``, per axis name, ``""`` for a run of one): that commissioning is not its own."""
    found = unit_of(backend.identity())
    if found == expected:
        return
    said = f"is {describe_unit(found)}" if found else "did not say which unit it is (no serial number at open)"
    where = f"axis {axis}: " if axis else ""
    msg = (f"{where}the device opened {said}, but the commissioning on record is of {describe_unit(expected)}: "
           "this unit has not been commissioned (run `rt-ident commission` on it)")
    if required:
        raise ConfigError("--require-commissioned", msg)
    log.warning(msg)
    summary.setdefault("commissioned_unit", {})[axis] = {"expected": expected, "found": found, "message": msg}


__all__ = ["check_config", "check_settings", "check_start", "check_unit", "drive_holds", "preflight"]

"""Check a run config by building what the run builds before it starts a process or opens a device.

:func:`preflight` constructs the backend (no I/O), the emulated device's model, the estimators,
the excitation, the controller, the safety monitor and the ticker, and drops them. A setting
they refuse surfaces here as one :class:`~rt_ident.errors.ConfigError` naming it (the CLI's exit
2), before anything is spawned, energized or written, rather than as a stop halfway through a
start. Cheap: no kernel is compiled, no process started, no file written.
"""

from __future__ import annotations

from drivers import BackendNotFound, make_backend
from rt_ident.config import RunConfig
from rt_ident.errors import ConfigError
from rt_ident.estimators import make_streaming
from rt_ident.estimators.state_estimation import AxisStateEstimator
from rt_ident.runtime.outputs import check_methods
from rt_ident.runtime.run import _excitation, _quanta, backend_options, controller_for, friction_estimator
from rt_ident.runtime.safety import SafetyMonitor
from rt_ident.runtime.scheduler import Ticker


def preflight(cfg: RunConfig, *, sink: str | None = None, connect_url: str | None = None) -> None:
    """Raise the first :class:`ConfigError` a run of ``cfg`` would meet while starting (``sink``,
    ``connect_url``: the command line's, as :func:`rt_ident.runtime.run.run` takes them)."""
    _telemetry(cfg, sink or cfg.telemetry.sink, connect_url or cfg.telemetry.connect_url)
    if not cfg.axes:
        _axis(cfg)
        return
    from rt_ident.runtime.multi import check_axes

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
    quanta = _quanta(cfg)
    AxisStateEstimator(dt, *quanta, cfg.estimator.kalman_process_noise)
    ex = cfg.excitation
    make_streaming(cfg.estimator.method, dt=dt, period=ex.period_samples, band=ex.band,
                   warmup_periods=cfg.loop.warmup_periods, forgetting=cfg.estimator.forgetting, lead=truth.lead,
                   quanta=quanta, process_noise=cfg.estimator.kalman_process_noise)
    _excitation(cfg)
    controller_for(cfg, backend, None, quanta)
    friction_estimator(cfg, dt, quanta)
    SafetyMonitor(lead=truth.lead, window=tuple(cfg.safety.window), max_decel=cfg.safety.max_decel,
                  watchdog_ticks=cfg.safety.watchdog_ticks, stuck_torque=cfg.stuck_torque(),
                  torque_hold=cfg.safety.torque_hold)
    Ticker(1.0 / cfg.loop.tick_hz, max_sleep_s=None if cfg.loop.max_sleep_us is None else cfg.loop.max_sleep_us * 1e-6)


def _telemetry(cfg: RunConfig, sink: str, connect_url: str | None) -> None:
    from rt_ident.runtime.telemetry import TelemetryConfig

    try:
        TelemetryConfig(sink=sink, rrd_path="check.rrd", connect_url=connect_url, bind_ip=cfg.telemetry.bind_ip)
    except ConfigError as exc:
        field = {"connect_url": "--connect / telemetry.connect_url"}.get(exc.field, f"telemetry.{exc.field}")
        raise ConfigError(field, str(exc)[len(exc.field) + 2:]) from None


def _emulator(cfg: RunConfig) -> None:
    """The emulated device's own options (``[emulator]``), as the emulator will read them."""
    if cfg.backend.name == "serial":
        from drivers.encoder_board.config import parse_emulator

        parse_emulator(dict(cfg.emulator))
    elif cfg.backend.name == "canopen":
        from drivers.cia402.emulator import build_emulator_for

        build_emulator_for(cfg)                       # the drive's model, not started: no bus opened

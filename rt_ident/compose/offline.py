"""The same loop, faster than real time: for benchmarks and tests of the closed loop.

:func:`run_offline` builds what :func:`rt_ident.compose.run.run` builds - the backend from the
config (the ``sim`` backend, free-running), the state estimator, the streaming estimator, the
host's controller and the :class:`~rt_ident.loop.loop.IdentificationLoop` itself - but ticks
on a :class:`VirtualClock` and runs the two workers in-process (:class:`InlineJobs`), with the
latency and the duty cycle the real job processes have, counted in virtual time. Nothing is
recorded and no telemetry is sent; nothing else differs from a real-time run, so a result here
is what the loop's code does, not what a model of it does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from rt_ident.axis.modal import modal_parameters
from rt_ident.compose import preflight
from rt_ident.compose.build import (
    backend_options,
    controller_for,
    friction_summary,
    identification_loop,
    recording_metadata,
    safety_monitor,
    state_and_streaming,
    warmup,
)
from rt_ident.config import RunConfig
from rt_ident.control import redesign
from rt_ident.errors import ConfigError
from rt_ident.estimators.streaming import fit_snapshot
from rt_ident.loop.loop import IdentificationLoop
from rt_ident.loop.scheduler import Ticker
from rt_ident.processes.jobs import newest_result


class VirtualClock:
    """A monotonic clock that only a sleep advances (the Ticker's clock and sleeper)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)


@dataclass
class InlineJobs:
    """Jobs run in this process (a job process's stand-in): the result of ``submit`` becomes visible to
    ``poll`` ``latency`` (virtual) seconds later, and the next job is taken ``min_interval`` after.
    ``cpu_latency``: at least the CPU time the job took here (a job process with a core of its own)."""

    job: Callable[[Any], Any]
    clock: VirtualClock
    latency: float = 0.1
    min_interval: float = 0.25
    cpu_latency: bool = False
    fits: int = 0
    errors: int = 0
    skipped: int = 0
    last_error: str | None = None
    _due: list = field(default_factory=list)
    _busy_until: float = 0.0

    @property
    def ready(self) -> bool:
        return self.clock() >= self._busy_until

    def submit(self, request: Any) -> bool:
        if request is None:
            return False
        if not self.ready:
            self.skipped += 1
            return False
        now = self.clock()
        c0 = time.process_time()
        try:
            result: Any = self.job(request)
        except Exception as exc:  # noqa: BLE001 - like the job process: reported, not raised
            result = exc
        latency = max(self.latency, time.process_time() - c0) if self.cpu_latency else self.latency
        self._due.append((now + latency, result))
        self._busy_until = now + max(latency, self.min_interval)
        return True

    def poll(self) -> Any:
        return self.unpack(self.take())

    def take(self) -> list:
        """The results due by now (as :meth:`rt_ident.processes.jobs.JobProcess.take`)."""
        now = self.clock()
        n = 0
        while n < len(self._due) and self._due[n][0] <= now:
            n += 1
        done, self._due = self._due[:n], self._due[n:]
        return [item for _, item in done]

    def unpack(self, items: list) -> Any:
        return newest_result(self, items) if items else None

    def close(self) -> None:
        self._due.clear()


def run_offline(cfg: RunConfig, *, tick_hook: Callable[[IdentificationLoop], None] | None = None,
                fit_latency: float = 0.1, design_cpu_latency: bool = False, record: str | None = None,
                overwrite: bool = False,
                loop_options: dict[str, Any] | None = None, paced: bool = False,
                error_after_s: float | None = None) -> dict[str, Any]:
    """Run ``cfg`` (a ``sim`` backend) on virtual time; returns identification, control and truth.

    ``tick_hook(loop)`` is called after every tick (e.g. to swap in an oracle controller).
    ``record``: write every sample to this ``.parquet`` with the metadata ``rt-ident run`` writes (in
    this process: the recorder of :mod:`rt_ident.processes.recorder`, no helper process).
    ``loop_options``: more keyword arguments of the :class:`IdentificationLoop` (e.g. a telemetry
    consumer ``on_telemetry``). ``paced``: the sim produces the samples due on the virtual clock, as
    on the wall clock in a real run (a hook that advances ``loop.clock.now`` then stalls the loop).
    ``design_cpu_latency``: a redesign's answer arrives after the CPU time the design took here (at
    least 50 ms), not after a fixed 50 ms.
    ``error_after_s``: where the controller's "after the change" error statistics start (default 0.5 s
    after the last plant change).
    """

    if cfg.backend.name != "sim":
        raise ConfigError("backend.name", "the offline loop runs the sim backend only")
    from drivers.sim import SimBackend

    clock = VirtualClock()
    backend = SimBackend({**backend_options(cfg), "paced": paced}, clock=clock)
    dt = backend.sample_period
    truth = cfg.axis_params()
    ex = cfg.excitation
    kf, est = state_and_streaming(cfg, dt)
    fit = None if ex.kind == "none" else \
        InlineJobs(partial(fit_snapshot, cfg.estimator.method, lead=truth.lead), clock, latency=fit_latency)
    ctl = controller_for(cfg, backend, InlineJobs(redesign, clock, latency=0.05, min_interval=0.0,
                                                  cpu_latency=design_cpu_latency),
                         error_after_s=error_after_s)
    warmup(kf, est, (cfg.loop.warmup_periods + 2) * ex.period_samples)
    recorder = None
    if record is not None:
        from rt_ident.processes.recorder import Recorder

        recorder = Recorder(record, recording_metadata(cfg, dt), flush_interval=1e9, overwrite=overwrite)
        recorder.open()
    loop: IdentificationLoop          # the tick hook below reads it
    loop = identification_loop(
        cfg, backend, kf, est, safety_monitor(cfg, dt), ctl, fit_process=fit, clock=clock,
        ticker=Ticker(1.0 / cfg.loop.tick_hz, clock=clock, sleeper=clock.sleep, spin_s=0.0, max_sleep_s=None),
        tick_hook=None if tick_hook is None else (lambda _n: tick_hook(loop)),
        **{"on_block": None if recorder is None else
           (lambda b: recorder.append(b.t, b.seq, b.theta1, b.theta2, b.torque_cmd, b.torque_meas)),
           **(loop_options or {})})
    stop = None
    with backend:
        start = backend.read_position()
        if start is not None:                           # (the sim always says)
            preflight.check_start(cfg, truth.lead * start[1], dt)
        backend.activate()
        try:
            loop.run()
        except Exception as exc:  # noqa: BLE001 - a stop is a result here (the bench counts it)
            stop = f"{type(exc).__name__}: {exc}{getattr(exc, 'after_stall', '')}"
        finally:
            if recorder is not None:
                recorder.close()
    now = getattr(backend, "current_params", None) or truth
    x_end = float(truth.lead * backend.plant.state[2])      # the true table position when the run ended
    out: dict[str, Any] = {"stop": stop, "loop": loop.stats.as_dict(), "table_end_m": x_end,
                           "control": ctl.summary() if ctl is not None else {"mode": "off"},
                           "friction": friction_summary(loop), "torque_estimate": loop.torque_estimate(),
                           "truth": {"I1": now.I1, "I2": now.I2, "B": now.B, "K": now.K, **modal_parameters(now)}}
    ident = loop.identification
    if ident is not None:
        d = ident.as_dict()
        out["parameters"], out["trusted"] = d["parameters"], d["trusted"]
    return out

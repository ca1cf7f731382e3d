"""``rt-ident commission``: check that the host's picture of an axis matches the axis, in stages, each
only after the one before passed, the host's position controller off until stage c.

a. connect: open the device, read what it says it is (:meth:`drivers.base.Backend.identity`) and where
   the table stands (inside the window, with the travel budget around it);
b. probe: open-loop torque pulses each way (:mod:`rt_ident.commission.probe`), bounded by
   ``[commission] travel_m`` and ``max_speed_m_s``: positive torque moves theta1 positive, the scale
   follows the motor at ``lead``, the acceleration per N m is within x3 of 1/(I1 + I2), the breakaway;
c. identify: a run holding with the conservative controller and the probing multisine;
d. verify: the model controller designed on the identified axis, its margins, and a small move measured
   against the same move on the identified model (the sim backend, on virtual time: the prediction
   has no host timing in it);
e. the report (HTML), the ``[axis]`` snippet, ``commission.json``, and the record ``run`` consults.

Every failed check names the config key to change. Whatever happens, the device ends at zero torque and
disabled (the backend's context manager), and every emulator this starts is stopped.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import gc
import json
import logging
import math
import os
import signal
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.commission.checks import check, probe_checks, probe_limits, scaled_torque_note
from rt_ident.commission.probe import LAPSED_RETRIES, ProbeError, Prober
from rt_ident.config import RunConfig, from_mapping
from rt_ident.errors import ConfigError, RtIdentError, ask_realtime, host_fix
from rt_ident.processes.guard import stop_signals

log = logging.getLogger(__name__)

#: the sim's stage-d prediction may differ from the measured move by this (overshoot, max error) + a floor
VERIFY_FACTOR, VERIFY_FLOOR_M = 2.0, 10e-6
#: a verification move the host disturbed (``host_trouble``) is run again this many times: a stall's
#: rejoin or lost samples are not the axis's response
STALLED_MOVE_RETRIES = 1

#: lost samples that disturb a run that passed (``host_trouble``): this share of the samples, or one gap this
#: long (the loop's default stall limit)
LOST_SHARE, LOST_GAP_S = 0.01, 0.01
#: a run that failed with more of its ticks late than this: the host's doing too (a device paced by its own
#: clock moves on under the held torque while the loop is late)
OVERRUN_SHARE = 0.01

Progress = Callable[[str], None]

def host_trouble(summary: dict[str, Any], sample_period: float, run_failed: bool = True) -> str | None:
    """What the host did to a run that no axis setting explains: a stop the run put on the host (its fix
    names ``loop.realtime``: a drive that stopped hearing the host, an emulated device starved), a loop
    stall, samples lost on the device's link, or many late ticks; else None. ``run_failed`` (a run that
    stopped or failed its check: the gaps may be why): any lost sample counts; else only enough to change what the run
    measures (more than ``LOST_SHARE`` of them, or one gap of ``LOST_GAP_S`` or longer): a move over a
    few short gaps measures the axis all the same. Overruns count only in a run that failed, and when
    more than ``OVERRUN_SHARE`` of its ticks: a non-real-time loop has a few in most runs."""
    loop = summary.get("loop") or {}
    stalls = loop.get("stalls") or {}
    said = []
    stop = summary.get("stop") or {}
    if str(stop.get("fix") or "").startswith("loop.realtime"):     # the run itself put its end on the host
        said.append(f"the run stopped ({stop.get('cause')}: {stop.get('message')})")
    if stalls.get("count") and stop.get("cause") != "loop-stall":     # a loop-stall stop has said it
        said.append(f"the loop stalled {stalls['count']} time(s), for {float(stalls.get('longest_ms') or 0):.0f} ms "
                    "at longest")
    lost = int(loop.get("lost_samples") or 0)
    longest = int(loop.get("lost_longest", lost) or 0)      # a summary without it: as if all in one gap
    if lost and (run_failed or lost > LOST_SHARE * int(loop.get("samples") or 0)
                 or longest * sample_period >= LOST_GAP_S):
        said.append(f"the device's link lost {lost} samples ({1e3 * longest * sample_period:.1f} ms at longest)")
    overruns, ticks = int(loop.get("overruns") or 0), int(loop.get("ticks") or 0)
    if run_failed and overruns > OVERRUN_SHARE * ticks > 0:
        late_ms = float((loop.get("lateness_us") or {}).get("max") or 0.0) / 1e3
        said.append(f"the loop was late on {overruns} of {ticks} ticks ({late_ms:.1f} ms at most)")
    return " and ".join(said) or None


def _connect_and_probe(cfg: RunConfig, result: dict[str, Any], progress: Progress) -> bool:
    """Stages a and b. True when every check passed."""
    from drivers import make_backend
    from drivers.base import settings_differ
    from rt_ident.compose.build import backend_options
    from rt_ident.loop.host import LoopRealtime, keep_off_loop_cpu
    checks = result["checks"]
    with contextlib.ExitStack() as stack:
        progress("a: connect")
        result["stage_reached"] = "a"
        emulator: Any = None
        if cfg.backend.emulate:
            from rt_ident.processes.emulation import start_emulator

            emulator = start_emulator(cfg)
            stack.callback(getattr(emulator, "close", None) or emulator.stop)
            if getattr(emulator, "pid", None):         # off the loop's CPU, as a run places it
                keep_off_loop_cpu([], cfg.loop.realtime, device=emulator.pid)
        opts = backend_options(cfg)
        if getattr(emulator, "port", None):
            opts["port"] = emulator.port
        backend = make_backend(cfg.backend.name, opts)
        # stage b's real time, its slow part (a collection that holds the GIL, the CPU claim) before the device
        # is opened and watches the host's heartbeat; its end after the device's stop
        realtime = LoopRealtime(cfg.model_copy(update={"loop": cfg.loop.model_copy(update={"idle_poll": False})}))
        stack.callback(gc.enable)                    # real time froze and disabled the collector, as in a run
        stack.callback(realtime.end)
        realtime.prepare()
        try:
            stack.enter_context(backend)                 # on exit, whatever happened: zero torque, disabled
        except RtIdentError as exc:
            key = exc.field if isinstance(exc, ConfigError) else "backend"
            checks.append(check("connect", False, str(exc), "the device answers and matches the config", key))
            return False
        result["identity"] = {**backend.identity(), **backend.signs}
        checks.append(check("connect", True, backend.name, "the device answers"))
        differ = settings_differ(result["identity"], cfg.backend.options())
        checks.append(check("device settings", not differ,
                            {k: v[0] for k, v in differ.items()} or "as configured",
                            "what [backend] says, where the device reports it",
                            ", ".join(f"backend.{k}: the device reports {v[0]:g}, the config says {v[1]:g}"
                                      for k, v in differ.items())))
        if differ:
            return False
        pos = backend.read_position()
        x = None if pos is None else cfg.axis_params().lead * pos[1]
        lo, hi = cfg.safety.window
        budget = cfg.commission.travel_m
        inside = x is None or (lo <= x - budget and x + budget <= hi)
        fix = ("safety.window (or move the table toward the middle of its travel)" if hi - lo >= 2 * budget else
               f"safety.window, narrower than the travel budget, or commission.travel_m ({budget * 1e3:g} mm)")
        checks.append(check("start position", inside, None if x is None else f"{x * 1e3:.4g} mm",
                            f"the travel budget +-{budget * 1e3:g} mm inside safety.window "
                            f"[{lo * 1e3:g}, {hi * 1e3:g}] mm", fix))
        if not inside:
            return False
        result["start_position_m"] = x
        progress("b: probe with torque pulses, the position controller off")
        result["stage_reached"] = "b"
        result["sample_period"] = backend.sample_period
        result["realtime"] = realtime.begin([])
        try:
            backend.activate()
        except RtIdentError as exc:                   # the device refused to enable or faulted: it is stopped
            checks.append(check("enable", False, str(exc), "the device enables", _device_fix(exc)))
            return False
        prober = Prober(backend, probe_limits(cfg, backend.torque_limit))
        pulses, probed = [], False
        try:
            prober.settle(0.05)
            for d in (1, -1):
                for _ in range(1 + LAPSED_RETRIES):
                    q = prober.pulse(d)
                    if not q.lapsed:
                        break
                    result["lapsed_pulses"] = result.get("lapsed_pulses", 0) + 1
                pulses.append(q)
                if q.aborted or q.breakaway_nm is None or q.fault:
                    break
            probed = True
        except ProbeError as exc:
            checks.append(check("probe", False, str(exc), "samples every tick", exc.key))
        except RtIdentError as exc:                   # the device stopped or failed: zero torque, disabled
            checks.append(check("probe", False, str(exc), "the device follows the pulses", _device_fix(exc)))
        finally:
            backend.safe_stop()
        if not probed:                                # the probe's own failure first, then the stop's
            _disable_confirmed(checks, backend.stop_unconfirmed)
            return False
        result["max_travel_m"] = prober.max_travel
        result["max_speed_m_s"] = prober.max_speed
        truth = [q.truth for q in pulses if q.truth]
        if truth:
            result["device_truth"] = {k: max(t[k] for t in truth) for k in truth[0]}
        result["pulses"] = [{"direction": q.direction, "fault": q.fault, "breakaway_nm": q.breakaway_nm,
                             "push_nm": q.push_nm, "aborted": q.aborted, "cap_held_s": q.cap_held_s,
                             "starved_samples": q.starved, "lost_samples": q.lost(backend.sample_period),
                             "theta1_rad": q.moved()[0], "x_m": q.moved()[1],
                             "ratio_m_per_rad": q.ratio(),
                             "accel_per_nm": q.dynamics(backend.sample_period)[0]} for q in pulses]
        checks.extend(probe_checks(cfg, pulses, backend.sample_period))
        _disable_confirmed(checks, backend.stop_unconfirmed)
        return all(c["ok"] for c in checks)


def _disable_confirmed(checks: list[dict[str, Any]], unconfirmed: str | dict[str, str] | None) -> bool:
    """A device that did not report itself disabled at a stop fails commissioning, in a check of its own."""
    if unconfirmed:
        checks.append(check("disable confirmed", False, unconfirmed, "the device reports itself disabled at each stop",
                            "the device's link and power; backend.stop_timeout (longer) if it answers late"))
    return not unconfirmed


def _device_fix(exc: RtIdentError) -> str:
    """The setting a device's error names: a config field, the driver's fix, else the backend and the cause."""
    if isinstance(exc, ConfigError):
        return exc.field
    return getattr(exc, "fix", None) or f"backend ({getattr(exc, 'cause', 'device')})"


#: sections a derived config replaces whole (the others are merged key by key)
_REPLACED = ("reference", "axis", "backend", "plant", "emulator")


def _derived(cfg: RunConfig, **sections: dict[str, Any]) -> RunConfig:
    """``cfg`` with ``sections`` laid over (as a stage runs it)."""
    data = cfg.model_dump(exclude={"source", "axes", "contour"}, exclude_none=True)
    plant = cfg.plant.model_dump(exclude_none=True)
    actual = plant.pop("actual", None)
    if actual:
        plant["actual"] = {k: v for k, v in actual.items() if v is not None}
    data["plant"] = plant
    if cfg.backend.name == "sim":              # the device's truth went into its options: given again by plant
        data["backend"] = {k: v for k, v in data["backend"].items() if k not in ("actual", "x0")}
    elif cfg.backend.emulate:
        data["emulator"] = {k: v for k, v in (data.get("emulator") or {}).items() if k not in ("actual", "x0")}
    for name, over in sections.items():
        data[name] = over if name in _REPLACED else {**(data.get(name) or {}), **over}
    return from_mapping(data, source=cfg.source)


#: stage c runs once more, this much longer at most, when only its intervals were too wide
IDENTIFY_LONGER_MAX = 4.0


def _longer(s: dict[str, Any], duration: float) -> float | None:
    """How long to identify again when the one criterion that failed is the intervals' width, finite:
    long enough for the widest interval to narrow to the limit with 30 % to spare (half-widths shrink
    as 1/sqrt(duration)), at most IDENTIFY_LONGER_MAX x and the config's 120 s. None: another run
    would not help (an impossible value, a missing interval, a stop)."""
    from rt_ident.estimators.uncertainty import INTERVAL_CRITERION, MAX_REL_HALFWIDTH

    failed = [c for c in (s.get("trust") or {}).get("criteria") or [] if not c.get("passed")]
    if len(failed) != 1 or not str(failed[0].get("criterion", "")).startswith(INTERVAL_CRITERION):
        return None
    ratio = float(failed[0].get("value") or math.inf) / (100.0 * MAX_REL_HALFWIDTH)
    if not math.isfinite(ratio) or ratio <= 1.0:
        return None
    longer = min(duration * max(2.0, (1.3 * ratio) ** 2), duration * IDENTIFY_LONGER_MAX, 120.0)
    return longer if longer > duration else None


def _identify(cfg: RunConfig, out: Path, result: dict[str, Any], progress: Progress) -> dict[str, Any] | None:
    """Stage c: the run's summary (identification, trust), or None when it did not pass. A run whose
    only shortfall is intervals wider than the limit runs once more, longer (``_longer``); the verdict
    is the second run's alone."""
    from rt_ident.compose.run import run as run_loop

    result["stage_reached"] = "c"
    duration = cfg.commission.identify_s
    attempts: list[dict[str, Any]] = []
    progress(f"c: identify for {duration:g} s, holding with the conservative controller")
    while True:
        c = _derived(cfg, control={"mode": "conservative"}, reference={"kind": "hold", "origin": "enable"},
                     loop={"duration": duration}, telemetry={"sink": "off"},
                     recording={"enabled": True, "path": str(out / "identify.parquet")})
        s = run_loop(c, sink="off", overwrite=True)
        unconfirmed = (s.get("stop") or {}).get("disable_unconfirmed")
        if (s.get("stop") or {}).get("interrupted"):
            _disable_confirmed(result["checks"], unconfirmed)
            raise KeyboardInterrupt                # Ctrl-C or SIGTERM during the run: commissioning ends
        stop = (s.get("stop") or {}).get("cause")
        trusted = bool(s.get("trusted"))
        reasons = (s.get("trust") or {}).get("reasons") or []
        attempts.append({"duration_s": duration, "trusted": trusted, "stop": stop, "reasons": reasons,
                         "lost_samples": (s.get("loop") or {}).get("lost_samples"),
                         "stalls": ((s.get("loop") or {}).get("stalls") or {}).get("count", 0)})
        again = not trusted and stop is None and not unconfirmed and len(attempts) == 1
        longer = _longer(s, duration) if again else None
        if longer is None:
            break
        progress(f"c: {reasons[0]}: identifying again for {longer:g} s")
        duration = longer
    result["identification"] = {**{k: s.get(k) for k in ("parameters", "ci95", "trusted", "trust", "friction")},
                                "attempts": attempts}
    result["parameters"] = s.get("parameters")
    if not trusted:
        measured = f"not trusted: {'; '.join(reasons) or stop}"
    else:
        measured = "trusted" if stop is None else f"trusted, but the run stopped: {stop}"
    period = result.get("sample_period") or _sample_period(cfg)
    ended = s.get("stop") or {}
    host = host_trouble(s, period)
    # an estimate from a run the host disturbed enough to change what it measured may be untrusted for that
    disturbed = None if trusted else host_trouble(s, period, run_failed=False)
    if stop is None and disturbed is not None:
        fix = ask_realtime(f"{disturbed} while identifying; else commission.identify_s (longer)")
    elif stop is None:
        fix = "commission.identify_s (longer), excitation.peak / excitation.band"
    elif host is not None:
        fix = ask_realtime(f"{host}, then the run stopped: {stop} - {ended.get('message')}")
    else:
        fix = f"the run stopped: {stop} - {ended.get('message')}" + (f"; {ended['fix']}" if ended.get("fix") else "")
    params = s.get("parameters") or {}
    note = None
    if trusted and "I1" in params and "I2" in params:
        p = cfg.axis_params()
        note = scaled_torque_note(cfg, (params["I1"] + params["I2"]) / (p.I1 + p.I2), "the identified I1 + I2")
    result["checks"].append(check("identification trusted", trusted and stop is None, measured,
                                  "trusted, run ended normally", fix, note))
    disabled = _disable_confirmed(result["checks"], unconfirmed)
    return s if trusted and stop is None and disabled else None


def _move_metrics(path: str, lead: float, origin: float, move: float, t_arrive: float) -> dict[str, float]:
    from rt_ident.outputs.recording_reader import read_recording

    rec = read_recording(path)
    assert rec.theta2 is not None           # a run's recording has the scale
    x = np.asarray(lead * rec.theta2 - origin)
    t = np.asarray(rec.t - rec.t[0])
    out = {"overshoot_m": float(max(0.0, x.max() - move))}
    band = 0.02 * move
    after = t >= t_arrive
    bad = np.flatnonzero(after & (np.abs(x - move) > band) & (t < t_arrive + 0.45))   # within the dwell
    out["settling_s"] = float(t[bad[-1]] - t_arrive) if bad.size else 0.0
    return out


def _verify(cfg: RunConfig, ident: dict[str, Any], out: Path, result: dict[str, Any], progress: Progress) -> bool:
    """Stage d: design on the identified axis (its margins), then the move, measured and predicted."""
    from rt_ident.axis.params import AxisParams
    from rt_ident.compose.offline import run_offline
    from rt_ident.compose.run import run as run_loop
    from rt_ident.control.job import model_controller
    from rt_ident.control.reference import Moves

    progress("d: design on the identified model, then a verification move")
    result["stage_reached"] = "d"
    prm = ident["parameters"]
    axis = {k: float(prm[k]) for k in ("I1", "I2", "B", "K")} | {"lead": cfg.axis_params().lead}
    settings = cfg.control.settings()
    bw, ctl, ok = settings.bandwidth_hz, None, False
    while bw >= 0.25 * settings.bandwidth_hz:      # as the conservative design: x 0.8 a step, to a quarter
        ctl = model_controller(AxisParams(**axis), 1.0 / cfg.loop.tick_hz, replace(settings, bandwidth_hz=bw))
        m = ctl.margins or {}
        pm, gm = m.get("pm_deg"), m.get("gm_down_db")
        ok = pm is not None and pm >= settings.phase_margin_deg and (gm is None or -gm >= settings.gain_margin_db)
        if ok:
            break
        bw *= 0.8
    assert ctl is not None
    m = ctl.margins or {}
    result["design"] = {"bandwidth_hz": ctl.bandwidth_hz, "margins": m}
    result["checks"].append(check("design margins", ok, {"bandwidth_hz": ctl.bandwidth_hz, "pm_deg": m.get("pm_deg"),
                                                         "gm_down_db": m.get("gm_down_db")},
                                  f"phase margin >= {settings.phase_margin_deg:g} deg, gain margin >= "
                                  f"{settings.gain_margin_db:g} dB at {settings.bandwidth_hz:g} Hz or down to a "
                                  "quarter of it", "control.bandwidth_hz (lower), control.delay_ticks"))
    if not ok:
        return False
    control = {"mode": "fixed", "bandwidth_hz": ctl.bandwidth_hz}
    move = cfg.commission.move_m
    v = 0.5 * cfg.commission.max_speed_m_s
    ref = {"kind": "moves", "positions": [0.0, move, 0.0], "v_max": v, "a_max": 20 * v, "j_max": 400 * v,
           "dwell": 0.5, "start": 0.3, "repeat": False, "origin": "enable"}
    path = Moves((0.0, move, 0.0), v, 20 * v, 400 * v, 0.5, 0.3, False)
    t_arrive = _arrival(path, move)
    duration = t_arrive + 0.5 + (t_arrive - 0.3) + 0.4
    # no probing: the move alone. Holding still, the motor encoder may not change for many ticks under
    # the small torques of the hold: the stuck-encoder check counts only above 5 % of the torque limit
    stuck = max(cfg.stuck_torque(), 0.05 * float(cfg.backend.options().get("torque_limit", 1.0)))
    common: dict[str, Any] = {"control": control, "reference": ref, "axis": axis,
                              "excitation": {"kind": "none"}, "loop": {"duration": duration},
                              "telemetry": {"sink": "off"}, "safety": {"stuck_torque": stuck}}
    meas = _derived(cfg, **common, recording={"enabled": True, "path": str(out / "move.parquet")})
    # the prediction first: the same loop and move on the identified model, on virtual time (no host in it)
    opts = cfg.backend.options()
    period = result.get("sample_period") or _sample_period(cfg)
    sim = {"name": "sim", "sample_period": period, "torque_limit": opts.get("torque_limit", 1.0),
           "counts_per_rev": opts.get("counts_per_rev", 2**17), "scale_resolution": opts.get("scale_resolution", 1e-7)}
    pred = _derived(cfg, **{**common, "loop": {**common["loop"], "realtime": False}}, backend=sim, plant={},
                    emulator={}, recording={"enabled": False})
    model_rec = out / "move-model.parquet"
    p = run_offline(pred, record=str(model_rec), overwrite=True) | {"files": {"recording": str(model_rec)}}
    for _ in range(1 + STALLED_MOVE_RETRIES):
        s = run_loop(meas, sink="off", overwrite=True)
        unconfirmed = (s.get("stop") or {}).get("disable_unconfirmed")
        if (s.get("stop") or {}).get("interrupted"):
            _disable_confirmed(result["checks"], unconfirmed)
            raise KeyboardInterrupt
        ok, got, want = _judge_move(s, p, cfg.axis_params().lead, move, t_arrive)
        # a move that failed or stopped with samples lost may have failed on the gaps: any count then; a device
        # that did not confirm its disable is not moved again
        host = None if unconfirmed else host_trouble(s, period, run_failed=not ok)
        if host is None:
            break
        result["stalled_moves"] = result.get("stalled_moves", 0) + 1   # the host's doing, not the axis's
    loop = s.get("loop") or {}
    timing = {"overruns": loop.get("overruns"), "lost_samples": loop.get("lost_samples"),
              "lateness_max_us": (loop.get("lateness_us") or {}).get("max")}
    result["verification"] = {"move_m": move, "measured": got, "model": want, "stalls": loop.get("stalls") or {},
                              "timing": timing,
                              "recordings": [s.get("files", {}).get("recording"), p.get("files", {}).get("recording")]}
    result["checks"].append(check(
        "verification move", ok,
        {k: got.get(k) for k in ("max_error_m", "overshoot_m", "settling_s", "stop")},
        {k: want.get(k) for k in ("max_error_m", "overshoot_m", "settling_s")} | {
            "tolerance": f"x{VERIFY_FACTOR:g} + {VERIFY_FLOOR_M * 1e6:g} um"},
        ask_realtime(f"in the move {1 + STALLED_MOVE_RETRIES} times: {host} (on a host that keeps time: "
                     "control.bandwidth_hz, lower)") if host is not None
        else "control.bandwidth_hz (lower) - the axis does not move as the identified model predicts"
        if got["stop"] is None else f"the move stopped: {got['stop']}"))
    late = (s.get("backend_counters") or {}).get("late_torques")
    timing["late_torques"] = late
    if late is not None and loop.get("samples"):          # each is a torque a sample late: the mean lateness
        timing["late_torque_ticks"] = round(late / loop["samples"], 4)
    disabled = _disable_confirmed(result["checks"], unconfirmed)
    return ok and disabled


def _judge_move(s: dict[str, Any], p: dict[str, Any], lead: float, move: float,
                t_arrive: float) -> tuple[bool, dict[str, Any], dict[str, Any]]:
    """The measured move's summary ``s`` against the prediction's ``p``: (passed, measured, predicted)."""
    sc = s.get("control") or {}
    got: dict[str, Any] = {"stop": (s.get("stop") or {}).get("cause"), "rms_error_m": sc.get("rms_error_m"),
                           "max_error_m": sc.get("max_error_m"), "fallbacks": sc.get("fallbacks")}
    want: dict[str, Any] = {"rms_error_m": (p.get("control") or {}).get("rms_error_m"),
                            "max_error_m": (p.get("control") or {}).get("max_error_m")}
    origin_m = float((sc.get("reference") or {}).get("origin_m") or 0.0)
    origin_p = ((p.get("control") or {}).get("reference") or {}).get("origin_m") or 0.0
    if got["stop"] is None and (s.get("files") or {}).get("recording"):
        got |= _move_metrics(s["files"]["recording"], lead, origin_m, move, t_arrive)
        want |= _move_metrics(p["files"]["recording"], lead, origin_p, move, t_arrive)
    ok = (got["stop"] is None and not got["fallbacks"] and got.get("max_error_m") is not None
          and want.get("max_error_m") is not None
          and got["max_error_m"] <= VERIFY_FACTOR * want["max_error_m"] + VERIFY_FLOOR_M
          and got.get("overshoot_m", 0.0) <= VERIFY_FACTOR * want.get("overshoot_m", 0.0) + VERIFY_FLOOR_M)
    return ok, got, want


def _arrival(path: Any, move: float) -> float:
    """When the reference first reaches the move's end [s]."""
    t = np.arange(0.0, 5.0, 1e-3)
    hit = np.flatnonzero(np.abs(path.at(t)[0] - move) <= 1e-6 * move)
    return float(t[hit[0]]) if hit.size else 0.3


def _sample_period(cfg: RunConfig) -> float:
    opts = cfg.backend.options()
    if cfg.backend.name == "canopen":
        return 1.0 / float(opts.get("sync_rate_hz", 2000))
    if cfg.backend.name == "serial":
        return 1.0 / float(opts.get("sample_rate_hz", 20000))
    return float(opts.get("sample_period", 2.9481e-5))


def axis_toml(cfg: RunConfig, params: dict[str, float], source: str | None, notes: tuple[str, ...] = ()) -> str:
    lead = cfg.axis_params().lead
    lines = [f"# identified by rt-ident commission on {_dt.datetime.now().isoformat(timespec='seconds')}"
             f" from {source}", *(f"# note: {n}" for n in notes), "[axis]"]
    lines += [f"{k} = {float(params[k]):.6g}" for k in ("I1", "I2", "B", "K")]
    lines.append(f"lead = {lead:.6g}")
    return "\n".join(lines) + "\n"


def _silent(_: str) -> None:
    return None


def commission(cfg: RunConfig, out: Path, progress: Progress = _silent) -> dict[str, Any]:
    """Run the stages (module docstring); the result as ``commission --json`` prints it. The folder is
    claimed host-wide for the commissioning's length: a second one into it is refused before it starts."""
    from rt_ident.outputs.paths import OutputClaims

    claims = OutputClaims()
    claims.claim(out, "--out", by="commissioning")
    try:
        return _commission(cfg, out, progress)
    finally:
        claims.release()


def _commission(cfg: RunConfig, out: Path, progress: Progress) -> dict[str, Any]:
    from rt_ident.commission import ledger, report
    from rt_ident.outputs.paths import check_output

    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:        # stage c records into the folder: one without room is refused before stage a moves the axis
        check_output(str(out / "identify.parquet"), ".parquet", "--out", overwrite=True)
    except ConfigError:
        if made:
            out.rmdir()
        raise
    result: dict[str, Any] = {"verdict": "fail", "stage_reached": None, "checks": [], "max_travel_m": None,
                              "max_speed_m_s": None, "parameters": None, "report": None, "axis_toml": None,
                              "config": cfg.source, "out": str(out)}
    old_handlers = _interrupts()
    try:
        ok = _connect_and_probe(cfg, result, progress)
        ident = _identify(cfg, out, result, progress) if ok else None
        ok = ident is not None and _verify(cfg, ident, out, result, progress)
        if ok:
            result["stage_reached"] = "e"
            toml = out / "axis.toml"
            ident_check = next(c for c in result["checks"] if c["name"] == "identification trusted")
            notes = (ident_check["note"],) if ident_check.get("note") else ()
            toml.write_text(axis_toml(cfg, result["parameters"], cfg.source, notes))
            result["axis_toml"] = str(toml)
        result["verdict"] = "pass" if ok else "fail"
    except KeyboardInterrupt:
        result["interrupted"] = True
        result["checks"].append(check("interrupted", False, "Ctrl-C, SIGTERM or SIGHUP", "the stages run to the end",
                                      "run rt-ident commission again"))
        raise
    finally:
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
        rt = result.get("realtime") if cfg.loop.realtime else False
        for c in result["checks"]:
            c["fix"] = host_fix(c["fix"], rt)
        first = next((c for c in result["checks"] if c["ok"] is False), None)
        result["failed"] = None if first is None else {"check": first["name"], "fix": first["fix"]}
        rep = out / "report.html"
        try:
            report.write(result, cfg, rep)
            result["report"] = str(rep)
        except Exception as exc:  # noqa: BLE001 - the verdict and the JSON stand without the report
            log.warning("commission report not written: %s", exc)
            result["report_error"] = str(exc)
        (out / "commission.json").write_text(json.dumps(result, indent=2, default=_json))
        ledger.record(cfg, result)
    return result


def _interrupts() -> dict[int, Any]:
    """The stop signals (:func:`~rt_ident.processes.guard.stop_signals`: a closed terminal's SIGHUP too, but
    under nohup) unwind as Ctrl-C does (the device's context stops it, the files are written), as ``rt-ident
    run`` stops on them; returns the handlers they had (none off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def handler(signum: int, frame: Any) -> None:  # noqa: ARG001
        raise KeyboardInterrupt

    return {sig: signal.signal(sig, handler) for sig in stop_signals()}


def _json(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    return str(o)

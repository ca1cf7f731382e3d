"""The checks of ``rt-ident commission``: one record per check, and the open-loop probe's checks from
its pulses (signs, scale against ``lead``, acceleration per N m, breakaway), each naming the key a
failure points at."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rt_ident.commission.probe import CAP_HOLD_S, ProbeLimits, Pulse
from rt_ident.config import RunConfig
from rt_ident.errors import ask_realtime

#: the scale may differ from ``lead`` by this much (relative) before the check fails
LEAD_TOLERANCE = 0.10
#: the acceleration per N m may be this factor off 1/(I1 + I2)
ACCEL_FACTOR = 3.0

#: an acceleration per N m (or an identified I1 + I2) this factor or more off [axis] is pointed out on a pass
NOTE_FACTOR = 1.25


def check(name: str, ok: bool | None, measured: Any, expected: Any, fix: str | None = None,
          note: str | None = None) -> dict[str, Any]:
    """One check's record; ``note``: what a pass still leaves to look at."""
    rec = {"name": name, "ok": ok, "measured": measured, "expected": expected, "fix": None if ok else fix}
    if note and ok:
        rec["note"] = note
    return rec


def scaled_torque_note(cfg: RunConfig, factor: float, what: str) -> str | None:
    """For ``what`` (an acceleration per N m or an inertia) ``factor`` x what [axis] gives: None within
    :data:`NOTE_FACTOR`, else that a torque scale and the inertias look alike to every measurement here."""
    if 1.0 / NOTE_FACTOR < factor < NOTE_FACTOR:
        return None
    key = f" ({_torque_key(cfg)})" if cfg.backend.name in ("canopen", "serial") else ""
    return (f"{what} is {factor:.2g} x what [axis] gives: either [axis] I1, I2 are not this axis's, or the torque "
            f"reaches the motor scaled{key}; the identified I1, I2, B, K carry such a scale, which a measurement "
            "in commanded torque cannot tell from the inertia")


def _torque_key(cfg: RunConfig) -> str:
    return {"canopen": "backend.rated_torque", "serial": "backend.torque_constant"}.get(
        cfg.backend.name, "axis.I1, axis.I2")


def probe_checks(cfg: RunConfig, pulses: list[Pulse], dt: float) -> list[dict[str, Any]]:
    """The checks of stage b from its pulses (in order; the first that fails ends the stage)."""
    p = cfg.axis_params()
    out: list[dict[str, Any]] = []
    cap = cfg.commission.torque_share * float(cfg.backend.options().get("torque_limit", 1.0))
    faulted = [q for q in pulses if q.fault]
    if faulted:
        lim = probe_limits(cfg, 2 * cap)
        moved = [q for q in pulses if q.t.size and abs(q.moved()[0]) > lim.motion_theta1
                 and abs(q.moved()[1]) > lim.motion_x]
        if moved:                                       # it moved before the device stopped: its signs
            q = moved[0]
            th, x = q.moved()
            sth, sx = int(np.sign(th * q.direction)), int(np.sign(x * q.direction))
            if sth < 0 or sx < 0:
                key = "backend.scale_sign" if sth > 0 else "backend.torque_sign" if sx < 0 \
                    else "backend.motor_encoder_sign"
                out.append(check("signs before the device stopped", False,
                                 f"theta1 {'+' if sth > 0 else '-'}, x {'+' if sx > 0 else '-'} for + torque, then "
                                 f"{faulted[0].fault}", "theta1 +, x +", f"{key}: set it to -1 x its value"))
                return out
        fault = faulted[0].fault or ""
        fix = ("backend.scale_sign, motor_encoder_sign, lead, counts_per_rev or scale_resolution: the device saw "
               "its motor encoder and scale move apart under the pulse before the host could measure them (one "
               "counts the other way or at another scale, or slips)" if "disagree" in fault
               else faulted[0].fault_fix or f"backend ({faulted[0].fault_cause})")
        out.append(check("device", False, fault, "no fault while probing", fix))
        return out
    still = [q for q in pulses if q.breakaway_nm is None and not q.aborted]   # a limit's stop: the limits check
    brk = [q.breakaway_nm for q in pulses if q.breakaway_nm is not None]
    late = [q for q in still if q.lapsed]
    if late:          # the host's plans lapsed: the cap was never in force long enough to tell
        q = late[0]
        out.append(check("motion", False, f"the torque cap was in force for {q.cap_held_s * 1e3:.0f} ms only; "
                         f"{q.starved} samples of the pulse had no torque plan in force (the host wrote late)",
                         f"the cap in force for {CAP_HOLD_S * 1e3:.0f} ms",
                         ask_realtime("the probe's torque plans lapsed between the host's writes")))
        return out
    out.append(check("motion", not still, f"moved at {max(brk, default=0):.4g} N m" if not still
                     else f"no motion up to {cap:.4g} N m ({'+' if still[0].direction > 0 else '-'}), in force "
                          f"{still[0].cap_held_s * 1e3:.0f} ms",
                     f"motion below {cap:.4g} N m",
                     "backend.torque_limit (or commission.torque_share): the axis did not move; check the brake, "
                     "the drive's enable and the motor's power"))
    aborted = [q.aborted for q in pulses if q.aborted]
    fix_lim = "commission.travel_m / commission.max_speed_m_s"
    if aborted:
        # the pushes are sized from [axis]: an axis far livelier per N m passes the limits because of that
        fits = [abs(q.dynamics(dt)[0]) for q in pulses if q.breakaway_nm is not None]
        fits = [f for f in fits if math.isfinite(f) and f > 0]
        acc = float(np.median(fits)) * (p.I1 + p.I2) if fits else math.nan
        if acc > ACCEL_FACTOR:
            fix_lim = (f"{_torque_key(cfg)}: the axis accelerates {acc:.3g} x as fast per N m as [axis] says, and "
                       f"the pulses sized from [axis] passed the limit (if [axis] and the torque are right: "
                       f"{fix_lim})")
    out.append(check("limits", not aborted, aborted[0] if aborted else
                     f"{max(q.max_travel_m for q in pulses) * 1e3:.3f} mm, "
                     f"{max(q.max_speed_m_s for q in pulses) * 1e3:.2f} mm/s",
                     f"within {cfg.commission.travel_m * 1e3:g} mm and {cfg.commission.max_speed_m_s * 1e3:g} mm/s",
                     fix_lim))
    if still or aborted:
        return out
    s_th = [int(np.sign(q.moved()[0] * q.direction)) for q in pulses]
    s_x = [int(np.sign(q.moved()[1] * q.direction)) for q in pulses]
    if len(set(s_th)) > 1 or len(set(s_x)) > 1 or 0 in s_th or 0 in s_x:
        lost, starved = sum(q.lost(dt) for q in pulses), sum(q.starved for q in pulses)
        out.append(check("direction", False, f"theta1 {s_th}, x {s_x} per pulse (+, -)", "the same each way",
                         ask_realtime(f"the pulses lost {lost} samples and had {starved} without a torque plan in "
                                      "force, so the host's lateness may have made the inconsistent motion (if it "
                                      "recurs on a host that keeps time: a load, a brake or backlash? check the "
                                      "mechanics)") if lost or starved else
                         "the axis moved inconsistently (a load, a brake or backlash?); check the mechanics"))
        return out
    sth, sx = s_th[0], s_x[0]
    fix_t = "backend.torque_sign" if sx < 0 else "backend.motor_encoder_sign"
    out.append(check("torque moves theta1 positive", sth > 0,
                     f"theta1 {'+' if sth > 0 else '-'}, x {'+' if sx > 0 else '-'} for + torque", "theta1 +",
                     f"{fix_t}: set it to {-1 if sth < 0 else 1} x its value ("
                     + ("the motor and the scale both move against the torque: the motor is wired the other way, "
                        "or the drive's polarity"
                        if sx < 0 else "the scale moves with the torque, the motor encoder against it") + ")"))
    if sth < 0:
        return out
    out.append(check("scale follows the motor", sx > 0, f"x {'+' if sx > 0 else '-'} when theta1 +", "x +",
                     "backend.scale_sign: set it to -1 x its value (the scale counts against the motor)"))
    if sx < 0:
        return out
    ratio = float(np.median([abs(q.ratio()) for q in pulses]))
    fits = [abs(q.dynamics(dt)[0]) for q in pulses]
    fits = [f for f in fits if math.isfinite(f) and f > 0]
    if not fits:
        lost = sum(q.lost(dt) for q in pulses) if any(q.gapped(dt) for q in pulses) else 0
        out.append(check("acceleration measured", False, f"no fit ({lost} samples lost)" if lost else "no fit",
                         "an acceleration per N m from the pulses",
                         ask_realtime(f"the device's link lost {lost} of the pulses' samples, too many at once to "
                                      "fit the motion", "check the bus") if lost else
                         "commission.max_speed_m_s / commission.travel_m (larger: longer pulses)"))
        return out
    inv_j = float(np.median(fits))
    nominal = 1.0 / (p.I1 + p.I2)
    acc = inv_j / nominal
    rel = ratio / p.lead
    lead_ok = abs(rel - 1.0) <= LEAD_TOLERANCE
    opts = cfg.backend.options()
    if lead_ok:
        fix_l = None
    else:
        # theta1 reading off by the ratio's factor shows in its acceleration per N m too; the scale's or the
        # lead's error does not. Between the two (a third of the way or closer to the middle, in log terms:
        # a noisy acceleration), for the pulses' median or any one pulse, the check names both rather than guess
        cpr, res = opts.get("counts_per_rev"), opts.get("scale_resolution")
        margin = abs(math.log(rel)) / 3.0

        def points_to(a: float) -> str:
            d_cpr, d_lead = abs(math.log(a * rel)), abs(math.log(a))
            return "cpr" if d_cpr < d_lead - margin else "lead" if d_lead < d_cpr - margin else "both"

        says = {points_to(a) for a in [acc] + [f / nominal for f in fits]}
        if says == {"cpr"}:
            fix_l = (f"backend.counts_per_rev: the motor encoder reads {1 / rel:.3g} x its motion (its acceleration "
                     f"per N m is off by the same factor); {cpr} counts/rev -> {round(cpr * rel) if cpr else '?'}")
        elif says == {"lead"}:
            fix_l = (f"backend.lead (and axis.lead): the scale moves {ratio:.4g} m per rad of the motor, not "
                     f"{p.lead:.4g}; set lead = {ratio:.4g}, or if the lead is right, scale_resolution "
                     f"{res} -> {res / rel if res else '?':.4g} m per count")
        else:
            fix_l = (f"backend.counts_per_rev or backend.lead/scale_resolution: x/theta1 is {rel:.3g} x the "
                     f"configured lead, and the acceleration per N m ({acc:.3g} x nominal"
                     + (f"; the pulses' {', '.join(f'{f / nominal:.3g}' for f in fits)}" if len(fits) > 1 else "")
                     + f") does not tell which sensor is off; check the encoder's counts per rev ({cpr}) and the "
                     "screw's lead")
    out.append(check("scale ratio x/theta1", lead_ok, ratio, f"lead {p.lead:.4g} m/rad +-{LEAD_TOLERANCE:.0%}", fix_l))
    if not lead_ok:
        return out
    acc_ok = 1.0 / ACCEL_FACTOR <= acc <= ACCEL_FACTOR
    out.append(check("acceleration per N m", acc_ok, inv_j, f"1/(I1 + I2) = {nominal:.4g} rad/s^2 per N m, "
                     f"within x{ACCEL_FACTOR:g}",
                     f"{_torque_key(cfg)}: the axis accelerates {acc:.3g} x as fast per N m as [axis] says "
                     "(the torque reaches the motor scaled, or the inertia is not what [axis] gives)",
                     scaled_torque_note(cfg, acc, "the acceleration per N m")))
    fc = [abs(q.dynamics(dt)[1]) for q in pulses]
    out.append(check("breakaway torque", True, max(brk), "measured (the static friction the ramp overcame)"))
    out[-1]["friction_nm"] = float(np.median(fc)) if all(map(math.isfinite, fc)) else None
    return out


def probe_limits(cfg: RunConfig, torque_limit: float) -> ProbeLimits:
    p, opts = cfg.axis_params(), cfg.backend.options()
    cpr = int(opts.get("counts_per_rev") or 0)
    res = float(opts.get("scale_resolution") or 0.0)
    return ProbeLimits(travel_m=cfg.commission.travel_m, max_speed_m_s=cfg.commission.max_speed_m_s,
                       torque_cap=cfg.commission.torque_share * torque_limit, lead=p.lead, inertia=p.I1 + p.I2,
                       motion_theta1=10 * 2 * math.pi / cpr if cpr else 1e-4,
                       motion_x=10 * res if res else 1e-6,
                       # as long as a run waits for fresh samples before its watchdog trips
                       no_samples_s=max(0.2, cfg.safety.watchdog_ticks / cfg.loop.tick_hz))

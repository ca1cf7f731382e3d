"""What the control process runs (:func:`redesign`), never the tick: a design for the trusted estimate,
accepted only when it is safe, or the design in force kept where a new one would not pay; and the
conservative controller, and a replacement for it that suits the estimate.

* a new design (:func:`model_controller`, :func:`rt_ident.control.design.design_lqr`) is accepted only
  if it stabilizes the estimate *and* its family (each parameter x 0.7 and x 1.3, and the corners of
  the estimate's 95 % intervals) with the configured gain and phase margins;
* the design in force is kept instead (:func:`keep_design`) where it passes that check on the new
  estimate and the new design would not do better by more than ``keep_margin``;
* likewise, while the conservative controller is in force, the configured axis's design (the one the
  fixed mode runs) is the first model design where it would be kept on the estimate.

:class:`ControlSettings` (the ``[control]`` table) is shared with the supervisor in the tick
(:mod:`rt_ident.control.adaptation`).
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rt_ident.axis.params import AxisParams
from rt_ident.control.design import (
    FamilyCheck,
    check_family,
    design_lqr,
    design_rigid,
    error_norm,
    loop_gain_view,
    loop_margins,
    reference_error,
)
from rt_ident.control.law import Controller

log = logging.getLogger(__name__)

KEYS = ("I1", "I2", "B", "K")


@dataclass(frozen=True)
class ControlSettings:
    """The ``[control]`` table (see :class:`rt_ident.config.ControlConfig`)."""

    mode: str = "adaptive"                   # "adaptive" | "fixed" | "off"
    bandwidth_hz: float = 20.0               # model controller
    effort: float = 1.0                      # LQR torque weight multiplier (larger: gentler)
    conservative_bandwidth_hz: float = 10.0  # rigid-body controller, before a trusted estimate (at most)
    conservative_load: float = 1.0           # ... which keeps its margins with the table inertia I2 x this (1: nominal)
    gain_margin_db: float = 6.0
    phase_margin_deg: float = 40.0
    family_factors: tuple[float, ...] = (0.7, 1.3)
    redesign_interval_s: float = 0.25        # at most this often
    min_change: float = 0.02                 # relative parameter change that asks for a redesign
    # ... and of B alone. B's share of the torque is small, so its estimate scatters most (per-sample
    # ~1.3 %), and the family check already keeps the margins for B x 0.7..1.3: at 2 % B's scatter
    # alone would ask for most redesigns, each one a controller switch and a loop-gain redraw
    # (docs/measurements.md, "Position control")
    min_change_damping: float = 0.10
    max_error_m: float = 2e-4                # tracking error bound -> fallback
    fallback_timeout_s: float = 0.5          # the fallback must bring the error back within this
    plausible: tuple[float, float] = (0.2, 5.0)  # an estimate outside nominal x this range diverged
    feedforward: bool = True
    probe_scale_trusted: float = 1.0         # probing amplitude x this while the estimate is trusted
    delay_ticks: int = 1                     # ticks from the newest sample to the torque landing
    trust_tolerance: float = 0.05            # per-sample estimate vs frequency fit: agree when within
    trust: str = "per-sample"                # "per-sample" (own evidence, the fit audits) | "cross-check"
    settle_tolerance: float = 0.02           # I1, I2, K each within this of the window's mean (B: DAMPING_TOLERANCE)
    trust_window: int = 4                    # per-sample estimates in the window (one every ASSESS_EVERY ticks)
    interval_tolerance: float = 0.05         # 95 % interval half-widths of I1, I2, K within this (B: DAMPING_TOLERANCE)
    audit_grace_s: float = 1.0               # after a detected change the frequency fit still lags this long
    audit_vetoes: int = 2                    # consecutive disagreements of the fit (past the grace) that veto
    # a model design in force is kept for a new estimate (no switch) while its predicted error is within
    # this of the new design's (keep_design); 0: every accepted design is switched in
    keep_margin: float = 0.05


def rigid_controller(nominal: AxisParams, tick: float, s: ControlSettings) -> Controller:
    """The conservative controller: the rigid-body design for the configured nominal I1 + I2, at the
    highest bandwidth from ``conservative_bandwidth_hz`` down (x 0.8 a step, to a quarter of it) that
    keeps the margins on the nominal axis *and* with a workpiece on its table (I2 x ``conservative_load``).

    It holds the axis until the first trusted estimate and after a fallback, so it must hold an axis
    the supervisor has not identified yet. A light axis with a workpiece is the hard case: for the XY
    table's Y (I2 = 2.5e-5) with I2 x 3 the mode sits at 375 Hz, where one tick of delay turns the
    collocated velocity feedback round, and the 10 Hz design is unstable; 4.1 Hz keeps 6 dB / 40 deg
    there. The THOMSON X axis passes at 10 Hz. The default load factor is 1 (the nominal axis only,
    10 Hz): a 4.1 Hz fallback follows a 1-turn/s circle too loosely for the circular test
    (docs/measurements.md, "Both axes of the XY table"). When no bandwidth passes, the lowest is used
    (and a warning logged)."""
    loaded = replace(nominal, I2=nominal.I2 * s.conservative_load)
    bw = s.conservative_bandwidth_hz
    while True:
        g = design_rigid(nominal.I1 + nominal.I2, tick, bw, s.effort, s.delay_ticks)
        if all(loop_margins(g, q, tick).meets(s.gain_margin_db, s.phase_margin_deg) for q in (nominal, loaded)):
            break
        if bw * 0.8 < 0.25 * s.conservative_bandwidth_hz:
            log.warning("conservative controller: no bandwidth down to %.2g Hz keeps the margins with I2 x %g; "
                        "using %.2g Hz", bw, s.conservative_load, bw)
            break
        bw *= 0.8
    return Controller(g, nominal, "conservative", bw, loop_margins(g, nominal, tick).as_dict(),
                      loop_gain_view(g, nominal, tick))


def model_controller(p: AxisParams, tick: float, s: ControlSettings, kind: str = "model") -> Controller:
    g = design_lqr(p, tick, s.bandwidth_hz, s.effort, s.delay_ticks)
    return Controller(g, p, kind, s.bandwidth_hz, loop_margins(g, p, tick).as_dict(), loop_gain_view(g, p, tick))


def redesign(request: dict[str, Any]) -> dict[str, Any]:
    """Job: design for ``request["params"]`` and check it over the family.

    Returns ``{"accepted", "reason", "check", "seq", "cpu_s"}`` and, when accepted, ``"controller"`` (the
    design to switch in) or ``"kept_for"`` (the estimate the design in force was kept for); with the
    configured axis's design as ``"controller"``, ``"confirms"`` is the estimate that confirmed it.
    """
    c0 = time.process_time()
    out = _redesign(request)
    out["cpu_s"] = time.process_time() - c0       # the job process's CPU for this job (the summary's "redesigns")
    return out


def _redesign(request: dict[str, Any]) -> dict[str, Any]:
    s: ControlSettings = request["settings"]
    tick = request["tick"]
    ci95 = request.get("ci95")
    seq = request.get("seq")
    p = AxisParams(**{k: request["params"][k] for k in KEYS}, lead=request["params"].get("lead", 7.96e-4))
    try:
        ctrl = model_controller(p, tick, s)
    except Exception as exc:  # noqa: BLE001 - a design that fails is a rejected design, with its reason
        return {"accepted": False, "reason": f"design failed: {exc}", "seq": seq}
    held = _held_design(request, p.lead, tick, s)
    kept = None if held is None else keep_design(held[0], held[1], ctrl.gains, p, tick, s, ci95)
    if held is not None and kept is not None:
        check, ratio = kept
        why = (f"its error norm on the estimate is {ratio:.3f} x the new design's (a switch needs it better by "
               f"more than {100 * s.keep_margin:g} %)")
        configured = held[2]
        out = {"accepted": True, "check": check.as_dict(), "seq": seq}
        if configured is None:
            out.update(kept_for=p, reason=f"the design in force kept: {why}")
        else:
            out.update(confirms=p, controller=configured, reason=f"the configured axis's design: {why}")
        return _with_fallback(out, request, p)
    check = check_family(ctrl.gains, p, tick, gm_db=s.gain_margin_db, pm_deg=s.phase_margin_deg,
                         factors=tuple(s.family_factors), ci95=ci95)
    out = {"accepted": check.ok, "reason": check.reason, "check": check.as_dict(), "seq": seq}
    if not check.ok:
        return out
    out["controller"] = Controller(ctrl.gains, p, "model", s.bandwidth_hz, check.nominal.as_dict(), ctrl.loop_view)
    return _with_fallback(out, request, p)


def _held_design(request: dict[str, Any], lead: float, tick: float,
                 s: ControlSettings) -> tuple[np.ndarray, AxisParams, Controller | None] | None:
    """The design that stays unless a new one pays, as (gains, its model, the controller to switch in):
    the model design in force (nothing to switch in); with the conservative controller in force, the
    configured axis's design (the fixed mode's), where it can be made; else None."""
    in_force, nominal = request.get("in_force"), request.get("nominal")
    if in_force is not None:
        return np.asarray(in_force["gains"], dtype=float), AxisParams(**in_force["model"], lead=lead), None
    if nominal is None:
        return None
    try:
        model = AxisParams(**nominal)
    except Exception:  # noqa: BLE001 - no configured axis to design for: the estimate's own design
        return None
    configured = _configured_design(model, tick, s)
    return None if configured is None else (configured.gains, configured.model, configured)


@functools.lru_cache(maxsize=4)
def _configured_design(nominal: AxisParams, tick: float, s: ControlSettings) -> Controller | None:
    """The configured axis's design, made once per job process: asked for with every request while the
    conservative controller is in force. None where it cannot be made (the estimate's own design then)."""
    try:
        return model_controller(nominal, tick, s)
    except Exception:  # noqa: BLE001 - no configured design to offer: the estimate's own
        return None


def _with_fallback(out: dict[str, Any], request: dict[str, Any], p: AxisParams) -> dict[str, Any]:
    """``out`` with a conservative controller that suits ``p`` where the one in force does not."""
    cons = request.get("conservative")
    if cons is not None:
        s = request["settings"]
        out["fallback"], out["fallback_reason"] = _fallback_for(np.asarray(cons, dtype=float), p, request["tick"], s,
                                                                request.get("ci95"))
    return out


def keep_design(gains: np.ndarray, model: AxisParams, new_gains: np.ndarray, p: AxisParams, tick: float,
                s: ControlSettings, ci95: dict[str, tuple[float, float]] | None) -> tuple[FamilyCheck, float] | None:
    """(its family check, its error norm over the new design's) when the model design in force (``gains``,
    designed for ``model``) should stay for the estimate ``p`` instead of the design ``new_gains`` made for it;
    else None.

    Every switch has a transient of its own (the re-seeded integral decays through the new loop), so a
    design is switched in only where it is predicted to do better by more than ``keep_margin``
    (hysteresis: an estimate near the edge does not flip between switching and not). Kept when its
    :func:`reference_error` on ``p`` is within ``min_change``, its :func:`error_norm` on ``p`` within
    ``keep_margin`` of the new design's, and it passes the family check on ``p`` with the margins, as
    a new design must."""
    if s.keep_margin <= 0.0 or not reference_error(gains, model, p) <= s.min_change:
        return None
    old, new = error_norm(gains, p, tick), error_norm(new_gains, p, tick)
    if not old <= (1.0 + s.keep_margin) * new:
        return None
    check = check_family(gains, p, tick, gm_db=s.gain_margin_db, pm_deg=s.phase_margin_deg,
                         factors=tuple(s.family_factors), ci95=ci95)
    if not check.ok:
        return None
    return check, old / new


def _fallback_for(gains: np.ndarray, p: AxisParams, tick: float, s: ControlSettings,
                  ci95: dict[str, tuple[float, float]] | None) -> tuple[Controller | None, str | None]:
    """A conservative controller that suits the estimate ``p``, when the one in force does not
    (None when it does, or when nothing better passes). The rigid-body controller is designed for
    the nominal inertia: on a light axis with a workpiece (the XY table's Y with I2 x 3) it can be
    unstable, the mode (375 Hz) sitting where one tick of delay turns the collocated velocity feedback
    round. Tried in turn:
    the rigid-body controller for the estimate's I1 + I2, then the model controller at the
    conservative bandwidth; the first that passes the family check is taken."""
    if loop_margins(gains, p, tick).meets(s.gain_margin_db, s.phase_margin_deg):
        return None, None
    bw = s.conservative_bandwidth_hz
    tries = (("rigid", lambda: design_rigid(p.I1 + p.I2, tick, bw, s.effort, s.delay_ticks)),
             ("model", lambda: design_lqr(p, tick, bw, s.effort, s.delay_ticks)))
    why = []
    for name, make in tries:
        try:
            g = make()
        except Exception as exc:  # noqa: BLE001 - a design that fails is one fewer candidate
            why.append(f"{name}: {exc}")
            continue
        chk = check_family(g, p, tick, gm_db=s.gain_margin_db, pm_deg=s.phase_margin_deg,
                           factors=tuple(s.family_factors), ci95=ci95)
        if chk.ok:
            return (Controller(g, p, "conservative", bw, chk.nominal.as_dict(), loop_gain_view(g, p, tick)),
                    f"the conservative controller in force fails on the estimate; now {name} at {bw:g} Hz")
        why.append(f"{name}: {chk.reason}")
    return None, "the conservative controller fails on the estimate and no replacement passed: " + "; ".join(why)

"""Indirect adaptive control: redesign from the identified model, accepted only when it is safe.

Certainty equivalence (Åström & Wittenmark, *Adaptive Control*, ch. 5: the indirect self-tuning
regulator) with a supervisor around it, because certainty equivalence alone can destabilize a
plant when the estimate is wrong:

* :func:`rt_ident.control.job.redesign` runs in a job process (never in the tick): it designs the
  model controller for the trusted estimate and accepts it only if it stabilizes the estimate *and*
  its family with the configured margins, or keeps the design in force where a new one would not pay;
* :class:`Supervisor` (in the tick, scalar arithmetic only) runs the current controller, swaps
  an accepted design in bumplessly, falls back to the conservative controller when the tracking
  error leaves its bound or the estimate diverges, and asks for a safe stop when the fallback
  does not recover in time.

**Trust** (``trust = "per-sample"``, the default): the per-sample estimate is trusted on its own
evidence, checked every ``ASSESS_EVERY`` ticks: no change detected since the window began (the
estimator's residual CUSUM, :mod:`rt_ident.estimators.svf`) and no row held back by its dead zone
(an estimate frozen for want of excitation is steady but not evidence), its 95 % intervals within
``interval_tolerance``, the last ``trust_window`` estimates
within ``settle_tolerance`` of each other (B, whose estimate scatters most, within ``DAMPING_TOLERANCE``),
and plausible. The design is made for the window's mean, not the newest estimate. The frequency fit
audits: it disagreeing by more than ``trust_tolerance`` (B: ``DAMPING_TOLERANCE``) ``audit_vetoes``
times in a row, outside ``audit_grace_s`` after a detected change or a redesign for a moved
estimate (its own averaging lags), vetoes the per-sample trust and rolls back to the last design it
agreed with (the conservative controller when there is none); its agreeing again lifts the veto.
With ``trust = "cross-check"`` the per-sample estimate is trusted only while the fit agrees.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numba
import numpy as np

from rt_ident.axis.params import AxisParams
from rt_ident.control.anchor import Anchor, ReferenceOptions, braking_limits
from rt_ident.control.job import KEYS, ControlSettings, model_controller, rigid_controller
from rt_ident.control.law import C_INERTIA, Controller, StateFeedback
from rt_ident.errors import RtIdentError
from rt_ident.estimators.svf import interval_halves

log = logging.getLogger(__name__)

#: ticks between two looks at the per-sample estimate's evidence (Supervisor.assess)
ASSESS_EVERY = 5
#: a finished design is switched in on a quiet tick (Supervisor._quiet): the reference not accelerating
#: and the new law's feedback torque before re-seeding within SWITCH_BUMP x the torque limit of the old
#: one. The re-seeded integral absorbs the difference, and what it absorbs decays as a slow transient
#: of the new loop. After QUIET_WAIT_S it is switched in regardless.
QUIET_WAIT_S = 0.15
#: how long after a detected change the inertia feedforward follows the per-sample estimate at most
FOLLOW_S = 0.25
#: ... and only while the 95 % half-widths of I1 and I2 are within this fraction of I1 + I2
FOLLOW_INTERVAL = 0.05
SWITCH_BUMP = 0.002


#: an estimate is trusted, designed for and followed only this far inside the plausible box
#: (``ControlSettings.plausible``); it has diverged only outside the box itself. Without the margin an estimate
#: at the box's edge is trusted and designed for, then called diverged by the next fit, over and over: a
#: controller switch and a fallback each time.
PLAUSIBLE_MARGIN = 0.1

#: B's share of the torque is small and its estimate scatters most; the family check keeps the margins
#: for B x 0.7..1.3, so two estimates of B agree (and a design still fits) within this
DAMPING_TOLERANCE = 0.25


def _tolerance(key: str, tol: float) -> float:
    """``tol`` for I1, I2, K; at least DAMPING_TOLERANCE for B."""
    return max(tol, DAMPING_TOLERANCE) if key == "B" else tol


# Supervisor.assess's compiled look (window_look): the window's mean, the estimate now and its 95 %
# half-widths, and (trusted) the parameter of the mean that moved most from the design in force and by how much ...
LOOK_MEAN, LOOK_NOW, LOOK_HALF, LOOK_WORST, LOOK_CHANGE, LOOK_SIZE = 0, 4, 8, 12, 13, 14
# ... its verdicts ...
WINDOW_FILLING, WINDOW_UNTRUSTED, WINDOW_TRUSTED = range(3)
# ... and what it compares with (Supervisor._trust_consts): nominal I1, I2, B, K, the plausible box's
# factors, settle_tolerance, interval_tolerance, the relative change of I1, I2, B, K that asks for a redesign
TC_NOMINAL, TC_LO, TC_HI, TC_SETTLE, TC_INTERVAL, TC_THRESHOLD, TC_SIZE = 0, 4, 5, 6, 7, 8, 12


@numba.njit(cache=True)
def largest_change(values, model, tc):
    """(the parameter of ``values`` that moved most from ``model`` against its own redesign threshold,
    its relative change); the first of equals. A model's B may be 0: any estimate has then moved."""
    worst, score, change = 0, -1.0, 0.0
    for j in range(4):
        c = abs(values[j] / max(model[j], 1e-300) - 1.0)
        if c / tc[TC_THRESHOLD + j] > score:
            worst, score, change = j, c / tc[TC_THRESHOLD + j], c
    return worst, change


@numba.njit(cache=True)
def window_look(win, n, vetoed, tc, R, Sigma, acc, p, scale, model, look):
    """One look at the per-sample estimate's own evidence (see the module docstring): the estimate
    now goes into row ``n`` (mod its length) of the window; once the window is full, it is trusted when
    every estimate in it is positive and finite (one outside physics is no evidence), I1, I2, K within
    settle_tolerance of the window's mean (B within DAMPING_TOLERANCE), the mean inside the plausible
    box, no audit veto, and every 95 % interval (:func:`rt_ident.estimators.svf.interval_halves`)
    within interval_tolerance of its centre (B: DAMPING_TOLERANCE). ``look`` receives the mean, the
    estimate now, its half-widths and the mean's :func:`largest_change` from ``model`` (the design in
    force). Compiled, in one call: each numpy call of a tick costs it microseconds."""
    m = win.shape[0]
    row = n % m
    for j in range(4):
        v = p[j] * scale[j]
        win[row, j] = v
        look[LOOK_NOW + j] = v
    if n + 1 < m:
        return WINDOW_FILLING
    for i in range(m):
        for j in range(4):
            if not (win[i, j] > 0.0 and math.isfinite(win[i, j])):
                return WINDOW_UNTRUSTED
    trusted = not vetoed
    for j in range(4):
        s, lo, hi = 0.0, win[0, j], win[0, j]
        for i in range(m):
            s += win[i, j]
            lo = min(lo, win[i, j])
            hi = max(hi, win[i, j])
        mean = s / m
        look[LOOK_MEAN + j] = mean
        tol = DAMPING_TOLERANCE if j == 2 else tc[TC_SETTLE]
        if not (hi - lo) / mean <= tol:
            trusted = False
        nom = tc[TC_NOMINAL + j]
        if not tc[TC_LO] * nom <= mean <= tc[TC_HI] * nom:
            trusted = False
    if not trusted:
        return WINDOW_UNTRUSTED
    half = look[LOOK_HALF:LOOK_HALF + 4]
    if not interval_halves(R, Sigma, acc, scale, half):
        return WINDOW_UNTRUSTED
    for j in range(4):
        tol = max(tc[TC_INTERVAL], DAMPING_TOLERANCE) if j == 2 else tc[TC_INTERVAL]
        c = look[LOOK_NOW + j]
        lo, hi = c - half[j], c + half[j]
        mid, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        if not (math.isfinite(lo) and math.isfinite(hi) and mid > 0.0 and h >= 0.0 and h <= tol * mid):
            return WINDOW_UNTRUSTED
    worst, change = largest_change(look[LOOK_MEAN:LOOK_MEAN + 4], model, tc)
    look[LOOK_WORST], look[LOOK_CHANGE] = worst, change
    return WINDOW_TRUSTED


def _inner(box: tuple[float, float]) -> tuple[float, float]:
    """The plausible box's factors narrowed by PLAUSIBLE_MARGIN: where an estimate is trusted."""
    return box[0] * (1.0 + PLAUSIBLE_MARGIN), box[1] / (1.0 + PLAUSIBLE_MARGIN)


def _intervals(look: np.ndarray) -> dict[str, tuple[float, float]]:
    """The 95 % intervals a window look saw (its estimate now +- its half-widths)."""
    return {k: (float(look[LOOK_NOW + i] - look[LOOK_HALF + i]), float(look[LOOK_NOW + i] + look[LOOK_HALF + i]))
            for i, k in enumerate(KEYS)}


def worst_difference(p: AxisParams, q: AxisParams, tol: float) -> tuple[str, float, bool]:
    """(the parameter of ``p`` furthest from ``q`` relative to its tolerance, its relative difference,
    whether it is within :func:`_tolerance`)."""
    worst = max(KEYS, key=lambda k: abs(getattr(p, k) / getattr(q, k) - 1.0) / _tolerance(k, tol))
    rel = abs(getattr(p, worst) / getattr(q, worst) - 1.0)
    return worst, rel, rel <= _tolerance(worst, tol)


class ControlFallbackStop(RtIdentError):
    """The conservative controller did not bring the tracking error back in time."""

    cause = "control-fallback"
    fix = ("the axis's model, which the controllers are designed from ([axis]: rt-ident commission, or rt-ident "
           "identify of a recording); else control.bandwidth_hz lower, or a wider control.max_error_m")


# the slots of ControlStats.err (the same three follow for the errors after error_after_s)
ERR_SQ, ERR_N, ERR_MAX = range(3)


@dataclass(eq=False)     # one axis's counters (err is an array): compared by identity
class ControlStats:
    accepted: int = 0
    rejected: int = 0
    kept: int = 0                # accepted results that kept the design in force (job.keep_design)
    fallbacks: int = 0
    reasons: list[str] = field(default_factory=list)
    events: list[tuple[float, str, str]] = field(default_factory=list)   # (t, kind, detail)
    # sum of squared tracking errors, their count, the largest; the same after error_after_s (ERR_*):
    # one array, changed in place by track_error (the compiled tick holds a view)
    err: np.ndarray = field(default_factory=lambda: np.zeros(6))
    max_step_nm: float = 0.0     # largest torque step a switch would have caused without re-seeding
    requests: int = 0            # redesigns asked of the control process
    why_requested: dict[str, int] = field(default_factory=dict)   # the parameter that moved most, per request
    latency_s: list[float] = field(default_factory=list)   # request -> answer, loop time
    cpu_s: list[float] = field(default_factory=list)       # the job process's CPU per redesign
    applied: list[tuple[float, str, AxisParams]] = field(default_factory=list)  # (t, kind, model) switched in
    changes_detected: int = 0    # the per-sample estimator's change detector, seen by the supervisor
    audit_vetoes: int = 0        # per-sample trust withdrawn by the frequency fit
    feedforward_updates: int = 0  # inertia feedforward moved to the per-sample I1 + I2 before a redesign
    trusted_at: list[float] = field(default_factory=list)   # when the per-sample estimate became trusted
    checks_agreed: int = 0       # cross-checks of the per-sample estimate against the frequency fit
    checks_disagreed: int = 0
    last_disagreement: str = ""


    sq_err = property(lambda self: float(self.err[ERR_SQ]))
    n_err = property(lambda self: int(self.err[ERR_N]))
    max_err = property(lambda self: float(self.err[ERR_MAX]))
    sq_err_after = property(lambda self: float(self.err[ERR_SQ + 3]))
    n_err_after = property(lambda self: int(self.err[ERR_N + 3]))
    max_err_after = property(lambda self: float(self.err[ERR_MAX + 3]))


# Supervisor.now: the tick's time, reference and error, the state and reference it was computed from
# (for a bumpless switch) and when the fallback's clock started (nan: not running) - in place only
NOW_T, NOW_XREF, NOW_ERR, NOW_STATE, NOW_REF, NOW_FALLBACK_SINCE = 0, 1, 2, 3, 7, 10
# Supervisor.consts: the lead [m/rad], the error bound [m], error_after_s (inf: none), the tick [s]
SC_LEAD, SC_MAX_ERROR, SC_ERROR_AFTER, SC_TICK = range(4)


@numba.njit(cache=True)
def track_error(now, err, sc, t, th1, w1, th2, w2, xr, vr, ar):
    """The tick's bookkeeping before the law (Supervisor.tick and the compiled tick both run this):
    the time, the reference and the state it saw, and the table's tracking error and its statistics.
    Returns the error [m]."""
    now[NOW_T] = t
    now[NOW_XREF] = xr
    now[NOW_STATE] = th1
    now[NOW_STATE + 1] = w1
    now[NOW_STATE + 2] = th2
    now[NOW_STATE + 3] = w2
    now[NOW_REF] = xr
    now[NOW_REF + 1] = vr
    now[NOW_REF + 2] = ar
    e = sc[SC_LEAD] * th2 - xr
    now[NOW_ERR] = e
    a = abs(e)
    err[ERR_SQ] += e * e
    err[ERR_N] += 1.0
    if a > err[ERR_MAX]:
        err[ERR_MAX] = a
    if t >= sc[SC_ERROR_AFTER]:
        err[ERR_SQ + 3] += e * e
        err[ERR_N + 3] += 1.0
        if a > err[ERR_MAX + 3]:
            err[ERR_MAX + 3] = a
    return e


def _now_slot(i: int, doc: str) -> Any:
    """A property reading and writing ``Supervisor.now[i]``; typed where it is bound."""
    return property(lambda self: float(self.now[i]), lambda self, v: self.now.__setitem__(i, v), doc=doc)


class Supervisor:
    """The host's position controller for one axis: reference, law, adaptation, fallback.

    ``tick()`` is called every tick with the state estimate at the newest sample and returns the
    control torque for the next tick. ``offer()`` passes a new identification (from the fit
    jobs); ``poll()`` collects redesigns from the control process. Nothing here blocks.
    """

    def __init__(self, settings: ControlSettings, nominal: AxisParams, *, tick: float, torque_limit: float,
                 reference, jobs=None, error_after_s: float | None = None, per_sample=None,
                 reference_options: ReferenceOptions | None = None) -> None:
        self.s = settings
        self.per_sample = per_sample            # e.g. rt_ident.estimators.svf.SvfEstimator, fed every sample
        self.nominal = nominal
        self.tick_s = tick
        self.lead = nominal.lead
        self.reference = reference              # the configured path; the controller follows self.anchor
        self.anchor = Anchor(reference, reference_options or ReferenceOptions(),
                             brake=braking_limits(nominal.I1 + nominal.I2, nominal.lead, torque_limit))
        self._last_stall: tuple[float, float] | None = None     # (t, length [s]) of the newest loop stall
        self.jobs = jobs
        self.error_after_s = error_after_s
        self.conservative = rigid_controller(nominal, tick, settings)
        initial = self.conservative
        if settings.mode == "fixed":
            initial = model_controller(nominal, tick, settings, kind="fixed")
        self.law = StateFeedback(initial, tick=tick, torque_limit=torque_limit, feedforward=settings.feedforward)
        self.stats = ControlStats()
        self.in_fallback = False
        self._held: Controller | None = None     # the model controller to go back to at the recovery
        self._last_request_t = -math.inf
        self._pending = False
        self._due: tuple[np.ndarray, Any, str] | None = None   # a request _consider() decided on
        self._taken: list | None = None                     # a result taken, unpickled on the next poll
        self._result: dict[str, Any] | None = None          # an accepted design waiting for a quiet tick
        self._result_t = 0.0
        self._req = 0
        self._req_generation = 0                            # the control process a request went to
        self.now = np.zeros(NOW_FALLBACK_SINCE + 1)     # NOW_*: t, x_ref, error, state, reference, fallback clock
        self.now[NOW_FALLBACK_SINCE] = math.nan
        self.consts = np.array([self.lead, settings.max_error_m,
                                math.inf if error_after_s is None else float(error_after_s), tick])
        self.probe_scale = 1.0      # probing-excitation amplitude factor (dual excitation)
        # per-sample trust (assess): the window of estimates, the changes seen, the latest one's time,
        # whether the estimate is trusted now, the audit's veto and its run of disagreements
        self._win = np.zeros((max(int(settings.trust_window), 2), 4))
        self._win_n = 0
        self._look = np.zeros(LOOK_SIZE)
        s = settings
        thresholds = np.maximum([s.min_change, s.min_change, s.min_change_damping, s.min_change], 1e-12)  # divisors
        self._trust_consts = np.array([*(float(getattr(nominal, k)) for k in KEYS), *_inner(s.plausible),
                                       s.settle_tolerance, s.interval_tolerance, *thresholds])
        self._model_of: tuple[Controller | None, np.ndarray] = (None, np.ones(4))  # (controller, its model's values)
        if per_sample is not None and s.mode == "adaptive" and s.trust == "per-sample":   # assess's look:
            # compiled (or loaded) now, not in the loop's first tick
            R, Sigma, acc, p, scale = per_sample.evidence
            window_look(np.zeros((2, 4)), 0, False, self._trust_consts, R, Sigma, acc, p, scale, np.ones(4),
                        np.zeros(LOOK_SIZE))
        largest_change(np.ones(4), np.ones(4), self._trust_consts)      # offer's, likewise
        self._changes_seen = 0
        self._frozen_seen = 0       # the estimator's dead-zone count at the last look
        self._change_t: float | None = None
        self._urgent = False        # a change detected and no request made since: the interval does not apply
        self._inertia_seen = np.full(3, math.nan)   # the per-sample I1 + I2 at the last three looks
        self._following = False     # from a detected change until a design is switched in
        self.own_trust = False
        self._vetoed = False
        self._disagreements = 0
        self._audited: Controller | None = None     # the model design in force when the fit last agreed

    @property
    def controller(self) -> Controller:
        return self.law.controller

    t: float = _now_slot(NOW_T, "the newest tick's time [s]")
    x_ref: float = _now_slot(NOW_XREF, "the table's reference then [m]")
    error: float = _now_slot(NOW_ERR, "the table's tracking error then [m]")

    @property
    def _fallback_since(self) -> float | None:
        v = float(self.now[NOW_FALLBACK_SINCE])
        return None if math.isnan(v) else v

    @_fallback_since.setter
    def _fallback_since(self, value: float | None) -> None:
        self.now[NOW_FALLBACK_SINCE] = math.nan if value is None else value

    # ------------------------------------------------------------------ tick
    def tick(self, t: float, th1: float, w1: float, th2: float, w2: float) -> float:
        xr, vr, ar, a_ff = self.reference_at(t)
        err = track_error(self.now, self.stats.err, self.consts, t, th1, w1, th2, w2, xr, vr, ar)
        self._watch(t, abs(err))
        return self.law.step(th1, w1, th2, w2, xr, vr, ar, a_ff, self.lead)

    def reference_at(self, t: float) -> tuple[float, float, float, float]:
        """The reference at ``t`` (position, velocity, acceleration) and its acceleration half a tick
        after the torque computed now lands (the feedforward's)."""
        ref = self.anchor
        xr, vr, ar = ref.point(t)
        return xr, vr, ar, ref.point(t + 1.5 * self.tick_s)[2]

    def start(self, t: float, th1: float, w1: float, th2: float, w2: float) -> None:
        """The first tick: the reference is anchored where the table is (:mod:`rt_ident.control.anchor`).
        The table was at rest when the drive was enabled: what speed it shows now is the probe's first
        millisecond, not a motion to follow."""
        a = self.anchor
        a.start(t, self.lead * th2, 0.0)
        detail = f"origin {a.origin * 1e3:+.3f} mm ({a.options.origin})"
        if a.rejoining and a.last_rejoin is not None and abs(a.last_rejoin["offset_m"]) > 1e-6:
            r = a.last_rejoin
            detail += (f"; approach {r['offset_m'] * -1e3:+.3f} mm to the path's start in "
                       f"{r['duration_s']:.2f} s")
        self.stats.events.append((t, "anchored", detail))

    def resume(self, t: float, th1: float, w1: float, th2: float, w2: float, stall_s: float) -> None:
        """The first tick after a loop stall long enough that the drive dropped the host's torque:
        re-plan from where the table is (a rejoin from its position and speed to the path), nothing in
        flight, the integral re-seeded for zero feedback torque. The torque does not step."""
        a = self.anchor
        x, v = self.lead * th2, self.lead * w2
        a.replan(t, x, v)
        xr, vr, ar = a.point(t)
        self.law.rebase(th1, w1, th2, w2, xr, vr, ar, self.lead)
        self._last_stall = (t, stall_s)
        r = a.last_rejoin if a.rejoining else None
        braked = f", braked at {r['brake_m_s2']:.2g} m/s²" if r is not None else ""
        self.stats.events.append((t, "stall", f"{stall_s * 1e3:.0f} ms loop stall: re-planned from x = "
                                             f"{x * 1e3:+.3f} mm at {v * 1e3:+.1f} mm/s{braked}"))

    def after_stall(self, t: float, within_s: float = 2.0) -> str:
        """' (0.40 s after a 470 ms loop stall)' when a stall came shortly before ``t``, else ''."""
        st = self._last_stall
        if st is None or not 0.0 <= t - st[0] <= within_s:
            return ""
        return f" ({t - st[0]:.2f} s after a {st[1] * 1e3:.0f} ms loop stall)"

    def _watch(self, t: float, abs_err: float) -> None:
        """Error above the bound: fall back to the conservative controller (once), and start the
        clock; back below half the bound: recovered. The clock running out stops the axis."""
        s = self.s
        if abs_err > s.max_error_m:
            if self.controller.kind != "conservative":
                self._fall_back(t, f"tracking error {abs_err * 1e6:.1f} um > {s.max_error_m * 1e6:.1f} um",
                                hold_current=True)
            elif self._fallback_since is None:
                self._fallback_since = t
        elif abs_err <= 0.5 * s.max_error_m and self._fallback_since is not None:
            self._fallback_since = None
            if self.in_fallback:
                self.in_fallback = False
                self.stats.events.append((t, "recovered", f"error {abs_err * 1e6:.1f} um"))
                held, self._held = self._held, None
                if held is not None and self._stale(held.model) is None:
                    # a design accepted while recovering waited for this: otherwise the axis would stay
                    # on the (slower) fallback until the next design, a second or more
                    self._switch(held)
                    self.stats.events.append((t, "applied", "the model controller held through the fallback"))
        if self._fallback_since is not None and t - self._fallback_since > s.fallback_timeout_s:
            raise ControlFallbackStop(f"tracking error above {s.max_error_m * 1e6:.1f} um for more than "
                                      f"{s.fallback_timeout_s:g} s on the conservative controller"
                                      + self.after_stall(t, within_s=s.fallback_timeout_s + 2.0))

    def _fall_back(self, t: float, why: str, hold_current: bool = False) -> None:
        """Onto the conservative controller. ``hold_current`` (a tracking-error fallback): the model
        controller in force goes back in at the recovery if it still fits the estimate then: a switch
        onto a fresh design while the error is still large can trip the fallback again at once, and the
        axis then runs the slower fallback for a second or more."""
        if hold_current and self.controller.kind == "model" and self._held is None:
            self._held = self.controller
        self.in_fallback = True
        self._fallback_since = t
        self.stats.fallbacks += 1
        self.stats.events.append((t, "fallback", why + self.after_stall(t)))
        self._switch(self.conservative)

    def adopt(self, ctrl: Controller) -> None:
        """Switch to ``ctrl`` now, bumplessly (e.g. an oracle design in a benchmark)."""
        self._switch(ctrl)

    def _state_and_reference(self) -> tuple[float, float, float, float, float, float, float]:
        """(th1, w1, th2, w2, x_ref, v_ref, a_ref) the newest tick saw."""
        th1, w1, th2, w2, xr, vr, ar = (float(v) for v in self.now[NOW_STATE:NOW_REF + 3])
        return th1, w1, th2, w2, xr, vr, ar

    def _switch(self, ctrl: Controller) -> None:
        step = self.law.switch(ctrl, *self._state_and_reference(), self.lead)
        st = self.stats
        st.max_step_nm = max(st.max_step_nm, abs(step))
        st.applied.append((self.t, ctrl.kind, ctrl.model))
        del st.applied[:-50]

    # ------------------------------------------------------------ adaptation
    def observe(self, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, gap: bool,
                trace: np.ndarray | None = None) -> None:
        """Feed the per-sample estimator every sample of the block (a sequence gap restarts its filter);
        ``trace`` receives its filtered signals (rt_ident.estimators.svf.SvfEstimator.update_block)."""
        est = self.per_sample
        if est is None or self.s.mode != "adaptive":
            return
        if gap:
            est.restart_filter()
        est.update_block(theta1, theta2, torque, trace)

    def diverged(self, ident) -> str | None:
        """Why ``ident`` (an Identification or AxisParams) is not a usable estimate (non-finite, or
        far outside the nominal box)."""
        params = getattr(ident, "params", ident)
        lo, hi = self.s.plausible
        for k in KEYS:
            v = float(getattr(params, k))
            ref = float(getattr(self.nominal, k))
            if not math.isfinite(v) or v <= 0:
                return f"{k} = {v!r}"
            if not lo * ref <= v <= hi * ref:
                return f"{k} = {v:.4g} outside x{lo:g}..x{hi:g} of nominal {ref:.4g}"
        return None

    def _cross_check(self, ident, trusted: bool) -> tuple[AxisParams | None, Any, bool, str | None]:
        """(estimate, its 95 % intervals, trusted, why it diverged) for a new frequency fit ``ident``.
        The intervals may be a callable that computes them (they cost ~60 us and are needed only for
        a redesign).

        With a per-sample estimator, *it* is the estimate the controller follows, and it is trusted
        when the frequency fit (independent data use, the job process's Gauss-Newton) agrees with it within
        ``trust_tolerance`` on every parameter. Without one, the frequency fit's own trust decides.
        """
        est = self.per_sample
        if est is None:
            return ident.params, ident.ci95, trusted, self.diverged(ident)
        if not est.ready:
            return None, None, False, None
        p = est.params
        why = self.diverged(p)
        if why is not None:
            return p, None, False, why
        fit_why = self.diverged(ident)
        if fit_why is not None:                        # a frequency fit that diverged only withholds trust
            self.stats.last_disagreement = f"t={self.t:.3f} s: the frequency fit's {fit_why}"
            return p, None, False, None
        worst, rel, agree = worst_difference(p, ident.params, self.s.trust_tolerance)
        st = self.stats
        if agree:
            st.checks_agreed += 1
            return p, est.ci95, True, None        # the intervals (a 4x4 inverse) only if a redesign is asked
        st.checks_disagreed += 1
        st.last_disagreement = f"t={self.t:.3f} s: {worst} per-sample {getattr(p, worst):.4g} vs frequency fit " \
                               f"{getattr(ident.params, worst):.4g} ({100 * rel:.1f} %)"
        return p, None, False, None

    def assess(self, window: bool = True) -> None:
        """Every ASSESS_EVERY ticks (``trust = "per-sample"``): the per-sample estimate's own evidence
        (see the module docstring); trusted, it asks for a redesign when due. ``window=False`` (the
        ticks between, while :attr:`following`): the inertia feedforward only; the window keeps its
        5 ms spacing."""
        est = self.per_sample
        if est is None or self.s.mode != "adaptive" or self.s.trust != "per-sample":
            return
        st = self.stats
        changes = est.changes
        if changes != self._changes_seen:
            self._changes_seen = changes
            self._change_t = self.t
            self._urgent = self._following = True
            self._win_n = 0
            self._inertia_seen[:] = math.nan
            self.own_trust = False
            st.changes_detected += 1
            st.events.append((self.t, "change detected", "the per-sample estimator's residual test"))
            return
        frozen, self._frozen_seen = self._frozen_seen, est.frozen
        if not est.ready or frozen != self._frozen_seen:     # unexcited rows held back: nothing new to trust
            self._win_n = 0
            return
        if self._following:
            v = est.values_array()
            self._follow_inertia(float(v[0] + v[1]))
        if not window:
            return
        R, Sigma, acc, p, scale = est.evidence
        verdict = window_look(self._win, self._win_n, self._vetoed, self._trust_consts, R, Sigma, acc, p, scale,
                              self._model_values(), self._look)
        self._win_n += 1
        if verdict == WINDOW_FILLING:
            return
        trusted = verdict == WINDOW_TRUSTED
        if trusted and not self.own_trust:
            st.trusted_at.append(self.t)
            del st.trusted_at[:-20]
        self.own_trust = trusted
        self.probe_scale = self.s.probe_scale_trusted if trusted else 1.0
        if trusted:
            look = self._look
            self._consider(look[LOOK_MEAN:LOOK_MEAN + 4], partial(_intervals, look.copy()),
                           int(look[LOOK_WORST]), float(look[LOOK_CHANGE]))

    @property
    def following(self) -> bool:
        """From a detected change until a design for the new plant is switched in (assessed every tick)."""
        return self._following

    def _follow_inertia(self, inertia: float) -> None:
        """After a detected change, before the redesign: the inertia feedforward follows the per-sample
        I1 + I2 (seen first, and within a few percent ~10 ms after the change) once three looks in a row
        agree within settle_tolerance x 2.5 and it is plausible. The feedback gains and the reference
        twist stay the design's until the redesign switches them (bumplessly); the feedforward's change
        is the torque the new inertia needs along the reference. No design within FOLLOW_S: the
        feedforward goes back to the design's (the estimate was not good enough for one)."""
        c = self.law.consts
        if self._change_t is not None and self.t - self._change_t > FOLLOW_S:
            self._following = False
            c[C_INERTIA] = self.controller.inertia
            return
        seen = self._inertia_seen
        seen[0], seen[1], seen[2] = seen[1], seen[2], inertia
        nom = self.nominal.I1 + self.nominal.I2
        lo, hi = _inner(self.s.plausible)
        if not bool(np.all((seen >= lo * nom) & (seen <= hi * nom))):      # NaN (no look yet) fails too
            return
        if (seen.max() - seen.min()) > 2.5 * self.s.settle_tolerance * inertia:
            return
        if abs(inertia / c[C_INERTIA] - 1.0) <= self.s.settle_tolerance:
            return
        ci = self.per_sample.ci95() if self.per_sample is not None else None    # 4 x 4 inverse: rare
        if ci is None or any(not (ci[k][1] - ci[k][0]) <= 2.0 * FOLLOW_INTERVAL * inertia for k in ("I1", "I2")):
            return
        c[C_INERTIA] = inertia
        self.stats.feedforward_updates += 1

    def offer(self, ident, trusted: bool) -> None:
        """A new identification from the fit process: cross-check (with ``trust = "per-sample"``: audit),
        and redesign when adaptive, trusted and due. ``trusted`` is the frequency fit's own verdict (used
        when there is no per-sample estimator)."""
        if self.s.mode != "adaptive" or ident is None:
            return
        params, ci95, trusted, why = self._cross_check(ident, trusted)
        per_sample = self.per_sample is not None and self.s.trust == "per-sample"
        if per_sample:
            self._audit(trusted, why)
        else:           # dual excitation: probe less while the estimate is trusted, fully again when it is not
            self.probe_scale = self.s.probe_scale_trusted if (trusted and why is None) else 1.0
        if why is not None:
            if not self.in_fallback and self.controller.kind == "model":
                self._fall_back(self.t, f"estimate diverged: {why}")
            return
        if params is None or not trusted or per_sample:
            return
        if self._outside_margin(params) is not None:
            return                                     # plausible, but not inside the margin: no design from it
        values = _values(params)
        self._consider(values, ci95, *largest_change(values, self._model_values(), self._trust_consts))

    def _audit(self, agreed: bool, why: str | None) -> None:
        """The frequency fit's verdict on the per-sample estimate: agreeing lifts a veto; disagreeing
        ``audit_vetoes`` times in a row outside the grace after a change vetoes the per-sample trust
        and rolls a model controller back to the last design the fit agreed with (the conservative
        one when there is none)."""
        if agreed:
            self._disagreements = 0
            if self.controller.kind == "model":
                self._audited = self.controller
            if self._vetoed:
                self._vetoed = False
                self.stats.events.append((self.t, "audit", "the frequency fit agrees again: per-sample trust restored"))
            return
        if why is not None or (self._change_t is not None and self.t - self._change_t < self.s.audit_grace_s):
            return
        if self.per_sample is None or not self.per_sample.ready:
            return
        self._disagreements += 1
        if self._disagreements < self.s.audit_vetoes or self._vetoed:
            return
        self._vetoed = True
        self.own_trust = False
        self.stats.audit_vetoes += 1
        detail = f"the frequency fit disagrees with the per-sample estimate: {self.stats.last_disagreement}"
        self.stats.events.append((self.t, "audit veto", detail))
        if self.in_fallback or self.controller.kind != "model":
            return
        back = self._audited
        if back is not None:
            if back is not self.controller:
                self._switch(back)
                self.stats.events.append((self.t, "rolled back", "to the last design the frequency fit agreed with: "
                                          + _params_text(back.model)))
        else:
            self._fall_back(self.t, "audit veto: " + detail)

    def _consider(self, values: np.ndarray, ci95: Any, worst: int, change: float) -> None:
        """A trusted estimate of (I1, I2, B, K) whose parameter ``worst`` moved most from the design in
        force (:func:`largest_change`, by ``change``): decide on a redesign (sent on the next :meth:`poll`)."""
        if self.jobs is None or self._pending:
            return
        if not self._urgent and self.t - self._last_request_t < self.s.redesign_interval_s:
            return
        # each parameter's change against its own threshold (B's is wider: ControlSettings.min_change_damping)
        if self.controller.kind == "model" and change < self._trust_consts[TC_THRESHOLD + worst]:
            self._urgent = False
            return
        if not self.jobs.ready:
            return
        # asked on the next tick (poll): the cross-check above and the request are each a few hundred
        # microseconds of Python, too much for one tick beside its own work
        self._pending = True
        if self.controller.kind == "model":     # the estimate moved: the fit lags behind it for a while
            self._change_t = self.t
        self._urgent = False
        self._due = (values.copy(), ci95, KEYS[worst])

    def _request(self, values: np.ndarray, ci95: Any, moved: str) -> None:
        """Ask the control process for a design for ``values`` (I1, I2, B, K; decided by :meth:`_consider`)."""
        assert self.jobs is not None                  # offer() decides only with a control process
        if not self.jobs.ready:
            self._pending = False
            return
        self._req += 1
        if callable(ci95):
            ci95 = ci95()
        ctrl = self.controller
        in_force = ({"gains": [float(v) for v in ctrl.gains],
                     "model": {k: float(getattr(ctrl.model, k)) for k in KEYS}}
                    if ctrl.kind == "model" and not self.in_fallback else None)
        req = {"conservative": [float(v) for v in self.conservative.gains], "in_force": in_force,
               "nominal": {**{k: float(getattr(self.nominal, k)) for k in KEYS}, "lead": self.lead},
               "params": {**{k: float(v) for k, v in zip(KEYS, values)}, "lead": self.lead},
               "ci95": {k: tuple(ci95[k]) for k in KEYS} if ci95 else None,
               "tick": self.tick_s, "settings": self.s, "seq": self._req}
        if not self.jobs.submit(req):
            self._pending = False
            return
        self._req_generation = getattr(self.jobs, "generation", 0)
        self._last_request_t = self.t
        st = self.stats
        st.requests += 1
        why = moved if self.controller.kind == "model" else self.controller.kind
        st.why_requested[why] = st.why_requested.get(why, 0) + 1

    def _model_values(self) -> np.ndarray:
        """(I1, I2, B, K) of the model the controller in force was designed for."""
        ctrl = self.controller
        if self._model_of[0] is not ctrl:
            self._model_of = (ctrl, _values(ctrl.model))
        return self._model_of[1]

    def poll(self) -> None:
        """One step per tick while a redesign is under way: send the request :meth:`offer` decided on;
        take a finished design; on the next tick unpickle it and reject it or wait for a quiet tick
        (:meth:`_quiet`) to adopt it."""
        if self.jobs is None or not self._pending:
            return
        if self._due is not None:
            due, self._due = self._due, None
            self._request(*due)
            return
        if self._result is not None:
            stale = self._stale(_designed_for(self._result))
            if stale is not None or self._quiet(self._result["controller"]):
                res, self._result = self._result, None
                self._pending = False
                if stale is not None:
                    res, self._urgent = {"accepted": False, "reason": stale}, True
                self._adopt(res)
            return
        if self._taken is None:
            if getattr(self.jobs, "generation", 0) != self._req_generation:
                # the control process was restarted (it died or hung) with the request: ask again at once
                self._pending, self._urgent = False, True
                self.stats.events.append((self.t, "request lost", "the control process was restarted; asking again"))
                return
            self._taken = self.jobs.take() or None
            return
        taken, self._taken = self._taken, None
        res = self.jobs.unpack(taken)
        if res is None:
            return
        st = self.stats
        st.latency_s.append(self.t - self._last_request_t)
        if res.get("cpu_s") is not None:
            st.cpu_s.append(float(res["cpu_s"]))
        stale = self._stale(_designed_for(res)) if res.get("accepted") else None
        if stale is not None:
            # a design can take ~1 s on a loaded host, and the axis it was made for may have changed
            # since: a design for the inertia before a load change, applied after it, can drive the
            # table hundreds of um off and into the fallback. The next trusted look asks again at once.
            res = {"accepted": False, "reason": stale}
            self._urgent = True
        if res.get("accepted") and not self.in_fallback and "kept_for" not in res:
            self._result_t = self.t
            if not self._quiet(res["controller"]):
                self._result = res
                return
        self._pending = False
        self._adopt(res)

    def _quiet(self, ctrl: Controller) -> bool:
        """Whether to switch to ``ctrl`` now: the reference does not accelerate and the new law's feedback
        torque before re-seeding is within ``SWITCH_BUMP`` of the old one (so the re-seeded integral
        starts no transient), or QUIET_WAIT_S has passed since the design arrived."""
        if self.t - self._result_t >= QUIET_WAIT_S:
            return True
        if abs(float(self.now[NOW_REF + 2])) > 0.0:
            return False
        bump = self.law.bump(ctrl, *self._state_and_reference(), self.lead)
        return abs(bump) <= SWITCH_BUMP * self.law.limit

    def _adopt(self, res: dict[str, Any]) -> None:
        """A redesign's result: switch to an accepted design (hold it through a fallback), or count the
        rejection."""
        st = self.stats
        if res.get("accepted") and "kept_for" in res:
            self._keep(res)
        elif res.get("accepted"):
            st.accepted += 1
            text = _params_text(res["controller"].model)
            if "confirms" in res:
                text += f" (the configured axis's design, confirmed by the estimate {_params_text(res['confirms'])})"
            st.events.append((self.t, "accepted", text + (" (not applied: in fallback)" if self.in_fallback else "")))
            fb = res.get("fallback")
            if fb is not None:                   # the fallback itself no longer suited the axis
                self.conservative = fb
                st.events.append((self.t, "fallback redesigned", str(res.get("fallback_reason"))))
            elif res.get("fallback_reason"):
                st.events.append((self.t, "fallback kept", str(res["fallback_reason"])))
            if not self.in_fallback:
                self._switch(res["controller"])
                self._following = False
                if "confirms" in res:       # the configured design, taken for this estimate: measure from it
                    self._model_of = (self.controller, _values(res["confirms"]))
            else:
                self._held = res["controller"]
            # recovering: onto the conservative controller that suits the axis
            if self.in_fallback and fb is not None:
                self._switch(fb)
        else:
            st.rejected += 1
            reason = str(res.get("reason"))
            st.reasons.append(reason)
            st.events.append((self.t, "rejected", reason))

    def _keep(self, res: dict[str, Any]) -> None:
        """The design in force checked and kept for the estimate ``res["kept_for"]``
        (:func:`rt_ident.control.job.keep_design`):
        later changes are measured from that estimate, the feedforward goes back to the design's."""
        st, p = self.stats, res["kept_for"]
        st.kept += 1
        st.events.append((self.t, "kept", f"{_params_text(p)}: {res.get('reason')}"))
        if self.in_fallback or self.controller.kind != "model":    # a fallback came while the job ran
            return
        self._model_of = (self.controller, _values(p))
        self._following = False
        self.law.consts[C_INERTIA] = self.controller.inertia
        st.applied.append((self.t, "kept", p))
        del st.applied[:-50]

    def _stale(self, model: AxisParams) -> str | None:
        """Why a finished design no longer fits the axis (the per-sample estimate now differs from the
        model it was designed for by more than ``trust_tolerance``), or None."""
        est = self.per_sample
        if est is None or not est.ready:
            return None
        p = est.params
        worst, rel, fits = worst_difference(p, model, self.s.trust_tolerance)
        if fits:
            return None
        return (f"stale: designed for {worst} = {getattr(model, worst):.4g}, the axis now reads "
                f"{getattr(p, worst):.4g} ({100 * rel:.0f} % off)")

    # --------------------------------------------------------------- summary
    def outside_design_box(self) -> str | None:
        """Why the loop makes no design for the axis as it identifies: the per-sample estimate outside the part
        of the plausible box it designs in (an [axis] far from the axis), or None."""
        est = self.per_sample
        if est is None or not est.ready or self.s.mode != "adaptive":
            return None
        return self._outside_margin(est.params)

    def _outside_margin(self, params: AxisParams) -> str | None:
        """Which parameter of ``params`` lies outside the plausible box narrowed by PLAUSIBLE_MARGIN, or None."""
        lo, hi = _inner(self.s.plausible)
        for k in KEYS:
            v, ref = float(getattr(params, k)), float(getattr(self.nominal, k))
            if not lo * ref <= v <= hi * ref:
                return (f"the axis identifies as {k} = {v:.4g}, {v / ref:.3g} x the configured axis.{k} ({ref:.4g}); "
                        f"the loop designs only within x{lo:.3g}..x{hi:.3g} of [axis]: correct [axis] (rt-ident "
                        "commission writes it)")
        return None

    def _per_sample_summary(self) -> dict[str, Any] | None:
        est, st = self.per_sample, self.stats
        if est is None:
            return None
        return {"method": type(est).__name__, "params": est.values(), "counters": est.counters,
                "cross_checks": {"agreed": st.checks_agreed, "disagreed": st.checks_disagreed,
                                 "last_disagreement": st.last_disagreement or None},
                "trust": self.s.trust, "trusted": self.own_trust if self.s.trust == "per-sample" else None,
                "changes_detected": st.changes_detected, "audit_vetoes": st.audit_vetoes,
                "feedforward_updates": st.feedforward_updates,
                "trusted_at_s": [round(t, 4) for t in st.trusted_at]}

    def summary(self) -> dict[str, Any]:
        st = self.stats
        rms = math.sqrt(st.sq_err / st.n_err) if st.n_err else None
        after = math.sqrt(st.sq_err_after / st.n_err_after) if st.n_err_after else None
        return {"mode": self.s.mode, "rms_error_m": rms, "max_error_m": st.max_err if st.n_err else None,
                "rms_error_after_change_m": after,
                "max_error_after_change_m": st.max_err_after if st.n_err_after else None,
                "redesigns": {"accepted": st.accepted, "rejected": st.rejected, "kept": st.kept,
                              "rejected_reasons": st.reasons[-10:], "requested": st.requests,
                              "requested_for": dict(st.why_requested),
                              "latency_s": _spread(st.latency_s), "worker_cpu_s": _spread(st.cpu_s)},
                "fallbacks": st.fallbacks, "controller": self.controller.kind,
                "controller_model": {k: float(getattr(self.controller.model, k)) for k in KEYS},
                "gains": [float(g) for g in self.controller.gains],
                "margins": self.controller.margins,
                "max_switch_step_nm": st.max_step_nm,
                "applied": [{"t": round(t, 4), "kind": k, "model": {q: float(getattr(m, q)) for q in KEYS}}
                            for t, k, m in st.applied],
                "reference": {"origin": self.anchor.options.origin, "origin_m": self.anchor.origin,
                              "rejoins": self.anchor.rejoins, "last_rejoin": self.anchor.last_rejoin},
                "per_sample": self._per_sample_summary(),
                "no_design": self.outside_design_box(),
                "events": [{"t": round(t, 4), "kind": k, "detail": d} for t, k, d in st.events[-50:]]}


def _values(p: AxisParams) -> np.ndarray:
    """(I1, I2, B, K) of ``p``."""
    return np.array([float(getattr(p, k)) for k in KEYS])


def _designed_for(res: dict[str, Any]) -> AxisParams:
    """The model an accepted result is for: its new design's, or the estimate the design in force was kept for."""
    return res.get("kept_for") or res.get("confirms") or res["controller"].model


def _spread(values: list[float]) -> dict[str, float] | None:
    """{"mean", "max", "last"} of a list of durations [s], or None when empty."""
    if not values:
        return None
    return {"mean": sum(values) / len(values), "max": max(values), "last": values[-1]}


def _params_text(p: AxisParams) -> str:
    return ", ".join(f"{k}={getattr(p, k):.4g}" for k in KEYS)

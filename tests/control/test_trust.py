"""Per-sample trust in the supervisor (rt_ident.control.adaptation: assess, the audit, the inertia
feedforward after a change, the quiet switch) and the change detector it reads
(rt_ident.estimators.svf)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.params import AxisParams
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.control import adaptation as A
from rt_ident.control import job as J
from rt_ident.control.adaptation import Supervisor
from rt_ident.control.design import check_family, error_norm, reference_error, sampled_model
from rt_ident.control.job import ControlSettings, model_controller
from rt_ident.control.law import C_INERTIA
from rt_ident.control.reference import Hold
from rt_ident.estimators.svf import ACC_SIZE, ACC_SSE, ACC_W, ACC_W2, SvfEstimator, SvfSettings, interval_halves
from tests.estimators.test_svf import FakeControlProcess

P = AxisParams(I1=2.7e-5, I2=8.3e-6, B=2.1e-3, K=110.0)
HEAVY = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)
DT = 2.9481e-5
S = ControlSettings()


class _Estimate:
    """A per-sample estimator whose estimate, intervals (+- ``half`` x each value), change count and
    dead-zone count a test sets (``nan``: its I2 not finite); its evidence arrays are laid out as
    SvfEstimator's."""
    ready = True
    nan = False

    def __init__(self, p: AxisParams, half: float = 0.002):
        self.p, self.half, self.changes, self.frozen = p, half, 0, 0

    def values_array(self):
        return np.array([self.p.I1, self.p.I2, self.p.B, self.p.K])

    @property
    def params(self):
        return self.p

    @property
    def evidence(self):
        W = 1000.0
        acc = np.zeros(ACC_SIZE)
        acc[ACC_W] = acc[ACC_W2] = W
        acc[ACC_SSE] = 2.0 * W                               # residual variance 1
        r = W / (W - 4.0) * (1.96 / self.half) ** 2          # interval_halves then gives half x value
        p = np.array([1.0, math.nan if self.nan else 1.0, 1.0, 1.0])      # scaled
        return r * np.eye(4), np.zeros((4, 4)), acc, p, self.values_array()

    def ci95(self):
        return {k: (getattr(self.p, k) * (1 - self.half), getattr(self.p, k) * (1 + self.half))
                for k in ("I1", "I2", "B", "K")}

    def values(self):
        return {}

    counters: dict = {}


def test_the_fake_estimators_evidence_gives_the_intervals_it_states():
    est = _Estimate(HEAVY, half=0.03)
    R, Sigma, acc, p, scale = est.evidence
    half = np.empty(4)
    assert interval_halves(R, Sigma, acc, scale, half)
    want = np.array([hi - lo for lo, hi in est.ci95().values()]) / 2
    assert np.allclose(half, want, rtol=1e-12)


def _supervisor(est, **settings):
    w = FakeControlProcess()
    sup = Supervisor(ControlSettings(**settings), P, tick=1e-3, torque_limit=1.0, reference=Hold(0.0), jobs=w,
                     per_sample=est)
    sup.adopt(model_controller(P, 1e-3, S))
    return sup, w


def _looks(sup, n, dt=0.005):
    for _ in range(n):
        sup.t = sup.t + dt
        sup.assess()


def test_a_steady_narrow_per_sample_estimate_asks_for_a_redesign_with_no_frequency_fit():
    est = _Estimate(HEAVY)
    sup, w = _supervisor(est)
    _looks(sup, S.trust_window - 1)
    assert not sup._pending                               # the window is not full yet
    _looks(sup, 1)
    assert sup.own_trust and sup._pending
    sup.poll()
    assert len(w.requests) == 1 and w.requests[0]["params"]["I2"] == pytest.approx(HEAVY.I2)
    assert sup.stats.trusted_at and sup.stats.checks_agreed == 0


def test_a_steady_narrow_estimate_outside_the_plausible_box_or_not_finite_is_not_trusted():
    far = AxisParams(I1=P.I1, I2=6 * P.I2, B=P.B, K=P.K)      # plausible: nominal x 0.2..5
    est = _Estimate(far)
    sup, w = _supervisor(est)
    _looks(sup, 8)
    assert not sup.own_trust and not sup._pending and not w.requests
    est.p = HEAVY
    _looks(sup, S.trust_window)
    assert sup.own_trust                                       # the same supervisor trusts a plausible one
    est.nan = True
    _looks(sup, 1)
    assert not sup.own_trust and sup.probe_scale == 1.0       # a NaN in the window: no evidence at once


def test_a_moving_estimate_wide_intervals_or_a_frozen_estimator_are_no_evidence():
    est = _Estimate(HEAVY)
    sup, w = _supervisor(est)
    for i in range(8):                                    # I2 climbing 1.5 % per look
        est.p = AxisParams(I1=P.I1, I2=HEAVY.I2 * (1 + 0.015 * i), B=P.B, K=P.K)
        _looks(sup, 1)
    assert not sup.own_trust and not sup._pending
    est.p, est.half = HEAVY, 0.2                          # steady, but the intervals are +-20 %
    _looks(sup, 8)
    assert not sup.own_trust and not sup._pending
    est.half = 0.002
    for _ in range(8):                                    # steady and narrow, but held back by the dead zone
        est.frozen += 100
        _looks(sup, 1)
    assert not sup.own_trust and not sup._pending
    _looks(sup, S.trust_window)
    assert sup.own_trust and sup._pending


def test_a_detected_change_restarts_the_window_and_is_not_held_back_by_the_redesign_interval():
    est = _Estimate(HEAVY)
    sup, w = _supervisor(est)
    _looks(sup, S.trust_window)
    sup.poll()
    w.result = {"accepted": True, "controller": model_controller(HEAVY, 1e-3, S), "seq": 1}
    sup.poll()
    sup.poll()
    assert sup.controller.model is not None and sup.controller.model.I2 == pytest.approx(HEAVY.I2)
    heavier = AxisParams(I1=P.I1, I2=4 * P.I2, B=P.B, K=P.K)
    est.p, est.changes = heavier, 1                       # 10 ms later the load changes again
    _looks(sup, 1, dt=0.002)
    assert sup.stats.changes_detected == 1 and not sup.own_trust
    _looks(sup, S.trust_window, dt=0.001)                 # well inside redesign_interval_s of the last request
    assert sup._pending
    sup.poll()
    assert len(w.requests) == 2 and w.requests[1]["params"]["I2"] == pytest.approx(heavier.I2)


def test_the_inertia_feedforward_follows_the_estimate_after_a_change_and_returns_without_a_design():
    est = _Estimate(P)
    sup, _ = _supervisor(est)
    est.p, est.changes = HEAVY, 1
    _looks(sup, 1, dt=0.001)
    assert sup.following
    _looks(sup, 3, dt=0.001)                              # three looks that agree
    c = sup.law.consts
    assert c[C_INERTIA] == pytest.approx(HEAVY.I1 + HEAVY.I2)
    assert sup.stats.feedforward_updates == 1
    sup.t += A.FOLLOW_S + 0.01                            # no design for the new plant in time
    sup.assess()
    assert not sup.following and c[C_INERTIA] == pytest.approx(P.I1 + P.I2)


def test_the_inertia_feedforward_does_not_follow_an_estimate_with_wide_intervals():
    est = _Estimate(P)
    sup, _ = _supervisor(est)
    est.p, est.changes, est.half = HEAVY, 1, 0.3
    _looks(sup, 5, dt=0.001)
    assert sup.law.consts[C_INERTIA] == pytest.approx(P.I1 + P.I2) and sup.stats.feedforward_updates == 0


def _ident(p: AxisParams):
    from types import SimpleNamespace

    return SimpleNamespace(params=p, ci95=None, trusted=True)


def test_the_audit_vetoes_and_rolls_back_to_the_last_design_it_agreed_with_then_lifts_the_veto():
    est = _Estimate(P)
    sup, w = _supervisor(est, audit_grace_s=0.0)
    agreed = sup.controller
    sup.t = 1.0
    sup.offer(_ident(P), True)                            # the fit agrees with the design in force
    sup.adopt(model_controller(HEAVY, 1e-3, S))           # later a design from the per-sample estimate alone
    est.p = HEAVY
    for t in (2.0, 2.1):                                  # the fit keeps seeing the nominal axis
        sup.t = t
        sup.offer(_ident(P), True)
    assert sup.stats.audit_vetoes == 1 and sup.controller is agreed and sup.stats.fallbacks == 0
    assert [e[1] for e in sup.stats.events[-2:]] == ["audit veto", "rolled back"]
    _looks(sup, 8)
    assert not sup.own_trust and not sup._pending         # vetoed: the per-sample evidence is not enough
    sup.offer(_ident(HEAVY), True)                        # the fit now agrees: trust restored
    _looks(sup, S.trust_window)
    assert sup.own_trust and sup._pending


def test_the_audit_waits_out_the_fits_lag_after_a_change():
    est = _Estimate(P)
    sup, _ = _supervisor(est, audit_grace_s=1.0)
    est.p, est.changes = HEAVY, 1
    _looks(sup, 1)
    for t in (0.3, 0.5, 0.7):                             # the fit still averages the old plant in
        sup.t = t
        sup.offer(_ident(P), True)
    assert sup.stats.audit_vetoes == 0
    for t in (1.2, 1.4):
        sup.t = t
        sup.offer(_ident(P), True)
    assert sup.stats.audit_vetoes == 1


def _design_arrives_mid_acceleration():
    """A supervisor whose finished design arrives while the reference accelerates; its controller before."""
    sup, w = _supervisor(_Estimate(HEAVY))
    before = sup.controller
    _looks(sup, S.trust_window)
    sup.poll()
    sup.now[A.NOW_REF + 2] = 0.5                          # the reference accelerates
    w.result = {"accepted": True, "controller": model_controller(HEAVY, 1e-3, S), "seq": 1}
    sup.poll()
    sup.poll()
    return sup, before


def test_a_finished_design_waits_for_a_tick_where_the_reference_does_not_accelerate():
    sup, before = _design_arrives_mid_acceleration()
    sup.t += 0.01
    sup.poll()
    assert sup.controller is before and sup._pending
    sup.now[A.NOW_REF + 2] = 0.0
    sup.poll()
    assert sup.controller is not before and not sup._pending and sup.stats.accepted == 1


def test_a_finished_design_is_switched_in_after_the_quiet_wait_even_mid_acceleration():
    sup, before = _design_arrives_mid_acceleration()
    assert sup.controller is before
    sup.t += A.QUIET_WAIT_S + 0.001
    sup.poll()
    assert sup.controller is not before and sup.stats.accepted == 1


def _excited(sim: PlantSimulator, seconds: float):
    u = np.resize(schroeder_multisine(512, (1, 20), peak=0.3).signal, int(seconds / DT))
    return sim.step_block(u)


def _feed(est: SvfEstimator, b, block: int = 34) -> list[tuple[int, np.ndarray]]:
    out = []
    for i in range(0, len(b.theta1), block):
        est.update_block(b.theta1[i:i + block], b.theta2[i:i + block], b.torque_meas[i:i + block])
        out.append((est.changes, est.values_array()))
    return out


def test_the_svf_detects_an_inertia_step_within_5_ms_and_is_within_2_percent_50_ms_later():
    sim = PlantSimulator(P, DT, sensors=SensorConfig(torque_meas_noise=5e-4), controller=HoldController(), seed=4)
    est = SvfEstimator(DT, P, SvfSettings(q1=2 * math.pi / 2**17, q2=1e-7 / 7.96e-4))
    _feed(est, _excited(sim, 1.0))
    assert est.changes == 0                               # a second of a steady plant: no alarm
    sim.set_params(HEAVY)
    trail = _feed(est, _excited(sim, 0.2))
    block_s = 34 * DT
    first = next(i for i, (c, _) in enumerate(trail) if c > 0)
    assert first * block_s <= 0.005, first * block_s
    later = trail[first + int(round(0.05 / block_s))][1]
    assert abs(later[1] / HEAVY.I2 - 1.0) < 0.02 and abs(later[0] / HEAVY.I1 - 1.0) < 0.02, later


def test_the_svf_without_its_detector_takes_several_memory_constants_for_the_same_step():
    sim = PlantSimulator(P, DT, sensors=SensorConfig(torque_meas_noise=5e-4), controller=HoldController(), seed=4)
    est = SvfEstimator(DT, P, SvfSettings(q1=2 * math.pi / 2**17, q2=1e-7 / 7.96e-4, change_discount=1.0,
                                          change_threshold=1e300))
    _feed(est, _excited(sim, 1.0))
    sim.set_params(HEAVY)
    trail = _feed(est, _excited(sim, 0.2))
    at_60_ms = trail[int(round(0.06 / (34 * DT)))][1]
    assert est.changes == 0 and abs(at_60_ms[1] / HEAVY.I2 - 1.0) > 0.1, at_60_ms


def test_largest_change_weighs_each_parameter_against_its_own_redesign_threshold():
    tc = _supervisor(_Estimate(P))[0]._trust_consts           # min_change 2 %, B's min_change_damping 10 %
    model = np.array([1.0, 1.0, 1.0, 1.0])
    worst, change = A.largest_change(np.array([1.0, 1.05, 1.2, 1.0]), model, tc)
    assert (worst, change) == (1, pytest.approx(0.05))        # I2: 2.5 thresholds; B's 20 % is 2
    worst, change = A.largest_change(np.array([1.0, 1.03, 1.4, 1.0]), model, tc)
    assert (worst, change) == (2, pytest.approx(0.4))         # B: 4 thresholds against I2's 1.5
    worst, change = A.largest_change(np.array([1.0, 1.0, 1e-3, 1.0]), np.array([1.0, 1.0, 0.0, 1.0]), tc)
    assert worst == 2 and change > 1e6                         # a model without damping: any B has moved


SOFT = AxisParams(I1=P.I1, I2=P.I2, B=P.B, K=0.6 * P.K)


def _answered_by_the_job(sup, w):
    """The supervisor's pending request answered by the real redesign job, taken and applied."""
    sup.poll()
    w.result = res = J.redesign(w.requests[-1])
    sup.poll()
    sup.poll()
    return res


def test_a_design_in_force_is_kept_for_a_stiffness_change_the_loop_hardly_feels_and_later_looks_measure_from_it():
    est = _Estimate(SOFT)
    sup, w = _supervisor(est)
    before = sup.controller
    _looks(sup, S.trust_window)
    assert sup._pending
    res = _answered_by_the_job(sup, w)
    assert w.requests[-1]["in_force"]["model"]["K"] == P.K and res["kept_for"] == SOFT
    assert sup.controller is before and not sup._pending
    assert sup.stats.kept == 1 and sup.stats.accepted == 0 and sup.stats.max_step_nm == 0.0
    assert sup.stats.applied[-1][1:] == ("kept", SOFT)
    sup.t += S.redesign_interval_s
    _looks(sup, 2 * S.trust_window)
    assert not sup._pending and len(w.requests) == 1    # K's 40 % is measured from the kept estimate now


def test_an_inertia_change_is_switched_in_not_kept():
    sup, w = _supervisor(_Estimate(HEAVY))
    before = sup.controller
    _looks(sup, S.trust_window)
    res = _answered_by_the_job(sup, w)
    assert "kept_for" not in res and res["accepted"]
    assert sup.controller is not before and sup.controller.model == HEAVY and sup.stats.kept == 0


def test_keep_margin_0_switches_in_every_accepted_design():
    sup, w = _supervisor(_Estimate(SOFT), keep_margin=0.0)
    before = sup.controller
    _looks(sup, S.trust_window)
    _answered_by_the_job(sup, w)
    assert sup.controller is not before and sup.controller.model == SOFT and sup.stats.kept == 0


def _on_the_conservative_controller(est, **settings):
    w = FakeControlProcess()
    sup = Supervisor(ControlSettings(**settings), P, tick=1e-3, torque_limit=1.0, reference=Hold(0.0), jobs=w,
                     per_sample=est)
    assert sup.controller.kind == "conservative"
    return sup, w


NEAR = AxisParams(I1=P.I1 * 0.995, I2=P.I2 * 1.04, B=P.B * 0.98, K=P.K * 0.97)   # I2 4 % off: asks for a redesign


def test_the_first_design_is_the_configured_axiss_where_the_estimate_confirms_it_and_looks_measure_from_the_estimate():
    sup, w = _on_the_conservative_controller(_Estimate(NEAR))
    _looks(sup, S.trust_window)
    res = _answered_by_the_job(sup, w)
    assert w.requests[-1]["in_force"] is None and res["confirms"] == NEAR
    assert sup.controller.kind == "model" and sup.controller.model == P
    assert np.array_equal(sup.controller.gains, model_controller(P, 1e-3, S).gains)     # the fixed mode's design
    assert sup.stats.accepted == 1 and "the configured axis's design" in sup.stats.events[-1][2]
    sup.t += S.redesign_interval_s
    _looks(sup, 2 * S.trust_window)
    assert not sup._pending and len(w.requests) == 1     # NEAR's 4 % in I2 not asked about: measured from NEAR


def test_the_first_design_is_a_new_one_where_the_estimate_differs_or_keep_margin_is_0():
    for est, over in ((_Estimate(HEAVY), {}), (_Estimate(NEAR), {"keep_margin": 0.0})):
        sup, w = _on_the_conservative_controller(est, **over)
        _looks(sup, S.trust_window)
        res = _answered_by_the_job(sup, w)
        assert res["accepted"] and "confirms" not in res and sup.controller.model == est.p


def test_a_configured_axis_that_cannot_be_designed_for_leaves_the_estimates_own_design():
    sup, w = _on_the_conservative_controller(_Estimate(NEAR))
    _looks(sup, S.trust_window)
    sup.poll()
    req = {**w.requests[-1], "nominal": {"I1": -1.0, "I2": P.I2, "B": P.B, "K": P.K, "lead": P.lead}}
    res = J.redesign(req)
    assert res["accepted"] and "confirms" not in res and res["controller"].model == NEAR


def test_the_configured_axiss_design_is_made_once_for_the_requests_made_on_the_conservative_controller(monkeypatch):
    sup, w = _on_the_conservative_controller(_Estimate(NEAR))
    _looks(sup, S.trust_window)
    sup.poll()
    made = []
    real = J.model_controller
    monkeypatch.setattr(J, "model_controller", lambda p, *a, **k: made.append(p) or real(p, *a, **k))
    J._configured_design.cache_clear()
    req = w.requests[-1]
    first, again = J.redesign(req), J.redesign({**req, "settings": ControlSettings(**vars(req["settings"]))})
    assert first["confirms"] == again["confirms"] == NEAR and np.array_equal(first["controller"].gains,
                                                                             again["controller"].gains)
    assert made.count(P) == 1 and made.count(NEAR) == 2       # the estimate's own design: made for each request


def test_keep_design_needs_the_reference_error_the_error_norm_and_the_family_check_each():
    g = model_controller(P, 1e-3, S).gains

    def keep(p, **over):
        return J.keep_design(g, P, model_controller(p, 1e-3, S).gains, p, 1e-3, ControlSettings(**over), None)

    assert keep(SOFT) is not None and keep(SOFT)[0].ok
    light = AxisParams(I1=P.I1 * 1.03, I2=P.I2, B=P.B, K=P.K)          # the feedforward 2.3 % short
    assert reference_error(g, P, light) > S.min_change and keep(light) is None
    floppy = AxisParams(I1=P.I1, I2=P.I2, B=P.B, K=0.02 * P.K)        # the twist reference far off
    assert reference_error(g, P, floppy) > S.min_change and keep(floppy) is None
    assert keep(SOFT, keep_margin=0.0) is None
    ratio = error_norm(g, SOFT, 1e-3) / error_norm(model_controller(SOFT, 1e-3, S).gains, SOFT, 1e-3)
    assert 1.0 < ratio < 1.01
    assert keep(SOFT, keep_margin=(ratio - 1.0) / 2) is None          # the new design is better by more
    moved = AxisParams(I1=0.385 * P.I1, I2=3 * P.I2, B=P.B, K=0.7 * P.K)   # same I1 + I2, mode at ~320 Hz
    new = model_controller(moved, 1e-3, S).gains
    assert reference_error(g, P, moved) < S.min_change                 # only the family check refuses it
    assert error_norm(g, moved, 1e-3) < (1 + S.keep_margin) * error_norm(new, moved, 1e-3)
    assert not check_family(g, moved, 1e-3).ok and keep(moved) is None


def test_error_norm_is_the_impulse_responses_energy_and_inf_for_an_unstable_loop():
    g = model_controller(P, 1e-3, S).gains
    Az, Bz = sampled_model(P, 1e-3, 1)
    Acl = Az - Bz @ g.reshape(1, -1)
    x, energy = Az[:, 4].copy(), 0.0
    x[4:] = 0.0
    for _ in range(20000):
        energy += x[2] ** 2
        x = Acl @ x
    assert error_norm(g, P, 1e-3) == pytest.approx(math.sqrt(energy), rel=1e-8)
    assert error_norm(-g, P, 1e-3) == math.inf


def test_an_estimate_at_the_plausible_boxs_edge_is_neither_designed_for_nor_cycled_through_the_fallback():
    """I1 at 5 x nominal, the box's edge: trusted only 10 % inside the box, diverged only outside it."""
    for side in (1 - 1e-4, 1 + 1e-4):                          # just inside, just outside
        est = _Estimate(AxisParams(I1=5 * side * P.I1, I2=P.I2, B=P.B, K=P.K))
        sup, w = _supervisor(est)
        _looks(sup, 8)
        assert not sup.own_trust and not sup._pending and not w.requests, side
        why = sup.summary()["no_design"]                        # and the run says why, naming the setting
        assert why.startswith("the axis identifies as I1 = ") and "x the configured axis.I1" in why, why
    inside = _Estimate(AxisParams(I1=5 / (1 + A.PLAUSIBLE_MARGIN) * 0.99 * P.I1, I2=P.I2, B=P.B, K=P.K))
    sup, w = _supervisor(inside)
    _looks(sup, S.trust_window)
    assert sup.own_trust and sup._pending                       # 1 % inside the margin: designed for
    assert sup.summary()["no_design"] is None


def test_a_frequency_fit_agreeing_at_the_plausible_boxs_edge_gets_no_design_either():
    """trust = "cross-check": the per-sample estimate the fit agrees with, just inside the box's edge."""
    from types import SimpleNamespace

    edge = AxisParams(I1=5 * (1 - 1e-4) * P.I1, I2=P.I2, B=P.B, K=P.K)
    sup, w = _supervisor(_Estimate(edge), trust="cross-check")
    sup.offer(SimpleNamespace(params=edge), True)
    sup.poll()
    assert sup.stats.checks_agreed == 1 and not sup._pending and not w.requests

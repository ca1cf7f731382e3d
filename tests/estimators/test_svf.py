"""The per-sample state-variable-filter estimator (rt_ident.estimators.svf) and its cross-check."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.params import AxisParams
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.bench import estimator as svf_bench
from rt_ident.config import from_mapping, load
from rt_ident.control.adaptation import Supervisor
from rt_ident.control.job import ControlSettings
from rt_ident.control.reference import Hold
from rt_ident.errors import ConfigError
from rt_ident.estimators.svf import ACC_SSE, ACC_W, ACC_W2, SvfEstimator, SvfSettings, make_svf, regressor_noise

P = AxisParams(I1=2.7e-5, I2=8.3e-6, B=2.1e-3, K=110.0)
DT = 2.9481e-5


def _feed(est: SvfEstimator, th1, th2, tq, block: int = 34) -> np.ndarray:
    out = []
    for i in range(0, len(th1), block):
        est.update_block(th1[i:i + block], th2[i:i + block], tq[i:i + block])
        out.append(est.scaled)
    return np.array(out)


def _clean_block(seconds: float, p: AxisParams = P):
    sim = PlantSimulator(p, DT, sensors=SensorConfig(counts_per_rev=0, scale_resolution=0),
                         controller=HoldController(), seed=1)
    u = np.resize(schroeder_multisine(512, (1, 20), peak=0.3).signal, int(seconds / DT))
    return sim.step_block(u)


def test_svf_recovers_table1_from_clean_data_without_differentiating_angles():
    b = _clean_block(1.0)
    est = SvfEstimator(DT, P, SvfSettings())
    h = _feed(est, b.theta1, b.theta2, b.torque_meas)
    assert est.ready
    assert np.abs(h[-1] - 1.0).max() < 0.005, h[-1]


def test_svf_follows_a_plant_it_was_not_told_about():
    p = AxisParams(I1=P.I1 * 1.3, I2=P.I2 * 0.8, B=P.B * 1.2, K=P.K * 0.9)
    b = _clean_block(1.0, p)
    est = SvfEstimator(DT, P, SvfSettings())
    _feed(est, b.theta1, b.theta2, b.torque_meas)
    for k, v in est.values().items():
        assert v == pytest.approx(getattr(p, k), rel=0.01), k


def test_svf_intervals_are_none_before_data_then_the_information_matrix_formula_compiled():
    b = _clean_block(0.5)
    est = SvfEstimator(DT, P, SvfSettings())
    assert est.ci95() is None                       # no rows yet
    _feed(est, b.theta1, b.theta2, b.torque_meas)
    R, Sigma, acc, p, scale = est.evidence
    W, sse, W2 = acc[ACC_W], acc[ACC_SSE], acc[ACC_W2]
    cov = sse / (2 * W) * np.linalg.inv(R - W * Sigma) * (W2 / W) * W / max(W - 4, 1)
    half = 1.96 * np.sqrt(np.diag(cov)) * scale
    ci = est.ci95()
    for i, k in enumerate(("I1", "I2", "B", "K")):
        lo, hi = ci[k]
        assert (lo + hi) / 2 == pytest.approx(p[i] * scale[i], rel=1e-12), k
        assert (hi - lo) / 2 == pytest.approx(half[i], rel=1e-9), k
        assert 0 < (hi - lo) / 2 < 0.01 * getattr(P, k), k       # clean data: narrow


def test_svf_skips_non_finite_samples_and_counts_them():
    b = _clean_block(0.6)
    th1 = b.theta1.copy()
    th1[5000:5010] = np.nan
    tq = b.torque_meas.copy()
    tq[9000] = np.inf
    est = SvfEstimator(DT, P, SvfSettings())
    h = _feed(est, th1, b.theta2, tq)
    assert est.counters["rejected_non_finite"] == 11
    assert np.all(np.isfinite(h)) and np.abs(h[-1] - 1.0).max() < 0.05


def test_svf_freezes_instead_of_winding_up_when_the_excitation_stops():
    sim = PlantSimulator(P, DT, sensors=SensorConfig(torque_meas_noise=5e-4), controller=HoldController(), seed=2)
    est = SvfEstimator(DT, P, SvfSettings(q1=2 * math.pi / 2**17, q2=1e-7 / 7.96e-4))
    u = np.resize(schroeder_multisine(512, (1, 20), peak=0.3).signal, int(0.5 / DT))
    b = sim.step_block(u)
    _feed(est, b.theta1, b.theta2, b.torque_meas)
    before = est.scaled
    n = int(2.0 / DT)                                    # 2 s = 40 memory time constants of noise only
    b = sim.step_block(np.zeros(n))
    h = _feed(est, b.theta1, b.theta2, b.torque_meas)
    assert np.all(np.isfinite(h))
    assert np.abs(est.scaled - before).max() < 0.02     # frozen, not drifting on sensor noise
    assert est.counters["frozen_unexcited"] > 0.9 * n
    assert est.changes == 0                             # the excitation dying away is not a plant change


def test_svf_refuses_a_filter_too_close_to_the_sample_rate():
    with pytest.raises(ConfigError, match="too close to the sample rate"):
        SvfEstimator(5e-4, P, SvfSettings(filter_hz=800))
    est, why = make_svf(5e-4, P, filter_hz=800, memory_s=0.05, quanta=(0.0, 0.0))
    assert est is None and "sample rate" in why


def test_regressor_noise_is_zero_without_quantization_and_positive_semidefinite_with_it():
    assert np.all(regressor_noise(SvfSettings(), P, DT) == 0.0)
    S = regressor_noise(SvfSettings(q1=2 * math.pi / 2**17, q2=1e-7 / 7.96e-4), P, DT)
    assert np.allclose(S, S.T) and np.linalg.eigvalsh(S).min() >= -1e-12 * np.abs(S).max()
    assert S[0, 0] > 0 and S[1, 1] > 0


def _short(**over):
    base = load("sim-load-change.toml")
    d = base.model_dump(exclude={"source"})
    for k, v in over.items():
        sec, key = k.split(".")
        d[sec][key] = v
    return from_mapping(d, source=base.source)


def test_svf_bias_on_bench_like_closed_loop_data_is_small():
    # quantized encoder and scale, torque noise, the host's loop closed, moves: tight figures in rt-ident bench
    # estimator
    r = svf_bench.bias_trial(_short(), duration=3.0)
    assert r["stop"] is None
    for k, v in r["bias"].items():
        assert abs(v) < 0.03, (k, r)


def test_svf_tracks_a_20_percent_inertia_step_in_closed_loop():
    r = svf_bench.step_trial(_short(), "I2", at=1.5, after=0.8)
    assert r["stop"] is None
    assert r["settle_s"] < 0.4, r
    assert abs(r["error_at_0_2_s"]["I2"]) < 0.05, r


class FakeControlProcess:
    """The control process as the supervisor sees it: requests in, ``result`` out when set."""
    ready = True

    def __init__(self):
        self.requests = []
        self.result = None

    def submit(self, req):
        self.requests.append(req)
        return True

    def take(self):
        out, self.result = ([self.result] if self.result is not None else []), None
        return out

    def unpack(self, msgs):
        return msgs[-1] if msgs else None


def _offer(sup, ident, trusted=False):
    """A fit result offered on one tick; the redesign it decides on is asked for on the next (poll)."""
    sup.offer(ident, trusted)
    sup.poll()


def _answer(sup, w, result):
    """The control process answers: taken on one tick, unpickled and applied on the next."""
    w.result = result
    sup.poll()
    sup.poll()


def _supervisor(per_sample, trust: str = "cross-check"):
    """The cross-check tests run ``trust = "cross-check"`` (the fit's agreement is the gate); the
    per-sample trust has its own tests (tests/control/test_trust.py)."""
    w = FakeControlProcess()
    sup = Supervisor(ControlSettings(trust=trust), P, tick=1e-3, torque_limit=1.0, reference=Hold(0.0), jobs=w,
                     per_sample=per_sample)
    return sup, w


def _ident(p: AxisParams, trusted=False):
    return SimpleNamespace(params=p, ci95=None, trusted=trusted)


def _fake_svf(p: AxisParams):
    return SimpleNamespace(ready=True, params=p, ci95=lambda: None, values=lambda: {}, counters={}, changes=0,
                           frozen=0)


def test_redesign_follows_the_per_sample_estimate_only_when_the_frequency_fit_agrees():
    moved = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)
    sup, w = _supervisor(_fake_svf(moved))
    _offer(sup, _ident(AxisParams(I1=P.I1, I2=2.4 * P.I2, B=P.B, K=P.K), trusted=True), True)   # 25 % apart
    assert w.requests == [] and sup.stats.checks_disagreed == 1
    _offer(sup, _ident(AxisParams(I1=P.I1, I2=2.95 * P.I2, B=P.B, K=P.K)))   # within 5 %
    assert len(w.requests) == 1 and sup.stats.checks_agreed == 1
    assert w.requests[0]["params"]["I2"] == pytest.approx(3 * P.I2)      # the per-sample estimate


def test_a_diverging_frequency_fit_withholds_trust_but_does_not_trigger_a_fallback():
    sup, w = _supervisor(_fake_svf(P))
    _offer(sup, _ident(AxisParams(I1=P.I1, I2=1e-12, B=1e-9, K=1e-5)))
    assert w.requests == [] and sup.stats.fallbacks == 0


def test_a_finished_design_for_an_axis_that_has_since_changed_is_not_applied():
    # a design requested before a load change and finished after it is stale: applied, it can drive the
    # table hundreds of um off and into the fallback (docs/measurements.md, "Position control")
    from rt_ident.control.job import model_controller

    est = _fake_svf(P)
    sup, w = _supervisor(est)
    before = sup.controller
    design = model_controller(P, 1e-3, ControlSettings())
    sup._pending = True
    est.params = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)          # the axis changed meanwhile
    _answer(sup, w, {"accepted": True, "controller": design, "seq": 1})
    assert sup.controller is before and sup.stats.accepted == 0 and sup.stats.rejected == 1
    assert "stale" in sup.stats.reasons[0] and "I2" in sup.stats.reasons[0]
    sup._pending = True
    est.params = AxisParams(I1=P.I1, I2=1.01 * P.I2, B=P.B, K=P.K)       # unchanged (within 5 %): applied
    _answer(sup, w, {"accepted": True, "controller": design, "seq": 1})
    assert sup.controller.gains is design.gains and sup.stats.accepted == 1


def test_a_fallback_that_no_longer_suits_the_axis_is_replaced_and_the_held_design_applied_on_recovery():
    from rt_ident.control.job import model_controller, rigid_controller

    heavy = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)
    est = _fake_svf(heavy)
    sup, w = _supervisor(est)
    sup._fall_back(0.0, "test")
    assert sup.in_fallback and sup.controller is sup.conservative
    s = ControlSettings()
    design, fallback = model_controller(heavy, 1e-3, s), rigid_controller(heavy, 1e-3, s)
    sup._pending = True
    _answer(sup, w, {"accepted": True, "controller": design, "fallback": fallback, "fallback_reason": "why", "seq": 1})
    assert sup.conservative is fallback and sup.controller.gains is fallback.gains      # not the model design yet
    assert [e[1] for e in sup.stats.events[-2:]] == ["accepted", "fallback redesigned"]
    sup._watch(0.1, 0.1 * s.max_error_m)                 # back within the bound: the held design goes in
    assert not sup.in_fallback and sup.controller.gains is design.gains
    assert [e[1] for e in sup.stats.events[-2:]] == ["recovered", "applied"]


def test_a_tracking_error_fallback_goes_back_to_the_model_controller_that_still_fits_at_recovery():
    from rt_ident.control.job import model_controller

    est = _fake_svf(P)
    sup, w = _supervisor(est)
    design = model_controller(P, 1e-3, ControlSettings())
    sup.adopt(design)
    bound = sup.s.max_error_m
    sup._watch(0.0, 1.5 * bound)                           # the error passes the bound: fallback
    assert sup.in_fallback and sup.controller is sup.conservative
    sup._watch(0.05, 0.2 * bound)                          # recovered: the design still fits the axis
    assert sup.controller.gains is design.gains
    sup._watch(0.10, 1.5 * bound)
    est.params = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)   # meanwhile the axis changed: not again
    sup._watch(0.15, 0.2 * bound)
    assert not sup.in_fallback and sup.controller is sup.conservative


def test_the_summary_reports_each_redesign_request_its_cause_and_its_latency():
    # the adaptation latency after a load change is request -> answer; the summary carries it
    from rt_ident.control.job import model_controller

    moved = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)
    sup, w = _supervisor(_fake_svf(moved))
    sup.adopt(model_controller(P, 1e-3, ControlSettings()))
    sup.t = 2.0
    _offer(sup, _ident(AxisParams(I1=P.I1, I2=2.95 * P.I2, B=P.B, K=P.K)))
    assert len(w.requests) == 1
    design = model_controller(moved, 1e-3, ControlSettings())
    sup.t = 2.3
    _answer(sup, w, {"accepted": True, "controller": design, "cpu_s": 0.07})
    r = sup.summary()["redesigns"]
    assert r["requested"] == 1 and r["requested_for"] == {"I2": 1} and r["accepted"] == 1
    assert r["latency_s"]["max"] == pytest.approx(0.3) and r["worker_cpu_s"]["last"] == pytest.approx(0.07)


def test_a_small_move_of_b_alone_asks_for_no_redesign_but_the_same_move_of_i2_does():
    from rt_ident.control.job import model_controller

    for moved, asked in ((AxisParams(I1=P.I1, I2=P.I2, B=1.06 * P.B, K=P.K), False),    # B's scatter
                         (AxisParams(I1=P.I1, I2=1.06 * P.I2, B=P.B, K=P.K), True),
                         (AxisParams(I1=P.I1, I2=P.I2, B=1.2 * P.B, K=P.K), True)):
        sup, w = _supervisor(_fake_svf(moved))
        sup.adopt(model_controller(P, 1e-3, ControlSettings()))
        _offer(sup, _ident(moved))
        assert (len(w.requests) == 1) is asked, moved


def test_a_redesign_is_asked_for_taken_and_adopted_on_three_ticks_not_one():
    # each step is a few hundred microseconds of Python: one tick holding them all passed its period
    from rt_ident.control.job import model_controller

    moved = AxisParams(I1=P.I1, I2=3 * P.I2, B=P.B, K=P.K)
    sup, w = _supervisor(_fake_svf(moved))
    sup.adopt(model_controller(P, 1e-3, ControlSettings()))
    before = sup.controller
    sup.offer(_ident(AxisParams(I1=P.I1, I2=2.95 * P.I2, B=P.B, K=P.K)), False)
    assert w.requests == [] and sup._pending                          # decided, not yet asked
    sup.poll()
    assert len(w.requests) == 1                                       # asked on the next tick
    w.result = {"accepted": True, "controller": model_controller(moved, 1e-3, ControlSettings()), "seq": 1}
    sup.poll()
    assert sup.controller is before and w.result is None              # taken, not yet applied
    sup.poll()
    assert sup.controller is not before and sup.stats.accepted == 1 and not sup._pending

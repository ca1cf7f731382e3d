"""Controller design on the sampled two-inertia model: margins, the family check, the bumpless switch."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.control.adaptation import ControlSettings, redesign
from rt_ident.control.design import (check_family, design_lqr, design_rigid, loop_margins, plant_family,
                                     sampled_model)
from rt_ident.control.law import Controller, StateFeedback
from rt_ident.errors import ConfigError

T = 1e-3
P = thomson_x()


def _scaled(p: AxisParams, **f: float) -> AxisParams:
    return AxisParams(**{k: getattr(p, k) * f.get(k, 1.0) for k in ("I1", "I2", "B", "K")}, lead=p.lead)


def test_sampled_model_aliases_the_662_hz_mode_to_338_hz_at_1_khz():
    Az, _ = sampled_model(P, T)
    z = np.linalg.eigvals(Az[:4, :4])
    flex = z[np.abs(z - 1.0) > 1e-6]
    f = np.abs(np.angle(flex)) / (2 * np.pi * T)
    assert np.allclose(f, 1000 - 662.5, atol=2.0), f
    assert np.allclose(np.abs(flex), 0.848, atol=0.002)


def test_model_design_for_table1_meets_6db_and_40deg_over_its_family():
    G = design_lqr(P, T, 20.0)
    check = check_family(G, P, T, gm_db=6.0, pm_deg=40.0)
    assert check.ok, check.reason
    assert check.plants == 9
    assert check.worst.pm_deg >= 40.0 and check.worst.radius < 1.0


def test_margin_check_rejects_a_destabilizing_design():
    G = design_lqr(P, T, 20.0)
    G[1] = -G[1]                                         # negative damping on the motor velocity
    m = loop_margins(G, P, T)
    assert not m.stable
    check = check_family(G, P, T)
    assert not check.ok and check.reason.startswith("unstable on the estimate")


def test_margin_check_rejects_a_design_too_fast_for_its_phase_margin():
    check = check_family(design_lqr(P, T, 60.0, effort=0.1), P, T, pm_deg=40.0)
    assert not check.ok and "phase margin" in check.reason


def test_family_includes_each_parameter_scaled_and_the_ci95_corners():
    ci = {k: (getattr(P, k) * 0.9, getattr(P, k) * 1.1) for k in ("I1", "I2", "B", "K")}
    fam = plant_family(P, (0.7, 1.3), ci)
    assert len(fam) == 1 + 8 + 16
    assert any(abs(q.I2 / P.I2 - 1.3) < 1e-12 and q.K == P.K for q in fam)


def test_conservative_rigid_body_design_stays_stable_for_every_half_to_double_corner():
    G = design_rigid(P.I1 + P.I2, T, 10.0)
    for f in itertools.product((0.5, 2.0), repeat=4):
        q = _scaled(P, I1=f[0], I2=f[1], B=f[2], K=f[3])
        assert loop_margins(G, q, T).stable, f


def test_nominal_model_design_stays_stable_for_every_half_to_double_corner():
    G = design_lqr(P, T, 20.0)
    for f in itertools.product((0.5, 2.0), repeat=4):
        assert loop_margins(G, _scaled(P, I1=f[0], I2=f[1], B=f[2], K=f[3]), T).stable, f


def test_bad_bandwidth_is_a_config_error_naming_the_field():
    with pytest.raises(ConfigError, match="control.bandwidth_hz"):
        design_lqr(P, T, 400.0)


def test_redesign_job_accepts_the_true_plant_and_rejects_an_impossible_margin():
    req = {"params": {"I1": P.I1, "I2": 3 * P.I2, "B": P.B, "K": P.K, "lead": P.lead}, "ci95": None, "tick": T,
           "settings": ControlSettings(), "seq": 1}
    ok = redesign(req)
    assert ok["accepted"] and ok["controller"].model.I2 == pytest.approx(3 * P.I2)
    bad = redesign({**req, "settings": ControlSettings(phase_margin_deg=89.0)})
    assert not bad["accepted"] and "phase margin" in bad["reason"]


def _run_law(law: StateFeedback, n: int, x_ref: float = 1e-5) -> list[float]:
    """Feed the law a slowly moving state (the plant's response is not the point here)."""
    out = []
    for k in range(n):
        th = (x_ref / P.lead) * (1 - np.exp(-k / 50))
        out.append(law.step(th * 1.01, 0.01, th, 0.01, x_ref, 0.0, 0.0, 0.0, P.lead))
    return out


def test_switch_is_bumpless_the_torque_does_not_step():
    a = Controller(design_rigid(P.I1 + P.I2, T, 10.0), P, "conservative", 10.0)
    b = Controller(design_lqr(_scaled(P, I2=3.0), T, 20.0), _scaled(P, I2=3.0), "model", 20.0)
    law = StateFeedback(a, tick=T, torque_limit=1.0)
    u = _run_law(law, 200)
    th = (1e-5 / P.lead) * (1 - np.exp(-200 / 50))
    state = (th * 1.01, 0.01, th, 0.01, 1e-5, 0.0, 0.0)
    before = law.feedback_torque(*state, P.lead)
    step = law.switch(b, *state, P.lead)
    after = law.feedback_torque(*state, P.lead)
    assert abs(after - before) < 1e-12 * max(1.0, abs(before))
    assert abs(step) < 1e-12
    # the same swap without re-seeding the integral would have stepped the torque
    naive = StateFeedback(a, tick=T, torque_limit=1.0)
    _run_law(naive, 200)
    naive._g = np.array(b.gains)
    assert abs(naive.feedback_torque(*state, P.lead) - before) > 1e-4
    assert abs(u[-1]) < 1.0

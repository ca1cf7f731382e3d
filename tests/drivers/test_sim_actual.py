"""The sim backend as a device that differs from what the host is told ([plant.actual]), and the host's
polarity settings that undo a sign difference."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim import SimBackend
from rt_ident.errors import ConfigError

LEAD = 7.96e-4
BASE = {"paced": False, "samples_per_read": 340, "torque_meas_noise": 0.0, "seed": 0}


def _pulse(**opts: object) -> tuple[float, float, float, float]:
    """(theta1, theta2, torque_meas mean, physical x) after 10 ms of +0.05 N m from rest."""
    with SimBackend({**BASE, **opts}) as b:
        b.activate()
        b.write(0.05)
        blk = b.read()
        x = b.true_params.lead * float(b.plant.state[2])
        return float(blk.theta1[-1]), float(blk.theta2[-1]), float(np.mean(blk.torque_meas[10:])), x


def test_the_sim_told_the_truth_moves_theta1_and_theta2_together_positive() -> None:
    th1, th2, tq, x = _pulse()
    assert th1 > 0.05 and th2 > 0.05 and th2 / th1 == pytest.approx(1.0, rel=0.05)
    assert tq == pytest.approx(0.05, rel=1e-6) and x == pytest.approx(LEAD * th2, rel=0.02)


@pytest.mark.parametrize(("actual", "f1", "f2", "fx"), [
    ({"torque_sign": -1}, -1.0, -1.0, -1.0),          # the motor turns against the torque: both read reversed
    ({"motor_encoder_sign": -1}, -1.0, 1.0, 1.0),
    ({"scale_sign": -1}, 1.0, -1.0, 1.0),
    ({"counts_per_rev": 2**16}, 0.5, 1.0, 1.0),      # a 2^16 encoder counted as 2^17: theta1 reads half
    ({"scale_resolution": 2e-7}, 1.0, 0.5, 1.0),     # 0.2 um counts read as 0.1 um: x reads half
    ({"lead": 2 * LEAD}, 1.0, 2.0, 2.0),             # the screw moves the table twice as far per radian
    ({"torque_scale": 10.0}, 10.0, 10.0, 10.0),      # ten times the torque: ten times the motion
])
def test_a_device_that_differs_reads_as_its_truth_implies(actual: dict, f1: float, f2: float, fx: float) -> None:
    th1, th2, _, x = _pulse()
    a1, a2, tq, ax = _pulse(actual=actual)
    assert a1 == pytest.approx(f1 * th1, rel=0.02)
    assert a2 == pytest.approx(f2 * th2, rel=0.02)
    assert ax == pytest.approx(fx * x, rel=0.02)
    assert tq == pytest.approx(0.05, rel=1e-6)       # the device reports the torque it believes it applies


@pytest.mark.parametrize("key", ["torque_sign", "motor_encoder_sign", "scale_sign"])
def test_the_hosts_matching_sign_undoes_the_devices(key: str) -> None:
    th1, th2, _, _ = _pulse()
    a1, a2, tq, _ = _pulse(actual={key: -1}, **{key: -1})
    assert (a1, a2) == pytest.approx((th1, th2), rel=1e-9)
    assert tq == pytest.approx(0.05, rel=1e-6)


def test_a_drive_rating_for_the_sim_is_refused_naming_torque_scale() -> None:
    with pytest.raises(ConfigError, match=r"plant\.actual\.rated_torque.*torque_scale"):
        SimBackend({**BASE, "actual": {"rated_torque": 6.4}})


def test_a_sign_other_than_plus_or_minus_one_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"backend\.torque_sign"):
        SimBackend({**BASE, "torque_sign": 0})


@pytest.mark.parametrize("key", ["torque_sign", "motor_encoder_sign", "scale_sign"])
def test_a_hosts_sign_describes_the_device_when_plant_actual_leaves_it_out(key: str) -> None:
    th1, th2, _, _ = _pulse()
    assert _pulse(**{key: -1})[:2] == pytest.approx((th1, th2), rel=1e-9)


@pytest.mark.parametrize("key", ["torque_sign", "motor_encoder_sign", "scale_sign"])
def test_a_host_sign_the_device_does_not_have_reverses_what_the_host_sees(key: str) -> None:
    th1, th2, _, _ = _pulse()
    a1, a2, _, _ = _pulse(actual={key: 1}, **{key: -1})
    f1 = -1.0 if key in ("torque_sign", "motor_encoder_sign") else 1.0
    f2 = -1.0 if key in ("torque_sign", "scale_sign") else 1.0
    assert (a1, a2) == pytest.approx((f1 * th1, f2 * th2), rel=0.02)

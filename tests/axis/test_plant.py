"""Tests of rt_ident.axis.plant: determinism, sensors, saturation, hold loop, travel, reference path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rt_ident.axis.integrators import ZeroOrderHold
from rt_ident.axis.model import state_space
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import (
    DEFAULT_KD,
    DEFAULT_KP,
    HoldController,
    PlantBlock,
    PlantSimulator,
    SensorConfig,
)
from rt_ident.errors import ConfigError, DataError

P = thomson_x()
DT1 = 2.9481e-5   # Table 2 case 1
DT2 = 1.0761e-4   # Table 2 case 2
NOISY = SensorConfig(angle_noise=2e-6, torque_meas_noise=1e-3, torque_process_noise=5e-4)


def _multisine(n: int, dt: float, amp: float = 0.05, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    f = np.arange(20.0, 2000.0, 20.0)
    ph = rng.uniform(0, 2 * np.pi, f.size)
    return amp * np.sin(2 * np.pi * np.outer(t, f) + ph).sum(axis=1) / np.sqrt(f.size)


def _fields(b: PlantBlock) -> list[np.ndarray]:
    return [b.theta1, b.theta2, b.torque_cmd, b.torque_applied, b.torque_meas, b.true_states]


def _concat(blocks: list[PlantBlock]) -> list[np.ndarray]:
    return [np.concatenate(parts) for parts in zip(*(_fields(b) for b in blocks))]


@pytest.mark.parametrize("integrator", ["zoh", "newmark"])
def test_block_split_does_not_change_results_bit_for_bit(integrator: str) -> None:
    u = _multisine(1000, DT1)
    kw = dict(sensors=NOISY, controller=HoldController(), torque_limit=0.3, integrator=integrator, seed=7)
    one = PlantSimulator(P, DT1, **kw)
    ten = PlantSimulator(P, DT1, **kw)
    whole = _fields(one.step_block(u))
    split = _concat([ten.step_block(u[i:i + 100]) for i in range(0, 1000, 100)])
    for a, b in zip(whole, split):
        assert np.array_equal(a, b)
    assert np.array_equal(one.state, ten.state)
    assert one.sample_index == ten.sample_index == 1000


def test_compiled_kernel_matches_interpreted_reference() -> None:
    u = _multisine(400, DT1)
    kw = dict(sensors=NOISY, controller=HoldController(), torque_limit=0.3, seed=3)
    fast = PlantSimulator(P, DT1, **kw)
    ref = PlantSimulator(P, DT1, **kw)
    for i in range(0, 400, 37):
        bf, br = fast.step_block(u[i:i + 37]), ref.step_block(u[i:i + 37], compiled=False)
        for a, b in zip(_fields(bf), _fields(br)):
            assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.max(np.abs(b)))


def test_seed_makes_noise_reproducible_and_distinct() -> None:
    u = np.zeros(200)
    a = PlantSimulator(P, DT1, sensors=NOISY, seed=1).step_block(u)
    b = PlantSimulator(P, DT1, sensors=NOISY, seed=1).step_block(u)
    c = PlantSimulator(P, DT1, sensors=NOISY, seed=2).step_block(u)
    assert np.array_equal(a.torque_meas, b.torque_meas)
    assert not np.array_equal(a.torque_meas, c.torque_meas)


def test_ideal_open_loop_plant_equals_zoh_integrator() -> None:
    u = _multisine(500, DT1)
    x0 = np.array([1e-3, 0.5, -2e-3, -1.0])
    sim = PlantSimulator(P, DT1, sensors=SensorConfig(counts_per_rev=0, scale_resolution=0.0), x0=x0)
    blk = sim.step_block(u)
    ref = ZeroOrderHold().simulate(P, u, DT1, x0).states()
    assert np.allclose(blk.true_states, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))
    assert np.array_equal(blk.theta1, blk.true_states[:, 0])
    assert np.array_equal(blk.theta2, blk.true_states[:, 2])
    assert np.array_equal(blk.torque_applied, u) and np.array_equal(blk.torque_meas, u)


def test_newmark_plant_is_trapezoidal_rule_with_held_torque() -> None:
    A, b = state_space(P)
    u = _multisine(300, DT1)
    sim = PlantSimulator(P, DT1, sensors=SensorConfig(0, 0.0), integrator="newmark")
    blk = sim.step_block(u)
    L = np.eye(4) - 0.5 * DT1 * A
    x, ref = np.zeros(4), []
    for uk in u:
        ref.append(x)
        x = np.linalg.solve(L, (np.eye(4) + 0.5 * DT1 * A) @ x + DT1 * b * uk)
    ref = np.array(ref)
    assert np.allclose(blk.true_states, ref, rtol=1e-9, atol=1e-10 * np.max(np.abs(ref)))


def test_quantization_steps_equal_encoder_and_scale_resolution() -> None:
    sensors = SensorConfig(counts_per_rev=2**12, scale_resolution=1e-6)
    q1 = 2 * math.pi / 2**12
    q2 = 1e-6 / P.lead
    assert sensors.theta1_quantum == pytest.approx(q1) and sensors.theta2_quantum(P.lead) == pytest.approx(q2)
    sim = PlantSimulator(P, DT2, sensors=sensors)
    blk = sim.step_block(np.full(3000, 1e-3))  # slow parabola: ~950 counts, < 1 count per sample
    true1, true2 = blk.true_states[:, 0], blk.true_states[:, 2]
    steps1 = np.unique(np.round(np.diff(blk.theta1) / q1, 9))
    steps2 = np.unique(np.round(np.diff(blk.theta2) / q2, 9))
    assert set(steps1) == {0.0, 1.0} and blk.theta1[-1] / q1 > 500
    assert set(steps2) == {0.0, 1.0} and blk.theta2[-1] / q2 > 500
    assert np.allclose(blk.theta1 / q1, np.round(blk.theta1 / q1), atol=1e-6)
    assert np.allclose(blk.theta2 / q2, np.round(blk.theta2 / q2), atol=1e-6)
    assert np.max(np.abs(blk.theta1 - true1)) <= 0.5 * q1 * (1 + 1e-9)
    assert np.max(np.abs(blk.theta2 - true2)) <= 0.5 * q2 * (1 + 1e-9)


def test_saturation_limits_applied_torque() -> None:
    limit = 0.05
    u = 4 * _multisine(2000, DT1)
    blk = PlantSimulator(P, DT1, controller=HoldController(), torque_limit=limit).step_block(u)
    assert np.max(np.abs(blk.torque_applied)) <= limit
    assert np.sum(np.abs(blk.torque_applied) == limit) > 100
    inside = np.abs(u) < 0.2 * limit
    assert np.any(np.abs(blk.torque_applied[inside]) < limit)


def test_noise_levels_match_configuration() -> None:
    n = 40000
    sens = SensorConfig(counts_per_rev=0, scale_resolution=0.0, angle_noise=1e-5,
                        torque_meas_noise=2e-3, torque_process_noise=1e-3)
    blk = PlantSimulator(P, DT2, sensors=sens, seed=5).step_block(np.zeros(n))
    assert np.std(blk.torque_meas - blk.torque_applied) == pytest.approx(2e-3, rel=0.03)
    assert np.std(blk.torque_applied - blk.torque_cmd) == pytest.approx(1e-3, rel=0.03)
    assert np.std(blk.theta1 - blk.true_states[:, 0]) == pytest.approx(1e-5, rel=0.03)
    assert np.std(blk.theta2 - blk.true_states[:, 2]) == pytest.approx(1e-5, rel=0.03)


def test_hold_controller_keeps_table_bounded_while_open_loop_drifts() -> None:
    n = int(0.5 / DT2)
    u = _multisine(n, DT2)  # zero-mean multisine
    sens = SensorConfig(torque_process_noise=1e-3)
    x_open = PlantSimulator(P, DT2, sensors=sens).step_block(u).true_states[:, 2] * P.lead
    x_hold = PlantSimulator(P, DT2, sensors=sens, controller=HoldController()).step_block(u).true_states[:, 2] * P.lead
    q = n // 4
    # open loop: the rigid body walks away
    assert np.max(np.abs(x_open[-q:])) > 3 * np.max(np.abs(x_open[:q]))
    assert np.max(np.abs(x_open[-q:])) > 1e-4
    # closed loop: the table vibrates about the reference and stays there
    assert np.max(np.abs(x_hold[-q:])) < 1.5 * np.max(np.abs(x_hold[:q]))
    assert np.max(np.abs(x_hold)) < 2e-5
    assert abs(np.mean(x_hold[-q:])) < 1e-6


def test_default_hold_gains_give_30hz_well_damped_loop() -> None:
    assert DEFAULT_KP == pytest.approx((P.I1 + P.I2) * (2 * math.pi * 30) ** 2)
    assert DEFAULT_KD == pytest.approx(math.sqrt(2) * (P.I1 + P.I2) * 2 * math.pi * 30)
    for dt in (DT1, DT2):
        sim = PlantSimulator(P, dt, controller=HoldController())
        lam = np.linalg.eigvals(sim.closed_loop_matrix()).astype(complex)
        assert np.max(np.abs(lam)) < 1.0
        s = np.log(lam[np.abs(lam) > 0]) / dt
        hold = [x for x in s if 2 * math.pi * 20 < abs(x) < 2 * math.pi * 40 and x.imag > 0]
        assert len(hold) == 1
        assert abs(hold[0]) / (2 * math.pi) == pytest.approx(30.0, rel=0.05)
        assert 0.6 < -hold[0].real / abs(hold[0]) < 0.8
    open_loop = PlantSimulator(P, DT1).closed_loop_matrix()
    assert np.max(np.abs(np.linalg.eigvals(open_loop))) == pytest.approx(1.0, abs=1e-6)


def test_hold_controller_tracks_nonzero_reference() -> None:
    ref = 0.5
    sim = PlantSimulator(P, DT2, controller=HoldController(reference=ref))
    blk = sim.step_block(np.zeros(int(0.2 / DT2)))
    assert blk.true_states[-1, 0] == pytest.approx(ref, abs=2 * sim.sensors.theta1_quantum)
    assert blk.true_states[-1, 2] == pytest.approx(ref, abs=1e-4)


def test_travel_window_sets_flag_and_keeps_simulating() -> None:
    sim = PlantSimulator(P, DT2, travel=(-1e-3, 1e-3))
    sim.step_block(np.zeros(100))
    assert not sim.travel_exceeded
    blk = sim.step_block(np.full(2000, 0.05))
    x = blk.true_states[:, 2] * P.lead
    assert np.any(x > 1e-3) and sim.travel_exceeded
    assert sim.sample_index == 2100
    sim.step_block(np.full(10, -0.05))
    assert sim.travel_exceeded  # sticky


def test_rejected_block_leaves_plant_untouched() -> None:
    sim = PlantSimulator(P, DT1, sensors=NOISY, seed=4)
    sim.step_block(np.full(10, 0.01))
    before = sim.state
    with pytest.raises(DataError, match="sample 2"):
        sim.step_block(np.array([0.0, 0.0, np.inf]))
    with pytest.raises(DataError, match="1-D"):
        sim.step_block(np.zeros((2, 2)))
    assert np.array_equal(sim.state, before) and sim.sample_index == 10
    twin = PlantSimulator(P, DT1, sensors=NOISY, seed=4)
    twin.step_block(np.full(10, 0.01))
    assert np.array_equal(sim.step_block(np.ones(5)).torque_meas, twin.step_block(np.ones(5)).torque_meas)
    assert len(sim.step_block(np.zeros(0))) == 0


@pytest.mark.parametrize("kw, field", [
    ({"dt": 0.0}, "dt"), ({"integrator": "rk4"}, "integrator"), ({"travel": (1.0, -1.0)}, "travel"),
    ({"torque_limit": 0.0}, "torque_limit"), ({"torque_limit": float("nan")}, "torque_limit"),
    ({"x0": np.zeros(2)}, "x0"), ({"seed": 1.5}, "seed"), ({"controller": "pd"}, "controller"),
])
def test_simulator_rejects_bad_configuration(kw: dict, field: str) -> None:
    args = {"dt": DT1, **kw}
    dt = args.pop("dt")
    with pytest.raises(ConfigError) as info:
        PlantSimulator(P, dt, **args)
    assert info.value.field == field


@pytest.mark.parametrize("cls, kw, field", [
    (SensorConfig, {"counts_per_rev": -1}, "counts_per_rev"),
    (SensorConfig, {"counts_per_rev": 1.5}, "counts_per_rev"),
    (SensorConfig, {"scale_resolution": -1e-7}, "scale_resolution"),
    (SensorConfig, {"angle_noise": float("nan")}, "angle_noise"),
    (HoldController, {"kp": -1.0}, "kp"),
    (HoldController, {"velocity_filter_hz": 0.0}, "velocity_filter_hz"),
    (HoldController, {"reference": float("inf")}, "reference"),
])
def test_sensor_and_controller_configs_are_validated(cls: type, kw: dict, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        cls(**kw)
    assert info.value.field == field


def test_the_compiled_finite_check_finds_the_first_bad_sample_in_any_of_three_arrays():
    from rt_ident.axis.kernels import first_non_finite3, first_non_finite3_py

    a, b, c = np.zeros(50), np.ones(50), np.full(50, 2.0)
    for f in (first_non_finite3, first_non_finite3_py):
        assert f(a, b, c) == -1 and f(a[:0], b[:0], c[:0]) == -1
    for arr, bad, at in ((a, np.nan, 31), (b, np.inf, 7), (c, -np.inf, 49)):
        x = [a.copy(), b.copy(), c.copy()]
        x[[id(a), id(b), id(c)].index(id(arr))][at] = bad
        x[2][40] = np.nan                                   # a later bad sample does not hide the first
        want = min(at, 40)
        assert first_non_finite3(*x) == first_non_finite3_py(*x) == want

"""Tests for drivers.sim.SimBackend: lifecycle, per-sample torque plans, pacing, travel trip, config errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

import drivers
from drivers.base import State
from drivers.errors import BackendStateError, TravelLimitTrip
from drivers.sim import PAPER_DT, SimBackend
from rt_ident.axis.params import thomson_x
from rt_ident.errors import ConfigError

FREE = {"paced": False, "position_hold": False, "samples_per_read": 10}


class FakeClock:
    def __init__(self, t: float = 10.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _cmd_by_seq(blocks: list) -> dict[int, float]:
    return {int(s): float(c) for b in blocks for s, c in zip(b.seq, b.torque_cmd)}


def test_context_manager_ends_with_zero_torque_and_disabled() -> None:
    b = SimBackend({"paced": False})
    with b:
        b.activate()
        b.write(0.2)
        b.read()
        assert b.drive_enabled and b.applied_torque != 0.0
    assert b.state is State.CLOSED
    assert not b.drive_enabled and b.applied_torque == 0.0 and b.last_torque == 0.0
    assert b.plant.controller is None            # hold loop off after the stop


def test_context_manager_stops_when_the_body_raises() -> None:
    b = SimBackend({"paced": False})
    with pytest.raises(RuntimeError, match="boom"):
        with b:
            b.activate()
            b.write(0.3)
            b.read()
            raise RuntimeError("boom")
    assert b.state is State.CLOSED and not b.drive_enabled and b.applied_torque == 0.0
    assert b.stop_cause == "RuntimeError"


def test_plan_is_applied_at_exact_sequence_numbers() -> None:
    with SimBackend(FREE) as b:
        b.activate()
        blocks = [b.read()]                      # seq 0..9 at hold 0
        plan = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
        b.write(plan, start_seq=13)
        blocks += [b.read(), b.read()]           # seq 10..29
        cmd = _cmd_by_seq(blocks)
        assert [cmd[s] for s in range(13)] == [0.0] * 13
        assert [cmd[s] for s in range(13, 18)] == plan.tolist()
        assert all(cmd[s] == 0.5 for s in range(18, 30))   # the last value holds
        # a newer plan replaces the rest of an older one; a gap holds the older plan's last value
        b.write(np.full(10, -0.1), start_seq=35)
        b.write(np.array([0.7, 0.8]), start_seq=40)
        b.write(np.array([0.9]), start_seq=45)
        blocks += [b.read(), b.read()]           # seq 30..49
        cmd = _cmd_by_seq(blocks)
        assert [cmd[s] for s in range(30, 35)] == [0.5] * 5
        assert [cmd[s] for s in range(35, 40)] == [-0.1] * 5
        assert [cmd[s] for s in (40, 41, 42, 43, 44, 45, 46)] == [0.7, 0.8, 0.8, 0.8, 0.8, 0.9, 0.9]
        # a plan partly in the past: the late values are counted and dropped, the rest applied
        b.write(np.array([1.0, 0.25, 0.35]), start_seq=48)
        blk = b.read()                           # seq 50..59
        assert b.late_plan_samples == 2
        assert blk.seq[0] == 50 and blk.torque_cmd[0] == 0.35 and np.all(blk.torque_cmd == 0.35)
        # a hold replaces any pending plan
        b.write(np.full(5, 0.6), start_seq=62)
        b.write(-0.2)
        assert np.all(b.read().torque_cmd == -0.2)
        # without hold loop or noise the drive reports exactly the command
        np.testing.assert_array_equal(blk.torque_meas, blk.torque_cmd)


def test_free_running_is_deterministic_and_timestamps_are_the_device_clock() -> None:
    cfg = {"paced": False, "angle_noise": 1e-5, "torque_meas_noise": 1e-3, "seed": 4}

    def run(config: dict) -> list:
        with SimBackend(config) as b:
            b.activate()
            b.write(0.05)
            return [b.read() for _ in range(5)]

    a, c = run(cfg), run(cfg)
    n = round(1e-3 / PAPER_DT)
    assert n == 34 and all(len(x) == n for x in a)
    for x, y in zip(a, c):
        for f in ("t", "seq", "theta1", "theta2", "torque_cmd", "torque_meas"):
            np.testing.assert_array_equal(getattr(x, f), getattr(y, f))
    seq = np.concatenate([x.seq for x in a])
    np.testing.assert_array_equal(seq, np.arange(5 * n))
    np.testing.assert_array_equal(np.concatenate([x.t for x in a]), seq * PAPER_DT)
    other = run({**cfg, "seed": 5})
    assert not np.array_equal(other[-1].torque_meas, a[-1].torque_meas)


def test_paced_mode_produces_floor_elapsed_over_dt_samples() -> None:
    clk = FakeClock(10.0)
    b = SimBackend({"paced": True}, clock=clk)
    with b:
        b.activate()
        assert len(b.read()) == 0                # no time has passed
        total = 0
        for step in (1e-3, 2.5e-3, 0.0, 7e-6, 1e-3, 40e-3):
            clk.t += step
            blk = b.read()
            if len(blk):
                assert blk.seq[0] == total       # contiguous, nothing lost
            total += len(blk)
            assert total == math.floor((clk.t - 10.0) / PAPER_DT)
        assert b.samples_produced == total


def test_leaving_travel_stops_torque_and_raises_travel_limit_trip() -> None:
    b = SimBackend({**FREE, "travel": [-1e-3, 1e-3], "samples_per_read": 34})
    with b:
        b.activate()
        b.write(1.0)                             # pushes the free table: ~9 ms to 1 mm
        with pytest.raises(TravelLimitTrip):
            for _ in range(100):
                b.read()
        assert not b.drive_enabled and b.applied_torque == 0.0
        assert b.trip_block is not None and b.trip_block.seq[-1] == b.samples_produced - 1
        with pytest.raises(TravelLimitTrip):
            b.read()
        with pytest.raises(TravelLimitTrip):
            b.write(0.1)
        assert b.samples_produced < 100 * 34
        x = thomson_x().lead * b.plant.state[2]
        assert abs(x) > 1e-3
    assert b.state is State.CLOSED


def test_travel_trip_cause_reaches_the_context_manager() -> None:
    b = SimBackend({**FREE, "travel": [-1e-3, 1e-3], "samples_per_read": 340})
    with pytest.raises(TravelLimitTrip):
        with b:
            b.activate()
            b.write(1.0)
            for _ in range(10):
                b.read()
    assert b.stop_cause == "travel-limit"


def test_position_hold_loop_acts_on_the_reported_torque() -> None:
    with SimBackend({"paced": False, "kp": 2.0, "position_hold": True}) as b:
        b.activate()
        b.write(0.05)
        blocks = [b.read() for _ in range(300)]   # 0.3 s
        last = blocks[-1]
        assert np.all(last.torque_cmd == 0.05)
        # the hold loop balances the command: reported torque ~ 0, motor angle ~ 0.05 / kp
        assert abs(last.torque_meas[-1]) < 5e-3
        assert last.theta1[-1] == pytest.approx(0.05 / 2.0, rel=0.05)


def test_torque_mode_holds_nothing_by_default_so_a_constant_torque_accelerates_the_axis() -> None:
    with SimBackend({"paced": False}) as b:
        b.activate()
        b.write(0.001)
        blocks = [b.read() for _ in range(100)]   # 0.1 s
        th = np.concatenate([blk.theta1 for blk in blocks])
        w = np.diff(th)
        # no hold loop balances it: the reported torque is the command and the axis keeps speeding up
        assert blocks[-1].torque_meas[-1] == pytest.approx(0.001, abs=5e-5)
        mid = w[len(w) // 2 - 50:len(w) // 2 + 50].mean()
        assert mid > 0 and w[-100:].mean() > 1.5 * mid      # constant acceleration: twice the speed at 2t


def test_lifecycle_errors() -> None:
    b = SimBackend(FREE)
    with pytest.raises(BackendStateError):
        b.activate()                             # before open
    b.open()
    with pytest.raises(BackendStateError):
        b.read()                                 # before activate
    with pytest.raises(BackendStateError):
        b.write(0.1)
    b.activate()
    assert len(b.read()) == 10
    b.safe_stop()
    with pytest.raises(BackendStateError):
        b.read()                                 # after stop
    b.close()
    b.close()                                    # idempotent


@pytest.mark.parametrize(
    ("config", "field"),
    [
        ({"sample_period": -1.0}, "backend.sample_period"),
        ({"integrator": "euler"}, "backend.integrator"),
        ({"sampel_period": 1e-4}, "backend.sampel_period"),
        ({"torque_limit": 0}, "backend.torque_limit"),
        ({"travel": [0.05, -0.05]}, "backend.travel"),
        ({"counts_per_rev": -3}, "backend.counts_per_rev"),
        ({"axis": {"I1": -1.0, "I2": 8.3e-6, "B": 2.1e-3, "K": 110.0}}, "backend.axis.I1"),
        ({"axis": {"I1": 2.7e-5, "I2": 8.3e-6, "B": 2.1e-3}}, "backend.axis.K"),
    ],
)
def test_config_errors_name_the_field(config: dict, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        SimBackend(config)
    assert info.value.field == field


def test_registry_builds_sim_backend_with_axis_and_defaults() -> None:
    axis = {"I1": 3e-5, "I2": 9e-6, "B": 2e-3, "K": 120.0, "lead": 8e-4}
    b = drivers.make_backend("sim", {"axis": axis, "name": "sim"})
    assert isinstance(b, SimBackend)
    assert b.true_params.I1 == 3e-5 and b.true_params.lead == 8e-4
    assert b.sample_period == PAPER_DT and b.torque_limit == 1.0 and b.has_measured_torque
    assert SimBackend().true_params == thomson_x()
    assert SimBackend({"has_measured_torque": False, "paced": False}).has_measured_torque is False


def test_the_plan_check_refuses_nan_and_clamps_only_values_beyond_the_limit():
    from drivers.errors import DriverError
    from drivers.sim import SimBackend

    be = SimBackend({"torque_limit": 1.0, "paced": False})
    with be:
        be.activate()
        start = be.samples_produced
        big = np.full(72, 0.9)                           # sum of squares 58 > limit^2: the exact check runs
        be.write(big, start_seq=start)
        assert be.clamped == 0 and be.last_torque == 0.9
        be.write(np.r_[np.full(71, 0.1), 1.0 + 1e-12], start_seq=start)
        assert be.clamped == 1 and be.last_torque == 1.0
        be.write(np.r_[0.1, -1.5, 0.1], start_seq=start)
        assert be.clamped == 2
        for bad in (np.nan, np.inf, -np.inf):
            with pytest.raises(DriverError, match="non-finite"):
                be.write(np.r_[np.zeros(10), bad], start_seq=start)
        with pytest.warns(RuntimeWarning, match="overflow"):   # finite, but the sum of squares overflows: clamped
            be.write(np.full(4, 1e200), start_seq=start)
        assert be.clamped == 6 and be.last_torque == 1.0

"""The emulated board as a device that differs from what the host is told ([emulator] actual), and the
board's INFO answer (identity())."""

from __future__ import annotations

import logging
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from drivers.base import unit_of
from drivers.encoder_board.board import SerialBoardBackend
from drivers.encoder_board.emulator import start_emulator_for
from drivers.errors import DeviceFault
from rt_ident.axis.params import thomson_x
from rt_ident.config import from_mapping
from rt_ident.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
T = 0.01                                  # N m: the pulse
P = thomson_x()
ACCEL = T / (P.I1 + P.I2)                 # rad/s^2 the pulse gives the nominal axis (rigid body)
# a busy machine may hold the test process off its CPU: the host's timeouts and the board's watch of the
# host's frames are wider than shipped (none of them is a subject here), and the board's FIFO unbounded
LENIENT = {"read_timeout": 2.0, "write_timeout": 0.5, "startup_timeout": 5.0}
LENIENT_BOARD = {"tx_buffer": 1 << 24, "heartbeat_timeout": 2.0}


@pytest.fixture
def rig():
    """rig(backend_opts, **emulator) -> (board, open backend); both torn down after the test. The board
    is started from the run's tables, as the loop starts it."""
    made = []

    def make(backend_opts=None, **emulator):
        backend = {**LENIENT, **(backend_opts or {})}
        board = start_emulator_for({"backend": backend, "emulator": {**LENIENT_BOARD, **emulator}})
        be = SerialBoardBackend({"port": board.port, **backend})
        made.append((board, be))
        be.open()
        return board, be

    yield make
    for board, be in made:
        be.close()
        board.stop()


def pulse(be, samples=1000, timeout=5.0):
    """Hold T from rest for ``samples`` board samples (50 ms): (t, theta1, theta2, torque_cmd, torque_meas)
    of those samples."""
    be.activate()
    be.read()
    be.write(T)
    blocks, on = [], 0
    end = time.monotonic() + timeout
    while on < samples and time.monotonic() < end:
        b = be.read()
        blocks.append(b)
        on += int(np.count_nonzero(b.torque_cmd))
        time.sleep(0.001)
    be.write(0.0)
    assert on >= samples
    t, th1, th2, cmd, meas = (np.concatenate([getattr(b, f) for b in blocks])
                              for f in ("t", "theta1", "theta2", "torque_cmd", "torque_meas"))
    i = cmd != 0
    return t[i] - t[i][0], th1[i], th2[i], cmd[i], meas[i]


def accel(t, theta):
    return 2 * np.polyfit(t, theta, 2)[0]


def assert_moves_as(be, f1, f2):
    """theta1 and theta2 accelerate at f1, f2 x the nominal axis's; the torque reads as commanded."""
    t, th1, th2, cmd, meas = pulse(be)
    assert accel(t, th1) == pytest.approx(f1 * ACCEL, rel=0.05)
    assert accel(t, th2) == pytest.approx(f2 * ACCEL, rel=0.05)
    # rigid motion: the displacements stand in the ratio the truth implies (the twist is ~1e-4 of them)
    assert (th2[-1] - th2[0]) / (th1[-1] - th1[0]) == pytest.approx(f2 / f1, rel=2e-3)
    assert np.all(cmd == np.float32(T))
    assert np.allclose(meas, T, atol=1e-4)         # the current the board believes it drives


# ----- the truth differs, the host is told the nominal values -----------------------------------
@pytest.mark.parametrize("actual, f1, f2", [
    ({"torque_sign": -1}, -1, -1),                 # the motor turns the other way: both read reversed
    ({"motor_encoder_sign": -1}, -1, 1),           # theta1 reversed
    ({"scale_sign": -1}, 1, -1),                   # theta2 reversed
    ({"counts_per_rev": 2 * 131072}, 2, 1),        # twice the counts per rev: theta1 doubled
    ({"scale_resolution": 2e-7}, 1, 0.5),          # twice the m per count: x (theta2) halved
    ({"lead": 2 * 7.96e-4}, 1, 2),                 # twice the lead: x (theta2) doubled
    ({"torque_scale": 10}, 10, 10),                # ten times the torque: ten times the acceleration
], ids=lambda v: next(iter(v)) if isinstance(v, dict) else None)
def test_a_pulse_on_a_device_that_differs_from_what_the_host_is_told_reads_as_the_truth_implies(rig, actual, f1, f2):
    board, be = rig({"encoder_mismatch_limit": None}, actual=actual)
    assert_moves_as(be, f1, f2)


@pytest.mark.parametrize("key", ["torque_sign", "motor_encoder_sign", "scale_sign"])
def test_the_hosts_matching_sign_setting_undoes_the_devices_sign(rig, key):
    # the encoder mismatch check stays on: it compares theta1 and theta2 in the host's convention
    board, be = rig({key: -1}, actual={key: -1})
    assert_moves_as(be, 1, 1)


def test_a_sign_the_host_is_told_is_the_devices_own_when_actual_leaves_it_out():
    be = SerialBoardBackend({"emulate": True, "torque_sign": -1, "motor_encoder_sign": -1, **LENIENT,
                             "emulator": LENIENT_BOARD})
    with be:
        assert be.emulator.torque_sign == -1 and be.emulator.motor_encoder_sign == -1
        assert_moves_as(be, 1, 1)


def test_a_motor_encoder_counting_the_other_way_trips_the_encoder_mismatch_check(rig):
    board, be = rig(actual={"motor_encoder_sign": -1})
    with pytest.raises(DeviceFault, match="disagree"):
        pulse(be, 10_000)


def test_x0_and_the_travel_are_the_true_table_position(rig):
    # the scale truly counts half as often: the host reads the table at half of where it truly is, inside
    # the travel, while it truly is outside: the board trips once enabled
    board, be = rig({"encoder_mismatch_limit": None}, actual={"scale_resolution": 2e-7}, travel=(-1e-4, 1e-4),
                    x0=1.5e-4)
    assert be.read_position()[1] * 7.96e-4 == pytest.approx(0.75e-4)
    be.activate()
    with pytest.raises(DeviceFault, match="limit-switch"):
        for _ in range(1000):
            be.read()
            time.sleep(0.001)


# ----- configuration ------------------------------------------------------------------------
def test_an_unknown_actual_key_is_a_config_error_naming_it():
    with pytest.raises(ConfigError) as e:
        SerialBoardBackend({"emulate": True, "emulator": {"actual": {"torque_gain": 2}}})
    assert e.value.field == "backend.emulator.actual.torque_gain" and "\n" not in str(e.value)


def test_a_rated_torque_is_refused_in_one_line_pointing_to_torque_scale():
    with pytest.raises(ConfigError, match="torque_scale") as e:
        SerialBoardBackend({"emulate": True, "emulator": {"actual": {"rated_torque": 2.0}}})
    assert e.value.field == "backend.emulator.actual.rated_torque" and "\n" not in str(e.value)


def test_plant_actual_of_a_run_config_reaches_the_emulated_board():
    with open(CONFIGS / "serial-virtual.toml", "rb") as fh:
        data = tomllib.load(fh)
    data["plant"] = {"actual": {"x0": 0.001, "torque_sign": -1, "counts_per_rev": 4096, "lead": 1e-3,
                                "torque_scale": 2.0}}
    with start_emulator_for(from_mapping(data)) as board:
        assert (board.torque_sign, board.counts_per_rev, board.params.lead, board.torque_scale) == (-1, 4096, 1e-3, 2.0)
        assert board.scale_sign == 1 and board.scale_resolution == 1e-7 and board.cfg.x0 == 0.001


# ----- identity (the INFO answer) -------------------------------------------------------------
def test_identity_returns_the_boards_info_and_its_unit_while_open_and_active(rig, caplog):
    with caplog.at_level(logging.INFO, logger="drivers.encoder_board.board"):
        board, be = rig({"torque_limit": 0.5}, actual={"counts_per_rev": 4096}, serial_number=7)
    want = {"model": "emulated-board", "firmware": "1.0.0", "serial_number": 7, "protocol_version": 2,
            "sample_rate_hz": 20000.0, "current_limit_a": 5.0, "torque_constant": 0.1,
            "counts_per_rev": 4096, "scale_resolution": 1e-7}
    assert be.identity() == want
    # the board is configured for other counts than the host is told: said at open (a run refuses it)
    assert [r.getMessage() for r in caplog.records if "configured for" in r.getMessage()] == [
        f"serial board on {board.port} is configured for counts_per_rev = 4096 ([backend]: 131072)"]
    be.activate()
    assert be.identity() == want
    assert unit_of(be.identity()) == {"model": "emulated-board", "serial_number": 7}


def test_a_board_that_never_answers_the_info_request_still_opens(rig):
    t0 = time.monotonic()
    board, be = rig({"info_timeout": 0.05}, answer_info=False)
    assert time.monotonic() - t0 < 2.0
    assert be.identity() == {"info": "not available"}
    be.activate()
    assert board.enabled and be.identity() == {"info": "not available"}
    assert unit_of(be.identity()) is None                       # no unit it could be told apart by

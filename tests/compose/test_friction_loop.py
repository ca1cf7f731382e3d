"""The friction model in the loop: ``[estimator] model = "two-inertia-friction"`` identifies the
friction per sample while the host controls the axis, and its Fc, Fv feed the controller forward."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.axis.friction import thomson_friction
from rt_ident.compose.offline import run_offline
from rt_ident.config import load


def _run(ff: bool, seconds: float = 4.0):
    cfg = load(None, **{"loop.duration": seconds, "estimator.model": "two-inertia-friction",
                        "control.friction_feedforward": ff, "control.mode": "fixed"})
    cfg = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"friction": {"preset": "thomson"}}),
                                 "reference": {"kind": "sine", "amplitude": 0.005, "frequency_hz": 1.0}})
    err: list[float] = []
    out = run_offline(cfg, tick_hook=lambda loop: err.append(loop.control.error))
    return out, np.abs(np.array(err[2000:]))        # after the first two seconds


@pytest.mark.slow
def test_loop_identifies_friction_per_sample_and_its_feedforward_shrinks_the_reversal_error():
    off, e_off = _run(False)
    on, e_on = _run(True)
    assert off["stop"] is None and on["stop"] is None
    f, p = thomson_friction(), on["friction"]["parameters"]
    for k in ("I1", "I2", "B", "K"):
        assert p[k] == pytest.approx(on["truth"][k], rel=0.02), k
    assert p["Fc1"] + p["Fc2"] == pytest.approx(f.Fc1 + f.Fc2, rel=0.05)
    assert off["friction"]["feedforward"] is None and on["friction"]["feedforward"]["Fc"] > 0
    assert e_on.max() < 0.8 * e_off.max()


def test_stuck_encoder_check_ignores_torque_below_the_sims_breakaway_torque():
    from rt_ident.loop.safety import SafetyMonitor

    plain = load(None)
    assert plain.stuck_torque() == 0.0
    cfg = load(None)
    cfg = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"friction": {"preset": "thomson"}})})
    f = thomson_friction()
    assert cfg.stuck_torque() == pytest.approx(f.Fs1 + f.Fs2)
    explicit = load(None, **{"safety.stuck_torque": 0.5})
    assert explicit.stuck_torque() == 0.5
    # a motionless encoder under a torque below breakaway is sticking, not stuck: no trip
    mon = SafetyMonitor(lead=1e-3, window=(-1.0, 1.0), max_decel=1e4, watchdog_ticks=3,
                        stuck_torque=cfg.stuck_torque())
    for _ in range(10):
        mon.check(10, 0.5, 0.0, 0.0, torque_active=0.5 * cfg.stuck_torque() > mon.stuck_torque)
    from drivers.errors import WatchdogTrip

    with pytest.raises(WatchdogTrip):
        for _ in range(10):
            mon.check(10, 0.5, 0.0, 0.0, torque_active=2.0 * cfg.stuck_torque() > mon.stuck_torque)


def test_plant_friction_reaches_both_emulated_devices_and_a_real_device_refuses_it():
    from drivers.cia402.emulator import build_emulator_for
    from drivers.encoder_board.emulator import start_emulator_for as start_board
    from rt_ident.errors import ConfigError

    f = thomson_friction()
    can = load("configs/canopen-virtual.toml", **{"plant.friction": {"preset": "thomson"}})
    assert can.emulator["friction"] == {"preset": "thomson"}
    assert can.stuck_torque() == pytest.approx(f.Fs1 + f.Fs2)
    drive = build_emulator_for(can)
    assert drive.plant.friction is not None and drive.plant.friction.Fc1 == pytest.approx(f.Fc1)
    ser = load("configs/serial-virtual.toml", **{"plant.friction": {"preset": "thomson"}})
    board = start_board(ser)
    try:
        assert board.friction is not None and board.friction.Fc2 == pytest.approx(f.Fc2)
    finally:
        board.stop()
    with pytest.raises(ConfigError, match="plant.friction"):
        load("configs/canopen-virtual.toml", **{"backend.emulate": False, "plant.friction": {"preset": "thomson"}})

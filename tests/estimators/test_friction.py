"""Friction and backlash: in the plant, in the estimators, in identify, in the controller."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from rt_ident.axis.friction import Friction, thomson_friction
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.cli import app
from rt_ident.config import from_mapping
from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.friction import fit_friction, predict_torque

DT = 2.9481e-5
IDEAL = SensorConfig(counts_per_rev=0, scale_resolution=0.0)
runner = CliRunner()


def closed_loop(p, fr, dt, seconds, *, sensors, amp, hz, probe, per_tick, offset=0.0, x0=0.0, standstill=0.0,
                seed=0, bw_hz=20.0, probe_per_sample=True, torque_limit=10.0):
    """A host PD loop on the measured motor angle (ticks of ``per_tick`` samples, torque held per tick)
    tracking a sine, plus a white probing torque per sample (or per tick); returns (t, theta1, theta2,
    torque_meas)."""
    sim = PlantSimulator(p, dt, sensors=sensors, friction=fr, seed=seed, torque_limit=torque_limit)
    J = p.I1 + p.I2
    w = 2 * math.pi * bw_hz
    kp, kd = J * w * w, 2 * 0.7 * J * w
    rng = np.random.default_rng(seed + 1)
    blocks, prev, v = [], None, 0.0
    for i in range(int(seconds / (dt * per_tick))):
        t = i * per_tick * dt
        moving = t >= standstill
        ts = t - standstill
        ref = amp * math.sin(2 * math.pi * hz * ts) if moving else 0.0
        vref = amp * 2 * math.pi * hz * math.cos(2 * math.pi * hz * ts) if moving else 0.0
        u = 0.0
        if blocks:
            m = blocks[-1][0][-1]
            v += 0.3 * ((0.0 if prev is None else (m - prev) / (per_tick * dt)) - v)
            prev = m
            u = kp * (ref - m) + kd * (vref - v)
        cmd = np.full(per_tick, u) + (probe * rng.standard_normal(per_tick if probe_per_sample else 1)
                                      if moving else 0.0)
        b = sim.step_block(cmd)
        blocks.append((b.theta1, b.theta2, b.torque_meas))
    th1, th2, tq = (np.concatenate([b[k] for b in blocks]) for k in range(3))
    return np.arange(th1.size) * dt, th1 + x0, th2 + x0, tq + offset


# ----------------------------------------------------------------------------- plant
def test_zero_friction_runs_the_unchanged_frictionless_plant_bit_for_bit():
    p = thomson_x()
    u = 0.05 * np.sin(np.arange(3000) * 0.01)
    sens = SensorConfig(torque_meas_noise=1e-3)
    a = PlantSimulator(p, DT, sensors=sens, seed=3).step_block(u)
    b = PlantSimulator(p, DT, sensors=sens, seed=3, friction=Friction()).step_block(u)
    assert PlantSimulator(p, DT, friction=Friction()).friction is None
    for f in ("theta1", "theta2", "torque_applied", "torque_meas", "true_states"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


def test_friction_kernel_compiled_equals_interpreted():
    p = thomson_x()
    fr = thomson_friction().with_(backlash=2e-3)
    u = 0.03 * np.sin(2 * np.pi * 20 * np.arange(4000) * DT) + 0.01
    a = PlantSimulator(p, DT, sensors=SensorConfig(torque_meas_noise=1e-3), friction=fr, seed=1).step_block(u)
    b = PlantSimulator(p, DT, sensors=SensorConfig(torque_meas_noise=1e-3), friction=fr,
                       seed=1).step_block(u, compiled=False)
    np.testing.assert_allclose(a.true_states, b.true_states, rtol=0, atol=1e-12)


def test_axis_sticks_below_breakaway_torque_and_slides_above_it():
    p, fr = thomson_x(), Friction(Fc1=0.01, Fc2=0.003)
    still = PlantSimulator(p, DT, sensors=IDEAL, friction=fr).step_block(np.full(20000, 0.009))
    assert np.all(still.true_states == 0.0)                  # exactly at rest: no creep, no chatter
    moving = PlantSimulator(p, DT, sensors=IDEAL, friction=fr).step_block(np.full(20000, 0.02))
    assert moving.true_states[-1, 1] > 0 and moving.true_states[-1, 3] > 0


def test_constant_torque_reaches_the_velocity_where_viscous_and_coulomb_balance_it():
    p = thomson_x()
    fr = Friction(Fc1=0.01, Fv1=2e-4, Fc2=0.004, Fv2=1e-4)
    T = 0.05
    s = PlantSimulator(p, 1e-4, sensors=IDEAL, friction=fr).step_block(np.full(60000, T)).true_states
    w_end = (T - fr.Fc1 - fr.Fc2) / (fr.Fv1 + fr.Fv2)
    assert s[-1, 1] == pytest.approx(w_end, rel=1e-3) and s[-1, 3] == pytest.approx(w_end, rel=1e-3)


def test_stribeck_breakaway_needs_static_not_coulomb_friction():
    p = thomson_x()
    fr = Friction(Fc1=0.01, Fs1=0.02, vs1=0.5)
    assert np.all(PlantSimulator(p, DT, sensors=IDEAL, friction=fr).step_block(np.full(5000, 0.015))
                  .true_states == 0.0)
    assert PlantSimulator(p, DT, sensors=IDEAL, friction=fr).step_block(np.full(5000, 0.025)).true_states[-1, 1] > 0


def test_backlash_lets_the_motor_turn_inside_the_gap_without_moving_the_table():
    p = thomson_x()
    gap = 1e-3                                                 # rad of theta1 - theta2
    fr = Friction(Fc2=0.003, backlash=gap)
    s = PlantSimulator(p, DT, sensors=IDEAL, friction=fr)
    blk = s.step_block(np.r_[np.full(100, 5e-5), np.zeros(2000)])    # a small push, then coast (no friction on 1)
    th1, th2 = blk.true_states[:, 0], blk.true_states[:, 2]
    assert np.all(th2 == 0.0) and 0 < th1.max() < gap / 2
    big = PlantSimulator(p, DT, sensors=IDEAL, friction=fr).step_block(np.full(20000, 0.01)).true_states
    assert big[-1, 2] > 0 and big[-1, 0] - big[-1, 2] == pytest.approx(gap / 2, rel=0.2)


def test_plant_friction_of_a_run_config_reaches_the_sim_backend_and_is_validated():
    from drivers import make_backend
    from rt_ident.compose.build import backend_options

    cfg = from_mapping({"plant": {"friction": {"preset": "thomson", "Fc1": 0.02}}})
    be = make_backend("sim", {**backend_options(cfg), "paced": False})
    assert be.plant.friction == thomson_friction().with_(Fc1=0.02, Fs1=0.024)
    assert make_backend("sim", {"paced": False}).plant.friction is None
    with pytest.raises(ConfigError, match="Fc1"):
        from_mapping({"plant": {"friction": {"Fc1": -1.0}}})
    with pytest.raises(ConfigError, match="friction"):
        from_mapping({"plant": {"friction": {"Fc1": 0.01}}, "backend": {"name": "canopen"}})


# ----------------------------------------------------------------------------- estimators
@pytest.fixture(scope="module")
def bench_record():
    """THOMSON axis + its friction, 2^17-count encoder, 0.1 um scale, 0.5 mN m torque noise, 34 kHz,
    closed loop (1 kHz host PD tracking a 1 Hz sine), 4 s."""
    p, fr = thomson_x(), thomson_friction()
    t, th1, th2, tq = closed_loop(p, fr, DT, 4.0, sensors=SensorConfig(torque_meas_noise=5e-4), amp=6.0, hz=1.0,
                                  probe=0.1, per_tick=34)
    truth = {"I1": p.I1, "I2": p.I2, "B": p.B, "K": p.K, "Fc1": fr.Fc1, "Fv1": fr.Fv1, "Fc2": fr.Fc2, "Fv2": fr.Fv2}
    return th1, th2, tq, truth


def test_two_inertia_friction_model_recovers_the_axis_and_its_coulomb_friction_on_bench_like_data(bench_record):
    th1, th2, tq, truth = bench_record
    r = fit_friction(th1, tq, DT, model="two-inertia-friction", theta2=th2)
    assert list(r.parameters) == ["I1", "I2", "B", "K", "Fc1", "Fv1", "Fc2", "Fv2", "offset"]
    err = {k: abs(r.parameters[k] / truth[k] - 1) for k in truth}
    assert max(err[k] for k in ("I1", "I2", "B", "K")) < 0.02, err
    assert err["Fc1"] < 0.05 and err["Fc2"] < 0.05, err
    for k in ("I1", "I2", "K", "Fc1", "Fc2"):
        lo, hi = r.ci95[k]
        assert lo < r.parameters[k] < hi


def test_frictionless_model_on_the_same_data_is_biased(bench_record):
    th1, th2, tq, truth = bench_record
    lin = fit_friction(th1, tq, DT, model="two-inertia", theta2=th2)
    fri = fit_friction(th1, tq, DT, model="two-inertia-friction", theta2=th2)
    worst = max(abs(lin.parameters[k] / truth[k] - 1) for k in ("I1", "I2", "B", "K"))
    assert worst > 0.05                                       # friction folded into K and B
    assert lin.nrmse_percent > 3 * fri.nrmse_percent


def _stiff_record(seed=0, hz=0.5):
    p = AxisParams(I1=2.0e-4, I2=1.0e-4, B=0.5, K=5e4)         # stiff: the mode is at 4.4 kHz
    fr = Friction(Fc1=0.05, Fv1=1e-3, Fc2=0.02, Fv2=5e-4)
    # the plant runs at 10 kHz, the recording keeps every 10th sample (1 kHz, the torque held over each
    # 1 ms like a drive's current command, only the measurement noise varies within it); 2^16-count encoder,
    # 5 mN m torque noise, a 0.03 N m current offset, the position starting at 123.4 rad, 2 s at standstill
    t, th1, _, tq = closed_loop(p, fr, 1e-4, 12.0, sensors=SensorConfig(counts_per_rev=2**16, scale_resolution=0,
                                torque_meas_noise=5e-3), amp=2.0, hz=hz, probe=0.05, per_tick=10, offset=0.03,
                                x0=123.4, standstill=2.0, seed=seed, probe_per_sample=False)
    truth = {"J": p.I1 + p.I2, "Fv": fr.Fv1 + fr.Fv2, "Fc": fr.Fc1 + fr.Fc2, "offset": 0.03}
    return t[::10], th1[::10], tq[::10], truth


def test_rigid_friction_recovers_J_Fv_Fc_offset_on_a_quantized_1khz_closed_loop_stiff_axis():
    t, th1, tq, truth = _stiff_record()
    r = fit_friction(th1, tq, 1e-3, model="rigid-friction")
    err = {k: abs(r.parameters[k] / truth[k] - 1) for k in truth}
    assert max(err.values()) < 0.05, err
    assert r.diagnostics["quanta"][0] == pytest.approx(2 * math.pi / 2**16)


def test_one_sensor_csv_identifies_rigid_friction_and_validates_on_another_recording(tmp_path):
    files = []
    for i, hz in enumerate((0.5, 0.8)):
        t, th1, tq, truth = _stiff_record(seed=10 + i, hz=hz)
        f = tmp_path / f"axis{i}.csv"
        np.savetxt(f, np.column_stack([t, th1, tq]), delimiter=",", header="t,theta1,torque", comments="")
        files.append(f)
    res = runner.invoke(app, ["identify", str(files[0]), "--model", "rigid-friction", "--validate", str(files[1]),
                              "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert set(d["parameters"]) == {"J", "Fv", "Fc", "offset"} and set(d["intervals"]) == set(d["parameters"])
    assert d["fit"]["nrmse_percent"] < 5
    for k in truth:
        assert d["parameters"][k] == pytest.approx(truth[k], rel=0.05), k
    assert d["validation"]["torque_error_percent"] < 5
    refused = runner.invoke(app, ["identify", str(files[0])])
    assert refused.exit_code != 0 and "rigid-friction" in str(refused.exception or refused.output)


def test_friction_models_are_refused_by_the_linear_only_methods():
    from rt_ident.estimators.registry import IdentData, identify, methods_for_model

    assert methods_for_model("two-inertia-friction") == ["svf-ls"]
    assert "frequency" in methods_for_model("two-inertia")
    data = IdentData(None, np.zeros(100), np.zeros(100), np.zeros(100), dt=1e-3)
    with pytest.raises(ConfigError, match="svf-ls"):
        identify(data, "frequency", model="rigid-friction")


def test_standstill_noise_does_not_enter_the_fit():
    # an axis that never moves: only quantization noise on the angle -> refused, not a made-up friction
    rng = np.random.default_rng(0)
    q = 2 * math.pi / 2**16
    th = np.round(rng.normal(0, 0.7 * q, 5000) / q) * q
    with pytest.raises(Exception, match="standstill"):
        fit_friction(th, 0.01 * rng.standard_normal(5000), 1e-3, model="rigid-friction")


def test_validation_of_a_wrong_model_shows_a_large_torque_error():
    t, th1, tq, truth = _stiff_record(seed=5)
    good = fit_friction(th1, tq, 1e-3, model="rigid-friction")
    from dataclasses import replace

    bad = replace(good, parameters={**good.parameters, "Fc": 0.0})
    assert predict_torque(bad, th1, tq, 1e-3)["torque_error_percent"] > 3 * predict_torque(
        good, th1, tq, 1e-3)["torque_error_percent"]


def test_two_inertia_models_need_theta2():
    with pytest.raises(DataError, match="rigid-friction"):
        fit_friction(np.zeros(1000), np.zeros(1000), 1e-3, model="two-inertia-friction")


# ----------------------------------------------------------------------------- controller
def test_friction_feedforward_shrinks_the_reversal_spikes_of_a_sine():
    from rt_ident.compose.offline import run_offline
    from rt_ident.control.feedforward import FrictionFeedforward

    fr = thomson_friction()
    ff = FrictionFeedforward(Fc=fr.Fc1 + fr.Fc2, Fv=fr.Fv1 + fr.Fv2)

    def peak(ffw):
        cfg = from_mapping({
            "backend": {"name": "sim", "sample_period": 1e-4, "torque_meas_noise": 5e-4},
            "plant": {"friction": {"preset": "thomson"}}, "excitation": {"kind": "none"},
            "control": {"mode": "fixed"}, "safety": {"watchdog_ticks": 100000},
            "reference": {"kind": "sine", "amplitude": 0.005, "frequency_hz": 1.0, "fade_periods": 1.0},
            "loop": {"duration": 2.5, "realtime": False}, "telemetry": {"sink": "off"},
            "recording": {"enabled": False}})
        ts, es = [], []

        def hook(loop):
            if ffw is not None:
                loop.control.law.friction = ffw
            ts.append(loop.control.t)
            es.append(loop.control.error)

        out = run_offline(cfg, tick_hook=hook)
        assert out["stop"] is None
        t, e = np.array(ts), np.array(es)
        return float(np.max(np.abs(e[t > 1.25])))            # after the fade-in: reversals at 1.25, 1.75, 2.25 s

    without, with_ff = peak(None), peak(ff)
    assert with_ff < 0.3 * without, (without, with_ff)


def test_emulated_serial_board_builds_its_plant_with_the_given_friction():
    from drivers.encoder_board.emulator import EmulatedBoard

    fr = thomson_friction()
    board = EmulatedBoard(friction=fr)
    assert board._plant.friction == fr
    assert EmulatedBoard()._plant.friction is None


def test_recursive_friction_estimator_per_sample_matches_the_truth_on_bench_like_data(bench_record):
    from rt_ident.estimators.friction_stream import RecursiveFrictionEstimator

    th1, th2, tq, truth = bench_record
    est = RecursiveFrictionEstimator(DT, "two-inertia-friction", quanta=(2 * math.pi / 2**17, 1e-7 / thomson_x().lead))
    for i in range(0, th1.size, 34):                          # the loop's blocks: one tick of samples at a time
        est.update_block(th1[i:i + 34], th2[i:i + 34], tq[i:i + 34])
    e = est.estimate()
    err = {k: abs(e[k] / truth[k] - 1) for k in truth}
    assert max(err[k] for k in ("I1", "I2", "B", "K")) < 0.02, err
    assert err["Fc1"] < 0.05 and err["Fc2"] < 0.05, err


def test_recursive_rigid_friction_skips_nan_samples_and_recovers_the_stiff_axis():
    from rt_ident.estimators.friction_stream import RecursiveFrictionEstimator

    t, th1, tq, truth = _stiff_record(seed=2)
    th1 = th1.copy()
    th1[5000] = np.nan
    est = RecursiveFrictionEstimator(1e-3, "rigid-friction", filter_hz=100.0, quanta=(2 * math.pi / 2**16, 0.0))
    assert est.estimate() is None
    est.update_block(th1, None, tq)
    e = est.estimate()
    assert all(abs(e[k] / truth[k] - 1) < 0.05 for k in truth), e


# ----------------------------------------------------------------------------- the verdict
def test_two_inertia_friction_on_a_recording_that_only_holds_still_is_not_trusted():
    # a drive holds the axis; only a random disturbance torque moves it (no excitation): the fit finds
    # negative friction, which no axis has
    sim = PlantSimulator(thomson_x(), DT, sensors=SensorConfig(counts_per_rev=2**17, scale_resolution=1e-7,
                                                               torque_meas_noise=5e-4, torque_process_noise=0.1),
                         controller=HoldController(), seed=1)
    b = sim.step_block(np.zeros(int(2.0 / DT)))
    r = fit_friction(b.theta1, b.torque_meas, DT, model="two-inertia-friction", theta2=b.theta2)
    negative = [k for k in ("Fc1", "Fv1", "Fc2", "Fv2") if r.parameters[k] < 0.0]
    assert negative
    assert not r.trusted
    assert any(why.startswith("not physical") and negative[0] in why for why in r.reasons), r.reasons
    assert r.as_dict()["trust"]["trusted"] is False


def test_rigid_friction_on_two_inertia_data_is_not_trusted():
    # a frictionless flexible axis fitted as one rigid body with friction: the torque is not explained
    t, th1, th2, tq = closed_loop(thomson_x(), None, DT, 2.0, sensors=SensorConfig(torque_meas_noise=5e-4),
                                  amp=6.0, hz=1.0, probe=0.1, per_tick=34)
    r = fit_friction(th1, tq, DT, model="rigid-friction")
    assert r.nrmse_percent > 20.0
    assert not r.trusted
    assert any("NRMSE" in why for why in r.reasons), r.reasons


def test_a_physical_fit_that_explains_the_torque_is_trusted_and_says_why(bench_record):
    th1, th2, tq, _ = bench_record
    r = fit_friction(th1, tq, DT, model="two-inertia-friction", theta2=th2)
    assert r.trusted, r.reasons
    names = [c["criterion"] for c in r.trust_criteria]
    assert any("physical" in n for n in names) and any("NRMSE" in n for n in names)
    assert any("resonance" in n for n in names) and any("interval" in n for n in names)


def test_a_validation_error_above_its_threshold_fails_the_verdict(tmp_path):
    t, th1, tq, _ = _stiff_record(seed=10)
    own = tmp_path / "axis.csv"
    np.savetxt(own, np.column_stack([t, th1, tq]), delimiter=",", header="t,theta1,torque", comments="")
    t, th1, tq, _ = _stiff_record(seed=11, hz=0.8)
    same = tmp_path / "same_axis.csv"
    np.savetxt(same, np.column_stack([t, th1, tq]), delimiter=",", header="t,theta1,torque", comments="")
    # another axis: three times the inertia, four times the friction
    t, o1, _, oq = closed_loop(AxisParams(I1=6.0e-4, I2=3.0e-4, B=0.5, K=5e4),
                               Friction(Fc1=0.2, Fv1=1e-3, Fc2=0.1, Fv2=5e-4), 1e-4, 6.0,
                               sensors=SensorConfig(counts_per_rev=2**16, scale_resolution=0, torque_meas_noise=5e-3),
                               amp=2.0, hz=0.5, probe=0.05, per_tick=10, seed=3, probe_per_sample=False)
    other = tmp_path / "other_axis.csv"
    np.savetxt(other, np.column_stack([t[::10], o1[::10], oq[::10]]), delimiter=",", header="t,theta1,torque",
               comments="")
    args = ["identify", str(own), "--model", "rigid-friction", "--json", "--validate"]
    good = json.loads(runner.invoke(app, args + [str(same)]).stdout)
    assert good["validation"]["torque_error_percent"] < 5 and good["trusted"] is True, good["trust"]
    res = runner.invoke(app, args + [str(other)])
    assert res.exit_code == 0, res.output
    bad = json.loads(res.stdout)
    assert bad["validation"]["torque_error_percent"] > 10
    assert bad["trusted"] is False
    crit = [c for c in bad["trust"]["criteria"] if c["criterion"].startswith("validation on")]
    assert len(crit) == 1 and crit[0]["value"] == pytest.approx(bad["validation"]["torque_error_percent"])
    assert crit[0]["limit"] == "<= 10 %" and not crit[0]["passed"]
    assert any(why.startswith(f"fails validation on {other}") for why in bad["trust"]["reasons"])
    text = runner.invoke(app, args[:-2] + ["--validate", str(other)]).stdout
    assert "trusted: no" in text and "fails validation on" in text

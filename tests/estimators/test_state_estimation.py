"""Tests for rt_ident.estimators.state_estimation: steady-state Kalman velocity/acceleration from quantized angles."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.state_estimation import (
    AxisStateEstimator,
    SteadyStateKalman,
    encoder_quanta,
    process_noise_for_bandwidth,
)

DT = 2.9481e-5                      # Table 2, N=512, k=10 (about 34 kHz)
Q1 = 2.0 * math.pi / 2**17          # motor encoder, 2^17 counts/rev
Q2 = 1e-7 / 7.96e-4                 # 0.1 um linear scale over the 7.96e-4 m/rad lead


def _quantize(x: np.ndarray, q: float) -> np.ndarray:
    return q * np.round(x / q)


def _long_filterpy_gain(f: SteadyStateKalman, max_iter: int = 50_000) -> np.ndarray:
    """Run filterpy's textbook predict/update until the gain stops changing."""
    kf = KalmanFilter(dim_x=f.dim, dim_z=1)
    kf.F = f.F.copy()
    kf.H = f.H.copy()
    kf.R = np.array([[f.R]])
    kf.Q = Q_continuous_white_noise(f.dim, f.dt, f.process_noise)
    kf.P = np.eye(f.dim)
    prev = None
    for _ in range(max_iter):
        kf.predict()
        kf.update(0.0)
        k = kf.K[:, 0].copy()
        if prev is not None and np.max(np.abs(k - prev) / np.abs(k)) < 1e-14:
            break
        prev = k
    return k


@pytest.mark.parametrize(("model", "bandwidth"), [("ca", 300.0), ("ca", 2000.0), ("cj", 2000.0)])
def test_steady_state_gain_matches_long_filterpy_run(model: str, bandwidth: float) -> None:
    f = SteadyStateKalman.from_bandwidth(DT, Q1, bandwidth, model)
    # our Q (physical units) is filterpy's continuous white noise model
    np.testing.assert_allclose(f.Q, Q_continuous_white_noise(f.dim, DT, f.process_noise), rtol=1e-12)
    np.testing.assert_allclose(f.gain, _long_filterpy_gain(f), rtol=1e-9)


@pytest.mark.parametrize("model", ["ca", "cj"])
def test_bandwidth_sets_filter_pole_radius(model: str) -> None:
    bw = 1500.0
    f = SteadyStateKalman.from_bandwidth(DT, Q1, bw, model)
    # error dynamics of the a posteriori estimate: x <- (I - K H) F x
    A = (np.eye(f.dim) - np.outer(f.gain, f.H[0])) @ f.F
    s = np.log(np.linalg.eigvals(A).astype(complex)) / DT
    np.testing.assert_allclose(np.abs(s), 2 * math.pi * bw, rtol=1e-2)
    assert np.all(s.real < 0)


def test_velocity_error_on_quantized_sine_is_far_below_finite_difference() -> None:
    t = np.arange(34_000) * DT      # 1 s at ~34 kHz
    a, fr = 0.5, 10.0
    theta = a * np.sin(2 * np.pi * fr * t)
    omega = a * 2 * np.pi * fr * np.cos(2 * np.pi * fr * t)
    alpha = -a * (2 * np.pi * fr) ** 2 * np.sin(2 * np.pi * fr * t)
    z = _quantize(theta, Q1)
    f = SteadyStateKalman.from_bandwidth(DT, Q1, 300.0)
    out = f.filter_block(z)
    fd = np.r_[0.0, np.diff(z)] / DT
    keep = slice(2000, None)         # after the start transient
    rms_kf = np.sqrt(np.mean((out[keep, 1] - omega[keep]) ** 2))
    rms_fd = np.sqrt(np.mean((fd[keep] - omega[keep]) ** 2))
    assert rms_kf < 0.15 * rms_fd, (rms_kf, rms_fd)
    # acceleration is usable too (finite difference twice would be pure noise)
    rms_alpha = np.sqrt(np.mean((out[keep, 2] - alpha[keep]) ** 2))
    assert rms_alpha < 0.2 * np.sqrt(np.mean(alpha**2))
    # angle estimate within a quantum of the truth
    assert np.max(np.abs(out[keep, 0] - theta[keep])) < Q1


@pytest.mark.parametrize("model", ["ca", "cj"])
def test_block_split_is_bit_for_bit_invariant(model: str) -> None:
    rng = np.random.default_rng(3)
    z = _quantize(np.cumsum(rng.normal(0, 1e-3, 5000)), Q1)
    whole = SteadyStateKalman.from_bandwidth(DT, Q1, 1000.0, model)
    parts = SteadyStateKalman.from_bandwidth(DT, Q1, 1000.0, model)
    ref = whole.filter_block(z)
    cuts = [0, 1, 34, 35, 1000, 2999, 5000]
    got = np.vstack([parts.filter_block(z[a:b]) for a, b in zip(cuts[:-1], cuts[1:])] + [parts.filter_block(z[:0])])
    assert got.shape == (5000, 3)
    assert np.array_equal(got, ref)


@pytest.mark.parametrize("model", ["ca", "cj"])
def test_compiled_kernel_equals_numpy_reference(model: str) -> None:
    rng = np.random.default_rng(7)
    t = np.arange(4000) * DT
    z = _quantize(0.3 * np.sin(2 * np.pi * 40 * t) + np.cumsum(rng.normal(0, 1e-4, t.size)), Q1)
    fast = SteadyStateKalman.from_bandwidth(DT, Q1, 800.0, model)
    slow = SteadyStateKalman.from_bandwidth(DT, Q1, 800.0, model)
    a = np.vstack([fast.filter_block(z[:1500]), fast.filter_block(z[1500:])])
    b = np.vstack([slow.filter_block_reference(z[:1500]), slow.filter_block_reference(z[1500:])])
    scale = np.max(np.abs(b), axis=0)
    assert np.max(np.abs(a - b) / scale) < 1e-12
    np.testing.assert_allclose(fast.x[:3], slow.x[:3], rtol=1e-12)
    # the internal jerk state (cj) is a noisy 4th derivative; it still agrees to ~1e-12
    np.testing.assert_allclose(fast.x, slow.x, rtol=1e-10)


def test_reset_starts_at_rest_at_given_angle() -> None:
    f = SteadyStateKalman.from_bandwidth(DT, Q1, 500.0)
    f.reset(1.25)
    out = f.filter_block(np.full(10, 1.25))
    np.testing.assert_allclose(out[:, 0], 1.25, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out[:, 1:], 0.0, atol=1e-9)


def test_axis_estimator_returns_both_angles_and_matches_single_filters() -> None:
    q1, q2 = encoder_quanta(2**17, 1e-7, 7.96e-4)
    assert q1 == pytest.approx(Q1) and q2 == pytest.approx(Q2)
    t = np.arange(3000) * DT
    th1 = _quantize(0.2 * np.sin(2 * np.pi * 15 * t), q1)
    th2 = _quantize(0.1 * np.sin(2 * np.pi * 15 * t), q2)
    est = AxisStateEstimator(DT, q1, q2, bandwidth_hz=(800.0, 600.0))
    res = est.filter_block(th1, th2)
    assert res.omega.shape == (3000, 2) and res.alpha.shape == (3000, 2) and res.theta.shape == (3000, 2)
    single = SteadyStateKalman.from_bandwidth(DT, q2, 600.0).filter_block(th2)
    assert np.array_equal(res.omega[:, 1], single[:, 1])
    with pytest.raises(DataError):
        est.filter_block(th1[:5], th2[:4])


def test_invalid_arguments_name_the_field() -> None:
    with pytest.raises(ConfigError, match="model"):
        SteadyStateKalman(DT, Q1, 1.0, model="cv")
    with pytest.raises(ConfigError, match="quantum"):
        SteadyStateKalman(DT, 0.0, 1.0)
    with pytest.raises(ConfigError, match="bandwidth_hz"):
        process_noise_for_bandwidth(DT, Q1, 1.0 / DT)
    with pytest.raises(ConfigError, match="process_noise"):
        AxisStateEstimator(DT, Q1, Q2)
    with pytest.raises(DataError):
        SteadyStateKalman(DT, Q1, 1.0).filter_block(np.zeros((3, 2)))


def test_lost_samples_are_stepped_through_so_the_velocity_does_not_jump_with_each_gap() -> None:
    """A CANopen exchange under load loses whole samples; with their sequence numbers the filter steps
    through each gap. Without them a 2-sample step reads as one and the speed jumps at every gap."""
    dt = 5e-4                                            # 2 kHz, the CANopen configuration's SYNC rate
    q1, q2 = encoder_quanta(2**17, 1e-7, 7.96e-4)
    n = 4000
    seq = np.arange(n)
    w = 20.0                                             # rad/s, steady
    th1 = _quantize(w * seq * dt, q1)
    th2 = _quantize(w * seq * dt, q2)
    keep = (seq % 3 != 1) & ~((seq >= 2000) & (seq < 2040))   # a third of the samples, and a 20 ms hole
    kw = {"process_noise": 1e9}
    with_seq = AxisStateEstimator(dt, q1, q2, **kw)
    without = AxisStateEstimator(dt, q1, q2, **kw)
    # in blocks of two samples, as the 1 kHz loop reads them (gaps also fall between blocks)
    kept = np.flatnonzero(keep)
    good, bad = [], []
    for i in range(0, kept.size, 2):
        idx = kept[i:i + 2]
        good.append(with_seq.filter_block(th1[idx], th2[idx], seq[idx]).omega)
        bad.append(without.filter_block(th1[idx], th2[idx]).omega)
    good, bad = np.vstack(good)[500:], np.vstack(bad)[500:]
    assert np.max(np.abs(good - w)) < 0.02 * w, np.max(np.abs(good - w))
    assert np.max(np.abs(bad - w)) > 0.5 * w               # without seq: speeds off by half and more
    whole = AxisStateEstimator(dt, q1, q2, **kw).filter_block(th1, th2, seq).omega[keep][500:]
    assert np.max(np.abs(whole - w)) < 0.02 * w


def test_sequence_numbers_must_match_the_angles() -> None:
    est = AxisStateEstimator(DT, Q1, Q2, process_noise=1e9)
    with pytest.raises(DataError, match="seq"):
        est.filter_block(np.zeros(3), np.zeros(3), np.arange(2))

"""Excitation identification, Eq. (18), and the NRMSE / fit% measures."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.model import state_space
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.errors import DataError
from rt_ident.estimators.excitation_id import (
    EQ18_N,
    EQ18_SIZE,
    eq18_accumulate,
    fit_percent,
    nrmse,
    nrmse_from_sums,
    reconstruct_torque,
)
from rt_ident.estimators.svf import TR_COLS, SvfEstimator, SvfSettings

DT = 2.9481e-5


def _exact_trajectory(p, n=3000, seed=0):
    """Exact sampled response to a zero-order-held torque (matrix exponential), with exact
    accelerations x' = A x + b T at each sample (torque right-continuous)."""
    A, b = state_space(p)
    M = np.zeros((5, 5))
    M[:4, :4] = A * DT
    M[:4, 4] = b * DT
    E = scipy.linalg.expm(M)
    Ad, Bd = E[:4, :4], E[:4, 4]
    rng = np.random.default_rng(seed)
    T = np.repeat(0.3 * rng.standard_normal(n // 10), 10)
    x = np.zeros((n, 4))
    for k in range(n - 1):
        x[k + 1] = Ad @ x[k] + Bd * T[k]
    xdot = x @ A.T + np.outer(T, b)
    theta, omega, alpha = x[:, [0, 2]], x[:, [1, 3]], xdot[:, [1, 3]]
    return theta, omega, alpha, T


def test_eq18_with_true_params_reproduces_the_true_torque():
    p = thomson_x()
    theta, omega, alpha, T = _exact_trajectory(p)
    That = reconstruct_torque(p, theta, omega, alpha)
    assert That.shape == (len(T), 2)
    scale = np.abs(T).max()
    assert np.abs(That[:, 0] - T).max() < 1e-9 * scale
    # table side: no input acts there; the spring term alone is of the order of T
    assert np.abs(That[:, 1]).max() < 1e-9 * scale
    assert nrmse(That[:, 0], T) < 1e-9


def test_eq18_matches_scalar_transliteration_of_eq1():
    p = thomson_x()
    rng = np.random.default_rng(2)
    th, om, al = rng.standard_normal((3, 50, 2))
    That = reconstruct_torque(p, th, om, al)
    # Eq. (1): I1 a1 + B (w1 - w2) + K (t1 - t2) = T ; I2 a2 - B (w1 - w2) - K (t1 - t2) = 0
    m1 = p.I1 * al[:, 0] + p.B * (om[:, 0] - om[:, 1]) + p.K * (th[:, 0] - th[:, 1])
    m2 = p.I2 * al[:, 1] - p.B * (om[:, 0] - om[:, 1]) - p.K * (th[:, 0] - th[:, 1])
    np.testing.assert_allclose(That, np.column_stack([m1, m2]), rtol=1e-13, atol=1e-13)


def test_one_percent_stiffness_error_raises_the_nrmse_measurably():
    p = thomson_x()
    theta, omega, alpha, T = _exact_trajectory(p)
    good = nrmse(reconstruct_torque(p, theta, omega, alpha)[:, 0], T)
    bad = nrmse(reconstruct_torque(p.with_(K=1.01 * p.K), theta, omega, alpha)[:, 0], T)
    assert bad > 1e-3
    assert bad > 1e5 * max(good, 1e-16)
    assert fit_percent(reconstruct_torque(p.with_(K=1.01 * p.K), theta, omega, alpha)[:, 0], T) < 99.9


def test_nrmse_definition_on_a_small_example():
    truth = np.array([1.0, 2.0, 3.0, 4.0])     # ||truth - mean|| = sqrt(5)
    est = truth + np.array([1.0, 0.0, 0.0, 0.0])
    assert nrmse(est, truth) == pytest.approx(1.0 / np.sqrt(5.0))
    assert fit_percent(est, truth) == pytest.approx(100.0 * (1.0 - 1.0 / np.sqrt(5.0)))
    assert nrmse(np.full(4, 2.5), truth) == pytest.approx(1.0)  # predicting the mean
    assert nrmse(truth, truth) == 0.0


def test_nrmse_rejects_constant_truth_mismatched_shapes_and_nonfinite():
    with pytest.raises(DataError, match="constant"):
        nrmse(np.ones(3), np.full(3, 2.0))
    with pytest.raises(DataError, match="shapes"):
        nrmse(np.ones(3), np.arange(4.0))
    with pytest.raises(DataError, match="non-finite"):
        nrmse(np.array([1.0, np.nan]), np.array([1.0, 2.0]))


def test_reconstruct_torque_rejects_bad_shapes():
    p = thomson_x()
    with pytest.raises(DataError, match="theta"):
        reconstruct_torque(p, np.zeros((5, 3)), np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(DataError, match="shapes differ"):
        reconstruct_torque(p, np.zeros((5, 2)), np.zeros((4, 2)), np.zeros((5, 2)))


def _eq18_nrmse_from_svf(p_used, seconds=0.5):
    """The live torque estimate on a simulated THOMSON axis (the default run's sensors: 2^17-count encoder,
    0.1 um scale, 0.5 mN m torque noise): the SVF fed tick by tick, Eq. (18) with ``p_used`` on its
    filtered derivatives against the filtered measured torque; the NRMSE [%] and the samples compared."""
    truth = thomson_x()
    sim = PlantSimulator(truth, DT, sensors=SensorConfig(torque_meas_noise=5e-4), controller=HoldController(), seed=3)
    b = sim.step_block(np.resize(schroeder_multisine(512, (1, 20), peak=0.3).signal, int(seconds / DT)))
    est = SvfEstimator(DT, truth, SvfSettings())
    sums = np.zeros(EQ18_SIZE)
    for i in range(0, len(b.theta1), 34):
        trace = np.empty((len(b.theta1[i:i + 34]), TR_COLS))
        est.update_block(b.theta1[i:i + 34], b.theta2[i:i + 34], b.torque_meas[i:i + 34], trace)
        eq18_accumulate(trace, p_used.I1, p_used.B, p_used.K, sums)
    return nrmse_from_sums(sums), int(sums[EQ18_N])


def test_eq18_from_svf_states_with_the_true_parameters_matches_the_filtered_measured_torque():
    value, n = _eq18_nrmse_from_svf(thomson_x())
    assert n > 0.9 * 0.5 / DT                       # every sample after the filter's 5-ms warm-up
    assert value < 3.0, value


def test_eq18_from_svf_states_tells_a_wrong_inertia_from_the_right_one():
    p = thomson_x()
    value, _ = _eq18_nrmse_from_svf(replace(p, I1=1.5 * p.I1))
    assert value > 20.0, value

"""The paper's Euler regression (Eqs. 8-9), LS/RLS fits and recovery of (I1, I2, B, K)."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.axis.model import state_space
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.errors import ConfigError, DataError, EstimationError
from rt_ident.estimators.paper import (
    euler_phi,
    euler_regression,
    fit_paper_ls,
    fit_paper_rls,
    recover_physical,
    recover_values,
    state_matrix_from_phi,
)

DT = 2.9481e-5  # Table 2, N = 512, k = 10


def _truth(p: AxisParams) -> np.ndarray:
    return np.array([p.I1, p.I2, p.B, p.K])


def _euler_data(p: AxisParams, dt: float = DT, n: int = 1500, seed: int = 0):
    """States generated exactly by the Euler model x_{k+1} = (I + A dt) x_k + dt b T_k."""
    A, b = state_space(p)
    F = np.eye(4) + A * dt
    T = 0.3 * np.random.default_rng(seed).standard_normal(n)
    x = np.zeros((n, 4))
    for k in range(n - 1):
        x[k + 1] = F @ x[k] + dt * b * T[k]
    return x, T


def test_euler_phi_matches_eq9_entry_by_entry_with_the_dt_over_i1_typo_corrected():
    p = thomson_x()
    I1, I2, B, K, D = p.I1, p.I2, p.B, p.K, DT
    # Eq. (9) transliterated, columns = next theta1, omega1, theta2, omega2;
    # the paper prints the last entry of the omega1 column as Dt: it is Dt/I1.
    oracle = np.array([
        [1.0, -K / I1 * D, 0.0, K / I2 * D],
        [D, 1.0 - B / I1 * D, 0.0, B / I2 * D],
        [0.0, K / I1 * D, 1.0, -K / I2 * D],
        [0.0, B / I1 * D, D, 1.0 - B / I2 * D],
        [0.0, D / I1, 0.0, 0.0],
    ])
    np.testing.assert_allclose(euler_phi(p, DT), oracle, rtol=1e-14, atol=0)


def test_euler_regression_rows_are_states_and_torque_at_k_targets_states_at_k_plus_1():
    x = np.arange(20.0).reshape(5, 4)
    T = np.array([10.0, 11, 12, 13, 14])
    A, b = euler_regression(x, T)
    assert A.shape == (4, 5) and b.shape == (4, 4)
    np.testing.assert_array_equal(A[2], [8, 9, 10, 11, 12])
    np.testing.assert_array_equal(b[2], x[3])


def test_recover_physical_of_true_euler_phi_returns_table1():
    p = thomson_x()
    got = recover_physical(euler_phi(p, DT), DT)
    np.testing.assert_allclose(_truth(got), _truth(p), rtol=1e-11)
    assert got.lead == p.lead


def test_state_matrix_from_true_phi_is_eq8_state_matrix():
    p = thomson_x()
    A, _ = state_space(p)
    np.testing.assert_allclose(state_matrix_from_phi(euler_phi(p, DT), DT), A, rtol=1e-9, atol=1e-9)


def test_ls_on_exact_euler_data_recovers_table1_to_1e8():
    p = thomson_x()
    x, T = _euler_data(p)
    est = fit_paper_ls(x, T, DT)
    np.testing.assert_allclose(_truth(est.params), _truth(p), rtol=1e-8)
    np.testing.assert_allclose(est.phi, euler_phi(p, DT), rtol=1e-9, atol=1e-9)
    assert est.method == "ls" and est.n_samples == len(T) - 1
    assert np.isfinite(est.cond)


def test_rls_on_exact_euler_data_recovers_table1_to_1e8():
    p = thomson_x()
    x, T = _euler_data(p)
    est = fit_paper_rls(x, T, DT, p0=1e14, history=0)
    np.testing.assert_allclose(_truth(est.params), _truth(p), rtol=1e-8)
    assert est.method == "rls" and est.history is None


def test_rls_with_paper_style_p0_approaches_ls_as_p0_grows():
    # Theorem 1 with a large P0: the bias (P0^-1 + A^T A)^-1 P0^-1 (theta0 - phi) falls as 1/p0.
    p = thomson_x()
    x, T = _euler_data(p)
    errs = [np.max(np.abs(_truth(fit_paper_rls(x, T, DT, p0=p0, history=0).params) / _truth(p) - 1))
            for p0 in (1e6, 1e9)]
    assert errs[0] > 100 * errs[1]
    assert errs[0] < 1e-3


def test_rls_history_traces_the_estimates_over_time_for_figs_9_to_12():
    p = thomson_x()
    x, T = _euler_data(p, n=1200)
    est = fit_paper_rls(x, T, DT, p0=1e14, history=-1)
    assert est.history_t.shape == (1199,)                           # every sample below 20k
    np.testing.assert_allclose(est.history_t[[0, -1]], [DT, 1199 * DT])
    assert set(est.history) == {"I1", "I2", "B", "K"}
    for i, name in enumerate(("I1", "I2", "B", "K")):
        assert est.history[name][-1] == pytest.approx(_truth(est.params)[i], rel=1e-12)
    dec = fit_paper_rls(x, T, DT, p0=1e14, history=100)           # decimated
    assert 100 <= len(dec.history_t) <= 120
    assert dec.history_t[-1] == pytest.approx(1199 * DT)


def test_recover_values_vectorizes_over_a_stack_of_phis():
    p, q = thomson_x(), thomson_x().with_(K=55.0)
    stack = np.stack([euler_phi(p, DT), euler_phi(q, DT)])
    vals = recover_values(stack, DT)
    np.testing.assert_allclose(vals, [_truth(p), _truth(q)], rtol=1e-11)


def test_negative_inertia_raises_estimation_error_with_the_value():
    phi = euler_phi(thomson_x(), DT)
    phi[4, 1] = -phi[4, 1]
    with pytest.raises(EstimationError, match=r"I1: .*-2\.7e-05"):
        recover_physical(phi, DT)
    phi = euler_phi(thomson_x(), DT)
    phi[3, 1] = -3 * phi[3, 1]  # B/I1 pair averages to a negative damping
    with pytest.raises(EstimationError, match="B:"):
        recover_physical(phi, DT)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(DataError, match="states"):
        euler_regression(np.zeros((10, 3)), np.zeros(10))
    with pytest.raises(DataError, match="torque"):
        euler_regression(np.zeros((10, 4)), np.zeros(9))
    with pytest.raises(DataError, match="phi"):
        recover_physical(np.zeros((4, 4)), DT)
    with pytest.raises(ConfigError, match="dt"):
        euler_phi(thomson_x(), -1.0)
    with pytest.raises(ConfigError, match="history"):
        x, T = _euler_data(thomson_x(), n=50)
        fit_paper_rls(x, T, DT, history=-5)

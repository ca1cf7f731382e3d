"""Batch least squares (Eq. 10) computed by column-scaled Householder QR."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.errors import DataError, EstimationError
from rt_ident.estimators.ls import lstsq


def _data(n: int = 300, p: int = 5, m: int = 4, noise: float = 0.1, seed: int = 0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, p))
    theta = rng.standard_normal((p, m))
    b = A @ theta + noise * rng.standard_normal((n, m))
    return A, b, theta


def test_lstsq_matches_eq10_normal_equations_on_well_conditioned_data():
    A, b, _ = _data()
    res = lstsq(A, b)
    oracle = np.linalg.solve(A.T @ A, A.T @ b)  # Eq. (10) literally (fine when well conditioned)
    np.testing.assert_allclose(res.theta, oracle, rtol=1e-12, atol=1e-13)
    assert res.rank == 5
    assert res.theta.shape == (5, 4)


def test_lstsq_vector_target_gives_vector_theta():
    A, b, _ = _data(m=1)
    res = lstsq(A, b[:, 0])
    assert res.theta.shape == (5,)
    np.testing.assert_allclose(res.theta, lstsq(A, b).theta[:, 0], rtol=1e-14)
    assert isinstance(res.rss, float)


def test_lstsq_residuals_are_orthogonal_to_regressors():
    A, b, _ = _data()
    res = lstsq(A, b)
    np.testing.assert_allclose(res.residuals, b - A @ res.theta, rtol=0, atol=1e-14)
    # normal equations hold at the minimiser: A^T r = 0
    assert np.abs(A.T @ res.residuals).max() < 1e-11 * np.abs(A.T @ b).max()
    np.testing.assert_allclose(res.rss, np.sum(res.residuals**2, axis=0))


def test_lstsq_is_accurate_where_explicit_inverse_of_normal_equations_is_not():
    # Badly scaled and nearly collinear columns (like the paper's angle/velocity columns):
    # cond(A^T A) ~ 1e19 while the column-scaled QR sees cond ~ 2e5.
    rng = np.random.default_rng(3)
    n = 2000
    base = rng.standard_normal(n)
    A = np.column_stack([
        1e-3 * base,
        1e-3 * (base + 1e-5 * rng.standard_normal(n)),
        1e3 * rng.standard_normal(n),
        rng.standard_normal(n),
    ])
    theta = np.array([2.0, -1.5, 3e-3, 0.7])
    b = A @ theta  # exactly consistent
    res = lstsq(A, b)
    err_qr = np.max(np.abs(res.theta - theta) / np.abs(theta))
    with np.errstate(all="ignore"):
        naive = np.linalg.inv(A.T @ A) @ (A.T @ b)
    err_naive = np.max(np.abs(naive - theta) / np.abs(theta))
    assert err_qr < 1e-7
    assert err_naive > 1e5 * err_qr
    assert 1e5 < res.cond < 1e6


def test_lstsq_condition_number_is_invariant_to_column_scaling():
    A, b, _ = _data()
    c1 = lstsq(A, b).cond
    A2 = A * np.array([1e-6, 1.0, 1e6, 3.0, 1e3])
    res2 = lstsq(A2, b)
    assert res2.cond == pytest.approx(c1, rel=1e-9)
    np.testing.assert_allclose(res2.theta * np.array([1e-6, 1.0, 1e6, 3.0, 1e3])[:, None],
                               lstsq(A, b).theta, rtol=1e-10)


def test_lstsq_rank_deficient_raises_estimation_error_naming_columns():
    A, b, _ = _data()
    A[:, 3] = 2.0 * A[:, 1]
    with pytest.raises(EstimationError, match="rank deficient"):
        lstsq(A, b)


def test_lstsq_zero_column_raises_estimation_error():
    A, b, _ = _data()
    A[:, 2] = 0.0
    with pytest.raises(EstimationError, match=r"column\(s\) \[2\]"):
        lstsq(A, b)


def test_lstsq_nonfinite_rows_raise_data_error_with_row_numbers():
    A, b, _ = _data()
    A[7, 1] = np.nan
    b[11, 0] = np.inf
    with pytest.raises(DataError, match=r"\[7, 11\]"):
        lstsq(A, b)


@pytest.mark.parametrize(
    "A_shape, b_shape",
    [((10,), (10,)), ((10, 3), (9,)), ((10, 3), (10, 2, 2)), ((10, 0), (10,))],
)
def test_lstsq_bad_shapes_raise_data_error(A_shape, b_shape):
    with pytest.raises(DataError):
        lstsq(np.ones(A_shape), np.ones(b_shape))


def test_lstsq_fewer_rows_than_columns_raises_estimation_error():
    with pytest.raises(EstimationError, match="need n >= p"):
        lstsq(np.ones((3, 5)), np.ones(3))


def test_lstsq_result_arrays_are_read_only():
    A, b, _ = _data()
    res = lstsq(A, b)
    with pytest.raises(ValueError):
        res.theta[0, 0] = 1.0

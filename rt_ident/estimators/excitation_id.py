"""Excitation identification, Eq. (18), and the fit measures used to judge it.

.. math::  \\hat T(t) = \\hat I \\ddot\\theta(t) + \\hat B \\dot\\theta(t) + \\hat K \\theta(t)   \\qquad (18)

with the 2x2 matrices of Eq. (3) built from estimated parameters. The first component
of :math:`\\hat T` is the motor torque T; the second (table side) carries no input in
the model and should be close to zero -- its size is a consistency check.

The live form (:func:`eq18_filtered`, :func:`eq18_accumulate`) departs from the paper: it takes the
derivatives from the state-variable filter F(s) = lam^3/(s + lam)^3 of
:mod:`rt_ident.estimators.svf` instead of differencing sampled angles (on a quantizing encoder
that is mostly noise), so it reconstructs F T, and is compared with the measured torque through
the same filter (the same lag and gain on both sides).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from rt_ident.axis.model import damping_matrix, mass_matrix, stiffness_matrix
from rt_ident.axis.params import AxisParams
from rt_ident.errors import DataError
from rt_ident.estimators.svf import TR_F_DELTA, TR_F_TORQUE, TR_S2F_TH1, TR_SF_DELTA

__all__ = ["eq18_accumulate", "eq18_filtered", "fit_percent", "nrmse", "nrmse_from_sums", "reconstruct_torque"]


def _as_n2(name: str, x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or x.shape[1] != 2:
        raise DataError(f"{name}: expected shape (n, 2) [motor, table], got {x.shape}")
    return x


def reconstruct_torque(p: AxisParams, theta: np.ndarray, omega: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Eq. (18): T_hat = I_hat theta'' + B_hat theta' + K_hat theta, row-wise -> (n, 2).

    ``theta``, ``omega``, ``alpha``: (n, 2) angles [rad], velocities [rad/s] and accelerations
    [rad/s^2] of [motor, table]. Column 0 of the result is the identified motor torque; column
    1 should be ~0 (no torque acts on the table in the model).
    """
    theta = _as_n2("theta", theta)
    omega = _as_n2("omega", omega)
    alpha = _as_n2("alpha", alpha)
    if not (theta.shape == omega.shape == alpha.shape):
        raise DataError(f"theta/omega/alpha: shapes differ: {theta.shape}, {omega.shape}, {alpha.shape}")
    M, C, K = mass_matrix(p), damping_matrix(p), stiffness_matrix(p)
    # Eq. (18), one row per sample: T^T = alpha^T M^T + omega^T C^T + theta^T K^T
    return alpha @ M.T + omega @ C.T + theta @ K.T


def nrmse(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Normalized RMS error ``||estimate - truth||_2 / ||truth - mean(truth)||_2``.

    Norms are Frobenius over all samples (and columns, for 2-D input, where the mean is
    taken per column). 0 is a perfect fit; 1 is no better than predicting the mean.

    Raises
    ------
    DataError
        Shapes differ, values are non-finite, or ``truth`` is constant (the ratio is undefined).
    """
    est = np.asarray(estimate, dtype=float)
    tru = np.asarray(truth, dtype=float)
    if est.shape != tru.shape:
        raise DataError(f"estimate/truth: shapes differ: {est.shape} vs {tru.shape}")
    if est.size == 0:
        raise DataError("truth: is empty")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(tru))):
        raise DataError("estimate/truth: contain non-finite values")
    denom = float(np.linalg.norm(tru - tru.mean(axis=0)))
    if denom == 0.0:
        raise DataError("truth: is constant; NRMSE is undefined")
    return float(np.linalg.norm(est - tru)) / denom


def fit_percent(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Fit [%] = 100 (1 - NRMSE) (100 = perfect; may be negative for a fit worse than the mean)."""
    return 100.0 * (1.0 - nrmse(estimate, truth))


# Eq. (18), motor row, I1 th1'' + B (th1' - th2') + K (th1 - th2) (th2 = x / lead: the table position as
# a screw angle), on one sample of an SVF trace (rt_ident.estimators.svf.svf_block's ``trace``: s^2 F th1,
# s F (th1 - th2), F (th1 - th2), F T): each derivative a filter state, not a difference of sampled angles
# (a departure from the paper), so the result is F T_hat
@numba.njit(inline="always")
def eq18_filtered(trace: np.ndarray, k: int, I1: float, B: float, K: float) -> float:
    return I1 * trace[k, TR_S2F_TH1] + B * trace[k, TR_SF_DELTA] + K * trace[k, TR_F_DELTA]


#: eq18_accumulate's running sums: samples, sum of squared errors, sum and sum of squares of F T
EQ18_N, EQ18_SSE, EQ18_SUM, EQ18_SUMSQ, EQ18_SIZE = range(5)


@numba.njit("void(float64[:, :], float64, float64, float64, float64[:])", cache=True)
def eq18_accumulate(trace: np.ndarray, I1: float, B: float, K: float, sums: np.ndarray) -> None:
    """Add a block's samples (rows of an SVF trace; rows with a NaN skipped) to the running sums of
    the reconstruction :func:`eq18_filtered` against the filtered measured torque (``sums``:
    ``EQ18_*``)."""
    for k in range(trace.shape[0]):
        m = trace[k, TR_F_TORQUE]
        e = eq18_filtered(trace, k, I1, B, K) - m
        if math.isfinite(e):
            sums[EQ18_N] += 1.0
            sums[EQ18_SSE] += e * e
            sums[EQ18_SUM] += m
            sums[EQ18_SUMSQ] += m * m


def nrmse_from_sums(sums: np.ndarray) -> float:
    """NRMSE [%] from :func:`eq18_accumulate`'s sums: 100 rms(error) / std(F T), as
    :func:`nrmse` (NaN with fewer than 10 samples or a constant torque)."""
    n = float(sums[EQ18_N])
    if n < 10:
        return math.nan
    mean = float(sums[EQ18_SUM]) / n
    var = float(sums[EQ18_SUMSQ]) / n - mean * mean
    if not var > 0.0:
        return math.nan
    return 100.0 * math.sqrt(float(sums[EQ18_SSE]) / n / var)

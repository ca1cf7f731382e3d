"""Excitation identification, Eq. (18), and the fit measures used to judge it.

.. math::  \\hat T(t) = \\hat I \\ddot\\theta(t) + \\hat B \\dot\\theta(t) + \\hat K \\theta(t)   \\qquad (18)

with the 2x2 matrices of Eq. (3) built from estimated parameters. The first component
of :math:`\\hat T` is the motor torque T; the second (table side) carries no input in
the model and should be close to zero -- its size is a consistency check.
"""

from __future__ import annotations

import numpy as np

from rt_ident.axis.model import damping_matrix, mass_matrix, stiffness_matrix
from rt_ident.axis.params import AxisParams
from rt_ident.errors import DataError

__all__ = ["fit_percent", "nrmse", "reconstruct_torque"]


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

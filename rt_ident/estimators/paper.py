"""The paper's estimator: the forward-Euler regression of Eqs. (8)-(9), LS/RLS, and recovery.

Eq. (9) stacks ``x_{k+1}^T = [x_k^T, T_k] phi`` for k = 1..n-1, with
``x = [theta1, omega1, theta2, omega2]``: a regressor A (n-1, 5) = rows
``[theta1, omega1, theta2, omega2, T]`` at k, targets b (n-1, 4) = the four states at
k+1, and ``phi`` (5, 4) = ``[(I + A_c Dt)^T ; Dt b_c^T]`` where (A_c, b_c) is Eq. (8).

Columns of the true phi (next theta1, omega1, theta2, omega2)::

    row theta1 : 1    -K Dt/I1       0    K Dt/I2
    row omega1 : Dt   1 - B Dt/I1    0    B Dt/I2
    row theta2 : 0     K Dt/I1       1   -K Dt/I2
    row omega2 : 0     B Dt/I1       Dt   1 - B Dt/I2
    row T      : 0     Dt/I1         0    0

The paper prints the T-row entry of the omega1 column as ``Dt``; it must be ``Dt/I1``
(typo in Eq. 9). It also prints the input column of Eq. (8) as -1/I1; we use +1/I1
(see :func:`rt_ident.axis.model.state_space`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rt_ident.axis.model import state_space
from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError, DataError, EstimationError
from rt_ident.estimators.ls import lstsq
from rt_ident.estimators.rls import RecursiveLeastSquares

log = logging.getLogger(__name__)

__all__ = [
    "PARAM_NAMES",
    "PaperEstimate",
    "euler_phi",
    "euler_regression",
    "fit_paper_ls",
    "fit_paper_rls",
    "recover_physical",
    "recover_values",
    "state_matrix_from_phi",
]

PARAM_NAMES: tuple[str, ...] = ("I1", "I2", "B", "K")
DEFAULT_HISTORY_POINTS = 20_000
_DEFAULT_LEAD = 7.96e-4


def _check_dt(dt: float) -> float:
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not (math.isfinite(dt) and dt > 0):
        raise ConfigError("dt", f"must be a finite number > 0, got {dt!r}")
    return float(dt)


def euler_regression(states: np.ndarray, torque: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (9): regressor A (n-1, 5) = [theta1, omega1, theta2, omega2, T] at k; b (n-1, 4) = states at k+1."""
    states = np.asarray(states, dtype=float)
    torque = np.asarray(torque, dtype=float)
    if states.ndim != 2 or states.shape[1] != 4:
        raise DataError(f"states: expected shape (n, 4) [theta1, omega1, theta2, omega2], got {states.shape}")
    if torque.shape != (states.shape[0],):
        raise DataError(f"torque: expected shape ({states.shape[0]},) to match states, got {torque.shape}")
    if states.shape[0] < 2:
        raise DataError(f"states: need at least 2 samples, got {states.shape[0]}")
    A = np.column_stack([states[:-1], torque[:-1]])
    b = np.array(states[1:])
    return A, b


def euler_phi(p: AxisParams, dt: float) -> np.ndarray:
    """The true (5, 4) phi of Eq. (9) for parameters ``p``: [(I + A_c Dt)^T ; Dt b_c^T]."""
    dt = _check_dt(dt)
    Ac, bc = state_space(p)
    phi = np.empty((5, 4))
    phi[:4] = (np.eye(4) + Ac * dt).T
    # Eq. (9) prints the T-row entry of the omega1 column as Dt; it is Dt/I1 (paper typo).
    phi[4] = dt * bc
    return phi


def state_matrix_from_phi(phi: np.ndarray, dt: float) -> np.ndarray:
    """Estimated continuous state matrix of Eq. (8): A_hat = (phi[:4]^T - I) / Dt."""
    dt = _check_dt(dt)
    phi = _check_phi(phi)
    return (phi[:4].T - np.eye(4)) / dt


def _check_phi(phi: np.ndarray) -> np.ndarray:
    phi = np.asarray(phi, dtype=float)
    if phi.shape[-2:] != (5, 4):
        raise DataError(f"phi: expected shape (5, 4) (or a stack (k, 5, 4)), got {phi.shape}")
    return phi


def recover_values(phi: np.ndarray, dt: float) -> np.ndarray:
    """Raw (I1, I2, B, K) from phi (5, 4) or a stack (k, 5, 4), without validation -> (..., 4).

    Entries used (Dt = dt):

    * I1 = Dt / phi[T, omega1]: the only entry that is 1/I1 alone.
    * K/I1 = (phi[theta2, omega1] - phi[theta1, omega1]) / (2 Dt): the symmetric pair
      +-K Dt/I1 of the omega1 column, averaged.
    * B/I1 = (phi[omega2, omega1] + 1 - phi[omega1, omega1]) / (2 Dt): the pair B Dt/I1 and
      1 - B Dt/I1, averaged.
    * K/I2 = (phi[theta1, omega2] - phi[theta2, omega2]) / (2 Dt), likewise from the omega2 column.
    * K = I1 (K/I1), B = I1 (B/I1), I2 = K / (K/I2).

    I2 comes from K/I2 rather than B/I2 because the stiffness entries are the large,
    well-determined ones of the omega2 column (B Dt/I2 is ~1e-2 of K Dt/I2 ... for Table 1
    at Dt = 3e-5 it is ~8e-3 vs ~0.4). The kinematic columns (theta1, theta2: 1 and Dt)
    carry no physical parameter and are not used. Non-physical values (I1 <= 0, ...) and
    division by zero come out as they are (inf/nan/negative); see :func:`recover_physical`.
    """
    dt = _check_dt(dt)
    phi = _check_phi(phi)
    with np.errstate(divide="ignore", invalid="ignore"):
        I1 = dt / phi[..., 4, 1]
        k_i1 = (phi[..., 2, 1] - phi[..., 0, 1]) / (2.0 * dt)
        b_i1 = (phi[..., 3, 1] + (1.0 - phi[..., 1, 1])) / (2.0 * dt)
        k_i2 = (phi[..., 0, 3] - phi[..., 2, 3]) / (2.0 * dt)
        K = I1 * k_i1
        B = I1 * b_i1
        I2 = K / k_i2
    return np.stack([I1, I2, B, K], axis=-1)


def recover_physical(phi: np.ndarray, dt: float, *, lead: float = _DEFAULT_LEAD) -> AxisParams:
    """Physical parameters from an estimated phi (5, 4); see :func:`recover_values` for the entries.

    Raises
    ------
    EstimationError
        A recovered value is non-finite, or non-physical (I1, I2, K <= 0 or B < 0); the
        message names the parameter and its value.
    """
    phi = _check_phi(phi)
    if phi.shape != (5, 4):
        raise DataError(f"phi: expected shape (5, 4), got {phi.shape}")
    vals = recover_values(phi, dt)
    for name, v in zip(PARAM_NAMES, vals):
        if not math.isfinite(v):
            raise EstimationError(f"{name}: recovered value is not finite ({v!r}); phi is degenerate")
        if (name == "B" and v < 0.0) or (name != "B" and v <= 0.0):
            kind = "damping" if name == "B" else ("stiffness" if name == "K" else "inertia")
            raise EstimationError(f"{name}: recovered {kind} is non-physical ({v:.6g}); the fit is not trustworthy")
    return AxisParams(I1=float(vals[0]), I2=float(vals[1]), B=float(vals[2]), K=float(vals[3]), lead=lead)


@dataclass(frozen=True)
class PaperEstimate:
    """Result of :func:`fit_paper_ls` / :func:`fit_paper_rls`.

    Attributes
    ----------
    params : recovered physical parameters.
    phi : (5, 4) estimated Euler phi of Eq. (9).
    method : "ls" or "rls".
    n_samples : number of regression rows used (n - 1).
    cond : column-scaled condition number of the regressor (LS only; nan for RLS).
    history_t : (k,) time [s] of each recorded RLS estimate (the time of the target row,
        ``(i + 1) dt`` after row i), or None.
    history : {"I1", "I2", "B", "K"} -> (k,) recovered values over the recursion (nan where
        the intermediate phi is degenerate), or None. For the paper's Figs. 9-12.
    """

    params: AxisParams
    phi: np.ndarray
    method: str
    n_samples: int
    cond: float = math.nan
    history_t: np.ndarray | None = None
    history: dict[str, np.ndarray] | None = None


def fit_paper_ls(states: np.ndarray, torque: np.ndarray, dt: float, *, lead: float = _DEFAULT_LEAD) -> PaperEstimate:
    """Eq. (10) on the Euler regression of Eq. (9), then :func:`recover_physical`."""
    dt = _check_dt(dt)
    A, b = euler_regression(states, torque)
    res = lstsq(A, b)
    phi = np.array(res.theta)
    return PaperEstimate(params=recover_physical(phi, dt, lead=lead), phi=phi, method="ls",
                         n_samples=A.shape[0], cond=res.cond)


def fit_paper_rls(
    states: np.ndarray,
    torque: np.ndarray,
    dt: float,
    *,
    p0: float | np.ndarray = 1e6,
    forgetting: float = 1.0,
    variant: str = "standard",
    history: int = -1,
    compiled: bool = True,
    lead: float = _DEFAULT_LEAD,
) -> PaperEstimate:
    """Eqs. (14)-(16) on the Euler regression of Eq. (9), one 5x5 P for the four outputs.

    ``p0`` is the paper's P(0) = p0 I (or any SPD matrix / diagonal), theta(0) = 0.
    ``history``: 0 = none; -1 = every sample when n <= 20 000, else evenly decimated to about
    20 000 points; k > 0 = at most about k points.
    """
    dt = _check_dt(dt)
    A, b = euler_regression(states, torque)
    if isinstance(history, bool) or not isinstance(history, (int, np.integer)) or history < -1:
        raise ConfigError("history", f"must be an integer >= -1, got {history!r}")
    m = A.shape[0]
    est = RecursiveLeastSquares(5, 4, p0=p0, forgetting=forgetting, variant=variant, compiled=compiled)
    hist_t = hist = None
    if history == 0:
        est.update_block(A, b)
    else:
        cap = DEFAULT_HISTORY_POINTS if history == -1 else int(history)
        stride = max(1, -(-m // cap))
        snaps = []
        rows = []
        for start in range(0, m, stride):
            stop = min(start + stride, m)
            est.update_block(A[start:stop], b[start:stop])
            snaps.append(np.array(est.theta))
            rows.append(stop - 1)
        vals = recover_values(np.stack(snaps), dt)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(vals) | (vals < 0.0)
            bad[:, [0, 1, 3]] |= vals[:, [0, 1, 3]] == 0.0
        vals = np.where(bad, np.nan, vals)  # non-physical intermediate estimates are not plotted
        hist_t = (np.asarray(rows, dtype=float) + 1.0) * dt
        hist = {name: vals[:, i].copy() for i, name in enumerate(PARAM_NAMES)}
    if est.n_rejected:
        log.warning("fit_paper_rls: %d non-finite samples were rejected", est.n_rejected)
    phi = np.array(est.theta)
    return PaperEstimate(params=recover_physical(phi, dt, lead=lead), phi=phi, method="rls",
                         n_samples=m, history_t=hist_t, history=hist)

"""Time-domain estimators that are exact for the way the data were made (beyond the paper).

The paper regresses Eq. (9), a forward-Euler discretization, on data made by
Newmark's method (Eqs. 4-6). The mismatch, not noise, causes its errors
(docs/theory/paper.md, "Where the paper is wrong or silent"). Here the regression matches the data:

* Newmark, average acceleration (alpha = 1/4, delta = 1/2) *is* the trapezoidal
  rule on Eq. (8): Eq. (4) with Eq. (6) at t_k and t_k+1 gives, per sample pair,
  rows that are linear in (I1, I2, B, K) -> :func:`fit_tustin_states`. Eliminating
  the velocities gives an exact three-point relation on angles only (the bilinear
  map s -> (2/dt)(z-1)/(z+1)) -> :func:`fit_tustin_angles`.
* A zero-order-hold plant obeys x_k+1 = Ad x_k + bd T_k exactly, so the paper's own
  regression Eq. (9) ``b = A phi`` is exact; only its reading through forward Euler is
  wrong. :func:`fit_zoh` reads phi through the matrix logarithm instead:
  A_c = logm(Ad)/dt and bd = (int_0^dt expm(A s) ds) b. :func:`fit_tustin_map` is the
  trapezoidal counterpart (inverse Cayley map).

With noise-free data of the matching kind all four are exact to rounding. They are
equation-error (least-squares) estimators: with noisy, quantized or closed-loop data
they are biased (errors in variables); use the frequency method for bench data.
Their covariances assume white equation errors (the three-point residuals are
coloured, so those intervals are optimistic).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import scipy.linalg

from rt_ident.errors import DataError, EstimationError
from rt_ident.estimators.base import Identification
from rt_ident.estimators.uncertainty import (
    build_identification,
    excitation_report,
    excited_band_of,
    excited_bands,
    inverse_normal_matrix,
    log_covariance,
    params_from_vector,
)

logger = logging.getLogger(__name__)

DEFAULT_LEAD = 7.96e-4
_Q, _V = [0, 2], [1, 3]     # positions / velocities inside an Eq. (8) state


def _signals(n_min: int, **arrays: np.ndarray) -> list[np.ndarray]:
    out = []
    n = None
    for name, a in arrays.items():
        a = np.asarray(a, dtype=float)
        if a.ndim != 1:
            raise DataError(f"{name}: must be 1-D, got shape {a.shape}")
        if n is None:
            n = a.size
        elif a.size != n:
            raise DataError(f"{name}: length {a.size} differs from {n}")
        if not np.all(np.isfinite(a)):
            raise DataError(f"{name}: contains non-finite values")
        out.append(a)
    if n is None or n < n_min:
        raise DataError(f"need at least {n_min} samples, got {n}")
    return out


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0.0):
        raise DataError(f"dt: must be finite and > 0, got {dt!r}")
    return dt


# --------------------------------------------------------------------------- linear two-equation LS
def _solve_two_equations(X1: np.ndarray, y1: np.ndarray, X2: np.ndarray, y2: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Stacked LS for p = [I1, I2, B, K]; X1 (m, 4) motor rows, X2 (m, 4) table rows.

    Feasible GLS: solve, estimate each equation's residual variance, reweight, solve
    again. Columns are scaled to unit norm before solving. Returns p, cov(p), info.
    """
    X = np.vstack([X1, X2])
    y = np.concatenate([y1, y2])
    w = np.ones(2)
    p = np.zeros(4)
    for _ in range(2):
        W = np.concatenate([np.full(y1.size, w[0]), np.full(y2.size, w[1])])
        Xw, yw = X * W[:, None], y * W
        scale = np.linalg.norm(Xw, axis=0)
        scale[scale == 0.0] = 1.0
        sol, *_ = np.linalg.lstsq(Xw / scale, yw, rcond=None)
        p = sol / scale
        r = y - X @ p
        s = np.array([np.sqrt(np.mean(r[:y1.size] ** 2)), np.sqrt(np.mean(r[y1.size:] ** 2))])
        if np.all(s > 0.0):
            w = s.min() / s      # relative weights; the overall scale is set by s2 below
    W = np.concatenate([np.full(y1.size, w[0]), np.full(y2.size, w[1])])
    rw = (y - X @ p) * W
    dof = max(y.size - 4, 1)
    s2 = float(rw @ rw) / dof
    cov = s2 * inverse_normal_matrix(X * W[:, None])
    return p, cov, {"rms_residual": math.sqrt(s2), "n_rows": float(y.size)}


def _bands(torque: np.ndarray, dt: float, held: bool) -> list[tuple[float, float]]:
    """The bands the recorded torque excited (its image too when the torque is held over a sample)."""
    return excited_bands(*excited_band_of(torque, dt), dt if held else None)


def _finish(p_vec: np.ndarray, cov: np.ndarray, regressors: list[np.ndarray], method: str,
            lead: float, info: dict[str, float], bands: list[tuple[float, float]]) -> Identification:
    p = params_from_vector(p_vec, lead, what=method)
    return build_identification(p, method, log_covariance(p, cov), excitation_report(regressors), info,
                                bands=bands)


def fit_tustin_states(theta1: np.ndarray, omega1: np.ndarray, theta2: np.ndarray, omega2: np.ndarray,
                      torque: np.ndarray, dt: float, *, lead: float = DEFAULT_LEAD) -> Identification:
    """Exact LS for Newmark (average acceleration) data with full states.

    Eq. (4) with delta = 1/2 and Eq. (6) at t_k and t_k+1, per sample pair (h = dt/2):
      I1 (w1_k+1 - w1_k) + B h [dw_k + dw_k+1] + K h [d_k + d_k+1] = h (T_k + T_k+1)
      I2 (w2_k+1 - w2_k) - B h [dw_k + dw_k+1] - K h [d_k + d_k+1] = 0
    with d = th1 - th2, dw = w1 - w2. Departure from the paper: the paper's Eq. (9)
    is forward Euler; this is the discretization the data were made with.
    """
    th1, w1, th2, w2, T = _signals(3, theta1=theta1, omega1=omega1, theta2=theta2, omega2=omega2,
                                   torque=torque)
    h = 0.5 * _check_dt(dt)
    d, dw = th1 - th2, w1 - w2
    sd, sdw, sT = h * (d[1:] + d[:-1]), h * (dw[1:] + dw[:-1]), h * (T[1:] + T[:-1])
    z = np.zeros_like(sd)
    X1 = np.column_stack([np.diff(w1), z, sdw, sd])
    X2 = np.column_stack([z, np.diff(w2), -sdw, -sd])
    p, cov, info = _solve_two_equations(X1, sT, X2, z)
    info["n_samples"] = float(th1.size)
    return _finish(p, cov, [X1[:, [0, 2, 3]], np.vstack([X1, X2])], "tustin", lead, info, _bands(T, 2 * h, False))


def fit_tustin_angles(theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, dt: float,
                      *, lead: float = DEFAULT_LEAD) -> Identification:
    """Exact LS for Newmark (average acceleration) data from angles and torque only.

    Eliminating the velocities from Eqs. (4)-(6) (trapezoidal rule) gives, for k = 1..n-2,
      I1 (4/dt^2)(th1_k+1 - 2 th1_k + th1_k-1) + B (2/dt)(d_k+1 - d_k-1) + K (d_k+1 + 2 d_k + d_k-1)
          = T_k+1 + 2 T_k + T_k-1
      I2 (4/dt^2)(th2_k+1 - 2 th2_k + th2_k-1) - B (2/dt)(...) - K (...) = 0
    i.e. Eq. (3) under the bilinear map s -> (2/dt)(z-1)/(z+1), multiplied by (z+1)^2/z.
    """
    th1, th2, T = _signals(4, theta1=theta1, theta2=theta2, torque=torque)
    dt = _check_dt(dt)
    d = th1 - th2
    c2 = 4.0 / dt**2
    acc1 = c2 * (th1[2:] - 2.0 * th1[1:-1] + th1[:-2])
    acc2 = c2 * (th2[2:] - 2.0 * th2[1:-1] + th2[:-2])
    vel = (2.0 / dt) * (d[2:] - d[:-2])
    pos = d[2:] + 2.0 * d[1:-1] + d[:-2]
    rhs = T[2:] + 2.0 * T[1:-1] + T[:-2]
    z = np.zeros_like(pos)
    X1 = np.column_stack([acc1, z, vel, pos])
    X2 = np.column_stack([z, acc2, -vel, -pos])
    p, cov, info = _solve_two_equations(X1, rhs, X2, z)
    info["n_samples"] = float(th1.size)
    return _finish(p, cov, [X1[:, [0, 2, 3]], np.vstack([X1, X2])], "tustin", lead, info, _bands(T, dt, False))


# --------------------------------------------------------------------------- one-step maps
def physical_from_continuous(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[I1, I2, B, K] from a continuous (A, b) of the Eq. (8) form (+1/I1 input column).

    I1 = 1/b[1]. Each of K/I1, B/I1, K/I2, B/I2 appears twice in A (rows 1 and 3);
    the two entries are averaged. Then K = I1 (K/I1), B = I1 (B/I1), and 1/I2 is the
    LS solution of [K; wn B] u = [K/I2; wn B/I2] with wn^2 = K/I1 + K/I2 (both rows
    in the same units, rad/s^2).
    """
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    I1 = 1.0 / b[1]
    k1 = 0.5 * (-A[1, 0] + A[1, 2])
    b1 = 0.5 * (-A[1, 1] + A[1, 3])
    k2 = 0.5 * (A[3, 0] - A[3, 2])
    b2 = 0.5 * (A[3, 1] - A[3, 3])
    K, B = I1 * k1, I1 * b1
    w2 = abs(k1 + k2)
    u = (K * k2 + w2 * B * b2) / (K * K + w2 * B * B)
    return np.array([I1, 1.0 / u, B, K])


def continuous_from_zoh(Ad: np.ndarray, bd: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Invert the exact ZOH discretization: A = logm(Ad)/dt, b = Gamma^-1 bd.

    The log is taken of the balanced matrix D Ad D^-1, D = diag(1, dt, 1, dt) (angles
    and velocity*dt have the same size), which keeps scipy's logm accurate to ~1e-12.
    The principal log is the right one only if |Im eig(A)| dt < pi (no aliasing);
    an eigenvalue of Ad on the negative real axis has no real log -> EstimationError.
    Gamma = int_0^dt expm(A s) ds is the top-right block of expm([[A, I], [0, 0]] dt).
    """
    mu = np.linalg.eigvals(Ad)
    near = np.abs(np.angle(mu)) > math.pi * (1.0 - 1e-9)
    if np.any(near & (mu.real <= 0.0)):
        raise EstimationError(f"zoh: Ad has an eigenvalue {mu[near][0]:.4g} on the negative real axis; "
                              "no real matrix logarithm (a mode at or above Nyquist)")
    D = np.array([1.0, dt, 1.0, dt])
    L = scipy.linalg.logm((Ad * D[:, None]) / D[None, :])
    if np.iscomplexobj(L):
        if np.max(np.abs(L.imag)) > 1e-8 * max(np.max(np.abs(L.real)), 1.0):
            raise EstimationError("zoh: the matrix logarithm of Ad is not real")
        L = L.real
    A = (L / D[:, None]) * D[None, :] / dt
    aug = np.zeros((8, 8))
    aug[:4, :4] = A * dt
    aug[:4, 4:] = np.eye(4) * dt
    Gam = scipy.linalg.expm(aug)[:4, 4:]
    return A, np.linalg.solve(Gam, bd)


def continuous_from_tustin(Ad: np.ndarray, g: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse Cayley map of x_k+1 = Ad x_k + g (T_k + T_k+1) (trapezoidal rule):

    Ad = (I - hA)^-1 (I + hA), g = (I - hA)^-1 h b, h = dt/2
    => A = (1/h)(Ad - I)(Ad + I)^-1 and b = (I - hA) g / h.
    """
    h = 0.5 * dt
    eye = np.eye(4)
    A = np.linalg.solve((Ad + eye).T, (Ad - eye).T).T / h
    return A, (eye - h * A) @ g / h


def _regress_map(X: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """LS of x_k+1 = Phi^T [x_k; u_k] (the paper's Eq. 9-10, ``b = A phi``).

    Returns phi (5, 4), the per-output residual covariance Sigma (4, 4), (Z^T Z)^-1, rms.
    """
    Z = np.column_stack([X[:-1], U])
    Y = X[1:]
    scale = np.linalg.norm(Z, axis=0)
    scale[scale == 0.0] = 1.0
    sol, *_ = np.linalg.lstsq(Z / scale, Y, rcond=None)     # Eq. (10), column-scaled
    phi = sol / scale[:, None]
    R = Y - Z @ phi
    dof = max(Y.shape[0] - Z.shape[1], 1)
    Sigma = (R.T @ R) / dof
    return phi, Sigma, inverse_normal_matrix(Z), float(np.sqrt(np.mean(R**2)))


def _map_fit(X: np.ndarray, U: np.ndarray, dt: float, to_continuous: Callable, method: str,
             lead: float) -> Identification:
    phi, Sigma, ZtZi, rms = _regress_map(X, U)

    def params_of(ph: np.ndarray) -> np.ndarray:
        A, b = to_continuous(ph[:4].T, ph[4], dt)
        return physical_from_continuous(A, b)

    p_vec = params_of(phi)
    p = params_from_vector(p_vec, lead, what=method)
    # Cov(vec phi) = Sigma (x) (Z^T Z)^-1; propagate by forward differences of phi -> log p
    # (relative step 1e-6: the Jacobian is good to ~1e-6, plenty for an interval).
    cov_log = None
    if np.all(np.isfinite(ZtZi)):
        flat = phi.ravel()              # index = 4 * regressor + output
        base = np.log(np.abs(p_vec))
        Jl = np.empty((4, flat.size))
        for i in range(flat.size):
            step = 1e-6 * abs(flat[i]) if flat[i] != 0.0 else 1e-9
            hi = flat.copy()
            hi[i] += step
            Jl[:, i] = (np.log(np.abs(params_of(hi.reshape(phi.shape)))) - base) / step
        cov_phi = np.kron(ZtZi, Sigma)   # ordering matches phi.ravel(): (regressor, output)
        cov_log = Jl @ cov_phi @ Jl.T
    # PE in deflection coordinates [d, dw, th2, w2, u]: rigid-body drift makes th1 and th2
    # nearly collinear, which says nothing about the information on the flexible mode.
    Zd = np.column_stack([X[:-1, 0] - X[:-1, 2], X[:-1, 1] - X[:-1, 3], X[:-1, 2], X[:-1, 3], U])
    info = {"rms_residual": rms, "n_samples": float(X.shape[0])}
    return build_identification(p, method, cov_log, excitation_report([Zd]), info,
                                bands=_bands(U, dt, to_continuous is continuous_from_zoh))


def fit_zoh(theta1: np.ndarray, omega1: np.ndarray, theta2: np.ndarray, omega2: np.ndarray,
            torque: np.ndarray, dt: float, *, lead: float = DEFAULT_LEAD) -> Identification:
    """Exact for zero-order-hold data: the paper's LS of Eq. (9) read through logm.

    Eq. (10): phi = [A^T A]^-1 A^T b on x_k+1 = phi^T [x_k; T_k], then Ad = phi[:4]^T,
    bd = phi[4] and A_c, b_c from :func:`continuous_from_zoh`, and (I1, I2, B, K) from
    :func:`physical_from_continuous`. Departure from the paper: Eq. (9) reads phi as
    I + A dt (forward Euler); here phi is exactly expm(A dt).
    """
    th1, w1, th2, w2, T = _signals(6, theta1=theta1, omega1=omega1, theta2=theta2, omega2=omega2,
                                   torque=torque)
    dt = _check_dt(dt)
    X = np.column_stack([th1, w1, th2, w2])
    return _map_fit(X, T[:-1], dt, continuous_from_zoh, "zoh", lead)


def fit_tustin_map(theta1: np.ndarray, omega1: np.ndarray, theta2: np.ndarray, omega2: np.ndarray,
                   torque: np.ndarray, dt: float, *, lead: float = DEFAULT_LEAD) -> Identification:
    """Exact for Newmark/trapezoidal data: LS of x_k+1 = Ad x_k + g (T_k + T_k+1), inverse Cayley.

    Same regression size as Eq. (9) with the torque column replaced by T_k + T_k+1
    (the trapezoidal rule needs the load at both ends of the step).
    """
    th1, w1, th2, w2, T = _signals(6, theta1=theta1, omega1=omega1, theta2=theta2, omega2=omega2,
                                   torque=torque)
    dt = _check_dt(dt)
    X = np.column_stack([th1, w1, th2, w2])
    return _map_fit(X, T[:-1] + T[1:], dt, continuous_from_tustin, "tustin", lead)


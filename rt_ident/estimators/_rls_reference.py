"""Plain-numpy side of :mod:`rt_ident.estimators.rls`: P0 parsing, UD factorisation, and the
reference implementations of one RLS sample (``compiled=False``), which the compiled kernels of
:mod:`._rls_kernels` must match to 1e-12 relative (tested). Same algorithms, same formulas
(see that module's docstring), vectorized with cumulative sums instead of loops.
"""

from __future__ import annotations

import math

import numpy as np

from rt_ident.errors import ConfigError
from rt_ident.estimators._rls_kernels import BOUNDED_TRACE, DIRECTIONAL

__all__ = ["cov_step_numpy", "parse_p0", "ud_factor", "ud_step_numpy"]


def parse_p0(p0: float | np.ndarray, n: int) -> np.ndarray:
    """Validated SPD initial covariance (n, n) from a scalar, a diagonal (n,) or a matrix (n, n)."""
    arr = np.asarray(p0, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ConfigError("p0", "must be finite")
    if arr.ndim == 0 or arr.shape == (n,):
        if np.any(arr <= 0):
            raise ConfigError("p0", f"diagonal entries must be > 0, got {p0!r}")
        return np.diag(np.broadcast_to(arr, (n,)).astype(float))
    if arr.shape != (n, n):
        raise ConfigError("p0", f"expected a scalar, shape ({n},) or ({n}, {n}), got {arr.shape}")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=0.0):
        raise ConfigError("p0", "matrix must be symmetric")
    P = 0.5 * (arr + arr.T)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ConfigError("p0", "matrix must be positive definite") from None
    return P


def ud_factor(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = U D U^T with U unit upper triangular (via Cholesky of the flipped matrix)."""
    J = P[::-1, ::-1]
    C = np.linalg.cholesky(J)  # J = C C^T, C lower; raises LinAlgError if not PD
    c = np.diag(C).copy()
    L = C / c  # unit lower
    U = np.ascontiguousarray(L[::-1, ::-1])
    d = np.ascontiguousarray((c * c)[::-1])
    return U, d


def _exclusive_colsum(U: np.ndarray, g: np.ndarray) -> np.ndarray:
    """W[:, j] = sum_{i<j} g_i U[:, i]."""
    W = np.zeros_like(U)
    W[:, 1:] = np.cumsum(U * g, axis=1)[:, :-1]
    return W


def _prior_error_numpy(theta: np.ndarray, phi: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(y))):
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        e = y - phi @ theta  # Eq. (14) bracket
    return e if np.all(np.isfinite(e)) else None


def ud_step_numpy(U: np.ndarray, d: np.ndarray, theta: np.ndarray, phi: np.ndarray, y: np.ndarray,
                  lam: float, variant: int, max_trace: float) -> bool:
    """Plain-numpy reference of the compiled UD step (vectorized with cumulative sums), in place."""
    e = _prior_error_numpy(theta, phi, y)
    if e is None:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        f = U.T @ phi
        g = d * f
        r = float(f @ g)
    if not math.isfinite(r):
        return False
    if variant == DIRECTIONAL:
        if lam < 1.0 and r > 0.0:
            c = (1.0 - lam) / (lam * r)
            W = _exclusive_colsum(U, g)
            w = g * g / d
            tail = np.zeros_like(w)  # tail[j] = sum_{i>j} g_i^2/d_i  ->  1/c_j = 1/c + tail[j]
            tail[:-1] = np.cumsum(w[::-1])[::-1][1:]
            cj = 1.0 / (1.0 / c + tail)
            dn = d + cj * g * g
            U += W * (cj * g / dn)
            d[:] = dn
            f = U.T @ phi
            g = d * f
    elif lam < 1.0 or variant == BOUNDED_TRACE:
        sc = 1.0 / lam
        if variant == BOUNDED_TRACE:
            tr = float(np.sum(d * np.sum(U * U, axis=0)))
            if tr * sc > max_trace:
                sc = max_trace / tr
        d *= sc
        g = g * sc
    # Eqs. (15)-(16), Bierman, vectorized
    alpha = 1.0 + np.cumsum(f * g)
    alpha_prev = np.empty_like(alpha)
    alpha_prev[0] = 1.0
    alpha_prev[1:] = alpha[:-1]
    W = _exclusive_colsum(U, g)
    K = (U @ g) / alpha[-1]  # Eq. (15)
    U += W * (-f / alpha_prev)
    d *= alpha_prev / alpha
    theta += np.outer(K, e)  # Eq. (14)
    return True


def cov_step_numpy(P: np.ndarray, theta: np.ndarray, phi: np.ndarray, y: np.ndarray,
                   lam: float, variant: int, max_trace: float) -> bool:
    """Plain-numpy reference of the compiled covariance step (Eqs. 14-16 with forgetting), in place."""
    e = _prior_error_numpy(theta, phi, y)
    if e is None:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        v = P @ phi
        r = float(phi @ v)
    if not math.isfinite(r):
        return False
    if variant == DIRECTIONAL:
        if lam < 1.0 and r > 0.0:
            a, b, c = 1.0, (r - (1.0 - lam)) / (r * (lam + r)), 1.0 / (lam + r)
        else:
            a, b, c = 1.0, 1.0 / (1.0 + r), 1.0 / (1.0 + r)
    else:
        s = 1.0 / lam
        tr = float(np.trace(P))
        if variant == BOUNDED_TRACE and tr * s > max_trace:
            s = max_trace / tr
        a, c = s, s / (1.0 + s * r)
        b = s * c
    theta += np.outer(c * v, e)                 # Eqs. (14)-(15)
    Pn = a * P - b * np.outer(v, v)             # Eq. (16), symmetric rank-one form
    P[:] = np.triu(Pn) + np.triu(Pn, 1).T       # exactly symmetric (upper triangle mirrored)
    return True

"""Kernels of :mod:`rt_ident.estimators.rls`: one RLS step on a UD-factored covariance.

State: ``P = U D U^T`` (U unit upper triangular (n, n), d = diag(D) (n,)), theta (n, q).
Two implementations of the same algorithm:

* ``step_nb`` / ``block_nb``: numba ``@njit(cache=True)`` loops, no allocation (work buffers
  are passed in);
* ``step_numpy``: a plain, vectorized numpy reference (cumulative sums instead of loops),
  used with ``compiled=False`` and to cross-check the compiled path.

Derivation (Bierman's UD measurement update). With f = U^T phi, g = D f,
a_0 = 1, a_j = a_{j-1} + f_j g_j (so a_n = 1 + phi^T P phi):
``D - g g^T / a_n = Ut D' Ut^T`` with ``d_j' = d_j a_{j-1}/a_j`` and ``Ut_ij = g_i p_j``
(i < j), ``p_j = -f_j/a_{j-1}``; the new U is ``U Ut``, i.e. column j gains
``p_j sum_{i<j} g_i U[:, i]``; the gain is ``K = U g / a_n`` (= P phi / (1 + phi^T P phi)).

Agee-Turner positive rank-one update (directional forgetting), P + c v v^T with v = P phi,
so U^-1 v = g: ``D + c g g^T = Ut D' Ut^T`` with, for j = n..1, ``d_j' = d_j + c_j g_j^2``,
``Ut_ij = c_j g_j g_i / d_j'``, ``c_{j-1} = c_j d_j / d_j'`` (c_n = c).
"""

from __future__ import annotations

import math

import numba
import numpy as np

STANDARD = 0
DIRECTIONAL = 1
BOUNDED_TRACE = 2
VARIANTS: dict[str, int] = {"standard": STANDARD, "directional": DIRECTIONAL, "bounded-trace": BOUNDED_TRACE}


# --------------------------------------------------------------------------- compiled path
@numba.njit(cache=True)
def _ut_phi(U: np.ndarray, d: np.ndarray, phi: np.ndarray, f: np.ndarray, g: np.ndarray) -> float:
    """f = U^T phi, g = D f; returns r = phi^T P phi = f^T D f."""
    n = U.shape[0]
    r = 0.0
    for j in range(n):
        s = phi[j]
        for i in range(j):
            s += U[i, j] * phi[i]
        f[j] = s
        g[j] = d[j] * s
        r += s * g[j]
    return r


@numba.njit(cache=True)
def _agee_turner(U: np.ndarray, d: np.ndarray, g: np.ndarray, c: float, W: np.ndarray) -> None:
    """In place: U D U^T <- U D U^T + c (U g)(U g)^T, c > 0 (stable: every d only grows)."""
    n = U.shape[0]
    # W[:, j] = sum_{i<j} g_i U[:, i] (prefix sums with the old columns)
    for i in range(n):
        W[i, 0] = 0.0
    for j in range(1, n):
        gj = g[j - 1]
        for i in range(n):
            W[i, j] = W[i, j - 1] + gj * U[i, j - 1]
    cj = c
    for j in range(n - 1, -1, -1):
        gj = g[j]
        dn = d[j] + cj * gj * gj
        coef = cj * gj / dn
        for i in range(j):
            U[i, j] += coef * W[i, j]
        cj = cj * d[j] / dn
        d[j] = dn


@numba.njit(cache=True)
def step_nb(U, d, theta, phi, y, f, g, k, e, W, lam, variant, max_trace):  # noqa: ANN001, ANN201
    """One RLS sample, in place. Returns False (state untouched) for a non-finite sample."""
    n = U.shape[0]
    q = theta.shape[1]
    for i in range(n):
        if not math.isfinite(phi[i]):
            return False
    for c in range(q):
        if not math.isfinite(y[c]):
            return False
    # Eq. (14) bracket: a-priori prediction error e = b - phi^T theta(t-1)
    for c in range(q):
        s = y[c]
        for i in range(n):
            s -= theta[i, c] * phi[i]
        if not math.isfinite(s):
            return False
        e[c] = s
    r = _ut_phi(U, d, phi, f, g)
    if not math.isfinite(r):
        return False

    # ---- forgetting (time update of P)
    if variant == DIRECTIONAL:
        if lam < 1.0 and r > 0.0:
            # R <- R - (1-lam) phi phi^T / r  <=>  P <- P + (1-lam)/(lam r) (P phi)(P phi)^T
            _agee_turner(U, d, g, (1.0 - lam) / (lam * r), W)
            _ut_phi(U, d, phi, f, g)
    else:
        if lam < 1.0:
            inv = 1.0 / lam  # P <- P / lambda
            for j in range(n):
                d[j] *= inv
                g[j] *= inv
        if variant == BOUNDED_TRACE:
            tr = 0.0
            for j in range(n):
                s = 1.0
                for i in range(j):
                    s += U[i, j] * U[i, j]
                tr += d[j] * s
            if tr > max_trace:
                sc = max_trace / tr
                for j in range(n):
                    d[j] *= sc
                    g[j] *= sc

    # ---- Eqs. (15)-(16), Bierman: k accumulates sum_{i<j} g_i U_old[:, i]
    # (one division per column: inv = 1/a_j is reused for p_{j+1} and d_j')
    alpha = 1.0
    inv = 1.0
    for i in range(n):
        k[i] = 0.0
    for j in range(n):
        fj = f[j]
        gj = g[j]
        p = -fj * inv
        alpha_new = alpha + fj * gj
        inv_new = 1.0 / alpha_new
        d[j] = d[j] * (alpha * inv_new)
        for i in range(j):
            uij = U[i, j]
            U[i, j] = uij + p * k[i]
            k[i] += gj * uij
        k[j] += gj
        alpha = alpha_new
        inv = inv_new
    # Eq. (15): K = P phi / (1 + phi^T P phi);  Eq. (14): theta += K e^T
    for i in range(n):
        ki = k[i] * inv
        for c in range(q):
            theta[i, c] += ki * e[c]
    return True


@numba.njit(cache=True)
def block_nb(U, d, theta, Phi, Y, f, g, k, e, W, lam, variant, max_trace, hist, hpos, record):  # noqa: ANN001, ANN201
    """Rows of Phi/Y in order; records theta into the ring buffer ``hist`` if ``record``.

    Returns (accepted count, new history position).
    """
    acc = 0
    H = hist.shape[0]
    for t in range(Phi.shape[0]):
        if step_nb(U, d, theta, Phi[t], Y[t], f, g, k, e, W, lam, variant, max_trace):
            acc += 1
            if record:
                hist[hpos % H, :, :] = theta
                hpos += 1
    return acc, hpos


# --------------------------------------------------------------------------- numpy reference
def _exclusive_colsum(U: np.ndarray, g: np.ndarray) -> np.ndarray:
    """W[:, j] = sum_{i<j} g_i U[:, i]."""
    W = np.zeros_like(U)
    W[:, 1:] = np.cumsum(U * g, axis=1)[:, :-1]
    return W


def step_numpy(U: np.ndarray, d: np.ndarray, theta: np.ndarray, phi: np.ndarray, y: np.ndarray,
               lam: float, variant: int, max_trace: float) -> bool:
    """Plain-numpy reference of :func:`step_nb` (vectorized with cumulative sums)."""
    if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(y))):
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        e = y - phi @ theta  # Eq. (14) bracket
        f = U.T @ phi
        g = d * f
        r = float(f @ g)
    if not (np.all(np.isfinite(e)) and math.isfinite(r)):
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
    else:
        if lam < 1.0:
            d /= lam
            g = g / lam
        if variant == BOUNDED_TRACE:
            tr = float(np.sum(d * np.sum(U * U, axis=0)))
            if tr > max_trace:
                d *= max_trace / tr
                g = g * (max_trace / tr)
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

"""Recursive least squares, Eqs. (14)-(16) of the paper, in factored (UD) form.

The paper's recursion (Theorem 1), for a regressor vector ``phi`` (n,) shared by all
outputs and a target row ``b`` (q,)::

    # Eq. (15): K = P phi [I + phi^T P phi]^-1   (a scalar denominator: one regressor row)
    # Eq. (14): theta = theta + K (b - phi^T theta)
    # Eq. (16): P = (I - K phi^T) P

All q outputs share one regressor, hence one n x n matrix P (the paper's phi is 5 x 4:
five regressors, four next states).

Numerically robust form (departure from the paper, same estimates in exact arithmetic):
P is never stored. It is kept as ``P = U D U^T`` with U unit upper triangular and D
diagonal, and Eq. (16) is carried out by Bierman's UD measurement update. Why this
form rather than Joseph form or symmetrizing: every new diagonal entry is a product of
positive ratios (``d_j' = d_j a_{j-1}/a_j`` with ``a_j`` increasing), so P stays
symmetric positive definite *by construction*, whatever the rounding, and U/D carry
roughly the square root of P's condition number. Measured: regressors scaled like the
paper's (angle columns 1e-3, nearly collinear, next to velocity columns 1e2) with lambda =
0.999 reach cond(P) ~ 1e18, where the plain Eq. (16) subtraction (even symmetrized) gave an
indefinite P at 30 % of the checkpoints while the UD factors stayed positive. Joseph form
was rejected: it is symmetric but still subtracts, so it has no such guarantee. Cost is
O(n^2) per sample like Eq. (16).

Forgetting (lambda = ``forgetting``):

* ``"standard"``: exponential forgetting, P <- P / lambda before each update. With no
  excitation P grows as lambda^-t (wind-up).
* ``"directional"``: forget only along the excited direction (Kulhavy & Karny 1984,
  Bittanti et al. 1990): the information matrix R = P^-1 loses the fraction (1 - lambda)
  of its rank-one part along phi, ``R <- R - (1 - lambda) phi phi^T / (phi^T P phi)``, i.e.
  ``P <- P + (1 - lambda)/(lambda r) P phi phi^T P`` with r = phi^T P phi (a positive
  rank-one UD update, Agee-Turner). The gain becomes ``P phi / (lambda + r)`` as with
  exponential forgetting, but directions that are not excited keep their information,
  so P does not wind up when excitation stops (phi = 0 changes nothing).
* ``"bounded-trace"``: exponential forgetting, then P is rescaled so trace(P) <= max_trace
  (default trace(P0)).

A sample with a non-finite phi or y (or whose prediction error or phi^T P phi overflows)
is rejected, counted in ``n_rejected``, and leaves the state untouched.
"""

from __future__ import annotations

import logging
import math

import numba
import numpy as np
import scipy.linalg

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators._rls_kernels import (
    VARIANTS,
    block_nb,
    step_nb,
    step_numpy,
)

log = logging.getLogger(__name__)

__all__ = ["RecursiveLeastSquares", "warmup", "VARIANTS"]


def _ud_factor(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = U D U^T with U unit upper triangular (via Cholesky of the flipped matrix)."""
    J = P[::-1, ::-1]
    C = np.linalg.cholesky(J)  # J = C C^T, C lower; raises LinAlgError if not PD
    c = np.diag(C).copy()
    L = C / c  # unit lower
    U = np.ascontiguousarray(L[::-1, ::-1])
    d = np.ascontiguousarray((c * c)[::-1])
    return U, d


class RecursiveLeastSquares:
    """Recursive least squares with one covariance P shared by ``n_outputs`` outputs.

    Parameters
    ----------
    n_regressors : length n of the regressor vector phi.
    n_outputs : number q of targets per sample (theta is n x q).
    p0 : initial P: a scalar (P0 = p0 I), a length-n vector (diagonal) or an n x n SPD matrix.
    theta0 : initial estimate, shape (n, q) (or (n,) when q == 1); default zeros.
    forgetting : lambda in (0, 1]; 1 = no forgetting (Theorem 1).
    variant : "standard" | "directional" | "bounded-trace" (see module docstring).
    max_trace : trace bound for "bounded-trace" (default trace(P0)); not allowed otherwise.
    history : keep the last ``history`` estimates (0 = none, -1 = all; the unbounded buffer
        grows by doubling, so that mode allocates now and then).
    compiled : use the numba kernels (default) or the plain-numpy reference path.
    """

    def __init__(
        self,
        n_regressors: int,
        n_outputs: int = 1,
        *,
        p0: float | np.ndarray = 1e6,
        theta0: np.ndarray | None = None,
        forgetting: float = 1.0,
        variant: str = "standard",
        max_trace: float | None = None,
        history: int = 0,
        compiled: bool = True,
    ) -> None:
        for name, val in (("n_regressors", n_regressors), ("n_outputs", n_outputs)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 1:
                raise ConfigError(name, f"must be an integer >= 1, got {val!r}")
        if not isinstance(forgetting, (int, float)) or not (0.0 < float(forgetting) <= 1.0):
            raise ConfigError("forgetting", f"must be in (0, 1], got {forgetting!r}")
        if variant not in VARIANTS:
            raise ConfigError("variant", f"must be one of {sorted(VARIANTS)}, got {variant!r}")
        if max_trace is not None:
            if variant != "bounded-trace":
                raise ConfigError("max_trace", f"only used by variant 'bounded-trace', not {variant!r}")
            if not (isinstance(max_trace, (int, float)) and math.isfinite(max_trace) and max_trace > 0):
                raise ConfigError("max_trace", f"must be a finite number > 0, got {max_trace!r}")
        if isinstance(history, bool) or not isinstance(history, (int, np.integer)) or history < -1:
            raise ConfigError("history", f"must be an integer >= -1, got {history!r}")
        self._n = int(n_regressors)
        self._q = int(n_outputs)
        self._lam = float(forgetting)
        self._variant = variant
        self._vcode = VARIANTS[variant]
        self._max_trace_arg = None if max_trace is None else float(max_trace)
        self._history_len = int(history)
        self._compiled = bool(compiled)
        n, q = self._n, self._q
        # preallocated work buffers for the kernels (the per-sample path allocates nothing)
        self._f = np.zeros(n)
        self._g = np.zeros(n)
        self._k = np.zeros(n)
        self._e = np.zeros(q)
        self._W = np.zeros((n, n))
        self._ybuf = np.zeros(q)
        self._dummy_hist = np.zeros((1, n, q))
        self.reset(theta0=theta0, p0=p0)

    # ------------------------------------------------------------------ state
    def reset(self, *, theta0: np.ndarray | None = None, p0: float | np.ndarray | None = None) -> None:
        """Restart from ``theta0`` / ``p0`` (p0=None keeps the constructor's P0)."""
        n, q = self._n, self._q
        if p0 is not None:
            self._U0, self._d0 = self._parse_p0(p0)
        self._U = self._U0.copy()
        self._d = self._d0.copy()
        self._max_trace = self._max_trace_arg if self._max_trace_arg is not None else float(
            np.sum(self._d0 * np.sum(self._U0**2, axis=0))
        )
        if theta0 is None:
            self._theta = np.zeros((n, q))
        else:
            t = np.asarray(theta0, dtype=float)
            if t.shape == (n,) and q == 1:
                t = t.reshape(n, 1)
            if t.shape != (n, q):
                raise ConfigError("theta0", f"expected shape ({n}, {q}), got {t.shape}")
            if not np.all(np.isfinite(t)):
                raise ConfigError("theta0", "must be finite")
            self._theta = np.ascontiguousarray(t).copy()
        self.n_updates = 0
        self.n_rejected = 0
        H = self._history_len
        cap = 1024 if H == -1 else max(H, 1)
        self._hist = np.zeros((cap, n, q)) if H != 0 else self._dummy_hist
        self._hpos = 0

    def _parse_p0(self, p0: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self._n
        arr = np.asarray(p0, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ConfigError("p0", "must be finite")
        if arr.ndim == 0 or arr.shape == (n,):
            if np.any(arr <= 0):
                raise ConfigError("p0", f"diagonal entries must be > 0, got {p0!r}")
            return np.eye(n), np.broadcast_to(arr, (n,)).astype(float).copy()
        if arr.shape != (n, n):
            raise ConfigError("p0", f"expected a scalar, shape ({n},) or ({n}, {n}), got {arr.shape}")
        if not np.allclose(arr, arr.T, rtol=1e-10, atol=0.0):
            raise ConfigError("p0", "matrix must be symmetric")
        try:
            return _ud_factor(0.5 * (arr + arr.T))
        except np.linalg.LinAlgError:
            raise ConfigError("p0", "matrix must be positive definite") from None

    # ------------------------------------------------------------- properties
    @property
    def n_regressors(self) -> int:
        return self._n

    @property
    def n_outputs(self) -> int:
        return self._q

    @property
    def variant(self) -> str:
        return self._variant

    @property
    def forgetting(self) -> float:
        return self._lam

    @property
    def compiled(self) -> bool:
        return self._compiled

    @property
    def max_trace(self) -> float | None:
        return self._max_trace if self._variant == "bounded-trace" else None

    @property
    def theta(self) -> np.ndarray:
        """Current estimate (n, q), a read-only view (copy it to keep it)."""
        v = self._theta.view()
        v.flags.writeable = False
        return v

    @property
    def P(self) -> np.ndarray:
        """Covariance P = U D U^T (n, n), a new exactly-symmetric array."""
        P = (self._U * self._d) @ self._U.T
        return 0.5 * (P + P.T)

    @property
    def trace_P(self) -> float:
        return float(np.sum(self._d * np.sum(self._U**2, axis=0)))

    def information_matrix(self) -> np.ndarray:
        """R = P^-1 = U^-T D^-1 U^-1 (the forgetting-weighted sum of phi phi^T plus P0^-1)."""
        Ui = scipy.linalg.solve_triangular(self._U, np.eye(self._n), lower=False, unit_diagonal=True)
        R = (Ui.T / self._d) @ Ui
        return 0.5 * (R + R.T)

    @property
    def min_eig(self) -> float:
        """Smallest eigenvalue of the information matrix (persistence of excitation), = 1/max eig(P)."""
        return float(1.0 / np.linalg.eigvalsh(self.P)[-1])

    @property
    def condition_number(self) -> float:
        """cond(P) = cond(P^-1), from the largest eigenvalues of P and of P^-1 (both well determined)."""
        return float(np.linalg.eigvalsh(self.P)[-1] * np.linalg.eigvalsh(self.information_matrix())[-1])

    @property
    def history(self) -> np.ndarray:
        """Recorded estimates, oldest first: (k, n, q). Empty when history=0."""
        if self._history_len == 0 or self._hpos == 0:
            return np.zeros((0, self._n, self._q))
        H = self._hist.shape[0]
        if self._hpos <= H:
            return self._hist[: self._hpos].copy()
        idx = (self._hpos + np.arange(H)) % H
        return self._hist[idx]

    def predict(self, phi: np.ndarray) -> np.ndarray:
        """phi^T theta for one regressor (n,) -> (q,) or a block (m, n) -> (m, q)."""
        return np.asarray(phi, dtype=float) @ self._theta

    # ---------------------------------------------------------------- updates
    def _grow_history(self, extra: int) -> None:
        if self._history_len == -1 and self._hpos + extra > self._hist.shape[0]:
            cap = max(2 * self._hist.shape[0], self._hpos + extra)
            new = np.zeros((cap, self._n, self._q))
            new[: self._hpos] = self._hist[: self._hpos]
            self._hist = new

    def update(self, phi: np.ndarray, y: np.ndarray | float) -> bool:
        """Fold in one sample (Eqs. 14-16). Returns False (and counts it) if rejected as non-finite."""
        n, q = self._n, self._q
        if not (type(phi) is np.ndarray and phi.dtype == np.float64 and phi.flags.c_contiguous
                and phi.flags.writeable):
            phi = np.array(phi, dtype=float)
        if phi.shape != (n,):
            raise DataError(f"phi: expected shape ({n},), got {phi.shape}")
        if type(y) is np.ndarray and y.dtype == np.float64 and y.shape == (q,) and y.flags.c_contiguous \
                and y.flags.writeable:
            yv = y
        elif q == 1 and np.ndim(y) <= 1 and np.size(y) == 1:
            self._ybuf[0] = y if np.ndim(y) == 0 else y[0]  # type: ignore[index]
            yv = self._ybuf
        else:
            yv = np.array(y, dtype=float)
            if yv.shape != (q,):
                raise DataError(f"y: expected shape ({q},), got {yv.shape}")
        if self._compiled:
            ok = step_nb(self._U, self._d, self._theta, phi, yv, self._f, self._g, self._k, self._e,
                         self._W, self._lam, self._vcode, self._max_trace)
        else:
            ok = step_numpy(self._U, self._d, self._theta, phi, yv, self._lam, self._vcode, self._max_trace)
        if not ok:
            self.n_rejected += 1
            return False
        self.n_updates += 1
        if self._history_len != 0:
            self._grow_history(1)
            self._hist[self._hpos % self._hist.shape[0]] = self._theta
            self._hpos += 1
        return True

    def update_block(self, Phi: np.ndarray, Y: np.ndarray) -> int:
        """Fold in the rows of ``Phi`` (m, n) / ``Y`` (m, q) (or (m,) when q == 1) in order.

        Returns the number of accepted samples; the others (non-finite) are counted in
        ``n_rejected``.
        """
        n, q = self._n, self._q
        Phi = np.asarray(Phi, dtype=float)
        Y = np.asarray(Y, dtype=float)
        if Phi.ndim != 2 or Phi.shape[1] != n:
            raise DataError(f"Phi: expected shape (m, {n}), got {Phi.shape}")
        m = Phi.shape[0]
        if q == 1 and Y.shape == (m,):
            Y = Y.reshape(m, 1)
        if Y.shape != (m, q):
            raise DataError(f"Y: expected shape ({m}, {q}) to match Phi {Phi.shape}, got {Y.shape}")
        if m == 0:
            return 0
        if not (Phi.flags.c_contiguous and Phi.flags.writeable):
            Phi = np.array(Phi, order="C")
        if not (Y.flags.c_contiguous and Y.flags.writeable):
            Y = np.array(Y, order="C")
        record = self._history_len != 0
        if record:
            self._grow_history(m)
        if self._compiled:
            acc, hpos = block_nb(self._U, self._d, self._theta, Phi, Y, self._f, self._g, self._k, self._e,
                                 self._W, self._lam, self._vcode, self._max_trace, self._hist, self._hpos, record)
        else:
            acc, hpos = 0, self._hpos
            H = self._hist.shape[0]
            for t in range(m):
                if step_numpy(self._U, self._d, self._theta, Phi[t], Y[t], self._lam, self._vcode,
                              self._max_trace):
                    acc += 1
                    if record:
                        self._hist[hpos % H] = self._theta
                        hpos += 1
        self._hpos = int(hpos)
        self.n_updates += int(acc)
        self.n_rejected += m - int(acc)
        if m - acc:
            log.debug("RLS: rejected %d non-finite samples out of %d", m - acc, m)
        return int(acc)

    def __repr__(self) -> str:
        return (f"RecursiveLeastSquares(n_regressors={self._n}, n_outputs={self._q}, variant={self._variant!r}, "
                f"forgetting={self._lam}, n_updates={self.n_updates}, n_rejected={self.n_rejected})")


def warmup() -> None:
    """Compile (or load from numba's cache) the RLS kernels on tiny data.

    Call once at start-up so the first real ``update``/``update_block`` is not the compile.
    """
    rng = np.random.default_rng(0)
    for variant in VARIANTS:
        est = RecursiveLeastSquares(2, 2, forgetting=0.99, variant=variant, history=4)
        Phi = rng.standard_normal((4, 2))
        est.update_block(Phi, Phi @ np.ones((2, 2)))
        est.update(Phi[0].copy(), np.ones(2))
        est1 = RecursiveLeastSquares(2, 1, variant=variant)
        est1.update(Phi[0].copy(), 1.0)
    log.debug("RLS kernels ready (numba %s)", numba.__version__)

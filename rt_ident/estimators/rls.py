"""Recursive least squares, Eqs. (14)-(16) of the paper, in UD-factored or covariance form.

The paper's recursion (Theorem 1), for a regressor vector ``phi`` (n,) shared by all
outputs and a target row ``b`` (q,)::

    # Eq. (15): K = P phi [I + phi^T P phi]^-1   (a scalar denominator: one regressor row)
    # Eq. (14): theta = theta + K (b - phi^T theta)
    # Eq. (16): P = (I - K phi^T) P

All q outputs share one regressor, hence one n x n matrix P (the paper's phi is 5 x 4:
five regressors, four next states).

Two storage forms of P (``form=``), same estimates in exact arithmetic:

* ``"ud"`` (default; departure from the paper): P is kept as ``P = U D U^T`` (U unit upper
  triangular, D diagonal) and Eq. (16) is Bierman's UD measurement update. Every new
  diagonal entry is a product of positive ratios (``d_j' = d_j a_{j-1}/a_j``, ``a_j``
  increasing), so P is symmetric positive definite *by construction*, whatever the
  rounding, and U/D carry roughly the square root of P's condition number.
* ``"covariance"``: Eq. (16) on the full P, as the symmetric rank-one update
  ``P <- a P - b v v^T`` (v = P phi, forgetting folded into a and b) on the upper triangle,
  mirrored: exactly symmetric, but with no definiteness guarantee (Joseph form was
  rejected for the same reason: symmetric, but it still subtracts).

Why "ud" is the default: regressors scaled like the paper's (angle columns 1e-3, nearly
collinear, next to velocity columns 1e2) with lambda = 0.999 reach cond(P) ~ 1e18; there
the covariance form held an indefinite P at 30-40 % of the checkpoints while the UD
factors stayed positive (tested). And robustness costs nothing here: with n, q compiled
in, the 5 x 4 UD kernel measured ~35 ns per sample against ~42 ns for the covariance
kernel (fewer multiply-adds: U is triangular). Use ``"covariance"`` on well-scaled
regressors when P itself is wanted every sample, or as a cross-check.

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
from numpy.typing import ArrayLike

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators._rls_kernels import VARIANTS, block_kernel, layout, update_kernel
from rt_ident.estimators._rls_reference import cov_step_numpy, parse_p0, ud_factor, ud_step_numpy

log = logging.getLogger(__name__)

__all__ = ["RecursiveLeastSquares", "warmup", "VARIANTS", "FORMS"]

FORMS: tuple[str, ...] = ("ud", "covariance")


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
    form : "ud" (default, P = U D U^T: positive definite by construction) or "covariance"
        (full symmetric P, Eq. 16 as written; see the module docstring for the trade-off).

    The whole state lives in one contiguous vector (see :mod:`._rls_kernels`). ``update``
    hands it to a shape-specialised compiled kernel with phi and y: no copy and no allocation
    when phi and y are C-contiguous writeable float64 arrays of the right shape (or y is a
    float and q == 1); measured ~1 us per call, ~35 ns per sample in ``update_block`` (5 x 4).
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
        form: str = "ud",
    ) -> None:
        for name, val in (("n_regressors", n_regressors), ("n_outputs", n_outputs)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 1:
                raise ConfigError(name, f"must be an integer >= 1, got {val!r}")
        if not isinstance(forgetting, (int, float)) or not (0.0 < float(forgetting) <= 1.0):
            raise ConfigError("forgetting", f"must be in (0, 1], got {forgetting!r}")
        if variant not in VARIANTS:
            raise ConfigError("variant", f"must be one of {sorted(VARIANTS)}, got {variant!r}")
        if form not in FORMS:
            raise ConfigError("form", f"must be one of {list(FORMS)}, got {form!r}")
        if max_trace is not None:
            if variant != "bounded-trace":
                raise ConfigError("max_trace", f"only used by variant 'bounded-trace', not {variant!r}")
            if not (isinstance(max_trace, (int, float)) and math.isfinite(max_trace) and max_trace > 0):
                raise ConfigError("max_trace", f"must be a finite number > 0, got {max_trace!r}")
        if isinstance(history, bool) or not isinstance(history, (int, np.integer)) or history < -1:
            raise ConfigError("history", f"must be an integer >= -1, got {history!r}")
        self._n = n = int(n_regressors)
        self._q = q = int(n_outputs)
        self._lam = float(forgetting)
        self._variant = variant
        self._vcode = VARIANTS[variant]
        self._form = form
        self._ud = form == "ud"
        self._max_trace_arg = None if max_trace is None else float(max_trace)
        self._history_len = int(history)
        self._compiled = bool(compiled)
        self._shape_n = (n,)
        self._shape_q = (q,)
        # packed state: header, U or P, d, theta, kernel scratch (views below share its memory)
        self._S = np.zeros(layout(n, q)["size"][1])
        self._bind()
        self._ybuf = np.zeros(q)
        self._dummy_hist = np.zeros((1, n, q))
        self.reset(theta0=theta0, p0=p0)

    def _bind(self) -> None:
        """Views into the packed state and the compiled kernels for this (form, n, q)."""
        n, q = self._n, self._q
        lay = layout(n, q)
        self._M = self._S[slice(*lay["M"])].reshape(n, n)      # U (UD form) or P
        self._d = self._S[slice(*lay["d"])]
        self._theta = self._S[slice(*lay["theta"])].reshape(n, q)
        self._update_kernel = self._first_update                 # compiled (or loaded) on first use
        self._block_kernel = block_kernel(self._form, n, q)

    def _first_update(self, S: np.ndarray, phi: np.ndarray, y: np.ndarray) -> bool:
        self._update_kernel = update_kernel(self._form, self._n, self._q)
        return self._update_kernel(S, phi, y)

    def __getstate__(self) -> dict:
        """Copy/pickle the packed state only: views and kernels are rebuilt on the copy."""
        state = self.__dict__.copy()
        for key in ("_M", "_d", "_theta", "_update_kernel", "_block_kernel"):
            del state[key]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._bind()

    # ------------------------------------------------------------------ state
    def reset(self, *, theta0: np.ndarray | None = None, p0: float | np.ndarray | None = None) -> None:
        """Restart from ``theta0`` / ``p0`` (p0=None keeps the constructor's P0)."""
        n, q = self._n, self._q
        if p0 is not None:
            self._P0 = parse_p0(p0, n)
            self._U0, self._d0 = ud_factor(self._P0)
        if self._ud:
            self._M[:] = self._U0
            self._d[:] = self._d0
        else:
            self._M[:] = self._P0
            self._d[:] = 0.0
        self._max_trace = self._max_trace_arg if self._max_trace_arg is not None else float(np.trace(self._P0))
        self._S[0] = self._lam
        self._S[1] = self._vcode
        self._S[2] = self._max_trace
        if theta0 is None:
            self._theta[:] = 0.0
        else:
            t = np.asarray(theta0, dtype=float)
            if t.shape == (n,) and q == 1:
                t = t.reshape(n, 1)
            if t.shape != (n, q):
                raise ConfigError("theta0", f"expected shape ({n}, {q}), got {t.shape}")
            if not np.all(np.isfinite(t)):
                raise ConfigError("theta0", "must be finite")
            self._theta[:] = t
        self.n_updates = 0
        self.n_rejected = 0
        H = self._history_len
        cap = 1024 if H == -1 else max(H, 1)
        self._hist = np.zeros((cap, n, q)) if H != 0 else self._dummy_hist
        self._hpos = 0

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
    def form(self) -> str:
        return self._form

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
        """Covariance P (n, n), a new exactly-symmetric array (U D U^T in the UD form)."""
        if not self._ud:
            return self._M.copy()
        P = (self._M * self._d) @ self._M.T
        return 0.5 * (P + P.T)

    @property
    def trace_P(self) -> float:
        if not self._ud:
            return float(np.trace(self._M))
        return float(np.sum(self._d * np.sum(self._M**2, axis=0)))

    def information_matrix(self) -> np.ndarray:
        """R = P^-1 (the forgetting-weighted sum of phi phi^T plus P0^-1); U^-T D^-1 U^-1 in UD form."""
        if self._ud:
            Ui = scipy.linalg.solve_triangular(self._M, np.eye(self._n), lower=False, unit_diagonal=True)
            R: np.ndarray = (Ui.T / self._d) @ Ui
        else:
            R = np.linalg.inv(self._M)
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

    def _reference_step(self, phi: np.ndarray, y: np.ndarray) -> bool:
        """The plain-numpy path (``compiled=False``) on the same packed state."""
        if self._ud:
            return ud_step_numpy(self._M, self._d, self._theta, phi, y, self._lam, self._vcode, self._max_trace)
        return cov_step_numpy(self._M, self._theta, phi, y, self._lam, self._vcode, self._max_trace)

    def _coerce_phi(self, phi: ArrayLike) -> np.ndarray:
        out = np.array(phi, dtype=float)  # a C-contiguous writeable copy
        if out.shape != self._shape_n:
            raise DataError(f"phi: expected shape ({self._n},), got {out.shape}")
        return out

    def _coerce_y(self, y: ArrayLike) -> np.ndarray:
        if self._q == 1 and np.ndim(y) <= 1 and np.size(y) == 1:
            self._ybuf[0] = y if np.ndim(y) == 0 else y[0]  # type: ignore[index]
            return self._ybuf
        out = np.array(y, dtype=float)
        if out.shape != self._shape_q:
            raise DataError(f"y: expected shape ({self._q},), got {out.shape}")
        return out

    def update(self, phi: np.ndarray, y: np.ndarray | float) -> bool:
        """Fold in one sample (Eqs. 14-16). Returns False (and counts it) if rejected as non-finite.

        Fast path (no copy, no allocation): C-contiguous writeable float64 ``phi`` (n,) and
        ``y`` (q,); anything else (lists, other dtypes or layouts, a float ``y`` when q == 1)
        is converted first.
        """
        try:
            if not isinstance(y, np.ndarray) or phi.shape != self._shape_n or y.shape != self._shape_q:
                raise TypeError
            if self._compiled:   # the kernel accepts exactly float64[::1] (else TypeError)
                ok = self._update_kernel(self._S, phi, y)
            else:
                ok = self._reference_step(phi, y)
        except (TypeError, AttributeError):
            phi = self._coerce_phi(phi)
            y = self._coerce_y(y)
            ok = self._update_kernel(self._S, phi, y) if self._compiled else self._reference_step(phi, y)
        if not ok:
            self.n_rejected += 1
            return False
        self.n_updates += 1
        if self._history_len:
            self._grow_history(1)
            self._hist[self._hpos % self._hist.shape[0]] = self._theta
            self._hpos += 1
        return True

    def update_block(self, Phi: np.ndarray, Y: np.ndarray) -> int:
        """Fold in the rows of ``Phi`` (m, n) / ``Y`` (m, q) (or (m,) when q == 1) in order.

        Returns the number of accepted samples; the others (non-finite) are counted in
        ``n_rejected``. C-contiguous writeable float64 inputs are used without a copy.
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
        if not Phi.flags.carray:
            Phi = np.array(Phi, order="C")
        if not Y.flags.carray:
            Y = np.array(Y, order="C")
        record = self._history_len != 0
        if record:
            self._grow_history(m)
        if self._compiled:
            acc, hpos = self._block_kernel(self._S, Phi, Y, self._hist, self._hpos, record)
        else:
            acc, hpos = 0, self._hpos
            H = self._hist.shape[0]
            for t in range(m):
                if self._reference_step(Phi[t], Y[t]):
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
                f"form={self._form!r}, forgetting={self._lam}, n_updates={self.n_updates}, "
                f"n_rejected={self.n_rejected})")


def warmup(shapes: tuple[tuple[int, int], ...] = ((5, 4),), forms: tuple[str, ...] = FORMS) -> None:
    """Compile (or load from numba's cache) the RLS kernels for these (n_regressors, n_outputs).

    Call once at start-up so the first real ``update``/``update_block`` is not the compile.
    The default is the paper's 5 x 4 problem (Eq. 9) in both forms.
    """
    for n, q in shapes:
        rng = np.random.default_rng(0)
        Phi = rng.standard_normal((4, n))
        Y = Phi @ np.ones((n, q))
        for form in forms:
            est = RecursiveLeastSquares(n, q, forgetting=0.99, history=2, form=form)
            est.update_block(Phi, Y)
            est.update(Phi[0].copy(), Y[0].copy())
    log.debug("RLS kernels ready for %s (numba %s)", shapes, numba.__version__)

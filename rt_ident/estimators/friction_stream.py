"""The friction models of :mod:`rt_ident.estimators.friction` per sample, for the loop: the batch fit's rows
accumulated sample by sample in information form with exponential forgetting, in one compiled kernel
(:class:`RecursiveFrictionEstimator`)."""

from __future__ import annotations

import copy
import math

import numba
import numpy as np
import scipy.linalg

from rt_ident.errors import ConfigError
from rt_ident.estimators.friction import MODELS, check_model, impulse_response, svf_filters


def _row_maps(key: str) -> tuple[np.ndarray, np.ndarray]:
    """(C, E) of a model: C (neq, p, 6) maps the filtered angle states (F, sF, s^2F of th1, then th2)
    to each row's regressors; E (neq, p) names the noise-free column (0 none, 1 F[1], 2 F[sgn v1],
    3 F[sgn v2]). Same rows as :func:`~rt_ident.estimators.friction.fit_friction`."""
    p = len(MODELS[key])
    if key == "rigid-friction":
        C = np.zeros((1, p, 6))
        C[0, 0, 2] = 1.0
        C[0, 1, 1] = 1.0
        E = np.array([[0, 0, 2, 1]], dtype=np.int64)
        return C, E
    C = np.zeros((2, p, 6))
    E = np.zeros((2, p), dtype=np.int64)
    C[0, 0, 2] = 1.0
    C[0, 2, 1], C[0, 2, 4] = 1.0, -1.0
    C[0, 3, 0], C[0, 3, 3] = 1.0, -1.0
    C[1, 0, 2] = 1.0
    C[1, 1, 5] = 1.0
    E[0, p - 1] = E[1, p - 1] = 1
    if key == "two-inertia-friction":
        C[0, 5, 1] = C[1, 5, 1] = 1.0
        C[1, 7, 4] = 1.0
        E[0, 4] = E[1, 4] = 2
        E[1, 6] = 3
    return C, E


def _rfs_block_py(th1, th2, tq, X, last, Phi, G0, G1, Gz, C, E, lamf, db, n_gate, n_warm, fv, R, r,
                  rbuf, ybuf, okbuf):
    """Advance the recursive friction estimator over one block (in place).

    X (6, 3): filter states of th1, th2 (FOH), torque, 1, sgn v1, sgn v2 (ZOH);
    last (12,): [th1, th2, torque, sgn1, sgn2, has_prev, gate1, gate2, samples, weight, v1 ms, v2 ms].
    db (2,): dead bands from the sensor noise (at least 2 % of the running rms velocity is used);
    fv: forgetting of that running mean square.
    rbuf (L, neq, p), ybuf (L,), okbuf (L,): rows wait L samples (the causal sign's lag) before they
    enter (R, r); a standstill sample in that time discards them (their sign may have been stale)."""
    n = th1.shape[0]
    neq = C.shape[0]
    p = C.shape[1]
    L = ybuf.shape[0]
    two_fric = neq == 2 and p == 9
    xn = np.empty(3)
    for k in range(n):
        a1 = th1[k]
        a2 = th2[k]
        u = tq[k]
        if not (math.isfinite(a1) and math.isfinite(a2) and math.isfinite(u)):
            continue
        if last[5] == 0.0:
            last[0] = a1
            last[1] = a2
            last[2] = u
            last[5] = 1.0
            continue
        # advance every filter from the previous sample to this one
        for f in range(6):
            if f == 0:
                uk, uk1 = last[0], a1
            elif f == 1:
                uk, uk1 = last[1], a2
            elif f == 2:
                uk, uk1 = last[2], last[2]
            elif f == 3:
                uk, uk1 = 1.0, 1.0
            elif f == 4:
                uk, uk1 = last[3], last[3]
            else:
                uk, uk1 = last[4], last[4]
            for i in range(3):
                acc = Phi[i, 0] * X[f, 0] + Phi[i, 1] * X[f, 1] + Phi[i, 2] * X[f, 2]
                if f < 2:
                    acc += G0[i] * uk + G1[i] * (uk1 - uk)
                else:
                    acc += Gz[i] * uk
                xn[i] = acc
            for i in range(3):
                X[f, i] = xn[i]
        last[0] = a1
        last[1] = a2
        last[2] = u
        last[8] += 1.0
        # the sign of the (causal) filtered velocity, with the dead band; gates count samples since standstill
        event = False
        for b in range(2):
            v = X[b, 1]
            last[10 + b] = fv * last[10 + b] + (1.0 - fv) * v * v
            band = max(db[b], 0.02 * math.sqrt(last[10 + b]))
            if abs(v) > band:
                last[3 + b] = 1.0 if v > 0.0 else -1.0
                last[6 + b] += 1.0
            else:
                last[3 + b] = 0.0
                last[6 + b] = 0.0
                if b == 0 or two_fric:
                    event = True
        if event:
            for i in range(L):
                okbuf[i] = 0.0
        # the row of L samples ago enters now (forgetting applies per sample from here)
        slot = int(last[8]) % L
        if okbuf[slot] != 0.0:
            for ii in range(p):
                for jj in range(p):
                    R[ii, jj] *= lamf
                r[ii] *= lamf
            last[9] = lamf * last[9] + 1.0
            yo = ybuf[slot]
            for e in range(neq):
                for ii in range(p):
                    ri = rbuf[slot, e, ii]
                    r[ii] += ri * yo
                    for jj in range(p):
                        R[ii, jj] += ri * rbuf[slot, e, jj]
        ok = last[8] >= n_warm and last[6] > n_gate and (not two_fric or last[7] > n_gate)
        okbuf[slot] = 1.0 if ok else 0.0
        ybuf[slot] = X[2, 0]
        for e in range(neq):
            for j in range(p):
                acc = 0.0
                for m in range(3):
                    acc += C[e, j, m] * X[0, m] + C[e, j, 3 + m] * X[1, m]
                ex = E[e, j]
                if ex == 1:
                    acc += X[3, 0]
                elif ex == 2:
                    acc += X[4, 0]
                elif ex == 3:
                    acc += X[5, 0]
                rbuf[slot, e, j] = acc


_rfs_block = numba.njit(cache=True)(_rfs_block_py)


class RecursiveFrictionEstimator:
    """The friction models per sample: the rows of :func:`~rt_ident.estimators.friction.fit_friction`
    accumulated sample by sample in information form with exponential forgetting, compiled.

    Differences from the batch fit: the sign comes from the *causal* filtered velocity (sF th, lag
    ~3/lam), so rows are used only once ``n_gate`` samples (the filter memory plus that lag) have
    passed since the last standstill sample, and each row waits that lag before it enters the sums
    (a standstill sample meanwhile discards it: its sign may have been stale); the dead band is 5
    sigma of the quantization noise of sF th and at least 2 % of the running rms velocity. ``estimate()`` solves the
    bias-compensated normal equations (Jacobi-scaled) on request - the update itself is O(p^2) per
    row. ``memory_s`` = inf: no forgetting (the batch answer, up to the causal sign)."""

    def __init__(self, dt: float, model: str = "two-inertia-friction", *, filter_hz: float = 800.0,
                 memory_s: float = math.inf, quanta: tuple[float, float] = (0.0, 0.0),
                 dead_band: tuple[float, float] | None = None) -> None:
        self.model = check_model(model)
        self.dt = float(dt)
        if not 0 < filter_hz <= 0.25 / dt:
            raise ConfigError("filter_hz", f"must be in (0, {0.25 / dt:g}] Hz (a quarter of the sample rate)")
        self.filter_hz = float(filter_hz)
        lam = 2 * math.pi * filter_hz
        Phi = np.zeros((3, 3))
        A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-lam**3, -3 * lam**2, -3 * lam]])
        M = np.zeros((5, 5))
        M[:3, :3] = A * dt
        M[:3, 3] = np.array([0.0, 0.0, lam**3]) * dt
        M[3, 4] = 1.0
        Ex = scipy.linalg.expm(M)
        Phi, g0, g1 = Ex[:3, :3].copy(), Ex[:3, 3].copy(), Ex[:3, 4].copy()
        self._mats = (Phi, g0, g1, g0.copy())
        self._C, self._E = _row_maps(self.model)
        self.names = MODELS[self.model]
        p = len(self.names)
        n_mem = int(math.ceil(8.0 / (lam * dt)))
        self._n_gate = float(n_mem + int(math.ceil(3.0 / (lam * dt))))
        self._n_warm = float(4 * n_mem)
        self._lamf = 1.0 if not math.isfinite(memory_s) else math.exp(-dt / memory_s)
        self._fv = math.exp(-dt / 0.5)               # running rms velocity over 0.5 s (dead band floor)
        # quantization: per-row noise covariance (white q^2/12 through the FOH filter)
        foh, _ = svf_filters(lam, dt)
        H = np.column_stack([impulse_response(f, 40 * n_mem) for f in foh])
        G = H.T @ H
        q1, q2 = quanta
        Nb = np.zeros((6, 6))
        Nb[:3, :3] = G * q1**2 / 12.0
        Nb[3:, 3:] = G * q2**2 / 12.0
        self._Sigma = sum(self._C[e] @ Nb @ self._C[e].T for e in range(self._C.shape[0]))
        sd = math.sqrt(G[1, 1])
        if dead_band is None:
            dead_band = (5.0 * sd * q1 / math.sqrt(12.0), 5.0 * sd * q2 / math.sqrt(12.0))
        self._db = np.array([float(dead_band[0]), float(dead_band[1])])
        self._X = np.zeros((6, 3))
        self._last = np.zeros(12)
        self._R = np.zeros((p, p))
        self._r = np.zeros(p)
        L = int(math.ceil(3.0 / (lam * dt))) + 1              # the causal sign's lag, in samples
        self._rbuf = np.zeros((L, self._C.shape[0], p))
        self._ybuf = np.zeros(L)
        self._okbuf = np.zeros(L)
        z = np.zeros(2)                     # compile (or load) the kernel now, on a copy: not in the loop's ticks
        copy.deepcopy(self).update_block(z, z, z)

    def update_block(self, theta1: np.ndarray, theta2: np.ndarray | None, torque: np.ndarray) -> None:
        th1 = np.ascontiguousarray(theta1, dtype=np.float64)
        th2 = np.zeros_like(th1) if theta2 is None else np.ascontiguousarray(theta2, dtype=np.float64)
        tq = np.ascontiguousarray(torque, dtype=np.float64)
        Phi, G0, G1, Gz = self._mats
        _rfs_block(th1, th2, tq, self._X, self._last, Phi, G0, G1, Gz, self._C, self._E, self._lamf,
                   self._db, self._n_gate, self._n_warm, self._fv, self._R, self._r, self._rbuf, self._ybuf,
                   self._okbuf)

    @property
    def rows_weight(self) -> float:
        return float(self._last[9])

    def estimate(self) -> dict[str, float] | None:
        """The current parameters (None before enough rows in motion)."""
        p = len(self.names)
        if self._last[9] < 10 * p:
            return None
        A = self._R - self._last[9] * self._Sigma
        d = np.sqrt(np.abs(np.diag(self._R)))
        d[d == 0] = 1.0
        try:
            ps = np.linalg.solve(A / np.outer(d, d), self._r / d)
        except np.linalg.LinAlgError:
            return None
        return {k: float(v) for k, v in zip(self.names, ps / d)}

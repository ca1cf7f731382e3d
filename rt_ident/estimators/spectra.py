"""Period-averaged spectra of a periodically excited recording, the input of :mod:`rt_ident.estimators.frequency`.

1. detect N (autocorrelation of the torque) and the excited harmonics when not given,
   drop the first period(s) (transient);
2. DFT each whole period of theta1, theta2, T at the excited harmonics, and keep the
   mean over the P periods (noise averages out, the periodic part does not) and the
   period-to-period covariance (the noise level, for weighting and intervals), less the part
   that the periods' leakage explains (:meth:`Spectra.from_sums`): a response that is not
   periodic (closed-loop drift, a host stall's coast and recovery) changes every line of a
   period through one leakage vector, which the fit estimates for the mean, so its scatter
   is not noise of the mean.

:func:`compute_spectra` does both on a recording; the streaming form
(:mod:`rt_ident.estimators.frequency_stream`) keeps the same sums period by period
(:class:`SpectraSums`) and makes the same :class:`Spectra` from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rt_ident.errors import ConfigError, DataError, EstimationError

MIN_SNR = 10.0          # median torque-line SNR (power, mean over periods) required for trust
LEAK_FEATURES = 5       # per period: change of deflection and table mean and slope at the period's end, torque sum
LEAK_WINDOW = 32        # samples at the end of a period the leakage features average over (at most N/8)
MOVED_STEPS = 0.25      # a period's angle path shifted by more than this many quantization steps: new errors
_LEAK_MIN_PERIODS = 2 * LEAK_FEATURES + 2   # fewer (effective) periods: the raw scatter is kept


def leak_window(N: int) -> int:
    """Samples ``m`` (even, >= 2) at the end of each period of N that the leakage features average over."""
    return max(2, min(LEAK_WINDOW, int(N) // 8) // 2 * 2)


def sums_layout(H: int) -> dict[str, Any]:
    """Offsets in the flat complex buffer of a streaming estimator's second-order sums: S2 (H, 3, 3),
    Svf (3, H, K), Sff (K, K), Sf (K,), Wf (the weight of the periods that have leakage features),
    Smv (2,) (the weight of those whose theta1, theta2 shifted by more than MOVED_STEPS steps)."""
    K = LEAK_FEATURES
    o = {"s2": 0, "vf": 9 * H, "ff": 9 * H + 3 * H * K}
    o["f"] = o["ff"] + K * K
    o["wf"] = o["f"] + K
    o["mv"] = o["wf"] + 1
    o["size"] = o["mv"] + 2
    return o


def leak_features(theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, N: int, first: int, P: int
                  ) -> np.ndarray:
    """(P, LEAK_FEATURES) leakage features of the P periods from sample ``first`` (>= m): the change,
    since the previous period, of the mean and of the slope (second half minus first half of the
    window, per sample) of the deflection theta1 - theta2 and of theta2 over the period's last m
    samples, and the period's torque sum (the momentum change of the free-free axis): columns
    [d mean(theta1 - theta2), d mean(theta2), sum T, d slope(theta1 - theta2), d slope(theta2)].
    They span the leakage vector ``c`` of the period (its state change,
    :mod:`rt_ident.estimators.sampled_model`) to within the quantization of the angles. Deflection
    and table are separate columns because the rigid-body drift moves both angles alike: as
    theta1 and theta2 the columns are collinear (condition number 3e8 after a host stall, where
    rounding in the sums then decides the fit), as deflection and table they are not (6e4).
    The streaming kernel computes the same numbers."""
    m = leak_window(N)
    half = m // 2
    ends = first + N * np.arange(P + 1) - m          # window starts: previous period's, then each period's
    out = np.empty((P, LEAK_FEATURES))
    feats = []
    for x in (theta1, theta2):
        w = np.asarray(x, dtype=float)[ends[:, None] + np.arange(m)]
        a, b = w[:, :half].sum(axis=1), w[:, half:].sum(axis=1)
        feats.append((np.diff((a + b) / m), np.diff((b - a) / half)))
    out[:, 0], out[:, 1] = feats[0][0] - feats[1][0], feats[1][0]
    out[:, 2] = np.asarray(torque, dtype=float)[first:first + P * N].reshape(P, N).sum(axis=1)
    out[:, 3], out[:, 4] = feats[0][1] - feats[1][1], feats[1][1]
    return out


@dataclass(frozen=True, eq=False)
class Spectra:
    """Period-averaged spectra at the excited harmonics (unnormalized DFT of one period).

    mean : (3, H) complex mean over periods of [Theta1, Theta2, T]
    cov  : (H, 3, 3) complex period-to-period covariance of one period's spectrum, less what the
           periods' leakage features explain (see :meth:`from_sums`)
    weight, weight2 : sum of period weights and of their squares (P and P without forgetting)
    quantum : (2,) quantization steps of theta1, theta2 (deterministic error floor)
    moved : (2,) share of the periods whose angle theta1, theta2 (mean over the leakage features'
           window) moved by more than a quarter quantization step since the previous period: their
           quantization errors differ from the previous period's (None: unknown, taken as 0)
    leak_dof : leakage features regressed out of ``cov`` (0: none, the raw scatter)
    """

    harmonics: np.ndarray
    N: int
    dt: float
    mean: np.ndarray
    cov: np.ndarray
    weight: float
    weight2: float
    periods: int
    quantum: np.ndarray
    moved: np.ndarray | None = None
    leak_dof: int = 0

    @property
    def omega(self) -> np.ndarray:
        return self.harmonics * (2.0 * math.pi / (self.N * self.dt))

    @property
    def z(self) -> np.ndarray:
        return np.exp(2j * math.pi * self.harmonics / self.N)

    @property
    def mean_cov_factor(self) -> float:
        """Covariance of the mean = cov * weight2 / weight^2 (1/P without forgetting)."""
        return self.weight2 / self.weight**2

    @classmethod
    def from_sums(cls, harmonics: np.ndarray, N: int, dt: float, S1: np.ndarray, S2: np.ndarray,
                  W: float, W2: float, periods: int, quantum: np.ndarray, *, Svf: np.ndarray | None = None,
                  Sff: np.ndarray | None = None, Sf: np.ndarray | None = None, Wf: float = 0.0,
                  Smv: np.ndarray | None = None) -> Spectra:
        """From running sums S1 = sum w v, S2 = sum w v v^H, W = sum w, W2 = sum w^2, and the
        leakage features' sums Svf = sum w v f^T (3, H, K), Sff = sum w f f^T, Sf = sum w f over the
        periods that have features (weight Wf), of which Smv (2,) shifted by more than MOVED_STEPS
        quantization steps (weighted count per angle).

        The covariance is that of the periods' spectra less its regression on the features,
        ``C_vv - C_vf C_ff^-1 C_vf^H`` per line, scaled by ``(P - 1) / (P - 1 - k)`` for the k
        features used (P the effective number of periods ``W^2 / W2``). The leakage of a period
        (its state change c, the same for every line) is a linear function of the features, so
        this removes the period-to-period variation that the fit's leakage term absorbs in the
        mean and keeps the noise. The raw scatter is kept (wider, never narrower intervals) when
        a period lacks features or there are fewer than ``2 K + 2`` periods.
        """
        if periods < 1 or W <= 0.0:
            raise EstimationError("frequency: no complete period accumulated yet")
        mean = S1 / W
        H = np.asarray(harmonics).size
        moved = None if Smv is None or Wf <= 0.0 else np.clip(np.asarray(Smv, dtype=float) / Wf, 0.0, 1.0)
        dof = 0
        if periods >= 2 and W * W > W2:
            # reliability-weighted unbiased covariance; W = W2 = P gives the usual 1/(P-1)
            den = W - W2 / W
            outer = np.einsum("ih,jh->hij", mean, mean.conj())
            cov = (S2 - W * outer) / den
            p_eff = W * W / W2
            if (Svf is not None and Sff is not None and Sf is not None and abs(W - Wf) <= 1e-9 * W
                    and p_eff >= _LEAK_MIN_PERIODS):
                fbar = np.asarray(Sf, dtype=float) / W
                Cff = (np.asarray(Sff, dtype=float) - W * np.outer(fbar, fbar)) / den
                Cvf = (Svf - W * mean[:, :, None] * fbar[None, None, :]) / den
                d = np.sqrt(np.clip(np.diag(Cff), 0.0, None))
                live = d > 0.0
                if np.any(live):
                    R = Cff[np.ix_(live, live)] / np.outer(d[live], d[live])
                    lam, U = np.linalg.eigh(R)
                    keep = lam > 1e-9 * lam.max()
                    Rinv = (U[:, keep] / lam[keep]) @ U[:, keep].T
                    B = Cvf[:, :, live] / d[live]                       # (3, H, k) correlation form
                    explained = np.einsum("ihk,kl,jhl->hij", B, Rinv, B.conj())
                    dof = int(np.count_nonzero(keep))
                    cov = (cov - explained) * ((p_eff - 1.0) / (p_eff - 1.0 - dof))
        else:
            cov = np.zeros((H, 3, 3), complex)
        return cls(np.asarray(harmonics), int(N), float(dt), mean, cov, float(W), float(W2),
                   int(periods), np.asarray(quantum, float), moved, dof)

    def to_fields(self) -> dict[str, np.ndarray]:
        """The spectra as flat arrays (a shared-memory ring message, :meth:`from_fields` undoes it):
        the loop hands a snapshot to the fit process this way, without pickling it."""
        return {"harmonics": np.ascontiguousarray(self.harmonics, dtype=np.int64),
                "mean": np.ascontiguousarray(self.mean, dtype=complex).view(np.float64).ravel(),
                "cov": np.ascontiguousarray(self.cov, dtype=complex).view(np.float64).ravel(),
                "quantum": np.asarray(self.quantum, dtype=np.float64).ravel(),
                "scalars": np.array([self.N, self.dt, self.weight, self.weight2, self.periods, self.leak_dof],
                                    dtype=np.float64),
                "moved": np.zeros(0) if self.moved is None else np.asarray(self.moved, dtype=np.float64).ravel()}

    @classmethod
    def from_fields(cls, f: dict[str, np.ndarray]) -> Spectra:
        h = np.asarray(f["harmonics"], dtype=np.int64)
        N, dt, W, W2, periods, *rest = (float(v) for v in f["scalars"])
        mean = np.ascontiguousarray(f["mean"], dtype=np.float64).view(complex).reshape(3, h.size)
        cov = np.ascontiguousarray(f["cov"], dtype=np.float64).view(complex).reshape(h.size, 3, 3)
        mv = np.asarray(f.get("moved", np.zeros(0)), dtype=np.float64)
        return cls(h, int(N), dt, mean, cov, W, W2, int(periods), np.asarray(f["quantum"], dtype=np.float64),
                   mv if mv.size else None, int(rest[0]) if rest else 0)


@dataclass(frozen=True, eq=False)
class SpectraSums:
    """The running sums a streaming estimator keeps (S1 = sum w v (3, H), S2 = sum w v v^H (H, 3, 3),
    W = sum w, W2 = sum w^2, over ``periods`` periods, and the leakage features' sums Svf (3, H, K),
    Sff (K, K), Sf (K,) over the periods of weight Wf that have features, Smv (2,) the weight of those
    whose angles shifted by more than MOVED_STEPS quantization steps; None: not kept): what the
    loop hands the fit process, which turns them into :class:`Spectra` (:meth:`spectra`). Copying two
    arrays is all the loop does; the means and covariances (an ``einsum``, divisions: ~150 us of a tick,
    docs/measurements.md) are the job process's. The compiled tick writes this message itself
    (rt_ident.processes.shm_ring.put_sums): ``sums`` is S1, then the flat buffer of :func:`sums_layout`."""

    harmonics: np.ndarray
    N: int
    dt: float
    S1: np.ndarray
    S2: np.ndarray
    W: float
    W2: float
    periods: int
    quantum: np.ndarray
    Svf: np.ndarray | None = None
    Sff: np.ndarray | None = None
    Sf: np.ndarray | None = None
    Wf: float = 0.0
    Smv: np.ndarray | None = None

    @classmethod
    def from_flat(cls, harmonics: np.ndarray, N: int, dt: float, S1: np.ndarray, flat: np.ndarray, W: float,
                  W2: float, periods: int, quantum: np.ndarray) -> SpectraSums:
        """From S1 and the flat complex buffer of :func:`sums_layout` (S2 alone: no features)."""
        H = np.asarray(harmonics).size
        K = LEAK_FEATURES
        o = sums_layout(H)
        flat = np.asarray(flat, dtype=complex).ravel()
        if flat.size == 9 * H:
            return cls(harmonics, N, dt, S1, flat.reshape(H, 3, 3), W, W2, periods, quantum)
        if flat.size != o["size"]:
            raise DataError(f"sums: {flat.size} second-order sums for {H} lines; expected {9 * H} or {o['size']}")
        return cls(harmonics, N, dt, S1, flat[:9 * H].reshape(H, 3, 3), W, W2, periods, quantum,
                   flat[o["vf"]:o["ff"]].reshape(3, H, K), flat[o["ff"]:o["f"]].real.reshape(K, K),
                   flat[o["f"]:o["wf"]].real.copy(), float(flat[o["wf"]].real), flat[o["mv"]:o["size"]].real.copy())

    def flat(self) -> np.ndarray:
        """S2 and the features' sums as the flat complex buffer of :func:`sums_layout`."""
        parts = [np.ascontiguousarray(self.S2, dtype=complex).ravel()]
        if self.Svf is not None:
            parts += [np.ascontiguousarray(self.Svf, dtype=complex).ravel(),
                      np.asarray(self.Sff, dtype=complex).ravel(), np.asarray(self.Sf, dtype=complex).ravel(),
                      np.array([self.Wf], dtype=complex),
                      np.asarray(self.Smv if self.Smv is not None else np.zeros(2), dtype=complex)]
        return np.concatenate(parts)

    def spectra(self) -> Spectra:
        return Spectra.from_sums(self.harmonics, self.N, self.dt, self.S1, self.S2, self.W, self.W2, self.periods,
                                 self.quantum, Svf=self.Svf, Sff=self.Sff, Sf=self.Sf, Wf=self.Wf, Smv=self.Smv)

    def to_fields(self) -> dict[str, np.ndarray]:
        """Flat arrays for a ring message (:meth:`from_fields` undoes it): ``sums`` is S1 then the flat
        buffer of :meth:`flat` as interleaved real and imaginary parts."""
        return {"harmonics": np.ascontiguousarray(self.harmonics, dtype=np.int64),
                "sums": np.concatenate([np.ascontiguousarray(a, dtype=complex).view(np.float64).ravel()
                                        for a in (self.S1, self.flat())]),
                "quantum": np.asarray(self.quantum, dtype=np.float64).ravel(),
                "scalars": np.array([self.N, self.dt, self.W, self.W2, self.periods], dtype=np.float64)}

    @classmethod
    def from_fields(cls, f: dict[str, np.ndarray]) -> SpectraSums:
        h = np.asarray(f["harmonics"], dtype=np.int64)
        N, dt, W, W2, periods = (float(v) for v in f["scalars"])
        z = np.ascontiguousarray(f["sums"], dtype=np.float64).view(complex)
        H = h.size
        return cls.from_flat(h, int(N), dt, z[:3 * H].reshape(3, H), z[3 * H:], W, W2, int(periods),
                             np.asarray(f["quantum"], dtype=np.float64))


def detect_period(x: np.ndarray, *, min_period: int = 4, threshold: float = 0.8) -> int:
    """Period in samples of a periodic signal, from its autocorrelation.

    The smallest lag past the main lobe whose normalized (unbiased) autocorrelation
    reaches ``threshold`` of the largest value in 1..n/2 and is a local maximum.
    Needs at least two periods. DataError when nothing periodic is found.
    """
    x = np.asarray(x, dtype=float) - float(np.mean(x))
    n = x.size
    if n < 2 * min_period:
        raise DataError(f"torque: {n} samples are too few to detect a period")
    F = np.fft.rfft(x, 2 * n)
    r = np.fft.irfft(F * F.conj(), 2 * n)[: n // 2 + 1]
    if r[0] <= 0.0:
        raise DataError("torque: constant signal, no period to detect")
    r = r / (n - np.arange(r.size)) / (r[0] / n)
    below = np.flatnonzero(r < 0.5)
    start = max(min_period, int(below[0]) if below.size else r.size)
    if start >= r.size - 1:
        raise DataError("torque: no periodicity found (need at least two periods)")
    seg = r[start:]
    top = float(seg.max())
    if top < 0.5:
        raise DataError(f"torque: no periodicity found (best autocorrelation {top:.2f} < 0.5)")
    for i in range(seg.size):
        L = start + i
        if seg[i] >= threshold * top and (L + 1 >= r.size or r[L] >= r[L + 1]) and r[L] >= r[L - 1]:
            return int(L)
    return int(start + np.argmax(seg))


def period_spectra(x: np.ndarray, N: int, first: int, P: int, harmonics: np.ndarray) -> np.ndarray:
    """(P, H) DFT of each of P whole periods starting at sample ``first``."""
    block = np.asarray(x[first:first + P * N], dtype=float).reshape(P, N)
    return np.fft.rfft(block, axis=1)[:, harmonics]


def quantum_of(x: np.ndarray) -> float:
    """Smallest non-zero step between consecutive samples (the quantization step if any)."""
    d = np.abs(np.diff(np.asarray(x, dtype=float)))
    d = d[d > 0.0]
    return float(d.min()) if d.size else 0.0


def detect_harmonics(T_mean: np.ndarray, T_var: np.ndarray | None, *, rel: float = 0.05) -> np.ndarray:
    """Excited lines: |T_h| >= rel * max|T| (and >= sqrt(10) noise sd when the noise is known)."""
    mag = np.abs(T_mean)
    ok = mag >= rel * mag.max()
    if T_var is not None:
        ok &= mag**2 >= MIN_SNR * T_var
    ok[0] = False
    return np.flatnonzero(ok)


def compute_spectra(theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, dt: float, *,
                    period: int | None = None, harmonics: np.ndarray | None = None,
                    discard_periods: int | None = None, quantum: tuple[float, float] | None = None
                    ) -> Spectra:
    """Period-averaged spectra of a recording (the arguments as for
    :func:`rt_ident.estimators.frequency.fit_frequency`)."""
    x = [np.asarray(a, dtype=float) for a in (theta1, theta2, torque)]
    n = x[0].size
    if any(a.ndim != 1 or a.size != n for a in x):
        raise DataError("theta1/theta2/torque: must be 1-D arrays of equal length")
    if not all(np.all(np.isfinite(a)) for a in x):
        raise DataError("theta1/theta2/torque: contain non-finite values")
    N = detect_period(x[2]) if period is None else int(period)
    if N < 4:
        raise ConfigError("period", f"must be >= 4 samples, got {N}")
    total = n // N
    if discard_periods is None:
        discard_periods = 1 if total >= 3 else 0
    P = total - int(discard_periods)
    if P < 1:
        raise DataError(f"theta1: {n} samples hold {total} whole period(s) of {N}; "
                        f"need more than discard_periods={discard_periods}")
    first = int(discard_periods) * N    # periods counted from sample 0, as the streaming form does
    q = np.array([quantum_of(x[0]), quantum_of(x[1])]) if quantum is None else np.asarray(quantum, float)
    all_h = np.arange(N // 2 + 1)
    if harmonics is None:
        V = np.stack([period_spectra(a, N, first, P, all_h) for a in x], axis=1)
        m = V[:, 2].mean(axis=0)
        var = V[:, 2].var(axis=0) / P if P >= 2 else None
        harmonics = detect_harmonics(m, var)
        harmonics = harmonics[harmonics < N / 2]
        V = V[:, :, harmonics]
    else:
        harmonics = np.asarray(harmonics, dtype=int)
        if harmonics.ndim != 1 or harmonics.size == 0 or harmonics.min() < 1 or harmonics.max() >= N / 2:
            raise ConfigError("harmonics", f"must be harmonic numbers in 1..{(N - 1) // 2}")
        V = np.stack([period_spectra(a, N, first, P, harmonics) for a in x], axis=1)
    if harmonics.size == 0:
        raise EstimationError("frequency: no excited harmonic found in the torque")
    S1 = V.sum(axis=0)
    S2 = np.einsum("pih,pjh->hij", V, V.conj())
    feats: dict[str, Any] = {}
    if first >= leak_window(N):            # the features need the previous period's end
        F = leak_features(x[0], x[1], x[2], N, first, P)
        d = np.abs(np.column_stack([F[:, 0] + F[:, 1], F[:, 1]]))       # the angles' moves since last period
        feats = {"Svf": np.einsum("pih,pk->ihk", V, F), "Sff": F.T @ F, "Sf": F.sum(axis=0), "Wf": float(P),
                 "Smv": np.sum((d > MOVED_STEPS * q) & (q > 0.0), axis=0).astype(float)}
    return Spectra.from_sums(harmonics, N, dt, S1, S2, float(P), float(P), P, q, **feats)

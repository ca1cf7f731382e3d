"""Frequency-domain identification from periodic excitation (beyond the paper).

Bench data are angles only, quantized, with a noisy torque and the drive's position
loop closed: time-domain equation error (the paper's Eq. 9-10, and even the exact
regressions of :mod:`consistent`) is then biased, because the noise sits in the
regressors and is fed back into the input. A periodic excitation (the paper's
Schroeder multisine, period N samples) removes that bias:

1. detect N (autocorrelation of the torque) and the excited harmonics when not given,
   drop the first period(s) (transient);
2. DFT each whole period of theta1, theta2, T at the excited harmonics, and keep the
   mean over the P periods (noise averages out, the periodic part does not) and the
   period-to-period covariance (the noise level, for weighting and intervals), less the part
   that the periods' leakage explains (:meth:`Spectra.from_sums`): a response that is not
   periodic (closed-loop drift, a host stall's coast and recovery) changes every line of a
   period through one leakage vector, which the fit estimates for the mean, so its scatter
   is not noise of the mean;
3. initialize with a linear equation-error fit of Eq. (3) per harmonic,
   ``I1 s^2 Th1 + (B s + K)(Th1 - Th2) = T`` and ``I2 s^2 Th2 - (B s + K)(Th1 - Th2) = 0``;
4. refine by Gauss-Newton on the *exact sampled* model Theta(z) = G(z; p) T(z) + R(z; p) c
   over log-parameters, weighted by the covariance of the output error
   ``Th - G T`` (sample-maximum-likelihood weighting: errors in the torque count too).

Exact sampled models (``hold`` = "zoh", "tustin", "tustin_held") and the leakage term
``c`` that makes the relation exact for windows that are not periodic (rigid-body drift,
remaining transient) are in :mod:`rt_ident.estimators.sampled_model`: nothing here needs
the response to be periodic, only the excitation.

The streaming form (recursive DFT, 1 kHz loop) is
:class:`rt_ident.estimators.frequency_stream.StreamingFrequencyEstimator`; it shares
:class:`Spectra` and :func:`fit_spectra` with the batch :func:`fit_frequency`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Literal, overload

import numpy as np

from rt_ident.errors import ConfigError, DataError, EstimationError
from rt_ident.estimators.base import Identification
from rt_ident.estimators.sampled_model import HOLDS, POS, check_hold, frequency_response, hold_model  # noqa: F401
from rt_ident.estimators.uncertainty import (
    build_identification,
    covariance_from_jacobian,
    criterion,
    excitation_report,
    excited_bands,
    params_from_log,
)

logger = logging.getLogger(__name__)

DEFAULT_LEAD = 7.96e-4
INIT_MAX_WDT = 2.0      # zoh: linear initial fit uses lines with w dt <= this
MIN_SNR = 10.0          # median torque-line SNR (power, mean over periods) required for trust
MAX_CHI2 = 10.0         # weighted residual per degree of freedom: above, the model does not explain the data
_TOL = 1e-10            # Gauss-Newton stop: largest step in log-parameters
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


# --------------------------------------------------------------------------- spectra
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


def transfer(theta: np.ndarray, sp: Spectra, hold: str) -> np.ndarray:
    """(H, 2) exact sampled frequency responses T -> (theta1, theta2) at the harmonics of ``sp``."""
    return frequency_response(theta, sp.z, sp.dt, hold)


def regressors(sp: Spectra, hold: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Real-stacked equation-error rows of Eq. (3) per harmonic: motor (2H,4), table (2H,4), rhs (2H,).

    ``I1 s^2 Th1 + (B s + K) D = T_eff`` and ``I2 s^2 Th2 - (B s + K) D = 0`` with
    D = Th1 - Th2 and the bilinear s = (2/dt)(z-1)/(z+1). Exact for ``tustin``
    (T_eff = T). For held torques T_eff = T 2/(z+1): exact for ``tustin_held`` and,
    for the rigid-body part, for ``zoh`` too (a held step integrated twice is
    dt^2 (z+1) / (2 (z-1)^2) in both); the flexible mode of ``zoh`` data comes out
    frequency-warped (see :func:`linear_init`).
    """
    Y1, Y2, T = sp.mean
    z = sp.z
    s = (2.0 / sp.dt) * (z - 1.0) / (z + 1.0)
    D = Y1 - Y2
    if hold != "tustin":
        T = T * 2.0 / (z + 1.0)
    zero = np.zeros_like(D)
    m1 = np.column_stack([s * s * Y1, zero, s * D, D])      # Eq. (3), motor row, per harmonic
    m2 = np.column_stack([zero, s * s * Y2, -s * D, -D])    # Eq. (3), table row
    return _real_rows(m1), _real_rows(m2), _real_rows(T)


def _real_rows(a: np.ndarray) -> np.ndarray:
    """Complex rows -> real rows [Re; Im] (real unknowns)."""
    return np.concatenate([a.real, a.imag])


def _unwarp(p: np.ndarray, dt: float) -> np.ndarray:
    """Map a Tustin-domain fit of zoh data back: same discrete poles, exact (expm) mapping.

    The Tustin model's flexible pole lambda_T sits at mu = (1 + lambda_T h)/(1 - lambda_T h);
    the zoh model puts it at mu = exp(lambda dt), so lambda = log(mu)/dt. K and B are
    rescaled to that wn and zeta at fixed I1, I2.
    """
    I1, I2, B, K = p
    g = 1.0 / I1 + 1.0 / I2
    lam_t = complex(-0.5 * B * g, math.sqrt(max(K * g - (0.5 * B * g) ** 2, 0.0)))
    if lam_t.imag == 0.0:
        return p
    h = 0.5 * dt
    lam = np.log((1.0 + lam_t * h) / (1.0 - lam_t * h)) / dt
    wn = abs(lam)
    return np.array([I1, I2, 2.0 * (-lam.real) / g, wn * wn / g])


def linear_init(sp: Spectra, hold: str) -> np.ndarray:
    """Log-parameters from the linear equation-error fit of :func:`regressors`.

    Rows are normalized by |T_h|. Each equation gets two real nuisance columns for the
    leakage of a non-periodic window, z/(z+1) and s z/(z+1): exact for the trapezoidal
    rule, where the DFT of x_k+1 - x_k = h (v_k + v_k+1) over one window gives
    (z-1) X = h (z+1) V + z (h dv - dx). For ``zoh`` the result is unwarped (:func:`_unwarp`).
    """
    if hold == "zoh":
        # keep lines where the Tustin warping is mild (tan(x)/x < 1.56 at w dt = 2): near
        # Nyquist the bilinear rows are huge and wrong for held data and would dominate
        keep = sp.omega * sp.dt <= INIT_MAX_WDT
        if np.count_nonzero(keep) >= 4:
            sp = Spectra(sp.harmonics[keep], sp.N, sp.dt, sp.mean[:, keep], sp.cov[keep], sp.weight,
                         sp.weight2, sp.periods, sp.quantum, sp.moved, sp.leak_dof)
    m1, m2, rhs = regressors(sp, hold)
    z = sp.z
    s = (2.0 / sp.dt) * (z - 1.0) / (z + 1.0)
    zz = z / (z + 1.0)
    L = np.column_stack([zz, s * zz * sp.dt])
    L = np.concatenate([L.real, L.imag])
    zero = np.zeros_like(L)
    H = sp.harmonics.size
    w = 1.0 / np.maximum(np.tile(np.hypot(rhs[:H], rhs[H:]), 2), 1e-300)      # 1 / |T_eff,h|
    X = np.vstack([np.hstack([m1, L, zero]) * w[:, None], np.hstack([m2, zero, L]) * w[:, None]])
    y = np.concatenate([rhs * w, np.zeros_like(rhs)])
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0.0] = 1.0
    sol, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    p = np.abs(sol[:4] / scale[:4])
    if not np.all(np.isfinite(p)) or np.any(p == 0.0):
        raise EstimationError("frequency: the linear initial fit failed (no excitation in the band?)")
    if hold == "zoh":
        p = _unwarp(p, sp.dt)
    return np.log(p)


def _natural_frequency(x: np.ndarray) -> float:
    """wn = sqrt(K (I1 + I2) / (I1 I2)) [rad/s], the two-inertia mode, of log-parameters ``x``."""
    I1, I2, _, K = np.exp(x[:4])
    return math.sqrt(K * (I1 + I2) / (I1 * I2))


def _alias_start(x: np.ndarray, dt: float) -> np.ndarray | None:
    """The start with the resonance mirrored about Nyquist (``2 pi / dt - wn``; zeta kept: B scales
    with sqrt(K)), when the resonance lies within two thirds of Nyquist on either side of it (where a
    held mode and its mirror fall on the same sampled line); None otherwise."""
    wn = _natural_frequency(x)
    ws = 2.0 * math.pi / dt
    if not (ws / 6.0 < wn < 5.0 * ws / 6.0) or wn == ws / 2.0:
        return None
    factor = ((ws - wn) / wn) ** 2
    out = np.array(x, dtype=float)
    out[3] += math.log(factor)
    out[2] += 0.5 * math.log(factor)
    return out


def _fit_among_aliases(sp: Spectra, hold: str, start: np.ndarray, *, transient: bool, max_iter: int,
                       tol: float) -> FitResult:
    """Gauss-Newton from ``start``, then from the mirrors about Nyquist of the start and of the fit.

    Sampled with a hold, a mode at w and one at 2 pi / dt - w alias onto the same line of the sampled
    spectrum; only the hold's own response tells them apart, and Gauss-Newton stays in the basin it
    starts in. Two cases need a mirror: a mode above Nyquist whose linear start (fitted on the lines
    well below Nyquist) lands on its alias - the start's mirror finds it (the THOMSON X axis, 662 Hz at
    1 kHz); and a mode below Nyquist whose fit ends on its mirror, trusted because the intervals there
    are narrow too - the fit's own mirror finds it (the XY table's Y, 463 Hz at 1 kHz). Figures:
    docs/measurements.md, "Aliasing on the 1 kHz bus". A mirror within 3 % of a start already tried or
    a fit already found is not fitted again (X: the fit's mirror is the linear start).
    A mirrored fit must converge and halve the cost to win (or beat an unconverged one): early in a run,
    on a few noisy periods, a spurious minimum could otherwise beat the true one by a hair (the aliased
    case differs by a factor of ten or more).
    """
    best = fit_spectra(sp, hold, transient=transient, x0=start, max_iter=max_iter, tol=tol)
    seen = [_natural_frequency(start), _natural_frequency(best.x)]
    for k in range(2):
        mirror = _alias_start(start if k == 0 else best.x, sp.dt)
        if mirror is None:
            continue
        wm = _natural_frequency(mirror)
        if any(abs(wm - w) < 0.03 * w for w in seen):
            continue
        seen.append(wm)
        try:
            alt = fit_spectra(sp, hold, transient=transient, x0=mirror, max_iter=max_iter, tol=tol, quiet=True)
        except EstimationError:
            continue
        seen.append(_natural_frequency(alt.x))
        if alt.converged and (alt.cost < 0.5 * best.cost or (not best.converged and alt.cost < best.cost)):
            best = alt
    return best


# --------------------------------------------------------------------------- Gauss-Newton fit
@dataclass(frozen=True, eq=False)
class FitResult:
    """Converged fit: x = [log I1, log I2, log B, log K, (c1..c4)]; cov of x; s2 = cost/dof."""

    x: np.ndarray
    cov: np.ndarray
    s2: float
    cost: float
    dof: int
    iterations: int
    converged: bool


@dataclass(frozen=True, eq=False)
class _Model:
    """The exact sampled model evaluated at one x: M^-1, N, derivatives, states X, transfer G."""

    Minv: np.ndarray
    N: np.ndarray
    dM: np.ndarray | None
    dN: np.ndarray | None
    X: np.ndarray
    G: np.ndarray


def _evaluate(x: np.ndarray, sp: Spectra, hold: str, jac: bool) -> _Model:
    M, N, dM, dN = hold_model(x[:4], sp.z, sp.dt, hold, derivs=jac)
    Minv = np.linalg.inv(M)
    rhs = N * sp.mean[2][:, None]
    if x.size > 4:
        rhs = rhs + sp.z[:, None] * x[4:]
    X = np.einsum("hij,hj->hi", Minv, rhs)
    G = np.einsum("hij,hj->hi", Minv[:, POS], N)
    return _Model(Minv, N, dM, dN, X, G)


def _whitener(G: np.ndarray, sp: Spectra) -> np.ndarray:
    """(H, 2, 2) inverse Cholesky factors of the output-error covariance ``Cov(Th - G T)``.

    Cov = [I, -G] S [I, -G]^H / P (sample-ML weighting, S the period-to-period
    covariance of [Th1, Th2, T] less its leakage, :meth:`Spectra.from_sums`) + the
    quantization error that repeats in every period (:func:`repeating_quantization`) + a
    1e-9 relative floor per line (noise-free data).
    """
    H = G.shape[0]
    V = np.zeros((H, 2, 3), complex)
    V[:, 0, 0] = V[:, 1, 1] = 1.0
    V[:, :, 2] = -G
    C = np.einsum("hia,hab,hjb->hij", V, sp.cov, V.conj()) * sp.mean_cov_factor
    lam, U = np.linalg.eigh(C)            # one-pass sums can leave it slightly indefinite: clip
    C = np.einsum("hik,hk,hjk->hij", U, np.maximum(lam, 0.0), U.conj())
    floor = 1e-18 * np.abs(sp.mean[:2]) ** 2 + 1e-300      # 1e-9 relative, per line and angle
    C[:, 0, 0] += repeating_quantization(sp, 0) + floor[0]
    C[:, 1, 1] += repeating_quantization(sp, 1) + floor[1]
    a, b, d = C[:, 0, 0].real, C[:, 1, 0], C[:, 1, 1].real
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(np.maximum(d - np.abs(l21) ** 2, 1e-300))
    Li = np.zeros((H, 2, 2), complex)
    Li[:, 0, 0] = 1.0 / l11
    Li[:, 1, 1] = 1.0 / l22
    Li[:, 1, 0] = -l21 / (l11 * l22)
    return Li


def repeating_quantization(sp: Spectra, angle: int) -> np.ndarray:
    """(H,) variance per line of the quantization error of one angle's mean spectrum that does not
    average out over the periods: ``(1 - moved)^2 N q^2 / 12``.

    A uniform error per sample gives ``N q^2 / 12`` per line and period. It repeats while the angle
    retraces the same path (a drive holding the axis: the response is periodic) and is new where the
    path has shifted since the previous period (a host loop's drift): the error of a path shifted by
    ``u q`` correlates with the old one by ``1 - 6 u (1 - u)``, zero near u = 0.21, so a shift of more
    than a quarter step (:data:`MOVED_STEPS`) counts as new; that error sits in the period scatter S
    and averages out. ``moved`` is the share of the periods that shifted (None: taken as 0); the
    others are taken to share one error pattern, a share (1 - moved) of the mean with variance
    (1 - moved)^2 N q^2 / 12 - the worst case: a path that returns to where it was (a hold after a
    disturbance) or creeps gives wider, never narrower intervals.
    """
    full = sp.N * float(sp.quantum[angle]) ** 2 / 12.0
    share = 0.0 if sp.moved is None else float(sp.moved[angle])
    return np.full(sp.harmonics.size, (1.0 - share) ** 2 * full)


@overload
def _residual(m: _Model, x: np.ndarray, sp: Spectra, Li: np.ndarray,
              jac: Literal[True]) -> tuple[np.ndarray, np.ndarray]: ...
@overload
def _residual(m: _Model, x: np.ndarray, sp: Spectra, Li: np.ndarray,
              jac: Literal[False]) -> tuple[np.ndarray, None]: ...
def _residual(m: _Model, x: np.ndarray, sp: Spectra, Li: np.ndarray, jac: bool
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """Whitened real residual of ``C M^-1 (N T + z c) - Th`` and its Jacobian w.r.t. x."""
    def white(v: np.ndarray) -> np.ndarray:      # (H, 2) complex -> (4H,) real
        w = np.einsum("hij,hj->hi", Li, v).ravel()
        return np.concatenate([w.real, w.imag])

    r = white(m.X[:, POS] - sp.mean[:2].T)
    if not jac:
        return r, None
    assert m.dM is not None and m.dN is not None
    T = sp.mean[2]
    cols = []
    for i in range(4):
        g = m.dN[i] * T[:, None] - np.einsum("hij,hj->hi", m.dM[i], m.X)
        cols.append(white(np.einsum("hij,hj->hi", m.Minv[:, POS], g)))
    for j in range(x.size - 4):
        cols.append(white(m.Minv[:, POS, j] * sp.z[:, None]))
    return r, np.column_stack(cols)


def fit_spectra(sp: Spectra, hold: str = "zoh", *, transient: bool = True, x0: np.ndarray | None = None,
                max_iter: int = 50, tol: float = _TOL, quiet: bool = False) -> FitResult:
    """Gauss-Newton on the exact sampled model, warm-started from ``x0`` or the linear fit.

    Weights are recomputed at each iterate and held fixed within its step-halving
    line search, so the fixed point is the weighted-LS stationary point (IRLS).
    """
    hold = check_hold(hold)
    n_x = 8 if transient else 4
    if x0 is None:
        x = np.concatenate([linear_init(sp, hold), np.zeros(n_x - 4)])
        if hold == "zoh":
            return _fit_among_aliases(sp, hold, x, transient=transient, max_iter=max_iter, tol=tol)
    else:
        x = np.array(x0, dtype=float)[:n_x]
        if x.size < n_x:
            x = np.concatenate([x, np.zeros(n_x - x.size)])
    converged = False
    it = 0
    model = _evaluate(x, sp, hold, True)
    # an iterate or trial far off (data without excitation) may overflow: inf is no descent, and a
    # diverged fit is refused below
    with np.errstate(over="ignore", invalid="ignore"):
        for it in range(1, max_iter + 1):  # noqa: B007 - the count is read after the loop
            Li = _whitener(model.G, sp)
            r, J = _residual(model, x, sp, Li, True)
            cost = float(r @ r)
            scale = np.linalg.norm(J, axis=0)
            scale[scale == 0.0] = 1.0
            step = -np.linalg.lstsq(J / scale, r, rcond=None)[0] / scale
            big = float(np.max(np.abs(step[:4])))
            if big > 2.0:                      # at most a factor e^2 per iteration on any parameter
                step *= 2.0 / big
            t = 1.0
            while t >= 1e-6:
                trial = _evaluate(x + t * step, sp, hold, True)
                r_new, _ = _residual(trial, x + t * step, sp, Li, False)
                if float(r_new @ r_new) <= cost:
                    break
                t *= 0.5
            if t < 1e-6:
                converged = True               # no descent left at machine precision
                break
            x, model = x + t * step, trial
            if float(np.max(np.abs(t * step[:4]))) < tol:
                converged = True
                break
    if not np.all(np.isfinite(x)):
        raise EstimationError("frequency: the fit diverged")
    r, J = _residual(model, x, sp, _whitener(model.G, sp), True)
    # the weights are absolute noise levels (period scatter + quantization model): s2 < 1 does
    # not narrow the intervals, s2 > 1 (model error, deterministic quantization) widens them
    cov, s2 = covariance_from_jacobian(J, r, min_scale=1.0)
    if not converged and not quiet:
        logger.warning("frequency: Gauss-Newton stopped after %d iterations without converging", it)
    return FitResult(x, cov, s2, float(r @ r), int(r.size - x.size), it, converged)


def identification_from_fit(sp: Spectra, fit: FitResult, hold: str, *, lead: float = DEFAULT_LEAD,
                            method: str = "frequency", n_samples: int | None = None) -> Identification:
    """Assemble the :class:`Identification` (intervals, PE monitor, torque-line SNR)."""
    p = params_from_log(fit.x[:4], lead)
    m1, m2, _ = regressors(sp, hold)
    pe = excitation_report([m1[:, [0, 2, 3]], np.vstack([m1, m2])])
    snr = math.nan
    checks = [criterion("Gauss-Newton fit converged", fit.converged, float(fit.iterations), "converged",
                        f"Gauss-Newton stopped after {fit.iterations} iterations without converging"),
              # the residual against the noise model: ~1 when the model explains the data; the
              # intervals grow with it, but a model error is a bias they do not cover
              criterion("fit error: weighted residual chi2 per degree of freedom", fit.s2 <= MAX_CHI2, fit.s2,
                        f"<= {MAX_CHI2:g}", f"the model does not explain the data: chi2/dof {fit.s2:.3g} > "
                        f"{MAX_CHI2:g} (residuals {math.sqrt(fit.s2):.3g} x the noise)")]
    if sp.periods >= 2:
        var_T = sp.cov[:, 2, 2].real * sp.mean_cov_factor
        snr = float(np.median(np.abs(sp.mean[2]) ** 2 / np.maximum(var_T, 1e-300)))
        checks.append(criterion("median torque-line SNR (power)", snr >= MIN_SNR, snr, f">= {MIN_SNR:g}",
                                f"torque lines barely above noise (median SNR {snr:.3g} < {MIN_SNR:g})"))
    diag = {"periods": float(sp.periods), "period_samples": float(sp.N), "n_harmonics": float(sp.harmonics.size),
            "chi2_dof": fit.s2, "iterations": float(fit.iterations), "converged": float(fit.converged),
            "leakage_features": float(sp.leak_dof),
            "snr_median_db": 10.0 * math.log10(snr) if snr > 0.0 else math.nan}
    if n_samples is not None:
        diag["n_samples"] = float(n_samples)
    held = hold in ("zoh", "tustin_held")
    bands = excited_bands(float(sp.omega.min()), float(sp.omega.max()), sp.dt if held else None)
    return build_identification(p, method, fit.cov[:4, :4], pe, diag, checks=checks, bands=bands)


def compute_spectra(theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, dt: float, *,
                    period: int | None = None, harmonics: np.ndarray | None = None,
                    discard_periods: int | None = None, quantum: tuple[float, float] | None = None
                    ) -> Spectra:
    """Period-averaged spectra of a recording (see :func:`fit_frequency` for the arguments)."""
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


def fit_frequency(theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, dt: float, *,
                  period: int | None = None, harmonics: np.ndarray | None = None, hold: str = "zoh",
                  discard_periods: int | None = None, transient: bool = True,
                  quantum: tuple[float, float] | None = None, lead: float = DEFAULT_LEAD,
                  max_iter: int = 50) -> Identification:
    """Identify (I1, I2, B, K) from a recording under periodic excitation.

    period          : excitation period in samples (detected from the torque when None)
    harmonics       : excited harmonic numbers (detected from the torque spectrum when None)
    hold            : how the data were made: "zoh" (drive), "tustin" (Newmark, paper), "tustin_held"
    discard_periods : whole periods dropped at the start (default 1 when >= 3 periods, else 0);
                      periods are counted from sample 0 and a trailing partial period is ignored
    transient       : estimate the leakage term c (needed for drifting open-loop data)
    quantum         : angle quantization steps; estimated as the smallest sample step when None
    """
    if not (math.isfinite(float(dt)) and float(dt) > 0.0):
        raise ConfigError("dt", f"must be finite and > 0, got {dt!r}")
    hold = check_hold(hold)
    sp = compute_spectra(theta1, theta2, torque, float(dt), period=period, harmonics=harmonics,
                         discard_periods=discard_periods, quantum=quantum)
    fit = fit_spectra(sp, hold, transient=transient, max_iter=max_iter)
    return identification_from_fit(sp, fit, hold, lead=lead, n_samples=int(np.asarray(theta1).size))

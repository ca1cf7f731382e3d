"""Streaming form of the frequency-domain estimator, for a real-time loop.

Per sample, a recursive DFT adds ``x_n exp(-2 pi j h n / N)`` to one accumulator per
excited harmonic ``h`` and signal (theta1, theta2, T). Every N samples a period is
complete: its spectrum ``v`` (3 x H) enters running sums

    S1 <- lam S1 + v,   S2 <- lam S2 + v v^H,   W <- lam W + 1,   W2 <- lam^2 W2 + 1

(``lam`` = forgetting per period; 1 keeps every period, < 1 tracks a drifting B or K
with an effective memory of 1/(1 - lam) periods), and the accumulator restarts.

A period whose response is not periodic (rigid-body drift in closed loop, the coast and the
recovery after a host stall) differs from the others by its leakage, the term ``z c`` of
:mod:`rt_ident.estimators.sampled_model` that the fit estimates for the mean. Its period-to-period
variation is not noise, and it is shared by every line, so the kernel also keeps the periods'
leakage features ``f`` (:func:`rt_ident.estimators.spectra.leak_features`) in sums ``Sf``,
``Sff`` and ``Svf = sum v f^T``; the fit removes the part of the scatter they explain
(:meth:`rt_ident.estimators.spectra.Spectra.from_sums`). It also counts the periods whose angles
shifted by more than a quarter quantization step (their quantization errors are new ones,
:func:`rt_ident.estimators.frequency.repeating_quantization`).
All sums live in one flat complex buffer (:func:`rt_ident.estimators.spectra.sums_layout`).
:meth:`StreamingFrequencyEstimator.estimate` turns the sums into the same
:class:`~rt_ident.estimators.spectra.Spectra` as the batch
:func:`~rt_ident.estimators.frequency.fit_frequency` and runs the same Gauss-Newton
fit, warm-started from the previous estimate (a few iterations).

The per-sample loop is a numba kernel (:func:`rdft_accumulate`) working in place on
preallocated arrays: nothing is allocated per sample. The twiddle factor of harmonic
h at sample n is read from one table ``exp(-2 pi j k / N)`` at index ``h n mod N``,
kept incrementally, so the DFT is exact (no phasor drift).
"""

from __future__ import annotations

import logging
import math

import numba
import numpy as np

from rt_ident.axis.kernels import first_non_finite3
from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.base import Identification
from rt_ident.estimators.frequency import DEFAULT_LEAD, FitResult, check_hold, fit_spectra, identification_from_fit
from rt_ident.estimators.spectra import LEAK_FEATURES, MOVED_STEPS, Spectra, SpectraSums, leak_window, sums_layout

logger = logging.getLogger(__name__)

# state vector layout of the kernel: position in the period, W, W2, periods completed and used, has-last
# flag; the leakage features' window m, its sums over the current period (theta1, theta2: first and second
# half of the last m samples), the previous period's means and slopes there, whether there is one, the
# torque sum; the count of completed periods up to which periods stay out of the sums (a loop stall)
_POS, _W, _W2, _DONE, _USED, _HAS_LAST, _M, _E = range(8)
_PREV, _HAS_PREV, _TSUM, _SKIP, STATE_SIZE = 11, 15, 16, 17, 18


def rdft_accumulate_py(th1: np.ndarray, th2: np.ndarray, torque: np.ndarray, harmonics: np.ndarray,
                       table: np.ndarray, idx: np.ndarray, acc: np.ndarray, S1: np.ndarray,
                       S2: np.ndarray, state: np.ndarray, last: np.ndarray, qmin: np.ndarray,
                       lam: float, discard: int) -> int:
    """Feed a block of samples; returns the number of periods added to the sums.

    table (N,) complex exp(-2 pi j k/N); idx (H,) int current h n mod N; acc (3, H) complex
    current-period DFT; S1 (3, H) complex running sum; S2 the flat complex buffer of the other sums
    (``sums_layout``: S2 (H, 3, 3), Svf (3, H, K), Sff (K, K), Sf (K,), Wf, Smv (2,)); state (STATE_SIZE,) float
    (see the layout above; ``state[_M]`` set by the caller); last (3,) previous sample; qmin (2,) smallest
    non-zero angle steps seen (0 = none yet).
    """
    N = table.shape[0]
    H = harmonics.shape[0]
    K = LEAK_FEATURES
    o_vf = 9 * H
    o_ff = o_vf + 3 * H * K
    o_f = o_ff + K * K
    o_wf = o_f + K
    o_mv = o_wf + 1
    m = int(state[_M])
    half = m // 2
    f = np.zeros(K)
    added = 0
    for n in range(th1.shape[0]):
        a, b, c = th1[n], th2[n], torque[n]
        if state[_HAS_LAST] != 0.0:
            d1 = abs(a - last[0])
            d2 = abs(b - last[1])
            if d1 > 0.0 and (qmin[0] == 0.0 or d1 < qmin[0]):
                qmin[0] = d1
            if d2 > 0.0 and (qmin[1] == 0.0 or d2 < qmin[1]):
                qmin[1] = d2
        last[0] = a
        last[1] = b
        last[2] = c
        state[_HAS_LAST] = 1.0
        for j in range(H):
            w = table[idx[j]]
            acc[0, j] += a * w
            acc[1, j] += b * w
            acc[2, j] += c * w
            k = idx[j] + harmonics[j]
            if k >= N:
                k -= N
            idx[j] = k
        cur = int(state[_POS])
        state[_TSUM] += c
        if cur >= N - m:                   # the last m samples: the leakage features' window
            e = _E if cur < N - half else _E + 1
            state[e] += a
            state[e + 2] += b
        pos = state[_POS] + 1.0
        if pos >= N:
            pos = 0.0
            state[_DONE] += 1.0
            mean1 = (state[_E] + state[_E + 1]) / m
            mean2 = (state[_E + 2] + state[_E + 3]) / m
            slope1 = (state[_E + 1] - state[_E]) / half
            slope2 = (state[_E + 3] - state[_E + 2]) / half
            if state[_DONE] > discard and state[_DONE] > state[_SKIP]:
                for j in range(H):
                    for r in range(3):
                        S1[r, j] = lam * S1[r, j] + acc[r, j]
                        for s in range(3):
                            i2 = (j * 3 + r) * 3 + s
                            S2[i2] = lam * S2[i2] + acc[r, j] * acc[s, j].conjugate()
                # leakage features: same phase in this period and the previous one
                has = state[_HAS_PREV] != 0.0
                f[1] = mean2 - state[_PREV + 1]
                f[0] = mean1 - state[_PREV] - f[1]
                f[2] = state[_TSUM]
                f[4] = slope2 - state[_PREV + 3]
                f[3] = slope1 - state[_PREV + 2] - f[4]
                for r in range(3):
                    for j in range(H):
                        for k in range(K):
                            i2 = o_vf + (r * H + j) * K + k
                            S2[i2] = lam * S2[i2] + (acc[r, j] * f[k] if has else 0.0)
                for k in range(K):
                    for k2 in range(K):
                        i2 = o_ff + k * K + k2
                        S2[i2] = lam * S2[i2] + (f[k] * f[k2] if has else 0.0)
                    S2[o_f + k] = lam * S2[o_f + k] + (f[k] if has else 0.0)
                S2[o_wf] = lam * S2[o_wf] + (1.0 if has else 0.0)
                # shifted by more than MOVED_STEPS of the smallest step seen: new quantization errors
                moved1 = has and qmin[0] > 0.0 and abs(mean1 - state[_PREV]) > MOVED_STEPS * qmin[0]
                moved2 = has and qmin[1] > 0.0 and abs(mean2 - state[_PREV + 1]) > MOVED_STEPS * qmin[1]
                S2[o_mv] = lam * S2[o_mv] + (1.0 if moved1 else 0.0)
                S2[o_mv + 1] = lam * S2[o_mv + 1] + (1.0 if moved2 else 0.0)
                state[_W] = lam * state[_W] + 1.0
                state[_W2] = lam * lam * state[_W2] + 1.0
                state[_USED] += 1.0
                added += 1
            state[_PREV] = mean1
            state[_PREV + 1] = mean2
            state[_PREV + 2] = slope1
            state[_PREV + 3] = slope2
            state[_HAS_PREV] = 1.0
            for i in range(4):
                state[_E + i] = 0.0
            state[_TSUM] = 0.0
            for j in range(H):
                idx[j] = 0
                for r in range(3):
                    acc[r, j] = 0.0
        state[_POS] = pos
    return added


rdft_accumulate = numba.njit(cache=True)(rdft_accumulate_py)


class StreamingFrequencyEstimator:
    """Recursive-DFT frequency estimator fed block by block (e.g. every 1 ms tick).

    period     : excitation period N in samples; sample 0 of the first block starts a period
    harmonics  : excited harmonic numbers (1 <= h < N/2)
    dt         : sample period [s]
    hold       : "zoh" (drive), "tustin" (Newmark with the load at both ends), "tustin_held"
    forgetting : per-period forgetting factor lam in (0, 1]
    discard_periods : completed periods ignored at the start (transient)
    transient  : estimate the leakage term (see rt_ident.estimators.frequency)
    quantum    : angle quantization steps; tracked from the data (smallest step) when None
    compiled   : False runs the same kernel interpreted (reference path for tests)
    """

    def __init__(self, period: int, harmonics: np.ndarray, dt: float, hold: str = "zoh",
                 forgetting: float = 1.0, *, discard_periods: int = 0, transient: bool = True,
                 quantum: tuple[float, float] | None = None, lead: float = DEFAULT_LEAD,
                 max_iter: int = 50, compiled: bool = True) -> None:
        if isinstance(period, bool) or not isinstance(period, (int, np.integer)) or period < 4:
            raise ConfigError("period", f"must be an integer >= 4 samples, got {period!r}")
        h = np.asarray(harmonics)
        if h.ndim != 1 or h.size == 0 or not np.issubdtype(h.dtype, np.integer):
            raise ConfigError("harmonics", "must be a non-empty 1-D array of integers")
        if h.min() < 1 or h.max() >= period / 2:
            raise ConfigError("harmonics", f"must lie in 1..{(int(period) - 1) // 2}")
        if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0.0):
            raise ConfigError("dt", f"must be finite and > 0, got {dt!r}")
        if not (isinstance(forgetting, (int, float)) and 0.0 < forgetting <= 1.0):
            raise ConfigError("forgetting", f"must be in (0, 1], got {forgetting!r}")
        if isinstance(discard_periods, bool) or not isinstance(discard_periods, int) or discard_periods < 0:
            raise ConfigError("discard_periods", f"must be an integer >= 0, got {discard_periods!r}")
        self.period = int(period)
        self.harmonics = np.ascontiguousarray(h, dtype=np.int64)
        self.dt = float(dt)
        self.hold = check_hold(hold)
        self.forgetting = float(forgetting)
        self.discard_periods = discard_periods
        self.transient = bool(transient)
        self.quantum = None if quantum is None else np.asarray(quantum, dtype=float)
        self.lead = float(lead)
        self.max_iter = int(max_iter)
        self._kernel = rdft_accumulate if compiled else rdft_accumulate_py
        H = self.harmonics.size
        self._table = np.exp(-2j * np.pi * np.arange(self.period) / self.period)
        self._idx = np.zeros(H, dtype=np.int64)
        self._acc = np.zeros((3, H), complex)
        self._S1 = np.zeros((3, H), complex)
        self._S2 = np.zeros(sums_layout(H)["size"], complex)     # S2, then the leakage features' sums
        self._state = np.zeros(STATE_SIZE)
        self._state[_M] = leak_window(self.period)
        self._last = np.zeros(3)
        self._qmin = np.zeros(2)
        self._count = np.zeros(1, dtype=np.int64)     # samples fed (in place: see rt_ident.loop.tick_core)
        self._fit: FitResult | None = None

    # -- feeding ------------------------------------------------------------------------
    def update_block(self, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray) -> int:
        """Add a block of samples; returns how many periods were completed and used."""
        a = np.ascontiguousarray(theta1, dtype=np.float64)
        b = np.ascontiguousarray(theta2, dtype=np.float64)
        c = np.ascontiguousarray(torque, dtype=np.float64)
        if a.ndim != 1 or a.shape != b.shape or a.shape != c.shape:
            raise DataError("theta1/theta2/torque: blocks must be 1-D and of equal length")
        if first_non_finite3(a, b, c) >= 0:
            raise DataError("theta1/theta2/torque: block contains non-finite values")
        self._count[0] += a.size
        return int(self._kernel(a, b, c, self.harmonics, self._table, self._idx, self._acc, self._S1,
                                self._S2, self._state, self._last, self._qmin, self.forgetting,
                                self.discard_periods))

    def skip(self, n: int) -> None:
        """The next ``n`` samples are not to be used (a loop stall: no excitation, a coasting table):
        every period they touch, and the one after (the resumed loop's transient), stays out of the sums."""
        if n <= 0:
            return
        st = self._state
        touched = (int(st[_POS]) + int(n)) // self.period + 1
        st[_SKIP] = max(st[_SKIP], st[_DONE] + touched + 1)

    @property
    def periods(self) -> int:
        """Periods accumulated in the sums (after the discarded ones)."""
        return int(self._state[_USED])

    @property
    def n_samples(self) -> int:
        return int(self._count[0])

    def sums(self) -> SpectraSums:
        """The running sums now (copies): what :meth:`spectra` and the fit process make the spectra from."""
        q = self.quantum if self.quantum is not None else self._qmin.copy()
        return SpectraSums.from_flat(self.harmonics, self.period, self.dt, self._S1.copy(), self._S2.copy(),
                                     float(self._state[_W]), float(self._state[_W2]), self.periods, q)

    def spectra(self) -> Spectra:
        """The accumulated period-averaged spectra (EstimationError before the first period)."""
        return self.sums().spectra()

    # -- estimating ---------------------------------------------------------------------
    def estimate(self, max_iter: int | None = None) -> Identification:
        """Fit the accumulated spectra, warm-started from the previous estimate."""
        sp = self.spectra()
        x0 = None if self._fit is None else self._fit.x
        fit = fit_spectra(sp, self.hold, transient=self.transient, x0=x0,
                          max_iter=self.max_iter if max_iter is None else int(max_iter))
        self._fit = fit
        return identification_from_fit(sp, fit, self.hold, lead=self.lead, n_samples=self.n_samples)

    def reset(self) -> None:
        """Forget everything (the next sample starts a period)."""
        for arr in (self._idx, self._acc, self._S1, self._S2, self._state, self._last, self._qmin, self._count):
            arr[...] = 0
        self._state[_M] = leak_window(self.period)
        self._fit = None

"""Per-sample recursive estimate of (I1, I2, B, K) through a state-variable filter (beyond the paper).

The paper's Eqs. (9)-(10) difference the sampled angles twice; on a 2^17-count encoder and a
0.1 um scale that amplifies quantization into the regressors and the estimate is biased
(the noise study shows it). Here nothing differentiates a raw angle:

* **State-variable filter.** Every signal u (theta1, theta1 - theta2, theta2, the torque) goes
  through the same low-pass F(s) = lam^3 / (s + lam)^3, realized as a chain whose states are
  F u, s F u and s^2 F u: the filtered derivatives come out of the filter, exactly. Because F is
  linear and time-invariant, the continuous-time model of Eq. (3) holds for the filtered signals:

      I1 s^2 F th1 + B s F (th1 - th2) + K F (th1 - th2) = F T          (motor)
      I2 s^2 F th2 - B s F (th1 - th2) - K F (th1 - th2) = 0            (table)

  two rows per sample, linear in (I1, I2, B, K). The filter is discretized exactly: angles as
  first-order hold (they are continuous signals sampled), the torque as zero-order hold (the
  drive holds it over the sample). The paper's Eq. (9) discretization is not used.
* **Bias compensation.** Quantization and encoder noise enter the regressors (errors in
  variables), which biases least squares by the noise's covariance in the regressors. That
  covariance is known: the quantum q gives q^2/12 per angle, and the filter's own impulse
  response maps it into the regressors (:func:`regressor_noise`). The estimate solves
  ``(R - W Sigma) p = r`` instead of ``R p = r`` (bias-compensated least squares).
  Closed loop: the controller's torque depends on the noise only through the state estimate and
  at least one tick of delay; the filter's memory (a few 1/lam) is far shorter than a tick, so
  the torque is uncorrelated with the regressor noise it sees (no instrumental variable needed at
  the sim's and the serial board's rates; at the CANopen drive's 2 kHz the filter is too close
  to the sample rate and the estimate is biased: the frequency cross-check then keeps it
  untrusted).
* **Forgetting with windup protection.** R and r forget with ``lam_f`` per sample; stabilized
  forgetting adds ``(1 - lam_f) rho I`` (and ``(1 - lam_f) rho p_prior`` to r), so in directions
  the data stop exciting R decays to ``rho I`` and the estimate to the prior instead of blowing up.
  Parameters are scaled by the nominal axis so the four columns are of one size.
* **Dead zone.** Stabilized forgetting alone does not stop a drift when the axis sits still and
  only sensor noise moves the regressors (noise says "motion without torque"). So rows update the
  estimate only while the rms of the filtered torque over a tenth of the memory is above
  ``min_torque``;
  below it the estimate freezes (the gate is a slow average, not a per-sample test on the
  regressand, which would bias the regression by selection).
* **NaN rejection.** A sample with a non-finite angle or torque is skipped (counted) and the
  filter holds its state.
* **Change detection** (beyond the paper). A one-sided CUSUM (Page's test) on the log ratio of the
  a-priori residual's short-term power (~2 ms) to its long-term baseline (~0.5 s):
  ``g = max(0, g + ln(fast / base) - ln(change_ratio))``, an alarm when ``g > change_threshold``.
  On an alarm the information is discounted at once (R, r and the weights x ``change_discount``:
  a covariance reset), so the estimate follows the new plant within a few memory-free
  milliseconds instead of ~3 memory time constants; the baseline then re-learns for
  ``change_rearm_s`` with the short time constant before the test is armed again.

The information form (R, r) is used rather than the UD-factored covariance of
:mod:`rt_ident.estimators.rls` because bias compensation subtracts from the information matrix;
with four parameters the per-sample solve is a 4 x 4 elimination (~0.2 us compiled).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg

from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError

KEYS = ("I1", "I2", "B", "K")


@dataclass(frozen=True)
class SvfSettings:
    filter_hz: float = 800.0        # corner of F(s) = lam^3/(s + lam)^3; must pass the resonance
    memory_s: float = 0.05          # forgetting time constant (estimate follows a change in ~3x this)
    rho: float = 1e-6               # stabilized-forgetting floor (scaled units, N^2 m^2 per sample)
    q1: float = 0.0                 # rad, motor-encoder quantum (0: none)
    q2: float = 0.0                 # rad, table quantum referred to theta2 (scale resolution / lead)
    bias_compensation: bool = True
    warmup_s: float = 0.005         # filter start-up: no regression rows before this
    min_torque: float = 0.002       # N m: below this rms of the filtered torque (over the memory) the
                                    # data are noise only; the estimate freezes instead of drifting
    change_ratio: float = 3.0       # residual power x this over its baseline counts toward a change
    change_threshold: float = 8.0   # CUSUM alarm level (sum of per-sample log ratios beyond change_ratio)
    change_discount: float = 0.01   # the information kept at an alarm (0 < d <= 1; 1: detection only)
    change_rearm_s: float = 0.05    # after an alarm (and at start) the baseline re-learns this long

    def check(self, dt: float) -> None:
        if not self.filter_hz > 0 or not self.memory_s > 0:
            raise ConfigError("estimator.svf_hz", "svf_hz and svf_memory_s must be > 0")
        if self.filter_hz * dt > 0.25:
            raise ConfigError("estimator.svf_hz", f"{self.filter_hz:g} Hz is too close to the sample rate "
                                                  f"{1 / dt:g} Hz (needs svf_hz <= sample rate / 4)")


def filter_matrices(lam: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact discretization of x' = A x + b u for F(s) = lam^3/(s+lam)^3, x = (F u, s F u, s^2 F u).

    Returns (Phi, G_foh0, G_foh1, G_zoh): for a first-order-hold input
    x+ = Phi x + G_foh0 u_k + G_foh1 (u_k+1 - u_k); for a zero-order-hold input x+ = Phi x + G_zoh u_k.
    """
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-lam**3, -3 * lam**2, -3 * lam]])
    b = np.array([0.0, 0.0, lam**3])
    M = np.zeros((5, 5))
    M[:3, :3] = A
    M[:3, 3] = b
    M[3, 4] = 1.0 / dt                      # u(t) = u_k + (t/dt) (u_k+1 - u_k)
    E = scipy.linalg.expm(M * dt)
    return E[:3, :3].copy(), E[:3, 3].copy(), E[:3, 4].copy(), E[:3, 3].copy()


def _impulse_states(Phi: np.ndarray, G0: np.ndarray, G1: np.ndarray, n: int) -> np.ndarray:
    """Filter states after a unit impulse in an FOH-interpolated input at sample 0, n samples."""
    out = np.empty((n, 3))
    x = G1.copy()                                      # step 0 -> 1 with u_0 = 0, u_1 = 1 ... see below
    # sample sequence u = (0, 1, 0, 0, ...): step (u0=0 -> u1=1): G0*0 + G1*(1 - 0); then (1 -> 0): G0*1 + G1*(-1)
    out[0] = x
    x = Phi @ x + G0 - G1
    out[1] = x
    for k in range(2, n):
        x = Phi @ x
        out[k] = x
    return out


def regressor_noise(settings: SvfSettings, nominal: AxisParams, dt: float) -> np.ndarray:
    """Sigma: the per-sample covariance that white quantization noise adds to phi1 phi1' + phi2 phi2'
    (scaled regressors), from the filter's impulse response."""
    lam = 2 * math.pi * settings.filter_hz
    Phi, G0, G1, _ = filter_matrices(lam, dt)
    h = _impulse_states(Phi, G0, G1, int(40 / (lam * dt)) + 10)     # (n, 3): F e, sF e, s^2F e
    C = h.T @ h                                                      # per unit noise variance
    v1, v2 = settings.q1**2 / 12.0, settings.q2**2 / 12.0
    I1n, I2n, Bn, Kn = (float(getattr(nominal, k)) for k in KEYS)
    # regressor noise = M_a s(e1) + M_b s(e2), s(e) = (F e, sF e, s^2F e); the Delta channel carries e1 - e2
    # phi1 = (I1n s^2F th1, 0, Bn sF D, Kn F D);  phi2 = (0, I2n s^2F th2, -Bn sF D, -Kn F D)
    m1a = np.array([[0, 0, I1n], [0, 0, 0], [0, Bn, 0], [Kn, 0, 0]], float)          # e1 in phi1
    m1b = np.array([[0, 0, 0], [0, 0, 0], [0, -Bn, 0], [-Kn, 0, 0]], float)          # e2 in phi1
    m2a = np.array([[0, 0, 0], [0, 0, 0], [0, -Bn, 0], [-Kn, 0, 0]], float)          # e1 in phi2
    m2b = np.array([[0, 0, 0], [0, 0, I2n], [0, Bn, 0], [Kn, 0, 0]], float)          # e2 in phi2
    return (v1 * (m1a @ C @ m1a.T + m2a @ C @ m2a.T) + v2 * (m1b @ C @ m1b.T + m2b @ C @ m2b.T))


@numba.njit(cache=True)
def _solve4(A: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """Gaussian elimination with partial pivoting on a 4 x 4 system; False when (near) singular."""
    M = np.empty((4, 5))
    for i in range(4):
        for j in range(4):
            M[i, j] = A[i, j]
        M[i, 4] = b[i]
    scale = 0.0
    for i in range(4):
        scale = max(scale, abs(M[i, i]))
    if not scale > 0.0:
        return False
    for c in range(4):
        p = c
        for i in range(c + 1, 4):
            if abs(M[i, c]) > abs(M[p, c]):
                p = i
        if abs(M[p, c]) < 1e-12 * scale:
            return False
        if p != c:
            for j in range(5):
                M[c, j], M[p, j] = M[p, j], M[c, j]
        for i in range(c + 1, 4):
            f = M[i, c] / M[c, c]
            for j in range(c, 5):
                M[i, j] -= f * M[c, j]
    for i in range(3, -1, -1):
        s = M[i, 4]
        for j in range(i + 1, 4):
            s -= M[i, j] * out[j]
        out[i] = s / M[i, i]
    for i in range(4):
        if not math.isfinite(out[i]):
            return False
    return True


#: columns of a block's trace (svf_block's ``trace``): the filtered signals of Eq. (18)'s motor row
TR_S2F_TH1, TR_SF_DELTA, TR_F_DELTA, TR_F_TORQUE, TR_COLS = range(5)
NO_TRACE = np.zeros((0, TR_COLS))


@numba.njit(cache=True)
def svf_block(th1, th2, tq, Phi, G0, G1, Gz, xs, prev, scale, lam_f, rho, prior, Sigma,
              R, r, acc, p, tmp, counts, min_torque2, lam_g, trace):
    """Advance the estimator over one block (every sample).

    xs (4, 3): filter states for theta1, Delta, theta2, torque; prev (4,): last theta1, theta2,
    torque, and 1.0 once a first sample was seen; acc (ACC_SIZE,): the ACC_* slots (sums, the change
    detector's state and its settings); counts (5,): samples, rejected (non-finite), rows, solve
    failures, rows frozen by the dead zone.
    trace (n, TR_COLS), or no rows: each sample's s^2 F th1, s F Delta, F Delta and F T (NaN for a
    sample the filters did not take, and through their warm-up).
    """
    n = th1.shape[0]
    keep = trace.shape[0] > 0
    phi1 = np.empty(4)
    phi2 = np.empty(4)
    for k in range(n):
        a, b, t = th1[k], th2[k], tq[k]
        counts[0] += 1.0
        if keep:
            for j in range(TR_COLS):
                trace[k, j] = np.nan
        if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(t)):
            counts[1] += 1.0
            continue
        if prev[3] == 0.0:                       # first sample: start the filters at rest on it
            xs[0, 0], xs[1, 0], xs[2, 0] = a, a - b, b
            prev[0], prev[1], prev[2], prev[3] = a, b, t, 1.0
            continue
        d0, d1 = prev[0] - prev[1], a - b
        u0 = (prev[0], d0, prev[1])
        u1 = (a, d1, b)
        for s in range(3):                       # angles: first-order hold between the samples
            x0, x1, x2 = xs[s, 0], xs[s, 1], xs[s, 2]
            du = u1[s] - u0[s]
            for i in range(3):
                xs[s, i] = Phi[i, 0] * x0 + Phi[i, 1] * x1 + Phi[i, 2] * x2 + G0[i] * u0[s] + G1[i] * du
        x0, x1, x2 = xs[3, 0], xs[3, 1], xs[3, 2]
        for i in range(3):                       # torque: held over the sample it was applied in
            xs[3, i] = Phi[i, 0] * x0 + Phi[i, 1] * x1 + Phi[i, 2] * x2 + Gz[i] * prev[2]
        prev[0], prev[1], prev[2] = a, b, t
        counts[2] += 1.0
        if counts[2] <= acc[3]:                  # acc[3] holds the warm-up length in samples
            continue
        if keep:
            trace[k, TR_S2F_TH1], trace[k, TR_SF_DELTA] = xs[0, 2], xs[1, 1]
            trace[k, TR_F_DELTA], trace[k, TR_F_TORQUE] = xs[1, 0], xs[3, 0]
        # Eq. (3) on the filtered signals, scaled by the nominal parameters
        phi1[0] = scale[0] * xs[0, 2]
        phi1[1] = 0.0
        phi1[2] = scale[2] * xs[1, 1]
        phi1[3] = scale[3] * xs[1, 0]
        phi2[0] = 0.0
        phi2[1] = scale[1] * xs[2, 2]
        phi2[2] = -phi1[2]
        phi2[3] = -phi1[3]
        y1 = xs[3, 0]
        acc[4] = lam_g * acc[4] + (1.0 - lam_g) * y1 * y1
        if acc[4] < min_torque2:
            counts[4] += 1.0
            continue
        e1 = y1 - (phi1[0] * p[0] + phi1[2] * p[2] + phi1[3] * p[3])
        e2 = -(phi2[1] * p[1] + phi2[2] * p[2] + phi2[3] * p[3])
        _detect_change(e1 * e1 + e2 * e2, y1 * y1, acc, R, r)
        g = 1.0 - lam_f
        acc[0] = lam_f * acc[0] + 1.0
        acc[1] = lam_f * acc[1] + e1 * e1 + e2 * e2
        acc[2] = lam_f * lam_f * acc[2] + 1.0
        for i in range(4):
            r[i] = lam_f * r[i] + phi1[i] * y1 + g * rho * prior[i]
            for j in range(4):
                R[i, j] = lam_f * R[i, j] + phi1[i] * phi1[j] + phi2[i] * phi2[j]
            R[i, i] += g * rho
        for i in range(4):
            for j in range(4):
                tmp[i, j] = R[i, j] - acc[0] * Sigma[i, j]
        if not _solve4(tmp, r, phi1):
            counts[3] += 1.0
            continue
        for i in range(4):
            p[i] = phi1[i]


# acc slots: the regression's weight W, its sum of squared a-priori residuals, W2 (sum of squared
# weights), the warm-up end (rows), the dead zone's mean square filtered torque; the change detector's
# fast and baseline residual power, CUSUM sum, alarms, samples left to re-arm; its settings: alarm
# level, ln(change_ratio), the fast and the baseline forgetting factors, the discount, re-arm samples;
# the filtered torque's baseline power
(ACC_W, ACC_SSE, ACC_W2, ACC_WARM, ACC_TQ2, ACC_FAST, ACC_BASE, ACC_CUSUM, ACC_ALARMS, ACC_REARM,
 ACC_H, ACC_NU, ACC_LAM_FAST, ACC_LAM_BASE, ACC_DISCOUNT, ACC_REARM_N, ACC_TQ_BASE, ACC_SIZE) = range(18)


#: the change detector's time constants: the residual's short-term power, its baseline
CHANGE_FAST_S = 0.002
CHANGE_BASE_S = 0.5


@numba.njit(cache=True)
def _detect_change(q, tq2, acc, R, r):
    """One sample of the change detector (see the module docstring): ``q`` is the squared a-priori
    residual, ``tq2`` the squared filtered torque. On an alarm R, r and the weights are discounted in
    place. While the excitation has fallen below a quarter of its baseline power the test pauses: a
    residual that grows as the excitation dies away is the data changing, not the plant."""
    lf = acc[ACC_LAM_FAST]
    lb = acc[ACC_LAM_BASE]
    acc[ACC_FAST] = lf * acc[ACC_FAST] + (1.0 - lf) * q
    acc[ACC_TQ_BASE] = lb * acc[ACC_TQ_BASE] + (1.0 - lb) * tq2
    if acc[ACC_REARM] > 0.0:                     # (re-)learning the baseline, fast
        acc[ACC_REARM] -= 1.0
        acc[ACC_BASE] = lf * acc[ACC_BASE] + (1.0 - lf) * q
        return
    acc[ACC_BASE] = lb * acc[ACC_BASE] + (1.0 - lb) * q
    if not (acc[ACC_BASE] > 0.0 and acc[ACC_FAST] > 0.0) or acc[ACC_TQ2] < 0.25 * acc[ACC_TQ_BASE]:
        acc[ACC_CUSUM] = 0.0
        return
    acc[ACC_CUSUM] = max(0.0, acc[ACC_CUSUM] + math.log(acc[ACC_FAST] / acc[ACC_BASE]) - acc[ACC_NU])
    if acc[ACC_CUSUM] <= acc[ACC_H]:
        return
    d = acc[ACC_DISCOUNT]
    for i in range(4):
        r[i] *= d
        for j in range(4):
            R[i, j] *= d
    acc[ACC_W] *= d
    acc[ACC_SSE] *= d
    acc[ACC_W2] *= d * d
    acc[ACC_CUSUM] = 0.0
    acc[ACC_ALARMS] += 1.0
    acc[ACC_REARM] = acc[ACC_REARM_N]


@numba.njit(cache=True)
def interval_halves(R, Sigma, acc, scale, out):
    """The 95 % half-widths of (I1, I2, B, K), physical units, into ``out``: from the bias-compensated
    information matrix and the residual variance, under a white-residual assumption (the filtered
    residuals are coloured, so these are optimistic). False with too little data or a singular matrix."""
    W, sse, W2 = acc[ACC_W], acc[ACC_SSE], acc[ACC_W2]
    if W <= 4.0:
        return False
    try:
        Rinv = np.linalg.inv(R - W * Sigma)
    except Exception:  # noqa: BLE001 - singular or not finite; compiled code catches only Exception
        return False
    sigma2 = sse / (2.0 * W)
    for i in range(4):
        var = sigma2 * Rinv[i, i] * (W2 / W) * W / max(W - 4.0, 1.0)
        out[i] = 1.96 * math.sqrt(max(var, 0.0)) * scale[i]
    return True


class SvfEstimator:
    """The per-sample estimator the adaptive loop feeds (see the module docstring).

    ``update_block(theta1, theta2, torque)`` runs every sample of a block (compiled);
    ``params`` is the estimate after the newest sample; ``ci95()`` an approximate interval.
    """

    def __init__(self, dt: float, nominal: AxisParams, settings: SvfSettings | None = None) -> None:
        self.s = settings or SvfSettings()
        self.s.check(dt)
        self.dt = float(dt)
        self.nominal = nominal
        lam = 2 * math.pi * self.s.filter_hz
        self._Phi, self._G0, self._G1, self._Gz = filter_matrices(lam, dt)
        self._scale = np.array([float(getattr(nominal, k)) for k in KEYS])
        self.lam_f = math.exp(-dt / self.s.memory_s)
        self.lam_g = math.exp(-dt / (0.1 * self.s.memory_s))   # the dead zone's average: closes fast
        self._Sigma = (regressor_noise(self.s, nominal, dt) if self.s.bias_compensation
                       else np.zeros((4, 4)))
        self._prior = np.ones(4)
        self.reset()
        z = np.zeros(2)                     # compile (or load) the kernels now, not in the loop's first tick
        self.update_block(z, z, z, np.zeros((2, TR_COLS)))
        self.reset()
        self.ci95()

    def reset(self) -> None:
        """Start over. The arrays are changed in place, never replaced: the compiled tick
        (rt_ident.loop.tick_core) holds views of them."""
        if not hasattr(self, "_xs"):
            self._xs = np.zeros((4, 3))
            self._prev = np.zeros(4)
            self._R = np.zeros((4, 4))
            self._r = np.zeros(4)
            self._acc = np.zeros(ACC_SIZE)
            self._p = np.zeros(4)
            self._tmp = np.zeros((4, 4))
            self._counts = np.zeros(5)   # samples, rejected, rows, solve failures, frozen
        for a in (self._xs, self._prev, self._R, self._r, self._acc, self._tmp, self._counts):
            a[...] = 0.0
        a, st = self._acc, self.s
        a[ACC_WARM] = float(math.ceil(st.warmup_s / self.dt))
        a[ACC_H], a[ACC_NU], a[ACC_DISCOUNT] = st.change_threshold, math.log(st.change_ratio), st.change_discount
        a[ACC_LAM_FAST] = math.exp(-self.dt / CHANGE_FAST_S)
        a[ACC_LAM_BASE] = math.exp(-self.dt / CHANGE_BASE_S)
        a[ACC_REARM] = a[ACC_REARM_N] = float(math.ceil(st.change_rearm_s / self.dt))
        self._p[:] = self._prior

    def restart_filter(self) -> None:
        """After lost samples: start the filters again on the next sample (the regression keeps its
        information; the first ``warmup_s`` of rows after the restart are skipped)."""
        self._prev[3] = 0.0
        self._acc[3] = self._counts[2] + math.ceil(self.s.warmup_s / self.dt)

    def update_block(self, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray,
                     trace: np.ndarray | None = None) -> None:
        """``trace`` (optional, (n, TR_COLS) C-contiguous float64) receives each sample's filtered
        signals (see :func:`svf_block`)."""
        if trace is None:
            trace = NO_TRACE
        elif trace.shape != (len(theta1), TR_COLS) or trace.dtype != np.float64 or not trace.flags.c_contiguous:
            raise ValueError(f"trace must be C-contiguous float64 of shape {(len(theta1), TR_COLS)}")
        svf_block(np.ascontiguousarray(theta1, dtype=np.float64), np.ascontiguousarray(theta2, dtype=np.float64),
                  np.ascontiguousarray(torque, dtype=np.float64), self._Phi, self._G0, self._G1, self._Gz,
                  self._xs, self._prev, self._scale, self.lam_f, self.s.rho, self._prior, self._Sigma,
                  self._R, self._r, self._acc, self._p, self._tmp, self._counts, self.s.min_torque ** 2,
                  self.lam_g, trace)

    @property
    def ready(self) -> bool:
        """True once the regression has seen about three memory time constants of data."""
        return self._counts[2] >= 3.0 * self.s.memory_s / self.dt + math.ceil(self.s.warmup_s / self.dt)

    @property
    def scaled(self) -> np.ndarray:
        return self._p.copy()

    @property
    def params(self) -> AxisParams:
        v = self._p * self._scale
        return AxisParams(**{k: float(max(x, 1e-30)) for k, x in zip(KEYS, v)}, lead=self.nominal.lead)

    def values(self) -> dict[str, float]:
        return {k: float(x) for k, x in zip(KEYS, self.values_array())}

    def values_array(self) -> np.ndarray:
        """(I1, I2, B, K) now, physical units."""
        return self._p * self._scale

    def ci95(self) -> dict[str, tuple[float, float]] | None:
        """Approximate 95 % intervals (:func:`interval_halves`) around the estimate now; None with too
        little data or a singular information matrix."""
        half = np.empty(4)
        if not interval_halves(self._R, self._Sigma, self._acc, self._scale, half):
            return None
        v = self._p * self._scale
        return {k: (float(v[i] - half[i]), float(v[i] + half[i])) for i, k in enumerate(KEYS)}

    @property
    def evidence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(R, Sigma, accumulators, scaled estimate, scale): what a compiled look at the estimate and its
        intervals reads (rt_ident.control.adaptation.window_look). Changed in place, never replaced."""
        return self._R, self._Sigma, self._acc, self._p, self._scale

    @property
    def changes(self) -> int:
        """Changes the residual test has detected (each discounted the information)."""
        return int(self._acc[ACC_ALARMS])

    @property
    def frozen(self) -> int:
        """Rows the dead zone has held back so far (the estimate does not move while it does)."""
        return int(self._counts[4])

    @property
    def counters(self) -> dict[str, int]:
        c = self._counts
        return {"samples": int(c[0]), "rejected_non_finite": int(c[1]), "rows": int(c[2]),
                "solve_failures": int(c[3]), "frozen_unexcited": int(c[4]), "changes_detected": self.changes}


def make_svf(dt: float, nominal: AxisParams, *, filter_hz: float, memory_s: float,
             quanta: tuple[float, float]) -> tuple[SvfEstimator | None, str | None]:
    """The per-sample estimator for a sample period ``dt``, or (None, why) when the sample rate is too
    low for the filter (the CANopen drive's 2 kHz: the adaptive loop then follows the frequency fit)."""
    settings = SvfSettings(filter_hz=filter_hz, memory_s=memory_s, q1=float(quanta[0]), q2=float(quanta[1]))
    try:
        return SvfEstimator(dt, nominal, settings), None
    except ConfigError as exc:
        return None, str(exc)

"""Frequency-domain identification from periodic excitation (beyond the paper).

Bench data are angles only, quantized, with a noisy torque and the drive's position
loop closed: time-domain equation error (the paper's Eq. 9-10, and even the exact
regressions of :mod:`consistent`) is then biased, because the noise sits in the
regressors and is fed back into the input. A periodic excitation (the paper's
Schroeder multisine, period N samples) removes that bias:

1. period-averaged spectra of theta1, theta2, T at the excited harmonics, with their
   period-to-period covariance (:mod:`rt_ident.estimators.spectra`);
2. initialize with a linear equation-error fit of Eq. (3) per harmonic,
   ``I1 s^2 Th1 + (B s + K)(Th1 - Th2) = T`` and ``I2 s^2 Th2 - (B s + K)(Th1 - Th2) = 0``;
3. refine by Gauss-Newton on the *exact sampled* model Theta(z) = G(z; p) T(z) + R(z; p) c
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
from typing import Literal, overload

import numpy as np

from rt_ident.errors import ConfigError, EstimationError
from rt_ident.estimators.base import Identification
from rt_ident.estimators.sampled_model import HOLDS, POS, check_hold, frequency_response, hold_model  # noqa: F401
from rt_ident.estimators.spectra import MIN_SNR, Spectra, compute_spectra
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
MAX_CHI2 = 10.0         # weighted residual per degree of freedom: above, the model does not explain the data
#: what makes a periodic response the linear two-inertia model cannot fit, and what identifies such an axis
MISFIT_CAUSES = ("friction or backlash the linear model lacks, or a plant that changed during the fit; "
                 "with friction, `rt-ident identify RECORDING --model two-inertia-friction` fits it")
_TOL = 1e-10            # Gauss-Newton stop: largest step in log-parameters


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


def _fit_among_aliases(sp: Spectra, hold: str, start: np.ndarray, *, max_iter: int, tol: float) -> FitResult:
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
    best = _gauss_newton(sp, hold, x0=start, max_iter=max_iter, tol=tol)
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
            alt = _gauss_newton(sp, hold, x0=mirror, max_iter=max_iter, tol=tol)
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
    than a quarter step (:data:`~rt_ident.estimators.spectra.MOVED_STEPS`) counts as new; that error sits
    in the period scatter S and averages out. ``moved`` is the share of the periods that shifted (None: taken as 0); the
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
    A fit that stops unconverged is logged as a warning unless ``quiet`` (its
    :class:`FitResult` and the identification's checks say so either way).
    """
    hold = check_hold(hold)
    n_x = 8 if transient else 4
    if x0 is None:
        x = np.concatenate([linear_init(sp, hold), np.zeros(n_x - 4)])
    else:
        x = np.array(x0, dtype=float)[:n_x]
        if x.size < n_x:
            x = np.concatenate([x, np.zeros(n_x - x.size)])
    if x0 is None and hold == "zoh":
        fit = _fit_among_aliases(sp, hold, x, max_iter=max_iter, tol=tol)
    else:
        fit = _gauss_newton(sp, hold, x0=x, max_iter=max_iter, tol=tol)
    if not fit.converged and not quiet:
        logger.warning("frequency: Gauss-Newton stopped after %d iterations without converging", fit.iterations)
    return fit


def _gauss_newton(sp: Spectra, hold: str, *, x0: np.ndarray, max_iter: int, tol: float) -> FitResult:
    """:func:`fit_spectra`'s iteration from ``x0`` (4 or 8 entries: with the leakage terms or not)."""
    x = np.array(x0, dtype=float)
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
                        f"{MAX_CHI2:g} (residuals {math.sqrt(fit.s2):.3g} x the noise): {MISFIT_CAUSES}")]
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

"""Trust signals: parameter covariance -> 95 % intervals, and a persistence-of-excitation monitor.

Intervals
---------
Every estimator here works with (or converts to) the covariance of the *log*
parameters ``theta = log [I1, I2, B, K]``. Intervals are log-normal,
``value * exp(+-1.96 sigma_log)``: they never cross zero and coincide with the
usual ``value +- 1.96 sigma`` when the relative error is small. Modal parameters
(wn, wd, zeta) get theirs by propagating the covariance through the Jacobian of
:func:`rt_ident.axis.modal.modal_parameters`, taken by central differences in log space.

Persistence of excitation
-------------------------
A regression ``y = X p`` is persistently exciting when its information matrix
``X^T X`` is well conditioned (Eq. 11: ``P = [A^T A]^-1`` must exist). Raw
information matrices mix units, so the monitor normalizes each column to unit norm
(``X^T X`` becomes a correlation matrix with unit diagonal, eigenvalues in
``[0, m]``) and reports its smallest eigenvalue and condition number. The
smallest eigenvalue is the squared fraction of the weakest regressor direction
that no combination of the others explains: ``MIN_EIG = 1e-4`` asks that at
least 1 % of it be independent (below that, noise in that direction is amplified
more than 100 times). The estimators monitor the motor equation of Eq. (3)
(columns of I1, B, K; the table equation has a zero right side, so its regressor
is singular by construction) and the stacked regression. A single sine in steady
state leaves the motor regressor rank-deficient (three columns spanned by one sine
and one cosine) and fails; the broadband Schroeder multisine gives min_eig of
0.2-0.7 (see tests/estimators/test_uncertainty.py).

``trusted`` additionally requires every physical parameter's 95 % interval to exist, be
finite and narrower than +-``MAX_REL_HALFWIDTH`` (10 %) of its value, which catches zero
excitation (noise alone can be "well conditioned" but gives wide intervals); a missing
interval fails this criterion, it is never left out. The resonance must lie in the band the
excitation covered (:func:`resonance_criterion`): a mode fitted outside it is an
extrapolation. The frequency estimator also requires the torque lines to stand above the
noise and the fit to explain the data.

The verdict is never more optimistic than its evidence: a criterion that cannot be evaluated
(no covariance, no band) fails, with the reason.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rt_ident.axis.modal import modal_parameters
from rt_ident.axis.params import AxisParams
from rt_ident.errors import EstimationError
from rt_ident.estimators.base import MODAL_KEYS, PARAM_KEYS, Identification

logger = logging.getLogger(__name__)

Z95 = 1.959963984540054          # two-sided 95 % quantile of the normal distribution
MIN_EIG = 1e-4                   # smallest eigenvalue of the normalized information matrix
MAX_COND = 1e6                   # largest condition number of the normalized information matrix
MAX_REL_HALFWIDTH = 0.10         # widest accepted 95 % half-width, relative, on I1, I2, B, K
#: how the interval criterion's name starts (``interval_criterion``); readers match on it
INTERVAL_CRITERION = "widest 95 % interval"
_MODAL_STEP = 1e-5               # central-difference step in log-parameter space


# --------------------------------------------------------------------------- parameters <-> log
def log_params(p: AxisParams) -> np.ndarray:
    """``log [I1, I2, B, K]``; EstimationError if B == 0 (no log-normal interval then)."""
    v = np.array([p.I1, p.I2, p.B, p.K])
    if np.any(v <= 0.0):
        raise EstimationError(f"parameters must be > 0 for log-space uncertainty, got {v.tolist()}")
    return np.log(v)


def params_from_log(theta: np.ndarray, lead: float) -> AxisParams:
    I1, I2, B, K = (float(x) for x in np.exp(theta))
    return AxisParams(I1=I1, I2=I2, B=B, K=K, lead=lead)


def params_from_vector(v: np.ndarray, lead: float, *, what: str) -> AxisParams:
    """AxisParams from a linear estimate [I1, I2, B, K]; EstimationError naming a non-positive one."""
    for key, x in zip(PARAM_KEYS, v):
        if not (math.isfinite(float(x)) and float(x) > 0.0):
            raise EstimationError(
                f"{what}: estimated {key} = {float(x):.6g} is not positive; the data do not determine it "
                f"(too little excitation, too much noise, or the wrong method for how the data were made)")
    return AxisParams(I1=float(v[0]), I2=float(v[1]), B=float(v[2]), K=float(v[3]), lead=lead)


# --------------------------------------------------------------------------- covariance
def covariance_from_jacobian(J: np.ndarray, residual: np.ndarray, *, min_scale: float = 0.0
                             ) -> tuple[np.ndarray, float]:
    """``max(s^2, min_scale) (J^T J)^-1``, ``s^2 = ||r||^2 / (rows - cols)``, for a whitened LS problem.

    With absolute weights (known noise levels) pass ``min_scale=1``: the residual may
    then widen the intervals (model error, underestimated noise) but never narrow them.
    Columns are scaled to unit norm before inverting. Returns (covariance, s^2).
    """
    J = np.asarray(J, dtype=float)
    m, n = J.shape
    dof = m - n
    if dof <= 0:
        return np.full((n, n), np.inf), math.inf
    s2 = float(residual @ residual) / dof
    return max(s2, min_scale) * inverse_normal_matrix(J), s2


def inverse_normal_matrix(J: np.ndarray) -> np.ndarray:
    """``(J^T J)^-1`` computed with column scaling (inf where singular)."""
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0.0] = 1.0
    Js = J / scale
    u, s, vt = np.linalg.svd(Js, full_matrices=False)
    if s.size == 0 or s[-1] <= s[0] * 1e-14:
        return np.full((J.shape[1], J.shape[1]), np.inf)
    inv = (vt.T / s**2) @ vt
    return inv / np.outer(scale, scale)


def log_covariance(p: AxisParams, cov: np.ndarray) -> np.ndarray:
    """Covariance of ``log [I1, I2, B, K]`` from that of ``[I1, I2, B, K]``."""
    v = np.array([p.I1, p.I2, p.B, p.K])
    return cov / np.outer(v, v)


def modal_jacobian(p: AxisParams, step: float = _MODAL_STEP) -> tuple[dict[str, float], np.ndarray]:
    """Modal parameters of ``p`` and their (3, 4) Jacobian w.r.t. log [I1, I2, B, K]."""
    theta = log_params(p)
    base = modal_parameters(p)
    J = np.empty((len(MODAL_KEYS), 4))
    for i in range(4):
        hi, lo = theta.copy(), theta.copy()
        hi[i] += step
        lo[i] -= step
        mh = modal_parameters(params_from_log(hi, p.lead))
        ml = modal_parameters(params_from_log(lo, p.lead))
        J[:, i] = [(mh[k] - ml[k]) / (2.0 * step) for k in MODAL_KEYS]
    return base, J


def intervals(p: AxisParams, cov_log: np.ndarray, z: float = Z95) -> dict[str, tuple[float, float]]:
    """Log-normal intervals ``value * exp(+-z sigma_log)`` on I1, I2, B, K, wn, wd, zeta."""
    cov_log = np.asarray(cov_log, dtype=float)
    theta = log_params(p)
    out: dict[str, tuple[float, float]] = {}
    sd = np.sqrt(np.clip(np.diag(cov_log), 0.0, None))
    modal, J = modal_jacobian(p)
    if np.all(np.isfinite(cov_log)):
        cov_m = J @ cov_log @ J.T
    else:
        cov_m = np.full((len(MODAL_KEYS), len(MODAL_KEYS)), np.inf)
    values = np.concatenate([np.exp(theta), [modal[k] for k in MODAL_KEYS]])
    with np.errstate(divide="ignore", invalid="ignore"):
        sd_m = np.sqrt(np.clip(np.diag(cov_m), 0.0, None)) / np.abs(values[4:])
    sd_all = np.concatenate([sd, sd_m])
    with np.errstate(over="ignore", invalid="ignore"):
        lo = values * np.exp(-z * sd_all)
        hi = values * np.exp(z * sd_all)
    for i, key in enumerate(PARAM_KEYS + MODAL_KEYS):
        if not np.isfinite(sd_all[i]):
            lo[i], hi[i] = 0.0, math.inf
        out[key] = (float(lo[i]), float(hi[i]))
    return out


def relative_halfwidths(ci: Mapping[str, tuple[float, float]], values: Mapping[str, float]) -> dict[str, float]:
    """``(hi - lo) / (2 |value|)`` per key."""
    return {k: (hi - lo) / (2.0 * abs(values[k])) if values[k] else math.inf for k, (lo, hi) in ci.items()}


def interval_problem(value: float, ci: tuple[float, float] | None) -> str | None:
    """Why ``ci`` is not a usable 95 % interval of ``value`` (None when it is): missing, not finite,
    of negative width, or not containing the value."""
    if ci is None:
        return "no interval"
    try:
        lo, hi = (float(c) for c in ci)
    except (TypeError, ValueError):
        return f"interval {ci!r} is not a pair of numbers"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"interval [{lo:.4g}, {hi:.4g}] is not finite"
    if hi < lo:
        return f"interval [{lo:.4g}, {hi:.4g}] has negative width"
    v, tol = float(value), 1e-9 * abs(float(value))     # rounding of exp(log(value))
    if not (math.isfinite(v) and lo - tol <= v <= hi + tol):
        return f"interval [{lo:.4g}, {hi:.4g}] does not contain the estimate {float(value):.4g}"
    return None


def interval_criterion(values: Mapping[str, float], ci: Mapping[str, tuple[float, float]] | None,
                       max_rel_halfwidth: float = MAX_REL_HALFWIDTH, *, why_missing: str = "") -> dict[str, Any]:
    """The interval criterion: every key of ``values`` has a finite 95 % interval containing its value,
    with half-width <= ``max_rel_halfwidth`` of the value. A missing, NaN, infinite or negative-width
    interval fails it (the value reported is then infinite)."""
    name = f"{INTERVAL_CRITERION} of {', '.join(values)} (half-width, relative)"
    limit = f"<= {100 * max_rel_halfwidth:g} %"
    got: Mapping[str, tuple[float, float]] = {} if ci is None else ci
    for k, v in values.items():
        bad = interval_problem(v, got.get(k))
        if bad is not None:
            why = f"95 % interval of {k}: {bad}" + (f" ({why_missing})" if why_missing and ci is None else "")
            return criterion(name, False, math.inf, limit, why)
    rel = relative_halfwidths({k: got[k] for k in values}, values)
    worst = max(rel, key=lambda k: rel[k])
    return criterion(name, rel[worst] <= max_rel_halfwidth, 100 * rel[worst], limit,
                     f"95 % interval of {worst} is +-{100 * rel[worst]:.3g} % (> {100 * max_rel_halfwidth:g} %)")


def excited_band_of(torque: np.ndarray, dt: float, *, share: float = 0.98) -> tuple[float, float]:
    """(w_lo, w_hi) [rad/s]: the band holding the central ``share`` of the torque's power (mean removed),
    for methods that are not told which lines were excited."""
    u = np.asarray(torque, dtype=float)
    P = np.abs(np.fft.rfft(u - u.mean())) ** 2
    P[0] = 0.0
    total = float(P.sum())
    if not total > 0.0:
        return (math.nan, math.nan)
    c = np.cumsum(P) / total
    tail = 0.5 * (1.0 - share)
    lo = int(np.searchsorted(c, tail))
    hi = int(np.searchsorted(c, 1.0 - tail))
    w = 2.0 * math.pi * np.fft.rfftfreq(u.size, dt)
    return float(w[max(lo, 1)]), float(w[min(hi, w.size - 1)])


def excited_bands(w_lo: float, w_hi: float, dt: float | None = None) -> list[tuple[float, float]]:
    """The bands [rad/s] an excitation over ``w_lo..w_hi`` reaches: the band itself and, for a torque
    held over each sample of ``dt``, its first image ``2 pi/dt - w_hi .. 2 pi/dt - w_lo`` (a held line
    at w also drives the plant at 2 pi/dt - w, weighted by sinc)."""
    out = [(float(w_lo), float(w_hi))]
    if dt is not None:
        ws = 2.0 * math.pi / float(dt)
        out.append((ws - float(w_hi), ws - float(w_lo)))
    return out


def resonance_criterion(wn: float, bands: Sequence[tuple[float, float]] | None) -> dict[str, Any]:
    """The resonance ``wn`` [rad/s] lies in one of the excited ``bands``; fails when it does not, when
    ``wn`` is not finite, or when the band is unknown (None)."""
    name = "resonance wn inside the excited band"
    ok_bands = [(lo, hi) for lo, hi in (bands or ()) if math.isfinite(lo) and math.isfinite(hi) and hi >= lo]
    limit = " or ".join(f"{lo:.4g}..{hi:.4g} rad/s" for lo, hi in ok_bands) or "a known band"
    if not ok_bands:
        return criterion(name, False, wn, limit, "the excited band is unknown: the resonance cannot be checked")
    if not math.isfinite(float(wn)):
        return criterion(name, False, None, limit, f"no finite resonance (wn = {wn})")
    inside = any(lo <= wn <= hi for lo, hi in ok_bands)
    return criterion(name, inside, wn, limit,
                     f"resonance wn = {wn:.4g} rad/s lies outside the excited band ({limit}): an extrapolation")


# --------------------------------------------------------------------------- excitation monitor
@dataclass(frozen=True)
class ExcitationReport:
    """Persistence-of-excitation numbers of one or more regressions (the worst one counts)."""

    min_eig: float      # smallest eigenvalue of the normalized information matrix
    cond: float         # its condition number
    trusted: bool       # min_eig >= MIN_EIG and cond <= MAX_COND
    reason: str
    min_eig_limit: float = MIN_EIG
    max_cond_limit: float = MAX_COND


def excitation_report(regressors: Sequence[np.ndarray], *, min_eig: float = MIN_EIG,
                      max_cond: float = MAX_COND) -> ExcitationReport:
    """PE monitor: normalized information matrix of each regressor (rows = equations).

    Each column is scaled to unit 2-norm so ``X^T X`` has a unit diagonal; the
    smallest eigenvalue and the condition number of the worst regressor are reported.
    An all-zero column (no excitation at all) gives min_eig = 0.
    """
    worst_eig, worst_cond = math.inf, 1.0
    for X in regressors:
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[0] < X.shape[1]:
            worst_eig, worst_cond = 0.0, math.inf
            continue
        norms = np.linalg.norm(X, axis=0)
        if np.any(norms == 0.0) or not np.all(np.isfinite(norms)):
            worst_eig, worst_cond = 0.0, math.inf
            continue
        # singular values of the normalized X: eig(X^T X) = s^2, without forming the product
        s = np.linalg.svd(X / norms, compute_uv=False)
        lo, hi = float(s[-1] ** 2), float(s[0] ** 2)
        cond = hi / lo if lo > 0.0 else math.inf
        worst_eig = min(worst_eig, lo)
        worst_cond = max(worst_cond, cond)
    if worst_eig < min_eig:
        ok, reason = False, f"not persistently exciting: min eigenvalue {worst_eig:.3g} < {min_eig:g}"
    elif worst_cond > max_cond:
        ok, reason = False, f"ill-conditioned regression: condition number {worst_cond:.3g} > {max_cond:g}"
    else:
        ok, reason = True, "persistently exciting"
    return ExcitationReport(min_eig=worst_eig, cond=worst_cond, trusted=ok, reason=reason,
                            min_eig_limit=min_eig, max_cond_limit=max_cond)


# --------------------------------------------------------------------------- assembly
def criterion(name: str, passed: bool, value: float | None = None, limit: str = "", why: str = "") -> dict[str, Any]:
    """One trust criterion as the JSON reports it: what was checked, the number, the limit, the verdict
    and (when it failed) why in words."""
    v = None if value is None or not math.isfinite(float(value)) else float(value)
    return {"criterion": name, "value": v, "limit": limit, "passed": bool(passed), "why": "" if passed else why}


def build_identification(p: AxisParams, method: str, cov_log: np.ndarray | None,
                         excitation: ExcitationReport, diagnostics: Mapping[str, float] | None = None,
                         *, extra_ok: bool = True, extra_reason: str = "",
                         checks: Sequence[dict[str, Any]] = (),
                         bands: Sequence[tuple[float, float]] | None = None,
                         max_rel_halfwidth: float = MAX_REL_HALFWIDTH) -> Identification:
    """Assemble an :class:`Identification` with intervals and the trust decision.

    trusted = every criterion passed: persistent excitation (min eigenvalue, condition number of
    the normalized information matrix), the method's own ``checks`` (e.g. the fit converged),
    ``extra_ok``, the resonance inside the excited ``bands`` [rad/s] (:func:`resonance_criterion`;
    unknown bands fail it) and a finite 95 % interval on each of I1, I2, B, K with half-width
    <= max_rel_halfwidth of its value (:func:`interval_criterion`; no covariance fails it).
    The criteria, with the reason of each failure, travel with the result (``trust_criteria``).
    """
    modal = modal_parameters(p)
    diag: dict[str, float] = {k: float(v) for k, v in (diagnostics or {}).items()}
    diag["min_eig"] = excitation.min_eig
    diag["cond"] = excitation.cond
    ci = None
    crit = [
        criterion("excitation: smallest eigenvalue of the normalized information matrix",
                  excitation.min_eig >= excitation.min_eig_limit, excitation.min_eig,
                  f">= {excitation.min_eig_limit:g}", excitation.reason),
        criterion("excitation: condition number of the normalized information matrix",
                  excitation.cond <= excitation.max_cond_limit, excitation.cond,
                  f"<= {excitation.max_cond_limit:g}", excitation.reason),
    ]
    crit += [dict(c) for c in checks]
    if not extra_ok:
        crit.append(criterion(f"{method}: method check", False, why=extra_reason))
    crit.append(resonance_criterion(float(modal["wn"]), bands))
    if cov_log is not None:
        ci = intervals(p, cov_log)        # a non-finite variance gives (0, inf): the criterion fails on it
    values = {k: float(getattr(p, k)) for k in PARAM_KEYS}
    crit.append(interval_criterion(values, ci, max_rel_halfwidth, why_missing="the method gives no covariance"))
    if ci is not None:
        rel = relative_halfwidths({k: ci[k] for k in PARAM_KEYS}, values)
        diag["max_rel_ci95"] = max(rel.values())
    trusted = all(c["passed"] for c in crit)
    if not trusted:
        logger.info("%s: identification not trusted: %s", method,
                    "; ".join(c["why"] for c in crit if not c["passed"]))
    return Identification(params=p, method=method, ci95=ci, modal=modal, trusted=bool(trusted),
                          diagnostics=diag, trust_criteria=tuple(crit))

"""Batch identification with friction to ground (beyond the paper): method ``svf-ls``.

Models (``MODELS``; JSON parameter names exactly these):

* ``two-inertia``: Eq. (3) as the paper has it, (I1, I2, B, K) plus a torque ``offset``;
* ``two-inertia-friction``: Eq. (3) with Coulomb and viscous friction to ground on each body,

      I1 th1'' + B (th1' - th2') + K (th1 - th2) + Fv1 th1' + Fc1 sgn(th1') + offset = T      (motor)
      I2 th2'' - B (th1' - th2') - K (th1 - th2) + Fv2 th2' + Fc2 sgn(th2')          = 0      (table)

  parameters ``I1, I2, B, K, Fc1, Fv1, Fc2, Fv2, offset``;
* ``rigid-friction``: one inertia (or mass) J with ``J th'' + Fv th' + Fc sgn(th') + offset = T``
  (a stiff axis, or a recording with one position sensor), parameters ``J, Fv, Fc, offset`` in the
  file's own units (rad and N m, or m and N).

**Regression.** Every model is linear in its parameters once sgn(th') is known, so it is a least
squares problem, in continuous time like Eq. (18) and :mod:`rt_ident.estimators.svf`: both sides
pass the state-variable filter F(s) = lam^3/(s + lam)^3 and s F, s^2 F give the filtered
derivatives (no raw angle is differenced; the paper's forward-Euler Eq. (9) is not used). The
two-inertia models stack the motor row and the sum of both rows (``F T = I1 s^2F th1 + I2 s^2F th2 +
friction + offset``), both with the filtered torque as the regressand. The filter is discretized
exactly per sample (angles first-order hold, torque zero-order hold), with one run of
:func:`scipy.signal.lfilter` per column.

**Sign of the velocity.** sgn(th') is taken from a *zero-phase* low-passed velocity (the batch can
look ahead: no lag at reversals) with a **dead band** around zero: rows whose filter memory
(8 / lam) contains a sample inside the dead band are left out of the fit, so standstill stretches,
sticking and the reversals themselves (where Karnopp/Stribeck friction is not Fc sgn(v)) neither
flip the sign column nor enter the fit. The dead band is 5 standard deviations of that velocity's
quantization noise (q^2 / 12 per sample, q detected from the data as the smallest position step)
unless given (``dead_band``, in position units per second).

**Quantization bias.** The angle noise enters the regressors (errors in variables); its covariance
per row is known from q and the filters' impulse responses, and is subtracted from the normal
equations (bias-compensated least squares, as :mod:`rt_ident.estimators.svf` does per sample).

**95 % intervals**: sigma^2 (A'A)^-1 from the residual, inflated by the residual's integrated
autocorrelation time (the filtered rows are strongly correlated).

**Trust** (:func:`friction_criteria`): the regression is well conditioned; every value is physical
(I1, I2, K, J > 0; B, Fc*, Fv* >= 0: friction and damping dissipate); every parameter has a finite
95 % interval, narrower than +-10 % for the inertias, B and K; the model explains the torque
(NRMSE <= ``MAX_NRMSE``); for the two-inertia models the resonance lies in the band the torque
excited. ``--validate`` adds the prediction error on another recording (<= ``MAX_VALIDATION_ERROR``,
:meth:`FrictionIdentification.with_validation`).

The frequency method stays linear-only (no friction model); this method accepts every model.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

# scipy.signal is imported by the functions that use it, not here: its import takes ~0.6 s of every run's start
import numpy as np

from rt_ident.errors import ConfigError, DataError, EstimationError
from rt_ident.estimators.base import trust_report, untrusted_reasons
from rt_ident.estimators.uncertainty import (
    MAX_REL_HALFWIDTH,
    criterion,
    excited_band_of,
    excited_bands,
    interval_criterion,
    resonance_criterion,
)

MODELS: dict[str, tuple[str, ...]] = {
    "two-inertia": ("I1", "I2", "B", "K", "offset"),
    "two-inertia-friction": ("I1", "I2", "B", "K", "Fc1", "Fv1", "Fc2", "Fv2", "offset"),
    "rigid-friction": ("J", "Fv", "Fc", "offset"),
}
DEFAULT_MODEL = "two-inertia"
#: Models that need a second (table) position sensor.
NEEDS_THETA2 = ("two-inertia", "two-inertia-friction")
#: Values that must be > 0 (inertias, stiffness) and >= 0 (damping and friction to ground dissipate).
POSITIVE = ("I1", "I2", "K", "J")
NON_NEGATIVE = ("B", "Fc1", "Fv1", "Fc2", "Fv2", "Fc", "Fv")
#: Parameters whose 95 % interval must be narrower than +-MAX_REL_HALFWIDTH (the others: finite).
WIDTH_CHECKED = ("I1", "I2", "B", "K", "J")
#: Torque fit error above which the model does not explain its own recording (%, rms error / rms torque).
MAX_NRMSE = 10.0
#: Torque prediction error on another recording above which the model fails validation (%).
MAX_VALIDATION_ERROR = 10.0
MAX_COND = 1e12


def check_model(model: str | None) -> str:
    key = DEFAULT_MODEL if model is None else str(model).strip().lower()
    if key not in MODELS:
        raise ConfigError("model", f"unknown model {model!r}; valid: {', '.join(MODELS)}")
    return key


@dataclass(frozen=True)
class FrictionIdentification:
    """Result of :func:`fit_friction` (the JSON of ``rt-ident identify --model ...``)."""

    model: str
    parameters: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    nrmse_percent: float
    method: str = "svf-ls"
    diagnostics: dict[str, Any] = field(default_factory=dict)
    trust_criteria: tuple[dict[str, Any], ...] = ()

    @property
    def trusted(self) -> bool:
        """Every criterion passed (none stated: never trusted)."""
        return bool(self.trust_criteria) and all(c["passed"] for c in self.trust_criteria)

    @property
    def reasons(self) -> list[str]:
        """Why the result is not trusted (empty when it is)."""
        return untrusted_reasons(self.trusted, self.trust_criteria, self.method)

    def trust(self) -> dict[str, Any]:
        """``{"trusted", "reasons", "criteria"}`` as the CLI's JSON reports it."""
        return trust_report(self.trusted, self.trust_criteria, self.method)

    def with_validation(self, validation: Mapping[str, Any]) -> FrictionIdentification:
        """This result with the validation on another recording as one more criterion: its torque
        prediction error must be <= MAX_VALIDATION_ERROR (a missing or non-finite error fails)."""
        err = validation.get("torque_error_percent")
        ok = err is not None and math.isfinite(float(err)) and float(err) <= MAX_VALIDATION_ERROR
        where = validation.get("file", "the other recording")
        c = criterion(f"validation on {where}: torque prediction error (%)", ok,
                      None if err is None else float(err), f"<= {MAX_VALIDATION_ERROR:g} %",
                      f"fails validation on {where}: torque prediction error "
                      f"{'unknown' if err is None else f'{float(err):.3g} %'} > {MAX_VALIDATION_ERROR:g} %")
        return replace(self, trust_criteria=self.trust_criteria + (c,))

    def as_dict(self) -> dict[str, Any]:
        return {"model": self.model, "method": self.method, "parameters": dict(self.parameters),
                "intervals": {k: [lo, hi] for k, (lo, hi) in self.ci95.items()},
                "ci95": {k: [lo, hi] for k, (lo, hi) in self.ci95.items()},
                "fit": {"nrmse_percent": self.nrmse_percent}, "trusted": self.trusted, "trust": self.trust(),
                "diagnostics": dict(self.diagnostics)}


def friction_criteria(key: str, params: Mapping[str, float], ci: Mapping[str, tuple[float, float]],
                      nrmse: float, cond: float, bands: list[tuple[float, float]] | None) -> tuple[dict[str, Any], ...]:
    """The trust criteria of a friction-model fit (module docstring, "Trust")."""
    out = [criterion("regression: condition number of the normal equations", cond < MAX_COND, cond,
                     f"< {MAX_COND:g}", f"the regression is ill-conditioned (condition number {cond:.3g})")]
    bad = [f"{k} = {v:.4g} must be > 0" for k, v in params.items() if k in POSITIVE and not v > 0.0]
    bad += [f"{k} = {v:.4g} must be >= 0" + _sign_note(ci.get(k))
            for k, v in params.items() if k in NON_NEGATIVE and not v >= 0.0]
    out.append(criterion("physical values: I1, I2, K, J > 0; B, Fc, Fv >= 0", not bad, None, "all",
                         "not physical: " + "; ".join(bad)))
    out.append(criterion("torque fit error NRMSE (%)", math.isfinite(nrmse) and nrmse <= MAX_NRMSE, nrmse,
                         f"<= {MAX_NRMSE:g} %", f"the model does not explain the torque: NRMSE {nrmse:.3g} % "
                         f"> {MAX_NRMSE:g} %"))
    if key in NEEDS_THETA2:
        I1, I2, B, K = (params[k] for k in ("I1", "I2", "B", "K"))
        wn = math.sqrt(K * (1.0 / I1 + 1.0 / I2)) if min(I1, I2, K) > 0.0 else math.nan
        out.append(resonance_criterion(wn, bands))
    width = {k: float(params[k]) for k in params if k in WIDTH_CHECKED}
    out.append(interval_criterion(width, ci, MAX_REL_HALFWIDTH))
    rest = [k for k in params if k not in WIDTH_CHECKED]
    missing = [(k, why) for k in rest for why in [_finite_problem(ci.get(k))] if why]
    out.append(criterion(f"finite 95 % interval of {', '.join(rest)}", not missing, None, "finite",
                         "; ".join(f"95 % interval of {k}: {why}" for k, why in missing)))
    return tuple(out)


def _finite_problem(c: tuple[float, float] | None) -> str | None:
    if c is None:
        return "no interval"
    lo, hi = float(c[0]), float(c[1])
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"[{lo:.4g}, {hi:.4g}] is not finite"
    return f"[{lo:.4g}, {hi:.4g}] has negative width" if hi < lo else None


def _sign_note(c: tuple[float, float] | None) -> str:
    if c is not None and math.isfinite(c[1]) and c[1] >= 0.0:
        return f" (its 95 % interval reaches {c[1]:.3g}: consistent with none)"
    return ""


# ----------------------------------------------------------------------------- filters
def svf_filters(lam: float, dt: float) -> tuple[list[tuple[np.ndarray, np.ndarray]], tuple[np.ndarray, np.ndarray]]:
    """Discrete s^k lam^3/(s+lam)^3, k = 0, 1, 2, for a first-order-hold input (angles), and F for a
    zero-order-hold input (torque). Exact: the continuous filter's state-space model sampled."""
    import scipy.linalg
    import scipy.signal
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-lam**3, -3 * lam**2, -3 * lam]])
    b = np.array([0.0, 0.0, lam**3])
    # ZOH and FOH input integrals via one expm of the augmented matrix
    M = np.zeros((5, 5))
    M[:3, :3] = A * dt
    M[:3, 3] = b * dt
    M[3, 4] = 1.0
    E = scipy.linalg.expm(M)
    Phi = E[:3, :3]
    g0 = E[:3, 3]                # ZOH: x+ = Phi x + g0 u_k
    g1 = E[:3, 4]                # FOH slope part: x+ = Phi x + (g0 - g1) u_k + g1 u_{k+1}
    outs = [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])]
    foh = []
    for c in outs:
        # y_k = c x_k; transfer from u: c (zI - Phi)^-1 ((g0 - g1) + g1 z)
        sys = scipy.signal.StateSpace(Phi, np.column_stack([g0 - g1, g1]), c[None, :], np.zeros((1, 2)), dt=dt)
        n0, den = scipy.signal.ss2tf(sys.A, sys.B, sys.C, sys.D, input=0)
        n1, _ = scipy.signal.ss2tf(sys.A, sys.B, sys.C, sys.D, input=1)
        # u_{k+1} term: multiply by z -> shift numerator one place left
        num = np.zeros(4)
        num[:] = n0[0][-4:] + np.append(n1[0][-3:], 0.0)
        foh.append((num, den))
    n0, den = scipy.signal.ss2tf(Phi, g0[:, None], outs[0][None, :], np.zeros((1, 1)))
    zoh = (np.asarray(n0[0][-4:], dtype=float), den)
    return foh, zoh


def _lfilter(nd: tuple[np.ndarray, np.ndarray], x: np.ndarray) -> np.ndarray:
    import scipy.signal
    return scipy.signal.lfilter(nd[0], nd[1], x)


def impulse_response(nd: tuple[np.ndarray, np.ndarray], n: int) -> np.ndarray:
    """The first ``n`` samples of the impulse response of the filter ``nd`` (numerator, denominator)."""
    import scipy.signal
    u = np.zeros(n)
    u[0] = 1.0
    return scipy.signal.lfilter(nd[0], nd[1], u)


def detect_quantum(x: np.ndarray) -> float:
    """The position step of a quantized signal (the smallest non-negligible |diff|), 0 if it looks continuous."""
    d = np.abs(np.diff(np.asarray(x, dtype=float)))
    scale = float(np.max(np.abs(x - x[0]))) if x.size else 0.0
    d = d[d > 1e-9 * max(scale, 1e-300)]
    if d.size < 10:
        return 0.0
    q = float(np.min(d))
    # quantized: most steps are integer multiples of q
    frac = np.abs(d / q - np.round(d / q))
    return q if float(np.mean(frac < 0.05)) > 0.9 else 0.0


def _zero_phase_velocity(x: np.ndarray, dt: float, hz: float) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    import scipy.signal
    v = np.gradient(x, dt)
    wn = min(0.9, 2.0 * hz * dt)
    b, a = scipy.signal.butter(2, wn)
    return scipy.signal.filtfilt(b, a, v), (b, a)


def _velocity_noise_std(q: float, dt: float, ba: tuple[np.ndarray, np.ndarray], n: int = 20000,
                        seed: int = 12345) -> float:
    import scipy.signal
    if q <= 0.0:
        return 0.0
    e = np.random.default_rng(seed).uniform(-q / 2, q / 2, n)
    v = scipy.signal.filtfilt(*ba, np.gradient(e, dt))
    return float(np.std(v[n // 10: -n // 10]))


#: the dead band is at least this fraction of the rms velocity (sticking stretches are smeared by the
#: velocity filter even when the position is not quantized)
DEAD_BAND_FLOOR = 0.02


def _dead_band(v: np.ndarray, q: float, dt: float, ba: tuple[np.ndarray, np.ndarray]) -> float:
    return max(5.0 * _velocity_noise_std(q, dt, ba), DEAD_BAND_FLOOR * float(np.sqrt(np.mean(v**2))), 1e-12)


def _memory_mask(bad: np.ndarray, n_mem: int, n_ahead: int = 0) -> np.ndarray:
    """True where no sample in [k - n_mem, k + n_ahead] is bad."""
    c = np.concatenate([[0], np.cumsum(bad.astype(np.int64))])
    k = np.arange(bad.size)
    lo = np.maximum(0, k - n_mem)
    hi = np.minimum(bad.size, k + n_ahead + 1)
    return (c[hi] - c[lo]) == 0


# ----------------------------------------------------------------------------- the fit
def fit_friction(theta1: np.ndarray, torque: np.ndarray, dt: float, *, model: str = "two-inertia-friction",
                 theta2: np.ndarray | None = None, filter_hz: float | None = None,
                 velocity_hz: float | None = None, dead_band: float | None = None,
                 dead_band2: float | None = None, quanta: tuple[float, float] | None = None,
                 bias_compensation: bool = True, torque_hold: str = "zoh",
                 lead: float | None = None) -> FrictionIdentification:
    """Identify ``model`` from sampled positions and torque (see the module docstring).

    ``filter_hz``: the SVF corner (default: 800 Hz for the two-inertia models - it must pass the
    resonance - capped at the sample rate / 8; for ``rigid-friction`` the sample rate / 40);
    ``velocity_hz``: the zero-phase velocity low-pass for the sign (default sample rate / 10);
    ``dead_band`` / ``dead_band2``: |velocity| below which a sample counts as standstill (motor /
    table); ``quanta``: (q1, q2) position quanta (default: detected); ``torque_hold``: "zoh" (the
    torque is held over each sample, as a drive applies a command) or "foh" (a sampled continuous
    torque, e.g. a measured current that varies within the sample). ``lead`` is accepted and
    ignored (the registry passes it to every method)."""
    del lead
    key = check_model(model)
    th1 = np.asarray(theta1, dtype=float)
    tq = np.asarray(torque, dtype=float)
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise DataError(f"dt: must be > 0, got {dt!r}")
    two = key in NEEDS_THETA2
    if two and theta2 is None:
        raise DataError(f"model {key!r} needs theta2 (the table position); a one-sensor recording needs "
                        f"--model rigid-friction")
    th2 = np.asarray(theta2, dtype=float) if two else None
    n = th1.size
    for name, a in (("theta1", th1), ("torque", tq)) + ((("theta2", th2),) if th2 is not None else ()):
        if a.shape != (n,):
            raise DataError(f"{name}: must be 1-D of length {n}, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise DataError(f"{name}: non-finite values")
    fs = 1.0 / dt
    if filter_hz is None:
        filter_hz = min(800.0, fs / 8.0) if two else fs / 40.0
    if velocity_hz is None:
        velocity_hz = fs / 10.0
    if not 0 < filter_hz <= fs / 4:
        raise ConfigError("filter_hz", f"must be in (0, {fs / 4:g}] Hz (a quarter of the sample rate)")
    lam = 2 * math.pi * filter_hz
    n_mem = int(math.ceil(8.0 / (lam * dt)))
    if n < 4 * n_mem + 50:
        raise DataError(f"only {n} samples; need more than {4 * n_mem + 50} at filter_hz = {filter_hz:g}")
    # positions start anywhere: only differences and derivatives matter (the offset absorbs the rest)
    th1 = th1 - th1[0]
    if th2 is not None:
        th2 = th2 - th2[0]
    q1, q2 = quanta if quanta is not None else (detect_quantum(th1),
                                                detect_quantum(th2) if th2 is not None else 0.0)
    foh, zoh = svf_filters(lam, dt)
    if torque_hold not in ("zoh", "foh"):
        raise ConfigError("torque_hold", f"must be 'zoh' or 'foh', got {torque_hold!r}")
    base = [_lfilter(f, th1) for f in foh]                 # F th1, sF th1, s^2F th1
    if th2 is not None:
        base += [_lfilter(f, th2) for f in foh]
    y = _lfilter(zoh if torque_hold == "zoh" else foh[0], tq)
    one = _lfilter(zoh, np.ones(n))
    # sign of a zero-phase velocity, with the dead band
    v1, ba = _zero_phase_velocity(th1, dt, velocity_hz)
    db1 = dead_band if dead_band is not None else _dead_band(v1, q1, dt, ba)
    s1 = np.where(np.abs(v1) > db1, np.sign(v1), 0.0)
    n_v = int(math.ceil(1.0 / (2 * math.pi * velocity_hz * dt)))   # the zero-phase filter's reach
    ok = _memory_mask(s1 == 0.0, n_mem + n_v, n_v)
    if th2 is not None:
        v2, _ = _zero_phase_velocity(th2, dt, velocity_hz)
        db2 = dead_band2 if dead_band2 is not None else _dead_band(v2, q2, dt, ba)
        s2 = np.where(np.abs(v2) > db2, np.sign(v2), 0.0)
        if key == "two-inertia-friction":
            ok &= _memory_mask(s2 == 0.0, n_mem + n_v, n_v)
    ok[: 4 * n_mem] = False                                # filter start-up
    rows = np.flatnonzero(ok)
    if rows.size < 20 * len(MODELS[key]):
        raise EstimationError(f"only {rows.size} samples in motion outside the dead band "
                              f"({db1:.3g}/s); the record is mostly at standstill")
    # regressor columns as linear maps of the base (for the noise covariance) plus noise-free columns
    nb = len(base)
    if key == "rigid-friction":
        names = MODELS[key]
        C = np.zeros((1, 4, nb))          # (equations, parameters, base)
        C[0, 0, 2] = 1.0                  # J: s^2F th
        C[0, 1, 1] = 1.0                  # Fv: sF th
        extra = [[None, None, _lfilter(zoh, s1), one]]
    else:
        names = MODELS[key]
        p = len(names)
        C = np.zeros((2, p, nb))
        # motor row: I1 s2F1 + B (sF1 - sF2) + K (F1 - F2) [+ Fv1 sF1]
        C[0, 0, 2] = 1.0
        C[0, 2, 1], C[0, 2, 4] = 1.0, -1.0
        C[0, 3, 0], C[0, 3, 3] = 1.0, -1.0
        # sum row: I1 s2F1 + I2 s2F2 [+ Fv1 sF1 + Fv2 sF2]
        C[1, 0, 2] = 1.0
        C[1, 1, 5] = 1.0
        ex0: list[Any] = [None] * p
        ex1: list[Any] = [None] * p
        ex0[-1] = ex1[-1] = one
        if key == "two-inertia-friction":
            fs1, fs2 = _lfilter(zoh, s1), _lfilter(zoh, s2)
            C[0, 5, 1] = 1.0                      # Fv1
            C[1, 5, 1] = 1.0
            C[1, 7, 4] = 1.0                      # Fv2
            ex0[4] = ex1[4] = fs1                 # Fc1
            ex1[6] = fs2                          # Fc2
        extra = [ex0, ex1]
    neq, p, _ = C.shape
    Bsel = np.column_stack([b[rows] for b in base])
    A_blocks = []
    for e in range(neq):
        Ae = Bsel @ C[e].T
        for j, col in enumerate(extra[e]):
            if col is not None:
                Ae[:, j] += col[rows]
        A_blocks.append(Ae)
    A = np.vstack(A_blocks)
    yy = np.concatenate([y[rows]] * neq)
    # scale columns
    sc = np.sqrt(np.mean(A**2, axis=0))
    sc[sc == 0] = 1.0
    As = A / sc
    R = As.T @ As
    r = As.T @ yy
    # bias compensation: noise covariance of the base signals (white q^2/12 per angle)
    Sig = np.zeros((p, p))
    if bias_compensation and (q1 > 0 or q2 > 0):
        H = np.column_stack([impulse_response(f, 40 * n_mem) for f in foh])
        G = H.T @ H
        Nb = np.zeros((nb, nb))
        Nb[:3, :3] = G * q1**2 / 12.0
        if two:
            Nb[3:, 3:] = G * q2**2 / 12.0
        for e in range(neq):
            Sig += rows.size * (C[e] @ Nb @ C[e].T)
        Sig = Sig / np.outer(sc, sc)
    try:
        ps = np.linalg.solve(R - Sig, r)
    except np.linalg.LinAlgError as exc:
        raise EstimationError(f"the regression is singular ({exc}); not enough excitation") from None
    res = yy - As @ ps
    m = rows.size
    nrmse = float(100.0 * math.sqrt(np.mean(res[:m] ** 2)) / max(float(np.std(yy[:m])), 1e-300))
    # intervals: residual variance x integrated autocorrelation time of the residual
    tau = _autocorr_time(res[:m])
    dof = max(yy.size - p, 1)
    var_res = float(res @ res) / dof
    try:
        Rinv = np.linalg.inv(R)
    except np.linalg.LinAlgError:
        Rinv = np.full((p, p), np.nan)
    cov = var_res * tau * Rinv / np.outer(sc, sc)
    est = ps / sc
    half = 1.96 * np.sqrt(np.maximum(np.diag(cov), 0.0))
    params = {k: float(v) for k, v in zip(names, est)}
    ci = {k: (float(v - h), float(v + h)) for k, v, h in zip(names, est, half)}
    cond = float(np.linalg.cond(R))
    positive = [k for k in names if k in POSITIVE]
    diag = {"samples": int(n), "rows_used": int(m), "filter_hz": float(filter_hz), "velocity_hz": float(velocity_hz),
            "dead_band": float(db1), "torque_hold": torque_hold, "quanta": [float(q1), float(q2)],
            "regressor_cond": cond,
            "autocorrelation_time": float(tau),
            "well_posed": bool(cond < MAX_COND and all(params[k] > 0 for k in positive))}
    bands = excited_bands(*excited_band_of(tq, dt), dt if torque_hold == "zoh" else None)
    return FrictionIdentification(key, params, ci, nrmse, diagnostics=diag,
                                  trust_criteria=friction_criteria(key, params, ci, nrmse, cond, bands))


def _autocorr_time(e: np.ndarray, max_lag: int = 20000) -> float:
    """1 + 2 sum of the residual's autocorrelation up to its first drop below 0.05 (>= 1)."""
    e = e - e.mean()
    n = e.size
    L = min(max_lag, n // 4)
    f = np.fft.rfft(e, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: L + 1]
    if ac[0] <= 0:
        return 1.0
    rho = ac / ac[0]
    cut = np.flatnonzero(rho < 0.05)
    k = int(cut[0]) if cut.size else L
    return max(1.0, float(1.0 + 2.0 * rho[1:k].sum()))


# ----------------------------------------------------------------------------- validation
def predict_torque(ident: FrictionIdentification, theta1: np.ndarray, torque: np.ndarray, dt: float, *,
                   theta2: np.ndarray | None = None) -> dict[str, float]:
    """Torque prediction of an identified model on *another* record, from its measured motion.

    The model's torque (motor row) is computed from the filtered derivatives of the measured
    positions (the same SVF and sign-with-dead-band as the fit) and compared with the filtered
    measured torque over the samples in motion. Returns the relative error (rms(error) /
    rms(torque - mean), %) and the correlation. This is the stable form of an open-loop check: a
    free simulation of a friction model from the torque drifts with any offset error."""
    d = ident.diagnostics
    key = ident.model
    P = ident.parameters
    th1 = np.asarray(theta1, float) - float(theta1[0])
    tq = np.asarray(torque, float)
    two = key in NEEDS_THETA2
    if two and theta2 is None:
        raise DataError(f"model {key!r} needs theta2 in the validation record")
    lam = 2 * math.pi * d["filter_hz"]
    n_mem = int(math.ceil(8.0 / (lam * dt)))
    foh, zoh = svf_filters(lam, dt)
    f1 = [_lfilter(f, th1) for f in foh]
    y = _lfilter(zoh if d.get("torque_hold", "zoh") == "zoh" else foh[0], tq)
    one = _lfilter(zoh, np.ones(th1.size))
    v1, ba = _zero_phase_velocity(th1, dt, d["velocity_hz"])
    q1 = detect_quantum(th1)
    db1 = max(d["dead_band"], 5.0 * _velocity_noise_std(q1, dt, ba))
    s1 = np.where(np.abs(v1) > db1, np.sign(v1), 0.0)
    n_v = int(math.ceil(1.0 / (2 * math.pi * d["velocity_hz"] * dt)))
    ok = _memory_mask(s1 == 0.0, n_mem + n_v, n_v)
    ok[: 4 * n_mem] = False
    fs1 = _lfilter(zoh, s1)
    if key == "rigid-friction":
        pred = P["J"] * f1[2] + P["Fv"] * f1[1] + P["Fc"] * fs1 + P["offset"] * one
    else:
        assert theta2 is not None    # checked above: the two-inertia models need it
        th2 = np.asarray(theta2, float) - float(theta2[0])
        f2 = [_lfilter(f, th2) for f in foh]
        pred = (P["I1"] * f1[2] + P["B"] * (f1[1] - f2[1]) + P["K"] * (f1[0] - f2[0]) + P["offset"] * one)
        if key == "two-inertia-friction":
            pred = pred + P["Fv1"] * f1[1] + P["Fc1"] * fs1
    e = (y - pred)[ok]
    yo = y[ok]
    rel = float(100.0 * math.sqrt(np.mean(e**2)) / max(float(np.std(yo)), 1e-300))
    corr = float(np.corrcoef(yo, pred[ok])[0, 1]) if yo.size > 2 else float("nan")
    return {"torque_error_percent": rel, "correlation": corr, "samples_used": int(ok.sum())}


def simulate_rigid(ident: FrictionIdentification, torque: np.ndarray, dt: float, v0: float = 0.0) -> np.ndarray:
    """Open-loop simulation of a ``rigid-friction`` model from a torque record (Karnopp sticking:
    held while |u - offset| <= Fc at zero velocity). Returns the position (from 0)."""
    if ident.model != "rigid-friction":
        raise ConfigError("model", "simulate_rigid needs a rigid-friction identification")
    J, Fv, Fc, off = (ident.parameters[k] for k in ("J", "Fv", "Fc", "offset"))
    n = len(torque)
    x = np.zeros(n)
    v = v0
    pos = 0.0
    a_v = math.exp(-Fv * dt / J) if Fv > 0 else 1.0
    for k in range(n - 1):
        u = float(torque[k]) - off
        if v == 0.0 and abs(u) <= Fc:
            x[k + 1] = pos
            continue
        sgn = math.copysign(1.0, v if v != 0.0 else u)
        f = u - Fc * sgn
        v_inf = f / Fv if Fv > 0 else math.inf
        vn = (v - v_inf) * a_v + v_inf if Fv > 0 else v + f / J * dt
        if v != 0.0 and vn * v < 0.0:
            vn = 0.0
        pos += 0.5 * (v + vn) * dt
        v = vn
        x[k + 1] = pos
    return x


__all__ = ["MODELS", "DEFAULT_MODEL", "NEEDS_THETA2", "FrictionIdentification", "fit_friction", "check_model",
           "detect_quantum", "predict_torque", "simulate_rigid"]

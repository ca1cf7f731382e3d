"""Shared value types of the estimators: the input record and the identification result.

:class:`IdentData` is one recording of an axis (angles, torque and optionally
velocities) sampled uniformly. :class:`Identification` is what every estimator
returns: physical parameters (Eq. 3), modal parameters (Section 6), optional 95 %
intervals and a trust flag with the numbers behind it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError, DataError

#: Keys of :attr:`Identification.ci95` and of ``as_dict()["parameters"]``.
PARAM_KEYS: tuple[str, ...] = ("I1", "I2", "B", "K")
MODAL_KEYS: tuple[str, ...] = ("wn", "wd", "zeta")

#: Sampling is "uniform" when every step is within this fraction of the median step
#: (host timestamps of a drive that samples on its own clock jitter by ~1e-4 dt).
UNIFORM_RTOL = 1e-3

MIN_SAMPLES = 8


def _as_signal(name: str, value: Any) -> np.ndarray:
    try:
        a = np.ascontiguousarray(value, dtype=float)
    except (TypeError, ValueError):
        raise DataError(f"{name}: not a numeric array") from None
    if a.ndim != 1:
        raise DataError(f"{name}: must be 1-D, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise DataError(f"{name}: non-finite value at sample {int(bad[0])} ({bad.size} in total)")
    a.setflags(write=False)
    return a


def uniform_dt(t: np.ndarray, rtol: float = UNIFORM_RTOL) -> float:
    """The sample period of uniformly spaced times ``t``; DataError if not uniform.

    Returns ``(t[-1] - t[0]) / (n - 1)`` (the least-jittery estimate) after checking
    that every step lies within ``rtol`` of the median step.
    """
    if t.size < 2:
        raise DataError("t: need at least 2 samples to infer dt")
    d = np.diff(t)
    med = float(np.median(d))
    if not med > 0.0:
        raise DataError("t: time stamps must increase")
    worst = int(np.argmax(np.abs(d - med)))
    if abs(d[worst] - med) > rtol * med:
        raise DataError(
            f"t: non-uniform sampling, step {worst} is {d[worst]:.6g} s against a median of {med:.6g} s "
            f"(tolerance {rtol:g} relative); resample the record or pass a method that handles gaps")
    return float((t[-1] - t[0]) / (t.size - 1))


@dataclass(frozen=True, eq=False)
class IdentData:
    """One uniformly sampled recording of an axis.

    ``t`` may be None when ``dt`` is given. With both, they must agree. ``omega1`` and
    ``omega2`` (velocities) come together or not at all. ``period`` is the excitation
    period in samples when known (frequency-domain methods detect it otherwise).
    """

    t: np.ndarray | None
    theta1: np.ndarray
    theta2: np.ndarray
    torque: np.ndarray
    omega1: np.ndarray | None = None
    omega2: np.ndarray | None = None
    dt: float | None = None
    period: int | None = None

    def __post_init__(self) -> None:
        th1 = _as_signal("theta1", self.theta1)
        n = th1.size
        if n < MIN_SAMPLES:
            raise DataError(f"theta1: need at least {MIN_SAMPLES} samples, got {n}")
        arrays = {"theta1": th1}
        for name in ("theta2", "torque", "omega1", "omega2", "t"):
            v = getattr(self, name)
            if v is None:
                if name in ("theta2", "torque"):
                    raise DataError(f"{name}: required")
                continue
            a = _as_signal(name, v)
            if a.size != n:
                raise DataError(f"{name}: length {a.size} differs from theta1's {n}")
            arrays[name] = a
        if (self.omega1 is None) != (self.omega2 is None):
            raise DataError("omega1/omega2: give both velocities or neither")
        dt = self.dt
        if dt is not None:
            if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not (
                    math.isfinite(float(dt)) and float(dt) > 0.0):
                raise ConfigError("dt", f"must be a finite number > 0, got {dt!r}")
            dt = float(dt)
        if "t" in arrays:
            dt_t = uniform_dt(arrays["t"])
            if dt is not None and abs(dt_t - dt) > UNIFORM_RTOL * dt:
                raise DataError(f"dt: given {dt:.6g} s but the time stamps step by {dt_t:.6g} s")
            dt = dt_t if dt is None else dt
        elif dt is None:
            raise DataError("t/dt: give the time stamps t or the sample period dt")
        else:
            t = np.arange(n) * dt
            t.setflags(write=False)
            arrays["t"] = t
        if self.period is not None:
            if isinstance(self.period, bool) or not isinstance(self.period, (int, np.integer)) or self.period < 2:
                raise ConfigError("period", f"must be an integer >= 2 samples, got {self.period!r}")
            object.__setattr__(self, "period", int(self.period))
        for name, a in arrays.items():
            object.__setattr__(self, name, a)
        object.__setattr__(self, "dt", dt)

    @property
    def n(self) -> int:
        return int(self.theta1.size)

    @property
    def sample_dt(self) -> float:
        """``dt``: always set once constructed (from ``t`` when not given)."""
        assert self.dt is not None
        return self.dt

    @property
    def has_states(self) -> bool:
        """True when velocities are recorded (full Eq. 8 states)."""
        return self.omega1 is not None


def _json_float(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def untrusted_reasons(trusted: bool, criteria: Sequence[Mapping[str, Any]], method: str) -> list[str]:
    """Why a result is not trusted (empty when it is): each failed criterion's reason in words; a method
    that states no criteria is never trusted, and says so."""
    if trusted:
        return []
    why = [c["why"] or c["criterion"] for c in criteria if not c["passed"]]
    return why or [f"{method} states no trust criteria; its result is never trusted"]


def trust_report(trusted: bool, criteria: Sequence[Mapping[str, Any]], method: str) -> dict[str, Any]:
    """``{"trusted", "reasons", "criteria"}`` as the CLI's JSON reports a result's trust."""
    return {"trusted": bool(trusted), "reasons": untrusted_reasons(trusted, criteria, method),
            "criteria": [dict(c) for c in criteria]}


@dataclass(frozen=True)
class Identification:
    """Result of one identification.

    params      : physical parameters (Eq. 3); ``lead`` is copied from the caller, not estimated
    method      : registry name of the estimator
    ci95        : 95 % interval per key of PARAM_KEYS + MODAL_KEYS, or None when not available
    modal       : wn, wd, zeta of the flexible mode of ``params``
    trusted     : whether the data were informative enough (see rt_ident.estimators.uncertainty)
    diagnostics : numbers behind ``trusted`` and the fit (cond, min_eig, periods, n_samples, ...)
    trust_criteria : each criterion behind ``trusted`` (see
                  :func:`rt_ident.estimators.uncertainty.criterion`); empty when the estimator
                  states none (then ``reasons`` says so for an untrusted result)
    frf         : the frequency-response view of the fit (:func:`rt_ident.estimators.frf.frf_view`),
                  when the method has one; the dashboard draws it
    """

    params: AxisParams
    method: str
    ci95: dict[str, tuple[float, float]] | None
    modal: dict[str, float]
    trusted: bool
    diagnostics: dict[str, float] = field(default_factory=dict)
    trust_criteria: tuple[dict[str, Any], ...] = ()
    frf: dict[str, Any] | None = field(default=None, compare=False, repr=False)

    @property
    def reasons(self) -> list[str]:
        """Why the result is not trusted (empty when it is)."""
        return untrusted_reasons(self.trusted, self.trust_criteria, self.method)

    def trust(self) -> dict[str, Any]:
        """``{"trusted", "reasons", "criteria"}`` as the CLI's JSON reports it."""
        return trust_report(self.trusted, self.trust_criteria, self.method)

    def value(self, key: str) -> float:
        """A physical (I1, I2, B, K) or modal (wn, wd, zeta) value by name."""
        if key in PARAM_KEYS:
            return float(getattr(self.params, key))
        if key in MODAL_KEYS:
            return float(self.modal[key])
        raise ConfigError("key", f"unknown parameter {key!r}; valid: {PARAM_KEYS + MODAL_KEYS}")

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly form (non-finite numbers become None)."""
        keys = PARAM_KEYS + MODAL_KEYS
        return {
            "parameters": {k: _json_float(self.value(k)) for k in keys},
            "lead": float(self.params.lead),
            "method": self.method,
            "ci95": None if self.ci95 is None else {
                k: [_json_float(lo), _json_float(hi)] for k, (lo, hi) in self.ci95.items()},
            "trusted": bool(self.trusted),
            "trust": self.trust(),
            "diagnostics": {k: _json_float(v) for k, v in self.diagnostics.items()},
        }

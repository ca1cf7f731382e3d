"""Estimators by name: one entry point from a recording to an :class:`Identification`.

>>> from rt_ident.estimators.registry import IdentData, identify
>>> result = identify(IdentData(t, theta1, theta2, torque))          # doctest: +SKIP
>>> result.as_dict()["parameters"]["K"]                               # doctest: +SKIP

Methods (``list_methods()``):

* ``frequency`` (default) - periodic excitation, angles only; consistent with
  quantized, noisy, closed-loop bench data (rt_ident.estimators.frequency).
* ``tustin`` - exact for Newmark / trapezoidal data; full states when the record has
  velocities, else the three-point angle relation (rt_ident.estimators.consistent).
* ``zoh`` - exact for zero-order-hold data; needs velocities.
* ``paper`` - the paper's forward-Euler LS (Eqs. 9-10); kept for comparison, never trusted.
* ``svf-ls`` - batch state-variable-filter least squares; the one method that accepts the friction
  models (``two-inertia-friction``, ``rigid-friction``; rt_ident.estimators.friction).

Models (``MethodInfo.models``): every method fits ``two-inertia`` (Eq. 3); the frequency method
and the discrete-time regressions stay linear-only.

Options are passed through to the method's function; unknown ones raise ConfigError.
"""

from __future__ import annotations

import inspect
import logging
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, overload

import numpy as np

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.base import IdentData, Identification
from rt_ident.estimators.consistent import fit_tustin_angles, fit_tustin_states, fit_zoh
from rt_ident.estimators.frequency import fit_frequency
from rt_ident.estimators.friction import MODELS as FRICTION_MODELS
from rt_ident.estimators.friction import FrictionIdentification, check_model, fit_friction
from rt_ident.estimators.uncertainty import build_identification, excitation_report, excited_band_of, excited_bands

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_METHOD", "IdentData", "METHODS", "MethodInfo", "identify", "list_methods", "methods_for_model"]

DEFAULT_METHOD = "frequency"
#: the methods that fit the linear model and return an Identification ("svf-ls" returns a FrictionIdentification)
LinearMethod = Literal["frequency", "tustin", "zoh", "paper"]


@dataclass(frozen=True)
class MethodInfo:
    """One registered estimator."""

    name: str
    summary: str
    needs: str                                  # "angles" or "states"
    fn: Callable[..., Identification | FrictionIdentification]   # fn(data: IdentData, **options)
    options: tuple[str, ...] = ()               # accepted option names
    models: tuple[str, ...] = ("two-inertia",)  # the models it can fit (rt_ident.estimators.friction.MODELS)


def _kw(*fns: Callable[..., Any]) -> tuple[str, ...]:
    """Keyword-only parameter names of the underlying estimator functions."""
    names: list[str] = []
    for f in fns:
        for prm in inspect.signature(f).parameters.values():
            if prm.kind is inspect.Parameter.KEYWORD_ONLY and prm.name not in names:
                names.append(prm.name)
    return tuple(names)


def _need_states(data: IdentData, method: str) -> tuple[np.ndarray, np.ndarray]:
    """The recorded velocities (omega1, omega2)."""
    if data.omega1 is None or data.omega2 is None:
        raise DataError(f"{method}: needs velocities omega1/omega2 in the record (full Eq. 8 states)")
    return data.omega1, data.omega2


def _frequency(data: IdentData, **options: Any) -> Identification:
    options.setdefault("period", data.period)
    return fit_frequency(data.theta1, data.theta2, data.torque, data.sample_dt, **options)


def _tustin(data: IdentData, *, use_states: bool | None = None, **options: Any) -> Identification:
    states = data.has_states if use_states is None else bool(use_states)
    if states:
        w1, w2 = _need_states(data, "tustin")
        return fit_tustin_states(data.theta1, w1, data.theta2, w2, data.torque, data.sample_dt, **options)
    return fit_tustin_angles(data.theta1, data.theta2, data.torque, data.sample_dt, **options)


def _zoh(data: IdentData, **options: Any) -> Identification:
    w1, w2 = _need_states(data, "zoh")
    return fit_zoh(data.theta1, w1, data.theta2, w2, data.torque, data.sample_dt, **options)


def _paper(data: IdentData, **options: Any) -> Identification:
    """The paper's Eq. (9)-(10) Euler LS. Never trusted: its model does not match the data."""
    from rt_ident.estimators.paper import fit_paper_ls  # lazy: owned by another module

    w1, w2 = _need_states(data, "paper")
    states = np.column_stack([data.theta1, w1, data.theta2, w2])
    est = fit_paper_ls(states, data.torque, data.sample_dt, **options)
    d = states[:-1, 0] - states[:-1, 2]
    dw = states[:-1, 1] - states[:-1, 3]
    pe = excitation_report([np.column_stack([d, dw, states[:-1, 2], states[:-1, 3], data.torque[:-1]])])
    diag = {"n_samples": float(data.n), "regressor_cond": float(est.cond)}
    return build_identification(est.params, "paper", None, pe, diag, extra_ok=False,
                                extra_reason="forward-Euler model (Eq. 9): biased by the discretization",
                                bands=excited_bands(*excited_band_of(data.torque, data.sample_dt)))


def _svf_ls(data: IdentData, *, model: str = "two-inertia", **options: Any) -> FrictionIdentification:
    """Batch SVF least squares (rt_ident.estimators.friction); returns a FrictionIdentification."""
    return fit_friction(data.theta1, data.torque, data.sample_dt, model=model, theta2=data.theta2, **options)


METHODS: Mapping[str, MethodInfo] = types.MappingProxyType({
    "frequency": MethodInfo("frequency", "periodic excitation, angles only: exact sampled model fitted to "
                            "period-averaged spectra (quantized, noisy, closed-loop data)", "angles", _frequency,
                            _kw(fit_frequency)),
    "tustin": MethodInfo("tustin", "exact LS for Newmark/trapezoidal data (states, or angles via the "
                         "three-point relation)", "angles", _tustin,
                         ("use_states",) + _kw(fit_tustin_states, fit_tustin_angles)),
    "zoh": MethodInfo("zoh", "exact LS for zero-order-hold data: Eq. (9) read through logm", "states", _zoh,
                      _kw(fit_zoh)),
    "paper": MethodInfo("paper", "the paper's forward-Euler LS, Eqs. (9)-(10) (biased; for comparison)",
                        "states", _paper, ("lead",)),
    "svf-ls": MethodInfo("svf-ls", "batch state-variable-filter LS in continuous time (Eq. 3 filtered), with "
                         "Coulomb/viscous friction and an offset; the one method for the friction models and for "
                         "one-sensor recordings", "angles", _svf_ls, ("model",) + _kw(fit_friction),
                         tuple(FRICTION_MODELS)),
})


def methods_for_model(model: str) -> list[str]:
    """Names of the methods that accept ``model``."""
    key = check_model(model)
    return [m.name for m in list_methods() if key in m.models]


def list_methods() -> list[MethodInfo]:
    """Registered methods, default first."""
    return [METHODS[DEFAULT_METHOD]] + [m for k, m in METHODS.items() if k != DEFAULT_METHOD]


@overload
def identify(data: IdentData, method: LinearMethod = ..., **options: Any) -> Identification: ...
@overload
def identify(data: IdentData, method: str, **options: Any) -> Identification | FrictionIdentification: ...
def identify(data: IdentData, method: str = DEFAULT_METHOD,
             **options: Any) -> Identification | FrictionIdentification:
    """Run the estimator ``method`` on ``data``; options go to the estimator.

    Raises ConfigError for an unknown method or option, DataError when the record lacks
    what the method needs, EstimationError when the data do not determine the parameters.
    """
    if not isinstance(data, IdentData):
        raise ConfigError("data", f"must be IdentData, got {type(data).__name__}")
    key = str(method).strip().lower()
    if key not in METHODS:
        raise ConfigError("method", f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    info = METHODS[key]
    if "model" in options:
        model = check_model(options["model"])
        if model not in info.models:
            raise ConfigError("model", f"method {key!r} fits {', '.join(info.models)} only; {model!r} needs "
                              f"{' or '.join(methods_for_model(model))}")
        if "model" not in info.options:
            options.pop("model")
    unknown = sorted(set(options) - set(info.options))
    if unknown:
        raise ConfigError(f"options.{unknown[0]}", f"not an option of method {key!r}; valid: {', '.join(info.options)}")
    logger.debug("identify: method=%s n=%d dt=%g options=%s", key, data.n, data.dt, sorted(options))
    return info.fn(data, **options)

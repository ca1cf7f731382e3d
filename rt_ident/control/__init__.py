"""Position control of the axis from the model it identifies: controller design on the sampled
two-inertia model (zero-order hold, one-tick delay), the margin check over a family of plants,
the adaptive supervisor that swaps controllers bumplessly, and reference trajectories.

May import :mod:`rt_ident.axis` and :mod:`rt_ident.estimators`.
"""

from __future__ import annotations

from typing import Any

from rt_ident.axis.params import AxisParams
from rt_ident.control.adaptation import ControlFallbackStop, Supervisor
from rt_ident.control.job import ControlSettings, redesign


def make_controller(settings: ControlSettings, nominal: AxisParams, *, tick: float, torque_limit: float,
                    reference: Any, jobs: Any = None, error_after_s: float | None = None,
                    per_sample: Any = None, reference_options: Any = None) -> Supervisor | None:
    """The host's position controller for one axis, or None when ``settings.mode == "off"``.

    ``nominal``: the configured axis (the conservative controller's rigid-body inertia and the
    fixed controller's model); ``jobs``: a job process running :func:`redesign` (adaptive mode);
    ``per_sample``: the recursive estimator fed every sample whose estimate the redesigns follow
    (:class:`rt_ident.estimators.svf.SvfEstimator`), cross-checked against the frequency fit;
    ``reference_options``: the reference's origin and rejoin limits (:mod:`rt_ident.control.anchor`).
    """
    if settings.mode == "off":
        return None
    return Supervisor(settings, nominal, tick=tick, torque_limit=torque_limit, reference=reference,
                      jobs=jobs if settings.mode == "adaptive" else None, error_after_s=error_after_s,
                      per_sample=per_sample if settings.mode == "adaptive" else None,
                      reference_options=reference_options)


__all__ = ["ControlFallbackStop", "ControlSettings", "Supervisor", "make_controller", "redesign"]

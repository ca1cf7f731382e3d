"""Where the reference is anchored on the scale, and how the table re-joins it.

A configured reference (:mod:`rt_ident.control.reference`) is a *path* relative to an origin. The
controller follows

    x_ref(t) = origin + path(t) + d(t)

* ``origin`` is the table's measured position at enable (``[reference] origin = "enable"``, the
  default: the table moves from where it is) or 0 (``origin = "scale"``: the path is in scale
  coordinates);
* ``d(t)`` is a *rejoin*: a jerk-limited offset that starts at the table's measured position and
  speed and ends at rest on the path, within the motion limits. One starts at enable (with
  ``origin = "scale"`` and the table away from the path's start, it is the approach move) and one
  after a loop stall (the drive zeroed the torque while the host was stalled and the table
  coasted): the reference then starts where the table *is*, so the error, and the torque, do not
  step.

A rejoin first brakes the offset's speed to zero, then moves the remaining distance rest to rest
(:func:`rt_ident.control.reference.s_curve`). It is not time-optimal when the table already moves
towards the path, but its speed never exceeds ``max(|v0|, v_max)`` and its acceleration and jerk
stay within ``a_max`` and ``j_max`` - except that an offset faster than ``v_max`` is braked with the
anchor's ``brake`` limits when they are stronger: a drive that kept its last torque through a host
stall leaves the table faster than any path asks, and braking it at a path's gentle ``a_max``
(0.5 m/s² from 0.2 m/s: 40 mm) would carry it to the end of its travel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rt_ident.control.reference import Segments, s_curve, velocity_change
from rt_ident.errors import ConfigError, validation_error


@dataclass(frozen=True)
class MotionLimits:
    """Speed [m/s], acceleration [m/s²] and jerk [m/s³] limits of a move of the table."""

    v_max: float
    a_max: float
    j_max: float


#: The approach and rejoin limits of references that have none of their own (hold, sine, circle, csv).
DEFAULT_LIMITS = MotionLimits(v_max=0.02, a_max=0.5, j_max=20.0)

#: A rejoin brakes a too-fast offset with this share of the torque limit over the nominal inertia,
#: its deceleration built up over ``BRAKE_RAMP_S`` (a ramp, not a torque step).
BRAKE_TORQUE_SHARE = 0.5
BRAKE_RAMP_S = 0.01

ORIGINS = ("enable", "scale")
_COMMON = ("origin", "v_max", "a_max", "j_max")


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid")
    origin: Literal["enable", "scale"] = "enable"
    v_max: float | None = Field(None, gt=0, allow_inf_nan=False)
    a_max: float | None = Field(None, gt=0, allow_inf_nan=False)
    j_max: float | None = Field(None, gt=0, allow_inf_nan=False)


@dataclass(frozen=True)
class ReferenceOptions:
    """The ``[reference]`` keys every kind takes: the origin and the approach/rejoin limits."""

    origin: str = "enable"
    limits: MotionLimits = DEFAULT_LIMITS


def split_reference_table(mapping: Mapping[str, Any] | None) -> tuple[dict[str, Any], ReferenceOptions]:
    """``[reference]`` -> (the path's own table, its :class:`ReferenceOptions`). ``moves`` keeps
    ``v_max``, ``a_max``, ``j_max`` (its own limits are also its rejoin limits); the other kinds take
    them as optional approach limits. Errors name the field."""
    data = dict(mapping or {"kind": "hold"})
    data.setdefault("kind", "hold")
    common = {k: data[k] for k in _COMMON if k in data}
    if data["kind"] != "moves":
        for k in _COMMON:
            data.pop(k, None)
    else:
        data.pop("origin", None)
    try:
        opt = _Options.model_validate(common)
    except ValidationError as exc:
        e, msg = validation_error(_Options, exc)
        loc = ".".join(str(p) for p in e["loc"]) or "origin"
        raise ConfigError(f"reference.{loc}", msg) from None
    d = DEFAULT_LIMITS
    limits = MotionLimits(opt.v_max or d.v_max, opt.a_max or d.a_max, opt.j_max or d.j_max)
    return data, ReferenceOptions(opt.origin, limits)


def braking_limits(inertia: float, lead: float, torque_limit: float) -> MotionLimits | None:
    """The ``brake`` limits of an axis of total ``inertia`` [kg m²] and ``lead`` [m/rad] whose torque is
    limited to ``torque_limit`` [N m]; None when those do not give a finite, positive deceleration."""
    a = BRAKE_TORQUE_SHARE * torque_limit * lead / inertia if inertia > 0 else math.nan
    if not (math.isfinite(a) and a > 0):
        return None
    return MotionLimits(v_max=math.inf, a_max=a, j_max=a / BRAKE_RAMP_S)


def braking(limits: MotionLimits, v0: float, brake: MotionLimits | None) -> MotionLimits:
    """The limits a rejoin brakes an offset speed ``v0`` with: ``brake`` when ``|v0|`` exceeds
    ``limits.v_max`` and ``brake`` decelerates harder, else ``limits``."""
    if brake is not None and abs(v0) > limits.v_max and brake.a_max > limits.a_max:
        return brake
    return limits


def rejoin(d0: float, v0: float, limits: MotionLimits, t0: float, brake: MotionLimits | None = None) -> Segments:
    """The offset d(t), t >= ``t0``: from ``d0`` [m] moving at ``v0`` [m/s] (zero acceleration) to rest at
    0, within ``limits``, braking a speed above ``limits.v_max`` with ``brake`` (see the module docstring)."""
    if not (math.isfinite(d0) and math.isfinite(v0)):
        raise ValueError(f"rejoin from a non-finite state (d0={d0!r}, v0={v0!r})")
    lim = limits
    b = braking(lim, v0, brake)
    segs = velocity_change(-v0, b.a_max, b.j_max) if v0 != 0.0 else []
    stop = Segments.build(d0, segs, t0, v0)            # where braking alone ends
    d1 = float(stop.x0[-1])
    if d1 != 0.0:
        segs += [(dur, j if d1 < 0 else -j) for dur, j in s_curve(abs(d1), lim.v_max, lim.a_max, lim.j_max)]
    return Segments.build(d0, segs, t0, v0)


def path_samples(path: Any, horizon_s: float = 60.0, step_s: float = 1e-3) -> tuple[np.ndarray, ...]:
    """(x, v, a) of a reference path every ``step_s`` over its duration (at most ``horizon_s``)."""
    end = float(getattr(path, "duration", math.inf))
    end = min(end if math.isfinite(end) else horizon_s, horizon_s)
    return tuple(np.asarray(c, dtype=float) for c in path.at(np.arange(0.0, end + step_s, step_s)))


def path_peak_speed(path: Any) -> float:
    """The largest |speed| of a reference path (sampled, :func:`path_samples`)."""
    return float(np.max(np.abs(path_samples(path)[1])))


class Anchor:
    """The reference the controller follows: the path, moved to its origin, plus the current rejoin.
    :meth:`point` runs every tick (plain floats; no rejoin once the last one has ended)."""

    def __init__(self, path: Any, options: ReferenceOptions = ReferenceOptions(),
                 brake: MotionLimits | None = None) -> None:
        self.path = path
        self.options = options
        self.brake = brake                  # what the axis brakes a too-fast offset with (see rejoin)
        self.origin = 0.0
        self.anchored = False
        self._rejoin: Segments | None = None
        self._end = -math.inf
        self.rejoins = 0
        self.last_rejoin: dict[str, float] | None = None

    def point(self, t: float) -> tuple[float, float, float]:
        x, v, a = self.path.point(t)
        x += self.origin
        r = self._rejoin
        if r is not None:
            if t >= self._end:               # ended at rest on the path
                self._rejoin = None
                return x, v, a
            d, dv, da = r.point(t)
            return x + d, v + dv, a + da
        return x, v, a

    def start(self, t: float, x: float, v: float) -> None:
        """Anchor at enable: the origin (``"enable"``: the table's position ``x`` less the path's start,
        so the path starts where the table is) and a rejoin from the table's state."""
        if self.options.origin == "enable":
            self.origin = x - self.path.point(t)[0]
        self.anchored = True
        self.replan(t, x, v)

    def replan(self, t: float, x: float, v: float) -> None:
        """A new rejoin from the table's measured position ``x`` and speed ``v`` at ``t`` (the path and
        the origin stay)."""
        px, pv, _ = self.path.point(t)
        d0, v0 = x - (px + self.origin), v - pv
        self._rejoin = None
        if d0 == 0.0 and v0 == 0.0:
            return
        seg = rejoin(d0, v0, self.options.limits, t, self.brake)
        self._rejoin, self._end = seg, seg.end
        self.rejoins += 1
        self.last_rejoin = {"t": t, "offset_m": d0, "speed_m_s": v0, "duration_s": seg.end - t,
                            "brake_m_s2": braking(self.options.limits, v0, self.brake).a_max}

    @property
    def rejoining(self) -> bool:
        return self._rejoin is not None


__all__ = ["Anchor", "BRAKE_RAMP_S", "BRAKE_TORQUE_SHARE", "DEFAULT_LIMITS", "MotionLimits", "ReferenceOptions",
           "braking", "braking_limits", "path_peak_speed", "path_samples", "rejoin", "split_reference_table"]

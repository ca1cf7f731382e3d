"""Friction feedforward from an identified friction model (beyond the paper).

The law (:mod:`rt_ident.control.law`) already feeds the inertia forward, (I1 + I2) alpha_ref.
A ball-screw axis also needs the torque its friction takes: at every reversal of the reference the
Coulomb torque flips sign, the integral and the position feedback need tens of ms to build it up,
and the table lags - the "quadrant glitch" of a ballbar plot. With Coulomb Fc and viscous Fv
identified (:mod:`rt_ident.estimators.friction`; on the two-inertia axis both bodies' friction is
seen by the motor at low frequency, Fc = Fc1 + Fc2, Fv = Fv1 + Fv2) the law adds

    u_ff,fr = Fv w_ref + Fc sat(w_ref / w_band)

with w_ref the reference (table) velocity in rad/s at the middle of the tick the torque is held
over. ``sat`` is a ramp of width ``w_band`` around zero rather than sign(): at standstill (a hold
reference) the feedforward is zero instead of chattering between +-Fc, and the flip at a reversal
is spread over w_band / |alpha_ref|.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from rt_ident.errors import ConfigError


@dataclass(frozen=True)
class FrictionFeedforward:
    """Coulomb + viscous friction feedforward on the motor torque (units of the model: N m, rad/s)."""

    Fc: float                  # N m, total Coulomb torque seen by the motor
    Fv: float = 0.0            # N m s/rad, total viscous coefficient
    w_band: float = 0.05       # rad/s: the sign is a ramp inside +-w_band

    def __post_init__(self) -> None:
        for name in ("Fc", "Fv", "w_band"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"control.friction.{name}", f"must be a finite number >= 0, got {v!r}")
        if self.w_band <= 0:
            raise ConfigError("control.friction.w_band", "must be > 0")

    def torque(self, w_ref: float) -> float:
        s = w_ref / self.w_band
        s = 1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)
        return self.Fv * w_ref + self.Fc * s

    @classmethod
    def from_parameters(cls, params: Mapping[str, float], w_band: float = 0.05) -> FrictionFeedforward:
        """From the ``parameters`` of a ``two-inertia-friction`` (Fc1 + Fc2, Fv1 + Fv2) or
        ``rigid-friction`` (Fc, Fv) identification; negative estimates are clipped to 0."""
        if "Fc1" in params:
            fc = params["Fc1"] + params.get("Fc2", 0.0)
            fv = params.get("Fv1", 0.0) + params.get("Fv2", 0.0)
        elif "Fc" in params:
            fc, fv = params["Fc"], params.get("Fv", 0.0)
        else:
            raise ConfigError("parameters", "no friction parameters (Fc1/Fc2 or Fc) in the identification")
        return cls(max(0.0, float(fc)), max(0.0, float(fv)), w_band)


__all__ = ["FrictionFeedforward"]

"""Axis parameters: the paper's two-inertia spring-damper (Fig. 3, Eq. 3).

:class:`AxisParams` is a validated, frozen value type. Construction rejects
non-positive inertias, stiffness or lead, negative damping and non-finite
numbers with a :class:`~rt_ident.errors.ConfigError` naming the field. Values read from a
config (:meth:`AxisParams.from_mapping`) must also lie in :data:`PLAUSIBLE`.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

from rt_ident.errors import ConfigError

#: The configs folder shipped next to the package (source checkout or editable install).
CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"   # <repo>/configs (rt_ident/axis/params.py)

#: What a config may give for a machine-tool axis: from a micro-motor (rotor ~1e-7 kg m^2) to a
#: heavy axis (~1 kg m^2 at the motor), with margin. Beyond these the controller design's and the
#: plant's arithmetic overflows or loses every digit. Estimates are not held to them.
PLAUSIBLE = {"I1": (1e-9, 10.0), "I2": (1e-9, 10.0),     # kg m^2
             "B": (0.0, 1e3),                             # N m s/rad
             "K": (1e-2, 1e8),                            # N m/rad
             "lead": (1e-6, 1.0)}                         # m/rad (1 mm/rev = 1.6e-4 m/rad)
UNITS = {"I1": "kg m^2", "I2": "kg m^2", "B": "N m s/rad", "K": "N m/rad", "lead": "m/rad"}


@dataclass(frozen=True, slots=True)
class AxisParams:
    """Physical parameters of one axis.

    Attributes
    ----------
    I1 : motor + spindle inertia [kg m^2]
    I2 : equivalent table inertia [kg m^2]
    B : coupling damping [N m s/rad]
    K : coupling stiffness [N m/rad]
    lead : spindle lead l [m/rad], table position x = l * theta2
    """

    I1: float
    I2: float
    B: float
    K: float
    lead: float = 7.96e-4

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f.name, f"must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ConfigError(f.name, f"must be finite, got {value!r}")
            if f.name == "B":
                if value < 0.0:
                    raise ConfigError(f.name, f"damping must be >= 0, got {value!r}")
            elif value <= 0.0:
                raise ConfigError(f.name, f"must be > 0, got {value!r}")
            object.__setattr__(self, f.name, value)

    # -- conversions -------------------------------------------------------
    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    def with_(self, **changes: float) -> AxisParams:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], *, where: str = "axis") -> AxisParams:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"{where}.{sorted(unknown)[0]}", f"unknown field (expected {sorted(known)})")
        missing = {"I1", "I2", "B", "K"} - set(data)
        if missing:
            raise ConfigError(f"{where}.{sorted(missing)[0]}", "missing")
        try:
            params = cls(**dict(data))
        except ConfigError as exc:
            raise ConfigError(f"{where}.{exc.field}", str(exc).split(": ", 1)[1]) from None
        for name, (lo, hi) in PLAUSIBLE.items():
            value = getattr(params, name)
            if not lo <= value <= hi:
                raise ConfigError(f"{where}.{name}", f"{value:g} {UNITS[name]} is outside the range of a "
                                  f"machine-tool axis, {lo:g} .. {hi:g} {UNITS[name]}")
        return params

    @classmethod
    def from_toml(cls, path: str | Path) -> AxisParams:
        """Read the ``[axis]`` table of a TOML file."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(str(path), "file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(str(path), f"not valid TOML: {exc}") from None
        if "axis" not in data:
            raise ConfigError(f"{path}:axis", "missing [axis] table")
        return cls.from_mapping(data["axis"], where=f"{path.name}:axis")


def thomson_x() -> AxisParams:
    """Table 1 of the paper: THOMSON X axis, read from ``configs/thomson_x.toml``.

    Falls back to the literal Table 1 values when the configs folder is not
    shipped alongside the package (a non-editable wheel install).
    """
    path = CONFIG_DIR / "thomson_x.toml"
    if path.is_file():
        return AxisParams.from_toml(path)
    return AxisParams(I1=2.7e-5, I2=8.3e-6, B=2.1e-3, K=1.1e2, lead=7.96e-4)

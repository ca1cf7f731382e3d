"""Friction to ground and backlash for the two-inertia axis (beyond the paper).

The paper's model (Eqs. 1-3) has no friction: ``I1 th1'' + B (th1' - th2') + K (th1 - th2) = T`` and
``I2 th2'' - B (th1' - th2') - K (th1 - th2) = 0``. A real ball-screw axis adds, on each body ``i``
(1 = motor + screw, 2 = table), a torque to ground

    f_i(v) = Fv_i v + sign(v) [Fc_i + (Fs_i - Fc_i) exp(-(v / vs_i)^2)]        (sliding, v != 0)
    |f_i| <= Fs_i, balancing every other torque on the body                      (sticking, v == 0)

so Eq. (3) becomes ``M th'' + C th' + K th + f(th') = [T, 0]`` and, with backlash of width ``b`` in
the nut, the coupling ``K (th1 - th2)`` becomes ``K dz(th1 - th2)`` with the dead zone
``dz(d) = d - b/2 sign(d)`` for ``|d| > b/2`` and 0 inside the gap (no coupling damping there either).

**Which stick-slip model, and why.** Karnopp's switching model (Karnopp 1985): a body whose velocity
is inside a window around zero is held (velocity zero) while the net torque of everything else on
it stays below the static friction Fs, and breaks away with Fs against that torque when it exceeds
it. We chose it over LuGre because (i) the plant is sampled exactly (ZOH) at 1-34 kHz and LuGre's
bristle state is stiff (sigma0 / I ~ 1e8-1e10 s^-2 for these inertias), so it would need an
implicit integrator or sub-steps in a kernel that must stay at tens of M samples/s; (ii) Karnopp
has no extra state to identify or to initialize, and its parameters (Fc, Fv, Fs, vs) are exactly
those the estimators fit; (iii) it sticks *exactly* (no creep, no chatter), which is what makes
reversal spikes and standstill stretches in the simulated data look like a real recording's.
Pre-sliding (micro-displacement) behaviour, which LuGre would add, is below the encoder's
resolution here.

The discrete version (:func:`rt_ident.axis.kernels.plant_block_friction`): the linear part,
*including the viscous terms Fv_i to ground*, is discretized exactly (ZOH, two inputs: torque on
body 1 and on body 2); the Coulomb/Stribeck torque is held over the sample like the drive torque.
The velocity window is "the velocity reached zero during the last sample, or is within
``stick_window`` of it": a body whose velocity crosses zero inside a sample is stopped there
(velocity set to 0), and at the next sample it sticks (position pinned) or breaks away.

**Values for the THOMSON axis** (Table 1 gives none; :func:`thomson_friction`). Plausible
magnitudes, not measurements: motor side Fc1 = 0.010 N m (motor brushes and bearings plus the
preloaded nut's drag torque, a few % of a ~0.3-0.5 N m rated small servomotor; ball-screw catalogs
give 0.01-0.05 N m drag for a preloaded 16-20 mm nut), Fs1 = 1.2 Fc1 with vs1 = 1 rad/s,
Fv1 = 2e-5 N m s/rad (2 mN m at 100 rad/s). Table side: the table mass is I2 / lead^2 = 13 kg;
rolling linear guides with seals have a friction coefficient ~0.003-0.005 plus 2-4 N of seal drag,
so ~4 N, i.e. Fc2 = 4 N x lead = 3.2e-3 N m in the model's table coordinate th2 = x / lead;
Fs2 = 1.3 Fc2 with vs2 = 1.26 rad/s (1 mm/s), Fv2 = 50 N s/m x lead^2 = 3.2e-5 N m s/rad.
No backlash (a preloaded nut); ``backlash`` is there to study a worn one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np
import scipy.linalg

from rt_ident.errors import ConfigError

#: Table 1's lead [m/rad], to convert the table-side values above (kept local: no params import cycle).
_LEAD_TABLE1 = 7.96e-4


@dataclass(frozen=True)
class Friction:
    """Friction to ground per body (1 = motor, 2 = table) and backlash in the coupling.

    Torques in N m on the model's angles (table side: force [N] x lead); velocities in rad/s.
    ``Fs`` (static/breakaway) defaults to ``Fc`` (no Stribeck drop) and must be >= Fc; ``vs`` = 0
    also means no Stribeck term. ``backlash`` [rad of th1 - th2]: width b of the dead zone.
    ``stick_window`` [rad/s]: Karnopp's velocity window (a zero crossing within a sample always
    counts). All zero (the default): no friction, and the plant runs its frictionless kernel.
    """

    Fc1: float = 0.0
    Fv1: float = 0.0
    Fs1: float | None = None
    vs1: float = 0.0
    Fc2: float = 0.0
    Fv2: float = 0.0
    Fs2: float | None = None
    vs2: float = 0.0
    backlash: float = 0.0
    stick_window: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ConfigError(f"friction.{f.name}", f"must be a number, got {v!r}")
            v = float(v)
            if not math.isfinite(v) or v < 0.0:
                raise ConfigError(f"friction.{f.name}", f"must be finite and >= 0, got {v!r}")
            object.__setattr__(self, f.name, v)
        for i in ("1", "2"):
            fc, fs = getattr(self, "Fc" + i), getattr(self, "Fs" + i)
            if fs is None:
                object.__setattr__(self, "Fs" + i, fc)
            elif fs < fc:
                raise ConfigError(f"friction.Fs{i}", f"static friction must be >= Fc{i} = {fc}, got {fs}")

    @property
    def active(self) -> bool:
        return any(getattr(self, k) > 0.0 for k in ("Fc1", "Fv1", "Fs1", "Fc2", "Fv2", "Fs2", "backlash"))

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    def with_(self, **changes: float) -> Friction:
        return replace(self, **changes)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None, *, where: str = "friction") -> Friction:
        """From a config table (``[plant.friction]`` / ``[backend.friction]``). ``preset = "thomson"``
        starts from :func:`thomson_friction` and the other keys override it."""
        if data is None:
            return cls()
        if isinstance(data, Friction):
            return data
        if not isinstance(data, Mapping):
            raise ConfigError(where, f"must be a table, got {data!r}")
        d = dict(data)
        preset = d.pop("preset", None)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"{where}.{unknown[0]}", f"unknown key (expected preset, {', '.join(sorted(known))})")
        if preset is None:
            base = cls()
        elif str(preset).lower() == "thomson":
            base = thomson_friction()
        elif str(preset).lower() == "none":
            base = cls()
        else:
            raise ConfigError(f"{where}.preset", f"unknown preset {preset!r} (thomson, none)")
        try:
            return replace(base, **{**_keep_static(base, d), **d})
        except ConfigError as exc:
            raise ConfigError(f"{where}.{exc.field.split('.')[-1]}", str(exc).split(": ", 1)[-1]) from None


def _keep_static(base: Friction, d: Mapping[str, Any]) -> dict[str, float | None]:
    """When an override changes Fc_i but not Fs_i, keep the preset's ratio Fs_i / Fc_i."""
    out: dict[str, float | None] = {}
    for i in ("1", "2"):
        if "Fc" + i in d and "Fs" + i not in d:
            fc0, fs0 = getattr(base, "Fc" + i), getattr(base, "Fs" + i)
            out["Fs" + i] = None if fc0 == 0.0 else float(d["Fc" + i]) * fs0 / fc0
    return out


def thomson_friction(lead: float = _LEAD_TABLE1) -> Friction:
    """Plausible friction of the THOMSON X axis (see the module docstring for where they come from)."""
    return Friction(Fc1=0.010, Fv1=2.0e-5, Fs1=0.012, vs1=1.0,
                    Fc2=4.0 * lead, Fv2=50.0 * lead**2, Fs2=1.3 * 4.0 * lead, vs2=1e-3 / lead)


def two_input_state_space(I1: float, I2: float, B: float, K: float, Fv1: float = 0.0,
                          Fv2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (8) with viscous friction to ground and two torque inputs (on body 1, on body 2).

    State [th1, w1, th2, w2] (Eq. 8's order); returns (A 4x4, Bm 4x2)."""
    A = np.array([[0.0, 1.0, 0.0, 0.0],
                  [-K / I1, -(B + Fv1) / I1, K / I1, B / I1],
                  [0.0, 0.0, 0.0, 1.0],
                  [K / I2, B / I2, -K / I2, -(B + Fv2) / I2]])
    Bm = np.array([[0.0, 0.0], [1.0 / I1, 0.0], [0.0, 0.0], [0.0, 1.0 / I2]])
    return A, Bm


def _zoh2(A: np.ndarray, Bm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    aug = np.zeros((6, 6))
    aug[:4, :4] = A
    aug[:4, 4:] = Bm
    E = scipy.linalg.expm(aug * dt)
    return E[:4, :4].copy(), E[:4, 4:].copy()


def friction_matrices(I1: float, I2: float, B: float, K: float, fr: Friction,
                      dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Step matrices of the friction kernel: Phi (2, 4, 4), Gam (2, 4, 2).

    Index 0: the coupled axis (nut in contact; viscous friction to ground included exactly);
    index 1: the two bodies decoupled (inside the backlash gap: no K, no B)."""
    P0, G0 = _zoh2(*two_input_state_space(I1, I2, B, K, fr.Fv1, fr.Fv2), dt)
    P1, G1 = _zoh2(*two_input_state_space(I1, I2, 0.0, 0.0, fr.Fv1, fr.Fv2), dt)
    return np.ascontiguousarray(np.stack([P0, P1])), np.ascontiguousarray(np.stack([G0, G1]))


def friction_par(B: float, K: float, fr: Friction) -> np.ndarray:
    """The kernel's friction parameter vector (see :func:`rt_ident.axis.kernels.plant_block_friction`)."""
    return np.array([fr.Fc1, fr.Fs1, fr.vs1, fr.Fc2, fr.Fs2, fr.vs2, fr.backlash, K, B, fr.stick_window])


def coulomb(v: np.ndarray, Fc: float, Fs: float | None = None, vs: float = 0.0) -> np.ndarray:
    """The sliding Coulomb + Stribeck torque sign(v) [Fc + (Fs - Fc) exp(-(v/vs)^2)] (0 at v = 0)."""
    v = np.asarray(v, dtype=float)
    mag = np.full(v.shape, float(Fc))
    if Fs is not None and vs > 0.0:
        mag = mag + (float(Fs) - Fc) * np.exp(-(v / vs) ** 2)
    return np.sign(v) * mag


__all__ = ["Friction", "thomson_friction", "friction_matrices", "friction_par", "two_input_state_space",
           "coulomb"]

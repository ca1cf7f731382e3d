"""A sampled closed-loop plant with realistic sensors (pure numerics: no clock, no I/O).

The simulated backend and the emulated CANopen / serial devices step this
object. Per sample ``k`` (:func:`rt_ident.axis.kernels.plant_block`):

1. measure: true angles at ``t_k`` + angle noise, then quantized to the motor
   encoder (``2 pi / counts_per_rev``) and to the table's linear scale
   (``x = lead theta2`` rounded to ``scale_resolution``, divided by ``lead``);
2. controller (optional :class:`HoldController`): PD on the *measured* motor
   angle, velocity from a first-order low-pass of the backward difference;
3. applied torque = saturate(command + controller, +-torque_limit) + process noise;
   reported torque = applied + measurement noise;
4. physics: the applied torque is held over ``[t_k, t_{k+1})`` - exact ZOH
   discretization of Eq. (8) (``integrator="zoh"``), or Newmark's average
   acceleration step with the held torque (``integrator="newmark"``, see
   :meth:`rt_ident.axis.integrators.Newmark.step_matrices`).

With ``friction`` (:class:`rt_ident.axis.friction.Friction`) the physics step is
:func:`rt_ident.axis.kernels.plant_block_friction` instead: Coulomb/viscous/Stribeck friction to
ground on each body with Karnopp sticking, and optional backlash (ZOH only). Without friction (the
default, or all-zero values) the frictionless kernel runs.

Noise comes from ``numpy.random.Generator(seed)``, drawn as one (n, 4) array
per block in sample order, so the result does not depend on how a run is
split into blocks.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rt_ident.axis.friction import Friction, friction_matrices, friction_par
from rt_ident.axis.integrators import Newmark, check_dt, check_x0, zoh_matrices
from rt_ident.axis.kernels import (
    first_non_finite3,
    plant_block,
    plant_block_friction,
    plant_block_friction_py,
    plant_block_py,
)
from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

# Default hold-loop gains: a PD on the rigid body J = I1 + I2 of Table 1 with a closed-loop
# natural frequency of 30 Hz and damping 1/sqrt(2) (so the -3 dB bandwidth of
# kp / (J s^2 + kd s + kp) is 30 Hz): kp = J w^2 = 1.254 N m/rad, kd = sqrt(2) J w = 9.41e-3 N m s/rad.
_J_TABLE1 = 2.7e-5 + 8.3e-6
_W_HOLD = 2.0 * math.pi * 30.0
DEFAULT_KP = _J_TABLE1 * _W_HOLD**2
DEFAULT_KD = math.sqrt(2.0) * _J_TABLE1 * _W_HOLD


def _check_number(field: str, value: float, *, minimum: float = 0.0, strict: bool = False,
                  allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(field, f"must be a number, got {value!r}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(field, f"must be finite, got {value!r}")
    if v < minimum or (strict and v == minimum):
        raise ConfigError(field, f"must be {'>' if strict else '>='} {minimum}, got {value!r}")
    return v


@dataclass(frozen=True)
class SensorConfig:
    """Sensors of one axis. A zero resolution means an ideal (unquantized) sensor."""

    counts_per_rev: int = 2**17        # motor encoder [counts/rev]
    scale_resolution: float = 1e-7     # table linear scale [m]
    angle_noise: float = 0.0           # rad rms added to both angles before quantization
    torque_meas_noise: float = 0.0     # N m rms added to the reported torque
    torque_process_noise: float = 0.0  # N m rms added to the torque actually applied

    def __post_init__(self) -> None:
        cpr = self.counts_per_rev
        if isinstance(cpr, bool) or not isinstance(cpr, (int, np.integer)) or cpr < 0:
            raise ConfigError("counts_per_rev", f"must be an integer >= 0, got {cpr!r}")
        for f in ("scale_resolution", "angle_noise", "torque_meas_noise", "torque_process_noise"):
            object.__setattr__(self, f, _check_number(f, getattr(self, f)))

    @property
    def theta1_quantum(self) -> float:
        """Motor-angle quantization step 2 pi / cpr [rad] (0: ideal)."""
        return 2.0 * math.pi / self.counts_per_rev if self.counts_per_rev else 0.0

    def theta2_quantum(self, lead: float) -> float:
        """Table-angle quantization step res / lead [rad] (0: ideal)."""
        return self.scale_resolution / lead

    @property
    def noisy(self) -> bool:
        return (self.angle_noise > 0.0 or self.torque_meas_noise > 0.0
                or self.torque_process_noise > 0.0)


@dataclass(frozen=True)
class HoldController:
    """A drive's position loop holding theta1 at ``reference``: T = kp (ref - th1m) - kd vf.

    ``vf`` is a first-order low-pass (``velocity_filter_hz``) of the backward
    difference of the measured, quantized theta1. Defaults: 30 Hz closed-loop
    bandwidth, damping 0.707 on I1 + I2 of Table 1 (see DEFAULT_KP/KD).
    """

    kp: float = DEFAULT_KP                # N m/rad
    kd: float = DEFAULT_KD                # N m s/rad
    velocity_filter_hz: float = 2000.0    # inf: unfiltered backward difference
    reference: float = 0.0                # rad

    def __post_init__(self) -> None:
        object.__setattr__(self, "kp", _check_number("kp", self.kp))
        object.__setattr__(self, "kd", _check_number("kd", self.kd))
        object.__setattr__(self, "velocity_filter_hz",
                           _check_number("velocity_filter_hz", self.velocity_filter_hz,
                                         strict=True, allow_inf=True))
        object.__setattr__(self, "reference", _check_number("reference", self.reference,
                                                            minimum=-math.inf))

    def filter_gain(self, dt: float) -> float:
        """beta of vf <- vf + beta (v_raw - vf): exact discretization of a first-order low-pass."""
        return 1.0 - math.exp(-2.0 * math.pi * self.velocity_filter_hz * dt)


@dataclass(frozen=True)
class PlantBlock:
    """Output of one :meth:`PlantSimulator.step_block` call; arrays of equal length n."""

    theta1: np.ndarray          # measured motor angle (noisy, quantized) [rad]
    theta2: np.ndarray          # measured table angle x/lead (noisy, quantized) [rad]
    torque_cmd: np.ndarray      # host command (excitation) [N m]
    torque_applied: np.ndarray  # true applied torque [N m]
    torque_meas: np.ndarray     # reported torque [N m]
    true_states: np.ndarray     # (n, 4) true [theta1, omega1, theta2, omega2] at each sample

    def __len__(self) -> int:
        return int(self.theta1.shape[0])


_PLANT_INTEGRATORS = ("zoh", "newmark")


class PlantSimulator:
    """The axis of Eq. (3) sampled every ``dt`` with sensors, a hold loop and limits.

    Stateful (the true state, the controller memory and the random generator
    advance with each :meth:`step_block`). Deterministic given ``seed``.
    """

    def __init__(self, p: AxisParams, dt: float, *, sensors: SensorConfig = SensorConfig(),
                 controller: HoldController | None = None, torque_limit: float = math.inf,
                 travel: tuple[float, float] | None = None, integrator: str = "zoh",
                 seed: int = 0, x0: np.ndarray | None = None, friction: Friction | None = None) -> None:
        if not isinstance(p, AxisParams):
            raise ConfigError("p", f"must be AxisParams, got {type(p).__name__}")
        if not isinstance(sensors, SensorConfig):
            raise ConfigError("sensors", f"must be SensorConfig, got {type(sensors).__name__}")
        if controller is not None and not isinstance(controller, HoldController):
            raise ConfigError("controller", f"must be HoldController or None, got {type(controller).__name__}")
        self.params = p
        self.dt = check_dt(dt)
        self.sensors = sensors
        self.controller = controller
        self.torque_limit = _check_number("torque_limit", torque_limit, strict=True, allow_inf=True)
        if travel is None:
            lo, hi = -math.inf, math.inf
        else:
            try:
                lo, hi = (float(v) for v in travel)
            except (TypeError, ValueError):
                raise ConfigError("travel", f"must be a (min, max) pair in metres, got {travel!r}") from None
            if math.isnan(lo) or math.isnan(hi) or not lo < hi:
                raise ConfigError("travel", f"must satisfy min < max, got {travel!r}")
        self.travel = (lo, hi)
        key = str(integrator).strip().lower()
        if key not in _PLANT_INTEGRATORS:
            raise ConfigError("integrator", f"unknown plant integrator {integrator!r}; valid: "
                              f"{', '.join(_PLANT_INTEGRATORS)}")
        self.integrator = key
        if friction is not None and not isinstance(friction, Friction):
            raise ConfigError("friction", f"must be Friction or None, got {type(friction).__name__}")
        self.friction = friction if friction is not None and friction.active else None
        if self.friction is not None and key != "zoh":
            raise ConfigError("integrator", "friction needs the 'zoh' plant integrator (the friction torque is "
                              "held over the sample like the drive torque)")
        self._fstate = np.zeros(2)       # Karnopp stuck flags of body 1 and 2
        self._fpar = friction_par(p.B, p.K, self.friction) if self.friction is not None else np.zeros(10)
        self._set_matrices(p)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise ConfigError("seed", f"must be an integer, got {seed!r}")
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self._x = check_x0(x0)
        # [previous measured theta1, filtered velocity, has-previous flag, travel-exceeded flag]
        self._ctrl = np.zeros(4)
        self._k = 0
        c = controller
        self._par = np.array([
            sensors.theta1_quantum, sensors.scale_resolution, p.lead,
            1.0 if c is not None else 0.0,
            c.kp if c else 0.0, c.kd if c else 0.0, c.reference if c else 0.0,
            c.filter_gain(self.dt) if c else 1.0,
            self.torque_limit, sensors.angle_noise, sensors.torque_meas_noise,
            sensors.torque_process_noise, lo, hi, 1.0 / self.dt,
        ])
        logger.debug("plant: dt=%g s, integrator=%s, controller=%s, torque_limit=%g, seed=%d",
                     self.dt, key, controller, self.torque_limit, self.seed)
        self._noisy = sensors.noisy
        self._noise = np.empty((64 if self._noisy else 0, 4))
        self._no_noise = np.empty((0, 4))

    def matrices_for(self, p: AxisParams) -> tuple[np.ndarray, np.ndarray]:
        """The step matrices (Phi, Gam) this plant would use for ``p`` (matrix exponential: ~ms).
        With friction: the stacked two-input matrices of :func:`~rt_ident.axis.friction.friction_matrices`."""
        if self.friction is not None:
            return friction_matrices(p.I1, p.I2, p.B, p.K, self.friction, self.dt)
        if self.integrator == "zoh":
            Phi, Gam = zoh_matrices(p, self.dt)
        else:
            Phi, Gam = Newmark().step_matrices(p, self.dt)
        return np.ascontiguousarray(Phi), np.ascontiguousarray(Gam)

    def _set_matrices(self, p: AxisParams) -> None:
        self._Phi, self._Gam = self.matrices_for(p)

    def set_params(self, p: AxisParams, matrices: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Change the physical parameters from the next sample on (a workpiece clamped on the
        table, worn preload...). The true state, the sensors, the hold loop's memory and the noise
        generator carry over; the lead must stay the same (the sensors are built on it).
        ``matrices``: ``matrices_for(p)`` computed ahead, so a scheduled change costs no expm."""
        if not isinstance(p, AxisParams):
            raise ConfigError("p", f"must be AxisParams, got {type(p).__name__}")
        if p.lead != self.params.lead:
            raise ConfigError("lead", f"cannot change the lead mid-run ({self.params.lead} -> {p.lead})")
        if matrices is None:
            self._set_matrices(p)
        else:
            self._Phi, self._Gam = (np.ascontiguousarray(m, dtype=np.float64) for m in matrices)
        if self.friction is not None:
            self._fpar = friction_par(p.B, p.K, self.friction)
        self.params = p

    # -- state -------------------------------------------------------------------------
    @property
    def state(self) -> np.ndarray:
        """True current state [theta1, omega1, theta2, omega2] (a copy)."""
        return self._x.copy()

    @property
    def sample_index(self) -> int:
        """Index of the next sample to be produced (= samples produced so far)."""
        return self._k

    @property
    def travel_exceeded(self) -> bool:
        """True once the table (x = lead theta2) has been seen outside the travel window."""
        return bool(self._ctrl[3])

    # -- stepping ----------------------------------------------------------------------
    def step_block(self, torque_cmd: np.ndarray, *, compiled: bool = True) -> PlantBlock:
        """Advance ``len(torque_cmd)`` samples; ``torque_cmd[i]`` is the command for sample k+i.

        ``compiled=False`` runs the same loop interpreted (reference path for tests).
        """
        cmd = np.asarray(torque_cmd, dtype=np.float64)
        if cmd.ndim != 1:
            raise DataError(f"torque_cmd: must be 1-D, got shape {cmd.shape}")
        n = cmd.shape[0]
        cmd_out = cmd.copy()
        th1 = np.empty(n)
        th2 = np.empty(n)
        applied = np.empty(n)
        meas = np.empty(n)
        states = np.empty((n, 4))
        if self._noisy:
            if self._noise.shape[0] < n:
                self._noise = np.empty((max(n, 2 * self._noise.shape[0]), 4))
            noise = self._noise[:n]
        else:
            noise = self._no_noise
        # validate before drawing noise so a rejected block leaves the plant untouched
        bad = _first_non_finite(cmd_out)
        if bad >= 0:
            raise DataError(f"torque_cmd: non-finite value at sample {bad} of the block")
        if self._noisy and n:
            self._rng.standard_normal(out=noise)
        if self.friction is not None:
            fk = plant_block_friction if compiled else plant_block_friction_py
            fk(self._Phi, self._Gam, self._x, self._ctrl, cmd_out, noise, self._par, self._fpar, self._fstate,
               th1, th2, applied, meas, states)
        else:
            kernel = plant_block if compiled else plant_block_py
            kernel(self._Phi, self._Gam, self._x, self._ctrl, cmd_out, noise, self._par,
                   th1, th2, applied, meas, states)
        self._k += n
        return PlantBlock(th1, th2, cmd_out, applied, meas, states)

    def closed_loop_matrix(self) -> np.ndarray:
        """6x6 map of [x_k, th1m_{k-1}, vf_{k-1}] with the hold loop, ideal sensors, no limits.

        Its eigenvalues show the stability and damping of the controlled plant
        (the rigid-body pair moves inside the unit circle when a controller is set).
        """
        c = self.controller
        kp, kd = (c.kp, c.kd) if c else (0.0, 0.0)
        beta = c.filter_gain(self.dt) if c else 1.0
        Phi, Gam = (self._Phi[0], self._Gam[0][:, 0]) if self.friction is not None else (self._Phi, self._Gam)
        F = np.zeros((6, 6))
        # vf_k = (1 - beta) vf_{k-1} + beta (x0_k - th1m_{k-1}) / dt
        vf_row = np.zeros(6)
        vf_row[0] = beta / self.dt
        vf_row[4] = -beta / self.dt
        vf_row[5] = 1.0 - beta
        torque_row = -kp * np.eye(6)[0] - kd * vf_row  # T_k = -kp th1m_k - kd vf_k
        F[:4] = np.hstack([Phi, np.zeros((4, 2))]) + np.outer(Gam, torque_row)
        F[4, 0] = 1.0
        F[5] = vf_row
        return F


def _first_non_finite(a: np.ndarray) -> int:
    return int(first_non_finite3(a, a, a)) if a.size else -1     # one compiled pass (see kernels)


def rest_at(x0: float, lead: float) -> np.ndarray | None:
    """The initial state (Eq. 8 order) with the table at rest at ``x0`` [m on the scale] and the coupling
    relaxed (motor and table at the same angle); None (the default, all zero) for the origin."""
    if x0 == 0.0:
        return None
    th = x0 / lead
    return np.array([th, 0.0, th, 0.0])

"""Five time integrators of the two-inertia model (Eq. 3) behind one interface.

Conventions shared by every integrator:

* ``torque[k]`` is the torque sample at ``t_k = k dt``; ``n = len(torque)``;
  sample 0 of the trajectory is ``x0`` (default: at rest at zero);
* states are in Eq. (8) order ``x = [theta1, omega1, theta2, omega2]``;
* ``Trajectory.alpha`` is the acceleration from the equilibrium Eq. (6) evaluated
  at each sample with ``torque[k]`` (for Newmark it is the method's own
  acceleration; Wilson-theta carries a slightly different internal one).

Implicit methods (Newmark, Wilson-theta, Houbolt) use the load at ``t_{k+1}``,
i.e. ``torque[k+1]``; RK4 and ZOH hold ``torque[k]`` over ``[t_k, t_{k+1})``.

Every method applied to this linear model is a linear recursion
``z[k+1] = S z[k] + G0 u[k] + G1 u[k+1]``. Each class writes its textbook step
once (``_step``, the reference path ``compiled=False``); the step matrices are
obtained by applying that step to unit vectors and the loop runs in the numba
kernel :func:`rt_ident.axis.kernels.trajectory_recursion` (``compiled=True``), which
also fills every field of the :class:`Trajectory` (times, angles, velocities, the
Eq. (6) accelerations, the torque copy) and checks the torque in the same pass.
``simulate(..., out=trajectory)`` reuses the arrays of an earlier result.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import scipy.linalg

from rt_ident.axis.kernels import trajectory_recursion
from rt_ident.axis.model import damping_matrix, mass_matrix, state_space, stiffness_matrix
from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

INTEGRATORS: tuple[str, ...] = ("newmark", "wilson", "houbolt", "rk4", "zoh")

_Q = np.array([0, 2])  # positions inside an Eq. (8) state
_V = np.array([1, 3])  # velocities


@dataclass(frozen=True)
class Trajectory:
    """A simulated response, ``n`` samples at ``t = k dt``."""

    t: np.ndarray       # (n,)
    theta: np.ndarray   # (n, 2) [theta1, theta2]
    omega: np.ndarray   # (n, 2)
    alpha: np.ndarray   # (n, 2) accelerations from the equilibrium Eq. (6) at each sample
    torque: np.ndarray  # (n,)

    def states(self) -> np.ndarray:
        """(n, 4) states in Eq. (8) order [theta1, omega1, theta2, omega2] (a new array)."""
        x = np.empty((self.theta.shape[0], 4), dtype=np.result_type(self.theta, self.omega))
        x[:, 0::2] = self.theta
        x[:, 1::2] = self.omega
        return x


@runtime_checkable
class Integrator(Protocol):
    name: ClassVar[str]

    def simulate(self, p: AxisParams, torque: np.ndarray, dt: float,
                 x0: np.ndarray | None = None) -> Trajectory: ...


# --------------------------------------------------------------------------- helpers
@dataclass(frozen=True)
class _Ctx:
    """Matrices of Eq. (3) and the step constants of one (p, dt)."""

    p: AxisParams
    M: np.ndarray
    C: np.ndarray
    K: np.ndarray
    dt: float
    extra: dict[str, Any]


def check_dt(dt: float) -> float:
    """Validate a sample period (finite, > 0)."""
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)):
        raise ConfigError("dt", f"must be a number, got {dt!r}")
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0.0:
        raise ConfigError("dt", f"must be finite and > 0, got {dt!r}")
    return dt


def check_x0(x0: np.ndarray | None) -> np.ndarray:
    """Validate an initial state (4,) in Eq. (8) order; None -> zeros."""
    if x0 is None:
        return np.zeros(4)
    x = np.asarray(x0, dtype=float)
    if x.shape != (4,):
        raise ConfigError("x0", f"must have shape (4,) [theta1, omega1, theta2, omega2], got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ConfigError("x0", "must be finite")
    return x.copy()


def _as_torque(torque: np.ndarray) -> np.ndarray:
    """The torque as a contiguous float 1-D non-empty array (no copy if it already is one)."""
    u = np.ascontiguousarray(torque, dtype=float)
    if u.ndim != 1 or u.size == 0:
        raise DataError(f"torque: must be a non-empty 1-D array, got shape {u.shape}")
    return u


def _check_finite(part: np.ndarray, u: np.ndarray) -> None:
    """If ``part`` of the torque ``u`` is not finite: DataError naming u's first bad sample and count."""
    if not np.isfinite(part).all():
        bad = np.flatnonzero(~np.isfinite(u))
        raise DataError(f"torque: non-finite value at sample {int(bad[0])} ({bad.size} in total)")


_FIELDS = ("t", "theta", "omega", "alpha", "torque")


def _outputs(out: Trajectory | None, n: int, u: np.ndarray) -> Trajectory:
    """New output arrays for ``n`` samples, or ``out``'s after checking them (float64, C order,
    writeable, no overlap; out.torque may be the torque array itself)."""
    if out is None:
        return Trajectory(np.empty(n), np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2)), np.empty(n))
    if not isinstance(out, Trajectory):
        raise ConfigError("out", f"must be a Trajectory, got {type(out).__name__}")
    arrays = [getattr(out, f) for f in _FIELDS]
    for i, (f, a) in enumerate(zip(_FIELDS, arrays)):
        shape = (n,) if f in ("t", "torque") else (n, 2)
        if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == shape
                and a.flags.c_contiguous and a.flags.writeable):
            got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
            raise ConfigError("out", f"out.{f} must be a writeable C-contiguous float64 array of shape {shape}, "
                                     f"got {got}")
        if np.may_share_memory(a, u) and not (f == "torque" and a is u):
            raise ConfigError("out", f"out.{f} overlaps the torque")
        if any(np.may_share_memory(a, b) for b in arrays[:i]):
            raise ConfigError("out", f"out.{f} overlaps another field of out")
    return out


def _fill(tr: Trajectory, p: AxisParams, X: np.ndarray, u: np.ndarray, dt: float) -> None:
    """Samples 0 .. len(X)-1 of ``tr`` from states X (m, 4) in Eq. (8) order and torques u (m,)."""
    m = X.shape[0]
    tr.t[:m] = np.arange(m) * dt
    tr.theta[:m] = X[:, _Q]
    tr.omega[:m] = X[:, _V]
    tr.alpha[:m] = equilibrium_acceleration(p, X, u)
    tr.torque[:m] = u


def _accel(ctx: _Ctx, q: np.ndarray, v: np.ndarray, u: float) -> np.ndarray:
    """Eq. (6) solved for the acceleration: I a = T - B v - K q."""
    return np.linalg.solve(ctx.M, np.array([u, 0.0]) - ctx.C @ v - ctx.K @ q)


def _probe(step: Callable[[np.ndarray, float, float], np.ndarray], nz: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step matrices of a linear step ``z1 = S z + G0 u0 + G1 u1`` by applying it to unit inputs."""
    S = np.empty((nz, nz))
    for j in range(nz):
        e = np.zeros(nz)
        e[j] = 1.0
        S[:, j] = step(e, 0.0, 0.0)
    zero = np.zeros(nz)
    return S, np.asarray(step(zero, 1.0, 0.0), float), np.asarray(step(zero, 0.0, 1.0), float)


def equilibrium_acceleration(p: AxisParams, states: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """(n, 2) accelerations from Eq. (6) at each sample: states (n, 4) in Eq. (8) order."""
    d = states[:, 0] - states[:, 2]
    dv = states[:, 1] - states[:, 3]
    coupling = p.B * dv + p.K * d
    return np.column_stack([(torque - coupling) / p.I1, coupling / p.I2])


class _OneStep:
    """Shared simulate(): validation, start-up, compiled or reference loop."""

    name: ClassVar[str]
    nz: ClassVar[int]

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        return _Ctx(p, mass_matrix(p), damping_matrix(p), stiffness_matrix(p), dt, {})

    def _start(self, ctx: _Ctx, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """First sample(s) of the extended state z, shape (m, nz): default [x0, a0], with the
        initial acceleration from the equilibrium Eq. (6) at t0 (the first-order methods drop a0)."""
        z0 = np.concatenate([x0, _accel(ctx, x0[_Q], x0[_V], u[0])])
        return z0[None, :self.nz]

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        raise NotImplementedError

    def recursion_matrices(self, p: AxisParams, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(S, G0, G1) of ``z[k+1] = S z[k] + G0 u[k] + G1 u[k+1]`` (z starts with the Eq. 8 state)."""
        ctx = self._setup(p, check_dt(dt))
        return _probe(lambda z, a, b: self._step(ctx, z, a, b), self.nz)

    def simulate(self, p: AxisParams, torque: np.ndarray, dt: float,
                 x0: np.ndarray | None = None, *, compiled: bool = True,
                 out: Trajectory | None = None) -> Trajectory:
        """Simulate the response to ``torque`` sampled every ``dt`` from ``x0``.

        ``out``: a :class:`Trajectory` of ``len(torque)`` samples (e.g. an earlier result) whose
        arrays are overwritten and returned instead of new ones (saves allocating and
        page-faulting 64 bytes per sample when simulating repeatedly); if a non-finite torque
        sample raises DataError, their contents are unspecified.
        """
        dt = check_dt(dt)
        u = _as_torque(torque)
        n = u.size
        _check_finite(u[:3] if compiled else u, u)  # the start-up uses <= 3 samples; the kernel checks the rest
        x = check_x0(x0)
        tr = _outputs(out, n, u)
        ctx = self._setup(p, dt)
        head = self._start(ctx, x, u)
        m = min(head.shape[0], n)
        if not compiled:  # reference path: the textbook step in the interpreter, then post-processing
            Z = np.empty((n, self.nz))
            Z[:m] = head[:m]
            for k in range(m - 1, n - 1):
                Z[k + 1] = self._step(ctx, Z[k], u[k], u[k + 1])
            _fill(tr, p, Z[:, :4], u, dt)
            return tr
        _fill(tr, p, head[:m, :4], u[:m], dt)  # samples 0 .. m-1: the start-up
        if m < n:  # samples m .. n-1: recursion and post-processing in one compiled pass
            S, G0, G1 = _probe(lambda z, a, b: self._step(ctx, z, a, b), self.nz)
            par = np.array([p.B, p.K, p.I1, p.I2])
            bad = trajectory_recursion(S, G0, G1, u, np.ascontiguousarray(head[m - 1]), m - 1, dt, par,
                                       tr.t, tr.theta, tr.omega, tr.alpha, tr.torque)
            if bad >= 0:
                _check_finite(u[bad:bad + 1], u)
        return tr


# --------------------------------------------------------------------------- Newmark
@dataclass(frozen=True)
class Newmark(_OneStep):
    """Newmark's method, Eqs. (4)-(6) (Bathe's alpha and delta; 1/4, 1/2 = average acceleration)."""

    alpha: float = 0.25
    delta: float = 0.5
    name: ClassVar[str] = "newmark"
    nz: ClassVar[int] = 6  # [x (Eq. 8), a1, a2]

    def __post_init__(self) -> None:
        for field in ("alpha", "delta"):
            v = getattr(self, field)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(field, f"must be a finite number >= 0, got {v!r}")
        if self.alpha == 0.0:
            raise ConfigError("alpha", "alpha = 0 (explicit central difference) is not supported; use alpha > 0")
        if self.delta < 0.5 or self.alpha < 0.25 * (0.5 + self.delta) ** 2 * (1.0 - 1e-12):
            logger.warning("Newmark(alpha=%g, delta=%g) is not unconditionally stable "
                           "(needs delta >= 0.5 and alpha >= (0.5 + delta)^2 / 4)", self.alpha, self.delta)

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        ctx = super()._setup(p, dt)
        al, de = self.alpha, self.delta
        c: dict[str, Any] = {  # integration constants (Bathe, Table 9.3); Keff below is a matrix
            "a0": 1.0 / (al * dt * dt), "a1": de / (al * dt), "a2": 1.0 / (al * dt),
            "a3": 0.5 / al - 1.0, "a4": de / al - 1.0, "a5": 0.5 * dt * (de / al - 2.0),
            "a6": dt * (1.0 - de), "a7": de * dt,
        }
        c["Keff"] = ctx.K + c["a0"] * ctx.M + c["a1"] * ctx.C
        ctx.extra.update(c)
        return ctx

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        c = ctx.extra
        q, v, a = z[_Q], z[_V], z[4:6]
        # Eq. (6) at t+dt with Eqs. (4), (5) substituted, solved for the increment d = q1 - q
        # (algebraically Bathe's Keff q1 = T1 + M(a0 q + ...) + C(a1 q + ...); the incremental
        # form avoids cancelling large rigid-body angles): Keff d = T1 - K q + M(a2 v + a3 a) + C(a4 v + a5 a)
        rhs = (np.array([u1, 0.0]) - ctx.K @ q + ctx.M @ (c["a2"] * v + c["a3"] * a)
               + ctx.C @ (c["a4"] * v + c["a5"] * a))
        d = np.linalg.solve(c["Keff"], rhs)
        a1 = c["a0"] * d - c["a2"] * v - c["a3"] * a   # Eq. (5) solved for the acceleration
        v1 = v + c["a6"] * a + c["a7"] * a1            # Eq. (4)
        q1 = q + d
        return np.array([q1[0], v1[0], q1[1], v1[1], a1[0], a1[1]])

    def step_matrices(self, p: AxisParams, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(Phi, Gam) of ``x[k+1] = Phi x[k] + Gam T[k]`` for a torque *held* over the sample.

        Departure from the paper (which knows the whole torque record in
        advance): in a closed loop T[k+1] is unknown at t_k, so the acceleration
        is recomputed from Eq. (6) with T[k] at each sample and the step to
        t_{k+1} uses the same held T[k] as the load at t_{k+1}. Used by the plant.
        """
        ctx = self._setup(p, check_dt(dt))

        def held_step(x: np.ndarray, u: float, _unused: float) -> np.ndarray:
            return self._step(ctx, np.concatenate([x, _accel(ctx, x[_Q], x[_V], u)]), u, u)[:4]
        Phi, Gam, _ = _probe(held_step, 4)
        return Phi, Gam


# --------------------------------------------------------------------------- Wilson-theta
@dataclass(frozen=True)
class WilsonTheta(_OneStep):
    """Wilson-theta method (Bathe, Table 9.4); unconditionally stable for theta >= 1.37."""

    theta: float = 1.4
    name: ClassVar[str] = "wilson"
    nz: ClassVar[int] = 6  # [x (Eq. 8), a1, a2] (a: the method's acceleration)

    def __post_init__(self) -> None:
        v = self.theta
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 1.0:
            raise ConfigError("theta", f"must be a finite number >= 1, got {v!r}")
        if v < 1.37:
            logger.warning("WilsonTheta(theta=%g) is not unconditionally stable (needs theta >= 1.37)", v)

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        ctx = super()._setup(p, dt)
        th = self.theta
        tau = th * dt
        c: dict[str, Any] = {"a0": 6.0 / tau**2, "a1": 3.0 / tau, "a2": 6.0 / tau, "a3": 0.5 * tau}
        c.update({"a4": c["a0"] / th, "a5": -c["a2"] / th, "a6": 1.0 - 3.0 / th,
                  "a7": 0.5 * dt, "a8": dt * dt / 6.0})
        c["Keff"] = ctx.K + c["a0"] * ctx.M + c["a1"] * ctx.C
        ctx.extra.update(c)
        return ctx

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        c, th = ctx.extra, self.theta
        q, v, a = z[_Q], z[_V], z[4:6]
        load = u0 + th * (u1 - u0)  # load linearly extrapolated to t + theta dt
        # equilibrium at t + theta dt, solved for the increment d = q(t + theta dt) - q (see Newmark)
        rhs = (np.array([load, 0.0]) - ctx.K @ q + ctx.M @ (c["a2"] * v + 2.0 * a)
               + ctx.C @ (2.0 * v + c["a3"] * a))
        d = np.linalg.solve(c["Keff"], rhs)
        a1 = c["a4"] * d + c["a5"] * v + c["a6"] * a
        v1 = v + c["a7"] * (a1 + a)
        q1 = q + ctx.dt * v + c["a8"] * (a1 + 2.0 * a)
        return np.array([q1[0], v1[0], q1[1], v1[1], a1[0], a1[1]])


# --------------------------------------------------------------------------- Houbolt
@dataclass(frozen=True)
class Houbolt(_OneStep):
    """Houbolt's three-step method (Bathe, Table 9.2).

    Start-up: samples 1 and 2 come from the average-acceleration Newmark method
    (second order, like Houbolt), then Houbolt's backward differences take over.
    """

    name: ClassVar[str] = "houbolt"
    nz: ClassVar[int] = 8  # [x_k (Eq. 8), d1 = q_k - q_{k-1} (2), d2 = q_{k-1} - q_{k-2} (2)]

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        ctx = super()._setup(p, dt)
        ctx.extra["Keff"] = ctx.K + (2.0 / dt**2) * ctx.M + (11.0 / (6.0 * dt)) * ctx.C
        return ctx

    def _start(self, ctx: _Ctx, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        nm = Newmark().simulate(ctx.p, u[:3], ctx.dt, x0, compiled=False).states()
        head = np.zeros((nm.shape[0], self.nz))
        head[:, :4] = nm
        q = nm[:, _Q]
        for k in range(1, nm.shape[0]):
            head[k, 4:6] = q[k] - q[k - 1]
            head[k, 6:8] = q[k - 1] - q[k - 2] if k >= 2 else 0.0
        return head

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        dt = ctx.dt
        q, d1, d2 = z[_Q], z[4:6], z[6:8]
        # Houbolt's differences written with increments d = q_{k+1} - q_k, d1, d2:
        #   a_{k+1} = (2 q_{k+1} - 5 q_k + 4 q_{k-1} - q_{k-2}) / dt^2 = (2 d - 3 d1 + d2) / dt^2
        #   v_{k+1} = (11 q_{k+1} - 18 q_k + 9 q_{k-1} - 2 q_{k-2}) / (6 dt) = (11 d - 7 d1 + 2 d2) / (6 dt)
        # substituted into the equilibrium Eq. (6) at t_{k+1}.
        rhs = (np.array([u1, 0.0]) - ctx.K @ q + ctx.M @ (3.0 * d1 - d2) / dt**2
               + ctx.C @ (7.0 * d1 - 2.0 * d2) / (6.0 * dt))
        d = np.linalg.solve(ctx.extra["Keff"], rhs)
        q1 = q + d
        v1 = (11.0 * d - 7.0 * d1 + 2.0 * d2) / (6.0 * dt)
        return np.array([q1[0], v1[0], q1[1], v1[1], d[0], d[1], d1[0], d1[1]])


# --------------------------------------------------------------------------- RK4 and exact ZOH
@dataclass(frozen=True)
class RungeKutta4(_OneStep):
    """Classical RK4 on Eq. (8) with torque[k] held over the step (4th order for ZOH input)."""

    name: ClassVar[str] = "rk4"
    nz: ClassVar[int] = 4

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        ctx = super()._setup(p, dt)
        A, b = state_space(p)
        ctx.extra.update(A=A, b=b)
        return ctx

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        A, b, h = ctx.extra["A"], ctx.extra["b"], ctx.dt
        bu = b * u0  # zero-order hold: the same torque in every stage
        k1 = A @ z + bu
        k2 = A @ (z + 0.5 * h * k1) + bu
        k3 = A @ (z + 0.5 * h * k2) + bu
        k4 = A @ (z + h * k3) + bu
        return z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def zoh_matrices(p: AxisParams, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretization of Eq. (8) for a torque held over [t_k, t_{k+1}).

    expm([[A, b], [0, 0]] dt) = [[Phi, Gam], [0, 1]].
    """
    dt = check_dt(dt)
    A, b = state_space(p)
    aug = np.zeros((5, 5))
    aug[:4, :4] = A
    aug[:4, 4] = b
    E = scipy.linalg.expm(aug * dt)
    return E[:4, :4].copy(), E[:4, 4].copy()


@dataclass(frozen=True)
class ZeroOrderHold(_OneStep):
    """Exact solution for a piecewise-constant torque (the physics of a sampled drive)."""

    name: ClassVar[str] = "zoh"
    nz: ClassVar[int] = 4

    def _setup(self, p: AxisParams, dt: float) -> _Ctx:
        ctx = super()._setup(p, dt)
        Phi, Gam = zoh_matrices(p, dt)
        ctx.extra.update(Phi=Phi, Gam=Gam)
        return ctx

    def _step(self, ctx: _Ctx, z: np.ndarray, u0: float, u1: float) -> np.ndarray:
        return ctx.extra["Phi"] @ z + ctx.extra["Gam"] * u0

    def step_matrices(self, p: AxisParams, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(Phi, Gam) of ``x[k+1] = Phi x[k] + Gam T[k]``."""
        return zoh_matrices(p, dt)


# --------------------------------------------------------------------------- registry
_CLASSES: dict[str, type[_OneStep]] = {
    "newmark": Newmark, "wilson": WilsonTheta, "houbolt": Houbolt, "rk4": RungeKutta4, "zoh": ZeroOrderHold,
}


def get_integrator(name: str, **kw: Any) -> Integrator:
    """An integrator by name (one of :data:`INTEGRATORS`), with its options as keywords."""
    key = str(name).strip().lower()
    if key not in _CLASSES:
        raise ConfigError("integrator", f"unknown integrator {name!r}; valid: {', '.join(INTEGRATORS)}")
    try:
        return _CLASSES[key](**kw)
    except TypeError as exc:
        raise ConfigError("integrator", f"bad option for {key!r}: {exc}") from None

r"""Position-controller design on the sampled two-inertia model, and its margin check.

The host closes the position loop at the *tick* rate (default 1 kHz). The plant seen by
the loop is Eq. (8) behind a zero-order hold, with one tick of computation delay: the
torque computed from the samples of tick k is applied from tick k+1 on. Table 1's mode
(662 Hz) lies above the 500 Hz Nyquist frequency of a 1 kHz loop and aliases into it
(to 338 Hz); the exact sampled model (zero-order hold, :func:`zoh`) carries it, so the
design sees the alias where the loop will.

State of the design model (one tick, period ``T``, a delay of ``d`` ticks, default 1)

.. math::

    z_k = [\theta_1, \omega_1, \theta_2, \omega_2, u_{k-d}, \dots, u_{k-1}, \xi_k]^T,\quad
    x_{k+1} = A_d x_k + B_d u_{k-d},\quad \xi_{k+1} = \xi_k + T\,(\theta_{2,k} - \theta_{2,k}^{ref})

(``u_{k-d} .. u_{k-1}``: the torques in flight, the delay; ``xi``: integral of the table-angle
error, for zero steady error under a constant load). A backend whose torque lands later than one
tick after the newest sample (a serial board that streams in bursts, a field bus) is designed with
``d = 2``: ``[control] delay_ticks``. The law is ``u_k = -G z_k`` on the errors from the
reference (:mod:`rt_ident.control.law`).

Two designs:

* :func:`design_lqr` - the *model* controller: discrete LQR (:func:`dlqr`) on the full
  two-inertia model identified for the axis, weights from a target bandwidth (Bryson's rule:
  the table-angle error, its integral and the torque scaled by what the bandwidth asks of
  them). It feeds back both angles and both velocities, so it sees the flexible mode.
* :func:`design_rigid` - the *conservative* controller: LQR on the rigid body J = I1 + I2 at a
  lower bandwidth, applied as position/integral feedback on the table and velocity feedback
  on the motor (collocated with the torque, so it damps whatever the mode does). With Table 1
  at 10 Hz it stays stable for every corner of each parameter x 0.5 ... x 2.

:func:`loop_margins` breaks the loop at the controller output (before the delay):
``L(z) = G (zI - A_z)^{-1} B_z`` for a plant (the true one, or one of a family), and reads
gain and phase margins from ``1 + L = det(zI - A_cl) / det(zI - A_z)`` on the unit circle
(its crossings bracketed on a grid and refined on L itself: no polynomial roots, which near a
lightly damped mode give crossings that are not there; a crossing at z = -1 counts). The loop
is conditionally stable (a double integrator plus the integral action), so there is a *lower*
gain margin (how much the gain may drop) as well as an upper one; both are checked.

:func:`error_norm` and :func:`reference_error` weigh a design on a plant it was not made for (the
supervisor keeps the design in force where a new one would not pay:
:func:`rt_ident.control.job.keep_design`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from rt_ident.axis.model import state_space
from rt_ident.axis.params import AxisParams
from rt_ident.errors import ConfigError

#: State names of the design model with one tick of delay, in order.
STATE = ("theta1", "omega1", "theta2", "omega2", "u_prev", "xi")
_ANGLE_SCALE = 1e-4  # rad: the table-angle error Bryson's rule normalizes by (0.08 um of table travel)


def _augment(Ad: np.ndarray, Bd: np.ndarray, tick: float, delay: int, pos: int) -> tuple[np.ndarray, np.ndarray]:
    """Append ``delay`` torques in flight and the integral of state ``pos`` to a sampled model."""
    n = Ad.shape[0]
    m = n + delay + 1
    Az = np.zeros((m, m))
    Az[:n, :n] = Ad
    Az[:n, n] = Bd.ravel()                               # x_{k+1} = Ad x_k + Bd u_{k-d}
    for i in range(delay - 1):                           # the shift register of torques in flight
        Az[n + i, n + i + 1] = 1.0
    Az[m - 1, pos] = tick                                # xi_{k+1} = xi_k + T theta2_k
    Az[m - 1, m - 1] = 1.0
    Bz = np.zeros((m, 1))
    Bz[n + delay - 1, 0] = 1.0                           # u_k enters the register
    return Az, Bz


def zoh(A: np.ndarray, B: np.ndarray, tick: float) -> tuple[np.ndarray, np.ndarray]:
    """(A_d, B_d) of ``x' = A x + B u`` under a zero-order hold of ``tick``: the exponential of the
    augmented matrix ``[[A, B], [0, 0]] tick``. python-control's ``c2d(..., "zoh")`` gives the same
    (a test compares them); it is not imported here, since with it come scipy.signal and matplotlib,
    a second of start-up in every control process."""
    n, m = A.shape[0], B.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = scipy.linalg.expm(M * tick)
    return E[:n, :n], E[:n, n:]


def dlqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Discrete LQR gain ``K = (R + B' P B)^-1 B' P A``, ``P`` the stabilizing solution of the discrete
    algebraic Riccati equation (as ``control.dlqr``, which a test compares it with)."""
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


def _check_delay(delay: int) -> int:
    if isinstance(delay, bool) or not isinstance(delay, (int, np.integer)) or not 1 <= delay <= 5:
        raise ConfigError("control.delay_ticks", f"must be an integer 1..5, got {delay!r}")
    return int(delay)


def sampled_model(p: AxisParams, tick: float, delay: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(A_z, B_z) of the design model: Eq. (8) under a ZOH of one tick, the delay and the integral."""
    A, b = state_space(p)                                # Eq. (8), input column +1/I1 (see model.py)
    Ad, Bd = zoh(A, b.reshape(-1, 1), tick)
    return _augment(Ad, Bd, tick, _check_delay(delay), 2)


def _rigid_model(J: float, tick: float, delay: int) -> tuple[np.ndarray, np.ndarray]:
    Ar = np.array([[0.0, 1.0], [0.0, 0.0]])
    Ad, Bd = zoh(Ar, np.array([[0.0], [1.0 / J]]), tick)
    return _augment(Ad, Bd, tick, _check_delay(delay), 0)


def _weights(J: float, bandwidth_hz: float, effort: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Bryson's rule: table-angle error 1e-4 rad, its integral over a third of the bandwidth,
    torque J w^2 1e-4 rad (what the bandwidth needs for that error), scaled by ``effort``."""
    w = 2.0 * math.pi * bandwidth_hz
    q = np.zeros(n)
    q[n - 1] = (w / 3.0 / _ANGLE_SCALE) ** 2             # integral of the error
    R = np.array([[effort / (J * w * w * _ANGLE_SCALE) ** 2]])
    return q, R


def _check_design_inputs(tick: float, bandwidth_hz: float, effort: float) -> None:
    if not (math.isfinite(tick) and tick > 0):
        raise ConfigError("loop.tick_hz", f"tick period must be > 0, got {tick!r}")
    if not (math.isfinite(bandwidth_hz) and 0 < bandwidth_hz < 0.25 / tick):
        raise ConfigError("control.bandwidth_hz",
                          f"must be > 0 and below a quarter of the tick rate ({0.25 / tick:g} Hz), "
                          f"got {bandwidth_hz!r}")
    if not (math.isfinite(effort) and effort > 0):
        raise ConfigError("control.effort", f"must be a finite number > 0, got {effort!r}")


def design_lqr(p: AxisParams, tick: float, bandwidth_hz: float, effort: float = 1.0, delay: int = 1) -> np.ndarray:
    """State-feedback gains G (5 + delay,) from discrete LQR on the two-inertia model ``p``."""
    _check_design_inputs(tick, bandwidth_hz, effort)
    Az, Bz = sampled_model(p, tick, delay)
    q, R = _weights(p.I1 + p.I2, bandwidth_hz, effort, Az.shape[0])
    q[2] = 1.0 / _ANGLE_SCALE**2                         # table angle
    return dlqr(Az, Bz, np.diag(q), R).ravel()


def design_rigid(J: float, tick: float, bandwidth_hz: float, effort: float = 1.0, delay: int = 1) -> np.ndarray:
    """Conservative gains G (5 + delay,): LQR on the rigid body J, position on theta2, velocity on omega1."""
    _check_design_inputs(tick, bandwidth_hz, effort)
    if not (math.isfinite(J) and J > 0):
        raise ConfigError("axis", f"rigid-body inertia must be > 0, got {J!r}")
    Az, Bz = _rigid_model(J, tick, delay)
    q, R = _weights(J, bandwidth_hz, effort, Az.shape[0])
    q[0] = 1.0 / _ANGLE_SCALE**2
    Gr = dlqr(Az, Bz, np.diag(q), R).ravel()             # (theta, omega, u's..., xi)
    return np.concatenate(([0.0, Gr[1], Gr[0], 0.0], Gr[2:]))


@dataclass(frozen=True)
class Margins:
    """Margins of one loop: spectral radius of the closed loop, gain margins (dB; upper > 0,
    lower < 0, +-inf when the Nyquist plot never crosses there) and the smallest phase margin."""

    radius: float
    gm_up_db: float
    gm_down_db: float
    pm_deg: float

    @property
    def stable(self) -> bool:
        return self.radius < 1.0

    def meets(self, gm_db: float, pm_deg: float) -> bool:
        return self.stable and self.gm_up_db >= gm_db and self.gm_down_db <= -gm_db and self.pm_deg >= pm_deg

    def as_dict(self) -> dict[str, float | None]:
        def f(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None
        return {"radius": f(self.radius), "gm_up_db": f(self.gm_up_db), "gm_down_db": f(self.gm_down_db),
                "pm_deg": f(self.pm_deg)}


def delay_of(G: np.ndarray) -> int:
    """The delay (ticks) a gain vector was designed for: 4 states, the torques in flight, xi."""
    return int(np.asarray(G).size) - 5


def loop_gain_view(G: np.ndarray, p: AxisParams, tick: float, n: int = 200) -> dict[str, np.ndarray]:
    """The loop gain of :func:`loop_margins` (broken at the controller output) on a log grid up to
    the tick's Nyquist frequency, for the dashboard: ``f_hz``, ``mag_db``, ``phase_deg``."""
    Az, Bz = sampled_model(p, tick, delay_of(G))
    Gr = np.asarray(G, dtype=float).reshape(1, -1)
    f = np.geomspace(0.1, 0.499 / tick, n)
    z = np.exp(2j * math.pi * f * tick)
    eye = np.eye(Az.shape[0])
    # L(z) = G (zI - Az)^-1 Bz; the loop's sign convention u = -G x makes -L the open-loop gain
    # whose Nyquist plot is checked against -1 (as loop_margins does with L)
    L = np.array([(Gr @ np.linalg.solve(zi * eye - Az, Bz))[0, 0] for zi in z])
    with np.errstate(divide="ignore"):
        mag = 20.0 * np.log10(np.abs(L))
    ph = np.degrees(np.unwrap(np.angle(L)))
    ph -= 360.0 * math.ceil(ph[0] / 360.0)   # the Bode convention: low-frequency phase in (-360, 0]
    return {"f_hz": f, "mag_db": mag, "phase_deg": ph}


def loop_margins(G: np.ndarray, p: AxisParams, tick: float) -> Margins:
    """Margins of the loop G on plant ``p`` (broken at the controller output).

    With ``u = -G x`` the return difference is ``1 + L(z) = det(zI - A_cl) / det(zI - A_z)``
    (the matrix determinant lemma, A_cl = A_z - B_z G), so L on the unit circle is a ratio of
    products over the closed- and the open-loop eigenvalues: no polynomial coefficients, no
    optimizer. Crossings are bracketed on a log grid (densified around each lightly damped pole)
    and refined on L itself; a crossing of the negative real axis at Nyquist (z = -1) counts."""
    Az, Bz = sampled_model(p, tick, delay_of(G))
    Gr = np.asarray(G, dtype=float).reshape(1, -1)
    if not np.all(np.isfinite(Gr)):
        return Margins(math.inf, -math.inf, math.inf, -math.inf)
    mu = np.linalg.eigvals(Az - Bz @ Gr)
    lam = _open_loop_poles(p, tick, delay_of(G))
    radius = float(np.abs(mu).max())
    gm_up, gm_down, pm = _crossing_margins(mu, lam, tick)
    return Margins(radius, gm_up, gm_down, pm)


def _open_loop_poles(p: AxisParams, tick: float, delay: int) -> np.ndarray:
    """The eigenvalues of the design model's A_z, from its structure rather than a numerical
    eigensolver (which returns a triple eigenvalue at 1 or a d-fold one at 0 only to eps^(1/3) and
    eps^(1/d)): ordered (torques in flight, plant, integral) A_z is block lower triangular, so they
    are d zeros (the shift register), exp(T s) of the plant's continuous poles (a double 0: the rigid
    body, 1 after sampling; the flexible pair) and 1 (the integral)."""
    A, _ = state_space(p)
    s = np.linalg.eigvals(A)
    flex = s[np.argsort(-np.abs(s))[:2]]                 # the rigid body's double 0 is the smallest pair
    return np.concatenate([np.zeros(delay), np.ones(3), np.exp(flex * tick)]).astype(complex)


def _return_ratio(mu: np.ndarray, lam: np.ndarray, tick: float) -> Callable[[np.ndarray], np.ndarray]:
    """w [rad/s] -> L(e^{j w T}) = prod(z - mu) / prod(z - lam) - 1."""
    def L(w: np.ndarray) -> np.ndarray:
        z = np.exp(1j * np.asarray(w, dtype=float) * tick)[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.prod((z - mu) / (z - lam), axis=1) - 1.0
    return L


def _grid(lam: np.ndarray, tick: float) -> np.ndarray:
    """A log grid from 1e-6 of Nyquist to Nyquist, densified around each pole near the unit circle."""
    wn = math.pi / tick
    parts = [np.geomspace(wn * 1e-6, wn * (1.0 - 1e-9), 2000)]
    for v in lam:
        ang, r = abs(float(np.angle(v))), float(abs(v))
        if r < 0.5 or not 0.0 < ang < math.pi:
            continue
        width = max(1.0 - r, 1e-5)                      # a pole's half-power width in z ~ its distance to |z| = 1
        parts.append(np.clip(ang + width * np.linspace(-20.0, 20.0, 81), 1e-6 * math.pi, math.pi * (1 - 1e-9))
                     / tick)
    return np.unique(np.concatenate(parts))


def _crossing_margins(mu: np.ndarray, lam: np.ndarray, tick: float) -> tuple[float, float, float]:
    """(upper gain margin dB, lower gain margin dB, smallest |phase margin| deg) of L (see loop_margins)."""
    L = _return_ratio(mu, lam, tick)
    w = _grid(lam, tick)
    v = L(w)
    ok = np.isfinite(v)
    both = ok[:-1] & ok[1:]
    mag, im = np.abs(v) - 1.0, v.imag
    gi = np.flatnonzero(both & (np.sign(mag[:-1]) * np.sign(mag[1:]) < 0))     # |L| crosses 1
    pi_ = np.flatnonzero(both & (np.sign(im[:-1]) * np.sign(im[1:]) < 0))     # L crosses the real axis
    lo = np.concatenate([w[gi], w[pi_]])
    hi = np.concatenate([w[gi + 1], w[pi_ + 1]])
    is_gain = np.arange(lo.size) < gi.size

    def f(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lx = L(x)
        return np.where(is_gain, np.abs(lx) - 1.0, lx.imag), lx

    lx = np.zeros(0, dtype=complex)
    if lo.size:                                          # regula falsi (Illinois), all brackets together
        flo, fhi = f(lo)[0], f(hi)[0]
        x = lo
        for _ in range(_REFINE_STEPS):
            x = hi - fhi * (hi - lo) / (fhi - flo)
            fx, lx = f(x)
            same = np.sign(fx) == np.sign(fhi)
            # the end that stays keeps half its value when the other moves twice in a row (Illinois)
            flo = np.where(same, flo * 0.5, fhi)
            lo = np.where(same, lo, hi)
            hi, fhi = x, fx
    lg, lp = lx[is_gain], lx[~is_gain]
    pms = np.remainder(np.angle(lg, deg=True) + 360.0, 360.0) - 180.0          # 180 + phase, in (-180, 180]
    gms = [1.0 / abs(x) for x in lp if x.real < 0 and abs(x) > 0]
    end = complex(L(np.array([math.pi / tick]))[0])      # z = -1: L is real there
    if math.isfinite(end.real) and end.real < 0:
        gms.append(1.0 / abs(end.real))
    g = np.array(gms, dtype=float)
    up, down = g[g > 1.0], g[g < 1.0]
    gm_up = 20.0 * math.log10(up.min()) if up.size else math.inf
    gm_down = 20.0 * math.log10(down.max()) if down.size else -math.inf
    pm = float(np.abs(pms).min()) if pms.size else math.inf
    return gm_up, gm_down, pm


_REFINE_STEPS = 8   # Illinois steps: a grid bracket (< 1 % of w) to round-off


def error_norm(G: np.ndarray, p: AxisParams, tick: float) -> float:
    """H2 norm of the closed loop ``G`` on ``p`` (:func:`sampled_model`) from
    a torque disturbance at the motor to the table-angle error: how much the loop lets the torques it
    does not know (the probe, friction, a feedforward's error) move the table. inf when unstable."""
    Az, Bz = sampled_model(p, tick, delay_of(G))
    Acl = Az - Bz @ np.asarray(G, dtype=float).reshape(1, -1)
    if not np.abs(np.linalg.eigvals(Acl)).max() < 1.0:
        return math.inf
    bw = Az[:, 4:5].copy()                      # the disturbance enters where the landing torque does
    bw[4:] = 0.0
    # the bilinear method: the direct one (a Kronecker system) is ill-conditioned on these state scales
    W = scipy.linalg.solve_discrete_lyapunov(Acl, bw @ bw.T, method="bilinear")
    return math.sqrt(max(float(W[2, 2]), 0.0))


def reference_error(gains: np.ndarray, model: AxisParams, p: AxisParams) -> float:
    """The share of the torque the reference needs (I1 + I2) alpha that a law built on ``model`` gets
    wrong on the axis ``p`` (rigid body): the inertia feedforward's error, and the motor-angle
    reference's twist I2 alpha / K (:mod:`rt_ident.control.law`) off by I2 alpha |1/K - 1/K'|, which
    the motor-angle gain turns into torque."""
    J = p.I1 + p.I2
    twist = abs(float(gains[0])) * p.I2 * abs(1.0 / model.K - 1.0 / p.K)
    return abs(model.I1 + model.I2 - J) / J + twist / J


@dataclass(frozen=True)
class FamilyCheck:
    """The margin check of one design over a family of plants around an estimate."""

    ok: bool
    reason: str | None
    nominal: Margins
    worst: Margins
    plants: int
    worst_plant: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "plants": self.plants, "nominal": self.nominal.as_dict(),
                "worst": self.worst.as_dict(), "worst_plant": self.worst_plant}


def plant_family(p: AxisParams, factors: tuple[float, ...] = (0.7, 1.3),
                 ci95: dict[str, tuple[float, float]] | None = None) -> list[AxisParams]:
    """``p``, each of I1, I2, B, K alone times each factor, and the corners of the 95 % box."""
    keys = ("I1", "I2", "B", "K")
    base = {k: float(getattr(p, k)) for k in keys}
    out = [p]
    for k in keys:
        for f in factors:
            out.append(AxisParams(**{**base, k: base[k] * f}, lead=p.lead))
    if ci95:
        ranges = []
        for k in keys:
            lo, hi = ci95.get(k, (base[k], base[k]))
            lo, hi = (lo if lo is not None and lo > 0 else base[k]), (hi if hi is not None and hi > 0 else base[k])
            ranges.append((lo, hi))
        for corner in itertools.product(*ranges):
            out.append(AxisParams(**dict(zip(keys, corner)), lead=p.lead))
    return out


def check_family(G: np.ndarray, p: AxisParams, tick: float, *, gm_db: float = 6.0, pm_deg: float = 40.0,
                 factors: tuple[float, ...] = (0.7, 1.3),
                 ci95: dict[str, tuple[float, float]] | None = None) -> FamilyCheck:
    """Accept ``G`` only if it stabilizes ``p`` and every plant of its family with the margins."""
    family = plant_family(p, factors, ci95)
    margins = [loop_margins(G, q, tick) for q in family]
    failing = [(q, m) for q, m in zip(family, margins) if not m.meets(gm_db, pm_deg)]
    reason = None
    if failing:
        q, m = failing[0]
        gm = min(m.gm_up_db, -m.gm_down_db)
        what = ("unstable" if not m.stable else f"gain margin {gm:.1f} dB < {gm_db:g} dB" if gm < gm_db
                else f"phase margin {m.pm_deg:.1f} deg < {pm_deg:g} deg")
        reason = f"{what} on " + ("the estimate" if q is p else
                                  ", ".join(f"{k}={getattr(q, k):.4g}" for k in ("I1", "I2", "B", "K")))
    worst = Margins(max(m.radius for m in margins), min(m.gm_up_db for m in margins),
                    max(m.gm_down_db for m in margins), min(m.pm_deg for m in margins))
    q_worst = (failing[0][0] if failing else
               min(zip(family, margins), key=lambda qm: qm[1].pm_deg)[0])
    return FamilyCheck(reason is None, reason, margins[0], worst, len(family),
                       {k: float(getattr(q_worst, k)) for k in ("I1", "I2", "B", "K")})

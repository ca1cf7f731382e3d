"""The per-tick control law and its bumpless switch (cheap scalar arithmetic only: it runs in the tick).

``u_k = u_ff,k - G (z_k - z_ref,k)`` with the design model's state
``z = [theta1, omega1, theta2, omega2, u_fb,k-d .. u_fb,k-1, xi]`` (:mod:`rt_ident.control.design`):

* the reference is the table position x_ref(t) [m] and its derivatives; in angles
  theta2_ref = x_ref / l, and the motor leads the table by the coupling's twist needed to
  accelerate it, theta1_ref = theta2_ref + I2 alpha_ref / K (Eq. 3, second row, without the
  damping term);
* feedforward u_ff = (I1 + I2) alpha_ref, taken half a tick after the torque lands (the
  middle of the tick it is held over), since the torque computed now is applied one tick later;
* optional friction feedforward (``StateFeedback.friction``, a
  :class:`rt_ident.control.feedforward.FrictionFeedforward`) adds Fv w + Fc sat(w / band)
  at the reference velocity of the same instant;
* the delay states are the feedback torques in flight (the design's ``u_{k-d} .. u_{k-1}``);
* the integral ``xi`` of the table-angle error stops integrating while the torque saturates
  in the direction that would wind it up.

:meth:`StateFeedback.switch` changes the gains (and the model behind the reference and the
feedforward) *bumplessly*: the integral state is re-seeded so that the new law gives the same
feedback torque as the old one at the switching instant, so the torque does not step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from rt_ident.axis.params import AxisParams


@dataclass(frozen=True)
class Controller:
    """One designed controller: gains on the design state and the model behind them."""

    gains: np.ndarray          # (5 + d,) on (theta1, omega1, theta2, omega2, u_{k-d}..u_{k-1}, xi)
    model: AxisParams          # the plant it was designed for (reference twist, feedforward)
    kind: str                  # "conservative" | "model" | "fixed"
    bandwidth_hz: float
    margins: dict | None = None
    loop_view: dict | None = field(default=None, compare=False, repr=False)  # design.loop_gain_view

    @property
    def inertia(self) -> float:
        return self.model.I1 + self.model.I2

    @property
    def gain_margin_db(self) -> float:
        """The smaller of the upper and the lower gain margin of the nominal loop [dB] (nan: unknown)."""
        m = self.margins or {}
        up, down = m.get("gm_up_db"), m.get("gm_down_db")
        vals = [v for v in (up, None if down is None else -down) if v is not None]
        return min(vals) if vals else (math.inf if m else math.nan)


# StateFeedback's per-tick state ``st`` (one float array; the compiled tick of rt_ident.loop.tick_core
# holds a view of it): the integral, the last total torque, its feedforward part, the ticks saturated,
# whether a friction feedforward is on (then only the Python step runs), then the torques in flight
ST_XI, ST_U, ST_UFF, ST_SAT, ST_FRICTION, ST_FLIGHT = range(6)
# ... and its constants ``c``: tick, torque limit, feedforward on, and the model's I1 + I2, I2, K
C_TICK, C_LIMIT, C_FF, C_INERTIA, C_I2, C_K = range(6)


@numba.njit(cache=True)
def tracking_errors(c, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead):
    th2r, w2r, al2r = x_ref / lead, v_ref / lead, a_ref / lead
    th1r = th2r + c[C_I2] * al2r / c[C_K]         # Eq. (3), 2nd row: K (th1 - th2) = I2 th2'' (B term dropped)
    return th1 - th1r, w1 - w2r, th2 - th2r, w2 - w2r


@numba.njit(cache=True)
def feedback_torque(g, st, c, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead):
    """The feedback part of the law at this state (no side effects)."""
    e1, e2, e3, e4 = tracking_errors(c, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
    d = g.shape[0] - 5
    s = 0.0                                        # the torques in flight, oldest first
    for i in range(d):
        s += g[4 + i] * st[ST_FLIGHT + i]
    return -(g[0] * e1 + g[1] * e2 + g[2] * e3 + g[3] * e4 + s + g[4 + d] * st[ST_XI])


@numba.njit(cache=True)
def law_step(g, st, c, th1, w1, th2, w2, x_ref, v_ref, a_ref, a_ff, lead, u_friction):
    """One tick of the law (the Python :meth:`StateFeedback.step` and the compiled tick both run this):
    the torque to apply from the next tick on. ``u_friction``: the friction feedforward's torque (added
    only when ``st[ST_FRICTION]`` is set)."""
    e3 = th2 - x_ref / lead
    u_fb = feedback_torque(g, st, c, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
    u_ff = c[C_INERTIA] * a_ff / lead if c[C_FF] != 0.0 else 0.0
    if st[ST_FRICTION] != 0.0:
        u_ff += u_friction
    u = u_fb + u_ff
    lim = c[C_LIMIT]
    wind = 0.0
    if u > lim:
        u, wind = lim, 1.0
    elif u < -lim:
        u, wind = -lim, -1.0
    if wind == 0.0 or wind * e3 > 0.0:             # xi enters u with -g[-1]: integrate only if it unwinds
        st[ST_XI] += c[C_TICK] * e3                # xi_{k+1} = xi_k + T (theta2 - theta2_ref)
    else:
        st[ST_SAT] += 1.0
    d = g.shape[0] - 5
    for i in range(d - 1):                         # the oldest torque in flight lands; this one joins
        st[ST_FLIGHT + i] = st[ST_FLIGHT + i + 1]
    st[ST_FLIGHT + d - 1] = u - u_ff
    st[ST_UFF] = u_ff
    st[ST_U] = u
    return u


class StateFeedback:
    """Runs a :class:`Controller` every tick; :meth:`switch` swaps it without a torque step.

    Its state lives in two float arrays, changed in place only: ``gains`` and ``st`` (``ST_*``), with
    the constants in ``consts`` (``C_*``); the compiled tick (:mod:`rt_ident.loop.tick_core`) holds
    views of them and runs the same :func:`law_step`.
    """

    def __init__(self, controller: Controller, *, tick: float, torque_limit: float,
                 feedforward: bool = True) -> None:
        self.tick = float(tick)
        self.limit = float(torque_limit)
        self.feedforward = feedforward
        self.controller = controller
        self.gains = np.array(controller.gains, dtype=float)
        self.delay = self.gains.shape[0] - 5
        if self.delay < 1:
            raise ValueError(f"a controller needs at least one tick of delay, its gains have {self.gains.shape[0]}")
        self.st = np.zeros(ST_FLIGHT + self.delay)
        self.consts = np.array([self.tick, self.limit, 1.0 if feedforward else 0.0, controller.inertia,
                                controller.model.I2, controller.model.K])
        self._friction = None

    @property
    def friction(self):
        """FrictionFeedforward or None (rt_ident.control.feedforward)."""
        return self._friction

    @friction.setter
    def friction(self, ff) -> None:
        self._friction = ff
        self.st[ST_FRICTION] = 0.0 if ff is None else 1.0

    @property
    def xi(self) -> float:
        """Integral of the table-angle error [rad s]."""
        return float(self.st[ST_XI])

    @property
    def u(self) -> float:
        """Last total control torque [N m]."""
        return float(self.st[ST_U])

    @property
    def u_ff(self) -> float:
        return float(self.st[ST_UFF])

    @property
    def saturated(self) -> int:
        """Ticks the command hit the limit."""
        return int(self.st[ST_SAT])

    @property
    def in_flight(self) -> list[float]:
        """Feedback torques in flight, oldest first [N m]."""
        return [float(v) for v in self.st[ST_FLIGHT:]]

    def step(self, th1: float, w1: float, th2: float, w2: float, x_ref: float, v_ref: float, a_ref: float,
             a_ff: float, lead: float) -> float:
        """The torque to apply from the next tick on. ``a_ff``: reference acceleration [m/s²] at the
        middle of the tick the torque will be held over."""
        fr = 0.0
        if self._friction is not None:          # velocity at the middle of the tick the torque is held over
            fr = self._friction.torque((v_ref + 0.75 * self.tick * (a_ref + a_ff)) / lead)
        return float(law_step(self.gains, self.st, self.consts, th1, w1, th2, w2, x_ref, v_ref, a_ref, a_ff, lead, fr))

    def switch(self, controller: Controller, th1: float, w1: float, th2: float, w2: float,
               x_ref: float, v_ref: float, a_ref: float, lead: float) -> float:
        """Adopt ``controller``; returns the feedback torque step it would have caused without
        re-seeding (0 after re-seeding, up to round-off)."""
        old = self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        g = np.array(controller.gains, dtype=float)
        if g.shape != self.gains.shape:
            raise ValueError(f"controller for a delay of {g.shape[0] - 5} ticks, the law runs {self.delay}")
        self.controller = controller
        c = self.consts
        c[C_INERTIA], c[C_I2], c[C_K] = controller.inertia, controller.model.I2, controller.model.K
        self.gains[:] = g                              # in place: the compiled tick holds a view
        self._seed_integral(old, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)   # same feedback torque
        return self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead) - old

    def bump(self, controller: Controller, th1: float, w1: float, th2: float, w2: float, x_ref: float,
             v_ref: float, a_ref: float, lead: float) -> float:
        """The feedback torque step switching to ``controller`` would cause without re-seeding the
        integral (what the re-seeded integral would absorb)."""
        c = self.consts.copy()
        c[C_INERTIA], c[C_I2], c[C_K] = controller.inertia, controller.model.I2, controller.model.K
        new = feedback_torque(np.asarray(controller.gains, dtype=float), self.st, c, th1, w1, th2, w2,
                              x_ref, v_ref, a_ref, lead)
        return float(new) - self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)

    def rebase(self, th1: float, w1: float, th2: float, w2: float, x_ref: float, v_ref: float, a_ref: float,
               lead: float, u_fb: float = 0.0) -> None:
        """After the drive dropped the host's torque (a stall outlasted the plan's lease): nothing is in
        flight any more, and the integral is re-seeded so that the feedback torque at this state is
        ``u_fb`` (the torque the drive applies now), so the next torque does not step."""
        self.st[ST_FLIGHT:] = 0.0
        self._seed_integral(u_fb, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)

    def _seed_integral(self, u_fb: float, th1: float, w1: float, th2: float, w2: float, x_ref: float,
                       v_ref: float, a_ref: float, lead: float) -> None:
        """xi such that the feedback torque under the gains in force is ``u_fb`` (unchanged without an
        integral gain or a finite target)."""
        g = self.gains
        e1, e2, e3, e4 = tracking_errors(self.consts, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        rest = g[0] * e1 + g[1] * e2 + g[2] * e3 + g[3] * e4 + _dot(g[4:-1], self.st[ST_FLIGHT:])
        if abs(g[-1]) > 0.0 and math.isfinite(u_fb):
            self.st[ST_XI] = (-u_fb - rest) / g[-1]

    def feedback_torque(self, th1: float, w1: float, th2: float, w2: float, x_ref: float, v_ref: float,
                        a_ref: float, lead: float) -> float:
        """The feedback part of the law at this state (no side effects)."""
        return float(feedback_torque(self.gains, self.st, self.consts, th1, w1, th2, w2, x_ref, v_ref, a_ref, lead))


def _dot(a, b) -> float:
    s = 0.0
    for x, y in zip(a, b):
        s += float(x) * float(y)
    return float(s)

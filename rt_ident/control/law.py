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
  :class:`rt_ident.control.feedforward.FrictionFeedforward`; issue #14) adds Fv w + Fc sat(w / band)
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


class StateFeedback:
    """Runs a :class:`Controller` every tick; :meth:`switch` swaps it without a torque step."""

    def __init__(self, controller: Controller, *, tick: float, torque_limit: float,
                 feedforward: bool = True) -> None:
        self.tick = float(tick)
        self.limit = float(torque_limit)
        self.feedforward = feedforward
        self.controller = controller
        # gains as floats and the torques in flight as a list: the law is a dozen multiply-adds, and on
        # numpy scalars and a 1-element array their per-call overhead was most of its cost in the tick
        self._g = tuple(float(v) for v in np.asarray(controller.gains, dtype=float))
        self.delay = len(self._g) - 5
        self.xi = 0.0               # integral of the table-angle error [rad s]
        self.in_flight = [0.0] * self.delay   # feedback torques in flight, oldest first [N m]
        self.u = 0.0                # last total control torque [N m]
        self.u_ff = 0.0
        self.saturated = 0          # ticks the command hit the limit
        self.friction = None        # FrictionFeedforward or None (rt_ident.control.feedforward)

    def _errors(self, th1: float, w1: float, th2: float, w2: float,
                x_ref: float, v_ref: float, a_ref: float, lead: float) -> tuple[float, float, float, float]:
        m = self.controller.model
        th2r, w2r, al2r = x_ref / lead, v_ref / lead, a_ref / lead
        th1r = th2r + m.I2 * al2r / m.K           # Eq. (3), 2nd row: K (th1 - th2) = I2 th2'' (B term dropped)
        return th1 - th1r, w1 - w2r, th2 - th2r, w2 - w2r

    def step(self, th1: float, w1: float, th2: float, w2: float, x_ref: float, v_ref: float, a_ref: float,
             a_ff: float, lead: float) -> float:
        """The torque to apply from the next tick on. ``a_ff``: reference acceleration [m/s²] at the
        middle of the tick the torque will be held over."""
        e3 = (th2 - x_ref / lead)
        u_fb = self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        u_ff = self.controller.inertia * a_ff / lead if self.feedforward else 0.0
        if self.friction is not None:           # velocity at the middle of the tick the torque is held over
            u_ff += self.friction.torque((v_ref + 0.75 * self.tick * (a_ref + a_ff)) / lead)
        u = u_fb + u_ff
        wind = 0.0
        if u > self.limit:
            u, wind = self.limit, 1.0
        elif u < -self.limit:
            u, wind = -self.limit, -1.0
        if wind == 0.0 or wind * e3 > 0.0:          # xi enters u with -g[-1]: integrate only if it unwinds
            self.xi += self.tick * e3                # xi_{k+1} = xi_k + T (theta2 - theta2_ref)
        else:
            self.saturated += 1
        if self.delay > 1:
            del self.in_flight[0]
            self.in_flight.append(u - u_ff)
        else:
            self.in_flight[-1] = u - u_ff
        self.u_ff = u_ff
        self.u = u
        return u

    def switch(self, controller: Controller, th1: float, w1: float, th2: float, w2: float,
               x_ref: float, v_ref: float, a_ref: float, lead: float) -> float:
        """Adopt ``controller``; returns the feedback torque step it would have caused without
        re-seeding (0 after re-seeding, up to round-off)."""
        old = self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        g = tuple(float(v) for v in np.asarray(controller.gains, dtype=float))
        if len(g) != len(self._g):
            raise ValueError(f"controller for a delay of {len(g) - 5} ticks, the law runs {self.delay}")
        self.controller = controller
        e1, e2, e3, e4 = self._errors(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        rest = g[0] * e1 + g[1] * e2 + g[2] * e3 + g[3] * e4 + _dot(g[4:-1], self.in_flight)
        if abs(g[-1]) > 0.0 and math.isfinite(old):
            self.xi = (-old - rest) / g[-1]          # same feedback torque under the new gains
        self._g = g
        return self.feedback_torque(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead) - old

    def feedback_torque(self, th1: float, w1: float, th2: float, w2: float, x_ref: float, v_ref: float,
                        a_ref: float, lead: float) -> float:
        """The feedback part of the law at this state (no side effects)."""
        g = self._g
        e1, e2, e3, e4 = self._errors(th1, w1, th2, w2, x_ref, v_ref, a_ref, lead)
        return -(g[0] * e1 + g[1] * e2 + g[2] * e3 + g[3] * e4 + _dot(g[4:-1], self.in_flight) + g[-1] * self.xi)


def _dot(a, b) -> float:
    s = 0.0
    for x, y in zip(a, b):
        s += x * y
    return float(s)

"""Host-side safety checks run by the loop every tick, for every backend.

- Position window on the table scale, tripped on the *predicted stopping
  position* x + v|v| / (2 a), not on position alone: a table moving fast toward
  a limit trips while it can still stop inside the window.
- Speed: the table's estimated speed above ``max_speed`` (m/s).
- Watchdog: no fresh feedback (no new samples) for ``watchdog_ticks`` ticks.
- Stuck encoder: samples keep arriving but the motor angle has not changed
  for ``watchdog_ticks`` ticks while torque was commanded.
- Sign: when the speed or the travel limit trips, the last ~20 ms of samples tell whether the motor or
  the table accelerated *against* the commanded torque (:func:`against_torque`). Friction and the
  resonance cannot do that; a wrong torque or encoder sign (a position loop with positive feedback)
  does, and the trip is then reported as what it is: a sign fault naming the settings.
- Command lease (``torque_hold``, applied by the loop when it writes its plan):
  the torque drops to zero that long after the plan ends, before the
  watchdog trips. Without it the drive holds the last planned torque while the
  host is stalled or blind: 0.3 N m held for 100 ms takes the free THOMSON
  table to ~0.7 m/s, and it coasts on far past its window.

Torque clamping happens in :class:`drivers.base.Backend.write` before a
command leaves the host. The monitor raises; the loop turns any raise into a
safe stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import STALE_FEEDBACK_FIX, SignTrip, SpeedTrip, TravelLimitTrip, WatchdogTrip, stuck_encoder_fix

SAFE_STALE, SAFE_STUCK, SAFE_LAST_THETA1 = range(3)


@dataclass(eq=False)     # a monitor is one axis's state: two are never 'equal' (and counters is an array)
class SafetyMonitor:
    lead: float                       # m/rad, x = lead * theta2
    window: tuple[float, float]       # m
    max_decel: float                  # rad/s^2 on theta2 the axis can brake at
    watchdog_ticks: int
    # |torque| above which a motionless motor encoder counts as stuck: 0 for a frictionless axis; an
    # axis with friction legitimately sticks under any torque below its breakaway torque
    stuck_torque: float = 0.0
    # s the last planned torque holds past the end of the loop's plan, then zero (Backend.write's lease);
    # None: held until the next plan, as a bare backend does
    torque_hold: float | None = None
    max_speed: float = math.inf        # m/s of the table
    # the counters (SAFE_*: ticks without samples, ticks with the motor encoder stuck, the last motor
    # angle seen), one array changed in place: the compiled tick (rt_ident.loop.tick_core) holds a view
    counters: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, math.nan]), repr=False)
    inertia: float = 0.0               # nominal I1 + I2 [kg m^2] for the sign check; 0: no sign check

    def __post_init__(self) -> None:
        lo, hi = self.window
        if not lo < hi:
            raise ValueError(f"safety.window: lower bound {lo} must be below upper bound {hi}")

    @property
    def stale_ticks(self) -> int:
        return int(self.counters[SAFE_STALE])

    @stale_ticks.setter
    def stale_ticks(self, value: int) -> None:
        self.counters[SAFE_STALE] = value

    @property
    def stuck_ticks(self) -> int:
        return int(self.counters[SAFE_STUCK])

    @stuck_ticks.setter
    def stuck_ticks(self, value: int) -> None:
        self.counters[SAFE_STUCK] = value

    @property
    def _last_theta1(self) -> float:
        return float(self.counters[SAFE_LAST_THETA1])

    @_last_theta1.setter
    def _last_theta1(self, value: float) -> None:
        self.counters[SAFE_LAST_THETA1] = value

    def sign_check(self, trip: Exception, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray,
                   dt: float) -> SignTrip | None:
        """After a speed or travel trip, the last ~20 ms of samples: when the motor or the table accelerated
        against the commanded torque (see the module docstring), the trip is a sign fault."""
        if not self.inertia > 0:
            return None
        for th, name in ((theta1, "motor"), (theta2, "table")):
            g = against_torque(th, torque, dt, self.inertia)
            if g is not None and g < -0.3:
                return SignTrip(f"the {name} accelerated against the commanded torque ({g:+.2f} x the nominal "
                                f"acceleration per N m) until {trip}: a wrong torque or encoder sign made the position "
                                "loop positive feedback; check backend.torque_sign / motor_encoder_sign / scale_sign "
                                "with rt-ident commission")
        return None

    def stopping_position(self, theta2: float, omega2: float) -> float:
        """x_stop = x + v|v| / (2 a): where the table ends if braking starts now [m]."""
        x = self.lead * theta2
        v = self.lead * omega2
        a = self.lead * self.max_decel
        return x + v * abs(v) / (2.0 * a)

    def check(self, n_samples: int, theta1_last: float, theta2_last: float, omega2_last: float,
              torque_active: bool) -> None:
        """Run every tick after ``read()``; raises a SafetyTrip subclass to stop."""
        if n_samples == 0:
            self.stale_ticks += 1
            if self.stale_ticks >= self.watchdog_ticks:
                raise WatchdogTrip(f"no fresh feedback for {self.stale_ticks} ticks", fix=STALE_FEEDBACK_FIX)
            return
        self.stale_ticks = 0
        if torque_active and theta1_last == self._last_theta1:
            self.stuck_ticks += 1
            if self.stuck_ticks >= self.watchdog_ticks:
                raise WatchdogTrip(f"motor encoder stuck at {theta1_last:.6g} rad for {self.stuck_ticks} ticks "
                                   "while torque was commanded", fix=stuck_encoder_fix("safety.stuck_torque"))
        else:
            self.stuck_ticks = 0
        self._last_theta1 = theta1_last
        lo, hi = self.window
        x = self.lead * theta2_last
        v = self.lead * omega2_last
        if abs(v) > self.max_speed:
            raise SpeedTrip(f"table at {v * 1e3:+.1f} mm/s, faster than safety.max_speed_m_s = "
                            f"{self.max_speed * 1e3:.1f} mm/s (at x={x * 1e3:.3f} mm)")
        x_stop = self.stopping_position(theta2_last, omega2_last)
        if not (lo <= x <= hi) or not (lo <= x_stop <= hi):
            raise TravelLimitTrip(f"table at x={x * 1e3:.3f} mm would stop at {x_stop * 1e3:.3f} mm, outside the "
                                  f"window [{lo * 1e3:.3f}, {hi * 1e3:.3f}] mm")



def against_torque(theta: np.ndarray, torque: np.ndarray, dt: float, inertia: float) -> float | None:
    """The acceleration per N m of ``theta`` under ``torque`` (samples ``dt`` apart), relative to the
    nominal 1 / ``inertia``: g of the least-squares fit theta(t) = c0 + c1 t + g S(t) / inertia, S the
    double integral of the torque. About 1 on a right axis; negative when the axis accelerates against
    the torque. None when the torque's term explains too little of the motion (coasting, noise)."""
    n = theta.shape[0]
    if n < 8:
        return None
    t = np.arange(n) * dt
    s = np.cumsum(np.cumsum(torque)) * dt * dt / inertia
    a = np.column_stack([np.ones(n), t, s])
    scale = np.linalg.norm(a, axis=0)
    if not np.all(scale > 0):
        return None
    coef, *_ = np.linalg.lstsq(a / scale, theta, rcond=None)
    coef = coef / scale
    full = theta - a @ coef
    c_lin, *_ = np.linalg.lstsq(a[:, :2], theta, rcond=None)
    lin = theta - a[:, :2] @ c_lin
    # the torque's term must carry the motion: it removes at least 3/4 of what a straight line leaves
    if not float(full @ full) <= 0.25 * float(lin @ lin):
        return None
    return float(coef[2])

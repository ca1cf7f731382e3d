"""Open-loop probing of an axis with small torque pulses, the host's position controller off.

Each pulse, in one direction: the torque ramps up until the axis moves (the breakaway torque), on to that
torque plus a push sized to reach a quarter of the speed limit in about 40 ms at the nominal inertia (none
when the ramp alone already gave that speed), then a brake: the torque reversed, sized by the push's measured
acceleration to take the speed back over :data:`BRAKE_TICKS` of the host's ticks or more, at the pace it keeps
(a brake ended a tick early or late leaves a small fraction of the speed, whatever the torque's true scale),
until the speed along the push's motion has fallen to a twentieth of its peak by either sensor (before it
reverses), the impulse is back to zero (summed from the torque the device's samples had in force, a lost
sample's from its neighbours'; not when samples were lost while a torque was written: what was in force then
is not known, and the speed alone ends the brake), or the brake has been in force for twice the push's time
(and 3 x BRAKE_TICKS ticks). The brake acts whatever the wiring: it is relative to the command and to the
signs the sensors moved in under the push. Then zero torque.
Every change of torque is a ramp. The push ends early once the table's speed would pass 0.4 x its limit within
four ticks (at the host's own recent pace), or its distance from where the pulse started passes a quarter of
the travel budget; if either limit is passed all the same, the pulse brakes and ends, and the check fails.
Travel past :data:`HARD_STOP` x the budget, whatever the pulse is doing, ends it at zero torque at once.
Distance and speed are taken from both sensors, the scale (x) and the motor encoder (lead x theta1), and the
larger is used: one wrong scaling cannot hide motion. Torque leaves the host as a short plan with a lease, so
a stalled host leaves the axis coasting, not pushed (once the brake has shown its deceleration, its plan holds
it to half the predicted stop instead); the ramp counts only the time its torque was in force, and "no motion"
needs the cap in force for :data:`CAP_HOLD_S` (a late host's lapsed plans are reported as such, not as an axis
that does not move).

From the samples of a pulse: the direction theta1 and x moved in, the ratio dx/dtheta1 (a slope fit),
and 1/J and the friction torque F from theta1(t) = c0 + c1 t + S(t)/J - F t^2 / (2 J), S the double
integral of the commanded torque (a linear least-squares fit over the motion before it reverses).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.base import Backend
from rt_ident.errors import RtIdentError

#: target time to reach the pushing speed (a quarter of the speed limit) at the nominal inertia [s]
PUSH_TIME_S = 0.04
#: the cap in force this long without motion: the axis does not move at the cap [s]
CAP_HOLD_S = 0.05
#: at rest: the drift would not pass the motion thresholds within this time [s]
REST_S = 0.05
#: a pulse whose plans lapsed (see :attr:`Pulse.lapsed`) is run again this many times before the check
#: says the host was late: it did not move the table
LAPSED_RETRIES = 2
#: the brake takes the push's speed back over at least this many host ticks (at the push's own measured
#: acceleration), so that ending it a tick late or early leaves a small fraction of that speed
BRAKE_TICKS = 10
#: travel past this multiple of the budget ends the pulse at zero torque, whatever its phase
HARD_STOP = 1.5
#: a pulse's acceleration fit needs no gap of lost samples longer than this share of its window
FIT_GAP_SHARE = 0.2


@dataclass(frozen=True)
class ProbeLimits:
    travel_m: float            # distance from where the table stood
    max_speed_m_s: float
    torque_cap: float          # N m no pulse exceeds
    lead: float                # m/rad as configured
    inertia: float             # nominal I1 + I2 [kg m^2]
    motion_theta1: float       # rad: theta1 beyond this counts as motion
    motion_x: float            # m: x beyond this counts as motion
    tick_s: float = 1e-3
    no_samples_s: float = 0.2  # this long without a sample: the device is gone


@dataclass
class Pulse:
    direction: int
    t: np.ndarray
    theta1: np.ndarray
    x: np.ndarray
    torque: np.ndarray
    breakaway_nm: float | None = None     # |torque| when the axis first moved
    push_nm: float = 0.0
    aborted: str | None = None            # a limit was passed: why
    max_travel_m: float = 0.0
    max_speed_m_s: float = 0.0
    truth: dict[str, float] = field(default_factory=dict)   # a simulated device's own motion
    drift: tuple[float, float] = (0.0, 0.0)   # (dtheta1/dt, dx/dt) at rest before the pulse
    brake_at: int | None = None               # samples before the brake began (None: it never pushed)
    fault: str | None = None                  # the device stopped during the pulse: why
    fault_cause: str | None = None
    fault_fix: str | None = None
    starved: int = 0                          # samples with a torque commanded but none in force (late plans)
    cap_held_s: float = 0.0                   # time the cap was in force before the pulse gave up moving

    @property
    def lapsed(self) -> bool:
        """It never moved, nor had the cap in force long enough to say the axis does not move (the host's
        plans lapsed), and nothing else stopped it."""
        return (self.breakaway_nm is None and self.cap_held_s < CAP_HOLD_S and not self.aborted
                and not self.fault)

    def _own(self) -> tuple[np.ndarray, np.ndarray]:
        """theta1 and x from the pulse's start, the drift at rest taken out (a table without static
        friction still coasts from the pulse before)."""
        t = self.t - self.t[0]
        return (self.theta1 - self.theta1[0] - self.drift[0] * t, self.x - self.x[0] - self.drift[1] * t)

    def moved(self) -> tuple[float, float]:
        """(theta1, x) when the brake began, from the pulse's start: the motion the command's own
        direction gave (the brake may overshoot it)."""
        if not self.t.size:
            return 0.0, 0.0
        th, x = self._own()
        k = (self.brake_at or th.size) - 1
        return float(th[k]), float(x[k])

    def ratio(self) -> float:
        """dx/dtheta1 over the pulse (a slope fit of x on theta1)."""
        if not self.t.size:
            return math.nan
        th = self.theta1 - self.theta1.mean()
        den = float(th @ th)
        return float(th @ (self.x - self.x.mean()) / den) if den > 0 else math.nan

    def lost(self, sample_period: float) -> int:
        """Samples the device's link lost between the pulse's first and last."""
        if self.t.size < 2:
            return 0
        return int(round((float(self.t[-1]) - float(self.t[0])) / sample_period)) + 1 - int(self.t.size)

    def _window(self, sample_period: float) -> tuple[int, int, int, np.ndarray] | None:
        """(first, end, the way the push moved theta1, sample numbers from the first) of the motion before it
        first reverses; None without one of 8 samples or more."""
        if self.brake_at is None or self.brake_at < 2 or not self.t.size:
            return None
        th = self._own()[0]
        d = int(np.sign(th[self.brake_at - 1])) or 1       # the way the push moved it
        peak = int(np.argmax(d * th))                       # where the brake stopped it (not its overshoot)
        moving = np.flatnonzero(d * th[:peak + 1] > 0)
        if moving.size < 8:
            return None
        i0, i1 = int(moving[0]), peak + 1
        return i0, i1, d, np.rint((self.t[i0:i1] - self.t[i0]) / sample_period).astype(np.int64)

    def gapped(self, sample_period: float) -> bool:
        """The motion's window has a gap of lost samples over :data:`FIT_GAP_SHARE` of its span."""
        w = self._window(sample_period)
        return w is not None and _too_gapped(w[3])

    def dynamics(self, sample_period: float) -> tuple[float, float]:
        """(1/J [rad/s^2 per N m], F [N m]) from theta1 over the motion before it first reverses.

        On the samples' own times: a lost sample's torque is interpolated between its neighbours' (the host's
        plan was in force), so the double integral runs on every sample period. A :meth:`gapped` window has
        lost the motion's shape: no fit (NaN)."""
        w = self._window(sample_period)
        if w is None or _too_gapped(w[3]):
            return math.nan, math.nan
        i0, i1, d, k = w
        th = self._own()[0][i0:i1]
        every = np.arange(k[-1] + 1)
        s = (np.cumsum(np.cumsum(np.interp(every, k, self.torque[i0:i1]))) * sample_period ** 2)[k]
        t = k * sample_period
        a = np.column_stack([np.ones_like(t), t, s, -0.5 * d * t ** 2])
        scale = np.linalg.norm(a, axis=0)
        scale[scale == 0] = 1.0
        coef, *_ = np.linalg.lstsq(a / scale, th, rcond=None)   # columns of like size: none cut off
        coef = coef / scale
        inv_j = float(coef[2])
        return inv_j, float(coef[3] / inv_j) if inv_j else math.nan


def _too_gapped(k: np.ndarray) -> bool:
    """Sample numbers ``k`` (from 0) with one gap over :data:`FIT_GAP_SHARE` of their span, or no span."""
    return bool(k[-1] <= 0 or float(np.max(np.diff(k))) > FIT_GAP_SHARE * float(k[-1]))


def fault_of(exc: Exception) -> tuple[str, str, str | None]:
    """What a device's stop says: its message, its cause tag and the setting that fixes it (if one does)."""
    return str(exc), getattr(exc, "cause", "device"), getattr(exc, "fix", None)


def _slope(t: np.ndarray, y: np.ndarray) -> float:
    if t.size < 3:
        return 0.0
    tc = t - t.mean()
    den = float(tc @ tc)
    return float(tc @ (y - y.mean()) / den) if den > 0 else 0.0


def _impulse(seq: np.ndarray, torque: np.ndarray, before: tuple[int, float] | None) -> float:
    """The sum of the torque in force over the samples up to ``seq[-1]`` from the one after ``before`` (seq,
    torque of the last sample read), in sample periods: a lost sample's torque halfway between its
    neighbours' (the host's plan was in force)."""
    total = float(np.sum(torque))
    if before is None:
        return total
    s = np.concatenate([[before[0]], seq])
    tq = np.concatenate([[before[1]], torque])
    gaps = np.diff(s) - 1
    return total + float(np.sum(gaps * 0.5 * (tq[1:] + tq[:-1])))


def _brake_nm(push_nm: float, peak: float, push_dur: float, tick_s: float) -> float:
    """A brake that takes ``peak`` back in BRAKE_TICKS host ticks of ``tick_s`` at the push's mean
    acceleration (friction, not counted, only shortens it), never stronger than the push."""
    a_push = peak / max(push_dur, tick_s)
    return push_nm * min(1.0, peak / (BRAKE_TICKS * tick_s) / a_push) if a_push > 0 else push_nm


class Prober:
    """Runs pulses on an active backend (see the module docstring)."""

    def __init__(self, backend: Backend, limits: ProbeLimits) -> None:
        self.b = backend
        self.lim = limits
        dt = backend.sample_period
        # a torque outlives the host's last write by ~1.5 ticks at most: a stalled host cannot push the axis
        # past the speed limit (at 10 x the nominal acceleration the push gains < 0.3 x the limit in that time)
        self.plan_len = int(math.ceil(limits.tick_s / dt)) + 2
        self.lease = max(1, int(math.ceil(0.5 * limits.tick_s / dt)))
        self.next_seq = 0
        self.start: tuple[float, float] | None = None     # (theta1, x) where the table stood
        self.max_travel = 0.0
        self.max_speed = 0.0
        self._clock = time.perf_counter
        self._tx0: float | None = None      # a simulated device's true table position at the start
        self.drift = (0.0, 0.0)     # (dtheta1/dt, dx/dt) at the end of the last rest

    def _travel(self, theta1: float, x: float) -> float:
        """Distance [m] from where the table stood, by the sensor that says it is further (``x`` in m)."""
        assert self.start is not None
        th0, x0 = self.start
        return max(abs(x - x0), abs(self.lim.lead * (theta1 - th0)))

    @property
    def past_hard_stop(self) -> bool:
        """The table has been past :data:`HARD_STOP` x the travel budget."""
        return self.max_travel > HARD_STOP * self.lim.travel_m

    def _read(self) -> Any:
        blk = self.b.read()
        if len(blk):
            self.next_seq = int(blk.seq[-1]) + 1
        return blk

    def _write(self, torque: float, until: int | None = None) -> None:
        """``torque`` from the next sample on, for the plan and its lease; with ``until``, for that many
        samples and then zero, whether or not the host writes again."""
        if until is None:
            self.b.write(np.full(self.plan_len, torque), start_seq=self.next_seq, lease=self.lease)
            return
        plan = np.zeros(max(self.plan_len, until + 1))
        plan[:until] = torque
        self.b.write(plan, start_seq=self.next_seq, lease=0)

    def settle(self, seconds: float) -> None:
        """Zero torque for ``seconds``, measuring the drift; the first call fixes where the table stands."""
        end = self._clock() + seconds
        stale = 0
        got: list[Any] = []
        while self._clock() < end:
            blk = self._read()
            if len(blk):
                got.append(blk)
            stale = 0 if len(blk) else stale + 1
            if stale * self.lim.tick_s > self.lim.no_samples_s:
                raise ProbeError(f"no samples from the device for {self.lim.no_samples_s:g} s", "backend")
            if len(blk) and self.start is None:
                self.start = (float(blk.theta1[0]), self.lim.lead * float(blk.theta2[0]))
                plant, true = getattr(self.b, "plant", None), getattr(self.b, "true_params", None)
                if plant is not None and true is not None:     # a simulated device: its own truth
                    self._tx0 = true.lead * float(plant.state[2])
            self._write(0.0)
            if len(blk):
                self.max_travel = max(self.max_travel, self._travel(float(blk.theta1[-1]),
                                                                    self.lim.lead * float(blk.theta2[-1])))
                if self.past_hard_stop:
                    return                       # moving at zero torque: the pulse says so (Prober.pulse)
            time.sleep(self.lim.tick_s)
        if got:      # the drift at rest (a table without static friction coasts on): motion is measured from it
            t = np.concatenate([g.seq for g in got]) * self.b.sample_period
            half = t.size // 2
            th, x = np.concatenate([g.theta1 for g in got]), self.lim.lead * np.concatenate([g.theta2 for g in got])
            self.drift = (_slope(t[half:], th[half:]), _slope(t[half:], x[half:]))

    def pulse(self, direction: int) -> Pulse:
        lim = self.lim
        out = Pulse(direction, *(np.empty(0),) * 4)
        try:
            # at rest before the pulse: a table still coasting from the last one (friction slowing it, which
            # the drift line does not follow) would read as motion at zero torque
            self.settle(0.1)
            for _ in range(9):
                if abs(self.drift[0]) * REST_S <= lim.motion_theta1 and abs(self.drift[1]) * REST_S <= lim.motion_x \
                        or self.past_hard_stop:
                    break
                self.settle(0.1)
        except RtIdentError as exc:
            out.fault, out.fault_cause, out.fault_fix = fault_of(exc)
            return out
        if self.past_hard_stop:
            out.aborted = (f"the table moved {self.max_travel * 1e3:.3f} mm from where it stood, at zero torque "
                           f"({self.drift[1] * 1e3:+.2f} mm/s at rest): a load or gravity pulls it?")
            out.max_travel_m, out.max_speed_m_s = self.max_travel, self.max_speed
            return out
        ts: list[np.ndarray] = []
        th1s: list[np.ndarray] = []
        xs: list[np.ndarray] = []
        tqs: list[np.ndarray] = []
        # the cap in 0.4 s of torque in force (a late host's lapsed plans do not count): slow enough to find
        # the breakaway
        ramp = lim.torque_cap / 400.0
        slew = ramp * 5.0
        push_target = min(lim.torque_cap, lim.inertia * 0.25 * lim.max_speed_m_s / lim.lead / PUSH_TIME_S)
        out.drift = self.drift
        deadline = self._clock() + 5.0
        try:
            self._pulse_loop(direction, out, ts, th1s, xs, tqs, push_target, ramp, slew, deadline)
        except RtIdentError as exc:            # the device stopped itself: what it did until then still counts
            out.fault, out.fault_cause, out.fault_fix = fault_of(exc)
        if ts:
            out.t, out.theta1, out.x, out.torque = (np.concatenate(a) for a in (ts, th1s, xs, tqs))
        out.max_travel_m, out.max_speed_m_s = self.max_travel, self.max_speed
        return out

    @staticmethod
    def _along(t: np.ndarray, theta1: np.ndarray, x: np.ndarray) -> tuple[int, int]:
        """The signs theta1 and x are moving in (whatever the wiring)."""
        return int(np.sign(_slope(t, theta1))) or 1, int(np.sign(_slope(t, x))) or 1

    def _pulse_loop(self, direction: int, out: Pulse, ts: list, th1s: list, xs: list, tqs: list,
                    push_target: float, ramp: float, slew: float, deadline: float) -> None:
        lim, b = self.lim, self.b
        phase, torque, target = "ramp", 0.0, 0.0
        ramp_per_s = ramp / lim.tick_s
        applied_s = 0.0                     # time with the ramp's torque in force
        t_push = push_dur = peak = impulse = brake_s = 0.0
        last_in_force: tuple[int, float] | None = None      # (seq, torque) of the last sample read
        unseen = False                         # the push's impulse is not known (see below)
        brake_tick = lim.tick_s
        along = (0, 0)                         # the signs theta1 and x moved in under the push
        braked: list[tuple[float, float]] = []   # (device time, speed along) with the brake in force
        brake_n: int | None = None             # samples the brake holds on its own (None: a plan and lease)
        t_written = t_looked = self._clock()
        pace = lim.tick_s
        rest = 0
        stale = 0
        p_th0: float | None = None
        p_x0 = p_t0 = 0.0
        def brake(dur: float) -> tuple[float, float, tuple[int, int], float, float, int]:
            """(push time, peak speed, signs moved in, the host's pace, brake torque, samples before it): the
            brake takes ``speed`` back over BRAKE_TICKS of the host's pace."""
            along_ = self._along(tw, thw, xw)
            return (dur, speed, along_, pace, -direction * _brake_nm(out.push_nm, speed, dur, pace),
                    sum(a.size for a in ts))

        while True:
            now = self._clock()
            # the host's own pace (a write that blocks counts): a late host looks further ahead (its next
            # write may come that late) and brakes over more of its ticks
            pace, t_looked = max(lim.tick_s, 0.8 * pace, now - t_looked), now
            if now > deadline:
                out.aborted = "; ".join(filter(None, (out.aborted, "the pulse did not end within 5 s")))
                break
            blk = self._read()
            if not len(blk):
                stale += 1
                if stale * lim.tick_s > lim.no_samples_s:
                    self._write(0.0)
                    raise ProbeError(f"no samples from the device for {lim.no_samples_s:g} s", "backend")
            else:
                stale = 0
                th1, x = blk.theta1, lim.lead * blk.theta2
                if p_th0 is None:
                    p_t0, p_th0, p_x0 = float(blk.seq[0]) * b.sample_period, float(th1[0]), float(x[0])
                # the drift at rest, from the pulse's first sample (not carried over a late host's gap since
                # the rest: a small error in its speed would grow into motion over it)
                dt_d = float(blk.seq[-1]) * b.sample_period - p_t0
                drift_th, drift_x = p_th0 + self.drift[0] * dt_d, p_x0 + self.drift[1] * dt_d
                ts.append(blk.seq * b.sample_period)
                th1s.append(th1)
                xs.append(x)
                tqs.append(blk.torque_cmd)
                travel = self._travel(float(th1[-1]), float(x[-1]))
                tw = ts[-1] if ts[-1].size >= 4 or len(ts) < 2 else np.concatenate(ts[-3:])
                xw = xs[-1] if xs[-1].size >= 4 or len(xs) < 2 else np.concatenate(xs[-3:])
                thw = th1s[-1] if th1s[-1].size >= 4 or len(th1s) < 2 else np.concatenate(th1s[-3:])
                speed = max(abs(_slope(tw, xw)), abs(lim.lead * _slope(tw, thw)))
                self.max_travel = max(self.max_travel, travel)
                self.max_speed = max(self.max_speed, speed)
                if self._tx0 is not None:
                    st = b.plant.state      # type: ignore[attr-defined]
                    lead = getattr(b, "true_params").lead      # noqa: B009 - a simulated device only
                    out.truth["max_travel_m"] = max(out.truth.get("max_travel_m", 0.0),
                                                    abs(lead * float(st[2]) - self._tx0))
                    out.truth["max_speed_m_s"] = max(out.truth.get("max_speed_m_s", 0.0),
                                                     abs(lead * float(st[3])))
                if travel > HARD_STOP * lim.travel_m:
                    # past the travel budget by half again with the brake or the rest in force: the pulse no
                    # longer governs the table; no more torque, the stage ends (the backend's stop disables)
                    self._write(0.0)
                    out.aborted = "; ".join(filter(None, (out.aborted or "travel limit passed", (
                        f"stopped at {travel * 1e3:.3f} mm ({HARD_STOP:g} x commission.travel_m), "
                        f"{speed * 1e3:.2f} mm/s"))))
                    break
                if (travel > lim.travel_m or speed > lim.max_speed_m_s) and out.aborted is None:
                    out.aborted = (f"{'travel' if travel > lim.travel_m else 'speed'} limit passed "
                                   f"({travel * 1e3:.3f} mm, {speed * 1e3:.2f} mm/s)")
                    if phase == "push":                 # brake what the push gave, as a pulse ends
                        push_dur, peak, along, brake_tick, target, out.brake_at = brake(now - t_push)
                        phase = "brake"
                    elif phase == "ramp":
                        phase, target = "rest", 0.0
                moved = (abs(float(th1[-1]) - drift_th) > lim.motion_theta1
                         or abs(float(x[-1]) - drift_x) > lim.motion_x)
                pulse_travel = max(abs(float(x[-1]) - p_x0), abs(lim.lead * (float(th1[-1]) - p_th0)))
                # samples that carried the torque last written (a lapsed plan leaves none in force)
                carried = np.abs(blk.torque_cmd) >= 0.5 * abs(torque) if torque != 0.0 else np.ones(len(blk), bool)
                out.starved += int(np.count_nonzero(~carried))
                if phase != "brake" and torque != 0.0 and last_in_force is not None and \
                        int(blk.seq[-1]) - last_in_force[0] > len(blk):
                    unseen = True      # samples lost with a torque written: what was in force is not known
                impulse += _impulse(blk.seq, blk.torque_cmd, last_in_force) * b.sample_period
                last_in_force = (int(blk.seq[-1]), float(blk.torque_cmd[-1]))
                if phase == "ramp":
                    applied_s += float(np.count_nonzero(carried)) * b.sample_period
                    if abs(torque) >= lim.torque_cap:
                        out.cap_held_s += float(np.count_nonzero(carried)) * b.sample_period
                    moved = moved and torque != 0.0          # at zero torque it is the drift's, not the pulse's
                    if moved and speed >= 0.25 * lim.max_speed_m_s:
                        # the ramp alone gave the push's speed (more torque than told, or a late host saw the
                        # motion late): no push, the brake at once
                        out.breakaway_nm = out.push_nm = abs(torque)
                        push_dur, peak, along, brake_tick, target, out.brake_at = brake(max(applied_s, lim.tick_s))
                        phase = "brake"
                    elif moved:
                        out.breakaway_nm = abs(torque)
                        out.push_nm = min(lim.torque_cap, abs(torque) + push_target)   # friction + the push
                        phase, target, t_push = "push", direction * out.push_nm, now
                    elif out.cap_held_s >= CAP_HOLD_S:
                        phase, target = "rest", 0.0
                elif phase == "push":
                    accel = abs(_slope(tw, np.gradient(xw, tw))) if tw.size >= 4 else 0.0
                    if (speed + 4 * pace * accel >= 0.4 * lim.max_speed_m_s
                            or pulse_travel >= 0.25 * lim.travel_m or now - t_push > 0.3):
                        push_dur, peak, along, brake_tick, target, out.brake_at = brake(now - t_push)
                        phase = "brake"
                elif phase == "brake":
                    peak = max(peak, speed)
                    # the speed along the push's motion, by the sensor that says it has fallen furthest: the
                    # brake ends where either sees the motion end, before it reverses it
                    v = min(along[0] * lim.lead * _slope(tw, thw), along[1] * _slope(tw, xw))
                    t_dev = float(tw[-1])
                    if direction * torque < 0.0:
                        brake_s += float(np.count_nonzero(carried)) * b.sample_period
                    if direction * torque < 0.0 and torque == target and bool(carried.all()):
                        braked.append((t_dev, v))
                    bt = np.array([t for t, _ in braked])
                    if bt.size >= 4 and bt[-1] - bt[0] >= 3 * lim.tick_s:
                        # the deceleration the brake has shown (a line through its speeds): the device brakes
                        # on to half the predicted stop (less the speed window's lag) should the host come
                        # late - a host back late brakes the rest, a reversal nothing would take back
                        decel = -_slope(bt, np.array([u for _, u in braked]))
                        if decel > 0.0:
                            stop = v / decel - 0.5 * float(tw[-1] - tw[0])
                            brake_n = max(self.plan_len, int(0.5 * stop / b.sample_period))
                    # the commanded impulse back to zero: the momentum the pulse gave, taken back
                    if ((direction * impulse <= 0.0 and not unseen) or v <= 0.05 * peak or speed < 0.05 * peak
                            or brake_s >= max(2.0 * push_dur, 3 * BRAKE_TICKS * brake_tick)):
                        phase, target = "rest", 0.0
            if phase == "ramp":
                target = direction * min(lim.torque_cap, ramp_per_s * applied_s)
            # the ramp rises with time (a late tick takes a larger, still small, step), never past its target
            step = slew if phase != "ramp" else min(5.0 * ramp, max(ramp, ramp_per_s * (now - t_written)))
            if phase == "brake" and not unseen:      # no overshoot of the impulse on the way back
                step = min(step, max(abs(impulse) / lim.tick_s, 0.0) + abs(torque))
            torque = torque + max(-step, min(step, target - torque))
            self._write(torque, brake_n if phase == "brake" and direction * torque < 0.0 else None)
            t_written = self._clock()
            if phase == "rest" and torque == 0.0:
                rest += 1
                if rest >= 50:
                    break
            time.sleep(lim.tick_s)

class ProbeError(RtIdentError):
    """The probe could not go on (no samples): the message, and the config key that may fix it."""

    def __init__(self, message: str, key: str) -> None:
        super().__init__(message)
        self.key = key

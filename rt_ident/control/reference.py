"""Reference trajectories of the table position x(t) [m], with velocity and acceleration.

Pure numerics: each reference is a frozen dataclass with ``at(t) -> (x, v, a)`` for an array of
times [s] and ``point(t) -> (x, v, a)`` for one time, in plain floats. The loop evaluates it at the
sample time of the newest sample (and half a tick after the torque lands, for the feedforward)
with ``point``: on two times numpy's per-call overhead makes ``at`` ~20 us of the tick, ``point``
costs 1-2 us. Both give the same numbers (a test checks them against each other).

* :class:`Hold` - stay at one position;
* :class:`Moves` - jerk-limited point-to-point moves (the 7-segment S-curve: jerk +-j_max,
  acceleration up to a_max, velocity up to v_max; short moves reach neither and the profile
  shrinks accordingly), with a dwell at each position, visited in turn and optionally repeated;
* :class:`Sine` - a sine with a raised-cosine fade-in, so it starts with zero velocity;
* :class:`CsvTrajectory` - ``t,x`` samples from a file, through a cubic spline (x, v, a
  continuous; v and a are the spline's derivatives).

:func:`make_reference` builds one from the ``[reference]`` table of a run configuration.
"""

from __future__ import annotations

import bisect
import csv
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rt_ident.errors import ConfigError, validation_error

Triple = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Hold:
    position: float = 0.0

    duration = math.inf

    def at(self, t: np.ndarray) -> Triple:
        t = np.asarray(t, dtype=float)
        return np.full(t.shape, self.position), np.zeros(t.shape), np.zeros(t.shape)

    def point(self, t: float) -> tuple[float, float, float]:
        return float(self.position), 0.0, 0.0


def ramp_times(v: float, a_max: float, j_max: float) -> tuple[float, float]:
    """(jerk time, total time) of a jerk-limited change of velocity by ``v`` >= 0 from rest acceleration
    to rest acceleration (trapezoidal acceleration, triangular when a_max is not reached)."""
    if v * j_max < a_max * a_max:
        tj = math.sqrt(v / j_max)
        return tj, 2.0 * tj
    tj = a_max / j_max
    return tj, v / a_max + tj


def velocity_change(dv: float, a_max: float, j_max: float) -> list[tuple[float, float]]:
    """(duration, jerk) segments that change the velocity by ``dv`` (either sign) within the limits,
    starting and ending with zero acceleration."""
    tj, ta = ramp_times(abs(dv), a_max, j_max)
    j = j_max if dv > 0 else -j_max
    return [s for s in ((tj, j), (ta - 2.0 * tj, 0.0), (tj, -j)) if s[0] > 0.0]


def s_curve(distance: float, v_max: float, a_max: float, j_max: float) -> list[tuple[float, float]]:
    """(duration, jerk) segments of a rest-to-rest move over ``distance`` > 0 within the limits."""

    def accel_time(v: float) -> tuple[float, float]:         # (jerk time, total accel time) to reach v
        return ramp_times(v, a_max, j_max)

    v = v_max
    tj, ta = accel_time(v)
    if v * ta > distance:                                    # v_max not reached: largest v that fits
        lo, hi = 0.0, v_max
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            if mid * accel_time(mid)[1] > distance:
                hi = mid
            else:
                lo = mid
        v = lo
        tj, ta = accel_time(v)
    cruise = max(0.0, (distance - v * ta) / v) if v > 0 else 0.0
    flat = max(0.0, ta - 2.0 * tj)
    acc = [(tj, j_max), (flat, 0.0), (tj, -j_max)]
    dec = [(tj, -j_max), (flat, 0.0), (tj, j_max)]
    return [s for s in acc + [(cruise, 0.0)] + dec if s[0] > 0.0]


@dataclass(frozen=True)
class Segments:
    """Piecewise-cubic x(t) from (start time, jerk, a0, v0, x0) per segment."""

    t0: np.ndarray
    j: np.ndarray
    a0: np.ndarray
    v0: np.ndarray
    x0: np.ndarray
    # the same as floats, for point() (set by __post_init__)
    _rows: list[tuple[float, ...]] = field(init=False, repr=False, compare=False)
    _starts: list[float] = field(init=False, repr=False, compare=False)

    @classmethod
    def build(cls, x_start: float, segments: list[tuple[float, float]], t_start: float = 0.0,
              v_start: float = 0.0) -> Segments:
        t, x, v, a = t_start, x_start, v_start, 0.0
        rows = []
        for dur, jerk in segments:
            rows.append((t, jerk, a, v, x))
            x += v * dur + a * dur**2 / 2 + jerk * dur**3 / 6
            v += a * dur + jerk * dur**2 / 2
            a += jerk * dur
            t += dur
        rows.append((t, 0.0, 0.0, 0.0, x))                   # rest at the end (a and v are 0 by design)
        arr = np.array(rows, dtype=float)
        return cls(*(arr[:, i].copy() for i in range(5)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "_rows", [tuple(float(c) for c in r) for r in
                                           zip(self.t0, self.j, self.a0, self.v0, self.x0)])
        object.__setattr__(self, "_starts", [float(c) for c in self.t0])

    @property
    def end(self) -> float:
        return float(self.t0[-1])

    def at(self, t: np.ndarray) -> Triple:
        i = np.clip(np.searchsorted(self.t0, t, side="right") - 1, 0, len(self.t0) - 1)
        tau = np.where(t >= self.t0[0], t - self.t0[i], 0.0)
        j, a0, v0, x0 = self.j[i], self.a0[i], self.v0[i], self.x0[i]
        x = x0 + v0 * tau + a0 * tau**2 / 2 + j * tau**3 / 6
        v = v0 + a0 * tau + j * tau**2 / 2
        a = a0 + j * tau
        return x, v, a

    def point(self, t: float) -> tuple[float, float, float]:
        """:meth:`at` for one time, in floats."""
        starts = self._starts
        i = min(max(bisect.bisect_right(starts, t) - 1, 0), len(starts) - 1)
        t0, j, a0, v0, x0 = self._rows[i]
        tau = t - t0 if t >= starts[0] else 0.0
        return (x0 + v0 * tau + a0 * tau**2 / 2 + j * tau**3 / 6, v0 + a0 * tau + j * tau**2 / 2,
                a0 + j * tau)


@dataclass(frozen=True)
class Moves:
    """Jerk-limited moves through ``positions`` (m), ``dwell`` s at each, from ``start`` s on."""

    positions: tuple[float, ...]
    v_max: float
    a_max: float
    j_max: float
    dwell: float = 0.2
    start: float = 0.0
    repeat: bool = True
    _cycle: Segments = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.positions) < 1:
            raise ConfigError("reference.positions", "needs at least one position")
        for name in ("v_max", "a_max", "j_max"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"reference.{name}", f"must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.dwell) and self.dwell >= 0 and math.isfinite(self.start) and self.start >= 0):
            raise ConfigError("reference.dwell", "dwell and start must be finite numbers >= 0")
        pos = list(self.positions) + ([self.positions[0]] if self.repeat and len(self.positions) > 1 else [])
        segs: list[tuple[float, float]] = [(self.dwell, 0.0)] if self.dwell > 0 else []
        x = pos[0]
        signed = []
        for target in pos[1:]:
            d = target - x
            if d != 0.0:
                for dur, jerk in s_curve(abs(d), self.v_max, self.a_max, self.j_max):
                    signed.append((dur, jerk if d > 0 else -jerk))
                segs += signed
                signed = []
            if self.dwell > 0:
                segs.append((self.dwell, 0.0))
            x = target
        object.__setattr__(self, "_cycle", Segments.build(pos[0], segs))

    @property
    def cycle(self) -> float:
        return self._cycle.end

    @property
    def duration(self) -> float:
        return math.inf if self.repeat else self.start + self.cycle

    def at(self, t: np.ndarray) -> Triple:
        t = np.asarray(t, dtype=float) - self.start
        if self.repeat and len(self.positions) > 1 and self.cycle > 0:
            t = np.where(t > 0, np.mod(t, self.cycle), t)
        return self._cycle.at(t)

    def point(self, t: float) -> tuple[float, float, float]:
        t = float(t) - self.start
        if self.repeat and len(self.positions) > 1 and self.cycle > 0 and t > 0:
            t = math.fmod(t, self.cycle)
        return self._cycle.point(t)


@dataclass(frozen=True)
class Sine:
    """``offset + amplitude * w(t) * sin(2 pi f (t - start))``; w rises as a raised cosine over
    ``fade_periods`` periods, so position, velocity and acceleration all start continuous."""

    amplitude: float
    frequency_hz: float
    offset: float = 0.0
    start: float = 0.0
    fade_periods: float = 2.0

    duration = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise ConfigError("reference.frequency_hz", f"must be > 0, got {self.frequency_hz!r}")
        if not math.isfinite(self.amplitude):
            raise ConfigError("reference.amplitude", f"must be finite, got {self.amplitude!r}")

    def at(self, t: np.ndarray) -> Triple:
        t = np.asarray(t, dtype=float) - self.start
        w = 2 * math.pi * self.frequency_hz
        tf = max(self.fade_periods / self.frequency_hz, 1e-12)
        on = t > 0
        u = np.clip(t / tf, 0.0, 1.0)
        # raised cosine fade and its derivatives (zero at both ends)
        f = np.where(u < 1, 0.5 - 0.5 * np.cos(math.pi * u), 1.0)
        df = np.where(u < 1, 0.5 * math.pi / tf * np.sin(math.pi * u), 0.0)
        ddf = np.where(u < 1, 0.5 * (math.pi / tf) ** 2 * np.cos(math.pi * u), 0.0)
        s, c = np.sin(w * t), np.cos(w * t)
        A = self.amplitude
        x = self.offset + np.where(on, A * f * s, 0.0)
        v = np.where(on, A * (df * s + f * w * c), 0.0)
        a = np.where(on, A * (ddf * s + 2 * df * w * c - f * w * w * s), 0.0)
        return x, v, a

    def point(self, t: float) -> tuple[float, float, float]:
        t = float(t) - self.start
        if not t > 0:
            return float(self.offset), 0.0, 0.0
        w = 2 * math.pi * self.frequency_hz
        tf = max(self.fade_periods / self.frequency_hz, 1e-12)
        u = min(t / tf, 1.0)
        if u < 1:
            f, df, ddf = (0.5 - 0.5 * math.cos(math.pi * u), 0.5 * math.pi / tf * math.sin(math.pi * u),
                          0.5 * (math.pi / tf) ** 2 * math.cos(math.pi * u))
        else:
            f, df, ddf = 1.0, 0.0, 0.0
        s, c = math.sin(w * t), math.cos(w * t)
        A = self.amplitude
        return self.offset + A * f * s, A * (df * s + f * w * c), A * (ddf * s + 2 * df * w * c - f * w * w * s)


@dataclass(frozen=True)
class Circle:
    """One axis's share of a circular test (ISO 230-4): the table goes round a circle of ``radius``
    counter-clockwise ``turns`` times at the feed ``2 pi radius frequency_hz``, dwells ``dwell`` s, then
    clockwise back. As ISO 230-4 asks, the turns measured are at constant feed: the angular speed rises
    on a start overshoot arc before them and falls on a stop overshoot arc after them, each half a turn
    (180 degrees) of raised-cosine ramp over ``1 / frequency_hz`` s (position, velocity and acceleration
    continuous). :meth:`measured` gives the constant-feed windows the figures are taken over,
    :meth:`windows` the whole motion of each direction. The circle starts and ends at the origin, its
    centre at (0, -radius): X = -R sin(phi), Y = R (cos(phi) - 1). Give the same numbers to ``[axes.x]``
    (``axis = "x"``) and ``[axes.y]`` (``axis = "y"``)."""

    radius: float
    frequency_hz: float
    axis: str = "x"
    turns: float = 1.0
    start: float = 0.5
    dwell: float = 0.2

    duration = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ConfigError("reference.radius", f"must be > 0, got {self.radius!r}")
        if not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise ConfigError("reference.frequency_hz", f"must be > 0, got {self.frequency_hz!r}")
        if self.turns < 1.0:
            raise ConfigError("reference.turns", f"must be >= 1 (ISO 230-4 measures a full turn), got {self.turns!r}")
        if self.axis not in ("x", "y"):
            raise ConfigError("reference.axis", f"must be 'x' or 'y', got {self.axis!r}")

    @property
    def _times(self) -> tuple[float, float, float]:
        """(ramp time, constant-speed time, one direction's time)."""
        tr = 1.0 / self.frequency_hz          # each ramp: half a turn (the overshoot arc)
        tc = self.turns / self.frequency_hz   # the measured turns, at constant feed
        return tr, tc, 2 * tr + tc

    def windows(self) -> dict[str, tuple[float, float]]:
        """Time windows of the two directions, ``{"ccw": (t0, t1), "cw": (t0, t1)}``."""
        _, _, d = self._times
        t0 = self.start
        return {"ccw": (t0, t0 + d), "cw": (t0 + d + self.dwell, t0 + 2 * d + self.dwell)}

    @property
    def overshoot_deg(self) -> float:
        """Each overshoot arc: the angle turned while the speed ramps (half a turn by construction)."""
        tr, _, _ = self._times
        return math.degrees(2 * math.pi * self.frequency_hz * tr / 2)

    def measured(self) -> dict[str, tuple[float, float]]:
        """The constant-feed windows of the two directions (the overshoot arcs excluded): ``turns`` full
        turns each, over which ISO 230-4's figures are taken."""
        tr, tc, _ = self._times
        return {k: (t0 + tr, t0 + tr + tc) for k, (t0, _) in self.windows().items()}

    def _phase1(self, t: float) -> tuple[float, float, float]:
        """(phi, phi', phi'') at one time: the loop asks for two points a tick, where the vectorized
        form below costs ~100 us in numpy call overhead and this one a few."""
        tr, tc, d = self._times
        w0 = 2 * math.pi * self.frequency_hz
        full = w0 * (tr + tc)
        k = math.pi / tr
        t1 = self.start + d + self.dwell
        if t < self.start:
            return 0.0, 0.0, 0.0
        sign, base, tau = (1.0, 0.0, t - self.start) if t < t1 else (-1.0, full, t - t1)
        if tau >= d:
            return base + sign * full, 0.0, 0.0
        if tau < tr:
            ph, w, a = w0 * (tau / 2 - math.sin(k * tau) / (2 * k)), w0 * (1 - math.cos(k * tau)) / 2, \
                w0 * k / 2 * math.sin(k * tau)
        elif tau < tr + tc:
            ph, w, a = w0 * (tr / 2 + tau - tr), w0, 0.0
        else:
            u = tau - tr - tc
            ph, w, a = w0 * (tr / 2 + tc + u / 2 + math.sin(k * u) / (2 * k)), w0 * (1 + math.cos(k * u)) / 2, \
                -w0 * k / 2 * math.sin(k * u)
        return base + sign * ph, sign * w, sign * a

    def phase(self, t: np.ndarray) -> Triple:
        """(phi, phi', phi'') at times ``t``."""
        t = np.asarray(t, dtype=float)
        if t.size <= 8:
            out = np.array([self._phase1(float(v)) for v in t.ravel()]).reshape(t.shape + (3,))
            return out[..., 0], out[..., 1], out[..., 2]
        tr, tc, d = self._times
        w0 = 2 * math.pi * self.frequency_hz
        full = w0 * (tr + tc)                                  # = 2 pi turns
        phi, om, al = np.zeros(t.shape), np.zeros(t.shape), np.zeros(t.shape)
        for sign, t0, base in ((1.0, self.start, 0.0), (-1.0, self.start + d + self.dwell, full)):
            tau = t - t0
            a = (tau >= 0) & (tau < tr)
            b = (tau >= tr) & (tau < tr + tc)
            c = (tau >= tr + tc) & (tau < d)
            e = tau >= d
            u = tau - tr - tc
            k = math.pi / tr
            ph = np.select([a, b, c, e], [w0 * (tau / 2 - np.sin(k * tau) / (2 * k)), w0 * (tr / 2 + tau - tr),
                                          w0 * (tr / 2 + tc + u / 2 + np.sin(k * u) / (2 * k)), full], 0.0)
            w = np.select([a, b, c], [w0 * (1 - np.cos(k * tau)) / 2, w0, w0 * (1 + np.cos(k * u)) / 2], 0.0)
            acc = np.select([a, c], [w0 * k / 2 * np.sin(k * tau), -w0 * k / 2 * np.sin(k * u)], 0.0)
            on = tau >= 0
            phi = np.where(on, base + sign * ph, phi)
            om = np.where(on & ~e, sign * w, om)
            al = np.where(on & ~e, sign * acc, al)
        return phi, om, al

    def at(self, t: np.ndarray) -> Triple:
        phi, om, al = self.phase(t)
        R = self.radius
        s, c = np.sin(phi), np.cos(phi)
        if self.axis == "x":
            return -R * s, -R * c * om, R * s * om * om - R * c * al
        return R * (c - 1.0), -R * s * om, -R * c * om * om - R * s * al

    def point(self, t: float) -> tuple[float, float, float]:
        phi, om, al = self._phase1(float(t))
        R = self.radius
        s, c = math.sin(phi), math.cos(phi)
        if self.axis == "x":
            return -R * s, -R * c * om, R * s * om * om - R * c * al
        return R * (c - 1.0), -R * s * om, -R * c * om * om - R * s * al


@dataclass(frozen=True)
class CsvTrajectory:
    """A trajectory from samples ``t, x`` (s, m): a cubic spline through them; held before and after."""

    t: np.ndarray
    x: np.ndarray
    path: str = ""
    _spline: Any = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        from scipy.interpolate import CubicSpline

        object.__setattr__(self, "_spline", CubicSpline(self.t, self.x, bc_type="clamped"))

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    @classmethod
    def load(cls, path: str | Path) -> CsvTrajectory:
        p = Path(path)
        where = "reference.path"
        if not p.is_file():
            raise ConfigError(where, f"trajectory file not found: {p}")
        try:
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise ConfigError(where, f"{p}: not UTF-8 text") from None
        rows = list(csv.reader(text.splitlines()))
        if not rows:
            raise ConfigError(where, f"{p}: empty file")
        header = [h.strip().lower() for h in rows[0]]
        if "t" not in header or "x" not in header:
            raise ConfigError(where, f"{p}: the header must name columns t and x (got {len(header)} columns)")
        it, ix = header.index("t"), header.index("x")
        t, x = [], []
        for n, row in enumerate(rows[1:], start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                t.append(float(row[it]))
                x.append(float(row[ix]))
            except (ValueError, IndexError):
                raise ConfigError(where, f"{p}: line {n}: t and x must be numbers") from None
        ta, xa = np.array(t), np.array(x)
        if ta.size < 2:
            raise ConfigError(where, f"{p}: needs at least two samples")
        if not (np.all(np.isfinite(ta)) and np.all(np.isfinite(xa))):
            raise ConfigError(where, f"{p}: NaN or infinite values")
        if np.any(np.diff(ta) <= 0):
            raise ConfigError(where, f"{p}: t must increase strictly")
        return cls(ta, xa, str(p))

    def at(self, t: np.ndarray) -> Triple:
        tq = np.clip(np.asarray(t, dtype=float), self.t[0], self.t[-1])
        inside = (np.asarray(t) >= self.t[0]) & (np.asarray(t) <= self.t[-1])
        s = self._spline
        return s(tq), np.where(inside, s(tq, 1), 0.0), np.where(inside, s(tq, 2), 0.0)

    def point(self, t: float) -> tuple[float, float, float]:
        x, v, a = self.at(np.array([float(t)]))
        return float(x[0]), float(v[0]), float(a[0])


class _HoldCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["hold"]
    position: float = 0.0


class _MovesCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["moves"]
    positions: list[float] = Field(min_length=1)
    v_max: float = Field(gt=0)
    a_max: float = Field(gt=0)
    j_max: float = Field(gt=0)
    dwell: float = Field(0.2, ge=0)
    start: float = Field(0.0, ge=0)
    repeat: bool = True


class _SineCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["sine"]
    amplitude: float
    frequency_hz: float = Field(gt=0)
    offset: float = 0.0
    start: float = Field(0.0, ge=0)
    fade_periods: float = Field(2.0, gt=0)


class _CircleCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["circle"]
    radius: float = Field(gt=0)
    frequency_hz: float = Field(gt=0)
    axis: Literal["x", "y"]
    turns: float = Field(1.0, ge=1.0)
    start: float = Field(0.5, ge=0)
    dwell: float = Field(0.2, ge=0)


class _CsvCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["csv"]
    path: str


class _ReferenceCfg(BaseModel):
    ref: _HoldCfg | _MovesCfg | _SineCfg | _CircleCfg | _CsvCfg = Field(discriminator="kind")


Reference = Hold | Moves | Sine | Circle | CsvTrajectory


def make_reference(mapping: Mapping[str, Any] | None, base_dir: str | Path | None = None) -> Reference:
    """The reference a ``[reference]`` table describes (default: hold at 0). Errors name the field."""
    data = dict(mapping or {"kind": "hold"})
    data.setdefault("kind", "hold")
    try:
        cfg = _ReferenceCfg.model_validate({"ref": data}).ref
    except ValidationError as exc:
        e, msg = validation_error(_ReferenceCfg, exc)
        loc = ".".join(str(p) for p in e["loc"][2:] if not isinstance(p, int)) or "kind"
        raise ConfigError(f"reference.{loc}", msg) from None
    if isinstance(cfg, _HoldCfg):
        return Hold(cfg.position)
    if isinstance(cfg, _MovesCfg):
        return Moves(tuple(cfg.positions), cfg.v_max, cfg.a_max, cfg.j_max, cfg.dwell, cfg.start, cfg.repeat)
    if isinstance(cfg, _SineCfg):
        return Sine(cfg.amplitude, cfg.frequency_hz, cfg.offset, cfg.start, cfg.fade_periods)
    if isinstance(cfg, _CircleCfg):
        return Circle(cfg.radius, cfg.frequency_hz, cfg.axis, cfg.turns, cfg.start, cfg.dwell)
    p = Path(cfg.path)
    if not p.is_absolute() and base_dir is not None and not p.is_file():
        p = Path(base_dir) / p
    return CsvTrajectory.load(p)

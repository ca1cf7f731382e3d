"""The simulated axis as a backend: :class:`rt_ident.axis.plant.PlantSimulator` behind the :class:`Backend` contract.

Two modes:

* **paced** (default): ``read()`` advances the plant to "now" on the injected
  wall clock, ``n = floor((now - t_activate) / dt) - produced`` samples, the
  way a drive streaming at its own rate would deliver them;
* **free-running** (``paced = false``): each ``read()`` produces exactly
  ``samples_per_read`` samples (default ``round(1 ms / dt)``) — for tests, CI
  and offline studies; deterministic given ``seed``.

Timestamps are the device clock: sample ``seq`` (from 0 at activation) is at
``t = seq * dt``. ``torque_cmd`` is the host command in force for each sample
(per-sample plans, see :mod:`drivers.base`), ``torque_meas`` the plant's
reported torque (the drive's "torque actual": command + hold loop, saturated,
plus noise).

When the table leaves ``travel``, ``read()`` disables the drive (zero torque,
hold loop off) and raises :class:`~drivers.errors.TravelLimitTrip`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from drivers.base import Backend, SampleBlock, State, Travel
from drivers.errors import DriverError, TravelLimitTrip
from drivers.sim_plan import PM_OFF, PM_SIZE, new_plan, plan_take, plan_write
from rt_ident.axis.friction import Friction
from rt_ident.axis.params import PLAUSIBLE, UNITS, AxisParams, thomson_x
from rt_ident.axis.plant import (
    DEFAULT_KD,
    DEFAULT_KP,
    HoldController,
    PlantBlock,
    PlantSimulator,
    SensorConfig,
    rest_at,
)
from rt_ident.errors import ConfigError, validation_error

log = logging.getLogger(__name__)

#: The paper's Dt (Table 2, N = 512, k = 10).
PAPER_DT = 2.9481e-5
#: A plan may not start further ahead than this many samples (guards against seq mix-ups).
MAX_PLAN_LEAD = 1 << 22
#: Shortest sample period [s]: 1 M samples/s, 1000 per 1 ms tick, the top of the loop's capacity search
#: (rt-ident bench; it keeps pace at 170 k/s). The per-sample state (filters, buffers, the svf's impulse
#: response) grows as 1 / sample_period: a shorter one cannot be processed in a tick, nor held in memory.
MIN_SAMPLE_PERIOD = 1e-6


class SimActual(BaseModel):
    """What the simulated device truly is where it differs from what the host is told
    (``[plant.actual]``; :class:`rt_ident.config.ActualPlant`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # None: as the host is told (a host set to -1 describes a device that is so)
    torque_sign: Literal[1, -1] | None = None     # -1: the motor turns against the torque the drive applies
    motor_encoder_sign: Literal[1, -1] | None = None
    scale_sign: Literal[1, -1] | None = None
    counts_per_rev: int | None = Field(None, ge=1)
    scale_resolution: float | None = Field(None, gt=0, le=1e-3)
    lead: float | None = Field(None, gt=0, le=0.1)
    torque_scale: float = Field(1.0, gt=0, le=100)  # physical torque per N m the drive believes it applies
    rated_torque: float | None = None

    @field_validator("rated_torque")
    @classmethod
    def _no_rated_torque(cls, v: float | None) -> float | None:
        if v is not None:
            raise ValueError("the sim has no drive rating object (0x6076 is CiA 402); give torque_scale = "
                             "actual torque per commanded N m instead")
        return v


class SimConfig(BaseModel):
    """Options of the ``sim`` backend (the ``[backend]`` table minus ``name``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: Literal["sim"] | None = None
    axis: dict[str, float] | None = None         # I1, I2, B, K, lead; None -> Table 1
    sample_period: float = Field(PAPER_DT, le=0.1)  # s, >= MIN_SAMPLE_PERIOD
    counts_per_rev: int = Field(2**17, ge=0)        # 0: ideal (unquantized) encoder
    scale_resolution: float = Field(1e-7, ge=0, le=1e-3)  # m; 0: ideal scale
    angle_noise: float = Field(0.0, ge=0)
    torque_meas_noise: float = Field(0.0, ge=0)
    torque_process_noise: float = Field(0.0, ge=0)
    torque_limit: float = Field(1.0, gt=0)          # N m, at most rated_torque
    rated_torque: float = Field(3.0, gt=0)          # N m the simulated motor can deliver (3 x the default limit)
    travel: Travel | None = (-0.05, 0.05)  # m on the linear scale
    position_hold: bool = False                     # a drive-side hold loop (identification-only runs)
    kp: float | None = Field(None, ge=0)
    kd: float | None = Field(None, ge=0)
    integrator: Literal["zoh", "newmark"] = "zoh"
    seed: int = 0
    paced: bool = True
    samples_per_read: int | None = Field(None, ge=1, le=1_000_000)   # at most 1 s at 1 M samples/s
    has_measured_torque: bool = True
    changes: list[dict[str, float]] = Field(default_factory=list)  # [{at: s, I1/I2/B/K: factor}], see _changes()
    # friction to ground and backlash (rt_ident.axis.friction.Friction keys, or preset = "thomson");
    # None / all zero: the frictionless plant. [plant.friction] of a run config lands here.
    friction: dict[str, Any] | None = None
    x0: float = Field(0.0, ge=-10.0, le=10.0, allow_inf_nan=False)   # m: the table's start on the scale (at rest)
    # host-side polarity (drivers.base)
    torque_sign: Literal[1, -1] = 1
    motor_encoder_sign: Literal[1, -1] = 1
    scale_sign: Literal[1, -1] = 1
    # the simulated device's own truth where it differs from the keys above ([plant.actual] of a run config)
    actual: SimActual | None = None

    @field_validator("scale_resolution")
    @classmethod
    def _scale_counts(cls, v: float) -> float:
        if v != 0 and v < 1e-12:
            raise ValueError(f"must be 0 (an ideal scale) or 1e-12 .. 1e-3 m per count, got {v:g}")
        return v

    @field_validator("sample_period")
    @classmethod
    def _sample_period_processable(cls, v: float) -> float:
        if not v >= MIN_SAMPLE_PERIOD:
            raise ValueError(f"must be >= {MIN_SAMPLE_PERIOD:g} s (at most {1e-6 / MIN_SAMPLE_PERIOD:g} M "
                             f"samples/s, what the loop can process per tick), got {v:g} s")
        return v

    @model_validator(mode="after")
    def _limit_within_rating(self) -> SimConfig:
        if self.torque_limit > self.rated_torque:
            raise ValueError(f"torque_limit: {self.torque_limit:g} N m exceeds the simulated motor's "
                             f"rated_torque {self.rated_torque:g} N m; lower torque_limit or raise rated_torque")
        return self


def _validate(config: Mapping[str, Any] | None) -> SimConfig:
    try:
        return SimConfig.model_validate(dict(config or {}))
    except ValidationError as exc:
        err, msg = validation_error(SimConfig, exc)
        loc = ".".join(str(p) for p in err["loc"] if not isinstance(p, int))
        if not loc and ": " in msg:                  # a model check that names its field itself
            loc, msg = msg.split(": ", 1)
        if loc.startswith("actual."):
            raise ConfigError(f"plant.{loc}", msg) from None
        raise ConfigError(f"backend.{loc}" if loc else "backend", msg) from None


class SimBackend(Backend):
    """Simulated axis (registry name ``"sim"``). See the module docstring.

    ``clock`` is injected (seconds, monotonic) for paced mode; tests pass a fake.
    """

    name = "sim"
    simulated = True

    @property
    def samples_in_real_time(self) -> bool:
        return bool(self.config.paced)

    def __init__(self, config: Mapping[str, Any] | None = None, *,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        cfg = _validate(config)
        super().__init__({"torque_limit": cfg.torque_limit, "torque_sign": cfg.torque_sign,
                          "motor_encoder_sign": cfg.motor_encoder_sign, "scale_sign": cfg.scale_sign})
        self.config = cfg
        told: AxisParams = (AxisParams.from_mapping(cfg.axis, where="backend.axis")
                            if cfg.axis is not None else thomson_x())
        act = cfg.actual or SimActual()
        #: the plant as it truly is (the host's axis, with the true lead)
        self.true_params = dataclasses.replace(told, lead=act.lead or told.lead)
        # the device's true sensors and torque against what the host converts with (1.0: they agree)
        cpr, res = act.counts_per_rev or cfg.counts_per_rev, act.scale_resolution or cfg.scale_resolution
        s_t, s_e, s_s = (cfg.torque_sign if act.torque_sign is None else act.torque_sign,
                         cfg.motor_encoder_sign if act.motor_encoder_sign is None else act.motor_encoder_sign,
                         cfg.scale_sign if act.scale_sign is None else act.scale_sign)
        self._k_torque = s_t * act.torque_scale
        self._k_theta1 = s_e * (cpr / cfg.counts_per_rev if cfg.counts_per_rev and cpr else 1.0)
        self._k_theta2 = (s_s * self.true_params.lead / told.lead
                          * (cfg.scale_resolution / res if cfg.scale_resolution and res else 1.0))
        self._k_identity = self._k_torque == self._k_theta1 == self._k_theta2 == 1.0
        self._dt = cfg.sample_period
        self.samples_per_read = cfg.samples_per_read or max(1, round(1e-3 / self._dt))
        self.sensors = SensorConfig(counts_per_rev=cpr, scale_resolution=res,
                                    angle_noise=cfg.angle_noise, torque_meas_noise=cfg.torque_meas_noise,
                                    torque_process_noise=cfg.torque_process_noise)
        self.controller = (HoldController(kp=DEFAULT_KP if cfg.kp is None else cfg.kp,
                                          kd=DEFAULT_KD if cfg.kd is None else cfg.kd)
                           if cfg.position_hold else None)
        self.friction = Friction.from_mapping(cfg.friction, where="backend.friction")
        self.plant = self._make_plant(self.controller, x0=rest_at(cfg.x0, self.true_params.lead))
        self._changes = _changes(cfg.changes, self.true_params, self._dt)
        # the step matrices of each change, computed now: a change costs the loop's tick no expm
        self._change_matrices = [self.plant.matrices_for(p) for _, p in self._changes]
        self.applied_changes: list[tuple[int, AxisParams]] = []   # (seq, params) applied so far
        self._clock = clock
        self._t_activate = 0.0
        self._produced = 0                # samples read() has handed out = seq of the next one it returns
        self._stepped = 0                 # samples the plant has stepped (ahead of _produced after step_ahead)
        # stepped ahead, not yet read (seq _produced .. _stepped - 1): t, seq, theta1, theta2, torque_cmd,
        # torque_applied, torque_meas from index _ahead_off on
        self._ahead: tuple[np.ndarray, ...] | None = None
        self._ahead_off = 0
        self._ahead_trip: str | None = None     # the travel limit tripped in the samples stepped ahead
        # the torque plan and the torque held where it has none (drivers.sim_plan)
        self._plan_buf, self._plan_meta, self._plan_hold = new_plan()
        self.late_plan_samples = 0        # plan values that arrived after their sample was produced
        self.drive_enabled = False
        self.applied_torque = 0.0         # last torque actually applied by the plant
        self.tripped: str | None = None
        self.trip_block: SampleBlock | None = None

    def _make_plant(self, controller: HoldController | None, x0: np.ndarray | None) -> PlantSimulator:
        cfg = self.config
        params = self.plant.params if hasattr(self, "plant") else self.true_params
        return PlantSimulator(params, self._dt, sensors=self.sensors, controller=controller,
                              torque_limit=cfg.torque_limit * abs(self._k_torque), travel=cfg.travel,
                              integrator=cfg.integrator, seed=cfg.seed, x0=x0, friction=self.friction)

    @property
    def current_params(self) -> AxisParams:
        """The plant's parameters now (after the changes applied so far)."""
        return self.plant.params

    # ----- properties -----------------------------------------------------
    @property
    def sample_period(self) -> float:
        return self._dt

    @property
    def has_measured_torque(self) -> bool:
        return self.config.has_measured_torque

    @property
    def samples_produced(self) -> int:
        """Sequence number of the next sample read() returns."""
        return self._produced

    # ----- hooks ----------------------------------------------------------
    def _open(self) -> None:
        # Compile (or load from cache) the plant kernel now, not in the first hot-path read().
        self.plant.step_block(np.empty(0))

    def _read_position(self) -> tuple[float, float]:
        st = self.plant.state
        return self._k_theta1 * float(st[0]), self._k_theta2 * float(st[2])

    def _activate(self) -> None:
        self._produced = 0
        self._stepped = 0
        self._ahead = None
        self._ahead_off = 0
        self._ahead_trip = None
        self._plan_buf, self._plan_meta, self._plan_hold = new_plan()
        self.drive_enabled = True
        self._t_activate = self._clock()

    def _due(self) -> int:
        if not self.config.paced:
            return self.samples_per_read
        n = math.floor((self._clock() - self._t_activate) / self._dt) - self._produced
        return n if n > 0 else 0

    def _commands(self, n: int) -> np.ndarray:
        """Per-sample host command for the next ``n`` samples to step (from seq ``_stepped`` on): the plan
        where it covers them, the held torque before it, its last value after it; they leave the plan."""
        cmd = np.empty(n)
        plan_take(self._plan_buf, self._plan_meta, self._plan_hold, cmd, self._stepped)
        return cmd if self._k_identity else cmd * self._k_torque

    @property
    def _hold(self) -> float:
        """The torque held where the plan has no value."""
        return float(self._plan_hold[0])

    def step_ahead(self, seconds: float) -> None:
        """Paced mode: step the plant now through the samples due in the next ``seconds`` (the loop
        calls this after its tick, with the time to its next deadline), so that read() only hands
        them out. Nothing changes for the samples: a drive applies the plan it holds when each sample
        comes, and until the next read() that is the plan the host has just written - the same plan
        the samples got when read() stepped them. A host write that arrives before they are read
        finds them already applied (``late_plan_samples``), as it would on a drive. A travel trip
        among them disables the drive at once and is raised by the read() that delivers them."""
        if not self.config.paced or self.state is not State.ACTIVE or self.tripped is not None \
                or self._ahead_trip is not None:
            return
        n = math.floor((self._clock() + seconds - self._t_activate) / self._dt) - self._stepped
        if n <= 0:
            return
        p = self._stepped
        blk = self._step(self._commands(n), p)
        self._stepped = p + n
        new = self._delivered(blk, p)
        if self._ahead is None:
            self._ahead = new
        else:                               # what the last read left (the copying is done here, not in read)
            o = self._ahead_off
            self._ahead = tuple(np.concatenate((old[o:], a)) for old, a in zip(self._ahead, new))
        self._ahead_off = 0
        if self.plant.travel_exceeded:
            self._ahead_trip = self._trip_message()
            self._disable()

    def _trip_message(self) -> str:
        x = self.true_params.lead * float(self.plant.state[2])
        return f"table at {x:.6f} m outside travel {self.config.travel}"

    def _take_ahead(self, n: int) -> tuple[np.ndarray, ...]:
        """Views of the next ``n`` samples stepped ahead: t, seq, theta1, theta2, torque_cmd, torque_applied,
        torque_meas (arrays never written again: step_ahead makes new ones)."""
        o, ahead = self._ahead_off, self._ahead
        assert ahead is not None            # the callers saw samples stepped ahead
        got = tuple(a[o:o + n] for a in ahead)
        if o + n >= ahead[0].shape[0]:
            self._ahead, self._ahead_off = None, 0
        else:
            self._ahead_off = o + n
        return got

    def _read(self) -> SampleBlock:
        if self.tripped is not None:
            raise TravelLimitTrip(f"sim: drive disabled after {self.tripped}")
        n = self._due()
        if n == 0:
            return SampleBlock.empty(self.has_measured_torque)
        p = self._produced
        ahead = self._stepped - p
        if ahead >= n and self._ahead_trip is None:
            # the usual read: samples step_ahead has made, handed out as they are (nothing computed here)
            t, seq, th1, th2, cmd, applied, meas = self._take_ahead(n)
        elif ahead == 0:
            b = self._step(self._commands(n), p)
            t, seq, th1, th2, cmd, applied, meas = self._delivered(b, p)
            self._stepped = p + n
        elif ahead >= n or self._ahead_trip is not None:
            n = min(n, ahead)               # after a trip the drive is off: nothing after its samples
            t, seq, th1, th2, cmd, applied, meas = self._take_ahead(n)
        else:                               # a late read: the rest is stepped now
            first = self._take_ahead(ahead)
            b = self._step(self._commands(n - ahead), self._stepped)
            t, seq, th1, th2, cmd, applied, meas = (np.concatenate(pair) for pair in
                                                    zip(first, self._delivered(b, self._stepped)))
            self._stepped = p + n
        self._produced = p + n
        self.applied_torque = float(applied[-1])
        out = SampleBlock(t, seq, th1, th2, cmd, meas if self.has_measured_torque else None)
        if self._ahead_trip is not None and self._produced == self._stepped:
            self.tripped, self._ahead_trip = self._ahead_trip, None
            self.trip_block = out         # the samples of the tripping read, for the recorder
            self.applied_torque = 0.0
            raise TravelLimitTrip(f"sim: {self.tripped}; torque stopped")
        if self.plant.travel_exceeded and self._ahead_trip is None:
            self.tripped = self._trip_message()
            self.trip_block = out
            self._disable()
            raise TravelLimitTrip(f"sim: {self.tripped}; torque stopped")
        return out

    def _delivered(self, blk: PlantBlock, first: int) -> tuple[np.ndarray, ...]:
        """What read() hands out of a block stepped from sample ``first`` on (and step_ahead keeps): t, seq,
        theta1, theta2, torque_cmd, torque_applied, torque_meas. The device clock: sample seq is at seq * dt.
        Angles as the device's sensors count them, torques as the device believes it applies them (the
        physical torque is torque_applied)."""
        seq = np.arange(first, first + blk.theta1.shape[0], dtype=np.int64)
        if self._k_identity:
            return seq * self._dt, seq, blk.theta1, blk.theta2, blk.torque_cmd, blk.torque_applied, blk.torque_meas
        k = 1.0 / self._k_torque
        return (seq * self._dt, seq, blk.theta1 * self._k_theta1, blk.theta2 * self._k_theta2, blk.torque_cmd * k,
                blk.torque_applied, blk.torque_meas * k)

    def _step(self, cmd: np.ndarray, p: int) -> PlantBlock:
        """Step the plant over seq [p, p + len(cmd)), applying each due change at its exact sample."""
        due = self._changes
        if not due or due[0][0] >= p + cmd.shape[0]:
            return self.plant.step_block(cmd)
        parts, k = [], 0
        while due and due[0][0] < p + cmd.shape[0]:
            seq, params = due.pop(0)
            cut = max(seq - p, k)
            if cut > k:
                parts.append(self.plant.step_block(cmd[k:cut]))
                k = cut
            self.plant.set_params(params, self._change_matrices.pop(0))
            self.applied_changes.append((max(seq, p), params))
            log.info("sim: plant changed at seq %d: %s", max(seq, p), params)
        parts.append(self.plant.step_block(cmd[k:]))
        return PlantBlock(*(np.concatenate([getattr(b, f.name) for b in parts])
                            for f in dataclasses.fields(PlantBlock)))

    def _refuse_if_disabled(self) -> None:
        why = self.tripped or self._ahead_trip
        if why is not None:
            raise TravelLimitTrip(f"sim: drive disabled after {why}; torque command refused")

    def _write_hold(self, torque: float) -> None:
        self._refuse_if_disabled()
        self._plan_hold[0] = float(torque)
        self._plan_meta[PM_SIZE] = 0              # the plan is gone

    def _write_plan(self, torques: np.ndarray, start_seq: int) -> None:
        self._write_leased_plan(torques, start_seq, -1)

    def _write_leased_plan(self, torques: np.ndarray, start_seq: int, lease: int) -> None:
        self._refuse_if_disabled()
        vals = np.asarray(torques, dtype=float)
        if vals.size == 0:
            return
        if start_seq - self._produced > MAX_PLAN_LEAD:
            raise DriverError(f"plan start_seq {start_seq} is {start_seq - self._produced} samples ahead "
                              f"(max {MAX_PLAN_LEAD})")
        if lease >= 0 and start_seq + vals.size + lease - self._produced > MAX_PLAN_LEAD:
            raise DriverError(f"a lease of {lease} samples after this plan ends {MAX_PLAN_LEAD} samples ahead")
        while True:
            late = plan_write(self._plan_buf, self._plan_meta, self._plan_hold, vals, start_seq, self._stepped,
                              lease)
            if late >= 0:
                self.late_plan_samples += late
                return
            grown = np.zeros(max(-late, 2 * self._plan_buf.shape[0]))    # a long plan: a larger buffer
            m = self._plan_meta
            grown[:m[PM_SIZE]] = self._plan_buf[m[PM_OFF]:m[PM_OFF] + m[PM_SIZE]]
            m[PM_OFF] = 0
            self._plan_buf = grown

    def _disable(self) -> None:
        """Zero torque, drive off: later stepping runs with zero command and no hold loop."""
        self._plan_hold[0] = 0.0
        self._plan_meta[PM_SIZE] = 0
        self.applied_torque = 0.0
        if self.drive_enabled and self.controller is not None:
            self.plant = self._make_plant(None, x0=self.plant.state)
        self.drive_enabled = False

    def _safe_stop(self) -> None:
        self._disable()                 # the simulated drive is this process: disabled once this returns

    def _close(self) -> None:
        self._disable()




def _changes(entries: list[dict[str, float]], base: AxisParams, dt: float) -> list[tuple[int, AxisParams]]:
    """``[[plant.change]]`` entries -> (first sample, parameters), sorted. Factors scale the configured
    axis (they do not compound: ``I2 = 3`` twice is still 3 x the configured I2)."""
    out = []
    for i, entry in enumerate(entries):
        where = f"plant.change[{i}]"
        unknown = set(entry) - {"at", *_CHANGE_KEYS}
        if unknown:
            raise ConfigError(f"{where}.{sorted(unknown)[0]}", f"unknown key (expected at, {', '.join(_CHANGE_KEYS)})")
        at = entry.get("at")
        if isinstance(at, bool) or not isinstance(at, (int, float)) or not math.isfinite(at) or at < 0:
            raise ConfigError(f"{where}.at", f"must be a time >= 0 in seconds, got {at!r}")
        scaled = {}
        for k in _CHANGE_KEYS:
            f = entry.get(k, 1.0)
            if isinstance(f, bool) or not isinstance(f, (int, float)) or not math.isfinite(f) or f <= 0:
                raise ConfigError(f"{where}.{k}", f"must be a factor > 0, got {f!r}")
            scaled[k] = getattr(base, k) * float(f)
            lo, hi = PLAUSIBLE[k]
            if not lo <= scaled[k] <= hi:
                raise ConfigError(f"{where}.{k}", f"factor {f:g} makes {k} {scaled[k]:g} {UNITS[k]}, outside the "
                                  f"range of a machine-tool axis, {lo:g} .. {hi:g} {UNITS[k]}")
        out.append((int(math.ceil(at / dt - 1e-9)), AxisParams(**scaled, lead=base.lead)))
    return sorted(out, key=lambda c: c[0])


_CHANGE_KEYS = ("I1", "I2", "B", "K")

__all__ = ["SimBackend", "SimConfig", "PAPER_DT"]

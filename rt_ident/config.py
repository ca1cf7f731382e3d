"""Run configuration: one TOML file describes a whole run.

Sections: ``[axis]`` (plant truth for sim / reference values), ``[backend]``
(``name`` plus the backend's own keys, validated by the backend),
``[emulator]`` (for emulated devices), ``[excitation]``, ``[loop]``,
``[estimator]``, ``[safety]``, ``[telemetry]``, ``[recording]``. Every
section is optional; the defaults are the sim backend with the THOMSON X axis.
Errors name the offending field, e.g. ``loop.tick_hz: must be > 0``.

Every number must be finite (``friction_memory_s = inf`` is the one documented exception).
A config file that holds nothing (empty, or comments only) is an error: it is more likely a
wrong or truncated file than a wish for the defaults (run without a config for those). A file
without ``[axis]``, ``[backend]`` or ``[safety]`` runs on their built-in defaults, and says so:
:attr:`RunConfig.defaulted` lists them, the CLI prints a warning line and the run summary
carries them as ``config_defaulted``.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from rt_ident.axis.params import CONFIG_DIR, AxisParams, thomson_x
from rt_ident.errors import ConfigError, validation_error

if TYPE_CHECKING:
    from rt_ident.control.job import ControlSettings


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class BackendConfig(BaseModel):
    """``name`` picks the backend; every other key is passed to it untouched."""

    model_config = ConfigDict(extra="allow", frozen=True)
    name: str = "sim"
    emulate: bool = False

    def options(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class ExcitationConfig(_Section):
    kind: Literal["schroeder", "random", "prbs", "chirp", "none"] = "schroeder"
    period_samples: int = Field(512, ge=4, le=65536)   # the warm-up replays a few periods: memory ~ this
    band: tuple[int, int] = (1, 20)            # harmonics of the period, inclusive
    peak: float = Field(0.3, ge=1e-9)          # N m, added to the position-hold torque
    seed: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _band_fits(self) -> ExcitationConfig:
        lo, hi = self.band
        if not (1 <= lo <= hi <= self.period_samples // 2 - 1):
            raise ValueError(f"band {list(self.band)} must satisfy 1 <= lo <= hi <= period_samples//2 - 1 "
                             f"= {self.period_samples // 2 - 1}")
        return self


#: What an ``[axes.NAME]`` name may be: it becomes part of file names and dashboard paths.
_AXIS_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,31}")

#: Tick rates the loop runs at [Hz]. At least 100: the host writes to the device (torque, heartbeat)
#: once per tick, and a serial board disables itself after 0.1 s without a host frame; the safety
#: watchdog counts ticks. At most 3333: the ticker spins the last 150 us before each deadline
#: (rt_ident/loop/scheduler.py), which must stay within half a tick.
TICK_HZ_RANGE = (100.0, 3333.0)


class LoopConfig(_Section):
    tick_hz: float = 1000.0
    duration: float = Field(10.0, gt=0)
    realtime: bool = True                      # try SCHED_FIFO, affinity, mlockall, gc.freeze
    warmup_periods: int = Field(2, ge=0, le=20)  # excitation periods discarded before estimating
    max_sleep_us: float | None = Field(100.0, gt=0)  # longest single sleep while waiting for a tick
                                               # (short sleeps keep a VM's vCPU from halting; scheduler.py)
    idle_poll: bool = True                     # real time, loop on its own CPU: a SCHED_IDLE thread keeps that
                                               # CPU busy while the loop sleeps (rt_ident/loop/idle_poll.py); the
                                               # ticker then sleeps in one piece unless max_sleep_us is set
    compiled_tick: bool = True                 # each axis's tick in one compiled call where its parts allow
                                               # (rt_ident/loop/tick_core.py); false: the Python path, step by step
    cpu_wait_s: float = Field(60.0, ge=0, le=3600)  # real time: how long to wait for another rt-ident loop
                                               # to free this one's CPU before refusing (rt_ident/loop/cpu_claim.py)

    @field_validator("tick_hz")
    @classmethod
    def _tick_hz_in_range(cls, v: float) -> float:
        lo, hi = TICK_HZ_RANGE
        if not lo <= v <= hi:
            raise ValueError(f"must be between {lo:g} and {hi:g} ticks per second, got {v:g} (at least {lo:g}: "
                             f"the device hears from the host every tick; at most {hi:g}: the ticker needs "
                             "300 us per tick)")
        return v


class EstimatorConfig(_Section):
    method: str = "frequency"
    forgetting: float = Field(1.0, gt=0, le=1)
    kalman_process_noise: float = Field(1e9, ge=1e-12, le=1e15)  # rad^2/s^5 (jerk spectral density) for the
    #                                                   velocity filter; beyond these its Riccati equation fails
    # the per-sample estimator that feeds the adaptive controller (rt_ident.estimators.svf)
    per_sample: Literal["svf", "none"] = "svf"      # none: the controller adapts from the frequency fit alone
    svf_hz: float = Field(800.0, ge=10)             # state-variable filter corner (passes the resonance); its
    #                                                 start-up computes ~6/(svf_hz * sample period) samples of it
    svf_memory_s: float = Field(0.05, gt=0)         # forgetting time constant of the per-sample estimate
    svf_quanta: tuple[float, float] | None = None  # rad (theta1, theta2) for bias compensation;
                                                    # None: from the backend's encoder and scale resolution
    # the model the loop also identifies per sample (rt_ident.estimators.friction_stream): two-inertia (the
    # linear frequency fit alone), two-inertia-friction (adds Fc1, Fv1, Fc2, Fv2, offset) or
    # rigid-friction (J, Fv, Fc, offset); its friction feeds the controller ([control] friction_feedforward)
    model: Literal["two-inertia", "two-inertia-friction", "rigid-friction"] = "two-inertia"
    friction_hz: float | None = Field(None, ge=1)  # its filter corner; None: 800 Hz (two-inertia-friction:
    #                                                   passes the resonance), 100 Hz (rigid-friction)
    friction_memory_s: float = Field(math.inf, gt=0, allow_inf_nan=True)  # its forgetting time constant (inf: none)

    @field_validator("svf_quanta")
    @classmethod
    def _quanta_in_range(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(0.0 <= q <= 0.1 for q in v):
            raise ValueError(f"must be two quanta in rad, each 0 .. 0.1 (a count of 1/63 rev at most), got {list(v)}")
        return v


class ControlConfig(_Section):
    """The host's position loop (:mod:`rt_ident.control`)."""

    # off: excitation only (needs a drive-side hold); conservative: the rigid-body controller throughout
    mode: Literal["adaptive", "fixed", "conservative", "off"] = "adaptive"
    # a position loop below 1 Hz holds nothing, and its LQR design fails; effort beyond 1e-6..1e6 too
    bandwidth_hz: float = Field(20.0, ge=1)           # model controller (LQR on the identified model)
    effort: float = Field(1.0, ge=1e-6, le=1e6)       # torque weight multiplier: larger is gentler
    conservative_bandwidth_hz: float = Field(10.0, ge=1)  # rigid-body controller from [axis] I1 + I2 (at most)
    # it keeps its margins with I2 x this (a workpiece; docs/theory/control.md)
    conservative_load: float = Field(1.0, ge=1, le=100)
    gain_margin_db: float = Field(6.0, ge=0)
    phase_margin_deg: float = Field(40.0, ge=0, lt=90)
    family_factors: tuple[float, ...] = (0.7, 1.3)    # each parameter x these must keep the margins
    redesign_interval_s: float = Field(0.25, gt=0)
    min_change: float = Field(0.02, ge=0)             # relative change of the estimate that asks for a redesign
    min_change_damping: float = Field(0.10, ge=0)     # the same for B alone (see ControlSettings)
    max_error_m: float = Field(2e-4, gt=0)            # tracking error bound -> conservative fallback
    fallback_timeout_s: float = Field(0.5, gt=0)      # fallback not recovered by then -> safe stop
    feedforward: bool = True                          # inertia feedforward from the reference acceleration
    friction_feedforward: bool = True                 # Fc, Fv feedforward from [estimator] model's friction
    trust_tolerance: float = Field(0.05, gt=0)        # per-sample estimate vs frequency fit: agree when within
    # per-sample: the per-sample estimate is trusted on its own evidence, the frequency fit audits it;
    # cross-check: trusted only while the frequency fit agrees (slower)
    trust: Literal["per-sample", "cross-check"] = "per-sample"
    settle_tolerance: float = Field(0.02, gt=0)       # per-sample: I1, I2, K steady within this over the window
    interval_tolerance: float = Field(0.05, gt=0)     # per-sample: 95 % half-widths of I1, I2, K within this
    audit_grace_s: float = Field(1.0, ge=0)           # the frequency fit's lag after a detected change
    keep_margin: float = Field(0.05, ge=0, le=1)     # a new design is switched in only if its predicted error
                                                      # beats the one in force by this (0: always switched in)
    probe_scale_trusted: float = Field(1.0, gt=0, le=1)  # probing amplitude x this while the estimate is trusted
    delay_ticks: int = Field(1, ge=1, le=5)           # ticks from the newest sample until the torque lands
    drive_holds: bool = False                         # a real drive holds the axis itself (a position mode):
                                                      # the only way mode = "off" runs on a real drive

    def settings(self) -> ControlSettings:
        from rt_ident.control.job import ControlSettings

        return ControlSettings(**{k: v for k, v in self.model_dump().items()
                                  if k in ControlSettings.__dataclass_fields__})


Sign = Literal[1, -1]


class ActualPlant(_Section):
    """``[plant.actual]``: the simulated or emulated device's own truth where it differs from what the
    host is told (``[backend]``, ``[axis]``). Each key left out: the device is what the host is told."""

    x0: float = Field(0.0, allow_inf_nan=False, ge=-10.0, le=10.0)   # m: the table's start on the scale
    torque_sign: Sign | None = None        # -1: the motor is wired the other way (torque acts reversed)
    motor_encoder_sign: Sign | None = None  # -1: the motor encoder counts the other way
    scale_sign: Sign | None = None         # -1: the linear scale counts the other way
    counts_per_rev: int | None = Field(None, ge=1)           # the motor encoder's true counts per revolution
    scale_resolution: float | None = Field(None, gt=0, le=1e-3)  # m per scale count, truly
    lead: float | None = Field(None, gt=0, le=0.1)           # m/rad the screw truly moves the table
    rated_torque: float | None = Field(None, gt=0)           # N m: the drive's true 0x6076 (CiA 402 only)
    torque_scale: float | None = Field(None, gt=0, le=100)   # actual torque per commanded N m (a wrong torque
    #                                                          constant; the device reports what it believes)

    def device_truth(self) -> dict[str, Any]:
        """The keys given, other than ``x0``: what the device truly is (``actual`` of a device's options)."""
        return {k: v for k, v in self.model_dump(exclude={"x0"}).items() if v is not None}


#: the ``[plant.actual]`` keys each simulated device takes (the sim has no CiA 402 rated torque)
ACTUAL_KEYS = tuple(k for k in ActualPlant.model_fields if k != "x0")


class PlantConfig(_Section):
    """Scenario changes of the simulated plant (sim backend only): ``[[plant.change]]``; and its friction
    and backlash, ``[plant.friction]`` (:class:`rt_ident.axis.friction.Friction` keys or ``preset =
    "thomson"``; handed to the sim backend as ``[backend] friction``)."""

    change: list[dict[str, float]] = Field(default_factory=list)  # {at = s, I1/I2/B/K = factor}
    friction: dict[str, Any] | None = None
    # the simulated device as it truly is where it differs from what the host is told: x0 = where the
    # table starts [m on the scale] (handed to the sim backend or the emulator as its x0), the rest as
    # its ``actual`` table (ActualPlant)
    actual: ActualPlant | None = None

    @model_validator(mode="after")
    def _friction_valid(self) -> PlantConfig:
        if self.friction is not None:
            from rt_ident.axis.friction import Friction

            Friction.from_mapping(self.friction, where="plant.friction")
        return self

    def last_change_s(self) -> float | None:
        return max((float(c.get("at", 0.0)) for c in self.change), default=None)


class SafetyConfig(_Section):
    window: tuple[float, float] = (-0.04, 0.04)  # table position window [m] on the scale
    max_decel: float = Field(2.0e4, gt=0)        # rad/s^2 the motor can brake at (stopping distance)
    watchdog_ticks: int = Field(20, ge=1)        # ticks without fresh feedback before a safe stop
    # N m: a motor encoder that does not move counts as stuck only while |torque| exceeds this. None: the
    # sim's configured breakaway torque Fs1 + Fs2 (both sides stick together), else 0 (any torque).
    # Set it to the breakaway torque of a real axis with friction.
    stuck_torque: float | None = Field(None, ge=0)
    # s the loop's last planned torque is held past the end of its plan (about two ticks ahead) before the
    # command drops to zero: a stalled host, or one without fresh feedback, leaves the axis coasting
    torque_hold: float = Field(0.005, ge=0)
    # a tick later than this is a loop stall (rt_ident.loop.stall): "resume" re-plans from where the
    # table is, "stop" stops safely; a stall longer than max_stall_stop_s always stops
    max_stall_s: float | None = Field(None, gt=0, allow_inf_nan=False)   # None: 10 ms, or the plan + lease + a tick
    on_stall: Literal["resume", "stop"] = "resume"
    max_stall_stop_s: float = Field(1.0, gt=0, allow_inf_nan=False)
    # m/s the table may move at (estimated from the scale); None: sized from the reference's speed, its
    # approach limits and the probing excitation's own motion (rt_ident.compose.preflight)
    max_speed_m_s: float | None = Field(None, gt=0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _stall_order(self) -> SafetyConfig:
        if self.max_stall_s is not None and self.max_stall_stop_s < self.max_stall_s:
            raise ValueError(f"max_stall_stop_s: must be >= max_stall_s = {self.max_stall_s:g} s, "
                             f"got {self.max_stall_stop_s:g}")
        return self

    def stall_after(self, tick_hz: float) -> float:
        """``max_stall_s``, or the default: 10 ms, and at least the plan (two ticks) and its lease and one
        more tick (a shorter stall leaves the drive applying the last plan)."""
        if self.max_stall_s is not None:
            return float(self.max_stall_s)
        return max(0.01, self.torque_hold + 3.0 / tick_hz)

    @field_validator("window")
    @classmethod
    def _window_ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not v[0] < v[1]:
            raise ValueError(f"must be [min, max] in m with min < max, got {list(v)}")
        return v


class CommissionConfig(_Section):
    """``[commission]``: the bounds of ``rt-ident commission``'s open-loop probing and its stages."""

    travel_m: float = Field(2e-3, gt=0, le=0.05)        # the table stays this close to where it stood
    max_speed_m_s: float = Field(5e-3, gt=0, le=0.5)    # the probing's speed limit
    torque_share: float = Field(0.5, gt=0, le=1)        # the pulses' torque at most this x the torque limit
    identify_s: float = Field(5.0, ge=1, le=120)        # stage c: identification while holding
    move_m: float = Field(5e-4, gt=0, le=0.01)          # stage d: the verification move


class TelemetryConfig(_Section):
    sink: Literal["rrd", "spawn", "connect", "serve", "off"] = "rrd"
    rrd: str | None = None
    connect_url: str | None = None
    bind_ip: str = "127.0.0.1"
    port: int | None = Field(None, ge=1, le=65535)  # --serve / --spawn port; None: 9876, or a free one
    rate_hz: float = Field(1000.0, ge=1)        # angle/torque samples per second sent to the viewer
    publish_every_ticks: int = Field(20, ge=1)


class RecordingConfig(_Section):
    path: str | None = None
    enabled: bool = True


class RunConfig(_Section):
    axis: dict[str, float] | None = None
    backend: BackendConfig = BackendConfig()
    emulator: dict[str, Any] = Field(default_factory=dict)
    excitation: ExcitationConfig = ExcitationConfig()
    loop: LoopConfig = LoopConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    safety: SafetyConfig = SafetyConfig()
    control: ControlConfig = ControlConfig()
    reference: dict[str, Any] = Field(default_factory=lambda: {"kind": "hold"})
    plant: PlantConfig = PlantConfig()
    telemetry: TelemetryConfig = TelemetryConfig()
    recording: RecordingConfig = RecordingConfig()
    commission: CommissionConfig = CommissionConfig()
    # several axes in one run (an XY table): [axes.x], [axes.y], each overlaying the sections above
    # (axis, backend, estimator, control, safety, reference, plant, excitation) on this config
    axes: dict[str, dict[str, Any]] = Field(default_factory=dict)
    contour: dict[str, Any] = Field(default_factory=dict)   # [contour]: reserved for a coordinated XY reference
    source: str | None = None
    _defaulted: tuple[str, ...] = PrivateAttr(default=())    # set by load(): see the module docstring

    _AXIS_SECTIONS = ("axis", "backend", "emulator", "excitation", "estimator", "safety", "control", "reference",
                      "plant")

    @field_validator("contour")
    @classmethod
    def _contour_not_read(cls, v: dict[str, Any]) -> dict[str, Any]:
        if v:
            raise ValueError("the run does not read [contour] (yet): give the circle per axis, e.g. [axes.x] reference "
                             '= { kind = "circle", axis = "x", ... } as configs/xy-circle.toml does')
        return v

    def axis_configs(self) -> dict[str, RunConfig]:
        """One validated config per ``[axes.NAME]`` (this config with the axis's sections laid over;
        a table merges key by key, ``reference`` and ``axis`` are replaced whole). Empty for a
        one-axis config. Errors name the field as ``axes.NAME.section.key``."""
        out: dict[str, RunConfig] = {}
        base = self.model_dump(exclude={"axes", "contour", "source"})
        for name, overlay in self.axes.items():
            if not _AXIS_NAME.fullmatch(name):
                raise ConfigError(f"axes.{name}", "an axis name is 1-32 letters, digits, '-' or '_', starting with a "
                                                  "letter or digit (it names the axis's files and dashboard)")
            if not isinstance(overlay, dict):
                raise ConfigError(f"axes.{name}", "must be a table")
            bad = sorted(set(overlay) - set(self._AXIS_SECTIONS))
            if bad:
                raise ConfigError(f"axes.{name}.{bad[0]}", f"not a per-axis section (per-axis: "
                                                           f"{', '.join(self._AXIS_SECTIONS)})")
            data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
            for key, value in overlay.items():
                if isinstance(value, dict) and isinstance(data.get(key), dict) and key not in ("reference", "axis"):
                    data[key] = {**data[key], **value}
                else:
                    data[key] = value
            try:
                out[name] = from_mapping(data, source=self.source)
            except ConfigError as exc:
                msg = str(exc)[len(exc.field) + 2:] if str(exc).startswith(f"{exc.field}: ") else str(exc)
                raise ConfigError(f"axes.{name}.{exc.field}", msg) from None
        return out

    @property
    def defaulted(self) -> tuple[str, ...]:
        """The sections of :data:`DEFAULTED_SECTIONS` the loaded file did not give (built-in defaults)."""
        return self._defaulted

    def stuck_torque(self) -> float:
        """``[safety] stuck_torque``, or the simulated (sim or emulated) plant's breakaway torque when
        friction is configured."""
        if self.safety.stuck_torque is not None:
            return float(self.safety.stuck_torque)
        fr = (self.backend.options().get("friction") if self.backend.name == "sim"
              else (self.emulator or {}).get("friction") if self.backend.emulate else None)
        if not fr:
            return 0.0
        from rt_ident.axis.friction import Friction

        f = Friction.from_mapping(fr, where="plant.friction")
        return float((f.Fs1 or 0.0) + (f.Fs2 or 0.0))

    def axis_params(self) -> AxisParams:
        return AxisParams.from_mapping(self.axis, where="axis") if self.axis else thomson_x()

    @model_validator(mode="after")
    def _host_picture_consistent(self) -> RunConfig:
        """What cannot all be true of one axis, refused before anything starts: the model's lead and the
        lead the backend converts the scale with; positions in the window beyond the 32-bit counts of
        the position objects (CiA 402 0x6064 / 0x60E4, the board's frames); a scale that cannot resolve
        the window."""
        opts = self.backend.options()
        a_lead, b_lead = (self.axis or {}).get("lead"), opts.get("lead")
        if isinstance(a_lead, (int, float)) and isinstance(b_lead, (int, float)) and not isinstance(b_lead, bool) \
                and abs(a_lead - b_lead) > 1e-9 * max(abs(a_lead), abs(b_lead)):
            raise ValueError(f"axis.lead: {a_lead:g} m/rad differs from backend.lead {b_lead:g}: the model and the "
                             "scale's conversion would disagree; set both to the screw's lead (rt-ident commission "
                             "measures it)")
        edge = max(abs(w) for w in self.safety.window)
        res, cpr = opts.get("scale_resolution"), opts.get("counts_per_rev")
        lead = b_lead if isinstance(b_lead, (int, float)) else (self.axis or {}).get("lead", 7.96e-4)
        if isinstance(res, (int, float)) and res > 0:
            if edge / res > 2**31 - 1:
                raise ValueError(f"backend.scale_resolution: {res:g} m per count puts the window's edge at "
                                 f"{edge / res:.3g} counts, beyond the 32-bit position values; check it")
            if res > (self.safety.window[1] - self.safety.window[0]) / 100:
                raise ValueError(f"backend.scale_resolution: {res:g} m per count resolves fewer than 100 steps of "
                                 f"safety.window; check it (m per count, e.g. 1e-7 for 0.1 um)")
        if isinstance(cpr, int) and cpr > 0 and isinstance(lead, (int, float)) and lead > 0 \
                and edge / lead * cpr / (2 * math.pi) > 2**31 - 1:
            raise ValueError(f"backend.counts_per_rev: {cpr} counts/rev with lead {lead:g} m/rad puts the window's "
                             "edge beyond the 32-bit motor position (0x6064); check counts_per_rev and lead")
        return self

    @model_validator(mode="before")
    @classmethod
    def _plant_to_device(cls, data: Any) -> Any:
        """``[plant.friction]`` and ``[plant.actual]`` describe the simulated device: they go to the sim
        backend as its ``friction`` / ``x0`` options (an explicit ``[backend]`` key wins), or to an
        emulated device's ``[emulator]`` table; a real device refuses them."""
        if not isinstance(data, dict) or not isinstance(data.get("plant"), dict):
            return data
        plant = data["plant"]
        moved: dict[str, Any] = {}
        if plant.get("friction") is not None:
            moved["friction"] = dict(plant["friction"]) if isinstance(plant["friction"], dict) else plant["friction"]
        actual = plant.get("actual")
        if isinstance(actual, dict):
            if "x0" in actual:
                moved["x0"] = actual["x0"]
            truth = {k: v for k, v in actual.items() if k != "x0"}
            if truth:
                moved["actual"] = truth
        if not moved:
            return data
        if not isinstance(data.get("backend") or {}, dict) or not isinstance(data.get("emulator") or {}, dict):
            return data                              # not tables: their own field errors
        backend = dict(data.get("backend") or {})
        if backend.get("name", "sim") == "sim":
            return {**data, "backend": {**moved, **backend}}
        if backend.get("emulate"):                 # the emulated drive or board simulates it
            return {**data, "emulator": {**moved, **dict(data.get("emulator") or {})}}
        what = "friction" if "friction" in moved else "actual"
        raise ValueError(f"plant.{what}: describes a simulated device; a real {backend.get('name')!r} device has "
                         "its own (only the sim backend and the emulated devices take it)")



def from_mapping(data: dict[str, Any], *, source: str | None = None) -> RunConfig:
    if not isinstance(data, dict):
        raise ConfigError("config", f"must be a table of sections, got {type(data).__name__}")
    try:
        cfg = RunConfig.model_validate({**data, "source": source})
    except ValidationError as exc:
        first, msg = validation_error(RunConfig, exc)
        field = ".".join(str(p) for p in first["loc"])
        head, sep, rest = msg.partition(": ")
        if sep and head.replace(".", "").replace("_", "").isalnum():   # a check across fields names its field
            field, msg = (f"{field}.{head}" if field else head), rest
        raise ConfigError(field or "config", msg) from None
    cfg.axis_params()  # validate physical values now, naming the field
    if cfg.axes:
        cfg.axis_configs()   # every axis validated now, errors naming axes.NAME...
    return cfg


def load(path: str | Path | None = None, **overrides: Any) -> RunConfig:
    """Load a run configuration (default: ``configs/sim.toml`` if shipped, else built-in defaults).

    A relative path that does not exist is also looked up in the shipped ``configs/`` folder; a relative
    file the config names is looked up beside it first (:func:`_files_beside`).
    """
    if path is None:
        candidate = CONFIG_DIR / "sim.toml"
        data = tomllib.loads(candidate.read_text()) if candidate.is_file() else {}
        source = str(candidate) if candidate.is_file() else "<defaults>"
    else:
        p = Path(path)
        if not p.is_file() and not p.is_absolute() and (CONFIG_DIR / p.name).is_file():
            p = CONFIG_DIR / p.name
        if p.is_dir():
            raise ConfigError(str(path), "is a folder; give a config file (TOML) in it, e.g. configs/sim.toml")
        if not p.is_file():
            raise ConfigError(str(path), "config file not found")
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8-sig"))     # -sig: a BOM as Windows editors write it
        except UnicodeDecodeError as exc:
            raise ConfigError(str(path), f"not a text file (byte 0x{exc.object[exc.start]:02x} at offset "
                                         f"{exc.start} is not UTF-8); a config is TOML text") from None
        except OSError as exc:
            raise ConfigError(str(path), f"cannot read it: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(str(path), f"not valid TOML: {exc}") from None
        if not data:
            raise ConfigError(str(path), "config is empty (no section, no key); give at least [backend], "
                                         "or run without a config for the built-in defaults")
        _files_beside(data, p.parent)
        source = str(p)
    for dotted, value in overrides.items():
        if value is None:
            continue
        section, _, key = dotted.partition(".")
        if not isinstance(data.setdefault(section, {}), dict):
            raise ConfigError(section, f"must be a table ([{section}]), got {type(data[section]).__name__}")
        data[section][key] = value
    cfg = from_mapping(data, source=source)
    if path is not None:
        cfg._defaulted = defaulted_sections(data)
    return cfg


def _files_beside(data: dict[str, Any], folder: Path) -> None:
    """A relative file a config names (a drive's EDS) is the one beside the config file, where there is
    one: the folder the command runs in and the shipped ``configs/`` are looked in after it."""
    tables = [data] + [a for a in (data.get("axes") or {}).values() if isinstance(a, dict)] \
        if isinstance(data.get("axes"), dict) else [data]
    for table in tables:
        for section in ("backend", "emulator"):
            sec = table.get(section)
            if not isinstance(sec, dict):
                continue
            name = sec.get("eds")
            if isinstance(name, str) and name and not Path(name).is_absolute() and (folder / name).is_file():
                sec["eds"] = str((folder / name).resolve())


#: Sections whose absence from a config file is reported (the run then drives the built-in sim
#: plant, the THOMSON X axis's values, or the default travel window).
DEFAULTED_SECTIONS = ("axis", "backend", "safety")


def defaulted_sections(data: dict[str, Any]) -> tuple[str, ...]:
    """The sections of :data:`DEFAULTED_SECTIONS` that ``data`` gives neither at the top level nor
    in every ``[axes.NAME]`` table."""
    axes = [a for a in (data.get("axes") or {}).values() if isinstance(a, dict)] \
        if isinstance(data.get("axes"), dict) else []
    return tuple(s for s in DEFAULTED_SECTIONS
                 if s not in data and not (axes and all(s in a for a in axes)))

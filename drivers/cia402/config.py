"""Options of the ``canopen`` backend, validated, and the CAN bus budget check.

The ``[backend]`` table of a run configuration (``name`` and ``emulate`` are
accepted and ignored). Every error is a :class:`~rt_ident.errors.ConfigError`
naming the field, e.g. ``backend.sync_rate_hz: 10000 Hz needs ...``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from drivers.cia402.bus import check_interface
from drivers.cia402.profile import frame_bits
from rt_ident.axis.params import CONFIG_DIR
from rt_ident.errors import ConfigError, validation_error

#: Data bytes of the PDOs this backend maps (see drivers.cia402.drive): RPDO1 = controlword (2) +
#: target torque (2); TPDO1 = statusword (2) + position actual (4) + torque actual (2);
#: TPDO2 = the 32-bit table scale object (4). The SYNC carries no counter (0 bytes).
SYNC_BYTES = 0
RPDO_BYTES = (4,)
TPDO_BYTES = (8, 4)
HEARTBEAT_BYTES = 1


class Cia402Config(BaseModel):
    """Options of :class:`drivers.cia402.drive.Cia402Backend` (units in the comments)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str | None = None                      # registry name, ignored here
    emulate: bool = False                           # read by the loop, ignored here
    # python-can bus (python-can's own option names)
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = Field(1_000_000, gt=0, le=1_000_000)    # bit/s (CAN 2.0: at most 1 Mbit/s)
    port: int | None = Field(None, ge=1, le=65535)      # udp_multicast only
    bus_options: dict[str, Any] = Field(default_factory=dict)  # further can.Bus keyword arguments
    # CANopen
    node_id: int = Field(..., ge=1, le=127)
    master_node_id: int = Field(127, ge=1, le=127)  # node id of this host's heartbeat (0x700 + id)
    eds: str = "cia402_generic.eds"                  # path; a bare relative name is also looked up in configs/
    sync_rate_hz: float = Field(1000.0, ge=100)     # SYNC rate = sample rate; at least one per 10 ms (the slowest tick)
    max_bus_load: float = Field(0.8, gt=0, le=0.95)  # refuse rates whose worst-case load exceeds this
    # us from a SYNC until every drive's answers are in; the host reads then. None: the answers' worst-case
    # time on the bus (answer_time) plus ANSWER_ALLOWANCE_S for the drives and the host's receive path
    answer_us: float | None = Field(None, gt=0, le=100_000)
    # torque
    torque_limit: float = Field(..., gt=0)          # N m, host-side clamp (drivers.base)
    rated_torque: float | None = Field(None, gt=0)  # N m; None: read 0x6076 (mN m) from the drive
    max_torque_permille: int | None = Field(None, ge=1, le=65535)  # 0x6072; None: from torque_limit
    # positions
    counts_per_rev: int = Field(..., gt=0)          # motor encoder (0x6064) counts per revolution
    scale_index: int = Field(0x60E4, ge=0x1000, le=0xFFFF)  # table linear scale object
    scale_subindex: int = Field(1, ge=0, le=255)
    scale_resolution: float = Field(..., ge=1e-12, le=1e-3)  # m per scale count
    lead: float = Field(7.96e-4, gt=0)              # m/rad: theta2 = x / lead
    # polarity, applied by drivers.base in the host's convention (see Cia402Backend for 0x607E)
    torque_sign: Literal[1, -1] = 1                 # -1: a positive 0x6071 turns the motor backwards
    motor_encoder_sign: Literal[1, -1] = 1          # -1: 0x6064 counts backwards
    scale_sign: Literal[1, -1] = 1                  # -1: the table scale counts backwards
    # supervision
    heartbeat_ms: int = Field(100, ge=1, le=65535)  # producer time of the drive (0x1017) and of this host
    heartbeat_consumer_ms: int | None = Field(None, ge=1, le=65535)  # None: 3 x heartbeat_ms
    # RPDO1's deadline (0x1400:05, ms; 0: off): a drive that gets no torque for this long faults and takes
    # the torque off (EMCY 0x8250), where without it a stalled host's last torque stays until the
    # heartbeat consumer trips. A drive without the object: a warning (an error if set here explicitly)
    rpdo_deadline_ms: int = Field(20, ge=0, le=65535)
    sdo_timeout: float = Field(0.5, gt=0, le=10)    # s per SDO request
    stale_limit: int = Field(10, ge=1)              # consecutive samples without fresh TPDO data tolerated
    stuck_torque_min: float | None = Field(None, ge=0)  # N m applied + frozen encoder = stuck; None: 5 %
    #                                                       of torque_limit
    startup_timeout: float = Field(2.0, gt=0, le=60)  # s from NMT OPERATIONAL to OPERATION ENABLED
    stop_timeout: float = Field(0.2, gt=0, le=5)    # s per safe-stop step (quick stop, disable)
    # the SYNC sender thread waits for the GIL at each deadline for up to the interpreter's switch
    # interval; while active the backend lowers it to this (restored when the SYNCs stop); None: untouched
    gil_switch_interval_us: float | None = Field(50.0, ge=5, le=5000)

    @field_validator("torque_sign", "motor_encoder_sign", "scale_sign", mode="before")
    @classmethod
    def _not_bool(cls, v: Any) -> Any:
        if isinstance(v, bool):                       # true == 1 for the Literal check
            raise ValueError(f"must be 1 or -1, got {v!r}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Cia402Config:
        if not math.isfinite(self.torque_limit):
            raise ValueError("torque_limit must be finite for a CANopen drive")
        if self.scale_index == 0x60E4 and self.scale_subindex == 0:
            raise ValueError("scale_subindex 0 of 0x60E4 is the entry count, not a position")
        if self.heartbeat_consumer_ms is not None and self.heartbeat_consumer_ms <= self.heartbeat_ms:
            raise ValueError("heartbeat_consumer_ms must exceed heartbeat_ms")
        if self.answer_us is not None and self.answer_us * 1e-6 >= 1.0 / self.sync_rate_hz:
            raise ValueError(f"answer_us {self.answer_us:g} is not shorter than the SYNC period "
                             f"({1e6 / self.sync_rate_hz:g} us): answers that come after the next SYNC leave no "
                             f"time to plan its torque; lower sync_rate_hz")
        return self

    # -- derived values ------------------------------------------------------------------
    @property
    def consumer_ms(self) -> int:
        return self.heartbeat_consumer_ms or 3 * self.heartbeat_ms

    @property
    def sample_period(self) -> float:
        return 1.0 / self.sync_rate_hz

    @property
    def stuck_torque(self) -> float:
        return self.stuck_torque_min if self.stuck_torque_min is not None else 0.05 * self.torque_limit

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus``."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel, "bitrate": self.bitrate}
        if self.port is not None:
            kw["port"] = self.port
        kw.update(self.bus_options)
        return kw

    def eds_path(self) -> Path:
        """The EDS file (:func:`find_eds`)."""
        return find_eds(self.eds, "backend.eds")


def find_eds(name: str, key: str) -> Path:
    """The EDS file ``name``; a relative path that does not exist is looked up in ``configs/`` (the config's
    own folder came first, when it was loaded). Missing: a :class:`ConfigError` naming ``key``."""
    p = Path(name)
    if not p.is_file() and not p.is_absolute() and (CONFIG_DIR / p).is_file():
        p = CONFIG_DIR / p
    if not p.is_file():
        raise ConfigError(key, f"EDS file not found: {name} (looked in {Path.cwd()} and {CONFIG_DIR}; a relative "
                               "path is looked for beside the config file first)")
    return p


@dataclass(frozen=True)
class BusBudget:
    """Worst-case CAN load of the cyclic traffic at a SYNC rate."""

    frames_per_sync: int
    bits_per_sync: int          # worst case, bit stuffing included
    background_bps: float       # heartbeats
    required_bps: float
    bitrate: int

    @property
    def load(self) -> float:
        return self.required_bps / self.bitrate

    def max_rate(self, max_load: float) -> float:
        return max(0.0, (max_load * self.bitrate - self.background_bps) / self.bits_per_sync)


def bus_budget(sync_rate_hz: float, bitrate: int, heartbeat_ms: int = 100, drives: int = 1) -> BusBudget:
    """Load of one SYNC plus RPDO1 + TPDO1 + TPDO2 of each of ``drives`` drives per SYNC, and the
    heartbeats of the host and of each drive every ``heartbeat_ms``."""
    sizes = (SYNC_BYTES, *(RPDO_BYTES + TPDO_BYTES) * drives)
    bits = sum(frame_bits(n) for n in sizes)
    background = (1 + drives) * frame_bits(HEARTBEAT_BYTES) * 1000.0 / heartbeat_ms
    return BusBudget(len(sizes), bits, background, bits * sync_rate_hz + background, bitrate)


#: a drive's own time to answer a SYNC, and the host's receive path, on top of the answers' bits on the bus
ANSWER_ALLOWANCE_S = 150e-6


def answer_time(cfg: Cia402Config, drives: int = 1) -> float:
    """Seconds from a SYNC until the TPDOs of ``drives`` drives answering it are in the host (``answer_us``,
    or the SYNC's and the answers' worst-case bits at the bit rate plus :data:`ANSWER_ALLOWANCE_S`)."""
    if cfg.answer_us is not None:
        return cfg.answer_us * 1e-6
    bits = frame_bits(SYNC_BYTES) + drives * sum(frame_bits(n) for n in TPDO_BYTES)
    return bits / cfg.bitrate + ANSWER_ALLOWANCE_S


def check_shared_bus(cfgs: list[Cia402Config], where: str = "backend") -> BusBudget:
    """Several drives on one bus (one SYNC for all): same bus settings, distinct node ids, and a
    SYNC rate the bit rate carries with every drive's PDOs counted."""
    first = cfgs[0]
    for cfg in cfgs[1:]:
        for field in ("interface", "channel", "port", "bitrate", "sync_rate_hz", "heartbeat_ms", "master_node_id"):
            if getattr(cfg, field) != getattr(first, field):
                raise ConfigError(f"{where}.{field}", f"drives on one bus share it: node {first.node_id} has "
                                  f"{getattr(first, field)!r}, node {cfg.node_id} {getattr(cfg, field)!r}")
    ids = [c.node_id for c in cfgs]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{where}.node_id", f"each drive on a bus needs its own node id, got {ids}")
    n = len(cfgs)
    b = bus_budget(first.sync_rate_hz, first.bitrate, first.heartbeat_ms, drives=n)
    limit = min(c.max_bus_load for c in cfgs)
    if b.load > limit:
        one = bus_budget(first.sync_rate_hz, first.bitrate, first.heartbeat_ms).max_rate(limit)
        raise ConfigError(
            f"{where}.sync_rate_hz",
            f"{first.sync_rate_hz:g} Hz for {n} drives on one bus needs {b.required_bps:,.0f} bit/s = "
            f"{100 * b.load:.1f} % of the {first.bitrate:,} bit/s bus ({b.frames_per_sync} frames per SYNC, "
            f"{b.bits_per_sync} bits worst case, plus heartbeats); the limit is {100 * limit:.0f} % "
            f"(max_bus_load): at most {b.max_rate(limit):.0f} Hz for {n} drives ({one:.0f} Hz for one)")
    return b


def check_bus_budget(cfg: Cia402Config) -> BusBudget:
    """Refuse a SYNC rate the bit rate cannot carry (worst-case stuffing, with the ``max_bus_load`` margin)."""
    b = bus_budget(cfg.sync_rate_hz, cfg.bitrate, cfg.heartbeat_ms)
    if b.load > cfg.max_bus_load:
        raise ConfigError(
            "backend.sync_rate_hz",
            f"{cfg.sync_rate_hz:g} Hz needs {b.required_bps:,.0f} bit/s = {100 * b.load:.1f} % of the "
            f"{cfg.bitrate:,} bit/s bus ({b.frames_per_sync} frames per SYNC, {b.bits_per_sync} bits worst "
            f"case with bit stuffing, plus heartbeats); the limit is {100 * cfg.max_bus_load:.0f} % "
            f"(max_bus_load), i.e. at most {b.max_rate(cfg.max_bus_load):.0f} Hz at this bit rate")
    return b


def validate(config: Mapping[str, Any] | None) -> Cia402Config:
    """Validate the ``[backend]`` options and the bus budget; errors name the field."""
    try:
        cfg = Cia402Config.model_validate(dict(config or {}))
    except ValidationError as exc:
        err, msg = validation_error(Cia402Config, exc)
        loc = ".".join(str(p) for p in err["loc"] if not isinstance(p, int))
        raise ConfigError(f"backend.{loc}" if loc else "backend", msg) from None
    rated = cfg.rated_torque
    if rated and cfg.torque_limit > 32.767 * rated:
        raise ConfigError("backend.torque_limit", f"{cfg.torque_limit} N m exceeds the int16 per-mille range "
                          f"of 0x6071 (32.767 x rated_torque = {32.767 * rated:g} N m)")
    check_bus_budget(cfg)
    check_interface(cfg.interface)
    return cfg


__all__ = ["Cia402Config", "BusBudget", "bus_budget", "check_bus_budget", "check_shared_bus", "validate"]

"""The serial encoder board's configuration: the ``[backend]`` keys and the emulator's ``[emulator]`` keys.

Shared by the backend (:mod:`drivers.encoder_board.board`) and the emulated board
(:mod:`drivers.encoder_board.emulator`), so that neither imports the other for it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from drivers.base import Travel
from drivers.encoder_board import protocol as sp
from rt_ident.errors import ConfigError, validation_error

_LINK_MARGIN = 1.1   # the link must carry 10 % more than the frame stream
#: The board's current range [A]: it reports the motor current as an int16 in mA (docs/serial-protocol.md),
#: so a torque beyond this x torque_constant can be neither measured nor, by the board, driven.
MAX_CURRENT_A = 32.767

Sign = Literal[1, -1]


class SerialBoardConfig(BaseModel):
    """The ``[backend]`` keys of the serial board (units in the field comments)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    name: str | None = None                  # registry name, ignored here
    port: str | None = None                  # device path (a pyserial URL only with allow_url); required unless emulate
    allow_url: bool = False                     # accept pyserial URLs (socket://, rfc2217://, spy://...) as port
    baudrate: int = Field(12_000_000, gt=0)     # 8N1; ignored by USB CDC devices but checked
    sample_rate_hz: float = Field(20000.0, ge=100, le=200_000)  # at least a sample per 10 ms (the slowest tick)
    counts_per_rev: int = Field(131072, gt=0)   # motor encoder counts per revolution
    scale_resolution: float = Field(1e-7, ge=1e-12, le=1e-3)  # linear scale [m/count]
    lead: float = Field(7.96e-4, gt=0)          # spindle lead [m/rad]: theta2 = x / lead
    torque_constant: float = Field(0.1, gt=0)   # [N m/A]: measured torque = kt * current
    torque_limit: float = Field(1.0, gt=0)      # [N m] clamp on the host; at most MAX_CURRENT_A x torque_constant
    # polarity, applied by drivers.base.Backend: -1 = the motor is wired / the motor encoder / the scale
    # counts the other way (the host negates torque / theta1 / theta2)
    torque_sign: Sign = 1
    motor_encoder_sign: Sign = 1
    scale_sign: Sign = 1
    read_timeout: float = Field(0.05, gt=0)     # [s] without a valid frame -> DeviceTimeout
    startup_timeout: float = Field(1.0, gt=0)   # [s] for the first frame (open) / enable ack
    info_timeout: float = Field(0.1, gt=0)      # [s] for the INFO answer at open (none: identity not available)
    poll_timeout: float = Field(0.0002, ge=0)   # [s] a read() looks this long for a first byte / behind a backlog
    write_timeout: float = Field(0.05, gt=0)    # [s] per write before DeviceTimeout
    heartbeat_period: float = Field(0.02, gt=0)  # [s] heartbeat if nothing else was sent
    stop_timeout: float = Field(0.1, ge=0)      # [s] safe_stop waits this long for the disable ack
    crc_storm_limit: int = Field(20, ge=0)      # CRC + header errors per read above which ProtocolError
    garbage_storm_limit: int = Field(4096, ge=0)  # discarded bytes per read above which ProtocolError
    encoder_mismatch_limit: float | None = Field(0.2, gt=0)  # [rad] |twist drift|; None: off
    plan_capacity: int = Field(4096, ge=1)      # samples the board can queue ahead
    emulate: bool = False                       # start an EmulatedBoard on a pty in open()
    emulator: dict[str, Any] = Field(default_factory=dict)  # EmulatorConfig keys

    @model_validator(mode="after")
    def _checks(self) -> SerialBoardConfig:
        if self.port is None and not self.emulate:
            raise ValueError("port: required unless emulate = true")
        if self.port is not None and "://" in self.port and not self.allow_url:
            raise ValueError(f"port: {self.port!r} is a pyserial URL (it can open network sockets or write files); "
                             "set allow_url = true to use it")
        need = self.sample_rate_hz * sp.DATA_FRAME_SIZE * 10 * _LINK_MARGIN
        if self.baudrate < need:
            raise ValueError(f"baudrate: {self.baudrate} baud carries {self.baudrate / 300:.0f} frames/s; "
                             f"sample_rate_hz={self.sample_rate_hz:g} needs >= {need:.3g} baud")
        rating = MAX_CURRENT_A * self.torque_constant
        if self.torque_limit > rating:
            raise ValueError(f"torque_limit: {self.torque_limit:g} N m exceeds the board's rating, {MAX_CURRENT_A:g} A "
                             f"(its current range) x torque_constant {self.torque_constant:g} N m/A = {rating:g} N m")
        return self


def _validate(model: type[BaseModel], data: Mapping[str, Any], where: str) -> Any:
    try:
        return model.model_validate(dict(data))
    except ValidationError as exc:
        err, msg = validation_error(model, exc)
        loc = ".".join(str(p) for p in err["loc"])
        head, sep, rest = msg.partition(": ")
        if sep and head.isidentifier():        # a check that names its field (or a key below it) itself
            loc, msg = (f"{loc}.{head}" if loc else head), rest
        raise ConfigError(f"{where}.{loc}" if loc else where, msg) from None


def parse_serial(data: Mapping[str, Any], where: str = "backend") -> SerialBoardConfig:
    """Validate a ``[backend]`` mapping; errors are ConfigError naming ``backend.<field>``."""
    return _validate(SerialBoardConfig, data, where)


class BoardTruth(BaseModel):
    """``[emulator] actual``: the emulated device as it truly is where it differs from what the host is
    told (``[backend]``); a key left out is what the host is told. From ``[plant.actual]`` of a run."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    torque_sign: Sign | None = None           # -1: the motor is wired the other way
    motor_encoder_sign: Sign | None = None    # -1: the motor encoder counts the other way
    scale_sign: Sign | None = None            # -1: the linear scale counts the other way
    counts_per_rev: int | None = Field(None, ge=1)                   # the encoder's true counts per rev
    scale_resolution: float | None = Field(None, ge=1e-12, le=1e-3)  # [m] per scale count, truly
    lead: float | None = Field(None, gt=0, le=0.1)                   # [m/rad] the screw truly moves the table
    torque_scale: float | None = Field(None, gt=0, le=100)           # physical torque per N m the board drives


class EmulatorConfig(BaseModel):
    """The ``[emulator]`` keys of the emulated board (faults may also be changed at run time)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    seed: int = Field(0, ge=0)
    hold: bool = False                         # a drive-side position loop holding theta1 (identification-only runs)
    heartbeat_timeout: float = Field(0.1, gt=0)  # [s] without a host frame -> disable + fault
    burst_period: float = Field(0.001, gt=0, le=0.1)  # [s] between bursts of frames
    angle_noise: float = Field(0.0, ge=0)      # [rad] rms before quantization
    torque_meas_noise: float = Field(0.0, ge=0)  # [N m] rms on the reported current
    torque_process_noise: float = Field(0.0, ge=0)  # [N m] rms on the applied torque
    travel: Travel | None = None  # [m] table travel; outside -> limit-switch fault
    tx_buffer: int = Field(65536, ge=sp.DATA_FRAME_SIZE)  # [bytes] transmit FIFO; full -> frames dropped
    seq0: int = Field(0, ge=0, lt=2**32)       # first sequence number (test wrap-around)
    t0_us: int = Field(0, ge=0, lt=2**32)      # first time stamp [us]
    drop_probability: float = Field(0.0, ge=0, le=1)
    corrupt_probability: float = Field(0.0, ge=0, le=1)
    garbage_probability: float = Field(0.0, ge=0, le=1)
    stuck_encoder: bool = False
    silent: bool = False
    deaf: bool = False
    friction: dict[str, Any] | None = None  # rt_ident.axis.friction.Friction keys or preset = "thomson"
    x0: float = Field(0.0, ge=-10.0, le=10.0, allow_inf_nan=False)   # [m] where the table truly starts (at rest)
    actual: BoardTruth = Field(default_factory=BoardTruth)   # the true device (BoardTruth)
    answer_info: bool = True                   # false: INFO_REQUEST ignored (as by a version 1 board)
    serial_number: int = Field(1, ge=0, lt=2**32)   # in INFO (0: a board without one; another unit: another)

    @field_validator("actual", mode="before")
    @classmethod
    def _actual_keys(cls, v: Any) -> Any:
        if isinstance(v, Mapping):
            if "rated_torque" in v:
                raise ValueError("rated_torque: the serial board has no rated torque (a CiA 402 drive's 0x6076); "
                                 "use torque_scale for a torque that differs from what the board believes")
            for k in v:
                if k not in BoardTruth.model_fields:
                    raise ValueError(f"{k}: unknown key; valid: {', '.join(BoardTruth.model_fields)}")
        return v


def parse_emulator(data: Mapping[str, Any], where: str = "emulator") -> EmulatorConfig:
    """Validate ``[emulator]``; errors are ConfigError naming ``<where>.<field>``."""
    return _validate(EmulatorConfig, data, where)

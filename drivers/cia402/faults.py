"""Faults the emulated CiA 402 drive injects (the ``[emulator.faults]`` table).

Shared by the drive (:mod:`drivers.cia402.emulated_drive`, which applies them) and its
launcher (:mod:`drivers.cia402.emulator`, which reads them from a run configuration).
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from rt_ident.errors import ConfigError

# COB-IDs no predefined-connection-set service uses (0x100 is TIME, 0x080-0x0FF SYNC/EMCY)
_GARBAGE_IDS = tuple(range(0x101, 0x180)) + tuple(range(0x500, 0x580))
_INT_FAULTS = frozenset({"drop_tpdo_every", "tpdo_faults_from_sample", "corrupt_tpdo_every", "emcy_at_sample",
                         "emcy_code", "stuck_encoder_at_sample", "garbage_frames_per_sync", "restart_at_sample",
                         "derate_at_sample", "derate_permille", "warning_at_sample", "seed"})
_BOOL_FAULTS = frozenset({"main_power_off", "local_control", "emcy_off"})


@dataclass(frozen=True)
class FaultConfig:
    """Faults injected by the emulated drive. Sample numbers count SYNCs in OPERATION ENABLED (from 1).

    tpdo_faults_from_sample: the three TPDO faults below start at this sample (so that the
        master can see OPERATION ENABLED first).
    drop_tpdo_every: all TPDOs of every n-th sample are not sent (0: never).
    delay_tpdo_s: TPDOs leave this much later.
    corrupt_tpdo_every: every n-th sample's TPDOs lose their last 2 bytes (wrong DLC: the only
        corruption a receiver sees; CAN's CRC rejects bit errors).
    emcy_at_sample / emcy_code: the drive faults (EMCY, FAULT state, torque 0) at that sample (once).
    heartbeat_stop_at_s: the drive stops its heartbeat this long after first OPERATION ENABLED.
    stuck_encoder_at_sample: the motor encoder 0x6064 freezes from that sample on.
    restart_at_sample: the drive restarts at that sample (a dip of its logic supply): power stage off, a
        boot-up message, then PRE-OPERATIONAL with no PDOs, as a drive comes up.
    derate_at_sample / derate_permille: from that sample the drive limits its torque to derate_permille of
        its rated torque (a thermal derating), below 0x6072, and reports statusword bit 11 (internal limit
        active) on every sample it limits, as it does for 0x6072 itself.
    garbage_frames_per_sync: random frames on COB-IDs no node uses, after each SYNC.
    main_power_off: the power stage has no main voltage (main power off, E-stop or STO): voltage enabled
        (statusword bit 4) is off and the drive does not switch on; it stays READY TO SWITCH ON.
    warning_at_sample: from that sample on the drive reports a warning (statusword bit 7), as for a motor
        running warm.
    emcy_off: the drive sends no EMCY (its 0x1014 bit 31 set, as some drives ship): a fault shows only in its
        statusword and its error code 0x603F.
    local_control: the drive is under local control (its panel or the vendor's software): remote
        (statusword bit 9) is off and it ignores the bus's controlword.
    """

    tpdo_faults_from_sample: int = 1
    drop_tpdo_every: int = 0
    delay_tpdo_s: float = 0.0
    corrupt_tpdo_every: int = 0
    emcy_at_sample: int | None = None
    emcy_code: int = 0x2310
    heartbeat_stop_at_s: float | None = None
    stuck_encoder_at_sample: int | None = None
    restart_at_sample: int | None = None
    derate_at_sample: int | None = None
    derate_permille: int = 100
    warning_at_sample: int | None = None
    garbage_frames_per_sync: int = 0
    main_power_off: bool = False
    local_control: bool = False
    emcy_off: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None and f.default is None:
                continue
            if f.name in _BOOL_FAULTS:
                if not isinstance(v, bool):
                    raise ConfigError(f"emulator.faults.{f.name}", f"must be true or false, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"emulator.faults.{f.name}", f"must be a finite number >= 0, got {v!r}")
            if f.name in _INT_FAULTS and not isinstance(v, int):
                raise ConfigError(f"emulator.faults.{f.name}", f"must be an integer, got {v!r}")
        if not 0 < self.emcy_code <= 0xFFFF:
            raise ConfigError("emulator.faults.emcy_code", f"must be 0x0001..0xFFFF, got {self.emcy_code!r}")

    # ----- applied by the drive (drivers.cia402.emulated_drive) ---------------------------------
    def tpdo_frames(self, frames: list[tuple[int, bytes]], sample: int, enabled: bool) -> list[tuple[int, bytes]]:
        """The ``(cob, data)`` TPDO frames of ``sample`` after the drop and corrupt faults."""
        if not enabled or sample < self.tpdo_faults_from_sample:
            return frames
        if self.drop_tpdo_every and sample % self.drop_tpdo_every == 0:
            return []
        if self.corrupt_tpdo_every and sample % self.corrupt_tpdo_every == 0:
            return [(cob, data[:-2]) for cob, data in frames]
        return frames

    def tpdo_delay(self, sample: int, enabled: bool) -> float:
        """How much later than normal the TPDOs of ``sample`` leave [s]."""
        return self.delay_tpdo_s if enabled and sample >= self.tpdo_faults_from_sample else 0.0

    def garbage(self, rng: random.Random) -> list[tuple[int, bytes]]:
        """Random frames for one SYNC on COB-IDs no predefined-connection-set service uses."""
        return [(rng.choice(_GARBAGE_IDS), bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 8))))
                for _ in range(self.garbage_frames_per_sync)]

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None) -> FaultConfig:
        data = dict(data or {})
        known = {f.name for f in fields(cls)}
        for key in data:
            if key not in known:
                raise ConfigError(f"emulator.faults.{key}", f"unknown fault (expected {sorted(known)})")
        return cls(**data)

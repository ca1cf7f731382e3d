"""Configuration, fault injection and start-up of the emulated CiA 402 drive.

* :class:`FaultConfig` - faults the emulated drive injects (``[emulator.faults]``);
* :func:`start_emulator_for` - build and start an :class:`~drivers.emulated_drive.EmulatedCia402Drive`
  from a run configuration (the ``[backend]``, ``[emulator]`` and ``[axis]`` tables), as the
  loop does when ``[backend] emulate = true``;
* :func:`main` - ``python -m drivers.emulated_drive --config configs/canopen-virtual.toml --port N``
  runs the drive alone, reachable from other processes on ``udp_multicast`` (the loop starts
  it in a child process itself: :class:`rt_ident.emulation.EmulatorProcess`).
"""

from __future__ import annotations

import argparse
import logging
import math
import random
import signal
import sys
import threading
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Mapping, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rt_ident.errors import ConfigError
from rt_ident.params import CONFIG_DIR, AxisParams, thomson_x

if TYPE_CHECKING:
    from drivers.emulated_drive import EmulatedCia402Drive

log = logging.getLogger(__name__)

# COB-IDs no predefined-connection-set service uses (0x100 is TIME, 0x080-0x0FF SYNC/EMCY)
_GARBAGE_IDS = tuple(range(0x101, 0x180)) + tuple(range(0x500, 0x580))
_INT_FAULTS = frozenset({"drop_tpdo_every", "tpdo_faults_from_sample", "corrupt_tpdo_every", "emcy_at_sample",
                         "emcy_code", "stuck_encoder_at_sample", "garbage_frames_per_sync", "seed"})


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
    garbage_frames_per_sync: random frames on COB-IDs no node uses, after each SYNC.
    """

    tpdo_faults_from_sample: int = 1
    drop_tpdo_every: int = 0
    delay_tpdo_s: float = 0.0
    corrupt_tpdo_every: int = 0
    emcy_at_sample: Optional[int] = None
    emcy_code: int = 0x2310
    heartbeat_stop_at_s: Optional[float] = None
    stuck_encoder_at_sample: Optional[int] = None
    garbage_frames_per_sync: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None and f.default is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"emulator.faults.{f.name}", f"must be a finite number >= 0, got {v!r}")
            if f.name in _INT_FAULTS and not isinstance(v, int):
                raise ConfigError(f"emulator.faults.{f.name}", f"must be an integer, got {v!r}")
        if not 0 < self.emcy_code <= 0xFFFF:
            raise ConfigError("emulator.faults.emcy_code", f"must be 0x0001..0xFFFF, got {self.emcy_code!r}")

    # ----- applied by the drive (drivers.emulated_drive) ---------------------------------
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
    def from_mapping(cls, data: Mapping[str, Any] | None) -> "FaultConfig":
        data = dict(data or {})
        known = {f.name for f in fields(cls)}
        for key in data:
            if key not in known:
                raise ConfigError(f"emulator.faults.{key}", f"unknown fault (expected {sorted(known)})")
        return cls(**data)


class EmulatorConfig(BaseModel):
    """The ``[emulator]`` table (plant and drive options not shared with the backend)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    eds: Optional[str] = None                      # the drive's own EDS; None: the backend's
    node_id: Optional[int] = Field(None, ge=1, le=127)  # None: the backend's
    rated_torque: Optional[float] = Field(None, gt=0)   # N m (0x6076); None: backend's or the EDS default
    position_hold: bool = False                    # a drive-side position loop under the CST torque
    kp: Optional[float] = Field(None, ge=0)
    kd: Optional[float] = Field(None, ge=0)
    angle_noise: float = Field(0.0, ge=0)          # rad rms
    torque_meas_noise: float = Field(0.0, ge=0)    # N m rms on 0x6077
    torque_process_noise: float = Field(0.0, ge=0)  # N m rms on the applied torque
    torque_limit: Optional[float] = Field(None, gt=0)  # N m peak of the power stage; None: backend's limit
    travel: Optional[tuple[float, float]] = (-0.05, 0.05)  # m on the scale; outside -> fault 0x8612
    integrator: Literal["zoh", "newmark"] = "zoh"
    poll_us: Optional[float] = Field(None, ge=0)   # receive poll period; None: 100 us on udp_multicast,
    #                                                blocking in-process (see drivers.canopen_frames.FrameIO)
    seed: int = 0
    faults: dict[str, Any] = Field(default_factory=dict)


def _sections(config: Any) -> tuple[dict, dict, AxisParams]:
    if hasattr(config, "backend") and hasattr(config.backend, "options"):      # rt_ident.config.RunConfig
        return dict(config.backend.options()), dict(config.emulator), config.axis_params()
    backend = dict(config.get("backend") or {})
    axis = config.get("axis")
    return backend, dict(config.get("emulator") or {}), (
        AxisParams.from_mapping(axis, where="axis") if axis else thomson_x())


def _eds_path(name: str) -> Path:
    p = Path(name)
    if not p.is_file() and not p.is_absolute() and (CONFIG_DIR / p).is_file():
        p = CONFIG_DIR / p
    if not p.is_file():
        raise ConfigError("emulator.eds", f"EDS file not found: {name}")
    return p


def build_emulator_for(config: Any) -> "EmulatedCia402Drive":
    """Construct (not start) the emulated drive a run configuration describes."""
    from drivers.canopen_config import validate
    from drivers.emulated_drive import EmulatedCia402Drive
    from rt_ident.plant import DEFAULT_KD, DEFAULT_KP, HoldController, PlantSimulator, SensorConfig

    backend, emulator, axis = _sections(config)
    cfg = validate(backend)
    try:
        emu = EmulatorConfig.model_validate(emulator)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"] if not isinstance(p, int))
        raise ConfigError(f"emulator.{loc}" if loc else "emulator", err["msg"]) from None
    if abs(axis.lead - cfg.lead) > 1e-12 * axis.lead:
        log.warning("emulator: axis lead %g differs from backend.lead %g", axis.lead, cfg.lead)
    sensors = SensorConfig(counts_per_rev=cfg.counts_per_rev, scale_resolution=cfg.scale_resolution,
                           angle_noise=emu.angle_noise, torque_meas_noise=emu.torque_meas_noise,
                           torque_process_noise=emu.torque_process_noise)
    controller = (HoldController(kp=DEFAULT_KP if emu.kp is None else emu.kp,
                                 kd=DEFAULT_KD if emu.kd is None else emu.kd) if emu.position_hold else None)
    plant = PlantSimulator(axis, cfg.sample_period, sensors=sensors, controller=controller,
                           torque_limit=emu.torque_limit or cfg.torque_limit, travel=emu.travel,
                           integrator=emu.integrator, seed=emu.seed)
    bus = cfg.bus_kwargs()
    return EmulatedCia402Drive(emu.node_id or cfg.node_id, _eds_path(emu.eds or cfg.eds), bus, plant,
                               FaultConfig.from_mapping(emu.faults), counts_per_rev=cfg.counts_per_rev,
                               scale_resolution=cfg.scale_resolution, scale_index=cfg.scale_index,
                               scale_subindex=cfg.scale_subindex,
                               rated_torque=emu.rated_torque or cfg.rated_torque,
                               poll_s="auto" if emu.poll_us is None else 1e-6 * emu.poll_us)


def start_emulator_for(config: Any) -> "EmulatedCia402Drive":
    """Build and start the emulated drive for a run configuration.

    ``config``: a mapping with ``backend`` (the canopen backend options), optional
    ``emulator`` (:class:`EmulatorConfig`) and ``axis`` tables, or an
    :class:`rt_ident.config.RunConfig`. The caller stops it (``drive.stop()``).
    """
    return build_emulator_for(config).start()


def main(argv: list[str] | None = None) -> int:
    """Run an emulated drive until SIGINT/SIGTERM. Prints ``READY node <id>`` once on the bus."""
    ap = argparse.ArgumentParser(prog="python -m drivers.emulated_drive", description=__doc__.split("\n")[0])
    ap.add_argument("--config", required=True, help="run configuration (TOML) with [backend] and [emulator]")
    ap.add_argument("--interface", help="override backend.interface (e.g. udp_multicast)")
    ap.add_argument("--channel", help="override backend.channel (e.g. 239.74.163.2)")
    ap.add_argument("--port", type=int, help="override backend.port (udp_multicast)")
    ap.add_argument("--log-level", default="WARNING")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    path = Path(args.config)
    if not path.is_file() and (CONFIG_DIR / path.name).is_file():
        path = CONFIG_DIR / path.name
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        print(f"error: cannot read {args.config}: {exc}", file=sys.stderr)
        return 2
    backend = data.setdefault("backend", {})
    for key in ("interface", "channel", "port"):
        if getattr(args, key) is not None:
            backend[key] = getattr(args, key)
    if backend.get("interface") == "virtual":
        log.warning("the virtual bus is in-process only: nothing outside this process can reach this drive")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        drive = start_emulator_for(data)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    where = f"{backend.get('interface')}:{backend.get('channel')}" + (f" port {backend['port']}"
                                                                      if backend.get("port") else "")
    print(f"READY node {drive.node_id} on {where}", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        drive.stop()
    return 0


__all__ = ["FaultConfig", "EmulatorConfig", "build_emulator_for", "start_emulator_for", "main"]

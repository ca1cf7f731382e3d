"""Configuration and start-up of the emulated CiA 402 drive.

* :class:`EmulatorConfig` - the ``[emulator]`` table; its faults are
  :class:`drivers.cia402.faults.FaultConfig` (``[emulator.faults]``);
* :func:`start_emulator_for` - build and start an
  :class:`~drivers.cia402.emulated_drive.EmulatedCia402Drive`
  from a run configuration (the ``[backend]``, ``[emulator]`` and ``[axis]`` tables), as the
  loop does when ``[backend] emulate = true``;
* :func:`main` - ``python -m drivers.cia402.emulator --config configs/canopen-virtual.toml --port N``
  runs the drive alone, reachable from other processes on ``udp_multicast`` (the loop starts
  it in a child process itself: :class:`rt_ident.processes.emulation.EmulatorProcess`).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from drivers.base import Travel
from drivers.cia402.emulated_drive import EmulatedCia402Drive
from drivers.cia402.faults import FaultConfig
from drivers.cia402.variants import drive_profile
from drivers.placement import clear_heap, device_placement, keep_to, settle_heap, start_realtime
from rt_ident.axis.params import CONFIG_DIR, AxisParams, thomson_x
from rt_ident.errors import ConfigError, validation_error

log = logging.getLogger(__name__)


class DriveTruth(BaseModel):
    """``actual`` of the ``[emulator]`` table (``[plant.actual]`` lands here): the drive and axis as they
    truly are where they differ from the ``[backend]`` the host is given. A key left out: as the host
    is told (the plant's lead: the ``[axis]`` lead)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    torque_sign: Literal[1, -1] = 1             # -1: the motor is wired the other way
    motor_encoder_sign: Literal[1, -1] = 1      # -1: 0x6064 counts the other way
    scale_sign: Literal[1, -1] = 1              # -1: the scale object counts the other way
    counts_per_rev: int | None = Field(None, ge=1)              # the motor encoder's true counts per rev
    scale_resolution: float | None = Field(None, gt=0, le=1e-3)  # m per scale count, truly
    lead: float | None = Field(None, gt=0, le=0.1)              # m/rad the screw truly moves the table
    rated_torque: float | None = Field(None, gt=0)              # N m: the drive's true 0x6076
    torque_scale: float = Field(1.0, gt=0, le=100)  # physical torque per torque the drive believes it applies


class EmulatorConfig(BaseModel):
    """The ``[emulator]`` table (plant and drive options not shared with the backend)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    eds: str | None = None                      # the drive's own EDS; None: the backend's
    node_id: int | None = Field(None, ge=1, le=127)  # None: the backend's
    rated_torque: float | None = Field(None, gt=0)   # N m (0x6076); None: backend's or the EDS default
    position_hold: bool = False                    # a drive-side position loop under the CST torque
    kp: float | None = Field(None, ge=0)
    kd: float | None = Field(None, ge=0)
    angle_noise: float = Field(0.0, ge=0)          # rad rms
    torque_meas_noise: float = Field(0.0, ge=0)    # N m rms on 0x6077
    torque_process_noise: float = Field(0.0, ge=0)  # N m rms on the applied torque
    torque_limit: float | None = Field(None, gt=0)  # N m peak of the power stage; None: backend's limit
    travel: Travel | None = (-0.05, 0.05)  # m on the scale; outside -> fault 0x8612
    integrator: Literal["zoh", "newmark"] = "zoh"
    poll_us: float | None = Field(None, ge=0)   # receive poll period; None: 100 us on udp_multicast,
    #                                                blocking in-process (see drivers.cia402.frames.FrameIO)
    seed: int = Field(0, ge=0)
    faults: dict[str, Any] = Field(default_factory=dict)
    friction: dict[str, Any] | None = None       # rt_ident.axis.friction.Friction keys or preset = "thomson"
    x0: float = Field(0.0, ge=-10.0, le=10.0, allow_inf_nan=False)   # m: where the table starts (at rest)
    actual: DriveTruth = Field(default_factory=DriveTruth)   # the true device ([plant.actual])
    polarity: int = Field(0, ge=0, le=255)      # 0x607E at power-up: bit 7 position, bit 6 velocity polarity
    profile: str = "generic"                    # the vendor variant of the drive (drivers.cia402.variants.PROFILES)
    serial_number: int | None = Field(None, ge=0, lt=2**32)   # 0x1018:04; None: the EDS's (another unit: another)
    # true: the table moves on while the master is silent (a real drive holds its torque); false: it steps
    # only on SYNCs (tests that compare two drives SYNC by SYNC, whose own SYNC thread is not real-time)
    run_through_silence: bool = True

    @field_validator("profile")
    @classmethod
    def _known_profile(cls, v: str) -> str:
        drive_profile(v)                        # ValueError names the profiles there are
        return v


def _sections(config: Any) -> tuple[dict, dict, AxisParams]:
    if hasattr(config, "backend") and hasattr(config.backend, "options"):      # rt_ident.config.RunConfig
        return dict(config.backend.options()), dict(config.emulator), config.axis_params()
    backend = dict(config.get("backend") or {})
    axis = config.get("axis")
    return backend, dict(config.get("emulator") or {}), (
        AxisParams.from_mapping(axis, where="axis") if axis else thomson_x())


def build_emulator_for(config: Any) -> EmulatedCia402Drive:
    """Construct (not start) the emulated drive a run configuration describes."""
    from drivers.cia402.config import find_eds, validate
    from rt_ident.axis.plant import DEFAULT_KD, DEFAULT_KP, HoldController, PlantSimulator, SensorConfig, rest_at

    backend, emulator, axis = _sections(config)
    cfg = validate(backend)
    try:
        emu = EmulatorConfig.model_validate(emulator)
    except ValidationError as exc:
        err, msg = validation_error(EmulatorConfig, exc)
        loc = ".".join(str(p) for p in err["loc"] if not isinstance(p, int))
        raise ConfigError(f"emulator.{loc}" if loc else "emulator", msg) from None
    truth = emu.actual
    if truth.lead is not None:
        axis = axis.with_(lead=truth.lead)
    elif abs(axis.lead - cfg.lead) > 1e-12 * axis.lead:
        log.warning("emulator: axis lead %g differs from backend.lead %g", axis.lead, cfg.lead)
    counts_per_rev = truth.counts_per_rev or cfg.counts_per_rev
    scale_resolution = truth.scale_resolution or cfg.scale_resolution
    sensors = SensorConfig(counts_per_rev=counts_per_rev, scale_resolution=scale_resolution,
                           angle_noise=emu.angle_noise, torque_meas_noise=emu.torque_meas_noise,
                           torque_process_noise=emu.torque_process_noise)
    controller = (HoldController(kp=DEFAULT_KP if emu.kp is None else emu.kp,
                                 kd=DEFAULT_KD if emu.kd is None else emu.kd) if emu.position_hold else None)
    from rt_ident.axis.friction import Friction

    friction = Friction.from_mapping(emu.friction, where="emulator.friction") if emu.friction else None
    # the power stage's peak in the drive's belief; physically torque_scale times it
    peak = (emu.torque_limit or cfg.torque_limit) * truth.torque_scale
    plant = PlantSimulator(axis, cfg.sample_period, sensors=sensors, controller=controller,
                           torque_limit=peak, travel=emu.travel,
                           integrator=emu.integrator, seed=emu.seed, friction=friction,
                           x0=rest_at(emu.x0, axis.lead))
    bus = cfg.bus_kwargs()
    eds = find_eds(emu.eds or cfg.eds, "emulator.eds" if emu.eds else "backend.eds")
    return EmulatedCia402Drive(emu.node_id or cfg.node_id, eds, bus, plant,
                               FaultConfig.from_mapping(emu.faults), counts_per_rev=counts_per_rev,
                               scale_resolution=scale_resolution, scale_index=cfg.scale_index,
                               scale_subindex=cfg.scale_subindex,
                               rated_torque=truth.rated_torque or emu.rated_torque or cfg.rated_torque,
                               poll_s="auto" if emu.poll_us is None else 1e-6 * emu.poll_us,
                               torque_sign=truth.torque_sign, motor_encoder_sign=truth.motor_encoder_sign,
                               scale_sign=truth.scale_sign, torque_scale=truth.torque_scale,
                               polarity=emu.polarity, profile=emu.profile,
                               run_through_silence=emu.run_through_silence, serial_number=emu.serial_number)


class EmulatedDrives:
    """Several emulated drives on one bus in one process (the two axes of an XY table): each is an
    :class:`EmulatedCia402Drive` with its own node id, plant and faults, on its own socket of the bus.
    ``stop()`` stops them all; ``stats()`` reports each by node id."""

    def __init__(self, drives: list[EmulatedCia402Drive]) -> None:
        ids = [d.node_id for d in drives]
        if len(set(ids)) != len(ids):
            raise ConfigError("emulator.node_id", f"two emulated drives with one node id: {ids}")
        self.drives = drives

    @property
    def node_id(self) -> str:
        return "+".join(str(d.node_id) for d in self.drives)

    def start(self) -> EmulatedDrives:
        started = []
        try:
            for d in self.drives:
                started.append(d.start())
        except BaseException:
            for d in started:
                d.stop()
            raise
        return self

    def stop(self) -> None:
        for d in self.drives:
            d.stop()

    def stats(self) -> dict[str, Any]:
        return {f"node {d.node_id}": d.stats() for d in self.drives}

    def __getitem__(self, node_id: int) -> EmulatedCia402Drive:
        return next(d for d in self.drives if d.node_id == node_id)

    def __enter__(self) -> EmulatedDrives:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def start_emulator_for(config: Any) -> EmulatedCia402Drive | EmulatedDrives:
    """Build and start the emulated drive for a run configuration.

    ``config``: a mapping with ``backend`` (the canopen backend options), optional
    ``emulator`` (:class:`EmulatorConfig`) and ``axis`` tables, or an
    :class:`rt_ident.config.RunConfig`; or ``{"drives": [such mappings]}`` for several drives
    on one bus in this process (:class:`EmulatedDrives`). The caller stops it (``.stop()``).
    """
    if isinstance(config, dict) and "drives" in config:
        return EmulatedDrives([build_emulator_for(c) for c in config["drives"]]).start()
    return build_emulator_for(config).start()


def main(argv: list[str] | None = None) -> int:
    """Run an emulated drive until SIGINT/SIGTERM. Prints ``READY node <id>`` once on the bus."""
    ap = argparse.ArgumentParser(prog="python -m drivers.cia402.emulator", description=__doc__.split("\n")[0])
    ap.add_argument("--config", required=True, help="run configuration (TOML) with [backend] and [emulator]")
    ap.add_argument("--interface", help="override backend.interface (e.g. udp_multicast)")
    ap.add_argument("--channel", help="override backend.channel (e.g. 239.74.163.2)")
    ap.add_argument("--port", type=int, help="override backend.port (udp_multicast)")
    ap.add_argument("--log-level", default="WARNING")
    ap.add_argument("--no-realtime", action="store_true",
                    help="do not keep off the loop's CPU / ask for SCHED_FIFO (use when the loop runs --no-realtime "
                         "and this host has CPUs to spare)")
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
    # the placement the loop gives its own emulator child: off the loop's CPU (before the drive starts
    # its threads: they inherit it), its threads SCHED_FIFO below the loop once started. Without it a
    # real-time loop on the same CPU starves this process and trips its watchdog on stale data.
    clear_heap()
    placement = device_placement(not args.no_realtime)
    placed = keep_to(placement["cpus"])
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        drive, rt = start_realtime(lambda: start_emulator_for(data), placement["fifo_priority"])
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    placed.update(rt)
    settle_heap()
    where = f"{backend.get('interface')}:{backend.get('channel')}" + (f" port {backend['port']}"
                                                                      if backend.get("port") else "")
    print(f"READY node {drive.node_id} on {where}" + (f" ({', '.join(f'{k} {v}' for k, v in placed.items())})"
                                                      if placed else ""), flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        st = drive.stats()                        # as the host left the drive, before its own stop
        drive.stop()
        print(f"STOPPED node {drive.node_id}: state {st.get('state')}, {st.get('samples')} samples, "
              f"{st.get('late_syncs')} SYNCs answered too late to send, paused {st.get('paused_s', 0.0):.3f} s",
              flush=True)
    return 0


__all__ = ["DriveTruth", "EmulatorConfig", "EmulatedDrives", "build_emulator_for", "start_emulator_for", "main"]

if __name__ == "__main__":
    raise SystemExit(main())

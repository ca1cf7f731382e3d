"""The emulated CiA 402 drive: profile tables, SDO/NMT behaviour, fault config, CLI across processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import canopen
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from drivers.cia402 import profile as p402
from drivers.cia402.drive import Cia402Backend
from drivers.cia402.emulated_drive import EmulatedCia402Drive
from drivers.cia402.emulator import build_emulator_for, start_emulator_for
from drivers.cia402.faults import FaultConfig
from rt_ident import config as run_config
from rt_ident.axis.params import CONFIG_DIR, thomson_x
from rt_ident.axis.plant import PlantSimulator, SensorConfig
from rt_ident.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
EDS = CONFIG_DIR / "cia402_generic.eds"


# ----- CiA 402 profile ---------------------------------------------------------------------
def test_statusword_of_each_state_decodes_to_that_state():
    for state, word in p402.STATUSWORD_OF.items():
        assert p402.decode_state(word) == state
    assert p402.decode_state(0x0637) == p402.OPERATION_ENABLED      # bits 9/10 do not matter


def test_controlword_walk_reaches_operation_enabled_and_quick_stop_leaves_it():
    state, cw = p402.SWITCH_ON_DISABLED, 0
    path = []
    for _ in range(5):
        new_cw = p402.next_controlword(state, cw)
        state, cw = p402.drive_transition(state, new_cw, cw), new_cw
        path.append(state)
    assert path[:3] == [p402.READY_TO_SWITCH_ON, p402.SWITCHED_ON, p402.OPERATION_ENABLED]
    assert p402.drive_transition(state, p402.CW_QUICK_STOP, cw) == p402.QUICK_STOP_ACTIVE
    assert p402.drive_transition(p402.QUICK_STOP_ACTIVE, p402.CW_DISABLE_VOLTAGE, 2) == p402.SWITCH_ON_DISABLED
    # quick stop option 2: enable operation does not leave QUICK STOP ACTIVE (transition 16 needs 5..8)
    assert p402.drive_transition(p402.QUICK_STOP_ACTIVE, p402.CW_ENABLE_OPERATION, 2) == p402.QUICK_STOP_ACTIVE
    # a fault reset needs a rising edge of bit 7
    assert p402.drive_transition(p402.FAULT, 0x80, 0x80) == p402.FAULT
    assert p402.drive_transition(p402.FAULT, 0x80, 0x00) == p402.SWITCH_ON_DISABLED


def test_fault_config_rejects_bad_values_naming_the_field():
    with pytest.raises(ConfigError) as err:
        FaultConfig.from_mapping({"drop_tpdo_every": -1})
    assert err.value.field == "emulator.faults.drop_tpdo_every"
    with pytest.raises(ConfigError) as err:
        FaultConfig.from_mapping({"drop_every": 2})
    assert err.value.field == "emulator.faults.drop_every"
    with pytest.raises(ConfigError) as err:
        FaultConfig.from_mapping({"emcy_at_sample": 1.5})
    assert err.value.field == "emulator.faults.emcy_at_sample"
    assert FaultConfig.from_mapping({"heartbeat_stop_at_s": 0.5}).heartbeat_stop_at_s == 0.5


# ----- the drive on the virtual bus, driven by a bare canopen master ----------------------------
def _drive(channel: str, **kw) -> EmulatedCia402Drive:
    plant = PlantSimulator(thomson_x(), 1e-3, sensors=SensorConfig())
    return EmulatedCia402Drive(5, EDS, {"interface": "virtual", "channel": channel}, plant, **kw)


def test_drive_answers_sdo_and_refuses_unmappable_objects():
    channel = f"e-{uuid.uuid4().hex[:8]}"
    drive = _drive(channel, rated_torque=0.5)
    assert drive.state == p402.NOT_READY                 # constructing did no I/O
    with drive:
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface="virtual", channel=channel)
        try:
            node = net.add_node(5, str(EDS))
            node.sdo.RESPONSE_TIMEOUT = 2.0     # the in-process drive answers late on a loaded test worker
            assert node.sdo[0x1000].raw == 0x00020192     # CiA 402 drive
            assert node.sdo[0x6076].raw == 500            # rated torque override, mN m
            assert p402.decode_state(node.sdo[0x6041].raw) == p402.SWITCH_ON_DISABLED
            with pytest.raises(SdoAbortedError) as err:   # 0x1000 is not PDO-mappable
                node.sdo[0x1A01][1].raw = p402.mapping_entry(0x1000, 0, 32)
            assert err.value.code == 0x06040041
            with pytest.raises(SdoAbortedError) as err:   # length does not match the object
                node.sdo[0x1A01][1].raw = p402.mapping_entry(0x6064, 0, 16)
            assert err.value.code == 0x06040041
            node.sdo[0x6060].raw = 10
            assert node.sdo[0x6061].raw == 10
            assert drive.samples == 0 and drive.applied_torque == 0.0   # no SYNC, no NMT start
        finally:
            net.disconnect()
    assert drive.nmt_state == "PRE-OPERATIONAL"


def test_start_emulator_for_accepts_a_run_config_and_holds_nothing_in_torque_mode():
    cfg = run_config.load(CONFIG_DIR / "canopen-virtual.toml")
    assert cfg.backend.name == "canopen" and cfg.backend.emulate
    drive = start_emulator_for(cfg)
    try:
        assert drive.node_id == 5 and drive.state == p402.SWITCH_ON_DISABLED
        # a real drive in cyclic torque mode closes no position loop: the host does
        assert drive.plant.dt == pytest.approx(1 / 2000) and drive.plant.controller is None
        assert drive.rated_torque == pytest.approx(0.64)
    finally:
        drive.stop()
        drive.stop()                                      # idempotent


def test_emulator_config_errors_name_the_field():
    base = {"backend": {"interface": "virtual", "channel": "x", "node_id": 5, "torque_limit": 1.0,
                        "counts_per_rev": 4096, "scale_resolution": 1e-6}}
    with pytest.raises(ConfigError) as err:
        build_emulator_for({**base, "emulator": {"positon_hold": True}})
    assert err.value.field == "emulator.positon_hold"
    with pytest.raises(ConfigError) as err:
        build_emulator_for({**base, "emulator": {"eds": "missing.eds"}})
    assert err.value.field == "emulator.eds"


def test_drive_does_not_answer_a_sync_once_the_next_one_has_arrived():
    """CiA 301 synchronous window: an answer sent after the next SYNC would be taken for that SYNC's."""
    channel = f"w-{uuid.uuid4().hex[:8]}"
    backend = {"interface": "virtual", "channel": channel, "node_id": 5, "sync_rate_hz": 1000, "torque_limit": 1.0,
               "rated_torque": 0.64, "counts_per_rev": 131072, "scale_resolution": 1e-7, "heartbeat_ms": 50,
               "stale_limit": 50, "startup_timeout": 3.0,
               "rpdo_deadline_ms": 0}                 # the test hands the frames over itself, in its own time
    drive = start_emulator_for({"backend": backend, "emulator": {"position_hold": True}})
    try:
        with Cia402Backend(backend) as be:
            be.activate()
            be._sender.stop()                          # the test plays the SYNC producer now
            drive._io.stop()                           # ... and the drive's receive thread
            drive._io.read_now()                       # frames still queued
            rpdo = (be._setup.rpdo_cob, bytes([0x0F, 0, 0, 0]), time.monotonic())
            sync = (0x80, b"", time.monotonic())
            samples, sent, late = drive.samples, drive.frames_sent, drive.late_syncs
            drive._on_frames([rpdo, sync, rpdo, sync])  # read together: the first SYNC's answer is late
            assert drive.samples == samples + 2        # the axis moved on both SYNCs
            assert drive.late_syncs == late + 1 and drive.frames_sent == sent + 2   # one TPDO1 + TPDO2 set
            drive._on_frames([rpdo, sync])
            assert drive.late_syncs == late + 1 and drive.frames_sent == sent + 4
            drive._io.start()                          # SDO for the stop
        assert drive.applied_torque == 0.0 and not drive.enabled
    finally:
        drive.stop()


_SYNC_PATH_COMPILES = r"""
import threading, time, uuid
from numba.core.dispatcher import Dispatcher
from drivers.cia402.drive import Cia402Backend
from drivers.cia402.emulator import start_emulator_for

backend = {"interface": "virtual", "channel": f"n-{uuid.uuid4().hex[:8]}", "node_id": 5, "sync_rate_hz": 1000,
           "torque_limit": 1.0, "rated_torque": 0.64, "counts_per_rev": 131072, "scale_resolution": 1e-7,
           "heartbeat_ms": 50, "stale_limit": 1000, "startup_timeout": 3.0,
           # not the watchdogs: this script's threads are not real-time, and a busy host holds them up for tens of ms
           "rpdo_deadline_ms": 1000, "heartbeat_consumer_ms": 1000}
drive = start_emulator_for({"backend": backend, "emulator": {"position_hold": True, "torque_meas_noise": 1e-4}})
calls = []
load = Dispatcher._compile_for_args              # a call with types not loaded yet: from the cache or compiled
def counted(self, *args, **kw):
    calls.append(f"{threading.current_thread().name}: {getattr(self, '__name__', self)}")
    return load(self, *args, **kw)
Dispatcher._compile_for_args = counted
try:
    with Cia402Backend(backend) as be:
        be.activate()
        end = time.monotonic() + 10.0            # until 60 SYNCs were answered (a busy host answers few at once)
        while time.monotonic() < end and drive.samples <= 60:
            be.read()
            be.write(0.05)
            time.sleep(0.002)
    print(drive.samples, [c for c in calls if c.startswith("emulated-drive")])
finally:
    drive.stop()
"""


def test_sync_path_loads_no_compiled_code_after_start():
    """Every compiled kernel a SYNC runs (enabled, with torque, hold loop on) is loaded before the drive goes
    on the bus: a first call loads or compiles it for milliseconds, and that SYNC goes unanswered.
    In a fresh interpreter, so that no earlier test has loaded them."""
    out = subprocess.run([sys.executable, "-c", _SYNC_PATH_COMPILES], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    samples, loaded = out.stdout.strip().splitlines()[-1].split(" ", 1)
    assert int(samples) > 50                          # it ran enabled, SYNC after SYNC
    assert loaded == "[]"


# ----- across processes on udp_multicast ---------------------------------------------------
def test_cli_drive_over_udp_multicast_serves_a_backend_in_another_process(tmp_path):
    port = 41000 + os.getpid() % 20000
    toml = tmp_path / "udp.toml"
    toml.write_text(f"""
[backend]
name = "canopen"
interface = "udp_multicast"
channel = "239.74.163.2"
port = {port}
node_id = 9
sync_rate_hz = 500
torque_limit = 1.0
rated_torque = 0.64
counts_per_rev = 131072
scale_resolution = 1e-7
heartbeat_ms = 50
sdo_timeout = 0.5
stale_limit = 50
rpdo_deadline_ms = 200
[emulator]
position_hold = true
""")                                # this process's SYNC thread is not real-time: a wide RPDO deadline
    import tomllib
    backend_cfg = tomllib.loads(toml.read_text())["backend"]
    child = subprocess.Popen([sys.executable, "-m", "drivers.cia402.emulator", "--config", str(toml)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        ready = child.stdout.readline()
        assert ready.startswith("READY node 9"), child.stderr.read() if child.poll() is not None else ready
        be = Cia402Backend(backend_cfg)
        n, last = 0, None
        with be:
            be.activate()
            # 150 samples (0.3 s at 500 Hz) within 10 s: a drive process starved by a busy host answers few SYNCs
            end = time.monotonic() + 10.0
            while time.monotonic() < end and n <= 150:
                time.sleep(0.002)
                blk = be.read()
                be.write(0.1)
                if len(blk):
                    n, last = n + len(blk), blk
        assert n > 150
        assert np.isfinite(last.theta1).all() and last.theta1[-1] > 0.01   # pushed by +0.1 N m against the hold loop
    finally:
        child.terminate()
        assert child.wait(10) == 0


def _silent_drive(deadline_s: float) -> tuple[EmulatedCia402Drive, list[int]]:
    """A drive in OPERATION ENABLED at 1 kHz holding 0.32 N m (500 per mille of 0.64 N m), its master's last
    SYNC and RPDO at t = 10 s, off the bus (the state a silence finds it in; no threads, no clock)."""
    from types import SimpleNamespace

    plant = PlantSimulator(thomson_x(), 1e-3, sensors=SensorConfig())
    drive = EmulatedCia402Drive(5, EDS, {"interface": "virtual"}, plant, rated_torque=0.64)
    sent: list[int] = []
    drive._node = SimpleNamespace(nmt=SimpleNamespace(state="OPERATIONAL"),
                                  emcy=SimpleNamespace(send=lambda code, reg: sent.append(code)))
    drive._values.update({(p402.TARGET_TORQUE, 0): 500, (0x60B2, 0): 0, (p402.MAX_TORQUE, 0): 1000})
    drive._state = p402.OPERATION_ENABLED
    drive._sync_period, drive._plant_wall, drive._syncs = 1e-3, 10.0, 100
    drive._deadline_s, drive._rpdo_t = deadline_s, 10.0
    return drive, sent


def _momentum(drive: EmulatedCia402Drive) -> float:
    p, s = drive.plant.params, drive.plant.state
    return p.I1 * s[1] + p.I2 * s[3]            # of the free two-inertia axis: grows by the torque's impulse


def test_a_master_silent_past_the_rpdo_deadline_faults_the_drive_after_the_torque_held_that_long():
    drive, sent = _silent_drive(0.020)
    m0 = _momentum(drive)
    drive._check_deadline(10.015)               # within the deadline: nothing happens yet
    assert drive.state == p402.OPERATION_ENABLED and drive.silent_samples == 0
    drive._check_deadline(10.300)               # the housekeeping sees the silence 300 ms on
    assert drive.state == p402.FAULT and sent == [0x8250] and drive.applied_torque == 0.0
    held = drive.silent_samples
    assert held == 20                           # the torque stayed in force up to the deadline only
    assert _momentum(drive) - m0 == pytest.approx(0.32 * held * 1e-3, rel=0.02)
    drive._run_through_silence(10.300)          # the rest of the silence (the next SYNC): coasting, no torque
    assert drive.silent_samples > held and _momentum(drive) - m0 == pytest.approx(0.32 * held * 1e-3, rel=0.02)


@pytest.mark.parametrize(("read_until", "faults"), [(10.010, False), (10.200, True)],
                         ids=["frames-not-read-yet", "silence-read"])
def test_the_housekeeping_counts_a_silence_only_as_far_as_the_bus_was_read(monkeypatch, read_until, faults):
    """A receive thread starved in a loaded host leaves RPDOs that came on time waiting in the socket: the
    housekeeping 300 ms on must not call that a silence (a real drive reads every frame as it comes); a
    silence the reader has seen through past the deadline faults the drive as before."""
    from types import SimpleNamespace

    from drivers.cia402 import emulated_drive as mod

    drive, sent = _silent_drive(0.020)
    drive._node.nmt.state = "OPERATIONAL"
    drive._io = SimpleNamespace(read_until=read_until)
    drive._pdo_dirty = False
    monkeypatch.setattr(drive, "_event_tpdos", lambda: None)
    monkeypatch.setattr(mod.time, "monotonic", lambda: 10.300)
    drive._alive_t = 10.299                     # the emulator itself ran (no pause of its own)
    drive._housekeeping()
    assert (drive.state == p402.FAULT, sent) == ((True, [0x8250]) if faults else (False, []))
    if faults:
        assert drive.silent_samples == 20       # the torque held up to the deadline only, as before


def test_without_an_rpdo_deadline_a_silent_master_leaves_the_last_torque_in_force():
    drive, sent = _silent_drive(0.0)
    m0 = _momentum(drive)
    drive._check_deadline(10.300)
    assert drive.state == p402.OPERATION_ENABLED and sent == []
    drive._run_through_silence(10.300)          # the next SYNC: 300 ms of the held torque
    assert drive.silent_samples == 300
    assert _momentum(drive) - m0 == pytest.approx(0.32 * 0.300, rel=0.02)


def test_an_rpdo_that_arrives_after_a_silence_past_the_deadline_faults_the_drive_first():
    # the host and the emulated drive stalled together (one VM): the RPDO's arrival shows the silence
    drive, sent = _silent_drive(0.020)
    drive._rpdo_by_cob = {0x205: type("L", (), {"event_s": 0.020, "trans_type": 1})()}
    drive._on_rpdo(0x205, bytearray(4), 10.100)
    assert drive.state == p402.FAULT and sent == [0x8250] and drive.silent_samples == 20


def test_time_the_emulator_itself_was_not_run_is_no_silence_of_its_master():
    # a paused VM stops the host and the emulated drive together: a drive with its own processor saw nothing
    drive, sent = _silent_drive(0.020)
    drive._alive_t = 10.0
    m0 = _momentum(drive)
    drive._note_alive(10.300)                   # the emulator runs again, 300 ms after it last did
    drive._check_deadline(10.301)
    drive._run_through_silence(10.301)
    assert drive.state == p402.OPERATION_ENABLED and sent == [] and drive.paused_s == pytest.approx(0.3)
    assert drive.silent_samples == 0 and _momentum(drive) == m0


def test_a_silence_is_counted_in_the_sync_period_the_master_set_not_in_arrival_gaps():
    # two SYNCs that arrive together (a burst after a late send) are no clock: a period learnt from them
    # once ran the table 100 samples through every ordinary SYNC
    drive, _ = _silent_drive(0.0)
    drive._sync_period = None
    drive._written(p402.CYCLE_PERIOD, 0, 1000)          # the master's 0x1006: 1000 us
    assert drive._sync_period == pytest.approx(1e-3)
    for t in (10.00001, 10.00101, 10.00201):             # a burst, then the ordinary pace
        drive._syncs += 1
        drive._note_sync_time(t)
    assert drive.silent_samples == 0
    drive._syncs += 1
    drive._note_sync_time(10.02201)                      # 20 ms silent: 19 samples besides this SYNC's own
    assert drive.silent_samples == 19

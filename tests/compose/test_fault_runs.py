"""Each injected device fault, through the whole product (`rt_ident.compose.run.run` with the emulator in its own
process): the run stops with a cause, zero torque, the device disabled, and a readable recording that
holds every sample the loop read.

The CANopen runs are real-time (the loop thread leaves SCHED_FIFO when the run ends): a SYNC sender that
is not leaves gaps of several periods, in which a drive in torque mode holds its last torque while the
table moves on, and the loop's own control then trips on speed before the injected fault. The watchdog
gets a longer stale limit than a bench would use, for a loaded test host.
"""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from rt_ident.axis.params import CONFIG_DIR
from rt_ident.compose import run as run_mod
from rt_ident.config import load
from rt_ident.processes.recorder import read_recording

COLUMNS = {"t", "seq", "theta1", "theta2", "torque_cmd", "torque_meas"}


def _check_recording(path, samples: int) -> None:
    if samples == 0:                                     # stopped before any sample: no empty file is left
        assert not path.exists() and not path.with_name(path.name + ".arrows").exists()
        return
    table = pq.read_table(path)
    assert COLUMNS <= set(table.column_names)
    assert table.num_rows == samples                     # every sample the loop read, nothing more
    if samples >= 10:
        assert len(read_recording(path)) == samples      # and the offline reader takes it


def _check_stopped(summary: dict, emulators: list, causes: set) -> None:
    stop = summary["stop"]
    assert stop["cause"] in causes, stop
    # "created": open() itself failed (nothing was ever energized); otherwise stopped and closed
    assert stop["final_torque"] == 0.0 and stop["backend_state"] in ("closed", "created")
    (emu,) = emulators
    assert emu.stats is not None and emu.stats["applied_torque"] == 0.0 and not emu.stats["enabled"], emu.stats


CANOPEN = [
    ("emcy", {"emcy_at_sample": 300, "emcy_code": 0x2310}, {"device-fault"}),
    ("heartbeat-loss", {"heartbeat_stop_at_s": 0.3}, {"device-fault"}),
    # a stuck motor encoder takes the host's omega1 damping away: with the watchdog at 200 ticks the table
    # can speed up past safety.max_speed_m_s, or reach the travel limit's stopping distance, before the
    # watchdog sees the encoder stuck. Each is a safe stop; the checks below hold for all three.
    ("stuck-encoder", {"stuck_encoder_at_sample": 300}, {"watchdog", "speed-limit", "travel-limit"}),
    ("tpdos-dropped", {"drop_tpdo_every": 1, "tpdo_faults_from_sample": 300}, {"watchdog"}),
    ("tpdos-corrupted", {"corrupt_tpdo_every": 1, "tpdo_faults_from_sample": 300}, {"watchdog", "protocol"}),
]


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("name,faults,causes", CANOPEN, ids=[c[0] for c in CANOPEN])
def test_canopen_fault_stops_at_zero_torque_disabled_with_the_recording_intact(name, faults, causes, emulators,
                                                                                tmp_path, host_made_end):
    # the host's watch of the drive's heartbeat widened but where it is the fault: a starved emulator's
    # heartbeat comes 250 ms late on a busy host
    wide = {} if name == "heartbeat-loss" else {"backend.heartbeat_consumer_ms": 1000}
    cfg = load(CONFIG_DIR / "canopen-virtual.toml",
               **{"loop.duration": 3.0, "loop.realtime": True, "telemetry.sink": "off",
                  "backend.stale_limit": 200, "safety.watchdog_ticks": 200, "emulator.faults": faults, **wide})
    host = []
    for k in range(3):      # a run the host ended (a loop stall past the drive's RPDO deadline): safe, then again
        emulators.clear()
        rec = tmp_path / f"r{k}.parquet"
        summary = run_mod.run(cfg, record=str(rec))
        why = host_made_end(summary["stop"], emulators[0].stats if emulators else None)
        if why is None:
            break
        _check_stopped(summary, emulators, {summary["stop"]["cause"]})
        host.append(why)
    else:
        pytest.skip(f"the host stopped all 3 runs before the injected fault: {host}")
    _check_stopped(summary, emulators, causes)
    _check_recording(rec, summary["loop"]["samples"])


SERIAL = [
    ("stuck-encoder", {"stuck_encoder": True}, {"watchdog", "device-fault"}),
    ("host-heartbeat-lost", {"deaf": True}, {"device-fault", "timeout", "connection"}),
    ("crc-storm", {"corrupt_probability": 0.5}, {"protocol", "device-fault", "timeout"}),
    ("silent", {"silent": True}, {"timeout", "connection"}),
]


@pytest.mark.parametrize("name,faults,causes", SERIAL, ids=[c[0] for c in SERIAL])
def test_serial_fault_stops_at_zero_torque_disabled_with_the_recording_intact(name, faults, causes, emulators,
                                                                               tmp_path):
    cfg = load(CONFIG_DIR / "serial-virtual.toml",
               **{"loop.duration": 2.0, "loop.realtime": False, "telemetry.sink": "off",
                  **{f"emulator.{k}": v for k, v in faults.items()}})
    rec = tmp_path / "r.parquet"
    summary = run_mod.run(cfg, record=str(rec))
    _check_stopped(summary, emulators, causes)
    _check_recording(rec, (summary.get("loop") or {}).get("samples", 0))

"""What a run checks of the device it opens, before enabling it. A commissioning is of one unit: the ledger keeps
the serial number the device gave, and a run on another unit put in its place (same config) is refused with
--require-commissioned, else warned about, and never reported as commissioned. A device that reports settings
unlike the config's is refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from drivers.sim import SimBackend
from rt_ident import config
from rt_ident.commission import ledger
from rt_ident.compose.run import run
from rt_ident.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
BOARD_1 = {"model": "emulated-board", "serial_number": 1}


@pytest.fixture(autouse=True)
def state_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("RT_IDENT_STATE_DIR", str(tmp_path / "state"))
    return tmp_path / "state"


def _sim() -> config.RunConfig:
    return config.from_mapping({"loop": {"realtime": False, "duration": 0.3},
                                "backend": {"name": "sim", "paced": False}, "recording": {"enabled": False}})


def test_the_ledger_keeps_the_unit_a_passed_commissioning_was_of():
    cfg = _sim()
    ledger.record(cfg, {"verdict": "pass", "identity": {**BOARD_1, "firmware": "1.0.0", "sample_rate_hz": 2e4}})
    assert ledger.lookup(cfg)["unit"] == BOARD_1
    ledger.record(cfg, {"verdict": "pass", "identity": {"model": "emulated-board", "serial_number": 0}})
    assert ledger.lookup(cfg)["unit"] is None                  # a device without a serial number names no unit


def test_a_config_file_changed_since_it_passed_names_the_settings_that_changed(tmp_path):
    from typer.testing import CliRunner

    from rt_ident.cli import app

    text = _board_text()
    path = tmp_path / "axis.toml"
    path.write_text(text)
    ledger.record(config.load(path), {"verdict": "pass", "identity": BOARD_1})
    assert ledger.changed_since_commissioned(config.load(path)) is None          # as it was commissioned
    path.write_text(text.replace("torque_constant = 0.1 ", "torque_constant = 0.2 ", 1))
    r = CliRunner().invoke(app, ["run", str(path), "--require-commissioned"])
    assert isinstance(r.exception, ConfigError), r.output
    assert str(r.exception).startswith("--require-commissioned: this device configuration has changed since it was "
                                       "commissioned (backend.torque_constant 0.1 -> 0.2); "), r.exception
    other = tmp_path / "other.toml"                     # the same settings in a file never commissioned
    other.write_text(path.read_text())
    assert ledger.changed_since_commissioned(config.load(other)) is None


def test_another_unit_is_refused_with_require_before_the_device_is_enabled_and_named_without(monkeypatch):
    enabled = []
    monkeypatch.setattr(SimBackend, "_activate", lambda self: enabled.append(self))
    with pytest.raises(ConfigError, match=r"^--require-commissioned: the device opened did not say which unit it "
                                          r"is \(no serial number at open\), but the commissioning on record is of "
                                          r"serial 1 \(model emulated-board\)"):
        run(_sim(), sink="off", commissioned_units={"": BOARD_1}, require_commissioned=True)
    assert not enabled
    monkeypatch.undo()
    s = run(_sim(), sink="off", commissioned_units={"": BOARD_1})
    other = s["commissioned_unit"][""]
    assert s["stop"]["cause"] is None and other["expected"] == BOARD_1
    assert other["found"] is None and "has not been commissioned" in other["message"]


def _board_text() -> str:
    """serial-virtual.toml as these tests run it: not real-time, and the link's and the board's watches widened (a
    busy host), as in the other rigs: the subject is the unit on record, not the link."""
    text = (ROOT / "configs" / "serial-virtual.toml").read_text().replace("realtime = true", "realtime = false")
    for shipped, wide in [("read_timeout = 0.05 ", "read_timeout = 1.0\nwrite_timeout = 1.0\ninfo_timeout = 1.0 "),
                          ("startup_timeout = 1.0 ", "startup_timeout = 5.0 "),
                          ("heartbeat_timeout = 0.1\n", "heartbeat_timeout = 1.0\n"),
                          ("watchdog_ticks = 20\n", "watchdog_ticks = 1000\n")]:
        assert shipped in text, shipped
        text = text.replace(shipped, wide, 1)
    return text


def _board_run(tmp_path: Path, serial: int, *args: str) -> subprocess.CompletedProcess:
    text = _board_text().replace("seed = 1\n", f"seed = 1\nserial_number = {serial}\n", 1)
    cfgfile = tmp_path / f"board-{serial}.toml"
    cfgfile.write_text(text)
    env = {**os.environ, "RT_IDENT_STATE_DIR": str(tmp_path / "state")}
    return subprocess.run([sys.executable, "-m", "rt_ident", "run", str(cfgfile), "--duration", "1", "--no-telemetry",
                           "--json", *args], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)


def _stop(proc: subprocess.CompletedProcess) -> object:
    """The stop of a ``--json`` run's summary (its cause, message and fix), or its stderr's end."""
    try:
        return json.loads(proc.stdout)["stop"]
    except (ValueError, KeyError, TypeError):
        return proc.stderr[-2000:]


def _board_run_to_its_end(tmp_path: Path, serial: int, host_made_end, *args: str) -> subprocess.CompletedProcess:
    """:func:`_board_run` again (3 runs at most) while the host ends it: the subject is the unit on record."""
    host = []
    for _ in range(3):
        proc = _board_run(tmp_path, serial, *args)
        stop = _stop(proc)
        why = host_made_end(stop) if proc.returncode == 3 and isinstance(stop, dict) else None
        if why is None:
            return proc
        assert stop["final_torque"] == 0.0 and stop["backend_state"] == "closed", stop
        host.append(why)
    pytest.skip(f"the host ended all 3 runs: {host}")


def test_a_board_swapped_for_another_unit_is_not_run_as_commissioned(tmp_path, host_made_end):
    ledger.record(config.from_mapping(tomllib.loads(_board_text())), {"verdict": "pass", "identity": BOARD_1})
    same = _board_run_to_its_end(tmp_path, 1, host_made_end, "--require-commissioned")
    assert same.returncode == 0, _stop(same)
    assert json.loads(same.stdout)["commissioning"]["verdict"] == "pass"
    files = sorted((tmp_path / "runs").iterdir())
    swapped = _board_run(tmp_path, 2, "--require-commissioned")
    assert swapped.returncode == 2, swapped.stderr[-2000:]
    assert ("--require-commissioned: the device opened is serial 2 (model emulated-board), but the commissioning on "
            "record is of serial 1 (model emulated-board)") in swapped.stderr
    assert sorted((tmp_path / "runs").iterdir()) == files                       # refused: no file of its own
    warned = _board_run_to_its_end(tmp_path, 2, host_made_end)
    assert warned.returncode == 0, _stop(warned)
    s = json.loads(warned.stdout)
    assert s["commissioning"]["verdict"] is None and "serial 2" in s["commissioning"]["warning"]
    assert "has not been commissioned" in warned.stderr


def test_a_board_set_to_other_counts_than_the_config_is_refused_before_it_is_enabled(tmp_path, monkeypatch):
    from drivers.encoder_board.board import SerialBoardBackend

    enabled = []
    monkeypatch.setattr(SerialBoardBackend, "_activate", lambda self: enabled.append(self))
    data = tomllib.loads(_board_text())          # its start-up and link timeouts widened for a busy host
    data["plant"] = {"actual": {"counts_per_rev": 4096}}       # the board's encoder setting, not the config's
    with pytest.raises(ConfigError, match=r"^backend.counts_per_rev: the device reports 4096, the config says "
                                          r"131072: correct backend.counts_per_rev"):
        run(config.from_mapping(data), sink="off", record=str(tmp_path / "r.parquet"))
    assert not enabled and not (tmp_path / "r.parquet").exists()


def _xy(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    (tmp_path / "xy.toml").write_text((ROOT / "configs" / "xy-canopen-virtual.toml").read_text())
    env = {**os.environ, "RT_IDENT_STATE_DIR": str(tmp_path / "state")}
    return subprocess.run([sys.executable, "-m", "rt_ident", "run", "xy.toml", "--duration", "1", "--no-telemetry",
                           "--json", *args], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)


@pytest.mark.xdist_group("realtime")
def test_an_xy_run_needs_each_axis_commissioned_as_a_config_of_its_own(tmp_path):
    refused = _xy(tmp_path, "--require-commissioned")
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert "--require-commissioned: axis x's device configuration has never been commissioned" in refused.stderr
    xy = config.from_mapping(tomllib.loads((tmp_path / "xy.toml").read_text()))
    for acfg in xy.axis_configs().values():                # as `rt-ident commission` records each axis's config
        ledger.record(acfg, {"verdict": "pass", "identity": {"vendor_id": 0, "product_code": 0x402,
                                                             "serial_number": 1}})
    ok = _xy(tmp_path, "--require-commissioned")
    assert ok.returncode != 2, ok.stderr[-2000:]              # let through (how the drives' run ends is theirs)
    s = json.loads(ok.stdout)
    assert s["commissioning"]["verdict"] == "pass" and set(s["commissioning"]["axes"]) == {"x", "y"}

"""A closed-loop run on an axis whose torque or encoder sign the host has wrong (never commissioned):
the position loop is positive feedback, and the run ends with a cause that names the wiring, not a
speed or travel limit; the run warned before enabling, and refuses with --require-commissioned."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_ident import config
from rt_ident.compose.run import run
from rt_ident.loop.safety import against_torque

ROOT = Path(__file__).resolve().parents[2]


def _cfg(actual: dict) -> config.RunConfig:
    return config.from_mapping({"loop": {"realtime": False, "duration": 2.0},
                                "backend": {"name": "sim", "paced": False, "torque_meas_noise": 0.0005},
                                "telemetry": {"sink": "off"}, "recording": {"enabled": False},
                                "plant": {"actual": actual}})


@pytest.mark.parametrize("key", ["torque_sign", "motor_encoder_sign", "scale_sign"])
def test_a_miswired_sign_ends_the_run_with_cause_sign_naming_the_settings(key):
    s = run(_cfg({key: -1}), sink="off")
    assert s["stop"]["cause"] == "sign", s["stop"]
    assert "torque_sign" in s["stop"]["message"] and "commission" in s["stop"]["message"]
    assert s["stop"]["final_torque"] == 0.0 and s["stop"]["backend_state"] == "closed"


def test_a_rightly_wired_run_never_reads_as_accelerating_against_its_torque():
    s = run(_cfg({"x0": 0.0}), sink="off")
    assert s["stop"]["cause"] is None, s["stop"]


def test_the_fit_tells_an_axis_that_follows_its_torque_from_one_that_opposes_it():
    dt, inertia = 1e-4, 3.5e-5
    torque = np.full(200, 0.2)
    theta = 0.5 * (torque[0] / inertia) * (np.arange(200) * dt) ** 2
    assert against_torque(theta, torque, dt, inertia) == pytest.approx(1.0, rel=0.05)
    assert against_torque(-theta, torque, dt, inertia) == pytest.approx(-1.0, rel=0.05)
    assert against_torque(np.arange(200) * 1e-3, np.zeros(200), dt, inertia) is None   # coasting: no verdict


def _cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    cfgfile = tmp_path / "mis.toml"
    text = (ROOT / "configs" / "sim.toml").read_text().replace("realtime = true", "realtime = false")
    cfgfile.write_text(text + "\n[plant.actual]\ntorque_sign = -1\n")
    env = {**os.environ, "RT_IDENT_STATE_DIR": str(tmp_path / "state")}
    return subprocess.run([sys.executable, "-m", "rt_ident", "run", str(cfgfile), *args], capture_output=True,
                          text=True, timeout=300, env=env, cwd=tmp_path)


def test_a_never_commissioned_device_is_warned_about_and_the_run_ends_on_the_sign(tmp_path):
    p = _cli(tmp_path, "--no-telemetry", "--duration", "2", "--json")
    assert "never been commissioned" in p.stderr and "rt-ident commission" in p.stderr
    s = json.loads(p.stdout)
    assert s["stop"]["cause"] == "sign" and s["commissioning"]["verdict"] is None
    assert p.returncode != 0


def test_require_commissioned_refuses_before_anything_starts(tmp_path):
    p = _cli(tmp_path, "--no-telemetry", "--require-commissioned")
    assert p.returncode == 2, p.stderr
    assert "--require-commissioned" in p.stderr and "never been commissioned" in p.stderr
    assert not (tmp_path / "runs").exists()

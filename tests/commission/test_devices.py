"""``rt-ident commission`` against the emulated devices: each miswiring or misscaling of the host's picture
fails the check that names its key, within the travel budget and the speed limit (as the host's two
sensors measure them: in each case one of them is right), and a right picture passes."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from rt_ident import config
from rt_ident.commission.stages import commission

ROOT = Path(__file__).resolve().parents[2]
LEAD = 7.96e-4


def device_cfg(name: str, actual: dict | None = None, **sections: dict) -> config.RunConfig:
    data = tomllib.loads((ROOT / "configs" / name).read_text())
    data["loop"]["realtime"] = False          # the test's process stays an ordinary one unless a test asks
    data["telemetry"] = {"sink": "off"}
    if actual:
        data["plant"] = {"actual": actual}
    for k, v in sections.items():
        data[k] = {**data.get(k, {}), **v}
    return config.from_mapping(data, source=str(ROOT / "configs" / name))


@pytest.fixture(autouse=True)
def state_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("RT_IDENT_STATE_DIR", str(tmp_path / "state"))


BOARD = [
    ({"torque_sign": -1}, "backend.torque_sign"),
    ({"motor_encoder_sign": -1}, "backend.motor_encoder_sign"),
    ({"scale_sign": -1}, "backend.scale_sign"),
    ({"counts_per_rev": 2**16}, "backend.counts_per_rev"),
    ({"lead": 2 * LEAD}, "backend.lead"),
    ({"torque_scale": 10.0}, "backend.torque_constant"),
]


@pytest.mark.parametrize(("actual", "key"), BOARD, ids=[k for _, k in BOARD])
def test_the_emulated_board_miswired_fails_the_check_naming_its_key_within_limits(tmp_path, actual, key,
                                                                                 restore_scheduling):
    # real time, as on a bench: the board's link (a frame every 50 us, 0.05 s timeouts) next to pytest's
    # other workers needs it
    cfg = device_cfg("serial-virtual.toml", {**actual, "x0": 0.01}, loop={"realtime": True})
    r = commission(cfg, tmp_path / "out")
    assert r["verdict"] == "fail", r["checks"]
    assert r["failed"]["fix"].startswith(key), r["failed"]
    if r["max_travel_m"] is not None:
        assert r["max_travel_m"] <= cfg.commission.travel_m and r["max_speed_m_s"] <= cfg.commission.max_speed_m_s


def test_the_emulated_board_told_the_truth_passes_connect_and_probe_off_centre(tmp_path, restore_scheduling):
    cfg = device_cfg("serial-virtual.toml", {"x0": -0.01}, commission={"identify_s": 1.0}, loop={"realtime": True})
    r = commission(cfg, tmp_path / "out")
    probe = r["checks"][:r["checks"].index(next(c for c in r["checks"] if c["name"] == "breakaway torque")) + 1]
    assert [c["name"] for c in probe if not c["ok"]] == [], probe
    assert r["stage_reached"] in ("c", "d", "e")
    assert r["max_travel_m"] <= cfg.commission.travel_m and r["max_speed_m_s"] <= cfg.commission.max_speed_m_s
    assert r["identity"].get("counts_per_rev") == 2**17

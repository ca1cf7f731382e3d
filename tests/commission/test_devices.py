"""``rt-ident commission`` against the emulated devices: each miswiring or misscaling of the host's picture
fails the check that names its key, within the travel budget and the speed limit (as the host's two
sensors measure them: in each case one of them is right), and a right picture passes from off centre, or
fails naming the host that disturbed it (never an axis setting)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from rt_ident import config
from rt_ident.commission.probe import HARD_STOP
from rt_ident.commission.stages import commission

ROOT = Path(__file__).resolve().parents[2]
LEAD = 7.96e-4


#: the emulated links' timeouts widened, as in test_adaptation's emulated runs: next to pytest's other
#: workers a device process that is not real-time is held off for 100 ms and more (the shipped limits are tested in the
#: drivers' own tests)
WIDE = {"serial-virtual.toml": {"backend": {"read_timeout": 1.0, "write_timeout": 1.0, "startup_timeout": 5.0,
                                            "info_timeout": 1.0},
                                "emulator": {"heartbeat_timeout": 1.0}, "safety": {"watchdog_ticks": 1000}},
        "canopen-virtual.toml": {"backend": {"stale_limit": 1000, "heartbeat_consumer_ms": 1000,
                                             "startup_timeout": 5.0, "sdo_timeout": 2.0},
                                 "safety": {"watchdog_ticks": 1000}}}


def device_cfg(name: str, actual: dict | None = None, **sections: dict) -> config.RunConfig:
    data = tomllib.loads((ROOT / "configs" / name).read_text())
    for k, v in WIDE[name].items():
        data[k] = {**data.get(k, {}), **v}
    data["loop"]["realtime"] = False          # the test's process stays an ordinary one unless a test asks
    data["telemetry"] = {"sink": "off"}
    if actual:
        data["plant"] = {"actual": actual}
    for k, v in sections.items():
        data[k] = {**data.get(k, {}), **v}
    return config.from_mapping(data, source=str(ROOT / "configs" / name))


#: commissionings a test runs before it accepts that the host disturbed every one
ATTEMPTS = 2


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


DRIVE = [*BOARD[:5], ({"torque_scale": 10.0}, "backend.rated_torque"), ({"rated_torque": 6.4}, "backend.rated_torque")]
CASES = [("serial-virtual.toml", a, k) for a, k in BOARD] + [("canopen-virtual.toml", a, k) for a, k in DRIVE]
#: the most a probe's read covers on a host it does not name as the cause: a few ticks
READ_S = 0.01


@pytest.mark.parametrize(("name", "actual", "key"), CASES,
                         ids=[f"{n.split('-')[0]}-{k}-{next(iter(a))}" for n, a, k in CASES])
@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_an_emulated_device_miswired_fails_the_check_naming_its_key_within_limits(tmp_path, name, actual, key,
                                                                                 restore_scheduling):
    # real time, as on a bench: the board's link (a frame every 50 us, 0.05 s timeouts) and the drive's
    # 2 kHz SYNC next to pytest's other workers need it
    cfg = device_cfg(name, {**actual, "x0": 0.01}, loop={"realtime": True})
    host_failures = []
    for k in range(ATTEMPTS):          # a commissioning the host disturbed names the host: it cannot tell the key
        r = commission(cfg, tmp_path / f"out{k}")
        assert r["verdict"] == "fail", r["checks"]
        if not r["failed"]["fix"].startswith("loop.realtime"):
            break
        host_failures.append(r["failed"]["fix"])
    else:
        pytest.skip(f"the host disturbed all {ATTEMPTS} commissionings: {host_failures}")
    # the key first, or (the board's encoder check stopped it before the host saw the motion) among those named
    named = r["failed"]["fix"].split(":")[0]
    assert named.startswith(key) or key.removeprefix("backend.") in named, (
        [(c["name"], c["measured"]) for c in r["checks"] if not c["ok"]], r["failed"]["fix"],
        [{k: p.get(k) for k in ("direction", "breakaway_nm", "push_nm", "aborted", "starved_samples", "lost_samples")}
         for p in r.get("pulses") or []], r.get("max_travel_m"), r.get("max_speed_m_s"))
    if r["max_travel_m"] is not None:
        # a limit passed all the same (a device's latency on a loaded host) fails 'limits' and is braked at once;
        # how far past it the table gets grows with the emulated device's latency behind a busy host
        # and past HARD_STOP x the budget the probe writes zero on the first sample it reads there: the table is
        # seen where that read ends, up to READ_S of motion at the speed measured
        within = all(c["ok"] for c in r["checks"] if c["name"] == "limits")
        budget = cfg.commission.travel_m
        travel = budget if within else HARD_STOP * budget + READ_S * r["max_speed_m_s"]
        assert r["max_travel_m"] <= travel
        assert r["max_speed_m_s"] <= (1.0 if within else HARD_STOP) * cfg.commission.max_speed_m_s


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
@pytest.mark.parametrize("name", ["serial-virtual.toml", "canopen-virtual.toml"], ids=["serial", "canopen"])
def test_an_emulated_device_wired_as_the_host_is_told_passes_from_off_centre_or_names_only_the_host(
        tmp_path, name, restore_scheduling):
    """A busy host can stall the loop or starve the emulated device's link (a real device has a processor of
    its own); commissioning must then fail naming ``loop.realtime``, never a key of the axis or the backend.
    A commissioning the host left alone passes every stage (identifying for 3 s, not the default 5 s: what is
    tested is every stage on the device's link, not the estimate's precision; shorter leaves the emulated
    drive's torque lines near the trust limit's SNR)."""
    cfg = device_cfg(name, {"x0": 0.01}, loop={"realtime": True}, commission={"identify_s": 3.0})
    host_failures = []
    for k in range(ATTEMPTS):
        r = commission(cfg, tmp_path / f"out{k}")
        assert r["max_travel_m"] <= cfg.commission.travel_m and r["max_speed_m_s"] <= cfg.commission.max_speed_m_s
        if r["verdict"] == "pass":
            break
        failed = [(c["name"], c["measured"], c["fix"]) for c in r["checks"] if not c["ok"]]
        assert r["failed"]["fix"].startswith("loop.realtime"), (failed, r.get("verification", {}).get("timing"),
                                                                 r.get("identification", {}).get("attempts"))
        host_failures.append(r["failed"]["fix"])
    else:
        pytest.skip(f"the host disturbed all {ATTEMPTS} commissionings: {host_failures}")
    assert r["stage_reached"] == "e"
    assert r["parameters"]["I2"] == pytest.approx(8.3e-6, rel=0.1)
    assert [c["name"] for c in r["checks"] if c.get("note")] == []     # the torque reaches the motor as told
    assert Path(r["report"]).is_file() and Path(r["axis_toml"]).is_file()
    timing = r["verification"]["timing"]          # both devices say how late the move's torques landed
    assert timing["late_torques"] >= 0 and 0 <= timing["late_torque_ticks"] <= 1, timing

"""Bad configs and recordings end in one line naming the setting that fixes them (exit 2), found
before anything starts: cases that fuzzing the configs turns up, each checked through the loader
(or the run's start-up checks) and through the command line."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_ident.compose.preflight import preflight
from rt_ident.config import TICK_HZ_RANGE, from_mapping, load
from rt_ident.errors import ConfigError, DataError, RtIdentError

REPO = Path(__file__).resolve().parents[1]
AXIS = {"I1": 2.7e-5, "I2": 8.3e-6, "B": 2.1e-3, "K": 110.0, "lead": 7.96e-4}


def _cli(args: list[str], cwd: Path, timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-m", "rt_ident", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def _one_line_error(res: subprocess.CompletedProcess, field: str) -> str:
    """rc 2, no traceback, stderr one line ``error: FIELD: ...``; returns that line."""
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert "Traceback" not in res.stderr + res.stdout
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"error: {field}"), lines[0]
    return lines[0]


def _write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _run_cfg(**sections) -> dict:
    """A quick sim config (no real time, no files) with ``sections`` laid over."""
    data = {"axis": dict(AXIS), "backend": {"name": "sim", "paced": False}, "safety": {},
            "loop": {"realtime": False}, "telemetry": {"sink": "off"}, "recording": {"enabled": False}}
    for k, v in sections.items():
        data[k] = {**data.get(k, {}), **v}
    return data


def _refused(data: dict) -> ConfigError:
    with pytest.raises(ConfigError) as e:
        preflight(from_mapping(data))
    return e.value


# 1 ------------------------------------------------------------------------- a binary file
def test_a_binary_config_file_is_refused_in_one_line_naming_the_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_bytes(bytes([0xDF, 0xFF, 0x00, 0x81]) + os.urandom(64))
    with pytest.raises(ConfigError, match="not a text file") as e:
        load(p)
    assert e.value.field == str(p)
    _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), str(p))


def test_a_config_saved_with_a_byte_order_mark_loads_as_without_one(tmp_path):
    from rt_ident.axis.params import CONFIG_DIR

    text = (CONFIG_DIR / "sim.toml").read_text(encoding="utf-8")
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))          # as Windows' Notepad saves UTF-8
    assert load(p).model_dump(exclude={"source"}) == load(CONFIG_DIR / "sim.toml").model_dump(exclude={"source"})


def test_a_folder_given_as_the_config_is_one_line_saying_so(tmp_path):
    with pytest.raises(ConfigError, match="is a folder") as e:
        load(tmp_path)
    assert e.value.field == str(tmp_path)


@pytest.mark.parametrize("name", ["x y", "../z", "a/b", "-x", "x" * 33, "é"])
def test_an_axis_name_that_could_not_name_its_files_is_refused_naming_it(name):
    with pytest.raises(ConfigError, match="an axis name is") as e:
        load("configs/xy-sim.toml").model_copy(update={"axes": {name: {}, "y": {}}}).axis_configs()
    assert e.value.field == f"axes.{name}"


def test_axis_names_of_letters_digits_dashes_and_underscores_are_taken():
    cfg = load("configs/xy-sim.toml").model_copy(update={"axes": {"X_1": {}, "y-2": {}, "3": {}}})
    assert list(cfg.axis_configs()) == ["X_1", "y-2", "3"]


@pytest.mark.parametrize(("reference", "needle"), [
    ({"kind": "sine", "amplitude": 0.005, "frequency_hz": 20.0}, "peak acceleration 78.9"),     # 20 for 2 Hz
    ({"kind": "sine", "amplitude": 0.001, "frequency_hz": 1000.0}, "peak acceleration"),      # the tick's own rate
    ({"kind": "moves", "positions": [0.01, 0.0], "v_max": 0.02, "a_max": 100.0, "j_max": 1e6}, "peak acceleration"),
], ids=["sine-20-hz", "sine-at-the-tick-rate", "move-100-m-s2"])
def test_a_reference_whose_acceleration_the_torque_limit_cannot_give_is_refused_before_enabling(reference, needle):
    e = _refused(_run_cfg(reference=reference, excitation={"peak": 0.1}, backend={"torque_limit": 1.0}))
    assert e.field == "reference" and needle in str(e) and "leaves beside the probe" in str(e), str(e)


def test_a_reference_faster_than_a_set_speed_limit_is_refused_and_one_within_it_is_taken():
    move = {"kind": "moves", "positions": [0.01, 0.0], "v_max": 0.02, "a_max": 0.5, "j_max": 50.0}
    e = _refused(_run_cfg(reference=move, safety={"max_speed_m_s": 0.01}))
    assert e.field == "reference" and "above safety.max_speed_m_s (10 mm/s)" in str(e), str(e)
    preflight(from_mapping(_run_cfg(reference=move, safety={"max_speed_m_s": 0.025})))
    preflight(from_mapping(_run_cfg(reference={"kind": "sine", "amplitude": 0.005, "frequency_hz": 2.0})))


def test_a_contour_section_the_run_would_ignore_is_refused_naming_where_the_circle_goes():
    with pytest.raises(ConfigError, match=r"does not read \[contour\].*per axis") as e:
        from_mapping(_run_cfg(contour={"kind": "circle", "radius": 0.005}))
    assert e.value.field == "contour"


# 2 ------------------------------------------------------------------------- the safety window
@pytest.mark.parametrize("window", [[0.04, -0.04], [0.01, 0.01], [math.nan, 0.04], [-0.04, math.inf]],
                         ids=["reversed", "empty", "nan", "inf"])
def test_a_safety_window_not_finite_and_ordered_is_refused_naming_safety_window(window):
    with pytest.raises(ConfigError) as e:
        from_mapping(_run_cfg(safety={"window": window}))
    assert e.value.field.startswith("safety.window")


def test_a_reversed_safety_window_is_one_line_on_the_command_line(tmp_path):
    p = _write(tmp_path, "[safety]\nwindow = [0.04, -0.04]\n")
    assert "min < max" in _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), "safety.window")


# 3 ------------------------------------------------------------------------- the sample period
def test_a_sample_period_the_loop_cannot_process_is_refused_before_any_allocation():
    e = _refused(_run_cfg(backend={"sample_period": 1e-12}))
    assert e.field == "backend.sample_period" and "1e-06 s" in str(e) and "samples/s" in str(e)
    preflight(from_mapping(_run_cfg(backend={"sample_period": 1e-6})))   # the bound itself runs


def test_a_picosecond_sample_period_is_one_line_on_the_command_line(tmp_path):
    p = _write(tmp_path, "[backend]\nname = \"sim\"\nsample_period = 1e-12\n")
    _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), "backend.sample_period")


# 4 ------------------------------------------------------------------------- physical parameters
@pytest.mark.parametrize(("key", "value"), [("I1", 1e300), ("I2", 1e-30), ("K", 1e12), ("B", 1e6), ("lead", 2.0)])
def test_axis_parameters_outside_a_machine_tool_axis_are_refused_naming_them(key, value):
    with pytest.raises(ConfigError, match="outside the range of a machine-tool axis") as e:
        from_mapping(_run_cfg(axis={key: value}))
    assert e.value.field == f"axis.{key}"


def test_a_plant_change_factor_beyond_the_axis_range_is_refused_naming_it():
    e = _refused(_run_cfg(plant={"change": [{"at": 0.5, "I2": 1e300}]}))
    assert e.field == "plant.change[0].I2"


def test_a_huge_inertia_is_one_line_on_the_command_line(tmp_path):
    p = _write(tmp_path, "[axis]\nI1 = 1e300\nI2 = 8.3e-6\nB = 2.1e-3\nK = 1.1e2\n")
    _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), "axis.I1")


# 5 ------------------------------------------------------------------------- SocketCAN
def _host_has_socketcan() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        return True
    except (AttributeError, OSError):
        return False


@pytest.mark.skipif(_host_has_socketcan(), reason="this host has SocketCAN")
@pytest.mark.parametrize("emulate", ["false", "true"])
def test_socketcan_on_a_host_without_it_is_one_line_naming_backend_interface(tmp_path, emulate):
    text = (REPO / "configs" / "canopen-virtual.toml").read_text()
    text = text.replace('interface = "udp_multicast"', 'interface = "socketcan"').replace(
        'channel = "239.74.163.2"', 'channel = "can0"').replace("emulate = true", f"emulate = {emulate}")
    p = _write(tmp_path, text)
    line = _one_line_error(_cli(["run", str(p), "--no-telemetry", "--no-realtime"], tmp_path), "backend.interface")
    assert "no SocketCAN on this host" in line and '"udp_multicast"' in line and '"virtual"' in line


# 6 ------------------------------------------------------------------------- a text angle column
def _recording_with_text_angle(path: Path, with_metadata: bool) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = 2048
    t = np.arange(n) * 1e-4
    th = np.sin(40.0 * t)
    tab = pa.table({"t": t, "seq": np.arange(n), "theta1": [f"{x:.6f}" for x in th], "theta2": th,
                    "torque_cmd": th, "torque_meas": th})
    if with_metadata:   # a run's metadata: identify replays it in record batches
        meta = {"backend": "sim", "sample_period": 1e-4, "method": "frequency", "warmup_periods": 0,
                "forgetting": 1.0, "excitation": {"period_samples": 512, "band": [1, 20]}}
        tab = tab.replace_schema_metadata({b"rt_ident.metadata": json.dumps(meta).encode()})
    pq.write_table(tab, path)
    return path


@pytest.mark.parametrize("with_metadata", [True, False], ids=["replayed", "batch"])
def test_identify_refuses_a_text_angle_column_in_one_line(tmp_path, with_metadata):
    from rt_ident.reports.identify import identify_file

    p = _recording_with_text_angle(tmp_path / "r.parquet", with_metadata)
    with pytest.raises(DataError, match=r"column 'theta1' holds string, not numbers"):
        identify_file(p)
    res = _cli(["identify", str(p)], tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == [f"error: {p}: column 'theta1' holds string, not numbers"]


# 8 ------------------------------------------------------------------------- the tick rate
def test_a_nan_tick_rate_is_refused_as_not_a_finite_number():
    with pytest.raises(ConfigError, match="finite number") as e:
        from_mapping(_run_cfg(loop={"tick_hz": math.nan}))
    assert e.value.field == "loop.tick_hz" and "20000" not in str(e.value)


@pytest.mark.parametrize("tick_hz", [0.1, 50.0, 5000.0, 20000.0])
def test_a_tick_rate_outside_its_range_is_refused_in_the_users_terms(tick_hz):
    with pytest.raises(ConfigError) as e:
        from_mapping(_run_cfg(loop={"tick_hz": tick_hz}))
    lo, hi = TICK_HZ_RANGE
    assert e.value.field == "loop.tick_hz" and f"between {lo:g} and {hi:g} ticks per second" in str(e.value)


def test_a_slow_tick_is_exit_2_naming_tick_hz_not_an_internal_name(tmp_path):
    p = _write(tmp_path, "[loop]\ntick_hz = 0.1\n[control]\nmode = \"off\"\n")
    line = _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), "loop.tick_hz")
    assert "spin_s" not in line and "period_s" not in line


def test_the_tick_rates_at_the_ends_of_the_range_pass_the_start_up_checks():
    for tick_hz in TICK_HZ_RANGE:
        cfg = from_mapping(_run_cfg(loop={"tick_hz": tick_hz}, control={"mode": "off", "drive_holds": True}))
        preflight(cfg)
        assert cfg.loop.tick_hz == tick_hz


# 9 ------------------------------------------------------------------------- torque ratings
def test_a_sim_torque_limit_above_the_rated_torque_is_refused_naming_torque_limit():
    e = _refused(_run_cfg(backend={"torque_limit": 1e9}))
    assert e.field == "backend.torque_limit" and "rated_torque 3 N m" in str(e)
    preflight(from_mapping(_run_cfg(backend={"torque_limit": 5.0, "rated_torque": 6.0})))   # a stronger motor


def test_a_serial_torque_limit_above_the_boards_current_range_is_refused_naming_torque_limit():
    from drivers.encoder_board.config import parse_serial

    with pytest.raises(ConfigError, match=r"32.767 A .* = 3.2767 N m") as e:
        parse_serial({"emulate": True, "torque_limit": 1e9, "torque_constant": 0.1})
    assert e.value.field == "backend.torque_limit"
    parse_serial({"emulate": True, "torque_limit": 3.0, "torque_constant": 0.1})


def test_a_huge_torque_limit_is_one_line_on_the_command_line(tmp_path):
    p = _write(tmp_path, "[backend]\nname = \"sim\"\ntorque_limit = 1e9\n")
    _one_line_error(_cli(["run", str(p), "--no-telemetry"], tmp_path), "backend.torque_limit")


# 10 ------------------------------------------------------------------------ missing sections
@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"], ids=["empty", "blank", "comment"])
def test_an_empty_config_file_is_an_error_saying_so(tmp_path, text):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError, match="config is empty"):
        load(p)


def test_a_config_without_axis_backend_safety_lists_them_as_defaulted(tmp_path):
    assert load(_write(tmp_path, "[loop]\nduration = 1\n")).defaulted == ("axis", "backend", "safety")
    assert load(_write(tmp_path, "[backend]\nname = \"sim\"\n", "b.toml")).defaulted == ("axis", "safety")
    assert load(REPO / "configs" / "sim.toml").defaulted == ()
    assert load(REPO / "configs" / "xy-sim.toml").defaulted == ()
    assert load(None).defaulted == ()                # no file: the shipped default, nothing to warn about


@pytest.mark.slow
def test_an_empty_config_is_exit_2_and_a_partial_one_warns_and_reports_config_defaulted(tmp_path):
    _one_line_error(_cli(["run", str(_write(tmp_path, "")), "--no-telemetry"], tmp_path), str(tmp_path / "c.toml"))
    p = _write(tmp_path, "[loop]\nduration = 0.3\nrealtime = false\n[recording]\nenabled = false\n", "p.toml")
    res = _cli(["run", str(p), "--no-telemetry", "--json"], tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    warning = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warning) == 1 and "[axis], [backend], [safety]" in warning[0] and "sim backend" in warning[0]
    assert json.loads(res.stdout)["config_defaulted"] == ["axis", "backend", "safety"]


# the loader's own error handling ------------------------------------------------------------
@pytest.mark.parametrize(("text", "field"), [
    ("loop = 5\n", "loop"),
    ("[backend]\nname = \"nope\"\n", "backend.name"),
    ("[loop]\nduration = inf\n", "loop.duration"),
    ("[backend]\nname = 5\n", "backend.name"),
    ("backend = 5\n[plant.friction]\nFc1 = 0.01\n", "backend"),
    ("[excitation]\npeak = nan\n", "excitation.peak"),
], ids=["section-not-a-table", "unknown-backend", "inf-duration", "backend-name-not-a-string",
        "backend-not-a-table-beside-friction", "nan-peak"])
def test_malformed_sections_and_values_are_config_errors_naming_the_field(tmp_path, text, field):
    with pytest.raises(RtIdentError) as e:
        preflight(load(_write(tmp_path, text)))
    assert str(e.value).startswith(f"{field}") and "\n" not in str(e.value)


def test_an_axis_lead_that_differs_from_the_backends_is_refused_naming_axis_lead():
    with pytest.raises(ConfigError, match=r"axis\.lead: .* differs from backend\.lead"):
        from_mapping({"axis": {"I1": 2.7e-5, "I2": 8.3e-6, "B": 2.1e-3, "K": 110.0, "lead": 7.96e-4},
                             "backend": {"name": "serial", "lead": 1.592e-3}})


@pytest.mark.parametrize(("backend", "key"), [({"name": "sim", "scale_resolution": 1e-3}, "scale_resolution"),
                                               ({"name": "serial", "scale_resolution": 1e-12}, "scale_resolution"),
                                               ({"name": "serial", "counts_per_rev": 2**30}, "counts_per_rev")])
def test_scale_and_encoder_counts_that_cannot_be_true_of_the_window_are_refused(backend, key):
    with pytest.raises(ConfigError, match=rf"backend\.{key}"):
        from_mapping({"backend": backend})


def test_an_eds_beside_the_config_is_the_one_used_from_any_folder_and_a_missing_one_names_the_key_set(
        tmp_path, monkeypatch):
    from rt_ident.axis.params import CONFIG_DIR

    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "drive.eds").write_text((CONFIG_DIR / "cia402_generic.eds").read_text())
    text = (CONFIG_DIR / "canopen-virtual.toml").read_text().replace('eds = "cia402_generic.eds"', 'eds = "drive.eds"')
    (bench / "axis.toml").write_text(text)
    (bench / "other.toml").write_text(text.replace('"drive.eds"', '"nothere.eds"'))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert load(str(bench / "axis.toml")).backend.options()["eds"] == str(bench / "drive.eds")
    from drivers.cia402.emulator import build_emulator_for

    with pytest.raises(ConfigError, match=r"^backend.eds: EDS file not found: nothere.eds \(looked in "):
        build_emulator_for(load(str(bench / "other.toml")))


@pytest.mark.parametrize(("section", "data", "line"), [
    ("top", {"safty": {"window": [-0.01, 0.01]}}, "safty: unknown key (did you mean safety?)"),
    ("excitation", {"excitation": {"peek": 0.3}}, "excitation.peek: unknown key (did you mean peak?)"),
    ("loop", {"loop": {"tickhz": 1000}}, "loop.tickhz: unknown key (did you mean tick_hz?)"),
    ("nothing near", {"loop": {"xyzzy": 1}}, "loop.xyzzy: unknown key; the keys here: tick_hz, "),
])
def test_a_mistyped_key_is_called_unknown_and_the_nearest_keys_are_named(section, data, line):
    with pytest.raises(ConfigError) as err:
        from_mapping({"axis": AXIS, **data})
    assert str(err.value).startswith(line), str(err.value)


@pytest.mark.parametrize(("backend", "plant", "line"), [
    ({"name": "serial", "emulate": True, "baudrat": 1}, {}, "backend.baudrat: unknown key (did you mean baudrate?)"),
    # the typo is reported, not the field it was meant to be as missing
    ({"name": "canopen", "emulate": True, "nodeid": 5}, {}, "backend.nodeid: unknown key (did you mean node_id or "),
    ({"name": "sim"}, {"actual": {"torque_scal": 2.0}},
     "plant.actual.torque_scal: unknown key (did you mean torque_scale or torque_sign?)"),
])
def test_a_mistyped_device_key_is_named_with_the_nearest_ones_by_the_devices_own_check(backend, plant, line):
    with pytest.raises(ConfigError) as err:
        preflight(from_mapping({"axis": AXIS, "backend": backend, "plant": plant}))
    assert str(err.value).startswith(line), str(err.value)


def test_a_mistyped_key_of_a_reference_kind_names_that_kinds_keys():
    from rt_ident.control.reference import make_reference

    with pytest.raises(ConfigError, match=r"^reference\.positons: unknown key \(did you mean positions\?\)$"):
        make_reference({"kind": "moves", "positons": [0.001]})
    with pytest.raises(ConfigError, match=r"^reference\.postion: unknown key \(did you mean position\?\)$"):
        make_reference({"kind": "hold", "postion": 0.001})

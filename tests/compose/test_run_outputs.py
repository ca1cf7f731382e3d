"""A run's output files: never overwritten silently, unique by default, and every path, suffix and
method checked in one line before anything starts."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rt_ident.cli import app
from rt_ident.compose import run as run_mod
from rt_ident.config import load
from rt_ident.errors import ConfigError
from rt_ident.outputs import paths as outputs
from rt_ident.processes.recorder import read_recording

runner = CliRunner()


@pytest.mark.slow
def test_two_runs_started_in_the_same_second_write_separate_files(tmp_path):
    cmd = [sys.executable, "-m", "rt_ident", "run", "--duration", "1", "--no-realtime", "--json"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    errs = [p.communicate(timeout=180)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    recs = sorted((tmp_path / "runs").glob("run-*.parquet"))
    rrds = sorted((tmp_path / "runs").glob("run-*.rrd"))
    assert len(recs) == 2 and len(rrds) == 2, os.listdir(tmp_path / "runs")
    for r in recs:
        assert len(read_recording(r)) > 0


def test_default_names_differ_even_within_one_process_and_second(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rrd1, rec1 = outputs.default_paths(stamp="same")
    rec1.parent.mkdir()
    rec1.write_bytes(b"x")
    rrd2, rec2 = outputs.default_paths(stamp="same")
    assert rec2 != rec1 and rrd2 != rrd1 and not rec2.exists()


def test_an_explicit_path_that_exists_is_refused_unless_overwrite(tmp_path):
    rec = tmp_path / "r.parquet"
    rec.write_bytes(b"precious")
    res = runner.invoke(app, ["run", "--duration", "0.2", "--no-realtime", "--no-telemetry", "--record", str(rec)])
    assert res.exit_code != 0 and "exists" in str(res.exception) and "--overwrite" in str(res.exception)
    assert rec.read_bytes() == b"precious"
    other = tmp_path / "d.rrd"
    other.write_bytes(b"old dashboard")
    with pytest.raises(ConfigError, match="exists"):
        run_mod.run(load(None, **{"loop.duration": 0.2, "loop.realtime": False, "recording.enabled": False}),
                    rrd=str(other), sink="rrd")
    assert other.read_bytes() == b"old dashboard"


def test_overwrite_replaces_an_existing_recording(tmp_path):
    rec = tmp_path / "r.parquet"
    rec.write_bytes(b"old")
    s = run_mod.run(load(None, **{"loop.duration": 0.3, "loop.realtime": False, "telemetry.sink": "off"}),
                    record=str(rec), overwrite=True)
    assert s["recording"]["complete"] and len(read_recording(rec)) == s["loop"]["samples"]


_WRITING = ("import sys; from rt_ident.outputs.paths import OutputClaims; c = OutputClaims(); "
            "[c.claim(p, 'x') for p in sys.argv[1:]]; open(sys.argv[1] + '.arrows', 'wb').write(b'live'); "
            "print('held', flush=True); sys.stdin.read(); c.release()")


def test_files_another_run_is_writing_are_refused_before_anything_starts_even_with_overwrite(tmp_path, monkeypatch):
    rec, rrd = tmp_path / "r.parquet", tmp_path / "d.rrd"           # its journal exists; its dashboard not yet
    other = subprocess.Popen([sys.executable, "-c", _WRITING, str(rec), str(rrd)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    cfg = load(None, **{"loop.duration": 0.3, "loop.realtime": False})
    try:
        assert other.stdout is not None and other.stdout.readline().strip() == "held"
        made = []
        with monkeypatch.context() as m:
            m.setattr(run_mod, "make_backend", lambda *a, **k: made.append(a) or pytest.fail("backend made"))
            with pytest.raises(ConfigError, match=rf"^--record / recording.path: {rec} is being written by another "
                                                  rf"run \(pid {other.pid} "):
                run_mod.run(cfg, record=str(rec), sink="off", overwrite=True)
            with pytest.raises(ConfigError, match=rf"^--rrd / telemetry.rrd: {rrd} is being written .*pid {other.pid}"):
                run_mod.run(cfg, rrd=str(rrd), sink="rrd", record=str(tmp_path / "mine.parquet"))
        assert not made and (tmp_path / "r.parquet.arrows").read_bytes() == b"live" and not rrd.exists()
    finally:
        other.communicate(timeout=30)                 # ends it, its claims released
    for _ in range(2):                                # the other run gone, and this one's claims let go at its end
        s = run_mod.run(cfg, record=str(rec), sink="off", overwrite=True)
        assert s["recording"]["complete"]


def test_a_recorder_that_stalls_stops_the_run_without_holding_the_loop_and_its_lost_samples_are_counted(
        tmp_path, monkeypatch):
    import signal
    import threading

    from rt_ident.processes import recorder as recorder_mod

    class SmallRing(recorder_mod.RecorderProcess):         # fills in well under the 2 s hang, not ~30 s,
        def __init__(self, *args, **kwargs):                # and holds the block a busy host's stall hands over
            super().__init__(*args, **{**kwargs, "ring_bytes": 1 << 20})

    monkeypatch.setattr(recorder_mod, "RecorderProcess", SmallRing)
    made: list[SmallRing] = []
    real_start = SmallRing.start
    monkeypatch.setattr(SmallRing, "start", lambda self: made.append(self) or real_start(self))
    waits: list[float] = []
    real_sleep = recorder_mod.time.sleep

    def hook(n: int) -> None:
        if n == 300:                                         # the recorder's disk hangs for 2 s
            os.kill(made[0].pid, signal.SIGSTOP)
            threading.Timer(2.0, os.kill, (made[0].pid, signal.SIGCONT)).start()
            monkeypatch.setattr(recorder_mod.time, "sleep", lambda s: (waits.append(s) if sys._getframe(1).f_code
                                                                       is recorder_mod.RecorderProcess._wait_for_room
                                                                       .__code__ else None) or real_sleep(s))

    rec = tmp_path / "r.parquet"
    cfg = load(None, **{"loop.duration": 5.0, "loop.realtime": False, "telemetry.sink": "off"})
    s = run_mod.run(cfg, record=str(rec), tick_hook=hook)
    assert s["stop"]["cause"] == "error" and "fell a whole ring behind" in s["stop"]["message"], s["stop"]
    assert waits == []                                       # the tick never waited for room
    r = s["recording"]
    assert r["samples_refused"] > 0 and not r["complete"]
    assert s["loop"]["samples"] == r["rows_written"] + r["samples_refused"] == len(read_recording(rec)) + \
        r["samples_refused"]
    assert f"{r['rows_written']} of {s['loop']['samples']} samples written: the recorder of" in s["data_lost"]


@pytest.mark.parametrize("args,needle", [
    (["--record", "r.txt"], "must end in .parquet"),
    (["--rrd", "dash.png"], "must end in .rrd"),
    (["--record", "/proc/foo/r.parquet"], "cannot create the directory"),
    (["--method", "tustin"], "no streaming form"),
])
def test_bad_paths_and_methods_fail_in_one_line_before_anything_starts(tmp_path, monkeypatch, args, needle):
    monkeypatch.chdir(tmp_path)
    started = []
    monkeypatch.setattr(run_mod, "make_backend", lambda *a, **k: started.append(a) or pytest.fail("backend made"))
    t0 = time.monotonic()
    res = runner.invoke(app, ["run", "--duration", "0.2", "--no-realtime", *args])
    assert res.exit_code != 0, res.output
    assert needle in str(res.exception)
    assert not started and time.monotonic() - t0 < 30        # refused at once, nothing started
    assert not Path("runs").exists() or not any(Path("runs").iterdir())      # no file left behind


@pytest.mark.xdist_group("realtime")
def test_a_run_that_fails_before_any_sample_says_why_once_and_leaves_no_file(tmp_path):
    import re

    from rt_ident.axis.params import CONFIG_DIR

    text = re.sub(r"^emulate = true", 'emulate = false\nport = "/dev/ttyNOPE"',
                  (CONFIG_DIR / "serial-virtual.toml").read_text(), flags=re.M)
    (tmp_path / "bad.toml").write_text(text)
    p = subprocess.run([sys.executable, "-m", "rt_ident", "run", "bad.toml", "--duration", "1"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 3
    text = p.stdout + p.stderr
    assert text.count("/dev/ttyNOPE': [Errno 2]") == 1, text        # the cause, once
    assert "Traceback" not in text and "no estimate" not in text and "param" not in text, text
    runs = tmp_path / "runs"
    assert not runs.exists() or not any(runs.iterdir()), list(runs.iterdir())


def test_serve_moves_to_a_free_port_when_9876_is_taken_and_refuses_a_taken_configured_port():
    import socket

    from rt_ident.outputs.sinks import DEFAULT_PORT

    holder, mine = socket.socket(), socket.socket()
    try:
        try:
            holder.bind(("127.0.0.1", DEFAULT_PORT))
        except OSError:
            pass                          # taken already (another run): the run must move anyway
        mine.bind(("127.0.0.1", 0))       # a port this test surely holds
        s = run_mod.run(load(None, **{"loop.duration": 0.3, "loop.realtime": False, "recording.enabled": False}),
                        sink="serve")
        assert s["stop"]["cause"] is None
        port = int(s["serve_url"].rsplit(":", 1)[1].split("/")[0])
        assert port != DEFAULT_PORT and s["serve_url"].startswith("rerun+http://127.0.0.1:")
        with pytest.raises(ConfigError, match="in use"):
            run_mod.run(load(None, **{"loop.duration": 0.3, "loop.realtime": False, "recording.enabled": False,
                                      "telemetry.port": mine.getsockname()[1]}), sink="serve")
    finally:
        holder.close()
        mine.close()


def test_spawn_without_a_display_is_refused_in_one_line_unless_a_viewer_already_listens(tmp_path, monkeypatch):
    import socket

    from rt_ident.outputs.sinks import TelemetryConfig, spawn_refusal

    for var in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.chdir(tmp_path)
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    from rt_ident.axis.params import CONFIG_DIR

    text = (CONFIG_DIR / "sim.toml").read_text().replace('[telemetry]\nsink = "rrd"', f'[telemetry]\nport = {port}')
    assert f"port = {port}" in text
    Path("spawn.toml").write_text(text)                            # a port no other test's viewer may hold
    res = runner.invoke(app, ["run", "spawn.toml", "--duration", "0.2", "--no-realtime", "--spawn"])
    assert res.exit_code != 0 and str(res.exception).startswith("--spawn / telemetry.sink: no display here")
    assert not Path("runs").exists()                               # refused before anything started
    assert spawn_refusal(TelemetryConfig(sink="spawn", port=port), {"DISPLAY": ":0"}) is None
    viewer = socket.socket()                                       # a viewer someone left running on this host
    viewer.bind(("127.0.0.1", port))
    viewer.listen()
    try:
        assert spawn_refusal(TelemetryConfig(sink="spawn", port=port), {}) is None
    finally:
        viewer.close()
    assert "ssh session" in (spawn_refusal(TelemetryConfig(sink="spawn", port=port), {}) or "")


def test_a_bad_eds_is_named_without_echoing_its_contents(tmp_path):
    from drivers import make_backend

    secret = "password=hunter2 this line must not be echoed"
    eds = tmp_path / "bad.eds"
    eds.write_text(secret + "\n[broken\n")
    from rt_ident.axis.params import CONFIG_DIR

    opts = load(CONFIG_DIR / "canopen-virtual.toml").backend.options()
    opts.update(interface="virtual", channel="eds-test", eds=str(eds), bus_options={})
    opts.pop("port", None)
    be = make_backend("canopen", opts)
    with pytest.raises(ConfigError) as info:
        be.open()
    be.close()
    assert "bad.eds" in str(info.value) and "hunter2" not in str(info.value)


@pytest.mark.parametrize("url", ["socket://127.0.0.1:9", "spy://loop://?file=/tmp/x", "rfc2217://h:1"])
def test_pyserial_urls_need_an_explicit_opt_in(url):
    from drivers import make_backend

    with pytest.raises(ConfigError, match="allow_url"):
        make_backend("serial", {"port": url})
    be = make_backend("serial", {"port": url, "allow_url": True})     # accepted when asked for
    assert be is not None


def _full_disk(path: Path) -> None:
    """Point ``path`` at /dev/full: every write to it fails with ENOSPC, as on a full disk."""
    path.symlink_to("/dev/full")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_disk_full_at_start_stops_before_the_device_is_enabled_in_one_line(tmp_path):
    rec = tmp_path / "r.parquet"
    _full_disk(tmp_path / "r.parquet.part")                # the Parquet header, written at open, fails
    energized = []
    from drivers.sim import SimBackend

    orig = SimBackend.activate

    def activate(self):
        energized.append(True)
        return orig(self)

    SimBackend.activate = activate
    try:
        s = run_mod.run(load(None, **{"loop.duration": 1.0, "loop.realtime": False, "telemetry.sink": "off"}),
                        record=str(rec), overwrite=True)
    finally:
        SimBackend.activate = orig
    assert not energized, "the device was enabled although the recording could not be written"
    assert s["stop"]["cause"] is not None and "ENOSPC" in s["stop"]["message"], s["stop"]
    assert "r.parquet" in s["stop"]["message"] and "\n" not in s["stop"]["message"]
    assert run_mod.exit_code(s) == 3


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_disk_that_fills_mid_run_stops_safely_and_never_reports_rows_it_did_not_write(tmp_path):
    rec = tmp_path / "r.parquet"
    _full_disk(tmp_path / "r.parquet.arrows")              # the journal's first batch (0.5 s in) fails
    s = run_mod.run(load(None, **{"loop.duration": 5.0, "loop.realtime": False, "telemetry.sink": "off"}),
                    record=str(rec), overwrite=True)
    assert s["stop"]["cause"] is not None and "ENOSPC" in s["stop"]["message"], s["stop"]
    assert s["stop"]["final_torque"] == 0.0
    assert not s["recording"]["complete"] and "ENOSPC" in s["data_lost"]
    assert s["recording"]["rows_written"] < s["loop"]["samples"]
    assert run_mod.exit_code(s) == 3


def test_a_dashboard_file_that_cannot_be_written_is_reported_lost_with_exit_4(tmp_path, monkeypatch):
    from rt_ident.processes.telemetry import TelemetryProcess

    def written(self):
        return {"written": False, "write_error": f"no space left on the device of {self.config.rrd_path}"}

    monkeypatch.setattr(TelemetryProcess, "_written", written)
    s = run_mod.run(load(None, **{"loop.duration": 0.5, "loop.realtime": False, "recording.enabled": False}),
                    rrd=str(tmp_path / "d.rrd"))
    assert s["stop"]["cause"] is None
    assert s["telemetry"]["written"] is False and "d.rrd" in s["telemetry"]["write_error"]
    assert "dashboard" in s["data_lost"] and "d.rrd" in s["data_lost"]
    assert run_mod.exit_code(s) == 4


def test_a_full_disk_stops_the_dashboard_and_is_never_reported_as_written(tmp_path):
    """The child checks the free space before each batch (rerun's file sink reports a failed write to
    nobody): with a bound no disk meets, nothing is sent and close() says why."""
    import numpy as np

    from rt_ident.outputs.sinks import TelemetryConfig
    from rt_ident.processes.telemetry import TelemetryProcess

    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "f.rrd"), min_free_bytes=1 << 62))
    tp.start()
    assert tp.wait_ready(20.0)
    for k in range(5):
        assert tp.publish({"t": np.arange(10.0) + 10 * k, "theta1": np.zeros(10)})
    out = tp.close(timeout=10.0)
    assert out["sent"] == 0 and out["written"] is False and "no space left" in out["write_error"]


def test_free_space_check_names_the_file(tmp_path):
    from rt_ident.outputs.sinks import disk_full

    assert disk_full(str(tmp_path / "x.rrd"), 1) is None
    why = disk_full(str(tmp_path / "x.rrd"), 1 << 62)
    assert why is not None and "x.rrd" in why and "no space left" in why


def test_an_incomplete_recording_whose_journal_is_left_says_where_and_how_to_read_it(tmp_path):
    from rt_ident.compose.helpers import recording_lost

    rec = tmp_path / "r.parquet"
    report = {"path": str(rec), "rows_written": 5, "samples_put": 9, "failure": "no space left on the device"}
    assert "journal" not in recording_lost(report) and ".arrows" not in recording_lost(report)
    (tmp_path / "r.parquet.arrows").write_bytes(b"x" * 64)
    text = recording_lost(report)
    assert f"{rec}.arrows" in text and f"rt-ident identify {rec} reads it" in text and "; " not in text


def test_a_recording_that_is_not_complete_is_reported_in_the_same_words_on_one_axis_and_two(tmp_path, monkeypatch):
    from rt_ident.compose.run import run
    from rt_ident.processes.recorder import RecorderProcess

    real_close = RecorderProcess.close

    def close(self, *a, **k):
        r = real_close(self, *a, **k)
        return {**r, "complete": False, "rows_written": 7, "failure": "no space left on the device"}

    monkeypatch.setattr(RecorderProcess, "close", close)
    quiet = {"loop.realtime": False, "loop.duration": 0.3, "telemetry.sink": "off"}
    one = run(load(None, **quiet), record=str(tmp_path / "one.parquet"))
    two = run(load("configs/xy-sim.toml", **quiet), record=str(tmp_path / "two.parquet"))
    import re

    def words(text: str, path) -> str:
        return re.sub(r"\d+ of \d+", "N of M", text.replace(str(path), "PATH"))

    expected = "recording PATH incomplete: N of M samples written: no space left on the device"
    assert words(one["data_lost"], tmp_path / "one.parquet") == expected
    for axis, text in zip("xy", two["data_lost"].split("; "), strict=True):
        name, body = text.split(": ", 1)
        assert name == axis and words(body, tmp_path / f"two-{axis}.parquet") == expected
    assert run_mod.exit_code(one) == run_mod.exit_code(two) == 4

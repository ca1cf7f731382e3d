"""However a run ends (Ctrl-C, SIGTERM or SIGHUP to the group, its terminal closed, kill -9 of the main
process), it leaves complete files, no orphan process, and an exit code and summary that tell the truth."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rt_ident.processes.recorder import read_recording

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="process groups and /proc")


def _group(pgid: int) -> list[int]:
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if os.getpgid(int(d.name)) == pgid:
                    pids.append(int(d.name))
            except (ProcessLookupError, PermissionError):
                pass
    return pids


def _start(tmp_path: Path) -> tuple[subprocess.Popen, Path, Path]:
    rec, rrd = tmp_path / "r.parquet", tmp_path / "r.rrd"
    cmd = [sys.executable, "-m", "rt_ident", "run", "--duration", "60", "--no-realtime", "--json",
           "--record", str(rec), "--rrd", str(rrd)]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    journal = rec.with_name(rec.name + ".arrows")
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and (not journal.exists() or journal.stat().st_size < 100_000):
        if proc.poll() is not None:
            pytest.fail(f"the run ended before it recorded: {proc.stderr.read()[-2000:]}")
        time.sleep(0.1)
    assert journal.exists(), "the run never started recording"
    return proc, rec, rrd


def _wait_group_empty(pgid: int, timeout: float) -> list[int]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        left = _group(pgid)
        if not left:
            return []
        time.sleep(0.1)
    return _group(pgid)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["ctrl-c", "sigterm", "sighup"])
@pytest.mark.slow
def test_a_signal_to_the_whole_group_records_every_sample_and_exits_cleanly(tmp_path, sig, sighup_default):
    proc, rec, rrd = _start(tmp_path)
    try:
        os.killpg(proc.pid, sig)                 # what a terminal's Ctrl-C / systemd's stop do
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    assert proc.returncode == 0, err[-2000:]
    s = json.loads(out)
    assert s["stop"]["interrupted"] and s["stop"]["cause"] is None
    assert s["recording"]["complete"] and "data_lost" not in s
    assert len(read_recording(rec)) == s["loop"]["samples"] == s["recording"]["rows_written"]
    assert rrd.exists() and rrd.stat().st_size > 0
    assert _wait_group_empty(proc.pid, 5.0) == []


@pytest.mark.slow
def test_a_run_whose_terminal_closes_stops_safely_with_complete_files_and_its_own_exit_code(tmp_path, sighup_default):
    import pty

    rec, rrd = tmp_path / "r.parquet", tmp_path / "r.rrd"
    pid, fd = pty.fork()                        # the run on a terminal of its own, as in an ssh session
    if pid == 0:
        os.chdir(tmp_path)
        os.execv(sys.executable, [sys.executable, "-m", "rt_ident", "run", "--duration", "60", "--no-realtime",
                                  "--record", str(rec), "--rrd", str(rrd)])
    journal = rec.with_name(rec.name + ".arrows")
    seen = b""
    deadline = time.monotonic() + 90
    status = None
    try:
        while time.monotonic() < deadline and (not journal.exists() or journal.stat().st_size < 100_000):
            try:
                seen += os.read(fd, 65536) if select.select([fd], [], [], 0.1)[0] else b""
            except OSError:
                break
        assert journal.exists(), seen.decode(errors="replace")[-2000:]
        os.close(fd)                            # the terminal goes away: SIGHUP, then EIO on every write
        fd = -1
        end = time.monotonic() + 60
        while time.monotonic() < end:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = st
                break
            time.sleep(0.05)
        assert status is not None, "the run went on after its terminal closed"
    finally:
        if fd >= 0:
            os.close(fd)
        if status is None:
            os.killpg(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0      # stopped on request, as Ctrl-C; not the output's failure
    assert len(read_recording(rec)) > 0 and not journal.exists() and rrd.stat().st_size > 0
    assert _wait_group_empty(pid, 5.0) == []


@pytest.mark.slow
def test_kill_9_of_the_main_process_leaves_no_orphan_and_a_finished_recording(tmp_path):
    proc, rec, rrd = _start(tmp_path)
    time.sleep(1.0)
    os.kill(proc.pid, signal.SIGKILL)           # the main process only: its helpers must notice
    proc.communicate(timeout=30)
    try:
        left = _wait_group_empty(proc.pid, 5.0)
    finally:
        if _group(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
    assert left == [], f"orphans still running 5 s after kill -9: {left}"
    # the recorder finished the file from what it had received, not only up to the last journal flush
    assert rec.exists(), "no finished Parquet file after kill -9"
    assert not rec.with_name(rec.name + ".part").exists() and not rec.with_name(rec.name + ".arrows").exists()
    assert len(read_recording(rec)) > 0
    assert rrd.exists() and rrd.stat().st_size > 0


@pytest.mark.slow
def test_a_dead_fit_worker_and_telemetry_are_reported_at_once_and_restarted(tmp_path, monkeypatch):
    import multiprocessing as mp

    from rt_ident.compose import run as run_mod
    from rt_ident.config import load
    from rt_ident.processes import guard

    # the fit processes not niced: a replacement takes the first one's nice value (15, tested in
    # tests/processes/test_jobs.py), and beside a busy host that share of a CPU may give no fit in the seconds left
    monkeypatch.setitem(guard.HELPER_NICE, "fit", 0)

    killed = []
    before = {p.pid for p in mp.active_children()}       # helpers of earlier tests are not this run's

    def hook(n: int) -> None:
        if n == 1000:                                    # 4 s left: a respawn imports for ~1 s, longer on a busy host
            for p in mp.active_children():
                if p.name in ("rt_ident-fit", "rt_ident-telemetry") and p.pid not in before:
                    os.kill(p.pid, signal.SIGKILL)
                    killed.append(p.name)

    import logging

    class Keep(logging.Handler):
        def __init__(self):
            super().__init__(logging.ERROR)
            self.records = []

        def emit(self, record):
            self.records.append(record)

    keep = Keep()
    helpers_log = logging.getLogger("rt_ident.processes.guard")
    helpers_log.addHandler(keep)
    rrd = tmp_path / "d.rrd"
    # what is tested is the helper watch, not the control: the drive holds the axis (a torque-mode axis
    # with the host's loop starved by a CPU hog while processes are respawned could run to its limit)
    cfg = load(None, **{"loop.duration": 6.0, "loop.realtime": False, "recording.enabled": False,
                        "control.mode": "off", "backend.position_hold": True})
    try:
        s = run_mod.run(cfg, rrd=str(rrd), sink="rrd", tick_hook=hook)
    finally:
        helpers_log.removeHandler(keep)
    assert sorted(killed) == ["rt_ident-fit", "rt_ident-telemetry"], (killed, s.get("helpers"))
    assert s["stop"]["cause"] is None, s["stop"]
    for name in ("fit", "telemetry"):
        st = s["helpers"][name]
        assert st["deaths"] == 1 and st["restarts"] == 1 and st["alive"], st
        assert any(f"helper {name} died" in r.getMessage() for r in keep.records), (
            helpers_log.disabled, helpers_log.getEffectiveLevel(), logging.root.manager.disable, keep.records)
    # the dead child's file is kept, the restarted one writes the next
    assert s["files"]["rrd_earlier"] == [str(rrd)] and Path(s["files"]["rrd"]).name == "d-2.rrd"
    assert Path(s["files"]["rrd"]).stat().st_size > 0
    assert s["helpers"]["fit"]["results_since_restart"] >= 1, s["helpers"]   # live estimates came back


@pytest.mark.slow
def test_a_restarted_telemetry_that_never_opens_its_file_is_not_named_as_the_dashboard(tmp_path):
    import multiprocessing as mp

    from rt_ident.compose import run as run_mod
    from rt_ident.config import load

    before = {p.pid for p in mp.active_children()}
    killed: list[int] = []
    stopped: list[int] = []

    def hook(n: int) -> None:                            # kill the telemetry, then stop its replacement at birth
        for p in mp.active_children():
            if p.name != "rt_ident-telemetry" or p.pid in before or p.pid in killed:
                continue
            if n == 1000:
                os.kill(p.pid, signal.SIGKILL)
                killed.append(p.pid)
            elif n > 1000 and not stopped:
                os.kill(p.pid, signal.SIGSTOP)
                stopped.append(p.pid)

    rrd = tmp_path / "d.rrd"
    cfg = load(None, **{"loop.duration": 3.0, "loop.realtime": False, "recording.enabled": False,
                        "control.mode": "off", "backend.position_hold": True})
    s = run_mod.run(cfg, rrd=str(rrd), sink="rrd", tick_hook=hook)
    assert killed and stopped, (killed, stopped, s.get("helpers"))
    replacement = tmp_path / "d-2.rrd"
    assert not replacement.exists()
    files = s["files"]
    assert files["rrd"] is None and files["not_written"] == [str(replacement)], files
    assert files["rrd_earlier"] == [str(rrd)] and rrd.stat().st_size > 0
    assert f"{replacement} was never written" in s["data_lost"], s.get("data_lost")
    for pid in stopped:                                  # the stopped replacement was ended, not left behind
        assert not Path(f"/proc/{pid}").exists() or Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"


@pytest.mark.slow
def test_a_control_process_that_stops_answering_is_restarted_and_the_load_change_still_gets_its_design(
        tmp_path, monkeypatch):
    # SIGSTOPped before the plant changes (I2 x 3 at 1 s): the request for the new plant is never taken.
    # The watch finds it hung and restarts it, and the supervisor asks the new process again
    import multiprocessing as mp

    from rt_ident.compose import run as run_mod
    from rt_ident.config import load
    from rt_ident.processes import guard

    monkeypatch.setattr(guard, "HANG_S", 2.0)
    before = {p.pid for p in mp.active_children()}
    stopped: list[int] = []

    def hook(n: int) -> None:
        if n == 300:
            stopped.extend(p.pid for p in mp.active_children() if p.name == "rt_ident-control" and p.pid not in before)
            for pid in stopped:
                os.kill(pid, signal.SIGSTOP)

    cfg = load(Path(__file__).resolve().parents[2] / "configs" / "sim-load-change.toml",
               **{"loop.duration": 6.0, "loop.realtime": False, "recording.enabled": False,
                  "telemetry.sink": "off"})
    cfg = cfg.model_copy(update={"plant": cfg.plant.model_copy(update={
        "change": [{**c, "at": 1.0} for c in cfg.plant.change]})})
    try:
        s = run_mod.run(cfg, tick_hook=hook)
    finally:
        for pid in stopped:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
    assert len(stopped) == 1 and s["stop"]["cause"] is None, (stopped, s["stop"])
    st = s["helpers"]["control"]
    assert st["hangs"] == 1 and st["restarts"] == 1 and st["alive"] and st["pid"] != stopped[0], st
    with pytest.raises(ProcessLookupError):
        os.kill(stopped[0], 0)                       # the hung process was ended, not left behind
    events = s["control"]["events"]
    lost = [e for e in events if e["kind"] == "request lost"]
    assert len(lost) == 1 and lost[0]["t"] > 1.0, events
    after = [a for a in s["control"]["applied"] if a["kind"] == "model" and a["t"] > lost[0]["t"]]
    assert after and after[0]["model"]["I2"] == pytest.approx(3 * 8.3e-6, rel=0.1), (s["control"]["applied"], events)


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("realtime", [True, False], ids=["real-time", "not-real-time"])
def test_a_run_the_host_ended_names_what_is_left_to_change_given_its_real_time(realtime, restore_scheduling):
    # a stop put on the host asks for loop.realtime = true only where the run was not real-time already
    from drivers.errors import HeartbeatLost
    from rt_ident.compose import run as run_mod
    from rt_ident.config import load

    def drive_heard_nothing(tick: int) -> None:
        if tick == 100:
            raise HeartbeatLost("node 5 sent EMCY 0x8130")

    cfg = load(None, **{"loop.duration": 0.5, "loop.realtime": realtime, "telemetry.sink": "off",
                        "recording.enabled": False, "control.mode": "off", "backend.position_hold": True})
    s = run_mod.run(cfg, tick_hook=drive_heard_nothing)
    fix = s["stop"]["fix"]
    assert s["stop"]["cause"] == "device-fault" and run_mod.exit_code(s) == 3
    if not realtime:
        assert fix == HeartbeatLost.fix
    elif s["realtime"]["sched_fifo"] is True:
        assert fix.startswith("loop.realtime is on and the loop ran at SCHED_FIFO: a less busy host (else a "
                              "longer backend.heartbeat_consumer_ms)"), fix
    else:
        refused = s["realtime"]["sched_fifo"]
        assert fix.startswith(f"loop.realtime is on but the loop ran without SCHED_FIFO ({refused})"), fix

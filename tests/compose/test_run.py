"""The real-time loop end to end against the sim backend (sink off or .rrd; realtime off in tests)."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from rt_ident import config
from rt_ident.compose.run import run
from rt_ident.errors import DataError
from rt_ident.processes.recorder import read_recording
from rt_ident.reports.identify import identify_file

PARAMS = ("I1", "I2", "B", "K", "wn", "wd", "zeta")


def cfg(**over):
    data = {"loop": {"realtime": False, "duration": 1.2},
            "backend": {"name": "sim", "paced": False, "torque_meas_noise": 0.0005},
            "telemetry": {"sink": "off"}}
    for dotted, v in over.items():
        sec, _, key = dotted.partition("__")
        data.setdefault(sec, {})[key] = v
    return config.from_mapping(data)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    rec = d / "r.parquet"
    rrd = d / "r.rrd"
    s = run(cfg(telemetry__sink="rrd"), rrd=str(rrd), record=str(rec))
    return s, rec, rrd


def test_loop_identifies_the_quantized_closed_loop_plant_within_2_percent(recorded):
    s, _, _ = recorded
    assert s["stop"]["cause"] is None
    for k in PARAMS:
        assert abs(s["error_pct"][k]) < 2.0, (k, s["error_pct"][k])


def test_summary_reports_host_steal_time_around_the_loop(recorded):
    s, _, _ = recorded
    host = s["loop"]["host"]
    assert set(host) == {"steal_ms", "steal_cpu", "interrupts"}
    if os.path.exists("/proc/stat"):
        assert host["steal_ms"] is not None and host["steal_ms"] >= 0.0


def test_loop_final_estimate_equals_identify_on_its_own_recording(recorded):
    s, rec, _ = recorded
    if s["loop"]["stalls"]["count"]:
        # after a stall the loop leaves the excitation periods it touched out of the fit, and the
        # recording does not carry the stall: the two are then not the same computation
        pytest.skip(f"the loop stalled ({s['loop']['stalls']['count']}x, longest "
                    f"{s['loop']['stalls']['longest_ms']:.0f} ms): a replay cannot see it")
    ident, info = identify_file(rec)
    assert info["how"].startswith("replay") and "streamed" in info["how"]   # row group by row group
    for k in PARAMS:
        assert ident.as_dict()["parameters"][k] == pytest.approx(s["parameters"][k], rel=1e-12)


def test_recording_holds_every_sample_in_order(recorded):
    s, rec, _ = recorded
    r = read_recording(rec)
    assert len(r) == s["loop"]["samples"]
    assert np.all(np.diff(r.seq) == 1)
    assert r.metadata["excitation"]["period_samples"] == 512


def test_rrd_holds_the_dashboard_entities_with_values(recorded):
    from rerun.chunk import RrdReader

    s, _, rrd = recorded
    seen = {}
    for chunk in RrdReader(str(rrd)).stream():
        batch = chunk.to_record_batch()
        seen.setdefault(str(chunk.entity_path), 0)
        seen[str(chunk.entity_path)] += batch.num_rows
    for entity in ("/params/K/estimate", "/params/K/true", "/params/K/ci95", "/params/B/estimate",
                   "/modal/zeta/estimate", "/modal/wd/estimate", "/modal/wd/ci95", "/torque/drive",
                   "/torque/nrmse_percent", "/angles", "/loop/lateness_us",
                   "/frf/theta1/magnitude/model", "/frf/theta1/magnitude/measured", "/frf/theta2/phase/model"):
        assert seen.get(entity, 0) > 0, (entity, sorted(seen))
    # the loop drops a block rather than wait for a telemetry process a busy host starves (counted: how many
    # depends on the host); every block that entered the ring reached the file
    tel = s["telemetry"]
    assert tel["published"] > 0 and tel["sent"] == tel["published"], tel


def test_a_runs_rrd_has_rerun_footer_opens_as_a_store_and_verifies(recorded):
    import warnings

    from rerun.chunk import RrdReader

    s, _, rrd = recorded
    assert s["telemetry"]["footer"] is True and s["telemetry"]["footer_error"] is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # no "RRD file has no footer" (legacy format)
        store = RrdReader(str(rrd)).store()
        assert "/params/K/estimate" in {chunk.entity_path for chunk in store.stream()}
    r = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(rrd)], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, CI="1"))
    assert r.returncode == 0, r.stdout + r.stderr


def test_rrd_true_value_series_holds_the_plant_stiffness(recorded):
    from rerun.chunk import RrdReader

    s, _, rrd = recorded
    values, seen = [], []
    for chunk in RrdReader(str(rrd)).stream():
        if str(chunk.entity_path).startswith("/params/K"):
            batch = chunk.to_record_batch()
            seen.append((str(chunk.entity_path), batch.num_rows, batch.column_names))
        if str(chunk.entity_path) == "/params/K/true":
            batch = chunk.to_record_batch()
            if "Scalars:scalars" not in batch.column_names:
                continue                 # the static series-style chunk
            values += [float(np.ravel(x)[0]) for x in batch.column("Scalars:scalars").to_pylist()]
    assert values and all(v == pytest.approx(110.0) for v in values), (seen, s["telemetry"], s.get("parameters"))


def test_injected_slow_tick_is_counted_as_an_overrun():
    def slow(tick):
        if tick == 50:
            time.sleep(0.0055)

    s = run(cfg(loop__duration=0.2, recording__enabled=False), tick_hook=slow)
    assert s["loop"]["overruns"] >= 1
    assert s["loop"]["skipped_periods"] >= 4     # a 5.5 ms stall skips whole 1 ms periods, never bursts


def test_sigint_stops_safely_with_zero_torque(tmp_path):
    def interrupt(tick):
        if tick == 100:
            os.kill(os.getpid(), signal.SIGINT)

    s = run(cfg(loop__duration=5.0), record=str(tmp_path / "i.parquet"), tick_hook=interrupt)
    assert s["stop"]["interrupted"] and s["stop"]["cause"] is None
    assert s["stop"]["final_torque"] == 0.0 and s["stop"]["backend_state"] == "closed"
    assert s["loop"]["ticks"] < 200
    assert len(read_recording(tmp_path / "i.parquet")) == s["loop"]["samples"]


def test_travel_trip_stops_with_a_cause_and_keeps_the_recording(tmp_path):
    # a drive declared to hold the axis that does not: the probe walks the free table out of its window
    s = run(cfg(safety__window=[-2e-4, 2e-4], control__mode="off", control__drive_holds=True),
            record=str(tmp_path / "t.parquet"))
    assert s["stop"]["cause"] == "travel-limit" and "safety.window" in s["stop"]["fix"], s["stop"]
    assert s["stop"]["final_torque"] == 0.0
    assert len(read_recording(tmp_path / "t.parquet")) == s["loop"]["samples"]


@pytest.mark.slow
def test_viewer_that_never_answers_does_not_block_the_loop():
    import socket

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)                    # accepts TCP but never speaks gRPC
    port = srv.getsockname()[1]
    try:
        t0 = time.monotonic()
        s = run(cfg(loop__duration=1.0, recording__enabled=False, telemetry__sink="connect",
                    telemetry__connect_url=f"rerun+http://127.0.0.1:{port}/proxy"))
        wall = time.monotonic() - t0
    finally:
        srv.close()
    assert s["loop"]["ticks"] == 1000
    # a blocked hand-off would stall the loop for seconds: whole periods skipped. The wall time is mostly the
    # helpers' start and the telemetry's bounded close (11 s idle here, 21.5 s beside a busy loop on each core)
    assert s["loop"]["skipped_periods"] < 1000 and wall < 60
    assert s["telemetry"]["sent"] + s["telemetry"]["dropped"] >= 1


def test_kill_9_mid_run_leaves_a_readable_recording(tmp_path):
    rec = tmp_path / "k.parquet"
    cmd = [sys.executable, "-m", "rt_ident", "run", "--duration", "60", "--no-realtime", "--no-telemetry",
           "--record", str(rec)]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen = 0
    try:
        deadline = time.monotonic() + 60
        journal = rec.with_name(rec.name + ".arrows")
        while time.monotonic() < deadline and seen <= 1000:
            time.sleep(0.2)
            if journal.exists():                # what a reader recovers while the run goes on
                try:
                    seen = len(read_recording(rec))
                except DataError:               # no whole batch flushed yet
                    pass
        assert seen > 1000, "the run never recorded a readable batch"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)     # the loop and its recorder process, no cleanup at all
        proc.wait(10)
    r = read_recording(rec)
    assert r.source == "journal"
    assert len(r) >= seen                       # nothing flushed before the kill is lost
    assert np.all(np.diff(r.seq) == 1) and r.seq[0] == 0
    assert np.all(np.isfinite(r.theta1))


def test_helpers_are_niced_in_every_thread_but_an_emulated_device_keeps_its_priority():
    import subprocess
    import sys

    from rt_ident.loop.host import keep_off_loop_cpu

    code = ("import threading, time\n"
            "for _ in range(2): threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n"
            "time.sleep(30)")
    helper = subprocess.Popen([sys.executable, "-c", code])
    device = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and any(len(os.listdir(f"/proc/{p.pid}/task")) < 3 for p in (helper, device)):
            time.sleep(0.05)
        report = keep_off_loop_cpu([helper.pid], realtime=False, device=device.pid)
        assert report["threads"] == 6 and report["device_pid"] == device.pid
        for tid in os.listdir(f"/proc/{helper.pid}/task"):
            assert os.getpriority(os.PRIO_PROCESS, int(tid)) == 10
        for tid in os.listdir(f"/proc/{device.pid}/task"):     # as started: this process's nice value
            assert os.getpriority(os.PRIO_PROCESS, int(tid)) == os.getpriority(os.PRIO_PROCESS, 0)
        # by role: the control process (rare, urgent) above the fit process (refits without pause)
        keep_off_loop_cpu([helper.pid], realtime=False, roles={helper.pid: "fit"})
        assert {os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir(f"/proc/{helper.pid}/task")} == {15}
        report = keep_off_loop_cpu([device.pid], realtime=False, roles={device.pid: "control"})
        assert {os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir(f"/proc/{device.pid}/task")} == {5}
        assert report["nice"] == {str(device.pid): 5}
    finally:
        for p in (helper, device):
            p.kill()
            p.wait()


def _report_env(q):
    q.put({k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")})


def test_helpers_are_spawned_with_single_threaded_blas_and_this_process_keeps_its_environment(monkeypatch):
    # two OpenBLAS threads that only spin made a redesign cost the control process 5x its CPU
    import multiprocessing as mp

    from rt_ident.processes.guard import start_ignoring_signals

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")                   # the user's own setting is kept
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=_report_env, args=(q,))
    start_ignoring_signals(proc)
    try:
        assert q.get(timeout=60) == {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "3"}
    finally:
        proc.join(10)
    assert "OPENBLAS_NUM_THREADS" not in os.environ and os.environ["OMP_NUM_THREADS"] == "3"


def test_a_run_without_any_fit_worker_result_still_ends_its_dashboard_on_the_final_estimate(tmp_path, monkeypatch):
    # beside a CPU hog a short run had no fit-jobs result in time: its .rrd had no estimate, no true
    # value, no FRF. The job process's results are withheld here; the final fit's must reach the dashboard.
    from rerun.chunk import RrdReader

    from rt_ident.loop.loop import IdentificationLoop

    monkeypatch.setattr(IdentificationLoop, "_fit_exchange", lambda self, ctl, t, tick: None)
    rrd = tmp_path / "r.rrd"
    s = run(cfg(telemetry__sink="rrd", recording__enabled=False), rrd=str(rrd))
    assert s["stop"]["cause"] is None and s["loop"]["estimates"] == 0      # no jobs result was taken
    rows, paths = {}, set()
    for chunk in RrdReader(str(rrd)).stream():
        batch = chunk.to_record_batch()
        paths.add(str(chunk.entity_path))
        if "Scalars:scalars" in batch.column_names:
            rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), []) + [
                float(np.ravel(x)[0]) for x in batch.column("Scalars:scalars").to_pylist()]
    assert rows["/params/K/estimate"][-1] == pytest.approx(s["parameters"]["K"], rel=1e-9)
    assert rows["/params/K/true"] and all(v == pytest.approx(110.0) for v in rows["/params/K/true"])
    assert "/frf/theta1/magnitude/model" in paths, sorted(paths)


@pytest.mark.parametrize("wait_s", [4.0, 0.0], ids=["waits", "peer-drops"])
def test_a_telemetry_process_starved_through_the_run_still_ends_the_dashboard_on_the_final_estimate(
        tmp_path, monkeypatch, wait_s):
    # its ring full from the first ticks on (a busy host's), the final fit's estimate and FRF wait for it to
    # drain once the loop is over; the peer, not waiting, leaves the dashboard on an older estimate. The wait
    # here is longer than the run's 2 s: the child resumes only well after the final fit, however slow
    import threading

    from rerun.chunk import RrdReader

    from rt_ident.compose import run as run_mod

    stopped: list[int] = []

    def hook(n):
        if n == 5:
            stopped.extend(p.pid for p in __import__("multiprocessing").active_children() if "telemetry" in p.name)
            for pid in stopped:
                os.kill(pid, signal.SIGSTOP)

    def resume():
        for pid in stopped:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass

    final_fit = run_mod.final_fit

    def final_fit_then_resume(*a, **k):   # the child runs again 1.5 s after the loop's end (after the final fit)
        threading.Timer(1.5, resume).start()
        return final_fit(*a, **k)

    monkeypatch.setattr(run_mod, "final_fit", final_fit_then_resume)
    monkeypatch.setattr(run_mod, "FINAL_HANDOFF_WAIT_S", wait_s)
    rrd = tmp_path / "r.rrd"
    try:
        s = run(cfg(telemetry__sink="rrd", recording__enabled=False), rrd=str(rrd), tick_hook=hook)
    finally:
        resume()
    assert len(stopped) == 1 and s["stop"]["cause"] is None and s["telemetry"]["dropped"] > 0
    last = {}
    for chunk in RrdReader(str(rrd)).stream():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" in batch.column_names and batch.num_rows:
            last[str(chunk.entity_path)] = float(np.ravel(batch.column("Scalars:scalars").to_pylist()[-1])[0])
    on_dashboard = last.get("/params/K/estimate")
    if wait_s:
        assert on_dashboard == pytest.approx(s["parameters"]["K"], rel=1e-12), (on_dashboard, s["telemetry"])
    else:
        assert on_dashboard != pytest.approx(s["parameters"]["K"], rel=1e-12), (on_dashboard, s["telemetry"])


def test_a_run_without_excitation_starts_no_fit_process_and_says_why_it_has_no_estimate():
    s = run(cfg(loop__duration=0.3, excitation__kind="none", control__mode="fixed", recording__enabled=False))
    assert s["stop"]["cause"] is None and s["stop"]["final_torque"] == 0.0
    assert "fit" not in s["helpers"] and "control" not in s["helpers"]
    assert s["final_fit_error"] == 'nothing to identify: no probing excitation (excitation.kind = "none")'
    assert not s.get("parameters")
    # the peer: with the probe there is a fit process
    with_probe = run(cfg(loop__duration=0.3, control__mode="fixed", recording__enabled=False))
    assert "fit" in with_probe["helpers"] and with_probe["final_fit_error"] is None


def test_a_run_without_real_time_keeps_the_collector_out_of_its_loop_and_turns_it_back_on_after():
    import gc

    seen = []
    s = run(cfg(loop__duration=0.3, recording__enabled=False), tick_hook=lambda n: seen.append(gc.isenabled()))
    assert s["realtime"]["requested"] is False and s["realtime"]["gc_freeze"] is True
    assert seen and not any(seen)              # off in every tick: no collection pause in the loop
    assert gc.isenabled()
    gc.unfreeze()


WATCHDOG = ("no fresh TPDO data for 201 SYNCs in a row (stale_limit 200); the host kept time: the drive sent "
            "no fresh data")


@pytest.mark.parametrize(("stats", "starved"), [
    ({"late_syncs": 892, "pickup_time": {"<100us": 1}}, True),                  # one drive, starved that long
    ({"late_syncs": 150}, False),                                               # fewer than the stale run
    ({"node 5": {"late_syncs": 12}, "node 6": {"late_syncs": 400}}, True),       # a bus of drives: any one
    ({"samples": 4000}, False),                                                 # no such count (the serial board)
])
def test_a_watchdog_stop_says_the_emulated_drive_was_starved_only_when_it_answered_that_many_syncs_late(
        stats, starved):
    import rt_ident.compose.run as run_mod

    note = run_mod.starved_emulator("watchdog", WATCHDOG, stats)
    assert (note is not None) == starved, note
    if starved:
        assert "starved" in note and "not the device" in note
    assert run_mod.starved_emulator("device-fault", WATCHDOG, stats) is None      # only a stale-data stop


def test_late_control_torques_are_reported_from_a_twentieth_of_a_tick_and_a_longer_design_only_from_half(capsys):
    from rt_ident.compose.run import late_torques
    from rt_ident.outputs.terminal import print_no_design

    assert late_torques({"late_torques": 49}, 1000, 1) is None          # a busy tick now and then
    assert late_torques({"stale": 3}, 1000, 1) is None                  # a backend without the count
    assert late_torques({"late_torques": 10}, 0, 1) is None
    late = late_torques({"late_torques": 600}, 1000, 1)                 # most ticks' torques a SYNC late
    assert late is not None and late["extra_delay_ticks"] == 0.6 and "control.delay_ticks = 2" in late["fix"]
    print_no_design({"late_torques": late})
    printed = capsys.readouterr().out
    assert "600 planned torques missed their SYNC" in printed and "control.delay_ticks = 2" in printed
    # a serial board whose plans land a sample of 20 late each tick: a twentieth of a tick, not a tick more
    board = late_torques({"late_torques": 6000}, 120000, 1, "serial")
    assert board is not None and "6000 samples ran on an older plan" in board["message"]
    assert "0.05 tick later" in board["message"]
    assert "delay_ticks" not in board["fix"] and "latency timer" in board["fix"] and "answer_us" not in board["fix"]
    board = late_torques({"late_torques": 66000}, 120000, 2, "serial")
    assert board is not None and "control.delay_ticks = 3" in board["fix"]

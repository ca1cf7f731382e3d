"""Telemetry process: .rrd content, non-blocking publish to a dead viewer, loopback-only server."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rt_ident.errors import ConfigError, DataError
from rt_ident.outputs import dashboard
from rt_ident.outputs.sinks import TelemetryConfig, default_sink, viewer_command
from rt_ident.processes.telemetry import TelemetryProcess


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _block(k: int, n: int = 7) -> dict[str, np.ndarray]:
    i = np.arange(n * k, n * (k + 1), dtype=np.float64)
    t = i * 1e-4
    return {
        "t": t,
        "theta1": 0.001 * i,
        "theta2": -0.002 * i,
        "torque_meas": np.sin(i),
        "torque_filt": np.cos(i),
        "torque_hat": np.cos(i) + 0.5,
        "t_tick": t[-1:],
        "I1": np.array([0.01 + k]),
        "K": np.array([1e5 + k]),
        "wn": np.array([4000.0 + k]),
        "lateness_us": np.array([3.0 * k]),
        "overruns": np.array([float(k // 10)]),
    }


def _read_rrd(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """entity -> (time [s], value) of every temporal Scalars chunk, concatenated in time order."""
    from rerun.chunk import RrdReader

    parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        if "time" not in rb.schema.names or "Scalars:scalars" not in rb.schema.names:
            continue
        t = rb.column("time").cast("int64").to_numpy() * 1e-9  # duration[ns]
        v = np.array([x for x in rb.column("Scalars:scalars").to_pylist()], dtype=float)
        v = v[:, 0] if v.ndim == 2 and v.shape[1] == 1 else v     # one series: a column of values
        parts.setdefault(chunk.entity_path.lstrip("/"), []).append((t, v))
    out = {}
    for ent, ps in parts.items():
        t, v = np.concatenate([p[0] for p in ps]), np.concatenate([p[1] for p in ps])
        order = np.argsort(t, kind="stable")
        out[ent] = (t[order], v[order])
    return out


def test_rrd_holds_dashboard_entities_with_the_values_sent(tmp_path: Path) -> None:
    path = tmp_path / "tele.rrd"
    cfg = TelemetryConfig(sink="rrd", rrd_path=str(path), decimation=3, queue_size=256)
    tp = TelemetryProcess(cfg)
    assert tp.set_truth({"I1": 0.0123, "K": 2.5e5, "wn": 4162.58})  # before start: handed over at start
    tp.start()
    assert tp.wait_ready(20.0)
    blocks = [_block(k) for k in range(40)]
    assert all(tp.publish(b) for b in blocks)
    summary = tp.close(timeout=10.0)
    assert summary["sent"] == 40 and summary["dropped"] == 0 and summary["exitcode"] == 0
    assert not summary["terminated"]

    data = _read_rrd(path)
    expected = {dashboard.ANGLES, dashboard.TORQUE_DRIVE, dashboard.TORQUE_ESTIMATE, dashboard.TORQUE_NRMSE,
                dashboard.estimate_path("I1"), dashboard.truth_path("I1"), dashboard.estimate_path("K"),
                dashboard.truth_path("K"), dashboard.estimate_path("wn"), dashboard.truth_path("wn"),
                dashboard.LATENESS, dashboard.OVERRUNS}
    assert expected <= set(data)
    # Decimation by 3 is continuous across blocks of 7 samples: every 3rd sample of the whole run;
    # theta1 and theta2 share the rows of one entity.
    t_all = np.concatenate([b["t"] for b in blocks])
    th1_all = np.concatenate([b["theta1"] for b in blocks])
    th2_all = np.concatenate([b["theta2"] for b in blocks])
    t, v = data[dashboard.ANGLES]
    assert np.allclose(t, t_all[::3], atol=1e-9, rtol=0)
    assert np.array_equal(v[:, 0], th1_all[::3]) and np.array_equal(v[:, 1], th2_all[::3])
    # the commanded torque is absent from every block: its series is NaN, the others are values
    t, v = data[dashboard.TORQUE_DRIVE]
    assert np.all(np.isnan(v[:, 1])) and np.all(np.isfinite(v[:, 0]))
    t, v = data[dashboard.TORQUE_ESTIMATE]
    assert np.array_equal(v[:, 0], np.cos(np.arange(280.0))[::3]) and np.all(np.isfinite(v[:, 1]))
    # Tick-rate estimates are not decimated and sit on t_tick (I1 changes every tick: every tick kept).
    t, v = data[dashboard.estimate_path("I1")]
    assert np.array_equal(v, [b["I1"][0] for b in blocks])
    assert np.allclose(t, [b["t_tick"][0] for b in blocks], atol=1e-9, rtol=0)
    # Lateness is thinned to the largest of every 10 ticks: every late tick stays visible.
    assert np.array_equal(data[dashboard.LATENESS][1], [3.0 * (k + 9) for k in range(0, 40, 10)])
    # Overruns change every 10th tick: sent as steps (the change, the tick before it, the last).
    t, v = data[dashboard.OVERRUNS]
    assert np.array_equal(v, [0, 0, 1, 1, 2, 2, 3, 3])
    # reconstruction = filtered measured + 0.5: the NRMSE is 0.5 / std(filtered measured) over the last second
    filt = np.concatenate([b["torque_filt"] for b in blocks])[::3]
    assert data[dashboard.TORQUE_NRMSE][1][-1] == pytest.approx(100 * 0.5 / np.std(filt), rel=1e-9)
    # The true value is drawn over the estimate's time span.
    t, v = data[dashboard.truth_path("K")]
    assert np.all(v == 2.5e5) and t.min() <= blocks[0]["t_tick"][0] and t.max() >= blocks[-1]["t_tick"][0]


def test_window_values_are_drawn_as_the_arrays_they_stand_for(tmp_path: Path) -> None:
    """The loop sends the signals that hold over a window as one vector; the dashboard must not tell."""
    window_keys = ("I1", "K", "wn")

    def run(name: str, as_window: bool) -> dict:
        path = tmp_path / name
        tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256)).start()
        assert tp.wait_ready(20.0)
        for k in range(40):
            b = _block(k, n=35)
            b["t_tick"] = b["t"][[16, 33, 34]]                 # three ticks per block
            for key in ("lateness_us", "overruns"):
                b[key] = np.repeat(b[key], 3)
            vals = {key: float(b.pop(key)[0]) for key in window_keys}
            if k >= 20:
                vals["zeta"] = 0.01 * k                         # a second set of names half-way
            if as_window:
                assert tp.publish(b, vals)
            else:
                assert tp.publish({**b, **{key: np.full(3, v) for key, v in vals.items()}})
        summary = tp.close(timeout=10.0)
        assert summary["sent"] == 40 and summary["dropped"] == 0 and summary["exitcode"] == 0
        return _read_rrd(path)

    arrays, window = run("arrays.rrd", False), run("window.rrd", True)
    for key in window_keys + ("zeta",):
        ent = dashboard.estimate_path(key)
        np.testing.assert_array_equal(window[ent][0], arrays[ent][0])
        np.testing.assert_array_equal(window[ent][1], arrays[ent][1])
    t, v = window[dashboard.estimate_path("I1")]
    assert t.size >= 40 and np.array_equal(np.unique(v), 0.01 + np.arange(40))
    t, v = window[dashboard.estimate_path("zeta")]
    assert t.min() >= _block(20, n=35)["t"][16] - 1e-12 and v[-1] == pytest.approx(0.39)


def _loop_messages(k: int, n: int = 34, ticks: int = 20) -> tuple[dict, dict, dict]:
    """What the loop sends per window: a samples block, a tick block and its window values."""
    i = np.arange(n * k, n * (k + 1), dtype=np.float64)
    samples = {"t": i * 1e-4, "theta1": 1e-3 * i, "theta2": -2e-3 * i, "torque_meas": np.sin(i),
               "torque_cmd": np.cos(i)}
    tt = (ticks * k + np.arange(ticks)) * 1e-3
    tick = {"t": tt, "t_tick": tt, "lateness_us": 0.5 * np.arange(ticks) + k}
    window = {"I1": 0.01 + k, "K": 1e5 + k}
    if k >= 5:
        window["wn"] = 4000.0 + k                         # a second set of window names half-way
    return samples, tick, window


def _send_loop_messages(tp: TelemetryProcess, ks: range) -> None:
    for k in ks:
        samples, tick, window = _loop_messages(k)
        assert tp.publish(samples)
        assert tp.publish(tick, window)


def test_a_restarted_telemetry_process_gets_the_names_again(tmp_path: Path) -> None:
    """A new child knows no names: the window names go to it again (otherwise a restarted child drops
    every window vector, "without their names", and the dashboard loses every estimate)."""
    path = tmp_path / "tele.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256)).start()
    assert tp.wait_ready(20.0)
    _send_loop_messages(tp, range(3))
    os.kill(tp.pid, signal.SIGKILL)                 # the child dies, as HelperWatch finds it
    end = time.monotonic() + 10.0
    while tp.alive and time.monotonic() < end:
        time.sleep(0.01)
    assert not tp.alive
    tp.restart()
    assert tp.wait_ready(20.0)
    _send_loop_messages(tp, range(3, 8))
    summary = tp.close(timeout=10.0)
    assert summary["exitcode"] == 0 and summary["dropped"] == 0
    second = _read_rrd(Path(tp.config.rrd_path))
    assert Path(tp.config.rrd_path) != path
    t, v = second[dashboard.estimate_path("K")]
    assert np.array_equal(np.unique(v), 1e5 + np.arange(3, 8))
    t, v = second[dashboard.ANGLES]
    assert np.array_equal(v[:, 0], np.concatenate([_loop_messages(k)[0]["theta1"] for k in range(3, 8)]))


def test_restarting_a_live_telemetry_process_leaves_no_old_child_behind(tmp_path: Path) -> None:
    """The child ignores SIGTERM (a helper must outlive the group's Ctrl-C): restart() kills it, or
    it would poll on and write into shared counters whose memory the new child's counters reuse."""
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "a.rrd"))).start()
    assert tp.wait_ready(20.0)
    old = tp.pid
    tp.restart()
    try:
        assert tp.wait_ready(20.0) and tp.pid != old      # replaced beside the caller
        with pytest.raises(ProcessLookupError):
            os.kill(old, 0)
    finally:
        tp.close(timeout=10.0)


def test_a_telemetry_restart_returns_before_its_child_is_made_and_drops_what_comes_meanwhile(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the loop's tick calls restart(): the new ring and the fork wait on other processes
    from rt_ident.processes import telemetry

    gate, let_go = threading.Event(), []
    end = telemetry.end_helper

    def held(proc, *args):
        let_go.append(gate.wait(10.0))
        end(proc, *args)

    monkeypatch.setattr(telemetry, "end_helper", held)
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "a.rrd"), queue_size=256)).start()
    try:
        assert tp.wait_ready(20.0)
        os.kill(tp.pid, signal.SIGKILL)
        old = tp.pid
        tp.restart()                                   # back here with the new child not yet made
        assert tp.alive and tp.pid == old
        samples, tick, window = _loop_messages(0)
        assert not tp.publish(samples) and not tp.publish(tick, window) and tp.dropped == 2
        gate.set()
        assert tp.wait_ready(20.0) and tp.pid != old and let_go == [True]
        dropped = tp.dropped
        _send_loop_messages(tp, range(1, 3))
        assert tp.dropped == dropped
    finally:
        gate.set()
        tp.close(timeout=10.0)


def test_a_restarted_telemetry_process_writes_its_next_file_with_every_thread_where_the_run_put_the_first(
        tmp_path: Path) -> None:
    # its rerun import and file opening run at the forkserver's priority (as the first's ran before the run placed
    # it): niced from the start, beside a busy host it may not open its file before the run ends
    cpus = sorted(os.sched_getaffinity(0))
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "a.rrd"), queue_size=256)).start()
    try:
        assert tp.wait_ready(20.0)
        tp.placement = {"nice": 13, "cpus": cpus[:1]}
        os.kill(tp.pid, signal.SIGKILL)
        tp.restart()
        assert tp.wait_ready(20.0) and (tmp_path / "a-2.rrd").is_file()

        def placed() -> bool:
            tids = os.listdir(f"/proc/{tp.pid}/task")
            return len(tids) > 1 and all(os.getpriority(os.PRIO_PROCESS, int(t)) == 13
                                         and os.sched_getaffinity(int(t)) == set(cpus[:1]) for t in tids)

        deadline = time.monotonic() + 10
        while not placed():
            assert time.monotonic() < deadline, [(t, os.getpriority(os.PRIO_PROCESS, int(t)))
                                                 for t in os.listdir(f"/proc/{tp.pid}/task")]
            time.sleep(0.01)
    finally:
        tp.close(timeout=10.0)


@pytest.mark.filterwarnings("ignore:RRD file has no footer")     # the parent adds the footer at close()
def test_a_telemetry_process_whose_ring_was_given_to_another_ring_finishes_its_rrd_and_says_so_in_one_line(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "reused.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256, batch_seconds=0.01))
    tp.start()
    assert tp.wait_ready(20.0)
    blocks = [_block(k) for k in range(10)]
    assert all(tp.publish(b) for b in blocks)
    deadline = time.monotonic() + 20.0
    while tp._sent.value < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert tp._sent.value == 10
    ring = tp._ring
    assert ring is not None
    ring._h[3] = ring._h[3] ^ 0x5A5A               # another ring's token: the parent let go of this memory
    tp._proc.join(20.0)
    assert tp._proc.exitcode == 0
    err = capfd.readouterr().err
    assert "given to another ring" in err and "Traceback" not in err, err
    t, v = _read_rrd(path)[dashboard.ANGLES]
    assert np.array_equal(v[:, 0], np.concatenate([b["theta1"] for b in blocks]))
    ring._h[3] = ring._h[3] ^ 0x5A5A               # this side's own token again, so close() can finish
    tp.close(timeout=10.0)


def test_window_values_need_tick_times_and_tick_signal_names() -> None:
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path="/nonexistent/never-started.rrd"))
    with pytest.raises(DataError, match="t_tick"):
        tp.publish({"t": np.zeros(3)}, {"I1": 1.0})
    with pytest.raises(DataError, match="theta1"):
        tp.publish({"t": np.zeros(3), "t_tick": np.zeros(1)}, {"theta1": 1.0})


def test_blocks_are_batched_into_few_chunks_per_entity(tmp_path: Path) -> None:
    """One chunk per entity per batch, not per block: rerun stores each send as a chunk, and tiny
    chunks would be most of an .rrd's size."""
    from rerun.chunk import RrdReader

    path = tmp_path / "batch.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256, batch_seconds=10.0))
    tp.start()
    assert tp.wait_ready(20.0)
    for k in range(200):
        assert tp.publish(_block(k))
    assert tp.close(timeout=10.0)["sent"] == 200
    chunks: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream():
        if "time" in chunk.to_record_batch().schema.names:
            chunks[chunk.entity_path.lstrip("/")] = chunks.get(chunk.entity_path.lstrip("/"), 0) + 1
    assert chunks[dashboard.ANGLES] <= 2 and chunks[dashboard.estimate_path("K")] <= 3, chunks


def _verify(path: Path) -> subprocess.CompletedProcess:
    """`rerun rrd verify` (it checks the footer too), as the rerun CLI runs it."""
    return subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)], capture_output=True,
                          text=True, timeout=60, env=dict(os.environ, CI="1"))


def test_rrd_gets_rerun_footer_at_close_and_opens_as_a_store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             capfd: pytest.CaptureFixture[str]) -> None:
    """The child writes no footer (see the next test); close() adds it: the file opens with the
    random-access store API and passes `rerun rrd verify`, with the same content."""
    import warnings

    from rerun.chunk import RrdReader

    monkeypatch.delenv("RUST_LOG", raising=False)    # the child's default filter, not the caller's
    path = tmp_path / "footer.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256)).start()
    assert tp.set_truth({"K": 2.5e5})
    assert tp.wait_ready(20.0)
    for k in range(20):
        assert tp.publish(_block(k))
    summary = tp.close(timeout=10.0)
    assert summary["exitcode"] == 0 and summary["sent"] == 20 and summary["written"]
    assert summary["footer"] is True and summary["footer_error"] is None and summary["write_error"] is None
    assert summary["seconds"] < 10.0
    assert os.listdir(tmp_path) == ["footer.rrd"]                 # the copy replaced it, nothing left beside
    with warnings.catch_warnings():
        warnings.simplefilter("error")                          # no "RRD file has no footer" (legacy format)
        reader = RrdReader(str(path))
        store = reader.store()
        assert len(store) > 0
        assert "/" + dashboard.ANGLES in {chunk.entity_path for chunk in store.stream()}
        assert [b.application_id for b in reader.blueprints()] == ["rt_ident"]   # the dashboard layout kept
    got = _read_rrd(path)
    t, v = got[dashboard.ANGLES]
    assert t.size == 140 and np.allclose(v[:, 0], 0.001 * np.arange(140))
    assert np.all(got[dashboard.truth_path("K")][1] == 2.5e5)
    r = _verify(path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "write_footer" not in capfd.readouterr().err


def test_the_child_writes_the_rrd_without_a_footer(tmp_path: Path) -> None:
    """While the run lasts, rerun's file sink keeps a manifest entry per chunk to write a footer at
    the end, growing the telemetry process for the whole run: the child asks for none."""
    from rt_ident.processes import telemetry as tel

    class Rec:
        def save(self, path, **kwargs):
            self.saved = (path, kwargs)

    rec = Rec()
    tel._open_sink(rec, TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "x.rrd")), None)
    assert rec.saved[0] == str(tmp_path / "x.rrd") and rec.saved[1]["write_footer"] is False


def _fake_cli(tmp_path: Path, body: str) -> str:
    exe = tmp_path / "rerun"
    exe.write_text("#!/bin/sh\n" + body + "\n")
    exe.chmod(0o755)
    return str(exe)


@pytest.mark.parametrize(("body", "why"), [("exec sleep 30", "not done within 0.5 s"),
                                           ("echo 'Error: bad chunk' >&2; exit 3", "failed: Error: bad chunk")])
def test_a_footer_that_cannot_be_added_is_reported_and_the_file_left_whole(tmp_path, monkeypatch, body, why):
    """A finishing step that hangs is stopped at finish_timeout, one that fails is named; either
    way the file is the complete stream it was (no data lost: no write error), with no copy beside."""
    from rt_ident.outputs import sinks

    monkeypatch.setattr(sinks, "_rerun_cli", lambda: _fake_cli(tmp_path / "bin", body))
    (tmp_path / "bin").mkdir()
    path = tmp_path / "d" / "nofooter.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path), queue_size=256,
                                          finish_timeout=0.5)).start()
    assert tp.wait_ready(20.0)
    for k in range(20):
        assert tp.publish(_block(k))
    summary = tp.close(timeout=10.0)
    assert summary["footer"] is False and why in summary["footer_error"], summary
    assert summary["written"] is True and summary["write_error"] is None
    assert summary["seconds"] < 5.0
    assert os.listdir(path.parent) == ["nofooter.rrd"]
    with pytest.warns(Warning, match="no footer"):                # RerunWarning
        t, _ = _read_rrd(path)[dashboard.ANGLES]
    assert t.size == 140
    assert tp.close()["footer_error"] == summary["footer_error"]      # a second close does not try again


def test_no_room_for_the_copy_leaves_the_file_without_a_footer_and_says_so(tmp_path: Path) -> None:
    from rt_ident.outputs.sinks import finish_rrd

    path = tmp_path / "x.rrd"
    path.write_bytes(b"x" * 1000)
    why = finish_rrd(str(path), 5.0, min_free=1 << 62)
    assert why is not None and "no room" in why and path.read_bytes() == b"x" * 1000


def test_fit_and_loop_gain_views_are_drawn_under_frf(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    from rt_ident.estimators.frf import FRF_KEYS

    path = tmp_path / "frf.rrd"
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(path))).start()
    assert tp.wait_ready(20.0)
    f = np.geomspace(10, 1000, 50)
    view = {k: np.linspace(-80, -20, 50) for k in FRF_KEYS}
    view.update(f_meas=f[::5], m1_db=np.linspace(-80, -20, 10), p1_deg=np.full(10, -180.0),
                m2_db=np.linspace(-85, -25, 10), p2_deg=np.full(10, -200.0), f_model=f,
                g1_deg=np.full(50, -180.0), g2_deg=np.full(50, -190.0), marks_hz=np.array([300.0, 250.0]))
    assert tp.publish_fit(1.0, view)
    lg = {"f_hz": f, "mag_db": np.linspace(40, -40, 50), "phase_deg": np.linspace(-270, -150, 50)}
    assert tp.publish_loop_gain(1.0, lg, {"pm_deg": 50.0, "gm_db": 8.0})
    assert tp.close(timeout=10.0)["exitcode"] == 0
    seen = {chunk.entity_path for chunk in RrdReader(str(path)).stream()}
    for entity in ("/frf/theta1/magnitude/model", "/frf/theta1/magnitude/measured", "/frf/theta1/magnitude/band_low",
                   "/frf/theta2/phase/model", "/frf/theta1/magnitude/marks", "/frf/loop/magnitude/loop_gain",
                   "/frf/loop/phase/marks"):
        assert entity in seen, (entity, sorted(seen))


def test_step_points_keep_each_change_and_the_row_before_it() -> None:
    from rt_ident.processes.telemetry import _step_points

    v = np.array([[1.0], [1.0], [1.0], [2.0], [2.0], [np.nan], [np.nan]])
    assert list(_step_points(v, np.array([1.0]), extend=False)) == [2, 3, 4, 5]
    assert list(_step_points(v, np.array([1.0]), extend=True)) == [2, 3, 4, 5, 6]
    assert list(_step_points(v, None, extend=False)) == [0, 2, 3, 4, 5]


def test_connect_to_absent_viewer_never_blocks_publish_and_counts_drops() -> None:
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    tp = TelemetryProcess(TelemetryConfig(sink="connect", connect_url=url, queue_size=8)).start()
    worst, n = 0.0, 300
    for k in range(n):
        t0 = time.perf_counter()
        tp.publish(_block(k, n=400))
        worst = max(worst, time.perf_counter() - t0)
    assert worst < 1.0          # a publish that waited on the connection would take its seconds-long timeout
    assert tp.dropped > 0 and tp.published + tp.dropped == n
    t0 = time.perf_counter()
    summary = tp.close(timeout=2.0)
    assert time.perf_counter() - t0 < 15.0   # bounded by the timeout and the termination, not by rerun
    assert summary["dropped"] == tp.dropped and summary["exitcode"] is not None  # the child is gone


def test_serve_listens_on_loopback_only() -> None:
    port = _free_port()
    tp = TelemetryProcess(TelemetryConfig(sink="serve", port=port)).start()
    try:
        assert tp.wait_ready(20.0)
        listening = [line.split()[1] for line in Path("/proc/net/tcp").read_text().splitlines()[1:]
                     if line.split()[3] == "0A"]  # state LISTEN
        assert f"0100007F:{port:04X}" in listening
        assert f"00000000:{port:04X}" not in listening
    finally:
        assert tp.close(timeout=5.0)["exitcode"] is not None


def test_sink_off_starts_no_process() -> None:
    tp = TelemetryProcess(TelemetryConfig(sink="off")).start()
    assert tp.publish(_block(0)) and tp.pid is None
    assert tp.close()["sent"] == 0 and tp.dropped == 0


def test_publish_before_start_is_dropped_and_counted() -> None:
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path="/nonexistent/never.rrd"))
    assert not tp.publish(_block(0))
    assert tp.dropped == 1 and tp.pid is None


def test_malformed_blocks_are_data_errors() -> None:
    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path="/nonexistent/never.rrd"))
    with pytest.raises(DataError, match="no 't'"):
        tp.publish({"theta1": np.zeros(3)})
    with pytest.raises(DataError, match="unknown block key 'speed'"):
        tp.publish({"t": np.zeros(3), "speed": np.zeros(3)})
    with pytest.raises(DataError, match="'theta2' has shape"):
        tp.publish({"t": np.zeros(3), "theta2": np.zeros(4)})
    with pytest.raises(DataError, match="unknown key 'Q'"):
        tp.set_truth({"Q": 1.0})


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"sink": "screen"}, "sink"),
        ({"sink": "rrd"}, "rrd_path"),
        ({"sink": "connect", "connect_url": "http://127.0.0.1:9876"}, "connect_url"),
        ({"sink": "off", "decimation": 0}, "decimation"),
        ({"sink": "off", "bind_ip": "localhost!"}, "bind_ip"),
        ({"sink": "off", "port": 0}, "port"),
    ],
)
def test_invalid_config_names_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError) as e:
        TelemetryConfig(**kwargs)
    assert e.value.field == field


def test_spawned_viewer_binds_the_configured_ip_and_default_sink_needs_a_display() -> None:
    cmd = viewer_command(TelemetryConfig(sink="spawn", port=9999))
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1" and cmd[cmd.index("--port") + 1] == "9999"
    assert default_sink({}) == "rrd" and default_sink({"DISPLAY": ":0"}) == "spawn"


def test_blueprint_has_a_view_for_every_entity() -> None:
    bp = dashboard.default_blueprint()
    grid = bp.root_container
    origins = [str(v.origin) for v in grid.contents]
    assert len(origins) == len(set(origins))
    paths = (list(dashboard.BLOCK_ENTITIES.values()) + [dashboard.truth_path(k) for k in dashboard.ESTIMATE_KEYS]
             + list(dashboard.CONTROL_ENTITIES.values()) + [dashboard.TORQUE_NRMSE]
             + [f"frf/{s}/{p}" for s in ("theta1", "theta2", "loop") for p in ("magnitude", "phase")])
    for path in paths:
        assert any(path == o or path.startswith(o + "/") for o in origins), path
    assert set(dashboard.SERIES_STYLES) >= set(dashboard.BLOCK_ENTITIES.values())


@pytest.mark.parametrize("last,new", [([0.0], [0.0]), ([0.0], [660.0]), ([np.nan], [660.0]), ([], [660.0])])
def test_a_wild_fits_resonance_mark_never_ends_the_telemetry_process(monkeypatch, last, new) -> None:
    # a loaded non-real-time XY run: a fit with a 0 Hz resonance, then another -> ZeroDivisionError killed
    # both telemetry processes; the FRF must be drawn (or waited for), never raise
    from rt_ident.processes import telemetry

    sender = telemetry._Sender(rec=None, rr=None)
    drawn = []
    monkeypatch.setattr(sender, "_draw_view", lambda kind, msg: drawn.append((kind, msg)))
    sender.view_marks = np.array(last)
    sender.views["frf:"] = {"frf:marks_hz": np.array(new), "frf:t": np.array([1.0])}
    sender.draw_views()
    assert [k for k, _ in drawn] == ["frf:"] and sender.view_marks.tolist() == new


@pytest.mark.parametrize("wait", [False, True], ids=["drops-at-once", "waits-for-room"])
def test_after_wait_for_room_a_full_ring_is_waited_on_until_the_starved_child_drains_it(tmp_path: Path, wait):
    """During the loop a full ring drops the block (nothing real-time waits); after it, the final fit's
    hand-offs wait for a child a busy host starved, so the dashboard ends on the values the run reports."""
    import threading

    tp = TelemetryProcess(TelemetryConfig(sink="rrd", rrd_path=str(tmp_path / "t.rrd"), queue_size=4)).start()
    assert tp.wait_ready(20.0)
    os.kill(tp.pid, signal.SIGSTOP)                  # starved: it drains nothing
    resume = threading.Timer(0.3, os.kill, (tp.pid, signal.SIGCONT))
    try:
        k = 0
        while tp.publish(_block(k)):                  # until the ring is full
            k += 1
            assert k < 100
        dropped = tp.dropped
        t0 = time.monotonic()
        if wait:
            resume.start()                            # the child drains again 0.3 s from now
            tp.wait_for_room(5.0)
        assert tp.publish_fit(1.0, {"f_hz": np.array([1.0, 2.0])}) is wait
        assert tp.dropped == dropped + (not wait)
        if wait:
            assert time.monotonic() - t0 >= 0.25      # it was put once the child had made room
    finally:
        resume.cancel()
        os.kill(tp.pid, signal.SIGCONT)
        summary = tp.close(timeout=10.0)
    assert summary["exitcode"] == 0

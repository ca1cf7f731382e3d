"""A dashboard streamed to a viewer that never got it is reported lost (summary, output, exit 4);
one that reached a listening viewer is reported delivered. Everything on 127.0.0.1."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rt_ident.outputs.sinks import TelemetryConfig
from rt_ident.processes.telemetry import TelemetryProcess

REPO = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _block(k: int, n: int = 200) -> dict:
    t = (k * n + np.arange(n)) * 1e-4
    return {"t": t, "theta1": np.sin(t), "theta2": np.cos(t)}


@pytest.mark.slow
def test_connect_to_a_port_nobody_listens_on_reports_the_dashboard_not_delivered():
    port = _free_port()
    tp = TelemetryProcess(TelemetryConfig(sink="connect", connect_url=f"rerun+http://127.0.0.1:{port}/proxy")).start()
    assert tp.wait_ready(30.0)
    for k in range(5):
        tp.publish(_block(k))
    t0 = time.monotonic()
    s = tp.close(timeout=5.0)
    assert s["delivered"] is False
    assert s["write_error"] == f"nothing listens at 127.0.0.1:{port}: the dashboard was not delivered"
    assert not s["terminated"] and time.monotonic() - t0 < 30.0   # the child left by itself, and closing ended


def test_connect_to_a_listening_viewer_reports_the_dashboard_delivered():
    port = _free_port()
    server = TelemetryProcess(TelemetryConfig(sink="serve", port=port)).start()     # a gRPC server on 127.0.0.1
    try:
        assert server.wait_ready(30.0)
        tp = TelemetryProcess(TelemetryConfig(sink="connect", connect_url=f"rerun+http://127.0.0.1:{port}/proxy",
                                              flush_timeout=10.0)).start()
        assert tp.wait_ready(30.0)
        for k in range(5):
            tp.publish(_block(k))
        s = tp.close(timeout=15.0)
    finally:
        server.close()
    assert s["delivered"] is True and s["write_error"] is None, s


def test_a_viewer_that_starts_after_the_connect_sink_is_ready_gets_the_dashboard():
    port = _free_port()
    tp = TelemetryProcess(TelemetryConfig(sink="connect", connect_url=f"rerun+http://127.0.0.1:{port}/proxy",
                                          flush_timeout=10.0)).start()
    server = None
    try:
        assert tp.wait_ready(30.0)                  # ready with nothing listening: blocks go to rerun's buffer
        for k in range(5):
            tp.publish(_block(k))
        server = TelemetryProcess(TelemetryConfig(sink="serve", port=port)).start()
        assert server.wait_ready(30.0)
        s = tp.close(timeout=20.0)
    finally:
        tp.close(timeout=5.0)
        if server is not None:
            server.close()
    assert s["delivered"] is True and s["write_error"] is None, s


@pytest.mark.slow
def test_a_run_streaming_to_no_viewer_exits_4_and_says_the_dashboard_was_lost(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text((REPO / "configs" / "sim.toml").read_text().replace("enabled = true", "enabled = false"))
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    res = subprocess.run([sys.executable, "-m", "rt_ident", "run", str(cfg), "--duration", "0.5", "--no-realtime",
                          "--connect", f"rerun+http://127.0.0.1:{port}/proxy"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=180)
    assert res.returncode == 4, res.stderr[-3000:]
    assert "Traceback" not in res.stderr
    loop_line = next(ln for ln in res.stdout.splitlines() if ln.startswith("loop:"))
    assert loop_line.endswith("not delivered")
    assert f"DATA LOST: dashboard: nothing listens at 127.0.0.1:{port}" in res.stdout
    assert f"telemetry: nothing listens at 127.0.0.1:{port} yet" in res.stderr     # said at the start, too


def test_rrd_beside_a_live_sink_is_refused_in_one_line_and_writes_nothing(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    rrd = tmp_path / "d.rrd"
    for flags in (["--connect", f"rerun+http://127.0.0.1:{_free_port()}/proxy"], ["--serve"], ["--no-telemetry"]):
        res = subprocess.run([sys.executable, "-m", "rt_ident", "run", "--duration", "0.5", "--rrd", str(rrd), *flags],
                             cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1, res.stderr
        assert lines[0].startswith(f"error: --rrd: {flags[0]} ") and f"{rrd} would not be written" in lines[0]
    cfg = tmp_path / "c.toml"                           # a config asking for both
    cfg.write_text(f'[backend]\nname = "sim"\n[telemetry]\nsink = "connect"\nrrd = "{rrd}"\n'
                   'connect_url = "rerun+http://127.0.0.1:9/proxy"\n')
    res = subprocess.run([sys.executable, "-m", "rt_ident", "run", str(cfg), "--duration", "0.5"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f'error: telemetry.rrd: telemetry.sink = "connect" streams the dashboard to a viewer, so {rrd} would not be '
        'written; drop telemetry.rrd, or drop telemetry.sink = "connect" to write the file (a live dashboard is saved '
        "from the viewer)"]
    assert not rrd.exists() and not (tmp_path / "runs").exists()

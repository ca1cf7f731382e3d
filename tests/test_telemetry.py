"""Telemetry process: .rrd content, non-blocking publish to a dead viewer, loopback-only server."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest

from rt_ident.errors import ConfigError, DataError
from rt_ident.runtime import dashboard
from rt_ident.runtime.telemetry import TelemetryConfig, TelemetryProcess, default_sink, viewer_command


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
        "torque_hat": np.sin(i) + 0.5,
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
        v = np.array([x[0] for x in rb.column("Scalars:scalars").to_pylist()])
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
    expected = {dashboard.THETA1, dashboard.THETA2, dashboard.TORQUE_MEASURED, dashboard.TORQUE_RECONSTRUCTED,
                dashboard.estimate_path("I1"), dashboard.truth_path("I1"), dashboard.estimate_path("K"),
                dashboard.truth_path("K"), dashboard.estimate_path("wn"), dashboard.truth_path("wn"),
                dashboard.LATENESS, dashboard.OVERRUNS}
    assert expected <= set(data)
    # Decimation by 3 is continuous across blocks of 7 samples: every 3rd sample of the whole run.
    t_all = np.concatenate([b["t"] for b in blocks])
    th1_all = np.concatenate([b["theta1"] for b in blocks])
    t, v = data[dashboard.THETA1]
    assert np.allclose(t, t_all[::3], atol=1e-9, rtol=0) and np.array_equal(v, th1_all[::3])
    # Tick-rate estimates are not decimated and sit on t_tick.
    t, v = data[dashboard.estimate_path("I1")]
    assert np.array_equal(v, [b["I1"][0] for b in blocks])
    assert np.allclose(t, [b["t_tick"][0] for b in blocks], atol=1e-9, rtol=0)
    assert data[dashboard.LATENESS][1][5] == 15.0
    # The true value is drawn over the estimate's time span.
    t, v = data[dashboard.truth_path("K")]
    assert np.all(v == 2.5e5) and t.min() <= blocks[0]["t_tick"][0] and t.max() >= blocks[-1]["t_tick"][0]


def test_connect_to_absent_viewer_never_blocks_publish_and_counts_drops() -> None:
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    tp = TelemetryProcess(TelemetryConfig(sink="connect", connect_url=url, queue_size=8)).start()
    worst, n = 0.0, 300
    for k in range(n):
        t0 = time.perf_counter()
        tp.publish(_block(k, n=400))
        worst = max(worst, time.perf_counter() - t0)
    assert worst < 0.05
    assert tp.dropped > 0 and tp.published + tp.dropped == n
    t0 = time.perf_counter()
    summary = tp.close(timeout=2.0)
    assert time.perf_counter() - t0 < 2.5
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
             + list(dashboard.CONTROL_ENTITIES.values()))
    for path in paths:
        assert any(path == o or path.startswith(o + "/") for o in origins), path
    assert set(dashboard.SERIES_STYLES) >= set(dashboard.BLOCK_ENTITIES.values())

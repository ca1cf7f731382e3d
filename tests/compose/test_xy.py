"""Several axes in one run (an XY table): the config's [axes.*], one loop ticking both axes, a
trip on either axis stopping both, the JSON shape."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.compose import run as run_mod
from rt_ident.compose.run import run as run_axes
from rt_ident.config import load
from rt_ident.errors import ConfigError


def _xy(**over):
    return load("configs/xy-sim.toml", **{"loop.realtime": False, "telemetry.sink": "off",
                                          "recording.enabled": False, **over})


def test_axes_overlay_the_shared_sections_and_name_the_bad_field():
    cfg = _xy()
    axes = cfg.axis_configs()
    assert set(axes) == {"x", "y"}
    assert axes["y"].axis_params().I2 == pytest.approx(3 * axes["x"].axis_params().I2, rel=0.01)
    assert axes["x"].control.bandwidth_hz == axes["y"].control.bandwidth_hz == cfg.control.bandwidth_hz
    assert axes["y"].backend.options()["seed"] == 1 and axes["x"].backend.name == "sim"
    with pytest.raises(ConfigError) as e:
        load("configs/xy-sim.toml", **{"axes.y": {"control": {"bandwidth_hz": -1}}})
    assert e.value.field.startswith("axes.y.control.bandwidth_hz")
    with pytest.raises(ConfigError) as e:
        load("configs/xy-sim.toml", **{"axes.y": {"loop": {"duration": 1}}})
    assert e.value.field == "axes.y.loop"


def test_the_circular_tests_trace_is_sized_by_the_circle_not_by_the_runs_duration():
    from rt_ident.compose.contour import MAX_ROWS, trace_rows
    from rt_ident.control.reference import Circle

    c = Circle(0.005, 1.0, "x", 1, 4.0, 0.2)                      # xy-sim.toml's: over at 10.2 s
    assert trace_rows(c, 1e-3, 10**10) == 10_200 + 8              # a run of 1e7 s: 10 208 rows, not 1e10
    assert trace_rows(c, 1e-3, 500) == 508                         # a run that ends before the circle
    assert trace_rows(Circle(0.005, 1.0, "x", 10**6, 4.0, 0.2), 1e-3, 10**10) == MAX_ROWS


def test_a_one_axis_config_has_no_axes_and_keeps_its_summary_shape():
    assert load(None).axis_configs() == {}


@pytest.mark.slow
def test_one_loop_runs_both_axes_and_reports_each():
    s = run_axes(_xy(**{"loop.duration": 2.0}))
    assert s["stop"]["cause"] is None and run_mod.exit_code(s) == 0
    assert set(s["axes"]) == {"x", "y"}
    n = {name: ax["loop"]["samples"] for name, ax in s["axes"].items()}
    assert n["x"] > 0 and abs(n["x"] - n["y"]) <= 2 * 34          # the same ticks read both axes
    assert s["loop"]["samples"] == n["x"] + n["y"] and s["loop"]["ticks"] == s["axes"]["x"]["loop"]["ticks"]
    for ax in s["axes"].values():
        assert ax["control"]["rms_error_m"] is not None and ax["control"]["rms_error_m"] < 1e-4
        assert "parameters" in ax and "truth" in ax


@pytest.mark.slow
@pytest.mark.parametrize("axis", ["x", "y"])
def test_a_trip_on_either_axis_stops_both_at_zero_torque(axis):
    # a drive declared to hold the axis that does not: the probe walks that free table out of its window
    free = {"safety": {"window": [-2e-4, 2e-4]}, "control": {"mode": "off", "drive_holds": True}}
    cfg = _xy(**{"loop.duration": 4.0})
    data = cfg.model_dump(exclude={"source"})
    data["axes"][axis] = {**data["axes"][axis], **free}
    from rt_ident.config import from_mapping

    s = run_axes(from_mapping(data))
    assert s["stop"]["cause"] == "travel-limit" and s["stop"]["axis"] == axis
    assert s["stop"]["final_torque"] == {"x": 0.0, "y": 0.0}
    assert set(s["stop"]["backend_state"].values()) == {"closed"}
    assert run_mod.exit_code(s) == 3


@pytest.mark.parametrize("axis", ["x", "y"])
def test_a_watchdog_trip_on_either_axis_names_that_axis_when_both_have_the_same_safety_config(axis, monkeypatch):
    # both axes' safety monitors hold the same settings and the same counters: the stop must still name the
    # axis whose encoder went silent (monitors compared by value would make the second axis's trip crash
    # the summary); the other axis's feedback never stops
    from drivers.base import SampleBlock
    from drivers.sim import SimBackend

    cfg = _xy(**{"loop.duration": 3.0})
    silent_seed = {"x": 0, "y": 1}[axis]                             # configs/xy-sim.toml: y's sim has seed 1
    axes = cfg.axis_configs()
    assert axes["y"].backend.options()["seed"] == 1 and "seed" not in axes["x"].backend.options()
    assert cfg.axis_configs()["x"].safety == cfg.axis_configs()["y"].safety
    real_read = SimBackend._read
    reads: dict[int, int] = {}

    def read(self):
        block = real_read(self)
        seed = self.config.seed
        reads[seed] = reads.get(seed, 0) + 1
        if seed == silent_seed and reads[seed] > 300:        # this axis's encoder goes silent after 0.3 s
            return SampleBlock.empty(self.has_measured_torque)
        return block

    monkeypatch.setattr(SimBackend, "_read", read)
    s = run_axes(cfg)
    assert s["stop"]["cause"] == "watchdog" and s["stop"]["axis"] == axis, s["stop"]
    assert s["stop"]["final_torque"] == {"x": 0.0, "y": 0.0}
    assert set(s["stop"]["backend_state"].values()) == {"closed"}
    assert run_mod.exit_code(s) == 3
    assert s["axes"]["y" if axis == "x" else "x"]["loop"]["samples"] > 300 * 30


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_the_circular_test_reports_g_f_h_per_direction_and_draws_the_polar_plot(tmp_path, restore_scheduling,
                                                                                host_made_end):
    cfg = load("configs/xy-circle.toml", **{"loop.realtime": True, "telemetry.sink": "rrd", "loop.duration": 7.0,
                                            "telemetry.rrd": str(tmp_path / "c.rrd"),
                                            "recording.enabled": True, "recording.path": str(tmp_path / "c.parquet")})
    s = run_axes(cfg)
    if s["stop"]["cause"] is not None and host_made_end(s["stop"]):
        assert s["stop"]["final_torque"] == {"x": 0.0, "y": 0.0}, s["stop"]
        pytest.skip(f"the host ended the run: {s['stop']['message']}")
    assert s["stop"]["cause"] is None, s["stop"]
    c = s["contour"]
    assert c["complete"] == {"ccw": True, "cw": True} and c["radius_mm"] == 5.0
    for d in ("ccw", "cw"):
        f = c[d]
        # an idle machine gives G 12-16 um, mostly the 0.1 N m probing multisine; a tick that stalls for
        # milliseconds on a loaded machine runs the plan out and can give ~100 um; a controller that does not
        # track gives millimetres. A loop stall in the turn (the host, not the axis) is flagged instead
        assert f["F_min_um"] <= 0.0 <= f["F_max_um"]
        assert 0.0 < f["G_um"] < 300.0 or "disturbed_by_stall_at_s" in f, f
        # one point per tick the loop ran over each 1 s measured turn; the ticks it skipped (it fell behind) counted
        assert f["points"] + f["ticks_missed"] > 800 and (f["points"] > 800 or f["ticks_missed"] > 0), f
    assert 0.0 < c["H_um"] < 300.0 or any("disturbed_by_stall_at_s" in c[d] for d in ("ccw", "cw"))
    assert c["polar_png"] == str(tmp_path / "c-contour.png") and (tmp_path / "c-contour.png").stat().st_size > 10_000
    # one dashboard for both axes: the XY path against the reference, the ballbar trace, the radial deviation
    # along the circle (one value per measured point) and the figures
    assert c["rrd"] == str(tmp_path / "c-contour.rrd")
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(c["rrd"]).stream():
        ent = chunk.entity_path.lstrip("/")
        rows[ent] = rows.get(ent, 0) + chunk.to_record_batch().num_rows
    for ent in ("contour/xy/reference", "contour/xy/table_ccw", "contour/xy/table_cw", "contour/ballbar/ccw",
                "contour/ballbar/cw", "contour/ballbar/nominal", "contour/figures"):
        assert rows.get(ent, 0) >= 1, (ent, sorted(rows))
    for d in ("ccw", "cw"):
        assert rows[f"contour/radial_error/{d}"] == c[d]["points"]


@pytest.mark.slow
def test_the_xy_budget_bench_times_both_axes_against_one_and_each_axis_share():
    from rt_ident.bench.xy import TARGET_P99_US, xy_budget

    res = xy_budget(0.6, realtime=False)
    two, one = res["two_axes"], res["one_axis"]
    assert two["stop"] is None and one["stop"] is None
    # both axes read, as many samples each (a trial's count follows its wall time: a busy host's late ticks
    # read more per tick, so the two trials' totals do not compare)
    per = two["per_axis_samples"]
    assert set(per) == {"x", "y"} and two["samples"] == sum(per.values()) and one["samples"] > 0
    assert min(per.values()) >= 0.95 * max(per.values()) > 0
    shares = two["per_axis_work_us"]
    assert set(shares) == {"x", "y"}
    for w in shares.values():                                          # each axis's share is part of the tick
        assert 0.0 < w["p50"] < two["work_us"]["p50"]
    assert res["met"] == (two["work_us"]["p99"] <= TARGET_P99_US)
    assert res["p99_ratio_two_over_one"] == pytest.approx(two["work_us"]["p99"] / one["work_us"]["p99"])
    off = res["two_axes_no_idle_poll"]                                 # the peer runs: the same two axes
    py = res["two_axes_python_path"]                                  # (the other: no compiled tick)
    for peer in (off, py):
        assert peer["stop"] is None and set(peer["per_axis_samples"]) == {"x", "y"}
        assert min(peer["per_axis_samples"].values()) >= 0.95 * max(peer["per_axis_samples"].values()) > 0
    assert not any(r["idle_poll"] for r in (two, one, off))           # not real time: no poller anywhere
    # the compiled tick takes the ticks; a tick with no sample or a burst (a busy host's overruns) is the Python path's
    share = 0.9 if not two["overruns"] else 0.5
    assert all(c["on"] and c["ticks"] > share * (c["ticks"] + c["python_ticks"])
               for c in two["compiled_tick"].values()), (two["compiled_tick"], two["overruns"])
    assert not any(c["on"] or c["ticks"] for c in py["compiled_tick"].values())
    assert res["p99_ratio_compiled_over_python"] == pytest.approx(two["work_us"]["p99"] / py["work_us"]["p99"])


@pytest.mark.slow
def test_the_axes_hand_their_telemetry_windows_over_on_different_ticks(tmp_path, monkeypatch):
    # each hand-off (a window's samples, its per-tick signals) costs tens of microseconds: two on one
    # tick set the two-axis tick's p99, so no two of them, on either axis, share a tick. A hand-off is a
    # message the axis's telemetry process counts as published (the compiled tick's own, or the Python path's)
    from rt_ident.loop.loop import MultiAxisLoop

    handed: dict[str, list[int]] = {}
    late: set[int] = set()           # ticks after skipped periods: a burst of samples is published at once
    original = MultiAxisLoop.run

    def run(self):
        seen = {name: 0 for name in self.axes}
        skipped = [0]
        hook = self.tick_hook

        def count(n):
            for name, ax in self.axes.items():
                now = ax._publisher.published
                handed.setdefault(name, []).extend([self.stats.ticks] * (now - seen[name]))
                seen[name] = now
            if self.stats.skipped_periods != skipped[0]:
                skipped[0] = self.stats.skipped_periods
                late.update((self.stats.ticks, self.stats.ticks + 1))
            if hook is not None:
                hook(n)
        self.tick_hook = count
        return original(self)

    monkeypatch.setattr(MultiAxisLoop, "run", run)
    # the sim free-running (one tick's samples per read): a busy host's late tick then brings no burst
    s = run_axes(_xy(**{"loop.duration": 1.0, "telemetry.sink": "rrd", "telemetry.rrd": str(tmp_path / "t.rrd"),
                        "backend.paced": False}))
    assert s["stop"]["cause"] is None
    every = load("configs/xy-sim.toml").telemetry.publish_every_ticks
    assert set(handed) == {"x", "y"} and all(len(t) > 20 for t in handed.values())
    ticks = handed["x"] + handed["y"]
    shared = {t for t in ticks if ticks.count(t) > 1}
    assert shared <= late, (sorted(shared - late), sorted(late))          # no tick has two hand-offs but a burst's
    if late:                                    # a busy host skipped periods: the windows' rhythm restarts there
        return
    for t in handed.values():                                          # a window's two, on consecutive ticks
        samples, signals = t[0::2], t[1::2]
        assert set(np.diff(samples)) == {every} and all(b - a == 1 for a, b in zip(samples, signals))


@pytest.fixture
def rerun_server(tmp_path):
    """A rerun gRPC server on 127.0.0.1 that saves what SDKs send it to an .rrd (stands in for the viewer)."""
    import os
    import socket
    import subprocess
    import sys
    import time

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "viewer.rrd"
    # its own session: `python -m rerun_cli` runs the rerun binary as a child, which a terminate of the
    # Python process left running (an orphan listening on the port); the whole group is stopped below
    proc = subprocess.Popen([sys.executable, "-m", "rerun_cli", "--save", str(out), "--port", str(port),
                             "--bind", "127.0.0.1"], env=dict(os.environ, CI="1"), start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop():
        import signal

        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        proc.wait(10)

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            break
        except OSError:
            time.sleep(0.1)
    try:
        yield f"rerun+http://127.0.0.1:{port}/proxy", out, stop
    finally:
        stop()


def _recordings(path):
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    return {st.application_id: {ch.entity_path.lstrip("/") for ch in r.stream(store=st)} for st in r.recordings()}


def _received(path, wanted, timeout=30.0):
    """What the stand-in viewer has written to ``path`` once every recording in ``wanted`` (application
    id -> entity paths) has its entities, or at ``timeout``. The server writes what it receives as it
    arrives; stopping it right after the sender returns can lose the last chunks."""
    import time
    import warnings

    deadline = time.monotonic() + timeout
    while True:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")       # no footer while the server is still writing
                got = _recordings(path)
        except Exception:  # noqa: BLE001 - the file may not exist yet or end mid-chunk
            got = {}
        if all(set(e) <= got.get(app, set()) for app, e in wanted.items()) or time.monotonic() > deadline:
            return got
        time.sleep(0.1)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_live_xy_run_streams_both_axes_to_one_viewer(rerun_server):
    url, out, stop = rerun_server
    s = run_axes(_xy(**{"loop.duration": 1.5}), sink="connect", connect_url=url)
    assert s["stop"]["cause"] is None and s["live_url"] == url
    assert all(f["rrd"] is None for f in s["files"].values())          # nothing written locally
    recs = _received(out, {f"rt_ident-{n}": {"control/error", "angles"} for n in ("x", "y")})
    stop()
    for name in ("x", "y"):                                              # each axis its own recording
        assert {"control/error", "angles"} <= recs.get(f"rt_ident-{name}", set()), sorted(recs)


def test_the_contour_dashboard_goes_to_the_viewer_of_a_live_run(rerun_server):
    from rt_ident.outputs.dashboard import write_contour_rrd

    url, out, stop = rerun_server
    a = np.linspace(0.0, 2 * np.pi, 400)
    path = (0.005 * np.cos(a), 0.005 * np.sin(a) - 0.005)
    fig = {"ccw": {"G_um": 1.0, "F_min_um": -0.5, "F_max_um": 0.5}, "H_um": 0.2}
    assert write_contour_rrd(None, path, {"ccw": path}, 0.005, (0.0, -0.005), fig, connect_url=url) == url
    wanted = {"contour/xy/table_ccw", "contour/figures", "contour/radial_error/ccw"}
    recs = _received(out, {"rt_ident-xy-contour": wanted})
    stop()
    assert wanted <= recs.get("rt_ident-xy-contour", set()), sorted(recs)


def test_an_xy_run_refuses_serve_and_a_connect_without_url():
    with pytest.raises(ConfigError, match="server per axis"):
        run_axes(_xy(), sink="serve")
    with pytest.raises(ConfigError, match="connect_url"):
        run_axes(_xy(), sink="connect")


def test_the_axes_supervisors_take_their_redesign_steps_on_alternate_ticks(monkeypatch):
    # each step (a request, taking a design, adopting it) is a few hundred microseconds of Python:
    # both axes' on one tick passed the period
    from rt_ident.control.adaptation import Supervisor
    from rt_ident.loop.loop import MultiAxisLoop

    loops: list = []
    init, poll = MultiAxisLoop.__init__, Supervisor.poll
    steps: dict[int, set[int]] = {}

    def keep(self, *a, **k):
        init(self, *a, **k)
        loops.append(self)

    def counted(self):
        if self._pending and loops:
            steps.setdefault(loops[0].stats.ticks, set()).add(id(self))
        poll(self)

    monkeypatch.setattr(MultiAxisLoop, "__init__", keep)
    monkeypatch.setattr(Supervisor, "poll", counted)
    s = run_axes(_xy(**{"loop.duration": 2.5, "loop.realtime": False, "telemetry.sink": "off",
                        "recording.enabled": False}))
    assert s["stop"]["cause"] is None
    # the first redesigns follow the first trusted fits: ~0.5 s on an idle machine, later beside other tests
    assert len({sup for both in steps.values() for sup in both}) == 2          # both axes asked for a redesign
    assert all(len(both) == 1 for both in steps.values()), sorted(t for t, b in steps.items() if len(b) > 1)


@pytest.mark.parametrize("several", [False, True], ids=["one-axis", "xy"])
def test_a_device_that_did_not_confirm_its_disable_is_named_in_the_summary_on_one_axis_and_two(several, monkeypatch):
    from drivers.sim import SimBackend

    stops: list[SimBackend] = []
    disable = SimBackend._safe_stop

    def first_unconfirmed(self):
        disable(self)
        stops.append(self)
        return "the drive did not report itself disabled" if len(stops) == 1 else None

    monkeypatch.setattr(SimBackend, "_safe_stop", first_unconfirmed)
    over = {"loop.duration": 0.3, "telemetry.sink": "off", "recording.enabled": False, "loop.realtime": False}
    s = run_axes(_xy(**over) if several else load(None, **over))
    assert s["stop"]["cause"] is None and run_mod.exit_code(s) == 0   # the run itself ended as asked
    got = s["stop"]["disable_unconfirmed"]
    if several:
        assert len(stops) == 2 and len(got) == 1 and set(got) <= {"x", "y"}      # the one axis that said so
        assert list(got.values()) == ["the drive did not report itself disabled"]
    else:
        assert got == "the drive did not report itself disabled" and len(stops) == 1

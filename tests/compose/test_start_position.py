"""The run starts where the table is: the reference is anchored at the position at enable (or moves there
from the scale's origin within its limits), and a config that would trip on its first ticks is refused
before anything is energized (rt_ident.compose.preflight, rt_ident.control.anchor)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers import make_backend
from rt_ident import config
from rt_ident.compose.build import max_speed, probe_motion
from rt_ident.compose.offline import run_offline
from rt_ident.compose.preflight import check_config
from rt_ident.compose.run import run
from rt_ident.control.anchor import DEFAULT_LIMITS, braking_limits, rejoin
from rt_ident.errors import ConfigError
from rt_ident.loop.safety import SafetyMonitor

LEAD = 7.96e-4


def cfg(**over):
    data = {"loop": {"realtime": False, "duration": 1.0},
            "backend": {"name": "sim", "paced": False, "torque_meas_noise": 0.0005},
            "telemetry": {"sink": "off"}, "recording": {"enabled": False}}
    for dotted, v in over.items():                       # section__key or section__table__key
        *path, key = dotted.split("__")
        node = data
        for part in path:
            node = node.setdefault(part, {})
        node[key] = v
    return config.from_mapping(data)


def _track(c, duration: float = 3.0):
    """The offline loop on ``c``; (t, table x, reference x, control torque) per tick with new samples."""
    rows = []

    def hook(loop):
        ctl = loop.control
        rows.append((ctl.t, ctl.x_ref + ctl.error, ctl.x_ref, ctl.law.u))

    out = run_offline(c.model_copy(update={"loop": c.loop.model_copy(update={"duration": duration})}), tick_hook=hook)
    r = np.array(rows)
    return out, r[np.r_[True, np.diff(r[:, 0]) > 0]]


def test_origin_enable_holds_the_table_where_it_starts_30_mm_from_zero_without_a_torque_step():
    out, r = _track(cfg(plant__actual__x0=0.03))
    assert out["stop"] is None and out["control"]["fallbacks"] == 0
    assert out["control"]["reference"]["origin_m"] == pytest.approx(0.03, abs=1e-6)
    t, x, xr, u = r.T
    assert np.all(np.abs(x - 0.03) < 1e-4) and np.all(np.abs(xr - 0.03) < 1e-5)
    assert np.abs(u[:50]).max() < 0.05                  # the first ticks hold still: no step towards 0


def test_origin_scale_moves_the_table_to_zero_within_the_approach_limits_never_as_a_step():
    out, r = _track(cfg(plant__actual__x0=0.03, reference__origin="scale"), duration=3.0)
    assert out["stop"] is None and out["control"]["fallbacks"] == 0
    t, x, xr, u = r.T
    v_ref = np.diff(xr) / np.diff(t)
    assert np.abs(v_ref).max() <= DEFAULT_LIMITS.v_max * 1.001
    assert np.abs(np.diff(v_ref) / np.diff(t[1:])).max() <= DEFAULT_LIMITS.a_max * 1.05
    # the table follows: its speed over whole probe periods (15 ms) stays near the reference's
    per = 15
    v_table = (x[per:] - x[:-per]) / (t[per:] - t[:-per])
    assert np.abs(v_table).max() <= DEFAULT_LIMITS.v_max * 1.2
    assert abs(x[-1]) < 1e-4 and abs(x[0] - 0.03) < 1e-4
    assert np.abs(u).max() < 0.5                        # far from the 1 N m limit: no lunge
    assert "approach" in next(e["detail"] for e in out["control"]["events"] if e["kind"] == "anchored")


def test_the_rejoin_starts_at_the_table_and_ends_at_rest_on_the_path_within_the_limits():
    for d0, v0 in ((0.03, 0.0), (-0.01, 0.02), (0.001, 0.02), (0.0, -0.05)):
        seg = rejoin(d0, v0, DEFAULT_LIMITS, 2.0)
        t = np.linspace(2.0, seg.end + 0.05, 100001)
        x, v, a = seg.at(t)
        assert x[0] == pytest.approx(d0) and v[0] == pytest.approx(v0)
        assert abs(x[-1]) < 1e-12 and abs(v[-1]) < 1e-12
        assert np.abs(v).max() <= max(abs(v0), DEFAULT_LIMITS.v_max) + 1e-12
        assert np.abs(a).max() <= DEFAULT_LIMITS.a_max + 1e-12


def test_a_rejoin_brakes_at_the_axis_rate_only_a_speed_above_the_paths_limit():
    brake = braking_limits(3.53e-5, LEAD, 1.0)
    assert brake is not None and brake.a_max == pytest.approx(0.5 * LEAD / 3.53e-5)
    for d0, v0 in ((0.03, 0.0), (-0.01, 0.02), (0.001, -0.02)):        # within v_max: the path's own limits
        assert rejoin(d0, v0, DEFAULT_LIMITS, 0.0, brake).end == rejoin(d0, v0, DEFAULT_LIMITS, 0.0).end
    seg = rejoin(0.0, 0.2, DEFAULT_LIMITS, 0.0, brake)
    t = np.linspace(0.0, seg.end, 200001)
    x, v, a = seg.at(t)
    stop = int(np.argmax(v <= 0.0))
    assert x[stop] < 4e-3                                 # the path's 0.5 m/s² would need 40 mm
    assert np.abs(a).max() <= brake.a_max * (1 + 1e-9) and a[0] == 0.0     # a ramp, not a step
    assert np.abs(a[stop:]).max() <= DEFAULT_LIMITS.a_max + 1e-12        # back to the path gently
    assert braking_limits(0.0, LEAD, 1.0) is None and braking_limits(3.53e-5, LEAD, float("inf")) is None


def test_a_start_outside_the_window_is_refused_before_the_device_is_enabled(monkeypatch):
    activated = []
    from drivers.sim import SimBackend

    real = SimBackend._activate
    monkeypatch.setattr(SimBackend, "_activate", lambda self: (activated.append(1), real(self)))
    outside = r"safety.window: the table is at 0.000 mm, outside safety.window \[10.000, 40.000\] mm"
    with pytest.raises(ConfigError, match=outside):
        run(cfg(safety__window=[0.01, 0.04]))
    assert activated == []


def test_a_scale_that_reads_no_number_is_refused_in_plain_words():
    from rt_ident.compose.preflight import check_start

    with pytest.raises(ConfigError, match=r"axis x: the table's position reads nan; check the scale$"):
        check_start(cfg(), np.float64("nan"), 1e-3, where="x")


def test_a_reference_that_leaves_the_window_from_where_the_table_is_is_refused():
    c = cfg(plant__actual__x0=0.035, reference__kind="moves", reference__positions=[0.0, 0.01],
            reference__v_max=0.02, reference__a_max=0.5, reference__j_max=20.0)
    with pytest.raises(ConfigError, match=r"reference: the run would take the table over"):
        run(c)


def test_control_off_is_refused_unless_something_holds_the_axis():
    with pytest.raises(ConfigError, match=r"control.mode: 'off' leaves a torque-mode axis"):
        check_config(cfg(control__mode="off"), 1.0)
    check_config(cfg(control__mode="off", backend__position_hold=True), 1.0)
    check_config(cfg(control__mode="off", control__drive_holds=True), 1.0)


def test_an_excitation_peak_the_loop_cannot_hold_against_is_refused():
    with pytest.raises(ConfigError, match=r"excitation.peak: 1e\+09 N m is more than 0.5 x the torque limit"):
        run(cfg(excitation__peak=1e9))


def test_the_default_speed_limit_covers_the_path_the_rejoin_and_the_probe():
    c = cfg(reference__kind="moves", reference__positions=[0.0, 0.01], reference__v_max=0.03,
            reference__a_max=0.5, reference__j_max=20.0)
    v_probe, x_probe = probe_motion(c, 2.9481e-5)
    assert 1e-3 < v_probe < 0.02 and 0 < x_probe < 5e-5          # the default multisine shakes by microns
    assert max_speed(c, 2.9481e-5) == pytest.approx(2.0 * (0.03 + 0.03 + v_probe), rel=1e-3)
    assert max_speed(cfg(safety__max_speed_m_s=0.1), 2.9481e-5) == 0.1


def test_the_speed_limit_trips_on_a_table_faster_than_it():
    from drivers.errors import SpeedTrip

    mon = SafetyMonitor(lead=LEAD, window=(-0.04, 0.04), max_decel=2e4, watchdog_ticks=20, max_speed=0.05)
    mon.check(10, 0.0, 0.0, 0.049 / LEAD, False)
    with pytest.raises(SpeedTrip, match=r"table at \+60.0 mm/s, faster than safety.max_speed_m_s = 50.0 mm/s"):
        mon.check(10, 0.0, 0.0, 0.06 / LEAD, False)


@pytest.mark.parametrize("name", ["sim", "serial", "canopen"])
def test_every_device_reports_where_the_table_starts_before_it_is_enabled(name):
    """[plant.actual] x0 reaches the sim and both emulators, and each backend reads it before enabling."""
    from rt_ident.compose.build import backend_options
    from rt_ident.processes.emulation import start_emulator

    path = {"sim": None, "serial": "serial-virtual.toml", "canopen": "canopen-virtual.toml"}[name]
    c = config.load(path, **{"loop.realtime": False})
    c = config.from_mapping({**c.model_dump(exclude={"source", "axes", "contour"}), "plant": {"actual": {"x0": 0.012}}})
    emu = start_emulator(c) if c.backend.emulate else None
    try:
        opts = backend_options(c)
        if getattr(emu, "port", None):
            opts["port"] = emu.port
        backend = make_backend(c.backend.name, opts)
        with backend:
            th1, th2 = backend.read_position()
        assert LEAD * th2 == pytest.approx(0.012, abs=2e-7)
        assert th1 == pytest.approx(th2, abs=1e-4)          # the coupling at rest: motor and table agree
    finally:
        if emu is not None:
            emu.close()


def test_plant_actual_is_refused_for_a_real_device():
    with pytest.raises(ConfigError, match=r"plant.actual: describes a simulated device"):
        config.from_mapping({"backend": {"name": "canopen"}, "plant": {"actual": {"x0": 0.01}}})

"""A loop stall (the host stops ticking while the drive runs on): the loop resumes from where the table is,
or stops, and says so (rt_ident.loop.stall, rt_ident.control.anchor)."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from rt_ident.compose.offline import run_offline
from rt_ident.config import load
from rt_ident.errors import DataError
from rt_ident.estimators.frequency_stream import StreamingFrequencyEstimator
from rt_ident.loop.stall import StallLog, StallPolicy

FAST = {"loop.realtime": False, "telemetry.sink": "off", "recording.enabled": False, "loop.duration": 4.0}
# a back-and-forth move: a stall mid-move leaves the table coasting at the move's speed
MOVES = {"kind": "moves", "positions": [0.0, 0.01], "v_max": 0.02, "a_max": 0.5, "j_max": 20.0, "dwell": 0.3}
STALL_TICK = 1500                     # the table is moving back at the move's speed then


def _stalled_run(stall_s: float, **over):
    """The offline loop on a paced sim; the clock jumps ``stall_s`` after tick STALL_TICK (the host froze,
    the drive did not). Returns the summary and (t, table x, reference x, control torque) per tick."""
    cfg = load(None, **{**FAST, **over})
    cfg = cfg.model_copy(update={"reference": MOVES})
    rows = []

    def hook(loop):
        if loop.stats.ticks == STALL_TICK:
            loop.clock.now += stall_s
        c = loop.control
        rows.append((c.t, c.x_ref + c.error, c.x_ref, c.law.u - c.law.u_ff))

    return run_offline(cfg, tick_hook=hook, paced=True), np.array(rows)


@pytest.fixture(scope="module")
def resumed():
    return _stalled_run(0.5)


def test_a_half_second_stall_resumes_from_where_the_table_is_without_a_lunge(resumed):
    out, rows = resumed
    assert out["stop"] is None
    assert out["loop"]["stalls"]["count"] == 1 and 490 <= out["loop"]["stalls"]["longest_ms"] <= 510
    ctl = out["control"]
    assert ctl["fallbacks"] == 0 and ctl["max_error_m"] < 1e-4        # the error never built up
    stall = [e for e in ctl["events"] if e["kind"] == "stall"]
    assert len(stall) == 1 and "re-planned from x =" in stall[0]["detail"]
    t, x, xr, u_fb = rows[np.r_[True, np.diff(rows[:, 0]) > 0]].T       # ticks with new samples
    after = t > rows[STALL_TICK - 1, 0] + 0.4
    # the reference starts where the table coasted to; it rejoins the path within the move's limits
    # on top of the path's own speed (each at most v_max)
    ref_speed = np.abs(np.diff(xr[after]) / np.diff(t[after]))
    assert ref_speed.max() <= 2 * MOVES["v_max"] * 1.01
    assert abs(xr[after][0] - x[after][0]) < 1e-4
    # no torque step: the feedback torque of the resumed tick is the drive's (zero) within a small fraction
    assert abs(u_fb[after][0]) < 0.05


def _held_run(torque: float, stall_s: float):
    """The offline loop holding the table; after tick STALL_TICK the drive keeps ``torque`` through a
    ``stall_s`` stall of the host (a CANopen drive applies its last RPDO until its own deadline), so the
    table is moving fast when the loop resumes. The speed limit is lifted: the braking is under test."""
    cfg = load(None, **{**FAST, "loop.duration": 3.0, "safety.max_speed_m_s": 1.0})
    rows = []

    def hook(loop):
        if loop.stats.ticks == STALL_TICK:
            loop.backend.write(torque)
            loop.clock.now += stall_s
        c = loop.control
        rows.append((c.t, c.x_ref + c.error, c.law.u))

    out = run_offline(cfg, tick_hook=hook, paced=True)
    r = np.array(rows)
    return out, r[np.r_[True, np.diff(r[:, 0]) > 0]].T


def test_a_table_the_drive_kept_pushing_through_a_stall_is_braked_at_the_axis_rate_not_the_paths():
    out, (t, x, u) = _held_run(0.3, 0.04)
    assert out["stop"] is None and out["control"]["fallbacks"] == 0
    (stall,) = [e["detail"] for e in out["control"]["events"] if e["kind"] == "stall"]
    speed = abs(float(re.search(r"at ([-+\d.]+) mm/s", stall).group(1)))
    assert speed > 200 and "braked at 11 m/s" in stall        # 0.5 x 1 N m over the nominal inertia
    resumed = int(np.searchsorted(t, t[STALL_TICK - 10] + 0.04)) + 1
    # from 263 mm/s the path's 0.5 m/s² would take 69 mm (past the 40 mm window); the axis's rate takes mm
    assert np.abs(x[resumed:] - x[resumed]).max() < 6e-3
    assert np.abs(u[resumed:]).max() < 0.75                      # braking within the torque limit's share


def test_the_same_stall_handled_as_before_lunges_into_a_trip():
    out, _ = _stalled_run(0.5, **{"safety.max_stall_s": 0.9, "safety.max_stall_stop_s": 1.0})
    # no re-plan: the half second of coasting is an error the controller drives back at full torque
    assert out["stop"] is not None and ("SpeedTrip" in out["stop"] or "TravelLimitTrip" in out["stop"])


def test_on_stall_stop_ends_the_run_with_loop_stall_naming_its_length():
    out, _ = _stalled_run(0.3, **{"safety.on_stall": "stop"})
    assert re.match(r"LoopStall: loop stalled for (299|300) ms", out["stop"]) and "on_stall = 'stop'" in out["stop"]


def test_a_stall_longer_than_max_stall_stop_s_always_stops():
    out, _ = _stalled_run(0.3, **{"safety.max_stall_stop_s": 0.2})
    assert "LoopStall" in out["stop"] and "max_stall_stop_s = 200 ms" in out["stop"]


def test_a_trip_after_a_stall_names_the_stall():
    # a window the coasting table leaves: the trip that follows the resume says which stall came before it
    out, _ = _stalled_run(0.8, **{"safety.window": [-0.012, 0.015]})
    assert "TravelLimitTrip" in out["stop"] and re.search(r"\(0\.0\d s after a (799|800) ms loop stall\)", out["stop"])


def test_short_late_ticks_are_not_stalls():
    out, _ = _stalled_run(0.005)
    assert out["stop"] is None and out["loop"]["stalls"]["count"] == 0


def test_stall_policy_verdicts():
    p = StallPolicy(max_s=0.01, action="resume", stop_s=1.0)
    assert p.verdict(0.01) is None and p.verdict(0.02) == "resume"
    assert "max_stall_stop_s" in p.verdict(1.5)
    assert "on_stall = 'stop'" in StallPolicy(action="stop").verdict(0.02)


def test_a_loop_stall_stop_puts_the_stall_on_the_host_and_keeps_its_fix_across_processes():
    import pickle

    from rt_ident.errors import HOST_FIX
    from rt_ident.loop.stall import LoopStall

    chosen = LoopStall("loop stalled for 20 ms", "safety.on_stall = 'resume'")
    assert chosen.fix.startswith(HOST_FIX + "; else safety.on_stall = 'resume')"), chosen.fix
    too_long = LoopStall("loop stalled for 1500 ms, longer than it may resume from")
    assert too_long.fix.startswith(HOST_FIX + ")") and "on_stall" not in too_long.fix, too_long.fix
    back = pickle.loads(pickle.dumps(chosen))
    assert (str(back), back.fix) == (str(chosen), chosen.fix)



@pytest.mark.parametrize(("stall_s", "names_resume"), [(0.3, True), (1.5, False)])
def test_on_stall_stop_names_resume_only_for_a_stall_resume_would_have_taken(stall_s, names_resume):
    from rt_ident.loop.loop import _stall_before
    from rt_ident.loop.stall import LoopStall
    from rt_ident.loop.stats import LoopStats

    with pytest.raises(LoopStall) as e:
        _stall_before([], [], LoopStats(), StallPolicy(action="stop", stop_s=1.0), stall_s, 0.0)
    assert ("on_stall = 'resume'" in e.value.fix) == names_resume, e.value.fix


def test_stall_log_links_only_a_recent_stall():
    log = StallLog()
    log.note(10.0, 0.47, "resume")
    assert log.before(10.4) == " (0.40 s after a 470 ms loop stall)"
    assert log.before(13.0) == "" and log.before(9.0) == ""
    assert log.as_dict()["count"] == 1 and log.as_dict()["longest_ms"] == pytest.approx(470)


def test_the_frequency_estimator_leaves_out_the_periods_a_stall_touched():
    N, H = 64, np.arange(1, 5)
    rng = np.random.default_rng(1)

    def fed(skip_at: int | None) -> StreamingFrequencyEstimator:
        est = StreamingFrequencyEstimator(N, H, 1e-4)
        x = rng.standard_normal((3, 10 * N))
        for i in range(0, 10 * N, 16):
            if skip_at is not None and i == skip_at:
                est.skip(40)                # 40 samples from mid-period 3 (48): periods 4 and 5 are touched
            est.update_block(x[0, i:i + 16], x[1, i:i + 16], x[2, i:i + 16])
        return est

    assert fed(None).periods == 10
    # periods 4 and 5 hold the skipped samples, period 6 the resumed loop's transient
    assert fed(3 * N + 48).periods == 7


def _sigstop_run(tmp_path, *extra: str, journal_of: str = "s.parquet", early_ok: bool = False,
                 journal_bytes: int = 2_000_000, duration: float = 3.5):
    """``rt-ident run`` (the quick start's command, real time, ``duration`` s) stopped for 0.5 s with SIGSTOP
    once ``journal_of`` (the recording that shows the loop is running) holds ``journal_bytes``, then SIGCONT:
    the exit code, the summary, the recording, stderr, and when the SIGSTOP was sent, in seconds after the start
    (False when it was not: ``early_ok``, the run may end by itself before it)."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from rt_ident.outputs.recording_reader import read_recording

    rec = tmp_path / "s.parquet"
    cmd = [sys.executable, "-m", "rt_ident", "run", "--duration", str(duration), "--json", "--no-telemetry",
           "--record", str(rec), *extra]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    started = time.monotonic()
    try:
        journal = rec.with_name(journal_of + ".arrows")
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not journal.exists() or journal.stat().st_size < journal_bytes) \
                and proc.poll() is None:
            time.sleep(0.05)                        # ~1.5 s of samples recorded: the loop is well under way
        if proc.poll() is not None and early_ok:     # a stall of its own (a busy machine) came first
            out, err = proc.communicate(timeout=60)
            s = json.loads(out)
            recorded = rec.with_name(journal_of).exists() or journal.exists()
            if not recorded and "no heartbeat from node 127" in err:
                pytest.skip(f"the host's own heartbeat lapsed before the run recorded (a busy host): {s.get('stop')}")
            if not recorded and (s["stop"].get("fix") or "").startswith("loop.realtime"):
                return proc.returncode, s, None, err, False      # the host ended it before it recorded
            assert recorded, f"the run ended before it recorded (rc {proc.returncode}): {s.get('stop')} {err[-3000:]}"
            try:
                early = read_recording(rec.with_name(journal_of))
            except DataError:                        # fewer samples than a recording reads back
                early = None
            return proc.returncode, s, early, err, False
        if not journal.exists() or proc.poll() is not None:
            out, err = proc.communicate(timeout=60)
            raise AssertionError(f"the run never started recording (rc {proc.returncode}): {out[-1500:]} {err[-3000:]}")
        os.kill(proc.pid, signal.SIGSTOP)
        sent = time.monotonic() - started
        time.sleep(0.5)
        os.kill(proc.pid, signal.SIGCONT)
        out, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    return proc.returncode, json.loads(out), read_recording(rec.with_name(journal_of)), err, sent


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_a_sigstop_of_the_run_process_resumes_without_a_lunge(tmp_path):
    rc, s, r, err, _ = _sigstop_run(tmp_path)
    assert rc == 0, (s["stop"], s["control"]["events"][-10:], s["loop"]["stalls"], err[-2000:])
    assert s["stop"]["cause"] is None
    stalls = s["loop"]["stalls"]
    assert stalls["count"] >= 1 and stalls["longest_ms"] >= 400, stalls
    assert s["loop"]["late_compiles"]["count"] == 0, s["loop"]["late_compiles"]
    assert s["loop"]["overruns_backlog"] >= 1, s["loop"]       # the 0.5 s of samples took the resume > a tick
    t_resume = max(e["t"] for e in s["control"]["events"] if e["kind"] == "stall")
    # the table's speed over whole probe periods (the probe's own motion averages out exactly)
    per = 512
    x = 7.96e-4 * r.theta2
    v = (x[per:] - x[:-per]) / (r.t[per:] - r.t[:-per])
    tv = r.t[per:]
    coast = np.abs(v[(tv > t_resume - 0.05) & (tv <= t_resume)]).max()   # the drive had dropped the torque
    after = np.abs(v[tv > t_resume + 0.02])
    # from the coasting speed the rejoin brakes; back to the hold position at most at its v_max (20 mm/s)
    assert after.max() <= max(coast, 0.02) * 1.15 + 2e-3, (after.max(), coast)
    assert s["control"]["max_error_m"] < 2e-3


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")
def test_a_sigstop_of_a_canopen_run_ends_on_the_drives_rpdo_deadline_not_a_lunge(tmp_path):
    """The whole process stops: no SYNC, no RPDO. A CiA 402 drive in torque mode holds its last target
    torque; the RPDO deadline the host set (backend.rpdo_deadline_ms) ends that within 20 ms, where the
    heartbeat consumer (250 ms here) would let the table run on."""
    early = []
    for k in range(3):                        # a run that stopped by itself (a busy host) is run again
        (tmp_path / str(k)).mkdir()
        rc, s, r, err, sent = _sigstop_run(tmp_path / str(k), "configs/canopen-virtual.toml", journal_bytes=150_000,
                                           early_ok=True)
        stop = s["stop"]
        # stopped by itself before the SIGSTOP, or after the journal's size was reached while its files were
        # written (the stop follows no stall of the SIGSTOP's length)
        before = stop["cause"] is not None and "loop stall" not in (stop["message"] or "") \
            and s["loop"]["stalls"]["longest_ms"] < 400
        if sent and not before:
            break
        early.append(f"{stop['cause']}: {stop['message']} (stalls {s['loop']['stalls']})")
    else:
        pytest.skip(f"each run stopped by itself before the SIGSTOP (a busy host): {early}")
    # the SIGSTOP's stall, or one of the busy host's own before it: the drive ended it, and the stop says so -
    # unless the emulated drive, starved after the resume, left the host stale data before its EMCY was read
    # (the stop then says that, naming the host)
    assert rc == 3, (stop, err[-2000:])
    from rt_ident.compose.run import emulator_nodes

    emulated = s.get("emulator") or {}
    paused = max(float(st.get("paused_s") or 0.0) for st in emulator_nodes(emulated))
    if stop["cause"] == "device-fault" and "no heartbeat from node" in (stop["message"] or "") and paused >= 0.2:
        # the emulated drive was itself starved through the stall (a drive has a processor of its own): it sent
        # neither its heartbeat nor its deadline's EMCY, so the host's heartbeat watch ended the run instead
        assert stop["fix"].startswith("loop.realtime"), stop
        pytest.skip(f"the emulated drive was paused {paused:.2f} s itself: {stop['message']}")
    # the drive's own account, short enough to survive pytest's truncation of a failure's message
    drive = [{k: st.get(k) for k in ("state", "nmt_state", "emcy_codes", "frames_sent", "paused_s",
                                     "longest_silence_s", "late_syncs")} for st in emulator_nodes(emulated)]
    if not (stop["cause"] == "watchdog" and "emulated drive answered" in stop["message"]):
        assert stop["cause"] == "device-fault", (stop["message"], drive, err[-2000:])
        assert "0x8250" in stop["message"] and "stall" in stop["message"], (stop["message"], drive,
                                                                             s["loop"]["stalls"])
        assert "backend.rpdo_deadline_ms" in stop["fix"], stop
    assert stop["fix"].startswith("loop.realtime"), stop
    # the drive's own account: the torque held 20 ms at most, so the table's speed at the fault is bounded
    # by the torque limit's impulse (1 N m x 20 ms on I1 + I2)
    bound = 1.0 * 0.020 / (2.7e-5 + 8.3e-6) * 7.96e-4
    fault = re.search(r"fault EMCY 0x8250.*table at x = (-?[\d.]+) mm, (-?[\d.]+) mm/s", err)
    if fault is not None:
        assert abs(float(fault.group(2))) * 1e-3 <= bound, (fault.group(0), bound)
    else:       # the host's watchdog stopped the starved drive before its deadline ran out: the host's last samples
        assert stop["cause"] == "watchdog", (stop, err[-3000:])
        n = min(20, len(r.t) - 1)
        v = 7.96e-4 * (r.theta2[-1] - r.theta2[-1 - n]) / (r.t[-1] - r.t[-1 - n])
        assert abs(v) <= bound, (v, bound, stop)


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_a_sigstop_with_on_stall_stop_ends_in_loop_stall(tmp_path):
    cfg_path = tmp_path / "stop.toml"
    from rt_ident.axis.params import CONFIG_DIR

    cfg_path.write_text((CONFIG_DIR / "sim.toml").read_text().replace("[safety]", "[safety]\non_stall = \"stop\""))
    # on a busy machine the run may stall by itself before the SIGSTOP: it must end the same way; and its
    # recorder may lag seconds behind the loop, whose journal times the SIGSTOP: 5 s keep it inside the loop
    rc, s, r, err, _ = _sigstop_run(tmp_path, str(cfg_path), early_ok=True, duration=5.0)
    assert rc == 3 and s["stop"]["cause"] == "loop-stall", (s["stop"], err[-2000:])
    assert re.match(r"loop stalled for \d+ ms", s["stop"]["message"])
    # the stall is the host's, and the setting that would have let the run resume is named
    assert s["stop"]["fix"].startswith("loop.realtime") and "safety.on_stall = 'resume'" in s["stop"]["fix"], s["stop"]
    # the stalled tick's samples are in the recording (one that ended too early to read back has under 10)
    assert len(r) == s["loop"]["samples"] if r is not None else s["loop"]["samples"] < 10, s["loop"]["samples"]


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_a_sigstop_of_an_xy_run_resumes_both_axes(tmp_path):
    # stopped once the x axis's journal holds 1 MB (about half a second of its samples): each axis's recorder
    # may trail the loop by seconds on a busy host, and a later threshold could fall after the loop's end
    rc, s, _, err, sent = _sigstop_run(tmp_path, "configs/xy-sim.toml", journal_of="s-x.parquet",
                                       journal_bytes=1_000_000)
    assert rc == 0 and s["stop"]["cause"] is None, (s["stop"], err[-2000:])
    assert s["loop"]["stalls"]["longest_ms"] >= 400, (f"SIGSTOP {sent:.2f} s after the start", s["loop"])
    assert s["loop"]["late_compiles"]["count"] == 0, s["loop"]["late_compiles"]
    for name in ("x", "y"):
        ax = s["axes"][name]
        assert ax["loop"]["stalls"]["count"] >= 1
        assert any(e["kind"] == "stall" for e in ax["control"]["events"])
        assert ax["control"]["max_error_m"] < 2e-3, name


def test_the_value_a_lease_holds_is_the_control_torque_not_the_probes_instant():
    from rt_ident.loop import tick_kernel as tk

    bi, bf = tk.new_books()
    bf[tk.BF_U_BASE] = 0.05                                  # the control torque in force
    plan = np.full(40, 0.3)                                  # the probe at its peak through the plan
    tk.shape_plan(plan, 1000, bi, bf, 512, 1.0)
    assert np.all(plan[:-1] == pytest.approx(0.35)) and plan[-1] == pytest.approx(0.05)


def test_a_stalled_host_leaves_the_table_coasting_at_the_probes_own_speed():
    # held for the lease, the probe's instant pushed the light table to 15 mm/s (median), 29 mm/s at worst
    # over 20 stall instants; the probe's own motion is +-6 mm/s
    import re as _re

    speeds = []
    for at in range(1000, 1400, 40):
        def hook(loop, at=at):
            if loop.stats.ticks == at:
                loop.clock.now += 0.05

        out = run_offline(load(None, **{**FAST, "loop.duration": 1.5}), tick_hook=hook, paced=True)
        detail = next(e["detail"] for e in out["control"]["events"] if e["kind"] == "stall")
        speeds.append(abs(float(_re.search(r"at ([-+\d.]+) mm/s", detail).group(1))))
    assert max(speeds) < 12.0, speeds


def test_a_stall_between_the_ticks_wait_and_its_read_is_caught_by_the_device_time_the_block_covers():
    # the host stops after the ticker let the tick start: the tick is on time, its block is not
    from drivers.sim import SimBackend

    cfg = load(None, **FAST).model_copy(update={"reference": MOVES})
    jumped = []
    real_read = SimBackend.read

    def read(self):
        if len(jumped) == 0 and self.samples_produced > int(1.5 / self.sample_period):
            jumped.append(1)
            self._clock.now += 0.5                    # the virtual clock: the host froze right before the read
        return real_read(self)

    from unittest import mock

    with mock.patch.object(SimBackend, "read", read):
        out = run_offline(cfg, paced=True)
    assert jumped and out["stop"] is None
    assert out["loop"]["stalls"]["count"] == 1 and out["loop"]["stalls"]["longest_ms"] >= 490
    assert out["control"]["fallbacks"] == 0 and out["control"]["max_error_m"] < 1e-4


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
@pytest.mark.parametrize("config", ["load-change", "friction"])
def test_nothing_compiles_after_the_first_tick_through_the_rare_paths(tmp_path, config):
    # a fresh process through a stall resume, redesigns, a plant change and the redesign for it, or the
    # friction feedforward; the SIGSTOP comes ~1.5 s in, the plant change (moved from 4 s) at 2.5 s
    from rt_ident.axis.params import CONFIG_DIR

    path = tmp_path / f"{config}.toml"
    if config == "friction":
        path.write_text((CONFIG_DIR / "sim.toml").read_text().replace(
            '[estimator]\nmethod = "frequency"', '[estimator]\nmethod = "frequency"\nmodel = "two-inertia-friction"')
            + '\n[plant.friction]\npreset = "thomson"\n')
    else:
        text = (CONFIG_DIR / "sim-load-change.toml").read_text()
        assert "at = 4.0 " in text
        path.write_text(text.replace("at = 4.0 ", "at = 2.5 "))
    _, s, _, err, _ = _sigstop_run(tmp_path, str(path), duration=4.0)
    assert s["loop"]["stalls"]["count"] >= 1, err[-2000:]
    assert s["loop"]["late_compiles"] == {"count": 0, "functions": []}
    applied = s["control"]["applied"]
    assert any(a["kind"] == "model" for a in applied), applied          # a model design went in
    if config == "friction":
        assert s["friction"]["feedforward"], s["friction"]
    else:                                                               # and one for the changed plant
        assert any(a["t"] > 2.5 and a["kind"] == "model" for a in applied), applied


def _piecewise_run(monkeypatch, piece: int, stall_s: float = 0.1):
    """The stalled offline run on a device that hands a backlog over ``piece`` samples per read (as a tty
    does, 4 KiB at a time): after the stall the loop reads samples tens of ms old for several ticks."""
    from drivers.base import SampleBlock
    from drivers.sim import SimBackend

    real_read = SimBackend.read
    queue: list[SampleBlock] = []
    fields = ("t", "seq", "theta1", "theta2", "torque_cmd", "torque_meas")

    def read(self):
        new = real_read(self)
        if len(new):
            queue.append(new)
        if not queue:
            return new
        cols = {f: np.concatenate([getattr(b, f) for b in queue]) for f in fields}
        head = SampleBlock(**{f: c[:piece] for f, c in cols.items()})
        queue[:] = [SampleBlock(**{f: c[piece:] for f, c in cols.items()})] if cols["t"].size > piece else []
        return head

    monkeypatch.setattr(SimBackend, "read", read)
    return _stalled_run(stall_s)


def test_after_a_stall_the_loop_catches_up_with_the_devices_backlog_before_it_re_plans(monkeypatch):
    out, rows = _piecewise_run(monkeypatch, piece=80)          # 4 ticks' samples per read
    assert out["stop"] is None
    st = out["loop"]["stalls"]
    assert st["count"] == 1 and st["catch_up_longest_ms"] >= 20   # 100 ms of backlog at 3 ticks' gain per tick
    assert out["control"]["fallbacks"] == 0 and out["control"]["max_error_m"] < 1e-4


def test_re_planning_from_the_first_piece_of_a_backlog_lunges(monkeypatch):
    from rt_ident.loop import loop as loop_mod

    monkeypatch.setattr(loop_mod, "CATCH_UP_TICKS", 10**9)     # resume on the first block after the stall
    out, _ = _piecewise_run(monkeypatch, piece=80)
    assert out["stop"] is not None or out["control"]["max_error_m"] > 4e-4     # the catching-up run: < 1e-4


def test_a_device_that_samples_only_when_read_resumes_at_once_after_a_stall():
    # the free-running sim has no backlog: its sample clock falls behind the host's for good, which
    # must not read as a catch-up that never ends (a loop-stall stop after max_stall_stop_s)
    cfg = load(None, **{**FAST, "loop.duration": 2.5}).model_copy(update={"reference": MOVES})

    def hook(loop):
        if loop.stats.ticks == 700:
            loop.clock.now += 0.05

    out = run_offline(cfg, tick_hook=hook, paced=False)
    assert out["stop"] is None, out["stop"]
    assert out["loop"]["stalls"]["count"] == 1 and out["loop"]["stalls"]["catch_up_longest_ms"] == 0.0
    assert any(e["kind"] == "stall" for e in out["control"]["events"])     # re-planned on the next tick


def test_an_overrun_after_a_tick_that_worked_through_a_stalls_backlog_is_put_down_to_the_stall():
    from types import SimpleNamespace

    from rt_ident.loop.loop import LoopStats, _count_tick

    st, late = LoopStats(), SimpleNamespace(skipped=1, lateness_s=0.002)
    _count_tick(st, late, 0.0015, 0.001, backlog=True)        # the resume's tick took 1.5 ms: the stall's
    _count_tick(st, late, 0.0015, 0.001)                      # an ordinary tick's 1.5 ms: our work
    _count_tick(st, late, 0.0002, 0.001, backlog=True)        # 0.2 ms and still late: a late start
    assert (st.overruns, st.overruns_backlog, st.overruns_work, st.overruns_late_start) == (3, 1, 1, 1)


def test_the_summary_counts_lost_samples_and_the_longest_gap_one_read_found(monkeypatch):
    from drivers.base import SampleBlock
    from drivers.sim import SimBackend

    real_read, reads, cut = SimBackend.read, [0], {100: 3, 300: 7, 500: 2}     # read number: samples lost

    def read(self):
        b = real_read(self)
        reads[0] += 1
        n = cut.get(reads[0], 0)
        if not n or len(b) <= n:
            return b
        f = ("t", "seq", "theta1", "theta2", "torque_cmd", "torque_meas")
        return SampleBlock(**{k: getattr(b, k)[n:] for k in f}, lost=b.lost + n)

    monkeypatch.setattr(SimBackend, "read", read)
    out = run_offline(load(None, **{**FAST, "loop.duration": 0.8}), paced=False)
    assert out["stop"] is None, out["stop"]
    assert out["loop"]["lost_samples"] == 12 and out["loop"]["lost_longest"] == 7, out["loop"]


def test_a_host_stopped_inside_a_read_that_then_raises_counts_the_stall_and_the_stop_names_it(monkeypatch):
    # a SIGSTOP inside the tick's read: the drive faulted meanwhile (its RPDO deadline), and the read that
    # resumes finds the fault; the stop must say it followed the host's 500 ms silence
    from drivers.errors import DeviceFault
    from drivers.sim import SimBackend

    real_read, reads = SimBackend.read, [0]

    def read(self):
        reads[0] += 1
        if reads[0] == 300:
            self._clock.now += 0.5
            raise DeviceFault("node 5 sent EMCY 0x8250 (RPDO timeout)")
        return real_read(self)

    monkeypatch.setattr(SimBackend, "read", read)
    out = run_offline(load(None, **{**FAST, "loop.duration": 1.0}), paced=True)
    assert out["stop"].startswith("DeviceFault: node 5 sent EMCY 0x8250"), out["stop"]
    assert out["loop"]["stalls"]["count"] == 1 and out["loop"]["stalls"]["longest_ms"] >= 490, out["loop"]["stalls"]
    assert re.search(r"after a 50\d ms loop stall", out["stop"]), out["stop"]


def test_the_summarys_stall_times_are_seconds_into_the_run():
    from rt_ident.compose.run import run

    def hook(tick: int) -> None:
        if tick == 300:
            time.sleep(0.3)                     # the host away for longer than safety.max_stall_s

    s = run(load(None, **{**FAST, "loop.duration": 1.0}), tick_hook=hook)
    events = s["loop"]["stalls"]["events"]          # a busy host may add stalls of its own
    assert any(e["ms"] >= 250 for e in events), events
    assert all(0.0 <= e["t"] <= 5.0 for e in events), events          # not the host's monotonic clock


def test_a_host_side_trip_names_what_was_failing_on_the_link_meanwhile(monkeypatch):
    # a drive whose bus went holds its last torque up to its own deadline: the trip that follows is the
    # first thing the host sees, and its message says the link was failing too
    from drivers.sim import SimBackend
    from rt_ident.compose.run import run

    monkeypatch.setattr(SimBackend, "link_trouble", lambda self: "; meanwhile the link was failing")
    s = run(load(None, **{**FAST, "loop.duration": 1.0, "safety.max_speed_m_s": 1e-4}))
    assert s["stop"]["cause"] == "speed-limit"
    assert s["stop"]["message"].endswith("; meanwhile the link was failing")


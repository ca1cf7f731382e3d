"""Cia402Backend against the emulated CiA 402 drive on python-can's virtual bus.

Each test gets its own virtual channel. The SYNC rate is 1 kHz. The drive runs in this process's
threads here, so a busy host starves it of CPU and its answers go missing for tens of SYNCs at a time:
``stale_limit`` is 1000 SYNCs (1 s) where the watchdog is not what a test is about, and 40 in the
fault tests, whose injected faults exceed it by far.
"""

from __future__ import annotations

import collections
import errno
import logging
import math
import os
import pickle
import re
import struct
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from drivers import make_backend
from drivers.base import describe_unit, unit_of
from drivers.cia402.config import bus_budget, validate
from drivers.cia402.drive import Cia402Backend
from drivers.cia402.emulator import start_emulator_for
from drivers.cia402.profile import OPERATION_ENABLED, SWITCH_ON_DISABLED, decode_state, frame_bits
from drivers.cia402.stream import CANCEL, ECHO, MARK, SampleAssembler, SyncSender, TorquePlan
from drivers.errors import (
    DeviceConnectionError,
    DeviceFault,
    DriveNotReady,
    HeartbeatLost,
    ProtocolError,
    WatchdogTrip,
)
from rt_ident.axis.params import CONFIG_DIR
from rt_ident.axis.plant import DEFAULT_KP
from rt_ident.errors import ConfigError

EDS = CONFIG_DIR / "cia402_generic.eds"
RATED = 0.64


def backend_cfg(channel: str, **over) -> dict:
    cfg = dict(interface="virtual", channel=channel, bitrate=1_000_000, node_id=5, eds="cia402_generic.eds",
               sync_rate_hz=1000, torque_limit=1.0, rated_torque=RATED, counts_per_rev=131072,
               scale_resolution=1e-7, heartbeat_ms=50, heartbeat_consumer_ms=1000, sdo_timeout=1.0,
               stale_limit=1000, startup_timeout=3.0,
               rpdo_deadline_ms=1000)    # the test's threads are not real-time: held up 200-350 ms on a busy host;
    # the emulated drive is an ordinary process too: its SDO answers come late beside busy workers (sdo_timeout)
    cfg.update(over)
    return cfg


@contextmanager
def rig(faults: dict | None = None, emulator: dict | None = None, **over):
    """An emulated drive on a fresh virtual channel and a (not yet opened) backend for it."""
    cfg = {"backend": backend_cfg(f"t-{uuid.uuid4().hex[:10]}", **over),
           "emulator": {"position_hold": True, "faults": faults or {}, **(emulator or {})}}
    drive = start_emulator_for(cfg)
    try:
        yield drive, Cia402Backend(cfg["backend"])
    finally:
        drive.stop()


def pump(be: Cia402Backend, seconds: float, torque=lambda seq: np.zeros_like(seq, dtype=float),
         ahead: int = 8, samples: int = 0) -> list:
    """Read every ~1 ms for ``seconds`` (and on, up to 10 s, until ``samples`` samples came: a drive a busy
    host starves answers few SYNCs) and write a plan for the next ``ahead`` samples; returns the blocks."""
    blocks, nxt, got = [], 0, 0
    start = time.monotonic()
    end = start + seconds
    while time.monotonic() < end or (got < samples and time.monotonic() < start + 10.0):
        time.sleep(0.001)
        blk = be.read()
        if len(blk):
            blocks.append(blk)
            got += len(blk)
            nxt = int(blk.seq[-1]) + 1
        seq = np.arange(nxt, nxt + ahead)
        be.write(torque(seq), start_seq=nxt)
    return blocks


def square(amplitude: float, half_period: int = 10):
    return lambda seq: amplitude * np.where((seq // half_period) % 2 == 0, 1.0, -1.0)


def assert_drive_safe(drive) -> None:
    assert drive.applied_torque == 0.0
    assert not drive.enabled
    assert drive.state in (SWITCH_ON_DISABLED, "FAULT")


# ----- configuration and bus budget ------------------------------------------------------
def test_frame_bits_match_worst_case_stuffing_formula():
    # Davis et al. (2007) Eq. (1), 11-bit ids: 47 + 8 s + floor((34 + 8 s - 1) / 4)
    assert [frame_bits(s) for s in (0, 1, 4, 8)] == [55, 65, 95, 135]
    assert frame_bits(8, extended=True) == 160
    # SYNC + RPDO(4) + TPDO(8) + TPDO(4) = 380 bits: ~38 % at 1 kHz on 1 Mbit/s (design note: 35-40 %)
    b = bus_budget(1000, 1_000_000, heartbeat_ms=100)
    assert b.bits_per_sync == 380 and 0.37 < b.load < 0.40


@pytest.mark.parametrize("rate, bitrate", [(10_000, 1_000_000), (2_000, 125_000)])
def test_bus_budget_refuses_rates_the_bitrate_cannot_carry(rate, bitrate):
    with pytest.raises(ConfigError) as err:
        validate(backend_cfg("x", sync_rate_hz=rate, bitrate=bitrate))
    assert err.value.field == "backend.sync_rate_hz"
    load = bus_budget(rate, bitrate, 50).load
    assert f"{100 * load:.1f} %" in str(err.value) and "bit stuffing" in str(err.value)


def test_bus_budget_accepts_2khz_at_1mbit_and_names_the_max_rate():
    cfg = validate(backend_cfg("x", sync_rate_hz=2000))
    assert cfg.sample_period == pytest.approx(5e-4)
    with pytest.raises(ConfigError, match=r"at most 2098 Hz"):   # (0.8 Mbit/s - 2 x 65 bit / 50 ms) / 380 bit
        validate(backend_cfg("x", sync_rate_hz=2200))


def test_config_errors_name_the_field():
    cfg = backend_cfg("x")
    del cfg["node_id"]
    with pytest.raises(ConfigError) as err:
        Cia402Backend(cfg)
    assert err.value.field == "backend.node_id"
    with pytest.raises(ConfigError) as err:
        Cia402Backend(backend_cfg("x", sync_rat_hz=1000))
    assert err.value.field == "backend.sync_rat_hz"
    with pytest.raises(ConfigError) as err:
        Cia402Backend(backend_cfg("x", node_id=200))
    assert err.value.field == "backend.node_id"
    with pytest.raises(ConfigError, match="eds"):
        Cia402Backend(backend_cfg("x", eds="no-such.eds")).open()


def test_registry_builds_the_canopen_backend_without_io():
    be = make_backend("canopen", backend_cfg("never-opened"))
    assert isinstance(be, Cia402Backend) and be.sample_period == pytest.approx(1e-3)


def test_torque_plan_follows_the_base_class_semantics():
    plan = TorquePlan()
    plan.hold(0.5)
    assert plan.take(0) == 0.5
    plan.plan(np.array([1.0, 2.0, 3.0]), start=3)
    assert [plan.take(k) for k in (1, 2, 3, 4, 5, 6)] == [0.5, 0.5, 1.0, 2.0, 3.0, 3.0]
    plan.plan(np.array([7.0, 8.0, 9.0]), start=6)    # values for SYNC 6 come too late
    assert plan.late == 1
    assert [plan.take(k) for k in (7, 8, 9)] == [8.0, 9.0, 9.0]
    plan.plan(np.array([1.0, 1.0, 1.0, 1.0]), start=12)
    plan.plan(np.array([5.0]), start=14)             # a newer plan replaces the rest of the older
    assert [plan.take(k) for k in (12, 13, 14, 15)] == [1.0, 1.0, 5.0, 5.0]


def test_late_plan_values_count_as_late_torques_only_where_they_differ_from_the_torque_sent():
    plan = TorquePlan()
    plan.plan(np.array([1.0, 2.0, 3.0, 4.0]), start=0)
    assert [plan.take(k) for k in (0, 1)] == [1.0, 2.0]
    plan.plan(np.array([2.0 + 1e-15, 3.0, 5.0]), start=1)   # SYNC 1 sent: the same torque (a last-bit sum)
    assert (plan.late, plan.late_changed) == (1, 0)
    assert plan.take(2) == 3.0
    plan.plan(np.array([3.5, 6.0, 7.0]), start=2)           # SYNC 2 sent with 3.0: this torque lands late
    assert (plan.late, plan.late_changed) == (2, 1)
    assert [plan.take(k) for k in (3, 4)] == [6.0, 7.0]


def test_a_drive_is_read_where_its_answers_to_a_sync_are_in():
    from drivers.cia402.config import ANSWER_ALLOWANCE_S, answer_time

    cfg = validate(backend_cfg("phase"))
    # CAN 2.0A worst case: SYNC 55 bits, TPDO1 (8 bytes) 135, TPDO2 (4 bytes) 95; at 1 Mbit/s
    assert answer_time(cfg) == pytest.approx(285e-6 + ANSWER_ALLOWANCE_S)
    assert answer_time(cfg, drives=2) == pytest.approx(515e-6 + ANSWER_ALLOWANCE_S)
    assert answer_time(validate(backend_cfg("phase", answer_us=420.0)), drives=2) == pytest.approx(420e-6)
    with pytest.raises(ConfigError, match=r"^backend: answer_us 1000 is not shorter than the SYNC .*sync_rate_hz"):
        validate(backend_cfg("phase", answer_us=1000.0))       # 1 kHz SYNC: the next SYNC comes first

    be = Cia402Backend(backend_cfg("phase"))
    assert be.read_phase() is None                          # no SYNC sent: the loop's ticks start now

    class Sender:
        running, channels = True, 2
        next_at = time.monotonic() + 0.3e-3

    be._sender = Sender()
    answers = answer_time(cfg, drives=2)
    before = time.monotonic()
    phase = be.read_phase()
    after = time.monotonic()
    # the next SYNC's time, seen from the moment of the call, plus both drives' answers
    assert Sender.next_at - after + answers <= phase <= Sender.next_at - before + answers


def test_the_loops_ticks_fall_at_the_read_phase_modulo_the_sample_period():
    from rt_ident.loop.loop import read_anchor
    from rt_ident.loop.scheduler import Ticker

    class Device:
        sample_period = 0.5e-3

        def __init__(self, phase):
            self.phase = phase

        def read_phase(self):
            return self.phase

    now = 100.0
    assert read_anchor(lambda: now, [Device(None)]) is None
    for phase in (0.2e-3, 0.7e-3, 3.45e-3):
        t0 = read_anchor(lambda: now, [Device(None), Device(phase)])
        ticker = Ticker(1e-3, clock=lambda: now)
        ticker.start(t0)
        first = ticker.next_deadline()
        assert now <= first < now + 1e-3                    # the first tick within a period
        for k in (1, 2, 50):                                # every tick phase after a SYNC's answers
            offset = (ticker.deadline(k) - (now + phase)) / 0.5e-3
            assert offset == pytest.approx(round(offset), abs=1e-6)


def test_a_leased_plan_ends_in_zero_taken_under_one_lock_with_the_plan():
    plan = TorquePlan()
    taken = []

    class Lock:                       # counts the sender's view: how often the plan was changed under it
        def __enter__(self):
            taken.append(1)

        def __exit__(self, *exc):
            return False

    plan._lock = Lock()
    plan.plan(np.array([1.0, 2.0]), start=0, lease=3)
    assert len(taken) == 1             # the sender can never take the plan without its end
    assert [plan.take(k) for k in range(7)] == [1.0, 2.0, 2.0, 2.0, 2.0, 0.0, 0.0]


# ----- window assembly with echoed SYNCs (udp_multicast) ---------------------------------------
TPDO1, TPDO2 = struct.Struct("<Hih"), struct.Struct("<i")
SW_ENABLED = 0x0237


def _answer(dq: collections.deque, pos: int) -> None:
    dq.append((0x185, 0.0, TPDO1.pack(SW_ENABLED, pos, 0)))
    dq.append((0x285, 0.0, TPDO2.pack(pos)))


def _echo_assembler() -> tuple[SampleAssembler, collections.deque]:
    """An assembler in echo mode after one complete window (SYNC -1, before the first delivered sample)."""
    asm = SampleAssembler([(0x185, TPDO1), (0x285, TPDO2)], stale_limit=10, stuck_permille=0.0, echo=True)
    dq: collections.deque = collections.deque([(MARK, -1, -1.0, 0.0), (ECHO, 0.0)])
    _answer(dq, 99)
    return asm, dq


def test_sync_sender_runs_fifo_above_a_loop_thread_that_resets_its_policy_on_fork():
    """The loop thread runs SCHED_FIFO | SCHED_RESET_ON_FORK (a helper it restarts must not be real-time).
    Threads it starts are then SCHED_OTHER; the SYNC sender must still end up one FIFO step above it,
    or on the loop's CPU it runs only while the loop sleeps (about half the samples are lost)."""
    import os
    import threading

    flag = getattr(os, "SCHED_RESET_ON_FORK", None)
    if flag is None:
        pytest.skip("no SCHED_RESET_ON_FORK on this platform")
    got: dict = {}

    def loop_thread() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | flag, os.sched_param(50))
        except PermissionError:
            got["skip"] = True
            return
        sender = SyncSender(lambda cob, data: None, 0.01, collections.deque(maxlen=100), TorquePlan(),
                            lambda t: (0, 0.0), rpdo_cob=0x205)
        sender.start()
        try:
            time.sleep(0.05)
            tid = sender._thread.native_id
            got["policy"] = os.sched_getscheduler(tid) & ~flag
            got["prio"] = os.sched_getparam(tid).sched_priority
        finally:
            sender.stop()

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join(5.0)
    if got.get("skip"):
        pytest.skip("SCHED_FIFO not permitted here")
    assert got == {"policy": os.SCHED_FIFO, "prio": 51}


def test_echoed_sync_not_sender_marker_opens_the_window():
    asm, dq = _echo_assembler()
    for k in range(3):                              # the sender runs ahead of the bus: three markers queued
        dq.append((MARK, k, float(k), 0.1 * k))
    for k in range(3):                              # bus order: SYNC k, then its answer
        dq.append((ECHO, 0.0))
        _answer(dq, 100 + k)
    dq.append((ECHO, 0.0))                          # SYNC 3 on the bus closes window 2 (no marker for it: ignored)
    asm.feed(dq, deliver=True)
    rows = asm.take_rows()
    assert rows["k"] == [0, 1, 2] and rows["pos"] == [100, 101, 102]
    assert rows["cmd"] == pytest.approx([0.0, 0.1, 0.2]) and asm.stale == 0 and asm.echoes == 4   # with SYNC -1


def test_lone_answer_after_a_missing_one_is_dropped_as_ambiguous():
    asm, dq = _echo_assembler()
    for k in range(6):
        dq.append((MARK, k, float(k), 0.0))
    answers = {0: [100], 1: [], 2: [102], 3: [], 4: [103, 104], 5: [105]}   # 2: maybe SYNC 1's late answer
    for k in range(6):
        dq.append((ECHO, 0.0))
        for pos in answers[k]:
            _answer(dq, pos)
    dq.append((MARK, 6, 6.0, 0.0))
    dq.append((ECHO, 0.0))
    asm.feed(dq, deliver=True)
    rows = asm.take_rows()
    # two answers in window 4: the drive caught up, the newest is SYNC 4's
    assert rows["k"] == [0, 4, 5] and rows["pos"] == [100, 104, 105]
    assert asm.stale == 3 and asm.ambiguous == 1 and asm.late == 2


# ----- window assembly by frame times on the bus (CAN, the loopback-confined bus: no echo) ---------------
def _timed_answer(dq: collections.deque, pos: int, t: float) -> None:
    dq.append((0x185, t, TPDO1.pack(SW_ENABLED, pos, 0)))
    dq.append((0x285, t, TPDO2.pack(pos)))


def test_timed_windows_put_a_frame_read_after_the_next_marker_where_its_bus_time_says():
    """A late reader (an 11 ms stall) hands over answers after the sender's later markers: their
    times on the bus, not the deque order, say which SYNC they answer."""
    asm = SampleAssembler([(0x185, TPDO1), (0x285, TPDO2)], stale_limit=10, stuck_permille=0.0, timed=True)
    dq: collections.deque = collections.deque()
    for k in range(4):                              # the sender ran on; nothing read yet
        dq.append((MARK, k, float(k), 0.1 * k))
    for k in range(4):                              # then every answer at once, each 0.3 periods after its SYNC
        _timed_answer(dq, 100 + k, k + 0.3)
    asm.feed(dq, deliver=True, read_until=3.5)
    rows = asm.take_rows()
    assert rows["k"] == [0, 1, 2, 3] and rows["pos"] == [100, 101, 102, 103]
    assert rows["cmd"] == pytest.approx([0.0, 0.1, 0.2, 0.3]) and asm.stale == asm.late == 0


def test_timed_window_stays_open_until_everything_before_the_next_sync_is_read():
    asm = SampleAssembler([(0x185, TPDO1), (0x285, TPDO2)], stale_limit=10, stuck_permille=0.0, timed=True)
    dq: collections.deque = collections.deque([(MARK, 0, 0.0, 0.0), (MARK, 1, 1.0, 0.0)])
    dq.append((0x185, 0.2, TPDO1.pack(SW_ENABLED, 100, 0)))   # TPDO2 of SYNC 0 not read yet
    asm.feed(dq, deliver=True, read_until=0.9)                  # the bus is read only up to before SYNC 1
    assert asm.take_rows()["k"] == [] and asm.stale == 0
    dq.append((0x285, 0.25, TPDO2.pack(100)))                   # read now, stamped in SYNC 0's window
    _timed_answer(dq, 101, 1.2)
    dq.append((MARK, 2, 2.0, 0.0))
    asm.feed(dq, deliver=True, read_until=2.1)
    assert asm.take_rows()["pos"] == [100, 101] and asm.stale == 0


def test_timed_windows_count_a_frame_of_a_closed_window_as_late_and_a_lone_late_answer_as_ambiguous():
    asm = SampleAssembler([(0x185, TPDO1), (0x285, TPDO2)], stale_limit=10, stuck_permille=0.0, timed=True)
    dq: collections.deque = collections.deque()
    for k in range(4):
        dq.append((MARK, k, float(k), 0.0))
    _timed_answer(dq, 100, 0.3)
    _timed_answer(dq, 101, 2.05)                    # SYNC 1's answer after SYNC 2 went out: maybe 2's
    _timed_answer(dq, 103, 3.3)
    asm.feed(dq, deliver=True, read_until=3.5)
    _timed_answer(dq, 99, 0.5)                      # stamped in window 0, long closed
    dq.append((MARK, 4, 4.0, 0.0))
    asm.feed(dq, deliver=True, read_until=4.1)
    rows = asm.take_rows()
    assert rows["k"] == [0, 3] and rows["pos"] == [100, 103]
    assert asm.stale == 2 and asm.ambiguous == 1 and asm.late == 2


def test_a_cancelled_sync_gives_its_window_back_to_the_one_before():
    asm = SampleAssembler([(0x185, TPDO1), (0x285, TPDO2)], stale_limit=10, stuck_permille=0.0, timed=True)
    dq: collections.deque = collections.deque([(MARK, 0, 0.0, 0.0), (MARK, 1, 1.0, 0.0), (CANCEL, 1)])
    _timed_answer(dq, 100, 1.1)                     # SYNC 1 never went out: SYNC 0's (late) answer
    dq.append((MARK, 2, 2.0, 0.0))
    _timed_answer(dq, 102, 2.1)
    dq.append((MARK, 3, 3.0, 0.0))
    asm.feed(dq, deliver=True, read_until=3.1)
    assert asm.take_rows()["k"] == [0, 2] and asm.stale == 0


def _silent_run(host_missed_during: int) -> WatchdogTrip:
    """SYNCs without an answer (stale_limit 10) while the host's sender skipped
    ``host_missed_during`` periods; returns the trip."""
    asm, dq = _echo_assembler()
    missed = [3]                                     # skipped before the run: not counted against it
    asm.host_missed = lambda: missed[0]
    for k in range(3):                               # the silent run starts
        dq.extend([(MARK, k, float(k), 0.0), (ECHO, 0.0)])
    asm.feed(dq, deliver=True)
    missed[0] += host_missed_during
    with pytest.raises(WatchdogTrip) as e:
        for k in range(3, 20):
            dq.extend([(MARK, k, float(k), 0.0), (ECHO, 0.0)])
            asm.feed(dq, deliver=True)
    return e.value


def test_a_stale_run_trip_says_the_drive_was_silent_when_the_host_kept_time():
    trip = _silent_run(0)
    assert "no fresh TPDO data" in str(trip) and "the drive sent no fresh data" in str(trip)
    assert trip.fix is None                          # no setting of the host's fixes a silent drive


def test_a_stale_run_trip_names_the_host_and_its_setting_when_its_sync_sender_skipped_periods():
    trip = _silent_run(5)
    msg = str(trip)
    assert "no fresh TPDO data" in msg and "a busy host, not a silent drive" in msg and "5 SYNC periods" in msg
    assert trip.fix is not None and trip.fix.startswith("loop.realtime")


def test_cancelled_sync_has_no_window():
    asm, dq = _echo_assembler()
    dq.extend([(MARK, 0, 0.0, 0.0), (ECHO, 0.0)])
    _answer(dq, 100)
    dq.extend([(MARK, 1, 1.0, 0.0), (CANCEL, 1), (MARK, 2, 2.0, 0.0), (ECHO, 0.0)])
    _answer(dq, 102)
    dq.extend([(MARK, 3, 3.0, 0.0), (ECHO, 0.0)])
    asm.feed(dq, deliver=True)
    assert asm.take_rows()["k"] == [0, 2] and asm.stale == 0


def test_stale_preoperational_heartbeats_after_nmt_start_do_not_trip():
    """Heartbeats sent before the drive saw NMT start, read after it (python-can's cyclic
    sender bursts after a stall, e.g. while the loop's process is locked in memory), are not a fault."""
    be = Cia402Backend(backend_cfg("never-opened"))
    be._hb_time = time.monotonic()
    for _ in range(3):                              # queued PRE-OPERATIONAL heartbeats
        be._on_heartbeat(0x705, bytearray([0x7F]), 0.0)
    be._check_emcy_heartbeat()                      # no fault
    be._on_heartbeat(0x705, bytearray([0x05]), 0.0)
    be._on_heartbeat(0x705, bytearray([0x7F]), 0.0)  # after OPERATIONAL: the drive really left it
    with pytest.raises(DeviceFault, match="left NMT OPERATIONAL: its heartbeat reports PRE-OPERATIONAL .*0x1029"):
        be._check_emcy_heartbeat()


def test_a_drive_that_restarted_mid_run_is_named_as_restarted_by_its_boot_up_message():
    be = Cia402Backend(backend_cfg("never-opened"))
    be._hb_time = time.monotonic()
    be._on_heartbeat(0x705, bytearray([0x05]), 0.0)
    be._on_heartbeat(0x705, bytearray([0x00]), 0.0)  # boot-up, then the state a restarted drive comes up in
    be._on_heartbeat(0x705, bytearray([0x7F]), 0.0)
    with pytest.raises(DeviceFault, match="left NMT OPERATIONAL: it sent a boot-up message, so it restarted"):
        be._check_emcy_heartbeat()


# ----- start-up and streaming ------------------------------------------------------------
def test_startup_reaches_operation_enabled_with_cst_mode_verified():
    with rig() as (drive, be):
        with be:
            assert drive.state == SWITCH_ON_DISABLED and drive.nmt_state == "PRE-OPERATIONAL"
            assert drive._values[(0x6061, 0)] == 10          # mode 10 written and displayed
            be.activate()
            assert drive.state == OPERATION_ENABLED and drive.nmt_state == "OPERATIONAL"
            assert decode_state(be.statusword) == OPERATION_ENABLED
            assert {lay.cob for lay in drive._tpdos} == {0x185, 0x285}
            assert drive._values[(0x6072, 0)] == round(1.0 / RATED * 1000)   # drive-side torque limit
        assert_drive_safe(drive)
        assert drive.state == SWITCH_ON_DISABLED and drive.nmt_state == "PRE-OPERATIONAL"


def test_a_second_master_for_the_same_node_is_refused_before_it_touches_the_bus_and_may_open_once_it_ends():
    with rig() as (drive, be):
        second = Cia402Backend(be.config.model_dump())
        with be:
            be.activate()
            with pytest.raises(DeviceConnectionError, match=rf"node 5 on virtual .* in use: pid {os.getpid()} "):
                second.open()
            assert second.state.value == "created" and drive.state == OPERATION_ENABLED
        with second:                                       # the first master gone: the node is free
            second.activate()
            assert drive.state == OPERATION_ENABLED
        assert_drive_safe(drive)


def test_the_drives_identity_names_its_unit_from_0x1018():
    with rig(emulator={"serial_number": 42}) as (_drive, be), be:
        ident = be.identity()
        assert (ident["vendor_id"], ident["product_code"], ident["serial_number"]) == (0, 0x402, 42)
        assert unit_of(ident) == {"vendor_id": 0, "product_code": 0x402, "serial_number": 42}
        assert describe_unit(unit_of(ident)) == "serial 42 (vendor id 0x0, product code 0x402)"


def test_samples_carry_plausible_angles_and_torque():
    hold = 0.1
    with rig() as (drive, be):
        with be:
            be.activate()
            blocks = pump(be, 0.6, lambda seq: np.full(seq.shape, hold), samples=250)
            assert drive.applied_torque != 0.0
        assert_drive_safe(drive)
    seq = np.concatenate([b.seq for b in blocks])
    t = np.concatenate([b.t for b in blocks])
    th1 = np.concatenate([b.theta1 for b in blocks])
    th2 = np.concatenate([b.theta2 for b in blocks])
    cmd = np.concatenate([b.torque_cmd for b in blocks])
    meas = np.concatenate([b.torque_meas for b in blocks])
    assert len(seq) > 200 and seq[0] >= 0 and np.all(np.diff(seq) > 0) and np.all(np.diff(t) > 0)
    assert sum(b.lost for b in blocks) == seq[-1] + 1 - len(seq)        # seq counts SYNCs from 0
    # the command leaves the host quantized to 1 per mille of the rated torque
    q = round(hold * 1000 / RATED) * RATED / 1000
    assert np.mean(cmd[10:] == q) > 0.95
    # the drive's hold loop (kp) balances the command: theta1 -> T / kp; the shaft twist T/K is tiny
    assert th1[-1] == pytest.approx(q / DEFAULT_KP, rel=0.1)
    assert abs(th1[-1] - th2[-1]) < 2e-3
    assert np.all(np.abs(meas) <= 1.0 + 1e-9) and abs(meas[-1]) < 0.02    # torque actual ~ 0 at rest
    # no jumps: at most 0.05 rad per SYNC period, and that many times across a gap of lost samples (under a
    # CPU hog two neighbouring samples can lie further apart than one period allows: the drive settles between)
    assert np.all(np.abs(np.diff(th1)) < 0.05 * np.diff(seq))


def test_torque_plan_values_reach_their_samples():
    with rig() as (drive, be):
        with be:
            be.activate()
            # planned 100 samples ahead: a test thread a busy host holds up for tens of ms still plans in time
            blocks = pump(be, 0.4, square(0.2, half_period=7), ahead=100)
    seq = np.concatenate([b.seq for b in blocks])
    cmd = np.concatenate([b.torque_cmd for b in blocks])
    want = np.round(square(0.2, 7)(seq) * 1000 / RATED) * RATED / 1000
    assert np.mean(cmd == want) > 0.9      # the rest: the first samples, before the first plan


# ----- faults ------------------------------------------------------------------------------
def test_emcy_raises_device_fault_with_the_code_and_drive_ends_disabled():
    with rig(faults={"emcy_at_sample": 80, "emcy_code": 0x2310}) as (drive, be):
        with pytest.raises(DeviceFault, match=r"0x2310.*over-current"):
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert drive.emcy_codes == [0x2310] and drive.state == "FAULT"
        assert_drive_safe(drive)
        assert be.stop_cause == "device-fault"


@pytest.mark.parametrize(("fault", "state", "what", "fix"), [
    ("main_power_off", "READY TO SWITCH ON", "bit 4", "main power on"),
    ("local_control", "SWITCH ON DISABLED", "bit 9", "hand its control to the bus"),
])
def test_a_drive_that_cannot_enable_says_why_and_what_to_do_on_the_drive_not_to_wait_longer(fault, state, what, fix):
    # a longer startup_timeout cures neither: the error names the statusword bit and the fix on the drive
    with rig(faults={fault: True}, startup_timeout=0.5) as (drive, be):
        with pytest.raises(DriveNotReady, match=rf"does not enable: state {state} .*{what}") as err:
            with be:
                be.activate()
        assert fix in err.value.fix and err.value.cause == "not-ready"
        assert pickle.loads(pickle.dumps(err.value)).fix == err.value.fix      # crosses a process intact
        assert_drive_safe(drive)                   # the host's stop still disables it


# python-can's thread-based cyclic task (the host's heartbeat before the SYNC runs) ends on the dead bus's
# error by raising in its thread, as it does on any interface without a kernel cyclic sender
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
@pytest.mark.parametrize("when", ["open", "enable"])
def test_a_python_can_send_error_ends_in_one_line_naming_the_step_and_the_drive_ends_safe(monkeypatch, when):
    # a SocketCAN interface that is down raises CanOperationError (ENETDOWN) from the first send: before,
    # it left the backend as an uncaught python-can error ("internal error", exit 1)
    import can

    import drivers.cia402.node as node_mod

    failing, opened = {"on": when == "open"}, node_mod.open_bus

    def open_bus(kwargs):
        bus = opened(kwargs)
        real = bus.send

        def send(msg, timeout=None):
            if failing["on"]:
                raise can.CanOperationError("Failed to transmit: Network is down", errno.ENETDOWN)
            return real(msg, timeout)

        bus.send = send
        return bus

    monkeypatch.setattr(node_mod, "open_bus", open_bus)
    enable = Cia402Backend._enable

    def enable_on_a_dead_bus(self, sender):
        failing["on"] = True
        return enable(self, sender)

    monkeypatch.setattr(Cia402Backend, "_enable", enable_on_a_dead_bus)
    said = {"open": r"^opening the drive on CAN interface virtual:\S+ failed: ",   # the SDO set-up's own sends
            "enable": r"^CAN send failing on virtual:\S+: "}[when]              # the SYNC sender's, counted
    with rig(startup_timeout=0.5) as (drive, be):
        with pytest.raises(DeviceConnectionError, match=said + r"CanOperationError: .*Network is down"):
            with be:
                be.activate()
        assert not drive.enabled and drive.applied_torque == 0.0


def test_a_canopen_backend_reports_sync_cycles_failing_in_a_row_and_nothing_once_they_send():
    from types import SimpleNamespace

    be = Cia402Backend(backend_cfg("x"))
    assert be.link_trouble() == ""                                      # never activated
    be._sender = SimpleNamespace(consecutive_errors=4, last_error="CanOperationError: Failed to transmit")
    assert be.link_trouble().startswith("; meanwhile the last 4 SYNC cycles failed to send on virtual:x ")
    be._sender = SimpleNamespace(consecutive_errors=0, last_error="CanOperationError: Failed to transmit")
    assert be.link_trouble() == ""
    be._sender = SimpleNamespace(consecutive_errors=4, last_error="CanOperationError: Failed to transmit")
    be.close()                              # released: as the close found it (the run asks after its exit)
    be._sender = None
    assert be.link_trouble().startswith("; meanwhile the last 4 SYNC cycles failed")


def test_a_socketcan_send_errno_is_explained_with_what_to_check_on_the_bench():
    from drivers.cia402.bus import bus_error_hint

    assert "sudo ip link set can0 up type can bitrate 500000" in bus_error_hint(errno.ENETDOWN, "socketcan", "can0",
                                                                                 500000)
    full = bus_error_hint(errno.ENOBUFS, "socketcan", "can0", 1000000)
    assert "no node acknowledges" in full and "bitrate other than 1000000" in full and "bus-off" in full
    assert bus_error_hint(errno.ENOBUFS, "udp_multicast", "239.0.0.1", 1000000) == ""      # not a CAN controller
    assert bus_error_hint(errno.EIO, "socketcan", "can0", 1000000) == ""


def test_the_emulated_faults_main_power_off_and_local_control_are_true_or_false():
    from drivers.cia402.faults import FaultConfig

    for key in ("main_power_off", "local_control", "emcy_off"):
        with pytest.raises(ConfigError, match=rf"emulator.faults.{key}: must be true or false"):
            FaultConfig.from_mapping({key: 1})


@pytest.mark.parametrize("emcy_off", [False, True])
def test_a_fault_without_an_emcy_is_named_by_the_error_code_read_after_the_stop(emcy_off):
    with rig(faults={"emcy_at_sample": 80, "emcy_code": 0x2310, "emcy_off": emcy_off}) as (drive, be):
        with pytest.raises(DeviceFault) as fault:
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert_drive_safe(drive)
    if emcy_off:                                 # only the statusword said so
        assert "left OPERATION ENABLED: state FAULT" in str(fault.value)
        assert be.fault_detail() == ("; node 5's error code 0x603F, read after the stop: 0x2310 (continuous "
                                     "over-current) (no EMCY reached this host: the drive's 0x1014 may have it off)")
    else:                                        # the EMCY named it already
        assert "0x2310" in str(fault.value) and be.fault_detail() == ""


def test_next_session_resets_a_faulted_drive_and_runs():
    with rig(faults={"emcy_at_sample": 30}) as (drive, be):
        with pytest.raises(DeviceFault):
            with be:
                be.activate()
                pump(be, 2.0)
        assert drive.state == "FAULT"
        be2 = Cia402Backend(backend_cfg(drive.bus_kwargs["channel"]))
        with be2:
            be2.activate()                         # fault reset (bit 7 edge), then the normal walk
            assert drive.enabled and drive.state == OPERATION_ENABLED
            # samples flow again (a drive a busy host starves answers few of the 1 kHz SYNCs)
            assert sum(len(b) for b in pump(be2, 1.0, samples=60)) > 50
        assert_drive_safe(drive)


def test_drive_heartbeat_loss_raises_device_fault():
    with rig(faults={"heartbeat_stop_at_s": 0.1}, heartbeat_consumer_ms=250) as (drive, be):
        with pytest.raises(DeviceFault, match=r"no heartbeat from node 5 for 0\.\d+ s \(consumer time 250 ms"):
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert_drive_safe(drive)
        assert drive.state == SWITCH_ON_DISABLED


def test_a_drive_that_restarts_mid_run_is_named_and_its_disable_confirmed_by_sdo_without_its_pdos():
    with rig(faults={"restart_at_sample": 100}) as (drive, be):
        with pytest.raises(DeviceFault, match=r"left NMT OPERATIONAL: it sent a boot-up message, so it restarted"):
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert_drive_safe(drive)
        assert be.stop_unconfirmed is None               # its statusword read by SDO: the power stage is off
        assert drive.nmt_state == "PRE-OPERATIONAL"


@pytest.mark.parametrize("derate", [None, 50])
def test_samples_in_which_the_drive_cut_the_torque_or_warned_are_counted_from_its_statusword_bits_11_and_7(derate):
    faults = {} if derate is None else {"derate_at_sample": 100, "derate_permille": derate, "warning_at_sample": 100}
    with rig(faults=faults) as (drive, be):
        with be:
            be.activate()
            blocks = pump(be, 0.3, square(0.1), ahead=100, samples=300)   # 0.1 N m: 156 per mille of rated
            got = sum(len(b) for b in blocks)
            limited, warned = be.counters["internal_limit"], be.counters["warning"]
        assert_drive_safe(drive)
    if derate is None:
        assert limited == 0 and warned == 0      # within 0x6072, no warning: nothing flagged
    else:                                        # every sample from the 100th on
        assert 0 < limited <= got and limited >= got - 150, (limited, got)
        assert 0 < warned <= got and warned >= got - 150, (warned, got)


def test_device_notes_name_a_cut_torque_and_a_warning_with_where_to_look():
    from rt_ident.compose.run import device_notes

    assert device_notes({"internal_limit": 0, "warning": 0}, 1000) == []
    assert device_notes(None, 1000) == []
    drive = device_notes({"internal_limit": 12, "warning": 3}, 1000)
    assert "the drive limited the torque below the command on 12 of 1000 samples" in drive[0]["message"]
    assert "bit 11" in drive[0]["message"] and "backend.torque_limit" in drive[0]["fix"]
    assert "warning on 3 of 1000 samples" in drive[1]["message"]
    board = device_notes({"torque_limited": 5}, 1000, "serial")
    assert len(board) == 1 and board[0]["message"].startswith("the board limited the torque")


def test_device_notes_are_printed_under_their_axis(capsys):
    from rt_ident.compose.run import device_notes
    from rt_ident.outputs.terminal import print_device_notes

    print_device_notes({"device_notes": device_notes({"internal_limit": 12}, 1000)}, "y")
    printed = capsys.readouterr().out
    assert printed.startswith("device y: the drive limited the torque") and "look at:" in printed
    print_device_notes({})
    assert capsys.readouterr().out == ""


def test_master_heartbeat_loss_faults_the_drive_and_names_the_host():
    with rig() as (drive, be):
        with pytest.raises(HeartbeatLost, match=r"0x8130") as lost:
            with be:
                be.activate()
                pump(be, 0.1, square(0.1))
                be._sender.heartbeat = None                # the host's heartbeat dies (sent by the SYNC thread)
                pump(be, 2.0, square(0.1))
        assert 0x8130 in drive.emcy_codes
        assert lost.value.fix.startswith("loop.realtime") and "heartbeat_consumer_ms" in lost.value.fix
        assert_drive_safe(drive)


def test_stuck_encoder_trips_the_watchdog():
    with rig(faults={"stuck_encoder_at_sample": 100}, stale_limit=40) as (drive, be):
        with pytest.raises(WatchdogTrip) as trip:
            with be:
                be.activate()
                pump(be, 2.0, square(0.3, half_period=25))
        assert_drive_safe(drive)
    if "a busy host, not a silent drive" in str(trip.value):      # the backend saw its own SYNCs late: it says so
        pytest.skip(f"the host fell behind before the encoder's stuck run was long enough: {trip.value}")
    assert re.search(r"0x6064 unchanged .* 41 samples with torque", str(trip.value)), trip.value
    assert be.counters["unchanged"] > 40


def test_dropping_every_tpdo_trips_the_watchdog():
    with rig(faults={"drop_tpdo_every": 1, "tpdo_faults_from_sample": 50}, stale_limit=40) as (drive, be):
        with pytest.raises(WatchdogTrip, match=r"no fresh TPDO data for 41 SYNCs in a row"):
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert_drive_safe(drive)


def test_sparse_tpdo_drops_are_counted_as_lost_samples():
    with rig(faults={"drop_tpdo_every": 10}) as (drive, be):
        with be:
            be.activate()
            blocks = pump(be, 0.5, square(0.1))
            stale = be.counters["stale"]
            # a sample after the count: every gap the count saw is then closed, and counted as lost
            end, n_before = time.monotonic() + 5.0, len(blocks)
            while len(blocks) == n_before and time.monotonic() < end:
                time.sleep(0.001)
                blk = be.read()
                if len(blk):
                    blocks.append(blk)
        assert_drive_safe(drive)
    seen = blocks[:n_before]                          # the samples read before the count
    assert stale >= (sum(len(b) for b in seen) + sum(b.lost for b in seen)) // 10 - 2
    assert sum(b.lost for b in blocks) >= stale - 2


def test_delayed_tpdos_trip_the_watchdog():
    with rig(faults={"delay_tpdo_s": 0.2, "tpdo_faults_from_sample": 50}, stale_limit=40) as (drive, be):
        with pytest.raises(WatchdogTrip, match="no fresh TPDO data"):
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        assert_drive_safe(drive)


def test_corrupted_tpdos_raise_protocol_error():
    with rig(faults={"corrupt_tpdo_every": 1, "tpdo_faults_from_sample": 50}, stale_limit=40) as (drive, be):
        with pytest.raises(ProtocolError, match=r"TPDO 0x[12]85 with \d bytes, [48] mapped") as err:
            with be:
                be.activate()
                pump(be, 2.0, square(0.1))
        # the message counts the corrupt frames up to the stop, the counter also those read while stopping (how
        # many of the 41 bad samples were corrupt rather than missed depends on how busy the host kept the drive)
        total = int(re.search(r"(\d+) corrupt frames in total", str(err.value)).group(1))
        assert 0 < total <= be.counters["corrupt"]
        assert_drive_safe(drive)


def test_garbage_frames_are_ignored():
    with rig(faults={"garbage_frames_per_sync": 3}) as (drive, be):
        with be:
            be.activate()
            blocks = pump(be, 0.4, square(0.1), samples=150)
            assert drive.enabled
            assert be.counters["corrupt"] == 0
        assert drive.garbage_frames > 300
        assert_drive_safe(drive)
    assert sum(len(b) for b in blocks) > 100


def test_exception_inside_the_with_block_stops_the_drive():
    with rig() as (drive, be):
        with pytest.raises(RuntimeError, match="boom"):
            with be:
                be.activate()
                pump(be, 0.2, lambda seq: np.full(seq.shape, 0.3))
                assert drive.applied_torque != 0.0
                raise RuntimeError("boom")
        assert_drive_safe(drive)
        assert drive.state == SWITCH_ON_DISABLED and be.stop_cause == "RuntimeError"
        be.close()          # idempotent
        be.safe_stop()


def test_safe_stop_is_bounded_and_silent_when_the_drive_vanished():
    with rig(stop_timeout=0.1) as (drive, be):
        be.open()
        be.activate()
        pump(be, 0.1)
        drive.stop()                                   # the drive drops off the bus
        t0 = time.monotonic()
        be.safe_stop("test")                           # must not raise
        be.close()
        assert time.monotonic() - t0 < 15.0            # two stop steps + one SDO timeout, not forever
        assert be.stop_unconfirmed is not None and "node 5 did not report itself disabled" in be.stop_unconfirmed


def test_a_drive_that_confirms_its_disable_is_left_without_its_watch_of_the_hosts_heartbeat():
    with rig() as (drive, be):
        be.open()
        be.activate()
        pump(be, 0.1)
        assert drive._master[1] == 1000                # the host set the drive's consumer time
        be.safe_stop("test")
        be.close()
        assert be.stop_unconfirmed is None and drive.state == SWITCH_ON_DISABLED
        assert drive._master[1] == 0                   # its heartbeat ends now: the drive stops watching it


def test_a_drive_whose_disable_is_not_confirmed_is_named_and_keeps_watching_the_hosts_heartbeat(monkeypatch):
    with rig(stop_timeout=0.1) as (drive, be):
        be.open()
        be.activate()
        pump(be, 0.1)
        monkeypatch.setattr(be, "_wait_state", lambda accept, timeout: False)   # its statusword answers lost,
        monkeypatch.setattr(be, "_sdo_confirms_disabled", lambda: False)         # by PDO and by SDO
        be.safe_stop("test")
        be.close()
        note = be.stop_unconfirmed
        assert note is not None and note.startswith("node 5 did not report itself disabled within 0.1 s"), note
        assert "RPDO deadline (1000 ms" in note and "heartbeat consumer time (1000 ms" in note, note
        assert drive._master[1] == 1000                # left on: the drive faults when this host falls silent


@pytest.mark.parametrize("acts_after_s", [0.0, 0.03])
def test_a_drive_that_sends_no_pdo_after_the_stop_is_disabled_by_sdo_and_confirmed_once_it_acts(monkeypatch,
                                                                                               acts_after_s):
    import threading

    with rig(stop_timeout=0.5) as (drive, be):
        be.open()
        be.activate()
        pump(be, 0.1)
        monkeypatch.setattr(be, "_wait_state", lambda accept, timeout: False)   # no PDO answer to the stop
        if acts_after_s:                               # a drive that acts on a controlword a cycle after the write
            step = drive._step_state_machine

            def later(cw: int, sample: bool = True) -> None:
                def act() -> None:
                    with drive._lock:
                        step(cw, sample)
                threading.Timer(acts_after_s, act).start()

            monkeypatch.setattr(drive, "_step_state_machine", later)
        be.safe_stop("test")
        assert be.stop_unconfirmed is None             # the statusword read by SDO, after the drive took the write
        be.close()
        assert_drive_safe(drive)
        assert drive._master[1] == 0                   # confirmed: its watch of this host's heartbeat is off


def test_no_node_at_that_id_raises_one_error_naming_the_settings_without_canopens_own_abort_line(caplog):
    with rig(node_id=5) as (drive, _):
        cfg = backend_cfg(drive.bus_kwargs["channel"], node_id=6, sdo_timeout=0.2)
        be = Cia402Backend(cfg)
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING), pytest.raises(
                DeviceConnectionError, match=r"no answer from CANopen node 6 .* within 0\.\d+ s.*backend\.node_id"):
            with be:
                pass
        assert time.monotonic() - t0 < 15.0            # the SDO timeout, not forever
        assert drive.state == SWITCH_ON_DISABLED
    assert not [r for r in caplog.records if r.name == "canopen.sdo.client"], caplog.text


def _edited_eds(tmp_path: Path, name: str, edit) -> str:
    text = edit(EDS.read_text())
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def test_eds_missing_an_object_raises_protocol_error(tmp_path):
    def drop_6077(text: str) -> str:
        start = text.index("[6077]")
        return text[:start] + text[text.index("[", start + 1):]
    eds = _edited_eds(tmp_path, "no6077.eds", drop_6077)
    with rig() as (drive, _):
        be = Cia402Backend(backend_cfg(drive.bus_kwargs["channel"], eds=eds))
        with pytest.raises(ProtocolError, match=r"lacks 0x6077 \(torque actual value\)"):
            be.open()
        assert drive.state == SWITCH_ON_DISABLED


def test_drive_refusing_a_mapping_raises_protocol_error(tmp_path):
    def unmappable_scale(text: str) -> str:
        start = text.index("[60E4sub1]")
        end = text.index("[", start + 1)
        return text[:start] + text[start:end].replace("PDOMapping=1", "PDOMapping=0") + text[end:]
    eds = _edited_eds(tmp_path, "drive.eds", unmappable_scale)
    with rig(emulator={"eds": eds}) as (drive, be):
        with pytest.raises(ProtocolError, match=r"cannot map 0x60E4:01 \(additional position actual value\) into "
                                                r"TPDO2: SDO abort 0x06040041 \(object cannot be mapped"):
            with be:
                pass
        assert_drive_safe(drive)


def test_drive_without_cst_mode_raises_protocol_error(tmp_path):
    eds = _edited_eds(tmp_path, "nocst.eds", lambda t: t.replace("DefaultValue=0x000003AD", "DefaultValue=0x000001AD"))
    with rig(emulator={"eds": eds}) as (drive, be):
        with pytest.raises(ProtocolError, match=r"0x6061 .* reads 0 after writing 0x6060 = 10"):
            with be:
                pass
        assert_drive_safe(drive)


def test_rated_torque_mismatch_is_a_config_error():
    with rig(emulator={"rated_torque": 1.27}) as (drive, be):
        with pytest.raises(ConfigError, match=r"0x6076") as err:
            with be:
                pass
        assert err.value.field == "backend.rated_torque"
        assert math.isclose(drive.rated_torque, 1.27)


def test_frames_the_hosts_receive_buffer_dropped_are_named_before_any_silence_of_the_drive():
    """The drive's heartbeats may be among the dropped frames: a stale heartbeat then says nothing of the drive."""
    import types

    from drivers.errors import DeviceFault, ProtocolError

    cfg = validate({"interface": "virtual", "channel": "rt-ident-dropped", "node_id": 5, "counts_per_rev": 131072,
                    "scale_resolution": 1e-7, "lead": 7.96e-4, "rated_torque": 0.64, "torque_limit": 1.0})
    io = types.SimpleNamespace(dropped=0)
    fake = types.SimpleNamespace(config=cfg, _emcy=None, _hb_time=time.monotonic() - 1.0,
                                 _setup=types.SimpleNamespace(io=io), _hb_not_operational=0, _sender=None)
    with pytest.raises(DeviceFault, match="no heartbeat from node 5"):
        Cia402Backend._check_emcy_heartbeat(fake)           # type: ignore[arg-type]
    io.dropped = 7
    with pytest.raises(ProtocolError, match="^7 frames dropped by this host's receive buffer on virtual:"):
        Cia402Backend._check_emcy_heartbeat(fake)           # type: ignore[arg-type]

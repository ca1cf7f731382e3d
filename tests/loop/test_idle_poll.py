"""The idle poller (rt_ident.loop.idle_poll): a SCHED_IDLE thread on the loop's CPU that keeps it
busy while the loop sleeps, never holds the GIL while it spins, and is gone when the run ends."""

from __future__ import annotations

import os
import threading
import time

import pytest

from rt_ident.compose import run as run_mod
from rt_ident.compose.run import run as run_axes
from rt_ident.config import load
from rt_ident.loop.host import loop_cpu
from rt_ident.loop.idle_poll import IdlePoller

QUIET = {"telemetry.sink": "off", "recording.enabled": False}


def _pollers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "rt_ident-idle-poll"]


def test_the_poller_spins_at_sched_idle_on_its_cpu_and_is_gone_after_stop():
    cpu = max(os.sched_getaffinity(0))
    p = IdlePoller(cpu)
    report = p.start()
    try:
        assert report == {"running": True, "cpu": cpu, "policy": "SCHED_IDLE"}
        tid = p._thread.native_id
        assert os.sched_getscheduler(tid) == os.SCHED_IDLE
        assert os.sched_getaffinity(tid) == {cpu}
        deadline = time.monotonic() + 30.0
        while not p._ts.any() and time.monotonic() < deadline:   # its clock read: it has spun once
            time.sleep(0.01)
    finally:
        p.stop()
    assert not p.alive and not _pollers()
    assert p.iterations > 0                        # it did spin until it was stopped


def test_the_poller_leaves_the_gil_to_other_threads_while_it_spins():
    # a thread that came back to Python between chunks could sit on the GIL; this one spins in one
    # compiled call: a pure-Python loop in this thread keeps running beside it
    p = IdlePoller(max(os.sched_getaffinity(0)))
    assert p.start()["running"]
    try:
        done = threading.Event()
        counts = []

        def count():
            n, end = 0, time.monotonic() + 0.2
            while time.monotonic() < end:
                n += 1
            counts.append(n)
            done.set()

        threading.Thread(target=count).start()
        assert done.wait(30.0)                 # with the GIL held by the spin it would never finish
        assert counts[0] > 1000
    finally:
        p.stop()


def test_a_poller_that_cannot_be_placed_says_why_and_leaves_no_thread():
    p = IdlePoller(100_000)                        # no such CPU
    report = p.start()
    assert report["running"] is False and "CPU 100000" in report["reason"]
    assert not p.alive and not _pollers()


@pytest.mark.xdist_group("realtime")
def test_a_real_time_run_polls_its_loop_cpu_sleeps_in_one_piece_and_stops_the_poller(restore_scheduling):
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.5, "loop.realtime": True}))
    assert s["stop"]["cause"] is None
    poll = s["realtime"]["idle_poll"]
    assert poll["running"] is True and poll["policy"] == "SCHED_IDLE" and poll["ticker_sleep"] == "one piece"
    assert poll["cpu"] == loop_cpu()                                  # the CPU the loop was pinned to
    assert not _pollers()


@pytest.mark.xdist_group("realtime")
def test_an_xy_run_polls_too_and_a_configured_max_sleep_keeps_its_chunks(restore_scheduling):
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    from rt_ident.axis.params import CONFIG_DIR

    cfg = load(CONFIG_DIR / "xy-sim.toml", **{**QUIET, "loop.duration": 0.5, "loop.max_sleep_us": 100.0})
    s = run_axes(cfg)
    assert s["stop"]["cause"] is None
    poll = s["realtime"]["idle_poll"]
    assert poll["running"] is True and "ticker_sleep" not in poll       # the user's max_sleep_us stands
    assert not _pollers()


@pytest.mark.xdist_group("realtime")
def test_idle_poll_off_or_not_real_time_starts_no_poller(restore_scheduling):
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True, "loop.idle_poll": False}))
    assert s["realtime"]["idle_poll"] == {"running": False, "reason": "[loop] idle_poll = false"}
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": False}))
    assert "idle_poll" not in s["realtime"]
    assert not _pollers()


@pytest.mark.xdist_group("realtime")
def test_a_poller_that_fails_to_start_is_reported_and_the_run_goes_on(restore_scheduling, monkeypatch):
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    import rt_ident.loop.idle_poll as ip

    def broken(self):
        raise RuntimeError("no compiler today")

    monkeypatch.setattr(ip.IdlePoller, "prepare", broken)
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True}))
    assert s["stop"]["cause"] is None and s["loop"]["samples"] > 0
    assert s["realtime"]["idle_poll"] == {"running": False,
                                          "reason": "failed to start: RuntimeError: no compiler today"}
    assert not _pollers()


def test_the_device_interrupts_of_proc_interrupts_are_read_per_cpu_without_timer_and_ipi_lines(tmp_path):
    from rt_ident.loop.host import read_interrupts

    f = tmp_path / "interrupts"
    f.write_text("           CPU0       CPU1       \n"
                 " 36:          0     288971 PCI-MSIX-0000:00:02.0   1-edge      virtio1-req.0\n"
                 " 39:      39331          0 PCI-MSIX-0000:00:03.0   2-edge      virtio2-output.0\n"
                 "LOC:   17016844   17738781   Local timer interrupts\n"
                 "RES:     276740     262179   Rescheduling interrupts\n")
    cpus, counts = read_interrupts(str(f))
    assert cpus == [0, 1]
    assert counts == {"36 virtio1-req.0": [0, 288971], "39 virtio2-output.0": [39331, 0]}
    assert read_interrupts(str(tmp_path / "missing")) is None


@pytest.mark.xdist_group("realtime")
def test_a_real_time_run_reports_the_device_interrupts_its_loop_cpu_served(restore_scheduling):
    if len(os.sched_getaffinity(0)) < 2 or not os.path.exists("/proc/interrupts"):
        pytest.skip("needs a CPU of the loop's own and /proc/interrupts")
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True}))
    irq = s["loop"]["host"]["interrupts"]
    assert irq["cpu"] == loop_cpu()                                   # the CPU the loop was pinned to
    assert irq["total"] >= sum(irq["top"].values()) >= 0 and len(irq["top"]) <= 3


def _privileged() -> bool:
    """Whether this process may leave SCHED_IDLE for SCHED_OTHER (root or a nice rlimit that allows it)."""
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
    except OSError:
        return False
    result = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before
    return result[0]


def test_the_poller_is_sched_idle_only_inside_its_compiled_spin_and_its_compile_changes_no_policy():
    # a SCHED_IDLE thread holding or waiting for the GIL stalls the real-time threads beside it; this
    # one takes SCHED_IDLE after it let the GIL go and gives it back before it takes the GIL again
    cpu = max(os.sched_getaffinity(0))
    p = IdlePoller(cpu)
    policy = os.sched_getscheduler(0)
    p.prepare()                                     # compiled without being run
    assert os.sched_getscheduler(0) == policy and not _pollers()
    assert p.start()["running"]
    try:
        assert os.sched_getscheduler(p._thread.native_id) == os.SCHED_IDLE
    finally:
        p.stop()
    assert not p.alive and p.iterations > 0
    if _privileged():
        assert p.exit_policy == os.SCHED_OTHER     # it took the GIL back as an ordinary thread


def _record_order(monkeypatch) -> list[str]:
    """'safe_stop' / 'poller stop' / 'final fit' (with the caller's policy) in the order a run does them."""
    from drivers.base import Backend

    events: list[str] = []
    safe_stop, stop, final_fit = Backend.safe_stop, IdlePoller.stop, run_mod.final_fit

    def backend_safe_stop(self, *a, **k):
        events.append("safe_stop")
        return safe_stop(self, *a, **k)

    def poller_stop(self, *a, **k):
        if self.alive:
            events.append("poller stop")
        return stop(self, *a, **k)

    def recorded_final_fit(*a, **k):
        fifo = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
        events.append(f"final fit {'FIFO' if fifo else 'not FIFO'}"
                      f" on {sorted(os.sched_getaffinity(0))}")
        return final_fit(*a, **k)

    monkeypatch.setattr(Backend, "safe_stop", backend_safe_stop)
    monkeypatch.setattr(IdlePoller, "stop", poller_stop)
    monkeypatch.setattr(run_mod, "final_fit", recorded_final_fit)
    return events


@pytest.mark.xdist_group("realtime")
def test_a_real_time_run_stops_the_poller_after_the_safe_stop_and_fits_outside_real_time(restore_scheduling,
                                                                                         monkeypatch):
    # the final fit is CPU-bound work: at SCHED_FIFO it would run into the RT throttle and hold the loop's
    # CPU; the poller is stopped only once the device is stopped (a SYNC sender may wait on it for the GIL)
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    before = os.sched_getscheduler(0), os.sched_getaffinity(0)
    events = _record_order(monkeypatch)
    s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True}))
    assert s["realtime"]["idle_poll"]["running"] is True
    everywhere = sorted(before[1])
    assert [e for e in events if e != "safe_stop"] == ["poller stop", f"final fit not FIFO on {everywhere}"]
    assert events.index("safe_stop") < events.index("poller stop")
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before      # the caller's thread as it was
    if s["realtime"]["sched_fifo"] is not True:
        pytest.skip(f"SCHED_FIFO not granted here ({s['realtime']['sched_fifo']}): the loop never ran at it")


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("locked_by_caller", [False, True], ids=["unlocked", "locked-by-caller"])
def test_a_real_time_run_unlocks_the_memory_it_locked_before_its_final_fit_and_keeps_a_callers_lock(
        restore_scheduling, monkeypatch, locked_by_caller):
    # mlockall's MCL_FUTURE outlives the loop: unlocked, the final fit and whatever the process does next
    # would fault in and pin every page they map
    from rt_ident.loop.scheduler import _mlockall, locked_memory_kb, unlock_memory

    if locked_memory_kb() != 0:
        pytest.skip(f"this process holds locked memory already ({locked_memory_kb()} kB)")
    if locked_by_caller and _mlockall() is not True:
        pytest.skip("mlockall is not allowed here")
    seen: dict[str, int | None] = {}
    final_fit = run_mod.final_fit

    def recorded_final_fit(*a, **k):
        seen["final fit"] = locked_memory_kb()
        return final_fit(*a, **k)

    def during(tick: int) -> None:
        if tick == 100:
            seen["loop"] = locked_memory_kb()

    monkeypatch.setattr(run_mod, "final_fit", recorded_final_fit)
    try:
        s = run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True}), tick_hook=during)
        after = locked_memory_kb()
    finally:
        unlock_memory()
    if s["realtime"]["mlockall"] is not True:
        pytest.skip(f"the run could not lock its memory: {s['realtime']['mlockall']}")
    assert seen["loop"] > 0
    if locked_by_caller:
        assert seen["final fit"] > 0 and after > 0
    else:
        assert seen["final fit"] == 0 and after == 0


def _shared_heap_bytes() -> int:
    """What multiprocessing's heap holds mapped in this process (the helpers' rings are there)."""
    import multiprocessing.heap

    return sum(a.size for a in multiprocessing.heap.BufferWrapper._heap._arenas)


@pytest.mark.parametrize("frozen_by_caller", [False, True], ids=["unfrozen", "frozen-by-caller"])
def test_runs_in_one_process_free_each_runs_helpers_and_rings_and_keep_a_callers_frozen_heap(frozen_by_caller):
    # the run freezes the heap for its loop: left frozen, each run's cycles (its helpers and their
    # 64 MB and 4 MB rings) would stay mapped for as long as the process lives
    import gc

    if gc.get_freeze_count():
        pytest.skip(f"this process has a frozen heap already ({gc.get_freeze_count()} objects)")
    cfg = load(None, **{**QUIET, "loop.duration": 0.2, "loop.realtime": False})
    try:
        if frozen_by_caller:
            gc.freeze()
        callers = gc.get_freeze_count()
        run_mod.run(cfg)
        gc.collect()
        after_one = _shared_heap_bytes()
        for _ in range(2):
            run_mod.run(cfg)
        gc.collect()
        after_three = _shared_heap_bytes()
        left_frozen = gc.get_freeze_count()
    finally:
        gc.unfreeze()
        gc.enable()
    if frozen_by_caller:
        assert left_frozen >= callers > 0
    else:
        assert left_frozen == 0 and after_three <= after_one, (after_one, after_three)


@pytest.mark.xdist_group("realtime")
def test_a_run_that_fails_in_its_loop_leaves_real_time_after_the_safe_stop(restore_scheduling, monkeypatch):
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    before = os.sched_getscheduler(0), os.sched_getaffinity(0)
    events = _record_order(monkeypatch)

    def boom(tick: int) -> None:
        if tick == 50:
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        run_mod.run(load(None, **{**QUIET, "loop.duration": 0.3, "loop.realtime": True}), tick_hook=boom)
    assert events[0] == "safe_stop" and events.count("poller stop") == 1
    assert events.index("poller stop") > events.index("safe_stop")
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


@pytest.mark.xdist_group("realtime")
def test_an_xy_run_fits_outside_real_time_too(restore_scheduling, monkeypatch):
    import rt_ident.compose.run as multi_mod
    from rt_ident.axis.params import CONFIG_DIR

    before = os.sched_getscheduler(0), os.sched_getaffinity(0)
    policies = []
    final_fit = multi_mod.final_fit

    def recorded_final_fit(*a, **k):
        policies.append(os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK)
        return final_fit(*a, **k)

    monkeypatch.setattr(multi_mod, "final_fit", recorded_final_fit)
    s = run_axes(load(CONFIG_DIR / "xy-sim.toml", **{**QUIET, "loop.duration": 0.3}))
    assert s["stop"]["cause"] is None
    assert policies and os.SCHED_FIFO not in policies
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before
    if s["realtime"]["sched_fifo"] is not True:
        pytest.skip(f"SCHED_FIFO not granted here ({s['realtime']['sched_fifo']}): the loop never ran at it")

"""rt_ident.processes.guard: a job process that dies or stops answering is found, said, restarted once;
a run's helpers carry their own names."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rt_ident.processes.guard import HelperWatch


class FakeJob:
    """A helper as the watch sees it: alive, progress (None: no work waits for it), restart()."""

    def __init__(self) -> None:
        self.alive, self.exitcode, self.pid, self.restarts = True, None, 100, 0
        self.progress: tuple[int, int] | None = None

    @property
    def busy(self) -> bool:
        return self.progress is not None

    @busy.setter
    def busy(self, on: bool) -> None:              # work waits, and none is taken while it stays so
        self.progress = (7, 7) if on else None

    def restart(self) -> FakeJob:
        self.restarts += 1
        self.pid += 1
        self.alive, self.progress = True, None
        return self


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _watch(job: FakeJob, clock: Clock, restartable: bool = True) -> HelperWatch:
    return HelperWatch({"control": job}, restartable=("control",) if restartable else (), every_ticks=1,
                       hang_s=10.0, clock=clock)


def _look_every(watch: HelperWatch, clock: Clock, seconds: float, step: float = 0.1) -> None:
    for _ in range(int(round(seconds / step))):
        clock.now += step
        watch(0)


def test_a_job_that_answers_within_the_hang_time_is_left_alone_however_often_it_is_busy():
    job, clock = FakeJob(), Clock()
    watch = _watch(job, clock)
    for _ in range(5):                      # busy 9 s, then an answer, again and again
        job.busy = True
        _look_every(watch, clock, 9.0)
        job.busy = False
        _look_every(watch, clock, 0.5)
    assert job.restarts == 0 and watch.summary()["control"]["hangs"] == 0


def test_a_job_busy_for_the_hang_time_is_restarted_once_and_said(caplog):
    job, clock = FakeJob(), Clock()
    watch = _watch(job, clock)
    job.busy = True
    with caplog.at_level(logging.ERROR, logger="rt_ident.processes.guard"):
        _look_every(watch, clock, 9.5)
        assert job.restarts == 0
        _look_every(watch, clock, 1.0)
    st = watch.summary()["control"]
    assert job.restarts == 1 and st["hangs"] == 1 and st["restarts"] == 1 and st["alive"] and st["pid"] == 101
    assert any("helper control gave no answer for 10 s" in r.getMessage()
               and "restarting it (the old pid 100)" in r.getMessage() for r in caplog.records)
    job.busy = True                          # the restarted one hangs too: reported, not restarted again
    _look_every(watch, clock, 11.0)
    st = watch.summary()["control"]
    assert job.restarts == 1 and st["hangs"] == 2 and st["hung"] is True


def test_a_job_fed_without_pause_is_never_hung_while_it_takes_the_work():
    # the fit process: a snapshot waits for it almost always, and it takes one every few hundred ms
    job, clock = FakeJob(), Clock()
    watch = _watch(job, clock)
    for k in range(300):
        job.progress = (k // 3, k // 3)
        clock.now += 0.1
        watch(0)
    assert job.restarts == 0 and watch.summary()["control"]["hangs"] == 0


@pytest.mark.parametrize("restartable", [True, False])
def test_time_the_watch_did_not_look_is_not_counted_as_a_hang(restartable):
    # a loop stalled for 30 s (the host, not the job): the job answered meanwhile as far as anyone knows
    job, clock = FakeJob(), Clock()
    watch = _watch(job, clock, restartable)
    job.busy = True
    _look_every(watch, clock, 5.0)
    clock.now += 30.0
    _look_every(watch, clock, 9.0)
    assert job.restarts == 0 and watch.summary()["control"]["hangs"] == 0
    _look_every(watch, clock, 1.5)
    st = watch.summary()["control"]
    assert st["hangs"] == 1 and job.restarts == (1 if restartable else 0) and st.get("hung", False) is not restartable


def test_a_dead_job_is_still_restarted_at_once_and_counted_as_a_death():
    job, clock = FakeJob(), Clock()
    watch = _watch(job, clock)
    job.alive, job.exitcode = False, -9
    watch(0)
    st = watch.summary()["control"]
    assert job.restarts == 1 and st["deaths"] == 1 and st["hangs"] == 0 and st["exitcodes"] == [-9]


def _comm_becomes(pid: int, want: str, timeout: float = 20.0) -> str:
    comm = ""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
        if comm == want:
            break
        time.sleep(0.02)
    return comm


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kernel thread names are Linux's")
def test_a_runs_helpers_and_its_emulated_device_carry_their_own_names_for_ps_top_and_pgrep():
    # forked from one forkserver, every helper has the forkserver's command line: only the kernel name
    # (/proc/PID/comm) tells the fit process from the recorder or the emulated board
    from rt_ident.axis.params import CONFIG_DIR
    from rt_ident.config import load
    from rt_ident.processes.emulation import start_emulator
    from rt_ident.processes.jobs import JobProcess

    jp = JobProcess(time.sleep, name="rt_ident-fit", min_interval=0.0).start()
    try:
        assert jp.pid is not None and _comm_becomes(jp.pid, "rt-fit") == "rt-fit"
    finally:
        jp.close()
    board = start_emulator(load(CONFIG_DIR / "serial-virtual.toml", **{"loop.realtime": False}))
    try:
        assert Path(f"/proc/{board.pid}/comm").read_text().strip() == "rt-board"
    finally:
        board.close()


def test_a_process_that_exits_without_closing_its_helper_ends_it_instead_of_waiting_for_ever():
    # multiprocessing's exit sends a daemonic child SIGTERM (which helpers ignore) and joins it without a timeout
    import subprocess

    script = ("import time\n"
              "from rt_ident.processes.jobs import JobProcess\n"
              "jp = JobProcess(time.sleep, min_interval=0.0).start()\n"
              "print(jp.pid, flush=True)\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    pid = int(r.stdout.split()[0])
    assert r.returncode == 0, r.stderr
    assert f"rt_ident-job (pid {pid}) was still running at exit" in r.stderr
    end = time.monotonic() + 5.0                 # reaped by the forkserver, which ends with its starter
    while Path(f"/proc/{pid}").exists() and time.monotonic() < end:
        time.sleep(0.05)
    assert not Path(f"/proc/{pid}").exists()


def test_a_closed_terminals_sighup_stops_the_main_process_but_not_under_nohup(sighup_default):
    probe = ("import signal, threading; from rt_ident.processes.guard import install_stop_signals, stop_signals; "
             "stop = threading.Event(); install_stop_signals(stop); signal.raise_signal(signal.SIGHUP); "
             "print(signal.SIGHUP in stop_signals(), stop.is_set())")
    plain = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert plain.stdout.split() == ["True", "True"], plain.stderr
    nohup = subprocess.run(["nohup", sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert nohup.returncode == 0 and nohup.stdout.split() == ["False", "False"], nohup.stderr   # it runs on

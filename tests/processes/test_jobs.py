"""The job process (rt_ident.processes.jobs): how it ends."""

from __future__ import annotations

import os
import threading
import time

import pytest

from rt_ident.processes import jobs
from rt_ident.processes.jobs import JobProcess


def test_a_job_process_busy_past_its_close_timeout_is_killed_not_left_behind():
    """A helper is born ignoring SIGTERM; one still inside a job when the run closes it must not outlive the
    run (it would hold the run's stdout and the forkserver open)."""
    jp = JobProcess(time.sleep, min_interval=0.0).start()
    deadline = time.monotonic() + 60
    while not jp.submit(30.0):                   # sent once the process says it is ready
        assert time.monotonic() < deadline, "the job process never became ready"
        time.sleep(0.01)
    time.sleep(0.3)                              # inside time.sleep(30) now
    t0 = time.monotonic()
    jp.close(timeout=0.2)
    assert not jp.alive and jp.exitcode is not None and time.monotonic() - t0 < 10


def _submit_when_ready(jp: JobProcess, request) -> None:
    deadline = time.monotonic() + 60
    while not jp.submit(request):
        assert time.monotonic() < deadline, "the job process never became ready"
        time.sleep(0.01)


def test_progress_moves_while_jobs_are_done_and_stands_still_while_one_hangs():
    jp = JobProcess(time.sleep, min_interval=0.0).start()
    try:
        seen = set()
        for _ in range(5):                           # short jobs, one after the other: each one moves it
            _submit_when_ready(jp, 0.01)
            seen.add(jp.progress)
            while jp.progress is not None:           # answered and waiting for the next
                time.sleep(0.005)
        seen.discard(None)
        assert len(seen) >= 4, seen
        _submit_when_ready(jp, 30.0)                 # a job that does not come back: the sixth taken, five answered
        deadline = time.monotonic() + 30
        while jp.progress != (6, 5):
            assert time.monotonic() < deadline, jp.progress
            time.sleep(0.01)
        time.sleep(0.5)
        assert jp.progress == (6, 5)
    finally:
        jp.close(timeout=0.2)


def test_a_restarted_job_process_has_no_progress_to_time_until_its_imports_are_done_and_restarts_count():
    jp = JobProcess(time.sleep, min_interval=0.0).start()
    try:
        assert jp.generation == 0
        jp.restart()
        assert jp.generation == 1 and jp.progress is None      # starting: not timed as a hang
        _submit_when_ready(jp, 30.0)
        assert jp.progress is not None
    finally:
        jp.close(timeout=0.2)


@pytest.mark.parametrize("role", ["fit", "control"])
def test_a_job_process_restarted_while_the_loop_runs_real_time_leaves_the_loops_cpu_at_its_roles_nice_value(role):
    """The run places the helpers it starts before the loop; one restarted during the loop places itself."""
    from rt_ident.processes.guard import HELPER_NICE

    main = os.getpid()                               # the main thread, where a run's loop runs
    cpus = os.sched_getaffinity(main)
    if len(cpus) < 2:
        pytest.skip("needs two CPUs: one for the loop, one for the helpers")
    loop_cpu = max(cpus)
    policy, param = os.sched_getscheduler(main), os.sched_getparam(main)
    jp = JobProcess(time.sleep, name=f"rt_ident-{role}", min_interval=0.0).start()
    try:
        _submit_when_ready(jp, 0.01)
        try:                                         # as the loop sets itself
            os.sched_setaffinity(main, {loop_cpu})
            os.sched_setscheduler(main, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(10))
        except PermissionError:
            pytest.skip("SCHED_FIFO not permitted here")
        jp.restart()
        _submit_when_ready(jp, 0.01)                 # the new process is in and took work
        assert loop_cpu not in os.sched_getaffinity(jp.pid)
        assert os.getpriority(os.PRIO_PROCESS, jp.pid) == HELPER_NICE[role]
    finally:
        os.sched_setscheduler(main, policy, param)
        os.sched_setaffinity(main, cpus)
        jp.close(timeout=0.2)


def test_a_restarted_job_process_takes_the_nice_value_and_cpus_the_run_gave_the_one_it_replaces():
    """Not real-time too (the run nices its helpers either way): the record the run left on the job."""
    cpus = sorted(os.sched_getaffinity(0))
    jp = JobProcess(time.sleep, name="rt_ident-fit", min_interval=0.0).start()
    try:
        _submit_when_ready(jp, 0.01)
        jp.placement = {"nice": 13, "cpus": cpus[:1]}
        jp.restart()
        _submit_when_ready(jp, 0.01)
        assert os.getpriority(os.PRIO_PROCESS, jp.pid) == 13
        assert os.sched_getaffinity(jp.pid) == set(cpus[:1])
    finally:
        jp.close(timeout=0.2)


@pytest.fixture
def held_restart(monkeypatch):
    """A gate the restarts' reaping of the old process waits on (10 s at most), and whether each was let go."""
    gate, let_go = threading.Event(), []
    end = jobs.end_helper

    def held(proc, **kw):
        let_go.append(gate.wait(10.0))
        end(proc, **kw)

    monkeypatch.setattr(jobs, "end_helper", held)
    yield gate, let_go
    gate.set()


def test_a_restart_returns_before_its_work_is_done_and_the_job_is_busy_until_the_new_process_is_in(held_restart):
    # the loop's tick calls restart(): the kill, the new rings and the fork wait on other processes
    gate, let_go = held_restart
    jp = JobProcess(time.sleep, min_interval=0.0).start()
    try:
        _submit_when_ready(jp, 0.01)
        old = jp.pid
        jp.restart()                                 # back here with the old process not yet reaped
        assert jp.alive and not jp.ready and jp.progress is None and jp.take() == [] and not jp.submit(0.01)
        assert jp.pid == old
        gate.set()
        _submit_when_ready(jp, 0.01)                 # the new process takes work
        assert let_go == [True] and jp.pid != old and jp.generation == 1
        deadline = time.monotonic() + 30
        while jp.fits == 0:                          # time.sleep's answer (None) counted as a result
            jp.poll()
            assert time.monotonic() < deadline, "the new process never answered"
            time.sleep(0.01)
    finally:
        jp.close(timeout=0.2)


def test_closing_a_job_while_its_restart_is_under_way_ends_the_new_process_too(held_restart):
    gate, _ = held_restart
    jp = JobProcess(time.sleep, min_interval=0.0).start()
    old = jp.pid
    jp.restart()
    threading.Timer(0.3, gate.set).start()
    jp.close(timeout=0.2)
    assert jp.pid != old and not jp.alive and jp.exitcode is not None
    for pid in (old, jp.pid):
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)

"""The job process (rt_ident.processes.jobs): how it ends."""

from __future__ import annotations

import time

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

"""rt_ident.errors.host_fix: a fix that puts a failure on the host says what is left to change in the run it ended."""

from __future__ import annotations

import pytest

from drivers.errors import HeartbeatLost, RpdoTimeout
from rt_ident.errors import HOST_FIX, host_fix

STARVED = f"{HOST_FIX}): the emulated drive's process was starved"


@pytest.mark.parametrize("realtime", [False, None])
def test_a_run_that_was_not_real_time_is_told_to_turn_it_on(realtime):
    assert host_fix(RpdoTimeout.fix, realtime) == RpdoTimeout.fix
    assert host_fix(STARVED, realtime) == STARVED


def test_a_run_whose_loop_was_real_time_is_told_the_host_is_too_busy_and_keeps_the_other_setting():
    got = host_fix(HeartbeatLost.fix, {"sched_fifo": True})
    assert got == ("loop.realtime is on and the loop ran at SCHED_FIFO: a less busy host (else a longer "
                   "backend.heartbeat_consumer_ms): the drive heard no heartbeat from this host within its "
                   "consumer time")
    assert host_fix(STARVED, {"sched_fifo": True}) == ("loop.realtime is on and the loop ran at SCHED_FIFO: "
                                                       "a less busy host: the emulated drive's process was starved")


def test_a_run_refused_sched_fifo_is_told_to_grant_the_privileges_and_why_it_was_refused():
    got = host_fix(RpdoTimeout.fix, {"sched_fifo": "denied: [Errno 1] Operation not permitted"})
    assert got.startswith("loop.realtime is on but the loop ran without SCHED_FIFO (denied: [Errno 1] Operation "
                          "not permitted): real-time privileges")
    assert got.endswith("or a less busy host (else a longer backend.rpdo_deadline_ms): the drive got no torque "
                        "write within its RPDO deadline")


@pytest.mark.parametrize("fix", [None, "", "backend.lead", "loop.realtime = false"])
def test_a_fix_that_does_not_put_the_failure_on_the_host_is_left_as_it_is(fix):
    assert host_fix(fix, {"sched_fifo": True}) == fix


@pytest.mark.parametrize("realtime", [False, {"sched_fifo": True}, {"sched_fifo": "denied"}])
def test_every_host_fix_still_begins_with_the_setting_that_marks_the_host(realtime):
    for fix in (RpdoTimeout.fix, HeartbeatLost.fix, STARVED):
        assert host_fix(fix, realtime).startswith("loop.realtime")

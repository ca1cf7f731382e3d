"""One real-time loop per CPU (rt_ident.loop.cpu_claim): a second one waits, then refuses, before anything moves."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from rt_ident.errors import ConfigError
from rt_ident.loop.cpu_claim import CpuClaim, CpuWaitInterrupted, claim_path
from rt_ident.loop.host import loop_cpu

_HOLD = ("import sys; from rt_ident.loop.cpu_claim import CpuClaim; "
         "c = CpuClaim(int(sys.argv[1]), 120.0, directory=sys.argv[2] or None); c.acquire(); "
         "print('held', flush=True); sys.stdin.read()")


class Holder:
    """Another process holding the claim on ``cpu`` until :meth:`end`."""

    def __init__(self, cpu: int, directory: str = "") -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(cpu), directory], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=os.getcwd())
        assert self.proc.stdout is not None and self.proc.stdout.readline().strip() == "held"

    def end(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            self.proc.wait(30)


@pytest.mark.xdist_group("realtime")
def test_a_second_loop_waits_for_the_cpu_then_refuses_naming_the_holder_and_the_setting(tmp_path):
    holder = Holder(3, str(tmp_path))
    try:
        claim = CpuClaim(3, 0.3, directory=tmp_path)
        t0 = time.monotonic()
        with pytest.raises(ConfigError) as err:
            claim.acquire()
        assert time.monotonic() - t0 >= 0.3
        msg = str(err.value)
        assert msg.startswith("loop.cpu_wait_s: CPU 3 is still held") and f"pid {holder.proc.pid}" in msg
        assert "loop.realtime = false" in msg
    finally:
        holder.end()


@pytest.mark.xdist_group("realtime")
def test_a_waiting_loop_gets_the_cpu_once_the_other_process_ends(tmp_path):
    holder = Holder(2, str(tmp_path))
    threading.Timer(0.4, holder.end).start()
    claim = CpuClaim(2, 30.0, directory=tmp_path)
    claim.acquire()
    try:
        assert 0.3 <= claim.waited_s < 20.0
        assert holder.proc.wait(5) is not None   # it had released the claim by ending; its exit may lag the release
    finally:
        claim.release()


@pytest.mark.xdist_group("realtime")
def test_a_stop_signal_while_waiting_ends_the_wait_without_claiming(tmp_path):
    holder = Holder(1, str(tmp_path))
    try:
        stop = threading.Event()
        threading.Timer(0.2, stop.set).start()
        claim = CpuClaim(1, 60.0, stop=stop, directory=tmp_path)
        t0 = time.monotonic()
        with pytest.raises(CpuWaitInterrupted):
            claim.acquire()
        assert time.monotonic() - t0 < 10.0
        assert CpuWaitInterrupted.cause is None           # the run ends as asked, not as a fault
    finally:
        holder.end()


def _free_elsewhere(cpu: int, directory) -> bool:
    """Whether another process could claim ``cpu`` now."""
    code = ("import sys, fcntl, os; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT); "
            "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)")
    return subprocess.run([sys.executable, "-c", code, str(claim_path(cpu, directory))],
                          capture_output=True).returncode == 0


@pytest.mark.xdist_group("realtime")
def test_nested_claims_in_one_process_share_it_and_the_last_release_frees_the_cpu(tmp_path):
    outer, inner = CpuClaim(0, 0.0, directory=tmp_path), CpuClaim(0, 0.0, directory=tmp_path)
    outer.acquire()
    inner.acquire()                                      # no wait on itself (wait_s 0 would refuse)
    assert not _free_elsewhere(0, tmp_path)
    inner.release()
    assert not _free_elsewhere(0, tmp_path)
    outer.release()
    assert _free_elsewhere(0, tmp_path)
    outer.release()                                      # idempotent


@pytest.mark.xdist_group("realtime")
@pytest.mark.skipif(loop_cpu() is None, reason="the loop gets a CPU of its own only with two or more")
def test_a_run_refuses_before_turning_real_time_while_another_loop_holds_its_cpu(tmp_path):
    from rt_ident.compose.run import run
    from rt_ident.config import load

    cpu = loop_cpu()
    assert cpu is not None
    holder = Holder(cpu)                                 # the real claim: this host's loops wait for it
    try:
        cfg = load("configs/sim.toml", **{"loop.realtime": True, "loop.cpu_wait_s": 0.2, "loop.duration": 0.5,
                                          "telemetry.sink": "off", "recording.enabled": False})
        with pytest.raises(ConfigError, match=r"^loop\.cpu_wait_s: CPU \d+ is still held"):
            run(cfg)
        assert os.sched_getscheduler(0) == os.SCHED_OTHER  # never turned real-time
    finally:
        holder.end()

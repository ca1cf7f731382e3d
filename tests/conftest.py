"""Shared pytest options (``--hardware``, ``--hardware-config``) and the ``emulators`` fixture.

Tests marked ``hardware`` (marker declared in pyproject.toml) are skipped unless
``--hardware`` is given. ``--hardware-config PATH`` names a run configuration
(TOML) whose ``[backend]`` is a real device; it may be repeated or hold several
comma-separated paths. Nothing here runs at import time.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os

import pytest

# One BLAS thread in the test processes, as ``rt-ident`` has in its own (rt_ident/cli.py) and the helpers in
# theirs: a second OpenBLAS thread spins after each small matrix product, doubling a test's CPU on a 2-core
# machine where the other xdist worker needs it. Read at numpy's import, which comes after this file's.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("hardware", "tests against real devices")
    group.addoption("--hardware", action="store_true", default=False,
                    help="run tests marked 'hardware' (they move a real axis)")
    group.addoption("--hardware-config", action="append", default=[], metavar="PATH",
                    help="run config (TOML) naming a real backend; repeat or comma-separate for several")


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: two workers per CPU, at most four. A worker spends most of its time in runs paced in
    real time, not on a CPU, so one worker per CPU leaves the CPUs idle much of the time. The real-time
    parts of all workers' runs take turns on the one CPU the loop takes (a run claims it:
    rt_ident/loop/cpu_claim.py): more workers would only queue there, some past a run's
    ``loop.cpu_wait_s``."""
    return min(2 * len(os.sched_getaffinity(0)), 4)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="real device: run with --hardware (and --hardware-config PATH)")
    for item in items:
        if item.get_closest_marker("hardware") is not None:
            item.add_marker(skip)


@pytest.fixture
def emulators(monkeypatch) -> list:
    """The emulators ``rt_ident.compose.run.run`` starts (handles kept for the checks after the run)."""
    from rt_ident.processes import emulation

    started: list = []
    original = emulation.start_emulator

    def start(cfg):
        dev = original(cfg)
        started.append(dev)
        return dev

    monkeypatch.setattr(emulation, "start_emulator", start)
    return started


@pytest.fixture
def restore_scheduling():
    """``rt_ident.compose.run`` with ``loop.realtime`` makes the calling thread real-time (SCHED_FIFO,
    one CPU, mlockall, GC frozen): undo it after the test."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    cpus = os.sched_getaffinity(0)
    yield
    try:
        os.sched_setscheduler(0, policy, param)
    except OSError:
        pass
    os.sched_setaffinity(0, cpus)
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.munlockall()
    gc.unfreeze()
    gc.enable()

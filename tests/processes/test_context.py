"""The helpers' start context: a forkserver that preloads, runs no threads and starts children as helpers
must be born (SIGINT/SIGTERM ignored, one BLAS thread, its starter's stdio and environment), or spawn when
asked."""

from __future__ import annotations

import importlib
import multiprocessing as mp
import os
import signal
import subprocess
import sys

import pytest

from rt_ident.processes import context

FORKSERVER = pytest.mark.skipif("forkserver" not in mp.get_all_start_methods(), reason="no forkserver here")


def _child_report(q) -> None:
    sig = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    q.put((sig[signal.SIGINT] == signal.SIG_IGN, sig[signal.SIGTERM] == signal.SIG_IGN,
           os.environ.get("OPENBLAS_NUM_THREADS"), "rt_ident.control.design" in sys.modules))


def test_every_preloaded_module_exists_so_none_is_silently_skipped():
    for name in context.PRELOAD:
        importlib.import_module(name)


@FORKSERVER
def test_helpers_are_forked_preloaded_ignoring_group_signals_with_one_blas_thread(monkeypatch):
    monkeypatch.setenv("RT_IDENT_START_METHOD", "forkserver")
    ctx = context.helper_context()
    q = ctx.Queue()
    p = ctx.Process(target=_child_report, args=(q,))
    p.start()
    got = q.get(timeout=60)
    p.join(10)
    assert got == (True, True, "1", True)
    assert "OPENBLAS_NUM_THREADS" not in os.environ or os.environ["OPENBLAS_NUM_THREADS"] == "1"


@FORKSERVER
def test_the_forkserver_runs_a_single_thread_so_forking_it_is_safe(monkeypatch):
    from multiprocessing import forkserver

    monkeypatch.setenv("RT_IDENT_START_METHOD", "forkserver")
    context.helper_context()
    pid = forkserver._forkserver._forkserver_pid      # multiprocessing keeps no public handle on it
    assert pid is not None
    assert len(os.listdir(f"/proc/{pid}/task")) == 1


def _child_writes(tag: str) -> None:
    sys.stdout.write(f"out {tag} {os.environ.get('RT_IDENT_TEST_LATE')}\n")
    sys.stdout.flush()
    os.write(2, f"err {tag}\n".encode())


@FORKSERVER
def test_a_forked_helper_writes_to_its_starters_current_stdout_and_stderr_and_sees_its_environment(
        monkeypatch, capfd):
    from rt_ident.processes.guard import start_with_helper_env

    monkeypatch.setenv("RT_IDENT_START_METHOD", "forkserver")
    with capfd.disabled():                      # the forkserver started (if it was not) outside this capture
        ctx = context.helper_context()
    monkeypatch.setenv("RT_IDENT_TEST_LATE", "set-later")
    p = ctx.Process(target=_child_writes, args=("a",))
    start_with_helper_env(p)
    p.join(60)
    assert p.exitcode == 0
    out, err = capfd.readouterr()
    assert "out a set-later" in out and "err a" in err


def test_helpers_are_forked_where_the_platform_can_and_spawned_when_asked(monkeypatch):
    monkeypatch.delenv("RT_IDENT_START_METHOD", raising=False)
    assert context.start_method() == ("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
    monkeypatch.setenv("RT_IDENT_START_METHOD", "spawn")
    assert context.start_method() == "spawn"
    assert context.helper_context().get_start_method() == "spawn"


def test_an_unknown_start_method_is_refused_in_one_line():
    code = "from rt_ident.processes.context import start_method; start_method()"
    r = subprocess.run([sys.executable, "-c", code], env={**os.environ, "RT_IDENT_START_METHOD": "fork"},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "RT_IDENT_START_METHOD='fork': use one of" in r.stderr


def _fresh_python(code: str) -> subprocess.CompletedProcess:
    """``code`` in a new interpreter with the default start method (no forkserver running yet)."""
    env = {k: v for k, v in os.environ.items() if k != "RT_IDENT_START_METHOD"}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)


@FORKSERVER
def test_a_discarded_prestart_ends_the_forkserver_while_it_still_imports():
    """A start refused before any helper (``rt-ident run``'s checks fail) leaves no forkserver finishing its
    imports after the command has ended: it ignores SIGTERM and hears of the end only once its imports are done."""
    code = ("import os, subprocess, sys\n"
            "from multiprocessing import forkserver as f\n"
            "from rt_ident.processes import context\n"
            "early = context.prestart(); pid = f._forkserver._forkserver_pid\n"
            "early.discard()\n"
            "print(pid, *subprocess.run(['ps', '-o', 'pid=', '--ppid', str(os.getpid())], capture_output=True, "
            "text=True).stdout.split())\n")
    r = _fresh_python(code)
    pid, *children = r.stdout.split()
    assert int(pid) > 0 and pid not in children, (r.stdout, r.stderr[-2000:])


@FORKSERVER
def test_a_prestarted_forkserver_is_the_one_helpers_start_from():
    code = ("from multiprocessing import forkserver as f\n"
            "from rt_ident.processes import context\n"
            "early = context.prestart(); pid = f._forkserver._forkserver_pid\n"
            "again = context.prestart()\n"
            "context.helper_context()\n"
            "print(early.started, again.started, pid == f._forkserver._forkserver_pid)\n")
    r = _fresh_python(code)
    assert r.stdout.split() == ["True", "False", "True"], r.stderr[-2000:]


@FORKSERVER
def test_a_ctrl_c_while_a_helper_starts_from_the_forkserver_reaches_the_starters_handler():
    """The first helper's start waits for the forkserver's preloads: a Ctrl-C then must reach the run's
    handler (which stops the run), not be ignored for the child's sake and lost."""
    code = ("import os, signal, threading, time\n"
            "from rt_ident.processes.context import helper_context\n"
            "from rt_ident.processes.guard import start_ignoring_signals\n"
            "got = []\n"
            "signal.signal(signal.SIGINT, lambda *a: got.append(1))\n"
            "ctx = helper_context()\n"
            "threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
            "p = ctx.Process(target=time.sleep, args=(0,))\n"
            "t = time.monotonic(); start_ignoring_signals(p); waited = time.monotonic() - t\n"
            "p.join(); time.sleep(0.1)\n"
            "print(len(got), waited > 0.2)\n")
    r = _fresh_python(code)
    got, waited_past_the_signal = r.stdout.split()
    if waited_past_the_signal != "True":
        pytest.skip("the forkserver preloaded in under 0.2 s: the start did not span the signal")
    assert got == "1", r.stderr[-2000:]


@FORKSERVER
def test_a_process_that_started_the_forkserver_reaps_it_before_it_exits():
    """No forkserver outlives the command that started it (it would end by itself a moment later, an orphan)."""
    code = ("from multiprocessing import forkserver as f\n"
            "from rt_ident.processes import context\n"
            "context.helper_context()\n"
            "print(f._forkserver._forkserver_pid, flush=True)\n")
    r = _fresh_python(code)
    pid = int(r.stdout.split()[0])
    assert not os.path.exists(f"/proc/{pid}"), (open(f"/proc/{pid}/stat").read(), r.stderr[-2000:])

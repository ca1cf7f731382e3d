"""No traceback reaches the user: a device that dies mid-run is reported once, log lines are one
line unless -v, and a bug is one 'internal error' line (exit 1) unless -v."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from rt_ident import cli

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}


def _script(tmp_path: Path, body: str) -> Path:
    """A command line run through rt_ident.cli.main with ``body`` patched in first."""
    p = tmp_path / "rt_ident_patched.py"
    p.write_text(textwrap.dedent(body) + textwrap.dedent("""
        if __name__ == "__main__":
            from rt_ident.cli import main
            sys.argv = ["rt-ident", *sys.argv[1:]]
            main()
    """))
    return p


@pytest.mark.slow
def test_a_serial_board_that_dies_mid_run_is_reported_once_without_traceback(tmp_path):
    script = _script(tmp_path, """
        import os, signal, sys
        from rt_ident.compose import run as run_mod
        from rt_ident.processes import emulation

        started = []
        original_start, original_run = emulation.start_emulator, run_mod.run

        def start(cfg):
            dev = original_start(cfg)
            started.append(dev)
            return dev

        def run(cfg, **kw):
            def kill_board(n):
                if n == 200 and started:
                    os.kill(started[0].pid, signal.SIGKILL)      # the board's process dies
            return original_run(cfg, tick_hook=kill_board, **kw)

        if __name__ == "__main__":
            emulation.start_emulator, run_mod.run = start, run
    """)
    res = subprocess.run([sys.executable, str(script), "run", str(REPO / "configs" / "serial-virtual.toml"),
                          "--duration", "3", "--no-telemetry", "--no-realtime",
                          "--record", str(tmp_path / "r.parquet")],
                         cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=180)
    text = res.stdout + res.stderr
    assert res.returncode == 3, text[-3000:]
    assert "Traceback" not in text and "During handling" not in text and "direct cause" not in text
    stops = [ln for ln in res.stderr.splitlines() if ln.startswith("stopped by ")]
    assert len(stops) == 1, res.stderr
    cause = re.match(r"stopped by [\w-]+: (.*) - zero torque commanded, the disable NOT confirmed", stops[0]).group(1)
    assert text.count(cause) == 1 and "link went away" in cause     # the cause, once, and what it means
    # the stop frames could not reach a dead board: never called disabled, said once in a line of its own
    (unconfirmed,) = [ln for ln in res.stderr.splitlines() if ln.startswith("disable not confirmed")]
    assert "the stop frames could not be sent" in unconfirmed
    # the final fit of the few seconds measured may warn about its own convergence: not the board's failure
    warnings = [ln for ln in res.stderr.splitlines() if ln.startswith(("WARNING", "ERROR"))
                and "rt_ident.estimators" not in ln]
    assert warnings == [], warnings


def _record_with_exception() -> logging.LogRecord:
    try:
        raise OSError(5, "Input/output error")
    except OSError:
        return logging.LogRecord("drivers.x", logging.WARNING, __file__, 1, "link lost on %s", ("/dev/pts/0",),
                                 sys.exc_info())


def test_log_lines_carry_the_exception_in_one_line_and_the_traceback_only_with_verbose(monkeypatch):
    fmt = cli._OneLineFormatter("%(levelname)s %(name)s: %(message)s")
    monkeypatch.setattr(cli, "_VERBOSE", 0)
    line = fmt.format(_record_with_exception())
    assert line == "WARNING drivers.x: link lost on /dev/pts/0: OSError: [Errno 5] Input/output error"
    monkeypatch.setattr(cli, "_VERBOSE", 1)
    full = fmt.format(_record_with_exception())
    assert full.startswith("WARNING drivers.x: link lost on /dev/pts/0\nTraceback") and "OSError" in full


@pytest.mark.parametrize("verbose", [False, True], ids=["plain", "-v"])
def test_an_unexpected_exception_is_one_internal_error_line_and_its_traceback_only_with_verbose(tmp_path, verbose):
    script = _script(tmp_path, """
        import sys
        import rt_ident.config

        def broken(*a, **k):
            raise ZeroDivisionError("a bug")

        rt_ident.config.load = broken
    """)
    args = ["-v"] * verbose + ["run", "--no-telemetry"]
    res = subprocess.run([sys.executable, str(script), *args], cwd=tmp_path, env=_env(), capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 1
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("internal error: ZeroDivisionError: a bug")
    assert ("Traceback" in res.stderr) is verbose
    if not verbose:
        assert res.stderr.strip() == last


@pytest.mark.parametrize(("raised", "code", "says"), [
    ("OSError(errno.ENOSPC, 'No space left on device')", 4, "No space left on device: what this command was writing "
                                                            "is incomplete; make room (or write elsewhere)"),
    ("OSError(errno.EROFS, 'Read-only file system', '/mnt/ro/out')", 4, "/mnt/ro/out: Read-only file system: what "
                                                                       "this command was writing is incomplete; write "
                                                                       "elsewhere"),
    ("PermissionError(errno.EACCES, 'Permission denied', '/etc/x')", 2, "/etc/x: Permission denied: this user may "
                                                                       "not do that there"),
    ("NotADirectoryError(errno.ENOTDIR, 'Not a directory', '/tmp/a-file/data')", 2, "/tmp/a-file/data: Not a "
                                                                                    "directory: a file where a folder "
                                                                                    "was meant"),
    ("OSError(errno.EBADF, 'Bad file descriptor')", 1, "internal error: OSError: [Errno 9] Bad file descriptor"),
], ids=["full", "read-only", "permission", "not-a-folder", "other"])
def test_a_full_disk_or_a_refused_permission_is_one_line_naming_the_fix_not_an_internal_error(tmp_path, raised, code,
                                                                                                says):
    script = _script(tmp_path, f"""
        import errno
        import sys
        import rt_ident.config

        def refused(*a, **k):
            raise {raised}

        rt_ident.config.load = refused
    """)
    res = subprocess.run([sys.executable, str(script), "run", "--no-telemetry"], cwd=tmp_path, env=_env(),
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == code, res.stderr[-2000:]
    assert says in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr[-2000:]


def test_a_ctrl_c_before_the_runs_own_handler_exits_130_saying_interrupted(tmp_path):
    script = _script(tmp_path, """
        import sys
        import rt_ident.config

        def interrupted(*a, **k):
            raise KeyboardInterrupt

        rt_ident.config.load = interrupted
    """)
    res = subprocess.run([sys.executable, str(script), "run", "--no-telemetry"], cwd=tmp_path, env=_env(),
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 130 and res.stderr.strip() == "interrupted", res.stderr[-2000:]

"""Shared pytest options (``--hardware``, ``--hardware-config``) and the ``emulators`` fixture.

Tests marked ``hardware`` (marker declared in pyproject.toml) are skipped unless
``--hardware`` is given. ``--hardware-config PATH`` names a run configuration
(TOML) whose ``[backend]`` is a real device; it may be repeated or hold several
comma-separated paths. Nothing here runs at import time.
"""

from __future__ import annotations

import ctypes
import fcntl
import gc
import os
import shutil
from collections.abc import Callable
from pathlib import Path

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


def pytest_configure(config: pytest.Config) -> None:
    """The session's temporary directory (TMPDIR, inherited by the xdist workers and every process a test
    starts) is one of its own, removed at the session's end: a run a test kills with SIGKILL leaves its
    forkserver's socket directory (multiprocessing's ``pymp-*``) behind, which would pile up in /tmp.
    This process keeps its own temporary directory: multiprocessing removes its ``pymp-*`` at the interpreter's
    exit, after this directory is gone."""
    if hasattr(config, "workerinput"):
        return
    import tempfile

    mine = tempfile.gettempdir()
    own = tempfile.mkdtemp(prefix="rt-ident-tests-", dir=mine)
    config.stash[_OWN_TMP] = (own, os.environ.get("TMPDIR"))
    os.environ["TMPDIR"] = own
    tempfile.tempdir = mine


def pytest_unconfigure(config: pytest.Config) -> None:
    own, before = config.stash.get(_OWN_TMP, (None, None))
    if own is None:
        return
    import tempfile

    if before is None:
        os.environ.pop("TMPDIR", None)
    else:
        os.environ["TMPDIR"] = before
    tempfile.tempdir = None
    shutil.rmtree(own, ignore_errors=True)


_OWN_TMP = pytest.StashKey[tuple]()


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: three workers per two CPUs. A worker spends about half its time in runs paced in real
    time or waiting on processes, not on a CPU, so one per CPU leaves the CPUs half idle. The tests whose runs
    take the loop's CPU in real time (its claim, rt_ident/loop/cpu_claim.py) are marked
    ``xdist_group("realtime")``: one worker runs them one after the other, where workers running them side by
    side would queue for the claim."""
    cpus = len(os.sched_getaffinity(0))
    return max(1, cpus + cpus // 2)


def pytest_sessionstart(session: pytest.Session) -> None:
    """With xdist workers and a cold kernel cache (a fresh clone): before the workers start, one short run,
    the tick kernel's compile and the offline kernels' compile, side by side, fill numba's cache (beside the
    package). Otherwise every worker, and the helper processes of their first runs, compile them at once."""
    config = session.config
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    import subprocess
    import sys
    import tempfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    _compile_bytecode(root)
    rewrite = _rewrite_tests_once(root)
    from rt_ident import kernel_cache

    kernel_cache.sync()         # entries compiled against sources changed since are removed first
    if kernel_cache.tick_kernel_cached():
        _wait_for(rewrite)
        return                  # compiled before
    # the tick kernel (over half the compile) in one process while a run on the Python path compiles the rest
    kernel = subprocess.Popen([sys.executable, "-c", "from rt_ident.loop.tick_kernel import compiled_kernel as k; k(); "
                               "from rt_ident.loop.idle_poll import IdlePoller; IdlePoller(0).prepare()"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # the kernels no run of the loop compiles (integrators, RLS, friction), which tests in every worker use
    rest = subprocess.Popen([sys.executable, "-c", _OFFLINE_KERNELS], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    run = ("import sys; from rt_ident.config import load; from rt_ident.compose.run import run, exit_code; "
           "s = run(load(sys.argv[1], **{'loop.duration': 0.3, 'loop.realtime': False, 'loop.compiled_tick': False}),"
           " sink='off'); sys.exit(exit_code(s))")
    with tempfile.TemporaryDirectory() as tmp:
        r = subprocess.run([sys.executable, "-c", run, os.path.join(root, "configs", "sim.toml")],
                           cwd=tmp, capture_output=True, text=True, timeout=600)
    k_err = kernel.communicate(timeout=600)[1]
    rest_err = rest.communicate(timeout=600)[1]
    _wait_for(rewrite)
    for what, code, err in (("run", r.returncode, r.stderr), ("tick kernel's compile", kernel.returncode, k_err),
                            ("offline kernels' compile", rest.returncode, rest_err)):
        if code != 0:       # the tests that run the loop say why; this only fills a cache
            print(f"conftest: the cache-filling {what} exited {code}: {err.strip()[-300:]}", file=sys.stderr)


# Compiles (fills numba's cache with) the kernels of the offline paths: the five integrators, RLS in the shapes
# the tests use, the friction plant and the per-sample friction estimator.
_OFFLINE_KERNELS = """
import numpy as np
from rt_ident.axis.friction import Friction
from rt_ident.axis.integrators import INTEGRATORS, get_integrator
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import PlantSimulator
from rt_ident.estimators.friction_stream import RecursiveFrictionEstimator
from rt_ident.estimators.rls import warmup
p = thomson_x()
for name in INTEGRATORS:
    get_integrator(name).simulate(p, np.zeros(16), 1e-3)
warmup(((5, 4), (3, 1)))
PlantSimulator(p, 1e-3, friction=Friction(Fc1=0.01)).step_block(np.zeros(8))
RecursiveFrictionEstimator(1e-4).update_block(np.zeros(64), np.zeros(64), np.zeros(64))
"""


def _rewrite_tests_once(root: str):
    """Where PYTHONDONTWRITEBYTECODE keeps pytest from caching the test modules it rewrites for its asserts,
    every worker rewrites all of them while it collects (most of its collection's CPU): one collection with
    the cache allowed, beside the kernels' compile, leaves the rewritten modules for the workers to read.
    Only the modules without a cache of their current source; None when there are none."""
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    tail = f"{sys.implementation.cache_tag}-pytest-{pytest.__version__}.pyc"
    tests = Path(root, "tests")

    def stale(f: Path) -> bool:      # pytest's cache is a checked-hash pyc (PEP 552): magic, flags, source hash
        try:
            with (f.parent / "__pycache__" / f"{f.stem}.{tail}").open("rb") as pyc:
                head = pyc.read(16)
        except OSError:
            return True
        return head != importlib.util.MAGIC_NUMBER + b"\x03\0\0\0" + importlib.util.source_hash(f.read_bytes())[:8]

    todo = {str(f.parent if f.name == "conftest.py" else f)
            for f in [*tests.rglob("test_*.py"), *tests.rglob("conftest.py")] if stale(f)}
    if not todo:
        return None
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return subprocess.Popen([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                             *sorted(todo)], cwd=root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def _wait_for(rewrite) -> None:
    """The collection above finished (or given up on: the workers then rewrite for themselves)."""
    import subprocess
    import sys

    if rewrite is None:
        return
    try:
        err = rewrite.communicate(timeout=120)[1]
    except subprocess.TimeoutExpired:
        rewrite.kill()
        err = rewrite.communicate()[1]
    if rewrite.returncode != 0:
        print(f"conftest: the collection that caches the rewritten tests exited {rewrite.returncode}: "
              f"{err.strip()[-300:]}", file=sys.stderr)


def _compile_bytecode(root: str) -> None:
    """The package's bytecode written once, where PYTHONDONTWRITEBYTECODE (or ``-B``) keeps imports from
    writing it: every ``rt-ident`` the tests start, its forkserver and its emulated devices would otherwise
    compile the same sources again (about half a second of CPU each). Python still reads bytecode it finds."""
    import compileall

    for pkg in ("rt_ident", "drivers"):
        compileall.compile_dir(os.path.join(root, pkg), quiet=1, workers=1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="real device: run with --hardware (and --hardware-config PATH)")
    for item in items:
        if item.get_closest_marker("hardware") is not None:
            item.add_marker(skip)


_CHECKOUT_RUNS = Path(__file__).resolve().parent.parent / "runs"


@pytest.fixture(autouse=True)
def _nothing_left_in_the_checkouts_runs_folder():
    """A test's runs write under its own tmp_path: a run's default outputs (``runs/`` under the working
    directory) left in the checkout would pile up with every suite run. Fails the test that left one."""
    before = set(os.listdir(_CHECKOUT_RUNS)) if _CHECKOUT_RUNS.is_dir() else set()
    yield
    left = (set(os.listdir(_CHECKOUT_RUNS)) if _CHECKOUT_RUNS.is_dir() else set()) - before
    if left:
        pytest.fail(f"the test left {sorted(left)} in {_CHECKOUT_RUNS}: give its run a tmp_path "
                    "(record=..., recording.enabled = false, or monkeypatch.chdir(tmp_path))", pytrace=False)


@pytest.fixture(scope="session", autouse=True)
def _commissioning_ledger_of_the_suite(tmp_path_factory):
    """Commissioning verdicts the tests write (and every process they start) go to the suite's own folder,
    never to the host's ledger (``~/.local/state/rt_ident``, or ``$RT_IDENT_STATE_DIR``), which a real run
    on this host reads before it enables a device. A test that needs its own sets its own."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RT_IDENT_STATE_DIR", str(tmp_path_factory.mktemp("commissioning-ledger")))
        yield


@pytest.fixture(scope="session")
def made_once(tmp_path_factory, worker_id) -> Callable[[str, Callable[[Path], None]], Path]:
    """``made_once(name, make)``: a folder ``make(folder)`` fills, made by the first xdist worker that asks (under a
    lock in the workers' shared temporary folder) and used by the others as it is. For data the tests only read
    (the others would each spend the seconds of CPU making it again)."""
    root = tmp_path_factory.getbasetemp()
    root = root if worker_id == "master" else root.parent

    def get(name: str, make: Callable[[Path], None]) -> Path:
        out = root / name
        with open(root / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (root / f"{name}.done").is_file():
                shutil.rmtree(out, ignore_errors=True)      # a worker that failed while making it
                out.mkdir(parents=True)
                make(out)
                (root / f"{name}.done").touch()
        return out

    return get


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
def sighup_default():
    """SIGHUP at its default action in this process, and so in what it starts, for the test: a suite started
    under ``nohup`` would otherwise hand its runs SIGHUP ignored, the case in which a run goes on."""
    import signal

    before = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    yield
    signal.signal(signal.SIGHUP, before)


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
    libc = ctypes.CDLL(None)                 # the process's own symbols hold libc's (find_library forks ldconfig)
    libc.munlockall()
    gc.unfreeze()
    gc.enable()


def _host_made_end(stop: dict, emulator: dict | None = None) -> str | None:
    """Why the host, not the device or the product, ended a run - from the run's own evidence - or None.

    The host's: a stop whose fix names ``loop.realtime`` (the product attributes it to the host); a trip right
    after a loop stall (a drive holds its torque while the host is away); a stale run no longer than the SYNCs
    the emulated drive itself answered too late to send (its process starved: a real drive has a processor of
    its own)."""
    message = stop.get("message") or ""
    if (stop.get("fix") or "").startswith("loop.realtime"):
        return message
    if "ms loop stall)" in message:
        return message
    from rt_ident.compose.run import starved_emulator

    starved = starved_emulator(stop.get("cause"), message, emulator)
    return f"{message}; {starved}" if starved else None


@pytest.fixture
def host_made_end() -> Callable[[dict, dict | None], str | None]:
    """``host_made_end(summary["stop"], emulator_stats)``: why the host ended the run, or None (see
    :func:`_host_made_end`). A device test whose run the host ended checks the safe end, then runs again or
    skips naming the host: it cannot tell the device's behaviour from it."""
    return _host_made_end

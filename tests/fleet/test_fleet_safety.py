"""A history nothing can corrupt or escape: `fleet query` runs one SELECT over the history only, manifest paths
stay under the manifest's folder, batch files appear whole, a damaged one is skipped and named, concurrent or
repeated runs keep one row per recording, and an interrupted or stuck run keeps what finished.

One small fleet is generated per module (2 machines x 1 axis x 3 days of closed-loop runs on the simulated axis).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rt_ident.errors import ConfigError
from rt_ident.fleet.history import query
from rt_ident.fleet.identify import append_history, identify_fleet, identify_recording, known_hashes
from rt_ident.fleet.make import make_fleet
from rt_ident.fleet.manifest import Entry, read_manifest, write_manifest
from rt_ident.fleet.store import parquet_files
from tests.fleet.conftest import local_cluster

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
CLI = [sys.executable, "-m", "rt_ident"]


@pytest.fixture(scope="module")
def small_fleet(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("small-fleet")
    make_fleet(out, machines=2, axes=("x",), days=3, worn=0.0, duration=0.3, seed=5)
    return out


@pytest.fixture(scope="module")
def entries(small_fleet) -> list[Entry]:
    return read_manifest(small_fleet / "manifest.csv")


@pytest.fixture(scope="module")
def rows(entries) -> list[dict]:
    out = [identify_recording({"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time})
           for e in entries]
    assert all(r["status"] == "ok" for r in out), [r["error"] for r in out]
    return out


@pytest.fixture
def history(rows, tmp_path) -> Path:
    h = tmp_path / "history"
    assert append_history(h, rows) == len(rows)
    return h


@pytest.fixture(scope="module")
def cluster():
    """A scheduler and one worker process on 127.0.0.1 for the in-process runs."""
    yield from local_cluster(1)


def _cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, env=ENV, timeout=timeout)


def _count(h: Path) -> tuple[int, int]:
    _, [(n, distinct)] = query(h, "SELECT count(*), count(DISTINCT hash) FROM history")
    return n, distinct


# --------------------------------------------------------------------------- fleet query: one SELECT, history only
def test_query_refuses_copy_to_and_writes_no_file(history, tmp_path):
    for target in (tmp_path / "x.csv", history / "x.csv"):     # outside the history, and inside it
        with pytest.raises(ConfigError, match="SQL: refused: statement type COPY"):
            query(history, f"COPY (SELECT * FROM history) TO '{target}'")
        assert not target.exists()


def test_query_refuses_reading_etc_passwd(history):
    with pytest.raises(ConfigError, match='SQL: refused: Permission Error: Cannot access file "/etc/passwd"'):
        query(history, "SELECT * FROM read_csv('/etc/passwd', header = false, sep = ':')")


def test_query_refuses_reading_other_parquet_files_than_the_history(history, small_fleet):
    with pytest.raises(ConfigError, match="SQL: refused: Permission Error"):
        query(history, f"SELECT count(*) FROM read_parquet('{small_fleet}/recordings/*.parquet')")


def test_query_refuses_attach_and_creates_no_database(history, tmp_path):
    with pytest.raises(ConfigError, match="SQL: refused: statement type ATTACH"):
        query(history, f"ATTACH '{tmp_path}/e.db' AS e")
    with pytest.raises(ConfigError, match="SQL: refused: 2 statements"):
        query(history, f"ATTACH '{tmp_path}/e.db' AS e; CREATE TABLE e.t AS SELECT 42 x")
    assert not (tmp_path / "e.db").exists()


def test_query_refuses_install_of_an_extension(history):
    with pytest.raises(ConfigError, match="SQL: refused: statement type LOAD"):
        query(history, "INSTALL httpfs")


def test_query_refuses_two_statements(history):
    with pytest.raises(ConfigError, match="SQL: refused: 2 statements; fleet query runs exactly one SELECT"):
        query(history, "SELECT 1; SELECT 2")


def test_query_refuses_switching_external_access_back_on(history):
    with pytest.raises(ConfigError, match="SQL: refused: statement type SET"):
        query(history, "SET enable_external_access = true")


def test_query_still_runs_a_select_over_the_history(history, entries):
    cols, got = query(history, "WITH h AS (SELECT * FROM history) SELECT machine, count(*) AS n FROM h "
                               "GROUP BY machine ORDER BY machine")
    assert cols == ["machine", "n"]
    assert got == [("m01", 3), ("m02", 3)]


def test_query_refusal_on_the_command_line_is_one_line_on_stderr_and_exit_2(history, tmp_path):
    r = _cli("fleet", "query", f"COPY (SELECT * FROM history) TO '{tmp_path}/x.csv'", "--history", str(history))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "error: SQL: refused: statement type COPY; fleet query runs one SELECT and nothing else (it only reads the "
        "history)"]
    assert not (tmp_path / "x.csv").exists()


def test_a_url_history_is_queried_with_external_access_off(rows):
    url = "memory://rt-ident-fleet-safety/history"
    assert append_history(url, rows) == len(rows)
    _, [(n,)] = query(url, "SELECT count(*) FROM history")
    assert n == len(rows)
    with pytest.raises(ConfigError, match="refused: Permission Error"):
        query(url, "SELECT * FROM read_csv('/etc/passwd')")


# --------------------------------------------------------------------------- a damaged batch file
@pytest.mark.slow
def test_a_truncated_batch_file_is_skipped_with_one_line_naming_it_by_query_drift_and_identify(history, small_fleet):
    (bad,) = (f for f in parquet_files(history) if "machine=m02" in f)
    data = Path(bad).read_bytes()
    Path(bad).write_bytes(data[: len(data) // 2])
    r = _cli("fleet", "query", "SELECT count(*) AS n FROM history", "--history", str(history), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == [{"n": 3}]
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and f"skipped damaged history file {bad}" in r.stderr
    r = _cli("fleet", "drift", "--history", str(history), "--json")
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)["series"]) == 1
    assert r.stderr.count(bad) == 1 and "Traceback" not in r.stderr
    r = _cli("fleet", "identify", str(small_fleet / "manifest.csv"), "--history", str(history), "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "3 identified" in r.stdout and "3 already in the history" in r.stdout   # m02's rows were unreadable
    assert bad in r.stderr and "Traceback" not in r.stderr


# --------------------------------------------------------------------------- manifest paths
def _manifest(folder: Path, good: str, bad: str, name: str = "m.csv") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    m = folder / name
    m.write_text(f"path,machine,axis,time\n{good},m01,x,2026-11-01\n{bad},m01,x,2026-11-02\n")
    return m


@pytest.mark.parametrize("bad", ["/dev/zero", "../../outside.parquet", "/etc/passwd", "file:///etc/passwd",
                                 "OUTSIDE", "LINK", "http://127.0.0.1:9/x.parquet", "simplecache::s3://b/x.parquet"])
def test_a_manifest_path_outside_its_folder_is_refused_naming_the_line(tmp_path, small_fleet, bad):
    folder = tmp_path / "a" / "b"
    folder.mkdir(parents=True)
    good = folder / "good.parquet"
    shutil.copy(small_fleet / "recordings" / "m01-x-day000.parquet", good)
    outside = tmp_path / "outside.parquet"
    shutil.copy(good, outside)
    if bad == "OUTSIDE":
        bad = str(outside)
    elif bad == "LINK":                          # a link inside the folder to a file outside it
        os.symlink(outside, folder / "link.parquet")
        bad = "link.parquet"
    with pytest.raises(ConfigError, match=r"MANIFEST: .*m\.csv line 3: .*(outside the manifest's folder|not one of "
                                          r"the remote filesystems)"):
        read_manifest(_manifest(folder, "good.parquet", bad))


def test_a_refused_link_names_its_target_and_a_bad_time_its_manifest_and_line(tmp_path):
    folder = tmp_path / "m"
    folder.mkdir()
    os.symlink("/etc/passwd", folder / "link.parquet")
    with pytest.raises(ConfigError) as err:
        read_manifest(_manifest(folder, "missing-yet.parquet", "link.parquet"))
    assert str(err.value) == (f"MANIFEST: {folder / 'm.csv'} line 3: link.parquet (a link to /etc/passwd) is outside "
                              f"the manifest's folder {folder.resolve()} (--allow-outside reads it)")
    with pytest.raises(ConfigError, match=r"line 3: \.\./elsewhere\.parquet is outside"):   # no link named
        read_manifest(_manifest(folder, "missing-yet.parquet", "../elsewhere.parquet"))
    m = folder / "t.csv"
    m.write_text("path,machine,axis,time\na.parquet,m01,x,2026-11-01\na.parquet,m01,x,yesterday\n")
    with pytest.raises(ConfigError) as err:
        read_manifest(m)
    assert str(err.value) == f"MANIFEST: {m} line 3: time: 'yesterday' is not ISO 8601 (e.g. 2026-11-24 or " \
                             "2026-11-24T06:00:00)"


def test_allow_outside_reads_a_file_elsewhere_but_never_a_device_a_folder_or_a_pipe(tmp_path, small_fleet):
    outside = tmp_path / "outside.parquet"
    shutil.copy(small_fleet / "recordings" / "m01-x-day000.parquet", outside)
    folder = tmp_path / "m"
    m = _manifest(folder, str(outside), str(outside))
    assert [e.path for e in read_manifest(m, allow_outside=True)] == [str(outside.resolve())] * 2
    os.mkfifo(folder / "pipe")
    (folder / "sub").mkdir()
    for bad in ("/dev/zero", "pipe", "sub"):
        with pytest.raises(ConfigError, match=r"line 3: .* is not a regular file"):
            read_manifest(_manifest(folder, str(outside), bad), allow_outside=True)
    for bad in ("pipe", "sub"):                 # inside the folder, without the flag
        with pytest.raises(ConfigError, match=r"line 3: .* is not a regular file"):
            read_manifest(_manifest(folder, "missing-yet.parquet", bad))


def test_a_remote_url_in_a_manifest_is_kept_as_written(tmp_path):
    m = _manifest(tmp_path, "s3://plant/rec/a.parquet", "gs://plant/rec/b.parquet")
    assert [e.path for e in read_manifest(m)] == ["s3://plant/rec/a.parquet", "gs://plant/rec/b.parquet"]


def test_identify_refuses_dev_zero_up_front_in_one_line(tmp_path, small_fleet):
    m = _manifest(small_fleet, "recordings/m01-x-day000.parquet", "/dev/zero", name="dev-zero.csv")
    r = _cli("fleet", "identify", str(m), "--history", str(tmp_path / "h"), timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"error: MANIFEST: {m} line 3: /dev/zero is outside the manifest's folder {m.parent} (--allow-outside "
        "reads it)"]
    r = _cli("fleet", "identify", str(m), "--history", str(tmp_path / "h"), "--allow-outside", timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"error: MANIFEST: {m} line 3: /dev/zero is not a regular file (a device, folder or pipe is never read)"]
    assert not (tmp_path / "h").exists()


def test_a_task_given_a_device_fails_at_once_instead_of_reading_it_forever():
    t0 = time.monotonic()
    row = identify_recording({"path": "/dev/zero", "machine": "m01", "axis": "x", "time": None})
    assert row["status"] == "failed" and "/dev/zero is not a regular file" in row["error"]
    assert time.monotonic() - t0 < 5


# --------------------------------------------------------------------------- whole files, one row per recording
def test_a_batch_file_is_written_under_a_hidden_name_and_renamed_into_place(rows, tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    import rt_ident.fleet.store as store

    seen = []
    real = os.replace

    def replace(src, dst):
        pq.read_metadata(src)                   # complete before it gets its name
        seen.append((Path(src), Path(dst), Path(dst).exists()))
        real(src, dst)

    monkeypatch.setattr(store.os, "replace", replace)
    append_history(tmp_path / "h", rows)
    assert len(seen) == 2                       # one file per machine
    for src, dst, existed in seen:
        assert src.parent == dst.parent and src.name.startswith(".") and src.name.endswith(".tmp")
        assert dst.suffix == ".parquet" and not existed
    assert sorted(str(d) for _, d, _ in seen) == parquet_files(tmp_path / "h")
    assert not list((tmp_path / "h").rglob("*.tmp"))


def test_a_write_that_fails_midway_leaves_no_file_a_reader_sees(rows, tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    def half_then_fail(table, where, **kw):
        where.write(b"PAR1 half a file")
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        append_history(tmp_path / "h", rows)
    assert parquet_files(tmp_path / "h") == [] and not list((tmp_path / "h").rglob("*.tmp"))


def test_append_history_keeps_one_row_per_recording_across_calls_and_within_one(rows, tmp_path):
    assert append_history(tmp_path / "h", rows) == 6
    assert append_history(tmp_path / "h", rows) == 0
    assert append_history(tmp_path / "h2", rows + rows[:2]) == 6
    assert _count(tmp_path / "h") == _count(tmp_path / "h2") == (6, 6)


@pytest.mark.slow
def test_two_concurrent_identify_runs_leave_one_row_per_recording(small_fleet, tmp_path):
    h = tmp_path / "h"
    args = [*CLI, "fleet", "identify", str(small_fleet / "manifest.csv"), "--history", str(h), "--workers", "1",
            "--flush-every", "0.1"]
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
             for _ in range(2)]
    outs = [p.communicate(timeout=180) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert _count(h) == (6, 6)
    identified = [int(o.split(" identified")[0]) for o, _ in outs]
    assert sum(identified) == 6, outs


def test_a_duplicated_manifest_line_and_a_copied_recording_give_one_row_each(small_fleet, tmp_path):
    shutil.copy(small_fleet / "recordings" / "m01-x-day000.parquet", small_fleet / "copy-of-day000.parquet")
    lines = (small_fleet / "manifest.csv").read_text().splitlines()
    m = small_fleet / "duplicates.csv"
    m.write_text("\n".join([*lines, lines[1], "copy-of-day000.parquet,m01,x,2026-11-09"]) + "\n")
    r = _cli("fleet", "identify", str(m), "--history", str(tmp_path / "h"), "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "6 identified" in r.stdout and "1 listed more than once" in r.stdout
    assert _count(tmp_path / "h") == (6, 6)


# --------------------------------------------------------------------------- interrupted, stuck
def test_finished_results_are_written_while_the_run_goes_on(entries, cluster, tmp_path):
    h = tmp_path / "h"
    on_disk = []

    def slow_reader(row):                       # time passes between results, as with long recordings
        time.sleep(0.3)
        on_disk.append(len(known_hashes(h)))

    res = identify_fleet(entries, h, scheduler=cluster.scheduler_address, flush_every=0.1, on_result=slow_reader)
    assert res["identified"] == 6
    assert on_disk == [0, 1, 2, 3, 4, 5]        # each result written before the next was taken


def test_an_interrupt_keeps_what_finished(entries, cluster, tmp_path):
    h = tmp_path / "h"
    seen = []

    def ctrl_c_at_the_second(row):
        seen.append(row)
        if len(seen) == 2:
            raise KeyboardInterrupt

    res = identify_fleet(entries, h, scheduler=cluster.scheduler_address, flush_every=3600,
                         on_result=ctrl_c_at_the_second)
    assert res["interrupted"] and res["identified"] == len(seen) >= 2     # no periodic write: the interrupt's
    assert len(known_hashes(h)) == res["identified"]


def test_a_history_that_refuses_a_write_ends_the_run_keeping_what_was_written_before(entries, cluster, tmp_path,
                                                                                     monkeypatch):
    import errno

    import rt_ident.fleet.identify as ident

    h = tmp_path / "h"
    real_write, writes = ident.write_rows, []

    def fill_up(history, table):                # the disk is full from the second write on
        writes.append(table.num_rows)
        if len(writes) > 1:
            raise OSError(errno.ENOSPC, "No space left on device", str(history))
        return real_write(history, table)

    monkeypatch.setattr(ident, "write_rows", fill_up)
    res = identify_fleet(entries, h, scheduler=cluster.scheduler_address, flush_every=0.05,
                         on_result=lambda row: time.sleep(0.2))
    assert res["write_error"] == f"{h}: No space left on device" and not res["interrupted"]
    assert res["identified"] == writes[0] == len(known_hashes(h)) >= 1
    assert res["unwritten"] >= 1 and res["identified"] + res["unwritten"] <= res["tasks"]


def test_the_command_line_says_what_the_refused_history_kept_and_exits_4(monkeypatch, tmp_path):
    import rt_ident.fleet.identify as ident
    from rt_ident.cli import app

    res = {"tasks": 6, "identified": 2, "untrusted": 0, "skipped": 0, "failed": 0, "duplicates": 0, "unwritten": 1,
           "interrupted": False, "write_error": "/h: No space left on device", "failures": [], "history": "/h",
           "dashboard": None, "scheduler": "LocalCluster on 127.0.0.1"}
    monkeypatch.setattr(ident, "identify_fleet", lambda *a, **k: res)
    monkeypatch.setattr("rt_ident.fleet.manifest.read_manifest", lambda *a, **k: [])
    r = CliRunner().invoke(app, ["fleet", "identify", str(tmp_path / "m.csv"), "--history", str(tmp_path / "h")])
    assert r.exit_code == 4, r.output
    assert ("cannot write to the history: /h: No space left on device; the 2 results written before are in /h, "
            "1 finished results could not be kept; make room and run the same command again to identify the "
            "other 4") in " ".join(r.output.split())


def _huge_sparse(folder: Path) -> Path:
    """A regular file whose hashing takes long (zeros, no disk used): a task that is still running."""
    p = folder / "huge.parquet"
    with open(p, "wb") as fh:
        fh.truncate(64 << 30)
    return p


def _with_huge(entries: list[Entry], folder: Path) -> Path:
    m = folder / "m.csv"
    write_manifest(m, [*entries, Entry(str(_huge_sparse(folder)), "m09", "x", entries[0].time)])
    return m


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.slow
def test_ctrl_c_or_sigterm_ends_a_run_with_130_and_keeps_what_finished_even_started_ignoring_ctrl_c(entries, tmp_path,
                                                                                                   sig):
    h = tmp_path / "h"
    m = _with_huge(entries, tmp_path)
    # started as a shell script starts a background job (SIGINT ignored, which Python keeps): the run stops on it
    # all the same, as `rt-ident run` does, not only when the signal happens to land during a write
    ignoring = [sys.executable, "-c", "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                "os.execv(sys.executable, [sys.executable, '-m', 'rt_ident', *sys.argv[1:]])"]
    p = subprocess.Popen([*ignoring, "fleet", "identify", str(m), "--history", str(h), "--allow-outside",
                          "--flush-every", "0.2", "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=ENV, start_new_session=True)
    try:
        t0 = time.monotonic()
        while not parquet_files(h) and time.monotonic() - t0 < 120 and p.poll() is None:
            time.sleep(0.05)
        assert parquet_files(h), "no result was written"
        time.sleep(0.5)                         # not only while a write holds the signals
        if sig == signal.SIGINT:
            os.killpg(p.pid, sig)               # Ctrl-C in a terminal reaches the whole process group
        else:
            p.send_signal(sig)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    n = len(known_hashes(h))
    assert 1 <= n <= 6
    assert f"interrupted: the {n} results finished are in {h}" in err and "Traceback" not in err
    assert "run the same command again to identify the other" in err          # the huge one at least is left


@pytest.mark.slow
def test_a_task_over_its_timeout_fails_with_a_message_and_the_run_ends(entries, history, tmp_path):
    # the two recordings are in the history already: their tasks only hash a small file, well within a timeout
    # short enough that the huge one's hashing (CPU-bound) is cut after seconds
    m = _with_huge(entries[:2], tmp_path)
    t0 = time.monotonic()
    r = _cli("fleet", "identify", str(m), "--history", str(history), "--allow-outside", "--workers", "1",
             "--task-timeout", "4")
    assert r.returncode == 1, r.stderr
    assert "0 identified" in r.stdout and "2 already in the" in r.stdout and "1 failed" in r.stdout, r.stdout
    assert f"failed: {tmp_path / 'huge.parquet'} (m09 x): timed out after 4 s (--task-timeout)" in r.stdout
    assert time.monotonic() - t0 < 120 and "Traceback" not in r.stderr


def test_identify_recording_returns_failed_when_its_work_overruns_the_timeout(entries, monkeypatch):
    import rt_ident.reports.identify as ident

    monkeypatch.setattr(ident, "identify_file", lambda *a, **k: time.sleep(3))
    e = entries[0]
    t0 = time.monotonic()
    row = identify_recording({"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time}, timeout=0.3)
    assert row["status"] == "failed" and row["error"].startswith("timed out after 0.3 s")
    assert row["path"] == e.path and time.monotonic() - t0 < 2


def test_a_recording_left_unclosed_points_to_its_journal_and_a_missing_one_says_so(entries, tmp_path):
    import shutil

    e = entries[0]
    crashed = tmp_path / "crashed.parquet"
    shutil.copy(e.path, tmp_path / "crashed.parquet.arrows")     # a journal stands beside no .parquet
    row = identify_recording({"path": str(crashed), "machine": e.machine, "axis": e.axis, "time": e.time})
    assert row["status"] == "failed", row
    assert row["error"] == ("DataError: not closed: only its journal crashed.parquet.arrows is there (a run that "
                            "crashed, or one still recording); list crashed.parquet.arrows in the manifest to "
                            "identify what it flushed"), row["error"]
    row = identify_recording({"path": str(tmp_path / "gone.parquet"), "machine": e.machine, "axis": e.axis,
                              "time": e.time})
    assert row["status"] == "failed" and row["error"] == "DataError: no such file", row["error"]


def test_a_task_timed_out_while_hashing_stops_reading_the_file(tmp_path):
    import threading

    huge = _huge_sparse(tmp_path)
    row = identify_recording({"path": str(huge), "machine": "m09", "axis": "x", "time": None}, timeout=0.3)
    assert row["status"] == "failed" and row["error"].startswith("timed out after 0.3 s")
    t0 = time.monotonic()
    while any(t.name == "identify huge.parquet" for t in threading.enumerate()) and time.monotonic() - t0 < 5:
        time.sleep(0.05)
    assert not any(t.name == "identify huge.parquet" for t in threading.enumerate())


def test_a_ctrl_c_during_the_last_write_keeps_what_it_wrote_and_the_run_returns_interrupted(entries, cluster, tmp_path,
                                                                                         monkeypatch):
    import rt_ident.fleet.identify as ident

    real = ident._append

    def append_then_ctrl_c(*args, **kwargs):
        written = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)      # delivered while the write's signals are held
        return written

    monkeypatch.setattr(ident, "_append", append_then_ctrl_c)
    h = tmp_path / "h"
    res = identify_fleet(entries[:2], h, scheduler=cluster.scheduler_address, flush_every=600)   # one write, the last
    assert res["interrupted"] is True and res["identified"] == 2
    assert len(known_hashes(h)) == 2


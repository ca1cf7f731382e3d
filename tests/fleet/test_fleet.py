"""The fleet: recordings identified on a real dask.distributed cluster on 127.0.0.1, the Parquet
history, re-runs that compute nothing twice, a corrupt recording among good ones, drift alarms on known wear,
DuckDB queries, and the command line end to end.

One small fleet is generated once per session by ``tools/make_fleet.py`` (closed-loop runs of the product on the
simulated axis): 2 machines x 1 axis x 10 days, one series wearing (K -0.5 %/day, B +2 %/day).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rt_ident.errors import ConfigError
from rt_ident.fleet.drift import drift
from rt_ident.fleet.history import query
from rt_ident.fleet.identify import PARAMS, identify_fleet, identify_recording
from rt_ident.fleet.manifest import read_manifest
from tests.fleet.conftest import local_cluster

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import make_fleet  # noqa: E402


def _make(out: Path) -> None:
    assert make_fleet.main([str(out), "--machines", "2", "--axes", "x", "--days", "10", "--worn", "0.5",
                            "--duration", "0.35", "--seed", "3"]) == 0


@pytest.fixture(scope="module")
def fleet(made_once) -> Path:
    """Read only: made once for all the workers."""
    return made_once("two-machine-fleet", _make)


@pytest.fixture(scope="module")
def cluster():
    """A real scheduler and two worker processes, confined to 127.0.0.1."""
    yield from local_cluster(2)


def _truth(fleet: Path) -> dict:
    return json.loads((fleet / "truth.json").read_text())


@pytest.mark.slow
def test_results_on_a_real_scheduler_with_two_workers_equal_a_serial_run(fleet, cluster, tmp_path):
    from distributed import Client

    with Client(cluster.scheduler_address) as client:
        info = client.scheduler_info()
        addresses = [cluster.scheduler_address, *info["workers"]]
        assert len(info["workers"]) == 2
    assert all(a.startswith("tcp://127.0.0.1:") for a in addresses), addresses
    entries = read_manifest(fleet / "manifest.csv")
    res = identify_fleet(entries, tmp_path / "h", scheduler=cluster.scheduler_address)
    assert res["identified"] == len(entries) == 20 and res["failed"] == 0
    cols, rows = query(tmp_path / "h", "SELECT path, " + ", ".join(PARAMS) + " FROM history")
    dist = {r[0]: r[1:] for r in rows}
    for e in entries:
        serial = identify_recording({"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time})
        assert serial["status"] == "ok", serial["error"]
        assert dist[e.path] == tuple(serial[k] for k in PARAMS)      # bit for bit: same code, same data


def test_rerunning_a_manifest_identifies_nothing_twice(fleet, cluster, tmp_path):
    entries = read_manifest(fleet / "manifest.csv")[:6]
    first = identify_fleet(entries, tmp_path / "h", scheduler=cluster.scheduler_address)
    again = identify_fleet(entries, tmp_path / "h", scheduler=cluster.scheduler_address)
    assert first["identified"] == 6 and again["identified"] == 0 and again["skipped"] == 6
    _, [(n,)] = query(tmp_path / "h", "SELECT count(*) FROM history")
    assert n == 6


def test_a_corrupt_recording_is_reported_and_the_others_succeed(fleet, cluster, tmp_path):
    entries = read_manifest(fleet / "manifest.csv")[:4]
    bad = tmp_path / "broken.parquet"
    bad.write_bytes(b"PAR1 this is not a parquet file")
    from rt_ident.fleet.manifest import Entry

    entries.append(Entry(str(bad), "m09", "x", entries[0].time))
    res = identify_fleet(entries, tmp_path / "h", scheduler=cluster.scheduler_address)
    assert res["identified"] == 4 and res["failed"] == 1
    (f,) = res["failures"]
    assert f["path"] == str(bad) and f["machine"] == "m09" and f["error"]


def test_drift_flags_the_worn_series_and_no_healthy_one(fleet, cluster, tmp_path):
    res = identify_fleet(read_manifest(fleet / "manifest.csv"), tmp_path / "h", scheduler=cluster.scheduler_address)
    assert res["failed"] == 0
    out = drift(tmp_path / "h")
    truth = _truth(fleet)
    worn = {(s["machine"], s["axis"]) for s in truth["series"] if s["worn"]}
    flagged = {(a["machine"], a["axis"]) for a in out["alarms"]}
    assert worn and flagged == worn, (out["alarms"], truth["series"])
    onset = {(s["machine"], s["axis"]): s["onset_day"] for s in truth["series"]}
    for a in out["alarms"]:                     # never before the wear began
        assert a["recordings_before"] >= onset[(a["machine"], a["axis"])]
    assert out["checked"] == 2 * 6


def test_manifest_errors_name_the_line():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.csv"
        p.write_text("path,machine,time\nx.parquet,m1,2026-11-01\n")
        with pytest.raises(ConfigError, match="lacks axis"):
            read_manifest(p)
        p.write_text("path,machine,axis,time\nx.parquet,m1,x,yesterday\n")
        with pytest.raises(ConfigError, match="line 2.*ISO 8601"):
            read_manifest(p)


def test_bad_sql_is_one_line_and_an_empty_history_is_refused(fleet, tmp_path):
    with pytest.raises(ConfigError, match="no fleet history"):
        query(tmp_path, "SELECT 1")


@pytest.mark.slow
def test_command_line_identify_drift_report_query_end_to_end(fleet, tmp_path):
    m = fleet / "manifest.csv"          # its recordings lie under its folder, as identify requires
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cli = [sys.executable, "-m", "rt_ident"]
    r = subprocess.run([*cli, "fleet", "identify", str(m), "--history", str(tmp_path / "h"), "--workers", "2"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "20 identified" in r.stdout and "tcp://" not in r.stderr      # the scheduler's INFO lines stay quiet
    r = subprocess.run([*cli, "fleet", "drift", "--history", str(tmp_path / "h"), "--json"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["checked"] == 12 and {a["machine"] for a in d["alarms"]} == {
        s["machine"] for s in _truth(fleet)["series"] if s["worn"]}
    r = subprocess.run([*cli, "fleet", "report", "--history", str(tmp_path / "h"), "--out", str(tmp_path / "rep")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "rep" / "report.html").stat().st_size > 20_000
    rows = (tmp_path / "rep" / "fleet.csv").read_text().splitlines()
    assert rows[1].split(",")[2] == "drifting"                # worst first: the worn series heads the table
    assert len(list((tmp_path / "rep" / "data").glob("m*-x.csv"))) == 2
    r = subprocess.run([*cli, "fleet", "query", "SELECT count(*) AS n FROM history", "--history",
                        str(tmp_path / "h"), "--json"], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0 and json.loads(r.stdout) == [{"n": 20}]
    r = subprocess.run([*cli, "fleet", "query", "SELECT nope FROM history", "--history", str(tmp_path / "h")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2 and "error" in r.stderr and len(r.stderr.strip().splitlines()) <= 3


def test_the_history_can_live_behind_an_fsspec_url(fleet, cluster):
    """Object storage through fsspec (here its in-memory filesystem): written by pyarrow, read by DuckDB."""
    url = "memory://rt-ident-fleet-test/history"
    entries = read_manifest(fleet / "manifest.csv")[:5]
    res = identify_fleet(entries, url, scheduler=cluster.scheduler_address)
    assert res["identified"] == 5
    again = identify_fleet(entries, url, scheduler=cluster.scheduler_address)
    assert again["skipped"] == 5 and again["identified"] == 0
    _, [(n, machines)] = query(url, "SELECT count(*), count(DISTINCT machine) FROM history")
    assert (n, machines) == (5, 1)


# --------------------------------------------------------------------------- the verdict in the history
def _misreport_lead(src: Path, dst: Path) -> Path:
    """A copy of a recording whose table scale was converted with twice the lead (an untrusted fit)."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    t = pq.read_table(src)
    md = dict(t.schema.metadata)
    meta = json.loads(md[b"rt_ident.metadata"])
    meta["axis"]["lead"] *= 2.0
    md[b"rt_ident.metadata"] = json.dumps(meta).encode()
    t = t.set_column(t.schema.get_field_index("theta2"), "theta2", pc.divide(t.column("theta2"), 2.0))
    pq.write_table(t.replace_schema_metadata(md), dst)
    return dst


def _rows(entries, **over) -> list:
    return [identify_recording({"path": str(over.get(e.path, e.path)), "machine": e.machine, "axis": e.axis,
                                "time": e.time}) for e in entries]


def test_every_history_row_records_its_verdict_and_its_reasons(fleet, tmp_path):
    from rt_ident.fleet.identify import append_history

    good, other = read_manifest(fleet / "manifest.csv")[:2]
    bad = _misreport_lead(Path(other.path), tmp_path / "lead2.parquet")
    rows = _rows([good, other], **{other.path: bad})
    assert append_history(tmp_path / "h", rows) == 2
    _, got = query(tmp_path / "h", "SELECT path, trusted, reasons, trust_criteria FROM history ORDER BY time")
    (p1, t1, r1, c1), (p2, t2, r2, c2) = got
    assert p1 == good.path and t1 is True and r1 == []
    assert all(c["passed"] for c in json.loads(c1)) and len(json.loads(c1)) >= 5
    assert p2 == str(bad) and t2 is False and r2 and any("interval" in w for w in r2)
    failed = [c for c in json.loads(c2) if not c["passed"]]
    assert failed and all(c["why"] for c in failed)


def test_drift_ignores_untrusted_rows_and_says_how_many(fleet, tmp_path):
    from rt_ident.fleet.identify import append_history

    entries = [e for e in read_manifest(fleet / "manifest.csv") if e.machine == "m01"]     # the healthy series
    swap = {e.path: _misreport_lead(Path(e.path), tmp_path / f"bad{i}.parquet")
            for i, e in enumerate(entries) if i in (6, 8)}
    rows = _rows(entries, **swap)
    assert [r["trusted"] for r in rows].count(False) == 2
    append_history(tmp_path / "h", rows)
    out = drift(tmp_path / "h")
    assert out["alarms"] == [], out["alarms"]          # the two wild (untrusted) fits raise no alarm
    assert out["ignored"] == {"untrusted": 2, "unknown_verdict": 0}
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "rt_ident", "fleet", "drift", "--history", str(tmp_path / "h")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "skipped 2 rows: 2 not trusted" in r.stdout


def test_an_old_history_without_verdict_columns_reads_as_unknown_verdicts_and_is_identified_again(fleet, tmp_path):
    import pyarrow.parquet as pq

    from rt_ident.fleet.identify import append_history, known_hashes

    entries = [e for e in read_manifest(fleet / "manifest.csv") if e.machine == "m01"]
    append_history(tmp_path / "h", _rows(entries))
    for f in (tmp_path / "h").glob("**/*.parquet"):          # as an older rt-ident wrote it
        t = pq.read_table(f)
        pq.write_table(t.drop_columns(["reasons", "trust_criteria"]), f)
    _, [(n,)] = query(tmp_path / "h", "SELECT count(*) FROM history")
    assert n == len(entries)
    out = drift(tmp_path / "h")
    assert out["ignored"] == {"untrusted": 0, "unknown_verdict": len(entries)} and out["alarms"] == []
    assert known_hashes(tmp_path / "h") == frozenset()          # identified again, with a verdict, next run
    append_history(tmp_path / "h", _rows(entries))
    out = drift(tmp_path / "h")
    assert out["ignored"] == {"untrusted": 0, "unknown_verdict": 0}
    assert len(known_hashes(tmp_path / "h")) == len(entries)


def test_query_results_too_wide_for_the_terminal_print_one_block_per_row_and_narrow_ones_a_table():
    """A squeezed rich table shows ``SELECT *`` over the history's columns as empty cells at 80 characters."""
    import io

    from rich.console import Console

    from rt_ident.fleet.commands import print_rows

    wide_cols = [f"column_{i}" for i in range(30)]
    text = io.StringIO()
    print_rows(Console(file=text, width=80), wide_cols, [tuple(float(i) + 0.5 for i in range(30)), tuple(range(30))])
    lines = text.getvalue().splitlines()
    assert lines[0] == "-- row 1 --" and lines[-1] == "(2 rows)"
    assert "column_29  29.5" in lines and "column_0   0" in lines
    assert max(len(x) for x in lines) <= 80
    text = io.StringIO()
    print_rows(Console(file=text, width=80), ["machine", "n"], [("m01", 3)])
    assert text.getvalue().splitlines()[1:4:2] == ["┃ machine ┃ n ┃", "│ m01     │ 3 │"]

"""The fleet generator as a command of the package (``rt-ident fleet make``, ``python -m rt_ident.fleet.make``),
and help texts that say which commands only read the history."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import typer

from rt_ident.fleet.make import make_cmd

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=120)


def test_every_option_of_fleet_make_has_a_help_text():
    app = typer.Typer(add_completion=False)
    app.command()(make_cmd)
    params = typer.main.get_command(app).params
    assert {p.name for p in params} == {"out", "machines", "axes", "days", "worn", "duration", "seed", "start", "wear"}
    for p in params:
        assert len(getattr(p, "help", "") or "") > 20, p.name


def test_python_m_rt_ident_fleet_make_writes_a_fleet_from_any_folder(tmp_path):
    r = _run("-m", "rt_ident.fleet.make", "fleet", "--machines", "1", "--axes", "x", "--days", "2",
             "--duration", "0.1", "--seed", "2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "2 recordings of 1 series" in r.stdout
    lines = (tmp_path / "fleet" / "manifest.csv").read_text().splitlines()
    assert lines[0] == "path,machine,axis,time" and len(lines) == 3
    assert all((tmp_path / "fleet" / ln.split(",")[0]).is_file() for ln in lines[1:])
    assert len(json.loads((tmp_path / "fleet" / "truth.json").read_text())["series"]) == 1


def test_fleet_make_help_lists_every_option_from_both_entries(tmp_path):
    for args in (["-m", "rt_ident", "fleet", "make", "--help"], ["-m", "rt_ident.fleet.make", "--help"],
                 [str(ROOT / "tools" / "make_fleet.py"), "--help"]):
        r = _run(*args, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        for opt in ("--machines", "--axes", "--days", "--worn", "--duration", "--seed", "--start"):
            assert opt in r.stdout, (args, opt)


def test_a_bad_make_option_is_one_line_and_exit_2(tmp_path):
    r = _run("-m", "rt_ident.fleet.make", "fleet", "--start", "yesterday", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip() == "error: --start: 'yesterday' is not an ISO 8601 date such as 2026-11-01"


def test_read_only_commands_say_they_only_read_the_history_and_identify_says_it_creates_it(tmp_path):
    for cmd in ("query", "drift", "report"):
        r = _run("-m", "rt_ident", "fleet", cmd, "--help", cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        text = " ".join(r.stdout.split())
        assert "created if missing" not in text and "only read, never written" in text, cmd
    r = _run("-m", "rt_ident", "fleet", "identify", "--help", cwd=tmp_path)
    assert "created if missing" in " ".join(r.stdout.split())


def test_an_axis_name_that_is_a_path_writes_its_recordings_inside_the_fleet_folder(tmp_path):
    from rt_ident.fleet.make import make_fleet
    from rt_ident.fleet.manifest import read_manifest

    out = tmp_path / "fleet" / "a"
    make_fleet(out, machines=1, axes=("x", "../../../../escaped"), days=1, worn=0.0, duration=0.2, seed=1)
    files = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert all(p.parts[:2] == ("fleet", "a") for p in files), files
    assert (out / "recordings" / "m01-x-day000.parquet").is_file()             # a plain name keeps its file name
    assert sorted(e.axis for e in read_manifest(out / "manifest.csv")) == ["../../../../escaped", "x"]

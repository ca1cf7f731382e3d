"""``fleet report``: one self-contained HTML page - the fleet worst first with the right findings, trend plots
whose intervals stay inside the axes and whose first alarm is marked and in the legend, the CSV data beside it -
and no file outside ``--out`` whatever the machine is called."""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rt_ident.cli import app
from rt_ident.fleet.report import write_report

ROOT = Path(__file__).resolve().parents[2]
SVG = "{http://www.w3.org/2000/svg}"


class _Tables(HTMLParser):
    """Every table of a page as rows of cell texts."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append([])
        elif tag == "tr" and self.tables:
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def _tables(html: str) -> list[list[list[str]]]:
    p = _Tables()
    p.feed(html)
    return p.tables


def _svgs(html: str) -> list[ET.Element]:
    return [ET.fromstring(m) for m in re.findall(r"<svg .*?</svg>", html, flags=re.S)]


@pytest.fixture(scope="module")
def report(wear_fleet, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("report") / "out"
    res = write_report(wear_fleet.history(out.parent / "h"), out)
    return out, Path(res["html"]).read_text(encoding="utf-8")


def test_the_fleet_table_puts_the_worn_series_on_top_by_severity_with_their_findings(wear_fleet, report):
    out, html = report
    head, *rows = _tables(html)[0]
    col = {c: head.index(c) for c in ("machine", "state", "severity")}
    col["finding"] = next(i for i, c in enumerate(head) if c.startswith("finding"))
    order = [r[col["machine"]] for r in rows]
    expect = {wear_fleet.kind("k")[0]: "stiffness loss", wear_fleet.kind("b")[0]: "lubrication",
              wear_fleet.kind("load")[0]: "heavier load"}
    assert set(order[:3]) == set(expect) and order[3] == wear_fleet.kind(None)[0]
    rank = ["critical", "high", "medium", "low", "-"]
    sev = [r[col["severity"]] for r in rows]
    assert sev == sorted(sev, key=rank.index) and sev[0] == "critical"
    for r in rows[:3]:
        assert r[col["state"]] == "drifting" and expect[r[col["machine"]]] in r[col["finding"]]
    assert rows[3][col["state"]] == "ok"
    with open(out / "fleet.csv", newline="", encoding="utf-8") as fh:
        assert [r["machine"] for r in csv.DictReader(fh)] == order       # the CSV beside it, same order


def test_every_interval_and_estimate_lies_inside_its_plots_axes(report):
    _, html = report
    svgs = _svgs(html)
    assert len(svgs) == 4 * 6
    n = 0
    for svg in svgs:
        frame = svg.find(f"{SVG}rect[@class='frame']")
        top, bottom = float(frame.get("y")), float(frame.get("y")) + float(frame.get("height"))
        for line in svg.findall(f"{SVG}line[@class='interval']"):
            assert top <= float(line.get("y1")) <= bottom and top <= float(line.get("y2")) <= bottom
            n += 1
        for dot in svg.findall(f"{SVG}circle[@class='point']"):
            assert top <= float(dot.get("cy")) <= bottom
    assert n == 4 * 6 * 10                          # every recording drawn with its interval


def test_each_alarmed_plot_marks_the_first_alarm_and_names_it_in_the_legend(wear_fleet, report):
    from rt_ident.fleet.drift import drift

    _, html = report
    n_alarms = len(drift(report[0].parent / "h")["alarms"])
    alarmed = [s for s in _svgs(html) if "ALARM" in "".join(s.itertext())]
    assert len(alarmed) == n_alarms >= 3
    for svg in alarmed:
        legend = " | ".join(svg.find(f"{SVG}g[@class='legend']").itertext())
        assert "first alarm 2026-" in legend, legend
        assert svg.findall(f"{SVG}line[@class='event']")
    calm = [s for s in _svgs(html) if "ALARM" not in "".join(s.itertext())]
    assert all("first alarm" not in "".join(s.itertext()) for s in calm)


def test_the_page_is_self_contained_and_links_only_the_csv_files_beside_it(report):
    out, html = report
    assert "<script" not in html and "<img" not in html and "http://" not in html.replace(
        "http://www.w3.org/2000/svg", "") and "https://" not in html
    links = set(re.findall(r"href='([^'#][^']*)'", html))
    assert "fleet.csv" in links and len(links) == 1 + 4
    assert all((out / link).is_file() for link in links)


def test_the_series_csv_holds_every_recording_with_its_estimate_and_change(wear_fleet, report):
    out, html = report
    key = wear_fleet.kind("k")
    rows = wear_fleet.series_rows(key)
    with open(out / "data" / f"{key[0]}-{key[1]}.csv", newline="", encoding="utf-8") as fh:
        got = list(csv.DictReader(fh))
    assert [float(r["K"]) for r in got] == pytest.approx([r["K"] for r in rows], rel=1e-8)
    mu0 = sum(r["K"] for r in rows[:5]) / 5
    assert float(got[-1]["K_change_percent"]) == pytest.approx(100 * (rows[-1]["K"] / mu0 - 1), abs=1e-6)
    assert float(got[-1]["K_cusum_minus"]) > 5.0 and all(r["trusted"] == "True" for r in got)


def test_a_machine_named_dot_dot_slash_writes_nothing_outside_out_and_shows_as_text(wear_fleet, tmp_path):
    rows = wear_fleet.series_rows(wear_fleet.kind(None))
    for r in rows:
        r["machine"], r["axis"] = "../../x", "<b>y</b>"
    h = wear_fleet.history(tmp_path / "h", rows)
    out = tmp_path / "a" / "b" / "out"
    write_report(h, out)
    written = {p for p in tmp_path.rglob("*") if p.is_file() and h not in p.parents}
    assert written and all(out in p.parents for p in written), sorted(map(str, written))
    (data,) = (out / "data").iterdir()
    assert re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9._-]*-[0-9a-f]{10}\.csv", data.name), data.name
    html = (out / "report.html").read_text()
    assert "<b>y</b>" not in html and "&lt;b&gt;y&lt;/b&gt;" in html and "../../x" in html


def test_an_out_that_is_a_file_is_refused_naming_out_and_left_as_it_was(wear_fleet, tmp_path):
    from rt_ident.errors import ConfigError

    h = wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(wear_fleet.kind(None)))
    out = tmp_path / "notes.txt"
    out.write_text("mine")
    with pytest.raises(ConfigError, match="is a file") as e:
        write_report(h, out)
    assert e.value.field == "--out" and out.read_text() == "mine"


def test_two_series_whose_names_clean_to_the_same_file_keep_apart(wear_fleet, tmp_path):
    a = wear_fleet.series_rows(wear_fleet.kind(None))
    b = wear_fleet.series_rows(wear_fleet.kind("b"))
    for r in a:
        r["machine"], r["axis"] = "m/1", "x"
    for r in b:
        r["machine"], r["axis"] = "m?1", "x"
    out = tmp_path / "out"
    res = write_report(wear_fleet.history(tmp_path / "h", a + b), out)
    assert len(set(res["series_csv"])) == 2 and all(Path(p).parent == out / "data" for p in res["series_csv"])


def test_the_report_command_writes_the_page_without_matplotlib(wear_fleet, tmp_path):
    h = wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(wear_fleet.kind("load")))
    code = ("import sys; sys.modules['matplotlib'] = None; from rt_ident.cli import main; "
            f"sys.argv = ['rt-ident', 'fleet', 'report', '--history', {str(h)!r}, '--out', {str(tmp_path / 'r')!r}]; "
            "main()")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr
    assert "1 series (1 drifting)" in p.stdout and (tmp_path / "r" / "report.html").stat().st_size > 20_000


def test_report_options_reach_the_drift_a_higher_h_makes_the_same_axis_alarm_later(wear_fleet, tmp_path):
    h = wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(wear_fleet.kind("k")))
    firsts = []
    for hh in ("5", "9"):
        r = CliRunner().invoke(app, ["fleet", "report", "--history", str(h), "--out", str(tmp_path / hh), "--h", hh])
        assert r.exit_code == 0, r.output
        with open(tmp_path / hh / "fleet.csv", newline="", encoding="utf-8") as fh:
            firsts.append(next(csv.DictReader(fh))["first_alarm"])
    assert firsts[0] and (not firsts[1] or firsts[1] > firsts[0])

"""The shared report pieces: the HTML page helpers the commissioning and fleet reports both use, and the SVG
trend plot (round ticks, a y-range that holds every interval, lines outside the data left out)."""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

from rt_ident import config
from rt_ident.commission import report as commission_report
from rt_ident.outputs.svg_plot import TrendPlot, nice_ticks, tick_text

ROOT = Path(__file__).resolve().parents[2]
SVG = "{http://www.w3.org/2000/svg}"


def test_the_commissioning_report_is_one_escaped_page_through_the_shared_helpers(tmp_path):
    cfg = config.from_mapping(tomllib.loads((ROOT / "configs" / "sim.toml").read_text()))
    result = {"verdict": "fail", "config": "a<b>.toml", "stage_reached": "b", "max_travel_m": 1e-3,
              "max_speed_m_s": 2e-3, "failed": {"check": "scale ratio x/theta1", "fix": "backend.lead = 2"},
              "checks": [{"name": "scale ratio x/theta1", "ok": False, "measured": 1.5e-3, "expected": 7.96e-4,
                          "fix": "backend.lead"}]}
    commission_report.write(result, cfg, tmp_path / "report.html")
    html = (tmp_path / "report.html").read_text()
    assert html.startswith("<!doctype html>") and html.rstrip().endswith("</body></html>")
    assert "<title>rt-ident commission: fail</title>" in html and "a&lt;b&gt;.toml" in html
    assert "<td>scale ratio x/theta1</td><td><span class='fail'>FAIL</span></td><td>0.0015</td>" in html
    assert not (tmp_path / "report.html.part").exists()


def test_nice_ticks_are_round_steps_inside_the_range_and_labelled_without_minus_zero():
    t = nice_ticks(-1.73, 0.31, 4)
    assert t == [-1.5, -1.0, -0.5, 0.0]
    assert [tick_text(v, 0.5) for v in t] == ["-1.5", "-1.0", "-0.5", "0.0"]
    assert nice_ticks(0.0, 30.2, 4) == [0.0, 10.0, 20.0, 30.0]
    assert tick_text(-1e-17, 0.25) == "0.00"


def _frame(svg: ET.Element) -> tuple[float, float]:
    f = svg.find(f"{SVG}rect[@class='frame']")
    return float(f.get("y")), float(f.get("y")) + float(f.get("height"))


def test_an_interval_far_wider_than_the_scatter_widens_the_range_to_hold_it():
    p = TrendPlot("K", "%")
    p.points([0, 1, 2], [0.0, 0.1, -0.1], [-0.1, -50.0, -0.2], [0.1, 40.0, 0.0], "estimate")
    svg = ET.fromstring(p.svg())
    top, bottom = _frame(svg)
    ys = [float(v) for ln in svg.findall(f"{SVG}line[@class='interval']") for v in (ln.get("y1"), ln.get("y2"))]
    assert len(ys) == 6 and all(top <= y <= bottom for y in ys)
    assert min(ys) - top < 0.1 * (bottom - top) and bottom - max(ys) < 0.1 * (bottom - top)


def test_a_level_outside_the_data_is_left_out_of_the_plot_and_its_legend():
    p = TrendPlot("K", "%")
    p.points([0, 1], [0.0, -1.0], [-0.1, -1.1], [0.1, -0.9], "estimate")
    p.hline(-15.0, "limit -15 %", dash=True, in_range=False)
    p.vline(1.0, "first alarm")
    svg = p.svg()
    legend = "".join(ET.fromstring(svg).find(f"{SVG}g[@class='legend']").itertext())
    assert "first alarm" in legend and "limit" not in legend
    assert not re.search(r'stroke-dasharray', svg)

"""``rt-ident fleet report``: one self-contained HTML page for the fleet, and the data behind it as CSV.

``OUT/report.html``: the fleet table, worst first (:func:`rt_ident.fleet.drift.order`), then one section per
machine and axis in the same order: its state, findings and checks, its alarms (since when, the change at
the first alarm and now, the rate, the limit, the severity) and a trend plot per watched parameter - every
trusted estimate as its change from the baseline mean in per cent, with its 95 % interval, the baseline's
+-2 sigma band (sigma as the CUSUM uses it), the baseline recordings shaded, the first alarm marked, the limit
when the plot's range reaches it, and the recordings that were not trusted as ticks along the bottom.
Figures are inline SVG (:mod:`rt_ident.outputs.svg_plot`): the page needs nothing beside it to open.

``OUT/fleet.csv``: the fleet table; ``OUT/data/<machine>-<axis>.csv``: every recording of a series with its
estimates, intervals, change from the baseline and CUSUM sums. File names are made from the machine and
axis names with everything but letters, digits, ``.``, ``_`` and ``-`` replaced (and a short hash added when
the name had to change or two series would share one), so they stay inside ``OUT``.
"""

from __future__ import annotations

import csv
import datetime as _dt
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.errors import ConfigError
from rt_ident.fleet.drift import WATCHED, DriftSettings, drift
from rt_ident.fleet.findings import Limits, limit_words
from rt_ident.fleet.paths import output_path, safe_name
from rt_ident.outputs.html import esc, page, table, write_page
from rt_ident.outputs.svg_plot import GREEN, GREY, ORANGE, RED, TrendPlot

UNITS = {"I1": "kg m²", "I2": "kg m²", "B": "N m s/rad", "K": "N m/rad", "wn": "rad/s", "zeta": "-"}
NAMES = {"I1": "motor inertia I1", "I2": "table inertia I2", "B": "coupling damping B", "K": "stiffness K",
         "wn": "resonance ωn", "zeta": "damping ratio ζ"}

_CSS = """.sev-critical{background:#f6c9c9}.sev-high{background:#fbdcc4}.sev-medium{background:#fff1bf}
.sev-low{background:#e8f0fa}.st-untrusted-data{background:#ececec}.st-insufficient-history{color:#666}
.finding{border-left:4px solid #b00020;padding:.3em .8em;margin:.4em 0;background:#fafafa}
.plots{display:grid;grid-template-columns:repeat(auto-fill,minmax(540px,1fr));gap:.5em}
section{border-top:1px solid #ccc;margin-top:1.5em}small{color:#666}"""


def _csv_text(v: Any) -> Any:
    """A text cell a spreadsheet will not run as a formula (names come from the manifest)."""
    return "'" + v if isinstance(v, str) and v[:1] in ("=", "+", "-", "@", "\t", "\r") else v


def _days(t: np.ndarray, t0: np.datetime64) -> np.ndarray:
    return (t - t0).astype("timedelta64[s]").astype(float) / 86400.0


def _date_ticks(t0: np.datetime64) -> Callable[[float, float], list[tuple[float, str]]]:
    """x ticks for days since ``t0``: a round number of days apart, labelled month-day."""
    def ticks(a: float, b: float) -> list[tuple[float, str]]:
        step = next((s for s in (1, 2, 5, 7, 14, 28, 56, 91, 182, 365) if (b - a) / s <= 6), 730)
        first = math.ceil(a / step)
        start = _dt.datetime.fromisoformat(str(t0.astype("datetime64[s]")))
        return [(k * step, (start + _dt.timedelta(days=k * step)).strftime("%m-%d"))
                for k in range(first, math.floor(b / step) + 1)]
    return ticks


def _when(iso: str | None) -> str:
    return "-" if not iso else iso[:16].replace("T", " ")


def _plot(p: str, state: dict[str, Any], det: dict[str, Any], settings: DriftSettings, limits: Limits,
          t0: np.datetime64) -> str:
    s, full, r = det["series"], det["all"], det["cusum"][p]
    x, lo, hi = s[p], s[f"{p}_lo"], s[f"{p}_hi"]
    ok = np.isfinite(x)
    if not ok.any():
        return f"<p><small>{esc(p)}: no estimate.</small></p>"
    mu0 = r["mu0"]
    has_baseline = math.isfinite(mu0)
    ref = mu0 if has_baseline else float(np.mean(x[ok]))

    def pct(v: Any) -> Any:                           # values, intervals and bands as per cent of the reference
        return 100.0 * (v / ref - 1.0)

    days = _days(s["time"], t0)
    times = [_when(str(np.datetime_as_string(v, unit="m"))) for v in s["time"]]
    tips = [f"{when}: {v:.6g} {UNITS[p]} ({pct(v):+.2f} %), 95 % {a:.6g} .. {b:.6g}"
            for when, v, a, b in zip(times, x, lo, hi)]
    alarm = next((a for a in state["alarms"] if a["parameter"] == p), None)
    now = state["parameters"][p]["change_now_percent"]
    title = f"{NAMES[p]}: {now:+.2f} % now" if now is not None else NAMES[p]
    plot = TrendPlot(title=title + (f" - ALARM, {alarm['direction']}" if alarm else ""),
                     ylabel="% vs baseline" if has_baseline else "% vs mean so far", x_ticks=_date_ticks(t0))
    if has_baseline:
        n0 = min(settings.baseline, int(x.size))
        plot.vspan(float(days[0]), float(days[n0 - 1]), f"baseline recordings ({n0})")
        half = 2.0 * max(r["s0"] * math.sqrt(1.0 + 1.0 / n0), settings.floor * abs(mu0))
        plot.band(pct(mu0 - half), pct(mu0 + half), "baseline ±2σ")
        plot.hline(0.0, "baseline mean")
        for direction, label in ((-1, "fall"), (1, "rise")):
            lim = limits.limit(p, direction)
            if lim is not None:
                plot.hline(direction * lim, f"limit {direction * lim:+g} % ({label})", ORANGE, dash=True,
                           in_range=False)
    plot.points(days, pct(x), pct(lo), pct(hi), "estimate, 95 % interval", tips=tips)
    if alarm:
        since = _days(np.array([np.datetime64(alarm["since"][:-1])]), t0)[0]
        first = _days(np.array([np.datetime64(alarm["first_alarm"][:-1])]), t0)[0]
        if since < first:
            plot.vline(float(since), f"drift began (estimated) {_when(alarm['since'])[:10]}", GREEN)
        plot.vline(float(first), f"first alarm {_when(alarm['first_alarm'])}", RED)
    skipped = ~full["trusted"]
    if skipped.any():
        plot.marks(_days(full["time"][skipped], t0), f"not trusted, skipped ({int(skipped.sum())})", GREY)
    return plot.svg()


def _alarm_rows(state: dict[str, Any]) -> str:
    rows = []
    for a in state["alarms"]:
        lim = limit_words(a).removeprefix("limit ")
        rate = "-" if a["rate_percent_per_day"] is None else f"{a['rate_percent_per_day']:+.2f}"
        rows.append([esc(a["parameter"]), esc(a["direction"]), esc(_when(a["since"])), esc(_when(a["first_alarm"])),
                     f"{a['change_at_first_alarm_percent']:+.2f} %", f"{a['change_now_percent']:+.2f} %",
                     rate, esc(lim), esc(a["severity"])])
    return table(["parameter", "moved", "drift began (estimated)", "first alarm", "change at first alarm",
                  "change now", "% per day", "limit", "severity"], rows,
                 [f"sev-{a['severity']}" for a in state["alarms"]])


def _row_class(s: dict[str, Any]) -> str:
    return f"sev-{s['severity']}" if s["severity"] else f"st-{s['state']}"


def _fleet_table(states: list[dict[str, Any]], stems: dict[tuple[str, str], str]) -> str:
    rows = []
    for i, s in enumerate(states, 1):
        stem = stems[(s["machine"], s["axis"])]
        since = min((a["since"] for a in s["alarms"]), default=None)
        what = "<br>".join(f"{esc(f['finding'])}<br><small>check: {esc(f['check'])}</small>" for f in s["findings"])
        rows.append([str(i), f"<a href='#s-{esc(stem)}'>{esc(s['machine'])}</a>", esc(s["axis"]), esc(s["state"]),
                     esc(s["severity"] or "-"), what or esc(s["message"]), esc(_when(since)[:10]),
                     f"{s['trusted']} of {s['recordings']}", f"<a href='data/{esc(stem)}.csv'>CSV</a>"])
    return table(["#", "machine", "axis", "state", "severity", "finding (change now vs baseline) and check / state",
                  "drift began", "trusted recordings", "data"], rows, [_row_class(s) for s in states])


def _section(s: dict[str, Any], det: dict[str, Any], stem: str, settings: DriftSettings, limits: Limits) -> str:
    head = f"{s['machine']} {s['axis']}: {s['state']}" + (f", {s['severity']}" if s["severity"] else "")
    parts = [f"<section id='s-{esc(stem)}'><h2>{esc(head)}</h2>"]
    if s["state"] != "drifting":
        parts.append(f"<p>{esc(s['message'])}</p>")
    for f in s["findings"]:
        parts.append(f"<div class='finding'><b>Finding ({esc(f['severity'])}):</b> {esc(f['finding'])}<br>"
                     f"<b>Check:</b> {esc(f['check'])}</div>")
    if s["alarms"]:
        parts.append(_alarm_rows(s))
    skipped = s["skipped_untrusted"] + s["skipped_unknown_verdict"]
    parts.append(f"<p><small>{s['trusted']} of {s['recordings']} recordings trusted ({skipped} skipped: "
                 f"{s['skipped_untrusted']} not trusted, {s['skipped_unknown_verdict']} with no recorded verdict); "
                 f"data: <a href='data/{esc(stem)}.csv'>data/{esc(stem)}.csv</a></small></p>")
    if det["series"]["time"].size:
        t0 = det["all"]["time"][0]
        parts.append("<div class='plots'>" + "".join(_plot(p, s, det, settings, limits, t0) for p in WATCHED)
                     + "</div>")
    parts.append("</section>")
    return "".join(parts)


def _series_csv(path: Path, det: dict[str, Any]) -> None:
    full, per = det["all"], det["cusum"]
    trusted_at = np.flatnonzero(full["trusted"])          # row of each trusted estimate in the full series
    head = ["time", "trusted", "verdict_recorded", "reasons"]
    for p in WATCHED:
        head += [p, f"{p}_lo", f"{p}_hi", f"{p}_change_percent", f"{p}_z", f"{p}_cusum_plus", f"{p}_cusum_minus"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for i in range(full["time"].size):
            j = np.searchsorted(trusted_at, i)
            k = int(j) if j < trusted_at.size and trusted_at[j] == i else None
            reasons = full["reasons"][i]
            row: list[Any] = [np.datetime_as_string(full["time"][i], unit="s") + "Z", bool(full["trusted"][i]),
                              bool(full["has_verdict"][i]),
                              _csv_text("; ".join(map(str, reasons)) if reasons is not None else "")]
            for p in WATCHED:
                r = per[p]
                mu0 = r["mu0"]
                v = full[p][i]
                change = 100.0 * (v / mu0 - 1.0) if math.isfinite(mu0) else math.nan
                z = r["z"][k] if k is not None else math.nan
                cp = r["cplus"][k] if k is not None and r["cplus"] is not None else math.nan
                cm = r["cminus"][k] if k is not None and r["cminus"] is not None else math.nan
                row += [_num(v), _num(full[f"{p}_lo"][i]), _num(full[f"{p}_hi"][i]), _num(change), _num(z),
                        _num(cp), _num(cm)]
            w.writerow(row)


def _num(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.9g}"


def _fleet_csv(path: Path, states: list[dict[str, Any]], stems: dict[tuple[str, str], str]) -> None:
    head = ["machine", "axis", "state", "severity", "message", "findings", "checks", "alarms", "drift_began",
            "first_alarm", "recordings", "trusted", "skipped_untrusted", "skipped_unknown_verdict", "data"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for s in states:
            alarms = "; ".join(f"{a['parameter']} {a['direction']}: {a['change_at_first_alarm_percent']:+.2f} % at "
                               f"first alarm, {a['change_now_percent']:+.2f} % now ({a['severity']})"
                               for a in s["alarms"])
            w.writerow([_csv_text(s["machine"]), _csv_text(s["axis"]), s["state"], s["severity"] or "",
                        _csv_text(s["message"]), _csv_text("; ".join(f["finding"] for f in s["findings"])),
                        _csv_text("; ".join(f["check"] for f in s["findings"])), alarms,
                        min((a["since"] for a in s["alarms"]), default=""),
                        min((a["first_alarm"] for a in s["alarms"]), default=""), s["recordings"], s["trusted"],
                        s["skipped_untrusted"], s["skipped_unknown_verdict"],
                        f"data/{stems[(s['machine'], s['axis'])]}.csv"])


def write_report(history: str | Path, out_dir: str | Path, settings: DriftSettings | None = None,
                 limits: Limits | None = None) -> dict[str, Any]:
    """Write ``OUT/report.html``, ``OUT/fleet.csv`` and ``OUT/data/<machine>-<axis>.csv``; returns the paths
    and the counts per state."""
    settings = settings or DriftSettings()
    limits = limits or Limits()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError("--out", f"{out} is a file; the report is a folder (its page, figures and data)")
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    res = drift(history, settings, limits)
    states, detail = res["series"], res["_detail"]
    stems = {(s["machine"], s["axis"]): safe_name(s["machine"], s["axis"]) for s in states}
    csvs = []
    for s in states:
        key = (s["machine"], s["axis"])
        path = output_path(data, *key, suffix=".csv")
        _series_csv(path, detail[key])
        csvs.append(str(path))
    fleet_csv = output_path(out, "fleet", suffix=".csv")
    _fleet_csv(fleet_csv, states, stems)
    counts = ", ".join(f"{n} {st.replace('-', ' ')}" for st, n in res["counts"].items() if n)
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = [f"<h1>Fleet drift report</h1><p>{len(states)} series: {esc(counts)}. History <code>{esc(history)}</code>, "
            f"made {stamp}.<br><small>{esc(res['method'])}; limits: {esc(limits.source)} (a limit reached within "
            f"{limits.soon_days:g} days at the current rate is urgent). Changes are against each series' baseline "
            f"mean (its first {settings.baseline} trusted recordings).</small></p>",
            "<h2>Fleet, worst first</h2>", _fleet_table(states, stems),
            "<p><small>Data: <a href='fleet.csv'>fleet.csv</a> (this table); each series' recordings in "
            "<code>data/</code>.</small></p>"]
    body += [_section(s, detail[(s["machine"], s["axis"])], stems[(s["machine"], s["axis"])], settings, limits)
             for s in states]
    html_path = output_path(out, "report", suffix=".html")
    write_page(html_path, page("rt-ident fleet report", body, _CSS))
    return {"html": str(html_path), "fleet_csv": str(fleet_csv), "data_dir": str(data), "series_csv": csvs,
            "series": len(states), "counts": res["counts"], "alarms": len(res["alarms"]),
            "order": [(s["machine"], s["axis"], s["state"], s["severity"]) for s in states]}


__all__ = ["write_report"]

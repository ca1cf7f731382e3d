"""``rt-ident fleet report``: one trend figure per machine and axis, and a one-page summary (PNG + CSV).

Each figure has a panel per watched parameter: every trusted estimate with its 95 % interval, the baseline mean
and its +-2 sigma band (sigma as the CUSUM uses it, :mod:`rt_ident.fleet.drift`), and the first alarm
marked. The summary lists every series worst first: series with an alarm before the others, then by the
largest |z| of their last recording.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.fleet.drift import WATCHED, DriftSettings, drift

UNITS = {"I1": "kg m²", "I2": "kg m²", "B": "N m s/rad", "K": "N m/rad", "wn": "rad/s", "zeta": "-"}


def _summary_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    alarms = {(a["machine"], a["axis"], a["parameter"]): a for a in result["alarms"]}
    rows = []
    for (machine, axis), det in result["_detail"].items():
        for p, r in det["cusum"].items():
            z = r["z"]
            last = float(z[-1]) if z.size and np.isfinite(z[-1]) else float("nan")
            a = alarms.get((machine, axis, p))
            x = det["series"][p]
            x_last = float(x[-1]) if x.size else float("nan")
            rows.append({"machine": machine, "axis": axis, "parameter": p, "alarm": a is not None,
                         "first_alarm": a["first_time"] if a else "", "change_percent": a["change_percent"] if a
                         else round(100.0 * (x_last / r["mu0"] - 1.0), 3) if np.isfinite(r["mu0"]) else None,
                         "baseline": r["mu0"], "last": x_last, "last_z": round(last, 2),
                         "recordings": int(x.size), "ignored_untrusted": det.get("ignored", 0)})
    rows.sort(key=lambda r: (not r["alarm"], -abs(r["last_z"]) if np.isfinite(r["last_z"]) else 0.0))
    return rows


def _series_figure(machine: str, axis: str, det: dict[str, Any], settings: DriftSettings, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = det["series"]
    t = s["time"].astype("datetime64[s]").astype(object)
    fig, axs = plt.subplots(len(WATCHED), 1, figsize=(8, 1.8 * len(WATCHED)), sharex=True)
    for ax, p in zip(axs, WATCHED):
        x, lo, hi = s[p], s[f"{p}_lo"], s[f"{p}_hi"]
        r = det["cusum"][p]
        err = np.vstack([np.where(np.isfinite(lo), x - lo, 0.0), np.where(np.isfinite(hi), hi - x, 0.0)])
        ax.errorbar(t, x, yerr=err, fmt="o", ms=3, lw=0.8, color="C0", label="estimate, 95 % interval")
        if np.isfinite(r["mu0"]):
            n0 = min(settings.baseline, x.size)
            band = 2.0 * max(r.get("s0", 0.0) * np.sqrt(1.0 + 1.0 / n0), settings.floor * abs(r["mu0"]))
            ax.axhline(r["mu0"], color="0.4", lw=0.8)
            ax.axhspan(r["mu0"] - band, r["mu0"] + band, color="0.85", zorder=0, label="baseline +-2 sigma")
            ax.axvspan(t[0], t[n0 - 1], color="C2", alpha=0.08, zorder=0)
            # keep the view on the estimates: an interval 100x wider than the scatter would flatten them
            span = max(np.nanmax(x) - np.nanmin(x), 2 * band)
            ax.set_ylim(np.nanmin(x) - 0.6 * span, np.nanmax(x) + 0.6 * span)
        if r["alarm"] is not None:
            ax.axvline(t[r["alarm"]], color="C3", lw=1.2, label="first alarm")
        ax.set_ylabel(f"{p} [{UNITS[p]}]", fontsize=8)
        ax.tick_params(labelsize=7)
    axs[0].legend(fontsize=7, loc="upper left", ncols=3)
    axs[0].set_title(f"{machine} axis {axis}: parameters over time (green: baseline recordings)", fontsize=9)
    fig.autofmt_xdate()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _summary_png(rows: list[dict[str, Any]], path: Path, limit: int = 40) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = rows[:limit]
    cols = ["machine", "axis", "parameter", "alarm", "first_alarm", "change_percent", "last_z", "recordings"]
    cells = [[("ALARM" if r[c] else "") if c == "alarm" else str(r[c]) for c in cols] for r in shown]
    fig, ax = plt.subplots(figsize=(10, 0.28 * (len(shown) + 3)))
    ax.axis("off")
    tab = ax.table(cellText=cells or [[""] * len(cols)], colLabels=cols, loc="upper center", cellLoc="left")
    tab.auto_set_font_size(False)
    tab.set_fontsize(7)
    for i, r in enumerate(shown, start=1):
        if r["alarm"]:
            for j in range(len(cols)):
                tab[i, j].set_facecolor("#f6d5d5")
    more = f" (first {limit} of {len(rows)})" if len(rows) > limit else ""
    ax.set_title(f"fleet drift summary, worst first{more}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(history: str | Path, out_dir: str | Path, settings: DriftSettings | None = None) -> dict[str, Any]:
    """Write ``OUT/summary.csv``, ``OUT/summary.png`` and ``OUT/<machine>-<axis>.png``; returns the paths."""
    settings = settings or DriftSettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = drift(history, settings)
    rows = _summary_rows(result)
    csv_path = out / "summary.csv"
    with open(csv_path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["machine"])
        w.writeheader()
        w.writerows(rows)
    _summary_png(rows, out / "summary.png")
    figures = []
    for (machine, axis), det in result["_detail"].items():
        if det["series"]["time"].size == 0:          # no trusted estimate: nothing to draw (summary says so)
            continue
        p = out / f"{machine}-{axis}.png"
        _series_figure(machine, axis, det, settings, p)
        figures.append(str(p))
    return {"summary_csv": str(csv_path), "summary_png": str(out / "summary.png"), "figures": figures,
            "alarms": len(result["alarms"]), "series": result["series"]}


__all__ = ["write_report"]

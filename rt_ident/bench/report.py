"""Rendering of :func:`rt_ident.bench.kernels.bench_main` results: rich tables on stdout, or JSON."""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import numpy as np

__all__ = ["print_report", "to_json"]


def _default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def to_json(result: dict[str, Any]) -> str:
    return json.dumps(result, indent=2, default=_default)


def _si(x: float | None, unit: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    for scale, prefix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= scale:
            return f"{x / scale:.3g} {prefix}{unit}"
    return f"{x:.3g} {unit}".strip()


def _x(v: float | None) -> str:
    return "-" if v is None else f"{v:.3g}x"


def _e(v: float | None) -> str:
    return "-" if v is None else f"{v:.1e}"


def print_report(result: dict[str, Any]) -> None:
    """Tables: machine, RLS, simulation, batch LS, loop, targets."""
    from rich.console import Console
    from rich.table import Table

    con = Console(width=None if sys.stdout.isatty() else 150)
    m = result["machine"]
    mt = Table(title="rt-ident bench - machine", show_header=False)
    for k in ("cpu", "cores", "cores_usable", "load_avg_1min", "python", "numpy", "numba", "scipy", "blas_threads"):
        mt.add_row(k, str(m.get(k)))
    mt.add_row("command", result.get("command", ""))
    mt.add_row("timings", f"median of {result['repeats']} runs after a warm-up (peers: up to 3 runs); 'best' is "
               "the fastest run; ratios and targets use medians" + (", quick sizes" if result.get("quick") else ""))
    con.print(mt)

    rls = result["rls"]
    t = Table(title="RLS, 5 regressors x 4 outputs (same data; peers on the first rows)")
    for col in ("method", "samples", "samples/s", "best", "ns/sample", "ours block is", "ours update is",
                "max rel. diff vs batch LS"):
        t.add_column(col, justify="left" if col == "method" else "right")
    for r in rls["rows"]:
        t.add_row(r["name"], str(r["n"]), _si(r["per_s"]), _si(r["n"] / r["min_s"]), f"{r['ns_per_item']:.4g}",
                  _x(r["ours_block_x"]),
                  _x(r["ours_update_x"]), _e(r["rel_diff"]))
    con.print(t)
    if rls.get("padasip") is None:
        con.print("[yellow]padasip is not installed: that peer was skipped (pip install -e '.[bench]')[/yellow]")

    sim = result["sim"]
    t = Table(title=f"Simulation of Eq. (3), dt = {sim['dt']:g} s (same system and torque)")
    for col in ("path", "steps", "steps/s", "best", "ns/step", "best Newmark is", "best ZOH is", "rel. diff"):
        t.add_column(col, justify="left" if col == "path" else "right")
    for r in sim["rows"]:
        t.add_row(r["name"], str(r["n"]), _si(r["per_s"]), _si(r["n"] / r["min_s"]), f"{r['ns_per_item']:.4g}",
                  _x(r["newmark_x"]),
                  _x(r["zoh_x"]), _e(r["rel_diff"]))
    con.print(t)
    con.print("rel. diff: interpreted loop vs our compiled result; scipy rows vs our ZOH result.")

    ls = result["ls"]
    t = Table(title=f"Batch LS, Eq. (10), paper's Euler regressor {ls['shape'][0]} x {ls['shape'][1]} "
                    f"(scaled cond {ls['cond_scaled']:.3g})")
    for col in ("method", "median ms", "rows/s", "max rel. diff vs numpy"):
        t.add_column(col, justify="left" if col == "method" else "right")
    for r in ls["rows"]:
        t.add_row(r["name"], f"{1e3 * r['median_s']:.3g}", _si(r["per_s"]), _e(r["rel_diff"]))
    con.print(t)
    con.print(f"ours / numpy time: {ls['time_ratio_ours_over_numpy']:.2f}")

    loop = result.get("loop") or {}
    if not loop.get("skipped"):
        t = Table(title=f"Loop end to end: sim backend, 1 kHz tick, {loop['seconds']:g} s trials, "
                        f"method {loop['method']}, SCHED_FIFO, one subprocess per trial")
        for col in ("telemetry", "samples/s", "0 overruns", "overruns (1st s)", "from work / late start",
                    "tick work p50/p99/max us", "lateness p50/p99/max us",
                    "longest gap ms @tick", "host steal ms", "lost", "tel. dropped", "RSS 1st/last tick MB",
                    "RSS growth (after 10 %)"):
            t.add_column(col, justify="right")
        for r in loop["trials"]:
            lat = r.get("lateness_us") or {}
            rss = r.get("rss_kb") or {}
            rss_s = ("-" if not rss.get("first_tick_kb") else
                     f"{rss['first_tick_kb'] / 1024:.0f} / {rss['last_tick_kb'] / 1024:.0f}")
            gaps = r.get("long_gaps_ms") or []
            gap = max(gaps, key=lambda g: g[1]) if gaps else None
            t.add_row(r["sink"], _si(r["rate"]) + (" (retry)" if r.get("attempt") else ""),
                      "[green]yes[/green]" if r["ok"] else "[red]no[/red]",
                      f"{r.get('overruns', '-')} ({r.get('overruns_first_1s', '-')})",
                      f"{r.get('overruns_work', '-')} / {r.get('overruns_late_start', '-')}",
                      "/".join(f"{(r.get('work_us') or {}).get(k, float('nan')):.3g}" for k in ("p50", "p99", "max")),
                      "/".join(f"{lat.get(k, float('nan')):.3g}" for k in ("p50", "p99", "max")) if lat else
                      str(r.get("error", r.get("stop_cause", "-")))[:60],
                      "-" if gap is None else f"{gap[1]:.1f} @{gap[0]}",
                      "-" if r.get("host_steal_ms") is None else f"{r['host_steal_ms']:g}",
                      str(r.get("lost_samples", "-")),
                      str(r.get("telemetry_dropped", "-")), rss_s,
                      "-" if r.get("rss_growth_pct") is None else f"{r['rss_growth_pct']:+.1f} %"
                      + ("" if r.get("rss_growth_after_10pct_pct") is None
                         else f" ({r['rss_growth_after_10pct_pct']:+.2f} %)"))
        con.print(t)
        for key, label in (("max_clean_rate", "0 overruns"), ("max_clean_after_startup_rate",
                                                               "0 overruns after the first second"),
                           ("max_sustained_rate", "kept pace")):
            con.print(f"largest rate with {label}: " + ", ".join(
                f"telemetry {k}: {_si(v, 'samples/s') if v else 'none'}" for k, v in loop[key].items()))
    t = Table(title="Speed and capacity targets, measured in this run")
    t.add_column("target")
    t.add_column("met", justify="right")
    for part in ("rls", "sim", "ls", "loop"):
        for k, v in ((result.get(part) or {}).get("targets") or {}).items():
            t.add_row(k, "-" if v is None else ("[green]yes[/green]" if v else "[red]no[/red]"))
    con.print(t)

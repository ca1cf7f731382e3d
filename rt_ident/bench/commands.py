"""``rt-ident bench kernels | control | estimator | xy | soak`` (mounted by :mod:`rt_ident.cli`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from rt_ident.errors import ConfigError, RtIdentError
from rt_ident.outputs.text import fmt, json_default, um

bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: our kernels against their peers, the loop's capacity "
                        "and soak, fixed against adaptive control, the per-sample estimator, the XY tick budget.")
err = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)
JSON = typer.Option(False, "--json", help="Print the results as JSON on stdout.")


@bench_app.command("kernels")
def kernels_cmd(
    json_out: bool = JSON,
    quick: bool = typer.Option(False, "--quick", help="Short loop trials (3 s)."),
    loop_seconds: float = typer.Option(60.0, "--loop-seconds", help="Seconds per loop trial (0 skips the loop)."),
    repeats: int = typer.Option(5, min=1, help="Repeats per micro-benchmark (medians are reported)."),
    loop_rates: str = typer.Option("", "--loop-rates",
                                   help="Comma-separated sample rates the loop search tries, e.g. 34000,170000."),
) -> None:
    """Speed of our kernels vs peers (padasip, filterpy, numpy, scipy) and the loop's capacity, in one run."""
    from rt_ident.bench.kernels import bench_main

    try:
        rates = tuple(sorted(int(float(r)) for r in loop_rates.split(",") if r.strip())) or None
    except ValueError:
        raise RtIdentError(f"--loop-rates: not a comma-separated list of numbers: {loop_rates!r}") from None
    if rates is not None and min(rates) <= 0:
        raise RtIdentError(f"--loop-rates: rates must be > 0, got {loop_rates!r}")
    bench_main(json_out=json_out, quick=quick, loop_seconds=loop_seconds, repeats=repeats, loop_rates=rates)


@bench_app.command("control")
def control_cmd(
    json_out: bool = JSON,
    quick: bool = typer.Option(False, "--quick", help="Shorter runs, 20 random plants."),
    figure: Path | None = typer.Option(None, "--figure", help="Write the comparison as a PNG."),
    cases: int = typer.Option(20, "--cases", min=0, help="Randomized plant changes (I2 x 1.5..4, I1 x 1.2..2)."),
    repeats: int = typer.Option(3, "--repeats", min=0,
                                help="Each named scenario again under this many other noise seeds (the spread)."),
) -> None:
    """Fixed vs adaptive vs oracle control after plant changes, change-to-redesign latency, the spread under
    other noise seeds, and the nominal design on 100 random plants."""
    if figure is not None:
        from rt_ident.errors import require

        require("matplotlib", "plots", "--figure")
    _print_control(json_out, quick, figure, cases, repeats)


@bench_app.command("estimator")
def estimator_cmd(json_out: bool = JSON) -> None:
    """The per-sample estimator's bias and tracking on bench-like data in closed loop."""
    _print_estimator(json_out)


@bench_app.command("xy")
def xy_cmd(json_out: bool = JSON,
           seconds: float = typer.Option(10.0, "--seconds", min=1.0, help="Seconds of each run.")) -> None:
    """The XY table's tick budget: both axes in one loop (configs/xy-sim.toml) against X alone, real time."""
    _print_xy(seconds, json_out)


@bench_app.command("soak")
def soak_cmd(
    seconds: float = typer.Argument(600.0, help="Seconds of the run."),
    json_out: bool = JSON,
    rate: float = typer.Option(170_000.0, "--rate", min=1000.0, help="Samples/s of the run."),
    sink: str = typer.Option("rrd", "--sink", help="Telemetry: rrd or off."),
    record: bool = typer.Option(True, "--record/--no-record", help="Record a Parquet too (its recorder is sampled)."),
) -> None:
    """One loop run this long and the memory (RSS) of its process and every helper over time."""
    _print_soak(seconds, rate, sink, json_out, record)


def _print_control(json_out: bool, quick: bool, figure: Path | None, cases: int, repeats: int) -> None:
    from rt_ident.bench.control import control_bench, targets

    res = control_bench(quick=quick, cases=cases, repeats=repeats,
                        progress=lambda s: err.print(f"control bench: {s}", highlight=False, markup=False))
    if figure is not None:
        from rt_ident.bench.control import control_comparison

        control_comparison(res, figure)
    if json_out:
        typer.echo(json.dumps(res, indent=2, default=json_default))
        return
    tab = Table(title="table tracking error from the plant change on, µm: RMS / max")
    for col in ("scenario", "fixed", "adaptive", "oracle", "adaptive / oracle", "adaptive / fixed",
                "change to redesign, ms", "first act, ms", "oracle that late / oracle, max"):
        tab.add_column(col, justify="right")
    c = res["control"]
    for r in c["scenarios"] + c["cases"]:
        cells = []
        for m in ("fixed", "adaptive", "oracle"):
            e = r[m]
            cell = f"{fmt(um(e['rms_error_m']))} / {fmt(um(e['max_error_m']))}"
            cells.append(cell + (" (stopped)" if e.get("stop") else ""))
        lat, act = r.get("change_to_redesign_s"), r.get("first_response_s")
        tab.add_row(r["name"], *cells, fmt(r.get("adaptive_over_oracle")), fmt(r.get("adaptive_over_fixed")),
                    "never" if lat is None else f"{1e3 * lat:.0f}", "never" if act is None else f"{1e3 * act:.1f}",
                    fmt(r.get("late_oracle_over_oracle_max")))
    out.print(tab)
    sm = c["summary"]
    for key, label in (("adaptive_over_oracle", "adaptive / oracle RMS"), ("adaptive_over_oracle_max",
                       "adaptive / oracle max"), ("adaptive_over_fixed", "adaptive / fixed RMS"),
                       ("late_oracle_over_oracle_max", "oracle as late as the adaptive first acted / oracle, max")):
        out.print(f"{label} over {sm['n']} changes: median {fmt(sm[key]['median'])}, worst {fmt(sm[key]['worst'])}")
    for p in c["perturbed"]:
        out.print(f"{p['name']} under other noise seeds: adaptive / oracle "
                  f"{', '.join(fmt(v) for v in p['adaptive_over_oracle'])} (spread {fmt(p['spread'])})")
    rp = res["control"]["random_plants"]
    out.print(f"random plants (I1, I2, B, K each x 0.5..2, seed {rp['seed']}): {rp['unstable']} of {rp['n']} unstable "
              f"with the nominal design; worst overshoot {100 * rp['worst_overshoot']:.1f} %")
    for name, ok, fig in targets(res):
        out.print(f"{'met' if ok else 'NOT met'}: {name} ({fig})", markup=False)
    if figure is not None:
        out.print(f"figure: {figure}", markup=False)


def _print_xy(seconds: float, json_out: bool) -> None:
    from rt_ident.bench.xy import xy_budget

    res = xy_budget(seconds, progress=lambda s: err.print(f"xy bench: {s}", highlight=False, markup=False))
    if json_out:
        typer.echo(json.dumps(res, indent=2, default=json_default))
        return
    tab = Table(title=f"tick work (µs), {seconds:g} s real time at the sim's 34 k samples/s per axis, 1 ms tick")
    for col in ("run", "p50", "p99", "max", "samples", "overruns", "idle poll", "stop"):
        tab.add_column(col, justify="right")

    def row(name: str, r: dict) -> None:
        w = r.get("work_us") or {}
        tab.add_row(name, fmt(w.get("p50")), fmt(w.get("p99")), fmt(w.get("max")), str(r.get("samples")),
                    str(r.get("overruns")), "on" if r.get("idle_poll") else "off", str(r.get("stop") or "-"))

    row("X and Y in one loop", res["two_axes"])
    for axis, w in (res["two_axes"].get("per_axis_work_us") or {}).items():
        tab.add_row(f"  axis {axis}'s share", fmt(w.get("p50")), fmt(w.get("p99")), fmt(w.get("max")), "", "", "", "")
    row("X alone", res["one_axis"])
    row("X and Y, no idle poll", res["two_axes_no_idle_poll"])
    row("X and Y, Python path", res["two_axes_python_path"])
    out.print(tab)
    ratio = res.get("p99_ratio_two_over_one")
    ahead = res["two_axes"].get("sim_ahead_us") or {}
    out.print(f"the simulated plants' stepping after each tick (the devices' part, not in the work): "
              f"p50 {fmt(ahead.get('p50'))}, p99 {fmt(ahead.get('p99'))} us")
    out.print(f"p99 two axes / one axis: {fmt(ratio)}")
    off99 = (res["two_axes_no_idle_poll"].get("work_us") or {}).get("p99")
    if p99_on := (res["two_axes"].get("work_us") or {}).get("p99"):
        out.print(f"p99 two axes, idle poller on / off: {fmt(p99_on / off99 if off99 else None)}")
    out.print(f"p99 two axes, compiled tick / Python path: {fmt(res.get('p99_ratio_compiled_over_python'))}")
    p99 = (res["two_axes"].get("work_us") or {}).get("p99")
    out.print(f"{'met' if res['met'] else 'NOT met'}: p99 of the two-axis tick <= {res['target_p99_us']:g} us "
              f"(40 % of the tick): {fmt(p99)} us")


def _print_estimator(json_out: bool) -> None:
    from rt_ident.bench.estimator import KEYS, estimator_bench, targets

    res = estimator_bench(progress=lambda s: err.print(f"estimator bench: {s}", highlight=False, markup=False))
    if json_out:
        typer.echo(json.dumps(res, indent=2, default=json_default))
        return
    r = res["estimator"]
    tab = Table(title=f"per-sample estimator (svf, {r['filter_hz']:g} Hz filter, {1e3 * r['memory_s']:g} ms memory), "
                      "closed loop, bench-like sensors: error [%]")
    tab.add_column("trial")
    for k in KEYS:
        tab.add_column(k, justify="right")
    tab.add_column("settled \\[ms]", justify="right")
    b = r["bias"]
    tab.add_row("bias, last 5 s of 10", *(f"{100 * b['bias'][k]:+.2f}" for k in KEYS), "")
    tab.add_row("std, last 5 s of 10", *(f"{100 * b['std'][k]:.2f}" for k in KEYS), "")
    for s in r["steps"]:
        settle = s["settle_s"]
        tab.add_row(f"{s['param']} x 1.2: error 0.2 s after", *(f"{100 * s['error_at_0_2_s'][k]:+.2f}" for k in KEYS),
                    f"{1e3 * settle:.0f}" if math.isfinite(settle) else "never")
    out.print(tab)
    for name, ok, fig in targets(res):
        out.print(f"{'met' if ok else 'NOT met'}: {name} ({fig})", markup=False)


def _print_soak(seconds: float, rate: float, sink: str, json_out: bool, record: bool = True) -> None:
    from rt_ident.bench.loop import soak

    if sink not in ("rrd", "off"):
        raise RtIdentError(f"--sink must be rrd or off, got {sink!r}")
    from rt_ident.bench.loop import trial_config
    from rt_ident.config import from_mapping

    try:                                      # what the trial's own process would refuse, said here in one line
        from_mapping(trial_config(rate, seconds, sink, record=record))
    except ConfigError as exc:
        raise ConfigError("--rate", f"{rate:g} samples/s makes a run config that is refused ({exc}); lower it"
                          ) from None
    err.print(f"soak: {seconds:g} s at {rate / 1e3:g} k samples/s, telemetry {sink} ...")
    res = soak(seconds, rate, sink, record=record)
    if json_out:
        typer.echo(json.dumps(res, indent=2, default=json_default))
        return
    if "error" in res and res["error"]:
        raise RtIdentError(f"soak run failed: {res['error']}")
    rss, lat = res.get("rss_kb") or {}, res.get("lateness_us") or {}
    tab = Table(title=f"loop soak: {seconds:g} s at {rate / 1e3:g} k samples/s, telemetry {sink}")
    tab.add_column("figure")
    tab.add_column("value", justify="right")
    for name, value in (("samples/s", f"{res.get('samples_per_s', 0):,.0f}"),
                        ("overruns", res.get("overruns")),
                        ("overruns in the first second", res.get("overruns_first_1s")),
                        ("lateness p50 / p99 / max (us)",
                         " / ".join(f"{lat.get(k, float('nan')):.1f}" for k in ("p50", "p99", "max"))),
                        ("telemetry dropped", res.get("telemetry_dropped")),
                        ("host steal on the loop CPU (ms)", res.get("host_steal_ms")),
                        ("RSS at first tick (MiB)", f"{(rss.get('first_tick_kb') or 0) / 1024:.1f}"),
                        ("RSS at last tick (MiB)", f"{(rss.get('last_tick_kb') or 0) / 1024:.1f}"),
                        ("RSS growth (%)", f"{res.get('rss_growth_pct') or 0:+.2f}"),
                        ("RSS growth after the first 10 % (%)", f"{res.get('rss_growth_after_10pct_pct') or 0:+.2f}"),
                        ("RSS flat within +-5 %", res.get("rss_flat_within_5pct"))):
        tab.add_row(name, str(value))
    for name, h in (res.get("helpers") or {}).items():
        g = h.get("growth_after_10pct_pct")
        tab.add_row(f"{name}: RSS first / last (MiB), growth after 10 % (%)",
                    f"{h['first_kb'] / 1024:.1f} / {h['last_kb'] / 1024:.1f}, "
                    f"{'n/a' if g is None else f'{g:+.2f}'}")
    tab.add_row("every helper flat within +-5 %", str(res.get("helpers_flat_within_5pct")))
    out.print(tab)

"""The ``rt-ident`` command line."""

from __future__ import annotations

import os

# Small dense linear algebra (4x4 expm, 8-parameter fits) is 10-20x slower with a multi-threaded BLAS on
# a busy 2-core machine, and BLAS threads would compete with the real-time loop: one thread, unless set.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json
import logging
import math
import sys
from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from rt_ident import kernel_cache
from rt_ident.errors import ConfigError, RtIdentError, require
from rt_ident.outputs.terminal import (
    UNITS,
    err,
    interval,
    out,
    param_table,
    print_axes,
    print_run,
    print_trust,
    tolerate_gone_terminal,
)
from rt_ident.outputs.text import fmt, json_default
from rt_ident.processes.context import prestart

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Identify a machine-tool axis (two-inertia spring-damper) from simulation or a bench.")


def _mount_subcommands() -> None:
    from rt_ident.bench.commands import bench_app
    from rt_ident.fleet.commands import fleet_app

    app.add_typer(fleet_app, name="fleet")
    app.add_typer(bench_app, name="bench")


_mount_subcommands()


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("rt-ident")
        except PackageNotFoundError:
            v = "unknown (not installed)"
        typer.echo(f"rt-ident {v}")
        raise typer.Exit()


#: -v count: 0 one-line warnings and errors; 1 also info, and tracebacks; 2 also debug
_VERBOSE = 0


class _OneLineFormatter(logging.Formatter):
    """A log record in one line: a traceback only with -v (an expected device failure is reported
    by its message; -v shows where it came from)."""

    def format(self, record: logging.LogRecord) -> str:
        if _VERBOSE or not (record.exc_info or record.stack_info):
            return super().format(record)
        exc = record.exc_info[1] if record.exc_info else None
        saved = record.exc_info, record.exc_text, record.stack_info
        record.exc_info = record.exc_text = record.stack_info = None
        try:
            line = super().format(record)
        finally:
            record.exc_info, record.exc_text, record.stack_info = saved
        return line if exc is None else f"{line}: {type(exc).__name__}: {exc}"


def _set_verbosity(level: int) -> None:
    global _VERBOSE
    _VERBOSE = level
    if level:                                    # else the level main() set (a test's own stays untouched)
        logging.getLogger().setLevel(logging.INFO if level == 1 else logging.DEBUG)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,  # noqa: ARG001 - the callback acts
                                 help="Print the version and exit."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True,
                                help="More detail: -v info lines and tracebacks, -vv debug lines."),
) -> None:
    """rt-ident: model, simulate and identify a machine-tool axis; run the real-time loop."""
    _set_verbosity(verbose)


def _progress():
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                    TimeElapsedColumn(), console=err, transient=True)


# --------------------------------------------------------------------------- reproduce
@app.command()
def reproduce(
    json_out: bool = typer.Option(False, "--json", help="Print the results as JSON on stdout."),
    figures: Path | None = typer.Option(None, "--figures", help="Write PNG figures (Figs. 4, 7-12) here."),
    band_factor: float = typer.Option(2.0, help="Excite harmonics 1..band_factor*k (k of Table 2)."),
    periods: int = typer.Option(4, min=1, help="Multisine periods simulated per case."),
    peak: float = typer.Option(0.3, min=1e-9, help="Peak excitation torque [N m]."),
    beyond: bool = typer.Option(True, help="Also run the estimators beyond the paper."),
    sensitivity: bool = typer.Option(False, "--sensitivity", help="Also sweep band and amplitude (LS errors)."),
    noise_study: Path | None = typer.Option(None, "--noise-study",
                                               help="Run the quantization x torque-noise x method study; "
                                                    "write noise_study.png and .csv here."),
) -> None:
    """Run both cases of Table 2 and print Tables 2-6: paper value, our value, error %."""
    from rt_ident.reports import reproduce as rp

    if figures is not None or noise_study is not None:
        require("matplotlib", "plots", "--figures / --noise-study")

    methods = _beyond_methods() if beyond else ()
    with _progress() as prog:
        task = prog.add_task("reproduce", total=1.0)

        def progress(desc: str, frac: float) -> None:
            prog.update(task, description=desc, completed=frac)

        result = rp.run_reproduce(band_factor=band_factor, periods=periods, peak_torque=peak, beyond=methods,
                                  keep_arrays=figures is not None, progress=progress)
        sens = None
        if sensitivity:
            prog.update(task, description="band/amplitude sensitivity", completed=0.0)
            sens = rp.sensitivity()
        study = None
        if noise_study is not None:
            from rt_ident.reports import noise_study as ns

            study = ns.run_study(progress)
    written = []
    if figures is not None:
        from rt_ident.reports.figures import write_figures

        written = [str(p) for p in write_figures(result, figures)]
    if study is not None and noise_study is not None:
        written += _write_study(study, noise_study)
    if json_out:
        doc = result.as_json()
        if sens is not None:
            doc["sensitivity"] = sens
        if study is not None:
            doc["noise_study"] = study
        if written:
            doc["figures"] = written
        typer.echo(json.dumps(doc, indent=2))
        return
    _print_reproduce(result, sens)
    if study is not None:
        _print_study(study)
    for path in written:
        err.print(f"wrote {path}", markup=False)


def _write_study(rows, folder: Path) -> list[str]:
    import csv

    from rt_ident.reports.noise_study import write_png

    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "noise_study.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return [str(folder / "noise_study.csv"), str(write_png(rows, folder / "noise_study.png"))]


def _print_study(rows) -> None:
    from rt_ident.reports.noise_study import METHODS, TORQUE_NOISE_PCT

    tab = Table(title="Noise study - max |error| over I1, I2, B, K [%] (closed loop, angles only, 34 kHz)")
    tab.add_column("encoder counts/rev")
    tab.add_column("torque noise %", justify="right")
    for m in METHODS:
        tab.add_column(m, justify="right")
    for cpr in dict.fromkeys(r["counts_per_rev"] for r in rows):
        for noise in TORQUE_NOISE_PCT:
            vals = {r["method"]: r["max_error_pct"] for r in rows
                    if r["counts_per_rev"] == cpr and r["torque_noise_pct"] == noise}
            tab.add_row("ideal" if cpr == 0 else str(cpr), f"{noise:g}",
                        *["failed" if math.isnan(vals[m]) else fmt(vals[m]) for m in METHODS])
    out.print(tab)


def _beyond_methods() -> tuple[str, ...]:
    from rt_ident.reports.reproduce import BEYOND

    return tuple(BEYOND)


def _print_reproduce(result, sens) -> None:
    from rt_ident.reports import paper_tables
    from rt_ident.reports.reproduce import ALL_KEYS, MODAL_KEYS, PARAM_KEYS, error_pct

    t2 = Table(title="Table 2 - time step  Dt = 2 pi k / (N wn),  w0 = wn / k")
    for col in ("N", "k", "wn paper", "wn ours", "w0 paper", "w0 ours", "Dt paper \\[s]", "Dt ours \\[s]", "Dt diff %"):
        t2.add_column(col, justify="right")
    for paper, ours in zip(paper_tables.TABLE2, result.table2):
        t2.add_row(str(ours["N"]), str(ours["k"]), fmt(paper["wn"]), fmt(ours["wn"]), fmt(paper["w0"]),
                   fmt(ours["w0"]), fmt(paper["dt"]), fmt(ours["dt"]), f"{error_pct(ours['dt'], paper['dt']):.3g}")
    out.print(t2)
    tables = (("Table 3 - LS, physical parameters", "ls", paper_tables.LS, PARAM_KEYS),
              ("Table 4 - LS, modal parameters", "ls", paper_tables.LS, MODAL_KEYS),
              ("Table 5 - RLS, physical parameters", "rls", paper_tables.RLS, PARAM_KEYS),
              ("Table 6 - RLS, modal parameters", "rls", paper_tables.RLS, MODAL_KEYS))
    flagged = False
    for title, attr, paper_table, keys in tables:
        tab = Table(title=title)
        for col in ("case", "param", "true", "paper", "ours", "paper err %", "our err %", ""):
            tab.add_column(col, justify="left" if col in ("case", "param") else "right")
        for c in result.cases:
            pc = paper_table[(c.N, c.k)]
            for i, key in enumerate(keys):
                ours = getattr(c, attr)[key]
                e_ours = error_pct(ours, result.truth[key])
                e_paper = pc["error_pct"][key]
                ratio = (e_ours / e_paper) if e_paper > 0 else math.inf
                flag = ""
                if ratio > 10 or ratio < 0.1:
                    flag, flagged = ">10x", True
                tab.add_row(f"N={c.N} k={c.k}" if i == 0 else "", key, fmt(result.truth[key]),
                            fmt(pc["estimate"][key]), fmt(ours), fmt(e_paper), fmt(e_ours), flag,
                            end_section=(i == len(keys) - 1))
        out.print(tab)
    fit = Table(title="Eq. (18) - identified excitation, NRMSE against the true torque")
    fit.add_column("case")
    fit.add_column("LS", justify="right")
    fit.add_column("RLS", justify="right")
    for c in result.cases:
        fit.add_row(f"N={c.N} k={c.k}", fmt(c.ls_fit_nrmse), fmt(c.rls_fit_nrmse))
    out.print(fit)
    if any(c.beyond for c in result.cases):
        bt = Table(title="Beyond the paper - error % of each method on the same data (paper's LS/RLS for reference)")
        bt.add_column("case")
        bt.add_column("method")
        for key in ALL_KEYS:
            bt.add_column(key, justify="right")
        for c in result.cases:
            pl, pr = paper_tables.LS[(c.N, c.k)], paper_tables.RLS[(c.N, c.k)]
            bt.add_row(f"N={c.N}", "paper LS (printed)", *[fmt(pl["error_pct"][k]) for k in ALL_KEYS])
            bt.add_row("", "paper RLS (printed)", *[fmt(pr["error_pct"][k]) for k in ALL_KEYS])
            bt.add_row("", "Euler LS (ours)", *[fmt(error_pct(c.ls[k], result.truth[k])) for k in ALL_KEYS])
            for name, est in c.beyond.items():
                bt.add_row("", name, *[fmt(error_pct(est[k], result.truth[k])) for k in ALL_KEYS])
        out.print(bt)
    if sens:
        st = Table(title="Sensitivity of the paper's LS to the unstated band and amplitude (error %)")
        for col in ("N", "band", "peak [N m]", *ALL_KEYS):
            st.add_column(col, justify="right")
        for r in sens:
            st.add_row(str(r["N"]), f"{r['band'][0]}..{r['band'][1]}", fmt(r["peak"]),
                       *[fmt(r["error_pct"][k]) for k in ALL_KEYS])
        out.print(st)
    out.print(f"Excitation: Schroeder multisine, harmonics 1..{result.band_factor:g}*k, "
              f"peak {result.peak_torque:g} N m, "
              f"{result.periods} periods, Newmark alpha=1/4 delta=1/2, from rest.")
    if flagged:
        out.print("[bold]>10x[/bold]: our error differs from the paper's by more than 10x. The paper does not state "
                  "the multisine band or amplitude, and its RLS beating its LS on the same data contradicts its own "
                  "Theorem 1; see docs/theory/paper.md.")


# --------------------------------------------------------------------------- run
@app.command()
def run(
    config: Path | None = typer.Argument(None, help="Run config (TOML). Default: configs/sim.toml."),
    duration: float | None = typer.Option(None, "--duration", min=0.001, help="Seconds to run."),
    rrd: str | None = typer.Option(None, "--rrd", help="Write the dashboard recording here (.rrd)."),
    record: str | None = typer.Option(None, "--record", help="Record raw samples here (.parquet)."),
    spawn: bool = typer.Option(False, "--spawn", help="Spawn a rerun viewer (bound to 127.0.0.1)."),
    connect: str | None = typer.Option(None, "--connect", help="Stream to a viewer at rerun+http://HOST:PORT/proxy."),
    serve: bool = typer.Option(False, "--serve", help="Serve telemetry over gRPC on 127.0.0.1."),
    no_telemetry: bool = typer.Option(False, "--no-telemetry", help="No rerun streaming."),
    method: str | None = typer.Option(None, "--method", help="Streaming estimator (frequency, paper)."),
    control: str | None = typer.Option(None, "--control",
                                       help="Host position loop: adaptive, fixed (nominal design), conservative "
                                            "(rigid-body) or off (excitation only; needs a drive-side hold)."),
    no_realtime: bool = typer.Option(False, "--no-realtime", help="Do not ask for SCHED_FIFO/mlockall."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --rrd / --record file."),
    require_commissioned: bool = typer.Option(False, "--require-commissioned",
                                              help="Refuse a closed-loop run on a device that has not passed "
                                                   "`rt-ident commission` with this config."),
) -> None:
    """Run the real-time identification loop (sim by default) with a live dashboard and a recording."""
    from rt_ident import config as cfgmod

    sink = "off" if no_telemetry else "spawn" if spawn else "connect" if connect else "serve" if serve else None
    if control is not None and control not in ("adaptive", "fixed", "conservative", "off"):
        raise typer.BadParameter(f"--control must be adaptive, fixed, conservative or off, got {control!r}")
    overrides = {"loop.duration": duration, "estimator.method": method, "control.mode": control}
    if no_realtime:
        overrides["loop.realtime"] = False
    cfg = cfgmod.load(config, **overrides)
    _check_rrd_sink(rrd or (cfg.telemetry.rrd if sink is None else None), sink or cfg.telemetry.sink, sink is not None,
                    "--rrd" if rrd else "telemetry.rrd")
    # the loop's modules (numba, scipy, python-control: seconds) only once the config is known to be good,
    # beside the helpers' forkserver importing its own
    early = prestart()
    try:
        from rt_ident.compose.preflight import preflight
        from rt_ident.compose.run import exit_code
        from rt_ident.compose.run import run as run_loop

        preflight(cfg, sink=sink, connect_url=connect)   # a setting the start would refuse: one line, nothing started
        commissioned = _commissioning(cfg, config, require_commissioned)
    except BaseException:
        early.discard()
        raise
    if cfg.defaulted:
        what = {"axis": "the THOMSON X axis's values", "backend": "the sim backend",
                "safety": f"the travel window {list(cfg.safety.window)} m"}
        err.print(f"[yellow]warning:[/yellow] {escape(str(cfg.source))} has no "
                  f"{escape(', '.join(f'[{s}]' for s in cfg.defaulted))}: running on the built-in "
                  f"{'default' if len(cfg.defaulted) == 1 else 'defaults'}, "
                  f"{', '.join(what[s] for s in cfg.defaulted)}", highlight=False)
    if not json_out:
        err.print(f"running {cfg.backend.name} for {cfg.loop.duration:g} s "
                  f"(method {cfg.estimator.method}, tick {cfg.loop.tick_hz:g} Hz); Ctrl-C stops safely")
        if not kernel_cache.tick_kernel_cached():
            err.print("compiling the loop's kernels first (after an install or a change of the sources; "
                      "about 20 s, before anything is energized)")
    per_axis = (commissioned or {}).get("axes") or ({"": commissioned} if commissioned else {})
    summary = run_loop(cfg, rrd=rrd, record=record, sink=sink, connect_url=connect, overwrite=overwrite,
                       commissioned_units={n: c.get("unit") for n, c in per_axis.items()},
                       require_commissioned=require_commissioned)
    for name, other in (summary.get("commissioned_unit") or {}).items():   # a pass of another unit is none
        per_axis[name] = {"verdict": None, "warning": other["message"]}
    if commissioned is not None and cfg.axes:
        verdicts = {c.get("verdict") for c in per_axis.values()}
        commissioned = {"verdict": "pass" if verdicts == {"pass"} else None, "axes": per_axis}
    elif commissioned is not None:
        commissioned = per_axis[""]
    if commissioned is not None:
        summary["commissioning"] = commissioned
    if cfg.defaulted:
        summary["config_defaulted"] = list(cfg.defaulted)
    if json_out:
        typer.echo(json.dumps(summary, indent=2, default=json_default))
    elif "axes" in summary:
        print_axes(summary)
    else:
        print_run(summary)
    raise typer.Exit(exit_code(summary))


def _commissioning(cfg, config: Path | None, required: bool) -> dict | None:
    """The device's last commissioning verdict, said before anything is enabled: a warning when it never
    passed (an error with ``--require-commissioned``). None for a run that needs none (the plain sim). With
    several axes, each axis's device is looked up as the config of that axis alone: ``{"axes": {NAME: ...}}``."""
    from rt_ident.commission import ledger

    if cfg.axes and cfg.control.mode != "off":
        per = {name: _commissioning_of(acfg, config, required, name) for name, acfg in cfg.axis_configs().items()
               if ledger.needs_commissioning(acfg)}
        return {"axes": per} if per else None
    if not ledger.needs_commissioning(cfg):
        return None
    return _commissioning_of(cfg, config, required)


def _commissioning_of(cfg, config: Path | None, required: bool, axis: str = "") -> dict:
    from rt_ident.commission import ledger

    entry = ledger.lookup(cfg)
    if entry is not None and entry.get("verdict") == "pass":
        return {"verdict": "pass", "report": entry.get("report"), "unit": entry.get("unit")}
    changed = ledger.changed_since_commissioned(cfg) if entry is None else None
    why = (f"has changed since it was commissioned ({changed})" if changed else
           "has never been commissioned" if entry is None else
           f"failed commissioning ({(entry.get('failed') or {}).get('check')}: "
           f"{(entry.get('failed') or {}).get('fix')})")
    what, how = (f"axis {axis}'s device configuration", "give the axis a config of its own (its [axes.NAME] "
                 "sections at the top level) and run `rt-ident commission` on it") if axis else \
        ("this device configuration", f"run `rt-ident commission {config or 'CONFIG'}`")
    msg = f"{what} {why}; a wrong sign or scale makes the host's position loop run away: {how} first"
    if required:
        raise ConfigError("--require-commissioned", msg)
    err.print(f"[yellow]warning:[/yellow] {escape(msg)}", highlight=False)
    return {"verdict": None if entry is None else entry.get("verdict"), "warning": msg}


def _check_rrd_sink(rrd: str | None, sink: str, from_flag: bool, field: str = "--rrd") -> None:
    """``--rrd FILE`` (or ``telemetry.rrd``) is written by the rrd sink only: refused with a live or no
    sink, not dropped."""
    if rrd and sink != "rrd":
        flag = ({"off": "--no-telemetry", "connect": "--connect", "serve": "--serve", "spawn": "--spawn"}[sink]
                if from_flag else f'telemetry.sink = "{sink}"')
        does = ("sends no dashboard" if sink == "off" else "serves the dashboard live" if sink == "serve"
                else "streams the dashboard to a viewer")
        raise RtIdentError(f"{field}: {flag} {does}, so {rrd} would not be written; drop {field}, or drop {flag} "
                           "to write the file (a live dashboard is saved from the viewer)")


# --------------------------------------------------------------------------- identify
@app.command()
def identify(
    file: Path | None = typer.Argument(None, help="A recording (.parquet from `run`) or a CSV t,theta1,theta2,torque "
                                          "(t,theta1,torque with --model rigid-friction); a recording's torque_cmd and "
                                          "torque_meas columns stand in for torque."),
    method: str | None = typer.Option(None, "--method", help="Estimator name (see --methods)."),
    model: str | None = typer.Option(None, "--model", help="two-inertia (default), two-inertia-friction or "
                                        "rigid-friction (the friction models: method svf-ls)."),
    validate: Path | None = typer.Option(None, "--validate", help="Another recording: report the identified "
                                            "model's relative torque-prediction error on it (--model fits)."),
    methods: bool = typer.Option(False, "--methods", help="List the estimators and exit."),
    period: int | None = typer.Option(None, "--period", min=2, help="Excitation period in samples (else detected)."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Identify I1, I2, B, K (and wn, wd, zeta) offline from a recording; with --model, friction too."""
    if methods:
        from rt_ident.estimators.registry import DEFAULT_METHOD, list_methods

        ms = list_methods()
        if json_out:
            typer.echo(json.dumps([m.name for m in ms]))
            return
        tab = Table(title="estimators (rt-ident identify --method NAME)")
        tab.add_column("name")
        tab.add_column("needs")
        tab.add_column("models (--model)")
        tab.add_column("when to use it")
        for m in ms:
            tab.add_row(m.name + (" (default)" if m.name == DEFAULT_METHOD else ""), m.needs, ", ".join(m.models),
                        m.summary)
        out.print(tab)
        return
    if file is None:
        raise typer.BadParameter("give a recording FILE (or --methods)")
    from rt_ident.reports.identify import identify_file

    ident, info = identify_file(file, method, period=period, model=model)
    validation = None
    if validate is not None:
        from rt_ident.estimators.friction import FrictionIdentification
        from rt_ident.reports.identify import validate_file

        validation = validate_file(ident, validate)
        assert isinstance(ident, FrictionIdentification)   # validate_file takes no other
        ident = ident.with_validation(validation)     # the validation is one of the verdict's criteria
    d = ident.as_dict()
    if validation is not None:
        d["validation"] = validation
    if json_out:
        typer.echo(json.dumps({**d, "input": info}, indent=2, default=json_default))
        return
    tab = param_table(f"{file} - method {d['method']} ({info['how']}, {info['samples']} samples)")
    for k, v in d["parameters"].items():
        tab.add_row(k, UNITS.get(k, ""), fmt(v), interval((d.get("ci95") or {}).get(k)))
    out.print(tab)
    if "fit" in d:      # a --model fit (svf-ls): units are the file's own (N m and rad, or N and m)
        out.print(f"model {d['model']}: torque fit NRMSE {d['fit']['nrmse_percent']:.2f} %")
    if "validation" in d:
        v = d["validation"]
        out.print(f"validation on {v['file']}: torque prediction error {v['torque_error_percent']:.2f} % "
                  f"(correlation {v['correlation']:.4f}, {v['samples_used']} samples in motion)", markup=False)
    print_trust(d.get("trust"), d["trusted"])


# --------------------------------------------------------------------------- commission
@app.command()
def commission(
    config: Path = typer.Argument(..., help="The axis's run config (TOML)."),
    out_dir: Path | None = typer.Option(None, "--out", help="Folder for the report and the \\[axis] snippet "
                                             "(default runs/commission-DATE-TIME)."),
    json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
) -> None:
    """Check a real axis before closing the loop on it: signs, scales, torque, then identify, design and
    verify with a small move; write an HTML report and an \\[axis] snippet. Exit 0 pass, 3 a failed check,
    130 interrupted (Ctrl-C, SIGTERM, SIGHUP: the device stopped, the report and commission.json written)."""
    import datetime as _dt

    from rt_ident import config as cfgmod

    cfg = cfgmod.load(config)
    if cfg.axes:
        raise ConfigError("axes", "commission one axis at a time: give a config per axis (copy the axis's "
                                  "[axes.NAME] sections to the top level)")
    folder = out_dir or Path("runs") / f"commission-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise ConfigError("--out", f"{folder} exists and is not an empty folder; choose another folder")
    early = prestart()                           # its imports beside those of the stages
    try:
        from rt_ident.commission.stages import commission as run_commission
    except BaseException:
        early.discard()
        raise

    def progress(msg: str) -> None:
        if not json_out:
            err.print(msg, highlight=False, markup=False)

    result = run_commission(cfg, folder, progress)
    if json_out:
        typer.echo(json.dumps(result, indent=2, default=json_default))
    else:
        for c in result["checks"]:
            mark = "[green]pass[/green]" if c["ok"] else "[red]FAIL[/red]"
            out.print(f"{mark} {escape(c['name'])}: {escape(_commission_value(c['measured']))}"
                      + ("" if c["ok"] else f" (expected: {escape(_commission_value(c['expected']))})"
                                            f" - fix: {escape(str(c['fix']))}")
                      + (f" - note: {escape(c['note'])}" if c.get("note") else ""), highlight=False)
        out.print(f"verdict: {result['verdict']} (stage {result['stage_reached']}); report {result['report']}"
                  + (f"; [axis] for run: {result['axis_toml']}" if result.get("axis_toml") else ""), highlight=False,
              markup=False)
    raise typer.Exit(0 if result["verdict"] == "pass" else 3)


def _commission_value(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_commission_value(x)}" for k, x in v.items())
    return str(v)


def _command():
    """The click command behind ``app``, with on/off flags shown as ``--flag`` or ``--flag/--no-flag``
    in ``--help`` rather than with a ``<bool>`` value they do not take."""
    cmd = typer.main.get_command(app)

    def fix(c) -> None:   # typer vendors its own click: duck-typed, not isinstance(click.Option)
        for p in c.params:
            if getattr(p, "is_flag", False):
                p.metavar = ""
        made = c.get_help_option

        def help_option(ctx, made=made):
            opt = made(ctx)
            if opt is not None:
                opt.metavar = ""
            return opt

        c.get_help_option = help_option
        for sub in getattr(c, "commands", {}).values():
            fix(sub)

    fix(cmd)
    return cmd


def _from_ctrl_c(exc: BaseException) -> bool:
    """True when a KeyboardInterrupt is among the exceptions ``exc`` was raised from or during."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def _environment_error(exc: OSError) -> int | None:
    """A full disk, a refused permission or a path of the wrong kind that no part of the command turned into
    its own message: one line and exit 4 (its output is incomplete) or 2 (a permission or a path to fix); None
    for any other OSError, which is then an internal error."""
    import errno

    full = {errno.ENOSPC, errno.EDQUOT, errno.EROFS}
    refused = {errno.EACCES, errno.EPERM}
    misplaced = {errno.ENOTDIR, errno.EISDIR}
    if exc.errno not in full | refused | misplaced:
        return None
    if _VERBOSE:
        err.print_exception()
    where = f"{exc.filename}: " if exc.filename else ""
    if exc.errno in misplaced:
        err.print(f"[red]error:[/red] {escape(where)}{escape(exc.strerror or str(exc))}: a file where a folder was "
                  "meant, or the other way round; choose another path", highlight=False)
        return 2
    if exc.errno in full:
        fix = "write elsewhere" if exc.errno == errno.EROFS else "make room (or write elsewhere)"
        err.print(f"[red]error:[/red] {escape(where)}{escape(exc.strerror or str(exc))}: what this command was "
                  f"writing is incomplete; {fix} and run it again", highlight=False)
        return 4
    err.print(f"[red]error:[/red] {escape(where)}{escape(exc.strerror or str(exc))}: this user may not do that "
              "there; choose another place or fix the permission", highlight=False)
    return 2


def main() -> None:
    """The ``rt-ident`` entry point. Exit codes: 0 ok, 2 bad input (one line naming the setting),
    3 a run stopped by a fault or trip, 4 data lost (a full disk included), 1 an internal error (one line; -v: the
    traceback)."""
    tolerate_gone_terminal()                     # a run outlives its terminal's hang-up: its exit code is its own
    handler = logging.StreamHandler()
    handler.setFormatter(_OneLineFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    try:
        _command()(prog_name="rt-ident")
    except RtIdentError as exc:
        if _VERBOSE:
            err.print_exception()
        err.print(f"[red]error:[/red] {escape(str(exc))}", highlight=False)
        sys.exit(2)
    except KeyboardInterrupt:                    # Ctrl-C before a run's own handler is installed
        err.print("interrupted")
        sys.exit(130)
    except SystemExit as exc:                    # typer turns that Ctrl-C into a silent exit 130
        if exc.code == 130 and _from_ctrl_c(exc):
            err.print("interrupted")
        raise
    except Exception as exc:  # noqa: BLE001 - a bug: one line for the user, the traceback with -v
        code = _environment_error(exc) if isinstance(exc, OSError) else None
        if code is not None:
            sys.exit(code)
        if _VERBOSE:
            err.print_exception()
        err.print(f"[red]internal error:[/red] {type(exc).__name__}: {escape(str(exc))} (rt-ident -v ... shows where; "
                  "please report it)", highlight=False)
        sys.exit(1)


if __name__ == "__main__":
    main()

"""``rt-ident fleet identify | drift | report | query | make`` (mounted by :mod:`rt_ident.cli`)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.table import Table

fleet_app = typer.Typer(no_args_is_help=True,
                        help="Many axes' recordings: identify on Dask, keep a history, flag drift.")
err = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)

@fleet_app.callback()
def _needs_the_fleet_extra(ctx: typer.Context) -> None:
    from rt_ident.errors import require

    if ctx.invoked_subcommand == "make":          # simulation and Parquet only: the core install
        return
    for module in ("dask", "distributed", "duckdb"):
        require(module, "fleet", "rt-ident fleet")


HISTORY = typer.Option(..., "--history", help="The fleet's Parquet history to read (only read, never written): a "
                       "folder or an fsspec URL such as s3://bucket/fleet.")
HISTORY_WRITTEN = typer.Option(..., "--history", help="The fleet's Parquet history new results are added to: a "
                               "folder (created if missing) or an fsspec URL such as s3://bucket/fleet.")


@fleet_app.command("identify")
def identify_cmd(
    manifest: Path = typer.Argument(..., help="CSV with columns path, machine, axis, time (ISO 8601). Recording "
                                              "paths must be regular files under the manifest's folder (or remote "
                                              "URLs such as s3://...)."),
    history: str = HISTORY_WRITTEN,
    scheduler: str | None = typer.Option(None, "--scheduler", help="A running Dask scheduler, e.g. "
                                            "tcp://10.0.0.5:8786 (workers need rt-ident installed). Default: a "
                                            "LocalCluster on 127.0.0.1."),
    workers: int = typer.Option(2, "--workers", min=1, help="LocalCluster worker processes."),
    method: str | None = typer.Option(None, "--method", help="Estimator (default: the recording's own)."),
    allow_outside: bool = typer.Option(False, "--allow-outside", help="Also read recordings outside the "
                                       "manifest's folder and URLs of any fsspec filesystem (a recording must "
                                       "still be a regular file)."),
    flush_every: float = typer.Option(2.0, "--flush-every", min=0.05, help="Seconds between writes of finished "
                                      "results to the history (they are written on Ctrl-C/SIGTERM/SIGHUP too)."),
    task_timeout: float = typer.Option(600.0, "--task-timeout", min=0.0, help="Seconds one recording may take; "
                                       "a task still running then is reported failed and the run goes on "
                                       "(0: no limit)."),
    json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
) -> None:
    """Identify every recording of MANIFEST (one Dask task each); add new results to the history. Exit 0 all
    identified or already there, 1 some failed, 2 bad input, 4 the history refused a write (a full disk: what
    was written before is kept), 130 interrupted (what finished is kept)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from rt_ident.fleet.identify import identify_fleet
    from rt_ident.fleet.manifest import read_manifest

    entries = read_manifest(manifest, allow_outside=allow_outside)
    bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("failed {task.fields[failed]}"), TimeElapsedColumn(), console=err, transient=True)
    state: dict[str, Any] = {"failed": 0}

    def started(n: int, dashboard: str | None) -> None:
        where = f"dashboard {dashboard}" if dashboard else "dashboard: none (bokeh not installed)"
        err.print(f"{n} recordings; Dask {where}")
        state["task"] = bar.add_task("identifying", total=n, failed=0)

    def done(row: dict[str, Any]) -> None:
        if row["status"] == "failed":
            state["failed"] += 1
        bar.update(state["task"], advance=1, failed=state["failed"])

    with bar:
        res = identify_fleet(entries, history, scheduler=scheduler, workers=workers, method=method,
                             flush_every=flush_every, task_timeout=task_timeout or None,
                             on_start=started, on_result=done)
    if json_out:
        typer.echo(json.dumps(res, indent=2))
    else:
        twice = f", {res['duplicates']} listed more than once" if res["duplicates"] else ""
        out.print(f"{res['identified']} identified ({res['untrusted']} not trusted), {res['skipped']} already in the "
                  f"history, {res['failed']} failed{twice} -> {res['history']}", highlight=False, markup=False)
        for f in res["failures"]:
            out.print(f"  failed: {f['path']} ({f['machine']} {f['axis']}): {f['error']}", highlight=False,
                      markup=False)
    if res["write_error"]:
        left = res["tasks"] - res["identified"] - res["skipped"] - res["failed"]
        err.print(f"error: cannot write to the history: {res['write_error']}; the {res['identified']} results "
                  f"written before are in {res['history']}, {res['unwritten']} finished results could not be "
                  f"kept; make room and run the same command again to identify the other {left}",
                  highlight=False, markup=False)
        raise typer.Exit(4)
    if res["interrupted"]:
        left = res["tasks"] - res["identified"] - res["skipped"] - res["failed"]
        rest = (f"; run the same command again to identify the other {left}" if left > 0
                else " (every task had finished)")
        err.print(f"interrupted: the {res['identified']} results finished are in {res['history']}{rest}",
                  highlight=False, markup=False)
        raise typer.Exit(130)
    if res["failed"]:
        raise typer.Exit(1)



def _when(iso: str) -> str:
    return iso[:16].replace("T", " ")


def _alarm_line(a: dict[str, Any]) -> str:
    from rt_ident.fleet.findings import limit_words

    since = f"since {_when(a['since'])}, first alarm {_when(a['first_alarm'])}"
    rate = "" if a["rate_percent_per_day"] is None else f"; {a['rate_percent_per_day']:+.2f} %/day"
    return (f"{a['parameter']:<5} {a['direction']} {since}: {a['change_at_first_alarm_percent']:+.2f} % at first "
            f"alarm, {a['change_now_percent']:+.2f} % now ({_when(a['now_time'])}), both vs baseline{rate}; "
            f"{limit_words(a)} [{a['severity']}]")


def print_states(res: dict[str, Any]) -> None:
    """Every series' state, worst first, in plain lines (what ``fleet drift`` prints)."""
    counts = ", ".join(f"{n} {st.replace('-', ' ')}" for st, n in res["counts"].items() if n)
    typer.echo(f"{len(res['series'])} series: {counts}")
    typer.echo(f"{res['method']}; limits: {res['limits']['source']}")
    ign = res["ignored"]
    if ign["untrusted"] or ign["unknown_verdict"]:
        typer.echo(f"skipped {ign['untrusted'] + ign['unknown_verdict']} rows: {ign['untrusted']} not trusted, "
                   f"{ign['unknown_verdict']} with no recorded verdict (written by an older rt-ident: treated as "
                   "untrusted; `fleet identify` on their manifest records one); per series below")
    for s in res["series"]:
        name = f"{s['machine']} {s['axis']}"
        if s["state"] != "drifting":
            said = s["message"].startswith(s["state"].replace("-", " "))
            typer.echo(f"{name}  {s['message']}" if said else f"{name}  {s['state']}: {s['message']}")
            continue
        typer.echo(f"{name}  DRIFTING, {s['severity']}")
        for f in s["findings"]:
            typer.echo(f"  finding [{f['severity']}]: {f['finding']}")
            typer.echo(f"  check: {f['check']}")
        for a in s["alarms"]:
            typer.echo(f"  {_alarm_line(a)}")
        skipped = s["skipped_untrusted"] + s["skipped_unknown_verdict"]
        if skipped or not s["latest"]["trusted"]:
            typer.echo(f"  {s['trusted']} of {s['recordings']} recordings trusted ({skipped} skipped)"
                       + ("; the latest is not trusted" if not s["latest"]["trusted"] else ""))


LIMITS = typer.Option(None, "--limits", help="TOML: how far each parameter may move from its baseline, in per cent, "
                      "e.g. [K] fall = 15; and soon_days (default 30). Sets each alarm's severity. Default: built-in "
                      "limits (docs: operation/fleet).")


@fleet_app.command("drift")
def drift_cmd(
    history: str = HISTORY,
    baseline: int = typer.Option(5, "--baseline", min=2, help="Trusted recordings per series that set its baseline."),
    h: float = typer.Option(5.0, "--h", min=0.5, help="CUSUM decision interval (in sigmas)."),
    limits: Path | None = LIMITS,
    json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
) -> None:
    """Every machine and axis: ok, drifting (what moved, since when, what it means, how urgent),
    insufficient history or untrusted data."""
    from rt_ident.fleet.drift import DriftSettings, drift
    from rt_ident.fleet.findings import read_limits

    res = drift(history, DriftSettings(baseline=baseline, h=h), read_limits(limits))
    res.pop("_detail")
    if json_out:
        typer.echo(json.dumps(res, indent=2))
        return
    print_states(res)


@fleet_app.command("report")
def report_cmd(
    history: str = HISTORY,
    out_dir: Path = typer.Option(..., "--out", help="Folder for report.html and the CSV data behind it."),
    baseline: int = typer.Option(5, "--baseline", min=2, help="Trusted recordings per series that set its baseline."),
    h: float = typer.Option(5.0, "--h", min=0.5, help="CUSUM decision interval (in sigmas)."),
    limits: Path | None = LIMITS,
) -> None:
    """One self-contained HTML page: the fleet worst first, each axis's trends, findings and checks;
    the data behind it as CSV beside it."""
    from rt_ident.fleet.drift import DriftSettings
    from rt_ident.fleet.findings import read_limits
    from rt_ident.fleet.report import write_report

    res = write_report(history, out_dir, DriftSettings(baseline=baseline, h=h), read_limits(limits))
    counts = ", ".join(f"{n} {st.replace('-', ' ')}" for st, n in res["counts"].items() if n)
    out.print(f"{res['series']} series ({counts}): {res['html']}; data: {res['fleet_csv']} and "
              f"{len(res['series_csv'])} series CSV files in {res['data_dir']}", markup=False, highlight=False)


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return "-" if math.isnan(v) else f"{v:.6g}"
    return str(v)


@fleet_app.command("query")
def query_cmd(
    sql: str = typer.Argument(..., help='One SELECT on the view "history", e.g. "SELECT machine, axis, avg(K) FROM '
                                        'history GROUP BY ALL".'),
    history: str = HISTORY,
    json_out: bool = typer.Option(False, "--json", help="Rows as JSON objects on stdout."),
) -> None:
    """Run one SELECT (DuckDB) over the fleet history. Read-only: another statement, a second statement or
    any file, network or extension access outside the history is refused (exit 2)."""
    from rt_ident.fleet.history import query

    cols, rows = query(history, sql)
    if json_out:
        typer.echo(json.dumps([dict(zip(cols, r)) for r in rows], indent=2, default=str))
        return
    print_rows(out, cols, rows)


def print_rows(console: Console, cols: list[str], rows: list[tuple[Any, ...]]) -> None:
    """A table where its columns fit the console; otherwise one block of "column  value" lines per row, as a
    squeezed table would show wide results (``SELECT *``) as empty columns."""
    from rich.measure import Measurement

    tab = Table()
    for c in cols:
        tab.add_column(c)
    for r in rows:
        tab.add_row(*(_cell(v) for v in r))
    if Measurement.get(console, console.options.update_width(1 << 20), tab).minimum <= console.width:
        console.print(tab)
        return
    pad = max((len(c) for c in cols), default=0)
    for i, r in enumerate(rows, 1):
        console.print(f"-- row {i} --", markup=False, highlight=False)
        for c, v in zip(cols, r):
            console.print(f"{c.ljust(pad)}  {_cell(v)}", markup=False, highlight=False)
    console.print(f"({len(rows)} row{'' if len(rows) == 1 else 's'})", markup=False, highlight=False)


def _mount_make() -> None:
    from rt_ident.fleet.make import make_cmd

    fleet_app.command("make")(make_cmd)


_mount_make()


__all__ = ["fleet_app"]

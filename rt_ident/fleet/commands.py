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
    for module in ("dask", "distributed", "duckdb", "matplotlib"):
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
                                      "results to the history (they are written on Ctrl-C/SIGTERM too)."),
    task_timeout: float = typer.Option(600.0, "--task-timeout", min=0.0, help="Seconds one recording may take; "
                                       "a task still running then is reported failed and the run goes on "
                                       "(0: no limit)."),
    json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
) -> None:
    """Identify every recording of MANIFEST (one Dask task each); add new results to the history. Exit 0 all
    identified or already there, 1 some failed, 2 bad input, 130 interrupted (what finished is kept)."""
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
                  f"history, {res['failed']} failed{twice} -> {res['history']}", highlight=False)
        for f in res["failures"]:
            out.print(f"  failed: {f['path']} ({f['machine']} {f['axis']}): {f['error']}", highlight=False)
    if res["interrupted"]:
        err.print(f"interrupted: the {res['identified']} results finished are in {res['history']}; run the same "
                  "command again to identify the rest", highlight=False)
        raise typer.Exit(130)
    if res["failed"]:
        raise typer.Exit(1)


@fleet_app.command("drift")
def drift_cmd(
    history: str = HISTORY,
    baseline: int = typer.Option(5, "--baseline", min=2, help="Recordings per series that set its baseline."),
    h: float = typer.Option(5.0, "--h", min=0.5, help="CUSUM decision interval (in sigmas)."),
    json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
) -> None:
    """Per machine, axis and parameter: alarms where the estimates leave their baseline (CUSUM)."""
    from rt_ident.fleet.drift import DriftSettings, drift

    res = drift(history, DriftSettings(baseline=baseline, h=h))
    res.pop("_detail")
    if json_out:
        typer.echo(json.dumps(res, indent=2))
        return
    out.print(f"{res['series']} series, {res['checked']} parameter series checked ({res['method']})")
    ign = res["ignored"]
    if ign["untrusted"] or ign["unknown_verdict"]:
        out.print(f"ignored {ign['untrusted'] + ign['unknown_verdict']} rows: {ign['untrusted']} not trusted, "
                  f"{ign['unknown_verdict']} with no recorded verdict (written by an older rt-ident: treated as "
                  "untrusted; `fleet identify` on their manifest records one)")
    if not res["alarms"]:
        out.print("no drift alarms")
        return
    tab = Table(title=f"{len(res['alarms'])} drift alarms, largest change first")
    for c in ("machine", "axis", "parameter", "first alarm (UTC)", "change %", "recordings before"):
        tab.add_column(c, no_wrap=c.startswith("first"))
    for a in res["alarms"]:
        tab.add_row(a["machine"], a["axis"], a["parameter"], a["first_time"][:16].replace("T", " "),
                    f"{a['change_percent']:+.2f}",
                    str(a["recordings_before"]))
    out.print(tab)


@fleet_app.command("report")
def report_cmd(
    history: str = HISTORY,
    out_dir: Path = typer.Option(..., "--out", help="Folder for the figures and the summary."),
) -> None:
    """Trend plots per axis (intervals, baseline band, alarms) and a one-page summary, worst first."""
    from rt_ident.fleet.report import write_report

    res = write_report(history, out_dir)
    out.print(f"{res['series']} series, {res['alarms']} alarms: {res['summary_png']}, {res['summary_csv']} and "
              f"{len(res['figures'])} trend figures in {out_dir}")


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
    tab = Table()
    for c in cols:
        tab.add_column(c)
    for r in rows:
        tab.add_row(*(_cell(v) for v in r))
    out.print(tab)


def _mount_make() -> None:
    from rt_ident.fleet.make import make_cmd

    fleet_app.command("make")(make_cmd)


_mount_make()


__all__ = ["fleet_app"]

"""The ``rt-ident`` command line."""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from rt_ident.errors import RtIdentError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Identify a machine-tool axis (two-inertia spring-damper) from simulation or a bench.")
err = Console(stderr=True)
out = Console()


@app.callback()
def _root() -> None:
    """rt-ident: model, simulate and identify a machine-tool axis; run the real-time loop."""


def _fmt(x: float) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.4g}"


def _progress():
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                    TimeElapsedColumn(), console=err, transient=True)


# --------------------------------------------------------------------------- reproduce
@app.command()
def reproduce(
    json_out: bool = typer.Option(False, "--json", help="Print the results as JSON on stdout."),
    figures: Optional[Path] = typer.Option(None, "--figures", help="Write PNG figures (Figs. 4, 7-12) here."),
    band_factor: float = typer.Option(2.0, help="Excite harmonics 1..band_factor*k (k of Table 2)."),
    periods: int = typer.Option(4, min=1, help="Multisine periods simulated per case."),
    peak: float = typer.Option(0.3, min=1e-9, help="Peak excitation torque [N m]."),
    beyond: bool = typer.Option(True, help="Also run the estimators beyond the paper."),
    sensitivity: bool = typer.Option(False, "--sensitivity", help="Also sweep band and amplitude (LS errors)."),
) -> None:
    """Run both cases of Table 2 and print Tables 2-6: paper value, our value, error %."""
    from rt_ident import reproduce as rp

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
    written = []
    if figures is not None:
        from rt_ident.figures import write_figures

        written = [str(p) for p in write_figures(result, figures)]
    if json_out:
        doc = result.as_json()
        if sens is not None:
            doc["sensitivity"] = sens
        if written:
            doc["figures"] = written
        typer.echo(json.dumps(doc, indent=2))
        return
    _print_reproduce(result, sens)
    for path in written:
        err.print(f"wrote {path}")


def _beyond_methods() -> tuple[str, ...]:
    try:
        from rt_ident.estimators.registry import METHODS
    except ImportError:
        return ()
    return tuple(name for name, info in METHODS.items() if name != "paper" and info.needs == "states")


def _print_reproduce(result, sens) -> None:
    from rt_ident import paper_tables
    from rt_ident.reproduce import ALL_KEYS, MODAL_KEYS, PARAM_KEYS, error_pct

    t2 = Table(title="Table 2 - time step  Dt = 2 pi k / (N wn),  w0 = wn / k")
    for col in ("N", "k", "wn paper", "wn ours", "w0 paper", "w0 ours", "Dt paper [s]", "Dt ours [s]", "Dt diff %"):
        t2.add_column(col, justify="right")
    for paper, ours in zip(paper_tables.TABLE2, result.table2):
        t2.add_row(str(ours["N"]), str(ours["k"]), _fmt(paper["wn"]), _fmt(ours["wn"]), _fmt(paper["w0"]),
                   _fmt(ours["w0"]), _fmt(paper["dt"]), _fmt(ours["dt"]), f"{error_pct(ours['dt'], paper['dt']):.3g}")
    out.print(t2)
    tables = (("Table 3 - LS, physical parameters", "ls", paper_tables.LS, PARAM_KEYS),
              ("Table 4 - LS, modal parameters", "ls", paper_tables.LS, MODAL_KEYS),
              ("Table 5 - RLS, physical parameters", "rls", paper_tables.RLS, PARAM_KEYS),
              ("Table 6 - RLS, modal parameters", "rls", paper_tables.RLS, MODAL_KEYS))
    flagged = False
    for title, attr, paper, keys in tables:
        tab = Table(title=title)
        for col in ("case", "param", "true", "paper", "ours", "paper err %", "our err %", ""):
            tab.add_column(col, justify="left" if col in ("case", "param") else "right")
        for c in result.cases:
            pc = paper[(c.N, c.k)]
            for i, key in enumerate(keys):
                ours = getattr(c, attr)[key]
                e_ours = error_pct(ours, result.truth[key])
                e_paper = pc["error_pct"][key]
                ratio = (e_ours / e_paper) if e_paper > 0 else math.inf
                flag = ""
                if ratio > 10 or ratio < 0.1:
                    flag, flagged = ">10x", True
                tab.add_row(f"N={c.N} k={c.k}" if i == 0 else "", key, _fmt(result.truth[key]),
                            _fmt(pc["estimate"][key]), _fmt(ours), _fmt(e_paper), _fmt(e_ours), flag,
                            end_section=(i == len(keys) - 1))
        out.print(tab)
    fit = Table(title="Eq. (18) - identified excitation, NRMSE against the true torque")
    fit.add_column("case")
    fit.add_column("LS", justify="right")
    fit.add_column("RLS", justify="right")
    for c in result.cases:
        fit.add_row(f"N={c.N} k={c.k}", _fmt(c.ls_fit_nrmse), _fmt(c.rls_fit_nrmse))
    out.print(fit)
    if any(c.beyond for c in result.cases):
        bt = Table(title="Beyond the paper - error % of each method on the same data (paper's LS/RLS for reference)")
        bt.add_column("case")
        bt.add_column("method")
        for key in ALL_KEYS:
            bt.add_column(key, justify="right")
        for c in result.cases:
            pl, pr = paper_tables.LS[(c.N, c.k)], paper_tables.RLS[(c.N, c.k)]
            bt.add_row(f"N={c.N}", "paper LS (printed)", *[_fmt(pl["error_pct"][k]) for k in ALL_KEYS])
            bt.add_row("", "paper RLS (printed)", *[_fmt(pr["error_pct"][k]) for k in ALL_KEYS])
            bt.add_row("", "Euler LS (ours)", *[_fmt(error_pct(c.ls[k], result.truth[k])) for k in ALL_KEYS])
            for name, est in c.beyond.items():
                bt.add_row("", name, *[_fmt(error_pct(est[k], result.truth[k])) for k in ALL_KEYS])
        out.print(bt)
    if sens:
        st = Table(title="Sensitivity of the paper's LS to the unstated band and amplitude (error %)")
        for col in ("N", "band", "peak [N m]", *ALL_KEYS):
            st.add_column(col, justify="right")
        for r in sens:
            st.add_row(str(r["N"]), f"{r['band'][0]}..{r['band'][1]}", _fmt(r["peak"]),
                       *[_fmt(r["error_pct"][k]) for k in ALL_KEYS])
        out.print(st)
    out.print(f"Excitation: Schroeder multisine, harmonics 1..{result.band_factor:g}*k, peak {result.peak_torque:g} N m, "
              f"{result.periods} periods, Newmark alpha=1/4 delta=1/2, from rest.")
    if flagged:
        out.print("[bold]>10x[/bold]: our error differs from the paper's by more than 10x. The paper does not state "
                  "the multisine band or amplitude, and its RLS beating its LS on the same data contradicts its own "
                  "Theorem 1; see the README section 'Reproducing the paper'.")


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except RtIdentError as exc:
        err.print(f"[red]error:[/red] {exc}")
        sys.exit(2)


if __name__ == "__main__":
    main()

"""How a run's summary reads on the terminal: the parameter tables, the trust verdict and its reasons,
the loop's and the controller's lines, the stalls, and how the run ended with the setting that fixes it.
``out`` and ``err`` are the command line's consoles (stdout, stderr)."""

from __future__ import annotations

import errno
import sys
from collections.abc import Sequence
from typing import Any, TextIO

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rt_ident.outputs.text import fmt, um


class GoneTolerant:
    """A standard stream whose terminal may go away while the command works (a closed window, a dropped ssh
    session: EIO; a reader that quit: EPIPE). What can no longer be written is dropped, so the command ends
    as its work did (files closed, its exit code), not on its own output."""

    _GONE = frozenset({errno.EIO, errno.EPIPE, errno.ENXIO})

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self.gone = False

    def _guard(self, call: Any, *args: Any) -> Any:
        if self.gone:
            return None
        try:
            return call(*args)
        except OSError as exc:
            if exc.errno not in self._GONE:
                raise
            self.gone = True
            return None

    def write(self, text: str) -> int:
        self._guard(self._stream.write, text)
        return len(text)

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        self._guard(self._stream.flush)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def tolerate_gone_terminal() -> None:
    """Wrap stdout and stderr in :class:`GoneTolerant` (the command line's entry point, once)."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, GoneTolerant):
            setattr(sys, name, GoneTolerant(stream))

# soft_wrap: a line (a file path, a command to copy) is never broken at 80 columns when piped;
# tables still fit the width (their columns fold instead of cutting values to "2.948...")
err = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


UNITS = {"I1": "kg m²", "I2": "kg m²", "B": "N m s/rad", "K": "N m/rad", "wn": "rad/s", "wd": "rad/s", "zeta": "-",
         "J": "kg m²", "Fc": "N m", "Fv": "N m s/rad", "Fc1": "N m", "Fv1": "N m s/rad", "Fc2": "N m",
         "Fv2": "N m s/rad", "offset": "N m"}


def param_table(title: str, truth: bool = False) -> Table:
    """The parameter table of run and identify: values never cut ('fold' wraps a cell instead)."""
    tab = Table(title=escape(title), title_justify="left")
    tab.add_column("param", overflow="fold")
    tab.add_column("unit", overflow="fold")
    tab.add_column("estimate", justify="right", overflow="fold")
    tab.add_column("95 % interval", justify="right", overflow="fold")
    if truth:
        tab.add_column("true", justify="right", overflow="fold")
        tab.add_column("error %", justify="right", overflow="fold")
    return tab


def summary_table(title: str, s: dict) -> Table:
    """The parameter table of a run's (or one axis's) summary: estimate, interval, truth and error."""
    truth = bool(s.get("truth") and s.get("error_pct"))
    tab = param_table(title, truth)
    ci = s.get("ci95") or {}
    for k, v in (s.get("parameters") or {}).items():
        row = [k, UNITS.get(k, ""), fmt(v), interval(ci.get(k))]
        if truth:
            row += [fmt(s["truth"][k]), f"{s['error_pct'][k]:+.3f}"]
        tab.add_row(*row)
    return tab


def kept(redesigns: dict) -> str:
    """' (3 more kept the design in force)' when some accepted results kept it, else ''."""
    n = redesigns.get("kept") or 0
    return f" ({n} more kept the design in force)" if n else ""


def interval(ci: Sequence[float | None] | None) -> str:
    """A 95 % interval as "lo .. hi", or "-"."""
    return "-" if not ci else f"{fmt(ci[0])} .. {fmt(ci[1])}"


def print_run(s: dict) -> None:
    loop = s.get("loop") or {}
    if not loop.get("samples"):
        print_stop(s)
        if not s["stop"].get("cause"):
            out.print("the run read no samples")
        return
    lat = loop.get("lateness_us") or {}
    params = s.get("parameters") or {}
    out.print(summary_table(f"rt-ident run - {s['backend']} - method {s.get('method')}", s))
    if not params and s.get("final_fit_error"):
        out.print(f"no estimate: {s['final_fit_error']}", markup=False)
    elif not params:
        out.print("no estimate yet: the run ended before a full excitation period after the warm-up")
    else:
        print_trust(s.get("trust"), s.get("trusted"))
    out.print(f"loop: {loop.get('ticks', 0)} ticks, {loop.get('samples', 0)} samples, "
              f"{loop.get('overruns', 0)} overruns, lateness p50 {fmt(lat.get('p50'))} us, "
              f"p99 {fmt(lat.get('p99'))} us, max {fmt(lat.get('max'))} us; "
              f"telemetry dropped {s['telemetry'].get('dropped', 0)}"
              + (", [bold red]not delivered[/]" if s["telemetry"].get("delivered") is False else "")
              + (", [yellow]its process did not finish and was ended (the dashboard holds what it had written)[/]"
                 if s["telemetry"].get("terminated") else ""))
    print_stalls(loop)
    lost, n = loop.get("lost_samples") or 0, loop.get("samples") or 0
    if lost and lost > 0.01 * (n + lost):
        hint = ""
        if not (s.get("realtime") or {}).get("sched_fifo"):
            hint = ("; without real-time scheduling this host did not keep pace with the device "
                    "(run without --no-realtime, or lower the device's rate)")
        out.print(f"[yellow]lost {lost} samples[/] ({100 * lost / (n + lost):.1f} % of what the device sent){hint}")
    ctl = s.get("control") or {}
    if ctl.get("mode") not in (None, "off"):
        rd = ctl.get("redesigns") or {}
        line = (f"control: {ctl['mode']}, table error rms {fmt(um(ctl.get('rms_error_m')))} um, "
                f"max {fmt(um(ctl.get('max_error_m')))} um")
        if ctl.get("rms_error_after_change_m") is not None:
            line += f", rms after the plant change {fmt(um(ctl['rms_error_after_change_m']))} um"
        line += (f"; redesigns accepted {rd.get('accepted', 0)}{kept(rd)}, rejected {rd.get('rejected', 0)}; "
                 f"fallbacks {ctl.get('fallbacks', 0)}; running the {ctl.get('controller')} controller")
        out.print(line)
        for reason in rd.get("rejected_reasons") or []:
            out.print(f"  rejected: {reason}", markup=False)
        print_no_design(ctl)
    elif ctl:
        out.print("control: off (the host sends the excitation only; the drive must hold the axis)")
    print_device_notes(s)
    te = s.get("torque_estimate") or {}
    if te.get("nrmse_percent") is not None:
        out.print(f"torque estimate (Eq. 18 on filtered derivatives vs the filtered measured torque): NRMSE "
                  f"{fmt(te['nrmse_percent'])} % over {fmt(te.get('seconds'))} s (from the first trusted fit on)")
    elif te.get("why_none"):
        out.print(f"torque estimate: none ({te['why_none']})", markup=False)
    work = loop.get("work_us") or {}
    if work:
        cpu = loop.get("work_cpu_us") or {}
        out.print(f"tick work: p50 {fmt(work.get('p50'))} us, p99 {fmt(work.get('p99'))} us, "
                  f"max {fmt(work.get('max'))} us (CPU time max {fmt(cpu.get('max'))} us); overruns from the "
                  f"tick's own work {loop.get('overruns_work', 0)}, from a stall's backlog "
                  f"{loop.get('overruns_backlog', 0)}, from a late start or a stolen CPU "
                  f"{loop.get('overruns_late_start', 0)}")
    rt = s.get("realtime") or {}
    if rt:
        out.print("real-time: " + ", ".join(f"{k}={'yes' if v is True else v}" for k, v in rt.items()))
    files = s.get("files") or {}
    if files.get("rrd"):
        out.print(f"dashboard: {files['rrd']}   (open with: rerun --bind 127.0.0.1 {files['rrd']})", markup=False)
    for name, st in (s.get("helpers") or {}).items():
        if st.get("deaths") or st.get("hangs"):
            what = []
            if st.get("deaths"):
                what.append(f"died {st['deaths']}x (exit codes {escape(str(st['exitcodes']))})")
            if st.get("hangs"):
                what.append(f"gave no answer for {st.get('hang_s', 0):g} s {st['hangs']}x")
            state = "hung" if st.get("hung") else "running" if st["alive"] else "not running"
            out.print(f"[yellow]helper {escape(name)} {' and '.join(what)}[/]; restarted {st['restarts']}x; "
                      f"{state} at the end")
    if (s.get("files") or {}).get("rrd_earlier"):
        out.print(f"dashboard before the telemetry restart: {', '.join(s['files']['rrd_earlier'])}", markup=False)
    if s.get("data_lost"):
        out.print(f"[bold red]DATA LOST[/]: {escape(str(s['data_lost']))}")
    elif files.get("recording"):
        out.print(f"recording: {files['recording']}   (re-identify: rt-ident identify {files['recording']})",
                  markup=False)
    print_stop(s)


def print_axes(s: dict) -> None:
    """A run with several axes: each axis's parameters, trust and tracking, then the shared loop."""
    for name, ax in s["axes"].items():
        params = ax.get("parameters") or {}
        out.print(summary_table(f"axis {name} - method {ax.get('method')}", ax))
        if params:
            print_trust(ax.get("trust"), ax.get("trusted"))
        elif ax.get("final_fit_error"):
            out.print(f"no estimate: {ax['final_fit_error']}", markup=False)
        ctl = ax.get("control") or {}
        if ctl.get("mode") not in (None, "off"):
            rd = ctl.get("redesigns") or {}
            out.print(f"control {name}: {ctl['mode']}, table error rms {fmt(um(ctl.get('rms_error_m')))} um, "
                      f"max {fmt(um(ctl.get('max_error_m')))} um; redesigns accepted {rd.get('accepted', 0)}"
                      f"{kept(rd)}, "
                      f"rejected {rd.get('rejected', 0)}; running the {ctl.get('controller')} controller")
            print_no_design(ctl)
        print_device_notes(ax, name)
        files = ax.get("files") or {}
        for key, what in (("rrd", "dashboard"), ("recording", "recording")):
            if files.get(key):
                out.print(f"{what} {name}: {files[key]}", markup=False)
    if s.get("live_url"):
        recs = [f"rt_ident-{n}" for n in s.get("axes") or {}]
        if (s.get("contour") or {}).get("rrd"):
            recs.append("rt_ident-xy-contour")
        out.print(f"dashboard: live at {s['live_url']} (recordings {', '.join(recs)})", markup=False)
    c = s.get("contour")
    if c and "radius_mm" in c:
        parts = []
        for d in ("ccw", "cw"):
            f = c.get(d)
            if f:
                parts.append(f"{d.upper()} G {f['G_um']:.2f} um, F {f['F_min_um']:+.2f}/{f['F_max_um']:+.2f} um"
                             + (f" (disturbed by a loop stall at {f['disturbed_by_stall_at_s']:g} s: not a "
                                "measurement of the axis)" if "disturbed_by_stall_at_s" in f else ""))
        h = f"; H {c['H_um']:.2f} um" if c.get("H_um") is not None else ""
        out.print(f"circular test (ISO 230-4), R {c['radius_mm']:g} mm at {c['feed_mm_min']:.0f} mm/min: "
                  + "; ".join(parts) + h + (f"; polar plot {c['polar_png']}" if c.get("polar_png") else ""),
                  markup=False)
    elif c:
        out.print(f"circular test: {c.get('note')}", markup=False)
    loop = s.get("loop") or {}
    if loop:
        work, lat = loop.get("work_us") or {}, loop.get("lateness_us") or {}
        out.print(f"loop (all axes): {loop.get('ticks', 0)} ticks, {loop.get('samples', 0)} samples, "
                  f"{loop.get('overruns', 0)} overruns; tick work p50 {fmt(work.get('p50'))} us, "
                  f"p99 {fmt(work.get('p99'))} us; lateness p99 {fmt(lat.get('p99'))} us")
        print_stalls(loop)
    if s.get("data_lost"):
        out.print(f"[bold red]DATA LOST[/]: {escape(str(s['data_lost']))}")
    stop = s.get("stop") or {}
    if stop.get("cause"):
        where = f" on axis {stop['axis']}" if stop.get("axis") else ""
        message = escape(str(stop.get("message")))
        err.print(f"[red]stopped by {stop['cause']}{where}:[/red] {message} - {_stopped(stop, True)}")
        print_fix(stop)
    elif stop.get("interrupted"):
        err.print(_INTERRUPTED.format(ticks=loop.get("ticks", 0), stopped=_stopped(stop, True)))
    print_unconfirmed(stop)


def print_device_notes(ax: dict, name: str = "") -> None:
    for note in ax.get("device_notes") or []:
        out.print(f"[yellow]device{' ' + name if name else ''}:[/] {escape(note['message'])}; "
                  f"look at: {escape(note['fix'])}")


def print_no_design(ctl: dict) -> None:
    if ctl.get("no_design"):
        out.print(f"[yellow]  no design:[/] {escape(str(ctl['no_design']))}")
    late = ctl.get("late_torques")
    if late:
        out.print(f"[yellow]  late torques:[/] {escape(late['message'])}; fix: {escape(late['fix'])}")


def print_fix(stop: dict) -> None:
    if stop.get("fix"):
        err.print(f"  fix: {stop['fix']}", highlight=False, markup=False)


def print_stalls(loop: dict) -> None:
    st = loop.get("stalls") or {}
    if st.get("count"):
        wait = st.get("catch_up_longest_ms") or 0.0
        caught = f"; it then read the device's backlog for up to {wait:.0f} ms before re-planning" if wait else ""
        out.print(f"[yellow]loop stalls: {st['count']}[/], longest {st['longest_ms']:.0f} ms (the host stopped ticking "
                  f"that long; safety.on_stall says what the loop did{caught})")


def print_trust(trust: dict | None, trusted: bool | None = None) -> None:
    """``trusted: yes`` or ``trusted: no`` with each failed criterion (and, with -v, all of them)."""
    if not trust:
        out.print(f"trusted: {'yes' if trusted else 'no'}")
        return
    if trust["trusted"]:
        out.print(f"trusted: yes ({len(trust['criteria'])} criteria met)")
        return
    out.print("trusted: [bold]no[/]")
    for why in trust["reasons"]:
        out.print(f"  - {why}", highlight=False, markup=False)
    for c in trust["criteria"]:
        if c["passed"]:
            out.print(f"  ok: {c['criterion']} {fmt(c['value'])} {c['limit']}", highlight=False, style="dim",
                      markup=False)


_INTERRUPTED = ("stopped early on request (Ctrl-C, SIGTERM or SIGHUP) after {ticks} ticks: the figures above cover "
                "only that part; {stopped}")


def _stopped(stop: dict, several: bool) -> str:
    """How the device(s) were left: disabled only where every device confirmed it; nothing said of a
    device this run never opened (another program may be driving it)."""
    state = stop.get("backend_state")
    states = state if isinstance(state, dict) else {"": state}
    never = [n for n, s in states.items() if s == "created"]
    if state is not None and len(never) == len(states):
        return "nothing energized: the device was never opened" if not several else \
            "nothing energized: no device was opened"
    if stop.get("disable_unconfirmed"):
        done = "zero torque commanded, the disable NOT confirmed (below)"
    else:
        done = "every axis at zero torque, disabled" if several else "torque zeroed, drive disabled"
    if never:
        done = done.replace("every axis", "every opened axis") + f"; never opened: axis {', '.join(never)}"
    return done


def print_unconfirmed(stop: dict) -> None:
    """A device that did not confirm its disable, in a line of its own whatever the run's ending."""
    note = stop.get("disable_unconfirmed")
    if not note:
        return
    notes = note.items() if isinstance(note, dict) else [("", note)]
    for axis, why in notes:
        where = f" (axis {axis})" if axis else ""
        err.print(f"[bold red]disable not confirmed{where}:[/] {escape(str(why))}: check the device before "
                  "anyone works near the axis")


def print_stop(s: dict) -> None:
    stop = s.get("stop") or {}
    if stop.get("cause"):
        message = escape(str(stop.get("message")))
        err.print(f"[red]stopped by {stop['cause']}:[/red] {message} - {_stopped(stop, False)}")
        print_fix(stop)
    elif stop.get("interrupted"):
        err.print(_INTERRUPTED.format(ticks=(s.get("loop") or {}).get("ticks", 0), stopped=_stopped(stop, False)))
    print_unconfirmed(stop)

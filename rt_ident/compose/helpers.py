"""A run's helper processes as one set: started per axis, waited for, placed off the loop's CPU,
watched every tick, closed in order and summarized. The loop never waits on them (the hand-offs are
shared-memory rings); what a run lost through them (a recording not complete, a dashboard not written
or not delivered) is said once, in the same words, whatever the number of axes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from rt_ident.loop.host import helper_role, keep_off_loop_cpu
from rt_ident.outputs.recording_reader import journal_path
from rt_ident.processes.guard import HelperWatch

log = logging.getLogger(__name__)


@dataclass
class AxisHelpers:
    """One axis's helper processes (None where the run has none)."""

    telemetry: Any = None
    recorder: Any = None
    fit: Any = None
    control: Any = None


@dataclass
class Helpers:
    """Every axis's helpers (``axes``: axis name -> :class:`AxisHelpers`; one axis is named ``""``)."""

    axes: dict[str, AxisHelpers] = field(default_factory=dict)
    watch: HelperWatch | None = None

    def named(self) -> dict[str, Any]:
        """"telemetry", "fit-x", ...: every helper by the name its reports use."""
        out: dict[str, Any] = {}
        for axis, h in self.axes.items():
            for role in ("telemetry", "recorder", "fit", "control"):
                proc = getattr(h, role)
                if proc is not None:
                    out[f"{role}-{axis}" if axis else role] = proc
        return out

    def ready(self) -> None:
        """Wait until each helper is up (imported, its ring mapped, its files created) before the device
        is enabled: a recorder that is not ready would lose the first samples."""
        for name, proc in self.named().items():
            role = helper_role(name)
            timeout = {"recorder": 30.0, "telemetry": 10.0}.get(role, 30.0)
            if not proc.wait_ready(timeout) and role in ("fit", "control"):
                log.warning("%s not ready after %g s: live estimates/redesigns will start late", proc.name, timeout)

    def place(self, realtime: bool, device: int | None) -> dict[str, Any]:
        """Off the loop's CPU and niced by role (:func:`rt_ident.loop.host.keep_off_loop_cpu`); the report
        names each pid's helper."""
        procs = {pid: (name, p) for name, p in self.named().items() if (pid := getattr(p, "pid", None)) is not None}
        report = keep_off_loop_cpu(list(procs), realtime, device=device,
                                   roles={pid: helper_role(n) for pid, (n, _) in procs.items()})
        report["names"] = {str(pid): n for pid, (n, _) in procs.items()}
        for pid, (_, p) in procs.items():          # what a restarted one takes (a recorder is not restarted)
            if hasattr(p, "placement"):
                p.placement = {"nice": report["nice"].get(str(pid)), "cpus": report["cpus"]}
        return report

    def start_watch(self, tick_hz: float) -> HelperWatch:
        """The check, ten times a second, that the helpers live and answer (a dead or hung one is restarted;
        the recorder is the loop's to watch: its death stops the run)."""
        named = self.named()
        self.watch = HelperWatch({n: p for n, p in named.items() if helper_role(n) != "recorder"},
                                 restartable=tuple(n for n in named if helper_role(n) != "recorder"),
                                 every_ticks=max(1, round(tick_hz / 10)))
        return self.watch

    def close(self) -> tuple[dict[str, dict[str, Any]], str | None]:
        """Close the recorders (each drains its ring and finishes its file), then telemetry; returns each
        axis's report (``recording``, ``telemetry``) and what was lost, in words (None: nothing)."""
        reports: dict[str, dict[str, Any]] = {}
        lost: list[str] = []
        for h in self.axes.values():                    # the job processes end while the files are finished
            for job in (h.fit, h.control):
                if job is not None:
                    job.begin_close()
        for axis, h in self.axes.items():
            rep: dict[str, Any] = {}
            where = f"{axis}: " if axis else ""
            if h.recorder is not None:
                rep["recording"] = r = h.recorder.close()
                if not r["complete"]:
                    lost.append(where + recording_lost(r))
            if h.telemetry is not None:
                t = h.telemetry.close()
                rep["telemetry"] = {"dropped": h.telemetry.dropped, "sent": h.telemetry.sent, **t}
                if t.get("write_error"):
                    lost.append(f"{where}dashboard: {t['write_error']}")
            else:
                rep["telemetry"] = {"dropped": 0, "sent": 0, "sink": "off"}
            reports[axis] = rep
        return reports, "; ".join(lost) or None

    def summary(self) -> dict[str, Any] | None:
        return self.watch.summary() if self.watch is not None else None


def recording_lost(r: dict[str, Any]) -> str:
    """A recording that is not complete, in words (``RecorderProcess.close()``'s report), and where its
    journal keeps what was recorded up to the last flush, when it does."""
    why = f": {r['failure'] or r.get('refusal')}" if r.get("failure") or r.get("refusal") else \
        f" (recorder exit code {r['exitcode']})"
    had = r["samples_put"] + r.get("samples_refused", 0)
    text = f"recording {r['path']} incomplete: {r['rows_written']} of {had} samples written{why}"
    journal = journal_path(r["path"])
    if journal.is_file() and journal.stat().st_size > 0:
        text += f" (what was recorded up to the last flush is in {journal}: rt-ident identify {r['path']} reads it)"
    return text


__all__ = ["AxisHelpers", "Helpers", "recording_lost"]

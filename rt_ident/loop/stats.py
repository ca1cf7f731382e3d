"""The counters of one run of the loop: ticks, samples, overruns by cause, lateness and work time, stalls
and compiles reached while it ran."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rt_ident.loop.compile_watch import CompileWatch
from rt_ident.loop.scheduler import LatenessHistogram
from rt_ident.loop.stall import StallLog


@dataclass
class LoopStats:
    """Counters of one run. An overrun is a tick that found its deadline passed by whole periods;
    it is put down to the work of the tick before (``overruns_work``: that tick's own computation,
    measured as the loop thread's CPU time, took longer than the period), to a stall's backlog
    (``overruns_backlog``: the tick before worked through the samples the device kept during a
    stall, work the stall made) or else to a late start (``overruns_late_start``: the host or the
    scheduler took the CPU before or during the tick, or the tick waited on I/O; the wall-clock work
    time ``work_us`` then exceeds the CPU time ``work_cpu_us``)."""

    ticks: int = 0
    samples: int = 0
    lost_samples: int = 0
    lost_longest: int = 0       # the most samples one read found missing: the longest gap in the device's stream
    overruns: int = 0
    overruns_work: int = 0
    overruns_backlog: int = 0
    overruns_late_start: int = 0
    skipped_periods: int = 0
    estimates: int = 0
    lateness: LatenessHistogram = field(default_factory=LatenessHistogram)
    work: LatenessHistogram = field(default_factory=LatenessHistogram)
    work_cpu: LatenessHistogram = field(default_factory=LatenessHistogram)
    # a simulated device's stepping ahead after the tick (Backend.step_ahead), not part of ``work``
    sim_ahead: LatenessHistogram = field(default_factory=LatenessHistogram)
    stalls: StallLog = field(default_factory=StallLog)
    # compiled code first reached while the loop ran (rt_ident.loop.compile_watch)
    compiles: CompileWatch = field(default_factory=CompileWatch)

    def as_dict(self) -> dict[str, Any]:
        lat = self.lateness.summary()
        work = self.work.summary()
        cpu = self.work_cpu.summary()
        return {"ticks": self.ticks, "samples": self.samples, "lost_samples": self.lost_samples,
                "lost_longest": self.lost_longest,
                "overruns": self.overruns, "overruns_work": self.overruns_work,
                "overruns_backlog": self.overruns_backlog,
                "overruns_late_start": self.overruns_late_start, "skipped_periods": self.skipped_periods,
                "estimates": self.estimates,
                "lateness_us": {"p50": lat["p50"], "p99": lat["p99"], "max": lat["max"]},
                "work_us": {"p50": work["p50"], "p99": work["p99"], "max": work["max"]},
                "work_cpu_us": {"p50": cpu["p50"], "p99": cpu["p99"], "max": cpu["max"]},
                "stalls": self.stalls.as_dict(), "late_compiles": self.compiles.as_dict(),
                **({"sim_ahead_us": {k: ahead[k] for k in ("p50", "p99", "max")}}
                   if (ahead := self.sim_ahead.summary())["count"] else {})}

"""Which ticks of a run took more than ``--threshold-us`` of the loop thread's CPU, and what ran on them.

Runs ``rt_ident.compose.run.run`` in this process (real time, as ``rt-ident run`` does) N times with
a tick hook that reads, after every tick, the loop thread's CPU time and its resource usage
(``getrusage(RUSAGE_THREAD)``: page faults, involuntary context switches) and what the loop did on that
tick: a fit result unpacked (the loop's ``estimates`` count), a redesign asked for, adopted or
rejected, a fallback, a tick left to the Python path, a friction feedforward update. A slow tick on
which none of these happened, with no fault and no context switch, is time the thread did not run
while it thought it did: the hypervisor took the vCPU (the run's ``loop.host.steal_ms`` then rises,
in 10 ms steps).

    python tools/slow_ticks.py                          # 5 default runs of 10 s
    python tools/slow_ticks.py --config configs/xy-sim.toml -n 3 --json

The CPU time between two hook calls includes the wait for the tick (a few microseconds of CPU), so
the figures are an upper bound of the tick's work.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from rt_ident.compose import run as run_mod
from rt_ident.config import load
from rt_ident.loop import loop as loop_mod

_LOOPS: list[Any] = []
_orig_init = loop_mod.IdentificationLoop.__init__


def _capturing_init(self: Any, *args: Any, **kwargs: Any) -> None:
    _orig_init(self, *args, **kwargs)
    _LOOPS.append(self)


def _state() -> tuple[int, ...]:
    """Counters of everything the loops may have done on a tick, in one tuple."""
    out: list[int] = []
    for lp in _LOOPS:
        ctl, core = lp.control, lp._core
        cs = ctl.stats if ctl is not None else None
        out += [lp.stats.estimates, cs.requests if cs else 0, cs.accepted if cs else 0,
                cs.rejected if cs else 0, cs.fallbacks if cs else 0, core.python_ticks if core else 0]
    return tuple(out)


_NAMES = ("fit result unpacked", "redesign requested", "redesign adopted", "redesign rejected", "fallback",
          "Python path")


class Hook:
    def __init__(self, threshold_us: float, tick_hz: float) -> None:
        self.tick_hz = tick_hz
        self.threshold = threshold_us * 1e-6
        self.slow: list[dict[str, Any]] = []
        self.last_cpu: float | None = None
        self.last_ru: Any = None
        self.last_state: tuple[int, ...] = ()
        self.last_work = 0
        self.unmatched = 0          # overruns_work not on the tick after a slow tick seen here

    def __call__(self, tick: int) -> None:
        cpu = time.thread_time()
        ru = resource.getrusage(resource.RUSAGE_THREAD)
        state = _state()
        if self.last_cpu is not None and cpu - self.last_cpu > self.threshold:
            what = [f"{_NAMES[i % len(_NAMES)]}" + (f" ({'xy'[i // len(_NAMES)]})" if len(_LOOPS) > 1 else "")
                    for i, (a, b) in enumerate(zip(self.last_state, state)) if a != b]
            if _LOOPS and _LOOPS[0].friction is not None and tick % _LOOPS[0]._FRICTION_EVERY == 0:
                what.append("friction feedforward")
            faults = ru.ru_minflt - self.last_ru.ru_minflt + ru.ru_majflt - self.last_ru.ru_majflt
            switches = ru.ru_nivcsw - self.last_ru.ru_nivcsw
            self.slow.append({"tick": tick, "t_s": round(tick / self.tick_hz, 3),
                              "cpu_us": round((cpu - self.last_cpu) * 1e6), "did": what,
                              "page_faults": faults, "preempted": switches})
        # an overrun is counted on the tick after the one whose CPU time passed the period: mark that one
        work = max((lp.stats.overruns_work for lp in _LOOPS), default=0)   # the axes of one loop count one overrun each
        if work > self.last_work:
            late = [t for t in self.slow if t["tick"] == tick - 1]
            if late:
                late[0]["overrun"] = True
            else:
                self.unmatched += work - self.last_work
        self.last_work = work
        self.last_cpu, self.last_ru, self.last_state = cpu, ru, state


def one_run(config: str | None, duration: float, threshold_us: float, work: Path, k: int) -> dict[str, Any]:
    _LOOPS.clear()
    cfg = load(config, **{"loop.duration": duration})
    hook = Hook(threshold_us, cfg.loop.tick_hz)
    s = run_mod.run(cfg, rrd=str(work / f"run{k}.rrd"), record=str(work / f"run{k}.parquet"), tick_hook=hook)
    loop = s.get("loop") or {}
    return {"run": k, "stop": (s.get("stop") or {}).get("cause"), "overruns_work": loop.get("overruns_work"),
            "work_cpu_max_us": round((loop.get("work_cpu_us") or {}).get("max", 0.0)),
            "steal_ms": (loop.get("host") or {}).get("steal_ms"),
            "late_compiles": (loop.get("late_compiles") or {}).get("count"), "slow_ticks": hook.slow,
            "overruns_unmatched": hook.unmatched}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--config", default=None, help="run config (default: configs/sim.toml)")
    ap.add_argument("-n", type=int, default=5, help="runs")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--threshold-us", type=float, default=1000.0)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    loop_mod.IdentificationLoop.__init__ = _capturing_init      # type: ignore[method-assign]
    rows = []
    with tempfile.TemporaryDirectory(prefix="slow-ticks-") as d:
        for k in range(a.n):
            r = one_run(a.config, a.duration, a.threshold_us, Path(d), k)
            rows.append(r)
            for f in Path(d).glob(f"run{k}*"):
                f.unlink()
            if not a.json:
                print(f"run {k}: stop {r['stop']}, overruns_work {r['overruns_work']}, work_cpu max "
                      f"{r['work_cpu_max_us']} us, steal {r['steal_ms']} ms, late compiles {r['late_compiles']}"
                      + (f", {r['overruns_unmatched']} overruns_work not after a tick seen slow"
                         if r["overruns_unmatched"] else ""), flush=True)
                for t in r["slow_ticks"]:
                    print(f"  tick {t['tick']} (t={t['t_s']} s): {t['cpu_us']} us CPU"
                          + (" (the next tick overran)" if t.get("overrun") else "") + "; "
                          f"{', '.join(t['did']) or 'nothing of the loop'}; page faults {t['page_faults']}, "
                          f"preempted {t['preempted']}", flush=True)
    if a.json:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

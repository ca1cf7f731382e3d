"""Which ticks of a run took more than ``--threshold-us`` of the loop thread's CPU, and what ran on them.

Runs ``rt_ident.compose.run.run`` in this process (real time, as ``rt-ident run`` does) N times with
a tick hook that reads, after every tick, the loop thread's CPU time and its resource usage
(``getrusage(RUSAGE_THREAD)``: page faults, involuntary context switches) and what the loop did on that
tick: a fit result unpacked (the loop's ``estimates`` count), a redesign asked for, adopted or
rejected, a fallback, a tick left to the Python path, a friction feedforward update. Each slow tick
also gets its CPU time by part: the read, the processing, the plan and a simulated device's stepping,
and inside the processing the compiled tick, the supervisor's look at the estimate, the fit exchange,
the telemetry hand-off, the Python path's finish and the redesign poll. A part far above its median
(printed per run) is where the time went; a tick slow in every part, with no fault, no context switch
and no extra interrupt, ran slow as a whole: the host.

    python tools/slow_ticks.py                          # 5 default runs of 10 s
    python tools/slow_ticks.py --config configs/xy-sim.toml -n 3 --json
    python tools/slow_ticks.py -n 3 --part supervisor   # that part's CPU time over every tick, p50..max

A tick's CPU time is the loop's own measure, the one its ``overruns_work`` is charged by (the
loop thread's CPU time from the end of the wait to the end of the tick, a simulated device's
stepping ahead included), read from the loop module's calls of ``time.thread_time``.

Each slow tick also lists the interrupts and softirqs the kernel handled on the loop's CPU during it
(``/proc/interrupts``, ``/proc/softirqs``, read after every tick, ~60 us): the kernel charges their
handling to the thread it interrupted (no IRQ time accounting on a kernel built without it), and the
median tick's counts are printed beside them for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
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


class _LoopCpu:
    """Stands in for the loop module's ``time``: its ``thread_time`` keeps the last two readings (the
    run loop reads it at a tick's start and end)."""

    def __init__(self) -> None:
        self.last = [0.0, 0.0]

    def thread_time(self) -> float:
        t = time.thread_time()
        self.last[0], self.last[1] = self.last[1], t
        return t

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


_CPU = _LoopCpu()
_orig_init = loop_mod.IdentificationLoop.__init__


_PHASES = ("read", "process", "plan", "sim step",
           # inside "process": the compiled kernel and the Python steps around it
           "compiled tick", "fit exchange", "snapshot", "supervisor", "telemetry", "Python finish", "redesign poll")
_INNER = (("_core", "kernel", 4), (None, "_fit_exchange", 5), (None, "_snapshot_due", 6), (None, "assess_turn", 7),
          (None, "_flush_telemetry", 8), ("_core", "_telemetry_sent", 8), ("_core", "_finish_in_python", 9),
          ("control", "poll", 10))


def _wrap_inner(lp: Any) -> None:
    """Time the steps inside a loop's processing (once its compiled tick and controller exist)."""
    for owner_name, attr, i in _INNER:
        owner = lp if owner_name is None else getattr(lp, owner_name, None)
        if owner is not None and hasattr(owner, attr):
            setattr(owner, attr, _timed(lp.tool_phases, i, getattr(owner, attr)))


def _timed(phases: list[float], i: int, fn: Any) -> Any:
    """``fn`` with the loop thread's CPU time it takes added to ``phases[i]``."""
    def call(*args: Any, **kwargs: Any) -> Any:
        c = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            phases[i] += time.thread_time() - c
    return call


def _capturing_init(self: Any, *args: Any, **kwargs: Any) -> None:
    _orig_init(self, *args, **kwargs)
    _LOOPS.append(self)
    self.tool_phases = phases = [0.0] * len(_PHASES)       # CPU time of each part of the tick
    self.backend.read = _timed(phases, 0, self.backend.read)
    self._process = _timed(phases, 1, self._process)
    self._write_plan = _timed(phases, 2, self._write_plan)
    self.backend.step_ahead = _timed(phases, 3, self.backend.step_ahead)


def _parts() -> dict[str, int]:
    """The tick's CPU time [us] by part (and axis, on two), largest first."""
    out = {}
    for j, lp in enumerate(_LOOPS):
        for name, v in zip(_PHASES, lp.tool_phases):
            out[name + (f" ({'xy'[j]})" if len(_LOOPS) > 1 else "")] = round(v * 1e6)
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


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


def _column(raw: bytes, cpu: int) -> dict[str, int]:
    """One CPU's counts by name from the text of /proc/interrupts or /proc/softirqs."""
    lines = raw.decode("ascii", "replace").splitlines()
    ncpu = len(lines[0].split()) if lines else 0
    out: dict[str, int] = {}
    for line in lines[1:]:
        head, _, rest = line.partition(":")
        fields = rest.split()
        if cpu >= ncpu or len(fields) < ncpu or not all(f.isdigit() for f in fields[:ncpu]):
            continue                                        # not a per-CPU row (ERR, MIS)
        head = head.strip()
        name = fields[-1] if head.isdigit() and len(fields) > ncpu else head    # a device's IRQ: its name
        out[name] = int(fields[cpu])
    return out


class KernelCounts:
    """The interrupts and softirqs handled on one CPU between two calls (raw text kept, parsed on demand)."""

    FILES = ("/proc/interrupts", "/proc/softirqs")

    def __init__(self) -> None:
        self.fds = [os.open(f, os.O_RDONLY) for f in self.FILES]
        self.last: list[bytes] = []
        self.now: list[bytes] = []

    def read(self) -> None:
        self.last, self.now = self.now, []
        for fd in self.fds:
            os.lseek(fd, 0, os.SEEK_SET)
            self.now.append(os.read(fd, 1 << 16))

    def delta(self, cpu: int) -> dict[str, int]:
        if not self.last:
            return {}
        out = {}
        for before, after in zip(self.last, self.now):
            a, b = _column(before, cpu), _column(after, cpu)
            out.update({k: b[k] - a.get(k, 0) for k in b if b[k] != a.get(k, 0)})
        return out

    def close(self) -> None:
        for fd in self.fds:
            os.close(fd)


class Hook:
    def __init__(self, threshold_us: float, tick_hz: float, part: str | None = None) -> None:
        self.part = None if part is None else _PHASES.index(part)
        self.part_us: list[list[float]] = []        # per axis, the part's CPU time on every tick
        self.tick_hz = tick_hz
        self.threshold = threshold_us * 1e-6
        self.slow: list[dict[str, Any]] = []
        self.last_ru: Any = None
        self.last_state: tuple[int, ...] = ()
        self.last_work = 0
        self.unmatched = 0          # overruns_work not on the tick after a slow tick seen here
        self.kernel = KernelCounts()
        self.wrapped = False
        self.cpu: int | None = None
        self.typical: list[dict[str, int]] = []     # the counts of every 100th tick, for comparison
        self.typical_parts: list[dict[str, int]] = []
        self.last_samples = 0
        self.typical_samples: list[dict[str, int]] = []

    def __call__(self, tick: int) -> None:
        if not self.wrapped:
            for lp in _LOOPS:
                _wrap_inner(lp)
            self.wrapped = True
        work = _CPU.last[1] - _CPU.last[0]
        ru = resource.getrusage(resource.RUSAGE_THREAD)
        state = _state()
        samples = [lp.stats.samples for lp in _LOOPS]
        n = sum(samples) - self.last_samples       # samples the tick processed (both axes)
        self.last_samples = sum(samples)
        self.kernel.read()
        if self.cpu is None:
            mine = os.sched_getaffinity(0)
            self.cpu = next(iter(mine)) if len(mine) == 1 else -1
        if tick % 100 == 50:
            self.typical_parts.append(_parts())
            self.typical_samples.append({"samples": n})
            if self.cpu >= 0:
                self.typical.append(self.kernel.delta(self.cpu))
        if self.last_ru is not None and work > self.threshold:
            what = [f"{_NAMES[i % len(_NAMES)]}" + (f" ({'xy'[i // len(_NAMES)]})" if len(_LOOPS) > 1 else "")
                    for i, (a, b) in enumerate(zip(self.last_state, state)) if a != b]
            if _LOOPS and _LOOPS[0].friction is not None and tick % _LOOPS[0]._FRICTION_EVERY == 0:
                what.append("friction feedforward")
            faults = ru.ru_minflt - self.last_ru.ru_minflt + ru.ru_majflt - self.last_ru.ru_majflt
            switches = ru.ru_nivcsw - self.last_ru.ru_nivcsw
            self.slow.append({"tick": tick, "t_s": round(tick / self.tick_hz, 3),
                              "cpu_us": round(work * 1e6), "did": what, "parts_us": _parts(), "samples": n,
                              "page_faults": faults, "preempted": switches,
                              "kernel": self.kernel.delta(self.cpu) if self.cpu is not None and self.cpu >= 0 else {}})
        # an overrun is counted on the tick after the one whose CPU time passed the period: mark that one
        overruns = max((lp.stats.overruns_work for lp in _LOOPS), default=0)   # the axes of one loop count one each
        if overruns > self.last_work:
            late = [t for t in self.slow if t["tick"] == tick - 1]
            if late:
                late[0]["overrun"] = True
            else:
                self.unmatched += overruns - self.last_work
        self.last_work = overruns
        self.last_ru, self.last_state = ru, state
        if self.part is not None:
            while len(self.part_us) < len(_LOOPS):
                self.part_us.append([])
            for j, lp in enumerate(_LOOPS):
                self.part_us[j].append(lp.tool_phases[self.part] * 1e6)
        for lp in _LOOPS:
            lp.tool_phases[:] = [0.0] * len(_PHASES)


def _spread(values: list[float]) -> dict[str, float]:
    """p50, p90, p99 and max of ``values`` [us], rounded."""
    if not values:
        return {}
    v = sorted(values)
    return {k: round(v[min(len(v) - 1, int(q * len(v)))], 1) for k, q in (("p50", 0.5), ("p90", 0.9), ("p99", 0.99))} \
        | {"max": round(v[-1], 1)}


def one_run(config: str | None, duration: float, threshold_us: float, work: Path, k: int,
            part: str | None = None) -> dict[str, Any]:
    _LOOPS.clear()
    cfg = load(config, **{"loop.duration": duration})
    hook = Hook(threshold_us, cfg.loop.tick_hz, part)
    try:
        s = run_mod.run(cfg, rrd=str(work / f"run{k}.rrd"), record=str(work / f"run{k}.parquet"), tick_hook=hook)
    finally:
        hook.kernel.close()
    loop = s.get("loop") or {}
    return {"run": k, "stop": (s.get("stop") or {}).get("cause"), "overruns_work": loop.get("overruns_work"),
            "overruns_backlog": loop.get("overruns_backlog"),
            "work_cpu_max_us": round((loop.get("work_cpu_us") or {}).get("max", 0.0)),
            "steal_ms": (loop.get("host") or {}).get("steal_ms"),
            "late_compiles": (loop.get("late_compiles") or {}).get("count"), "slow_ticks": hook.slow,
            "stalls": [(e["t"], e["ms"]) for e in (loop.get("stalls") or {}).get("events", [])],
            "overruns_unmatched": hook.unmatched, "loop_cpu": hook.cpu, "typical_kernel": _median_counts(hook.typical),
            "typical_parts_us": _median_counts(hook.typical_parts),
            "typical_samples": _median_counts(hook.typical_samples).get("samples", 0),
            "part_us": [_spread(v) for v in hook.part_us]}


def _median_counts(rows: list[dict[str, int]]) -> dict[str, float]:
    """Per name, the median count over the sampled ticks (names seen in any)."""
    names = sorted({k for r in rows for k in r})
    out = {}
    for k in names:
        vals = sorted(r.get(k, 0) for r in rows)
        med = vals[len(vals) // 2] if vals else 0
        if med:
            out[k] = med
    return out


def _counts_text(counts: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v:g}" for k, v in sorted(counts.items())) or "none"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--config", default=None, help="run config (default: configs/sim.toml)")
    ap.add_argument("-n", type=int, default=5, help="runs")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--threshold-us", type=float, default=1000.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--part", choices=_PHASES, default=None,
                    help="also print this part's CPU time over every tick (p50, p90, p99, max per axis)")
    a = ap.parse_args(argv)
    loop_mod.IdentificationLoop.__init__ = _capturing_init      # type: ignore[method-assign]
    loop_mod.time = _CPU                                        # type: ignore[assignment]
    rows = []
    with tempfile.TemporaryDirectory(prefix="slow-ticks-") as d:
        for k in range(a.n):
            r = one_run(a.config, a.duration, a.threshold_us, Path(d), k, a.part)
            rows.append(r)
            for f in Path(d).glob(f"run{k}*"):
                f.unlink()
            if not a.json:
                print(f"run {k}: stop {r['stop']}, overruns_work {r['overruns_work']}, overruns_backlog "
                      f"{r['overruns_backlog']}, work_cpu max "
                      f"{r['work_cpu_max_us']} us, steal {r['steal_ms']} ms, late compiles {r['late_compiles']}, "
                      f"stalls {', '.join(f'{ms} ms at {t} s' for t, ms in r['stalls']) or 'none'}; "
                      f"a median tick's kernel work on CPU {r['loop_cpu']}: {_counts_text(r['typical_kernel'])}, "
                      f"its samples {r['typical_samples']:g}, its parts [us]: {_counts_text(r['typical_parts_us'])}"
                      + (f", {r['overruns_unmatched']} overruns_work not after a tick seen slow"
                         if r["overruns_unmatched"] else ""), flush=True)
                for j, sp in enumerate(r["part_us"]):
                    axis = f" ({'xy'[j]})" if len(r["part_us"]) > 1 else ""
                    print(f"  {a.part}{axis} over every tick [us]: {_counts_text(sp)}", flush=True)
                for t in r["slow_ticks"]:
                    print(f"  tick {t['tick']} (t={t['t_s']} s): {t['cpu_us']} us CPU, {t['samples']} samples"
                          + (" (the next tick overran)" if t.get("overrun") else "") + "; "
                          f"{', '.join(t['did']) or 'nothing of the loop'}; page faults {t['page_faults']}, "
                          f"preempted {t['preempted']}; kernel: {_counts_text(t['kernel'])}", flush=True)
                    print("    by part [us]: " + ", ".join(f"{k} {v}" for k, v in list(t["parts_us"].items())[:6]),
                          flush=True)
    if a.json:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

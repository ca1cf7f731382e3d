"""The loop end to end: the largest sample rate the sim backend + loop sustain at a 1 kHz tick.

Each trial is a separate ``python -c`` process running :func:`rt_ident.compose.run.run` on a config
built with :func:`rt_ident.config.from_mapping` (sim backend paced by the wall clock,
``loop.realtime = true``), so SCHED_FIFO, CPU affinity, ``mlockall`` and ``gc.freeze`` apply to
that process only and never to the benchmark. The child samples its resident set size
(``/proc/self/statm``) at the first tick and every 1000 ticks from the loop's tick hook, and
prints one JSON line. Recording to Parquet is off (it is not what is measured and would write
gigabytes at high rates); telemetry is either ``off`` or streamed to a temporary ``.rrd``.

The search walks the rates upwards (see :func:`bench_loop`); the answer is the largest rate
that ran clean (0 overruns) for the whole trial, and the largest that at least kept pace.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_RATES", "bench_loop", "loop_trial", "soak"]

#: Sample rates tried (samples/s): the paper's ~33.9 kHz, then multiples up to ~30x.
DEFAULT_RATES: tuple[int, ...] = (34_000, 68_000, 136_000, 170_000, 250_000, 340_000, 500_000, 680_000, 1_000_000)

_CHILD = r"""
import json, os, sys, time
page_kb = os.sysconf("SC_PAGE_SIZE") // 1024
def rss_kb():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * page_kb
rss = {"process_start_kb": rss_kb()}
def children_rss_kb():
    # every child of this process (the run's helpers, an emulator): {pid: rss_kb}
    out = {}
    try:
        with open(f"/proc/self/task/{os.getpid()}/children") as fh:
            kids = [int(x) for x in fh.read().split()]
    except OSError:
        return out
    for k in kids:
        try:
            with open(f"/proc/{k}/statm") as fh:
                out[k] = int(fh.read().split()[1]) * page_kb
        except OSError:
            pass
    return out
helpers_rss = []
from rt_ident import config
from rt_ident.compose import run as runmod
mapping, rrd = json.loads(sys.argv[1]), sys.argv[2] or None
n_ticks = int(mapping["loop"]["duration"] * mapping["loop"]["tick_hz"]) + 2
import array
# end of each tick's work: a C array of doubles, so that storing a time allocates nothing (a list
# would keep one float object per tick: ~32 bytes/tick, +20 MB over a 10-minute soak)
stamps = array.array("d", bytes(8 * n_ticks))
ticks_rss = []
startup = {}
clock = time.perf_counter
def hook(ticks):
    if ticks < n_ticks:
        stamps[ticks] = clock()
    if ticks == 1 or ticks % 1000 == 0:
        ticks_rss.append((ticks, rss_kb()))
        helpers_rss.append((ticks, children_rss_kb()))
    if ticks == 1000:   # overruns during the first second (the loop's LoopStats, read from its frame)
        st = sys._getframe(1).f_locals.get("stats")
        startup["overruns_first_1s"] = getattr(st, "overruns", None)
cfg = config.from_mapping(mapping, source="bench")
s = runmod.run(cfg, rrd=rrd, sink=mapping["telemetry"]["sink"], tick_hook=hook)
rss["after_run_kb"] = rss_kb()
rss["first_tick_kb"] = ticks_rss[0][1] if ticks_rss else None
rss["last_tick_kb"] = ticks_rss[-1][1] if ticks_rss else None
period = 1.0 / mapping["loop"]["tick_hz"]
gaps = [(k, round(1e3 * (stamps[k] - stamps[k - 1]), 3)) for k in range(2, n_ticks)
        if stamps[k] and stamps[k - 1] and stamps[k] - stamps[k - 1] > 1.5 * period]
print(json.dumps({"loop": s.get("loop"), "stop": s.get("stop"), "telemetry": s.get("telemetry"),
                  "realtime": s.get("realtime"), "rss": rss, "rss_ticks": ticks_rss,
                  "helpers_rss": helpers_rss, "helper_processes": s.get("helper_processes"),
                  "long_gaps_ms": gaps[:50], "n_long_gaps": len(gaps), **startup}, default=str))
"""

def _growth_after(series: list, frac: float) -> float | None:
    """RSS growth (%) from ``frac`` of the run to its end: a leak grows, a warm-up does not."""
    if len(series) < 3:
        return None
    start = series[min(len(series) - 1, int(frac * len(series)))][1]
    return 100.0 * (series[-1][1] - start) / start if start else None


def trial_config(rate: float, seconds: float, sink: str, method: str = "frequency",
                 record: bool = False) -> dict[str, Any]:
    """The run config of one trial (see the module docstring).

    The multisine period scales with the rate so that the excitation keeps the default config's
    spectrum (fundamental ~66 Hz, harmonics 1..20): a fixed 512-sample period at 500 k samples/s
    would put it at 1-20 kHz, where the axis barely moves and the encoder watchdog trips.
    """
    period = max(64, int(round(rate * 512 * 2.9481e-5)))
    return {"backend": {"name": "sim", "sample_period": 1.0 / rate, "paced": True},
            "excitation": {"kind": "schroeder", "period_samples": period, "band": [1, 20]},
            "loop": {"tick_hz": 1000.0, "duration": float(seconds), "realtime": True},
            "estimator": {"method": method},
            "telemetry": {"sink": sink},
            # record: the recorder process too, into the trial's temporary directory (its cwd)
            "recording": {"enabled": True, "path": "bench.parquet"} if record else {"enabled": False}}


def loop_trial(rate: float, seconds: float, sink: str, *, method: str = "frequency",
               timeout: float | None = None, record: bool = False) -> dict[str, Any]:
    """Run one loop trial in a subprocess; returns its summary, RSS and whether it ran clean."""
    with tempfile.TemporaryDirectory(prefix="rt-ident-bench-") as tmp:
        rrd = str(Path(tmp) / "bench.rrd") if sink == "rrd" else ""
        env = dict(os.environ, CI="1")   # CI: the rerun SDK writes no analytics config under HOME
        cmd = [sys.executable, "-c", _CHILD, json.dumps(trial_config(rate, seconds, sink, method, record)), rrd]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp,
                                  timeout=timeout or seconds + 180.0)
        except subprocess.TimeoutExpired:
            return {"rate": rate, "sink": sink, "seconds": seconds, "ok": False, "error": "timeout"}
        rrd_bytes = Path(rrd).stat().st_size if rrd and Path(rrd).exists() else None
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        log.warning("loop trial at %g samples/s (%s) failed: %s", rate, sink, " | ".join(tail))
        return {"rate": rate, "sink": sink, "seconds": seconds, "ok": False,
                "error": " | ".join(tail) or f"exit code {proc.returncode}"}
    res = json.loads(lines[-1])
    loop = res.get("loop") or {}
    rss = res.get("rss") or {}
    first, last = rss.get("first_tick_kb"), rss.get("last_tick_kb")
    ok = (loop.get("overruns", 1) == 0 and (res.get("stop") or {}).get("cause") is None
          and loop.get("samples", 0) > 0)
    return {"rate": rate, "sink": sink, "seconds": seconds, "ok": ok,
            "overruns": loop.get("overruns"), "ticks": loop.get("ticks"), "samples": loop.get("samples"),
            "samples_per_s": (loop.get("samples") or 0) / seconds, "lost_samples": loop.get("lost_samples"),
            "lateness_us": loop.get("lateness_us"), "work_us": loop.get("work_us"),
            "overruns_work": loop.get("overruns_work"), "overruns_backlog": loop.get("overruns_backlog"),
            "overruns_late_start": loop.get("overruns_late_start"),
            "stop_cause": (res.get("stop") or {}).get("cause"),
            "host_steal_ms": (loop.get("host") or {}).get("steal_ms"),
            "telemetry_dropped": (res.get("telemetry") or {}).get("dropped"), "rrd_bytes": rrd_bytes,
            "realtime": res.get("realtime"), "rss_kb": rss, "stop_message": (res.get("stop") or {}).get("message"),
            "long_gaps_ms": res.get("long_gaps_ms"), "n_long_gaps": res.get("n_long_gaps"),
            "overruns_first_1s": res.get("overruns_first_1s"),
            "rss_series_kb": (res.get("rss_ticks") or [])[::max(1, len(res.get("rss_ticks") or []) // 20)],
            "rss_growth_after_10pct_pct": _growth_after(res.get("rss_ticks") or [], 0.1),
            "rss_growth_pct": None if not first or not last else 100.0 * (last - first) / first,
            "helpers": _helper_growth(res)}


def _helper_growth(res: dict[str, Any]) -> dict[str, Any]:
    """RSS of every helper process over the run: first, 10 % in, last, and growth after 10 %."""
    series = res.get("helpers_rss") or []
    pids = (res.get("helper_processes") or {}).get("pids") or []
    # the run names its helpers by pid; older summaries only listed them, in this order
    names = {int(p): n for p, n in ((res.get("helper_processes") or {}).get("names") or {}).items()} or dict(
        zip(pids, ("telemetry", "recorder", "fit", "control")))
    out: dict[str, Any] = {}
    for pid in sorted({int(p) for _, d in series for p in d}):
        pts = [(t, d[str(pid)] if str(pid) in d else d.get(pid)) for t, d in series]
        pts = [(t, v) for t, v in pts if v]
        if len(pts) < 3:
            continue
        name = names.get(pid, f"pid {pid}")
        out[name] = {"first_kb": pts[0][1], "last_kb": pts[-1][1],
                     "growth_after_10pct_pct": _growth_after(pts, 0.1)}
    return out


def _saturated(res: dict[str, Any]) -> bool:
    """The loop cannot keep up (as opposed to a rare spike): a stop, lost pace or >1 % overruns."""
    if "error" in res or res.get("stop_cause") is not None:
        return True
    return (res.get("samples_per_s") or 0.0) < 0.97 * res["rate"] or (res.get("overruns") or 0) > 0.01 * (
        res.get("ticks") or 1)


def _steady_ok(res: dict[str, Any]) -> bool:
    """No overrun after the first second (start-up stalls excluded) and no stop."""
    if "error" in res or res.get("stop_cause") is not None:
        return False
    return (res.get("overruns") or 0) - (res.get("overruns_first_1s") or 0) == 0


def bench_loop(seconds: float = 60.0, rates: tuple[int, ...] = DEFAULT_RATES, sinks: tuple[str, ...] = ("off", "rrd"),
               method: str = "frequency", retries: int = 1,
               progress: Callable[[str, float], None] | None = None) -> dict[str, Any]:
    """Per telemetry sink: the largest rate in ``rates`` that ran ``seconds`` with 0 overruns.

    Rates are tried upwards until a trial saturates (see :func:`_saturated`). A trial with
    overruns after its first second that still kept pace (a millisecond spike on a shared VM)
    is repeated up to ``retries`` times. Reported per sink: ``max_clean_rate`` (0 overruns, the
    target), ``max_clean_after_startup_rate`` (0 overruns after the first second:
    separates a one-time start-up stall from steady-state capacity) and ``max_sustained_rate``
    (kept pace, spikes or not).
    """
    trials: list[dict[str, Any]] = []
    best: dict[str, dict[str, float | None]] = {"clean": {}, "clean_after_startup": {}, "sustained": {}}
    total = len(sinks) * len(rates)
    for si, sink in enumerate(sinks):
        for key in best:
            best[key][sink] = None
        for ri, rate in enumerate(rates):
            for attempt in range(retries + 1):
                if progress is not None:
                    progress(f"loop: {rate / 1e3:g} k samples/s, telemetry {sink}, {seconds:g} s"
                             + (f" (retry {attempt})" if attempt else ""), (si * len(rates) + ri) / total)
                res = loop_trial(rate, seconds, sink, method=method)
                res["attempt"] = attempt
                trials.append(res)
                if _steady_ok(res) or _saturated(res):
                    break
            if _saturated(res):
                break
            best["sustained"][sink] = rate
            if _steady_ok(res):
                best["clean_after_startup"][sink] = rate
            if res["ok"]:
                best["clean"][sink] = rate
    if progress is not None:
        progress("loop: done", 1.0)
    return {"seconds": seconds, "tick_hz": 1000.0, "method": method, "rates_tried": list(rates),
            "max_clean_rate": best["clean"], "max_clean_after_startup_rate": best["clean_after_startup"],
            "max_sustained_rate": best["sustained"], "trials": trials,
            # not measured (None, shown "-") when no trial went as high as the target rate (bench kernels --quick)
            "targets": {"rrd streaming: 0 overruns at >= 170 k samples/s":
                        None if max(rates) < 170_000 or "rrd" not in sinks
                        else (best["clean"].get("rrd") or 0) >= 170_000}}


def soak(seconds: float = 600.0, rate: float = 170_000, sink: str = "rrd",
         method: str = "frequency", record: bool = True) -> dict[str, Any]:
    """One long trial (default 10 min at 170 k samples/s, streaming to an .rrd): is RSS flat?

    ``rss_growth_pct`` compares the resident set at the first tick with the last sample (every
    1000 ticks); ``rss_growth_after_10pct_pct`` starts after the first tenth of the run, when
    every buffer has been touched. The target is +-5 %.
    """
    res = loop_trial(rate, seconds, sink, method=method, record=record)
    res["record"] = record
    growth = res.get("rss_growth_pct")
    res["rss_flat_within_5pct"] = None if growth is None else abs(growth) <= 5.0
    grow = [h.get("growth_after_10pct_pct") for h in (res.get("helpers") or {}).values()]
    res["helpers_flat_within_5pct"] = None if not grow or None in grow else all(abs(g) <= 5.0 for g in grow)
    return res

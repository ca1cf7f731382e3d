"""Do a CANopen run's lost samples line up with spans where a CPU executed nothing at all?

Runs ``rt-ident run CONFIG --record ...`` once under the kernel's tracer (tracefs: needs root) with the
scheduler and interrupt events of every CPU on the monotonic clock, then compares:

* the recording's gaps (consecutive sample numbers missing, as ``tools/canopen_gaps.py`` finds them);
* each CPU's *silences*: spans longer than ``--silence-ms`` with no event at all on that CPU, not even
  a timer interrupt, while the emulated drive's receive thread wakes every 100 us. The guest kernel
  did not run there: the hypervisor had the vCPU;
* how long the run's real-time threads (SCHED_FIFO) waited between being woken and running.

A gap is put down to a silence when one on any CPU overlaps it (the recording's clock is aligned to the
trace by the offset that lines up the most gaps with silences). Exit code 0 when every gap longer than
``--limit-ms`` lines up with a silence, 1 otherwise, 2 when the tracer is not available.

    sudo python tools/cpu_silences.py                           # configs/canopen-virtual.toml, 10 s
    sudo python tools/cpu_silences.py --config configs/canopen-virtual.toml --duration 5 --json
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from canopen_gaps import gaps  # noqa: E402 - the tools folder is not a package

TRACEFS = Path("/sys/kernel/tracing")
EVENTS = ("sched:sched_switch", "sched:sched_wakeup", "irq:irq_handler_entry", "irq:softirq_entry",
          "irq_vectors:local_timer_entry")
_LINE = re.compile(r"^\s*.+?-(\d+)\s+\[(\d+)\]\s+\S+\s+([\d.]+):\s+(\w+):\s*(.*)$")
_FIELD = re.compile(r"(\w+)=(\S+)")


def _write(name: str, value: str) -> None:
    (TRACEFS / name).write_text(value)


def traced_run(config: str, duration: float, work: Path) -> tuple[Path, Path, dict[str, Any]]:
    """One run under the tracer; the trace, the recording and the run's JSON summary."""
    rec, trace = work / "run.parquet", work / "trace.txt"
    _write("tracing_on", "0")
    _write("trace", "")
    _write("trace_clock", "mono")
    _write("buffer_size_kb", "300000")
    _write("set_event", "\n".join(EVENTS) + "\n")
    cmd = [sys.executable, "-m", "rt_ident.cli", "run", config, "--duration", str(duration), "--json",
           "--record", str(rec), "--rrd", str(work / "run.rrd")]
    try:
        _write("tracing_on", "1")
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=duration + 120)
    finally:
        _write("tracing_on", "0")
        with open(TRACEFS / "trace") as src, open(trace, "w") as dst:
            for line in src:
                dst.write(line)
        _write("trace", "")
        _write("set_event", "")
        _write("buffer_size_kb", "1408")
    try:
        summary = json.loads(p.stdout)
    except json.JSONDecodeError:
        summary = {"error": (p.stderr.strip().splitlines() or ["no output"])[-1]}
    summary["exit"] = p.returncode
    return trace, rec, summary


def read_trace(path: Path, silence_s: float) -> tuple[list[tuple[float, float, int]], dict[int, list[float]]]:
    """(start, length s, cpu) of every silence while the run streamed; the wake-to-run waits [s] of each
    SCHED_FIFO thread. A CPU is watched from the first to the last time its busiest real-time thread
    (the emulated drive's receive thread, the SYNC sender) was switched in: in that span the thread
    wakes every few hundred microseconds, and before and after it an idle or busy CPU is quiet anyway."""
    events: list[tuple[float, int]] = []
    woken: dict[int, float] = {}
    waits: dict[int, list[float]] = defaultdict(list)
    runs: dict[tuple[int, int], list[float]] = defaultdict(list)
    with open(path, errors="replace") as f:
        for line in f:
            m = _LINE.match(line)
            if m is None:
                continue
            pid, cpu, ts, name, rest = int(m[1]), int(m[2]), float(m[3]), m[4], m[5]
            events.append((ts, cpu))
            woken.pop(pid, None)                  # an event in a thread's own context: it runs
            if name == "sched_wakeup":
                d = dict(_FIELD.findall(rest))
                if int(d.get("prio", 120)) < 100:
                    woken.setdefault(int(d["pid"]), ts)
            elif name == "sched_switch":
                d = dict(_FIELD.findall(rest))
                nxt = int(d.get("next_pid", -1))
                if nxt in woken:
                    waits[nxt].append(ts - woken.pop(nxt))
                    runs[(nxt, cpu)].append(ts)
    window: dict[int, tuple[float, float]] = {}
    for (_, cpu), times in sorted(runs.items(), key=lambda kv: len(kv[1])):
        window[cpu] = (times[0], times[-1])        # the busiest thread on that CPU is the last one set
    last: dict[int, float] = {}
    silences: list[tuple[float, float, int]] = []
    for ts, cpu in events:
        if cpu not in window or not window[cpu][0] <= ts <= window[cpu][1]:
            continue
        if cpu in last and ts - last[cpu] > silence_s:
            silences.append((last[cpu], ts - last[cpu], cpu))
        last[cpu] = ts
    return silences, waits


def align(gap_list: list[tuple[float, float]], silences: list[tuple[float, float, int]]) -> float:
    """The offset (trace time - recording time) that puts the most gaps inside silences."""
    best, best_n = 0.0, -1
    for g, _ in gap_list:
        for s, _, _ in silences:
            off = s - g
            n = sum(1 for g2, _ in gap_list for s2, l2, _ in silences
                    if s2 - 0.002 <= g2 + off <= s2 + l2 + 0.002)
            if n > best_n:
                best, best_n = off, n
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--config", default="configs/canopen-virtual.toml")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--silence-ms", type=float, default=1.0, help="a CPU with no event this long is silent")
    ap.add_argument("--limit-ms", type=float, default=2.0, help="gaps longer than this must line up with a silence")
    ap.add_argument("--keep", default=None, help="folder to keep the trace, recording and summary in")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--analyse", default=None, help="only analyse a folder kept with --keep")
    a = ap.parse_args(argv)
    if a.analyse:
        return report(a, Path(a.analyse) / "trace.txt", Path(a.analyse) / "run.parquet", {"exit": None})
    if not (TRACEFS / "trace").exists():
        print(f"error: no tracefs at {TRACEFS} (mount it, or run as root)", file=sys.stderr)
        return 2
    try:
        _write("tracing_on", "0")
    except OSError as exc:
        print(f"error: cannot use the tracer: {exc} (needs root)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="cpu-silences-") as d:
        work = Path(a.keep) if a.keep else Path(d)
        work.mkdir(parents=True, exist_ok=True)
        trace, rec, summary = traced_run(a.config, a.duration, work)
        return report(a, trace, rec, summary)


def report(a: argparse.Namespace, trace: Path, rec: Path, summary: dict[str, Any]) -> int:
    gap_list = gaps(rec) if rec.exists() else []
    silences, waits = read_trace(trace, 1e-3 * a.silence_ms)
    off = align([g for g in gap_list if g[1] > a.limit_ms], silences) if silences else 0.0
    rows = []
    for t, ms in sorted(gap_list, key=lambda g: -g[1]):
        hit = [(round(1e3 * length, 2), cpu) for s, length, cpu in silences
               if s - 0.002 <= t + off <= s + length + 0.002]
        rows.append({"t_s": round(t, 4), "gap_ms": round(ms, 2), "silences": hit})
    long = [r for r in rows if r["gap_ms"] > a.limit_ms]
    explained = [r for r in long if r["silences"]]
    worst_wait = {pid: round(1e3 * max(w), 2) for pid, w in waits.items() if w}
    out = {"exit": summary.get("exit"), "stop": (summary.get("stop") or {}).get("cause"),
           "gaps": len(rows), "gaps_over_limit": len(long), "explained": len(explained),
           "longest_silence_ms": round(1e3 * max((s[1] for s in silences), default=0.0), 2),
           "silences_per_cpu": {c: sum(1 for s in silences if s[2] == c) for c in sorted({s[2] for s in silences})},
           "rt_thread_longest_wait_ms": worst_wait, "longest_gaps": rows[:15]}
    if a.json:
        print(json.dumps(out, indent=1))
    else:
        print(f"run exit {out['exit']}, stop {out['stop']}; {out['gaps']} gaps, {len(long)} longer than "
              f"{a.limit_ms:g} ms, {len(explained)} of them inside a CPU silence")
        print(f"CPU silences over {a.silence_ms:g} ms: {out['silences_per_cpu']}, longest "
              f"{out['longest_silence_ms']} ms")
        print(f"longest wait from wake-up to running, per real-time thread [ms]: {worst_wait}")
        for r in rows[:15]:
            where = ", ".join(f"{ms} ms on CPU {c}" for ms, c in r["silences"]) or "no silence"
            print(f"  gap {r['gap_ms']} ms at t={r['t_s']} s: {where}")
    return 0 if len(explained) == len(long) else 1


if __name__ == "__main__":
    sys.exit(main())

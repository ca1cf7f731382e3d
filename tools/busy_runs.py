"""Run the quick start's ``rt-ident run`` several times with a busy loop on every core beside it.

A desktop bench PC runs other work while the loop runs: the loop then stalls now and then (tens to
hundreds of ms) and must come back without a lunge. This tool starts one CPU hog per core (plain
busy loops at normal priority), runs ``rt-ident run --json`` N times in a row, and prints per run: the
exit code, the stop cause, the stalls (count, longest), the overruns, the fallbacks and the largest
tracking error; at the end, how many runs ended as asked.

    python tools/busy_runs.py                 # 10 runs of the default config
    python tools/busy_runs.py -n 3 --duration 5 --json
    python tools/busy_runs.py --config configs/sim-load-change.toml
    python tools/busy_runs.py --stall-ms 300  # and a real-time process that takes the loop's CPU
                                              # for 300 ms every 2 s (the loop stalls that long)

Exit code 0 when every run exited 0, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _hog() -> None:
    x = 0
    while True:
        x += 1


def _stealer(cpu: int, busy_s: float, every_s: float) -> None:
    """SCHED_FIFO above the loop's priority on the loop's CPU, busy ``busy_s`` every ``every_s``: another
    real-time program that stalls the loop (the kernel's RT throttle leaves it 5 % of each second)."""
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
    while True:
        time.sleep(every_s)
        end = time.monotonic() + busy_s
        while time.monotonic() < end:
            pass


def one_run(config: str | None, duration: float | None, workdir: Path, k: int) -> dict:
    cmd = [sys.executable, "-m", "rt_ident", "run", "--json", "--rrd", str(workdir / f"run-{k}.rrd"),
           "--record", str(workdir / f"run-{k}.parquet")]
    if config:
        cmd.insert(4, config)
    if duration:
        cmd += ["--duration", str(duration)]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.monotonic() - t0
    try:
        s = json.loads(proc.stdout)
    except json.JSONDecodeError:
        return {"run": k, "rc": proc.returncode, "error": proc.stderr.strip().splitlines()[-1:] or ["no output"],
                "wall_s": wall}
    loop = s.get("loop") or {}
    ctl = s.get("control") or {}
    stalls = loop.get("stalls") or {}
    return {"run": k, "rc": proc.returncode, "cause": s["stop"]["cause"], "message": s["stop"]["message"],
            "stalls": stalls.get("count", 0), "longest_stall_ms": stalls.get("longest_ms", 0.0),
            "overruns": loop.get("overruns"), "fallbacks": ctl.get("fallbacks"),
            "max_error_um": None if ctl.get("max_error_m") is None else 1e6 * ctl["max_error_m"],
            "trusted": s.get("trusted"), "wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-n", "--runs", type=int, default=10)
    ap.add_argument("--config", default=None, help="run config (default: the quick start's)")
    ap.add_argument("--duration", type=float, default=None, help="seconds per run (default: the config's)")
    ap.add_argument("--hogs", type=int, default=os.cpu_count() or 1,
                    help="busy loops beside the runs (default: one a core)")
    ap.add_argument("--stall-ms", type=float, default=0.0,
                    help="also a SCHED_FIFO process that takes the loop's CPU this long every 2 s (needs root)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    hogs = [mp.Process(target=_hog, daemon=True) for _ in range(args.hogs)]
    if args.stall_ms > 0:
        cpu = max(os.sched_getaffinity(0))                 # the loop's CPU (rt_ident.loop.host.loop_cpu)
        hogs.append(mp.Process(target=_stealer, args=(cpu, args.stall_ms / 1e3, 2.0), daemon=True))
    for h in hogs:
        h.start()
    rows = []
    try:
        with tempfile.TemporaryDirectory(prefix="rt_ident-busy-") as d:
            for k in range(args.runs):
                row = one_run(args.config, args.duration, Path(d), k)
                rows.append(row)
                if not args.json:
                    print(" ".join(f"{key}={row[key]:.1f}" if isinstance(row[key], float) else f"{key}={row[key]}"
                                   for key in row if key != "message"), flush=True)
                    if row.get("message"):
                        print(f"    {row['message']}", flush=True)
    finally:
        for h in hogs:
            h.kill()
            h.join(5)
    ok = sum(1 for r in rows if r["rc"] == 0)
    summary = {"runs": len(rows), "exit_0": ok, "hogs": args.hogs, "stall_ms": args.stall_ms,
               "trips": sorted({r.get("cause") for r in rows if r.get("cause")}),
               "stalls": sum(r.get("stalls") or 0 for r in rows),
               "longest_stall_ms": max((r.get("longest_stall_ms") or 0.0 for r in rows), default=0.0),
               "rows": rows}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{ok} of {len(rows)} runs exited 0 beside {args.hogs} busy loops; stalls {summary['stalls']} "
              f"(longest {summary['longest_stall_ms']:.0f} ms); stop causes: {summary['trips'] or 'none'}")
    return 0 if ok == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())

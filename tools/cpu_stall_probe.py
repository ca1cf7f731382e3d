"""How often does this machine take the CPU away from a thread that never yields it?

A loop that only reads the clock, pinned to one CPU, records every gap between two clock
readings longer than ``--threshold-us``. Nothing in the loop can take that long, so each gap
is time the thread did not run: an interrupt storm, a higher-priority task, or - on a virtual
machine - the hypervisor running something else (steal). The real-time loop cannot do better
than this floor: a gap longer than (tick period - the loop's work) is an overrun whatever the
program does. Run it on the CPU the loop would get (by default the last one) while the
machine is otherwise as it will be during a run.

    python tools/cpu_stall_probe.py --seconds 10

Runs under SCHED_OTHER on purpose: a SCHED_FIFO thread that never sleeps is paused by the
kernel's RT throttle (50 ms every second), which would be measured instead of the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def probe(seconds: float, cpu: int | None, threshold_us: float) -> dict:
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    threshold_ns = int(threshold_us * 1000)
    clock = time.perf_counter_ns
    start = last = clock()
    end = start + int(seconds * 1e9)
    gaps: list[int] = []
    while last < end:
        now = clock()
        if now - last > threshold_ns:
            gaps.append(now - last)
        last = now
    gaps_us = sorted(g / 1000.0 for g in gaps)
    steal = _steal_ms(cpu)
    return {"cpu": cpu, "seconds": seconds, "threshold_us": threshold_us, "stalls": len(gaps_us),
            "stalled_ms": sum(gaps_us) / 1000.0, "largest_us": gaps_us[-5:][::-1],
            "over_1ms": sum(g > 1000.0 for g in gaps_us), "steal_ms_total_since_boot": steal}


def _steal_ms(cpu: int | None) -> float | None:
    key = "cpu" if cpu is None else f"cpu{cpu}"
    try:
        with open("/proc/stat") as fh:
            for line in fh:
                f = line.split()
                if f and f[0] == key and len(f) > 8:
                    return int(f[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")
    except OSError:
        pass
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the last usable one)")
    ap.add_argument("--threshold-us", type=float, default=500.0, help="report gaps longer than this")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.seconds <= 0 or args.threshold_us <= 0:
        ap.error("--seconds and --threshold-us must be > 0")
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    res = probe(args.seconds, cpu, args.threshold_us)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"CPU {cpu}, {args.seconds:g} s of a clock-reading loop: {res['stalls']} stalls longer than "
              f"{args.threshold_us:g} us ({res['over_1ms']} over 1 ms, {res['stalled_ms']:.1f} ms in total); "
              f"largest {', '.join(f'{g:.0f}' for g in res['largest_us']) or '-'} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())

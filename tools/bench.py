#!/usr/bin/env python
"""Benchmark rt_ident against peers on this machine (thin wrapper of :func:`rt_ident.bench.kernels.bench_main`).

    python tools/bench.py                      # full run, 60 s loop trials (takes ~15-25 min)
    python tools/bench.py --quick              # small data, 3 s loop trials
    python tools/bench.py --loop-seconds 0     # RLS / simulation / LS only
    python tools/bench.py --json > bench.json  # the same data as JSON
"""

from __future__ import annotations

import argparse
import logging

from rt_ident.bench.kernels import bench_main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON on stdout instead of tables")
    ap.add_argument("--quick", action="store_true", help="small data and loop trials of at most 3 s")
    ap.add_argument("--loop-seconds", type=float, default=60.0, help="length of each loop trial (0 skips the loop)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per contender (median reported)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    bench_main(json_out=args.json, quick=args.quick, loop_seconds=args.loop_seconds, repeats=args.repeats)


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Benchmark of ``rt-ident fleet`` on a generated fleet: throughput with 1 and 2 local workers (and the
scaling ratio), peak memory per worker, drift detection delay and false alarms, and what a plant costs.

    python tools/bench_fleet.py [FLEET_DIR] [--machines 6 --days 14 --duration 0.4]

Without FLEET_DIR (or if it holds no manifest) a fleet is generated there (tools/make_fleet.py) first.
Every figure comes from this run; the machine is shared, so compare the ratios, not the absolute rates.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import make_fleet  # noqa: E402

from rt_ident.fleet.drift import drift  # noqa: E402
from rt_ident.fleet.identify import identify_fleet  # noqa: E402
from rt_ident.fleet.manifest import read_manifest  # noqa: E402


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run(entries, history: Path, workers: int) -> dict:
    """Identify on a fresh LocalCluster of ``workers``; time only the tasks (cluster start-up apart)."""
    from distributed import Client, LocalCluster, as_completed

    from rt_ident.fleet.identify import append_history, identify_recording

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        items = [{"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time} for e in entries]
        # warm each worker (imports, numba kernels from the cache) outside the timing
        client.run(lambda: __import__("rt_ident.reports.identify"))
        t0 = time.perf_counter()
        futures = [client.submit(identify_recording, it, pure=False) for it in items]
        rows = [f.result() for f in as_completed(futures)]
        wall = time.perf_counter() - t0
        rss = client.run(_peak_rss_mb)
    append_history(history, rows)
    failed = sum(r["status"] == "failed" for r in rows)
    return {"workers": workers, "recordings": len(rows), "failed": failed, "wall_s": wall,
            "recordings_per_s": len(rows) / wall, "peak_rss_mb_per_worker": max(rss.values())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fleet", nargs="?", type=Path)
    ap.add_argument("--machines", type=int, default=6)
    ap.add_argument("--days", type=int, default=14)
    ap.add_argument("--duration", type=float, default=0.4)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    tmp = None
    folder = args.fleet
    if folder is None:
        tmp = tempfile.mkdtemp(prefix="rt-ident-fleet-bench-")
        folder = Path(tmp)
    try:
        if not (folder / "manifest.csv").is_file():
            t = time.perf_counter()
            make_fleet.main([str(folder), "--machines", str(args.machines), "--axes", "x,y", "--days", str(args.days),
                             "--duration", str(args.duration), "--seed", "7"])
            print(f"generated in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        entries = read_manifest(folder / "manifest.csv")
        runs = []
        for w in (1, 2):
            h = folder / f"bench-history-{w}"
            shutil.rmtree(h, ignore_errors=True)
            runs.append(_run(entries, h, w))
        # drift on the history of the 2-worker run; the full command once more for its skip path
        again = identify_fleet(entries, folder / "bench-history-2", workers=2)
        res = drift(folder / "bench-history-2")
        truth = json.loads((folder / "truth.json").read_text())
        onset = {(s["machine"], s["axis"]): s["onset_day"] for s in truth["series"]}
        first: dict = {}
        for a in res["alarms"]:
            key = (a["machine"], a["axis"])
            first[key] = min(first.get(key, 1 << 30), a["recordings_before"])
        worn = [k for k, d in onset.items() if d is not None]
        delays = {f"{m}-{a}": (first[(m, a)] - onset[(m, a)]) if (m, a) in first else None for m, a in worn}
        false = sorted(f"{m}-{a}" for (m, a) in first if onset[(m, a)] is None)
        per_rec = runs[0]["wall_s"] / runs[0]["recordings"]
        out = {"recordings": len(entries), "series": len(onset), "worn": len(worn),
               "runs": runs, "scaling_2_over_1": runs[1]["recordings_per_s"] / runs[0]["recordings_per_s"],
               "rerun_identified": again["identified"], "rerun_skipped": again["skipped"],
               "detection_delay_days": delays, "missed": [k for k, v in delays.items() if v is None],
               "false_alarm_series": false, "healthy_series": len(onset) - len(worn),
               "seconds_per_recording_one_worker": per_rec,
               "plant_200_axes_3_shifts": {"recordings_per_day": 600,
                                           "worker_seconds_per_day": 600 * per_rec}}
        if args.json:
            print(json.dumps(out, indent=1))
            return 0
        print(f"fleet: {out['recordings']} recordings of {out['series']} series ({out['worn']} wearing), "
              f"{args.duration} s each")
        for r in runs:
            print(f"  {r['workers']} worker(s): {r['recordings_per_s']:.2f} recordings/s ({r['wall_s']:.1f} s), "
                  f"peak RSS per worker {r['peak_rss_mb_per_worker']:.0f} MB, failed {r['failed']}")
        print(f"  scaling 2 workers / 1 worker: {out['scaling_2_over_1']:.2f}x (2 cores, shared)")
        print(f"  re-run: {out['rerun_identified']} identified, {out['rerun_skipped']} skipped")
        print(f"  drift: detection delay (recordings = days after onset) {delays}; missed {out['missed']}; "
              f"false alarms on {len(false)} of {out['healthy_series']} healthy series {false}")
        print(f"  a plant of 200 axes x 3 shifts/day: 600 recordings/day x {per_rec:.2f} s = "
              f"{600 * per_rec / 60:.1f} worker-minutes/day")
        return 0
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())

"""The longest run of samples a CANopen run loses, over several runs, and what the host did meanwhile.

Runs ``rt-ident run CONFIG --duration D --json --record ...`` N times in a row (the emulated drive in
its own process, as the quick start's CANopen config does) and reads each recording's ``seq`` column:
a gap is consecutive sample numbers missing (a SYNC whose TPDOs came late, stale or not at all). Per
run it prints the longest gap in ms, the number of gaps, the samples lost, the SYNC sender's overruns,
the loop's overruns, its largest lateness and the hypervisor's steal time on the loop's CPU, so a gap
can be put beside what the host did at the same time.

    python tools/canopen_gaps.py                     # 10 runs of configs/canopen-virtual.toml, 10 s each
    python tools/canopen_gaps.py -n 3 --duration 5 --json

Exit code 0 when no run lost more than ``--limit-ms`` (default 5 ms) in one go, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq


def gaps(parquet: Path) -> list[tuple[float, float]]:
    """(time s, length ms) of each gap in the recorded sample numbers (the period: the median step of t)."""
    table = pq.read_table(parquet, columns=["t", "seq"])
    seq = table.column("seq").to_numpy()
    t = table.column("t").to_numpy()
    d = np.diff(seq)
    period_s = float(np.median(np.diff(t)[d == 1]))
    idx = np.flatnonzero(d > 1)
    return [(float(t[k]), float((d[k] - 1) * period_s * 1e3)) for k in idx]


def one_run(config: str, duration: float, work: Path, k: int) -> dict[str, Any]:
    rec = work / f"run{k}.parquet"
    cmd = [sys.executable, "-m", "rt_ident.cli", "run", config, "--duration", str(duration), "--json",
           "--record", str(rec), "--rrd", str(work / f"run{k}.rrd")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=duration + 120)
    out: dict[str, Any] = {"run": k, "exit": p.returncode}
    try:
        s = json.loads(p.stdout)
    except json.JSONDecodeError:
        out["error"] = (p.stderr.strip().splitlines() or ["no output"])[-1]
        return out
    loop, bc = s.get("loop", {}), s.get("backend_counters", {})
    g = gaps(rec) if rec.exists() else []
    stop = s.get("stop") or {}
    if stop.get("cause"):
        out["stop"] = f"{stop.get('cause')}: {stop.get('message', '')}"[:200]
    out.update(longest_gap_ms=max((ms for _, ms in g), default=0.0),
               at_s=max(g, key=lambda x: x[1])[0] if g else None, gaps=len(g),
               lost=loop.get("lost_samples"), sync_overruns=bc.get("sync_overruns"),
               overruns=loop.get("overruns"), lateness_max_us=loop.get("lateness_us", {}).get("max"),
               steal_ms=loop.get("host", {}).get("steal_ms"))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/canopen-virtual.toml")
    ap.add_argument("-n", type=int, default=10, help="runs")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per run")
    ap.add_argument("--limit-ms", type=float, default=5.0, help="longest gap allowed")
    ap.add_argument("--json", action="store_true", help="one JSON document instead of a table")
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="canopen-gaps-") as d:
        for k in range(a.n):
            r = one_run(a.config, a.duration, Path(d), k)
            rows.append(r)
            for f in Path(d).glob(f"run{k}.*"):
                f.unlink()
            if not a.json:
                print(" ".join(f"{key}={val:.4g}" if isinstance(val, float) else f"{key}={val}"
                               for key, val in r.items()), flush=True)
    worst = max((r.get("longest_gap_ms", float("inf")) for r in rows), default=0.0)
    ok = all(r.get("exit") == 0 for r in rows) and worst <= a.limit_ms
    if a.json:
        print(json.dumps({"runs": rows, "longest_gap_ms": worst, "ok": ok}, indent=1))
    else:
        verdict = "ok" if ok else "NOT MET"
        print(f"longest gap over {len(rows)} runs: {worst:.2f} ms (limit {a.limit_ms:g} ms): {verdict}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

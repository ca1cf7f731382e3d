#!/usr/bin/env python
"""Write a fleet to test ``rt-ident fleet`` on: N machines x A axes x D days of recordings, some worn.

Each recording is a short closed-loop run of the whole product on the simulated axis (``run_offline``:
the host's position loop, quantized 2^17-count encoder and 0.1 um scale, torque noise on the measured
torque and on the applied torque, a different noise seed per recording, each machine's axis a few
per cent off the nominal Table 1 axis). A chosen fraction of the series wears from a random day on; by
default both ways at once: ball-screw stiffness K -0.5 %/day (preload loss) and coupling damping B +2 %/day
(lubrication). ``--wear k,b,load`` gives the worn series one kind each, in turn: K alone, B alone, or a load
change (table inertia I2 +30 % from the day after the onset: a heavier fixture).

Writes ``OUT/recordings/*.parquet``, ``OUT/manifest.csv`` (``rt-ident fleet identify`` input) and
``OUT/truth.json`` (which series wear, how, from which day, and each recording's true parameters).

    python tools/make_fleet.py OUT --machines 4 --axes x,y --days 12 --worn 0.5 --seed 1
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

from rt_ident.axis.params import thomson_x
from rt_ident.compose.offline import run_offline
from rt_ident.config import load
from rt_ident.fleet.manifest import Entry, write_manifest

K_PER_DAY = -0.005
B_PER_DAY = 0.02
LOAD_STEP = 0.30

#: kind of wear -> which parameters move and how; ``d`` is the number of days since the onset
WEAR = {
    "k-b": {"K": lambda d: 1.0 + K_PER_DAY * d, "B": lambda d: 1.0 + B_PER_DAY * d},
    "k": {"K": lambda d: 1.0 + K_PER_DAY * d},
    "b": {"B": lambda d: 1.0 + B_PER_DAY * d},
    "load": {"I2": lambda d: 1.0 + LOAD_STEP * (d > 0)},
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--machines", type=int, default=4)
    ap.add_argument("--axes", default="x,y")
    ap.add_argument("--days", type=int, default=12)
    ap.add_argument("--worn", type=float, default=0.5, help="fraction of the series that wear (default 0.5)")
    ap.add_argument("--duration", type=float, default=0.4, help="seconds per recording (default 0.4)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--start", default="2026-11-01", help="date of day 0 (ISO)")
    ap.add_argument("--wear", default="k-b", help="kinds of wear, comma-separated, given to the worn series in "
                    f"turn: {', '.join(WEAR)} (default k-b: K and B together)")
    args = ap.parse_args(argv)
    if args.machines < 1 or args.days < 1 or not 0 <= args.worn <= 1 or args.duration <= 0:
        ap.error("--machines and --days must be >= 1, --worn in [0, 1], --duration > 0")
    kinds = [w.strip() for w in args.wear.split(",") if w.strip()]
    if not kinds or any(w not in WEAR for w in kinds):
        ap.error(f"--wear: comma-separated kinds among {', '.join(WEAR)}")
    rng = np.random.default_rng(args.seed)
    axes = [a.strip() for a in args.axes.split(",") if a.strip()]
    rec_dir = args.out / "recordings"
    rec_dir.mkdir(parents=True, exist_ok=True)
    day0 = dt.datetime.fromisoformat(args.start).replace(hour=6, tzinfo=dt.UTC)
    nominal = thomson_x()
    series = [(f"m{i + 1:02d}", a) for i in range(args.machines) for a in axes]
    n_worn = int(round(args.worn * len(series)))
    worn = set(map(tuple, rng.permutation(np.array(series, dtype=object))[:n_worn].tolist()))
    wear_of = {s: kinds[i % len(kinds)] for i, s in enumerate(x for x in series if x in worn)}
    truth: dict = {"series": [], "k_per_day": K_PER_DAY, "b_per_day": B_PER_DAY, "load_step": LOAD_STEP}
    entries: list[Entry] = []
    total = len(series) * args.days
    t0 = time.monotonic()
    done = 0
    for machine, axis in series:
        spread = 1.0 + 0.03 * rng.standard_normal(4)          # this machine's axis vs the nominal one
        base = {k: getattr(nominal, k) * f for k, f in zip(("I1", "I2", "B", "K"), spread)}
        onset = int(rng.integers(max(6, args.days // 3), max(7, args.days - 3))) if (machine, axis) in worn else None
        recs = []
        for day in range(args.days):
            worn_days = max(0, day - onset) if onset is not None else 0
            p = dict(base)
            for k, factor in WEAR[wear_of[(machine, axis)]].items() if onset is not None else ():
                p[k] *= factor(worn_days)
            path = rec_dir / f"{machine}-{axis}-day{day:03d}.parquet"
            cfg = load(None, **{"loop.realtime": False, "telemetry.sink": "off", "recording.enabled": False,
                                "loop.duration": args.duration, **{f"axis.{k}": v for k, v in p.items()},
                                "backend.seed": int(rng.integers(1 << 31)), "backend.torque_meas_noise": 2e-4,
                                "backend.torque_process_noise": 1e-4})
            out = run_offline(cfg, record=str(path), overwrite=True)
            if out["stop"]:
                print(f"error: {path.name}: the run stopped: {out['stop']}", file=sys.stderr)
                return 1
            entries.append(Entry(str(path.relative_to(args.out)), machine, axis,
                                 day0 + dt.timedelta(days=day, minutes=int(rng.integers(0, 120)))))
            recs.append({"day": day, **p})
            done += 1
            print(f"\r{done}/{total} recordings ({time.monotonic() - t0:.0f} s)", end="", file=sys.stderr, flush=True)
        truth["series"].append({"machine": machine, "axis": axis, "worn": onset is not None, "onset_day": onset,
                                "wear": wear_of.get((machine, axis)), "recordings": recs})
    print(file=sys.stderr)
    write_manifest(args.out / "manifest.csv", entries)
    (args.out / "truth.json").write_text(json.dumps(truth, indent=1))
    print(f"{total} recordings of {len(series)} series ({n_worn} wearing) in {args.out}; "
          f"manifest {args.out / 'manifest.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

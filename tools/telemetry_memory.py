"""Drive a TelemetryProcess with synthetic loop telemetry faster than real time; print its RSS.

The memory measurement of docs/measurements.md.

    PYTHONPATH=$PWD python tools/telemetry_memory.py --minutes 10 --speed 10 --out /tmp/t.rrd

The child's clock runs ``--speed`` times faster than the wall clock (its batches, step-line extensions
and FRF draws are paced per simulated second as in a real run); the parent publishes what a loop at
``--rate`` samples/s and 1 kHz ticks would, 20 ticks a window, a fit that moves every estimate and
the resonance every half simulated second (with its FRF view) and a loop gain every 10 s. RSS of the
telemetry process is read from /proc every simulated ``--every`` seconds and once more before
``close()``; the time ``close()`` took, its report and the file's chunk count are printed too.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import types
from pathlib import Path

import numpy as np

import rt_ident.processes.telemetry as tel
from rt_ident.outputs.sinks import TelemetryConfig

_ORIG_MAIN = tel._telemetry_main


def _scaled_main(*args, **kwargs):                           # the child: its clock runs --speed times faster
    speed = float(os.environ["TELEMETRY_DRIVER_SPEED"])
    t0 = time.monotonic()
    tel.time = types.SimpleNamespace(monotonic=lambda: t0 + (time.monotonic() - t0) * speed, sleep=time.sleep)
    return _ORIG_MAIN(*args, **kwargs)


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _frf_view() -> dict[str, np.ndarray]:
    f = np.geomspace(10, 5000, 200)
    fm = np.geomspace(10, 5000, 60)
    view = {f"g{j}_{k}": np.linspace(-80, -20, 200) + d for j in (1, 2) for k, d in
            (("db", 0.0), ("lo", -2.0), ("hi", 2.0), ("deg", -100.0))}
    view.update(f_model=f, f_meas=fm, m1_db=np.linspace(-80, -20, 60), p1_deg=np.full(60, -180.0),
                m2_db=np.linspace(-85, -25, 60), p2_deg=np.full(60, -200.0))
    return view


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes")
    ap.add_argument("--speed", type=float, default=10.0, help="simulated seconds per wall-clock second")
    ap.add_argument("--rate", type=int, default=1000, help="samples/s sent to the viewer (telemetry.rate_hz)")
    ap.add_argument("--every", type=float, default=30.0, help="RSS every this many simulated seconds")
    ap.add_argument("--out", default="/tmp/telemetry_memory.rrd")
    a = ap.parse_args()
    os.environ["TELEMETRY_DRIVER_SPEED"] = str(a.speed)
    tel._telemetry_main = _scaled_main    # pickled by name: the spawned child imports this module too
    out = Path(a.out)
    out.unlink(missing_ok=True)
    cfg = TelemetryConfig(sink="rrd", rrd_path=str(out), queue_size=1024, ring_bytes=32 << 20)
    tp = tel.TelemetryProcess(cfg).start()
    tp.set_truth({"I1": 0.01, "I2": 0.02, "B": 1.0, "K": 1e5, "wn": 4162.0, "wd": 4159.0, "zeta": 0.04})
    assert tp.wait_ready(30.0)
    window_s, ticks = 0.02, 20
    n = int(round(a.rate * window_s))
    total = int(round(a.minutes * 60.0 / window_s))
    frf = _frf_view()
    lg = {"f_hz": np.geomspace(10, 5000, 200), "mag_db": np.linspace(40, -40, 200),
          "phase_deg": np.linspace(-270, -150, 200)}
    rng = np.random.default_rng(0)
    t0 = time.monotonic()
    samples: list[tuple[float, float, float]] = []   # (simulated s, wall s, RSS MB)
    next_rss = 0.0
    for w in range(total):
        ts = w * window_s
        while time.monotonic() - t0 < ts / a.speed:      # pace: speed x real time
            time.sleep(0.001)
        t = ts + np.arange(n) / a.rate
        x = rng.standard_normal(n)
        tp.publish({"t": t, "theta1": x, "theta2": -x, "torque_meas": x, "torque_cmd": x, "torque_filt": x,
                    "torque_hat": x})
        tt = ts + np.arange(ticks) * 1e-3
        fit = float(int(2 * ts))                      # a new fit every half simulated second
        tick = {"t": tt, "t_tick": tt, "lateness_us": 20 + 5 * rng.random(ticks),
                "x_ref": np.sin(tt), "x_table": np.sin(tt), "error_m": 1e-6 * rng.standard_normal(ticks),
                "u_control": rng.standard_normal(ticks),
                **{f"svf_{k}": 1.0 + 1e-3 * rng.standard_normal(ticks) for k in ("I1", "I2", "B", "K")}}
        est = {"I1": 0.01, "I2": 0.02, "B": 1.0, "K": 1e5, "wn": 4162.0, "wd": 4159.0, "zeta": 0.04}
        win = {k: v * (1.0 + 1e-4 * (fit % 7)) for k, v in est.items()}           # every fit moves them all
        win.update({f"lo_{k}": 0.9 * v for k, v in win.items()} | {f"hi_{k}": 1.1 * v for k, v in win.items()})
        win.update(overruns=0.0, stalls=0.0, gain_theta2=1.0, gain_omega1=2.0, pm_deg=50.0, gm_db=8.0,
                   n_accepted=float(int(ts / 10)), n_rejected=0.0, fallbacks=0.0)
        tp.publish(tick, win)
        if w % int(round(0.5 / window_s)) == 0:      # with each fit its FRF (the resonance moves: drawn every 2 s)
            frf["marks_hz"] = np.array([662.0 * (1.0 + 0.01 * (fit % 2)), 400.0])
            tp.publish_fit(ts, frf)
        if w % int(round(10.0 / window_s)) == 0:
            tp.publish_loop_gain(ts, lg, {"pm_deg": 50.0, "gm_db": 8.0})
        if ts >= next_rss:
            samples.append((ts, time.monotonic() - t0, _rss_mb(tp.pid)))
            next_rss += a.every
    last_rss = _rss_mb(tp.pid)
    c0 = time.monotonic()
    rep = tp.close(timeout=30.0)
    close_s = time.monotonic() - c0
    chunks = None
    if rep.get("footer"):                            # the manifest counts them (a footerless file: not counted)
        from rerun.chunk import RrdReader

        chunks = len(RrdReader(str(out)).store())
    first = next(r for s, _, r in samples if s >= 0.1 * a.minutes * 60.0)
    print(json.dumps({"minutes": a.minutes, "speed": a.speed, "rss_mb": [(round(s), round(w, 1), round(r, 1))
                                                                        for s, w, r in samples],
                      "rss_last_mb": round(last_rss, 1), "growth_after_first_tenth_pct":
                      round(100.0 * (last_rss / first - 1.0), 2), "close_s": round(close_s, 2),
                      "rrd_mb": round(out.stat().st_size / 1e6, 1), "chunks": chunks, "close": rep}, default=str))


if __name__ == "__main__":
    main()

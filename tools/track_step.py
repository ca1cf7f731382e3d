"""Measure how fast the streaming "frequency" estimator tracks a 20 % step in the damping B.

Default loop settings: sim plant at the paper's Dt (34 kHz), 2^17-count encoder, 0.1 um scale, torque
noise, position hold closed, Schroeder period 512 samples (15.1 ms), harmonics 1..20. After 20 periods
B steps by +20 % (a friction change); the estimator is fitted after every period. Printed: for each
forgetting factor (per period), the time after the step until the estimate stays within 2 % of the new
B, and the steady scatter before the step.

    python tools/track_step.py [--step 0.2] [--band 0.02]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.estimators.frequency_stream import StreamingFrequencyEstimator


def track(forgetting: float, step: float, band: float, before: int = 20, after: int = 60, seed: int = 3) -> dict:
    p, dt, N = thomson_x(), 2.9481e-5, 512
    ms = schroeder_multisine(N, (1, 20), peak=0.3)
    sensors = SensorConfig(counts_per_rev=2**17, scale_resolution=1e-7, torque_meas_noise=0.0005)
    sim = PlantSimulator(p, dt, sensors=sensors, controller=HoldController(), torque_limit=1.0, seed=seed)
    est = StreamingFrequencyEstimator(N, ms.harmonics, dt, forgetting=forgetting, discard_periods=2)
    B_new = p.B * (1 + step)
    history = []
    for k in range(before + after):
        if k == before:
            sim = PlantSimulator(p.with_(B=B_new), dt, sensors=sensors, controller=HoldController(),
                                 torque_limit=1.0, seed=seed + 1, x0=sim.state)
        blk = sim.step_block(ms.signal)
        est.update_block(blk.theta1, blk.theta2, blk.torque_meas)
        if est.periods >= 1:
            history.append((k, est.estimate().params.B))
    ks = np.array([k for k, _ in history])
    Bs = np.array([b for _, b in history])
    pre = Bs[(ks >= before - 8) & (ks < before)]
    post_k, post_B = ks[ks >= before], Bs[ks >= before]
    outside = np.abs(post_B / B_new - 1) > band
    settle = None
    if not outside[-1]:
        last_out = np.flatnonzero(outside)
        first_in = 0 if last_out.size == 0 else last_out[-1] + 1
        settle = int(post_k[first_in] - before + 1) * N * dt
    return {"forgetting": forgetting, "settle_s": settle, "period_s": N * dt,
            "scatter_before_pct": float(100 * np.std(pre / p.B)),
            "final_error_pct": float(100 * (post_B[-1] / B_new - 1))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=0.2)
    ap.add_argument("--band", type=float, default=0.02)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rows = [track(lam, a.step, a.band) for lam in (1.0, 0.9, 0.7, 0.5)]
    if a.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"B step +{a.step:.0%}, settle = stays within {a.band:.0%} of the new B")
    print(f"{'forgetting/period':>18} {'settle [s]':>11} {'scatter before [%]':>19} {'final err [%]':>14}")
    for r in rows:
        s = "not within" if r["settle_s"] is None else f"{r['settle_s']:.3f}"
        print(f"{r['forgetting']:>18} {s:>11} {r['scatter_before_pct']:>19.3f} {r['final_error_pct']:>14.3f}")


if __name__ == "__main__":
    main()

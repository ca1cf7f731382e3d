"""When the control torque lands, and what a tick of delay more than designed costs.

Prints (1) the margins of the XY axes' designs as designed (one tick) and with the torque one tick
later (the loop the design does not know about), (2) for the emulated drives, how many control
torques missed their SYNC (``late_torques``) with the ticks put just after the answers to a SYNC
(Backend.read_phase) and with the ticks wherever the start left them, and (3) for the emulated serial
board, how many samples ran on an older torque than the one planned for them, designed for a delay of
two ticks (the shipped config) and of one.

    python tools/late_torque.py [--seconds 4] [--runs 2]
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def margins() -> None:
    from rt_ident.axis.params import AxisParams
    from rt_ident.control.design import design_lqr, design_rigid, loop_margins

    tick = 1e-3
    axes = {"X": AxisParams(2.7e-5, 8.3e-6, 2.1e-3, 1.1e2), "Y": AxisParams(2.7e-5, 2.5e-5, 2.1e-3, 1.1e2)}
    print("design            as designed (gm up dB, pm deg)   one tick later")
    for name, p in axes.items():
        designs = (("model 20 Hz", design_lqr(p, tick, 20.0)), ("rigid 10 Hz", design_rigid(p.I1 + p.I2, tick, 10.0)))
        for kind, g in designs:
            g = np.asarray(g, dtype=float).ravel()
            late = np.concatenate([g[:4], [0.0], g[4:]])     # the torque in flight one tick longer, unseen
            m1, m2 = loop_margins(g, p, tick), loop_margins(late, p, tick)
            print(f"{name} {kind}    {m1.gm_up_db:6.2f} {m1.pm_deg:6.2f}                  "
                  f"{m2.gm_up_db:6.2f} {m2.pm_deg:6.2f}")


def runs(seconds: float, n: int) -> None:
    from drivers.cia402.drive import Cia402Backend
    from rt_ident.compose import run as run_mod
    from rt_ident.config import load

    anchored = Cia402Backend.read_phase

    def unanchored(_self: Cia402Backend) -> None:
        return None

    for config in ("configs/canopen-virtual.toml", "configs/xy-canopen-virtual.toml"):
        for how, phase in (("after the answers", anchored), ("where the start left them", unanchored)):
            Cia402Backend.read_phase = phase      # type: ignore[method-assign]
            for _ in range(n):
                cfg = load(config, **{"loop.duration": seconds, "telemetry.sink": "off",
                                      "recording.enabled": False})
                s = run_mod.run(cfg)
                counters = {name: ax["backend_counters"] for name, ax in (s.get("axes") or {}).items()} \
                    or {"": s["backend_counters"]}
                late = {k: (c["late_torques"], c["late_plan_samples"]) for k, c in counters.items()}
                print(json.dumps({"config": config, "ticks": how, "ticks_run": s["loop"]["ticks"],
                                  "late_torques, late_plan_samples": late, "stop": s["stop"]["cause"]}))
    Cia402Backend.read_phase = anchored          # type: ignore[method-assign]


def serial_runs(seconds: float, n: int) -> None:
    from rt_ident.compose import run as run_mod
    from rt_ident.config import load

    for delay in (2, 1):
        for _ in range(n):
            cfg = load("configs/serial-virtual.toml", **{"loop.duration": seconds, "telemetry.sink": "off",
                                                         "recording.enabled": False, "control.delay_ticks": delay})
            s = run_mod.run(cfg)
            c = s["backend_counters"]
            print(json.dumps({"config": "configs/serial-virtual.toml", "delay_ticks": delay,
                              "samples": s["loop"]["samples"], "late_torques": c["late_torques"],
                              "plan_late": c["plan_late"], "table_rms_um": 1e6 * s["control"]["rms_error_m"],
                              "stop": s["stop"]["cause"]}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--runs", type=int, default=2)
    a = ap.parse_args()
    margins()
    runs(a.seconds, a.runs)
    serial_runs(a.seconds, a.runs)


if __name__ == "__main__":
    main()

"""The friction bias table: the axis with friction identified with and without a friction model.

    python tools/friction_ident.py [--seconds 4] [--seeds 3]

Data (per seed): the simulated THOMSON axis of Table 1 with :func:`rt_ident.axis.friction.thomson_friction`
(Karnopp sticking, Stribeck), the paper's Dt (34 kHz), 2^17-count motor encoder, 0.1 um linear scale,
0.5 mN m torque noise, in closed loop: a host PD at 1 kHz (20 Hz, on the measured motor angle) tracks a
1 Hz sine of 6 rad (4.8 mm), and a Schroeder multisine probe (512 samples, harmonics 1..20, 0.1 N m peak,
per sample - what ``rt-ident run`` superposes) excites the resonance. Fitted by

* ``svf-ls`` with ``two-inertia`` (no friction) and with ``two-inertia-friction``;
* ``frequency`` (the default, linear-only: two-inertia) on the same data.

Prints the error (%) of each parameter, mean and worst over the seeds; and, as a check that the friction
model does no harm, ``two-inertia-friction`` on the same axis without friction (Fc estimates vs 0).
"""

from __future__ import annotations

import argparse
import logging
import math
import warnings

import numpy as np

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.friction import Friction, thomson_friction
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import PlantSimulator, SensorConfig
from rt_ident.estimators.friction import fit_friction
from rt_ident.estimators.registry import IdentData, identify

DT = 2.9481e-5
KEYS = ("I1", "I2", "B", "K")


def record(fr: Friction | None, seconds: float, seed: int):
    p = thomson_x()
    sim = PlantSimulator(p, DT, sensors=SensorConfig(torque_meas_noise=5e-4), friction=fr, seed=seed,
                         torque_limit=1.0)
    ms = schroeder_multisine(512, (1, 20), peak=0.1, seed=seed)
    per = 34
    J = p.I1 + p.I2
    w = 2 * math.pi * 20.0
    kp, kd = J * w * w, 2 * 0.7 * J * w
    out, prev, v, k = [], None, 0.0, 0
    for i in range(int(seconds / (per * DT))):
        t = i * per * DT
        ref, vref = 6.0 * math.sin(2 * math.pi * t), 12 * math.pi * math.cos(2 * math.pi * t)
        u = 0.0
        if out:
            m = out[-1][0][-1]
            v += 0.3 * ((0.0 if prev is None else (m - prev) / (per * DT)) - v)
            prev = m
            u = kp * (ref - m) + kd * (vref - v)
        b = sim.step_block(u + ms.at(np.arange(k, k + per)))
        k += per
        out.append((b.theta1, b.theta2, b.torque_meas))
    return tuple(np.concatenate([o[j] for o in out]) for j in range(3))


def main() -> None:
    logging.getLogger("rt_ident.estimators").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    p, fr = thomson_x(), thomson_friction()
    truth = {"I1": p.I1, "I2": p.I2, "B": p.B, "K": p.K, "Fc1": fr.Fc1, "Fv1": fr.Fv1, "Fc2": fr.Fc2, "Fv2": fr.Fv2}
    rows: dict[str, list[dict[str, float]]] = {"svf-ls two-inertia": [], "svf-ls two-inertia-friction": [],
                                               "frequency (two-inertia)": []}
    zero_fc = []
    for seed in range(a.seeds):
        th1, th2, tq = record(fr, a.seconds, seed)
        for model in ("two-inertia", "two-inertia-friction"):
            r = fit_friction(th1, tq, DT, model=model, theta2=th2)
            rows[f"svf-ls {model}"].append({k: 100 * (r.parameters[k] / truth[k] - 1) for k in truth
                                            if k in r.parameters})
        f = identify(IdentData(None, th1, th2, tq, dt=DT, period=512), "frequency")
        fp = f.as_dict()["parameters"]
        rows["frequency (two-inertia)"].append({k: 100 * (fp[k] / truth[k] - 1) for k in KEYS})
        th1, th2, tq = record(None, a.seconds, seed)
        r0 = fit_friction(th1, tq, DT, model="two-inertia-friction", theta2=th2)
        zero_fc.append((r0.parameters["Fc1"], r0.parameters["Fc2"],
                        max(abs(r0.parameters[k] / truth[k] - 1) * 100 for k in KEYS)))
    cols = list(truth)
    print(f"error % (mean / worst |.| over {a.seeds} seeds), {a.seconds:g} s each")
    print(f"{'fit':30s}" + "".join(f"{c:>16s}" for c in cols))
    for name, rs in rows.items():
        cells = []
        for c in cols:
            vals = [r[c] for r in rs if c in r]
            cells.append(f"{np.mean(vals):+7.2f} / {np.max(np.abs(vals)):5.2f}" if vals else "-")
        print(f"{name:30s}" + "".join(f"{x:>16s}" for x in cells))
    fc1 = [z[0] for z in zero_fc]
    fc2 = [z[1] for z in zero_fc]
    print(f"frictionless axis, two-inertia-friction: Fc1 {np.mean(fc1):+.2e} N m, Fc2 {np.mean(fc2):+.2e} N m "
          f"(true 0; THOMSON Fc1 = {fr.Fc1:g}), worst I1/I2/B/K error {max(z[2] for z in zero_fc):.2f} %")


if __name__ == "__main__":
    main()

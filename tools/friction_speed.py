"""Steps/s of the sampled plant kernel with and without friction.

    python tools/friction_speed.py [--steps 1000000] [--repeats 5]

Runs :class:`rt_ident.axis.plant.PlantSimulator` (THOMSON axis of Table 1, the paper's Dt, 2^17-count
encoder, 0.1 um scale, 0.5 mN m torque noise, a 20 Hz sine torque) once frictionless and once with
:func:`rt_ident.axis.friction.thomson_friction` (and once more with 2 um of backlash); prints the
median steps/s of each. :func:`plant_steps_per_second` is what a bench can call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from rt_ident.axis.friction import Friction, thomson_friction
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import PlantSimulator, SensorConfig

DT = 2.9481e-5


def plant_steps_per_second(friction: Friction | None, steps: int = 1_000_000, repeats: int = 5) -> float:
    """Median steps/s of ``PlantSimulator.step_block`` over ``steps`` samples (compiled kernel)."""
    p = thomson_x()
    sensors = SensorConfig(torque_meas_noise=5e-4)
    u = 0.05 * np.sin(2 * np.pi * 20.0 * np.arange(steps) * DT)
    rates = []
    for r in range(repeats):
        sim = PlantSimulator(p, DT, sensors=sensors, friction=friction, seed=r)
        sim.step_block(u[:16])                 # compile / load from cache outside the timing
        t0 = time.perf_counter()
        sim.step_block(u)
        rates.append(steps / (time.perf_counter() - t0))
    return statistics.median(rates)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    fr = thomson_friction()
    cases = [("frictionless", None), ("THOMSON friction (Karnopp, Stribeck)", fr),
             ("friction + 2 um backlash", fr.with_(backlash=2e-6 / thomson_x().lead))]
    for name, f in cases:
        print(f"{name:40s} {plant_steps_per_second(f, a.steps, a.repeats) / 1e6:7.2f} M steps/s")


if __name__ == "__main__":
    main()

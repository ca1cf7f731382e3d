"""Reversal spikes with and without friction feedforward: one axis, sine reference.

    python tools/friction_reversal.py [--duration 4] [--amplitude 0.005] [--hz 1] [--png docs/friction_reversal.png]

1. identify: the simulated THOMSON axis with its friction (:func:`rt_ident.axis.friction.thomson_friction`,
   Karnopp sticking, Stribeck), 2^17-count encoder, 0.1 um scale, 0.5 mN m torque noise, in closed loop
   (a host PD at 1 kHz tracking a sine, a white probing torque), fitted with ``two-inertia-friction``
   by ``svf-ls`` (:func:`rt_ident.estimators.friction.fit_friction`);
2. control: :func:`rt_ident.compose.offline.run_offline` (the real loop on virtual time) with the same
   plant, ``control.mode = "fixed"`` (the model controller of the nominal axis, 20 Hz) and a sine
   reference, twice: inertia feedforward only (the law's default) and inertia + friction feedforward from
   the *estimated* Fc1 + Fc2, Fv1 + Fv2 (:class:`rt_ident.control.feedforward.FrictionFeedforward`,
   attached to the law on the first tick).

Prints the peak |table error| around the reference's reversals (after the fade-in) and the RMS, with and
without compensation, and writes a PNG of the error over time.
"""

from __future__ import annotations

import argparse
import logging
import math
import warnings

import numpy as np

from rt_ident.axis.friction import thomson_friction
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import PlantSimulator, SensorConfig
from rt_ident.compose.offline import run_offline
from rt_ident.config import from_mapping
from rt_ident.control.feedforward import FrictionFeedforward
from rt_ident.estimators.friction import fit_friction

DT = 2.9481e-5


def bench_record(seconds: float = 3.0, seed: int = 0):
    """Closed-loop bench-like record of the THOMSON axis with friction: (theta1, theta2, torque_meas)."""
    p, fr = thomson_x(), thomson_friction()
    sim = PlantSimulator(p, DT, sensors=SensorConfig(torque_meas_noise=5e-4), friction=fr, seed=seed,
                         torque_limit=1.0)
    per = 34
    J = p.I1 + p.I2
    w = 2 * math.pi * 20.0
    kp, kd = J * w * w, 2 * 0.7 * J * w
    rng = np.random.default_rng(seed + 1)
    out, prev, v = [], None, 0.0
    for i in range(int(seconds / (per * DT))):
        t = i * per * DT
        ref, vref = 6.0 * math.sin(2 * math.pi * t), 12 * math.pi * math.cos(2 * math.pi * t)
        u = 0.0
        if out:
            m = out[-1][0][-1]
            v += 0.3 * ((0.0 if prev is None else (m - prev) / (per * DT)) - v)
            prev = m
            u = kp * (ref - m) + kd * (vref - v)
        b = sim.step_block(u + 0.1 * rng.standard_normal(per))
        out.append((b.theta1, b.theta2, b.torque_meas))
    return tuple(np.concatenate([o[k] for o in out]) for k in range(3))


def reversal_run(ff: FrictionFeedforward | None, *, duration: float, amplitude: float, hz: float):
    cfg = from_mapping({
        "backend": {"name": "sim", "sample_period": DT, "torque_meas_noise": 5e-4},
        "plant": {"friction": {"preset": "thomson"}},
        "excitation": {"kind": "none"},
        "control": {"mode": "fixed"},
        "reference": {"kind": "sine", "amplitude": amplitude, "frequency_hz": hz, "fade_periods": 1.0},
        "loop": {"duration": duration, "realtime": False},
        "telemetry": {"sink": "off"}, "recording": {"enabled": False},
        # the stuck-encoder check ignores torques below the sim's breakaway torque ([safety] stuck_torque
        # defaults to Fs1 + Fs2 when the plant has friction): a sticking axis at a reversal does not trip it
    })
    ts, errs = [], []

    def hook(loop) -> None:
        ctl = loop.control
        if ff is not None and ctl.law.friction is None:
            ctl.law.friction = ff
        ts.append(ctl.t)
        errs.append(ctl.error)

    out = run_offline(cfg, tick_hook=hook)
    return np.array(ts), np.array(errs), out


def reversal_peaks(t: np.ndarray, e: np.ndarray, hz: float, start: float) -> np.ndarray:
    """max |error| within +-1/8 period of each reversal of sin(2 pi hz t) after ``start``."""
    peaks = []
    k = 0
    while True:
        tr = (2 * k + 1) / (4 * hz)              # cos(2 pi hz t) = 0
        k += 1
        if tr < start:
            continue
        if tr + 1 / (8 * hz) > t[-1]:
            break
        m = (t > tr - 1 / (8 * hz)) & (t < tr + 1 / (8 * hz))
        peaks.append(float(np.max(np.abs(e[m]))))
    return np.array(peaks)


def main() -> None:
    # no probing excitation here (the comparison is about the reversals): the frequency fit the loop still
    # runs in its worker has nothing to fit and says so every time; silence it
    logging.getLogger("rt_ident.estimators").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--amplitude", type=float, default=0.005, help="m")
    ap.add_argument("--hz", type=float, default=1.0)
    ap.add_argument("--png", default=None)
    a = ap.parse_args()
    th1, th2, tq = bench_record()
    ident = fit_friction(th1, tq, DT, model="two-inertia-friction", theta2=th2)
    ff = FrictionFeedforward.from_parameters(ident.parameters)
    fr = thomson_friction()
    print(f"identified Fc1 + Fc2 = {ff.Fc:.5g} N m (true {fr.Fc1 + fr.Fc2:.5g}), "
          f"Fv1 + Fv2 = {ff.Fv:.4g} N m s/rad (true {fr.Fv1 + fr.Fv2:.4g})")
    start = 1.0 / a.hz + 0.25 / a.hz          # after the one-period fade-in
    res = {}
    for name, f in (("inertia feedforward only", None), ("+ friction feedforward", ff)):
        t, e, out = reversal_run(f, duration=a.duration, amplitude=a.amplitude, hz=a.hz)
        pk = reversal_peaks(t, e, a.hz, start)
        after = t >= start
        rms = float(np.sqrt(np.mean(e[after] ** 2)))
        res[name] = (t, e)
        print(f"{name:26s} peak reversal error: mean {1e6 * pk.mean():7.2f} um, max {1e6 * pk.max():7.2f} um "
              f"over {pk.size} reversals; RMS {1e6 * rms:6.2f} um; stop: {out['stop']}")
    if a.png:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(9, 4))
        ax = fig.subplots()
        for name, (t, e) in res.items():
            ax.plot(t, 1e6 * e, lw=0.8, label=name)
        for k in range(int(a.duration * 2 * a.hz) + 1):
            tr = (2 * k + 1) / (4 * a.hz)
            if tr < a.duration:
                ax.axvline(tr, color="0.8", lw=0.5, zorder=0)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("table error [um]")
        ax.set_title(f"THOMSON axis with friction, sine {1e3 * a.amplitude:g} mm at {a.hz:g} Hz "
                     "(grey: reversals)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(a.png, dpi=120)
        print(f"wrote {a.png}")


if __name__ == "__main__":
    main()

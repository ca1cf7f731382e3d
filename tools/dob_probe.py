"""Probe: what a disturbance observer added to the position law would do to `rt-ident bench control`'s cases.

Not a product feature. On virtual time (`run_offline`, the Python tick path), every tick adds to the law's
torque the negated low-passed disturbance of the momentum balance, d = J a - tau: J the inertia the law's
feedforward uses in that tick, a the I1/I2-weighted mean of the Kalman filter's two accelerations over the
tick (differences of its velocities), tau the mean torque command over the tick. When the law's inertia
changes (a switched design, or the feedforward following the per-sample estimate), the estimate is moved
by the same change times the last acceleration, so that observer and feedforward do not compensate the
same torque twice. The observer runs in each of the fixed, adaptive and oracle loops, as a law of the
product would; the bench's case names select the cases (`case N` of the randomized set, or a named one).

    python tools/dob_probe.py --hz 0,120,250 --cases all
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

import rt_ident.bench.control as bench
from rt_ident.compose import offline
from rt_ident.config import load
from rt_ident.control.law import C_INERTIA
from rt_ident.loop import loop as loop_mod

_plain_control = loop_mod.IdentificationLoop._control


def observed_control(hz: float):
    """The loop's ``_control`` with the observer's torque subtracted from the law's (``hz`` its bandwidth)."""

    def control(self, ctl, block, states) -> None:
        if self._catching_up:
            return _plain_control(self, ctl, block, states)
        w1, w2 = (float(v) for v in states.omega[-1])
        tick = 1.0 / self.tick_hz
        m = ctl.law.controller.model
        J = float(ctl.law.consts[C_INERTIA])
        ob = self.__dict__.setdefault("_probe_dob", {"w": None, "d": 0.0, "J": J, "a": 0.0})
        if ob["w"] is not None:
            a = (m.I1 * (w1 - ob["w"][0]) + m.I2 * (w2 - ob["w"][1])) / (tick * (m.I1 + m.I2))
            ob["d"] += (J - ob["J"]) * ob["a"]               # the law's inertia moved: so does the estimate
            raw = J * a - float(np.mean(block.torque_cmd))
            ob["d"] += (1.0 - math.exp(-2.0 * math.pi * hz * tick)) * (raw - ob["d"])
            ob["a"] = a
        ob["w"], ob["J"] = (w1, w2), J
        law_tick = ctl.tick
        lim = ctl.law.limit
        ctl.tick = lambda *args: max(-lim, min(lim, law_tick(*args) - ob["d"]))
        try:
            return _plain_control(self, ctl, block, states)
        finally:
            del ctl.tick

    return control


def python_path_run_offline(cfg, **kw):
    options = {**(kw.pop("loop_options", None) or {}), "compiled_tick": False}    # the observer patches this path
    return offline.run_offline(cfg, loop_options=options, **kw)


def probe(hz: float, names: list[str]) -> list[dict[str, Any]]:
    base = load("sim-load-change.toml")
    try:
        cases = [bench.bench_case(n) for n in names]
    except ValueError as exc:
        raise SystemExit(f"dob_probe: {exc}") from None
    loop_mod.IdentificationLoop._control = observed_control(hz) if hz > 0 else _plain_control
    bench.run_offline = python_path_run_offline
    rows = []
    try:
        for case in cases:
            rows.append(_row(hz, base, *case))
    finally:
        loop_mod.IdentificationLoop._control = _plain_control
        bench.run_offline = offline.run_offline
    return rows


def _row(hz: float, base, label: str, factors: dict[str, float], at: float, seed: int, duration: float) -> dict:
    row = bench.run_case(base, label, factors, change_at=at, duration=duration, seed=seed, cpu_latency=False)
    return {"hz": hz, "case": label, **{m: row[m] for m in ("fixed", "adaptive", "oracle")},
            "adaptive_over_oracle": row["adaptive_over_oracle"],
            "adaptive_over_oracle_max": row["adaptive_over_oracle_max"],
            "adaptive_over_fixed": row["adaptive_over_fixed"],
            "change_to_redesign_s": row["change_to_redesign_s"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hz", default="0,250", help="observer bandwidths [Hz], comma-separated; 0: no observer")
    ap.add_argument("--cases", default="case 2,I2 x 3,all three",
                    help="bench cases, comma-separated, or 'all' (the four named and the 20 randomized)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    names = args.cases.split(",")
    if args.cases == "all":
        names = [n for n, _ in bench.SCENARIOS] + [f"case {i}" for i in range(1, 21)]
    rows = [r for hz in (float(h) for h in args.hz.split(",")) for r in probe(hz, names)]
    if args.json:
        print(json.dumps(rows, indent=1, default=str))
        return
    um = 1e6
    print(f"{'Hz':>5} {'case':42} {'RMS f / a / o [um]':>22} {'max f / a / o [um]':>22} {'a/o':>6} {'a/o max':>7}"
          f" {'a/f':>6}  stop")
    for r in rows:
        f, a, o = r["fixed"], r["adaptive"], r["oracle"]
        stops = ",".join(m for m in ("fixed", "adaptive", "oracle") if r[m]["stop"]) or "-"
        print(f"{r['hz']:5g} {r['case'][:42]:42} "
              f"{um * f['rms_error_m']:6.2f} {um * a['rms_error_m']:6.2f} {um * o['rms_error_m']:6.2f}    "
              f"{um * f['max_error_m']:6.2f} {um * a['max_error_m']:6.2f} {um * o['max_error_m']:6.2f}    "
              f"{r['adaptive_over_oracle']:6.3f} {r['adaptive_over_oracle_max']:7.2f} "
              f"{r['adaptive_over_fixed']:6.3f}  {stops}")


if __name__ == "__main__":
    main()

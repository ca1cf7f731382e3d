#!/usr/bin/env python
"""The circular test after a load change on Y: the host's controller designed once (fixed) against the one
redesigned from the identified axis (adaptive).

A workpiece is clamped on the table at ``--change-at`` s (Y's table inertia I2 x ``--factor``: Y carries
it; X carries Y and the workpiece too, but less, and is left unchanged here); the circle of
configs/xy-circle.toml starts at ``--circle-at`` s, when the adaptive loop has had time to identify the
new Y and redesign. Both runs use the same seeds; only ``[control] mode`` differs. Prints G (per
direction) and H of each run and the table error per axis; ``--json`` for the numbers.

    python tools/xy_contour_compare.py [--factor 3 --change-at 1 --circle-at 4]
"""

from __future__ import annotations

import argparse
import json

from rt_ident.compose.run import run as run_axes
from rt_ident.config import load


def _run(mode: str, args) -> dict:
    circle = {"kind": "circle", "radius": 0.005, "frequency_hz": 1.0, "turns": 1, "start": args.circle_at}
    cfg = load("configs/xy-circle.toml", **{
        "loop.realtime": not args.no_realtime, "telemetry.sink": "off", "recording.enabled": False,
        "loop.duration": args.circle_at + 6.6, "control.mode": mode,
        "estimator.forgetting": args.forgetting,
        "axes.x": {"reference": {**circle, "axis": "x"}},
        "axes.y": {"reference": {**circle, "axis": "y"}, "axis": {"I1": 2.7e-5, "I2": 2.5e-5, "B": 2.1e-3,
                                                                  "K": 1.1e2, "lead": 7.96e-4},
                   "backend": {"seed": 1}, "plant": {"change": [{"at": args.change_at, "I2": args.factor}]}}})
    s = run_axes(cfg)
    c = s.get("contour") or {}
    return {"mode": mode, "stop": s["stop"]["cause"],
            "G_ccw_um": (c.get("ccw") or {}).get("G_um"), "G_cw_um": (c.get("cw") or {}).get("G_um"),
            "H_um": c.get("H_um"),
            "rms_error_um": {n: 1e6 * (ax["control"].get("rms_error_m") or float("nan"))
                             for n, ax in s["axes"].items()},
            "redesigns_y": (s["axes"]["y"]["control"].get("redesigns") or {}).get("accepted")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--factor", type=float, default=3.0)
    ap.add_argument("--change-at", type=float, default=1.0)
    ap.add_argument("--circle-at", type=float, default=4.0)
    ap.add_argument("--no-realtime", action="store_true")
    ap.add_argument("--forgetting", type=float, default=0.9,
                    help="frequency fit forgetting per excitation period (as configs/sim-load-change.toml: the "
                         "estimate follows the change; 1.0 keeps the data from before it forever)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not 0 <= args.change_at < args.circle_at:
        ap.error("--change-at must come before --circle-at")
    rows = [_run(mode, args) for mode in ("fixed", "adaptive")]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"Y's I2 x {args.factor:g} at {args.change_at:g} s; circle R 5 mm at 1 turn/s from {args.circle_at:g} s")
    for r in rows:
        g = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"  {r['mode']:8s}: G CCW {g(r['G_ccw_um'])} um, G CW {g(r['G_cw_um'])} um, H {g(r['H_um'])} um; "
              f"table error rms X {r['rms_error_um']['x']:.2f} um, Y {r['rms_error_um']['y']:.2f} um; "
              f"Y redesigns {r['redesigns_y']}; stop {r['stop']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

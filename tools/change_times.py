"""Measurement: one plant change of `rt-ident bench control` at several change times, fixed against the oracle
(the design for the true new plant, switched in at the change) and the adaptive loop.

For a change the loop hardly feels (K x 0.6) the bench's adaptive / fixed ratio sits within a part in a thousand
of 1; this shows where perfect knowledge lands on the same runs. Virtual time, the bench's seed; RMS of the
table's error from the change to the end.

    python tools/change_times.py --factors K=0.6 --at 3,3.5,4,4.5,5
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from rt_ident.bench.control import run_case
from rt_ident.config import load

MODES = ("fixed", "oracle", "adaptive")


def parse_factors(text: str) -> dict[str, float]:
    """``"K=0.6,B=1.5"`` -> ``{"K": 0.6, "B": 1.5}`` (I1, I2, B, K only)."""
    out: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        if not sep or key not in ("I1", "I2", "B", "K"):
            raise argparse.ArgumentTypeError(f"'{part}' is not NAME=FACTOR with NAME one of I1, I2, B, K")
        try:
            out[key] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{value}' in '{part}' is not a number") from None
        if not out[key] > 0:
            raise argparse.ArgumentTypeError(f"{key} must be scaled by a positive factor, got {value}")
    if not out:
        raise argparse.ArgumentTypeError("give at least one, e.g. K=0.6")
    return out


def parse_times(text: str) -> list[float]:
    try:
        times = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of seconds") from None
    if not times or min(times) <= 0:
        raise argparse.ArgumentTypeError(f"change times must be positive seconds, got '{text}'")
    return times


def rows(factors: dict[str, float], times: list[float], after_s: float) -> list[dict[str, Any]]:
    """Each change time's RMS errors [m] in MODES and the ratios to the fixed design."""
    base = load("sim-load-change.toml")
    name = ", ".join(f"{k} x {v:g}" for k, v in factors.items())
    out = []
    for at in times:
        row = run_case(base, name, factors, change_at=at, duration=at + after_s, modes=MODES)
        rms = {m: row[m]["rms_error_m"] for m in MODES}
        out.append({"change_at_s": at, "rms_error_m": rms,
                    "oracle_over_fixed": rms["oracle"] / rms["fixed"],
                    "adaptive_over_fixed": rms["adaptive"] / rms["fixed"]})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--factors", type=parse_factors, default={"K": 0.6}, help="the change, e.g. K=0.6 or I2=3,B=1.5")
    ap.add_argument("--at", type=parse_times, default=[3.0, 3.5, 4.0, 4.5, 5.0],
                    help="change times [s], comma-separated")
    ap.add_argument("--after", type=float, default=4.0, help="seconds each run goes on after its change")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args(argv)
    if not args.after > 0:
        ap.error("--after must be positive seconds")
    out = rows(args.factors, args.at, args.after)
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print("change at | fixed | oracle | adaptive [um RMS] | oracle / fixed | adaptive / fixed")
    for r in out:
        e = r["rms_error_m"]
        um = " | ".join(f"{e[m] * 1e6:.4f}" for m in MODES)
        print(f"{r['change_at_s']:g} s | {um} | {r['oracle_over_fixed']:.5f} | {r['adaptive_over_fixed']:.5f}")


if __name__ == "__main__":
    main()

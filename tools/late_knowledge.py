"""Probe: how early, how exactly and with what loop the new plant must be known to bound a bench case's error.

Not a product feature. On virtual time (`run_offline`), one of `rt-ident bench control`'s cases runs with a
design switched in by hand (no design time: each row bounds what a loop that acts at that moment reaches).
The reference is the oracle, the true plant's design from the change on; `--switch` is what is switched in:

- `truth`: the fixed loop, `--after-ms` after the change, gets the design for the new plant with both
  inertias times `--known` (below 1: an estimate still short of the change) at `--hz`. A design at another
  bandwidth, or on a short estimate, gives way to the configured design for the true plant `--hand-back-ms`
  after the change (where the adaptive loop's own redesign lands).
- `estimate`: the adaptive loop, `--after-ms` after its change detector fires, gets a design at `--hz` for
  its own per-sample estimate of that tick (the row says how far that estimate was from the new plant);
  its own redesign takes over when it lands. `--hz 0`: nothing switched (the adaptive loop as it is).
- `model`: as `estimate`, with a design at `--hz` for the model of the design in force (a stiffer
  stand-by design, which needs no estimate).

    python tools/late_knowledge.py --after-ms 0,1,2,3,4,8
    python tools/late_knowledge.py --after-ms 2,3.7 --hz 20,30,40,50,60 --known 1,0.9,0.79
    python tools/late_knowledge.py --switch estimate --after-ms 0,2 --hz 0,20,30,40,50,60,70
    python tools/late_knowledge.py --switch model --case all --after-ms 0 --hz 0,80,100
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

import rt_ident.bench.control as bench
from rt_ident.axis.params import AxisParams
from rt_ident.compose.offline import run_offline
from rt_ident.config import load
from rt_ident.control.job import model_controller

KEYS = ("I1", "I2", "B", "K")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def _errors(cfg: Any, at: float, hook: Any) -> dict[str, Any]:
    out = run_offline(cfg, tick_hook=hook, error_after_s=at)
    c, stop = out["control"], out.get("stop")
    return {"max_um": 1e6 * c["max_error_after_change_m"], "rms_um": 1e6 * c["rms_error_after_change_m"],
            "stop": (stop.get("message") or stop.get("cause")) if isinstance(stop, dict) else stop}


def _scheduled(steps: list[tuple[float, Any]], at: float) -> Any:
    """A tick hook adopting each (seconds after the change, controller) in turn."""
    pending = sorted(steps, key=lambda s: s[0])

    def hook(loop: Any) -> None:
        ctl = loop.control
        while ctl is not None and pending and ctl.t >= at + pending[0][0]:
            ctl.adopt(pending.pop(0)[1])

    return hook


def _after_detection(after_s: float, at: float, design: Any, seen: dict[str, Any]) -> Any:
    """A tick hook adopting ``design(ctl)`` ``after_s`` after the adaptive loop's change detector fires."""

    def hook(loop: Any) -> None:
        ctl = loop.control
        if ctl is None:
            return
        if ctl.stats.changes_detected > seen.get("changes", 0) and ctl.t >= at:
            seen.update(changes=ctl.stats.changes_detected, detected=ctl.t, done=False)
        if seen.get("detected") is None or seen["done"] or ctl.t < seen["detected"] + after_s:
            return
        seen.update(done=True, at_ms=1e3 * (ctl.t - at))
        ctl.adopt(design(ctl))

    return hook


def run_one(case: str, switch: str, after_ms: list[float], hz: list[float], known: list[float],
            hand_back_ms: float) -> dict[str, Any]:
    base = load("sim-load-change.toml")
    label, factors, at, seed, duration = bench.bench_case(case)
    fixed = bench._with_mode(bench.scenario_config(base, factors, change_at=at, duration=duration, seed=seed), "fixed")
    adaptive = bench._with_mode(fixed, "adaptive")
    settings = fixed.control.settings()
    tick = 1.0 / fixed.loop.tick_hz
    true = bench.changed_plant(fixed.axis_params(), factors)

    def design(plant: AxisParams, bw: float) -> Any:
        return model_controller(plant, tick, dataclasses.replace(settings, bandwidth_hz=bw), kind="oracle")

    oracle = _errors(fixed, at, _scheduled([(0.0, design(true, settings.bandwidth_hz))], at))
    rows = []
    for a in after_ms:
        for bw in hz:
            row: dict[str, Any] = {"after_ms": a, "hz": bw}
            if switch == "truth":
                for k in known:
                    steps = [(a * 1e-3, design(dataclasses.replace(true, I1=true.I1 * k, I2=true.I2 * k), bw))]
                    if bw != settings.bandwidth_hz or k != 1.0:
                        steps.append((hand_back_ms * 1e-3, design(true, settings.bandwidth_hz)))
                    rows.append({**row, "known": k, **_errors(fixed, at, _scheduled(steps, at))})
                continue
            seen: dict[str, Any] = {}

            def chosen(ctl: Any, bw: float = bw, seen: dict[str, Any] = seen) -> Any:
                if switch == "model":
                    return design(ctl.controller.model, bw)
                v = [float(x) for x in ctl.per_sample.values_array()[:4]]
                seen["known"] = {k: x / getattr(true, k) for k, x in zip(KEYS, v)}
                return design(AxisParams(**dict(zip(KEYS, v)), lead=true.lead), bw)

            hook = _after_detection(a * 1e-3, at, chosen, seen) if bw > 0 else None
            rows.append({**row, **_errors(adaptive, at, hook), "switched_ms": seen.get("at_ms"),
                         "known": seen.get("known")})
    for r in rows:
        r["over_oracle_max"] = r["max_um"] / oracle["max_um"]
        r["over_oracle_rms"] = r["rms_um"] / oracle["rms_um"]
    return {"case": label, "change_at_s": at, "switch": switch, "oracle": oracle, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="case 2",
                    help="'case 1'..'case 20' or a named scenario of the bench, comma-separated, or 'all'")
    ap.add_argument("--switch", choices=("truth", "estimate", "model"), default="truth",
                    help="what is switched in (see the module's docstring)")
    ap.add_argument("--after-ms", default="0,1,2,3,4,8",
                    help="when [ms after the change; estimate, model: after the change detector fired]")
    ap.add_argument("--hz", default="20", help="bandwidths of the design switched in [Hz], comma-separated")
    ap.add_argument("--known", default="1", help="truth: the inertias known as this fraction of the new plant's")
    ap.add_argument("--hand-back-ms", type=float, default=95.0,
                    help="truth: when a design at another bandwidth or on a short estimate gives way to the "
                         "true plant's")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cases = args.case.split(",")
    if args.case == "all":
        cases = [n for n, _ in bench.SCENARIOS] + [f"case {i}" for i in range(1, 21)]
    try:
        args_ = (_floats(args.after_ms), _floats(args.hz), _floats(args.known), args.hand_back_ms)
        for case in cases:
            bench.bench_case(case)
    except ValueError as exc:
        raise SystemExit(f"late_knowledge: {exc}") from None
    results = []
    for case in cases:
        result = run_one(case, args.switch, *args_)
        results.append(result)
        if args.json:
            continue
        o = result["oracle"]
        print(f"{result['case']}: oracle max {o['max_um']:.2f} um, RMS {o['rms_um']:.3f} um")
        print(f"{'after ms':>8} {'Hz':>5} {'known':>6} {'max um':>7} {'RMS um':>7} {'max/oracle':>10} "
              f"{'RMS/oracle':>10}  stop")
        for r in result["rows"]:
            k = r["known"]
            print(f"{r['after_ms']:8g} {r['hz']:5g} {f'{k:6g}' if isinstance(k, float) else '      '} "
                  f"{r['max_um']:7.2f} {r['rms_um']:7.3f} {r['over_oracle_max']:10.2f} {r['over_oracle_rms']:10.3f}"
                  f"  {r['stop'] or '-'}")
            if r.get("switched_ms") is not None:
                on = (", on " + ", ".join(f"{n} x {v:.3f}" for n, v in k.items()) + " of the new plant"
                      if isinstance(k, dict) else "")
                print(f"{'':24} switched {r['switched_ms']:.1f} ms after the change{on}")
    if args.json:
        print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()

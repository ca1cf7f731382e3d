"""``rt-ident bench estimator``: the per-sample estimator on bench-like data, in closed loop.

Every trial runs the real loop on virtual time (:func:`rt_ident.compose.offline.run_offline`,
``configs/sim-load-change.toml``: 2^17-count motor encoder, 0.1 um scale, 0.5 mN m rms torque
noise, the host's adaptive position loop closed, jerk-limited moves, 0.1 N m probing) and reads
the per-sample estimate (:mod:`rt_ident.estimators.svf`) after every tick.

* **bias**: no plant change, 10 s; the mean of the estimate over the last 5 s against the truth,
  per parameter (and the estimate's standard deviation over that window);
* **tracking**: each of I1, I2, B, K steps by +20 % at 4 s; the settling time is the time after the
  step from which the estimate of *the stepped parameter* stays within 2 % of its new value (to the
  end of the 2 s after the step); the errors of all four at 0.2 s after the step are reported too.

Targets: bias <= 1 % on I1, I2, B, K in 10 s; settling <= 0.2 s after any +20 % step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from rt_ident.compose.offline import run_offline
from rt_ident.config import RunConfig, from_mapping, load
from rt_ident.loop.loop import IdentificationLoop

KEYS = ("I1", "I2", "B", "K")


def _trial(base: RunConfig, change: dict[str, float] | None, duration: float) -> tuple[np.ndarray, np.ndarray, dict]:
    data = base.model_dump(exclude={"source"})
    data["plant"] = {"change": [change] if change else []}
    data["loop"] = {**data["loop"], "duration": duration, "realtime": False}
    data["telemetry"] = {**data["telemetry"], "sink": "off"}
    data["recording"] = {**data["recording"], "enabled": False}
    cfg = from_mapping(data, source=base.source)
    ts: list[float] = []
    est: list[list[float]] = []

    def hook(loop: IdentificationLoop) -> None:
        ctl = loop.control
        if ctl is None or ctl.per_sample is None:
            return
        v = ctl.per_sample.values()
        ts.append(ctl.t)
        est.append([v[k] for k in KEYS])

    out = run_offline(cfg, tick_hook=hook)
    if not est:
        raise RuntimeError("the configuration runs no per-sample estimator ([estimator] per_sample)")
    return np.asarray(ts), np.asarray(est), out


def bias_trial(base: RunConfig, duration: float = 10.0) -> dict[str, Any]:
    t, est, out = _trial(base, None, duration)
    truth = np.array([out["truth"][k] for k in KEYS])
    late = est[t >= duration / 2]
    rel = late / truth - 1.0
    return {"seconds": duration, "window_s": duration / 2, "stop": out["stop"],
            "bias": {k: float(rel[:, i].mean()) for i, k in enumerate(KEYS)},
            "std": {k: float(rel[:, i].std()) for i, k in enumerate(KEYS)}}


def step_trial(base: RunConfig, key: str, *, factor: float = 1.2, at: float = 4.0, after: float = 2.0,
               tol: float = 0.02) -> dict[str, Any]:
    t, est, out = _trial(base, {"at": at, key: factor}, at + after)
    truth = np.array([out["truth"][k] for k in KEYS])          # the plant after the change
    post = t >= at
    i = KEYS.index(key)
    rel = np.abs(est[post, i] / truth[i] - 1.0)
    bad = np.nonzero(rel > tol)[0]
    if bad.size and bad[-1] == rel.size - 1:
        settle = math.inf
    else:
        settle = float(t[post][bad[-1] + 1] - at) if bad.size else 0.0
    at_02 = est[np.searchsorted(t, at + 0.2)] / truth - 1.0
    return {"param": key, "factor": factor, "settle_s": settle, "stop": out["stop"],
            "error_at_0_2_s": {k: float(at_02[j]) for j, k in enumerate(KEYS)}}


def estimator_bench(*, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    base = load("sim-load-change.toml")
    if progress:
        progress("bias: 10 s, no change")
    bias = bias_trial(base)
    steps = []
    for k in KEYS:
        if progress:
            progress(f"tracking: {k} x 1.2 at 4 s")
        steps.append(step_trial(base, k))
    s = base.estimator
    return {"estimator": {"method": "svf", "filter_hz": s.svf_hz, "memory_s": s.svf_memory_s,
                          "config": str(base.source), "bias": bias, "steps": steps}}


def targets(result: dict[str, Any]) -> list[tuple[str, bool, str]]:
    r = result["estimator"]
    worst = max(KEYS, key=lambda k: abs(r["bias"]["bias"][k]))
    b = abs(r["bias"]["bias"][worst])
    out = [(f"bias <= 1 % on I1, I2, B, K in 10 s (worst: {worst})", b <= 0.01, f"{100 * b:.2f} %")]
    for s in r["steps"]:
        out.append((f"{s['param']} +20 %: within 2 % in <= 0.2 s", s["settle_s"] <= 0.2,
                    f"{1e3 * s['settle_s']:.0f} ms" if math.isfinite(s["settle_s"]) else "never"))
    return out

"""``rt-ident bench control``: fixed vs adaptive vs oracle control after a load change, and the
nominal design on 100 random plants.

Every scenario runs the real loop (:func:`rt_ident.compose.offline.run_offline`: the same loop,
estimators and supervisor as ``rt-ident run``, on virtual time) three times on the same seed:

* **fixed**: the model controller designed once for the configured (nominal) axis;
* **adaptive**: the supervisor redesigning from the identified model (``control.mode = "adaptive"``);
* **oracle**: the fixed controller, swapped (bumplessly) at each plant change for the model
  controller designed from the *true* new plant - the best a redesign could do.

The tracking error of the table is measured from 0.5 s after the last change to the end.

Random plants: each of I1, I2, B, K of Table 1 scaled by a factor drawn log-uniformly in
0.5 ... 2 (seeded); the nominal model controller on each (exact sampled closed loop,
:func:`rt_ident.control.design.sampled_model`): stable or not (spectral radius), and the
overshoot of the table after a small reference step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.axis.params import AxisParams
from rt_ident.compose.offline import run_offline
from rt_ident.config import RunConfig, from_mapping, load
from rt_ident.control.adaptation import model_controller
from rt_ident.control.design import delay_of, design_lqr, sampled_model
from rt_ident.loop.loop import IdentificationLoop

#: (name, factors applied at the change)
SCENARIOS: tuple[tuple[str, dict[str, float]], ...] = (
    ("I2 x 3", {"I2": 3.0}),
    ("B x 1.5", {"B": 1.5}),
    ("K x 0.6", {"K": 0.6}),
    ("all three", {"I2": 3.0, "B": 1.5, "K": 0.6}),
)


def scenario_config(base: RunConfig, factors: dict[str, float], *, change_at: float, duration: float) -> RunConfig:
    data = base.model_dump(exclude={"source"})
    data["plant"] = {"change": [{"at": change_at, **factors}]}
    data["loop"] = {**data["loop"], "duration": duration, "realtime": False}
    data["telemetry"] = {**data["telemetry"], "sink": "off"}
    data["recording"] = {**data["recording"], "enabled": False}
    return from_mapping(data, source=base.source)


def _with_mode(cfg: RunConfig, mode: str) -> RunConfig:
    data = cfg.model_dump(exclude={"source"})
    data["control"] = {**data["control"], "mode": mode}
    return from_mapping(data, source=cfg.source)


def _oracle_hook(cfg: RunConfig) -> Callable[[Any], None]:
    """Swap in the model controller of the true plant at each change (bumpless)."""
    changes = sorted(cfg.plant.change, key=lambda c: c["at"])
    nominal = cfg.axis_params()
    settings = cfg.control.settings()
    tick = 1.0 / cfg.loop.tick_hz
    done = [0]

    def hook(loop: IdentificationLoop) -> None:
        i = done[0]
        if i >= len(changes):
            return
        ctl = loop.control
        if ctl is None or ctl.t < changes[i]["at"]:
            return
        f = changes[i]
        p = AxisParams(**{k: getattr(nominal, k) * float(f.get(k, 1.0)) for k in ("I1", "I2", "B", "K")},
                       lead=nominal.lead)
        ctl.adopt(model_controller(p, tick, settings, kind="oracle"))
        done[0] = i + 1

    return hook


def tracking_errors(out: dict[str, Any]) -> dict[str, Any]:
    c = out["control"]
    return {"rms_error_m": c.get("rms_error_after_change_m"), "max_error_m": c.get("max_error_after_change_m"),
            "stop": out.get("stop"), "redesigns": c.get("redesigns", {}), "fallbacks": c.get("fallbacks")}


def run_scenarios(base: RunConfig | None = None, *, change_at: float = 4.0, duration: float = 8.0,
                  progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    base = base or load("sim-load-change.toml")
    rows = []
    for name, factors in SCENARIOS:
        cfg = scenario_config(base, factors, change_at=change_at, duration=duration)
        row: dict[str, Any] = {"name": name, "factors": factors}
        for mode in ("fixed", "adaptive", "oracle"):
            if progress:
                progress(f"{name}: {mode}")
            run_cfg = _with_mode(cfg, "fixed" if mode == "oracle" else mode)
            out = run_offline(run_cfg, tick_hook=_oracle_hook(run_cfg) if mode == "oracle" else None)
            row[mode] = tracking_errors(out)
        a, o, f = (row[m]["rms_error_m"] for m in ("adaptive", "oracle", "fixed"))
        row["adaptive_over_oracle"] = a / o if a and o else None
        row["adaptive_over_fixed"] = a / f if a and f else None
        rows.append(row)
    return rows


def _step_overshoot(G: np.ndarray, p: AxisParams, tick: float, seconds: float = 1.0) -> float:
    """Overshoot (fraction) of the table after a reference step, exact sampled closed loop."""
    Az, Bz = sampled_model(p, tick, delay_of(G))
    Acl = Az - Bz @ G.reshape(1, -1)
    z = np.zeros(G.size)
    z[2] = -1.0                                  # error coordinates: start 1 rad below the new reference
    z[0] = -1.0
    worst = 0.0
    for _ in range(int(seconds / tick)):
        z = Acl @ z
        worst = max(worst, z[2])                 # error above 0: past the reference
        if not np.all(np.isfinite(z)) or abs(z[2]) > 1e6:
            return math.inf
    return worst


def random_plants(nominal: AxisParams, *, n: int = 100, seed: int = 0, tick: float = 1e-3,
                  bandwidth_hz: float = 20.0, delay: int = 1) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    G = design_lqr(nominal, tick, bandwidth_hz, delay=delay)
    unstable, worst, worst_plant = 0, 0.0, None
    for _ in range(n):
        f = np.exp(rng.uniform(math.log(0.5), math.log(2.0), 4))
        p = AxisParams(I1=nominal.I1 * f[0], I2=nominal.I2 * f[1], B=nominal.B * f[2], K=nominal.K * f[3],
                       lead=nominal.lead)
        Az, Bz = sampled_model(p, tick, delay)
        radius = float(np.abs(np.linalg.eigvals(Az - Bz @ G.reshape(1, -1))).max())
        if radius >= 1.0:
            unstable += 1
            continue
        ov = _step_overshoot(G, p, tick)
        if ov > worst:
            worst, worst_plant = ov, [round(float(x), 3) for x in f]
    return {"n": n, "unstable": unstable, "worst_overshoot": worst, "worst_factors_I1_I2_B_K": worst_plant,
            "seed": seed}


def control_bench(*, quick: bool = False, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    base = load("sim-load-change.toml")
    duration = 6.0 if quick else 8.0
    rows = run_scenarios(base, change_at=3.0 if quick else 4.0, duration=duration, progress=progress)
    plants = random_plants(base.axis_params(), n=20 if quick else 100,
                           bandwidth_hz=base.control.bandwidth_hz, tick=1.0 / base.loop.tick_hz,
                           delay=base.control.delay_ticks)
    return {"control": {"scenarios": rows, "random_plants": plants}}


def targets(result: dict[str, Any]) -> list[tuple[str, bool, str]]:
    """(target, met, figure) for the printed summary."""
    rows = result["control"]["scenarios"]
    out = []
    for r in rows:
        ratio = r.get("adaptive_over_oracle")
        out.append((f"{r['name']}: adaptive <= 1.2 x oracle RMS", ratio is not None and ratio <= 1.2,
                    "n/a" if ratio is None else f"{ratio:.2f}"))
    i2 = next((r for r in rows if r["name"] == "I2 x 3"), None)
    if i2 is not None:
        ratio = i2.get("adaptive_over_fixed")
        out.append(("I2 x 3: adaptive <= 0.7 x fixed RMS", ratio is not None and ratio <= 0.7,
                    "n/a" if ratio is None else f"{ratio:.2f}"))
    rp = result["control"]["random_plants"]
    out.append((f"random plants: 0 unstable of {rp['n']}", rp["unstable"] == 0, str(rp["unstable"])))
    return out


def control_comparison(result: dict[str, Any], path: str | Path) -> Path:
    """Bar chart: RMS and max table error after the change, per scenario, fixed / adaptive / oracle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["control"]["scenarios"]
    modes = ("fixed", "adaptive", "oracle")
    colors = {"fixed": "#7f7f7f", "adaptive": "#1f77b4", "oracle": "#2ca02c"}
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, key, title in ((axes[0], "rms_error_m", "RMS after the change"),
                           (axes[1], "max_error_m", "max after the change")):
        for i, m in enumerate(modes):
            vals = [1e6 * (r[m][key] or np.nan) for r in rows]
            ax.bar(x + (i - 1) * 0.27, vals, 0.27, label=m, color=colors[m])
        ax.set_xticks(x, [r["name"] for r in rows])
        ax.set_ylabel("table error [um]")
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend()
    fig.suptitle("Host position loop after a plant change: fixed (nominal design) vs adaptive vs oracle")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out

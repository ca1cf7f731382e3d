"""``rt-ident bench control``: fixed vs adaptive vs oracle control after a plant change (four named
scenarios and a randomized set), how fast the adaptive loop redesigns, how much its result moves
under other noise seeds, and the nominal design on 100 random plants.

Every scenario runs the real loop (:func:`rt_ident.compose.offline.run_offline`: the same loop,
estimators and supervisor as ``rt-ident run``, on virtual time) three times on the same seed:

* **fixed**: the model controller designed once for the configured (nominal) axis;
* **adaptive**: the supervisor redesigning from the identified model (``control.mode = "adaptive"``);
* **oracle**: the fixed controller, swapped (bumplessly) at each plant change for the model
  controller designed from the *true* new plant - the best a redesign could do.

The tracking error of the table is measured from the change to the end, so the time the adaptive
loop runs the old design on the new plant counts. **Change-to-redesign latency**: from the change
to the first model design switched in whose every parameter is within ``NEW_PLANT_TOLERANCE`` of
the new plant.

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
from rt_ident.control.design import delay_of, design_lqr, sampled_model
from rt_ident.control.job import model_controller
from rt_ident.loop.loop import IdentificationLoop

#: (name, factors applied at the change)
SCENARIOS: tuple[tuple[str, dict[str, float]], ...] = (
    ("I2 x 3", {"I2": 3.0}),
    ("B x 1.5", {"B": 1.5}),
    ("K x 0.6", {"K": 0.6}),
    ("all three", {"I2": 3.0, "B": 1.5, "K": 0.6}),
)


def scenario_config(base: RunConfig, factors: dict[str, float], *, change_at: float, duration: float,
                    seed: int = 0) -> RunConfig:
    data = base.model_dump(exclude={"source"})
    data["backend"] = {**data["backend"], "seed": seed}
    data["plant"] = {"change": [{"at": change_at, **factors}]}
    data["loop"] = {**data["loop"], "duration": duration, "realtime": False}
    data["telemetry"] = {**data["telemetry"], "sink": "off"}
    data["recording"] = {**data["recording"], "enabled": False}
    return from_mapping(data, source=base.source)


def _with_mode(cfg: RunConfig, mode: str) -> RunConfig:
    data = cfg.model_dump(exclude={"source"})
    data["control"] = {**data["control"], "mode": mode}
    return from_mapping(data, source=cfg.source)


def _oracle_hook(cfg: RunConfig, late_s: float = 0.0) -> Callable[[Any], None]:
    """Swap in the model controller of the true plant ``late_s`` after each change (bumpless)."""
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
        if ctl is None or ctl.t < changes[i]["at"] + late_s:
            return
        ctl.adopt(model_controller(changed_plant(nominal, changes[i]), tick, settings, kind="oracle"))
        done[0] = i + 1

    return hook


#: a design is "for the new plant" when every parameter of its model is within this of the true value
NEW_PLANT_TOLERANCE = 0.10
#: the adaptive loop's acts on a new estimate in ``control.applied``: a design switched in, or the one in
#: force kept after its check on the estimate
REDESIGN_KINDS = ("model", "kept")


def changed_plant(nominal: AxisParams, factors: dict[str, float]) -> AxisParams:
    return AxisParams(**{k: getattr(nominal, k) * float(factors.get(k, 1.0)) for k in ("I1", "I2", "B", "K")},
                      lead=nominal.lead)


def change_to_redesign(control: dict[str, Any], truth: AxisParams, change_at: float) -> float | None:
    """Seconds from the change to the first model design switched in, or kept after the family check on
    the new estimate, whose model (kept: that estimate) is within NEW_PLANT_TOLERANCE of the new plant
    ``truth`` on every parameter (None: none was)."""
    for a in control.get("applied") or ():
        if a["t"] < change_at or a["kind"] not in REDESIGN_KINDS:
            continue
        if all(abs(a["model"][k] / getattr(truth, k) - 1.0) <= NEW_PLANT_TOLERANCE for k in ("I1", "I2", "B", "K")):
            return float(a["t"]) - change_at
    return None


def first_response(control: dict[str, Any], change_at: float) -> float | None:
    """Seconds from the change to the adaptive loop's first act on it: its change detector firing, or a
    model design switched in or kept for a new estimate, whichever came first (None: none)."""
    ts = [e["t"] for e in control.get("events") or () if e["kind"] == "change detected" and e["t"] >= change_at]
    ts += [a["t"] for a in control.get("applied") or () if a["kind"] in REDESIGN_KINDS and a["t"] >= change_at]
    return min(ts) - change_at if ts else None


def tracking_errors(out: dict[str, Any]) -> dict[str, Any]:
    c = out["control"]
    return {"rms_error_m": c.get("rms_error_after_change_m"), "max_error_m": c.get("max_error_after_change_m"),
            "stop": out.get("stop"), "redesigns": c.get("redesigns", {}), "fallbacks": c.get("fallbacks")}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def run_case(base: RunConfig, name: str, factors: dict[str, float], *, change_at: float, duration: float,
             seed: int = 0, modes: tuple[str, ...] = ("fixed", "adaptive", "oracle"),
             progress: Callable[[str], None] | None = None, cpu_latency: bool = True,
             late_oracle: bool = False) -> dict[str, Any]:
    """One plant change run in each of ``modes``; errors from the change to the end. ``cpu_latency``:
    a redesign's answer comes after the CPU time the design took (as from a control process with a
    core of its own), else after a fixed 50 ms (reproducible to the digit). ``late_oracle``: also the
    oracle switched in as late as the adaptive loop first acted on the change."""
    cfg = scenario_config(base, factors, change_at=change_at, duration=duration, seed=seed)
    row: dict[str, Any] = {"name": name, "factors": factors, "change_at_s": change_at, "seed": seed}
    for mode in modes:
        if progress:
            progress(f"{name}: {mode}")
        run_cfg = _with_mode(cfg, "fixed" if mode == "oracle" else mode)
        out = run_offline(run_cfg, tick_hook=_oracle_hook(run_cfg) if mode == "oracle" else None,
                          error_after_s=change_at, design_cpu_latency=cpu_latency)
        row[mode] = tracking_errors(out)
        if mode == "adaptive":
            row["change_to_redesign_s"] = change_to_redesign(out["control"], changed_plant(base.axis_params(), factors),
                                                             change_at)
            row["first_response_s"] = first_response(out["control"], change_at)
    late = row.get("first_response_s")
    if late_oracle and "oracle" in row and late is not None:
        # what perfect knowledge gets when it arrives as late as the adaptive loop first acted: the
        # part of the adaptive's error no estimator that has to see the change first can avoid
        if progress:
            progress(f"{name}: oracle {1e3 * late:.1f} ms late")
        out = run_offline(_with_mode(cfg, "fixed"), tick_hook=_oracle_hook(cfg, late), error_after_s=change_at,
                          design_cpu_latency=cpu_latency)
        row["late_oracle"] = tracking_errors(out)
        row["late_oracle_over_oracle_max"] = _ratio(row["late_oracle"]["max_error_m"], row["oracle"]["max_error_m"])
    if "adaptive" in row:
        a = row["adaptive"]
        for other in ("oracle", "fixed"):
            if other in row:
                row[f"adaptive_over_{other}"] = _ratio(a["rms_error_m"], row[other]["rms_error_m"])
                row[f"adaptive_over_{other}_max"] = _ratio(a["max_error_m"], row[other]["max_error_m"])
    return row


def run_scenarios(base: RunConfig | None = None, *, change_at: float = 4.0, duration: float = 8.0,
                  progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    base = base or load("sim-load-change.toml")
    return [run_case(base, name, factors, change_at=change_at, duration=duration, progress=progress,
                     late_oracle=True) for name, factors in SCENARIOS]


def random_cases(n: int, *, seed: int = 1) -> list[tuple[str, dict[str, float], float, int]]:
    """``n`` randomized changes (name, factors, change time, sim seed): I2 x 1.5..4, I1 x 1.2..2 or
    both (log-uniform), at a time drawn in 2.5..4.5 s."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        which = ("I2", "I1", "both")[int(rng.integers(3))]
        f: dict[str, float] = {}
        if which in ("I2", "both"):
            f["I2"] = round(float(np.exp(rng.uniform(math.log(1.5), math.log(4.0)))), 3)
        if which in ("I1", "both"):
            f["I1"] = round(float(np.exp(rng.uniform(math.log(1.2), math.log(2.0)))), 3)
        at = round(float(rng.uniform(2.5, 4.5)), 3)
        name = f"case {i + 1}: " + ", ".join(f"{k} x {v:g}" for k, v in f.items()) + f" at {at:g} s"
        out.append((name, f, at, int(rng.integers(1, 2**31))))
    return out


#: the named scenarios' change time and run length, and how long a randomized case runs on after its
#: change [s]: the full bench's (False) and ``--quick``'s (True)
TIMING: dict[bool, tuple[float, float, float]] = {False: (4.0, 8.0, 3.5), True: (3.0, 6.0, 2.5)}


def bench_case(name: str) -> tuple[str, dict[str, float], float, int, float]:
    """A case as :func:`control_bench` runs it, by name (``case N`` of the randomized set, or a named
    scenario): (label, factors, change time, sim seed, duration)."""
    change_at, duration, after = TIMING[False]
    known = {c[0].split(":")[0]: (*c, c[2] + after) for c in random_cases(20)}
    known.update({n: (n, f, change_at, 0, duration) for n, f in SCENARIOS})
    if name not in known:
        raise ValueError(f"no case {name!r}; give 'case 1'..'case 20' or one of "
                         + ", ".join(n for n, _ in SCENARIOS))
    return known[name]


def perturbed_spread(base: RunConfig, *, repeats: int, change_at: float, duration: float,
                     progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Each named scenario's adaptive / oracle RMS under ``repeats`` other sensor-noise seeds (the
    oracle run once per seed too): the spread a decision on a knife edge would show."""
    rows = []
    for name, factors in SCENARIOS:
        ratios, latencies = [], []
        for k in range(repeats):
            seed = 1000 + k
            tell: Callable[[str], None] | None = None
            if progress is not None:
                def tell(s: str, seed: int = seed, report: Callable[[str], None] = progress) -> None:
                    report(f"{s} (seed {seed})")
            r = run_case(base, name, factors, change_at=change_at, duration=duration, seed=seed,
                         modes=("adaptive", "oracle"), progress=tell)
            ratios.append(r.get("adaptive_over_oracle"))
            latencies.append(r.get("change_to_redesign_s"))
        ok = [x for x in ratios if x is not None]
        rows.append({"name": name, "adaptive_over_oracle": ratios, "change_to_redesign_s": latencies,
                     "spread": (max(ok) - min(ok)) if len(ok) == len(ratios) and ok else None})
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians and worsts over every scenario and case."""
    def col(key: str) -> list[float | None]:
        return [r.get(key) for r in rows]

    def stat(values: list[float | None]) -> dict[str, float | int | None]:
        ok = [float(v) for v in values if v is not None]
        return {"median": float(np.median(ok)) if ok else None, "worst": max(ok) if ok else None,
                "missing": len(values) - len(ok)}

    stops = sum(1 for r in rows for m in ("fixed", "adaptive", "oracle") if m in r and r[m].get("stop"))
    fallbacks = sum(int(r["adaptive"].get("fallbacks") or 0) for r in rows if "adaptive" in r)
    return {"n": len(rows), "adaptive_over_oracle": stat(col("adaptive_over_oracle")),
            "adaptive_over_oracle_max": stat(col("adaptive_over_oracle_max")),
            "adaptive_over_fixed": stat(col("adaptive_over_fixed")),
            "adaptive_over_fixed_max": stat(col("adaptive_over_fixed_max")),
            "change_to_redesign_s": stat(col("change_to_redesign_s")),
            "first_response_s": stat(col("first_response_s")),
            "late_oracle_over_oracle_max": stat(col("late_oracle_over_oracle_max")),
            "stops": stops, "adaptive_fallbacks": fallbacks}


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


def control_bench(*, quick: bool = False, cases: int = 20, repeats: int = 3,
                  progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The four named scenarios, ``cases`` randomized ones, each named scenario under ``repeats``
    other noise seeds, and the nominal design on random plants."""
    base = load("sim-load-change.toml")
    change_at, duration, after = TIMING[quick]
    rows = run_scenarios(base, change_at=change_at, duration=duration, progress=progress)
    case_rows = [run_case(base, name, f, change_at=at, duration=at + after, seed=sd,
                          progress=progress, late_oracle=True)
                 for name, f, at, sd in random_cases(cases)]
    spread = perturbed_spread(base, repeats=repeats, change_at=change_at, duration=duration, progress=progress) \
        if repeats > 0 else []
    plants = random_plants(base.axis_params(), n=20 if quick else 100,
                           bandwidth_hz=base.control.bandwidth_hz, tick=1.0 / base.loop.tick_hz,
                           delay=base.control.delay_ticks)
    return {"control": {"scenarios": rows, "cases": case_rows, "perturbed": spread,
                        "summary": summarize(rows + case_rows), "random_plants": plants,
                        "new_plant_tolerance": NEW_PLANT_TOLERANCE}}


def targets(result: dict[str, Any]) -> list[tuple[str, bool, str]]:
    """(target, met, figure) for the printed summary."""
    c = result["control"]
    sm = c["summary"]
    rows = c["scenarios"] + c["cases"]

    def fig(v: float | None, unit: str = "") -> str:
        return "n/a" if v is None else f"{v:.3g}{unit}"

    lat = sm["change_to_redesign_s"]
    aor = sm["adaptive_over_oracle"]
    out = [("change-to-redesign latency: median <= 150 ms",
            lat["median"] is not None and lat["median"] <= 0.150 and lat["missing"] == 0,
            f"median {fig(None if lat['median'] is None else 1e3 * lat['median'], ' ms')}, "
            f"worst {fig(None if lat['worst'] is None else 1e3 * lat['worst'], ' ms')}, {lat['missing']} never"),
           ("adaptive / oracle RMS: median <= 1.1", aor["median"] is not None and aor["median"] <= 1.1,
            fig(aor["median"])),
           ("adaptive / oracle RMS: worst <= 1.3", aor["worst"] is not None and aor["worst"] <= 1.3, fig(aor["worst"]))]
    mx = [r.get("adaptive_over_oracle_max") for r in rows]
    over = [r for r in rows if r.get("adaptive_over_oracle_max") is not None and r["adaptive_over_oracle_max"] > 2.0]
    bound = "".join(f"; {r['name']}: {r['adaptive_over_oracle_max']:.3g}, the oracle's design switched in "
                    f"{fig(None if r.get('first_response_s') is None else 1e3 * r['first_response_s'], ' ms')} "
                    f"after the change (the adaptive loop's first act) {fig(r.get('late_oracle_over_oracle_max'))}"
                    for r in over)
    out.append(("adaptive max error <= 2 x oracle's in every case", all(v is not None and v <= 2.0 for v in mx),
                f"worst {fig(max((v for v in mx if v is not None), default=None))}{bound}"))
    big_rows = [r for r in rows if max(r["factors"].values(), default=1.0) >= 1.5
                or min(r["factors"].values(), default=1.0) <= 1 / 1.5]
    big = [r.get("adaptive_over_fixed") for r in big_rows]
    worse = "".join(f"; {r['name']}: {r['adaptive_over_fixed']:.5f}, the oracle from the change "
                    f"{fig(_ratio(r['oracle']['rms_error_m'], r['fixed']['rms_error_m']))}"
                    for r in big_rows if (r.get("adaptive_over_fixed") or 0.0) > 1.0 and "oracle" in r)
    out.append(("adaptive <= fixed RMS where the change is >= 1.5 x", all(v is not None and v <= 1.0 for v in big),
                f"worst {_fig5(max((v for v in big if v is not None), default=None))} of {len(big)}{worse}"))
    spreads = [p["spread"] for p in c["perturbed"]]
    if spreads:
        out.append(("adaptive / oracle spread under other noise seeds <= 0.05",
                    all(v is not None and v <= 0.05 for v in spreads),
                    f"worst {fig(max((v for v in spreads if v is not None), default=None))}"))
    out.append(("no fallback or stop in any case", sm["stops"] == 0 and sm["adaptive_fallbacks"] == 0,
                f"{sm['adaptive_fallbacks']} fallbacks, {sm['stops']} stops"))
    rp = c["random_plants"]
    out.append((f"random plants: 0 unstable of {rp['n']}", rp["unstable"] == 0, str(rp["unstable"])))
    return out


def _fig5(v: float | None) -> str:
    """A ratio near 1 with the digits that decide it (0.99968 is not "1")."""
    return "n/a" if v is None else f"{v:.5f}"


def control_comparison(result: dict[str, Any], path: str | Path) -> Path:
    """Bar chart: RMS and max table error after the change, per scenario, fixed / adaptive / oracle."""
    from matplotlib.figure import Figure

    rows = result["control"]["scenarios"]
    modes = ("fixed", "adaptive", "oracle")
    colors = {"fixed": "#7f7f7f", "adaptive": "#1f77b4", "oracle": "#2ca02c"}
    x = np.arange(len(rows))
    fig = Figure(figsize=(10, 3.8))
    axes = fig.subplots(1, 2)
    for ax, key, title in ((axes[0], "rms_error_m", "RMS from the change on"),
                           (axes[1], "max_error_m", "max from the change on")):
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
    return out

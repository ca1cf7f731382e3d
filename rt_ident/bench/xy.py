"""The XY table's tick budget: both axes at the sim's 34 k samples/s each, with
per-sample estimation and control, in one loop - against one axis alone, in the same run.

``rt-ident bench xy``: the two-axis run is ``configs/xy-sim.toml`` as shipped (its circle, dashboards
and recordings written into a temporary directory, real time), cut to ``seconds``; the one-axis run is
its X axis alone (the same sections, no ``[axes]``); a third run is the two-axis one with ``[loop]
idle_poll = false`` (rt_ident.loop.idle_poll: what keeping the loop's CPU busy while it sleeps
buys, measured beside it); a fourth with ``[loop] compiled_tick = false`` (every tick on the Python
path the compiled tick replaces: rt_ident.loop.tick_core). Reported: the tick's work (read, estimate,
control, plan of every axis;
``loop.work_us``) at p50/p99/max, each axis's share, overruns, whether the idle poller ran, the
simulated plant's stepping after the tick (``loop.sim_ahead_us``: a real device's part, not in the
work) and the target (p99 <= 40 % of the 1 ms tick, on the shipped config).
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from rt_ident.axis.params import CONFIG_DIR

TARGET_P99_US = 400.0


def _trial(summary: dict[str, Any]) -> dict[str, Any]:
    loop = summary.get("loop") or {}
    out = {"work_us": loop.get("work_us"), "sim_ahead_us": loop.get("sim_ahead_us"),
           "samples": loop.get("samples"), "overruns": loop.get("overruns"),
           "lost_samples": loop.get("lost_samples"), "stop": (summary.get("stop") or {}).get("cause")}
    out["idle_poll"] = bool(((summary.get("realtime") or {}).get("idle_poll") or {}).get("running"))
    if "axes" in summary:
        out["per_axis_work_us"] = {n: ax["loop"]["work_us"] for n, ax in summary["axes"].items()}
        out["per_axis_samples"] = {n: ax["loop"].get("samples") for n, ax in summary["axes"].items()}
        out["compiled_tick"] = {n: ax["loop"].get("compiled_tick") for n, ax in summary["axes"].items()}
    return out


@contextlib.contextmanager
def _scheduling_restored() -> Iterator[None]:
    """A real-time run leaves the calling thread on one CPU under SCHED_FIFO (the CLI runs once per
    process). Between the bench's runs, put it back: the next run picks its loop CPU from the thread's
    affinity, and without two CPUs to choose from it runs unpinned and without the idle poller."""
    import gc
    import os

    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    cpus = os.sched_getaffinity(0)
    try:
        yield
    finally:
        try:
            os.sched_setscheduler(0, policy, param)
            os.sched_setaffinity(0, cpus)
        except OSError:
            pass
        gc.unfreeze()
        gc.enable()


def xy_budget(seconds: float = 10.0, *, realtime: bool = True,
              progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    from rt_ident.compose.run import run
    from rt_ident.config import from_mapping, load

    say = progress or (lambda _s: None)
    with tempfile.TemporaryDirectory(prefix="rt_ident-xy-bench-") as tmp:
        over = {"loop.duration": seconds, "loop.realtime": realtime}
        cfg = load(CONFIG_DIR / "xy-sim.toml", **over, **{"telemetry.rrd": str(Path(tmp) / "xy.rrd"),
                                                         "recording.path": str(Path(tmp) / "xy.parquet")})
        say(f"two axes, {seconds:g} s")
        with _scheduling_restored():
            xy = _trial(run(cfg))
        data = cfg.axis_configs()["x"].model_dump(exclude={"source"})
        data["telemetry"]["rrd"] = str(Path(tmp) / "x.rrd")
        data["recording"]["path"] = str(Path(tmp) / "x.parquet")
        one_cfg = from_mapping(data, source=f"{cfg.source} [axes.x] alone")
        say(f"X alone, {seconds:g} s")
        with _scheduling_restored():
            one = _trial(run(one_cfg))
        off = load(CONFIG_DIR / "xy-sim.toml", **over, **{"loop.idle_poll": False,
                                                         "telemetry.rrd": str(Path(tmp) / "xy-off.rrd"),
                                                         "recording.path": str(Path(tmp) / "xy-off.parquet")})
        say(f"two axes without the idle poller, {seconds:g} s")
        with _scheduling_restored():
            no_poll = _trial(run(off))
        py = load(CONFIG_DIR / "xy-sim.toml", **over, **{"loop.compiled_tick": False,
                                                        "telemetry.rrd": str(Path(tmp) / "xy-py.rrd"),
                                                        "recording.path": str(Path(tmp) / "xy-py.parquet")})
        say(f"two axes, each tick on the Python path, {seconds:g} s")
        with _scheduling_restored():
            python_path = _trial(run(py))
    p99 = (xy.get("work_us") or {}).get("p99")
    one99 = (one.get("work_us") or {}).get("p99")
    py99 = (python_path.get("work_us") or {}).get("p99")
    return {"seconds": seconds, "realtime": realtime, "two_axes": xy, "one_axis": one, "two_axes_no_idle_poll": no_poll,
            "two_axes_python_path": python_path,
            "target_p99_us": TARGET_P99_US, "met": p99 is not None and p99 <= TARGET_P99_US,
            "p99_ratio_two_over_one": (p99 / one99) if p99 and one99 else None,
            "p99_ratio_compiled_over_python": (p99 / py99) if p99 and py99 else None}


__all__ = ["TARGET_P99_US", "xy_budget"]

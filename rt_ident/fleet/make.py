"""A generated fleet to try ``rt-ident fleet`` on: machines x axes x days of recordings, some worn.

``rt-ident fleet make OUT ...`` or ``python -m rt_ident.fleet.make OUT ...`` (the same options).

Each recording is a short closed-loop run of the whole product on the simulated axis (``run_offline``:
the host's position loop, quantized 2^17-count encoder and 0.1 um scale, torque noise on the measured
torque and on the applied torque, a different noise seed per recording, each machine's axis a few
per cent off the nominal Table 1 axis). A chosen fraction of the series wears from a random day on; by
default both ways at once: ball-screw stiffness K -0.5 %/day (preload loss) and coupling damping B +2 %/day
(lubrication). ``--wear k,b,load`` gives the worn series one kind each, in turn: K alone, B alone, or a load
change (table inertia I2 +30 % from the day after the onset: a heavier fixture).

Writes ``OUT/recordings/*.parquet``, ``OUT/manifest.csv`` (``rt-ident fleet identify`` input) and
``OUT/truth.json`` (which series wear, how, from which day, and each recording's true parameters).
"""

from __future__ import annotations

import datetime as dt
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

from rt_ident.errors import ConfigError, RtIdentError

K_PER_DAY = -0.005
B_PER_DAY = 0.02
LOAD_STEP = 0.30

#: kind of wear -> which parameters move and how; ``d`` is the number of days since the onset
WEAR: dict[str, dict[str, Callable[[int], float]]] = {
    "k-b": {"K": lambda d: 1.0 + K_PER_DAY * d, "B": lambda d: 1.0 + B_PER_DAY * d},
    "k": {"K": lambda d: 1.0 + K_PER_DAY * d},
    "b": {"B": lambda d: 1.0 + B_PER_DAY * d},
    "load": {"I2": lambda d: 1.0 + LOAD_STEP * (d > 0)},
}


def make_fleet(out: str | Path, *, machines: int = 4, axes: tuple[str, ...] = ("x", "y"), days: int = 12,
               worn: float = 0.5, duration: float = 0.4, seed: int = 1, start: str = "2026-11-01",
               wear: tuple[str, ...] = ("k-b",), progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Write the fleet (see the module docstring) under ``out``; returns ``manifest``, ``truth``,
    ``recordings``, ``series`` and ``worn`` (how many series wear). ``progress(done, total)`` after
    each recording."""
    import numpy as np

    from rt_ident.axis.params import thomson_x
    from rt_ident.compose.offline import run_offline
    from rt_ident.config import load
    from rt_ident.fleet.manifest import Entry, write_manifest
    from rt_ident.fleet.paths import output_path

    if machines < 1 or days < 1:
        raise ConfigError("--machines/--days", "must be at least 1")
    if not 0.0 <= worn <= 1.0:
        raise ConfigError("--worn", f"{worn:g} is not a fraction in [0, 1]")
    if duration <= 0:
        raise ConfigError("--duration", f"{duration:g} s: must be > 0")
    if not axes:
        raise ConfigError("--axes", "name at least one axis")
    if not wear or any(w not in WEAR for w in wear):
        raise ConfigError("--wear", f"{','.join(wear)!r}: comma-separated kinds among {', '.join(WEAR)}")
    try:
        day0 = dt.datetime.fromisoformat(start).replace(hour=6, tzinfo=dt.UTC)
    except ValueError:
        raise ConfigError("--start", f"{start!r} is not an ISO 8601 date such as 2026-11-01") from None
    out = Path(out)
    rng = np.random.default_rng(seed)
    rec_dir = out / "recordings"
    rec_dir.mkdir(parents=True, exist_ok=True)
    nominal = thomson_x()
    series = [(f"m{i + 1:02d}", a) for i in range(machines) for a in axes]
    n_worn = int(round(worn * len(series)))
    wearing = set(map(tuple, rng.permutation(np.array(series, dtype=object))[:n_worn].tolist()))
    wear_of = {s: wear[i % len(wear)] for i, s in enumerate(x for x in series if x in wearing)}
    truth: dict[str, Any] = {"series": [], "k_per_day": K_PER_DAY, "b_per_day": B_PER_DAY, "load_step": LOAD_STEP}
    entries: list[Entry] = []
    total = len(series) * days
    done = 0
    for machine, axis in series:
        spread = 1.0 + 0.03 * rng.standard_normal(4)          # this machine's axis vs the nominal one
        base = {k: getattr(nominal, k) * f for k, f in zip(("I1", "I2", "B", "K"), spread)}
        onset = int(rng.integers(max(6, days // 3), max(7, days - 3))) if (machine, axis) in wearing else None
        recs = []
        for day in range(days):
            worn_days = max(0, day - onset) if onset is not None else 0
            p = dict(base)
            for k, factor in WEAR[wear_of[(machine, axis)]].items() if onset is not None else ():
                p[k] *= factor(worn_days)
            path = output_path(rec_dir, machine, axis, f"day{day:03d}", suffix=".parquet")    # a typed name: no path
            cfg = load(None, **{"loop.realtime": False, "telemetry.sink": "off", "recording.enabled": False,
                                "loop.duration": duration, **{f"axis.{k}": v for k, v in p.items()},
                                "backend.seed": int(rng.integers(1 << 31)), "backend.torque_meas_noise": 2e-4,
                                "backend.torque_process_noise": 1e-4})
            res = run_offline(cfg, record=str(path), overwrite=True)
            if res["stop"]:
                raise RtIdentError(f"{path.name}: the simulated run stopped: {res['stop']}")
            entries.append(Entry(str(path.relative_to(out.resolve())), machine, axis,
                                 day0 + dt.timedelta(days=day, minutes=int(rng.integers(0, 120)))))
            recs.append({"day": day, **p})
            done += 1
            if progress is not None:
                progress(done, total)
        truth["series"].append({"machine": machine, "axis": axis, "worn": onset is not None, "onset_day": onset,
                                "wear": wear_of.get((machine, axis)), "recordings": recs})
    write_manifest(out / "manifest.csv", entries)
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return {"manifest": str(out / "manifest.csv"), "truth": str(out / "truth.json"), "recordings": total,
            "series": len(series), "worn": n_worn}


def make_cmd(
    out: Path = typer.Argument(..., help="Folder to write into (created if missing): recordings/*.parquet, "
                                         "manifest.csv (the input of `fleet identify`) and truth.json (which series "
                                         "wear, from which day, each recording's true parameters)."),
    machines: int = typer.Option(4, "--machines", min=1, help="Machines in the fleet, named m01, m02, ..."),
    axes: str = typer.Option("x,y", "--axes", help="Axis names, comma-separated: every machine has each axis; a "
                                                   "series is one machine's axis."),
    days: int = typer.Option(12, "--days", min=1, help="Recordings per series: one a day from --start."),
    worn: float = typer.Option(0.5, "--worn", min=0.0, max=1.0,
                               help=f"Fraction of the series that wear from a random day on (K {100 * K_PER_DAY:+g} "
                                    f"%/day: preload loss; B {100 * B_PER_DAY:+g} %/day: lubrication)."),
    duration: float = typer.Option(0.4, "--duration", min=0.01, help="Seconds of closed-loop run per recording "
                                                                     "(simulated faster than real time)."),
    seed: int = typer.Option(1, "--seed", help="Random seed: the same seed and options write the same fleet."),
    start: str = typer.Option("2026-11-01", "--start", help="Date of day 0 (ISO 8601); each recording is made "
                                                            "between 06:00 and 08:00 UTC of its day."),
    wear: str = typer.Option("k-b", "--wear", help="Kinds of wear, comma-separated, given to the worn series in "
                                                   "turn: k (K alone), b (B alone), load (I2 +30 % from the day "
                                                   "after the onset), k-b (K and B together, the default)."),
) -> None:
    """Write a generated fleet to try `rt-ident fleet` on: closed-loop runs of the product on the simulated
    axis, each machine's axis a few per cent off the nominal one, a fraction of the series wearing."""
    names = tuple(a.strip() for a in axes.split(",") if a.strip())

    def progress(done: int, total: int) -> None:
        print(f"\r{done}/{total} recordings", end="\n" if done == total else "", file=sys.stderr, flush=True)

    res = make_fleet(out, machines=machines, axes=names, days=days, worn=worn, duration=duration, seed=seed,
                     start=start, wear=tuple(w.strip() for w in wear.split(",") if w.strip()),
                     progress=progress if sys.stderr.isatty() else None)
    typer.echo(f"{res['recordings']} recordings of {res['series']} series ({res['worn']} wearing) in {out}; "
               f"manifest {res['manifest']}")


def main(argv: list[str] | None = None) -> int:
    """``python -m rt_ident.fleet.make``: the same command outside the ``rt-ident`` CLI; returns its exit code."""
    app = typer.Typer(add_completion=False)
    app.command()(make_cmd)
    command = typer.main.get_command(app)
    try:
        command.main(args=argv, prog_name="python -m rt_ident.fleet.make", standalone_mode=True)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except RtIdentError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A fleet with one series per kind of wear, generated once per session by
:func:`rt_ident.fleet.make.make_fleet` and identified serially (no cluster): 4 machines, axis x, 10 days;
three series wear from day 6 on - one K alone (-0.5 %/day), one B alone (+2 %/day), one a load change
(I2 +30 %) - and one stays healthy. ``truth.json`` says which is which."""

from __future__ import annotations

import copy
import json
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest


@dataclass(frozen=True)
class WearFleet:
    folder: Path
    truth: dict[str, Any]
    rows: list[dict[str, Any]]          # identified history rows, manifest order

    def kind(self, wear: str | None) -> tuple[str, str]:
        """(machine, axis) of the series with this kind of wear (None: the healthy one)."""
        (s,) = [s for s in self.truth["series"] if s["wear"] == wear]
        return s["machine"], s["axis"]

    def onset(self, key: tuple[str, str]) -> int | None:
        return next(s["onset_day"] for s in self.truth["series"] if (s["machine"], s["axis"]) == key)

    def series_rows(self, key: tuple[str, str]) -> list[dict[str, Any]]:
        """A deep copy of that series' rows, in time order (free to alter)."""
        return copy.deepcopy(sorted((r for r in self.rows if (r["machine"], r["axis"]) == key),
                                    key=lambda r: r["time"]))

    def history(self, folder: Path, rows: list[dict[str, Any]] | None = None) -> Path:
        """A history under ``folder`` holding ``rows`` (default: the whole fleet)."""
        from rt_ident.fleet.identify import append_history

        append_history(folder, self.rows if rows is None else rows)
        return folder


@pytest.fixture(scope="session")
def wear_fleet(made_once) -> WearFleet:
    """Made once for all the xdist workers (each making its own cost 5-15 s of CPU the others needed)."""
    out = made_once("wear-fleet", _make_wear_fleet)
    rows = pickle.loads((out / "rows.pickle").read_bytes())
    return WearFleet(out, json.loads((out / "truth.json").read_text()), rows)


def _make_wear_fleet(out: Path) -> None:
    from rt_ident.fleet.identify import identify_recording
    from rt_ident.fleet.make import make_fleet
    from rt_ident.fleet.manifest import read_manifest

    out.mkdir(parents=True, exist_ok=True)
    make_fleet(out, machines=4, axes=("x",), days=10, worn=0.75, wear=("k", "b", "load"), duration=0.3, seed=5)
    rows = [identify_recording({"path": e.path, "machine": e.machine, "axis": e.axis, "time": e.time})
            for e in read_manifest(out / "manifest.csv")]
    assert all(r["status"] == "ok" and r["trusted"] for r in rows), [r["error"] or r["reasons"] for r in rows]
    truth = json.loads((out / "truth.json").read_text())
    assert sorted(str(s["wear"]) for s in truth["series"]) == ["None", "b", "k", "load"]
    (out / "rows.pickle").write_bytes(pickle.dumps(rows))


def local_cluster(workers: int):
    """A real scheduler and ``workers`` worker processes, confined to 127.0.0.1 (dashboard included)."""
    from distributed import LocalCluster

    c = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                     dashboard_address="127.0.0.1:0")
    yield c
    c.close()

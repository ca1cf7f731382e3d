"""``rt-ident fleet drift``: per machine, axis and parameter, a CUSUM on standardized differences from a
baseline, each estimate weighted by its own 95 % interval.

Method (tabular two-sided CUSUM, Page 1954, "Continuous inspection schemes", Biometrika 41; reference
values as in Montgomery, *Introduction to Statistical Quality Control*, ch. 9):

* baseline: the first ``baseline`` recordings of the series (in time order): mean ``mu0`` and sample
  standard deviation ``s0`` (the recording-to-recording scatter);
* each later estimate ``x_k`` with its own standard error ``se_k`` (half its 95 % interval / 1.96) is
  standardized: ``z_k = (x_k - mu0) / sigma_k`` with
  ``sigma_k^2 = s0^2 (1 + 1/n0) + se_k^2`` (the baseline mean's own uncertainty counted), and
  ``sigma_k >= floor * |mu0|`` - a baseline of a few near-identical fits must not make a 0.1 % wiggle an
  alarm (``floor`` = 0.2 % by default);
* ``C+ = max(0, C+ + z - k)``, ``C- = max(0, C- - z - k)``; an alarm when either exceeds ``h``
  (``k = 0.5``, ``h = 5``: a shift of one sigma is found in about 10 recordings, and an in-control series
  raises a false alarm about once in 465).

Only trusted estimates enter a series: a row whose verdict is "not trusted", or unknown (written before
verdicts were recorded: no ``trusted``/``trust_criteria``), is left out and counted (``ignored``). An
untrusted estimate is not evidence of drift, and an alarm must not rest on one.

The history is read with DuckDB (:mod:`rt_ident.fleet.history`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.fleet.history import columns, connect, verdict_sql
from rt_ident.fleet.identify import PARAMS

#: parameters watched by default (wd follows wn and zeta)
WATCHED = ("I1", "I2", "B", "K", "wn", "zeta")


@dataclass(frozen=True)
class DriftSettings:
    baseline: int = 5
    k: float = 0.5
    h: float = 5.0
    floor: float = 0.002


def series(history: str | Path) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """(machine, axis) -> arrays ``time`` (datetime64[us]), each parameter with ``_lo``/``_hi``, ``trusted`` and
    ``has_verdict`` (bool), in time order: every recording once (its latest identification with a recorded
    verdict, else its latest)."""
    con = connect(history)
    cols = ", ".join(f"{k}, {k}_lo, {k}_hi" for k in PARAMS)
    rows = con.execute(
        f"SELECT machine, axis, time, {cols}, trusted, has_verdict FROM (SELECT *, {verdict_sql(columns(con))} "
        "FROM history) QUALIFY row_number() OVER (PARTITION BY machine, axis, hash ORDER BY has_verdict DESC, "
        "version DESC) = 1 ORDER BY machine, axis, time").fetchnumpy()
    out: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    machine, axis = np.asarray(rows["machine"]).astype(str), np.asarray(rows["axis"]).astype(str)
    keys = sorted(set(zip(machine, axis)))
    known = np.asarray(rows["has_verdict"], dtype=bool)
    trusted = known & (np.asarray(np.ma.filled(np.ma.asarray(rows["trusted"]), False), dtype=bool))
    for m, a in keys:
        sel = (machine == m) & (axis == a)
        d = {"time": np.asarray(rows["time"])[sel], "trusted": trusted[sel], "has_verdict": known[sel]}
        for k in PARAMS:
            for suffix in ("", "_lo", "_hi"):
                d[k + suffix] = np.asarray(np.ma.filled(np.ma.asarray(rows[k + suffix], dtype=float), np.nan))[sel]
        out[(m, a)] = d
    return out


def cusum(x: np.ndarray, se: np.ndarray, s: DriftSettings) -> dict[str, Any]:
    """CUSUM of one parameter's series (see the module docstring). Returns the baseline, the statistic
    and the first alarm index (None: no alarm)."""
    n0 = s.baseline
    ok = np.isfinite(x)
    base = x[:n0][ok[:n0]]
    if base.size < 2:
        return {"mu0": math.nan, "alarm": None, "z": np.full(x.shape, np.nan), "cplus": None, "cminus": None}
    mu0 = float(base.mean())
    s0 = float(base.std(ddof=1))
    se = np.where(np.isfinite(se), se, 0.0)
    sigma = np.sqrt(s0 * s0 * (1.0 + 1.0 / base.size) + se * se)
    sigma = np.maximum(sigma, s.floor * abs(mu0))
    z = (x - mu0) / sigma
    cp = np.zeros(x.shape)
    cm = np.zeros(x.shape)
    up = dn = 0.0
    alarm = None
    for i in range(n0, x.shape[0]):
        if not ok[i]:
            cp[i], cm[i] = up, dn
            continue
        up = max(0.0, up + z[i] - s.k)
        dn = max(0.0, dn - z[i] - s.k)
        cp[i], cm[i] = up, dn
        if alarm is None and (up > s.h or dn > s.h):
            alarm = i
    return {"mu0": mu0, "s0": s0, "alarm": alarm, "z": z, "cplus": cp, "cminus": cm}


def drift(history: str | Path, settings: DriftSettings = DriftSettings(),
          params: tuple[str, ...] = WATCHED) -> dict[str, Any]:
    """Every (machine, axis, parameter) series checked on its trusted rows; alarms in JSON-ready form, the
    largest change first; ``ignored`` counts the rows left out (not trusted / no recorded verdict)."""
    alarms = []
    checked = 0
    ignored = {"untrusted": 0, "unknown_verdict": 0}
    detail: dict[tuple[str, str], dict[str, Any]] = {}
    for (machine, axis), full in series(history).items():
        use = full["trusted"]
        ignored["untrusted"] += int(np.count_nonzero(full["has_verdict"] & ~use))
        ignored["unknown_verdict"] += int(np.count_nonzero(~full["has_verdict"]))
        d = {k: v[use] for k, v in full.items()}
        per: dict[str, Any] = {}
        for p in params:
            x = d[p]
            se = (d[f"{p}_hi"] - d[f"{p}_lo"]) / (2.0 * 1.96)
            r = cusum(x, se, settings)
            checked += 1
            per[p] = r
            i = r["alarm"]
            if i is not None:
                recent = x[max(i - 2, settings.baseline):i + 1]
                change = 100.0 * (float(np.nanmean(recent)) / r["mu0"] - 1.0)
                alarms.append({"machine": machine, "axis": axis, "parameter": p,
                               "first_time": np.datetime_as_string(d["time"][i], unit="s") + "Z",
                               "change_percent": round(change, 3), "recordings_before": int(i)})
        detail[(machine, axis)] = {"series": d, "cusum": per, "ignored": int(full["time"].size - d["time"].size)}
    alarms.sort(key=lambda a: -abs(a["change_percent"]))
    return {"checked": checked, "series": len(detail), "alarms": alarms, "ignored": ignored,
            "method": f"two-sided CUSUM (Page 1954), k={settings.k}, h={settings.h}, baseline {settings.baseline}, "
                      "trusted estimates only",
            "_detail": detail}


__all__ = ["DriftSettings", "drift", "cusum", "series", "WATCHED"]

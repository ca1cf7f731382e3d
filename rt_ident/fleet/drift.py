"""``rt-ident fleet drift``: the state of every series (machine, axis) of the history, and what its alarms mean.

Method (tabular two-sided CUSUM, Page 1954, "Continuous inspection schemes", Biometrika 41; reference
values as in Montgomery, *Introduction to Statistical Quality Control*, ch. 9), per parameter of a series:

* baseline: the first ``baseline`` trusted recordings of the series (in time order): mean ``mu0`` and
  sample standard deviation ``s0`` (the recording-to-recording scatter);
* each later estimate ``x_k`` with its own standard error ``se_k`` (half its 95 % interval / 1.96) is
  standardized: ``z_k = (x_k - mu0) / sigma_k`` with
  ``sigma_k^2 = s0^2 (1 + 1/n0) + se_k^2`` (the baseline mean's own uncertainty counted), and
  ``sigma_k >= floor * |mu0|`` - a baseline of a few near-identical fits must not make a 0.1 % wiggle an
  alarm (``floor`` = 0.2 % by default);
* ``C+ = max(0, C+ + z - k)``, ``C- = max(0, C- - z - k)``; an alarm when either exceeds ``h``
  (``k = 0.5``, ``h = 5``: a shift of one sigma is found in about 10 recordings, and an in-control series
  raises a false alarm about once in 465). The drift began, as the chart estimates it, after the last
  recording where the alarmed side's sum was zero (Montgomery 9.1.3).

Only trusted estimates enter a series: a row whose verdict is "not trusted", or unknown (written before
verdicts were recorded), is skipped and counted per series. An untrusted estimate is not evidence of
drift, and an alarm must not rest on one.

Each series gets one state:

* ``drifting``: at least one parameter alarmed. Each alarm names the parameter, the direction, since when
  (the estimated start and the first alarm), the change at the first alarm and the change now (the
  latest trusted estimate), both against the baseline mean, the rate (per cent per day) and its severity;
  the series' findings say what it means (:mod:`rt_ident.fleet.findings`);
* ``untrusted-data``: the series cannot be judged now for want of trusted rows: fewer trusted recordings
  than the baseline needs although there are enough recordings, or the latest recording is not trusted
  (its reasons quoted);
* ``insufficient-history``: fewer recordings than the baseline needs, or none after the baseline yet;
* ``ok``: a baseline, at least one trusted recording after it, the latest trusted, and no alarm.

The history is read with DuckDB (:mod:`rt_ident.fleet.history`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.fleet.findings import FELL, ROSE, SEVERITIES, Limits, findings, severity, worst
from rt_ident.fleet.history import columns, connect, verdict_sql
from rt_ident.fleet.identify import PARAMS

#: parameters watched by default (wd follows wn and zeta)
WATCHED = ("I1", "I2", "B", "K", "wn", "zeta")
STATES = ("drifting", "untrusted-data", "insufficient-history", "ok")
#: recordings (at least) the rate of change is fitted over
RATE_WINDOW = 3


@dataclass(frozen=True)
class DriftSettings:
    baseline: int = 5
    k: float = 0.5
    h: float = 5.0
    floor: float = 0.002


def series(history: str | Path) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """(machine, axis) -> arrays ``time`` (datetime64[us]), each parameter with ``_lo``/``_hi``, ``trusted``,
    ``has_verdict`` (bool) and ``reasons`` (object: a list of words per row), in time order: every recording
    once (its latest identification with a recorded verdict, else its latest)."""
    con = connect(history)
    have = columns(con)
    cols = ", ".join(f"{k}, {k}_lo, {k}_hi" for k in PARAMS)
    reasons = "reasons" if "reasons" in have else "CAST(NULL AS VARCHAR[]) AS reasons"
    rows = con.execute(
        f"SELECT machine, axis, time, {cols}, trusted, has_verdict, {reasons} FROM (SELECT *, "
        f"{verdict_sql(have)} FROM history) QUALIFY row_number() OVER (PARTITION BY machine, axis, hash ORDER BY "
        "has_verdict DESC, version DESC) = 1 ORDER BY machine, axis, time").fetchnumpy()
    out: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    machine, axis = np.asarray(rows["machine"]).astype(str), np.asarray(rows["axis"]).astype(str)
    keys = sorted({(str(m), str(a)) for m, a in zip(machine, axis)})
    known = np.asarray(rows["has_verdict"], dtype=bool)
    trusted = known & (np.asarray(np.ma.filled(np.ma.asarray(rows["trusted"]), False), dtype=bool))
    words = np.asarray(rows["reasons"], dtype=object)
    for m, a in keys:
        sel = (machine == m) & (axis == a)
        d = {"time": np.asarray(rows["time"])[sel], "trusted": trusted[sel], "has_verdict": known[sel],
             "reasons": words[sel]}
        for k in PARAMS:
            for suffix in ("", "_lo", "_hi"):
                d[k + suffix] = np.asarray(np.ma.filled(np.ma.asarray(rows[k + suffix], dtype=float), np.nan))[sel]
        out[(m, a)] = d
    return out


def cusum(x: np.ndarray, se: np.ndarray, s: DriftSettings) -> dict[str, Any]:
    """CUSUM of one parameter's series (see the module docstring). Returns the baseline (``mu0``, ``s0``,
    ``sigma`` per recording), the statistic, the first alarm index (None: no alarm), its ``direction``
    (ROSE: C+ fired, FELL: C-) and ``since``, the index where the drift began as the chart estimates it."""
    n0 = s.baseline
    ok = np.isfinite(x)
    base = x[:n0][ok[:n0]]
    if base.size < 2:
        return {"mu0": math.nan, "s0": math.nan, "alarm": None, "direction": None, "since": None,
                "z": np.full(x.shape, np.nan), "sigma": np.full(x.shape, np.nan), "cplus": None, "cminus": None}
    mu0 = float(base.mean())
    s0 = float(base.std(ddof=1))
    se = np.where(np.isfinite(se), se, 0.0)
    sigma = np.sqrt(s0 * s0 * (1.0 + 1.0 / base.size) + se * se)
    sigma = np.maximum(sigma, s.floor * abs(mu0))
    z = (x - mu0) / sigma
    cp = np.zeros(x.shape)
    cm = np.zeros(x.shape)
    up = dn = 0.0
    zero_up = zero_dn = n0 - 1           # the last recording where each sum was zero
    alarm = direction = since = None
    for i in range(n0, x.shape[0]):
        if ok[i]:
            up = max(0.0, up + z[i] - s.k)
            dn = max(0.0, dn - z[i] - s.k)
        cp[i], cm[i] = up, dn
        if alarm is not None:
            continue
        if up > s.h or dn > s.h:
            alarm = i
            direction = ROSE if up > s.h else FELL
            since = (zero_up if direction == ROSE else zero_dn) + 1
        zero_up = i if up == 0.0 else zero_up
        zero_dn = i if dn == 0.0 else zero_dn
    return {"mu0": mu0, "s0": s0, "alarm": alarm, "direction": direction, "since": since, "z": z, "sigma": sigma,
            "cplus": cp, "cminus": cm}


def _iso(t: np.datetime64) -> str:
    return str(np.datetime_as_string(t, unit="s")) + "Z"


def _days(t: np.ndarray) -> np.ndarray:
    return (t - t[0]).astype("timedelta64[s]").astype(float) / 86400.0


def _percent(x: float, mu0: float) -> float:
    return 100.0 * (x / mu0 - 1.0)


def _rate(days: np.ndarray, change: np.ndarray, alarm: int, n0: int) -> float:
    """Per cent per day: a straight line through the recordings from the first alarm on (at least the
    last RATE_WINDOW after the baseline)."""
    start = max(n0, min(alarm, days.size - RATE_WINDOW))
    d, c = days[start:], change[start:]
    ok = np.isfinite(c)
    if np.count_nonzero(ok) < 2 or np.ptp(d[ok]) <= 0:
        return math.nan
    return float(np.polyfit(d[ok], c[ok], 1)[0])


def _alarm(p: str, r: dict[str, Any], x: np.ndarray, t: np.ndarray, limits: Limits, n0: int) -> dict[str, Any]:
    i, mu0, direction = r["alarm"], r["mu0"], r["direction"]
    last = int(np.flatnonzero(np.isfinite(x))[-1])
    change = 100.0 * (x / mu0 - 1.0)
    rate = _rate(_days(t), change, i, n0)
    limit = limits.limit(p, direction)
    sev = severity(float(change[last]), rate, limit, limits.soon_days, direction)
    return {"parameter": p, "direction": "rose" if direction == ROSE else "fell",
            "since": _iso(t[r["since"]]), "first_alarm": _iso(t[i]), "recordings_before": int(i),
            "baseline": mu0, "at_first_alarm": float(x[i]), "now": float(x[last]), "now_time": _iso(t[last]),
            "change_at_first_alarm_percent": round(float(change[i]), 3),
            "change_now_percent": round(float(change[last]), 3),
            "rate_percent_per_day": None if math.isnan(rate) else round(rate, 4),
            "limit_percent": None if limit is None else direction * limit, **sev}


def _reasons(v: Any) -> list[str]:
    return [str(w) for w in v] if v is not None and not (isinstance(v, float) and math.isnan(v)) else []


def assess(machine: str, axis: str, full: dict[str, np.ndarray], settings: DriftSettings, limits: Limits,
           params: tuple[str, ...] = WATCHED) -> tuple[dict[str, Any], dict[str, Any]]:
    """One series' state (JSON-ready) and the arrays behind it (the report draws them)."""
    n0 = settings.baseline
    use = full["trusted"]
    t_all = full["time"]
    d = {k: v[use] for k, v in full.items()}
    t = d["time"]
    n_all, n_trusted = int(t_all.size), int(t.size)
    skipped_untrusted = int(np.count_nonzero(full["has_verdict"] & ~use))
    skipped_unknown = int(np.count_nonzero(~full["has_verdict"]))
    per = {p: cusum(d[p], (d[f"{p}_hi"] - d[f"{p}_lo"]) / (2.0 * 1.96), settings) for p in params}
    alarms = [_alarm(p, r, d[p], t, limits, n0) for p, r in per.items() if r["alarm"] is not None]
    parameters = {}
    for p, r in per.items():
        x = d[p][np.isfinite(d[p])]
        now = float(x[-1]) if x.size else math.nan
        mu0 = r["mu0"]
        parameters[p] = {"baseline": None if math.isnan(mu0) else mu0, "now": None if math.isnan(now) else now,
                         "change_now_percent": None if math.isnan(mu0) or math.isnan(now)
                         else round(_percent(now, mu0), 3)}
    skipped = f"{skipped_untrusted + skipped_unknown} not trusted, skipped" if skipped_untrusted + skipped_unknown \
        else ""
    latest_trusted = bool(use[-1]) if n_all else False
    found: list[dict[str, Any]] = []
    if alarms:
        state = "drifting"
        by_p = {a["parameter"]: a for a in alarms}
        for f in findings({a["parameter"]: ROSE if a["direction"] == "rose" else FELL for a in alarms}):
            moved = ", ".join(f"{p} {by_p[p]['change_now_percent']:+.1f} %" for p in f["parameters"])
            found.append({**f, "finding": f"{f['finding']} ({moved} now vs baseline)",
                          "severity": worst([by_p[p]["severity"] for p in f["parameters"]])})
        message = "; ".join(f["finding"] for f in found)
    elif n_trusted < n0 and n_all >= n0:
        state = "untrusted-data"
        message = (f"only {n_trusted} of {n_all} recordings trusted: the baseline needs {n0} "
                   f"({skipped_untrusted} not trusted, {skipped_unknown} with no recorded verdict)")
    elif n_trusted <= n0:
        state = "insufficient-history"
        message = (f"insufficient history: {n_trusted} of {n0} baseline recordings" if n_trusted < n0 else
                   f"insufficient history: {n0} of {n0} baseline recordings, none after them yet")
    elif not latest_trusted:
        state = "untrusted-data"
        why = _reasons(full["reasons"][-1]) or ["no recorded verdict (written by an older rt-ident)"]
        message = (f"the latest recording ({_iso(t_all[-1])[:16].replace('T', ' ')}) is not trusted: "
                   f"{'; '.join(why)}; no alarm up to the last trusted one ({_iso(t[-1])[:16].replace('T', ' ')})")
    else:
        state = "ok"
        message = f"no drift in {n_trusted - n0} trusted recordings after the {n0}-recording baseline"
    if state == "drifting" and not latest_trusted:
        message += "; the latest recording is not trusted"
    if skipped and state != "untrusted-data":
        message += f" ({skipped})"
    public = {"machine": machine, "axis": axis, "state": state,
              "severity": worst([f["severity"] for f in found]), "message": message,
              "recordings": n_all, "trusted": n_trusted, "skipped_untrusted": skipped_untrusted,
              "skipped_unknown_verdict": skipped_unknown,
              "baseline": {"needed": n0, "have": min(n_trusted, n0),
                           "until": _iso(t[n0 - 1]) if n_trusted >= n0 else None},
              "latest": {"time": _iso(t_all[-1]), "trusted": latest_trusted} if n_all else None,
              "parameters": parameters, "alarms": sorted(alarms, key=_alarm_order), "findings": found}
    return public, {"series": d, "all": full, "cusum": per}


def _alarm_order(a: dict[str, Any]) -> tuple[float, float]:
    return -SEVERITIES.index(a["severity"]), -(a["limit_used"] or 0.0)


def order(s: dict[str, Any]) -> tuple[Any, ...]:
    """Worst first: drifting series by severity and the share of a limit used, then untrusted data, then
    insufficient history, then ok; by name within."""
    used = max((a["limit_used"] or 0.0 for a in s["alarms"]), default=0.0)
    sev = SEVERITIES.index(s["severity"]) if s["severity"] else -1
    return STATES.index(s["state"]), -sev, -used, s["machine"], s["axis"]


def drift(history: str | Path, settings: DriftSettings = DriftSettings(), limits: Limits | None = None,
          params: tuple[str, ...] = WATCHED) -> dict[str, Any]:
    """Every series' state (``series``, worst first) and every alarm (``alarms``, in the same order);
    ``counts`` per state; ``ignored`` totals the rows skipped (not trusted / no recorded verdict).
    ``_detail`` (not JSON) holds the arrays per series."""
    limits = limits or Limits()
    states = []
    detail: dict[tuple[str, str], dict[str, Any]] = {}
    for (machine, axis), full in series(history).items():
        public, det = assess(machine, axis, full, settings, limits, params)
        states.append(public)
        detail[(machine, axis)] = det
    states.sort(key=order)
    alarms = [{"machine": s["machine"], "axis": s["axis"], **a} for s in states for a in s["alarms"]]
    return {"method": f"two-sided CUSUM (Page 1954), k={settings.k}, h={settings.h}, baseline {settings.baseline}, "
                      "trusted estimates only",
            "limits": limits.as_dict(), "checked": len(params) * len(states),
            "counts": {st: sum(s["state"] == st for s in states) for st in STATES},
            "ignored": {"untrusted": sum(s["skipped_untrusted"] for s in states),
                        "unknown_verdict": sum(s["skipped_unknown_verdict"] for s in states)},
            "series": states, "alarms": alarms, "_detail": detail}


__all__ = ["DriftSettings", "drift", "assess", "cusum", "series", "order", "WATCHED", "STATES"]

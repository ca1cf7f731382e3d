"""What a drift alarm means on the machine, and how urgent it is.

**Findings.** :data:`RULES` is the one table that turns the directions in which a series' parameters moved
(each watched parameter: rose, fell, or steady - no alarm) into a finding in plain words and a check for
the maintenance engineer. Every rule rests on the two-inertia model (motor inertia I1, table inertia I2,
coupling stiffness K and damping B between them)::

    wn^2 = K (I1 + I2) / (I1 I2) = K (1/I1 + 1/I2)
    zeta = B (1/I1 + 1/I2) / (2 wn) = (B / 2) sqrt((1/I1 + 1/I2) / K)

so a K loss lowers wn (as sqrt K) and raises zeta (as 1/sqrt K); a B rise raises zeta alone; more table
inertia lowers wn and zeta with K unchanged; and a torque read with another scale multiplies I1, I2, B
and K alike while wn and zeta stay put. Rules are tried in order; one fires when its conditions hold
and it accounts for an alarmed parameter no earlier finding accounted for (``explains``: the parameters
it accounts for, each with the direction the physics predicts). The last rule takes whatever is left.

**Severity.** Each alarm's change now is compared with its limit (:class:`Limits`: how far a parameter
may move from its baseline, in per cent, each way; ``--limits FILE``) and with the rate at which it
moves (per cent per day over the recent recordings):

* ``critical``: the limit is reached or passed;
* ``high``: half the limit used, or the limit reached within ``soon_days`` at the current rate;
* ``medium``: a quarter used, or the limit within 3 x ``soon_days``;
* ``low``: an alarm well inside its limit and moving slowly.

A finding's severity is its worst alarm's; a series' is its worst finding's.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rt_ident.errors import ConfigError

#: parameters whose direction the rules read (the drift's watched parameters)
PARAMETERS = ("I1", "I2", "B", "K", "wn", "zeta")
SEVERITIES = ("low", "medium", "high", "critical")
ROSE, FELL, STEADY = 1, -1, 0


@dataclass(frozen=True)
class Rule:
    name: str
    when: Mapping[str, int]        # parameter -> ROSE / FELL / STEADY (no alarm); absent: any
    explains: Mapping[str, int]    # alarmed parameters this finding accounts for, with the predicted direction
    finding: str
    check: str
    why: str                       # the physics behind it (the docs quote it)
    catch_all: bool = False        # accounts for any alarmed parameter left over


_SCALE_WHY = ("the model's torque balance is linear in I1, I2, B and K: a torque read c times too large "
              "multiplies all four by c and leaves wn and zeta unchanged")

RULES: tuple[Rule, ...] = (
    *(Rule(f"torque scale {way}", {**dict.fromkeys(("I1", "I2", "B", "K"), moved), "wn": STEADY, "zeta": STEADY},
           dict.fromkeys(("I1", "I2", "B", "K"), moved),
           f"every physical parameter {verb} by the same factor with wn and zeta steady: the torque's scale "
           "changed, not the mechanics",
           "the drive's torque constant and rated-torque settings, a replaced motor or drive, the current "
           "sensing", _SCALE_WHY)
      for way, moved, verb in (("up", ROSE, "rose"), ("down", FELL, "fell"))),
    # the damping rules first: when B and K both moved, zeta goes with B (it moves in proportion to B,
    # as 1/sqrt K only)
    Rule("damping rise", {"B": ROSE}, {"B": ROSE, "zeta": ROSE},
         "more damping between motor and table: lubrication (grease aged, dirty or short) or wipers and seals "
         "dragging",
         "the lubrication of the ball-screw nut and the guides (lubricator level and cycle, grease condition), "
         "the wipers",
         "B is the viscous loss between motor and table; zeta rises in proportion to B, wn does not move"),
    Rule("damping fall", {"B": FELL}, {"B": FELL, "zeta": FELL},
         "less damping between motor and table than at the baseline: a thinner or warmer lubricant, or a joint "
         "that no longer rubs",
         "which lubricant is in use and at what temperature compared with the baseline, the nut's and "
         "coupling's screws",
         "B is the viscous loss between motor and table; zeta falls in proportion to B, wn does not move"),
    Rule("stiffness loss", {"K": FELL}, {"K": FELL, "wn": FELL, "zeta": ROSE},
         "stiffness loss between motor and table (ball-screw nut preload, coupling or support bearings)",
         "the ball-screw nut's preload (a reversal or backlash test), the coupling's clamping screws and "
         "elastomer, the screw's support bearings",
         "K is the spring between motor and table; wn falls as sqrt K and zeta rises as 1/sqrt K"),
    Rule("stiffness gain", {"K": ROSE}, {"K": ROSE, "wn": ROSE, "zeta": FELL},
         "the drive train is stiffer than at the baseline",
         "what was serviced since the baseline (preload reset, coupling replaced); if nothing, look for "
         "binding: chips, a guard or cable carrier rubbing, a clamp left on",
         "K is the spring between motor and table; wn rises as sqrt K and zeta falls as 1/sqrt K"),
    Rule("load increase", {"I2": ROSE, "K": STEADY}, {"I2": ROSE, "wn": FELL, "zeta": FELL},
         "a heavier load on the table (workpiece, fixture) with the stiffness unchanged",
         "the workpiece and fixture against the baseline's; if the load stays, commission the axis again (its "
         "controller was designed for the lighter table)",
         "I2 is the table side's inertia; with K fixed, more I2 lowers wn and zeta (1/I1 + 1/I2 falls)"),
    Rule("load decrease", {"I2": FELL, "K": STEADY}, {"I2": FELL, "wn": ROSE, "zeta": ROSE},
         "a lighter load on the table (workpiece, fixture) with the stiffness unchanged",
         "the workpiece and fixture against the baseline's; if the load stays, commission the axis again",
         "I2 is the table side's inertia; with K fixed, less I2 raises wn and zeta"),
    Rule("motor-side inertia increase", {"I1": ROSE, "K": STEADY}, {"I1": ROSE, "wn": FELL, "zeta": FELL},
         "more inertia on the motor side with the stiffness unchanged",
         "the parts on the motor shaft: coupling hub, brake (replaced, or dragging), pulley, encoder",
         "I1 is the motor side's inertia; with K fixed, more I1 lowers wn and zeta"),
    Rule("motor-side inertia decrease", {"I1": FELL, "K": STEADY}, {"I1": FELL, "wn": ROSE, "zeta": ROSE},
         "less inertia on the motor side with the stiffness unchanged",
         "the parts on the motor shaft: coupling hub, brake, pulley, encoder",
         "I1 is the motor side's inertia; with K fixed, less I1 raises wn and zeta"),
    Rule("mode shift down, K steady", {"wn": FELL, "K": STEADY}, {"wn": FELL, "zeta": FELL},
         "the resonance fell while K stayed: more inertia (a load change) than the single inertia estimates "
         "resolve",
         "the workpiece and fixture against the baseline's",
         "with K fixed, wn^2 = K (1/I1 + 1/I2) falls only if an inertia grew"),
    Rule("mode shift up, K steady", {"wn": ROSE, "K": STEADY}, {"wn": ROSE, "zeta": ROSE},
         "the resonance rose while K stayed: less inertia (a load change) than the single inertia estimates "
         "resolve",
         "the workpiece and fixture against the baseline's",
         "with K fixed, wn^2 = K (1/I1 + 1/I2) rises only if an inertia shrank"),
    Rule("unexplained", {}, {},
         "a change that no rule on the physical parameters explains",
         "repeat the recording under the baseline's conditions (position, speed, temperature); if it persists, "
         "identify the axis again (rt-ident commission) and compare",
         "none of the rules above accounts for it", catch_all=True),
)


def _explains(rule: Rule, p: str, d: int) -> bool:
    return rule.catch_all or rule.explains.get(p) == d


def findings(directions: Mapping[str, int]) -> list[dict[str, Any]]:
    """The findings for one series. ``directions``: every alarmed parameter -> ROSE or FELL (parameters
    missing count as STEADY). Returns the fired rules in table order, each with the alarmed parameters it
    accounts for."""
    moved = {p: d for p, d in directions.items() if d != STEADY}
    left = dict(moved)
    out = []
    for rule in RULES:
        if not left:
            break
        if any(moved.get(p, STEADY) != d for p, d in rule.when.items()):
            continue
        mine = [p for p, d in left.items() if _explains(rule, p, d)]
        if not mine:
            continue
        for p in mine:
            del left[p]
        out.append({"rule": rule.name, "parameters": mine, "finding": rule.finding, "check": rule.check})
    return out


@dataclass(frozen=True)
class Limits:
    """How far each parameter may move from its baseline, in per cent: ``percent[p] = (fall, rise)``
    (None: no limit that way); ``soon_days``: a limit reached within this many days at the current rate
    is urgent. The built-in values are starting points, to be set from the machine's own tolerances."""

    percent: Mapping[str, tuple[float | None, float | None]] = field(default_factory=lambda: {
        "K": (15.0, 15.0), "B": (50.0, 50.0), "I1": (10.0, 10.0), "I2": (25.0, 25.0),
        "wn": (8.0, 8.0), "zeta": (50.0, 50.0)})
    soon_days: float = 30.0
    source: str = "built-in"

    def limit(self, p: str, direction: int) -> float | None:
        fall, rise = self.percent.get(p, (None, None))
        return rise if direction == ROSE else fall

    def as_dict(self) -> dict[str, Any]:
        return {"source": self.source, "soon_days": self.soon_days,
                "percent": {p: {"fall": f, "rise": r} for p, (f, r) in self.percent.items()}}


def _positive(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ConfigError("--limits", f"{where} must be a positive number of per cent, not {v!r}")
    return float(v)


def read_limits(path: str | Path | None) -> Limits:
    """Limits from a TOML file: a table per parameter with ``fall`` and/or ``rise`` (per cent from the
    baseline), and ``soon_days``; what the file leaves out keeps its built-in value."""
    base = Limits()
    if path is None:
        return base
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8-sig"))     # -sig: a BOM as Windows editors write it
    except FileNotFoundError:
        raise ConfigError("--limits", f"{p} not found") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError("--limits", f"cannot read {p}: {exc}") from None
    percent = dict(base.percent)
    soon = base.soon_days
    for key, val in data.items():
        if key == "soon_days":
            soon = _positive(val, f"{p}: soon_days")
            continue
        if key not in PARAMETERS:
            raise ConfigError("--limits", f"{p}: unknown key {key!r} (parameters: {', '.join(PARAMETERS)}; "
                              "and soon_days)")
        if not isinstance(val, dict) or not val or set(val) - {"fall", "rise"}:
            raise ConfigError("--limits", f"{p}: [{key}] takes fall and/or rise (per cent), e.g. [K] fall = 15")
        fall, rise = percent.get(key, (None, None))
        fall = _positive(val["fall"], f"{p}: {key}.fall") if "fall" in val else fall
        rise = _positive(val["rise"], f"{p}: {key}.rise") if "rise" in val else rise
        percent[key] = (fall, rise)
    return Limits(percent=percent, soon_days=soon, source=str(p))


def severity(change_now: float, rate_per_day: float, limit: float | None, soon_days: float,
             direction: int) -> dict[str, Any]:
    """One alarm's severity (module docstring) from its change now and rate (per cent, per cent per day)
    and its limit that way (per cent, or None). Also returns the share of the limit used and the days
    to reach it at the current rate (None: not moving towards it)."""
    if limit is None:
        return {"severity": "low", "limit_used": None, "days_to_limit": None}
    toward = direction * change_now               # > 0 when the change goes the limit's way
    used = max(0.0, toward) / limit
    speed = direction * rate_per_day if math.isfinite(rate_per_day) else 0.0
    days = (limit - toward) / speed if speed > 0 and used < 1 else None
    if used >= 1:
        level = "critical"
    elif used >= 0.5 or (days is not None and days <= soon_days):
        level = "high"
    elif used >= 0.25 or (days is not None and days <= 3 * soon_days):
        level = "medium"
    else:
        level = "low"
    return {"severity": level, "limit_used": round(used, 3), "days_to_limit": None if days is None else round(days, 1)}


def limit_words(alarm: dict[str, Any]) -> str:
    """An alarm's limit in words: passed, reached in about N days at this rate, or not approaching."""
    lim = alarm["limit_percent"]
    if lim is None:
        return "no limit set"
    if alarm["severity"] == "critical":
        return f"limit {lim:+g} % passed"
    days = alarm["days_to_limit"]
    if days is None:
        return f"limit {lim:+g} %, not approaching it"
    if days > 365:
        return f"limit {lim:+g} %, more than a year away at this rate"
    return f"limit {lim:+g} % in about {days:.0f} days at this rate"


def worst(levels: list[str]) -> str | None:
    return max(levels, key=SEVERITIES.index) if levels else None


__all__ = ["RULES", "Rule", "Limits", "read_limits", "findings", "severity", "limit_words", "worst", "SEVERITIES",
           "PARAMETERS", "ROSE", "FELL", "STEADY"]

"""``fleet drift`` on a generated fleet with known wear: every series has a state (ok, insufficient-history,
drifting, untrusted-data), alarms carry the change at the first alarm and the change now, untrusted rows are
skipped and counted per series, each kind of wear gets its finding and check, and a limits file sets the
severity."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rt_ident.cli import app
from rt_ident.fleet.drift import drift
from rt_ident.fleet.findings import FELL, ROSE, read_limits

runner = CliRunner()


def _state(res: dict, key: tuple[str, str]) -> dict:
    (s,) = [s for s in res["series"] if (s["machine"], s["axis"]) == key]
    return s


def _distrust(row: dict, why: str = "95 % interval of K wider than 5 % of K") -> dict:
    row.update(trusted=False, reasons=[why], trust_criteria=json.dumps([{"name": "K interval", "passed": False}]))
    return row


# --------------------------------------------------------------------------- findings on known wear
@pytest.mark.parametrize(("wear", "rule", "moved", "check_word"), [
    ("k", "stiffness loss", {"K": "fell"}, "preload"),
    ("b", "damping rise", {"B": "rose"}, "lubrication"),
    ("load", "load increase", {"I2": "rose", "wn": "fell"}, "fixture"),
])
def test_each_kind_of_wear_is_found_as_that_wear_with_its_check(wear_fleet, tmp_path, wear, rule, moved, check_word):
    key = wear_fleet.kind(wear)
    s = _state(drift(wear_fleet.history(tmp_path / "h")), key)
    assert s["state"] == "drifting", s
    assert [f["rule"] for f in s["findings"]] == [rule], s["findings"]
    assert check_word in s["findings"][0]["check"]
    got = {a["parameter"]: a["direction"] for a in s["alarms"]}
    assert got.items() >= moved.items(), got
    assert "K" not in got or wear == "k"                          # the stiffness stays put but for K wear
    onset = wear_fleet.onset(key)
    assert all(a["recordings_before"] > onset for a in s["alarms"])       # the wear starts the day after onset


def test_the_healthy_series_is_ok_and_the_worn_ones_lead_the_list(wear_fleet, tmp_path):
    res = drift(wear_fleet.history(tmp_path / "h"))
    order = [(s["machine"], s["axis"]) for s in res["series"]]
    healthy = wear_fleet.kind(None)
    assert order[-1] == healthy and _state(res, healthy)["state"] == "ok"
    assert [s["state"] for s in res["series"][:3]] == ["drifting"] * 3
    assert res["counts"] == {"drifting": 3, "untrusted-data": 0, "insufficient-history": 0, "ok": 1}
    assert order[0] == wear_fleet.kind("load") and res["series"][0]["severity"] == "critical"   # I2 +30 % > 25 %


def test_change_at_first_alarm_and_change_now_are_those_recordings_against_the_baseline_mean(wear_fleet, tmp_path):
    key = wear_fleet.kind("k")
    rows = wear_fleet.series_rows(key)
    s = _state(drift(wear_fleet.history(tmp_path / "h", rows)), key)
    (a,) = [a for a in s["alarms"] if a["parameter"] == "K"]
    k = np.array([r["K"] for r in rows])
    mu0 = k[:5].mean()
    i = a["recordings_before"]
    assert a["change_at_first_alarm_percent"] == pytest.approx(100 * (k[i] / mu0 - 1), abs=1e-3)
    assert a["change_now_percent"] == pytest.approx(100 * (k[-1] / mu0 - 1), abs=1e-3)
    assert a["change_now_percent"] < a["change_at_first_alarm_percent"] < 0   # K went on falling after the alarm
    assert "change_percent" not in a
    assert a["since"] <= a["first_alarm"] < a["now_time"]


# --------------------------------------------------------------------------- the states without an alarm
def test_four_recordings_are_insufficient_history_of_the_five_the_baseline_needs(wear_fleet, tmp_path):
    key = wear_fleet.kind(None)
    h = wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(key)[:4])
    s = _state(drift(h), key)
    assert s["state"] == "insufficient-history" and s["alarms"] == []
    assert s["message"] == "insufficient history: 4 of 5 baseline recordings"
    r = runner.invoke(app, ["fleet", "drift", "--history", str(h)])
    assert r.exit_code == 0, r.output
    assert "insufficient history: 4 of 5 baseline recordings" in r.output and "no drift" not in r.output


def test_a_baseline_with_nothing_after_it_is_still_insufficient_history(wear_fleet, tmp_path):
    key = wear_fleet.kind("load")
    s = _state(drift(wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(key)[:5])), key)
    assert s["state"] == "insufficient-history"
    assert s["message"] == "insufficient history: 5 of 5 baseline recordings, none after them yet"


def test_untrusted_rows_are_skipped_and_counted_per_series_and_raise_no_alarm(wear_fleet, tmp_path):
    key = wear_fleet.kind(None)
    rows = wear_fleet.series_rows(key)
    for r in (rows[6], rows[8]):                     # wild untrusted fits: K a third lower
        _distrust(r)["K"] *= 0.66
    other = wear_fleet.series_rows(wear_fleet.kind("b"))
    res = drift(wear_fleet.history(tmp_path / "h", rows + other))
    s = _state(res, key)
    assert s["state"] == "ok" and s["alarms"] == [], s
    assert (s["skipped_untrusted"], s["skipped_unknown_verdict"], s["trusted"], s["recordings"]) == (2, 0, 8, 10)
    assert s["message"].endswith("(2 not trusted, skipped)")
    assert _state(res, wear_fleet.kind("b"))["skipped_untrusted"] == 0
    assert res["ignored"] == {"untrusted": 2, "unknown_verdict": 0}
    r = runner.invoke(app, ["fleet", "drift", "--history", str(tmp_path / "h")])
    assert "skipped 2 rows: 2 not trusted" in r.output


def test_a_latest_recording_that_is_not_trusted_makes_the_series_untrusted_data_with_its_reason(wear_fleet, tmp_path):
    key = wear_fleet.kind(None)
    rows = wear_fleet.series_rows(key)
    _distrust(rows[-1], "the fit's chi2/dof 41 is above 4")
    s = _state(drift(wear_fleet.history(tmp_path / "h", rows)), key)
    assert s["state"] == "untrusted-data" and s["latest"]["trusted"] is False
    assert "is not trusted: the fit's chi2/dof 41 is above 4" in s["message"]
    r = runner.invoke(app, ["fleet", "drift", "--history", str(tmp_path / "h"), "--json"])
    assert json.loads(r.output)["series"][0]["state"] == "untrusted-data"


def test_too_few_trusted_recordings_for_a_baseline_among_enough_recordings_is_untrusted_data(wear_fleet, tmp_path):
    key = wear_fleet.kind(None)
    rows = wear_fleet.series_rows(key)
    for r in rows[1:7]:
        _distrust(r)
    s = _state(drift(wear_fleet.history(tmp_path / "h", rows)), key)
    assert s["state"] == "untrusted-data"
    assert s["message"].startswith("only 4 of 10 recordings trusted: the baseline needs 5")


def test_an_alarm_on_a_worn_series_survives_an_untrusted_latest_recording(wear_fleet, tmp_path):
    key = wear_fleet.kind("b")
    rows = wear_fleet.series_rows(key)
    _distrust(rows[-1])
    s = _state(drift(wear_fleet.history(tmp_path / "h", rows)), key)
    assert s["state"] == "drifting" and s["message"].endswith("; the latest recording is not trusted "
                                                              "(1 not trusted, skipped)")


# --------------------------------------------------------------------------- limits from a file
def test_a_limits_file_sets_the_severity_and_the_cli_reads_it(wear_fleet, tmp_path):
    key = wear_fleet.kind("k")
    h = wear_fleet.history(tmp_path / "h", wear_fleet.series_rows(key))
    assert _state(drift(h), key)["severity"] == "high"
    lim = tmp_path / "limits.toml"
    lim.write_text("soon_days = 10\n[K]\nfall = 1.2\n")
    limits = read_limits(lim)
    assert limits.limit("K", FELL) == 1.2 and limits.limit("K", ROSE) == 15.0 and limits.soon_days == 10
    s = _state(drift(h, limits=limits), key)
    (a,) = [a for a in s["alarms"] if a["parameter"] == "K"]
    assert a["limit_percent"] == -1.2 and a["severity"] == "critical" and s["severity"] == "critical"
    r = runner.invoke(app, ["fleet", "drift", "--history", str(h), "--limits", str(lim), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["limits"]["source"] == str(lim) and out["series"][0]["severity"] == "critical"

"""The findings table and the severity: which physical parameters moved, and how, name the finding and the check;
the severity follows the limit and the rate of change; a limits file is read or refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.errors import ConfigError
from rt_ident.fleet.findings import FELL, ROSE, Limits, findings, read_limits, severity


def test_k_down_with_b_up_is_both_lubrication_with_the_zeta_rise_and_a_stiffness_loss():
    got = findings({"K": FELL, "wn": FELL, "B": ROSE, "zeta": ROSE})
    assert [(f["rule"], f["parameters"]) for f in got] == [("damping rise", ["B", "zeta"]),
                                                          ("stiffness loss", ["K", "wn"])]
    assert "lubrication" in got[0]["check"] and "preload" in got[1]["check"]


def test_all_four_physical_parameters_scaled_with_wn_steady_is_the_torque_scale_not_wear():
    (f,) = findings({"I1": ROSE, "I2": ROSE, "B": ROSE, "K": ROSE})
    assert f["rule"] == "torque scale up" and "torque constant" in f["check"]


def test_wn_down_with_k_steady_and_no_inertia_alarm_is_a_load_change():
    (f,) = findings({"wn": FELL, "zeta": FELL})
    assert f["rule"] == "mode shift down, K steady" and "fixture" in f["check"]


def test_a_move_no_rule_explains_gets_the_catch_all_finding():
    got = findings({"K": FELL, "zeta": FELL})               # K loss predicts zeta up, not down
    assert [(f["rule"], f["parameters"]) for f in got] == [("stiffness loss", ["K"]), ("unexplained", ["zeta"])]


def test_severity_is_critical_past_the_limit_high_when_the_limit_is_near_in_time_and_low_when_slow_and_far():
    assert severity(-16.0, -0.1, 15.0, 30.0, FELL)["severity"] == "critical"
    near = severity(-3.0, -0.5, 15.0, 30.0, FELL)                     # 24 days to -15 %
    assert near["severity"] == "high" and near["days_to_limit"] == pytest.approx(24.0)
    assert severity(-3.0, -0.2, 15.0, 30.0, FELL)["severity"] == "medium"   # 60 days
    assert severity(-4.5, 0.0, 15.0, 30.0, FELL)["severity"] == "medium"    # 30 % used, not moving
    assert severity(-3.0, -0.1, 15.0, 30.0, FELL)["severity"] == "low"      # 120 days, 20 % used
    assert severity(-8.0, 0.0, 15.0, 30.0, FELL)["severity"] == "high"      # half the limit used, not moving
    away = severity(-3.0, +0.5, 15.0, 30.0, FELL)                           # recovering
    assert away["days_to_limit"] is None and away["severity"] == "low"


@pytest.mark.parametrize(("text", "match"), [
    ("[Kx]\nfall = 15\n", "unknown key 'Kx'"),
    ("[K]\nfall = -3\n", "K.fall must be a positive number"),
    ("[K]\ndrop = 3\n", r"\[K\] takes fall and/or rise"),
    ("[K\n", "cannot read"),
])
def test_a_bad_limits_file_is_refused_in_one_line_naming_the_key(tmp_path, text, match):
    p = tmp_path / "limits.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match) as e:
        read_limits(p)
    assert "\n" not in str(e.value)


def test_a_limits_file_saved_with_a_byte_order_mark_reads_as_without_one(tmp_path):
    p = tmp_path / "limits.toml"
    p.write_bytes(b"\xef\xbb\xbf[K]\nfall = 12\n")
    assert read_limits(p).limit("K", FELL) == 12


def test_built_in_limits_keep_k_within_15_percent_and_wn_within_what_that_k_gives():
    lim = Limits()
    assert lim.limit("K", FELL) == 15.0
    assert 100 * (1 - np.sqrt(0.85)) <= lim.limit("wn", FELL)         # wn ~ sqrt K: K -15 % is wn -7.8 %


def _modal(p: dict[str, float]) -> tuple[float, float]:
    """wn and zeta of the two-inertia model (the paper's Eq. (1)-(3), free-free)."""
    inv = 1.0 / p["I1"] + 1.0 / p["I2"]
    wn = np.sqrt(p["K"] * inv)
    return wn, p["B"] * inv / (2.0 * wn)


def test_every_rules_predicted_wn_and_zeta_moves_follow_from_the_two_inertia_formulas():
    from rt_ident.axis.params import thomson_x
    from rt_ident.fleet.findings import RULES

    nominal = {k: getattr(thomson_x(), k) for k in ("I1", "I2", "B", "K")}
    wn0, z0 = _modal(nominal)
    checked = 0
    for rule in RULES:
        moved = {p: d for p, d in rule.when.items() if p in nominal and d != 0}
        if not moved:
            continue
        p = {k: v * (1.0 + 0.1 * moved.get(k, 0)) for k, v in nominal.items()}
        wn, z = _modal(p)
        actual = {"wn": int(np.sign(round(wn / wn0 - 1.0, 9))), "zeta": int(np.sign(round(z / z0 - 1.0, 9)))}
        for m in ("wn", "zeta"):
            assert rule.explains.get(m, 0) == actual[m], (rule.name, m, actual)
            if rule.when.get(m) is not None:
                assert rule.when[m] == actual[m], (rule.name, m)
        checked += 1
    assert checked == 10

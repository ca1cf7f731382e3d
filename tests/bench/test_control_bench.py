"""``rt-ident bench control`` (rt_ident.bench.control): its measures, its randomized set, and the
adaptive loop it measures after a load change."""

from __future__ import annotations

import pytest

from rt_ident.axis.params import AxisParams
from rt_ident.bench import control as cb
from rt_ident.config import load

P = AxisParams(I1=2.7e-5, I2=8.3e-6, B=2.1e-3, K=110.0)


def _applied(t, kind, **f):
    return {"t": t, "kind": kind, "model": {k: getattr(P, k) * f.get(k, 1.0) for k in ("I1", "I2", "B", "K")}}


def test_change_to_redesign_is_the_first_model_design_switched_in_or_kept_near_the_new_plant_after_the_change():
    new = cb.changed_plant(P, {"I2": 3.0})
    control = {"applied": [_applied(0.2, "model"), _applied(4.05, "conservative", I2=3.0),
                           _applied(4.06, "model", I2=2.0), _applied(4.12, "model", I2=3.05),
                           _applied(4.5, "model", I2=3.0)]}
    assert cb.change_to_redesign(control, new, 4.0) == pytest.approx(0.12)
    assert cb.change_to_redesign({"applied": [_applied(4.06, "model", I2=2.0)]}, new, 4.0) is None
    soft = cb.changed_plant(P, {"K": 0.6})                # the design in force kept for the new estimate
    kept = {"applied": [_applied(0.2, "model"), _applied(4.03, "kept", K=0.7), _applied(4.08, "kept", K=0.61)]}
    assert cb.change_to_redesign(kept, soft, 4.0) == pytest.approx(0.08)


def test_random_cases_are_reproducible_and_inside_the_stated_ranges():
    cases = cb.random_cases(30, seed=5)
    assert cases == cb.random_cases(30, seed=5) and cases != cb.random_cases(30, seed=6)
    for _, f, at, _seed in cases:
        assert f and set(f) <= {"I1", "I2"} and 2.5 <= at <= 4.5
        assert 1.5 <= f.get("I2", 2.0) <= 4.0 and 1.2 <= f.get("I1", 1.5) <= 2.0


def test_bench_case_by_name_is_the_case_the_full_bench_runs_and_an_unknown_name_lists_the_known(monkeypatch):
    ran = {}

    def run_case(base, name, factors, *, change_at, duration, seed=0, **_):
        ran[name] = (name, factors, change_at, seed, duration)
        return {"name": name}

    monkeypatch.setattr(cb, "run_case", run_case)
    monkeypatch.setattr(cb, "random_plants", lambda *a, **k: {})
    cb.control_bench(cases=20, repeats=0)
    assert len(ran) == 24
    for label, case in ran.items():
        assert cb.bench_case(label.split(":")[0]) == case
    with pytest.raises(ValueError, match="'case 21'.*case 1'..'case 20'.*I2 x 3"):
        cb.bench_case("case 21")


def test_summary_takes_medians_and_worsts_and_counts_what_is_missing():
    rows = [{"adaptive_over_oracle": 1.0, "change_to_redesign_s": 0.1, "adaptive": {"fallbacks": 0}},
            {"adaptive_over_oracle": 1.2, "change_to_redesign_s": None, "adaptive": {"fallbacks": 1}},
            {"adaptive_over_oracle": 1.1, "change_to_redesign_s": 0.3, "adaptive": {"fallbacks": 0}}]
    s = cb.summarize(rows)
    assert s["adaptive_over_oracle"] == {"median": pytest.approx(1.1), "worst": 1.2, "missing": 0}
    assert s["change_to_redesign_s"]["missing"] == 1 and s["change_to_redesign_s"]["worst"] == 0.3
    assert s["adaptive_fallbacks"] == 1


@pytest.mark.slow
def test_after_i2_x3_with_a_50_ms_design_the_adaptive_loop_redesigns_within_150_ms_and_tracks_like_the_oracle():
    row = cb.run_case(load("sim-load-change.toml"), "I2 x 3", {"I2": 3.0}, change_at=2.0, duration=3.0,
                      cpu_latency=False)             # a 50 ms design: the figure does not depend on this host
    assert row["change_to_redesign_s"] is not None and row["change_to_redesign_s"] <= 0.15, row
    assert row["adaptive_over_oracle"] <= 1.1 and row["adaptive_over_fixed"] <= 0.7, row
    assert row["adaptive"]["fallbacks"] == 0 and row["adaptive"]["stop"] is None


def test_first_response_is_the_earlier_of_the_change_detector_and_a_model_design_switched_in_or_kept():
    control = {"events": [{"t": 1.0, "kind": "change detected"}, {"t": 4.0037, "kind": "change detected"},
                          {"t": 4.2, "kind": "accepted"}],
               "applied": [_applied(0.2, "model"), _applied(4.002, "conservative"), _applied(4.09, "model")]}
    assert cb.first_response(control, 4.0) == pytest.approx(0.0037)
    assert cb.first_response({"events": [], "applied": [_applied(4.077, "model")]}, 4.0) == pytest.approx(0.077)
    assert cb.first_response({"events": [], "applied": [_applied(4.08, "kept")]}, 4.0) == pytest.approx(0.08)
    assert cb.first_response({"events": [{"t": 1.0, "kind": "change detected"}], "applied": []}, 4.0) is None


def test_the_max_error_target_names_each_case_over_it_with_the_late_oracles_figure():
    def row(name, a_max, late=None, resp=None):
        return {"name": name, "factors": {"I2": 2.0}, "adaptive_over_oracle_max": a_max, "adaptive_over_fixed": 0.5,
                "late_oracle_over_oracle_max": late, "first_response_s": resp}
    rows = [row("case 1", 1.2), row("case 2", 2.95, 2.43, 0.0037)]
    summary = {"change_to_redesign_s": {"median": 0.1, "worst": 0.2, "missing": 0},
               "adaptive_over_oracle": {"median": 1.0, "worst": 1.1}, "stops": 0, "adaptive_fallbacks": 0}
    result = {"control": {"summary": summary, "scenarios": rows, "cases": [], "perturbed": [],
                          "random_plants": {"n": 1, "unstable": 0}}}
    (line,) = [t for t in cb.targets(result) if t[0].startswith("adaptive max error")]
    said = "case 2: 2.95, the oracle's design switched in 3.7 ms after the change (the adaptive loop's first act) 2.43"
    assert line[1] is False and said in line[2]
    assert "case 1" not in line[2]


def test_the_adaptive_against_fixed_target_prints_the_digits_that_decide_it():
    def result(ratio):
        r = {"name": "K x 0.6", "factors": {"K": 0.6}, "adaptive_over_oracle_max": 1.0, "adaptive_over_fixed": ratio,
             "fixed": {"rms_error_m": 1.0}, "oracle": {"rms_error_m": 1.0}}
        summary = {"change_to_redesign_s": {"median": 0.1, "worst": 0.2, "missing": 0},
                   "adaptive_over_oracle": {"median": 1.0, "worst": 1.1}, "stops": 0, "adaptive_fallbacks": 0}
        return {"control": {"summary": summary, "scenarios": [r], "cases": [], "perturbed": [],
                            "random_plants": {"n": 1, "unstable": 0}}}

    def line(ratio):
        (t,) = [t for t in cb.targets(result(ratio)) if t[0].startswith("adaptive <= fixed")]
        return t
    assert line(0.99968)[1] is True and "worst 0.99968 of 1" in line(0.99968)[2]
    assert line(1.00005)[1] is False and "worst 1.00005 of 1" in line(1.00005)[2]


def test_after_k_x06_the_adaptive_loop_keeps_its_design_checked_on_the_new_estimate():
    row = cb.run_case(load("sim-load-change.toml"), "K x 0.6", {"K": 0.6}, change_at=2.0, duration=2.6,
                      modes=("adaptive",), cpu_latency=False)
    rd = row["adaptive"]["redesigns"]
    assert rd["kept"] >= 1 and row["change_to_redesign_s"] is not None and row["change_to_redesign_s"] <= 0.15, row
    assert row["adaptive"]["fallbacks"] == 0 and row["adaptive"]["stop"] is None
    out = cb.run_offline(cb._with_mode(cb.scenario_config(load("sim-load-change.toml"), {"K": 0.6}, change_at=2.0,
                                                          duration=2.6), "adaptive"), error_after_s=2.0)
    applied = out["control"]["applied"]
    assert [a for a in applied if a["t"] >= 2.0 and a["kind"] == "kept"], applied
    assert not [a for a in applied if a["t"] >= 2.0 and a["kind"] == "model"], applied   # no switch after it


def test_the_run_summary_counts_the_results_that_kept_the_design_in_force():
    from rt_ident.outputs.terminal import kept

    assert kept({"accepted": 2, "kept": 3}) == " (3 more kept the design in force)"
    assert kept({"accepted": 2, "kept": 0}) == "" and kept({"accepted": 2}) == ""

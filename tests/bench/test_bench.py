"""The benchmark library runs on tiny sizes and every peer answers the same question the same way.

Never asserts a timing: only that the numbers exist, are positive, and that answers agree.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from rt_ident.bench import kernels as bench
from rt_ident.bench.kernels import bench_ls, bench_rls, bench_sim, filterpy_rls, numpy_rls, rls_data
from rt_ident.bench.loop import _saturated, _steady_ok, loop_trial, trial_config
from rt_ident.bench.report import print_report
from rt_ident.config import from_mapping
from rt_ident.estimators.rls import RecursiveLeastSquares


def test_every_rls_peer_gives_our_answer_and_the_batch_ls_answer_on_the_same_data():
    Phi, Y = rls_data(300, seed=3)
    p0 = 1e6
    ours = {}
    for form in ("ud", "covariance"):
        est = RecursiveLeastSquares(5, 4, p0=p0, form=form)
        est.update_block(Phi, Y)
        ours[form] = np.array(est.theta)
    peers = {"numpy": numpy_rls(Phi, Y, p0), "filterpy": filterpy_rls(Phi, Y, p0)}
    if bench._padasip_version() is not None:
        peers["padasip"] = bench.padasip_rls(Phi, Y, p0)
    ls = np.linalg.lstsq(Phi, Y, rcond=None)[0]
    scale = np.abs(ls).max()
    for name, theta in {**ours, **peers}.items():
        assert np.abs(theta - ours["ud"]).max() <= 1e-9 * scale, name     # same recursion, same P0
        assert np.abs(theta - ls).max() <= 1e-6 * scale, name             # Theorem 1: -> batch LS


def test_bench_rls_on_tiny_sizes_reports_rates_ratios_and_distances_to_batch_ls():
    out = bench_rls(m_block=400, m_sample=100, m_peer=60, repeats=1)
    names = [r["name"] for r in out["rows"]]
    assert names[:3] == ["ours update_block (ud)", "ours update_block (covariance)", "ours update, per sample (ud)"]
    assert any(n.startswith("filterpy") for n in names) and any(n.startswith("numpy lstsq") for n in names)
    assert any(n.startswith("padasip") for n in names) == (out["padasip"] is not None)
    for r in out["rows"]:
        assert r["per_s"] > 0 and r["ours_block_x"] > 0 and r["ours_update_x"] > 0
        assert 0.0 <= r["rel_diff"] < 1e-6
    assert set(out["targets"]) >= {"block >= 20 M samples/s", "update <= 2 us"}


def test_bench_rls_without_padasip_says_so_and_skips_that_peer(monkeypatch):
    monkeypatch.setattr(bench, "_padasip_version", lambda: None)
    out = bench_rls(m_block=200, m_sample=50, m_peer=30, repeats=1)
    assert out["padasip"] is None
    assert not any(r["name"].startswith("padasip") for r in out["rows"])
    assert out["targets"]["block >= 150x padasip"] is None


def test_bench_sim_on_tiny_sizes_and_the_peers_reproduce_our_trajectories():
    out = bench_sim(n_steps=3000, n_peer=400, repeats=1)
    rows = {r["name"]: r for r in out["rows"]}
    assert rows["newmark interpreted loop (compiled=False)"]["rel_diff"] < 1e-10
    assert rows["zoh interpreted loop (compiled=False)"]["rel_diff"] < 1e-10
    assert rows["scipy.signal.dlsim (ZOH model)"]["rel_diff"] < 1e-9
    assert rows["scipy.signal.lsim (interp=False)"]["rel_diff"] < 1e-9
    assert all(r["per_s"] > 0 and r["newmark_x"] > 0 and r["zoh_x"] > 0 for r in out["rows"])


def test_bench_ls_on_the_paper_regressor_agrees_with_numpy():
    out = bench_ls(periods=2, repeats=1)
    assert out["shape"] == [1023, 5]
    assert out["rows"][0]["rel_diff"] < 1e-8
    assert out["time_ratio_ours_over_numpy"] > 0


@pytest.mark.parametrize("rate", [34_000, 250_000, 1_000_000])
def test_loop_trial_config_is_valid_and_keeps_the_excitation_spectrum(rate):
    m = trial_config(rate, 2.0, "rrd")
    cfg = from_mapping(m)
    assert cfg.backend.options()["sample_period"] == pytest.approx(1.0 / rate)
    assert cfg.loop.realtime and not cfg.recording.enabled and cfg.telemetry.sink == "rrd"
    fundamental = rate / cfg.excitation.period_samples
    assert 60.0 < fundamental < 70.0                                  # ~66 Hz, as in configs/sim.toml


def test_trial_classification_separates_startup_stalls_spikes_and_saturation():
    base = {"rate": 1e5, "samples_per_s": 1e5, "ticks": 3000, "stop_cause": None}
    assert _steady_ok({**base, "overruns": 1, "overruns_first_1s": 1}) and not _saturated({**base, "overruns": 1})
    assert not _steady_ok({**base, "overruns": 2, "overruns_first_1s": 1})
    assert _saturated({**base, "samples_per_s": 0.5e5, "overruns": 0})
    assert _saturated({**base, "overruns": 100})
    assert _saturated({**base, "overruns": 0, "stop_cause": "watchdog"})


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_one_short_loop_trial_runs_in_a_subprocess_and_reports_rss():
    res = loop_trial(34_000, 0.3, "off")
    assert "error" not in res, res.get("error")
    assert res["ticks"] == 300 and res["samples"] > 0
    assert res["rss_kb"]["first_tick_kb"] > 0 and res["rss_kb"]["last_tick_kb"] > 0
    assert res["lateness_us"]["p50"] >= 0.0


def _tiny_main(monkeypatch, capsys, json_out: bool) -> tuple[dict, str]:
    monkeypatch.setattr(bench, "bench_rls", functools.partial(bench_rls, m_block=200, m_sample=50, m_peer=30))
    monkeypatch.setattr(bench, "bench_sim", functools.partial(bench_sim, n_steps=1000, n_peer=100))
    monkeypatch.setattr(bench, "bench_ls", functools.partial(bench_ls, periods=2))
    out = bench.bench_main(json_out=json_out, quick=True, loop_seconds=0.0, repeats=1)
    return out, capsys.readouterr().out


def test_bench_main_json_prints_the_returned_data(monkeypatch, capsys):
    out, text = _tiny_main(monkeypatch, capsys, json_out=True)
    doc = json.loads(text)
    assert set(doc) >= {"machine", "rls", "sim", "ls", "loop"}
    assert doc["loop"] == {"skipped": True}
    assert doc["machine"]["cores"] == out["machine"]["cores"] >= 1
    assert len(doc["rls"]["rows"]) == len(out["rls"]["rows"])


def test_bench_main_tables_name_the_machine_and_every_section(monkeypatch, capsys):
    out, text = _tiny_main(monkeypatch, capsys, json_out=False)
    for needle in (out["machine"]["cpu"][:20], "RLS, 5 regressors x 4 outputs", "Simulation of Eq. (3)",
                   "Batch LS", "Speed and capacity targets"):
        assert needle in text


def test_report_renders_loop_trials_and_the_largest_clean_rates(capsys):
    trial = {"rate": 34_000, "sink": "rrd", "seconds": 3.0, "ok": False, "overruns": 1, "overruns_first_1s": 1,
             "ticks": 3000, "samples": 102_000, "samples_per_s": 34_000.0, "lost_samples": 0,
             "lateness_us": {"p50": 0.1, "p99": 9.0, "max": 800.0}, "long_gaps_ms": [[46, 4.4]],
             "telemetry_dropped": 0, "rss_kb": {"first_tick_kb": 600_000, "last_tick_kb": 606_000},
             "rss_growth_pct": 1.0, "attempt": 0}
    result = {"machine": bench.machine_info(), "repeats": 1, "rls": {"rows": [], "targets": {}, "padasip": "x"},
              "sim": {"dt": 1e-5, "rows": [], "targets": {}},
              "ls": {"rows": [], "shape": [10, 5], "cond_scaled": 1.0, "time_ratio_ours_over_numpy": 1.0,
                     "targets": {}},
              "loop": {"seconds": 3.0, "method": "frequency", "trials": [trial],
                       "max_clean_rate": {"rrd": None}, "max_clean_after_startup_rate": {"rrd": 34_000},
                       "max_sustained_rate": {"rrd": 34_000}, "targets": {"t": False}}}
    print_report(result)
    text = capsys.readouterr().out
    assert "4.4 @46" in text
    assert "largest rate with 0 overruns after the first second: telemetry rrd: 34 ksamples/s" in text


def test_soak_calls_rss_flat_only_within_five_percent(monkeypatch):
    from rt_ident.bench import loop as bench_loop

    for growth, flat in ((4.9, True), (-4.9, True), (5.1, False), (None, None)):
        monkeypatch.setattr(bench_loop, "loop_trial", lambda *a, g=growth, **k: {"rss_growth_pct": g, "ok": True})
        assert bench_loop.soak(1.0, 1000, "off")["rss_flat_within_5pct"] is flat


def test_bench_soak_command_prints_the_memory_table(monkeypatch):
    from typer.testing import CliRunner

    from rt_ident.bench import loop as bench_loop
    from rt_ident.cli import app

    fake = {"ok": True, "samples_per_s": 170001.0, "overruns": 0, "overruns_first_1s": 0,
            "lateness_us": {"p50": 0.1, "p99": 9.0, "max": 300.0}, "telemetry_dropped": 0,
            "rss_kb": {"first_tick_kb": 512000, "last_tick_kb": 513024}, "rss_growth_pct": 0.2,
            "rss_growth_after_10pct_pct": 0.1}
    monkeypatch.setattr(bench_loop, "loop_trial", lambda *a, **k: dict(fake))
    res = CliRunner().invoke(app, ["bench", "soak", "5", "--rate", "170000"])
    assert res.exit_code == 0, res.output
    assert "RSS flat within +-5 %" in res.output and "True" in res.output and "500.0" in res.output


@pytest.mark.parametrize(("args", "says"), [
    (["--rate", "1e12"], "--rate: 1e+12 samples/s makes a run config that is refused (excitation.period_samples"),
    (["--sink", "foo"], "--sink must be rrd or off, got 'foo'"),
], ids=["rate", "sink"])
def test_bench_soak_refuses_what_its_run_would_refuse_naming_the_option_before_starting_it(monkeypatch, args, says):
    from typer.testing import CliRunner

    from rt_ident.bench import loop as bench_loop
    from rt_ident.cli import app

    monkeypatch.setattr(bench_loop, "loop_trial", lambda *a, **k: pytest.fail("a trial was started"))
    res = CliRunner().invoke(app, ["bench", "soak", "5", *args])
    assert res.exit_code != 0 and says in str(res.exception), (res.output, res.exception)


def test_bench_loop_rates_option_is_parsed_sorted_and_bad_values_are_refused(monkeypatch):
    from typer.testing import CliRunner

    from rt_ident.bench import kernels as bench_mod
    from rt_ident.cli import app

    seen = {}
    monkeypatch.setattr(bench_mod, "bench_main", lambda **kw: seen.update(kw))
    res = CliRunner().invoke(app, ["bench", "kernels", "--loop-rates", "170000, 34000"])
    assert res.exit_code == 0, res.output
    assert seen["loop_rates"] == (34000, 170000)
    for bad in ("fast", "0,170000"):
        res = CliRunner().invoke(app, ["bench", "kernels", "--loop-rates", bad])
        assert res.exit_code != 0 and "--loop-rates" in res.output + str(res.exception)


def test_soak_reports_every_helper_process_and_flags_one_that_grows():
    from rt_ident.bench.loop import _helper_growth

    series = [(t, {"11": 100_000, "12": 100_000 + 50 * t, "13": 20_000}) for t in range(0, 20_000, 1000)]
    out = _helper_growth({"helpers_rss": series, "helper_processes": {"pids": [12, 11]}})
    assert set(out) == {"telemetry", "recorder", "pid 13"}          # named by the run's helper order
    assert out["recorder"]["growth_after_10pct_pct"] == 0.0
    assert out["telemetry"]["growth_after_10pct_pct"] > 50.0         # 100 -> 195 MB: a leak shows


def test_soak_names_helpers_by_pid_when_there_is_no_recorder():
    """Recording off (as in the soak): the fit process is the second helper, not a recorder."""
    from rt_ident.bench.loop import _helper_growth

    series = [(t, {"11": 100_000, "12": 100_000, "13": 20_000}) for t in range(0, 20_000, 1000)]
    out = _helper_growth({"helpers_rss": series, "helper_processes": {
        "pids": [11, 12, 13], "names": {"11": "telemetry", "12": "fit", "13": "control"}}})
    assert set(out) == {"telemetry", "fit", "control"}

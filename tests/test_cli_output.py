"""What the CLI says: why an estimate is (not) trusted, units, 80 columns, one-line file hints,
--version, flags without a <bool> value, the FRF view a fit carries."""

from __future__ import annotations

import io

import numpy as np
import pytest
from rich.console import Console

from rt_ident import cli
from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.integrators import Newmark
from rt_ident.axis.params import thomson_x
from rt_ident.estimators.frequency import fit_frequency
from rt_ident.outputs import terminal


def _data(periods: int = 4, noise: float = 0.0):
    p, dt = thomson_x(), 2.9481e-5
    u = schroeder_multisine(512, (1, 60), peak=1.0).periodic(periods)
    tr = Newmark().simulate(p, u, dt)
    rng = np.random.default_rng(0)
    return tr.theta[:, 0], tr.theta[:, 1], u + noise * rng.standard_normal(u.size), dt


def test_trusted_fit_lists_every_criterion_as_passed():
    r = fit_frequency(*_data()[:3], _data()[3], hold="tustin")
    t = r.as_dict()["trust"]
    assert t["trusted"] is True and t["reasons"] == []
    names = [c["criterion"] for c in t["criteria"]]
    assert any("converged" in n for n in names) and any("eigenvalue" in n for n in names)
    assert all(c["passed"] for c in t["criteria"])


def test_non_converged_fit_is_never_trusted_and_says_why():
    th1, th2, u, dt = _data()
    r = fit_frequency(th1, th2, u, dt, hold="zoh", max_iter=1)      # wrong hold, one iteration
    t = r.as_dict()["trust"]
    assert t["trusted"] is False
    assert any("without converging" in why for why in t["reasons"])
    failed = [c for c in t["criteria"] if not c["passed"]]
    assert failed and all(c["why"] for c in failed)


def _capture(monkeypatch, width: int = 80) -> io.StringIO:
    buf = io.StringIO()
    console = Console(file=buf, width=width, soft_wrap=True, color_system=None)
    monkeypatch.setattr(cli, "out", console)
    monkeypatch.setattr(terminal, "out", console)
    return buf


def _summary(path: str) -> dict:
    params = {"I1": 2.9481234e-05, "I2": 8.2999876e-06, "B": 0.0021234567, "K": 110.123456, "wn": 4162.5812,
              "wd": 4159.2871, "zeta": 0.0397123}
    return {"backend": "sim", "method": "frequency", "parameters": params,
            "ci95": {k: [0.98 * v, 1.02 * v] for k, v in params.items()}, "truth": params,
            "error_pct": {k: 0.0123 for k in params}, "trusted": False,
            "trust": {"trusted": False, "reasons": ["95 % interval of I2 is +-12 % (> 10 %)"],
                      "criteria": [{"criterion": "widest 95 % interval", "value": 12.0, "limit": "<= 10 %",
                                    "passed": False, "why": "95 % interval of I2 is +-12 % (> 10 %)"}]},
            "loop": {"ticks": 10, "samples": 340}, "telemetry": {"dropped": 0}, "stop": {},
            "files": {"rrd": path + ".rrd", "recording": path + ".parquet"}}


def test_run_table_has_units_and_cuts_no_value_at_80_columns(monkeypatch):
    buf = _capture(monkeypatch, 80)
    terminal.print_run(_summary("runs/x"))
    text = buf.getvalue()
    assert "…" not in text
    assert "kg m²" in text and "N m/rad" in text and "N m s/rad" in text
    assert "2.948e-05" in text and "110.1" in text
    assert "trusted: no" in text and "95 % interval of I2 is +-12 % (> 10 %)" in text


def test_the_stall_line_says_how_long_the_loop_read_the_backlog_before_re_planning(monkeypatch):
    buf = _capture(monkeypatch, 200)
    terminal.print_stalls({"stalls": {"count": 1, "longest_ms": 90.0, "catch_up_longest_ms": 15.0}})
    terminal.print_stalls({"stalls": {"count": 2, "longest_ms": 40.0, "catch_up_longest_ms": 0.0}})
    first, second = buf.getvalue().splitlines()
    assert "longest 90 ms" in first and "backlog for up to 15 ms before re-planning" in first
    assert "longest 40 ms" in second and "backlog" not in second


@pytest.mark.parametrize("terminated", [False, True])
def test_the_loop_line_says_when_the_dashboards_process_had_to_be_ended(monkeypatch, terminated):
    buf = _capture(monkeypatch, 200)
    s = _summary("runs/x")
    s["telemetry"] = {"dropped": 466, "terminated": terminated}
    terminal.print_run(s)
    line = next(ln for ln in buf.getvalue().splitlines() if ln.startswith("loop:"))
    assert "telemetry dropped 466" in line
    assert ("did not finish and was ended" in line) is terminated


def test_file_hints_stay_on_one_line_when_piped(monkeypatch):
    buf = _capture(monkeypatch, 80)
    long = "runs/" + "a-very-long-directory-name/" * 3 + "run-20261125-022806-5971"
    terminal.print_run(_summary(long))
    lines = buf.getvalue().splitlines()
    hint = [ln for ln in lines if ln.startswith("recording:")]
    assert len(hint) == 1 and f"rt-ident identify {long}.parquet" in hint[0]


def test_brackets_in_paths_reasons_and_stop_messages_are_printed_as_written_not_read_as_markup(monkeypatch):
    buf = _capture(monkeypatch, 200)
    ebuf = io.StringIO()
    monkeypatch.setattr(terminal, "err", Console(file=ebuf, width=200, soft_wrap=True, color_system=None))
    s = _summary("runs/[s]/rec[x]")
    s["trust"]["reasons"] = ["[axis] I2 disagrees [/red] with the fit"]
    s["stop"] = {"cause": "speed-trip", "message": "[axis] lead [s] is wrong [/]", "fix": "set [safety] max_speed"}
    terminal.print_run(s)
    text, etext = buf.getvalue(), ebuf.getvalue()
    assert "rt-ident identify runs/[s]/rec[x].parquet" in text
    assert "[axis] I2 disagrees [/red] with the fit" in text
    assert "[axis] lead [s] is wrong [/]" in etext and "fix: set [safety] max_speed" in etext


def test_the_reproduce_tables_keep_their_units_in_brackets(capsys, monkeypatch):
    wide = _capture(monkeypatch, 200)
    code, _ = _invoke(["reproduce", "--no-beyond", "--periods", "1"], capsys, monkeypatch)
    assert code == 0 and "Dt paper [s]" in wide.getvalue() and "Dt ours [s]" in wide.getvalue(), wide.getvalue()[:800]


def _invoke(args: list[str], capsys, monkeypatch) -> tuple[int, str]:
    monkeypatch.setenv("COLUMNS", "120")
    with pytest.raises(SystemExit) as e:
        cli._command().main(args=args, prog_name="rt-ident")
    return int(e.value.code or 0), capsys.readouterr().out


def test_version_prints_the_installed_version(capsys, monkeypatch):
    from importlib.metadata import version

    code, text = _invoke(["--version"], capsys, monkeypatch)
    assert code == 0 and text.strip() == f"rt-ident {version('rt-ident')}"


@pytest.mark.parametrize("command", [[], ["run"], ["identify"], ["reproduce"], ["bench", "kernels"], ["bench", "soak"]])
def test_help_shows_flags_without_a_bool_value(command, capsys, monkeypatch):
    code, text = _invoke([*command, "--help"], capsys, monkeypatch)
    assert code == 0 and "--help" in text
    assert "<bool>" not in text and "BOOLEAN" not in text


def test_a_frequency_fit_carries_its_frf_view_with_model_and_band():
    from rt_ident.axis.plant import HoldController, PlantSimulator
    from rt_ident.estimators.spectra import compute_spectra
    from rt_ident.estimators.streaming import fit_snapshot

    p, dt = thomson_x(), 2.9481e-5      # closed loop: periodic response, so Theta/T is the FRF
    ms = schroeder_multisine(512, (1, 60), peak=0.3)
    blk = PlantSimulator(p, dt, controller=HoldController(), seed=0).step_block(ms.periodic(6))
    sp = compute_spectra(blk.theta1, blk.theta2, blk.torque_meas, dt, period=512)
    r = fit_snapshot("frequency", sp, hold="zoh")
    v = r.frf
    assert v is not None and v["f_meas"].size == sp.harmonics.size
    # the model passes through the measured lines (quantized angles; the grid is interpolated, so
    # the lines next to the sharp resonance are compared loosely) ...
    d = np.abs(np.interp(np.log(v["f_meas"]), np.log(v["f_model"]), v["g1_db"]) - v["m1_db"])
    assert np.median(d) < 0.3 and np.mean(d < 1.5) >= 0.85
    # ... inside its band, and the resonance mark is the model's damped frequency
    assert np.all(v["g1_lo"] <= v["g1_db"] + 1e-9) and np.all(v["g1_db"] <= v["g1_hi"] + 1e-9)
    assert v["marks_hz"][0] == pytest.approx(r.modal["wd"] / (2 * np.pi), rel=1e-9)


def test_an_frf_view_of_a_fit_with_a_wild_covariance_never_raises():
    """A fit with absurd intervals (early in a run) can overflow in the band's parameter draws; that must
    not take the whole final fit down with it: the band collapses onto the model instead."""
    from rt_ident.axis.plant import HoldController, PlantSimulator
    from rt_ident.estimators.frf import frf_view
    from rt_ident.estimators.spectra import compute_spectra

    p, dt = thomson_x(), 2.9481e-5
    ms = schroeder_multisine(512, (1, 60), peak=0.3)
    blk = PlantSimulator(p, dt, controller=HoldController(), seed=0).step_block(ms.periodic(4))
    sp = compute_spectra(blk.theta1, blk.theta2, blk.torque_meas, dt, period=512)
    v = frf_view(sp, np.log([p.I1, p.I2, p.B, p.K]), np.eye(4) * 1e6, "zoh")
    assert all(np.all(np.isfinite(v[k])) for k in ("g1_db", "g1_lo", "g1_hi", "g2_db"))


def test_a_run_stopped_by_ctrl_c_or_sigterm_says_it_stopped_early_and_a_full_run_does_not(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(terminal, "err", Console(file=buf, width=120, soft_wrap=True, color_system=None))
    terminal.print_stop({"stop": {"cause": None, "message": None, "interrupted": True}, "loop": {"ticks": 1428}})
    terminal.print_stop({"stop": {"cause": None, "message": None, "interrupted": False}, "loop": {"ticks": 10000}})
    assert buf.getvalue().splitlines() == ["stopped early on request (Ctrl-C, SIGTERM or SIGHUP) after 1428 ticks: the "
                                           "figures above cover only that part; torque zeroed, drive disabled"]


def test_a_device_the_run_never_opened_is_not_said_to_be_disabled(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(terminal, "err", Console(file=buf, width=400, soft_wrap=True, color_system=None))
    terminal.print_stop({"stop": {"cause": "no-connection", "message": "port in use", "interrupted": False,
                                  "backend_state": "created"}})
    terminal.print_axes({"axes": {}, "stop": {"cause": "no-connection", "message": "port in use", "interrupted": False,
                                              "backend_state": {"X": "closed", "Y": "created"}}})
    terminal.print_stop({"stop": {"cause": "watchdog", "message": "late", "interrupted": False,
                                  "backend_state": "closed"}})
    assert buf.getvalue().splitlines() == [
        "stopped by no-connection: port in use - nothing energized: the device was never opened",
        "stopped by no-connection: port in use - every opened axis at zero torque, disabled; never opened: axis Y",
        "stopped by watchdog: late - torque zeroed, drive disabled"]


def test_a_device_that_did_not_confirm_its_disable_is_never_called_disabled_and_gets_a_line_of_its_own(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(terminal, "err", Console(file=buf, width=400, soft_wrap=True, color_system=None))
    note = "node 5 did not report itself disabled within 0.2 s"
    terminal.print_stop({"stop": {"cause": "watchdog", "message": "no fresh TPDO data", "interrupted": False,
                                  "disable_unconfirmed": note}})
    terminal.print_stop({"stop": {"cause": None, "message": None, "interrupted": False, "disable_unconfirmed": note}})
    terminal.print_stop({"stop": {"cause": "watchdog", "message": "no fresh TPDO data", "interrupted": False}})
    lines = buf.getvalue().splitlines()
    assert lines[0] == ("stopped by watchdog: no fresh TPDO data - zero torque commanded, the disable NOT confirmed "
                        "(below)")
    assert lines[1].startswith(f"disable not confirmed: {note}: check the device") and lines[2] == lines[1]
    assert lines[3] == "stopped by watchdog: no fresh TPDO data - torque zeroed, drive disabled" and len(lines) == 4

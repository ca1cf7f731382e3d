"""The live torque estimate in a run's summary: Eq. (18) on the SVF's filtered derivatives against the
measured torque through the same filter."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from rt_ident.cli import app

runner = CliRunner()


def test_the_default_run_has_a_torque_estimate_nrmse_of_at_most_10_percent():
    # the run's own code, stepped without a wall clock: the figure does not depend on how busy the host is
    from rt_ident.compose.offline import run_offline
    from rt_ident.config import load

    te = run_offline(load(None, **{"loop.duration": 2.0, "telemetry.sink": "off",
                                   "recording.enabled": False}))["torque_estimate"]
    assert te["samples"] > 0 and te["nrmse_percent"] is not None, te
    assert 0.0 < te["nrmse_percent"] <= 10.0, te


def test_run_json_gives_the_torque_estimate_or_says_why_there_is_none(tmp_path, monkeypatch):
    # real time: on a busy host the first trusted fit may come after a 2 s run, and then there is no estimate
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, ["run", "--duration", "2", "--no-realtime", "--no-telemetry", "--json"])
    assert res.exit_code == 0, res.output
    te = json.loads(res.stdout)["torque_estimate"]
    if te["nrmse_percent"] is None:
        assert te["why_none"], te
    else:
        assert te["samples"] > 0 and 0.0 < te["nrmse_percent"] <= 10.0, te
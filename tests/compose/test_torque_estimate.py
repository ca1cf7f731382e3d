"""The live torque estimate in a run's summary: Eq. (18) on the SVF's filtered derivatives against the
measured torque through the same filter."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from rt_ident.cli import app

runner = CliRunner()


def test_the_default_runs_json_has_a_torque_estimate_nrmse_of_at_most_10_percent(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, ["run", "--duration", "2", "--no-realtime", "--no-telemetry", "--json"])
    assert res.exit_code == 0, res.output
    te = json.loads(res.stdout)["torque_estimate"]
    assert te["samples"] > 0 and te["nrmse_percent"] is not None, te
    assert 0.0 < te["nrmse_percent"] <= 10.0, te

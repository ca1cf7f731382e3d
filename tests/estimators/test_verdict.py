"""The verdict never lies: "trusted: yes" only when every criterion was evaluated and passed.

Each test is a way a result could be more optimistic than its evidence: a criterion that cannot be
evaluated left out, an impossible value or a bad fit passing, a failed validation not counting.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from rt_ident.axis.params import thomson_x
from rt_ident.cli import app
from rt_ident.estimators.uncertainty import (
    build_identification,
    excitation_report,
    excited_bands,
    interval_criterion,
    resonance_criterion,
)
from rt_ident.reports.identify import identify_file

runner = CliRunner()
DT = 2.9481e-5


def _good_pe():
    return excitation_report([np.random.default_rng(0).standard_normal((200, 3))])


def _run_recording(path, seconds: float = 1.0):
    """A recording of the default sim run, made by the loop's own code on virtual time."""
    from rt_ident.compose.offline import run_offline
    from rt_ident.config import load

    cfg = load(None, **{"loop.realtime": False, "telemetry.sink": "off", "recording.enabled": False,
                        "loop.duration": seconds})
    out = run_offline(cfg, record=str(path), overwrite=True)
    assert out["stop"] is None, out["stop"]
    return path


def _misreport_lead(src, dst, factor: float = 2.0):
    """The table's scale converted with ``factor`` x the lead: theta2 = x / (factor lead), and the
    metadata says that lead."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    t = pq.read_table(src)
    md = dict(t.schema.metadata)
    meta = json.loads(md[b"rt_ident.metadata"])
    meta["axis"]["lead"] *= factor
    md[b"rt_ident.metadata"] = json.dumps(meta).encode()
    t = t.set_column(t.schema.get_field_index("theta2"), "theta2", pc.divide(t.column("theta2"), factor))
    pq.write_table(t.replace_schema_metadata(md), dst)
    return dst


# --------------------------------------------------------------------------- intervals
def test_missing_interval_fails_trust_instead_of_being_dropped():
    p = thomson_x()
    r = build_identification(p, "x", None, _good_pe(), bands=[(100.0, 1e4)])
    assert not r.trusted
    c = [c for c in r.trust_criteria if c["criterion"].startswith("widest 95 % interval")]
    assert len(c) == 1 and not c[0]["passed"] and "no interval" in c[0]["why"]


@pytest.mark.parametrize("bad,what", [((math.nan, 1.0), "not finite"), ((0.0, math.inf), "not finite"),
                                      ((2.0, 0.5), "negative width"), (None, "no interval")])
def test_nan_infinite_and_negative_width_intervals_fail_the_interval_criterion(bad, what):
    values = {"I1": 1.0, "I2": 1.0}
    ci = {"I1": (0.99, 1.01)}
    if bad is not None:
        ci["I2"] = bad
    c = interval_criterion(values, ci)
    assert not c["passed"] and what in c["why"] and "I2" in c["why"]
    assert interval_criterion(values, {"I1": (0.99, 1.01), "I2": (0.98, 1.02)})["passed"]


def test_an_infinite_covariance_fails_the_interval_criterion():
    p = thomson_x()
    cov = np.diag([1e-6, np.inf, 1e-6, 1e-6])
    r = build_identification(p, "x", cov, _good_pe(), bands=[(100.0, 1e4)])
    assert not r.trusted and any("I2" in why and "not finite" in why for why in r.reasons)


def test_identify_on_a_lead_doubled_recording_is_not_trusted(tmp_path):
    good = _run_recording(tmp_path / "run.parquet")
    bad = _misreport_lead(good, tmp_path / "lead2.parquet")
    r_good, _ = identify_file(good)
    assert r_good.trusted, r_good.reasons
    r, info = identify_file(bad)
    assert info["how"].startswith("replay")
    assert not r.trusted
    why = " | ".join(r.reasons)
    assert "interval" in why and "resonance" in why and "chi2" in why, why
    res = runner.invoke(app, ["identify", str(bad)])
    assert res.exit_code == 0, res.output
    assert "trusted: no" in res.stdout and "trusted: yes" not in res.stdout
    d = json.loads(runner.invoke(app, ["identify", str(bad), "--json"]).stdout)
    assert d["trusted"] is False and d["trust"]["reasons"]
    crit = {c["criterion"]: c for c in d["trust"]["criteria"]}
    assert not crit["widest 95 % interval of I1, I2, B, K (half-width, relative)"]["passed"]


# --------------------------------------------------------------------------- resonance
def test_a_resonance_outside_the_excited_band_fails():
    assert resonance_criterion(4163.0, [(416.0, 8325.0)])["passed"]
    out = resonance_criterion(8.7e4, excited_bands(416.0, 8325.0, DT))
    assert not out["passed"] and "outside the excited band" in out["why"]
    assert not resonance_criterion(4163.0, None)["passed"]          # unknown band: cannot pass
    assert not resonance_criterion(math.nan, [(1.0, 1e9)])["passed"]


def test_a_mode_above_nyquist_still_counts_as_excited_through_the_hold_image():
    # 1 kHz bus, lines 15.6..496 Hz: the held torque also drives 504..984 Hz, where X's 662 Hz mode is
    w_lo, w_hi = 2 * math.pi * 15.6, 2 * math.pi * 496.0
    wn = 2 * math.pi * 662.0
    assert not resonance_criterion(wn, excited_bands(w_lo, w_hi))["passed"]
    assert resonance_criterion(wn, excited_bands(w_lo, w_hi, 1e-3))["passed"]

"""`rt-ident identify` as a user runs it: a CSV from someone else's bench, no metadata."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.modal import modal_parameters
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.cli import app

runner = CliRunner()


def bench_csv(path, p, rate, *, seed, periods=10, N=2048):
    """Angles-only, quantized, closed-loop recording; the band is a fixed wide one around the nominal
    Table 1 resonance (0.05..4 x 662 Hz, capped at 0.6 x Nyquist), not designed for this plant."""
    dt = 1.0 / rate
    f0 = rate / N
    wn_nominal_hz = modal_parameters(thomson_x())["wn"] / (2 * np.pi)
    lo = max(1, int(0.05 * wn_nominal_hz / f0))
    hi = min(int(4 * wn_nominal_hz / f0), int(0.6 * (N // 2)))
    ms = schroeder_multisine(N, (lo, hi), peak=0.3)
    torque_cmd = ms.periodic(periods)
    rms = float(np.sqrt(np.mean(torque_cmd**2)))
    plant = PlantSimulator(p, dt, sensors=SensorConfig(counts_per_rev=2**17, scale_resolution=1e-7,
                                                       torque_meas_noise=0.005 * rms),
                           controller=HoldController(), torque_limit=2.0, seed=seed)
    blk = plant.step_block(torque_cmd)
    t = np.arange(len(torque_cmd)) * dt
    # a user's export: different column order, an extra column, no omega
    np.savetxt(path, np.column_stack([t, blk.torque_meas, blk.theta2, blk.theta1, blk.torque_cmd]),
               delimiter=",", header="t,torque,theta2,theta1,command", comments="")


@pytest.mark.parametrize("seed,rate", [(11, 12_000.0), (12, 25_000.0)])
def test_identify_csv_from_untuned_plant_and_rate_within_one_percent(tmp_path, seed, rate):
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.5, 2.0, size=4)
    base = thomson_x()
    p = base.with_(I1=base.I1 * s[0], I2=base.I2 * s[1], B=base.B * s[2], K=base.K * s[3])
    f = tmp_path / "bench.csv"
    bench_csv(f, p, rate, seed=seed)
    res = runner.invoke(app, ["identify", str(f), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert d["method"] == "frequency" and d["input"]["how"] == "batch"
    for k in ("I1", "I2", "B", "K"):
        err = abs(d["parameters"][k] / getattr(p, k) - 1)
        assert err < 0.01, (k, err, s)


def test_methods_list_names_default_first():
    res = runner.invoke(app, ["identify", "--methods", "--json"])
    assert res.exit_code == 0
    names = json.loads(res.stdout)
    assert names[0] == "frequency" and {"tustin", "zoh", "paper"} <= set(names)


def test_methods_table_says_when_to_use_each():
    res = runner.invoke(app, ["identify", "--methods"])
    assert res.exit_code == 0 and "default" in res.stdout and "zero-order-hold" in res.stdout


def test_missing_file_is_a_clear_error(tmp_path):
    res = runner.invoke(app, ["identify", str(tmp_path / "none.csv")])
    assert res.exit_code != 0
    assert "none.csv" in str(res.exception) or "none.csv" in res.output


def test_csv_missing_a_column_names_it(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("t,theta1,torque\n" + "\n".join(f"{i*1e-4},{i*1e-3},0.1" for i in range(50)))
    res = runner.invoke(app, ["identify", str(f)])
    assert res.exit_code != 0
    assert "theta2" in str(res.exception)


def test_unknown_method_lists_the_valid_ones(tmp_path):
    f = tmp_path / "b.csv"
    bench_csv(f, thomson_x(), 20_000.0, seed=1, periods=3, N=512)
    res = runner.invoke(app, ["identify", str(f), "--method", "magic"])
    assert res.exit_code != 0
    assert "frequency" in str(res.exception)


def test_absurd_torque_and_non_utf8_csv_are_one_line_errors_not_tracebacks(tmp_path):
    import subprocess
    import sys

    big = tmp_path / "big.csv"
    bench_csv(big, thomson_x(), 12_000.0, seed=3, periods=3)
    rows = np.loadtxt(big, delimiter=",", skiprows=1)
    rows[:, 1] *= 1e300                                   # torque x 1e300 (a unit mix-up gone wild)
    np.savetxt(big, rows, delimiter=",", header="t,torque,theta2,theta1,command", comments="")
    latin = tmp_path / "latin.csv"
    latin.write_bytes(b"t,theta1,theta2,torque\n" + "0,1,2,\xe9\n".encode("latin-1"))
    for f, needle in ((big, "beyond any plausible value"), (latin, "not UTF-8")):
        p = subprocess.run([sys.executable, "-m", "rt_ident", "identify", str(f)], capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 2, p.stderr
        assert needle in p.stderr and "Traceback" not in p.stderr and "Warning" not in p.stderr, p.stderr

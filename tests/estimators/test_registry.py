"""Registry and shared types: identify(), IdentData validation, Identification.as_dict()."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.integrators import Newmark, ZeroOrderHold
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.base import Identification
from rt_ident.estimators.registry import DEFAULT_METHOD, METHODS, IdentData, MethodInfo, identify, list_methods


def _bench_record() -> tuple[IdentData, int]:
    """A 4 kHz closed-loop quantized recording, as a user would bring from the bench."""
    dt, N = 2.5e-4, 512
    ms = schroeder_multisine(N, (9, 153), peak=0.3)
    sensors = SensorConfig(counts_per_rev=2**17, scale_resolution=1e-7, torque_meas_noise=0.005 * ms.rms)
    blk = PlantSimulator(thomson_x(), dt, sensors=sensors, controller=HoldController(), seed=4).step_block(
        ms.periodic(9))
    t = np.arange(blk.theta1.size) * dt
    return IdentData(t, blk.theta1, blk.theta2, blk.torque_meas), N


def _newmark_record() -> IdentData:
    dt = 2.9481e-5
    u = schroeder_multisine(512, (1, None), peak=1.0).periodic(4)
    tr = Newmark().simulate(thomson_x(), u, dt)
    return IdentData(None, tr.theta[:, 0], tr.theta[:, 1], u, omega1=tr.omega[:, 0], omega2=tr.omega[:, 1],
                     dt=dt)


def _rel_err(r: Identification) -> float:
    p = thomson_x()
    return max(abs(r.value(k) / getattr(p, k) - 1.0) for k in ("I1", "I2", "B", "K"))


def test_default_method_is_frequency_and_handles_a_bench_recording():
    data, N = _bench_record()
    assert DEFAULT_METHOD == "frequency" and list_methods()[0].name == "frequency"
    r = identify(data)
    assert r.method == "frequency" and r.trusted
    assert _rel_err(r) < 0.01
    assert r.diagnostics["period_samples"] == N


def test_tustin_uses_states_when_present_and_angles_otherwise():
    data = _newmark_record()
    with_states = identify(data, "tustin")
    angles = identify(data, "tustin", use_states=False)
    assert _rel_err(with_states) < 1e-8 and _rel_err(angles) < 1e-8
    assert with_states.diagnostics["n_rows"] != angles.diagnostics["n_rows"]   # different regressions


def test_zoh_method_exact_and_requires_velocities():
    p, dt = thomson_x(), 2.5e-4
    u = schroeder_multisine(256, (1, None), peak=0.5).periodic(4)
    tr = ZeroOrderHold().simulate(p, u, dt)
    data = IdentData(None, tr.theta[:, 0], tr.theta[:, 1], u, omega1=tr.omega[:, 0], omega2=tr.omega[:, 1],
                     dt=dt)
    assert _rel_err(identify(data, "zoh")) < 1e-8
    with pytest.raises(DataError, match="omega"):
        identify(IdentData(None, tr.theta[:, 0], tr.theta[:, 1], u, dt=dt), "zoh")


def test_paper_method_runs_but_is_never_trusted():
    r = identify(_newmark_record(), "paper")
    assert r.method == "paper" and not r.trusted and r.ci95 is None
    assert _rel_err(r) > 1e-3            # forward Euler on Newmark data is biased


def test_unknown_method_and_option_raise_config_error_listing_valid_names():
    data = _newmark_record()
    with pytest.raises(ConfigError, match="frequency, tustin, zoh, paper"):
        identify(data, "kalman")
    with pytest.raises(ConfigError, match="options.forgeting"):
        identify(data, "tustin", forgeting=0.9)
    with pytest.raises(ConfigError, match="data"):
        identify({"theta1": []})       # type: ignore[arg-type]


def test_methods_registry_is_read_only_and_described():
    assert set(METHODS) >= {"frequency", "tustin", "zoh", "paper"}
    for info in list_methods():
        assert isinstance(info, MethodInfo) and info.summary and info.needs in ("angles", "states")
    with pytest.raises(TypeError):
        METHODS["x"] = METHODS["zoh"]    # type: ignore[index]


def test_identdata_infers_dt_and_rejects_non_uniform_sampling():
    n = 100
    x = np.zeros(n)
    t = np.arange(n) * 1e-3
    assert IdentData(t, x, x, x).dt == pytest.approx(1e-3)
    jitter = t + 1e-7 * np.random.default_rng(0).standard_normal(n)        # 1e-4 relative: accepted
    assert IdentData(jitter, x, x, x).dt == pytest.approx(1e-3, rel=1e-4)
    gap = t.copy()
    gap[50:] += 2e-3
    with pytest.raises(DataError, match="non-uniform sampling"):
        IdentData(gap, x, x, x)
    assert IdentData(None, x, x, x, dt=2e-3).t[-1] == pytest.approx(99 * 2e-3)


def test_identdata_rejects_malformed_records():
    x = np.zeros(50)
    with pytest.raises(DataError, match="theta2: length"):
        IdentData(None, x, x[:40], x, dt=1e-3)
    bad = x.copy()
    bad[7] = np.inf
    with pytest.raises(DataError, match="torque: non-finite value at sample 7"):
        IdentData(None, x, x, bad, dt=1e-3)
    with pytest.raises(DataError, match="omega1/omega2"):
        IdentData(None, x, x, x, omega1=x, dt=1e-3)
    with pytest.raises(DataError, match="t/dt"):
        IdentData(None, x, x, x)
    with pytest.raises(DataError, match="dt: given"):
        IdentData(np.arange(50) * 1e-3, x, x, x, dt=2e-3)
    with pytest.raises(ConfigError, match="period"):
        IdentData(None, x, x, x, dt=1e-3, period=1)


def test_as_dict_is_json_friendly_with_all_keys():
    r = identify(_newmark_record(), "tustin")
    d = json.loads(json.dumps(r.as_dict()))
    assert set(d["parameters"]) == {"I1", "I2", "B", "K", "wn", "wd", "zeta"}
    assert set(d["ci95"]) == {"I1", "I2", "B", "K", "wn", "wd", "zeta"}
    assert d["method"] == "tustin" and d["trusted"] is True
    assert d["parameters"]["K"] == pytest.approx(110.0, rel=1e-8)
    lo, hi = d["ci95"]["wn"]
    assert lo <= d["parameters"]["wn"] <= hi
    inf_diag = Identification(r.params, "x", None, r.modal, False, {"cond": math.inf}).as_dict()
    assert inf_diag["diagnostics"]["cond"] is None and inf_diag["ci95"] is None

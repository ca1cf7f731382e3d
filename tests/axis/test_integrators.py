"""Tests of rt_ident.axis.integrators: accuracy orders, Newmark's period error, conservation laws, API."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

from rt_ident.axis.integrators import (
    INTEGRATORS,
    Houbolt,
    Newmark,
    RungeKutta4,
    Trajectory,
    WilsonTheta,
    ZeroOrderHold,
    equilibrium_acceleration,
    get_integrator,
    zoh_matrices,
)
from rt_ident.axis.kernels import (
    linear_recursion,
    trajectory_recursion,
    trajectory_recursion_py,
)
from rt_ident.axis.model import natural_frequency, state_space
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.errors import ConfigError, DataError

P = thomson_x()
DT_CASE1 = 2.9481e-5  # Table 2, N = 512, k = 10
X0 = np.array([1e-3, 0.5, -2e-3, -1.0])


def _multisine(n: int, dt: float, amp: float = 0.05, seed: int = 1) -> np.ndarray:
    """Zero-mean sum of sines, 20 Hz .. 2 kHz, random phases."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    f = np.arange(20.0, 2000.0, 20.0)
    ph = rng.uniform(0, 2 * np.pi, f.size)
    return amp * np.sin(2 * np.pi * np.outer(t, f) + ph).sum(axis=1) / np.sqrt(f.size)


def _rel_err_per_state(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.max(np.max(np.abs(x - ref), axis=0) / np.max(np.abs(ref), axis=0)))


def _exact_free(p: AxisParams, x0: np.ndarray, t: np.ndarray) -> np.ndarray:
    A, _ = state_space(p)
    return np.array([scipy.linalg.expm(A * tk) @ x0 for tk in t])


# --------------------------------------------------------------------------- compiled vs reference
@pytest.mark.parametrize("name", INTEGRATORS)
def test_compiled_kernel_matches_python_reference(name: str) -> None:
    u = _multisine(1000, DT_CASE1)
    integ = get_integrator(name)
    fast = integ.simulate(P, u, DT_CASE1, X0).states()
    ref = integ.simulate(P, u, DT_CASE1, X0, compiled=False).states()
    assert _rel_err_per_state(fast, ref) < 1e-12


def _two_pass_simulate(integ, p: AxisParams, u: np.ndarray, dt: float, x0: np.ndarray) -> Trajectory:
    """The previous compiled path, kept as a reference: (n, nz) state history from the bare
    recursion, then numpy post-processing (copies, Eq. 6 accelerations, times)."""
    ctx = integ._setup(p, dt)
    head = integ._start(ctx, x0, u)
    n = u.size
    m = min(head.shape[0], n)
    Z = np.empty((n, integ.nz))
    Z[:m] = head[:m]
    if m < n:
        S, G0, G1 = integ.recursion_matrices(p, dt)
        linear_recursion(S, G0, G1, u, Z, m - 1)
    X = Z[:, :4]
    return Trajectory(t=np.arange(n) * dt, theta=np.ascontiguousarray(X[:, [0, 2]]),
                      omega=np.ascontiguousarray(X[:, [1, 3]]), alpha=equilibrium_acceleration(p, X, u),
                      torque=u.copy())


_FIELDS = ("t", "theta", "omega", "alpha", "torque")


@pytest.mark.parametrize("name", INTEGRATORS)
def test_fused_simulate_is_bit_identical_to_the_two_pass_reference(name: str) -> None:
    integ = get_integrator(name)
    for n, x0, dt in ((3000, X0, DT_CASE1), (3000, np.zeros(4), 1e-4), (2, X0, DT_CASE1), (4, X0, DT_CASE1)):
        u = _multisine(n, dt, seed=n)
        new, ref = integ.simulate(P, u, dt, x0), _two_pass_simulate(integ, P, u, dt, x0)
        for f in _FIELDS:
            a = getattr(new, f)
            assert np.array_equal(a, getattr(ref, f)), (name, n, f)
            assert a.flags.c_contiguous and a.flags.owndata
        assert np.array_equal(new.states(), ref.states())


def test_trajectory_kernel_compiled_matches_its_interpreted_source() -> None:
    n, integ = 400, Newmark()
    u = _multisine(n, DT_CASE1)
    S, G0, G1 = integ.recursion_matrices(P, DT_CASE1)
    z0 = np.array([*X0, 3.0, -2.0])
    par = np.array([P.B, P.K, P.I1, P.I2])
    outs = []
    for kernel in (trajectory_recursion, trajectory_recursion_py):
        tr = Trajectory(np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n))
        assert kernel(S, G0, G1, u, z0, 5, DT_CASE1, par, tr.t, tr.theta, tr.omega, tr.alpha, tr.torque) == -1
        assert np.all(tr.theta[:6] == 0.0) and np.all(tr.theta[6:] != 0.0)  # rows after k0 only
        outs.append(tr)
    for f in _FIELDS:
        assert _rel_err_per_state(getattr(outs[0], f)[6:], getattr(outs[1], f)[6:]) < 1e-12
    assert outs[0].t[6] == 6 * DT_CASE1 and np.array_equal(outs[0].torque[6:], u[6:])


@pytest.mark.parametrize("compiled", [True, False])
def test_simulate_out_overwrites_and_returns_the_given_arrays(compiled: bool) -> None:
    u = _multisine(300, DT_CASE1)
    integ = Houbolt()
    out = integ.simulate(P, np.zeros(300), DT_CASE1)
    arrays = [getattr(out, f) for f in _FIELDS]
    res = integ.simulate(P, u, DT_CASE1, X0, compiled=compiled, out=out)
    assert res is out and all(getattr(res, f) is a for f, a in zip(_FIELDS, arrays))
    fresh = integ.simulate(P, u, DT_CASE1, X0, compiled=compiled)
    for f in _FIELDS:
        assert np.array_equal(getattr(res, f), getattr(fresh, f))
    # the torque array itself may serve as out.torque
    tr = Trajectory(np.empty(300), np.empty((300, 2)), np.empty((300, 2)), np.empty((300, 2)), u)
    assert np.array_equal(integ.simulate(P, u, DT_CASE1, X0, compiled=compiled, out=tr).theta, fresh.theta)


def test_simulate_out_rejects_wrong_shape_dtype_and_overlap() -> None:
    u, n = np.zeros(10), 10
    good = {"t": np.empty(n), "theta": np.empty((n, 2)), "omega": np.empty((n, 2)), "alpha": np.empty((n, 2)),
            "torque": np.empty(n)}
    shared = np.empty((n, 2))
    bad = [{**good, "theta": np.empty((n + 1, 2))}, {**good, "alpha": np.empty((n, 2), dtype=np.float32)},
           {**good, "omega": np.empty((2, n)).T}, {**good, "t": u}, {**good, "theta": shared, "omega": shared}]
    for kw in bad:
        with pytest.raises(ConfigError) as info:
            ZeroOrderHold().simulate(P, u, 1e-4, out=Trajectory(**kw))
        assert info.value.field == "out"
    with pytest.raises(ConfigError):
        ZeroOrderHold().simulate(P, u, 1e-4, out=np.empty((n, 4)))  # type: ignore[arg-type]


@pytest.mark.parametrize("name", INTEGRATORS)
def test_nonfinite_torque_anywhere_names_first_sample_and_count(name: str) -> None:
    for bad_at in ((1500, 1700), (1, 2999), (2, 3)):
        u = _multisine(3000, DT_CASE1)
        u[bad_at[0]], u[bad_at[1]] = np.nan, -np.inf
        with pytest.raises(DataError, match=rf"sample {bad_at[0]} \(2 in total\)"):
            get_integrator(name).simulate(P, u, DT_CASE1)


def test_states_matches_column_stack_and_is_a_new_array() -> None:
    tr = Newmark().simulate(P, _multisine(50, DT_CASE1), DT_CASE1, X0)
    x = tr.states()
    assert np.array_equal(x, np.column_stack([tr.theta[:, 0], tr.omega[:, 0], tr.theta[:, 1], tr.omega[:, 1]]))
    assert not np.shares_memory(x, tr.theta) and x.flags.c_contiguous


# --------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("name, order", [("newmark", 2), ("wilson", 2), ("houbolt", 2), ("rk4", 4)])
def test_free_vibration_converges_at_theoretical_order(name: str, order: int) -> None:
    wn, t_end = natural_frequency(P), 2e-3
    errs, steps = [], []
    for wdt in (0.2, 0.1, 0.05, 0.025):
        n = int(round(t_end * wn / wdt))
        dt = t_end / n
        tr = get_integrator(name).simulate(P, np.zeros(n + 1), dt, X0)
        errs.append(_rel_err_per_state(tr.states(), _exact_free(P, X0, tr.t)))
        steps.append(dt)
    slope = np.polyfit(np.log(steps), np.log(errs), 1)[0]
    assert abs(slope - order) < 0.15, (slope, errs)


def test_zoh_free_vibration_error_is_roundoff() -> None:
    n = 200
    tr = ZeroOrderHold().simulate(P, np.zeros(n), DT_CASE1, X0)
    assert _rel_err_per_state(tr.states(), _exact_free(P, X0, tr.t)) < 1e-12


def test_zoh_exact_for_piecewise_constant_torque_against_ode_solver() -> None:
    A, b = state_space(P)
    u = _multisine(12, DT_CASE1, amp=0.2)
    tr = ZeroOrderHold().simulate(P, u, DT_CASE1, X0)
    x, ref = X0.copy(), [X0.copy()]
    for k in range(u.size - 1):
        sol = scipy.integrate.solve_ivp(lambda t, y, uk=u[k]: A @ y + b * uk, (0.0, DT_CASE1), x,
                                        method="DOP853", rtol=1e-13, atol=1e-16)
        x = sol.y[:, -1]
        ref.append(x)
    assert _rel_err_per_state(tr.states(), np.array(ref)) < 1e-9


def test_newmark_period_error_matches_theory() -> None:
    """For B = 0, average acceleration: w_num dt = 2 arctan(w dt / 2), elongation ~ (w dt)^2 / 12."""
    p = P.with_(B=0.0)
    w = natural_frequency(p)
    x0 = np.array([p.I2 * 1e-3, 0.0, -p.I1 * 1e-3, 0.0])  # flexible mode only, centre of mass at rest
    for wdt in (0.1, 0.3, 1.0):
        dt = wdt / w
        tr = Newmark().simulate(p, np.zeros(400), dt, x0)
        d = tr.theta[:, 0] - tr.theta[:, 1]
        # a sampled undamped sinusoid obeys d[k+1] + d[k-1] = 2 cos(W) d[k]: least squares for cos(W)
        cos_w = np.dot(d[2:] + d[:-2], d[1:-1]) / (2.0 * np.dot(d[1:-1], d[1:-1]))
        w_num_dt = math.acos(cos_w)
        assert w_num_dt == pytest.approx(2.0 * math.atan(wdt / 2.0), rel=1e-9)
        elongation = wdt / w_num_dt - 1.0
        if wdt <= 0.1:
            assert elongation == pytest.approx(wdt**2 / 12.0, rel=0.01)
        # no amplitude decay (the method is energy conserving for B = 0)
        assert np.max(np.abs(d[-100:])) == pytest.approx(np.max(np.abs(d[:100])), rel=1e-3)
        cm = p.I1 * tr.theta[:, 0] + p.I2 * tr.theta[:, 1]
        assert np.max(np.abs(cm)) < 1e-12 * p.I1 * p.I2


@pytest.mark.parametrize("name", INTEGRATORS)
def test_constant_torque_moves_centre_of_mass_as_parabola(name: str) -> None:
    torque, n = 0.1, 2000
    tr = get_integrator(name).simulate(P, np.full(n, torque), DT_CASE1)
    J = P.I1 + P.I2
    theta_cm = (P.I1 * tr.theta[:, 0] + P.I2 * tr.theta[:, 1]) / J
    expected = torque * tr.t**2 / (2.0 * J)
    assert np.max(np.abs(theta_cm - expected)) < 1e-9 * expected[-1]
    # the motor angle follows the parabola up to the small spring deflection
    assert tr.theta[-1, 0] == pytest.approx(expected[-1], rel=1e-3)


def test_table1_case1_momentum_equals_torque_integral() -> None:
    n = 4096
    u = _multisine(n, DT_CASE1)
    nm = Newmark().simulate(P, u, DT_CASE1)
    assert np.all(np.isfinite(nm.states()))
    momentum = P.I1 * nm.omega[:, 0] + P.I2 * nm.omega[:, 1]
    trapezoid = np.concatenate([[0.0], np.cumsum(0.5 * DT_CASE1 * (u[1:] + u[:-1]))])
    assert np.max(np.abs(momentum - trapezoid)) < 1e-10 * np.max(np.abs(trapezoid))
    # ZOH physics: the held torque integrates by the rectangle rule
    zoh = ZeroOrderHold().simulate(P, u, DT_CASE1)
    momentum = P.I1 * zoh.omega[:, 0] + P.I2 * zoh.omega[:, 1]
    rectangle = np.concatenate([[0.0], np.cumsum(DT_CASE1 * u[:-1])])
    assert np.max(np.abs(momentum - rectangle)) < 1e-10 * np.max(np.abs(rectangle))


def test_newmark_reported_acceleration_satisfies_eq4_and_eq6() -> None:
    u = _multisine(500, DT_CASE1)
    tr = Newmark().simulate(P, u, DT_CASE1, X0)
    # Eq. (4), delta = 1/2: omega[k+1] = omega[k] + dt/2 (alpha[k] + alpha[k+1])
    lhs = tr.omega[1:] - tr.omega[:-1]
    rhs = 0.5 * DT_CASE1 * (tr.alpha[1:] + tr.alpha[:-1])
    assert np.max(np.abs(lhs - rhs)) < 1e-9 * np.max(np.abs(tr.omega))
    # Eq. (6) at every sample
    d, dv = tr.theta[:, 0] - tr.theta[:, 1], tr.omega[:, 0] - tr.omega[:, 1]
    resid = P.I1 * tr.alpha[:, 0] + P.B * dv + P.K * d - u
    assert np.max(np.abs(resid)) < 1e-12 * np.max(np.abs(u))


def test_step_matrices_match_closed_forms() -> None:
    A, b = state_space(P)
    h = DT_CASE1
    Phi, Gam = zoh_matrices(P, h)
    assert np.allclose(Phi, scipy.linalg.expm(A * h), rtol=1e-13, atol=1e-15)
    # Newmark (1/4, 1/2) with a held torque is the trapezoidal rule: Cayley transform of A
    Phi_n, Gam_n = Newmark().step_matrices(P, h)
    L = np.eye(4) - 0.5 * h * A
    assert np.allclose(Phi_n, np.linalg.solve(L, np.eye(4) + 0.5 * h * A), rtol=1e-10, atol=1e-13)
    assert np.allclose(Gam_n, np.linalg.solve(L, h * b), rtol=1e-10, atol=1e-16)
    assert np.allclose(ZeroOrderHold().step_matrices(P, h)[1], Gam)


# --------------------------------------------------------------------------- API and validation
def test_trajectory_layout_and_initial_sample() -> None:
    u = np.linspace(0.0, 0.1, 7)
    for name in INTEGRATORS:
        tr = get_integrator(name).simulate(P, u, 1e-4, X0)
        assert isinstance(tr, Trajectory)
        assert tr.t.shape == (7,) and tr.theta.shape == tr.omega.shape == tr.alpha.shape == (7, 2)
        assert np.allclose(tr.t, np.arange(7) * 1e-4)
        assert np.array_equal(tr.states()[0], X0)
        assert np.array_equal(tr.torque, u)
        assert tr.states()[3, 2] == tr.theta[3, 1] and tr.states()[3, 1] == tr.omega[3, 0]


def test_houbolt_short_records_and_single_sample() -> None:
    for n in (1, 2, 3, 4):
        tr = Houbolt().simulate(P, np.full(n, 0.1), 1e-4, X0)
        assert tr.theta.shape == (n, 2)
        nm = Newmark().simulate(P, np.full(n, 0.1), 1e-4, X0)
        m = min(n, 3)  # the first three samples are the Newmark start-up
        assert np.allclose(tr.states()[:m], nm.states()[:m], rtol=1e-13, atol=0)


def test_get_integrator_names_and_unknown_name() -> None:
    assert INTEGRATORS == ("newmark", "wilson", "houbolt", "rk4", "zoh")
    classes = (Newmark, WilsonTheta, Houbolt, RungeKutta4, ZeroOrderHold)
    for name, cls in zip(INTEGRATORS, classes):
        integ = get_integrator(name)
        assert isinstance(integ, cls) and integ.name == name
    assert get_integrator("newmark", alpha=0.3, delta=0.6) == Newmark(0.3, 0.6)
    with pytest.raises(ConfigError, match="newmark, wilson, houbolt, rk4, zoh"):
        get_integrator("euler")
    with pytest.raises(ConfigError, match="bad option"):
        get_integrator("zoh", alpha=0.3)


@pytest.mark.parametrize("kw, field", [({"alpha": float("nan")}, "alpha"), ({"alpha": -0.1}, "alpha"),
                                       ({"alpha": 0.0}, "alpha"), ({"delta": float("inf")}, "delta"),
                                       ({"delta": -0.5}, "delta")])
def test_newmark_rejects_bad_parameters(kw: dict, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        Newmark(**kw)
    assert info.value.field == field


def test_newmark_warns_only_when_not_unconditionally_stable(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="rt_ident.axis.integrators"):
        Newmark()
        Newmark(alpha=0.3025, delta=0.6)
        assert not caplog.records
        Newmark(alpha=0.25, delta=0.45)
        Newmark(alpha=0.2, delta=0.5)
    assert len(caplog.records) == 2
    assert all("not unconditionally stable" in r.getMessage() for r in caplog.records)


def test_wilson_theta_validation() -> None:
    with pytest.raises(ConfigError) as info:
        WilsonTheta(theta=0.9)
    assert info.value.field == "theta"


def test_simulate_rejects_bad_dt_torque_and_x0() -> None:
    integ = Newmark()
    for dt in (0.0, -1e-4, float("nan"), float("inf")):
        with pytest.raises(ConfigError) as info:
            integ.simulate(P, np.zeros(5), dt)
        assert info.value.field == "dt"
    with pytest.raises(DataError, match="sample 2"):
        integ.simulate(P, np.array([0.0, 1.0, np.nan, 0.0]), 1e-4)
    with pytest.raises(DataError, match="non-empty 1-D"):
        integ.simulate(P, np.zeros((3, 2)), 1e-4)
    with pytest.raises(DataError):
        integ.simulate(P, np.zeros(0), 1e-4)
    with pytest.raises(ConfigError) as info:
        integ.simulate(P, np.zeros(5), 1e-4, x0=np.zeros(3))
    assert info.value.field == "x0"

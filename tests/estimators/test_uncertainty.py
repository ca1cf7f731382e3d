"""Trust signals: interval coverage (Monte Carlo), modal propagation, persistence-of-excitation monitor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.integrators import Newmark
from rt_ident.axis.modal import modal_parameters
from rt_ident.axis.params import thomson_x
from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
from rt_ident.estimators.consistent import fit_tustin_angles
from rt_ident.estimators.frequency import fit_frequency, transfer
from rt_ident.estimators.spectra import Spectra
from rt_ident.estimators.uncertainty import (
    MAX_REL_HALFWIDTH,
    MIN_EIG,
    Z95,
    covariance_from_jacobian,
    excitation_report,
    intervals,
    log_params,
    modal_jacobian,
)


def _periodic_zoh_response(N: int, dt: float, harmonics: np.ndarray, amplitude: float, seed: int):
    """Exact periodic steady state of the zoh-sampled axis (computed line by line)."""
    p = thomson_x()
    T = np.zeros(N // 2 + 1, complex)
    T[harmonics] = 0.5 * N * amplitude * np.exp(1j * np.random.default_rng(seed).uniform(-np.pi, np.pi,
                                                                                          harmonics.size))
    empty = Spectra(harmonics, N, dt, np.zeros((3, harmonics.size), complex),
                    np.zeros((harmonics.size, 3, 3), complex), 1.0, 1.0, 1, np.zeros(2))
    G = transfer(log_params(p), empty, "zoh")
    Y1, Y2 = np.zeros_like(T), np.zeros_like(T)
    Y1[harmonics], Y2[harmonics] = G[:, 0] * T[harmonics], G[:, 1] * T[harmonics]
    return [np.fft.irfft(a, N) for a in (Y1, Y2, T)]


def test_monte_carlo_coverage_of_95_percent_intervals_is_between_90_and_99_percent():
    """200 noisy realizations (2 % white noise on both angles and the torque, 10 periods)."""
    dt, N, P, M = 2.5e-4, 128, 10, 200
    h = np.arange(2, 41)                           # 49 .. 7850 rad/s around wn = 4163 rad/s
    x1, x2, u = (np.tile(s, P) for s in _periodic_zoh_response(N, dt, h, 0.02, seed=1))
    p = thomson_x()
    truth = {"I1": p.I1, "I2": p.I2, "B": p.B, "K": p.K, **modal_parameters(p)}
    rng = np.random.default_rng(2024)
    hits = dict.fromkeys(truth, 0)
    for _ in range(M):
        noisy = [s + 0.02 * s.std() * rng.standard_normal(s.size) for s in (x1, x2, u)]
        r = fit_frequency(*noisy, dt, period=N, harmonics=h, discard_periods=0)
        for key, value in truth.items():
            lo, hi = r.ci95[key]
            hits[key] += lo <= value <= hi
    coverage = {k: v / M for k, v in hits.items()}
    pooled = sum(hits.values()) / (M * len(hits))
    assert 0.90 <= pooled <= 0.99, coverage
    assert all(0.85 <= c <= 1.0 for c in coverage.values()), coverage


def test_intervals_are_lognormal_and_match_normal_for_small_errors():
    p = thomson_x()
    cov = np.diag([1e-6, 4e-6, 1e-4, 1e-6])        # sigma_log = 0.1 %, 0.2 %, 1 %, 0.1 %
    ci = intervals(p, cov)
    lo, hi = ci["B"]
    assert lo > 0.0 and hi / p.B == pytest.approx(math.exp(Z95 * 0.01))
    assert (hi - lo) / 2.0 == pytest.approx(Z95 * 0.01 * p.B, rel=1e-3)
    assert ci["wn"][0] < modal_parameters(p)["wn"] < ci["wn"][1]
    huge = intervals(p, np.diag([1e6] * 4))         # no overflow for hopeless fits
    assert huge["K"][1] == math.inf or huge["K"][1] > 1e100


def test_modal_jacobian_matches_closed_form_sensitivities():
    """wn^2 = K (1/I1 + 1/I2): d log wn / d log K = 1/2; zeta is proportional to B."""
    p = thomson_x()
    modal, J = modal_jacobian(p)
    wn, zeta = modal["wn"], modal["zeta"]
    assert J[0, 3] / wn == pytest.approx(0.5, rel=1e-6)
    assert J[2, 2] / zeta == pytest.approx(1.0, rel=1e-6)
    g = 1.0 / p.I1 + 1.0 / p.I2
    assert J[0, 0] / wn == pytest.approx(-0.5 * (1.0 / p.I1) / g, rel=1e-6)


def test_covariance_scale_never_below_one_with_absolute_weights():
    J = np.eye(6)[:, :2] + 0.1
    r = np.full(6, 1e-3)
    cov_rel, s2 = covariance_from_jacobian(J, r)
    cov_abs, _ = covariance_from_jacobian(J, r, min_scale=1.0)
    assert s2 < 1e-5
    assert np.allclose(cov_abs, cov_rel / s2)


# --------------------------------------------------------------------------- PE monitor
def test_pe_monitor_flags_rank_deficient_and_zero_regressors():
    rng = np.random.default_rng(0)
    good = rng.standard_normal((200, 3))
    collinear = good.copy()
    collinear[:, 2] = good[:, 0] - 2.0 * good[:, 1] + 1e-4 * rng.standard_normal(200)
    zero = good.copy()
    zero[:, 1] = 0.0
    assert excitation_report([good]).trusted
    bad = excitation_report([good, collinear])
    assert not bad.trusted and bad.min_eig < MIN_EIG and bad.cond > 1e6
    assert excitation_report([zero]).min_eig == 0.0
    assert not excitation_report([good[:2]]).trusted          # fewer rows than columns


def _closed_loop(u: np.ndarray, dt: float, seed: int = 3, process_noise: float = 0.0):
    sensors = SensorConfig(counts_per_rev=2**17, scale_resolution=1e-7, torque_meas_noise=1e-3,
                           torque_process_noise=process_noise)
    sim = PlantSimulator(thomson_x(), dt, sensors=sensors, controller=HoldController(), seed=seed)
    return sim.step_block(u)


def test_multisine_trusted_single_sine_and_zero_excitation_untrusted():
    dt, N = 2.5e-4, 512
    ms = schroeder_multisine(N, (9, 169), peak=0.3)
    multi = _closed_loop(ms.periodic(9), dt)
    r = fit_frequency(multi.theta1, multi.theta2, multi.torque_meas, dt, period=N, harmonics=ms.harmonics)
    assert r.trusted and r.diagnostics["min_eig"] > 100 * MIN_EIG
    assert r.diagnostics["max_rel_ci95"] < MAX_REL_HALFWIDTH

    sine = _closed_loop(np.tile(0.3 * np.cos(2 * np.pi * 40 * np.arange(N) / N), 9), dt)
    r1 = fit_frequency(sine.theta1, sine.theta2, sine.torque_meas, dt, period=N, harmonics=np.array([40]))
    assert not r1.trusted and r1.diagnostics["min_eig"] < MIN_EIG

    # no excitation: only a random disturbance torque moves the axis
    still = _closed_loop(np.zeros(9 * N), dt, process_noise=1e-2)
    r0 = fit_frequency(still.theta1, still.theta2, still.torque_meas, dt, period=N, harmonics=ms.harmonics)
    assert not r0.trusted


def test_time_domain_single_sine_in_steady_state_is_not_persistently_exciting():
    p, dt = thomson_x(), 1e-4
    n = 12000                                       # 1.2 s: the flexible transient (tau = 6 ms) is gone
    u = 0.3 * np.sin(2 * np.pi * 100.0 * np.arange(n) * dt)
    tr = Newmark().simulate(p, u, dt)
    keep = slice(8000, None)
    r = fit_tustin_angles(tr.theta[keep, 0], tr.theta[keep, 1], u[keep], dt)
    assert not r.trusted and r.diagnostics["min_eig"] < MIN_EIG
    ms = schroeder_multisine(1000, (1, 400), peak=0.3).periodic(4)
    tr = Newmark().simulate(p, ms, dt)
    assert fit_tustin_angles(tr.theta[:, 0], tr.theta[:, 1], ms, dt).diagnostics["min_eig"] > 0.01

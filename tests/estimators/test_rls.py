"""Recursive least squares (Eqs. 14-16): Theorem 1, forgetting variants, robustness, compiled vs plain."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators._rls_kernels import block_kernel, update_kernel
from rt_ident.estimators.ls import lstsq
from rt_ident.estimators.rls import FORMS, RecursiveLeastSquares, warmup

VARIANTS = ("standard", "directional", "bounded-trace")


def _data(n: int = 600, p: int = 5, q: int = 4, noise: float = 0.05, seed: int = 0):
    rng = np.random.default_rng(seed)
    Phi = rng.standard_normal((n, p)) * np.array([1.0, 3.0, 0.5, 2.0, 1.0])[:p]
    theta = rng.standard_normal((p, q))
    Y = Phi @ theta + noise * rng.standard_normal((n, q))
    return Phi, Y, theta


def _textbook_rls(Phi, Y, p0, lam=1.0, variant="standard"):
    """Oracle: Eqs. (14)-(16) transliterated on the full covariance (plus forgetting)."""
    n = Phi.shape[1]
    P = p0 * np.eye(n)
    th = np.zeros((n, Y.shape[1]))
    for phi, y in zip(Phi, Y):
        r = phi @ P @ phi
        if variant == "directional":
            if lam < 1 and r > 0:
                v = P @ phi
                P = P + (1 - lam) / (lam * r) * np.outer(v, v)
        else:
            P = P / lam
        K = P @ phi / (1.0 + phi @ P @ phi)           # Eq. (15)
        th = th + np.outer(K, y - phi @ th)           # Eq. (14)
        P = (np.eye(n) - np.outer(K, phi)) @ P         # Eq. (16)
    return th, P


def _assert_spd(P, tol=1e-12):
    assert np.all(np.isfinite(P))
    assert np.array_equal(P, P.T) or np.abs(P - P.T).max() <= tol * np.abs(P).max()
    assert np.linalg.eigvalsh(P).min() > 0.0


# --------------------------------------------------------------------------- Theorem 1
def test_theorem1_rls_initialised_from_ls_equals_batch_ls_on_all_rows():
    Phi, Y, _ = _data(n=400)
    t0 = 20
    A0 = Phi[:t0]
    P0 = np.linalg.inv(A0.T @ A0)                     # P(t0) = [A^T(t0) A(t0)]^-1
    theta0 = lstsq(A0, Y[:t0]).theta                  # LS estimate on the first t0 rows
    est = RecursiveLeastSquares(5, 4, p0=P0, theta0=theta0)
    est.update_block(Phi[t0:], Y[t0:])
    batch = lstsq(Phi, Y).theta
    assert np.max(np.abs(est.theta - batch)) < 1e-9 * np.max(np.abs(batch))
    # and P(t) = [A^T A]^-1 over all rows (Eq. 11)
    np.testing.assert_allclose(est.P, np.linalg.inv(Phi.T @ Phi), rtol=1e-9, atol=1e-15)


def test_theorem1_large_p0_converges_to_ls_and_gap_shrinks_with_p0():
    Phi, Y, _ = _data(n=2000)
    batch = lstsq(Phi, Y).theta
    gaps = []
    for p0 in (1e2, 1e5, 1e8):
        est = RecursiveLeastSquares(5, 4, p0=p0)
        est.update_block(Phi, Y)
        gaps.append(np.max(np.abs(est.theta - batch)) / np.max(np.abs(batch)))
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[2] < 1e-9


def test_ud_form_agrees_with_textbook_eqs_14_to_16():
    Phi, Y, _ = _data(n=300)
    for variant, lam in (("standard", 1.0), ("standard", 0.97), ("directional", 0.97)):
        th_ref, P_ref = _textbook_rls(Phi, Y, 100.0, lam, variant)
        est = RecursiveLeastSquares(5, 4, p0=100.0, forgetting=lam, variant=variant)
        est.update_block(Phi, Y)
        np.testing.assert_allclose(est.theta, th_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(est.P, P_ref, rtol=1e-9, atol=1e-12 * np.abs(P_ref).max())


def test_covariance_form_agrees_with_textbook_and_ud_form_and_keeps_p_exactly_symmetric():
    Phi, Y, _ = _data(n=300)
    for variant, lam in (("standard", 1.0), ("standard", 0.97), ("directional", 0.97)):
        th_ref, P_ref = _textbook_rls(Phi, Y, 100.0, lam, variant)
        cov = RecursiveLeastSquares(5, 4, p0=100.0, forgetting=lam, variant=variant, form="covariance")
        ud = RecursiveLeastSquares(5, 4, p0=100.0, forgetting=lam, variant=variant, form="ud")
        for i in range(0, 300, 60):
            cov.update_block(Phi[i:i + 60], Y[i:i + 60])
            ud.update_block(Phi[i:i + 60], Y[i:i + 60])
            np.testing.assert_array_equal(cov.P, cov.P.T)       # mirrored upper triangle
        np.testing.assert_allclose(cov.theta, th_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(cov.P, P_ref, rtol=1e-9, atol=1e-12 * np.abs(P_ref).max())
        np.testing.assert_allclose(cov.theta, ud.theta, rtol=1e-10, atol=1e-12)


def test_covariance_form_loses_definiteness_on_paper_scaled_regressors_where_ud_factors_stay_positive():
    # Why "ud" is the default: paper-like column scales (1e-3 next to 1e2, two nearly collinear
    # columns) with lambda = 0.999 drive cond(P) towards 1e18.
    rng = np.random.default_rng(7)
    m = 30_000
    Phi = rng.standard_normal((m, 5)) * np.array([1e-3, 1e2, 1e-3, 1e2, 0.3])
    Phi[:, 2] = Phi[:, 0] + 1e-7 * rng.standard_normal(m)
    Y = Phi @ rng.standard_normal((5, 4)) + 1e-6 * rng.standard_normal((m, 4))
    cov = RecursiveLeastSquares(5, 4, p0=1e6, forgetting=0.999, form="covariance")
    ud = RecursiveLeastSquares(5, 4, p0=1e6, forgetting=0.999, form="ud")
    indefinite = 0
    for i in range(0, m, 1000):
        cov.update_block(Phi[i:i + 1000], Y[i:i + 1000])
        ud.update_block(Phi[i:i + 1000], Y[i:i + 1000])
        indefinite += np.linalg.eigvalsh(cov.P).min() <= 0.0
        assert np.all(ud._d > 0.0)
    assert indefinite > 0


# --------------------------------------------------------------------------- compiled vs plain
@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("variant", VARIANTS)
def test_compiled_and_plain_numpy_paths_agree_to_1e12(variant, form):
    Phi, Y, _ = _data(n=1500, seed=4)
    Phi[300:600] = 0.0                                 # an excitation gap
    Phi[700, 2] = np.nan                               # and a rejected sample
    kw = dict(p0=1e3, forgetting=0.995, variant=variant, history=50, form=form)
    a = RecursiveLeastSquares(5, 4, compiled=True, **kw)
    b = RecursiveLeastSquares(5, 4, compiled=False, **kw)
    assert a.update_block(Phi, Y) == b.update_block(Phi, Y) == 1499
    for i in range(50):                                # and the per-sample path
        assert a.update(Phi[i], Y[i]) and b.update(Phi[i], Y[i])
    scale = np.abs(a.theta).max()
    assert np.abs(a.theta - b.theta).max() <= 1e-12 * scale
    assert np.abs(a.P - b.P).max() <= 1e-12 * np.abs(a.P).max()
    assert np.abs(a.history - b.history).max() <= 1e-12 * scale


@pytest.mark.parametrize("form", FORMS)
def test_per_sample_update_and_block_update_give_identical_estimates(form):
    Phi, Y, _ = _data(n=200)
    a = RecursiveLeastSquares(5, 4, forgetting=0.99, variant="directional", form=form)
    b = RecursiveLeastSquares(5, 4, forgetting=0.99, variant="directional", form=form)
    a.update_block(Phi, Y)
    for phi, y in zip(Phi, Y):
        b.update(phi, y)
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(a.P, b.P)


def test_warmup_compiles_the_kernels_for_the_requested_shapes():
    warmup(shapes=((3, 1),))                  # a shape other tests use too: one compile fewer from a cold cache
    for form in FORMS:
        assert len(update_kernel(form, 3, 1).signatures) == 1
        assert len(block_kernel(form, 3, 1).signatures) >= 1


_KERNELS_IN_A_NEW_PROCESS = """
import hashlib, sys, numpy as np
from rt_ident.estimators.rls import FORMS, RecursiveLeastSquares
for n in map(int, sys.argv[1].split(",")):
    rng = np.random.default_rng(n)
    Phi = rng.standard_normal((300, n))
    Y = Phi @ rng.standard_normal((n, 1)) + 0.05 * rng.standard_normal((300, 1))
    for form in FORMS:
        a = RecursiveLeastSquares(n, 1, forgetting=0.99, variant="directional", form=form)
        b = RecursiveLeastSquares(n, 1, forgetting=0.99, variant="directional", form=form)
        a.update_block(Phi, Y)
        for phi, y in zip(Phi, Y):
            b.update(phi, y)
        same = np.array_equal(a.theta, b.theta) and np.array_equal(a.P, b.P)
        print("theta", form, n, same, hashlib.sha256(a.theta.tobytes() + a.P.tobytes()).hexdigest())
"""


def test_rls_kernels_of_two_sizes_compiled_in_two_processes_load_into_a_third_bit_identical_to_their_compiles(
        tmp_path):
    # block and update are closures over a compiled core, and numba keys their cache entries by those cells;
    # each size compiled first in a process of its own gives the symbols the same counter there
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_DEBUG_CACHE": "1"}

    def start(sizes: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-c", _KERNELS_IN_A_NEW_PROCESS, sizes], env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    def finish(p: subprocess.Popen) -> tuple[list[str], list[list[str]]]:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-500:]
        return ([line for line in out.splitlines() if line.startswith("[cache] data saved")],
                [line.split() for line in out.splitlines() if line.startswith("theta")])

    (saved2, two), (saved3, three) = [finish(p) for p in [start("2"), start("3")]]
    saved, both = finish(start("3,2"))
    assert len(saved2) >= 3 * len(FORMS) and len(saved3) >= 3 * len(FORMS)   # core, block, update per form
    assert saved == []                                                      # all loaded from the cache
    assert [(form, n) for _, form, n, _, _ in both] == [(f, n) for n in ("3", "2") for f in FORMS]
    assert all(same == "True" for run in (two, three, both) for _, _, _, same, _ in run)   # one sample or a block
    assert both == three + two


# --------------------------------------------------------------------------- forgetting
def _step_change_data(seed=1, n=12000, t_step=4000):
    rng = np.random.default_rng(seed)
    Phi = rng.standard_normal((n, 3))
    th_a = np.array([1.0, -2.0, 0.5])
    th_b = np.array([1.0, -1.0, 0.5])                 # second parameter jumps by +1
    Y = np.where(np.arange(n)[:, None] < t_step, Phi @ th_a[:, None], Phi @ th_b[:, None])[:, 0]
    Y = Y + 0.01 * rng.standard_normal(n)
    return Phi, Y, th_b


@pytest.mark.parametrize("variant, tol", [("standard", 0.01), ("directional", 0.1), ("bounded-trace", 0.01)])
def test_forgetting_0999_tracks_a_parameter_step_but_lambda_1_does_not(variant, tol):
    # 8000 samples after the step: 8 time constants of 1/(1 - lambda); directional forgetting
    # forgets along one of the 3 directions per sample, so it is ~3x slower (~e^-8/3).
    Phi, Y, th_b = _step_change_data()
    kw = {"max_trace": 3e3} if variant == "bounded-trace" else {}
    fast = RecursiveLeastSquares(3, forgetting=0.999, variant=variant, p0=1e3, **kw)
    fast.update_block(Phi, Y)
    slow = RecursiveLeastSquares(3, forgetting=1.0, p0=1e3)
    slow.update_block(Phi, Y)
    err_fast = abs(fast.theta[1, 0] - th_b[1])
    err_slow = abs(slow.theta[1, 0] - th_b[1])
    assert err_fast < tol
    assert err_slow > 0.3                               # lambda = 1 averages both regimes (~1/3)


@pytest.mark.parametrize("form", FORMS)
def test_zero_excitation_winds_up_standard_forgetting_but_not_directional_or_bounded_trace(form):
    Phi, Y, _ = _data(n=500)
    zeros = np.zeros((20000, 5))
    yz = np.zeros((20000, 4))
    traces = {}
    for variant in VARIANTS:
        est = RecursiveLeastSquares(5, 4, p0=10.0, forgetting=0.99, variant=variant, form=form)
        est.update_block(Phi, Y)
        before = est.trace_P
        theta_before = np.array(est.theta)
        est.update_block(zeros, yz)
        traces[variant] = (before, est.trace_P)
        if variant != "standard":
            _assert_spd(est.P)
            np.testing.assert_allclose(est.theta, theta_before, rtol=0, atol=1e-12)
    b, a = traces["standard"]
    assert not np.isfinite(a) or a > 1e80 * b            # 0.99^-20000: wind-up
    b, a = traces["directional"]
    assert a == pytest.approx(b, rel=1e-12)            # nothing excited -> nothing forgotten
    b, a = traces["bounded-trace"]
    assert a <= 50.0 * (1 + 1e-12)                     # default bound: trace(P0) = 5 * 10


@pytest.mark.parametrize("form", FORMS)
def test_bounded_trace_never_exceeds_max_trace(form):
    Phi, Y, _ = _data(n=3000, seed=2)
    Phi[1000:2500] *= 1e-4                             # weak excitation stretch
    est = RecursiveLeastSquares(5, 4, p0=1.0, forgetting=0.95, variant="bounded-trace", max_trace=7.0,
                                form=form)
    for i in range(0, 3000, 100):
        est.update_block(Phi[i:i + 100], Y[i:i + 100])
        assert est.trace_P <= 7.0 * (1 + 1e-12)
    _assert_spd(est.P)


def test_directional_forgetting_keeps_information_in_unexcited_directions():
    rng = np.random.default_rng(5)
    n = 4000
    Phi = rng.standard_normal((n, 3))
    Phi[2000:, 2] = 0.0                                  # third regressor stops being excited
    Y = Phi @ np.array([1.0, 2.0, 3.0]) + 0.01 * rng.standard_normal(n)
    d = RecursiveLeastSquares(3, forgetting=0.99, variant="directional", p0=1e3)
    s = RecursiveLeastSquares(3, forgetting=0.99, variant="standard", p0=1e3)
    d.update_block(Phi[:2000], Y[:2000])
    p22 = d.P[2, 2]
    d.update_block(Phi[2000:], Y[2000:])
    s.update_block(Phi, Y)
    # standard forgetting lets P[2,2] grow as 0.99^-2000; directional keeps it at its value at t=2000
    assert d.P[2, 2] < 1.05 * p22 < 1e-2
    assert s.P[2, 2] > 1e5
    assert abs(d.theta[2, 0] - 3.0) < 1e-2


# --------------------------------------------------------------------------- robustness
def test_nonfinite_samples_are_rejected_counted_and_leave_state_unchanged():
    Phi, Y, _ = _data(n=100)
    est = RecursiveLeastSquares(5, 4, forgetting=0.99, history=-1)
    est.update_block(Phi[:50], Y[:50])
    th, P, n_hist = np.array(est.theta), est.P, len(est.history)
    bad_phi = Phi[50].copy()
    bad_phi[3] = np.nan
    bad_y = Y[50].copy()
    bad_y[1] = np.inf
    assert est.update(bad_phi, Y[50]) is False
    assert est.update(Phi[50], bad_y) is False
    assert est.update(np.full(5, 1e200), Y[50]) is False        # phi^T P phi overflows
    block = np.vstack([bad_phi, bad_phi])
    assert est.update_block(block, Y[50:52]) == 0
    np.testing.assert_array_equal(est.theta, th)
    np.testing.assert_array_equal(est.P, P)
    assert est.n_rejected == 5
    assert est.n_updates == 50
    assert len(est.history) == n_hist
    assert est.update(Phi[50], Y[50]) is True


@pytest.mark.slow
def test_ten_million_updates_with_gaps_and_nans_keep_p_spd_and_finite():
    rng = np.random.default_rng(7)
    m = 100_000
    Phi = rng.standard_normal((m, 5)) * np.array([1e-3, 1e2, 1e-3, 1e2, 0.3])   # paper-like scales
    Phi[:, 2] = Phi[:, 0] + 1e-7 * rng.standard_normal(m)                       # nearly collinear
    Y = Phi @ rng.standard_normal((5, 4)) + 1e-6 * rng.standard_normal((m, 4))
    Phi[20_000:60_000] = 0.0                          # long zero-excitation stretch
    Phi[70_000:80_000, 1:] = 0.0                      # only one direction excited
    Phi[rng.integers(0, m, 500)] = np.nan             # NaN samples mixed in
    est = RecursiveLeastSquares(5, 4, p0=1e6, forgetting=0.999, variant="directional")
    accepted = 0
    for _ in range(100):                              # 1e7 updates, compiled block path
        accepted += est.update_block(Phi, Y)
    assert est.n_updates + est.n_rejected == 10_000_000
    assert est.n_rejected == 10_000_000 - accepted > 0
    P = est.P
    _assert_spd(P)
    assert np.all(np.isfinite(est.theta))
    assert np.all(est._d > 0)                         # the factor D itself stays positive


# --------------------------------------------------------------------------- API
def test_history_ring_buffer_keeps_the_last_estimates_in_order():
    Phi, Y, _ = _data(n=30)
    ring = RecursiveLeastSquares(5, 4, history=7)
    full = RecursiveLeastSquares(5, 4, history=-1)
    none = RecursiveLeastSquares(5, 4)
    for est in (ring, full, none):
        est.update_block(Phi[:20], Y[:20])
        for i in range(20, 30):
            est.update(Phi[i], Y[i])
    assert full.history.shape == (30, 5, 4)
    np.testing.assert_array_equal(ring.history, full.history[-7:])
    np.testing.assert_array_equal(full.history[-1], full.theta)
    assert none.history.shape == (0, 5, 4)


def test_information_matrix_is_sum_of_outer_products_plus_prior():
    Phi, Y, _ = _data(n=200)
    est = RecursiveLeastSquares(5, 4, p0=10.0)
    est.update_block(Phi, Y)
    R = Phi.T @ Phi + np.eye(5) / 10.0                  # Eq. (12) with P(0)^-1
    np.testing.assert_allclose(est.information_matrix(), R, rtol=1e-10)
    ev = np.linalg.eigvalsh(R)
    assert est.min_eig == pytest.approx(ev[0], rel=1e-9)
    assert est.condition_number == pytest.approx(ev[-1] / ev[0], rel=1e-9)


def test_single_output_accepts_scalar_targets_and_vector_theta0():
    est = RecursiveLeastSquares(3, theta0=np.array([1.0, 2.0, 0.5]), p0=[1.0, 4.0, 2.0])
    assert est.theta.shape == (3, 1)
    assert est.update(np.array([1.0, 0.0, 0.0]), 3.0)
    assert est.theta[0, 0] == pytest.approx(1.0 + 1.0 * (3.0 - 1.0) / 2.0)
    assert est.update_block(np.ones((3, 3)), np.ones(3)) == 3
    assert est.predict(np.array([1.0, 1.0, 1.0])).shape == (1,)
    with pytest.raises(ValueError):
        est.theta[0, 0] = 5.0                             # read-only view


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(n_regressors=0), "n_regressors"),
        (dict(n_outputs=0), "n_outputs"),
        (dict(forgetting=0.0), "forgetting"),
        (dict(forgetting=1.5), "forgetting"),
        (dict(variant="kalman"), "variant"),
        (dict(max_trace=10.0), "max_trace"),
        (dict(variant="bounded-trace", max_trace=-1.0), "max_trace"),
        (dict(p0=-1.0), "p0"),
        (dict(p0=np.ones((3, 3))), "p0"),
        (dict(p0=np.array([[1.0, 2.0, 0], [0, 1.0, 0], [0, 0, 1.0]])), "p0"),
        (dict(theta0=np.zeros((2, 2))), "theta0"),
        (dict(history=-2), "history"),
        (dict(form="qr"), "form"),
    ],
)
def test_bad_constructor_arguments_raise_config_error_naming_the_field(kwargs, field):
    args = dict(n_regressors=3, n_outputs=1)
    args.update(kwargs)
    with pytest.raises(ConfigError) as exc:
        RecursiveLeastSquares(args.pop("n_regressors"), args.pop("n_outputs"), **args)
    assert exc.value.field == field


def test_bad_sample_shapes_raise_data_error():
    est = RecursiveLeastSquares(3, 2)
    with pytest.raises(DataError, match="phi"):
        est.update(np.ones(4), np.ones(2))
    with pytest.raises(DataError, match="y"):
        est.update(np.ones(3), np.ones(3))
    with pytest.raises(DataError, match="Phi"):
        est.update_block(np.ones((5, 2)), np.ones((5, 2)))
    with pytest.raises(DataError, match="Y"):
        est.update_block(np.ones((5, 3)), np.ones((4, 2)))
    assert est.n_updates == 0 and est.n_rejected == 0


def test_update_converts_lists_noncontiguous_and_readonly_inputs_to_the_same_result():
    Phi, Y, _ = _data(n=40)
    ref = RecursiveLeastSquares(5, 4)
    est = RecursiveLeastSquares(5, 4)
    for i in range(40):
        assert ref.update(Phi[i].copy(), Y[i].copy())
        readonly = Phi[i].copy()
        readonly.flags.writeable = False
        strided = np.repeat(Phi[i], 2)[::2]              # same values, not contiguous
        assert not strided.flags.c_contiguous
        phi = (list(Phi[i]), readonly, strided, tuple(Phi[i]))[i % 4]
        assert est.update(phi, Y[i].copy() if i % 2 else list(Y[i]))
    np.testing.assert_array_equal(est.theta, ref.theta)


def test_deepcopy_and_pickle_keep_the_state_and_rebind_the_kernels():
    import copy
    import pickle

    Phi, Y, _ = _data(n=100)
    est = RecursiveLeastSquares(5, 4, forgetting=0.99, history=5)
    est.update_block(Phi[:50], Y[:50])
    for clone in (copy.deepcopy(est), pickle.loads(pickle.dumps(est))):
        np.testing.assert_array_equal(clone.theta, est.theta)
        clone.update_block(Phi[50:], Y[50:])
        assert not np.shares_memory(clone.theta, est.theta)
        assert est.n_updates == 50 and clone.n_updates == 100
    est.update_block(Phi[50:], Y[50:])
    np.testing.assert_array_equal(clone.theta, est.theta)

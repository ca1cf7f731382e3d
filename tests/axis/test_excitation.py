"""Tests for rt_ident.axis.excitation: multisines, PRBS, chirp, factory and validation."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from rt_ident.axis.excitation import (
    EXCITATION_KINDS,
    PRBS_TAPS,
    Multisine,
    chirp,
    crest_factor,
    make_excitation,
    prbs,
    random_phase_multisine,
    schroeder_multisine,
    schroeder_phases,
)
from rt_ident.errors import ConfigError


# ----------------------------------------------------------------------------- multisine
@pytest.mark.parametrize("N, band", [(512, (1, None)), (512, (3, 40)), (2048, (1, 146)), (101, (2, 49)), (4, (1, 1))])
def test_multisine_dft_has_flat_energy_only_on_band_harmonics(N, band):
    ms = schroeder_multisine(N, band, rms=1.0)
    lo = band[0]
    hi = N // 2 - 1 if band[1] is None else band[1]
    X = np.fft.rfft(ms.signal)
    in_band = np.zeros(X.size, dtype=bool)
    in_band[lo:hi + 1] = True
    mag = np.abs(X) * 2.0 / N  # amplitude of each cosine
    scale = ms.amplitudes[0]
    assert np.max(mag[~in_band]) < 1e-10 * scale
    np.testing.assert_allclose(mag[in_band], scale, rtol=1e-10)
    np.testing.assert_array_equal(ms.harmonics, np.arange(lo, hi + 1))
    # phases of the DFT are the declared phases
    np.testing.assert_allclose(np.exp(1j * np.angle(X[in_band])), np.exp(1j * ms.phases), atol=1e-10)


def test_multisine_is_sum_of_cosines_oracle():
    N = 64
    ms = schroeder_multisine(N, (2, 9), peak=1.5)
    n = np.arange(N)
    direct = sum(a * np.cos(2 * np.pi * h * n / N + p) for h, a, p in zip(ms.harmonics, ms.amplitudes, ms.phases))
    np.testing.assert_allclose(ms.signal, direct, atol=1e-12)


def test_multisine_periodic_repeats_exactly_every_N_samples():
    ms = schroeder_multisine(256, (1, 30))
    x = ms.periodic(5)
    assert x.shape == (5 * 256,)
    for p in range(1, 5):
        np.testing.assert_array_equal(x[p * 256:(p + 1) * 256], x[:256])
    x[0] = 99.0  # periodic returns a copy; the period is untouched
    assert ms.signal[0] != 99.0


def test_multisine_at_streams_by_sequence_number():
    ms = schroeder_multisine(128, (1, 20))
    idx = np.array([0, 1, 127, 128, 129, 10_000_003, -1])
    np.testing.assert_array_equal(ms.at(idx), ms.signal[[0, 1, 127, 0, 1, 10_000_003 % 128, 127]])
    assert ms.at(130) == ms.signal[2]
    with pytest.raises(ConfigError) as exc:
        ms.at(np.array([1.5]))
    assert exc.value.field == "sample_index"


def test_multisine_arrays_are_read_only():
    ms = schroeder_multisine(64)
    with pytest.raises(ValueError):
        ms.signal[0] = 1.0
    assert isinstance(ms, Multisine)


def test_schroeder_phases_follow_flat_spectrum_formula():
    F = 7
    j = np.arange(1, F + 1)
    np.testing.assert_allclose(schroeder_phases(F), -np.pi * j * (j - 1) / F, rtol=0, atol=0)
    ms = schroeder_multisine(64, (5, 11))
    np.testing.assert_allclose(ms.phases, schroeder_phases(7))


def test_random_phases_deterministic_given_seed_and_differ_between_seeds():
    a = random_phase_multisine(512, (1, 100), seed=3)
    b = random_phase_multisine(512, (1, 100), seed=3)
    c = random_phase_multisine(512, (1, 100), seed=4)
    np.testing.assert_array_equal(a.signal, b.signal)
    assert not np.allclose(a.signal, c.signal)
    expected = np.random.default_rng(3).uniform(-np.pi, np.pi, size=100)
    np.testing.assert_array_equal(a.phases, expected)
    s1, s2 = schroeder_multisine(512), schroeder_multisine(512)
    np.testing.assert_array_equal(s1.signal, s2.signal)


@pytest.mark.parametrize("N, band", [(512, (1, None)), (2048, (1, 256)), (512, (1, 20)), (1024, (5, 60))])
def test_schroeder_crest_factor_beats_median_random_phase(N, band):
    schroeder_cf = schroeder_multisine(N, band).crest_factor
    random_cf = [random_phase_multisine(N, band, seed=s).crest_factor for s in range(20)]
    assert schroeder_cf < np.median(random_cf)
    assert schroeder_cf < 1.9  # Schroeder 1970: ~1.6-1.8 for wide flat bands (lower when sampled)


def test_peak_scaling_is_exact():
    ms = schroeder_multisine(1000, (1, 300), peak=2.5)
    assert np.max(np.abs(ms.signal)) == pytest.approx(2.5, rel=1e-14)
    assert ms.peak == pytest.approx(2.5, rel=1e-14)


def test_rms_scaling_is_exact_and_default_is_unit_rms():
    ms = schroeder_multisine(1000, (3, 300), rms=0.7)
    assert np.sqrt(np.mean(ms.signal ** 2)) == pytest.approx(0.7, rel=1e-13)
    np.testing.assert_allclose(ms.amplitudes, 0.7 / np.sqrt(298 / 2), rtol=1e-14)
    assert schroeder_multisine(1000).rms == pytest.approx(1.0, rel=1e-13)


def test_crest_factor_of_a_sine_and_square():
    n = np.arange(1000)
    assert crest_factor(np.sin(2 * np.pi * 10 * n / 1000)) == pytest.approx(math.sqrt(2), rel=1e-12)
    assert crest_factor(np.array([1.0, -1.0, 1.0, -1.0])) == pytest.approx(1.0)
    with pytest.raises(ConfigError):
        crest_factor(np.zeros(4))


def test_crest_factor_of_a_huge_sine_is_a_sines_without_overflow_and_a_non_finite_signal_is_refused():
    n = np.arange(1000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # x * x of 1e300 would overflow to inf, and warn
        assert crest_factor(1e300 * np.sin(2 * np.pi * 10 * n / 1000)) == pytest.approx(math.sqrt(2), rel=1e-12)
    with pytest.raises(ConfigError, match="inf or NaN"):
        crest_factor(np.array([1.0, math.inf]))


# ----------------------------------------------------------------------------- PRBS
def _maximal(bits: np.ndarray, order: int) -> bool:
    """Every non-zero `order`-bit window appears exactly once in one circular period."""
    L = 2**order - 1
    ext = np.concatenate([bits[:L], bits[:order - 1]])
    windows = np.lib.stride_tricks.sliding_window_view(ext, order).astype(np.int64)
    codes = windows @ (np.int64(1) << np.arange(order, dtype=np.int64))
    return np.unique(codes).size == L and not np.any(codes == 0)


@pytest.mark.parametrize("order", sorted(PRBS_TAPS))
def test_prbs_every_table_polynomial_gives_maximum_length(order):
    L = 2**order - 1
    x = prbs(2 * L, order=order)
    bits = (x > 0).astype(np.int8)
    assert _maximal(bits, order)
    np.testing.assert_array_equal(x[:L], x[L:])
    assert int(bits[:L].sum()) == 2 ** (order - 1)  # balance: one more 1 than 0s


def test_prbs_recurrence_matches_plain_python_oracle():
    order, seed = 9, 0b101100111
    taps = PRBS_TAPS[order]
    s = [(seed >> i) & 1 for i in range(order)]
    while len(s) < 600:
        k = len(s) - order
        b = s[k]
        for t in taps:
            b ^= s[k + t]
        s.append(b)
    x = prbs(600, order=order, seed=seed, amplitude=2.0)
    np.testing.assert_array_equal(x, np.where(np.array(s) == 1, 2.0, -2.0))


def test_prbs_is_plus_minus_amplitude_with_held_bits():
    x = prbs(1000, order=7, amplitude=0.3, samples_per_bit=4, seed=5)
    assert x.shape == (1000,)
    assert set(np.unique(x).tolist()) == {-0.3, 0.3}
    blocks = x.reshape(-1, 4)
    assert np.all(blocks == blocks[:, :1])
    np.testing.assert_array_equal(blocks[:, 0], prbs(250, order=7, amplitude=0.3, seed=5))
    np.testing.assert_array_equal(x, prbs(1000, order=7, amplitude=0.3, samples_per_bit=4, seed=5))


def test_prbs_spectrum_is_flat_except_dc():
    order = 10
    L = 2**order - 1
    X = np.abs(np.fft.fft(prbs(L, order=order)))
    # +-1 m-sequence: |X_0| = 1, |X_k| = sqrt(L + 1) for every k != 0
    assert X[0] == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(X[1:], math.sqrt(L + 1), rtol=1e-10)


@pytest.mark.parametrize(
    "kw, field",
    [({"order": 1}, "order"), ({"order": 21}, "order"), ({"amplitude": 0.0}, "amplitude"),
     ({"amplitude": math.nan}, "amplitude"), ({"samples_per_bit": 0}, "samples_per_bit"),
     ({"seed": 0}, "seed"), ({"order": 4, "seed": 16}, "seed"), ({"order": 4.0}, "order")],
)
def test_prbs_bad_arguments_name_the_field(kw, field):
    with pytest.raises(ConfigError) as exc:
        prbs(100, **kw)
    assert exc.value.field == field


# ----------------------------------------------------------------------------- chirp
def _zero_crossing_frequency(x: np.ndarray, dt: float, which: str) -> tuple[float, float]:
    """Frequency from the first/last two zero crossings (linear interpolation): (t_mid, f)."""
    s = np.signbit(x)
    idx = np.nonzero(s[1:] != s[:-1])[0]
    idx = idx[idx > 0]  # skip the crossing at t = 0 itself
    i0, i1 = (idx[0], idx[1]) if which == "first" else (idx[-2], idx[-1])
    tz = [(i + x[i] / (x[i] - x[i + 1])) * dt for i in (i0, i1)]
    return 0.5 * (tz[0] + tz[1]), 1.0 / (2.0 * (tz[1] - tz[0]))


@pytest.mark.parametrize("method", ["linear", "log"])
def test_chirp_instantaneous_frequency_endpoints(method):
    dt, n, f0, f1 = 1e-4, 200_001, 5.0, 200.0
    x = chirp(n, dt, f0, f1, amplitude=2.0, method=method)
    T = (n - 1) * dt
    assert x.shape == (n,)
    assert abs(x[0]) < 1e-12  # starts at zero: no torque step
    assert np.max(np.abs(x)) == pytest.approx(2.0, rel=1e-4)

    def f_inst(t: float) -> float:
        return f0 + (f1 - f0) * t / T if method == "linear" else f0 * (f1 / f0) ** (t / T)

    t_a, f_a = _zero_crossing_frequency(x, dt, "first")
    t_b, f_b = _zero_crossing_frequency(x, dt, "last")
    assert f_a == pytest.approx(f_inst(t_a), rel=1e-2)
    assert f_b == pytest.approx(f_inst(t_b), rel=1e-2)
    assert f_b == pytest.approx(f1, rel=0.01)
    # closed-form phase oracle: f(0) = f0 and f(T) = f1 exactly
    t = np.arange(n) * dt
    if method == "linear":
        phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) * t**2 / T)
    else:
        beta = T / math.log(f1 / f0)
        phase = 2 * np.pi * beta * f0 * ((f1 / f0) ** (t / T) - 1.0)
    np.testing.assert_allclose(x, 2.0 * np.sin(phase), atol=1e-8)


@pytest.mark.parametrize(
    "args, kw, field",
    [((1, 1e-3, 1.0, 10.0), {}, "n_samples"), ((100, 0.0, 1.0, 10.0), {}, "dt"),
     ((100, 1e-3, -1.0, 10.0), {}, "f0"), ((100, 1e-3, 0.0, 10.0), {"method": "log"}, "f0"),
     ((100, 1e-3, 1.0, 600.0), {}, "f1"), ((100, 1e-3, 1.0, math.inf), {}, "f1"),
     ((100, 1e-3, 1.0, 10.0), {"method": "cubic"}, "method"),
     ((100, 1e-3, 1.0, 10.0), {"amplitude": -1.0}, "amplitude")],
)
def test_chirp_bad_arguments_name_the_field(args, kw, field):
    with pytest.raises(ConfigError) as exc:
        chirp(*args, **kw)
    assert exc.value.field == field


# ----------------------------------------------------------------------------- validation & factory
@pytest.mark.parametrize(
    "args, kw, field",
    [((3,), {}, "N"), ((512.0,), {}, "N"), ((True,), {}, "N"),
     ((512, (0, 10)), {}, "band"), ((512, (1, 256)), {}, "band"), ((512, (20, 10)), {}, "band"),
     ((512, 5), {}, "band"), ((512, (1.5, 10)), {}, "band"),
     ((512,), {"peak": 1.0, "rms": 1.0}, "peak"), ((512,), {"peak": 0.0}, "peak"),
     ((512,), {"rms": -1.0}, "rms"), ((512,), {"rms": math.nan}, "rms"), ((512,), {"peak": math.inf}, "peak"),
     ((512,), {"phases": "zero"}, "phases"), ((512,), {"phases": "random", "seed": -1}, "seed")],
)
def test_multisine_bad_arguments_name_the_field(args, kw, field):
    with pytest.raises(ConfigError) as exc:
        schroeder_multisine(*args, **kw)
    assert exc.value.field == field
    assert field in str(exc.value)


def test_make_excitation_builds_each_kind():
    s = make_excitation("schroeder", N=256, band=[1, 40], peak=1.0)
    np.testing.assert_array_equal(s.signal, schroeder_multisine(256, (1, 40), peak=1.0).signal)
    r = make_excitation("random", N=256, seed=2)
    np.testing.assert_array_equal(r.signal, random_phase_multisine(256, seed=2).signal)
    np.testing.assert_array_equal(make_excitation("prbs", n_samples=50, order=5), prbs(50, order=5))
    np.testing.assert_array_equal(make_excitation("chirp", n_samples=50, dt=1e-3, f0=1.0, f1=20.0),
                                  chirp(50, 1e-3, 1.0, 20.0))
    assert set(EXCITATION_KINDS) == {"schroeder", "random", "prbs", "chirp"}


def test_make_excitation_unknown_kind_lists_valid_kinds():
    with pytest.raises(ConfigError) as exc:
        make_excitation("sweep", N=64)
    assert exc.value.field == "kind"
    for k in ("schroeder", "random", "prbs", "chirp"):
        assert k in str(exc.value)


def test_make_excitation_unknown_or_missing_argument_named():
    with pytest.raises(ConfigError) as e1:
        make_excitation("prbs", n_samples=10, bogus=3)
    assert e1.value.field == "bogus"
    with pytest.raises(ConfigError) as e2:
        make_excitation("chirp", n_samples=10, dt=1e-3, f0=1.0)
    assert e2.value.field == "f1"
    with pytest.raises(ConfigError) as e3:
        make_excitation("schroeder", N=2)
    assert e3.value.field == "N"

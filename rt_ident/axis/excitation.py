"""Excitation signals: Schroeder / random-phase multisines, PRBS and chirps.

The paper excites the axis with a Schroeder signal (Section 3, Fig. 4; Schroeder
1970): a periodic sum of harmonics with a flat amplitude spectrum and phases
chosen for a low peak factor. The paper gives neither the harmonic band nor the
amplitude; both are arguments here (docs/theory/paper.md, "Where the paper is wrong or silent").

Conventions
-----------
A multisine is periodic over exactly ``N`` samples. Sample ``n`` is at time
``t = n dt`` and harmonic ``h`` has frequency ``h w0`` with ``w0 = 2 pi / (N dt)``
(the paper's excitation frequency, Section 6). With ``dt`` from
:func:`rt_ident.axis.timestep.dt_for`, harmonic ``k`` sits exactly on ``wn``.

Every invalid argument raises :class:`~rt_ident.errors.ConfigError` naming it.
Pure numerics: no I/O, no clock, no module-level mutable state.
"""

from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# scipy.signal is imported by the functions that use it, not here: its import takes ~0.6 s of every run's start
import numpy as np

from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)

#: Primitive polynomials over GF(2), x^order + sum(x^t for t in taps) + 1, by order.
#: Each was checked to give a maximum-length sequence (every non-zero state once per
#: period; see tests/axis/test_excitation.py). Low-degree middle terms were preferred.
PRBS_TAPS: dict[int, tuple[int, ...]] = {
    2: (1,), 3: (1,), 4: (1,), 5: (2,), 6: (1,), 7: (1,), 8: (4, 3, 2), 9: (4,),
    10: (3,), 11: (2,), 12: (6, 4, 1), 13: (4, 3, 1), 14: (10, 6, 1), 15: (1,),
    16: (12, 3, 1), 17: (3,), 18: (7,), 19: (5, 2, 1), 20: (3,),
}

PHASE_KINDS = ("schroeder", "random")
CHIRP_METHODS = ("linear", "log")


# --------------------------------------------------------------------------- checks
def _check_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(name, f"must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(name, f"must be >= {minimum}, got {value!r}")
    return int(value)


def _check_positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(name, f"must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(name, f"must be finite, got {value!r}")
    if value <= 0.0:
        raise ConfigError(name, f"must be > 0, got {value!r}")
    return value


def _check_band(N: int, band: Any) -> tuple[int, int]:
    top = N // 2 - 1  # highest harmonic strictly below Nyquist for even N (kept for odd N too)
    try:
        lo, hi = band
    except (TypeError, ValueError):
        raise ConfigError("band", f"must be a pair (first, last) of harmonic numbers, got {band!r}") from None
    hi = top if hi is None else hi
    lo = _check_int("band", lo, 1)
    hi = _check_int("band", hi, 1)
    if lo > hi:
        raise ConfigError("band", f"reversed: first harmonic {lo} > last harmonic {hi}")
    if hi > top:
        raise ConfigError("band", f"last harmonic {hi} outside 1..{top} (N//2 - 1 for N={N})")
    return lo, hi


def crest_factor(x: np.ndarray) -> float:
    """Crest (peak) factor ``max|x| / rms(x)`` of a sampled signal."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        raise ConfigError("x", "empty signal")
    peak = float(np.max(np.abs(x)))
    if peak == 0.0:
        raise ConfigError("x", "all-zero signal has no crest factor")
    if not math.isfinite(peak):
        raise ConfigError("x", "a signal with inf or NaN in it has no crest factor")
    return 1.0 / float(np.sqrt(np.mean((x / peak) ** 2)))       # scaled by the peak: no overflow of x * x


# --------------------------------------------------------------------------- multisine
@dataclass(frozen=True, eq=False)
class Multisine:
    """One period of a multisine ``x[n] = sum_h A_h cos(2 pi h n / N + phi_h)``.

    Arrays are read-only. ``eq=False``: compare the arrays explicitly.
    """

    signal: np.ndarray       # (N,) one period, sample n at t = n*dt
    harmonics: np.ndarray    # int harmonic numbers h (frequency h*w0, w0 = 2pi/(N dt))
    amplitudes: np.ndarray   # per-harmonic amplitude (after scaling)
    phases: np.ndarray       # rad

    @property
    def N(self) -> int:
        """Period in samples."""
        return int(self.signal.size)

    @property
    def crest_factor(self) -> float:
        """``max|x| / rms(x)`` over the samples of one period."""
        return crest_factor(self.signal)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.signal * self.signal)))

    @property
    def peak(self) -> float:
        return float(np.max(np.abs(self.signal)))

    def frequencies(self, dt: float) -> np.ndarray:
        """Harmonic frequencies ``h w0`` [rad/s] for sample time ``dt``, ``w0 = 2 pi / (N dt)``."""
        dt = _check_positive("dt", dt)
        return self.harmonics * (2.0 * np.pi / (self.N * dt))

    def periodic(self, n_periods: int) -> np.ndarray:
        """``n_periods`` back-to-back copies of the period (a new, writable array)."""
        n_periods = _check_int("n_periods", n_periods, 1)
        return np.tile(self.signal, n_periods)

    def at(self, sample_index: np.ndarray | int) -> np.ndarray:
        """``signal[idx % N]``: the value at absolute sample number(s), for streaming by sequence number.

        Negative indices wrap as well. A scalar index gives a numpy scalar.
        """
        idx = np.asarray(sample_index)
        if not np.issubdtype(idx.dtype, np.integer):
            raise ConfigError("sample_index", f"must be integer, got dtype {idx.dtype}")
        return self.signal[idx % self.N]


def schroeder_phases(n_harmonics: int) -> np.ndarray:
    """Schroeder phases for a flat spectrum of ``F`` harmonics.

    Schroeder 1970, Eq. for flat spectrum: ``phi_j = phi_1 - 2 pi sum_{l<j} (j - l) p_l``
    with equal powers ``p_l = 1/F`` and ``phi_1 = 0`` gives
    ``phi_j = -pi j (j - 1) / F`` for j = 1..F.
    """
    F = _check_int("n_harmonics", n_harmonics, 1)
    j = np.arange(1, F + 1, dtype=float)
    return -np.pi * j * (j - 1.0) / F


def schroeder_multisine(
    N: int,
    band: tuple[int, int | None] = (1, None),
    *,
    peak: float | None = None,
    rms: float | None = None,
    phases: str = "schroeder",
    seed: int = 0,
) -> Multisine:
    """Flat-spectrum multisine periodic over ``N`` samples.

    Parameters
    ----------
    N : period in samples (>= 4).
    band : first and last harmonic, inclusive; ``None`` as last means ``N//2 - 1``
        (the highest harmonic below Nyquist). Must lie in ``1..N//2 - 1``.
    peak, rms : scale so that ``max|x| == peak`` (over the samples) or the rms equals
        ``rms``. At most one; neither gives unit rms.
    phases : ``"schroeder"`` (Schroeder 1970) or ``"random"`` (uniform in [-pi, pi)
        from ``numpy.random.default_rng(seed)``). ``seed`` is unused for Schroeder.
    """
    N = _check_int("N", N, 4)
    lo, hi = _check_band(N, band)
    if peak is not None and rms is not None:
        raise ConfigError("peak", "give at most one of peak and rms, not both")
    if peak is not None:
        peak = _check_positive("peak", peak)
    if rms is not None:
        rms = _check_positive("rms", rms)
    if phases not in PHASE_KINDS:
        raise ConfigError("phases", f"must be one of {PHASE_KINDS}, got {phases!r}")
    seed = _check_int("seed", seed, 0)

    harmonics = np.arange(lo, hi + 1)
    F = harmonics.size
    if phases == "schroeder":
        phi = schroeder_phases(F)
    else:
        phi = np.random.default_rng(seed).uniform(-np.pi, np.pi, size=F)

    # Unit-amplitude spectrum: rfft coefficient X_h = (N/2) A e^{j phi} gives A cos(2 pi h n/N + phi)
    # after the inverse real FFT (no DC, no Nyquist bin, so the factor N/2 is exact).
    spectrum = np.zeros(N // 2 + 1, dtype=complex)
    spectrum[harmonics] = 0.5 * N * np.exp(1j * phi)
    unit = np.fft.irfft(spectrum, n=N)

    if peak is not None:
        scale = peak / float(np.max(np.abs(unit)))
    else:
        target = 1.0 if rms is None else rms
        # rms of F distinct unit cosines on the DFT grid is sqrt(F/2) exactly
        scale = target / math.sqrt(F / 2.0)
    signal = unit * scale
    amplitudes = np.full(F, scale)
    for arr in (signal, harmonics, amplitudes, phi):
        arr.setflags(write=False)
    ms = Multisine(signal=signal, harmonics=harmonics, amplitudes=amplitudes, phases=phi)
    if log.isEnabledFor(logging.DEBUG):
        log.debug("multisine N=%d band=%d..%d phases=%s crest=%.3f", N, lo, hi, phases, ms.crest_factor)
    return ms


def random_phase_multisine(
    N: int,
    band: tuple[int, int | None] = (1, None),
    *,
    peak: float | None = None,
    rms: float | None = None,
    seed: int = 0,
) -> Multisine:
    """Flat-spectrum multisine with uniform random phases (see :func:`schroeder_multisine`)."""
    return schroeder_multisine(N, band, peak=peak, rms=rms, phases="random", seed=seed)


# --------------------------------------------------------------------------- PRBS
def prbs(
    n_samples: int,
    *,
    order: int = 10,
    amplitude: float = 1.0,
    samples_per_bit: int = 1,
    seed: int = 1,
) -> np.ndarray:
    """Maximum-length binary sequence (+-amplitude), period ``2**order - 1`` bits.

    The linear recurrence ``s[k+order] = s[k] xor s[k+t1] xor ...`` of the primitive
    polynomial ``PRBS_TAPS[order]`` runs from the initial register contents
    ``seed`` (bit i of ``seed`` is s[i]; ``1 <= seed < 2**order``). Bit 1 -> +amplitude,
    bit 0 -> -amplitude. Each bit is held for ``samples_per_bit`` samples, and the
    sequence repeats to fill ``n_samples``.
    """
    import scipy.signal
    n_samples = _check_int("n_samples", n_samples, 1)
    order = _check_int("order", order, 0)
    if order not in PRBS_TAPS:
        raise ConfigError("order", f"must be in {min(PRBS_TAPS)}..{max(PRBS_TAPS)}, got {order}")
    amplitude = _check_positive("amplitude", amplitude)
    samples_per_bit = _check_int("samples_per_bit", samples_per_bit, 1)
    seed = _check_int("seed", seed, 1)
    if seed >= 2**order:
        raise ConfigError("seed", f"initial register must be in 1..{2**order - 1} for order {order}, got {seed}")

    n_bits = -(-n_samples // samples_per_bit)
    period = 2**order - 1
    state = [(seed >> i) & 1 for i in range(order)]
    # scipy's generator implements exactly this recurrence (taps = middle exponents).
    bits, _ = scipy.signal.max_len_seq(order, state=state, length=min(n_bits, period),
                                       taps=list(PRBS_TAPS[order]))
    bits = np.resize(bits, n_bits)  # np.resize repeats the sequence cyclically
    x = amplitude * (2.0 * bits.astype(float) - 1.0)
    return np.repeat(x, samples_per_bit)[:n_samples]


# --------------------------------------------------------------------------- chirp
def chirp(
    n_samples: int,
    dt: float,
    f0: float,
    f1: float,
    *,
    amplitude: float = 1.0,
    method: str = "linear",
) -> np.ndarray:
    """Swept sine ``amplitude * sin(phase(t))`` from ``f0`` to ``f1`` [Hz].

    The instantaneous frequency is ``f0`` at the first sample (t = 0) and ``f1`` at the
    last (t = (n_samples - 1) dt); it varies linearly or geometrically (``"log"``, which
    needs f0 > 0). Starts at zero (sine phase), so there is no torque step.
    Frequencies must lie below Nyquist ``1 / (2 dt)``.
    """
    import scipy.signal
    n_samples = _check_int("n_samples", n_samples, 2)
    dt = _check_positive("dt", dt)
    amplitude = _check_positive("amplitude", amplitude)
    if method not in CHIRP_METHODS:
        raise ConfigError("method", f"must be one of {CHIRP_METHODS}, got {method!r}")
    if method == "log":
        f0 = _check_positive("f0", f0)
    else:
        if isinstance(f0, bool) or not isinstance(f0, (int, float, np.integer, np.floating)) \
                or not math.isfinite(f0) or f0 < 0:
            raise ConfigError("f0", f"must be a finite number >= 0, got {f0!r}")
        f0 = float(f0)
    f1 = _check_positive("f1", f1)
    nyquist = 0.5 / dt
    for name, f in (("f0", f0), ("f1", f1)):
        if f >= nyquist:
            raise ConfigError(name, f"{f} Hz is not below Nyquist {nyquist} Hz (dt={dt})")
    t = np.arange(n_samples) * dt
    t1 = t[-1]
    return amplitude * scipy.signal.chirp(t, f0=f0, t1=t1, f1=f1,
                                          method="linear" if method == "linear" else "logarithmic",
                                          phi=-90.0)


# --------------------------------------------------------------------------- factory
_KINDS: dict[str, Callable[..., Any]] = {
    "schroeder": schroeder_multisine,
    "random": random_phase_multisine,
    "prbs": prbs,
    "chirp": chirp,
}
EXCITATION_KINDS = tuple(_KINDS)


def make_excitation(kind: str, **kw: Any) -> Multisine | np.ndarray:
    """Build an excitation by name (for configs).

    ``"schroeder"`` and ``"random"`` return a :class:`Multisine` (one period);
    ``"prbs"`` and ``"chirp"`` return the sample array. Keyword arguments are
    those of the matching function; an unknown or missing one raises
    :class:`ConfigError` naming it.
    """
    if kind not in _KINDS:
        raise ConfigError("kind", f"unknown excitation {kind!r}; valid kinds: {', '.join(EXCITATION_KINDS)}")
    fn = _KINDS[kind]
    sig = inspect.signature(fn)
    for name in kw:
        if name not in sig.parameters:
            raise ConfigError(name, f"not an argument of excitation {kind!r} (expected {sorted(sig.parameters)})")
    try:
        sig.bind(**kw)
    except TypeError:
        missing = [n for n, p in sig.parameters.items() if p.default is inspect.Parameter.empty and n not in kw]
        raise ConfigError(missing[0] if missing else kind, f"missing for excitation {kind!r}") from None
    return fn(**kw)

r"""Velocity and acceleration from quantized angles: a steady-state Kalman filter.

Real hardware gives angles only (motor encoder counts, table linear scale),
quantized. The paper (Sec. 2-3) assumes measured angular velocities; here they
are estimated. Each angle gets a kinematic model — constant acceleration
("ca", state ``[theta, omega, alpha]``) or constant jerk ("cj", adds the jerk)
— driven by continuous white noise of spectral density ``process_noise``
(units rad^2/s^5 for "ca", rad^2/s^7 for "cj") and observed through the
quantizer, whose error is modelled as white with variance

.. math:: R = q^2 / 12 .

The Kalman gain of this time-invariant model converges to a constant, so it is
computed ONCE (the discrete algebraic Riccati equation, solved with scipy in a
dimensionless form and checked against a long filterpy run in the tests) and
then applied per sample by a compiled kernel:

.. math:: x_k = F x_{k-1} + K (z_k - H F x_{k-1}) .

Bandwidth: in the continuous limit the filter poles form a Butterworth pattern
of radius :math:`\omega_0 = (q_c / (R\,\Delta t))^{1/(2n)}` (n = 3 for "ca",
4 for "cj"); :meth:`SteadyStateKalman.from_bandwidth` inverts that. The
estimates lag a fast signal (phase grows with frequency / bandwidth): pick the
bandwidth well above the mode to be identified and keep the lag in mind when
velocities and accelerations are regressed against measured torque.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg

from rt_ident.errors import ConfigError, DataError

_MODELS = {"ca": 3, "cj": 4}


def _check_positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(name, f"must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ConfigError(name, f"must be a finite number > 0, got {value!r}")
    return v


def _model_dim(model: str) -> int:
    try:
        return _MODELS[model]
    except (KeyError, TypeError):
        raise ConfigError("model", f"must be one of {sorted(_MODELS)}, got {model!r}") from None


def kinematic_matrices(dt: float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """F (Taylor transition of an integrator chain) and Q1 (white-noise covariance for dt=1, q=1).

    ``F[i, j] = dt**(j-i) / (j-i)!`` for j >= i. ``Q1`` is the discretized
    continuous white noise on the highest derivative for unit sample period:
    ``Q1[i, j] = 1 / ((p_i + p_j + 1) p_i! p_j!)`` with ``p_i = dim-1-i``.
    """
    F = np.zeros((dim, dim))
    for i in range(dim):
        for j in range(i, dim):
            F[i, j] = dt ** (j - i) / math.factorial(j - i)
    Q1 = np.empty((dim, dim))
    for i in range(dim):
        for j in range(dim):
            pi, pj = dim - 1 - i, dim - 1 - j
            Q1[i, j] = 1.0 / ((pi + pj + 1) * math.factorial(pi) * math.factorial(pj))
    return F, Q1


def steady_state_gain(dt: float, quantum: float, process_noise: float, model: str = "ca") -> np.ndarray:
    """Steady-state Kalman gain (a posteriori form, from the predicted covariance).

    Solved in scaled coordinates ``s_i = x_i dt**i`` (where F has unit steps)
    with R normalized to 1, so the DARE is well conditioned whatever dt and q:
    there ``Q = lam * Q1`` with ``lam = q_c dt**(2n-1) / R``.
    """
    dim = _model_dim(model)
    dt = _check_positive("dt", dt)
    quantum = _check_positive("quantum", quantum)
    q_c = _check_positive("process_noise", process_noise)
    R = quantum**2 / 12.0  # quantization noise variance
    lam = q_c * dt ** (2 * dim - 1) / R
    F1, Q1 = kinematic_matrices(1.0, dim)
    H = np.zeros((1, dim))
    H[0, 0] = 1.0
    # Predicted covariance P solves P = F P F' - F P H' (H P H' + 1)^-1 H P F' + lam Q1
    P = scipy.linalg.solve_discrete_are(F1.T, H.T, lam * Q1, np.eye(1))
    K_s = P[:, 0] / (P[0, 0] + 1.0)  # K = P H' (H P H' + R)^-1 in scaled units
    scale = dt ** -np.arange(dim, dtype=float)  # x = S s, S = diag(dt^-i)
    return K_s * scale


def process_noise_for_bandwidth(dt: float, quantum: float, bandwidth_hz: float, model: str = "ca") -> float:
    r"""Process-noise density giving filter poles of radius :math:`2\pi f_b` (continuous-limit Butterworth).

    :math:`q_c = R\,\Delta t\,\omega_0^{2n}` with :math:`R = q^2/12`.
    """
    dim = _model_dim(model)
    dt = _check_positive("dt", dt)
    quantum = _check_positive("quantum", quantum)
    fb = _check_positive("bandwidth_hz", bandwidth_hz)
    if fb >= 0.5 / dt:
        raise ConfigError("bandwidth_hz", f"must be below Nyquist {0.5 / dt:.1f} Hz, got {fb!r}")
    w0 = 2.0 * math.pi * fb
    return quantum**2 / 12.0 * dt * w0 ** (2 * dim)


@numba.njit(cache=True)
def kalman_block(z: np.ndarray, F: np.ndarray, K: np.ndarray, x: np.ndarray, xp: np.ndarray, out: np.ndarray,
               skip: np.ndarray, zlast: np.ndarray) -> None:
    """x <- F x + K (z - H F x) per sample; writes the first 3 state components to out.

    ``skip[i]`` samples were lost just before ``z[i]`` (``skip`` empty: none). The filter steps through
    them on angles interpolated between the last one seen (``zlast[0]``, kept up to date here) and
    ``z[i]``: a gap then neither reads as one long step (a velocity too high by the lost fraction) nor
    leaves the fixed gain without its updates (prediction alone through a gap is unstable with a
    high-bandwidth steady-state gain). Rows of ``out`` are written for the samples in ``z`` only.
    """
    m = x.shape[0]
    gaps = skip.shape[0] > 0
    for i in range(z.shape[0]):
        g = skip[i] if gaps else 0
        for j in range(g + 1):
            zi = z[i] if j == g else zlast[0] + (z[i] - zlast[0]) * (j + 1) / (g + 1)
            for r in range(m):
                acc = 0.0
                for c in range(r, m):  # F is upper triangular
                    acc += F[r, c] * x[c]
                xp[r] = acc
            innov = zi - xp[0]
            for r in range(m):
                x[r] = xp[r] + K[r] * innov
        zlast[0] = z[i]
        for r in range(3):
            out[i, r] = x[r]


class SteadyStateKalman:
    """Steady-state Kalman filter for one quantized angle.

    Parameters
    ----------
    dt : sample period [s]
    quantum : angle quantization step q [rad] (R = q^2/12)
    process_noise : spectral density q_c of the white noise on the highest derivative
    model : "ca" (constant acceleration) or "cj" (constant jerk)

    ``filter_block(z)`` returns ``(n, 3)`` columns ``[angle, velocity,
    acceleration]`` and keeps the state between calls, so splitting a record
    into blocks gives bit-for-bit the same output. Without :meth:`reset` the
    state starts at ``[z[0], 0, 0...]`` on the first sample seen.
    """

    def __init__(self, dt: float, quantum: float, process_noise: float, model: str = "ca") -> None:
        self.dim = _model_dim(model)
        self.model = model
        self.dt = _check_positive("dt", dt)
        self.quantum = _check_positive("quantum", quantum)
        self.process_noise = _check_positive("process_noise", process_noise)
        self.R = self.quantum**2 / 12.0
        self.F, Q1 = kinematic_matrices(self.dt, self.dim)
        self.H = np.zeros((1, self.dim))
        self.H[0, 0] = 1.0
        self.Q = self.process_noise * Q1 * self._q_scale()  # design Q (= filterpy's Q_continuous_white_noise)
        self.gain = steady_state_gain(self.dt, self.quantum, self.process_noise, model)
        self.x = np.zeros(self.dim)
        self._xp = np.zeros(self.dim)
        self._zlast = np.zeros(1)          # the last angle filtered (interpolation across lost samples)
        self.initialized = False

    def _q_scale(self) -> np.ndarray:
        # Q[i, j] = q_c dt^(2n-1-i-j) Q1[i, j]: physical units of the unit-dt white-noise covariance
        i = np.arange(self.dim)
        return self.dt ** (2 * self.dim - 1 - i[:, None] - i[None, :])

    @classmethod
    def from_bandwidth(cls, dt: float, quantum: float, bandwidth_hz: float, model: str = "ca") -> SteadyStateKalman:
        """Filter whose poles have radius about 2*pi*bandwidth_hz (see :func:`process_noise_for_bandwidth`)."""
        return cls(dt, quantum, process_noise_for_bandwidth(dt, quantum, bandwidth_hz, model), model)

    def reset(self, z0: float) -> None:
        """Start from angle z0 at rest."""
        self.x[:] = 0.0
        self.x[0] = float(z0)
        self._zlast[0] = float(z0)
        self.initialized = True

    def _prepare(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, dtype=np.float64)
        if z.ndim != 1:
            raise DataError(f"z must be 1-D, got shape {z.shape}")
        if z.size and not self.initialized:
            self.reset(z[0])
        return np.ascontiguousarray(z)

    def filter_block(self, z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Filter a block of angles; returns (n, 3) [angle, velocity, acceleration] (compiled path).

        ``out`` (optional, (n, 3) float64, may be a strided view) receives the result.
        """
        z = self._prepare(z)
        if out is None:
            out = np.empty((z.shape[0], 3))
        elif out.shape != (z.shape[0], 3) or out.dtype != np.float64:
            raise DataError(f"out must be float64 of shape {(z.shape[0], 3)}, got {out.dtype} {out.shape}")
        kalman_block(z, self.F, self.gain, self.x, self._xp, out, _NO_GAPS, self._zlast)
        return out

    def filter_block_reference(self, z: np.ndarray) -> np.ndarray:
        """Plain-numpy reference of :meth:`filter_block` (same state, same equations)."""
        z = self._prepare(z)
        out = np.empty((z.shape[0], 3))
        F, K = self.F, self.gain
        x = self.x.copy()
        for i in range(z.shape[0]):
            xp = F @ x                      # predict: x- = F x
            x = xp + K * (z[i] - xp[0])     # update:  x = x- + K (z - H x-)
            out[i] = x[:3]
        self.x[:] = x
        if z.size:
            self._zlast[0] = z[-1]
        return out


_NO_GAPS = np.zeros(0, dtype=np.int64)
#: longest gap stepped through sample by sample; a longer one counts as this many samples
#: (the loop's watchdog has stopped the axis long before: 20 ticks)
MAX_GAP = 4096


@dataclass(frozen=True)
class AxisStates:
    """Estimated states of both angles; each array is (n, 2) with columns [motor, table]."""

    theta: np.ndarray
    omega: np.ndarray
    alpha: np.ndarray


def encoder_quanta(counts_per_rev: int, scale_resolution: float, lead: float) -> tuple[float, float]:
    """(q1, q2) [rad]: motor encoder step 2*pi/counts and table scale step as an angle, resolution/lead."""
    cpr = _check_positive("counts_per_rev", counts_per_rev)
    return 2.0 * math.pi / cpr, _check_positive("scale_resolution", scale_resolution) / _check_positive("lead", lead)


class AxisStateEstimator:
    """Two :class:`SteadyStateKalman` filters, motor angle and table angle.

    Give either ``process_noise`` (a number or a (motor, table) pair) or
    ``bandwidth_hz`` (a number or a pair).
    """

    def __init__(
        self,
        dt: float,
        quantum1: float,
        quantum2: float,
        process_noise: float | tuple[float, float] | None = None,
        *,
        bandwidth_hz: float | tuple[float, float] | None = None,
        model: str = "ca",
    ) -> None:
        if (process_noise is None) == (bandwidth_hz is None):
            raise ConfigError("process_noise", "give exactly one of process_noise or bandwidth_hz")
        quanta = (quantum1, quantum2)
        if process_noise is not None:
            qs = _pair(process_noise, "process_noise")
            self.filters = tuple(SteadyStateKalman(dt, q, pn, model) for q, pn in zip(quanta, qs))
        else:
            bws = _pair(bandwidth_hz, "bandwidth_hz")
            self.filters = tuple(SteadyStateKalman.from_bandwidth(dt, q, bw, model) for q, bw in zip(quanta, bws))
        self.dt = float(dt)
        # the sample expected next (filter_block with seq; -1: none yet), in place: the compiled tick
        # (rt_ident.loop.tick_core) holds a view
        self.next_seq = np.full(1, -1, dtype=np.int64)

    @property
    def _next_seq(self) -> int | None:
        v = int(self.next_seq[0])
        return None if v < 0 else v

    @_next_seq.setter
    def _next_seq(self, value: int | None) -> None:
        self.next_seq[0] = -1 if value is None else value

    def reset(self, theta1_0: float, theta2_0: float) -> None:
        self.filters[0].reset(theta1_0)
        self.filters[1].reset(theta2_0)
        self._next_seq = None

    def filter_block(self, theta1: np.ndarray, theta2: np.ndarray, seq: np.ndarray | None = None) -> AxisStates:
        """Filter one block of both angles; state carries over to the next call.

        ``seq``: the samples' sequence numbers. Samples missing from them (within the block, or since
        the previous block) are stepped through on interpolated angles, not skipped: without that a
        lost sample reads as a twice-as-long step, and the velocity estimate jumps by the lost fraction,
        which the position loop and the stopping-distance check would act on. Without ``seq`` samples are
        taken as consecutive.
        """
        z1 = np.ascontiguousarray(theta1, dtype=np.float64)
        z2 = np.ascontiguousarray(theta2, dtype=np.float64)
        if z1.ndim != 1 or z1.shape != z2.shape:
            raise DataError(f"theta1 and theta2 must be 1-D of equal length, got {z1.shape} and {z2.shape}")
        f1, f2 = self.filters
        if z1.size and not f1.initialized:
            f1.reset(z1[0])
        if z2.size and not f2.initialized:
            f2.reset(z2[0])
        # one allocation; each filter writes its (n, 3) result into a strided view of it
        skip = _NO_GAPS
        if seq is not None and z1.size:
            s = np.asarray(seq, dtype=np.int64)
            if s.shape != z1.shape:
                raise DataError(f"seq must match the angles' shape {z1.shape}, got {s.shape}")
            prev = self._next_seq if self._next_seq is not None else int(s[0])
            self._next_seq = int(s[-1]) + 1
            if s[-1] - prev + 1 != s.size:               # a gap somewhere (the common case has none)
                skip = np.empty(s.size, dtype=np.int64)
                skip[0] = s[0] - prev
                skip[1:] = np.diff(s) - 1
                np.clip(skip, 0, MAX_GAP, out=skip)
        big = np.empty((3, z1.shape[0], 2))
        kalman_block(z1, f1.F, f1.gain, f1.x, f1._xp, big[:, :, 0].T, skip, f1._zlast)
        kalman_block(z2, f2.F, f2.gain, f2.x, f2._xp, big[:, :, 1].T, skip, f2._zlast)
        return AxisStates(theta=big[0], omega=big[1], alpha=big[2])


def _pair(value: float | tuple[float, float] | None, name: str) -> tuple[float, float]:
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise ConfigError(name, f"must be a number or a (motor, table) pair, got {value!r}")
        return _check_positive(name, value[0]), _check_positive(name, value[1])
    v = _check_positive(name, value)  # type: ignore[arg-type]
    return v, v


__all__ = [
    "SteadyStateKalman",
    "AxisStateEstimator",
    "AxisStates",
    "steady_state_gain",
    "process_noise_for_bandwidth",
    "kinematic_matrices",
    "encoder_quanta",
]

"""Estimators the real-time loop can feed sample by sample, and the fit of their snapshots.

The loop's per-sample work must stay in microseconds, but a full fit can take
tens of milliseconds (the frequency method's Gauss-Newton on the exact sampled
model: ~90 ms measured). So each streaming estimator splits in two:

- ``update_block(theta1, theta2, torque, seq) -> bool``: the per-sample
  recursive part, run in the loop (a recursive DFT for "frequency", a UD-RLS
  update for "paper"); returns True when a new snapshot is worth fitting;
- ``snapshot()``: a small picklable summary of everything seen so far, and
  :func:`fit_snapshot` (method, snapshot) -> Identification, run by
  :func:`rt_ident.processes.jobs.make_fit_process` in its own process, never in the loop.

After the loop ends, :meth:`final` fits the last snapshot *cold* (no warm
start), so the loop's final estimate is a pure function of the samples: the
same value ``rt-ident identify`` computes by replaying the recording.

Lost samples (sequence gaps) are filled by linear interpolation so the
excitation period stays aligned with the sequence numbers; the count is
reported (``filled``), never hidden. A gap longer than ``MAX_FILL`` samples
is still filled but logged as a warning: the period it falls in is then
biased by the interpolation (the period-to-period scatter, and so the
intervals, show it). Sequence numbers going backwards raise DataError.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.base import Identification

if TYPE_CHECKING:
    from rt_ident.estimators.spectra import SpectraSums

log = logging.getLogger(__name__)

MAX_FILL = 64
STREAMING_METHODS = ("frequency", "paper")


class _GapFiller:
    """Keeps sequence numbers contiguous: interpolates short gaps, refuses long ones."""

    def __init__(self) -> None:
        # the last sequence number seen (-1: none) and its samples, in place: the compiled tick
        # (rt_ident.loop.tick_core) holds views
        self.seq = np.full(1, -1, dtype=np.int64)
        self.last = np.zeros(3)
        self.filled = 0

    @property
    def last_seq(self) -> int | None:
        v = int(self.seq[0])
        return None if v < 0 else v

    @last_seq.setter
    def last_seq(self, value: int | None) -> None:
        self.seq[0] = -1 if value is None else value

    def __call__(self, th1: np.ndarray, th2: np.ndarray, tq: np.ndarray,
                 seq: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seq = np.asarray(seq, dtype=np.int64)
        if seq.size == 0:
            return th1, th2, tq
        prev = self.last_seq
        n = seq.shape[0]
        first, last = int(seq[0]), int(seq[-1])
        if prev is not None and first == prev + 1 and last - first == n - 1:
            # the common case, in O(1): backends deliver strictly increasing sequence numbers
            # (drivers.base contract), so first/last spanning n values means no gap
            self.last_seq = last
            self.last[0], self.last[1], self.last[2] = th1[-1], th2[-1], tq[-1]
            return th1, th2, tq
        d = np.diff(seq)
        contiguous = (prev is None or first == prev + 1) and bool(np.all(d == 1))
        if not contiguous:
            full = np.arange(seq[0] if prev is None else prev + 1, seq[-1] + 1)
            gap = full.size - seq.size
            if gap < 0 or np.any(d <= 0):
                raise DataError("seq: sequence numbers go backwards or repeat")
            if gap > MAX_FILL:
                log.warning("seq: %d samples missing at seq %d; filled by interpolation", gap, int(full[0]))
            xs = seq if prev is None else np.concatenate(([prev], seq))
            cols = []
            for i, y in enumerate((th1, th2, tq)):
                ys = y if prev is None else np.concatenate(([self.last[i]], y))
                cols.append(np.interp(full, xs, ys))
            th1, th2, tq = cols
            self.filled += gap
            seq = full
        self.last_seq = int(seq[-1])
        self.last[:] = (th1[-1], th2[-1], tq[-1])
        return th1, th2, tq


class FrequencyStream:
    """The "frequency" method in streaming form (recursive DFT per sample)."""

    method = "frequency"

    def __init__(self, *, dt: float, period: int, band: tuple[int, int], warmup_periods: int = 2,
                 forgetting: float = 1.0, hold: str = "zoh", lead: float = 7.96e-4) -> None:
        from rt_ident.estimators.frequency_stream import StreamingFrequencyEstimator

        self.hold = hold
        self.lead = lead
        self.inner = StreamingFrequencyEstimator(period, np.arange(band[0], band[1] + 1), dt, hold,
                                                 forgetting, discard_periods=warmup_periods, lead=lead)
        self.gaps = _GapFiller()

    def update_block(self, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, seq: ArrayLike) -> bool:
        a, b, c = self.gaps(theta1, theta2, torque, seq)
        return self.inner.update_block(a, b, c) > 0

    def skip(self, n: int) -> None:
        """Leave the excitation periods the next ``n`` samples touch out of the fit (a loop stall)."""
        self.inner.skip(n)

    def snapshot(self) -> SpectraSums | None:
        """The running sums (:class:`~rt_ident.estimators.spectra.SpectraSums`), None before a period."""
        return self.inner.sums() if self.inner.periods >= 1 else None

    def final(self) -> Identification | None:
        snap = self.snapshot()
        return None if snap is None else fit_snapshot(self.method, snap, hold=self.hold, lead=self.lead)


class PaperStream:
    """The paper's Euler regression (Eq. 9) with recursive LS (Eqs. 14-16), every sample.

    Velocities come from the steady-state Kalman filter, as they would on a bench.
    """

    method = "paper"

    def __init__(self, *, dt: float, quanta: tuple[float, float], process_noise: float = 1e9,
                 forgetting: float = 1.0, lead: float = 7.96e-4, **_: Any) -> None:
        from rt_ident.estimators.rls import RecursiveLeastSquares
        from rt_ident.estimators.state_estimation import AxisStateEstimator

        self.dt, self.lead = dt, lead
        self.kf = AxisStateEstimator(dt, quanta[0], quanta[1], process_noise)
        self.rls = RecursiveLeastSquares(5, 4, p0=1e6, forgetting=forgetting)
        self._prev: np.ndarray | None = None
        self.gaps = _GapFiller()
        self._since = 0
        self._skip = 0

    def skip(self, n: int) -> None:
        """The next ``n`` samples are filtered but not regressed (a loop stall)."""
        self._skip = max(self._skip, int(n))

    def update_block(self, theta1: np.ndarray, theta2: np.ndarray, torque: np.ndarray, seq: ArrayLike) -> bool:
        a, b, c = self.gaps(theta1, theta2, torque, seq)
        st = self.kf.filter_block(a, b)
        x = np.column_stack((st.theta[:, 0], st.omega[:, 0], st.theta[:, 1], st.omega[:, 1], c))
        if self._prev is not None:
            x = np.vstack((self._prev, x))
        if self._skip:
            drop = min(self._skip, x.shape[0] - 1)
            self._skip -= drop
            x = x[drop:]
        if x.shape[0] >= 2:
            self.rls.update_block(x[:-1], x[1:, :4])     # Eq. (9): [x_k, T_k] -> x_{k+1}
        self._prev = x[-1:].copy()
        self._since += len(a)
        if self._since >= 512:
            self._since = 0
            return True
        return False

    def snapshot(self) -> dict[str, Any] | None:
        return {"phi": self.rls.theta.copy(), "dt": self.dt, "n": self.rls.n_updates} if self.rls.n_updates else None

    def final(self) -> Identification | None:
        snap = self.snapshot()
        return None if snap is None else fit_snapshot(self.method, snap, lead=self.lead)


def make_streaming(method: str, *, dt: float, period: int, band: tuple[int, int],
                             warmup_periods: int = 2, forgetting: float = 1.0, lead: float = 7.96e-4,
                             quanta: tuple[float, float] = (2 * np.pi / 2**17, 1e-7 / 7.96e-4),
                             process_noise: float = 1e9) -> FrequencyStream | PaperStream:
    if method == "frequency":
        return FrequencyStream(dt=dt, period=period, band=band, warmup_periods=warmup_periods,
                               forgetting=forgetting, lead=lead)
    if method == "paper":
        return PaperStream(dt=dt, quanta=quanta, process_noise=process_noise, forgetting=forgetting, lead=lead)
    raise ConfigError("estimator.method", f"{method!r} has no streaming form for the loop; "
                      f"use one of {', '.join(STREAMING_METHODS)} (all methods work offline with "
                      "'rt-ident identify')")


def fit_snapshot(method: str, snap: Any, *, hold: str = "zoh", lead: float = 7.96e-4) -> Identification:
    """Fit one snapshot, cold (deterministic). Runs in the job process or after the loop."""
    if method == "frequency":
        import dataclasses

        from rt_ident.estimators.frequency import fit_spectra, identification_from_fit
        from rt_ident.estimators.frf import frf_view

        if hasattr(snap, "spectra"):              # the loop's snapshot: the running sums
            snap = snap.spectra()
        fit = fit_spectra(snap, hold, quiet=True)    # an unconverged fit fails its trust check instead
        ident = identification_from_fit(snap, fit, hold, lead=lead)
        try:                              # the dashboard's FRF view; a fit is never lost over it
            view = frf_view(snap, fit.x, fit.cov[:4, :4], hold)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:   # OverflowError: a wild draw
            log.debug("frf view not built: %s", e)
            view = None
        return dataclasses.replace(ident, frf=view)
    if method == "paper":
        from rt_ident.axis.modal import modal_parameters
        from rt_ident.estimators.base import Identification as Ident
        from rt_ident.estimators.paper import recover_physical

        p = recover_physical(snap["phi"], snap["dt"], lead=lead)
        return Ident(p, "paper", None, modal_parameters(p), False, {"n_samples": float(snap["n"])})
    raise ConfigError("estimator.method", f"unknown streaming method {method!r}")

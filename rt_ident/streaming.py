"""Estimators the real-time loop can feed sample by sample, and the process that fits them.

The loop's per-sample work must stay in microseconds, but a full fit can take
tens of milliseconds (the frequency method's Gauss-Newton on the exact sampled
model: ~90 ms measured). So each streaming estimator splits in two:

- ``update_block(theta1, theta2, torque, seq) -> bool``: the per-sample
  recursive part, run in the loop (a recursive DFT for "frequency", a UD-RLS
  update for "paper"); returns True when a new snapshot is worth fitting;
- ``snapshot()``: a small picklable summary of everything seen so far, and
  :func:`fit_snapshot` (method, snapshot) -> Identification, run by
  :class:`FitWorker` in its own process, never in the loop.

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
import multiprocessing as mp
from dataclasses import dataclass
from typing import Any

import numpy as np

from rt_ident.errors import ConfigError, DataError
from rt_ident.estimators.base import Identification
from rt_ident.shm_ring import MessageRing

log = logging.getLogger(__name__)

_WORKER_POLL_S = 0.002  # fit worker: sleep between polls of an empty inbox

MAX_FILL = 64
STREAMING_METHODS = ("frequency", "paper")


class _GapFiller:
    """Keeps sequence numbers contiguous: interpolates short gaps, refuses long ones."""

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.last = np.zeros(3)
        self.filled = 0

    def __call__(self, th1, th2, tq, seq) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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

    def update_block(self, theta1, theta2, torque, seq) -> bool:
        a, b, c = self.gaps(theta1, theta2, torque, seq)
        return self.inner.update_block(a, b, c) > 0

    def snapshot(self):
        return self.inner.spectra() if self.inner.periods >= 1 else None

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
        from rt_ident.state_estimation import AxisStateEstimator

        self.dt, self.lead = dt, lead
        self.kf = AxisStateEstimator(dt, quanta[0], quanta[1], process_noise)
        self.rls = RecursiveLeastSquares(5, 4, p0=1e6, forgetting=forgetting)
        self._prev: np.ndarray | None = None
        self.gaps = _GapFiller()
        self._since = 0

    def update_block(self, theta1, theta2, torque, seq) -> bool:
        a, b, c = self.gaps(theta1, theta2, torque, seq)
        st = self.kf.filter_block(a, b)
        x = np.column_stack((st.theta[:, 0], st.omega[:, 0], st.theta[:, 1], st.omega[:, 1], c))
        if self._prev is not None:
            x = np.vstack((self._prev, x))
        if x.shape[0] >= 2:
            self.rls.update_block(x[:-1], x[1:, :4])     # Eq. (9): [x_k, T_k] -> x_{k+1}
        self._prev = x[-1:].copy()
        self._since += len(a)
        if self._since >= 512:
            self._since = 0
            return True
        return False

    def snapshot(self):
        return {"phi": self.rls.theta.copy(), "dt": self.dt, "n": self.rls.n_updates} if self.rls.n_updates else None

    def final(self) -> Identification | None:
        snap = self.snapshot()
        return None if snap is None else fit_snapshot(self.method, snap, lead=self.lead)


def make_streaming_estimator(method: str, *, dt: float, period: int, band: tuple[int, int],
                             warmup_periods: int = 2, forgetting: float = 1.0, lead: float = 7.96e-4,
                             quanta: tuple[float, float] = (2 * np.pi / 2**17, 1e-7 / 7.96e-4),
                             process_noise: float = 1e9):
    if method == "frequency":
        return FrequencyStream(dt=dt, period=period, band=band, warmup_periods=warmup_periods,
                               forgetting=forgetting, lead=lead)
    if method == "paper":
        return PaperStream(dt=dt, quanta=quanta, process_noise=process_noise, forgetting=forgetting, lead=lead)
    raise ConfigError("estimator.method", f"{method!r} has no streaming form for the loop; "
                      f"use one of {', '.join(STREAMING_METHODS)} (all methods work offline with "
                      "'rt-ident identify')")


def fit_snapshot(method: str, snap: Any, *, hold: str = "zoh", lead: float = 7.96e-4) -> Identification:
    """Fit one snapshot, cold (deterministic). Runs in the worker process or after the loop."""
    if method == "frequency":
        from rt_ident.estimators.frequency import fit_spectra, identification_from_fit

        fit = fit_spectra(snap, hold)
        return identification_from_fit(snap, fit, hold, lead=lead)
    if method == "paper":
        from rt_ident.estimators.base import Identification as Ident
        from rt_ident.estimators.paper import recover_physical
        from rt_ident.modal import modal_parameters

        p = recover_physical(snap["phi"], snap["dt"], lead=lead)
        return Ident(p, "paper", None, modal_parameters(p), False, {"n_samples": float(snap["n"])})
    raise ConfigError("estimator.method", f"unknown streaming method {method!r}")


def _worker_main(method: str, hold: str, lead: float, inbox: MessageRing, outbox: MessageRing,
                 min_interval: float) -> None:
    import time

    inbox.flag = 1                                   # ready for a snapshot
    while True:
        closed = inbox.writer_closed
        if not inbox.pending_messages:
            if closed:
                return
            time.sleep(_WORKER_POLL_S)
            continue
        inbox.flag = 0                               # busy: the loop keeps its snapshots
        _, snap = inbox.get_object()
        t0 = time.monotonic()
        try:
            result: Any = fit_snapshot(method, snap, hold=hold, lead=lead)
        except Exception as exc:  # noqa: BLE001 - reported to the parent, never fatal here
            result = exc
        try:
            ok = outbox.put_object(result)
        except Exception as exc:  # noqa: BLE001 - e.g. an exception that does not pickle
            ok = outbox.put_object(RuntimeError(f"{type(result).__name__}: {exc}"))
        if not ok:
            log.warning("fit worker: result ring full, result dropped")
        # duty-cycle limit: a fit takes ~25 ms; a few per second are plenty for a live view, and
        # the CPU left over belongs to the loop (meanwhile the loop keeps its newer snapshots)
        while time.monotonic() - t0 < min_interval and not inbox.writer_closed:
            time.sleep(0.01)
        inbox.flag = 1


@dataclass
class FitWorker:
    """Fits snapshots in a separate process. ``submit`` and ``poll`` never block the caller.

    Snapshots and results travel through shared-memory rings (:mod:`rt_ident.shm_ring`: no
    feeder thread in the loop's process). The worker says when it is ready for the next
    snapshot; ``submit`` sends one only then, so a snapshot is pickled at most a few times
    per second (``skipped`` counts the ones not sent because a fit was running).
    """

    method: str
    hold: str = "zoh"
    lead: float = 7.96e-4
    min_interval: float = 0.25      # s between fits
    ring_bytes: int = 4 << 20       # per direction; a snapshot is a few kB

    def __post_init__(self) -> None:
        ctx = mp.get_context("spawn")
        self._in = MessageRing(self.ring_bytes, max_messages=1, ctx=ctx)
        self._out = MessageRing(self.ring_bytes, ctx=ctx)
        self._proc = ctx.Process(target=_worker_main, args=(self.method, self.hold, self.lead, self._in, self._out,
                                                            self.min_interval),
                                 name="rt_ident-fit", daemon=True)
        self.skipped = 0
        self.fits = 0
        self.errors = 0
        self.last_error: str | None = None

    def start(self) -> "FitWorker":
        self._proc.start()
        return self

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    @property
    def ready(self) -> bool:
        """True when the worker waits for a snapshot (and none is on its way)."""
        return bool(self._in.flag) and not self._in.pending_messages

    def submit(self, snap: Any) -> bool:
        """Send ``snap`` if the worker is ready for it (True), else count it as skipped."""
        if snap is None:
            return False
        if not self.ready or not self._in.put_object(snap):
            self.skipped += 1
            return False
        return True

    def poll(self) -> Identification | None:
        """The newest result the worker has returned since the last poll, or None."""
        if not self._out.pending_messages:
            return None
        latest = None
        for msg in self._out.get():
            item = MessageRing.unpickle(msg)
            if isinstance(item, Exception):
                self.errors += 1
                self.last_error = str(item)
            else:
                self.fits += 1
                latest = item
        return latest

    def close(self, timeout: float = 5.0) -> None:
        self._in.close_writer()
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(1.0)

"""The loop's telemetry windows (a part of :class:`rt_ident.loop.loop.IdentificationLoop`): every
``stride``-th sample and each tick's signals go into preallocated rows; every ``publish_every`` ticks
the window is handed to the telemetry process, its samples on one tick and its per-tick signals (with
the values that hold over the whole window as one vector) on the next, so that no tick carries both
hand-offs. A :class:`~rt_ident.processes.telemetry.TelemetryProcess` takes the rows as they are
(``publish_rows``: one compiled write into its ring); any other consumer gets dicts of arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.base import Backend, SampleBlock
from rt_ident.loop import tick_kernel as tk

if TYPE_CHECKING:
    from rt_ident.control.adaptation import Supervisor
    from rt_ident.estimators.base import Identification
    from rt_ident.loop.stats import LoopStats
    from rt_ident.loop.tick_core import AxisCore

_WINDOW_CI_KEYS = frozenset(("I1", "I2", "B", "K", "wn", "wd", "zeta"))


class TelemetryWindow:
    """The window half of the loop (its state: ``tel_rows``, ``tick_rows`` and the counters in
    ``book_i``, which the compiled tick writes too)."""

    # the loop's, set by IdentificationLoop.__init__
    backend: Backend
    tick_hz: float
    stride: int
    publish_every: int
    control: Supervisor | None
    identification: Identification | None
    torque_ident: Identification | None
    stats: LoopStats
    on_telemetry: Callable[..., Any] | None
    on_loop_gain: Callable[[float, Any, Any], Any] | None
    _shown_controller: Any
    _core: AxisCore | None
    # the loop's bookkeeping by name (IdentificationLoop's views of book_i)
    _next_seq: int
    _tel_n: int
    _tick_n: int
    _win_ticks: int
    _flush_at: int
    _sample_keys: tuple[str, ...]

    def _telemetry_buffers(self) -> None:
        """Preallocated window buffers (rows ``tick_kernel.SAMPLE_KEYS`` and ``TICK_KEYS``): a tick writes
        into them; nothing is concatenated."""
        per_tick = int(math.ceil(1.0 / (self.tick_hz * self.backend.sample_period) / self.stride)) + 2
        cap = max(64, 4 * self.publish_every * per_tick)
        self.tel_rows = np.zeros((len(tk.SAMPLE_KEYS), cap))
        self.tick_rows = np.zeros((len(tk.TICK_KEYS), self.publish_every + 1))   # a tick window may be one tick longer
        self._win_next: tuple[tuple[str, ...], np.ndarray] | None = None   # window values gathered for the next tick
        # the window's values, and what they were made from (the estimate, the controller, the counts)
        self._win_cache: tuple[Any, Any, Any, Any] = (None, None, None, None)
        # the per-sample estimate goes as tick rows (its values change every tick)
        self._svf_rows = self.control is not None and getattr(self.control, "per_sample", None) is not None and \
            self.control.s.mode == "adaptive"
        tp = getattr(self.on_telemetry, "__self__", None)
        # a TelemetryProcess takes the window's rows as they are (publish_rows); anything else a dict
        self._publisher = tp if getattr(self.on_telemetry, "__name__", "") == "publish" and \
            hasattr(tp, "publish_rows") else None

    @property
    def _tel_buf(self) -> dict[str, np.ndarray]:
        return dict(zip(tk.SAMPLE_KEYS, self.tel_rows))

    def _collect_telemetry(self, block: SampleBlock, trace: np.ndarray, lateness_s: float) -> None:
        self._collect_samples(block, trace)
        k = self._tick_n
        rows = self.tick_rows
        rows[0, k] = block.t[-1]
        rows[1, k] = lateness_s * 1e6
        ctl = self.control
        if ctl is not None:
            rows[2, k] = ctl.x_ref
            rows[3, k] = ctl.x_ref + ctl.error
            rows[4, k] = ctl.error
            rows[5, k] = ctl.law.u
            if self._svf_rows:
                rows[6:10, k] = ctl.per_sample.values_array()
        self._tick_n = k + 1
        self._win_ticks += 1
        # the samples go when a window ends, the per-tick signals one tick later: each hand-off costs
        # tens of microseconds, and both on one tick would make it the slowest tick of all but a few
        if self._win_ticks >= self._flush_at:
            self._flush_telemetry(ticks=False)
            self._flush_at = self.publish_every
        elif self._tick_n > self.publish_every or (self._win_ticks == 1 and self._tick_n > 1):
            self._flush_telemetry(samples=False)

    def _collect_samples(self, block: SampleBlock, trace: np.ndarray) -> None:
        """Every ``stride``-th sample of the block (from its first) into the window buffers, with the
        measured torque through the SVF and its Eq. (18) reconstruction (``trace``: the SVF's filtered
        signals of the block, no rows without it; ``tick_kernel.collect_samples``, as the compiled tick)."""
        stride = self.stride
        n = len(block)
        m = -(-n // stride)
        cap = self.tel_rows.shape[1]
        start = 0
        if self._tel_n + m > cap:
            self._flush_telemetry()               # a burst (after a stall): publish what is there first
            if m > cap:                           # keep the newest samples of an oversized burst
                start = (m - cap) * stride
        ident = self.torque_ident
        if ident is None:
            hat = (False, 0.0, 0.0, 0.0)
        else:
            p = ident.params
            hat = (True, float(p.I1), float(p.B), float(p.K))
        i = self._tel_n
        self._tel_n = i + tk.collect_samples(self.tel_rows, i, stride, block.t[start:], block.theta1[start:],
                                             block.theta2[start:], block.torque[start:], block.torque_cmd[start:],
                                             trace[start:], *hat)

    def _flush_telemetry(self, samples: bool = True, ticks: bool = True) -> None:
        """Publish the window: the decimated samples, per-tick lateness and the current estimate.

        ``on_telemetry(block)`` gets the samples, then ``on_telemetry(ticks, window)`` the per-tick
        signals and, in ``window`` (name -> float), those that hold one value over the whole window.
        The arrays are views of the window buffers, valid only during the call (it copies, as
        :meth:`rt_ident.processes.telemetry.TelemetryProcess.publish` does into its ring). A
        :class:`~rt_ident.processes.telemetry.TelemetryProcess` gets the same through
        ``publish_rows``: the rows and the window vector, written into its ring by one compiled call.
        """
        if self.on_telemetry is None:
            return
        if self._core is not None:           # a window vector the compiled tick kept is stale now
            self._core.forget_window()
        n = self._tel_n if samples else 0
        k = self._tick_n if ticks else 0
        if samples:
            self._win_ticks = 0
        if n:
            self._hand_over(self._sample_keys, self.tel_rows, n)
        if samples and not ticks:
            # the window values are gathered now, the per-tick signals go on the next tick: this
            # tick's hand-off is the smaller one, so the two ticks carry about the same extra work
            self._win_next = self._window_values(self._tick_n)
        if k:
            m = 3 if self.control is None else len(_TICK_FIELDS) if self._svf_rows else len(_TICK_FIELDS) - 4
            win = self._win_next if self._win_next is not None else self._window_values(k)
            self._win_next = None
            self._hand_over(_TICK_FIELDS[:m], self.tick_rows, k, _TICK_ROWS[:m], win)
        if samples:
            self._tel_n = 0
        if ticks:
            self._tick_n = 0

    def _hand_over(self, keys: tuple[str, ...], rows: np.ndarray, n: int, index: np.ndarray | None = None,
                   window: tuple[tuple[str, ...], np.ndarray] | None = None) -> None:
        """``{keys[i]: rows[index[i], :n]}`` (and the window) to the telemetry consumer."""
        tp = self._publisher
        if tp is not None:
            tp.publish_rows(keys, rows, n, index, window)
            return
        send = self.on_telemetry
        if send is None:                  # no consumer: the callers do not hand over then
            return
        idx = range(len(keys)) if index is None else index
        block = {key: rows[i, :n] for key, i in zip(keys, idx)}
        if window is None:
            send(block)
        else:
            send(block, dict(zip(*window)))

    def publish_final(self) -> None:
        """After the run's final fit: one more telemetry window, at the last sample's time, carrying
        the final estimate, so that the dashboard's estimate lines (and the true values beside them)
        end on the value the run reports. A short run, or one beside a busy machine, may have no
        fit-process result at all, and its dashboard would show no estimate and no true value."""
        if self.on_telemetry is None or self.identification is None:
            return
        t = np.full((1, 1), max(self._next_seq - 1, 0) * self.backend.sample_period)
        self._hand_over(("t", "t_tick"), t, 1, _TICK_ROWS[:2], self._window_values(0))

    def _window_values(self, k: int) -> tuple[tuple[str, ...], np.ndarray]:
        """The signals that hold one value over a telemetry window (the estimate, its intervals, the
        controller's figures, the overruns), as (names, values). They go as one vector (``window``), not
        as ~30 arrays of k equal values: building and copying those would be most of a window's hand-off.
        They change only with a new estimate, a new controller, a redesign's verdict, a fallback, an
        overrun or a stall: the vector is rebuilt then, and handed over as it is otherwise."""
        ident, ctl, overruns, stalls = self.identification, self.control, self.stats.overruns, self.stats.stalls.count
        c = ctl.controller if ctl is not None else None
        if c is not None and self.on_loop_gain is not None and c is not self._shown_controller and k:
            self._shown_controller = c
            self.on_loop_gain(float(self.tick_rows[0, k - 1]), c.loop_view,
                              {"pm_deg": (c.margins or {}).get("pm_deg"), "gm_db": c.gain_margin_db})
        st = ctl.stats if ctl is not None else None
        key = (overruns, stalls, st.accepted, st.rejected, st.fallbacks) if st is not None else (overruns, stalls)
        cached = self._win_cache
        if cached[0] is ident and cached[1] is c and cached[2] == key:
            return cached[3]
        part: dict[str, float] = {"overruns": float(overruns), "stalls": float(stalls)}
        if ident is not None:
            p = ident.params
            part["I1"], part["I2"], part["B"], part["K"] = p.I1, p.I2, p.B, p.K
            modal = ident.modal
            part["wn"], part["wd"], part["zeta"] = modal["wn"], modal["wd"], modal["zeta"]
            for name, (lo, hi) in (ident.ci95 or {}).items():
                if name in _WINDOW_CI_KEYS:
                    part[f"lo_{name}"] = lo
                    part[f"hi_{name}"] = hi if math.isfinite(hi) else math.nan
        if c is not None and st is not None:
            pm = (c.margins or {}).get("pm_deg")
            part["n_accepted"], part["n_rejected"], part["fallbacks"] = \
                float(st.accepted), float(st.rejected), float(st.fallbacks)
            part["gain_theta2"], part["gain_omega1"] = float(c.gains[2]), float(c.gains[1])
            part["pm_deg"] = math.nan if pm is None else float(pm)
            part["gm_db"] = float(c.gain_margin_db)
        window = (tuple(part), np.array(list(part.values())))
        self._win_cache = (ident, c, key, window)
        return window


_TICK_FIELDS = tk.TICK_FIELDS                                  # a tick window's fields ...
_TICK_ROWS = np.array(tk.TICK_ROWS, dtype=np.int64)             # ... and their rows in tick_rows

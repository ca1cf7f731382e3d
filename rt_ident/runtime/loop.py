"""The real-time identification loop: read -> estimate -> write, on absolute deadlines.

Each tick (default 1 kHz):

1. ``backend.read()`` returns every sample since the previous tick;
2. the steady-state Kalman filter turns the angles into omega and alpha
   (for the safety monitor and the Eq. 18 torque reconstruction);
3. the streaming estimator takes every sample (the default "frequency"
   method updates its per-harmonic DFT sums sample by sample); when a full
   excitation period completes, a snapshot goes to the fit worker process
   and the newest fit it returned becomes the current estimate;
4. the position controller (:class:`rt_ident.control.adaptation.Supervisor`, when there is
   one) takes the state estimate at the newest sample and returns the torque for the next
   tick: the host closes the position loop (a drive in torque mode holds nothing);
5. the safety monitor checks watchdog, stuck encoder and the stopping window;
6. the torque plan for the next two ticks is written, keyed by sample sequence number: the
   control torque held per tick (the one computed now lands one tick after the newest
   sample, the one-tick delay the controller was designed with) plus the probing
   excitation per sample, so the excitation is exact at the backend's sample rate.
   The plan is leased (``[safety] torque_hold``): without a newer plan its last value
   holds that long, then the torque is zero. The plan starts at the first sample not yet
   read, so feedback that stops coming also ends the torque, not only a stalled loop;
7. raw samples go to the recorder process and, every few ticks, a decimated
   block to the telemetry process — both through non-blocking hand-offs.

Nothing else runs here: no rerun call, no file write, no per-tick logging.
Any exception, a safety trip, SIGINT or SIGTERM ends the loop; the backend's
context manager then stops it (zero torque, drive disabled).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.base import Backend, SampleBlock
from rt_ident.errors import RtIdentError
from rt_ident.runtime.safety import SafetyMonitor
from rt_ident.runtime.scheduler import LatenessHistogram, Ticker

log = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """Counters of one run. An overrun is a tick that found its deadline passed by whole periods;
    it is put down to the work of the tick before (``overruns_work``: that tick's own computation,
    measured as the loop thread's CPU time, took longer than the period) or else to a late start
    (``overruns_late_start``: the host or the scheduler took the CPU before or during the tick, or
    the tick waited on I/O; the wall-clock work time ``work_us`` then exceeds the CPU time
    ``work_cpu_us``)."""

    ticks: int = 0
    samples: int = 0
    lost_samples: int = 0
    overruns: int = 0
    overruns_work: int = 0
    overruns_late_start: int = 0
    skipped_periods: int = 0
    estimates: int = 0
    lateness: LatenessHistogram = field(default_factory=LatenessHistogram)
    work: LatenessHistogram = field(default_factory=LatenessHistogram)
    work_cpu: LatenessHistogram = field(default_factory=LatenessHistogram)
    # a simulated device's stepping ahead after the tick (Backend.step_ahead), not part of ``work``
    sim_ahead: LatenessHistogram = field(default_factory=LatenessHistogram)

    def as_dict(self) -> dict[str, Any]:
        lat = self.lateness.summary()
        work = self.work.summary()
        cpu = self.work_cpu.summary()
        return {"ticks": self.ticks, "samples": self.samples, "lost_samples": self.lost_samples,
                "overruns": self.overruns, "overruns_work": self.overruns_work,
                "overruns_late_start": self.overruns_late_start, "skipped_periods": self.skipped_periods,
                "estimates": self.estimates,
                "lateness_us": {"p50": lat["p50"], "p99": lat["p99"], "max": lat["max"]},
                "work_us": {"p50": work["p50"], "p99": work["p99"], "max": work["max"]},
                "work_cpu_us": {"p50": cpu["p50"], "p99": cpu["p99"], "max": cpu["max"]},
                **({"sim_ahead_us": {k: ahead[k] for k in ("p50", "p99", "max")}}
                   if (ahead := self.sim_ahead.summary())["count"] else {})}


#: A simulated device steps ahead to this long after the next deadline (Backend.step_ahead). The
#: next read comes a few microseconds after the deadline; without a margin, one read in ~6 found a
#: sample come due in between and stepped it then (a full stepping call for one sample: the read's
#: p99 stayed at 52-65 us). A drive applies its samples in that stretch with the plan it holds, the
#: one written a tick earlier: the host's next write lands only after the tick's work (>= 90 us
#: here), and its first values for those samples count as ``late_plan_samples``. The torque is the
#: same either way: the controller's torque lands ``delay_ticks`` >= 1 tick later, and the probe's
#: values are the same in both plans.
SIM_AHEAD_MARGIN_S = 100e-6


def _count_tick(stats: LoopStats, info, last_cpu: float, period: float) -> None:
    """A tick's timing counters: an overrun is charged to the previous tick's CPU time when that
    exceeded the period (its own work), else to a late start."""
    stats.ticks += 1
    if info.skipped:
        stats.overruns += 1
        stats.skipped_periods += info.skipped
        if last_cpu > period:
            stats.overruns_work += 1
        else:
            stats.overruns_late_start += 1
    stats.lateness.record(info.lateness_s)


_WINDOW_CI_KEYS = frozenset(("I1", "I2", "B", "K", "wn", "wd", "zeta"))


def _eq18(p, th1, th2, w1, w2, a1):
    """Eq. (18), motor row: T_hat = I1 th1'' + B (th1' - th2') + K (th1 - th2); floats or arrays."""
    return p.I1 * a1 + p.B * (w1 - w2) + p.K * (th1 - th2)


class IdentificationLoop:
    """Joins a backend, a state estimator, a streaming estimator and the hand-offs.

    Everything is constructed and warmed up by the caller (:mod:`rt_ident.runtime.run`);
    :meth:`run` only ticks.
    """

    def __init__(self, backend: Backend, *, tick_hz: float, excitation: Callable[[np.ndarray], np.ndarray],
                 state_estimator, estimator, safety: SafetyMonitor, duration: float, fit_worker=None,
                 on_block: Callable[[SampleBlock], None] | None = None,
                 on_telemetry: Callable[..., Any] | None = None,
                 publish_every: int = 20, telemetry_stride: int = 34,
                 stop_event: threading.Event | None = None, clock: Callable[[], float] = time.perf_counter,
                 tick_hook: Callable[[int], None] | None = None,
                 max_sleep_s: float | None = 100e-6, control=None, ticker: Ticker | None = None,
                 probe_period: int | None = None, on_fit: Callable[[float, Any], Any] | None = None,
                 on_loop_gain: Callable[[float, Any, Any], Any] | None = None, friction=None,
                 friction_feedforward: bool = True) -> None:
        self.backend = backend
        self.ticker = ticker or Ticker(1.0 / tick_hz, clock=clock, max_sleep_s=max_sleep_s)
        self.tick_hz = tick_hz
        self.excitation = excitation
        self.kf = state_estimator
        self.est = estimator
        self.worker = fit_worker
        self.safety = safety
        self._stuck_torque = float(getattr(safety, "stuck_torque", 0.0))   # see SafetyMonitor.stuck_torque
        self.duration = duration
        self.on_block = on_block
        self.on_telemetry = on_telemetry
        self.on_fit = on_fit                # a new fit's FRF view -> the dashboard (never blocks)
        self.on_loop_gain = on_loop_gain    # a new controller's loop gain -> the dashboard
        self._shown_controller: Any = None
        self.publish_every = max(1, publish_every)
        self._flush_at = self.publish_every      # ticks in the current telemetry window (MultiAxisLoop staggers)
        self.fit_phase = 3                       # the fit exchange's 10-tick cycle starts here (_fit_exchange)
        # snapshot to send, results taken, result to offer, FRF to draw (_fit_exchange)
        self._fit_stage: list[Any] = [None, None, None, None]
        self.stride = max(1, telemetry_stride)
        self.stop_event = stop_event or threading.Event()
        self.clock = clock
        self.tick_hook = tick_hook          # test seam: e.g. inject a slow tick
        self.stats = LoopStats()
        self.identification = None          # latest Identification (or None before the first period)
        self.control = control              # the host's position controller (None: excitation only)
        self.friction = friction            # per-sample friction-model estimator ([estimator] model), or None
        self.friction_feedforward = friction_feedforward
        self._next_seq = 0
        self._seq0: int | None = None       # first sequence number: the control clock starts there
        self._per_tick = max(1, int(round(1.0 / (tick_hz * backend.sample_period))))
        self._u_base = 0.0                  # control torque in force at the newest sample
        self._u_sched: list[tuple[int, float]] = []   # (first seq, torque) still to land, in order
        self._probe_period = probe_period   # excitation period [samples]: its amplitude changes on period edges
        self._probe = (1.0, 1.0, 0)         # (scale now, scale from seq on, that seq)
        self._plan_len = int(math.ceil(2.0 / (tick_hz * backend.sample_period))) + 2
        # a periodic probe is tabulated once (a period and a plan's length more): the plan slices it
        self._ex_table = (None if not probe_period else
                          np.asarray(excitation(np.arange(probe_period + self._plan_len)), dtype=float))
        hold = getattr(safety, "torque_hold", None)      # the plan's lease (see drivers.base.Backend.write)
        self._lease = None if hold is None else int(math.ceil(hold / backend.sample_period))
        if on_telemetry is not None:
            self._telemetry_buffers()

    # ------------------------------------------------------------------ run
    def run(self) -> LoopStats:
        backend, stats = self.backend, self.stats
        self._write_plan()
        n_ticks = int(round(self.duration * self.tick_hz))
        period = 1.0 / self.tick_hz
        clock = self.clock
        cpu_clock = time.thread_time
        last_cpu = 0.0
        self.ticker.start()
        for _ in range(n_ticks):
            if self.stop_event.is_set():
                break
            info = self.ticker.wait_next()
            t0 = clock()
            c0 = cpu_clock()
            _count_tick(stats, info, last_cpu, period)
            block = backend.read()
            self._process(block, info.lateness_s)
            self._write_plan()
            t1 = clock()
            stats.work.record(t1 - t0)
            # a simulated device steps through the samples due by the next deadline now (a real one
            # does nothing): what the tick's work measures is the host's part, as with a device
            backend.step_ahead(self.ticker.next_deadline() - t1 + SIM_AHEAD_MARGIN_S)
            if backend.simulated:
                stats.sim_ahead.record(clock() - t1)
            last_cpu = cpu_clock() - c0
            stats.work_cpu.record(last_cpu)
            if self.tick_hook is not None:
                self.tick_hook(stats.ticks)
        self._flush_telemetry()
        return stats

    # --------------------------------------------------------------- pieces
    def _process(self, block: SampleBlock, lateness_s: float = 0.0) -> None:
        n = len(block)
        stats = self.stats
        if n == 0:
            self.safety.check(0, 0.0, 0.0, 0.0, True)
            return
        stats.samples += n
        stats.lost_samples += block.lost
        if self.on_block is not None:               # record first: a block that trips a check is kept
            self.on_block(block)
        torque = block.torque
        states = self.kf.filter_block(block.theta1, block.theta2, block.seq)
        if self.est.update_block(block.theta1, block.theta2, torque, block.seq) and self.worker is not None:
            if self.worker.ready:                       # a snapshot only when the worker waits for one
                self._fit_stage[0] = self.est.snapshot()    # taken now, sent on this axis's send tick
            else:
                self.worker.skipped += 1
        ctl = self.control
        if ctl is not None:                             # the per-sample estimator, every sample
            ctl.observe(block.theta1, block.theta2, torque, block.lost > 0 or int(block.seq[0]) != self._next_seq)
        if self.friction is not None:
            self._friction(block, torque, ctl, stats.ticks)
        if self.worker is not None:
            self._fit_exchange(ctl, float(block.t[-1]), stats.ticks)
        if ctl is not None:
            self._control(ctl, block, states)
        self.safety.check(n, float(block.theta1[-1]), float(block.theta2[-1]), float(states.omega[-1, 1]),
                          abs(self.backend.last_torque) > self._stuck_torque)
        self._next_seq = int(block.seq[-1]) + 1
        if self.on_telemetry is not None:
            self._collect_telemetry(block, states, lateness_s)

    def _fit_exchange(self, ctl, t: float, tick: int) -> None:
        """The exchange with the fit worker, one step per tick of a 10-tick cycle: send the snapshot
        taken at the end of an excitation period; take a result from the worker's ring; unpickle
        it; hand it to the controller; draw its FRF. Each step costs tens of microseconds; done on
        one tick they and a telemetry hand-off made the tick's p99. ``fit_phase`` shifts the cycle
        (MultiAxisLoop gives each axis its own ticks)."""
        step = (tick - self.fit_phase) % 10
        stage = self._fit_stage
        if step == 0:
            if stage[0] is not None:
                self.worker.submit(stage[0])            # the fit runs in the worker process
                stage[0] = None
        elif step == 1:
            stage[1] = self.worker.take()
        elif step == 2:
            got, stage[1] = stage[1], None
            latest = self.worker.unpack(got) if got else None
            if latest is not None:
                self.identification = latest
                self.stats.estimates += 1
                stage[2] = latest
        elif step == 3:
            latest, stage[2] = stage[2], None
            if latest is not None:
                if ctl is not None:
                    ctl.offer(latest, bool(latest.trusted))
                stage[3] = latest
        elif step == 4:
            latest, stage[3] = stage[3], None
            if latest is not None and self.on_fit is not None and latest.frf is not None:
                self.on_fit(t, latest.frf)

    _FRICTION_EVERY = 100   # ticks between friction estimates handed to the controller's feedforward

    def _friction(self, block: SampleBlock, torque, ctl, tick: int) -> None:
        """Feed the friction-model estimator every sample; every 100 ticks its Fc, Fv become the
        controller's friction feedforward (rt_ident.control.feedforward) when that is on."""
        fr = self.friction
        fr.update_block(block.theta1, None if fr.model == "rigid-friction" else block.theta2, torque)
        if ctl is None or not self.friction_feedforward or tick % self._FRICTION_EVERY:
            return
        est = fr.estimate()
        if est is None:
            return
        from rt_ident.control.feedforward import FrictionFeedforward

        try:
            ff = FrictionFeedforward.from_parameters(est)
        except RtIdentError:
            return
        if all(math.isfinite(v) for v in (ff.Fc, ff.Fv)):
            ctl.law.friction = ff

    def _control(self, ctl, block: SampleBlock, states) -> None:
        """The controller's torque from the newest sample's state estimate; it lands ``delay`` ticks
        after that sample (the delay the controller was designed with)."""
        last = int(block.seq[-1])
        if self._seq0 is None:
            self._seq0 = int(block.seq[0])
        th, om = states.theta[-1], states.omega[-1]
        u = ctl.tick((last - self._seq0) * self.backend.sample_period, float(th[0]), float(om[0]),
                     float(th[1]), float(om[1]))
        ctl.poll()
        sched = self._u_sched
        while sched and sched[0][0] <= last + 1:     # landed: in force from the next sample on
            self._u_base = sched.pop(0)[1]
        sched.append((last + 1 + ctl.law.delay * self._per_tick, u))

    def _write_plan(self) -> None:
        start, n = self._next_seq, self._plan_len
        torque = self._excitation_window(start)
        ctl = self.control
        if ctl is not None:
            self._probe_amplitude(ctl.probe_scale, start)
            now, later, edge = self._probe
            if now != 1.0 or later != 1.0:
                cut = min(max(edge - start, 0), n)
                torque[:cut] *= now
                torque[cut:] *= later
            torque += self._u_base                      # the control torque: piecewise constant over the plan
            level = self._u_base
            for first, value in self._u_sched:
                cut = max(first - start, 0)
                if cut >= n:
                    break
                torque[cut:] += value - level
                level = value
        self.backend.write(torque, start_seq=start, lease=self._lease)

    def _excitation_window(self, start: int) -> np.ndarray:
        """The probing excitation for seq [start, start + plan length), a new array. A periodic
        excitation (``probe_period`` given) is read from one period tabulated up front, as a slice."""
        n = self._plan_len
        table = self._ex_table
        if table is None:
            return np.array(self.excitation(np.arange(start, start + n)), dtype=float)
        i = start % self._probe_period
        return table[i:i + n].copy()

    def _probe_amplitude(self, want: float, start: int) -> None:
        """Dual excitation: the probing amplitude follows ``want`` from the next period edge on
        (a whole period at one amplitude keeps the multisine periodic for the estimator)."""
        now, later, edge = self._probe
        if start >= edge:
            now = later
        if want != later:
            n = self._probe_period or 1
            later, edge = want, -(-start // n) * n
        self._probe = (now, later, edge)

    # ------------------------------------------------------------ telemetry
    _SAMPLE_KEYS = ("t", "theta1", "theta2", "torque_meas", "torque_cmd", "torque_hat")
    _CONTROL_TICK_KEYS = ("x_ref", "x_table", "error_m", "u_control")

    def _telemetry_buffers(self) -> None:
        """Preallocated window buffers: a tick writes slices into them; nothing is concatenated."""
        per_tick = int(math.ceil(1.0 / (self.tick_hz * self.backend.sample_period) / self.stride)) + 2
        cap = max(64, 4 * self.publish_every * per_tick)
        self._tel_buf = {k: np.empty(cap) for k in self._SAMPLE_KEYS}
        self._tel_n = 0
        self._tel_hat_ok = True
        self._tick_t = np.empty(self.publish_every + 1)          # a tick window may be one tick longer
        self._tick_late = np.empty(self.publish_every + 1)
        self._tick_ctl = {k: np.empty(self.publish_every + 1) for k in self._CONTROL_TICK_KEYS}
        self._tick_n = 0
        self._win_ticks = 0                     # ticks in the current sample window
        self._win_next: dict[str, float] | None = None      # window values gathered for the next tick
        self._win_ident: tuple[Any, dict[str, float]] = (None, {})   # the estimate's window values

    def _collect_telemetry(self, block: SampleBlock, states, lateness_s: float) -> None:
        if len(block) <= self.stride and self._tel_n < self._tel_buf["t"].shape[0]:
            self._collect_one(block, states)        # the usual tick at the usual rate: one sample kept
        else:
            self._collect_slices(block, states)
        k = self._tick_n
        self._tick_t[k] = block.t[-1]
        self._tick_late[k] = lateness_s * 1e6
        ctl = self.control
        if ctl is not None:
            c = self._tick_ctl
            c["x_ref"][k] = ctl.x_ref
            c["x_table"][k] = ctl.x_ref + ctl.error
            c["error_m"][k] = ctl.error
            c["u_control"][k] = ctl.law.u
        self._tick_n = k + 1
        self._win_ticks += 1
        # the samples go when a window ends, the per-tick signals one tick later: each hand-off costs
        # tens of microseconds, and both on one tick made it the slowest tick of all but a few
        if self._win_ticks >= self._flush_at:
            self._flush_telemetry(ticks=False)
            self._flush_at = self.publish_every
        elif self._tick_n > self.publish_every or (self._win_ticks == 1 and self._tick_n > 1):
            self._flush_telemetry(samples=False)

    def _collect_one(self, block: SampleBlock, states) -> None:
        """:meth:`_collect_slices` for a block that keeps one sample (its first), in floats: at the
        telemetry's default rate of one sample a tick, a dozen slicing calls became scalar copies."""
        buf, i = self._tel_buf, self._tel_n
        buf["t"][i] = block.t[0]
        buf["theta1"][i] = block.theta1[0]
        buf["theta2"][i] = block.theta2[0]
        buf["torque_meas"][i] = block.torque[0]
        buf["torque_cmd"][i] = block.torque_cmd[0]
        ident = self.identification
        if ident is not None:
            th, om, al = states.theta[0], states.omega[0], states.alpha[0]
            buf["torque_hat"][i] = _eq18(ident.params, float(th[0]), float(th[1]), float(om[0]), float(om[1]),
                                         float(al[0]))
        else:
            self._tel_hat_ok = False
        self._tel_n = i + 1

    def _collect_slices(self, block: SampleBlock, states) -> None:
        """Every ``stride``-th sample of the block (from its first) into the window buffers."""
        s = slice(None, None, self.stride)
        t = block.t[s]
        m = t.shape[0]
        buf = self._tel_buf
        cap = buf["t"].shape[0]
        if self._tel_n + m > cap:
            self._flush_telemetry()               # a burst (after a stall): publish what is there first
            if m > cap:                           # keep the newest samples of an oversized burst
                s = slice((m - cap) * self.stride, None, self.stride)
                t = block.t[s]
                m = cap
        i, j = self._tel_n, self._tel_n + m
        buf["t"][i:j] = t
        buf["theta1"][i:j] = block.theta1[s]
        buf["theta2"][i:j] = block.theta2[s]
        buf["torque_meas"][i:j] = block.torque[s]
        buf["torque_cmd"][i:j] = block.torque_cmd[s]
        ident = self.identification
        if ident is not None:
            p = ident.params
            th, om, al = states.theta[s], states.omega[s], states.alpha[s]
            buf["torque_hat"][i:j] = _eq18(p, th[:, 0], th[:, 1], om[:, 0], om[:, 1], al[:, 0])
        else:
            self._tel_hat_ok = False
        self._tel_n = j

    def _flush_telemetry(self, samples: bool = True, ticks: bool = True) -> None:
        """Publish the window: the decimated samples, per-tick lateness and the current estimate.

        ``on_telemetry(block)`` gets the samples, then ``on_telemetry(ticks, window)`` the per-tick
        signals and, in ``window`` (name -> float), those that hold one value over the whole window.
        The arrays are views of the window buffers, valid only during the call (it copies, as
        :meth:`rt_ident.runtime.telemetry.TelemetryProcess.publish` does into its ring).
        """
        if self.on_telemetry is None:
            return
        n = self._tel_n if samples else 0
        k = self._tick_n if ticks else 0
        if samples:
            self._win_ticks = 0
        if n:
            out = {key: v[:n] for key, v in self._tel_buf.items() if key != "torque_hat" or self._tel_hat_ok}
            self.on_telemetry(out)
        if samples and not ticks:
            # the window values are gathered now, the per-tick signals go on the next tick: this
            # tick's hand-off is the smaller one, so the two ticks carry about the same extra work
            self._win_next = self._window_values(self._tick_n)
        if k:
            tick = {"t": self._tick_t[:k], "t_tick": self._tick_t[:k], "lateness_us": self._tick_late[:k]}
            if self.control is not None:
                for key, v in self._tick_ctl.items():
                    tick[key] = v[:k]
            win = self._win_next if self._win_next is not None else self._window_values(k)
            self._win_next = None
            self.on_telemetry(tick, win)
        if samples:
            self._tel_n = 0
            self._tel_hat_ok = True
        if ticks:
            self._tick_n = 0

    def publish_final(self) -> None:
        """After the run's final fit: one more telemetry window, at the last sample's time, carrying
        the final estimate, so that the dashboard's estimate lines (and the true values beside them)
        end on the value the run reports. A short run, or one beside a busy machine, may have had no
        fit-worker result at all: its dashboard had no estimate and no true value then."""
        if self.on_telemetry is None or self.identification is None:
            return
        t = np.array([max(self._next_seq - 1, 0) * self.backend.sample_period])
        self.on_telemetry({"t": t, "t_tick": t.copy()}, self._window_values(0))

    def _window_values(self, k: int) -> dict[str, float]:
        """The signals that hold one value over a telemetry window (the estimate, its intervals, the
        controller's figures). They go as one vector (``window``), not as ~35 arrays of k equal
        values: building and copying those was most of a window's hand-off. The estimate's part is
        built once per estimate."""
        win: dict[str, float] = {"overruns": float(self.stats.overruns)}
        ident = self.identification
        if ident is not None:
            if self._win_ident[0] is not ident:
                part: dict[str, float] = {}
                p = ident.params
                part["I1"], part["I2"], part["B"], part["K"] = p.I1, p.I2, p.B, p.K
                modal = ident.modal
                part["wn"], part["wd"], part["zeta"] = modal["wn"], modal["wd"], modal["zeta"]
                for key, (lo, hi) in (ident.ci95 or {}).items():
                    if key in _WINDOW_CI_KEYS:
                        part[f"lo_{key}"] = lo
                        part[f"hi_{key}"] = hi if math.isfinite(hi) else math.nan
                self._win_ident = (ident, part)
            win.update(self._win_ident[1])
        ctl = self.control
        if ctl is not None:
            st, c = ctl.stats, ctl.controller
            if self.on_loop_gain is not None and c is not self._shown_controller and k:
                self._shown_controller = c
                self.on_loop_gain(float(self._tick_t[k - 1]), c.loop_view,
                                  {"pm_deg": (c.margins or {}).get("pm_deg"), "gm_db": c.gain_margin_db})
            win["n_accepted"] = float(st.accepted)
            win["n_rejected"] = float(st.rejected)
            win["fallbacks"] = float(st.fallbacks)
            win["gain_theta2"] = float(c.gains[2])
            win["gain_omega1"] = float(c.gains[1])
            pm = (c.margins or {}).get("pm_deg")
            win["pm_deg"] = math.nan if pm is None else float(pm)
            win["gm_db"] = float(c.gain_margin_db)
            svf = getattr(ctl, "per_sample", None)
            if svf is not None:
                for key, v in svf.values().items():
                    win[f"svf_{key}"] = v
        return win


class MultiAxisLoop:
    """One loop for several axes (an XY table): each tick reads every axis's block first, then
    estimates and controls each axis, then writes every axis's plan - no thread per axis, one ticker.

    ``axes``: name -> :class:`IdentificationLoop` (its backend, estimators, controller, safety,
    telemetry; its own ``run`` is not used). A safety trip or device error on any axis ends the loop
    (the caller stops every axis). ``stats`` holds the shared timing (lateness, work, overruns) and
    the samples of all axes; each axis's ``stats`` its own samples, estimates and lateness.
    """

    def __init__(self, axes: dict[str, IdentificationLoop], *, tick_hz: float, duration: float,
                 stop_event: threading.Event | None = None, clock: Callable[[], float] = time.perf_counter,
                 ticker: Ticker | None = None, max_sleep_s: float | None = 100e-6,
                 tick_hook: Callable[[int], None] | None = None) -> None:
        if not axes:
            raise ValueError("MultiAxisLoop needs at least one axis")
        self.axes = dict(axes)
        self.tick_hz = tick_hz
        self.duration = duration
        self.stop_event = stop_event or threading.Event()
        self.clock = clock
        self.ticker = ticker or Ticker(1.0 / tick_hz, clock=clock, max_sleep_s=max_sleep_s)
        self.tick_hook = tick_hook
        self.stats = LoopStats()

    def run(self) -> LoopStats:
        axes = list(self.axes.values())
        stats, clock, cpu_clock = self.stats, self.clock, time.thread_time
        period = 1.0 / self.tick_hz
        for i, ax in enumerate(axes):
            ax._write_plan()
            # the axes' telemetry windows end on different ticks: a window's hand-off to the telemetry
            # process (~200 us) is the tick's largest single cost, and all axes at once set its p99
            ax._flush_at = max(1, ax.publish_every * (i + 1) // len(axes))
            # ... and their fit exchanges (five steps in a 10-tick cycle; a step's last one, drawing an
            # FRF, is rare: a view comes every few seconds) on other ticks still
            ax.fit_phase = 2 + (4 * i) % 10
        last_cpu = 0.0
        spent = [0.0] * len(axes)
        any_simulated = any(ax.backend.simulated for ax in axes)
        self.ticker.start()
        try:
            for _ in range(int(round(self.duration * self.tick_hz))):
                if self.stop_event.is_set():
                    break
                info = self.ticker.wait_next()
                t0, c0 = clock(), cpu_clock()
                _count_tick(stats, info, last_cpu, period)
                # every axis's samples of this tick first; each axis's share of the work is timed
                # (its read, its processing, its plan) into its own ``work_us``
                blocks = []
                for i, ax in enumerate(axes):
                    t1 = clock()
                    blocks.append(ax.backend.read())
                    spent[i] = clock() - t1
                for i, (ax, block) in enumerate(zip(axes, blocks)):
                    _count_tick(ax.stats, info, last_cpu, period)
                    t1 = clock()
                    ax._process(block, info.lateness_s)
                    spent[i] += clock() - t1
                for i, ax in enumerate(axes):
                    t1 = clock()
                    ax._write_plan()
                    spent[i] += clock() - t1
                t1 = clock()
                stats.work.record(t1 - t0)
                for i, ax in enumerate(axes):
                    ax.stats.work.record(spent[i])
                horizon = self.ticker.next_deadline() - t1 + SIM_AHEAD_MARGIN_S
                for ax in axes:                     # simulated devices step ahead (IdentificationLoop.run)
                    t2 = clock()
                    ax.backend.step_ahead(horizon)
                    if ax.backend.simulated:
                        ax.stats.sim_ahead.record(clock() - t2)
                if any_simulated:
                    stats.sim_ahead.record(clock() - t1)
                last_cpu = cpu_clock() - c0
                stats.work_cpu.record(last_cpu)
                if self.tick_hook is not None:
                    self.tick_hook(stats.ticks)
        finally:
            stats.samples = sum(ax.stats.samples for ax in axes)
            stats.lost_samples = sum(ax.stats.lost_samples for ax in axes)
            stats.estimates = sum(ax.stats.estimates for ax in axes)
        for ax in axes:
            ax._flush_telemetry()
        return stats

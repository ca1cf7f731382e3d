"""The real-time identification loop: read -> estimate -> write, on absolute deadlines.

Each tick (default 1 kHz):

1. ``backend.read()`` returns every sample since the previous tick;
2. the steady-state Kalman filter turns the angles into omega and alpha
   (for the controller and the safety monitor);
3. the streaming estimator takes every sample (the default "frequency"
   method updates its per-harmonic DFT sums sample by sample); when a full
   excitation period completes, a snapshot goes to the fit process
   and the newest fit it returned becomes the current estimate;
4. the position controller (:class:`rt_ident.control.adaptation.Supervisor`, when there is
   one) takes the state estimate at the newest sample and returns the torque for the next
   tick: the host closes the position loop (a drive in torque mode holds nothing); its
   per-sample estimator's state-variable filter gives the filtered derivatives of the
   torque estimate (Eq. 18 with the last trusted fit, against the measured torque through the
   same filter: :meth:`IdentificationLoop.torque_estimate`);
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
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.base import Backend, SampleBlock
from drivers.errors import SpeedTrip, TravelLimitTrip
from rt_ident.control.adaptation import ASSESS_EVERY
from rt_ident.errors import RtIdentError
from rt_ident.estimators.excitation_id import EQ18_N, EQ18_SIZE, eq18_accumulate, nrmse_from_sums
from rt_ident.estimators.svf import NO_TRACE, TR_COLS
from rt_ident.loop import tick_kernel as tk
from rt_ident.loop.safety import SafetyMonitor
from rt_ident.loop.scheduler import Ticker
from rt_ident.loop.stall import LoopStall, StallPolicy
from rt_ident.loop.stats import LoopStats
from rt_ident.loop.tick_core import AxisCore
from rt_ident.loop.window import TelemetryWindow

if TYPE_CHECKING:
    from rt_ident.estimators.base import Identification

log = logging.getLogger(__name__)


#: A simulated device steps ahead to this long after the next deadline (Backend.step_ahead). The
#: next read comes a few microseconds after the deadline; without a margin, about one read in six
#: finds a sample come due in between and steps it then (a full stepping call for one sample, tens of
#: microseconds of the read). A drive applies its samples in that stretch with the plan it holds, the
#: one written a tick earlier: the host's next write lands only after the tick's work (~90 us or
#: more), and its first values for those samples count as ``late_plan_samples``. The torque is the
#: same either way: the controller's torque lands ``delay_ticks`` >= 1 tick later, and the probe's
#: values are the same in both plans.
SIM_AHEAD_MARGIN_S = 100e-6

#: After a stall the loop has caught up with the device once the newest sample read trails the host's
#: clock by at most this many ticks more than it does when the loop keeps up (rt_ident.loop.stall).
CATCH_UP_TICKS = 2


def read_anchor(clock: Callable[[], float], backends: Sequence[Backend]) -> float | None:
    """Tick 0's time (Ticker.start): the ticks fall where a device's sample has just been answered
    (Backend.read_phase, modulo its sample period), or None (now) when no device samples on the host's
    signal. One SYNC for every drive on a bus: the first phase serves them all."""
    for b in backends:
        phase = b.read_phase()
        if phase is not None:
            period = b.sample_period
            return clock() + phase % period - period
    return None


def _stall_before(loops: list[IdentificationLoop], blocks: list[SampleBlock], stats: LoopStats,
                  policy: StallPolicy, stall_s: float, now: float) -> None:
    """The host stopped for ``stall_s`` between two reads (the wall time between them less a period):
    past ``policy.max_s`` it is a stall (rt_ident.loop.stall), wherever in the tick it came - while
    waiting, before the read, after it. Each axis then resumes on this tick, or the blocks read are
    recorded and the loop stops."""
    verdict = policy.verdict(stall_s)
    if verdict is None:
        return
    action = "resume" if verdict == "resume" else "stop"
    for st in [stats] + [lp.stats for lp in loops if lp.stats is not stats]:
        st.stalls.note(now, stall_s, action)        # the loop's and each axis's (its dashboard shows it)
    if verdict != "resume":
        for lp, block in zip(loops, blocks):
            lp.stats.samples += len(block)
            if lp.on_block is not None and len(block):
                lp.on_block(block)              # nothing read is lost
        resumable = policy.action == "stop" and stall_s <= policy.stop_s
        raise LoopStall(verdict, "safety.on_stall = 'resume'" if resumable else None)
    for lp in loops:
        lp._resume = stall_s


def _note_stall(exc: BaseException, stats: LoopStats, now: float, since_read: float = 0.0) -> None:
    """A stop shortly after a stall says so (``exc.after_stall``, added to the stop message). ``since_read``:
    the host's silence before the read or tick that raised, less a period; longer than the stall limit, it is
    a stall that ended in this stop (a device that faulted while the host was silent) and is counted."""
    if isinstance(exc, LoopStall):
        return
    if since_read > 0.0:
        stats.stalls.note(now, since_read, "stopped")
    if stats.stalls.count:
        exc.after_stall = stats.stalls.before(now)      # type: ignore[attr-defined]


def _stall_length(t: float, last_read: float, period: float, policy: StallPolicy) -> float:
    """The host's silence from the last read to ``t``, less a period, when it exceeds the stall limit; else 0.
    For a tick that raised, ``t`` is when it raised: a host stopped inside the read (a device's read waits
    at most a poll, far below the limit) is a stall that ended in the stop."""
    gap = t - last_read - period
    return gap if gap > policy.max_s else 0.0


def _count_tick(stats: LoopStats, info, last_cpu: float, period: float, backlog: bool = False) -> None:
    """A tick's timing counters: an overrun is charged to the previous tick's CPU time when that
    exceeded the period (its own work, or a stall's backlog when it worked through one), else to a
    late start."""
    stats.ticks += 1
    if info.skipped:
        stats.overruns += 1
        stats.skipped_periods += info.skipped
        if last_cpu > period and backlog:
            stats.overruns_backlog += 1
        elif last_cpu > period:
            stats.overruns_work += 1
        else:
            stats.overruns_late_start += 1
    stats.lateness.record(info.lateness_s)


def _book_int(i: int, none_below: int | None = None) -> Any:
    """A property reading and writing ``book_i[i]`` (None below ``none_below``); typed where it is bound."""
    def get(self: IdentificationLoop) -> int | None:
        v = int(self.book_i[i])
        return None if none_below is not None and v < none_below else v

    def put(self: IdentificationLoop, value: int | None) -> None:
        self.book_i[i] = -1 if value is None else value
    return property(get, put)


class IdentificationLoop(TelemetryWindow):
    """Joins a backend, a state estimator, a streaming estimator and the hand-offs.

    Everything is constructed and warmed up by the caller (:mod:`rt_ident.compose.run`);
    :meth:`run` only ticks.
    """

    def __init__(self, backend: Backend, *, tick_hz: float, excitation: Callable[[np.ndarray], np.ndarray],
                 state_estimator, estimator, safety: SafetyMonitor, duration: float, fit_process=None,
                 on_block: Callable[[SampleBlock], None] | None = None,
                 on_telemetry: Callable[..., Any] | None = None,
                 publish_every: int = 20, telemetry_stride: int = 34,
                 stop_event: threading.Event | None = None, clock: Callable[[], float] = time.perf_counter,
                 tick_hook: Callable[[int], None] | None = None,
                 max_sleep_s: float | None = 100e-6, control=None, ticker: Ticker | None = None,
                 probe_period: int | None = None, on_fit: Callable[[float, Any], Any] | None = None,
                 on_loop_gain: Callable[[float, Any, Any], Any] | None = None, friction=None,
                 friction_feedforward: bool = True, compiled_tick: bool = True,
                 stall: StallPolicy | None = None) -> None:
        self.backend = backend
        self.ticker = ticker or Ticker(1.0 / tick_hz, clock=clock, max_sleep_s=max_sleep_s)
        self.tick_hz = tick_hz
        self.excitation = excitation
        self.kf = state_estimator
        self.est = estimator
        self.jobs = fit_process
        self.safety = safety
        self._stuck_torque = float(getattr(safety, "stuck_torque", 0.0))   # see SafetyMonitor.stuck_torque
        self.duration = duration
        self.on_block = on_block
        self.on_telemetry = on_telemetry
        self.on_fit = on_fit                # a new fit's FRF view -> the dashboard (never blocks)
        self.on_loop_gain = on_loop_gain    # a new controller's loop gain -> the dashboard
        self._shown_controller: Any = None
        self.publish_every = max(1, publish_every)
        self.fit_phase = 3                       # the fit exchange's 10-tick cycle starts here (_fit_exchange)
        self.control_phase = 0                   # the supervisor's redesign steps run on ticks of this parity
        # snapshot to send, results taken, result to offer, FRF to draw (_fit_exchange)
        self._fit_stage: list[Any] = [None, None, None, None]
        self.stride = max(1, telemetry_stride)
        self.stop_event = stop_event or threading.Event()
        self.clock = clock
        self.tick_hook = tick_hook          # test seam: e.g. inject a slow tick
        self.stats = LoopStats()
        self.stall_policy = stall or StallPolicy()
        self._resume: float | None = None   # a stall's length [s] until the tick that resumes from it
        self._catching_up = False           # after a stall, still reading the device's backlog (_catch_up)
        self._catch_up_ticks = 0
        # the host's clock at this tick's read (the run loops set it), and the floor of the newest sample's
        # offset from it while the loop keeps up (_track_sample_clock)
        self._t_read: float | None = None
        self._offset_floor = math.inf
        self._backlog_possible = bool(getattr(backend, "samples_in_real_time", True))
        self.identification: Identification | None = None   # latest (None before the first period)
        # the fit whose parameters the torque estimate uses: the last trusted one (see torque_estimate)
        self.torque_ident: Identification | None = None
        self.eq18_sums = np.zeros(EQ18_SIZE)     # its running sums (excitation_id.eq18_accumulate)
        self.control = control              # the host's position controller (None: excitation only)
        # the per-sample estimator runs (and its filter gives the torque estimate's derivatives)
        self._feeds_svf = control is not None and getattr(control, "per_sample", None) is not None and \
            control.s.mode == "adaptive"
        self._sample_keys = tk.SAMPLE_KEYS if self._feeds_svf else tk.SAMPLE_KEYS[:tk.SAMPLE_KEYS_NO_SVF]
        self.friction = friction            # per-sample friction-model estimator ([estimator] model), or None
        self.friction_feedforward = friction_feedforward
        # the tick's bookkeeping (tick_kernel.BI_* / BF_*: the sample expected next, the control clock's
        # first sample, the control torque in force and those in flight, the probe amplitude, the
        # telemetry window's counters), in two arrays changed in place: the compiled tick holds views
        self.book_i, self.book_f = tk.new_books()
        self._flush_at = self.publish_every      # ticks in the current telemetry window (MultiAxisLoop staggers)
        self._per_tick = max(1, int(round(1.0 / (tick_hz * backend.sample_period))))
        self._probe_period = probe_period   # excitation period [samples]: its amplitude changes on period edges
        self._plan_len = int(math.ceil(2.0 / (tick_hz * backend.sample_period))) + 2
        # a periodic probe is tabulated once (a period and a plan's length more): the plan slices it
        self._ex_table = (None if not probe_period else
                          np.asarray(excitation(np.arange(probe_period + self._plan_len)), dtype=float))
        hold = getattr(safety, "torque_hold", None)      # the plan's lease (see drivers.base.Backend.write)
        self._lease = None if hold is None else int(math.ceil(hold / backend.sample_period))
        self._core: AxisCore | None = None    # the compiled tick (built last, below)
        # the last ~20 ms of blocks (references, nothing copied): a speed or travel trip looks back at them
        self._recent: deque[SampleBlock] = deque(maxlen=max(2, int(math.ceil(0.02 * tick_hz))))
        self._publisher = None               # a TelemetryProcess taking the window's rows (_telemetry_buffers)
        if on_telemetry is not None:
            self._telemetry_buffers()
        self._plan_start: int | None = None  # the compiled tick built the plan from this sample on
        tk.warm_up()
        # the whole tick in one compiled call where the parts allow (rt_ident.loop.tick_core)
        self._core = AxisCore.for_loop(self) if compiled_tick else None

    # the bookkeeping by name (the Python path's view of book_i / book_f)
    _next_seq: int = _book_int(tk.BI_NEXT_SEQ)
    _seq0: int | None = _book_int(tk.BI_SEQ0, none_below=0)   # first sequence number: the control clock starts there
    _tel_n: int = _book_int(tk.BI_TEL_N)
    _tick_n: int = _book_int(tk.BI_TICK_N)
    _win_ticks: int = _book_int(tk.BI_WIN_TICKS)       # ticks in the current sample window
    _flush_at: int = _book_int(tk.BI_FLUSH_AT)         # ticks in the current telemetry window (MultiAxisLoop staggers)

    _u_base = property(lambda self: float(self.book_f[tk.BF_U_BASE]),
                       doc="the control torque in force at the newest sample")

    @property
    def _u_sched(self) -> list[tuple[int, float]]:
        """(first seq, torque) still to land, in order."""
        bi, bf = self.book_i, self.book_f
        return [(int(bi[tk.BI_SCHED_SEQ + k]), float(bf[tk.BF_SCHED_VAL + k])) for k in range(int(bi[tk.BI_SCHED_N]))]

    @property
    def compiled_ticks(self) -> dict[str, Any]:
        """Whether the compiled tick is on, and how many ticks it ran (whole or in part) and left to Python."""
        core = self._core
        return {"on": core is not None, "ticks": core.ticks if core else 0,
                "python_ticks": core.python_ticks if core else self.stats.ticks}

    # ------------------------------------------------------------------ run
    def run(self) -> LoopStats:
        backend, stats = self.backend, self.stats
        self._write_plan()
        n_ticks = int(round(self.duration * self.tick_hz))
        period = 1.0 / self.tick_hz
        clock = self.clock
        cpu_clock = time.thread_time
        last_cpu, backlog = 0.0, False      # the tick before: its CPU time, whether it had a stall's backlog
        policy = self.stall_policy
        stats.compiles.start()
        last_read = t0 = self.ticker.start(read_anchor(clock, [backend]))
        stats.stalls.origin = t0                # the summary's stall times: seconds into the run
        try:
            for _ in range(n_ticks):
                if self.stop_event.is_set():
                    break
                info = self.ticker.wait_next()
                t0 = clock()
                c0 = cpu_clock()
                _count_tick(stats, info, last_cpu, period, backlog)
                block = backend.read()
                t_read = clock()
                stall_s = _stall_length(t_read, last_read, period, policy)
                if stall_s:
                    _stall_before([self], [block], stats, policy, stall_s, t_read)
                last_read = self._t_read = t_read
                resuming = self._resume is not None
                self._process(block, info.lateness_s)
                self._write_plan()
                t1 = clock()
                stats.work.record(t1 - t0)
                # a simulated device steps through the samples due by the next deadline now (a real one
                # does nothing): what the tick's work measures is the host's part, as with a device
                backend.step_ahead(self.ticker.next_deadline() - t1 + SIM_AHEAD_MARGIN_S)
                if backend.simulated:
                    stats.sim_ahead.record(clock() - t1)
                last_cpu, backlog = cpu_clock() - c0, resuming
                stats.work_cpu.record(last_cpu)
                if self.tick_hook is not None:
                    self.tick_hook(stats.ticks)
        except RtIdentError as exc:
            now = clock()
            _note_stall(exc, stats, now, _stall_length(now, last_read, period, policy))
            raise
        finally:
            stats.compiles.stop()
        self._flush_telemetry()
        return stats

    # --------------------------------------------------------------- pieces
    def _process(self, block: SampleBlock, lateness_s: float = 0.0) -> None:
        if len(block):
            self._recent.append(block)
            if self._resume is None:
                self._track_sample_clock(block)
        try:
            core = self._core
            if core is not None:
                if self._resume is None and core.tick(self, block, lateness_s):
                    return
                if self._resume is not None:        # a resume is the Python path's (the controller re-plans)
                    core.python_ticks += 1
            self._process_py(block, lateness_s)
        except (SpeedTrip, TravelLimitTrip) as exc:
            self._sign_fault(exc)
            raise

    def _sign_fault(self, trip: Exception) -> None:
        """A speed or travel trip: raise it as a sign fault when the last samples show the axis
        accelerating against the torque (SafetyMonitor.sign_check)."""
        blocks = list(self._recent)
        if not blocks:
            return
        th1, th2, tq = (np.concatenate([getattr(b, f) for b in blocks]) for f in ("theta1", "theta2", "torque_cmd"))
        seq = np.concatenate([b.seq for b in blocks])
        if seq.size and int(seq[-1] - seq[0]) + 1 != seq.size:    # a gap: the samples are not one stretch
            return
        fault = self.safety.sign_check(trip, th1, th2, tq, self.backend.sample_period)
        if fault is not None:
            raise fault from trip

    def _process_py(self, block: SampleBlock, lateness_s: float = 0.0) -> None:
        """The tick's processing step by step (the compiled tick's reference, and its fallback)."""
        n = len(block)
        stats = self.stats
        resume = self._resume is not None
        self._catching_up = resume and not (n and self._behind(block) <= CATCH_UP_TICKS / self.tick_hz)
        if n == 0:
            self.safety.check(0, 0.0, 0.0, 0.0, True)
            if resume:
                self._catch_up()
            return
        stats.samples += n
        stats.lost_samples += block.lost
        if block.lost > stats.lost_longest:
            stats.lost_longest = block.lost
        if self.on_block is not None:               # record first: a block that trips a check is kept
            self.on_block(block)
        if self._catching_up:
            self._catch_up()
        torque = block.torque
        states = self.kf.filter_block(block.theta1, block.theta2, block.seq)
        if resume:                                      # the stall's samples: no excitation, a coasting table
            self.est.skip(int(block.seq[-1]) + 1 - self._next_seq)
        if self.est.update_block(block.theta1, block.theta2, torque, block.seq):
            self._snapshot_due()
        ctl = self.control
        trace = np.empty((n, TR_COLS)) if self._feeds_svf else NO_TRACE
        if ctl is not None:                             # the per-sample estimator, every sample
            ctl.observe(block.theta1, block.theta2, torque,
                        resume or block.lost > 0 or int(block.seq[0]) != self._next_seq,
                        trace if self._feeds_svf else None)
        elif resume and not self._catching_up:
            self._resumed()
        if self.friction is not None:
            self._friction(block, torque, ctl, stats.ticks)
        if self.jobs is not None:
            self._fit_exchange(ctl, float(block.t[-1]), stats.ticks)
        if ctl is not None:
            self._control(ctl, block, states)
            self.assess_turn(ctl, stats.ticks)
        self._check_safety(block, states)
        self._torque_estimate(trace)
        if self.on_telemetry is not None:
            self._collect_telemetry(block, trace, lateness_s)

    def _offset(self, t_read: float, block: SampleBlock) -> float:
        """The host's time of the read less the newest sample's time on the device's sample clock."""
        return t_read - int(block.seq[-1]) * self.backend.sample_period

    def _track_sample_clock(self, block: SampleBlock) -> None:
        """The floor of :meth:`_offset` while the loop keeps up: it follows a fresher read at once and a
        staler one slowly (clock drift), so a late tick's read does not raise it."""
        if self._t_read is None:
            return
        off, floor = self._offset(self._t_read, block), self._offset_floor
        self._offset_floor = off if off < floor else floor + 1e-3 * (off - floor)

    def _behind(self, block: SampleBlock) -> float:
        """How far [s] the newest sample read trails where a read that keeps up would be: a device that
        kept sampling through a stall hands its backlog over in pieces over several ticks."""
        if self._t_read is None or not math.isfinite(self._offset_floor) or not self._backlog_possible:
            return 0.0
        return self._offset(self._t_read, block) - self._offset_floor

    def _catch_up(self) -> None:
        """A tick after a stall before the loop has caught up with the device: nothing is written (the
        torque stays at the zero the lease left) and nothing re-planned from samples that are not the
        newest. Stall and catch-up together longer than ``max_stall_stop_s`` stop the loop."""
        self._catch_up_ticks += 1
        stall_s, wait_s = float(self._resume or 0.0), self._catch_up_ticks / self.tick_hz
        limit = self.stall_policy.stop_s
        if stall_s + wait_s > limit:
            raise LoopStall(f"loop stalled for {stall_s * 1e3:.0f} ms and had not caught up with the device's "
                            f"samples {wait_s * 1e3:.0f} ms later (safety.max_stall_stop_s = {limit * 1e3:g} ms)")

    def _resumed(self) -> None:
        self._resume = None
        self.stats.stalls.caught_up(self._catch_up_ticks / self.tick_hz)
        self._catch_up_ticks = 0

    def _torque_estimate(self, trace: np.ndarray) -> None:
        """The block's samples into the torque estimate's running sums, once there is a trusted fit."""
        ident = self.torque_ident
        if ident is not None and trace.shape[0]:
            p = ident.params
            eq18_accumulate(trace, float(p.I1), float(p.B), float(p.K), self.eq18_sums)

    def torque_estimate(self) -> dict[str, Any]:
        """The live torque estimate's figure for the summary: the NRMSE [%] of the Eq. (18) reconstruction
        from the SVF's filtered derivatives against the measured torque through the same filter, over
        every sample from the first trusted fit to the end, each with the last trusted fit's parameters
        at its time (None, with why, when there is none)."""
        n = int(self.eq18_sums[EQ18_N])
        out: dict[str, Any] = {"nrmse_percent": None, "samples": n,
                               "seconds": n * float(self.backend.sample_period)}
        if not self._feeds_svf:
            out["why_none"] = "no per-sample estimator: its state-variable filter gives the derivatives"
        elif self.torque_ident is None:
            out["why_none"] = "no trusted fit yet"
        else:
            v = nrmse_from_sums(self.eq18_sums)
            if math.isfinite(v):
                out["nrmse_percent"] = v
            else:
                out["why_none"] = "too few samples, or a constant torque"
        return out

    def _snapshot_due(self) -> None:
        """An excitation period completed: a snapshot for the fit process, taken now and sent on this
        axis's send tick - only when the job process waits for one."""
        if self.jobs is not None:
            if self.jobs.ready:
                self._fit_stage[0] = self.est.snapshot()
            else:
                self.jobs.skipped += 1

    def _check_safety(self, block: SampleBlock, states) -> None:
        self.safety.check(len(block), float(block.theta1[-1]), float(block.theta2[-1]), float(states.omega[-1, 1]),
                          abs(self.backend.last_torque) > self._stuck_torque)
        self._next_seq = int(block.seq[-1]) + 1

    def _fit_exchange(self, ctl, t: float, tick: int) -> None:
        """The exchange with the fit process, one step per tick of a 10-tick cycle: send the snapshot
        taken at the end of an excitation period; take a result from the job process's ring; unpickle
        it; hand it to the controller; draw its FRF. Each step costs tens of microseconds; done on
        one tick, they and a telemetry hand-off would set the tick's p99. ``fit_phase`` shifts the cycle
        (MultiAxisLoop gives each axis its own ticks)."""
        step = (tick - self.fit_phase) % 10
        stage = self._fit_stage
        if step == 0:
            if stage[0] is not None:
                self.jobs.submit(stage[0])            # the fit runs in the job process
                stage[0] = None
        elif step == 1:
            stage[1] = self.jobs.take()
        elif step == 2:
            got, stage[1] = stage[1], None
            latest = self.jobs.unpack(got) if got else None
            if latest is not None:
                self.identification = latest
                if latest.trusted:
                    self.torque_ident = latest
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
        if self._catching_up:                           # the newest sample read is not the device's newest
            tk.clear_schedule(self.book_i, self.book_f)
            return
        last = int(block.seq[-1])
        th, om = states.theta[-1], states.omega[-1]
        seq0 = self._seq0
        first = seq0 is None
        if seq0 is None:
            seq0 = self._seq0 = int(block.seq[0])
        t = (last - seq0) * self.backend.sample_period
        state = (float(th[0]), float(om[0]), float(th[1]), float(om[1]))
        if first:                                       # the reference starts where the table is
            ctl.start(t, *state)
        elif self._resume is not None:                  # the drive dropped the torque during the stall
            ctl.resume(t, *state, self._resume)
            tk.clear_schedule(self.book_i, self.book_f)
        if self._resume is not None:
            self._resumed()
        u = ctl.tick(t, *state)
        if self.control_turn(self.stats.ticks):
            ctl.poll()
        if not tk.schedule_torque(self.book_i, self.book_f, last, ctl.law.delay * self._per_tick, u):
            raise RtIdentError(f"more than {tk.SCHED_CAP} control torques in flight (delay {ctl.law.delay} ticks)")

    def assess_turn(self, ctl, tick: int) -> None:
        """The supervisor's look at the per-sample estimate's evidence, after the law and its redesign
        step, every ASSESS_EVERY ticks (on ticks the fit exchange leaves free); every tick from a
        detected change until its redesign."""
        if getattr(ctl, "per_sample", None) is None:
            return
        turn = (tick - self.fit_phase) % ASSESS_EVERY == 1
        if turn or ctl.following:
            ctl.assess(turn)

    def control_turn(self, tick: int) -> bool:
        """Whether the supervisor takes its next redesign step on ``tick`` (every other tick, the axes
        of a multi-axis loop on alternate ones)."""
        return (tick - self.control_phase) % 2 == 0

    def _write_plan(self) -> None:
        if self._catching_up:
            return
        start, core = self._plan_start, self._core
        if start is not None and core is not None:      # the compiled tick built it
            self._plan_start = None
            self.backend.write(core.plan, start_seq=start, lease=self._lease)
            return
        start = self._next_seq
        torque = self._excitation_window(start)
        ctl = self.control
        if ctl is not None:
            tk.shape_plan(torque, start, self.book_i, self.book_f, self._probe_period or 1, float(ctl.probe_scale))
        elif torque.size:
            torque[-1] = 0.0        # the value a lease holds: not the probe's instant (tick_kernel.shape_plan)
        self.backend.write(torque, start_seq=start, lease=self._lease)

    def _excitation_window(self, start: int) -> np.ndarray:
        """The probing excitation for seq [start, start + plan length), a new array. A periodic
        excitation (``probe_period`` given) is read from one period tabulated up front, as a slice."""
        n, table, period = self._plan_len, self._ex_table, self._probe_period
        if table is None or not period:         # (the table is there exactly when the period is)
            return np.array(self.excitation(np.arange(start, start + n)), dtype=float)
        i = start % period
        return table[i:i + n].copy()


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
                 tick_hook: Callable[[int], None] | None = None, stall: StallPolicy | None = None) -> None:
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
        self.stall_policy = stall or StallPolicy()
        # the name of the axis whose read, processing, plan or simulation step raised (None: none did)
        self.failed_axis: str | None = None

    def run(self) -> LoopStats:
        axes = list(self.axes.values())
        names = list(self.axes)
        cur = -1                                    # the axis being worked on (-1: none), for failed_axis
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
            # ... and their supervisors' redesign steps (a few hundred microseconds each) on alternate ticks
            ax.control_phase = i % 2
        last_cpu, backlog = 0.0, False      # the tick before: its CPU time, whether it had a stall's backlog
        spent = [0.0] * len(axes)
        any_simulated = any(ax.backend.simulated for ax in axes)
        policy = self.stall_policy
        stats.compiles.start()
        last_read = t0 = self.ticker.start(read_anchor(self.clock, [ax.backend for ax in axes]))
        for st in [stats] + [ax.stats for ax in axes]:
            st.stalls.origin = t0               # the summary's stall times: seconds into the run
        try:
            for _ in range(int(round(self.duration * self.tick_hz))):
                if self.stop_event.is_set():
                    break
                info = self.ticker.wait_next()
                t0, c0 = clock(), cpu_clock()
                _count_tick(stats, info, last_cpu, period, backlog)
                # every axis's samples of this tick first; each axis's share of the work is timed
                # (its read, its processing, its plan) into its own ``work_us``
                blocks = []
                for cur, ax in enumerate(axes):
                    t1 = clock()
                    blocks.append(ax.backend.read())
                    spent[cur] = clock() - t1
                cur = -1
                t_read = clock()
                stall_s = _stall_length(t_read, last_read, period, policy)
                if stall_s:
                    _stall_before(axes, blocks, stats, policy, stall_s, t_read)
                last_read = t_read
                resuming = any(ax._resume is not None for ax in axes)
                for cur, (ax, block) in enumerate(zip(axes, blocks)):
                    ax._t_read = t_read
                    _count_tick(ax.stats, info, last_cpu, period, backlog)
                    t1 = clock()
                    ax._process(block, info.lateness_s)
                    spent[cur] += clock() - t1
                for cur, ax in enumerate(axes):
                    t1 = clock()
                    ax._write_plan()
                    spent[cur] += clock() - t1
                t1 = clock()
                stats.work.record(t1 - t0)
                for i, ax in enumerate(axes):
                    ax.stats.work.record(spent[i])
                horizon = self.ticker.next_deadline() - t1 + SIM_AHEAD_MARGIN_S
                for cur, ax in enumerate(axes):  # noqa: B007 - cur names the axis if it raises; devices step ahead
                    t2 = clock()
                    ax.backend.step_ahead(horizon)
                    if ax.backend.simulated:
                        ax.stats.sim_ahead.record(clock() - t2)
                if any_simulated:
                    stats.sim_ahead.record(clock() - t1)
                last_cpu, backlog = cpu_clock() - c0, resuming
                stats.work_cpu.record(last_cpu)
                cur = -1
                if self.tick_hook is not None:
                    self.tick_hook(stats.ticks)
        except BaseException as exc:
            self.failed_axis = names[cur] if cur >= 0 else None
            now = clock()
            _note_stall(exc, stats, now, _stall_length(now, last_read, period, policy))
            raise
        finally:
            stats.compiles.stop()
            stats.samples = sum(ax.stats.samples for ax in axes)
            stats.lost_samples = sum(ax.stats.lost_samples for ax in axes)
            stats.lost_longest = max((ax.stats.lost_longest for ax in axes), default=0)
            stats.estimates = sum(ax.stats.estimates for ax in axes)
        for ax in axes:
            ax._flush_telemetry()
        return stats

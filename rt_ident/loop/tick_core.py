"""One axis's tick in one compiled call: the estimators, the law, the safety checks, the telemetry
window and the recording hand-off, between the device's read and its write.

Why: every step of the tick is compiled, but called from Python one by one, with a few dozen lines
of glue around each, the steps cost the tick 200-250 us per axis. A tick comes after ~0.8 ms of sleep
with its caches cold, and its cost grows with how much distinct code and data it touches; a compiled
call costs more the more arguments it takes, and more after a sleep (docs/measurements.md, "Host
facts behind the loop's design"). Here the same compiled steps run composed in one call
(:func:`rt_ident.loop.tick_kernel.axis_tick`) whose state is three buffers (float, int, complex: the
*arena*) and one table of offsets, so a tick pays one dispatch (the block, the arena, the rings it
writes and a few scalars) instead of ~40 calls.

The state stays where it was: each component (the Kalman filters, the recursive DFT and its gap
filler, the per-sample SVF estimator, the law, the supervisor's bookkeeping, the safety counters,
the loop's own bookkeeping and window buffers, the recorder's counters) keeps its arrays as
attributes, and :class:`AxisCore` copies each into the arena once and rebinds the attribute to the
view. The Python path (``IdentificationLoop._process``) and this one then read and write the same
memory, so a tick may take either path, and the components' own methods (``summary()``, the fit
snapshot, a bumpless switch) see every compiled tick. The components change those arrays in place
only (their docstrings say so); :meth:`AxisCore.bound` checks that nothing was rebound.

The compiled tick does only what it can do exactly as the Python path does (a test runs both paths
over the same closed-loop run, and alternates them, and compares every sample, every estimate sum,
every torque and every telemetry value bit for bit), and leaves a tick to Python *before* changing
anything a Python step would change:

* the whole tick (:data:`BAIL`): lost samples, a sequence gap, a non-finite value, a block larger
  than the buffers, a full recorder ring (the Python put waits; the compiled one never does);
* from the controller on (:data:`PY_CONTROL`): the tracking error above its bound or a fallback clock
  running (the supervisor acts), a friction feedforward on;
* from the safety check on (:data:`PY_SAFETY`): the motor encoder unchanged under torque, the
  table's stopping position outside the window or its speed above the limit (the monitor counts or
  raises, with its message);
* the telemetry store (:data:`PY_TELEMETRY`): a block that overflows the window (flush first).

Where the Python path hands something over to another process, the kernel writes the same message
into that process's ring itself: the recorder's block, the telemetry window (its samples, then its
tick signals with the window's vector) and, when the fit process waits for one, the running sums at the
end of an excitation period. The loop's glue (:meth:`AxisCore.tick`) evaluates the reference (Python
objects), runs the rest of the fit exchange (taking results, unpickling them, offering them to the
supervisor), prepares the window's vector, counts what the kernel handed over and writes the plan the
kernel built - in the Python path's order relative to the steps they depend on.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from rt_ident.control.adaptation import Supervisor
from rt_ident.control.law import StateFeedback
from rt_ident.estimators.frequency_stream import StreamingFrequencyEstimator, rdft_accumulate
from rt_ident.estimators.state_estimation import AxisStateEstimator, AxisStates
from rt_ident.estimators.streaming import FrequencyStream
from rt_ident.estimators.svf import TR_COLS, SvfEstimator
from rt_ident.loop import tick_kernel as tk
from rt_ident.loop.safety import SafetyMonitor
from rt_ident.processes.shm_ring import key_words

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------- the arena
class _Arena:
    """Collects the arrays of one axis's tick, then copies them into three buffers and rebinds each
    owner's attribute to its view (same shape, same values): from then on both paths share them."""

    _KINDS = {np.dtype(np.float64): 0, np.dtype(np.int64): 1, np.dtype(np.complex128): 2}

    def __init__(self) -> None:
        self._items: list[list[tuple[int, Any, str | None, np.ndarray]]] = [[], [], []]
        self._count = (tk.F_SLOTS, tk.I_SLOTS, tk.C_SLOTS)

    def adopt(self, slot: int, owner: Any, attr: str) -> None:
        """``owner.attr`` (an ndarray) goes into the arena at ``slot``."""
        self._add(slot, owner, attr, getattr(owner, attr))

    def own(self, slot: int, array: np.ndarray) -> None:
        """An array only the core holds (constants, buffers)."""
        self._add(slot, None, None, array)

    def _add(self, slot: int, owner: Any, attr: str | None, a: np.ndarray) -> None:
        kind = self._KINDS[np.asarray(a).dtype]
        self._items[kind].append((slot, owner, attr, np.asarray(a)))

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[tuple[int, int], np.ndarray]]:
        lay = np.zeros(2 * sum(self._count), dtype=np.int64)
        bufs, views = [], {}
        base = 0
        for kind, (items, count) in enumerate(zip(self._items, self._count)):
            seen = sorted(slot for slot, *_ in items)
            if seen != sorted(set(seen)):
                raise ValueError("tick_core: a slot given twice")
            dtype = list(self._KINDS)[kind]
            buf = np.zeros(max(1, sum(a.size for *_, a in items)), dtype=dtype)
            off = 0
            for slot, owner, attr, a in items:
                view = buf[off:off + a.size].reshape(a.shape)
                view[...] = a
                lay[2 * (base + slot)], lay[2 * (base + slot) + 1] = off, a.size
                if attr is not None:            # adopted: the owner's attribute becomes the view
                    setattr(owner, attr, view)
                views[(kind, slot)] = view
                off += a.size
            bufs.append(buf)
            base += count
        return bufs[0], bufs[1], bufs[2], lay, views


class AxisCore:
    """One axis's compiled tick for an :class:`~rt_ident.loop.loop.IdentificationLoop` (see the
    module docstring). Build it with :meth:`for_loop`, which returns None when the loop's parts are not
    the ones it knows (then the loop runs its Python path only)."""

    def __init__(self, loop: Any, recorder: Any) -> None:
        kf, est, ctl, safety = loop.kf, loop.est, loop.control, loop.safety
        backend = loop.backend
        inner: StreamingFrequencyEstimator = est.inner
        svf = ctl.per_sample if ctl is not None and ctl.s.mode == "adaptive" else None
        self.dt = float(backend.sample_period)
        per_tick = loop._per_tick
        self.nmax = 8 * per_tick + 64
        ar = _Arena()
        f1, f2 = kf.filters
        for owner, slots in ((f1, (tk.F_KF1_F, tk.F_KF1_K, tk.F_KF1_X, tk.F_KF1_XP, tk.F_KF1_ZL)),
                             (f2, (tk.F_KF2_F, tk.F_KF2_K, tk.F_KF2_X, tk.F_KF2_XP, tk.F_KF2_ZL))):
            for slot, attr in zip(slots, ("F", "gain", "x", "_xp", "_zlast")):
                ar.adopt(slot, owner, attr)
        ar.adopt(tk.I_KF_SEQ, kf, "next_seq")
        for slot, attr in ((tk.F_FS_STATE, "_state"), (tk.F_FS_LAST, "_last"), (tk.F_FS_QMIN, "_qmin"),
                           (tk.I_FS_HARM, "harmonics"), (tk.I_FS_IDX, "_idx"), (tk.I_FS_COUNT, "_count"),
                           (tk.C_FS_TABLE, "_table"), (tk.C_FS_ACC, "_acc"), (tk.C_FS_S1, "_S1"), (tk.C_FS_S2, "_S2")):
            ar.adopt(slot, inner, attr)
        ar.adopt(tk.F_GAP_LAST, est.gaps, "last")
        ar.adopt(tk.I_GAP_SEQ, est.gaps, "seq")
        if svf is not None:
            for slot, attr in ((tk.F_SVF_PHI, "_Phi"), (tk.F_SVF_G0, "_G0"), (tk.F_SVF_G1, "_G1"),
                               (tk.F_SVF_GZ, "_Gz"), (tk.F_SVF_XS, "_xs"), (tk.F_SVF_PREV, "_prev"),
                               (tk.F_SVF_SCALE, "_scale"), (tk.F_SVF_PRIOR, "_prior"), (tk.F_SVF_SIGMA, "_Sigma"),
                               (tk.F_SVF_RM, "_R"), (tk.F_SVF_RV, "_r"), (tk.F_SVF_ACC, "_acc"), (tk.F_SVF_P, "_p"),
                               (tk.F_SVF_TMP, "_tmp"), (tk.F_SVF_COUNTS, "_counts")):
                ar.adopt(slot, svf, attr)
        if ctl is not None:
            for slot, owner, attr in ((tk.F_LAW_G, ctl.law, "gains"), (tk.F_LAW_ST, ctl.law, "st"),
                                      (tk.F_LAW_C, ctl.law, "consts"), (tk.F_SUP_NOW, ctl, "now"),
                                      (tk.F_SUP_ERR, ctl.stats, "err"), (tk.F_SUP_C, ctl, "consts")):
                ar.adopt(slot, owner, attr)
        ar.adopt(tk.F_SAFE, safety, "counters")
        ar.adopt(tk.I_BOOK, loop, "book_i")
        ar.adopt(tk.F_BOOK, loop, "book_f")
        if loop.on_telemetry is not None:
            ar.adopt(tk.F_TEL, loop, "tel_rows")
            ar.adopt(tk.F_TICKS, loop, "tick_rows")
        ar.adopt(tk.F_EXTABLE, loop, "_ex_table")
        ar.own(tk.F_PLAN, np.zeros(loop._plan_len))
        ar.own(tk.F_STATES, np.zeros((3, self.nmax, 2)))
        ar.own(tk.F_SVF_TRACE, np.zeros((self.nmax if svf is not None else 0, TR_COLS)))
        ar.adopt(tk.F_EQ18, loop, "eq18_sums")
        fc = np.zeros(tk.FC_SIZE)
        fc[tk.FC_DT] = self.dt
        fc[tk.FC_FS_LAM] = inner.forgetting
        if svf is not None:
            fc[tk.FC_SVF_LAMF], fc[tk.FC_SVF_RHO], fc[tk.FC_SVF_MINT2], fc[tk.FC_SVF_LAMG] = \
                svf.lam_f, svf.s.rho, svf.s.min_torque ** 2, svf.lam_g
        fc[tk.FC_SAFE_LEAD], (fc[tk.FC_SAFE_LO], fc[tk.FC_SAFE_HI]) = safety.lead, safety.window
        fc[tk.FC_SAFE_DECEL], fc[tk.FC_STUCK_TORQUE] = safety.max_decel, loop._stuck_torque
        fc[tk.FC_SAFE_VMAX] = safety.max_speed
        ar.own(tk.F_CONST, fc)
        icn = np.zeros(tk.IC_SIZE, dtype=np.int64)
        icn[tk.IC_HAS_CTL] = ctl is not None
        icn[tk.IC_HAS_SVF] = svf is not None
        icn[tk.IC_HAS_TEL] = loop.on_telemetry is not None
        icn[tk.IC_KF_DIM] = f1.dim
        icn[tk.IC_H] = inner.harmonics.size
        icn[tk.IC_NMAX] = self.nmax
        icn[tk.IC_STRIDE] = loop.stride
        icn[tk.IC_PUBLISH_EVERY] = loop.publish_every
        icn[tk.IC_PERIOD] = loop._probe_period
        icn[tk.IC_LAG] = ctl.law.delay * per_tick if ctl is not None else 0
        icn[tk.IC_FS_DISCARD] = inner.discard_periods
        self.recorder = recorder
        target = recorder.compiled_target() if recorder is not None else None
        if target is not None:
            ring, counts = target
            self.rec = ring.compiled_views()
            icn[tk.IC_HAS_REC] = 1
            icn[tk.IC_REC_CAP], icn[tk.IC_REC_MAXMSG] = ring.capacity, ring.max_messages
            icn[tk.IC_REC_KEYS:tk.IC_REC_KEYS + 4] = np.concatenate([key_words("seq"), key_words("floats")])
            ar.adopt(tk.I_REC_COUNTS, recorder, "put_counts")
        else:
            self.rec = (np.zeros(8, dtype=np.int64), np.zeros(8, dtype=np.int64), np.zeros(8))
        ar.own(tk.I_CONST, icn)
        # the telemetry hand-off the kernel makes itself, into a TelemetryProcess's ring (tick_kernel.I_TEL)
        tel = np.zeros(tk.TEL_SIZE, dtype=np.int64)
        tel[tk.TEL_WID] = -1
        tel[tk.TEL_TICK_FIELDS] = (3 if ctl is None else len(tk.TICK_FIELDS) if svf is not None
                                   else len(tk.TICK_FIELDS) - 4)
        tel[tk.TEL_SAMPLE_FIELDS] = len(loop._sample_keys) if loop.on_telemetry is not None else 0
        tel[tk.TEL_SKEYS:tk.TEL_TKEYS] = np.concatenate([key_words(k) for k in tk.SAMPLE_KEYS])
        tel[tk.TEL_TKEYS:tk.TEL_TAIL] = np.concatenate([key_words(k) for k in tk.TICK_FIELDS])
        tel[tk.TEL_TAIL:tk.TEL_SROWS] = np.concatenate([key_words(k) for k in ("window_id", "window")])
        tel[tk.TEL_SROWS:tk.TEL_TROWS] = np.arange(len(tk.SAMPLE_KEYS))
        tel[tk.TEL_TROWS:tk.TEL_SIZE] = tk.TICK_ROWS
        ar.own(tk.I_TEL, tel)
        ar.own(tk.F_WIN, np.zeros(tk.WIN_CAP))
        # the fit process's snapshot the kernel hands over itself (tick_kernel.I_FIT)
        fit = np.zeros(tk.FIT_SIZE, dtype=np.int64)
        name = b"SpectraSums"
        fit[tk.FIT_KEYS:tk.FIT_CODEC] = np.concatenate([key_words(k) for k in
                                                        ("harmonics", "sums", "quantum", "scalars", "codec")])
        fit[tk.FIT_CODEC:tk.FIT_SIZE] = np.frombuffer(name.ljust(16, b"\0"), dtype=np.int64)
        fit[tk.FIT_CODEC_LEN] = len(name)
        fit[tk.FIT_FIXED_Q] = inner.quantum is not None
        ff = np.zeros(tk.FIT_FSIZE)
        ff[tk.FIT_SCALARS], ff[tk.FIT_SCALARS + 1] = inner.period, inner.dt
        if inner.quantum is not None:
            ff[tk.FIT_QUANTUM:tk.FIT_QUANTUM + 2] = inner.quantum
        ar.own(tk.I_FIT, fit)
        ar.own(tk.F_FIT, ff)
        self.fb, self.ib, self.cb, self.lay, views = ar.build()
        self._bindings = [(owner, attr, views[(ar._KINDS[a.dtype], slot)])
                          for kind in ar._items for slot, owner, attr, a in kind if attr is not None]
        self.big = views[(0, tk.F_STATES)]
        self.trace_rows = views[(0, tk.F_SVF_TRACE)]
        self.plan = views[(0, tk.F_PLAN)]
        self.tel, self.win = views[(1, tk.I_TEL)], views[(0, tk.F_WIN)]
        self.fit = views[(1, tk.I_FIT)]
        self.jobs = loop.jobs if hasattr(loop.jobs, "_in") else None   # a JobProcess: its ring
        self.fit_ring = None
        self.fit_arrays = (np.zeros(8, dtype=np.int64), np.zeros(8, dtype=np.int64), np.zeros(8))
        self.tp = loop._publisher                # a TelemetryProcess: the kernel may hand windows over itself
        self.tel_ring, self.tel_truth = None, None
        self.tel_arrays = (np.zeros(8, dtype=np.int64), np.zeros(8, dtype=np.int64), np.zeros(8))
        self._seq0: int | None = None
        self._hat_ident, self._hat_args = None, (0, 0.0, 0.0, 0.0)
        self.ticks = 0                      # ticks the compiled path ran, whole or in part
        self.python_ticks = 0               # ticks it left to the Python path whole
        self.refused = False                # a block's types were not the kernel's (logged once)
        self._warm()

    # -------------------------------------------------------------------------------- construction
    @classmethod
    def for_loop(cls, loop: Any) -> AxisCore | None:
        """The compiled tick for ``loop``, or None (with the reason logged at debug level) when its parts
        are not the ones the kernel knows: a frequency-method streaming estimator, the Kalman state
        estimator, a supervisor (or none) with an SVF per-sample estimator (or none), the safety monitor,
        a tabulated probe, no friction estimator, a recorder process (or none)."""
        why = None
        ctl = loop.control
        recorder = getattr(loop.on_block, "__self__", None) if loop.on_block is not None else None
        if type(loop.kf) is not AxisStateEstimator:
            why = "state estimator"
        elif type(loop.est) is not FrequencyStream or type(loop.est.inner) is not StreamingFrequencyEstimator \
                or loop.est.inner._kernel is not rdft_accumulate:
            why = "streaming estimator"
        elif ctl is not None and (type(ctl) is not Supervisor or type(ctl.law) is not StateFeedback
                                  or (ctl.per_sample is not None and type(ctl.per_sample) is not SvfEstimator)):
            why = "controller"
        elif type(loop.safety) is not SafetyMonitor:
            why = "safety monitor"
        elif loop.friction is not None:
            why = "friction estimator"
        elif loop._probe_period is None or loop._ex_table is None:
            why = "probe not tabulated"
        elif loop.on_block is not None and not hasattr(recorder, "compiled_target"):
            why = "recording hand-off"
        if why is not None:
            log.debug("compiled tick off: %s", why)
            return None
        return cls(loop, recorder)

    def _warm(self) -> None:
        """Compile (or load) the kernel now, not in the first tick, and call it once doing nothing (mode 0)."""
        self.kernel = kernel = tk.compiled_kernel()
        z, zi = np.zeros(2), np.arange(2, dtype=np.int64)
        kernel(0, z, zi, z, z, z, z, 1, self.fb, self.ib, self.cb, self.lay, *self.rec, *self.tel_arrays,
               *self.fit_arrays,
               0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0, 0.0, 0.0, 0.0, 0.0)

    def bound(self) -> bool:
        """Whether every adopted attribute still is its arena view (a component that replaced one would
        split the two paths' state)."""
        return all(getattr(owner, attr) is view for owner, attr, view in self._bindings)

    def states(self, n: int) -> AxisStates:
        """The state estimates of the block just filtered (views of the arena)."""
        big = self.big
        return AxisStates(theta=big[0, :n], omega=big[1, :n], alpha=big[2, :n])

    def trace(self, n: int) -> np.ndarray:
        """The SVF's filtered signals of the block just filtered (a view of the arena; no rows without it)."""
        return self.trace_rows[:n]

    # ------------------------------------------------------------------------------------ the tick
    def tick(self, loop: Any, block: Any, lateness_s: float) -> bool:
        """``loop._process(block)`` through the kernel; False when the Python path is to run the whole
        tick (nothing has been done then). The Python steps around the kernel run in the Python path's
        order relative to what they depend on: the reference before the law; the fit exchange after the
        estimators (a snapshot taken, a cross-check against the per-sample estimate) and before the
        telemetry store and the law (a new estimate; a result offered to the controller, then the law
        in a second call)."""
        t = block.t
        n = t.shape[0]
        if n == 0 or block.lost:
            self.python_ticks += 1
            return False
        last = int(block.seq[-1])
        ctl = loop.control
        jobs = loop.jobs
        stats = loop.stats
        tick = stats.ticks
        split = False
        step = 9
        if jobs is not None:
            step = (tick - loop.fit_phase) % 10
            if step == 2:                       # a result unpacked: the estimators do not read it, the telemetry
                loop._fit_exchange(ctl, float(t[-1]), tick)     # store and the law do (as after the Python B)
                step = 9
            else:
                split = step == 3 and loop._fit_stage[2] is not None
        t_ctl = xr = vr = ar = a_ff = 0.0
        want = 1.0
        if ctl is not None:
            s0 = self._seq0
            if s0 is None:
                s0 = self._seq0 = loop._seq0
                if s0 is None:                  # the first tick starts the control clock (Python)
                    self.python_ticks += 1
                    return False
            t_ctl = (last - s0) * self.dt
            xr, vr, ar, a_ff = ctl.reference_at(t_ctl)
            want = float(ctl.probe_scale)
        tq = block.torque_meas
        has_meas = 1
        if tq is None:
            tq, has_meas = block.torque_cmd, 0
        hat = self._hat(loop.torque_ident)
        tp = self.tp
        if tp is not None and (tp._ring is not self.tel_ring or tp._truth_pending is not self.tel_truth or tp._closed):
            self._telemetry_state(tp)
        fw = self.jobs
        if fw is not None and fw._in is not self.fit_ring:
            self._fit_state(fw)
        args = (t, block.seq, block.theta1, block.theta2, block.torque_cmd, tq, has_meas, self.fb, self.ib, self.cb,
                self.lay, *self.rec, *self.tel_arrays, *self.fit_arrays)
        last_torque = loop.backend.last_torque
        try:
            code = self.kernel(tk.MODE_ESTIMATE if split else tk.MODE_ESTIMATE | tk.MODE_CONTROL, *args,
                               t_ctl, xr, vr, ar, a_ff, lateness_s, want, *hat, last_torque)
        except TypeError:                       # a block whose arrays the kernel does not take: KERNEL_SIGNATURE
            self.python_ticks += 1
            if not self.refused:
                self.refused = True
                log.warning("compiled tick: a block of types %s goes to the Python path",
                            [getattr(a, "dtype", type(a)) for a in args[:6]])
            return False
        if code & tk.BAIL:
            self.python_ticks += 1
            return False
        self.ticks += 1
        stats.samples += n
        if code & tk.PERIODS:
            loop._snapshot_due()
        elif fw is not None and code & tk.SNAPSHOT_SKIPPED:  # the job process was busy (as JobProcess.submit counts)
            fw.skipped += 1
        if step < 5:                            # the fit exchange's steps (the other five ticks do nothing)
            loop._fit_exchange(ctl, float(t[-1]), tick)
            if split:                           # the controller got a result: the law runs after it
                if ctl is not None:
                    want = float(ctl.probe_scale)
                code |= self.kernel(tk.MODE_CONTROL, *args, t_ctl, xr, vr, ar, a_ff, lateness_s, want,
                                    *self._hat(loop.torque_ident), last_torque)
        if self.recorder is not None and tick % 10 == 5:
            self.recorder.check_alive()         # Python's put checks on every call (rate-limited to 10/s)
        if code & (tk.PY_CONTROL | tk.PY_SAFETY | tk.PY_TELEMETRY | tk.SCHED_FULL):
            self._finish_in_python(loop, block, code, lateness_s)
            return True
        if ctl is not None:
            if ctl._pending and loop.control_turn(tick):
                ctl.poll()
            loop.assess_turn(ctl, tick)
        if code & (tk.TEL_SENT | tk.TEL_DROPPED | tk.WINDOW_DUE):
            self._telemetry_sent(loop, code)
        if code & tk.FLUSH_SAMPLES:
            loop._flush_telemetry(ticks=False)
            loop._flush_at = loop.publish_every
        elif code & tk.FLUSH_TICKS:
            loop._flush_telemetry(samples=False)
        loop._plan_start = last + 1
        return True

    def _hat(self, ident: Any) -> tuple[int, float, float, float]:
        """(1, I1, B, K) of the fit Eq. (18) uses, or (0, 0, 0, 0) without one (kept per fit)."""
        if ident is not self._hat_ident:
            self._hat_ident = ident
            self._hat_args = (0, 0.0, 0.0, 0.0) if ident is None else \
                (1, float(ident.params.I1), float(ident.params.B), float(ident.params.K))
        return self._hat_args

    def _fit_state(self, jobs: Any) -> None:
        """The fit process's ring (new after a restart): the kernel hands its snapshots over into it."""
        ring = self.fit_ring = jobs._in
        self.fit_arrays = ring.compiled_views()
        fit = self.fit
        fit[tk.FIT_CAP], fit[tk.FIT_MAXMSG] = ring.capacity, ring.max_messages
        fit[tk.FIT_OK] = 1

    def _telemetry_state(self, tp: Any) -> None:
        """The telemetry process's ring changed (a restart), or it has a truth to push first, or it closed:
        whether the kernel may hand windows over itself now, and into which ring."""
        ring = tp._ring
        self.tel_ring, self.tel_truth = ring, tp._truth_pending
        tel = self.tel
        ok = ring is not None and not tp._closed and not tp._truth_pending and tp.config.decimation == 1 \
            and tp.config.sink != "off"
        if ring is not None:
            self.tel_arrays = ring.compiled_views()
            tel[tk.TEL_CAP], tel[tk.TEL_MAXMSG] = ring.capacity, ring.max_messages
        tel[tk.TEL_OK] = int(ok)
        tel[tk.TEL_WID] = -1                    # a new child has no window names yet: the next vector via Python

    def forget_window(self) -> None:
        """The Python path hands a window over: the vector the kernel was to send with the next tick
        signals is not that window's any more."""
        self.tel[tk.TEL_WID] = -1

    def _telemetry_sent(self, loop: Any, code: int) -> None:
        """What the kernel handed to the telemetry process, counted as publish_rows counts it; after a
        window's samples, the vector of its tick signals (as _flush_telemetry(ticks=False) gathers it)."""
        tp = self.tp
        if code & tk.TEL_SENT:
            tp._published += 1
        elif code & tk.TEL_DROPPED:
            tp._dropped += 1
        if not code & tk.WINDOW_DUE:           # that was a window's tick signals: its vector is used
            loop._win_next = None
            return
        names, values = win = loop._window_values(loop._tick_n)
        loop._win_next = win
        wid = tp._schemas.get(names)
        if wid is not None and values.shape[0] <= tk.WIN_CAP:
            self.win[:values.shape[0]] = values
            self.tel[tk.TEL_NVAL], self.tel[tk.TEL_WID] = values.shape[0], wid

    def _finish_in_python(self, loop: Any, block: Any, code: int, lateness_s: float) -> None:
        """The rest of a tick the kernel stopped short of (see the PY_* bits), as the Python path runs it."""
        ctl = loop.control
        states = self.states(len(block))
        if code & tk.SCHED_FULL:
            from rt_ident.errors import RtIdentError

            raise RtIdentError(f"more than {tk.SCHED_CAP} control torques in flight (delay {ctl.law.delay} ticks)")
        if code & tk.PY_CONTROL:
            loop._control(ctl, block, states)
        elif ctl is not None and loop.control_turn(loop.stats.ticks):
            ctl.poll()
        if ctl is not None:
            loop.assess_turn(ctl, loop.stats.ticks)
        trace = self.trace(len(block))
        if code & (tk.PY_CONTROL | tk.PY_SAFETY):
            loop._check_safety(block, states)
            loop._torque_estimate(trace)
        if loop.on_telemetry is not None:
            loop._collect_telemetry(block, trace, lateness_s)

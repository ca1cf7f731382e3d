"""The compiled half of the tick (rt_ident.loop.tick_core is the Python half): the layout of the
loop's bookkeeping and of an axis's arena, the steps both paths run (the Python path one call at a
time, the kernel inlined), and :func:`axis_tick`, one axis's whole tick. The numerics are the
components' own kernels (the Kalman filter's, the recursive DFT's, the SVF estimator's, the law's,
the supervisor's bookkeeping, the rings' writers); this module only composes them.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from rt_ident.axis.kernels import first_non_finite3
from rt_ident.control.adaptation import NOW_ERR, NOW_FALLBACK_SINCE, NOW_XREF, SC_LEAD, SC_MAX_ERROR, track_error
from rt_ident.control.law import ST_FRICTION, ST_U, law_step
from rt_ident.estimators.excitation_id import eq18_accumulate, eq18_filtered
from rt_ident.estimators.frequency_stream import rdft_accumulate
from rt_ident.estimators.state_estimation import kalman_block
from rt_ident.estimators.svf import TR_COLS, TR_F_TORQUE, svf_block
from rt_ident.loop.safety import SAFE_LAST_THETA1, SAFE_STALE, SAFE_STUCK
from rt_ident.processes.shm_ring import consumer_waits, put_rows, put_seq_floats, put_sums

# --------------------------------------------------------------------------- the loop's bookkeeping
# IdentificationLoop.book_i (int64): the sample expected next, the control clock's first sample (-1:
# none yet), the probe amplitude's next period edge, the torques in flight to the drive (count, then
# their first samples), the telemetry window's counters ...
BI_NEXT_SEQ, BI_SEQ0, BI_PROBE_EDGE, BI_SCHED_N, BI_TEL_N, BI_TICK_N, BI_WIN_TICKS, BI_FLUSH_AT, \
    BI_SCHED_SEQ = range(9)
SCHED_CAP = 16
BI_SIZE = BI_SCHED_SEQ + SCHED_CAP
# ... and book_f (float64): the control torque in force, the probe amplitude now and from the edge on,
# the torques in flight
BF_U_BASE, BF_PROBE_NOW, BF_PROBE_LATER, BF_SCHED_VAL = range(4)
BF_SIZE = BF_SCHED_VAL + SCHED_CAP

# the telemetry window's rows (IdentificationLoop.tel_rows / tick_rows); the last two (the measured torque
# through the SVF, its Eq. (18) reconstruction) only with the per-sample estimator, whose filter gives them
SAMPLE_KEYS = ("t", "theta1", "theta2", "torque_meas", "torque_cmd", "torque_filt", "torque_hat")
SAMPLE_KEYS_NO_SVF = 5
TICK_KEYS = ("t", "lateness_us", "x_ref", "x_table", "error_m", "u_control", "svf_I1", "svf_I2", "svf_B", "svf_K")


def new_books() -> tuple[np.ndarray, np.ndarray]:
    bi = np.zeros(BI_SIZE, dtype=np.int64)
    bi[BI_SEQ0] = -1
    bf = np.zeros(BF_SIZE)
    bf[BF_PROBE_NOW] = bf[BF_PROBE_LATER] = 1.0
    return bi, bf


# ----------------------------------------------------- steps both paths run (the Python one, one by one)
@numba.njit(cache=True)
def schedule_torque(bi, bf, last, lag, u) -> bool:
    """The control torques in flight to the drive: those landing by the sample after ``last`` become the
    torque in force, and ``u`` joins, to land ``lag`` samples after ``last`` (the torque of sample s acts
    from s to s + 1: ``lag`` = delay x samples per tick is the design's delay, rt_ident.control.design).
    False: no room (a delay of more than ``SCHED_CAP`` ticks)."""
    n = bi[BI_SCHED_N]
    k = 0
    while k < n and bi[BI_SCHED_SEQ + k] <= last + 1:
        bf[BF_U_BASE] = bf[BF_SCHED_VAL + k]
        k += 1
    for j in range(n - k):
        bi[BI_SCHED_SEQ + j] = bi[BI_SCHED_SEQ + j + k]
        bf[BF_SCHED_VAL + j] = bf[BF_SCHED_VAL + j + k]
    n -= k
    if n >= SCHED_CAP:
        bi[BI_SCHED_N] = n
        return False
    bi[BI_SCHED_SEQ + n] = last + lag
    bf[BF_SCHED_VAL + n] = u
    bi[BI_SCHED_N] = n + 1
    return True


def clear_schedule(bi, bf) -> None:
    """Nothing in flight and no control torque in force: the drive dropped the host's torque (a stall
    outlasted the plan's lease), so the plan starts again from zero."""
    bi[BI_SCHED_N] = 0
    bf[BF_U_BASE] = 0.0


@numba.njit(cache=True)
def shape_plan(torque, start, bi, bf, period, want) -> None:
    """The plan from the probing excitation ``torque`` (seq ``start`` on, changed in place): the probe at
    the amplitude of its period (``want`` from the next period edge on: dual excitation keeps a whole
    period at one amplitude, periodic for the estimator), plus the control torque, piecewise constant:
    the one in force, then each in flight from the sample it lands at. The last value is the control
    torque alone: it is the one the drive holds through the lease when no newer plan comes (a stalled
    host), and the probe's value of that instant, held for milliseconds, would push the table (0.3 N m
    for 5 ms is 34 mm/s on the THOMSON X axis)."""
    n = torque.shape[0]
    now, later, edge = bf[BF_PROBE_NOW], bf[BF_PROBE_LATER], bi[BI_PROBE_EDGE]
    if start >= edge:
        now = later
    if want != later:
        later, edge = want, (start + period - 1) // period * period     # the next period edge (start >= 0)
    bf[BF_PROBE_NOW], bf[BF_PROBE_LATER], bi[BI_PROBE_EDGE] = now, later, edge
    if now != 1.0 or later != 1.0:
        cut = min(max(edge - start, 0), n)
        for j in range(cut):
            torque[j] *= now
        for j in range(cut, n):
            torque[j] *= later
    base = bf[BF_U_BASE]
    for j in range(n):
        torque[j] += base
    level = base
    for s in range(bi[BI_SCHED_N]):
        cut = max(bi[BI_SCHED_SEQ + s] - start, 0)
        if cut >= n:
            break
        d = bf[BF_SCHED_VAL + s] - level
        for j in range(cut, n):
            torque[j] += d
        level = bf[BF_SCHED_VAL + s]
    if n:
        torque[n - 1] = level


# explicit types (any layout): whatever strides a backend's block arrays have, nothing compiles in a tick
@numba.njit("int64(float64[:, :], int64, int64, float64[:], float64[:], float64[:], float64[:], float64[:], "
            "float64[:, :], boolean, float64, float64, float64)", cache=True)
def collect_samples(rows, i0, stride, t, th1, th2, tq, tcmd, trace, hat, I1, B, K) -> int:
    """Every ``stride``-th sample of a block (from its first) into the telemetry window's rows from
    column ``i0`` on. With the SVF's ``trace`` of the block (rt_ident.estimators.svf.svf_block; no rows:
    none), also the measured torque through the filter and, when ``hat``, its Eq. (18) reconstruction
    from the filtered derivatives (excitation_id.eq18_filtered; NaN otherwise). Returns the samples
    stored."""
    m = 0
    svf = trace.shape[0] > 0
    for i in range(0, t.shape[0], stride):
        j = i0 + m
        rows[0, j] = t[i]
        rows[1, j] = th1[i]
        rows[2, j] = th2[i]
        rows[3, j] = tq[i]
        rows[4, j] = tcmd[i]
        if svf:
            rows[5, j] = trace[i, TR_F_TORQUE]
            rows[6, j] = eq18_filtered(trace, i, I1, B, K) if hat else np.nan
        m += 1
    return m


# ------------------------------------------------------------------------------- the arena's slots
# float arena
(F_KF1_F, F_KF1_K, F_KF1_X, F_KF1_XP, F_KF1_ZL, F_KF2_F, F_KF2_K, F_KF2_X, F_KF2_XP, F_KF2_ZL,
 F_FS_STATE, F_FS_LAST, F_FS_QMIN, F_GAP_LAST,
 F_SVF_PHI, F_SVF_G0, F_SVF_G1, F_SVF_GZ, F_SVF_XS, F_SVF_PREV, F_SVF_SCALE, F_SVF_PRIOR, F_SVF_SIGMA, F_SVF_RM,
 F_SVF_RV, F_SVF_ACC, F_SVF_P, F_SVF_TMP, F_SVF_COUNTS,
 F_LAW_G, F_LAW_ST, F_LAW_C, F_SUP_NOW, F_SUP_ERR, F_SUP_C, F_SAFE,
 F_BOOK, F_STATES, F_TEL, F_TICKS, F_EXTABLE, F_PLAN, F_CONST, F_WIN, F_FIT, F_SVF_TRACE, F_EQ18, F_SLOTS) = range(48)
# int arena
I_FS_HARM, I_FS_IDX, I_FS_COUNT, I_GAP_SEQ, I_KF_SEQ, I_BOOK, I_REC_COUNTS, I_CONST, I_TEL, I_FIT, I_SLOTS = range(11)
# complex arena
C_FS_TABLE, C_FS_ACC, C_FS_S1, C_FS_S2, C_SLOTS = range(5)
# F_CONST
FC_DT, FC_FS_LAM, FC_SVF_LAMF, FC_SVF_RHO, FC_SVF_MINT2, FC_SVF_LAMG, FC_SAFE_LEAD, FC_SAFE_LO, FC_SAFE_HI, \
    FC_SAFE_DECEL, FC_STUCK_TORQUE, FC_SAFE_VMAX, FC_SIZE = range(13)
# I_CONST
(IC_HAS_CTL, IC_HAS_SVF, IC_HAS_TEL, IC_HAS_REC, IC_KF_DIM, IC_H, IC_NMAX, IC_STRIDE, IC_PUBLISH_EVERY,
 IC_PERIOD, IC_LAG, IC_FS_DISCARD, IC_REC_CAP, IC_REC_MAXMSG, IC_REC_KEYS, IC_SIZE) = (*range(15), 18)
# I_TEL: the telemetry hand-off the kernel makes itself (TelemetryProcess.publish_rows' message, written by the
# kernel): whether it may (the ring as the glue saw it, no truth to push first, no decimation), the window
# vector's id (-1: none ready) and length, the ring's capacity and message limit, the fields of a tick window
# and of the samples, then the key words of the samples' fields, of a tick window's fields and of the window
# tail, and the rows of the samples' fields and of a tick window's fields
TEL_OK, TEL_WID, TEL_NVAL, TEL_CAP, TEL_MAXMSG, TEL_TICK_FIELDS, TEL_SAMPLE_FIELDS, TEL_SKEYS = range(8)
TEL_TKEYS = TEL_SKEYS + 2 * len(SAMPLE_KEYS)
TEL_TAIL = TEL_TKEYS + 2 * (len(TICK_KEYS) + 1)
TEL_SROWS = TEL_TAIL + 4
TEL_TROWS = TEL_SROWS + len(SAMPLE_KEYS)
TEL_SIZE = TEL_TROWS + len(TICK_KEYS) + 1
TICK_FIELDS = ("t", "t_tick", "lateness_us", *TICK_KEYS[2:])    # a tick window's fields (t twice: t, t_tick) ...
TICK_ROWS = (0, 0, *range(1, len(TICK_KEYS)))                   # ... and their rows
WIN_CAP = 64        # window values the arena holds
# I_FIT: the fit process's snapshot the kernel hands over itself (rt_ident.processes.jobs; the message of
# SpectraSums.to_fields): whether it may (the job process's ring as the glue saw it), the ring's capacity and message
# limit, whether the quantum is the configured one (else the smallest steps seen), the codec name's length,
# the fields' key words, the name's bytes
FIT_OK, FIT_CAP, FIT_MAXMSG, FIT_FIXED_Q, FIT_CODEC_LEN, FIT_KEYS = range(6)
FIT_CODEC = FIT_KEYS + 10
FIT_SIZE = FIT_CODEC + 2
# F_FIT: the snapshot's scalars (N, dt, W, W2, periods), then the configured quantum
FIT_SCALARS, FIT_QUANTUM, FIT_FSIZE = 0, 5, 7

# the kernel's answer (bits)
BAIL = 1            # nothing done: the Python path runs the whole tick
PY_CONTROL = 2      # estimators done; the controller on is the Python path's
PY_SAFETY = 4       # ... and the controller; the safety check on is the Python path's
PY_TELEMETRY = 8    # ... and the safety check; the telemetry store is the Python path's
PERIODS = 16        # the recursive DFT completed a period (a fit snapshot is due)
FLUSH_SAMPLES = 32  # the telemetry window's samples are due (IdentificationLoop._flush_telemetry)
FLUSH_TICKS = 64    # its per-tick signals are due
PLAN_BUILT = 128    # the plan for the next samples is in the plan buffer
SCHED_FULL = 256    # more torques in flight than SCHED_CAP (an error)
TEL_SENT = 512      # the kernel handed a telemetry window message over ...
TEL_DROPPED = 1024  # ... or the ring was full (dropped, as publish() drops)
WINDOW_DUE = 2048   # it handed a window's samples over: the window vector for its tick signals is due
SNAPSHOT_SENT = 4096      # a period completed and the kernel handed the running sums to the fit process ...
SNAPSHOT_SKIPPED = 8192   # ... or the job process was busy (counted as its skipped snapshots)
# modes
MODE_ESTIMATE = 1   # record, Kalman filters, recursive DFT, SVF
MODE_CONTROL = 2    # law, safety, telemetry store, plan


@numba.njit(inline="always")
def _fs(fb, lay, k):
    o = lay[2 * k]
    return fb[o:o + lay[2 * k + 1]]


@numba.njit(inline="always")
def _is(ib, lay, k):
    o = lay[2 * (F_SLOTS + k)]
    return ib[o:o + lay[2 * (F_SLOTS + k) + 1]]


@numba.njit(inline="always")
def _cs(cb, lay, k):
    o = lay[2 * (F_SLOTS + I_SLOTS + k)]
    return cb[o:o + lay[2 * (F_SLOTS + I_SLOTS + k) + 1]]


def axis_tick(mode, t, seq, th1, th2, tcmd, tq, has_meas, fb, ib, cb, lay, rh, rdi, rdf, th, tdi, tdf, fh, fdi, fdf,
              t_ctl, xr, vr, ar, a_ff, lateness_s, want, ident, I1, B, K, last_torque) -> int:
    """One axis's tick (see the module docstring): ``mode`` MODE_ESTIMATE and/or MODE_CONTROL; the
    block (``tq``: the measured torque, or the commanded one when ``has_meas`` is 0); the arena; the
    recorder ring (``rh``, ``rdi``, ``rdf``), the telemetry ring (``th``, ``tdi``, ``tdf``) and the
    fit process's (``fh``, ``fdi``, ``fdf``); the
    reference at ``t_ctl`` (the newest sample's time on the control clock) and the feedforward's
    acceleration; the probe amplitude wanted; the parameters of Eq. (18) (``ident`` 0: none yet); the
    torque last written. Returns the bits above."""
    ic = _is(ib, lay, I_CONST)
    fc = _fs(fb, lay, F_CONST)
    bi = _is(ib, lay, I_BOOK)
    bf = _fs(fb, lay, F_BOOK)
    n = th1.shape[0]
    nmax = ic[IC_NMAX]
    code = 0
    if n == 0 or n > nmax:
        return BAIL
    big = _fs(fb, lay, F_STATES).reshape((3, nmax, 2))
    # the SVF's filtered signals of the block (no rows without the per-sample estimator)
    trace = _fs(fb, lay, F_SVF_TRACE).reshape((nmax if ic[IC_HAS_SVF] else 0, TR_COLS))[:n]
    first, last = seq[0], seq[n - 1]
    if mode & MODE_ESTIMATE:
        # ---- everything that would leave the tick to Python is checked before anything changes
        kf_seq = _is(ib, lay, I_KF_SEQ)
        gap_seq = _is(ib, lay, I_GAP_SEQ)
        if last - first + 1 != n or first != bi[BI_NEXT_SEQ] or first != kf_seq[0] or first != gap_seq[0] + 1:
            return BAIL
        if first_non_finite3(th1, th2, tq) >= 0:
            return BAIL
        if ic[IC_HAS_REC]:                      # record first: a block that trips a check is kept
            k = ic[IC_REC_KEYS:IC_REC_KEYS + 4]
            ncols = 5 if has_meas else 4
            if put_seq_floats(rh, rdi, rdf, ic[IC_REC_CAP], ic[IC_REC_MAXMSG], k, seq, t, th1, th2, tcmd, tq,
                              ncols) != 1:
                return BAIL
            counts = _is(ib, lay, I_REC_COUNTS)
            counts[0] += 1
            counts[1] += n
        # the steady-state Kalman filters, both angles (AxisStateEstimator.filter_block)
        m = ic[IC_KF_DIM]
        noskip = ib[0:0]
        kalman_block(th1, _fs(fb, lay, F_KF1_F).reshape((m, m)), _fs(fb, lay, F_KF1_K), _fs(fb, lay, F_KF1_X),
                   _fs(fb, lay, F_KF1_XP), big[:, :n, 0].T, noskip, _fs(fb, lay, F_KF1_ZL))
        kalman_block(th2, _fs(fb, lay, F_KF2_F).reshape((m, m)), _fs(fb, lay, F_KF2_K), _fs(fb, lay, F_KF2_X),
                   _fs(fb, lay, F_KF2_XP), big[:, :n, 1].T, noskip, _fs(fb, lay, F_KF2_ZL))
        kf_seq[0] = last + 1
        # the recursive DFT (FrequencyStream.update_block: its gap filler, then the sums)
        gap_seq[0] = last
        gl = _fs(fb, lay, F_GAP_LAST)
        gl[0], gl[1], gl[2] = th1[n - 1], th2[n - 1], tq[n - 1]
        H = ic[IC_H]
        added = rdft_accumulate(th1, th2, tq, _is(ib, lay, I_FS_HARM), _cs(cb, lay, C_FS_TABLE),
                                _is(ib, lay, I_FS_IDX), _cs(cb, lay, C_FS_ACC).reshape((3, H)),
                                _cs(cb, lay, C_FS_S1).reshape((3, H)), _cs(cb, lay, C_FS_S2),
                                _fs(fb, lay, F_FS_STATE), _fs(fb, lay, F_FS_LAST), _fs(fb, lay, F_FS_QMIN),
                                fc[FC_FS_LAM], ic[IC_FS_DISCARD])
        cnt = _is(ib, lay, I_FS_COUNT)
        cnt[0] += n
        if added > 0:
            code |= _hand_over_sums(ib, fb, cb, lay, fh, fdi, fdf)
        if ic[IC_HAS_SVF]:                      # the per-sample estimator (Supervisor.observe)
            svf_block(th1, th2, tq, _fs(fb, lay, F_SVF_PHI).reshape((3, 3)), _fs(fb, lay, F_SVF_G0),
                      _fs(fb, lay, F_SVF_G1), _fs(fb, lay, F_SVF_GZ), _fs(fb, lay, F_SVF_XS).reshape((4, 3)),
                      _fs(fb, lay, F_SVF_PREV), _fs(fb, lay, F_SVF_SCALE), fc[FC_SVF_LAMF], fc[FC_SVF_RHO],
                      _fs(fb, lay, F_SVF_PRIOR), _fs(fb, lay, F_SVF_SIGMA).reshape((4, 4)),
                      _fs(fb, lay, F_SVF_RM).reshape((4, 4)), _fs(fb, lay, F_SVF_RV), _fs(fb, lay, F_SVF_ACC),
                      _fs(fb, lay, F_SVF_P), _fs(fb, lay, F_SVF_TMP).reshape((4, 4)), _fs(fb, lay, F_SVF_COUNTS),
                      fc[FC_SVF_MINT2], fc[FC_SVF_LAMG], trace)
    if not mode & MODE_CONTROL:
        return code
    # ---- the controller (Supervisor.tick; its bookkeeping, then the law)
    has_ctl = ic[IC_HAS_CTL]
    if has_ctl:
        now = _fs(fb, lay, F_SUP_NOW)
        sc = _fs(fb, lay, F_SUP_C)
        st = _fs(fb, lay, F_LAW_ST)
        if bi[BI_SEQ0] < 0 or st[ST_FRICTION] != 0.0:
            return code | PY_CONTROL
        th1f, th2f = big[0, n - 1, 0], big[0, n - 1, 1]
        w1f, w2f = big[1, n - 1, 0], big[1, n - 1, 1]
        e = sc[SC_LEAD] * th2f - xr
        if abs(e) > sc[SC_MAX_ERROR] or not math.isnan(now[NOW_FALLBACK_SINCE]):
            return code | PY_CONTROL            # Supervisor._watch acts on it (it does nothing otherwise)
        track_error(now, _fs(fb, lay, F_SUP_ERR), sc, t_ctl, th1f, w1f, th2f, w2f, xr, vr, ar)
        u = law_step(_fs(fb, lay, F_LAW_G), st, _fs(fb, lay, F_LAW_C), th1f, w1f, th2f, w2f, xr, vr, ar, a_ff,
                     sc[SC_LEAD], 0.0)
        if not schedule_torque(bi, bf, last, ic[IC_LAG], u):
            return code | SCHED_FULL
    # ---- the safety checks (SafetyMonitor.check)
    sf = _fs(fb, lay, F_SAFE)
    a1, a2 = th1[n - 1], th2[n - 1]
    if abs(last_torque) > fc[FC_STUCK_TORQUE] and a1 == sf[SAFE_LAST_THETA1]:
        return code | PY_SAFETY
    lead = fc[FC_SAFE_LEAD]
    x = lead * a2
    v = lead * big[1, n - 1, 1]
    x_stop = x + v * abs(v) / (2.0 * (lead * fc[FC_SAFE_DECEL]))
    lo, hi = fc[FC_SAFE_LO], fc[FC_SAFE_HI]
    if not (lo <= x <= hi) or not (lo <= x_stop <= hi) or abs(v) > fc[FC_SAFE_VMAX]:
        return code | PY_SAFETY
    sf[SAFE_STALE] = 0.0
    sf[SAFE_STUCK] = 0.0
    sf[SAFE_LAST_THETA1] = a1
    bi[BI_NEXT_SEQ] = last + 1
    # ---- the torque estimate's running sums (IdentificationLoop._torque_estimate)
    if ident:
        eq18_accumulate(trace, I1, B, K, _fs(fb, lay, F_EQ18))
    # ---- the telemetry window (IdentificationLoop._collect_telemetry)
    if ic[IC_HAS_TEL]:
        stride = ic[IC_STRIDE]
        rows = _fs(fb, lay, F_TEL)
        cap = rows.shape[0] // len(SAMPLE_KEYS)
        rows = rows.reshape((len(SAMPLE_KEYS), cap))
        i0 = bi[BI_TEL_N]
        if i0 + (n + stride - 1) // stride > cap:
            return code | PY_TELEMETRY
        bi[BI_TEL_N] = i0 + collect_samples(rows, i0, stride, t, th1, th2, tq, tcmd, trace, ident != 0, I1, B, K)
        pe = ic[IC_PUBLISH_EVERY]
        tk = _fs(fb, lay, F_TICKS).reshape((len(TICK_KEYS), pe + 1))
        k = bi[BI_TICK_N]
        tk[0, k] = t[n - 1]
        tk[1, k] = lateness_s * 1e6
        if has_ctl:
            now = _fs(fb, lay, F_SUP_NOW)
            tk[2, k] = now[NOW_XREF]
            tk[3, k] = now[NOW_XREF] + now[NOW_ERR]
            tk[4, k] = now[NOW_ERR]
            tk[5, k] = _fs(fb, lay, F_LAW_ST)[ST_U]
            if ic[IC_HAS_SVF]:                  # the per-sample estimate, in physical units (SvfEstimator.values)
                p, scale = _fs(fb, lay, F_SVF_P), _fs(fb, lay, F_SVF_SCALE)
                for j in range(4):
                    tk[6 + j, k] = p[j] * scale[j]
        bi[BI_TICK_N] = k + 1
        bi[BI_WIN_TICKS] += 1
        if bi[BI_WIN_TICKS] >= bi[BI_FLUSH_AT]:
            code |= _hand_over_samples(bi, _is(ib, lay, I_TEL), rows, pe, th, tdi, tdf)
        elif bi[BI_TICK_N] > pe or (bi[BI_WIN_TICKS] == 1 and bi[BI_TICK_N] > 1):
            code |= _hand_over_ticks(bi, _is(ib, lay, I_TEL), tk, _fs(fb, lay, F_WIN), th, tdi, tdf)
    # ---- the plan for the next samples (IdentificationLoop._write_plan)
    plan = _fs(fb, lay, F_PLAN)
    table = _fs(fb, lay, F_EXTABLE)
    start = bi[BI_NEXT_SEQ]
    period = ic[IC_PERIOD]
    i = start % period
    for j in range(plan.shape[0]):
        plan[j] = table[i + j]
    if has_ctl:
        shape_plan(plan, start, bi, bf, period, want)
    else:
        plan[plan.shape[0] - 1] = 0.0          # the value a lease holds: no probe (IdentificationLoop._write_plan)
    return code | PLAN_BUILT


@numba.njit(inline="always")
def _hand_over_sums(ib, fb, cb, lay, fh, fdi, fdf) -> int:
    """A period completed: the running sums to the fit process when it waits for them (the Python path takes
    the snapshot now and sends it on the axis's send tick: IdentificationLoop._snapshot_due), or PERIODS:
    the Python path's to do."""
    fit = _is(ib, lay, I_FIT)
    if fit[FIT_OK] == 0:
        return PERIODS
    if not consumer_waits(fh):
        return SNAPSHOT_SKIPPED
    ff = _fs(fb, lay, F_FIT)
    st = _fs(fb, lay, F_FS_STATE)
    ff[FIT_SCALARS + 2], ff[FIT_SCALARS + 3], ff[FIT_SCALARS + 4] = st[1], st[2], st[4]    # W, W2, periods used
    q = ff[FIT_QUANTUM:FIT_QUANTUM + 2] if fit[FIT_FIXED_Q] else _fs(fb, lay, F_FS_QMIN)
    got = put_sums(fh, fdi, fdf, fit[FIT_CAP], fit[FIT_MAXMSG], fit[FIT_KEYS:FIT_KEYS + 10], _is(ib, lay, I_FS_HARM),
                   _cs(cb, lay, C_FS_S1), _cs(cb, lay, C_FS_S2), q, ff[FIT_SCALARS:FIT_SCALARS + 5],
                   fit[FIT_CODEC:FIT_CODEC + 2], fit[FIT_CODEC_LEN])
    return SNAPSHOT_SENT if got == 1 else PERIODS


@numba.njit(inline="always")
def _hand_over_samples(bi, tel, rows, pe, th, tdi, tdf) -> int:
    """The window's samples into the telemetry ring (IdentificationLoop._flush_telemetry(ticks=False),
    as TelemetryProcess.publish_rows writes them), or FLUSH_SAMPLES: the Python path's to do."""
    if tel[TEL_OK] == 0:
        return FLUSH_SAMPLES
    m = tel[TEL_SAMPLE_FIELDS]
    n = bi[BI_TEL_N]
    got = 1
    if n:
        got = put_rows(th, tdi, tdf, tel[TEL_CAP], tel[TEL_MAXMSG], tel[TEL_SKEYS:TEL_SKEYS + 2 * m],
                       tel[TEL_SROWS:TEL_SROWS + m], rows, n, tel[TEL_TAIL:TEL_TAIL + 4], -1, rows[0, :0],
                       False)
        if got < 0:                         # it never fits: publish_rows says why
            return FLUSH_SAMPLES
    bi[BI_WIN_TICKS] = 0
    bi[BI_TEL_N] = 0
    bi[BI_FLUSH_AT] = pe
    tel[TEL_WID] = -1                       # the window vector for the next tick's signals: the glue's
    code = WINDOW_DUE
    if n:
        code |= TEL_SENT if got == 1 else TEL_DROPPED
    return code


@numba.njit(inline="always")
def _hand_over_ticks(bi, tel, tk, win, th, tdi, tdf) -> int:
    """The window's per-tick signals and its vector into the telemetry ring (_flush_telemetry(samples=False)),
    or FLUSH_TICKS when the vector is not ready (a new set of names: its schema goes first, from Python)."""
    if tel[TEL_OK] == 0 or tel[TEL_WID] < 0:
        return FLUSH_TICKS
    m = tel[TEL_TICK_FIELDS]
    k = bi[BI_TICK_N]
    got = put_rows(th, tdi, tdf, tel[TEL_CAP], tel[TEL_MAXMSG], tel[TEL_TKEYS:TEL_TKEYS + 2 * m],
                   tel[TEL_TROWS:TEL_TROWS + m], tk, k, tel[TEL_TAIL:TEL_TAIL + 4], tel[TEL_WID],
                   win[:tel[TEL_NVAL]], True)
    if got < 0:
        return FLUSH_TICKS
    bi[BI_TICK_N] = 0
    tel[TEL_WID] = -1
    return TEL_SENT if got == 1 else TEL_DROPPED


# The kernel's argument types, fixed: block arrays of any layout (a serial board's sequence numbers are a
# strided view), the arena and the ring C-contiguous. A call with other types (read-only arrays, say)
# raises TypeError and the tick goes to the Python path: nothing is compiled in a tick (a lazily compiled
# new specialization stalls that tick for seconds).
_BLOCK = "float64[:], int64[:], float64[:], float64[:], float64[:], float64[:]"
_RING = "int64[::1], int64[::1], float64[::1]"
KERNEL_SIGNATURE = (f"int64(int64, {_BLOCK}, int64, float64[::1], int64[::1], complex128[::1], int64[::1], "
                    f"{_RING}, {_RING}, {_RING}, float64, float64, float64, float64, float64, float64, "
                    "float64, int64, float64, float64, float64, float64)")


@functools.cache
def compiled_kernel():
    """:func:`axis_tick` compiled for :data:`KERNEL_SIGNATURE` (from numba's cache after the first time;
    ~10 s the first time: docs/measurements.md), when the first :class:`AxisCore` is built."""
    return numba.njit(KERNEL_SIGNATURE, cache=True)(axis_tick)


def warm_up() -> None:
    """Compile (or load from the cache) the steps the Python path calls one by one, with the argument
    types it calls them with, before a loop's first tick: left to their first call, each costs that
    tick 0.1-2 s, long enough to trip a drive's heartbeat watchdog."""
    from rt_ident.control.law import feedback_torque, tracking_errors

    bi, bf = new_books()
    z1, z2 = np.zeros(3), np.zeros((3, 2))
    schedule_torque(bi, bf, 0, 1, 0.0)
    shape_plan(np.zeros(4), 0, bi, bf, 1, 1.0)
    for hat in (True, False):
        collect_samples(np.zeros((len(SAMPLE_KEYS), 4)), 0, 1, z1, z1, z1, z1, z1, np.zeros((3, TR_COLS)), hat,
                        0.0, 0.0, 0.0)
    eq18_accumulate(np.zeros((3, TR_COLS)), 0.0, 0.0, 0.0, np.zeros(4))
    g, st, c = np.zeros(6), np.zeros(6), np.ones(6)
    law_step(g, st, c, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
    feedback_torque(g, st, c, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    tracking_errors(c, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)       # a controller switch's and a stall resume's
    track_error(np.zeros(NOW_FALLBACK_SINCE + 1), np.zeros(6), np.ones(4), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    from rt_ident.processes.shm_ring import MessageRing, put_rows

    ring = MessageRing(1024)
    h, di, df = ring.compiled_views()
    keys = np.zeros(4, dtype=np.int64)
    put_seq_floats(h, di, df, 0, 0, keys, np.zeros(1, dtype=np.int64), z1, z1, z1, z1, z1, 5)
    put_rows(h, di, df, 0, 0, keys, np.zeros(1, dtype=np.int64), z2, 1, keys, 0, z1, True)

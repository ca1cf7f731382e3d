"""The simulated drive's torque plan: per-sample values keyed by sequence number, in one buffer, changed
by compiled calls.

The semantics are :class:`drivers.base.Backend`'s (a newer plan replaces the rest of an older one,
samples not covered hold the last value, values for samples already applied count as late): the older
plan is cut at the newer one's start, the gap between them held at the older plan's last value, the
newer one appended; the samples stepped take the plan's values and drop them. The loop writes a plan
and its lease every tick, on each axis: with numpy's slicing, ``np.full`` and ``np.concatenate`` of the
two plans that costs ~25 us per write with cold caches, in one compiled call a few.

State: ``buf`` (the values, float64), ``pm`` (int64: the plan's first sequence number, its length, the
offset of its first value in ``buf``) and ``pf`` (float64: the torque held where there is no plan).
"""

from __future__ import annotations

import numba
import numpy as np

PM_START, PM_SIZE, PM_OFF = range(3)


def new_plan(capacity: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An empty plan holding 0 N m: (buf, pm, pf)."""
    return np.zeros(capacity), np.zeros(3, dtype=np.int64), np.zeros(1)


@numba.njit(cache=True)
def _put(buf, pm, vals, first, start) -> int:
    """``vals[first:]`` from sample ``start`` on, over the plan (see the module docstring); returns 0, or
    the buffer length it needs (> len(buf): nothing changed)."""
    n = vals.shape[0] - first
    cap = buf.shape[0]
    size, ps, off = pm[PM_SIZE], pm[PM_START], pm[PM_OFF]
    if size > 0 and ps < start:
        keep = min(size, start - ps)
        gap = start - (ps + keep)
        last = buf[off + size - 1]
        need = keep + gap + n
        if need > cap:
            return need
        if off + need > cap:                # compact: the kept values to the front
            for j in range(keep):
                buf[j] = buf[off + j]
            off = 0
        for j in range(gap):
            buf[off + keep + j] = last
        for j in range(n):
            buf[off + keep + gap + j] = vals[first + j]
        pm[PM_SIZE], pm[PM_OFF] = need, off
    else:
        if n > cap:
            return n
        for j in range(n):
            buf[j] = vals[first + j]
        pm[PM_START], pm[PM_SIZE], pm[PM_OFF] = start, n, 0
    return 0


@numba.njit(cache=True)
def _lease(buf, pm, pf, zero, at, stepped, late) -> int:
    """The lease's one-value plan of 0 N m at sample ``at`` (a late one: the torque is zero from now)."""
    if at < stepped:
        pf[0] = 0.0
        pm[PM_SIZE] = 0
        return late + 1
    need = _put(buf, pm, zero, 0, at)
    return -need if need else late


@numba.njit("int64(float64[::1], int64[::1], float64[::1], float64[:], int64, int64, int64)", cache=True)
def plan_write(buf, pm, pf, vals, start, stepped, lease) -> int:
    """Write ``vals`` for samples ``start``, ``start + 1``, ...; the plant has stepped the samples before
    ``stepped``. ``lease`` >= 0: then a one-value plan of 0 N m ``lease`` samples after the plan's end (the
    base class's lease). Returns the values that came late (>= 0), or minus the buffer length needed
    (nothing changed then: grow ``buf`` and call again)."""
    n = vals.shape[0]
    if n == 0:
        return 0
    first = 0
    if start < stepped:                     # values for samples already applied: late, dropped
        first = min(stepped - start, n)
        if first == n:
            pf[0] = vals[n - 1]
            pm[PM_SIZE] = 0
            if lease >= 0:                  # the lease's zero still lands after the plan's end
                zero = np.zeros(1)
                return _lease(buf, pm, pf, zero, start + n + lease, stepped, first)
            return first
        start = stepped
    if lease >= 0:
        # check the room both need before changing anything
        size, ps = pm[PM_SIZE], pm[PM_START]
        base = ps if size > 0 and ps < start else start
        need = (start + n - first + lease + 1) - base
        if need > buf.shape[0]:
            return -need
    need = _put(buf, pm, vals, first, start)
    if need:
        return -need
    if lease >= 0:
        zero = np.zeros(1)
        return _lease(buf, pm, pf, zero, start + n - first + lease, stepped, first)
    return first


@numba.njit("void(float64[::1], int64[::1], float64[::1], float64[::1], int64)", cache=True)
def plan_take(buf, pm, pf, out, p) -> None:
    """The commands for samples ``p .. p + len(out) - 1`` into ``out``, and drop them from the plan: the
    held torque before the plan's start, the plan's values, its last value after its end (which then
    becomes the held torque)."""
    n = out.shape[0]
    size = pm[PM_SIZE]
    hold = pf[0]
    if size == 0:
        for j in range(n):
            out[j] = hold
        return
    ps, off = pm[PM_START], pm[PM_OFF]
    pe = ps + size
    end = p + n
    head = min(ps - p, n)
    for j in range(head):
        out[j] = hold
    for s in range(max(ps, p), min(end, pe)):
        out[s - p] = buf[off + s - ps]
    if end >= pe:
        last = buf[off + size - 1]
        for j in range(pe - p, n):
            out[j] = last
        pf[0] = last
        pm[PM_SIZE] = 0
    elif end > ps:
        pm[PM_OFF] = off + (end - ps)
        pm[PM_SIZE] = size - (end - ps)
        pm[PM_START] = end

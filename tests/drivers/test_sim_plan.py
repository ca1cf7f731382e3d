"""The sim's compiled torque plan (drivers.sim_plan) against the numpy plan it replaced, write by write."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim_plan import PM_OFF, PM_SIZE, new_plan, plan_take, plan_write


class NumpyPlan:
    """The sim's plan as it was (numpy slicing and concatenation): the oracle."""

    def __init__(self) -> None:
        self.hold, self.plan, self.start, self.late = 0.0, np.empty(0), 0, 0

    def write(self, vals: np.ndarray, start: int, stepped: int) -> None:
        if vals.size == 0:
            return
        if start < stepped:
            late = min(stepped - start, vals.size)
            self.late += late
            if late == vals.size:
                self.hold, self.plan = float(vals[-1]), vals[:0]
                return
            vals, start = vals[late:], stepped
        old, os_ = self.plan, self.start
        if old.size and os_ < start:
            keep = old[: max(0, min(old.size, start - os_))]
            gap = start - (os_ + keep.size)
            self.plan = np.concatenate((keep, np.full(gap, old[-1]), vals))
        else:
            self.plan, self.start = vals.copy(), start

    def take(self, n: int, p: int) -> np.ndarray:
        end, plan = p + n, self.plan
        if not plan.size:
            return np.full(n, self.hold)
        cmd = np.empty(n)
        ps = self.start
        pe = ps + plan.size
        cmd[:min(ps - p, n)] = self.hold
        b = min(end, pe)
        if ps < b:
            cmd[ps - p:b - p] = plan[:b - ps]
        if end >= pe:
            cmd[pe - p:] = plan[-1]
            self.hold, self.plan = float(plan[-1]), plan[:0]
        elif end > ps:
            self.plan, self.start = plan[end - ps:], end
        return cmd


def _write(state, vals, start, stepped, lease):
    buf, pm, pf = state
    while True:
        late = plan_write(buf, pm, pf, vals, start, stepped, lease)
        if late >= 0:
            return state, late
        grown = np.zeros(-late)
        grown[:pm[PM_SIZE]] = buf[pm[PM_OFF]:pm[PM_OFF] + pm[PM_SIZE]]
        pm[PM_OFF] = 0
        state = (grown, pm, pf)
        buf = grown


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_plan_commands_every_sample_as_the_numpy_plan_did(seed):
    rng = np.random.default_rng(seed)
    oracle, state = NumpyPlan(), new_plan(capacity=64)     # small: the buffer compacts and grows too
    stepped, late = 0, 0
    for _ in range(400):
        if rng.random() < 0.6:                 # a plan, like the loop's: near the next sample, sometimes late
            n = int(rng.integers(0, 90))
            start = stepped + int(rng.integers(-40, 60))
            vals = rng.normal(size=n)
            lease = int(rng.integers(0, 200)) if rng.random() < 0.7 else -1
            oracle.write(vals, start, stepped)
            if lease >= 0 and n:                  # the base class's lease: a one-value plan of 0 after the plan
                oracle.write(np.zeros(1), start + n + lease, stepped)
            state, got = _write(state, vals, start, stepped, lease)
            late += got
        else:                                    # the plant steps
            n = int(rng.integers(1, 120))
            out = np.empty(n)
            plan_take(*state, out, stepped)
            np.testing.assert_array_equal(out, oracle.take(n, stepped))
            stepped += n
    assert late == oracle.late

"""SimBackend.step_ahead: in paced mode the loop lets the simulated drive step, after each tick,
through the samples due by the next deadline; read() then only hands them out. The samples must be
the ones stepping at read() gave, and the drive must do nothing a real one would not."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import TravelLimitTrip
from drivers.sim import PAPER_DT, SimBackend

PACED = {"paced": True, "position_hold": False, "torque_meas_noise": 0.001, "seed": 3}
TICK = 1e-3


class FakeClock:
    def __init__(self, t: float = 10.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _run(ahead: bool, ticks: int = 40, late_every: int = 7):
    """A loop's pattern on a fake clock: read at the deadline (every ``late_every``-th tick 0.3 ms
    late), write a two-tick plan keyed by sequence number, then (``ahead``) step to the next deadline."""
    clk = FakeClock()
    blocks = []
    with SimBackend(PACED, clock=clk) as b:
        b.activate()
        t0 = clk.t
        rng = np.random.default_rng(0)
        for k in range(1, ticks + 1):
            clk.t = t0 + k * TICK + (0.3e-3 if k % late_every == 0 else 0.0)
            blk = b.read()
            blocks.append(blk)
            b.write(rng.uniform(-0.05, 0.05, 70), start_seq=int(blk.seq[-1]) + 1)
            if ahead:
                b.step_ahead(t0 + (k + 1) * TICK - clk.t)
        late = b.late_plan_samples
    return blocks, late


def test_stepping_ahead_gives_exactly_the_samples_that_stepping_at_read_gave():
    plain, late_plain = _run(ahead=False)
    ahead, late_ahead = _run(ahead=True)
    assert [len(b) for b in plain] == [len(b) for b in ahead] and sum(len(b) for b in plain) > 1000
    for p, a in zip(plain, ahead):
        np.testing.assert_array_equal(p.seq, a.seq)
        np.testing.assert_array_equal(p.torque_cmd, a.torque_cmd)
        np.testing.assert_array_equal(p.theta1, a.theta1)
        np.testing.assert_array_equal(p.theta2, a.theta2)
        np.testing.assert_array_equal(p.torque_meas, a.torque_meas)
    assert late_plain == late_ahead == 0


def test_a_read_before_the_stepped_samples_are_due_returns_only_the_due_ones_and_a_write_finds_the_rest_applied():
    clk = FakeClock()
    with SimBackend(PACED, clock=clk) as b:
        b.activate()
        t0 = clk.t
        b.write(np.full(200, 0.02), start_seq=0)
        b.step_ahead(2 * TICK)                       # through the samples due by t0 + 2 ms
        stepped = int(np.floor(2 * TICK / PAPER_DT))
        clk.t = t0 + TICK                            # read after 1 ms: only those due then
        blk = b.read()
        due = int(np.floor(TICK / PAPER_DT))
        assert len(blk) == due and b.samples_produced == due
        b.write(np.full(100, -0.02), start_seq=due)  # the drive applied 0.02 to the rest already
        assert b.late_plan_samples == stepped - due
        clk.t = t0 + 3 * TICK
        rest = b.read()
        assert rest.seq[0] == due                    # nothing lost, nothing twice
        assert np.all(rest.torque_cmd[:stepped - due] == 0.02)
        assert np.all(rest.torque_cmd[stepped - due:] == -0.02)


def test_a_travel_trip_while_stepping_ahead_stops_the_torque_at_once_and_the_read_that_delivers_it_raises():
    clk = FakeClock()
    with SimBackend({**PACED, "travel": [-1e-3, 1e-3]}, clock=clk) as b:
        b.activate()
        t0 = clk.t
        b.write(1.0)                                 # pushes the free table out of travel in ~10 ms
        k = 0
        with pytest.raises(TravelLimitTrip, match="outside travel"):
            while k < 200:
                k += 1
                clk.t = t0 + k * TICK
                b.read()
                b.step_ahead(TICK)
                if b._ahead_trip is not None:        # tripped while stepping ahead: drive off now
                    assert not b.drive_enabled and b.applied_torque == 0.0
                    with pytest.raises(TravelLimitTrip):
                        b.write(0.5)                 # refused before the read that reports it
        assert b._ahead_trip is None and b.tripped is not None
        assert b.trip_block is not None and b.trip_block.seq[-1] == b.samples_produced - 1
        with pytest.raises(TravelLimitTrip):
            b.read()


def test_step_ahead_does_nothing_unpaced_or_before_activation():
    b = SimBackend({"paced": False, "samples_per_read": 10})
    b.step_ahead(1.0)                                 # not open, not active: ignored
    with b:
        b.activate()
        b.step_ahead(1.0)
        assert len(b.read()) == 10 and b.samples_produced == 10


def test_a_paced_run_steps_the_sim_ahead_and_reports_that_apart_from_the_tick_work():
    from rt_ident.compose import run as run_mod
    from rt_ident.config import load

    s = run_mod.run(load(None, **{"loop.duration": 0.5, "loop.realtime": False, "telemetry.sink": "off",
                                  "recording.enabled": False, "backend.paced": True}))
    loop = s["loop"]
    assert s["stop"]["cause"] is None and loop["lost_samples"] == 0
    assert loop["samples"] >= 0.9 * 0.5 / PAPER_DT                     # every due sample was handed out
    ahead = loop["sim_ahead_us"]
    assert ahead["p50"] > 0 and ahead["max"] >= ahead["p50"]

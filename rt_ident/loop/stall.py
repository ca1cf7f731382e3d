"""Loop stalls: a tick that comes far later than its deadline.

A host stalls (a desktop's other work, a USB adapter, a disk flush, a paused VM). While it does, the
plan the loop wrote runs out and its lease drops the torque to zero (:mod:`drivers.base`): the table
coasts. The tick after the stall must not act on the error the coasting built up as if it had been
tracking all along: acting on it drives a frictionless table at the torque limit into its travel limit. So a
stall longer than ``[safety] max_stall_s`` is handled, as ``[safety] on_stall`` says:

* ``resume`` (default): once the loop has caught up with the device (a device that kept sampling
  hands its backlog over in pieces over several ticks; until the newest sample read is as recent as
  when the loop keeps up, it is tens of ms old, and the torque stays at the zero the lease left), the
  controller re-plans from where the table is (a jerk-limited rejoin of the
  path, :mod:`rt_ident.control.anchor`), nothing in flight, its integral re-seeded; the estimators
  skip the stretch (the per-sample estimator restarts its filters, the frequency fit leaves out the
  excitation periods the stall touched);
* ``stop``: a safe stop with cause ``loop-stall``.

A stall longer than ``max_stall_stop_s`` always stops. Every stall is counted and reported
(``loop.stalls``), and a trip or fallback shortly after one names it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rt_ident.errors import RtIdentError, ask_realtime


class LoopStall(RtIdentError):
    """The loop stalled longer than it may resume from (or ``on_stall = "stop"``). The stall is the
    host's: its ``fix`` asks for a real-time loop or a less busy host (``otherwise``: a setting that
    would have let the run go on)."""

    cause = "loop-stall"

    def __init__(self, message: str, otherwise: str | None = None) -> None:
        super().__init__(message)
        self._otherwise = otherwise
        self.fix = ask_realtime("the loop's thread was kept off its CPU (other processes, a disk or USB "
                                "driver, a paused VM)", otherwise)

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), (str(self), self._otherwise)


@dataclass(frozen=True)
class StallPolicy:
    """``[safety] max_stall_s``, ``on_stall``, ``max_stall_stop_s``."""

    max_s: float = 0.01
    action: str = "resume"
    stop_s: float = 1.0

    def verdict(self, stall_s: float) -> str | None:
        """None (not a stall), ``"resume"`` or the message of the stop."""
        if not stall_s > self.max_s:
            return None
        if self.action == "stop":
            return (f"loop stalled for {stall_s * 1e3:.0f} ms (> safety.max_stall_s = {self.max_s * 1e3:g} ms; "
                    "safety.on_stall = 'stop')")
        if stall_s > self.stop_s:
            return (f"loop stalled for {stall_s * 1e3:.0f} ms, longer than it may resume from "
                    f"(safety.max_stall_stop_s = {self.stop_s * 1e3:g} ms)")
        return "resume"


@dataclass
class StallLog:
    """The stalls of a run: when (the newest sample's time on the device clock) and how long."""

    events: list[tuple[float, float, str]] = field(default_factory=list)    # (t, length [s], action)
    count: int = 0
    longest_s: float = 0.0
    catch_up_longest_s: float = 0.0     # the longest wait, after a stall, for the device's backlog
    origin: float = 0.0                 # the loop's start on the clock ``t`` is on (the summary's zero)

    def caught_up(self, wait_s: float) -> None:
        self.catch_up_longest_s = max(self.catch_up_longest_s, wait_s)

    def note(self, t: float, stall_s: float, action: str) -> None:
        self.count += 1
        self.longest_s = max(self.longest_s, stall_s)
        if len(self.events) < 100:
            self.events.append((t, stall_s, action))

    def before(self, t: float, within_s: float = 2.0) -> str:
        """' (0.40 s after a 470 ms loop stall)' for the newest stall up to ``within_s`` before ``t``."""
        for ts, length, _ in reversed(self.events):
            if 0.0 <= t - ts <= within_s:
                return f" ({t - ts:.2f} s after a {length * 1e3:.0f} ms loop stall)"
            if ts <= t:
                break
        return ""

    def as_dict(self) -> dict[str, Any]:
        return {"count": self.count, "longest_ms": self.longest_s * 1e3,
                "catch_up_longest_ms": self.catch_up_longest_s * 1e3,
                "events": [{"t": round(t - self.origin, 4), "ms": round(s * 1e3, 1), "action": a}
                           for t, s, a in self.events[-20:]]}


__all__ = ["LoopStall", "StallLog", "StallPolicy"]

"""tools/slow_ticks.py: the kernel's per-CPU counts it reads and the per-part CPU time it charges."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

spec = importlib.util.spec_from_file_location("slow_ticks", Path(__file__).parents[2] / "tools" / "slow_ticks.py")
slow_ticks = importlib.util.module_from_spec(spec)
spec.loader.exec_module(slow_ticks)

INTERRUPTS = b"""           CPU0       CPU1
 36:          0     258427 PCI-MSIX-0000:00:02.0   1-edge      virtio1-req.0
 39:      33049          7 PCI-MSIX-0000:00:03.0   2-edge      virtio2-output.0
LOC:   26360592   10337232   Local timer interrupts
ERR:          0
"""

SOFTIRQS = b"""                    CPU0       CPU1
          HI:          0          0
       TIMER:     313589     472747
      NET_RX:    2601415    2440139
"""


def test_column_reads_one_cpus_counts_by_device_or_softirq_name():
    assert slow_ticks._column(INTERRUPTS, 1) == {"virtio1-req.0": 258427, "virtio2-output.0": 7,
                                                "LOC": 10337232}
    assert slow_ticks._column(INTERRUPTS, 0)["virtio2-output.0"] == 33049
    assert "ERR" not in slow_ticks._column(INTERRUPTS, 0)          # one count for all CPUs: no CPU's
    assert slow_ticks._column(SOFTIRQS, 0) == {"HI": 0, "TIMER": 313589, "NET_RX": 2601415}


def test_kernel_counts_delta_lists_only_what_changed_on_that_cpu():
    kc = slow_ticks.KernelCounts()
    try:
        kc.now = [INTERRUPTS, SOFTIRQS]
        kc.last = [INTERRUPTS.replace(b"258427", b"258420"), SOFTIRQS.replace(b"472747", b"472745")]
        assert kc.delta(1) == {"virtio1-req.0": 7, "TIMER": 2}
        assert kc.delta(0) == {}
    finally:
        kc.close()


def test_timed_charges_the_calls_cpu_time_to_its_own_part_and_passes_results_and_errors_through():
    parts = [0.0, 0.0]

    def spin(n: int) -> int:
        return sum(i * i for i in range(n))

    timed = slow_ticks._timed(parts, 1, spin)
    assert timed(200_000) == spin(200_000)
    assert parts[0] == 0.0 and parts[1] > 0.0
    with pytest.raises(ZeroDivisionError):
        slow_ticks._timed(parts, 0, lambda: 1 / 0)()


def test_the_steps_inside_processing_are_timed_each_into_its_own_part_and_missing_ones_are_skipped():
    from types import SimpleNamespace

    def busy() -> int:
        return sum(i * i for i in range(100_000))

    lp = SimpleNamespace(tool_phases=[0.0] * len(slow_ticks._PHASES), _core=SimpleNamespace(kernel=busy),
                         control=None, assess_turn=busy)
    slow_ticks._wrap_inner(lp)
    lp._core.kernel()
    lp.assess_turn()
    names = dict(zip(slow_ticks._PHASES, lp.tool_phases))
    assert names["compiled tick"] > 0.0 and names["supervisor"] > 0.0
    assert all(v == 0.0 for k, v in names.items() if k not in ("compiled tick", "supervisor"))


def test_spread_gives_the_nearest_rank_percentiles_and_the_max_of_a_parts_cpu_time():
    sp = slow_ticks._spread([float(v) for v in range(1, 101)])       # 1..100 us
    assert sp == {"p50": 51.0, "p90": 91.0, "p99": 100.0, "max": 100.0}
    assert slow_ticks._spread([]) == {}

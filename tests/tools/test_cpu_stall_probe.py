"""tools/cpu_stall_probe.py counts the gaps between clock readings that exceed its threshold."""

from __future__ import annotations

import importlib.util
from pathlib import Path

spec = importlib.util.spec_from_file_location("cpu_stall_probe",
                                              Path(__file__).parents[2] / "tools" / "cpu_stall_probe.py")
probe_mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(probe_mod)


def test_probe_counts_every_gap_above_a_tiny_threshold_and_none_above_a_huge_one():
    every = probe_mod.probe(0.05, None, threshold_us=1e-3)        # every clock step is a "stall"
    assert every["stalls"] > 1000 and every["largest_us"] == sorted(every["largest_us"], reverse=True)
    none = probe_mod.probe(0.05, None, threshold_us=1e7)          # nothing lasts 10 s
    assert none["stalls"] == 0 and none["over_1ms"] == 0 and none["largest_us"] == []


def test_probe_cli_refuses_a_non_positive_duration(capsys):
    import pytest

    with pytest.raises(SystemExit):
        probe_mod.main(["--seconds", "0"])
    assert "--seconds" in capsys.readouterr().err

"""Where an emulated device runs (drivers.placement): the heap treatment around its start."""

from __future__ import annotations

import gc

from drivers.placement import clear_heap, settle_heap


def _collections(fn) -> tuple[list[int], int]:
    """The generations the collector passed over while ``fn`` ran, and the objects frozen after it."""
    seen: list[int] = []

    def cb(phase: str, info: dict) -> None:
        if phase == "start":
            seen.append(info["generation"])

    gc.callbacks.append(cb)
    try:
        fn()
        frozen = gc.get_freeze_count()
    finally:
        gc.callbacks.remove(cb)
        gc.unfreeze()
    return seen, frozen


def test_settle_heap_freezes_what_is_alive_without_a_pass_of_the_collector() -> None:
    """Once the device's threads run, a full pass would hold the GIL against them for tens of ms."""
    seen, frozen = _collections(settle_heap)
    assert seen == [] and frozen > 0


def test_clear_heap_is_the_full_pass_made_before_the_device_starts() -> None:
    seen, _ = _collections(clear_heap)
    assert 2 in seen

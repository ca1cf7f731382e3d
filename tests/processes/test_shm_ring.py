"""The shared-memory message ring that replaces multiprocessing queues in the loop's hand-offs."""

from __future__ import annotations

import multiprocessing as mp
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rt_ident.errors import ConfigError, DataError
from rt_ident.processes.shm_ring import MessageRing


def _msg(i: int, n: int) -> dict[str, np.ndarray]:
    return {"t": np.arange(n, dtype=np.float64) + i, "seq": np.arange(n, dtype=np.int64) + 1000 * i,
            "raw": np.full(n % 13, i % 256, dtype=np.uint8)}


def test_messages_come_back_in_order_with_their_dtypes_and_values() -> None:
    ring = MessageRing(1 << 16)
    for i in range(5):
        assert ring.put(_msg(i, 10 + i))
    got = ring.get()
    assert len(got) == 5 and ring.pending_messages == 0 and ring.used_bytes == 0
    for i, m in enumerate(got):
        ref = _msg(i, 10 + i)
        assert set(m) == set(ref)
        for k in ref:
            assert m[k].dtype == ref[k].dtype
            np.testing.assert_array_equal(m[k], ref[k])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=200), min_size=1, max_size=200),
       st.integers(min_value=1, max_value=7))
def test_wraparound_keeps_every_message_intact(sizes: list[int], drain_every: int) -> None:
    ring = MessageRing(8192)
    sent: list[dict[str, np.ndarray]] = []
    got: list[dict[str, np.ndarray]] = []
    for i, n in enumerate(sizes):
        m = _msg(i, n)
        while not ring.put(m):          # full: drain, then it must fit
            drained = ring.get()
            assert drained, "put refused an empty ring"
            got += drained
        sent.append(m)
        if i % drain_every == 0:
            got += ring.get(max_messages=2)
    got += ring.get()
    assert len(got) == len(sent)
    for a, b in zip(sent, got):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])


def test_a_full_ring_refuses_without_writing_part_of_the_message() -> None:
    ring = MessageRing(4096)
    n = 0
    while ring.put({"x": np.full(40, float(n))}):
        n += 1
    assert n > 5
    used = ring.used_bytes
    assert not ring.put({"x": np.zeros(40)})
    assert ring.used_bytes == used and ring.pending_messages == n
    first = ring.get(1)[0]["x"]
    assert np.all(first == 0.0)
    assert ring.put({"x": np.full(40, -1.0)})       # room again


def test_max_messages_bounds_the_unread_messages() -> None:
    ring = MessageRing(1 << 16, max_messages=3)
    assert all(ring.put({"a": np.zeros(1)}) for _ in range(3))
    assert not ring.put({"a": np.zeros(1)})
    assert len(ring.get()) == 3
    assert ring.put({"a": np.zeros(1)})


def test_objects_round_trip_through_pickle_messages() -> None:
    ring = MessageRing(1 << 16)
    assert ring.get_object() == (False, None)
    assert ring.put_object({"fit": [1, 2.5], "err": ValueError("x")})
    ok, obj = ring.get_object()
    assert ok and obj["fit"] == [1, 2.5] and isinstance(obj["err"], ValueError)


def test_bad_messages_and_sizes_are_refused_with_clear_errors() -> None:
    with pytest.raises(ConfigError):
        MessageRing(100)
    ring = MessageRing(4096)
    with pytest.raises(DataError, match="longer than 16"):
        ring.put({"a_key_that_is_far_too_long": np.zeros(1)})
    with pytest.raises(DataError, match="does not fit"):
        ring.put({"x": np.zeros(1000)})
    with pytest.raises(DataError, match="dtype"):
        ring.put({"x": np.array(["a"])})
    ring.close_writer()
    assert ring.writer_closed
    with pytest.raises(DataError, match="closed"):
        ring.put({"x": np.zeros(1)})


def _consume(ring: MessageRing, result) -> None:
    total, count = 0.0, 0
    ring.flag = 1
    while True:
        closed = ring.writer_closed
        msgs = ring.get()
        for m in msgs:
            total += float(m["v"].sum())
            count += 1
        if closed and not msgs:
            break
    result.send((total, count))


def test_a_spawned_consumer_receives_every_message_the_producer_wrote() -> None:
    ctx = mp.get_context("spawn")
    ring = MessageRing(1 << 14, ctx=ctx)       # small: the producer laps the ring many times
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_consume, args=(ring, child), daemon=True)
    proc.start()
    try:
        expected, sent = 0.0, 0
        for i in range(3000):
            v = np.arange(i % 50, dtype=np.float64)
            while not ring.put({"v": v}):
                pass
            expected += float(v.sum())
            sent += 1
        ring.close_writer()
        assert parent.poll(30.0), "consumer did not finish"
        total, count = parent.recv()
        assert count == sent and total == expected
        assert ring.flag == 1                    # the consumer's flag is seen by the producer
    finally:
        proc.join(5.0)
        if proc.is_alive():
            proc.terminate()


def _ring_resident_kb(ring: MessageRing, result) -> None:
    """In the child: (resident kB, size kB) of the mapping that holds the ring's data."""
    import ctypes

    addr = ctypes.addressof(ring._data)
    with open("/proc/self/smaps") as fh:
        lines = fh.read().splitlines()
    for i, line in enumerate(lines):
        lo, _, hi = line.split(" ", 1)[0].partition("-")
        if hi and all(c in "0123456789abcdef" for c in lo + hi) and int(lo, 16) <= addr < int(hi, 16):
            fields = {ln.split(":")[0]: ln.split()[1] for ln in lines[i + 1:i + 25] if ln.endswith(" kB")}
            result.send((int(fields["Rss"]), int(fields["Size"])))
            return
    result.send(None)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/smaps")
def test_a_child_maps_the_whole_ring_when_it_attaches() -> None:
    """A helper's resident set holds the whole ring from the start, not one more page each time the
    ring's position first reaches it (which would grow a fit process's RSS for minutes, like a leak)."""
    ctx = mp.get_context("spawn")
    ring = MessageRing(4 << 20, ctx=ctx)
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_ring_resident_kb, args=(ring, child), daemon=True)
    proc.start()
    try:
        assert parent.poll(30.0), "child did not answer"
        rss_kb, size_kb = parent.recv()
        assert size_kb >= 4 << 10 and rss_kb >= 4 << 10, (rss_kb, size_kb)
    finally:
        proc.join(5.0)

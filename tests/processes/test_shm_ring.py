"""The shared-memory message ring that replaces multiprocessing queues in the loop's hand-offs."""

from __future__ import annotations

import multiprocessing as mp
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rt_ident.errors import ConfigError, DataError
from rt_ident.processes.shm_ring import MessageRing, RingReused


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


def test_a_side_whose_ring_memory_holds_another_rings_token_stops_without_touching_it() -> None:
    ring = MessageRing(4096)
    other = MessageRing.__new__(MessageRing)
    other.__setstate__(ring.__getstate__())          # the other side, as a child process holds it
    assert ring.put({"x": np.arange(3.0)}) and len(other.get()) == 1
    ring._h[3] = ring._h[3] ^ 0x5A5A               # a new ring took the memory: its own token there
    before = list(ring._h)
    for touch in (other.get, lambda: other.put({"x": np.zeros(1)}), lambda: setattr(other, "flag", 1),
                  other.close_writer):
        with pytest.raises(RingReused, match="given to another ring"):
            touch()
    assert list(ring._h) == before


def _stale_consumer(ring: MessageRing, seconds: float) -> None:
    """A helper that outlives its parent's ring: it keeps polling, as a job process does."""
    import os
    import time

    ring.flag = 1
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            ring.get()
            time.sleep(0.001)
    except RingReused:
        os._exit(3)
    os._exit(0)


def test_multiprocessing_gives_a_freed_rings_memory_to_the_next_ring_at_once() -> None:
    """Why rings carry a token: in a fresh interpreter the next ring lands on the freed one's addresses."""
    import subprocess

    code = ("import ctypes, gc\n"
            "from rt_ident.processes.shm_ring import MessageRing\n"
            "a = MessageRing(1 << 14)\n"
            "where = ctypes.addressof(a._header), ctypes.addressof(a._data)\n"
            "del a; gc.collect()\n"
            "b = MessageRing(1 << 14)\n"
            "print((ctypes.addressof(b._header), ctypes.addressof(b._data)) == where)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "True", out.stderr[-2000:]


def test_a_helper_still_running_on_a_ring_its_parent_let_go_of_does_not_consume_the_next_ring() -> None:
    """The next ring made on the same memory (zeroed, its own token, as multiprocessing hands it out): the
    stale helper stops at its next look instead of taking the new ring's messages."""
    import ctypes
    import time

    ctx = mp.get_context("spawn")
    old = MessageRing(1 << 14, ctx=ctx)
    proc = ctx.Process(target=_stale_consumer, args=(old, 30.0), daemon=True)
    proc.start()
    try:
        end = time.monotonic() + 30.0
        while old.flag != 1 and time.monotonic() < end:
            time.sleep(0.01)
        assert old.flag == 1, "the helper did not start"
        new = MessageRing.__new__(MessageRing)
        new.__setstate__({**old.__getstate__(), "token": old._token ^ 0x5A5A})
        ctypes.memset(ctypes.addressof(old._header), 0, ctypes.sizeof(old._header))
        new._h[3] = new._token
        for i in range(5):
            assert new.put({"v": np.full(3, float(i))})
        proc.join(10.0)
        assert proc.exitcode == 3                   # it stopped at its next look
        assert [float(m["v"][0]) for m in new.get()] == [0.0, 1.0, 2.0, 3.0, 4.0]
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join(5.0)


def test_python_and_compiled_producers_interleaved_deliver_every_message_intact() -> None:
    """Random sizes, rings of a few kB and message limits, ``put``, ``put_rows`` and ``put_seq_floats`` in
    any order with partial reads between them: what comes out is what went in, in order."""
    from rt_ident.processes.shm_ring import key_words, put_rows, put_seq_floats

    rng = np.random.default_rng(5)
    names = ["t", "x", "y", "z"]
    for _ in range(40):
        ring = MessageRing(int(rng.choice([1024, 2048, 4096])), max_messages=int(rng.choice([3, 10, 1 << 30])))
        h, di, df = ring.compiled_views()
        sent: list[dict[str, np.ndarray]] = []
        got: list[dict[str, np.ndarray]] = []
        for _ in range(300):
            r = rng.random()
            if r < 0.3:
                msg = {"a": rng.standard_normal(int(rng.integers(0, 40))),
                       "u": rng.integers(0, 255, int(rng.integers(0, 13))).astype(np.uint8)}
                if ring.put(msg):
                    sent.append(msg)
            elif r < 0.5:
                n, m, nv = int(rng.integers(1, 30)), int(rng.integers(1, 5)), int(rng.integers(0, 6))
                rows, tv, tail = rng.standard_normal((4, 40)), rng.standard_normal(nv), bool(rng.random() < 0.5)
                keys = np.concatenate([key_words(k) for k in names[:m]])
                tk = np.concatenate([key_words("wid"), key_words("win")])
                if put_rows(h, di, df, ring.capacity, ring.max_messages, keys, np.arange(m), rows, n, tk, 7, tv,
                            tail) == 1:
                    sent.append({k: rows[i, :n] for i, k in enumerate(names[:m])}
                                | ({"wid": np.array([7]), "win": tv} if tail else {}))
            elif r < 0.65:
                n, nc = int(rng.integers(0, 20)), int(rng.integers(1, 6))
                seq, cs = rng.integers(0, 1000, n), [rng.standard_normal(n) for _ in range(5)]
                keys = np.concatenate([key_words("seq"), key_words("f")])
                if put_seq_floats(h, di, df, ring.capacity, ring.max_messages, keys, seq, *cs, nc) == 1:
                    sent.append({"seq": seq, "f": np.concatenate(cs[:nc])})
            else:
                got.extend(ring.get(None if rng.random() < 0.5 else int(rng.integers(1, 4))))
        got.extend(ring.get())
        assert len(got) == len(sent)
        for a, b in zip(sent, got):
            assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)

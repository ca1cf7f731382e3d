"""The loop's telemetry windows: decimated samples and per-tick lateness, published without concatenation."""

from __future__ import annotations

import numpy as np

from drivers.base import SampleBlock
from rt_ident.runtime.loop import IdentificationLoop


class _Backend:
    sample_period = 1e-5          # 100 samples per 1 ms tick
    last_torque = 0.0


def _loop(published: list) -> IdentificationLoop:
    def keep(block, window=None):  # the loop hands out views of its window buffers: copy, as publish() does
        out = {k: v.copy() for k, v in block.items()}
        out.update({k: np.full(block["t_tick"].shape, v) for k, v in (window or {}).items()})
        published.append(out)

    return IdentificationLoop(_Backend(), tick_hz=1000.0, excitation=lambda seq: np.zeros(seq.size),
                              state_estimator=None, estimator=None, safety=None, duration=1.0,
                              on_telemetry=keep, publish_every=4, telemetry_stride=10)


def _block(start: int, n: int) -> SampleBlock:
    seq = np.arange(start, start + n)
    t = seq * 1e-5
    return SampleBlock(t, seq, np.sin(t), np.cos(t), np.full(n, 0.1), None)


def test_a_window_publishes_every_stride_th_sample_and_each_ticks_lateness():
    published: list = []
    loop = _loop(published)
    blocks = [_block(100 * k, 100) for k in range(4)]
    for k, b in enumerate(blocks):
        loop._collect_telemetry(b, None, lateness_s=k * 1e-6)
    samples, ticks = published
    t_all = np.concatenate([b.t for b in blocks])
    np.testing.assert_array_equal(samples["t"], np.concatenate([b.t[::10] for b in blocks]))
    np.testing.assert_array_equal(samples["theta1"], np.sin(samples["t"]))
    assert samples["t"].size == 40 and "torque_hat" not in samples      # no estimate yet: no Eq. 18 torque
    np.testing.assert_allclose(ticks["lateness_us"], [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_array_equal(ticks["t_tick"], [b.t[-1] for b in blocks])
    assert ticks["t_tick"][-1] == t_all[-1]


def test_a_burst_after_a_stall_flushes_first_and_keeps_its_newest_samples():
    published: list = []
    loop = _loop(published)
    loop._collect_telemetry(_block(0, 100), None, 0.0)
    burst = _block(100, 5000)                  # 50 ticks of samples in one read
    loop._collect_telemetry(burst, None, 0.05)
    loop._flush_telemetry()
    first, second = published[0], published[2]          # [1] and [3] are the per-tick messages
    assert "t_tick" in published[1] and "t_tick" in published[3]
    np.testing.assert_array_equal(first["t"], _block(0, 100).t[::10])   # what was there went out first
    cap = loop._tel_buf["t"].shape[0]
    expect = burst.t[::10][-cap:]
    np.testing.assert_array_equal(second["t"], expect)
    assert np.all(np.diff(second["t"]) > 0)

"""The loop's telemetry windows: decimated samples and per-tick lateness, published without concatenation."""

from __future__ import annotations

import numpy as np

from drivers.base import SampleBlock
from rt_ident.estimators.svf import NO_TRACE, TR_COLS
from rt_ident.loop import tick_kernel as tk
from rt_ident.loop.loop import IdentificationLoop


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
    blocks = [_block(100 * k, 100) for k in range(5)]
    for k, b in enumerate(blocks[:4]):
        loop._collect_telemetry(b, NO_TRACE, lateness_s=k * 1e-6)
    (samples,) = published                     # the window's samples at its end ...
    loop._collect_telemetry(blocks[4], NO_TRACE, lateness_s=4e-6)
    ticks = published[1]                       # ... its per-tick signals one tick later (with that tick)
    np.testing.assert_array_equal(samples["t"], np.concatenate([b.t[::10] for b in blocks[:4]]))
    np.testing.assert_array_equal(samples["theta1"], np.sin(samples["t"]))
    assert samples["t"].size == 40
    assert "torque_filt" not in samples and "torque_hat" not in samples    # no SVF: no torque estimate
    np.testing.assert_allclose(ticks["lateness_us"], [0.0, 1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(ticks["t_tick"], [b.t[-1] for b in blocks])
    loop._flush_telemetry()                    # the run's end: what is left goes, nothing twice
    assert len(published) == 2 + 1 and published[2]["t"].size == 10 and "t_tick" not in published[2]


def test_a_burst_after_a_stall_flushes_first_and_keeps_its_newest_samples():
    published: list = []
    loop = _loop(published)
    loop._collect_telemetry(_block(0, 100), NO_TRACE, 0.0)
    burst = _block(100, 5000)                  # 50 ticks of samples in one read
    loop._collect_telemetry(burst, NO_TRACE, 0.05)
    loop._flush_telemetry()
    first, second = published[0], published[2]          # [1] and [3] are the per-tick messages
    assert "t_tick" in published[1] and "t_tick" in published[3]
    np.testing.assert_array_equal(first["t"], _block(0, 100).t[::10])   # what was there went out first
    cap = loop._tel_buf["t"].shape[0]
    expect = burst.t[::10][-cap:]
    np.testing.assert_array_equal(second["t"], expect)
    assert np.all(np.diff(second["t"]) > 0)


def test_one_sample_a_tick_keeps_each_blocks_first_sample_its_filtered_torque_and_eq18_from_the_svf_trace():
    from types import SimpleNamespace

    from rt_ident.axis.modal import modal_parameters
    from rt_ident.axis.params import thomson_x

    published: list = []
    loop = _loop(published)
    loop.stride = 100                                  # one sample of each 100-sample tick
    loop._sample_keys = tk.SAMPLE_KEYS                 # as with a per-sample estimator
    p = thomson_x()
    loop.identification = SimpleNamespace(params=p, modal=modal_parameters(p), ci95=None)
    rng = np.random.default_rng(1)
    blocks, traces = [], []
    for k in range(4):
        if k == 2:
            loop.torque_ident = loop.identification    # a trusted fit from the third tick on
        blocks.append(_block(100 * k, 100))
        traces.append(rng.normal(size=(100, TR_COLS)))
        loop._collect_telemetry(blocks[-1], traces[-1], 0.0)
    samples = published[0]
    np.testing.assert_array_equal(samples["t"], [b.t[0] for b in blocks])
    np.testing.assert_array_equal(samples["theta2"], [b.theta2[0] for b in blocks])
    np.testing.assert_array_equal(samples["torque_cmd"], [b.torque_cmd[0] for b in blocks])
    np.testing.assert_array_equal(samples["torque_filt"], [tr[0, 3] for tr in traces])
    want = [np.nan, np.nan] + [p.I1 * tr[0, 0] + p.B * tr[0, 1] + p.K * tr[0, 2] for tr in traces[2:]]
    np.testing.assert_allclose(samples["torque_hat"], want, rtol=1e-15, atol=0)

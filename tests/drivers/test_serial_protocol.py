"""The serial board codec: layout, round trips, resynchronization, unwrapping (docs/serial-protocol.md)."""

from __future__ import annotations

import struct
from binascii import crc_hqx

import numpy as np
import pytest
import serial
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from drivers.encoder_board import protocol as sp


def _data_block(n: int, seq0: int = 0, t0: int = 0) -> bytes:
    k = np.arange(n, dtype=np.int64)
    return sp.encode_data_block(seq0 + k, t0 + 50 * k, 1000 - 3 * k, -7 * k, 0.25 + 1e-3 * k,
                                (k % 100) - 50, np.full(n, sp.ST_ENABLED))


def _frames(n: int, seq0: int = 0) -> list[sp.DataFrame]:
    return sp.FrameDecoder().feed(_data_block(n, seq0))


# ----- layout and round trips ---------------------------------------------------------------
def test_crc_is_ccitt_false_with_its_check_value():
    assert crc_hqx(b"123456789", sp.CRC_INIT) == 0x29B1


def test_data_frame_layout_matches_the_spec_byte_for_byte():
    f = sp.DataFrame(seq=0x01020304, t_us=0xA0B0C0D0, enc=-2, scale=300, cmd=0.5, current=-1000,
                     status=sp.ST_ENABLED | sp.ST_PLAN_ACTIVE)
    raw = f.encode()
    # oracle: the table of section 2, written out by hand
    payload = (bytes([4, 3, 2, 1, 0xD0, 0xC0, 0xB0, 0xA0]) + (-2).to_bytes(4, "little", signed=True)
               + (300).to_bytes(4, "little") + struct.pack("<f", 0.5)
               + (-1000).to_bytes(2, "little", signed=True) + (0x21).to_bytes(2, "little"))
    body = bytes([0x01, 24]) + payload
    assert raw == b"\xa5\x5a" + body + crc_hqx(body, 0xFFFF).to_bytes(2, "little")
    assert len(raw) == sp.DATA_FRAME_SIZE == 30


def test_data_block_round_trip_preserves_every_field():
    frames = _frames(50, seq0=2**32 - 10)
    assert len(frames) == 50
    assert frames[0] == sp.DataFrame(2**32 - 10, 0, 1000, 0, 0.25, -50, sp.ST_ENABLED)
    assert frames[12].seq == 2 and frames[12].enc == 1000 - 36 and frames[12].scale == -84
    assert frames[12].cmd == pytest.approx(0.262, rel=1e-7)   # float32 on the wire
    single = b"".join(f.encode() for f in frames)
    assert single == _data_block(50, seq0=2**32 - 10)        # vectorized == one-by-one encoder


def test_host_frames_round_trip():
    sent = [sp.Enable(), sp.Disable(), sp.QuickStop(), sp.Heartbeat(2**32 - 1), sp.TorqueHold(-0.125),
            sp.TorquePlan(7, (0.5, -0.25, 1.0)), sp.InfoRequest()]
    got = sp.FrameDecoder().feed(b"".join(f.encode() for f in sent))
    assert got == sent
    assert sp.encode_info_request() == b"\xa5\x5a\x16\x00" + crc_hqx(b"\x16\x00", 0xFFFF).to_bytes(2, "little")


def test_info_frame_layout_matches_the_spec_and_round_trips_between_data_frames():
    info = sp.Info(2, (1, 4, 9), 0xDEADBEEF, "XB-20", 20000.0, 10.0, 0.125, 131072, 1e-7)
    raw = info.encode()
    # oracle: the INFO table of section 2, written out by hand
    payload = (bytes([2, 1, 4, 9]) + (0xDEADBEEF).to_bytes(4, "little") + b"XB-20" + bytes(11)
               + struct.pack("<fff", 20000.0, 10.0, 0.125) + (131072).to_bytes(4, "little") + struct.pack("<d", 1e-7))
    body = bytes([0x02, 48]) + payload
    assert raw == b"\xa5\x5a" + body + crc_hqx(body, 0xFFFF).to_bytes(2, "little")
    samples, others = sp.FrameDecoder().feed_samples(_data_block(5) + raw + _data_block(5, seq0=5))
    assert samples.shape[0] == 10 and others == [info]
    assert info.as_dict()["firmware"] == "1.4.9"


def test_long_plan_is_split_into_62_value_frames_with_consecutive_start_seq():
    values = np.arange(150, dtype=float) / 64.0              # exact in float32
    got = sp.FrameDecoder().feed(sp.encode_torque_plan(2**32 - 70, values))
    assert [len(f.torques) for f in got] == [62, 62, 26]
    assert [f.start_seq for f in got] == [2**32 - 70, 2**32 - 8, 54]    # wraps modulo 2^32
    assert np.array_equal(np.concatenate([f.torques for f in got]), values)


def test_feed_samples_fast_path_agrees_with_frame_objects():
    raw = _data_block(40) + sp.encode_heartbeat(3) + _data_block(5, seq0=40)
    arr, others = sp.FrameDecoder().feed_samples(raw)
    objs = [f for f in sp.FrameDecoder().feed(raw) if isinstance(f, sp.DataFrame)]
    assert others == [sp.Heartbeat(3)]
    assert [sp.DataFrame(*r) for r in arr[list(sp.SAMPLE_FIELDS)].tolist()] == objs


def test_codec_works_over_a_pyserial_loop_url():
    port = serial.serial_for_url("loop://", timeout=0.01)
    try:
        port.write(_data_block(100))
        dec = sp.FrameDecoder()
        got = []
        while len(got) < 100:
            got += dec.feed(port.read(port.in_waiting or 1))
        assert [f.seq for f in got] == list(range(100))
    finally:
        port.close()


# ----- resynchronization --------------------------------------------------------------------
def test_frames_split_at_every_byte_boundary_are_all_recovered():
    stream = _data_block(3) + sp.encode_torque_plan(5, [1.0, 2.0]) + sp.encode_enable() + _data_block(2, 3)
    expected = sp.FrameDecoder().feed(stream)
    assert len(expected) == 7
    for cut in range(len(stream) + 1):
        dec = sp.FrameDecoder()
        assert dec.feed(stream[:cut]) + dec.feed(stream[cut:]) == expected, cut
        assert dec.garbage_bytes == 0 and dec.crc_errors == 0
    dec = sp.FrameDecoder()
    assert [f for i in range(len(stream)) for f in dec.feed(stream[i:i + 1])] == expected


def test_garbage_is_skipped_and_counted_exactly():
    frames = _frames(4)
    junk1, junk2 = b"\x00\xff\x5a\x13", b"\xa5\xa5\x00"      # includes lone sync halves
    stream = junk1 + frames[0].encode() + frames[1].encode() + junk2 + frames[2].encode() + frames[3].encode()
    dec = sp.FrameDecoder()
    assert dec.feed(stream) == frames
    assert dec.garbage_bytes == len(junk1) + len(junk2)
    assert dec.resyncs == 2 and dec.crc_errors == 0


def test_a_crc_error_loses_only_the_corrupted_frame():
    frames = _frames(6)
    raw = bytearray(b"".join(f.encode() for f in frames))
    raw[2 * 30 + 10] ^= 0x40                                  # a payload byte of frame 2
    dec = sp.FrameDecoder()
    assert dec.feed(bytes(raw)) == frames[:2] + frames[3:]
    assert dec.crc_errors == 1 and dec.garbage_bytes == 30 and dec.resyncs == 1


def test_a_corrupted_length_byte_does_not_swallow_the_following_frames():
    frames = _frames(3)
    raw = bytearray(b"".join(f.encode() for f in frames))
    raw[3] = 200                                              # frame 0 claims a 200-byte payload
    dec = sp.FrameDecoder()
    assert dec.feed(bytes(raw)) == frames[1:]
    assert dec.header_errors == 1 and dec.buffered == 0


def test_flush_releases_a_frame_held_behind_a_truncated_header():
    hb = sp.encode_heartbeat(9)
    dec = sp.FrameDecoder()
    assert dec.feed(b"\xa5\x5a\x01\x18" + hb) == []       # waits: the data frame could still complete
    assert dec.flush() == [sp.Heartbeat(9)]
    assert dec.incomplete == 1 and dec.garbage_bytes == 4 and dec.buffered == 0


def test_a_truncated_frame_followed_by_a_good_one():
    frames = _frames(3)
    raw = frames[0].encode() + frames[1].encode()[:17] + frames[2].encode()
    dec = sp.FrameDecoder()
    assert dec.feed(raw) == [frames[0], frames[2]]
    assert dec.crc_errors == 1 and dec.garbage_bytes == 17


_frame_strategy = st.one_of(
    st.builds(sp.DataFrame, st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
              st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1),
              st.sampled_from([0.0, -1.5, 0.3125]), st.integers(-2**15, 2**15 - 1), st.integers(0, 0xFFFF)),
    st.builds(sp.Heartbeat, st.integers(0, 2**32 - 1)),
    st.builds(sp.TorqueHold, st.sampled_from([0.0, 1.25, -0.5])),
    st.builds(sp.TorquePlan, st.integers(0, 2**32 - 1),
              st.lists(st.sampled_from([0.5, -2.0, 0.0]), min_size=1, max_size=62).map(tuple)),
    st.just(sp.Enable()), st.just(sp.QuickStop()),
)


def _holds_no_frame(data: bytes) -> bool:
    dec = sp.FrameDecoder()
    return not (dec.feed(data) + dec.flush())


@st.composite
def _noisy_stream(draw):
    """Intact frames interleaved with garbage, truncated and corrupted frames, cut into chunks. Bytes that
    are not an intact frame never make one between two intact ones (garbage that completes a truncated
    frame's CRC is that frame: no decoder can tell; hypothesis found one)."""
    frames = draw(st.lists(_frame_strategy, min_size=1, max_size=12))
    parts, intact = [], []
    between = b""                                   # the bytes since the last intact frame
    for f in frames:
        raw = f.encode()
        kind = draw(st.sampled_from(["intact", "intact", "garbage", "truncated", "corrupt"]))
        if kind == "garbage":
            part = draw(st.binary(min_size=1, max_size=40).filter(lambda g: _holds_no_frame(between + g)))
        elif kind == "truncated":
            part = raw[:draw(st.integers(1, len(raw) - 1))]
        elif kind == "corrupt":
            i = draw(st.integers(2, len(raw) - 1))
            bad = bytearray(raw)
            bad[i] ^= draw(st.integers(1, 255))
            part = bytes(bad)
        if kind != "intact":
            parts.append(part)
            between += part
            assume(_holds_no_frame(between))
            intact_after = draw(st.booleans())
            if not intact_after:
                continue
        parts.append(raw)
        intact.append(f)
        between = b""
    stream = b"".join(parts)
    cuts = sorted(draw(st.lists(st.integers(0, len(stream)), max_size=6)))
    return stream, cuts, intact


@settings(max_examples=300, deadline=None)
@given(_noisy_stream())
def test_any_garbage_interleaving_recovers_every_intact_frame_and_invents_none(case):
    stream, cuts, intact = case
    dec = sp.FrameDecoder()
    got, prev = [], 0
    for c in cuts + [len(stream)]:
        got += dec.feed(stream[prev:c])
        prev = c
    got += dec.flush()                           # end of stream: a trailing partial frame is final
    assert got == intact
    assert dec.buffered == 0


# ----- sequence and time ------------------------------------------------------------------
def test_seq_time_and_counters_unwrap_across_32_bit_wrap_in_any_blocking():
    n = 400
    k = np.arange(n, dtype=np.int64)
    seq0, t0, e0 = 2**32 - 150, 2**32 - 5000, 2**31 - 100
    raw = sp.encode_data_block(seq0 + k, t0 + 50 * k, e0 + k, -(2**31) + 50 - k, np.zeros(n),
                               np.zeros(n), np.zeros(n))
    arr, _ = sp.FrameDecoder().feed_samples(raw)
    for split in (1, 150, 151, 399):
        un = sp.StreamUnwrapper()
        a, b = un.update(arr[:split]), un.update(arr[split:])
        seq = np.concatenate([a.seq, b.seq])
        assert np.array_equal(seq, seq0 + k)                   # int64, no wrap
        t = np.concatenate([a.t, b.t])
        assert np.allclose(np.diff(t), 50e-6, rtol=0, atol=1e-12)
        assert t[0] == pytest.approx(t0 * 1e-6)
        assert np.array_equal(np.concatenate([a.enc, b.enc]), e0 + k)          # past +2^31 - 1
        assert np.array_equal(np.concatenate([a.scale, b.scale]), -(2**31) + 50 - k)  # below -2^31
        assert un.lost == 0 and un.backsteps == 0


def test_sequence_gaps_are_reported_as_lost_samples_across_blocks():
    arr, _ = sp.FrameDecoder().feed_samples(_data_block(100, seq0=2**32 - 30))
    keep = np.ones(100, dtype=bool)
    keep[[5, 6, 7, 29, 30, 60]] = False          # 3 + 2 (across the wrap) + 1 lost
    arr = arr[keep]
    un = sp.StreamUnwrapper()
    a = un.update(arr[:26])                      # the block boundary falls inside the gap 29-30
    b = un.update(arr[26:])
    assert (a.lost, b.lost, un.lost) == (3, 3, 6)
    assert b.seq[-1] - a.seq[0] + 1 == len(arr) + 6


def test_a_repeated_sequence_number_is_a_backstep_not_a_sample():
    arr, _ = sp.FrameDecoder().feed_samples(_data_block(10))
    un = sp.StreamUnwrapper()
    un.update(arr[:6])
    r = un.update(arr[5:])                       # frame 5 again
    assert r.backsteps == 1 and un.backsteps == 1 and r.lost == 0


def test_status_text_names_flags():
    assert sp.status_text(sp.ST_FAULT | sp.ST_HEARTBEAT_LOST) == "fault|heartbeat-lost"
    assert sp.status_text(0) == "none"

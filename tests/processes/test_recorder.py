"""Recordings: round trip, crash safety (SIGKILL), CSV input and input errors."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from drivers.base import SampleBlock
from rt_ident.axis.params import thomson_x
from rt_ident.errors import ConfigError, DataError, RtIdentError
from rt_ident.processes.recorder import (
    Recorder,
    RecorderProcess,
    journal_path,
    part_path,
    read_recording,
)

DT = 1.0 / 40_000.0


def _signals(seq: np.ndarray) -> dict[str, np.ndarray]:
    """Deterministic values as a function of the sequence number (the oracle)."""
    s = seq.astype(np.float64)
    return {
        "t": s * DT,
        "seq": seq,
        "theta1": np.sin(1e-3 * s),
        "theta2": np.cos(1e-3 * s),
        "torque_cmd": 0.25 * s - 3.0,
    }


def _assert_matches_oracle(rec) -> None:
    n = len(rec)
    assert np.array_equal(rec.seq, np.arange(n))
    ref = _signals(np.arange(n, dtype=np.int64))
    for name in ("t", "theta1", "theta2", "torque_cmd"):
        assert np.array_equal(getattr(rec, name), ref[name]), name


def test_round_trip_keeps_values_metadata_and_one_row_group_per_flush(tmp_path: Path) -> None:
    path = tmp_path / "run.parquet"
    meta = {"axis": thomson_x(), "sample_period": DT, "backend": "sim", "method": "rls"}
    with Recorder(path, meta, flush_interval=0.5) as r:
        for k in range(3):
            seq = np.arange(100 * k, 100 * (k + 1), dtype=np.int64)
            sig = _signals(seq)
            r.append(sig["t"], seq, sig["theta1"], sig["theta2"], sig["torque_cmd"])
            assert r.flush()
        assert r.rows_written == 300
    assert path.is_file() and not journal_path(path).exists() and not part_path(path).exists()
    assert pq.ParquetFile(path).metadata.num_row_groups == 3
    rec = read_recording(path)
    assert rec.source == "parquet" and len(rec) == 300
    _assert_matches_oracle(rec)
    assert rec.torque_meas is None  # all NaN -> no measured torque
    assert np.array_equal(rec.torque, rec.torque_cmd)
    assert rec.metadata["backend"] == "sim" and rec.metadata["sample_period"] == DT
    assert rec.metadata["axis"]["I1"] == thomson_x().I1


def test_torque_is_measured_where_finite_else_commanded(tmp_path: Path) -> None:
    path = tmp_path / "m.parquet"
    seq = np.arange(20, dtype=np.int64)
    sig = _signals(seq)
    meas = 10.0 + seq.astype(float)
    meas[5] = np.nan
    with Recorder(path, {}) as r:
        r.append(sig["t"], seq, sig["theta1"], sig["theta2"], sig["torque_cmd"], meas)
    rec = read_recording(path)
    assert rec.torque_meas is not None and np.isnan(rec.torque_meas[5])
    assert rec.torque[5] == sig["torque_cmd"][5]
    assert np.array_equal(np.delete(rec.torque, 5), np.delete(meas, 5))


def test_flush_if_due_waits_for_the_interval(tmp_path: Path) -> None:
    r = Recorder(tmp_path / "f.parquet", {}, flush_interval=0.5)
    sig = _signals(np.arange(10, dtype=np.int64))
    r.append(sig["t"], sig["seq"], sig["theta1"], sig["theta2"], sig["torque_cmd"])
    assert not r.flush_if_due(100.0)  # first call starts the clock
    assert not r.flush_if_due(100.4)
    assert r.flush_if_due(100.5) and r.rows_written == 10
    r.close()
    r.close()  # idempotent
    assert len(read_recording(tmp_path / "f.parquet")) == 10


def test_existing_recording_is_not_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "x.parquet"
    path.write_bytes(b"precious")
    with pytest.raises(ConfigError, match="path"):
        Recorder(path, {}).open()
    assert path.read_bytes() == b"precious"


def test_append_with_mismatched_lengths_is_a_data_error(tmp_path: Path) -> None:
    r = Recorder(tmp_path / "e.parquet", {})
    with pytest.raises(DataError, match="theta2"):
        r.append(np.zeros(3), np.arange(3), np.zeros(3), np.zeros(2), np.zeros(3))


def test_torn_final_batch_is_dropped_whole(tmp_path: Path) -> None:
    """A kill in the middle of a journal write leaves a truncated batch: it must vanish entirely."""
    path = tmp_path / "torn.parquet"
    r = Recorder(path, {"method": "ls"})
    for k in range(3):
        sig = _signals(np.arange(50 * k, 50 * (k + 1), dtype=np.int64))
        r.append(sig["t"], sig["seq"], sig["theta1"], sig["theta2"], sig["torque_cmd"])
        r.flush()
    r._journal_file.close()  # simulate the crash: no close(), then tear the last batch
    jp = journal_path(path)
    jp.write_bytes(jp.read_bytes()[:-30])
    rec = read_recording(path)
    assert rec.source == "journal" and len(rec) == 100
    assert rec.metadata == {"method": "ls"}
    _assert_matches_oracle(rec)


def test_a_full_disk_fails_close_once_and_leaves_no_traceback_for_the_garbage_collector(tmp_path, monkeypatch):
    import errno
    import gc
    import sys

    class FullDisk(pq.ParquetWriter):                   # every write, and the footer at close, hit ENOSPC
        def write_table(self, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        def close(self):
            if self.is_open:
                raise OSError(errno.ENOSPC, "No space left on device")

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    monkeypatch.setattr(pq, "ParquetWriter", FullDisk)
    path = tmp_path / "full.parquet"
    r = Recorder(path, {"method": "ls"})
    sig = _signals(np.arange(50, dtype=np.int64))
    r.append(sig["t"], sig["seq"], sig["theta1"], sig["theta2"], sig["torque_cmd"])
    with pytest.raises(OSError) as e:
        r.close()
    assert e.value.errno == errno.ENOSPC
    r.close()                                           # a second close does nothing
    del r, e                                            # (the traceback holds the recorder too)
    gc.collect()
    assert unraisable == []
    assert len(read_recording(path)) == 50              # the journal kept the batch the Parquet write lost
    assert not part_path(path).exists()                 # its footerless copy no reader opens gave its space back


def _append(r: Recorder, seq: np.ndarray) -> None:
    sig = _signals(seq)
    r.append(sig["t"], seq, sig["theta1"], sig["theta2"], sig["torque_cmd"])


def test_a_batch_only_the_journal_took_before_the_disk_filled_is_counted_once_and_never_written_twice(
        tmp_path, monkeypatch):
    import errno

    class FullAfterOne(pq.ParquetWriter):               # the disk fills between the journal's copy and this one
        writes = 0

        def write_table(self, *a, **k):
            FullAfterOne.writes += 1
            if FullAfterOne.writes > 1:
                raise OSError(errno.ENOSPC, "No space left on device")
            super().write_table(*a, **k)

    monkeypatch.setattr(pq, "ParquetWriter", FullAfterOne)
    path = tmp_path / "full.parquet"
    r = Recorder(path, {"method": "ls"})
    _append(r, np.arange(50, dtype=np.int64))
    assert r.flush()
    _append(r, np.arange(50, 80, dtype=np.int64))
    with pytest.raises(OSError):
        r.flush()
    assert r.rows_written == 80 and not part_path(path).exists()
    r.close()                                           # writes nothing more: the journal is the recording
    rec = read_recording(path)
    assert rec.source == "journal"
    _assert_matches_oracle(rec)
    assert len(rec) == 80


def test_a_journal_write_cut_short_by_a_full_disk_is_the_journals_last_write(tmp_path, monkeypatch):
    import errno

    import rt_ident.processes.recorder as recorder_mod

    class CutOnce:                                      # writes half of one write, then ENOSPC; space frees after
        def __init__(self, f):
            self.f, self.armed = f, False

        def write(self, b):
            if self.armed:
                self.armed = False
                self.f.write(bytes(b)[: len(b) // 2])
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(b)

        def __getattr__(self, name):
            return getattr(self.f, name)

    journals: list[CutOnce] = []

    def journal_open(*a, **k):
        journals.append(CutOnce(open(*a, **k)))         # noqa: SIM115 - the recorder closes it
        return journals[-1]

    monkeypatch.setattr(recorder_mod, "open", journal_open, raising=False)
    path = tmp_path / "cut.parquet"
    r = Recorder(path, {"method": "ls"})
    _append(r, np.arange(50, dtype=np.int64))
    assert r.flush()
    journals[0].armed = True
    _append(r, np.arange(50, 80, dtype=np.int64))
    with pytest.raises(OSError):
        r.flush()
    assert r.rows_written == 50
    r.close()                                           # no retry after the cut batch: it would be read as its body
    rec = read_recording(path)
    _assert_matches_oracle(rec)
    assert len(rec) == 50 and not part_path(path).exists()


def test_recorder_process_close_writes_complete_parquet(tmp_path: Path) -> None:
    path = tmp_path / "p.parquet"
    with RecorderProcess(path, {"backend": "sim"}, flush_interval=0.1) as rp:
        for k in range(20):
            sig = _signals(np.arange(40 * k, 40 * (k + 1), dtype=np.int64))
            if k % 2:  # a backend's SampleBlock or a plain dict
                rp.put(SampleBlock(sig["t"], sig["seq"], sig["theta1"], sig["theta2"], sig["torque_cmd"]))
            else:
                rp.put(sig)
    assert rp.rows_written == 800
    rec = read_recording(path)
    assert rec.source == "parquet" and len(rec) == 800
    _assert_matches_oracle(rec)


def test_a_stalled_recorder_whose_ring_fills_refuses_the_block_at_once_and_counts_it_lost(tmp_path, monkeypatch):
    import rt_ident.processes.recorder as recorder_mod

    path = tmp_path / "stalled.parquet"
    rp = RecorderProcess(path, {"backend": "sim"}, ring_bytes=1 << 16).start()
    slept = []                                               # time.sleep in the put's wait for room
    real_sleep = recorder_mod.time.sleep
    monkeypatch.setattr(recorder_mod.time, "sleep", lambda s: (slept.append(s) if sys._getframe(1).f_code
                                                               is RecorderProcess._wait_for_room.__code__
                                                               else None) or real_sleep(s))
    os.kill(rp.pid, signal.SIGSTOP)                          # its disk hangs: it takes nothing more
    try:
        k = 0
        with pytest.raises(RtIdentError, match=r"fell a whole ring behind \(\d+ blocks, 0 MiB not yet written\): "
                                               r"its disk or its process stalled"):
            while k < 10_000:
                rp.put(_signals(np.arange(40 * k, 40 * (k + 1), dtype=np.int64)))
                k += 1
        assert slept == [] and rp.full_waits == 1            # the real-time caller was not held
    finally:
        os.kill(rp.pid, signal.SIGCONT)
    monkeypatch.undo()
    summary = rp.close()
    assert summary["samples_put"] == 40 * k and summary["samples_refused"] == 40
    assert summary["rows_written"] == 40 * k and not summary["complete"]   # the refused block is not in it
    assert "fell a whole ring behind" in summary["refusal"]


def test_sigkilled_recorder_process_is_readable_up_to_last_flush(tmp_path: Path) -> None:
    path = tmp_path / "crash.parquet"
    rp = RecorderProcess(path, {"backend": "sim"}, flush_interval=0.02).start()
    k, flushed = 0, 0
    deadline = time.monotonic() + 15.0
    while time.monotonic() < deadline:
        rp.put(_signals(np.arange(40 * k, 40 * (k + 1), dtype=np.int64)))
        k += 1
        time.sleep(0.0005)
        flushed = rp.rows_written
        if flushed >= 4000:
            break
    assert flushed >= 4000, "recorder never flushed"
    os.kill(rp.pid, signal.SIGKILL)  # mid-run: blocks are still being put and written
    rp._proc.join(5.0)
    time.sleep(0.15)  # put() looks at the child's exit status at most every 0.1 s
    with pytest.raises(RtIdentError, match="not running"):
        rp.put(_signals(np.arange(40 * k, 40 * (k + 1), dtype=np.int64)))
    summary = rp.close(timeout=2.0)
    assert summary["exitcode"] == -signal.SIGKILL
    assert not path.exists()  # never finalized
    rec = read_recording(path)
    assert rec.source == "journal"
    assert flushed <= len(rec) <= 40 * k
    assert np.all(np.diff(rec.seq) > 0)
    _assert_matches_oracle(rec)
    assert rec.metadata == {"backend": "sim"}


def test_a_recorder_whose_ring_was_given_to_another_ring_finishes_its_file_and_says_so_in_one_line(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "reused.parquet"
    rp = RecorderProcess(path, {"backend": "sim"}, flush_interval=0.02).start()
    rp.wait_ready()
    for k in range(3):
        rp.put(_signals(np.arange(40 * k, 40 * (k + 1), dtype=np.int64)))
    deadline = time.monotonic() + 15.0
    while rp.rows_written < 120 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rp.rows_written == 120
    ring = rp._ring
    assert ring is not None
    ring._h[3] = ring._h[3] ^ 0x5A5A               # another ring's token: the parent let go of this memory
    rp._proc.join(15.0)
    assert rp._proc.exitcode == 1
    assert "given to another ring" in (rp.failure or "")
    err = capfd.readouterr().err
    assert "given to another ring" in err and "Traceback" not in err, err
    rec = read_recording(path)
    assert rec.source != "journal" and len(rec) == 120
    _assert_matches_oracle(rec)
    ring._h[3] = ring._h[3] ^ 0x5A5A               # this side's own token again, so close() can finish
    assert rp.close(timeout=2.0)["exitcode"] == 1


# ---------------------------------------------------------------- CSV and input errors


def _write_csv(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    lines = [",".join(header)] + [",".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _csv_rows(n: int, with_omega: bool) -> tuple[list[str], list[list[float]]]:
    header = ["t", "theta1", "theta2", "torque"] + (["omega1", "omega2"] if with_omega else [])
    rows = [[i * 1e-3, 0.1 * i, 0.05 * i, -0.5 * i] + ([1.0 * i, 2.0 * i] if with_omega else []) for i in range(n)]
    return header, rows


@pytest.mark.parametrize("with_omega", [False, True])
def test_csv_is_read_with_and_without_omega(tmp_path: Path, with_omega: bool) -> None:
    header, rows = _csv_rows(20, with_omega)
    rec = read_recording(_write_csv(tmp_path / "a.csv", header, rows))
    assert rec.source == "csv" and len(rec) == 20 and rec.metadata == {}
    assert rec.theta2[4] == pytest.approx(0.2) and rec.torque[3] == pytest.approx(-1.5)
    assert np.array_equal(rec.torque_cmd, rec.torque) and rec.torque_meas is None and rec.seq is None
    if with_omega:
        assert rec.omega2 is not None and rec.omega2[7] == pytest.approx(14.0)
    else:
        assert rec.omega1 is None and rec.omega2 is None


def test_csv_column_order_is_free_and_extra_columns_ignored(tmp_path: Path) -> None:
    header, rows = _csv_rows(15, True)
    order = [5, 3, 0, 2, 1, 4]  # omega2, torque, t, theta2, theta1, omega1
    h = [header[i] for i in order] + ["note"]
    r = [[row[i] for i in order] + ["x"] for row in rows]
    rec = read_recording(_write_csv(tmp_path / "b.csv", h, r))
    assert np.allclose(rec.t, np.arange(15) * 1e-3)
    assert np.allclose(rec.theta1, 0.1 * np.arange(15))
    assert np.allclose(rec.omega1, np.arange(15.0)) and np.allclose(rec.omega2, 2.0 * np.arange(15))


def test_a_recording_exported_to_csv_reads_as_the_recording_with_its_measured_torque_where_finite(tmp_path):
    import pyarrow.csv as pc

    path = tmp_path / "run.parquet"
    seq = np.arange(40, dtype=np.int64)
    sig = _signals(seq)
    meas = 0.9 * sig["torque_cmd"]
    meas[5] = np.nan                                    # a sample the device did not report
    with Recorder(path, {"method": "ls"}) as r:
        r.append(sig["t"], seq, sig["theta1"], sig["theta2"], sig["torque_cmd"], meas)
    pc.write_csv(pq.read_table(path), tmp_path / "run.csv")   # as a user exports one: every column, quoted names
    rec, csv_rec = read_recording(path), read_recording(tmp_path / "run.csv")
    assert csv_rec.source == "csv" and len(csv_rec) == 40
    for name in ("t", "theta1", "theta2", "torque", "torque_cmd"):
        assert np.array_equal(getattr(csv_rec, name), getattr(rec, name)), name
    assert csv_rec.torque[5] == sig["torque_cmd"][5] and csv_rec.torque[6] == meas[6]


def test_a_csv_without_a_torque_column_names_the_recordings_columns_that_would_do(tmp_path: Path) -> None:
    header, rows = _csv_rows(20, False)
    p = _write_csv(tmp_path / "g.csv", header[:3] + ["tau"], rows)
    told = r"missing column\(s\) torque .*a recording's torque_cmd and torque_meas also do"
    with pytest.raises(DataError, match=told):
        read_recording(p)


def test_missing_file_is_a_data_error(tmp_path: Path) -> None:
    for name in ("nope.csv", "nope.parquet", "nope.parquet.arrows"):
        with pytest.raises(DataError, match="no such file"):
            read_recording(tmp_path / name)


def test_a_folder_is_named_as_a_folder_whatever_its_name_ends_in(tmp_path: Path) -> None:
    for name in ("runs", "old.parquet", "x.csv"):
        (tmp_path / name).mkdir()
        with pytest.raises(DataError, match=r": a folder, not a recording \(one \.parquet, \.arrows or \.csv file\)$"):
            read_recording(tmp_path / name)


def test_unknown_extension_is_a_data_error(tmp_path: Path) -> None:
    p = tmp_path / "data.xlsx"
    p.write_text("t\n")
    with pytest.raises(DataError, match="unknown extension"):
        read_recording(p)


def test_missing_columns_are_named(tmp_path: Path) -> None:
    header, rows = _csv_rows(20, False)
    keep = [0, 1]  # t, theta1 only
    p = _write_csv(tmp_path / "c.csv", [header[i] for i in keep], [[r[i] for i in keep] for r in rows])
    with pytest.raises(DataError, match="missing column.*theta2, torque"):
        read_recording(p)


def test_non_numeric_value_names_the_row(tmp_path: Path) -> None:
    header, rows = _csv_rows(20, False)
    rows[6][2] = "abc"
    with pytest.raises(DataError, match=r"non-numeric 'theta2' value 'abc' at data row 7"):
        read_recording(_write_csv(tmp_path / "d.csv", header, rows))


def test_non_monotonic_time_names_the_row(tmp_path: Path) -> None:
    header, rows = _csv_rows(20, False)
    rows[9][0] = rows[8][0]
    told = rf"not strictly increasing at data row 10 \(t={rows[9][0]} after {rows[8][0]}\)$"   # numbers, not np reprs
    with pytest.raises(DataError, match=told):
        read_recording(_write_csv(tmp_path / "e.csv", header, rows))


def test_too_few_rows_is_a_data_error(tmp_path: Path) -> None:
    header, rows = _csv_rows(5, False)
    with pytest.raises(DataError, match="only 5 data rows"):
        read_recording(_write_csv(tmp_path / "f.csv", header, rows))


def test_non_finite_value_is_a_data_error(tmp_path: Path) -> None:
    header, rows = _csv_rows(20, False)
    rows[2][3] = "nan"
    with pytest.raises(DataError, match="'torque' has a non-finite value nan at data row 3"):
        read_recording(_write_csv(tmp_path / "g.csv", header, rows))



def test_recorder_process_rejects_a_malformed_block_in_the_caller(tmp_path: Path) -> None:
    rp = RecorderProcess(tmp_path / "bad.parquet", {})  # validation comes before any queueing
    with pytest.raises(DataError, match="'theta1' has shape"):
        rp.put({**_signals(np.arange(5, dtype=np.int64)), "theta1": np.zeros(4)})
    with pytest.raises(DataError, match="no 'torque_cmd'"):
        rp.put({"t": np.zeros(3), "seq": np.arange(3), "theta1": np.zeros(3), "theta2": np.zeros(3)})
    with pytest.raises(RtIdentError, match="not started"):
        rp.put(_signals(np.arange(5, dtype=np.int64)))


def test_a_finished_recording_streams_in_bounded_blocks_equal_to_the_whole_read(tmp_path):
    from rt_ident.outputs.recording_reader import iter_parquet_blocks

    path = tmp_path / "s.parquet"
    rng = np.random.default_rng(0)
    with Recorder(path, {"sample_period": 1e-4}, flush_interval=1.0) as rec:
        for k in range(7):                                   # seven row groups of 3000
            seq = np.arange(k * 3000, (k + 1) * 3000)
            rec.append(seq * 1e-4, seq, rng.normal(size=3000), rng.normal(size=3000), rng.normal(size=3000),
                       rng.normal(size=3000))
            rec.flush()
    blocks = list(iter_parquet_blocks(path, rows=1000))
    assert max(len(b[0]) for b in blocks) <= 1000 and len(blocks) == 21
    whole = read_recording(path)
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), whole.theta1)
    np.testing.assert_array_equal(np.concatenate([b[2] for b in blocks]), whole.torque)
    np.testing.assert_array_equal(np.concatenate([b[3] for b in blocks]), whole.seq)


def test_streamed_blocks_still_refuse_time_going_backwards_across_a_block_edge(tmp_path):
    from rt_ident.outputs.recording_reader import iter_parquet_blocks

    path = tmp_path / "b.parquet"
    with Recorder(path, {}, flush_interval=1.0) as rec:
        rec.append(np.arange(100) * 1e-3, np.arange(100), np.zeros(100), np.zeros(100), np.zeros(100))
        rec.flush()
        rec.append(np.arange(100) * 1e-3, np.arange(100, 200), np.zeros(100), np.zeros(100), np.zeros(100))
    with pytest.raises(DataError, match="not strictly increasing at data row 101"):
        list(iter_parquet_blocks(path, rows=64))

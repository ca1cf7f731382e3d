"""Host-wide locks (rt_ident.hostlock): one holder at a time across processes, gone with their holder, and no
lock file left behind by a release."""

from __future__ import annotations

import os
import subprocess
import sys

from rt_ident.hostlock import NamedLock

_HOLD = ("import sys; from rt_ident.hostlock import NamedLock; "
         "lock = NamedLock('t', sys.argv[1], sys.argv[2]); print(lock.try_acquire(), flush=True); sys.stdin.read()")


def _holder(key: str, directory) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, key, str(directory)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "True"
    return proc


def test_a_lock_held_by_another_process_is_refused_and_names_that_process(tmp_path):
    proc = _holder("/data/a.parquet", tmp_path)
    try:
        lock = NamedLock("t", "/data/a.parquet", tmp_path)
        assert not lock.try_acquire() and not lock.held
        assert lock.who().startswith(f"pid {proc.pid} (")
        assert NamedLock("t", "/data/b.parquet", tmp_path).try_acquire()     # another key is another lock
    finally:
        proc.kill()
        proc.wait(30)


def test_a_lock_whose_holder_was_killed_is_free_at_once(tmp_path):
    proc = _holder("k", tmp_path)
    proc.kill()
    proc.wait(30)
    assert NamedLock("t", "k", tmp_path).try_acquire()


def test_a_released_lock_leaves_no_file_and_can_be_taken_again(tmp_path):
    lock = NamedLock("t", "k", tmp_path)
    assert lock.try_acquire() and lock.path.exists()
    assert lock.try_acquire()                                   # idempotent
    lock.release()
    lock.release()
    assert not lock.path.exists() and os.listdir(tmp_path) == []
    assert NamedLock("t", "k", tmp_path).try_acquire()


def test_a_file_opened_before_its_release_and_deletion_does_not_count_as_the_lock(tmp_path, monkeypatch):
    import rt_ident.hostlock as hostlock

    first = NamedLock("t", "k", tmp_path)
    assert first.try_acquire()
    stale = os.open(first.path, os.O_RDWR)                      # a second run opens the file the first one holds
    first.release()                                             # the first ends: its file deleted, unlocked
    third = NamedLock("t", "k", tmp_path)
    assert third.try_acquire()                                  # a third run takes the lock on a new file
    fds = iter([stale])
    real_open = hostlock.open_lock_file
    monkeypatch.setattr(hostlock, "open_lock_file", lambda path: next(fds, None) or real_open(path))
    second = NamedLock("t", "k", tmp_path)
    assert not second.try_acquire()                             # its flock on the deleted file is no lock
    third.release()


def test_a_release_deletes_the_files_of_killed_holders_and_leaves_a_live_ones(tmp_path):
    proc = _holder("live", tmp_path)                           # another process, holding its lock
    killed = _holder("killed", tmp_path)
    killed.kill()                                               # its file stays behind, unlocked
    killed.wait(30)
    try:
        mine = NamedLock("t", "mine", tmp_path)
        assert mine.try_acquire() and len(list(tmp_path.iterdir())) == 3
        mine.release()
        assert [p.name for p in tmp_path.iterdir()] == [NamedLock("t", "live", tmp_path).path.name]
        assert not NamedLock("t", "live", tmp_path).try_acquire()          # still held, by the live process
    finally:
        proc.kill()
        proc.wait(30)

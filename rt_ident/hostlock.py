"""Host-wide locks on things one process at a time may use: an output file, a device, a CPU.

A lock is an ``flock`` on a small file in /run/lock (one for every user and every TMPDIR), else the
temporary directory. The kernel drops it when its process ends, however it ends, so a crashed run
never leaves a lock that blocks the next one. :func:`holder` names the process that holds one, from
/proc/locks, for the error that says who is in the way.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import tempfile
from pathlib import Path

#: The host's lock directory, when writable.
LOCK_DIR = Path("/run/lock")


def lock_dir(directory: str | os.PathLike[str] | None = None) -> Path:
    """``directory``, else /run/lock, else the temporary directory."""
    if directory is not None:
        return Path(directory)
    return LOCK_DIR if LOCK_DIR.is_dir() and os.access(LOCK_DIR, os.W_OK) else Path(tempfile.gettempdir())


def holder(path: str | os.PathLike[str]) -> str | None:
    """Who holds an ``flock`` on ``path`` (``pid N (command line)``), from /proc/locks; None when unknown."""
    try:
        inode = os.stat(path).st_ino
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        parts = line.split()
        if len(parts) >= 6 and parts[1] == "FLOCK" and parts[5].rsplit(":", 1)[-1] == str(inode):
            pid = parts[4]
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                cmd = ""
            cmd = " ".join(cmd.split())[:80]
            return f"pid {pid}" + (f" ({cmd})" if cmd else "")
    return None


def open_lock_file(path: Path) -> int:
    """A descriptor of ``path`` to lock (created if missing; read-only when it is another user's)."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except PermissionError:
        return os.open(path, os.O_RDONLY | os.O_CLOEXEC)


def try_flock(path: Path) -> int | None:
    """A descriptor of ``path`` holding its exclusive ``flock``, or None when another one holds it (no wait)."""
    fd = open_lock_file(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


class NamedLock:
    """An exclusive host-wide lock named by ``key`` (any string: a resolved path, a bus and node).

    :meth:`try_acquire` never waits. :meth:`release` deletes the lock file while still holding it, so
    the lock directory does not fill with one file per run; a process that opened the old file in
    between finds it gone after its ``flock`` and tries again on the new one.
    """

    def __init__(self, kind: str, key: str, directory: str | os.PathLike[str] | None = None) -> None:
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        self.key = key
        self.kind = kind
        self.path = lock_dir(directory) / f"rt-ident-{kind}-{digest}.lock"
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def try_acquire(self) -> bool:
        """Hold the lock (True), or False when another descriptor holds it. Idempotent."""
        if self._fd is not None:
            return True
        for _ in range(100):
            fd = try_flock(self.path)
            if fd is None:
                return False
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                return True
            os.close(fd)                          # released and deleted by its holder meanwhile: again
        return False

    def who(self) -> str:
        return holder(self.path) or "another process"

    def release(self) -> None:
        """Drop the lock (idempotent), and delete the files of its kind that nobody holds (left by a process
        that was killed)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(fd)
        for left in self.path.parent.glob(f"rt-ident-{self.kind}-*.lock"):
            try:
                stale = try_flock(left)
            except OSError:
                continue
            if stale is None:
                continue
            try:
                if os.fstat(stale).st_ino == os.stat(left).st_ino:
                    left.unlink()
            except OSError:
                pass
            finally:
                os.close(stale)


__all__ = ["LOCK_DIR", "NamedLock", "holder", "lock_dir", "open_lock_file", "try_flock"]

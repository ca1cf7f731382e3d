"""How a run's helper processes (recorder, telemetry, fit and control workers) live and die.

* **Signals go to the main process only.** Ctrl-C in a terminal sends SIGINT to the whole process
  group, systemd's stop sends SIGTERM to the whole group. A helper that took them would die in the
  middle of its work (the recorder with samples still in its ring) or print a KeyboardInterrupt
  traceback. So helpers are started with SIGINT and SIGTERM *ignored* (:func:`start_ignoring_signals`:
  the disposition is inherited through the spawn's exec, and Python keeps an inherited SIG_IGN, so
  there is no window during the child's start-up), and set them ignored again first thing
  (:func:`become_helper`). The main process stops them in order: loop, then recorder (drains every
  sample, closes the file), telemetry, workers.
* **A helper notices its parent's death** (kill -9 of the main process) within ~0.2 s
  (:class:`ParentWatch`: the parent pid changes when the helper is re-parented) and then finishes
  what it holds (the recorder writes the Parquet file from every sample it received) and exits:
  no orphan keeps files open.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

_GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def start_ignoring_signals(proc: Any) -> None:
    """``proc.start()`` with SIGINT/SIGTERM ignored, so the child is born ignoring them."""
    if threading.current_thread() is not threading.main_thread():
        proc.start()                  # cannot touch dispositions here; become_helper() covers the child
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in _GROUP_SIGNALS}
    try:
        proc.start()
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def become_helper() -> "ParentWatch":
    """First call in a helper's main: ignore the group's SIGINT/SIGTERM; returns the parent watch."""
    for s in _GROUP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    return ParentWatch()


class ParentWatch:
    """``gone`` becomes True once the process that started this helper has died."""

    def __init__(self, every_s: float = 0.2) -> None:
        self.ppid = os.getppid()
        self.every_s = every_s
        self._next = 0.0
        self._gone = False

    @property
    def gone(self) -> bool:
        if self._gone:
            return True
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.every_s
            self._gone = os.getppid() != self.ppid
        return self._gone

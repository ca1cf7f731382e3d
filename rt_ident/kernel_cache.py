"""numba's on-disk cache of this distribution's kernels, kept in step with its sources.

numba keys a cached function on the modification time and size of its own file only, while a compiled
caller holds its callees from other modules compiled in: after an edit or a ``git pull`` that changes a
callee's module but not the caller's (the law, not the tick kernel that runs it), numba loads the caller
as compiled against the old callee, and the compiled tick runs code that is no longer in the tree.

So, once per process, :func:`sync` compares the modification times and sizes of every module of
``rt_ident`` and ``drivers`` with the record left when the cache was last in step; on any difference it
removes the compiled entries of both packages (numba compiles them again where they are next used) and
writes the new record. The entries are those beside the sources and, with ``NUMBA_CACHE_DIR`` set, their
mirror there (numba's layout: ``<folder name>_<sha1 of the folder's path>``). Where the package folders
are read-only numba keeps its cache in the user's cache folder instead; an install there rewrites every
file, so every entry goes stale at once, as numba sees.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

#: the record of the sources the cache was last in step with, beside rt_ident's own entries
RECORD = "kernel-sources.txt"
_ENTRY_SUFFIXES = (".nbi", ".nbc")
_done = False


def package_roots() -> list[Path]:
    """rt_ident's folder and, when installed beside it (one distribution), drivers'."""
    here = Path(__file__).resolve().parent
    roots = [here]
    drivers = here.parent / "drivers"
    if (drivers / "__init__.py").is_file():
        roots.append(drivers)
    return roots


def _folders(roots: list[Path]) -> Iterator[tuple[Path, list[str]]]:
    """Every package folder under ``roots`` (``__pycache__`` left out) with its file names, in a fixed order."""
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            yield Path(dirpath), sorted(filenames)


def _sources(roots: list[Path]) -> Iterator[Path]:
    for folder, names in _folders(roots):
        yield from (folder / name for name in names if name.endswith(".py"))


def fingerprint(roots: list[Path]) -> str:
    """One line per module: its path under the distribution, modification time [ns] and size."""
    base = roots[0].parent
    lines = []
    for f in _sources(roots):
        st = f.stat()
        lines.append(f"{f.relative_to(base)} {st.st_mtime_ns} {st.st_size}")
    return "\n".join(lines) + "\n"


def mirror_of(folder: Path, cache_dir: str) -> Path:
    """Where numba keeps the entries of ``folder``'s modules under ``NUMBA_CACHE_DIR`` = ``cache_dir``."""
    return Path(cache_dir, f"{folder.name}_{hashlib.sha1(os.path.abspath(folder).encode()).hexdigest()}")


def cache_dirs(roots: list[Path]) -> list[Path]:
    """Every folder numba may keep an entry of these packages in (existing or not)."""
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    out = []
    for folder, _ in _folders(roots):
        out.append(folder / "__pycache__")
        if cache_dir:
            out.append(mirror_of(folder, cache_dir))
    return out


def sync(roots: list[Path] | None = None) -> bool:
    """Remove the compiled entries when the sources changed since the record (True: removed). Once per
    process for the installed packages; nothing is done where the record cannot be written."""
    global _done
    if roots is None:
        if _done:
            return False
        _done = True
        roots = package_roots()
    record = roots[0] / "__pycache__" / RECORD
    try:
        now = fingerprint(roots)
        if record.is_file() and record.read_text() == now:
            return False
        record.parent.mkdir(exist_ok=True)
        for folder in cache_dirs(roots):
            if folder.is_dir():
                for entry in folder.iterdir():
                    if entry.suffix in _ENTRY_SUFFIXES:
                        entry.unlink(missing_ok=True)
        tmp = record.with_name(f"{RECORD}.{os.getpid()}")
        tmp.write_text(now)
        os.replace(tmp, record)
    except OSError:
        return False
    return True


def cache_variant(fn: Callable[..., Any], tag: str) -> Callable[..., Any]:
    """``fn`` (a closure made per shape) named for its variant before ``numba.njit(cache=True)``: numba names a
    compiled function's symbol from its qualified name, argument types and a counter that starts afresh in each
    process, so two variants of one closure with the same argument types, compiled first in two processes and
    both loaded from the cache into a third, define one symbol, and a caller can run the other variant's code
    (on arrays sized for its own). The name also gives each variant its own index file in the cache."""
    fn.__qualname__ = f"{fn.__qualname__}_{tag}"
    return fn


def tick_kernel_cached() -> bool:
    """Whether numba will find the tick kernel in its cache (False: the next run compiles it first, which takes
    seconds of CPU). Where numba keeps it elsewhere (read-only package folders), True: it cannot be told here."""
    loop = package_roots()[0] / "loop"
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        where = mirror_of(loop, cache_dir)            # numba then looks only there
    else:
        where = loop / "__pycache__"
        if not os.access(loop, os.W_OK):
            return True
    return where.is_dir() and any(where.glob("tick_kernel.axis_tick-*.nbi"))

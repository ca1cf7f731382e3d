"""rt_ident.kernel_cache: a compiled caller is not loaded from numba's cache as built against a callee whose
module has changed since."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from rt_ident import kernel_cache

CALLEE = """import numba

@numba.njit(cache=True)
def f(x):
    return x + {add}
"""
CALLER = """import numba
from pk.a import f

@numba.njit(cache=True)
def g(x):
    return f(x) * 2.0
"""


def _package(tmp_path: Path, add: float) -> Path:
    pk = tmp_path / "pk"
    pk.mkdir(exist_ok=True)
    (pk / "__init__.py").write_text("")
    (pk / "a.py").write_text(CALLEE.format(add=add))
    (pk / "b.py").write_text(CALLER)
    return pk


def _g(tmp_path: Path, sync: bool, env: dict[str, str] | None = None) -> float:
    """g(1.0) in a fresh process (its dispatchers load from the cache), after kernel_cache.sync or not."""
    code = ("import sys; from pathlib import Path; from rt_ident import kernel_cache; "
            + ("kernel_cache.sync([Path(sys.argv[1])]); " if sync else "")
            + "from pk.b import g; print(g(1.0))")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "pk")], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(tmp_path), **(env or {})})
    assert r.returncode == 0, r.stderr[-2000:]
    return float(r.stdout.split()[-1])


def _edit_callee(pk: Path, add: float) -> None:
    st = (pk / "a.py").stat()
    (pk / "a.py").write_text(CALLEE.format(add=add))
    os.utime(pk / "a.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))   # a later edit, whatever the clock's grain


def test_numba_alone_loads_a_caller_compiled_against_the_old_callee(tmp_path):
    """What sync guards against: without it, g still returns f's old value after f's module changed."""
    pk = _package(tmp_path, 1.0)
    assert _g(tmp_path, sync=False) == 4.0
    _edit_callee(pk, 100.0)
    assert _g(tmp_path, sync=False) == 4.0


def test_after_a_callees_module_changes_sync_makes_the_caller_compile_again(tmp_path):
    pk = _package(tmp_path, 1.0)
    assert _g(tmp_path, sync=True) == 4.0
    assert list((pk / "__pycache__").glob("b.g-*.nbi"))
    _edit_callee(pk, 100.0)
    assert _g(tmp_path, sync=True) == 202.0


def test_sync_keeps_the_entries_while_the_sources_are_unchanged_and_clears_the_numba_cache_dir_mirror(tmp_path,
                                                                                                    monkeypatch):
    mirror = tmp_path / "nbcache"
    pk = _package(tmp_path, 1.0)
    env = {"NUMBA_CACHE_DIR": str(mirror)}
    assert _g(tmp_path, sync=True, env=env) == 4.0
    entries = sorted(mirror.rglob("*.nbi"))
    assert entries and {e.parent for e in entries} == {kernel_cache.mirror_of(pk, str(mirror))}
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(mirror))
    assert kernel_cache.sync([pk]) is False and sorted(mirror.rglob("*.nbi")) == entries
    _edit_callee(pk, 100.0)
    assert kernel_cache.sync([pk]) is True and not list(mirror.rglob("*.nb[ic]"))
    assert kernel_cache.sync([pk]) is False
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert _g(tmp_path, sync=True, env=env) == 202.0


def test_the_installed_packages_record_lists_every_module_of_rt_ident_and_drivers():
    roots = kernel_cache.package_roots()
    assert [r.name for r in roots] == ["rt_ident", "drivers"]
    listed = {line.split()[0] for line in kernel_cache.fingerprint(roots).splitlines()}
    assert "rt_ident/control/law.py" in listed and "rt_ident/loop/tick_kernel.py" in listed
    assert "drivers/sim_plan.py" in listed and not any("__pycache__" in p for p in listed)


def test_the_tick_kernel_counts_as_cached_only_where_numba_will_look_for_it(tmp_path, monkeypatch):
    from rt_ident.loop.tick_kernel import compiled_kernel

    compiled_kernel()                                   # in the cache beside the package from here on
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert kernel_cache.tick_kernel_cached()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "empty"))   # numba then looks only there
    assert not kernel_cache.tick_kernel_cached()
    loop = kernel_cache.package_roots()[0] / "loop"
    mirror = kernel_cache.mirror_of(loop, str(tmp_path / "empty"))
    mirror.mkdir(parents=True)
    (mirror / "tick_kernel.axis_tick-228.py311.nbi").write_bytes(b"")
    assert kernel_cache.tick_kernel_cached()

"""The loop's late-compile watch (rt_ident.loop.compile_watch): what it reports, and what it leaves out."""

from __future__ import annotations

import sys
import types

import numba
import pytest

from rt_ident.loop.compile_watch import CompileWatch


def _module(name: str) -> types.ModuleType:
    mod = types.ModuleType(name)

    @numba.njit(cache=False)
    def double(x):
        return 2 * x

    mod.double = double
    return mod


@pytest.fixture
def scratch_modules():
    names: list[str] = []

    def add(name: str) -> types.ModuleType:
        mod = _module(name)
        sys.modules[name] = mod
        names.append(name)
        return mod

    yield add
    for name in names:
        sys.modules.pop(name, None)


def test_a_signature_compiled_between_start_and_stop_is_reported_late(scratch_modules):
    mod = scratch_modules("rt_ident._watch_known")
    mod.double(1.0)                                   # compiled before the watch: not late
    watch = CompileWatch()
    watch.start()
    mod.double(3)                                     # a new argument type while it runs: late
    watch.stop()
    mod.double(1j)                                    # after stop: the final work's, not the loop's
    assert watch.late == ["rt_ident._watch_known.double('int64',)"]
    assert watch.as_dict() == {"count": 1, "functions": ["rt_ident._watch_known.double('int64',)"]}


def test_a_module_imported_while_the_loop_ran_has_its_compiles_reported(scratch_modules):
    watch = CompileWatch()
    watch.start()
    mod = scratch_modules("drivers._watch_new")
    mod.double(2.0)
    watch.stop()
    assert watch.late == ["drivers._watch_new.double('float64',)"]


def test_nothing_compiled_while_the_loop_ran_reports_nothing(scratch_modules):
    mod = scratch_modules("rt_ident._watch_quiet")
    mod.double(1.0)
    watch = CompileWatch()
    watch.start()
    mod.double(2.0)                                   # a signature it has: no compile
    watch.stop()
    assert watch.as_dict() == {"count": 0, "functions": []}

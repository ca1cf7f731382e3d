"""The folder layout's import directions (docs/development.md "Layout"), checked by import-linter's contracts in
pyproject.toml."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_import_contracts_hold_downward_only_and_no_circles():
    # in a child process: import-linter configures logging with dictConfig, which disables every
    # logger that exists at that moment (ours included) for the rest of the test session
    code = ("import sys; from importlinter.cli import lint_imports; "
            f"sys.exit(lint_imports(config_filename={str(ROOT / 'pyproject.toml')!r}, no_cache=True))")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, f"an import breaks the layout's contracts:\n{p.stdout[-4000:]}{p.stderr[-2000:]}"


def test_every_rt_ident_folder_has_a_layer_in_the_contract():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layered = {m.strip() for c in cfg["contracts"] if c["type"] == "layers"
               for layer in c["layers"] for m in layer.split("|")}
    folders = {f"rt_ident.{p.name}" for p in (ROOT / "rt_ident").iterdir()
               if p.is_dir() and (p / "__init__.py").is_file()}
    assert folders, "no sub-packages found under rt_ident/"
    missing = sorted(folders - layered)
    assert not missing, f"folders with no place in the layers contract: {missing}"


def test_no_module_left_at_the_top_of_rt_ident_but_the_face():
    top = sorted(p.name for p in (ROOT / "rt_ident").glob("*.py"))
    # and kernel_cache, which the package's import runs before any compiled kernel loads, and hostlock, the
    # host-wide locks the devices, the loop and the outputs take (below all of them)
    assert top == ["__init__.py", "__main__.py", "cli.py", "config.py", "errors.py", "hostlock.py",
                   "kernel_cache.py"], top


def test_drivers_top_holds_only_the_contract_sim_and_shared_emulator_placement():
    top = sorted(p.name for p in (ROOT / "drivers").glob("*.py"))
    assert top == ["__init__.py", "base.py", "errors.py", "placement.py", "sim.py", "sim_plan.py"], top


def test_no_module_imports_another_modules_private_names():
    import ast

    offenders = []
    for path in sorted([*(ROOT / "rt_ident").rglob("*.py"), *(ROOT / "drivers").rglob("*.py")]):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in ("rt_ident", "drivers"):
                for alias in node.names:
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        offenders.append(f"{path.relative_to(ROOT)}: from {node.module} import {alias.name}")
    assert not offenders, "private names imported across modules:\n" + "\n".join(offenders)


def test_tests_live_in_a_folder_per_package():
    packages = {p.name for p in (ROOT / "rt_ident").iterdir() if (p / "__init__.py").is_file()} | {"drivers", "tools"}
    folders = {p.name for p in (ROOT / "tests").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders <= packages, sorted(folders - packages)
    top = sorted(p.stem for p in (ROOT / "tests").glob("test_*.py"))
    # at the top: what tests the project as a whole or its top-level modules (cli, config, errors, hostlock,
    # kernel_cache, the layout, the README)
    assert all(name.split("_")[1] in ("cli", "config", "errors", "hostlock", "kernel", "layout", "readme")
               for name in top), top


def test_the_code_tells_what_and_why_not_its_history():
    # run statistics, CI anecdotes and issue numbers belong in git log and docs/measurements.md
    pattern = re.compile(r"CI run|of [0-9]+ runs|this VM|issue #?[0-9]+", re.IGNORECASE)
    sources = [*(ROOT / "rt_ident").rglob("*.py"), *(ROOT / "drivers").rglob("*.py")]
    found = [f"{p.relative_to(ROOT)}:{i}" for p in sources
             for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert not found, found


@pytest.mark.xdist_group("realtime")
def test_the_realtime_mark_puts_its_tests_in_one_xdist_group(request, worker_id):
    """xdist's loadgroup sends the tests marked ``xdist_group("realtime")`` to one worker by a suffix on their
    node ids. A pytest that drops the suffix spreads them over every worker, where their runs queue for the
    loop's CPU claim, and nothing else fails."""
    if worker_id == "master":
        pytest.skip("only under xdist workers (-n)")
    assert request.node.nodeid.endswith("@realtime"), (
        f"{request.node.nodeid}: xdist did not group this test; keep the test extra's pytest to one that keeps it")

"""The README's quick start: exactly two commands, each self-contained in a virtual environment
(PEP 668 systems refuse a bare `pip install`), and CI runs the second one as written."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _quick_start() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", section, flags=re.S)]


def test_quick_start_is_two_commands_that_make_their_own_venv():
    cmds = _quick_start()
    assert len(cmds) == 2 and all("\n" not in c for c in cmds), cmds
    run, tests = cmds
    for c in cmds:
        assert c.startswith("python3 -m venv .venv && .venv/bin/pip install -e ")
    assert run.endswith(".venv/bin/rt-ident run") and tests.endswith(".venv/bin/python -m pytest -q -n auto")


def test_ci_runs_the_readme_test_command_as_written():
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1].strip() == _quick_start()[1]


def test_every_relative_link_in_the_readme_resolves_to_a_file():
    text = (ROOT / "README.md").read_text()
    links = [m for m in re.findall(r"\]\(([^)\s]+)\)", text) if "://" not in m and not m.startswith(("#", "mailto:"))]
    assert links, "the README links its docs pages"
    missing = [m for m in links if not (ROOT / m.split("#", 1)[0]).exists()]
    assert not missing, missing


def test_the_readme_stays_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 200

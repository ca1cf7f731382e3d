"""File names made from machine and axis names stay inside the output folder and never collide."""

from __future__ import annotations

import os

import pytest

from rt_ident.errors import ConfigError
from rt_ident.fleet.paths import output_path, safe_name


def test_plain_machine_and_axis_names_are_kept_as_written():
    assert safe_name("m01", "x") == "m01-x"
    assert safe_name("lathe_3.b", "z2") == "lathe_3.b-z2"


@pytest.mark.parametrize("machine", ["../../../../tmp/escaped", "/etc/cron.d/job", "..", ".hidden", "a\nb", "é",
                                     "x" * 300, ""])
def test_a_hostile_machine_name_gives_a_file_directly_inside_the_output_folder(tmp_path, machine):
    p = output_path(tmp_path / "out", machine, "x", suffix=".png")
    assert p.parent == (tmp_path / "out").resolve()
    assert "/" not in p.name and not p.name.startswith(".") and "\n" not in p.name
    assert len(p.name) < 120


def test_the_traversal_name_of_the_issue_writes_inside_out_not_to_tmp(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    p = output_path(out, "../../../../tmp/escaped", "x", suffix=".png")
    p.write_bytes(b"png")
    assert list(out.iterdir()) == [p]
    assert p.name.startswith("_.._.._.._tmp_escaped-x-") and p.suffix == ".png"


def test_different_name_tuples_never_share_a_file_name():
    names = [("a-b", "c"), ("a", "b-c"), ("a/b", "c"), ("a_b", "c"), ("a b", "c"), ("A", "c"), ("a", "c")]
    made = [safe_name(*n) for n in names]
    assert len(set(made)) == len(names), made


def test_a_link_out_of_the_output_folder_is_refused_not_written_through(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    target = tmp_path / "elsewhere.png"
    os.symlink(target, out / "m01-x.png")
    with pytest.raises(ConfigError, match="--out: .*m01-x.png leads out of"):
        output_path(out, "m01", "x", suffix=".png")
    assert not target.exists()


def test_a_suffix_that_is_not_an_extension_is_a_programming_error(tmp_path):
    with pytest.raises(ValueError, match="not a file extension"):
        output_path(tmp_path, "m01", suffix="/../x.png")

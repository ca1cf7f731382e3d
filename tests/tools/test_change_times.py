import argparse
import importlib.util
from pathlib import Path

import pytest

spec = importlib.util.spec_from_file_location("change_times", Path(__file__).parents[2] / "tools" / "change_times.py")
change_times = importlib.util.module_from_spec(spec)
spec.loader.exec_module(change_times)


def test_each_change_time_gives_the_three_loops_errors_and_their_ratios_to_the_fixed_design():
    (row,) = change_times.rows({"I2": 3.0}, [1.0], after_s=1.0)
    e = row["rms_error_m"]
    assert set(e) == {"fixed", "oracle", "adaptive"} and all(v > 0 for v in e.values())
    assert row["oracle_over_fixed"] == pytest.approx(e["oracle"] / e["fixed"])
    # a load the fixed design was not made for: the true plant's design tracks it better
    assert row["oracle_over_fixed"] < 0.9


@pytest.mark.parametrize(("text", "names"), [("Q=2", "Q=2"), ("K", "'K' is not NAME=FACTOR"), ("K=-1", "positive"),
                                              ("K=x", "'x'"), ("", "at least one")])
def test_a_bad_factor_is_refused_in_one_line_naming_it(text, names):
    with pytest.raises(argparse.ArgumentTypeError) as e:
        change_times.parse_factors(text)
    assert names in str(e.value)


def test_bad_change_times_are_refused():
    for text in ("a,b", "0,1", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="change times|seconds"):
            change_times.parse_times(text)
    assert change_times.parse_times("3, 3.5") == [3.0, 3.5]

"""The loop's streaming front end: sequence gaps filled by interpolation, contiguous blocks untouched."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.errors import DataError
from rt_ident.estimators.streaming import _GapFiller


def test_contiguous_blocks_pass_through_unchanged_and_a_gap_is_interpolated_and_counted():
    g = _GapFiller()
    x = np.arange(10.0)
    a = g(x[:4], 2 * x[:4], 3 * x[:4], np.arange(4))
    np.testing.assert_array_equal(a[0], x[:4])
    b = g(x[4:6], 2 * x[4:6], 3 * x[4:6], np.arange(4, 6))
    np.testing.assert_array_equal(b[1], 2 * x[4:6])
    assert g.filled == 0
    # samples 6, 7, 8 lost: filled linearly from 5 to 9
    c = g(x[9:], 2 * x[9:], 3 * x[9:], np.array([9]))
    np.testing.assert_allclose(c[0], [6.0, 7.0, 8.0, 9.0])
    np.testing.assert_allclose(c[2], [18.0, 21.0, 24.0, 27.0])
    assert g.filled == 3 and g.last_seq == 9


def test_sequence_numbers_that_repeat_or_go_back_are_refused():
    g = _GapFiller()
    g(np.zeros(3), np.zeros(3), np.zeros(3), np.arange(3))
    with pytest.raises(DataError, match="backwards or repeat"):
        g(np.zeros(3), np.zeros(3), np.zeros(3), np.array([3, 5, 4]))

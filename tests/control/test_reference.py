"""The loop's one-time form of every reference (``point``) gives the numbers of the array form (``at``)."""

from __future__ import annotations

import numpy as np
import pytest

from rt_ident.control.reference import Circle, CsvTrajectory, Hold, Moves, Sine

REFERENCES = {
    "hold": Hold(0.002),
    "moves-repeat": Moves((0.0, 0.01, -0.005), v_max=0.05, a_max=0.5, j_max=20.0, dwell=0.1, start=0.2),
    "moves-once": Moves((0.0, 0.004), v_max=0.05, a_max=0.5, j_max=20.0, dwell=0.05, repeat=False),
    "sine": Sine(0.003, 2.5, offset=0.001, start=0.1, fade_periods=1.5),
    "circle-x": Circle(0.01, 1.0, "x", turns=1.25, start=0.3, dwell=0.1),
    "circle-y": Circle(0.01, 1.0, "y", turns=1.25, start=0.3, dwell=0.1),
    "csv": CsvTrajectory(np.array([0.0, 0.5, 1.0, 2.0]), np.array([0.0, 0.002, 0.001, 0.0])),
}


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_the_loops_one_time_form_of_each_reference_equals_its_array_form(name):
    ref = REFERENCES[name]
    times = np.concatenate([np.linspace(-0.5, 6.0, 2601), [0.0, 0.1, 0.2, 0.3]])
    x, v, a = ref.at(times)
    got = np.array([ref.point(float(t)) for t in times])
    assert got.dtype == np.float64
    for col, want in zip(got.T, (x, v, a)):
        scale = max(1e-12, float(np.max(np.abs(want))))
        np.testing.assert_allclose(col, want, rtol=0, atol=1e-12 * scale)
    assert np.ptp(x) > 0 or name == "hold"        # the grid crosses the motion, not only its rest

"""The XY circular test: the circle reference both axes follow, and ISO 230-4's figures
(circular deviation G, radial deviation F, circular hysteresis H) from the table's path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rt_ident.control.contour import circle_figures, fit_circle, polar_plot
from rt_ident.control.reference import Circle, make_reference
from rt_ident.errors import ConfigError

R = 0.005


def test_the_circle_reference_goes_round_once_each_way_and_ends_where_it_began():
    cx, cy = Circle(R, 1.0, "x"), Circle(R, 1.0, "y")
    t = np.linspace(0.0, 8.0, 800_001)
    x, vx, ax = cx.at(t)
    y, vy, ay = cy.at(t)
    assert np.allclose(np.hypot(x, y + R), R, rtol=0, atol=1e-12)          # on the circle, centre (0, -R)
    assert x[0] == y[0] == 0.0 and abs(x[-1]) < 1e-15 and abs(y[-1]) < 1e-15
    dt = t[1] - t[0]
    for p, v, a in ((x, vx, ax), (y, vy, ay)):                              # velocity and acceleration consistent
        assert np.max(np.abs(np.gradient(p, dt) - v)) < 1e-8
        assert np.max(np.abs(np.gradient(v, dt) - a)) < 1e-6
    w = cx.windows()
    mid_ccw = (t > w["ccw"][0] + 0.9) & (t < w["ccw"][0] + 1.1)
    mid_cw = (t > w["cw"][0] + 0.9) & (t < w["cw"][0] + 1.1)
    cross = lambda sel: np.mean(x[sel] * vy[sel] - (y[sel] + R) * vx[sel])  # noqa: E731 - z of r x v
    assert cross(mid_ccw) > 0 > cross(mid_cw)                               # counter-clockwise, then clockwise
    assert max(np.max(np.abs(vx)), np.max(np.abs(vy))) == pytest.approx(2 * math.pi * R, rel=1e-3)


def test_the_measured_turns_are_at_constant_feed_between_half_turn_overshoot_arcs():
    # ISO 230-4: start and stop overshoot arcs outside the measured turn, which is a full turn at the feed
    cx, cy = Circle(R, 1.0, "x", turns=1, start=0.5), Circle(R, 1.0, "y", turns=1, start=0.5)
    for d, (t0, t1) in cx.measured().items():
        t = np.linspace(t0, t1, 10_001)
        phi, om, al = cx.phase(t)
        assert np.allclose(np.abs(om), 2 * math.pi, rtol=0, atol=1e-9) and np.allclose(al, 0.0, atol=1e-9)
        assert abs(phi[-1] - phi[0]) == pytest.approx(2 * math.pi, rel=1e-9)          # one full turn measured
        w0, w1 = cx.windows()[d]
        ramp = cx.phase(np.array([w0, t0]))[0]
        assert abs(ramp[1] - ramp[0]) == pytest.approx(math.pi, rel=1e-9)              # a 180 degree start arc
        x, vx, _ = cx.at(t)
        y, vy, _ = cy.at(t)
        assert np.allclose(np.hypot(vx, vy), 2 * math.pi * R, rtol=1e-9)              # the feed, all along


def test_a_circle_reference_names_its_bad_field():
    with pytest.raises(ConfigError, match="reference.axis"):
        make_reference({"kind": "circle", "radius": R, "frequency_hz": 1.0})
    with pytest.raises(ConfigError, match="reference.turns"):
        make_reference({"kind": "circle", "radius": R, "frequency_hz": 1.0, "axis": "x", "turns": 0.5})
    assert isinstance(make_reference({"kind": "circle", "radius": R, "frequency_hz": 2, "axis": "y"}), Circle)


def _path(radius_of_angle, n=2000, centre=(0.0, -R)):
    th = np.linspace(0, 2 * math.pi, n, endpoint=False)
    r = radius_of_angle(th)
    return centre[0] + r * np.cos(th), centre[1] + r * np.sin(th)


def test_g_is_the_band_about_the_least_squares_centre_and_f_is_about_the_nominal_one():
    # a perfect circle 3 um larger, its centre 2 um off in x: G ~ 0, F = the offset plus the size
    x, y = _path(lambda th: np.full_like(th, R + 3e-6), centre=(2e-6, -R))
    f = circle_figures({"ccw": (x, y)}, R, (0.0, -R))["ccw"]
    assert f["G_um"] < 1e-3
    assert f["F_max_um"] == pytest.approx(5.0, abs=0.01) and f["F_min_um"] == pytest.approx(1.0, abs=0.01)
    assert f["centre_offset_um"][0] == pytest.approx(2.0, abs=1e-3)
    assert f["radius_error_um"] == pytest.approx(3.0, abs=1e-3)
    # an ellipse-like two-lobe error of +-4 um: G = 8 um
    x, y = _path(lambda th: R + 4e-6 * np.cos(2 * th))
    assert circle_figures({"ccw": (x, y)}, R, (0.0, -R))["ccw"]["G_um"] == pytest.approx(8.0, abs=0.01)
    assert fit_circle(x, y)[2] == pytest.approx(R, abs=1e-9)


def test_h_is_the_largest_radial_gap_between_the_two_directions():
    ccw = _path(lambda th: R + 2e-6 * np.sin(th))
    cw = _path(lambda th: R - 2e-6 * np.sin(th))
    fig = circle_figures({"ccw": ccw, "cw": cw}, R, (0.0, -R))
    assert fig["H_um"] == pytest.approx(4.0, abs=0.05) == fig["circular_hysteresis_um"]
    assert fig["circular_deviation_um"] == pytest.approx(max(fig["ccw"]["G_um"], fig["cw"]["G_um"]))
    assert fig["radius_deviation_um"] == pytest.approx(2.0, abs=0.01)      # the largest |F|, either direction
    assert circle_figures({"ccw": ccw, "cw": ccw}, R, (0.0, -R))["H_um"] < 1e-6


def test_the_polar_plot_is_written(tmp_path):
    paths = {"ccw": _path(lambda th: R + 2e-6 * np.sin(3 * th)), "cw": _path(lambda th: R - 1e-6 * np.cos(th))}
    fig = circle_figures(paths, R, (0.0, -R))
    out = polar_plot(paths, R, (0.0, -R), fig, str(tmp_path / "c.png"), title="test")
    assert (tmp_path / "c.png").stat().st_size > 10_000 and out.endswith("c.png")


def test_the_loops_two_point_form_of_the_circle_equals_the_vectorized_one():
    c = Circle(R, 1.0, "y", turns=1.5, start=0.3, dwell=0.1)
    for v in np.linspace(0.0, 6.0, 1201):
        pair = np.array([v, v + 1.5e-3])
        small = c.at(pair)                                   # <= 8 points: the scalar path the loop uses
        big = c.at(np.concatenate([pair, np.zeros(10)]))     # the vectorized path
        for a, b in zip(small, big):
            assert np.array_equal(a, b[:2])

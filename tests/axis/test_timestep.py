"""Tests for rt_ident.axis.timestep: Table 2 of the paper and the k search."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.modal import modal_parameters
from rt_ident.axis.params import thomson_x
from rt_ident.axis.timestep import (
    TABLE2_PAPER,
    KSearchResult,
    TimeStepCase,
    dt_for,
    excitation_fundamental,
    search_k,
    table2_cases,
)
from rt_ident.errors import ConfigError, EstimationError


@pytest.fixture(scope="module")
def wn() -> float:
    return modal_parameters(thomson_x())["wn"]


def test_dt_for_is_direct_transliteration_of_table2_criterion():
    # Section 6: Dt = (2 pi / (N wn)) k
    assert dt_for(512, 10, 4000.0) == pytest.approx((2 * math.pi / (512 * 4000.0)) * 10, rel=1e-15)


def test_table2_dt_matches_paper_within_0p01_percent(wn):
    cases = table2_cases(wn)
    for got, paper in zip(cases, TABLE2_PAPER):
        assert (got.N, got.k) == (paper.N, paper.k)
        assert got.dt == pytest.approx(paper.dt, rel=1e-4)
    assert cases[0].dt == pytest.approx(2.9481e-5, rel=1e-4)
    assert cases[1].dt == pytest.approx(1.0761e-4, rel=1e-4)


def test_table2_w0_matches_paper_within_0p01_percent(wn):
    cases = table2_cases(wn)
    assert cases[0].w0 == pytest.approx(416.2582, rel=1e-4)
    assert cases[1].w0 == pytest.approx(28.5108, rel=1e-4)
    for got, paper in zip(cases, TABLE2_PAPER):
        assert got.w0 == pytest.approx(paper.w0, rel=1e-4)
        assert got.wn == pytest.approx(paper.wn, rel=1e-4)


def test_table2_cases_in_paper_order_and_frozen(wn):
    a, b = table2_cases(wn)
    assert (a.N, a.k, b.N, b.k) == (512, 10.0, 2048, 146.0)
    assert isinstance(a, TimeStepCase)
    with pytest.raises(AttributeError):
        a.dt = 1.0  # type: ignore[misc]


def test_fundamental_equals_two_pi_over_period_length(wn):
    for N, k in ((512, 10), (2048, 146), (100, 3.5)):
        dt = dt_for(N, k, wn)
        assert excitation_fundamental(wn, k) == pytest.approx(2 * math.pi / (N * dt), rel=1e-13)


def test_harmonic_k_of_multisine_lands_on_natural_frequency(wn):
    case = table2_cases(wn)[0]
    ms = schroeder_multisine(case.N, (1, 20))
    freqs = ms.frequencies(case.dt)
    assert freqs[list(ms.harmonics).index(10)] == pytest.approx(wn, rel=1e-13)
    assert freqs[0] == pytest.approx(case.w0, rel=1e-13)


def test_search_k_picks_minimum_of_known_function():
    calls: list[tuple[int, int]] = []
    ks = [2.0, 5.0, 7.0, 10.0, 13.0, 20.0]
    res = search_k(512, ks, lambda k: (k - 9.6) ** 2 + 1.0, progress=lambda i, n: calls.append((i, n)))
    assert isinstance(res, KSearchResult)
    assert res.best_k == 10.0
    assert res.best_score == pytest.approx(1.16)
    assert res.N == 512
    assert [k for k, _ in res.pairs] == ks
    assert res.pairs[0][1] == pytest.approx((2 - 9.6) ** 2 + 1)
    assert calls == [(i, len(ks)) for i in range(1, len(ks) + 1)]


def test_search_k_skips_non_finite_scores_and_keeps_them_recorded():
    res = search_k(64, [1, 2, 3], lambda k: {1: math.nan, 2: 5.0, 3: math.inf}[k])
    assert res.best_k == 2.0
    assert np.isnan(res.scores[0]) and np.isinf(res.scores[2])


def test_search_k_all_failed_raises_estimation_error():
    with pytest.raises(EstimationError):
        search_k(64, [1, 2], lambda k: math.nan)


def test_search_k_ties_go_to_first_k():
    assert search_k(8, [3, 1, 2], lambda k: 0.0).best_k == 3.0


@pytest.mark.parametrize(
    "args, field",
    [((0, 10, 4000.0), "N"), ((-5, 10, 4000.0), "N"), ((512.0, 10, 4000.0), "N"),
     ((512, 0, 4000.0), "k"), ((512, -1, 4000.0), "k"), ((512, math.nan, 4000.0), "k"),
     ((512, 10, 0.0), "wn"), ((512, 10, -1.0), "wn"), ((512, 10, math.inf), "wn")],
)
def test_dt_for_rejects_bad_arguments_naming_field(args, field):
    with pytest.raises(ConfigError) as exc:
        dt_for(*args)
    assert exc.value.field == field


def test_other_entry_points_reject_bad_arguments_naming_field():
    with pytest.raises(ConfigError) as e1:
        excitation_fundamental(0.0, 10)
    assert e1.value.field == "wn"
    with pytest.raises(ConfigError) as e2:
        excitation_fundamental(4000.0, -2)
    assert e2.value.field == "k"
    with pytest.raises(ConfigError) as e3:
        table2_cases(-1.0)
    assert e3.value.field == "wn"
    with pytest.raises(ConfigError) as e4:
        search_k(0, [1], lambda k: k)
    assert e4.value.field == "N"
    with pytest.raises(ConfigError) as e5:
        search_k(8, [1, 0], lambda k: k)
    assert e5.value.field == "ks"
    with pytest.raises(ConfigError) as e6:
        search_k(8, [], lambda k: k)
    assert e6.value.field == "ks"

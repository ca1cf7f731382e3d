"""The paper's integration time-step criterion (Section 6, Table 2).

``Dt = 2 pi k / (N wn)``: with N samples per excitation period, the excitation
fundamental ``w0 = 2 pi / (N Dt)`` equals ``wn / k``, i.e. harmonic ``k`` of the
periodic excitation falls exactly on the natural frequency. The paper fixes N and
searches k for the smallest estimation error (:func:`search_k`).

Pure numerics; invalid arguments raise :class:`~rt_ident.errors.ConfigError`
naming the argument.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rt_ident.errors import ConfigError, EstimationError

log = logging.getLogger(__name__)


def _check_N(N: Any) -> int:
    if isinstance(N, bool) or not isinstance(N, (int, np.integer)):
        raise ConfigError("N", f"must be an integer, got {N!r}")
    if N <= 0:
        raise ConfigError("N", f"must be > 0, got {N!r}")
    return int(N)


def _check_positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(name, f"must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ConfigError(name, f"must be finite and > 0, got {value!r}")
    return value


def dt_for(N: int, k: float, wn: float) -> float:
    """Integration time step [s] for N points per excitation period.

    Section 6, "Table 2 criterion": ``Dt = 2 pi k / (N wn)``.
    """
    N = _check_N(N)
    k = _check_positive("k", k)
    wn = _check_positive("wn", wn)
    return 2.0 * math.pi * k / (N * wn)


def excitation_fundamental(wn: float, k: float) -> float:
    """Excitation fundamental [rad/s]: Section 6, ``w0 = wn / k`` (= 2 pi / (N Dt))."""
    wn = _check_positive("wn", wn)
    k = _check_positive("k", k)
    return wn / k


@dataclass(frozen=True)
class TimeStepCase:
    """One row of Table 2."""

    N: int
    k: float
    wn: float   # [rad/s]
    w0: float   # [rad/s]
    dt: float   # [s]


def time_step_case(N: int, k: float, wn: float) -> TimeStepCase:
    """The Table 2 row for (N, k) at natural frequency ``wn``."""
    return TimeStepCase(N=_check_N(N), k=_check_positive("k", k), wn=_check_positive("wn", wn),
                        w0=excitation_fundamental(wn, k), dt=dt_for(N, k, wn))


#: (N, k) of Table 2, in the paper's order.
TABLE2_NK: tuple[tuple[int, float], tuple[int, float]] = ((512, 10.0), (2048, 146.0))

#: Table 2 exactly as printed (wn printed to 5 significant figures; w0 and Dt as printed).
TABLE2_PAPER: tuple[TimeStepCase, TimeStepCase] = (
    TimeStepCase(N=512, k=10.0, wn=4.1626e3, w0=416.2582, dt=2.9481e-5),
    TimeStepCase(N=2048, k=146.0, wn=4.1626e3, w0=28.5108, dt=1.0761e-4),
)


def table2_cases(wn: float) -> tuple[TimeStepCase, TimeStepCase]:
    """Table 2 recomputed for natural frequency ``wn``: (N=512, k=10) then (N=2048, k=146)."""
    a, b = (time_step_case(N, k, wn) for N, k in TABLE2_NK)
    return a, b


@dataclass(frozen=True, eq=False)
class KSearchResult:
    """Outcome of :func:`search_k`. ``scores`` may hold inf/nan for failed k (never chosen)."""

    N: int
    best_k: float
    best_score: float
    ks: np.ndarray       # (m,) in the order tried
    scores: np.ndarray   # (m,)

    @property
    def pairs(self) -> tuple[tuple[float, float], ...]:
        return tuple(zip(self.ks.tolist(), self.scores.tolist()))


def search_k(
    N: int,
    ks: Iterable[float],
    score: Callable[[float], float],
    *,
    progress: Callable[[int, int], None] | None = None,
) -> KSearchResult:
    """The paper's search (Section 6): N fixed, k varied, keep the k with the smallest score.

    ``score(k)`` is typically an estimation error obtained with ``dt_for(N, k, wn)``.
    A non-finite score marks k as unusable (recorded, never best). Ties go to the
    first k tried. ``progress(i, total)`` is called after each k (i = 1..total).
    Raises :class:`EstimationError` if no k gives a finite score.
    """
    N = _check_N(N)
    k_list = [_check_positive("ks", k) for k in ks]
    if not k_list:
        raise ConfigError("ks", "no k values to search")
    total = len(k_list)
    scores = np.empty(total)
    for i, k in enumerate(k_list):
        scores[i] = float(score(k))
        log.debug("search_k N=%d k=%g score=%g", N, k, scores[i])
        if progress is not None:
            progress(i + 1, total)
    finite = np.isfinite(scores)
    if not finite.any():
        raise EstimationError(f"search_k: no finite score for N={N} over {total} values of k")
    best = int(np.argmin(np.where(finite, scores, np.inf)))
    ks_arr = np.asarray(k_list)
    ks_arr.setflags(write=False)
    scores.setflags(write=False)
    return KSearchResult(N=N, best_k=k_list[best], best_score=float(scores[best]), ks=ks_arr, scores=scores)

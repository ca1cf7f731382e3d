"""Estimators: batch LS (Eq. 10), recursive LS (Eqs. 14-16) and the paper's Euler regression.

Other estimators live in sibling modules (consistent, frequency, uncertainty, registry, the
state estimator, excitation identification) and are imported from there directly.
:func:`make_streaming` builds the per-sample estimator the real-time loop feeds.
"""

from rt_ident.estimators.ls import LSResult, lstsq
from rt_ident.estimators.paper import (
    PaperEstimate,
    euler_phi,
    euler_regression,
    fit_paper_ls,
    fit_paper_rls,
    recover_physical,
    recover_values,
    state_matrix_from_phi,
)
from rt_ident.estimators.rls import RecursiveLeastSquares, warmup
from rt_ident.estimators.streaming import make_streaming

__all__ = [
    "LSResult",
    "PaperEstimate",
    "RecursiveLeastSquares",
    "euler_phi",
    "euler_regression",
    "fit_paper_ls",
    "fit_paper_rls",
    "lstsq",
    "make_streaming",
    "recover_physical",
    "recover_values",
    "state_matrix_from_phi",
    "warmup",
]

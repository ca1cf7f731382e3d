"""Modal analysis of a state matrix (Section 6 of the paper).

Eigenvalues of A (Eq. 8) come as rigid-body zeros and complex pairs
``lambda = -zeta wn +/- j wd``. For the free-free two-inertia axis there is a
double zero (a Jordan block: both inertias turning together) and one flexible
pair. A defective zero eigenvalue is computed by LAPACK as a pair of order
sqrt(eps) * ||A|| (about 1e-5 rad/s for Table 1), so eigenvalues with
``|lambda| <= rigid_tol * max|lambda|`` are classified rigid-body and reported
with wn = wd = zeta = 0 rather than as a spurious, badly damped mode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rt_ident.axis.model import state_space
from rt_ident.axis.params import AxisParams
from rt_ident.errors import EstimationError

DEFAULT_RIGID_TOL = 1e-6


@dataclass(frozen=True)
class Mode:
    """One complex-conjugate pair (or one real / rigid-body eigenvalue)."""

    eigenvalue: complex        # the member with Im >= 0
    eigenvector: np.ndarray    # right eigenvector, normalized to unit 2-norm
    wn: float                  # |lambda|            [rad/s]
    wd: float                  # |Im lambda|         [rad/s]
    zeta: float                # -Re(lambda)/|lambda|
    rigid: bool                # rigid-body (zero) eigenvalue


@dataclass(frozen=True)
class ModalResult:
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    modes: tuple[Mode, ...]    # flexible modes first (ascending wn), then rigid ones

    @property
    def flexible(self) -> tuple[Mode, ...]:
        return tuple(m for m in self.modes if not m.rigid)

    @property
    def n_rigid(self) -> int:
        return sum(1 for m in self.modes if m.rigid)

    def first_flexible(self) -> Mode:
        flex = self.flexible
        if not flex:
            raise EstimationError("no flexible (oscillatory) mode: every eigenvalue is rigid-body or real")
        return flex[0]


def modal_analysis(A: np.ndarray, *, rigid_tol: float = DEFAULT_RIGID_TOL) -> ModalResult:
    """Eigen-decomposition of a state matrix into modes.

    ``|A - lambda I| = 0`` gives the eigenvalues; each pair
    ``-zeta wn +/- j wd`` gives wn = |lambda|, wd = |Im lambda|,
    zeta = -Re(lambda)/wn, so that wd = wn sqrt(1 - zeta^2) (Section 6).
    A real non-zero eigenvalue (overdamped) is reported as its own mode with
    wd = 0 and zeta = +/-1.
    """
    A = np.asarray(A, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise EstimationError(f"state matrix must be square, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise EstimationError("state matrix has non-finite entries")
    lam, vec = np.linalg.eig(A)
    scale = float(np.max(np.abs(lam))) if lam.size else 0.0
    thresh = rigid_tol * scale
    modes: list[Mode] = []
    used = np.zeros(lam.size, dtype=bool)
    for i in np.argsort(np.abs(lam)):
        if used[i]:
            continue
        li = lam[i]
        used[i] = True
        v = vec[:, i] / np.linalg.norm(vec[:, i])
        if abs(li) <= thresh:
            modes.append(Mode(0j, v, 0.0, 0.0, 0.0, True))
            continue
        if abs(li.imag) > 0:
            # consume the conjugate partner
            rest = np.where(~used)[0]
            if rest.size:
                j = rest[np.argmin(np.abs(lam[rest] - np.conj(li)))]
                used[j] = True
            if li.imag < 0:
                li, v = np.conj(li), np.conj(v)
        wn = float(abs(li))
        modes.append(Mode(complex(li), v, wn, float(abs(li.imag)), float(-li.real / wn), False))
    flex = sorted((m for m in modes if not m.rigid), key=lambda m: m.wn)
    rigid = [m for m in modes if m.rigid]
    return ModalResult(lam, vec, tuple(flex + rigid))


def modal_parameters(p: AxisParams) -> dict[str, float]:
    """wn, wd, zeta of the flexible mode of the axis with parameters ``p``."""
    A, _ = state_space(p)
    m = modal_analysis(A).first_flexible()
    return {"wn": m.wn, "wd": m.wd, "zeta": m.zeta}

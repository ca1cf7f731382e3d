"""Matrices of the two-inertia model (Eqs. 2-3) and its state-space form (Eq. 8).

State order everywhere in this package: ``x = [theta1, omega1, theta2, omega2]``,
as in Eq. (8).
"""

from __future__ import annotations

import numpy as np

from rt_ident.axis.params import AxisParams


def mass_matrix(p: AxisParams) -> np.ndarray:
    """Eq. (3): diag(I1, I2)."""
    return np.array([[p.I1, 0.0], [0.0, p.I2]])


def damping_matrix(p: AxisParams) -> np.ndarray:
    """Eq. (3): B [[1, -1], [-1, 1]]."""
    return p.B * np.array([[1.0, -1.0], [-1.0, 1.0]])


def stiffness_matrix(p: AxisParams) -> np.ndarray:
    """Eq. (3): K [[1, -1], [-1, 1]]."""
    return p.K * np.array([[1.0, -1.0], [-1.0, 1.0]])


def input_vector() -> np.ndarray:
    """Eq. (3) right-hand side per unit torque: T acts on the motor inertia only."""
    return np.array([1.0, 0.0])


def state_space(p: AxisParams) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state-space model of Eq. (8): xdot = A x + b T.

    Departure from the paper: Eq. (8) prints the input column as
    ``[0, -1/I1, 0, 0]``. With T = Tm - Tc on the right of Eq. (3) the motor
    inertia is driven by +T, so the column is ``[0, +1/I1, 0, 0]``.
    """
    k1, b1 = p.K / p.I1, p.B / p.I1
    k2, b2 = p.K / p.I2, p.B / p.I2
    A = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-k1, -b1, k1, b1],
            [0.0, 0.0, 0.0, 1.0],
            [k2, b2, -k2, -b2],
        ]
    )
    b = np.array([0.0, 1.0 / p.I1, 0.0, 0.0])  # +1/I1: sign corrected (see docstring)
    return A, b


def natural_frequency(p: AxisParams) -> float:
    """Closed form of the flexible mode: wn^2 = K (1/I1 + 1/I2)."""
    return float(np.sqrt(p.K * (1.0 / p.I1 + 1.0 / p.I2)))


def damping_ratio(p: AxisParams) -> float:
    """Closed form of the flexible mode: 2 zeta wn = B (1/I1 + 1/I2)."""
    return float(p.B * (1.0 / p.I1 + 1.0 / p.I2) / (2.0 * natural_frequency(p)))

import numpy as np

from rt_ident.axis.model import (
    damping_matrix,
    damping_ratio,
    mass_matrix,
    natural_frequency,
    state_space,
    stiffness_matrix,
)
from rt_ident.axis.params import thomson_x


def test_second_order_matrices_match_eq3():
    p = thomson_x()
    assert np.array_equal(mass_matrix(p), np.diag([p.I1, p.I2]))
    assert np.allclose(damping_matrix(p), [[p.B, -p.B], [-p.B, p.B]])
    assert np.allclose(stiffness_matrix(p), [[p.K, -p.K], [-p.K, p.K]])


def test_state_space_equals_first_order_form_of_eq3():
    # Oracle: xdot = [w; M^-1 (f - C w - K th)] built directly from Eq. 3.
    p = thomson_x()
    A, b = state_space(p)
    rng = np.random.default_rng(1)
    M, C, K = mass_matrix(p), damping_matrix(p), stiffness_matrix(p)
    for _ in range(5):
        th, w, T = rng.normal(size=2), rng.normal(size=2), rng.normal()
        acc = np.linalg.solve(M, np.array([T, 0.0]) - C @ w - K @ th)
        x = np.array([th[0], w[0], th[1], w[1]])
        assert np.allclose(A @ x + b * T, [w[0], acc[0], w[1], acc[1]], rtol=1e-12, atol=0)


def test_input_sign_is_corrected_to_plus_one_over_I1():
    p = thomson_x()
    _, b = state_space(p)
    assert b[1] == 1.0 / p.I1 > 0


def test_closed_forms_give_table_values():
    p = thomson_x()
    assert abs(natural_frequency(p) - 4162.58) < 0.01
    assert abs(damping_ratio(p) - 0.03973) < 5e-6

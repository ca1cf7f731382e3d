import numpy as np
import pytest

from rt_ident.axis.modal import modal_analysis, modal_parameters
from rt_ident.axis.model import damping_ratio, natural_frequency, state_space
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.errors import EstimationError


def test_table1_modal_parameters_to_four_digits():
    m = modal_parameters(thomson_x())
    assert round(m["wn"], 2) == 4162.58
    assert round(m["zeta"], 5) == 0.03973
    assert abs(m["wd"] - 4159.3) < 0.05


def test_rigid_body_double_zero_is_classified_not_reported_as_a_mode():
    r = modal_analysis(state_space(thomson_x())[0])
    assert r.n_rigid == 2
    assert len(r.flexible) == 1


def test_eigenvector_satisfies_eigen_equation():
    A = state_space(thomson_x())[0]
    m = modal_analysis(A).first_flexible()
    assert np.linalg.norm(A @ m.eigenvector - m.eigenvalue * m.eigenvector) < 1e-9 * abs(m.eigenvalue)


@pytest.mark.parametrize("scale", [0.3, 1.0, 3.0])
def test_modal_matches_closed_form_for_other_plants(scale):
    p = AxisParams(I1=2.7e-5 * scale, I2=8.3e-6 / scale, B=2.1e-3 * scale, K=110.0 * scale)
    m = modal_parameters(p)
    assert m["wn"] == pytest.approx(natural_frequency(p), rel=1e-10)
    assert m["zeta"] == pytest.approx(damping_ratio(p), rel=1e-9)
    assert m["wd"] == pytest.approx(m["wn"] * np.sqrt(1 - m["zeta"] ** 2), rel=1e-10)


def test_no_flexible_mode_is_an_error():
    with pytest.raises(EstimationError):
        modal_analysis(np.zeros((4, 4))).first_flexible()


def test_non_finite_state_matrix_rejected():
    A = state_space(thomson_x())[0].copy()
    A[1, 1] = np.nan
    with pytest.raises(EstimationError):
        modal_analysis(A)

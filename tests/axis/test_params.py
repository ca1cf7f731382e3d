import math

import pytest

from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.errors import ConfigError


def test_thomson_x_matches_table1():
    p = thomson_x()
    assert (p.I1, p.I2, p.B, p.K, p.lead) == (2.7e-5, 8.3e-6, 2.1e-3, 1.1e2, 7.96e-4)


@pytest.mark.parametrize(
    "field,value",
    [("I1", 0.0), ("I1", -1e-5), ("I2", 0.0), ("K", -1.0), ("K", 0.0), ("lead", 0.0),
     ("B", -1e-9), ("I1", math.nan), ("K", math.inf), ("B", math.nan), ("I2", "heavy"), ("K", True)],
)
def test_invalid_values_rejected_naming_the_field(field, value):
    kw = dict(I1=2.7e-5, I2=8.3e-6, B=2.1e-3, K=110.0)
    kw[field] = value
    with pytest.raises(ConfigError) as e:
        AxisParams(**kw)
    assert e.value.field == field
    assert field in str(e.value)


def test_zero_damping_is_allowed():
    assert AxisParams(I1=1.0, I2=1.0, B=0.0, K=1.0).B == 0.0


def test_from_toml_reports_the_bad_field_with_its_table(tmp_path):
    f = tmp_path / "axis.toml"
    f.write_text("[axis]\nI1 = 2.7e-5\nI2 = -8.3e-6\nB = 2.1e-3\nK = 110.0\n")
    with pytest.raises(ConfigError, match=r"axis\.I2"):
        AxisParams.from_toml(f)


def test_from_toml_rejects_unknown_and_missing_fields(tmp_path):
    f = tmp_path / "axis.toml"
    f.write_text("[axis]\nI1 = 2.7e-5\nI2 = 8.3e-6\nB = 2.1e-3\nK = 110.0\nmass = 3\n")
    with pytest.raises(ConfigError, match="mass"):
        AxisParams.from_toml(f)
    f.write_text("[axis]\nI1 = 2.7e-5\nI2 = 8.3e-6\nB = 2.1e-3\n")
    with pytest.raises(ConfigError, match=r"axis\.K.*missing"):
        AxisParams.from_toml(f)


def test_from_toml_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        AxisParams.from_toml(tmp_path / "nope.toml")


def test_with_revalidates():
    with pytest.raises(ConfigError):
        thomson_x().with_(K=-1.0)
    assert thomson_x().with_(K=200.0).K == 200.0

import math

import pytest
from pydantic import ValidationError

from synth.params import OperatingBounds, VehicleParams


def test_defaults_are_table_1_and_eq_13():
    p = VehicleParams()
    assert p.symbols() == {
        "M_v": 1481.0,
        "m_eff": 443.0,
        "R_w": 1.0,
        "I_z": 1807.0,
        "l_f": 1.12,
        "l_r": 1.5,
        "C_f": 57110.0,
        "C_r": 58100.0,
        "C_x": 0.37,
        "F_r": 0.0,
        "C_y": 0.42,
        "b_T": 1.0,
        "b_delta": 1.0,
        "s": 0.01,
    }
    b = OperatingBounds()
    assert (b.vx_min_mps, b.vx_max_mps, b.vy_min_mps, b.vy_max_mps, b.r_min_radps, b.r_max_radps) == (
        5.0,
        30.0,
        -1.5,
        1.5,
        -0.55,
        0.55,
    )
    assert b.inverse_speed_bounds == (1 / 30, 1 / 5)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("mass_kg", -1.0),
        ("mass_kg", 0.0),
        ("yaw_inertia_kgm2", math.nan),
        ("sample_period_s", 0.0),
        ("front_cornering_stiffness_npr", math.inf),
    ],
)
def test_bad_parameter_is_rejected_naming_the_field(field, value):
    with pytest.raises(ValidationError) as info:
        VehicleParams(**{field: value})
    assert field in str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"vx_min_mps": 30.0, "vx_max_mps": 5.0}, "vx_min_mps"),
        ({"vx_min_mps": 0.0}, "vx_min_mps"),
        ({"r_min_radps": 0.6}, "r_min_radps"),
        ({"vy_min_mps": 2.0}, "vy_min_mps"),
    ],
)
def test_bad_bounds_are_rejected_naming_the_field(kwargs, named):
    with pytest.raises(ValidationError) as info:
        OperatingBounds(**kwargs)
    assert named in str(info.value)


def test_unknown_field_is_rejected():
    with pytest.raises(ValidationError, match="mass"):
        VehicleParams(mass=1000.0)

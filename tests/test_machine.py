import math
import warnings

import pytest

from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Deflector, Machine, OperatingPoint


def test_default_geometry_matches_documented_values():
    m = Machine.default()
    assert m.n_stages == 5
    assert m.flingers_per_rotor == 18
    assert m.liner_clearance_m == pytest.approx(0.075)
    assert m.stage_clearance_m == pytest.approx(0.07)
    assert m.casing_width_m == pytest.approx(0.96)
    assert m.stage_axis_z_m(1) - m.stage_axis_z_m(2) == pytest.approx(0.45)
    assert m.stage_band_m(5)[0] == 0.0
    assert m.inlet_zone_bottom_z_m == pytest.approx(m.stage_axis_z_m(1) + 0.225)


def test_toml_round_trip(tmp_path):
    m = Machine.default().model_copy(
        update={"central_sweep": [("down", "down")] * 4 + [("up", "down")],
                "deflectors": [Deflector(stage=1, height_above_axis_m=0.2, length_m=0.1, angle_deg=30)]}
    )
    m = Machine.model_validate(m.model_dump())
    p = tmp_path / "m.toml"
    m.to_toml(p)
    again = Machine.from_toml(p)
    assert again == m
    assert again.sweep(5) == ("up", "down")


@pytest.mark.parametrize(
    ("update", "field"),
    [
        ({"tip_radius_m": 0.04}, "tip_radius_m"),
        ({"rotor_axis_offset_m": 0.3}, "liners"),
        ({"stage_spacing_m": 0.3}, "consecutive stages"),
        ({"n_stages": 0}, "n_stages"),
        ({"central_sweep": [["down", "down"]]}, "central_sweep"),
        ({"central_sweep": [["left", "down"]] * 5}, "central_sweep"),
        ({"gate_length_m": 0.5}, "gates"),
    ],
)
def test_validation_errors_are_one_line(update, field):
    data = Machine.default().model_dump() | update
    with pytest.raises(MsmillInputError) as info:
        Machine.from_dict(data)
    msg = str(info.value)
    assert "\n" not in msg
    assert field in msg


def test_bad_toml_names_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[machine]\nn_stages = 'five'\n")
    with pytest.raises(MsmillInputError, match=r"bad.toml.n_stages"):
        Machine.from_toml(p)
    p.write_text("[machine\n")
    with pytest.raises(MsmillInputError, match="valid TOML"):
        Machine.from_toml(p)


def test_operating_point_recipe_and_explicit_speeds():
    op = OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=40)
    assert op.stage_speeds(5) == [1500, 1500, 1500, 1500, 3000]
    op2 = OperatingPoint(feed_tph=30, stage_speeds_rpm=[1400, 1500, 1600])
    assert op2.stage_speeds(3) == [1400, 1500, 1600]
    with pytest.raises(MsmillInputError, match="stage_speeds_rpm"):
        op2.stage_speeds(5)
    with pytest.raises(MsmillInputError):
        OperatingPoint.from_dict({"feed_tph": 30})


def test_operating_point_warns_outside_design_space():
    with pytest.warns(OutOfDomainWarning, match="speed_rpm"):
        OperatingPoint(feed_tph=30, speed_rpm=2500)
    with pytest.warns(OutOfDomainWarning, match="feed_tph"):
        OperatingPoint(feed_tph=80, speed_rpm=1500)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OperatingPoint(feed_tph=30, speed_rpm=1500, gate_deg=80)


def test_rotation_sense_and_gate_geometry():
    m = Machine.default()
    # left rotor sweeping down in the centre turns at +omega about +y: v = omega x r
    assert m.omega_sign(1, 0) == 1 and m.omega_sign(1, 1) == -1
    x0, z0 = m.gate_tip_m(0.0, 0)
    assert x0 == pytest.approx(-0.48 + 0.3) and z0 == pytest.approx(m.gate_hinge_z_m)
    assert m.gate_opening_m(80) > m.gate_opening_m(0)
    assert m.tip_speed_m_s(1500) == pytest.approx(1500 * 2 * math.pi / 60 * 0.19)


def test_a_rock_size_in_mm_gives_its_radius_in_m_for_scalars_and_arrays():
    import numpy as np

    from msmill.machine import size_mm_to_radius_m

    assert size_mm_to_radius_m(10) == 0.005 and isinstance(size_mm_to_radius_m(10), float)
    sizes = np.array([2.0, 6.4, 30.0])
    np.testing.assert_array_equal(size_mm_to_radius_m(sizes), sizes / 2000.0)
    np.testing.assert_array_equal(size_mm_to_radius_m([2.0, 6.4]), [0.001, 0.0032])

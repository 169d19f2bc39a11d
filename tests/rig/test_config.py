"""Rig configuration: the shipped preset, the example file, and clear errors."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from gonio.errors import ConfigError
from gonio.rig.config import default_rig_config, load_rig_config

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig.toml"


def test_default_preset():
    cfg = default_rig_config()
    assert [s.joint for s in cfg.servos] == [
        "light_azimuth",
        "camera_azimuth",
        "stage_tilt",
        "stage_spin",
    ]
    assert cfg.geometry.kind == "arms_tilt_spin"
    assert cfg.home_rad["light_azimuth"] == pytest.approx(math.radians(-45))


def test_example_file_loads_and_converts():
    cfg = load_rig_config(EXAMPLE)
    tilt = cfg.servo_for("stage_tilt")
    # gear 2, mirrored, zero at 180 deg: joint +10 deg -> servo 180 - 20 deg
    assert tilt.pulses(math.radians(10)) == pytest.approx((180 - 20) * 4096 / 360)
    assert tilt.joint_rad(tilt.pulses(0.3)) == pytest.approx(0.3, abs=1e-15)
    assert cfg.park_rad["camera_azimuth"] == pytest.approx(math.radians(60))


def write(tmp_path, text):
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_errors_name_file_and_field(tmp_path):
    base = EXAMPLE.read_text()
    with pytest.raises(ConfigError, match=r"rig.toml.*baud_rate.*4500000"):
        load_rig_config(write(tmp_path, base.replace("baud_rate = 1000000", "baud_rate = 4500000")))
    with pytest.raises(ConfigError, match=r"servos.0.joint.*unknown joint 'lamp'"):
        load_rig_config(write(tmp_path, base.replace('joint = "light_azimuth"', 'joint = "lamp"')))
    with pytest.raises(ConfigError, match=r"servos.*min_deg.*max_deg"):
        load_rig_config(write(tmp_path, base.replace("min_deg = -150.0", "min_deg = 170.0", 1)))
    with pytest.raises(ConfigError, match="outside 0..4095 of position mode"):
        load_rig_config(write(tmp_path, base.replace("max_deg = 85.0", "max_deg = 120.0")))
    with pytest.raises(ConfigError, match="geometry.*colour"):
        load_rig_config(
            write(
                tmp_path,
                base.replace('kind = "arms_tilt_spin"', 'kind = "arms_tilt_spin"\ncolour = 1'),
            )
        )
    with pytest.raises(ConfigError, match=r"servos.1.model.*unknown servo model 'AX-12'"):
        load_rig_config(write(tmp_path, base.replace('model = "XM430-W350"', 'model = "AX-12"', 2)))
    with pytest.raises(ConfigError, match="not a valid TOML"):
        load_rig_config(write(tmp_path, "[bus\nport="))
    with pytest.raises(ConfigError, match="cannot read"):
        load_rig_config(tmp_path / "missing.toml")


def test_other_geometry_is_a_config_change(tmp_path):
    """Raised camera arm (elevation 20 deg): still a round trip, now with a different tilt."""
    from gonio.radiometry import spherical_to_direction
    from gonio.rig.kinematics import Kinematics

    text = EXAMPLE.read_text().replace("camera_elevation_deg = 0.0", "camera_elevation_deg = 20.0")
    kin = Kinematics(load_rig_config(write(tmp_path, text)))
    wi = spherical_to_direction(math.radians(30), 0.2)
    wo = spherical_to_direction(math.radians(45), 2.4)
    q = kin.inverse(wi, wo)
    ai, ao = kin.forward(q)
    assert max(abs(ai - wi).max(), abs(ao - wo).max()) < 1e-12
    # the camera really is 20 deg above the horizontal plane in the world
    cam_world = kin.sample_to_world(q["stage_tilt"], q["stage_spin"]) @ ao
    assert math.degrees(math.asin(cam_world[2])) == pytest.approx(20.0, abs=1e-9)


def test_virtual_rig_document_is_the_preset_on_the_virtual_port():
    import tomllib

    from gonio.rig.config import default_rig_document, rig_config_from_dict, virtual_rig_document

    text = virtual_rig_document()
    doc = tomllib.loads(text)
    # the preset file as parsed, with only the port changed
    expected = tomllib.loads(default_rig_document())
    expected["bus"]["port"] = "virtual"
    assert doc == expected
    cfg = rig_config_from_dict(doc, "virtual rig")
    preset = default_rig_config()
    assert cfg.bus.port == "virtual"
    assert (
        cfg.model_dump()
        == preset.model_copy(
            update={"bus": preset.bus.model_copy(update={"port": "virtual"})}
        ).model_dump()
    )


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("tilt_axis = [0.0, -1.0, 0.0]", "tilt_axis = [0.0, nan, 0.0]", "geometry.tilt_axis.1"),
        (
            "rest_normal = [1.0, 0.0, 0.0]",
            "rest_normal = [nan, 0.0, 0.0]",
            "geometry.rest_normal.0",
        ),
        ("light_radius_m = 0.55", "light_radius_m = inf", "geometry.light_radius_m"),
        ("move_timeout_s = 20.0", "move_timeout_s = inf", "motion.move_timeout_s"),
        (
            'kind = "arms_tilt_spin"',
            'kind = "arms_tilt_spin"\nstage_offset_m = [inf, 0.0, 0.0]',
            "geometry.stage_offset_m.0",
        ),
        (
            'kind = "arms_tilt_spin"',
            'kind = "arms_tilt_spin"\ncamera_mount_deg = [nan, 0.0, 0.0]',
            "geometry.camera_mount_deg.0",
        ),
    ],
)
def test_non_finite_numbers_are_refused_naming_the_field(tmp_path, old, new, field):
    # A NaN axis passed the config and raised a bare ValueError in the kinematics (a
    # traceback from `gonio capture plan`); an infinite radius, offset or timeout and a NaN
    # mount were accepted.
    base = EXAMPLE.read_text()
    assert old in base
    with pytest.raises(ConfigError) as info:
        load_rig_config(write(tmp_path, base.replace(old, new, 1)))
    assert "rig.toml" in str(info.value) and f"field '{field}'" in str(info.value)
    assert "finite" in str(info.value)


@pytest.mark.parametrize(
    ("old", "new", "field", "bound"),
    [
        ("light_radius_m = 0.55", "light_radius_m = 1e300", "geometry.light_radius_m", "10"),
        ("tilt_axis = [0.0, -1.0, 0.0]", "tilt_axis = [0.0, -1e200, 0.0]",
         "geometry.tilt_axis.1", "-1000"),
        ('kind = "arms_tilt_spin"', 'kind = "arms_tilt_spin"\nholder_offset_m = [0, 0, 5e9]',
         "geometry.holder_offset_m.2", "1"),
        ('kind = "arms_tilt_spin"', 'kind = "arms_tilt_spin"\ncamera_mount_deg = [0, 1e9, 0]',
         "geometry.camera_mount_deg.1", "90"),
        ("move_timeout_s = 20.0", "move_timeout_s = 1e300", "motion.move_timeout_s", "86400"),
    ],
)  # fmt: skip
def test_huge_finite_numbers_are_refused_naming_the_field_and_bound(
    tmp_path, old, new, field, bound
):
    # 1e300 m arms and 1e200 axes were accepted, and overflowed in the kinematics
    base = EXAMPLE.read_text()
    assert old in base
    with pytest.raises(ConfigError) as info:
        load_rig_config(write(tmp_path, base.replace(old, new, 1)))
    assert f"field '{field}'" in str(info.value) and bound in str(info.value)
    # the nominal values stay accepted
    load_rig_config(write(tmp_path, base))


def test_a_speed_beyond_the_servos_register_is_refused_when_loaded(tmp_path):
    # 50000 deg/s passed the config and the servo refused the write at run time ("data
    # limit error"): the Profile Velocity register holds at most 32767 x 0.229 rpm
    base = EXAMPLE.read_text()
    old = "velocity_deg_s = 45.0"
    assert old in base
    with pytest.raises(ConfigError) as info:
        load_rig_config(write(tmp_path, base.replace(old, "velocity_deg_s = 50000.0", 1)))
    assert "velocity_deg_s = 50000" in str(info.value) and "45022 deg/s" in str(info.value)
    load_rig_config(write(tmp_path, base.replace(old, "velocity_deg_s = 45000.0", 1)))

"""The as-built world model: presets, draws, overrides, files, round trip, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from gonio.errors import ConfigError
from gonio.simulator.scene import Camera
from gonio.simulator.world import (
    JOINTS,
    PARAMETER_UNITS,
    RIG_PARAMETERS,
    World,
    draw_world,
    load_world,
    world_document,
)


def test_perfect_is_all_zero_and_exact():
    w = draw_world("perfect", 7)
    assert w.perfect
    assert all(v == 0.0 for v in w.rig.values())
    assert w.servos.landing_pulses == 0 and w.camera_serial() is None
    cam = Camera(resolution=(64, 48), focal_length=0.035, fov_deg=26.0)
    assert w.as_built_camera(cam) is cam


def test_realistic_draw_is_seeded_and_within_the_documented_ranges():
    a, b, c = draw_world("realistic", 1), draw_world("realistic", 1), draw_world("realistic", 2)
    assert a == b and a != c
    assert set(a.rig) == set(RIG_PARAMETERS) == set(PARAMETER_UNITS)
    draws = [draw_world("realistic", s) for s in range(40)]
    r = {n: np.array([w.rig[n] for w in draws]) for n in RIG_PARAMETERS}
    for j in JOINTS:
        assert np.abs(r[f"{j}.offset"]).max() <= 2.0 and np.abs(r[f"{j}.offset"]).max() > 1.0
        assert r[f"{j}.backlash"].min() >= 0.15 and r[f"{j}.backlash"].max() <= 0.35
    assert np.abs(r["light_elevation"]).max() <= 0.5
    assert np.abs(r["camera_radius"]).max() <= 2e-3
    assert (r["holder_offset_z"] >= 1e-3).all() and (r["holder_offset_z"] <= 5e-3).all()
    assert all(abs(w.camera.fx_scale) <= 0.015 for w in draws)
    assert all(w.servos.landing_pulses == 1 for w in draws)
    assert {w.servos.initial_approach["stage_tilt"] for w in draws} == {-1, 1}
    assert not any(w.perfect for w in draws)


def test_explicit_values_override_the_draw():
    w = draw_world(
        "realistic",
        3,
        {
            "rig": {"stage_tilt.offset": 0.8},
            "servos": {"landing_pulses": 0},
            "camera": {"fx_scale": 0.02},
        },
    )
    base = draw_world("realistic", 3)
    assert w.rig["stage_tilt.offset"] == 0.8
    assert w.rig["light_azimuth.offset"] == base.rig["light_azimuth.offset"]
    assert w.servos.landing_pulses == 0
    assert w.camera.fx_scale == w.camera.fy_scale == 0.02


def test_truth_parameters_are_absolute():
    w = draw_world(
        "perfect",
        0,
        {"rig": {"light_elevation": 0.3, "camera_radius": 0.001, "stage_tilt.offset": 1.0}},
    )
    t = w.truth_parameters({"geometry": {"light_elevation_deg": 10.0, "camera_radius_m": 0.4}})
    assert t["light_elevation"] == pytest.approx(10.3)
    assert t["camera_radius"] == pytest.approx(0.401)
    assert t["light_radius"] == pytest.approx(0.5)  # the default rig's nominal
    assert t["stage_tilt.offset"] == 1.0


def test_intrinsics_in_opencv_convention():
    cam = Camera(resolution=(400, 300), focal_length=0.016, fov_deg=30.0)
    w = draw_world(
        "perfect",
        0,
        {
            "camera": {
                "fx_scale": 0.01,
                "principal_offset": [0.01, -0.02],
                "dist": [0.1, 0, 0, 0, 0],
            }
        },
    )
    K, dist = w.intrinsics(cam)
    f = 200 / np.tan(np.radians(15))  # closed form: half width over tan(half fov)
    assert K[0, 0] == pytest.approx(f * 1.01) and K[1, 1] == pytest.approx(f * 1.01)
    assert K[0, 2] == pytest.approx(200 + 4 - 0.5) and K[1, 2] == pytest.approx(150 - 6 - 0.5)
    assert dist.tolist() == [0.1, 0, 0, 0, 0]
    built = w.as_built_camera(cam)
    np.testing.assert_allclose(built.intrinsics(), w.scene_intrinsics(cam), rtol=1e-12)
    assert w.camera_serial().startswith("SIM")


def test_document_round_trip_rebuilds_the_same_world(tmp_path):
    w = draw_world("realistic", 11, {"rig": {"stage_spin.backlash": 0.5}})
    doc = world_document(w)
    assert load_world(doc) == w
    (tmp_path / "w.toml").write_text(tomli_w.dumps({"world": doc}))
    assert load_world(tmp_path / "w.toml") == w
    (tmp_path / "top.toml").write_text(tomli_w.dumps(doc))
    assert load_world(tmp_path / "top.toml") == w


def test_preset_names_and_seed():
    assert load_world("realistic", 4) == draw_world("realistic", 4)
    assert load_world({"preset": "realistic", "seed": 4}) == draw_world("realistic", 4)
    assert load_world({"preset": "realistic", "seed": 4}, seed=5) == draw_world("realistic", 5)
    assert load_world(None).perfect


@pytest.mark.parametrize(
    "table, words",
    [
        ({"preset": "sloppy"}, ["sloppy", "perfect", "realistic"]),
        ({"rig": {"stage_tilt.ofset": 1.0}}, ["stage_tilt.ofset"]),
        ({"rig": {"stage_tilt.offset": "big"}}, ["stage_tilt.offset", "number"]),
        ({"rig": {"light_azimuth.backlash": -0.1}}, ["light_azimuth.backlash", ">= 0"]),
        ({"servos": {"landing_pulses": -1}}, ["landing_pulses"]),
        ({"servos": {"initial_approach": {"elbow": 1}}}, ["elbow"]),
        ({"camera": {"dist": [0.1]}}, ["dist"]),
        ({"colour": 1}, ["colour"]),
        ({"seed": -3}, ["seed"]),
    ],
)
def test_bad_world_tables_name_the_field(table, words, tmp_path):
    p = tmp_path / "world.toml"
    p.write_text(tomli_w.dumps({"world": table}))
    with pytest.raises(ConfigError) as exc:
        load_world(p)
    msg = str(exc.value)
    assert str(p) in msg
    for w in words:
        assert w in msg


def test_unreadable_world_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read the world"):
        load_world(tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("[world\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_world(tmp_path / "bad.toml")


def test_world_is_frozen_and_strict():
    w = draw_world("perfect")
    with pytest.raises(Exception):  # noqa: B017,PT011 - pydantic's frozen error
        w.seed = 3
    with pytest.raises(Exception):  # noqa: B017,PT011
        World.model_validate({"preset": "perfect", "extra": 1})


def test_fx_fy_different_cannot_be_rendered():
    cam = Camera(resolution=(64, 48), focal_length=0.035, fov_deg=26.0)
    w = draw_world("perfect", 0, {"camera": {"fx_scale": 0.01, "fy_scale": 0.0}})
    with pytest.raises(ConfigError, match="square pixels"):
        w.as_built_camera(cam)

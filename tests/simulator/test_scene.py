"""Scene files: schema, field-naming errors, ChArUco board geometry, spectra, rig poses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gonio.errors import ConfigError
from gonio.simulator.render import render
from gonio.simulator.scene import load_scene, look_at_rotation, parse_scene

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "scene.toml"

GOOD = """
[sample]
width = 0.05
height = 0.05
[sample.brdf]
model = "lambert+ggx"
params = { albedo = 0.5, ks = 0.2, alpha = 0.2 }
[[lights]]
type = "disk"
position = [0.0, 0.25, 0.43]
radius = 0.01
radiance = 100.0
[camera]
resolution = [32, 24]
fov_deg = 20
position = [0.0, -0.25, 0.43]
"""


def write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_example_scene_loads_and_renders():
    scene = load_scene(EXAMPLE)
    assert scene.camera.resolution == (640, 480)
    assert scene.lights[0].type == "disk" and scene.occluders[0].type == "cylinder"
    assert scene.build_brdf() is not None


def test_minimal_scene_defaults(tmp_path):
    scene = load_scene(write(tmp_path, GOOD))
    assert scene.holder is None and scene.render.strategy == "auto"
    assert scene.camera.sensor.cfa_pattern == "RGGB"
    assert np.allclose(
        scene.lights[0].emit_normal(), -np.array([0, 0.25, 0.43]) / np.hypot(0.25, 0.43)
    )


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("radius = 0.01", "radius = -0.01", "lights.0.disk.radius"),
        ("width = 0.05\nheight", "height", "sample.width"),
        ('type = "disk"', 'type = "laser"', "lights.0"),
        ("fov_deg = 20", "fov_deg = 20\npixel_pitch = 1e-5", "camera"),
        ("resolution = [32, 24]", "resolution = [32, 24]\nzoom = 2", "camera.zoom"),
        ("radiance = 100.0", 'radiance = "bright"', "lights.0.disk.radiance"),
    ],
)
def test_bad_fields_are_named(tmp_path, old, new, field):
    assert old in GOOD
    p = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        load_scene(p)
    assert f"field '{field}" in str(exc.value) and str(p) in str(exc.value)


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("radiance = 100.0", "radiance = nan", "lights.0.disk.radiance"),
        ("radiance = 100.0", "radiance = inf", "lights.0.disk.radiance"),
        ("radiance = 100.0", "radiance = [100.0, -1.0, 100.0]", "lights.0.disk.radiance"),
        ("radiance = 100.0", "radiance = -100.0", "lights.0.disk.radiance"),
        ("radius = 0.01", "radius = inf", "lights.0.disk.radius"),
        ("position = [0.0, 0.25, 0.43]", "position = [nan, 0.25, 0.43]", "lights.0.disk.position"),
        (
            "[camera]",
            "[holder]\nwidth = 0.15\nheight = 0.15\nalbedo_black = nan\n[camera]",
            "holder.albedo_black",
        ),
        (
            "[camera]",
            "[holder]\nwidth = 0.15\nheight = 0.15\nalbedo_white = 1.5\n[camera]",
            "holder.albedo_white",
        ),
    ],
)
def test_non_finite_negative_or_impossible_light_and_albedo_are_named(tmp_path, old, new, field):
    # They were accepted: `gonio sim render` wrote a DNG from NaN, infinite or negative
    # radiance (or a NaN holder albedo) and exited 0.
    assert old in GOOD
    p = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        load_scene(p)
    assert f"field '{field}" in str(exc.value) and str(p) in str(exc.value)


def test_unknown_brdf_model_names_the_field(tmp_path):
    scene = load_scene(write(tmp_path, GOOD.replace("lambert+ggx", "velvet")))
    with pytest.raises(ConfigError, match="sample.brdf"):
        scene.build_brdf()


def test_missing_measured_file_names_the_field(tmp_path):
    text = GOOD.replace(
        'model = "lambert+ggx"\nparams = { albedo = 0.5, ks = 0.2, alpha = 0.2 }',
        'file = "nope.bsdf"',
    )
    scene = load_scene(write(tmp_path, text))
    with pytest.raises(ConfigError, match=r"sample\.brdf\.file: .*nope\.bsdf"):
        scene.build_brdf()


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not a valid TOML"):
        load_scene(write(tmp_path, "[sample\nwidth = 1"))
    with pytest.raises(ConfigError, match="not found"):
        load_scene(tmp_path / "missing.toml")


def test_board_must_fit_holder(tmp_path):
    text = GOOD + "[holder]\nwidth = 0.1\nheight = 0.1\n[holder.board]\nsquares_x = 7\n"
    with pytest.raises(ConfigError, match="does not fit on the holder"):
        load_scene(write(tmp_path, text))


def test_look_at_rotation_is_opencv():
    R = look_at_rotation([0, 0, 1], [0, 0, 0], up=[0, 1, 0])
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
    assert np.allclose(R[2], [0, 0, -1])  # z forward
    assert np.allclose(R[1], [0, -1, 0])  # y down = -up


def test_charuco_board_in_render_gives_camera_pose():
    """The printed board is where the scene says: OpenCV finds the camera pose from it."""
    scene = load_scene(EXAMPLE)
    res = render(scene, tolerance=1e-3)
    img = res.radiance[..., 1]
    img8 = np.clip(img / np.percentile(img[res.region == 2], 95) * 200, 0, 255).astype(np.uint8)
    board = scene.holder.board.cv_board()
    det = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = det.detectBoard(img8)
    assert ids is not None and len(ids) >= 12
    obj, imgp = board.matchImagePoints(corners, ids)
    Rb, tb = scene.holder.board.board_to_sample()
    obj_s = obj.reshape(-1, 3) @ Rb.T + tb
    ok, rvec, tvec = cv2.solvePnP(obj_s, imgp.reshape(-1, 2), scene.camera.intrinsics(), None)
    assert ok
    C, R = scene.camera_pose()
    R_est = cv2.Rodrigues(rvec)[0]
    C_est = -R_est.T @ tvec.ravel()
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est @ R.T) - 1) / 2, -1, 1)))
    assert angle < 0.1 and np.linalg.norm(C_est - C) < 1e-3


def test_spectrum_light_is_integrated_against_camera_sensitivities(tmp_path):
    import colour

    csv = tmp_path / "flat.csv"
    csv.write_text("\n".join(f"{w},1.0" for w in range(300, 831, 10)))
    text = GOOD.replace("radiance = 100.0", 'radiance = { csv = "flat.csv", scale = 2.0 }')
    scene = load_scene(write(tmp_path, text))
    rgb = scene.light_rgb(scene.lights[0].radiance)
    cam = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    expected = 2.0 * np.trapezoid(cam.values, cam.wavelengths, axis=0)
    assert np.allclose(rgb, expected, rtol=1e-2)
    d65 = parse_scene(
        {
            **_dict(GOOD),
            "lights": [dict(type="point", position=[0, 0, 1], intensity={"illuminant": "D65"})],
        }
    )
    a = d65.light_rgb(d65.lights[0].intensity)
    assert a[2] / a[0] > 0.8  # D65 is bluish against a flat spectrum
    with pytest.raises(ConfigError, match="exactly one"):
        parse_scene(
            {
                **_dict(GOOD),
                "lights": [
                    dict(
                        type="point",
                        position=[0, 0, 1],
                        intensity={"illuminant": "D65", "blackbody": 5000},
                    )
                ],
            }
        )


def _dict(text):
    import tomllib

    return tomllib.loads(text)


def test_poses_from_rig_joint_angles(tmp_path):
    kin = pytest.importorskip("gonio.rig.kinematics")
    from gonio.rig.config import default_rig_config

    k = kin.Kinematics(default_rig_config())
    wi = np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    wo = np.array([-np.sin(0.4), 0.1, np.cos(0.4)])
    wo /= np.linalg.norm(wo)
    joints = k.inverse(wi, wo)
    poses = k.poses(joints)
    text = GOOD.replace("position = [0.0, -0.25, 0.43]\n", "")
    text += (
        "[rig]\njoints_deg = { "
        + ", ".join(f"{n} = {float(np.degrees(v))!r}" for n, v in joints.items())
        + " }\n"
    )
    path = write(tmp_path, text)
    with pytest.raises(
        ConfigError, match="camera.position"
    ):  # the simulator alone has no kinematics
        load_scene(path).camera_pose()
    from gonio.app.scenes import load_scene as load_with_rig

    scene = load_with_rig(path)
    C, R = scene.camera_pose()
    assert np.allclose(C, poses.camera_position) and np.allclose(R, poses.camera_rotation.T)
    assert np.allclose(scene.lights[0].position, poses.light_position)
    res = render(
        scene.model_copy(update={"render": scene.render.model_copy(update={"tolerance": 1e-3})})
    )
    centre = res.wo[12, 16]
    assert np.degrees(np.arccos(np.clip(centre @ wo, -1, 1))) < 0.5


# --- issue 14.6 / 14.8: exposure bounds and albedo maps that cannot be loaded -----------


@pytest.mark.parametrize("value", ["1e308", "inf", "nan", "3600.5"])
def test_scene_exposure_time_is_finite_and_at_most_an_hour(tmp_path, value):
    p = write(tmp_path, GOOD.replace("fov_deg = 20", f"fov_deg = 20\nexposure_time = {value}"))
    with pytest.raises(ConfigError) as exc:
        load_scene(p)
    assert "field 'camera.exposure_time'" in str(exc.value) and str(p) in str(exc.value)
    ok = write(tmp_path, GOOD.replace("fov_deg = 20", "fov_deg = 20\nexposure_time = 3600"))
    assert load_scene(ok).camera.exposure_time == 3600.0


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda p: np.save(p, np.array([{"x": 1}], dtype=object), allow_pickle=True),
         "holds Python objects"),
        (lambda p: np.save(p, np.array(["a", "b"])), "not a numeric .npy array"),
        (lambda p: p.write_bytes(b"\x93NUMPY garbage"), "not a numeric .npy array"),
    ],
)  # fmt: skip
def test_albedo_map_that_cannot_be_loaded_names_file_and_field(tmp_path, make, match):
    npy = tmp_path / "albedo.npy"
    make(npy)
    p = write(
        tmp_path, GOOD.replace("height = 0.05\n", "height = 0.05\nalbedo_map = 'albedo.npy'\n", 1)
    )
    scene = load_scene(p)
    with pytest.raises(ConfigError) as exc:
        render(scene)
    msg = str(exc.value)
    assert msg.startswith("sample.albedo_map: ") and str(npy) in msg and match in msg


def test_a_board_of_more_markers_than_its_dictionary_is_named(tmp_path):
    # OpenCV builds such a board (repeating marker IDs), and a huge one for minutes.
    text = GOOD + "[holder]\nwidth = 0.15\nheight = 0.15\n[holder.board]\nsquares_x = 100000\n"
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_scene(p)
    assert "field 'holder.board'" in str(exc.value) and "more than the 50 of DICT_4X4_50" in str(
        exc.value
    )

"""The mirror target: the light's image in a flat mirror against the law of reflection."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.errors import CameraError
from gonio.simulator.render import HOLDER, SAMPLE, render
from gonio.simulator.rig_camera import SimulatedRigCamera, minimal_scene
from gonio.simulator.scene import look_at_rotation, parse_scene

DIST = (-0.15, 0.02, 0.001, -0.001, 0.0)
RADIANCE = 10.0


def mirror_scene(light, camera_look_at, light_kind="disk", dist=DIST, spot_antialias=16):
    d = minimal_scene(320, 240)
    lt = d["lights"][0]
    lt["position"] = list(light)
    lt["radiance"] = [RADIANCE, 2 * RADIANCE, 3 * RADIANCE]
    if light_kind == "rectangle":
        del lt["radius"]
        lt.update(type="rectangle", width=0.02, height=0.012, up=[0.3, 0.0, 1.0])
    cam = d["camera"]
    cam["look_at"] = list(camera_look_at)
    cam["distortion"] = list(dist)
    cam["principal_point"] = [163.2, 118.9]
    d["render"].update(antialias=4, spot_antialias=spot_antialias)
    return parse_scene(d)


# light position, camera look-at: the spot away from the image centre, where distortion acts
POSES = [
    ((0.01, 0.24, 0.44), (0.01, 0.004, 0.0), "disk"),
    ((-0.02, 0.26, 0.42), (-0.012, -0.006, 0.0), "disk"),
    ((0.013, 0.2537, 0.431), (0.0, 0.015, 0.0), "rectangle"),
]


def mirrored_centre_projection(scene):
    """The closed form: the image of a point in a flat mirror is the projection of its
    reflection, here through OpenCV's camera model (pixel centres at integers)."""
    cam = scene.camera
    C = np.asarray(cam.position)
    R = look_at_rotation(C, cam.look_at, cam.up)
    K = cam.intrinsics()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    L = np.asarray(scene.lights[0].position) * (1.0, 1.0, -1.0)
    rvec, _ = cv2.Rodrigues(R)
    img, _ = cv2.projectPoints(L[None], rvec, -R @ C, K, np.asarray(cam.distortion))
    return img.reshape(2)


def spot_centroid(result):
    """Intensity-weighted centroid (OpenCV pixel convention) of the spot, measured in a
    window around its bright pixels so that the lit holder does not count."""
    L = result.radiance[..., 1]
    on = (result.region == SAMPLE) & (L > 0.5 * L.max())
    jj, ii = np.nonzero(on)
    win = np.zeros_like(on)
    win[jj.min() - 2 : jj.max() + 3, ii.min() - 2 : ii.max() + 3] = True
    w = np.where(win & (result.region == SAMPLE), L, 0.0)
    v, u = np.mgrid[0 : L.shape[0], 0 : L.shape[1]]
    return np.array([(w * u).sum(), (w * v).sum()]) / w.sum(), on.sum()


def test_spot_centroid_is_the_image_of_the_mirrored_light_centre():
    for light, look, kind in POSES:
        scene = mirror_scene(light, look, kind).with_mirror_target()
        c, n = spot_centroid(render(scene))
        ref = mirrored_centre_projection(scene)
        err = np.hypot(*(c - ref))
        print(f"{kind} {light}: spot of {n} px at {c}, closed form {ref}, off by {err:.4f} px")
        assert n > 50  # a spot of some size, not a pixel
        assert np.hypot(*(ref - [159.5, 119.5])) > 5  # off the image centre
        assert err < 0.02


def test_without_rim_antialiasing_the_centroid_is_biased():
    # The rim's sub-rays are what make the centroid unbiased: one ray per pixel is not.
    errs = []
    for light, look, kind in POSES:
        scene = mirror_scene(light, look, kind, spot_antialias=1).with_mirror_target()
        c, _ = spot_centroid(render(scene))
        errs.append(np.hypot(*(c - mirrored_centre_projection(scene))))
    assert max(errs) > 0.02


def test_spot_radiance_is_the_reflectance_times_the_emitted_radiance():
    light, look, _ = POSES[0]
    scene = mirror_scene(light, look)
    res = render(scene.with_mirror_target(0.9))
    on_mirror = (res.region == SAMPLE) & ~res.edge
    values = res.radiance[on_mirror]
    lit = values[:, 1] > 0
    expected = 0.9 * RADIANCE * np.array([1.0, 2.0, 3.0])
    assert lit.sum() > 50
    assert np.array_equal(values[lit], np.broadcast_to(expected, values[lit].shape))
    assert np.all(values[~lit] == 0.0)  # the mirror elsewhere reflects the dark room
    # the rest of the holder renders as with the sample in place
    ref = render(scene)
    holder = (res.region == HOLDER) & ~res.edge & ~ref.edge
    assert holder.sum() > 1000
    assert np.array_equal(res.radiance[holder], ref.radiance[holder])


@pytest.mark.parametrize(
    "change",
    [
        {"type": "point", "intensity": 1.0},  # no area: invisible in a mirror
        {"normal": [0.0, -0.5, 0.866]},  # emits away from the mirror (one-sided)
    ],
)
def test_no_spot_from_a_point_light_or_the_back_of_a_light(change):
    light, look, _ = POSES[0]
    d = minimal_scene(320, 240)
    lt = d["lights"][0]
    lt.update(position=list(light), **change)
    if change.get("type") == "point":
        for k in ("radius", "look_at", "radiance"):
            lt.pop(k)
    else:
        lt.pop("look_at")
    d["camera"]["look_at"] = list(look)
    res = render(parse_scene(d).with_mirror_target())
    assert np.all(res.radiance[res.region == SAMPLE] == 0.0)


def test_an_occluder_between_mirror_and_light_hides_the_spot():
    light, look, _ = POSES[0]
    d = minimal_scene(320, 240)
    d["lights"][0]["position"] = list(light)
    d["camera"]["look_at"] = list(look)
    mid = (np.asarray(light) / 2).tolist()
    d["occluders"] = [{"type": "box", "center": mid, "size": [0.06, 0.06, 0.01]}]
    res = render(parse_scene(d).with_mirror_target())
    assert np.all(res.radiance[res.region == SAMPLE] == 0.0)
    del d["occluders"]
    assert render(parse_scene(d).with_mirror_target()).radiance[..., 1].max() > 0


def rig_camera(serial=None, radiance=RADIANCE):
    light, look, _ = POSES[0]
    scene = mirror_scene(light, look)
    cam = scene.camera
    poses = {
        "camera_position": np.asarray(cam.position),
        "camera_rotation": look_at_rotation(cam.position, cam.look_at, cam.up).T,
        "light_position": np.asarray(light),
        "light_normal": -np.asarray(light) / np.linalg.norm(light),
    }
    return SimulatedRigCamera(scene, lambda: poses, seed=5, serial=serial), scene


def spot_electrons_per_second(scene, f_number):
    """Closed form: E = L pi / (4 N^2) cos^4, electrons = E A t lambda / (h c) QE (green)."""
    s = scene.camera.sensor
    L = 0.9 * 2 * RADIANCE  # green channel of the spot
    K = scene.camera.intrinsics()
    ref = mirrored_centre_projection(scene)
    r2 = ((ref[0] + 0.5 - K[0, 2]) ** 2 + (ref[1] + 0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2
    E = L * np.pi / (4 * f_number**2) / (1 + r2) ** 2
    photons = E * scene.camera.pitch**2 * 540e-9 / (6.62607015e-34 * 299792458.0)
    return photons * s.quantum_efficiency[1]


def test_rig_camera_shoots_the_mirror_and_the_exposure_it_needs():
    from gonio.capture.raw import read_raw

    cam, scene = rig_camera()
    cam.set_target("mirror")
    rate = spot_electrons_per_second(scene, 8.0)
    t_sat = scene.camera.sensor.full_well / rate
    print(f"spot of 0.9 x {2 * RADIANCE} W/(sr m^2) fills the well in {t_sat:.3g} s at f/8")
    white = scene.camera.sensor.white_level
    # the plan's default first exposure (10 ms) clips the spot ...
    shot = cam.capture(0.01, 100, 8.0)
    assert shot.extra["target"] == "mirror"
    assert (read_raw(shot.data).raw == white).sum() > 50
    # ... a quarter of the saturating time keeps every pixel below the white level
    raw = read_raw(cam.capture(0.25 * t_sat, 100, 8.0).data).raw
    assert raw.max() < white
    assert raw.max() > scene.camera.sensor.black_level + 0.1 * (white - 512)
    with pytest.raises(CameraError, match="mirror"):
        cam.set_target("glass")


def test_rig_camera_reports_its_serial():
    cam, _ = rig_camera(serial="SIM-0042")
    info = cam.describe()
    assert info.serial == "SIM-0042"
    assert info.to_json()["serial"] == "SIM-0042"
    # a camera without one writes the manifest it always wrote
    assert "serial" not in rig_camera()[0].describe().to_json()

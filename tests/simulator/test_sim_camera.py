"""SimulatedCamera: DNG captures at the pose the rig reports, reference shots, the CLI."""

from __future__ import annotations

import io
from pathlib import Path

import h5py
import numpy as np
import pytest
import rawpy

from gonio.cli import main
from gonio.errors import CameraError
from gonio.radiometry.emitters import irradiance_disk
from gonio.simulator.camera import SimulatedCamera
from gonio.simulator.scene import look_at_rotation, parse_scene
from gonio.simulator.sensor import cfa_indices

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "scene.toml"


def small_scene():
    return parse_scene(
        dict(
            sample=dict(
                width=0.06,
                height=0.06,
                brdf=dict(model="lambert+ggx", params={"albedo": 0.4, "ks": 0.2, "alpha": 0.3}),
            ),
            holder=dict(width=0.2, height=0.2, board=None),
            lights=[
                dict(
                    type="disk",
                    position=[0, 0.25, 0.433],
                    look_at=[0, 0, 0],
                    radius=0.01,
                    radiance=50.0,
                )
            ],
            camera=dict(
                resolution=[48, 32],
                focal_length=0.016,
                pixel_pitch=4e-5,
                position=[0, -0.3, 0.4],
                look_at=[0, 0, 0],
                up=[0, 1, 0],
            ),
            render=dict(tolerance=1e-4),
        )
    )


class Poses:
    """Stands in for the rig: camera on a circle, wired the way RigPoses is."""

    def __init__(self, angle_deg=30.0):
        self.angle = angle_deg

    def __call__(self):
        a = np.radians(self.angle)
        c = 0.5 * np.array([0, -np.sin(a), np.cos(a)])
        return {
            "camera_position": c,
            "camera_rotation": look_at_rotation(c, [0, 0, 0], [0, 1, 0]).T,
            "light_position": np.array([0, 0.25, 0.433]),
            "light_normal": -np.array([0, 0.25, 0.433]) / 0.5,
        }


def test_capture_is_a_dng_whose_mean_matches_the_radiance():
    cam = SimulatedCamera(small_scene())
    data, truth = cam.capture(0.02, 200, 8.0, seed=1, return_truth=True)
    with rawpy.imread(io.BytesIO(data)) as raw:
        mosaic = raw.raw_image_visible.astype(float)
        assert raw.other.iso_speed == 200
    s = cam.scene.camera.sensor
    # Expected DN from radiance, by hand: E = L pi / (4 N^2) cos^4, photons, QE, gain.
    K = cam.scene.camera.intrinsics()
    v, u = np.mgrid[0:32, 0:48]
    cos4 = np.cos(np.arctan(np.hypot(u + 0.5 - K[0, 2], v + 0.5 - K[1, 2]) / K[0, 0])) ** 4
    idx = cfa_indices("RGGB", (32, 48))
    L = np.take_along_axis(truth.radiance, idx[..., None], 2)[..., 0]
    lam = np.array(s.wavelength_nm)[idx] * 1e-9
    qe = np.array(s.quantum_efficiency)[idx]
    e = L * np.pi / 256 * cos4 * (4e-5) ** 2 * 0.02 * lam / (6.62607015e-34 * 299792458) * qe
    e += s.dark_current * 0.02
    dn = s.black_level + e * s.gain_at_base_iso * 2
    m = truth.region > 0
    assert dn[m].max() < s.white_level  # no clipping in the comparison
    resid = (mosaic - dn)[m] / np.sqrt((s.gain_at_base_iso * 2) ** 2 * (e[m] + s.read_noise**2) + 1)
    assert abs(resid.mean()) < 4 / np.sqrt(m.sum()) and 0.8 < resid.std() < 1.2


def test_same_seed_same_bytes_and_render_is_cached():
    cam = SimulatedCamera(small_scene())
    a = cam.capture(0.01, 100, 8.0, seed=4)
    b = cam.capture(0.01, 100, 8.0, seed=4)
    c = cam.capture(0.04, 100, 8.0, seed=5)
    assert a == b and a != c
    assert cam.renders == 1  # a bracket at one pose renders once


def test_pose_provider_moves_the_camera():
    poses = Poses(30.0)
    cam = SimulatedCamera(small_scene(), pose_provider=poses)
    _, t1 = cam.capture(0.01, 100, 8.0, seed=1, return_truth=True)
    C = poses()["camera_position"]
    centre = t1.wo[16, 24]
    assert np.allclose(centre, C / np.linalg.norm(C), atol=0.02)
    poses.angle = 50.0
    _, t2 = cam.capture(0.01, 100, 8.0, seed=1, return_truth=True)
    assert cam.renders == 2
    assert np.degrees(np.arccos(t2.wo[16, 24] @ centre)) == pytest.approx(20, abs=1.5)


def test_camera_that_does_not_see_the_sample_raises():
    def away():
        c = np.array([0, -0.3, 0.4])
        return {
            "camera_position": c,
            "camera_rotation": look_at_rotation(c, [0, 2, 3]).T,
            "light_position": None,
            "light_normal": None,
        }

    cam = SimulatedCamera(small_scene(), pose_provider=away)
    with pytest.raises(CameraError, match="does not see the sample"):
        cam.capture(0.01, 100, 8.0, seed=1)


def test_reference_target_is_lambertian_with_its_albedo():
    cam = SimulatedCamera(small_scene(), reference_albedo=0.99)
    _, truth = cam.capture(0.01, 100, 8.0, seed=1, target="reference", return_truth=True)
    m = (truth.region == 1) & ~truth.edge
    p = truth.points[m]
    n = -np.array([0, 0.25, 0.433])
    E = irradiance_disk(p, [0, 0, 1], [0, 0.25, 0.433], n, 0.01, 50.0)
    assert np.allclose(truth.radiance[m][:, 1], 0.99 / np.pi * E, rtol=1e-6)
    _, sample = cam.capture(0.01, 100, 8.0, seed=1, return_truth=True)
    assert not np.allclose(sample.radiance[m], truth.radiance[m])


def test_cli_render_writes_dng_and_truth(tmp_path, capsys):
    out, truth = tmp_path / "shot.dng", tmp_path / "shot.h5"
    main(
        [
            "sim",
            "render",
            str(EXAMPLE),
            "--out",
            str(out),
            "--truth",
            str(truth),
            "--seed",
            "2",
            "--tolerance",
            "1e-3",
        ]
    )
    with rawpy.imread(str(out)) as raw:
        assert raw.raw_image_visible.shape == (480, 640)
    with h5py.File(truth) as f:
        assert f["radiance"].shape == (480, 640, 3) and f["wi"].shape == (480, 640, 3)
        assert set(np.unique(f["region"][()])) >= {0, 1, 2, 3}
    # An existing output is not overwritten; the CLI exits non-zero naming the file.
    before = out.read_bytes()
    with pytest.raises(SystemExit) as exc:
        main(["sim", "render", str(EXAMPLE), "--out", str(out), "--seed", "3"])
    assert exc.value.code == 1 and "refusing to overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before


def test_cli_bad_scene_names_the_field(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.read_text().replace("radius = 0.01", "radius = -1.0"))
    with pytest.raises(SystemExit) as exc:
        main(["sim", "render", str(bad), "--out", str(tmp_path / "x.dng")])
    err = capsys.readouterr().err
    assert exc.value.code == 1 and "lights.0.disk.radius" in err
    assert not (tmp_path / "x.dng").exists()

"""Reduction accuracy on the simulated rig: reduced BRDF against the simulator's truth.

Each pose is rendered by :class:`gonio.simulator.camera.SimulatedCamera` at the rig's
kinematic pose, exposed as a two-frame bracket of noisy DNGs (shot + read noise,
quantisation, clipping), decoded by rawpy and reduced by the capture path: board -> camera
pose -> regions -> HDR merge -> calibration against rendered reference-target shots.

Two references:
- the BRDF model itself at the directions the reduction reports (must agree to 1 %
  median): this checks the physics and the geometry;
- the simulator's noise-free radiance over exactly the pixels of each region, divided by
  the light's irradiance there (exact disk formula, true surface points): the noise-free
  answer for those pixels, against which ``(f - truth) / std`` must be standard normal.

The analytic materials need nothing but the simulator; only the measured (RGL) material
needs the shared reference data, so only its test asks for ``rgl_file``.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.pose_measure import measure_pose
from gonio.capture.radiometric import brdf_of, light_scale
from gonio.capture.raw import read_raw
from gonio.radiometry import spherical_to_direction
from gonio.radiometry.emitters import irradiance_disk

pytestmark = pytest.mark.slow

LIGHT = {
    "type": "disk",
    "position": [0.0, 0.25, 0.433],
    "look_at": [0, 0, 0],
    "radius": 0.01,
    "radiance": [2e4, 2e4, 2e4],
}
SAMPLE_POSES = [
    (20, 0, 20, 180),
    (40, 0, 40, 180),
    (30, 0, 50, 180),
    (45, 90, 30, 270),
    (10, 0, 60, 180),
]
REFERENCE_POSES = [(0, 0, 30, 180), (30, 0, 30, 180)]
FULL_WELL_DN = 15871.0  # 14-bit white 16383 minus black 512


def scene_doc(brdf):
    return {
        "sample": {"width": 0.05, "height": 0.05, "brdf": brdf},
        "holder": {"width": 0.16, "height": 0.16, "board": {}},
        "lights": [LIGHT],
        "camera": {
            "resolution": [400, 300],
            "focal_length": 0.016,
            "fov_deg": 30.0,
            "position": [0.1, -0.2, 0.35],
            "look_at": [0, 0, 0],
        },
        # 4-node quadrature over the disk: the point approximation would be off by
        # (r/d)^2 = 4e-4, a third of the noise, in the reference as in the truth
        "render": {"strategy": "quadrature", "quadrature_order": 1},
    }


class Rig:
    """Kinematic poses of the default rig, fed to the simulated camera."""

    def __init__(self):
        from gonio.rig.config import default_rig_config
        from gonio.rig.kinematics import Kinematics

        self.kin = Kinematics(default_rig_config())
        self.poses = None

    def go(self, ti, pi, to, po):
        wi = spherical_to_direction(np.radians(ti), np.radians(pi))
        wo = spherical_to_direction(np.radians(to), np.radians(po))
        self.poses = self.kin.poses(self.kin.inverse(wi, wo))
        return self.poses


def shoot_and_measure(cam, rig, setup, target, k, pose):
    """Render, expose a bracket (t, 4 t) and measure the pose; also return the truth."""
    from gonio.simulator.sensor import mean_electrons

    rp = rig.go(*pose)
    truth = cam.render(target)
    e_per_s = mean_electrons(truth.radiance, cam.scene.camera, 1.0, 8.0)
    gain = cam.scene.camera.sensor.gain_at_base_iso
    t = 0.5 * FULL_WELL_DN / gain / e_per_s[truth.region == 1].max()
    frames = [
        read_raw(
            cam.capture(tt, 100, 8.0, seed=100 * k + j, target=target), name=f"{target}{k}_{j}"
        )
        for j, tt in enumerate((t, 4 * t))
    ]
    m = measure_pose(
        frames,
        setup,
        rp.light_position,
        rp.light_normal,
        pose=k,
        kind=target,
        reported_wo=rp.wo,
        reported_camera=(rp.camera_position, rp.camera_rotation.T),
    )
    return m, truth, rp, frames[0].channel


@pytest.fixture(scope="module")
def rig():
    return Rig()


@pytest.fixture(scope="module")
def light_in_camera_units(rig):
    """The reference target is the same for every sample: shoot it once."""
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(scene_doc({"model": "lambert", "params": {"albedo": 0.5}}))
    setup = setup_from_scene(scene, 0.99)
    cam = SimulatedCamera(scene, pose_provider=lambda: rig.poses, reference_albedo=0.99)
    refs = [
        shoot_and_measure(cam, rig, setup, "reference", 50 + k, p)[0]
        for k, p in enumerate(REFERENCE_POSES)
    ]
    assert all((r.flags == 0).all() for r in refs)
    return light_scale(refs, setup)


def reduce_material(brdf, rig, light):
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(scene_doc(brdf))
    setup = setup_from_scene(scene, 0.99)
    cam = SimulatedCamera(scene, pose_provider=lambda: rig.poses)
    model = scene.build_brdf()
    I, I_var = light
    Le = np.asarray(LIGHT["radiance"], float)
    got, std, truth_px, truth_model = [], [], [], []
    for k, pose in enumerate(SAMPLE_POSES):
        m, truth, rp, _ = shoot_and_measure(cam, rig, setup, "sample", k, pose)
        assert (m.flags == 0).all(), m.reasons
        f, s, _, _ = brdf_of(m, I, I_var)
        box, lab = m.regions.box, m.regions.label
        rad, pts = truth.radiance[box], truth.points[box]
        tp = np.empty_like(f)
        for j in range(m.regions.n_regions):
            for c in range(3):
                # every pixel of the region, whatever its filter: the reduction reports
                # each channel at the region's pixel centroid (its directions), not at
                # that channel's own CFA sites half a pixel away
                px = lab == j
                G = irradiance_disk(
                    pts[px],
                    [0, 0, 1],
                    rp.light_position,
                    rp.light_normal,
                    LIGHT["radius"],
                    1.0,
                    n_nodes=64,
                )
                tp[j, c] = rad[px, c].mean() / (Le[c] * G.mean())
        got.append(f)
        std.append(s)
        truth_px.append(tp)
        truth_model.append(model.eval(m.wi, m.wo))
    return tuple(np.concatenate(x) for x in (got, std, truth_px, truth_model))


def check_against_truth(name, brdf, rig, light):
    f, s, truth_px, truth_model = reduce_material(brdf, rig, light)
    rel = np.abs(f / truth_model - 1)
    z = (f - truth_px) / s
    print(
        f"{name}: median rel err {np.median(rel):.2e} (max {rel.max():.2e}), "
        f"z mean {z.mean():+.3f} std {z.std():.3f} over {z.size}, "
        f"median rel std {np.median(s / f):.2e}"
    )
    assert np.median(rel) <= 0.01
    # 135 z-scores: the standard deviation of their std is ~6 %
    assert 0.8 <= z.std() <= 1.25
    assert abs(z.mean()) < 0.35


@pytest.mark.parametrize(
    "material",
    [
        {"model": "lambert", "params": {"albedo": [0.6, 0.5, 0.4]}},
        {"model": "ggx", "params": {"alpha": 0.2, "ks": [0.8, 0.8, 0.8]}},
    ],
    ids=["lambert", "ggx"],
)
def test_reduced_brdf_matches_truth_with_calibrated_errors(material, rig, light_in_camera_units):
    check_against_truth(material["model"], material, rig, light_in_camera_units)


def test_reduced_measured_brdf_matches_truth_with_calibrated_errors(
    rig, light_in_camera_units, rgl_file
):
    brdf = {"file": str(rgl_file("paper_white"))}
    check_against_truth("rgl paper_white", brdf, rig, light_in_camera_units)

"""Grazing angles, 85 to 89.9 deg, through the reduction's numerics and the fitter.

The rig itself stops at 85 deg (the holder's rim), so the poses here are placed
directly: the simulated camera renders the sample at a camera and a light put at the
swept angles (the light 0.5 m away, the camera 0.4 m), a two-frame bracket is exposed
and :func:`gonio.capture.pose_measure.measure_pose` reduces it with the exact camera
pose (``geometry = "rig"``); :func:`gonio.capture.radiometric.brdf_of` turns it into BRDF
with the light's scale from a reference-target shot.  Every region must come out either
finite (directions unit and above the horizon, irradiance > 0, BRDF and its std finite)
and within a few percent of the simulator's BRDF at the reported directions -- a
silently clipped irradiance or direction would show there -- or flagged with a reason.
Where the light's disk reaches below the horizon (theta_i 89.9 deg: 0.1 deg above it,
less than the 2 mm disk's 0.24 deg angular radius at 0.475 m) the regions must be
flagged SHADOWED; at 89.5 deg (0.5 deg above) they must not.

The fitter is then given samples that include grazing ones (the closed-form model plus
1 % noise, both directions swept to 89.9 deg): the fit succeeds, nothing in it is NaN or
inf, and the parameters are the truth within 4 reported sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.pose_measure import measure_pose
from gonio.capture.radiometric import brdf_of, light_scale
from gonio.capture.raw import read_raw
from gonio.dataset import BRDFSamples, Flag
from gonio.radiometry import look_at_rotation, spherical_to_direction

pytestmark = pytest.mark.slow

GRAZING = [85.0, 87.0, 89.0, 89.5, 89.9]
LIGHT_M, CAMERA_M = 0.5, 0.4
RADIUS = 0.002
FULL_WELL_DN = 15871.0
MATERIAL = {"albedo": [0.5, 0.4, 0.3], "ks": [0.2, 0.2, 0.2], "alpha": [0.2, 0.2, 0.2]}


def scene_doc(brdf):
    return {
        "sample": {"width": 0.05, "height": 0.05, "brdf": brdf},
        "holder": {"width": 0.15, "height": 0.15, "board": {}},
        "lights": [
            {
                "type": "disk",
                "position": [0.0, 0.25, 0.433],
                "look_at": [0, 0, 0],
                "radius": RADIUS,
                "radiance": [4e5, 4e5, 4e5],
            }
        ],
        "camera": {
            "resolution": [480, 360],
            "focal_length": 0.035,
            "fov_deg": 30.0,
            "position": [0.0, -0.25, 0.433],
            "look_at": [0, 0, 0],
        },
        "render": {"strategy": "quadrature", "quadrature_order": 1},
    }


def place(theta_i, theta_o, phi_o=180.0):
    """Rig-like poses (the fields of gonio.rig.kinematics.RigPoses) at any angle."""
    lp = LIGHT_M * spherical_to_direction(math.radians(theta_i), 0.0)
    cp = CAMERA_M * spherical_to_direction(math.radians(theta_o), math.radians(phi_o))
    w2c = look_at_rotation(cp, np.zeros(3))
    return {
        "light_position": lp,
        "light_normal": -lp / np.linalg.norm(lp),
        "camera_position": cp,
        "camera_rotation": w2c.T,  # camera to sample frame, as the rig reports it
        "wi": lp / np.linalg.norm(lp),
        "wo": cp / np.linalg.norm(cp),
    }


class World:
    def __init__(self, brdf, reference_albedo=0.99):
        from gonio.simulator.camera import SimulatedCamera
        from gonio.simulator.scene import parse_scene

        self.scene = parse_scene(scene_doc(brdf))
        self.pose = None
        self.cam = SimulatedCamera(
            self.scene, pose_provider=lambda: self.pose, reference_albedo=reference_albedo
        )
        self.setup = setup_from_scene(self.scene, 0.99).replace(
            grid=3, geometry="rig", geometry_tolerance_deg=5.0, position_tolerance_m=0.05
        )

    def measure(self, pose, target="sample", k=0):
        from gonio.simulator.sensor import mean_electrons

        self.pose = pose
        truth = self.cam.render(target)
        e_per_s = mean_electrons(truth.radiance, self.scene.camera, 1.0, 8.0)
        lit = e_per_s[truth.region == 1]
        gain = self.scene.camera.sensor.gain_at_base_iso
        # half the full well at the brightest sample pixel (the camera's longest exposure
        # where no pixel of the sample is seen)
        t = 0.5 * FULL_WELL_DN / gain / float(lit.max()) if lit.size else 900.0
        t = min(t, 900.0)
        frames = [
            read_raw(
                self.cam.capture(tt, 100, 8.0, seed=10 * k + j, target=target), name=f"f{k}{j}"
            )
            for j, tt in enumerate((t, 4 * t))
        ]
        return measure_pose(
            frames,
            self.setup,
            pose["light_position"],
            pose["light_normal"],
            pose=k,
            kind=target,
            reported_wo=pose["wo"],
            reported_camera=(pose["camera_position"], pose["camera_rotation"].T),
        )


@pytest.fixture(scope="module")
def sweep():
    brdf = {"model": "lambert+ggx", "params": MATERIAL}
    world = World(brdf)
    ref = world.measure(place(0.0, 30.0), "reference", 99)
    assert (ref.flags == 0).all(), ref.reasons
    I, I_var = light_scale([ref], world.setup)
    poses = [(ti, 30.0) for ti in GRAZING] + [(30.0, to) for to in GRAZING] + [(89.9, 89.9)]
    out = []
    for k, (ti, to) in enumerate(poses):
        m = world.measure(place(ti, to), "sample", k)
        out.append(((ti, to), m, *brdf_of(m, I, I_var)))
    return world, out


def test_every_grazing_region_is_finite_and_right_or_flagged_with_a_reason(sweep):
    world, out = sweep
    model = world.scene.build_brdf()
    kept = {}
    for (ti, to), m, f, f_std, E, _ in out:
        ok = m.flags == 0
        kept[(ti, to)] = int(ok.sum())
        for j in np.flatnonzero(~ok):
            assert m.reasons[j], ((ti, to), j)  # never flagged without saying why
        bad = ~(np.isfinite(f).all(1) & np.isfinite(f_std).all(1) & (E > 0).all(1))
        assert not (bad & ok).any(), ((ti, to), m.reasons)
        if not ok.any():
            continue
        for w in (m.wi[ok], m.wo[ok]):
            assert np.isfinite(w).all()
            np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, rtol=0, atol=1e-12)
            assert (w[:, 2] > 0).all()
        assert (f_std[ok] > 0).all()
        truth = model.eval(m.wi[ok], m.wo[ok])
        rel = f[ok] / truth - 1
        print(f"theta_i {ti}, theta_o {to}: {ok.sum()} kept, |rel err| max {np.abs(rel).max():.3g}")
        # a few percent: the region's mean over its spread of directions, the disk's
        # size and the noise (~1 %); a clipped irradiance or direction is far beyond
        assert np.abs(rel).max() < 0.05, ((ti, to), rel)
    print(kept)
    # the light's side: measured to 89.5 deg, its disk across the horizon at 89.9 flagged
    for ti in GRAZING[:-1]:
        assert kept[(ti, 30.0)] == 9, (ti, kept)
    by = {pose: m for pose, m, *_ in out}
    shadowed = by[(89.9, 30.0)].flags & Flag.SHADOWED
    assert shadowed.all() and any("horizon" in r for r in by[(89.9, 30.0)].reasons[0])
    assert not (by[(89.5, 30.0)].flags & Flag.SHADOWED).any()
    # the camera's side: regions without pixels (a 1 cm region is 1.3 px high at
    # 87 deg here) are refused as such, never reported as numbers
    assert kept[(30.0, 85.0)] > 0
    for to in GRAZING:
        m = by[(30.0, to)]
        for j in np.flatnonzero(m.flags != 0):
            assert m.flags[j] & (Flag.INVALID | Flag.UNDEREXPOSED | Flag.SATURATED)


def test_the_fit_with_grazing_samples_is_finite_and_recovers_the_truth():
    from gonio.brdf import get_model
    from gonio.fitting import fit

    rng = np.random.default_rng(16)
    n = 300
    g = np.tile(GRAZING, 30)
    ti = np.concatenate([rng.uniform(0, 80, n), g, rng.uniform(0, 60, g.size), g])
    to = np.concatenate([rng.uniform(0, 80, n), rng.uniform(0, 60, g.size), g, g[::-1]])
    wi = spherical_to_direction(np.radians(ti), np.zeros_like(ti))
    wo = spherical_to_direction(np.radians(to), rng.uniform(0, 2 * np.pi, ti.size))
    for spec, params in (
        ("lambert+ggx", MATERIAL),
        ("lambert+ggx[fresnel=schlick]", None),
    ):
        if params is None:
            base = get_model("lambert+ggx", fresnel="schlick")
            params = {k: [float(v)] * 3 for k, v in base.defaults.items()}
            params["albedo"] = MATERIAL["albedo"]
        else:
            base = get_model(spec)
        truth = base.bind({k: np.asarray(v, float) for k, v in params.items()})
        f = truth.eval(wi, wo)
        assert np.isfinite(f).all()
        std = 0.01 * f
        samples = BRDFSamples(wi, wo, f + std * rng.standard_normal(f.shape), std)
        with np.errstate(all="raise"):  # no overflow, 0/0 or invalid value anywhere
            r = fit(samples, model=spec, absolute_sigma=True)
        assert r.success, r.message
        assert math.isfinite(r.cost)
        assert not r.diagnostics.get("dropped"), r.diagnostics.get("dropped")
        pred = r.bind().eval(wi, wo)
        assert np.isfinite(pred).all()
        for k, tv in params.items():
            v, s = np.asarray(r.params[k], float), np.asarray(r.std[k], float)
            assert np.isfinite(v).all() and np.isfinite(s).all() and (s > 0).all(), (k, s)
            z = (v - np.asarray(tv, float)) / s
            print(spec, k, v, s, z)
            assert np.all(np.abs(z) < 4.0), (spec, k, v, s, z)

"""The camera in an as-built world: drift over rig time, ambient and stray light, dark
frames, flats, PRNU, DSNU and hot pixels -- against closed forms and sampling errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.errors import CameraError
from gonio.simulator.camera import SimulatedCamera
from gonio.simulator.rig_camera import SimulatedRigCamera
from gonio.simulator.scene import look_at_rotation, parse_scene
from gonio.simulator.sensor import cfa_indices, default_flat_radiance, simulate_raw
from gonio.simulator.sensor_defects import fixed_pattern
from gonio.simulator.world import Radiometry, draw_world

_HC = 6.62607015e-34 * 299792458.0
LIGHT = np.array([0.0, 0.25, 0.433])


def scene_doc(w=48, h=32, **sensor):
    return dict(
        sample=dict(
            width=0.06,
            height=0.06,
            brdf=dict(model="lambert", params={"albedo": 0.5}),
        ),
        holder=dict(width=0.2, height=0.2, board=None, albedo_white=0.8),
        lights=[
            dict(
                type="disk", position=LIGHT.tolist(), look_at=[0, 0, 0], radius=0.01, radiance=50.0
            )
        ],
        camera=dict(
            resolution=[w, h],
            focal_length=0.016,
            pixel_pitch=4e-5,
            position=[0, -0.3, 0.4],
            look_at=[0, 0, 0],
            up=[0, 1, 0],
            sensor=sensor,
        ),
        render=dict(tolerance=1e-4, antialias=1),
    )


def world(**radiometry):
    return draw_world("perfect", 5, {"radiometry": radiometry})


def electrons(frame, s, iso=100.0):
    g = s.gain_at_base_iso * iso / s.base_iso
    return (frame.mosaic.astype(float) - s.black_level) / g


def test_drift_scales_the_frame_by_the_light_output_ratio():
    A, tau, r = (0.1, 0.08, 0.06), 600.0, 0.004
    w = world(drift_amplitude=A, drift_tau_s=tau, drift_rate_per_h=r, stray_fraction=0.01)

    def out(t):  # the warm-up law, written out
        return 1 + np.array(A) * math.exp(-t / tau) + r * t / 3600

    assert np.allclose(w.light_output(900.0), out(900.0), rtol=1e-15)
    cam = SimulatedCamera(parse_scene(scene_doc()), world=w)
    L0 = cam.radiance(rig_time=0.0)
    L1 = cam.radiance(rig_time=1800.0)
    m = L0[..., 0] > 0
    # direct and stray light drift together: the image scales by the output ratio
    assert np.allclose(L1[m] / L0[m], out(1800.0) / out(0.0), rtol=1e-12)
    assert cam.renders == 1  # a drifting light does not re-render
    # through the sensor: the mean electrons per channel follow the same ratio
    s = cam.scene.camera.sensor
    idx = cfa_indices(s.cfa_pattern, m.shape)
    e0 = electrons(cam.capture_frame(0.02, 100, 8, seed=1, rig_time=0.0), s)
    e1 = electrons(cam.capture_frame(0.02, 100, 8, seed=2, rig_time=1800.0), s)
    for c in range(3):
        sel = m & (idx == c)
        ratio = e1[sel].sum() / e0[sel].sum()
        # shot + read noise of the sums, relative
        sig = math.sqrt(2 * (e0[sel].sum() + sel.sum() * (s.read_noise**2 + 7))) / e0[sel].sum()
        want = out(1800.0)[c] / out(0.0)[c]
        assert abs(ratio - want) < 5 * sig
        assert abs(want - 1) > 10 * sig  # the test sees the drift


def test_the_rig_camera_reads_the_clock_at_each_lit_shot():
    w = world(drift_amplitude=(0.2, 0.2, 0.2), drift_tau_s=100.0)
    t = {"now": 0.0}
    doc = scene_doc()
    scene = parse_scene(doc)
    C = np.array(doc["camera"]["position"])

    def poses():
        return {
            "camera_position": C,
            "camera_rotation": look_at_rotation(C, [0, 0, 0], [0, 1, 0]).T,
            "light_position": LIGHT,
            "light_normal": -LIGHT / np.linalg.norm(LIGHT),
        }

    rig = SimulatedRigCamera(scene, poses, seed=3, clock=lambda: t["now"], world=w)
    ref = SimulatedCamera(scene, poses, world=w)
    for now in (0.0, 250.0):
        t["now"] = now
        rig.next_shot(1, 0)
        got = rig.capture(0.01, 100, 8).data
        from gonio.simulator.rig_camera import shot_seed

        assert got == ref.capture(0.01, 100, 8, shot_seed(3, 1, 0), rig_time=now)
    assert got != ref.capture(0.01, 100, 8, shot_seed(3, 1, 0), rig_time=0.0)
    bad = SimulatedRigCamera(scene, poses, clock=lambda: float("nan"), world=w)
    with pytest.raises(CameraError, match="rig clock"):
        bad.capture(0.01, 100, 8)


def test_ambient_in_a_dark_frame_is_e0_albedo_over_pi():
    amb = 0.05
    cam = SimulatedCamera(parse_scene(scene_doc()), world=world(ambient_fraction=amb))
    L = cam.radiance(light_on=False)
    res = cam.render(diffuse=True)
    # E0: the disk's on-axis irradiance from its distance, pi L R^2 / (d^2 + R^2)
    d = np.linalg.norm(LIGHT)
    E0 = np.pi * 50.0 * 0.01**2 / (d**2 + 0.01**2)
    hold = res.region == 2
    samp = res.region == 1
    assert np.allclose(L[hold], amb * E0 * 0.8 / np.pi, rtol=1e-9)
    assert np.allclose(L[samp], amb * E0 * 0.5 / np.pi, rtol=2e-3)  # the tabulated albedo
    # light on: direct light plus the same ambient
    on = cam.radiance(light_on=True)
    assert np.allclose(on - L, res.radiance, rtol=1e-12, atol=1e-300)
    # the dark frame's electrons: the ambient's, by hand (photons, QE), over the holder
    s = cam.scene.camera.sensor
    t = 0.5
    f = cam.capture_frame(t, 100, 8, seed=4, light_on=False)
    K = cam.scene.camera.intrinsics()
    v, u = np.mgrid[0:32, 0:48]
    cos4 = (1 + ((u + 0.5 - K[0, 2]) ** 2 + (v + 0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2) ** -2
    idx = cfa_indices("RGGB", (32, 48))
    lam = np.array(s.wavelength_nm)[idx] * 1e-9
    qe = np.array(s.quantum_efficiency)[idx]
    Lp = np.take_along_axis(L, idx[..., None], 2)[..., 0]
    mu = Lp * np.pi / (4 * 64) * cos4 * (4e-5) ** 2 * t * lam / _HC * qe + s.dark_current * t
    e = electrons(f, s)
    z = (e - mu)[hold] / np.sqrt(mu[hold] + s.read_noise**2 + 1 / (12 * 0.4**2))
    assert abs(z.mean()) < 5 / np.sqrt(hold.sum()) and 0.85 < z.std() < 1.15
    assert mu[hold].mean() > 20 * s.read_noise  # the ambient is well above the noise
    # a perfect world's dark frame is black
    plain = SimulatedCamera(parse_scene(scene_doc()))
    dark = electrons(plain.capture_frame(t, 100, 8, seed=4, light_on=False), s)
    assert abs(dark.mean()) < 1.0


def _flat_camera(**rad):
    # a wide lens (cos^4 reaches ~0.6 in the corners); big well, gain 1 e-/DN
    doc = scene_doc(80, 60, full_well=60000.0, gain_at_base_iso=0.25, read_noise=2.0)
    doc["camera"]["focal_length"] = 0.004
    return SimulatedCamera(parse_scene(doc), world=world(**rad) if rad else None)


def _flat_expectation(cam, L, t=0.01, N=8.0):
    s, cm = cam.scene.camera.sensor, cam.scene.camera
    K = cm.intrinsics()
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w]
    tan2 = ((u + 0.5 - K[0, 2]) ** 2 + (v + 0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2
    cos4 = np.cos(np.arctan(np.sqrt(tan2))) ** 4
    idx = cfa_indices("RGGB", (h, w))
    lam = np.array(s.wavelength_nm)[idx] * 1e-9
    qe = np.array(s.quantum_efficiency)[idx]
    return np.asarray(L)[idx] * np.pi / (4 * N**2) * cm.pitch**2 * t * lam / _HC * qe * cos4


def test_flat_frame_is_cos4_shaped_and_half_full_by_default():
    cam = _flat_camera()
    s = cam.scene.camera.sensor
    L = cam.flat_radiance()
    mu = _flat_expectation(cam, L)
    assert mu.max() == pytest.approx(0.5 * s.full_well, rel=1e-3)  # strongest channel
    e = electrons(cam.capture_frame(0.01, 100, 8, seed=1, target="flat"), s)
    z = (e - mu) / np.sqrt(mu + s.read_noise**2 + 1 / (12 * 0.25**2))
    assert abs(z.mean()) < 5 / np.sqrt(z.size) and 0.95 < z.std() < 1.05
    corner = mu < 0.7 * mu.max()
    assert corner.sum() > 50  # the shape is tested where cos^4 is far from 1
    # no light, no ambient, no drift reach the flat
    w = world(ambient_fraction=0.1, drift_amplitude=(0.5, 0.5, 0.5))
    other = SimulatedCamera(cam.scene, world=w)
    assert np.array_equal(
        other.radiance("flat", rig_time=10.0, light_on=False), cam.radiance("flat")
    )
    with pytest.raises(CameraError, match="flat"):
        cam.render("flat")


def test_flat_frame_shows_the_prnu_and_two_frames_share_it():
    p = 0.01
    bright = default_flat_radiance(_flat_camera().scene.camera) * 0.6
    cam = _flat_camera(prnu=p, flat_radiance=tuple(bright))
    s = cam.scene.camera.sensor
    mu = _flat_expectation(cam, cam.flat_radiance())
    e1 = electrons(cam.capture_frame(0.01, 100, 8, seed=1, target="flat"), s)
    e2 = electrons(cam.capture_frame(0.01, 100, 8, seed=2, target="flat"), s)
    noise = mu + s.read_noise**2 + 1 / (12 * 0.25**2)
    n = mu.size
    # relative deviation: PRNU (fixed) plus noise; its variance is p^2 + noise / mu^2
    r = e1 / mu - 1
    want = np.mean(p**2 + noise / mu**2)
    assert abs(r.var() / want - 1) < 5 * math.sqrt(2 / n)
    assert p**2 > np.mean(noise / mu**2)  # PRNU is the larger part: the test sees it
    # the difference of two frames has no PRNU left: the pattern is fixed
    dvar = np.mean(2 * noise / mu**2)
    assert abs(((e1 - e2) / mu).var() / dvar - 1) < 5 * math.sqrt(2 / n)


def _dark_sensor_scene(w, h):
    return parse_scene(scene_doc(w, h, read_noise=0.0, dark_current=0.0, gain_at_base_iso=1.0))


def test_dsnu_is_a_clipped_gaussian_offset():
    sigma = 4.0
    scene = _dark_sensor_scene(160, 120)
    r = Radiometry(dsnu_e=sigma)
    fp = fixed_pattern(r, 7, (120, 160))
    f = simulate_raw(
        np.zeros((120, 160, 3)), scene.camera, exposure_time=1e-3, seed=1, fixed_pattern=fp
    )
    e = f.mosaic.astype(float) - scene.camera.sensor.black_level
    # e = Poisson(max(0, N(0, sigma))): mean sigma / sqrt(2 pi), variance
    # Var(m) + E(m) with Var(m) = sigma^2 (1/2 - 1/(2 pi))
    mean = sigma / math.sqrt(2 * math.pi)
    var = sigma**2 * (0.5 - 1 / (2 * math.pi)) + mean
    n = e.size
    assert abs(e.mean() - mean) < 5 * math.sqrt(var / n)
    assert abs(e.var() / var - 1) < 5 * math.sqrt(3 / n)  # heavy-ish tail: kurtosis ~ 3-4
    # the same map in every frame
    g = simulate_raw(
        np.zeros((120, 160, 3)), scene.camera, exposure_time=1e-3, seed=2, fixed_pattern=fp
    )
    e2 = g.mosaic.astype(float) - scene.camera.sensor.black_level
    assert np.corrcoef(e.ravel(), e2.ravel())[0, 1] > 0.5


def test_hot_pixels_fraction_and_current():
    frac, cur, t = 0.01, 1000.0, 1.0
    scene = _dark_sensor_scene(100, 80)
    fp = fixed_pattern(Radiometry(hot_pixel_fraction=frac, hot_pixel_current_e_s=cur), 3, (80, 100))
    f = simulate_raw(
        np.zeros((80, 100, 3)), scene.camera, exposure_time=t, seed=1, fixed_pattern=fp
    )
    e = f.mosaic.astype(float) - scene.camera.sensor.black_level
    hot = e > 100
    n = e.size
    k = int(hot.sum())
    assert abs(k - frac * n) < 4 * math.sqrt(n * frac * (1 - frac))
    assert not e[~hot].any()  # the others get nothing (no dark current, no read noise)
    # their charge: U(0.5, 1.5) * cur * t plus shot noise
    q = e[hot]
    assert q.min() > 0.5 * cur * t - 5 * math.sqrt(cur) and q.max() < 1.5 * cur * t + 5 * math.sqrt(
        2 * cur
    )
    sd = math.sqrt((cur * t) ** 2 / 12 + cur * t)
    assert abs(q.mean() - cur * t) < 5 * sd / math.sqrt(k)


def test_fixed_patterns_depend_on_the_world_seed_and_frame_size_only():
    r = Radiometry(prnu=0.01, dsnu_e=2.0, hot_pixel_fraction=0.01, hot_pixel_current_e_s=500.0)
    a, b = fixed_pattern(r, 1, (30, 40)), fixed_pattern(r, 1, (30, 40))
    assert np.array_equal(a.gain, b.gain) and np.array_equal(a.hot_index, b.hot_index)
    assert not np.array_equal(a.gain, fixed_pattern(r, 2, (30, 40)).gain)
    assert fixed_pattern(r, 1, (31, 40)).gain.shape == (31, 40)
    # switching one defect off leaves the others' maps as they were
    only = fixed_pattern(Radiometry(dsnu_e=2.0), 1, (30, 40))
    assert only.gain is None and np.array_equal(only.dark_offset, a.dark_offset)
    assert fixed_pattern(Radiometry(), 1, (30, 40)) is None
    # a camera builds them once, for its frame size
    cam = SimulatedCamera(
        parse_scene(scene_doc()),
        world=draw_world("perfect", 1, {"radiometry": r.model_dump(exclude_none=True)}),
    )
    assert cam.fixed_pattern() is cam.fixed_pattern()
    assert np.array_equal(cam.fixed_pattern().gain, fixed_pattern(r, 1, (32, 48)).gain)

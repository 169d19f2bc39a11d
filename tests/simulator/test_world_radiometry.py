"""[world.radiometry]: its own random stream, the documented ranges, overrides, files,
the perfect world unchanged, and the world reaching the camera through the wiring."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from gonio.app.world_wiring import simulated_camera_kwargs
from gonio.errors import CameraError, ConfigError
from gonio.simulator.rig_camera import SimulatedRigCamera
from gonio.simulator.world import JOINTS, RIG_PARAMETERS, draw_world, load_world, world_document
from gonio.simulator.world_radiometry import REALISTIC_RADIOMETRY

# Main's draw (issue 15, commit 6724de2) of a few seeds: values that code produced.
_MAIN = {
    0: (
        -1.2048256123579644,
        0.0029352212474503276,
        0.012407110330247176,
        0.08416705269556793,
        (-1, -1, 1, 1),
    ),
    1: (
        0.5475312798852889,
        0.001294082696321297,
        -0.009824653700036495,
        0.0635448916977813,
        (1, 1, -1, 1),
    ),
    7: (
        -1.9846185062477275,
        0.0032336810108249928,
        0.011304705289947387,
        -0.05845988529719795,
        (-1, 1, 1, 1),
    ),
    123: (
        1.9363886927854472,
        0.004266312761092805,
        -0.0010476872524134966,
        -0.006636348063903674,
        (-1, -1, -1, 1),
    ),
}


def _main_draw(seed):
    """Main's draw order, re-written: rig in RIG_PARAMETERS order, fx, principal point,
    distortion, initial approach, all from default_rng([seed, 0x57071D])."""
    from gonio.simulator.world import _REALISTIC_DIST, _REALISTIC_RIG

    rng = np.random.default_rng([seed, 0x57071D])
    rig = {n: float(rng.uniform(*_REALISTIC_RIG[n])) for n in RIG_PARAMETERS}
    fx = float(rng.uniform(-0.015, 0.015))
    pp = tuple(float(x) for x in rng.uniform(-0.01, 0.01, 2))
    dist = tuple(float(rng.uniform(lo, hi)) if hi > lo else 0.0 for lo, hi in _REALISTIC_DIST)
    approach = {j: int(rng.choice([-1, 1])) for j in JOINTS}
    return rig, fx, pp, dist, approach


@pytest.mark.parametrize("seed", sorted(_MAIN))
def test_kinematic_and_camera_draws_are_main_s(seed):
    w = draw_world("realistic", seed)
    off, hz, fx, k1, appr = _MAIN[seed]
    assert w.rig["stage_tilt.offset"] == off and w.rig["holder_offset_z"] == hz
    assert w.camera.fx_scale == fx and w.camera.dist[0] == k1
    assert tuple(w.servos.initial_approach[j] for j in JOINTS) == appr
    rig, fx, pp, dist, approach = _main_draw(seed)
    assert w.rig == rig
    assert (w.camera.fx_scale, w.camera.principal_offset, w.camera.dist) == (fx, pp, dist)
    assert w.servos.initial_approach == approach


def test_realistic_radiometry_within_the_ranges_and_seeded():
    draws = [draw_world("realistic", s).radiometry for s in range(40)]
    assert draws[3] == draw_world("realistic", 3).radiometry and draws[3] != draws[4]
    for name, (lo, hi) in REALISTIC_RADIOMETRY.items():
        v = np.array([getattr(r, name) for r in draws], float)
        assert v.min() >= lo and v.max() <= hi, name
        assert np.ptp(v) > 0.5 * (hi - lo), name  # spread over the range, not a constant
    assert all(not r.off and r.flat_radiance is None for r in draws)
    # the table's numbers, spelled out (i16 section 1)
    assert REALISTIC_RADIOMETRY["prnu"] == (0.003, 0.01)
    assert REALISTIC_RADIOMETRY["stray_fraction"] == (0.0, 5e-4)
    assert REALISTIC_RADIOMETRY["hot_pixel_current_e_s"] == (200.0, 2000.0)


def test_perfect_world_has_no_radiometry_and_light_output_one():
    w = draw_world("perfect", 9)
    assert w.perfect and w.radiometry.off
    assert np.array_equal(w.light_output(1234.0), np.ones(3))
    assert not draw_world("perfect", 9, {"radiometry": {"ambient_fraction": 1e-4}}).perfect


def test_overrides_round_trip_and_bad_values_are_named(tmp_path):
    w = draw_world("realistic", 2, {"radiometry": {"prnu": 0.02, "flat_radiance": [1.0, 2.0, 3.0]}})
    base = draw_world("realistic", 2)
    assert w.radiometry.prnu == 0.02 and w.radiometry.dsnu_e == base.radiometry.dsnu_e
    assert w.rig == base.rig  # a radiometric override changes no other draw
    doc = world_document(w)
    assert load_world(doc) == w
    p = tmp_path / "w.toml"
    p.write_text(tomli_w.dumps({"world": world_document(base)}))
    assert load_world(p) == base  # no flat_radiance: absent from the file, None again
    for bad, field in [
        ({"prnu": -0.1}, "radiometry.prnu"),
        ({"drift_tau_s": 0}, "radiometry.drift_tau_s"),
        ({"drift_amplitude": [0.1, "x", 0.1]}, "radiometry.drift_amplitude"),
        ({"colour": 1}, "radiometry.colour"),
    ]:
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            draw_world("perfect", 0, {"radiometry": bad})
    with pytest.raises(ConfigError, match="radiometry"):
        draw_world("perfect", 0, {"radiometry": "bright"})


def _poses():
    c = np.array([0, -0.25, 0.433])
    from gonio.simulator.scene import look_at_rotation

    return {
        "camera_position": c,
        "camera_rotation": look_at_rotation(c, [0, 0, 0]).T,
        "light_position": np.array([0, 0.25, 0.433]),
        "light_normal": -np.array([0, 0.25, 0.433]) / 0.5,
    }


def test_a_perfect_world_camera_writes_the_same_bytes():
    plain = SimulatedRigCamera(None, _poses, seed=4, width=32, height=24)
    worldly = SimulatedRigCamera(
        None,
        _poses,
        seed=4,
        width=32,
        height=24,
        clock=lambda: 500.0,
        world=draw_world("perfect", 3),
    )
    for light, target in [(True, "sample"), (False, "sample"), (True, "reference")]:
        for cam in (plain, worldly):
            cam.set_light(light)
            cam.set_target(target)
            cam.next_shot(2, 1)
        assert plain.capture(0.01, 100, 8).data == worldly.capture(0.01, 100, 8).data


def test_flat_target_and_bad_targets():
    cam = SimulatedRigCamera(None, _poses, seed=4, width=32, height=24)
    cam.set_target("flat")
    cam.set_light(False)  # the panel does not care
    shot = cam.capture(0.01, 100, 8)
    assert shot.extra["target"] == "flat"
    with pytest.raises(CameraError, match=r"'lens cap'.*'sample', 'reference', 'mirror', 'flat'"):
        cam.set_target("lens cap")
    with pytest.raises(CameraError, match="clock"):
        SimulatedRigCamera(None, _poses, clock=5.0)


def test_the_wiring_hands_a_radiometric_world_to_the_camera():
    real = draw_world("realistic", 1)
    kw = simulated_camera_kwargs(real)
    assert kw["world"] is real and kw["serial"] == real.camera_serial()
    assert "world" not in simulated_camera_kwargs(draw_world("perfect", 1))
    cam = SimulatedRigCamera(None, _poses, seed=1, width=32, height=24, **kw)
    assert cam._cam.radiometry == real.radiometry
    assert cam._cam.scene.lights[0].profile_n == real.radiometry.light_profile_n


def test_a_flat_radiance_of_its_own_reaches_the_camera():
    w = draw_world("perfect", 0, {"radiometry": {"flat_radiance": [2.0, 3.0, 4.0]}})
    assert not w.radiometry.off and not w.perfect
    cam = SimulatedRigCamera(None, _poses, width=8, height=6, **simulated_camera_kwargs(w))
    assert np.array_equal(cam._cam.flat_radiance(), [2.0, 3.0, 4.0])
    assert draw_world("perfect", 0, {"radiometry": {"drift_tau_s": 100.0}}).radiometry.off

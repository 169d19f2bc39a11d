"""The as-built world wired into simulated sessions.

* perfect world: journal and RAW bytes identical to the wiring before worlds existed
  (re-implemented here: nominal kinematics of the controller's read-back, exact servos,
  the scene's own camera);
* realistic world: recorded in the manifest, rebuilt on resume, the camera renders the
  world's pose (a board measured in a rendered frame shows a 1 deg tilt offset the
  controller does not know of), reduction.toml keeps the nominal camera;
* bad --world values exit 1 with a message, nothing written.
"""

from __future__ import annotations

import contextlib
import json
import math
import tomllib

import numpy as np
import pytest

from gonio.app.devices import device_opener
from gonio.app.world_wiring import (
    as_built_scene,
    nominal_scene,
    resolve_world,
    world_pose_provider,
    world_servos,
)
from gonio.capture.engine import SessionDevices
from gonio.capture.plan import load_plan
from gonio.capture.sessions import run_session
from gonio.cli import run
from gonio.rig.config import load_rig_config, virtual_rig_document
from gonio.simulator.world import draw_world, world_document

PLAN = """
name = "world-test"
seed = 3
[grid]
theta_i_deg = [30]
phi_i_deg = [0]
theta_o_deg = [20, 40]
phi_o_deg = [180]
[bracket]
policy = "adaptive"
roi = [0.42, 0.42, 0.58, 0.58]
exposure_time_s = 0.0005
[darks]
count = 0
[simulation]
width = 96
height = 64
"""

SCENE = {
    "sample": {
        "width": 0.05,
        "height": 0.05,
        "brdf": {"model": "lambert", "params": {"albedo": [0.6, 0.5, 0.4]}},
    },
    "holder": {"width": 0.16, "height": 0.16, "board": {}},
    "lights": [
        {
            "type": "disk",
            "position": [0.0, 0.25, 0.433],
            "look_at": [0.0, 0.0, 0.0],
            "radius": 0.01,
            "radiance": [2e4, 2e4, 2e4],
        }
    ],
    "camera": {
        "resolution": [400, 300],
        "focal_length": 0.016,
        "fov_deg": 30.0,
        "position": [0.1, -0.2, 0.35],
        "look_at": [0.0, 0.0, 0.0],
    },
    "render": {"strategy": "point", "antialias": 1},
}


@pytest.fixture
def setup(tmp_path):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    return load_plan(tmp_path / "plan.toml"), load_rig_config(tmp_path / "rig.toml")


def _legacy_opener():
    """The session devices as wired before the as-built world (a second implementation
    of the old composition root, for the perfect-world identity check)."""
    from gonio.app.sim_reduction import CONFIG_FILE, reduction_document, reduction_toml_text
    from gonio.rig.device import Rig
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.rig_camera import SimulatedRigCamera
    from gonio.simulator.servo_clock import parse_time_scale
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    @contextlib.contextmanager
    def opener(request):
        cfg = request.rig_config
        sim = dict(request.simulation or {})
        kin = Kinematics(cfg)
        refl = request.reference_reflectance
        if refl is None:
            refl = sim.get("reference_reflectance")
        if isinstance(refl, list | tuple):
            refl = tuple(float(x) for x in refl)
        park = cfg.park_pulses
        servos = [VirtualServo(s.id, model=s.model, position=park[s.id]) for s in cfg.servos]
        with VirtualBus(
            servos,
            baud_rate=cfg.bus.baud_rate,
            seed=request.seed,
            time_scale=parse_time_scale("virtual"),
        ) as bus:
            cfg2 = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})
            with Rig(cfg2, clock=bus.clock) as rig:
                camera = SimulatedRigCamera(
                    dict(sim["scene"]),
                    lambda: kin.poses({k: float(v) for k, v in rig.read().joints.items()}),
                    request.seed,
                    width=sim.get("width"),
                    height=sim.get("height"),
                    base_dir=request.session_dir,
                    **({"reference_albedo": refl} if refl is not None else {}),
                    sleep=bus.sleep,  # frames take rig time (issue 16)
                )
                setup = reduction_toml_text(reduction_document(camera.scene, refl))
                try:
                    yield SessionDevices(
                        rig,
                        camera,
                        light=camera,
                        target=camera,
                        kinematics=kin,
                        sleep=bus.sleep,
                        read_noise_dn=camera.read_noise_dn,
                        files={CONFIG_FILE: setup.encode()},
                        clock=bus.clock,  # rig time in the shot records (issue 16)
                    )
                finally:
                    camera.close()

    return opener


def _journal(session):
    """The journal's records without their wall-clock stamps."""
    out = []
    for line in (session / "journal.jsonl").read_text().splitlines():
        rec = json.loads(line)
        rec.pop("time", None)
        out.append(rec)
    return out


def _raws(session):
    return {p.name: p.read_bytes() for p in sorted((session / "raw").glob("*"))}


def _sim(plan, world=None):
    sim = {
        "scene": SCENE,
        "width": plan.simulation.width,
        "height": plan.simulation.height,
        "time_scale": "virtual",
    }
    if world is not None:
        sim["world"] = world_document(world)
    return sim


def test_perfect_world_session_is_todays(setup, tmp_path):
    plan, cfg = setup
    run_session(
        tmp_path / "old",
        plan,
        cfg,
        _legacy_opener(),
        camera_backend="simulated",
        simulation=_sim(plan),
    )
    run_session(
        tmp_path / "new",
        plan,
        cfg,
        device_opener(),
        camera_backend="simulated",
        simulation=_sim(plan, draw_world("perfect")),
    )
    old, new = _journal(tmp_path / "old"), _journal(tmp_path / "new")
    assert len(old) == len(new) > 2
    assert old == new
    assert _raws(tmp_path / "old") == _raws(tmp_path / "new") != {}
    assert (tmp_path / "old" / "reduction.toml").read_bytes() == (
        tmp_path / "new" / "reduction.toml"
    ).read_bytes()


def test_realistic_world_is_recorded_and_the_reduction_keeps_the_nominal_camera(setup, tmp_path):
    plan, cfg = setup
    world = draw_world("realistic", 6)
    run_session(
        tmp_path / "S",
        plan,
        cfg,
        device_opener(),
        camera_backend="simulated",
        simulation=_sim(plan, world),
    )
    manifest = json.loads((tmp_path / "S" / "manifest.json").read_text())
    assert resolve_world(recorded=manifest["simulation"]["world"]) == world
    red = tomllib.loads((tmp_path / "S" / "reduction.toml").read_text())
    nominal = nominal_scene(SCENE, None, 96, 64).camera
    K_nominal = nominal.intrinsics() - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    np.testing.assert_allclose(red["camera"]["K"], K_nominal, rtol=1e-12)
    K_true, _ = world.intrinsics(nominal)
    assert abs(K_true[0, 0] - K_nominal[0, 0]) > 1e-3 * K_nominal[0, 0]
    # the same plan in a perfect world: the as-built camera renders other bytes
    run_session(
        tmp_path / "P",
        plan,
        cfg,
        device_opener(),
        camera_backend="simulated",
        simulation=_sim(plan, draw_world("perfect")),
    )
    assert _raws(tmp_path / "S").keys() == _raws(tmp_path / "P").keys()
    assert _raws(tmp_path / "S") != _raws(tmp_path / "P")


def test_world_pose_provider_reads_the_servos_truth(setup):
    """A 1 deg tilt offset: the frame the camera renders shows a board pose 1 deg off
    the controller's report (OpenCV detection on a rendered frame)."""
    from gonio.capture.fiducials import BoardSpec, detect_pose, to_uint8
    from gonio.rig.device import Rig
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.virtual_bus import VirtualBus

    _, cfg = setup
    world = draw_world("perfect", 0, {"rig": {"stage_tilt.offset": 1.0}})
    kin = Kinematics(cfg)
    doc = {**SCENE, "render": {"strategy": "point", "antialias": 3}}
    scene = as_built_scene(world, nominal_scene(doc, None, 1200, 900))
    with VirtualBus(
        world_servos(world, cfg), baud_rate=cfg.bus.baud_rate, time_scale="virtual"
    ) as bus:
        cfg2 = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})
        with Rig(cfg2, clock=bus.clock) as rig:
            target = {
                "light_azimuth": math.radians(-60),
                "camera_azimuth": math.radians(0),
                "stage_tilt": math.radians(-55),
                "stage_spin": 0.0,
            }
            rig.move_joints(target)
            reported = kin.poses(rig.read().joints)
            provider = world_pose_provider(world, cfg, bus)
            truth = provider()
            cam = SimulatedCamera(scene, pose_provider=provider)
            img = cam.render().radiance.mean(axis=-1)
    grey = to_uint8((img / np.percentile(img, 99)).clip(0, 1).astype(np.float32))
    K = scene.camera.intrinsics() - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    pose = detect_pose(grey, BoardSpec(), K)
    angle = math.degrees(pose.angle_to(reported.camera_rotation.T))
    err = math.degrees(pose.angle_to(truth.camera_rotation.T))
    assert err < 0.05  # the frame shows the world's pose ...
    assert angle == pytest.approx(1.0, abs=0.05)  # ... 1 deg off what the controller reports


def test_cli_bad_world_exits_1_and_writes_nothing(tmp_path):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    out = tmp_path / "S"
    code = run(
        "capture",
        "run",
        str(tmp_path / "plan.toml"),
        "--rig",
        str(tmp_path / "rig.toml"),
        "--camera",
        "simulated",
        "--out",
        str(out),
        "--world",
        "sloppy",
        "--quiet",
    )
    assert code == 1
    assert not out.exists() or not any(out.iterdir())
    (tmp_path / "w.toml").write_text(
        '[world]\npreset = "realistic"\n[world.rig]\n"stage_tilt.ofset" = 1.0\n'
    )
    code = run(
        "capture",
        "run",
        str(tmp_path / "plan.toml"),
        "--rig",
        str(tmp_path / "rig.toml"),
        "--camera",
        "simulated",
        "--out",
        str(out),
        "--world",
        str(tmp_path / "w.toml"),
        "--quiet",
    )
    assert code == 1
    assert not out.exists() or not any(out.iterdir())


def test_cli_world_needs_the_simulated_camera(tmp_path, capsys):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    code = run(
        "capture",
        "run",
        str(tmp_path / "plan.toml"),
        "--rig",
        str(tmp_path / "rig.toml"),
        "--out",
        str(tmp_path / "S"),
        "--world",
        "realistic",
    )
    assert code != 0


def test_where_the_world_comes_from(tmp_path):
    """--world > the plan's [simulation] world > the scene's [world] > perfect."""
    import tomli_w

    from gonio.app.simulation import simulated_run

    scene = {**SCENE, "world": {"preset": "realistic", "seed": 2}}
    (tmp_path / "scene.toml").write_text(tomli_w.dumps(scene))
    (tmp_path / "w.toml").write_text('[world]\npreset = "realistic"\nseed = 9\n')
    base = PLAN + 'scene = "scene.toml"\n'
    (tmp_path / "a.toml").write_text(base)
    (tmp_path / "b.toml").write_text(base + 'world = "w.toml"\n')
    (tmp_path / "c.toml").write_text(PLAN)
    a, b, c = (load_plan(tmp_path / f"{n}.toml") for n in "abc")
    doc = world_document

    def world_of(plan, path, *args):
        return simulated_run(plan, path, None, "virtual", *args).simulation["world"]

    assert world_of(a, tmp_path / "a.toml") == doc(draw_world("realistic", 2))
    assert world_of(b, tmp_path / "b.toml") == doc(draw_world("realistic", 9))
    assert world_of(b, tmp_path / "b.toml", "perfect") == doc(draw_world("perfect"))
    assert world_of(b, tmp_path / "b.toml", "realistic", 4) == doc(draw_world("realistic", 4))
    assert world_of(c, tmp_path / "c.toml") == doc(draw_world("perfect"))
    # the renderer never sees the [world] table
    sim = simulated_run(a, tmp_path / "a.toml", None, "virtual").simulation
    assert "world" not in sim["scene"]


def test_world_servos_start_on_the_worlds_side_of_backlash(setup):
    from gonio.simulator.world_kinematics import NominalRig, approach_from_servos

    _, cfg = setup
    world = draw_world("realistic", 12)
    servos = world_servos(world, cfg)
    rig = NominalRig.of(cfg.model_dump(mode="json"))
    got = approach_from_servos(rig, {s.dxl_id: s.last_direction for s in servos})
    assert got == dict(world.servos.initial_approach)
    assert {s.dxl_id: s.true_state()[0] for s in servos} == cfg.park_pulses
    assert all(s.landing_pulses == 1 and s.landing_seed == 12 for s in servos)


def test_resume_rebuilds_the_recorded_world(tmp_path):
    """A realistic world (landing, backlash and the light's drift zeroed so that where
    and when a resumed rig starts does not matter: a resume's new bus restarts rig time):
    the frames a resume shoots are byte for byte those of the uninterrupted run -- they
    would not be in any other world (checked: perfect)."""
    import shutil

    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    (tmp_path / "scene.toml").write_text(tomllib_dumps(SCENE))
    backlash = "\n".join(
        f'"{j}.backlash" = 0.0'
        for j in ("light_azimuth", "camera_azimuth", "stage_tilt", "stage_spin")
    )
    (tmp_path / "w.toml").write_text(
        '[world]\npreset = "realistic"\nseed = 5\n[world.servos]\nlanding_pulses = 0\n'
        f"[world.rig]\n{backlash}\n"
        "[world.radiometry]\ndrift_amplitude = [0.0, 0.0, 0.0]\ndrift_rate_per_h = 0.0\n"
    )
    args = [
        "--rig",
        str(tmp_path / "rig.toml"),
        "--camera",
        "simulated",
        "--scene",
        str(tmp_path / "scene.toml"),
        "--quiet",
    ]
    full, perfect = tmp_path / "full", tmp_path / "perfect"
    assert (
        run(
            "capture",
            "run",
            str(tmp_path / "plan.toml"),
            "--out",
            str(full),
            "--world",
            str(tmp_path / "w.toml"),
            *args,
        )
        == 0
    )
    assert run("capture", "run", str(tmp_path / "plan.toml"), "--out", str(perfect), *args) == 0
    cut = tmp_path / "cut"
    shutil.copytree(full, cut)
    lines = (cut / "journal.jsonl").read_bytes().splitlines(keepends=True)
    first_pose_done = next(
        i for i, line in enumerate(lines) if json.loads(line).get("type") == "pose_done"
    )
    (cut / "journal.jsonl").write_bytes(b"".join(lines[: first_pose_done + 1]))
    kept = {json.loads(line).get("file") for line in lines[: first_pose_done + 1]}
    for p in (cut / "raw").iterdir():
        if f"raw/{p.name}" not in kept:
            p.unlink()
    assert len(list((cut / "raw").iterdir())) < len(_raws(full))
    assert run("capture", "resume", str(cut), "--quiet") == 0
    assert _raws(cut) == _raws(full)
    assert _raws(full) != _raws(perfect)
    assert (
        json.loads((cut / "manifest.json").read_text())["simulation"]["world"]
        == json.loads((full / "manifest.json").read_text())["simulation"]["world"]
    )


def tomllib_dumps(doc):
    import tomli_w

    return tomli_w.dumps(doc)

"""Wiring the simulator's as-built world into a simulated session.

The composition root is the only place that knows both the controller's rig (its nominal
configuration) and the simulator's world.  Here the world decides:

* the virtual servos: their landing error and the side of its backlash each starts on;
* the pose the simulated camera renders: the world's :func:`true_poses` of the servos'
  physical state (:meth:`~gonio.simulator.virtual_bus.ServoBus.servo_states`), never the
  controller's read-back;
* the camera the renderer uses: the scene's camera as built (focal scale, principal point,
  distortion), while the session's ``reduction.toml`` keeps the NOMINAL camera -- what a
  lab knows before it calibrates;
* the radiometry the camera sees (light profile, drift over rig time, ambient and stray
  light, the sensor's fixed patterns): the world is handed to the camera
  (:func:`simulated_camera_kwargs`), which reads the rig time from ``clock``.

A ``perfect`` world changes nothing: the session is today's, bit for bit.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from gonio.errors import ConfigError

__all__ = [
    "SCENE_WORLD_KEY",
    "as_built_scene",
    "nominal_scene",
    "resolve_world",
    "simulated_camera_kwargs",
    "split_scene_world",
    "world_pose_provider",
    "world_servos",
]

#: The table of a scene document that holds its world (the renderer never sees it).
SCENE_WORLD_KEY = "world"


def split_scene_world(document: Mapping[str, Any]) -> tuple[dict[str, Any], Any]:
    """A scene document without its ``[world]`` table, and that table (or None)."""
    doc = dict(document)
    return doc, doc.pop(SCENE_WORLD_KEY, None)


def resolve_world(
    cli_world: str | None = None,
    world_seed: int | None = None,
    plan_world: str | Mapping[str, Any] | None = None,
    plan_dir: Path | None = None,
    scene_world: Mapping[str, Any] | None = None,
    recorded: Mapping[str, Any] | None = None,
) -> Any:
    """The session's world: ``--world`` (preset or file), else the plan's ``[simulation]
    world``, else the scene's ``[world]`` table, else a session's recorded world, else
    ``perfect``.  ``world_seed`` (``--world-seed``) replaces the chosen world's seed
    (its errors are drawn again from it; explicit values still win).

    Raises
    ------
    ConfigError
        Unknown preset, unreadable world file, invalid field (named).
    """
    from gonio.simulator.world import load_world

    if cli_world is not None:
        return load_world(cli_world, world_seed)
    if plan_world is not None:
        if isinstance(plan_world, str) and plan_world not in ("perfect", "realistic"):
            p = Path(plan_world)
            if not p.is_absolute() and plan_dir is not None:
                p = plan_dir / p
            return load_world(p, world_seed)
        return load_world(plan_world, world_seed)
    if scene_world is not None:
        if not isinstance(scene_world, Mapping):
            raise ConfigError("scene: [world] must be a table")
        return load_world(scene_world, world_seed)
    if recorded is not None:
        return load_world(recorded, world_seed)
    return load_world("perfect", world_seed)


def world_servos(world: Any, config: Any) -> list[Any]:
    """The rig's virtual servos as built, parked (where a real rig is left).

    Each servo lands within ``world.servos.landing_pulses`` of its goals (errors seeded
    from the world's seed) and starts on the side of its backlash the world says
    (``initial_approach`` per joint, in the joint's sense: turned into the horn's sense
    by the servo's ``direction``).
    """
    from gonio.simulator.servo_model import VirtualServo

    park = config.park_pulses
    return [
        VirtualServo(
            s.id,
            model=s.model,
            position=park[s.id],
            landing_pulses=world.servos.landing_pulses,
            landing_seed=world.seed,
            last_direction=world.approach0(s.joint) * s.direction,
        )
        for s in config.servos
    ]


def world_pose_provider(world: Any, config: Any, bus: Any) -> Callable[[], Any]:
    """Poses of the as-built rig from the virtual servos' physical state.

    ``config`` is the NOMINAL rig configuration (the world's errors are relative to it).
    """
    from gonio.simulator.world_kinematics import NominalRig, true_poses

    rig = NominalRig.of(config.model_dump(mode="json"))

    def poses() -> Any:
        return true_poses(world, rig, bus.servo_states())

    return poses


def nominal_scene(
    document: Mapping[str, Any] | None,
    base_dir: Path | None,
    width: int | None = None,
    height: int | None = None,
) -> Any:
    """The scene as drawn (nominal camera), at the session's resolution."""
    from gonio.simulator.rig_camera import minimal_scene
    from gonio.simulator.scene import parse_scene

    doc, _ = split_scene_world(document if document is not None else minimal_scene())
    scene = parse_scene(doc, "<simulated camera scene>", base_dir)
    if width or height:
        w, h = scene.camera.resolution
        cam = scene.camera.model_copy(update={"resolution": (int(width or w), int(height or h))})
        scene = scene.model_copy(update={"camera": cam})
    return scene


def as_built_scene(world: Any, scene: Any) -> Any:
    """``scene`` with its camera as built (the same object for a perfect camera)."""
    cam = world.as_built_camera(scene.camera)
    return scene if cam is scene.camera else scene.model_copy(update={"camera": cam})


def simulated_camera_kwargs(world: Any) -> dict[str, Any]:
    """Extra constructor arguments of the simulated camera: its ``serial`` from the world
    (when the camera accepts one and the world's camera is not the nominal one), and the
    ``world`` itself when its radiometry is not off (the light's profile and drift, the
    room's light, the sensor's fixed patterns: the camera renders them)."""
    from gonio.simulator.rig_camera import SimulatedRigCamera

    accepts = inspect.signature(SimulatedRigCamera).parameters
    out: dict[str, Any] = {}
    serial = world.camera_serial()
    if serial is not None and "serial" in accepts:
        out["serial"] = serial
    if not world.radiometry.off and "world" in accepts:
        out["world"] = world
    return out

"""Building a session's devices, real or simulated: the one place that wires them.

:func:`device_opener` gives the session API (:mod:`gonio.capture.sessions`) what it asks
for: a rig (a virtual Dynamixel bus on a pty for ``bus.port = "virtual"``, driven through
the real dynamixel-sdk like the lab rig), its kinematics, and a camera -- gphoto2, or the
simulator's :class:`~gonio.simulator.rig_camera.SimulatedRigCamera`, which is also the
session's light and target changer and sees the pose the virtual servos reached.

A virtual bus keeps servo time on a virtual clock by default (:data:`DEFAULT_TIME_SCALE`,
``"virtual"``): moves and settle times cost no wall time, and the journal is the one a
watched session (a speed-up factor, e.g. ``--sim-speed 20``) writes.

A simulated session renders the as-built world its simulation record names
(:mod:`gonio.app.world_wiring`; none recorded: ``perfect``, exactly the rig as configured):
the camera sees the world's true pose of the servos' physical state through the as-built
lens, while ``reduction.toml`` and the controller keep the nominal rig and camera.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from gonio.app.light_switch import open_light
from gonio.capture.engine import SessionDevices
from gonio.capture.sessions import DeviceOpener, DeviceRequest
from gonio.devices import RigDevice

__all__ = [
    "DEFAULT_TIME_SCALE",
    "VIRTUAL_PORTS",
    "device_opener",
    "is_virtual_port",
    "open_rig",
    "open_session_devices",
]

VIRTUAL_PORTS = ("virtual", "sim", "simulated")

#: Packet timeout (ms) on a virtual bus whose rig configuration sets none: the SDK's
#: default budget (~35 ms at 1 Mbaud) is for a USB adapter; the virtual servos' thread
#: shares the CPU with the rest of the session and, on a loaded machine (8 test workers
#: on 2 cores), missed it often enough to end sessions on a "did not answer" fault.  A
#: reply is never waited for longer than it takes: only a silent servo costs the time.
VIRTUAL_BUS_TIMEOUT_MS = 250.0

#: A virtual bus's speed when neither the caller nor the session's simulation record
#: says: servo time advances by the commanded motion, not by the wall clock.
DEFAULT_TIME_SCALE = "virtual"


def is_virtual_port(port: str) -> bool:
    """A rig port that asks for the simulator's virtual bus (``"virtual"``)."""
    return port.strip().lower() in VIRTUAL_PORTS


@contextlib.contextmanager
def open_rig(config: Any, clock: Callable[[], float] | None = None) -> Iterator[RigDevice]:
    """Open the rig of ``config`` (pings, checks models, reboots servos left in a fault).

    ``clock`` (s) times its moves (a virtual bus's servo clock); default the wall clock.
    """
    from gonio.rig.device import Rig

    with Rig(config, clock=clock) as rig:
        yield rig


@contextlib.contextmanager
def open_session_devices(
    request: DeviceRequest,
    *,
    camera_port: str | None = None,
    time_scale: float | str | None = None,
    scene: Mapping[str, Any] | None = None,
    scene_base: Path | None = None,
    light_spec: str | None = None,
    render_ahead: Any = None,
) -> Iterator[SessionDevices]:
    """Open the rig, its kinematics and the camera a session asks for.

    Parameters
    ----------
    request
        What the session needs (rig configuration, camera backend, seed, simulation).
    camera_port
        gphoto2 port.
    time_scale
        Speed of a virtual bus: ``"virtual"`` (servo time advances by the commanded
        motion and the settle times) or a speed-up factor over the wall clock; default
        the simulation record's, else :data:`DEFAULT_TIME_SCALE`.
    scene, scene_base
        The scene to render and the folder its paths start from (a new run: the user's
        files); by default the simulation record's scene, relative to the session.
    render_ahead
        A :class:`gonio.app.render_ahead.RenderAhead` worker (forked by the caller
        before any thread): a simulated camera of a perfect world then has its next
        poses rendered ahead on the second core (the same frames); None: no worker.

    Everything opened is closed on exit (torque off is the session finalizer's job and
    is repeated by the rig's own exit as a last resort).
    """
    from gonio.app.world_wiring import (
        as_built_scene,
        nominal_scene,
        resolve_world,
        simulated_camera_kwargs,
        world_pose_provider,
        world_servos,
    )
    from gonio.rig.kinematics import Kinematics

    cfg = request.rig_config
    # The world's errors are relative to the rig as drawn: a calibrated configuration
    # carries the nominal one it was calibrated from.
    nominal_cfg = _nominal_of(cfg)
    sim = dict(request.simulation or {})
    # The as-built world: recorded in the simulation record (a new run writes it there,
    # resume rebuilds the same one); none recorded: perfect (sessions from before).
    world = resolve_world(recorded=sim.get("world"))
    # A real camera's rig cannot swap the calibration mirror in: the operator does.
    # Whether someone is there to answer is asked before the rig is even opened.
    target = None
    if request.camera_backend != "simulated" and (
        any(p.target == "mirror" for p in request.plan.joint_poses) or request.plan.flats.count
    ):
        from gonio.app.operator import OperatorTargetChanger

        target = OperatorTargetChanger()
    kin = Kinematics(cfg)
    bus = None
    with contextlib.ExitStack() as stack:
        sleep: Callable[[float], None] = time.sleep
        clock: Callable[[], float] | None = None
        if is_virtual_port(cfg.bus.port):
            from gonio.simulator.servo_clock import parse_time_scale
            from gonio.simulator.servo_model import VirtualServo
            from gonio.simulator.virtual_bus import VirtualBus

            scale = parse_time_scale(time_scale or sim.get("time_scale") or DEFAULT_TIME_SCALE)
            if world.perfect:
                # The virtual rig starts where a real one is left: parked.
                park = cfg.park_pulses
                servos = [
                    VirtualServo(s.id, model=s.model, position=park[s.id]) for s in cfg.servos
                ]
            else:
                servos = world_servos(world, cfg)
            bus = VirtualBus(
                servos, baud_rate=cfg.bus.baud_rate, seed=request.seed, time_scale=scale
            )
            stack.enter_context(bus)
            link: dict[str, Any] = {"port": bus.port}
            if cfg.bus.timeout_ms is None:
                # The virtual servos answer from a thread of this process: on a busy
                # machine it can be scheduled later than a USB adapter's budget.
                link["timeout_ms"] = VIRTUAL_BUS_TIMEOUT_MS
            cfg = cfg.model_copy(update={"bus": cfg.bus.model_copy(update=link)})
            # Settle times and move durations in servo time, whichever clock it keeps.
            sleep, clock = bus.sleep, bus.clock
        rig = stack.enter_context(open_rig(cfg, clock))
        # Rig time for the journal's shots (and the simulated light's drift): the servo
        # clock of a virtual bus, else the wall's monotonic clock.
        rig_clock: Callable[[], float] = clock if clock is not None else time.monotonic
        if request.camera_backend == "simulated":
            from gonio.simulator.rig_camera import SimulatedRigCamera

            if scene is None:
                scene = sim.get("scene")
                legacy = (scene or {}).get("_base_dir") if isinstance(scene, dict) else None
                if legacy:  # sessions from before relocatable manifests
                    scene = {k: v for k, v in scene.items() if k != "_base_dir"}
                scene_base = Path(legacy) if legacy else request.session_dir
                if isinstance(scene, dict) and "schema_version" not in scene:
                    # recorded before scene schema 2: resume renders as the session began
                    scene = {**scene, "schema_version": 1}
            refl = request.reference_reflectance
            if refl is None:
                refl = sim.get("reference_reflectance")
            if isinstance(refl, list | tuple):
                refl = tuple(float(x) for x in refl)

            def poses() -> Any:
                return kin.poses({k: float(v) for k, v in rig.read().joints.items()})

            drawn = nominal_scene(
                dict(scene) if scene is not None else None,
                scene_base,
                sim.get("width"),
                sim.get("height"),
            )
            if not world.perfect and bus is not None:
                # The camera sees where the rig really is: the world's physics of the
                # servos' true state, not the controller's read-back.
                poses = world_pose_provider(world, nominal_cfg, bus)
            camera = SimulatedRigCamera(
                as_built_scene(world, drawn),
                poses,
                request.seed,
                **({"reference_albedo": refl} if refl is not None else {}),
                **simulated_camera_kwargs(world),
                clock=rig_clock,
                # frames take rig time on a virtual bus (a wall clock passes by itself)
                sleep=sleep if bus is not None else None,
            )
            stack.callback(camera.close)
            if (
                render_ahead is not None
                and render_ahead.active
                and bus is not None
                and world.perfect
                and not simulated_camera_kwargs(world)
                and refl is not None
            ):
                camera = _rendered_ahead(
                    camera, render_ahead, poses, rig, kin, request, refl, sleep
                )
            from gonio.app.sim_reduction import CONFIG_FILE, reduction_document, reduction_toml_text

            # The reduction learns the simulated camera as a lab's reduction learns its
            # camera: from the session's reduction.toml, never from the scene -- and the
            # NOMINAL camera (the drawing), as a lab knows it before calibrating.
            setup = reduction_toml_text(reduction_document(drawn, refl))
            files = {CONFIG_FILE: setup.encode()}
            if drawn.sample.spatially_varying:
                from gonio.simulator.svbrdf import TRUTH_FILE, truth_bytes

                # the sample's maps beside the DNGs, for tests and benchmarks only: the
                # reduction and the fit never read them
                files[TRUTH_FILE] = truth_bytes(drawn)
            yield SessionDevices(
                rig,
                camera,
                light=camera,
                target=camera,
                kinematics=kin,
                sleep=sleep,
                read_noise_dn=camera.read_noise_dn,
                files=files,
                clock=rig_clock,
            )
            return
        from gonio.capture.camera import open_camera

        camera = open_camera(
            request.camera_backend, **({"port": camera_port} if camera_port else {})
        )
        stack.callback(camera.close)
        light = open_light(light_spec) if light_spec is not None else None
        if light is not None:
            stack.callback(getattr(light, "close", lambda: None))
        yield SessionDevices(
            rig, camera, light=light, target=target, kinematics=kin, sleep=sleep, clock=rig_clock
        )


def _rendered_ahead(
    camera: Any,
    ahead: Any,
    poses: Callable[[], Any],
    rig: Any,
    kin: Any,
    request: DeviceRequest,
    reference_albedo: Any,
    sleep: Callable[[float], None],
) -> Any:
    """``camera`` with its next poses rendered by ``ahead``'s worker
    (:class:`gonio.app.render_ahead.RenderAheadCamera`): the schedule comes from the
    session's manifest, written once the devices are open."""
    from gonio.app.render_ahead import RenderAheadCamera, predicted_poses
    from gonio.capture.manifest import load_manifest

    def steps() -> list[dict[str, Any]]:
        return list(load_manifest(request.session_dir).get("schedule") or [])

    return RenderAheadCamera(
        camera,
        ahead,
        poses,
        steps,
        lambda step: predicted_poses(rig, kin, step),
        reference_albedo,
        sleep,
    )


def _nominal_of(cfg: Any) -> Any:
    """The nominal rig a configuration describes (itself, unless it is a calibrated one)."""
    record = getattr(cfg, "calibration", None)
    if record is None or record.nominal is None:
        return cfg
    from gonio.rig.config import rig_config_from_dict

    return rig_config_from_dict(dict(record.nominal), "rig configuration: calibration.nominal")


def device_opener(
    *,
    camera_port: str | None = None,
    time_scale: float | str | None = None,
    scene: Mapping[str, Any] | None = None,
    scene_base: Path | None = None,
    light_spec: str | None = None,
    render_ahead: Any = None,
) -> DeviceOpener:
    """A device opener for :func:`gonio.capture.sessions.run_session` /
    :func:`~gonio.capture.sessions.resume_session` (see :func:`open_session_devices`)."""

    def opener(request: DeviceRequest) -> contextlib.AbstractContextManager[SessionDevices]:
        return open_session_devices(
            request,
            camera_port=camera_port,
            time_scale=time_scale,
            scene=scene,
            scene_base=scene_base,
            light_spec=light_spec,
            render_ahead=render_ahead,
        )

    return opener

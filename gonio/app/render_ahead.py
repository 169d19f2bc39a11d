"""Rendering a simulated session's next poses on the second core, ahead of the capture.

A simulated frame is a render of the pose (the costly part, once per pose) and a sensor
exposure of it (per frame).  The render needs only the scene and the pose; the capture
engine needs the frame only after the rig has moved there.  :class:`RenderAhead` is a
process forked when the demo starts (before any thread, lock or numba pool exists, as
:mod:`gonio.figure_worker`) that renders the poses the session's schedule will visit
next, predicted from the schedule's joints as the rig will quantise them
(:func:`predicted_poses`).  :class:`RenderAheadCamera` wraps the session's
:class:`~gonio.simulator.rig_camera.SimulatedRigCamera`: at each shot it builds the
scene of the pose the rig *did* reach (the same pose provider the camera reads) and
takes the worker's render only when that scene is the worker's, JSON for JSON -- then
the render's input is the camera's own, and the frame's bytes are too.  Anything else
(a pose not predicted, a missed prediction, a dark frame, a flat, a mirror, an as-built
world's radiometry, a worker that died) is the wrapped camera's own capture, as
without this module.

Why a process and not a thread: the render is numpy and numba code that holds the GIL
for much of its time, and the capture's own work (bus traffic, journal, the bracket's
frame decoding) is Python; two processes use two cores.  Why not
:class:`concurrent.futures.ProcessPoolExecutor`: its processes start (spawn) when the
first job arrives, paying the imports while the capture waits, and a pool gives no
place to keep the one camera (its BRDF, its per-camera tables) that every render uses.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from gonio.app.forked_server import ForkedServer
from gonio.errors import CameraError, GonioError

__all__ = ["ENV", "RenderAhead", "RenderAheadCamera", "predicted_poses"]

log = logging.getLogger(__name__)

#: ``GONIO_RENDER_AHEAD=0``: no worker; the simulated camera renders every pose itself.
ENV = "GONIO_RENDER_AHEAD"

#: How many steps past the one being shot are handed to the worker: two keeps it busy
#: through a short pose, and a render left over when a pose is skipped costs one render.
DEPTH = 2

#: Targets the worker renders: the sample and the reference target, lit.  Darks, flats
#: and the mirror are the camera's own (rare, and the mirror's spot search differs).
_RENDERED = ("sample", "reference")


def _serve(conn: Any) -> None:
    """The worker's loop: ``("setup", scene, reference_albedo)``, then ``("render", step,
    poses, target)`` answered by ``("done", step, key, site_radiance)`` or ``("failed",
    step, message)``; the end of the pipe ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the command's to handle
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.rig_camera import minimal_scene
    from gonio.simulator.scene import parse_scene

    # Warm: the renderer's kernels are loaded (from numba's cache) by a tiny render, so
    # the first pose of the session does not pay for them.
    with contextlib.suppress(Exception):
        SimulatedCamera(parse_scene(minimal_scene(16, 12), "<warm-up>")).render("sample")
    pose: list[Any] = [None]
    cam: Any = None
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        if msg[0] == "close":
            break
        if msg[0] == "setup":
            _, scene, reference_albedo = msg
            cam = SimulatedCamera(
                scene, pose_provider=lambda: pose[0], reference_albedo=reference_albedo
            )
            continue
        _, step, poses, target = msg
        try:
            if cam is None:
                raise CameraError("render-ahead worker: no scene set up")
            pose[0] = poses
            key = cam.current_scene(target).model_dump_json()
            reply: tuple = ("done", step, key, cam.site_radiance(target))
        except Exception as exc:  # noqa: BLE001 - the camera itself reports it at the shot
            reply = ("failed", step, f"{type(exc).__name__}: {exc}")
        try:
            conn.send(reply)
        except (EOFError, OSError):
            break
    os._exit(0)


class RenderAhead(ForkedServer):
    """A forked process rendering poses ahead of a simulated capture.

    Parameters
    ----------
    enabled
        False (or ``GONIO_RENDER_AHEAD=0``, or not Linux, or a failed fork): no process;
        :attr:`active` is False and the camera renders every pose itself.

    Fork it before the command starts threads (the virtual bus's, a progress bar's) or
    numba's pool: the child keeps only the forking thread.
    """

    def __init__(self, enabled: bool = True) -> None:
        self._pending: set[int] = set()
        self._results: dict[int, tuple] = {}
        self.hits = 0
        self.misses = 0
        super().__init__(_serve, name="render-ahead", env=ENV, enabled=enabled)

    def setup(self, scene: Any, reference_albedo: Any) -> bool:
        """Give the worker the camera's scene (a :class:`~gonio.simulator.scene.Scene`)
        and reference albedo; False when there is no worker."""
        return self._send(("setup", scene, reference_albedo))

    def submit(self, step: int, poses: Any, target: str) -> bool:
        """Render ``target`` at ``poses`` for step ``step`` (one job per step)."""
        if step in self._pending or step in self._results:
            return True
        if not self._send(("render", int(step), poses, target)):
            return False
        self._pending.add(int(step))
        return True

    def submitted(self, step: int) -> bool:
        """A job for ``step`` is queued, running or done."""
        return step in self._pending or step in self._results

    def take(self, step: int, key: str) -> np.ndarray | None:
        """The site radiance of step ``step`` if the worker rendered exactly the scene
        ``key`` (JSON), waiting for a job in flight; None otherwise."""
        while step in self._pending and self.active:
            self._receive()
        res = self._results.get(step)
        if res is None or res[0] != "done" or res[1] != key:
            self.misses += 1
            return None
        self.hits += 1
        return res[2]

    def forget_before(self, step: int) -> None:
        """Drop the renders of steps before ``step`` (the capture has left them)."""
        for s in [s for s in self._results if s < step]:
            del self._results[s]

    def _receive(self) -> None:
        try:
            msg = self._conn.recv()
        except (EOFError, OSError):
            self.close()
            return
        step = msg[1]
        self._pending.discard(step)
        self._results[step] = ("done", msg[2], msg[3]) if msg[0] == "done" else ("failed",)

    def close(self) -> None:
        """End the worker (idempotent); renders not taken are dropped."""
        if self._conn is not None:
            log.debug(
                "render-ahead: %d shots from the worker's renders, %d not", self.hits, self.misses
            )
        self._pending.clear()
        super().close()


def predicted_poses(rig: Any, kinematics: Any, step: Mapping[str, Any]) -> Any:
    """The poses (``kinematics.poses``) the rig will read back at a schedule step of a
    nominal rig whose servos land on their goals, or None when not predictable.

    The goal is :meth:`gonio.rig.device.Rig.quantised_goals` of the step's joints (what
    ``move_to`` sends) and the joint angles are those a state read decodes from goal
    pulses, ``(pulses - zero) * direction * RAD_PER_PULSE / gear_ratio`` (the same
    operations, so the same floats).  A wrong prediction costs a render, never a
    different frame: the camera compares the scenes.
    """
    from gonio.rig import control_table as ct

    joints = step.get("joints")
    if not joints or step.get("wi") is None or step.get("wo") is None:
        return None
    if not getattr(kinematics, "nominal", False):
        return None  # as built: the backlash side decides; not worth predicting
    try:
        wi = np.asarray(step["wi"], dtype=np.float64)
        wo = np.asarray(step["wo"], dtype=np.float64)
        wi, wo = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
        goals = rig.quantised_goals(wi, wo, {j: float(v) for j, v in joints.items()})
        read: dict[str, float] = {}
        for j, servo in rig.servos.items():
            c = servo.config
            zero = c.zero_deg * ct.PULSES_PER_TURN / 360.0
            scale = c.direction * ct.RAD_PER_PULSE / c.gear_ratio
            read[j] = float((goals[servo.id] - zero) * scale)
        return kinematics.poses(read)
    except (GonioError, KeyError, TypeError, ValueError):
        return None


class RenderAheadCamera:
    """A :class:`~gonio.simulator.rig_camera.SimulatedRigCamera` whose poses are
    rendered ahead by a :class:`RenderAhead` worker (see the module docstring).

    Parameters
    ----------
    camera
        The session's simulated camera (perfect world: no radiometry of its own).
    ahead
        The worker (its scene is set up here).
    pose_provider
        The camera's pose provider (the rig's read-back through the kinematics).
    steps
        Returns the session's schedule steps (``manifest.json``'s ``schedule``), read
        when the first shot is named (the manifest is written after the devices open).
    predict
        ``predict(step) -> poses | None`` (:func:`predicted_poses` on the session's rig).
    reference_albedo
        The camera's reference target reflectance.
    sleep
        The camera's rig-time sleep (a frame takes its exposure plus the download).

    It is the camera, light and target changer the session sees; each shot the worker
    rendered is exposed here with the camera's own sensor model, seed and download
    time; every other shot is the wrapped camera's.
    """

    def __init__(
        self,
        camera: Any,
        ahead: RenderAhead,
        pose_provider: Callable[[], Any],
        steps: Callable[[], Sequence[Mapping[str, Any]]],
        predict: Callable[[Mapping[str, Any]], Any],
        reference_albedo: Any,
        sleep: Callable[[float], None] | None,
    ) -> None:
        from gonio.simulator.camera import SimulatedCamera

        self.camera = camera
        self.ahead = ahead
        self._steps_source = steps
        self._steps: Sequence[Mapping[str, Any]] | None = None
        self._predict = predict
        self._sleep = sleep
        # Builds the scene a shot sees exactly as the camera does (pose, then target);
        # it never renders.
        self._scenes = SimulatedCamera(
            camera.scene, pose_provider=pose_provider, reference_albedo=reference_albedo
        )
        self._light_on = True
        self._target = "sample"
        self._next: tuple[int, int] | None = None
        ahead.setup(camera.scene, reference_albedo)

    # -- what passes through ------------------------------------------------------------
    @property
    def scene(self) -> Any:
        return self.camera.scene

    @property
    def seed(self) -> int:
        return self.camera.seed

    def describe(self) -> Any:
        return self.camera.describe()

    def read_noise_dn(self, iso: float) -> float:
        return self.camera.read_noise_dn(iso)

    def rig_time(self) -> float:
        return self.camera.rig_time()

    def set_light(self, on: bool) -> None:
        self.camera.set_light(on)
        self._light_on = bool(on)

    def set_target(self, kind: str) -> None:
        self.camera.set_target(kind)  # refuses an unknown kind
        self._target = kind

    def close(self) -> None:
        self.camera.close()  # the worker is its owner's to end

    # -- the shots ----------------------------------------------------------------------
    def next_shot(self, step: int, frame: int) -> None:
        """The next capture is frame ``frame`` of step ``step``; the steps after it go to
        the worker."""
        self._next = (int(step), int(frame))
        self._look_ahead(int(step))

    def _look_ahead(self, step: int) -> None:
        if not self.ahead.active:
            return
        if self._steps is None:
            try:
                self._steps = list(self._steps_source())
            except (GonioError, OSError):
                self._steps = []
        self.ahead.forget_before(step)
        for s in range(step, min(step + 1 + DEPTH, len(self._steps))):
            entry = self._steps[s]
            if entry.get("kind") not in _RENDERED or self.ahead.submitted(s):
                continue
            poses = self._predict(entry)
            if poses is None or not self.ahead.submit(s, poses, entry["kind"]):
                continue

    def capture(self, exposure_time: float, iso: float | None, f_number: float | None) -> Any:
        """The frame, from the worker's render when it rendered this very scene."""
        named, self._next = self._next, None
        site = None
        if named is not None and self._light_on and self._target in _RENDERED:
            site = self.ahead.take(
                named[0], self._scenes.current_scene(self._target).model_dump_json()
            )
        if site is None:
            if named is not None:
                self.camera.next_shot(*named)
            return self.camera.capture(exposure_time, iso, f_number)
        return self._expose(site, named, exposure_time, iso, f_number)

    def _expose(
        self,
        site: np.ndarray,
        named: tuple[int, int],
        exposure_time: float,
        iso: float | None,
        f_number: float | None,
    ) -> Any:
        """What :meth:`SimulatedRigCamera.capture` does with the pose's render, for a
        camera without an as-built world's radiometry: the sensor at the shot's seed,
        the DNG, the frame's rig time."""
        from gonio.devices import Shot
        from gonio.errors import ParameterError
        from gonio.simulator.dng import dng_bytes
        from gonio.simulator.rig_camera import shot_seed
        from gonio.simulator.sensor import simulate_mosaic

        if not (isinstance(exposure_time, int | float) and math.isfinite(exposure_time)):
            raise CameraError(f"exposure_time = {exposure_time!r}: expected a finite number of s")
        if exposure_time <= 0:
            raise CameraError(f"exposure_time = {exposure_time!r}: expected a positive time, s")
        cam = self.camera.scene.camera
        iso_v = float(cam.iso if iso is None else iso)
        f_v = float(cam.f_number if f_number is None else f_number)
        for name, v in (("iso", iso_v), ("f_number", f_v)):
            if not (math.isfinite(v) and v > 0):
                raise CameraError(f"simulated camera does not support {name} = {v!r}")
        try:
            frame = simulate_mosaic(
                site.copy(),
                cam,
                exposure_time=exposure_time,
                iso=iso_v,
                f_number=f_v,
                seed=np.random.default_rng(shot_seed(self.camera.seed, *named)),
                fixed_pattern=None,
            )
        except ParameterError as exc:
            raise CameraError(f"simulated camera: {exc}") from exc
        data = dng_bytes(frame)
        if self._sleep is not None:
            self._sleep(float(exposure_time) + self.camera.download_s)
        return Shot(
            data=data,
            suffix=".dng",
            exposure_time=float(exposure_time),
            iso=iso_v,
            f_number=f_v,
            extra={"target": self._target, "light": self._light_on},
        )

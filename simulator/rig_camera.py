"""The simulated rig camera: what the rig's camera would see at the pose the rig reached.

It implements the core's device interfaces (:mod:`gonio.devices`): :class:`Camera`
(each capture asks ``pose_provider()`` where the light and camera are now, renders the
scene there with :class:`gonio.simulator.camera.SimulatedCamera` and returns its DNG),
and the abilities a real rig gets from extra hardware, :class:`Light` (dark frames are
exposures with the light off; the room's light still reaches them) and
:class:`TargetChanger` (the reference target or the mirror in the sample's place, or a
flat light panel over the lens), plus :class:`SeededShots`: the session seed is given at
construction and the engine names each shot's (step, frame) with :meth:`next_shot` before
capturing it, so its noise is drawn from :func:`shot_seed` -- a session is reproducible
bit for bit, and a shot redone after a crash renders the same bytes.

The camera knows nothing of the rig's kinematics: the composition root wires
``pose_provider = lambda: Kinematics(cfg).poses(rig.read().joints)``, and the rig's time
``clock`` (the virtual bus's servo clock): the as-built ``world``'s light drifts with it
(``world.light_output(clock())`` at each lit shot), so the drift is a function of exactly
the ``rig_time`` the engine journals.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gonio.devices import CameraInfo, Shot
from gonio.errors import CameraError, ConfigError
from gonio.simulator.camera import TARGETS, SimulatedCamera
from gonio.simulator.scene import Scene, parse_scene

__all__ = ["DOWNLOAD_S", "SimulatedRigCamera", "minimal_scene", "shot_seed"]

#: Rig time a simulated frame's RAW file takes to reach the host, s: a lab camera over
#: USB 2 downloads a 25-30 MB RAW in about a second (the example plan's
#: ``shot_overhead_s`` is 0.8 s for the same reason).
DOWNLOAD_S = 0.8


def shot_seed(seed: int, step: int, frame: int) -> int:
    """Seed of the sensor noise of frame ``frame`` of step ``step`` in a session of
    ``seed``: a session is reproducible from its seed, and a redone shot renders the same
    noise."""
    return int(np.random.SeedSequence([int(seed), int(step), int(frame)]).generate_state(1)[0])


def minimal_scene(width: int = 64, height: int = 48) -> dict[str, Any]:
    """A small scene document (lambert+ggx sample on a holder, one disk light): the
    fallback when a plan names no scene.  Poses come from the rig at capture time."""
    return {
        "sample": {
            "width": 0.05,
            "height": 0.05,
            "brdf": {
                "model": "lambert+ggx",
                "params": {"albedo": [0.5, 0.4, 0.3], "ks": 0.04, "alpha": 0.2},
            },
        },
        "holder": {"width": 0.15, "height": 0.15, "albedo_black": 0.04, "albedo_white": 0.85},
        "lights": [
            {
                "type": "disk",
                "position": [0.0, 0.25, 0.433],
                "look_at": [0.0, 0.0, 0.0],
                "radius": 0.01,
                "radiance": [10.0, 10.0, 10.0],
            }
        ],
        "camera": {
            "resolution": [int(width), int(height)],
            "focal_length": 0.035,
            "fov_deg": 26.0,
            "position": [0.0, -0.25, 0.433],
            "look_at": [0.0, 0.0, 0.0],
        },
        "render": {"strategy": "point", "antialias": 1},
    }


class SimulatedRigCamera:
    """Renders the rig's current pose; a camera, a light and a target changer.

    Parameters
    ----------
    scene
        A :class:`gonio.simulator.scene.Scene`, a scene document (dict), or None for
        :func:`minimal_scene`.
    pose_provider
        Returns the present poses (``gonio.rig.kinematics.RigPoses`` or a mapping with
        ``camera_position``, ``camera_rotation``, ``light_position``, ``light_normal``).
    seed
        The session seed; each shot's noise comes from ``shot_seed(seed, step, frame)``.
    width, height
        Override the scene's resolution (quick runs), pixels.
    reference_albedo
        Reflectance of the rendered reference target.
    base_dir
        Folder a scene document's relative paths start from.
    serial
        The camera unit's serial number, reported by :meth:`describe` (calibrations
        name the camera they belong to by it); the as-built world gives one.
    clock
        Rig time, s (``Devices.clock``: the servo clock of a simulated rig), read when a
        frame is shot; None: t = 0 (no drift).
    world
        The as-built :class:`~gonio.simulator.world.World` whose radiometry the camera
        sees (light profile and drift, ambient and stray light, sensor defects; its
        geometry is the caller's: pose provider and as-built scene camera); None: none.
    sleep, download_s
        ``sleep(s)`` waits rig time (the virtual bus's ``sleep``): after each frame the
        camera spends its exposure plus ``download_s`` (s, the RAW file's transfer to the
        host; a lab camera over USB takes about a second) of rig time, as a real camera
        would, so a simulated session's rig time -- and the light's warm-up drift over
        it -- runs as long as a lab session's.  None: frames take no rig time.
    """

    def __init__(
        self,
        scene: Scene | dict[str, Any] | None,
        pose_provider: Callable[[], Any],
        seed: int = 0,
        *,
        width: int | None = None,
        height: int | None = None,
        reference_albedo: float | tuple[float, float, float] = 0.99,
        base_dir: str | Path | None = None,
        serial: str | None = None,
        clock: Callable[[], float] | None = None,
        world: Any = None,
        sleep: Callable[[float], None] | None = None,
        download_s: float = DOWNLOAD_S,
    ) -> None:
        if pose_provider is None:
            raise CameraError("the simulated camera needs a pose provider (the rig's pose)")
        if scene is None:
            scene = minimal_scene()
        if isinstance(scene, dict):
            scene = parse_scene(
                scene, "<simulated camera scene>", Path(base_dir) if base_dir else None
            )
        if not isinstance(scene, Scene):
            raise ConfigError(f"scene must be a gonio.simulator Scene or dict, got {type(scene)}")
        if width or height:
            w, h = scene.camera.resolution
            cam = scene.camera.model_copy(
                update={"resolution": (int(width or w), int(height or h))}
            )
            scene = scene.model_copy(update={"camera": cam})
        self.scene = scene
        self.seed = int(seed)
        self.serial = None if serial is None else str(serial)
        if clock is not None and not callable(clock):
            raise CameraError(
                f"clock must be a callable returning the rig time in s, got {clock!r}"
            )
        self.clock = clock
        if sleep is not None and not callable(sleep):
            raise CameraError(f"sleep must be a callable taking seconds, got {sleep!r}")
        if not (math.isfinite(download_s) and download_s >= 0):
            raise CameraError(f"download_s = {download_s!r}: expected a finite time >= 0 s")
        self._sleep = sleep
        self.download_s = float(download_s)
        self._cam = SimulatedCamera(
            scene, pose_provider=pose_provider, reference_albedo=reference_albedo, world=world
        )
        self.world = world
        self._light_on = True
        self._target = "sample"
        self._closed = False
        self._next: tuple[int, int] | None = None
        self._unnamed = 0

    # -- SeededShots --------------------------------------------------------------------
    def next_shot(self, step: int, frame: int) -> None:
        """The next capture is frame ``frame`` of step ``step`` (its noise stream)."""
        self._next = (int(step), int(frame))

    def _shot_seed(self) -> int:
        if self._next is None:
            # Not named by an engine (a bare capture): a stream of its own, still
            # reproducible from the seed, that no (step, frame) of a session can reach.
            self._unnamed += 1
            return shot_seed(self.seed, 2**32 - 1, self._unnamed)
        step, frame = self._next
        self._next = None
        return shot_seed(self.seed, step, frame)

    # -- Camera -------------------------------------------------------------------------
    def describe(self) -> CameraInfo:
        """The simulated sensor (resolution, focal length, noise, levels)."""
        cam = self.scene.camera
        w, h = cam.resolution
        pitch_mm = cam.pitch * 1e3
        return CameraInfo(
            backend="simulated",
            model=self._cam.model,
            serial=self.serial,
            sensor_size_mm=(w * pitch_mm, h * pitch_mm),
            settings={
                "resolution": [w, h],
                "focal_length_m": cam.focal_length,
                "read_noise_e": cam.sensor.read_noise,
                "black_level": cam.sensor.black_level,
                "white_level": cam.sensor.white_level,
            },
        )

    def read_noise_dn(self, iso: float) -> float:
        """Read noise in DN rms at ``iso`` (for the bracket's noise floor)."""
        s = self.scene.camera.sensor
        return float(s.read_noise * s.gain_at_base_iso * iso / s.base_iso)

    def capture(self, exposure_time: float, iso: float | None, f_number: float | None) -> Shot:
        """Render the reached pose and expose it for ``exposure_time`` s; a DNG
        :class:`~gonio.devices.Shot`."""
        if self._closed:
            raise CameraError("simulated camera is closed")
        if not (isinstance(exposure_time, int | float) and math.isfinite(exposure_time)):
            raise CameraError(f"exposure_time = {exposure_time!r}: expected a finite number of s")
        if exposure_time <= 0:
            raise CameraError(f"exposure_time = {exposure_time!r}: expected a positive time, s")
        cam = self.scene.camera
        iso_v = float(cam.iso if iso is None else iso)
        f_v = float(cam.f_number if f_number is None else f_number)
        for name, v in (("iso", iso_v), ("f_number", f_v)):
            if not (math.isfinite(v) and v > 0):
                raise CameraError(f"simulated camera does not support {name} = {v!r}")
        seed = self._shot_seed()
        if self._cam.radiometry is not None:
            data = self._cam.capture(
                exposure_time,
                iso_v,
                f_v,
                seed,
                target=self._target,
                rig_time=self.rig_time(),
                light_on=self._light_on,
            )
        elif self._target == "flat":
            data = self._cam.capture(exposure_time, iso_v, f_v, seed, target="flat")
        elif self._light_on:
            data = self._cam.capture(exposure_time, iso_v, f_v, seed, target=self._target)
        else:
            data = self._dark(exposure_time, iso_v, f_v, seed)
        if self._sleep is not None:
            self._sleep(float(exposure_time) + self.download_s)
        return Shot(
            data=data,
            suffix=".dng",
            exposure_time=float(exposure_time),
            iso=iso_v,
            f_number=f_v,
            extra={"target": self._target, "light": self._light_on},
        )

    def rig_time(self) -> float:
        """The rig time now, s (0 without a clock)."""
        if self.clock is None:
            return 0.0
        t = float(self.clock())
        if not math.isfinite(t):
            raise CameraError(f"the rig clock returned {t!r}: expected a finite time in s")
        return t

    def _dark(self, exposure_time: float, iso: float, f_number: float, seed: int) -> bytes:
        from gonio.simulator.dng import dng_bytes
        from gonio.simulator.sensor import simulate_raw

        w, h = self.scene.camera.resolution
        frame = simulate_raw(
            np.zeros((h, w, 3)),
            self.scene.camera,
            exposure_time=exposure_time,
            iso=iso,
            f_number=f_number,
            seed=np.random.default_rng(seed),
        )
        return dng_bytes(frame)

    def close(self) -> None:
        """Release the camera (idempotent)."""
        self._closed = True

    # -- Light, TargetChanger -----------------------------------------------------------
    def set_light(self, on: bool) -> None:
        """Switch the simulated light (dark frames are exposures with it off)."""
        self._light_on = bool(on)

    def set_target(self, kind: str) -> None:
        """``"sample"``, ``"reference"`` (the Lambertian target in the sample's place),
        ``"mirror"`` (a flat first-surface mirror there, reflectance 0.9: the light's
        image in it is the rig calibration's spot) or ``"flat"`` (a uniform diffuse light
        panel over the lens: every pixel sees the world's ``flat_radiance``, with
        vignetting and the sensor's fixed patterns and noise; the light, its drift and
        the room's light do not reach it).

        Raises
        ------
        CameraError
            Any other kind (the accepted ones are named).
        """
        if kind not in TARGETS:
            raise CameraError(
                f"set_target({kind!r}): unknown target; target must be one of "
                f"{', '.join(repr(t) for t in TARGETS)}"
            )
        self._target = kind

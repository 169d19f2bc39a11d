"""The ``simulated`` camera backend: what the rig's camera would see at the reached pose.

Each capture reads the joint angles the (virtual) servos actually reached through the
rig's status read-back, turns them into light and camera poses with
``Kinematics.poses(joints)``, renders the scene with
:class:`gonio.simulator.camera.SimulatedCamera` and returns its DNG.  The session treats it
exactly like the gphoto2 backend (:class:`gonio.capture.camera.Camera`); it adds the two
abilities a real rig gets from extra hardware: switching the light off for dark frames
(:class:`~gonio.capture.camera.LightSwitch`) and putting the reference target in place of
the sample (:class:`~gonio.capture.camera.TargetChanger`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from gonio.capture.camera import CameraInfo, Shot
from gonio.errors import CameraError, ConfigError

__all__ = ["SimulatedRigCamera", "minimal_scene"]


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
    """Camera backend that renders the rig's current pose.

    Parameters
    ----------
    rig
        The rig device; ``read_joints()`` gives the reached joint angles (rad).
    kinematics
        ``gonio.rig.kinematics.Kinematics`` of the same rig configuration.
    scene
        A :class:`gonio.simulator.scene.Scene`, a scene document (dict), or None for
        :func:`minimal_scene`.
    width, height
        Override the scene's resolution (quick runs), pixels.
    reference_albedo
        Reflectance of the rendered reference target.
    read_joints
        Alternative to ``rig``: a callable returning joint angles (rad).
    """

    def __init__(
        self,
        rig: Any = None,
        kinematics: Any = None,
        scene: Any = None,
        *,
        width: int | None = None,
        height: int | None = None,
        reference_albedo: float | tuple[float, float, float] = 0.99,
        read_joints: Callable[[], Mapping[str, float]] | None = None,
    ) -> None:
        from gonio.simulator.camera import SimulatedCamera
        from gonio.simulator.scene import Scene, parse_scene

        if read_joints is None:
            if rig is None:
                raise CameraError("the simulated camera needs the rig (to read the reached pose)")
            read_joints = rig.read_joints
        if kinematics is None:
            raise CameraError("the simulated camera needs the rig's kinematics")
        self._read_joints = read_joints
        self._kin = kinematics
        if scene is None:
            scene = minimal_scene()
        if isinstance(scene, dict):
            scene = parse_scene(scene, "<simulated camera scene>")
        if not isinstance(scene, Scene):
            raise ConfigError(f"scene must be a gonio.simulator Scene or dict, got {type(scene)}")
        if width or height:
            w, h = scene.camera.resolution
            cam = scene.camera.model_copy(
                update={"resolution": (int(width or w), int(height or h))}
            )
            scene = scene.model_copy(update={"camera": cam})
        self.scene = scene
        self._cam = SimulatedCamera(
            scene, pose_provider=self._poses, reference_albedo=reference_albedo
        )
        self._light_on = True
        self._target = "sample"
        self._closed = False

    def _poses(self):
        joints = {k: float(v) for k, v in self._read_joints().items()}
        return self._kin.poses(joints)

    # -- Camera interface ---------------------------------------------------------------
    def describe(self) -> CameraInfo:
        cam = self.scene.camera
        w, h = cam.resolution
        pitch_mm = cam.pitch * 1e3
        return CameraInfo(
            backend="simulated",
            model=self._cam.model,
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
        """Read noise in DN at ``iso`` (for the bracket's noise floor)."""
        s = self.scene.camera.sensor
        return float(s.read_noise * s.gain_at_base_iso * iso / s.base_iso)

    def capture(
        self, exposure_time: float, iso: float | None, f_number: float | None, *, seed: int = 0
    ) -> Shot:
        """Render the reached pose and expose it; DNG bytes in a :class:`Shot`."""
        if self._closed:
            raise CameraError("simulated camera is closed")
        cam = self.scene.camera
        iso_v = float(cam.iso if iso is None else iso)
        f_v = float(cam.f_number if f_number is None else f_number)
        if self._light_on:
            data = self._cam.capture(exposure_time, iso_v, f_v, seed, target=self._target)
        else:
            data = self._dark(exposure_time, iso_v, f_v, seed)
        return Shot(
            data=data,
            suffix=".dng",
            exposure_time=float(exposure_time),
            iso=iso_v,
            f_number=f_v,
            extra={"target": self._target, "light": self._light_on},
        )

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

    def set_light(self, on: bool) -> None:
        """Switch the simulated light (dark frames are exposures with it off)."""
        self._light_on = bool(on)

    def set_target(self, kind: str) -> None:
        """``"sample"`` or ``"reference"`` (the Lambertian target in the sample's place)."""
        if kind not in ("sample", "reference"):
            raise CameraError(f"target must be 'sample' or 'reference', got {kind!r}")
        self._target = kind

    def close(self) -> None:
        self._closed = True

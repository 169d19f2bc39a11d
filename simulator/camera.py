"""A simulated camera: renders the scene at the rig's current pose and returns a DNG.

>>> cam = SimulatedCamera(load_scene("scene.toml"), pose_provider=rig_poses)
>>> dng = cam.capture(exposure_time=0.01, iso=100, f_number=8.0, seed=7)
>>> dng, truth = cam.capture(0.01, 100, 8.0, seed=7, return_truth=True)
>>> ref = cam.capture(0.01, 100, 8.0, seed=8, target="reference")   # calibration shot
>>> spot = cam.capture(1e-5, 100, 8.0, seed=9, target="mirror")   # light's direction

``pose_provider()`` returns where the light and the camera are *now*, in the sample
frame: a :class:`gonio.rig.kinematics.RigPoses` (or a mapping with the same names:
``camera_position``, ``camera_rotation`` (camera-to-sample, OpenCV axes),
``light_position``, ``light_normal``).  The capture engineer wires it to the virtual
servos' read-back joint angles and ``Kinematics.poses``, so the image shows the pose the
rig actually reached.  Without a provider the scene's own poses are used.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from gonio.errors import CameraError, ConfigError
from gonio.simulator.dng import dng_bytes
from gonio.simulator.render import RenderResult, render
from gonio.simulator.scene import Scene, scene_with_rig_poses
from gonio.simulator.sensor import RawFrame, simulate_raw

__all__ = ["MIRROR_REFLECTANCE", "TARGETS", "SimulatedCamera"]

#: What can be put in the sample's place.
TARGETS = ("sample", "reference", "mirror")
#: Grey reflectance of the simulated first-surface mirror (aluminium: ~0.9 in the visible).
MIRROR_REFLECTANCE = 0.9
Target = Literal["sample", "reference", "mirror"]


class SimulatedCamera:
    """Render-and-expose camera backend.

    Parameters
    ----------
    scene
        The scene (sample, holder, lights, occluders, camera intrinsics and sensor).
    pose_provider
        Callable returning the current poses (see the module docstring), or None.
    reference_albedo
        Albedo of the Lambertian reference target rendered for ``target="reference"``.
    mirror_reflectance
        Reflectance of the flat mirror rendered for ``target="mirror"``
        (:meth:`gonio.simulator.scene.Scene.with_mirror_target`).
    """

    def __init__(
        self,
        scene: Scene,
        pose_provider: Callable[[], Any] | None = None,
        reference_albedo: float | tuple[float, float, float] = 0.99,
        mirror_reflectance: float = MIRROR_REFLECTANCE,
    ) -> None:
        self.scene = scene
        self.pose_provider = pose_provider
        self.reference_albedo = reference_albedo
        self.mirror_reflectance = mirror_reflectance
        self._brdf: Any = None
        self._cache: tuple[bytes, RenderResult] | None = None
        self.renders = 0

    @property
    def model(self) -> str:
        """Camera model name written into the DNG."""
        return self.scene.camera.sensor.model

    def current_scene(self, target: Target = "sample") -> Scene:
        """The scene at the current pose, with the sample, the reference target or the
        mirror in the sample's place."""
        if target not in TARGETS:
            raise CameraError(f"target must be one of {', '.join(TARGETS)}; got {target!r}")
        scene = self.scene
        if self.pose_provider is not None:
            scene = scene_with_rig_poses(scene, self.pose_provider())
        if target == "reference":
            scene = scene.with_reference_target(self.reference_albedo)
        elif target == "mirror":
            scene = scene.with_mirror_target(self.mirror_reflectance)
        return scene

    def render(self, target: Target = "sample") -> RenderResult:
        """Noise-free radiance and ground truth at the current pose (cached per pose)."""
        scene = self.current_scene(target)
        key = scene.model_dump_json().encode()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        brdf = None
        if target == "sample":
            if self._brdf is None:
                self._brdf = scene.build_brdf()
            brdf = self._brdf
        try:
            result = render(scene, brdf=brdf)
        except ConfigError as exc:
            raise CameraError(f"simulated camera cannot take this picture: {exc}") from exc
        self.renders += 1
        self._cache = (key, result)
        return result

    def capture_frame(
        self,
        exposure_time: float,
        iso: float,
        f_number: float,
        seed: int,
        target: Target = "sample",
    ) -> RawFrame:
        """The RAW frame (mosaic and metadata) of one exposure."""
        result = self.render(target)
        return simulate_raw(
            result.radiance,
            self.scene.camera,
            exposure_time=exposure_time,
            iso=iso,
            f_number=f_number,
            seed=np.random.default_rng(seed),
        )

    def capture(
        self,
        exposure_time: float,
        iso: float,
        f_number: float,
        seed: int,
        *,
        target: Target = "sample",
        return_truth: bool = False,
    ) -> bytes | tuple[bytes, RenderResult]:
        """Take one exposure and return it as DNG bytes.

        Parameters
        ----------
        exposure_time
            Seconds.
        iso
            ISO speed (sets the gain).
        f_number
            Aperture.
        seed
            Seed of the sensor noise: equal seeds (and poses) give equal bytes.
        target
            ``"sample"``, ``"reference"`` for a radiometric calibration shot of a
            Lambertian target of ``reference_albedo`` in the sample's place, or
            ``"mirror"`` for the light's image in a flat mirror there (rig calibration).
        return_truth
            Also return the :class:`RenderResult` (noise-free radiance, wi, wo, masks).

        Raises
        ------
        CameraError
            The camera does not see the sample at this pose, or bad settings.
        """
        from gonio.errors import ParameterError

        try:
            frame = self.capture_frame(exposure_time, iso, f_number, seed, target)
        except ParameterError as exc:
            raise CameraError(f"simulated camera: {exc}") from exc
        data = dng_bytes(frame)
        if return_truth:
            return data, self.render(target)
        return data

"""A simulated camera: renders the scene at the rig's current pose and returns a DNG.

>>> cam = SimulatedCamera(load_scene("scene.toml"), pose_provider=rig_poses)
>>> dng = cam.capture(exposure_time=0.01, iso=100, f_number=8.0, seed=7)
>>> dng, truth = cam.capture(0.01, 100, 8.0, seed=7, return_truth=True)
>>> ref = cam.capture(0.01, 100, 8.0, seed=8, target="reference")   # calibration shot
>>> spot = cam.capture(1e-5, 100, 8.0, seed=9, target="mirror")   # light's direction
>>> flat = cam.capture(0.01, 100, 8.0, seed=10, target="flat")     # a panel over the lens
>>> dark = cam.capture(0.01, 100, 8.0, seed=11, light_on=False)    # ambient light only

``pose_provider()`` returns where the light and the camera are *now*, in the sample
frame: a :class:`gonio.rig.kinematics.RigPoses` (or a mapping with the same names:
``camera_position``, ``camera_rotation`` (camera-to-sample, OpenCV axes),
``light_position``, ``light_normal``).  The capture engineer wires it to the virtual
servos' read-back joint angles and ``Kinematics.poses``, so the image shows the pose the
rig actually reached.  Without a provider the scene's own poses are used.

With an as-built ``world`` (:mod:`gonio.simulator.world_radiometry`) the camera sees its
radiometry: the light's emission profile and face gradient (written into the scene's
area lights), its output ``world.light_output(rig_time)`` at the shot's rig time, the
room's ambient light (light on or off) and the light's stray light (on), and the sensor's
fixed patterns (built once per frame size).  The noise-free direct and diffuse renders
of a pose are cached and scaled per shot, so a drifting light does not re-render.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from gonio.errors import CameraError, ConfigError
from gonio.simulator.dng import dng_bytes
from gonio.simulator.lights import nominal_irradiance
from gonio.simulator.render import RenderResult, albedo_table, render
from gonio.simulator.scene import PointLight, Scene, scene_with_rig_poses
from gonio.simulator.sensor import (
    _MIN_KERNEL_SITES,
    RawFrame,
    cfa_indices,
    cfa_radiance,
    default_flat_radiance,
    simulate_mosaic,
)
from gonio.simulator.sensor_defects import FixedPattern, fixed_pattern

__all__ = ["MIRROR_REFLECTANCE", "TARGETS", "SimulatedCamera", "with_light_emission"]

#: What can be put in the sample's place -- or, ``"flat"``, over the lens: a uniform
#: diffuse light panel (flat-field frames).
TARGETS = ("sample", "reference", "mirror", "flat")
#: Grey reflectance of the simulated first-surface mirror (aluminium: ~0.9 in the visible).
MIRROR_REFLECTANCE = 0.9
Target = Literal["sample", "reference", "mirror", "flat"]


def with_light_emission(scene: Scene, radiometry: Any) -> Scene:
    """``scene`` with its area lights' emission profile and face gradient as the world's
    radiometry says; the same object when the world's light is Lambertian and uniform
    (a scene's own profile is then kept)."""
    r = radiometry
    if r.light_profile_n == 0.0 and r.light_gradient == 0.0:
        return scene
    upd = {
        "profile_n": float(r.light_profile_n),
        "gradient": float(r.light_gradient),
        "gradient_angle_deg": float(r.light_gradient_angle_deg),
    }
    lights = [
        li if isinstance(li, PointLight) else li.model_copy(update=upd) for li in scene.lights
    ]
    return scene.model_copy(update={"lights": lights})


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
    world
        The as-built :class:`~gonio.simulator.world.World` whose radiometry the camera
        sees (None, or a world whose radiometry is off: none, frames as before).
    """

    def __init__(
        self,
        scene: Scene,
        pose_provider: Callable[[], Any] | None = None,
        reference_albedo: float | tuple[float, float, float] = 0.99,
        mirror_reflectance: float = MIRROR_REFLECTANCE,
        world: Any = None,
    ) -> None:
        self.radiometry = None
        self._pattern_seed = 0
        if world is not None and not world.radiometry.off:
            self.radiometry = world.radiometry
            self._pattern_seed = int(world.seed)
            scene = with_light_emission(scene, world.radiometry)
        self.scene = scene
        self.pose_provider = pose_provider
        self.reference_albedo = reference_albedo
        self.mirror_reflectance = mirror_reflectance
        self._brdf: Any = None
        self._cache: tuple[bytes, bool, bool, RenderResult, np.ndarray] | None = None
        self._albedo: dict[str, Any] = {}
        self._patterns: dict[tuple[int, int], FixedPattern | None] = {}
        self.renders = 0
        self._site_cache: dict[Any, Any] = {}
        self._site_index_cache: dict[Any, Any] = {}

    @property
    def model(self) -> str:
        """Camera model name written into the DNG."""
        return self.scene.camera.sensor.model

    def current_scene(self, target: Target = "sample") -> Scene:
        """The scene at the current pose, with the sample, the reference target or the
        mirror in the sample's place."""
        if target not in TARGETS:
            raise CameraError(f"target must be one of {', '.join(TARGETS)}; got {target!r}")
        if target == "flat":
            raise CameraError("the flat panel covers the lens: there is no scene to render")
        scene = self.scene
        if self.pose_provider is not None:
            scene = scene_with_rig_poses(scene, self.pose_provider())
        if target == "reference":
            scene = scene.with_reference_target(self.reference_albedo)
        elif target == "mirror":
            scene = scene.with_mirror_target(self.mirror_reflectance)
        return scene

    def render(
        self, target: Target = "sample", *, direct: bool = True, diffuse: bool = False
    ) -> RenderResult:
        """Noise-free radiance and ground truth at the current pose (cached per pose).

        ``direct``: integrate the lights (output factor 1); ``diffuse``: also the
        response to uniform diffuse light (:attr:`RenderResult.diffuse`)."""
        return self._render(target, direct, diffuse)[0]

    def _render(self, target: Target, direct: bool, diffuse: bool) -> tuple[RenderResult, Any]:
        scene = self.current_scene(target)
        key = scene.model_dump_json().encode()
        c = self._cache
        # a render with more in it serves a request for less (a dark frame after a lit one)
        if c is not None and c[0] == key and (c[1] or not direct) and (c[2] or not diffuse):
            return c[3], c[4]
        brdf = None
        if target == "sample":
            if self._brdf is None:
                self._brdf = scene.build_brdf()
            brdf = self._brdf
        albedo = None
        if diffuse and target != "mirror":
            if target not in self._albedo:
                self._albedo[target] = albedo_table(
                    brdf if brdf is not None else scene.build_brdf()
                )
            albedo = self._albedo[target]
        try:
            result = render(scene, brdf=brdf, direct=direct, diffuse=diffuse, sample_albedo=albedo)
        except ConfigError as exc:
            raise CameraError(f"simulated camera cannot take this picture: {exc}") from exc
        e0 = nominal_irradiance(scene) if diffuse else None
        self.renders += 1
        self._cache = (key, direct, diffuse, result, e0)
        return result, e0

    def flat_radiance(self) -> np.ndarray:
        """The flat panel's radiance (3,), W/(sr m^2): the world's ``flat_radiance`` or
        :func:`~gonio.simulator.sensor.default_flat_radiance`."""
        r = self.radiometry
        if r is not None and r.flat_radiance is not None:
            return np.asarray(r.flat_radiance, dtype=np.float64)
        return default_flat_radiance(self.scene.camera)

    def fixed_pattern(self) -> FixedPattern | None:
        """The sensor's PRNU, DSNU and hot-pixel maps at the camera's frame size (built
        once; None without them)."""
        if self.radiometry is None:
            return None
        w, h = self.scene.camera.resolution
        if (h, w) not in self._patterns:
            self._patterns[(h, w)] = fixed_pattern(self.radiometry, self._pattern_seed, (h, w))
        return self._patterns[(h, w)]

    def radiance(
        self, target: Target = "sample", *, rig_time: float = 0.0, light_on: bool = True
    ) -> np.ndarray:
        """The radiance (H, W, 3) the sensor sees in a shot, W/(sr m^2): the direct light
        times ``light_output(rig_time)`` (light on), plus ``albedo / pi`` times the diffuse
        irradiance ``E0 (ambient + stray * light_output)`` (stray: light on only); the
        flat panel's uniform radiance for ``target="flat"``."""
        w, h = self.scene.camera.resolution
        if target == "flat":
            return np.broadcast_to(self.flat_radiance(), (h, w, 3)).copy()
        r = self.radiometry
        if r is None:
            return self.render(target).radiance if light_on else np.zeros((h, w, 3))
        stray = r.stray_fraction if light_on else 0.0
        diffuse = r.ambient_fraction > 0.0 or stray > 0.0
        if not (light_on or diffuse):
            return np.zeros((h, w, 3))
        result, e0 = self._render(target, light_on, diffuse)
        out = np.zeros((h, w, 3))
        k = r.light_output(rig_time)
        if light_on:
            out = result.radiance * k if r.drifts else result.radiance.copy()
        if diffuse:
            out += result.diffuse * (e0 * (r.ambient_fraction + stray * k))
        return out

    def site_radiance(
        self, target: Target = "sample", *, rig_time: float = 0.0, light_on: bool = True
    ) -> np.ndarray:
        """:meth:`radiance` at the colour filters' sites (H, W), W/(sr m^2), clamped at 0
        (:func:`~gonio.simulator.sensor.cfa_radiance`): the same values, bit for bit,
        from the pose's cached render taken at the sites once, so a shot does the work
        of one channel."""
        cam = self.scene.camera
        w, h = cam.resolution
        r = self.radiometry
        if target == "flat":
            return cfa_radiance(np.broadcast_to(self.flat_radiance(), (h, w, 3)), cam)
        if r is None:
            if not light_on:
                return np.zeros((h, w))
            out = self._sites(self._render(target, True, False)[0], "radiance").copy()
        else:
            stray = r.stray_fraction if light_on else 0.0
            diffuse = r.ambient_fraction > 0.0 or stray > 0.0
            if not (light_on or diffuse):
                return np.zeros((h, w))
            result, e0 = self._render(target, light_on, diffuse)
            k = r.light_output(rig_time)
            if h * w >= _MIN_KERNEL_SITES and os.environ.get("GONIO_NUMBA") != "0":
                return self._shot_kernel(result, e0, k, light_on, diffuse, stray)
            idx = cfa_indices(cam.sensor.cfa_pattern, (h, w))
            out = np.zeros((h, w))
            if light_on:
                direct = self._sites(result, "radiance")
                out = direct * k[idx] if r.drifts else direct.copy()
            if diffuse:
                out += self._sites(result, "diffuse") * (e0 * (r.ambient_fraction + stray * k))[idx]
        # every path clamps as cfa_radiance does: a measured BRDF's interpolation, and so
        # a render, can dip below 0
        return np.nan_to_num(np.maximum(out, 0.0, out=out), copy=False)

    def _shot_kernel(
        self, result: RenderResult, e0: Any, k: np.ndarray, light_on: bool, diffuse: bool,
        stray: float,
    ) -> np.ndarray:  # fmt: skip
        """:meth:`site_radiance`'s per-shot arithmetic (the radiometry's branch) by the
        kernel :func:`~gonio.simulator.sensor_kernels.shot_sites`: the same bits."""
        from gonio.simulator.sensor_kernels import shot_sites

        r = self.radiometry
        h, w = result.radiance.shape[:2]
        none = np.zeros(0)
        direct = self._sites(result, "radiance").reshape(-1) if light_on else none
        # numpy's `direct.copy()` without drift is `direct * 1.0`: the same bits
        k_direct = np.asarray(k, dtype=np.float64) if r.drifts else np.ones(3)
        dif, k_diffuse = none, none
        if diffuse:
            dif = self._sites(result, "diffuse").reshape(-1)
            k_diffuse = np.asarray(e0 * (r.ambient_fraction + stray * k), dtype=np.float64)
        out = np.empty((h, w))
        shot_sites(direct, dif, self._site_index((h, w))[1], k_direct, k_diffuse,
                   out.reshape(-1))  # fmt: skip
        return out

    def _site_index(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(flat index of each site's channel in the (H W 3) image, channel index (H W,)),
        per CFA pattern and frame size (read-only)."""
        key = (self.scene.camera.sensor.cfa_pattern, shape)
        if key not in self._site_index_cache:
            idx = cfa_indices(key[0], shape).ravel()
            idx = np.ascontiguousarray(idx, dtype=np.intp)
            flat = np.arange(shape[0] * shape[1]) * 3 + idx
            flat.flags.writeable = False
            idx.flags.writeable = False
            self._site_index_cache[key] = (flat, idx)
        return self._site_index_cache[key]

    def _sites(self, result: RenderResult, name: str) -> np.ndarray:
        """``result.<name>`` at the colour filters' sites, cached with the render (not
        clamped: a sum is clamped, not its terms)."""
        if self._site_cache.get("result") is not result:
            self._site_cache = {"result": result}
        if name not in self._site_cache:
            img = getattr(result, name)
            flat = self._site_index(img.shape[:2])[0]
            self._site_cache[name] = np.take(img.reshape(-1), flat).reshape(img.shape[:2])
        return self._site_cache[name]

    def capture_frame(
        self,
        exposure_time: float,
        iso: float,
        f_number: float,
        seed: int,
        target: Target = "sample",
        *,
        rig_time: float = 0.0,
        light_on: bool = True,
    ) -> RawFrame:
        """The RAW frame (mosaic and metadata) of one exposure at rig time ``rig_time``
        (s) with the light on or off (see :meth:`radiance`)."""
        if target not in TARGETS:
            raise CameraError(f"target must be one of {', '.join(TARGETS)}; got {target!r}")
        return simulate_mosaic(
            self.site_radiance(target, rig_time=rig_time, light_on=light_on),
            self.scene.camera,
            exposure_time=exposure_time,
            iso=iso,
            f_number=f_number,
            seed=np.random.default_rng(seed),
            fixed_pattern=self.fixed_pattern(),
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
        rig_time: float = 0.0,
        light_on: bool = True,
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
            ``"mirror"`` for the light's image in a flat mirror there (rig calibration),
            or ``"flat"``: a uniform light panel over the lens (flat field).
        return_truth
            Also return the :class:`RenderResult` (noise-free radiance at output factor
            1, wi, wo, masks); not for ``"flat"``.
        rig_time
            Rig time of the shot, s (the light's drift).
        light_on
            The light is on (off: a dark frame, which still sees the room's light).

        Raises
        ------
        CameraError
            The camera does not see the sample at this pose, or bad settings.
        """
        from gonio.errors import ParameterError

        try:
            frame = self.capture_frame(
                exposure_time, iso, f_number, seed, target, rig_time=rig_time, light_on=light_on
            )
        except ParameterError as exc:
            raise CameraError(f"simulated camera: {exc}") from exc
        data = dng_bytes(frame)
        if return_truth:
            return data, self.render(target)
        return data

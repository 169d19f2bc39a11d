"""The as-built world: what the simulated rig and camera really are.

The controller and the reduction never read it; they learn it only through gonio's
calibrations, as a lab does.  A :class:`World` holds every error of the rig under the
canonical parameter names that ``gonio calibrate rig`` reports (DEVELOPING.md, "The
as-built world"), the camera's intrinsic errors, and the servos' landing error.  Its
physics is in :mod:`gonio.simulator.world_kinematics` (written independently of the
controller's :mod:`gonio.rig.asbuilt`; tests compare the two).

Presets
-------
``perfect``
    Every error zero, servos land exactly on their goal: today's behaviour bit for bit.
``realistic``
    Errors drawn (uniformly in the ranges below, from ``seed``) with the magnitudes of a
    DIY rig of ROBOTIS X-series servos and a 35 mm-class lens:

    ==========================  ==================  =============================================
    parameter                   range               source
    ==========================  ==================  =============================================
    ``<joint>.offset``          +-2 deg             horn and zero mounting of a DIY rig (a
                                                    degree or two; a typical tolerance, not a
                                                    manufacturer figure)
    ``<joint>.backlash``        0.15 .. 0.35 deg    ROBOTIS e-Manual: "Backlash 15 [arcmin]
                                                    (0.25 [deg])" on the X-series pages
                                                    (XH430-W350, XM540-W150/W270); the
                                                    XM430-W350 page itself could not be
                                                    retrieved here
    ``stage_tilt.compliance_*`` +-0.1 deg           gravity sag of a loaded tilt stage
    ``*_elevation``             nominal +-0.5 deg   arm elevation incl. sag (DIY tolerance)
    ``*_radius``                nominal +-2 mm      arm length (DIY tolerance)
    ``camera_mount_*``          +-1 deg             camera on its arm (DIY tolerance)
    ``tilt_axis_pitch``         +-0.3 deg           stage tilt axis off horizontal
    ``spin_axis_yaw``           +-0.5 deg           spin axis off the drawing
    ``holder_tilt_*``           +-0.3 deg           holder plate on the spin plate
    ``holder_offset_x/_y``      +-1 mm              sample off the spin axis
    ``holder_offset_z``         1 .. 5 mm           holder and sample thickness
    ``stage_offset_x/_y``       +-1 mm              stage centre off the arms' axis
    ``fx_scale``                +-1.5 %             ISO 517 allows +-5 % on the focal length
    ``fy_scale``                = fx_scale          square pixels (the renderer's model)
    ``principal_offset``        +-1 % of the frame  lens and sensor centring
    ``dist`` k1, k2, p1, p2, k3 +-0.1, +-0.05,      a typical 35 mm lens (Brown-Conrady);
                                +-1e-3, +-1e-3, 0   k3 = 0 because ``gonio calibrate
                                                    camera`` holds it at 0 (the rig's
                                                    board views cannot separate it from
                                                    k1, k2: ``cv2.CALIB_FIX_K3``)
    ``landing_pulses``          1                   servos stop within +-1 pulse of the goal
    ==========================  ==================  =============================================

The light, the room and the sensor's fixed patterns (``[world.radiometry]``) are drawn
from a stream of their own: see :mod:`gonio.simulator.world_radiometry`.

Values given explicitly in a ``[world]`` table override the drawn ones.  ``[world.rig]``
values are ERRORS from the nominal rig (for the elevations and radii: deg / m added to the
nominal value; the other parameters have nominal value 0); :meth:`World.truth_parameters`
gives the absolute values a perfect calibration would report.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import tomli_w
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from gonio.errors import ConfigError
from gonio.simulator.world_radiometry import Radiometry, draw_radiometry

__all__ = [
    "JOINTS",
    "PARAMETER_UNITS",
    "RIG_PARAMETERS",
    "CameraErrors",
    "Radiometry",
    "ServoErrors",
    "World",
    "draw_world",
    "load_world",
    "world_document",
]

#: The joints of an ``arms_tilt_spin`` rig (the simulator's own copy of the names).
JOINTS: tuple[str, ...] = ("light_azimuth", "camera_azimuth", "stage_tilt", "stage_spin")

#: Canonical rig parameter -> unit (docs/i15 table; ``gonio calibrate rig`` uses the same).
PARAMETER_UNITS: dict[str, str] = {
    **{f"{j}.offset": "deg" for j in JOINTS},
    **{f"{j}.backlash": "deg" for j in JOINTS},
    "stage_tilt.compliance_a": "deg",
    "stage_tilt.compliance_b": "deg",
    "light_elevation": "deg",
    "camera_elevation": "deg",
    "camera_radius": "m",
    "light_radius": "m",
    "camera_mount_x": "deg",
    "camera_mount_y": "deg",
    "camera_mount_z": "deg",
    "tilt_axis_pitch": "deg",
    "spin_axis_yaw": "deg",
    "holder_tilt_x": "deg",
    "holder_tilt_y": "deg",
    "holder_offset_x": "m",
    "holder_offset_y": "m",
    "holder_offset_z": "m",
    "stage_offset_x": "m",
    "stage_offset_y": "m",
}
RIG_PARAMETERS: tuple[str, ...] = tuple(PARAMETER_UNITS)

#: Parameters whose world value is an error ADDED to a nominal rig value (the others'
#: nominal value is 0, so error and truth are the same number).
_RELATIVE = {
    "light_elevation": "light_elevation_deg",
    "camera_elevation": "camera_elevation_deg",
    "light_radius": "light_radius_m",
    "camera_radius": "camera_radius_m",
}

#: Nominal geometry values of the default rig (gonio/rig/default_rig.toml leaves them
#: at the GeometryConfig defaults).
_NOMINAL_GEOMETRY = {
    "light_elevation_deg": 0.0,
    "camera_elevation_deg": 0.0,
    "light_radius_m": 0.50,
    "camera_radius_m": 0.40,
}

# Realistic ranges: (low, high) of a uniform draw, in the parameter's unit.
_MM = 1e-3
_REALISTIC_RIG: dict[str, tuple[float, float]] = {
    **{f"{j}.offset": (-2.0, 2.0) for j in JOINTS},
    **{f"{j}.backlash": (0.15, 0.35) for j in JOINTS},
    "stage_tilt.compliance_a": (-0.1, 0.1),
    "stage_tilt.compliance_b": (-0.1, 0.1),
    "light_elevation": (-0.5, 0.5),
    "camera_elevation": (-0.5, 0.5),
    "camera_radius": (-2 * _MM, 2 * _MM),
    "light_radius": (-2 * _MM, 2 * _MM),
    "camera_mount_x": (-1.0, 1.0),
    "camera_mount_y": (-1.0, 1.0),
    "camera_mount_z": (-1.0, 1.0),
    "tilt_axis_pitch": (-0.3, 0.3),
    "spin_axis_yaw": (-0.5, 0.5),
    "holder_tilt_x": (-0.3, 0.3),
    "holder_tilt_y": (-0.3, 0.3),
    "holder_offset_x": (-1 * _MM, 1 * _MM),
    "holder_offset_y": (-1 * _MM, 1 * _MM),
    "holder_offset_z": (1 * _MM, 5 * _MM),
    "stage_offset_x": (-1 * _MM, 1 * _MM),
    "stage_offset_y": (-1 * _MM, 1 * _MM),
}
_REALISTIC_DIST = ((-0.1, 0.1), (-0.05, 0.05), (-1e-3, 1e-3), (-1e-3, 1e-3), (0.0, 0.0))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class CameraErrors(_Strict):
    """The camera's intrinsics as built, relative to the scene's nominal camera.

    ``fx = fx_nominal * (1 + fx_scale)`` (likewise y); the principal point moves by
    ``principal_offset * (width, height)`` px; ``dist`` = OpenCV ``(k1, k2, p1, p2, k3)``.
    """

    fx_scale: float = Field(default=0.0, gt=-0.5, lt=0.5)
    fy_scale: float = Field(default=0.0, gt=-0.5, lt=0.5)
    principal_offset: tuple[float, float] = (0.0, 0.0)
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def perfect(self) -> bool:
        """No error at all (the nominal pinhole)."""
        return self == CameraErrors()


class ServoErrors(_Strict):
    """The servos as built.

    ``landing_pulses``: a move ends within +-N pulses of its goal (the encoder reports
    where it ended).  ``initial_approach``: joint -> +1 / -1, the side of its backlash
    each joint starts on (the sign of the joint's last move before the session).
    """

    landing_pulses: int = Field(default=0, ge=0, le=20)
    initial_approach: dict[str, Literal[-1, 0, 1]] = {}

    @field_validator("initial_approach")
    @classmethod
    def _joints(cls, v: dict[str, int]) -> dict[str, int]:
        bad = sorted(set(v) - set(JOINTS))
        if bad:
            raise ValueError(f"unknown joint(s) {bad}; expected names from {JOINTS}")
        return v


class World(_Strict):
    """The as-built rig and camera (see the module docstring).

    Attributes
    ----------
    preset, seed
        Where the errors come from.
    rig
        Canonical parameter name -> error (deg or m, :data:`PARAMETER_UNITS`); every
        name of :data:`RIG_PARAMETERS` is present.
    camera, servos
        Camera and servo errors.
    radiometry
        The light's emission and drift, ambient and stray light, the sensor's fixed
        patterns (:class:`~gonio.simulator.world_radiometry.Radiometry`).
    """

    preset: Literal["perfect", "realistic"] = "perfect"
    seed: int = Field(default=0, ge=0)
    rig: dict[str, float] = Field(default_factory=lambda: dict.fromkeys(RIG_PARAMETERS, 0.0))
    camera: CameraErrors = CameraErrors()
    servos: ServoErrors = ServoErrors()
    radiometry: Radiometry = Radiometry()

    @field_validator("rig")
    @classmethod
    def _complete(cls, v: dict[str, float]) -> dict[str, float]:
        bad = sorted(set(v) - set(RIG_PARAMETERS))
        if bad:
            raise ValueError(f"unknown rig parameter(s) {bad}; expected names from the table")
        for k in ("backlash",):
            neg = [n for n in v if n.endswith(k) and v[n] < 0]
            if neg:
                raise ValueError(f"{neg} must be >= 0 (deg)")
        for n, x in v.items():
            if not math.isfinite(x):
                raise ValueError(f"{n} = {x} is not a finite number")
        return {**dict.fromkeys(RIG_PARAMETERS, 0.0), **v}

    @property
    def perfect(self) -> bool:
        """As built = nominal: no rig, camera, landing or radiometric error (today's
        behaviour)."""
        return (
            all(x == 0.0 for x in self.rig.values())
            and self.camera.perfect
            and self.servos.landing_pulses == 0
            and self.radiometry.off
        )

    def light_output(self, t: float) -> np.ndarray:
        """The light's output factor (3,) (R, G, B) at rig time ``t`` (s): ``1 + A_c
        exp(-t / tau) + r t / 3600`` (the truth the reduction's drift tracking meets)."""
        return self.radiometry.light_output(t)

    def approach0(self, joint: str) -> int:
        """Sign of ``joint``'s last move before the session (0: unknown)."""
        return int(self.servos.initial_approach.get(joint, 0))

    def truth_parameters(self, rig_doc: Mapping[str, Any] | None = None) -> dict[str, float]:
        """The canonical parameters' absolute values (what a perfect calibration reports).

        Parameters
        ----------
        rig_doc
            The nominal rig as a TOML dict (its ``geometry`` gives the nominal elevations
            and radii); None: the default rig's.

        Returns
        -------
        dict
            Name -> value in :data:`PARAMETER_UNITS`.
        """
        geometry = dict(_NOMINAL_GEOMETRY)
        geometry.update((rig_doc or {}).get("geometry", {}))
        out = dict(self.rig)
        for name, field in _RELATIVE.items():
            out[name] = float(geometry[field]) + self.rig[name]
        return out

    def intrinsics(self, scene_camera: Any) -> tuple[np.ndarray, np.ndarray]:
        """The camera's true intrinsics in OpenCV form.

        Parameters
        ----------
        scene_camera
            The scene's nominal :class:`gonio.simulator.scene.Camera`.

        Returns
        -------
        K : ndarray (3, 3)
            Camera matrix, px, OpenCV convention (pixel centres at integer coordinates:
            the scene's ``cx - 0.5``).
        dist : ndarray (5,)
            ``(k1, k2, p1, p2, k3)``.
        """
        K = self.scene_intrinsics(scene_camera)
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K, np.array(self.camera.dist, dtype=np.float64)

    def scene_intrinsics(self, scene_camera: Any) -> np.ndarray:
        """The true camera matrix in the scene's convention (pixel centres at +0.5), px."""
        K = np.array(scene_camera.intrinsics(), dtype=np.float64)
        w, h = scene_camera.resolution
        c = self.camera
        K[0, 0] *= 1.0 + c.fx_scale
        K[1, 1] *= 1.0 + c.fy_scale
        K[0, 2] += c.principal_offset[0] * w
        K[1, 2] += c.principal_offset[1] * h
        return K

    def as_built_camera(self, scene_camera: Any) -> Any:
        """The scene camera as built: focal scale, principal point and distortion.

        A perfect camera is returned unchanged (the same object).  The renderer's
        ``distortion`` field is set when the scene model has it.
        """
        if self.camera.perfect:
            return scene_camera
        if self.camera.fx_scale != self.camera.fy_scale:
            # The scene camera has one focal length (square pixels).
            raise ConfigError(
                f"[world.camera]: fx_scale = {self.camera.fx_scale} and fy_scale = "
                f"{self.camera.fy_scale} differ, but the renderer models square pixels; "
                "give them equal (the corner-level views accept them different)"
            )
        K = self.scene_intrinsics(scene_camera)
        pitch = scene_camera.pitch
        f_px = K[0, 0]
        update: dict[str, Any] = {
            "focal_length": f_px * pitch,
            "pixel_pitch": pitch,
            "fov_deg": None,
            "principal_point": (float(K[0, 2]), float(K[1, 2])),
        }
        if "distortion" in type(scene_camera).model_fields:
            update["distortion"] = tuple(float(x) for x in self.camera.dist)
        return scene_camera.model_copy(update=update)

    def camera_serial(self) -> str | None:
        """The simulated camera's serial number: None for a perfect camera (today's
        identity), else derived from the camera's errors (another lens, another
        serial)."""
        if self.camera.perfect:
            return None
        text = json.dumps(self.camera.model_dump(mode="json"), sort_keys=True)
        return "SIM" + hashlib.sha256(text.encode()).hexdigest()[:10].upper()


def draw_world(
    preset: str = "perfect", seed: int = 0, overrides: Mapping[str, Any] | None = None
) -> World:
    """A world of ``preset`` with the errors drawn from ``seed``.

    Parameters
    ----------
    preset
        ``"perfect"`` (all zero) or ``"realistic"`` (module docstring's ranges).
    seed
        Seed of the draw (>= 0).
    overrides
        A ``[world]`` table's explicit values (``rig``, ``camera``, ``servos`` tables):
        they replace the drawn ones.

    Raises
    ------
    ConfigError
        Unknown preset or an invalid override (the field is named).
    """
    if preset not in ("perfect", "realistic"):
        raise ConfigError(f"world preset {preset!r} is unknown; expected 'perfect' or 'realistic'")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"world seed {seed!r}: expected an integer >= 0")
    rig = dict.fromkeys(RIG_PARAMETERS, 0.0)
    camera: dict[str, Any] = {}
    servos: dict[str, Any] = {}
    radiometry: dict[str, Any] = {}
    if preset == "realistic":
        rng = np.random.default_rng([int(seed), 0x57071D])
        for name in RIG_PARAMETERS:
            lo, hi = _REALISTIC_RIG[name]
            rig[name] = float(rng.uniform(lo, hi))
        fx = float(rng.uniform(-0.015, 0.015))
        camera = {
            "fx_scale": fx,
            "fy_scale": fx,
            "principal_offset": tuple(float(x) for x in rng.uniform(-0.01, 0.01, 2)),
            "dist": tuple(
                float(rng.uniform(lo, hi)) if hi > lo else 0.0 for lo, hi in _REALISTIC_DIST
            ),
        }
        servos = {
            "landing_pulses": 1,
            "initial_approach": {j: int(rng.choice([-1, 1])) for j in JOINTS},
        }
        # its own stream: the draws above are those of a world without radiometry
        radiometry = draw_radiometry(seed)
    over = dict(overrides or {})
    unknown = sorted(set(over) - {"rig", "camera", "servos", "radiometry", "preset", "seed"})
    if unknown:
        raise ConfigError(
            f"[world]: unknown key(s) {unknown}; expected preset, seed, rig, camera, servos, "
            "radiometry"
        )
    try:
        rig.update({k: _number(f"rig.{k}", v) for k, v in dict(over.get("rig", {})).items()})
        cam_over = dict(over.get("camera", {}))
        if "fx_scale" in cam_over and "fy_scale" not in cam_over:
            cam_over["fy_scale"] = cam_over["fx_scale"]  # square pixels unless told
        camera.update(cam_over)
        servos.update(over.get("servos", {}))
        radiometry.update(over.get("radiometry", {}))
        return World.model_validate(
            {
                "preset": preset,
                "seed": seed,
                "rig": rig,
                "camera": camera,
                "servos": servos,
                "radiometry": radiometry,
            },
            strict=False,
        )
    except ValidationError as exc:
        raise ConfigError(f"[world]: {_messages(exc)}") from None
    except (TypeError, ValueError) as exc:  # e.g. rig = "x": not a table
        raise ConfigError(
            f"[world]: {exc} (rig, camera, servos and radiometry are tables)"
        ) from None


def _number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(f"[world.{name}] = {v!r}: expected a number")
    return float(v)


def _messages(exc: ValidationError) -> str:
    return "; ".join(
        f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']} (got {e.get('input')!r})"
        for e in exc.errors()
    )


def load_world(source: str | Path | Mapping[str, Any] | None, seed: int | None = None) -> World:
    """The world of a preset name, a TOML file or a ``[world]`` table.

    Parameters
    ----------
    source
        ``"perfect"`` / ``"realistic"``; a path to a world TOML (a ``[world]`` table, or
        the world's keys at top level; a scene TOML with a ``[world]`` table works too);
        a mapping (the table itself); None: perfect.
    seed
        Overrides the table's ``seed`` (``--world-seed``).

    Raises
    ------
    ConfigError
        Unreadable file, not TOML, unknown preset, or an invalid field (file and field
        named).
    """
    if source is None:
        return draw_world("perfect", seed or 0)
    if isinstance(source, Mapping):
        table, where = dict(source), "[world]"
    elif str(source) in ("perfect", "realistic"):
        return draw_world(str(source), 0 if seed is None else seed)
    else:
        p = Path(source)
        where = str(p)
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except OSError as exc:
            raise ConfigError(
                f"{p}: cannot read the world (expected 'perfect', 'realistic' or a TOML "
                f"file): {exc.strerror}"
            ) from None
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{p}: world is not valid TOML: {exc}") from None
        table = doc.get("world", doc)
        if not isinstance(table, dict):
            raise ConfigError(f"{p}: [world] must be a table")
    preset = table.pop("preset", "perfect")
    s = table.pop("seed", 0) if seed is None else (table.pop("seed", None), seed)[1]
    try:
        return draw_world(preset, s, table)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def world_document(world: World) -> dict[str, Any]:
    """The world as a TOML-ready table holding every value (not just the preset), so a
    session's manifest records the exact world and resume rebuilds it with
    :func:`load_world`.  ``tomli_w.dumps({"world": world_document(w)})`` writes it."""
    doc = world.model_dump(mode="json")
    doc["camera"]["principal_offset"] = list(doc["camera"]["principal_offset"])
    doc["camera"]["dist"] = list(doc["camera"]["dist"])
    rad = doc["radiometry"]
    rad["drift_amplitude"] = list(rad["drift_amplitude"])
    if rad["flat_radiance"] is None:  # TOML has no null: absent = the sensor's default
        del rad["flat_radiance"]
    else:
        rad["flat_radiance"] = list(rad["flat_radiance"])
    tomli_w.dumps(doc)  # fails here, not in a manifest writer, if a value is not TOML
    return doc

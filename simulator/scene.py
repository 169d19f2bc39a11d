"""The simulated scene: sample, holder with ChArUco board, lights, occluders, camera.

A scene is a pydantic model, usually read from TOML with :func:`load_scene`.  All
positions are in the *sample frame* (metres): the sample and its holder lie in the plane
z = 0 with +z their normal, +x the sample's reference direction.

TOML schema (every length in metres, angles in degrees where the name says ``_deg``)::

    schema_version = 2           # optional (the current one); 1: print edges by sub-rays

    [sample]
    width = 0.05                 # extent along x
    height = 0.05                # extent along y
    albedo_map = "albedo.npy"    # optional: (H, W) or (H, W, 3) array or 8/16-bit image,
                                 # multiplies f_r; row 0 at +y, column 0 at -x
    [sample.brdf]                # either an analytic model ...
    model = "lambert+ggx"        # any gonio.brdf model name
    params = { albedo = [0.5, 0.4, 0.3], ks = 0.04, alpha = 0.2 }
    options = { fresnel = "schlick" }   # keyword options of get_model
    # file = "paper_white_rgb.bsdf"     # ... or a measured file (gonio.brdf.load)

    [sample.maps]                # optional: parameters of the analytic sample.brdf.model
                                 # per texel (gonio.simulator.svbrdf; piecewise constant,
                                 # row 0 at +y, column 0 at -x; maps may differ in size)
    alpha = [[0.1, 0.2], [0.3, 0.4]]     # inline rows (of numbers or of [r, g, b])
    ks = "ks.npy"                        # (ny, nx) or (ny, nx, 3) .npy, natural units
    albedo = { file = "albedo.png", range = [0.0, 0.8] }   # 8/16-bit image [0,1] -> range
    # [sample.mix]               # ... or materials by an integer mask (not both; neither
    # mask = [[0, 1], [1, 0]]    # combines with albedo_map; sample.brdf is then not needed)
    # [[sample.mix.materials]]   # label k -> materials[k]: a BRDFSpec (model + params,
    # file = "paper_white_rgb.bsdf"      # or a measured file)

    [holder]                     # optional: a Lambertian plate around the sample
    width = 0.15
    height = 0.15
    albedo_black = 0.04          # printed black (per channel or scalar)
    albedo_white = 0.85          # printed white / bare plate
    [holder.board]               # ChArUco board printed on it, centred on the origin
    squares_x = 7
    squares_y = 7
    square_length = 0.02
    marker_length = 0.015
    dictionary = "DICT_4X4_50"   # any cv2.aruco predefined dictionary
    [holder.reference_patch]     # optional Lambertian patch of known albedo
    center = [0.055, -0.055]
    size = [0.015, 0.015]
    albedo = 0.99

    [[lights]]                   # one or more
    type = "disk"                # "point" | "disk" | "rectangle"
    position = [0.0, 0.25, 0.433]
    look_at = [0.0, 0.0, 0.0]    # or normal = [...], the emitting direction
    radius = 0.01                # disk
    # width, height, up: rectangle; intensity (W/sr) for point lights
    radiance = [1.0e4, 1.0e4, 1.0e4]        # camera-space RGB, W/(sr m^2)
    # profile_n = 0.0            # emission cos^n off the normal (0: Lambertian)
    # gradient = 0.0             # face non-uniformity, relative, at the rim
    # gradient_angle_deg = 0.0   # its direction in the light's (e1, e2) frame
    # radiance = { illuminant = "D65", scale = 100.0 }   # or a spectrum (see Spectrum)

    [[occluders]]
    type = "box"                 # center, size, rotation_deg (xyz Euler, degrees)
    center = [0.0, 0.1, 0.2]
    size = [0.02, 0.02, 0.1]
    [[occluders]]
    type = "cylinder"            # start, end, radius
    start = [0.1, 0.0, 0.0]
    end = [0.1, 0.0, 0.3]
    radius = 0.01

    [camera]
    resolution = [640, 480]      # width, height in pixels
    focal_length = 0.035
    pixel_pitch = 5.0e-6         # or fov_deg (horizontal), giving the pitch
    principal_point = [320.0, 240.0]   # optional (cx, cy), px, pixel centres at +0.5
    distortion = [-0.15, 0.02, 0.0, 0.0, 0.0]   # optional OpenCV Brown-Conrady
                                 # (k1, k2, p1, p2, k3) on normalised coordinates
    position = [0.0, -0.25, 0.433]
    look_at = [0.0, 0.0, 0.0]    # or rotation (3x3 world->camera, OpenCV axes)
    up = [0.0, 0.0, 1.0]
    f_number = 8.0
    exposure_time = 0.01
    iso = 100
    [camera.sensor]              # see Sensor for the fields and their defaults

    [render]
    tolerance = 1e-4             # relative per-pixel error target of the light integral
    strategy = "auto"            # "auto" | "point" | "quadrature" | "mc"
    antialias = 4                # sub-samples per axis on edge pixels (1: off)
    spot_antialias = 16          # the same on the rim of a light's image in the mirror
    print_antialias = "exact"    # edges of the board print alone: "exact" area coverage
                                 # (gonio.simulator.print_coverage) or "rays" (the
                                 # antialias^2 sub-rays; the RAW bytes before schema 2)

    [rig]                        # optional: light and camera poses from joint angles
    joints_deg = { light_azimuth = 0.0, camera_azimuth = 180.0, stage_tilt = 30.0,
                   stage_spin = 0.0 }    # (one line in TOML)
    config = "rig.toml"          # optional; the default rig preset otherwise

The camera follows OpenCV's convention: camera x right, y down, z forward; ``rotation``
maps sample-frame vectors to camera-frame vectors.  The scene's K puts pixel centres at
integer + 0.5 (pixel (0, 0) spans [0, 1) x [0, 1)); OpenCV puts them at integers, so the
OpenCV matrix of the same camera has ``cx - 0.5, cy - 0.5``.  ``distortion`` is the same
in both conventions: a normalised point (x, y) = (X/Z, Y/Z) is imaged at
``K @ (x_d, y_d, 1)`` with OpenCV's ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) +
2 p1 x y + p2 (r^2 + 2 x^2)`` (and y likewise).

``[sample] mirror_reflectance = 0.9`` (set by :meth:`Scene.with_mirror_target`, not
usually written) puts a flat first-surface mirror of that grey reflectance in the
sample's rectangle in place of the sample (the rig calibration's light-direction target).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from gonio.config import read_toml, validate
from gonio.errors import ConfigError
from gonio.radiometry import frames

__all__ = [
    "SCENE_SCHEMA_VERSION",
    "BRDFSpec",
    "Board",
    "BoxOccluder",
    "Camera",
    "MapFile",
    "Mix",
    "CylinderOccluder",
    "DiskLight",
    "Holder",
    "PointLight",
    "RectangleLight",
    "ReferencePatch",
    "RenderSettings",
    "RigPoseSpec",
    "Sample",
    "Scene",
    "Sensor",
    "Spectrum",
    "MAX_EXPOSURE_S",
    "load_scene",
    "look_at_rotation",
    "parse_scene",
]

Vec3 = tuple[float, float, float]
Vec2 = tuple[float, float]
Positive = Annotated[float, Field(gt=0)]

#: Longest exposure a scene (or the sensor model) accepts, s.  Cameras time at most 30 s
#: (longer in bulb mode only); in an hour the dark current alone fills a pixel's well,
#: and the bound keeps the sensor's Poisson mean far inside numpy's range.  The same
#: bound as a plan's (``gonio.capture.plan.MAX_EXPOSURE_S``).
MAX_EXPOSURE_S = 3600.0
ExposureTime = Annotated[float, Field(gt=0, le=MAX_EXPOSURE_S, allow_inf_nan=False)]
#: A reflectance or efficiency, per channel or one for all: a fraction of the light.
Fraction = Annotated[float, Field(ge=0, le=1)]
RGBOrScalar = Fraction | tuple[Fraction, Fraction, Fraction]
#: An emitted radiance or intensity, per channel or one for all: no light emits less
#: than nothing.
NonNegative = Annotated[float, Field(ge=0)]


class _Model(BaseModel):
    # No inf/nan anywhere in a scene: a NaN radiance or albedo passed every bound (all
    # comparisons with NaN are false) and rendered a DNG of NaN-derived pixels, exit 0.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _rgb(value: RGBOrScalar) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()


def _unit(v: Any, what: str) -> np.ndarray:
    u = frames.normalize(v)
    if not np.all(np.isfinite(u)):
        raise ValueError(f"{what} must be a non-zero finite vector, got {v}")
    return u


def look_at_rotation(position: Any, target: Any, up: Any = (0.0, 0.0, 1.0)) -> np.ndarray:
    """:func:`gonio.radiometry.frames.look_at_rotation` for one camera, validated.

    Raises
    ------
    ValueError
        When ``target == position`` or ``up`` is zero (the scene names the field).
    """
    _unit(np.asarray(target, float) - np.asarray(position, float), "look direction")
    _unit(up, "up")
    return frames.look_at_rotation(position, target, up)


class Spectrum(_Model):
    """A light's spectral radiance, converted to camera RGB with the camera's sensitivities.

    Exactly one of ``illuminant`` (a name in ``colour.SDS_ILLUMINANTS``), ``blackbody``
    (temperature, K) or ``csv`` (two columns: wavelength nm, value) is given.  The
    spectrum is normalised to 1 at 560 nm and multiplied by ``scale`` (W/(sr m^2 nm), or
    W/(sr nm) for point lights).  Channel c is ``sum S(l) s_c(l) dl`` over the camera
    sensitivities ``s_c`` (peak 1), so a flat spectrum of 1 gives each channel the
    equivalent width of its sensitivity in nm.
    """

    illuminant: str | None = None
    blackbody: Positive | None = None
    csv: Path | None = None
    scale: Positive = 1.0

    @model_validator(mode="after")
    def _one_source(self) -> Spectrum:
        given = [x is not None for x in (self.illuminant, self.blackbody, self.csv)]
        if sum(given) != 1:
            raise ValueError("give exactly one of 'illuminant', 'blackbody' or 'csv'")
        return self

    def to_camera_rgb(self, sensitivities: str, base: Path | None = None) -> np.ndarray:
        """Integrate against the named ``colour.MSDS_CAMERA_SENSITIVITIES`` entry."""
        import colour

        if sensitivities not in colour.MSDS_CAMERA_SENSITIVITIES:
            raise ConfigError(
                f"camera.sensor.spectral_sensitivities: unknown camera {sensitivities!r}; "
                f"known: {sorted(colour.MSDS_CAMERA_SENSITIVITIES)}"
            )
        cam = colour.MSDS_CAMERA_SENSITIVITIES[sensitivities]
        wl = cam.wavelengths
        if self.illuminant is not None:
            if self.illuminant not in colour.SDS_ILLUMINANTS:
                raise ConfigError(f"unknown illuminant {self.illuminant!r}")
            sd = colour.SDS_ILLUMINANTS[self.illuminant]
            values = np.interp(wl, sd.wavelengths, sd.values)
            ref = np.interp(560.0, sd.wavelengths, sd.values)
        elif self.blackbody is not None:
            values = colour.colorimetry.planck_law(wl * 1e-9, self.blackbody)
            ref = colour.colorimetry.planck_law(560e-9, self.blackbody)
        else:
            path = self.csv if base is None or self.csv.is_absolute() else base / self.csv
            try:
                data = np.loadtxt(path, delimiter=",", ndmin=2)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"spectrum csv {path}: {exc}") from exc
            values = np.interp(wl, data[:, 0], data[:, 1], left=0.0, right=0.0)
            ref = np.interp(560.0, data[:, 0], data[:, 1])
        s = np.asarray(values, float) / float(ref) * self.scale
        dl = np.gradient(wl)
        return np.einsum("l,lc,l->c", s, np.asarray(cam.values, float), dl)


Colour = NonNegative | tuple[NonNegative, NonNegative, NonNegative] | Spectrum


class BRDFSpec(_Model):
    """The sample's BRDF: a ``gonio.brdf`` model with parameters, or a measured file."""

    model: str | None = None
    params: dict[str, float | list[float]] = Field(default_factory=dict)
    options: dict[str, Any] = Field(default_factory=dict)
    file: Path | None = None

    @model_validator(mode="after")
    def _model_or_file(self) -> BRDFSpec:
        if (self.model is None) == (self.file is None):
            raise ValueError("give exactly one of 'model' (with 'params') or 'file'")
        return self


class MapFile(_Model):
    """A parameter map in a file: ``.npy`` (natural units) or an 8/16-bit image whose
    [0, 1] values are taken to ``range`` (default [0, 1])."""

    file: Path
    range: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _finite_range(self) -> MapFile:
        if self.range is not None and not all(np.isfinite(self.range)):
            raise ValueError(f"range must be two finite numbers, got {list(self.range)}")
        return self


#: A map's value in ``[sample.maps]``: a path, a file with a value range, or an inline
#: nested list (rows of numbers or of [r, g, b]); loaded by
#: :func:`gonio.simulator.svbrdf.load_maps`, which checks shape, NaN and bounds.
MapValue = MapFile | Path | list[Any]


class Mix(_Model):
    """A sample made of measured or analytic materials laid out by an integer mask:
    texel label k has ``materials[k]``."""

    mask: Path | list[Any]
    materials: list[BRDFSpec] = Field(min_length=1)


class Sample(_Model):
    """The measured sample: a rectangle centred on the origin in the plane z = 0.

    Spatially varying samples (``maps`` or ``mix``, not both, and neither with
    ``albedo_map``): see :mod:`gonio.simulator.svbrdf`.
    """

    width: Positive
    height: Positive
    brdf: BRDFSpec | None = None
    albedo_map: Path | None = None
    maps: dict[str, MapValue] | None = None
    mix: Mix | None = None
    mirror_reflectance: Annotated[float, Field(gt=0, le=1)] | None = None

    @model_validator(mode="after")
    def _one_layout(self) -> Sample:
        if self.maps is not None and self.mix is not None:
            raise ValueError(
                "give 'maps' (parameter maps of sample.brdf) or 'mix' (materials by a "
                "mask), not both"
            )
        if self.albedo_map is not None and (self.maps is not None or self.mix is not None):
            which = "maps" if self.maps is not None else "mix"
            raise ValueError(
                f"'albedo_map' does not combine with '{which}' (give the albedo as "
                "sample.maps.albedo instead)"
            )
        if self.brdf is None and self.mix is None:
            raise ValueError("give 'brdf' (or 'mix' with its materials)")
        if self.maps is not None:
            if self.brdf is None or self.brdf.model is None:
                raise ValueError(
                    "'maps' replace parameters of an analytic sample.brdf.model; a "
                    "measured file has none (use 'mix' for measured materials)"
                )
            if not self.maps:
                raise ValueError("'maps' is empty: give at least one parameter map")
        return self

    @property
    def spatially_varying(self) -> bool:
        """Whether the sample has parameter maps or a material mix."""
        return self.maps is not None or self.mix is not None


class Board(_Model):
    """A ChArUco board (OpenCV ``cv2.aruco.CharucoBoard``) printed on the holder."""

    squares_x: Annotated[int, Field(ge=2)] = 7
    squares_y: Annotated[int, Field(ge=2)] = 7
    square_length: Positive = 0.02
    marker_length: Positive = 0.015
    dictionary: str = "DICT_4X4_50"
    pixels_per_square: Annotated[int, Field(ge=8)] = 64

    @model_validator(mode="after")
    def _marker_fits(self) -> Board:
        if self.marker_length >= self.square_length:
            raise ValueError("marker_length must be smaller than square_length")
        return self

    @model_validator(mode="after")
    def _dictionary_has_the_markers(self) -> Board:
        from gonio.charuco import board_markers_problem

        problem = board_markers_problem(self.squares_x, self.squares_y, self.dictionary)
        if problem:
            raise ValueError(problem)
        return self

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, v: str) -> str:
        import cv2

        if not v.startswith("DICT_") or not hasattr(cv2.aruco, v):
            raise ValueError(f"unknown cv2.aruco dictionary {v!r} (e.g. 'DICT_4X4_50')")
        return v

    def cv_board(self) -> Any:
        """The OpenCV board object (object points in metres, board frame)."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, d
        )

    @property
    def extent(self) -> tuple[float, float]:
        """Board width and height, metres."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    def board_to_sample(self) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and translation taking board-frame points to the sample frame.

        OpenCV's board frame has its origin at the board's top-left corner, x along the
        image columns, y down the rows, z into the board.  The board is printed centred on
        the sample-frame origin with its columns along +x and its rows along -y, so
        ``p_sample = R @ p_board + t``.
        """
        bw, bh = self.extent
        return np.diag([1.0, -1.0, -1.0]), np.array([-bw / 2, bh / 2, 0.0])

    def image(self) -> np.ndarray:
        """The printed board as a boolean array (True = white), row 0 at the board's top."""
        n = self.pixels_per_square
        img = self.cv_board().generateImage(
            (self.squares_x * n, self.squares_y * n), marginSize=0, borderBits=1
        )
        return img > 127


class ReferencePatch(_Model):
    """A Lambertian patch of known albedo on the holder (radiometric reference)."""

    center: Vec2
    size: tuple[Positive, Positive]
    albedo: RGBOrScalar = 0.99


class Holder(_Model):
    """A Lambertian plate around the sample carrying a ChArUco board."""

    width: Positive
    height: Positive
    albedo_black: RGBOrScalar = 0.04
    albedo_white: RGBOrScalar = 0.85
    board: Board | None = Field(default_factory=Board)
    reference_patch: ReferencePatch | None = None


class PointLight(_Model):
    """An isotropic point source; ``intensity`` in W/sr per channel."""

    type: Literal["point"] = "point"
    position: Vec3
    intensity: Colour


class _AreaLight(_Model):
    """An area light.  ``radiance`` is its emitted radiance along its normal; off the
    normal it falls as ``cos^profile_n(psi)`` (0: a Lambertian emitter), and over its face
    it varies linearly, ``1 + gradient (rho / R) cos(phi - gradient_angle_deg)`` on a disk
    (``1 + gradient ((2x/w) cos + (2y/h) sin)`` on a rectangle), phi in the light's face
    frame: the light body's, ``face_up`` its "up" in the face plane (set by the rig's poses:
    a light on an arm keeps its face pattern as the arm and the stage move), else its
    tangent frame (:class:`gonio.simulator.lights.PreparedLight` ``e1``, ``e2``)."""

    position: Vec3
    normal: Vec3 | None = None
    look_at: Vec3 | None = None
    radiance: Colour
    profile_n: Annotated[float, Field(ge=0, le=50, allow_inf_nan=False)] = 0.0
    gradient: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.0
    gradient_angle_deg: Annotated[float, Field(allow_inf_nan=False)] = 0.0
    face_up: Vec3 | None = None

    @model_validator(mode="after")
    def _orientation(self) -> _AreaLight:
        if self.normal is not None and self.look_at is not None:
            raise ValueError("give 'normal' or 'look_at', not both")
        n = _unit(self.emit_normal(), "light normal")
        if self.face_up is not None:
            up = np.asarray(self.face_up, float)
            if np.linalg.norm(up - n * (up @ n)) < 1e-9 * max(np.linalg.norm(up), 1.0):
                raise ValueError(
                    f"face_up {list(self.face_up)} has no component in the light's face "
                    f"plane (normal {n.round(6).tolist()}): expected a direction across it"
                )
        return self

    def emit_normal(self) -> np.ndarray:
        """Unit emitting direction (the light emits into its +normal half-space)."""
        if self.normal is not None:
            return _unit(self.normal, "normal")
        target = np.zeros(3) if self.look_at is None else np.asarray(self.look_at, float)
        return _unit(target - np.asarray(self.position, float), "look_at - position")


class DiskLight(_AreaLight):
    """A one-sided disk emitter (Lambertian unless ``profile_n``); ``radiance`` in
    W/(sr m^2) per channel."""

    type: Literal["disk"] = "disk"
    radius: Positive


class RectangleLight(_AreaLight):
    """A one-sided rectangle emitter (Lambertian unless ``profile_n``); ``width`` along
    ``up x normal``, ``height`` along ``up`` (projected perpendicular to the normal)."""

    type: Literal["rectangle"] = "rectangle"
    width: Positive
    height: Positive
    up: Vec3 = (0.0, 0.0, 1.0)


Light = Annotated[PointLight | DiskLight | RectangleLight, Field(discriminator="type")]


class BoxOccluder(_Model):
    """An opaque box: centre, full size along its axes, xyz Euler rotation in degrees."""

    type: Literal["box"] = "box"
    center: Vec3
    size: tuple[Positive, Positive, Positive]
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)

    def rotation(self) -> np.ndarray:
        """Box-to-world rotation (columns are the box axes)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_euler("xyz", self.rotation_deg, degrees=True).as_matrix()


class CylinderOccluder(_Model):
    """An opaque capped cylinder from ``start`` to ``end``."""

    type: Literal["cylinder"] = "cylinder"
    start: Vec3
    end: Vec3
    radius: Positive

    @model_validator(mode="after")
    def _has_length(self) -> CylinderOccluder:
        _unit(np.subtract(self.end, self.start), "end - start")
        return self


Occluder = Annotated[BoxOccluder | CylinderOccluder, Field(discriminator="type")]


class Sensor(_Model):
    """Sensor and RAW-file parameters (defaults: a generic 14-bit CMOS)."""

    quantum_efficiency: RGBOrScalar = (0.45, 0.55, 0.40)
    wavelength_nm: tuple[Positive, Positive, Positive] = (610.0, 540.0, 465.0)
    full_well: Positive = 40000.0
    read_noise: Annotated[float, Field(ge=0)] = 3.0
    dark_current: Annotated[float, Field(ge=0)] = 0.1
    gain_at_base_iso: Positive = 0.4
    base_iso: Positive = 100.0
    black_level: Annotated[int, Field(ge=0)] = 512
    bits: Annotated[int, Field(ge=8, le=16)] = 14
    cfa_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] = "RGGB"
    vignetting: bool = True
    spectral_sensitivities: str = "Nikon 5100 (NPL)"
    model: str = "gonio simulated camera"

    @property
    def white_level(self) -> int:
        """Largest DN the ADC produces."""
        return 2**self.bits - 1

    @model_validator(mode="after")
    def _black_below_white(self) -> Sensor:
        if self.black_level >= 2**self.bits - 1:
            raise ValueError(f"black_level must be below the white level {2**self.bits - 1}")
        return self


class Camera(_Model):
    """A pinhole camera with a thin-lens aperture for exposure, optionally with lens
    distortion (OpenCV Brown-Conrady ``(k1, k2, p1, p2, k3)``, see the module docstring)."""

    resolution: tuple[Annotated[int, Field(ge=1)], Annotated[int, Field(ge=1)]]
    focal_length: Positive = 0.035
    pixel_pitch: Positive | None = None
    fov_deg: Annotated[float, Field(gt=0, lt=180)] | None = None
    principal_point: Vec2 | None = None
    distortion: tuple[float, float, float, float, float] | None = None
    position: Vec3 | None = None
    look_at: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 0.0, 1.0)
    rotation: tuple[Vec3, Vec3, Vec3] | None = None
    f_number: Positive = 8.0
    exposure_time: ExposureTime = 0.01
    iso: Positive = 100.0
    sensor: Sensor = Field(default_factory=Sensor)

    @model_validator(mode="after")
    def _intrinsics(self) -> Camera:
        if (self.pixel_pitch is None) == (self.fov_deg is None):
            raise ValueError("give exactly one of 'pixel_pitch' or 'fov_deg'")
        if self.distortion is not None and not all(np.isfinite(self.distortion)):
            raise ValueError(f"distortion must be finite, got {list(self.distortion)}")
        return self

    @property
    def has_distortion(self) -> bool:
        """Whether ``distortion`` is given and not all zero."""
        return self.distortion is not None and any(c != 0.0 for c in self.distortion)

    @property
    def pitch(self) -> float:
        """Pixel pitch, metres."""
        if self.pixel_pitch is not None:
            return self.pixel_pitch
        half = np.tan(np.radians(self.fov_deg) / 2)
        return 2 * self.focal_length * half / self.resolution[0]

    def intrinsics(self) -> np.ndarray:
        """The 3x3 OpenCV camera matrix K (pixels; pixel centres at integer + 0.5)."""
        w, h = self.resolution
        f = self.focal_length / self.pitch
        cx, cy = self.principal_point if self.principal_point else (w / 2, h / 2)
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])


class RigPoseSpec(_Model):
    """Light and camera poses from rig joint angles (``gonio.rig.kinematics``)."""

    joints_deg: dict[str, float]
    config: Path | None = None


class RenderSettings(_Model):
    """Renderer controls (see :func:`gonio.simulator.render.render`)."""

    tolerance: Positive = 1e-4
    strategy: Literal["auto", "point", "quadrature", "mc"] = "auto"
    quadrature_order: Annotated[int, Field(ge=1, le=64)] = 4
    mc_samples: Annotated[int, Field(ge=1)] = 64
    antialias: Annotated[int, Field(ge=1, le=16)] = 4
    spot_antialias: Annotated[int, Field(ge=1, le=32)] = 16
    print_antialias: Literal["exact", "rays"] = "exact"
    chunk_size: Annotated[int, Field(ge=1024)] = 262144
    seed: int = 0


#: The scene document's schema version.  2: the board print's edges are anti-aliased by
#: their exact area coverage unless ``render.print_antialias = "rays"`` (different RAW
#: bytes on those pixels); 1: by sub-rays, as before (a session's manifest without a
#: version is from then, and resumes as it began).  A document without one is current.
SCENE_SCHEMA_VERSION = 2


class Scene(_Model):
    """Everything the simulated camera sees.  See the module docstring for the schema."""

    schema_version: Literal[1, 2] = SCENE_SCHEMA_VERSION
    sample: Sample
    holder: Holder | None = None
    lights: list[Light] = Field(min_length=1)
    occluders: list[Occluder] = Field(default_factory=list)
    camera: Camera
    render: RenderSettings = Field(default_factory=RenderSettings)
    rig: RigPoseSpec | None = None
    base_dir: Path | None = Field(default=None, exclude=True)

    @model_validator(mode="before")
    @classmethod
    def _schema_defaults(cls, data: Any) -> Any:
        # a version-1 document renders what it rendered then: print edges by sub-rays
        if isinstance(data, dict) and data.get("schema_version") == 1:
            render = data.get("render")
            render = dict(render) if isinstance(render, dict) else {}
            if render.get("print_antialias") is None:
                data = {**data, "render": {**render, "print_antialias": "rays"}}
        return data

    @model_validator(mode="after")
    def _geometry(self) -> Scene:
        h = self.holder
        if h is not None:
            if h.width < self.sample.width or h.height < self.sample.height:
                raise ValueError("holder must be at least as large as the sample")
            if h.board is not None:
                bw, bh = h.board.extent
                if bw > h.width + 1e-12 or bh > h.height + 1e-12:
                    raise ValueError(
                        f"board ({bw:g} x {bh:g} m) does not fit on the holder "
                        f"({h.width:g} x {h.height:g} m)"
                    )
        if self.camera.position is None and self.camera.rotation is None and self.rig is None:
            raise ValueError("camera: give 'position' (and 'look_at' or 'rotation') or [rig]")
        return self

    def resolve(self, path: Path) -> Path:
        """A path from the scene file, relative to the file's folder."""
        if path.is_absolute() or self.base_dir is None:
            return path
        return self.base_dir / path

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre (3,) and world-to-camera rotation (3, 3), sample frame."""
        cam = self.camera
        if cam.position is None:
            raise ConfigError(
                "camera.position: not given, and the [rig] joint angles were not turned into "
                "poses (load the scene with gonio.app.scenes.load_scene, as gonio sim render "
                "does, or give the camera a pose provider)"
            )
        pos = np.asarray(cam.position, float)
        if cam.rotation is not None:
            R = np.asarray(cam.rotation, float)
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ConfigError("camera.rotation: not a proper rotation matrix")
            return pos, R
        try:
            return pos, look_at_rotation(pos, cam.look_at, cam.up)
        except ValueError as exc:
            raise ConfigError(f"camera.look_at: {exc}") from exc

    def light_rgb(self, value: Colour) -> np.ndarray:
        """A light's colour as camera RGB (3,)."""
        if isinstance(value, Spectrum):
            return value.to_camera_rgb(self.camera.sensor.spectral_sensitivities, self.base_dir)
        return _rgb(value)

    def build_brdf(self) -> Any:
        """The bound sample BRDF: an object with ``eval(wi, wo) -> (..., 3)``.

        Raises
        ------
        ConfigError
            Unknown model, bad parameters, or a missing measured file (field named).
        """
        from gonio.errors import GonioError

        if self.sample.spatially_varying:
            from gonio.simulator.svbrdf import build_spatial_brdf

            return build_spatial_brdf(self)
        spec = self.sample.brdf
        assert spec is not None  # Sample's validator: brdf unless mix
        if spec.file is not None:
            import gonio.brdf

            path = self.resolve(spec.file)
            if not path.is_file():
                raise ConfigError(f"sample.brdf.file: {path} does not exist")
            return gonio.brdf.load(path)
        import gonio.brdf

        try:
            model = gonio.brdf.get_model(spec.model, **spec.options)
            params = {k: np.asarray(v, dtype=np.float64) for k, v in spec.params.items()}
            return model.bind(params)
        except GonioError as exc:
            raise ConfigError(f"sample.brdf: {exc}") from exc

    def with_reference_target(self, albedo: RGBOrScalar = 0.99) -> Scene:
        """The same scene with a Lambertian target of ``albedo`` in place of the sample."""
        brdf = BRDFSpec(model="lambert", params={"albedo": list(_rgb(albedo))})
        sample = self.sample.model_copy(
            update={"brdf": brdf, "albedo_map": None, "maps": None, "mix": None}
        )
        return self.model_copy(update={"sample": sample})

    def with_mirror_target(self, reflectance: float = 0.9) -> Scene:
        """The same scene with a flat first-surface mirror of grey ``reflectance`` in the
        sample's rectangle (flush with the holder) in place of the sample.

        Raises
        ------
        ConfigError
            ``reflectance`` is not in (0, 1].
        """
        if not 0.0 < float(reflectance) <= 1.0:
            raise ConfigError(f"mirror reflectance = {reflectance!r}: expected a value in (0, 1]")
        sample = self.sample.model_copy(
            update={
                "mirror_reflectance": float(reflectance),
                "albedo_map": None,
                "maps": None,
                "mix": None,
            }
        )
        return self.model_copy(update={"sample": sample})

    def with_poses(
        self,
        camera_position: Any,
        camera_rotation: Any,
        light_position: Any | None = None,
        light_normal: Any | None = None,
        light_up: Any | None = None,
    ) -> Scene:
        """The same scene with the camera (and first light) moved; sample-frame metres.

        ``camera_rotation`` is world-to-camera in OpenCV axes.  A point light ignores
        ``light_normal`` and ``light_up`` (the light body's up in its face plane: the
        frame of its face gradient).
        """
        R = np.asarray(camera_rotation, float)
        cam = self.camera.model_copy(
            update={
                "position": tuple(map(float, np.asarray(camera_position, float))),
                "rotation": tuple(tuple(map(float, r)) for r in R),
            }
        )
        lights = list(self.lights)
        if light_position is not None:
            upd: dict[str, Any] = {"position": tuple(map(float, light_position))}
            if not isinstance(lights[0], PointLight) and light_normal is not None:
                upd.update(normal=tuple(map(float, light_normal)), look_at=None)
            if not isinstance(lights[0], PointLight) and light_up is not None:
                upd.update(face_up=tuple(map(float, light_up)))
            lights[0] = lights[0].model_copy(update=upd)
        return self.model_copy(update={"camera": cam, "lights": lights})


def parse_scene(
    data: dict[str, Any],
    source: str = "<scene>",
    base_dir: Path | None = None,
    *,
    rig_poses: Callable[[Scene], Any] | None = None,
):
    """Validate a scene given as a dict (e.g. parsed TOML).

    Parameters
    ----------
    data, source, base_dir
        The document, its name for messages, and the folder its paths start from.
    rig_poses
        For a scene with a ``[rig]`` table: ``scene -> RigPoses``-like poses of the light
        and camera at its joint angles.  The simulator does not know the rig's
        kinematics (they are the controller's); the composition root passes them
        (:func:`gonio.app.scenes.load_scene`).  Without it the scene keeps the poses it
        states, if any, and a camera without a pose is refused when it is rendered.

    Raises
    ------
    ConfigError
        Naming the source and each offending field.
    """
    scene = validate(Scene, {**data, "base_dir": base_dir}, f"{source}: invalid scene")
    if scene.sample.spatially_varying:
        from gonio.simulator.svbrdf import check_layout

        try:
            check_layout(scene)  # shapes, NaN, bounds, labels: before anything renders
        except ConfigError as exc:
            raise ConfigError(f"{source}: invalid scene: {exc}") from None
    if scene.rig is not None and rig_poses is not None:
        scene = scene_with_rig_poses(scene, rig_poses(scene))
    return scene


def scene_with_rig_poses(scene: Scene, poses: Any) -> Scene:
    """Apply a ``gonio.rig.kinematics.RigPoses``-like object (or mapping) to the scene.

    Uses ``camera_position``, ``camera_rotation`` (camera-to-sample, OpenCV axes),
    ``light_position`` and ``light_normal``.
    """

    def get(name: str, *default: Any) -> Any:
        if isinstance(poses, dict):
            return poses.get(name, *default) if default else poses[name]
        return getattr(poses, name, *default)

    # RigPoses.camera_rotation is camera-to-sample (columns are the camera axes).
    return scene.with_poses(
        get("camera_position"),
        np.asarray(get("camera_rotation"), float).T,
        get("light_position"),
        get("light_normal"),
        get("light_up", None),  # the controller's poses carry no light body frame
    )


def load_scene(path: str | Path, *, rig_poses: Callable[[Scene], Any] | None = None) -> Scene:
    """Read and validate a scene TOML file.

    Raises
    ------
    ConfigError
        The file is missing, is not TOML, or a field is invalid (the field is named).
    """
    p = Path(path)
    return parse_scene(read_toml(p, "scene"), str(p), p.resolve().parent, rig_poses=rig_poses)

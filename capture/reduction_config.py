"""What the reduction knows besides the frames: ``reduction.toml`` and ``noise.json``.

A session is reduced with the facts of the camera, holder, light and reference target
that it was shot with: the camera matrix and distortion, the ChArUco board, the sample's
size, the light's radius, the sensor's noise model and the target's reflectance.  A lab
measures them with gonio's calibrations and writes them into ``SESSION/reduction.toml``
(``examples/reduction.toml`` explains every field); a simulated session gets its own,
written from its scene by the composition root (:mod:`gonio.app.sim_reduction`), so the
reduction never reads a scene.  ``gonio capture calibrate-noise`` writes ``noise.json``.

Both documents are pydantic models read through :func:`gonio.config.read_toml` and
:func:`gonio.config.validate`, so a wrong value is a :class:`~gonio.errors.ConfigError`
naming the file and the field, as for plans, rigs and scenes.
:class:`ReductionSetup` is the validated result the rest of the reduction reads.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gonio.capture.calibration import reference_reflectance
from gonio.capture.fiducials import BoardSpec
from gonio.capture.noise import NoiseModel
from gonio.capture.raw import CameraSignature
from gonio.charuco import board_markers_problem
from gonio.config import read_toml, validate
from gonio.errors import ConfigError, FileFormatError, ReductionError, SessionError

__all__ = [
    "CONFIG_FILE",
    "CameraCalibrationSection",
    "CameraIdentity",
    "CameraSection",
    "NOISE_FILE",
    "NoiseDocument",
    "ReductionConfig",
    "ReductionSetup",
    "camera_identity",
    "check_camera_identity",
    "identity_digest",
    "load_camera_file",
    "load_noise",
    "load_reduction_config",
    "resolve_setup",
    "setup_from_config",
]

CONFIG_FILE = "reduction.toml"
NOISE_FILE = "noise.json"

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)]
Row3 = tuple[Finite, Finite, Finite]


class _Strict(BaseModel):
    # unknown keys are refused: a misspelt field (``gird = 6``) must not be ignored
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraIdentity(BaseModel):
    """``[camera.calibration.camera]``: the camera a calibration was made with, as its
    ``describe()`` reports it (other keys are kept)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    backend: str
    model: str
    serial: str | None = None
    resolution: tuple[Annotated[int, Field(ge=1)], Annotated[int, Field(ge=1)]] | None = None


class CameraCalibrationSection(BaseModel):
    """``[camera.calibration]``: how ``gonio calibrate camera`` found the ``[camera]``
    numbers: their standard deviations, the reprojection RMS, the camera's identity and
    its digest (further keys, such as the views used and rejected, are kept as given)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    K_std: tuple[tuple[NonNegative, ...], ...] | tuple[NonNegative, ...] | None = None
    dist_std: tuple[NonNegative, ...] | None = None
    rms_px: NonNegative | None = None
    camera: CameraIdentity | None = None
    digest: Annotated[str, Field(pattern=r"^sha256:[0-9a-f]{64}$")] | None = None
    created: str | None = None


class CameraSection(_Strict):
    """``[camera]``: intrinsics (OpenCV convention: pixel centres at integers) and the
    CFA layout and size every frame of the session must have; or ``file`` naming a
    camera calibration (``gonio calibrate camera --out camera.toml``) relative to the
    ``reduction.toml``, whose ``[camera]`` table gives all of them."""

    file: str | None = None
    K: tuple[Row3, Row3, Row3] | None = None
    dist: tuple[Finite, ...] | None = None
    cfa_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] | None = None
    width: Annotated[int, Field(ge=1)] | None = None
    height: Annotated[int, Field(ge=1)] | None = None
    calibration: CameraCalibrationSection | None = None

    @model_validator(mode="after")
    def _file_or_numbers(self) -> CameraSection:
        if self.file is not None:
            given = [k for k in self.model_fields_set if k != "file"]
            if given:
                raise ValueError(
                    f"give file = 'camera.toml' or the camera's numbers, not both (also "
                    f"given: {', '.join(sorted(given))})"
                )
        elif self.K is None:
            raise ValueError("give K (3x3 camera matrix, pixels), or file = 'camera.toml'")
        return self

    @field_validator("cfa_pattern", mode="before")
    @classmethod
    def _upper(cls, v: Any) -> Any:
        return v.upper() if isinstance(v, str) else v

    @field_validator("K")
    @classmethod
    def _camera_matrix(cls, v: tuple[Row3, Row3, Row3] | None) -> tuple[Row3, Row3, Row3] | None:
        if v is None:
            return v
        if not (v[0][0] > 0 and v[1][1] > 0):
            raise ValueError(f"focal lengths K[0][0] and K[1][1] must be > 0 pixels, got {v}")
        if tuple(v[2]) != (0.0, 0.0, 1.0):
            raise ValueError(f"the last row of K must be [0, 0, 1], got {list(v[2])}")
        return v

    @field_validator("dist")
    @classmethod
    def _opencv_length(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and len(v) not in (4, 5, 8, 12, 14):
            raise ValueError(f"OpenCV takes 4, 5, 8, 12 or 14 coefficients, got {len(v)}")
        return v

    @model_validator(mode="after")
    def _size_together(self) -> CameraSection:
        if (self.width is None) != (self.height is None):
            raise ValueError("give both width and height (pixels), or neither")
        return self


class NoiseSection(_Strict):
    """``[noise]``: the photon-transfer model (DN per electron and DN at ``iso``), or
    ``file`` naming a ``noise.json`` relative to the ``reduction.toml``."""

    file: str | None = None
    gain: Positive | None = None
    read_noise: NonNegative | None = None
    iso: Positive = 100.0
    quantisation: bool = True
    #: The sensor's photo-response non-uniformity, relative rms per pixel: the budget's
    #: ``flat`` term of a session without flat fields (a lab's statement, or the
    #: sensor's data sheet).
    prnu: NonNegative = 0.01
    #: The sensor's dark signal non-uniformity, electrons rms per pixel: the budget's
    #: ``dark`` term of a session without dark frames.
    dsnu_e: NonNegative = 5.0

    @model_validator(mode="after")
    def _file_or_numbers(self) -> NoiseSection:
        numbers = self.gain is not None or self.read_noise is not None
        if self.file is not None and numbers:
            raise ValueError("give file = 'noise.json' or gain and read_noise, not both")
        if self.file is None and (self.gain is None or self.read_noise is None):
            raise ValueError("give gain (DN/e-) and read_noise (DN), or file = 'noise.json'")
        return self


class BoardSection(_Strict):
    """``[board]``: the holder's ChArUco board (defaults: the simulator's board)."""

    squares_x: Annotated[int, Field(ge=2)] = 7
    squares_y: Annotated[int, Field(ge=2)] = 7
    square_length: Positive = 0.02
    marker_length: Positive = 0.015
    dictionary: str = "DICT_4X4_50"

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, v: str) -> str:
        import cv2

        if not v.startswith("DICT_") or not hasattr(cv2.aruco, v):
            raise ValueError(f"unknown cv2.aruco dictionary {v!r} (e.g. 'DICT_4X4_50')")
        return v

    @model_validator(mode="after")
    def _marker_fits(self) -> BoardSection:
        if self.marker_length >= self.square_length:
            raise ValueError("marker_length must be smaller than square_length")
        return self

    @model_validator(mode="after")
    def _dictionary_has_the_markers(self) -> BoardSection:
        problem = board_markers_problem(self.squares_x, self.squares_y, self.dictionary)
        if problem:
            raise ValueError(problem)
        return self


class SampleSection(_Strict):
    """``[sample]``: width (x) and height (y) of the sample, metres, centred on the origin."""

    width: Positive
    height: Positive


class LightSection(_Strict):
    """``[light]``: radius of the disk light, metres (left out: a point source); its
    radiance profile; and the lab's statements the budget needs where the session does
    not measure them."""

    radius: Positive | None = None
    #: The emitted radiance's profile ``cos^n(psi)`` about the light's normal:
    #: ``"none"`` (n = 0, a Lambertian emitter: today's G), ``"fit"`` (n fitted from the
    #: reference target's regions and applied in G) or a number (a measured n).
    profile: Literal["none", "fit"] | NonNegative = "none"
    #: Standard uncertainty of the profile's exponent n when it is not fitted (or the
    #: fit is no better): the lab's statement (an unmeasured LED lies within n = 0..2).
    profile_n_std: NonNegative = 1.0
    #: Upper bound of the room's stray light (the light's own output scattered back onto
    #: the sample) as a fraction of the light's direct irradiance at normal incidence.
    stray_fraction: Annotated[float, Field(ge=0, le=0.5)] = 5e-4
    #: Relative standard uncertainty of the light's output between the reference shots
    #: when the session shot the reference group once (the drift is not measured).
    drift_rel_std: Annotated[float, Field(ge=0, le=0.5)] = 0.01


class ReferenceSection(_Strict):
    """``[reference]``: the reference target's reflectance (one value, three for R, G, B,
    or a CSV spectrum relative to the ``reduction.toml``; left out: the session's plan
    value) and its standard uncertainty."""

    reflectance: Fraction | tuple[Fraction, Fraction, Fraction] | str | None = None
    reflectance_std: NonNegative | tuple[NonNegative, NonNegative, NonNegative] = 0.0


class ReductionSection(_Strict):
    """``[reduction]``: defaults of the ``gonio capture reduce`` options."""

    roi_fraction: Annotated[float, Field(ge=0.05, le=1.0)] = 0.6
    grid: Annotated[int, Field(ge=1, le=20)] = 3
    geometry_tolerance_deg: Positive = 0.5
    position_tolerance_m: Positive = 0.01
    min_snr: NonNegative = 5.0
    geometry: Literal["board", "rig", "auto"] = "auto"
    max_board_obliquity_deg: Annotated[float, Field(gt=0, le=90, allow_inf_nan=False)] = 60.0
    min_board_corners: Annotated[int, Field(ge=4)] = 10
    max_region_spread_deg: Annotated[float, Field(gt=0, le=90, allow_inf_nan=False)] | None = None
    #: Image pixels kept clear of the boundaries between regions (a texel reduction
    #: takes at least gonio.capture.texel_reduce.TEXEL_MARGIN_PX).
    region_margin_px: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    #: Assumed std of each joint's zero offset (deg) when the rig has no calibration
    #: covariance: the uncertainty budget's session geometry modes (issue 16, H3).
    nominal_joint_std_deg: NonNegative = 0.1
    #: Correct each region's mean over its pixels to its reported direction
    #: (:mod:`gonio.capture.aperture`; false: the region's mean as measured).
    aperture_correction: bool = True
    #: The chart of the budget's model-free BRDF gradient
    #: (:func:`gonio.capture.budget.local_log_gradient`): "auto" follows the plan's
    #: ``[reductions] isotropic`` (a material declared isotropic: "isotropic"), or
    #: "isotropic" / "projected" whatever the plan says.
    gradient_chart: Literal["auto", "isotropic", "projected"] = "auto"


class ReductionConfig(_Strict):
    """A whole ``reduction.toml`` (see ``examples/reduction.toml``)."""

    camera: CameraSection
    noise: NoiseSection | None = None
    board: BoardSection = BoardSection()
    sample: SampleSection
    light: LightSection = LightSection()
    reference: ReferenceSection = ReferenceSection()
    reduction: ReductionSection = ReductionSection()


class NoiseDocument(_Strict):
    """A ``noise.json`` (:meth:`gonio.capture.noise.NoiseModel.save`)."""

    type: Literal["gonio.noise_model"] | None = None
    gain: Positive
    read_noise: NonNegative
    iso: Positive = 100.0
    quantisation: bool = True

    def model(self) -> NoiseModel:
        """The :class:`~gonio.capture.noise.NoiseModel` it describes."""
        return NoiseModel(self.gain, self.read_noise, self.iso, self.quantisation)


@dataclass(frozen=True)
class ReductionSetup:
    """Camera, holder, light and noise facts the reduction needs.

    Attributes
    ----------
    K
        3x3 camera matrix, pixels, OpenCV convention (pixel centres at integers).
    board
        The holder's ChArUco board.
    sample_size
        Sample width (x) and height (y), metres, centred on the origin.
    noise
        Photon-transfer noise model of the camera.
    reflectance
        Reference target reflectance per channel (R, G, B).
    reflectance_std
        Its standard uncertainty per channel.
    light_radius
        Radius of the (disk) light, metres; None treats it as a point source.
    dist
        Lens distortion coefficients (OpenCV), None for none.
    signature
        The session camera's CFA pattern and mosaic size (frames that differ are refused);
        None takes it from the first frame.
    roi_fraction, grid
        Central fraction of the sample used, and regions per side (along x).
    grid_y
        Regions along y when they differ from ``grid`` (a texel reduction's NXxNY), None
        for a square grid.
    geometry_tolerance_deg, position_tolerance_m
        Largest disagreement between the camera pose from the board and the rig's report.
    geometry
        Where the camera pose comes from: ``"auto"`` (the default: the board where it is
        trustworthy and known better than the rig, else the rig), ``"board"`` (measured
        from the fiducials in each pose; a pose without a board takes the rig's, flagged
        GEOMETRY_MISMATCH) or ``"rig"`` (the rig's read-back pose through its
        (calibrated) kinematics).  The board checks the rig wherever it is used or
        trusted, flagging disagreements.
        Use ``"rig"`` when the rig's geometry is known better than one board view
        measures it (a calibrated rig, or the simulator, whose rig is exact): on a sharp
        lobe's flank a 0.04 deg pose error is a percent of BRDF, shared by every region
        of the pose.  ``"auto"`` takes the board's pose when it was found with at least
        ``min_board_corners`` corners and is seen at most ``max_board_obliquity_deg``
        off its normal, unless the rig's covariance (its calibration's, through the
        kinematics at the pose) moves the pose's directions less than the board's own
        (:func:`gonio.capture.budget.direction_variance`), when the rig's pose is taken
        and the board checks it; otherwise the rig's, not flagged (a board seen edge-on,
        or not at all, says nothing against the rig), and not checked.
    max_board_obliquity_deg, min_board_corners
        ``"auto"``'s limits of a trustworthy board view (degrees off the board's normal,
        by the board's own pose; ChArUco corners).  Chosen from the default demo's
        perfect world at 320 x 240, where the rig is exact: up to 60 deg the board's
        camera direction was within 0.31 deg of the rig's (90th percentile 0.22 deg)
        with 10 corners or more; at 60-70 deg the board showed 6-9 corners, its
        direction was off by 0.24 deg in the median and up to 0.40 deg, and beyond 70
        deg it was rarely found at all.
    region_margin_px
        Image pixels kept free inside each region along its boundaries with the others
        (0: none; a texel reduction sets :data:`gonio.capture.texel_reduce.TEXEL_MARGIN_PX`):
        a pixel whose footprint or whose Bayer interpolation stencil reaches across a
        boundary mixes the neighbouring region's radiance in, which for a spatially
        varying sample is another material (:func:`gonio.capture.pose_measure.region_margins`).
    max_region_spread_deg
        Largest spread (full width, degrees) of a region's directions seen from the
        camera and from the light, or None (the default: whole cells, the grid alone
        sets a region's size).  Each cell is trimmed to its central part along the axes
        where it spans more (:func:`gonio.capture.fiducials.spread_margins`), never
        along an axis seen foreshortened (the tilt of a grazing view), so oblique
        regions keep their pixels.  A region's value is the BRDF's mean over its
        directions, reported at their mean, which on a lobe's peak is low by about
        (spread / lobe width)^2: at 320 x 240 and 6 x 6 regions of 5 mm (0.7 deg from
        0.4 m) a grazing near-specular region of a GGX alpha = 0.2 lobe came out 0.6 %
        low; ``gonio demo`` takes 0.3 deg, what the former 2-pixel margins kept at its
        near-normal views (~2.3 mm of a 5 mm cell).
    min_snr
        Regions whose signal-to-noise ratio is lower are flagged UNDEREXPOSED.
    nominal_joint_std_deg
        Assumed standard deviation of every joint's zero offset, deg, for the budget's
        geometry when the rig carries no calibration covariance (an assumption).
    gradient_chart
        ``[reduction] gradient_chart``: the chart the budget's BRDF gradient is fitted on,
        ``"auto"`` (the plan's ``[reductions] isotropic`` decides: ``"isotropic"`` when
        set, else ``"projected"``), ``"isotropic"`` or ``"projected"``
        (:func:`gonio.capture.budget.local_log_gradient`); what was used is the samples'
        ``budget_gradient_chart`` attribute.
    aperture_correction
        Subtract each region's aperture bias ``1/2 tr(H S)`` (the curvature of the BRDF
        over the sample, measured from the pose's neighbouring regions, times the
        covariance of the region's pixel positions; :mod:`gonio.capture.aperture`) so
        that its value is the BRDF at its reported direction, not the mean over its
        pixels (default True; False keeps the mean as measured).
    camera_calibration
        The camera calibration's ``[camera.calibration]`` table (standard deviations,
        RMS, camera identity and digest) when the camera came from one, else None.
    camera_file
        The camera calibration file it came from, None for numbers in the document.
    light_profile
        ``[light] profile``: ``"none"``, ``"fit"`` or a stated exponent n.
    light_profile_n
        The exponent n of the ``cos^n(psi)`` radiance profile applied in G (0: a
        Lambertian emitter; the reduction sets it from ``light_profile``).
    light_profile_n_std
        ``[light] profile_n_std``: the stated std of n when it is not fitted.
    stray_fraction, drift_rel_std
        ``[light]``: the stray light's upper bound (fraction of the direct irradiance at
        normal incidence) and the drift's relative std with one reference group.
    prnu, dsnu_e
        ``[noise]``: PRNU (relative rms) and DSNU (e- rms) per pixel, the budget's
        ``flat`` and ``dark`` terms without flats or darks.
    intrinsics_source
        Where ``K`` and ``dist`` come from: ``"camera"`` (reduction.toml or the camera
        calibration) or ``"rig calibration"`` (:func:`rig_refined_camera`).
    """

    K: NDArray[np.float64]
    board: BoardSpec
    sample_size: tuple[float, float]
    noise: NoiseModel
    reflectance: NDArray[np.float64]
    reflectance_std: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    light_radius: float | None = None
    dist: NDArray[np.float64] | None = None
    signature: CameraSignature | None = None
    roi_fraction: float = 0.6
    grid: int = 3
    geometry_tolerance_deg: float = 0.5
    position_tolerance_m: float = 0.01
    min_snr: float = 5.0
    geometry: str = "auto"
    max_board_obliquity_deg: float = 60.0
    min_board_corners: int = 10
    max_region_spread_deg: float | None = None
    nominal_joint_std_deg: float = 0.1
    aperture_correction: bool = True
    gradient_chart: str = "auto"
    camera_calibration: dict[str, Any] | None = None
    camera_file: str | None = None
    light_profile: str | float = "none"
    light_profile_n: float = 0.0
    light_profile_n_std: float = 1.0
    stray_fraction: float = 5e-4
    drift_rel_std: float = 0.01
    intrinsics_source: str = "camera"
    prnu: float = 0.01
    dsnu_e: float = 5.0
    grid_y: int | None = None
    region_margin_px: float = 0.0

    @property
    def grid_xy(self) -> tuple[int, int]:
        """Regions along x and along y."""
        return (self.grid, self.grid if self.grid_y is None else self.grid_y)

    def replace(self, **changes: Any) -> ReductionSetup:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)


def load_noise(path: str | os.PathLike) -> NoiseModel:
    """Read a ``noise.json``.

    Raises
    ------
    FileFormatError
        When the file cannot be read or is not JSON (names the file).
    ConfigError
        When a field is missing or wrong (names the file and the field).
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise FileFormatError(p, f"not a readable JSON noise model ({exc})") from None
    return validate(NoiseDocument, doc, f"{p} (noise model)").model()


def load_camera_file(path: str | os.PathLike) -> CameraSection:
    """Read the ``[camera]`` table of a camera calibration file (``gonio calibrate camera
    --out camera.toml``), with its ``[camera.calibration]`` sub-table.

    Raises
    ------
    ConfigError
        Unreadable, not TOML, no ``[camera]`` table, or a field missing or wrong (names
        the file and the field); a camera file that names another (``file =``).
    """
    p = Path(path)
    doc = read_toml(p, "camera calibration")
    if not isinstance(doc.get("camera"), dict):
        raise ConfigError(
            f"{p}: field 'camera': missing: a camera calibration holds a [camera] table "
            "(K, dist, width, height, cfa_pattern; from gonio calibrate camera)"
        )
    cam = validate(CameraSection, doc["camera"], f"{p} (camera calibration), table [camera]")
    if cam.file is not None:
        raise ConfigError(
            f"{p} (camera calibration): field 'camera.file': a camera file must give the "
            f"camera's numbers itself, not name another file ({cam.file!r})"
        )
    return cam


def identity_of(
    record: Mapping[str, Any], image_size: tuple[int, int] | None = None
) -> dict[str, Any]:
    """The identity ``{backend, model, serial, resolution}`` of a camera record
    (:meth:`gonio.devices.CameraInfo.to_json`, a session manifest's ``camera``, or a
    mapping already in this form).  ``serial`` and ``resolution`` are read from the
    record or its ``settings``; a camera that reports no resolution (gphoto2) takes
    ``image_size`` (width, height) -- the size of its frames -- else None."""
    settings = record.get("settings") or {}

    def pick(key: str) -> Any:
        v = record.get(key)
        return settings.get(key) if v is None and isinstance(settings, Mapping) else v

    res = pick("resolution")
    if res is None:
        res = image_size
    return {
        "backend": str(record.get("backend", "")),
        "model": str(record.get("model", "")),
        "serial": None if pick("serial") is None else str(pick("serial")),
        "resolution": None if res is None else [int(x) for x in res],
    }


def camera_identity(
    record: Mapping[str, Any], image_size: tuple[int, int] | None = None
) -> dict[str, Any] | None:
    """:func:`identity_of` a manifest's camera record, or None when it records no
    backend and model (nothing to check a calibration against)."""
    if not isinstance(record, Mapping) or not record.get("backend") or not record.get("model"):
        return None
    return identity_of(record, image_size)


def identity_digest(identity: Mapping[str, Any]) -> str:
    """``"sha256:<hex>"`` of a camera identity's canonical JSON (sorted keys, no spaces);
    :func:`gonio.capture.camera_calibration.camera_digest` is this function."""
    doc = {
        "backend": identity.get("backend"),
        "model": identity.get("model"),
        "serial": identity.get("serial"),
        "resolution": None
        if identity.get("resolution") is None
        else [int(x) for x in identity["resolution"]],
    }
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def check_camera_identity(setup: ReductionSetup, manifest: Mapping[str, Any]) -> None:
    """Refuse a camera calibration made with another camera than the session's.

    Checked when the calibration carries a ``digest`` and the manifest records the
    camera (:func:`camera_identity`).  The calibration is accepted when its digest is
    the session camera's, or when its recorded ``camera`` identity is the session's
    field by field.

    Raises
    ------
    ReductionError
        Naming the calibration file, both digests and the fields that differ.
    """
    cal = setup.camera_calibration or {}
    digest = cal.get("digest")
    # A camera that does not report its size (gphoto2) is taken at the size of the
    # calibration's frames, as `gonio calibrate camera` records it: every frame of this
    # session is checked against that size anyway.
    size = None if setup.signature is None else tuple(reversed(setup.signature.shape))
    session = camera_identity(manifest.get("camera") or {}, size)
    if digest is None or session is None:
        return
    ours = identity_digest(session)
    if digest == ours:
        return
    theirs = cal.get("camera")
    if isinstance(theirs, Mapping):
        mine = {k: theirs.get(k) for k in session}
        if mine.get("resolution") is not None:
            mine["resolution"] = [int(x) for x in mine["resolution"]]
        if mine == session:
            return
        diff = "; ".join(
            f"{k}: calibration {mine[k]!r}, session {session[k]!r}"
            for k in session
            if mine[k] != session[k]
        )
    else:
        diff = f"session camera {session}"
    raise ReductionError(
        f"{setup.camera_file or 'camera calibration'}: made with another camera (calibration "
        f"digest {digest}, the session's camera {ours}; {diff}): calibrate this camera "
        "(gonio calibrate camera) or give its own calibration"
    )


def _camera_setup(setup: ReductionSetup, cam: CameraSection, source: Path | None) -> ReductionSetup:
    """``setup`` with the camera numbers of a ``[camera]`` table (from ``source``)."""
    assert cam.K is not None
    signature = None
    if cam.cfa_pattern is not None and cam.width is not None and cam.height is not None:
        signature = CameraSignature(cam.cfa_pattern, (cam.height, cam.width))
    return setup.replace(
        K=np.asarray(cam.K, dtype=np.float64),
        dist=None if cam.dist is None else np.asarray(cam.dist, dtype=np.float64),
        signature=signature,
        camera_calibration=None
        if cam.calibration is None
        else cam.calibration.model_dump(mode="json", exclude_none=True),
        camera_file=None if source is None else str(source),
    )


def load_reduction_config(path: str | os.PathLike) -> ReductionConfig:
    """Read and validate a ``reduction.toml``.

    Raises
    ------
    ConfigError
        Unreadable, not TOML, or a field missing or wrong (names the file and the field).
    """
    p = Path(path)
    return validate(ReductionConfig, read_toml(p, "reduction setup"), str(p))


def setup_from_config(
    config: ReductionConfig,
    source: str | os.PathLike,
    *,
    base: str | os.PathLike | None = None,
    reflectance: Any = 0.99,
    noise: NoiseModel | None = None,
) -> ReductionSetup:
    """The :class:`ReductionSetup` a validated ``reduction.toml`` describes.

    Parameters
    ----------
    config
        The document.
    source
        Its file, for messages.
    base
        Directory that relative file names (``noise.file``, a reflectance CSV) refer to;
        the file's own directory by default.
    reflectance
        The reference reflectance when the document gives none (the session plan's).
    noise
        A noise model that replaces the document's (``noise.json``, ``--noise``).

    Raises
    ------
    ReductionError
        When no noise model is given anywhere.
    """
    src = Path(source)
    root = Path(base) if base is not None else src.parent
    if noise is None:
        if config.noise is None:
            raise ReductionError(
                f"{src}: field 'noise': missing, and no {NOISE_FILE} beside it: give gain "
                "(DN/e-) and read_noise (DN), or file = 'noise.json'"
            )
        if config.noise.file is not None:
            noise = load_noise(root / config.noise.file)
        else:
            assert config.noise.gain is not None and config.noise.read_noise is not None
            noise = NoiseModel(
                config.noise.gain,
                config.noise.read_noise,
                config.noise.iso,
                config.noise.quantisation,
            )
    cam = config.camera
    cam_file = None
    if cam.file is not None:
        cam_file = root / cam.file
        cam = load_camera_file(cam_file)
    ref = config.reference
    refl = reflectance if ref.reflectance is None else ref.reflectance
    if isinstance(refl, str):
        refl = root / refl
    b = config.board
    red = config.reduction
    setup = ReductionSetup(
        K=np.eye(3),  # the camera's numbers follow (_camera_setup)
        board=BoardSpec(b.squares_x, b.squares_y, b.square_length, b.marker_length, b.dictionary),
        sample_size=(config.sample.width, config.sample.height),
        noise=noise,
        reflectance=reference_reflectance(refl),
        reflectance_std=np.broadcast_to(np.asarray(ref.reflectance_std, float), (3,)).copy(),
        light_radius=config.light.radius,
        roi_fraction=red.roi_fraction,
        grid=red.grid,
        geometry_tolerance_deg=red.geometry_tolerance_deg,
        position_tolerance_m=red.position_tolerance_m,
        min_snr=red.min_snr,
        geometry=red.geometry,
        max_board_obliquity_deg=red.max_board_obliquity_deg,
        min_board_corners=red.min_board_corners,
        max_region_spread_deg=red.max_region_spread_deg,
        region_margin_px=red.region_margin_px,
        light_profile=config.light.profile,
        light_profile_n=(
            float(config.light.profile) if not isinstance(config.light.profile, str) else 0.0
        ),
        light_profile_n_std=config.light.profile_n_std,
        stray_fraction=config.light.stray_fraction,
        drift_rel_std=config.light.drift_rel_std,
        prnu=config.noise.prnu if config.noise is not None else 0.01,
        dsnu_e=config.noise.dsnu_e if config.noise is not None else 5.0,
        nominal_joint_std_deg=red.nominal_joint_std_deg,
        aperture_correction=red.aperture_correction,
        gradient_chart=red.gradient_chart,
    )
    return _camera_setup(setup, cam, cam_file)


def resolve_setup(
    session: str | os.PathLike,
    manifest: dict[str, Any],
    noise: NoiseModel | None = None,
    *,
    config: str | os.PathLike | None = None,
    camera_calibration: str | os.PathLike | None = None,
) -> ReductionSetup:
    """Find the reduction facts of a session.

    The setup is ``config`` when given, else ``SESSION/reduction.toml``.  The noise model
    is ``noise`` when given, else ``SESSION/noise.json`` (``gonio capture
    calibrate-noise``) when present, else the document's ``[noise]``.  The reference
    reflectance defaults to the session plan's (the manifest's ``reference``).  The
    camera is ``camera_calibration``'s ``[camera]`` when given (``--camera-calibration``),
    else the document's; a calibration of another camera than the manifest's is refused
    (:func:`check_camera_identity`).

    Raises
    ------
    SessionError
        When there is no ``reduction.toml`` to read.
    ConfigError
        When it or the camera file is not valid (names the file and the field).
    ReductionError
        When the camera calibration was made with another camera (names both digests).
    """
    session = Path(session)
    path = Path(config) if config is not None else session / CONFIG_FILE
    if config is None and not path.is_file():
        raise SessionError(
            f"{session}: no {CONFIG_FILE} (camera matrix, board, sample size, noise model): "
            "the reduction does not know the camera; write one (see examples/reduction.toml) "
            "or pass --config.  A simulated session captured before sessions wrote their own: "
            f"python -m gonio.app.sim_reduction {session}"
        )
    ref = manifest.get("reference") or {}
    nfile = session / NOISE_FILE
    if noise is None and nfile.is_file():
        noise = load_noise(nfile)
    setup = setup_from_config(
        load_reduction_config(path),
        path,
        reflectance=ref.get("reflectance", 0.99),
        noise=noise,
    )
    if camera_calibration is not None:
        cam_file = Path(camera_calibration)
        setup = _camera_setup(setup, load_camera_file(cam_file), cam_file)
    check_camera_identity(setup, manifest)
    return rig_refined_camera(setup, manifest)


#: The intrinsics a rig calibration refines (``CalibrationRecord.intrinsics``), in the
#: order of OpenCV's K and distortion vector.
_RIG_INTRINSICS = ("fx", "fy", "cx", "cy")
_RIG_DISTORTION = ("k1", "k2", "p1", "p2", "k3")


def rig_refined_camera(setup: ReductionSetup, manifest: Mapping[str, Any]) -> ReductionSetup:
    """The camera with the intrinsics the session's rig calibration refined, when that
    calibration was made with this session's camera.

    ``gonio calibrate rig`` solves the intrinsics together with the rig, starting from the
    camera calibration and tied to it by its uncertainties; with more views (and the rig's
    constraints) it pins the principal point a camera calibration of a ring of board
    corners leaves loose (1.5 px against 0.75 px on the realistic world).  A camera pose
    from the rig's kinematics is only right with the intrinsics it was calibrated with:
    with the camera calibration's cx 2.5 px away the camera turns by ~0.15 deg.  So when
    the manifest's rig carries a record whose ``camera_digest`` is the session camera's
    identity digest, its fx, fy, cx, cy (and the distortion terms it refined) replace the
    setup's, and ``setup.intrinsics_source`` says ``"rig calibration"``; otherwise the
    setup is returned unchanged.
    """
    rec = (manifest.get("rig") or {}).get("calibration") or {}
    intr = rec.get("intrinsics") or {}
    if not isinstance(intr, Mapping) or not all(k in intr for k in _RIG_INTRINSICS):
        return setup
    size = None if setup.signature is None else tuple(reversed(setup.signature.shape))
    session = camera_identity(manifest.get("camera") or {}, size)
    if session is None or rec.get("camera_digest") != identity_digest(session):
        return setup

    def value(name: str) -> float:
        v = intr[name]
        return float(v["value"] if isinstance(v, Mapping) else v)

    fx, fy, cx, cy = (value(k) for k in _RIG_INTRINSICS)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = np.zeros(5) if setup.dist is None else np.asarray(setup.dist, float).copy()
    if dist.size < 5:
        dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    for i, name in enumerate(_RIG_DISTORTION):
        if name in intr:
            dist[i] = value(name)
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
        return setup
    return setup.replace(K=K, dist=dist, intrinsics_source="rig calibration")

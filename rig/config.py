"""Rig configuration: bus, servos, joints and geometry, read from TOML and validated.

Degrees appear only here, at the edge (field names end in ``_deg``); everything the
configuration hands to the rest of the code is in radians via the ``*_rad`` properties.

The default preset (``default_rig.toml``, shipped as package data) is a four-servo rig:
a light arm and a camera arm turning about the vertical axis through the sample centre,
and a sample stage that tilts about a horizontal axis and spins about the sample normal.
"""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import tomli_w
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_serializer,
    model_validator,
)

from gonio.config import read_toml, validate
from gonio.errors import ConfigError
from gonio.rig.calibration_record import CalibrationRecord

#: The joints the ``arms_tilt_spin`` geometry knows.  A servo drives exactly one of them.
JOINT_NAMES: tuple[str, ...] = ("light_azimuth", "camera_azimuth", "stage_tilt", "stage_spin")

#: Baud rates dynamixel-sdk's PortHandler accepts (``setBaudRate`` whitelist).
SDK_BAUD_RATES: tuple[int, ...] = (
    9600,
    19200,
    38400,
    57600,
    115200,
    230400,
    460800,
    500000,
    576000,
    921600,
    1000000,
    1152000,
    2000000,
    2500000,
    3000000,
    3500000,
    4000000,
)


#: How far from horizontal an as-built tilt axis may be, deg.
MAX_TILT_AXIS_PITCH_DEG = 10.0

#: As-built angles and offsets: bounded far beyond any real error, so that a typo (1e300)
#: is refused by name instead of overflowing in the kinematics.
_Deg90 = Annotated[float, Field(ge=-90, le=90)]
_Metre = Annotated[float, Field(ge=-1, le=1)]
#: A direction's component (normalised where used; bounded so its norm cannot overflow)
_Comp = Annotated[float, Field(ge=-1e3, le=1e3)]


class _Strict(BaseModel):
    # No inf/nan anywhere in a rig: a NaN axis or offset passed every range check (all
    # comparisons with NaN are false) and surfaced as a traceback deep in the kinematics,
    # and an infinite radius or timeout is always a typo.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class BusConfig(_Strict):
    """Serial bus settings.

    ``timeout_ms`` overrides dynamixel-sdk's reply timeout (None keeps the SDK formula
    ``10000/baud * bytes + 2 * latency_timer_ms + 2 ms``); ``latency_timer_ms`` is the
    USB adapter's latency the SDK budgets for (16 ms on FTDI; a larger value makes the
    SDK tolerant of a loaded CPU, see dynamixel.md).
    """

    port: str = "/dev/ttyUSB0"
    baud_rate: int = 1_000_000
    timeout_ms: float | None = Field(default=None, gt=0)
    latency_timer_ms: int = Field(default=16, ge=1, le=1000)
    retries: int = Field(default=3, ge=0, le=100)

    @field_validator("baud_rate")
    @classmethod
    def _known_baud(cls, v: int) -> int:
        if v not in SDK_BAUD_RATES:
            raise ValueError(f"baud rate {v} is not one dynamixel-sdk supports: {SDK_BAUD_RATES}")
        return v


class ServoConfig(_Strict):
    """One servo and the joint it drives.

    joint angle (rad) = direction * (servo angle - zero) / gear_ratio, where the servo
    angle is Present Position * 2 pi / 4096.
    """

    id: int = Field(ge=0, le=252)
    model: str = "XM430-W350"
    joint: str
    # upper bounds: far beyond any rig, near enough that the kinematics cannot overflow
    gear_ratio: float = Field(default=1.0, gt=0, le=1000)
    direction: Literal[1, -1] = 1
    zero_deg: float = Field(default=180.0, ge=-1e5, le=1e5)
    min_deg: float = Field(default=-180.0, ge=-1e5, le=1e5)
    max_deg: float = Field(default=180.0, ge=-1e5, le=1e5)
    velocity_deg_s: float = Field(default=60.0, ge=0, le=1e5)
    acceleration_deg_s2: float = Field(default=240.0, ge=0, le=1e7)
    operating_mode: Literal["position", "extended_position"] = "position"
    #: As built: the joint lags the encoder by half this on the side it was approached
    #: from (``gonio.rig.asbuilt``), deg.  0 on a nominal rig; ``gonio calibrate rig``
    #: measures it.
    backlash_deg: float = Field(default=0.0, ge=0, le=10)
    #: As built: the joint bends under gravity by ``a cos(q) + b sin(q)`` (q the joint
    #: angle the encoder gives), ``(a, b)`` in deg.  Only a joint whose axis is not
    #: vertical (the stage tilt) carries a gravity torque that changes with its angle.
    compliance_deg: tuple[
        Annotated[float, Field(ge=-10, le=10)], Annotated[float, Field(ge=-10, le=10)]
    ] = (0.0, 0.0)

    @field_validator("model")
    @classmethod
    def _known_model(cls, v: str) -> str:
        from gonio.rig.control_table import MODELS

        if v not in MODELS:
            raise ValueError(f"unknown servo model {v!r}; known models: {sorted(MODELS)}")
        return v

    @field_validator("joint")
    @classmethod
    def _known_joint(cls, v: str) -> str:
        if v not in JOINT_NAMES:
            raise ValueError(f"unknown joint {v!r}; expected one of {JOINT_NAMES}")
        return v

    @model_validator(mode="after")
    def _limits_ordered(self) -> ServoConfig:
        from gonio.rig import control_table as ct

        # the registers' range, so the servo does not refuse the write at run time
        # ("data limit error") after the config was accepted
        regs = ct.MODELS[self.model].registers
        turn = math.radians(self.gear_ratio)
        for field_name, value, reg, to_reg, unit_deg, unit in (
            ("velocity_deg_s", self.velocity_deg_s, "profile_velocity",
             ct.velocity_register, ct.RPM_PER_VELOCITY_UNIT * 360.0 / 60.0, "deg/s"),
            ("acceleration_deg_s2", self.acceleration_deg_s2, "profile_acceleration",
             ct.acceleration_register, ct.RPM2_PER_ACCELERATION_UNIT * 360.0 / 3600.0,
             "deg/s^2"),
        ):  # fmt: skip
            high = regs[reg].high
            if high is not None and to_reg(value * turn) > high:
                raise ValueError(
                    f"{field_name} = {value:g} is beyond the servo's {reg} register (at "
                    f"most {high * unit_deg / self.gear_ratio:.0f} {unit} of joint at gear ratio "
                    f"{self.gear_ratio:g})"
                )
        if not self.min_deg < self.max_deg:
            raise ValueError(f"min_deg ({self.min_deg}) must be below max_deg ({self.max_deg})")
        if self.operating_mode == "position":
            # Position mode clamps goals to 0..4095 pulses (one turn of the servo horn).
            ends = [self.pulses(math.radians(d)) for d in (self.min_deg, self.max_deg)]
            if min(ends) < 0 or max(ends) > 4095:
                raise ValueError(
                    f"limits [{self.min_deg}, {self.max_deg}] deg need servo positions {ends}, "
                    "outside 0..4095 of position mode; narrow them, move zero_deg or use "
                    "operating_mode = 'extended_position'"
                )
        return self

    def pulses(self, joint_rad: float) -> float:
        """Servo position (pulses, unrounded) for a joint angle (rad)."""
        zero = self.zero_deg * 4096.0 / 360.0
        return zero + self.direction * self.gear_ratio * joint_rad * 4096.0 / (2 * math.pi)

    def joint_rad(self, pulses: float) -> float:
        """Joint angle (rad) for a servo position (pulses)."""
        zero = self.zero_deg * 4096.0 / 360.0
        return self.direction * (pulses - zero) * (2 * math.pi / 4096.0) / self.gear_ratio

    @property
    def limits_rad(self) -> tuple[float, float]:
        """Joint limits (rad)."""
        return math.radians(self.min_deg), math.radians(self.max_deg)


class GeometryConfig(_Strict):
    """Geometry of the rig (kind ``arms_tilt_spin``), world frame: origin at the sample
    centre, +z up.

    Both arms turn about the world z axis; an arm at azimuth ``a`` and elevation ``e``
    holds its device in direction ``(cos e cos a, cos e sin a, sin e)``.  The stage
    orientation (sample -> world) is ``A(tilt) @ B @ Rz(spin)``: ``B`` places the sample
    normal along ``rest_normal`` and the sample +x along ``rest_reference``; ``A`` turns
    about the horizontal ``tilt_axis``.
    """

    kind: Literal["arms_tilt_spin"] = "arms_tilt_spin"
    light_radius_m: float = Field(default=0.50, gt=0, le=10)
    camera_radius_m: float = Field(default=0.40, gt=0, le=10)
    light_elevation_deg: float = Field(default=0.0, gt=-90, lt=90)
    camera_elevation_deg: float = Field(default=0.0, gt=-90, lt=90)
    tilt_axis: tuple[_Comp, _Comp, _Comp] = (0.0, -1.0, 0.0)
    rest_normal: tuple[_Comp, _Comp, _Comp] = (1.0, 0.0, 0.0)
    rest_reference: tuple[_Comp, _Comp, _Comp] = (0.0, 0.0, 1.0)
    min_separation_deg: float = Field(default=10.0, ge=0, lt=180)
    arm_clearance_deg: float = Field(default=8.0, ge=0, lt=180)
    arms_can_cross: bool = False
    max_theta_deg: float = Field(default=85.0, gt=0, le=90)
    camera_body_radius_m: float = Field(default=0.04, ge=0, le=1)
    light_body_radius_m: float = Field(default=0.03, ge=0, le=1)
    # As built (``gonio.rig.asbuilt``; all 0 on a nominal rig, measured by ``gonio
    # calibrate rig``).  The camera's turn on its arm, about its own x, y, z axes:
    camera_mount_deg: tuple[_Deg90, _Deg90, _Deg90] = (0.0, 0.0, 0.0)
    #: The holder plate (sample and board) tilted on the spin plate, about the sample's
    #: x then y axis, deg.
    holder_tilt_deg: tuple[_Deg90, _Deg90] = (0.0, 0.0)
    #: The sample centre in the spin plate's frame (off the spin axis in x, y; above the
    #: rotation centre along the normal in z: holder and sample thickness), m.
    holder_offset_m: tuple[_Metre, _Metre, _Metre] = (0.0, 0.0, 0.0)
    #: The stage's rotation centre from the arms' axis, world frame, m.
    stage_offset_m: tuple[_Metre, _Metre, _Metre] = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _axes(self) -> GeometryConfig:
        def norm(v):
            return math.sqrt(sum(c * c for c in v))

        for name in ("tilt_axis", "rest_normal", "rest_reference"):
            if norm(getattr(self, name)) < 1e-9:
                raise ValueError(f"{name} must be a non-zero vector")
        n, r, k = self.rest_normal, self.rest_reference, self.tilt_axis
        if abs(sum(a * b for a, b in zip(n, r, strict=True))) > 1e-6 * norm(n) * norm(r):
            raise ValueError("rest_reference must be perpendicular to rest_normal")
        if abs(k[2]) > math.sin(math.radians(MAX_TILT_AXIS_PITCH_DEG)) * norm(k):
            raise ValueError(
                f"tilt_axis must be within {MAX_TILT_AXIS_PITCH_DEG:g} deg of horizontal "
                "(a calibrated rig's axis is a little off it; a nominal one has z = 0)"
            )
        return self


class MotionConfig(_Strict):
    """How moves are verified.  Poses are in degrees, by joint name."""

    position_tolerance_pulses: int = Field(default=1, ge=0, le=100)
    move_timeout_s: float = Field(default=20.0, gt=0, le=86400)
    poll_interval_s: float = Field(default=0.01, gt=0, le=1.0)
    home_deg: dict[str, float] = {
        "light_azimuth": -45.0,
        "camera_azimuth": 0.0,
        "stage_tilt": 0.0,
        "stage_spin": 0.0,
    }
    park_deg: dict[str, float] | None = None

    @field_validator("home_deg", "park_deg")
    @classmethod
    def _joints(cls, v):
        if v is not None:
            bad = sorted(set(v) - set(JOINT_NAMES))
            if bad:
                raise ValueError(f"unknown joint(s) {bad}; expected names from {JOINT_NAMES}")
        return v


class RigConfig(_Strict):
    """A whole rig: bus, servos (one per joint), geometry, motion settings."""

    name: str = "rig"
    bus: BusConfig = BusConfig()
    servos: tuple[ServoConfig, ...]
    geometry: GeometryConfig = GeometryConfig()
    motion: MotionConfig = MotionConfig()
    #: Set on a calibrated rig (``gonio calibrate rig``): provenance, uncertainties.
    calibration: CalibrationRecord | None = None

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        # A nominal rig dumps (and digests) as it did before the field existed.
        data = handler(self)
        if self.calibration is None and isinstance(data, dict):
            data.pop("calibration", None)
        return data

    @model_validator(mode="after")
    def _servos_consistent(self) -> RigConfig:
        ids = [s.id for s in self.servos]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicate servo ID(s) {dup}: every servo needs its own ID")
        joints = [s.joint for s in self.servos]
        dupj = sorted({j for j in joints if joints.count(j) > 1})
        if dupj:
            raise ValueError(f"joint(s) {dupj} driven by more than one servo")
        missing = [j for j in JOINT_NAMES if j not in joints]
        if missing:
            raise ValueError(
                f"no servo drives joint(s) {missing}; "
                f"{self.geometry.kind} needs all of {JOINT_NAMES}"
            )
        for pose_name in ("home_deg", "park_deg"):
            pose = getattr(self.motion, pose_name)
            lacking = [j for j in JOINT_NAMES if pose is not None and j not in pose]
            if lacking:
                raise ValueError(f"motion.{pose_name} lacks joint(s) {lacking}")
            for s in self.servos if pose else ():
                v = pose.get(s.joint)
                if v is not None and not s.min_deg <= v <= s.max_deg:
                    raise ValueError(
                        f"motion.{pose_name}.{s.joint} = {v} deg outside the servo limits "
                        f"[{s.min_deg}, {s.max_deg}]"
                    )
        return self

    def servo_for(self, joint: str) -> ServoConfig:
        """The servo that drives ``joint``."""
        for s in self.servos:
            if s.joint == joint:
                return s
        raise ConfigError(f"no servo drives joint {joint!r}")

    @property
    def home_rad(self) -> dict[str, float]:
        """Home pose, joint name -> rad."""
        return {j: math.radians(v) for j, v in self.motion.home_deg.items()}

    @property
    def park_rad(self) -> dict[str, float]:
        """Park pose (defaults to home), joint name -> rad."""
        pose = self.motion.park_deg if self.motion.park_deg is not None else self.motion.home_deg
        return {j: math.radians(v) for j, v in pose.items()}

    @property
    def park_pulses(self) -> dict[int, int]:
        """Park pose as each servo's position, servo ID -> pulses (joints left out: 0 rad)."""
        park = self.park_rad
        return {s.id: int(round(s.pulses(park.get(s.joint, 0.0)))) for s in self.servos}


def rig_config_from_dict(data: dict, source: str = "<dict>") -> RigConfig:
    """Validate a parsed TOML document into a :class:`RigConfig`.

    Raises
    ------
    ConfigError
        Naming ``source`` and each offending field.
    """
    return validate(RigConfig, data, source)


def load_rig_config(path: str | Path) -> RigConfig:
    """Read and validate a rig configuration TOML file.

    Raises
    ------
    ConfigError
        If the file is missing, is not TOML, or a field is invalid (the message names the
        file and the field).
    """
    return rig_config_from_dict(read_toml(path, "rig configuration"), str(path))


def default_rig_document() -> str:
    """The default four-servo preset as TOML text (``gonio/rig/default_rig.toml``)."""
    return resources.files("gonio.rig").joinpath("default_rig.toml").read_text(encoding="utf-8")


def virtual_rig_document() -> str:
    """The default preset with its bus on the simulator's virtual port, as TOML text.

    Written with tomli-w from the parsed preset, so it holds the same values
    (``bus.port = "virtual"`` aside) whatever the preset file's layout and comments.
    """
    doc = tomllib.loads(default_rig_document())
    doc["bus"]["port"] = "virtual"
    return _VIRTUAL_HEADER + tomli_w.dumps(doc)


_VIRTUAL_HEADER = (
    "# The default four-servo preset (gonio/rig/default_rig.toml) on the simulator:\n"
    '# port = "virtual" runs the servos on the simulator\'s Dynamixel bus (a pseudo-terminal).\n'
)


def default_rig_config() -> RigConfig:
    """The default four-servo preset (``gonio/rig/default_rig.toml``)."""
    return rig_config_from_dict(tomllib.loads(default_rig_document()), "gonio.rig:default_rig.toml")

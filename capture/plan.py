"""Measurement plans: which directions to measure, which to skip and why, how to expose.

A plan is a TOML file validated with pydantic (see ``examples/plan.toml``).  It expands to
a list of poses (``wi``, ``wo`` in the sample frame) by

1. a grid, either in incident/outgoing spherical angles (``theta_i``, ``phi_i``,
   ``theta_o``, ``phi_o``) or in Rusinkiewicz half/difference angles;
2. reductions that drop poses a symmetry makes redundant: *isotropic* (only the relative
   azimuth ``phi_o - phi_i`` and its mirror matter) and *reciprocity* (``f(wi, wo) =
   f(wo, wi)``);
3. exclusions, each with a reason: below the horizon, grazing limits, the camera shadowing
   the light's path (too small a separation between ``wi`` and ``wo``), and whatever the
   rig's kinematics refuses (unreachable joint angles, arm collisions, arm shadowing).

Instead of a grid, a plan may list joint poses (``[[joint_poses]]``: the four joint
angles in degrees and the ``target``, ``"sample"`` or ``"mirror"``): a calibration plan,
whose poses and their order (which decides the side each joint approaches from) are
given, not derived.  Its poses are checked against the rig by the schedule
(:func:`gonio.capture.schedule.build_schedule`), which knows the kinematics.

Degrees appear only in the file (``*_deg`` fields); :class:`Pose` holds unit vectors.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from gonio.config import read_toml, validate
from gonio.errors import PoseRefused
from gonio.radiometry import (
    direction_to_spherical,
    directions_from_half_diff,
    spherical_to_direction,
)

__all__ = [
    "AdaptivePlan",
    "AdaptiveWeights",
    "BracketPolicy",
    "DarkFrames",
    "Exclusions",
    "FlatFrames",
    "Grid",
    "JointPose",
    "Plan",
    "Pose",
    "ExcludedPose",
    "ExpandedPlan",
    "Limits",
    "MAX_EXPOSURE_S",
    "MAX_SETTLE_S",
    "PlanEstimate",
    "estimate_plan",
    "ReferenceShots",
    "Reductions",
    "check_limits",
    "expand_plan",
    "load_plan",
    "plan_from_dict",
    "plan_digest",
]

SCHEMA_VERSION = 1

#: Longest exposure accepted anywhere in a plan, s.  Cameras offer at most 30 s timed
#: (longer only in bulb mode); an hour is far beyond any BRDF frame (the sensor's dark
#: current fills a pixel's well long before) and keeps every derived figure (duration
#: estimates, the simulated sensor's Poisson mean) in range.  Beyond it a value is a
#: typo or a unit mistake.
MAX_EXPOSURE_S = 3600.0

#: Longest wait after a move before shooting, s.  A servo arm's vibration dies out within
#: a second or two; a minute covers a heavy arm on a soft mount with a wide margin.  More
#: would multiply a session's duration (10 000 poses x 60 s = a week) for nothing.
MAX_SETTLE_S = 60.0

Seconds = Annotated[float, Field(gt=0, le=MAX_EXPOSURE_S)]
#: A reflectance in (0, 1]: the reduction divides by it (0 is no reference at all) and a
#: passive target cannot reflect more than it receives.  The same bounds as
#: ``reduction.toml``'s ``[reference] reflectance``, which the session copies it into: a
#: plan refused only at the reduction would have cost a whole session first.
Reflectance = Annotated[float, Field(gt=0, le=1)]


class _Strict(BaseModel):
    # No inf/nan anywhere in a plan: an infinite time, angle or limit is always a mistake.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Range(_Strict):
    """An inclusive range ``start, start + step, ..., <= stop`` (degrees)."""

    start: float
    stop: float
    step: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> Range:
        if self.stop < self.start:
            raise ValueError(f"stop ({self.stop}) must not be below start ({self.start})")
        if (self.stop - self.start) / self.step > 100_000:
            raise ValueError("range has more than 100000 values; check step")
        return self

    def values(self) -> list[float]:
        n = int(math.floor((self.stop - self.start) / self.step + 1e-9)) + 1
        return [self.start + k * self.step for k in range(n)]


AngleList = list[float] | Range


def _angles(v: AngleList | None) -> list[float]:
    if v is None:
        return [0.0]
    return v.values() if isinstance(v, Range) else list(v)


class Grid(_Strict):
    """The pose grid, in degrees.

    ``kind = "spherical"`` uses ``theta_i_deg``, ``phi_i_deg``, ``theta_o_deg``,
    ``phi_o_deg``; ``kind = "half_difference"`` uses ``theta_h_deg``, ``phi_h_deg``,
    ``theta_d_deg``, ``phi_d_deg``.  Each is a list of values or ``{start, stop, step}``
    (stop included); an azimuth left out is 0.
    """

    kind: Literal["spherical", "half_difference"] = "spherical"
    theta_i_deg: AngleList | None = None
    phi_i_deg: AngleList | None = None
    theta_o_deg: AngleList | None = None
    phi_o_deg: AngleList | None = None
    theta_h_deg: AngleList | None = None
    phi_h_deg: AngleList | None = None
    theta_d_deg: AngleList | None = None
    phi_d_deg: AngleList | None = None

    @model_validator(mode="after")
    def _fields_match_kind(self) -> Grid:
        sph = ("theta_i_deg", "phi_i_deg", "theta_o_deg", "phi_o_deg")
        hd = ("theta_h_deg", "phi_h_deg", "theta_d_deg", "phi_d_deg")
        use, other = (sph, hd) if self.kind == "spherical" else (hd, sph)
        wrong = [n for n in other if getattr(self, n) is not None]
        if wrong:
            raise ValueError(f"fields {wrong} do not belong to a grid of kind {self.kind!r}")
        for name in (use[0], use[2]):
            if getattr(self, name) is None:
                raise ValueError(f"a {self.kind} grid needs {name}")
        for name in use:
            v = _angles(getattr(self, name))
            if not v:
                raise ValueError(f"{name} is empty")
            if name.startswith("theta") and not all(-1e-9 <= t <= 90 for t in v):
                raise ValueError(f"{name} values must lie in [0, 90] degrees, got {v}")
        return self

    def axes(self) -> list[list[float]]:
        names = (
            ("theta_i_deg", "phi_i_deg", "theta_o_deg", "phi_o_deg")
            if self.kind == "spherical"
            else ("theta_h_deg", "phi_h_deg", "theta_d_deg", "phi_d_deg")
        )
        return [_angles(getattr(self, n)) for n in names]


class JointPose(_Strict):
    """One pose of a joint-pose plan: joint angles (deg) and what stands on the stage.

    ``target = "mirror"`` puts the flat calibration mirror in the sample's place (a rig
    calibration's spot views); ``label`` names the pose in messages and the journal.
    """

    light_azimuth_deg: float
    camera_azimuth_deg: float
    stage_tilt_deg: float
    stage_spin_deg: float
    target: Literal["sample", "mirror"] = "sample"
    label: str | None = None

    def joints_rad(self) -> dict[str, float]:
        """Joint name -> angle (rad)."""
        return {
            "light_azimuth": math.radians(self.light_azimuth_deg),
            "camera_azimuth": math.radians(self.camera_azimuth_deg),
            "stage_tilt": math.radians(self.stage_tilt_deg),
            "stage_spin": math.radians(self.stage_spin_deg),
        }


class Reductions(_Strict):
    """Symmetries of the material that make some poses redundant."""

    isotropic: bool = False
    reciprocity: bool = False


class Exclusions(_Strict):
    """Plan-level limits (the rig's own limits apply on top, through its kinematics).

    ``grazing_limit_deg``: largest theta allowed for either direction.
    ``min_separation_deg``: smallest angle between ``wi`` and ``wo``; below it the
    camera sits in the light's path (and shadows the sample).
    """

    grazing_limit_deg: float = Field(default=85.0, gt=0, le=90)
    min_separation_deg: float = Field(default=0.0, ge=0, lt=180)
    check_rig: bool = True


class BracketPolicy(_Strict):
    """How each pose is exposed.

    ``policy = "adaptive"``: start from a predicted exposure (``exposure_time_s`` for the
    first pose, then the last good exposure of the previous pose scaled by the change of
    ``cos(theta_i)``), and add frames ``step_ev`` stops shorter or longer only until the
    region of interest is neither saturated nor under the noise floor, at most
    ``max_frames``.  ``policy = "fixed"``: shoot ``exposures_s`` at every pose.
    ``iso``/``f_number = "camera"`` leaves the camera's own setting alone.
    """

    def camera_iso(self) -> float | None:
        return None if self.iso == "camera" else float(self.iso)

    def camera_f_number(self) -> float | None:
        return None if self.f_number == "camera" else float(self.f_number)

    policy: Literal["adaptive", "fixed"] = "adaptive"
    exposure_time_s: float = Field(default=0.01, gt=0, le=MAX_EXPOSURE_S)
    exposures_s: tuple[Seconds, ...] = ()
    iso: Annotated[float, Field(gt=0)] | Literal["camera"] = 100.0
    f_number: Annotated[float, Field(gt=0)] | Literal["camera"] = 8.0
    step_ev: float = Field(default=2.0, gt=0, le=6)
    max_frames: int = Field(default=5, ge=1, le=20)
    min_exposure_s: float = Field(default=1e-5, gt=0, le=MAX_EXPOSURE_S)
    max_exposure_s: float = Field(default=30.0, gt=0, le=MAX_EXPOSURE_S)
    saturated_fraction: float = Field(default=1e-3, ge=0, lt=1)
    noise_floor_snr: float = Field(default=10.0, gt=0)
    roi: tuple[float, float, float, float] | None = None
    shot_overhead_s: float = Field(default=0.5, ge=0, le=MAX_EXPOSURE_S)

    @model_validator(mode="after")
    def _consistent(self) -> BracketPolicy:
        if self.policy == "fixed" and not self.exposures_s:
            raise ValueError("policy 'fixed' needs exposures_s (a list of exposure times)")
        if any(t <= 0 for t in self.exposures_s):
            raise ValueError(f"exposures_s must be positive, got {list(self.exposures_s)}")
        if self.min_exposure_s >= self.max_exposure_s:
            raise ValueError("min_exposure_s must be below max_exposure_s")
        if self.roi is not None:
            x0, y0, x1, y1 = self.roi
            if not (0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1):
                raise ValueError(
                    f"roi = {list(self.roi)} must be [x0, y0, x1, y1] fractions in [0, 1]"
                )
        return self


class DarkFrames(_Strict):
    """Dark frames (light off): ``count`` frames per distinct exposure time, shot at
    ``when`` (``"end"`` or ``"start"`` of the session; ``count = 0`` for none)."""

    count: int = Field(default=0, ge=0, le=100)
    when: Literal["start", "end"] = "end"
    exposure_times_s: tuple[Seconds, ...] = ()


class FlatFrames(_Strict):
    """Flat fields: ``count`` frames of a uniform diffuse panel over the lens (the target
    changer's ``"flat"``), at ``exposure_s`` and ``iso`` (None: the bracket's), shot at
    ``when``; ``count = 0`` for none.  Darks are also shot at this exposure and ISO, so
    the flats are dark-subtracted.  The reduction makes the PRNU gain map and the
    hot/dead pixel mask from them."""

    count: int = Field(default=0, ge=0, le=100)
    exposure_s: Seconds = 0.01
    iso: float | None = Field(default=None, gt=0)
    when: Literal["start", "end"] = "start"


class ReferencePose(_Strict):
    theta_i_deg: float = Field(ge=0, le=90)
    phi_i_deg: float = 0.0
    theta_o_deg: float = Field(ge=0, le=90)
    phi_o_deg: float = 0.0


class ReferenceShots(_Strict):
    """Shots of the reference target (e.g. a diffuse reflectance standard) at given poses,
    exposed with the same bracket policy; ``reflectance`` is the target's known value."""

    poses: tuple[ReferencePose, ...] = ()
    reflectance: Reflectance | tuple[Reflectance, Reflectance, Reflectance] = 0.99
    when: Literal["start", "end"] = "start"
    #: Shoot the reference group again after every this many sample poses (and at
    #: ``when``), so the reduction can follow the light's drift; 0: only at ``when``.
    every_poses: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _repeats_need_poses(self) -> ReferenceShots:
        if self.every_poses and not self.poses:
            raise ValueError(
                f"every_poses = {self.every_poses} repeats the reference group, but the "
                "plan names no reference poses ([reference] poses = [...])"
            )
        return self


class SimulationSettings(_Strict):
    """Used only with ``--camera simulated``: the scene the simulator renders."""

    scene: str | None = None
    #: The as-built world: ``"perfect"``, ``"realistic"``, a world TOML (relative to
    #: the plan) or an inline table (``gonio.simulator.world``).
    world: str | dict[str, Any] | None = None
    width: int | None = Field(default=None, ge=8)
    height: int | None = Field(default=None, ge=8)
    options: dict[str, Any] = {}

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> Any:
        data = handler(self)
        # No world: dumped as before the field existed (plan digests, sessions resume).
        if self.world is None and isinstance(data, dict):
            data.pop("world", None)
        return data


#: The ``gonio fit --model auto`` candidates (``gonio.fitting.select.DEFAULT_CANDIDATES``;
#: capture may not import fitting, so the tuple is repeated here and a test holds the two
#: equal).
AUTO_CANDIDATES = ("lambert", "oren-nayar", "lambert+ggx", "lambert+beckmann")


def _model_params(spec: str) -> tuple[str, ...]:
    """Parameter names of a model spec ``name[key=value,...]`` (``gonio fit --candidates``);
    a ValueError naming the spec when gonio.brdf does not know it."""
    from gonio.brdf import get_model
    from gonio.errors import GonioError

    s = spec.strip()
    name, opts = s, {}
    if "[" in s or "]" in s:
        if not (s.endswith("]") and s.count("[") == 1 and s.count("]") == 1 and s.index("[") > 0):
            raise ValueError(
                f"model spec {spec!r}: expected 'name' or 'name[key=value,...]', e.g. "
                "'lambert+ggx[fresnel=schlick]'"
            )
        name, body = s[:-1].split("[", 1)
        for item in filter(None, (x.strip() for x in body.split(","))):
            key, eq, value = item.partition("=")
            if not eq or not key.strip() or not value.strip():
                raise ValueError(f"model spec {spec!r}: option {item!r} is not written key=value")
            opts[key.strip()] = value.strip()
    try:
        return tuple(get_model(name.strip(), **opts).param_names)
    except GonioError as exc:  # UnknownNameError is a KeyError: pydantic wants ValueError
        raise ValueError(f"unknown candidate model {spec!r}: {str(exc).strip(chr(34))}") from None


class AdaptiveWeights(_Strict):
    """Weights of the three terms of the expected information of a candidate pose
    (``gonio.fitting.design.score_candidates``)."""

    d_optimal: float = Field(default=1.0, ge=0)
    discrimination: float = Field(default=1.0, ge=0)
    model_free: float = Field(default=1.0, ge=0)


class AdaptivePlan(_Strict):
    """``[adaptive]``: measure a seed design, then batches chosen by expected information.

    The candidate pool is every pose with ``wi`` and ``wo`` on rings ``pool_step_deg``
    apart up to ``max_theta_deg`` (the isotropic/reciprocity reductions applied), less the
    plan's exclusions and what the rig refuses.  ``seed_poses`` of them are always
    measured (``retro_poses`` nearest to retro-reflection, ``in_plane_poses`` in one
    incidence plane, the rest space-filling, from the plan's ``seed``); then rounds of
    ``batch_poses`` until every parameter named in ``target_rel_sigma`` (relative 1-sigma)
    and ``target_brdf_rel_sigma`` (median predicted relative sigma of f) is reached, or
    ``max_poses`` sample poses (seed included), or the estimated session time reaches
    ``max_time_s`` (travel + exposures + download, as ``gonio capture plan`` estimates
    it), or the pool is empty.
    """

    seed_poses: int = Field(default=24, ge=1, le=10_000)
    retro_poses: int = Field(default=4, ge=0)
    in_plane_poses: int = Field(default=8, ge=0)
    batch_poses: int = Field(default=8, ge=1, le=1000)
    candidates: tuple[str, ...] = AUTO_CANDIDATES
    target_rel_sigma: dict[str, Annotated[float, Field(gt=0, lt=1)]] = {}
    target_brdf_rel_sigma: float | None = Field(default=None, gt=0, lt=1)
    max_poses: int = Field(default=120, ge=1)
    max_time_s: float | None = Field(default=None, gt=0)
    pool_step_deg: float = Field(default=5.0, ge=1, le=45)
    max_theta_deg: float = Field(default=80.0, gt=0, le=89)
    #: Smallest angle between two poses of one batch (6-D distance of (wi, wo), deg);
    #: None: ``pool_step_deg``.
    batch_separation_deg: float | None = Field(default=None, ge=0, le=180)
    weights: AdaptiveWeights = AdaptiveWeights()

    @field_validator("candidates")
    @classmethod
    def _known_models(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if not v:
            raise ValueError("at least one candidate model (e.g. ['lambert', 'lambert+ggx'])")
        for spec in v:
            _model_params(spec)
        return v

    @model_validator(mode="after")
    def _consistent(self) -> AdaptivePlan:
        if self.retro_poses + self.in_plane_poses > self.seed_poses:
            raise ValueError(
                f"retro_poses ({self.retro_poses}) + in_plane_poses ({self.in_plane_poses}) "
                f"exceed seed_poses ({self.seed_poses}): the seed design includes both"
            )
        if self.max_poses < self.seed_poses:
            raise ValueError(
                f"max_poses = {self.max_poses} is smaller than the seed design (seed_poses = "
                f"{self.seed_poses}), which is always measured: raise max_poses or lower "
                "seed_poses"
            )
        params = {p for spec in self.candidates for p in _model_params(spec)}
        unknown = sorted(set(self.target_rel_sigma) - params)
        if unknown:
            raise ValueError(
                f"target_rel_sigma names {unknown}, which no candidate model "
                f"({', '.join(self.candidates)}) has; their parameters: {', '.join(sorted(params))}"
            )
        return self

    @property
    def separation_deg(self) -> float:
        """``batch_separation_deg``, or ``pool_step_deg`` when not given."""
        sep = self.batch_separation_deg
        return self.pool_step_deg if sep is None else sep


def _physical_memory() -> float:
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 16e9


class Limits(_Strict):
    """What a plan may ask for; checked from the grid's sizes before it is expanded.

    Defaults are sized for a lab: ``max_poses`` 50 000 (at a few seconds per pose for
    move, settle and bracket, two to four days of unattended capture), ``max_frames``
    500 000, ``max_bytes`` 2 TB of RAW files, ``max_memory_bytes`` half of this
    machine's physical memory (expansion and pose ordering).  ``frame_bytes`` is the
    size of one RAW file: by default ``simulation.width x height x 2`` bytes plus a
    64 KiB header when both are set, else 30 MB (a 24 MP RAW).  Raise a limit in the
    plan's ``[limits]`` table when a bigger plan is meant.
    """

    max_poses: int = Field(default=50_000, ge=1)
    max_frames: int = Field(default=500_000, ge=1)
    max_bytes: float = Field(default=2e12, gt=0)
    max_memory_bytes: float | None = Field(default=None, gt=0)
    frame_bytes: int | None = Field(default=None, ge=1)

    def memory_limit(self) -> float:
        """``max_memory_bytes``, or half of the physical memory (bytes)."""
        return self.max_memory_bytes or 0.5 * _physical_memory()


class Plan(_Strict):
    """A whole measurement plan (the TOML file)."""

    name: str = "plan"
    description: str = ""
    seed: int = Field(default=0, ge=0)
    settle_s: float = Field(default=0.0, ge=0, le=MAX_SETTLE_S)
    limits: Limits = Limits()
    # Where the plan came from (its file), for messages; not part of the plan's content.
    _source: str = PrivateAttr(default="plan")
    # joint_poses and adaptive before grid: grid's validator sees them (and names 'grid'
    # in errors).
    joint_poses: tuple[JointPose, ...] = ()
    adaptive: AdaptivePlan | None = None
    grid: Grid | None = Field(default=None, validate_default=True)
    reductions: Reductions = Reductions()
    exclusions: Exclusions = Exclusions()
    bracket: BracketPolicy = BracketPolicy()
    darks: DarkFrames = DarkFrames()
    flats: FlatFrames = FlatFrames()
    reference: ReferenceShots = ReferenceShots()
    simulation: SimulationSettings = SimulationSettings()

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("name must not be empty")
        return v

    @field_validator("grid")
    @classmethod
    def _grid_or_joint_poses(cls, v: Grid | None, info: ValidationInfo) -> Grid | None:
        if "joint_poses" not in info.data:  # joint_poses invalid: that error is enough
            return v
        n = len(info.data["joint_poses"])
        if info.data.get("adaptive") is not None:
            if v is not None or n:
                has = "a [grid]" if v is not None else f"{n} [[joint_poses]]"
                raise ValueError(
                    f"an [adaptive] plan chooses its own poses: it has no [grid] or "
                    f"[[joint_poses]] (this one has [adaptive] and {has}); remove one of them"
                )
            return v
        if "adaptive" not in info.data:  # adaptive invalid: that error is enough
            return v
        if v is None and not n:
            raise ValueError(
                "required: a [grid] of directions, a list of [[joint_poses]] or an "
                "[adaptive] table (the plan has none)"
            )
        if v is not None and n:
            raise ValueError(
                f"a plan has either a [grid] or [[joint_poses]], not both (this one has a "
                f"grid and {n} joint poses)"
            )
        return v

    @model_validator(mode="after")
    def _adaptive_needs_reference(self) -> Plan:
        if self.adaptive is None:
            return self
        if not self.reference.poses:
            raise ValueError(
                "[adaptive] reduces each batch as it is captured, which needs the light "
                "calibrated from the reference target at the start: give [reference] poses "
                "(e.g. poses = [{ theta_i_deg = 0, theta_o_deg = 45, phi_o_deg = 180 }])"
            )
        if self.reference.when != "start":
            raise ValueError(
                "[adaptive] needs the reference group at the start ([reference] when = "
                f"'start', not {self.reference.when!r}): the rounds are reduced with it"
            )
        if self.reference.every_poses:
            raise ValueError(
                f"[reference] every_poses = {self.reference.every_poses} is not supported "
                "with [adaptive] yet (the reference group is shot once, at the start)"
            )
        return self

    @property
    def is_adaptive(self) -> bool:
        """Whether the plan chooses its poses as it goes (``[adaptive]``)."""
        return self.adaptive is not None

    @property
    def is_joint_pose_plan(self) -> bool:
        """Whether the plan lists joint poses (a calibration plan) instead of a grid."""
        return bool(self.joint_poses)

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        # Default limits, and the side (grid or joint poses) a plan does not use, are left
        # out of the dump, so a plan's digest and its manifest copy stay what they were
        # before these fields existed (sessions resume unchanged).
        data = handler(self)
        if isinstance(data, dict):
            if self.limits == Limits():
                data.pop("limits", None)
            if not self.joint_poses:
                data.pop("joint_poses", None)
            if self.grid is None:
                data.pop("grid", None)
            if self.adaptive is None:
                data.pop("adaptive", None)
            # The same for the flats and the repeated references (issue 16).
            if self.flats == FlatFrames():
                data.pop("flats", None)
            if not self.reference.every_poses and isinstance(data.get("reference"), dict):
                data["reference"].pop("every_poses", None)
        return data

    @property
    def flats_iso(self) -> float | None:
        """The flats' ISO: their own, else the bracket's (None: the camera's own)."""
        return self.flats.iso if self.flats.iso is not None else self.bracket.camera_iso()

    def reference_repeats(self, n_sample: int) -> int:
        """How many times the reference group is shot for ``n_sample`` sample poses: at
        ``when``, and after every ``every_poses``-th sample pose (the group at the end is
        not shot twice)."""
        if not self.reference.poses:
            return 0
        n = self.reference.every_poses
        if not n or n_sample <= 0:
            return 1
        if self.reference.when == "start":
            return 1 + n_sample // n
        return n_sample // n + (1 if n_sample % n else 0)


def plan_from_dict(data: dict, source: str = "<plan>") -> Plan:
    """Validate a parsed plan document.

    Raises
    ------
    ConfigError
        Naming ``source`` and each offending field, e.g. ``field 'bracket.iso'``.
    """
    plan = validate(Plan, data, source)
    plan._source = source
    return plan


def load_plan(path: str | Path, *, adaptive: bool = False) -> Plan:
    """Read and validate a plan TOML file (see ``examples/plan.toml``).

    ``adaptive``: ``gonio capture run --adaptive``: add the default ``[adaptive]`` table
    to a plan that names no poses (one with its own ``[adaptive]`` keeps it).

    Raises
    ------
    ConfigError
        If the file is missing, is not TOML, or a field is invalid; with ``adaptive``,
        a plan that has a ``[grid]`` or ``[[joint_poses]]``.
    """
    data = read_toml(path, "plan")
    if adaptive and "adaptive" not in data:
        from gonio.errors import ConfigError

        has = [k for k in ("grid", "joint_poses") if k in data]
        if has:
            raise ConfigError(
                f"{path}: --adaptive chooses the poses, but the plan has [{has[0]}]; remove "
                "it, or run without --adaptive"
            )
        data["adaptive"] = {}
    return plan_from_dict(data, str(path))


def plan_digest(obj: BaseModel | dict) -> str:
    """sha256 of a model's canonical JSON: how a session recognises its plan and rig."""
    data = obj.model_dump(mode="json") if isinstance(obj, BaseModel) else obj
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


# --------------------------------------------------------------------------------------
# Expansion


@dataclass(frozen=True)
class Pose:
    """One measurement pose in the sample frame.

    ``wi``/``wo`` are unit vectors (tuples, JSON friendly); ``kind`` is ``"sample"``,
    ``"reference"`` or ``"mirror"``; ``joints`` the planned joint angles (rad) when the
    rig was consulted (given, for a joint pose); ``label`` a joint pose's label.
    """

    wi: tuple[float, float, float]
    wo: tuple[float, float, float]
    kind: str = "sample"
    joints: dict[str, float] | None = None
    label: str | None = None
    #: An adaptive plan's pose: its id in the candidate pool.
    pool_id: int | None = None

    def angles_deg(self) -> dict[str, float]:
        ti, pi = direction_to_spherical(np.array(self.wi))
        to, po = direction_to_spherical(np.array(self.wo))
        return {
            "theta_i_deg": round(math.degrees(float(ti)), 6),
            "phi_i_deg": round(math.degrees(float(pi)), 6),
            "theta_o_deg": round(math.degrees(float(to)), 6),
            "phi_o_deg": round(math.degrees(float(po)), 6),
        }

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "wi": list(self.wi), "wo": list(self.wo)}
        d.update(self.angles_deg())
        if self.joints is not None:
            d["joints"] = dict(self.joints)
        if self.label is not None:
            d["label"] = self.label
        if self.pool_id is not None:
            d["pool_id"] = self.pool_id
        return d


@dataclass(frozen=True)
class ExcludedPose:
    """A grid pose left out, with the reason (shown by ``gonio capture plan``).

    ``code`` is machine-readable: ``"plan"`` for the plan's own exclusions (grazing
    limit, horizon, the plan's shadowing rule), else the rig's
    :class:`~gonio.errors.RefusalReason` value.
    """

    pose: Pose
    reason: str
    code: str = "plan"


@dataclass
class ExpandedPlan:
    """The poses a plan yields: to measure, excluded (with reasons), and how many the
    symmetry reductions removed."""

    poses: list[Pose]
    excluded: list[ExcludedPose]
    n_grid: int
    n_reduced: int
    notes: list[str] = field(default_factory=list)
    #: An adaptive plan's candidate pool (:class:`gonio.capture.adaptive_pool.CandidatePool`).
    pool: Any = None


def _grid_directions(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    a, b, c, d = (np.radians(np.asarray(v, dtype=np.float64)) for v in grid.axes())
    A, B, C, D = (x.ravel() for x in np.meshgrid(a, b, c, d, indexing="ij"))
    if grid.kind == "spherical":
        return spherical_to_direction(A, B), spherical_to_direction(C, D)
    wi, wo = directions_from_half_diff(A, B, C, D)
    return wi, wo


def _as_tuple(v: np.ndarray) -> tuple[float, float, float]:
    # Snap float noise (cos 90 deg = 6e-17) so keys and JSON are stable across platforms.
    r = np.round(v, 12) + 0.0
    return (float(r[0]), float(r[1]), float(r[2]))


def _symmetry_key(wi: np.ndarray, wo: np.ndarray, red: Reductions) -> tuple:
    ti, pi = direction_to_spherical(wi)
    to, po = direction_to_spherical(wo)
    q = 1e-6  # radians: poses closer than this are the same pose
    if red.isotropic:
        dphi = abs(math.remainder(float(po - pi), 2 * math.pi))
        if ti < q or to < q:
            dphi = 0.0  # azimuth of the normal direction is meaningless
        a, b = round(float(ti) / q), round(float(to) / q)
        if red.reciprocity and b < a:
            a, b = b, a
        return ("iso", a, b, round(dphi / q))
    ki = (round(float(ti) / q), 0 if ti < q else round(float(pi % (2 * math.pi)) / q))
    ko = (round(float(to) / q), 0 if to < q else round(float(po % (2 * math.pi)) / q))
    if red.reciprocity and ko < ki:
        ki, ko = ko, ki
    return ("aniso", ki, ko)


def _canonical_isotropic(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotate a pose about the normal so that ``phi_i = 0`` and ``phi_o`` lies in [0, pi]."""
    ti, pi = direction_to_spherical(wi)
    to, po = direction_to_spherical(wo)
    dphi = abs(math.remainder(float(po - pi), 2 * math.pi))
    return spherical_to_direction(ti, 0.0), spherical_to_direction(to, dphi)


def _exclusion_reason(wi: np.ndarray, wo: np.ndarray, ex: Exclusions) -> str | None:
    if wi[2] <= 0 or wo[2] <= 0:
        return "below the horizon (half/difference angles outside the hemisphere)"
    ti = math.degrees(math.acos(min(1.0, float(wi[2]))))
    to = math.degrees(math.acos(min(1.0, float(wo[2]))))
    if ti > ex.grazing_limit_deg + 1e-9 or to > ex.grazing_limit_deg + 1e-9:
        return (
            f"grazing: theta_i = {ti:.1f} deg, theta_o = {to:.1f} deg, "
            f"limit {ex.grazing_limit_deg:g} deg (exclusions.grazing_limit_deg)"
        )
    sep = math.degrees(math.acos(float(np.clip(np.dot(wi, wo), -1.0, 1.0))))
    if sep < ex.min_separation_deg - 1e-9:
        return (
            f"camera shadows the light's path: wi-wo separation {sep:.1f} deg < "
            f"{ex.min_separation_deg:g} deg (exclusions.min_separation_deg)"
        )
    return None


#: ``rig_check(wi, wo)``: why the rig cannot reach a pose (a ``PoseRefused``, or a
#: sentence), or None.
RigCheck = Callable[[np.ndarray, np.ndarray], "PoseRefused | str | None"]


def _excluded(pose: Pose, refusal: PoseRefused | str) -> ExcludedPose:
    if isinstance(refusal, PoseRefused):
        return ExcludedPose(pose, str(refusal), refusal.reason.value)
    return ExcludedPose(pose, refusal, "rig")


#: Progress of a long expansion: ``progress(done, total)`` in grid poses.
Progress = Callable[[int, int], None]

# Measured peak of the expansion loop (tracemalloc, 108 000 poses, nothing reduced):
# ~720 bytes per grid pose (Pose objects, symmetry keys, direction arrays), rounded up.
_EXPANSION_BYTES_PER_POSE = 1024
# Pose ordering (gonio.capture.ordering) holds about five (n+1) x (n+1) arrays of 8-byte
# values at its peak (move times, pulse distances, np.unique's sort and inverse).
_ORDERING_BYTES_PER_PAIR = 40
_DEFAULT_FRAME_BYTES = 30_000_000  # a 24 MP RAW file
_DNG_HEADER_BYTES = 65_536


@dataclass(frozen=True)
class PlanEstimate:
    """What a plan needs, from the grid's sizes alone (before it is expanded).

    Attributes
    ----------
    n_grid
        Grid poses (product of the axes' lengths).
    n_poses
        Poses to measure at most: the grid after the symmetry reductions that can be
        counted on the axes (isotropy), plus reference poses; exclusions and the rig
        only remove more.
    n_frames
        Frames at most: ``n_poses`` x frames per pose (``len(exposures_s)`` or
        ``max_frames``) plus dark frames.
    frame_bytes, bytes
        One RAW file and all of them, bytes.
    memory_bytes
        Peak memory of expanding and ordering the poses, bytes.
    """

    n_grid: int
    n_poses: int
    n_frames: int
    frame_bytes: int
    bytes: float
    memory_bytes: float

    def summary(self) -> str:
        """One line with the figures, for messages and the dry run."""
        return (
            f"{self.n_grid:,} grid poses, up to {self.n_poses:,} poses and "
            f"{self.n_frames:,} frames, {_fmt_bytes(self.bytes)} of RAW files "
            f"({_fmt_bytes(self.frame_bytes)} each), {_fmt_bytes(self.memory_bytes)} of memory "
            "to expand and order the poses"
        )


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"  # pragma: no cover


def _distinct_relative_azimuths(phi_i: list[float], phi_o: list[float]) -> int:
    d = {
        round(abs(math.remainder(math.radians(b - a), 2 * math.pi)), 6)
        for a in phi_i
        for b in phi_o
    }
    return len(d)


def estimate_plan(plan: Plan) -> PlanEstimate:
    """Count a plan's poses, frames, bytes and memory from the grid's sizes.

    Arithmetic on the axes only (microseconds whatever the grid's size): this is what
    :func:`expand_plan` checks against ``plan.limits`` before it allocates anything.

    Returns
    -------
    PlanEstimate
        Upper bounds (see its attributes).
    """
    if plan.adaptive is not None:  # the pool's size; at most max_poses are measured
        from gonio.capture.adaptive_pool import pool_size

        a = b = c = d = [0.0]
        n_grid = pool_size(plan)
    elif plan.grid is None:  # joint poses: each one is measured, none reduced
        a = b = c = d = [0.0]
        n_grid = len(plan.joint_poses)
    else:
        a, b, c, d = plan.grid.axes()
        n_grid = len(a) * len(b) * len(c) * len(d)
    if not plan.reductions.isotropic or plan.grid is None:
        n_sample = n_grid
    elif plan.grid.kind == "spherical":
        # Isotropy keeps (theta_i, theta_o, |phi_o - phi_i|).
        n_sample = len(a) * len(c) * _distinct_relative_azimuths(b, d)
    else:
        n_sample = len(a) * len(c) * len(d)  # phi_h is a rotation about the normal
    n_sample_poses = min(n_grid, n_sample)
    if plan.adaptive is not None:
        n_sample_poses = min(n_grid, plan.adaptive.max_poses)
    n_poses = n_sample_poses + len(plan.reference.poses) * plan.reference_repeats(n_sample_poses)
    br = plan.bracket
    per_pose = len(br.exposures_s) if br.policy == "fixed" else br.max_frames
    n_frames = n_poses * per_pose + plan.flats.count
    if plan.darks.count:
        if plan.darks.exposure_times_s:
            n_times = len(set(plan.darks.exposure_times_s))
        elif br.policy == "fixed":
            n_times = len(set(br.exposures_s))
        else:  # one per rung of the exposure ladder between the limits
            n_times = int(math.log2(br.max_exposure_s / br.min_exposure_s) / br.step_ev) + 2
        n_frames += plan.darks.count * (n_times + (1 if plan.flats.count else 0))
    lim = plan.limits
    sim = plan.simulation
    if lim.frame_bytes is not None:
        frame = lim.frame_bytes
    elif sim.width and sim.height:
        frame = sim.width * sim.height * 2 + _DNG_HEADER_BYTES
    else:
        frame = _DEFAULT_FRAME_BYTES
    memory = (
        float(n_grid) * _EXPANSION_BYTES_PER_POSE
        + _ORDERING_BYTES_PER_PAIR * float(n_poses + 1) ** 2
    )
    return PlanEstimate(n_grid, n_poses, n_frames, frame, float(n_frames) * frame, memory)


def check_limits(plan: Plan, source: str | None = None) -> PlanEstimate:
    """Refuse a plan that needs more than ``plan.limits`` allows, before expanding it.

    Raises
    ------
    ConfigError
        Naming ``source``, each limit exceeded with what the plan would need, and the
        ``[limits]`` field to raise.
    """
    from gonio.errors import ConfigError

    source = source or plan._source
    est = estimate_plan(plan)
    lim = plan.limits
    over = []
    if est.n_poses > lim.max_poses:
        over.append(f"{est.n_poses:,} poses > limits.max_poses = {lim.max_poses:,}")
    if est.n_frames > lim.max_frames:
        over.append(f"{est.n_frames:,} frames > limits.max_frames = {lim.max_frames:,}")
    if est.bytes > lim.max_bytes:
        over.append(
            f"{_fmt_bytes(est.bytes)} of RAW files > limits.max_bytes = {_fmt_bytes(lim.max_bytes)}"
        )
    if est.memory_bytes > lim.memory_limit():
        over.append(
            f"{_fmt_bytes(est.memory_bytes)} of memory > limits.max_memory_bytes = "
            f"{_fmt_bytes(lim.memory_limit())}"
            + ("" if lim.max_memory_bytes else " (half of this machine's memory)")
        )
    if over:
        raise ConfigError(
            f"{source}: plan {plan.name!r} is too large: {'; '.join(over)}. It would need "
            f"{est.summary()}. Use a coarser grid or symmetry reductions, or raise the "
            "limit in the plan's [limits] table"
        )
    return est


def expand_plan(
    plan: Plan,
    rig_check: RigCheck | None = None,
    progress: Progress | None = None,
    source: str | None = None,
    kinematics: Any = None,
) -> ExpandedPlan:
    """Expand a plan into the poses to measure, in grid (raster) order.

    Parameters
    ----------
    plan
        The validated plan.
    rig_check
        ``check(wi, wo) -> reason | None`` of the rig's kinematics (unreachable, collision,
        arm shadowing); ``None`` skips the rig (a pure geometric dry run).
    progress
        ``progress(done, total)`` in grid poses, called about a hundred times over the
        expansion and once at its end (a dry run shows it as a progress bar).
    source
        Name of the plan in messages (default: the file :func:`load_plan` read).
    kinematics
        The rig's ``Kinematics``: a joint-pose plan needs it (each pose's directions
        are its ``forward``, each pose is checked with ``joints_refusal``).

    Returns
    -------
    ExpandedPlan
        Sample poses first (raster order, or the joint poses in their order), then
        reference poses.

    Raises
    ------
    ConfigError
        The plan needs more than ``plan.limits`` allows (:func:`check_limits`): refused
        before anything is allocated.
    """
    check_limits(plan, source or plan._source)
    if plan.adaptive is not None:
        from gonio.capture.adaptive_pool import expand_adaptive

        return expand_adaptive(plan, rig_check, progress, _reference_poses)
    if plan.grid is None:
        return _expand_joint_poses(plan, rig_check, kinematics, source or plan._source)
    wi_all, wo_all = _grid_directions(plan.grid)
    n_total = len(wi_all)
    every = max(1, n_total // 100)
    seen: set[tuple] = set()
    poses: list[Pose] = []
    excluded: list[ExcludedPose] = []
    n_reduced = 0
    red = plan.reductions
    use_rig = rig_check is not None and plan.exclusions.check_rig
    for k, (wi, wo) in enumerate(zip(wi_all, wo_all, strict=True)):
        if progress is not None and k % every == 0:
            progress(k, n_total)
        if red.isotropic and wi[2] > 0 and wo[2] > 0:
            wi, wo = _canonical_isotropic(wi, wo)
        key = _symmetry_key(wi, wo, red) if (wi[2] > 0 and wo[2] > 0) else None
        if key is not None and key in seen:
            n_reduced += 1
            continue
        if key is not None:
            seen.add(key)
        pose = Pose(_as_tuple(wi), _as_tuple(wo))
        reason = _exclusion_reason(wi, wo, plan.exclusions)
        refusal = (
            rig_check(np.array(pose.wi), np.array(pose.wo)) if reason is None and use_rig else None
        )
        if reason is not None:
            excluded.append(ExcludedPose(pose, reason))
        elif refusal is not None:
            excluded.append(_excluded(pose, refusal))
        else:
            poses.append(pose)
    n_grid = len(wi_all)
    if progress is not None:
        progress(n_grid, n_total)
    notes: list[str] = []
    for rp in plan.reference.poses:
        wi = spherical_to_direction(math.radians(rp.theta_i_deg), math.radians(rp.phi_i_deg))
        wo = spherical_to_direction(math.radians(rp.theta_o_deg), math.radians(rp.phi_o_deg))
        pose = Pose(_as_tuple(wi), _as_tuple(wo), kind="reference")
        refusal = rig_check(np.array(pose.wi), np.array(pose.wo)) if use_rig else None
        if refusal is not None:
            excluded.append(_excluded(pose, refusal))
        else:
            poses.append(pose)
    return ExpandedPlan(
        poses=poses, excluded=excluded, n_grid=n_grid, n_reduced=n_reduced, notes=notes
    )


def _reference_poses(plan: Plan, rig_check: RigCheck | None, use_rig: bool):
    poses, excluded = [], []
    for rp in plan.reference.poses:
        wi = spherical_to_direction(math.radians(rp.theta_i_deg), math.radians(rp.phi_i_deg))
        wo = spherical_to_direction(math.radians(rp.theta_o_deg), math.radians(rp.phi_o_deg))
        pose = Pose(_as_tuple(wi), _as_tuple(wo), kind="reference")
        refusal = rig_check(np.array(pose.wi), np.array(pose.wo)) if use_rig else None
        if refusal is not None:
            excluded.append(_excluded(pose, refusal))
        else:
            poses.append(pose)
    return poses, excluded


def _expand_joint_poses(
    plan: Plan, rig_check: RigCheck | None, kinematics: Any, source: str
) -> ExpandedPlan:
    from gonio.errors import ConfigError

    if kinematics is None:
        raise ConfigError(
            f"{source}: plan {plan.name!r} lists joint poses; expanding it needs the rig's "
            "kinematics (their directions and limits)"
        )
    use_rig = plan.exclusions.check_rig
    poses: list[Pose] = []
    excluded: list[ExcludedPose] = []
    for k, jp in enumerate(plan.joint_poses):
        q = jp.joints_rad()
        wi, wo = (np.asarray(v, dtype=np.float64) for v in kinematics.forward(q))
        label = jp.label if jp.label is not None else f"joint pose {k}"
        pose = Pose(_as_tuple(wi), _as_tuple(wo), kind=jp.target, joints=q, label=label)
        refusal = kinematics.joints_refusal(q) if use_rig else None
        if refusal is not None:
            excluded.append(
                ExcludedPose(pose, f"joint_poses[{k}] ({label}): {refusal}", refusal.reason.value)
            )
        else:
            poses.append(pose)
    ref, ref_excluded = _reference_poses(plan, rig_check, rig_check is not None and use_rig)
    return ExpandedPlan(
        poses=poses + ref,
        excluded=excluded + ref_excluded,
        n_grid=len(plan.joint_poses),
        n_reduced=0,
    )


def exposure_times_for_darks(plan: Plan, used: Sequence[float]) -> list[float]:
    """Exposure times to shoot dark frames at: the plan's list, else every one used."""
    if plan.darks.exposure_times_s:
        return sorted(set(plan.darks.exposure_times_s))
    return sorted({float(t) for t in used})

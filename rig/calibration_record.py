"""The record a calibrated rig configuration carries: where it came from and how good it is.

``gonio calibrate rig`` writes a full rig TOML whose ``[calibration]`` table is a
:class:`CalibrationRecord`: when it was made, the digests of the nominal rig and of the
camera it was calibrated with, the residual RMS per observation kind, how many
observations it used, every parameter's estimate with its standard deviation and unit
(canonical names of ``gonio.rig.calibration``), and the terms it cannot observe (why).

Digests.  A rig's identity is what does not change when it is calibrated: its servos'
ids, models, joints, directions and gear ratios, and its geometry kind;
:func:`rig_digest` is ``"sha256:<hex>"`` of its canonical JSON (``json.dumps(...,
sort_keys=True)``).  A camera's digest is the camera calibration's
(``gonio.capture.camera_calibration.camera_digest`` of ``{backend, model, serial,
resolution}``), recorded here as given.  A calibration made on another rig or camera is
refused with both digests named (:func:`check_rig_digest`, :func:`check_camera_digest`).
"""

from __future__ import annotations

import hashlib
import json
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from gonio.errors import GonioError

if TYPE_CHECKING:  # pragma: no cover
    from gonio.rig.config import RigConfig

__all__ = [
    "CalibrationError",
    "CalibrationRecord",
    "ParameterCovariance",
    "ParameterEstimate",
    "check_camera_digest",
    "check_rig_digest",
    "rig_digest",
    "rig_identity",
]


class CalibrationError(GonioError, ValueError):
    """A calibration cannot be made or used as asked (too few or unsuited observations,
    an unobservable or ill-conditioned parameter, a calibration of another rig or
    camera).  The message names the parameter, file or digest concerned."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ParameterEstimate(_Strict):
    """One calibrated parameter: estimate, standard deviation (same unit) and unit."""

    value: float
    std: float = Field(ge=0)
    unit: str


#: Relative asymmetry and negative-eigenvalue slack a covariance table may show: TOML
#: keeps float64 to the bit, so anything larger is a hand edit or another program's
#: rounding, not the calibration's matrix.
COVARIANCE_TOLERANCE = 1e-9


class ParameterCovariance(_Strict):
    """The ``[calibration.covariance]`` table: the joint covariance of the fitted
    parameters, so their correlations reach the uncertainty budget.

    Attributes
    ----------
    names
        Parameter names (rows and columns, in order): canonical rig parameter names
        (``gonio.rig.calibration.PARAMETER_NAMES``) and camera intrinsics
        (``INTRINSIC_NAMES``), each once.
    matrix
        Square, symmetric, positive semi-definite matrix in the parameters' units
        squared (deg^2, m^2, px^2, 1).
    """

    names: list[str]
    matrix: list[list[float]]

    @model_validator(mode="after")
    def _valid(self) -> ParameterCovariance:
        from gonio.rig.calibration import INTRINSIC_NAMES, PARAMETER_NAMES

        known = set(PARAMETER_NAMES) | set(INTRINSIC_NAMES)
        unknown = [n for n in self.names if n not in known]
        if unknown:
            raise ValueError(
                f"names: unknown parameter(s) {unknown}; expected rig calibration parameters "
                "or camera intrinsics (gonio.rig.calibration.PARAMETER_NAMES, INTRINSIC_NAMES)"
            )
        dup = sorted({n for n in self.names if self.names.count(n) > 1})
        if dup:
            raise ValueError(f"names: parameter(s) {dup} given more than once")
        n = len(self.names)
        rows = [len(r) for r in self.matrix]
        if len(rows) != n or any(r != n for r in rows):
            raise ValueError(
                f"matrix: expected {n} x {n} (one row and column per name), got "
                f"{len(rows)} rows of lengths {sorted(set(rows))}"
            )
        m = np.asarray(self.matrix, dtype=np.float64).reshape(n, n)
        scale = float(np.max(np.abs(np.diag(m)), initial=0.0))
        if np.any(np.diag(m) < 0):
            k = int(np.argmin(np.diag(m)))
            raise ValueError(f"matrix: negative variance {m[k, k]:g} of {self.names[k]}")
        asym = float(np.max(np.abs(m - m.T), initial=0.0))
        if asym > COVARIANCE_TOLERANCE * max(scale, 1e-300):
            i, j = np.unravel_index(int(np.argmax(np.abs(m - m.T))), m.shape)
            raise ValueError(
                f"matrix: not symmetric ({self.names[i]}, {self.names[j]}: "
                f"{m[i, j]:g} vs {m[j, i]:g})"
            )
        if n:
            d = np.sqrt(np.where(np.diag(m) > 0, np.diag(m), 1.0))
            low = float(np.linalg.eigvalsh(m / np.outer(d, d)).min())
            if low < -1e-6:
                raise ValueError(
                    f"matrix: not positive semi-definite (correlation eigenvalue {low:.3g})"
                )
        return self

    def array(self) -> NDArray[np.float64]:
        """The matrix as a (n, n) float64 array."""
        n = len(self.names)
        return np.asarray(self.matrix, dtype=np.float64).reshape(n, n)


class CalibrationRecord(_Strict):
    """The ``[calibration]`` table of a calibrated rig configuration.

    Attributes
    ----------
    created
        ISO 8601 UTC time of the calibration.
    nominal_digest
        :func:`rig_digest` of the nominal rig the calibration started from.
    camera_digest
        The camera calibration's digest of the camera the observations were made with (None when
        unknown).
    rms_px
        Residual RMS per observation kind (``"board"``, ``"spot"``), px.
    counts
        How many observations of each kind were used (``"board_views"``,
        ``"board_corners"``, ``"spots"``, ``"rejected"``).
    parameters
        Canonical parameter name -> estimate (value, std, unit).
    intrinsics
        The camera intrinsics refined with the rig (``fx``, ``fy``, ``cx``, ``cy`` px,
        ``k1``..``k3``), tied to the camera calibration by its uncertainties.
    rejected
        View label -> why it was left out.
    not_observable
        Term -> why no calibration can measure it.
    nominal
        The nominal rig configuration itself (a rig TOML's tables): what was calibrated,
        so a calibration can be redone from it and a simulated rig knows its drawing.
    covariance
        The joint covariance of the fitted parameters (:class:`ParameterCovariance`);
        None in records written before it was kept.
    """

    created: str
    nominal_digest: str
    camera_digest: str | None = None
    rms_px: dict[str, float] = {}
    counts: dict[str, int] = {}
    parameters: dict[str, ParameterEstimate] = {}
    intrinsics: dict[str, ParameterEstimate] = {}
    rejected: dict[str, str] = {}
    not_observable: dict[str, str] = {}
    nominal: dict[str, Any] | None = None
    covariance: ParameterCovariance | None = None


def _digest(data: Any) -> str:
    return "sha256:" + hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def rig_identity(config: RigConfig) -> dict[str, Any]:
    """What identifies a rig whatever its calibration: servos (id, model, joint,
    direction, gear ratio; sorted by id) and geometry kind."""
    servos = sorted(config.servos, key=lambda s: s.id)
    return {
        "servos": [
            {
                "id": s.id,
                "model": s.model,
                "joint": s.joint,
                "direction": s.direction,
                "gear_ratio": float(s.gear_ratio),
            }
            for s in servos
        ],
        "geometry_kind": config.geometry.kind,
    }


def rig_digest(config: RigConfig) -> str:
    """``"sha256:<hex>"`` of :func:`rig_identity` (unchanged by a calibration)."""
    return _digest(rig_identity(config))


def check_rig_digest(expected: str, actual: str, *, what: str = "the rig") -> None:
    """Refuse a calibration made on another rig.

    Raises
    ------
    CalibrationError
        Naming both digests when they differ.
    """
    if expected != actual:
        raise CalibrationError(
            f"{what} is not the rig the calibration was made for: calibration nominal_digest "
            f"{expected}, this rig {actual} (servo ids, models, joints, directions, gear "
            "ratios or geometry kind differ)"
        )


def check_camera_digest(calibration: str | None, session: str | None, *, source: str) -> None:
    """Refuse a camera calibration of another camera than the session's.

    Raises
    ------
    CalibrationError
        Naming both digests (and ``source``, the camera calibration file) when they differ.
    """
    if calibration != session:
        raise CalibrationError(
            f"{source}: camera calibration digest {calibration} is not the session's camera "
            f"{session} (backend, model, serial or resolution differ): calibrate this camera"
        )

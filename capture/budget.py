"""The per-sample uncertainty budget (GUM): geometric modes, their BRDF effect, the terms.

Every reduced sample carries a budget of standard deviations in BRDF units (1/sr), one
per term of :data:`TERMS`, whose root sum of squares is its ``brdf_std``; terms shared
by every sample (:data:`SHARED_TERMS`, relative) are kept apart, for the fitter to treat
as fully correlated.

Geometry enters as *modes*: 1-sigma perturbations of ``(wi, wo)`` (sample frame) that
one error source causes in every sample it touches.

- ``"session"`` modes: the rig calibration's covariance (``[calibration.covariance]``
  of the manifest's rig), eigen-decomposed, each eigenvector scaled by the root of its
  eigenvalue; every mode moves the light (and, for a pose whose camera came from the
  rig, the camera) through the rig's kinematics at the pose's journaled joints and
  approach sides (:class:`SessionModes`).  Without a calibration record the rig is
  taken as nominal to ``nominal_joint_std_deg`` per joint zero offset (an assumption,
  stated in ``reduction.toml``'s ``[reduction]``).
- ``"pose"`` modes: the board pose of one pose (``CameraPose.covariance``,
  eigen-decomposed): shared only by that pose's regions.

A mode moves a region's directions from its centroid point: the point the ray through
the region's centroid pixel meets the sample plane at (:func:`centroid_points`).
Perturbing the camera moves that ray, hence the point, and both directions are
recomputed; perturbing the light changes ``wi`` only.

The BRDF's response ``df/dw`` needs a model, and the capture layer has none: it is the
gradient of a model-free local fit of the measured samples (:func:`local_log_gradient`:
k-nearest-neighbour, tricube-weighted, ridge-regularised quadratic regression of
``log f`` on the projected directions ``(wi_x, wi_y, wo_x, wo_y)``, or, for a material the
plan declares isotropic, on three rotation-invariant features of the pair,
:func:`isotropic_features`, so that neighbours at other azimuths of the same
``(theta_i, theta_o, phi_o - phi_i)`` inform the slope and none is fitted along the
rotation the material ignores).  The marginal ``geometry`` term is
``f sqrt(sum_j (grad . dX_j)^2)`` over all modes (:func:`geometry_std`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.dataset import BUDGET_TERMS, SHARED_BUDGET_TERMS

__all__ = [
    "BUDGET_COLUMNS",
    "INTRINSICS",
    "MODE_WIDTH",
    "POSE_MODE_NAMES",
    "SHARED_TERMS",
    "TERMS",
    "CameraModes",
    "RigShifts",
    "SessionModes",
    "budget_cells",
    "budget_rows",
    "budget_table",
    "camera_modes",
    "centroid_points",
    "direction_features",
    "geometry_std",
    "isotropic_features",
    "isotropic_jacobian",
    "local_log_gradient",
    "pose_modes",
    "rig_shifts",
    "session_modes",
]

Array = NDArray[np.float64]

#: Per-sample terms, std in 1/sr, (N, C): photon/read/dark-subtraction noise, geometry
#: (marginal over the modes), then the radiometric terms (samples.h5's budget group).
TERMS: tuple[str, ...] = BUDGET_TERMS
#: Terms shared by every sample, relative std per channel, (C,).
SHARED_TERMS: tuple[str, ...] = SHARED_BUDGET_TERMS
#: The six modes of a board pose (eigenvectors of its covariance, largest first).
POSE_MODE_NAMES: tuple[str, ...] = tuple(f"board pose {k + 1}" for k in range(6))
#: ``(wi, wo)`` components of a mode: (..., 6).
MODE_WIDTH = 6
_Z = np.array([0.0, 0.0, 1.0])


def _unit(v: Array) -> Array:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _plane_hit(C: Array, d: Array) -> Array:
    """(..., n, 3) points where rays from ``C`` (..., 3) along ``d`` (..., n, 3) meet
    z = 0."""
    with np.errstate(invalid="ignore", divide="ignore"):
        s = -C[..., 2, None] / d[..., 2]
    return C[..., None, :] + s[..., None] * d


def centroid_points(camera_position: Array, wo: Array) -> Array:
    """The sample-plane points (z = 0) whose direction to the camera is ``wo``.

    Parameters
    ----------
    camera_position
        (3,) camera centre, sample frame, m.
    wo
        (n, 3) measured unit directions to the camera of the regions.

    Returns
    -------
    ndarray
        (n, 3) points, m: each region's centroid as its measured ``wo`` sees it (NaN
        rows stay NaN).
    """
    C = np.asarray(camera_position, float)
    return _plane_hit(C, -np.asarray(wo, float))


@dataclass
class SessionModes:
    """The session's geometric modes: 1-sigma steps of the rig's parameters.

    Attributes
    ----------
    names
        One name per mode (``"rig k: <largest parameter>"`` or ``"nominal <joint>"``).
    parameter_names
        The parameters the steps are over (rig parameters, then camera intrinsics).
    steps
        (M, P) one 1-sigma step per mode, in the parameters' units (deg, m, px, 1).
    plus, minus
        Per mode, the rig configuration moved by ``+step`` and ``-step``.
    joint_steps
        Per mode, the step of each joint's zero offset, rad: a journal's joint readings
        were converted with the rig's zeros, so a zero off by ``d`` puts the joint at
        ``reading + d`` (as :mod:`gonio.rig.calibration` models its observations).
    source
        ``"calibration"`` (the record's covariance), ``"nominal"`` (the assumed joint
        tolerance) or ``"none"``.
    warnings
        What could not be done (e.g. a rig the parameters cannot express).
    """

    names: list[str] = field(default_factory=list)
    parameter_names: list[str] = field(default_factory=list)
    steps: Array = field(default_factory=lambda: np.zeros((0, 0)))
    plus: list[Any] = field(default_factory=list)
    minus: list[Any] = field(default_factory=list)
    joint_steps: list[dict[str, float]] = field(default_factory=list)
    source: str = "none"
    warnings: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.names)

    def intrinsic_steps(self) -> Array:
        """(M, 4) the modes' steps of ``fx, fy, cx, cy`` (px; 0 where not in the set)."""
        out = np.zeros((len(self.names), 4))
        for k, n in enumerate(("fx", "fy", "cx", "cy")):
            if n in self.parameter_names:
                out[:, k] = self.steps[:, self.parameter_names.index(n)]
        return out


def session_modes(rig: Any, *, nominal_joint_std_deg: float = 0.1) -> SessionModes:
    """The geometric modes a rig configuration's uncertainty gives.

    Parameters
    ----------
    rig
        The manifest's :class:`gonio.rig.config.RigConfig` (None: no modes).
    nominal_joint_std_deg
        Standard deviation of each joint's zero offset, deg, assumed when the rig carries
        no calibration covariance.

    Returns
    -------
    SessionModes
        Modes from the eigen-decomposition of the rig's parameter covariance (rig
        parameters and camera intrinsics), eigenvalues below 1e-12 of the largest left
        out.
    """
    if rig is None:
        return SessionModes(warnings=["no rig configuration: no session geometry modes"])
    from gonio.errors import GonioError
    from gonio.rig.calibration import PARAMETER_NAMES, apply_parameters, parameters_of
    from gonio.rig.config import JOINT_NAMES, rig_config_from_dict

    rec = rig.calibration
    try:
        nominal = rig
        if rec is not None and rec.nominal is not None:
            nominal = rig_config_from_dict(dict(rec.nominal), "calibration.nominal")
        if rec is not None and rec.covariance is not None:
            names = list(rec.covariance.names)
            cov = rec.covariance.array()
            source = "calibration"
        elif rec is not None and rec.parameters:
            # a record written before the covariance was kept: its standard deviations,
            # uncorrelated (the correlations are lost)
            names = list(rec.parameters) + list(rec.intrinsics)
            est = {**rec.parameters, **rec.intrinsics}
            cov = np.diag([est[n].std ** 2 for n in names])
            source = "calibration"
        else:
            names = [f"{j}.offset" for j in JOINT_NAMES]
            cov = np.diag(np.full(len(names), float(nominal_joint_std_deg) ** 2))
            source = "nominal"
        p0 = parameters_of(rig, nominal)
    except GonioError as exc:
        return SessionModes(warnings=[f"the rig's uncertainty cannot be propagated: {exc}"])
    if not len(names):
        return SessionModes(source=source)
    # The eigen-decomposition of the correlation, not of the covariance: the parameters
    # are in deg, m and px (variances 1e-9 m^2 beside 1 px^2), which an eigen-solver's
    # absolute accuracy would mix; steps D U sqrt(lam) still sum to D R D = C.
    steps, tops = _eigen_steps(cov, names)
    rig_idx = [i for i, n in enumerate(names) if n in PARAMETER_NAMES]
    out = SessionModes(parameter_names=names, steps=steps, source=source)
    for j, step in enumerate(steps):
        # the name says which parameter the mode moves most
        top = tops[j]
        out.names.append(f"nominal {top}" if source == "nominal" else f"rig {j + 1}: {top}")
        out.joint_steps.append(
            {
                j: math.radians(float(step[names.index(f"{j}.offset")]))
                for j in JOINT_NAMES
                if f"{j}.offset" in names
            }
        )
        for sign, dest in ((1.0, out.plus), (-1.0, out.minus)):
            v = dict(p0)
            for i in rig_idx:
                v[names[i]] = v[names[i]] + sign * float(step[i])
            dest.append(apply_parameters(nominal, v, validate=False))
    return out


#: The camera intrinsics a camera mode moves (``CameraPose.intrinsics_sensitivity``'s
#: columns): px, then OpenCV distortion coefficients.
INTRINSICS: tuple[str, ...] = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass
class CameraModes:
    """The camera calibration's modes: 1-sigma steps of the intrinsics the reduction
    uses (``reduction.toml``'s camera, from ``gonio calibrate camera``).

    Attributes
    ----------
    names
        ``"camera k: <largest intrinsic>"`` per mode.
    steps
        (Mk, 9) steps of :data:`INTRINSICS`.
    """

    names: list[str] = field(default_factory=list)
    steps: Array = field(default_factory=lambda: np.zeros((0, 9)))

    def __len__(self) -> int:
        return len(self.names)


def camera_modes(calibration: Mapping[str, Any] | None) -> CameraModes:
    """The intrinsics' modes from a camera calibration's ``[camera.calibration]`` table.

    Parameters
    ----------
    calibration
        ``ReductionSetup.camera_calibration``: its ``covariance`` ((9, 9) over
        :data:`INTRINSICS`) when present, else ``K_std`` (fx, fy, cx, cy, px) and
        ``dist_std`` (k1, k2, p1, p2, k3), uncorrelated.  None: no modes (a camera given
        as numbers, whose uncertainty nobody stated).

    Returns
    -------
    CameraModes
        From the eigen-decomposition of the correlation (as :func:`session_modes`).
    """
    if not calibration:
        return CameraModes()
    cov = None
    raw = calibration.get("covariance")
    if raw is not None:
        a = np.asarray(raw, dtype=np.float64)
        if a.shape == (9, 9) and np.all(np.isfinite(a)):
            cov = 0.5 * (a + a.T)
    if cov is None:
        sd = np.zeros(9)
        for key, sl in (("K_std", slice(0, 4)), ("dist_std", slice(4, 9))):
            v = np.asarray(calibration.get(key) or [], dtype=np.float64).ravel()
            n = min(len(v), sl.stop - sl.start)
            sd[sl.start : sl.start + n] = np.nan_to_num(v[:n])
        cov = np.diag(sd**2)
    steps, names = _eigen_steps(cov, list(INTRINSICS))
    return CameraModes([f"camera {j + 1}: {n}" for j, n in enumerate(names)], steps)


def _eigen_steps(cov: Array, names: Sequence[str]) -> tuple[Array, list[str]]:
    """1-sigma steps ``D U sqrt(lam)`` of the correlation's eigen-decomposition (mixed
    units: the covariance's own would mix them), largest first, and per step the name of
    the parameter it moves most (in its own standard deviations)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    scale = np.where(sd > 0, sd, 1.0)
    lam, U = np.linalg.eigh(cov / np.outer(scale, scale))
    order = np.argsort(lam)[::-1]
    lam, U = lam[order], U[:, order]
    keep = (lam > 1e-12 * max(float(lam[0]), 1e-300)) & (lam > 0)
    if not np.any(sd > 0):
        keep[:] = False
    steps = (U[:, keep] * np.sqrt(lam[keep])).T * scale
    top = [names[int(np.argmax(np.abs(st) / scale))] for st in steps]
    return steps, top


@dataclass
class RigShifts:
    """The session modes' light and camera at every pose: ``[mode, +/-, pose]``.

    Attributes
    ----------
    light
        (M, 2, P, 3) light centre, sample frame, m (index 1: ``+step``, ``-step``).
    camera_position
        (M, 2, P, 3) camera centre, m.
    camera_rotation
        (M, 2, P, 3, 3) sample-to-camera rotation.
    """

    light: Array
    camera_position: Array
    camera_rotation: Array

    def at(self, k: int) -> tuple[Array, Array, Array]:
        """The ``(M, 2, ...)`` slices of pose ``k``."""
        return self.light[:, :, k], self.camera_position[:, :, k], self.camera_rotation[:, :, k]


def rig_shifts(
    session: SessionModes,
    joints: Sequence[Mapping[str, float] | None],
    approach: Sequence[Mapping[str, int] | None],
) -> RigShifts:
    """Light and camera of every pose under every session mode, one vectorised
    kinematics evaluation per mode and sign (:func:`gonio.rig.asbuilt.rig_poses`).

    Parameters
    ----------
    session
        The session's modes.
    joints, approach
        Per pose, its journaled joint readings (rad) and approach sides (None: unknown;
        a pose without joints gets NaN).

    Returns
    -------
    RigShifts
    """
    from gonio.rig.asbuilt import rig_poses
    from gonio.rig.config import JOINT_NAMES

    P, M = len(joints), len(session)
    have = np.array([bool(q) and all(j in q for j in JOINT_NAMES) for q in joints])
    q0 = {
        j: np.array([float(q[j]) if h else 0.0 for q, h in zip(joints, have, strict=True)])
        for j in JOINT_NAMES
    }
    sides = {j: np.array([float((a or {}).get(j, 0)) for a in approach]) for j in JOINT_NAMES}
    light = np.full((M, 2, P, 3), np.nan)
    cpos = np.full((M, 2, P, 3), np.nan)
    crot = np.full((M, 2, P, 3, 3), np.nan)
    for m in range(M):
        for k, (sign, config) in enumerate(((1.0, session.plus[m]), (-1.0, session.minus[m]))):
            dq = session.joint_steps[m]
            q = {j: q0[j] + sign * dq.get(j, 0.0) for j in JOINT_NAMES}
            rp = rig_poses(config, q, sides)
            light[m, k] = np.broadcast_to(rp.light_position, (P, 3))
            cpos[m, k] = np.broadcast_to(rp.camera_position, (P, 3))
            crot[m, k] = np.swapaxes(np.broadcast_to(rp.camera_rotation, (P, 3, 3)), -1, -2)
    light[:, :, ~have] = np.nan
    return RigShifts(light, cpos, crot)


def pose_modes(
    wi: Array,
    wo: Array,
    camera: Any,
    light_position: Array,
    *,
    source: str = "board",
    session: SessionModes | None = None,
    shifts: tuple[Array, Array, Array] | None = None,
    K: Array | None = None,
    camera_modes: CameraModes | None = None,
    dist: Array | None = None,
) -> Array:
    """The geometric modes of one pose's regions: ``(n, M + Mk + 6, 6)``.

    Parameters
    ----------
    wi, wo
        (n, 3) the regions' measured directions (sample frame).
    camera
        The pose's :class:`gonio.capture.fiducials.CameraPose` (rotation, translation,
        position and, from the board, covariance).
    light_position
        (3,) the light's centre the reduction used, sample frame, m.
    source
        Where the camera pose came from: ``"board"`` (the rig's modes move the light
        only; the board's covariance gives the six pose modes), ``"rig"`` (the rig's
        modes move light and camera, and the intrinsics move the pixel rays; no pose
        modes) or ``"none"`` (no modes).
    session
        The session's modes (:func:`session_modes`); None: none.
    shifts
        This pose's light positions, camera positions and sample-to-camera rotations
        under each session mode, ``(M, 2, 3)``, ``(M, 2, 3)``, ``(M, 2, 3, 3)``
        (:meth:`RigShifts.at`); None: no session modes.
    K, dist
        The intrinsics the reduction used (px; OpenCV distortion, None: none).
    camera_modes
        The camera calibration's modes (:func:`camera_modes`): on a ``"board"`` pose a
        step of the intrinsics moves the board pose
        (``camera.intrinsics_sensitivity``) and the centroid pixel's ray (undistorted
        with the moved intrinsics); zeros on ``"rig"`` poses (the rig's covariance holds
        the intrinsics it was calibrated with).

    Returns
    -------
    ndarray
        (n, M + Mk + 6, 6) per region the 1-sigma change of ``(wi, wo)`` along each
        session mode (central difference through the kinematics), each camera mode,
        then along the six board pose modes (zeros where they do not apply).
    """
    wi = np.asarray(wi, float)
    wo = np.asarray(wo, float)
    n = len(wi)
    M = 0 if session is None else len(session)
    Mk = 0 if camera_modes is None else len(camera_modes)
    out = np.zeros((n, M + Mk + 6, MODE_WIDTH))
    if source == "none":
        return out
    C = np.asarray(camera.position, float)
    R = np.asarray(camera.rotation, float)
    L = np.asarray(light_position, float)
    x = centroid_points(C, wo)
    d_cam = _unit((x - C) @ R.T)  # the centroid pixel's ray, camera frame
    # Every mode and sign at once, (modes, 2, n, ...), with the same elementwise
    # operations (and the same 3 x 3 products) as one mode at a time: the same bits, in
    # a tenth of the time (the reduction calls this twice a pose to choose the camera's
    # source, and once a pose for the budget).
    if M and shifts is not None and np.isfinite(shifts[0]).all():
        Ls, Cs, Rs = (np.asarray(a, float) for a in shifts)
        if source == "rig":
            if K is None:
                ray = np.broadcast_to(d_cam, (M, 2, n, 3))
            else:
                sign = np.array([1.0, -1.0])[None, :, None]
                ray = _ray_moved(d_cam, K, sign * session.intrinsic_steps()[:, None, :])
            xp = _plane_hit(Cs, ray @ Rs)
            pair = np.concatenate([_unit(Ls[:, :, None] - xp), _unit(Cs[:, :, None] - xp)], axis=-1)
        else:
            pair = np.concatenate(
                [_unit(Ls[:, :, None] - x), np.broadcast_to(wo, (M, 2, n, 3))], axis=-1
            )
        out[:, :M] = np.swapaxes(0.5 * (pair[:, 0] - pair[:, 1]), 0, 1)
    cov = getattr(camera, "covariance", None)
    if source == "board" and cov is not None and np.all(np.isfinite(cov)):
        import cv2

        lam, U = np.linalg.eigh(0.5 * (cov + cov.T))
        order = np.argsort(lam)[::-1]
        rvec = cv2.Rodrigues(R)[0].ravel()
        t = np.asarray(camera.translation, float)
        Rp = np.empty((6, 2, 3, 3))
        Cp = np.empty((6, 2, 3))
        for k, i in enumerate(order):
            step = U[:, i] * math.sqrt(max(float(lam[i]), 0.0))
            for s, sign in enumerate((1.0, -1.0)):
                Rp[k, s] = cv2.Rodrigues(rvec + sign * step[:3])[0]
                tp = t + sign * step[3:]
                Cp[k, s] = -Rp[k, s].T @ tp
        xp = _plane_hit(Cp, d_cam @ Rp)
        pair = np.concatenate([_unit(L - xp), _unit(Cp[:, :, None] - xp)], axis=-1)
        out[:, M + Mk :] = np.swapaxes(0.5 * (pair[:, 0] - pair[:, 1]), 0, 1)
    sens = getattr(camera, "intrinsics_sensitivity", None)
    if source == "board" and Mk and K is not None and sens is not None and np.isfinite(sens).all():
        out[:, M : M + Mk] = _camera_mode_shifts(x, L, camera, K, dist, camera_modes)
    return out


def direction_variance(
    camera: Any,
    light_position: Array,
    roi_half: tuple[float, float],
    **modes: Any,
) -> float:
    """The geometric variance (rad^2) of one pose's directions by one camera source: the
    squared 1-sigma ``(wi, wo)`` changes of every mode, summed over modes and components
    and averaged over the ROI's centre and corners (:func:`pose_modes`).

    It is what ``geometry = "auto"`` compares to choose between the board's camera pose
    and the rig's at a pose: the source whose covariance moves the directions less.

    Parameters
    ----------
    camera
        The pose's camera by that source (:class:`gonio.capture.fiducials.CameraPose`).
    light_position
        (3,) the light's centre, sample frame, m.
    roi_half
        Half the ROI's width and height on the sample, m.
    **modes
        :func:`pose_modes`' keywords (``source``, ``session``, ``shifts``, ``K``,
        ``camera_modes``, ``dist``).

    Returns
    -------
    float
        rad^2; NaN when a mode cannot be evaluated.
    """
    hx, hy = roi_half
    x = np.array([[0.0, 0.0, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0], [hx, -hy, 0.0], [-hx, -hy, 0.0]])
    L = np.asarray(light_position, float)
    wo = _unit(np.asarray(camera.position, float) - x)
    wi = _unit(L - x)
    d = pose_modes(wi, wo, camera, L, **modes)
    return float(np.mean(np.sum(d**2, axis=(1, 2))))


def _camera_mode_shifts(
    x: Array, L: Array, camera: Any, K: Array, dist: Array | None, modes: CameraModes
) -> Array:
    """(n, Mk, 6): a board pose's ``(wi, wo)`` change along each camera mode: the pose
    follows the intrinsics (``intrinsics_sensitivity``) and the centroid pixel's ray is
    the one the moved intrinsics see."""
    import cv2

    R = np.asarray(camera.rotation, float)
    t = np.asarray(camera.translation, float)
    rvec = cv2.Rodrigues(R)[0].ravel()
    d0 = np.zeros(5)
    if dist is not None:
        dd = np.asarray(dist, float).ravel()
        d0[: min(len(dd), 5)] = dd[:5]
    K = np.asarray(K, float)
    good = np.isfinite(x).all(axis=1)
    out = np.zeros((len(x), len(modes), MODE_WIDTH))
    if not good.any():
        return out
    pix, _ = cv2.projectPoints(x[good], rvec, t, K, d0)
    for j, step in enumerate(modes.steps):
        pair = []
        for sign in (1.0, -1.0):
            dk = sign * step
            dp = np.asarray(camera.intrinsics_sensitivity, float) @ dk
            Rp = cv2.Rodrigues(rvec + dp[:3])[0]
            tp = t + dp[3:]
            Cp = -Rp.T @ tp
            Kp = K.copy()
            Kp[0, 0] += dk[0]
            Kp[1, 1] += dk[1]
            Kp[0, 2] += dk[2]
            Kp[1, 2] += dk[3]
            # the same pixel, seen with the moved intrinsics: its undistorted ray
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-15)
            xy = cv2.undistortPoints(
                pix, Kp, d0 + dk[4:], R=np.eye(3), P=np.eye(3), criteria=crit
            ).reshape(-1, 2)
            ray = _unit(np.concatenate([xy, np.ones((len(xy), 1))], axis=1))
            xp = _plane_hit(Cp, ray @ Rp)
            pair.append(np.concatenate([_unit(L - xp), _unit(Cp - xp)], axis=1))
        out[good, j] = 0.5 * (pair[0] - pair[1])
    return out


def _ray_moved(d_cam: Array, K: Array, dk: Array) -> Array:
    """The camera-frame rays (..., n, 3) of the same pixels (``d_cam``, (n, 3)) with
    ``fx, fy, cx, cy`` moved by ``dk`` (..., 4) (px): pinhole ``x = (u - cx) / fx``, so
    ``dx = -(dcx + x dfx) / fx`` (distortion's own derivative left out: second order
    here)."""
    K = np.asarray(K, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        xn = d_cam[:, 0] / d_cam[:, 2]
        yn = d_cam[:, 1] / d_cam[:, 2]
    dk = np.asarray(dk, float)[..., None]
    dfx, dfy, dcx, dcy = dk[..., 0, :], dk[..., 1, :], dk[..., 2, :], dk[..., 3, :]
    # the pixel stays, the intrinsics move: the ray that pixel sees changes by -d(K)/K
    xp = xn - (dcx + xn * dfx) / K[0, 0]
    yp = yn - (dcy + yn * dfy) / K[1, 1]
    return _unit(np.stack([xp, yp, np.ones_like(xp)], axis=-1))


# ------------------------------------------------------------------ df/dw
def direction_features(wi: Array, wo: Array) -> Array:
    """(N, 4) ``(wi_x, wi_y, wo_x, wo_y)``: the projected-disk chart of the direction
    pair that :func:`local_log_gradient` regresses on (a mode's feature change is its
    ``(dwi_x, dwi_y, dwo_x, dwo_y)``)."""
    wi = np.asarray(wi, float)
    wo = np.asarray(wo, float)
    return np.concatenate([wi[..., :2], wo[..., :2]], axis=-1)


def isotropic_features(wi: Array, wo: Array) -> Array:
    """(N, 3) rotation-invariant features of a direction pair (an isotropic BRDF's chart).

    With ``a = (wi_x, wi_y) = sin(theta_i) (cos phi_i, sin phi_i)``, ``b`` the same of
    ``wo`` and ``r = sqrt(|a|^2 + |b|^2)``::

        Y = (|a|^2 - |b|^2, 2 a . b, 2 a x b) / r
          = (sin^2 theta_i - sin^2 theta_o,
             2 sin theta_i sin theta_o cos(phi_o - phi_i),
             2 sin theta_i sin theta_o sin(phi_o - phi_i)) / r

    a function of ``(theta_i, theta_o, phi_o - phi_i)`` only, so two pairs that differ by
    a rotation about the normal have the same features.  Why this chart and not
    ``(theta_i, theta_o, phi_d)`` or the half-vector angles: those are singular where a
    session measures (``phi_d`` at normal incidence, the half-vector azimuth at the
    specular peak), this one only where both directions are the normal (the rig cannot
    put light and camera there).  It is the Hopf map of ``(a, b)`` as one point of
    ``C^2``, divided by ``r`` so that ``|Y| = r``: distances are those of the projected
    chart along ``r`` and twice them across it, and the sign of ``a x b`` keeps the
    mirror images apart (no bilateral symmetry is assumed).

    Parameters
    ----------
    wi, wo
        (N, 3) unit directions (sample frame).

    Returns
    -------
    ndarray
        (N, 3) features, dimensionless; NaN where both directions are the normal or an
        input is NaN.
    """
    a = np.asarray(wi, float)[..., :2]
    b = np.asarray(wo, float)[..., :2]
    aa = np.sum(a * a, axis=-1)
    bb = np.sum(b * b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(aa + bb)
        r = np.where(r > 0, r, np.nan)
    H = np.stack(
        [aa - bb, 2 * np.sum(a * b, axis=-1), 2 * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])],
        axis=-1,
    )
    return H / r[..., None]


def isotropic_jacobian(wi: Array, wo: Array) -> Array:
    """(N, 3, 4) ``dY / dX``: the derivative of :func:`isotropic_features` by
    :func:`direction_features` (closed form; the chain rule that brings an isotropic
    chart's gradient back to the projected chart the modes are in).

    ``Y = H / r``: ``dY/dX = (dH/dX) / r - H X^T / r^3``; its null space is the rotation
    about the normal, ``(-a_y, a_x, -b_y, b_x)``.
    """
    X = direction_features(wi, wo)
    ax, ay, bx, by = np.moveaxis(X, -1, 0)
    dH = 2.0 * np.stack(
        [
            np.stack([ax, ay, -bx, -by], axis=-1),
            np.stack([bx, by, ax, ay], axis=-1),
            np.stack([by, -bx, -ay, ax], axis=-1),
        ],
        axis=-2,
    )  # (N, 3, 4)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(np.sum(X * X, axis=-1))
        r = np.where(r > 0, r, np.nan)
    H = isotropic_features(wi, wo) * r[..., None]
    return dH / r[..., None, None] - H[..., :, None] * X[..., None, :] / r[..., None, None] ** 3


def local_log_gradient(
    wi: Array,
    wo: Array,
    brdf: Array,
    usable: NDArray[np.bool_] | None = None,
    *,
    k: int = 32,
    ridge: float = 1e-4,
    curvature_ridge: float = 1e-4,
    isotropic: bool = False,
) -> Array:
    """The gradient of ``log f`` over :func:`direction_features`, from the samples alone.

    For every sample: its ``k`` nearest usable samples in feature space
    (``scipy.spatial.cKDTree``), tricube weights over the ``k``-th distance ``h``, and
    the weighted least-squares quadratic ``log f ~ a + g . D + D^T H D / 2`` per channel
    (``D = (X - X_0) / h``; LOESS of degree 2), ridge-regularised (``ridge`` on the
    slopes, ``curvature_ridge`` on the curvatures, times the weight sum) and solved by
    the pseudo-inverse, so directions the neighbourhood does not span get no slope
    rather than noise.  The curvature terms matter on a narrow lobe: a linear fit there
    gives the secant's slope, wrong at the neighbourhood's edges.

    ``isotropic=True`` fits the same quadratic on :func:`isotropic_features` (three
    features: the neighbours are the samples of nearby ``(theta_i, theta_o,
    phi_o - phi_i)`` whatever their azimuth) and returns its gradient in the projected
    chart through :func:`isotropic_jacobian`, hence exactly 0 along a rotation about the
    normal.  Why: a session's poses sit at a few azimuths, and in the projected chart
    the neighbours of a grazing pose's regions are other poses 10-25 deg away, so a
    slope along a direction the pose's regions do not span is missed (world 1607's
    theta_i 75 / theta_o 80 pose: 5 per unit against the truth's 55-66).  Only for a
    material that is isotropic: an anisotropic one would have its azimuthal slope
    averaged away.

    Parameters
    ----------
    wi, wo
        (N, 3) unit directions.
    brdf
        (N, C) measured f_r, 1/sr.
    usable
        (N,) samples that may serve as neighbours (default: all); only those with every
        channel finite and positive are used.
    k
        Neighbours per fit (at least 6).
    ridge, curvature_ridge
        Relative ridge weights (dimensionless).
    isotropic
        Regress on the isotropic chart (the plan's ``[reductions] isotropic``).

    Returns
    -------
    ndarray
        (N, C, 4) ``d log f / dX`` (per unit of the projected features, whichever chart
        was fitted); NaN where fewer than 6 neighbours exist.
    """
    from scipy.spatial import cKDTree

    X = isotropic_features(wi, wo) if isotropic else direction_features(wi, wo)
    f = np.asarray(brdf, float)
    if f.ndim == 1:
        f = f[:, None]
    N, C = f.shape
    ok = np.isfinite(X).all(axis=1) & np.isfinite(f).all(axis=1) & (f > 0).all(axis=1)
    if usable is not None:
        ok &= np.asarray(usable, bool)
    out = np.full((N, C, X.shape[1]), np.nan)
    pool = np.flatnonzero(ok)
    kk = min(int(k), len(pool))
    if kk < 6:
        return np.full((N, C, 4), np.nan)
    tree = cKDTree(X[pool])
    logf = np.log(np.where(ok[:, None], f, np.nan))
    q_all = np.flatnonzero(np.isfinite(X).all(axis=1))
    # Queries in blocks: the neighbourhoods' design matrices take ~14 kB per sample, which
    # a texel reduction (T x P samples) would otherwise hold all at once; each sample's
    # fit is its own, so the result is the same block by block.
    for b0 in range(0, len(q_all), _GRADIENT_BLOCK):
        q = q_all[b0 : b0 + _GRADIENT_BLOCK]
        out[q] = _local_fits(X, logf, tree, pool, q, kk, ridge, curvature_ridge)
    if isotropic:
        # d log f / dX = (d log f / dY) dY/dX: the modes are in the projected chart
        return np.einsum("ncy,nyx->ncx", out, isotropic_jacobian(wi, wo))
    return out


#: Samples whose neighbourhood fits :func:`local_log_gradient` solves at a time.
_GRADIENT_BLOCK = 4096


def _local_fits(
    X: Array,
    logf: Array,
    tree: Any,
    pool: NDArray[np.int64],
    q: NDArray[np.int64],
    kk: int,
    ridge: float,
    curvature_ridge: float,
) -> Array:
    """(Q, C, d) gradients of the queries ``q`` over the d features of ``X`` (see
    :func:`local_log_gradient`)."""
    d = X.shape[1]
    dist, idx = tree.query(X[q], k=kk)
    nb = pool[idx]  # (Q, k)
    h = dist[:, -1] * 1.0001 + 1e-12
    w = (1.0 - (dist / h[:, None]) ** 3) ** 3  # tricube
    D = (X[nb] - X[q][:, None, :]) / h[:, None, None]  # (Q, k, d), scaled to the radius
    quad = [D[..., a] * D[..., b] for a in range(d) for b in range(a, d)]
    A = np.stack([np.ones(D.shape[:2]), *np.moveaxis(D, -1, 0), *quad], axis=-1)
    AtW = A.transpose(0, 2, 1) * w[:, None, :]
    normal = AtW @ A  # (Q, 1 + d + d(d+1)/2, ...)
    reg = np.zeros(A.shape[-1])
    reg[1 : 1 + d] = ridge
    reg[1 + d :] = curvature_ridge
    normal += w.sum(axis=1)[:, None, None] * np.diag(reg)
    rhs = AtW @ logf[nb]  # (Q, 1 + d + d(d+1)/2, C)
    if ridge > 0 and curvature_ridge > 0:  # positive definite: a direct solve (5x faster)
        beta = np.linalg.solve(normal, rhs)
    else:
        # the pseudo-inverse: a neighbourhood that spans fewer directions than the
        # features gets the minimum-norm slope there, not an error
        beta = np.linalg.pinv(normal) @ rhs
    return beta[:, 1 : 1 + d, :].transpose(0, 2, 1) / h[:, None, None]


def geometry_std(brdf: Array, gradient: Array, modes: Array) -> Array:
    """The marginal geometric std of each sample, 1/sr: ``f sqrt(sum_j (g . dX_j)^2)``.

    Parameters
    ----------
    brdf
        (N, C) f_r, 1/sr.
    gradient
        (N, C, 4) ``d log f / dX`` (:func:`local_log_gradient`).
    modes
        (N, M, 6) the samples' mode perturbations of ``(wi, wo)``.

    Returns
    -------
    ndarray
        (N, C), 0 where the gradient is unknown (NaN) but the sample is finite.
    """
    dX = np.asarray(modes, float)[..., [0, 1, 3, 4]]  # (N, M, 4)
    g = np.nan_to_num(np.asarray(gradient, float))
    dlog = np.einsum("ncf,nmf->ncm", g, dX)
    return np.abs(np.asarray(brdf, float)) * np.sqrt(np.sum(dlog**2, axis=2))


# ------------------------------------------------------------------ reporting
def budget_rows(
    budget: Mapping[str, Array],
    brdf: Array,
    usable: NDArray[np.bool_] | None = None,
    shared: Mapping[str, Sequence[float]] | None = None,
) -> list[dict[str, Any]]:
    """The budget's terms, largest first: median relative std and share of the variance.

    Parameters
    ----------
    budget
        Term -> (N, C) std, 1/sr.
    brdf
        (N, C) f_r, 1/sr.
    usable
        (N,) samples to summarise (default: all with finite, positive f).
    shared
        Shared term -> (C,) relative std (listed after the per-sample terms, their share
        taken of the same total at the median sample).

    Returns
    -------
    list of dict
        ``{"term", "median_rel_std", "share", "scope"}``: the median over samples and
        channels of ``std / f``, and the term's share of the summed relative variance
        (over the usable samples and channels; a shared term counts once per value);
        None where no sample is usable.
    """
    f = np.asarray(brdf, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = {t: np.asarray(v, float) / f for t, v in budget.items()}
    sel = np.isfinite(f).all(axis=1) & (f > 0).all(axis=1)
    if usable is not None:
        sel &= np.asarray(usable, bool)
    for v in rel.values():
        sel &= np.isfinite(v).all(axis=1)
    rows = []
    var = {t: float(np.sum(v[sel] ** 2)) for t, v in rel.items()}
    n = max(int(sel.sum()) * f.shape[1], 1)
    shared_var = {t: float(np.sum(np.square(v))) / f.shape[1] for t, v in (shared or {}).items()}
    total = sum(var.values()) + sum(shared_var.values()) * n
    for t, v in rel.items():
        rows.append(
            {
                "term": t,
                "median_rel_std": float(np.median(v[sel])) if sel.any() else math.nan,
                "share": var[t] / total if total > 0 else math.nan,
                "scope": "sample",
            }
        )
    for t, v in (shared or {}).items():
        rows.append(
            {
                "term": t,
                "median_rel_std": float(np.median(np.asarray(v, float))),
                "share": shared_var[t] * n / total if total > 0 else math.nan,
                "scope": "shared",
            }
        )
    rows.sort(key=lambda r: -(r["share"] if np.isfinite(r["share"]) else -1.0))
    for r in rows:  # reduction.json is strict JSON: no NaN
        for key in ("median_rel_std", "share"):
            if not np.isfinite(r[key]):
                r[key] = None
    return rows


#: The columns of a budget term's row, as :func:`budget_cells` fills them.
BUDGET_COLUMNS = ("term", "scope", "median std / f", "share of variance")


def budget_cells(row: Mapping[str, Any]) -> tuple[str, str, str, str]:
    """One term of :func:`budget_rows` as the text of :data:`BUDGET_COLUMNS` (the CLI's
    table and the demo's report print the same)."""
    med = row.get("median_rel_std")
    return (
        str(row["term"]),
        str(row.get("scope", "")),
        "-" if med is None else f"{med:.3%}",
        f"{row['share']:.1%}",
    )


def budget_table(rows: Sequence[Mapping[str, Any]], *, top: int = 6) -> Any:
    """A ``rich`` table of the budget's largest terms (:func:`budget_rows`, as stored in
    ``reduction.json["budget"]["terms"]``): term, scope, median relative std, share of
    the variance; terms with no share are left out."""
    from rich.table import Table

    table = Table(title="Uncertainty budget (largest terms)")
    for k, col in enumerate(BUDGET_COLUMNS):
        table.add_column(col, justify="right" if k >= 2 else "left")
    shown = [r for r in rows if r.get("share") and r["share"] > 0][:top]
    if not shown:
        table.caption = "no usable sample"
    for r in shown:
        table.add_row(*budget_cells(r))
    return table

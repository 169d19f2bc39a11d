"""One pose's measurement: camera pose, regions, merged radiance per region, flags.

:func:`measure_pose` finds the holder's ChArUco board in the best-exposed frame and takes
the camera pose from it or from the rig's report (``[reduction] geometry``: board, rig, or
auto, the board where it is trustworthy, else the rig), maps the sample's central area onto
``grid x grid`` regions, merges the bracket with inverse-variance weights, and sums each
region per CFA channel with Bayer-centred weights (:mod:`gonio.capture.bayer`).  The sums
come from the fused numba kernel (:mod:`gonio.capture.pose_kernel`) when it can run, else
from :func:`_pose_sums_numpy`, its reference; :attr:`PoseMeasurement.kernel` says which.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from gonio.capture.bayer import bayer_region_entries, masked_site_shares, site_stencils
from gonio.capture.calibration import irradiance_geometry
from gonio.capture.fiducials import (
    CameraPose,
    RegionMap,
    angle_between,
    detect_pose_in_frame,
    edge_margins,
    has_distortion,
    map_regions,
    roi_geometry,
    spread_margins,
    undistorted_coordinates,
)
from gonio.capture.hdr import check_bracket, merge_bracket
from gonio.capture.raw import CHANNELS, RawFrame
from gonio.capture.reduction_config import ReductionSetup
from gonio.errors import ReductionError

__all__ = [
    "GeometrySource",
    "PoseMeasurement",
    "board_obliquity_deg",
    "detect_board",
    "invalid_pose",
    "measure_pose",
    "region_margins",
]

#: Where a pose's camera geometry came from (:attr:`PoseMeasurement.geometry_source`).
GeometrySource = Literal["board", "rig", "none"]


@dataclass
class PoseMeasurement:
    """Per-region measurements of one pose.

    Attributes
    ----------
    pose, kind
        Journal pose index and kind (``"sample"`` or ``"reference"``).
    wi, wo
        (n, 3) measured directions per region (sample frame).
    radiance, radiance_var
        (n, 3) mean relative radiance per region and channel, and its variance.
    geometry
        (n, 3) mean of ``G(x)`` (irradiance from a unit-radiance light) over the same pixels.
    ratio, ratio_var
        (n, 3) mean of ``L(x) / G(x)`` and its variance (for reference poses).
    flags
        (n,) :class:`gonio.dataset.Flag` bits.
    reasons
        Per region, the reasons for its flags.
    frames
        Files of the bracket.
    camera
        The camera pose the regions were mapped with (the board's or the rig's: see
        ``geometry_source``), None for no measurement.
    regions
        The :class:`RegionMap` (pixel sets), for inspection and tests.
    kernel
        Which path computed the region sums: ``"numba"`` (the fused kernel,
        :mod:`gonio.capture.pose_kernel`), ``"numpy"`` (its reference,
        :func:`_pose_sums_numpy`), or ``"none"`` (no measurement: :func:`invalid_pose`).
    geometry_source
        Where the camera pose of the regions came from: ``"board"`` (the holder's
        ChArUco board in this pose's frames), ``"rig"`` (the rig's read-back pose through
        its kinematics, calibrated when the session's rig is) or ``"none"`` (no
        measurement: :func:`invalid_pose`); see ``[reduction] geometry``.
    n_pixels
        (n,) pixels of each region (None for :func:`invalid_pose`).
    n_sites
        (n, 3) each region's effective number of CFA sites per channel,
        ``(sum w)^2 / sum w^2`` over its Bayer weights (masked sites left out), NaN where
        a region has none: :func:`gonio.capture.radiometric.effective_sites`' number,
        summed by the pose's own pass (None for :func:`invalid_pose`).
    radiometric_rel_std
        The radiometric budget terms of each region, relative standard uncertainties of
        the BRDF, (n, 3) per term: ``drift``, ``flat``, ``dark``, ``irradiance``,
        ``stray`` (a missing key is 0).  Filled by the reduction after the light scale
        (:func:`gonio.capture.radiometric.radiometric_terms`); empty from
        :func:`measure_pose`.
    """

    pose: int
    kind: str
    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    radiance: NDArray[np.float64]
    radiance_var: NDArray[np.float64]
    geometry: NDArray[np.float64]
    ratio: NDArray[np.float64]
    ratio_var: NDArray[np.float64]
    flags: NDArray[np.uint32]
    reasons: list[list[str]]
    frames: tuple[str, ...]
    camera: CameraPose | None = None
    regions: RegionMap | None = None
    kernel: Literal["numba", "numpy", "none"] = "none"
    geometry_source: GeometrySource = "none"
    n_pixels: NDArray[np.float64] | None = None
    n_sites: NDArray[np.float64] | None = None
    radiometric_rel_std: dict[str, NDArray[np.float64]] = field(default_factory=dict)


def _flag(name: str) -> int:
    from gonio.dataset import Flag  # h5py only when measuring

    return int(Flag[name])


def _detection_frame(frames: list[RawFrame]) -> RawFrame:
    """The longest exposure with (almost) nothing saturated: the best-exposed board."""
    by_exp = sorted(frames, key=lambda f: f.exposure_factor())
    # longest first, stopping at the first good one (the estimate costs a pass per frame)
    return next((f for f in reversed(by_exp) if f.saturated_fraction() < 0.02), by_exp[0])


def reported_pose(reported_camera: Any, rms: float = math.nan, n_corners: int = 0) -> CameraPose:
    """The rig's reported camera ``(position, world-to-camera rotation)`` as a CameraPose
    (``rms`` and ``n_corners``: the board's, carried for the record)."""
    C, R = (np.asarray(x, float) for x in reported_camera)
    return CameraPose(R, -R @ C, C, rms, n_corners)


def measure_pose(
    frames: list[RawFrame],
    setup: ReductionSetup,
    light_position: NDArray[np.float64],
    light_normal: NDArray[np.float64] | None,
    *,
    pose: int = 0,
    kind: str = "sample",
    reported_wo: NDArray[np.float64] | None = None,
    reported_camera: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    dark_variance: float | NDArray[np.float64] = 0.0,
    pixel_mask: NDArray[np.bool_] | None = None,
    detected: CameraPose | ReductionError | None = None,
) -> PoseMeasurement:
    """Measure one pose's bracket: camera pose, regions, merged radiance per region.

    Parameters
    ----------
    frames
        The pose's decoded (dark-subtracted) frames.
    setup
        Camera, board, sample and noise facts.
    light_position, light_normal
        The light's centre and emitting normal in the sample frame (from the rig), metres.
    pose, kind
        Journal pose index and kind, carried into the result.
    reported_wo
        The rig's reported direction to the camera (sample frame), for the geometry check.
    reported_camera
        The rig's reported camera ``(position, world-to-camera rotation)``: the geometry
        with ``setup.geometry = "rig"``, and with ``"auto"`` where the board is not found,
        shows too few corners or is seen too obliquely; with ``"board"`` the fallback
        when the board cannot be seen (the samples are then flagged GEOMETRY_MISMATCH).
    dark_variance
        Variance (DN^2) added by the subtracted master dark.
    pixel_mask
        (H, W) hot or dead pixels (from the master darks and flat): their sites weigh 0
        in every region's sums, in both paths; None for none.  The light's ``cos^n``
        radiance profile in G is ``setup.light_profile_n``.
    detected
        What :func:`detect_board` gave for these frames and ``reported_camera``, computed
        ahead (the reduction runs it in the thread that decodes the frames); None: it is
        run here.  The result is the same either way.

    Raises
    ------
    ReductionError
        When neither the board nor a reported camera pose gives the geometry.
    """
    cam, pose_flags, pose_reasons, source = _camera_pose(
        frames, setup, reported_wo, reported_camera, detected
    )
    lp = np.asarray(light_position, float)
    ln = None if light_normal is None else np.asarray(light_normal, float)
    fused = _fused_kernel() if all(f.raw is not None for f in frames) else None
    mask = _checked_mask(pixel_mask, frames[0])
    if fused is not None:
        regions, sums, dirs = _pose_sums_fused(
            fused, frames, setup, cam, lp, ln, dark_variance, mask
        )
        kernel: Literal["numba", "numpy"] = "numba"
    else:
        regions, sums, dirs = _pose_sums_numpy(frames, setup, cam, lp, ln, dark_variance, mask)
        kernel = "numpy"
    k, s_L, s_Lv, s_G, s_Q, s_Qv, s_sat, s_k2 = np.moveaxis(sums, -1, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        # effective_sites' number, from the same weights (dyadic: exact in any order)
        n_sites = np.where(s_k2 > 0, k * k / s_k2, np.nan)
        L = s_L / k
        Lv = s_Lv / k**2
        G = s_G / k
        Q = s_Q / k
        Qv = s_Qv / k**2
    any_sat = s_sat > 0
    for arr in (L, Lv, G, Q, Qv):
        arr[any_sat | (k == 0)] = np.nan
    npx, wi, wo = dirs[:, 0], dirs[:, 1:4].copy(), dirs[:, 4:7].copy()
    flags, reasons = _region_flags(npx, any_sat, L, Lv, setup.min_snr, pose_flags, pose_reasons)
    with np.errstate(invalid="ignore", divide="ignore"):  # empty regions: NaN, flagged
        wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    _horizon_flags(wi, lp, setup, npx, flags, reasons)
    names = tuple(f.name for f in frames)
    return PoseMeasurement(
        pose,
        kind,
        wi,
        wo,
        L,
        Lv,
        G,
        Q,
        Qv,
        flags,
        reasons,
        names,
        cam,
        regions,
        kernel,
        source,
        npx,
        n_sites=n_sites,
    )


def _checked_mask(mask: NDArray[np.bool_] | None, frame: RawFrame) -> NDArray[np.bool_] | None:
    """The pixel mask as a boolean array of the frame's size; None when it masks nothing
    (so a session without hot pixels is reduced exactly as without a mask)."""
    if mask is None:
        return None
    m = np.asarray(mask, dtype=bool)
    if m.shape != frame.shape:
        raise ReductionError(f"{frame.name}: pixel mask is {m.shape}, frame is {frame.shape}")
    return m if m.any() else None


def detect_board(
    frames: list[RawFrame],
    setup: ReductionSetup,
    reported_camera: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
) -> CameraPose | ReductionError:
    """The board's camera pose in the bracket's best-exposed frame, or the
    :class:`ReductionError` saying why there is none (returned, not raised, so that it
    can be computed ahead in another thread and handed to :func:`measure_pose`).

    Reads only the frames' raw mosaics (not their dark or flat corrections), so the
    frames may be given before those are applied.
    """
    det = _detection_frame(frames)
    expected = None if reported_camera is None else reported_pose(reported_camera)
    try:
        return detect_pose_in_frame(det, setup.board, setup.K, setup.dist, expected=expected)
    except ReductionError as exc:
        return exc


def _camera_pose(
    frames: list[RawFrame],
    setup: ReductionSetup,
    reported_wo: NDArray[np.float64] | None,
    reported_camera: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    detected: CameraPose | ReductionError | None = None,
) -> tuple[CameraPose, int, list[str], GeometrySource]:
    """The pose's camera by ``setup.geometry``: ``(camera, flags, reasons, source)``, the
    flags and reasons shared by every region of the pose, ``source`` ``"board"`` or
    ``"rig"``.

    - ``"board"``: the board's pose, checked against the rig's report; without a board
      the rig's pose, flagged GEOMETRY_MISMATCH.
    - ``"rig"``: the rig's pose, checked by the board when one is found.
    - ``"auto"``: the board's pose (checked against the rig's) when the board is
      trustworthy -- found with at least ``min_board_corners`` corners and seen at most
      ``max_board_obliquity_deg`` off its normal -- else the rig's pose, not flagged: a
      view that shows too little of the board says nothing against the rig.

    Without a reported camera pose the board is the only source (refused without one).
    """
    if detected is None:
        detected = detect_board(frames, setup, reported_camera)
    cam: CameraPose | None = None
    lost = ""
    if isinstance(detected, ReductionError):
        if reported_camera is None:
            raise detected
        lost = str(detected)
    else:
        cam = detected
    if reported_camera is None:
        assert cam is not None
        return cam, 0, [], "board"
    rig = reported_pose(
        reported_camera,
        math.nan if cam is None else cam.reprojection_rms,
        0 if cam is None else cam.n_corners,
    )
    mode = setup.geometry
    if mode == "auto" and cam is not None and not board_trusted(cam, setup):
        cam = None
    if cam is None:
        if mode == "board":
            why = f"board not found ({lost}); the rig's camera pose was used"
            return rig, _flag("GEOMETRY_MISMATCH"), [why], "rig"
        return rig, 0, [], "rig"
    flags, reasons = _board_vs_rig(cam, setup, reported_wo, reported_camera)
    if mode == "rig":
        return rig, flags, reasons, "rig"
    return cam, flags, reasons, "board"


def board_obliquity_deg(cam: CameraPose) -> float:
    """Angle (deg) between the board's normal (the sample's +z) and the direction from
    the sample's centre to the camera, by the board's own pose: its theta_o."""
    p = np.asarray(cam.position, float)
    return math.degrees(math.atan2(math.hypot(p[0], p[1]), p[2]))


def board_trusted(cam: CameraPose, setup: ReductionSetup) -> bool:
    """Whether ``geometry = "auto"`` takes this board pose over the rig's."""
    return (
        cam.n_corners >= setup.min_board_corners
        and board_obliquity_deg(cam) <= setup.max_board_obliquity_deg
    )


def _board_vs_rig(
    cam: CameraPose,
    setup: ReductionSetup,
    reported_wo: NDArray[np.float64] | None,
    reported_camera: tuple[NDArray[np.float64], NDArray[np.float64]],
) -> tuple[int, list[str]]:
    """GEOMETRY_MISMATCH and its reasons when the board's camera and the rig's disagree
    by more than the tolerances (direction, position)."""
    flags = 0
    reasons: list[str] = []
    if reported_wo is not None:
        ang = math.degrees(
            float(
                angle_between(
                    cam.position / np.linalg.norm(cam.position), np.asarray(reported_wo, float)
                )
            )
        )
        if ang > setup.geometry_tolerance_deg:
            flags |= _flag("GEOMETRY_MISMATCH")
            reasons.append(
                f"camera direction from the board is {ang:.2f} deg from the rig's report "
                f"(tolerance {setup.geometry_tolerance_deg} deg)"
            )
    dpos = float(np.linalg.norm(cam.position - np.asarray(reported_camera[0], float)))
    if dpos > setup.position_tolerance_m:
        flags |= _flag("GEOMETRY_MISMATCH")
        reasons.append(
            f"camera position from the board is {dpos * 1e3:.1f} mm from the rig's "
            f"report (tolerance {setup.position_tolerance_m * 1e3:g} mm)"
        )
    return flags, reasons


#: The largest inner margin region_margin_px may take on each side, as a fraction of the
#: cell: a third leaves the central third of a region seen at grazing incidence.
MAX_MARGIN_FRACTION = 1 / 3


def region_margins(
    cam: CameraPose, light_position: NDArray[np.float64], setup: ReductionSetup
) -> tuple[float, float]:
    """The margins inside each region (metres along x, y) that keep its spread of
    directions, from the camera and from the light, within
    ``setup.max_region_spread_deg`` (:func:`gonio.capture.fiducials.spread_margins`;
    none when it is None), and at least ``setup.region_margin_px`` image pixels clear of
    the boundaries between regions (:func:`gonio.capture.fiducials.edge_margins`, at
    most :data:`MAX_MARGIN_FRACTION` of the cell)."""
    hw = 0.5 * setup.roi_fraction * setup.sample_size[0]
    hh = 0.5 * setup.roi_fraction * setup.sample_size[1]
    gx, gy = setup.grid_xy
    cell = (2 * hw / gx, 2 * hh / gy)
    margins = (0.0, 0.0)
    if setup.max_region_spread_deg is not None:
        margins = spread_margins(
            [cam.position, light_position], cell, (hw, hh), setup.max_region_spread_deg
        )
    if setup.region_margin_px > 0 and (gx > 1 or gy > 1):
        # metres that region_margin_px image pixels span on the sample, per axis (the
        # foreshortened axis needs more); capped so that an oblique region a few pixels
        # across keeps its central part rather than vanishing
        px = edge_margins(cam, setup.K, setup.sample_size, (hw, hh), setup.region_margin_px)
        margins = tuple(
            max(m, min(p, MAX_MARGIN_FRACTION * c) if n > 1 else 0.0)
            for m, p, c, n in zip(margins, px, cell, (gx, gy), strict=True)
        )
    return margins


def _horizon_flags(
    wi: NDArray[np.float64],
    lp: NDArray[np.float64],
    setup: ReductionSetup,
    npx: NDArray[np.float64],
    flags: NDArray[np.uint32],
    reasons: list[list[str]],
) -> None:
    """Flag SHADOWED (in place, with the reason) the regions whose light is not wholly
    above their horizon.

    ``G(x)`` clips the light at the horizon by its centre only (``max(cos theta_i, 0)``:
    a light below it gives nothing, a disk across it is counted whole), so a region
    whose light's centre is less than the disk's angular radius above its horizon
    (theta_i within ``asin(r / d)`` of 90 deg: 0.23 deg for a 2 mm disk at 0.5 m) would
    get an irradiance that is silently wrong, and one below it none at all (an
    infinite BRDF).  ``d`` is taken as the light's distance from the sample's nearest
    point (the radius' largest angle).
    """
    r = float(setup.light_radius or 0.0)
    d = float(np.linalg.norm(lp)) - 0.5 * math.hypot(*setup.sample_size)
    ang = math.asin(min(1.0, r / d)) if d > 0 else 0.5 * math.pi
    with np.errstate(invalid="ignore"):
        elev = np.degrees(np.arcsin(np.clip(wi[:, 2], -1.0, 1.0)))
    for j in np.flatnonzero((npx > 0) & ~(elev > math.degrees(ang))):
        flags[j] |= _flag("SHADOWED")
        reasons[j].append(
            f"the light is {elev[j]:.3f} deg above the region's horizon, within its "
            f"angular radius {math.degrees(ang):.3f} deg: part of it (or all) is below "
            "the horizon, where the irradiance model does not hold"
        )


def _region_flags(
    npx: NDArray[np.float64],
    any_sat: NDArray[np.bool_],
    L: NDArray[np.float64],
    Lv: NDArray[np.float64],
    min_snr: float,
    pose_flags: int,
    pose_reasons: list[str],
) -> tuple[NDArray[np.uint32], list[list[str]]]:
    """Each region's flags and reasons: the pose's, plus no pixels, saturation in every
    frame, and a signal-to-noise ratio below ``min_snr``."""
    n, nc = len(npx), len(CHANNELS)
    flags = np.full(n, pose_flags, dtype=np.uint32)
    reasons = [list(pose_reasons) for _ in range(n)]
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = L / np.sqrt(Lv)
    for j in range(n):
        if npx[j] == 0:
            flags[j] |= _flag("INVALID")
            reasons[j].append("region has no pixels in the image")
            continue
        for c in np.flatnonzero(any_sat[j]):
            flags[j] |= _flag("SATURATED")
            reasons[j].append(f"{CHANNELS[c]} saturated in every frame of the bracket")
        low = [c for c in range(nc) if snr[j, c] < min_snr]
        if low:
            flags[j] |= _flag("UNDEREXPOSED")
            txt = ", ".join(f"{CHANNELS[c]} {snr[j, c]:.1f}" for c in low)
            reasons[j].append(f"signal-to-noise below {min_snr:g} ({txt})")
    return flags, reasons


def _pose_sums_numpy(
    frames: list[RawFrame],
    setup: ReductionSetup,
    cam: CameraPose,
    lp: NDArray[np.float64],
    light_normal: NDArray[np.float64] | None,
    dark_variance: float | NDArray[np.float64],
    mask: NDArray[np.bool_] | None = None,
) -> tuple[RegionMap, NDArray[np.float64], NDArray[np.float64]]:
    """The regions of a pose, their weighted sums per channel and their direction sums.

    Returns ``(regions, sums, dirs)``: ``sums`` (n, 3, 8) holds per region and channel the
    sums of w, w L, w^2 var(L), w G, w L / G, w^2 var(L) / G^2, w over saturated sites
    and w^2 (w the Bayer weights, :func:`bayer_region_weights`); ``dirs`` (n, 7) the pixel count
    and the sums of the per-pixel unit vectors to the light and to the camera.  The
    reference implementation of :mod:`gonio.capture.pose_kernel`.
    """
    regions = map_regions(
        cam,
        setup.K,
        frames[0].shape,
        setup.sample_size,
        roi_fraction=setup.roi_fraction,
        grid=setup.grid_xy,
        dist=setup.dist,
        inner_margin=region_margins(cam, lp, setup),
    )
    merged = merge_bracket(frames, setup.noise, dark_variance, region=regions.box, mask=mask)
    n, nc = regions.n_regions, len(CHANNELS)
    # flat indices of the ROI's pixels, found once (each boolean-mask index searches again)
    inside = np.flatnonzero(regions.label >= 0)

    def at(a: NDArray) -> NDArray:
        return a.reshape(-1)[inside]

    lab = at(regions.label)
    # Each region and channel is a weighted mean over that channel's CFA sites whose
    # weighted centroid is the region's own pixel centroid (see bayer_region_weights):
    # the directions below are that centroid's, so R and B (whose sites sit half a pixel
    # off it) would otherwise be measured at other directions than reported.
    site, row, wt = bayer_region_entries(regions.label, merged.channel, n)
    if mask is not None:  # hot/dead pixels: their weights go to their channel's neighbours
        site, row, wt = masked_site_shares(site, row, wt, mask[regions.box], merged.channel)

    def on(a: NDArray) -> NDArray:
        return a.reshape(-1)[site]

    def region_sum(x: NDArray) -> NDArray:
        return np.bincount(row, x, minlength=n * nc).reshape(n, nc)

    vign = on(regions.vignetting)
    val = on(merged.value) / vign
    var = on(merged.variance) / vign**2
    sat = on(merged.saturated) | ~np.isfinite(val)
    pts = np.stack([on(a) for a in regions.xyz], axis=-1)
    # G(x): a Lambertian disk of radius r whose axis passes through x gives exactly
    # E = pi L sin^2(a) cos(theta), sin^2(a) = r^2 / (r^2 + d^2): the small-source law
    # (pi r^2 L cos(theta) cos(theta') / d^2) times d^2 / (d^2 + r^2).  The rig aims the
    # light at the sample centre; off that axis the correction changes by < 1e-4 over a
    # 5 cm sample at 0.5 m (checked against the exact rim integral in the tests).
    g = irradiance_geometry(pts, lp, light_normal)
    to_light_u = [lp[a] - pts[:, a] for a in range(3)]
    d2u = to_light_u[0] ** 2 + to_light_u[1] ** 2 + to_light_u[2] ** 2
    if light_normal is not None and setup.light_profile_n != 0.0:
        # the emitted radiance's cos^n(psi), psi the emission's angle off the normal
        ln_ = np.asarray(light_normal, float)
        cos_e = -(to_light_u[0] * ln_[0] + to_light_u[1] * ln_[1] + to_light_u[2] * ln_[2])
        cos_psi = np.maximum(cos_e, 0.0) / (np.sqrt(d2u) * np.linalg.norm(ln_))
        g = g * cos_psi**setup.light_profile_n
    if setup.light_radius:
        g = g * (np.pi * setup.light_radius**2) * d2u / (d2u + setup.light_radius**2)
    val = np.where(sat, 0.0, val)
    var = np.where(sat, 0.0, var)
    wt2 = wt * wt
    with np.errstate(invalid="ignore", divide="ignore"):
        cols = (wt, wt * val, wt2 * var, wt * g, wt * val / g, wt2 * var / g**2, wt * sat, wt2)
    sums = np.stack([region_sum(x) for x in cols], axis=-1, dtype=float)
    # directions: mean over the region's pixels of the per-pixel unit vectors to the light
    # and to the camera, one component at a time (sums over a trailing axis of 3 are slow)
    xyz = [at(a) for a in regions.xyz]

    def direction_sum(to: NDArray) -> list[NDArray]:
        v = [to[a] - xyz[a] for a in range(3)]
        inv = 1.0 / np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        return [np.bincount(lab, v[a] * inv, minlength=n) for a in range(3)]

    dirs = np.stack(
        [
            np.bincount(lab, minlength=n),
            *direction_sum(lp),
            *direction_sum(regions.camera_position),
        ],
        axis=1,
        dtype=float,  # bincount of no pixels at all gives integers
    )
    return regions, sums, dirs


_numba_broken = False


def _fused_kernel() -> Any | None:
    """:func:`gonio.capture.pose_kernel.pose_sums`, or None (the numpy path) when
    ``GONIO_NUMBA=0`` or numba cannot load here."""
    global _numba_broken
    if _numba_broken or os.environ.get("GONIO_NUMBA") == "0":
        return None
    try:
        from gonio.capture.pose_kernel import pose_sums
    except ImportError as exc:  # a broken numba/llvmlite install: slower, not wrong
        import warnings

        warnings.warn(f"numba unavailable ({exc}); reducing with the numpy path", stacklevel=2)
        _numba_broken = True
        return None
    return pose_sums


def _pose_sums_fused(
    kernel: Any,
    frames: list[RawFrame],
    setup: ReductionSetup,
    cam: CameraPose,
    lp: NDArray[np.float64],
    light_normal: NDArray[np.float64] | None,
    dark_variance: float | NDArray[np.float64],
    mask: NDArray[np.bool_] | None = None,
) -> tuple[RegionMap, NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_pose_sums_numpy` in one pass of :mod:`gonio.capture.pose_kernel`."""
    from gonio.capture import pose_kernel as pk

    check_bracket(frames)
    ref = frames[0]
    roi = roi_geometry(
        cam,
        setup.K,
        ref.shape,
        setup.sample_size,
        roi_fraction=setup.roi_fraction,
        grid=setup.grid_xy,
        dist=setup.dist,
        inner_margin=region_margins(cam, lp, setup),
    )
    box = roi.box
    r0, c0 = box[0].start, box[1].start
    frames = sorted(frames, key=lambda f: f.exposure_factor())  # merge_bracket's order

    # a (2, 2) cell as seen from the crop origin: np.roll by (-(r0 % 2), -(c0 % 2)), by
    # indexing (np.roll costs 15 us a call, a dozen calls a pose)
    phase = np.ix_([r0 % 2, 1 - r0 % 2], [c0 % 2, 1 - c0 % 2])

    def crop_cell(cell: NDArray) -> NDArray:
        return np.asarray(cell, float)[phase]

    def stack(key: str) -> NDArray:
        if all(f.extra.get(key) is None for f in frames):
            return np.zeros((len(frames), 0, 0))
        return np.stack(
            [
                np.zeros(ref.shape)[box] if f.extra.get(key) is None else f.extra[key][box]
                for f in frames
            ]
        )

    gains = stack("_gain")
    if gains.size and any(f.extra.get("_gain") is None for f in frames):
        gains[[f.extra.get("_gain") is None for f in frames]] = 1.0
    models = [setup.noise.at_iso(f.iso) for f in frames]
    dv = np.asarray(dark_variance, dtype=np.float64)
    st_n = np.zeros(4, np.int64)
    st = np.zeros((3, 4, 9))
    cell = crop_cell(ref.cell_channel).astype(np.int64)
    for (y0, x0), entries in site_stencils(cell, len(CHANNELS)).items():
        st_n[2 * y0 + x0] = len(entries)
        for t, e in enumerate(entries):
            st[:, 2 * y0 + x0, t] = e
    K = np.asarray(setup.K, float)
    dist = np.asarray(setup.dist, float) if has_distortion(setup.dist) else None
    if dist is not None:  # once per pose: the kernel reads each pixel's ray from these
        ray_x, ray_y = undistorted_coordinates(K, dist, box)
    else:
        ray_x = ray_y = np.zeros((0, 0))
    hw, hh = roi.half_size
    bracket = pk.Bracket(
        raws=np.stack([f.raw[box] for f in frames]),
        black=np.stack([crop_cell(f.cell_black) for f in frames]),
        sat_level=np.stack([crop_cell(f.cell_saturation) for f in frames]),
        offset=stack("_offset"),
        gain=gains,
        expo=np.array([f.exposure_factor() for f in frames]),
        noise_gain=np.array([m.gain for m in models]),
        noise_read2=np.array([m.read_noise**2 for m in models]),
        noise_quant=1.0 / 12.0 if setup.noise.quantisation else 0.0,
        # contiguous: a layout is part of numba's argument type (a slice is "A"), and
        # each layout would be a compilation of its own (~7 s cold)
        dark_var=np.ascontiguousarray(dv[box]) if dv.ndim == 2 else np.zeros((0, 0)),
        dark_var0=float(dv) if dv.ndim != 2 else 0.0,
        mask=np.ascontiguousarray(mask[box]) if mask is not None else np.zeros((0, 0), bool),
    )
    stencils = pk.Stencils(
        cell_channel=cell,
        size=st_n,
        dy=st[0].astype(np.int64),
        dx=st[1].astype(np.int64),
        weight=st[2],
    )
    view = pk.View(
        cam=np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
        rot=np.ascontiguousarray(cam.rotation, float),
        cpos=np.asarray(cam.position, float),
        r0=int(r0),
        c0=int(c0),
        roi=np.array([hw, hh, *roi.cell, *roi.limit, *roi.inner_margin]),
        grid=int(roi.grid_xy[0]),
        grid_y=int(roi.grid_xy[1]),
        light=lp,
        light_normal=np.zeros(3) if light_normal is None else light_normal,
        has_normal=light_normal is not None,
        light_radius=float(setup.light_radius or 0.0),
        profile_n=float(setup.light_profile_n),
        n_channels=len(CHANNELS),
        ray_x=ray_x,
        ray_y=ray_y,
        undistorted=dist is not None,
    )
    label, sums, dirs, mom = kernel(bracket, stencils, view)
    regions = RegionMap(box, label, roi.grid_xy[0] * roi.grid_xy[1], roi.centers, cam, K, dist=dist)
    # region_moments' centroids and covariances from the kernel's sums, with its divisions
    # (the aperture correction needs them: without, it computes the crop's rays again)
    cnt = dirs[:, pk.DIR_N]
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = mom[:, pk.MOM_X] / cnt, mom[:, pk.MOM_Y] / cnt
        sxx, sxy, syy = (mom[:, c] / cnt for c in (pk.MOM_XX, pk.MOM_XY, pk.MOM_YY))
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    regions.extra["moments"] = (np.stack([mx, my], -1), cov)
    return regions, sums, dirs


def invalid_pose(
    p: int, wi: NDArray, wo: NDArray, why: str, frames: tuple[str, ...]
) -> PoseMeasurement:
    """A sample pose that gave no measurement: one INVALID sample at the rig's directions,
    ``why`` its reason."""
    nan3 = np.full((1, 3), np.nan)
    return PoseMeasurement(
        p,
        "sample",
        wi[None, :],
        wo[None, :],
        nan3,
        nan3,
        nan3,
        nan3,
        nan3,
        np.array([_flag("INVALID")], np.uint32),
        [[why]],
        frames,
    )

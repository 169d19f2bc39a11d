"""The per-texel side of ``gonio capture reduce --texels N`` (issue 18, item 2).

A texel reduction is the ordinary per-pose reduction with its region grid made the
texel grid: ``nx x ny`` regions (``grid = nx``, ``grid_y = ny``) over the *whole* sample
(``roi_fraction = 1``), so every region is one texel of the :mod:`gonio.texels`
convention.  This module holds what differs:

* :func:`texel_setup` turns the reduction setup into that grid;
* :func:`texel_resolution` refuses a grid finer than the camera resolves: a texel must be
  at least :data:`MIN_TEXEL_PX` pixels across its narrower side at the best-resolving
  sample pose (the closest, most frontal view), before any frame is decoded;
* :func:`region_to_texel` maps the region order to the texel order.  The regions are
  numbered ``r = iy * nx + ix`` with ``iy`` counted from -y
  (:func:`gonio.capture.fiducials.map_regions`), the texels with row 0 at +y: region
  ``(iy, ix)`` is texel ``(ny - 1 - iy, ix)``, ``t = (ny - 1 - iy) nx + ix``;
* :func:`texel_arrays` scatters the reduction's samples (one per region and sample pose,
  in journal order) into ``(T, P, ...)`` arrays: a pose that gave no measurement (one
  INVALID sample) is INVALID with NaN for every texel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.capture.reduction_config import ReductionSetup
from gonio.dataset import BRDFSamples, Flag
from gonio.errors import ReductionError

__all__ = [
    "MAX_TEXEL_MODES_BYTES",
    "MIN_TEXEL_PX",
    "modes_omitted",
    "TexelResolution",
    "parse_texels",
    "region_to_texel",
    "texel_arrays",
    "texel_levelled",
    "texel_resolution",
    "texel_setup",
]

#: Largest geometry-mode array (T, P, M, 6) float64 a texel file takes, bytes.  The
#: modes are the largest part by far (M ~ 10: 480 bytes per texel and pose against ~150
#: for everything else); beyond this the texel file leaves them out, says so, and keeps
#: the geometry term they give (``budget/geometry``), so that a full-resolution grid does
#: not double the reduction's largest array in memory once more.
MAX_TEXEL_MODES_BYTES = 2**30

#: Fewest pixels across a texel's narrower side at the best-resolving pose.  A Bayer
#: mosaic samples each colour once per 2 x 2 cell: a texel narrower than 2 pixels would
#: not hold a whole cell, so its R, G and B would come from different places (or be
#: missing) even in the best view.
MIN_TEXEL_PX = 2.0


def parse_texels(text: str | int | Sequence[int]) -> tuple[int, int]:
    """``"N"`` or ``"NXxNY"`` (or an int, or a pair) as ``(nx, ny)``.

    Raises
    ------
    ReductionError
        Not of that form, or a count below 1 (the message quotes the value).
    """
    if isinstance(text, int):
        parts: list[Any] = [text, text]
    elif isinstance(text, str):
        s = text.strip().lower()
        parts = s.split("x") if "x" in s else [s, s]
    else:
        parts = list(text)
    try:
        if len(parts) != 2:
            raise ValueError
        nx, ny = (int(str(p).strip()) for p in parts)
    except ValueError:
        raise ReductionError(
            f"--texels: expected N or NXxNY (integers, e.g. 16 or 16x12), got {text!r}"
        ) from None
    if nx < 1 or ny < 1:
        raise ReductionError(f"--texels: the texel counts must be >= 1, got {nx}x{ny}")
    return nx, ny


#: Image pixels left out inside each texel along its boundaries: half a pixel of the
#: pixel's own footprint plus one of the Bayer interpolation's 3 x 3 stencil, the reach
#: of a neighbouring texel's radiance into a pixel counted in this one.  Without it the
#: texels next to a brighter neighbour read high and those next to a darker one low
#: (on 8 x 8 texels of examples/svbrdf_scene.toml's maps at 320 x 240: up to 5 % at the
#: highlight, 67 % of texels with every parameter within 3 sigma).
TEXEL_MARGIN_PX = 1.5


def texel_setup(setup: ReductionSetup, texels: tuple[int, int]) -> ReductionSetup:
    """The reduction setup whose region grid is the texel grid: ``nx x ny`` regions over
    the whole sample (``grid = nx``, ``grid_y = ny`` or None when square,
    ``roi_fraction = 1``, regions kept :data:`TEXEL_MARGIN_PX` clear of each other) and
    no aperture correction: :mod:`gonio.capture.aperture` reads the BRDF's curvature
    across the sample from each region's neighbours, which on a spatially varying sample
    are other materials (a texel next to a brighter one would be "corrected" towards
    it); a texel's own aperture bias stays uncorrected (on the 4 x 4 example, 1-2 % of f
    at the highlight between the texel's centre and its mean)."""
    nx, ny = (int(v) for v in texels)
    return setup.replace(
        grid=nx,
        grid_y=None if ny == nx else ny,
        roi_fraction=1.0,
        region_margin_px=max(setup.region_margin_px, TEXEL_MARGIN_PX),
        aperture_correction=False,
    )


def _counts(n: int | tuple[int, int]) -> tuple[int, int]:
    return (int(n), int(n)) if isinstance(n, int | np.integer) else (int(n[0]), int(n[1]))


def region_to_texel(n: int | tuple[int, int]) -> NDArray[np.int64]:
    """(nx * ny,) texel index of each region of an ``n x n`` (or ``(nx, ny)``) region
    grid (see module)."""
    nx, ny = _counts(n)
    iy, ix = np.divmod(np.arange(nx * ny), nx)
    return ((ny - 1 - iy) * nx + ix).astype(np.int64)


@dataclass(frozen=True)
class TexelResolution:
    """How many pixels a texel spans in the best-resolving sample pose.

    Attributes
    ----------
    pixels
        The texel's narrower side, pixels, at that pose (the sample's central texel,
        pinhole projection of its edge midpoints).
    pose
        Journal pose index of that pose.
    distance_m
        The camera's distance from the sample centre there, metres.
    closest_distance_m
        The smallest camera distance over the sample poses, metres.
    """

    pixels: float
    pose: int
    distance_m: float
    closest_distance_m: float

    def to_json(self) -> dict[str, Any]:
        return {
            "pixels_per_texel": round(self.pixels, 4),
            "pose": self.pose,
            "camera_distance_m": round(self.distance_m, 6),
            "closest_camera_distance_m": round(self.closest_distance_m, 6),
            "required_pixels": MIN_TEXEL_PX,
        }


def texel_resolution(
    setup: ReductionSetup,
    texels: tuple[int, int],
    cameras: Mapping[int, tuple[NDArray[np.float64], NDArray[np.float64]]],
) -> TexelResolution | None:
    """The texel's size in pixels at the best-resolving sample pose, and refusal below
    :data:`MIN_TEXEL_PX`.

    Parameters
    ----------
    setup
        The camera matrix ``K`` and ``sample_size`` (m).
    texels
        ``(nx, ny)``.
    cameras
        Sample pose -> (camera position (3,), world-to-camera rotation (3, 3)), sample
        frame, metres (the rig's report through its kinematics).

    Returns
    -------
    TexelResolution or None
        None when no pose's camera is known (the reduction then fails on its own terms).

    Raises
    ------
    ReductionError
        A texel narrower than :data:`MIN_TEXEL_PX` pixels even there; the message names
        the figure, the pose and the largest texel count the camera resolves.
    """
    if not cameras:
        return None
    nx, ny = texels
    w, h = setup.sample_size
    a, b = w / nx, h / ny
    K = np.asarray(setup.K, float)
    pts = np.array([[-a / 2, 0, 0], [a / 2, 0, 0], [0, -b / 2, 0], [0, b / 2, 0]])
    best: tuple[float, int, float, float, float] | None = None
    closest = math.inf
    for pose, (C, R) in sorted(cameras.items()):
        C, R = np.asarray(C, float), np.asarray(R, float)
        pc = (pts - C) @ R.T
        if not (pc[:, 2] > 0).all():
            continue  # the sample's centre is behind this camera
        uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
        side_x, side_y = np.linalg.norm(uv[1] - uv[0]), np.linalg.norm(uv[3] - uv[2])
        side = min(side_x, side_y)
        d = float(np.linalg.norm(C))
        closest = min(closest, d)
        if best is None or side > best[0]:
            best = (float(side), int(pose), d, float(side_x), float(side_y))
    if best is None:
        return None
    res = TexelResolution(best[0], best[1], best[2], closest)
    if res.pixels < MIN_TEXEL_PX:
        # a texel's side scales as 1/N along its axis: the finest grid keeping MIN_TEXEL_PX
        mx = int(math.floor(nx * best[3] / MIN_TEXEL_PX))
        my = int(math.floor(ny * best[4] / MIN_TEXEL_PX))
        fits = f"{min(mx, my)}" if nx == ny else f"{mx}x{my}"
        raise ReductionError(
            f"--texels {nx}x{ny}: a texel is {res.pixels:.2f} pixels across (its narrower "
            f"side) at the closest, best-resolving sample pose (pose {res.pose}, camera "
            f"{res.distance_m:.3f} m from the sample; closest {res.closest_distance_m:.3f} m); "
            "the camera resolves "
            f"texels of at least {MIN_TEXEL_PX:g} pixels (a whole Bayer cell): use at most "
            f"--texels {fits}"
            + (" (the camera does not resolve the sample)" if min(mx, my) < 1 else "")
        )
    return res


def modes_omitted(
    n_texels: int, n_poses: int, n_modes: int, limit: int = MAX_TEXEL_MODES_BYTES
) -> str | None:
    """Why a texel file leaves its geometry modes out (their array exceeds ``limit``
    bytes), or None when it keeps them."""
    size = int(n_texels) * int(n_poses) * int(n_modes) * 6 * 8
    if size <= limit:
        return None
    return (
        f"geometry_modes ({n_texels} texels x {n_poses} poses x {n_modes} modes x 6 "
        f"float64 = {size / 2**30:.2f} GiB) exceed the texel file's limit of "
        f"{limit / 2**30:.2f} GiB: left out of texels.h5 (samples.h5 holds them; "
        "budget/geometry, the term they give, is kept)"
    )


def texel_arrays(
    samples: BRDFSamples,
    counts: Sequence[int],
    poses: Sequence[int],
    n: int | tuple[int, int],
    *,
    with_modes: bool = True,
) -> dict[str, Any]:
    """The reduction's samples as ``(T, P, ...)`` arrays for :func:`gonio.texels.save_texels`.

    Parameters
    ----------
    samples
        The reduction's samples, pose after pose (``samples.h5``'s content).
    counts
        Samples of each sample pose, in order: ``nx * ny`` (one per region) or 1 (a pose
        that gave no measurement: :func:`gonio.capture.pose_measure.invalid_pose`).
    poses
        Journal pose index of each sample pose.
    n
        Regions (texels) per side, or ``(nx, ny)``.
    with_modes
        Include the geometry modes (see :func:`modes_omitted`).

    Returns
    -------
    dict
        ``wi, wo, brdf, brdf_std, flags, pose, radiance, irradiance, budget`` and, when
        the samples have them, ``geometry_modes, geometry_mode_scope,
        geometry_mode_names``; a texel/pose without a sample is INVALID with NaN.

    Raises
    ------
    ReductionError
        A pose's sample count is neither ``nx * ny`` nor 1, or they do not add up.
    """
    nx, ny = _counts(n)
    t, p = nx * ny, len(counts)
    if sum(counts) != len(samples) or len(poses) != p:
        raise ReductionError(
            f"{len(samples)} samples for {p} poses of {list(counts)[:5]}... regions"
        )
    to_texel = region_to_texel(n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    full = np.array([k == t for k in counts])
    for k, c in zip(poses, counts, strict=True):
        if c not in (t, 1):
            raise ReductionError(f"pose {k} has {c} samples; expected {t} (one per texel) or 1")
    # sample index of (texel, pose), -1 where the pose has no measurement
    src = np.full((t, p), -1, np.int64)
    src[to_texel[:, None], np.flatnonzero(full)[None, :]] = (
        start[full][None, :] + np.arange(t)[:, None]
    )
    have = src >= 0
    idx = np.where(have, src, 0)

    def per(a: NDArray | None) -> NDArray | None:
        if a is None:
            return None
        out = np.asarray(a, float)[idx]
        out[~have] = np.nan
        return out

    flags = np.where(have, samples.flags[idx], np.uint32(Flag.INVALID)).astype(np.uint32)
    out: dict[str, Any] = {
        "wi": per(samples.wi),
        "wo": per(samples.wo),
        "brdf": per(samples.brdf),
        "brdf_std": per(samples.brdf_std),
        "flags": flags,
        "pose": np.asarray(poses, np.int32),
        "radiance": per(samples.radiance),
        "irradiance": per(samples.irradiance),
        "budget": {k: per(v) for k, v in (samples.budget or {}).items()} or None,
        "shared_budget": samples.shared_budget,
    }
    if samples.geometry_modes is not None and with_modes:
        out["geometry_modes"] = per(samples.geometry_modes)
        out["geometry_mode_scope"] = list(samples.geometry_mode_scope)
        out["geometry_mode_names"] = list(samples.geometry_mode_names)
    return out


def texel_levelled(
    brdf: NDArray[np.float64],
    counts: Sequence[int],
    usable: NDArray[np.bool_],
    texels: tuple[int, int],
) -> NDArray[np.float64]:
    """The BRDF with each texel's own level divided out, for the geometry term's gradient.

    The gradient of ``log f`` over the directions is estimated from neighbouring samples
    (:func:`gonio.capture.budget.local_log_gradient`).  On a texel grid those neighbours
    are mostly other texels seen in the same pose, whose directions differ with their
    place on the sample: a sample whose albedo varies across it would have its spatial
    variation read as a directional slope (on a Lambertian sample with a 40 % albedo
    ramp, 0.7 % of f instead of ~0.002 %).  Each texel's geometric mean over its usable
    poses (per channel) is divided out, so a multiplicative spatial variation leaves
    the neighbourhoods.  The cost: the share of a real directional slope that is common
    to a texel over all its poses goes with it (small with many poses).

    Parameters
    ----------
    brdf
        (N, C) the reduction's samples, pose after pose, 1/sr.
    counts
        Samples of each sample pose: ``nx * ny``, or 1 for a pose without a measurement
        (left as it is).
    usable
        (N,) the samples that set a texel's level.
    texels
        ``(nx, ny)``.

    Returns
    -------
    ndarray
        (N, C) the levelled BRDF (for the gradient only: never stored).
    """
    n_regions = texels[0] * texels[1]
    to_texel = region_to_texel(texels)
    ids = np.concatenate([to_texel if c == n_regions else np.full(c, -1) for c in counts])
    with np.errstate(invalid="ignore", divide="ignore"):
        logf = np.log(brdf)
    ok = usable & (ids >= 0) & np.isfinite(logf).all(axis=1)
    n_tex = int(n_regions)
    cnt = np.bincount(ids[ok], minlength=n_tex)
    out = brdf.copy()
    for c in range(brdf.shape[1]):
        level = np.bincount(ids[ok], logf[ok, c], minlength=n_tex) / np.maximum(cnt, 1)
        centre = float(np.mean(level[cnt > 0])) if (cnt > 0).any() else 0.0
        shift = np.where(cnt > 0, level - centre, 0.0)
        sel = ids >= 0
        out[sel, c] = brdf[sel, c] / np.exp(shift[ids[sel]])
    return out

"""Reduce a capture session to BRDF samples: ``reduce_session(SESSION/) -> samples.h5``.

For every pose of the session (see DEVELOPING.md, "Session directory"):

1. the RAW frames are checked against their journal hash and the session's camera (CFA
   pattern and size), decoded on the mosaic (:mod:`gonio.capture.raw`), and the matching
   master dark (same exposure time and ISO) is subtracted;
2. the holder's ChArUco board gives the camera pose (:mod:`gonio.capture.fiducials`);
   the sample's central area is split into ``grid x grid`` regions, each one BRDF sample
   with its own measured ``wo`` and ``wi`` (from the light's position given by the rig's
   kinematics at the joint angles read back); a camera pose further than the tolerance
   from the rig's report flags the pose;
3. the bracket is merged with inverse-variance weights (:mod:`gonio.capture.hdr`),
   corrected for natural vignetting, and averaged per region and CFA channel with
   weights that centre every channel on the region's pixel centroid (the directions
   reported; :func:`bayer_region_weights`), the variance following from the
   photon-transfer model;
4. the reference target's poses give the light's radiance in camera units,
   ``I = pi / rho * <L_ref(x) / G(x)>`` with ``G`` the irradiance a unit-radiance light
   puts on point ``x`` (disk light), pooled over regions and reference poses;
   a sample region's BRDF is ``f = <L(x)> / (I <G(x)>)`` in 1/sr.

Frames are read once (one buffer both hashed and decoded) in worker threads that run
ahead of the measurement by one pose (see :class:`_FrameLoader`); results are taken in
journal order, so the output is the same for any number of threads.

Each region is one sample of ``samples.h5`` (:mod:`gonio.dataset`); its ``frames`` entry
lists the bracket's RAW files joined by ``;``.  Nothing in ``raw/`` is touched;
``samples.h5`` is written atomically, and the same session gives the same file.  A summary
(``reduction.json``) lists samples kept and rejected with their reasons, and
``samples.png`` shows them over the angle domain.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tomllib
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.atomic import write_text_atomic
from gonio.capture.calibration import irradiance_geometry, reference_reflectance
from gonio.capture.fiducials import (
    BoardSpec,
    CameraPose,
    RegionMap,
    angle_between,
    detect_pose_in_frame,
    map_regions,
    roi_geometry,
)
from gonio.capture.hdr import check_bracket, merge_bracket
from gonio.capture.journal import xxh3_bytes
from gonio.capture.noise import NoiseModel
from gonio.capture.raw import (
    CHANNELS,
    CameraSignature,
    RawFrame,
    read_file,
    read_raw,
    subtract_dark,
)
from gonio.errors import FileFormatError, GonioError, ReductionError, SessionError

SAMPLES_FILE = "samples.h5"
SUMMARY_FILE = "reduction.json"
PLOT_FILE = "samples.png"
NOISE_FILE = "noise.json"
CONFIG_FILE = "reduction.toml"
#: Completed poses whose frames are decoded ahead of the one being measured.
PREFETCH_POSES = 2


# --------------------------------------------------------------------------------------
# What the reduction needs to know besides the frames


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
        Central fraction of the sample used, and regions per side.
    geometry_tolerance_deg, position_tolerance_m
        Largest disagreement between the camera pose from the board and the rig's report.
    geometry
        Where the camera pose comes from: ``"board"`` (measured from the fiducials in each
        pose, the default) or ``"rig"`` (the rig's read-back pose through its calibrated
        kinematics; the board still checks it and flags disagreements).  Use ``"rig"``
        when the rig's geometry is known better than one board view measures it (a
        calibrated rig, or the simulator, whose rig is exact): on a sharp lobe's flank a
        0.04 deg pose error is a percent of BRDF, shared by every region of the pose.
    min_snr
        Regions whose signal-to-noise ratio is lower are flagged UNDEREXPOSED.
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
    geometry: str = "board"


def setup_from_scene(scene: Any, reflectance: Any = 0.99, **options: Any) -> ReductionSetup:
    """Reduction facts of a simulated rig, from its :class:`gonio.simulator.scene.Scene`.

    The simulator's camera matrix puts pixel centres at integer + 0.5; OpenCV puts them at
    integers, hence the half-pixel shift.
    """
    cam = scene.camera
    K = np.array(cam.intrinsics(), float)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    s = cam.sensor
    if scene.holder is None or scene.holder.board is None:
        raise ReductionError(
            "the scene's holder has no ChArUco board: the camera pose cannot be measured"
        )
    b = scene.holder.board
    board = BoardSpec(b.squares_x, b.squares_y, b.square_length, b.marker_length, b.dictionary)
    light = scene.lights[0]
    radius = getattr(light, "radius", None)
    noise = NoiseModel(s.gain_at_base_iso, s.read_noise * s.gain_at_base_iso, s.base_iso)
    w, h = cam.resolution
    opts = dict(
        light_radius=radius,
        signature=CameraSignature(s.cfa_pattern, (int(h), int(w))),
    )
    opts.update(options)
    return ReductionSetup(
        K=K,
        board=board,
        sample_size=(scene.sample.width, scene.sample.height),
        noise=noise,
        reflectance=reference_reflectance(reflectance),
        **opts,
    )


def setup_from_mapping(d: Mapping[str, Any], source: Path, base: Path) -> ReductionSetup:
    """Reduction facts from a ``reduction.toml`` document (a lab's calibration).

    Schema::

        [camera]   K = [[fx,0,cx],[0,fy,cy],[0,0,1]]   dist = [k1,k2,p1,p2,k3]
                   cfa_pattern = "RGGB"   width = 6000   height = 4000
        [noise]    gain = 0.4  read_noise = 1.2  iso = 100     # or file = "noise.json"
        [board]    squares_x, squares_y, square_length, marker_length, dictionary
        [sample]   width = 0.05  height = 0.05
        [light]    radius = 0.01                 # omit for a point source
        [reference] reflectance = 0.99 (or "spectrum.csv")  reflectance_std = 0.005
        [reduction] roi_fraction, grid, geometry_tolerance_deg, position_tolerance_m, min_snr
    """
    try:
        cam = d["camera"]
        K = np.asarray(cam["K"], float)
        if K.shape != (3, 3):
            raise FileFormatError(source, f"must be 3x3, got shape {K.shape}", "camera.K")
        noise_d = d.get("noise")
        if not isinstance(noise_d, Mapping):
            raise FileFormatError(
                source, "missing: give gain and read_noise, or file = 'noise.json'", "noise"
            )
        if "file" in noise_d:
            noise = NoiseModel.load(base / noise_d["file"])
        else:
            noise = NoiseModel.from_mapping(noise_d, source=source)
        sample = d["sample"]
        ref = d.get("reference", {})
        refl = ref.get("reflectance", 0.99)
        if isinstance(refl, str):
            refl = base / refl
        red = d.get("reduction", {})
        return ReductionSetup(
            K=K,
            board=BoardSpec.from_mapping(d.get("board", {})),
            sample_size=(float(sample["width"]), float(sample["height"])),
            noise=noise,
            reflectance=reference_reflectance(refl),
            reflectance_std=np.broadcast_to(
                np.asarray(ref.get("reflectance_std", 0.0), float), (3,)
            ).copy(),
            light_radius=d.get("light", {}).get("radius"),
            dist=np.asarray(cam["dist"], float) if "dist" in cam else None,
            signature=CameraSignature.from_mapping(cam),
            **{
                k: red[k]
                for k in (
                    "roi_fraction",
                    "grid",
                    "geometry_tolerance_deg",
                    "position_tolerance_m",
                    "min_snr",
                )
                if k in red
            },
        )
    except KeyError as exc:
        raise FileFormatError(source, "missing", str(exc.args[0])) from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, GonioError):
            raise
        raise FileFormatError(source, str(exc)) from None


def _scene_of_manifest(manifest: Mapping[str, Any], session: Path) -> Any | None:
    sim = manifest.get("simulation")
    if not sim:
        return None
    doc = sim.get("scene", sim) if isinstance(sim, Mapping) else sim
    from gonio.simulator.scene import load_scene, parse_scene

    if isinstance(doc, str):
        p = Path(doc)
        scene = load_scene(p if p.is_absolute() else session / p)
    elif isinstance(doc, Mapping) and "camera" in doc:
        doc = dict(doc)
        base = doc.pop("_base_dir", None)
        scene = parse_scene(
            doc, f"{session}/manifest.json: simulation.scene", Path(base) if base else None
        )
    else:
        from gonio.capture.sim_camera import minimal_scene

        scene = parse_scene(minimal_scene(), "minimal scene")
    w = sim.get("width") if isinstance(sim, Mapping) else None
    h = sim.get("height") if isinstance(sim, Mapping) else None
    if w or h:
        W, H = scene.camera.resolution
        cam = scene.camera.model_copy(update={"resolution": (int(w or W), int(h or H))})
        scene = scene.model_copy(update={"camera": cam})
    return scene


def resolve_setup(
    session: Path, manifest: Mapping[str, Any], noise: NoiseModel | None = None
) -> ReductionSetup:
    """Find the reduction facts of a session.

    In order: ``SESSION/reduction.toml`` (a lab's calibration), else the simulated scene
    recorded in the manifest.  A ``SESSION/noise.json`` written by
    ``gonio capture calibrate-noise`` (or ``noise``) replaces the noise model.
    """
    ref = manifest.get("reference") or {}
    cfg = session / CONFIG_FILE
    if cfg.is_file():
        try:
            doc = tomllib.loads(cfg.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise FileFormatError(cfg, f"not valid TOML ({exc})") from None
        doc.setdefault("reference", {}).setdefault("reflectance", ref.get("reflectance", 0.99))
        setup = setup_from_mapping(doc, cfg, session)
    else:
        scene = _scene_of_manifest(manifest, session)
        if scene is None:
            raise SessionError(
                f"{session}: no {CONFIG_FILE} (camera matrix, board, sample size, noise model) "
                "and no simulated scene in the manifest: the reduction does not know the camera"
            )
        setup = setup_from_scene(
            scene,
            ref.get("reflectance", 0.99),
            reflectance_std=np.broadcast_to(
                np.asarray(ref.get("reflectance_std", 0.0), float), (3,)
            ).copy(),
        )
    nfile = session / NOISE_FILE
    if noise is None and nfile.is_file():
        noise = NoiseModel.load(nfile)
    if noise is not None:
        setup = _replace(setup, noise=noise)
    return setup


def _replace(setup: ReductionSetup, **kw: Any) -> ReductionSetup:
    from dataclasses import replace

    return replace(setup, **kw)


# --------------------------------------------------------------------------------------
# One pose


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
        Camera pose from the board (None when not found).
    regions
        The :class:`RegionMap` (pixel sets), for inspection and tests.
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


def _flag(name: str) -> int:
    from gonio.dataset import Flag

    return int(Flag[name])


def _detection_frame(frames: list[RawFrame]) -> RawFrame:
    """The longest exposure with (almost) nothing saturated: the best-exposed board."""
    by_exp = sorted(frames, key=lambda f: f.exposure_factor())
    # longest first, stopping at the first good one (the estimate costs a pass per frame)
    return next((f for f in reversed(by_exp) if f.saturated_fraction() < 0.02), by_exp[0])


def bayer_region_weights(
    label: NDArray[np.integer],
    channel: NDArray[np.integer],
    n_regions: int,
    n_channels: int = 3,
) -> tuple[Any, NDArray[np.intp]]:
    """Weights of each CFA site in each region's mean, per channel, centred on the region.

    A region's pixels sample R and B at one site per 2x2 cell, G at two; the plain mean
    over a region's R pixels is centred half a pixel up-left of the region's pixel
    centroid (B down-right), while the region's directions are those of the centroid.
    On a lobe's flank that half pixel is a bias of the order of the noise (measured:
    z-score std 1.10-1.13 in R and B, 1.01 in G, at 640x480, 6x6 regions), and a region
    one or two pixels high at grazing angles may hold no R or B site at all.  Instead
    every pixel p of the region contributes a unit weight per channel: to itself when its
    filter passes the channel, else shared equally by its nearest sites of that channel
    (the 2 or 4 edge neighbours, or else the 4 diagonal ones), which lie symmetrically
    around p.  That is the adjoint of bilinear interpolation: the weighted mean is the
    region's mean of the channel bilinearly interpolated to every pixel, exact for any
    linear variation, so every channel is measured at the same centroid.  Sites shared by
    neighbouring pixels get larger weights; the variance of the mean is
    ``sum_q W_q^2 var_q / (sum_q W_q)^2`` over the independent sites q.

    Parameters
    ----------
    label
        (h, w) region index of each pixel, -1 outside every region.  Pixels on the
        crop's border (whose neighbours are unknown) are left out.
    channel
        (h, w) channel index of each pixel (a 2x2-periodic CFA).
    n_regions, n_channels
        Number of regions and channels.

    Returns
    -------
    A : scipy.sparse matrix
        (n_regions * n_channels, len(used)) weights; row ``r * n_channels + c``.  The row
        sum is the region's pixel count.
    used : ndarray
        Flat indices (into the (h, w) crop) of the sites the columns refer to.
    """
    from scipy.sparse import csr_matrix

    site, row, weight = bayer_region_entries(label, channel, n_regions, n_channels)
    used, col = np.unique(site, return_inverse=True)
    A = csr_matrix((weight, (row, col.ravel())), shape=(n_regions * n_channels, used.size))
    return A, used


def _site_weights(cell: NDArray[np.integer], n_channels: int) -> dict:
    """For each CFA position (y0, x0) of a site: the pixels that use it for the site's
    own channel, as ``[(dy, dx, weight), ...]`` offsets from the site (the weights of
    :func:`bayer_region_weights` seen from the site instead of the pixel)."""
    edge = ((0, 1), (0, -1), (1, 0), (-1, 0))
    diag = ((1, 1), (1, -1), (-1, 1), (-1, -1))
    out: dict[tuple[int, int], list[tuple[int, int, float]]] = {
        (a, b): [] for a in range(2) for b in range(2)
    }
    for a in range(2):
        for b in range(2):
            for c in range(n_channels):
                if cell[a, b] == c:
                    offs: list[tuple[int, int]] = [(0, 0)]
                else:
                    offs = [o for o in edge if cell[(a + o[0]) % 2, (b + o[1]) % 2] == c]
                    offs = offs or [o for o in diag if cell[(a + o[0]) % 2, (b + o[1]) % 2] == c]
                for dy, dx in offs:
                    # pixel (a, b) uses the site at (a + dy, b + dx): seen from the site,
                    # the pixel sits at (-dy, -dx)
                    out[((a + dy) % 2, (b + dx) % 2)].append((-dy, -dx, 1.0 / len(offs)))
    return out


def bayer_region_entries(
    label: NDArray[np.integer],
    channel: NDArray[np.integer],
    n_regions: int,
    n_channels: int = 3,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """The non-zero weights of :func:`bayer_region_weights` as ``(site, row, weight)``.

    Each (site, row) pair appears once, its weight summed over the region's pixels that
    use the site, so a region's weighted sum of ``x`` is
    ``np.bincount(row, weight * x[site])`` (and its variance uses ``weight**2``).

    Built site by site rather than pixel by pixel: a site of channel c is used by the
    pixels of a fixed 3x3 stencil around it (the adjoint of bilinear interpolation), so
    its weight in a region is the stencil's weight over its neighbours in that region,
    one OpenCV 3x3 filter of the "pixel counts" mask; the region is the neighbours' label
    (a 3x3 dilation).  Assembling a sparse matrix pixel by pixel, which has to sum ~7
    duplicates per pixel, cost more than the rest of the pose.  A site with neighbours
    in two regions (a boundary closer than the margin map_regions keeps) gets one entry
    per region, computed neighbour by neighbour.

    Returns
    -------
    site : ndarray
        (m,) flat indices into the (h, w) crop.
    row : ndarray
        (m,) ``region * n_channels + channel``.
    weight : ndarray
        (m,) weights; per row they sum to the region's pixel count.
    """
    import cv2

    lab = np.asarray(label)
    h, w = lab.shape
    cell = np.asarray(channel)[:2, :2]
    if h < 3 or w < 3:  # no pixel with all its neighbours in the crop
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
    # Labels of the pixels that count, padded by one so that a site's stencil never
    # leaves the array; pixels on the crop's border (neighbours unknown) do not count.
    # float32 holds labels exactly (to 2^24) and is what OpenCV's filters take.
    P = np.full((h + 2, w + 2), -1, np.float32)
    P[2:h, 2:w] = lab[1:-1, 1:-1]
    counts = (P >= 0).astype(np.float32)
    P_low = np.where(P >= 0, P, np.float32(np.inf))
    filtered: dict[bytes, tuple[NDArray, NDArray, NDArray]] = {}
    sites, rows, weights = [], [], []
    o_sites, o_rows, o_weights = [], [], []
    for (y0, x0), stencil in _site_weights(cell, n_channels).items():
        if y0 >= h or x0 >= w or not stencil:
            continue
        c = int(cell[y0, x0])
        kernel = np.zeros((3, 3), np.float32)
        for dy, dx, wt in stencil:
            kernel[1 + dy, 1 + dx] = wt  # powers of 2: the filtered sums are exact
        key = kernel.tobytes()
        if key not in filtered:
            el = (kernel > 0).astype(np.uint8)
            filtered[key] = (
                cv2.filter2D(counts, -1, kernel, borderType=cv2.BORDER_CONSTANT),
                cv2.dilate(P, el),  # highest label among the neighbours
                cv2.erode(P_low, el),  # lowest (inf: none)
            )
        wsum, top, low = (a[1 + y0 : 1 + h : 2, 1 + x0 : 1 + w : 2] for a in filtered[key])
        nx = top.shape[1]
        keep = np.flatnonzero((top >= 0) & (low == top))
        iy, ix = np.divmod(keep, nx)
        sites.append((y0 + 2 * iy) * w + x0 + 2 * ix)
        rows.append(top.ravel()[keep].astype(np.intp) * n_channels + c)
        weights.append(wsum.ravel()[keep].astype(np.float64))
        mixed = np.flatnonzero(low < top)
        if mixed.size:
            my, mx = np.divmod(mixed, nx)
            for dy, dx, wt in stencil:
                L = P[1 + y0 + 2 * my + dy, 1 + x0 + 2 * mx + dx]
                ok = L >= 0
                o_sites.append((y0 + 2 * my[ok]) * w + x0 + 2 * mx[ok])
                o_rows.append(L[ok].astype(np.intp) * n_channels + c)
                o_weights.append(np.full(int(ok.sum()), wt))
    if o_sites:
        # one entry per (site, row): several neighbours of a site may share the region
        n_rows = n_regions * n_channels
        key, inv = np.unique(
            np.concatenate(o_sites) * n_rows + np.concatenate(o_rows), return_inverse=True
        )
        sites.append(key // n_rows)
        rows.append(key % n_rows)
        weights.append(np.bincount(inv.ravel(), np.concatenate(o_weights)))
    if not sites:
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
    return (
        np.concatenate(sites).astype(np.intp, copy=False),
        np.concatenate(rows).astype(np.intp, copy=False),
        np.concatenate(weights),
    )


def _reported_pose(reported_camera: Any, rms: float, n_corners: int) -> CameraPose:
    """The rig's reported camera ``(position, world-to-camera rotation)`` as a CameraPose."""
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
        The rig's reported camera ``(position, world-to-camera rotation)``: used when the
        board cannot be seen (the samples are then flagged GEOMETRY_MISMATCH).
    dark_variance
        Variance (DN^2) added by the subtracted master dark.

    Raises
    ------
    ReductionError
        When neither the board nor a reported camera pose gives the geometry.
    """
    names = tuple(f.name for f in frames)
    pose_flags = 0
    pose_reasons: list[str] = []
    det = _detection_frame(frames)
    expected = None if reported_camera is None else _reported_pose(reported_camera, math.nan, 0)
    try:
        cam = detect_pose_in_frame(det, setup.board, setup.K, setup.dist, expected=expected)
    except ReductionError as exc:
        if reported_camera is None:
            raise
        cam = _reported_pose(reported_camera, math.nan, 0)
        pose_flags |= _flag("GEOMETRY_MISMATCH")
        pose_reasons.append(f"board not found ({exc}); the rig's camera pose was used")
    else:
        if reported_wo is not None:
            ang = math.degrees(
                float(
                    angle_between(
                        cam.position / np.linalg.norm(cam.position), np.asarray(reported_wo, float)
                    )
                )
            )
            if ang > setup.geometry_tolerance_deg:
                pose_flags |= _flag("GEOMETRY_MISMATCH")
                pose_reasons.append(
                    f"camera direction from the board is {ang:.2f} deg from the rig's report "
                    f"(tolerance {setup.geometry_tolerance_deg} deg)"
                )
        if reported_camera is not None:
            dpos = float(np.linalg.norm(cam.position - np.asarray(reported_camera[0], float)))
            if dpos > setup.position_tolerance_m:
                pose_flags |= _flag("GEOMETRY_MISMATCH")
                pose_reasons.append(
                    f"camera position from the board is {dpos * 1e3:.1f} mm from the rig's "
                    f"report (tolerance {setup.position_tolerance_m * 1e3:g} mm)"
                )
    if setup.geometry == "rig" and reported_camera is not None and not pose_flags:
        cam = _reported_pose(reported_camera, cam.reprojection_rms, cam.n_corners)
    lp = np.asarray(light_position, float)
    ln = None if light_normal is None else np.asarray(light_normal, float)
    fused = _fused_kernel() if all(f.raw is not None for f in frames) else None
    if fused is not None:
        regions, sums, dirs = _pose_sums_fused(fused, frames, setup, cam, lp, ln, dark_variance)
    else:
        regions, sums, dirs = _pose_sums_numpy(frames, setup, cam, lp, ln, dark_variance)
    n, nc = regions.n_regions, len(CHANNELS)
    k, s_L, s_Lv, s_G, s_Q, s_Qv, s_sat = np.moveaxis(sums, -1, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        L = s_L / k
        Lv = s_Lv / k**2
        G = s_G / k
        Q = s_Q / k
        Qv = s_Qv / k**2
    any_sat = s_sat > 0
    for arr in (L, Lv, G, Q, Qv):
        arr[any_sat | (k == 0)] = np.nan
    npx, wi, wo = dirs[:, 0], dirs[:, 1:4].copy(), dirs[:, 4:7].copy()
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
        low = [c for c in range(nc) if snr[j, c] < setup.min_snr]
        if low:
            flags[j] |= _flag("UNDEREXPOSED")
            txt = ", ".join(f"{CHANNELS[c]} {snr[j, c]:.1f}" for c in low)
            reasons[j].append(f"signal-to-noise below {setup.min_snr:g} ({txt})")
    with np.errstate(invalid="ignore", divide="ignore"):  # empty regions: NaN, flagged
        wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    return PoseMeasurement(pose, kind, wi, wo, L, Lv, G, Q, Qv, flags, reasons, names, cam, regions)


def _pose_sums_numpy(
    frames: list[RawFrame],
    setup: ReductionSetup,
    cam: CameraPose,
    lp: NDArray[np.float64],
    light_normal: NDArray[np.float64] | None,
    dark_variance: float | NDArray[np.float64],
) -> tuple[RegionMap, NDArray[np.float64], NDArray[np.float64]]:
    """The regions of a pose, their weighted sums per channel and their direction sums.

    Returns ``(regions, sums, dirs)``: ``sums`` (n, 3, 7) holds per region and channel the
    sums of w, w L, w^2 var(L), w G, w L / G, w^2 var(L) / G^2 and w over saturated sites
    (w the Bayer weights, :func:`bayer_region_weights`); ``dirs`` (n, 7) the pixel count
    and the sums of the per-pixel unit vectors to the light and to the camera.  The
    reference implementation of :mod:`gonio.capture.pose_kernel`.
    """
    regions = map_regions(
        cam,
        setup.K,
        frames[0].shape,
        setup.sample_size,
        roi_fraction=setup.roi_fraction,
        grid=setup.grid,
    )
    merged = merge_bracket(frames, setup.noise, dark_variance, region=regions.box)
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
    if setup.light_radius:
        g = g * (np.pi * setup.light_radius**2) * d2u / (d2u + setup.light_radius**2)
    val = np.where(sat, 0.0, val)
    var = np.where(sat, 0.0, var)
    wt2 = wt * wt
    with np.errstate(invalid="ignore", divide="ignore"):
        cols = (wt, wt * val, wt2 * var, wt * g, wt * val / g, wt2 * var / g**2, wt * sat)
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
) -> tuple[RegionMap, NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_pose_sums_numpy` in one pass of :mod:`gonio.capture.pose_kernel`."""
    check_bracket(frames)
    ref = frames[0]
    roi = roi_geometry(
        cam,
        setup.K,
        ref.shape,
        setup.sample_size,
        roi_fraction=setup.roi_fraction,
        grid=setup.grid,
    )
    box = roi.box
    r0, c0 = box[0].start, box[1].start
    frames = sorted(frames, key=lambda f: f.exposure_factor())  # merge_bracket's order

    def crop_cell(cell: NDArray) -> NDArray:  # a (2, 2) cell as seen from the crop origin
        return np.roll(np.asarray(cell, float), (-(r0 % 2), -(c0 % 2)), axis=(0, 1))

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
    for (y0, x0), entries in _site_weights(cell, len(CHANNELS)).items():
        st_n[2 * y0 + x0] = len(entries)
        for t, e in enumerate(entries):
            st[:, 2 * y0 + x0, t] = e
    K = np.asarray(setup.K, float)
    hw, hh = roi.half_size
    label, sums, dirs = kernel(
        np.stack([f.raw[box] for f in frames]),
        np.stack([crop_cell(f.cell_black) for f in frames]),
        np.stack([crop_cell(f.cell_saturation) for f in frames]),
        stack("_offset"),
        gains,
        np.array([f.exposure_factor() for f in frames]),
        np.array([m.gain for m in models]),
        np.array([m.read_noise**2 for m in models]),
        1.0 / 12.0 if setup.noise.quantisation else 0.0,
        dv[box] if dv.ndim == 2 else np.zeros((0, 0)),
        float(dv) if dv.ndim != 2 else 0.0,
        cell,
        st_n,
        st[0].astype(np.int64),
        st[1].astype(np.int64),
        st[2],
        np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
        np.asarray(cam.rotation, float),
        np.asarray(cam.position, float),
        r0,
        c0,
        np.array([hw, hh, *roi.cell, roi.margin]),
        roi.grid,
        lp,
        np.zeros(3) if light_normal is None else light_normal,
        light_normal is not None,
        float(setup.light_radius or 0.0),
        len(CHANNELS),
    )
    regions = RegionMap(box, label, roi.grid**2, roi.centers, cam, K)
    return regions, sums, dirs


def light_scale(
    references: list[PoseMeasurement], setup: ReductionSetup
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The light's radiance in camera units per channel, from the reference poses.

    ``I_c = pi / rho_c * <L_ref / G>``, pooled with inverse-variance weights over every
    unflagged region of every reference pose; the variance includes the reflectance's
    uncertainty.

    Raises
    ------
    ReductionError
        When no usable reference region exists.
    """
    q, qv = [], []
    for r in references:
        ok = (r.flags == 0)[:, None] & np.isfinite(r.ratio) & np.isfinite(r.ratio_var)
        q.append(np.where(ok, r.ratio, np.nan))
        qv.append(np.where(ok, r.ratio_var, np.nan))
    if not q:
        raise ReductionError(
            "the session has no reference-target frames: the irradiance is unknown"
        )
    Q = np.concatenate(q)
    V = np.concatenate(qv)
    good = np.isfinite(Q)
    if not good.any(axis=0).all():
        missing = [CHANNELS[c] for c in range(len(CHANNELS)) if not good[:, c].any()]
        raise ReductionError(
            f"no usable reference-target region in channel(s) {', '.join(missing)} "
            "(all flagged saturated, underexposed, or without the board)"
        )
    w = np.where(good, 1.0 / np.where(good, V, 1.0), 0.0)
    qm = np.nansum(w * np.nan_to_num(Q), axis=0) / w.sum(0)
    qm_var = 1.0 / w.sum(0)
    rho = setup.reflectance
    I = np.pi * qm / rho
    I_var = I**2 * (qm_var / qm**2 + (setup.reflectance_std / rho) ** 2)
    return I, I_var


def brdf_of(
    m: PoseMeasurement, I: NDArray[np.float64], I_var: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """BRDF, its standard deviation, and the irradiance of each region of a sample pose.

    ``f = <L> / (I <G>)``; ``var f = var<L> / E^2 + f^2 var(I) / I^2`` with ``E = I <G>``.
    """
    E = I[None, :] * m.geometry
    with np.errstate(invalid="ignore", divide="ignore"):
        f = m.radiance / E
        var = m.radiance_var / E**2 + f**2 * (I_var / I**2)[None, :]
    return f, np.sqrt(var), E, I_var[None, :] * m.geometry**2


# --------------------------------------------------------------------------------------
# Reading frames, overlapped with the measurement


def default_threads() -> int:
    """Threads :func:`reduce_session` uses, the calling one included: 2 if the machine has
    2 or more cores (one measures poses and decodes, the other decodes ahead; more give
    little, since the measurement is serial and LibRaw's decoding is bound by memory)."""
    return 2 if (os.cpu_count() or 1) >= 2 else 1


def _load_frame(
    session: Path, signature: CameraSignature | None, rec: Mapping[str, Any]
) -> tuple[RawFrame | None, str | None]:
    """Read one journal frame once, check it against the journal and decode it from the
    same bytes.

    The check is the journal's byte count and XXH3-128 digest (sessions from before it
    was recorded: sha256); see :func:`gonio.capture.journal.xxh3_bytes` for why.
    Returns ``(frame, None)``, or ``(None, problem)`` for a missing, changed, corrupt or
    foreign file.  Runs in worker threads: it touches no shared state.
    """
    rel = rec.get("file", "")
    path = session / rel
    try:
        if not path.is_file():
            raise FileFormatError(path, "missing (the journal lists it)")
        data = read_file(path)
        changed = "the file was changed, truncated or corrupted after capture"
        if rec.get("bytes") is not None and len(data) != int(rec["bytes"]):
            raise FileFormatError(
                path, f"{len(data)} bytes, the journal recorded {int(rec['bytes'])}: {changed}"
            )
        if rec.get("xxh3_128"):
            if xxh3_bytes(data) != rec["xxh3_128"]:
                raise FileFormatError(path, f"XXH3-128 digest differs from the journal: {changed}")
        elif rec.get("sha256") and hashlib.sha256(data).hexdigest() != rec["sha256"]:
            raise FileFormatError(path, f"sha256 differs from the journal: {changed}")
        fr = read_raw(data, name=rel, expect=signature)
    except GonioError as exc:
        return None, str(exc)
    return (
        fr.with_exposure(
            exposure_time=rec.get("exposure_time") if not np.isfinite(fr.exposure_time) else None,
            iso=rec.get("iso") if not np.isfinite(fr.iso) else None,
            f_number=rec.get("f_number") if not np.isfinite(fr.f_number) else None,
        ),
        None,
    )


class _FrameLoader:
    """Reads, hashes and decodes frames in worker threads, handing them out in order.

    File reads, hashing, LibRaw's unpack, OpenCV's board detection and the fused pose
    kernel release the GIL, so with two threads the worker decodes the next poses' frames
    while this thread measures the current pose.  When this thread needs frames the
    worker has not started, it decodes them itself rather than wait (decoding takes
    longer than measuring, so the two threads share it).  Every frame is decoded
    independently and the results are collected in journal order, so the output does not
    depend on the thread count.  With one thread frames are decoded on demand.
    """

    def __init__(self, session: Path, signature: CameraSignature | None, threads: int) -> None:
        self._args = (session, signature)
        # ``threads`` counts this thread: the pool has the others
        self._pool = ThreadPoolExecutor(threads - 1, "gonio-reduce") if threads > 1 else None
        self._pending: dict[int, Future] = {}

    def __enter__(self) -> _FrameLoader:
        return self

    def __exit__(self, *exc: object) -> None:
        for fut in self._pending.values():
            fut.cancel()
        self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def prefetch(self, recs: list[dict[str, Any]]) -> None:
        """Queue these frames for decoding (no-op with one thread or when already queued)."""
        if self._pool is None:
            return
        for rec in recs:
            if id(rec) not in self._pending:
                self._pending[id(rec)] = self._pool.submit(_load_frame, *self._args, rec)

    def results(self, recs: list[dict[str, Any]]) -> list[tuple[RawFrame | None, str | None]]:
        """``(frame, problem)`` of each record, in the order given."""
        futs = [self._pending.pop(id(rec), None) for rec in recs]
        # frames no worker has started are decoded here (cancel() fails once started)
        local = [fut is None or fut.cancel() for fut in futs]
        out: list[Any] = [
            _load_frame(*self._args, rec) if here else None
            for rec, here in zip(recs, local, strict=True)
        ]
        for k, (fut, here) in enumerate(zip(futs, local, strict=True)):
            if not here:
                out[k] = fut.result()
        return out


# --------------------------------------------------------------------------------------
# The session


@dataclass
class ReductionResult:
    """What :func:`reduce_session` did.

    Attributes
    ----------
    path
        The written ``samples.h5``.
    n_samples, n_kept
        Samples written, and those with no flag.
    rejected
        Reason -> number of samples (or frames) rejected for it.
    summary
        The JSON summary written next to the samples.
    plot
        The plot file, or None.
    """

    path: Path
    n_samples: int
    n_kept: int
    rejected: dict[str, int]
    summary: dict[str, Any]
    plot: Path | None


def _kinematics(manifest: Mapping[str, Any]) -> Any | None:
    rig = manifest.get("rig")
    if not rig:
        return None
    try:
        from gonio.rig.config import rig_config_from_dict
        from gonio.rig.kinematics import Kinematics

        return Kinematics(rig_config_from_dict(dict(rig), "manifest.json: rig"))
    except (ImportError, GonioError):
        return None


def _shots_by_pose(records: list[dict[str, Any]]) -> tuple[dict[int, list[dict]], set[int]]:
    shots: dict[int, dict[int, dict]] = defaultdict(dict)
    done: set[int] = set()
    for r in records:
        if r.get("type") == "shot":
            shots[int(r["pose"])][int(r["frame"])] = r  # a redone frame replaces the old
        elif r.get("type") == "pose_done":
            done.add(int(r["pose"]))
    return {p: [fr[k] for k in sorted(fr)] for p, fr in shots.items()}, done


def reduce_session(
    session_dir: str | os.PathLike,
    *,
    out: str | os.PathLike | None = None,
    noise: NoiseModel | None = None,
    setup: ReductionSetup | None = None,
    plot: bool = True,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
) -> ReductionResult:
    """Reduce a session's RAW frames to calibrated BRDF samples (``samples.h5``).

    Parameters
    ----------
    session_dir
        The session directory (manifest, journal, raw/).
    out
        Output file; ``SESSION/samples.h5`` by default.
    noise
        Noise model overriding the session's (``noise.json`` / the simulated sensor).
    setup
        All reduction facts, overriding what the session says.
    plot
        Write ``samples.png`` (angle-domain plot) next to the output.
    progress
        Called as ``progress(done, total)`` after each pose.
    threads
        Threads, this one included: the others read, hash and decode frames ahead while
        poses are measured (:func:`default_threads` when None; 1 does everything in
        this thread).  The output is the same for any number.

    Returns
    -------
    ReductionResult

    Raises
    ------
    SessionError
        Not a session directory, or nothing to reduce.
    ReductionError
        No usable reference frames (the irradiance cannot be calibrated).
    """
    from gonio.capture.journal import read_journal
    from gonio.capture.session import load_manifest
    from gonio.dataset import BRDFSamples, save_samples

    session = Path(session_dir)
    manifest = load_manifest(session)
    records = read_journal(session / "journal.jsonl")
    if setup is None:
        setup = resolve_setup(session, manifest, noise)
    elif noise is not None:
        setup = _replace(setup, noise=noise)
    kin = _kinematics(manifest)
    shots, done = _shots_by_pose(records)
    frame_problems: dict[str, str] = {}
    rejected: Counter[str] = Counter()

    def load(rec: dict[str, Any]) -> RawFrame | None:
        fr, problem = _load_frame(session, setup.signature, rec)
        if problem is not None:
            frame_problems[rec.get("file", "")] = problem
        return fr

    if setup.signature is None:
        first = next((r for recs in shots.values() for r in recs if r.get("kind") != "dark"), None)
        if first is not None:
            fr = load(first)
            if fr is not None:
                setup = _replace(setup, signature=fr.signature)

    n_threads = default_threads() if threads is None else max(1, int(threads))
    with _FrameLoader(session, setup.signature, n_threads) as loader:

        def collect(recs: list[dict[str, Any]]) -> list[RawFrame | None]:
            out = []
            for rec, (fr, problem) in zip(recs, loader.results(recs), strict=True):
                if problem is not None:
                    frame_problems[rec.get("file", "")] = problem
                out.append(fr)
            return out

        # Master darks per (exposure time, ISO)
        dark_recs = [rec for recs in shots.values() for rec in recs if rec.get("kind") == "dark"]
        loader.prefetch(dark_recs)
        dark_groups: dict[tuple[float, float], list[RawFrame]] = defaultdict(list)
        for fr in collect(dark_recs):
            if fr is not None:
                dark_groups[(round(fr.exposure_time, 9), fr.iso)].append(fr)
        masters = {
            k: (np.mean([f.linear for f in v], axis=0), len(v)) for k, v in dark_groups.items()
        }
        poses = sorted(
            p
            for p, recs in shots.items()
            if recs and recs[0].get("kind") in ("sample", "reference")
        )
        measurements: list[PoseMeasurement] = []
        failed_poses: list[dict[str, Any]] = []
        for i, p in enumerate(poses):
            recs = shots[p]
            kind = recs[0]["kind"]
            if p not in done:
                failed_poses.append(
                    {"pose": p, "kind": kind, "reason": "pose not completed (no pose_done record)"}
                )
                rejected["pose not completed"] += 1
                if progress:
                    progress(i + 1, len(poses))
                continue
            # keep the worker two completed poses ahead of the measurement
            for q in [q for q in poses[i + 1 :] if q in done][:PREFETCH_POSES]:
                loader.prefetch(shots[q])
            frames = []
            dvar = 0.0
            for fr in collect(recs):
                if fr is None:
                    continue
                key = (round(fr.exposure_time, 9), fr.iso)
                if key in masters:
                    mdark, nd = masters[key]
                    fr = subtract_dark(fr, mdark)
                    dvar = setup.noise.variance(0.0, iso=fr.iso) / nd
                frames.append(fr)
            last = recs[-1]
            wi_rep = np.asarray(last.get("wi_achieved") or last.get("wi_requested"), float)
            wo_rep = np.asarray(last.get("wo_achieved") or last.get("wo_requested"), float)
            light_pos, light_n, cam_rep = _rig_pose(kin, last.get("joints"), wi_rep, wo_rep)
            if not frames:
                why = "; ".join(frame_problems.get(r.get("file", ""), "?") for r in recs)
                failed_poses.append(
                    {"pose": p, "kind": kind, "reason": f"no decodable frame: {why}"}
                )
                rejected["no decodable frame"] += 1
                if kind == "sample":
                    measurements.append(
                        _invalid_pose(
                            p,
                            wi_rep,
                            wo_rep,
                            f"no decodable frame: {why}",
                            tuple(r["file"] for r in recs),
                        )
                    )
            else:
                try:
                    m = measure_pose(
                        frames,
                        setup,
                        light_pos,
                        light_n,
                        pose=p,
                        kind=kind,
                        reported_wo=wo_rep,
                        reported_camera=cam_rep,
                        dark_variance=dvar,
                    )
                except ReductionError as exc:
                    failed_poses.append({"pose": p, "kind": kind, "reason": str(exc)})
                    rejected["pose could not be reduced"] += 1
                    if kind == "sample":
                        measurements.append(
                            _invalid_pose(
                                p,
                                wi_rep,
                                wo_rep,
                                f"pose could not be reduced: {exc}",
                                tuple(f.name for f in frames),
                            )
                        )
                else:
                    measurements.append(m)
            if progress:
                progress(i + 1, len(poses))

    samples_m = [m for m in measurements if m.kind == "sample"]
    if not samples_m:
        raise SessionError(
            f"{session}: no sample pose to reduce"
            + (f" ({failed_poses[0]['reason']})" if failed_poses else "")
        )
    I, I_var = light_scale([m for m in measurements if m.kind == "reference"], setup)
    # The calibration scale I is one number per channel shared by every sample: its
    # uncertainty is fully correlated, so it is stored once (calibration_rel_std) for the
    # fitter to add to the parameters it scales, not folded into each sample's sigma
    # (which would let N samples average it down by sqrt(N)).
    parts = [brdf_of(m, I, np.zeros_like(I_var)) for m in samples_m]
    f = np.concatenate([x[0] for x in parts])
    fstd = np.concatenate([x[1] for x in parts])
    E = np.concatenate([x[2] for x in parts])
    wi = np.concatenate([m.wi for m in samples_m])
    wo = np.concatenate([m.wo for m in samples_m])
    flags = np.concatenate([m.flags for m in samples_m])
    L = np.concatenate([m.radiance for m in samples_m])
    frames_col = np.array([";".join(m.frames) for m in samples_m for _ in range(len(m.flags))])
    reasons = [r for m in samples_m for r in m.reasons]
    for rs in reasons:
        for r in rs:
            rejected[_reason_key(r)] += 1
    attrs = {
        "session": str(manifest.get("created", "")),
        "software_version": _version(),
        "session_software_version": str(manifest.get("software_version", "")),
        "radiance_units": "camera DN per (s ISO/100 / N^2), vignetting corrected (relative)",
        "irradiance_units": "same camera units x sr (relative); brdf = radiance / irradiance",
        "light_radiance_camera_units": I.tolist(),
        "light_radiance_std": np.sqrt(I_var).tolist(),
        "calibration_rel_std": (np.sqrt(I_var) / I).tolist(),
        "noise_model": json.dumps(
            {"gain": setup.noise.gain, "read_noise": setup.noise.read_noise, "iso": setup.noise.iso}
        ),
        "reference_reflectance": setup.reflectance.tolist(),
        "roi_fraction": setup.roi_fraction,
        "grid": setup.grid,
    }
    samples = BRDFSamples(
        wi=wi,
        wo=wo,
        brdf=f,
        brdf_std=fstd,
        flags=flags,
        channels=CHANNELS,
        radiance=L,
        irradiance=E,
        frames=frames_col,
        attrs=attrs,
    )
    path = Path(out) if out is not None else session / SAMPLES_FILE
    save_samples(path, samples)
    n_kept = int(samples.valid.sum())
    summary = {
        "samples": len(samples),
        "kept": n_kept,
        "rejected": dict(sorted(rejected.items())),
        "sample_poses": len(samples_m),
        "reference_poses": sum(m.kind == "reference" for m in measurements),
        "failed_poses": failed_poses,
        "frame_problems": dict(sorted(frame_problems.items())),
        "light_radiance_camera_units": I.tolist(),
        "output": path.name,
    }
    _write_json(path.with_name(SUMMARY_FILE), summary)
    plot_path = None
    if plot:
        plot_path = plot_samples(samples, path.with_name(PLOT_FILE))
    return ReductionResult(path, len(samples), n_kept, dict(rejected), summary, plot_path)


def _reason_key(reason: str) -> str:
    for key in (
        "saturated",
        "signal-to-noise",
        "board not found",
        "camera direction",
        "camera position",
        "no decodable frame",
        "pose could not be reduced",
        "no pixels",
    ):
        if key in reason:
            return {
                "signal-to-noise": "underexposed",
                "camera direction": "geometry mismatch",
                "camera position": "geometry mismatch",
            }.get(key, key)
    return reason.split(":")[0][:60]


def _invalid_pose(
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


def _rig_pose(kin: Any, joints: Mapping[str, float] | None, wi: NDArray, wo: NDArray):
    """Light position/normal and reported camera (position, world->camera R) of a pose."""
    if kin is not None and joints:
        try:
            rp = kin.poses({k: float(v) for k, v in joints.items()})
            return (
                np.asarray(rp.light_position, float),
                np.asarray(rp.light_normal, float),
                (np.asarray(rp.camera_position, float), np.asarray(rp.camera_rotation, float).T),
            )
        except GonioError:
            pass
    raise ReductionError(
        "the light's position is unknown: the manifest has no rig configuration with "
        "kinematics for the journal's joint angles"
    )


def _version() -> str:
    try:
        from gonio import __version__

        return str(__version__)
    except ImportError:  # pragma: no cover
        return "unknown"


def _write_json(path: Path, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, default=str) + "\n")


def plot_samples(samples: Any, path: Path) -> Path:
    """Samples over the angle domain: theta_i vs theta_o (colour: BRDF G), and the
    outgoing directions projected on the disk; rejected samples as crosses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ang = samples.angles()
    ok = samples.valid
    g = samples.brdf[:, 1 if samples.n_channels > 1 else 0]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    ax = axes[0]
    sc = ax.scatter(
        np.degrees(ang["theta_i"][ok]),
        np.degrees(ang["theta_o"][ok]),
        c=np.log10(np.clip(g[ok], 1e-6, None)),
        s=14,
        cmap="viridis",
    )
    ax.scatter(
        np.degrees(ang["theta_i"][~ok]),
        np.degrees(ang["theta_o"][~ok]),
        marker="x",
        c="red",
        s=18,
        label=f"rejected ({int((~ok).sum())})",
    )
    ax.set_xlabel("theta_i (deg)")
    ax.set_ylabel("theta_o (deg)")
    ax.set_title(f"{int(ok.sum())} samples kept")
    fig.colorbar(sc, ax=ax, label="log10 f_r (G channel, 1/sr)")
    if (~ok).any():
        ax.legend(loc="upper left")
    ax = axes[1]
    for sel, style in (
        (ok, dict(c="tab:blue", s=10, label="wo")),
        (ok, dict(c="tab:orange", s=10, label="wi")),
    ):
        w = samples.wo if style["label"] == "wo" else samples.wi
        ax.scatter(w[sel, 0], w[sel, 1], **style)
    ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="grey"))
    ax.set_aspect("equal")
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(-1.05, 1.05)
    ax.set_xlabel("x (sample frame)")
    ax.set_ylabel("y")
    ax.set_title("directions seen from above")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

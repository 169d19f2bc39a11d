"""Render what the camera sees of the sample and its holder: the rendering equation.

For each pixel the camera ray meets the plane z = 0 at x; the radiance towards the camera
is the area form of the rendering equation, summed over the lights,

    L(x -> wo) = int_light f_r(x, wi, wo) L_e V(x, y) cos(theta) cos(theta') / |x - y|^2 dA(y),

evaluated by one of

- ``"point"``: the light's centre with its whole area (exact for point lights);
- ``"quadrature"``: a deterministic rule over the light's area (see ``lights.py``);
- ``"mc"``: stratified Monte Carlo over the light's area (seeded);
- ``"auto"``: the cheapest of those whose *estimated* error meets ``tolerance``.  The
  estimate compares consecutive quadrature levels (point, 4, 16, 36, ... nodes) on a
  pilot set of pixels spread over the image; the first level whose difference to the
  next is below ``tolerance / 2`` wins.  The error measure is relative per pixel, with a
  floor of 1e-3 of the brightest pilot pixel so that near-black pixels do not dominate.

Penumbrae: where occluders hide part of a light (some of 25 probe points on the emitter
are blocked, some not) the integrand has a step and the level chosen on smooth pixels is
too coarse; those points get the finest rule of the ladder (1024 nodes on a disk, 625 on a
rectangle), whose error there (about 1e-2 of the unshadowed radiance: a step converges
like 1/n) is estimated against the next coarser rule and reported as ``penumbra_error``;
``tolerance_met`` is false when it exceeds the tolerance.

With ``camera.distortion`` each pixel's ray is the undistorted direction the lens images
there (:func:`gonio.simulator.geometry.pixel_grid`, cached per camera); pixel corners and
anti-aliasing sub-rays likewise.  With the mirror target (``sample.mirror_reflectance``)
the sample's rectangle is a flat mirror: its pixels are not integrated over the lights
but see, along the reflected ray, ``reflectance * L_e`` of an area light or nothing
(:mod:`gonio.simulator.mirror`); the spot's rim gets ``render.spot_antialias``^2
sub-rays (counted in ``edge_pixels``), whatever ``render.antialias`` is.

Uniform diffuse light (the room's ambient light and the light's own stray light, see
:mod:`gonio.simulator.world_radiometry`) is not integrated: ``render(..., diffuse=True)``
also returns, per pixel, the radiance a unit uniform diffuse irradiance reflects towards
the camera, ``albedo(theta_o) / pi`` (the surface's directional albedo, by reciprocity:
the holder's, board's and reference patch's albedo, the sample BRDF's ``albedo`` at the
viewing angle, tabulated once per BRDF by :func:`albedo_table`, the mirror's
reflectance); the camera scales it by the irradiance of each shot.

Only the plane z = 0 is shaded: occluders seen by the camera are black (region 4), an
emitter in view is not drawn, and there is no interreflection (the gonio scene has none
worth the cost: the arms are matte black and far away).

Work that the scene does not need is skipped and counted in :class:`RenderStats`: no
visibility tests for occluders whose bounding box misses the box around the lit surface
and the light; no shading for pixels that see neither sample nor holder; sub-pixel
anti-aliasing samples only on pixels whose four corners and centre do not all see the
same thing (region, board print, reference patch, light-centre visibility).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from gonio.brdf.base import readonly
from gonio.errors import ConfigError
from gonio.simulator.geometry import (
    _NEWTON_MAX,
    _UNDISTORT_TOL,
    UNDISTORT_ACCURACY,
    _normalized,
    intersect_plane_z0,
    pixel_grid,
    prepare_occluders,
    rays_from_normalized,
    segments_blocked,
)
from gonio.simulator.lights import LEVELS, PreparedLight, prepare_lights
from gonio.simulator.mirror import light_hits, mirror_radiance
from gonio.simulator.scene import Scene

__all__ = [
    "REGION_NAMES",
    "albedo_table",
    "RenderResult",
    "RenderStats",
    "Surface",
    "estimate_render_memory",
    "render",
    "render_memory_limit",
    "save_truth",
]

# Measured peaks (tracemalloc, examples/scene.toml at 640 x 480): ~400 bytes per pixel
# (rays, surface points, labels, radiance, the truth arrays: shading itself is chunked)
# and ~150 bytes per anti-aliasing sub-sample, which are not chunked.  Edge pixels were
# 5-6 % of the image there (board squares and markers); 10 % is assumed.
_BYTES_PER_PIXEL = 400
_BYTES_PER_SUBSAMPLE = 150
_EDGE_FRACTION = 0.10

NONE, SAMPLE, HOLDER, PATCH, OCCLUDED = 0, 1, 2, 3, 4
REGION_NAMES = {
    NONE: "none",
    SAMPLE: "sample",
    HOLDER: "holder",
    PATCH: "patch",
    OCCLUDED: "occluded",
}
_PILOT_PIXELS = 2048
#: Batches of camera rays from which the numba kernels label them (numpy below).
_MIN_KERNEL_POINTS = 4096
_SAFETY = 0.5
_MC_MAX = 1024
_QUAD_MAX = 1024


@dataclass
class LightStats:
    """How one light was integrated."""

    kind: str
    strategy: str
    level: int | None
    nodes: int
    estimated_error: float
    tolerance_met: bool
    occluders_tested: int
    occluders_culled: int
    penumbra_points: int = 0
    penumbra_nodes: int = 0
    penumbra_error: float = float("nan")


@dataclass
class RenderStats:
    """What the renderer did and what it skipped."""

    pixels: int
    pixels_shaded: int
    pixels_skipped: int
    pixels_occluded: int
    edge_pixels: int
    subpixel_samples: int
    camera_occluders_tested: int
    lights: list[LightStats] = field(default_factory=list)
    seconds: float = 0.0
    #: edge pixels (of ``edge_pixels``) anti-aliased by the board print's exact area
    #: coverage (``render.print_antialias = "exact"``) instead of sub-rays
    coverage_pixels: int = 0

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class RenderResult:
    """A rendered image with its ground truth (sample frame).

    Attributes
    ----------
    radiance
        (H, W, 3) noise-free radiance towards the camera, W/(sr m^2) (camera RGB).
    wi, wo
        (H, W, 3) unit directions from the pixel-centre surface point to the first
        light's centre and to the camera; NaN where the pixel sees no surface.
    points
        (H, W, 3) pixel-centre surface points, metres (NaN where none).
    region
        (H, W) uint8: 0 none, 1 sample, 2 holder, 3 reference patch, 4 occluded.
    edge
        (H, W) bool: pixels that received sub-pixel anti-aliasing samples.
    stats
        :class:`RenderStats`.
    diffuse
        (H, W, 3) radiance towards the camera per unit uniform diffuse irradiance,
        1/sr (``albedo(theta_o) / pi``); None unless rendered with ``diffuse=True``.

    ``wi``, ``wo`` and ``points`` may be given as one callable returning the three: they
    are then computed when first read (a camera's shots never read them).
    """

    def __init__(
        self,
        radiance: np.ndarray,
        wi: np.ndarray | None,
        wo: np.ndarray | None,
        points: np.ndarray | None,
        region: np.ndarray,
        edge: np.ndarray,
        stats: RenderStats,
        diffuse: np.ndarray | None = None,
        *,
        truth: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        self.radiance = radiance
        self._truth = truth
        self._wi, self._wo, self._points = wi, wo, points
        self.region = region
        self.edge = edge
        self.stats = stats
        self.diffuse = diffuse

    def _computed(self) -> None:
        if self._truth is not None:
            self._wi, self._wo, self._points = self._truth()
            self._truth = None

    @property
    def wi(self) -> np.ndarray:
        self._computed()
        return self._wi

    @property
    def wo(self) -> np.ndarray:
        self._computed()
        return self._wo

    @property
    def points(self) -> np.ndarray:
        self._computed()
        return self._points


class Surface:
    """The plane z = 0: sample rectangle (its BRDF, albedo map) and Lambertian holder."""

    def __init__(self, scene: Scene, brdf: Any = None) -> None:
        s = scene.sample
        self.half = np.array([s.width / 2, s.height / 2])
        self.mirror = s.mirror_reflectance
        # a mirror target has no BRDF to evaluate (a measured file is slow to load)
        if self.mirror is not None:
            self.brdf = None
        else:
            self.brdf = scene.build_brdf() if brdf is None else brdf
        # a spatially varying sample (gonio.simulator.svbrdf): per-texel BRDF and albedo
        self.spatial = bool(getattr(self.brdf, "spatial", False))
        self.albedo_map = None
        if s.albedo_map is not None:
            self.albedo_map = _load_albedo_map(scene.resolve(s.albedo_map))
        h = scene.holder
        self.holder_half = None if h is None else np.array([h.width / 2, h.height / 2])
        self.board_img = None
        self.patch = None
        self._kernel_args: tuple[np.ndarray, ...] | None = None
        self._albedo_rows: np.ndarray | None = None
        self._print_cells: Any = None
        if h is not None:
            self.black = np.broadcast_to(np.asarray(h.albedo_black, float), (3,))
            self.white = np.broadcast_to(np.asarray(h.albedo_white, float), (3,))
            if h.board is not None:
                self.board_img = _board_image(h.board)
                self.board_half = np.array(h.board.extent) / 2
            if h.reference_patch is not None:
                p = h.reference_patch
                self.patch = (
                    np.asarray(p.center, float),
                    np.asarray(p.size, float) / 2,
                    np.broadcast_to(np.asarray(p.albedo, float), (3,)),
                )

    def kernel_args(self) -> tuple[np.ndarray, ...]:
        """The surface as :func:`gonio.simulator.render_kernels.label_points` reads it:
        sample half-size, holder half-size, board print, its half extent, patch."""
        from gonio.simulator.render_kernels import board_uint8

        if self._kernel_args is None:
            holder = np.zeros(0) if self.holder_half is None else self.holder_half
            board = board_uint8(self.board_img)
            bh = self.board_half if self.board_img is not None else np.ones(2)
            patch = np.zeros(0)
            if self.patch is not None:
                patch = np.concatenate([self.patch[0][:2], self.patch[1][:2]])
            self._kernel_args = tuple(
                np.ascontiguousarray(a, dtype=float) if a.dtype != np.uint8 else a
                for a in (self.half, holder, board, bh, patch)
            )
        return self._kernel_args

    def print_cells(self) -> Any:
        """The board print merged into one-colour cells
        (:func:`gonio.simulator.print_coverage.print_cells`), or None without a board."""
        if self.board_img is None:
            return None
        if self._print_cells is None:
            self._print_cells = _cached_cells(self.board_img, self.board_half)
        return self._print_cells

    def albedo_rows(self) -> np.ndarray:
        """(3, 3) albedo of the black print, the white print and the reference patch
        (zeros without one): :meth:`lambert_albedo` as the kernels read it."""
        if self._albedo_rows is None:
            if self.holder_half is None:
                self._albedo_rows = np.zeros((3, 3))
            else:
                patch = np.zeros(3) if self.patch is None else self.patch[2]
                self._albedo_rows = np.array([self.black, self.white, patch], dtype=np.float64)
        return self._albedo_rows

    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box (lo, hi) of the surface, metres."""
        half = self.half if self.holder_half is None else self.holder_half
        return np.array([-half[0], -half[1], 0.0]), np.array([half[0], half[1], 0.0])

    def classify(self, x: np.ndarray, front: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Region code (...) uint8 and board print bit (...) bool of surface points."""
        ax, ay = np.abs(x[..., 0]), np.abs(x[..., 1])
        region = np.zeros(x.shape[:-1], np.uint8)
        white = np.zeros(x.shape[:-1], bool)
        if self.holder_half is not None:
            on_h = front & (ax <= self.holder_half[0]) & (ay <= self.holder_half[1])
            region[on_h] = HOLDER
            white = on_h & self._board_white(x)
            if self.patch is not None:
                c, hs, _ = self.patch
                on_p = (
                    on_h & (np.abs(x[..., 0] - c[0]) <= hs[0]) & (np.abs(x[..., 1] - c[1]) <= hs[1])
                )
                region[on_p] = PATCH
        on_s = front & (ax <= self.half[0]) & (ay <= self.half[1])
        region[on_s] = SAMPLE
        white &= region == HOLDER
        return region, white

    def _board_white(self, x: np.ndarray) -> np.ndarray:
        if self.board_img is None:
            return np.ones(x.shape[:-1], bool)
        hb = self.board_half
        rows, cols = self.board_img.shape
        c = np.floor((x[..., 0] + hb[0]) / (2 * hb[0]) * cols)
        r = np.floor((hb[1] - x[..., 1]) / (2 * hb[1]) * rows)
        inside = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
        ci = np.clip(c, 0, cols - 1).astype(np.intp)
        ri = np.clip(r, 0, rows - 1).astype(np.intp)
        return np.where(inside, self.board_img[ri, ci], True)

    def lambert_albedo(self, x: np.ndarray, region: np.ndarray, white: np.ndarray) -> np.ndarray:
        """Albedo (..., 3) of holder and patch points."""
        out = np.where(white[..., None], self.white, self.black)
        if self.patch is not None:
            out = np.where((region == PATCH)[..., None], self.patch[2], out)
        return out

    def diffuse_albedo(
        self,
        x: np.ndarray,
        region: np.ndarray,
        white: np.ndarray,
        camera: np.ndarray,
        sample_albedo: Callable[..., np.ndarray] | None,
    ) -> np.ndarray:
        """Directional albedo (M, 3) towards the camera of surface points x (M, 3): what
        a uniform diffuse irradiance E reflects is ``E / pi`` times it."""
        out = np.zeros((x.shape[0], 3))
        lam = region != SAMPLE
        rk = _kernels(x.shape[0])
        if rk is not None:
            rk.lambert_albedo(region, white, self.albedo_rows(), out)
        elif np.any(lam):
            out[lam] = self.lambert_albedo(x[lam], region[lam], white[lam])
        smp = np.flatnonzero(~lam)  # an index: take and put rows ~3x faster than a mask
        if len(smp):
            if self.mirror is not None:
                out[smp] = self.mirror
            else:
                xs = _take(x, smp)
                wo = camera - xs
                cos_o = wo[:, 2] / np.linalg.norm(wo, axis=-1)
                theta = np.arccos(np.clip(cos_o, -1.0, 1.0))
                a = sample_albedo(theta, xs) if self.spatial else sample_albedo(theta)
                scale = self.albedo_scale(xs)
                _put_rows(out, smp, a if scale is None else a * scale)
        return out

    def albedo_scale(self, x: np.ndarray) -> np.ndarray | None:
        """The albedo map's factor (..., 3) at sample points, or None without a map."""
        if self.albedo_map is None:
            return None
        from scipy.ndimage import map_coordinates

        m = self.albedo_map
        rows, cols = m.shape[:2]
        c = (x[..., 0] + self.half[0]) / (2 * self.half[0]) * cols - 0.5
        r = (self.half[1] - x[..., 1]) / (2 * self.half[1]) * rows - 0.5
        coords = np.stack([r.ravel(), c.ravel()])
        out = np.stack(
            [map_coordinates(m[..., k], coords, order=1, mode="nearest") for k in range(3)], -1
        )
        return out.reshape(x.shape[:-1] + (3,))


_BOARD_IMAGES: dict[str, np.ndarray] = {}
_PRINT_CELLS: dict[tuple[int, bytes], Any] = {}


def _cached_cells(img: np.ndarray, half: np.ndarray) -> Any:
    """:func:`gonio.simulator.print_coverage.print_cells` once per board print."""
    from gonio.simulator.print_coverage import print_cells

    key = (id(img), np.asarray(half, dtype=np.float64).tobytes())
    cells = _PRINT_CELLS.get(key)
    if cells is None:
        if len(_PRINT_CELLS) >= 8:
            _PRINT_CELLS.clear()
        # the print images are kept alive by _BOARD_IMAGES; a cleared one gets a new id
        cells = (img, print_cells(img, half))
        _PRINT_CELLS[key] = cells
    return cells[1] if cells[0] is img else print_cells(img, half)


def _board_image(board: Any) -> np.ndarray:
    """The board's print (read-only; drawn by OpenCV once per board)."""
    key = board.model_dump_json()
    img = _BOARD_IMAGES.get(key)
    if img is None:
        if len(_BOARD_IMAGES) >= 8:
            _BOARD_IMAGES.clear()
        img = board.image()
        img.flags.writeable = False
        _BOARD_IMAGES[key] = img
    return img


def _load_albedo_map(path) -> np.ndarray:
    if not path.is_file():
        raise ConfigError(f"sample.albedo_map: {path} does not exist")
    if path.suffix == ".npy":
        try:
            # Never unpickle: an object array in a scene's folder is not run, refused.
            raw = np.load(path, allow_pickle=False)
            m = np.asarray(raw, dtype=np.float64)
        except (ValueError, TypeError, OSError, EOFError) as exc:
            why = (
                "holds Python objects (a pickled array), which gonio does not load"
                if "allow_pickle" in str(exc)
                else f"is not a numeric .npy array ({exc})"
            )
            raise ConfigError(
                f"sample.albedo_map: {path} {why}; expected an (H, W) or (H, W, 3) "
                "array of numbers in [0, 1]"
            ) from None
    else:
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ConfigError(f"sample.albedo_map: {path} is not a readable image")
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        m = img.astype(np.float64) / scale
        if m.ndim == 3:
            m = m[..., 2::-1]  # OpenCV's BGR -> RGB
    if m.ndim == 2:
        m = np.repeat(m[..., None], 3, -1)
    if m.ndim != 3 or m.shape[-1] != 3 or not np.all(np.isfinite(m)):
        raise ConfigError(f"sample.albedo_map: {path} must be (H, W) or (H, W, 3) finite values")
    return m


#: Viewing angles of :func:`albedo_table`, rad: up to 89.5 deg (the albedo quadrature
#: degenerates at the horizon; beyond, the last value is kept).
_ALBEDO_THETA = np.linspace(0.0, np.radians(89.5), 33)


def albedo_table(brdf: Any) -> Callable[[np.ndarray], np.ndarray]:
    """The directional albedo of an isotropic BRDF as a function of the viewing angle.

    ``brdf.albedo(theta)`` (analytic and measured models have it; ~5-15 ms per angle)
    is tabulated once at 33 angles up to 89.5 deg and interpolated linearly per channel
    (anisotropic BRDFs: their albedo at phi = 0).  The diffuse light it weighs is a
    fraction of a percent of the direct light, so the table's ~1e-3 error is ~1e-6 of
    a pixel.

    Returns
    -------
    callable
        ``theta_o (M,) rad -> (M, 3)`` albedo; for a spatially varying sample
        (:class:`gonio.simulator.svbrdf.SpatialBRDF`) ``(theta_o, x (M, 3)) -> (M, 3)``,
        each point's texel tabulated once.
    """
    if getattr(brdf, "spatial", False):
        return brdf.albedo_at
    a = np.asarray(brdf.albedo(_ALBEDO_THETA), dtype=np.float64)
    a = np.broadcast_to(a.reshape(len(_ALBEDO_THETA), -1), (len(_ALBEDO_THETA), 3)).copy()

    def albedo(theta: np.ndarray) -> np.ndarray:
        t = np.asarray(theta, dtype=np.float64)
        return np.stack([np.interp(t, _ALBEDO_THETA, a[:, c]) for c in range(3)], -1)

    return albedo


class _Integrator:
    """Shades surface points for one light with a fixed node set or stratified MC."""

    def __init__(self, light: PreparedLight, occluders, surface: Surface, camera: np.ndarray):
        self.light = light
        self.occ = occluders
        self.surface = surface
        self.camera = camera

    def shade(
        self,
        x,
        region,
        white,
        strategy: str,
        level: int,
        n_mc: int = 0,
        rng: np.random.Generator | None = None,
        chunk: int = 262144,
    ) -> np.ndarray:
        """Radiance (M, 3) at points x (M, 3) towards the camera."""
        m = x.shape[0]
        out = np.zeros((m, 3))
        if m == 0:
            return out
        if strategy == "mc":
            k = n_mc
        else:
            nodes, weights = self.light.quadrature(level)
            k = len(weights)
        step = max(1, chunk // max(k, 1))
        for s in range(0, m, step):
            sl = slice(s, min(m, s + step))
            if strategy == "mc":
                y, wt = self.light.stratified(n_mc, rng, sl.stop - sl.start)
                w = np.full(y.shape[:-1], wt)
            else:
                y, w = nodes[None], weights[None]
            out[sl] = self._shade_nodes(x[sl], region[sl], white[sl], y, w)
        return out

    def partial(self, x: np.ndarray, chunk: int = 262144) -> np.ndarray:
        """Whether the light may be partly hidden from each point (M,): the occluders
        block some but not all of the light's probe points."""
        out = np.zeros(x.shape[0], bool)
        if not self.occ or self.light.is_point:
            return out
        probe = self.light.probe_points()
        step = max(1, chunk // len(probe))
        for s in range(0, x.shape[0], step):
            blk = segments_blocked(self.occ, x[s : s + step, None, :], probe[None])
            out[s : s + step] = blk.any(-1) & ~blk.all(-1)
        return out

    def _shade_nodes(self, x, region, white, y, w) -> np.ndarray:
        light = self.light
        m, k = x.shape[0], y.shape[-2]
        rk = _kernels(m * k)
        if rk is not None and not self.occ:
            return self._shade_nodes_fused(rk, x, region, white, y, w)
        if rk is None:
            d = y - x[:, None, :]
            r2 = np.einsum("mki,mki->mk", d, d)
            r = np.sqrt(r2)
            wi = d / r[..., None]
            cos_s = np.maximum(wi[..., 2], 0.0)
            if light.is_point:
                g = cos_s / r2
            else:
                cos_l = np.maximum(-(wi @ light.normal), 0.0)
                g = w * cos_s * cos_l / r2
                # the LED's cos^n emission and its face's gradient (none: Lambertian, uniform)
                prof = light.profile(cos_l)
                if prof is not None:
                    g = g * prof
                face = light.face(y)
                if face is not None:
                    g = g * face
        else:
            wi, g = np.empty((m, k, 3)), np.empty((m, k))
            face = None if light.is_point else light.face(y)
            rk.node_geometry(
                np.ascontiguousarray(x, dtype=np.float64),
                np.ascontiguousarray(np.reshape(y, (-1, k, 3)), dtype=np.float64),
                np.ascontiguousarray(np.reshape(w, (-1, k)), dtype=np.float64),
                np.ascontiguousarray(light.normal, dtype=np.float64),
                bool(light.is_point),
                float(light.profile_n),
                np.zeros((0, k))
                if face is None
                else np.ascontiguousarray(np.reshape(face, (-1, k))),
                wi,
                g,
            )
        if self.occ:
            live = g > 0
            blocked = np.zeros_like(live)
            xb = np.broadcast_to(x[:, None, :], wi.shape)
            yb = np.broadcast_to(y, wi.shape)
            blocked[live] = segments_blocked(self.occ, xb[live], yb[live])
            g = np.where(blocked, 0.0, g)
        out = np.zeros((x.shape[0], 3))
        lam = region != SAMPLE
        if rk is not None:
            rk.lambert_radiance(region, white, g, self.surface.albedo_rows(), out)
        elif np.any(lam):
            alb = self.surface.lambert_albedo(x[lam], region[lam], white[lam])
            out[lam] = alb / np.pi * g[lam].sum(-1)[:, None]
        smp = ~lam
        if np.any(smp):
            xs = x[smp]
            wo = self.camera - xs
            wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
            wis = wi[smp]
            wob = np.broadcast_to(wo[:, None, :], wis.shape)
            if self.surface.spatial:
                f = np.asarray(self.surface.brdf.eval_at(xs, wis, wob))
            elif rk is None:  # the numpy reference path
                f = np.asarray(self.surface.brdf.eval(wis, wob))
            else:
                f = _eval_kernel_size(self.surface.brdf, wis, wob)
            f = np.nan_to_num(f, nan=0.0)
            val = np.einsum("mkc,mk->mc", f, g[smp])
            scale = self.surface.albedo_scale(xs)
            out[smp] = val if scale is None else val * scale
        return out * light.rgb

    def _shade_nodes_fused(self, rk, x, region, white, y, w) -> np.ndarray:
        """:meth:`_shade_nodes` without occluders by the kernels (the same expressions
        in the same order): the holder's and patch's points in one fused pass
        (``lambert_shade``), the node directions only for the sample's points."""
        light = self.light
        m, k = x.shape[0], y.shape[-2]
        yk = np.ascontiguousarray(np.reshape(y, (-1, k, 3)), dtype=np.float64)
        wk = np.ascontiguousarray(np.reshape(w, (-1, k)), dtype=np.float64)
        face = None if light.is_point else light.face(y)
        fk = np.zeros((0, k)) if face is None else np.ascontiguousarray(np.reshape(face, (-1, k)))
        normal = np.ascontiguousarray(light.normal, dtype=np.float64)
        rgb = np.ascontiguousarray(np.broadcast_to(light.rgb, (3,)), dtype=np.float64)
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.zeros((m, 3))
        table = self.surface.albedo_rows()
        point, n_prof = bool(light.is_point), float(light.profile_n)
        rk.lambert_shade(x, region, white, yk, wk, normal, point, n_prof, fk, table, rgb, out)
        smp = np.flatnonzero(region == SAMPLE)  # an index: rows taken and put ~3x faster
        if not len(smp):
            return out
        xs = _take(x, smp)
        ms = xs.shape[0]

        # per-point node rows (stratified MC) follow their points; one row serves all
        def rows(a):
            return a if a.shape[0] <= 1 else np.ascontiguousarray(_take(a, smp))

        wis, g = np.empty((ms, k, 3)), np.empty((ms, k))
        rk.node_geometry(xs, rows(yk), rows(wk), normal, point, n_prof, rows(fk), wis, g)
        wo = self.camera - xs
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
        wob = np.broadcast_to(wo[:, None, :], wis.shape)
        if self.surface.spatial:
            f = np.asarray(self.surface.brdf.eval_at(xs, wis, wob))
        else:
            f = _eval_kernel_size(self.surface.brdf, wis, wob)
        f = np.nan_to_num(f, nan=0.0)
        val = np.einsum("mkc,mk->mc", f, g)
        scale = self.surface.albedo_scale(xs)
        _put_rows(out, smp, (val if scale is None else val * scale) * light.rgb)
        return out


def _eval_kernel_size(brdf: Any, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """``brdf.eval(wi, wo)`` (..., 3) on the numba path, a measured RGL file's batch
    padded up to the size from which :mod:`gonio.brdf` evaluates it by its kernel.

    The same values bit for bit (``tests/brdf/test_kernels.py`` holds the kernel equal
    to the numpy path), ~8x faster: a 320 x 240 frame's sample is 1-4k pairs (its
    pixel centres, then its anti-aliasing sub-rays), where the numpy path costs ~1.1
    ms a call and the kernel ~0.13 ms for 4096 pairs.  Importing
    :mod:`gonio.brdf.kernels` lets the file use its kernel below 10^5 pairs too (its
    own rule loads the kernel only for a large batch): with the renderer's numba
    already loaded that costs a process ~0.03 s once (a realistic RGL camera's first
    frame 0.55 -> 0.58 s), back in ~25 frames.  Analytic models stay as they are (numpy is
    faster there at these sizes); padding pairs are (0, 0, 0), below the horizon: 0 at
    no cost.  Both of gonio.brdf's paths give their values in C order, so the node
    sum's einsum rounds the same whichever ran.
    """
    rgl = sys.modules.get("gonio.brdf.rgl")  # not loaded: not an RGL file
    if rgl is None or not isinstance(brdf, rgl.RGLBRDF):
        return np.asarray(brdf.eval(wi, wo))
    from gonio.brdf import kernels

    shape = np.broadcast_shapes(wi.shape, wo.shape)
    n = int(np.prod(shape[:-1]))
    if n == 0:
        return np.asarray(brdf.eval(wi, wo))
    m = max(n, kernels.MIN_PAIRS)
    a = np.zeros((m, 3))
    b = np.zeros((m, 3))
    a[:n] = np.broadcast_to(wi, shape).reshape(-1, 3)
    b[:n] = np.broadcast_to(wo, shape).reshape(-1, 3)
    f = np.asarray(brdf.eval(a, b))[:n]
    return f.reshape(shape[:-1] + f.shape[-1:])


def _levels_for(light: PreparedLight) -> tuple[int, ...]:
    return (0,) if light.is_point else LEVELS


def _choose(
    integ: _Integrator, xs, region, white, tol, settings, rng
) -> tuple[str, int, int, float, bool]:
    """Pick (strategy, level, n_mc, estimated error, met) for one light on pilot points."""
    light = integ.light
    if light.is_point:
        return "point", 0, 0, 0.0, True
    mode = settings.strategy
    if mode == "point":
        return "point", 0, 0, float("nan"), False
    if mode == "quadrature":
        return "quadrature", settings.quadrature_order, 0, float("nan"), False
    if mode == "mc":
        return "mc", 0, settings.mc_samples, float("nan"), False
    # Penumbra points are refined separately (see render): estimate on the others.
    smooth = ~integ.partial(xs)
    xs, region, white = xs[smooth], region[smooth], white[smooth]
    if len(xs) == 0:  # nothing smooth to estimate on
        return "quadrature", settings.quadrature_order, 0, float("nan"), False

    def rel_err(a, b):
        floor = 1e-3 * max(float(np.max(np.abs(b))), 1e-300)
        return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), floor)))

    prev = integ.shade(xs, region, white, "quadrature", 0)
    levels = [k for k in _levels_for(light) if light.n_nodes(k) <= _QUAD_MAX]
    err = np.inf
    for k0, k1 in zip(levels[:-1], levels[1:], strict=True):
        cur = integ.shade(xs, region, white, "quadrature", k1)
        err = rel_err(prev, cur)
        if err <= _SAFETY * tol:
            return ("point" if k0 == 0 else "quadrature"), k0, 0, err, True
        prev = cur
    # Quadrature converges slowly where the integrand is not smooth (penumbrae, measured
    # BRDFs interpolated piecewise): try stratified MC, its sample count scaled from the
    # spread of two independent estimates, and keep it only if it is predicted to meet
    # the tolerance; otherwise the finest quadrature, flagged as not meeting it.
    n0 = 64
    a = integ.shade(xs, region, white, "mc", 0, n0, rng)
    b = integ.shade(xs, region, white, "mc", 0, n0, rng)
    sigma = rel_err(a, b) / np.sqrt(2.0)  # max over pilots of one estimate's error
    n = int(np.ceil(n0 * (sigma / (_SAFETY * tol)) ** 2))
    if max(n, 16) <= _MC_MAX:
        return "mc", 0, max(n, 16), sigma * np.sqrt(n0 / max(n, 16)), True
    return "quadrature", levels[-1], 0, err, False


def _kernels(points: int) -> Any:
    """:mod:`gonio.simulator.render_kernels` for a batch of ``points``, or None: small
    batches (numba's import would cost more than it saves) and ``GONIO_NUMBA=0`` stay
    on the numpy path, the reference."""
    if points < _MIN_KERNEL_POINTS or os.environ.get("GONIO_NUMBA") == "0":
        return None
    from gonio.simulator import render_kernels

    return render_kernels


def _kernel(rk: Any, name: str, points: int) -> Any:
    """Kernel ``name`` of module ``rk``: its multi-threaded build for large batches."""
    return getattr(rk, name if points >= rk.PARALLEL_POINTS else name + "_serial")


def _edges(code_c: np.ndarray, code_k: np.ndarray, print_only: bool = False) -> Any:
    """Pixels (H, W) bool whose centre's code (H, W) differs from any of its four
    corners' (H + 1, W + 1): numpy, or the kernel (the same booleans) for many; with
    ``print_only`` also (edge, :func:`_print_only`) in one pass."""
    rk = _kernels(code_c.size)
    if rk is None:
        k = code_k
        corners = np.stack([k[:-1, :-1], k[1:, :-1], k[:-1, 1:], k[1:, 1:]])
        edge = np.any(corners != code_c[None], axis=0)
        return (edge, edge & _print_only(code_c, code_k)) if print_only else edge
    out = np.empty(code_c.shape, bool)
    cc, ck = np.ascontiguousarray(code_c), np.ascontiguousarray(code_k)
    if not print_only:
        rk.edge_pixels(cc, ck, out)
        return out
    pr = np.empty(code_c.shape, bool)
    rk.edge_print_pixels(cc, ck, HOLDER, out, pr)
    return out, pr


def _print_only(code_c: np.ndarray, code_k: np.ndarray) -> np.ndarray:
    """Pixels (H, W) whose centre sees the holder and whose corners' codes differ from
    the centre's in the print bit (8) alone (see :func:`_codes`)."""
    base = code_c & ~np.int64(8)
    k = code_k & ~np.int64(8)
    same = (
        (k[:-1, :-1] == base) & (k[1:, :-1] == base) & (k[:-1, 1:] == base) & (k[1:, 1:] == base)
    )
    return same & ((code_c & 7) == HOLDER)


def _coverage(
    xc: np.ndarray, cj: np.ndarray, ci: np.ndarray, cells: Any, R: np.ndarray, C: np.ndarray
) -> np.ndarray:
    """White print coverage (P,) of pixels (cj, ci) whose corner rays meet z = 0 at
    ``xc`` (H + 1, W + 1, 3): the numba kernel, or the numpy reference
    (:func:`gonio.simulator.print_coverage.coverage_numpy`) for small batches and
    ``GONIO_NUMBA=0``."""
    from gonio.simulator.print_coverage import coverage_numpy

    rk = _kernels(16 * len(cj))
    if rk is None:
        quad = np.stack([xc[cj, ci], xc[cj, ci + 1], xc[cj + 1, ci + 1], xc[cj + 1, ci]], 1)
        return coverage_numpy(quad, cells, R, C)
    out = np.empty(len(cj))
    rk.print_coverage_grid(
        np.ascontiguousarray(xc, dtype=np.float64),
        np.ascontiguousarray(cj, dtype=np.int64),
        np.ascontiguousarray(ci, dtype=np.int64),
        cells.col_edges,
        cells.row_edges,
        cells.black,
        cells.scale,
        np.ascontiguousarray(R, dtype=np.float64),
        np.ascontiguousarray(C, dtype=np.float64),
        out,
    )
    return out


def _take(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` (rows of ``a`` by an index array): ``np.take`` copies whole rows, ~3x
    faster than fancy indexing (0.09 against 0.32 ms for 39k of 77k (N, 3) rows)."""
    return np.take(a, idx, axis=0)


_ROW = np.dtype((np.void, 24))  # one (3,) float64 row as one item


def _put_rows(a: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> None:
    """``a[idx] = rows`` for a C-contiguous (N, 3) float64 ``a``: ``np.put`` of 24-byte
    items, ~3x faster than fancy assignment of rows (the same bytes)."""
    if not (a.flags.c_contiguous and a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3):
        a[idx] = rows
        return
    v = np.ascontiguousarray(np.broadcast_to(rows, (len(idx), 3)), dtype=np.float64)
    np.put(a.view(_ROW).reshape(-1), idx, v.view(_ROW).reshape(-1))


def _box_filter(sub: np.ndarray, n: int, ej: np.ndarray, ei: np.ndarray, image: np.ndarray):
    """``image[ej, ei]`` (H, W, 3) = the mean of each pixel's ``n`` sub-samples (rows of
    ``sub`` (P n, 3), pixel by pixel): numpy, or the kernel (the same bits) for many."""
    rk = _kernels(sub.shape[0])
    if rk is None:
        image[ej, ei] = sub.reshape(len(ej), n, 3).mean(1)
    else:
        rk.subsample_mean(np.ascontiguousarray(sub), int(n), ej, ei, image)


def _hits(
    surface: Surface, C: np.ndarray, R: np.ndarray, xn: np.ndarray, yn: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Surface points (..., 3), in front (...), region (...) uint8 and board print
    (...) bool of the rays through undistorted normalised image points (xn, yn)."""
    rk = _kernels(xn.size)
    if rk is None:
        x, front = intersect_plane_z0(C, rays_from_normalized(R, xn, yn))
        region, white = surface.classify(x, front)
        return x, front, region, white
    n = xn.size
    x = np.empty((n, 3))
    front = np.empty(n, bool)
    region = np.empty(n, np.uint8)
    white = np.empty(n, bool)
    _kernel(rk, "label_points", n)(
        # read-only views: the writeable flag is part of numba's argument type (see
        # gonio.brdf.base.readonly), and the rays arrive either way
        readonly(np.ascontiguousarray(xn, dtype=np.float64).reshape(-1)),
        readonly(np.ascontiguousarray(yn, dtype=np.float64).reshape(-1)),
        np.ascontiguousarray(R, dtype=np.float64),
        np.ascontiguousarray(C, dtype=np.float64),
        *surface.kernel_args(),
        x,
        front,
        region,
        white,
    )
    shape = xn.shape
    return (
        x.reshape(shape + (3,)),
        front.reshape(shape),
        region.reshape(shape),
        white.reshape(shape),
    )


def _codes(
    region: np.ndarray, white: np.ndarray, occ_cam, C, x, light_vis
) -> tuple[np.ndarray, np.ndarray]:
    """Region with occluded points marked (a new array when there are occluders), and the
    code whose change between a pixel's centre and corners marks an edge (region, print,
    light-centre visibility bits)."""
    if occ_cam:
        region = region.copy()
        seen = region > 0
        blk = np.zeros_like(seen)
        blk[seen] = segments_blocked(occ_cam, C, x[seen])
        region[blk] = OCCLUDED
    # region + 8 white in int64, with one temporary instead of three
    code = white.astype(np.int64)
    code <<= 3
    code += region
    for bit, (occ, center) in enumerate(light_vis):
        lit = region > 0
        sh = np.zeros_like(lit)
        sh[lit] = segments_blocked(occ, x[lit], center)
        code = code + (16 << bit) * sh
    return region, code


def _subpixel_normalized(
    K: np.ndarray, ei: np.ndarray, ej: np.ndarray, n_aa: int, dist, grid=None
) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of the n_aa x n_aa sub-pixel points of pixels
    (ei, ej), (len(ei) * n_aa^2,) each, pixel by pixel; ``grid`` the pixel centres'
    (:func:`pixel_grid`, the kernel's starting points; computed when not given)."""
    m = len(ei) * n_aa * n_aa
    rk = _kernels(m)
    if rk is None:
        off = (np.arange(n_aa) + 0.5) / n_aa
        ou, ov = np.meshgrid(off, off, indexing="ij")
        su = (ei[:, None] + ou.ravel()).ravel()
        sv = (ej[:, None] + ov.ravel()).ravel()
        return _normalized(K, su, sv, dist)
    xn, yn, err = np.empty(m), np.empty(m), np.empty(m)
    has = dist is not None and bool(np.any(np.asarray(dist, float) != 0.0))
    if has and grid is None:
        grid = pixel_grid(K, int(ei.max()) + 1, int(ej.max()) + 1, dist)
    _kernel(rk, "subpixel_normalized", m)(
        np.ascontiguousarray(ei, dtype=np.int64),
        np.ascontiguousarray(ej, dtype=np.int64),
        int(n_aa),
        np.ascontiguousarray(K, dtype=np.float64),
        np.asarray(dist, float) if has else np.zeros(0),
        *(grid if has else (np.zeros((0, 0)), np.zeros((0, 0)))),
        _UNDISTORT_TOL,
        _NEWTON_MAX,
        xn,
        yn,
        err,
    )
    bad = ~(err <= UNDISTORT_ACCURACY)
    if np.any(bad):
        # the numpy path names the first point where the lens model folds over
        off = (np.arange(n_aa) + 0.5) / n_aa
        ou, ov = np.meshgrid(off, off, indexing="ij")
        su = (ei[:, None] + ou.ravel()).ravel()[bad]
        sv = (ej[:, None] + ov.ravel()).ravel()[bad]
        _normalized(K, su, sv, dist)
    return xn, yn


def _spot_code(lights, light_occ, C, x, region) -> np.ndarray:
    """Bit i set where a mirror point's reflected camera ray reaches light i."""
    code = np.zeros(region.shape, np.int64)
    on = region == SAMPLE
    for bit, (light, occ) in enumerate(zip(lights, light_occ, strict=True)):
        hit = np.zeros(region.shape, bool)
        hit[on] = light_hits(light, occ, C, x[on])
        code += np.int64(1 << bit) * hit
    return code


def estimate_render_memory(scene: Scene, antialias: int | None = None) -> float:
    """Peak memory of :func:`render` for the scene's resolution and anti-aliasing, bytes.

    ``W H (400 + 0.1 n^2 150)`` for ``n`` sub-samples per axis: measured per-pixel and
    per-sub-sample peaks with edge pixels assumed to be 10 % of the image.
    """
    w, h = scene.camera.resolution
    n = scene.render.antialias if antialias is None else int(antialias)
    sub = _EDGE_FRACTION * n * n * _BYTES_PER_SUBSAMPLE if n > 1 else 0.0
    return float(w) * float(h) * (_BYTES_PER_PIXEL + sub)


def render_memory_limit() -> float:
    """Default memory allowed to one render: half of the physical memory, bytes."""
    try:
        return 0.5 * float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 8e9


def _check_memory(scene: Scene, antialias: int | None, limit: float | None) -> None:
    need = estimate_render_memory(scene, antialias)
    cap = render_memory_limit() if limit is None else float(limit)
    if need > cap:
        w, h = scene.camera.resolution
        n = scene.render.antialias if antialias is None else antialias
        raise ConfigError(
            f"camera.resolution: rendering {w} x {h} pixels with render.antialias = {n} "
            f"would need about {need / 1e9:.3g} GB of memory, more than the "
            f"{cap / 1e9:.3g} GB allowed"
            + (" (half of this machine's memory)" if limit is None else "")
            + "; lower the resolution or the anti-aliasing, or raise the limit "
            "(gonio sim render --max-memory-gb)"
        )


def render(
    scene: Scene,
    *,
    tolerance: float | None = None,
    strategy: str | None = None,
    antialias: int | None = None,
    seed: int | None = None,
    brdf: Any = None,
    max_memory_bytes: float | None = None,
    direct: bool = True,
    diffuse: bool = False,
    sample_albedo: Callable[..., np.ndarray] | None = None,
) -> RenderResult:
    """Render the scene's camera view of the sample plane.

    Parameters
    ----------
    scene
        The scene (poses in the sample frame, metres).
    tolerance, strategy, antialias, seed
        Override ``scene.render`` (see :class:`gonio.simulator.scene.RenderSettings`).
    brdf
        An already built sample BRDF (``eval(wi, wo) -> (..., 3)``) to use instead of
        building ``scene.sample.brdf`` again (measured files are slow to load).
    max_memory_bytes
        Refuse a render whose :func:`estimate_render_memory` exceeds this (bytes;
        default :func:`render_memory_limit`), before allocating anything.
    direct
        Integrate the lights (False: a frame with the light off; ``radiance`` is zero,
        and a camera that does not see the sample is not an error).
    diffuse
        Also return :attr:`RenderResult.diffuse` (the response to uniform diffuse light).
    sample_albedo
        ``theta_o -> (M, 3)`` directional albedo of ``brdf`` (:func:`albedo_table`,
        tabulated once per BRDF by the caller); default: tabulated here.

    Returns
    -------
    RenderResult
        Radiance image (W/(sr m^2), camera RGB) with ground truth and stats.

    Raises
    ------
    ConfigError
        The camera does not see the sample (it is reported, not rendered black), or
        the render would need more memory than allowed.
    """
    _check_memory(scene, antialias, max_memory_bytes)
    t0 = time.perf_counter()
    upd = {
        k: v
        for k, v in dict(
            tolerance=tolerance, strategy=strategy, antialias=antialias, seed=seed
        ).items()
        if v is not None
    }
    settings = scene.render.model_copy(update=upd)
    rng = np.random.default_rng(settings.seed)
    C, R = scene.camera_pose()
    if C[2] <= 0:
        raise ConfigError(f"camera.position: {C.tolist()} is not above the sample plane (z > 0)")
    K = scene.camera.intrinsics()
    dist = scene.camera.distortion if scene.camera.has_distortion else None
    W, H = scene.camera.resolution
    surface = Surface(scene, brdf)
    lights = prepare_lights(scene)
    occluders = prepare_occluders(scene.occluders)
    lo, hi = surface.extent()

    # Bounding tests: an occluder matters for a light only if it meets the box around the
    # surface and the emitter, for the camera only if it meets the box around both.
    light_occ = []
    for light in lights:
        pts = np.vstack([light.extent_points(), lo, hi])
        light_occ.append([o for o in occluders if o.overlaps(pts.min(0), pts.max(0))])
    cam_box = np.vstack([C, lo, hi])
    occ_cam = [o for o in occluders if o.overlaps(cam_box.min(0), cam_box.max(0))]
    light_vis = [(oc, li.center) for li, oc in zip(lights, light_occ, strict=True) if oc]

    # Pixel centres and corners (their undistorted coordinates are cached per camera).
    x, _, region, white = _hits(surface, C, R, *pixel_grid(K, W, H, dist))
    region, code_c = _codes(region, white, occ_cam, C, x, light_vis)
    xc, _, region_k, white_k = _hits(surface, C, R, *pixel_grid(K, W, H, dist, True))
    region_k, code_k = _codes(region_k, white_k, occ_cam, C, xc, light_vis)
    if direct and not (np.any(region == SAMPLE) or np.any(region_k == SAMPLE)):
        raise ConfigError(
            f"camera: at {np.round(C, 4).tolist()} the camera does not see the sample "
            f"({scene.sample.width:g} x {scene.sample.height:g} m at the origin); "
            "check camera.position, look_at/rotation and the field of view"
        )
    # Edges of the board print alone (centre and corners on the holder, the same light
    # visibility, only the print's colour differs): their box filter is the print's exact
    # area coverage times the two albedos' radiances (gonio.simulator.print_coverage),
    # not antialias^2 sub-rays.  Every other edge keeps its rays.
    exact = settings.print_antialias == "exact" and surface.board_img is not None
    cover = np.zeros((H, W), bool)
    if settings.antialias <= 1:
        edge = np.zeros((H, W), bool)
    elif exact:
        edge, cover = _edges(code_c, code_k, print_only=True)
        edge &= ~cover
    else:
        edge = _edges(code_c, code_k)
    surf = (region > 0) & (region != OCCLUDED)
    mirror = surface.mirror is not None
    spot_rim = np.zeros((H, W), bool)
    if mirror and direct:
        # The light's image in the mirror has a hard rim: pixels whose centre and corners
        # do not all see the same lights get spot_antialias^2 sub-rays (even when the
        # rest of the image is not anti-aliased), so that the spot's centroid is unbiased.
        sc = _spot_code(lights, light_occ, C, x, region)
        sk = _spot_code(lights, light_occ, C, xc, region_k)
        sk4 = np.stack([sk[:-1, :-1], sk[1:, :-1], sk[:-1, 1:], sk[1:, 1:]])
        spot_rim = np.any(sk4 != sc[None], axis=0)
        edge &= ~spot_rim

    radiance = np.zeros((H, W, 3))
    # a frame with the light off integrates no light
    integrators = [
        _Integrator(li, oc, surface, C) for li, oc in zip(lights, light_occ, strict=True)
    ]
    if not direct:
        integrators, light_occ = [], []
    # The shaded pixels by their flat indices: gathering (and later scattering) rows
    # through one index array costs half what three boolean masks of the image do.
    at = np.flatnonzero(surf)
    xs, rs, ws = (
        _take(x.reshape(-1, 3), at),
        _take(region.reshape(-1), at),
        _take(white.reshape(-1), at),
    )
    # the mirror is not integrated over the lights: the strategy is chosen without it
    # only "auto" estimates on pilot pixels (and only for area lights): none otherwise
    pilot = np.zeros(0, np.intp)
    if settings.strategy == "auto" and any(not i.light.is_point for i in integrators):
        lit = np.flatnonzero(rs != SAMPLE) if mirror else np.arange(len(xs))
        n_pilot = min(_PILOT_PIXELS, len(lit))
        pilot = lit[np.unique(np.linspace(0, len(lit) - 1, n_pilot).astype(int))]
    light_stats = []
    plans = []
    for integ, oc in zip(integrators, light_occ, strict=True):
        strat, level, n_mc, err, met = _choose(
            integ, xs[pilot], rs[pilot], ws[pilot], settings.tolerance, settings, rng
        )
        plans.append((strat, level, n_mc))
        nodes = n_mc if strat == "mc" else integ.light.n_nodes(level)
        light_stats.append(
            LightStats(
                integ.light.kind,
                strat,
                None if strat == "mc" else level,
                nodes,
                err,
                met,
                len(oc),
                len(occluders) - len(oc),
            )
        )

    # Penumbrae: where an occluder hides part of a light, the integrand jumps and the
    # level chosen on smooth pixels is too coarse; those points get the finest rule.
    penumbra = {}
    for i, (integ, (_, level, _)) in enumerate(zip(integrators, plans, strict=True)):
        if settings.strategy == "auto" and integ.occ and not integ.light.is_point:
            lv = [k for k in LEVELS if integ.light.n_nodes(k) <= _QUAD_MAX]
            if lv[-1] > level:
                penumbra[i] = lv[-1]
                pp = pilot[integ.partial(xs[pilot])]
                if len(pp):
                    fine = integ.shade(xs[pp], rs[pp], ws[pp], "quadrature", lv[-1])
                    coarse = integ.shade(xs[pp], rs[pp], ws[pp], "quadrature", lv[-2])
                    # relative to the unshadowed value: a tiny lit sliver of the light
                    # is a small error however large relative to itself
                    free = _Integrator(integ.light, [], surface, C).shade(
                        xs[pp], rs[pp], ws[pp], "quadrature", max(level, 1)
                    )
                    floor = 1e-3 * max(float(np.max(np.abs(free))), 1e-300)
                    light_stats[i].penumbra_error = float(
                        np.max(np.abs(coarse - fine) / np.maximum(np.abs(free), floor))
                    )
                light_stats[i].penumbra_nodes = integ.light.n_nodes(lv[-1])
                if light_stats[i].penumbra_error > settings.tolerance:
                    light_stats[i].tolerance_met = False

    def shade_all(xp, rp, wp):
        if not direct:
            return np.zeros((len(xp), 3))
        if mirror:
            acc = np.zeros((len(xp), 3))
            on = rp == SAMPLE
            acc[on] = mirror_radiance(lights, light_occ, C, xp[on], surface.mirror)
            acc[~on] = shade_lit(xp[~on], rp[~on], wp[~on])
            return acc
        return shade_lit(xp, rp, wp)

    def shade_lit(xp, rp, wp):
        acc = np.zeros((len(xp), 3))
        for i, (integ, (strat, level, n_mc)) in enumerate(zip(integrators, plans, strict=True)):
            out = integ.shade(xp, rp, wp, strat, level, n_mc, rng, settings.chunk_size)
            if i in penumbra:
                pm = integ.partial(xp, settings.chunk_size)
                if pm.any():
                    out[pm] = integ.shade(
                        xp[pm],
                        rp[pm],
                        wp[pm],
                        "quadrature",
                        penumbra[i],
                        chunk=settings.chunk_size,
                    )
                    light_stats[i].penumbra_points += int(pm.sum())
            acc += out
        return acc

    _put_rows(radiance.reshape(-1, 3), at, shade_all(xs, rs, ws))
    diff = None
    if diffuse:
        if sample_albedo is None and surface.brdf is not None:
            sample_albedo = albedo_table(surface.brdf)

        def diffuse_all(xp, rp, wp):
            a = surface.diffuse_albedo(xp, rp, wp, C, sample_albedo)  # a new array
            return np.divide(a, np.pi, out=a)

        diff = np.zeros((H, W, 3))
        _put_rows(diff.reshape(-1, 3), at, diffuse_all(xs, rs, ws))

    if cover.any():
        # the two print colours' radiances weighted by the white print's share of the
        # pixel's area
        q = np.flatnonzero(cover)
        cj, ci = np.divmod(q, W)
        cw = _coverage(xc, cj, ci, surface.print_cells(), R, C)[:, None]
        wq = _take(white.reshape(-1), q)[:, None]
        a_w, a_b = surface.white, surface.black
        blend = cw * a_w + (1.0 - cw) * a_b  # the pixel's mean albedo (P, 3)
        if np.all(a_w > 0) and np.all(a_b > 0):
            # a Lambertian point's radiance is its albedo times the rest (every strategy,
            # with or without occluders): rescale the centre's instead of shading again
            flat = radiance.reshape(-1, 3)
            _put_rows(flat, q, _take(flat, q) * (blend / np.where(wq, a_w, a_b)))
            if diff is not None:
                _put_rows(diff.reshape(-1, 3), q, blend / np.pi)
        else:  # an albedo of 0: shade the centre with the other colour
            xq, rq = x.reshape(-1, 3)[q], region.reshape(-1)[q]
            fns = ((radiance, shade_all), (diff, diffuse_all if diff is not None else None))
            for img, fn in fns:
                if img is None:
                    continue
                flat = img.reshape(-1, 3)
                own, other = flat[q], fn(xq, rq, ~wq[:, 0])
                lw = np.where(wq, own, other)
                lb = np.where(wq, other, own)
                flat[q] = cw * lw + (1.0 - cw) * lb

    # Anti-aliasing: n x n sub-pixel samples (box filter) on edge pixels only.
    n_sub = 0
    for mask, n_aa in ((edge, settings.antialias), (spot_rim, settings.spot_antialias)):
        if not mask.any():  # (spot_rim without a mirror): nonzero costs ~0.1 ms a frame
            continue
        ej, ei = np.divmod(np.flatnonzero(mask), W)  # np.nonzero's order, 10x faster
        if not len(ej):
            continue
        xsub, _, rsub, wsub = _hits(
            surface, C, R, *_subpixel_normalized(K, ei, ej, n_aa, dist, pixel_grid(K, W, H, dist))
        )
        rsub, _ = _codes(rsub, wsub, occ_cam, C, xsub, [])
        n_rays = len(rsub)
        ok = np.flatnonzero((rsub > 0) & (rsub != OCCLUDED))
        xsub, rsub, wsub = _take(xsub, ok), _take(rsub, ok), _take(wsub, ok)
        lsub = np.zeros((n_rays, 3))
        _put_rows(lsub, ok, shade_all(xsub, rsub, wsub))
        _box_filter(lsub, n_aa * n_aa, ej, ei, radiance)
        if diff is not None:
            dsub = np.zeros((n_rays, 3))
            _put_rows(dsub, ok, diffuse_all(xsub, rsub, wsub))
            _box_filter(dsub, n_aa * n_aa, ej, ei, diff)
        n_sub += n_rays
    edge = edge | spot_rim | cover

    def truth() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nan3 = np.full((H, W, 3), np.nan)
        pts = np.where(surf[..., None], x, nan3)
        wo = C - pts
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
        wi = lights[0].center - pts
        wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
        return wi, wo, pts

    stats = RenderStats(
        pixels=H * W,
        # count_nonzero: a tenth of the cost of bool.sum()'s add.reduce
        pixels_shaded=int(np.count_nonzero(surf)),
        pixels_skipped=int(np.count_nonzero(region == NONE)),
        pixels_occluded=int(np.count_nonzero(region == OCCLUDED)),
        edge_pixels=int(np.count_nonzero(edge)),
        subpixel_samples=n_sub,
        camera_occluders_tested=len(occ_cam),
        lights=light_stats,
        seconds=time.perf_counter() - t0,
        coverage_pixels=int(np.count_nonzero(cover)),
    )
    return RenderResult(radiance, None, None, None, region, edge, stats, diff, truth=truth)


def save_truth(
    path, result: RenderResult, scene: Scene | None = None, *, overwrite: bool = False
) -> None:
    """Write a render's ground truth to HDF5 (atomic: temporary file, then rename).

    Datasets: ``radiance`` (H, W, 3) W/(sr m^2), ``wi``, ``wo`` (H, W, 3) sample frame,
    ``points`` (H, W, 3) m, ``region`` (H, W) uint8 (attribute ``names``), ``edge``
    (H, W) bool; attributes ``stats`` (JSON) and ``scene`` (JSON, when given).  A
    spatially varying sample's scene adds ``texel`` (H, W) int64: the flat index
    ``row * nx + col`` of the pixel centre's texel in the finest map's grid (attribute
    ``texels`` = [nx, ny]; -1 off the sample), :mod:`gonio.simulator.svbrdf`'s
    convention.

    Raises
    ------
    FileFormatError
        ``path`` exists and ``overwrite`` is false.
    """
    import json
    from pathlib import Path

    import h5py

    from gonio.atomic import atomic_path
    from gonio.errors import FileFormatError

    p = Path(path)
    if p.exists() and not overwrite:
        raise FileFormatError(p, "exists; refusing to overwrite (use --force)")
    with atomic_path(p) as tmp, h5py.File(tmp, "w") as f:
        for name in ("radiance", "wi", "wo", "points", "region", "edge"):
            f.create_dataset(name, data=getattr(result, name), compression="gzip")
        f["region"].attrs["names"] = json.dumps(REGION_NAMES)
        if scene is not None and scene.sample.spatially_varying:
            from gonio.simulator.svbrdf import load_layout, texel_of

            ny, nx = load_layout(scene).shape
            pts = result.points
            r, c = texel_of(
                pts[..., 0], pts[..., 1], (scene.sample.width, scene.sample.height), (ny, nx)
            )
            idx = np.where(result.region == SAMPLE, r * nx + c, -1).astype(np.int64)
            f.create_dataset("texel", data=idx, compression="gzip")
            f["texel"].attrs["texels"] = [nx, ny]
        f.attrs["stats"] = json.dumps(result.stats.as_dict())
        f.attrs["frame"] = "sample"
        if scene is not None:
            f.attrs["scene"] = scene.model_dump_json()

"""Sensor model: radiance -> photo-electrons -> noise -> digital numbers -> Bayer mosaic.

Per pixel, for the channel its colour filter passes (camera RGB):

1. image-plane irradiance ``E = L pi / (4 N^2) cos^4(theta)`` (thin lens focused far away;
   ``cos^4`` is natural vignetting at field angle theta);
2. mean photo-electrons ``mu = QE_c E A t lambda_c / (h c) + dark_current t`` with pixel
   area A, exposure time t and the channel's effective wavelength lambda_c;
3. with a camera's fixed patterns (:mod:`gonio.simulator.sensor_defects`): PRNU gain,
   DSNU offset and hot pixels' dark charge applied to mu;
4. shot noise (Poisson in mu, which covers dark-current shot noise), Gaussian read noise,
   clipping at the full well;
5. gain ``g = gain_at_base_iso * ISO / base_iso`` DN per electron, black-level offset,
   rounding to integers, clipping to [0, 2^bits - 1].

Only the channel the colour filter passes is simulated at each site (selecting the
channel first and drawing the noise afterwards is statistically the same as mosaicking at
the end, and three times cheaper).  Every draw comes from the given seed.

The arithmetic around the draws runs in fused numba kernels
(:mod:`gonio.simulator.sensor_kernels`, the same bits) for frames of
``_MIN_KERNEL_SITES`` sites or more; ``GONIO_NUMBA=0`` keeps it on numpy (the reference).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from gonio.errors import ParameterError
from gonio.simulator.geometry import pixel_grid
from gonio.simulator.scene import MAX_EXPOSURE_S, Camera
from gonio.simulator.sensor_defects import FixedPattern

__all__ = [
    "RawFrame",
    "cfa_indices",
    "cfa_radiance",
    "colour_metadata",
    "default_flat_radiance",
    "electrons_per_radiance",
    "mean_electrons",
    "simulate_mosaic",
    "simulate_raw",
]

_H = 6.62607015e-34  # J s
_C = 299792458.0  # m/s
_CHANNEL = {"R": 0, "G": 1, "B": 2}


@dataclass
class RawFrame:
    """A simulated RAW frame and the metadata a DNG carries.

    Attributes
    ----------
    mosaic
        (H, W) uint16 Bayer mosaic, DN including the black level.
    cfa_pattern
        2x2 pattern read row by row, e.g. ``"RGGB"``.
    black_level, white_level
        DN.
    colour_matrix
        (3, 3) XYZ (D65) -> camera-native RGB, DNG ColorMatrix1 convention.
    as_shot_neutral
        (3,) camera response to the scene white, green = 1.
    exposure_time, f_number, iso, focal_length
        Capture settings (s, -, ISO, m).
    model
        Camera model name.
    """

    mosaic: np.ndarray
    cfa_pattern: str
    black_level: int
    white_level: int
    colour_matrix: np.ndarray
    as_shot_neutral: np.ndarray
    exposure_time: float
    f_number: float
    iso: float
    focal_length: float
    model: str = "gonio simulated camera"
    extra: dict = field(default_factory=dict)


def cfa_indices(pattern: str, shape: tuple[int, int]) -> np.ndarray:
    """Channel index (0 R, 1 G, 2 B) of every site of a ``shape`` mosaic."""
    p = np.array([_CHANNEL[c] for c in pattern]).reshape(2, 2)
    h, w = shape
    return np.tile(p, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


#: Largest Poisson mean drawn, electrons.  numpy refuses lam above ~9.2e18; any mean
#: this far above a full well (1e5 electrons at most on real sensors) saturates anyway,
#: so such pixels are set to the full well without a draw.  Below it the draws are
#: exactly those of a plain ``rng.poisson(mu)`` (same frames for the same seed).
_POISSON_MAX = 1e18
#: Frames from this many sites on run the fused kernels (below, numba's import and the
#: call cost more than they save).
_MIN_KERNEL_SITES = 4096


def _check(name: str, value: float, upper: float = np.inf) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be a positive number, got {value!r}")
    if v > upper:
        raise ParameterError(f"{name} must be at most {upper:g}, got {value!r}")
    return v


def mean_electrons(
    radiance: np.ndarray, camera: Camera, exposure_time: float, f_number: float
) -> np.ndarray:
    """Expected photo-electrons per pixel and channel (H, W, 3), without dark current.

    Parameters
    ----------
    radiance
        (H, W, 3) radiance, W/(sr m^2) per camera channel.
    camera
        Intrinsics and sensor parameters.
    exposure_time
        Seconds.
    f_number
        Aperture N.
    """
    s = camera.sensor
    h, w = radiance.shape[:2]
    irr = radiance * (np.pi / (4.0 * f_number**2))
    if s.vignetting:
        K = camera.intrinsics()
        if camera.has_distortion:
            # the field angle is the true ray's: undistorted normalised coordinates
            x, y = pixel_grid(K, w, h, camera.distortion)
            r2 = x * x + y * y
        else:
            v, u = np.mgrid[0:h, 0:w]
            r2 = ((u + 0.5 - K[0, 2]) ** 2 + (v + 0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2
        irr = irr * (1.0 / (1.0 + r2))[..., None] ** 2  # cos^4 = (1 + tan^2)^-2
    energy = irr * camera.pitch**2 * exposure_time  # J per pixel
    photons_per_joule = np.asarray(s.wavelength_nm) * 1e-9 / (_H * _C)
    qe = np.broadcast_to(np.asarray(s.quantum_efficiency, float), (3,))
    return energy * photons_per_joule * qe


def electrons_per_radiance(camera: Camera, exposure_time: float, f_number: float) -> np.ndarray:
    """Mean photo-electrons (3,) per unit radiance (W/(sr m^2)) at the image centre
    (no vignetting there), per channel."""
    s = camera.sensor
    qe = np.broadcast_to(np.asarray(s.quantum_efficiency, float), (3,))
    lam = np.asarray(s.wavelength_nm, float) * 1e-9
    return np.pi / (4.0 * f_number**2) * camera.pitch**2 * exposure_time * lam / (_H * _C) * qe


def default_flat_radiance(camera: Camera) -> np.ndarray:
    """The flat panel's default radiance (3,), W/(sr m^2), the same in every channel:
    half the full well at the image centre in the channel with most signal, at 10 ms,
    f/8 (ISO does not change the electrons)."""
    k = electrons_per_radiance(camera, 0.01, 8.0)
    return np.full(3, 0.5 * camera.sensor.full_well / float(k.max()))


def colour_metadata(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(ColorMatrix1, AsShotNeutral) for camera RGB taken as linear sRGB primaries.

    The scene's colours are given in camera RGB; the sensor's channels then differ only by
    quantum efficiency and photon energy, so the raw response to white is
    ``QE_c lambda_c`` (normalised to green), and XYZ -> camera is the sRGB matrix scaled by
    that neutral (the DNG convention: the illuminant's XYZ maps to the neutral).
    """
    s = camera.sensor
    qe = np.broadcast_to(np.asarray(s.quantum_efficiency, float), (3,))
    neutral = qe * np.asarray(s.wavelength_nm)
    neutral = neutral / neutral[1]
    cm = np.diag(neutral) @ _XYZ_TO_SRGB
    return cm / np.abs(cm @ _D65_XYZ).max(), neutral


# colour-science's sRGB XYZ -> RGB matrix (IEC 61966-2-1) and its ``xy_to_XYZ`` of D65
# (0.3127, 0.3290), as literals: importing colour costs the capture's process ~1 s of CPU
# (it imports matplotlib) for two constants; tests/simulator/test_dng.py holds them equal
# to colour's.
_XYZ_TO_SRGB = np.array(
    [[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.204, 1.057]]
)
_D65_XYZ = np.array([0.9504559270516716, 1.0, 1.0890577507598784])
_XYZ_TO_SRGB.flags.writeable = False
_D65_XYZ.flags.writeable = False


def cfa_radiance(radiance: np.ndarray, camera: Camera) -> np.ndarray:
    """The radiance (H, W) of the channel each site's colour filter passes, W/(sr m^2),
    from a (H, W, 3) image (NaN and negative values as 0)."""
    radiance = np.asarray(radiance, float)
    if radiance.ndim != 3 or radiance.shape[2] != 3:
        raise ParameterError(f"radiance must have shape (H, W, 3), got {radiance.shape}")
    k = _constants(camera, radiance.shape[:2])
    sites = radiance.reshape(-1)[k.flat_index].reshape(k.shape)
    return np.nan_to_num(np.maximum(sites, 0.0, out=sites), copy=False)


def simulate_raw(
    radiance: np.ndarray,
    camera: Camera,
    *,
    exposure_time: float | None = None,
    iso: float | None = None,
    f_number: float | None = None,
    seed: int | np.random.Generator = 0,
    fixed_pattern: FixedPattern | None = None,
) -> RawFrame:
    """Turn a radiance image into a noisy Bayer RAW frame.

    Parameters
    ----------
    radiance
        (H, W, 3) radiance, W/(sr m^2) per camera channel (see :mod:`gonio.simulator.render`).
    camera
        Camera with sensor parameters; its ``exposure_time``, ``iso`` and ``f_number``
        are used unless given here.
    exposure_time, iso, f_number
        Capture settings (s, ISO, N); positive and finite, the exposure at most
        :data:`~gonio.simulator.scene.MAX_EXPOSURE_S`.
    seed
        Seed or generator for every random draw: equal seeds give equal frames.
    fixed_pattern
        The camera's PRNU, DSNU and hot-pixel maps for this frame size
        (:func:`gonio.simulator.sensor_defects.fixed_pattern`), applied to the mean
        electrons before the noise draw; None: a sensor without them.

    Returns
    -------
    RawFrame

    Raises
    ------
    ParameterError
        A setting is not a positive finite number, or the exposure exceeds an hour.
    """
    settings = _settings(camera, exposure_time, iso, f_number)
    return simulate_mosaic(
        cfa_radiance(radiance, camera),
        camera,
        exposure_time=settings[0],
        iso=settings[2],
        f_number=settings[1],
        seed=seed,
        fixed_pattern=fixed_pattern,
    )


def simulate_mosaic(
    site_radiance: np.ndarray,
    camera: Camera,
    *,
    exposure_time: float | None = None,
    iso: float | None = None,
    f_number: float | None = None,
    seed: int | np.random.Generator = 0,
    fixed_pattern: FixedPattern | None = None,
) -> RawFrame:
    """:func:`simulate_raw` of a radiance already taken at the colour filters' sites.

    ``site_radiance`` (H, W), W/(sr m^2), non-negative and finite (:func:`cfa_radiance`):
    the same frame, bit for bit, as :func:`simulate_raw` of the (H, W, 3) image, without
    the work on the two channels a site does not see.  The other parameters as there.
    """
    t, n, iso_v = _settings(camera, exposure_time, iso, f_number)
    sites = np.asarray(site_radiance, float)
    if sites.ndim != 2:
        raise ParameterError(f"site radiance must have shape (H, W), got {sites.shape}")
    s = camera.sensor
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    k = _constants(camera, sites.shape)
    if fixed_pattern is not None and fixed_pattern.shape != sites.shape:
        raise ParameterError(
            f"fixed pattern of a {fixed_pattern.shape} frame given for a {sites.shape} frame"
        )
    gain = s.gain_at_base_iso * iso_v / s.base_iso
    kernels = sites.size >= _MIN_KERNEL_SITES and os.environ.get("GONIO_NUMBA") != "0"
    if kernels:
        mu, over, any_over = _mean_kernel(sites, camera, k, t, n, fixed_pattern)
    else:
        mu, over, any_over = _mean_numpy(sites, camera, k, t, n, fixed_pattern)
    counts = rng.poisson(mu)
    if kernels:
        from gonio.simulator.sensor_kernels import quantise, quantise_read

        mosaic = np.empty(mu.shape, np.uint16)
        # the read noise is drawn in the kernel, from rng, as rng.normal below draws it
        levels = (float(s.full_well), float(gain), float(s.black_level), float(s.white_level))
        if s.read_noise > 0:
            quantise_read(counts.reshape(-1), rng, float(s.read_noise), over.reshape(-1),
                          *levels, mosaic.reshape(-1))  # fmt: skip
        else:
            quantise(counts.reshape(-1), np.zeros(0), over.reshape(-1), *levels,
                     mosaic.reshape(-1))  # fmt: skip
    else:
        read = rng.normal(0.0, s.read_noise, mu.shape) if s.read_noise > 0 else None
        electrons = counts.astype(np.float64)
        if read is not None:
            electrons += read
        np.minimum(electrons, s.full_well, out=electrons)
        if any_over:
            electrons[over] = s.full_well
        electrons *= gain
        electrons += s.black_level
        np.rint(electrons, out=electrons)
        mosaic = np.clip(electrons, 0, s.white_level, out=electrons).astype(np.uint16)
    return RawFrame(
        mosaic=mosaic,
        cfa_pattern=s.cfa_pattern,
        black_level=s.black_level,
        white_level=s.white_level,
        colour_matrix=k.colour_matrix.copy(),
        as_shot_neutral=k.neutral.copy(),
        exposure_time=t,
        f_number=n,
        iso=iso_v,
        focal_length=camera.focal_length,
        model=s.model,
        extra={"gain_dn_per_electron": gain},
    )


def _mean_numpy(
    sites: np.ndarray,
    camera: Camera,
    k: _Constants,
    t: float,
    n: float,
    fixed_pattern: FixedPattern | None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Mean electrons (H, W) with the fixed patterns, the sites whose mean is beyond
    numpy's Poisson range (H, W) bool (their mean set to 0) and whether there are any."""
    s = camera.sensor
    # mean_electrons' products in its order (same bits), on the site's channel only
    with np.errstate(over="ignore"):  # an overflow is a saturated pixel (below)
        mu = sites * (np.pi / (4.0 * n**2))
        if k.vignette is not None:
            mu *= k.vignette
        mu *= camera.pitch**2
        mu *= t
        mu *= k.photons_per_joule
        mu *= k.qe
    if fixed_pattern is None:
        mu += s.dark_current * t
    else:
        with np.errstate(invalid="ignore"):  # inf * gain: saturated below
            mu = fixed_pattern.apply(mu, t, s.dark_current * t)
    # A mean beyond numpy's range (a huge radiance or exposure) is a saturated pixel.
    over = ~(mu <= _POISSON_MAX)
    any_over = bool(over.any())
    if any_over:
        mu[over] = 0.0
    return mu, over, any_over


def _mean_kernel(
    sites: np.ndarray,
    camera: Camera,
    k: _Constants,
    t: float,
    n: float,
    fixed_pattern: FixedPattern | None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`_mean_numpy` by the fused kernel (the same bits)."""
    from gonio.simulator.sensor_kernels import mean_electrons

    empty = np.zeros(0)
    fp = fixed_pattern
    mu = np.empty(sites.shape)
    over = np.empty(sites.shape, bool)
    any_over = mean_electrons(
        np.ascontiguousarray(sites, dtype=np.float64).reshape(-1),
        np.pi / (4.0 * n**2),
        empty if k.vignette is None else k.vignette.reshape(-1),
        camera.pitch**2,
        t,
        k.photons_per_joule.reshape(-1),
        k.qe.reshape(-1),
        empty if fp is None or fp.gain is None else fp.gain.reshape(-1),
        camera.sensor.dark_current * t,
        empty if fp is None or fp.dark_offset is None else fp.dark_offset.reshape(-1),
        empty if fp is None or not len(fp.hot_index) else fp.hot_map(),
        fp is not None,
        _POISSON_MAX,
        mu.reshape(-1),
        over.reshape(-1),
    )
    return mu, over, bool(any_over)


def _settings(
    camera: Camera, exposure_time: float | None, iso: float | None, f_number: float | None
) -> tuple[float, float, float]:
    t = _check(
        "exposure_time (s)",
        camera.exposure_time if exposure_time is None else exposure_time,
        MAX_EXPOSURE_S,
    )
    n = _check("f_number", camera.f_number if f_number is None else f_number)
    iso_v = _check("iso", camera.iso if iso is None else iso)
    return t, n, iso_v


@dataclass(frozen=True)
class _Constants:
    """What a camera's frames share: per-site channel factors, the vignetting map."""

    shape: tuple[int, int]
    flat_index: np.ndarray  # (H*W,) index of each site's channel in the (H*W*3) image
    vignette: np.ndarray | None  # (H, W) cos^4 of the field angle
    photons_per_joule: np.ndarray  # (H, W) of the site's channel
    qe: np.ndarray  # (H, W)
    colour_matrix: np.ndarray
    neutral: np.ndarray


_CONSTANTS: OrderedDict[tuple[str, tuple[int, int]], _Constants] = OrderedDict()
_CONSTANTS_SIZE = 8
# A camera's pose and exposure settings do not change its per-site constants.
_POSE_FIELDS = {"position", "look_at", "up", "rotation", "exposure_time", "iso", "f_number"}


def _constants(camera: Camera, shape: tuple[int, int]) -> _Constants:
    h, w = int(shape[0]), int(shape[1])
    key = (camera.model_dump_json(exclude=_POSE_FIELDS), (h, w))
    hit = _CONSTANTS.get(key)
    if hit is not None:
        _CONSTANTS.move_to_end(key)
        return hit
    s = camera.sensor
    idx = cfa_indices(s.cfa_pattern, (h, w))
    vignette = None
    if s.vignetting:
        K = camera.intrinsics()
        if camera.has_distortion:
            # the field angle is the true ray's: undistorted normalised coordinates
            x, y = pixel_grid(K, w, h, camera.distortion)
            r2 = x * x + y * y
        else:
            v, u = np.mgrid[0:h, 0:w]
            r2 = ((u + 0.5 - K[0, 2]) ** 2 + (v + 0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2
        vignette = (1.0 / (1.0 + r2)) ** 2  # cos^4 = (1 + tan^2)^-2
    ppj = np.asarray(s.wavelength_nm) * 1e-9 / (_H * _C)
    qe = np.broadcast_to(np.asarray(s.quantum_efficiency, float), (3,))
    cm, neutral = colour_metadata(camera)
    out = _Constants(
        (h, w),
        (np.arange(h * w) * 3 + idx.ravel()).astype(np.intp),
        vignette,
        ppj[idx],
        qe[idx],
        cm,
        neutral,
    )
    for a in (out.flat_index, out.photons_per_joule, out.qe, out.colour_matrix, out.neutral):
        a.flags.writeable = False
    if vignette is not None:
        vignette.flags.writeable = False
    _CONSTANTS[key] = out
    while len(_CONSTANTS) > _CONSTANTS_SIZE:
        _CONSTANTS.popitem(last=False)
    return out

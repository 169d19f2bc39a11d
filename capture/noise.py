"""Photon-transfer noise model of a camera, and its estimation from flat and dark frames.

The variance of a pixel's linear value ``S`` (DN above black) is

    var(S) = g * S + sigma_r**2 (+ 1/12 for quantisation)

with ``g`` the conversion gain in DN per photo-electron (shot noise: the electron count is
Poisson, so its variance in DN is ``g`` times the mean in DN) and ``sigma_r`` the read noise
in DN.  Both scale with the ISO gain: the model is stored at one ISO and
:meth:`NoiseModel.at_iso` rescales it, taking the read noise as input-referred (constant
in electrons), which is what a sensor with one analogue gain stage does.

Estimation (the classic photon-transfer curve, EMVA 1288 style): for pairs of flat frames
at several exposure levels, the variance of the difference of the two frames over two
removes fixed-pattern noise; its slope against the mean is ``g`` and the intercept
``sigma_r**2``.  Dark-frame pairs pin the intercept.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.atomic import write_text_atomic
from gonio.capture.raw import CHANNELS, RawFrame
from gonio.errors import ReductionError


@dataclass(frozen=True)
class NoiseModel:
    """Shot + read noise of a sensor at one ISO.

    Parameters
    ----------
    gain
        Conversion gain, DN per photo-electron, at ``iso``.
    read_noise
        Read noise standard deviation, DN, at ``iso``.
    iso
        ISO speed the two numbers refer to.
    quantisation
        Whether to add the 1/12 DN^2 of uniform quantisation.
    """

    gain: float
    read_noise: float
    iso: float = 100.0
    quantisation: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.gain) and self.gain > 0):
            raise ReductionError(f"noise model gain must be > 0 DN/e-, got {self.gain}")
        if not (np.isfinite(self.read_noise) and self.read_noise >= 0):
            raise ReductionError(f"noise model read noise must be >= 0 DN, got {self.read_noise}")

    def at_iso(self, iso: float | None) -> NoiseModel:
        """The model at another ISO (gain and read noise in DN scale with ISO)."""
        if iso is None or not np.isfinite(iso) or iso == self.iso:
            return self
        k = float(iso) / self.iso
        return NoiseModel(self.gain * k, self.read_noise * k, float(iso), self.quantisation)

    def variance(self, signal: ArrayLike, iso: float | None = None) -> NDArray[np.float64]:
        """Variance in DN^2 of a pixel whose expected linear value is ``signal`` DN.

        Negative expected signals (noise around zero) contribute no shot noise.
        """
        m = self.at_iso(iso)
        s = np.maximum(np.asarray(signal, dtype=np.float64), 0.0)
        return m.gain * s + m.read_noise**2 + (1.0 / 12.0 if self.quantisation else 0.0)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model as JSON (``noise.json``), atomically."""
        p = Path(path)
        doc = {"type": "gonio.noise_model", **asdict(self)}
        write_text_atomic(p, json.dumps(doc, indent=2) + "\n")
        return p

    @classmethod
    def load(cls, path: str | os.PathLike) -> NoiseModel:
        """Read a model written by :meth:`save`.

        Raises
        ------
        FileFormatError
            When the file cannot be read or is not JSON.
        ConfigError
            When a field is missing or out of range (names the file and the field).
        """
        # the document's model lives with the reduction's other configuration
        from gonio.capture.reduction_config import load_noise

        return load_noise(path)


@dataclass(frozen=True)
class PhotonTransfer:
    """Result of a photon-transfer estimation.

    Attributes
    ----------
    model
        The fitted :class:`NoiseModel` (all channels pooled).
    gain_per_channel
        Gain fitted per channel (R, G, B), DN/e-, to check that pooling is fair.
    means, variances
        The points of the curve (DN, DN^2), one per flat pair and channel.
    """

    model: NoiseModel
    gain_per_channel: NDArray[np.float64]
    means: NDArray[np.float64]
    variances: NDArray[np.float64]


#: Relative difference at which two frames' exposure times or f-numbers are different
#: settings: EXIF rationals (1/50 against 0.02) agree far better, a stop differs by 2x.
_SETTING_RTOL = 1e-3


def _pair_points(a: RawFrame, b: RawFrame) -> tuple[NDArray, NDArray]:
    if a.shape != b.shape:
        raise ReductionError(f"{a.name} and {b.name} differ in size; a pair must match")
    # The difference of a pair cancels the fixed pattern only at one signal level: frames
    # of two exposures give a variance of their difference dominated by the level step,
    # and a photon-transfer "gain" orders of magnitude off, written without complaint.
    for what, x, y in (
        ("exposure time", a.exposure_time, b.exposure_time),
        ("f-number", a.f_number, b.f_number),
    ):
        if np.isfinite(x) and np.isfinite(y) and not np.isclose(x, y, rtol=_SETTING_RTOL, atol=0):
            raise ReductionError(
                f"{a.name} and {b.name} differ in {what} ({x:g} and {y:g}); a pair is two "
                "frames shot with identical settings (give the frames pair by pair)"
            )
    ok = ~(a.saturated | b.saturated)
    diff = a.linear - b.linear
    avg = 0.5 * (a.linear + b.linear)
    means, varis = [], []
    for c in range(len(CHANNELS)):
        m = ok & (a.channel == c)
        if m.sum() < 16:
            means.append(np.nan)
            varis.append(np.nan)
            continue
        means.append(avg[m].mean())
        # var(a - b) = 2 var(pixel); the difference cancels fixed-pattern noise
        varis.append(diff[m].var(ddof=1) / 2.0)
    return np.array(means), np.array(varis)


def estimate_noise(
    flat_pairs: list[tuple[RawFrame, RawFrame]],
    dark_pairs: list[tuple[RawFrame, RawFrame]] | None = None,
    quantisation: bool = True,
) -> PhotonTransfer:
    """Fit gain and read noise from pairs of flat (and dark) frames.

    Parameters
    ----------
    flat_pairs
        Pairs of frames of a uniform, unsaturated target shot twice with identical
        settings; several exposure levels give a better slope.
    dark_pairs
        Optional pairs of dark frames (cap on) at the same ISO: pin the read noise.
    quantisation
        Passed on to the model (the fitted intercept then excludes the 1/12 DN^2).

    Returns
    -------
    PhotonTransfer

    Raises
    ------
    ReductionError
        Too few usable points, or a non-positive slope (no shot noise seen).
    """
    pts = [_pair_points(a, b) for a, b in flat_pairs] + [
        _pair_points(a, b) for a, b in (dark_pairs or [])
    ]
    if not pts:
        raise ReductionError("no flat frame pairs given")
    means = np.array([p[0] for p in pts])  # (P, 3)
    varis = np.array([p[1] for p in pts])
    isos = {f.iso for pair in flat_pairs + list(dark_pairs or []) for f in pair}
    iso = next(iter(isos)) if len(isos) == 1 else np.nan
    if len(isos) > 1:
        raise ReductionError(f"frames mix ISO settings {sorted(isos)}; estimate one ISO at a time")
    q = 1.0 / 12.0 if quantisation else 0.0
    ok = np.isfinite(means) & np.isfinite(varis)
    if len(pts) < 2 or ok.sum() < 2 or np.ptp(means[ok]) <= 0:
        raise ReductionError(
            "need flat pairs at two or more signal levels for a photon-transfer fit"
        )
    # Pooled weighted least squares: var = g * mean + r2, weights 1/var^2 (the variance of
    # a sample variance grows with its square).
    x, y = means[ok], varis[ok]
    w = 1.0 / np.maximum(y, 1e-12) ** 2
    A = np.stack([x, np.ones_like(x)], axis=1) * np.sqrt(w)[:, None]
    g, r2 = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)[0]
    if not g > 0:
        raise ReductionError(
            f"photon-transfer slope is {g:.3g} DN/e-: the flats show no shot noise"
        )
    per_ch = np.full(len(CHANNELS), np.nan)
    for c in range(len(CHANNELS)):
        okc = ok[:, c]
        if okc.sum() >= 2 and np.ptp(means[okc, c]) > 0:
            per_ch[c] = np.polyfit(means[okc, c], varis[okc, c], 1, w=1.0 / varis[okc, c])[0]
    model = NoiseModel(
        float(g),
        float(np.sqrt(max(r2 - q, 0.0))),
        float(iso) if np.isfinite(iso) else 100.0,
        quantisation,
    )
    return PhotonTransfer(model, per_ch, means, varis)

"""The sensor's fixed patterns: PRNU, DSNU and hot pixels.

A camera's defects are the same in every frame it takes: the maps are functions of the
world seed and the frame size only (``default_rng([seed, 16, k, height, width])``, one
stream ``k`` per map, so switching one defect off leaves the others' maps as they were),
built once per camera and applied to the mean electrons before the noise draw
(:func:`gonio.simulator.sensor.simulate_raw`):

``mu = gain * mu_signal + dark_current t + dark_offset + hot_current t``, clipped at 0,

- ``gain = 1 + N(0, prnu)`` per pixel (photo-response non-uniformity);
- ``dark_offset = N(0, dsnu_e)`` electrons per pixel (dark-signal non-uniformity);
- a fraction ``hot_pixel_fraction`` of the pixels (each independently) has a dark current
  ``U(0.5, 1.5) * hot_pixel_current_e_s`` e-/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gonio.simulator.world_radiometry import Radiometry

__all__ = ["FixedPattern", "fixed_pattern"]


@dataclass(frozen=True)
class FixedPattern:
    """A camera's fixed-pattern maps for one frame size (H, W).

    Attributes
    ----------
    gain
        (H, W) relative gain (PRNU), or None.
    dark_offset
        (H, W) dark offset, electrons (DSNU), or None.
    hot_index, hot_current
        Flat indices of the hot pixels (k,) and their dark current (k,), e-/s.
    """

    shape: tuple[int, int]
    gain: np.ndarray | None
    dark_offset: np.ndarray | None
    hot_index: np.ndarray
    hot_current: np.ndarray

    def apply(self, mu: np.ndarray, exposure_time: float, dark: float = 0.0) -> np.ndarray:
        """Mean electrons (H, W) with the defects: the signal part ``mu`` times the gain,
        plus the sensor's uniform dark charge ``dark`` (e-), the offsets and the hot
        pixels' dark charge in ``exposure_time`` s.  The result is clipped at 0 electrons
        (and is a new array)."""
        out = mu * self.gain if self.gain is not None else mu.copy()
        out += dark
        if self.dark_offset is not None:
            out += self.dark_offset
        if len(self.hot_index):
            out.ravel()[self.hot_index] += self.hot_current * exposure_time
        return np.maximum(out, 0.0, out=out)

    def hot_map(self) -> np.ndarray:
        """The hot pixels' dark current as a (H * W,) map, e-/s (0 elsewhere; built once):
        what the fused sensor kernel reads per site."""
        cached = self.__dict__.get("_hot_map")
        if cached is None:
            cached = np.zeros(self.shape[0] * self.shape[1])
            cached[self.hot_index] = self.hot_current
            cached.flags.writeable = False
            object.__setattr__(self, "_hot_map", cached)
        return cached


def fixed_pattern(radiometry: Radiometry, seed: int, shape: tuple[int, int]) -> FixedPattern | None:
    """The fixed patterns of a camera of world ``seed`` at frame ``shape`` (H, W), or None
    when the sensor has none."""
    if not radiometry.has_fixed_pattern:
        return None
    h, w = (int(shape[0]), int(shape[1]))

    def rng(k: int) -> np.random.Generator:
        return np.random.default_rng([int(seed), 16, k, h, w])

    gain = None
    if radiometry.prnu:
        gain = 1.0 + rng(1).normal(0.0, radiometry.prnu, (h, w))
    offset = None
    if radiometry.dsnu_e:
        offset = rng(2).normal(0.0, radiometry.dsnu_e, (h, w))
    index = np.zeros(0, np.intp)
    current = np.zeros(0)
    if radiometry.hot_pixel_fraction and radiometry.hot_pixel_current_e_s:
        g = rng(3)
        index = np.flatnonzero(g.random(h * w) < radiometry.hot_pixel_fraction)
        current = radiometry.hot_pixel_current_e_s * g.uniform(0.5, 1.5, len(index))
    return FixedPattern((h, w), gain, offset, index, current)

"""The as-built world's radiometry: the light as it really shines, the room, the sensor's
fixed patterns (``[world.radiometry]``; DEVELOPING.md, "The as-built world").

The reduction never reads these values: it learns them from flats, darks and reference
shots, as a lab does.  ``perfect`` switches every effect off (frames byte-identical to a
world without radiometry).  ``realistic`` draws them uniformly in these ranges, from a
random stream of their own (``default_rng([seed, 16])``), so the kinematic and camera
draws of every seed are those of a world without radiometry:

=============================  ======  ===============  ===========================================
key                            unit    realistic        meaning
=============================  ======  ===============  ===========================================
``light_profile_n``            -       U(0, 2)          emitted radiance ``L_e cos^n(psi)``, psi off
                                                        the light's emitting normal (LED
                                                        emitters behind a diffuser: n ~ 0..2)
``light_gradient``             -       U(0, 0.04)       face non-uniformity: ``L_e (1 + g (rho/R)
                                                        cos(phi - phi_g))`` on a disk, ``L_e (1 +
                                                        g ((2x/w) cos phi_g + (2y/h) sin phi_g))``
                                                        on a rectangle, in the light's (e1, e2)
``light_gradient_angle_deg``   deg     U(0, 360)        phi_g
``drift_amplitude``            - (3,)  U(0.005, 0.03)   warm-up: output ``1 + A_c exp(-t/tau) +
                                                        r t / 3600`` at rig time t, s
``drift_tau_s``                s       U(300, 1500)     warm-up time constant
``drift_rate_per_h``           1/h     U(-0.005, 0.005) slow linear drift r
``ambient_fraction``           -       U(0, 2e-4)       room light, light on or off: uniform diffuse
                                                        irradiance ``fraction * E0``
``stray_fraction``             -       U(0, 5e-4)       the light's output scattered by the room,
                                                        light on only, drifting with the light
``prnu``                       -       U(0.003, 0.01)   per-pixel relative gain, Gaussian rms
``dsnu_e``                     e-      U(1, 5)          per-pixel dark offset, Gaussian rms (the
                                                        pixel's mean electrons clipped at >= 0)
``hot_pixel_fraction``         -       U(1e-4, 5e-4)    fraction of pixels with a high dark current
``hot_pixel_current_e_s``      e-/s    U(200, 2000)     their dark current, uniform in [0.5, 1.5] x
``flat_radiance``              W/(sr   not drawn        radiance of the flat panel over the lens
                               m^2)                     (absent: half the full well in the
                               (3,)                     strongest channel at 10 ms, f/8)
=============================  ======  ===============  ===========================================

``E0`` is the irradiance the light (output factor 1) puts on the sample centre at normal
incidence from its distance (:func:`gonio.simulator.lights.nominal_irradiance`); a diffuse
irradiance E is reflected as radiance ``E / pi * albedo(theta_o)`` by every surface.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["REALISTIC_RADIOMETRY", "Radiometry", "draw_radiometry"]

#: Realistic ranges (low, high) of the uniform draws, in the key's unit; drawn in this
#: order from ``default_rng([seed, 16])`` (``drift_amplitude`` is three draws, R, G, B).
REALISTIC_RADIOMETRY: dict[str, tuple[float, float]] = {
    "light_profile_n": (0.0, 2.0),
    "light_gradient": (0.0, 0.04),
    "light_gradient_angle_deg": (0.0, 360.0),
    "drift_amplitude": (0.005, 0.03),
    "drift_tau_s": (300.0, 1500.0),
    "drift_rate_per_h": (-0.005, 0.005),
    "ambient_fraction": (0.0, 2e-4),
    "stray_fraction": (0.0, 5e-4),
    "prnu": (0.003, 0.01),
    "dsnu_e": (1.0, 5.0),
    "hot_pixel_fraction": (1e-4, 5e-4),
    "hot_pixel_current_e_s": (200.0, 2000.0),
}


class Radiometry(BaseModel):
    """The ``[world.radiometry]`` table (module docstring: keys, units, draws).

    The defaults switch every effect off (``drift_tau_s`` matters only with a drift
    amplitude).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    light_profile_n: float = Field(default=0.0, ge=0.0, le=50.0, allow_inf_nan=False)
    light_gradient: float = Field(default=0.0, ge=0.0, lt=1.0, allow_inf_nan=False)
    light_gradient_angle_deg: float = Field(default=0.0, allow_inf_nan=False)
    drift_amplitude: tuple[float, float, float] = (0.0, 0.0, 0.0)
    drift_tau_s: float = Field(default=600.0, gt=0.0, allow_inf_nan=False)
    drift_rate_per_h: float = Field(default=0.0, gt=-1.0, lt=1.0, allow_inf_nan=False)
    ambient_fraction: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False)
    stray_fraction: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False)
    prnu: float = Field(default=0.0, ge=0.0, lt=0.5, allow_inf_nan=False)
    dsnu_e: float = Field(default=0.0, ge=0.0, allow_inf_nan=False)
    hot_pixel_fraction: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False)
    hot_pixel_current_e_s: float = Field(default=0.0, ge=0.0, allow_inf_nan=False)
    flat_radiance: tuple[float, float, float] | None = None

    @field_validator("drift_amplitude", "flat_radiance")
    @classmethod
    def _finite(cls, v: tuple[float, ...] | None, info: Any) -> tuple[float, ...] | None:
        if v is None:
            return v
        if not all(math.isfinite(x) for x in v):
            raise ValueError(f"{info.field_name} = {list(v)}: expected finite numbers")
        if info.field_name == "drift_amplitude" and any(x <= -1.0 for x in v):
            raise ValueError(f"drift_amplitude = {list(v)}: each must be > -1")
        if info.field_name == "flat_radiance" and any(x < 0 for x in v):
            raise ValueError(f"flat_radiance = {list(v)}: expected values >= 0, W/(sr m^2)")
        return v

    @property
    def off(self) -> bool:
        """No radiometric effect at all (a perfect world's light, room and sensor; a
        ``flat_radiance`` of its own counts as an effect).  ``drift_tau_s`` alone is none."""
        return self.model_dump(exclude={"drift_tau_s"}) == _OFF

    @property
    def drifts(self) -> bool:
        """Whether the light's output changes with rig time."""
        return any(a != 0.0 for a in self.drift_amplitude) or self.drift_rate_per_h != 0.0

    @property
    def has_fixed_pattern(self) -> bool:
        """Whether the sensor has PRNU, DSNU or hot pixels."""
        return bool(
            self.prnu or self.dsnu_e or (self.hot_pixel_fraction and self.hot_pixel_current_e_s)
        )

    def light_output(self, t: float) -> np.ndarray:
        """The light's output factor (3,) (R, G, B) at rig time ``t`` (s):
        ``1 + A_c exp(-t / tau) + r t / 3600``."""
        a = np.asarray(self.drift_amplitude, dtype=np.float64)
        t = float(t)
        return 1.0 + a * math.exp(-t / self.drift_tau_s) + self.drift_rate_per_h * t / 3600.0


_OFF = Radiometry().model_dump(exclude={"drift_tau_s"})


def draw_radiometry(seed: int) -> dict[str, Any]:
    """The realistic radiometry of world ``seed`` (a ``[world.radiometry]`` dict).

    Drawn from ``default_rng([seed, 16])``, a stream no other world draw uses.
    """
    rng = np.random.default_rng([int(seed), 16])
    out: dict[str, Any] = {}
    for name, (lo, hi) in REALISTIC_RADIOMETRY.items():
        if name == "drift_amplitude":
            out[name] = tuple(float(x) for x in rng.uniform(lo, hi, 3))
        else:
            out[name] = float(rng.uniform(lo, hi))
    return out

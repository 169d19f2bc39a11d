"""Lights prepared for integration: node sets over the emitter's area.

Every area light maps the unit square (a, b) onto its surface with a constant Jacobian
(the light's area), so quadrature rules and stratified Monte Carlo share one code path:

- disk: rho = R sqrt(a), phi = 2 pi b (area preserving).  Gauss-Legendre in a and the
  midpoint rule in b: the periodic trapezoid rule is spectrally accurate in phi, and in
  a = (rho / R)^2 the angular averages of a smooth integrand are polynomials, so
  Gauss-Legendre converges fast too;
- rectangle: tensor Gauss-Legendre in (a, b);
- point approximation: the centre with the whole area (level 0).

An area light's emitted radiance is ``rgb * cos^profile_n(psi) * face(y)``: psi the angle
off its emitting normal, ``face`` its linear non-uniformity (:meth:`PreparedLight.face`);
both are 1 for a Lambertian, uniform light (and then cost nothing).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from gonio.simulator.scene import DiskLight, PointLight, RectangleLight, Scene, _unit

__all__ = ["LEVELS", "PreparedLight", "nominal_irradiance", "prepare_lights"]

# Quadrature ladder: level k >= 1 has ``k`` Gauss-Legendre nodes in a and 4k midpoint
# nodes in phi on a disk (the phi integrand's Fourier modes decay like (R/d)^m and the
# a-rule is exact to degree 4k-2 in rho: balanced), k+1 per axis on a rectangle.
LEVELS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 24, 32)


@dataclass
class PreparedLight:
    """A light as arrays: kind, colour (3,), centre, emitting normal, tangent axes, size,
    and its emission profile ``profile_n``, face ``gradient`` and its angle (rad)."""

    kind: str
    rgb: np.ndarray
    center: np.ndarray
    normal: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    size: tuple[float, float]  # disk: (radius, radius); rectangle: (width, height)
    area: float
    profile_n: float = 0.0
    gradient: float = 0.0
    gradient_angle: float = 0.0
    #: The face frame of the gradient: the light body's (None: ``e1``, ``e2``).
    f1: np.ndarray | None = None
    f2: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.f1 is None:
            self.f1, self.f2 = self.e1, self.e2

    def face(self, y: np.ndarray) -> np.ndarray | None:
        """The face non-uniformity factor (...) at emitter points y (..., 3), or None for
        a uniform face: ``1 + g (rho/R) cos(phi - phi_g)`` on a disk, ``1 + g ((2x/w)
        cos(phi_g) + (2y/h) sin(phi_g))`` on a rectangle ((x, y) along (e1, e2))."""
        if self.gradient == 0.0 or self.is_point:
            return None
        rel = y - self.center
        p1, p2 = rel @ self.f1, rel @ self.f2
        c, s = np.cos(self.gradient_angle), np.sin(self.gradient_angle)
        if self.kind == "disk":
            u = (p1 * c + p2 * s) / self.size[0]
        else:
            u = (2 * p1 / self.size[0]) * c + (2 * p2 / self.size[1]) * s
        return 1.0 + self.gradient * u

    def profile(self, cos_psi: np.ndarray) -> np.ndarray | None:
        """The emission profile ``cos^n(psi)`` for cosines off the normal, or None for a
        Lambertian emitter."""
        if self.profile_n == 0.0 or self.is_point:
            return None
        return np.maximum(cos_psi, 0.0) ** self.profile_n

    def on_axis_irradiance(self, distance: float, level: int = 16) -> np.ndarray:
        """Irradiance (3,) W/m^2 on a surface facing the light at ``distance`` m on its
        axis, by the light's own quadrature (the face gradient averages out there).

        ``int L cos^n(psi) cos(theta) cos(psi) / r^2 dA`` with ``cos(theta) = cos(psi) =
        d / r`` (a point light: ``I / d^2``).
        """
        d = float(distance)
        if self.is_point:
            return self.rgb / d**2
        nodes, w = self.quadrature(level)
        rel = nodes - self.center
        rho2 = (rel @ self.e1) ** 2 + (rel @ self.e2) ** 2
        r2 = d * d + rho2
        cos = d / np.sqrt(r2)
        return self.rgb * float(np.sum(w * cos ** (self.profile_n + 2.0) / r2))

    @property
    def is_point(self) -> bool:
        return self.kind == "point"

    def extent_points(self) -> np.ndarray:
        """Points bounding the emitter (for bounding-box tests), (n, 3)."""
        if self.is_point:
            return self.center[None]
        s1, s2 = (self.size[0], self.size[1]) if self.kind == "disk" else np.divide(self.size, 2)
        return np.array(
            [self.center + i * s1 * self.e1 + j * s2 * self.e2 for i in (-1, 1) for j in (-1, 1)]
        )

    def probe_points(self) -> np.ndarray:
        """Points whose visibility decides whether a surface point may be in penumbra:
        the centre, 16 on the rim and 8 half-way (disk), or the same on the rectangle's
        border and its half-size copy, (25, 3)."""
        if self.is_point:
            return self.center[None]
        t = np.arange(16) / 16
        h = np.arange(8) / 8
        if self.kind == "disk":
            a = np.concatenate([[0.0], np.ones(16), np.full(8, 0.25)])
            b = np.concatenate([[0.0], t, h])
        else:

            def border(n, scale):
                # walk the unit square's border, scaled about its centre
                s = np.arange(n) * 4 / n
                side, f = np.floor(s), s % 1
                u = np.select([side == 0, side == 1, side == 2], [f, 1 + 0 * f, 1 - f], 0 * f)
                v = np.select([side == 0, side == 1, side == 2], [0 * f, f, 1 + 0 * f], 1 - f)
                return 0.5 + (u - 0.5) * scale, 0.5 + (v - 0.5) * scale

            u1, v1 = border(16, 1.0)
            u2, v2 = border(8, 0.5)
            a = np.concatenate([[0.5], u1, u2])
            b = np.concatenate([[0.5], v1, v2])
        return self.map(a, b)

    def map(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Points on the emitter for unit-square coordinates (a, b), shape (..., 3)."""
        if self.kind == "disk":
            rho = self.size[0] * np.sqrt(a)
            phi = 2 * np.pi * b
            p1, p2 = rho * np.cos(phi), rho * np.sin(phi)
        else:
            p1, p2 = (a - 0.5) * self.size[0], (b - 0.5) * self.size[1]
        return self.center + p1[..., None] * self.e1 + p2[..., None] * self.e2

    def quadrature(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Nodes (K, 3) and area weights (K,) of quadrature ``level`` (0: point)."""
        if self.is_point or level == 0:
            return self.center[None], np.array([self.area])
        if self.kind == "disk":
            xa, wa = _leggauss(level)
            nb = 4 * level
            xb, wb = (np.arange(nb) + 0.5) / nb, np.full(nb, 1.0 / nb)
        else:
            xa, wa = _leggauss(level + 1)
            xb, wb = xa, wa
            xb, wb = (xb + 1) / 2, wb / 2
        xa, wa = (xa + 1) / 2, wa / 2
        A, B = np.meshgrid(xa, xb, indexing="ij")
        w = np.outer(wa, wb).ravel() * self.area
        return self.map(A.ravel(), B.ravel()), w

    def n_nodes(self, level: int) -> int:
        """Number of nodes of a quadrature level."""
        if self.is_point or level == 0:
            return 1
        return level * 4 * level if self.kind == "disk" else (level + 1) ** 2

    def stratified(self, n: int, rng: np.random.Generator, m: int) -> tuple[np.ndarray, float]:
        """Stratified random nodes for ``m`` points: (m, K, 3) and the weight per node."""
        if self.kind == "disk":
            na = max(1, int(round(np.sqrt(n / 4))))
            nb = max(1, int(np.ceil(n / na)))
        else:
            na = max(1, int(round(np.sqrt(n))))
            nb = max(1, int(np.ceil(n / na)))
        ia, ib = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
        a = (ia.ravel() + rng.random((m, na * nb))) / na
        b = (ib.ravel() + rng.random((m, na * nb))) / nb
        return self.map(a, b), self.area / (na * nb)


@lru_cache(maxsize=64)
def _leggauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``numpy.polynomial.legendre.leggauss(n)``, read-only, computed once per ``n``.

    The rule (an eigenvalue problem and a Newton polish) cost ~0.15 ms a call, and a
    camera's every render asked for it again (``nominal_irradiance`` at level 16: 0.33
    -> 0.16 ms, of a ~10 ms realistic 320 x 240 frame).  The same bits.
    """
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w


def _prepare(light, scene: Scene) -> PreparedLight:
    c = np.asarray(light.position, float)
    if isinstance(light, PointLight):
        z = np.array([0.0, 0.0, 1.0])
        return PreparedLight("point", scene.light_rgb(light.intensity), c, z, z, z, (0, 0), 1.0)
    n = light.emit_normal()
    if isinstance(light, RectangleLight):
        up = np.asarray(light.up, float)
        up = up - n * (up @ n)
        if np.linalg.norm(up) < 1e-9:
            raise ValueError("rectangle light: 'up' is parallel to the normal")
        e2 = _unit(up, "up")
        e1 = np.cross(e2, n)
        size = (light.width, light.height)
        area = light.width * light.height
        kind = "rectangle"
    else:
        assert isinstance(light, DiskLight)
        helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
        e1 = _unit(np.cross(helper, n), "disk tangent")
        e2 = np.cross(n, e1)
        size = (light.radius, light.radius)
        area = np.pi * light.radius**2
        kind = "disk"
    return PreparedLight(
        kind,
        scene.light_rgb(light.radiance),
        c,
        n,
        e1,
        e2,
        size,
        area,
        float(light.profile_n),
        float(light.gradient),
        float(np.radians(light.gradient_angle_deg)),
        *_face_frame(light.face_up, n),
    )


def _face_frame(face_up, n: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(f1, f2) of a light body whose "up" is ``face_up`` (None: the tangent frame),
    handed like the tangent frames (``f1 x f2 = n``)."""
    if face_up is None:
        return None, None
    up = np.asarray(face_up, float)
    f2 = _unit(up - n * (up @ n), "face_up")  # not parallel to n: the scene checked it
    return np.cross(f2, n), f2


def prepare_lights(scene: Scene) -> list[PreparedLight]:
    """The scene's lights as :class:`PreparedLight` objects."""
    return [_prepare(light, scene) for light in scene.lights]


def nominal_irradiance(scene: Scene) -> np.ndarray:
    """``E0`` (3,), W/m^2: the irradiance the scene's lights (at output factor 1) put on
    the sample centre at normal incidence, each from its present distance to the sample
    origin (the light arm's radius): the unit of ambient and stray light."""
    total = np.zeros(3)
    for light in prepare_lights(scene):
        total = total + light.on_axis_irradiance(float(np.linalg.norm(light.center)))
    return total

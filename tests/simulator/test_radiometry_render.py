"""The light as built in the renderer: cos^n emission, face gradient, the mirror's spot,
and the response to uniform diffuse light -- against closed forms and scipy quadrature."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from gonio.simulator.lights import nominal_irradiance, prepare_lights
from gonio.simulator.render import HOLDER, SAMPLE, albedo_table, render
from gonio.simulator.scene import parse_scene


def scene_dict(light, **over):
    d = dict(
        sample=dict(width=0.4, height=0.4, brdf=dict(model="lambert", params={"albedo": 0.6})),
        lights=[light],
        camera=dict(
            resolution=[33, 33], fov_deg=30, position=[0, 0, 0.6], look_at=[0, 0, 0], up=[0, 1, 0]
        ),
        render=dict(tolerance=1e-8, antialias=1),
    )
    d.update(over)
    return d


@pytest.mark.parametrize("n", [0.0, 1.5, 4.0])
def test_on_axis_irradiance_of_a_cos_n_disk_is_the_closed_form(n):
    # E = 2 pi L (1 - cos^(n+2) a) / (n + 2) on the axis of a cos^n disk of half-angle a;
    # a Lambertian sample reflects albedo / pi E.
    d, R = 0.3, 0.1
    light = dict(
        type="disk", position=[0, 0, d], normal=[0, 0, -1], radius=R, radiance=[1.0, 2.0, 3.0]
    )
    light["profile_n"] = n
    res = render(parse_scene(scene_dict(light)))
    assert np.allclose(res.points[16, 16], 0, atol=1e-15)
    cos_a = d / np.hypot(d, R)
    E = 2 * np.pi * np.array([1.0, 2.0, 3.0]) * (1 - cos_a ** (n + 2)) / (n + 2)
    assert np.max(np.abs(res.radiance[16, 16] / (0.6 / np.pi * E) - 1)) < 1e-7
    # E0, the unit of ambient and stray light, is the same closed form
    assert np.allclose(nominal_irradiance(parse_scene(scene_dict(light))), E, rtol=1e-7)


def _quad_irradiance(light, x, e1, e2, n, g, phi_g):
    """E(x) = int L (1 + face) cos^n(psi) cos(theta) cos(psi) / r^2 dA by scipy."""
    c = np.asarray(light["position"], float)
    nrm = -c / np.linalg.norm(c)  # look_at the origin

    def integrand(p1, p2, face):
        y = c + p1 * e1 + p2 * e2
        dv = y - x
        r2 = dv @ dv
        w = dv / np.sqrt(r2)
        cos_t, cos_p = max(w[2], 0.0), max(-(w @ nrm), 0.0)
        return (1 + g * face) * cos_p**n * cos_t * cos_p / r2

    if light["type"] == "disk":
        R = light["radius"]

        def f(phi, rho):
            return rho * integrand(
                rho * np.cos(phi), rho * np.sin(phi), rho / R * np.cos(phi - phi_g)
            )

        val, _ = integrate.dblquad(f, 0, R, 0, 2 * np.pi, epsabs=0, epsrel=1e-11)
    else:
        w, h = light["width"], light["height"]

        def f(p2, p1):
            return integrand(p1, p2, 2 * p1 / w * np.cos(phi_g) + 2 * p2 / h * np.sin(phi_g))

        val, _ = integrate.dblquad(f, -w / 2, w / 2, -h / 2, h / 2, epsabs=0, epsrel=1e-11)
    return val


@pytest.mark.parametrize(
    "light",
    [
        dict(type="disk", radius=0.06),
        dict(type="rectangle", width=0.1, height=0.05, up=[0, 0, 1]),
    ],
)
def test_face_gradient_and_profile_off_axis_against_scipy_quadrature(light):
    n, g, ang = 1.3, 0.3, 40.0
    light = dict(light, position=[0.12, 0.05, 0.3], look_at=[0, 0, 0], radiance=2.0)
    light.update(profile_n=n, gradient=g, gradient_angle_deg=ang)
    scene = parse_scene(scene_dict(light))
    res = render(scene)
    pl = prepare_lights(scene)[0]  # the light's own (e1, e2): phi_g's frame, by definition
    for j, i in [(5, 27), (20, 9), (16, 16)]:
        x = res.points[j, i]
        E = _quad_irradiance(light, x, pl.e1, pl.e2, n, g, np.radians(ang))
        assert res.radiance[j, i, 0] == pytest.approx(0.6 / np.pi * 2.0 * E, rel=1e-6)
    # the gradient matters at this size: its direction reversed changes the image
    flipped = dict(light, gradient_angle_deg=ang + 180)
    other = render(parse_scene(scene_dict(flipped)))
    assert np.max(np.abs(other.radiance[5, 27] / res.radiance[5, 27] - 1)) > 1e-3


def test_mirror_spot_carries_the_profile_and_the_gradient():
    n, g, ang = 2.0, 0.3, 90.0
    pos = np.array([0.0, 0.25, 0.433])
    light = dict(type="disk", position=pos.tolist(), look_at=[0, 0, 0], radius=0.03, radiance=10.0)
    light.update(profile_n=n, gradient=g, gradient_angle_deg=ang)
    d = scene_dict(
        light,
        camera=dict(
            resolution=[64, 48],
            fov_deg=12,
            position=[0, -0.25, 0.433],
            look_at=[0, 0, 0],
            up=[0, 0, 1],
        ),
    )
    scene = parse_scene(d).with_mirror_target(0.9)
    res = render(scene)
    pl = prepare_lights(scene)[0]
    C = np.array([0, -0.25, 0.433])
    spot = (res.region == SAMPLE) & (res.radiance[..., 0] > 0) & ~res.edge
    assert spot.sum() > 20
    x = res.points[spot]
    # the mirrored camera sees the light straight: rays from C' = (Cx, Cy, -Cz) through x
    Cm = C * np.array([1, 1, -1])
    u = (x - Cm) / np.linalg.norm(x - Cm, axis=-1, keepdims=True)
    t = ((pos - x) @ pl.normal) / (u @ pl.normal)
    y = x + t[:, None] * u
    cos_psi = -(u @ pl.normal)
    rel = y - pos
    face = (
        1
        + g
        * ((rel @ pl.e1) * np.cos(np.radians(ang)) + (rel @ pl.e2) * np.sin(np.radians(ang)))
        / 0.03
    )
    expected = 0.9 * 10.0 * cos_psi**n * face
    assert np.allclose(res.radiance[spot][:, 0], expected, rtol=1e-9)
    assert np.ptp(face) > 0.1  # the spot spans the gradient


def test_diffuse_response_is_albedo_over_pi_on_every_surface():
    light = dict(type="disk", position=[0, 0.2, 0.4], look_at=[0, 0, 0], radius=0.02, radiance=5.0)
    d = scene_dict(
        light,
        sample=dict(
            width=0.06,
            height=0.06,
            brdf=dict(model="lambert+ggx", params={"albedo": 0.3, "ks": 0.5, "alpha": 0.3}),
        ),
        holder=dict(
            width=0.2,
            height=0.2,
            albedo_white=0.85,
            board=None,
            reference_patch=dict(center=[0.07, -0.07], size=[0.02, 0.02], albedo=0.99),
        ),
        camera=dict(resolution=[40, 30], fov_deg=40, position=[0, -0.25, 0.3], look_at=[0, 0, 0]),
    )
    scene = parse_scene(d)
    table = albedo_table(scene.build_brdf())
    res = render(scene, diffuse=True, sample_albedo=table)
    plain = render(scene)
    assert np.array_equal(res.radiance, plain.radiance)  # the direct light is unchanged
    assert plain.diffuse is None
    hold = (res.region == HOLDER) & ~res.edge
    patch = (res.region == 3) & ~res.edge
    assert hold.any() and patch.any()
    assert np.allclose(res.diffuse[hold], 0.85 / np.pi, rtol=1e-12)
    assert np.allclose(res.diffuse[patch], 0.99 / np.pi, rtol=1e-12)
    # the sample: its directional albedo at the viewing angle, by a plain tensor
    # Gauss-Legendre rule over the hemisphere (reciprocity: a(theta_o) = int f(wi, wo)
    # cos(theta_i) dwi; the lobe is broad, alpha = 0.3)
    brdf = scene.build_brdf()
    xt, wt = np.polynomial.legendre.leggauss(200)
    xp, wp = np.polynomial.legendre.leggauss(200)
    th, ph = np.pi / 4 * (xt + 1), np.pi * (xp + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    wi = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    wq = np.outer(wt * np.pi / 4, wp * np.pi) * np.cos(T) * np.sin(T)
    smp = np.argwhere((res.region == SAMPLE) & ~res.edge)
    for j, i in smp[[0, len(smp) // 2, -1]]:
        f = brdf.eval(wi, np.broadcast_to(res.wo[j, i], wi.shape))[..., 0]
        a = float(np.sum(f * wq))
        assert res.diffuse[j, i, 0] == pytest.approx(a / np.pi, rel=2e-3)
    # a dark render has no direct light and the same diffuse response
    dark = render(scene, direct=False, diffuse=True, sample_albedo=table)
    assert not dark.radiance.any()
    assert np.array_equal(dark.diffuse, res.diffuse)

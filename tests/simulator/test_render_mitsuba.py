"""The renderer against Mitsuba 3 (independent oracle): same camera, film, plane, BSDF,
disk emitter, ``direct`` integrator.

Per-pixel check: K independent Mitsuba renders (distinct seeds) give a per-pixel mean and
standard error; t = (mean - ours) / stderr follows Student's t with K - 1 degrees of
freedom if ours is the converged value, so mean(t^2) ~ (K-1)/(K-3) and the signed mean of
t ~ 0.  A bias of a fraction of Mitsuba's noise shifts both.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import pytest

from gonio.simulator.mitsuba_scene import to_mitsuba_dict
from gonio.simulator.render import render
from gonio.simulator.scene import parse_scene

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

K_RENDERS = 16
SPP = 32


@pytest.fixture(scope="module")
def mi():
    os.environ.setdefault("DRJIT_CACHE_DIR", tempfile.mkdtemp(prefix="drjit-"))
    from gonio.mitsuba_oracle import MitsubaUnavailableError, load_mitsuba

    try:
        mi, _variant = load_mitsuba("llvm")
    except MitsubaUnavailableError as exc:
        pytest.skip(str(exc))
    import drjit as dr

    dr.set_thread_count(1)
    return mi


def _scene(brdf: dict, res=(64, 64)):
    return parse_scene(
        dict(
            sample=dict(width=0.3, height=0.24, brdf=brdf),
            lights=[
                dict(
                    type="disk",
                    position=[0.05, 0.25, 0.4330127],
                    look_at=[0, 0, 0],
                    radius=0.01,
                    radiance=[1000.0, 800.0, 600.0],
                )
            ],
            camera=dict(
                resolution=list(res),
                fov_deg=20,
                position=[0.0, -0.25, 0.4330127],
                look_at=[0.02, 0, 0],
                up=[0, 1, 0],
            ),
            render=dict(tolerance=1e-4),
        )
    )


def _mitsuba_stats(mi, scene):
    imgs = np.array(
        [
            np.array(
                mi.render(mi.load_dict(to_mitsuba_dict(scene, mi, SPP, seed))), dtype=np.float64
            )
            for seed in range(1, K_RENDERS + 1)
        ]
    )
    return imgs.mean(0), imgs.std(0, ddof=1) / np.sqrt(K_RENDERS)


def _compare(ours, mean, stderr):
    rel_mean = ours.mean((0, 1)) / mean.mean((0, 1)) - 1
    assert np.all(np.abs(rel_mean) < 1e-3), rel_mean
    ok = stderr > 0
    assert ok.mean() > 0.9  # almost every pixel carries signal
    t = (mean - ours)[ok] / stderr[ok]
    nu = K_RENDERS - 1
    n = ok.sum() / 3  # channels are correlated: count pixels
    # Var(t^2) for Student's t: 2 nu^2 (nu - 1) / ((nu - 2)^2 (nu - 4)).
    sd_t2 = np.sqrt(2 * nu**2 * (nu - 1) / ((nu - 2) ** 2 * (nu - 4)) / n)
    # Heavy-tailed MC samples make the sample variance noisy: allow 25 % + 5 sd.
    assert abs(np.mean(t**2) / (nu / (nu - 2)) - 1) < 0.25 + 5 * sd_t2, np.mean(t**2)
    assert abs(np.mean(t)) < 5 * np.sqrt(nu / (nu - 2) / n), np.mean(t)
    print(
        f"relative mean difference {rel_mean}, mean t^2 {np.mean(t**2):.3f} "
        f"(expected {nu / (nu - 2):.3f}), mean t {np.mean(t):.3f}"
    )
    return rel_mean, np.mean(t**2)


def test_diffuse_matches_mitsuba(mi):
    scene = _scene(dict(model="lambert", params={"albedo": [0.7, 0.5, 0.3]}))
    ours = render(scene).radiance
    _compare(ours, *_mitsuba_stats(mi, scene))


def test_roughconductor_ggx_matches_mitsuba(mi):
    scene = _scene(dict(model="ggx", params={"ks": 1.0, "alpha": 0.2}))
    ours = render(scene).radiance
    mean, stderr = _mitsuba_stats(mi, scene)
    _compare(ours, mean, stderr)
    # The test can fail: a 2 % error in the BRDF is many standard errors away.
    with pytest.raises(AssertionError):
        _compare(ours * 1.02, mean, stderr)


class _Reversed:
    """Mitsuba's ``measured`` plugin evaluates the data with its ``si.wi`` (towards the
    camera in a path tracer) as the data's incident direction; measured BRDFs are not
    exactly reciprocal, so for this comparison we swap the arguments the same way."""

    def __init__(self, brdf):
        self.brdf = brdf

    def eval(self, wi, wo):
        return self.brdf.eval(wo, wi)


def test_measured_rgl_matches_mitsuba_measured(mi, rgl_file):
    scene = _scene(dict(file=str(rgl_file("paper_white"))), res=(48, 40))
    scene = scene.model_copy(update={"render": scene.render.model_copy(update={"tolerance": 1e-3})})
    brdf = scene.build_brdf()
    res = render(scene, brdf=_Reversed(brdf))
    print(res.stats.lights, res.stats.seconds)
    ours = res.radiance
    assert np.all(np.isfinite(render(scene, brdf=brdf).radiance))
    _compare(ours, *_mitsuba_stats(mi, scene))

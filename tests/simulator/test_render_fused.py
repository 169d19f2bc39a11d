"""The renderer's fused shading and box filter against the numpy path (issue 19.2).

``test_render_kernels.py`` holds a whole realistic render (quadrature nodes) to the
numpy path; here the cases it does not reach: per-point node rows (stratified Monte
Carlo), a point light, and the box filter's summation order (the same bits as numpy's
``reshape(...).mean(1)``).
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.simulator import render_kernels
from gonio.simulator.render import render
from gonio.simulator.rig_camera import minimal_scene
from gonio.simulator.scene import parse_scene


def _scene(strategy: str, light: dict | None = None):
    doc = minimal_scene(160, 120)
    doc["camera"]["fov_deg"] = 30.0
    doc["render"] = {"strategy": strategy, "antialias": 3, "mc_samples": 8}
    doc["holder"]["board"] = {"squares_x": 7, "squares_y": 7, "square_length": 0.02,
                              "marker_length": 0.015}  # fmt: skip
    doc["holder"]["reference_patch"] = {"center": [0.05, -0.05], "size": [0.02, 0.02]}
    doc["lights"][0].update(profile_n=1.5, gradient=0.03, gradient_angle_deg=40.0)
    if light is not None:
        doc["lights"] = [light]
    return parse_scene(doc)


@pytest.mark.parametrize(
    "strategy, light",
    [
        ("mc", None),
        ("point", {"type": "point", "position": [0.05, 0.2, 0.4], "intensity": 2.0}),
    ],
)
def test_fused_shading_equals_the_numpy_path(monkeypatch, strategy, light):
    scene = _scene(strategy, light)
    fast = render(scene, diffuse=True)
    monkeypatch.setenv("GONIO_NUMBA", "0")
    ref = render(scene, diffuse=True)
    assert fast.stats.subpixel_samples > 4096  # the kernels ran on the sub-samples too
    assert (ref.region == 1).sum() > 500 and (ref.region == 3).sum() > 100
    np.testing.assert_array_equal(fast.region, ref.region)
    assert (ref.radiance > 0).sum() > 10000
    # numpy's matrix products may fuse multiply-adds (BLAS): rounding only
    np.testing.assert_allclose(fast.radiance, ref.radiance, rtol=1e-12, atol=0)
    np.testing.assert_allclose(fast.diffuse, ref.diffuse, rtol=1e-12, atol=0)


@pytest.mark.parametrize("n", [4, 9, 256])
def test_box_filter_kernel_sums_like_numpy_mean(n):
    rng = np.random.default_rng(n)
    p = 700
    sub = rng.lognormal(0.0, 3.0, (p * n, 3))  # spread over many binades: order shows
    ej, ei = np.divmod(rng.permutation(50 * 60)[:p], 60)
    ref = np.zeros((50, 60, 3))
    ref[ej, ei] = sub.reshape(p, n, 3).mean(1)
    out = np.zeros((50, 60, 3))
    render_kernels.subsample_mean(sub, n, ej, ei, out)
    np.testing.assert_array_equal(out, ref)

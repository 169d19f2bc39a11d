"""The fast paths of the simulated camera against their numpy references (issue 19.2).

- the renderer's numba kernels (ray labels, sub-pixel undistortion) against the numpy
  path (``GONIO_NUMBA=0``) on a realistic world's frame: same labels and edges, radiance
  equal to rounding;
- the camera's per-site shot (the pose's render taken at the colour filters' sites once)
  against ``simulate_raw`` of the full radiance image the camera reports: the same bytes.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.simulator.camera import SimulatedCamera
from gonio.simulator.geometry import undistort_normalized
from gonio.simulator.render import _subpixel_normalized, render
from gonio.simulator.rig_camera import minimal_scene
from gonio.simulator.scene import parse_scene
from gonio.simulator.sensor import simulate_raw
from gonio.simulator.world import draw_world

WORLD_SEED = 5


def realistic_scene(w=240, h=180):
    """The demo's scene (board, anti-aliased edges) with a realistic world's camera
    (distortion, principal point) and light (emission profile, face gradient)."""
    doc = minimal_scene(w, h)
    doc["camera"]["fov_deg"] = 30.0
    doc["lights"][0]["radius"] = 0.004
    doc["render"] = {"strategy": "auto", "tolerance": 1e-3, "antialias": 3}
    doc["holder"]["board"] = {
        "squares_x": 7,
        "squares_y": 7,
        "square_length": 0.02,
        "marker_length": 0.015,
    }
    doc["holder"]["reference_patch"] = {"center": [0.05, -0.05], "size": [0.02, 0.02]}
    world = draw_world("realistic", WORLD_SEED)
    scene = parse_scene(doc)
    scene = scene.model_copy(update={"camera": world.as_built_camera(scene.camera)})
    return scene, world


@pytest.fixture(scope="module")
def scene_world():
    return realistic_scene()


def test_kernel_render_equals_the_numpy_render(scene_world, monkeypatch):
    scene, world = scene_world
    assert scene.camera.has_distortion  # the as-built lens: the kernels' Newton runs
    from gonio.simulator.camera import with_light_emission

    scene = with_light_emission(scene, world.radiometry)
    fast = render(scene, diffuse=True)
    monkeypatch.setenv("GONIO_NUMBA", "0")
    ref = render(scene, diffuse=True)
    assert fast.stats.edge_pixels > 500 and fast.stats.subpixel_samples > 4000
    np.testing.assert_array_equal(fast.region, ref.region)
    np.testing.assert_array_equal(fast.edge, ref.edge)
    assert fast.stats.lights[0].nodes == ref.stats.lights[0].nodes
    # rays differ by BLAS's fused multiply-adds and one Newton step: rounding only
    lit = ref.radiance > 0
    assert lit.sum() > 10000
    np.testing.assert_allclose(fast.radiance, ref.radiance, rtol=1e-12, atol=0)
    np.testing.assert_allclose(fast.diffuse, ref.diffuse, rtol=1e-12, atol=0)
    np.testing.assert_allclose(fast.points, ref.points, rtol=0, atol=1e-15)
    np.testing.assert_allclose(fast.wi, ref.wi, rtol=0, atol=1e-13)


def test_kernel_subpixel_rays_undistort_like_the_numpy_newton(scene_world, monkeypatch):
    scene, _ = scene_world
    cam = scene.camera
    K = cam.intrinsics()
    w, h = cam.resolution
    rng = np.random.default_rng(3)
    ei, ej = rng.integers(0, w, 2000), rng.integers(0, h, 2000)
    xk, yk = _subpixel_normalized(K, ei, ej, 3, cam.distortion)
    monkeypatch.setenv("GONIO_NUMBA", "0")
    xr, yr = _subpixel_normalized(K, ei, ej, 3, cam.distortion)
    np.testing.assert_allclose(xk, xr, rtol=0, atol=1e-15)
    np.testing.assert_allclose(yk, yr, rtol=0, atol=1e-15)
    # and both invert the lens: the sub-pixel points of pixel (i, j) at i + 1/6 ...
    u = np.repeat(ei, 9) + np.tile(np.repeat([1, 3, 5], 3), 2000) / 6
    v = np.repeat(ej, 9) + np.tile(np.tile([1, 3, 5], 3), 2000) / 6
    x0, y0 = undistort_normalized((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], cam.distortion)
    np.testing.assert_allclose(xk, x0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(yk, y0, rtol=0, atol=1e-14)


@pytest.mark.parametrize("target,light_on", [("sample", True), ("sample", False), ("flat", True)])
def test_site_shot_is_simulate_raw_of_the_radiance_image(scene_world, target, light_on):
    scene, world = scene_world
    cam = SimulatedCamera(scene, world=world)
    assert cam.radiometry.drifts and cam.fixed_pattern() is not None
    for k, (t, rig_time) in enumerate(((0.004, 30.0), (0.008, 900.0))):
        fast = cam.capture_frame(
            t, 200, 8, seed=k, target=target, rig_time=rig_time, light_on=light_on
        )
        image = cam.radiance(target, rig_time=rig_time, light_on=light_on)
        ref = simulate_raw(
            image,
            cam.scene.camera,
            exposure_time=t,
            iso=200,
            f_number=8,
            seed=np.random.default_rng(k),
            fixed_pattern=cam.fixed_pattern(),
        )
        np.testing.assert_array_equal(fast.mosaic, ref.mosaic)
        assert fast.mosaic.std() > 1.0
    assert cam.renders == (0 if target == "flat" else 1)  # a bracket renders once


def test_ideal_world_site_shot_clamps_like_simulate_raw():
    """Without a world's radiometry the per-site shot also takes radiance below 0 (a
    measured BRDF's interpolation dips there) or NaN as 0, as ``simulate_raw`` does: the
    same bytes, and no negative mean reaches the Poisson draw (the RGL demo did)."""
    scene = parse_scene(minimal_scene(64, 48))
    cam = SimulatedCamera(scene)
    assert cam.radiometry is None
    result, _ = cam._render("sample", True, False)
    rad = result.radiance
    rad[:4, :, :] = -1e-4  # the render is cached: the shot sees these values
    rad[4, :5, :] = np.nan
    sites = cam.site_radiance("sample")
    assert np.isfinite(sites).all() and sites.min() >= 0.0
    fast = cam.capture_frame(0.01, 100, 8, seed=3)
    ref = simulate_raw(
        rad, cam.scene.camera, exposure_time=0.01, iso=100, f_number=8,
        seed=np.random.default_rng(3),
    )  # fmt: skip
    np.testing.assert_array_equal(fast.mosaic, ref.mosaic)


@pytest.mark.parametrize("light_on", [True, False])
def test_kernel_site_shot_equals_the_numpy_site_shot(scene_world, monkeypatch, light_on):
    """``shot_sites`` (the per-shot drift, room light, clamp) against the numpy path of
    ``site_radiance`` bit for bit, with the values the clamp exists for: below 0, -0, NaN
    and inf in the cached direct and diffuse renders."""
    scene, world = scene_world
    cam = SimulatedCamera(scene, world=world)
    assert cam.radiometry.drifts and cam.radiometry.ambient_fraction > 0
    result, _ = cam._render("sample", True, True)
    for img in (result.radiance, result.diffuse):  # cached: every shot sees these
        img[:3] = -1e-4
        img[3, :4] = -0.0
        img[4, :4] = np.nan
        img[5, :4] = np.inf
    for rig_time in (30.0, 900.0):
        fast = cam.site_radiance("sample", rig_time=rig_time, light_on=light_on)
        monkeypatch.setenv("GONIO_NUMBA", "0")
        ref = cam.site_radiance("sample", rig_time=rig_time, light_on=light_on)
        monkeypatch.delenv("GONIO_NUMBA")
        assert fast.tobytes() == ref.tobytes()  # -0 and +0 told apart
        assert np.isfinite(fast).all() and fast.min() >= 0.0 and fast.max() > 1e300
    assert cam.renders == 1


def test_label_kernel_blocks_equal_the_numpy_labels(scene_world, monkeypatch):
    """The label kernel's vectorised blocks (``render_kernels._BLOCK`` rays): batches of
    one, a block, a block and one, and rays that miss the plane (behind the camera, and
    parallel to it) against the numpy path."""
    from gonio.simulator import render_kernels
    from gonio.simulator.render import Surface, _hits

    scene, _ = scene_world
    surface = Surface(scene, None)
    C, R = scene.camera_pose()
    rng = np.random.default_rng(5)
    b = render_kernels._BLOCK
    for n in (1, b - 1, b, b + 1, 3 * b + 7):
        xn, yn = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n)
        yn[: n // 2] *= 50.0  # far off axis: some rays point away from the plane
        out = (np.empty((n, 3)), np.empty(n, bool), np.empty(n, np.uint8), np.empty(n, bool))
        render_kernels.label_points_serial(xn, yn, R, C, *surface.kernel_args(), *out)
        monkeypatch.setenv("GONIO_NUMBA", "0")
        ref = _hits(surface, C, R, xn, yn)
        monkeypatch.delenv("GONIO_NUMBA")
        for a, e in zip(out[1:], ref[1:], strict=True):
            np.testing.assert_array_equal(a, e)
        np.testing.assert_allclose(out[0], ref[0], rtol=0, atol=1e-15)
        if n > b:
            assert not out[1].all() and out[1].any()  # some rays miss, some hit


def test_rgl_batches_padded_to_the_kernel_give_the_numpy_values(rgl_file, monkeypatch):
    """A measured file's small batches (``_eval_kernel_size``: padded up to the kernel's
    size) give the numpy path's values and memory layout (the node sum's einsum follows
    it), and the albedo table is the same whether or not the kernel module is loaded."""
    import sys

    from gonio.brdf import load
    from gonio.simulator.render import _eval_kernel_size, albedo_table

    brdf = load(rgl_file("paper_white"))
    monkeypatch.setenv("GONIO_NUMBA", "0")
    table_numpy = albedo_table(brdf)(np.linspace(0.0, 1.5, 40))
    rng = np.random.default_rng(2)
    for below in (False, True):  # the numpy path's layout: F, or C with a pair at 0
        wi = rng.normal(size=(700, 4, 3))
        wo = rng.normal(size=(700, 1, 3))
        wi[..., 2], wo[..., 2] = np.abs(wi[..., 2]), np.abs(wo[..., 2])
        if below:
            wi[0, 0, 2] = -0.3
        wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
        wob = np.broadcast_to(wo, wi.shape)
        monkeypatch.setenv("GONIO_NUMBA", "0")
        ref = np.asarray(brdf.eval(wi, wob))
        monkeypatch.delenv("GONIO_NUMBA")
        fast = _eval_kernel_size(brdf, wi, wob)
        assert "gonio.brdf.kernels" in sys.modules
        np.testing.assert_array_equal(fast, ref)
        assert fast.strides == ref.strides
        assert (fast[0, 0].sum() == 0.0) == below
        g = rng.uniform(size=wi.shape[:2])
        sums = [np.einsum("mkc,mk->mc", f, g) for f in (fast, ref)]
        assert sums[0].tobytes() == sums[1].tobytes()
    np.testing.assert_array_equal(albedo_table(brdf)(np.linspace(0.0, 1.5, 40)), table_numpy)

"""The board print's exact area coverage (``render.print_antialias = "exact"``) against
independent references: a closed-form half-plane coverage of a pixel, and many sub-rays
labelled by the renderer's point labels (which converge to the area)."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.errors import ConfigError
from gonio.radiometry.frames import look_at_rotation
from gonio.simulator import render_kernels
from gonio.simulator.geometry import pixel_grid
from gonio.simulator.print_coverage import PrintCells, coverage_numpy, print_cells
from gonio.simulator.render import HOLDER, Surface, _hits, _subpixel_normalized, render
from gonio.simulator.rig_camera import minimal_scene
from gonio.simulator.scene import parse_scene
from gonio.simulator.world import draw_world


def board_scene(w=160, h=120, mode="exact", antialias=3, distortion=False):
    doc = minimal_scene(w, h)
    doc["camera"]["fov_deg"] = 30.0
    doc["camera"]["position"] = [0.05, -0.3, 0.4]
    doc["render"] = {"strategy": "point", "antialias": antialias, "print_antialias": mode}
    scene = parse_scene(doc)
    if distortion:
        world = draw_world("realistic", 5)
        scene = scene.model_copy(update={"camera": world.as_built_camera(scene.camera)})
        assert scene.camera.has_distortion
    return scene


def _kernel(quad, cells, R, C):
    out = np.empty(len(quad))
    render_kernels.print_coverage(
        np.ascontiguousarray(quad), cells.col_edges, cells.row_edges, cells.black,
        cells.scale, np.ascontiguousarray(R), np.ascontiguousarray(C), out,
    )  # fmt: skip
    return out


def test_cells_are_one_colour_and_rebuild_the_print():
    scene = board_scene()
    surface = Surface(scene)
    img = surface.board_img
    cells = print_cells(img, surface.board_half)
    ce, re = cells.col_edges.astype(int), cells.row_edges.astype(int)
    rebuilt = np.repeat(np.repeat(cells.black, np.diff(re), 0), np.diff(ce), 1)
    np.testing.assert_array_equal(rebuilt.astype(bool), ~img)
    # the merge pays: a ChArUco square is a few marker bits, not 64 x 64 texels
    assert cells.black.size * 20 < img.size


def _box_spline_area(a, b, c):
    """Area of {(s, t) in [0, 1]^2: a s + b t <= c} (a, b != 0): the second difference
    of g(x) = max(x, 0)^2 / 2, an identity independent of polygon clipping."""

    def g(x):
        return np.maximum(x, 0.0) ** 2 / 2

    return (g(c) - g(c - a) - g(c - b) + g(c - a - b)) / (a * b)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_half_plane_edge_matches_the_closed_form(seed):
    """A print black for x < x_e, white beyond, seen by an oblique, rolled pinhole: each
    pixel the edge crosses is covered by the half-plane the edge's image bounds."""
    rng = np.random.default_rng(seed)
    cols, rows, half = 400, 400, np.array([0.1, 0.1])
    x_e = rng.uniform(-0.01, 0.01)
    img = np.ones((rows, cols), bool)
    k_e = int(round((x_e + half[0]) / (2 * half[0]) * cols))
    x_e = k_e * 2 * half[0] / cols - half[0]  # the edge on a texel boundary
    img[:, :k_e] = False
    cells = print_cells(img, half)
    C = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.3, -0.15), rng.uniform(0.25, 0.4)])
    up = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.0])
    R = np.asarray(look_at_rotation(C, [x_e, 0.0, 0.0], up))
    f, cx, cy = 400.0, 80.0, 60.0

    def to_plane(u, v):  # pixel coordinates -> points on z = 0
        d = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1) @ R
        return C + (-C[2] / d[..., 2])[..., None] * d

    def to_pixel(p):
        q = (p - C) @ R.T
        return f * q[..., 0] / q[..., 2] + cx, f * q[..., 1] / q[..., 2] + cy

    # the edge's image: a u + b v = c, black where a u + b v < c
    u1, v1 = to_pixel(np.array([x_e, -0.03, 0.0]))
    u2, v2 = to_pixel(np.array([x_e, 0.03, 0.0]))
    a, b = v2 - v1, -(u2 - u1)
    c = a * u1 + b * v1
    ub, vb = to_pixel(np.array([x_e - 0.01, 0.0, 0.0]))
    if a * ub + b * vb > c:
        a, b, c = -a, -b, -c
    jj, ii = np.mgrid[0:120, 0:160]
    jj, ii = jj.ravel().astype(float), ii.ravel().astype(float)
    # pixel (i, j): black area = {(s, t): a (i + s) + b (j + t) < c}
    black = _box_spline_area(a, b, c - a * ii - b * jj)
    crossed = (black > 1e-9) & (black < 1 - 1e-9)
    ii, jj, black = ii[crossed], jj[crossed], black[crossed]
    quad = np.stack([to_plane(ii, jj), to_plane(ii + 1, jj), to_plane(ii + 1, jj + 1),
                     to_plane(ii, jj + 1)], 1)  # fmt: skip
    inside = np.all(np.abs(quad[..., :2]) < half - 1e-3, axis=(1, 2))  # on the print
    assert inside.sum() > 100
    quad, ref = quad[inside], 1.0 - black[inside]
    np.testing.assert_allclose(coverage_numpy(quad, cells, R, C), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(_kernel(quad, cells, R, C), ref, rtol=0, atol=1e-9)


def _camera(scene):
    """(surface, C, R, K, distortion or None, W, H) of a scene, as the renderer sets them up."""
    dist = scene.camera.distortion if scene.camera.has_distortion else None
    C, R = scene.camera_pose()
    W, H = scene.camera.resolution
    return Surface(scene), C, R, scene.camera.intrinsics(), dist, W, H


def _holder_only(scene):
    """Pixels (H, W) whose centre and four corners see the holder."""
    surface, C, R, K, dist, W, H = _camera(scene)
    _, _, rk, _ = _hits(surface, C, R, *pixel_grid(K, W, H, dist, True))
    _, _, rc, _ = _hits(surface, C, R, *pixel_grid(K, W, H, dist))
    on = rk == HOLDER
    return (rc == HOLDER) & on[:-1, :-1] & on[1:, :-1] & on[:-1, 1:] & on[1:, 1:]


def _rays_coverage(scene, ei, ej, n):
    """White share of n x n sub-rays per pixel, labelled by the renderer's rays."""
    surface, C, R, K, dist, W, H = _camera(scene)
    xn, yn = _subpixel_normalized(K, ei, ej, n, dist, pixel_grid(K, W, H, dist))
    _, _, region, white = _hits(surface, C, R, xn, yn)
    assert np.all(region == HOLDER)
    return white.reshape(len(ei), n * n).mean(1)


@pytest.mark.parametrize("distortion", [False, True])
def test_many_sub_rays_converge_to_the_exact_coverage(distortion):
    scene = board_scene(distortion=distortion)
    res = render(scene)
    st = res.stats
    assert st.coverage_pixels > 300 and st.edge_pixels > st.coverage_pixels
    surface, C, R, K, dist, W, H = _camera(scene)
    xc, _, _, _ = _hits(surface, C, R, *pixel_grid(K, W, H, dist, True))
    # edge pixels whose centre and corners all see the holder (no occluders here): the
    # print-only edges, each of its sub-rays on the holder
    sel = res.edge & _holder_only(scene)
    assert sel.sum() == st.coverage_pixels
    ej, ei = np.nonzero(sel)
    quad = np.stack([xc[ej, ei], xc[ej, ei + 1], xc[ej + 1, ei + 1], xc[ej + 1, ei]], 1)
    cells = surface.print_cells()
    exact = _kernel(quad, cells, R, C)
    np.testing.assert_allclose(coverage_numpy(quad, cells, R, C), exact, rtol=0, atol=1e-12)
    errs = {}
    for n in (16, 64):
        errs[n] = np.abs(_rays_coverage(scene, ei, ej, n) - exact)
        # a straight edge cuts at most ~2n of the n^2 cells of the midpoint rule, each
        # miscounted by at most its area 1/n^2
        assert errs[n].max() <= 2.0 / n
    # and the error shrinks as the rays multiply (midpoint rule: ~1/n on average or better)
    assert errs[64].mean() < 0.5 * errs[16].mean()
    assert errs[64].mean() < 2e-3


def test_exact_mode_changes_only_the_print_edges_and_agrees_with_fine_rays():
    exact = render(board_scene(mode="exact"))
    rays = render(board_scene(mode="rays"))
    fine = render(board_scene(mode="rays", antialias=16))
    assert rays.stats.coverage_pixels == 0
    assert exact.stats.edge_pixels == rays.stats.edge_pixels
    assert rays.stats.subpixel_samples == 9 * rays.stats.edge_pixels
    n_ray_px = exact.stats.edge_pixels - exact.stats.coverage_pixels
    assert exact.stats.subpixel_samples == 9 * n_ray_px
    scene = board_scene()
    cover = exact.edge & _holder_only(scene)
    assert cover.sum() == exact.stats.coverage_pixels
    # every other pixel as before (to rounding: fewer sub-rays take the numpy paths
    # below the kernels' batch size, equal to 1e-12, test_render_kernels.py)
    np.testing.assert_allclose(exact.radiance[~cover], rays.radiance[~cover], rtol=1e-12)
    # albedo contrast of the two prints: white and black radiance differ by (0.85-0.04)/0.85
    lw = exact.radiance[cover].max()
    err_exact = np.abs(exact.radiance - fine.radiance)[cover]
    err_rays = np.abs(rays.radiance - fine.radiance)[cover]
    # 16 x 16 rays are within 2/16 of the area; 3 x 3 within 2/3
    assert err_exact.max() <= 2.0 / 16 * lw
    assert err_exact.mean() < err_rays.mean()


def test_print_antialias_is_validated():
    doc = minimal_scene()
    doc["render"]["print_antialias"] = "area"
    with pytest.raises(ConfigError, match="print_antialias"):
        parse_scene(doc)


def test_cells_outside_the_print_count_white():
    cells = PrintCells(np.array([0.0, 1.0]), np.array([0.0, 1.0]), np.ones((1, 1), np.uint8),
                       np.array([1.0, 0.5, 1.0, 0.5]))  # fmt: skip
    C = np.array([0.0, 0.0, 1.0])
    R = np.diag([1.0, -1.0, -1.0])  # looking straight down
    # a footprint half on the 1 m print (x in [-0.5, 0.5]), half beyond its right edge
    quad = np.array([[[0.25, 0.1, 0], [0.75, 0.1, 0], [0.75, -0.1, 0], [0.25, -0.1, 0]]], float)
    np.testing.assert_allclose(coverage_numpy(quad, cells, R, C), [0.5], atol=1e-12)
    np.testing.assert_allclose(_kernel(quad, cells, R, C), [0.5], atol=1e-12)


def test_schema_version_1_renders_print_edges_by_rays():
    doc = minimal_scene()
    assert parse_scene(doc).render.print_antialias == "exact"  # no version: the current
    assert parse_scene({**doc, "schema_version": 2}).render.print_antialias == "exact"
    assert parse_scene({**doc, "schema_version": 1}).render.print_antialias == "rays"
    old = {**doc, "schema_version": 1, "render": {**doc["render"], "print_antialias": "exact"}}
    assert parse_scene(old).render.print_antialias == "exact"  # said so: as said
    with pytest.raises(ConfigError, match="schema_version"):
        parse_scene({**doc, "schema_version": 3})


def test_black_albedo_zero_shades_instead_of_rescaling():
    """The blend rescales the centre's radiance by the albedos' ratio; a zero albedo has
    no ratio and is shaded again: the two branches agree where both apply."""

    def scene(black):
        s = board_scene()
        return s.model_copy(update={"holder": s.holder.model_copy(update={"albedo_black": black})})

    zero = render(scene(0.0), diffuse=True)
    tiny = render(scene(1e-9), diffuse=True)
    assert zero.stats.coverage_pixels == tiny.stats.coverage_pixels > 300
    scale = zero.radiance.max()
    np.testing.assert_allclose(zero.radiance, tiny.radiance, rtol=0, atol=2e-9 * scale)
    np.testing.assert_allclose(zero.diffuse, tiny.diffuse, rtol=0, atol=2e-9)

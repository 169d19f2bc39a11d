"""The fused pose kernel (:mod:`gonio.capture.pose_kernel`) against the numpy path.

The numpy path of :func:`gonio.capture.pose_measure.measure_pose` is the reference (itself
checked against closed forms in ``test_reduce_bayer.py`` and against the simulator's truth
in ``test_reduce_accuracy.py``).  Both run on the same decoded DNG brackets, rendered by
the simulator at the rig's poses, with and without the parts the kernel handles apart:
saturated pixels, a subtracted master dark with a per-pixel variance, a flat field, a
point light and a light without a normal.  Labels and directions must agree bit for bit
(same operations in the same order), the region sums to rounding.  Each comparison also
checks which path ran (``PoseMeasurement.kernel``): without numba both sides would be the
numpy path, and the comparison would prove nothing.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.pose_measure import measure_pose
from gonio.capture.raw import apply_flat, read_raw, subtract_dark
from gonio.radiometry import spherical_to_direction


@pytest.fixture(scope="module", autouse=True)
def numba_kernel():
    """The fused kernel, compiled: numba is a dependency (pyproject.toml), so its absence
    is a broken install that this file must report, not skip."""
    try:
        from gonio.capture.pose_kernel import pose_sums
    except ImportError as exc:
        pytest.fail(f"numba cannot load ({exc}): the fused kernel cannot be compared")
    return pose_sums


LIGHT = {
    "type": "disk",
    "position": [0.0, 0.25, 0.433],
    "look_at": [0, 0, 0],
    "radius": 0.01,
    "radiance": [2e4, 2e4, 2e4],
}


@pytest.fixture(scope="module")
def brackets():
    """Two poses of a GGX sample, each a 3-frame bracket whose longest frame clips the
    highlight; and the setup."""
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene
    from gonio.simulator.sensor import mean_electrons

    scene = parse_scene(
        {
            "sample": {
                "width": 0.05,
                "height": 0.05,
                "brdf": {"model": "ggx", "params": {"alpha": 0.15, "ks": 0.8}},
            },
            "holder": {"width": 0.16, "height": 0.16, "board": {}},
            "lights": [LIGHT],
            "camera": {
                "resolution": [400, 300],
                "focal_length": 0.016,
                "fov_deg": 30.0,
                "position": [0.1, -0.2, 0.35],
                "look_at": [0, 0, 0],
            },
        }
    )
    kin = Kinematics(default_rig_config())
    state = {}
    cam = SimulatedCamera(scene, pose_provider=lambda: state["poses"])
    out = []
    for k, (ti, to) in enumerate(((30, 30), (50, 40))):
        wi = spherical_to_direction(np.radians(ti), 0.0)
        wo = spherical_to_direction(np.radians(to), np.pi)
        state["poses"] = rp = kin.poses(kin.inverse(wi, wo))
        truth = cam.render("sample")
        e_per_s = mean_electrons(truth.radiance, scene.camera, 1.0, 8.0)
        gain = scene.camera.sensor.gain_at_base_iso
        t = 0.5 * 15871.0 / gain / e_per_s[truth.region == 1].max()  # highlight at half scale
        frames = [
            read_raw(cam.capture(tt, 100, 8.0, seed=10 * k + j), name=f"p{k}f{j}")
            for j, tt in enumerate((t / 4, t, 3 * t))
        ]
        out.append((frames, rp))
    return setup_from_scene(scene, 0.99), out


def both_paths(monkeypatch, frames, setup, rp, **kw):
    args = (frames, setup, rp.light_position, kw.pop("light_normal", rp.light_normal))
    kw.setdefault("reported_camera", (rp.camera_position, rp.camera_rotation.T))
    monkeypatch.setenv("GONIO_NUMBA", "0")
    ref = measure_pose(*args, **kw)
    monkeypatch.setenv("GONIO_NUMBA", "1")
    got = measure_pose(*args, **kw)
    # the comparison means something only if each side took its own path
    assert ref.kernel == "numpy"
    assert got.kernel == "numba"
    return ref, got


def assert_same(ref, got):
    assert np.array_equal(ref.regions.label, got.regions.label)
    assert ref.regions.box == got.regions.box
    assert (ref.regions.label >= 0).sum() > 1000
    np.testing.assert_array_equal(got.wi, ref.wi)
    np.testing.assert_array_equal(got.wo, ref.wo)
    for name in ("radiance", "radiance_var", "geometry", "ratio", "ratio_var"):
        a, b = getattr(ref, name), getattr(got, name)
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        ok = np.isfinite(a)
        assert ok.any(), name
        np.testing.assert_allclose(b[ok], a[ok], rtol=1e-12, atol=0, err_msg=name)
    np.testing.assert_array_equal(got.flags, ref.flags)
    assert got.reasons == ref.reasons


@pytest.mark.parametrize("pose", [0, 1])
def test_fused_kernel_matches_numpy_path(brackets, monkeypatch, pose):
    setup, poses = brackets
    frames, rp = poses[pose]
    assert any(f.saturated.any() for f in frames)  # the bracket clips somewhere
    ref, got = both_paths(monkeypatch, frames, setup, rp)
    assert_same(ref, got)
    # and the merge's clip guard acts here (frames left out that their own reading keeps),
    # so the comparison covers it
    from gonio.capture.hdr import merge_bracket

    box = ref.regions.box
    merged = merge_bracket(frames, setup.noise, region=box)
    by_reading = sum((~f.region(box)[2]).astype(np.int64) for f in frames)
    assert (merged.frames_used < by_reading).sum() > 20  # 57 and 78 pixels here


def test_fused_kernel_with_dark_flat_and_saturated_regions(brackets, monkeypatch):
    setup, poses = brackets
    frames, rp = poses[0]
    rng = np.random.default_rng(1)
    dark = rng.normal(3.0, 1.0, frames[0].shape)
    flat = rng.uniform(0.95, 1.05, frames[0].shape)
    frames = [apply_flat(subtract_dark(f, dark), flat) for f in frames]
    dark_var = rng.uniform(0.5, 2.0, frames[0].shape)
    ref, got = both_paths(monkeypatch, frames, setup, rp, dark_variance=dark_var)
    assert_same(ref, got)
    # only the longest frame: the highlight's regions are saturated in every frame
    ref, got = both_paths(monkeypatch, frames[2:], setup, rp, dark_variance=1.5)
    assert np.isnan(ref.radiance).any() and np.isfinite(ref.radiance).any()
    assert_same(ref, got)


def test_fused_kernel_with_a_point_light_without_normal(brackets, monkeypatch):
    setup, poses = brackets
    frames, rp = poses[1]
    point = setup.replace(light_radius=None)
    assert_same(*both_paths(monkeypatch, frames, point, rp, light_normal=None))


def test_the_kernel_is_compiled_for_the_structured_arguments(brackets, monkeypatch, numba_kernel):
    """The dispatcher holds one compiled signature of three namedtuples (the reduction's
    measurement compiled it): named fields, not 28 positional arguments."""
    from gonio.capture import pose_kernel as pk

    setup, poses = brackets
    frames, rp = poses[0]
    monkeypatch.setenv("GONIO_NUMBA", "1")
    m = measure_pose(
        frames,
        setup,
        rp.light_position,
        rp.light_normal,
        reported_camera=(rp.camera_position, rp.camera_rotation.T),
    )
    assert m.kernel == "numba"
    sigs = numba_kernel.signatures
    assert sigs, "the fused kernel was never compiled"
    assert all(len(sig) == 3 for sig in sigs)
    assert [t.instance_class for t in sigs[0]] == [pk.Bracket, pk.Stencils, pk.View]


def test_fused_kernel_matches_numpy_path_with_distortion(brackets, monkeypatch):
    """Both paths read each pixel's ray from the same undistorted coordinates: labels and
    directions the same to the bit, sums to rounding; and the distortion changed them."""
    setup, poses = brackets
    frames, rp = poses[1]
    lens = setup.replace(dist=np.array([-0.3, 0.1, 0.002, -0.001, 0.01]))
    ref, got = both_paths(monkeypatch, frames, lens, rp)
    assert_same(ref, got)
    pinhole, _ = both_paths(monkeypatch, frames, setup, rp)
    assert not np.array_equal(pinhole.wo, ref.wo)


def test_zero_distortion_is_the_pinhole_path_to_the_bit(brackets, monkeypatch):
    setup, poses = brackets
    frames, rp = poses[0]
    for zero in (np.zeros(5), np.zeros(4)):
        a = both_paths(monkeypatch, frames, setup, rp)
        b = both_paths(monkeypatch, frames, setup.replace(dist=zero), rp)
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x.regions.label, y.regions.label)
            for name in ("wi", "wo", "radiance", "radiance_var", "geometry", "ratio"):
                np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)


def test_fused_kernel_matches_numpy_path_with_regions_trimmed_to_a_spread(brackets, monkeypatch):
    """``max_region_spread_deg``: both paths keep the same pixels; every region's pixels
    see the camera and the light within the spread (angles between the pixels' own
    directions, from their points on the sample), and the trim removed pixels."""
    setup, poses = brackets
    frames, rp = poses[0]
    spread = 1.0
    ref, got = both_paths(monkeypatch, frames, setup.replace(max_region_spread_deg=spread), rp)
    assert_same(ref, got)
    whole, _ = both_paths(monkeypatch, frames, setup, rp)
    n_trim, n_whole = (ref.regions.label >= 0).sum(), (whole.regions.label >= 0).sum()
    assert n_trim < 0.8 * n_whole, (n_trim, n_whole)
    pts = ref.regions.points
    for j in range(ref.regions.n_regions):
        p = pts[ref.regions.label == j]
        assert len(p) > 20
        for pos in (rp.camera_position, rp.light_position):
            w = np.asarray(pos)[None, :] - p
            w /= np.linalg.norm(w, axis=1, keepdims=True)
            # the largest angle between two of the region's directions: between the
            # extremes of its bounding directions (pixels on opposite corners)
            cosmin = float(np.min(w @ w.T))
            assert np.degrees(np.arccos(min(cosmin, 1.0))) <= spread * np.sqrt(2) + 1e-6


def _hot_mask(shape, seed=7, n=40):
    rng = np.random.default_rng(seed)
    mask = np.zeros(shape, bool)
    mask.reshape(-1)[rng.choice(mask.size, n * 50, replace=False)] = True
    return mask


def test_masked_pixels_weigh_nothing_in_both_paths(brackets, monkeypatch):
    """A hot/dead pixel mask (2000 pixels) in both paths: the same sums; and it changes
    them (the masked sites really leave the sums)."""
    setup, poses = brackets
    frames, rp = poses[0]
    mask = _hot_mask(frames[0].shape)
    ref, got = both_paths(monkeypatch, frames, setup, rp, pixel_mask=mask)
    assert_same(ref, got)
    plain, _ = both_paths(monkeypatch, frames, setup, rp)
    ok = np.isfinite(plain.radiance) & np.isfinite(ref.radiance)
    assert not np.array_equal(plain.radiance[ok], ref.radiance[ok])
    np.testing.assert_array_equal(plain.wi, ref.wi)  # directions: every pixel of the region


def test_planted_hot_pixels_are_excluded(brackets, monkeypatch):
    """Frames with hot pixels planted (a dark signal of 500 DN at 2000 pixels) reduce,
    with those pixels masked, to exactly what the frames without them give."""
    setup, poses = brackets
    frames, rp = poses[1]
    mask = _hot_mask(frames[0].shape, seed=8)
    hot = np.where(mask, -500.0, 0.0)  # subtracting a negative dark adds the hot signal
    planted = [subtract_dark(f, hot) for f in frames]
    clean = [subtract_dark(f, np.zeros(f.shape)) for f in frames]
    for kernel in ("0", "1"):
        monkeypatch.setenv("GONIO_NUMBA", kernel)
        a = measure_pose(
            planted,
            setup,
            rp.light_position,
            rp.light_normal,
            pixel_mask=mask,
            reported_camera=(rp.camera_position, rp.camera_rotation.T),
        )
        b = measure_pose(
            clean,
            setup,
            rp.light_position,
            rp.light_normal,
            pixel_mask=mask,
            reported_camera=(rp.camera_position, rp.camera_rotation.T),
        )
        unmasked, clean_unmasked = (
            measure_pose(
                fs,
                setup,
                rp.light_position,
                rp.light_normal,
                reported_camera=(rp.camera_position, rp.camera_rotation.T),
            )
            for fs in (planted, clean)
        )
        assert a.kernel == ("numba" if kernel == "1" else "numpy")
        for name in ("radiance", "radiance_var", "geometry", "ratio"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        ok = np.isfinite(clean_unmasked.radiance) & np.isfinite(unmasked.radiance)
        # unmasked, the hot signal is in the regions' radiance
        assert np.all(unmasked.radiance[ok] >= clean_unmasked.radiance[ok])
        assert (unmasked.radiance[ok] > clean_unmasked.radiance[ok]).sum() > ok.sum() // 2


def test_light_profile_in_g_in_both_paths_and_its_closed_form(brackets, monkeypatch):
    """``cos^n(psi)`` in G: the same in both paths, and each region's G divided by the
    Lambertian emitter's is the mean of cos^n(psi) over its pixels (psi: the angle off
    the light's normal of the direction from the light to the pixel's point), to the
    weights' second order."""
    setup, poses = brackets
    frames, rp = poses[1]
    prof = setup.replace(light_profile_n=1.7)
    ref, got = both_paths(monkeypatch, frames, prof, rp)
    assert_same(ref, got)
    lambertian, _ = both_paths(monkeypatch, frames, setup, rp)
    n_l = np.asarray(rp.light_normal, float) / np.linalg.norm(rp.light_normal)
    lp = np.asarray(rp.light_position, float)
    x, y, z = ref.regions.xyz
    v = np.stack([x - lp[0], y - lp[1], z - lp[2]], axis=-1)
    cos_psi = (v @ n_l) / np.linalg.norm(v, axis=-1)
    lab = ref.regions.label
    want = np.array([np.mean(cos_psi[lab == r] ** 1.7) for r in range(len(ref.flags))])
    ok = np.isfinite(ref.geometry[:, 1])
    ratio = ref.geometry[ok, 1] / lambertian.geometry[ok, 1]
    np.testing.assert_allclose(1 - ratio, 1 - want[ok], rtol=0.02)
    assert np.ptp(ratio) > 1e-4  # the profile changes G across the sample


def test_fused_kernel_matches_numpy_path_on_a_rectangular_grid(brackets, monkeypatch):
    """``grid_y`` (a texel reduction's NXxNY): both paths label the same pixels, and each
    region ``iy * nx + ix`` holds the pixels whose sample point lies in cell (ix, iy),
    ``iy`` counted from -y (worked from the points themselves)."""
    setup, poses = brackets
    frames, rp = poses[0]
    s = setup.replace(grid=5, grid_y=2, roi_fraction=1.0)
    ref, got = both_paths(monkeypatch, frames, s, rp)
    assert_same(ref, got)
    assert ref.regions.n_regions == 10 and len(ref.flags) == 10
    w, h = s.sample_size
    inside = ref.regions.label >= 0
    pts, lab = ref.regions.points[inside], ref.regions.label[inside]
    ix = np.floor((pts[:, 0] + w / 2) / (w / 5)).astype(int)
    iy = np.floor((pts[:, 1] + h / 2) / (h / 2)).astype(int)
    assert np.array_equal(lab, iy * 5 + ix)


def test_fused_kernel_matches_numpy_path_with_the_texel_margin(brackets, monkeypatch):
    """A texel reduction's ``region_margin_px``: both paths keep the same pixels, fewer
    than the whole cells."""
    from gonio.capture.texel_reduce import texel_setup

    setup, poses = brackets
    frames, rp = poses[0]
    ref, got = both_paths(monkeypatch, frames, texel_setup(setup, (4, 4)), rp)
    assert_same(ref, got)
    whole, _ = both_paths(monkeypatch, frames, setup.replace(grid=4, roi_fraction=1.0), rp)
    n_kept, n_whole = (ref.regions.label >= 0).sum(), (whole.regions.label >= 0).sum()
    assert 0.3 * n_whole < n_kept < 0.95 * n_whole, (n_kept, n_whole)


@pytest.mark.parametrize("masked", [False, True])
def test_effective_sites_of_the_pose_pass_equal_the_budgets_own(brackets, monkeypatch, masked):
    """``PoseMeasurement.n_sites`` (summed by the pose's own pass, which the reduction's
    budget now uses) equals :func:`gonio.capture.radiometric.effective_sites` computed
    from the regions afterwards (the reference, built site by site with OpenCV filters),
    bit for bit in both paths: the Bayer weights are powers of two, so their sums and
    sums of squares are exact in any order.  With a pixel mask too, which must change
    the counts (masked sites leave both)."""
    from gonio.capture.radiometric import effective_sites

    setup, poses = brackets
    frames, rp = poses[0]
    mask = _hot_mask(frames[0].shape) if masked else None
    ref, got = both_paths(monkeypatch, frames, setup, rp, pixel_mask=mask)
    n = ref.regions.n_regions
    want = effective_sites(ref.regions.label, ref.regions.box, frames[0].cell_channel, n, mask)
    assert np.isfinite(want).sum() > n  # regions with sites, in more than one channel
    np.testing.assert_array_equal(ref.n_sites, want)
    np.testing.assert_array_equal(got.n_sites, want)
    if masked:
        plain = effective_sites(ref.regions.label, ref.regions.box, frames[0].cell_channel, n)
        assert not np.array_equal(plain, want)


@pytest.mark.parametrize("lens", [False, True])
def test_region_moments_of_the_kernel_equal_region_moments(brackets, monkeypatch, lens):
    """The fused kernel's centroids and covariances of the regions' points (which the
    aperture correction uses instead of computing the crop's rays again) are
    :func:`gonio.capture.aperture.region_moments`' on the regions' own rays, to the bit,
    pinhole and with a distorting lens."""
    from gonio.capture.aperture import region_moments

    setup, poses = brackets
    frames, rp = poses[1]
    if lens:
        setup = setup.replace(dist=np.array([-0.3, 0.1, 0.002, -0.001, 0.01]))
    _, got = both_paths(monkeypatch, frames, setup, rp)
    reg = got.regions
    x, y, _ = reg.xyz
    want_c, want_cov = region_moments(reg.label, x, y, reg.n_regions)
    c, cov = reg.extra["moments"]
    assert np.isfinite(want_cov).all() and (want_cov[:, 0, 0] > 0).all()
    np.testing.assert_array_equal(c, want_c)
    np.testing.assert_array_equal(cov, want_cov)

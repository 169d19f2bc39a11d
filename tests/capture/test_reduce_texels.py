"""``gonio capture reduce --texels N``: texels.h5 from a small simulated session.

The session (real dynamixel-sdk on the virtual bus, rendered DNGs at 320 x 240, two sample
poses) has an albedo map that grows along +x and along +y, so that a texel's place on
the sample shows in its BRDF.  Checked: the per-texel samples equal the region
samples of an ordinary ``--grid N --roi-fraction 1`` reduction of the same session (the
existing path with the texel reduction's ``region_margin_px`` and without its aperture
correction, mapped region -> texel by
the convention, worked out here by hand); each
texel's BRDF follows the map's mean over that texel's rectangle (the truth, independent
of the reduction); the chunk layout; the refusals (too fine for the camera, N < 1,
malformed, with --grid), which write nothing; an NXxNY grid.
"""

from __future__ import annotations

import json
import os
import tomllib

import h5py
import numpy as np
import pytest
import tomli_w
from sim_sessions import REFERENCE_NORMAL, capture, grid_plan, scene_toml, write_inputs

from gonio.app.sim_reduction import write_reduction_toml
from gonio.capture.texel_reduce import TEXEL_MARGIN_PX
from gonio.cli import run
from gonio.dataset import BUDGET_TERMS, Flag, load_samples
from gonio.texels import ORIENTATION, open_texels

pytestmark = pytest.mark.slow  # captures a simulated session (virtual bus, renders)

N = 4
PLAN = grid_plan(
    "texel-test",
    seed=5,
    theta_i_deg=[30],
    theta_o_deg=[0, 40],
    darks=2,
    references=[REFERENCE_NORMAL],
)
# the albedo factor map over a uniform lambert sample
SCENE = scene_toml(albedo_map="map.npy")


def albedo_map(size: int = 64) -> np.ndarray:
    """The map's factor: row 0 at +y, column 0 at -x (the simulator's convention), rising
    along +x (columns) and along +y (towards row 0)."""
    r, c = np.mgrid[0:size, 0:size]
    return (0.6 + 0.4 * c / (size - 1)) * (1.0 - 0.4 * r / (size - 1))


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    """The session reduced twice: with --texels N, then (into the same folder) with the
    ordinary --grid N --roi-fraction 1; the texel file's content is kept in memory."""
    d = tmp_path_factory.mktemp("texels")
    write_inputs(d, PLAN, SCENE)
    np.save(d / "map.npy", albedo_map())
    s = capture(d)
    write_reduction_toml(s)
    rect = d / "R" / "samples.h5"  # NXxNY, into another folder
    assert run("capture", "reduce", str(s), "--texels", "4x2", "--out", str(rect), "--quiet") == 0
    with open_texels(rect.with_name("texels.h5")) as tf:
        rect_rows = (tf.shape, tf.block(0, tf.n_texels))
    assert run("capture", "reduce", str(s), "--texels", str(N), "--quiet", "--no-plot") == 0
    summary = json.loads((s / "reduction.json").read_text())
    with open_texels(s / "texels.h5") as tf:
        rows = tf.block(0, tf.n_texels)
        meta = dict(shape=tf.shape, n_poses=tf.n_poses, pose=tf.pose, chunk=tf.chunk_texels)
    with h5py.File(s / "texels.h5") as f:
        chunks = {k: f[k].chunks for k in ("wi", "brdf", "flags", "budget/noise", "geometry_modes")}
        attrs = dict(f.attrs)
    texel_samples = load_samples(s / "samples.h5")
    # the ordinary reduction with the texel reduction's margin between regions and, as
    # there, no aperture correction
    config = tomllib.loads((s / "reduction.toml").read_text())
    config.setdefault("reduction", {})["region_margin_px"] = TEXEL_MARGIN_PX
    config["reduction"]["aperture_correction"] = False
    (d / "margin.toml").write_text(tomli_w.dumps(config))
    grid = ("--grid", str(N), "--roi-fraction", "1", "--config", str(d / "margin.toml"))
    assert run("capture", "reduce", str(s), *grid, "--quiet") == 0
    return dict(
        session=s,
        rows=rows,
        meta=meta,
        chunks=chunks,
        attrs=attrs,
        summary=summary,
        texel_samples=texel_samples,
        grid=load_samples(s / "samples.h5"),
        grid_summary=json.loads((s / "reduction.json").read_text()),
        rect=rect_rows,
    )


def test_texels_equal_the_region_samples_of_a_grid_reduction(reduced):
    rows, grid = reduced["rows"], reduced["grid"]
    t_count, p = N * N, reduced["meta"]["n_poses"]
    assert len(rows) == t_count and p == 2 and len(grid) == t_count * p
    # samples.h5 is pose after pose, regions r = iy * N + ix with iy counted from -y;
    # the texel of region (iy, ix) is row N - 1 - iy, column ix (worked by hand)
    for k in range(len(grid)):
        pose_col, r = divmod(k, t_count)
        iy, ix = divmod(r, N)
        s = rows[(N - 1 - iy) * N + ix]
        np.testing.assert_array_equal(s.wi[pose_col], grid.wi[k])
        np.testing.assert_array_equal(s.wo[pose_col], grid.wo[k])
        np.testing.assert_array_equal(s.brdf[pose_col], grid.brdf[k])
        assert s.flags[pose_col] == grid.flags[k] and s.pose[pose_col] == grid.pose[k]
        # every term but the geometry's, whose gradient a texel run takes with each
        # texel's level divided out (see test_geometry_term_ignores_the_albedo_map)
        for term in set(BUDGET_TERMS) - {"geometry"}:
            np.testing.assert_array_equal(s.budget[term][pose_col], grid.budget[term][k])
        rss = np.sqrt(sum(s.budget[term][pose_col] ** 2 for term in BUDGET_TERMS))
        np.testing.assert_allclose(s.brdf_std[pose_col], rss, rtol=1e-12)
        np.testing.assert_array_equal(s.geometry_modes[pose_col], grid.geometry_modes[k])
    s0 = rows[0]
    assert list(s0.geometry_mode_names) == list(grid.geometry_mode_names)
    for term in ("reference", "light_scale"):
        np.testing.assert_array_equal(s0.shared_budget[term], grid.shared_budget[term])
    np.testing.assert_array_equal(
        s0.attrs["calibration_rel_std"], grid.attrs["calibration_rel_std"]
    )
    # samples.h5 of the texel reduction is the same set of samples, pooled
    np.testing.assert_array_equal(reduced["texel_samples"].brdf, grid.brdf)
    assert all(int(s.flags.max()) == 0 for s in rows)


def test_geometry_term_ignores_the_albedo_map(reduced):
    """A Lambertian BRDF has no slope over the directions, so the geometry term (the
    gradient of log f times the directions' modes) is ~0 whatever the albedo map does
    (a texel's directions move nothing).  Pooled over texels, as an ordinary reduction
    takes its neighbours, the map's 40 % ramp across the sample reads as a directional
    slope; the texel run divides each texel's level out first."""
    rel = np.array([s.budget["geometry"] / s.brdf for s in reduced["rows"]])
    assert np.median(rel) < 1e-4 and rel.max() < 5e-4
    grid = reduced["grid"]
    assert np.median(grid.budget["geometry"] / grid.brdf) > 3e-3  # the pooled estimate


def test_texel_orientation_follows_the_albedo_map(reduced):
    """Each texel's BRDF over the map's mean on that texel's rectangle: one common factor
    (the Lambertian albedo / pi and the calibration), to 3 %; a texel landing elsewhere
    would be off by 10-50 %."""
    m = albedo_map()
    k = m.shape[0] // N
    truth = m.reshape(N, k, N, k).mean(axis=(1, 3)).ravel()  # row 0 at +y
    for pose_col in range(2):
        f = np.array([s.brdf[pose_col, 1] for s in reduced["rows"]])
        ratio = f / truth
        np.testing.assert_allclose(ratio / np.median(ratio), 1.0, atol=0.03)
        # and the absolute scale: the G albedo 0.5 / pi, to the reduction's accuracy
        np.testing.assert_allclose(np.median(ratio), 0.5 / np.pi, rtol=0.03)


def test_a_rectangular_texel_grid_follows_the_map_too(reduced):
    """--texels 4x2: 4 texels along x, 2 along y (an image of 2 rows by 4 columns)."""
    shape, rows = reduced["rect"]
    assert shape == (2, 4) and len(rows) == 8
    m = albedo_map()
    truth = m.reshape(2, 32, 4, 16).mean(axis=(1, 3)).ravel()
    f = np.array([s.brdf[0, 1] for s in rows])
    ratio = f / truth
    np.testing.assert_allclose(ratio / np.median(ratio), 1.0, atol=0.03)
    np.testing.assert_allclose(rows[5].attrs["texel_center"], [-0.00625, -0.0125])


def test_file_layout_and_summary(reduced):
    meta, summary = reduced["meta"], reduced["summary"]["texels"]
    assert meta["shape"] == (N, N)
    k = meta["chunk"]
    assert k == summary["chunk_texels"] == N * N  # 16 texels x 2 poses: one small chunk
    chunks = reduced["chunks"]
    assert chunks["brdf"] == (k, 2, 3) and chunks["flags"] == (k, 2)
    assert chunks["budget/noise"] == (k, 2, 3) and chunks["geometry_modes"][:2] == (k, 2)
    attrs = reduced["attrs"]
    assert attrs["orientation"] == ORIENTATION and list(attrs["texels"]) == [N, N]
    assert attrs["session"] == str(reduced["session"])
    np.testing.assert_allclose(attrs["sample_size"], [0.05, 0.05])
    assert summary["kept"] == 2 * N * N and summary["texels_without_samples"] == 0
    assert summary["roi_fraction"] == 1.0 and summary["grid"] == [N, N]
    assert summary["boundary_margin_px"] == TEXEL_MARGIN_PX
    res = summary["resolution"]
    # the texel's side in pixels at the best pose (the frontal one, theta_o = 0): 12.5 mm
    # at 0.40 m with fx = 160 / tan(15 deg) = 597.1 px (320 px over a 30 deg fov)
    fx = 160 / np.tan(np.radians(15))
    assert res["pixels_per_texel"] == pytest.approx(fx * 0.0125 / 0.4, rel=0.01)
    # the plain reduction that followed dropped texels.h5 with its output set
    assert reduced["grid_summary"]["texels"] is None
    assert not os.path.lexists(reduced["session"] / "texels.h5")


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--texels", "40"), "1.87 pixels across.*use at most --texels 37"),
        (("--texels", "0"), "must be >= 1, got 0x0"),
        (("--texels", "4x"), "expected N or NXxNY"),
        (("--texels", "four"), "expected N or NXxNY"),
        (("--texels", "64x4"), "1.17 pixels across.*use at most --texels 37x37"),
        (("--texels", "4", "--grid", "3"), "leave out --grid"),
    ],
)
def test_refusals_write_nothing(reduced, extra, message, capsys):
    s = reduced["session"]
    before = {p.name: (p.is_symlink() and os.readlink(p)) for p in s.iterdir()}
    before_bytes = (s / "samples.h5").read_bytes()
    assert run("capture", "reduce", str(s), *extra, "--quiet") == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    import re

    assert re.search(message, " ".join(err.split())), err
    assert {p.name: (p.is_symlink() and os.readlink(p)) for p in s.iterdir()} == before
    assert (s / "samples.h5").read_bytes() == before_bytes


def test_an_empty_pose_is_invalid_in_every_texel():
    """A pose that gave no measurement (one INVALID sample) is INVALID with NaN in every
    texel; the others are scattered by the convention (hand-made samples)."""
    from gonio.capture.texel_reduce import region_to_texel, texel_arrays
    from gonio.dataset import BRDFSamples

    n = 2
    z = np.tile([0.0, 0.0, 1.0], (n * n + 1, 1))
    brdf = np.arange(n * n + 1, dtype=float)[:, None] * np.ones(3)
    flags = np.zeros(n * n + 1, np.uint32)
    flags[-1] = Flag.INVALID
    s = BRDFSamples(wi=z, wo=z, brdf=brdf, flags=flags, pose=[3] * (n * n) + [5])
    a = texel_arrays(s, [n * n, 1], [3, 5], n)
    assert list(region_to_texel(2)) == [2, 3, 0, 1]  # region (iy=0: -y) is texel row 1
    assert a["brdf"][:, 0, 0].tolist() == [2.0, 3.0, 0.0, 1.0]
    assert (a["flags"][:, 1] == Flag.INVALID).all() and np.isnan(a["brdf"][:, 1]).all()
    assert np.isnan(a["wi"][:, 1]).all() and a["pose"].tolist() == [3, 5]


def test_a_texel_reduction_takes_the_outputs_lock(reduced, capsys):
    """texels.h5 belongs to samples.h5's output set: a reduction holding its lock (here
    this process, through another open file) makes a --texels run refuse, write nothing."""
    from gonio.capture.reduce import output_lock
    from gonio.locks import hold_lock

    s = reduced["session"]
    before = sorted(p.name for p in s.iterdir())
    with hold_lock(output_lock(s / "samples.h5"), "a test's reduction"):
        assert run("capture", "reduce", str(s), "--texels", str(N), "--quiet") == 1
    assert f"in use by process {os.getpid()}" in capsys.readouterr().err
    assert sorted(p.name for p in s.iterdir()) == before
    assert not os.path.lexists(s / "texels.h5")


def test_geometry_modes_beyond_the_limit_are_left_out_and_said_so():
    """The modes' (T, P, M, 6) array is the texel file's largest: 128 x 128 texels, 200
    poses and 10 modes are 16384 x 200 x 480 bytes = 1.46 GiB, beyond 1 GiB (by hand)."""
    from gonio.capture.texel_reduce import MAX_TEXEL_MODES_BYTES, modes_omitted, texel_arrays
    from gonio.dataset import BRDFSamples

    assert MAX_TEXEL_MODES_BYTES == 2**30
    assert modes_omitted(64 * 64, 200, 10) is None  # 0.37 GiB
    why = modes_omitted(128 * 128, 200, 10)
    assert "1.46 GiB" in why and "samples.h5 holds them" in why
    z = np.tile([0.0, 0.0, 1.0], (4, 1))
    s = BRDFSamples(
        wi=z,
        wo=z,
        brdf=np.ones((4, 3)),
        geometry_modes=np.zeros((4, 2, 6)),
        geometry_mode_scope=["session", "pose"],
        geometry_mode_names=["a", "b"],
    )
    assert "geometry_modes" in texel_arrays(s, [4], [0], 2)
    assert "geometry_modes" not in texel_arrays(s, [4], [0], 2, with_modes=False)


def test_levelling_divides_out_each_texels_geometric_mean():
    """2 x 1 texels, two poses and a pose without a measurement (hand-made numbers):
    texel levels 2 and 8 (geometric means over their poses) become their common
    geometric mean 4; the directional change between the poses (x 1.5) stays."""
    from gonio.capture.texel_reduce import texel_levelled

    # regions r = ix (one row): texel = ix; pose 1 is 1.5 x pose 0
    f = np.array([[2 / 1.5**0.5], [8 / 1.5**0.5], [2 * 1.5**0.5], [8 * 1.5**0.5], [7.0]])
    out = texel_levelled(f * np.ones(3), [2, 2, 1], np.ones(5, bool), (2, 1))
    np.testing.assert_allclose(out[:4, 0], [4 / 1.5**0.5] * 2 + [4 * 1.5**0.5] * 2)
    assert out[4, 0] == 7.0  # the empty pose's sample is left alone


def test_a_texels_h5_that_is_not_ours_is_never_touched(reduced, capsys):
    """A file named texels.h5 beside the output that no texel reduction wrote: --texels
    refuses (nothing written), and a plain reduction leaves it alone."""
    s = reduced["session"]
    foreign = s / "texels.h5"
    foreign.write_bytes(b"the lab's own notes")
    try:
        assert run("capture", "reduce", str(s), "--texels", str(N), "--quiet") == 1
        assert "is not a gonio texel file" in capsys.readouterr().err
        assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
        assert not foreign.is_symlink() and foreign.read_bytes() == b"the lab's own notes"
    finally:
        foreign.unlink()

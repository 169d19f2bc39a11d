"""Spatially varying samples: parameter maps and material mixes in the renderer.

References are independent of the map code: the renderer without maps (each texel's
parameters as a plain scene), the closed form of a Lambertian texel under a parallel
disk, the renderer's own surface points (geometry) for orientation, and the scene's
inline numbers for the truth file.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gonio.errors import ConfigError, FileFormatError
from gonio.simulator.render import render
from gonio.simulator.scene import parse_scene
from gonio.simulator.svbrdf import (
    ORIENTATION,
    SpatialBRDF,
    read_truth,
    texel_of,
    truth_bytes,
    write_truth,
)

RGL = Path("/work/shared/data/rgl")
BASE = {"albedo": [0.5, 0.4, 0.3], "ks": 0.2, "alpha": 0.3}


def scene_dict(sample=None, resolution=(80, 60), **render_opts):
    render_opts.setdefault("tolerance", 1e-6)
    """A 0.4 m sample seen obliquely (a highlight on it), a disk light off to +x."""
    s = sample or dict(brdf=dict(model="lambert+ggx", params=dict(BASE)))
    return dict(
        sample=dict(width=0.4, height=0.4, **s),
        lights=[
            dict(
                type="disk",
                position=[0.1, 0.0, 0.5],
                look_at=[0, 0, 0],
                radius=0.01,
                radiance=[1.0, 2.0, 3.0],
            )
        ],
        camera=dict(
            resolution=list(resolution),
            fov_deg=40,
            position=[-0.1, 0.0, 0.6],
            look_at=[0, 0, 0],
            up=[0, 1, 0],
        ),
        render=render_opts,
    )


def mapped(maps, params=None, model="lambert+ggx"):
    return dict(brdf=dict(model=model, params=dict(params or BASE)), maps=maps)


# -- uniform map == no map ------------------------------------------------------------


@pytest.fixture(scope="module", params=["numba", "numpy"])
def uniform_pair(request):
    """Renders (with diffuse) without maps and with maps of the same constant values, on
    the numba path (80 x 60: the batches reach the kernels) and on numpy's."""
    mp = pytest.MonkeyPatch()
    if request.param == "numpy":
        mp.setenv("GONIO_NUMBA", "0")
    try:
        plain = render(parse_scene(scene_dict(strategy="quadrature")), diffuse=True)
        maps = {
            "albedo": [[BASE["albedo"]] * 3] * 2,  # a (2, 3, 3) RGB map
            "ks": [[0.2] * 5] * 4,
            "alpha": [[0.3]],
        }
        scene = parse_scene(scene_dict(mapped(maps), strategy="quadrature"))
        mapped_res = render(scene, diffuse=True)
    finally:
        mp.undo()
    return plain, mapped_res


def test_a_uniform_map_renders_what_no_map_renders(uniform_pair):
    plain, res = uniform_pair
    assert (res.region == 1).sum() > 1000
    np.testing.assert_allclose(res.radiance, plain.radiance, rtol=1e-12, atol=0)
    np.testing.assert_allclose(res.diffuse, plain.diffuse, rtol=1e-12, atol=0)
    assert res.stats.lights[0].nodes == plain.stats.lights[0].nodes


# -- a two-texel map ------------------------------------------------------------------


@pytest.mark.slow  # two whole-model albedo tables for the references: ~3-5 s
def test_each_half_of_a_two_texel_map_renders_as_its_own_parameters():
    left = {"albedo": [0.2, 0.3, 0.4], "ks": 0.05, "alpha": 0.1}
    right = {"albedo": [0.6, 0.5, 0.4], "ks": 0.4, "alpha": 0.5}
    maps = {
        "albedo": [[left["albedo"], right["albedo"]]],
        "ks": [[left["ks"], right["ks"]]],
        "alpha": [[left["alpha"], right["alpha"]]],
    }
    # antialias 1: every pixel is its centre's point, which lies in one half; a fixed
    # rule (auto would choose the level on each scene's own pilot pixels)
    opts = dict(antialias=1, strategy="quadrature")
    res = render(parse_scene(scene_dict(mapped(maps), **opts)), diffuse=True)
    refs = {
        side: render(
            parse_scene(scene_dict(dict(brdf=dict(model="lambert+ggx", params=p)), **opts)),
            diffuse=True,
        )
        for side, p in (("left", left), ("right", right))
    }
    x = res.points[..., 0]
    on = res.region == 1
    for side, half in (("left", on & (x < 0)), ("right", on & (x > 0))):
        assert half.sum() > 500
        np.testing.assert_allclose(res.radiance[half], refs[side].radiance[half], rtol=1e-12)
        # the diffuse response: per-lobe tables scaled by the weights' maps against the
        # texel's whole-model albedo table (the same up to rounding)
        np.testing.assert_allclose(res.diffuse[half], refs[side].diffuse[half], rtol=1e-12)
    # the halves differ: the map was used
    assert not np.allclose(refs["left"].radiance[on], refs["right"].radiance[on])


def parallel_disk_irradiance(p, height, radius, radiance):
    """Irradiance under a disk parallel to the receiver plane, centred above the origin."""
    rho2 = p[..., 0] ** 2 + p[..., 1] ** 2
    h2, r2 = height**2, radius**2
    return (
        math.pi
        * radiance
        / 2
        * (1 - (h2 + rho2 - r2) / np.sqrt((h2 + rho2 + r2) ** 2 - 4 * r2 * rho2))
    )


def test_a_lambertian_two_texel_map_against_the_closed_form():
    d = scene_dict(
        mapped({"albedo": [[0.2, 0.8]]}, {"albedo": 0.5}, "lambert"),
        (40, 40),
        antialias=1,
        tolerance=1e-8,
    )
    d["lights"][0].update(position=[0, 0, 0.5], normal=[0, 0, -1], look_at=None)
    d["camera"].update(position=[0, 0, 0.6])
    res = render(parse_scene(d))
    on = res.region == 1
    x = res.points[..., 0]
    E = parallel_disk_irradiance(res.points, 0.5, 0.01, 1.0)
    albedo = np.where(x < 0, 0.2, 0.8)
    rel = res.radiance[..., 0][on] / (albedo / np.pi * E)[on] - 1
    assert on.sum() > 1000 and np.max(np.abs(rel)) < 1e-6


# -- a mix of measured materials ------------------------------------------------------


@pytest.mark.skipif(not RGL.is_dir(), reason="shared RGL files not present")
def test_a_mix_of_two_rgl_files_by_mask(tmp_path):
    files = [str(RGL / "paper_white_rgb.bsdf"), str(RGL / "vch_golden_yellow_rgb.bsdf")]
    mix = {"mask": [[0, 1], [1, 0]], "materials": [{"file": f} for f in files]}
    scene = parse_scene(scene_dict(dict(mix=mix), (48, 36), antialias=1, strategy="point"))
    brdf = scene.build_brdf()
    res = render(scene, brdf=brdf)
    refs = [
        render(
            parse_scene(
                scene_dict(dict(brdf=dict(file=f)), (48, 36), antialias=1, strategy="point")
            )
        )
        for f in files
    ]
    x, y = res.points[..., 0], res.points[..., 1]
    on = res.region == 1
    # row 0 at +y, column 0 at -x: label 0 at (+y, -x) and (-y, +x)
    zero = on & ((x < 0) == (y > 0))
    one = on & ((x < 0) != (y > 0))
    assert zero.sum() > 100 and one.sum() > 100
    np.testing.assert_allclose(res.radiance[zero], refs[0].radiance[zero], rtol=1e-12)
    np.testing.assert_allclose(res.radiance[one], refs[1].radiance[one], rtol=1e-12)
    # the truth of a mix: labels and the materials' files
    t = read_truth(write_truth(tmp_path / "truth" / "svbrdf.h5", scene))
    assert t.model == "mix" and t.texels == (2, 2) and t.params == {}
    np.testing.assert_array_equal(t.labels, [[0, 1], [1, 0]])
    assert [m["file"] for m in t.materials] == [Path(f).name for f in files]


# -- orientation and the truth file ---------------------------------------------------


@pytest.fixture(scope="module")
def corner_scene():
    """A 4 x 4 albedo map, 0.3 everywhere but 0.9 in texel (row 0, column 3): +y, +x."""
    m = np.full((4, 4), 0.3)
    m[0, 3] = 0.9
    alpha = [[0.1, 0.2], [0.3, 0.4]]  # a coarser map beside it
    return parse_scene(
        scene_dict(mapped({"albedo": m.tolist(), "alpha": alpha}), (40, 40), antialias=1)
    )


def test_a_distinct_corner_texel_appears_in_that_corner_of_the_render(corner_scene, tmp_path):
    import h5py

    from gonio.simulator.render import save_truth

    res = render(corner_scene)
    plain = render(
        parse_scene(
            scene_dict(
                mapped({"alpha": [[0.1, 0.2], [0.3, 0.4]]}, {**BASE, "albedo": 0.3}),
                (40, 40),
                antialias=1,
            )
        )
    )
    x, y = res.points[..., 0], res.points[..., 1]
    on = res.region == 1
    corner = on & (x > 0.1) & (y > 0.1)
    elsewhere = on & ((x < 0.1) | (y < 0.1))
    assert corner.sum() > 20
    np.testing.assert_allclose(res.radiance[elsewhere], plain.radiance[elsewhere], rtol=1e-12)
    assert np.all(res.radiance[corner] > plain.radiance[corner] * 1.2)
    # the render's truth names each pixel's texel: texel 3 (row 0, column 3) is the corner
    save_truth(tmp_path / "t.h5", res, corner_scene)
    with h5py.File(tmp_path / "t.h5") as f:
        texel = f["texel"][:]
        assert list(f["texel"].attrs["texels"]) == [4, 4]
    np.testing.assert_array_equal(texel == 3, corner)
    assert np.all(texel[~on] == -1) and set(np.unique(texel[on])) == set(range(16))


def test_the_truth_file_round_trips_with_the_scene_orientation(corner_scene, tmp_path):
    path = write_truth(tmp_path / "svbrdf.h5", corner_scene)
    t = read_truth(path)
    assert t.model == "lambert+ggx" and t.texels == (4, 4) and t.sample_size == (0.4, 0.4)
    a = t.params["albedo"]
    assert a.shape == (4, 4, 3) and a[0, 3, 0] == 0.9
    assert np.count_nonzero(a[..., 0] == 0.9) == 1 and np.all(a[a != 0.9] == 0.3)
    # the 2 x 2 alpha map resampled (nearest) to the 4 x 4 grid; ks constant
    np.testing.assert_array_equal(t.params["alpha"][::2, ::2, 1], [[0.1, 0.2], [0.3, 0.4]])
    np.testing.assert_array_equal(t.params["alpha"][1::2, 1::2, 1], [[0.1, 0.2], [0.3, 0.4]])
    assert np.all(t.params["ks"] == 0.2)
    import h5py

    with h5py.File(path) as f:
        assert f.attrs["schema"] == "gonio.svbrdf_truth" and f.attrs["schema_version"] == 1
        assert f.attrs["orientation"] == ORIENTATION
        assert list(f.attrs["channels"]) == ["R", "G", "B"]
    # the same bytes each time (no time stamps): a resumed session's would match
    assert truth_bytes(corner_scene) == path.read_bytes()
    # finer grids repeat, coarser ones average (and say where that is exact)
    fine = t.params_at(8, 8)["albedo"]
    assert np.all(fine[:2, 6:, 0] == 0.9) and np.count_nonzero(fine[..., 0] == 0.9) == 4
    coarse = t.params_at(2, 2)["albedo"][..., 0]
    np.testing.assert_allclose(coarse, [[0.3, 0.45], [0.3, 0.3]], rtol=1e-15)
    # the 2 x 2 alpha map is uniform over each block: only the 0.9 texel's block is mixed
    np.testing.assert_array_equal(t.uniform_at(2, 2), [[True, False], [True, True]])
    with pytest.raises(ValueError, match="does not nest"):
        t.params_at(3, 4)


def test_texel_centres_map_to_their_own_texel():
    w, h, ny, nx = 0.3, 0.2, 3, 5
    col, row = np.meshgrid(np.arange(nx), np.arange(ny))
    x = -w / 2 + (col + 0.5) * w / nx
    y = h / 2 - (row + 0.5) * h / ny
    r, c = texel_of(x, y, (w, h), (ny, nx))
    np.testing.assert_array_equal(r, row)
    np.testing.assert_array_equal(c, col)
    # the rim belongs to the outermost texels
    r, c = texel_of(np.array([-w / 2, w / 2]), np.array([h / 2, -h / 2]), (w, h), (ny, nx))
    assert r.tolist() == [0, ny - 1] and c.tolist() == [0, nx - 1]


def test_a_truth_file_of_another_kind_is_refused(tmp_path):
    import h5py

    with h5py.File(tmp_path / "x.h5", "w") as f:
        f.attrs["schema"] = "gonio.samples"
    with pytest.raises(FileFormatError, match="schema"):
        read_truth(tmp_path / "x.h5")
    with pytest.raises(FileFormatError, match="does not exist"):
        read_truth(tmp_path / "nope.h5")


def test_maps_from_files_npy_and_16_bit_png_with_a_range(tmp_path):
    import cv2

    np.save(tmp_path / "ks.npy", np.array([[0.1, 0.2]]))
    img = np.array([[0, 65535]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "alpha.png"), img)
    maps = {"ks": "ks.npy", "alpha": {"file": "alpha.png", "range": [0.1, 0.5]}}
    scene = parse_scene(scene_dict(mapped(maps)), base_dir=tmp_path)
    b = scene.build_brdf()
    assert isinstance(b, SpatialBRDF)
    t = read_truth(write_truth(tmp_path / "t.h5", scene))
    np.testing.assert_allclose(t.params["ks"][0, :, 2], [0.1, 0.2], rtol=1e-15)
    np.testing.assert_allclose(t.params["alpha"][0, :, 0], [0.1, 0.5], rtol=1e-15)


# -- bad input ------------------------------------------------------------------------


def _bad(maps=None, mix=None, **sample):
    s = {"brdf": dict(model="lambert+ggx", params=dict(BASE)), **sample}
    if maps is not None:
        s["maps"] = maps
    if mix is not None:
        s["mix"] = mix
    return scene_dict(s)


MIX = {"mask": [[0, 1]], "materials": [{"model": "lambert"}, {"model": "lambert"}]}


@pytest.mark.parametrize(
    "doc, expect",
    [
        (_bad({"alpha": [[0.1, 0.2], [0.3]]}), ["sample.maps.alpha", "inline", "rectangular"]),
        (_bad({"alpha": [[[0.1, 0.2]]]}), ["sample.maps.alpha", "shape (1, 1, 2)", "(ny, nx, 3)"]),
        (_bad({"ks": [[0.1, float("nan")]]}), ["sample.maps.ks", "nan", "row 0, column 1"]),
        (_bad({"ks": [[0.1], [1.5]]}), ["sample.maps.ks", "1.5", "row 1, column 0", "[0, 1]"]),
        (_bad({"alpha": [[0.0]]}), ["sample.maps.alpha", "outside the bounds"]),
        (_bad({"roughness": [[0.1]]}), ["sample.maps.roughness", "no parameter", "alpha"]),
        (_bad({"ks": "nope.npy"}), ["sample.maps.ks", "nope.npy", "does not exist"]),
        (_bad(mix={**MIX, "mask": [[0, 2]]}), ["sample.mix.mask", "label 2", "has 2"]),
        (_bad(mix={**MIX, "mask": [[0, -1]]}), ["sample.mix.mask", "-1", "integer labels"]),
        (_bad({"ks": [[0.1]]}, MIX), ["maps", "mix", "not both"]),
        (_bad({"ks": [[0.1]]}, albedo_map="a.npy"), ["albedo_map", "does not combine"]),
        (_bad({}), ["maps", "empty"]),
        (
            _bad(mix={**MIX, "materials": [{"model": "lambert", "params": {"albedo": 2.0}}] * 2}),
            ["sample.mix.materials[0]", "albedo", "2"],
        ),
        (
            _bad(mix={**MIX, "materials": [{"model": "lambert"}, {"file": "nope.bsdf"}]}),
            ["sample.mix.materials[1].file", "nope.bsdf", "does not exist"],
        ),
        (
            _bad({"ks": [[0.1]]}, brdf=dict(model="lambert+ggx", params={"alpha": 5.0})),
            ["sample.brdf.params", "alpha"],
        ),
    ],
    ids=[
        "ragged",
        "channels",
        "nan",
        "bounds",
        "alpha-zero",
        "unknown-name",
        "missing-file",
        "label-without-material",
        "negative-label",
        "maps-and-mix",
        "albedo-map",
        "empty",
        "material-params",
        "material-file",
        "base-params",
    ],
)
def test_bad_maps_are_refused_naming_field_and_value(doc, expect, tmp_path):
    with pytest.raises(ConfigError) as info:
        parse_scene(doc, "scene.toml", tmp_path)
    msg = str(info.value)
    assert "scene.toml" in msg
    for e in expect:
        assert e in msg, (e, msg)


def test_maps_on_a_measured_file_and_a_pickled_map_are_refused(tmp_path):
    d = scene_dict(dict(brdf=dict(file="x.bsdf"), maps={"ks": [[0.1]]}))
    with pytest.raises(ConfigError, match="use 'mix' for measured"):
        parse_scene(d, "scene.toml", tmp_path)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ConfigError, match=r"sample.maps.ks .*obj.npy.*Python objects"):
        parse_scene(_bad({"ks": "obj.npy"}), "scene.toml", tmp_path)


def test_gonio_sim_render_names_the_bad_map_and_exits_1(tmp_path):
    repo = Path(__file__).resolve().parents[2]
    text = (repo / "examples" / "svbrdf_scene.toml").read_text()
    bad = text.replace("[0.05, 0.15, 0.30, 0.45],\n  [0.05", "[0.05, 0.15, 0.30, 7.0],\n  [0.05", 1)
    assert bad != text
    (tmp_path / "bad.toml").write_text(bad)
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "gonio",
            "sim",
            "render",
            str(tmp_path / "bad.toml"),
            "--out",
            str(tmp_path / "a.dng"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 1, p.stderr
    assert "bad.toml" in p.stderr and "sample.maps.ks" in p.stderr and "7" in p.stderr
    assert "Traceback" not in p.stderr and not (tmp_path / "a.dng").exists()


# -- the session's copies -------------------------------------------------------------


def test_map_and_mask_files_are_copied_into_the_session(tmp_path):
    from gonio.app.simulation import SceneSource, relocatable

    np.save(tmp_path / "ks.npy", np.array([[0.1, 0.2]]))
    (tmp_path / "alpha.png").write_bytes(b"png")
    doc = scene_dict(mapped({"ks": "ks.npy", "alpha": {"file": "alpha.png"}, "albedo": [[0.5]]}))
    out, files = relocatable(SceneSource(doc, tmp_path))
    assert out["sample"]["maps"] == {
        "ks": "sim/ks.npy",
        "alpha": {"file": "sim/alpha.png"},
        "albedo": [[0.5]],
    }
    assert files == {"sim/ks.npy": tmp_path / "ks.npy", "sim/alpha.png": tmp_path / "alpha.png"}
    np.save(tmp_path / "mask.npy", np.array([[0, 1]]))
    mix = scene_dict(dict(mix={"mask": "mask.npy", "materials": [{"file": "a.bsdf"}]}))
    (tmp_path / "a.bsdf").write_bytes(b"x")
    out, files = relocatable(SceneSource(mix, tmp_path))
    assert out["sample"]["mix"] == {"mask": "sim/mask.npy", "materials": [{"file": "sim/a.bsdf"}]}
    assert json.dumps(out).count(str(tmp_path)) == 0


def test_a_label_image_mask_and_the_calibration_targets(tmp_path):
    import cv2

    from gonio.brdf.base import BoundModel

    # an 8-bit label image stores the labels themselves
    cv2.imwrite(str(tmp_path / "mask.png"), np.array([[1, 0, 1]], dtype=np.uint8))
    mats = [{"model": "lambert", "params": {"albedo": a}} for a in (0.2, 0.7)]
    scene = parse_scene(
        scene_dict(dict(mix={"mask": "mask.png", "materials": mats})), "s", tmp_path
    )
    t = read_truth(write_truth(tmp_path / "t.h5", scene))
    np.testing.assert_array_equal(t.labels, [[1, 0, 1]])
    # one analytic model for every material: its parameters are in the truth too
    np.testing.assert_array_equal(t.params["albedo"][0, :, 1], [0.7, 0.2, 0.7])
    # the reference target and the mirror replace the whole sample, maps and mix included
    ref = scene.with_reference_target(0.99)
    assert not ref.sample.spatially_varying and isinstance(ref.build_brdf(), BoundModel)
    assert not scene.with_mirror_target(0.9).sample.spatially_varying

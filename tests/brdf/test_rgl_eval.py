"""RGL evaluator against Mitsuba 3's ``measured`` plugin (the independent oracle) and data checks.

Mitsuba's ``eval`` returns ``f_r cos(theta_o)`` computed in float32; directions are
rounded to float32 before both evaluate them so that only the arithmetic differs.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from gonio.brdf.rgl import read_rgl
from gonio.brdf.tensor_file import read_tensor_file, write_tensor_file
from gonio.errors import FileFormatError

MATERIALS = ["paper_white", "colodur_napoli_4f", "vch_golden_yellow", "cc_ibiza_sunset"]


def _uniform_hemisphere(rng: np.random.Generator, n: int) -> np.ndarray:
    z = rng.random(n)
    r = np.sqrt(1 - z * z)
    p = 2 * np.pi * rng.random(n)
    return np.stack([r * np.cos(p), r * np.sin(p), z], axis=-1)


def _test_pairs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Half uniform pairs, half near the mirror direction (where glossy lobes are)."""
    wi = _uniform_hemisphere(rng, n)
    wo = _uniform_hemisphere(rng, n)
    k = n // 2
    near = wi[:k] * [-1, -1, 1] + rng.normal(scale=0.08, size=(k, 3))
    near[:, 2] = np.abs(near[:, 2]) + 1e-3
    wo[:k] = near / np.linalg.norm(near, axis=1, keepdims=True)
    # float32-rounded: the oracle sees exactly the same directions
    return wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)


@pytest.fixture(scope="module")
def mi(tmp_path_factory):
    os.environ.setdefault("DRJIT_CACHE_DIR", str(tmp_path_factory.mktemp("drjit")))
    from gonio.mitsuba_oracle import MitsubaUnavailableError, load_mitsuba

    try:
        mi, _ = load_mitsuba("scalar")
    except MitsubaUnavailableError as exc:
        pytest.skip(str(exc))
    import drjit as dr

    dr.set_thread_count(1)
    return mi


def _mitsuba_eval(mi, path, wi, wo) -> np.ndarray:
    mi.set_variant("scalar_rgb")
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    out = np.empty((wi.shape[0], 3))
    for j in range(wi.shape[0]):
        si.wi = mi.Vector3f(*wi[j])
        out[j] = list(bsdf.eval(ctx, si, mi.Vector3f(*wo[j])))
    return out


def _relative_differences(mine_fcos, ref):
    sel = ref > 1e-3 * ref.max()
    return np.abs(mine_fcos - ref)[sel] / ref[sel]


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("name", MATERIALS)
def test_matches_mitsuba_measured(mi, rgl_file, name):
    path = rgl_file(name)
    rng = np.random.default_rng(20181204)
    wi, wo = _test_pairs(rng, 10_000)
    ref = _mitsuba_eval(mi, path, wi, wo)
    mine = read_rgl(path).eval(wi, wo) * wo[:, 2:3]
    rel = _relative_differences(mine, ref)
    med, p99, mx = np.median(rel), np.percentile(rel, 99), rel.max()
    print(f"{name}: n={rel.size} median {med:.2e} p99 {p99:.2e} max {mx:.2e}")
    assert rel.size > 10_000  # a third or more of the 30,000 channel values are significant
    assert med <= 1e-4
    assert p99 <= 1e-3


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize(
    "reduction,lo,hi", [(1, -np.pi, np.pi), (2, -np.pi, 0.0), (4, -np.pi, -np.pi / 2)]
)
def test_anisotropic_paths_match_mitsuba(mi, rgl_file, tmp_path, reduction, lo, hi):
    # No anisotropic file is shared, so build one: five phi_i slices whose RGB tables are
    # scaled differently, so phi_i interpolation and the mirror reduction both matter.
    f = dict(read_tensor_file(rgl_file("vch_golden_yellow")))
    phis = np.linspace(lo, hi, 5).astype(np.float32)
    scale = (1 + 0.5 * np.cos(phis) + 0.2 * np.sin(phis)).astype(np.float32)
    f["phi_i"] = phis
    f["vndf"] = np.repeat(f["vndf"], 5, axis=0)
    f["luminance"] = np.repeat(f["luminance"], 5, axis=0)
    f["rgb"] = (np.repeat(f["rgb"], 5, axis=0) * scale[:, None, None, None, None]).astype(
        np.float32
    )
    path = tmp_path / "aniso.bsdf"
    write_tensor_file(path, f)
    b = read_rgl(path)
    assert not b.isotropic and b.reduction == reduction
    wi, wo = _test_pairs(np.random.default_rng(reduction), 3000)
    rel = _relative_differences(b.eval(wi, wo) * wo[:, 2:3], _mitsuba_eval(mi, path, wi, wo))
    assert np.median(rel) <= 1e-4
    assert np.percentile(rel, 99) <= 1e-3


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("name", ["paper_white", "vch_golden_yellow"])
def test_albedo_matches_mitsuba_importance_sampling(mi, rgl_file, name):
    # Mitsuba's sample() weights are f cos / pdf: their mean is an unbiased estimate of the
    # directional albedo, obtained by a different method (its own luminance + VNDF warps).
    path = rgl_file(name)
    mi.set_variant("scalar_rgb")
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    rng = np.random.default_rng(7)
    thetas = np.radians([10.0, 45.0, 75.0])
    mine = read_rgl(path).albedo(thetas)
    n = 20_000
    for t, a in zip(thetas, mine, strict=True):
        si.wi = mi.Vector3f(np.sin(t), 0.0, np.cos(t))
        u = rng.random((n, 3))
        w = np.array(
            [list(bsdf.sample(ctx, si, u[j, 0], mi.Point2f(u[j, 1], u[j, 2]))[1]) for j in range(n)]
        )
        mean, sem = w.mean(0), w.std(0) / np.sqrt(n)
        # 4 standard errors of the estimate + 2e-3 relative for the quadrature (its
        # change from 96x96 to 256x256 nodes is below 1e-3 on these files)
        assert np.all(np.abs(a - mean) <= 4 * sem + 2e-3 * a), (np.degrees(t), a, mean, sem)


def test_readme_sanity_figure(rgl_file):
    # Data README: Mitsuba gives f cos = (0.2450, 0.2479, 0.2875) for paper_white at
    # theta_i = theta_o = 30 deg, mirror configuration.  The exact mirror direction sits on
    # the pole of the half-vector parameterisation, where the tabulated value depends
    # slightly on phi (Mitsuba itself gives 0.2438..0.2449 for phi_i = 0..90 deg), hence
    # 1 % here; the oracle test above checks agreement to 1e-4.
    b = read_rgl(rgl_file("paper_white"))
    t = np.radians(30.0)
    for phi in (0.0, np.pi / 2):
        wi = np.array([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)])
        wo = wi * [-1, -1, 1]
        np.testing.assert_allclose(b.eval(wi, wo) * np.cos(t), [0.2450, 0.2479, 0.2875], rtol=1e-2)


@pytest.mark.parametrize("name", MATERIALS)
def test_albedo_at_most_one(rgl_file, name):
    a = read_rgl(rgl_file(name)).albedo(np.radians(np.arange(0.0, 86.0, 5.0)))
    assert a.shape == (18, 3)
    assert np.all(a > 0)
    assert np.all(a <= 1.0), a.max()


# Reciprocity of the measured data, f(wi, wo) vs f(wo, wi), relative to their mean, over
# pairs with both elevations <= 80 deg and f above 1 % of the maximum.  Measured by this
# test (seed 0, 2 x 10^4 pairs before the cut): median 1.8 % (paper), 3.5 % (wall
# paint), 9.7 % (golden yellow film), 12.7 % (ibiza sunset film); 90th percentiles 6.3 %,
# 11.8 %, 25.6 %, 35.4 %.  The data are only approximately reciprocal (each theta_i slice
# is measured and parameterised separately).  The bounds below are those medians with
# ~25 % margin: they document the level and catch an evaluator change that makes the
# data markedly less reciprocal (e.g. interpolating theta_i wrongly), nothing finer.
RECIPROCITY_MEDIAN = {
    "paper_white": 0.022,
    "colodur_napoli_4f": 0.043,
    "vch_golden_yellow": 0.12,
    "cc_ibiza_sunset": 0.16,
}


@pytest.mark.parametrize("name", MATERIALS)
def test_reciprocity_level_of_the_data(rgl_file, name):
    b = read_rgl(rgl_file(name))
    rng = np.random.default_rng(0)
    wi = _uniform_hemisphere(rng, 20_000)
    wo = _uniform_hemisphere(rng, 20_000)
    keep = (wi[:, 2] > np.cos(np.radians(80))) & (wo[:, 2] > np.cos(np.radians(80)))
    a, c = b.eval(wi[keep], wo[keep]), b.eval(wo[keep], wi[keep])
    sel = np.maximum(a, c) > 1e-2 * a.max()
    asym = (np.abs(a - c) / (0.5 * (a + c)))[sel]
    print(f"{name}: reciprocity median {np.median(asym):.3f} p90 {np.percentile(asym, 90):.3f}")
    assert np.median(asym) <= RECIPROCITY_MEDIAN[name]


def test_horizon_nan_and_broadcasting(rgl_file):
    b = read_rgl(rgl_file("paper_white"))
    wi = np.array([[0.0, 0.6, 0.8], [0.0, 0.6, -0.8], [np.nan, 0.0, 1.0]])
    wo = np.array([0.6, 0.0, 0.8])
    f = b.eval(wi, wo)
    assert f.shape == (3, 3)
    assert np.all(f[0] > 0) and np.all(f[1] == 0) and np.all(np.isnan(f[2]))
    grid = b.eval(wi[:1, None, :], np.broadcast_to(wo, (4, 3))[None])
    assert grid.shape == (1, 4, 3)
    np.testing.assert_allclose(grid[0, 0], f[0])
    assert b.eval(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0])).shape == (3,)


def test_spectral_file_is_read_but_not_evaluated_to_rgb(rgl_file, tmp_path):
    # A spectral variant built from the RGB file: channels R, G, B, G at four wavelengths.
    f = dict(read_tensor_file(rgl_file("cc_ibiza_sunset")))
    rgb = f.pop("rgb")
    f["wavelengths"] = np.array([450.0, 550.0, 650.0, 700.0], dtype=np.float32)
    f["spectra"] = np.ascontiguousarray(rgb[:, :, [0, 1, 2, 1]])
    path = tmp_path / "spec.bsdf"
    write_tensor_file(path, f)
    b = read_rgl(path)
    assert b.metadata["spectral"] and b.metadata["wavelengths_nm"] == [450.0, 550.0, 650.0, 700.0]
    wi, wo = _test_pairs(np.random.default_rng(3), 500)
    with pytest.raises(FileFormatError, match="spectral RGL file: RGB evaluation is not supported"):
        b.eval(wi, wo)
    ref = read_rgl(rgl_file("cc_ibiza_sunset")).eval(wi, wo)
    np.testing.assert_array_equal(b.eval_channels(wi, wo), ref[:, [0, 1, 2, 1]])


def test_spectral_file_without_spectra_field(rgl_file, tmp_path):
    f = dict(read_tensor_file(rgl_file("paper_white")))
    f["wavelengths"] = np.array([500.0], dtype=np.float32)
    path = tmp_path / "half_spectral.bsdf"
    write_tensor_file(path, f)
    with pytest.raises(FileFormatError, match="expected a 'spectra' field"):
        read_rgl(path)

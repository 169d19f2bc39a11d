"""MERL binary format: indexing by hand, byte layout, round trip, resampling accuracy."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from gonio.brdf.measured import load
from gonio.brdf.merl import (
    DIMS,
    FILE_SIZE,
    MERLBRDF,
    SCALES,
    bin_angles,
    indices_reference,
    read_merl,
    resample,
    write_merl,
)
from gonio.errors import FileFormatError
from gonio.radiometry.frames import directions_from_half_diff, half_diff_from_directions

DEG = np.pi / 180


def test_constants_from_the_format_definition():
    assert DIMS == (90, 90, 180)
    np.testing.assert_array_equal(SCALES, [1 / 1500, 1.15 / 1500, 1.66 / 1500])
    assert FILE_SIZE == 34_992_012  # size of every file of the MERL database


# theta_h index = int(sqrt(theta_h_deg * 90)); theta_d index = int(theta_d_deg);
# phi_d index = int(phi_d_deg) after adding 180 deg to negative phi_d; all clamped.
HAND = [
    # theta_h deg, theta_d deg, phi_d deg, (ih, id, ip)
    (0.0, 0.0, 0.0, (0, 0, 0)),
    (1.0, 0.5, 10.5, (9, 0, 10)),  # sqrt(90) = 9.49
    (45.0, 30.5, -10.5, (63, 30, 169)),  # sqrt(4050) = 63.6; -10.5 + 180 = 169.5
    (10.05, 45.2, 179.5, (30, 45, 179)),  # sqrt(904.5) = 30.07
    (89.9, 89.99, 90.2, (89, 89, 90)),  # sqrt(8091) = 89.95
    (90.0, 90.0, 180.0, (89, 89, 179)),  # upper edges clamp
    (0.04, 3.0, -179.5, (1, 3, 0)),  # sqrt(3.6) = 1.9 -> 1; -179.5 + 180 = 0.5
]


@pytest.mark.parametrize("th,td,pd,expected", HAND)
def test_reference_indices_by_hand(th, td, pd, expected):
    got = indices_reference(th * DEG, td * DEG, pd * DEG)
    assert tuple(int(g) for g in got) == expected


def test_node_angles_by_hand():
    th, td, pd = bin_angles()
    assert th[30] == pytest.approx(10 * DEG)  # (30/90)^2 * 90 deg = 10 deg
    assert th[45] == pytest.approx(22.5 * DEG)
    assert td[17] == pytest.approx(17 * DEG) and pd[123] == pytest.approx(123 * DEG)
    # every node maps back to its own index under the reference rule (within roundoff
    # guard: nudge up by 1e-9 since int() truncates)
    ih, _, _ = indices_reference(th + 1e-9, 0.0, 0.0)
    np.testing.assert_array_equal(ih, np.arange(90))


def _coded_table() -> np.ndarray:
    # A distinct value per entry: channel*1e7 + theta_h*1e5 + theta_d*1e3 + phi_d
    c, i, j, k = np.meshgrid(*(np.arange(n) for n in (3, *DIMS)), indexing="ij")
    return (c * 1e7 + i * 1e5 + j * 1e3 + k).astype(np.float64)


@pytest.fixture(scope="module")
def coded_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("merl") / "coded.binary"
    write_merl(p, MERLBRDF(_coded_table()))
    return p


def test_byte_layout_by_hand(coded_file):
    raw = coded_file.read_bytes()
    assert len(raw) == FILE_SIZE
    assert raw[:12] == struct.pack("<3i", 90, 90, 180)
    n = 90 * 90 * 180
    for c, i, j, k in [(0, 0, 0, 0), (1, 2, 3, 4), (2, 89, 89, 179), (0, 63, 30, 169)]:
        off = 12 + 8 * (c * n + (i * 90 + j) * 180 + k)
        assert struct.unpack_from("<d", raw, off)[0] == c * 1e7 + i * 1e5 + j * 1e3 + k


@pytest.mark.parametrize("th,td,pd,expected", [h for h in HAND if h[0] + h[1] < 80])
def test_nearest_lookup_reads_the_hand_derived_entry(coded_file, th, td, pd, expected):
    b = read_merl(coded_file)
    ih, idd, ip = expected
    for phi_h in (0.0, 1.0, -2.5):  # isotropy: the half-vector azimuth must not matter
        wi, wo = directions_from_half_diff(th * DEG, phi_h, td * DEG, pd * DEG)
        f = b.eval(wi, wo, interpolation="nearest")
        codes = np.array([c * 1e7 + ih * 1e5 + idd * 1e3 + ip for c in range(3)])
        np.testing.assert_allclose(f, codes * SCALES, rtol=1e-12)


def test_write_read_round_trip_is_byte_exact(tmp_path):
    rng = np.random.default_rng(5)
    raw = rng.random((3, *DIMS)) * 3000
    raw[rng.random(raw.shape) < 0.1] = -1.0  # missing entries survive as stored
    a = tmp_path / "a.binary"
    b = tmp_path / "b.binary"
    # written independently of write_merl: header + float64, as the format defines
    a.write_bytes(struct.pack("<3i", *DIMS) + raw.astype("<f8").tobytes())
    m = load(a)
    assert m.format == "merl" and m.description == "a"
    np.testing.assert_array_equal(m.raw, raw)
    m.write(b)
    assert b.read_bytes() == a.read_bytes()


# ----------------------------------------------------------- resampling a known lobe
# A reciprocal, isotropic test BRDF in product form f = A(theta_h) B(theta_d) C(phi_d)
# (per channel factor), with derivatives known in closed form.  For trilinear
# interpolation I = I_h I_d I_p in MERL index coordinates (unit spacing),
#   |f - I f| <= e_A max|B| max|C| + max|A| e_B max|C| + max|A| max|B| e_C,
# with e_X = max|X''| / 8 over the cell (1-D linear interpolation error) and max|.| over
# the cell (|I_X X| never exceeds the node values).  The maxima are taken on 257 points
# per cell edge of these smooth functions.
S = 0.1  # rad, width of the specular factor
CH = np.array([1.0, 0.5, 0.25])
K_H = (np.pi / 2) / 90**2  # theta_h = K_H u^2
K_D = (np.pi / 2) / 90  # theta_d = K_D v
K_P = np.pi / 180  # phi_d = K_P w


def _A(u):
    t = K_H * u**2
    e = np.exp(-((t / S) ** 2))
    dt, d2t = 2 * K_H * u, 2 * K_H
    a1 = -2 * t / S**2 * e
    a2 = (4 * t**2 / S**4 - 2 / S**2) * e
    return 0.2 + e, a2 * dt**2 + a1 * d2t


def _B(v):
    t = K_D * v
    c, s = np.cos(t), np.sin(t)
    b2 = 80 * (1 - c) ** 3 * s**2 + 20 * (1 - c) ** 4 * c
    return 1 + 4 * (1 - c) ** 5, b2 * K_D**2


def _C(w):
    p = K_P * w
    return 1 + 0.3 * np.cos(2 * p), -1.2 * np.cos(2 * p) * K_P**2


class ProductLobe:
    description = "product test lobe"

    def eval(self, wi, wo):
        th, _, td, pd = half_diff_from_directions(wi, wo)
        f = (
            _A(90 * np.sqrt(th / (np.pi / 2)))[0]
            * _B(td / K_D)[0]
            * _C(np.mod(pd, np.pi) / K_P)[0]
            / np.pi
        )
        f = np.where((wi[..., 2] > 0) & (wo[..., 2] > 0), f, 0.0)
        return f[..., None] * CH


@pytest.fixture(scope="module")
def resampled():
    return resample(ProductLobe())


def _cell_bound(lo, fn):
    t = lo[:, None] + np.linspace(0, 1, 257)[None, :]
    v, d2 = fn(t)
    return np.abs(v).max(1), np.abs(d2).max(1) / 8


def test_resampled_table_at_nodes_equals_the_model(resampled):
    rng = np.random.default_rng(1)
    th, td, pd = bin_angles()
    # theta_h index 0 is left out because sqrt(theta_h) turns the ~1e-16 roundoff of the
    # direction round trip into an index offset of ~1e-6; theta_d index 0 because there
    # wi = wo and phi_d is undefined (the product lobe, unlike a BRDF, depends on it)
    i, j, k = rng.integers(1, 60, 2000), rng.integers(1, 60, 2000), rng.integers(0, 180, 2000)
    wi, wo = directions_from_half_diff(th[i], rng.uniform(-np.pi, np.pi, 2000), td[j], pd[k])
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(
        resampled.eval(wi[ok], wo[ok]), ProductLobe().eval(wi[ok], wo[ok]), rtol=1e-9
    )


def _random_interior_points(rng, n):
    u = rng.uniform(0, 89, n)
    # theta_d >= 1 deg: the nodes at theta_d = 0 have wi = wo, where phi_d is undefined and
    # the product lobe (unlike a real BRDF) is not a function of the directions
    v = rng.uniform(1, 89, n)
    w = rng.uniform(0, 180, n)
    ih, iv, iw = np.floor(u), np.floor(v), np.floor(w)
    # keep points whose 8 cell corners all have wi and wo above the horizon (the model
    # jumps to 0 there, which no interpolation bound covers)
    ok = np.ones(n, bool)
    for a in (ih, ih + 1):
        for b in (iv, iv + 1):
            for c in (iw, iw + 1):
                ci, co = directions_from_half_diff(K_H * a**2, 0.0, K_D * b, K_P * c)
                ok &= (ci[:, 2] > 1e-9) & (co[:, 2] > 1e-9)
    return u[ok], v[ok], w[ok], ih[ok], iv[ok], iw[ok]


def test_interpolation_error_within_the_derived_bound(resampled):
    rng = np.random.default_rng(2)
    u, v, w, ih, iv, iw = _random_interior_points(rng, 6000)
    assert u.size > 2000
    wi, wo = directions_from_half_diff(
        K_H * u**2, rng.uniform(-np.pi, np.pi, u.size), K_D * v, K_P * w
    )
    truth = ProductLobe().eval(wi, wo)
    got = resampled.eval(wi, wo)
    (am, ea), (bm, eb), (cm, ec) = _cell_bound(ih, _A), _cell_bound(iv, _B), _cell_bound(iw, _C)
    bound = (ea * bm * cm + am * eb * cm + am * bm * ec)[:, None] * CH / np.pi
    err = np.abs(got - truth)
    assert np.all(err <= bound * (1 + 1e-9) + 1e-12)
    # the bound is informative: a few % of f at most here, and nearest-bin look-up breaks it
    assert np.median(bound / truth) < 0.02
    nearest = np.abs(resampled.eval(wi, wo, interpolation="nearest") - truth)
    assert np.mean(nearest > bound) > 0.9  # measured: 97.5 %


def test_resample_analytic_model_with_params():
    # the contract of gonio.brdf models: model + params; checked at table nodes
    get_model = pytest.importorskip("gonio.brdf.registry").get_model
    model = get_model("lambert+ggx")
    params = {"albedo": 0.6, "ks": 0.3, "alpha": 0.3}
    m = resample(model, params, symmetrize=False)  # the model is reciprocal
    th, td, pd = bin_angles()
    rng = np.random.default_rng(4)
    i, j, k = rng.integers(0, 70, 500), rng.integers(0, 50, 500), rng.integers(0, 180, 500)
    wi, wo = directions_from_half_diff(th[i], 0.7, td[j], pd[k])
    ok = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    np.testing.assert_allclose(
        m.eval(wi[ok], wo[ok]), model.bind(params).eval(wi[ok], wo[ok]), rtol=1e-9
    )


def test_missing_entries_are_skipped_and_all_missing_gives_zero():
    raw = np.full((3, *DIMS), 1500.0)
    raw[:, 0, 0, :] = -1.0  # theta_h = theta_d = 0 row missing
    m = MERLBRDF(raw)
    wi, wo = directions_from_half_diff(0.0, 0.0, 0.5 * DEG, 10 * DEG)
    np.testing.assert_allclose(m.eval(wi, wo), SCALES * 1500)  # only valid nodes used
    m2 = MERLBRDF(np.full((3, *DIMS), -1.0))
    assert np.all(m2.eval(wi, wo) == 0)
    assert m2.metadata["missing_fraction"] == 1.0


def test_below_horizon_and_nan(resampled):
    f = resampled.eval(
        np.array([[0, 0, 1.0], [0, 0, -1.0], [np.nan, 0, 1]]), np.array([0.3, 0, 0.95])
    )
    assert np.all(f[0] > 0) and np.all(f[1] == 0) and np.all(np.isnan(f[2]))


def test_albedo_of_resampled_lambertian():
    class Lambert:
        def eval(self, wi, wo):
            up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
            return np.where(up, 0.7 / np.pi, 0.0)[..., None] * np.ones(3)

    m = resample(Lambert(), symmetrize=False)
    # constant in the interior; the horizon cells (a node below, renormalised away) are
    # also exact for a constant, so the albedo is the quadrature's: 0.7 to 1e-3
    np.testing.assert_allclose(m.albedo(np.radians([0.0, 40.0, 70.0])), 0.7, rtol=2e-3)


# ----------------------------------------------------------- bad files
def _expect(path, field, words):
    with pytest.raises(FileFormatError) as ei:
        load(path)
    assert ei.value.field == field and words in str(ei.value) and str(path) in str(ei.value)


def test_truncated(coded_file, tmp_path):
    p = tmp_path / "cut.binary"
    p.write_bytes(coded_file.read_bytes()[:1_000_012])
    _expect(p, "data", "truncated")


def test_trailing_bytes(coded_file, tmp_path):
    p = tmp_path / "long.binary"
    p.write_bytes(coded_file.read_bytes() + b"\0" * 8)
    _expect(p, "data", "trailing bytes")


def test_wrong_dimensions(tmp_path):
    p = tmp_path / "dims.binary"
    p.write_bytes(struct.pack("<3i", 90, 90, 360) + b"\0" * 64)
    _expect(p, "header", "expected (90, 90, 180)")


def test_nan_value(tmp_path):
    raw = np.ones((3, *DIMS))
    raw[1, 5, 6, 7] = np.nan
    p = tmp_path / "nan.binary"
    p.write_bytes(struct.pack("<3i", *DIMS) + raw.tobytes())
    _expect(p, "data", "channel G, theta_h bin 5, theta_d bin 6, phi_d bin 7")


def test_not_a_brdf_file(tmp_path):
    p = tmp_path / "text.binary"
    p.write_bytes(b"hello, this is not a BRDF at all")
    _expect(p, None, "unrecognised measured-BRDF format")

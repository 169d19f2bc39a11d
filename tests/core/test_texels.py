"""texels.h5 (gonio.texels): round trip against the arrays written, the texel convention,
the chunk layout, a block read touching only its own chunks, refusals naming the
dataset, and a texel's samples as gonio.fitting.fit takes them."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from gonio.dataset import BUDGET_TERMS, Flag
from gonio.errors import FileFormatError
from gonio.radiometry import normalize
from gonio.texels import (
    CHUNK_BYTES,
    ORIENTATION,
    chunk_texels_for,
    open_texels,
    save_texels,
    texel_centers,
)

NX, NY, P, C, M = 4, 3, 7, 3, 5
T = NX * NY


def arrays(seed: int = 3) -> dict:
    rng = np.random.default_rng(seed)
    wi, wo = (normalize(np.abs(rng.normal(size=(T, P, 3))) + [0, 0, 0.2]) for _ in "io")
    # a Lambertian albedo per texel: rho_t = 0.1 + 0.05 t (closed form for the fit test)
    rho = 0.1 + 0.05 * np.arange(T)
    brdf = np.repeat(rho[:, None, None] / np.pi, P, axis=1) * np.ones(C)
    budget = {term: rng.uniform(0, 1e-3, (T, P, C)) for term in BUDGET_TERMS}
    flags = np.zeros((T, P), np.uint32)
    flags[5, 2] = Flag.SATURATED
    # texel 7 has no sample in pose 4: INVALID and NaN, as the reduction writes it
    flags[7, 4] = Flag.INVALID
    for a in (wi, wo, brdf):
        a[7, 4] = np.nan
    return dict(
        wi=wi,
        wo=wo,
        brdf=brdf,
        brdf_std=np.sqrt(sum(v**2 for v in budget.values())),
        flags=flags,
        pose=np.arange(P) * 2 + 1,
        texels=(NX, NY),
        sample_size=(0.04, 0.03),
        budget=budget,
        shared_budget={"reference": np.full(C, 0.01), "light_scale": np.full(C, 0.002)},
        geometry_modes=rng.normal(0, 1e-3, (T, P, M, 6)),
        geometry_mode_scope=["session"] * 3 + ["pose"] * 2,
        geometry_mode_names=[f"mode {k}" for k in range(M)],
        attrs={"session": "S/", "grid": 4},
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    a = arrays()
    path = save_texels(tmp_path_factory.mktemp("tex") / "texels.h5", **a, chunk_texels=4)
    return path, a


def test_round_trip(written):
    path, a = written
    with open_texels(path) as tf:
        assert (tf.n_texels, tf.shape, tf.n_poses) == (T, (NY, NX), P)
        assert tf.channels == ("R", "G", "B") and tf.sample_size == (0.04, 0.03)
        assert tf.chunk_texels == 4 and tf.orientation == ORIENTATION
        assert tf.attrs["session"] == "S/" and tf.attrs["grid"] == 4
        rows = tf.block(0, T)
        for t, s in enumerate(rows):
            np.testing.assert_array_equal(s.wi, a["wi"][t])
            np.testing.assert_array_equal(s.brdf, a["brdf"][t])
            np.testing.assert_array_equal(s.brdf_std, a["brdf_std"][t])
            np.testing.assert_array_equal(s.flags, a["flags"][t])
            np.testing.assert_array_equal(s.pose, a["pose"])
            np.testing.assert_array_equal(s.geometry_modes, a["geometry_modes"][t])
            for term in BUDGET_TERMS:
                np.testing.assert_array_equal(s.budget[term], a["budget"][term][t])
            assert list(s.geometry_mode_scope) == a["geometry_mode_scope"]
            assert s.shared_budget["reference"].tolist() == [0.01] * 3
            # the shared calibration scale: rss of the shared terms, as samples.h5 has it
            np.testing.assert_allclose(s.attrs["calibration_rel_std"], np.hypot(0.01, 0.002))
        s7 = tf.samples(7)
        assert s7.flags[4] == Flag.INVALID and np.isnan(s7.wi[4]).all()
        assert not s7.valid[4] and s7.valid.sum() == P - 1
        assert len(s7) == P and s7.attrs["texel"] == 7


def test_texel_convention(written):
    path, _ = written
    # texel (row, col): row 0 at +y, column 0 at -x, t = row * nx + col (worked by hand)
    c = texel_centers((NX, NY), (0.04, 0.03))
    np.testing.assert_allclose(c[0], [-0.015, 0.01])  # top-left
    np.testing.assert_allclose(c[NX - 1], [0.015, 0.01])  # top-right
    np.testing.assert_allclose(c[T - NX], [-0.015, -0.01])  # bottom-left
    with open_texels(path) as tf:
        assert tf.index(2, 1) == 9
        s = tf.samples(9)
        assert (s.attrs["texel_row"], s.attrs["texel_col"]) == (2, 1)
        np.testing.assert_allclose(s.attrs["texel_center"], [-0.005, -0.01])
        assert list(tf.blocks()) == [(0, 4), (4, 8), (8, 12)]


def test_chunk_layout(written):
    path, _ = written
    with h5py.File(path) as f:
        assert f["brdf"].chunks == (4, P, C)
        assert f["flags"].chunks == (4, P)
        assert f["budget/noise"].chunks == (4, P, C)
        assert f["geometry_modes"].chunks == (4, P, M, 6)
        assert f["brdf"].compression == "gzip"
    # the default: the largest dataset's chunk near 1 MiB (numbers worked by hand)
    assert CHUNK_BYTES == 1048576
    assert chunk_texels_for(10_000, 100, 24) == 436  # 1048576 // 2400
    assert chunk_texels_for(10_000, 100, 8 * 20 * 6) == 10  # 1048576 // 96000
    assert chunk_texels_for(3, 100, 24) == 3  # never more than T
    assert chunk_texels_for(10, 10**6, 960) == 1  # a texel is never split


def test_block_reads_only_its_chunks(tmp_path):
    a = arrays()
    path = save_texels(tmp_path / "t.h5", **a, chunk_texels=4)
    with h5py.File(path) as f:
        info = f["brdf"].id.get_chunk_info(0)  # texels 0..3
        assert info.chunk_offset == (0, 0, 0)
    with open(path, "r+b") as fh:  # overwrite chunk 0 of brdf with garbage
        fh.seek(info.byte_offset)
        fh.write(b"\xff" * info.size)
    with open_texels(path) as tf:  # the header is intact
        rows = tf.block(4, 12)  # chunks 1 and 2: the damaged chunk is never read
        np.testing.assert_array_equal(rows[0].brdf, a["brdf"][4])
        with pytest.raises(FileFormatError, match=r"field 'brdf'.*texels 2\.\.4"):
            tf.block(2, 5)


def bad(tmp_path, **change):
    a = {**arrays(), **change}
    return save_texels(tmp_path / "bad.h5", **a)


def test_writer_refusals(tmp_path):
    a = arrays()
    with pytest.raises(ValueError, match=r"wi must have shape \(12, 7, 3\)"):
        bad(tmp_path, wi=a["wi"][:-1])
    with pytest.raises(ValueError, match="brdf must have shape"):
        bad(tmp_path, texels=(3, 4), brdf=a["brdf"][:, :, :2])
    with pytest.raises(ValueError, match="not unit vectors"):
        bad(tmp_path, wo=a["wo"] * 2)
    with pytest.raises(ValueError, match="unknown term 'glare'"):
        bad(tmp_path, budget={"glare": a["brdf"]})
    with pytest.raises(ValueError, match="flags must be integers"):
        bad(tmp_path, flags=a["flags"] - 1.5)
    with pytest.raises(ValueError, match="geometry_mode_names must have 5"):
        bad(tmp_path, geometry_mode_names=["x"])
    with pytest.raises(ValueError, match="texels must be two integers >= 1"):
        bad(tmp_path, texels=(0, 12))
    with pytest.raises(ValueError, match="brdf_std: standard deviations"):
        bad(tmp_path, brdf_std=-a["brdf_std"])
    with pytest.raises(ValueError, match="written by save_texels"):
        bad(tmp_path, attrs={"texels": [1, 1]})
    assert not (tmp_path / "bad.h5").exists()


def test_reader_refusals_name_the_dataset(tmp_path, written):
    src, _ = written
    import shutil

    def damaged(edit):
        p = tmp_path / "d.h5"
        shutil.copy(src, p)
        with h5py.File(p, "r+") as f:
            edit(f)
        return p

    cases = [
        (lambda f: f.attrs.__setitem__("schema", "gonio.samples"), "field 'schema'"),
        (lambda f: f.attrs.__setitem__("texels", [5, 3]), r"field 'wi'.*expected shape \(15"),
        (lambda f: f.__delitem__("flags"), "field 'flags': required dataset is missing"),
        (lambda f: f.__delitem__("geometry_mode_names"), "field 'geometry_mode_names'"),
        (lambda f: f["budget"].attrs.__setitem__("glare", [0.0] * 3), r"field 'budget\.glare'"),
        (lambda f: f.attrs.__setitem__("sample_size", [0.04, -1.0]), "field 'sample_size'"),
        (lambda f: f.attrs.__setitem__("orientation", "row 0 at -y"), "field 'orientation'"),
    ]
    for edit, msg in cases:
        with pytest.raises(FileFormatError, match=msg):
            with open_texels(damaged(edit)):
                pass
    p = damaged(lambda f: f["wi"].__setitem__((3, 1), [2.0, 0.0, 0.0]))
    with open_texels(p) as tf, pytest.raises(FileFormatError, match="field 'wi'.*unit vectors"):
        tf.samples(3)
    not_h5 = tmp_path / "x.h5"
    not_h5.write_bytes(b"not hdf5")
    with pytest.raises(FileFormatError, match="not a readable HDF5"):
        open_texels(not_h5).__enter__()
    with open_texels(src) as tf, pytest.raises(IndexError):
        tf.samples(T)


def test_a_texel_fits_like_a_samples_file(written):
    """gonio.fitting.fit takes a texel's samples as it takes samples.h5's: the Lambertian
    albedo of each texel is the one it was made with (closed form rho_t = 0.1 + 0.05 t)."""
    from gonio.fitting import fit

    path, _ = written
    with open_texels(path) as tf:
        for t in (0, 7, 11):
            r = fit(tf.samples(t), "lambert", maxeval=100)
            if t == 7:  # its empty pose is left out as a flagged samples.h5 row is
                assert r.diagnostics["dropped"] == {"flagged": 1}
            np.testing.assert_allclose(r.params["albedo"], 0.1 + 0.05 * t, rtol=1e-6)


def test_damage_is_an_error_or_nothing(tmp_path, written):
    """Random byte changes and truncations of a texels.h5: reading every texel either
    raises FileFormatError or gives back exactly what was written (chunk checksums,
    checksummed headers and chunk indexes, fill values of no sample), never a traceback
    or silently changed numbers."""
    src, a = written
    data = src.read_bytes()
    rng = np.random.default_rng(0)
    p = tmp_path / "fuzz.h5"
    outcomes = {"error": 0, "same": 0}
    for _ in range(100):
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 8))):
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        if rng.uniform() < 0.2:
            b = b[: int(rng.integers(0, len(b)))]
        p.write_bytes(bytes(b))
        try:
            with open_texels(p) as tf:
                rows = tf.block(0, tf.n_texels)
        except FileFormatError:
            outcomes["error"] += 1
            continue
        for t, s in enumerate(rows):
            for name in ("wi", "wo", "brdf", "brdf_std", "flags", "geometry_modes"):
                np.testing.assert_array_equal(getattr(s, name), a[name][t])
            for term in BUDGET_TERMS:
                np.testing.assert_array_equal(s.budget[term], a["budget"][term][t])
        outcomes["same"] += 1
    assert outcomes["error"] > 70, outcomes

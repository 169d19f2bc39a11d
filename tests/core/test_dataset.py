"""samples.h5: round trip, atomic writes, and clear errors on bad files."""

import h5py
import numpy as np
import pytest

from gonio.dataset import BRDFSamples, Flag, load_samples, save_samples
from gonio.errors import FileFormatError
from gonio.radiometry import normalize


def make(n=20, c=3):
    rng = np.random.default_rng(3)
    wi = normalize(rng.normal(size=(n, 3)) + [0, 0, 2])
    wo = normalize(rng.normal(size=(n, 3)) + [0, 0, 2])
    return BRDFSamples(
        wi=wi,
        wo=wo,
        brdf=rng.uniform(0, 1, (n, c)),
        brdf_std=rng.uniform(0, 0.1, (n, c)),
        flags=np.where(np.arange(n) % 5 == 0, Flag.SATURATED, 0),
        frames=[f"raw/p{k:04d}.dng" for k in range(n)],
        attrs={"session": "S1", "nested": {"a": 1}},
    )


def test_round_trip(tmp_path):
    s = make()
    p = save_samples(tmp_path / "samples.h5", s)
    r = load_samples(p)
    for name in ("wi", "wo", "brdf", "brdf_std", "flags"):
        np.testing.assert_array_equal(getattr(r, name), getattr(s, name))
    assert r.channels == ("R", "G", "B")
    assert list(r.frames) == list(s.frames)
    assert r.attrs["session"] == "S1"
    assert r.valid.sum() == 16
    with h5py.File(p) as f:
        assert f["brdf"].attrs["units"] == "1/sr"
        np.testing.assert_allclose(f["theta_i"][()], np.arccos(s.wi[:, 2]), atol=1e-12)


def test_failed_write_keeps_the_old_file(tmp_path):
    p = save_samples(tmp_path / "samples.h5", make())
    before = p.read_bytes()
    bad = make()
    bad.attrs["unstorable"] = object()
    with pytest.raises(TypeError):
        save_samples(p, bad)
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["samples.h5"]


def test_bad_files_name_file_and_field(tmp_path):
    with pytest.raises(FileFormatError, match="no such file"):
        load_samples(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5")
    with pytest.raises(FileFormatError, match="junk.h5.*HDF5"):
        load_samples(junk)
    p = save_samples(tmp_path / "s.h5", make())
    with h5py.File(p, "a") as f:
        del f["brdf"]
    with pytest.raises(FileFormatError, match="field 'brdf'.*missing"):
        load_samples(p)
    p = save_samples(tmp_path / "v.h5", make())
    with h5py.File(p, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(FileFormatError, match="schema_version"):
        load_samples(p)
    p = save_samples(tmp_path / "w.h5", make())
    with h5py.File(p, "a") as f:
        del f["brdf_std"]
        f["brdf_std"] = np.zeros((3, 3))
    with pytest.raises(FileFormatError, match="brdf_std"):
        load_samples(p)


def test_shape_checks():
    with pytest.raises(ValueError, match=r"wi must have shape \(N, 3\)"):
        BRDFSamples(wi=np.zeros((3, 2)), wo=np.zeros((3, 3)), brdf=np.zeros(3))
    s = BRDFSamples(wi=[[0, 0, 1.0]], wo=[[0, 0, 1.0]], brdf=[0.3])
    assert s.n_channels == 1 and np.isnan(s.brdf_std).all() and s.valid.all()


def _rewrite(p, name, data):
    with h5py.File(p, "a") as f:
        del f[name]
        f[name] = data


def test_empty_datasets_are_refused_as_no_samples(tmp_path):
    # issue 14.8: length-0 datasets reached the fit ("cannot reshape" in objective.py)
    p = save_samples(tmp_path / "empty.h5", make())
    with h5py.File(p, "a") as f:
        for name in list(f):
            shape = (0,) + f[name].shape[1:]
            dtype = f[name].dtype
            del f[name]
            f.create_dataset(name, shape=shape, dtype=dtype)
    with pytest.raises(FileFormatError, match=r"empty.h5, field 'wi'.*no samples"):
        load_samples(p)


@pytest.mark.parametrize("name", ["wi", "wo"])
def test_non_unit_directions_are_refused_naming_the_dataset(tmp_path, name):
    s = make()
    p = save_samples(tmp_path / "s.h5", s)
    v = getattr(s, name).copy()
    v[7] *= 1.0 + 1e-5  # beyond the 1e-6 tolerance
    _rewrite(p, name, v)
    with pytest.raises(
        FileFormatError, match=rf"field '{name}': 1 of 20 rows are not unit vectors \(row 7"
    ):
        load_samples(p)
    v = getattr(s, name).copy()
    v[7] *= 1.0 + 1e-7  # within it (float32 round trip level)
    v[3] = np.nan  # an unusable sample, not a malformed file
    _rewrite(p, name, v)
    r = load_samples(p)
    assert not r.valid[3] and r.valid.sum() == 15


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        (np.zeros(20, np.float64), "expected integers"),
        (np.full(20, -1, np.int64), r"\[0, 2\^32\)"),
        (np.full(20, 2**40, np.int64), r"\[0, 2\^32\)"),
    ],
)
def test_flags_must_be_an_integer_bit_mask(tmp_path, flags, match):
    p = save_samples(tmp_path / "s.h5", make())
    _rewrite(p, "flags", flags)
    with pytest.raises(FileFormatError, match=rf"field 'flags'.*{match}"):
        load_samples(p)


def test_units_say_what_radiance_and_irradiance_hold(tmp_path):
    s = make()
    dn = {"radiance": "camera DN/s (relative)", "irradiance": "camera DN/s (relative)"}
    n = len(s)
    s = BRDFSamples(
        wi=s.wi,
        wo=s.wo,
        brdf=s.brdf,
        radiance=np.ones((n, 3)),
        irradiance=np.ones((n, 3)),
        units=dn,
    )
    p = save_samples(tmp_path / "s.h5", s)
    with h5py.File(p) as f:
        assert f["radiance"].attrs["units"] == dn["radiance"]
        assert f["irradiance"].attrs["units"] == dn["irradiance"]
        assert f["brdf"].attrs["units"] == "1/sr"
    assert load_samples(p).units == dn
    # Without units the stored values are taken as calibrated SI values.
    plain = save_samples(
        tmp_path / "t.h5", BRDFSamples(wi=s.wi, wo=s.wo, brdf=s.brdf, radiance=np.ones((n, 3)))
    )
    with h5py.File(plain) as f:
        assert f["radiance"].attrs["units"] == "W/(sr m^2)"
    assert load_samples(plain).units == {"radiance": "W/(sr m^2)", "irradiance": "W/m^2"}
    with pytest.raises(ValueError, match="units apply to"):
        BRDFSamples(wi=s.wi, wo=s.wo, brdf=s.brdf, units={"brdf": "1/sr"})
    assert s.subset(np.arange(3)).units == dn


def test_a_group_or_bad_attribute_is_a_format_error(tmp_path):
    p = save_samples(tmp_path / "s.h5", make())
    with h5py.File(p, "a") as f:
        del f["brdf_std"]
        f.create_group("brdf_std")
    with pytest.raises(FileFormatError, match="field 'brdf_std'.*expected a dataset"):
        load_samples(p)
    p = save_samples(tmp_path / "c.h5", make())
    with h5py.File(p, "a") as f:
        f.attrs["channels"] = 5
    with pytest.raises(FileFormatError, match="field 'channels'"):
        load_samples(p)

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
        wi=wi, wo=wo, brdf=rng.uniform(0, 1, (n, c)), brdf_std=rng.uniform(0, 0.1, (n, c)),
        flags=np.where(np.arange(n) % 5 == 0, Flag.SATURATED, 0),
        frames=[f"raw/p{k:04d}.dng" for k in range(n)], attrs={"session": "S1", "nested": {"a": 1}},
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

"""samples.h5's uncertainty budget: round trip, subsets, old files, refusals naming the
dataset."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from gonio.dataset import BUDGET_TERMS, BRDFSamples, load_samples, save_samples
from gonio.errors import FileFormatError
from gonio.radiometry import normalize


def make(n=30, c=3, m=5):
    rng = np.random.default_rng(11)
    budget = {t: rng.uniform(0, 0.01, (n, c)) for t in BUDGET_TERMS}
    budget["geometry"][3] = np.nan  # unknown is allowed
    return BRDFSamples(
        wi=normalize(rng.normal(size=(n, 3)) + [0, 0, 2]),
        wo=normalize(rng.normal(size=(n, 3)) + [0, 0, 2]),
        brdf=rng.uniform(0.1, 1, (n, c)),
        brdf_std=np.sqrt(sum(np.nan_to_num(v) ** 2 for v in budget.values())),
        budget=budget,
        shared_budget={
            "reference": np.array([0.01, 0.011, 0.012]),
            "light_scale": np.full(3, 1e-3),
        },
        geometry_modes=rng.normal(0, 1e-3, (n, m, 6)),
        geometry_mode_scope=(["session"] * 3 + ["pose"] * 2)[:m],
        geometry_mode_names=[f"mode {k}" for k in range(m)],
        pose=np.arange(n) // 9,
        geometry_source=np.where(np.arange(n) % 4 == 0, "rig", "board"),
        stray_gain=np.where(np.arange(n)[:, None] == 5, np.nan, rng.uniform(1, 5, (n, c))),
    )


def test_round_trip_and_layout(tmp_path):
    s = make()
    p = save_samples(tmp_path / "s.h5", s)
    r = load_samples(p)
    assert set(r.budget) == set(BUDGET_TERMS)
    for t in BUDGET_TERMS:
        np.testing.assert_array_equal(r.budget[t], s.budget[t])
    for t in ("reference", "light_scale"):
        np.testing.assert_array_equal(r.shared_budget[t], s.shared_budget[t])
    np.testing.assert_array_equal(r.geometry_modes, s.geometry_modes)
    assert list(r.geometry_mode_scope) == ["session"] * 3 + ["pose"] * 2
    assert list(r.geometry_mode_names) == [f"mode {k}" for k in range(5)]
    assert r.pose.dtype == np.int32 and list(r.pose) == list(np.arange(30) // 9)
    assert list(r.geometry_source) == list(s.geometry_source)
    np.testing.assert_array_equal(r.stray_gain, s.stray_gain)  # NaN (unknown) kept
    with h5py.File(p) as f:  # the layout the contract names
        assert isinstance(f["budget"], h5py.Group)
        assert f["budget/noise"].shape == (30, 3) and f["budget/noise"].attrs["units"] == "1/sr"
        assert f["budget"].attrs["reference"].shape == (3,)
        assert f["geometry_modes"].shape == (30, 5, 6)
        assert f["pose"].dtype == np.int32
        assert f["stray_gain"].shape == (30, 3) and f["stray_gain"].attrs["units"] == "1"
    sub = r.subset(np.arange(30) % 2 == 0)
    assert sub.geometry_modes.shape == (15, 5, 6) and sub.budget["noise"].shape == (15, 3)
    np.testing.assert_array_equal(sub.pose, r.pose[::2])
    np.testing.assert_array_equal(sub.stray_gain, r.stray_gain[::2])
    assert list(sub.geometry_mode_names) == list(r.geometry_mode_names)


def test_no_modes_and_an_old_file(tmp_path):
    s = make(m=0)
    r = load_samples(save_samples(tmp_path / "zero.h5", s))
    assert r.geometry_modes.shape == (30, 0, 6) and r.geometry_mode_names.size == 0
    old = BRDFSamples(wi=s.wi, wo=s.wo, brdf=s.brdf, brdf_std=s.brdf_std)
    r = load_samples(save_samples(tmp_path / "old.h5", old))
    for name in ("budget", "shared_budget", "geometry_modes", "pose", "geometry_source",
                 "stray_gain"):  # fmt: skip
        assert getattr(r, name) is None, name
    with h5py.File(tmp_path / "old.h5") as f:
        assert "budget" not in f and "geometry_modes" not in f


def _mutate(tmp_path, fn):
    p = save_samples(tmp_path / "m.h5", make())
    with h5py.File(p, "a") as f:
        fn(f)
    return p


def _replace(name, value):
    def fn(f):
        del f[name]
        f[name] = value

    return fn


@pytest.mark.parametrize(
    ("fn", "match"),
    [
        (
            lambda f: f["budget"].create_dataset("sunspots", data=np.zeros((30, 3))),
            "budget/sunspots",
        ),
        (_replace("budget/noise", np.zeros((29, 3))), "budget/noise"),
        (_replace("budget/noise", -np.ones((30, 3))), "budget/noise"),
        (_replace("budget/drift", np.full((30, 3), np.inf)), "budget/drift"),
        (_replace("budget/noise", np.array([b"x"] * 30)), "budget/noise"),
        (lambda f: f["budget"].attrs.__setitem__("reference", [0.1, 0.2]), "budget.reference"),
        (lambda f: f["budget"].attrs.__setitem__("moon", [0.1, 0.2, 0.3]), "budget.moon"),
        (_replace("geometry_modes", np.zeros((30, 5, 3))), "geometry_modes"),
        (_replace("geometry_mode_scope", np.array([b"session"] * 4)), "geometry_mode_scope"),
        (_replace("geometry_mode_scope", np.array([b"galaxy"] * 5)), "geometry_mode_scope"),
        (lambda f: f.__delitem__("geometry_mode_names"), "geometry_mode_names"),
        (_replace("pose", np.zeros(30, float)), "pose"),
        (_replace("pose", np.full(30, 2**40)), "pose"),
        (_replace("geometry_source", np.array([b"astrology"] * 30)), "geometry_source"),
        (_replace("budget", np.zeros(3)), "budget"),
        (_replace("stray_gain", -np.ones((30, 3))), "stray_gain"),
        (_replace("stray_gain", np.full((30, 3), np.inf)), "stray_gain"),
        (_replace("stray_gain", np.ones((30, 2))), "stray_gain"),
        (_replace("stray_gain", np.array([b"x"] * 30)), "stray_gain"),
    ],
)
def test_bad_budget_is_refused_naming_the_dataset(tmp_path, fn, match):
    p = _mutate(tmp_path, fn)
    with pytest.raises(FileFormatError, match=match) as exc:
        load_samples(p)
    assert str(p) in str(exc.value)

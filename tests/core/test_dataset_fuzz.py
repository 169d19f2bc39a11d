"""Fuzzing ``load_samples`` (issue 14, "Must show"): mutated valid files, truncated files
and random bytes give a :class:`FileFormatError` or a valid sample set, nothing else.

Bounded: a few hundred examples, each on a file of ~20 kB; ``deadline=None`` because one
HDF5 open can take tens of milliseconds on a loaded CI machine.  A hang would stall the
test (and the suite's time budget shows it): nothing in ``load_samples`` loops on input.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gonio.dataset import BRDFSamples, Flag, load_samples, save_samples
from gonio.errors import FileFormatError
from gonio.radiometry import normalize

SETTINGS = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,  # the same examples on every run: a failure reproduces
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

DATASETS = (
    "wi",
    "wo",
    "theta_i",
    "brdf",
    "brdf_std",
    "flags",
    "radiance",
    "frames",
    # the uncertainty budget (issue 16)
    "budget",
    "budget/noise",
    "budget/geometry",
    "geometry_modes",
    "geometry_mode_scope",
    "geometry_mode_names",
    "pose",
    "geometry_source",
    "stray_gain",
)


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory) -> Path:
    rng = np.random.default_rng(7)
    n = 40
    s = BRDFSamples(
        wi=normalize(rng.normal(size=(n, 3)) + [0, 0, 2]),
        wo=normalize(rng.normal(size=(n, 3)) + [0, 0, 2]),
        brdf=rng.uniform(0, 1, (n, 3)),
        brdf_std=rng.uniform(0, 0.1, (n, 3)),
        flags=np.where(np.arange(n) % 7 == 0, Flag.SATURATED, 0),
        radiance=rng.uniform(0, 1, (n, 3)),
        frames=[f"raw/p{k:04d}.dng" for k in range(n)],
        attrs={"session": "S"},
        units={"radiance": "camera DN/s"},
        budget={t: rng.uniform(0, 0.01, (n, 3)) for t in ("noise", "geometry", "drift")},
        shared_budget={"reference": np.full(3, 0.01)},
        geometry_modes=rng.normal(0, 1e-3, (n, 4, 6)),
        geometry_mode_scope=["session", "session", "pose", "pose"],
        geometry_mode_names=["rig 1", "rig 2", "board pose 1", "board pose 2"],
        pose=np.arange(n) // 9,
        geometry_source=np.where(np.arange(n) % 3 == 0, "rig", "board"),
        stray_gain=rng.uniform(1, 5, (n, 3)),
    )
    return save_samples(tmp_path_factory.mktemp("fuzz") / "valid.h5", s)


def _load_is_clean(path) -> None:
    try:
        s = load_samples(path)
    except FileFormatError as exc:
        assert str(path) in str(exc)  # every refusal names the file
        return
    # Accepted: then it really is a consistent sample set.
    assert isinstance(s, BRDFSamples)
    n = len(s)
    assert n > 0 and s.wo.shape == (n, 3) and s.brdf.shape[0] == n and s.flags.shape == (n,)
    c = s.brdf.shape[1]
    for v in (s.budget or {}).values():
        assert v.shape == (n, c) and not (v < 0).any() and not np.isinf(v).any()
    for v in (s.shared_budget or {}).values():
        assert v.shape == (c,)
    if s.geometry_modes is not None:
        m = s.geometry_modes.shape[1]
        assert s.geometry_modes.shape == (n, m, 6)
        assert s.geometry_mode_scope.shape == s.geometry_mode_names.shape == (m,)
        assert set(s.geometry_mode_scope) <= {"session", "pose"}
    assert s.pose is None or (s.pose.shape == (n,) and s.pose.dtype == np.int32)
    assert s.geometry_source is None or set(s.geometry_source) <= {"board", "rig", "none"}
    if s.stray_gain is not None:
        assert s.stray_gain.shape == (n, c) and not (s.stray_gain < 0).any()
        assert not np.isinf(s.stray_gain).any()


@SETTINGS
@given(data=st.data())
def test_byte_level_damage(valid_file, tmp_path, data):
    b = bytearray(valid_file.read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "splice", "random"]))
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 16))):
            i = data.draw(st.integers(0, len(b) - 1))
            b[i] = data.draw(st.integers(0, 255))
    elif kind == "truncate":
        b = b[: data.draw(st.integers(0, len(b) - 1))]
    elif kind == "splice":
        i = data.draw(st.integers(0, len(b) - 1))
        b[i : i + 64] = data.draw(st.binary(min_size=1, max_size=64))
    else:
        b = bytearray(data.draw(st.binary(max_size=4096)))
    p = tmp_path / f"damaged_{kind}.h5"
    p.write_bytes(bytes(b))
    _load_is_clean(p)


_dtypes = st.sampled_from(["f8", "f4", "i8", "u4", "u1", "i2", "b1", "c16", "S4"])
_values = hnp.arrays(
    dtype=_dtypes,
    shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=50),
    elements=None,
)
# h5py cannot store a variable-length string with an embedded NUL or a lone surrogate
# (it raises before anything is written), so the damage drawn here has neither: no file
# can hold one.
_chars = st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",))
_text = st.text(alphabet=_chars, max_size=20)
_attr_values = st.one_of(
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True),
    _text,
    st.binary(max_size=20),
    st.lists(st.text(alphabet=_chars, max_size=5), max_size=5),
    st.just(np.array([1.5, 2.5])),
)


@SETTINGS
@given(data=st.data())
def test_structural_damage(valid_file, tmp_path, data):
    p = tmp_path / "mutated.h5"
    p.write_bytes(valid_file.read_bytes())
    with h5py.File(p, "a") as f:
        for _ in range(data.draw(st.integers(1, 3))):
            what = data.draw(st.sampled_from(["replace", "delete", "group", "attr", "values"]))
            name = data.draw(st.sampled_from(DATASETS))
            parent = name.rpartition("/")[0]
            if parent and not isinstance(f.get(parent), h5py.Group):
                continue  # "budget/x" under a "budget" that an earlier damage replaced
            if what == "replace":
                if name in f:
                    del f[name]
                f[name] = data.draw(_values)
            elif what == "delete" and name in f:
                del f[name]
            elif what == "group":
                if name in f:
                    del f[name]
                f.create_group(name)
            elif what == "attr":
                key = data.draw(st.sampled_from(["schema", "schema_version", "channels", "x"]))
                target = f if data.draw(st.booleans()) or name not in f else f[name]
                if target is f:
                    k = key
                elif name == "budget":  # the shared terms live in its attributes
                    k = data.draw(st.sampled_from(["reference", "light_scale", "other"]))
                else:
                    k = "units"
                value = data.draw(_attr_values)
                try:
                    target.attrs[k] = value
                except ValueError:  # a value HDF5 cannot store (a NUL byte): nothing written
                    pass
            elif (
                what == "values"
                and isinstance(f.get(name), h5py.Dataset)
                and f[name].dtype.kind == "f"
            ):
                v = f[name][()]
                if v.size:
                    flat = v.reshape(-1)
                    k = data.draw(st.integers(0, flat.size - 1))
                    flat[k] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e308, -2.0]))
                    f[name][...] = v
    _load_is_clean(p)

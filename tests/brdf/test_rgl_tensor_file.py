"""The tensor_file container and the RGL structure checks, on the real RGL files.

Corrupted inputs are copies written to tmp_path; the shared data are never modified.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from gonio.brdf.measured import load
from gonio.brdf.rgl import read_rgl
from gonio.brdf.tensor_file import read_tensor_file, write_tensor_file
from gonio.errors import FileFormatError

MATERIALS = ["paper_white", "colodur_napoli_4f", "vch_golden_yellow", "cc_ibiza_sunset"]


@pytest.mark.parametrize("name", MATERIALS)
def test_rewrite_reproduces_real_file_byte_for_byte(rgl_file, tmp_path, name):
    # Reading every field and writing them back must give the published file exactly:
    # checks names, dtype codes, shapes, offsets, alignment and data of the parser at once.
    src = rgl_file(name)
    out = tmp_path / "copy.bsdf"
    write_tensor_file(out, read_tensor_file(src))
    assert out.read_bytes() == src.read_bytes()


def test_known_header_of_paper_white(rgl_file):
    # Values listed in the data README / Mitsuba's TensorFile printout of this file.
    f = read_tensor_file(rgl_file("paper_white"))
    assert list(f) == [
        "version", "description", "phi_i", "theta_i", "sigma", "ndf",
        "vndf", "luminance", "rgb", "jacobian", "valid",
    ]  # fmt: skip
    assert bytes(f["description"]).decode() == "White A4 paper (160 gsm)"
    assert f["version"].dtype == np.uint32 and f["version"].tolist() == [1, 0]
    assert f["theta_i"].dtype == np.float32 and f["theta_i"].shape == (8,)
    assert f["vndf"].shape == (1, 8, 128, 128)
    assert f["rgb"].shape == (1, 8, 3, 32, 32)
    assert f["valid"].shape == (1024,) and f["jacobian"].tolist() == [1]
    assert f["theta_i"][0] == 0.0


def test_metadata_and_description(rgl_file):
    b = read_rgl(rgl_file("vch_golden_yellow"))
    assert b.format == "rgl"
    assert b.description == "TeckWrap vinyl wrapping film (Golden Yellow VCH508N)"
    assert b.metadata["isotropic"] and not b.metadata["spectral"]
    assert b.metadata["resolution"] == (32, 32)
    assert b.metadata["theta_i_deg"][-1] == pytest.approx(90.0)


# ---------------------------------------------------------------- corrupted copies
@pytest.fixture(scope="module")
def fields(refdata):
    p = refdata / "rgl" / "paper_white_rgb.bsdf"
    if not p.is_file():
        pytest.skip(f"{p} not found")
    return {k: np.array(v) for k, v in read_tensor_file(p).items()}


def _write(tmp_path: Path, fields: dict, name: str = "bad.bsdf") -> Path:
    p = tmp_path / name
    write_tensor_file(p, fields)
    return p


def _expect(path: Path, field: str | None, words: str):
    with pytest.raises(FileFormatError) as ei:
        load(path)
    e = ei.value
    assert str(path) in str(e)
    assert e.field == field
    assert words in str(e)
    return e


def test_truncated_header(fields, tmp_path):
    good = _write(tmp_path, fields, "good.bsdf").read_bytes()
    p = tmp_path / "cut.bsdf"
    p.write_bytes(good[:30])  # inside the header of the first field, 'version'
    _expect(p, "version", "truncated while reading the field header")


def test_truncated_data_names_the_field(fields, tmp_path):
    good = _write(tmp_path, fields, "good.bsdf").read_bytes()
    p = tmp_path / "cut.bsdf"
    p.write_bytes(good[:600_000])  # inside the 'rgb' block, which starts at 559592
    e = _expect(p, "rgb", "past the end of the file")
    assert "truncated" in str(e)


def test_file_too_small(tmp_path):
    p = tmp_path / "tiny.bsdf"
    p.write_bytes(b"tensor_file\x00\x01")
    _expect(p, None, "too small")


def test_wrong_magic(fields, tmp_path):
    good = bytearray(_write(tmp_path, fields, "good.bsdf").read_bytes())
    good[10] = ord("X")  # b"tensor_filX\0"
    p = tmp_path / "magic.bsdf"
    p.write_bytes(bytes(good))
    with pytest.raises(FileFormatError) as ei:
        read_rgl(p)
    assert ei.value.field == "magic"
    # load() does not recognise it as either format, and says what it expected
    _expect(p, None, "unrecognised measured-BRDF format")


def test_wrong_version(fields, tmp_path):
    good = bytearray(_write(tmp_path, fields, "good.bsdf").read_bytes())
    good[12] = 2
    p = tmp_path / "v2.bsdf"
    p.write_bytes(bytes(good))
    _expect(p, "version", "unsupported tensor_file version 2.0")


def test_unknown_dtype_code(fields, tmp_path):
    good = bytearray(_write(tmp_path, fields, "good.bsdf").read_bytes())
    at = good.index(b"\x07\x00theta_i") + 2 + 7 + 2  # name length, name, ndim -> dtype
    assert good[at] == 10  # float32
    good[at] = 12
    p = tmp_path / "dtype.bsdf"
    p.write_bytes(bytes(good))
    _expect(p, "theta_i", "unknown dtype code 12")


@pytest.mark.parametrize("missing", ["vndf", "theta_i", "rgb", "jacobian"])
def test_missing_field(fields, tmp_path, missing):
    f = {k: v for k, v in fields.items() if k != missing}
    _expect(_write(tmp_path, f), missing, "missing")


def test_rgb_with_wrong_channel_count(fields, tmp_path):
    f = dict(fields, rgb=np.concatenate([fields["rgb"], fields["rgb"][:, :, :1]], axis=2))
    _expect(_write(tmp_path, f), "rgb", "expected 3 colour channels, got 4")


def test_vndf_not_matching_theta_i(fields, tmp_path):
    f = dict(fields, vndf=fields["vndf"][:, :7])
    _expect(_write(tmp_path, f), "vndf", "do not match")


def test_wrong_dtype(fields, tmp_path):
    f = dict(fields, theta_i=fields["theta_i"].astype(np.float64))
    _expect(_write(tmp_path, f), "theta_i", "float32")


def test_nan_in_rgb(fields, tmp_path):
    rgb = fields["rgb"].copy()
    rgb[0, 3, 1, 5, 5] = np.nan
    _expect(_write(tmp_path, dict(fields, rgb=rgb)), "rgb", "NaN")


def test_negative_vndf(fields, tmp_path):
    v = fields["vndf"].copy()
    v[0, 2, 10, 10] = -1.0
    _expect(_write(tmp_path, dict(fields, vndf=v)), "vndf", "negative")


def test_theta_i_not_increasing(fields, tmp_path):
    t = fields["theta_i"].copy()
    t[[2, 3]] = t[[3, 2]]
    _expect(_write(tmp_path, dict(fields, theta_i=t)), "theta_i", "strictly increasing")


def test_duplicate_field(fields, tmp_path):
    good = bytearray(_write(tmp_path, fields, "good.bsdf").read_bytes())
    at = good.index(b"\x03\x00ndf")
    good[at + 2 : at + 5] = b"rgb"  # rename 'ndf' to a name that comes later
    p = tmp_path / "dup.bsdf"
    p.write_bytes(bytes(good))
    _expect(p, "rgb", "appears twice")


def test_missing_file(tmp_path):
    with pytest.raises(FileFormatError, match="cannot read"):
        load(tmp_path / "nope.bsdf")


def test_header_count_is_little_endian_uint32(fields, tmp_path):
    raw = _write(tmp_path, fields, "good.bsdf").read_bytes()
    assert struct.unpack_from("<I", raw, 14)[0] == len(fields)

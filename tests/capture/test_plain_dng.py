"""The simulator's DNGs read without LibRaw's unpack give LibRaw's frame, field for field
and pixel for pixel; every other file still goes through LibRaw (the oracle here)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import gonio.simulator.dng as dng
from gonio.capture.plain_dng import read_plain_dng
from gonio.capture.raw import read_raw
from gonio.simulator.sensor import RawFrame as SimFrame

FIELDS = ("cfa_pattern", "white_level", "exposure_time", "iso", "f_number", "shape")


def sim_dng(pattern="RGGB", black=512, white=16383, t=0.004, n=5.6, iso=400.0, seed=0):
    rng = np.random.default_rng(seed)
    mosaic = rng.integers(0, white + 1, (40, 56)).astype(np.uint16)
    mosaic[0, 0] = white  # a clipped pixel: the saturation mask is compared too
    frame = SimFrame(mosaic, pattern, black, white, np.eye(3), np.ones(3), t, n, iso, 0.035)
    return dng.dng_bytes(frame), mosaic


def both(data, monkeypatch):
    """``(direct, libraw)`` frames of the same bytes."""
    monkeypatch.delenv("GONIO_DIRECT_DNG", raising=False)
    direct = read_raw(data, name="f.dng")
    monkeypatch.setenv("GONIO_DIRECT_DNG", "0")
    libraw = read_raw(data, name="f.dng")
    monkeypatch.delenv("GONIO_DIRECT_DNG")
    return direct, libraw


def assert_same_frame(a, b):
    for f in FIELDS:
        assert getattr(a, f) == getattr(b, f), f
    for f in ("cell_black", "cell_channel", "cell_saturation", "raw"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        np.testing.assert_array_equal(x, y, err_msg=f)
    box = (slice(3, 17), slice(5, 30))  # odd offsets: the CFA phase of a crop
    for x, y in zip(a.region(box), b.region(box), strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.saturated, b.saturated)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize(
    "t, n, iso",
    [(0.004, 5.6, 400.0), (9 / 200000, 8.0, 100.0), (1 / 3, 2.8, 3200.0), (1.7e-5, 11.0, 64.0)],
)
def test_direct_read_is_libraws_frame(pattern, t, n, iso, monkeypatch):
    data, mosaic = sim_dng(pattern, t=t, n=n, iso=iso)
    assert read_plain_dng(data) is not None  # the direct path is the one taken
    direct, libraw = both(data, monkeypatch)
    assert_same_frame(direct, libraw)
    np.testing.assert_array_equal(direct.raw, mosaic)
    # a view of the file's bytes, not a copy; read-only like LibRaw's buffer
    assert not direct.raw.flags.owndata and not direct.raw.flags.writeable


def test_per_position_black_levels_and_12_bit_white(monkeypatch):
    blacks = (500, 510, 520, 530)
    tags = dng._tags
    monkeypatch.setattr(
        dng,
        "_tags",
        lambda fr: [(50714, t[1], 4, blacks, True) if t[0] == 50714 else t for t in tags(fr)],
    )
    data, _ = sim_dng("GRBG", white=4095)
    assert read_plain_dng(data) is not None
    direct, libraw = both(data, monkeypatch)
    assert_same_frame(direct, libraw)
    np.testing.assert_array_equal(direct.cell_black, np.reshape(blacks, (2, 2)))


def _retag(data: bytes, tag: int, new_tag: int) -> bytes:
    """The file with IFD0's entry ``tag`` renumbered (the IFD stays sorted enough for
    LibRaw, which does not require order)."""
    b = bytearray(data)
    off = struct.unpack_from("<I", b, 4)[0]
    for k in range(struct.unpack_from("<H", b, off)[0]):
        at = off + 2 + 12 * k
        if struct.unpack_from("<H", b, at)[0] == tag:
            struct.pack_into("<H", b, at, new_tag)
            return bytes(b)
    raise AssertionError(f"no tag {tag}")


def test_other_files_go_to_libraw(refdata, monkeypatch):
    # real camera files: a CinemaDNG (linearisation table, another maker) and a Kodak
    for name in ("Blackmagic.dng", "RAW_KODAK_DC50.KDC"):
        assert read_plain_dng((refdata / "raw" / name).read_bytes()) is None
    data, _ = sim_dng()
    # another maker (LibRaw may correct its files), a tag this reader does not know
    # (50712 LinearizationTable's number on the Model entry), no BlackLevel type it takes
    assert read_plain_dng(data.replace(b"gonio\0", b"Gonio\0", 1)) is None
    assert read_plain_dng(_retag(data, 272, 50712)) is None
    assert read_plain_dng(b"MM\0*" + data[4:]) is None
    assert read_plain_dng(data[:100]) is None
    assert read_plain_dng(b"") is None
    # the whole frame of a foreign file is LibRaw's, unchanged by the switch
    path = refdata / "raw" / "RAW_KODAK_DC50.KDC"
    a, b = both(path.read_bytes(), monkeypatch)
    assert_same_frame(a, b)


def test_truncated_simulator_file_is_still_refused(tmp_path):
    from gonio.errors import FileFormatError

    data, _ = sim_dng()
    with pytest.raises(FileFormatError, match="cut.dng.*truncated"):
        read_raw(data[:-500], name="cut.dng")

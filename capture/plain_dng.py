"""The simulator's DNG files read without LibRaw's unpack: the mosaic is a view of the
file's bytes.

LibRaw's unpack of an uncompressed 16-bit DNG goes pixel by pixel into a buffer of its
own: 7-14 ms for a 1600 x 1200 frame on the 2-core machine, where the same pixels are
already in the file's bytes, in the mosaic's order (a numpy view of them costs nothing,
a copy under 1 ms).  :func:`read_plain_dng` reads those bytes directly for the one kind
of file whose layout gonio knows in every detail, the simulator's
(:mod:`gonio.simulator.dng`: Make ``gonio``, one IFD, one uncompressed little-endian
16-bit CFA strip, BlackLevel and WhiteLevel as integers, no linearisation table, no
active area, the ISO in an EXIF IFD), and returns None for anything else, which LibRaw
decodes as before (:func:`gonio.capture.raw.read_raw`).

Hand-written, like :func:`gonio.capture.raw.tiff_data_end`, rather than with tifffile:
tifffile parses every tag of the file in Python (about 0.5 ms a frame, holding the GIL
that the decoding threads need) and copies the strip.  The metadata are LibRaw's
numbers, bit for bit: LibRaw keeps shutter, aperture and ISO as float32, so the values
here are rounded the same way.  LibRaw applies maker-specific corrections even to DNGs;
requiring Make ``gonio`` and nothing but the simulator's tags keeps this reader to files
where it has none.  ``tests/capture/test_plain_dng.py`` compares every field and every
pixel with LibRaw's on the simulator's files (all four CFA phases, per-position black
levels, exposures, ISO speeds) and checks that other files go to LibRaw.
``GONIO_DIRECT_DNG=0`` sends every file through LibRaw (the oracle).
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["PlainDNG", "direct_enabled", "read_plain_dng"]

#: The tags the simulator's DNG writer puts in IFD0 (gonio.simulator.dng, tifffile's
#: baseline tags included) plus harmless descriptive ones: a file with any other tag is
#: left to LibRaw, which may act on it.
_IFD0_TAGS = frozenset(
    {
        254, 256, 257, 258, 259, 262, 271, 272, 273, 277, 278, 279, 282, 283, 284, 296,
        305, 306,  # Software, DateTime
        33421, 33422, 33434, 33437, 34665, 37386,
        50706, 50707, 50708, 50710, 50711, 50713, 50714, 50717, 50721, 50728, 50778,
    }
)  # fmt: skip
#: The EXIF IFD's tags the simulator writes.
_EXIF_TAGS = frozenset({33434, 33437, 34855, 34864, 36864, 37386})
_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1, 10: 8}
_CFA_LETTER = {0: "R", 1: "G", 2: "B"}


@dataclass(frozen=True)
class PlainDNG:
    """What :func:`gonio.capture.raw.read_raw` takes from LibRaw, read from the file.

    Attributes
    ----------
    mosaic
        (H, W) uint16 view of the file's strip (read-only), raw DN with black level.
    cfa_pattern
        2x2 pattern as letters, row-major (``"RGGB"``...).
    cell_black
        (2, 2) black level of each CFA position, DN.
    white_level
        WhiteLevel, DN.
    exposure_time, iso, f_number
        As LibRaw reports them (float32 values; NaN where the file has none).
    """

    mosaic: NDArray[np.uint16]
    cfa_pattern: str
    cell_black: NDArray[np.float64]
    white_level: float
    exposure_time: float
    iso: float
    f_number: float


def direct_enabled() -> bool:
    """False when ``GONIO_DIRECT_DNG=0``: every file then goes through LibRaw."""
    return os.environ.get("GONIO_DIRECT_DNG") != "0"


def _ifd(data: bytes, off: int) -> tuple[dict[int, tuple[int, int, int]], int] | None:
    """``{tag: (type, count, value offset)}`` of the IFD at ``off`` and the next IFD's
    offset; None when it lies outside ``data``."""
    if off < 8 or off + 2 > len(data):
        return None
    n = struct.unpack_from("<H", data, off)[0]
    if off + 2 + 12 * n + 4 > len(data):
        return None
    tags = {}
    for k in range(n):
        at = off + 2 + 12 * k
        tag, typ, cnt = struct.unpack_from("<HHI", data, at)
        size = _TYPE_SIZE.get(typ)
        if size is None:
            return None
        vat = at + 8
        if cnt * size > 4:
            vat = struct.unpack_from("<I", data, vat)[0]
            if vat + cnt * size > len(data):
                return None
        tags[tag] = (typ, cnt, vat)
    return tags, struct.unpack_from("<I", data, off + 2 + 12 * n)[0]


def _ints(data: bytes, entry: tuple[int, int, int] | None) -> tuple[int, ...] | None:
    """A BYTE, SHORT or LONG field's values (None: absent or another type)."""
    if entry is None:
        return None
    typ, cnt, at = entry
    fmt = {1: "B", 3: "H", 4: "I"}.get(typ)
    if fmt is None:
        return None
    return struct.unpack_from(f"<{cnt}{fmt}", data, at)


def _real(data: bytes, entry: tuple[int, int, int] | None) -> float | None:
    """A single RATIONAL, SHORT or LONG as LibRaw's ``getreal`` reads it (double)."""
    if entry is None or entry[1] != 1:
        return None
    typ, _, at = entry
    if typ == 5:
        num, den = struct.unpack_from("<II", data, at)
        return num / (den if den else 1.0)
    v = _ints(data, entry)
    return None if v is None else float(v[0])


def _f32(x: float | None) -> float:
    """LibRaw's float32 field as rawpy returns it; 0 and absent are NaN (read_raw's rule)."""
    if x is None:
        return math.nan
    return float(np.float32(x)) or math.nan


def read_plain_dng(data: bytes) -> PlainDNG | None:
    """The simulator's DNG read directly, or None when ``data`` is any other file.

    Parameters
    ----------
    data
        The whole file.

    Returns
    -------
    PlainDNG or None
        None for anything but the simulator's layout (see the module docstring): those
        files go through LibRaw.  Never raises on malformed input: it returns None and
        LibRaw's own checks name the problem.
    """
    if len(data) < 8 or data[:4] != b"II*\x00":
        return None
    first = _ifd(data, struct.unpack_from("<I", data, 4)[0])
    if first is None:
        return None
    tags, nxt = first
    if nxt != 0 or not set(tags) <= _IFD0_TAGS:
        return None
    make = tags.get(271)
    if make is None or make[0] != 2 or data[make[2] : make[2] + make[1]].rstrip(b"\0") != b"gonio":
        return None

    def one(tag: int, default: int | None = None) -> int | None:
        v = _ints(data, tags.get(tag))
        if v is None:
            return default if tag not in tags else None
        return v[0] if len(v) == 1 else None

    w, h = one(256), one(257)
    if (
        w is None
        or h is None
        or one(254, 0) != 0
        or one(258) != 16
        or one(259) != 1
        or one(262) != 32803
        or one(277, 1) != 1
        or one(284, 1) != 1
        or one(50711, 1) != 1
        or _ints(data, tags.get(33421)) != (2, 2)
        or (50710 in tags and _ints(data, tags[50710]) != (0, 1, 2))
    ):
        return None
    cfa = _ints(data, tags.get(33422))
    if cfa is None or tags[33422][0] != 1 or sorted(cfa) != [0, 1, 1, 2]:
        return None
    offs, counts = _ints(data, tags.get(273)), _ints(data, tags.get(279))
    if not offs or not counts or len(offs) != len(counts):
        return None
    # one view: the strips must follow each other in the file, in order
    if any(o + c != o2 for o, c, o2 in zip(offs, counts, offs[1:], strict=False)):
        return None
    start, size = offs[0], 2 * w * h
    if sum(counts) != size or start + size > len(data) or start % 2:
        return None
    # black level: one value, or one per position of the 2x2 CFA cell (LibRaw's cblack)
    rep = _ints(data, tags.get(50713)) if 50713 in tags else (1, 1)
    black = _ints(data, tags.get(50714)) if 50714 in tags else (0,)
    if black is None or tags.get(50714, (3,))[0] not in (3, 4):
        return None
    if rep == (1, 1) and len(black) == 1:
        cell = np.full((2, 2), float(black[0]))
    elif rep == (2, 2) and len(black) == 4:
        cell = np.asarray(black, float).reshape(2, 2)
    else:
        return None
    white = one(50717)
    if white is None or not 0 < white <= 65535:
        return None
    exp = {"t": _real(data, tags.get(33434)), "n": _real(data, tags.get(33437))}
    iso = None
    if 34665 in tags:
        ex_off = one(34665)
        sub = None if ex_off is None else _ifd(data, ex_off)
        if sub is None or not set(sub[0]) <= _EXIF_TAGS:
            return None
        et = sub[0]
        # LibRaw reads both copies, the EXIF one last: they must agree for this reader
        for key, tag in (("t", 33434), ("n", 33437)):
            v = _real(data, et.get(tag))
            if v is not None:
                if exp[key] is not None and v != exp[key]:
                    return None
                exp[key] = v
        iso_v = _ints(data, et.get(34855))
        if iso_v is not None:
            if len(iso_v) != 1:
                return None
            iso = float(iso_v[0])
    mosaic = np.frombuffer(data, "<u2", w * h, start).reshape(h, w)
    return PlainDNG(
        mosaic=mosaic,
        cfa_pattern="".join(_CFA_LETTER[c] for c in cfa),
        cell_black=cell,
        white_level=float(white),
        exposure_time=_f32(exp["t"]),
        iso=_f32(iso),
        f_number=_f32(exp["n"]),
    )

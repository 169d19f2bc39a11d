"""Write a :class:`~gonio.simulator.sensor.RawFrame` as a DNG file that LibRaw (rawpy) reads.

tifffile writes the image and IFD0 tags (CFA layout, black/white levels, colour matrix,
as-shot neutral, exposure time, f-number, focal length).  LibRaw reads the ISO only from
an EXIF sub-IFD (tag 34665), which tifffile cannot write: we write a placeholder offset,
append a small EXIF IFD by hand and patch the offset (see ``_append_exif``).  No time
stamps are written, so equal frames give equal bytes.
"""

from __future__ import annotations

import io
import struct
from collections import OrderedDict
from fractions import Fraction
from pathlib import Path

import numpy as np
import tifffile

from gonio.atomic import write_bytes_atomic
from gonio.errors import FileFormatError
from gonio.simulator.sensor import RawFrame

__all__ = ["dng_bytes", "write_dng"]

_CFA_CODE = {"R": 0, "G": 1, "B": 2}
_EXIF_IFD = 34665
# tifffile refuses to write tag 34665; an unassigned neighbour sorts into the same IFD
# position and is renamed after writing.
_PLACEHOLDER = 34664
# TIFF field types
_SHORT, _LONG, _RATIONAL, _UNDEFINED = 3, 4, 5, 7


def _rational(x: float, max_den: int = 1_000_000) -> tuple[int, int]:
    f = Fraction(float(x)).limit_denominator(max_den)
    return f.numerator, f.denominator


def _srational_flat(values: np.ndarray, den: int = 10000) -> list[int]:
    out = []
    for v in np.asarray(values, float).ravel():
        out += [int(round(v * den)), den]
    return out


def _tags(frame: RawFrame) -> list[tuple]:
    t_num = _rational(frame.exposure_time)
    return [
        (50706, 1, 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, 1, 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (271, 2, None, "gonio", True),  # Make
        (272, 2, None, frame.model, True),  # Model
        (50708, 2, None, frame.model, True),  # UniqueCameraModel
        (33421, _SHORT, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, 1, 4, tuple(_CFA_CODE[c] for c in frame.cfa_pattern), True),  # CFAPattern
        (50710, 1, 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, _SHORT, 1, 1, True),  # CFALayout: rectangular
        (50713, _SHORT, 2, (2, 2), True),  # BlackLevelRepeatDim
        (50714, _LONG, 4, (frame.black_level,) * 4, True),  # BlackLevel
        (50717, _LONG, 1, frame.white_level, True),  # WhiteLevel
        (50721, 10, 9, tuple(_srational_flat(frame.colour_matrix)), True),  # ColorMatrix1
        (50778, _SHORT, 1, 21, True),  # CalibrationIlluminant1: D65
        (
            50728,
            _RATIONAL,
            3,
            tuple(v for x in frame.as_shot_neutral for v in _rational(x, 100000)),
            True,
        ),
        (33434, _RATIONAL, 1, t_num, True),  # ExposureTime
        (33437, _RATIONAL, 1, _rational(frame.f_number, 1000), True),  # FNumber
        (37386, _RATIONAL, 1, _rational(frame.focal_length * 1000, 1000), True),  # mm
        (_PLACEHOLDER, _LONG, 1, 0, True),  # becomes the EXIF IFD pointer
    ]


def _append_exif(data: bytearray, frame: RawFrame) -> bytearray:
    # Hand-written because tifffile writes sub-IFDs only for image data, not EXIF.
    with tifffile.TiffFile(io.BytesIO(bytes(data))) as tif:
        if tif.byteorder != "<":
            raise AssertionError("tifffile wrote big-endian TIFF")
        tag = tif.pages[0].tags[_PLACEHOLDER]
        entry, slot = tag.offset, tag.valueoffset
    if len(data) % 2:
        data += b"\0"
    ifd_at = len(data)
    iso = int(min(max(round(frame.iso), 1), 65535))
    entries = [
        (33434, _RATIONAL, 1, _rational(frame.exposure_time)),
        (33437, _RATIONAL, 1, _rational(frame.f_number, 1000)),
        (34855, _SHORT, 1, iso),  # ISOSpeedRatings
        (34864, _SHORT, 1, 3),  # SensitivityType: ISO speed
        (36864, _UNDEFINED, 4, b"0231"),  # ExifVersion
        (37386, _RATIONAL, 1, _rational(frame.focal_length * 1000, 1000)),
    ]
    n = len(entries)
    extra_at = ifd_at + 2 + 12 * n + 4
    head = struct.pack("<H", n)
    extra = b""
    for tag, typ, count, value in entries:
        if typ == _RATIONAL:
            head += struct.pack("<HHII", tag, typ, count, extra_at + len(extra))
            extra += struct.pack("<II", *value)
        elif typ == _SHORT:
            head += struct.pack("<HHIHH", tag, typ, count, value, 0)
        else:
            head += struct.pack("<HHI", tag, typ, count) + value
    data += head + struct.pack("<I", 0) + extra
    struct.pack_into("<HH", data, entry, _EXIF_IFD, _LONG)
    struct.pack_into("<I", data, slot, ifd_at)
    return data


def dng_bytes(frame: RawFrame) -> bytes:
    """The DNG file of a RAW frame, as bytes (deterministic).

    The bytes are those tifffile and :func:`_append_exif` write (:func:`_dng_bytes_tifffile`,
    the reference): the file of a frame's metadata is built that way once and kept
    (:data:`_TEMPLATES`), and each frame's mosaic is put in its image strip, which is
    uncompressed and the only part of the file the pixels reach.  A session's brackets
    use a handful of exposure settings, so a few templates serve all its frames (the
    tifffile writer and the EXIF patch cost ~5 ms a frame, the copy ~0.05 ms).

    Parameters
    ----------
    frame
        Mosaic and metadata (:func:`gonio.simulator.sensor.simulate_raw`).
    """
    mosaic = np.ascontiguousarray(frame.mosaic, dtype=np.uint16)
    if mosaic.ndim != 2:
        raise ValueError(f"mosaic must be 2-D, got shape {mosaic.shape}")
    key = _template_key(frame, mosaic)
    hit = _TEMPLATES.get(key)
    if hit is None:
        hit = _template(frame, mosaic)
        _TEMPLATES[key] = hit
        while len(_TEMPLATES) > _TEMPLATES_SIZE:
            _TEMPLATES.popitem(last=False)
    else:
        _TEMPLATES.move_to_end(key)
    head, tail = hit
    return b"".join((head, mosaic.astype("<u2", copy=False).tobytes(), tail))


#: Files of frames' metadata with the image strip cut out: key -> (head, tail) bytes.
_TEMPLATES: OrderedDict[tuple, tuple[bytes, bytes]] = OrderedDict()
_TEMPLATES_SIZE = 32


def _template_key(frame: RawFrame, mosaic: np.ndarray) -> tuple:
    """Everything of a frame that reaches its file's bytes, but the pixels."""
    return (
        mosaic.shape,
        frame.cfa_pattern,
        int(frame.black_level),
        int(frame.white_level),
        np.asarray(frame.colour_matrix, float).tobytes(),
        np.asarray(frame.as_shot_neutral, float).tobytes(),
        float(frame.exposure_time),
        float(frame.f_number),
        float(frame.iso),
        float(frame.focal_length),
        frame.model,
    )


def _template(frame: RawFrame, mosaic: np.ndarray) -> tuple[bytes, bytes]:
    """The reference file of ``frame``'s metadata split around its image strip."""
    data = _dng_bytes_tifffile(frame, np.zeros_like(mosaic))
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        page = tif.pages[0]
        offsets, counts = list(page.dataoffsets), list(page.databytecounts)
    start = offsets[0]
    contiguous = all(o == start + sum(counts[:i]) for i, o in enumerate(offsets))
    if not contiguous or sum(counts) != mosaic.nbytes:
        # tifffile writes one uncompressed, contiguous strip for such a page
        raise AssertionError("tifffile wrote the DNG's image data in pieces")
    return data[:start], data[start + mosaic.nbytes :]


def _dng_bytes_tifffile(frame: RawFrame, mosaic: np.ndarray) -> bytes:
    """:func:`dng_bytes` of ``frame`` with ``mosaic`` (2-D uint16), written by tifffile."""
    buf = io.BytesIO()
    tifffile.imwrite(
        buf,
        mosaic,
        photometric=32803,
        extratags=_tags(frame),
        metadata=None,
        subfiletype=0,
        software=False,
    )
    return bytes(_append_exif(bytearray(buf.getvalue()), frame))


def write_dng(path: str | Path, frame: RawFrame | bytes, *, overwrite: bool = False) -> Path:
    """Write a DNG atomically (temporary file, then rename).

    Parameters
    ----------
    path
        Destination file.
    frame
        A :class:`RawFrame` or DNG bytes from :func:`dng_bytes`.
    overwrite
        Replace an existing file; otherwise an existing file is an error.

    Raises
    ------
    FileFormatError
        ``path`` exists and ``overwrite`` is false.
    """
    p = Path(path)
    if p.exists() and not overwrite:
        raise FileFormatError(p, "exists; refusing to overwrite (use overwrite/--force)")
    data = frame if isinstance(frame, bytes | bytearray) else dng_bytes(frame)
    write_bytes_atomic(p, bytes(data))
    return p

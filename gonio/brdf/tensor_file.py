"""Strict reader and writer of the ``tensor_file`` container (RGL-EPFL ``*.bsdf`` files).

The container is the one Mitsuba's ``TensorFile`` reads (``src/core/tensor.cpp``); its
layout, all little-endian::

    12 bytes   b"tensor_file\\0"
    2 bytes    version: major, minor (1, 0)
    uint32     number of fields
    per field: uint16 name length, name (UTF-8), uint16 ndim, uint8 dtype code,
               uint64 byte offset of the data, ndim x uint64 shape
    data       C-ordered arrays at their offsets (the RGL files align them to 8 bytes)

The dtype codes are Mitsuba's ``Struct::Type`` values (UInt8 = 1 ... Float64 = 11).

Hand-written because no maintained Python package reads this container; numpy does the
array work.  Every inconsistency (truncation, bad magic, unknown dtype, a field running
past the end of the file, duplicate names) raises :class:`gonio.errors.FileFormatError`
naming the file and the field.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from gonio.errors import FileFormatError

__all__ = ["MAGIC", "DTYPE_CODES", "read_tensor_file", "write_tensor_file"]

MAGIC = b"tensor_file\x00"
VERSION = (1, 0)

# Mitsuba Struct::Type code -> numpy dtype (little-endian)
DTYPE_CODES: dict[int, np.dtype] = {
    1: np.dtype("<u1"),
    2: np.dtype("<i1"),
    3: np.dtype("<u2"),
    4: np.dtype("<i2"),
    5: np.dtype("<u4"),
    6: np.dtype("<i4"),
    7: np.dtype("<u8"),
    8: np.dtype("<i8"),
    9: np.dtype("<f2"),
    10: np.dtype("<f4"),
    11: np.dtype("<f8"),
}
_CODE_OF = {dt: code for code, dt in DTYPE_CODES.items()}

# Far above any real file (11 fields); stops a corrupted count from looping for long.
_MAX_FIELDS = 4096
_MAX_NDIM = 16


def _unpack(fmt: str, buf: bytes, pos: int, path: Path, what: str, field: str | None):
    size = struct.calcsize(fmt)
    if pos + size > len(buf):
        raise FileFormatError(
            path,
            f"file truncated while reading {what} (needs bytes {pos}..{pos + size}, "
            f"file has {len(buf)})",
            field=field,
        )
    return struct.unpack_from(fmt, buf, pos), pos + size


def read_tensor_file(path: str | Path) -> dict[str, np.ndarray]:
    """Read every field of a tensor file.

    Parameters
    ----------
    path
        The ``*.bsdf`` (tensor_file v1.0) file.

    Returns
    -------
    dict
        Field name -> read-only numpy array of the stored dtype and shape, in file order.

    Raises
    ------
    FileFormatError
        Missing/unreadable file, wrong magic or version, truncated header or data, unknown
        dtype code, duplicate field names.
    """
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(path, f"cannot read file: {exc.strerror or exc}") from exc
    if len(buf) < len(MAGIC) + 2 + 4:
        raise FileFormatError(
            path, f"file too small for a tensor_file header ({len(buf)} bytes, needs >= 18)"
        )
    if buf[: len(MAGIC)] != MAGIC:
        raise FileFormatError(
            path, f"not a tensor_file: magic is {buf[:12]!r}, expected {MAGIC!r}", field="magic"
        )
    major, minor = buf[12], buf[13]
    if (major, minor) != VERSION:
        raise FileFormatError(
            path,
            f"unsupported tensor_file version {major}.{minor}, expected 1.0",
            field="version",
        )
    (n_fields,), pos = _unpack("<I", buf, 14, path, "the field count", None)
    if n_fields > _MAX_FIELDS:
        raise FileFormatError(path, f"implausible field count {n_fields}", field="n_fields")

    fields: dict[str, np.ndarray] = {}
    for k in range(n_fields):
        where = f"field #{k}"
        (name_len,), pos = _unpack("<H", buf, pos, path, f"the name length of {where}", None)
        if pos + name_len > len(buf):
            raise FileFormatError(path, f"file truncated in the name of {where}")
        try:
            name = buf[pos : pos + name_len].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise FileFormatError(path, f"name of {where} is not UTF-8") from exc
        pos += name_len
        (ndim, code, offset), pos = _unpack("<HBQ", buf, pos, path, "the field header", name)
        if ndim > _MAX_NDIM:
            raise FileFormatError(path, f"implausible number of dimensions {ndim}", field=name)
        shape, pos = _unpack(f"<{ndim}Q", buf, pos, path, "the field shape", name)
        if code not in DTYPE_CODES:
            raise FileFormatError(
                path,
                f"unknown dtype code {code} (expected 1..11, Mitsuba Struct::Type)",
                field=name,
            )
        if name in fields:
            raise FileFormatError(path, "field appears twice", field=name)
        dtype = DTYPE_CODES[code]
        count = int(np.prod(shape, dtype=np.uint64)) if ndim else 1
        end = offset + count * dtype.itemsize
        if end > len(buf):
            raise FileFormatError(
                path,
                f"data of shape {tuple(shape)} {dtype.name} at offset {offset} run to byte "
                f"{end}, past the end of the file ({len(buf)} bytes): truncated?",
                field=name,
            )
        arr = np.frombuffer(buf, dtype=dtype, count=count, offset=offset).reshape(shape)
        fields[name] = arr
    return fields


def write_tensor_file(path: str | Path, fields: dict[str, np.ndarray]) -> None:
    """Write ``fields`` as a tensor_file v1.0, data aligned to 8 bytes like the RGL files.

    Parameters
    ----------
    path
        Output file (overwritten).
    fields
        Name -> array; dtypes must be one of :data:`DTYPE_CODES` (little-endian).
    """
    arrays = {}
    for name, a in fields.items():
        a = np.ascontiguousarray(a)
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        dt = np.dtype(dt.str.replace("|", "<").replace("=", "<"))
        if dt not in _CODE_OF:
            raise ValueError(f"field {name!r}: dtype {a.dtype} cannot be stored in a tensor_file")
        arrays[name] = a.astype(dt, copy=False)

    header_len = len(MAGIC) + 2 + 4
    for name, a in arrays.items():
        header_len += 2 + len(name.encode()) + 2 + 1 + 8 + 8 * a.ndim

    def align(n: int) -> int:
        return (n + 7) // 8 * 8

    offsets, pos = {}, align(header_len)
    for name, a in arrays.items():
        offsets[name] = pos
        pos = align(pos + a.nbytes)

    out = bytearray(pos)
    out[: len(MAGIC)] = MAGIC
    out[12:14] = bytes(VERSION)
    struct.pack_into("<I", out, 14, len(arrays))
    hp = 18
    for name, a in arrays.items():
        nb = name.encode()
        struct.pack_into("<H", out, hp, len(nb))
        out[hp + 2 : hp + 2 + len(nb)] = nb
        hp += 2 + len(nb)
        struct.pack_into(
            f"<HBQ{a.ndim}Q", out, hp, a.ndim, _CODE_OF[a.dtype], offsets[name], *a.shape
        )
        hp += 11 + 8 * a.ndim
        out[offsets[name] : offsets[name] + a.nbytes] = a.tobytes()
    Path(path).write_bytes(bytes(out))

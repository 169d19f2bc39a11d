"""RAW frames as linear measurements on the Bayer mosaic.

A BRDF measurement wants the numbers the sensor counted, not a pretty picture: this module
decodes RAW files with rawpy (LibRaw) and stops before any demosaicing, white balance or
colour conversion.  What comes out is the mosaic in DN above the per-channel black level,
float64, with

- the CFA colour of every pixel (``R``, ``G``, ``B``; both greens are ``G``),
- a saturation mask (pixels at or near the white level, or on the linearisation table's
  ceiling),
- the exposure settings needed to normalise to a quantity proportional to radiance.

Linearisation tables (DNG ``LinearizationTable``, camera curves) are applied by LibRaw
while unpacking; ``raw_image_visible`` already holds linearised values.  The test-suite
verifies that on a real CinemaDNG with such a table.

Exposure normalisation: a pixel's signal in DN is proportional to
``L * t * (ISO / 100) / N**2`` (radiance, exposure time in s, ISO speed, f-number).
:meth:`RawFrame.exposure_factor` is that factor, so ``linear / exposure_factor`` is in
"DN per (s ISO/100 / N^2)", a relative radiance that the radiometric calibration turns into
absolute units.
"""

from __future__ import annotations

import io
import math
import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rawpy
from numpy.typing import ArrayLike, NDArray

from gonio.capture.plain_dng import direct_enabled, read_plain_dng
from gonio.errors import FileFormatError, ReductionError

#: Channel names in the order of the channel index used everywhere in the capture path.
CHANNELS: tuple[str, ...] = ("R", "G", "B")

#: Default fraction of the (white - black) range below the white level above which a
#: pixel counts as saturated.  Noise lets pixels whose mean is just below the clip level
#: clip sometimes; dropping only the clipped ones would bias the survivors low.  5 % of the
#: range is many standard deviations of shot noise for any real sensor near full well.
DEFAULT_SATURATION_MARGIN = 0.05

RawSource = str | os.PathLike | bytes | bytearray | io.IOBase


@dataclass(frozen=True)
class CameraSignature:
    """What every RAW file of one camera shares: CFA layout and visible size.

    Parameters
    ----------
    cfa_pattern
        The 2x2 CFA pattern, row-major, e.g. ``"RGGB"`` or ``"GRBG"``.
    shape
        Visible mosaic size ``(height, width)`` in pixels.
    """

    cfa_pattern: str
    shape: tuple[int, int]

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any]) -> CameraSignature | None:
        """Build from a manifest's camera section when it names the CFA and size."""
        pattern = m.get("cfa_pattern")
        shape = m.get("shape") or (
            (m["height"], m["width"]) if "height" in m and "width" in m else None
        )
        if not pattern or not shape:
            return None
        return cls(str(pattern).upper(), (int(shape[0]), int(shape[1])))


class RawFrame:
    """One decoded RAW frame on its mosaic.

    Decoded frames keep the camera's uint16 mosaic (a read-only view of LibRaw's own
    buffer, never copied) and compute float64 values lazily, for the whole frame
    (:attr:`linear`) or only for a crop (:meth:`region`): a reduction needs the sample's
    region of a large sensor, not all of it.

    Attributes
    ----------
    name
        The file the frame came from (for messages).
    linear
        (H, W) float64, DN above the per-channel black level (may be negative from noise).
    channel
        (H, W) int8 channel index into :data:`CHANNELS` (0 R, 1 G, 2 B).
    saturated
        (H, W) bool: the raw value is at or above the saturation threshold.
    black_level
        (H, W) float64 black level that was subtracted, DN.
    white_level
        Effective clip level in raw DN (the white level, or the linearisation table's
        ceiling when lower).
    cfa_pattern
        2x2 pattern, e.g. ``"RGGB"``.
    exposure_time, iso, f_number
        Exposure settings (s, ISO speed, f-number); NaN where the file does not say.
    camera
        Camera model as reported by the file, if any.
    """

    def __init__(
        self,
        name: str,
        linear: NDArray[np.float64] | None,
        channel: NDArray[np.int8] | None,
        saturated: NDArray[np.bool_] | None,
        black_level: NDArray[np.float64] | None,
        white_level: float,
        cfa_pattern: str,
        exposure_time: float = math.nan,
        iso: float = math.nan,
        f_number: float = math.nan,
        camera: str = "",
        extra: dict[str, Any] | None = None,
        *,
        raw: NDArray[np.uint16] | None = None,
        cell_channel: NDArray[np.int8] | None = None,
        cell_black: NDArray[np.float64] | None = None,
        saturation_threshold: NDArray[np.float64] | None = None,
    ) -> None:
        self.name = name
        self.white_level = float(white_level)
        self.cfa_pattern = cfa_pattern
        self.exposure_time = float(exposure_time)
        self.iso = float(iso)
        self.f_number = float(f_number)
        self.camera = camera
        self.extra = dict(extra or {})
        self._raw = raw
        self._cell_channel = cell_channel  # (2, 2) channel of each CFA position
        self._cell_black = cell_black  # (2, 2) black level of each CFA position
        self._cell_sat = saturation_threshold  # (2, 2) raw value from which it clips
        self._linear = linear
        self._channel = channel
        self._saturated = saturated
        self._black = black_level
        if raw is None and linear is None:
            raise ValueError("RawFrame needs either the raw mosaic or linear values")

    def _tile(self, cell: NDArray, box: tuple[slice, slice]) -> NDArray:
        r, c = box
        h, w = self.shape
        r0, r1, _ = r.indices(h)
        c0, c1, _ = c.indices(w)
        cell = np.roll(cell, (-(r0 % 2), -(c0 % 2)), axis=(0, 1))
        return np.tile(cell, ((r1 - r0 + 1) // 2, (c1 - c0 + 1) // 2))[: r1 - r0, : c1 - c0]

    @property
    def shape(self) -> tuple[int, int]:
        """Visible mosaic size (height, width)."""
        a = self._raw if self._raw is not None else self._linear
        return a.shape  # type: ignore[union-attr,return-value]

    def region(
        self, box: tuple[slice, slice] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.int8], NDArray[np.bool_]]:
        """``(linear, channel, saturated)`` of a crop, computed for the crop only."""
        box = box if box is not None else (slice(None), slice(None))
        if self._raw is None:
            return self.linear[box], self.channel[box], self.saturated[box]
        raw = self._raw[box]
        lin = raw - self._tile(self._cell_black, box)  # float64 by promotion
        sat = raw >= self._tile(self._cell_sat, box)
        if (off := self.extra.get("_offset")) is not None:
            lin -= off[box]
        if (gain := self.extra.get("_gain")) is not None:
            lin /= gain[box]
        return lin, self._tile(self._cell_channel, box), sat

    def clip_region(self, box: tuple[slice, slice] | None = None) -> NDArray[np.float64] | None:
        """The linear value (as :meth:`region` gives it: dark offset and flat gain applied)
        from which each pixel of a crop counts as saturated; None for a frame given as
        linear values (its saturation rule is not known)."""
        if self._raw is None or self._cell_sat is None:
            return None
        box = box if box is not None else (slice(None), slice(None))
        # the same operations in the same order as region()'s on the raw value
        clip = self._tile(self._cell_sat, box) - self._tile(self._cell_black, box)
        if (off := self.extra.get("_offset")) is not None:
            clip = clip - off[box]
        if (gain := self.extra.get("_gain")) is not None:
            clip = clip / gain[box]
        return clip

    @property
    def linear(self) -> NDArray[np.float64]:
        if self._linear is None:
            self._linear = self.region()[0]
        return self._linear

    @property
    def channel(self) -> NDArray[np.int8]:
        if self._channel is None:
            self._channel = self._tile(self._cell_channel, (slice(None), slice(None)))
        return self._channel

    @property
    def saturated(self) -> NDArray[np.bool_]:
        if self._saturated is None:
            self._saturated = self._raw >= self._tile(self._cell_sat, (slice(None), slice(None)))
        return self._saturated

    @property
    def black_level(self) -> NDArray[np.float64]:
        if self._black is None:
            self._black = self._tile(self._cell_black, (slice(None), slice(None)))
        return self._black

    def saturated_fraction(self, step: int = 8) -> float:
        """Fraction of saturated pixels, estimated on every ``step``-th cell (fast)."""
        if self._raw is None:
            return float(self.saturated[::step, ::step].mean())
        fr = [
            np.mean(self._raw[i::step, j::step] >= self._cell_sat[i, j])
            for i in range(2)
            for j in range(2)
        ]
        return float(np.mean(fr))

    @property
    def raw(self) -> NDArray[np.uint16] | None:
        """The camera's mosaic (raw DN with black level), when decoded from a file."""
        return self._raw

    @property
    def cell_saturation(self) -> NDArray[np.float64] | None:
        """(2, 2) raw value from which each CFA position counts as saturated, when
        decoded from a file."""
        return self._cell_sat

    @property
    def cell_black(self) -> NDArray[np.float64] | None:
        """(2, 2) black level of each CFA position, when decoded from a file."""
        return self._cell_black

    @property
    def cell_channel(self) -> NDArray[np.int8]:
        """(2, 2) channel index of each CFA position."""
        if self._cell_channel is None:
            return self.channel[:2, :2]
        return self._cell_channel

    @property
    def signature(self) -> CameraSignature:
        """CFA pattern and size, to compare with the session's camera."""
        return CameraSignature(self.cfa_pattern, self.shape)

    @property
    def headroom(self) -> NDArray[np.float64]:
        """Largest linear value a pixel can hold before it clips, DN (white - black)."""
        if self._cell_black is not None:
            return self.white_level - self._cell_black
        return self.white_level - self.black_level

    def exposure_factor(self, iso_reference: float = 100.0) -> float:
        """``t * (ISO / iso_reference) / N**2``: what the DN scale with at fixed radiance.

        Raises
        ------
        ReductionError
            If exposure time, ISO or f-number is unknown (NaN) or not positive.
        """
        return exposure_factor(
            self.exposure_time, self.iso, self.f_number, iso_reference, name=self.name
        )

    def _copy(self, **kw: Any) -> RawFrame:
        new = RawFrame.__new__(RawFrame)
        new.__dict__.update(self.__dict__)
        new.extra = dict(self.extra)
        for k, v in kw.items():
            setattr(new, k, v)
        return new

    def with_exposure(
        self,
        exposure_time: float | None = None,
        iso: float | None = None,
        f_number: float | None = None,
    ) -> RawFrame:
        """A copy with exposure settings filled in (e.g. from the session journal)."""
        kw = {
            k: float(v)
            for k, v in dict(exposure_time=exposure_time, iso=iso, f_number=f_number).items()
            if v is not None
        }
        return self._copy(**kw)

    def __repr__(self) -> str:
        return (
            f"RawFrame({self.name!r}, {self.cfa_pattern}, {self.shape[0]}x{self.shape[1]}, "
            f"t={self.exposure_time:g} s, ISO {self.iso:g}, f/{self.f_number:g})"
        )


def exposure_factor(
    exposure_time: float,
    iso: float,
    f_number: float,
    iso_reference: float = 100.0,
    name: str = "frame",
) -> float:
    """Scale of the DN with exposure: ``t * (ISO / iso_reference) / N**2``.

    Parameters
    ----------
    exposure_time
        Exposure time in s.
    iso
        ISO speed (the sensor gain is taken proportional to it).
    f_number
        Aperture f-number N (the irradiance on the sensor goes as 1/N^2).
    iso_reference
        ISO speed at which the factor is ``t / N**2``.
    """
    vals = {"exposure_time": exposure_time, "iso": iso, "f_number": f_number}
    for k, v in vals.items():
        if not (v is not None and np.isfinite(v) and v > 0):
            raise ReductionError(
                f"{name}: {k} is {v!r}; a positive value is needed to normalise the exposure"
            )
    return float(exposure_time) * float(iso) / iso_reference / float(f_number) ** 2


def _name_of(source: RawSource, name: str | None) -> str:
    if name:
        return name
    if isinstance(source, (str, os.PathLike)):
        return str(source)
    return "<bytes>"


def read_file(path: str | os.PathLike) -> bytes:
    """A whole file's bytes in one read into one buffer.

    ``Path.read_bytes`` goes through a ``BufferedReader``, which reads in chunks and joins
    them: on a 4 MB RAW file that costs 5x the read itself.
    """
    with open(path, "rb", buffering=0) as fh:
        return fh.readall()


def _read_bytes(source: RawSource, name: str) -> bytes:
    if isinstance(source, (bytes, bytearray)):
        return bytes(source)
    if isinstance(source, io.IOBase):
        return source.read()
    p = Path(source)
    if not p.is_file():
        raise FileFormatError(name, "no such RAW file")
    return read_file(p)


_DATA_TAGS = ((273, 279), (324, 325))  # (StripOffsets, StripByteCounts), tile offsets/counts
_SUBIFDS = 330
_TIFF_INTS = {3: "u2", 4: "u4", 13: "u4"}  # SHORT, LONG, IFD


def tiff_data_end(data: bytes) -> int | None:
    """Byte just past the last image strip or tile of a classic TIFF/DNG, over every IFD
    of the main chain and their SubIFDs (where a DNG keeps its raw image); 0 if there is
    none, None when ``data`` is not a classic (32-bit offset) TIFF.

    Written by hand rather than with tifffile, which parses every tag of every page:
    about 0.5 ms of Python per frame, holding the GIL, in a reduction whose decoding
    runs in another thread.  This reads only the tags that locate the image data.

    Raises
    ------
    ValueError
        When an IFD or a tag's values lie outside the file (a damaged structure).
    """
    if len(data) < 8 or data[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    e = "<" if data[:2] == b"II" else ">"
    end = 0
    todo = [struct.unpack_from(e + "I", data, 4)[0]]
    seen: set[int] = set()
    while todo:
        off = todo.pop()
        if off == 0 or off in seen:
            continue
        if len(seen) >= 256:
            raise ValueError("more than 256 IFDs")
        seen.add(off)
        if off + 2 > len(data):
            raise ValueError(f"an IFD at byte {off} is past the end")
        n = struct.unpack_from(e + "H", data, off)[0]
        if off + 2 + 12 * n + 4 > len(data):
            raise ValueError(f"the IFD at byte {off} runs past the end")
        tags: dict[int, np.ndarray] = {}
        for k in range(n):
            tag, typ, cnt = struct.unpack_from(e + "HHI", data, off + 2 + 12 * k)
            if tag not in (273, 279, 324, 325, _SUBIFDS):
                continue
            if typ not in _TIFF_INTS:
                raise ValueError(f"tag {tag} has TIFF type {typ}, not an integer")
            dt = np.dtype(e + _TIFF_INTS[typ])
            at = off + 2 + 12 * k + 8
            if cnt * dt.itemsize > 4:  # the field holds the values' offset
                at = struct.unpack_from(e + "I", data, at)[0]
                if at + cnt * dt.itemsize > len(data):
                    raise ValueError(f"tag {tag}'s values run past the end")
            tags[tag] = np.frombuffer(data, dt, cnt, at).astype(np.int64)
        for offs_tag, counts_tag in _DATA_TAGS:
            offs, counts = tags.get(offs_tag), tags.get(counts_tag)
            if offs is not None and counts is not None and offs.size and counts.size:
                m = min(offs.size, counts.size)
                end = max(end, int((offs[:m] + counts[:m]).max()))
        todo.extend(int(x) for x in tags.get(_SUBIFDS, ()))
        todo.append(struct.unpack_from(e + "I", data, off + 2 + 12 * n)[0])
    return end


def _check_tiff_strips(data: bytes, name: str) -> None:
    """Refuse TIFF/DNG files whose image strips or tiles run past the end of the file.

    LibRaw fills the missing part of an uncompressed, truncated DNG with zeros instead of
    failing; the strip table tells us the file is short, so say so.
    """
    try:
        end = tiff_data_end(data)
    except ValueError as exc:
        raise FileFormatError(name, f"damaged TIFF structure ({exc})") from None
    if end is not None and end > len(data):
        raise FileFormatError(
            name,
            f"truncated: image data run to byte {end} but the file has {len(data)} bytes",
            "StripOffsets",
        )


def _open(data: bytes, name: str) -> rawpy.RawPy:
    try:
        raw = rawpy.imread(io.BytesIO(data))
        raw.raw_image_visible  # noqa: B018 (forces unpack: errors surface here)
    except rawpy.LibRawFileUnsupportedError:
        raise FileFormatError(name, "not a RAW file LibRaw can read") from None
    except (rawpy.LibRawIOError, rawpy.LibRawDataError) as exc:
        raise FileFormatError(name, f"corrupt or truncated RAW file ({exc})") from None
    except rawpy.LibRawError as exc:
        raise FileFormatError(name, f"LibRaw cannot decode it ({exc})") from None
    return raw


def cfa_pattern_of(raw: rawpy.RawPy) -> str:
    """The 2x2 CFA pattern of an open rawpy image as letters, e.g. ``"GRBG"``."""
    desc = raw.color_desc.decode()
    pat = raw.raw_pattern
    if pat is None or pat.shape != (2, 2):
        raise ReductionError(f"unsupported CFA (pattern {pat!r}); only 2x2 Bayer is handled")
    return "".join(desc[i] for i in pat.ravel())


def read_raw(
    source: RawSource,
    *,
    name: str | None = None,
    expect: CameraSignature | None = None,
    saturation_margin: float = DEFAULT_SATURATION_MARGIN,
) -> RawFrame:
    """Decode a RAW file to a linear mosaic without demosaicing.

    Parameters
    ----------
    source
        Path, bytes or binary file object of a RAW file (DNG, or any format LibRaw reads).
    name
        Name used in error messages (defaults to the path).
    expect
        The session camera's CFA pattern and size; a frame that differs is refused.
    saturation_margin
        Fraction of the (white - black) range below the clip level from which pixels are
        marked saturated (0 marks only pixels at the clip level).

    Returns
    -------
    RawFrame
        Linear values in DN above black, channel map, saturation mask and exposure.

    Raises
    ------
    FileFormatError
        Missing, truncated, corrupt or unsupported file; or (field ``CFAPattern`` /
        ``ImageSize``) a frame that does not match ``expect``.
    """
    nm = _name_of(source, name)
    data = _read_bytes(source, nm)
    if len(data) == 0:
        raise FileFormatError(nm, "empty file")
    _check_tiff_strips(data, nm)
    plain = read_plain_dng(data) if direct_enabled() else None
    if plain is not None:  # the simulator's DNG: its strip is the mosaic (plain_dng)
        pattern, mosaic, white = plain.cfa_pattern, plain.mosaic, plain.white_level
        cell_channel = np.array([CHANNELS.index(ch) for ch in pattern], dtype=np.int8).reshape(2, 2)
        cell_black = plain.cell_black
        exp = dict(exposure_time=plain.exposure_time, iso=plain.iso, f_number=plain.f_number)
        handle = None  # nothing to close: the mosaic is a view of ``data``
    else:
        pattern, mosaic, cell_channel, cell_black, white, exp, handle = _libraw_decode(data, nm)
    if expect is not None:
        if pattern != expect.cfa_pattern:
            if handle is not None:
                handle.close()
            raise FileFormatError(
                nm,
                f"CFA pattern is {pattern}, the session's camera has {expect.cfa_pattern}",
                "CFAPattern",
            )
        if tuple(mosaic.shape) != tuple(expect.shape):
            if handle is not None:
                handle.close()
            raise FileFormatError(
                nm,
                f"mosaic is {mosaic.shape[0]}x{mosaic.shape[1]}, the "
                f"session's camera gives {expect.shape[0]}x{expect.shape[1]}",
                "ImageSize",
            )
    if not 0.0 <= saturation_margin < 1.0:
        raise ValueError(f"saturation_margin must be in [0, 1), got {saturation_margin}")
    threshold = white - saturation_margin * (white - cell_black)
    return RawFrame(
        nm,
        None,
        None,
        None,
        None,
        white,
        pattern,
        **exp,
        raw=mosaic,
        cell_channel=cell_channel,
        cell_black=cell_black,
        saturation_threshold=threshold,
    )


def _libraw_decode(
    data: bytes, nm: str
) -> tuple[str, NDArray[np.uint16], NDArray[np.int8], NDArray[np.float64], float, dict, Any]:
    """``(pattern, mosaic, cell_channel, cell_black, white, exposure, handle)`` by LibRaw."""
    # The handle is not closed here: the mosaic below is a view of LibRaw's buffer (which
    # keeps the handle alive and frees it with the last view), so the full frame is never
    # copied.  A copy of a fresh 4-bytes-per-2-pixels buffer costs half an unpack.
    raw = _open(data, nm)
    try:
        pattern = cfa_pattern_of(raw)
        desc = raw.color_desc.decode()
        # raw colour index (0..3) -> our channel (R, G, B); the second green is 'G' too
        lut = np.array([CHANNELS.index(ch) if ch in CHANNELS else -1 for ch in desc], dtype=np.int8)
        if (lut < 0).any():
            raise FileFormatError(
                nm, f"colour filter '{desc}' is not an RGB Bayer filter", "CFAPattern"
            )
        sz = raw.sizes
        # the 2x2 cell at the visible origin (raw_colors_visible would build a full-size
        # array just to read four values)
        colors = np.array(
            [
                [raw.raw_color(i + sz.top_margin, j + sz.left_margin) for j in range(2)]
                for i in range(2)
            ]
        )
        cell_channel = lut[colors]
        cell_black = np.asarray(raw.black_level_per_channel, dtype=np.float64)[colors]
        white = float(raw.white_level)
        # With a linearisation table LibRaw maps codes through it; its ceiling, not the
        # nominal white level, is where the sensor clipped.
        curve = raw.tone_curve
        if curve is not None and curve.size and int(curve.max()) > 0:
            white = min(white, float(curve.max()))
        other = raw.other
        exp = dict(
            exposure_time=float(other.shutter_speed) or math.nan,
            iso=float(other.iso_speed) or math.nan,
            f_number=float(other.aperture) or math.nan,
        )
        mosaic = raw.raw_image_visible
        if mosaic.dtype != np.uint16:  # pragma: no cover (LibRaw's mosaic is uint16)
            mosaic = mosaic.astype(np.uint16)
        mosaic.flags.writeable = False  # a view of LibRaw's buffer: read-only by contract
    except BaseException:
        raw.close()
        raise
    return pattern, mosaic, cell_channel, cell_black, white, exp, raw


def subtract_dark(frame: RawFrame, dark: RawFrame | NDArray[np.float64]) -> RawFrame:
    """Subtract a dark frame (or a master dark, in linear DN above black).

    A dark frame shot with the same exposure time and ISO removes dark current and fixed
    pattern offsets on top of the black level.  Saturation is carried over from ``frame``.
    """
    d = dark.linear if isinstance(dark, RawFrame) else np.asarray(dark, dtype=np.float64)
    if d.shape != frame.shape:
        raise ReductionError(f"{frame.name}: dark frame is {d.shape}, frame is {frame.shape}")
    return _with_offset(frame, d, None)


def _with_offset(frame: RawFrame, offset: NDArray | None, gain: NDArray | None) -> RawFrame:
    """A frame whose linear values are ``(linear - offset) / gain``, applied per crop."""
    prev_offset = frame.extra.get("_offset")
    prev_gain = frame.extra.get("_gain")
    if offset is not None and prev_gain is not None:
        raise ReductionError(f"{frame.name}: subtract the dark before applying the flat field")
    new = frame._copy(_linear=None)
    if offset is not None:
        new.extra["_offset"] = offset if prev_offset is None else prev_offset + offset
    if gain is not None:
        new.extra["_gain"] = gain if prev_gain is None else prev_gain * gain
    if frame._raw is None:  # built from arrays: apply now
        lin = frame.linear
        if offset is not None:
            lin = lin - offset
        if gain is not None:
            lin = lin / gain
        new._linear = lin
        new.extra.pop("_offset", None)
        new.extra.pop("_gain", None)
    return new


def master_flat(flats: list[RawFrame], darks: list[RawFrame] | None = None) -> NDArray[np.float64]:
    """A flat-field gain map: mean of the flats, dark-subtracted, normalised to 1 per channel.

    Returns
    -------
    ndarray
        (H, W) relative pixel response; divide a frame's ``linear`` by it.
    """
    if not flats:
        raise ReductionError("master_flat needs at least one flat frame")
    mean = np.mean([f.linear for f in flats], axis=0)
    if darks:
        mean = mean - np.mean([d.linear for d in darks], axis=0)
    ch = flats[0].channel
    out = np.empty_like(mean)
    for c in range(len(CHANNELS)):
        m = ch == c
        level = mean[m].mean()
        if not level > 0:
            raise ReductionError(f"flat frames have no signal in channel {CHANNELS[c]}")
        out[m] = mean[m] / level
    return out


def apply_flat(frame: RawFrame, flat: NDArray[np.float64]) -> RawFrame:
    """Divide a frame by a flat-field gain map from :func:`master_flat`."""
    flat = np.asarray(flat, dtype=np.float64)
    if flat.shape != frame.shape:
        raise ReductionError(f"{frame.name}: flat field is {flat.shape}, frame is {frame.shape}")
    return _with_offset(frame, None, flat)


@dataclass(frozen=True)
class ChannelStats:
    """Per-channel statistics of a region of a mosaic (arrays indexed like :data:`CHANNELS`)."""

    mean: NDArray[np.float64]
    std: NDArray[np.float64]
    count: NDArray[np.int64]
    saturated_fraction: NDArray[np.float64]


def channel_stats(frame: RawFrame, mask: ArrayLike | None = None) -> ChannelStats:
    """Mean, standard deviation, pixel count and saturated fraction per CFA channel.

    Parameters
    ----------
    frame
        A decoded frame.
    mask
        (H, W) boolean region of interest; the whole frame when omitted.
    """
    m = np.ones(frame.shape, bool) if mask is None else np.asarray(mask, dtype=bool)
    n = len(CHANNELS)
    ch = frame.channel[m].astype(np.intp)
    v = frame.linear[m]
    count = np.bincount(ch, minlength=n)
    s1 = np.bincount(ch, v, minlength=n)
    s2 = np.bincount(ch, v * v, minlength=n)
    sat = np.bincount(ch, frame.saturated[m].astype(np.float64), minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / count
        var = (s2 - count * mean**2) / np.maximum(count - 1, 1)
        return ChannelStats(mean, np.sqrt(np.maximum(var, 0.0)), count, sat / count)


@dataclass(frozen=True)
class ExposureStats:
    """What the adaptive bracketing needs to know about one frame's region of interest.

    Attributes
    ----------
    saturated_fraction
        Fraction of ROI pixels (all channels) at or near the clip level, 0..1.
    signal_dn
        Per channel (R, G, B), median linear signal above black in the ROI, DN.
    snr
        Per channel, ``signal_dn / noise`` with the noise from the photon-transfer model
        when given, else from the pixel scatter in the ROI (which also contains texture).
    headroom_dn
        Linear DN available before clipping (white - black), the smallest over the ROI.
    """

    saturated_fraction: float
    signal_dn: NDArray[np.float64]
    snr: NDArray[np.float64]
    headroom_dn: float


def roi_exposure_stats(
    source: RawSource | RawFrame,
    roi: ArrayLike | tuple[slice, slice] | None = None,
    noise: Any | None = None,
) -> ExposureStats:
    """Is a frame's region of interest saturated, and how far above the noise is it?

    The session's adaptive bracketing calls this after every shot: add a shorter frame
    while ``saturated_fraction > 0``, a longer one while ``snr`` is too low.

    Parameters
    ----------
    source
        RAW file path, bytes, file object, or an already decoded :class:`RawFrame`.
    roi
        Region of interest: a boolean (H, W) mask, a ``(row_slice, col_slice)`` tuple, or
        ``(row0, row1, col0, col1)`` pixel bounds; the whole frame when None.
    noise
        Optional :class:`gonio.capture.noise.NoiseModel` (gain, read noise) for the SNR.

    Returns
    -------
    ExposureStats
    """
    frame = source if isinstance(source, RawFrame) else read_raw(source)
    return _exposure_stats(frame, roi_mask(frame.shape, roi), noise)


def _exposure_stats(
    frame: RawFrame, mask: NDArray[np.bool_], noise: Any | None, fast: bool = True
) -> ExposureStats:
    """:func:`roi_exposure_stats` of a decoded frame; ``fast=False``: the general path
    only (the fast one's oracle in the tests)."""
    if not mask.any():
        raise ReductionError(f"{frame.name}: region of interest is empty")
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    m = mask[box]
    n = len(CHANNELS)
    sig = np.full(n, np.nan)
    snr = np.full(n, np.nan)
    fast = _box_mosaic_stats(frame, box) if fast and m.all() else None
    if fast is not None:
        values, medians, sat_fraction = fast
    else:
        lin, chan, sat = frame.region(box)  # only the ROI's bounding box is converted
        values = [lin[m & (chan == c)] for c in range(n)]
        medians = [float(np.median(v)) if v.size else math.nan for v in values]
        sat_fraction = float(sat[m].mean())
    for c in range(n):
        v = values[c]
        if v.size == 0:
            continue
        sig[c] = medians[c]
        if noise is not None:
            sd = math.sqrt(max(float(noise.variance(max(sig[c], 0.0), iso=frame.iso)), 1e-300))
        else:
            sd = float(np.std(v)) if v.size > 1 else math.nan
        snr[c] = sig[c] / sd if sd > 0 else math.inf
    black = frame.black_level[box][m] if frame.cell_black is None else frame.cell_black
    return ExposureStats(
        saturated_fraction=sat_fraction,
        signal_dn=sig,
        snr=snr,
        headroom_dn=float(frame.white_level - np.max(black)),
    )


#: Flat indices, row-major, of each channel's pixels in a box: keyed by the box's size,
#: its CFA phase and the 2 x 2 channel layout (a session's frames share one or two).
_CHANNEL_INDEX: dict[tuple, tuple[NDArray[np.intp], ...]] = {}


def _channel_index(cell_channel: NDArray, phase: tuple[int, int], shape: tuple[int, int]):
    key = (shape, phase, cell_channel.tobytes())
    idx = _CHANNEL_INDEX.get(key)
    if idx is None:
        cell = np.roll(cell_channel, (-phase[0], -phase[1]), axis=(0, 1))
        h, w = shape
        chan = np.tile(cell, ((h + 1) // 2, (w + 1) // 2))[:h, :w].ravel()
        idx = tuple(np.flatnonzero(chan == c) for c in range(len(CHANNELS)))
        if len(_CHANNEL_INDEX) > 64:  # bounded: ROIs are per plan, not per frame
            _CHANNEL_INDEX.clear()
        _CHANNEL_INDEX[key] = idx
    return idx


def _median_of_counts(values: NDArray, black: float) -> float:
    """``np.median(values - black)`` of non-negative integers, from their histogram.

    The middle order statistic(s) are found in the counts (linear time, no partition of
    a float copy); the result is formed with numpy's own operations on them -- the
    element itself for an odd count, the two middle ones' sum over 2 for an even one --
    so it is the same float64 as ``np.median``'s.
    """
    cum = np.cumsum(np.bincount(values))
    n = int(cum[-1])
    lo = np.float64(np.searchsorted(cum, (n - 1) // 2, side="right")) - black
    if n % 2:
        return float(lo)
    hi = np.float64(np.searchsorted(cum, n // 2, side="right")) - black
    return float((lo + hi) / 2.0)


def _box_mosaic_stats(frame: RawFrame, box: tuple[slice, slice]):
    """Per channel the linear values (row-major, as a mask would select them) and their
    medians, and the saturated fraction, of a whole box of an undecoded mosaic; None
    where the general path is needed (no integer mosaic, an offset or gain map, a
    channel whose CFA positions differ in black level).

    The bracket calls this on every shot: the general path converts the whole box to
    float64, selects each channel through boolean masks and partitions float copies
    (~5 ms for a 320 x 240 frame); here each channel is gathered with cached indices
    and its median taken from a histogram of the raw integers -- the same values.
    """
    raw, cell_ch, cell_black = frame.raw, frame.cell_channel, frame.cell_black
    cell_sat = frame.cell_saturation
    if (
        raw is None
        or cell_ch is None
        or cell_black is None
        or cell_sat is None
        or raw.dtype.kind != "u"
        or "_offset" in frame.extra
        or "_gain" in frame.extra
    ):
        return None
    sub = raw[box]
    h, w = sub.shape
    r0, c0 = box[0].indices(raw.shape[0])[0], box[1].indices(raw.shape[1])[0]
    phase = (r0 % 2, c0 % 2)
    flat = sub.ravel()
    values, medians = [], []
    for c, idx in enumerate(_channel_index(cell_ch, phase, (h, w))):
        blacks = {float(cell_black[i, j]) for i in range(2) for j in range(2) if cell_ch[i, j] == c}
        if len(blacks) > 1:
            return None
        if idx.size == 0:
            values.append(np.empty(0))
            medians.append(math.nan)
            continue
        b = blacks.pop()
        vr = flat[idx]
        values.append(vr.astype(np.float64) - b)
        medians.append(_median_of_counts(vr, b))
    n_sat = 0
    for i in range(2):
        for j in range(2):
            part = sub[i::2, j::2]
            if part.size:
                n_sat += int(np.count_nonzero(part >= cell_sat[(r0 + i) % 2, (c0 + j) % 2]))
    return values, medians, n_sat / float(h * w)


def roi_mask(shape: tuple[int, int], roi: Any) -> NDArray[np.bool_]:
    """A boolean mask from a mask, a ``(slice, slice)`` pair or ``(r0, r1, c0, c1)`` bounds."""
    if roi is None:
        return np.ones(shape, bool)
    if isinstance(roi, tuple) and len(roi) == 2 and all(isinstance(s, slice) for s in roi):
        m = np.zeros(shape, bool)
        m[roi] = True
        return m
    a = np.asarray(roi)
    if a.dtype == bool:
        if a.shape != tuple(shape):
            raise ReductionError(f"ROI mask is {a.shape}, frame is {tuple(shape)}")
        return a
    if a.shape == (4,):
        r0, r1, c0, c1 = (int(x) for x in a)
        m = np.zeros(shape, bool)
        m[r0:r1, c0:c1] = True
        return m
    raise ReductionError(f"cannot use {roi!r} as a region of interest")

"""DNG files from the simulator read back with rawpy (LibRaw) and exifread."""

from __future__ import annotations

import io

import exifread
import numpy as np
import pytest
import rawpy
import tifffile

from gonio.errors import FileFormatError
from gonio.simulator.dng import dng_bytes, write_dng
from gonio.simulator.scene import Camera
from gonio.simulator.sensor import simulate_raw


def frame(pattern="RGGB", seed=3, **kw):
    cam = Camera(
        resolution=(64, 48),
        focal_length=0.035,
        pixel_pitch=5e-6,
        position=(0, 0, 1),
        sensor=dict(
            cfa_pattern=pattern, black_level=600, bits=12, quantum_efficiency=(0.4, 0.5, 0.35)
        ),
    )
    rad = np.random.default_rng(0).uniform(0, 0.3, (48, 64, 3))
    return simulate_raw(rad, cam, exposure_time=1 / 125, iso=800, f_number=5.6, seed=seed, **kw)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_rawpy_reads_mosaic_and_metadata(pattern):
    fr = frame(pattern)
    assert 600 < fr.mosaic.mean() < 4095  # a real signal, not clipped
    with rawpy.imread(io.BytesIO(dng_bytes(fr))) as raw:
        assert np.array_equal(raw.raw_image_visible, fr.mosaic)
        desc = raw.color_desc.decode()
        assert "".join(desc[i] for i in raw.raw_pattern.ravel()) == pattern
        assert list(raw.black_level_per_channel) == [600] * 4
        assert raw.white_level == 4095
        wb = np.array(raw.camera_whitebalance[:3])
        assert np.allclose(wb / wb[1], 1 / fr.as_shot_neutral, rtol=1e-4)
        other = raw.other
        assert np.isclose(other.shutter_speed, 1 / 125, rtol=1e-6)
        assert np.isclose(other.aperture, 5.6, rtol=1e-6)
        assert other.iso_speed == 800
        assert np.isclose(other.focal_length, 35.0)
        # LibRaw turns ColorMatrix1 (XYZ -> camera) into camera -> sRGB the DNG way:
        # cam_rgb = CM @ sRGB_to_XYZ with rows normalised to 1, then inverted.
        import colour

        cam_rgb = fr.colour_matrix @ colour.models.RGB_COLOURSPACE_sRGB.matrix_RGB_to_XYZ
        cam_rgb /= cam_rgb.sum(1, keepdims=True)
        assert np.allclose(raw.color_matrix[:, :3], np.linalg.inv(cam_rgb), atol=1e-3)


def test_colour_matrix_and_neutral_tags():
    fr = frame()
    data = dng_bytes(fr)
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        tags = tif.pages[0].tags
        cm = np.array(tags[50721].value, float).reshape(9, 2)
        neutral = np.array(tags[50728].value, float).reshape(3, 2)
        assert tags[50778].value == 21  # D65
        assert bytes(tags[50706].value) == b"\x01\x04\x00\x00"
    assert np.allclose((cm[:, 0] / cm[:, 1]).reshape(3, 3), fr.colour_matrix, atol=1e-4)
    assert np.allclose(neutral[:, 0] / neutral[:, 1], fr.as_shot_neutral, atol=1e-5)
    # The DNG convention: the calibration illuminant's white maps to the neutral.
    xyz_d65 = np.array([0.95047, 1.0, 1.08883])
    cam = fr.colour_matrix @ xyz_d65
    assert np.allclose(cam / cam[1], fr.as_shot_neutral, rtol=2e-3)
    exif = exifread.process_file(io.BytesIO(data), details=False)
    assert str(exif["EXIF ISOSpeedRatings"]) == "800"
    assert str(exif["EXIF ExposureTime"]) == "1/125"


def test_same_seed_same_bytes():
    assert dng_bytes(frame(seed=5)) == dng_bytes(frame(seed=5))
    assert dng_bytes(frame(seed=5)) != dng_bytes(frame(seed=6))


def test_write_dng_is_atomic_and_never_overwrites(tmp_path):
    p = write_dng(tmp_path / "a.dng", frame())
    before = p.read_bytes()
    with pytest.raises(FileFormatError, match="refusing to overwrite"):
        write_dng(p, frame(seed=9))
    assert p.read_bytes() == before
    write_dng(p, frame(seed=9), overwrite=True)
    assert p.read_bytes() != before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.dng"]


def test_template_bytes_are_tifffiles_bytes():
    """A frame's file from its metadata's cached template is, byte for byte, the file
    tifffile and the EXIF patch write for it (the reference), whatever the size, the
    exposure, the pattern or the order in which templates are made and evicted."""
    from gonio.simulator import dng

    rng = np.random.default_rng(7)
    shots = []
    for pattern in ("RGGB", "BGGR"):
        for exposure in (1 / 125, 1 / 60, 0.02, 1 / 125):  # the last one: a cached template
            fr = frame(pattern, seed=int(rng.integers(1 << 30)))
            fr.exposure_time = exposure
            shots.append(fr)
    odd = frame()
    odd.mosaic = rng.integers(0, 4096, (7, 9)).astype(np.uint16)  # odd sizes, one strip
    shots.append(odd)
    for fr in shots:
        assert dng_bytes(fr) == dng._dng_bytes_tifffile(fr, fr.mosaic)
    # more metadata than the cache holds: evicted templates are rebuilt the same
    for i in range(dng._TEMPLATES_SIZE + 3):
        fr = frame(seed=i)
        fr.iso = 100 + i
        assert dng_bytes(fr) == dng._dng_bytes_tifffile(fr, fr.mosaic)
    assert len(dng._TEMPLATES) <= dng._TEMPLATES_SIZE
    # the pixels do reach the file: two mosaics of the same metadata give two files
    a, b = frame(seed=1), frame(seed=2)
    assert not np.array_equal(a.mosaic, b.mosaic) and dng_bytes(a) != dng_bytes(b)


def test_colour_constants_are_colour_sciences():
    """The sRGB matrix and D65 white the DNG's ColorMatrix1 is built from are
    colour-science's, bit for bit (they are literals so the camera does not import it)."""
    import colour

    from gonio.simulator import sensor

    m = np.asarray(colour.models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB, float)
    assert np.array_equal(sensor._XYZ_TO_SRGB, m)
    assert np.array_equal(sensor._D65_XYZ, np.asarray(colour.xy_to_XYZ([0.3127, 0.3290])))

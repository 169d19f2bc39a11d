"""RAW decoding on the mosaic, checked against rawpy's own linear output on real files."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy

from gonio.capture.raw import (
    CameraSignature,
    channel_stats,
    exposure_factor,
    read_raw,
    roi_exposure_stats,
)
from gonio.errors import FileFormatError, ReductionError

# rawpy's linear output (see shared/reference/libraries.md); half_size puts one 2x2 CFA
# cell into one output pixel, the two greens averaged (and floored) by LibRaw.
LINEAR = dict(
    half_size=True,
    gamma=(1, 1),
    no_auto_bright=True,
    output_bps=16,
    use_camera_wb=False,
    user_wb=[1, 1, 1, 1],
    output_color=rawpy.ColorSpace.raw,
    adjust_maximum_thr=0,
)


def _half_size_from_mosaic(frame):
    """Our linear mosaic folded to LibRaw's half-size layout: (H/2, W/2, 3), G averaged."""
    h, w = frame.shape
    v = frame.linear[: h // 2 * 2, : w // 2 * 2].reshape(h // 2, 2, w // 2, 2)
    c = frame.channel[:2, :2]
    out = np.zeros((h // 2, w // 2, 3))
    cnt = np.zeros(3)
    for i in range(2):
        for j in range(2):
            out[..., c[i, j]] += v[:, i, :, j]
            cnt[c[i, j]] += 1
    return out / cnt


@pytest.mark.parametrize(
    "fname, pattern, black, white",
    [("Blackmagic.dng", "RGGB", 512, 65472), ("RAW_KODAK_DC50.KDC", "GRBG", 0, 16383)],
)
def test_real_files_match_rawpy_linear_half_size(refdata, fname, pattern, black, white):
    path = refdata / "raw" / fname
    frame = read_raw(path)
    assert frame.cfa_pattern == pattern
    assert np.all(frame.black_level == black)
    assert frame.white_level == white  # the linearisation table's ceiling for the DNG
    ours = np.maximum(_half_size_from_mosaic(frame), 0.0)  # LibRaw clips below black
    with rawpy.imread(str(path)) as raw:
        # black subtracted by LibRaw, no scaling: the same DN scale as ours
        plain = raw.postprocess(no_auto_scale=True, **LINEAR).astype(np.float64)
        # LibRaw's default scaling to 16 bits: (v - black) * 65535 / (white - black)
        scaled = raw.postprocess(**LINEAR).astype(np.float64)
        scale_max = raw.white_level  # LibRaw scales by its nominal maximum
    assert plain.shape == ours.shape
    assert np.max(np.abs(plain - ours)) <= 1.0
    # R and B are single pixels: LibRaw rounds once; green it averages already-scaled,
    # rounded values, hence the test on R and B only for the scaled output.
    s = 65535.0 / (scale_max - black)
    for c in (0, 2):
        assert np.max(np.abs(scaled[..., c] - np.clip(ours[..., c] * s, 0, 65535))) <= 1.0


def test_linearisation_table_is_applied(refdata):
    """Every decoded code of the CinemaDNG is an output value of its LinearizationTable."""
    path = refdata / "raw" / "Blackmagic.dng"
    with rawpy.imread(str(path)) as raw:
        table = raw.tone_curve.copy()
        values = np.unique(raw.raw_image_visible)
    assert table.max() == 65472 and not np.array_equal(table[:4096], np.arange(4096))
    assert np.isin(values, table[:4096]).all()
    frame = read_raw(path)
    # pixels on the table's ceiling are marked saturated
    raw_codes = frame.linear + frame.black_level
    assert np.array_equal(
        frame.saturated[raw_codes >= 65472], np.ones((raw_codes >= 65472).sum(), bool)
    )


def test_kodak_exposure_metadata(refdata):
    frame = read_raw(refdata / "raw" / "RAW_KODAK_DC50.KDC")
    assert frame.exposure_time == pytest.approx(0.00435, rel=1e-6)
    assert frame.iso == pytest.approx(84.0)
    assert frame.f_number == pytest.approx(6.2, rel=1e-6)
    assert frame.exposure_factor() == pytest.approx(0.00435 * 0.84 / 6.2**2, rel=1e-6)


def test_exposure_factor_scales_as_t_iso_over_n2():
    assert exposure_factor(0.01, 100, 8) == pytest.approx(0.01 / 64)
    assert exposure_factor(0.02, 400, 4) == pytest.approx(0.02 * 4 / 16)
    with pytest.raises(ReductionError, match="f_number"):
        exposure_factor(0.01, 100, float("nan"), name="x.dng")


def test_channel_stats_per_cfa_colour(refdata):
    frame = read_raw(refdata / "raw" / "RAW_KODAK_DC50.KDC")
    st = channel_stats(frame)
    # GRBG: greens at (0,0) and (1,1)
    g = np.concatenate([frame.linear[0::2, 0::2].ravel(), frame.linear[1::2, 1::2].ravel()])
    assert st.mean[1] == pytest.approx(g.mean())
    assert st.std[1] == pytest.approx(g.std(ddof=1))
    assert st.mean[0] == pytest.approx(frame.linear[0::2, 1::2].mean())
    assert st.mean[2] == pytest.approx(frame.linear[1::2, 0::2].mean())
    assert st.count.sum() == frame.linear.size


def test_roi_exposure_stats(refdata):
    path = refdata / "raw" / "RAW_KODAK_DC50.KDC"
    frame = read_raw(path)
    st = roi_exposure_stats(path, (10, 60, 20, 90))
    roi = frame.linear[10:60, 20:90]
    ch = frame.channel[10:60, 20:90]
    assert st.signal_dn[0] == pytest.approx(np.median(roi[ch == 0]))
    assert st.saturated_fraction == pytest.approx(frame.saturated[10:60, 20:90].mean())
    assert st.headroom_dn == 16383
    with pytest.raises(ReductionError, match="empty"):
        roi_exposure_stats(frame, (5, 5, 0, 10))


# ---- bad input -------------------------------------------------------------------------


@pytest.mark.parametrize("fname", ["Blackmagic.dng", "RAW_KODAK_DC50.KDC"])
def test_truncated_raw_is_refused(refdata, fname, tmp_path):
    data = (refdata / "raw" / fname).read_bytes()
    for n in (len(data) // 2, len(data) - 100):
        p = tmp_path / f"cut_{n}_{fname}"
        p.write_bytes(data[:n])
        with pytest.raises(FileFormatError, match=str(p.name)):
            read_raw(p)


def test_garbage_and_missing_files_are_refused(tmp_path):
    p = tmp_path / "noise.dng"
    p.write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(FileFormatError, match="noise.dng"):
        read_raw(p)
    (tmp_path / "empty.dng").write_bytes(b"")
    with pytest.raises(FileFormatError, match="empty"):
        read_raw(tmp_path / "empty.dng")
    with pytest.raises(FileFormatError, match="no such"):
        read_raw(tmp_path / "absent.dng")


def test_camera_mismatch_is_refused(refdata):
    path = refdata / "raw" / "RAW_KODAK_DC50.KDC"
    with pytest.raises(FileFormatError, match="CFA pattern is GRBG.*RGGB"):
        read_raw(path, expect=CameraSignature("RGGB", (512, 768)))
    with pytest.raises(FileFormatError, match="ImageSize.*512x768.*480x640"):
        read_raw(path, expect=CameraSignature("GRBG", (480, 640)))
    assert read_raw(path, expect=CameraSignature("GRBG", (512, 768))).shape == (512, 768)


def test_simulated_dng_round_trip_and_truncation(tmp_path):
    """The simulator's DNG (uncompressed strips, ISO in an EXIF sub-IFD) decodes to its
    mosaic minus black, with the exposure; cut short, it is refused (LibRaw alone would
    fill the missing strips with zeros)."""
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.sensor import RawFrame as SimFrame

    rng = np.random.default_rng(0)
    mosaic = rng.integers(512, 16383, (64, 96)).astype(np.uint16)
    data = dng_bytes(
        SimFrame(mosaic, "GBRG", 512, 16383, np.eye(3), np.ones(3), 0.004, 5.6, 400.0, 0.035)
    )
    frame = read_raw(data, name="sim.dng")
    assert frame.cfa_pattern == "GBRG"
    np.testing.assert_array_equal(frame.linear, mosaic.astype(float) - 512)
    assert (frame.exposure_time, frame.iso, frame.f_number) == pytest.approx(
        (0.004, 400, 5.6), rel=1e-6
    )
    assert np.array_equal(frame.channel[:2, :2], [[1, 2], [0, 1]])
    p = tmp_path / "cut.dng"
    p.write_bytes(data[: len(data) - 2000])
    with pytest.raises(FileFormatError, match="cut.dng.*truncated"):
        read_raw(p)


def test_dark_subtraction_and_flat_field():
    from gonio.capture.raw import RawFrame, apply_flat, master_flat, subtract_dark

    rng = np.random.default_rng(1)
    ch = np.tile(np.array([[0, 1], [1, 2]], np.int8), (20, 20))
    gain_map = 1 + 0.05 * rng.standard_normal(ch.shape)  # pixel response non-uniformity
    offset = rng.uniform(0, 3, ch.shape)  # dark signal pattern
    level = np.array([1000.0, 2000.0, 800.0])[ch]

    def frame(signal, name):
        return RawFrame(
            name,
            signal,
            ch,
            np.zeros(ch.shape, bool),
            np.zeros(ch.shape),
            16383.0,
            "RGGB",
            0.01,
            100.0,
            8.0,
        )

    dark = frame(offset, "dark")
    flats = [frame(level * gain_map + offset, f"flat{k}") for k in range(2)]
    flat = master_flat(flats, [dark])
    # normalised to 1 per channel, proportional to the response within a channel
    for c in range(3):
        m = ch == c
        assert flat[m].mean() == pytest.approx(1.0)
        np.testing.assert_allclose(flat[m] / gain_map[m], (flat[m] / gain_map[m]).mean())
    scene = np.full(ch.shape, 500.0)
    shot = frame(scene * gain_map + offset, "shot")
    corrected = apply_flat(subtract_dark(shot, dark), flat)
    for c in range(3):
        m = ch == c
        v = corrected.linear[m]
        assert v.std() / v.mean() < 1e-12  # flat again
    with pytest.raises(ReductionError, match="flat field is"):
        apply_flat(shot, flat[:10])


def test_per_channel_black_levels(monkeypatch):
    """A DNG whose BlackLevel differs per CFA position (BlackLevelRepeatDim 2x2)."""
    import gonio.simulator.dng as dng
    from gonio.simulator.sensor import RawFrame as SimFrame

    blacks = (500, 510, 520, 530)  # row-major over the 2x2 CFA cell
    tags = dng._tags

    def per_channel(frame):
        return [(50714, t[1], 4, blacks, True) if t[0] == 50714 else t for t in tags(frame)]

    monkeypatch.setattr(dng, "_tags", per_channel)
    mosaic = np.random.default_rng(3).integers(600, 4000, (32, 48)).astype(np.uint16)
    data = dng.dng_bytes(
        SimFrame(mosaic, "RGGB", 512, 16383, np.eye(3), np.ones(3), 0.01, 8.0, 100.0, 0.035)
    )
    frame = read_raw(data)
    expected_black = np.tile(np.array(blacks, float).reshape(2, 2), (16, 24))
    np.testing.assert_array_equal(frame.black_level, expected_black)
    np.testing.assert_array_equal(frame.linear, mosaic - expected_black)
    lin, ch, _ = frame.region((slice(3, 9), slice(5, 12)))  # odd offsets: CFA phase kept
    np.testing.assert_array_equal(lin, (mosaic - expected_black)[3:9, 5:12])


def _tifffile_data_end(data):
    """The same end of the image data, by tifffile: every page and its SubIFD pages."""
    import io

    import tifffile

    end = 0
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        stack = list(tf.pages)
        while stack:
            p = stack.pop()
            if p.dataoffsets and p.databytecounts:
                ends = zip(p.dataoffsets, p.databytecounts, strict=True)
                end = max(end, max(o + c for o, c in ends))
            stack.extend(p.pages or [])
    return end


@pytest.mark.parametrize("fname", ["Blackmagic.dng", "RAW_KODAK_DC50.KDC"])
def test_tiff_data_end_agrees_with_tifffile_on_camera_files(refdata, fname):
    from gonio.capture.raw import tiff_data_end

    data = (refdata / "raw" / fname).read_bytes()
    assert tiff_data_end(data) == _tifffile_data_end(data) > len(data) // 2


def test_tiff_data_end_walks_strips_tiles_and_subifds():
    import io

    import tifffile

    from gonio.capture.raw import tiff_data_end

    for byteorder in ("<", ">"):
        buf = io.BytesIO()
        with tifffile.TiffWriter(buf, byteorder=byteorder) as w:
            w.write(np.ones((256, 256), np.uint16), tile=(64, 64))
            w.write(np.zeros((64, 48), np.uint16), subifds=1)
            w.write(np.ones((300, 200), np.uint16), rowsperstrip=16)  # the SubIFD, last
        data = buf.getvalue()
        with tifffile.TiffFile(io.BytesIO(data)) as tf:  # the main chain alone ends sooner
            ends = [zip(p.dataoffsets, p.databytecounts, strict=True) for p in tf.pages]
            main = max(o + c for e in ends for o, c in e)
        assert tiff_data_end(data) == _tifffile_data_end(data) > main
    assert tiff_data_end(b"not a tiff at all") is None
    damaged = bytearray(data)
    damaged[4:8] = (len(data) + 10).to_bytes(4, "big")  # the first IFD past the end
    with pytest.raises(FileFormatError, match="x.dng.*damaged TIFF structure"):
        read_raw(bytes(damaged), name="x.dng")


def _sim_dng(mosaic, pattern="RGGB", black=512, white=16383):
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.sensor import RawFrame as SimFrame

    return dng_bytes(
        SimFrame(mosaic, pattern, black, white, np.eye(3), np.ones(3), 0.01, 8.0, 100.0, 0.035)
    )


def _assert_same_stats(a, b):
    assert a.saturated_fraction == b.saturated_fraction
    assert a.headroom_dn == b.headroom_dn
    np.testing.assert_array_equal(a.signal_dn, b.signal_dn)  # exactly (NaN where empty)
    np.testing.assert_array_equal(a.snr, b.snr)


@pytest.mark.parametrize("noise", [False, True])
def test_roi_stats_fast_path_equals_the_general_one(refdata, noise):
    """The bracket's per-shot statistics of a whole box (cached channel indices, medians
    from a histogram of the raw integers) are the general path's (float conversion of
    the box, boolean masks, np.median), to the bit: real cameras' files (two CFA
    layouts, black 512 and 0) and simulated DNGs with clipped pixels, boxes of odd and
    even offsets and sizes (odd and even channel counts: both median forms)."""
    from gonio.capture.noise import NoiseModel
    from gonio.capture.raw import _box_mosaic_stats, _exposure_stats, roi_mask

    rng = np.random.default_rng(7)
    sat = rng.integers(512, 16383, (60, 90)).astype(np.uint16)
    sat[10:30, 20:50] = 16383  # a clipped patch
    frames = [
        read_raw(refdata / "raw" / "RAW_KODAK_DC50.KDC"),
        read_raw(refdata / "raw" / "Blackmagic.dng"),
        read_raw(_sim_dng(sat, "GBRG"), name="sat.dng"),
        read_raw(_sim_dng(rng.integers(500, 700, (61, 91)).astype(np.uint16)), name="odd.dng"),
    ]
    model = NoiseModel(gain=2.0, read_noise=3.0) if noise else None
    taken = 0
    for frame in frames:
        h, w = frame.shape
        for roi in [
            None,
            (0, h, 0, w),
            (10, 60, 20, 90),
            (3, 40, 5, 61),
            (1, 2, 1, 4),
            (7, 8, 9, 10),
        ]:
            mask = roi_mask(frame.shape, roi)
            rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
            box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
            taken += _box_mosaic_stats(frame, box) is not None
            _assert_same_stats(
                _exposure_stats(frame, mask, model), _exposure_stats(frame, mask, model, fast=False)
            )
    assert taken == 6 * len(frames)  # every case went through the fast path


def test_roi_stats_fast_path_declines_mixed_blacks(monkeypatch):
    """A channel whose CFA positions have different black levels (both greens here) is
    left to the general path: one black per channel is what the histogram median needs."""
    import gonio.simulator.dng as dng
    from gonio.capture.raw import _box_mosaic_stats

    blacks = (500, 510, 520, 530)
    tags = dng._tags
    monkeypatch.setattr(
        dng,
        "_tags",
        lambda f: [(50714, t[1], 4, blacks, True) if t[0] == 50714 else t for t in tags(f)],
    )
    mosaic = np.random.default_rng(3).integers(600, 4000, (32, 48)).astype(np.uint16)
    frame = read_raw(_sim_dng(mosaic))
    assert _box_mosaic_stats(frame, (slice(0, 32), slice(0, 48))) is None
    st = roi_exposure_stats(frame, None)
    g = (mosaic - np.tile(np.array(blacks, float).reshape(2, 2), (16, 24)))[
        np.tile(np.array([[False, True], [True, False]]), (16, 24))
    ]
    assert st.signal_dn[1] == np.median(g)

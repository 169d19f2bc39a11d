"""HDR merge of a bracket: agreement with colour_hdri, honest per-pixel variance."""

from __future__ import annotations

import colour_hdri
import numpy as np
import pytest

from gonio.capture.hdr import merge_bracket
from gonio.capture.noise import NoiseModel
from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError

GAIN, READ_E, BLACK, WHITE = 0.4, 3.0, 512, 16383  # DN/e-, e-, DN, DN
SHAPE = (120, 160)
CH = np.tile(np.array([[0, 1], [1, 2]], np.int8), (SHAPE[0] // 2, SHAPE[1] // 2))


def frame(dn, t, name, iso=100.0, f_number=8.0):
    return RawFrame(
        name,
        dn - BLACK,
        CH,
        dn >= WHITE - 0.05 * (WHITE - BLACK),
        np.full(SHAPE, float(BLACK)),
        float(WHITE),
        "RGGB",
        t,
        iso,
        f_number,
    )


def sensor(rng, radiance, t, iso=100.0, f_number=8.0, noise=True):
    """Electrons = radiance * t * ISO/100 / N^2 (independent of the code under test)."""
    e_mean = radiance * t / f_number**2
    g = GAIN * iso / 100.0
    if not noise:
        return np.clip(BLACK + g * e_mean, 0, WHITE)
    e = rng.poisson(e_mean) + rng.normal(0, READ_E, SHAPE)
    return np.clip(np.round(BLACK + g * e), 0, WHITE)


def test_matches_colour_hdri_where_both_weightings_agree():
    """Pure shot noise: inverse-variance weights are proportional to exposure, and so is
    colour_hdri's weight w(d) = d at a given pixel; noise-free frames must merge alike."""
    rng = np.random.default_rng(0)
    rad = rng.uniform(1.3e9, 1.9e9, SHAPE)  # data in (0.25, 0.4) of range in frame 1
    times = (0.0005, 0.0011)
    frames = [frame(sensor(rng, rad, t, noise=False), t, f"f{t}") for t in times]
    assert (frames[0].linear / (WHITE - BLACK)).max() < 0.5
    assert (frames[1].linear / (WHITE - BLACK)).min() > 0.5
    m = merge_bracket(frames, NoiseModel(GAIN, 0.0, quantisation=False))

    stack = colour_hdri.ImageStack()
    for f in frames:
        d = np.repeat((f.linear / (WHITE - BLACK))[..., None], 3, axis=2)
        stack.append(
            colour_hdri.Image(
                f.name,
                d,
                colour_hdri.Metadata(f_number=f.f_number, exposure_time=f.exposure_time, iso=f.iso),
            )
        )
    ref = colour_hdri.image_stack_to_HDRI(stack, weighting_function=lambda d: d)[..., 0]
    # colour_hdri's unit: d * k N^2 / (t S), ours: DN * N^2 / (t ISO/100)
    ours = m.value * 12.5 / 100.0 / (WHITE - BLACK)
    np.testing.assert_allclose(ours, ref, rtol=1e-12)


@pytest.mark.filterwarnings("ignore:.*negative or equal to zero values")
def test_noisy_bracket_is_unbiased_and_its_variance_calibrated():
    rng = np.random.default_rng(1)
    # four decades of radiance across the image, so each frame saturates somewhere
    rad = 10 ** np.linspace(5.5, 9.5, SHAPE[1])[None, :] * np.ones(SHAPE)
    truth = rad * GAIN  # DN per unit exposure factor (t ISO/100 / N^2)
    model = NoiseModel(GAIN, GAIN * READ_E)
    z = []
    ours_err, hdri_err = [], []
    for _ in range(6):
        frames = [frame(sensor(rng, rad, t), t, f"f{t}") for t in (1e-4, 1e-3, 1e-2)]
        m = merge_bracket(frames, model)
        ok = ~m.saturated
        z.append(((m.value - truth) / np.sqrt(m.variance))[ok])
        stack = colour_hdri.ImageStack()
        for f in frames:
            d = np.repeat((f.linear / (WHITE - BLACK))[..., None], 3, axis=2)
            stack.append(
                colour_hdri.Image(
                    f.name,
                    d,
                    colour_hdri.Metadata(
                        f_number=f.f_number, exposure_time=f.exposure_time, iso=f.iso
                    ),
                )
            )
        ref = colour_hdri.image_stack_to_HDRI(stack)[..., 0] * 100.0 / 12.5 * (WHITE - BLACK)
        ours_err.append(((m.value - truth) / truth)[ok])
        hdri_err.append(((ref - truth) / truth)[ok])
    z = np.concatenate(z)
    # ~1e5 pixels: the standard deviation of z is known to ~0.3 %
    assert abs(z.mean()) < 0.02
    assert 0.97 < z.std() < 1.03
    # inverse-variance weights beat a hat function on the same frames
    assert np.sqrt(np.mean(np.concatenate(ours_err) ** 2)) < np.sqrt(
        np.mean(np.concatenate(hdri_err) ** 2)
    )
    # relative error distributions agree in the middle: both are unbiased estimators
    assert abs(np.median(np.concatenate(ours_err))) < 2e-3


def test_iso_and_aperture_normalise():
    rng = np.random.default_rng(2)
    rad = np.full(SHAPE, 2e8)
    fr = [
        frame(sensor(rng, rad, 1e-3, iso=400, f_number=4.0), 1e-3, "a", 400, 4.0),
        frame(sensor(rng, rad, 4e-3, iso=100, f_number=8.0), 4e-3, "b", 100, 8.0),
    ]
    m = merge_bracket(fr, NoiseModel(GAIN, GAIN * READ_E))
    z = (m.value - rad * GAIN) / np.sqrt(m.variance)
    assert abs(z.mean()) < 0.05 and 0.9 < z.std() < 1.1


def test_all_saturated_pixels_are_nan_and_flagged():
    rng = np.random.default_rng(3)
    rad = np.full(SHAPE, 1e12)
    fr = [frame(sensor(rng, rad, t), t, f"f{t}") for t in (1e-3, 1e-2)]
    m = merge_bracket(fr, NoiseModel(GAIN, 1.2))
    assert m.saturated.all() and np.isnan(m.value).all() and (m.frames_used == 0).all()


def test_bad_brackets():
    with pytest.raises(ReductionError, match="empty"):
        merge_bracket([], NoiseModel(GAIN, 1.2))
    a = frame(np.full(SHAPE, 1000.0), 1e-3, "a")
    b = RawFrame(
        "b",
        a.linear,
        a.channel,
        a.saturated,
        a.black_level,
        a.white_level,
        "GRBG",
        1e-3,
        100.0,
        8.0,
    )
    with pytest.raises(ReductionError, match="GRBG"):
        merge_bracket([a, b], NoiseModel(GAIN, 1.2))
    c = RawFrame(
        "c",
        a.linear,
        a.channel,
        a.saturated,
        a.black_level,
        a.white_level,
        "RGGB",
        float("nan"),
        100.0,
        8.0,
    )
    with pytest.raises(ReductionError, match="exposure_time"):
        merge_bracket([a, c], NoiseModel(GAIN, 1.2))


def raw_frame(dn, t, name):
    """A frame decoded from a mosaic, as read_raw builds it (black and clip per cell)."""
    black = np.full((2, 2), float(BLACK))
    return RawFrame(
        name, None, None, None, None, float(WHITE), "RGGB", t, 100.0, 8.0,
        raw=dn.astype(np.uint16),
        cell_channel=np.array([[0, 1], [1, 2]], np.int8),
        cell_black=black,
        saturation_threshold=WHITE - 0.05 * (WHITE - black),
    )  # fmt: skip


@pytest.mark.parametrize("times", [(2.5e-3, 1e-2), (1.25e-3, 1e-2), (1.5625e-4, 1.25e-3, 1e-2)])
@pytest.mark.parametrize("sigmas_below_clip", [-1.0, 0.0, 0.5, 1.5, 3.0, 6.0])
def test_a_long_frame_at_its_clip_does_not_bias_the_merge(sigmas_below_clip, times):
    """A bracket whose long frame sits at its saturation threshold (a pixel's mean within
    a few sigma of it, as a realistic world's G channel was): judged by its own reading,
    the long frame is kept only where it read low, and the merge came out low (-0.15 %
    at 0.5 sigma below the clip, 60 of its standard errors).  The truth is the sensor
    model's radiance; over 90000 pixels the mean relative error is known to ~3e-5.
    Brackets of 2 frames 4x and 8x apart, and of 3 frames 8x apart."""
    rng = np.random.default_rng(11)
    shape = (300, 300)
    clip = WHITE - 0.05 * (WHITE - BLACK) - BLACK  # DN above black
    g = GAIN  # ISO 100
    # the long frame's mean: sigmas_below_clip of its own noise below the clip
    mean_dn = clip - sigmas_below_clip * np.sqrt(g * clip)
    rad = mean_dn / g * 8.0**2 / times[-1]  # electrons = rad t / N^2
    frames = []
    for t in times:
        e = rng.poisson(np.full(shape, rad * t / 64.0)) + rng.normal(0, READ_E, shape)
        frames.append(raw_frame(np.clip(np.round(BLACK + g * e), 0, WHITE), t, f"f{t}"))
    m = merge_bracket(frames, NoiseModel(GAIN, GAIN * READ_E))
    truth = rad * GAIN  # DN per unit exposure factor
    rel = m.value / truth - 1
    se = np.sqrt(np.mean(m.variance)) / truth / np.sqrt(rel.size)
    assert np.isfinite(rel).all()
    assert abs(rel.mean()) < 5 * se, (rel.mean(), se)

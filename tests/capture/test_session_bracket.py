"""Adaptive brackets: frames are added only while the ROI clips or sits in the noise."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy

from gonio.capture.bracket import FrameVerdict, next_exposure, predict_exposure, roi_pixels
from gonio.capture.journal import read_journal
from gonio.capture.plan import BracketPolicy
from gonio.cli import main
from gonio.rig.config import virtual_rig_document


def _v(t, sat=False, under=False, frac=0.3):
    return FrameVerdict(t, sat, under, frac)


POLICY = BracketPolicy(
    exposure_time_s=0.01, step_ev=2, max_frames=4, min_exposure_s=1e-4, max_exposure_s=1.0
)


def test_one_good_frame_is_enough():
    assert next_exposure([_v(0.01)], POLICY) is None


def test_saturated_adds_shorter_until_clean():
    assert next_exposure([_v(0.01, sat=True)], POLICY) == pytest.approx(0.0025)
    assert next_exposure([_v(0.01, sat=True), _v(0.0025, sat=True)], POLICY) == pytest.approx(
        0.000625
    )
    assert next_exposure([_v(0.01, sat=True), _v(0.0025)], POLICY) is None


def test_dark_adds_longer_and_both_ends_are_covered():
    assert next_exposure([_v(0.01, under=True)], POLICY) == pytest.approx(0.04)
    # a high-contrast ROI: clipped highlights and shadows in the noise at once
    first = [_v(0.01, sat=True, under=True)]
    assert next_exposure(first, POLICY) == pytest.approx(0.0025)
    assert next_exposure([*first, _v(0.0025, under=True)], POLICY) == pytest.approx(0.04)


def test_limits_stop_the_bracket():
    assert next_exposure([_v(1.0, under=True)], POLICY) is None  # 4 s > max_exposure_s
    assert next_exposure([_v(2e-4, sat=True)], POLICY) is None  # 5e-5 s < min_exposure_s
    four = [_v(0.01 * 4.0**-k, sat=True) for k in range(4)]
    assert next_exposure(four, POLICY) is None  # max_frames


def test_prediction_follows_irradiance():
    prev = [_v(0.02, frac=0.5)]
    # the irradiance drops by cos(60)/cos(0) = 1/2: twice the exposure
    assert predict_exposure(POLICY, prev, 1.0, 0.5) == pytest.approx(0.04)
    assert predict_exposure(POLICY, None, None, 0.5) == POLICY.exposure_time_s


def test_roi_pixels_are_whole_bayer_quads():
    rows, cols = roi_pixels((24, 32), (0.4, 0.4, 0.6, 0.6))
    assert rows.start % 2 == 0 and cols.start % 2 == 0
    assert (rows.stop - rows.start) % 2 == 0 and (cols.stop - cols.start) % 2 == 0


PLAN = """
name = "bracket"
seed = 5
[grid]
theta_i_deg = [10, 20, 30]
phi_i_deg = [0]
theta_o_deg = [40]
phi_o_deg = [180]
[bracket]
exposure_time_s = 0.5     # far too long for the first pose: it must clip
step_ev = 2
max_frames = 6
roi = [0.375, 0.375, 0.625, 0.625]
[simulation]
width = 32
height = 24
"""


def test_adaptive_brackets_in_a_simulated_session(tmp_path):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    out = tmp_path / "S"
    try:
        main(
            [
                "capture",
                "run",
                str(tmp_path / "plan.toml"),
                "--rig",
                str(tmp_path / "rig.toml"),
                "--camera",
                "simulated",
                "--out",
                str(out),
                "--sim-speed",
                "virtual",
                "--quiet",
            ]
        )
    except SystemExit as exc:
        assert exc.code in (0, None)
    shots = [r for r in read_journal(out / "journal.jsonl") if r["type"] == "shot"]
    by_pose: dict[int, list[dict]] = {}
    for r in shots:
        by_pose.setdefault(r["pose"], []).append(r)

    def clipped_fraction(path):
        # independent of the reduction code: raw mosaic values at the DNG's white level
        with rawpy.imread(str(path)) as raw:
            img = raw.raw_image_visible
            rows, cols = roi_pixels(img.shape, (0.375, 0.375, 0.625, 0.625))
            return float(np.mean(img[rows, cols] >= raw.white_level))

    first = by_pose[0]
    t = [r["exposure_time"] for r in first]
    assert len(first) >= 2 and t[0] == pytest.approx(0.5)
    assert np.allclose(np.array(t[1:]) / np.array(t[:-1]), 0.25)  # 2 EV shorter each time
    fr = [clipped_fraction(out / r["file"]) for r in first]
    assert all(f > 0.001 for f in fr[:-1]) and fr[-1] <= 0.001
    # later poses start from the predicted exposure and need one frame each
    assert [len(by_pose[k]) for k in sorted(by_pose)[1:]] == [1] * (len(by_pose) - 1)
    for k in sorted(by_pose)[1:]:
        assert clipped_fraction(out / by_pose[k][0]["file"]) <= 0.001

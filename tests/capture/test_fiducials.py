"""Camera pose from the holder's ChArUco board against the simulator's true pose."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.fiducials import (
    BoardSpec,
    CameraPose,
    binned_grey_uint8,
    binning_for,
    detect_pose,
    detect_pose_in_frame,
    grey_from_mosaic,
    grey_image,
    map_regions,
    to_uint8,
)
from gonio.capture.raw import read_raw
from gonio.errors import ReductionError
from gonio.radiometry import spherical_to_direction


def scene_doc(resolution, board=True):
    holder = {"width": 0.16, "height": 0.16}
    if not board:
        holder["board"] = None
    return {
        "sample": {
            "width": 0.05,
            "height": 0.05,
            "brdf": {"model": "lambert", "params": {"albedo": 0.5}},
        },
        "holder": holder,
        "lights": [
            {
                "type": "disk",
                "position": [0.0, 0.25, 0.433],
                "look_at": [0, 0, 0],
                "radius": 0.01,
                "radiance": [2e4, 2e4, 2e4],
            }
        ],
        "camera": {
            "resolution": list(resolution),
            "focal_length": 0.016,
            "fov_deg": 30.0,
            "position": [0.1, -0.2, 0.35],
            "look_at": [0, 0, 0],
        },
        "render": {"tolerance": 1e-3},
    }


@pytest.fixture(scope="module")
def rig_views():
    """Three views of the default rig (camera at 0.4 m), rendered at 800 x 600."""
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(scene_doc((800, 600)))
    kin = Kinematics(default_rig_config())
    state = {}
    cam = SimulatedCamera(scene, pose_provider=lambda: state["p"])
    views = []
    for k, (ti, pi, to, po) in enumerate([(20, 0, 20, 180), (40, 0, 60, 180), (30, 90, 45, 270)]):
        wi = spherical_to_direction(np.radians(ti), np.radians(pi))
        wo = spherical_to_direction(np.radians(to), np.radians(po))
        rp = kin.poses(kin.inverse(wi, wo))
        state["p"] = rp
        dng, truth = cam.capture(3e-4, 100, 8.0, seed=k, return_truth=True)
        views.append((read_raw(dng, name=f"view{k}"), rp, truth))
    return setup_from_scene(scene), views


@pytest.mark.slow
def test_pose_matches_the_simulators_true_pose(rig_views):
    setup, views = rig_views
    for frame, rp, _ in views:
        R_true = rp.camera_rotation.T  # RigPoses gives camera-to-sample
        rig = CameraPose(R_true, -R_true @ rp.camera_position, rp.camera_position, np.nan, 0)
        # seen at 20 deg the markers are big enough to be found on a 2x binned image, at
        # 60 deg (foreshortened by half) they are not
        factor = binning_for(setup.board, setup.K, rig, frame.shape)
        assert factor == {"view0": 2, "view1": 1}.get(frame.name, factor)
        for pose in (
            detect_pose(grey_from_mosaic(frame), setup.board, setup.K),  # full resolution
            detect_pose_in_frame(frame, setup.board, setup.K, max_width=400),  # binned + refined
            detect_pose_in_frame(frame, setup.board, setup.K, expected=rig),  # binned by size
        ):
            err_mm = np.linalg.norm(pose.position - rp.camera_position) * 1e3
            err_deg = np.degrees(pose.angle_to(R_true))
            rms = pose.reprojection_rms
            print(f"{frame.name}: {err_mm:.3f} mm, {err_deg:.4f} deg, rms {rms:.3f} px")
            assert err_mm < 0.5
            assert err_deg < 0.1
            assert pose.reprojection_rms < 0.5


@pytest.mark.slow
def test_regions_map_pixels_to_the_true_surface_points(rig_views):
    setup, views = rig_views
    for frame, _rp, truth in views:
        pose = detect_pose_in_frame(frame, setup.board, setup.K)
        reg = map_regions(pose, setup.K, frame.shape, setup.sample_size, grid=3)
        inside = reg.label >= 0
        true_pts = truth.points[reg.box][inside]
        # every region pixel sees the sample in the simulator too
        assert (truth.region[reg.box][inside] == 1).all()
        err = np.linalg.norm(reg.points[inside] - true_pts, axis=-1)
        assert np.max(err) < 5e-4  # metres
        cosang = np.sum(reg.wo[inside] * truth.wo[reg.box][inside], axis=-1)
        assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 0.1
        # nine regions, each with pixels, each inside its cell on the sample
        for j in range(9):
            p = reg.points[reg.label == j]
            assert len(p) > 100
            assert np.all(np.abs(p[:, :2] - reg.centers[j]) <= 0.05 * 0.6 / 3 / 2 + 1e-9)


def test_no_visible_board_is_a_clear_error():
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(scene_doc((320, 240), board=False))
    frame = read_raw(SimulatedCamera(scene).capture(3e-4, 100, 8.0, seed=0), name="noboard.dng")
    with pytest.raises(ReductionError, match="noboard.dng.*board not visible"):
        detect_pose_in_frame(
            frame, BoardSpec(), np.array([[600.0, 0, 160], [0, 600, 120], [0, 0, 1]])
        )


def test_board_placement_matches_the_simulators_convention():
    from gonio.simulator.scene import Board

    b = Board()
    R, t = BoardSpec.from_mapping(b.model_dump()).transform()
    R2, t2 = b.board_to_sample()
    np.testing.assert_array_equal(R, R2)
    np.testing.assert_array_equal(t, t2)


@pytest.mark.slow
def test_geometry_mismatch_with_the_rig_is_flagged(rig_views):
    from gonio.capture.pose_measure import measure_pose
    from gonio.dataset import Flag

    setup, views = rig_views
    # the 45 deg view: the 60 deg one sits at max_board_obliquity_deg, where the board's
    # own obliquity estimate decides whether "auto" trusts it (and checks it) at all
    frame, rp, _ = views[2]
    reported = (rp.camera_position, rp.camera_rotation.T)
    ok = measure_pose(
        [frame],
        setup,
        rp.light_position,
        rp.light_normal,
        reported_wo=rp.wo,
        reported_camera=reported,
    )
    assert not (ok.flags & Flag.GEOMETRY_MISMATCH).any()
    # the rig claims the camera 1 degree further round than the board shows
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    wo_claimed = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ rp.wo
    bad = measure_pose(
        [frame],
        setup,
        rp.light_position,
        rp.light_normal,
        reported_wo=wo_claimed,
        reported_camera=reported,
    )
    assert ok.geometry_source == bad.geometry_source == "board"
    assert (bad.flags & Flag.GEOMETRY_MISMATCH).all()
    assert "deg from the rig's report" in bad.reasons[0][0]


def looking_down(height):
    """A camera ``height`` metres above the sample centre, looking straight down."""
    R = np.diag([1.0, -1.0, -1.0])  # world -> camera: x right, y down the image, z forward
    C = np.array([0.0, 0.0, height])
    return CameraPose(R, -R @ C, C, np.nan, 0)


@pytest.mark.parametrize(("height", "factor"), [(0.6, 1), (0.3, 2), (0.15, 4)])
def test_binning_follows_the_expected_marker_size(height, factor):
    """Seen square on, a marker of side L at distance Z is f L / Z pixels: 25, 50 and 100
    pixels at f = 1000 for the 15 mm markers; the coarsest binning keeps >= 20 pixels."""
    K = np.array([[1000.0, 0, 1500], [0, 1000.0, 1000], [0, 0, 1]])
    got = binning_for(BoardSpec(), K, looking_down(height), (2000, 3000), min_marker_px=20)
    assert got == factor
    # never finer than asked, never so coarse the image is under 160 pixels wide
    assert binning_for(BoardSpec(), K, looking_down(0.6), (2000, 3000), min_factor=4) == 4
    assert binning_for(BoardSpec(), K, looking_down(0.01), (2000, 3000)) == 16  # 187 px wide


@pytest.mark.slow
@pytest.mark.parametrize("factor", [2, 4])
def test_fast_binned_grey_is_to_uint8_of_the_grey_image(rig_views, factor):
    _setup, views = rig_views
    for frame, _rp, _ in views:
        want = to_uint8(grey_image(frame, factor)).astype(int)
        got = binned_grey_uint8(frame, factor).astype(int)
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= 1


def test_a_dim_board_beside_a_bright_sample_is_still_found():
    """Under grazing light a glossy sample's highlight sets the grey scale; the board at
    4 % of it must still decode (a linear scale leaves it ~10 grey levels, none found)."""
    from gonio.capture.fiducials import _detect_corners

    board = BoardSpec()
    img = board.cv_board().generateImage((700, 700), marginSize=20).astype(np.float32) / 255
    canvas = np.zeros((900, 1200), np.float32)
    canvas[100:800, 250:950] = 0.04 * img
    canvas[300:600, 450:750] = 1.0  # the sample's highlight
    _corners, ids = _detect_corners(to_uint8(canvas), board, "dim", 6)
    assert len(ids) == 24  # every corner the sample leaves uncovered


def test_a_degenerate_corner_set_is_an_error_not_a_nan_pose():
    from gonio.capture.fiducials import _solve

    K = np.array([[1000.0, 0, 400], [0, 1000.0, 300], [0, 0, 1]])
    corners = np.stack([np.linspace(100, 500, 5), np.full(5, 300.0)], axis=1)  # one line
    with pytest.raises(ReductionError, match="degenerate"):
        _solve(BoardSpec(), corners, np.arange(5), K, None)


@pytest.mark.parametrize("factor", [1, 2, 4, 6, 8])
def test_halvings_are_the_block_mean_to_one_dn(factor):
    """Marker finding bins the mosaic by successive halvings (OpenCV's fast path): a 2x
    binning is OpenCV's one-step block mean exactly, a coarser one within the 1 DN each
    halving may round differently (a factor not a power of 2: one step, exactly); the
    odd rows and columns past the last block go."""
    import cv2

    from gonio.capture.fiducials import _halvings

    raw = np.random.default_rng(factor).integers(0, 65536, (203, 317), dtype=np.uint16)
    h, w = 203 // factor * factor, 317 // factor * factor
    want = cv2.resize(raw[:h, :w], (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    got = _halvings(raw, factor)
    assert got.dtype == np.uint16
    assert got.shape == (203 // factor, 317 // factor)
    diff = np.abs(got.astype(int) - want)
    assert diff.max() <= (0 if factor in (1, 2, 6) else 1)
    if factor in (4, 8):
        assert 0 < np.count_nonzero(diff)  # really a different rounding, still a mean
        assert abs(float(np.mean(got.astype(int) - want))) < 0.5


@pytest.mark.slow
def test_halved_binning_moves_the_refined_corners_far_less_than_their_noise(rig_views, monkeypatch):
    """The corners are refined on the mosaic, so binning by halvings (not one 4x block
    mean) only moves where refinement starts: the same corners, within cornerSubPix's
    1e-3 px stopping step, against a reprojection RMS of ~0.1 px."""
    import cv2

    import gonio.capture.fiducials as fid

    setup, views = rig_views

    def one_step(raw, factor):
        h, w = raw.shape[0] // factor * factor, raw.shape[1] // factor * factor
        return cv2.resize(raw[:h, :w], (w // factor, h // factor), interpolation=cv2.INTER_AREA)

    def corners(frame, halvings):
        seen = {}
        solve = fid._solve

        def spy(board, c, ids, K, dist):
            seen["c"], seen["ids"] = np.array(c), np.array(ids)
            return solve(board, c, ids, K, dist)

        with monkeypatch.context() as m:
            m.setattr(fid, "_solve", spy)
            m.setattr(fid, "_halvings", halvings)
            pose = detect_pose_in_frame(frame, setup.board, setup.K, max_width=200)  # 4x
        return seen["c"], seen["ids"], pose

    compared = 0
    for frame, _rp, _ in views:
        try:
            c0, ids0, pose0 = corners(frame, one_step)
        except ReductionError:
            continue  # too few corners at 4x (a grazing view): nothing to compare
        c1, ids1, _pose1 = corners(frame, fid._halvings)
        np.testing.assert_array_equal(ids1, ids0)
        moved = np.linalg.norm(c1 - c0, axis=1)
        print(f"{frame.name}: max {moved.max():.2e} px, rms {pose0.reprojection_rms:.3f} px")
        assert moved.max() < 2e-3 < 0.05 * pose0.reprojection_rms
        compared += 1
    assert compared >= 1  # the 20 deg view; the others' markers are too small at 4x


@pytest.mark.parametrize(
    ("table", "words"),
    [
        ({"squares_x": 11, "squares_y": 11, "dictionary": "DICT_4X4_50"}, "60 markers"),
        ({"squares_x": 1}, "squares_x"),
        ({"marker_length": 0.03}, "marker_length"),
        ({"dictionary": "DICT_9X9_7"}, "dictionary"),
    ],
)
def test_board_tables_opencv_cannot_use_are_refused_by_name(table, words):
    """A board of more markers than its dictionary has IDs (11 x 11 squares: 60 markers,
    DICT_4X4_50 holds 50) is refused like a field out of range, before OpenCV builds it."""
    with pytest.raises(ValueError, match=words):
        BoardSpec.from_mapping(table)
    # the same board with a dictionary large enough is accepted
    if "squares_x" in table and table["squares_x"] == 11:
        assert BoardSpec.from_mapping({**table, "dictionary": "DICT_4X4_100"}).squares_x == 11

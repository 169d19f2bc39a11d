"""Pose ordering: a valid permutation, never worse than nearest neighbour, beats raster."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from gonio.capture.ordering import move_time_matrix, order_poses, tour_time


def _chebyshev(points):
    return np.abs(points[:, None, :] - points[None, :, :]).max(-1)


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_small_instances_are_optimal(n):
    # brute force over all permutations is the independent reference
    rng = np.random.default_rng(n)
    D = _chebyshev(rng.uniform(0, 1, (n + 1, 3)))
    order = order_poses(D, start=0)
    assert order[0] == 0 and sorted(order) == list(range(n + 1))
    best = min(tour_time(D, (0, *p)) for p in itertools.permutations(range(1, n + 1)))
    # 2-opt + Or-opt is a heuristic; on <= 7 nodes it finds the optimum here
    assert tour_time(D, order) == pytest.approx(best, rel=1e-12)


def test_points_on_a_line_are_swept_once():
    x = np.array([0.0, 5, 1, 4, 2, 3])[:, None]
    D = np.abs(x - x.T)
    order = order_poses(D, start=0)
    assert tour_time(D, order) == pytest.approx(5.0)  # the optimum: one sweep 0 -> 5


def test_grid_order_is_no_worse_than_the_boustrophedon():
    # 6 rows (tilt, step 0.2) of 16 azimuths (0..3): raster flies back 3 after every row
    # (6 * 3 + 5 * 3 = 33); the boustrophedon (snake) needs 6 * 3 + 5 * 0.2 = 19.
    az = np.linspace(0, 3, 16)
    rows = [np.stack([np.full(16, 0.2 * r), az], axis=1) for r in range(6)]
    pts = np.vstack([[[0.0, 0.0]], *rows])
    D = _chebyshev(pts)
    raster = tour_time(D, range(len(pts)))
    snake = [0] + [1 + 16 * r + (k if r % 2 == 0 else 15 - k) for r in range(6) for k in range(16)]
    assert raster == pytest.approx(33.0) and tour_time(D, snake) == pytest.approx(19.0)
    order = order_poses(D)
    assert tour_time(D, order) <= 19.0 + 1e-9


def test_matrix_from_scalar_move_time():
    joints = [{"a": 0.0, "b": 1.0}, {"a": 2.0, "b": 1.0}, {"a": 2.0, "b": -1.0}]

    def mt(p, q):  # scalar only: forces the fallback path
        return float(max(abs(float(q[k]) - float(p[k])) for k in p))

    D = move_time_matrix(joints, mt, start={"a": 0.0, "b": 0.0})
    assert D.shape == (4, 4)
    assert D[0, 1] == 1.0 and D[1, 2] == 2.0 and D[2, 3] == 2.0 and D[3, 0] == 2.0


def test_per_joint_matrix_equals_pairwise_move_times():
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics

    cfg = default_rig_config()
    kin = Kinematics(cfg)
    rng = np.random.default_rng(1)
    joints = [
        {s.joint: float(rng.uniform(*s.limits_rad) * 0.5) for s in cfg.servos} for _ in range(12)
    ]
    fast = move_time_matrix(joints, kin.move_time, start=cfg.park_rad, servos=cfg.servos)
    nodes = [cfg.park_rad, *joints]
    for a in range(len(nodes)):
        for b in range(len(nodes)):
            expected = 0.0 if a == b else kin.move_time(nodes[a], nodes[b])
            assert fast[a, b] == pytest.approx(expected, abs=1e-12)

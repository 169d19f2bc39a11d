"""Order poses to minimise the total servo travel time.

Visiting a grid in raster order sends the arms back across the whole range at the end of
every row.  The cost of going from one pose to the next is the duration of the move, from
the rig's velocity/acceleration profiles (``Kinematics.move_time``), so ordering is an open
travelling-salesman path from the park position.  We build it with nearest neighbour and
improve it with 2-opt and Or-opt moves, vectorised over candidate positions in numpy.

Hand-written because no installed library solves path-TSP on a precomputed asymmetric
matrix (scipy has only linear assignment; OR-tools is not a dependency) and a few hundred
poses need no more than these classic local searches.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["move_time_matrix", "order_poses", "tour_time"]

Joints = Mapping[str, float]


def move_time_matrix(
    joints: Sequence[Joints],
    move_time: Callable[[Joints, Joints], float],
    start: Joints | None = None,
    servos: Sequence[Any] | None = None,
) -> np.ndarray:
    """Move durations between all poses (s).

    Parameters
    ----------
    joints
        Joint angles (rad) of each pose, joint name -> angle.
    move_time
        ``move_time(joints_from, joints_to) -> s`` (e.g. ``Kinematics.move_time``).
    start
        Joint angles the tour starts from (e.g. the park pose); it becomes node 0.
    servos
        The rig's servo configurations (``RigConfig.servos``).  When given, the matrix is
        built joint by joint: a move's time is the slowest joint's, and one joint's time
        depends only on its distance in whole pulses, so ``move_time`` is called once per
        distinct distance (with single-joint mappings: joints missing from a mapping do
        not move) instead of once per pair of poses.

    Returns
    -------
    ndarray, shape (n, n)
        ``D[a, b]`` = duration of the move from node ``a`` to node ``b``; with ``start``,
        node 0 is the start and pose ``k`` is node ``k + 1``.
    """
    nodes = ([start] if start is not None else []) + list(joints)
    n = len(nodes)
    names = sorted(nodes[0]) if n else []
    if servos is not None and n:
        return _per_joint_matrix(nodes, move_time, servos)
    # Try one vectorised call (joint arrays broadcast to (n, n)); fall back to scalar calls
    # for a move_time that only takes floats.
    try:
        a = {k: np.array([p[k] for p in nodes], dtype=np.float64)[:, None] for k in names}
        b = {k: np.array([p[k] for p in nodes], dtype=np.float64)[None, :] for k in names}
        D = np.asarray(move_time(a, b), dtype=np.float64)
        if D.shape != (n, n):
            raise ValueError("not vectorised")
    except Exception:  # noqa: BLE001 - any failure means "call it pose by pose"
        D = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                if i != j:
                    D[i, j] = float(move_time(nodes[i], nodes[j]))
    np.fill_diagonal(D, 0.0)
    return D


def _per_joint_matrix(nodes: list, move_time: Callable, servos: Sequence[Any]) -> np.ndarray:
    n = len(nodes)
    D = np.zeros((n, n))
    for s in servos:
        j = s.joint
        if j not in nodes[0]:
            continue
        p = np.rint([s.pulses(float(q[j])) for q in nodes]).astype(np.int64)
        dist = np.abs(p[:, None] - p[None, :])
        uniq, inv = np.unique(dist, return_inverse=True)
        base = int(p.min())
        t = np.array(
            [
                float(move_time({j: s.joint_rad(base)}, {j: s.joint_rad(base + int(d))}))
                for d in uniq
            ]
        )
        np.maximum(D, t[inv].reshape(n, n), out=D)
    np.fill_diagonal(D, 0.0)
    return D


def tour_time(D: np.ndarray, order: Sequence[int]) -> float:
    """Total duration (s) of visiting nodes in ``order`` (consecutive moves summed)."""
    o = np.asarray(order, dtype=int)
    return float(D[o[:-1], o[1:]].sum()) if len(o) > 1 else 0.0


def _nearest_neighbour(D: np.ndarray, start: int) -> list[int]:
    n = len(D)
    left = np.ones(n, dtype=bool)
    left[start] = False
    tour = [start]
    cur = start
    for _ in range(n - 1):
        cand = np.where(left, D[cur], np.inf)
        nxt = int(np.argmin(cand))
        tour.append(nxt)
        left[nxt] = False
        cur = nxt
    return tour


def _two_opt(D: np.ndarray, tour: np.ndarray, max_passes: int) -> np.ndarray:
    """2-opt on an open path whose first node is fixed; the symmetric part of D is used
    for the reversal gains, the true (asymmetric) cost decides acceptance."""
    S = 0.5 * (D + D.T)
    n = len(tour)
    for _ in range(max_passes):
        improved = False
        for i in range(1, n - 1):
            # reverse tour[i..j]: edges (i-1, i) and (j, j+1) become (i-1, j) and (i, j+1)
            j = np.arange(i + 1, n)
            a, b = tour[i - 1], tour[i]
            c = tour[j]
            d = np.append(tour[j[:-1] + 1], -1)
            after_old = np.where(d >= 0, S[c, np.maximum(d, 0)], 0.0)
            after_new = np.where(d >= 0, S[b, np.maximum(d, 0)], 0.0)
            gain = S[a, b] + after_old - S[a, c] - after_new
            k = int(np.argmax(gain))
            if gain[k] > 1e-9:
                jj = j[k]
                cand = tour.copy()
                cand[i : jj + 1] = tour[i : jj + 1][::-1]
                if tour_time(D, cand) < tour_time(D, tour) - 1e-12:
                    tour = cand
                    improved = True
        if not improved:
            break
    return tour


def _or_opt(D: np.ndarray, tour: np.ndarray, max_passes: int) -> np.ndarray:
    """Move segments of 1-3 nodes elsewhere in the path (first node fixed)."""
    n = len(tour)
    for _ in range(max_passes):
        improved = False
        for seg in (1, 2, 3):
            for i in range(1, n - seg + 1):
                segment = tour[i : i + seg]
                rest = np.concatenate([tour[:i], tour[i + seg :]])
                base = tour_time(D, tour)
                # insert after rest[p] for every p, in both orientations
                p = np.arange(len(rest))
                nxt = np.append(rest[1:], -1)
                first, last = segment[0], segment[-1]
                old = D[rest[p[:-1]], rest[p[:-1] + 1]]
                old = np.append(old, 0.0)
                rest_time = tour_time(D, rest)
                seg_time = tour_time(D, segment)
                seg_rev_time = tour_time(D, segment[::-1])
                has = nxt >= 0
                nx = np.maximum(nxt, 0)
                fwd = D[rest, first] + seg_time + np.where(has, D[last, nx], 0.0) - old
                rev = D[rest, last] + seg_rev_time + np.where(has, D[first, nx], 0.0) - old
                totals = rest_time + np.minimum(fwd, rev)
                k = int(np.argmin(totals))
                if totals[k] < base - 1e-9:
                    ins = segment if fwd[k] <= rev[k] else segment[::-1]
                    tour = np.concatenate([rest[: k + 1], ins, rest[k + 1 :]])
                    improved = True
        if not improved:
            break
    return tour


def order_poses(D: np.ndarray, start: int = 0, max_passes: int = 20) -> list[int]:
    """A short open path through all nodes of ``D`` beginning at ``start``.

    Parameters
    ----------
    D
        Move-time matrix (s), e.g. from :func:`move_time_matrix`.
    start
        Node the path starts from (the park pose).
    max_passes
        Cap on improvement sweeps of each local search.

    Returns
    -------
    list of int
        Node indices, ``start`` first.  Deterministic for a given ``D``.
    """
    n = len(D)
    if n <= 2:
        return [start] + [k for k in range(n) if k != start]
    tour = np.asarray(_nearest_neighbour(D, start))
    for _ in range(3):
        before = tour_time(D, tour)
        tour = _two_opt(D, tour, max_passes)
        tour = _or_opt(D, tour, max_passes)
        if tour_time(D, tour) >= before - 1e-9:
            break
    return [int(k) for k in tour]

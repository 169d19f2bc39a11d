"""An adaptive plan's candidate pool and its seed design.

The pool (:func:`candidate_pool`) is every pose whose ``wi`` and ``wo`` lie on the rings
of a hemisphere grid ``pool_step_deg`` apart up to ``max_theta_deg`` (a ring at theta
holds ``round(360 sin(theta) / step)`` azimuths, so the directions are about evenly
spread), reduced by the plan's symmetries (isotropy: ``phi_i = 0`` and ``phi_o`` in
[0, 180] deg; reciprocity), less the plan's exclusions and whatever the rig's kinematics
refuses from its home pose.  The ids of the pool are its entries' positions (stable:
the pool is a pure function of the plan and the rig, stored in the session as
``adaptive_pool.json``).

The seed design (:func:`seed_design`) is measured before any round: the
``retro_poses`` entries nearest to retro-reflection (``wi = wo`` itself is where the
camera shadows the light), ``in_plane_poses`` in the incidence plane of one
``theta_i`` (near 45 deg: the specular peak and both sides of it), and the rest
space-filling (farthest-point in ``(wi, wo)`` from a start drawn from the plan's seed).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.capture.plan import (
    ExcludedPose,
    ExpandedPlan,
    Plan,
    Pose,
    _as_tuple,
    _canonical_isotropic,
    _exclusion_reason,
    _symmetry_key,
)
from gonio.errors import ConfigError, FileFormatError, PoseRefused
from gonio.radiometry import spherical_to_direction

__all__ = [
    "POOL_FILE",
    "CandidatePool",
    "candidate_pool",
    "expand_adaptive",
    "farthest_point",
    "pool_features",
    "pool_size",
    "read_pool",
    "seed_design",
]

#: Where a session keeps its pool (written at creation, before the manifest).
POOL_FILE = "adaptive_pool.json"


@dataclass(frozen=True)
class CandidatePool:
    """The reachable candidate poses of an adaptive plan (sample frame, unit vectors).

    Attributes
    ----------
    wi, wo
        (K, 3) directions; entry ``k`` has pool id ``k``.
    n_generated, n_reduced
        Ring poses generated, and those the symmetry reductions removed.
    excluded
        Code (``"plan"`` or a ``RefusalReason`` value) -> poses left out for it.
    """

    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    n_generated: int = 0
    n_reduced: int = 0
    excluded: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.wi)

    def to_json(self) -> dict[str, Any]:
        return {
            "wi": np.round(self.wi, 12).tolist(),
            "wo": np.round(self.wo, 12).tolist(),
            "n_generated": self.n_generated,
            "n_reduced": self.n_reduced,
            "excluded": dict(sorted(self.excluded.items())),
        }

    @classmethod
    def from_json(cls, doc: Any, source: Any = POOL_FILE) -> CandidatePool:
        """Read :meth:`to_json`'s document; a ``FileFormatError`` naming the field."""
        if not isinstance(doc, dict):
            raise FileFormatError(source, "expected a JSON object (the candidate pool)")
        arrays = []
        for key in ("wi", "wo"):
            try:
                a = np.asarray(doc.get(key), dtype=np.float64)
            except (TypeError, ValueError):
                a = np.zeros((0,))
            if a.ndim != 2 or a.shape[1:] != (3,) or not np.all(np.isfinite(a)):
                raise FileFormatError(source, "expected a list of finite 3-vectors", key)
            arrays.append(a)
        if len(arrays[0]) != len(arrays[1]):
            raise FileFormatError(source, "wi and wo have different lengths", "wo")
        return cls(
            arrays[0],
            arrays[1],
            int(doc.get("n_generated", 0)),
            int(doc.get("n_reduced", 0)),
            dict(doc.get("excluded") or {}),
        )

    def pose(self, k: int) -> Pose:
        """Pool entry ``k`` as a sample :class:`~gonio.capture.plan.Pose`."""
        return Pose(_as_tuple(self.wi[k]), _as_tuple(self.wo[k]), pool_id=int(k))


def read_pool(session_dir: Any) -> CandidatePool:
    """A session's ``adaptive_pool.json``.

    Raises
    ------
    FileFormatError
        Missing, not JSON or a field wrong (named).
    """
    from pathlib import Path

    path = Path(session_dir) / POOL_FILE
    try:
        doc = json.loads(path.read_bytes())
    except OSError as exc:
        raise FileFormatError(path, f"cannot read the candidate pool: {exc.strerror}") from None
    except ValueError as exc:
        raise FileFormatError(path, f"not valid JSON ({exc})") from None
    return CandidatePool.from_json(doc, path)


def _rings(step_deg: float, max_theta_deg: float, phi_max_deg: float = 360.0):
    """Directions (theta, phi) rad on rings ``step_deg`` apart, phi in [0, phi_max)."""
    out = []
    for t in np.arange(0.0, max_theta_deg + 1e-9, step_deg):
        if t < 1e-9:
            out.append((0.0, 0.0))
            continue
        n = max(1, int(round(360.0 * math.sin(math.radians(t)) / step_deg)))
        for k in range(n):
            phi = 360.0 * k / n
            if phi <= phi_max_deg + 1e-9:
                out.append((math.radians(t), math.radians(phi)))
    return out


def _ring_pairs(plan: Plan) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    a = plan.adaptive
    assert a is not None
    if plan.reductions.isotropic:
        # phi_i = 0 and phi_o in [0, 180]: every relative azimuth once (the reduction)
        thetas = np.arange(0.0, a.max_theta_deg + 1e-9, a.pool_step_deg)
        wis = [(math.radians(t), 0.0) for t in thetas]
        wos = _rings(a.pool_step_deg, a.max_theta_deg, 180.0)
    else:
        wis = wos = _rings(a.pool_step_deg, a.max_theta_deg)
    return [(i, o) for i in wis for o in wos]


def pool_size(plan: Plan) -> int:
    """Ring poses the pool is made from (before reductions and exclusions): an upper
    bound of its size, counted without solving anything."""
    a = plan.adaptive
    assert a is not None
    if plan.reductions.isotropic:
        n_i = len(np.arange(0.0, a.max_theta_deg + 1e-9, a.pool_step_deg))
        return n_i * len(_rings(a.pool_step_deg, a.max_theta_deg, 180.0))
    return len(_rings(a.pool_step_deg, a.max_theta_deg)) ** 2


#: ``rig_check(wi, wo)``: the kinematics' refusal of a pose, or None.
RigCheck = Callable[[np.ndarray, np.ndarray], "PoseRefused | str | None"]


def candidate_pool(
    plan: Plan,
    rig_check: RigCheck | None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[CandidatePool, list[ExcludedPose]]:
    """The reachable candidates of ``plan`` (see the module docstring).

    Returns
    -------
    pool, excluded
        The pool, and the poses left out with their reasons.
    """
    pairs = _ring_pairs(plan)
    red = plan.reductions
    use_rig = rig_check is not None and plan.exclusions.check_rig
    seen: set[tuple] = set()
    wi_out, wo_out, excluded = [], [], []
    n_reduced = 0
    every = max(1, len(pairs) // 100)
    for k, ((ti, pi), (to, po)) in enumerate(pairs):
        if progress is not None and k % every == 0:
            progress(k, len(pairs))
        wi, wo = spherical_to_direction(ti, pi), spherical_to_direction(to, po)
        if red.isotropic:
            wi, wo = _canonical_isotropic(wi, wo)
        key = _symmetry_key(wi, wo, red)
        if key in seen:
            n_reduced += 1
            continue
        seen.add(key)
        pose = Pose(_as_tuple(wi), _as_tuple(wo))
        reason = _exclusion_reason(np.array(pose.wi), np.array(pose.wo), plan.exclusions)
        if reason is not None:
            excluded.append(ExcludedPose(pose, reason))
            continue
        refusal = rig_check(np.array(pose.wi), np.array(pose.wo)) if use_rig else None
        if refusal is not None:
            code = refusal.reason.value if isinstance(refusal, PoseRefused) else "rig"
            excluded.append(ExcludedPose(pose, str(refusal), code))
            continue
        wi_out.append(pose.wi)
        wo_out.append(pose.wo)
    if progress is not None:
        progress(len(pairs), len(pairs))
    counts = Counter(e.code for e in excluded)
    pool = CandidatePool(
        np.asarray(wi_out, dtype=np.float64).reshape(-1, 3),
        np.asarray(wo_out, dtype=np.float64).reshape(-1, 3),
        len(pairs),
        n_reduced,
        dict(counts),
    )
    return pool, excluded


def pool_features(wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
    """(K, 6) ``(wi, wo)``: the space the seed design and the placeholder choice spread
    poses in (a chord of 2 sin(d/2) per direction)."""
    return np.concatenate([np.asarray(wi, float), np.asarray(wo, float)], axis=-1)


def farthest_point(
    features: NDArray[np.float64],
    n: int,
    chosen: Sequence[int] = (),
    start: int | None = None,
    allowed: NDArray[np.bool_] | None = None,
) -> list[int]:
    """Greedy farthest-point choice of ``n`` rows of ``features``.

    Each pick is the allowed row farthest (Euclidean) from every row already chosen
    (``chosen``, then the picks); ties go to the lowest index.  With nothing chosen the
    first pick is ``start`` (default 0).

    Returns
    -------
    list of int
        The picks in order (fewer than ``n`` when the allowed rows run out).
    """
    K = len(features)
    ok = np.ones(K, bool) if allowed is None else np.asarray(allowed, bool).copy()
    ok[list(chosen)] = False
    d = np.full(K, np.inf)
    for c in chosen:
        d = np.minimum(d, np.linalg.norm(features - features[c], axis=1))
    picks: list[int] = []
    while len(picks) < n and ok.any():
        if not np.isfinite(d[ok]).any():  # nothing chosen yet
            k = start if start is not None and ok[start] else int(np.flatnonzero(ok)[0])
        else:
            k = int(np.flatnonzero(ok)[np.argmax(d[ok])])
        picks.append(k)
        ok[k] = False
        d = np.minimum(d, np.linalg.norm(features - features[k], axis=1))
    return picks


def _separation(pool: CandidatePool) -> NDArray[np.float64]:
    return np.arccos(np.clip(np.sum(pool.wi * pool.wo, axis=1), -1.0, 1.0))


def _retro(pool: CandidatePool, n: int, step: float) -> list[int]:
    """The ``n`` entries nearest to retro-reflection, spread over theta."""
    if n <= 0 or not len(pool):
        return []
    sep = _separation(pool)
    near = sep <= sep.min() + step + 1e-9
    theta = np.arccos(np.clip(pool.wi[:, 2], -1, 1)), np.arccos(np.clip(pool.wo[:, 2], -1, 1))
    feat = np.stack(theta, axis=1)
    start = int(np.flatnonzero(near)[np.argmin(sep[near] + 1e-3 * feat[near, 0])])
    return farthest_point(feat, n, start=start, allowed=near)


def _in_plane(pool: CandidatePool, n: int, exclude: Sequence[int]) -> list[int]:
    """``n`` entries in one incidence plane (the theta_i nearest 45 deg that has
    enough), spread over the signed theta_o (the specular direction first)."""
    if n <= 0 or not len(pool):
        return []
    wi, wo = pool.wi, pool.wo
    horiz = np.linalg.norm(wi[:, :2], axis=1)
    ok = horiz > 1e-9
    normal = np.zeros_like(wi)
    normal[ok, 0] = -wi[ok, 1] / horiz[ok]
    normal[ok, 1] = wi[ok, 0] / horiz[ok]
    in_plane = ok & (np.abs(np.sum(normal * wo, axis=1)) < 1e-6)
    in_plane[list(exclude)] = False
    if not in_plane.any():
        return []
    ti = np.round(np.degrees(np.arccos(np.clip(wi[:, 2], -1, 1))), 6)
    values = sorted(set(ti[in_plane].tolist()), key=lambda t: (abs(t - 45.0), t))
    counts = {t: int(np.sum(in_plane & (ti == t))) for t in values}
    best = next((t for t in values if counts[t] >= n), max(values, key=lambda t: counts[t]))
    allowed = in_plane & (ti == best)
    # signed theta_o: positive on the side opposite the light (the specular side)
    side = -np.sign(np.sum(wi[:, :2] * wo[:, :2], axis=1) + 1e-15)
    signed = side * np.arccos(np.clip(wo[:, 2], -1, 1))
    spec = np.radians(best)
    start = int(np.flatnonzero(allowed)[np.argmin(np.abs(signed[allowed] - spec))])
    return farthest_point(signed[:, None], n, start=start, allowed=allowed)


def seed_design(plan: Plan, pool: CandidatePool) -> list[int]:
    """Pool ids of the seed design (see the module docstring), in choice order.

    Deterministic from ``plan.seed``: the space-filling part starts from an entry drawn
    with ``numpy.random.default_rng([seed, 17])``.

    Raises
    ------
    ConfigError
        The pool has fewer entries than ``seed_poses``.
    """
    a = plan.adaptive
    assert a is not None
    if len(pool) < a.seed_poses:
        raise ConfigError(
            f"{plan._source}: plan {plan.name!r}: the candidate pool has {len(pool)} "
            f"reachable poses, fewer than adaptive.seed_poses = {a.seed_poses} (excluded: "
            f"{pool.excluded}); use a finer adaptive.pool_step_deg or fewer seed poses"
        )
    retro = _retro(pool, a.retro_poses, math.radians(a.pool_step_deg))
    plane = _in_plane(pool, a.in_plane_poses, retro)
    chosen = retro + plane
    rest = a.seed_poses - len(chosen)
    if rest > 0:
        # the space-filling part starts at an entry the seed draws, then spreads out
        free = np.setdiff1d(np.arange(len(pool)), chosen)
        chosen.append(int(free[np.random.default_rng([plan.seed, 17]).integers(len(free))]))
        chosen += farthest_point(pool_features(pool.wi, pool.wo), rest - 1, chosen=chosen)
    return chosen


def expand_adaptive(
    plan: Plan,
    rig_check: RigCheck | None,
    progress: Callable[[int, int], None] | None,
    reference_poses: Callable[..., tuple[list[Pose], list[ExcludedPose]]],
) -> ExpandedPlan:
    """An adaptive plan's :class:`~gonio.capture.plan.ExpandedPlan`: the seed design's
    poses (each with its ``pool_id``), then the reference poses; ``pool`` holds the
    candidate pool."""
    pool, excluded = candidate_pool(plan, rig_check, progress)
    seed = seed_design(plan, pool)
    use_rig = rig_check is not None and plan.exclusions.check_rig
    ref, ref_excluded = reference_poses(plan, rig_check, use_rig)
    return ExpandedPlan(
        poses=[pool.pose(k) for k in seed] + ref,
        excluded=excluded + ref_excluded,
        n_grid=pool.n_generated,
        n_reduced=pool.n_reduced,
        notes=[
            f"adaptive: {len(pool)} candidate poses, seed design {len(seed)}, then batches "
            f"of {plan.adaptive.batch_poses} up to {plan.adaptive.max_poses} poses"  # type: ignore[union-attr]
        ],
        pool=pool,
    )

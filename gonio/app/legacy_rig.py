"""Interim adapter: the pre-contract ``gonio.rig.device.Rig`` as a :class:`RigDevice`.

REMOVE WITH THE RIG MERGE.  The rig engineer's ``Rig`` implements
:class:`gonio.devices.RigDevice` itself (``read()``, ``move_to(wi, wo, joints=...)``,
typed :class:`~gonio.errors.PoseRefused` / :class:`~gonio.errors.BusError`);
:func:`gonio.app.devices.as_rig_device` then uses it as it is and never builds this.
Until then this adapter gives the old ``Rig`` the interface:

- ``read()`` from ``read_states()``;
- ``move_to`` runs the checks the old ``Rig.move_to`` runs (inverse kinematics from the
  present pose, quantised goals, joint and path checks) *before* calling it, so a refusal
  surfaces as :class:`PoseRefused` before anything moved (classified by
  :func:`gonio.capture.refusals.as_refusal`); any other ``RigError`` from the old rig is
  a bus failure (:class:`BusError`) and ``RigFault`` passes through.  The ``joints`` hint
  is not used: the old rig solves from where it is, as it always did.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from gonio.capture.refusals import as_refusal
from gonio.devices import MoveResult, RigState
from gonio.errors import BusError, PoseRefused, RigError, RigFault
from gonio.rig.config import JOINT_NAMES

__all__ = ["LegacyRigAdapter"]


def _typed(exc: RigError) -> RigError:
    if isinstance(exc, RigFault | BusError | PoseRefused):
        return exc
    return BusError(str(exc))


class LegacyRigAdapter:
    """:class:`gonio.devices.RigDevice` over an open old-style ``Rig``."""

    def __init__(self, rig: Any) -> None:
        self.rig = rig
        self.kinematics = rig.kinematics

    def read(self) -> RigState:
        try:
            states = self.rig.read_states()
        except RigError as exc:
            raise _typed(exc) from exc
        return RigState(
            joints={j: float(s.position) for j, s in states.items()},
            temperatures={j: float(s.temperature) for j, s in states.items()},
            errors={j: int(s.hardware_error) for j, s in states.items()},
            moving=any(s.moving for s in states.values()),
        )

    def _refusal(self, wi: np.ndarray, wo: np.ndarray) -> PoseRefused | None:
        """What the old ``Rig.move_to`` would refuse, found without moving."""
        current = self.read().joints
        kin = self.kinematics
        try:
            q = kin.inverse(wi, wo, current=current)
            wi_u, wo_u = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
            goals = self.rig.quantised_goals(wi_u, wo_u, q)
        except RigError as exc:
            return as_refusal(exc)
        servos = self.rig.servos
        target = {j: servos[j].to_joint(goals[servos[j].id]) for j in JOINT_NAMES}
        reason = kin.check_joints(target) or kin._path_reason(current, target)
        return as_refusal(RigError(f"refusing to move: {reason}")) if reason else None

    def move_to(
        self, wi: ArrayLike, wo: ArrayLike, *, joints: Mapping[str, float] | None = None
    ) -> MoveResult:
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        refused = self._refusal(wi, wo)
        if refused is not None:
            raise refused
        try:
            r = self.rig.move_to(wi, wo)
        except RigError as exc:
            raise _typed(exc) from exc
        return MoveResult(
            r.wi, r.wo, r.wi_achieved, r.wo_achieved, r.joints, r.error_i, r.error_o, r.duration
        )

    def stop(self) -> None:
        self.rig._abort.set()

    def park(self) -> dict[str, float]:
        return self.rig.park()

    def torque_off(self) -> list[int]:
        return list(self.rig.torque_off())

"""What a rig calibration observes: board corners and mirror spots at known joint readings.

Produced from a calibration session's frames (``gonio.capture.rig_views``) or, in tests,
from the simulator's as-built world; consumed by :mod:`gonio.rig.calibration`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["BoardObservation", "SpotObservation"]


@dataclass(frozen=True)
class BoardObservation:
    """The holder's ChArUco corners seen at one pose.

    Attributes
    ----------
    label
        Where it came from, for messages (e.g. ``"pose 12"``).
    joints
        Joint name -> encoder reading (rad), the journal's ``joints``.
    approach
        Joint name -> sign of the joint's last move (+1, -1, 0 unknown).
    object_points
        (n, 3) the corners in the sample frame, m.
    image_points
        (n, 2) where they were detected, px (OpenCV: pixel centres at integers).
    """

    label: str
    joints: Mapping[str, float]
    approach: Mapping[str, int]
    object_points: NDArray[np.float64]
    image_points: NDArray[np.float64]


@dataclass(frozen=True)
class SpotObservation:
    """The light's centre seen in a mirror lying in the sample plane, at one pose.

    Attributes
    ----------
    label, joints, approach
        As :class:`BoardObservation`.
    image_point
        (2,) centroid of the light's mirror image, px (OpenCV convention).
    box
        ``(u0, v0, u1, v1)``, px: the pixels the centroid summed (the blob and its rim);
        None when unknown.  Where the mirror's edge crosses it, the centroid is biased.
    """

    label: str
    joints: Mapping[str, float]
    approach: Mapping[str, int]
    image_point: NDArray[np.float64]
    box: tuple[float, float, float, float] | None = None

"""Scenes whose light and camera stand where rig joint angles put them (``[rig]``).

A scene file may pose its light and camera by the rig's joint angles instead of by
coordinates.  Turning joints into poses takes the rig's kinematics, which belong to the
controller: the simulator never imports them (it renders an as-built world that the
controller only learns by calibration), so the composition root resolves ``[rig]`` here
and hands the poses to :func:`gonio.simulator.scene.parse_scene`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gonio.errors import ConfigError, GonioError

__all__ = ["load_scene", "parse_scene", "rig_poses"]


def rig_poses(scene: Any) -> Any:
    """The light and camera poses at the joint angles of ``scene.rig`` (``RigPoses``).

    The rig configuration is ``scene.rig.config`` (relative to the scene file) or the
    built-in preset.

    Raises
    ------
    ConfigError
        The configuration cannot be read or the joints are not a valid pose, named.
    """
    from gonio.rig.config import default_rig_config, load_rig_config
    from gonio.rig.kinematics import Kinematics

    spec = scene.rig
    try:
        cfg = load_rig_config(scene.resolve(spec.config)) if spec.config else default_rig_config()
        joints = {k: float(np.radians(v)) for k, v in spec.joints_deg.items()}
        return Kinematics(cfg).poses(joints)
    except GonioError as exc:
        raise ConfigError(f"rig: {exc}") from exc


def parse_scene(data: dict[str, Any], source: str = "<scene>", base_dir: Path | None = None):
    """:func:`gonio.simulator.scene.parse_scene` with ``[rig]`` joint angles resolved."""
    from gonio.simulator.scene import parse_scene as parse

    return parse(data, source, base_dir, rig_poses=rig_poses)


def load_scene(path: str | Path):
    """:func:`gonio.simulator.scene.load_scene` with ``[rig]`` joint angles resolved."""
    from gonio.simulator.scene import load_scene as load

    return load(path, rig_poses=rig_poses)

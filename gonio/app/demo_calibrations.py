"""The calibrations of ``gonio demo --world realistic``: what a lab does before measuring.

The same steps as the README's lab path (``gonio calibrate plan``, ``gonio calibrate
camera``, ``gonio capture run`` of the rig plan, ``gonio calibrate rig``), through the
library so that the demo prints only what it says: a camera-calibration session and a
rig-calibration session on the simulated as-built rig, ``camera.toml`` and
``rig_calibrated.toml`` in the demo's folder, and a summary of both with, because the
simulator knows the world, each estimate's distance from the truth in its own sigma.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CalibrationSummary", "calibrate_simulated_rig"]


@dataclass
class CalibrationSummary:
    """What the demo's calibrations found, and how far from the simulator's truth.

    Attributes
    ----------
    camera_file, rig_file
        ``camera.toml`` and ``rig_calibrated.toml``.
    camera_rms_px, camera_views, camera_rejected
        Reprojection RMS (px), views used, views rejected.
    rig_rms_px
        Residual RMS per observation kind (``board``, ``spot``), px.
    rows
        One per calibrated parameter: name, estimate, std, truth, unit.
    seconds
        Wall time per stage (``camera``, ``rig``).
    """

    camera_file: Path
    rig_file: Path
    camera_rms_px: float
    camera_views: int
    camera_rejected: int
    rig_rms_px: dict[str, float]
    rows: list[tuple[str, float, float, float | None, str]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)

    def z(self) -> dict[str, float]:
        """(estimate - truth) / std per parameter whose truth is known."""
        return {
            name: (v - t) / s
            for name, v, s, t, _ in self.rows
            if t is not None and s > 0 and math.isfinite(s)
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "camera_file": str(self.camera_file),
            "rig_file": str(self.rig_file),
            "camera_rms_px": self.camera_rms_px,
            "camera_views": self.camera_views,
            "camera_rejected": self.camera_rejected,
            "rig_rms_px": self.rig_rms_px,
            "parameters": {
                n: {"value": v, "std": s, "truth": t, "unit": u} for n, v, s, t, u in self.rows
            },
            "z_abs_max": max((abs(x) for x in self.z().values()), default=math.nan),
            "seconds": self.seconds,
        }


def _shoot(
    out: Path,
    name: str,
    poses: list[Any],
    kind: str,
    cfg_path: Path,
    scene_path: Path,
    world: str,
    world_seed: int,
    size: tuple[int, int],
    time_scale: Any,
    quiet: bool,
) -> Path:
    """Write a calibration plan and shoot it into ``out/name``: the session directory."""
    from gonio.app.simulation import run_simulated_session
    from gonio.rig.calibration_plan import write_plan

    plan_path = out / f"{name}_plan.toml"
    # The spot exposure `gonio calibrate plan` writes by default (the 2 mm source's image
    # in the mirror clips at ~1e-4 s at these sizes), and a long one for the board: that
    # small source leaves the board at ~25 DN in 0.02 s, and views are lost.
    write_plan(plan_path, poses, kind=kind, exposures_s=(2e-5, 2.0), width=size[0], height=size[1])
    session = out / f"{name}_session"
    run_simulated_session(
        session,
        plan_path,
        cfg_path,
        time_scale,
        scene_path=scene_path,
        world=world,
        world_seed=world_seed,
        quiet=quiet,
    )
    return session


def calibrate_simulated_rig(
    out: Path,
    cfg_path: Path,
    scene_path: Path,
    *,
    world: str,
    world_seed: int,
    size: tuple[int, int],
    time_scale: Any = "virtual",
    quiet: bool = False,
    say: Callable[[str], None] = print,
) -> CalibrationSummary:
    """Calibrate the camera, then the rig, of the simulated as-built rig into ``out``.

    Parameters
    ----------
    out
        The demo's folder (``camera.toml``, ``rig_calibrated.toml`` and the two
        calibration sessions go there).
    cfg_path, scene_path
        The nominal rig configuration and the simulated camera's scene.
    world, world_seed
        The as-built world (``realistic``, or a world TOML) and the seed of its errors.
    size
        Camera resolution (width, height), px: the measurement session must use it too.

    Raises
    ------
    gonio.errors.GonioError
        A calibration that cannot be made (too few views, an unobservable parameter, an
        ill-conditioned fit): nothing of it is written.
    """
    import tomllib

    from gonio.app.calibrate_cli import _board_from, _session_identity
    from gonio.app.calibrate_rig_cli import camera_prior
    from gonio.capture.camera_calibration import (
        calibrate_camera,
        camera_digest,
        views_from_session,
        write_camera_calibration,
    )
    from gonio.capture.manifest import load_manifest
    from gonio.capture.rig_views import calibration_observations
    from gonio.rig.calibration import calibrate_rig, write_calibrated_rig
    from gonio.rig.calibration_plan import camera_calibration_poses, rig_calibration_poses
    from gonio.rig.config import load_rig_config
    from gonio.simulator.world import load_world

    nominal = load_rig_config(cfg_path)
    seconds: dict[str, float] = {}
    common = dict(
        cfg_path=cfg_path,
        scene_path=scene_path,
        world=world,
        world_seed=world_seed,
        size=size,
        time_scale=time_scale,
        quiet=quiet,
    )

    t = time.perf_counter()
    say("calibrating the camera: ChArUco views of the holder's board (gonio calibrate camera)")
    cam_session = _shoot(out, "camera", camera_calibration_poses(nominal), "camera", **common)
    board, _ = _board_from(None, cam_session)
    cam = calibrate_camera(views_from_session(cam_session, board), source=str(cam_session))
    identity, cfa = _session_identity(cam_session, cam.image_size)
    camera_file = write_camera_calibration(out / "camera.toml", cam, identity, cfa_pattern=cfa)
    seconds["camera"] = time.perf_counter() - t

    t = time.perf_counter()
    say("calibrating the rig: board and mirror views (gonio calibrate rig)")
    rig_session = _shoot(out, "rig", rig_calibration_poses(nominal), "rig", **common)
    boards, spots, _ = calibration_observations(rig_session, board)
    cal = calibrate_rig(
        nominal, boards, spots, camera_prior(camera_file), camera_digest=camera_digest(identity)
    )
    rig_file = out / "rig_calibrated.toml"
    write_calibrated_rig(rig_file, cal)
    seconds["rig"] = time.perf_counter() - t

    # The simulator's truth, which no lab has: how far each estimate is, in its sigma.
    the_world = load_world(load_manifest(rig_session)["simulation"]["world"])
    truth = the_world.truth_parameters(tomllib.loads(cfg_path.read_text(encoding="utf-8")))
    K, dist = the_world.intrinsics(_scene_camera(scene_path, size))
    truth.update(
        fx=K[0, 0],
        fy=K[1, 1],
        cx=K[0, 2],
        cy=K[1, 2],
        **dict(zip(("k1", "k2", "p1", "p2", "k3"), np.ravel(dist)[:5], strict=True)),
    )
    rows = []
    for i, name in enumerate(cal.names):
        est = cal.record.parameters.get(name) or cal.record.intrinsics.get(name)
        unit = est.unit if est is not None else ""
        rows.append((name, float(cal.values[i]), float(cal.std[i]), truth.get(name), unit))
    return CalibrationSummary(
        camera_file=camera_file,
        rig_file=rig_file,
        camera_rms_px=float(cam.rms_px),
        camera_views=len(cam.used),
        camera_rejected=len(cam.rejected),
        rig_rms_px={k: float(v) for k, v in cal.rms_px.items()},
        rows=rows,
        seconds={k: round(v, 3) for k, v in seconds.items()},
    )


def _scene_camera(scene_path: Path, size: tuple[int, int]) -> Any:
    from gonio.app.world_wiring import nominal_scene
    from gonio.config import read_toml

    scene = nominal_scene(read_toml(scene_path, "scene"), scene_path.parent, *size)
    return scene.camera

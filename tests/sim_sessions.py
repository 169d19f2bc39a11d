"""The simulated sessions that the capture and reduction tests share, built in one place.

Most session tests capture the same small world: a 5 cm sample on the 16 cm holder with
its fiducial board, one 1 cm disk light at 30 deg from the normal, a 16 mm camera at
(0.1, -0.2, 0.35) m, and a grid plan with an adaptive bracket on the sample's centre.
They differ in a few fields (the sample's BRDF, the resolution, the render strategy, the
grid, the darks, the reference poses); :func:`scene` and :func:`grid_plan` take those as
arguments, so each test says what is particular to it and the rest is written once.
:func:`capture` writes the three input files and runs ``gonio capture run`` (the real
dynamixel-sdk on the virtual bus, rendered DNGs).

Imported by name (``from sim_sessions import ...``): ``tests/conftest.py`` puts this
folder on ``sys.path`` (the suite runs with ``--import-mode=importlib``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import tomli_w

from gonio.cli import run
from gonio.rig.config import default_rig_config, rig_config_from_dict, virtual_rig_document

#: The uniform grey-brown diffuse sample most tests capture.
LAMBERT = {"model": "lambert", "params": {"albedo": [0.6, 0.5, 0.4]}}
#: One quadrature node per pixel (cheap; the sample's BRDF is smooth).
QUADRATURE = {"strategy": "quadrature", "quadrature_order": 1}
#: The reference target's pose: seen from 30 deg at normal incidence.
REFERENCE_NORMAL = {"theta_i_deg": 0, "theta_o_deg": 30}
#: A second reference pose, in the incidence plane opposite the light.
REFERENCE_OBLIQUE = {"theta_i_deg": 30, "theta_o_deg": 30, "phi_o_deg": 180}
#: The adaptive bracket's metering window: the sample's centre.
CENTRE_ROI = [0.42, 0.42, 0.58, 0.58]


def scene(
    *,
    brdf: dict[str, Any] = LAMBERT,
    resolution: tuple[int, int] = (320, 240),
    render: dict[str, Any] = QUADRATURE,
    **sample: Any,
) -> dict[str, Any]:
    """The shared scene document (as ``scene.toml`` parses).

    Parameters
    ----------
    brdf
        The sample's ``[sample.brdf]`` table (default: :data:`LAMBERT`).
    resolution
        The camera's (width, height) in pixels: the reduction needs 320 x 240 to find
        the board, ~400 x 300 for the reference target's region.
    render
        The ``[render]`` table (default: :data:`QUADRATURE`).
    **sample
        More ``[sample]`` fields (e.g. ``albedo_map = "map.npy"``), after width and
        height.
    """
    return {
        "sample": {"width": 0.05, "height": 0.05, **sample, "brdf": dict(brdf)},
        "holder": {"width": 0.16, "height": 0.16, "board": {}},
        "lights": [
            {
                "type": "disk",
                "position": [0.0, 0.25, 0.433],
                "look_at": [0.0, 0.0, 0.0],
                "radius": 0.01,
                "radiance": [2.0e4, 2.0e4, 2.0e4],
            }
        ],
        "camera": {
            "resolution": list(resolution),
            "focal_length": 0.016,
            "fov_deg": 30.0,
            "position": [0.1, -0.2, 0.35],
            "look_at": [0.0, 0.0, 0.0],
        },
        "render": dict(render),
    }


def scene_toml(**kwargs: Any) -> str:
    """:func:`scene` as TOML text."""
    return tomli_w.dumps(scene(**kwargs))


def grid_plan(
    name: str,
    *,
    seed: int,
    theta_i_deg: list[float],
    theta_o_deg: list[float],
    darks: int,
    references: list[dict[str, float]],
    roi: list[float] = CENTRE_ROI,
    exposure_time_s: float = 0.0005,
    settle_s: float | None = None,
    reflectance: float | None = None,
    simulation: dict[str, Any] | None = None,
) -> str:
    """A grid plan in the incidence plane (phi_i 0, phi_o 180 deg), adaptive bracket, as
    TOML text.

    Parameters
    ----------
    name, seed
        The plan's name and seed.
    theta_i_deg, theta_o_deg
        The grid's polar angles in degrees.
    darks
        Dark frames at the end (``[darks] count``).
    references
        The reference target's poses (``[reference] poses``).
    roi, exposure_time_s
        The bracket's metering window (fractions of the frame) and first exposure (s).
    settle_s
        The plan's settle time in s (None: the plan's default).
    reflectance
        The reference target's reflectance (None: the plan's default).
    simulation
        The ``[simulation]`` table (default: ``scene = "scene.toml"``).
    """
    plan: dict[str, Any] = {"name": name, "seed": seed}
    if settle_s is not None:
        plan["settle_s"] = settle_s
    plan["grid"] = {
        "theta_i_deg": list(theta_i_deg),
        "phi_i_deg": [0],
        "theta_o_deg": list(theta_o_deg),
        "phi_o_deg": [180],
    }
    plan["bracket"] = {"policy": "adaptive", "roi": list(roi), "exposure_time_s": exposure_time_s}
    plan["darks"] = {"count": darks}
    plan["reference"] = {"poses": [dict(p) for p in references]}
    if reflectance is not None:
        plan["reference"] = {"reflectance": reflectance, **plan["reference"]}
    plan["simulation"] = dict(simulation) if simulation is not None else {"scene": "scene.toml"}
    return tomli_w.dumps(plan)


def write_inputs(d: Path, plan: str, scene: str | None = None, rig: str | None = None) -> None:
    """``d/rig.toml`` (default: the virtual rig), ``d/plan.toml`` and ``d/scene.toml``."""
    (d / "rig.toml").write_text(virtual_rig_document() if rig is None else rig)
    (d / "plan.toml").write_text(plan)
    if scene is not None:
        (d / "scene.toml").write_text(scene)


def capture(d: Path, out: str = "S", *options: str) -> Path:
    """``gonio capture run d/plan.toml --rig d/rig.toml --camera simulated --out d/out``
    (quiet, with ``options``); asserts it succeeds and returns the session folder."""
    session = d / out
    args = ("capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml"))
    assert run(*args, "--camera", "simulated", "--out", str(session), *options, "--quiet") == 0
    return session


def fast_rig_config(backlash_deg: float = 0.0):
    """The default rig with instant servo moves (no velocity or acceleration profile), a
    1 ms poll and every servo's backlash set to ``backlash_deg``: for tests that drive
    the real controller over the virtual bus many times."""
    d = default_rig_config().model_dump()
    for s in d["servos"]:
        s["velocity_deg_s"] = 0.0
        s["acceleration_deg_s2"] = 0.0
        s["backlash_deg"] = backlash_deg
    d["motion"]["poll_interval_s"] = 0.001
    return rig_config_from_dict(d)

"""Simulated sessions: the scene a session renders, made self-contained.

A plan's ``[simulation] scene`` (or ``--scene``) is read here, validated with the
simulator's own model, and recorded in the manifest as a document whose file references
(a measured BRDF, an albedo map, a spectrum, a rig file) point at copies inside the
session (``sim/NAME``), relative to the session directory: the manifest holds no absolute
path, so the session can be moved or shared and still resumes.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gonio.errors import ConfigError

__all__ = [
    "SIM_DIR",
    "SceneSource",
    "SimulatedRun",
    "relocatable",
    "run_simulated_session",
    "scene_source",
    "simulated_run",
]

#: Folder inside a session for the files a simulated scene refers to.
SIM_DIR = "sim"


@dataclass(frozen=True)
class SceneSource:
    """A scene document and the folder its relative paths start from."""

    document: dict[str, Any]
    base_dir: Path | None = None
    #: The scene's ``[world]`` table (the as-built world), kept apart from the document
    #: the renderer reads.
    world: dict[str, Any] | None = None


def scene_source(plan: Any, plan_path: Path | None, scene_path: str | Path | None) -> SceneSource:
    """The simulated camera's scene for a run: ``scene_path``, else the plan's
    ``simulation.scene`` (relative to the plan file), else the minimal scene.

    Raises
    ------
    ConfigError
        The file cannot be read, is not TOML, or is not a valid scene (file and field
        named) -- before anything is opened.
    """
    from gonio.simulator.rig_camera import minimal_scene
    from gonio.simulator.scene import parse_scene

    path = scene_path or plan.simulation.scene
    if path is None:
        return SceneSource(minimal_scene())
    p = Path(path)
    if not p.is_absolute() and scene_path is None and plan_path is not None:
        p = plan_path.parent / p
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the simulation scene: {exc.strerror}") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{p}: scene is not valid TOML: {exc}") from None
    from gonio.app.world_wiring import split_scene_world

    base = p.resolve().parent
    doc, world = split_scene_world(doc)
    parse_scene(doc, str(p), base)  # an error names this file, before the session starts
    return SceneSource(doc, base, world)


#: Keys whose string values in a scene document are file paths.
_PATH_KEYS = ("file", "albedo_map", "csv", "config")


@dataclass
class _Copies:
    base: Path | None
    files: dict[str, Path] = field(default_factory=dict)

    def take(self, value: str) -> str:
        src = Path(value)
        if not src.is_absolute():
            if self.base is None:
                return value
            src = self.base / src
        if not src.is_file():
            raise ConfigError(f"simulation scene: {value!r} ({src}) is not a file")
        for known, path in self.files.items():
            if path == src.resolve():
                return known
        name, n = src.name, 1
        while f"{SIM_DIR}/{name}" in self.files:
            n += 1
            name = f"{src.stem}-{n}{src.suffix}"
        rel = f"{SIM_DIR}/{name}"
        self.files[rel] = src.resolve()
        return rel


def relocatable(source: SceneSource) -> tuple[dict[str, Any], dict[str, Path]]:
    """The scene document as the manifest stores it, and the files to copy in.

    Returns
    -------
    document, attachments
        The document with every file reference replaced by ``sim/NAME`` (relative to
        the session directory), and ``{"sim/NAME": source file}``.
    """
    copies = _Copies(source.base_dir)

    def walk(node: Any, maps: bool = False) -> Any:
        if isinstance(node, dict):
            return {
                k: (
                    copies.take(v)
                    # a parameter map's value and a mix's mask are paths when strings
                    if isinstance(v, str) and (k in _PATH_KEYS or maps or k == "mask")
                    else walk(v, k == "maps")
                )
                for k, v in node.items()
            }
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    doc = walk(copy.deepcopy(source.document))
    return doc, dict(copies.files)


@dataclass(frozen=True)
class SimulatedRun:
    """What a simulated session needs besides its plan and rig.

    Attributes
    ----------
    simulation
        The manifest's simulation record (relocatable scene document, resolution, servo
        time scale).
    attachments
        Files to copy into the session (``{"sim/NAME": source}``).
    opener
        The device opener (virtual bus, rig, simulated camera) for
        :func:`gonio.capture.sessions.run_session`.
    """

    simulation: dict[str, Any]
    attachments: dict[str, Path]
    opener: Any


def simulated_run(
    plan: Any,
    plan_path: Path | None,
    scene_path: str | Path | None,
    time_scale: Any,
    world: str | None = None,
    world_seed: int | None = None,
    render_ahead: Any = None,
) -> SimulatedRun:
    """Everything ``gonio capture run --camera simulated`` and the demo wire the same way.

    Parameters
    ----------
    plan, plan_path
        The validated plan and its file (a relative ``[simulation] scene`` starts there).
    scene_path
        ``--scene``, overriding the plan's scene; None for the plan's (or the default).
    time_scale
        ``"virtual"`` or a wall-clock speed-up factor of the virtual servos.
    world, world_seed
        ``--world`` (``perfect``, ``realistic`` or a world TOML) and ``--world-seed``;
        None: the plan's ``[simulation] world``, else the scene's ``[world]``, else
        perfect.  The record holds the whole world, so resume rebuilds it.
    render_ahead
        A :class:`gonio.app.render_ahead.RenderAhead` worker for the camera (see
        :func:`gonio.app.devices.open_session_devices`), or None.
    """
    from gonio.app.devices import device_opener
    from gonio.app.world_wiring import resolve_world
    from gonio.simulator.scene import SCENE_SCHEMA_VERSION
    from gonio.simulator.world import world_document

    source = scene_source(plan, plan_path, scene_path)
    the_world = resolve_world(
        world,
        world_seed,
        getattr(plan.simulation, "world", None),
        plan_path.parent if plan_path is not None else None,
        source.world,
    )
    document, attachments = relocatable(source)
    # the manifest records the scene schema the session renders with (resume reads it)
    if isinstance(document, dict):
        document.setdefault("schema_version", SCENE_SCHEMA_VERSION)
    simulation = {
        "scene": document,
        "width": plan.simulation.width,
        "height": plan.simulation.height,
        "time_scale": time_scale,
        "world": world_document(the_world),
    }
    opener = device_opener(
        scene=source.document,
        scene_base=source.base_dir,
        time_scale=time_scale,
        render_ahead=render_ahead,
    )
    return SimulatedRun(simulation, attachments, opener)


def run_simulated_session(
    session: Path,
    plan_path: Path,
    rig_path: Path,
    time_scale: Any = "virtual",
    *,
    scene_path: str | Path | None = None,
    world: str | None = None,
    world_seed: int | None = None,
    quiet: bool = False,
    render_ahead: Any = None,
    subscribers: Any = (),
) -> None:
    """Capture ``plan_path`` on the simulated rig of ``rig_path`` into ``session``.

    What ``gonio capture run PLAN --rig RIG --camera simulated`` does, through the
    library (for the demo): the API prints nothing, a progress bar shows unless
    ``quiet``.  ``scene_path``, ``world``, ``world_seed``, ``render_ahead``: as
    :func:`simulated_run`; ``subscribers`` receive every document after the progress
    bar.
    """
    from gonio.app.progress import SessionProgress
    from gonio.capture.plan import load_plan
    from gonio.capture.sessions import plan_session, run_session
    from gonio.rig.config import load_rig_config

    plan = load_plan(plan_path)
    cfg = load_rig_config(rig_path)
    sim = simulated_run(plan, plan_path, scene_path, time_scale, world, world_seed, render_ahead)
    with SessionProgress(quiet) as progress:
        run_session(
            session,
            plan,
            cfg,
            sim.opener,
            camera_backend="simulated",
            dry_run=plan_session(plan, cfg),
            simulation=sim.simulation,
            attachments=sim.attachments,
            subscribers=[progress, *subscribers],
        )

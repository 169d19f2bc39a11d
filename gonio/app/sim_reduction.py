"""A simulated session's ``reduction.toml``, written from its scene.

A lab writes ``SESSION/reduction.toml`` from its calibrations (camera matrix,
distortion, board, sample size, light, noise model; see ``examples/reduction.toml``).  A
simulated session knows those facts from the scene the simulator rendered, and the
reduction must not read a scene (``gonio.capture`` imports nothing from the simulator):
so the composition root converts the scene into the same document, once, at capture
time.  The conversion is exact: every number is written with ``repr`` (tomli-w), so the
reduction of the written file is the reduction the scene describes, to the bit.

Usage for a session captured before sessions wrote their own file::

    python -m gonio.app.sim_reduction SESSION [SESSION ...]
"""

from __future__ import annotations

import os
import sys
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from gonio.atomic import write_text_atomic
from gonio.capture.reduction_config import (
    CONFIG_FILE,
    ReductionConfig,
    ReductionSetup,
    setup_from_config,
)
from gonio.config import validate
from gonio.errors import GonioError, ReductionError, SessionError

__all__ = [
    "reduction_document",
    "scene_of_manifest",
    "setup_from_scene",
    "write_reduction_toml",
]

_HEADER = (
    "# Reduction setup of a simulated session, written by gonio.app.sim_reduction from the\n"
    "# NOMINAL scene: what a lab knows before calibrating (see examples/reduction.toml).\n"
    "# [camera] is the nominal camera (the lens's focal length over the pixel pitch, a\n"
    "# centred principal point, no distortion), not the camera as built: after\n"
    "#   gonio calibrate camera --out camera.toml\n"
    "# replace the [camera] table with\n"
    "#   [camera]\n"
    '#   file = "camera.toml"\n'
    "# (or pass gonio capture reduce S/ --camera-calibration camera.toml).\n"
)


def reduction_document(
    scene: Any,
    reference_reflectance: float | Sequence[float] | str | None = None,
    reference_std: float | Sequence[float] | None = None,
) -> dict[str, Any]:
    """The ``reduction.toml`` document of a simulated scene.

    Only what a lab knows before it calibrates goes in: the camera is the NOMINAL one
    (focal length over pixel pitch, the principal point at the image centre, no
    distortion), whatever the scene's camera says about its principal point or lens.
    The camera as built (an as-built world's intrinsics and distortion) is found by
    ``gonio calibrate camera``, whose ``camera.toml`` then replaces ``[camera]``.

    Parameters
    ----------
    scene
        The NOMINAL :class:`gonio.simulator.scene.Scene` (the session's scene as drawn,
        never a world's as-built camera).
    reference_reflectance
        The reference target's reflectance (the session plan's); left out when None, so
        the reduction takes the manifest's.
    reference_std
        Its standard uncertainty, when known.

    Returns
    -------
    dict
        ``camera`` (K in pixels with pixel centres at integers, CFA pattern, size),
        ``noise`` (gain DN/e-, read noise DN, ISO), ``board``, ``sample`` (m), ``light``
        (disk radius, m; absent for a point or rectangle light) and ``reference``.

    Raises
    ------
    ReductionError
        When the scene's holder has no ChArUco board (the camera pose cannot be measured).
    """
    cam = scene.camera
    w, h = cam.resolution
    f = cam.focal_length / cam.pitch
    # The nominal principal point is the image centre; the simulator puts pixel centres
    # at integer + 0.5, OpenCV at integers.
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    if scene.holder is None or scene.holder.board is None:
        raise ReductionError(
            "the scene's holder has no ChArUco board: the camera pose cannot be measured"
        )
    b = scene.holder.board
    s = cam.sensor
    doc: dict[str, Any] = {
        "camera": {
            "K": K.tolist(),
            "cfa_pattern": str(s.cfa_pattern),
            "width": int(w),
            "height": int(h),
        },
        "noise": {
            "gain": float(s.gain_at_base_iso),
            # the sensor's read noise is in electrons, the model's in DN
            "read_noise": float(s.read_noise * s.gain_at_base_iso),
            "iso": float(s.base_iso),
            "quantisation": True,
        },
        "board": {
            "squares_x": int(b.squares_x),
            "squares_y": int(b.squares_y),
            "square_length": float(b.square_length),
            "marker_length": float(b.marker_length),
            "dictionary": str(b.dictionary),
        },
        "sample": {"width": float(scene.sample.width), "height": float(scene.sample.height)},
    }
    radius = getattr(scene.lights[0], "radius", None)
    if radius is not None:
        doc["light"] = {"radius": float(radius)}
    ref: dict[str, Any] = {}
    if reference_reflectance is not None:
        ref["reflectance"] = _plain(reference_reflectance)
    if reference_std is not None:
        ref["reflectance_std"] = _plain(reference_std)
    if ref:
        doc["reference"] = ref
    return doc


def setup_from_scene(
    scene: Any, reference_reflectance: float | Sequence[float] = 0.99, **options: Any
) -> ReductionSetup:
    """The :class:`~gonio.capture.reduction_config.ReductionSetup` of a simulated scene.

    The same validation as a ``reduction.toml`` file (:func:`reduction_document` through
    :class:`~gonio.capture.reduction_config.ReductionConfig`), without the file; for
    tests and tools that render frames themselves.  ``scene`` is the nominal scene (the
    camera is the nominal one, :func:`reduction_document`).  ``options`` replace setup fields
    (``grid=6``, ``geometry="rig"``).
    """
    doc = reduction_document(scene, reference_reflectance)
    config = validate(ReductionConfig, doc, "simulated scene (reduction setup)")
    setup = setup_from_config(config, "<simulated scene>")
    return setup.replace(**options) if options else setup


def _plain(v: Any) -> Any:
    if isinstance(v, str):
        return v
    a = np.asarray(v, dtype=np.float64)
    return float(a) if a.ndim == 0 else a.tolist()


def scene_of_manifest(manifest: Mapping[str, Any], session: str | os.PathLike) -> Any | None:
    """The simulated scene a session's manifest records, or None for a lab session.

    The manifest's ``simulation`` holds the scene document (or a scene file's path, or
    nothing: the default minimal scene) and an optional resolution override.
    """
    from gonio.simulator.scene import load_scene, parse_scene

    session = Path(session)
    sim = manifest.get("simulation")
    if not sim:
        return None
    doc = sim.get("scene", sim) if isinstance(sim, Mapping) else sim
    if isinstance(doc, str):
        p = Path(doc)
        scene = load_scene(p if p.is_absolute() else session / p)
    elif isinstance(doc, Mapping) and "camera" in doc:
        doc = dict(doc)
        base = doc.pop("_base_dir", None)
        # Relocatable sessions keep the scene's files inside the session (sim/).
        scene = parse_scene(
            doc, f"{session}/manifest.json: simulation.scene", Path(base) if base else session
        )
    else:
        from gonio.simulator.rig_camera import minimal_scene

        scene = parse_scene(minimal_scene(), "minimal scene")
    w = sim.get("width") if isinstance(sim, Mapping) else None
    h = sim.get("height") if isinstance(sim, Mapping) else None
    if w or h:
        W, H = scene.camera.resolution
        cam = scene.camera.model_copy(update={"resolution": (int(w or W), int(h or H))})
        scene = scene.model_copy(update={"camera": cam})
    return scene


def reduction_toml_text(document: Mapping[str, Any]) -> str:
    """The ``reduction.toml`` text of a :func:`reduction_document` (header comment + TOML)."""
    return _HEADER + tomli_w.dumps(dict(document))


def write_reduction_toml(
    session_dir: str | os.PathLike, scene: Any | None = None, *, overwrite: bool = False
) -> Path:
    """Write ``SESSION/reduction.toml`` for a simulated session, atomically.

    Parameters
    ----------
    session_dir
        The session directory (its ``manifest.json`` gives the reference reflectance, and
        the scene when ``scene`` is None).
    scene
        The :class:`gonio.simulator.scene.Scene` the session was rendered with; None reads
        the manifest's ``simulation`` scene.
    overwrite
        Replace a ``reduction.toml`` with other content (by default that is refused: it
        may be a lab's calibration).  The same content is never rewritten.

    Returns
    -------
    Path
        The file.

    Raises
    ------
    SessionError
        Not a simulated session, or another ``reduction.toml`` is there.
    """
    from gonio.capture.manifest import load_manifest

    session = Path(session_dir)
    manifest = load_manifest(session)
    if scene is None:
        scene = scene_of_manifest(manifest, session)
        if scene is None:
            raise SessionError(
                f"{session}: the manifest records no simulated scene: a lab session's "
                f"{CONFIG_FILE} comes from its calibrations (see examples/reduction.toml)"
            )
    ref = manifest.get("reference") or {}
    doc = reduction_document(scene, ref.get("reflectance"), ref.get("reflectance_std"))
    text = reduction_toml_text(doc)
    path = session / CONFIG_FILE
    if path.is_file():
        old = path.read_text(encoding="utf-8")
        if old == text:
            return path
        if not overwrite:
            try:
                same = tomllib.loads(old) == doc
            except tomllib.TOMLDecodeError:
                same = False
            if not same:
                raise SessionError(
                    f"{path} exists with another setup; not replaced (it may be a lab calibration)"
                )
    write_text_atomic(path, text)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gonio.app.sim_reduction SESSION...``: write each session's file."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__.strip().splitlines()[0])
        print("usage: python -m gonio.app.sim_reduction SESSION [SESSION ...]")
        return 0 if args else 2
    for a in args:
        try:
            print(write_reduction_toml(a))
        except GonioError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

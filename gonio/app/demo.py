"""``gonio demo``: a whole simulated measurement session, from servos to fitted BRDF.

The demo lives in the composition root (``gonio.app``) with the CLI: it wires every
subsystem together (a virtual servo bus on a pty driven through dynamixel-sdk, the
simulated camera writing DNG files, reduction with rawpy and radiometric calibration,
fitting with nlopt) through their library APIs -- the capture through
:func:`gonio.capture.sessions.run_session`, which prints nothing.  It writes the rig,
plan and scene files it used next to the session (TOML, with tomli-w), so a user can
rerun any stage by hand.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import click
import numpy as np

from gonio.app.capture_cli import sim_speed_option
from gonio.atomic import write_text_atomic
from gonio.errors import ConfigError, GonioError, SessionError

#: The default ground truth: a glossy plastic-like material.
DEFAULT_MATERIAL = "lambert+ggx albedo=0.50,0.40,0.30 ks=0.2 alpha=0.2"
DEFAULT_POSES = 240
#: The demo's grid reaches theta_i and theta_o of this many degrees (and no further).
MAX_THETA_DEG = 80.0
#: The demo's regions: their directions' spread (deg) seen from camera and light.
REGION_SPREAD_DEG = 0.3
#: The perfect world's reduction (``ReductionSetup`` fields over the session's
#: reduction.toml) = ``--geometry rig --grid 6 --max-region-spread-deg 0.3``.
#: The simulated rig's geometry is exact, so the camera pose comes from the rig's
#: read-back through its kinematics; the board checks it (flagging disagreements).
#: From the board alone, a ~0.04 deg pose error per view at this resolution is a
#: percent of BRDF on a lobe's flank, shared by the pose's regions.
#: Regions of ~5 mm: a region's mean over its spread of directions flattens a lobe's
#: peak in proportion to (spread / lobe width)^2; 6 x 6 regions, each trimmed to a
#: spread of 0.3 deg from the camera and the light (~2.1 mm at normal view, the whole
#: cell along the tilt of a grazing view), keep that below the noise for alpha >= 0.1.
#: The perfect world's rig is exactly its configuration (the demo's own statement about
#: its simulated rig, a self-consistency case), so the budget's assumed joint tolerance
#: (``nominal_joint_std_deg``) is 0 here.
PERFECT_WORLD_REDUCTION: dict[str, Any] = {
    "geometry": "rig",
    "grid": 6,
    "max_region_spread_deg": REGION_SPREAD_DEG,
    "nominal_joint_std_deg": 0.0,
}


# --------------------------------------------------------------------------------------
# Ground truth
@dataclass
class Material:
    """The demo's ground truth: an analytic model with parameters, or a measured file."""

    spec: str
    model: str | None = None
    params: dict[str, list[float]] = field(default_factory=dict)
    file: Path | None = None
    #: ``get_model`` options (``fresnel``, ``g1``), as in ``lambert+ggx[fresnel=schlick]``
    options: dict[str, str] = field(default_factory=dict)

    def scene_brdf(self) -> dict[str, Any]:
        if self.file is not None:
            return {"file": str(self.file)}
        brdf: dict[str, Any] = {"model": self.model, "params": self.params}
        if self.options:
            brdf["options"] = dict(self.options)
        return brdf

    def truth(self) -> Any:
        """An object with ``eval(wi, wo) -> (..., 3)``."""
        if self.file is not None:
            from gonio.brdf import load

            return load(self.file)
        from gonio.brdf import get_model

        return get_model(self.model, **self.options).bind(self.params)

    def same_model(self, name: str, options: dict[str, Any]) -> bool:
        """Whether a fit of model ``name`` with ``options`` has this truth's parameters
        (a lobe's default option, e.g. ``fresnel = "none"``, written or not)."""
        if self.model is None or name != self.model:
            return False
        from gonio.brdf import get_model

        def lobe_options(opts: dict[str, Any]) -> list[dict[str, str]]:
            return [dict(lobe.options) for lobe in get_model(name, **opts).lobes]

        return lobe_options(options) == lobe_options(self.options)


def _split_head(spec: str) -> tuple[str, str]:
    """``spec`` split at its first blank outside brackets: a model spec's options may be
    written with blanks (``lambert+ggx[fresnel=schlick, g1=rational]``), as ``--model``
    takes them."""
    depth = 0
    for i, ch in enumerate(spec):
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth = max(depth - 1, 0)
        elif ch.isspace() and depth == 0:
            return spec[:i], spec[i:]
    return spec, ""


def parse_material(spec: str) -> Material:
    """Parse ``--material``.

    Forms: ``"MODEL k=v k=v1,v2,v3 ..."`` (an analytic model, spelt as ``gonio fit
    --model`` spells it, options included: ``lambert+ggx[fresnel=schlick] f0=0.04``;
    omitted parameters take the model's defaults; three comma-separated values are R, G,
    B), a path to a measured file (RGL ``.bsdf`` or MERL ``.binary``), or ``rgl:NAME``
    for a file of the shared reference data (``$GONIO_REFDATA/rgl/NAME_rgb.bsdf``).
    """
    spec = spec.strip()
    if not spec:
        raise ConfigError("--material is empty: give a model with parameters or a file")
    if spec.startswith("rgl:"):
        name = spec[4:]
        root = Path(os.environ.get("GONIO_REFDATA", Path.cwd().parent / "shared" / "data"))
        path = root / "rgl" / f"{name}_rgb.bsdf"
        if not path.is_file():
            raise ConfigError(
                f"--material {spec}: {path} not found (set GONIO_REFDATA to the folder "
                "holding rgl/, or give the file's path)"
            )
        return Material(spec, file=path.resolve())
    if Path(spec).is_file():  # a measured file, its name spaces and all
        tokens = [spec]
    else:
        head, rest = _split_head(spec)
        tokens = [head, *rest.split()]
    looks_like_file = "/" in tokens[0] or Path(tokens[0]).suffix.lower() in (".bsdf", ".binary")
    if looks_like_file and not Path(tokens[0]).is_file():
        raise ConfigError(
            f"--material {tokens[0]}: no such file (expected a measured BRDF file, "
            ".bsdf or .binary, a model name, or rgl:NAME)"
        )
    if Path(tokens[0]).is_file():
        from gonio.brdf import load

        load(tokens[0])  # fail now, with the reader's message, not mid-session
        return Material(spec, file=Path(tokens[0]).resolve())
    from gonio.brdf import get_model
    from gonio.brdf.registry import parse_model_spec

    try:
        name, options = parse_model_spec(tokens[0])
        model = get_model(name, **options)
    except GonioError as exc:
        raise ConfigError(f"--material: {exc}") from None
    params: dict[str, list[float]] = {k: [float(v)] * 3 for k, v in model.defaults.items()}
    for tok in tokens[1:]:
        if "=" not in tok:
            raise ConfigError(f"--material: '{tok}' is not of the form name=value")
        k, v = tok.split("=", 1)
        if k not in model.param_names:
            raise ConfigError(
                f"--material: model {name} has no parameter '{k}' "
                f"(it has {', '.join(model.param_names)})"
            )
        try:
            vals = [float(x) for x in v.split(",")]
        except ValueError:
            raise ConfigError(f"--material: {k}={v} is not a number or three numbers") from None
        if len(vals) not in (1, 3):
            raise ConfigError(f"--material: {k} takes one value or three (R,G,B), got {len(vals)}")
        params[k] = vals * 3 if len(vals) == 1 else vals
    model.check_params({k: np.asarray(v) for k, v in params.items()})
    # the canonical name ("Lambert+GGX" -> "lambert+ggx"), as the fit reports it
    return Material(spec, model=model.name, params=params, options=options)


# --------------------------------------------------------------------------------------
# Files the demo writes
def _grid_for(n_poses: int) -> dict[str, Any]:
    """A spherical grid whose isotropic, reciprocity-reduced pose count is near ``n_poses``."""
    from gonio.capture.plan import expand_plan, plan_from_dict

    candidates = []
    for n_i in range(2, 12):
        for n_o in range(3, 24):
            for phis in ([0, 180], [0, 90, 180], [0, 45, 90, 135, 180]):
                grid = {
                    "kind": "spherical",
                    "theta_i_deg": [float(round(v, 3)) for v in np.linspace(0, MAX_THETA_DEG, n_i)],
                    "phi_i_deg": [0.0],
                    "theta_o_deg": [float(round(v, 3)) for v in np.linspace(0, MAX_THETA_DEG, n_o)],
                    "phi_o_deg": [float(p) for p in phis],
                }
                # About 3/4 of such a grid survives the reductions and exclusions.
                candidates.append((abs(0.75 * n_i * n_o * len(phis) - n_poses), grid))
    candidates.sort(key=lambda c: c[0])
    best: tuple[float, dict[str, Any]] | None = None
    for _, grid in candidates[:12]:  # count exactly only the most promising few
        n = len(expand_plan(plan_from_dict(_plan_dict(grid, 0, 64, 48))).poses)
        if best is None or abs(n - n_poses) < best[0]:
            best = (abs(n - n_poses), grid)
    assert best is not None
    return best[1]


#: A realistic demo repeats its reference group after this many sample poses: ~30-60 s of
#: rig time, against the light's warm-up constant of 300 s or more.
REFERENCE_EVERY_POSES = 8


def _plan_dict(
    grid: dict[str, Any], seed: int, width: int, height: int, *, lab: bool = False
) -> dict[str, Any]:
    """The demo's plan; ``lab``: with the radiometric calibration a lab's session shoots
    (darks, flats, a reference group every ``REFERENCE_EVERY_POSES`` poses)."""
    plan = {
        "name": "gonio demo",
        "description": "isotropic in-plane and out-of-plane grid, adaptive brackets",
        "seed": seed,
        "settle_s": 0.0,
        "grid": grid,
        "reductions": {"isotropic": True, "reciprocity": True},
        "exclusions": {
            "grazing_limit_deg": MAX_THETA_DEG,
            "min_separation_deg": 12,
            "check_rig": True,
        },
        "bracket": {
            "policy": "adaptive",
            "exposure_time_s": 0.02,
            "iso": 100,
            "f_number": 8.0,
            "max_frames": 4,
        },
        "darks": {"count": 0},
        "reference": {
            "when": "start",
            "reflectance": 0.99,
            "poses": [
                {"theta_i_deg": 0, "theta_o_deg": 40, "phi_o_deg": 180},
                {"theta_i_deg": 40, "theta_o_deg": 0},
            ],
        },
        "simulation": {"scene": "scene.toml", "width": width, "height": height},
    }
    if lab:
        # A realistic world's light warms up over the session (0.5-3 %, tau 5-25 min of
        # rig time) and its camera has fixed patterns: with one reference group at the
        # start and no darks or flats the fit's albedo and ks came out 0.75-1.95 % low
        # (world seed 11), inside the wide drift and flat terms that then stand in the
        # budget, but a lab would shoot the calibration instead.
        plan["darks"] = {"count": 2}
        plan["flats"] = {"count": 4}
        plan["reference"]["every_poses"] = REFERENCE_EVERY_POSES
    return plan


def _toml(d: dict[str, Any]) -> str:
    """A TOML document (tomllib only reads)."""
    import tomli_w

    return tomli_w.dumps(d)


def scene_document(material: Material, width: int, height: int) -> dict[str, Any]:
    """The simulated camera's scene with ``material`` as the sample's BRDF."""
    from gonio.simulator.rig_camera import minimal_scene

    scene = minimal_scene(width, height)
    scene["sample"]["brdf"] = material.scene_brdf()
    # The reduction finds the holder's ChArUco board to measure the camera pose: it needs
    # about 320 px across a 30 deg field of view at the camera arm's 0.4 m.
    scene["camera"]["fov_deg"] = 30.0
    # A small source: a 1 cm disk at 0.5 m blurs a GGX alpha = 0.1 lobe by ~2 % in alpha,
    # which the fitted point-source model would report as a (real) bias.
    scene["lights"][0]["radius"] = 0.002
    # Edge pixels anti-aliased (3 x 3 sub-rays): with one ray per pixel the board's
    # squares have stair-step edges, its corners come out 0.3-0.4 px off (RMS) and the
    # board's camera direction 0.6-0.9 deg off the (exact) rig's near normal views, so
    # a quarter of the poses were flagged as geometry mismatches.  With 3 x 3: RMS
    # ~0.11 px, within 0.26 deg; capture ~15 % slower (4 x 4 gains little more and costs
    # ~50 %).
    scene["render"]["antialias"] = 3
    # The board print's edges by sub-rays, not their exact area coverage (the scene's
    # default since schema 2, ~1.2x faster renders): with the exact coverage the demo's
    # fitted values moved in the 4th digit (albedo R 0.49998 -> 0.49956, ks B 0.20005 ->
    # 0.20032; 36 fewer region samples kept), and the demo keeps today's values.
    scene["render"]["print_antialias"] = "rays"
    return scene


# --------------------------------------------------------------------------------------
# The run
@dataclass
class DemoResult:
    out: Path
    session: Path
    poses: int
    frames: int
    model: str
    params: dict[str, list[float]]
    sigma: dict[str, list[float]]
    truth: dict[str, list[float]] | None
    rel_error: dict[str, list[float]]
    z: dict[str, list[float]]
    brdf_rel_error_median: float
    seconds: dict[str, float]
    report: Path
    material: str
    world: str = "perfect"
    world_seed: int | None = None
    calibration: Any = None
    retention: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            "session": str(self.session),
            "material": self.material,
            "poses": self.poses,
            "frames": self.frames,
            "model": self.model,
            "params": self.params,
            "truth": self.truth,
            "rel_error": self.rel_error,
            "sigma": self.sigma,
            "z": self.z,
            "brdf_rel_error_median": self.brdf_rel_error_median,
            "seconds": self.seconds,
            "report": str(self.report),
            "world": self.world,
            "world_seed": self.world_seed,
            "calibration": None if self.calibration is None else self.calibration.to_json(),
            "retention": self.retention,
        }


def _list(v: Any) -> list[float]:
    return [float(x) for x in np.broadcast_to(np.asarray(v, dtype=float), (3,))]


def run_demo(
    out: Path,
    material: Material,
    *,
    seed: int = 0,
    n_poses: int = DEFAULT_POSES,
    width: int = 320,
    height: int = 240,
    model: str = "auto",
    quiet: bool = False,
    say: Callable[[str], None] = print,
    time_scale: float | str = "virtual",
    world: str = "perfect",
    world_seed: int = 0,
    figure_worker: bool = True,
    overlap: bool = True,
) -> DemoResult:
    """Run capture, reduction and fit of a simulated session into ``out``.

    ``quiet`` hides the capture's progress bar; ``say`` receives one line per stage.
    ``time_scale`` is the virtual bus's speed: ``"virtual"`` (servo time advanced by the
    commanded motion: no waiting) or a speed-up factor over the wall clock (to watch).
    ``world`` is the simulator's as-built world: ``"perfect"`` (the rig exactly as
    configured: no calibration needed) or ``"realistic"`` (errors drawn from
    ``world_seed``): then the camera and the rig are calibrated first, the session runs
    on the calibrated rig and the reduction uses the calibrated camera.
    ``figure_worker``: draw the figures in a second process beside the main one
    (:mod:`gonio.app.demo_figures`); False: all in this process (the same files).
    ``overlap``: render the capture's next poses and reduce its finished ones in two
    processes beside it (:mod:`gonio.app.render_ahead`, :mod:`gonio.app.reduce_ahead`;
    perfect world); False: the camera renders each pose when it shoots and the
    reduction starts after the capture (the same files).
    """

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise SessionError(f"{out} exists and is not empty: choose a new --out (nothing touched)")
    from gonio.app.demo_figures import figure_worker as start_figures
    from gonio.app.reduce_ahead import ReduceAhead
    from gonio.app.render_ahead import RenderAhead

    t_all = time.perf_counter()
    # Started first, before any thread: the figures' imports run beside the capture (see
    # gonio.app.demo_figures); in a perfect world the capture's poses are rendered
    # ahead (gonio.app.render_ahead) and reduced as they are done (gonio.app.
    # reduce_ahead), both on the second core.  The reducer is forked before the
    # renderer, which ends first: neither holds the other's pipe open.
    overlap = overlap and world == "perfect"
    with (
        start_figures(enabled=figure_worker) as figures,
        ReduceAhead(enabled=overlap) as reducer,
        RenderAhead(enabled=overlap) as ahead,
    ):
        return _run_demo(
            out, material, figures, t_all, seed=seed, n_poses=n_poses, width=width,
            height=height, model=model, quiet=quiet, say=say, time_scale=time_scale,
            world=world, world_seed=world_seed, render_ahead=ahead, reducer=reducer,
        )  # fmt: skip


def _run_demo(
    out: Path,
    material: Material,
    figures: Any,
    t_all: float,
    *,
    seed: int,
    n_poses: int,
    width: int,
    height: int,
    model: str,
    quiet: bool,
    say: Callable[[str], None],
    time_scale: float | str,
    world: str,
    world_seed: int,
    render_ahead: Any = None,
    reducer: Any = None,
) -> DemoResult:
    from gonio.app.simulation import run_simulated_session
    from gonio.capture.manifest import load_manifest
    from gonio.capture.reduce import reduce_session, resolve_setup
    from gonio.dataset import load_samples
    from gonio.fitting import fit
    from gonio.rig.config import virtual_rig_document

    seconds: dict[str, float] = {}

    t = time.perf_counter()
    grid = _grid_for(n_poses)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "rig.toml", virtual_rig_document())
    write_text_atomic(
        out / "plan.toml",
        "# Written by gonio demo: rerun with gonio capture run plan.toml --rig rig.toml "
        "--camera simulated --out S/\n"
        + _toml(_plan_dict(grid, seed, width, height, lab=world != "perfect"))
        + "\n",
    )
    write_text_atomic(
        out / "scene.toml",
        "# Written by gonio demo: the simulated camera's scene (gonio sim render scene.toml)\n"
        + _toml(scene_document(material, width, height))
        + "\n",
    )
    seconds["setup"] = time.perf_counter() - t

    rig_path = out / "rig.toml"
    calibration = None
    if world != "perfect":
        from gonio.app.demo_calibrations import calibrate_simulated_rig

        calibration = calibrate_simulated_rig(
            out,
            out / "rig.toml",
            out / "scene.toml",
            world=world,
            world_seed=world_seed,
            size=(width, height),
            time_scale=time_scale,
            quiet=quiet,
            say=say,
        )
        seconds.update({f"calibrate_{k}": v for k, v in calibration.seconds.items()})
        rig_path = calibration.rig_file

    session = out / "session"
    say(f"capturing into {session} (virtual servo bus on a pty, simulated camera)")
    t = time.perf_counter()
    # The perfect world's poses are reduced as the capture finishes them, by the
    # reducer process (gonio.app.reduce_ahead; the same files as a reduction after it).
    live = calibration is None and reducer is not None and reducer.active
    subscribers = [reducer.subscriber(session, **PERFECT_WORLD_REDUCTION)] if live else []
    # What 'gonio capture run plan.toml --rig rig.toml --camera simulated' does, through
    # the library: the API prints nothing, the demo says what it does through ``say``.
    run_simulated_session(
        session,
        out / "plan.toml",
        rig_path,
        time_scale,
        world=None if world == "perfect" else world,
        world_seed=None if world == "perfect" else world_seed,
        quiet=quiet,
        render_ahead=render_ahead,
        subscribers=subscribers,
    )
    if render_ahead is not None:
        render_ahead.close()  # its core is the reduction's and the figures' from here
    say(f"session {session} completed")
    seconds["capture"] = time.perf_counter() - t
    say("reducing RAW brackets to BRDF samples")
    t = time.perf_counter()
    if live:
        red = reducer.finish(plot=True)
    elif calibration is None:
        setup = dataclasses.replace(
            resolve_setup(session, load_manifest(session)), **PERFECT_WORLD_REDUCTION
        )
        red = reduce_session(session, setup=setup, plot=True)
    else:
        # = --camera-calibration camera.toml --grid 6 --max-region-spread-deg 0.3: the
        # calibrated camera; each view's pose from the board where it shows enough of it
        # and its covariance moves the directions less than the calibrated rig's
        # (geometry "auto"), else from the calibrated rig, which the board checks; the
        # rig gives the light.
        setup = resolve_setup(
            session, load_manifest(session), camera_calibration=calibration.camera_file
        )
        setup = dataclasses.replace(setup, grid=6, max_region_spread_deg=REGION_SPREAD_DEG)
        red = reduce_session(session, setup=setup, plot=True)
    seconds["reduce"] = time.perf_counter() - t

    say(f"fitting (model={model})")
    t = time.perf_counter()
    samples = load_samples(red.path)
    # Covariance scaled by the observed reduced chi-square (as scipy's curve_fit does by
    # default): it then also covers what the noise model leaves out.
    result = fit(samples, model=model, absolute_sigma=False)
    if not result.success:
        raise GonioError(f"the fit did not succeed: {result.message}")
    seconds["fit"] = time.perf_counter() - t

    t = time.perf_counter()
    params = {k: _list(v) for k, v in result.params.items()}
    sigma = {k: _list(v) for k, v in result.std.items()}
    truth = material.params if material.model else None
    rel_error: dict[str, list[float]] = {}
    z: dict[str, list[float]] = {}
    if truth is not None and material.same_model(result.model, result.model_options):
        for k, tv in truth.items():
            if k in params:
                f, s, tr = np.array(params[k]), np.array(sigma[k]), np.array(tv)
                rel_error[k] = _list(np.abs(f - tr) / np.where(tr != 0, np.abs(tr), 1.0))
                with np.errstate(divide="ignore", invalid="ignore"):
                    z[k] = _list(np.where(s > 0, (f - tr) / s, np.nan))
    # Whatever model was chosen, how far the fitted BRDF is from the truth on the samples.
    ok = samples.valid
    f_true = material.truth().eval(samples.wi[ok], samples.wo[ok])
    f_fit = result.bind().eval(samples.wi[ok], samples.wo[ok])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(f_fit - f_true) / np.abs(f_true)
    brdf_err = float(np.nanmedian(rel)) if rel.size else math.nan

    frames = _count_frames(session)
    from gonio.app.demo_report import write_report

    report = write_report(
        out,
        session,
        samples,
        result,
        material,
        red,
        params,
        sigma,
        truth,
        rel_error,
        z,
        brdf_err,
        seconds,
        frames,
        calibration,
        figures=figures,
    )
    seconds["report"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t_all
    return DemoResult(
        out=out,
        session=session,
        poses=_count_poses(session),
        frames=frames,
        model=result.spec,
        params=params,
        sigma=sigma,
        truth=truth,
        rel_error=rel_error,
        z=z,
        brdf_rel_error_median=brdf_err,
        seconds={k: round(v, 3) for k, v in seconds.items()},
        report=report,
        material=material.spec,
        world=world,
        world_seed=None if world == "perfect" else world_seed,
        calibration=calibration,
        retention=red.summary.get("retention"),
    )


def _journal(session: Path) -> list[dict[str, Any]]:
    from gonio.capture.journal import read_journal

    return read_journal(session / "journal.jsonl")


def _count_frames(session: Path) -> int:
    return sum(1 for r in _journal(session) if r.get("type") == "shot")


def _count_poses(session: Path) -> int:
    manifest = json.loads((session / "manifest.json").read_text())
    return sum(1 for s in manifest["schedule"] if s.get("kind") == "sample")


#: The camera size of ``--world realistic`` unless ``--resolution`` says: the rig
#: calibration needs the board corners' precision.
REALISTIC_RESOLUTION = (480, 360)


# --------------------------------------------------------------------------------------
@click.command("demo")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="New directory for everything the demo writes [default: ./gonio-demo-<time>].",
)
@click.option(
    "--material",
    default=DEFAULT_MATERIAL,
    show_default=True,
    help='Ground truth: "MODEL name=value ..." (three comma-separated values for R,G,B; '
    'MODEL as for --model, options included: "lambert+ggx[fresnel=schlick] f0=0.04"), '
    "a measured file (.bsdf, .binary), or rgl:NAME from $GONIO_REFDATA/rgl.",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Seed of the session: the same seed gives the same RAW files.",
)
@click.option(
    "--poses",
    "n_poses",
    type=click.IntRange(10, 5000),
    default=DEFAULT_POSES,
    show_default=True,
    help="About how many sample poses to measure.",
)
@click.option(
    "--model",
    default="auto",
    show_default=True,
    help="Model to fit, spelt as for gonio fit (e.g. lambert+ggx, "
    "lambert+ggx[fresnel=schlick]; auto: choose by information criterion and gloss).",
)
@click.option(
    "--resolution",
    type=(click.IntRange(8, 8192), click.IntRange(8, 8192)),
    default=None,
    help="Simulated camera resolution, pixels (width height) [default: 320 240; "
    "--world realistic: 480 360].",
)
@click.option(
    "--sim-speed",
    metavar="virtual|FACTOR",
    default="virtual",
    show_default=True,
    callback=sim_speed_option,
    help='Virtual servo bus speed: "virtual" advances servo time by the commanded motion '
    "(no waiting for it); a number runs servo time that many times faster than the wall "
    "clock, to watch the arms (e.g. 20). Same journal and results either way.",
)
@click.option(
    "--world",
    type=click.Choice(["perfect", "realistic"]),
    default="perfect",
    show_default=True,
    help="The simulated rig as built: perfect (exactly its configuration) or realistic "
    "(servo offsets, backlash, misaligned axes, lens distortion...): then the camera and "
    "the rig are calibrated first, as in the README's lab path.",
)
@click.option(
    "--world-seed",
    type=click.IntRange(0),
    default=None,
    help="Seed of a realistic world's errors [default: drawn at random and printed].",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of tables.")
def demo(
    out: Path | None,
    material: str,
    seed: int,
    n_poses: int,
    model: str,
    resolution: tuple[int, int] | None,
    sim_speed: float | str,
    world: str,
    world_seed: int | None,
    as_json: bool,
) -> None:
    """Run a whole simulated measurement session: no hardware, no network.

    \b
    1. starts a virtual Dynamixel bus on a pseudo-terminal and drives it through
       dynamixel-sdk, exactly as the lab rig;
    2. shoots adaptive RAW brackets with the simulated camera (the rendering equation,
       a sensor noise model, DNG files);
    3. reduces them (rawpy, HDR merge, radiometric calibration) to samples.h5;
    4. fits a BRDF model (nlopt) and compares it with the ground truth;
    5. writes report.md with plots, and prints a summary.

    \b
    With --world realistic the simulated rig is not its own drawing: the camera and
    the rig are calibrated first (two calibration sessions), the session runs on the
    calibrated rig and shoots darks, flats and a reference group every 8 poses (the
    light drifts as it warms up), the reduction uses the calibrated camera, and the
    report shows the calibrations' residuals and estimates beside the fit.

    \b
    Examples:
      gonio demo
      gonio demo --world realistic --world-seed 7
      gonio demo --material "lambert albedo=0.7" --poses 100
      gonio demo --material "lambert+ggx[fresnel=schlick]" --model "lambert+ggx[fresnel=schlick]"
      gonio demo --material rgl:vch_golden_yellow --json
    Ctrl-C stops it with the servos parked and torque off; continue the capture with
    'gonio capture resume OUT/session'.
    """
    from rich.console import Console

    console = Console(stderr=as_json)
    out = out or Path(f"gonio-demo-{datetime.now():%Y%m%d-%H%M%S}")
    mat = parse_material(material)
    # Checked before the capture, which takes minutes, rather than at the fit.
    if model != "auto":
        from gonio.brdf import get_model
        from gonio.brdf.registry import parse_model_spec

        try:
            name, options = parse_model_spec(model)
            get_model(name, **options)
        except GonioError as exc:
            raise ConfigError(f"--model: {exc}") from None
    from rich.markup import escape

    # escaped: a model spec's options ("[fresnel=schlick]") read as rich markup otherwise
    say = (lambda s: None) if as_json else (lambda s: console.print(f"[bold cyan]>[/] {escape(s)}"))
    if world != "perfect" and world_seed is None:
        import secrets

        world_seed = secrets.randbelow(2**31)
    if world != "perfect":
        if resolution is None:
            # The calibrations need the corners' precision: at 320 x 240 the rig plan
            # cannot tell the tilt's gravity compliance from its zero offset (and the
            # rig calibration refuses, naming it).
            resolution = REALISTIC_RESOLUTION
        say(
            f"as-built world: {world}, seed {world_seed} (replay with --world-seed "
            f"{world_seed}); camera {resolution[0]} x {resolution[1]}"
        )
    if resolution is None:
        resolution = (320, 240)
    try:
        res = run_demo(
            out,
            mat,
            seed=seed,
            n_poses=n_poses,
            width=resolution[0],
            height=resolution[1],
            model=model,
            quiet=as_json,
            say=say,
            time_scale=sim_speed,
            world=world,
            world_seed=world_seed or 0,
        )
    except KeyboardInterrupt:
        console.print(
            f"[yellow]interrupted[/]: servos parked, torque off. Continue the capture with "
            f"'gonio capture resume {escape(str(out / 'session'))}'."
        )
        raise SystemExit(130) from None
    if as_json:
        click.echo(json.dumps(res.to_json(), indent=1, default=float))
        return
    _print_summary(console, res)


def retention_table(ret: dict[str, Any]) -> Any:
    """A rich table of ``reduction.json``'s ``"retention"``: kept of the planned region
    samples by theta band (the larger of theta_i and theta_o), and in all up to
    ``up_to_deg``."""
    from rich.table import Table

    def pct(f: float | None) -> str:
        return "-" if f is None else f"{f:.1%}"

    t = Table(
        "theta band (deg)",
        "planned",
        "kept",
        "retained",
        title=f"region samples kept, by max(theta_i, theta_o) (up to {ret['up_to_deg']:g} deg)",
    )
    for b in ret["bands"]:
        lo, hi = b["theta_deg"]
        t.add_row(f"{lo:g}-{hi:g}", str(b["planned"]), str(b["kept"]), pct(b["fraction"]))
    t.add_row(
        f"[bold]0-{ret['up_to_deg']:g}[/]",
        f"[bold]{ret['planned']}[/]",
        f"[bold]{ret['kept']}[/]",
        f"[bold]{pct(ret['fraction'])}[/]",
    )
    src = ", ".join(f"{k} {v}" for k, v in ret.get("geometry_source", {}).items())
    if src:
        t.caption = f"geometry of the kept samples: {src}"
    return t


def _print_summary(console: Any, res: DemoResult) -> None:
    from rich.markup import escape
    from rich.table import Table

    console.print(
        f"\n[bold]{res.poses}[/] poses, [bold]{res.frames}[/] frames; "
        f"chosen model [bold]{escape(res.model)}[/] (truth: {escape(res.material)})"
    )
    t = Table(
        "parameter",
        "channel",
        "fitted",
        "sigma",
        "truth",
        "rel. error",
        "z",
        title="fitted against true parameters",
    )
    for k, v in res.params.items():
        for c, name in enumerate("RGB"):
            tr = res.truth.get(k) if res.truth else None
            t.add_row(
                k,
                name,
                f"{v[c]:.5g}",
                f"{res.sigma[k][c]:.2g}",
                f"{tr[c]:.5g}" if tr else "-",
                f"{res.rel_error[k][c]:.2%}" if k in res.rel_error else "-",
                f"{res.z[k][c]:+.2f}" if k in res.z else "-",
            )
    console.print(t)
    console.print(
        f"median relative BRDF error against the truth on the samples: "
        f"{res.brdf_rel_error_median:.2%}"
    )
    if res.retention:
        console.print(retention_table(res.retention))
    st = Table("stage", "seconds", title="time per stage")
    for k, v in res.seconds.items():
        st.add_row(k, f"{v:.1f}")
    console.print(st)
    console.print(
        f"report: [bold]{escape(str(res.report))}[/]   session: {escape(str(res.session))}"
    )

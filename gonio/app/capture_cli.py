"""``gonio capture``: plan, run, resume, inspect and reduce measurement sessions.

The ``plan``/``run``/``resume``/``inspect`` commands are thin callers of the session API
(:mod:`gonio.capture.sessions`) with the devices of :mod:`gonio.app.devices`; ``reduce``
and ``calibrate-noise`` live with the reduction (:mod:`gonio.capture.reduce_cli`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from gonio.cli import LazyGroup
from gonio.errors import SessionError

__all__ = ["capture", "inspect_cmd", "plan_cmd", "resume_cmd", "run_cmd"]


@click.group(
    cls=LazyGroup,
    lazy_commands={
        "reduce": "gonio.capture.reduce_cli:reduce_cmd",
        "calibrate-noise": "gonio.capture.reduce_cli:calibrate_noise_cmd",
    },
)
def capture() -> None:
    """Measurement sessions: dry-run a plan, capture, resume, reduce to BRDF samples."""


def _fmt_duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}h{m:02d}m{sec:02d}s" if h else (f"{m}m{sec:02d}s" if m else f"{sec}s")


def _load_rig(rig_path: str | None):
    from gonio.rig.config import default_rig_config, load_rig_config

    return load_rig_config(rig_path) if rig_path else default_rig_config()


# --------------------------------------------------------------------------------------
@capture.command("plan")
@click.argument("plan_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--rig",
    "rig_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Rig configuration TOML (default: the built-in four-servo preset).",
)
@click.option("--show-poses", is_flag=True, help="List every pose in visiting order.")
@click.option("--json", "as_json", is_flag=True, help="Print the dry run as JSON.")
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Save a polar plot of the poses (measured and excluded) to this PNG.",
)
@click.option("--force", is_flag=True, help="Overwrite an existing --plot file.")
def plan_cmd(
    plan_file: Path,
    rig_file: str | None,
    show_poses: bool,
    as_json: bool,
    plot: Path | None,
    force: bool,
) -> None:
    """Dry-run a measurement plan: nothing moves.

    \b
    Prints how many poses the grid gives, how many the symmetry reductions remove, every
    excluded pose with its reason (grazing limit, camera shadowing the light, unreachable
    or colliding on this rig), the poses the rig would refuse in the visiting order (the
    path from the previous pose included: the dry run executes the session's own plan
    against the kinematics), the total servo travel time of the optimised visiting
    order against raster order, and the estimated duration.

    \b
    Example:
      gonio capture plan examples/plan.toml --rig rig.toml --plot poses.png
    """
    from rich.console import Console
    from rich.markup import escape as esc
    from rich.table import Table

    from gonio.capture.plan import load_plan
    from gonio.capture.sessions import plan_session

    if plot is not None:
        _check_image_path(plot, force, "--plot")
    plan = load_plan(plan_file)
    cfg = _load_rig(rig_file)
    with _DryRunProgress() as progress:
        dry = plan_session(plan, cfg, progress=progress)
    sched = dry.schedule
    ex = sched.expanded
    summary = dry.summary(with_poses=show_poses or as_json)
    if plot is not None:
        _plot_poses(plot, sched)
    if as_json:
        click.echo(json.dumps(summary, indent=1))
        return
    n_sample, n_ref = summary["sample_poses"], summary["reference_poses"]
    con = Console()
    # escaped: names, paths and messages may hold brackets, which rich reads as markup
    con.print(f"[bold]{esc(plan.name)}[/]  ({esc(str(plan_file))})  rig: {esc(cfg.name)}")
    con.print(
        f"grid {ex.n_grid} poses, {ex.n_reduced} removed by symmetry, "
        f"{len(ex.excluded)} excluded -> [bold]{n_sample}[/] sample poses"
        + (f" + {n_ref} reference" if n_ref else "")
    )
    if ex.excluded and plan.adaptive is not None:
        # the candidate pool's exclusions: thousands at a fine pool step; counted by code
        from collections import Counter

        counts = Counter(e.code for e in ex.excluded)
        con.print(
            f"adaptive: {summary['adaptive']['pool']} candidate poses, seed design "
            f"{n_sample}, batches of {plan.adaptive.batch_poses} up to "
            f"{plan.adaptive.max_poses} poses; excluded from the pool: "
            + ", ".join(f"{n} {code}" for code, n in counts.most_common())
        )
    elif ex.excluded:
        t = Table(
            "theta_i", "phi_i", "theta_o", "phi_o", "code", "reason", title="excluded poses"
        )  # fmt: skip
        for e in ex.excluded:
            a = e.pose.angles_deg()
            t.add_row(
                *(f"{a[k]:.1f}" for k in ("theta_i_deg", "phi_i_deg", "theta_o_deg", "phi_o_deg")),
                e.code,
                esc(e.reason),
            )
        con.print(t)
    if sched.refused:
        t = Table("step", "code", "reason", title="refused in the visiting order (dry run)")
        for r in sched.refused:
            t.add_row(str(r.step), r.code, esc(r.message))
        con.print(t)
    if show_poses:
        t = Table("#", "kind", "theta_i", "phi_i", "theta_o", "phi_o", title="visiting order")
        for k, s in enumerate(sched.steps):
            if s["kind"] in ("dark", "flat"):
                t.add_row(str(k), s["kind"], "", "", "", "")
                continue
            t.add_row(
                str(k),
                s["kind"],
                *(f"{s[n]:.1f}" for n in ("theta_i_deg", "phi_i_deg", "theta_o_deg", "phi_o_deg")),
            )
        con.print(t)
    ratio = (
        sched.raster_travel_time_s / sched.travel_time_s if sched.travel_time_s > 0 else math.inf
    )
    con.print(
        f"servo travel {_fmt_duration(sched.travel_time_s)} in the optimised order "
        f"({_fmt_duration(sched.raster_travel_time_s)} in raster order, {ratio:.1f}x)"
    )
    con.print(
        f"estimated duration [bold]{_fmt_duration(sched.estimated_duration_s)}[/] "
        f"(bracket policy {plan.bracket.policy!r}; nothing was moved)"
    )


def _rounds_table(rounds):
    """An adaptive session's rounds: poses chosen, the winning fit's rel sigma, stop."""
    from rich.markup import escape
    from rich.table import Table

    t = Table(
        "round", "chosen", "before", "model", "rel sigma", "advise s", "batch s (rig)", "stop",
        title="adaptive rounds (chosen: poses; before: poses measured; batch s: its estimated "
        "capture time on the rig)",
    )  # fmt: skip
    for r in rounds:
        rel = r.get("rel_sigma") or {}
        rel_s = ", ".join(
            f"{k} {100 * v:.3g} %" for k, v in rel.items() if isinstance(v, int | float)
        )
        t.add_row(
            str(r.get("round")),
            str(r.get("poses")),
            str(r.get("poses_done", "")),
            escape(str(r.get("model") or "")),  # a spec's "[fresnel=schlick]" is not markup
            rel_s,
            f"{r['advise_s']:.2f}" if isinstance(r.get("advise_s"), int | float) else "",
            f"{r['batch_time_s']:.0f}" if isinstance(r.get("batch_time_s"), int | float) else "",
            escape(str(r.get("stop") or "")),
        )
    return t


class _DryRunProgress:
    """A progress bar on stderr for the dry run's stages, shown only when it takes long
    (a few seconds: large grids), so a quick plan prints nothing extra."""

    SHOW_AFTER_S = 2.0

    def __init__(self) -> None:
        import time

        from rich.console import Console

        from gonio.progress import task_progress

        self._clock = time.monotonic
        self._t0 = self._clock()
        self._progress = task_progress(
            "[bold]{task.description}", eta=False, console=Console(stderr=True), transient=True
        )
        self._tasks: dict[str, int] = {}
        self._shown = False

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self._shown:
            if self._clock() - self._t0 < self.SHOW_AFTER_S:
                return
            self._progress.start()
            self._shown = True
        if stage not in self._tasks:
            self._tasks[stage] = self._progress.add_task(stage, total=total)
        self._progress.update(self._tasks[stage], completed=done, total=total)

    def __enter__(self) -> _DryRunProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._shown:
            self._progress.stop()


def _check_image_path(path: Path, force: bool, hint: str) -> None:
    """Refuse, before any work, a plot path matplotlib cannot write or that would clobber."""
    if path.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise click.BadParameter(
            f"expected a .png, .pdf or .svg file name, got '{path.name}'", param_hint=hint
        )
    if not path.parent.is_dir():
        raise click.BadParameter(
            f"folder '{path.parent}' of {path.name} does not exist; create it first",
            param_hint=hint,
        )
    if path.exists() and not force:
        raise click.BadParameter(
            f"'{path}' exists; pass --force to overwrite it or choose another file",
            param_hint=hint,
        )


def sim_speed_option(ctx, param, value: str | None) -> float | str | None:
    """``--sim-speed``: ``virtual`` or a speed-up factor (click callback)."""
    if value is None:
        return None
    from gonio.simulator.servo_clock import parse_time_scale

    # Zero, negative or nan time would stall or crash the virtual servos mid-session.
    try:
        return parse_time_scale(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _plot_poses(path: Path, sched) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 2, subplot_kw={"projection": "polar"}, figsize=(9, 4.5))
    for ax, which, title in (
        (axes[0], "i", "light (incident)"),
        (axes[1], "o", "camera (outgoing)"),
    ):
        steps = [s for s in sched.steps if s["kind"] not in ("dark", "flat")]
        th = np.array([s[f"theta_{which}_deg"] for s in steps])
        ph = np.radians([s[f"phi_{which}_deg"] for s in steps])
        ax.plot(ph, th, "-", color="0.8", lw=0.6, zorder=1)
        ax.scatter(
            ph, th, c=np.arange(len(steps)), cmap="viridis", s=14, zorder=2, label="measured"
        )
        exc = [e.pose.angles_deg() for e in sched.expanded.excluded]
        if exc:
            ax.scatter(
                np.radians([a[f"phi_{which}_deg"] for a in exc]),
                [a[f"theta_{which}_deg"] for a in exc],
                marker="x",
                c="red",
                s=14,
                label="excluded",
            )
        ax.set_rmax(90)
        ax.set_title(f"{title}: theta (deg) vs phi\ncolour = visiting order", fontsize=9)
    axes[1].legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------------------
def _report(result) -> None:
    n = len(result.skipped)
    if n:
        # a session that skipped poses must not read as complete at a glance
        click.echo(
            f"session {result.session} completed; {n} pose{'s' if n > 1 else ''} skipped "
            f"(the rig refused {'them' if n > 1 else 'it'}): see 'gonio capture inspect "
            f"{result.session}'"
        )
    else:
        click.echo(f"session {result.session} completed")
    if result.retaken:
        click.echo(f"{len(result.retaken)} frame(s) shot again: {', '.join(result.retaken)}")
    st = getattr(result, "adaptive_stop", None)
    if st:
        click.echo(
            f"adaptive: stopped after round {st['round']} ({st['stop']}) with "
            f"{st['poses_done']} sample poses; the rounds: 'gonio capture inspect "
            f"{result.session}'"
        )


def _light_option(spec: str, camera_backend: str | None) -> str | None:
    """The ``--light`` option checked (a :class:`ConfigError` naming it), or None for
    ``none``; a simulated camera is its own light switch."""
    from gonio.app.light_switch import parse_light_spec

    kind = parse_light_spec(spec)["kind"]
    if kind != "none" and camera_backend == "simulated":
        raise click.UsageError("--light is for a real rig; --camera simulated switches its own")
    return None if kind == "none" else spec


#: Only for ``run``: a resumed session keeps the camera backend it was started with.
_CAMERA = click.option(
    "--camera",
    "camera_backend",
    type=click.Choice(["simulated", "gphoto2"]),
    default="gphoto2",
    show_default=True,
    help="Camera backend: a tethered camera via gphoto2, or the renderer.",
)

_COMMON_RUN = [
    click.option(
        "--camera-port",
        default=None,
        help="gphoto2 port (e.g. usb:001,004); first camera found by default.",
    ),
    click.option(
        "--sim-speed",
        metavar="virtual|FACTOR",
        default=None,
        callback=sim_speed_option,
        help='With a virtual bus (rig bus.port = "virtual"): "virtual" advances servo '
        "time by the commanded motion (no waiting for it); a number makes servo time run "
        "that many times faster than the wall clock, to watch the arms (e.g. 20) "
        "[run: virtual; resume: the session's own]. The journal is the same either way.",
    ),
    click.option("--quiet", is_flag=True, help="No progress bar."),
    click.option(
        "--light",
        "light_spec",
        metavar="relay:PORT|operator|none",
        default="none",
        show_default=True,
        help="A real rig's light switch, needed for [darks]: a serial relay "
        "(relay:/dev/ttyUSB0, optionally ,on=HEX,off=HEX,baud=N,settle=S; default the "
        "LCUS-1 relay's commands A00101A2/A00100A1), or the operator, asked at the "
        "terminal. --camera simulated switches its own light.",
    ),
]


def _common(f):
    for opt in reversed(_COMMON_RUN):
        f = opt(f)
    return f


@capture.command("run")
@click.argument("plan_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--rig",
    "rig_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Rig configuration TOML (default: the built-in preset). Use "
    'bus.port = "virtual" for the simulated servo bus.',
)
@click.option(
    "--out",
    "out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="New session directory (must not exist, or be empty).",
)
@click.option(
    "--scene",
    "scene_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="With --camera simulated: scene TOML (overrides the plan's [simulation]).",
)
@click.option(
    "--world",
    "world",
    metavar="perfect|realistic|FILE",
    default=None,
    help="With --camera simulated: the as-built world the simulator renders (overrides "
    "the plan's [simulation] world and the scene's [world]) [default: perfect, the rig "
    "exactly as configured].",
)
@click.option(
    "--world-seed",
    type=click.IntRange(min=0),
    default=None,
    help="Seed the world's errors are drawn from (a realistic world) [default: 0].",
)
@click.option(
    "--adaptive",
    is_flag=True,
    help="Choose the poses as the session goes: add the default [adaptive] table to a "
    "plan that names no poses (a seed design, then batches by expected information until "
    "the targets or budgets of [adaptive] are met; needs [reference] poses).",
)
@_CAMERA
@_common
def run_cmd(
    plan_file: Path,
    rig_file: str | None,
    out: Path,
    scene_file: str | None,
    world: str | None,
    world_seed: int | None,
    adaptive: bool,
    camera_backend: str,
    camera_port: str | None,
    sim_speed: float | str | None,
    quiet: bool,
    light_spec: str,
) -> None:
    """Run a measurement session: move, shoot adaptive brackets, journal every shot.

    \b
    Poses are visited in the order that minimises servo travel time. Each RAW file is
    written atomically to SESSION/raw/ and recorded (with its sha256, the requested and
    achieved pose, the joint angles read back and the servo temperatures) in
    SESSION/journal.jsonl before the rig moves again. Whatever stops the run (a rig fault,
    the camera going away, Ctrl-C) the arms are parked and torque is turned off; then
    continue with 'gonio capture resume SESSION/'. One process at a time: a second run
    into the same --out is refused.

    \b
    Simulated end to end (virtual servo bus on a pty, rendered DNGs):
      gonio capture run examples/plan.toml --rig virtual_rig.toml --camera simulated --out S/
    where virtual_rig.toml has [bus] port = "virtual". Servo time is virtual by default
    (the moves cost no wall time); add --sim-speed 20 to watch the arms at 20x.
    """
    from gonio.app.devices import DEFAULT_TIME_SCALE, device_opener
    from gonio.app.progress import SessionProgress
    from gonio.app.simulation import simulated_run
    from gonio.capture.plan import load_plan
    from gonio.capture.session_dir import check_new_session_dir
    from gonio.capture.sessions import check_calibration_devices, plan_session, run_session

    check_new_session_dir(out)  # before anything slow or physical
    if (world is not None or world_seed is not None) and camera_backend != "simulated":
        raise click.UsageError("--world and --world-seed need --camera simulated")
    plan = load_plan(plan_file, adaptive=adaptive)
    light = _light_option(light_spec, camera_backend)
    if camera_backend != "simulated":  # before the rig or the camera is opened
        check_calibration_devices(plan, light is not None, True)
    cfg = _load_rig(rig_file)
    dry = plan_session(plan, cfg)
    speed = sim_speed or DEFAULT_TIME_SCALE
    simulation, attachments = None, None
    opener = device_opener(camera_port=camera_port, time_scale=speed, light_spec=light)
    if camera_backend == "simulated":
        sim = simulated_run(plan, plan_file, scene_file, speed, world, world_seed)
        simulation, attachments, opener = sim.simulation, sim.attachments, sim.opener
    with SessionProgress(quiet) as progress:
        result = run_session(
            out,
            plan,
            cfg,
            opener,
            camera_backend=camera_backend,
            dry_run=dry,
            simulation=simulation,
            attachments=attachments,
            subscribers=[progress],
            advisor=_advisor,
        )
    _report(result)


def _advisor(plan):
    """An adaptive session's advisor (gonio.app.adaptive_advisor), for run and resume."""
    from gonio.app.adaptive_advisor import FitAdvisor

    return FitAdvisor(plan)


@capture.command("resume")
@click.argument("session_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--plan",
    "plan_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Check that this is the plan the session was started with.",
)
@click.option(
    "--rig",
    "rig_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Rig configuration to use; must match the session's unless --force.",
)
@click.option(
    "--force",
    is_flag=True,
    help="Resume even though --plan/--rig differ from the session's (recorded).",
)
@click.option(
    "--retake",
    is_flag=True,
    help="Shoot again the journaled frames that are missing or changed (journaled as "
    "replacements) instead of refusing to resume.",
)
@click.option(
    "--camera",
    "camera_backend",
    type=click.Choice(["simulated", "gphoto2"]),
    default=None,
    hidden=True,  # accepted for old scripts; must name the session's own backend
)
@_common
def resume_cmd(
    session_dir: Path,
    plan_file: Path | None,
    rig_file: str | None,
    force: bool,
    retake: bool,
    camera_backend: str | None,
    camera_port: str | None,
    sim_speed: float | str | None,
    quiet: bool,
    light_spec: str,
) -> None:
    """Continue a session after a fault, a crash or Ctrl-C.

    \b
    Every frame the session relies on is checked first (byte count and XXH3-128); a
    missing or changed one is refused, naming the files, unless --retake. Poses already
    done are skipped; a pose cut short keeps its journaled frames and the bracket
    continues where it stopped; a RAW file written but not journaled is shot again.
    The session's own plan and rig configuration (from its manifest) are used; with --plan
    or --rig the files are compared with them and a difference is refused unless --force.
    The camera backend is the session's own. One process at
    a time: a second resume of the same session is refused.
    """
    from gonio.app.devices import device_opener
    from gonio.app.progress import SessionProgress
    from gonio.capture.plan import load_plan
    from gonio.capture.sessions import resume_session

    plan = load_plan(plan_file) if plan_file is not None else None
    cfg = _load_rig(rig_file) if rig_file is not None else None
    if camera_backend is not None:
        from gonio.capture.manifest import read_manifest

        own = read_manifest(session_dir).camera.backend
        if camera_backend != own:
            raise SessionError(
                f"{session_dir} was shot with the {own} camera; a session resumes with its "
                f"own backend (drop --camera {camera_backend})"
            )
    with SessionProgress(quiet) as progress:
        result = resume_session(
            session_dir,
            device_opener(
                camera_port=camera_port,
                time_scale=sim_speed,
                light_spec=_light_option(light_spec, None),
            ),
            plan=plan,
            rig_config=cfg,
            force=force,
            retake=retake,
            subscribers=[progress],
            plan_source=str(plan_file),
            rig_source=str(rig_file),
            advisor=_advisor,
        )
    _report(result)


@capture.command("inspect")
@click.argument("session_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--verify/--no-verify",
    default=True,
    show_default=True,
    help="Check every RAW file against its journal record (byte count and sha256).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def inspect_cmd(session_dir: Path, verify: bool, as_json: bool) -> None:
    """Show what a session has done, what failed and what is left.

    Exits with status 1 when a RAW file is missing or does not match its journal hash;
    also lists frames shot again and temporary files an interrupted write left.
    """
    from gonio.capture.sessions import inspect_session

    info = inspect_session(session_dir, verify=verify).to_json()
    if as_json:
        click.echo(json.dumps(info, indent=1))
    else:
        from rich.console import Console
        from rich.markup import escape as esc

        con = Console()
        # escaped: paths and messages may hold brackets, which rich reads as markup
        con.print(
            f"[bold]{esc(str(session_dir))}[/]  plan {esc(repr(info['plan']))}, "
            f"camera {esc(str(info['camera']))}"
        )
        con.print(
            f"status: [bold]{info['status']}[/]; poses done {info['poses_done']}/"
            f"{info['poses_total']}"
            # poses_done counts skipped poses (finished, never retried): say so
            + (f" ({len(info['skipped'])} of them skipped)" if info["skipped"] else "")
            + f", shots {info['shots']} ({info['files_verified']} files verified)"
        )
        if info["partial_poses"]:
            con.print(f"cut short (will be continued): poses {info['partial_poses']}")
        for r in info["skipped"]:
            con.print(f"[yellow]skipped[/] pose {r['pose']}: {esc(str(r['reason']))}")
        for f in info["faults"]:
            con.print(f"[red]fault[/] ({esc(str(f.get('source')))}): {esc(str(f.get('error')))}")
        for p in info["bad_files"]:
            con.print(f"[red]bad file[/]: {esc(str(p))}")
        if info["orphans"]:
            con.print(
                f"orphan files (not journaled, redone on resume): {info['orphans']}", markup=False
            )
        if info["retaken"]:
            con.print(f"shot again (--retake): {info['retaken']}", markup=False)
        if info["stale_temporaries"]:
            con.print(
                "temporary files of an interrupted write (removed by the next run or "
                f"resume): {info['stale_temporaries']}",
                markup=False,
            )
        left = info["poses_total"] - info["poses_done"]
        if left:
            con.print(
                f"left: {left} poses; continue with 'gonio capture resume {session_dir}'",
                markup=False,
            )
        if info.get("rounds"):
            con.print(_rounds_table(info["rounds"]))
        if info.get("budget") and info["budget"]["terms"]:
            from gonio.capture.budget import budget_table

            con.print(budget_table(info["budget"]["terms"]))
    if info["bad_files"]:
        raise SessionError(
            f"{session_dir}: {len(info['bad_files'])} RAW file(s) missing or "
            "not matching their journal hash"
        )

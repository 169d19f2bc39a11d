"""``gonio capture plan | run | resume | inspect``: measurement sessions from the shell."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

import click

from gonio.errors import ConfigError, SessionError

__all__ = ["inspect_cmd", "plan_cmd", "resume_cmd", "run_cmd"]


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


def _scene_for(plan, plan_path: Path | None, scene_path: str | None) -> dict[str, Any] | None:
    """The simulation scene as a document (stored in the manifest, so resume needs no file)."""
    path = scene_path or plan.simulation.scene
    if path is None:
        return None
    p = Path(path)
    if not p.is_absolute() and scene_path is None and plan_path is not None:
        p = plan_path.parent / p
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the simulation scene: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: scene is not valid TOML: {exc}") from None
    from gonio.simulator.scene import parse_scene

    # Validated here, so an error names this file and comes before the session starts.
    parse_scene(doc, str(p), p.resolve().parent)
    return doc | {"_base_dir": str(p.resolve().parent)}


# --------------------------------------------------------------------------------------
@click.command("plan")
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
    or colliding on this rig), the total servo travel time of the optimised visiting
    order against raster order, and the estimated duration.

    \b
    Example:
      gonio capture plan examples/plan.toml --rig rig.toml --plot poses.png
    """
    from rich.console import Console
    from rich.table import Table

    from gonio.capture.plan import load_plan
    from gonio.capture.session import build_schedule
    from gonio.rig.kinematics import Kinematics

    if plot is not None:
        _check_image_path(plot, force, "--plot")
    plan = load_plan(plan_file)
    cfg = _load_rig(rig_file)
    kin = Kinematics(cfg)
    sched = build_schedule(plan, kin, cfg.park_rad)
    ex = sched.expanded
    n_sample = sum(1 for s in sched.steps if s["kind"] == "sample")
    n_ref = sum(1 for s in sched.steps if s["kind"] == "reference")
    summary = {
        "plan": plan.name,
        "grid_poses": ex.n_grid,
        "reduced_by_symmetry": ex.n_reduced,
        "excluded": len(ex.excluded),
        "sample_poses": n_sample,
        "reference_poses": n_ref,
        "dark_steps": sum(1 for s in sched.steps if s["kind"] == "dark"),
        "travel_time_s": round(sched.travel_time_s, 3),
        "raster_travel_time_s": round(sched.raster_travel_time_s, 3),
        "estimated_duration_s": round(sched.estimated_duration_s, 1),
        "excluded_poses": [{**e.pose.angles_deg(), "reason": e.reason} for e in ex.excluded],
    }
    if show_poses or as_json:
        summary["poses"] = [
            {k: s[k] for k in s if k.endswith("_deg") or k == "kind"} for s in sched.steps
        ]
    if plot is not None:
        _plot_poses(plot, sched)
    if as_json:
        click.echo(json.dumps(summary, indent=1))
        return
    con = Console()
    con.print(f"[bold]{plan.name}[/]  ({plan_file})  rig: {cfg.name}")
    con.print(
        f"grid {ex.n_grid} poses, {ex.n_reduced} removed by symmetry, "
        f"{len(ex.excluded)} excluded -> [bold]{n_sample}[/] sample poses"
        + (f" + {n_ref} reference" if n_ref else "")
    )
    if ex.excluded:
        t = Table("theta_i", "phi_i", "theta_o", "phi_o", "reason", title="excluded poses")
        for e in ex.excluded:
            a = e.pose.angles_deg()
            t.add_row(
                *(f"{a[k]:.1f}" for k in ("theta_i_deg", "phi_i_deg", "theta_o_deg", "phi_o_deg")),
                e.reason,
            )
        con.print(t)
    if show_poses:
        t = Table("#", "kind", "theta_i", "phi_i", "theta_o", "phi_o", title="visiting order")
        for k, s in enumerate(sched.steps):
            if s["kind"] == "dark":
                t.add_row(str(k), "dark", "", "", "", "")
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


def _sim_speed(ctx, param, value: float | None) -> float | None:
    # Zero, negative or nan time would stall or crash the virtual servos mid-session.
    if value is not None and not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"expected a positive finite speed-up factor, got {value}")
    return value


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
        steps = [s for s in sched.steps if s["kind"] != "dark"]
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
class _Progress:
    """Rich progress bar over the session's poses, fed by journal events."""

    def __init__(self, total: int, done: int, quiet: bool) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.quiet = quiet
        self.progress = Progress(
            TextColumn("[bold]poses"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("shots {task.fields[shots]}"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            disable=quiet,
        )
        self.task = self.progress.add_task("poses", total=total, completed=done, shots=0)
        self.shots = 0
        self.skipped = 0

    def __call__(self, rec: dict[str, Any]) -> None:
        t = rec.get("type")
        if t == "shot":
            self.shots += 1
            self.progress.update(self.task, shots=self.shots)
        elif t in ("pose_done", "pose_skipped"):
            # a skipped pose is finished too: without this the bar stopped short of 100 %
            self.progress.advance(self.task)
            if t == "pose_skipped":
                self.skipped += 1
                self.progress.console.print(
                    f"[yellow]pose {rec.get('pose')} skipped: {rec.get('reason')}"
                )
        elif t == "fault":
            self.progress.console.print(f"[red]fault ({rec.get('source')}): {rec.get('error')}")

    def __enter__(self):
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        self.progress.__exit__(*exc)


def _run_with_progress(session_dir: Path, devices, resumed: bool, quiet: bool) -> None:
    from gonio.capture.journal import read_journal
    from gonio.capture.session import JOURNAL, load_manifest, run_steps, session_state

    manifest = load_manifest(session_dir)
    jp = session_dir / JOURNAL
    done = len(session_state(read_journal(jp)).done) if jp.exists() else 0
    with _Progress(len(manifest["schedule"]), done, quiet) as prog:
        run_steps(
            session_dir,
            devices.rig,
            devices.camera,
            devices.kinematics,
            on_event=prog,
            resumed=resumed,
            read_noise_dn=devices.read_noise_dn(manifest),
        )
    if prog.skipped:
        # a session that skipped poses must not read as complete at a glance
        n = prog.skipped
        click.echo(
            f"session {session_dir} completed; {n} pose{'s' if n > 1 else ''} skipped "
            f"(the rig refused {'them' if n > 1 else 'it'}): see 'gonio capture inspect "
            f"{session_dir}'"
        )
    else:
        click.echo(f"session {session_dir} completed")


_COMMON_RUN = [
    click.option(
        "--camera",
        "camera_backend",
        type=click.Choice(["simulated", "gphoto2"]),
        default="gphoto2",
        show_default=True,
        help="Camera backend: a tethered camera via gphoto2, or the renderer.",
    ),
    click.option(
        "--camera-port",
        default=None,
        help="gphoto2 port (e.g. usb:001,004); first camera found by default.",
    ),
    click.option(
        "--sim-speed",
        type=float,
        default=None,
        callback=_sim_speed,
        help='With a virtual bus (rig bus.port = "virtual"): servo time runs this many '
        "times faster than the wall clock [run: 20; resume: the session's own].",
    ),
    click.option("--quiet", is_flag=True, help="No progress bar."),
]


def _common(f):
    for opt in reversed(_COMMON_RUN):
        f = opt(f)
    return f


@click.command("run")
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
@_common
def run_cmd(
    plan_file: Path,
    rig_file: str | None,
    out: Path,
    scene_file: str | None,
    camera_backend: str,
    camera_port: str | None,
    sim_speed: float | None,
    quiet: bool,
) -> None:
    """Run a measurement session: move, shoot adaptive brackets, journal every shot.

    \b
    Poses are visited in the order that minimises servo travel time. Each RAW file is
    written atomically to SESSION/raw/ and recorded (with its sha256, the requested and
    achieved pose, the joint angles read back and the servo temperatures) in
    SESSION/journal.jsonl before the rig moves again. Whatever stops the run (a rig fault,
    the camera going away, Ctrl-C) the arms are parked and torque is turned off; then
    continue with 'gonio capture resume SESSION/'.

    \b
    Simulated end to end (virtual servo bus on a pty, rendered DNGs):
      gonio capture run examples/plan.toml --rig virtual_rig.toml --camera simulated --out S/
    where virtual_rig.toml has [bus] port = "virtual".
    """
    from gonio.capture.plan import load_plan
    from gonio.capture.session import (
        build_schedule,
        check_new_session_dir,
        create_session,
        open_devices,
    )
    from gonio.rig.kinematics import Kinematics

    check_new_session_dir(out)  # before anything slow or physical
    plan = load_plan(plan_file)
    cfg = _load_rig(rig_file)
    kin = Kinematics(cfg)
    sched = build_schedule(plan, kin, cfg.park_rad)
    simulation = None
    if camera_backend == "simulated":
        simulation = {
            "scene": _scene_for(plan, plan_file, scene_file),
            "width": plan.simulation.width,
            "height": plan.simulation.height,
            "time_scale": sim_speed or 20.0,
        }
        if simulation["scene"] is None:  # keep the manifest self-contained
            from gonio.capture.sim_camera import minimal_scene

            simulation["scene"] = minimal_scene()
    with open_devices(
        cfg,
        camera_backend,
        simulation=simulation,
        camera_port=camera_port,
        seed=plan.seed,
        reference_reflectance=plan.reference.reflectance,
    ) as dev:
        from gonio.capture.camera import LightSwitch

        if plan.darks.count and not isinstance(dev.camera, LightSwitch):
            raise SessionError(
                f"{plan_file}: darks.count = {plan.darks.count} but the {camera_backend} camera "
                "cannot switch the rig's light off; set darks.count = 0 and shoot darks with "
                "the lens capped (nothing was written)"
            )
        create_session(out, plan, cfg, sched, dev.camera.describe(), simulation=simulation)
        _run_with_progress(out, dev, resumed=False, quiet=quiet)


@click.command("resume")
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
@_common
def resume_cmd(
    session_dir: Path,
    plan_file: Path | None,
    rig_file: str | None,
    force: bool,
    camera_backend: str,
    camera_port: str | None,
    sim_speed: float | None,
    quiet: bool,
) -> None:
    """Continue a session after a fault, a crash or Ctrl-C.

    \b
    Poses already done are skipped; a pose cut short keeps its journaled frames and the
    bracket continues where it stopped; a RAW file written but not journaled is shot again.
    The session's own plan and rig configuration (from its manifest) are used; with --plan
    or --rig the files are compared with them and a difference is refused unless --force.
    The camera backend is the session's (the --camera option is ignored).
    """
    from gonio.capture.plan import load_plan, plan_digest
    from gonio.capture.session import JOURNAL, load_manifest, open_devices
    from gonio.rig.config import rig_config_from_dict

    manifest = load_manifest(session_dir)
    diffs = []
    if plan_file is not None:
        plan = load_plan(plan_file)
        if plan_digest(plan) != manifest["plan_digest"]:
            diffs.append(
                f"plan {plan_file} differs from the session's plan "
                f"({_diff_keys(plan.model_dump(mode='json'), manifest['plan'])})"
            )
    cfg = rig_config_from_dict(manifest["rig"], f"{session_dir}/manifest.json: rig")
    if rig_file is not None:
        new_cfg = _load_rig(rig_file)
        if plan_digest(new_cfg) != manifest["rig_digest"]:
            diffs.append(
                f"rig {rig_file} differs from the session's rig "
                f"({_diff_keys(new_cfg.model_dump(mode='json'), manifest['rig'])})"
            )
            if force:
                cfg = new_cfg
    if diffs and not force:
        raise SessionError("; ".join(diffs) + ". Refusing to resume; use --force to override")
    if diffs:
        from gonio.capture.journal import Journal

        j, _ = Journal.open(session_dir / JOURNAL)
        with j:
            j.append({"type": "note", "forced": True, "differences": diffs})
    from gonio.rig.kinematics import Kinematics

    Kinematics(cfg)  # validate before opening anything
    sim = manifest.get("simulation")
    if sim is not None:
        sim = {
            **sim,
            "time_scale": sim_speed or sim.get("time_scale") or 20.0,
        }
    backend = manifest["camera"]["backend"]
    with open_devices(
        cfg,
        backend,
        simulation=sim,
        camera_port=camera_port,
        seed=int(manifest.get("seed", 0)),
        reference_reflectance=(manifest.get("reference") or {}).get("reflectance"),
    ) as dev:
        _run_with_progress(session_dir, dev, resumed=True, quiet=quiet)


def _diff_keys(a: dict, b: dict, prefix: str = "") -> str:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            sub = _diff_keys(va, vb, f"{prefix}{k}.")
            if sub:
                out.append(sub)
        elif va != vb:
            out.append(f"{prefix}{k}")
    return ", ".join(out)


@click.command("inspect")
@click.argument("session_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--verify/--no-verify",
    default=True,
    show_default=True,
    help="Check every RAW file against its journaled sha256.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def inspect_cmd(session_dir: Path, verify: bool, as_json: bool) -> None:
    """Show what a session has done, what failed and what is left.

    Exits with status 1 when a RAW file is missing or does not match its journal hash.
    """
    from gonio.capture.session import inspect_session

    info = inspect_session(session_dir, verify=verify)
    if as_json:
        click.echo(json.dumps(info, indent=1))
    else:
        from rich.console import Console

        con = Console()
        con.print(f"[bold]{session_dir}[/]  plan {info['plan']!r}, camera {info['camera']}")
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
            con.print(f"[yellow]skipped[/] pose {r['pose']}: {r['reason']}")
        for f in info["faults"]:
            con.print(f"[red]fault[/] ({f.get('source')}): {f.get('error')}")
        for p in info["bad_files"]:
            con.print(f"[red]bad file[/]: {p}")
        if info["orphans"]:
            con.print(f"orphan files (not journaled, redone on resume): {info['orphans']}")
        left = info["poses_total"] - info["poses_done"]
        if left:
            con.print(f"left: {left} poses; continue with 'gonio capture resume {session_dir}'")
    if info["bad_files"]:
        raise SessionError(
            f"{session_dir}: {len(info['bad_files'])} RAW file(s) missing or "
            "not matching their journal hash"
        )

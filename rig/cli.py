"""``gonio rig``: find, inspect, move and power down the servo rig."""

from __future__ import annotations

import json
import math

import click
import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from gonio.errors import RigError
from gonio.rig import control_table as ct
from gonio.rig.config import default_rig_config, load_rig_config
from gonio.rig.device import Rig
from gonio.rig.transport import Transport

_console = Console()


def _config(path, port, baud):
    cfg = load_rig_config(path) if path else default_rig_config()
    return cfg, port or cfg.bus.port, baud or cfg.bus.baud_rate


_cfg_opts = [
    click.option(
        "--config",
        "config_path",
        type=click.Path(dir_okay=False),
        default=None,
        help="Rig configuration TOML (default: the built-in four-servo preset).",
    ),
    click.option("--port", default=None, help="Serial port; overrides bus.port of the config."),
    click.option("--baud", default=None, type=int, help="Baud rate; overrides bus.baud_rate."),
]


def cfg_options(f):
    for opt in reversed(_cfg_opts):
        f = opt(f)
    return f


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def rig() -> None:
    """Drive the gonioreflectometer's Dynamixel servos.

    \b
    Start with `gonio rig scan --port /dev/ttyUSB0` to see which servos answer, write a
    rig.toml (see examples/rig.toml), then:
      gonio rig status --config rig.toml
      gonio rig move --config rig.toml --theta-i 30 --phi-i 0 --theta-o 30 --phi-o 180
      gonio rig home --config rig.toml
      gonio rig off --config rig.toml
    Without --config the built-in four-servo preset is used.  Try it on the virtual bus:
    `gonio sim bus` prints a port path to use as --port.
    """


@rig.command()
@click.option(
    "--port", required=True, help="Serial port, e.g. /dev/ttyUSB0 (or a `gonio sim bus` pty)."
)
@click.option(
    "--baud", default=1_000_000, show_default=True, type=int, help="Baud rate to scan at."
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def scan(port: str, baud: int, as_json: bool) -> None:
    """List the servos answering on PORT: ID, model, firmware (broadcast PING, ~1 s)."""
    with Transport(port, baud) as bus:
        found = bus.broadcast_ping()
    rows = [
        {
            "id": i,
            "model_number": m,
            "model": getattr(ct.MODELS_BY_NUMBER.get(m), "name", "unknown"),
            "firmware": fw,
        }
        for i, (m, fw) in found.items()
    ]
    if as_json:
        click.echo(json.dumps({"port": port, "baud_rate": baud, "servos": rows}))
        return
    if not rows:
        raise RigError(f"no servo answered on {port} at {baud} baud; try another --baud")
    t = Table(title=escape(f"servos on {port} at {baud} baud"))
    for c in ("ID", "model", "model number", "firmware"):
        t.add_column(c)
    for r in rows:
        t.add_row(str(r["id"]), r["model"], str(r["model_number"]), str(r["firmware"]))
    _console.print(t)


def _print_status(r: Rig, as_json: bool) -> None:
    st = r.status().as_dict()
    wi, wo = r.directions()
    st["wi"], st["wo"] = wi.tolist(), wo.tolist()
    if as_json:
        click.echo(json.dumps(st))
        return
    t = Table(title="rig status")
    for c in (
        "ID",
        "joint",
        "position deg",
        "goal deg",
        "temp degC",
        "voltage V",
        "current A",
        "torque",
        "errors",
    ):
        t.add_column(c)
    for s in st["servos"]:
        t.add_row(
            str(s["id"]),
            s["joint"],
            f"{s['position_deg']:.2f}",
            f"{s['goal_deg']:.2f}",
            f"{s['temperature_c']:.0f}",
            f"{s['voltage_v']:.1f}",
            f"{s['current_a']:.3f}",
            "on" if s["torque"] else "off",
            ", ".join(s["hardware_error_names"]) or "-",
        )
    _console.print(t)
    ti, pi = (math.degrees(a) for a in _sph(wi))
    to, po = (math.degrees(a) for a in _sph(wo))
    _console.print(f"light theta {ti:.3f} phi {pi:.3f} deg; camera theta {to:.3f} phi {po:.3f} deg")


def _sph(w):
    return math.acos(max(-1.0, min(1.0, float(w[2])))), math.atan2(float(w[1]), float(w[0]))


@rig.command()
@cfg_options
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def status(config_path, port, baud, as_json) -> None:
    """Positions, temperatures, voltages, currents, torque and errors of every servo."""
    cfg, port, baud = _config(config_path, port, baud)
    with Rig(cfg, port=port, baud_rate=baud) as r:
        _print_status(r, as_json)


def _polar(ctx, param, value: float | None) -> float | None:
    # Checked here, before the port is opened: a bad angle is the user's typo, not a fault.
    if value is not None and not (math.isfinite(value) and 0.0 <= value <= 90.0):
        raise click.BadParameter(
            f"expected a polar angle in [0, 90] degrees from the sample normal, got {value}"
        )
    return value


def _azimuth(ctx, param, value: float | None) -> float | None:
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"expected a finite azimuth in degrees, got {value}")
    return value


def _direction(theta_deg: float, phi_deg: float) -> np.ndarray:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


@rig.command()
@cfg_options
@click.option(
    "--theta-i",
    type=float,
    required=True,
    callback=_polar,
    help="Light polar angle from the normal (deg).",
)
@click.option(
    "--phi-i",
    type=float,
    callback=_azimuth,
    default=0.0,
    show_default=True,
    help="Light azimuth from sample +x (deg).",
)
@click.option(
    "--theta-o", type=float, required=True, callback=_polar, help="Camera polar angle (deg)."
)
@click.option(
    "--phi-o",
    type=float,
    default=180.0,
    show_default=True,
    callback=_azimuth,
    help="Camera azimuth (deg).",
)
@click.option(
    "--hold/--no-hold",
    default=False,
    show_default=True,
    help="Keep torque on after the move (otherwise it is cut on exit).",
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def move(config_path, port, baud, theta_i, phi_i, theta_o, phi_o, hold, as_json) -> None:
    """Move light and camera to directions given in the sample frame (degrees).

    The request is checked (reachability, joint limits, camera shadow, arm collision)
    before anything moves; the achieved directions are read back and printed.
    """
    cfg, port, baud = _config(config_path, port, baud)
    wi, wo = _direction(theta_i, phi_i), _direction(theta_o, phi_o)
    with Rig(cfg, port=port, baud_rate=baud) as r:
        res = r.move_to(wi, wo)
        r.hold_on_exit = hold
    out = {
        "joints_deg": {j: math.degrees(v) for j, v in res.joints.items()},
        "wi_achieved": res.wi_achieved.tolist(),
        "wo_achieved": res.wo_achieved.tolist(),
        "error_i_deg": math.degrees(res.error_i),
        "error_o_deg": math.degrees(res.error_o),
        "duration_s": res.duration,
    }
    if as_json:
        click.echo(json.dumps(out))
    else:
        click.echo(
            "moved: "
            + ", ".join(f"{j} {v:.3f} deg" for j, v in out["joints_deg"].items())
            + f"\nachieved within {out['error_i_deg']:.4f} deg (light), "
            + f"{out['error_o_deg']:.4f} deg "
            f"(camera) in {res.duration:.2f} s"
        )


@rig.command()
@cfg_options
@click.option(
    "--hold/--no-hold", default=False, show_default=True, help="Keep torque on afterwards."
)
def home(config_path, port, baud, hold) -> None:
    """Move every joint to the configured home pose (motion.home_deg)."""
    cfg, port, baud = _config(config_path, port, baud)
    with Rig(cfg, port=port, baud_rate=baud) as r:
        q = r.home()
        r.hold_on_exit = hold
    click.echo("home: " + ", ".join(f"{j} {math.degrees(v):.3f} deg" for j, v in q.items()))


@rig.command()
@cfg_options
def off(config_path, port, baud) -> None:
    """Cut torque on every configured servo (works even when a servo reports a fault)."""
    cfg, port, baud = _config(config_path, port, baud)
    with Transport(port, baud, retries=cfg.bus.retries) as bus:
        reg = ct.MODELS[cfg.servos[0].model]["torque_enable"]
        bus.broadcast_write(reg, 0)
        failed = []
        for s in cfg.servos:
            try:
                bus.write(s.id, reg, 0)
            except RigError as exc:
                failed.append(f"servo {s.id}: {exc}")
    if failed:
        raise RigError("torque off not confirmed: " + "; ".join(failed))
    click.echo(f"torque off on servos {[s.id for s in cfg.servos]}")

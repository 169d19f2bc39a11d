"""``gonio sim bus``: serve a virtual Dynamixel bus on a pseudo-terminal.

Part of the composition root because it wires a simulated device (the virtual bus) from
the rig's configuration (its park pose); the simulator itself knows only the protocol.
"""

from __future__ import annotations

import json
import signal
import sys
import threading

import click

from gonio.cli import FiniteFloatRange
from gonio.rig.control_table import BAUD_CODES, MODELS
from gonio.simulator.virtual_bus import VirtualBus


def _int_list(ctx, param, value: str | None) -> list[int] | None:
    if value is None:
        return None
    try:
        return [int(v) for v in value.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated integers, got {value!r}") from None


@click.command("bus")
@click.option(
    "--servos",
    default="1,2,3,4",
    show_default=True,
    callback=_int_list,
    help="Comma-separated servo IDs on the bus.",
)
@click.option(
    "--model",
    default="XM430-W350",
    show_default=True,
    type=click.Choice(sorted(MODELS)),
    help="Model of every servo.",
)
@click.option(
    "--firmware",
    default=45,
    show_default=True,
    type=click.IntRange(0, 255),
    help="Firmware Version the servos report (FAST_SYNC_READ needs >= 45 on X430).",
)
@click.option(
    "--baud",
    default=1_000_000,
    show_default=True,
    type=click.Choice([str(b) for b in BAUD_CODES.values()]),
    callback=lambda ctx, param, value: int(value),
    help="The servos' baud rate (one an X-series servo supports); clients set to another "
    "rate are not heard.",
)
@click.option(
    "--positions",
    default=None,
    callback=_int_list,
    help="Initial Present Position of each servo (pulses, same order as --servos); "
    "default: the rig's park pose (see --rig), 2048 (centre) for servos not in it.",
)
@click.option(
    "--rig",
    "rig_file",
    default=None,
    type=click.Path(dir_okay=False, exists=True),
    help="Rig configuration whose park pose the servos start in (default: the built-in "
    "four-servo preset), so a fresh virtual rig is in a pose a real one can be in.",
)
@click.option(
    "--fault-rate",
    default=0.0,
    show_default=True,
    type=FiniteFloatRange(0, 1),
    help="Probability that a reply is corrupted or dropped (half each).",
)
@click.option(
    "--seed",
    default=None,
    type=click.IntRange(min=0),
    help="Seed of the fault generator (reproducible faults).",
)
@click.option(
    "--time-scale",
    default=1.0,
    show_default=True,
    type=FiniteFloatRange(min=1e-3, max=1e6),
    help="Servo time runs this many times faster than the wall clock.",
)
def bus_cmd(
    servos, model, firmware, baud, positions, rig_file, fault_rate, seed, time_scale
) -> None:
    """Serve virtual Dynamixel X-series servos (Protocol 2.0) on a pseudo-terminal.

    The first line printed is the port path: point any Dynamixel tool at it, e.g.
    `gonio rig scan --port /dev/pts/7`, or dynamixel-sdk's PortHandler.  Serves until
    Ctrl-C or SIGTERM, then prints bus statistics (JSON) on stderr.

    \b
    Example:
      gonio sim bus --servos 1,2,3,4 --fault-rate 0.01 --seed 3
    """
    if not servos:
        raise click.BadParameter("expected at least one servo ID", param_hint="--servos")
    if positions is not None and len(positions) != len(servos):
        raise click.BadParameter(
            f"{len(positions)} positions for {len(servos)} servos", param_hint="--positions"
        )
    if len(set(servos)) != len(servos):
        raise click.BadParameter(f"duplicate IDs in {servos}", param_hint="--servos")
    bad = [i for i in servos if not 0 <= i <= 252]
    if bad:
        raise click.BadParameter(f"IDs must be 0..252, got {bad}", param_hint="--servos")
    if positions is None:
        positions = _park_positions(servos, rig_file)
    stop = threading.Event()

    def handler(signum, frame):
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with VirtualBus(
            servos,
            model=model,
            firmware=firmware,
            baud_rate=baud,
            fault_rate=fault_rate,
            seed=seed,
            time_scale=time_scale,
        ) as bus:
            for i, p in zip(servos, positions, strict=True):
                bus.servos[i].set_position(p)
            click.echo(bus.port)
            sys.stdout.flush()
            click.echo(
                f"serving servos {servos} ({model}) at {baud} baud; Ctrl-C to stop", err=True
            )
            while not stop.wait(3600):
                pass
            st = bus.stats
            click.echo(
                json.dumps({k: v for k, v in vars(st).items() if k != "instructions"}), err=True
            )
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _park_positions(servos: list[int], rig_file: str | None) -> list[int]:
    """Initial pulses: the rig's park pose for its servos, the centre for the others.

    At the centre (2048) the preset's two arms would both face the same azimuth, a state a
    real rig cannot be in, and every move out of it is refused as an arm collision.
    """
    from gonio.rig.config import default_rig_config, load_rig_config

    cfg = load_rig_config(rig_file) if rig_file else default_rig_config()
    park = cfg.park_pulses
    return [park.get(i, 2048) for i in servos]

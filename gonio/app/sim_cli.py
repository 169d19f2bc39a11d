"""``gonio sim``: the simulated rig (renderer, virtual servo bus)."""

from __future__ import annotations

import click

from gonio.cli import LazyGroup


@click.group(
    cls=LazyGroup,
    lazy_commands={
        "render": "gonio.app.sim_render:render_cmd",
        "bus": "gonio.app.sim_bus:bus_cmd",
    },
)
def sim() -> None:
    """Simulated hardware: render camera RAW files, serve a virtual Dynamixel bus."""

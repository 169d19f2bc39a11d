"""``gonio brdf``: list, plot and check BRDF models and measured files."""

from __future__ import annotations

import click

from gonio.cli import LazyGroup


@click.group(
    cls=LazyGroup,
    lazy_commands={
        "list": "gonio.brdf.cli_models:list_cmd",
        "plot": "gonio.brdf.cli_models:plot_cmd",
        "albedo": "gonio.brdf.cli_models:albedo_cmd",
        "info": "gonio.brdf.cli_measured:info_cmd",
        "convert": "gonio.brdf.cli_measured:convert_cmd",
    },
)
def brdf() -> None:
    """Analytic BRDF models and measured BRDF files (RGL .bsdf, MERL .binary)."""

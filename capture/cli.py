"""``gonio capture``: plan, run, resume, inspect and reduce measurement sessions."""

from __future__ import annotations

import click

from gonio.cli import LazyGroup


@click.group(
    cls=LazyGroup,
    lazy_commands={
        "plan": "gonio.capture.session_cli:plan_cmd",
        "run": "gonio.capture.session_cli:run_cmd",
        "resume": "gonio.capture.session_cli:resume_cmd",
        "inspect": "gonio.capture.session_cli:inspect_cmd",
        "reduce": "gonio.capture.reduce_cli:reduce_cmd",
        "calibrate-noise": "gonio.capture.reduce_cli:calibrate_noise_cmd",
    },
)
def capture() -> None:
    """Measurement sessions: dry-run a plan, capture, resume, reduce to BRDF samples."""

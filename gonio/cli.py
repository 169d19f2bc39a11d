"""The ``gonio`` command line.

Subcommand groups live beside the code they drive (``gonio.rig.cli`` and so on) and are
imported only when used, which keeps ``gonio --help`` fast and lets the core stay free of
imports from the subsystems.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import os
import sys
from pathlib import Path
from typing import Any

import click

from gonio.errors import GonioError

# command name -> "module:attribute" of a click command or group.  A group appears in
# --help only once its module exists, so there are never placeholder commands.
_SUBCOMMANDS: dict[str, str] = {
    "brdf": "gonio.brdf.cli:brdf",
    "sim": "gonio.app.sim_cli:sim",
    "rig": "gonio.rig.cli:rig",
    "capture": "gonio.app.capture_cli:capture",
    "calibrate": "gonio.app.calibrate_cli:calibrate",
    "fit": "gonio.fitting.cli:fit",
    "demo": "gonio.app.demo:demo",
}


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use.

    Parameters
    ----------
    lazy_commands
        Command name -> ``"module:attribute"``.  Entries whose module does not exist are
        hidden, so a group shows exactly the commands that are implemented.
    """

    def __init__(self, *args, lazy_commands: dict[str, str] | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.lazy_commands = dict(lazy_commands or {})

    def list_commands(self, ctx: click.Context) -> list[str]:
        found = [n for n, t in self.lazy_commands.items() if _module_exists(t.split(":")[0])]
        return sorted(set(found) | set(super().list_commands(ctx)))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = self.lazy_commands.get(cmd_name)
        if target is None or not _module_exists(target.split(":")[0]):
            return super().get_command(ctx, cmd_name)
        module_name, attr = target.split(":")
        return getattr(importlib.import_module(module_name), attr)


def distinct_outputs(*outputs: tuple[str, Path | None]) -> None:
    """Refuse two output options that name one file (``--out x.png --plot x.png``: the
    second write silently replaced the first, exit 0).

    Raises
    ------
    click.UsageError
        Naming both options and the path.
    """
    seen: dict[Path, str] = {}
    for hint, path in outputs:
        if path is None:
            continue
        key = Path(os.path.abspath(path))
        if key in seen:
            raise click.UsageError(f"{seen[key]} and {hint} name the same file {path}")
        seen[key] = hint


class FiniteFloatRange(click.FloatRange):
    """``click.FloatRange`` that also refuses NaN and infinities.

    click checks a range with comparisons, which are all false for NaN, so ``--x nan``
    passes any ``FloatRange`` (and ``inf`` one without a maximum) and surfaces later as
    a traceback, a misleading error or a NaN result.  Use this for every float option
    whose value must be a real number; it shows in ``--help`` as ``FloatRange`` does.
    """

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        # finiteness first: with a maximum, click's range message would hide it
        rv = click.FLOAT.convert(value, param, ctx)
        if math.isfinite(rv):
            rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            # the user's own text (e.g. "-nan"), not its float
            got = value if isinstance(value, str) else rv
            self.fail(
                f"expected a finite number in {self._describe_range()}, got {got}", param, ctx
            )
        return rv


@click.group(
    cls=LazyGroup,
    lazy_commands=_SUBCOMMANDS,
    context_settings={"help_option_names": ["-h", "--help"]},
)
@click.option(
    "--version",
    is_flag=True,
    expose_value=False,
    is_eager=True,
    callback=lambda ctx, _param, value: _print_version(ctx) if value else None,
    help="Show the version and exit.",
)
def cli() -> None:
    """gonio: measure BRDFs with a Dynamixel gonioreflectometer, and fit them.

    \b
    Typical lab session:
      gonio rig scan --port /dev/ttyUSB0     find the servos
      gonio capture plan plan.toml --rig rig.toml   dry-run a plan
      gonio capture run plan.toml --rig rig.toml --camera gphoto2 --out S/
      gonio capture reduce S/                RAW brackets -> S/samples.h5
      gonio fit S/samples.h5 --model auto --out fit/

    Run any command with --help to learn its options.
    """


def _print_version(ctx: click.Context) -> None:
    """``--version``, as click's version_option prints it, with the version looked up only
    here (importlib.metadata is not on every command's start-up path)."""
    import gonio

    click.echo(f"gonio, version {gonio.__version__}")
    ctx.exit()


def run(*argv: str) -> int | str | None:
    """Run ``gonio ARGV...`` in this process and return its exit code rather than exit
    (0 for success; tests, notebooks and benchmarks drive the CLI this way)."""
    try:
        main(list(argv))
    except SystemExit as exc:
        return exc.code
    return 0


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the CLI and turn :class:`GonioError` into exit code 1."""
    from gonio import interrupts

    try:
        with interrupts.noting():
            cli.main(args=argv, prog_name="gonio", standalone_mode=False)
            # A Ctrl-C whose KeyboardInterrupt a garbage-collector callback swallowed:
            # the command ran on, but the user asked to stop, and the exit code says so.
            if interrupts.noted():
                raise KeyboardInterrupt
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except GonioError as exc:
        click.secho(f"error: {exc}", fg="red", err=True)
        sys.exit(1)
    except OSError as exc:
        # The last resort for a file system that refuses (a read-only or missing folder,
        # a full disk): the path and the system's reason, not a traceback.
        where = f"{exc.filename}: " if exc.filename else ""
        click.secho(f"error: {where}{exc.strerror or exc}", fg="red", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)

"""The click parameter types of ``gonio.cli`` that the subsystem commands share."""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from gonio.cli import FiniteFloatRange


@click.command()
@click.option("--x", type=FiniteFloatRange(0.0, 90.0, min_open=True), default=None)
@click.option("--y", type=FiniteFloatRange(min=0.0), default=None)
def _cmd(x: float | None, y: float | None) -> None:
    click.echo(f"x={x} y={y}")


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (["--x", "nan"], "--x"),
        (["--x", "-nan"], "--x"),
        (["--y", "nan"], "--y"),
        (["--y", "inf"], "--y"),
        (["--x", "inf"], "--x"),
        (["--x", "0"], "--x"),
        (["--y", "-1"], "--y"),
        (["--y", "abc"], "--y"),
    ],
)
def test_nan_inf_and_out_of_range_values_are_usage_errors_naming_the_option(args, option):
    # click.FloatRange compares, and every comparison with NaN is false: it let NaN through
    # (and inf, without a maximum).
    res = CliRunner().invoke(_cmd, args)
    assert res.exit_code == 2, res.output
    assert f"'{option}'" in res.output and args[1] in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)


def test_finite_values_in_range_pass_unchanged():
    res = CliRunner().invoke(_cmd, ["--x", "90", "--y", "1e300"])
    assert res.exit_code == 0, res.output
    assert res.output.strip() == "x=90.0 y=1e+300"


def test_the_help_shows_the_range_as_float_range_does():
    res = CliRunner().invoke(_cmd, ["--help"])
    assert "0<x<=90" in res.output and "x>=0" in res.output

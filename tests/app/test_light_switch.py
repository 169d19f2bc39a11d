"""A real rig's light switches: the serial relay's bytes on a pty pair (read back from
the other end), the operator's prompt answered through click's runner, the ``--light``
option's parsing, and the CLI's refusal of darks without a switch before anything is
opened."""

from __future__ import annotations

import os
import select

import click
import pytest
from click.testing import CliRunner

from gonio.app.light_switch import (
    DEFAULT_OFF,
    DEFAULT_ON,
    OperatorLight,
    SerialRelayLight,
    open_light,
    parse_light_spec,
)
from gonio.errors import CameraError, ConfigError


@pytest.fixture
def pty_pair():
    """(master fd, slave device name): the relay writes to the slave, the test reads
    what arrived at the master."""
    master, slave = os.openpty()
    import tty

    tty.setraw(master)
    tty.setraw(slave)
    name = os.ttyname(slave)
    yield master, name
    os.close(master)
    os.close(slave)


def _read(fd: int, n: int) -> bytes:
    out = b""
    while len(out) < n:
        ready, _, _ = select.select([fd], [], [], 5.0)
        assert ready, f"the relay sent {out!r}, expected {n} bytes"
        out += os.read(fd, n - len(out))
    return out


def test_serial_relay_sends_its_commands_and_waits(pty_pair):
    master, port = pty_pair
    slept = []
    light = SerialRelayLight(port, sleep=slept.append, settle_s=0.25)
    try:
        light.set_light(False)
        assert _read(master, 4) == bytes([0xA0, 0x01, 0x00, 0xA1])  # the LCUS-1's "off"
        light.set_light(True)
        assert _read(master, 4) == bytes([0xA0, 0x01, 0x01, 0xA2])
        assert slept == [0.25, 0.25]
        assert light.is_on is True
    finally:
        light.close()
    light.close()  # idempotent


def test_serial_relay_with_configured_commands_from_the_option(pty_pair):
    master, port = pty_pair
    spec = f"relay:{port},on=FF0101,off=FF0100,baud=115200,settle=0"
    light = open_light(spec)
    assert isinstance(light, SerialRelayLight)
    try:
        light.set_light(False)
        light.set_light(True)
        assert _read(master, 6) == bytes.fromhex("FF0100FF0101")
    finally:
        light.close()


def test_serial_relay_on_a_missing_port_is_a_camera_error():
    with pytest.raises(CameraError, match="/dev/nonexistent-gonio-relay"):
        SerialRelayLight("/dev/nonexistent-gonio-relay")


def test_operator_light_asks_and_waits_for_enter():
    light = OperatorLight()

    @click.command()
    def cmd():
        light.set_light(True)  # already on at the start: nothing asked
        light.set_light(False)
        click.echo("dark frames now")
        light.set_light(True)

    res = CliRunner().invoke(cmd, input="\n\n")
    assert res.exit_code == 0, res.output
    out = res.output
    assert out.count("Switch the rig's light") == 2
    assert out.index("light OFF") < out.index("dark frames now") < out.index("light ON")


def test_operator_light_without_an_answer_stops_the_session():
    light = OperatorLight()

    @click.command()
    def cmd():
        light.set_light(False)

    res = CliRunner().invoke(cmd, input="")  # end of input: nobody there
    assert isinstance(res.exception, CameraError)
    assert "did not confirm the light off" in str(res.exception)


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        ("lamp", "expected relay:PORT, operator or none"),
        ("relay:", "needs a serial port"),
        ("relay:/dev/ttyUSB0,on=XYZ", "'on=XYZ'"),
        ("relay:/dev/ttyUSB0,baud=fast", "'baud=fast'"),
        ("relay:/dev/ttyUSB0,settle=-1", "'settle=-1'"),
        ("relay:/dev/ttyUSB0,colour=red", "unknown key"),
        ("relay:/dev/ttyUSB0,on", "expected key=value"),
    ],
)
def test_bad_light_option_names_the_part(spec, words):
    with pytest.raises(ConfigError) as info:
        parse_light_spec(spec)
    assert "--light" in str(info.value) and words in str(info.value)


def test_light_option_kinds():
    assert parse_light_spec("none") == {"kind": "none"}
    assert open_light("none") is None
    assert isinstance(open_light("operator"), OperatorLight)
    p = parse_light_spec("relay:COM3")
    assert p == {"kind": "relay", "port": "COM3"}
    assert DEFAULT_ON != DEFAULT_OFF


def test_run_with_darks_and_no_light_switch_is_refused_before_anything_opens(tmp_path, capsys):
    from gonio.cli import run

    plan = tmp_path / "plan.toml"
    plan.write_text("[grid]\ntheta_i_deg = [0]\ntheta_o_deg = [30]\n[darks]\ncount = 2\n")
    out = tmp_path / "S"
    # the gphoto2 camera (the default) has no light of its own
    assert run("capture", "run", str(plan), "--out", str(out)) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "[darks] count = 2" in err and "--light" in err
    assert not out.exists()
    assert run("capture", "run", str(plan), "--out", str(out), "--light", "lamp") == 1
    assert "expected relay:PORT, operator or none" in capsys.readouterr().err
    assert not out.exists()

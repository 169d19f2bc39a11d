"""`gonio rig ...` and `gonio sim bus` as a user runs them."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gonio.cli import main


def run(capsys, *args):
    with pytest.raises(SystemExit) as info:
        main(list(args))
        raise SystemExit(0)
    out = capsys.readouterr()
    return info.value.code, out.out, out.err


def test_scan_json(vbus, capsys):
    code, out, _ = run(capsys, "rig", "scan", "--port", vbus.port, "--json")
    assert code == 0
    data = json.loads(out)
    assert [s["id"] for s in data["servos"]] == [1, 2, 3, 4]
    assert data["servos"][0] == {
        "id": 1,
        "model_number": 1020,
        "model": "XM430-W350",
        "firmware": 45,
    }


def test_move_status_off(vbus, capsys):
    code, out, err = run(
        capsys,
        "rig",
        "move",
        "--port",
        vbus.port,
        "--theta-i",
        "30",
        "--phi-i",
        "0",
        "--theta-o",
        "40",
        "--phi-o",
        "150",
        "--json",
    )
    assert code == 0, err
    res = json.loads(out)
    assert res["error_i_deg"] < 0.088 and res["error_o_deg"] < 0.088
    assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
    code, out, err = run(
        capsys,
        "rig",
        "move",
        "--port",
        vbus.port,
        "--theta-i",
        "30",
        "--theta-o",
        "30",
        "--phi-o",
        "170",
        "--hold",
    )
    assert code == 0, err
    assert vbus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
    code, out, _ = run(capsys, "rig", "status", "--port", vbus.port, "--json")
    st = json.loads(out)
    assert [s["torque"] for s in st["servos"]] == [True] * 4  # opening keeps them holding
    assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}  # ... and status cut torque on exit
    code, out, _ = run(capsys, "rig", "off", "--port", vbus.port)
    assert code == 0 and "torque off" in out


def test_cli_bad_input_exits_nonzero(vbus, capsys):
    code, _, err = run(capsys, "rig", "status", "--port", "/dev/nope")
    assert code == 1 and "cannot open serial port '/dev/nope'" in err
    code, _, err = run(
        capsys,
        "rig",
        "move",
        "--port",
        vbus.port,
        "--theta-i",
        "30",
        "--phi-i",
        "0",
        "--theta-o",
        "30",
        "--phi-o",
        "5",
    )
    assert code == 1 and "shadow" in err
    assert all(not any(v for _, v in s.torque_log) for s in vbus.servos.values())


def test_sim_bus_command_serves_until_sigterm():
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "gonio"),
            "sim",
            "bus",
            "--servos",
            "1,2,3,4",
            "--fault-rate",
            "0",
            "--seed",
            "3",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/pts/")
        from gonio.rig.transport import Transport

        with Transport(port) as bus:
            assert bus.ping(4) == (1020, 45)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0
    assert json.loads(err.strip().splitlines()[-1])["packets"] >= 1  # the PING was served

"""The README's lab walkthrough, against `gonio sim bus` instead of a U2D2 adapter."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
GONIO = [sys.executable, "-m", "gonio"]


@pytest.fixture()
def bus_port():
    p = subprocess.Popen(
        GONIO + ["sim", "bus", "--rig", str(REPO / "examples" / "rig.toml")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        port = p.stdout.readline().strip()
        assert port.startswith("/dev/"), p.stderr.read()
        yield port
    finally:
        p.send_signal(2)  # Ctrl-C: the bus prints its statistics and exits
        p.communicate(timeout=20)


def gonio(*args):
    r = subprocess.run(GONIO + list(args), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


@pytest.mark.slow
def test_scan_home_move_status_off_on_a_fresh_virtual_rig(bus_port):
    scan = json.loads(gonio("rig", "scan", "--port", bus_port, "--json"))
    servos = scan["servos"] if isinstance(scan, dict) else scan
    assert sorted(s["id"] for s in servos) == [1, 2, 3, 4]
    cfg = ["--config", str(REPO / "examples" / "rig.toml"), "--port", bus_port]
    # a freshly powered virtual rig starts parked, so homing is allowed (at the servos'
    # centre position both arms would face the same azimuth and every move is refused)
    gonio("rig", "home", *cfg)
    out = json.loads(
        gonio(
            "rig",
            "move",
            *cfg,
            "--theta-i",
            "30",
            "--phi-i",
            "0",
            "--theta-o",
            "45",
            "--phi-o",
            "180",
            "--json",
        )
    )
    assert out, out
    status = gonio("rig", "status", *cfg)
    assert "light theta 29.9" in status or "light theta 30.0" in status, status
    assert "camera theta 45.0" in status, status
    gonio("rig", "off", *cfg)


@pytest.mark.slow
def test_the_example_session_plans_runs_inspects_reduces_and_fits(tmp_path):
    """The README's session commands on examples/ (a virtual bus in place of the U2D2):
    each step as a user types it, each output opened by the next step."""
    rig = tmp_path / "rig.toml"
    text = (REPO / "examples" / "rig.toml").read_text()
    rig.write_text(text.replace('port = "/dev/ttyUSB0"', 'port = "virtual"'))
    assert 'port = "virtual"' in rig.read_text()
    plan = str(REPO / "examples" / "plan.toml")
    dry = json.loads(gonio("capture", "plan", plan, "--rig", str(rig), "--json"))
    s = tmp_path / "S"
    gonio("capture", "run", plan, "--rig", str(rig), "--camera", "simulated", "--out", str(s),
          "--quiet")  # fmt: skip
    info = json.loads(gonio("capture", "inspect", str(s), "--json"))
    assert info["status"] == "completed" and info["bad_files"] == []
    steps = dry["sample_poses"] + dry["reference_poses"] + dry["dark_steps"]
    assert info["poses_done"] == info["poses_total"] == steps
    gonio("capture", "reduce", str(s), "--quiet")
    fit = tmp_path / "fit"
    gonio("fit", str(s / "samples.h5"), "--model", "auto", "--out", str(fit))
    result = json.loads((fit / "fit.json").read_text())
    assert result["success"] is True
    assert (fit / "material.xml").is_file()

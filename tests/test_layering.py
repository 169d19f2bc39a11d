"""The layering contract (``.importlinter``, run by ``.ci/layering.py``) catches what it must.

Each test stages the package as installed, adds one import inside a function (grimp reads
function-level imports too) and checks that import-linter reports exactly that import under
the contract that forbids it, and that it was not reported before.  The comparison is with
the unmodified tree rather than with a clean report, because the tree may still carry
violations being removed elsewhere; ``.ci/run`` runs the check on the real tree.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RUNNER = ROOT / ".ci" / "layering.py"

INWARDS = "Dependencies point inwards"
FITTING_RIG = "gonio.fitting does not import gonio.rig"
SIMULATOR_RIG = "gonio.simulator imports of gonio.rig only its protocol definitions"


def _runner():
    spec = importlib.util.spec_from_file_location("gonio_ci_layering", RUNNER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _lint(staged: Path) -> tuple[int, str]:
    # A separate process: in this one `gonio` is already imported from the source tree,
    # and grimp would find that instead of the staged copy.
    proc = subprocess.run(
        [sys.executable, str(RUNNER), "--root", str(ROOT), "--staged", str(staged)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return proc.returncode, proc.stdout + proc.stderr


def _status(report: str, contract: str) -> str:
    """KEPT or BROKEN for the contract whose name starts with ``contract``."""
    m = re.search(rf"^{re.escape(contract)}.*? (KEPT|BROKEN)", report, re.MULTILINE)
    assert m, f"contract {contract!r} not in the report:\n{report}"
    return m.group(1)


def _inject(path: Path, module: str) -> int:
    """Append a function that imports ``module``; return the import's line number."""
    text = path.read_text()
    lines = text.splitlines()
    lines += ["", "", "def _layering_probe():", f"    import {module}  # noqa: F401", ""]
    path.write_text("\n".join(lines))
    return len(lines) - 1


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    staged = _runner().stage(ROOT, tmp_path_factory.mktemp("baseline"))
    return _lint(staged)


@pytest.fixture
def staged(tmp_path):
    return _runner().stage(ROOT, tmp_path)


def test_the_tree_keeps_every_contract(baseline):
    """ARCHITECTURE's rules hold as written: what CI's .ci/layering.py checks."""
    rc, report = baseline
    assert rc == 0, report
    for contract in (INWARDS, FITTING_RIG, SIMULATOR_RIG):
        assert _status(report, contract) == "KEPT", report


def test_staging_lays_out_the_installed_package(staged, baseline):
    # Every mapped folder lands at its dotted name, and grimp analyses every file of it.
    assert (staged / "gonio" / "rig" / "kinematics.py").is_file()
    assert (staged / "gonio" / "simulator" / "scene.py").is_file()
    assert (staged / "gonio" / "radiometry" / "frames.py").is_file()
    sources = [
        p
        for folder in ("gonio", "rig", "capture", "fitting", "simulator")
        for p in (ROOT / folder).rglob("*.py")
        if "__pycache__" not in p.parts
    ]
    m = re.search(r"Analyzed (\d+) files", baseline[1])
    assert m, baseline[1]
    assert int(m.group(1)) == len(sources)


@pytest.mark.parametrize(
    ("where", "module", "contract", "importer"),
    [
        # capture never imports the simulator
        ("gonio/capture/fiducials.py", "gonio.simulator.scene", INWARDS, "gonio.capture.fiducials"),
        # the core imports no subsystem
        ("gonio/radiometry/frames.py", "gonio.capture.plan", INWARDS, "gonio.radiometry.frames"),
        ("gonio/brdf/base.py", "gonio.fitting.fit", INWARDS, "gonio.brdf.base"),
        # nothing but the composition root imports it
        ("gonio/fitting/export.py", "gonio.app", INWARDS, "gonio.fitting.export"),
        # the rig imports no subsystem above it
        ("gonio/rig/servo.py", "gonio.capture.plan", INWARDS, "gonio.rig.servo"),
        # fitting and the rig are independent
        ("gonio/fitting/losses.py", "gonio.rig.config", FITTING_RIG, "gonio.fitting.losses"),
        # of the rig the simulator imports only the protocol definitions
        (
            "gonio/simulator/render.py",
            "gonio.rig.kinematics",
            SIMULATOR_RIG,
            "gonio.simulator.render",
        ),
        ("gonio/simulator/dng.py", "gonio.rig.device", SIMULATOR_RIG, "gonio.simulator.dng"),
        # ... and the protocol definitions do not reach past themselves
        ("gonio/rig/protocol.py", "gonio.rig.kinematics", SIMULATOR_RIG, "gonio.rig.protocol"),
    ],
)
def test_a_forbidden_function_level_import_breaks_its_contract(
    staged, baseline, where, module, contract, importer
):
    line = _inject(staged / where, module)
    rc, report = _lint(staged)
    chain = f"{importer} -> {module} (l.{line})"
    assert rc == 1, report
    assert _status(report, contract) == "BROKEN", report
    assert chain in report, report
    assert chain not in baseline[1]


def test_a_new_rig_module_is_forbidden_to_the_simulator_too(staged, baseline):
    (staged / "gonio" / "rig" / "homing.py").write_text('"""A rig module added later."""\n')
    line = _inject(staged / "gonio" / "simulator" / "sensor.py", "gonio.rig.homing")
    rc, report = _lint(staged)
    assert rc == 1
    assert _status(report, SIMULATOR_RIG) == "BROKEN", report
    assert f"gonio.simulator.sensor -> gonio.rig.homing (l.{line})" in report


def test_a_new_core_module_must_be_placed_in_a_layer(staged, baseline):
    (staged / "gonio" / "colours.py").write_text('"""A core module nobody listed."""\n')
    rc, report = _lint(staged)
    assert rc == 1
    assert _status(report, INWARDS) == "BROKEN", report
    assert "gonio.colours" in report
    assert "gonio.colours" not in baseline[1]


@pytest.mark.parametrize(
    ("where", "module"),
    [
        ("gonio/capture/fiducials.py", "gonio.rig.kinematics"),  # capture may use the rig
        ("gonio/simulator/render.py", "gonio.rig.protocol"),  # the protocol definitions
        ("gonio/simulator/render.py", "gonio.rig.control_table"),
        ("gonio/app/__init__.py", "gonio.simulator.scene"),  # the composition root wires
        ("gonio/fitting/losses.py", "gonio.brdf.base"),  # subsystems import the core
    ],
)
def test_an_allowed_import_changes_nothing(staged, baseline, where, module):
    _inject(staged / where, module)
    rc, report = _lint(staged)
    assert rc == baseline[0] == 0, report
    for contract in (INWARDS, FITTING_RIG, SIMULATOR_RIG):
        assert _status(report, contract) == _status(baseline[1], contract)
    importer = where.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
    assert f"{importer} -> {module}" not in report

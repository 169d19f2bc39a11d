"""The package installs as one `gonio` namespace and its command line works."""

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from gonio import __version__
from gonio.cli import main

REPO = Path(__file__).resolve().parents[2]


def test_every_package_folder_is_listed_in_pyproject():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    dirs = {v: k for k, v in cfg["package-dir"].items()}
    found = set()
    for init in REPO.glob("*/**/__init__.py"):
        rel = init.parent.relative_to(REPO).parts
        if rel[0] in dirs:
            found.add(".".join([dirs[rel[0]], *rel[1:]]))
    assert found == listed


@pytest.mark.slow
def test_wheel_contains_every_subpackage(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(REPO)],
        check=True,
    )
    (wheel,) = tmp_path.glob("gonio-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for pkg in (
        "gonio",
        "gonio/radiometry",
        "gonio/brdf",
        "gonio/rig",
        "gonio/capture",
        "gonio/fitting",
        "gonio/simulator",
    ):
        assert f"{pkg}/__init__.py" in names, pkg
    assert any(n.endswith("entry_points.txt") for n in names)


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"]) or sys.exit(0)
    assert e.value.code in (0, None)
    assert __version__ in capsys.readouterr().out
    r = subprocess.run([sys.executable, "-m", "gonio", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "Usage: gonio" in r.stdout


def test_unknown_command_exits_non_zero():
    r = subprocess.run([sys.executable, "-m", "gonio", "nonsense"], capture_output=True, text=True)
    assert r.returncode != 0 and "No such command" in r.stderr

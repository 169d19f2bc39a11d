"""Check the layering contract (``.importlinter``) against the installed package layout.

``pyproject.toml`` maps the subsystem folders into the ``gonio`` namespace (setuptools
``package-dir``: ``gonio.rig`` lives in ``rig/``), but grimp finds a package's modules by
walking the package's own directory, so on the source tree it would see ``gonio`` without
``gonio.rig``, ``gonio.capture``, ``gonio.fitting`` and ``gonio.simulator``, and every
contract about them would pass vacuously.  This script copies the ``.py`` files into a
temporary tree laid out as installed (``gonio/rig/...``), then runs import-linter on it.

Usage::

    python .ci/layering.py [--root REPO] [--config FILE] [--keep DIR | --staged DIR]

Exit status 0 when every contract is kept, 1 otherwise (import-linter's report says which
contract, which modules, and the line of each import).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import tomllib
from pathlib import Path


def package_dirs(root: Path) -> dict[str, Path]:
    """Read ``[tool.setuptools] package-dir`` from ``root/pyproject.toml``.

    Returns
    -------
    dict
        Dotted package name -> its folder in the repository.
    """
    with open(root / "pyproject.toml", "rb") as f:
        mapping = tomllib.load(f)["tool"]["setuptools"]["package-dir"]
    return {name: root / folder for name, folder in mapping.items()}


def stage(root: Path, dest: Path) -> Path:
    """Lay out the repository's packages under ``dest`` as an installation would.

    Only ``.py`` files are copied: that is all grimp reads.

    Returns
    -------
    Path
        ``dest`` (put it first on ``sys.path`` to import the staged ``gonio``).
    """
    for name, folder in package_dirs(root).items():
        target = dest.joinpath(*name.split("."))
        for src in folder.rglob("*.py"):
            rel = src.relative_to(folder)
            if "__pycache__" in rel.parts:
                continue
            out = target / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, out)
    return dest


def lint(staged: Path, config: Path) -> int:
    """Run import-linter with ``config`` on the ``gonio`` staged in ``staged``.

    Returns
    -------
    int
        0 when every contract is kept, 1 otherwise.
    """
    # A wide console, so that CI logs keep one import chain per line.
    os.environ["COLUMNS"] = "200"
    from importlinter.cli import lint_imports

    # import-linter puts the working directory first on sys.path: make that the staged
    # tree, so the repository's own gonio/ (without the subsystems) cannot shadow it.
    previous = os.getcwd()
    os.chdir(staged)
    try:
        return lint_imports(config_filename=str(config), no_cache=True, no_logo=True)
    finally:
        os.chdir(previous)


def main(argv: list[str] | None = None) -> int:
    """Stage the repository given by ``--root`` and lint it; return the exit status."""
    here = Path(__file__).resolve().parent.parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=here, help="repository (default: this one)")
    parser.add_argument("--config", type=Path, help="contract file (default: ROOT/.importlinter)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--keep", type=Path, help="stage into this directory and keep it")
    where.add_argument("--staged", type=Path, help="lint this already staged tree as it is")
    args = parser.parse_args(argv)
    root = args.root.resolve()
    config = (args.config or root / ".importlinter").resolve()
    if args.staged is not None:
        return lint(args.staged.resolve(), config)
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        return lint(stage(root, args.keep.resolve()), config)
    with tempfile.TemporaryDirectory(prefix="gonio-layering-") as tmp:
        return lint(stage(root, Path(tmp)), config)


if __name__ == "__main__":
    sys.exit(main())

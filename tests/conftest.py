"""Shared fixtures: where the real third-party reference data live."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def refdata_dir() -> Path:
    """``$GONIO_REFDATA`` or ``../shared/data`` next to the repository."""
    return Path(os.environ.get("GONIO_REFDATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def refdata() -> Path:
    """The shared reference data folder; skips the test (with the reason) when absent."""
    d = refdata_dir()
    if not d.is_dir():
        pytest.skip(f"reference data not found at {d} (set GONIO_REFDATA)")
    return d


@pytest.fixture(scope="session")
def rgl_file(refdata):
    """Factory: path of a shared RGL .bsdf file by material name."""

    def get(name: str) -> Path:
        p = refdata / "rgl" / f"{name}_rgb.bsdf"
        if not p.is_file():
            pytest.skip(f"RGL file {p} not found")
        return p

    return get

"""Shared fixtures.

The published reference files live outside the repository (``../shared/reference`` beside the
checkout, the path CI has). ``REACHPLAN_SHARED`` overrides that one path. When ``CI=true`` a missing
reference folder is an error, not a skip.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The folder that holds ``reference/`` (``$REACHPLAN_SHARED`` or ``<repo>/../shared``)."""
    return Path(os.environ.get("REACHPLAN_SHARED", REPO_ROOT.parent / "shared")).resolve()


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    """``<shared>/reference``; skipped visibly outside CI when absent, a failure in CI."""
    ref = shared_dir() / "reference"
    if not ref.is_dir():
        msg = f"reference files not found at {ref}; set REACHPLAN_SHARED to the folder holding reference/"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return ref


@pytest.fixture(scope="session")
def dciodvfy() -> Callable[[Path], list[str]]:
    """Run David Clunie's ``dciodvfy`` on a file; returns its output lines. Must run in CI."""
    exe = shutil.which("dciodvfy") or shutil.which("dciodvfy", path=str(Path(sys.executable).parent))
    if exe is None:
        msg = "dciodvfy not found: install the test extra (dicom3tools) or Debian's dicom3tools"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)

    def run(path: Path) -> list[str]:
        out = subprocess.run([exe, str(path)], capture_output=True, text=True, timeout=60)
        return (out.stdout + out.stderr).splitlines()

    return run

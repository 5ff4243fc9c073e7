"""Shared fixtures.

The published reference files live outside the repository (``../shared/reference`` beside the
checkout, the path CI has). ``REACHPLAN_SHARED`` overrides that one path. Tests reach every reference file
through the ``reference_file`` fixture, which skips a test whose file is missing with a reason
naming the file, and fails it when ``CI=true``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The folder that holds ``reference/`` (``$REACHPLAN_SHARED`` or ``<repo>/../shared``)."""
    return Path(os.environ.get("REACHPLAN_SHARED", REPO_ROOT.parent / "shared")).resolve()


def _missing(msg: str) -> NoReturn:
    """Skip the test visibly, or fail it when ``CI=true`` (CI must run every test)."""
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg)
    pytest.skip(msg)


@pytest.fixture(scope="session")
def reference_file() -> Callable[[str], Path]:
    """``reference_file("tps_examples/hdr/RP.HDR.dcm")``: that file of ``<shared>/reference``, which must exist.

    A missing file skips the test (fails it when ``CI=true``) with a reason that names the file and
    ``REACHPLAN_SHARED``. Tests name every file they read, not a folder: a folder with one file gone is reported too.
    """

    def get(rel: str) -> Path:
        path = shared_dir() / "reference" / rel
        if not path.is_file():
            _missing(f"reference file {rel} not found at {path}; "
                     "set REACHPLAN_SHARED to the folder holding reference/")
        return path

    return get


@pytest.fixture(scope="session")
def dciodvfy() -> Callable[[Path], list[str]]:
    """Run David Clunie's ``dciodvfy`` on a file; returns its output lines. Must run in CI."""
    exe = shutil.which("dciodvfy") or shutil.which("dciodvfy", path=str(Path(sys.executable).parent))
    if exe is None:
        _missing("dciodvfy not found: install the test extra (dicom3tools) or Debian's dicom3tools")

    def run(path: Path) -> list[str]:
        out = subprocess.run([exe, str(path)], capture_output=True, text=True, timeout=60)
        return (out.stdout + out.stderr).splitlines()

    return run


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the files that hold a test marked ``slow`` first, each file's tests kept together and in order.

    With ``--dist loadfile`` (pyproject.toml) xdist hands out whole files in this order, so the long ones start at
    once instead of leaving one worker busy at the end while the other idles.
    """
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)

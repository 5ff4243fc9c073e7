"""Importing reachplan changes no process-wide state: no matplotlib backend chosen, no pyplot, umask kept."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

CODE = """
import importlib, os, pkgutil, sys
import matplotlib
import reachplan
os.umask(0o027)
names = [m.name for m in pkgutil.walk_packages(reachplan.__path__, "reachplan.") if not m.name.endswith("__main__")]
for name in names:
    importlib.import_module(name)
assert len(names) > 40, names
print("pyplot" if "matplotlib.pyplot" in sys.modules else "no pyplot")
print(matplotlib.rcParams._get("backend"))
print(oct(os.umask(0o027)))
"""


def test_importing_every_module_leaves_matplotlib_and_the_umask_alone(tmp_path: Path) -> None:
    env = dict(os.environ, MPLBACKEND="svg")
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, cwd=tmp_path, env=env,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["no", "pyplot", "svg", "0o27"]

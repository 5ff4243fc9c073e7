"""Start-up stays light: building the command line imports none of the heavy libraries (issue 19).

The time itself is measured by ``reachplan bench startup``, not here; this checks the cause, which cannot be noisy.
"""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("numpy", "scipy", "numba", "trimesh", "fcl", "matplotlib", "pydicom", "importlib.metadata")


def test_help_imports_no_heavy_library() -> None:
    code = ("import sys, json; from reachplan.planner.cli import build_parser; build_parser(); "
            f"print(json.dumps([m for m in {list(HEAVY)!r} if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert json.loads(out) == []


def test_rod_does_not_import_the_planner_or_mesh_libraries() -> None:
    code = ("import sys, json, contextlib, io\n"
            "from reachplan.planner.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    main(['rod', '--preset', '15ga-30j-tip', '--tension', '2', '--json'])\n"
            "print(json.dumps([m for m in ('trimesh', 'fcl', 'matplotlib', 'pydicom', 'reachplan.planner.pipeline')"
            " if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_plugin_kinds_spelled_out_for_start_up_match_the_registry() -> None:
    from reachplan.planner.cli import plugins as cli_plugins
    from reachplan.plugins.registry import KINDS

    assert cli_plugins.KINDS == KINDS

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
            "print(json.dumps([m for m in ('trimesh', 'fcl', 'matplotlib', 'pydicom', 'reachplan.planner.case.search')"
            " if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_plugin_kinds_spelled_out_for_start_up_match_the_registry() -> None:
    from reachplan.planner.cli import plugins as cli_plugins
    from reachplan.plugins.registry import KINDS

    assert cli_plugins.KINDS == KINDS


def test_one_rod_solve_from_the_command_runs_without_numba_and_gives_the_compiled_shape() -> None:
    """``reachplan rod --tension N`` (its own process): the kernel as plain Python, numba not even imported; the
    same shape as the compiled kernel of a caller of ``main`` (and a sweep keeps the compiled kernel)."""
    import contextlib
    import io

    from reachplan.planner.cli import main

    def child(*args: str) -> tuple[dict[str, object], bool]:
        code = ("import sys, json, contextlib, io\n"
                "from reachplan.planner.cli import console\n"
                f"sys.argv = ['reachplan', *{list(args)!r}]\n"
                "buf = io.StringIO()\n"
                "with contextlib.redirect_stdout(buf):\n"
                "    console()\n"
                "print(json.dumps([json.loads(buf.getvalue()), 'numba' in sys.modules]))")
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
        doc, numba = json.loads(out.strip().splitlines()[-1])
        return doc, numba

    args = ("rod", "--preset", "15ga-30j-tip", "--tension", "5", "--json")
    plain, numba_loaded = child(*args)
    assert not numba_loaded
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(list(args)) == 0
    compiled = json.loads(buf.getvalue())
    assert plain["converged"] and compiled["converged"]
    assert plain["tip_position_mm"] == compiled["tip_position_mm"]
    sweep, numba_loaded = child("rod", "--preset", "15ga-30j-tip", "--tensions", "2,5", "--json")
    assert numba_loaded and len(sweep) == 2  # type: ignore[arg-type]

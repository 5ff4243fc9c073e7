"""The house: one import root, floors that hold (import-linter contracts in pyproject.toml), every package shipped."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import reachplan

REPO_ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = REPO_ROOT / "pyproject.toml"
FLOORS = ("planner", "imaging", "rod_model", "plugins")


def _lint(pythonpath: Path | None, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run import-linter's contracts of ``pyproject.toml`` on the ``reachplan`` found first on the path."""
    code = ("import sys; from importlinter.cli import lint_imports; "
            f"sys.exit(lint_imports(config_filename={str(PYPROJECT)!r}))")
    env = None
    if pythonpath is not None:
        import os

        env = dict(os.environ, PYTHONPATH=str(pythonpath))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=120)


def test_installed_package_keeps_its_floors_and_rooms(tmp_path: Path) -> None:
    out = _lint(None, tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "3 kept, 0 broken" in out.stdout


@pytest.mark.parametrize(("module", "upward"), [
    ("imaging/meshing.py", "import reachplan.planner.run.case"),           # floor 1 -> floor 3
    ("rod_model/select.py", "import reachplan.plugins.registry"),           # floor 1 -> floor 2
    ("plugins/exporters/device.py", "import reachplan.planner.errors"),     # floor 2 -> floor 3
    ("planner/geometry/collision.py", "import reachplan.planner.dose.tg43"),  # room -> a room above it
    ("planner/dose/coverage.py", "import reachplan.planner.implant.plan"),  # dose -> the implant room above it
    ("planner/implant/plan.py", "import reachplan.planner.delivery"),  # implant -> delivery above it
    ("planner/case/scene.py", "import reachplan.planner.dose.tg43"),  # case and dose are independent
    ("planner/lookup.py", "import reachplan.planner.geometry.template"),  # lookup sits right above errors
    ("planner/delivery.py", "import reachplan.planner.run.case"),  # delivery -> run above it
    ("planner/verify/find.py", "import reachplan.planner.report.html"),  # verify -> the report room above it
])
def test_an_upward_import_breaks_the_contract(tmp_path: Path, module: str, upward: str) -> None:
    copy = tmp_path / "site" / "reachplan"
    shutil.copytree(Path(reachplan.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / module
    target.write_text(target.read_text(encoding="utf-8") + f"\n{upward}  # noqa\n", encoding="utf-8")
    out = _lint(tmp_path / "site", tmp_path)
    assert out.returncode != 0
    assert "BROKEN" in out.stdout


def _copy_with(tmp_path: Path, module: str, extra: str) -> Path:
    """Copy the installed package to ``tmp_path/site/reachplan`` with ``extra`` appended to ``module``; the site."""
    copy = tmp_path / "site" / "reachplan"
    shutil.copytree(Path(reachplan.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / module
    target.write_text(target.read_text(encoding="utf-8") + extra, encoding="utf-8")
    return tmp_path / "site"


@pytest.mark.parametrize(("module", "extra"), [
    # the circle insertion.py <-> tissue_rod.py had: at module level, and hidden in a function (grimp sees both)
    ("planner/steering/insertion.py", "\nimport reachplan.planner.steering.tissue_rod  # noqa\n"),
    ("planner/steering/insertion.py", "\n\ndef _f() -> None:\n    from reachplan.planner.steering.tissue_rod import "
                                      "TISSUE_ROD  # noqa\n"),
    ("plugins/checks.py", "\n\ndef _f() -> None:\n    from reachplan.plugins import registry  # noqa\n"),
])
def test_an_import_cycle_among_siblings_breaks_the_contract(tmp_path: Path, module: str, extra: str) -> None:
    out = _lint(_copy_with(tmp_path, module, extra), tmp_path)
    assert out.returncode != 0
    package = "reachplan." + ".".join(Path(module).parent.parts)
    assert "no import cycle among siblings BROKEN" in out.stdout
    assert f"No cycles are allowed in {package}." in out.stdout
    assert "2 kept, 1 broken" in out.stdout  # the floors and rooms still hold: the cycle is inside one room


#: Where a module sits: (floor, room), higher numbers higher up, from the import-linter contracts of pyproject.toml.
Rank = tuple[int, int]


def _ranks() -> tuple[dict[str, int], dict[str, int]]:
    """Floor of each top-level package and room of each planner module (the ``layers`` contracts), by name."""
    import tomllib

    contracts = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["tool"]["importlinter"]["contracts"]
    floors_c, = [c for c in contracts if c["type"] == "layers" and "containers" not in c]
    rooms_c, = [c for c in contracts if c["type"] == "layers" and c.get("containers") == ["reachplan.planner"]]
    floors = {name.strip(): len(floors_c["layers"]) - i
              for i, layer in enumerate(floors_c["layers"]) for name in layer.split("|")}
    rooms = {name.strip(): len(rooms_c["layers"]) - i
             for i, layer in enumerate(rooms_c["layers"]) for name in layer.split("|")}
    return floors, rooms


def _rank(module: str, floors: dict[str, int], rooms: dict[str, int]) -> Rank | None:
    """``module``'s (floor, room); room 0 outside the planner; None for the root package or an unknown name."""
    parts = module.split(".")
    floor = floors.get(".".join(parts[:2]))
    if floor is None:
        return None
    room = rooms.get(parts[2], 0) if parts[1] == "planner" and len(parts) > 2 else 0
    return floor, room


#: a module path of a floor of the package (a word boundary after the floor: "reachplan.rod_models" is an entry-point
#: group, not a module)
MODULE_PATH = re.compile(r"\breachplan\.(?:planner|plugins|imaging|rod_model|_arrays)\b(?:\.[A-Za-z_]\w*)*")


def _above(named: Rank, own: Rank) -> bool:
    """Whether a module of rank ``named`` sits above one of rank ``own`` (a higher floor, or a higher room of it)."""
    if named[0] != own[0]:
        return named[0] > own[0]
    return own[1] > 0 and named[1] > own[1]


def _names_above(root: Path) -> list[str]:
    """Every string in the package at ``root`` that names a module of a floor or room above its own module's.

    The string literals of the code (a call to ``importlib.import_module`` or ``__import__``, a ``"module:attribute"``
    target, a ``python -m`` argument, code given to ``python -c``), found in the AST; documentation (a string that is a
    statement of its own: docstrings) is not code and is left out. Returns ``"module: named"`` lines.
    """
    floors, rooms = _ranks()
    found: list[str] = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        own = _rank(module, floors, rooms)
        if own is None:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
                for named in MODULE_PATH.findall(node.value):
                    rank = _rank(named, floors, rooms)
                    if rank is not None and _above(rank, own):
                        found.append(f"{module}: {named}")
    return found


def test_no_module_names_a_higher_floor_or_room_in_a_string() -> None:
    assert _names_above(Path(reachplan.__file__).parent) == []


@pytest.mark.parametrize(("module", "extra", "named"), [
    ("plugins/exporters/device.py", "\n\ndef _f() -> object:\n    import importlib\n\n"
                                    "    return importlib.import_module('reachplan.planner.errors')\n",
     "reachplan.plugins.exporters.device: reachplan.planner.errors"),
    ("plugins/registry.py", "\nCHECK = 'reachplan.planner.steering.insertion:check_insertion_model'\n",
     "reachplan.plugins.registry: reachplan.planner.steering.insertion"),
    ("rod_model/select.py", "\nREGISTRY = __import__('reachplan.plugins.registry')\n",
     "reachplan.rod_model.select: reachplan.plugins.registry"),
    ("planner/bench/startup.py", "\nHELP = ('-m', 'reachplan.planner.cli', '--help')\n",
     "reachplan.planner.bench.startup: reachplan.planner.cli"),
    ("planner/geometry/collision.py", "\nWORK = 'from reachplan.planner.dose.dwells import dose_on_grid'\n",
     "reachplan.planner.geometry.collision: reachplan.planner.dose.dwells"),
])
def test_a_string_naming_a_module_above_is_found(tmp_path: Path, module: str, extra: str, named: str) -> None:
    site = _copy_with(tmp_path, module, extra)
    assert _names_above(site / "reachplan") == [named]


def test_a_docstring_or_a_string_naming_a_module_below_is_not_code_reaching_up(tmp_path: Path) -> None:
    extra = ('\n\ndef _f() -> str:\n    """See :mod:`reachplan.planner.cli`."""\n'
             '    return "reachplan.plugins.templates" + "reachplan.rod_model.protocol" + "reachplan.rod_models"\n')
    site = _copy_with(tmp_path, "plugins/checks.py", extra)
    assert _names_above(site / "reachplan") == []


def test_one_import_root_and_every_package_shipped(tmp_path: Path) -> None:
    files = importlib.metadata.files("reachplan") or []
    tops = {f.parts[0] for f in files if not f.parts[0].endswith(".dist-info") and f.parts[0] != ".."}
    assert tops == {"reachplan"}, tops
    out = subprocess.run([sys.executable, "-c", "import planner"], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode != 0 and "No module named 'planner'" in out.stderr
    assert (Path(reachplan.__file__).parent / "py.typed").is_file()
    assert issubclass(reachplan.ReachplanError, Exception) and reachplan.__version__


def test_every_package_folder_is_listed_in_pyproject() -> None:
    import tomllib

    listed = set(tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["tool"]["setuptools"]["packages"])
    found = {"reachplan"} | {
        "reachplan." + ".".join(p.parent.relative_to(REPO_ROOT).parts)
        for floor in FLOORS for p in (REPO_ROOT / floor).rglob("__init__.py") if "__pycache__" not in p.parts
    }
    assert found == listed


#: The only module that may look plugins up: planner/lookup.py (everything else is passed
#: what it needs).
REGISTRY = "reachplan.plugins.registry"


def _registry_importers(pythonpath: Path | None, cwd: Path) -> list[str]:
    """Modules of the ``reachplan`` found first on the path that import the plugin registry (grimp's graph)."""
    code = ("import grimp; g = grimp.build_graph('reachplan'); "
            f"print('\\n'.join(sorted(g.find_modules_that_directly_import({REGISTRY!r}))))")
    env = None
    if pythonpath is not None:
        import os

        env = dict(os.environ, PYTHONPATH=str(pythonpath))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, env=env,
                         timeout=120, check=True)
    return out.stdout.split()


def _may_look_up_plugins(module: str) -> bool:
    return module == "reachplan.planner.lookup"


def test_only_the_lookup_module_imports_the_plugin_registry(tmp_path: Path) -> None:
    importers = _registry_importers(None, tmp_path)
    assert "reachplan.planner.lookup" in importers  # the check sees the registry's imports at all
    assert [m for m in importers if not _may_look_up_plugins(m)] == []


@pytest.mark.parametrize("module", ["planner/steering/insertion.py", "planner/report/build.py", "planner/cli/plan.py",
                                    "planner/dose/tg43.py", "rod_model/select.py"])
def test_a_registry_import_elsewhere_is_found(tmp_path: Path, module: str) -> None:
    copy = tmp_path / "site" / "reachplan"
    shutil.copytree(Path(reachplan.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / module
    target.write_text(target.read_text(encoding="utf-8") + "\n\ndef _f() -> None:\n"
                      "    from reachplan.plugins import registry  # noqa\n", encoding="utf-8")
    importers = _registry_importers(tmp_path / "site", tmp_path)
    name = "reachplan." + module.removesuffix(".py").replace("/", ".")
    assert name in importers and not _may_look_up_plugins(name)

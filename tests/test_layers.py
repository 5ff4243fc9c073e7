"""The house: one import root, floors that hold (import-linter contracts in pyproject.toml), every package shipped."""

from __future__ import annotations

import importlib.metadata
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
    assert "2 kept, 0 broken" in out.stdout


@pytest.mark.parametrize(("module", "upward"), [
    ("imaging/meshing.py", "import reachplan.planner.pipeline"),           # floor 1 -> floor 3
    ("rod_model/select.py", "import reachplan.plugins.registry"),           # floor 1 -> floor 2
    ("plugins/exporters/device.py", "import reachplan.planner.errors"),     # floor 2 -> floor 3
    ("planner/geometry/collision.py", "import reachplan.planner.dose.tg43"),  # room -> a room above it
])
def test_an_upward_import_breaks_the_contract(tmp_path: Path, module: str, upward: str) -> None:
    copy = tmp_path / "site" / "reachplan"
    shutil.copytree(Path(reachplan.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / module
    target.write_text(target.read_text(encoding="utf-8") + f"\n{upward}  # noqa\n", encoding="utf-8")
    out = _lint(tmp_path / "site", tmp_path)
    assert out.returncode != 0
    assert "BROKEN" in out.stdout


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


#: The only modules that may look plugins up: the pipeline, the planner's look-up module and the command line
#: (everything else is passed what it needs, or asks ``reachplan.planner.lookup``).
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
    return module in ("reachplan.planner.pipeline", "reachplan.planner.lookup") or module.startswith(
        "reachplan.planner.cli.")


def test_only_the_pipeline_and_the_cli_import_the_plugin_registry(tmp_path: Path) -> None:
    importers = _registry_importers(None, tmp_path)
    assert "reachplan.planner.pipeline" in importers  # the check sees the registry's imports at all
    assert [m for m in importers if not _may_look_up_plugins(m)] == []


@pytest.mark.parametrize("module", ["planner/steering/insertion.py", "planner/report/build.py",
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

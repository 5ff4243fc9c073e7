"""Every public function and class documents its Parameters and Returns (numpydoc: shape, unit, frame).

pydoclint checks each function's sections against its signature with the options of ``[tool.pydoclint]`` in
pyproject.toml; a dataclass documents its fields in its class docstring's Parameters section, which is checked
here (pydoclint's own class-attribute check wants an Attributes section). Private names (leading underscore),
private modules (``_name.py``, pydoclint's ``exclude``), dunders and ``__init__`` are exempt. The source tree is
checked (the files a change edits), not the installed copy.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = REPO_ROOT / "pyproject.toml"

#: Files and folders checked, relative to the repository root.
CHECKED = ("imaging", "planner")
#: Files and folders under ``CHECKED`` left out, relative to the repository root.
NOT_CHECKED: tuple[str, ...] = ()

#: DOC105 compares a docstring type with the annotation; ours are shapes and units (``(n, 3) float, mm, LPS``).
DROPPED_CODES = ("DOC105",)
_DUNDER = re.compile(r"`(?:\w+\.)*__\w+__`")
_FINDING = re.compile(r"^(?P<path>.+?):(?P<line>\d+): (?P<code>DOC\d+): (?P<msg>.*)$")


def _require_pydoclint() -> None:
    if importlib.util.find_spec("pydoclint") is None:
        msg = "pydoclint not installed: install the test extra (pip install -e '.[test]' or pydoclint>=0.12)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)


def _pydoclint(paths: list[Path]) -> list[str]:
    """Findings of pydoclint (pyproject options) on ``paths``, one ``path:line: DOCnnn: message`` line each."""
    if not paths:
        return []
    args = ["--config", str(PYPROJECT), "--show-filenames-in-every-violation-message", "true"]
    names = [str(p.relative_to(REPO_ROOT)) if p.is_relative_to(REPO_ROOT) else str(p) for p in paths]
    out = subprocess.run([sys.executable, "-c", "from pydoclint.main import main; main()", *args, *names],
                         capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
    findings = []
    for line in (out.stdout + out.stderr).splitlines():  # pydoclint writes its findings to stderr
        m = _FINDING.match(line.strip())
        if m is None or m["code"] in DROPPED_CODES or _DUNDER.search(m["msg"]):
            continue
        findings.append(line.strip())
    if out.returncode not in (0, 1) or (out.returncode == 1 and "DOC" not in out.stderr + out.stdout):
        findings.append(f"pydoclint exited {out.returncode}: {out.stderr.strip()}")
    return findings


def _checked_findings() -> list[str]:
    paths = [REPO_ROOT / p for p in CHECKED]
    missing = [p for p in paths if not p.exists()]
    assert not missing, f"listed in CHECKED but not found: {missing}"
    files = _python_files(paths)
    with ThreadPoolExecutor(2) as pool:  # two processes at once, each on half of the files
        runs = [pool.submit(_pydoclint, files[i::2]) for i in range(2)]
        return [f for run in runs for f in run.result()]


def test_functions_document_their_parameters_and_returns() -> None:
    _require_pydoclint()
    findings = _checked_findings()
    assert not findings, f"{len(findings)} docstring findings (pydoclint):\n" + "\n".join(findings)


_UNDOCUMENTED = '''
import numpy as np


def positions(points_mm: np.ndarray, step_mm: float) -> np.ndarray:
    """Resample a curve.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
    """
    return points_mm


def one_liner(points_mm: np.ndarray) -> np.ndarray:
    """Return the points."""
    return points_mm


def documented(points_mm: np.ndarray) -> np.ndarray:
    """Return the points.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS

    Returns
    -------
    (n, 3) float, mm, LPS
    """
    return points_mm


class Box:
    """A box."""

    def __len__(self) -> int:
        """Three."""
        return 3

    def _private(self, x: int) -> int:
        return x
'''


def test_a_missing_parameter_or_returns_section_is_found(tmp_path: Path) -> None:
    _require_pydoclint()
    module = tmp_path / "undocumented.py"
    module.write_text(_UNDOCUMENTED, encoding="utf-8")
    found = {(m["code"], m["msg"].split("`")[1]) for line in _pydoclint([module])
             if (m := _FINDING.match(line)) is not None}
    assert found == {("DOC101", "positions"), ("DOC103", "positions"), ("DOC201", "positions"),
                     ("DOC101", "one_liner"), ("DOC103", "one_liner"), ("DOC201", "one_liner")}


# --- dataclass fields ---------------------------------------------------------------------------------------------

_NAMES = re.compile(r"^(\*{0,2}\w+(?:\s*,\s*\*{0,2}\w+)*)\s*(?::.*)?$")


def _section_names(doc: str, title: str) -> set[str]:
    """Names listed in a numpydoc section (``a, b : type`` gives both)."""
    lines = inspect.cleandoc(doc).splitlines()

    def underlined(j: int) -> bool:
        return j + 1 < len(lines) and lines[j].strip() != "" and set(lines[j + 1].strip()) == {"-"}

    names: set[str] = set()
    for i in range(len(lines)):
        if lines[i].strip() == title and underlined(i):
            for j in range(i + 2, len(lines)):
                if underlined(j):  # the next section
                    break
                if lines[j] and not lines[j][0].isspace():
                    m = _NAMES.match(lines[j])
                    if m is None:
                        break
                    names.update(n.strip().lstrip("*") for n in m[1].split(","))
    return names


def _is_dataclass(node: ast.ClassDef) -> bool:
    for deco in node.decorator_list:
        target = deco.func if isinstance(deco, ast.Call) else deco
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def _init_false(value: ast.expr | None) -> bool:
    """``field(..., init=False)``: not a parameter of the class."""
    return isinstance(value, ast.Call) and any(
        k.arg == "init" and isinstance(k.value, ast.Constant) and k.value.value is False for k in value.keywords)


def _fields(node: ast.ClassDef) -> list[str]:
    """The public fields a dataclass's ``__init__`` takes (no ``ClassVar``, no ``init=False``)."""
    out = []
    for stmt in node.body:
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) \
                and not stmt.target.id.startswith("_") and "ClassVar" not in ast.unparse(stmt.annotation) \
                and not _init_false(stmt.value):
            out.append(stmt.target.id)
    return out


def _dataclass_findings(path: Path) -> Iterator[str]:
    """Public dataclasses of ``path`` whose fields and Parameters section differ."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if not isinstance(node, ast.ClassDef) or node.name.startswith("_") or not _is_dataclass(node):
            continue
        doc = ast.get_docstring(node) or ""
        fields = _fields(node)
        params = _section_names(doc, "Parameters")
        documented = params | _section_names(doc, "Attributes")
        where = f"{path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path}:{node.lineno}"
        if undocumented := [f for f in fields if f not in documented]:
            yield f"{where}: dataclass {node.name}: fields not in its Parameters section: {undocumented}"
        if extra := sorted(params - set(fields)):
            yield f"{where}: dataclass {node.name}: Parameters that are not fields: {extra}"


def _not_checked(path: Path) -> bool:
    return any(path == REPO_ROOT / n or (REPO_ROOT / n) in path.parents for n in NOT_CHECKED)


def _python_files(paths: list[Path]) -> list[Path]:
    """The modules at ``paths``, private ones (``_name.py``, as pydoclint's ``exclude``) and :data:`NOT_CHECKED`
    left out."""
    return sorted(f for p in paths for f in ([p] if p.is_file() else p.rglob("*.py"))
                  if "__pycache__" not in f.parts and (f.name == "__init__.py" or not f.name.startswith("_"))
                  and not _not_checked(f))


def test_dataclasses_document_their_fields() -> None:
    findings = [f for p in CHECKED for path in _python_files([REPO_ROOT / p]) for f in _dataclass_findings(path)]
    assert not findings, f"{len(findings)} dataclass docstring findings:\n" + "\n".join(findings)


def test_an_undocumented_field_is_found(tmp_path: Path) -> None:
    module = tmp_path / "fields.py"
    module.write_text('''
from dataclasses import dataclass, field
from typing import ClassVar


@dataclass(frozen=True)
class Hole:
    """A hole.

    Parameters
    ----------
    name, row : str
        Label and row.
    position_mm : (3,) float, mm, LPS
    radius_mm : float

    Returns
    -------
    nothing
    """

    name: str
    row: str
    position_mm: tuple[float, float, float]
    depth_mm: float = field(default=0.0)
    area_mm2: float = field(init=False, default=0.0)
    KIND: ClassVar[str] = "hole"
    _cache: int = 0


@dataclass
class Prose:
    """A ``name`` told in prose."""

    name: str
''', encoding="utf-8")
    assert [f.split(": ", 1)[1] for f in _dataclass_findings(module)] == [
        "dataclass Hole: fields not in its Parameters section: ['depth_mm']",
        "dataclass Hole: Parameters that are not fields: ['radius_mm']",
        "dataclass Prose: fields not in its Parameters section: ['name']",
    ]


def test_only_the_listed_files_are_left_out() -> None:
    checked = set(_python_files([REPO_ROOT / p for p in CHECKED]))
    assert REPO_ROOT / "planner/dose/implant.py" not in checked
    assert REPO_ROOT / "planner/dose/optimize.py" not in checked
    assert {REPO_ROOT / "planner/dose/tg43.py", REPO_ROOT / "planner/dose/coverage.py",
            REPO_ROOT / "planner/case/search.py", REPO_ROOT / "imaging/solids.py"} <= checked
    every = {f for p in CHECKED for f in (REPO_ROOT / p).rglob("*.py")
             if "__pycache__" not in f.parts and (f.name == "__init__.py" or not f.name.startswith("_"))}
    assert {f.relative_to(REPO_ROOT).as_posix() for f in every - checked} <= {
        "planner/dose/implant.py", "planner/dose/optimize.py"} | {
        f.relative_to(REPO_ROOT).as_posix() for f in every if (REPO_ROOT / "planner/implant") in f.parents}

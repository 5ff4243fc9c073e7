"""The house's sizes: no package module over 800 lines, no function over 100 lines.

The source tree is checked (the files a change edits): the package's top-level modules and its floors. A module
that is too long is split by concept; a function that is too long is split into named steps.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
FLOORS = ("planner", "imaging", "rod_model", "plugins")
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100

#: Files not held to the sizes yet, relative to the repository root.
EXEMPT: tuple[str, ...] = ()


def package_modules(root: Path) -> list[Path]:
    """The package's modules below ``root``: its top-level ``*.py`` and every ``*.py`` of its floors."""
    files = sorted(root.glob("*.py"))
    for floor in FLOORS:
        files += sorted(p for p in (root / floor).rglob("*.py") if "__pycache__" not in p.parts)
    return files


def oversize(root: Path, exempt: tuple[str, ...] = EXEMPT) -> list[str]:
    """Modules over :data:`MAX_MODULE_LINES` lines and functions over :data:`MAX_FUNCTION_LINES` below ``root``."""
    found = []
    for path in package_modules(root):
        name = path.relative_to(root).as_posix()
        if name in exempt:
            continue
        source = path.read_text(encoding="utf-8")
        if (n := len(source.splitlines())) > MAX_MODULE_LINES:
            found.append(f"{name}: {n} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(source, filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{name}:{node.lineno} {node.name}: {length} lines (at most {MAX_FUNCTION_LINES})")
    return found


def test_no_module_or_function_is_too_long() -> None:
    assert len(package_modules(REPO_ROOT)) > 100  # the scan sees the package at all
    found = oversize(REPO_ROOT)
    assert not found, "split by concept:\n" + "\n".join(found)


def test_the_exempt_files_exist() -> None:
    assert all((REPO_ROOT / name).is_file() for name in EXEMPT)


def test_a_long_module_and_a_long_function_are_found(tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))  # def line + 100 lines: 101
    (tmp_path / "planner").mkdir()
    (tmp_path / "planner" / "long_function.py").write_text(f"def work() -> None:\n{body}\n", encoding="utf-8")
    (tmp_path / "planner" / "just_right.py").write_text(
        "def work() -> None:\n" + "\n".join(body.splitlines()[:-1]) + "\n", encoding="utf-8")
    (tmp_path / "imaging").mkdir()
    (tmp_path / "imaging" / "long_module.py").write_text("X = 1\n" * (MAX_MODULE_LINES + 1), encoding="utf-8")
    (tmp_path / "imaging" / "full_module.py").write_text("X = 1\n" * MAX_MODULE_LINES, encoding="utf-8")
    (tmp_path / "big.py").write_text("X = 1\n" * (MAX_MODULE_LINES + 1), encoding="utf-8")
    assert oversize(tmp_path, exempt=("big.py",)) == [
        f"planner/long_function.py:1 work: {MAX_FUNCTION_LINES + 1} lines (at most {MAX_FUNCTION_LINES})",
        f"imaging/long_module.py: {MAX_MODULE_LINES + 1} lines (at most {MAX_MODULE_LINES})",
    ]
    assert len(oversize(tmp_path, exempt=())) == 3  # the exemption is what let big.py pass

"""Plugin registry: Protocol checks per kind, unavailable plugins with reasons, and a third-party
distribution built and pip-installed (offline) in the test that registers a template and an exporter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from reachplan.planner.cli import main
from reachplan.plugins import registry
from reachplan.plugins.errors import PluginError
from reachplan.plugins.exporters.base import ExportPlan

REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class FakeEntryPoint:
    """What the registry uses of an ``importlib.metadata.EntryPoint``: name, value, group, dist, load()."""

    name: str
    value: str
    group: str
    dist: SimpleNamespace

    def load(self) -> Any:
        from importlib.metadata import EntryPoint

        return EntryPoint(self.name, self.value, self.group).load()


@pytest.fixture
def fake_entry_points(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., None]]:
    """Replace the installed entry points by a given list: ``install((kind, name, target, dist), ...)``."""

    def install(*rows: tuple[str, str, str, str]) -> None:
        eps = [FakeEntryPoint(name, target, f"reachplan.{kind}", SimpleNamespace(name=dist))
               for kind, name, target, dist in rows]
        monkeypatch.setattr(registry, "entry_points", lambda group: [e for e in eps if e.group == group])
        registry.refresh()

    yield install
    monkeypatch.undo()
    registry.refresh()


def test_checks_per_kind_and_reasons(fake_entry_points: Callable[..., None]) -> None:
    fake_entry_points(
        ("templates", "syed", "reachplan.plugins.templates:needlefinder_syed_63", "reachplan"),
        ("templates", "needs_arg", "reachplan.plugins.templates:load_template_csv", "thirdparty"),
        ("sources", "gm", "reachplan.plugins.sources:gammamed_plus_hdr", "reachplan"),
        ("sources", "not_a_source", "reachplan.plugins.templates:needlefinder_syed_63", "thirdparty"),
        ("exporters", "dicom_rt", "reachplan.plugins.exporters.dicom_rt:EXPORTER", "reachplan"),
        ("exporters", "device_json", "reachplan.plugins.exporters.device:JSON_EXPORTER", "reachplan"),
        ("exporters", "device_csv", "reachplan.plugins.exporters.device:CSV_EXPORTER", "reachplan"),
        ("exporters", "a_class", "reachplan.plugins.exporters.base:ExportPlan", "thirdparty"),
        ("exporters", "missing", "no_such_module_xyz:EXPORTER", "thirdparty"),
        ("rod_models", "not_a_model", "reachplan.plugins.exporters.dicom_rt:EXPORTER", "thirdparty"),
        ("insertion_models", "len", "builtins:len", "thirdparty"),
    )
    by = {(i.kind, i.name): i for i in registry.info()}
    assert len(by) == 11
    ok = {k for k, i in by.items() if i.available}
    assert ok == {("templates", "syed"), ("sources", "gm"), ("exporters", "dicom_rt"), ("exporters", "device_json"),
                  ("exporters", "device_csv")}
    assert "without arguments" in by["templates", "needs_arg"].reason
    assert "SourceData" in by["sources", "not_a_source"].reason
    assert "Exporter" in by["exporters", "a_class"].reason
    assert "ModuleNotFoundError" in by["exporters", "missing"].reason
    assert "RodModel" in by["rod_models", "not_a_model"].reason
    assert by["insertion_models", "len"].reason
    assert by["exporters", "dicom_rt"].description.startswith("DICOM RT Plan")
    assert registry.names("exporters") == ("device_csv", "device_json", "dicom_rt")
    with pytest.raises(PluginError, match="unavailable: TypeError"):
        registry.get("exporters", "a_class")
    with pytest.raises(PluginError, match="available: device_csv, device_json, dicom_rt"):
        registry.get("exporters", "nope")
    with pytest.raises(PluginError, match="unknown plugin kind"):
        registry.names("beams")


def test_builtin_wins_a_name_clash(fake_entry_points: Callable[..., None]) -> None:
    fake_entry_points(
        ("exporters", "dicom_rt", "reachplan.plugins.exporters.device:JSON_EXPORTER", "aaa-thirdparty"),
        ("exporters", "dicom_rt", "reachplan.plugins.exporters.dicom_rt:EXPORTER", "reachplan"),
    )
    from reachplan.plugins.exporters.dicom_rt import EXPORTER

    assert registry.get("exporters", "dicom_rt") is EXPORTER
    (loser,) = [i for i in registry.info("exporters") if not i.available]
    assert loser.distribution == "aaa-thirdparty" and "reachplan" in loser.reason


def test_set_check_replaces_the_default(fake_entry_points: Callable[..., None],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_CHECKS", {})
    fake_entry_points(("insertion_models", "len", "builtins:len", "thirdparty"))
    assert registry.names("insertion_models") == ()
    registry.set_check("insertion_models", lambda obj: None)
    assert registry.names("insertion_models") == ("len",)


def test_cli_lists_plugins_as_json(fake_entry_points: Callable[..., None], capsys: pytest.CaptureFixture[str]) -> None:
    fake_entry_points(("exporters", "dicom_rt", "reachplan.plugins.exporters.dicom_rt:EXPORTER", "reachplan"),
                      ("exporters", "missing", "no_such_module_xyz:EXPORTER", "thirdparty"))
    assert main(["plugins", "--json", "--kind", "exporters"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(d["name"], d["available"]) for d in doc] == [("dicom_rt", True), ("missing", False)]
    assert main(["plugins"]) == 0
    assert "UNAVAILABLE: ModuleNotFoundError" in capsys.readouterr().out


def test_builtin_exporters_are_declared_in_pyproject() -> None:
    """The built-ins register through entry points; each declared one must pass its Protocol check."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = project.get("entry-points", {}).get("reachplan.exporters", {})
    assert {"dicom_rt", "device_json", "device_csv"} <= set(declared)
    from importlib.metadata import EntryPoint

    from reachplan.plugins.exporters.base import check_exporter

    for name, target in declared.items():
        obj = EntryPoint(name, target, "reachplan.exporters").load()
        check_exporter(obj)
        assert obj.name == name


# --- a third-party distribution, built with its own PEP 517 backend and pip-installed offline ----------------

DEMO_PYPROJECT = """\
[build-system]
requires = []
build-backend = "tiny_backend"
backend-path = ["."]

[project]
name = "reachplan-demo-plugin"
version = "0.1.0"

[project.entry-points."reachplan.templates"]
demo_row = "reachplan_demo_plugin:demo_row"

[project.entry-points."reachplan.exporters"]
demo_txt = "reachplan_demo_plugin:EXPORTER"
"""

DEMO_MODULE = '''\
"""A third-party reachplan plugin: a three-hole template and a plain-text exporter."""
from dataclasses import dataclass
from pathlib import Path

from reachplan.plugins.templates import Hole, Template
from reachplan.plugins.exporters.base import ExportedFile, ExportedFiles, ExportOptions, check_targets, prepare_out_dir


def demo_row():
    """Three holes in a row, 10 mm apart."""
    return Template("demo_row", tuple(Hole(f"R{i}", (10.0 * i, 0.0)) for i in range(3)), source="test")


@dataclass(frozen=True)
class TextExporter:
    name: str = "demo_txt"
    description: str = "hole ids and total dwell time per needle, plain text"

    def export(self, plan, out_dir, options=None):
        path = prepare_out_dir(Path(out_dir)) / "plan.txt"
        check_targets((path,), plan, options or ExportOptions())
        lines = [f"{n.hole_id} {float(n.dwell_times_s.sum()):.1f}" for n in plan.needles]
        path.write_text("\\n".join(lines) + "\\n", encoding="utf-8")
        return ExportedFiles(self.name, (ExportedFile("text", path),))


EXPORTER = TextExporter()
'''

TINY_BACKEND = '''\
"""A minimal PEP 517 backend (wheel only) so the test builds offline with no build dependencies."""
import base64, hashlib, tomllib, zipfile
from pathlib import Path


def get_requires_for_build_wheel(config_settings=None):
    return []


def build_wheel(wheel_directory, config_settings=None, metadata_directory=None):
    project = tomllib.loads(Path("pyproject.toml").read_text())["project"]
    name, version = project["name"], project["version"]
    dist = name.replace("-", "_") + "-" + version
    eps = "".join(f"[{group}]\\n" + "".join(f"{k} = {v}\\n" for k, v in items.items()) + "\\n"
                  for group, items in project.get("entry-points", {}).items())
    files = {
        "reachplan_demo_plugin.py": Path("reachplan_demo_plugin.py").read_bytes(),
        f"{dist}.dist-info/METADATA": f"Metadata-Version: 2.1\\nName: {name}\\nVersion: {version}\\n".encode(),
        f"{dist}.dist-info/WHEEL": (b"Wheel-Version: 1.0\\nGenerator: tiny_backend\\nRoot-Is-Purelib: true\\n"
                                    b"Tag: py3-none-any\\n"),
        f"{dist}.dist-info/entry_points.txt": eps.encode(),
    }
    record = []
    for path, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{path},sha256={digest},{len(data)}")
    record.append(f"{dist}.dist-info/RECORD,,")
    wheel = f"{dist}-py3-none-any.whl"
    with zipfile.ZipFile(Path(wheel_directory) / wheel, "w") as zf:
        for path, data in files.items():
            zf.writestr(path, data)
        zf.writestr(f"{dist}.dist-info/RECORD", "\\n".join(record) + "\\n")
    return wheel
'''


@pytest.fixture(scope="module")
def demo_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build the demo distribution and ``pip install --target`` it (no network, no index, no deps)."""
    src = tmp_path_factory.mktemp("demo_src")
    (src / "pyproject.toml").write_text(DEMO_PYPROJECT, encoding="utf-8")
    (src / "reachplan_demo_plugin.py").write_text(DEMO_MODULE, encoding="utf-8")
    (src / "tiny_backend.py").write_text(textwrap.dedent(TINY_BACKEND), encoding="utf-8")
    site = tmp_path_factory.mktemp("demo_site")
    env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1", "PIP_NO_INPUT": "1"}
    cmd = [sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index",
           "--target", str(site), str(src)]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert list(site.glob("reachplan_demo_plugin-0.1.0.dist-info/entry_points.txt"))
    return site


@pytest.mark.slow
def test_third_party_distribution_is_listed_by_the_cli(demo_site: Path) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(demo_site), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from reachplan.planner.cli import main; sys.exit(main(['plugins', '--json']))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    doc = {(d["kind"], d["name"]): d for d in json.loads(done.stdout)}
    for key in (("templates", "demo_row"), ("exporters", "demo_txt")):
        assert doc[key]["available"], doc[key]
        assert doc[key]["distribution"] == "reachplan-demo-plugin"
    assert doc["templates", "needlefinder_syed_63"]["available"]  # the built-ins are still there


@pytest.mark.slow
def test_third_party_plugins_work(demo_site: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                  make_plan: Callable[..., ExportPlan]) -> None:
    from reachplan.plugins.templates import Template

    try:
        with monkeypatch.context() as m:
            m.syspath_prepend(str(demo_site))
            registry.refresh()
            template = registry.get("templates", "demo_row")()
            assert isinstance(template, Template) and [h.hole_id for h in template.holes] == ["R0", "R1", "R2"]
            exporter = registry.get("exporters", "demo_txt")
            plan = make_plan()
            out = exporter.export(plan, tmp_path)
            lines = out.path("text").read_text(encoding="utf-8").split()
            assert lines[0::2] == [n.hole_id for n in plan.needles]
            assert [float(x) for x in lines[1::2]] == pytest.approx([float(n.dwell_times_s.sum())
                                                                     for n in plan.needles], abs=0.05)
    finally:
        sys.modules.pop("reachplan_demo_plugin", None)
        registry.refresh()
    assert "demo_row" not in registry.names("templates")

"""The first run's background compile (reachplan.planner.cli.kernels), each case in a fresh interpreter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# one rod solve after start(): the solve must load the kernel the child compiled, not compile it again
SCRIPT = """
import json, sys
from reachplan.planner.cli import kernels
kernels.BACKGROUND = ("rod",)  # the dose group goes the same way; the rod alone keeps the test short
was_cold = kernels.cold("rod")
started = kernels.start(quiet=False)
from reachplan.plugins import registry
from reachplan.rod_model import _kernel
from reachplan.rod_model.design import preset
d = preset("15ga-30j-tip")
path = registry.get("rod_models", "two_tube_cosserat").solve(d, d.loads(5.0))
print(json.dumps({"was_cold": was_cold, "started": started, "cold_after": kernels.cold("rod"),
                  "tip_mm": path.positions_mm[-1].tolist(),
                  "compiled_here": sum(_kernel.shoot.stats.cache_misses.values()),
                  "loaded": sum(_kernel.shoot.stats.cache_hits.values())}))
"""


def _run(cache: Path) -> tuple[dict[str, object], str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("NUMBA_DISABLE_JIT", None)
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True,
                          timeout=600)
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


@pytest.mark.slow
def test_a_cold_cache_is_compiled_by_the_child_and_loaded_by_the_main_process(tmp_path: Path) -> None:
    first, err = _run(tmp_path / "cache")
    assert first["was_cold"] and first["started"]
    assert "compiling the numerical kernels once" in err and "in the background" in err
    assert first["compiled_here"] == 0 and first["loaded"] == 1  # waited for the child, then loaded its code
    assert not first["cold_after"]
    second, err = _run(tmp_path / "cache")
    assert not second["was_cold"] and not second["started"] and "compiling" not in err
    assert second["compiled_here"] == 0 and second["loaded"] == 1
    assert second["tip_mm"] == first["tip_mm"]


def test_a_warm_cache_starts_nothing(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.planner.cli import kernels

    monkeypatch.setattr(kernels, "_child", None)
    monkeypatch.setattr(kernels, "cold", lambda group: False)
    assert not kernels.start(quiet=False)
    assert kernels._child is None
    assert capsys.readouterr().err == ""

"""The first run's background compile (reachplan.planner.kernels), each case in a fresh interpreter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# one rod solve and the dose kernels after start(): each must load the kernel the child compiled, not compile it
# again; the second run (the same cache) finds every background group cached and starts nothing
SCRIPT = """
import json, sys
from reachplan.planner import kernels
was_cold = kernels.cold("rod") or kernels.cold("dose")
started = kernels.start(quiet=False)
from reachplan.plugins import registry
from reachplan.rod_model import _kernel
from reachplan.rod_model.design import preset
from reachplan.planner.dose import _tg43_numba
d = preset("15ga-30j-tip")
path = registry.get("rod_models", "two_tube_cosserat").solve(d, d.loads(5.0))
kernels.warm_up(["dose"])
dose = [_tg43_numba.grid_dose, _tg43_numba.pair_matrix, _tg43_numba.pair_dose]
print(json.dumps({"was_cold": was_cold, "started": started,
                  "cold_after": kernels.cold("rod") or kernels.cold("dose"),
                  "tip_mm": path.positions_mm[-1].tolist(),
                  "compiled_here": sum(sum(k.stats.cache_misses.values()) for k in [_kernel.shoot, *dose]),
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


def test_a_kernel_inlined_into_its_callers_does_not_make_its_group_cold() -> None:
    from reachplan.planner import kernels
    from reachplan.planner.dose import _tg43_numba

    inlined = [d for d in kernels._dispatchers("dose") if kernels._inlined(d)]
    assert _tg43_numba._pair in inlined and _tg43_numba.grid_dose not in inlined  # _pair has no cache file of its own
    assert all(kernels._inlined(d) == (d.targetoptions.get("inline") == "always")
               for g in kernels.GROUPS for d in kernels._dispatchers(g))


def test_a_warm_cache_starts_nothing(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.planner import kernels

    monkeypatch.setattr(kernels, "_child", None)
    monkeypatch.setattr(kernels, "cold", lambda group: False)
    assert not kernels.start(quiet=False)
    assert kernels._child is None
    assert capsys.readouterr().err == ""


def test_the_program_and_the_wait_without_a_child(monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.planner import kernels

    monkeypatch.setattr(kernels, "_child", None)
    assert kernels.waited_s() == 0.0
    assert kernels.main(["warm", "no-such-group"]) == 2 and kernels.main([]) == 2
    assert "usage: python -m reachplan.planner.kernels warm" in capsys.readouterr().err
    with pytest.raises(ValueError, match="unknown kernel group"):
        kernels.warm_up(["no-such-group"])

"""The dwell-optimiser seam: a new optimiser is one file plus its entry point, chosen by name in ImplantSettings;
an unknown name is a typed error that lists the available ones."""

from __future__ import annotations

import textwrap
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import ImplantArm
from reachplan.planner.implant.candidates import Channel, needle_candidates
from reachplan.planner.implant.optimiser import DwellOptimiser, resolve
from reachplan.planner.implant.plan import plan_implant
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.lookup import get_source
from reachplan.plugins import registry
from reachplan.plugins.errors import PluginError

SK = 40700.0
LOOSE = Aims(oar_d2cc_eqd2_gy=(("rectum", 400.0),))
#: no dwell-share limit: a uniform loading of a few dwells would be clipped by it; the neighbour ratio instead of
#: the smoothness term (the built-in's loading is then modulated, not a plateau like the stand-in's); nominal planning
SETTINGS = ImplantSettings(max_needles=3, max_dwell_share=1.0, extra_after_aims=0, smoothness_weight=0.0,
                           neighbour_ratio=2.0, shift_mm=0.0, v200_max_pct=None)

#: The whole of a new optimiser: one module (its registration is the entry point written next to it).
UNIFORM = textwrap.dedent('''
    """A stand-in dwell optimiser: one time on every dwell of the cheapest needles, scaled to the prescription."""

    import numpy as np

    from reachplan.planner.implant.optimiser import DwellSolution


    class Uniform:
        name = "uniform"
        description = "uniform loading of the cheapest needles"

        def optimise(self, problem, *, budget=None, limit_factor=None, start=()):
            on = np.ones(problem.n_columns, dtype=bool)
            chosen = ()
            if problem.needles is not None:
                order = np.argsort(problem.needles.cost, kind="stable")
                chosen = tuple(sorted(int(i) for i in order[:len(order) if budget is None else budget]))
                used = {problem.needles.channels[i] for i in chosen}
                on = np.array([c not in problem.needles.channels or c in used for c in problem.channel])
            rate = problem.target_rates[:, on].sum(axis=1)  # Gy per fraction per second on every loaded dwell
            t = float(np.median(problem.target_dose_gy / np.maximum(rate, 1e-30)))
            times = np.where(on, t, 0.0)
            return DwellSolution(times, f"uniform: {t:.6g} s on {int(on.sum())} dwells", float(t * on.sum()), None,
                                 chosen)


    UNIFORM = Uniform()
''')


def _install(folder: Path, monkeypatch: pytest.MonkeyPatch, module: str, source: str, entry: str) -> None:
    """Install ``module`` (its ``source``) as a distribution on the path that registers ``entry`` as an optimiser."""
    (folder / f"{module}.py").write_text(source, encoding="utf-8")
    info = folder / f"{module}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 0.1\n", encoding="utf-8")
    (info / "entry_points.txt").write_text(f"[reachplan.optimisers]\n{entry}\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(folder))
    registry.refresh()


@pytest.fixture
def uniform_installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Install the stand-in as a distribution on the path: its module and a dist-info with its entry point."""
    _install(tmp_path, monkeypatch, "uniform_optimiser", UNIFORM, "uniform = uniform_optimiser:UNIFORM")
    yield
    monkeypatch.undo()
    registry.refresh()


@pytest.fixture(scope="module")
def case() -> tuple[tuple[Channel, ...], PlanningStructures, Tg43Kernel]:
    """A 9 mm sphere 50 mm deep, an organ to one side; straight candidates from holes every 5 mm."""
    h, lo, n = 2.0, np.array([-20.0, -20.0, 0.0]), (20, 20, 40)
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = lo + h / 2
    grid = Grid((n[2], n[1], n[0]), aff)
    k, j, i = np.meshgrid(np.arange(n[2]), np.arange(n[1]), np.arange(n[0]), indexing="ij")
    p = grid.to_patient(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)).reshape(n[2], n[1], n[0], 3)
    target = Structure("HR-CTV", np.linalg.norm(p - np.array([0.0, 0.0, 50.0]), axis=-1) <= 9.0)
    organ = Structure("Rectum", np.all((p >= [-20.0, 14.0, 20.0]) & (p <= [20.0, 20.0, 70.0]), axis=-1))
    planning = PlanningStructures(grid, target, (organ,))
    xy = np.array([(x, y) for x in np.arange(-10.0, 11.0, 5.0) for y in np.arange(-10.0, 11.0, 5.0)])
    ids = [f"x{x:+.0f}y{y:+.0f}" for x, y in xy]
    cands = needle_candidates(ids, xy, np.hypot(xy[:, 0], xy[:, 1]), np.eye(4), planning, (), 0.915, SETTINGS)
    assert len(cands) >= 4
    return cands, planning, Tg43Kernel(get_source("gammamed_plus_hdr"))


def _plan(case: tuple[tuple[Channel, ...], PlanningStructures, Tg43Kernel], optimiser: str) -> ImplantArm:
    cands, planning, kernel = case
    return plan_implant("straight", cands, planning, kernel, SK, LOOSE, replace(SETTINGS, optimiser=optimiser))


def test_the_builtin_optimiser_is_registered_by_name() -> None:
    lp = resolve("lp")
    assert isinstance(lp, DwellOptimiser) and lp.name == "lp"
    assert "lp" in registry.names("optimisers")


def test_a_new_optimiser_is_one_file_and_its_entry_point(
        uniform_installed: None, case: tuple[tuple[Channel, ...], PlanningStructures, Tg43Kernel]) -> None:
    assert "uniform" in registry.names("optimisers")
    arm = _plan(case, "uniform")
    assert arm.plan is not None and arm.budgets
    assert arm.selection["model"] == "uniform loading of the cheapest needles"
    for b in arm.budgets:  # every budget was selected by the stand-in: its status, its (absent) bound
        assert b.status.startswith("uniform: ") and b.dual_bound is None and b.mip_gap is None
    # its selection: the cheapest needles (cost grows with the hole's distance from the centre)
    first = arm.budgets[0]
    assert first.n_needles == 1 and first.selected[0].name == "x+0y+0"
    # its dwell times: the final loading of the chosen channels is uniform too (one time on every dwell)
    times = arm.plan.dwells.times_s
    assert len(times) >= 3 and np.ptp(times) <= 1e-9 * times.max()
    assert "uniform: " in arm.plan.mip_status
    # the built-in optimiser on the same case modulates its dwells and reports its LP bound
    lp = _plan(case, "lp")
    assert lp.plan is not None and np.ptp(lp.plan.dwells.times_s) > 1e-3 * lp.plan.dwells.times_s.max()
    assert all(b.dual_bound is not None for b in lp.budgets)
    assert lp.selection["model"] != arm.selection["model"]


def test_an_unknown_optimiser_is_a_typed_error_naming_the_available_ones(
        case: tuple[tuple[Channel, ...], PlanningStructures, Tg43Kernel]) -> None:
    with pytest.raises(PluginError, match=r"no optimisers plugin named 'simplex'; available: .*\blp\b"):
        _plan(case, "simplex")


def test_an_object_without_optimise_is_listed_unavailable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _install(tmp_path, monkeypatch, "broken_optimiser", "class Broken:\n    name = 'broken'\n\n\nBROKEN = Broken()\n",
             "broken = broken_optimiser:BROKEN")
    try:
        row = next(i for i in registry.info("optimisers") if i.name == "broken")
        assert not row.available and "callable 'optimise'" in row.reason
        with pytest.raises(PluginError, match="unavailable"):
            resolve("broken")
    finally:
        monkeypatch.undo()
        registry.refresh()

"""The report's implant section: both arms' Pareto curves and DVHs, read back from the figures' data."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import cumulative_dvh
from reachplan.planner.implant.arms import ImplantArm, ParetoPoint
from reachplan.planner.report import charts

ORGANS = ("Bladder", "Rectum", "Sigmoid")


def _arm(name: str, pareto: list[tuple[int, float, bool]], chosen: int | None, seed: int) -> ImplantArm:
    """An arm with a Pareto curve and, when ``chosen`` is a needle count, a plan at that point with DVHs."""
    rng = np.random.default_rng(seed)
    points = tuple(ParetoPoint(n, d90, met) for n, d90, met in pareto)
    plan = None
    if chosen is not None:
        d90 = next(p.hrctv_d90_eqd2_gy for p in points if p.n_needles == chosen) + 0.4  # finer final metrics
        dvhs = (("HR-CTV", cumulative_dvh(rng.gamma(9.0, 1.0, 4000), 0.01)),
                *((o, cumulative_dvh(rng.exponential(1.5, 3000), 0.03)) for o in ORGANS))
        plan = SimpleNamespace(n_needles=chosen, target=SimpleNamespace(d90_eqd2_gy=d90), dvhs=dvhs)
    return ImplantArm(name, 40, points, plan, 1.0)  # type: ignore[arg-type]


@pytest.fixture
def arms() -> tuple[ImplantArm, ImplantArm]:
    straight = _arm("straight", [(0, 60.0, False), (1, 74.0, False), (2, 79.5, False), (3, 81.0, False)], 3, 1)
    steered = _arm("steered", [(0, 60.0, False), (1, 78.0, False), (2, 86.0, True), (3, 88.5, True),
                               (4, 89.0, True)], 2, 2)
    return straight, steered


def _lines(fig: object) -> dict[str, object]:
    ax = fig.axes[0]  # type: ignore[attr-defined]
    return {ln.get_gid(): ln for ln in ax.lines if ln.get_gid()}


def test_pareto_figure_has_both_curves_the_aims_and_each_chosen_plan(arms: tuple[ImplantArm, ImplantArm]) -> None:
    lines = _lines(charts.pareto_figure(arms, Aims().target_d90_eqd2_gy))
    for arm in arms:
        xy = lines[f"pareto:{arm.name}"].get_xydata()  # type: ignore[attr-defined]
        assert len(xy) == len(arm.pareto)
        assert np.allclose(xy, [(p.n_needles, p.hrctv_d90_eqd2_gy) for p in arm.pareto])
        met = lines[f"met:{arm.name}"].get_xydata()  # type: ignore[attr-defined]
        unmet = lines[f"unmet:{arm.name}"].get_xydata()  # type: ignore[attr-defined]
        assert len(met) == sum(p.aims_met for p in arm.pareto) and len(unmet) == sum(not p.aims_met for p in arm.pareto)
        assert lines[f"unmet:{arm.name}"].get_markerfacecolor() == "none"  # type: ignore[attr-defined]
        assert lines[f"met:{arm.name}"].get_markerfacecolor() != "none"  # type: ignore[attr-defined]
        chosen = lines[f"chosen:{arm.name}"].get_xydata()  # type: ignore[attr-defined]
        assert arm.plan is not None
        assert np.allclose(chosen, [(arm.plan.n_needles, arm.plan.target.d90_eqd2_gy)])
    aim = lines["aim:D90"].get_ydata()  # type: ignore[attr-defined]
    assert np.allclose(aim, Aims().target_d90_eqd2_gy)
    assert lines["pareto:straight"].get_linestyle() != lines["pareto:steered"].get_linestyle()  # type: ignore[attr-defined]


def test_an_arm_without_a_plan_has_its_curve_and_no_circle(arms: tuple[ImplantArm, ImplantArm]) -> None:
    empty = _arm("straight", [(0, 60.0, False)], None, 3)
    lines = _lines(charts.pareto_figure((empty, arms[1]), 85.0))
    assert "chosen:straight" not in lines and "chosen:steered" in lines
    assert len(lines["pareto:straight"].get_xydata()) == 1  # type: ignore[attr-defined]
    dvh = _lines(charts.implant_dvh_figure((empty, arms[1]), Aims()))
    assert not any(str(g).startswith("dvh:straight:") for g in dvh)


def test_implant_dvhs_both_arms_by_line_style_monotone_with_the_aims(arms: tuple[ImplantArm, ImplantArm]) -> None:
    aims = Aims()
    lines = _lines(charts.implant_dvh_figure(arms, aims))
    for arm in arms:
        assert arm.plan is not None
        for name, dvh in arm.plan.dvhs:
            ln = lines[f"dvh:{arm.name}:{name}"]
            x, v = ln.get_xdata(), ln.get_ydata()  # type: ignore[attr-defined]
            assert len(x) == len(dvh.dose_gy) and np.all(np.diff(x) > 0)
            assert np.all(np.diff(v) <= 0), f"{arm.name} {name}: a cumulative DVH never rises"
            assert v[0] == pytest.approx(dvh.volume_cc[0])  # the whole structure at 0 Gy
            assert ln.get_linestyle() == {"straight": "--", "steered": "-"}[arm.name]  # type: ignore[attr-defined]
        assert lines[f"dvh:{arm.name}:HR-CTV"].get_linewidth() > lines[f"dvh:{arm.name}:Rectum"].get_linewidth()  # type: ignore[attr-defined]
    assert np.allclose(lines["aim:D90"].get_xdata(), aims.prescription_gy)  # type: ignore[attr-defined]
    for organ in ("Bladder", "Rectum", "Sigmoid"):
        assert np.allclose(lines[f"limit:{organ}"].get_xydata(), [(aims.oar_gy(organ), 2.0)])  # type: ignore[attr-defined]
    assert sum(str(g).startswith("aim:") for g in lines) == 1  # the marks once, not per arm

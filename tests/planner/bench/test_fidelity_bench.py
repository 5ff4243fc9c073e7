"""``reachplan bench fidelity``: the ranking-fidelity numbers on planted rankings, against a hand count."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from reachplan.planner.bench.fidelity import compare
from reachplan.planner.steering.candidates import Candidate
from reachplan.planner.steering.insertion import STRAIGHT


def _cand(hole: str, reach_mm: float = 0.5, clearance_mm: float = 3.0, feasible: bool = True) -> Candidate:
    return Candidate("T", hole, 10.0, reach_mm, clearance_mm, "Bladder", 90.0, False, 0.0, STRAIGHT,
                     collides=not feasible, reaches=True, reason="", path_mm=np.zeros((2, 3)))


def _tau_by_hand(a: list[int], b: list[int]) -> float:
    """Kendall's tau-b of two rank lists, pairs counted directly."""
    conc = disc = ta = tb = 0
    for i, j in itertools.combinations(range(len(a)), 2):
        da, db = np.sign(a[i] - a[j]), np.sign(b[i] - b[j])
        if da == 0 and db == 0:
            continue
        if da == 0:
            ta += 1
        elif db == 0:
            tb += 1
        elif da == db:
            conc += 1
        else:
            disc += 1
    return (conc - disc) / np.sqrt((conc + disc + ta) * (conc + disc + tb))


def test_identical_rankings_agree_fully() -> None:
    ranked = tuple(_cand(h) for h in "ABCD")
    got = compare({"T": ranked}, {"T": ranked})
    assert got == {"top1_same": 1.0, "kendall_tau": 1.0, "worst_tau": 1.0, "worst_reach_err_mm": 0.0,
                   "worst_clearance_err_mm": 0.0}


def test_a_swap_an_extra_candidate_and_changed_numbers_are_counted() -> None:
    ref = (_cand("A", clearance_mm=7.0), *(_cand(h) for h in "BCD"))
    # the policy holds an extra feasible candidate X first (the reference found it infeasible), swaps C and D,
    # and has B's reach 0.7 mm and clearance 2 mm off; clearances beyond the 6 mm cap do not count
    other = (_cand("X"), _cand("A", clearance_mm=9.0), _cand("B", reach_mm=1.2, clearance_mm=5.0), _cand("D"),
             _cand("C"))
    got = compare({"T": ref}, {"T": other})
    assert got["top1_same"] == 0.0
    # the union A, B, C, D, X: ranks in the reference (X not feasible there: last) and in the policy
    assert got["kendall_tau"] == pytest.approx(_tau_by_hand([0, 1, 2, 3, 4], [1, 2, 4, 3, 0]))
    assert got["kendall_tau"] < 0.5
    assert got["worst_reach_err_mm"] == pytest.approx(0.7) and got["worst_clearance_err_mm"] == pytest.approx(2.0)

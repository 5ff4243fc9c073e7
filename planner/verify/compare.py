"""Needles found against another set of centre lines: the truth of a synthetic image, or the plan.

Against the truth: every needle matched by hole; the tip error is the distance between the tips, the shaft
distance the mean (and largest) distance of the found centre line's points (about 1 mm apart, template plane to
tip) from the true centre line. Against the plan (issue #32, item 3): per needle the tip error, the largest
lateral deviation (distance of the found points from the planned line, over the depths both reach) and the depth
error (the tip's offset along the planned tip direction: positive when the needle went deeper).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.planner.verify.find import FoundNeedle, distances_to_line


@dataclass(frozen=True)
class NeedleError:
    """One needle found against its reference (the truth, or the plan).

    Parameters
    ----------
    hole_id : str
        The hole.
    tip_mm : float, mm
        Distance between the tips.
    shaft_mean_mm, shaft_max_mm : float, mm
        Mean and largest distance of the found points from the reference line.
    depth_mm : float, mm
        The found tip's offset along the reference's tip direction (+: deeper).
    """

    hole_id: str
    tip_mm: float
    shaft_mean_mm: float
    shaft_max_mm: float
    depth_mm: float

    def to_json(self) -> dict[str, object]:
        """Return the numbers rounded to 0.01 mm.

        Returns
        -------
        dict of str to object
            ``hole_id``, ``tip_error_mm``, ``shaft_mean_mm``, ``shaft_max_mm``, ``depth_error_mm``.
        """
        return {"hole_id": self.hole_id, "tip_error_mm": round(self.tip_mm, 2),
                "shaft_mean_mm": round(self.shaft_mean_mm, 2), "shaft_max_mm": round(self.shaft_max_mm, 2),
                "depth_error_mm": round(self.depth_mm, 2)}


def needle_error(found: FoundNeedle, reference_mm: np.ndarray) -> NeedleError:
    """Compare one needle with its reference centre line.

    Parameters
    ----------
    found : FoundNeedle
        The needle found.
    reference_mm : (m, 3) float, mm, LPS
        The reference centre line, hole to tip.

    Returns
    -------
    NeedleError
        Tip error, shaft distances and depth error (module docstring).
    """
    ref = np.asarray(reference_mm, dtype=float)
    back = ref[max(0, len(ref) - 5)]
    t = ref[-1] - back
    t = t / max(float(np.linalg.norm(t)), 1e-12)
    depth = float((found.tip_mm - ref[-1]) @ t)
    beyond = (found.points_mm - ref[-1]) @ t > 0  # found points past the reference's tip: the depth error's
    d = distances_to_line(found.points_mm[~beyond] if (~beyond).any() else found.points_mm, ref)
    return NeedleError(found.hole_id, float(np.linalg.norm(found.tip_mm - ref[-1])), float(d.mean()),
                       float(d.max()), depth)


@dataclass(frozen=True)
class Matching:
    """Needles found against a reference set, matched by hole.

    Parameters
    ----------
    errors : tuple of NeedleError
        One per needle found whose hole the reference holds.
    missed : tuple of str
        Reference holes with no needle found.
    false : tuple of str
        Needles found through holes the reference does not hold.
    """

    errors: tuple[NeedleError, ...]
    missed: tuple[str, ...]
    false: tuple[str, ...]

    def summary(self) -> dict[str, object]:
        """Return the means and counts.

        Returns
        -------
        dict of str to object
            ``found``, ``missed``, ``false`` counts and holes; mean and largest tip error and shaft distance (mm).
        """
        tips = [e.tip_mm for e in self.errors]
        shafts = [e.shaft_mean_mm for e in self.errors]
        return {
            "found": len(self.errors), "missed": list(self.missed), "false": list(self.false),
            "mean_tip_error_mm": round(float(np.mean(tips)), 3) if tips else None,
            "max_tip_error_mm": round(float(np.max(tips)), 3) if tips else None,
            "mean_shaft_distance_mm": round(float(np.mean(shafts)), 3) if shafts else None,
            "max_shaft_distance_mm": round(float(max(e.shaft_max_mm for e in self.errors)), 3) if shafts else None,
        }


def match(found: Sequence[FoundNeedle], reference: Mapping[str, np.ndarray]) -> Matching:
    """Match needles found with reference centre lines by hole and measure each.

    Parameters
    ----------
    found : sequence of FoundNeedle
        The needles found.
    reference : mapping of str to (m, 3) float, mm, LPS
        Hole id to the reference centre line (hole to tip).

    Returns
    -------
    Matching
        Per needle errors, the holes missed and the needles found where the reference has none.
    """
    errors = tuple(needle_error(f, reference[f.hole_id]) for f in found if f.hole_id in reference)
    got = {f.hole_id for f in found}
    return Matching(errors, tuple(h for h in reference if h not in got),
                    tuple(f.hole_id for f in found if f.hole_id not in reference))

"""The hand-off: one "insert these" list of the delivered implant, as plain data.

The planner builds it once from the delivered plan (``reachplan.planner.handoff``); the terminal's first screen, the
report's first section and the bedside device instructions (:mod:`reachplan.plugins.exporters.device`) all print its
:meth:`InsertList.rows`, so a needle has the same name, depth and margins everywhere. Per needle: the template hole,
the needle and stylet, the insertion depth, the tension schedule in words (the bending direction in patient terms,
from the template pose), the tension reserve, the worst-case reach and clearance under the perturbations with the
perturbation that causes each (as margins to the tolerance, not a flag), and check depths with the expected tip
position for imaging during the insertion. Applicator channels (the tandem) carry their length and curvature.

Nothing here is computed from a patient: the values come in; the only logic is formatting. No patient identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The research-use statement at the top of the terminal summary, the report and the device page.
RESEARCH_USE = ("RESEARCH USE ONLY: a pre-plan computed by reachplan for research, not a treatment plan. The "
                "steering predictions are models (tissue stiffness assumed); every implant must be planned, "
                "imaged and checked in the clinic's own treatment-planning system.")

#: Columns of :meth:`InsertList.rows` (units in the headers).
COLUMNS = ("ch", "hole", "needle", "stylet", "depth (mm)", "peak / limit (N)", "reserve (N)",
           "reach margin (mm)", "clearance margin (mm)")
#: The columns of :data:`COLUMNS` that hold numbers (right-aligned): channel, depth, reserve.
NUMERIC_COLUMNS = (0, 4, 6)


def mm(v: float) -> str:
    """Return a length with one decimal, never ``-0.0``.

    Parameters
    ----------
    v : float, mm
        The value.

    Returns
    -------
    str
        E.g. ``"12.3"``; a value that rounds to zero is ``"0.0"``.
    """
    text = f"{v:.1f}"
    return "0.0" if text == "-0.0" else text


def _r(x: float | None, nd: int = 2) -> float | None:
    """Return a finite number rounded for JSON (-0.0 made 0.0), None otherwise."""
    return None if x is None or not np.isfinite(x) else float(round(float(x), nd)) + 0.0


@dataclass(frozen=True)
class CheckDepth:
    """Where the tip should be at one insertion depth, for imaging during the insertion.

    Parameters
    ----------
    depth_mm : float, mm
        Insertion depth beyond the template plane (arc length along the needle).
    tip_mm : (float, float, float), mm, LPS
        The expected tip position at that depth (the shaft follows the track its tip cut).
    offset_mm : float, mm
        Distance of the expected tip from the hole's straight line (the template axis through the hole).
    toward : str
        That offset's direction in patient terms (e.g. ``"anterior and the patient's left"``); "" for none.
    what : str
        Why this depth (e.g. ``"the pull starts"``, ``"full tension"``, ``"tip"``).
    """

    depth_mm: float
    tip_mm: tuple[float, float, float]
    offset_mm: float
    toward: str
    what: str

    def text(self) -> str:
        """Return the check in words, e.g. ``80 mm (full tension): 3.1 mm anterior of the hole's line``.

        Returns
        -------
        str
            Depth, why, and the offset (or "on the hole's line").
        """
        where = (f"{self.offset_mm:.1f} mm {self.toward} of the hole's line" if self.toward
                 else "on the hole's line")
        lps = ", ".join(mm(v) for v in self.tip_mm)
        return f"{self.depth_mm:.0f} mm ({self.what}): tip {where}, at ({lps}) mm LPS"

    def to_json(self) -> dict[str, object]:
        """Return the check as JSON-ready values (mm, LPS).

        Returns
        -------
        dict
            ``depth_mm``, ``tip_mm``, ``offset_mm``, ``toward``, ``what``.
        """
        return {"depth_mm": _r(self.depth_mm), "tip_mm": [_r(v) for v in self.tip_mm],
                "offset_mm": _r(self.offset_mm), "toward": self.toward, "what": self.what}


@dataclass(frozen=True)
class Margin:
    """A robustness margin: how far the worst case stays inside (+) or goes over (-) its limit, and why.

    Parameters
    ----------
    worst_mm : float, mm
        The worst case: the largest tip displacement from the planned tip (reach), or the smallest clearance to an
        organ at risk (clearance; 0 when one collides).
    limit_mm : float, mm
        The reach tolerance, or the clearance margin.
    margin_mm : float, mm
        ``limit - worst`` for reach, ``worst - limit`` for clearance: positive on the safe side.
    cause : str
        The perturbation that gives the worst case (``"nominal"`` when none is worse than the plan).
    organ : str
        The organ at the smallest clearance ("" for reach).
    """

    worst_mm: float
    limit_mm: float
    margin_mm: float
    cause: str
    organ: str = ""

    def text(self) -> str:
        """Return the margin as a short cell, e.g. ``-1.3 (entry tilt +2 deg about template x)``.

        Returns
        -------
        str
            Signed margin (mm), the organ when there is one, and the cause.
        """
        if not np.isfinite(self.margin_mm):
            return "- (no organ)"
        organ = f" {self.organ}" if self.organ else ""
        return f"{self.margin_mm:+.1f}{organ} ({self.cause})"

    def to_json(self) -> dict[str, object]:
        """Return the margin as JSON-ready values (mm).

        Returns
        -------
        dict
            ``worst_mm``, ``limit_mm``, ``margin_mm``, ``cause``, ``organ``.
        """
        return {"worst_mm": _r(self.worst_mm), "limit_mm": _r(self.limit_mm), "margin_mm": _r(self.margin_mm),
                "cause": self.cause, "organ": self.organ or None}


@dataclass(frozen=True)
class Scenario:
    """One perturbation of a needle's insertion and where it puts the needle.

    Parameters
    ----------
    label : str
        The perturbation (e.g. ``"roll +10 deg"``, ``"entry tilt -2 deg about template y"``; ``"nominal"``).
    reach_mm : float, mm
        The tip's displacement from the planned tip.
    clearance_mm : float, mm
        The smallest clearance to an organ at risk (0 when the needle collides; inf without organs).
    organ : str
        The organ at that clearance ("" without organs).
    """

    label: str
    reach_mm: float
    clearance_mm: float
    organ: str

    def to_json(self) -> dict[str, object]:
        """Return the scenario as JSON-ready values (mm).

        Returns
        -------
        dict
            ``perturbation``, ``reach_mm``, ``clearance_mm`` (None when not finite), ``organ``.
        """
        return {"perturbation": self.label, "reach_mm": _r(self.reach_mm), "clearance_mm": _r(self.clearance_mm),
                "organ": self.organ or None}


@dataclass(frozen=True)
class InsertNeedle:
    """One needle to insert, as the bedside needs it.

    Parameters
    ----------
    channel : int
        Its channel number in the RT Plan (from 1; applicator channels are numbered too).
    hole_id : str
        The template hole.
    kind : str
        ``"steered"`` or ``"straight"``.
    needle : str
        The needle type in words (gauge and outer diameter).
    stylet : str
        The steerable stylet's preset; "" for a straight needle (its plain stylet).
    depth_mm : float, mm
        Insertion depth beyond the template plane (arc length to the tip).
    tension_words : str
        The tension schedule in words, the bending direction in patient terms.
    peak_tension_n : float, N
        The schedule's largest tendon tension (0 for a straight needle).
    tension_limit_n : float or None, N
        The stylet's design limit (None for a straight needle).
    reach : Margin
        Worst tip displacement from the planned tip against the reach tolerance.
    clearance : Margin
        Smallest clearance to an organ at risk against the clearance margin.
    checks : tuple of CheckDepth
        Depths to image at, with the expected tip there (deepest last: the tip).
    model : str
        The model that predicted the path (e.g. ``straight``, ``tissue_rod+two_tube_cosserat``).
    scenarios : tuple of Scenario
        The nominal insertion and every perturbation the margins were taken over, each with its tip displacement
        and clearance.
    steering : tuple of (Margin, Margin) or None
        The reach and clearance margins over the steering errors alone (tension and roll, not the entry tilt that
        every needle shares): what sets a steered needle apart; None for a straight needle.
    """

    channel: int
    hole_id: str
    kind: str
    needle: str
    stylet: str
    depth_mm: float
    tension_words: str
    peak_tension_n: float
    tension_limit_n: float | None
    reach: Margin
    clearance: Margin
    checks: tuple[CheckDepth, ...]
    model: str
    scenarios: tuple[Scenario, ...] = ()
    steering: tuple[Margin, Margin] | None = None

    @property
    def reserve_n(self) -> float | None:
        """The tension left below the stylet's limit, N (None for a straight needle)."""
        return None if self.tension_limit_n is None else self.tension_limit_n - self.peak_tension_n

    def schedule_text(self) -> str:
        """Return the tension schedule in words, with the steering errors' own margins for a steered needle.

        Returns
        -------
        str
            :attr:`tension_words`, then (steered) ``steering errors alone: reach margin ..., clearance margin ...``.
        """
        if self.steering is None:
            return self.tension_words
        reach, clear = self.steering
        return (f"{self.tension_words}. Steering errors alone: reach margin {reach.text()}, clearance margin "
                f"{clear.text()}")

    def cells(self) -> tuple[str, ...]:
        """Return the needle's row of :data:`COLUMNS` as text cells.

        Returns
        -------
        tuple of str
            One cell per column.
        """
        limit = "-" if self.tension_limit_n is None else f"{self.peak_tension_n:.1f} / {self.tension_limit_n:g}"
        reserve = "-" if self.reserve_n is None else f"{self.reserve_n:.1f}"
        return (str(self.channel), self.hole_id, self.kind, self.stylet or "-", f"{self.depth_mm:.1f}", limit,
                reserve, self.reach.text(), self.clearance.text())

    def to_json(self) -> dict[str, object]:
        """Return the needle as JSON-ready values (mm, N, LPS).

        Returns
        -------
        dict
            Every field, ``reserve_n`` added; margins and checks as their own JSON.
        """
        return {"channel": self.channel, "hole_id": self.hole_id, "kind": self.kind, "needle": self.needle,
                "stylet": self.stylet or None, "insertion_depth_mm": _r(self.depth_mm),
                "tension_schedule": self.tension_words, "peak_tension_n": _r(self.peak_tension_n),
                "tension_limit_n": _r(self.tension_limit_n), "tension_reserve_n": _r(self.reserve_n),
                "reach": self.reach.to_json(), "clearance": self.clearance.to_json(),
                "check_depths": [c.to_json() for c in self.checks], "model": self.model,
                "scenarios": [s.to_json() for s in self.scenarios],
                "steering_errors": None if self.steering is None else {
                    "reach": self.steering[0].to_json(), "clearance": self.steering[1].to_json()}}


@dataclass(frozen=True)
class ApplicatorChannel:
    """An intracavitary channel (tandem, ring, ovoid) placed by hand: its length and curvature.

    Parameters
    ----------
    channel : int
        Its channel number in the RT Plan.
    name : str
        The channel's name (e.g. ``Tandem``).
    length_mm : float, mm
        Arc length of the channel's path.
    bend_deg : float, degrees
        Angle between the channel's direction at its entry and at its tip.
    radius_mm : float, mm
        The tightest radius of curvature along the channel (inf when straight).
    toward : str
        The direction the channel turns toward, in patient terms ("" when straight).
    """

    channel: int
    name: str
    length_mm: float
    bend_deg: float
    radius_mm: float
    toward: str

    def text(self) -> str:
        """Return the channel in words: length, bend, radius and direction.

        Returns
        -------
        str
            E.g. ``Tandem (channel 2): 60.0 mm long, bent 30 deg toward anterior (radius 115 mm)``.
        """
        bend = ("straight" if not self.toward else
                f"bent {self.bend_deg:.0f} deg toward {self.toward} (radius {self.radius_mm:.0f} mm)")
        return f"{self.name} (channel {self.channel}): {self.length_mm:.1f} mm long, {bend}"

    def to_json(self) -> dict[str, object]:
        """Return the channel as JSON-ready values.

        Returns
        -------
        dict
            ``channel``, ``name``, ``length_mm``, ``bend_deg``, ``radius_mm`` (None when straight), ``toward``.
        """
        return {"channel": self.channel, "name": self.name, "length_mm": _r(self.length_mm),
                "bend_deg": _r(self.bend_deg, 1), "radius_mm": _r(self.radius_mm, 1), "toward": self.toward}


@dataclass(frozen=True)
class InsertList:
    """The delivered implant's "insert these" list, built once; everything that hands the plan over prints it.

    Parameters
    ----------
    plan : str
        Which plan is delivered (e.g. ``implant, straight + steered``).
    needles : tuple of InsertNeedle
        The template needles to insert, in channel order.
    applicators : tuple of ApplicatorChannel
        The intracavitary channels of the plan.
    perturbations : str
        The perturbation model behind the margins, with its source.
    tension_rule : str
        What to do at the tension limit.
    obstacles : str
        Which ROIs were taken as applicators, and which of them needles must keep off.
    statement : str
        The research-use statement.
    """

    plan: str
    needles: tuple[InsertNeedle, ...]
    applicators: tuple[ApplicatorChannel, ...] = ()
    perturbations: str = ""
    tension_rule: str = ""
    obstacles: str = ""
    statement: str = RESEARCH_USE

    @property
    def hole_ids(self) -> tuple[str, ...]:
        """The needles' template holes, in channel order."""
        return tuple(n.hole_id for n in self.needles)

    def title(self) -> str:
        """Return the list's heading, e.g. ``Insert these: 2 needles (Bd, Cj) + Tandem``.

        Returns
        -------
        str
            Counts and names.
        """
        n = len(self.needles)
        ic = "".join(f" + {a.name}" for a in self.applicators)
        return f"Insert these ({self.plan}): {n} needle{'s' if n != 1 else ''} ({', '.join(self.hole_ids)}){ic}"

    def rows(self) -> list[tuple[str, ...]]:
        """Return the list as text rows: :data:`COLUMNS`, then one row per needle.

        Returns
        -------
        list of tuple of str
            Header first.
        """
        return [COLUMNS, *(n.cells() for n in self.needles)]

    def details(self) -> list[tuple[str, str, str]]:
        """Return per needle its tension schedule in words and its check depths in words.

        Returns
        -------
        list of (str, str, str)
            ``(hole_id, schedule, checks)``: the schedule as :meth:`InsertNeedle.schedule_text`, the checks joined
            with ``"; "``.
        """
        return [(n.hole_id, n.schedule_text(), "; ".join(c.text() for c in n.checks)) for n in self.needles]

    def scenario_rows(self) -> list[tuple[str, ...]]:
        """Return every needle's perturbations as text rows, the header first: the margins' evidence.

        Returns
        -------
        list of tuple of str
            ``hole, perturbation, tip displacement, reach margin, clearance, clearance margin, organ`` (mm).
        """
        head = ("hole", "perturbation", "tip displacement (mm)", "reach margin (mm)", "clearance (mm)",
                "clearance margin (mm)", "organ")
        rows: list[tuple[str, ...]] = [head]
        for n in self.needles:
            for s in n.scenarios:
                finite = bool(np.isfinite(s.clearance_mm))
                rows.append((n.hole_id, s.label, f"{s.reach_mm:.1f}", f"{n.reach.limit_mm - s.reach_mm:+.1f}",
                             f"{s.clearance_mm:.1f}" if finite else "-",
                             f"{s.clearance_mm - n.clearance.limit_mm:+.1f}" if finite else "-", s.organ or "-"))
        return rows

    def to_json(self) -> dict[str, object]:
        """Return the list as JSON-ready values (plan.json ``insert_list``; the device JSON's).

        Returns
        -------
        dict
            Every field; needles and applicator channels as their own JSON.
        """
        return {"statement": self.statement, "plan": self.plan, "needles": [n.to_json() for n in self.needles],
                "applicators": [a.to_json() for a in self.applicators], "perturbations": self.perturbations,
                "tension_rule": self.tension_rule, "obstacles": self.obstacles}

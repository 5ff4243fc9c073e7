"""The report's first section: the delivered implant's insert list (the hand-off), as the terminal prints it.

The rows are :meth:`~reachplan.plugins.exporters.handoff.InsertList.rows`, the same the terminal's first screen and
the device page print, so a needle is named identically everywhere.
"""

from __future__ import annotations

from reachplan.planner.case.scene import Scene
from reachplan.planner.delivery import Delivery
from reachplan.planner.handoff import obstacles_line
from reachplan.planner.report.html import Block, Paragraph, Section, Table
from reachplan.plugins.exporters.handoff import NUMERIC_COLUMNS

#: The section's anchor (``report.html#insert-these``).
ANCHOR = "insert-these"


def handoff_section(delivery: Delivery | None, scene: Scene) -> Section:
    """Return the report's first section: what to insert, then how, where to check, and the margins' model.

    Parameters
    ----------
    delivery : Delivery or None
        The delivered plan; its export carries the insert list. None (ranked only) or no list: the section says so.
    scene : Scene
        The applicators taken (the line that names them).

    Returns
    -------
    Section
        Anchor :data:`ANCHOR`: the list's table, per needle its schedule in words and check depths, the applicator
        channels, the rule at the tension limit, the perturbation model and the applicators taken.
    """
    handoff = delivery.export.handoff if delivery is not None else None
    if handoff is None:
        return Section("Insert these", ANCHOR, (
            Paragraph("No implant to insert: the plan was ranked only (--no-export); the per-target needles below "
                      "explain what a steered needle could reach."), Paragraph(obstacles_line(scene))))
    rows = handoff.rows()
    blocks: list[Block] = [
        Paragraph("The needles to insert for the delivered plan, in RT Plan channel order (the same list as the "
                  "terminal's first screen, the device page export/*_device.html and plan.json insert_list). The "
                  "per-target candidates further down explain the choice; the template map, slices and 3-D view "
                  "show the needles."),
        Table(rows[0], tuple(rows[1:]), "One row per needle, in RT Plan channel order", numeric=NUMERIC_COLUMNS),
        Table(("hole", "tension schedule (direction in patient terms)", "check depths: expected tip"),
              tuple(handoff.details()), "How to insert each needle, and where to image it"),
    ]
    blocks += [Paragraph(a.text()) for a in handoff.applicators]
    if handoff.tension_rule:
        blocks.append(Paragraph(handoff.tension_rule))
    blocks.append(Paragraph(handoff.perturbations))
    scenarios = handoff.scenario_rows()
    if len(scenarios) > 1:
        blocks.append(Table(scenarios[0], tuple(scenarios[1:]), "The margins' evidence: every needle under every "
                            "perturbation", numeric=(2, 3, 4, 5), collapsed=True))
    blocks.append(Paragraph(handoff.obstacles))
    return Section(handoff.title(), ANCHOR, tuple(blocks))

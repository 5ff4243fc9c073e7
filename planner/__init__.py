"""The application floor: plans steered and straight needles from a scene, ranks them, doses and reports.

Rooms, from the bottom (each imports only the rooms below it; ``docs/architecture.md``): ``errors``,
:mod:`~reachplan.planner.geometry`, :mod:`~reachplan.planner.steering`, :mod:`~reachplan.planner.ranking`,
:mod:`~reachplan.planner.dose`, :mod:`~reachplan.planner.pipeline` (the one place the stages are chained),
:mod:`~reachplan.planner.report`, :mod:`~reachplan.planner.study`, :mod:`~reachplan.planner.bench` and
:mod:`~reachplan.planner.cli`. Patient geometry is in mm, DICOM LPS.
"""

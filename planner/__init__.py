"""The application floor: plans steered and straight needles from a scene, ranks them, doses and reports.

Rooms, from the bottom (each imports only the rooms below it; ``docs/architecture.md``): ``errors``,
:mod:`~reachplan.planner.lookup` (the one module that calls the plugin registry),
:mod:`~reachplan.planner.geometry`, :mod:`~reachplan.planner.steering`, :mod:`~reachplan.planner.ranking`,
:mod:`~reachplan.planner.case` (the scene and the steering search) beside :mod:`~reachplan.planner.dose`,
:mod:`~reachplan.planner.implant`, :mod:`~reachplan.planner.delivery`, :mod:`~reachplan.planner.report`,
:mod:`~reachplan.planner.study`, :mod:`~reachplan.planner.run` (``run_case``: the chain ``plan`` and ``demo``
share), :mod:`~reachplan.planner.bench` and :mod:`~reachplan.planner.cli`. Patient geometry is in mm, DICOM LPS.
"""

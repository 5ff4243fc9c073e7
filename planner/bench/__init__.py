"""Benchmarks behind ``reachplan bench <target>``: one module per target, CSV + PNG into a results folder.

Targets: :mod:`~reachplan.planner.bench.models` (rod models), :mod:`~reachplan.planner.bench.planning`,
:mod:`~reachplan.planner.bench.dose`, :mod:`~reachplan.planner.bench.imaging_load` (``imaging``) and
:mod:`~reachplan.planner.bench.study`; what they share is in :mod:`~reachplan.planner.bench.common`.
"""

"""Mechanics of the steerable stylet in its needle: design -> loads -> shape.

Knows nothing of patients or DICOM. Positions are millimetres in the needle's own frame (base at the origin,
unactuated axis ``+z``; at roll 0 the rod bends in the x-z plane toward the pulled tendon at ``+x``).

Modules: :mod:`~reachplan.rod_model.design` (designs, presets, loads), :mod:`~reachplan.rod_model.protocol`
(the ``RodModel`` Protocol), :mod:`~reachplan.rod_model.result` (``RodPath``, ``FailedSolve``, ``RodBatch``), models
:mod:`~reachplan.rod_model.kinematic` (``constant_curvature``), :mod:`~reachplan.rod_model.beam` (``planar_beam``),
:mod:`~reachplan.rod_model.cosserat` (``cosserat_rod``, ``two_tube_cosserat``; shooting),
:mod:`~reachplan.rod_model.collocation` (the same BVP by collocation) and :mod:`~reachplan.rod_model.joints`
(``discrete_joints``: each ball joint a spring with Coulomb friction), :mod:`~reachplan.rod_model.calibrate`
(``calibrate()``), :mod:`~reachplan.rod_model.select` (plugin lookup and the tolerance-driven model selector).
"""

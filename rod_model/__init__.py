"""Mechanics of the steerable stylet in its needle: design -> loads -> shape.

Knows nothing of patients or DICOM. Positions are millimetres in the needle's own frame (base at the origin,
unactuated axis ``+z``; at roll 0 the rod bends in the x-z plane toward the pulled tendon at ``+x``).

Modules: :mod:`~rod_model.design` (designs, presets, loads), :mod:`~rod_model.protocol` (the ``RodModel``
Protocol), :mod:`~rod_model.result` (``RodPath``, ``FailedSolve``, ``RodBatch``), models
:mod:`~rod_model.kinematic` (``constant_curvature``), :mod:`~rod_model.beam` (``planar_beam``),
:mod:`~rod_model.cosserat` (``cosserat_rod``, ``two_tube_cosserat``; shooting) and
:mod:`~rod_model.collocation` (the same BVP by collocation), :mod:`~rod_model.calibrate`
(``calibrate()``), :mod:`~rod_model.select` (plugin lookup and the tolerance-driven model selector).
"""

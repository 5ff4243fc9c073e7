"""Implant planning: candidate needles for a volume, selection, dwell times, straight against steered.

One module per job: ``settings`` (ImplantSettings), ``candidates`` (channels for a volume), ``problem`` (the sampled
problem of one arm), ``optimiser`` (the dwell-optimiser seam, chosen by name), ``model`` and ``selection`` (the
built-in optimiser ``"lp"``), ``dwells`` (dwell times of a chosen set), ``plan`` (the budgets of one arm, several
arms), ``arms`` (the results and Pareto curve), ``compare`` (straight versus steered on given needles).
"""

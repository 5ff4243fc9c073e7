"""Needles found in post-insertion images and compared with the plan and with the truth of a synthetic case.

``implant.py`` draws where a plan's needles really go (the planner's own uncertainty model, seeded) for a synthetic
post-insertion image; ``find.py`` finds the needles in an image from the template's holes, without being told which;
``compare.py`` measures found needles against the truth or the plan; ``outputs.py`` writes ``needles.json`` and
the RT Structure Set. Nothing here reads a truth file to find a needle.
"""

"""Figures, the reachable-workspace map and the self-contained HTML report of a plan, built in memory."""

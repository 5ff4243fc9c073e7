"""Steering: tension schedules, insertion models, candidates (straight and steered), robustness, shape banks."""

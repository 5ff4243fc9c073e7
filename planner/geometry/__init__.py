"""Geometry: template pose in the patient, hole frames, and organ clearance and collision (mm, LPS)."""

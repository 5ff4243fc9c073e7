"""Dose: TG-43 dose from dwell positions, DVH and coverage metrics with EQD2, and dwell-time optimisation."""

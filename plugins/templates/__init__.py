"""Built-in template layouts (registered under the ``reachplan.templates`` entry-point group)."""

from __future__ import annotations

from pathlib import Path

from planner.template import Template, load_template_csv

_HERE = Path(__file__).parent


def needlefinder_syed_63() -> Template:
    """The 63-hole Syed-Neblett-style layout of 3D Slicer's NeedleFinder module (see the CSV header)."""
    return load_template_csv(_HERE / "needlefinder_syed_63.csv", "needlefinder_syed_63")

"""Template layouts: hole positions in the template frame, and the built-in layouts.

Template frame: origin at the template centre (the obturator axis on the template plane), ``x``/``y`` in the
template plane, ``+z`` the insertion direction. Built-ins register under the ``reachplan.templates`` entry-point
group; a third party registers a zero-argument callable returning a :class:`Template` the same way. Placing a
template in the patient is the planner's job (:mod:`reachplan.planner.geometry.template`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reachplan.plugins.errors import PluginError

_HERE = Path(__file__).parent


class TemplateFileError(PluginError):
    """A template layout file cannot be read (missing column, bad number, duplicate hole)."""


@dataclass(frozen=True)
class Hole:
    """One template hole.

    Parameters
    ----------
    hole_id : str
        Hole label as printed on the template face.
    xy_mm : (2,) float, mm, template frame
        Hole centre in the template plane.
    kind : str
        ``"needle"`` or ``"tandem"`` (the central channel the tandem/obturator occupies).

    Raises
    ------
    ValueError
        An empty id, a non-finite position or an unknown kind.
    """

    hole_id: str
    xy_mm: tuple[float, float]
    kind: str = "needle"

    def __post_init__(self) -> None:
        if not self.hole_id:
            raise ValueError("a hole needs a non-empty hole_id")
        if not all(np.isfinite(self.xy_mm)):
            raise ValueError(f"hole {self.hole_id}: position must be finite, got {self.xy_mm}")
        if self.kind not in ("needle", "tandem"):
            raise ValueError(f"hole {self.hole_id}: kind must be 'needle' or 'tandem', got {self.kind!r}")

    @property
    def distance_mm(self) -> float:
        """Distance from the template centre (mm); smaller is more medial."""
        return float(np.hypot(*self.xy_mm))


@dataclass(frozen=True)
class Template:
    """A hole layout (from a template plugin).

    Parameters
    ----------
    name : str
        Plugin or file name.
    holes : tuple of Hole
        At least one; ids unique.
    source : str
        Where the layout comes from (its citation).
    application_setup_type : str
        DICOM Application Setup Type (300A,0232) of an implant through this template (PS3.3 C.8.8.15 defined
        terms): ``PERINEAL`` for transperineal needles (as Oncentra/Vitesse writes, rtplan_conventions.md §6),
        ``SYED_NEBLETT`` for a Syed-Neblett template.

    Raises
    ------
    ValueError
        No holes, or duplicate hole ids.
    """

    name: str
    holes: tuple[Hole, ...]
    source: str = ""
    application_setup_type: str = "PERINEAL"

    def __post_init__(self) -> None:
        ids = [h.hole_id for h in self.holes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"template {self.name}: hole ids must be unique")
        if not self.holes:
            raise ValueError(f"template {self.name}: no holes")

    @property
    def needle_holes(self) -> tuple[Hole, ...]:
        """The holes a needle may use (the tandem channel excluded)."""
        return tuple(h for h in self.holes if h.kind == "needle")


def load_template_csv(path: Path, name: str | None = None, application_setup_type: str = "PERINEAL") -> Template:
    """Read a template layout: CSV with ``hole_id,x_mm,y_mm[,kind]``; lines starting with ``#`` are comments.

    The comment lines are kept as the template's ``source`` (its citation).

    Parameters
    ----------
    path : Path
        The CSV file (UTF-8); positions in mm in the template frame.
    name : str, optional
        Template name (default: the file's stem).
    application_setup_type : str
        See :class:`Template`.

    Raises
    ------
    TemplateFileError
        A missing column, a bad number, an empty hole id or an unknown kind.
    ValueError
        Duplicate hole ids or no holes (raised by :class:`Template`, not turned into a TemplateFileError).
    OSError
        The file cannot be read.
    """
    text = Path(path).read_text(encoding="utf-8").splitlines()
    comments = [line[1:].strip() for line in text if line.startswith("#")]
    reader = csv.DictReader(line for line in text if line.strip() and not line.startswith("#"))
    missing = {"hole_id", "x_mm", "y_mm"} - set(reader.fieldnames or ())
    if missing:
        raise TemplateFileError(f"template {path}: missing column(s) {sorted(missing)}; need hole_id,x_mm,y_mm")
    try:
        holes = tuple(
            Hole(r["hole_id"], (float(r["x_mm"]), float(r["y_mm"])), r.get("kind") or "needle") for r in reader
        )
    except ValueError as exc:
        raise TemplateFileError(f"template {path}: {exc}") from None
    return Template(name or Path(path).stem, holes, " ".join(comments), application_setup_type)


def needlefinder_syed_63() -> Template:
    # The registry shows this docstring's first line as the plugin's description: a noun phrase on purpose.
    """The 63-hole Syed-Neblett-style layout of 3D Slicer's NeedleFinder module (see the CSV header)."""  # noqa: D401
    return load_template_csv(_HERE / "needlefinder_syed_63.csv", "needlefinder_syed_63", "SYED_NEBLETT")

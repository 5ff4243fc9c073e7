"""ROI name normalisation through a configurable synonym table.

Clinical structure names vary (``BLADDER``, ``Bladder_P``, ``Blase``). :class:`SynonymTable` maps them to
the standard names the planner uses; the original name is always kept beside the normalised one
(:class:`reachplan.imaging.types.Roi`). Matching ignores case, spaces, ``_``, ``-`` and ``.``. Standard names follow
AAPM TG-263 where it has one (``Femur_Head_L``), and the gynecologic brachytherapy usage otherwise
(``HR-CTV``, GEC-ESTRO).
"""

from __future__ import annotations

import csv
import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from reachplan.imaging.errors import ImagingError, StructureError
from reachplan.imaging.types import StructureSet

# TG-263 primary and reverse-order names first (TG263_Nomenclature_Worksheet_20170815; Mayo et al., IJROBP
# 100(4):1057, 2018; see shared reference gyn_anatomy.md §5), then clinical variants and other languages.
_DEFAULT: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Bladder", ("Bladder", "Bladder_P", "UrinaryBladder", "Blase", "Harnblase", "Vessie", "Vejiga", "Vescica")),
    ("Rectum", ("Rectum", "Rectum_P", "Rectal", "Rektum", "Recto", "Retto")),
    ("Sigmoid", ("Colon_Sigmoid", "Sigmoid_Colon", "Sigmoid", "Sigmoid_P", "Sigma", "SigmoidColon", "Sigmoide",
                 "Sigmoidcolon", "Sigmoideum")),
    ("Bowel", ("Bowel_Small", "Small_Bowel", "Bowel", "Bag_Bowel", "Bowel_Bag", "Spc_Bowel", "Spc_Bowel_Small",
               "Bowel_P", "SmallBowel", "BowelBag", "Small_Intestine", "Bowel_Loops", "Intestine", "Duenndarm",
               "Dünndarm", "Darm")),
    ("HR-CTV", ("HR-CTV", "HRCTV", "CTV_HR", "CTVHR", "HR_CTV", "CTV_HighRisk", "CTV-T_HR", "CTVT_HR")),
    ("IR-CTV", ("IR-CTV", "IRCTV", "CTV_IR", "CTVIR", "IR_CTV", "CTV_IntermediateRisk")),
    ("GTV", ("GTV", "GTV_Res", "GTVres", "GTV-T_res")),
    ("Uterus", ("Uterus", "Uterus_P", "Gebaermutter", "Gebärmutter")),
    ("Cervix", ("Cervix", "Cervix_Uteri", "Zervix", "Portio")),
    ("Vagina", ("Vagina", "Vaginal_Canal", "Scheide")),
    ("Obturator", ("Obturator", "Vaginal_Obturator", "Cylinder", "Vaginal_Cylinder", "Cyl_Vaginal", "Vaginal_Cyl",
                   "Vaginal_Applicator")),
    ("Bone", ("Bone_Pelvic", "Pelvic_Bone", "Bone", "Bones", "Pelvis", "Pelvic_Bones", "Knochen")),
    ("Body", ("Body", "External", "Skin", "Outer_Contour", "Patient", "Koerper", "Körper")),
    ("Femur_Head_L", ("Femur_Head_L", "L_Head_Femur", "Femoral_Head_Lt", "Femoral_Head_L", "Femoral_Head_Left",
                      "FemHead_L", "Lt_Femoral_Head", "Left_Femoral_Head", "Femur_L")),
    ("Femur_Head_R", ("Femur_Head_R", "R_Head_Femur", "Femoral_Head_Rt", "Femoral_Head_R", "Femoral_Head_Right",
                      "FemHead_R", "Rt_Femoral_Head", "Right_Femoral_Head", "Femur_R")),
    ("Prostate", ("Prostate", "PROS", "Prostata")),
    ("Urethra", ("Urethra", "Urethra_P", "Harnroehre")),
)

_SEPARATORS = re.compile(r"[\s_\-.]+")


def name_key(name: str) -> str:
    """Return the matching key of a name: case-folded, without spaces, ``_``, ``-`` and ``.``.

    Parameters
    ----------
    name : str
        An ROI name.

    Returns
    -------
    str
        The key two names match on.
    """
    return _SEPARATORS.sub("", name.casefold())


@dataclass(frozen=True)
class SynonymTable:
    """Standard names and the synonyms that map to them.

    Parameters
    ----------
    entries : tuple of (str, tuple of str)
        ``((standard_name, (synonym, ...)), ...)``; each standard name also matches itself.

    Raises
    ------
    ValueError
        An empty standard name or synonym, or a synonym that maps to two standard names.
    """

    entries: tuple[tuple[str, tuple[str, ...]], ...] = _DEFAULT
    _lookup: dict[str, str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        seen: dict[str, str] = {}
        for standard, synonyms in self.entries:
            if not standard.strip():
                raise ValueError("a synonym table entry has an empty standard name")
            for s in (standard, *synonyms):
                key = name_key(s)
                if not key:
                    raise ValueError(f"synonym {s!r} of {standard!r} is empty after normalisation")
                if seen.get(key, standard) != standard:
                    raise ValueError(f"synonym {s!r} maps to both {seen[key]!r} and {standard!r}")
                seen[key] = standard
        object.__setattr__(self, "_lookup", seen)

    def normalize(self, name: str) -> str:
        """Return the standard name for ``name``; ``name`` itself (stripped) when no synonym matches.

        Parameters
        ----------
        name : str
            An ROI name as written.

        Returns
        -------
        str
            Its standard name.
        """
        return self._lookup.get(name_key(name), name.strip())

    @property
    def standard_names(self) -> tuple[str, ...]:
        """The standard names, in table order."""
        return tuple(standard for standard, _ in self.entries)

    def synonyms_of(self, standard: str) -> tuple[str, ...]:
        """Return the synonyms listed for ``standard`` (empty when it is not in the table).

        Parameters
        ----------
        standard : str
            A standard name.

        Returns
        -------
        tuple of str
            Its synonyms, as the table lists them.
        """
        return next((syn for std, syn in self.entries if std == standard), ())

    def extended(self, entries: tuple[tuple[str, tuple[str, ...]], ...]) -> SynonymTable:
        """Return a new table with ``entries`` added (synonyms of an existing standard name are merged).

        Parameters
        ----------
        entries : tuple of (str, tuple of str)
            Standard name and its synonyms.

        Returns
        -------
        SynonymTable
            This table's entries and ``entries``.

        Raises
        ------
        ValueError
            A new synonym maps to two standard names.
        """
        merged: dict[str, tuple[str, ...]] = dict(self.entries)
        for standard, synonyms in entries:
            merged[standard] = (*merged.get(standard, ()), *synonyms)
        return SynonymTable(tuple(merged.items()))

    @classmethod
    def from_csv(cls, path: Path, base: SynonymTable | None = None) -> SynonymTable:
        """Read ``standard,synonym`` rows (header line ``standard,synonym``) on top of ``base``.

        Parameters
        ----------
        path : Path
            CSV file, UTF-8, one synonym per row.
        base : SynonymTable, optional
            The table to extend (default: the built-in table).

        Returns
        -------
        SynonymTable
            ``base`` extended by the file's rows.

        Raises
        ------
        ImagingError
            The file cannot be read or has the wrong columns.
        """
        try:
            with Path(path).open(newline="", encoding="utf-8") as fh:
                rows = list(csv.DictReader(fh))
        except OSError as exc:
            raise ImagingError(f"cannot read synonym table {path}: {exc.strerror}") from None
        except (UnicodeDecodeError, csv.Error) as exc:
            raise ImagingError(f"synonym table {path} is not UTF-8 CSV text ({type(exc).__name__}); give a CSV file "
                               "with 'standard,synonym' rows") from None
        if rows and not {"standard", "synonym"} <= set(rows[0]):
            raise ImagingError(f"synonym table {path} needs the header line 'standard,synonym'")
        if any(not isinstance(r.get("standard"), str) or not isinstance(r.get("synonym"), str) for r in rows):
            raise ImagingError(f"synonym table {path}: every row needs two columns 'standard,synonym'")
        add: dict[str, tuple[str, ...]] = {}
        for r in rows:
            if not (r.get("standard") or "").strip() or not (r.get("synonym") or "").strip():
                raise ImagingError(f"synonym table {path}: a row has an empty standard name or synonym")
            add[r["standard"].strip()] = (*add.get(r["standard"].strip(), ()), r["synonym"].strip())
        try:
            return (base or cls()).extended(tuple(add.items()))
        except ValueError as exc:
            raise ImagingError(f"synonym table {path}: {exc}") from None


DEFAULT_SYNONYMS = SynonymTable()


def rename(structures: StructureSet, overrides: Mapping[str, str]) -> StructureSet:
    """Give ROIs standard names by hand (``--oar Bladder=BL_1``).

    Parameters
    ----------
    structures : StructureSet
        The structure set as read.
    overrides : mapping of str to str
        Original ROI name -> standard name. Matching of the ROI name ignores case. Any other ROI that
        the table had mapped to one of these standard names keeps its original name instead (``NAME (ROI n)``
        when that is the standard name itself), so the choice by hand is the only ROI with that standard name.

    Returns
    -------
    StructureSet
        The same structure set with the ROIs renamed.

    Raises
    ------
    StructureError
        An ROI name is not in the structure set.
    """
    by_key = {k.strip().casefold(): v.strip() for k, v in overrides.items()}
    names = {r.name.strip().casefold() for r in structures.rois}
    unknown = [k for k in overrides if k.strip().casefold() not in names]
    if unknown:
        raise StructureError(f"no ROI named {', '.join(repr(u) for u in unknown)}; available: "
                             f"{', '.join(repr(r.name) for r in structures.rois) or 'none'}")
    taken = {v.casefold() for v in by_key.values()}
    rois = []
    for r in structures.rois:
        new = by_key.get(r.name.strip().casefold())
        if new is None and r.normalized_name.casefold() in taken:
            new = r.name.strip()
            if new.casefold() in taken:  # its own name is the standard name chosen for another ROI
                new = f"{new} (ROI {r.number})"
        rois.append(r if new is None else dataclasses.replace(r, normalized_name=new))
    return dataclasses.replace(structures, rois=tuple(rois))

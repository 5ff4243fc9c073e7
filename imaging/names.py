"""ROI name normalisation through a configurable synonym table.

Clinical structure names vary (``BLADDER``, ``Bladder_P``, ``Blase``). :class:`SynonymTable` maps them to
the standard names the planner uses; the original name is always kept beside the normalised one
(:class:`reachplan.imaging.types.Roi`). Matching ignores case, spaces, ``_``, ``-`` and ``.``. Standard names follow
AAPM TG-263 where it has one (``Femur_Head_L``), and the gynecologic brachytherapy usage otherwise
(``HR-CTV``, GEC-ESTRO).
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

from reachplan.imaging.errors import ImagingError

_DEFAULT: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Bladder", ("Bladder", "Bladder_P", "Blase", "Harnblase", "Vessie", "Vejiga", "Vescica", "UrinaryBladder")),
    ("Rectum", ("Rectum", "Rectum_P", "Rektum", "Rectal", "Recto", "Retto")),
    ("Sigmoid", ("Sigmoid", "Sigmoid_P", "Sigma", "SigmoidColon", "Colon_Sigmoid", "Sigmoid_Colon", "Sigmoide",
                 "Sigmoidcolon", "Sigmoideum")),
    ("Bowel", ("Bowel", "Bowel_P", "SmallBowel", "Bowel_Small", "Small_Intestine", "Duenndarm", "Dünndarm",
               "Darm", "BowelBag", "Bowel_Bag", "Bowel_Loops", "Intestine")),
    ("HR-CTV", ("HR-CTV", "HRCTV", "CTV_HR", "CTVHR", "HR_CTV", "CTV_HighRisk", "CTV-T_HR", "CTVT_HR")),
    ("IR-CTV", ("IR-CTV", "IRCTV", "CTV_IR", "CTVIR", "IR_CTV", "CTV_IntermediateRisk")),
    ("GTV", ("GTV", "GTV_Res", "GTVres", "GTV-T_res")),
    ("Uterus", ("Uterus", "Gebaermutter", "Gebärmutter", "Uterus_P")),
    ("Cervix", ("Cervix", "Cervix_Uteri", "Zervix", "Portio")),
    ("Vagina", ("Vagina", "Vaginal_Canal", "Scheide")),
    ("Obturator", ("Obturator", "Vaginal_Obturator", "Cylinder", "Vaginal_Cylinder")),
    ("Bone", ("Bone", "Bones", "Pelvis", "Bone_Pelvic", "Pelvic_Bones", "Knochen")),
    ("Body", ("Body", "External", "Outer_Contour", "Skin", "Patient", "Koerper", "Körper")),
    ("Femur_Head_L", ("Femur_Head_L", "Femoral_Head_Lt", "Femoral_Head_L", "Femoral_Head_Left", "FemHead_L",
                      "Lt_Femoral_Head", "Left_Femoral_Head", "Femur_L")),
    ("Femur_Head_R", ("Femur_Head_R", "Femoral_Head_Rt", "Femoral_Head_R", "Femoral_Head_Right", "FemHead_R",
                      "Rt_Femoral_Head", "Right_Femoral_Head", "Femur_R")),
    ("Prostate", ("Prostate", "PROS", "Prostata")),
    ("Urethra", ("Urethra", "Urethra_P", "Harnroehre")),
)

_SEPARATORS = re.compile(r"[\s_\-.]+")


def name_key(name: str) -> str:
    """The matching key of a name: case-folded, without spaces, ``_``, ``-`` and ``.``."""
    return _SEPARATORS.sub("", name.casefold())


@dataclass(frozen=True)
class SynonymTable:
    """Standard names and the synonyms that map to them.

    Parameters
    ----------
    entries : ``((standard_name, (synonym, ...)), ...)``; the standard name matches itself.
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
        """The standard name for ``name``; ``name`` itself (stripped) when no synonym matches."""
        return self._lookup.get(name_key(name), name.strip())

    def extended(self, entries: tuple[tuple[str, tuple[str, ...]], ...]) -> SynonymTable:
        """A new table with ``entries`` added (synonyms of an existing standard name are merged)."""
        merged: dict[str, tuple[str, ...]] = dict(self.entries)
        for standard, synonyms in entries:
            merged[standard] = (*merged.get(standard, ()), *synonyms)
        return SynonymTable(tuple(merged.items()))

    @classmethod
    def from_csv(cls, path: Path, base: SynonymTable | None = None) -> SynonymTable:
        """Read ``standard,synonym`` rows (header line ``standard,synonym``) on top of ``base``.

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
            add[r["standard"].strip()] = (*add.get(r["standard"].strip(), ()), r["synonym"].strip())
        try:
            return (base or cls()).extended(tuple(add.items()))
        except ValueError as exc:
            raise ImagingError(f"synonym table {path}: {exc}") from None


DEFAULT_SYNONYMS = SynonymTable()

"""ROI names: TG-263 names first, clinical variants, tables from files, and renaming by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reachplan.imaging.errors import ImagingError, StructureError
from reachplan.imaging.names import DEFAULT_SYNONYMS, SynonymTable, rename
from reachplan.imaging.types import Contour, Roi, StructureSet


@pytest.mark.parametrize(("name", "standard"), [
    ("Colon_Sigmoid", "Sigmoid"), ("Sigmoid_Colon", "Sigmoid"), ("Bowel_Small", "Bowel"), ("Small_Bowel", "Bowel"),
    ("Bag_Bowel", "Bowel"), ("Bone_Pelvic", "Bone"), ("L_Head_Femur", "Femur_Head_L"), ("External", "Body"),
    ("BLADDER", "Bladder"), ("Blase", "Bladder"), ("ctv_hr", "HR-CTV"), ("Rect_PRV", "Rect_PRV"),
])
def test_tg263_names_and_variants(name: str, standard: str) -> None:
    assert DEFAULT_SYNONYMS.normalize(name) == standard


def test_tg263_primary_names_come_first() -> None:
    # gyn_anatomy.md §5 (TG-263 worksheet v20170815): the primary name heads each entry
    firsts = {s: DEFAULT_SYNONYMS.synonyms_of(s)[0] for s in ("Sigmoid", "Bowel", "Bone", "Bladder", "Rectum")}
    assert firsts == {"Sigmoid": "Colon_Sigmoid", "Bowel": "Bowel_Small", "Bone": "Bone_Pelvic",
                      "Bladder": "Bladder", "Rectum": "Rectum"}
    assert DEFAULT_SYNONYMS.synonyms_of("NoSuchOrgan") == ()


def test_table_from_a_binary_or_broken_file_is_a_typed_error(tmp_path: Path) -> None:
    f = tmp_path / "t.csv"
    f.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ImagingError, match="not UTF-8 CSV"):
        SynonymTable.from_csv(f)
    f.write_text("standard,synonym\nBladder,\n")
    with pytest.raises(ImagingError, match="empty"):
        SynonymTable.from_csv(f)


def test_rename_by_hand_takes_the_name_from_the_others() -> None:
    c = (Contour(np.zeros((1, 3)), "POINT"),)
    ss = StructureSet((Roi(0, "Bladder", c, "Bladder"), Roi(1, "BL_2", c), Roi(2, "Rect_PRV", c)), "1.2")
    out = rename(ss, {"bl_2": "Bladder", "Rect_PRV": "Rectum"})
    assert out.names == ("Bladder (ROI 0)", "Bladder", "Rectum")
    assert out.get("Bladder").name == "BL_2" and out.get("Rectum").name == "Rect_PRV"
    assert [r.name for r in out.rois] == ["Bladder", "BL_2", "Rect_PRV"]
    with pytest.raises(StructureError, match="no ROI named 'Nope'"):
        rename(ss, {"Nope": "Bladder"})


def test_names_that_differ_only_in_case_are_found_as_spelt() -> None:
    """Issue 27: Vitesse channels ``B5.5`` and ``b5.5`` are told apart (by ROI number, and by spelling when asked)."""
    c = (Contour(np.zeros((1, 3)), "POINT"),)
    ss = StructureSet((Roi(7, "B5.5", c), Roi(8, "b5.5", c), Roi(9, "Rectum", c)), "1.2")
    assert ss.get("b5.5").number == 8 and ss.get("B5.5").number == 7 and ss.get("RECTUM").number == 9

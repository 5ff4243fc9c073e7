"""Whether a CT's stored values read as CT numbers: the signed/unsigned check of Pixel Representation.

A CT slice holds air (about -1000 HU) and water or soft tissue (about 0 HU); no patient tissue or metal reaches
:data:`CT_MAX_HU` and nothing but the padding outside the field of view goes below :data:`CT_MIN_HU`. A signed CT
declared unsigned (Pixel Representation 0) reads its air, stored as -1000, as 64,536 HU; read as signed it is
consistent again. :func:`ct_stored_values` tells the two readings apart by these ranges: it keeps the declared one
when it is consistent, takes the other one (and says so) when only that one is, and refuses the slice when neither is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.errors import InvalidValueError

#: CT numbers below this (HU) are not tissue nor air: only the padding value outside the field of view may be lower.
CT_MIN_HU = -10_000.0
#: CT numbers above this (HU) do not exist: the extended CT scale of metal implants ends near 31,000 HU.
CT_MAX_HU = 32_767.0


@dataclass(frozen=True)
class Reading:
    """The range of CT numbers one reading of a slice gives.

    Parameters
    ----------
    signed : bool
        The stored values read as two's complement.
    lo, hi : float, HU
        The lowest and highest CT number, the padding (the slice's lowest value, when below :data:`CT_MIN_HU`)
        left out.
    median : float, HU
        The median CT number (water or soft tissue in a patient).
    """

    signed: bool
    lo: float
    hi: float
    median: float

    @property
    def consistent(self) -> bool:
        """The CT numbers lie within [:data:`CT_MIN_HU`, :data:`CT_MAX_HU`]."""
        return self.lo >= CT_MIN_HU and self.hi <= CT_MAX_HU

    def describe(self) -> str:
        """Return ``"as signed: -1000 to 150 HU (median 0 HU)"``.

        Returns
        -------
        str
            The reading and its range of CT numbers.
        """
        return (f"as {'signed' if self.signed else 'unsigned'}: {self.lo:.0f} to {self.hi:.0f} HU "
                f"(median {self.median:.0f} HU)")


def _reading(stored: np.ndarray, signed: bool, rescales: Sequence[tuple[float, float]]) -> Reading:
    """Read ``stored`` (frames first) as CT numbers, frame by frame, and return their range without the padding."""
    hu = np.concatenate([(np.asarray(f, dtype=np.float64) * s + b).ravel() for f, (s, b) in zip(
        stored, rescales, strict=True)])
    low = float(hu.min())
    if low < CT_MIN_HU:  # the padding outside the field of view: one value, the lowest
        rest = hu[hu > low]
        hu = rest if rest.size else hu
    return Reading(signed, float(hu.min()), float(hu.max()), float(np.median(hu)))


def _other_signedness(stored: np.ndarray, signed: bool, bits_stored: int) -> np.ndarray:
    """Return the stored values read with the other Pixel Representation (two's complement on ``bits_stored``)."""
    out = stored.astype(np.int64)
    if signed:
        out[out < 0] += 1 << bits_stored
    else:
        out[out >= 1 << (bits_stored - 1)] -= 1 << bits_stored
    return out


def ct_stored_values(
    stored: np.ndarray, ds: Any, path: Path, rescales: Sequence[tuple[float, float]]
) -> tuple[np.ndarray, tuple[Reading, Reading] | None]:
    """Check that a CT object's stored values read as CT numbers; read them as the other signedness when only it does.

    Parameters
    ----------
    stored : (rows, columns) or (frames, rows, columns) int array
        The stored values as decoded with the declared Pixel Representation.
    ds : pydicom.Dataset
        The object's header (Modality, Pixel Representation, Bits Stored).
    path : Path
        Its file (named in the message).
    rescales : sequence of (float, float)
        (slope, intercept) of each frame: CT number = slope * stored + intercept.

    Returns
    -------
    values : array
        ``stored`` itself (declared reading consistent, not a CT, or not integers), else the values read the
        other way (int64, same shape).
    readings : (Reading, Reading) or None
        The declared reading and the one used instead; None when the declared one was kept.

    Raises
    ------
    InvalidValueError
        Neither reading gives CT numbers between :data:`CT_MIN_HU` and :data:`CT_MAX_HU`.
    """
    if str(ds.get("Modality", "")).upper() != "CT" or stored.dtype.kind not in "iu" or not stored.size:
        return stored, None
    frames = stored[None] if stored.ndim == 2 else stored
    slopes = np.array([s for s, _ in rescales], dtype=float)
    intercepts = np.array([b for _, b in rescales], dtype=float)
    lo, hi = float(frames.min()), float(frames.max())
    ends = np.concatenate([slopes * lo + intercepts, slopes * hi + intercepts])
    if ends.min() >= CT_MIN_HU and ends.max() <= CT_MAX_HU:
        return stored, None  # the usual case: no need to look closer
    signed = stored.dtype.kind == "i"
    declared = _reading(frames, signed, rescales)
    if declared.consistent:
        return stored, None
    try:
        bits_stored = int(ds.get("BitsStored", 8 * stored.dtype.itemsize) or 8 * stored.dtype.itemsize)
    except (TypeError, ValueError):
        bits_stored = 8 * stored.dtype.itemsize
    bits_stored = min(max(bits_stored, 2), 8 * stored.dtype.itemsize)
    other_values = _other_signedness(stored, signed, bits_stored)
    other = _reading(other_values[None] if other_values.ndim == 2 else other_values, not signed, rescales)
    if not other.consistent:
        raise InvalidValueError(
            f"{path}: the CT numbers are impossible read either way: {declared.describe()}, {other.describe()}; a CT "
            f"holds air near -1000 HU and water near 0 HU, within {CT_MIN_HU:g} to {CT_MAX_HU:g} HU: check Pixel "
            "Representation, Bits Stored and the rescale, or re-export the series")
    return other_values, (declared, other)

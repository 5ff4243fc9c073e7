"""Errors raised while reading images, structure sets and plans."""

from __future__ import annotations

from plugins.errors import ReachplanError


class ImagingError(ReachplanError):
    """Base of the imaging errors."""


class NoDicomError(ImagingError):
    """A path holds no readable DICOM object of the kind asked for."""


class CorruptFileError(ImagingError):
    """A file is truncated or is not valid DICOM."""


class SeriesError(ImagingError):
    """A series cannot be assembled into one regular volume (missing slices, duplicates, tilt, ...)."""


class ReferenceMismatchError(ImagingError):
    """An object refers to another series or Frame of Reference than the one it is used with."""


class StructureError(ImagingError):
    """A structure is missing, empty or cannot be turned into a mask or mesh."""

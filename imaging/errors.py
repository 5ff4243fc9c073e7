"""Errors raised while reading images, structure sets and plans."""

from __future__ import annotations

from reachplan import ReachplanError


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


class OutputExistsError(ImagingError):
    """A file that reachplan did not write is in the way of an output; nothing was overwritten."""


class UnsupportedDataError(ImagingError):
    """Valid DICOM that reachplan cannot use (an undecodable transfer syntax, an unsupported layout)."""


class ImagingWarning(UserWarning):
    """Base of the warnings about input that was read but is not quite right."""


class ObliqueSliceWarning(ImagingWarning):
    """Slices step sideways (gantry tilt); the volume's affine carries the shear."""


class DicomQuirkWarning(ImagingWarning):
    """A file breaks a DICOM rule in a way that could be worked around; the message names the quirk."""


class MeshDecimationWarning(ImagingWarning):
    """A mesh could not be decimated to the requested size without losing watertightness."""

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


class OutputPlaceError(ImagingError):
    """A place cannot hold an output: a system file system, no space, read-only, a file where a folder is expected.

    The message names the place as the user gave it (never an internal staging path) and what to do; nothing
    partial is left there.
    """


class OutputBusyError(OutputPlaceError):
    """Another reachplan run is writing to the same output place (it holds the place's lock)."""


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


class InvalidValueError(CorruptFileError):
    """A value is readable but impossible.

    E.g. a negative time, a NaN weight, a pixel data length that does not fit the image's declared size; the
    message names the file, the element and what to do.
    """


class QuestionableValueWarning(ImagingWarning):
    """A value is possible but unlikely to be right; it was used as written (the message says what to check)."""


class CalibrationDateWarning(QuestionableValueWarning):
    """A source's strength reference (calibration) date is far from the plan's date, or cannot be read."""


class DuplicateRoiNameWarning(QuestionableValueWarning):
    """Two or more ROIs have the same name, or names that differ only in case; they are told apart by ROI number."""


class SparseContourWarning(QuestionableValueWarning):
    """A closed contour has fewer than 3 points (1 or 2): it encloses nothing and is left out of masks and volumes."""


class OutsideImageWarning(QuestionableValueWarning):
    """A ROI's contours lie wholly or partly outside the images they are said to be drawn on."""


class SignednessWarning(QuestionableValueWarning):
    """A CT's Pixel Representation (signed or unsigned) gives impossible CT numbers and the other reading does not.

    E.g. a signed CT declared unsigned, whose air reads about 64,536 HU: it was read the other way (the message says
    which slices and what air and water read as).
    """


class SelfIntersectingContourWarning(QuestionableValueWarning):
    """A closed contour crosses itself; masks and volumes fill it by the even-odd rule (each lobe once)."""


class ZeroAreaContourWarning(QuestionableValueWarning):
    """A closed contour of 3 or more points encloses no area (its points on a line); it is left out of masks."""


class UnusablePlanWarning(QuestionableValueWarning):
    """A brachy plan that ``plan`` and ``dose`` refuse (no channels, dwells unknown, no source, no strength, ...).

    ``inspect`` lists it with this warning; the message is the one ``plan`` and ``dose`` stop with.
    """

"""Find DICOM files and open them with pydicom, turning damage into typed errors.

Every reader of the imaging floor opens its files here (:func:`read_dataset`) and wraps its use of the values in
:func:`parsing`, so that a truncated or damaged file is a :class:`~reachplan.imaging.errors.CorruptFileError` that
says what to do, never a pydicom traceback.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pydicom.errors import BytesLengthException

from reachplan.imaging.errors import CorruptFileError, ImagingError, NoDicomError

MEDIA_STORAGE_DIRECTORY = "1.2.840.10008.1.3.10"  # DICOMDIR



def list_files(path: Path) -> list[Path]:
    """List every regular, non-hidden file at ``path`` (itself, or recursively below a folder), sorted.

    Parameters
    ----------
    path : Path
        A file, or a folder walked recursively (hidden files and folders skipped).

    Returns
    -------
    list of Path
        ``[path]`` for a file; the files below a folder, sorted folder by folder.

    Raises
    ------
    NoDicomError
        When ``path`` does not exist.
    """
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise NoDicomError(f"{path} does not exist; give a DICOM file or a folder that holds DICOM files")
    out = []
    for root, dirs, files in os.walk(path):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        out += [Path(root) / f for f in sorted(files) if not f.startswith(".")]
    return out


def _looks_like_dicom(path: Path) -> bool:
    """Tell whether the file claims to be DICOM: ``DICM`` magic at byte 128 or a ``.dcm`` name."""
    if path.suffix.lower() in (".dcm", ".dicom"):
        return True
    try:
        with path.open("rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def corrupt_error(path: Path, what: str) -> CorruptFileError:
    """Build the error for a file that is truncated or damaged: ``what`` is wrong, re-export or remove it.

    Parameters
    ----------
    path : Path
        The damaged file.
    what : str
        What is wrong with it.

    Returns
    -------
    CorruptFileError
        The error to raise, its message telling the user to re-export or remove the file.
    """
    return CorruptFileError(f"{path}: {what}; the file is truncated or damaged: re-export it or remove it")


def invalid_error(path: Path, what: str) -> CorruptFileError:
    """Build the error for a file that breaks the DICOM standard: ``what`` is wrong, fix or re-export it.

    Parameters
    ----------
    path : Path
        The offending file: it breaks the standard.
    what : str
        Which value breaks it.

    Returns
    -------
    CorruptFileError
        The error to raise, its message telling the user to fix or re-export the file.
    """
    return CorruptFileError(f"{path}: {what}; the file breaks the DICOM standard: fix or re-export it")


#: SOP classes read by reachplan whose objects must carry a Modality (General or RT Series module, type 1); one
#: without it was cut short (at an element boundary, where no length check sees it) or mis-edited.
NEEDS_MODALITY = {
    "1.2.840.10008.5.1.4.1.1.2": "CT Image", "1.2.840.10008.5.1.4.1.1.2.1": "Enhanced CT Image",
    "1.2.840.10008.5.1.4.1.1.4": "MR Image", "1.2.840.10008.5.1.4.1.1.4.1": "Enhanced MR Image",
    "1.2.840.10008.5.1.4.1.1.481.2": "RT Dose", "1.2.840.10008.5.1.4.1.1.481.3": "RT Structure Set",
    "1.2.840.10008.5.1.4.1.1.481.5": "RT Plan", "1.2.840.10008.5.1.4.1.1.481.8": "RT Ion Plan",
}

DEFLATED = frozenset({"1.2.840.10008.1.2.1.99", "1.2.840.10008.1.2.8.1"})  # Deflated Explicit VR LE, Deflated Image


def _check_complete(ds: Any, path: Path) -> None:
    """Raise :class:`CorruptFileError` when the last element of ``ds`` runs past the end of the file.

    Deflated files are not checked here: their element offsets count in the inflated stream, and a truncated
    deflate stream already fails while pydicom reads it.
    """
    if str(getattr(getattr(ds, "file_meta", None), "get", lambda *_: "")("TransferSyntaxUID", "")) in DEFLATED:
        return
    size = path.stat().st_size
    tags = list(ds.keys())
    if not tags:
        raise corrupt_error(path, "no data elements after the file meta header")
    elem = ds.get_item(tags[-1], keep_deferred=True)
    tell = getattr(elem, "value_tell", None)
    length = getattr(elem, "length", None)
    if tell is not None and length is not None and length != 0xFFFFFFFF and tell + length > size:
        raise corrupt_error(path, f"element {elem.tag} needs {tell + length} bytes but the file has {size}")
    if tell is not None and length is not None and length != 0xFFFFFFFF and tell + length < size:
        # bytes after the last element that pydicom skipped (fewer than an element header): bytes were inserted
        # into a value (pixel data shifted) or appended
        raise corrupt_error(path, f"{size - tell - length} byte(s) follow the last element {elem.tag}, which ends "
                                  f"at byte {tell + length} of {size}; bytes were inserted or appended")
    if length == 0xFFFFFFFF and getattr(ds, "is_little_endian", True):
        with path.open("rb") as fh:  # an undefined-length sequence must end with its delimiter
            fh.seek(max(0, size - 8))
            if fh.read() != b"\xfe\xff\xdd\xe0\x00\x00\x00\x00":
                raise corrupt_error(path, f"sequence {elem.tag} has no end delimiter")


def read_dataset(
    path: Path, *, header_only: bool = False, required: bool = False, defer_size: int | None = None
) -> Any:
    """Read one DICOM file with pydicom.

    Returns ``None`` for a file that does not claim to be DICOM (no ``DICM`` magic, no ``.dcm`` name) and
    cannot be read as DICOM. A file that claims to be DICOM but cannot be read is an error.

    Parameters
    ----------
    path : Path
        The file.
    header_only : bool
        Stop before the pixel data (no completeness check).
    required : bool
        A file that is not DICOM at all is an error too (:class:`NoDicomError`).
    defer_size : int, optional
        Values longer than this many bytes are read from the file only when used.

    Returns
    -------
    pydicom.Dataset or None

    Raises
    ------
    CorruptFileError
        The file claims to be DICOM (or is parsed as such) but is truncated or cannot be parsed.
    NoDicomError
        With ``required``: the file is not DICOM.
    """
    from pydicom import dcmread
    from pydicom.errors import InvalidDicomError

    claims = _looks_like_dicom(path)
    try:
        ds = dcmread(path, stop_before_pixels=header_only, defer_size=defer_size)
    except InvalidDicomError:
        if not claims:
            if required:
                raise NoDicomError(f"{path} is not a DICOM file; give a DICOM file or folder") from None
            return None
        try:  # a DICOM dataset without preamble / file meta is still readable
            ds = dcmread(path, stop_before_pixels=header_only, defer_size=defer_size, force=True)
        except Exception as exc:
            raise corrupt_error(path, f"cannot be parsed as DICOM ({type(exc).__name__})") from None
        if "SOPClassUID" not in ds:
            raise corrupt_error(path, "has no DICOM preamble and no SOP Class UID") from None
    except PARSE_ERRORS as exc:
        raise corrupt_error(path, f"cannot be parsed as DICOM ({type(exc).__name__}: {one_line(exc)})") from None
    if not header_only:
        _check_complete(ds, path)
    with parsing(path):
        media_class = str(getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or "")
        if "SOPClassUID" not in ds and "Modality" not in ds and media_class != MEDIA_STORAGE_DIRECTORY:
            raise corrupt_error(path, "has neither SOP Class UID nor Modality")
        _ = ds.get("Modality"), ds.get("SOPClassUID")  # the values every caller looks at first
        kind = NEEDS_MODALITY.get(str(ds.get("SOPClassUID", "") or media_class))
        if kind is not None and not str(ds.get("Modality", "") or "").strip():
            last = list(ds.keys())[-1]
            raise corrupt_error(path, f"an {kind} object without Modality (0008,0060), which every {kind} has (its "
                                      f"last element is {last})")
    return ds


#: What pydicom raises on damaged bytes, when a file is read or when its values are first used.
PARSE_ERRORS: tuple[type[Exception], ...] = (
    OSError, EOFError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError, struct.error,
    NotImplementedError, RuntimeError, BytesLengthException, zlib.error, MemoryError,
)


@contextmanager
def parsing(path: Path) -> Iterator[None]:
    """Turn pydicom's errors on damaged values met while using a dataset into :class:`CorruptFileError`.

    Parameters
    ----------
    path : Path
        The file the dataset came from (named in the message).

    Yields
    ------
    None
        While the block runs; imaging errors pass through unchanged.
    """
    try:
        yield
    except ImagingError:
        raise
    except PARSE_ERRORS as exc:
        raise corrupt_error(path, f"a value cannot be parsed ({type(exc).__name__}: {one_line(exc)})") from None


def one_line(exc: BaseException, limit: int = 160) -> str:
    """Return ``exc``'s message on one line, without the traceback pydicom embeds in nested errors.

    The chain of "With tag X got exception:" prefixes is kept as the path of tags to the damaged element.

    Parameters
    ----------
    exc : BaseException
        The exception.
    limit : int
        Longest message kept, characters; a longer one is cut and ends in ``...``.

    Returns
    -------
    str
        The message, whitespace collapsed.
    """
    text = " ".join(str(exc).split("Traceback (most recent call last)")[0].split())
    return text if len(text) <= limit else text[: limit - 3] + "..."

"""The pixel data of one image object as stored values: fast paths for native data, pydicom, then GDCM.

The description of the pixels (bits, rows, columns, frames) is checked against the bytes first
(:func:`check_pixel_length`), so a damaged header is an error rather than a garbled volume.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.dicom_files import corrupt_error, invalid_error, one_line, parsing
from reachplan.imaging.errors import InvalidValueError, UnsupportedDataError
from reachplan.imaging.series_geometry import rescale

_NATIVE_LE = frozenset({"1.2.840.10008.1.2", "1.2.840.10008.1.2.1"})


def _native_pixels(ds: Any, path: Path) -> np.ndarray | None:
    """Uncompressed little-endian single-frame grey pixels straight from the bytes; None when not that simple."""
    meta = getattr(ds, "file_meta", None)
    if meta is None or str(meta.get("TransferSyntaxUID", "")) not in _NATIVE_LE:
        return None
    try:
        bits, stored = int(ds.BitsAllocated), int(ds.BitsStored)
        rows, cols, signed = int(ds.Rows), int(ds.Columns), int(ds.PixelRepresentation) == 1
        spp, frames = int(ds.get("SamplesPerPixel", 1)), int(ds.get("NumberOfFrames", 1) or 1)
    except (AttributeError, TypeError, ValueError):
        return None
    if bits not in (8, 16, 32) or stored != bits or spp != 1 or frames != 1 or "PixelData" not in ds:
        return None
    dtype = np.dtype(f"<{'i' if signed else 'u'}{bits // 8}")
    n = rows * cols
    elem = ds.get_item(0x7FE00010, keep_deferred=True)
    if getattr(elem, "value", b"") is None and getattr(elem, "length", 0) >= n * dtype.itemsize:
        # deferred: read the pixels from the file without keeping a copy in the dataset
        arr = np.fromfile(path, dtype=dtype, count=n, offset=int(elem.value_tell))
        return arr.reshape(rows, cols) if arr.size == n else None
    data = ds.PixelData
    if len(data) < n * dtype.itemsize:
        return None  # let pydicom explain what is wrong
    return np.frombuffer(data, dtype=dtype, count=n).reshape(rows, cols)


_NATIVE = _NATIVE_LE | {"1.2.840.10008.1.2.2", "1.2.840.10008.1.2.1.99"}  # + big endian, deflated


def check_pixel_length(ds: Any, path: Path) -> None:
    """Check that the pixel description is coherent and fits the pixel data.

    BitsAllocated 1, 8, 16, 32 or 64; BitsStored <= BitsAllocated; HighBit = BitsStored - 1; and, for
    uncompressed pixel data, its length must be exactly Rows x Columns x frames x samples x BitsAllocated / 8 (plus
    the one padding byte that makes an odd length even): a BitsAllocated of 8 on 16-bit data, or a byte inserted
    into the pixels, would otherwise give a garbled volume.

    Parameters
    ----------
    ds : pydicom.Dataset
        An image object (its pixel data is not decoded).
    path : Path
        Its file (named in the message).

    Raises
    ------
    InvalidValueError
    """
    with parsing(path):
        bits = int(ds.get("BitsAllocated", 16) or 16)
        stored = int(ds.get("BitsStored", bits) or bits)
        high = ds.get("HighBit")
        high = stored - 1 if high in (None, "") else int(high)
        rows, cols = int(ds.Rows), int(ds.Columns)
        n = rows * cols * int(ds.get("NumberOfFrames", 1) or 1) * int(ds.get("SamplesPerPixel", 1) or 1)
    if bits not in (1, 8, 16, 32, 64) or not (1 <= stored <= bits) or high != stored - 1:
        raise InvalidValueError(
            f"{path}: BitsAllocated {bits}, BitsStored {stored}, HighBit {high} do not describe valid pixels "
            "(BitsStored <= BitsAllocated, HighBit = BitsStored - 1); fix the header or re-export the image")
    meta = getattr(ds, "file_meta", None)
    if meta is None or str(meta.get("TransferSyntaxUID", "")) not in _NATIVE:
        return
    with parsing(path):
        elem = ds.get_item(0x7FE00010, keep_deferred=True) if 0x7FE00010 in ds else None
        if elem is None:
            raise invalid_error(path, "the image has no Pixel Data")
        length = getattr(elem, "length", None)
        if length is None or (length == 0xFFFFFFFF and getattr(elem, "value", None) is not None):
            length = len(elem.value or b"")
    need = (n * bits + 7) // 8
    if length != 0xFFFFFFFF and length != need and not (need % 2 and length == need + 1):
        raise InvalidValueError(
            f"{path}: pixel data (7FE0,0010) has {length} bytes but Rows {rows} x Columns {cols} x frames x samples at "
            f"BitsAllocated {bits} need {need}{' (+1 padding byte)' if need % 2 else ''}; the header does not describe "
            "the pixels (damaged or mis-edited BitsAllocated, Rows or Columns, or bytes inserted): re-export the image")


def _sitk_pixels(ds: Any, path: Path) -> np.ndarray | None:
    """Decode a single-frame image with SimpleITK (GDCM) into stored values; None when it cannot.

    GDCM applies the rescale slope and intercept; they are undone here so that every decoder returns stored
    values and the rescale is applied in one place.
    """
    if int(ds.get("NumberOfFrames", 1) or 1) != 1:
        return None
    try:
        import SimpleITK as sitk

        reader = sitk.ImageFileReader()
        reader.SetImageIO("GDCMImageIO")
        reader.SetFileName(str(path))
        arr = sitk.GetArrayFromImage(reader.Execute())
    except (ImportError, RuntimeError):
        return None
    arr = arr.reshape(arr.shape[-2:]) if arr.ndim == 3 and arr.shape[0] == 1 else arr
    if arr.ndim != 2:
        return None
    slope, intercept = rescale(ds, path)
    if slope != 1 or intercept != 0:
        arr = np.rint((arr.astype(np.float64) - intercept) / slope)
    return arr


def read_pixels(ds: Any, path: Path) -> np.ndarray:
    """Decode the pixel data of one image object into stored values (no rescale applied).

    Native little-endian single-frame data is read straight from the bytes; anything else goes through pydicom,
    then SimpleITK (GDCM) when pydicom has no decoder.

    Parameters
    ----------
    ds : pydicom.Dataset
        The object's dataset (pixel data possibly deferred).
    path : Path
        Its file.

    Returns
    -------
    (rows, columns) or (frames, rows, columns) array
        Stored values, dtype as stored.

    Raises
    ------
    UnsupportedDataError
        No decoder for the transfer syntax, or pixel data that is not a grey-level image.
    CorruptFileError
        The pixel data cannot be read.
    """
    fast = _native_pixels(ds, path)
    if fast is not None:
        return fast
    try:
        arr = ds.pixel_array
    except (NotImplementedError, RuntimeError) as exc:
        arr = _sitk_pixels(ds, path)  # GDCM inside SimpleITK decodes JPEG lossless, JPEG-LS, ...
        if arr is None:
            ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "unknown")
            raise UnsupportedDataError(
                f"{path}: neither pydicom nor SimpleITK can decode pixel data with transfer syntax {ts} "
                f"({one_line(exc, 80)}); install a pydicom decoder plugin (e.g. pylibjpeg) or decompress the series"
            ) from None
    except (ValueError, AttributeError, KeyError, TypeError, EOFError, OSError) as exc:
        raise corrupt_error(path, f"pixel data cannot be read ({one_line(exc, 100)})") from None
    if arr.ndim not in (2, 3) or np.iscomplexobj(arr):
        raise UnsupportedDataError(f"{path}: pixel data of shape {arr.shape} is not a grey-level image")
    return arr

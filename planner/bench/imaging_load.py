"""Benchmark: loading a CT series with :func:`reachplan.imaging.dicom_io.read_series` against SimpleITK's series reader.

Writes a synthetic uncompressed CT series (default 300 slices of 512 x 512, int16, rescale slope and
intercept) into a work folder, then loads it alternately with both readers, each run in a fresh Python
process (imports excluded from the timing), after one warm-up run each (warm file cache). Records wall time,
CPU time and peak resident memory (``ru_maxrss`` of the child process).

Run: ``reachplan bench imaging --out DIR [--quick] [--slices N] [--size N] [--repeat N] [--install]``.
Writes ``imaging_load.csv`` and ``imaging_load.png`` under ``--out`` (``--install`` copies both to ``docs/``);
prints the ratio of medians. The acceptance target (issue 4) is ours <= 1.2 x SimpleITK's time and < 1 GB peak.
``--quick``: 12 slices of 64 x 64, one run each.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.common import BenchError, settings, write_csv, write_png

INSTALLS = {"imaging_load.csv": "docs/imaging_load.csv", "imaging_load.png": "docs/imaging_load.png"}
COLUMNS = ("reader", "run", "wall_s", "cpu_s", "peak_mb")
READERS = ("reachplan", "simpleitk")


@dataclass(frozen=True)
class ImagingSettings:
    """How big a series to load and how often.

    Parameters
    ----------
    slices : int
        Images in the series, one per slice.
    size : int
        Rows and columns of each slice (int16 pixels).
    repeat : int
        Alternating runs per reader.
    workdir : Path or None
        Where the series is written (``None``: a temporary folder).
    """

    slices: int = 300
    size: int = 512
    repeat: int = 5
    workdir: Path | None = None


QUICK = ImagingSettings(slices=12, size=64, repeat=1)

_CHILD = r"""
import json, resource, sys, time
folder, which = sys.argv[1], sys.argv[2]
if which == "reachplan":
    from reachplan.imaging.dicom_io import read_series
    import pydicom.pixels  # noqa: F401  (imports outside the timing)
else:
    import SimpleITK as sitk
t0, c0 = time.perf_counter(), time.process_time()
if which == "reachplan":
    v = read_series(folder)
    shape, checksum = v.array.shape, float(v.array[::7, ::5, ::3].sum(dtype="float64"))
else:
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(folder))
    img = reader.Execute()
    arr = sitk.GetArrayViewFromImage(img)
    shape, checksum = arr.shape, float(arr[::7, ::5, ::3].sum(dtype="float64"))
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "shape": list(shape), "checksum": checksum}))
"""


def write_ct(folder: Path, slices: int, size: int) -> None:
    """Write a plain CT series: 0.8 mm pixels, 1 mm slices, files named in reverse slice order.

    Parameters
    ----------
    folder : Path
        Where to write (created).
    slices : int
        Number of slices.
    size : int
        Rows and columns per slice.
    """
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import UID, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    base = (rng.normal(0, 40, (size, size)) + 1000).astype(np.int16)
    series, study, frame = (generate_uid(prefix=None) for _ in range(3))
    for k in range(slices):
        uid = generate_uid(prefix=None)
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = UID("1.2.840.10008.5.1.4.1.1.2")
        meta.MediaStorageSOPInstanceUID = UID(uid)
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = meta.MediaStorageSOPClassUID, uid, "CT"
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.PatientName, ds.PatientID, ds.InstanceNumber = "Bench", "B", k + 1
        ds.ImagePositionPatient = [-204.8, -204.8, 100.0 - k]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing, ds.SliceThickness = [0.8, 0.8], 1.0
        ds.Rows = ds.Columns = size
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = np.roll(base, k, axis=0).tobytes()
        ds.save_as(folder / f"IM{slices - k:05d}.dcm", enforce_file_format=True)


def run_child(folder: Path, which: str) -> dict[str, float]:
    """Load the series in ``folder`` with ``which`` reader in a fresh process.

    Parameters
    ----------
    folder : Path
        The folder holding the series.
    which : str
        ``reachplan`` or ``simpleitk``.

    Returns
    -------
    dict of str to float
        ``wall_s`` and ``cpu_s`` (s), ``peak_mb`` (MB), the array's ``shape`` and a ``checksum``.
    """
    res = subprocess.run([sys.executable, "-c", _CHILD, str(folder), which], capture_output=True, text=True,
                         check=True)
    out: dict[str, float] = json.loads(res.stdout.strip().splitlines()[-1])
    return out


def measure(s: ImagingSettings) -> list[dict[str, object]]:
    """Write the series and load it with both readers; one row per run and reader.

    Parameters
    ----------
    s : ImagingSettings
        Series size and runs.

    Returns
    -------
    list of dict of str to object
        Each row holds :data:`COLUMNS` and the shape and checksum the child read.

    Raises
    ------
    BenchError
        The two readers disagree on the voxel values.
    """
    with tempfile.TemporaryDirectory(dir=s.workdir) as tmp:
        folder = Path(tmp) / "ct"
        write_ct(folder, s.slices, s.size)
        for which in READERS:  # warm-up (file cache, imports compiled)
            run_child(folder, which)
        rows: list[dict[str, object]] = []
        for r in range(s.repeat):
            for which in READERS:
                rows.append({"reader": which, "run": r, **run_child(folder, which)})
    checks = {str(row["reader"]): float(row["checksum"]) for row in rows}  # type: ignore[arg-type]
    if abs(checks["reachplan"] - checks["simpleitk"]) > 1e-6 * max(1.0, abs(checks["simpleitk"])):
        raise BenchError(f"the readers disagree on the voxel values ({checks}): a reader bug, report it")
    return rows


def medians(rows: list[dict[str, object]]) -> dict[str, dict[str, float]]:
    """Return the median of ``wall_s``, ``cpu_s`` and ``peak_mb`` per reader.

    Parameters
    ----------
    rows : list of dict of str to object
        The rows of :func:`measure`.

    Returns
    -------
    dict of str to dict of str to float
        Metric -> reader -> median (s or MB).
    """
    return {m: {rd: float(np.median([float(row[m]) for row in rows if row["reader"] == rd]))  # type: ignore[arg-type]
                for rd in READERS} for m in ("wall_s", "cpu_s", "peak_mb")}


def write_results(out: Path, rows: list[dict[str, object]], title: str) -> None:
    """Write ``imaging_load.csv`` (:data:`COLUMNS`) and ``imaging_load.png`` (time, peak memory per reader).

    Parameters
    ----------
    out : Path
        The results folder.
    rows : list of dict of str to object
        The rows of :func:`measure`.
    title : str
        The figure's title.
    """
    write_csv(out / "imaging_load.csv", COLUMNS, rows)
    med = medians(rows)
    fig = Figure(figsize=(8, 3.2))
    axes = fig.subplots(1, 2)
    for ax, metric, label in ((axes[0], "wall_s", "load time (s)"), (axes[1], "peak_mb", "peak memory (MB)")):
        for i, rd in enumerate(READERS):
            vals = [float(row[metric]) for row in rows if row["reader"] == rd]  # type: ignore[arg-type]
            ax.scatter(np.full(len(vals), i), vals, s=12, alpha=0.6, color=f"C{i}")
            ax.bar(i, med[metric][rd], alpha=0.4, color=f"C{i}")
        ax.set_xticks(range(len(READERS)), READERS)
        ax.set_ylabel(label)
    axes[1].axhline(1024, color="r", lw=0.8, ls="--")
    fig.suptitle(title)
    fig.tight_layout()
    write_png(out / "imaging_load.png", fig, dpi=120)


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench imaging`` (``--quick``, ``--slices``, ``--size``, ``--repeat``, ``--workdir``).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options: ``out``, ``quick``, ``slices``, ``size``, ``repeat``, ``workdir``.

    Returns
    -------
    int
        Zero; the medians are printed.
    """
    s = settings(args, ImagingSettings(), QUICK)
    rows = measure(s)
    write_results(args.out, rows, f"CT series {s.slices} x {s.size}² (median of {s.repeat})")
    med = medians(rows)
    print(f"{s.slices} x {s.size} x {s.size} CT, median of {s.repeat} runs")
    for rd in READERS:
        print(f"  {rd:10s} wall {med['wall_s'][rd]:.2f} s  cpu {med['cpu_s'][rd]:.2f} s  "
              f"peak {med['peak_mb'][rd]:.0f} MB")
    print(f"  ratio reachplan / SimpleITK: wall {med['wall_s']['reachplan'] / med['wall_s']['simpleitk']:.2f}, "
          f"cpu {med['cpu_s']['reachplan'] / med['cpu_s']['simpleitk']:.2f}")
    return 0

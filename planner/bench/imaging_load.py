"""Benchmark: loading a CT series with :func:`reachplan.imaging.dicom_io.read_series` against SimpleITK's series reader.

Writes a synthetic uncompressed CT series (default 300 slices of 512 x 512, int16, rescale slope and
intercept) into a work folder, then loads it alternately with both readers, each run in a fresh Python
process (imports excluded from the timing), after one warm-up run each (warm file cache). Records wall time,
CPU time and peak resident memory (``ru_maxrss`` of the child process).

Usage::

    python benchmarks/imaging_load.py --out results/imaging_load [--slices 300] [--size 512] [--repeat 5]

Writes ``imaging_load.csv`` and ``imaging_load.png`` under ``--out``; prints the ratio of medians. The
acceptance target (issue 4) is ours <= 1.2 x SimpleITK's time and < 1 GB peak.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

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
    """A plain CT series: 0.8 mm pixels, 1 mm slices, files named in reverse slice order."""
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
    res = subprocess.run([sys.executable, "-c", _CHILD, str(folder), which], capture_output=True, text=True,
                         check=True)
    out: dict[str, float] = json.loads(res.stdout.strip().splitlines()[-1])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--slices", type=int, default=300)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workdir", type=Path, default=None, help="where to write the series (default: a temp dir)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        folder = Path(tmp) / "ct"
        write_ct(folder, args.slices, args.size)
        readers = ("reachplan", "simpleitk")
        for which in readers:  # warm-up (file cache, imports compiled)
            run_child(folder, which)
        rows = []
        for r in range(args.repeat):
            for which in readers:
                rows.append({"reader": which, "run": r, **run_child(folder, which)})
    checks = {row["reader"]: row["checksum"] for row in rows}
    if abs(checks["reachplan"] - checks["simpleitk"]) > 1e-6 * max(1.0, abs(checks["simpleitk"])):
        raise SystemExit(f"the readers disagree on the voxel values: {checks}")
    with (args.out / "imaging_load.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["reader", "run", "wall_s", "cpu_s", "peak_mb"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    med = {m: {rd: float(np.median([row[m] for row in rows if row["reader"] == rd])) for rd in readers}
           for m in ("wall_s", "cpu_s", "peak_mb")}
    print(f"{args.slices} x {args.size} x {args.size} CT, median of {args.repeat} runs")
    for rd in readers:
        print(f"  {rd:10s} wall {med['wall_s'][rd]:.2f} s  cpu {med['cpu_s'][rd]:.2f} s  "
              f"peak {med['peak_mb'][rd]:.0f} MB")
    print(f"  ratio reachplan / SimpleITK: wall {med['wall_s']['reachplan'] / med['wall_s']['simpleitk']:.2f}, "
          f"cpu {med['cpu_s']['reachplan'] / med['cpu_s']['simpleitk']:.2f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    for ax, metric, label in ((axes[0], "wall_s", "load time (s)"), (axes[1], "peak_mb", "peak memory (MB)")):
        for i, rd in enumerate(readers):
            vals = [row[metric] for row in rows if row["reader"] == rd]
            ax.scatter(np.full(len(vals), i), vals, s=12, alpha=0.6)
            ax.bar(i, med[metric][rd], alpha=0.4)
        ax.set_xticks(range(len(readers)), readers)
        ax.set_ylabel(label)
    axes[1].axhline(1024, color="r", lw=0.8, ls="--")
    fig.suptitle(f"CT series {args.slices} x {args.size}² (median of {args.repeat})")
    fig.tight_layout()
    fig.savefig(args.out / "imaging_load.png", dpi=120)


if __name__ == "__main__":
    main()

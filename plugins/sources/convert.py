"""Re-write the consensus TG-43 tables of ``reference/tg43/<source>/`` as this package's JSON data.

Run once by a maintainer (``python -m reachplan.plugins.sources.convert REFERENCE_TG43_DIR``); the runtime only
reads the JSON files beside this module. The conversion keeps the published numbers and drops
the ``r = 0`` row/column that the reference CSVs carry as a copy of the first measured distance: the
kernel applies the same nearest-neighbour rule explicitly (see :mod:`reachplan.planner.dose.tg43`).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

FORMAT = "reachplan-tg43/1"

#: Strings that identify the source in a DICOM RT Plan (Source Isotope Name, Treatment Machine Name,
#: Source Manufacturer), compared case-insensitively with spaces, dashes and underscores removed.
ALIASES: dict[str, tuple[str, ...]] = {
    "flexisource_hdr": ("flexisource",),
    "gammamed_plus_hdr": ("gammamedplushdr", "gammamedhdrplus"),
    "gammamed_plus_pdr": ("gammamedpluspdr", "gammamedpdrplus"),
    "spec_m19_hdr": ("m19", "specm19"),
    "varisource_vs2000_hdr": ("vs2000", "varisource"),
}


def _drop_duplicate_r0(r: list[float], cols: list[list[float]]) -> tuple[list[float], list[list[float]]]:
    if len(r) > 1 and r[0] == 0.0 and cols[0] == cols[1]:
        return r[1:], cols[1:]
    return r, cols


def convert_one(src: Path) -> dict[str, object]:
    """Convert one source folder of the reference into this package's JSON document.

    Parameters
    ----------
    src : Path
        ``reference/tg43/<source>/`` with ``params.json``, ``radial_dose_gL.csv`` (r in cm, g_L) and
        ``anisotropy_F.csv`` (θ in degrees by row, ``r=<cm>cm`` by column); the folder name is the plugin name.

    Returns
    -------
    dict
        The ``reachplan-tg43/1`` document; radii in cm, angles in degrees, Λ in cGy h⁻¹ U⁻¹.
    """
    params = json.loads((src / "params.json").read_text())
    with (src / "radial_dose_gL.csv").open() as f:
        rows = [row for row in csv.reader(f)][1:]
    g_r = [float(a) for a, _ in rows]
    g = [float(b) for _, b in rows]
    g_r2, g_cols = _drop_duplicate_r0(g_r, [[v] for v in g])
    with (src / "anisotropy_F.csv").open() as f:
        table = list(csv.reader(f))
    f_r = [float(h.removeprefix("r=").removesuffix("cm")) for h in table[0][1:]]
    theta = [float(row[0]) for row in table[1:]]
    values = [[float(v) for v in row[1:]] for row in table[1:]]
    columns = [[values[i][j] for i in range(len(theta))] for j in range(len(f_r))]
    f_r2, columns = _drop_duplicate_r0(f_r, columns)
    values2 = [[columns[j][i] for j in range(len(f_r2))] for i in range(len(theta))]
    return {
        "format": FORMAT,
        "citation": params["source"],
        "converted_from": f"reference/tg43/{src.name} ({params['sheet_title']})",
        "name": src.name,
        "title": params["name"],
        "kind": params["kind"],
        "isotope": params["isotope"],
        "dose_rate_constant_cgy_per_h_per_u": params["dose_rate_constant_cGy_per_h_per_U"],
        "active_length_cm": params["active_length_cm"],
        "aliases": list(ALIASES.get(src.name, ())),
        "radial_dose": {"r_cm": g_r2, "g_l": [c[0] for c in g_cols]},
        "anisotropy": {"r_cm": f_r2, "theta_deg": theta, "f": values2},
    }


def dumps(doc: dict[str, object]) -> str:
    """Format ``doc`` as JSON with one key per line and each table row on one line (readable diffs)."""

    def block(value: object, indent: str) -> str:
        if isinstance(value, dict):
            inner = ",\n".join(f"{indent} {json.dumps(k)}: {block(v, indent + ' ')}" for k, v in value.items())
            return "{\n" + inner + "\n" + indent + "}"
        if isinstance(value, list) and value and isinstance(value[0], list):
            rows = ",\n".join(f"{indent} {json.dumps(r)}" for r in value)
            return "[\n" + rows + "\n" + indent + "]"
        return json.dumps(value)

    return block(doc, "") + "\n"


def main(argv: list[str] | None = None) -> int:
    """Convert every source folder of the directory given in ``argv``; return the exit status (2: usage)."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m plugins.sources.convert REFERENCE_TG43_DIR", file=sys.stderr)
        return 2
    out = Path(__file__).parent
    for src in sorted(p for p in Path(args[0]).iterdir() if p.is_dir()):
        doc = convert_one(src)
        (out / f"{src.name}.json").write_text(dumps(doc))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

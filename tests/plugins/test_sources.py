"""Built-in TG-43 data sets: loaders, validation, and faithfulness to the reference tables."""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reachplan.plugins.errors import PluginError
from reachplan.plugins.sources import BUILTIN, SourceData, load_builtin

NAMES = sorted(BUILTIN)


def test_five_builtins_load_with_citation() -> None:
    assert len(NAMES) == 5
    for name in NAMES:
        src = BUILTIN[name]()
        assert isinstance(src, SourceData)
        assert src.name == name
        assert "Perez-Calatayud" in src.citation
        assert src.isotope == "Ir-192"
        # g_L(1 cm) = 1 and F(r, 90°) = 1 by definition
        assert np.interp(1.0, src.radial_r_cm, src.radial_g) == pytest.approx(1.0)
        assert np.allclose(src.anisotropy_f[src.anisotropy_theta_deg == 90.0], 1.0)


def test_source_data_is_frozen() -> None:
    src = BUILTIN["gammamed_plus_hdr"]()
    with pytest.raises(ValueError):
        src.radial_g[0] = 2.0
    with pytest.raises(AttributeError):
        src.name = "x"  # type: ignore[misc]


def test_unknown_builtin_is_plugin_error() -> None:
    with pytest.raises(PluginError, match="built-ins"):
        load_builtin("nope")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"active_length_cm": 0.0}, "active length"),
        ({"dose_rate_constant": -1.0}, "dose rate constant"),
        ({"radial_r_cm": [1.0, 0.5], "radial_g": [1.0, 1.0]}, "increasing"),
        ({"anisotropy_theta_deg": [0.0, 90.0], "anisotropy_f": [[1.0], [1.0]], "anisotropy_r_cm": [1.0]},
         "0 to 180"),
        ({"radial_g": [1.0, np.nan]}, "positive and finite"),
    ],
)
def test_validation(change: dict[str, object], match: str) -> None:
    base: dict[str, object] = dict(
        name="t", title="t", kind="HDR", isotope="Ir-192", dose_rate_constant=1.1, active_length_cm=0.35,
        radial_r_cm=[0.5, 1.0], radial_g=[1.0, 1.0], anisotropy_r_cm=[1.0],
        anisotropy_theta_deg=[0.0, 180.0], anisotropy_f=[[1.0], [1.0]], citation="c",
    )
    base.update(change)
    with pytest.raises(ValueError, match=match):
        SourceData(**base)  # type: ignore[arg-type]


def test_from_json_rejects_other_format() -> None:
    with pytest.raises(ValueError, match="reachplan-tg43"):
        SourceData.from_json(json.dumps({"format": "x"}))


@pytest.mark.parametrize("name", NAMES)
def test_package_data_matches_reference(reference_file: Callable[[str], Path], name: str) -> None:
    """The re-written tables carry the published numbers (the r = 0 copies dropped)."""
    params = json.loads(reference_file(f"tg43/{name}/params.json").read_text())
    src = BUILTIN[name]()
    assert src.dose_rate_constant == params["dose_rate_constant_cGy_per_h_per_U"]
    assert src.active_length_cm == params["active_length_cm"]
    rows = list(csv.reader(reference_file(f"tg43/{name}/radial_dose_gL.csv").read_text().splitlines()))[1:]
    r = np.array([float(a) for a, _ in rows])
    g = np.array([float(b) for _, b in rows])
    assert np.array_equal(np.interp(r[r > 0], src.radial_r_cm, src.radial_g), g[r > 0])
    table = list(csv.reader(reference_file(f"tg43/{name}/anisotropy_F.csv").read_text().splitlines()))
    fr = np.array([float(h[2:-2]) for h in table[0][1:]])
    f = np.array([[float(v) for v in row[1:]] for row in table[1:]])
    theta = np.array([float(row[0]) for row in table[1:]])
    assert np.array_equal(theta, src.anisotropy_theta_deg)
    cols = [np.flatnonzero(src.anisotropy_r_cm == x)[0] for x in fr[fr > 0]]
    assert np.array_equal(src.anisotropy_f[:, cols], f[:, fr > 0])
    if fr[0] == 0:  # the dropped column was a copy of the first distance
        assert np.array_equal(f[:, 0], src.anisotropy_f[:, 0])

"""TG-43U1 source data sets (``reachplan.sources`` plugins).

Each built-in loader is a zero-argument callable returning a frozen :class:`SourceData`. The numbers
are the AAPM/ESTRO consensus data (Perez-Calatayud et al., Med. Phys. 39:2904, 2012), re-written from
``reference/tg43/`` into this package's JSON format by :mod:`reachplan.plugins.sources.convert`; each JSON file
carries its citation.

A third-party source registers a callable of the same shape under the entry-point group
``reachplan.sources``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import cache
from importlib import resources

import numpy as np

from reachplan._arrays import frozen_floats
from reachplan.plugins.errors import PluginError

FORMAT = "reachplan-tg43/1"


@dataclass(frozen=True, eq=False)
class SourceData:
    """Consensus TG-43U1 data of one source model (2D line-source formalism).

    Parameters
    ----------
    name : str
        Plugin name, e.g. ``"gammamed_plus_hdr"``.
    title : str
        Human-readable model name.
    kind : str
        ``"HDR"``, ``"PDR"`` or ``"LDR"``.
    isotope : str
        e.g. ``"Ir-192"``.
    dose_rate_constant : float
        Λ, cGy h⁻¹ U⁻¹.
    active_length_cm : float
        L of the line-source geometry function, cm (> 0).
    radial_r_cm : (m,) float, cm
        Strictly increasing radii of the radial dose function table.
    radial_g : (m,) float
        g_L(r) at ``radial_r_cm`` (1 at r = 1 cm).
    anisotropy_r_cm : (nr,) float, cm
        Strictly increasing radii of the anisotropy table.
    anisotropy_theta_deg : (nt,) float, degrees
        Strictly increasing polar angles, covering 0 to 180; θ = 0 points toward the source tip.
    anisotropy_f : (nt, nr) float
        F(r, θ).
    citation : str
        Where the numbers come from.
    aliases : tuple of str
        Normalised strings (lower case, no spaces, dashes or underscores) that identify this source
        in a DICOM RT Plan (Source Isotope Name, Treatment Machine Name).

    Raises
    ------
    ValueError
        A non-positive dose rate constant or active length, tables of the wrong shape, radii or angles not
        strictly increasing, angles not covering 0 to 180 degrees, or g_L or F not positive and finite.
    """

    name: str
    title: str
    kind: str
    isotope: str
    dose_rate_constant: float
    active_length_cm: float
    radial_r_cm: np.ndarray
    radial_g: np.ndarray
    anisotropy_r_cm: np.ndarray
    anisotropy_theta_deg: np.ndarray
    anisotropy_f: np.ndarray
    citation: str
    aliases: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for field in ("radial_r_cm", "radial_g", "anisotropy_r_cm", "anisotropy_theta_deg", "anisotropy_f"):
            object.__setattr__(self, field, frozen_floats(getattr(self, field)))
        if not (self.dose_rate_constant > 0 and np.isfinite(self.dose_rate_constant)):
            raise ValueError(f"source {self.name}: dose rate constant must be positive and finite")
        if not (self.active_length_cm > 0 and np.isfinite(self.active_length_cm)):
            raise ValueError(f"source {self.name}: active length must be positive (cm)")
        r, g = self.radial_r_cm, self.radial_g
        if r.ndim != 1 or r.shape != g.shape or len(r) < 2 or np.any(np.diff(r) <= 0) or r[0] < 0:
            raise ValueError(f"source {self.name}: g_L table needs >= 2 strictly increasing radii >= 0")
        fr, ft, f = self.anisotropy_r_cm, self.anisotropy_theta_deg, self.anisotropy_f
        if fr.ndim != 1 or ft.ndim != 1 or f.shape != (len(ft), len(fr)):
            raise ValueError(f"source {self.name}: F table must be (n_theta, n_r), got {f.shape}")
        if np.any(np.diff(fr) <= 0) or np.any(np.diff(ft) <= 0) or ft[0] != 0 or ft[-1] != 180:
            raise ValueError(f"source {self.name}: F table needs increasing r and θ from 0 to 180 degrees")
        if not (np.all(np.isfinite(g)) and np.all(g > 0) and np.all(np.isfinite(f)) and np.all(f > 0)):
            raise ValueError(f"source {self.name}: g_L and F must be positive and finite")

    @classmethod
    def from_json(cls, text: str) -> SourceData:
        """Parse this package's JSON format (``"format": "reachplan-tg43/1"``).

        Raises
        ------
        ValueError
            Not JSON, another format, or tables that do not validate.
        KeyError
            A required key is missing.
        """
        doc = json.loads(text)
        if doc.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} document (format={doc.get('format')!r})")
        return cls(
            name=doc["name"],
            title=doc["title"],
            kind=doc["kind"],
            isotope=doc["isotope"],
            dose_rate_constant=float(doc["dose_rate_constant_cgy_per_h_per_u"]),
            active_length_cm=float(doc["active_length_cm"]),
            radial_r_cm=doc["radial_dose"]["r_cm"],
            radial_g=doc["radial_dose"]["g_l"],
            anisotropy_r_cm=doc["anisotropy"]["r_cm"],
            anisotropy_theta_deg=doc["anisotropy"]["theta_deg"],
            anisotropy_f=doc["anisotropy"]["f"],
            citation=doc["citation"],
            aliases=tuple(doc.get("aliases", ())),
        )


def normalise_label(text: str) -> str:
    """Case-fold ``text`` and remove spaces, dashes, underscores and dots (for matching DICOM strings)."""
    return re.sub(r"[\s_\-.]+", "", text).casefold()


@cache
def load_builtin(name: str) -> SourceData:
    """Load the built-in data set ``name`` from the package data (cached: the result is immutable).

    Raises
    ------
    PluginError
        No built-in data set ``name``.
    """
    try:
        text = resources.files(__name__).joinpath(f"{name}.json").read_text()
    except FileNotFoundError:
        raise PluginError(f"no built-in TG-43 source {name!r}; built-ins: {', '.join(BUILTIN)}") from None
    return SourceData.from_json(text)


def flexisource_hdr() -> SourceData:
    """Elekta (Isodose Control) Flexisource HDR Ir-192."""
    return load_builtin("flexisource_hdr")


def gammamed_plus_hdr() -> SourceData:
    """Varian GammaMed Plus HDR Ir-192."""
    return load_builtin("gammamed_plus_hdr")


def gammamed_plus_pdr() -> SourceData:
    """Varian GammaMed Plus PDR Ir-192."""
    return load_builtin("gammamed_plus_pdr")


def spec_m19_hdr() -> SourceData:
    """SPEC M-19 HDR Ir-192."""
    return load_builtin("spec_m19_hdr")


def varisource_vs2000_hdr() -> SourceData:
    """Varian VariSource VS2000 HDR Ir-192."""
    return load_builtin("varisource_vs2000_hdr")


#: The built-in loaders by plugin name (the same callables the entry points name).
BUILTIN = {
    "flexisource_hdr": flexisource_hdr,
    "gammamed_plus_hdr": gammamed_plus_hdr,
    "gammamed_plus_pdr": gammamed_plus_pdr,
    "spec_m19_hdr": spec_m19_hdr,
    "varisource_vs2000_hdr": varisource_vs2000_hdr,
}


"""Treatment protocols as data files (``reachplan.protocols`` plugins): each aim's planning value and hard limit.

A protocol is a TOML file (format in ``docs/commands.md``, ``--protocol``); the planner reads it into its aims
(:func:`reachplan.planner.dose.protocol.load_protocol`). This floor only ships the files: each built-in loader is a
zero-argument callable returning a :class:`ProtocolFile` (the file's name and text), and a third party registers a
callable of the same shape under the entry-point group ``reachplan.protocols``.

Built-in: ``embrace_ii`` (EMBRACE II, cervix: Pötter et al., Clin. Transl. Radiat. Oncol. 9:48, 2018).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources


@dataclass(frozen=True)
class ProtocolFile:
    """A protocol file as shipped: its name and its text, parsed by the planner.

    Parameters
    ----------
    name : str
        The plugin's name (``"embrace_ii"``).
    text : str
        The file's content (TOML).
    origin : str
        Where it comes from, for messages (``"built-in protocol embrace_ii"``).
    """

    name: str
    text: str
    origin: str


def _packaged(name: str) -> ProtocolFile:
    text = resources.files(__package__).joinpath(f"{name}.toml").read_text(encoding="utf-8")
    return ProtocolFile(name, text, f"built-in protocol {name}")


def embrace_ii() -> ProtocolFile:
    """EMBRACE II (cervix, 45 Gy / 25 fractions external beam + 4 brachytherapy fractions).

    Returns
    -------
    ProtocolFile
        ``embrace_ii.toml`` as shipped.
    """
    return _packaged("embrace_ii")

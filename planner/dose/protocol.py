"""Protocols as data: a TOML file (or a built-in one, by name) read into :class:`~reachplan.planner.dose.aims.Aims`.

``--protocol FILE_OR_NAME``: a path to a file, else the name of an installed protocol (entry-point group
``reachplan.protocols``; built-in ``embrace_ii``), matched without regard to case, spaces, dashes and underscores
(``"EMBRACE II"`` and ``embrace-ii`` name ``embrace_ii``). The format (``docs/commands.md``, the built-in
``reachplan/plugins/protocols/embrace_ii.toml`` as the example): top-level ``name``, ``site``, ``source``,
``target_names``, ``headroom_eqd2_gy``; tables ``fractionation`` (``brachytherapy_fractions``, ``ebrt_dose_gy``,
``ebrt_fractions``), ``alpha_beta_gy`` (``target``, ``organ``), ``target`` (``d90``: ``aim_min``, optional
``aim_max``, ``limit_min``; ``d98``: ``aim_min``), ``gtv`` (``d98``: ``aim_min``, ``limit_min``), ``organs`` (per
organ ``aim_max``, optional ``limit_max``: D2cm³) and ``points`` (per point ``match``, optional ``aim_max``,
``limit_max``, ``tissue``). Doses are totals of external beam and brachytherapy in Gy EQD2.

Every problem is a :class:`~reachplan.planner.errors.ProtocolError` naming the file and the key: a missing or
unknown key, a value of the wrong type, a dose that is not positive and finite, a hard limit stricter than its
planning aim.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from reachplan.planner.dose.aims import Aims, PointAim
from reachplan.planner.dose.coverage import Fractionation
from reachplan.planner.errors import ProtocolError
from reachplan.planner.lookup import protocol_file, protocol_names

#: The protocol used when none is named.
DEFAULT_PROTOCOL = "embrace_ii"

_TOP = {"name", "site", "source", "target_names", "headroom_eqd2_gy", "fractionation", "alpha_beta_gy", "target",
        "gtv", "organs", "points"}


def _leaf(key: str) -> str:
    """Return the last part of a dotted key (``organs."a.b"`` -> ``a.b``)."""
    return key[key.rindex('"', 0, len(key) - 1) + 1:-1] if key.endswith('"') else key.rsplit(".", 1)[-1]


def _child(key: str, name: str) -> str:
    return f"{key}.{name}" if re.fullmatch(r"[A-Za-z0-9_\-]+", name) else f'{key}."{name}"'


def _key(text: str) -> str:
    return re.sub(r"[\s_\-]", "", text).casefold()


class _Reader:
    """Typed access to a parsed protocol document; every error names the file and the dotted key."""

    def __init__(self, doc: Mapping[str, Any], where: str) -> None:
        self.doc, self.where = doc, where

    def fail(self, key: str, what: str) -> ProtocolError:
        return ProtocolError(f"protocol {self.where}: {key}: {what}; see the protocol format in docs/commands.md")

    def table(self, parent: Mapping[str, Any], key: str, allowed: set[str]) -> Mapping[str, Any]:
        value = self.get(parent, key)
        if not isinstance(value, Mapping):
            raise self.fail(key, f"must be a table, got {value!r}")
        self.known(value, allowed, key)
        return value

    def known(self, table: Mapping[str, Any], allowed: set[str], prefix: str) -> None:
        unknown = sorted(set(table) - allowed)
        if unknown:
            raise self.fail(f"{prefix}.{unknown[0]}" if prefix else unknown[0],
                            f"unknown key (known here: {', '.join(sorted(allowed))})")

    def get(self, parent: Mapping[str, Any], key: str) -> Any:
        leaf = _leaf(key)
        if leaf not in parent:
            raise self.fail(key, "missing")
        return parent[leaf]

    def text(self, parent: Mapping[str, Any], key: str) -> str:
        value = self.get(parent, key)
        if not isinstance(value, str) or not value.strip():
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        return value.strip()

    def names(self, parent: Mapping[str, Any], key: str) -> tuple[str, ...]:
        value = self.get(parent, key)
        if (not isinstance(value, list) or not value
                or not all(isinstance(v, str) and v.strip() for v in value)):
            raise self.fail(key, f"must be a non-empty list of names, got {value!r}")
        return tuple(v.strip() for v in value)

    def number(self, parent: Mapping[str, Any], key: str, *, zero: bool = False) -> float:
        value = self.get(parent, key)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if value < 0 or (value == 0 and not zero):
            raise self.fail(key, f"must be {'>= 0' if zero else '> 0'} Gy, got {value!r}")
        return float(value)

    def optional(self, parent: Mapping[str, Any], key: str) -> float | None:
        return self.number(parent, key) if _leaf(key) in parent else None

    def count(self, parent: Mapping[str, Any], key: str) -> int:
        value = self.get(parent, key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise self.fail(key, f"must be a whole number >= 1, got {value!r}")
        return value

    def bounds(self, parent: Mapping[str, Any], key: str, sense: str, *, limit: bool = True,
               ) -> tuple[float, float | None]:
        # (aim, limit) of a ``sense`` ("min" or "max") aim table at ``key``; the limit no stricter than the aim
        allowed = {f"aim_{sense}", *((f"limit_{sense}",) if limit else ())}
        if key.endswith("d90"):
            allowed.add("aim_max")
        table = self.table(parent, key, allowed)
        aim = self.number(table, f"{key}.aim_{sense}")
        bound = self.optional(table, f"{key}.limit_{sense}") if limit else None
        if bound is not None and (bound > aim if sense == "min" else bound < aim):
            word = "above" if sense == "min" else "below"
            raise self.fail(f"{key}.limit_{sense}", f"the hard limit {bound:g} Gy is {word} the planning aim "
                                                    f"{aim:g} Gy (a limit must not be stricter than its aim)")
        return aim, bound


def _organs(r: _Reader) -> tuple[tuple[tuple[str, float], ...], tuple[tuple[str, float], ...]]:
    organs = r.doc.get("organs", {})
    if not isinstance(organs, Mapping):
        raise r.fail("organs", f"must be a table, got {organs!r}")
    aims, limits = [], []
    for organ in organs:
        aim, limit = r.bounds(organs, _child("organs", organ), "max")
        aims.append((str(organ), aim))
        if limit is not None:
            limits.append((str(organ), limit))
    return tuple(aims), tuple(limits)


def _points(r: _Reader) -> tuple[PointAim, ...]:
    points = r.doc.get("points", {})
    if not isinstance(points, Mapping):
        raise r.fail("points", f"must be a table, got {points!r}")
    out = []
    for name in points:
        key = _child("points", name)
        table = r.table(points, key, {"match", "aim_max", "limit_max", "tissue"})
        aim = r.optional(table, f"{key}.aim_max")
        limit = r.optional(table, f"{key}.limit_max")
        if aim is not None and limit is not None and limit < aim:
            raise r.fail(f"{key}.limit_max", f"the hard limit {limit:g} Gy is below the planning aim {aim:g} Gy "
                                             "(a limit must not be stricter than its aim)")
        tissue = table.get("tissue", "organ")
        if tissue not in ("organ", "target"):
            raise r.fail(f"{key}.tissue", f"must be 'organ' or 'target', got {tissue!r}")
        out.append(PointAim(str(name), r.names(table, f"{key}.match"), aim, limit, tissue))
    return tuple(out)


def aims_from_document(doc: Mapping[str, Any], where: str) -> Aims:
    """Return the aims a parsed protocol document describes (format: the module docstring).

    Parameters
    ----------
    doc : mapping
        The parsed TOML (or JSON) document.
    where : str
        The file or built-in protocol it came from, for messages and :attr:`Aims.origin`.

    Returns
    -------
    Aims
        Planning aims, hard limits, headroom, fractionation, α/β, points and the citation.

    Raises
    ------
    ProtocolError
        A missing or unknown key, a wrong type, a dose that is not positive, or a limit stricter than its aim
        (the message names ``where`` and the key).
    """
    r = _Reader(doc, where)
    r.known(doc, _TOP, "")
    fr = r.table(doc, "fractionation", {"brachytherapy_fractions", "ebrt_dose_gy", "ebrt_fractions"})
    ab = r.table(doc, "alpha_beta_gy", {"target", "organ"})
    target = r.table(doc, "target", {"d90", "d98"})
    gtv = r.table(doc, "gtv", {"d98"})
    d90, d90_limit = r.bounds(target, "target.d90", "min")
    d90_max = r.optional(target["d90"], "target.d90.aim_max")
    if d90_max is not None and d90_max < d90:
        raise r.fail("target.d90.aim_max", f"{d90_max:g} Gy is below aim_min {d90:g} Gy")
    if d90_limit is None:
        raise r.fail("target.d90.limit_min", "missing (the D90 hard limit every scenario keeps)")
    d98, _ = r.bounds(target, "target.d98", "min", limit=False)
    gtv_d98, gtv_limit = r.bounds(gtv, "gtv.d98", "min")
    if gtv_limit is None:
        raise r.fail("gtv.d98.limit_min", "missing")
    oar_aims, oar_limits = _organs(r)
    ebrt = r.number(fr, "fractionation.ebrt_dose_gy", zero=True)
    try:
        return Aims(
            name=r.text(doc, "name"), site=r.text(doc, "site"), source=r.text(doc, "source"),
            target_names=r.names(doc, "target_names"),
            target_d90_eqd2_gy=d90, target_d90_max_eqd2_gy=d90_max, target_d90_limit_eqd2_gy=d90_limit,
            target_d98_eqd2_gy=d98, gtv_d98_eqd2_gy=gtv_d98, gtv_d98_limit_eqd2_gy=gtv_limit,
            oar_d2cc_eqd2_gy=oar_aims, oar_d2cc_limit_eqd2_gy=oar_limits,
            headroom_eqd2_gy=r.number(doc, "headroom_eqd2_gy", zero=True),
            alpha_beta_target_gy=r.number(ab, "alpha_beta_gy.target"),
            alpha_beta_oar_gy=r.number(ab, "alpha_beta_gy.organ"),
            fractionation=Fractionation(r.count(fr, "fractionation.brachytherapy_fractions"), ebrt,
                                        r.count(fr, "fractionation.ebrt_fractions")),
            points=_points(r), origin=where)
    except ValueError as exc:  # what the fields' own checks refuse beyond the reader's
        raise ProtocolError(f"protocol {where}: {exc}") from None


def _parse(text: str, where: str, suffix: str) -> Mapping[str, Any]:
    try:
        doc = json.loads(text) if suffix == ".json" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError(f"protocol {where}: not valid {'JSON' if suffix == '.json' else 'TOML'}: {exc}") from None
    if not isinstance(doc, Mapping):
        raise ProtocolError(f"protocol {where}: must hold a table of keys (see docs/commands.md)")
    return doc


def _looks_like_path(spec: str) -> bool:
    return any(s in spec for s in ("/", "\\")) or spec.casefold().endswith((".toml", ".json"))


def load_protocol(spec: str | Path | None = None) -> Aims:
    """Return the aims of a protocol file, or of an installed protocol by name (None: EMBRACE II).

    Parameters
    ----------
    spec : str, Path or None
        A path to a TOML (or ``.json``) protocol file, or an installed protocol's name (case, spaces, dashes and
        underscores ignored); None: :data:`DEFAULT_PROTOCOL`.

    Returns
    -------
    Aims
        With :attr:`Aims.origin` naming the file or the built-in protocol.

    Raises
    ------
    ProtocolError
        No such file or protocol (the message lists the installed ones), an unreadable file, or a bad document.
    """
    spec = DEFAULT_PROTOCOL if spec is None else spec
    path = Path(spec)
    if isinstance(spec, Path) or path.is_file() or _looks_like_path(str(spec)):
        if not path.is_file():
            raise ProtocolError(f"protocol file {path} does not exist (or is not a file); give a protocol file or "
                                f"one of the installed protocols: {', '.join(protocol_names())}")
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ProtocolError(f"protocol file {path}: cannot be read as text ({exc})") from None
        return aims_from_document(_parse(text, str(path), path.suffix.casefold()), str(path))
    installed = {_key(n): n for n in protocol_names()}
    name = installed.get(_key(str(spec)))
    if name is None:
        raise ProtocolError(f"no protocol named {spec!r}: give a protocol file (TOML) or one of the installed "
                            f"protocols: {', '.join(protocol_names()) or 'none'}")
    shipped = protocol_file(name)
    return aims_from_document(_parse(shipped.text, shipped.origin, ".toml"), shipped.origin)

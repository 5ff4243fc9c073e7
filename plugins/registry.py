"""Plugin registry over entry points.

Groups (entry-point group ``reachplan.<kind>``) and the Protocol each plugin is checked against:

``rod_models``       objects implementing :class:`reachplan.rod_model.protocol.RodModel`
``insertion_models`` objects with a ``str`` ``name`` and ``insert(design, schedules, depth_mm)`` (the planner's
                     insertion-model Protocol, checked structurally)
``templates``        zero-argument callables returning a :class:`reachplan.plugins.templates.Template`
``sources``          zero-argument callables returning a :class:`reachplan.plugins.sources.SourceData`
``exporters``        objects implementing :class:`reachplan.plugins.exporters.base.Exporter`
``applicators``      objects implementing :class:`reachplan.plugins.applicators.ApplicatorKind`
``optimisers``       dwell optimisers: objects with a str ``name`` and a callable ``optimise`` (the implant
                     planner's optimiser Protocol, checked structurally)
``protocols``        zero-argument callables returning a :class:`reachplan.plugins.protocols.ProtocolFile`

The checks are the functions of :mod:`reachplan.plugins.checks` (:data:`DEFAULT_CHECKS`).

Built-ins register through the same entry points as third-party plugins (see ``pyproject.toml``).
Entry points are loaded lazily, on first use of their group; a plugin that fails to import, or does not
pass its group's check, is listed as unavailable with the reason instead of breaking the registry
(the approach of pydicom's pixel-decoder plugins). When two distributions register the same name, the
built-in (distribution ``reachplan``) wins, else the first distribution by name; the other is listed as
unavailable. Call :func:`refresh` after installing a distribution at run time.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from reachplan.plugins.checks import DEFAULT_CHECKS
from reachplan.plugins.errors import PluginError

KINDS: tuple[str, ...] = ("rod_models", "insertion_models", "templates", "sources", "exporters", "applicators",
                          "optimisers", "protocols")

BUILTIN_DISTRIBUTION = "reachplan"

#: Checks registered at run time with :func:`set_check`; they replace the default check of their kind.
_CHECKS: dict[str, Callable[[Any], None]] = {}


@dataclass(frozen=True)
class PluginInfo:
    """What the registry knows of one plugin.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`.
    name : str
        Entry-point name.
    target : str
        The entry point's ``module:attribute``.
    distribution : str
        The distribution that registers it (empty when unknown).
    available : bool
        Loaded and passed its kind's check.
    reason : str
        Why an unavailable plugin is unavailable.
    description : str
        The plugin's ``description`` attribute or the first line of its docstring.
    """

    kind: str
    name: str
    target: str
    distribution: str
    available: bool
    reason: str = ""
    description: str = ""


def _group(kind: str) -> str:
    if kind not in KINDS:
        raise PluginError(f"unknown plugin kind {kind!r}; kinds are: {', '.join(KINDS)}")
    return f"reachplan.{kind}"


def _check_for(kind: str) -> Callable[[Any], None]:
    return _CHECKS.get(kind, DEFAULT_CHECKS[kind])


def _describe(obj: Any) -> str:
    text = getattr(obj, "description", None)
    if not isinstance(text, str):
        doc = inspect.getdoc(obj) or ""
        text = doc.strip().splitlines()[0] if doc.strip() else ""
    return text


def _dist(ep: EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return str(dist.name) if dist is not None else ""


@cache
def _load_group(kind: str) -> tuple[dict[str, Any], tuple[PluginInfo, ...]]:
    group = _group(kind)
    check = _check_for(kind)
    loaded: dict[str, Any] = {}
    infos: list[PluginInfo] = []
    eps = sorted(entry_points(group=group), key=lambda e: (e.name, _dist(e) != BUILTIN_DISTRIBUTION, _dist(e)))
    seen: dict[str, str] = {}
    for ep in eps:
        dist = _dist(ep)
        if ep.name in seen:
            infos.append(PluginInfo(kind, ep.name, ep.value, dist, False,
                                    f"duplicate name; the one from {seen[ep.name] or 'another distribution'} is used"))
            continue
        seen[ep.name] = dist
        try:
            obj = ep.load()
            check(obj)
        except Exception as exc:  # a broken plugin must not break the registry
            infos.append(PluginInfo(kind, ep.name, ep.value, dist, False, f"{type(exc).__name__}: {exc}"))
            continue
        loaded[ep.name] = obj
        infos.append(PluginInfo(kind, ep.name, ep.value, dist, True, description=_describe(obj)))
    return loaded, tuple(infos)


def refresh() -> None:
    """Forget what was loaded so that the next call re-reads the entry points (after installing a plugin)."""
    _load_group.cache_clear()


def set_check(kind: str, check: Callable[[Any], None]) -> None:
    """Replace the Protocol check of ``kind`` (clears the cache so it applies on the next load).

    ``check(obj)`` raises ``TypeError`` or ``ValueError`` with the reason when ``obj`` does not qualify.

    Raises
    ------
    PluginError
        An unknown kind.
    """
    _group(kind)
    _CHECKS[kind] = check
    refresh()


def names(kind: str) -> tuple[str, ...]:
    """List the names of the available plugins of ``kind``, sorted.

    Raises
    ------
    PluginError
        An unknown kind.
    """
    return tuple(sorted(_load_group(kind)[0]))


def info(kind: str | None = None) -> tuple[PluginInfo, ...]:
    """Describe every plugin of ``kind`` (or of all kinds), available or not, with the reason when not.

    Raises
    ------
    PluginError
        An unknown kind.
    """
    kinds = KINDS if kind is None else (kind,)
    return tuple(i for k in kinds for i in _load_group(k)[1])


def get(kind: str, name: str) -> Any:
    """Return the plugin ``name`` of ``kind`` (loading the kind's entry points on first use).

    Raises
    ------
    PluginError
        An unknown kind, no such plugin installed, or an unavailable one (the message says why).
    """
    loaded, infos = _load_group(kind)
    if name in loaded:
        return loaded[name]
    for i in infos:
        if i.name == name:
            raise PluginError(f"{kind} plugin {name!r} is unavailable: {i.reason}")
    raise PluginError(
        f"no {kind} plugin named {name!r}; available: {', '.join(sorted(loaded)) or 'none'}"
        " (install the distribution that provides it)"
    )

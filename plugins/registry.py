"""Plugin registry over entry points.

Groups (entry-point group ``reachplan.<kind>``) and the Protocol each plugin is checked against:

``rod_models``       objects implementing :class:`reachplan.rod_model.protocol.RodModel`
                     (check: ``reachplan.rod_model.protocol.check_rod_model``)
``insertion_models`` objects implementing the planner's insertion-model Protocol
                     (check: ``reachplan.planner.steering.insertion.check_insertion_model``)
``templates``        zero-argument callables returning a :class:`reachplan.plugins.templates.Template`
``sources``          zero-argument callables returning a :class:`reachplan.plugins.sources.SourceData`
``exporters``        objects implementing :class:`reachplan.plugins.exporters.base.Exporter`
                     (check: ``reachplan.plugins.exporters.base.check_exporter``)
``optimisers``       dwell optimisers: objects with a str ``name`` and a callable ``optimise``, the implant
                     planner's optimiser Protocol (check: :func:`check_optimiser`, structural)

Built-ins register through the same entry points as third-party plugins (see ``pyproject.toml``).
Entry points are loaded lazily, on first use of their group; a plugin that fails to import, or does not
pass its group's check, is listed as unavailable with the reason instead of breaking the registry
(the approach of pydicom's pixel-decoder plugins). When two distributions register the same name, the
built-in (distribution ``reachplan``) wins, else the first distribution by name; the other is listed as
unavailable. Call :func:`refresh` after installing a distribution at run time.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from types import MappingProxyType
from typing import Any

from reachplan.plugins.errors import PluginError

KINDS: tuple[str, ...] = ("rod_models", "insertion_models", "templates", "sources", "exporters", "optimisers")

BUILTIN_DISTRIBUTION = "reachplan"

#: Checks registered at run time with :func:`set_check`; they replace the default check of their kind.
_CHECKS: dict[str, Callable[[Any], None]] = {}


def _zero_argument_factory(obj: Any, kind: str) -> Any:
    if not callable(obj):
        raise TypeError(f"a {kind} plugin must be a zero-argument callable, got {type(obj).__name__}")
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):  # builtins without a signature: try the call
        sig = None
    if sig is not None and any(p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
                               for p in sig.parameters.values()):
        raise TypeError(f"a {kind} plugin must be callable without arguments; {obj!r} requires {sig}")
    return obj()


def _factory_check(kind: str, module: str, class_name: str) -> Callable[[Any], None]:
    def check(obj: Any) -> None:
        made_class = getattr(importlib.import_module(module), class_name)
        made = _zero_argument_factory(obj, kind)
        if not isinstance(made, made_class):
            raise TypeError(f"a {kind} plugin must return {module}.{class_name}, got {type(made).__name__}")

    check.__doc__ = (f"Check that ``obj()`` returns a :class:`{module}.{class_name}` (the {kind} check).\n\n"
                     "Raises ``TypeError`` when ``obj`` is not a zero-argument callable, or returns something else.")
    return check


check_template_factory = _factory_check("templates", "reachplan.plugins.templates", "Template")
check_source_factory = _factory_check("sources", "reachplan.plugins.sources", "SourceData")


def check_optimiser(obj: Any) -> None:
    """Check that ``obj`` has the shape of a dwell optimiser (the optimisers check, structural).

    Parameters
    ----------
    obj : object
        The loaded entry point.

    Raises
    ------
    TypeError
        ``obj`` has no str ``name`` or no callable ``optimise``.
    """
    name = getattr(obj, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"an optimisers plugin needs a non-empty str 'name', got {name!r}")
    if not callable(getattr(obj, "optimise", None)):
        raise TypeError(f"an optimisers plugin needs a callable 'optimise', {type(obj).__name__} has none")


#: The default check of each kind, as ``"module:function"`` (imported when the group is first loaded).
DEFAULT_CHECKS: Mapping[str, str] = MappingProxyType({
    "rod_models": "reachplan.rod_model.protocol:check_rod_model",
    "insertion_models": "reachplan.planner.steering.insertion:check_insertion_model",
    "templates": "reachplan.plugins.registry:check_template_factory",
    "sources": "reachplan.plugins.registry:check_source_factory",
    "exporters": "reachplan.plugins.exporters.base:check_exporter",
    "optimisers": "reachplan.plugins.registry:check_optimiser",
})


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
    if kind in _CHECKS:
        return _CHECKS[kind]
    module, _, attr = DEFAULT_CHECKS[kind].partition(":")
    try:
        check = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        msg = f"cannot check it against its Protocol: {DEFAULT_CHECKS[kind]} is missing ({exc})"

        def unavailable(obj: Any) -> None:
            raise TypeError(msg)

        return unavailable
    return check


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

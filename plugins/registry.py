"""Plugin registry over entry points.

Groups (entry-point group ``reachplan.<kind>``):

``rod_models``       objects implementing :class:`rod_model.protocol.RodModel`
``insertion_models`` objects implementing the planner's insertion-model Protocol
``templates``        zero-argument callables returning a :class:`planner.template.Template`
``sources``          zero-argument callables returning TG-43 source data
``exporters``        objects implementing the planner's exporter Protocol

Built-ins register through the same entry points as third-party plugins (see ``pyproject.toml``).
Entry points are loaded lazily, on first use of their group; a plugin that fails to import, or does not
pass its group's check, is listed as unavailable with the reason instead of breaking the registry
(the approach of pydicom's pixel-decoder plugins).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from importlib.metadata import entry_points
from typing import Any

from plugins.errors import PluginError

KINDS: tuple[str, ...] = ("rod_models", "insertion_models", "templates", "sources", "exporters")

#: Optional per-kind checks: raise ``TypeError``/``ValueError`` with a reason when a loaded object does
#: not implement its Protocol. Packages register their check with :func:`set_check`.
_CHECKS: dict[str, Callable[[Any], None]] = {}


@dataclass(frozen=True)
class PluginInfo:
    """What the registry knows of one plugin."""

    kind: str
    name: str
    target: str
    distribution: str
    available: bool
    reason: str = ""


def _group(kind: str) -> str:
    if kind not in KINDS:
        raise PluginError(f"unknown plugin kind {kind!r}; kinds are: {', '.join(KINDS)}")
    return f"reachplan.{kind}"


@cache
def _load_group(kind: str) -> tuple[dict[str, Any], tuple[PluginInfo, ...]]:
    loaded: dict[str, Any] = {}
    infos: list[PluginInfo] = []
    for ep in sorted(entry_points(group=_group(kind)), key=lambda e: e.name):
        dist = ep.dist.name if ep.dist is not None else ""
        try:
            obj = ep.load()
            check = _CHECKS.get(kind)
            if check is not None:
                check(obj)
        except Exception as exc:  # a broken plugin must not break the registry
            infos.append(PluginInfo(kind, ep.name, ep.value, dist, False, f"{type(exc).__name__}: {exc}"))
            continue
        if ep.name in loaded:
            infos.append(PluginInfo(kind, ep.name, ep.value, dist, False, "duplicate name; first one kept"))
            continue
        loaded[ep.name] = obj
        infos.append(PluginInfo(kind, ep.name, ep.value, dist, True))
    return loaded, tuple(infos)


def set_check(kind: str, check: Callable[[Any], None]) -> None:
    """Register the Protocol check for ``kind`` (clears the cache so it applies on the next load)."""
    _group(kind)
    _CHECKS[kind] = check
    _load_group.cache_clear()


def names(kind: str) -> tuple[str, ...]:
    """Names of the available plugins of ``kind``, sorted."""
    return tuple(sorted(_load_group(kind)[0]))


def info(kind: str | None = None) -> tuple[PluginInfo, ...]:
    """Every plugin of ``kind`` (or of all kinds), available or not, with the reason when not."""
    kinds = KINDS if kind is None else (kind,)
    return tuple(i for k in kinds for i in _load_group(k)[1])


def get(kind: str, name: str) -> Any:
    """The plugin ``name`` of ``kind``.

    Raises
    ------
    PluginError
        When no such plugin is installed, or it is unavailable (the message says why).
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

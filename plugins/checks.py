"""The check each plugin kind is held to before the registry lists a plugin as available (:data:`DEFAULT_CHECKS`).

One function per kind, ``check(obj)``, which returns None for a plugin that qualifies and raises ``TypeError`` with
the reason otherwise:

``rod_models``       :func:`reachplan.rod_model.protocol.check_rod_model`
``insertion_models`` :func:`check_insertion_model`
``templates``        ``obj()`` (no arguments) returns a :class:`reachplan.plugins.templates.Template`
``sources``          ``obj()`` (no arguments) returns a :class:`reachplan.plugins.sources.SourceData`
``exporters``        :func:`reachplan.plugins.exporters.base.check_exporter`
``applicators``      :func:`reachplan.plugins.applicators.base.check_applicator_kind`
``optimisers``       :func:`check_optimiser` (structural: the implant planner types them)
``protocols``        ``obj()`` (no arguments) returns a :class:`reachplan.plugins.protocols.ProtocolFile`

A kind whose Protocol is defined in another module imports it when a plugin of that kind is first checked, so
importing the registry stays cheap.

Insertion models are the planner's: the planner defines their typed Protocol, and this floor, which the planner
builds on, holds the structural check the registry applies (a ``str`` name and an ``insert(design, schedules,
depth_mm)`` method).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any


def check_insertion_model(obj: object) -> None:
    """Check that ``obj`` is an insertion model: a ``str`` ``name`` and ``insert(design, schedules, depth_mm)``.

    Structural: the attributes and the call's arity, what the planner's typed ``InsertionModel`` Protocol asks.

    Parameters
    ----------
    obj : object
        What a ``reachplan.insertion_models`` entry point loaded.

    Raises
    ------
    TypeError
        No ``str`` name, no callable ``insert``, or an ``insert`` that cannot take three positional arguments.
    """
    if not isinstance(getattr(obj, "name", None), str):
        raise TypeError(f"{obj!r} does not implement InsertionModel: no str name "
                        "(.name, .insert(design, schedules, depth_mm))")
    insert = getattr(obj, "insert", None)
    if not callable(insert):
        raise TypeError(f"{obj!r} does not implement InsertionModel: no callable insert "
                        "(.name, .insert(design, schedules, depth_mm))")
    try:
        signature = inspect.signature(insert)
    except (TypeError, ValueError):  # a callable without a signature (a builtin): the call will tell
        return
    try:
        signature.bind(None, None, None)
    except TypeError as exc:
        raise TypeError(f"{obj!r}: insert must take (design, schedules, depth_mm), its signature is "
                        f"{signature} ({exc})") from None


def _zero_argument_factory(obj: Any, kind: str) -> Any:
    """Call a factory plugin without arguments and return what it made (``TypeError`` if it needs arguments)."""
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


def _check_made(obj: Any, kind: str, made_class: type) -> None:
    made = _zero_argument_factory(obj, kind)
    if not isinstance(made, made_class):
        raise TypeError(f"a {kind} plugin must return {made_class.__module__}.{made_class.__qualname__}, "
                        f"got {type(made).__name__}")


def _rod_model(obj: object) -> None:
    """Apply the rod-model Protocol's own check (:func:`reachplan.rod_model.protocol.check_rod_model`)."""
    from reachplan.rod_model.protocol import check_rod_model

    check_rod_model(obj)


def _template_factory(obj: object) -> None:
    """Check that ``obj()`` returns a :class:`reachplan.plugins.templates.Template`."""
    from reachplan.plugins.templates import Template

    _check_made(obj, "templates", Template)


def _source_factory(obj: object) -> None:
    """Check that ``obj()`` returns a :class:`reachplan.plugins.sources.SourceData`."""
    from reachplan.plugins.sources import SourceData

    _check_made(obj, "sources", SourceData)


def _protocol_factory(obj: object) -> None:
    """Check that ``obj()`` returns a :class:`reachplan.plugins.protocols.ProtocolFile`."""
    from reachplan.plugins.protocols import ProtocolFile

    _check_made(obj, "protocols", ProtocolFile)


def _exporter(obj: object) -> None:
    """Apply the exporter Protocol's own check (:func:`reachplan.plugins.exporters.base.check_exporter`)."""
    from reachplan.plugins.exporters.base import check_exporter

    check_exporter(obj)


def _applicator_kind(obj: object) -> None:
    """Apply the applicator-kind check (:func:`reachplan.plugins.applicators.base.check_applicator_kind`)."""
    from reachplan.plugins.applicators.base import check_applicator_kind

    check_applicator_kind(obj)


def check_optimiser(obj: Any) -> None:
    """Check that ``obj`` has the shape of a dwell optimiser (the optimisers check, structural).

    The implant room types optimisers (``DwellOptimiser``); this floor only checks what a caller relies on: a
    non-empty str ``name`` and a callable ``optimise``, else ``TypeError`` saying which is missing.

    Parameters
    ----------
    obj : object
        What a ``reachplan.optimisers`` entry point loaded.
    """
    name = getattr(obj, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"an optimisers plugin needs a non-empty str 'name', got {name!r}")
    if not callable(getattr(obj, "optimise", None)):
        raise TypeError(f"an optimisers plugin needs a callable 'optimise', {type(obj).__name__} has none")


#: The default check of each plugin kind (:data:`reachplan.plugins.registry.KINDS`).
DEFAULT_CHECKS: Mapping[str, Callable[[Any], None]] = MappingProxyType({
    "rod_models": _rod_model,
    "insertion_models": check_insertion_model,
    "templates": _template_factory,
    "sources": _source_factory,
    "exporters": _exporter,
    "applicators": _applicator_kind,
    "optimisers": check_optimiser,
    "protocols": _protocol_factory,
})

"""The planner's plugin look-ups: the one module of the planner that calls the plugin registry.

Every other room receives what it needs (a template, a rod model, a source's TG-43 data, an exporter) as an
argument, or asks this module for it by name. It sits directly above the planner's errors, so that any room may
resolve a default by name without reaching the registry itself; ``tests/test_layers.py`` checks that nothing
else in the planner imports :mod:`reachplan.plugins.registry`.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from reachplan.planner.errors import PlanInputError
from reachplan.plugins import registry
from reachplan.plugins.errors import PluginError
from reachplan.plugins.protocols import ProtocolFile
from reachplan.plugins.sources import BUILTIN, SourceData
from reachplan.plugins.templates import Template

if TYPE_CHECKING:  # only for the types: `reachplan rod` imports this module and must not pay for pydicom
    from reachplan.plugins.applicators import ApplicatorKind
    from reachplan.plugins.exporters.base import Exporter
    from reachplan.plugins.registry import PluginInfo
    from reachplan.rod_model.protocol import Capabilities, RodModel


def load_template(name: str) -> Template:
    """Return the template layout registered as ``name``.

    Parameters
    ----------
    name : str
        Entry-point name in ``reachplan.templates`` (e.g. ``"needlefinder_syed_63"``).

    Returns
    -------
    Template
        The layout (hole positions in mm, template frame).

    Raises
    ------
    PluginError
        Unknown or unavailable template.
    PlanInputError
        The plugin did not return a :class:`~reachplan.plugins.templates.Template`.
    """
    template = registry.get("templates", name)()
    if not isinstance(template, Template):
        raise PlanInputError(f"template plugin {name!r} did not return a Template")
    return template


def rod_model(name: str) -> RodModel:
    """Return the rod-model plugin called ``name``.

    Parameters
    ----------
    name : str
        The model's entry-point name in ``reachplan.rod_models``, e.g. ``"planar_beam"``.

    Returns
    -------
    RodModel
        The model object (its ``solve``/``solve_batch`` map a design and loads to a shape).

    Raises
    ------
    PluginError
        Unknown or unavailable rod model.
    """
    model: RodModel = registry.get("rod_models", name)
    return model


def rod_model_capabilities() -> dict[str, Capabilities]:
    """Return what every loadable rod-model plugin can represent, by name (the model selector's input).

    Returns
    -------
    dict of str to Capabilities
        One entry per available rod model.
    """
    return {name: registry.get("rod_models", name).capabilities for name in registry.names("rod_models")}


def source_names() -> tuple[str, ...]:
    """Return the names of every TG-43 data set: the built-ins first, then the installed plugins'.

    Returns
    -------
    tuple of str
        Unique names, in that order.
    """
    return tuple(dict.fromkeys([*BUILTIN, *registry.names("sources")]))


def get_source(name: str) -> SourceData:
    """Return the TG-43 data set ``name`` through the plugin registry (the built-ins as fallback).

    Parameters
    ----------
    name : str
        The data set's name (e.g. ``"gammamed_plus_hdr"``).

    Returns
    -------
    SourceData
        Λ, g_L(r), F(r, θ) and the source's description.

    Raises
    ------
    PluginError
        Unknown or unavailable source (the message lists the known names), or a plugin that does not return
        :class:`~reachplan.plugins.sources.SourceData`.
    """
    try:
        loader = registry.get("sources", name)
    except PluginError:
        if name not in BUILTIN:
            known = sorted(set(BUILTIN) | set(registry.names("sources")))
            raise PluginError(f"no TG-43 source named {name!r}; available: {', '.join(known)}") from None
        loader = BUILTIN[name]
    data = loader()
    if not isinstance(data, SourceData):
        raise PluginError(f"sources plugin {name!r} did not return SourceData (got {type(data).__name__})")
    return data


def all_sources() -> Mapping[str, SourceData]:
    """Return every TG-43 data set by name (:func:`source_names`), loaded.

    Returns
    -------
    Mapping of str to SourceData
        The input of :func:`reachplan.plugins.sources.identify.identify_source`.
    """
    return {name: get_source(name) for name in source_names()}


def exporter(name: str) -> Exporter:
    """Return the exporter plugin called ``name``.

    Parameters
    ----------
    name : str
        Entry-point name of the exporter (group ``reachplan.exporters``), e.g. ``"dicom_rt"``.

    Returns
    -------
    Exporter
        The exporter (its ``export(plan, folder, options)`` writes files).

    Raises
    ------
    PluginError
        Unknown or unavailable exporter.
    """
    out: Exporter = registry.get("exporters", name)
    return out


def plugin_info(kind: str | None = None) -> tuple[PluginInfo, ...]:
    """Describe every installed plugin of ``kind`` (all kinds when None), available or not, with the reason.

    Parameters
    ----------
    kind : str or None
        One of the registry's kinds.

    Returns
    -------
    tuple of PluginInfo
        One per plugin.

    Raises
    ------
    PluginError
        An unknown kind.
    """
    return registry.info(kind)


def applicator_kinds() -> Mapping[str, ApplicatorKind]:
    """Return the installed applicator kinds (entry-point group ``reachplan.applicators``) by name.

    Returns
    -------
    mapping of str to ApplicatorKind
        Kind name -> kind, sorted by name; unavailable plugins are left out (``reachplan plugins`` says why).
    """
    return MappingProxyType({name: registry.get("applicators", name) for name in registry.names("applicators")})


def optimiser(name: str) -> Any:
    """Return the dwell optimiser registered as ``name`` (entry-point group ``reachplan.optimisers``).

    Parameters
    ----------
    name : str
        Its entry-point name (e.g. ``"lp"``).

    Returns
    -------
    object
        An object with a str ``name`` and a callable ``optimise`` (the registry's structural check); the implant
        room types it (:func:`reachplan.planner.implant.optimiser.resolve`).

    Raises
    ------
    PluginError
        No optimiser of that name is installed (the message lists the available ones), or it is unavailable.
    """
    return registry.get("optimisers", name)


def protocol_names() -> tuple[str, ...]:
    """Return the names of the installed protocols (entry-point group ``reachplan.protocols``), sorted.

    Returns
    -------
    tuple of str
        E.g. ``("embrace_ii",)``.
    """
    return registry.names("protocols")


def protocol_file(name: str) -> ProtocolFile:
    """Return the protocol file registered as ``name``.

    Parameters
    ----------
    name : str
        Its entry-point name in ``reachplan.protocols`` (e.g. ``"embrace_ii"``).

    Returns
    -------
    ProtocolFile
        The file's name, text and origin.

    Raises
    ------
    PluginError
        Unknown or unavailable protocol, or a plugin that does not return a ProtocolFile.
    """
    made = registry.get("protocols", name)()
    if not isinstance(made, ProtocolFile):
        raise PluginError(f"protocols plugin {name!r} did not return a ProtocolFile (got {type(made).__name__})")
    return made

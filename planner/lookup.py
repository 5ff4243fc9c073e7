"""Plugins by name: the one planner module that imports the plugin registry."""

from __future__ import annotations

from typing import Any


def optimiser(name: str) -> Any:
    """Return the dwell optimiser registered as ``name`` (entry-point group ``reachplan.optimisers``).

    Parameters
    ----------
    name : str
        Its entry-point name (e.g. ``"lp"``).

    Returns
    -------
    object
        An object with a str ``name`` and a callable ``optimise`` (the registry's structural check); the
        implant room types it (``reachplan.planner.implant.optimiser.DwellOptimiser``).

    Raises
    ------
    reachplan.plugins.errors.PluginError
        No optimiser of that name is installed (the message lists the available ones), or it is unavailable.
    """
    from reachplan.plugins import registry

    return registry.get("optimisers", name)

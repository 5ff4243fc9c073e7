"""The planner's one door to the plugin registry: plugins by name, for the rooms above that may not import it."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from reachplan.plugins import registry
from reachplan.plugins.applicators import ApplicatorKind


def applicator_kinds() -> Mapping[str, ApplicatorKind]:
    """Return the installed applicator kinds (entry-point group ``reachplan.applicators``) by name.

    Returns
    -------
    mapping of str to ApplicatorKind
        Kind name -> kind, sorted by name; unavailable plugins are left out (``reachplan plugins`` says why).
    """
    return MappingProxyType({name: registry.get("applicators", name) for name in registry.names("applicators")})

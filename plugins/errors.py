"""Errors of the plugin floor (registry lookups, exporters and applicators)."""

from __future__ import annotations

from reachplan import ReachplanError


class PluginError(ReachplanError):
    """A plugin is unknown, unavailable or does not implement its Protocol."""


class ExportError(ReachplanError):
    """A plan cannot be exported as asked (file exists, would overwrite an input, inconsistent identity)."""


class SourceMatchError(PluginError):
    """A plan's source matches no registered TG-43 data set, or several, or contradicts the one it names."""


class ApplicatorError(ReachplanError):
    """Applicators cannot be built as asked (an unknown kind or ROI assigned, a name two kinds claim)."""

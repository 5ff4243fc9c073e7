"""The project's one base error.

Every package's ``errors.py`` derives from :class:`ReachplanError`, so the command line can turn any
expected failure into a one-line message and exit code 2 without a traceback.
"""

from __future__ import annotations


class ReachplanError(Exception):
    """Base of every error reachplan raises on purpose.

    The message is one line that says what is wrong and what to do next.
    """

    exit_code: int = 2


class PluginError(ReachplanError):
    """A plugin is unknown, unavailable or does not implement its Protocol."""


class ExportError(ReachplanError):
    """A plan cannot be exported as asked (file exists, would overwrite an input, inconsistent identity)."""

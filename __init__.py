"""reachplan: pre-planning of steered (tendon-driven stylet) needle paths for interstitial gynecologic brachytherapy.

The package has four floors; a floor imports only from the floors below it:

* :mod:`reachplan.imaging` and :mod:`reachplan.rod_model` (floor 1): files to volumes, structures and meshes; a
  stylet design and its loads to a shape.
* :mod:`reachplan.plugins` (floor 2): the entry-point registry and the built-in plugins (templates, TG-43 source
  data, exporters).
* :mod:`reachplan.planner` (floor 3): the application (geometry, steering, ranking, dose, report, study, CLI).

Below the floors, ``reachplan._arrays`` holds the array helpers every floor shares (it imports no floor).

This module holds only the version and :class:`ReachplanError`, the base of every error reachplan raises on purpose.
"""

from __future__ import annotations

__all__ = ["ReachplanError", "__version__"]


def __getattr__(name: str) -> str:
    """``__version__`` on first use: importlib.metadata costs about 80 ms of every command's start-up."""
    if name != "__version__":
        raise AttributeError(f"module 'reachplan' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("reachplan")
    except PackageNotFoundError:  # pragma: no cover - running from an uninstalled tree
        return "0+unknown"


class ReachplanError(Exception):
    """Base of every error reachplan raises on purpose.

    The message is one line that says what is wrong and what to do next; the command line prints it and exits
    with :attr:`exit_code`.
    """

    exit_code: int = 2

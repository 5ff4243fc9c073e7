"""``reachplan plugins``: every installed plugin, with availability and the reason when unavailable."""

from __future__ import annotations

import argparse
import dataclasses

from reachplan.planner.cli.edges import print_json

NAME = "plugins"
HELP = ("list installed plugins (rod models, insertion models, templates, sources, exporters, applicators, "
        "optimisers, protocols) and whether they load")


#: the registry's ``KINDS``, spelled out: importing the registry (importlib.metadata) would cost every command's
#: start-up about 70 ms (tests/planner/cli/test_cli_startup.py checks the two agree)
KINDS: tuple[str, ...] = ("rod_models", "insertion_models", "templates", "sources", "exporters", "applicators",
                          "optimisers", "protocols")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--kind`` and ``--json``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        Sub-parser of ``reachplan plugins``.
    """
    parser.add_argument("--kind", choices=KINDS, help="only this kind of plugin")
    parser.add_argument("--json", action="store_true", help="print one JSON document (a list of plugins)")


def run(args: argparse.Namespace) -> int:
    """Print the installed plugins and whether they load; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        ``kind`` (None: every kind) and ``json``.

    Returns
    -------
    int
        0, also when a plugin does not load (its line says why).
    """
    from reachplan.planner.lookup import plugin_info

    infos = plugin_info(args.kind)
    if args.json:
        print_json([dataclasses.asdict(i) for i in infos], NAME)
        return 0
    if not infos:
        print("no plugins installed" + (f" of kind {args.kind}" if args.kind else ""))
        return 0
    for i in infos:
        state = "ok" if i.available else f"UNAVAILABLE: {i.reason}"
        print(f"{i.kind:<17}{i.name:<26}{i.distribution:<24}{state}")
    return 0

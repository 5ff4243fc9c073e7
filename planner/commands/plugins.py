"""``reachplan plugins``: every installed plugin, with availability and the reason when unavailable."""

from __future__ import annotations

import argparse
import json

NAME = "plugins"
HELP = "list installed plugins (rod models, templates, sources, exporters) and whether they load"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON")


def run(args: argparse.Namespace) -> int:
    from plugins import registry

    infos = registry.info()
    if args.json:
        print(json.dumps([i.__dict__ for i in infos], indent=2))
        return 0
    for i in infos:
        state = "ok" if i.available else f"UNAVAILABLE: {i.reason}"
        print(f"{i.kind:<17}{i.name:<26}{i.distribution:<14}{state}")
    return 0

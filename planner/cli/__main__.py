"""``python -m reachplan.planner.cli``: the same as the ``reachplan`` command."""

import sys

from reachplan.planner.cli import console

sys.exit(console())

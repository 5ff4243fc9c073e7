"""``reachplan rod``: solve one stylet design for one tension (or a sweep) and print the shape."""

from __future__ import annotations

import argparse
import json

from reachplan import ReachplanError

NAME = "rod"
HELP = "Solve the stylet-in-needle shape for a preset design and tendon tension(s)."


class RodArgumentError(ReachplanError):
    """A ``reachplan rod`` argument is invalid."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", required=True,
                        help="design preset {13|15}ga-{joints}j-{tip|mid|base|asym}, e.g. 15ga-30j-tip "
                             "(an unknown name lists the usual ones)")
    parser.add_argument("--tension", type=float, help="tension of tendon 0, N")
    parser.add_argument("--tensions", help="comma-separated tensions for a sweep, N (one object per tension)")
    parser.add_argument("--model", default="two_tube_cosserat",
                        help="rod model plugin name, or 'auto' to pick the cheapest within --tolerance "
                             "(default two_tube_cosserat)")
    parser.add_argument("--tolerance", type=float, default=0.5, help="tip error allowed with --model auto, mm")
    parser.add_argument("--roll", type=float, default=0.0, help="roll of the stylet, degrees")
    parser.add_argument("--json", action="store_true", help="print JSON (the only output format so far)")


def _tensions(args: argparse.Namespace) -> tuple[list[float], bool]:
    if (args.tension is None) == (args.tensions is None):
        raise RodArgumentError("give exactly one of --tension N or --tensions a,b,c")
    if args.tensions is None:
        values, sweep = [args.tension], False
    else:
        try:
            values, sweep = [float(t) for t in args.tensions.split(",") if t.strip()], True
        except ValueError:
            raise RodArgumentError(f"--tensions must be comma-separated numbers, got {args.tensions!r}") from None
    if not values or any(not (0.0 <= t < 1e3) for t in values):
        raise RodArgumentError("tensions must be numbers between 0 and 1000 N")
    return values, sweep


def run(args: argparse.Namespace) -> int:
    # imported here, not at the top: ``reachplan --help`` and the other commands must not pay for them
    from reachplan.plugins import registry
    from reachplan.rod_model.design import preset
    from reachplan.rod_model.select import Scene, select_model

    values, sweep = _tensions(args)
    design = preset(args.preset)
    if args.model == "auto":
        from reachplan.planner.pipeline import rod_model_capabilities

        name = select_model(args.tolerance, Scene.of(design.loads(values[0], args.roll)), rod_model_capabilities())
    else:
        name = args.model
    model = registry.get("rod_models", name)
    model.solve(design, design.loads(0.0))  # load compiled kernels before timing (solve_ms is the solve only)
    out = []
    for t in values:
        result = model.solve(design, design.loads(t, args.roll))
        doc = result.to_json()
        doc.update(preset=design.name, tension_n=t, max_tension_n=design.max_tension_n)
        out.append(doc)
    if args.json:
        print(json.dumps(out if sweep else out[0]))
    else:
        for d in out:
            state = (f"tip deflection {d['tip_deflection_mm']:.3f} mm" if d["converged"]
                     else f"FAILED: {d['reason']}")
            print(f"{design.name} {d['model']} tension {d['tension_n']:g} N roll {args.roll:g} deg: {state}")
    return 0 if all(d["converged"] for d in out) else 1

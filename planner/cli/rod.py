"""``reachplan rod``: solve one stylet design for one tension (or a sweep) and print the shape."""

from __future__ import annotations

import argparse
import warnings
from dataclasses import replace
from typing import Any

from reachplan import ReachplanError
from reachplan.planner.cli.edges import finite, print_json
from reachplan.planner.cli.points import comma_items
from reachplan.rod_model.errors import TensionAboveLimitWarning

NAME = "rod"
HELP = "Solve the stylet-in-needle shape for a preset design and tendon tension(s)."


class RodArgumentError(ReachplanError):
    """A ``reachplan rod`` argument is invalid."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the preset, tension, model, roll and ``--json`` options.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        Where the ``reachplan rod`` options go.
    """
    parser.add_argument("--preset", required=True,
                        help="design preset {13|15}ga-{joints}j-{tip|mid|base|asym}, e.g. 15ga-30j-tip "
                             "(an unknown name lists the usual ones)")
    parser.add_argument("--tension", type=float, help="tension of tendon 0, N")
    parser.add_argument("--tensions", help="comma-separated tensions for a quasi-static sweep in that order, N (one "
                        "object per tension); up then down (0,2,...,10,...,0) shows the friction hysteresis loop")
    parser.add_argument("--tendon-friction", type=float, default=None, metavar="MU",
                        help="capstan friction coefficient of the tendon on its routing (design default 0)")
    parser.add_argument("--joint-friction", type=float, default=None, metavar="MU",
                        help="Coulomb friction coefficient in the ball joints (design default 0)")
    parser.add_argument("--model", default="two_tube_cosserat",
                        help="rod model plugin name, or 'auto' to pick the cheapest within --tolerance "
                             "(default two_tube_cosserat)")
    parser.add_argument("--tolerance", type=float, default=0.5,
                        help="with --model auto: largest tip error allowed, mm, measured against the converged "
                             "two-tube Cosserat model in free space: a modelling/numerical error, not an error against "
                             "experiment (the calibrated two-tube model is itself up to ~1 mm off the published "
                             "calibration rows; see rod_model/calibrate.py)")
    parser.add_argument("--allow-over-limit", action="store_true",
                        help="solve tensions above the design's limit (max_tension_n: 10 N on 15 ga, 14 N on 13 ga)")
    parser.add_argument("--roll", type=float, default=0.0, help="roll of the stylet, degrees")
    parser.add_argument("--json", action="store_true", help="print JSON (the only output format so far)")


def _tensions(args: argparse.Namespace) -> tuple[list[float], bool]:
    if (args.tension is None) == (args.tensions is None):
        raise RodArgumentError("give exactly one of --tension N or --tensions a,b,c")
    if args.tensions is None:
        values, sweep = [args.tension], False
    else:
        try:
            values, sweep = [float(t) for t in comma_items(args.tensions, "--tensions", RodArgumentError)], True
        except ValueError:
            raise RodArgumentError(f"--tensions must be comma-separated numbers, got {args.tensions!r}") from None
    if not values or any(not (0.0 <= t < 1e3) for t in values):  # also refuses NaN
        raise RodArgumentError("tensions must be numbers between 0 and 1000 N")
    return values, sweep


def _check(args: argparse.Namespace) -> None:
    finite(args.roll, "--roll", lo=-3600.0, hi=3600.0)
    finite(args.tolerance, "--tolerance", lo=0.0, lo_open=True, hi=1e3)


def run(args: argparse.Namespace) -> int:
    """Solve the preset at each tension and print the shapes; return 0, or 1 when a solve did not converge.

    Parameters
    ----------
    args : argparse.Namespace
        Preset, tension or tensions (N), friction coefficients, model, roll and ``json``.

    Returns
    -------
    int
        0 when every solve converged, else 1.
    """
    # imported here, not at the top: ``reachplan --help`` and the other commands must not pay for them
    from reachplan.planner.lookup import rod_model, rod_model_capabilities
    from reachplan.rod_model.design import preset
    from reachplan.rod_model.friction import loop_width_mm, solve_sweep
    from reachplan.rod_model.select import Scene, select_model

    values, sweep = _tensions(args)
    _check(args)
    design = preset(args.preset)
    friction = {k: v for k, v in (("tendon_friction_coefficient", args.tendon_friction),
                                  ("joint_friction_coefficient", args.joint_friction)) if v is not None}
    if friction:
        try:
            design = replace(design, stylet=replace(design.stylet, **friction))
        except ValueError as exc:
            raise RodArgumentError(f"{exc}; give friction coefficients between 0 and 2") from None
    over = [t for t in values if t > design.max_tension_n]
    if over and not args.allow_over_limit:
        raise RodArgumentError(f"tension {max(over):g} N exceeds {design.name}'s limit of {design.max_tension_n:g} N; "
                               "lower it or pass --allow-over-limit")
    if args.model == "auto":
        scene = Scene.of(design.loads(values[0], args.roll), design)
        name = select_model(args.tolerance, scene, rod_model_capabilities())
    else:
        name = args.model
    model = rod_model(name)
    model.solve(design, design.loads(0.0))  # load compiled kernels before timing (solve_ms is the solve only)
    out: list[dict[str, Any]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TensionAboveLimitWarning)  # refused above unless explicitly allowed
        results = solve_sweep(model, design, values, args.roll)
    previous = 0.0
    for t, result in zip(values, results, strict=True):
        doc = result.to_json()
        doc.update(preset=design.name, tension_n=t, max_tension_n=design.max_tension_n,
                   pulling=t >= previous if t != previous else None)
        out.append(doc)
        previous = t
    if args.json:
        print_json(out if sweep else out[0], NAME)
    else:
        for d in out:
            state = (f"tip deflection {d['tip_deflection_mm']:.3f} mm" if d["converged"]
                     else f"FAILED: {d['reason']}")
            way = {True: " (pulling)", False: " (releasing)"}.get(d["pulling"], "")
            print(f"{design.name} {d['model']} tension {d['tension_n']:g} N{way} roll {args.roll:g} deg: {state}")
        if sweep and all(d["converged"] for d in out) and max(values) != values[-1]:
            width = loop_width_mm(values, [float(d["tip_deflection_mm"]) for d in out])
            print(f"hysteresis: largest release-minus-pull tip difference {width:.3f} mm "
                  f"(tendon friction {design.stylet.tendon_friction_coefficient:g}, "
                  f"joint friction {design.stylet.joint_friction_coefficient:g})")
    return 0 if all(d["converged"] for d in out) else 1

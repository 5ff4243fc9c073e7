"""``reachplan study``: plan every case x stylet design x target of a cohort, in parallel, resumably.

``--implant N``: instead, the straight-vs-steered implant comparison on the clinical case of seeds ``--seed`` ..
``--seed + N - 1`` (:mod:`reachplan.planner.study.implant`).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from reachplan.planner.cli.edges import output_folder, print_json

NAME = "study"
HELP = ("plan every case x stylet design x target of a cohort on a local process pool or a Dask cluster; "
        "resumable; writes study.parquet, summary.csv and summary.png (or --make-cohort N phantom cases, or "
        "--implant N: straight against steered implants on N clinical cases)")

#: ``--implant`` without a count: the cohort's size.
IMPLANT_CASES = 30

#: ``--family coarse``: 3 onsets x 1 ramp x 2 plateaus, for quick looks and tests.
COARSE_FAMILY = {"onsets_mm": (0.0, 40.0, 80.0), "ramps_mm": (10.0,), "plateau_fractions": (0.5, 1.0)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the cohort, design, cluster, resume and output options.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The parser ``reachplan study`` builds its options on.
    """
    parser.add_argument("--cases", nargs="+", type=Path, metavar="DIR",
                        help="case folders (each holding an RS*.dcm), or folders of case folders")
    parser.add_argument("--designs", nargs="+", default=["15ga-30j-tip"], metavar="PRESET",
                        help="stylet presets to compare ('straight': straight needles only); with --implant: a "
                             "straight + steered arm per preset, the straight arm shared (designs.csv)")
    parser.add_argument("--targets", nargs="+", metavar="ROI", help="target ROI names (default: every Target* ROI)")
    parser.add_argument("--template", default="needlefinder_syed_63", help="template plugin name")
    parser.add_argument("--family", choices=("default", "coarse"), default="default",
                        help="tension schedules screened per design (coarse: 6 instead of 110, for quick looks)")
    parser.add_argument("--dose", action="store_true",
                        help="also optimise the dwell times of each case x design's needles (TG-43) and report the "
                             "HR-CTV D90")
    parser.add_argument("--out", type=Path, required=True, help="output folder (resumes the study it holds)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address, e.g. tcp://host:8786")
    parser.add_argument("--workers", type=int, metavar="N",
                        help="local worker processes (default: CPU count; 0: run in this process)")
    parser.add_argument("--retry-failed", action="store_true", help="run again the tasks recorded as failed")
    parser.add_argument("--make-cohort", type=int, metavar="N",
                        help="instead of a study: write N deterministic phantom variants to --out")
    parser.add_argument("--implant", type=int, nargs="?", const=IMPLANT_CASES, metavar="N",
                        help="instead of a design study: plan the implant arms (straight; straight + steered, one "
                             "per --designs preset) on the clinical case of N seeds from --seed (N default "
                             f"{IMPLANT_CASES}) and summarise needles saved and D90 gained by steering (Wilcoxon, "
                             "sign and paired t tests with 95 %% CIs, strata of anatomy); writes cases.csv, "
                             "designs.csv, summary.json (with the CPU cost per case), summary.png")
    parser.add_argument("--max-needles", type=int, default=16, metavar="K",
                        help="with --implant: largest needle budget on each arm's Pareto curve")
    parser.add_argument("--seed", type=int, default=0, help="seed of --make-cohort and --implant (first case)")
    parser.add_argument("--case", choices=("clinical", "pilot"), default="clinical",
                        help="what --make-cohort varies: the clinical case (default) or the pilot phantom")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or table")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")


def run(args: argparse.Namespace) -> int:
    """Write a phantom cohort (``--make-cohort``) or run the study and print its summary; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        The cohort (``cases`` or ``make_cohort``), designs, targets, template, family, dose, cluster, resume and
        output options.

    Returns
    -------
    int
        0 (a failing study raises :class:`StudyError`).
    """
    from reachplan.planner.errors import StudyError

    quiet = args.quiet or args.json
    if args.make_cohort is not None:
        from reachplan.planner.study.cohort import make_cohort

        if args.make_cohort < 1:
            raise StudyError(f"--make-cohort needs at least 1 case, got {args.make_cohort}")
        output_folder(args.out)
        cases = make_cohort(args.out, args.make_cohort, args.seed, args.case)
        if args.json:
            print_json({"cases": [str(c) for c in cases]}, NAME)
        elif not quiet:
            print(f"wrote {len(cases)} phantom cases to {args.out} (cohort.json lists their perturbations)")
        return 0
    if args.scheduler is not None and args.workers is not None:
        raise StudyError("--workers sets the local pool; with --scheduler the cluster's workers are used")
    if args.workers is not None and not 0 <= args.workers <= 1024:
        raise StudyError(f"--workers must be between 0 and 1024, got {args.workers}")
    if args.implant is not None:
        return _implant(args, quiet)
    if not args.cases:
        raise StudyError("give --cases DIR... (or --make-cohort N to write phantom cases, or --implant N)")
    output_folder(args.out, args.cases)
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.steering.steered import ScheduleFamily
    from reachplan.planner.study import StudySpec, discover_cases, run_study
    from reachplan.planner.study.summary import format_summary

    family = ScheduleFamily(**COARSE_FAMILY) if args.family == "coarse" else ScheduleFamily()
    config = PlanConfig(template=args.template, family=family)
    try:
        spec = StudySpec(discover_cases(args.cases), tuple(args.designs),
                         None if args.targets is None else tuple(args.targets), config, dose=args.dose)
    except ValueError as exc:
        raise StudyError(str(exc)) from None
    result = run_study(spec, args.out, scheduler=args.scheduler, workers=args.workers,
                       retry_failed=args.retry_failed, quiet=quiet)
    if args.json:
        print_json({"out": str(result.out), "tasks": result.n_tasks, "resumed": result.n_resumed,
                   "failed_tasks": result.n_failed_tasks, "rows": result.table.num_rows,
                   "wall_s": round(result.wall_s, 3),
                   "designs": [dataclasses.asdict(s) for s in result.summaries]}, NAME)
    elif not quiet:
        print(format_summary(result.summaries))
        print(f"\n{result.n_tasks} tasks ({result.n_resumed} already done, {result.n_failed_tasks} failed) in "
              f"{result.wall_s:.1f} s; wrote {result.out / 'study.parquet'}, summary.csv and summary.png")
    return 0


def _implant(args: argparse.Namespace, quiet: bool) -> int:
    """Run the implant study of ``--implant N`` cases and print its summary; return 0."""
    from reachplan.planner.errors import StudyError

    if args.cases or args.targets or args.dose:
        raise StudyError("--implant builds its own clinical cases; drop --cases, --targets and --dose")
    if not 1 <= args.implant <= 10_000:
        raise StudyError(f"--implant needs between 1 and 10000 cases, got {args.implant}")
    if "straight" in args.designs:
        raise StudyError("--implant always plans the straight arm; give only stylet presets with --designs")
    if len(set(args.designs)) != len(args.designs):
        raise StudyError("--designs names a preset twice; give each once")
    if args.max_needles < 1:
        raise StudyError(f"--max-needles must be at least 1, got {args.max_needles}")
    output_folder(args.out)
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.steering.steered import ScheduleFamily
    from reachplan.planner.study.designs import format_designs
    from reachplan.planner.study.implant import ImplantStudySpec, run_implant_study, study_settings
    from reachplan.planner.study.summary import format_implant_summary

    family = ScheduleFamily(**COARSE_FAMILY) if args.family == "coarse" else ScheduleFamily()
    # as the demo: the clinical case's tandem (an applicator) is an obstacle, a needle must not cross it
    config = PlanConfig(template=args.template, family=family, designs=tuple(args.designs))
    spec = ImplantStudySpec(tuple(range(args.seed, args.seed + args.implant)), config,
                            study_settings(max_needles=args.max_needles))
    result = run_implant_study(spec, args.out, scheduler=args.scheduler, workers=args.workers,
                               retry_failed=args.retry_failed, quiet=quiet)
    if args.json:
        print_json({"out": str(result.out), "resumed": result.n_resumed, **result.doc}, NAME)
    elif not quiet:
        print(format_implant_summary(result.summary, [dataclasses.asdict(r) for r in result.rows]))
        print("\n" + format_designs(result.doc["designs"]))
        cpu = result.doc["cost"]["cpu_s_per_case"]
        median = "-" if cpu["median"] is None else f"{cpu['median']:.1f} s"
        print(f"\n{len(result.rows)} cases ({result.n_resumed} already done) in {result.wall_s:.1f} s; CPU per case "
              f"(both arms, every design): median {median} over {cpu['n']}; wrote {result.out / 'cases.csv'}, "
              "designs.csv, summary.json and summary.png")
    return 0

"""Design studies over patient cohorts: every case x stylet design x target, planned in parallel.

The work is split into tasks of one case x one design (all targets), run by Dask distributed: on a
``LocalCluster`` of worker processes by default, on a user's cluster when given a scheduler address
(started the standard way: ``dask scheduler`` and ``dask worker ADDRESS``; the workers must read the case
folders under the same paths; only this process writes results), or in this process (``workers=0``).
Tasks ship names and paths only. Each worker loads a case once and keeps it for the case's other designs
(:func:`reachplan.planner.study.tasks.load_scene`), and tasks prefer the worker that holds their case.

Results stream to ``OUT/parts/<task>.parquet`` as tasks finish (the folder is a Parquet dataset:
``pyarrow.parquet.read_table(OUT / "parts")`` shows the progress of a running study). A task is done
exactly when its part file exists, so a killed study resumes where it stopped, with no row lost or
repeated. A task that fails is recorded (rows with ``status = failed`` and the reason) and the study goes
on; ``retry_failed`` runs those again. At the end the parts are consolidated into ``OUT/study.parquet``,
with ``summary.csv`` and ``summary.png`` (reach rate and best-candidate metrics per design).

The straight-vs-steered implant comparison over clinical cases (:mod:`reachplan.planner.study.implant`) runs on
the same runners (:func:`serial_results`, :func:`dask_results`, :func:`dask_client`) with a ledger of its own.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from tqdm import tqdm

from reachplan.imaging.files import atomic_write_json
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.errors import StudyError
from reachplan.planner.study import store
from reachplan.planner.study.summary import DesignSummary, summarise, summary_figure, write_dataclass_csv
from reachplan.planner.study.tasks import STRAIGHT, Case, StudyRow, StudyTask, discover_cases, failed_rows, run_task

if TYPE_CHECKING:
    import pyarrow as pa

__all__ = ["STRAIGHT", "Case", "DesignSummary", "StudyResult", "StudyRow", "StudySpec", "StudyTask",
           "discover_cases", "run_study", "run_task"]

TaskFn = Callable[[StudyTask, PlanConfig], Sequence[StudyRow]]


class Keyed(Protocol):
    """A study task: its ``key`` names it uniquely (and its result file)."""

    @property
    def key(self) -> str:
        """Return the task's unique, file-name-safe key."""
        ...


T = TypeVar("T", bound=Keyed)
R = TypeVar("R")
MANIFEST = "study.json"
MANIFEST_VERSION = 1


@dataclass(frozen=True)
class StudySpec:
    """What a study plans: every case x design x target with one plan configuration.

    Its :meth:`manifest` identifies the study's results: a resumed study must match it.

    Parameters
    ----------
    cases : tuple of Case, at least one
        The cases, each planned with every design.
    designs : tuple of str
        Stylet presets or ``straight`` (straight needles only), each once.
    targets : tuple of str or None
        ROI names; None: every ROI named ``Target*`` in each case.
    config : PlanConfig
        The plan configuration; its ``designs`` are ignored (each task sets its own).
    dose : bool
        Also optimise each case x design's dwell times and report the HR-CTV D90.

    Raises
    ------
    ValueError
        No case, no design or a design twice, or an empty or repeated target list.
    """

    cases: tuple[Case, ...]
    designs: tuple[str, ...]
    targets: tuple[str, ...] | None = None
    config: PlanConfig = field(default_factory=PlanConfig)
    dose: bool = False

    def __post_init__(self) -> None:
        if not self.cases:
            raise ValueError("a study needs at least one case")
        if not self.designs or len(set(self.designs)) != len(self.designs):
            raise ValueError("a study needs at least one design, each named once")
        if self.targets is not None and (not self.targets or len(set(self.targets)) != len(self.targets)):
            raise ValueError("targets, when given, must be at least one ROI name, each named once")

    def tasks(self) -> tuple[StudyTask, ...]:
        """Case-major order: a worker that takes consecutive tasks reuses the loaded case.

        Returns
        -------
        tuple of StudyTask
            One per case x design.
        """
        return tuple(StudyTask(c, d, self.targets, self.dose) for c in self.cases for d in self.designs)

    def manifest(self) -> dict[str, Any]:
        """Return what identifies the study's results (JSON-ready); a resumed study must match it.

        Returns
        -------
        dict of str to JSON value
            Version, cases (id -> structure set path), designs, targets, dose and the configuration without designs.
        """
        config = dataclasses.asdict(dataclasses.replace(self.config, designs=()))
        return {"version": MANIFEST_VERSION, "cases": {c.case_id: str(c.rtstruct) for c in self.cases},
                "designs": list(self.designs), "targets": None if self.targets is None else list(self.targets),
                "dose": self.dose,
                "config": json.loads(json.dumps(config))}


@dataclass(frozen=True, eq=False)
class StudyResult:
    """A finished study.

    Parameters
    ----------
    out : Path
        The study's folder, as given to :func:`run_study`.
    table : pyarrow.Table
        The consolidated rows: one per case x design x target, or per failed task whose targets were not known.
    summaries : tuple of DesignSummary
        One per design.
    n_tasks : int
        Tasks of the study.
    n_resumed : int
        Tasks already done before this run.
    n_failed_tasks : int
        Tasks that failed.
    wall_s : float, s
        Wall time of this run.
    """

    out: Path
    table: pa.Table = field(repr=False)
    summaries: tuple[DesignSummary, ...]
    n_tasks: int
    n_resumed: int
    n_failed_tasks: int
    wall_s: float


def check_manifest(out: Path, want: dict[str, Any]) -> None:
    """Write the study's manifest ``want`` into ``out``, or check that the study already there has the same one.

    Parameters
    ----------
    out : Path
        The study's folder.
    want : dict of str to JSON value
        The manifest of the study to run (:meth:`StudySpec.manifest`).

    Raises
    ------
    StudyError
        ``out`` holds another study, or files that are not a study.
    """
    path = out / MANIFEST
    if path.exists():
        have = json.loads(path.read_text(encoding="utf-8"))
        if have != want:
            diff = [k for k in want if have.get(k) != want[k]] or ["version"]
            raise StudyError(f"{out} holds another study ({', '.join(diff)} differ); give the same arguments "
                                 "to resume it, or a new --out folder")
    elif out.exists() and any(out.iterdir()):
        raise StudyError(f"{out} is not empty and holds no study; give a new or empty --out folder")
    else:
        atomic_write_json(path, want)


def serial_results(todo: Sequence[T], config: Any, task_fn: Callable[[T, Any], R],
            fail: Callable[[T, str], R]) -> Iterator[tuple[T, R]]:
    """Run ``task_fn(task, config)`` per task in this process; a task that raises gives ``fail(task, reason)``.

    Parameters
    ----------
    todo : sequence of tasks
        Tasks with a unique ``key``.
    config : object
        Passed to every task.
    task_fn : callable (task, config) -> result
        Runs one task.
    fail : callable (task, reason) -> result
        The result of a task that raised.

    Yields
    ------
    tuple of (task, result)
        In the order of ``todo``.
    """
    for task in todo:
        try:
            rows = task_fn(task, config)
        except Exception as exc:  # a failing task is recorded, the study goes on
            rows = fail(task, f"{type(exc).__name__}: {exc}")
        yield task, rows


def dask_results(client: Any, todo: Sequence[T], config: Any, task_fn: Callable[[T, Any], R],
          fail: Callable[[T, str], R], worker_setup: Any = None, *, blocks: bool = True) -> Iterator[tuple[T, R]]:
    """Run ``task_fn(task, config)`` per task on the Dask ``client``, yielding results as they finish.

    Each task needs a unique ``key``; a task that raises (or whose worker keeps dying) gives ``fail(task, reason)``.

    Parameters
    ----------
    client : distributed.Client
        Connected client.
    todo : sequence of tasks
        Tasks with a unique ``key``.
    config : object
        Passed to every task.
    task_fn : callable (task, config) -> result
        Runs one task (importable by the workers).
    fail : callable (task, reason) -> result
        The result of a task that raised.
    worker_setup : WorkerSetup or None
        Registered on the cluster's workers first (:func:`setup_workers`); None: the default set-up.
    blocks : bool
        Prefer (loosely) one worker for each block of consecutive tasks, so a worker runs one case's tasks in a row
        and loads each case once; False (tasks that share nothing): each task to the first worker that frees.

    Yields
    ------
    tuple of (task, result)
        In the order they finish.

    Raises
    ------
    StudyError
        The scheduler cancelled a task.
    """
    from distributed import as_completed

    setup_workers(client, worker_setup)
    run = uuid.uuid4().hex[:8]
    workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
    futures = {}
    for k, t in enumerate(todo):
        # Case-major blocks of equal size per worker (a loose preference: the scheduler still moves tasks to idle
        # or surviving workers), so a worker runs one case's designs in a row and loads each case once.
        prefer = {"workers": [workers[k * len(workers) // len(todo)]], "allow_other_workers": True} \
            if workers and blocks else {}
        futures[client.submit(task_fn, t, config, key=f"reachplan-study-{run}-{t.key}", pure=False, **prefer)] = t
    try:
        for fut in as_completed(futures):
            task = futures[fut]
            if fut.status == "finished":
                rows = fut.result()
            elif fut.status == "cancelled":  # the scheduler dropped it (restarted, or the client lost it)
                raise StudyError(f"the Dask scheduler cancelled task {task.key}; run the study again to "
                                 "resume it (finished tasks are kept)")
            else:  # an error inside the task, or a worker that kept dying while running it (KilledWorker)
                exc = fut.exception()
                rows = fail(task, f"{type(exc).__name__}: {exc}")
            fut.release()
            yield task, rows
    finally:
        client.cancel(list(futures))


def run_study(spec: StudySpec, out: Path, *, scheduler: str | None = None, workers: int | None = None,
              client: Any = None, retry_failed: bool = False, quiet: bool = True,
              task_fn: TaskFn = run_task, worker_setup: Any = None) -> StudyResult:
    """Run (or resume) a study into the folder ``out``.

    Parameters
    ----------
    spec : StudySpec
        The cases, designs, targets and plan configuration.
    out : Path
        The study's folder (new, empty, or holding this study to resume).
    scheduler : str or None
        Address of a running Dask scheduler (``tcp://host:8786``); None = a local cluster.
    workers : int or None
        Worker processes of the local cluster (default: the CPU count); 0 = run in this process.
    client : distributed.Client or None
        An existing client to use instead (``scheduler``/``workers`` ignored).
    retry_failed : bool
        Run again the tasks a previous run recorded as failed.
    quiet : bool
        No progress bar.
    task_fn : callable (StudyTask, PlanConfig) -> sequence of StudyRow
        The function a worker runs per task (default :func:`run_task`; must be importable by workers).
    worker_setup : WorkerSetup or None
        How Dask workers are set up (:func:`setup_workers`); None: one thread per library, the kernels the tasks use
        loaded.

    Returns
    -------
    StudyResult
        The consolidated table and per-design summaries (also written to ``out``: parts, ``summary.csv``,
        ``summary.png``).

    Raises
    ------
    StudyError
        ``out`` holds another study or unrelated files; Dask or pyarrow is missing.
    """
    store.require_pyarrow()
    out = Path(out)
    t0 = time.perf_counter()
    check_manifest(out, spec.manifest())
    tasks = spec.tasks()
    done = store.finished(out)
    redo = store.failed_keys(out) if retry_failed else set()
    todo = [t for t in tasks if t.key not in done or t.key in redo]
    with ExitStack() as stack:
        if not todo:
            results: Iterator[tuple[StudyTask, Sequence[StudyRow]]] = iter(())
        elif client is None and scheduler is None and workers == 0:
            results = serial_results(todo, spec.config, task_fn, failed_rows)
        else:
            if client is None:
                client = stack.enter_context(dask_client(scheduler, workers, len(todo)))
            if worker_setup is None:  # the kernels the tasks use: the rod and the organs' distance (and the dose)
                from reachplan.planner.study.workers import WorkerSetup

                worker_setup = WorkerSetup(("distance", "rod", *(("dose",) if spec.dose else ())))
            results = dask_results(client, todo, spec.config, task_fn, failed_rows, worker_setup)
        bar = stack.enter_context(tqdm(total=len(todo), desc="study tasks", unit="task", disable=quiet or not todo))
        kill_after = _kill_after_parts()
        for n_written, (task, rows) in enumerate(results, start=1):
            store.write_part(out, task.key, rows)
            bar.update()
            if n_written == kill_after:  # test hook: die like a killed process, after a whole part file
                os.kill(os.getpid(), signal.SIGKILL)
    table = store.consolidate(out, [t.key for t in tasks])
    summaries = summarise(table)
    write_dataclass_csv(DesignSummary, summaries, out / "summary.csv")
    summary_figure(table, summaries, out / "summary.png")
    n_failed = len({k for k, s in zip(table["task"].to_pylist(), table["status"].to_pylist(), strict=True)
                    if s == "failed"})
    return StudyResult(out, table, summaries, len(tasks), len(tasks) - len(todo), n_failed,
                       time.perf_counter() - t0)


#: Test hook: the study process kills itself (SIGKILL) right after writing this many part files.
KILL_AFTER_PARTS_ENV = "REACHPLAN_STUDY_KILL_AFTER_PARTS"


def _kill_after_parts() -> int | None:
    value = os.environ.get(KILL_AFTER_PARTS_ENV, "")
    return int(value) if value.strip().isdigit() else None


#: The scheduler's HTTP server (health and metrics routes; it runs even without the dashboard) on a free loopback
#: port: its default, port 8787 on every interface, warns and moves when another cluster on the machine holds it.
LOOPBACK_HTTP = {"dashboard_address": "127.0.0.1:0"}


def dask_client(scheduler: str | None, workers: int | None, n_tasks: int) -> Any:
    """Connect a ``distributed.Client`` to ``scheduler``, or to a new loopback-only local cluster.

    The local cluster runs worker processes and is closed with the client.

    Parameters
    ----------
    scheduler : str or None
        Address of a running scheduler; None starts a local cluster.
    workers : int or None
        Worker processes of the local cluster (default: the CPU count).
    n_tasks : int
        Tasks to run (the local cluster starts no more workers than this).

    Returns
    -------
    distributed.Client or context manager
        The client for a scheduler; for a local cluster a context manager giving the client and closing both.

    Raises
    ------
    StudyError
        Dask is not installed, the scheduler cannot be reached, or ``workers`` < 1.
    """
    try:
        from distributed import Client, LocalCluster
    except ModuleNotFoundError:
        raise StudyError("dask[distributed] is not installed: pip install 'dask[distributed]', "
                             "or run in this process with --workers 0") from None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="20s")
        except OSError as exc:
            raise StudyError(f"cannot reach the Dask scheduler at {scheduler} ({exc}); start it with "
                                 "'dask scheduler' and give its address") from None
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise StudyError(f"--workers must be >= 0, got {n}")
    from reachplan.planner.study.workers import WORKER_ENV, worker_config

    # one thread per worker and per numerical library (numba, OpenMP, BLAS; HiGHS: WorkerSetup): parallelism comes
    # from the workers, one per core; the allocator set before the worker processes start
    with worker_config():
        cluster = LocalCluster(n_workers=min(n, n_tasks), threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, scheduler_kwargs=LOOPBACK_HTTP, env=dict(WORKER_ENV))
    client = Client(cluster)
    return _Closing(client, cluster)


def setup_workers(client: Any, plugin: Any = None) -> None:
    """Set up every worker of ``client``'s cluster, present and future, for study tasks (once per worker).

    One numba, HiGHS and BLAS thread and the numerical kernels loaded
    (:class:`reachplan.planner.study.workers.WorkerSetup`).

    Parameters
    ----------
    client : distributed.Client
        Connected client (a local cluster's or a scheduler's).
    plugin : WorkerSetup or None
        The set-up to register; None: ``WorkerSetup()`` (every kernel group).
    """
    from reachplan.planner.study.workers import WorkerSetup

    client.register_plugin(plugin if plugin is not None else WorkerSetup())


class _Closing:
    """Context manager closing a client and then the local cluster it runs on."""

    def __init__(self, client: Any, cluster: Any) -> None:
        self.client, self.cluster = client, cluster

    def __enter__(self) -> Any:
        return self.client

    def __exit__(self, *exc: object) -> None:
        self.client.close()
        self.cluster.close()

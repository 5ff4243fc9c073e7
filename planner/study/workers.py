r"""A study worker's set-up: one numba thread, one HiGHS thread, the numerical kernels loaded before the first case.

A study runs one case (or task) per worker thread and gets its parallelism from the workers, so every worker
computes on one core: more threads per task would only fight over the cores the other workers use (and the CPU time
a case reports would count their spinning).

- **numba**: the worker process starts with ``NUMBA_NUM_THREADS=1`` (:data:`WORKER_ENV`, set by the study's local
  cluster on its worker processes), and every task sets one thread for itself (:func:`limit_threads`: numba's
  thread count is per calling thread).
- **HiGHS** (the selection and dwell-time programmes, through SciPy): each thread that solves gets a task scheduler
  sized by its first solve (by default half the machine's cores; SciPy does not pass a thread count);
  :func:`limit_threads` makes the calling thread's first solve a one-thread one, after which every solve of that
  thread runs on one thread (HiGHS keeps a thread's first scheduler: a later solve asking for more gets the same).
- **BLAS / OpenMP**: one thread (:data:`WORKER_ENV`, read when the libraries load).
- **Memory allocator**: Dask's nanny starts a worker with ``MALLOC_TRIM_THRESHOLD_=65536``, which also fixes glibc's
  mmap threshold at 128 kB: every larger array is then mapped fresh and returned to the system when freed, and each
  new one faults its pages in again. A case allocates and frees such arrays by the thousand. Measured on clinical
  seeds 0, 3 and 4 in one process: 7.5, 4.1 and 7.1 s of CPU with glibc's defaults, 8.8, 5.0 and 8.3 s with Dask's
  setting alone (0.4-0.6 million page faults per case instead of 4-40 thousand); in a study's workers 0.5-1.3
  million page faults and 1-3.7 s of system time per case. :data:`ALLOCATOR_ENV` sets the thresholds glibc's own
  adaptive rule reaches (mmap 32 MiB, trim twice that; ``mallopt(3)``) before the worker process starts
  (:func:`worker_config`, which also turns Dask's statistical profiler off and slows its monitors:
  :data:`WORKER_DASK_CONFIG`).
- **Kernels**: :class:`WorkerSetup` (a Dask worker plugin, registered by the study on every worker of its cluster,
  a scheduler's included) loads every numba kernel from numba's on-disk cache (compiling, once per install, any
  that is missing) when the worker starts (:func:`reachplan.planner.kernels.warm_up`), so the first case a worker
  plans costs what the others do.

Workers of a cluster started by hand should get the same environment (a nanny takes the allocator's variables from
its environment before its configuration, and passes them on before the worker process starts)::

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \\
    MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=67108864 DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False \\
    DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL=1s DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL=2s \\
    DASK_DISTRIBUTED__WORKER__MEMORY__MONITOR_INTERVAL=1s \\
        dask worker tcp://SCHEDULER:8786 --nthreads 1 --nworkers N

and its scheduler :data:`SCHEDULER_DASK_CONFIG`
(``DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0 dask scheduler``).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import dask
from distributed.diagnostics.plugin import WorkerPlugin

#: Environment of a study's worker processes: one thread for numba, OpenMP and the BLAS libraries.
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}

#: glibc's allocator in a study's worker processes (set before they start, :func:`worker_config`): arrays up to
#: 32 MiB from the heap, the heap's top returned to the system past 64 MiB (instead of Dask's 64 kiB; module docstring)
ALLOCATOR_ENV = {"MALLOC_MMAP_THRESHOLD_": str(32 * 2**20), "MALLOC_TRIM_THRESHOLD_": str(64 * 2**20)}

#: Dask's configuration for a study's workers (:func:`worker_config`): no statistical profiler (it samples the task
#: thread's stack every 10 ms; a study never reads it), and Dask's own monitors at a slower pace (event-loop tick
#: every 1 s instead of 20 ms, system monitor every 2 s instead of 0.5 s, memory monitor every 1 s instead of 0.1 s:
#: nothing reads them but the memory limits). An idle worker process then uses 0.3 % of a core instead of 1.5 %
#: (measured: two workers over 30 s), CPU a case would be charged with.
WORKER_DASK_CONFIG = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "1s",
                      "distributed.admin.system-monitor.interval": "2s",
                      "distributed.worker.memory.monitor-interval": "1s"}

#: Dask's configuration for a study's scheduler: a worker holds one task at a time (with one thread, the default
#: saturation of 1.1 lets it take two), the others wait at the scheduler for the first worker that frees, so a worker
#: never waits while a task is held for another (a case takes 4-30 s; the extra round trip, milliseconds)
SCHEDULER_DASK_CONFIG = {"distributed.scheduler.worker-saturation": 1.0}

_HIGHS = threading.local()  # ``threads``: the HiGHS scheduler size this thread set


@dataclass(frozen=True)
class ThreadLimits:
    """The thread counts of this process's numerical libraries, as set by :func:`limit_threads`.

    Parameters
    ----------
    numba_threads : int or None
        numba's threads for the calling thread (None without numba).
    highs_threads : int or None
        Threads of the calling thread's HiGHS scheduler, when :func:`limit_threads` sized it (None: it did not).
    """

    numba_threads: int | None
    highs_threads: int | None


def _pin_highs(threads: int) -> int | None:
    """Size the calling thread's HiGHS scheduler with one tiny solve at ``threads`` threads (once per thread)."""
    if getattr(_HIGHS, "threads", None) is None:
        try:
            import numpy as np
            from scipy.optimize._highspy import _core as highs  # SciPy's HiGHS (a private module)
        except ImportError:  # pragma: no cover - SciPy without its bundled HiGHS
            return None
        h = highs._Highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("threads", int(threads))
        lp = highs.HighsLp()
        lp.num_col_, lp.num_row_ = 1, 0
        lp.col_cost_, lp.col_lower_, lp.col_upper_ = np.ones(1), np.zeros(1), np.ones(1)
        h.passModel(lp)
        h.run()
        _HIGHS.threads = int(threads)
    return int(_HIGHS.threads)


def limit_threads(threads: int = 1) -> ThreadLimits:
    """Run this thread's numerical work on ``threads`` threads: numba and HiGHS (BLAS: :data:`WORKER_ENV`).

    The thread's HiGHS scheduler is sized only if it has not solved yet (see the module docstring): call this before
    the first solve.

    Parameters
    ----------
    threads : int
        Threads per library, >= 1.

    Returns
    -------
    ThreadLimits
        The counts in force.
    """
    numba_threads: int | None = None
    try:
        import numba

        numba.set_num_threads(min(threads, int(getattr(numba.config, "NUMBA_NUM_THREADS", threads))))
        numba_threads = int(numba.get_num_threads())
    except ImportError:  # pragma: no cover - numba is a dependency
        pass
    return ThreadLimits(numba_threads, _pin_highs(threads))


@contextlib.contextmanager
def worker_config() -> Iterator[None]:
    """Create Dask nannies in this context to start study workers with :data:`ALLOCATOR_ENV`, Dask's as set here.

    Dask's ``distributed.nanny.pre-spawn-environ`` with the allocator's variables added, and the worker's statistical
    profiler off and monitors slowed (:data:`WORKER_DASK_CONFIG`). A nanny takes both when
    it is created (and keeps them for restarts), so create the cluster inside the context; its scheduler then takes
    :data:`SCHEDULER_DASK_CONFIG`. A nanny prefers this
    process's environment to its configuration, and an earlier nanny leaves Dask's own values there: the allocator's
    variables are set in it too while the context lasts.

    Yields
    ------
    None
    """
    pre = {**(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {}), **ALLOCATOR_ENV}
    before = {k: os.environ.get(k) for k in ALLOCATOR_ENV}
    os.environ.update(ALLOCATOR_ENV)
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": pre, **WORKER_DASK_CONFIG,
                              **SCHEDULER_DASK_CONFIG}):
            yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def on_worker() -> bool:
    """Return True when called inside a Dask worker's task.

    Returns
    -------
    bool
        Whether a ``distributed`` worker runs the calling code.
    """
    from distributed import get_worker

    try:
        get_worker()
    except ValueError:
        return False
    return True


class WorkerSetup(WorkerPlugin):
    """Dask worker plugin: one thread per numerical library and the kernels loaded, when the worker starts.

    Registered with ``client.register_plugin(WorkerSetup())``; Dask runs :meth:`setup` on every worker, present and
    future. The seconds it took and the thread counts are kept on the worker (``worker.reachplan_setup``).

    Parameters
    ----------
    groups : tuple of str
        The kernel groups to load (or compile) (:func:`reachplan.planner.kernels.warm_up`; default: all); empty:
        none.
    """

    name = "reachplan-study-setup"

    idempotent = True  # registering it again (a resumed study on the same cluster) does not set the workers up twice

    def __init__(self, groups: tuple[str, ...] | None = None) -> None:
        from reachplan.planner.kernels import GROUPS

        self.groups = GROUPS if groups is None else tuple(groups)

    def setup(self, worker: Any) -> None:
        """Limit the threads and warm the kernels in the worker's process.

        Parameters
        ----------
        worker : distributed.Worker
            The worker being set up.
        """
        t, cpu = time.perf_counter(), time.process_time()
        limits = limit_threads(1)
        if self.groups:
            from reachplan.planner.kernels import warm_up

            warm_up(self.groups)
        worker.reachplan_setup = {"seconds": round(time.perf_counter() - t, 3),
                                  "cpu_seconds": round(time.process_time() - cpu, 3),
                                  "numba_threads": limits.numba_threads, "highs_threads": limits.highs_threads,
                                  "kernel_groups": list(self.groups),
                                  "env": {k: os.environ.get(k) for k in (*WORKER_ENV, *ALLOCATOR_ENV)},
                                  "dask": {k: dask.config.get(k) for k in WORKER_DASK_CONFIG}}

    def teardown(self, worker: Any) -> None:
        """Nothing to undo.

        Parameters
        ----------
        worker : distributed.Worker
            The worker being closed.
        """

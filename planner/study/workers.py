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
- **Kernels**: :class:`WorkerSetup` (a Dask worker plugin, registered by the study on every worker of its cluster,
  a scheduler's included) loads every numba kernel from numba's on-disk cache (compiling, once per install, any
  that is missing) when the worker starts (:func:`reachplan.planner.kernels.warm_up`), so the first case a worker
  plans costs what the others do.

Workers of a cluster started by hand should get the same environment::

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \\
        dask worker tcp://SCHEDULER:8786 --nthreads 1 --nworkers N
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

#: Environment of a study's worker processes: one thread for numba, OpenMP and the BLAS libraries.
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}

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
                                  "env": {k: os.environ.get(k) for k in WORKER_ENV}}

    def teardown(self, worker: Any) -> None:
        """Nothing to undo.

        Parameters
        ----------
        worker : distributed.Worker
            The worker being closed.
        """

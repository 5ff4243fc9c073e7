"""The numba kernels: compiled once after an install, in a background process while a plan starts.

Every numba kernel is compiled with ``cache=True``, so only the first run after an install (or after numba's cache
was emptied) compiles; that costs about 10 s of CPU, mostly the two-tube rod kernel. A plan spends its first
seconds on work that needs no rod or dose kernel (the case write, the scene: organ meshes and distance fields) on
one core; :func:`start` compiles the rod and dose kernels meanwhile in a child interpreter on the other core, into
the same on-disk cache, in the order a plan needs them. The main process compiles the kernels it needs first (the
case's sweep field, the organ distance field) itself, and the first time it calls a rod or dose kernel it waits
for the child to have compiled that group (:meth:`_Child.wait`), then loads the machine code from the cache.

Races: numba writes each cache file (index and data) to a temporary name and renames it into place
(``numba.core.caching.IndexDataCacheFile._open_for_write``, ``os.replace``), so a reader sees a whole file or none.
Two processes saving *different* signatures of one function could still lose an index entry, so the main process
never compiles a kernel of a group while the child works on it: it waits, and compiles only what the child did not
(a signature the child's work did not use), after the child has finished that group.

Kernel groups (:data:`GROUPS`): ``sweep`` (the applicator sweep field, :mod:`reachplan.imaging`), ``distance`` (the
organ distance field), ``rod`` (the two-tube rod) and ``dose`` (TG-43); :func:`warm_up` compiles groups in this
process (the first-run benchmark's kernels-only work). Run as a program (:func:`main`)::

    python -m reachplan.planner.kernels warm [GROUP...]       compile the groups here (default: all); errors raise
    python -m reachplan.planner.kernels child DIR GROUP...    the background child: for each group compile its
                                                             kernels, then create DIR/GROUP.done

The command line starts the background compile (:func:`start`); the benchmarks read :func:`waited_s`.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

#: every kernel group, in the order a plan needs them
GROUPS: tuple[str, ...] = ("sweep", "distance", "rod", "dose")
#: the groups the child compiles, in the order a plan needs them (planning: rod, delivery: dose)
BACKGROUND: tuple[str, ...] = ("rod", "dose")
#: longest wait for one group (s): a child that hangs must not hang the plan (the main process then compiles)
_MAX_WAIT_S = 600.0


def _modules(group: str) -> list[ModuleType]:
    """Import and return the kernel modules of ``group``."""
    if group == "sweep":
        from reachplan.imaging import _sweep_kernel

        return [_sweep_kernel]
    if group == "distance":
        from reachplan.planner.geometry import distance_field

        return [distance_field]
    if group == "rod":
        from reachplan.rod_model import _kernel

        return [_kernel]
    if group == "dose":
        from reachplan.planner.dose import _tg43_numba

        return [_tg43_numba]
    raise ValueError(f"unknown kernel group {group!r}")


def _dispatchers(group: str) -> list[Any]:
    """Return the numba dispatchers of ``group``'s modules (none without numba)."""
    try:
        from numba.core.dispatcher import Dispatcher
    except ImportError:  # pragma: no cover - the rod kernel runs as plain Python without numba
        return []
    return [v for m in _modules(group) for v in vars(m).values() if isinstance(v, Dispatcher)]


def warm_up(groups: Sequence[str] = GROUPS) -> None:
    """Compile (or load from numba's cache) the kernels of ``groups`` in this process, one group after the other.

    Each group's kernels are called with the argument types a plan uses: the public calls, on tiny inputs.

    Parameters
    ----------
    groups : sequence of str
        Kernel groups, each one of :data:`GROUPS` (default: all).

    Raises
    ------
    ValueError
        An unknown group.
    """
    for group in groups:
        _warm(group)


def _warm(group: str) -> None:
    """Compile (or load) ``group``'s kernels with the argument types a plan uses: the public calls, on tiny inputs."""
    import numpy as np

    if group == "sweep":
        from reachplan.imaging._sweep_kernel import warm_up as warm_sweep

        warm_sweep()
    elif group == "distance":
        from reachplan.planner.geometry.distance_field import warm_up as warm_distance

        warm_distance()
    elif group == "rod":
        from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT as model  # the registered built-in
        from reachplan.rod_model.design import preset

        d = preset("15ga-30j-tip")
        model.solve(d, d.loads(5.0))
        model.solve_batch(d, np.array([1.0, 2.0]))
    elif group == "dose":
        from reachplan.imaging.types import Grid
        from reachplan.planner.dose.dwells import DwellSet, dose_on_grid
        from reachplan.planner.dose.tg43 import Tg43Kernel
        from reachplan.plugins.sources import BUILTIN

        k = Tg43Kernel(BUILTIN["gammamed_plus_hdr"]())
        dw = DwellSet(np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)), np.ones(2))
        k.compiled_rates(np.ones((3, 3)), dw.positions_mm, dw.directions)
        k.compiled_dose(np.ones((3, 3)), dw.positions_mm, dw.directions, np.ones(2))
        dose_on_grid(Grid((4, 4, 4), np.diag([2.0, 2.0, 2.0, 1.0])), dw, k, 40000.0)
    else:
        raise ValueError(f"unknown kernel group {group!r}")


def cold(group: str) -> bool:
    """Whether ``group`` has a kernel without fresh machine code in numba's cache.

    Reads numba's cache index (an internal of numba: any surprise there reads as "cold", which costs only a
    child that loads the kernels from the cache). A stale index (the source changed, e.g. a reinstall) is cold. A
    function inlined into its callers (``inline="always"``) has no cache of its own and is not counted.

    Parameters
    ----------
    group : str
        A kernel group of :data:`GROUPS` (``"sweep"``, ``"distance"``, ``"rod"``, ``"dose"``).

    Returns
    -------
    bool
        True when a kernel of the group would compile on its first call.
    """
    try:
        return any(not d._cache._cache_file._load_index() for d in _dispatchers(group) if not _inlined(d))
    except Exception:
        return True


def _inlined(dispatcher: Any) -> bool:
    """Whether ``dispatcher`` is inlined into its callers (``inline="always"``): it then has no machine code of its own.

    Numba compiles such a function into each kernel that calls it, never on its own, so it never has a cache file:
    counting it made the TG-43 group read as cold on every run (and every run started a background compile).
    """
    return getattr(dispatcher, "targetoptions", {}).get("inline", "never") == "always"


class _Child:
    """The background compile: the child process and its folder of ``GROUP.done`` markers."""

    def __init__(self, proc: subprocess.Popen[bytes], folder: Path) -> None:
        self.proc = proc
        self.folder = folder
        self.done: set[str] = set()
        self.waited_s: dict[str, float] = {}  # how long the main process waited for each group

    def wait(self, group: str) -> None:
        """Block until the child has compiled ``group`` (or has exited).

        Parameters
        ----------
        group : str
            The kernel group whose ``GROUP.done`` marker is awaited (at most ``_MAX_WAIT_S`` seconds).
        """
        marker = self.folder / f"{group}.done"
        t0 = time.perf_counter()
        while not marker.exists() and self.proc.poll() is None and time.perf_counter() - t0 < _MAX_WAIT_S:
            time.sleep(0.02)
        self.done.add(group)
        self.waited_s[group] = time.perf_counter() - t0


_child: _Child | None = None


def waited_s() -> float:
    """Return how long this process has waited for the background compile, s (0 when none was started).

    Returns
    -------
    float
        The sum over kernel groups of the main process's waits (:func:`start`), s.
    """
    return sum(_child.waited_s.values()) if _child is not None else 0.0


def _hook(group: str, dispatcher: Any) -> Callable[[], None]:
    """Return ``dispatcher``'s compile hook, which first waits for the child's work on ``group``."""
    numba_hook = dispatcher._compilation_chain_init_hook  # numba's own (it initialises extension entry points)

    def hook() -> None:  # numba calls it before compiling (or loading) a new signature called from Python
        if _child is not None and group not in _child.done:
            _child.wait(group)
        numba_hook()

    return hook


def start(quiet: bool = False) -> bool:
    """Start compiling the cold kernel groups in a background process; return whether one was started.

    Prints one line on stderr unless ``quiet``. Safe to call more than once (the second call does nothing).
    Without numba, with numba's JIT disabled, or when every group is cached, nothing is started.

    Parameters
    ----------
    quiet : bool
        No line on stderr.

    Returns
    -------
    bool
        True when a background process was started.
    """
    global _child
    if _child is not None or os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return False
    try:
        groups = [g for g in BACKGROUND if _dispatchers(g) and cold(g)]
    except ImportError:  # pragma: no cover - numba missing
        return False
    if not groups:
        return False
    folder = Path(tempfile.mkdtemp(prefix="reachplan-kernels-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)  # a child still compiling then fails only its marker
    proc = subprocess.Popen([sys.executable, "-m", __spec__.name, "child", str(folder), *groups],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    atexit.register(proc.poll)  # reap a child that has finished: its CPU time is then counted as this process's
    _child = _Child(proc, folder)
    for g in groups:
        for d in _dispatchers(g):
            # numba's Dispatcher._compile_for_args calls this per-instance hook first (an internal of numba; a
            # numba without it only loses the wait: both processes then compile, each saving whole files)
            d._compilation_chain_init_hook = _hook(g, d)
    if not quiet:
        print("reachplan: compiling the numerical kernels once (first run after an install: about 10 s of CPU), "
              "in the background; later runs load them from the cache", file=sys.stderr)
    return True


def stop() -> None:
    """Stop the background compile if it still runs (the command was interrupted: nothing waits for it any more)."""
    if _child is not None and _child.proc.poll() is None:
        _child.proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            _child.proc.wait(timeout=5)


def main(argv: Sequence[str]) -> int:
    """Run ``python -m reachplan.planner.kernels`` (see the module docstring) on ``argv``; return the exit code.

    Parameters
    ----------
    argv : sequence of str
        ``["warm", GROUP, ...]``: compile the groups in this process (none named: every group), errors raise;
        ``["child", DIR, GROUP, ...]``: the background child of :func:`start`.

    Returns
    -------
    int
        0; 2 for arguments of neither form.
    """
    if argv[:1] == ["warm"] and set(argv[1:]) <= set(GROUPS):
        warm_up(argv[1:] or GROUPS)
        return 0
    if argv[:1] == ["child"] and len(argv) >= 2:
        return _background(Path(argv[1]), argv[2:])
    print(f"usage: python -m {__spec__.name} warm [GROUP...] | child DIR GROUP... (groups: {', '.join(GROUPS)})",
          file=sys.stderr)
    return 2


def _background(folder: Path, groups: Sequence[str]) -> int:
    """Run the child: compile each group in turn, then create ``folder/GROUP.done``."""
    for group in groups:
        try:
            _warm(group)
        except Exception as exc:  # the main process compiles what is missing and reports any real error itself
            with contextlib.suppress(OSError):
                (folder / f"{group}.error").write_text(f"{type(exc).__name__}: {exc}\n", encoding="utf-8")
        try:
            (folder / f"{group}.done").touch()
        except OSError:  # the main process has exited (and removed the folder): nobody waits
            return 0
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

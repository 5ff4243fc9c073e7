"""Progress bars that move during a long step: refreshed from a thread, so the elapsed time keeps counting.

A tqdm bar is redrawn only when it is updated; a step of 20 s with no update looks stuck (and its rate-based ETA is
wrong). :class:`MovingBar` redraws itself every half second until it is closed; :func:`spinner` is one for a step
of unknown length (no total, no ETA: the step's name and its elapsed time).
"""

from __future__ import annotations

import threading
from typing import Any

from tqdm import tqdm


class MovingBar(tqdm):
    """A tqdm bar redrawn every ``every_s`` seconds from a daemon thread until :meth:`close`.

    Parameters
    ----------
    *args : Any
        tqdm's.
    every_s : float
        Seconds between redraws.
    **kwargs : Any
        tqdm's (``disable=True``: no thread).
    """

    def __init__(self, *args: Any, every_s: float = 0.5, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        if not self.disable:
            self._ticker = threading.Thread(target=self._tick, args=(every_s,), name="reachplan-progress",
                                            daemon=True)
            self._ticker.start()

    def _tick(self, every_s: float) -> None:
        while not self._stop.wait(every_s):
            self.refresh()

    def close(self) -> None:
        """Stop the redraws and close the bar."""
        stop = getattr(self, "_stop", None)
        if stop is not None:
            stop.set()
        ticker = getattr(self, "_ticker", None)
        if ticker is not None and ticker is not threading.current_thread():
            ticker.join()
        super().close()


def spinner(desc: str, quiet: bool) -> MovingBar:
    """Return a bar for a step of unknown length: its name and elapsed time, redrawn every half second.

    Use it as a context manager (closed at the end of the block).

    Parameters
    ----------
    desc : str
        What the step does.
    quiet : bool
        No bar.

    Returns
    -------
    MovingBar
        The bar (no total, no ETA).
    """
    return MovingBar(total=None, desc=desc, bar_format="{desc}: {elapsed}", disable=quiet, leave=False)

"""What a study's cases cost: CPU and wall seconds per case and per planning stage (``summary.json`` ``cost``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


def cost_json(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return ``summary.json``'s ``cost``: CPU seconds per case (both arms and every design) and per stage.

    Parameters
    ----------
    parts : sequence of mapping
        Each case's part (its row's ``cpu_seconds`` and ``seconds``, and ``cpu_s`` by stage when planned).

    Returns
    -------
    dict of str to JSON value
        ``cpu_s_per_case`` and ``wall_s_per_case`` (``median``, ``mean``, ``max``, ``n``) over the cases with a
        time, and ``stage_cpu_s_median``: the median of each stage (``case``, ``scene``, ``candidates``, ``arms``,
        ``check``). CPU time is the worker process's (all its threads), so it does not grow when cores are shared.
    """
    def dist(values: list[float]) -> dict[str, Any]:
        if not values:
            return {"median": None, "mean": None, "max": None, "n": 0}
        return {"median": round(float(np.median(values)), 3), "mean": round(float(np.mean(values)), 3),
                "max": round(max(values), 3), "n": len(values)}

    rows = [p["row"] for p in parts]
    stages: dict[str, list[float]] = {}
    for p in parts:
        for k, v in (p.get("cpu_s") or {}).items():
            stages.setdefault(k, []).append(float(v))
    return {"cpu_s_per_case": dist([float(r["cpu_seconds"]) for r in rows if r.get("cpu_seconds") is not None]),
            "wall_s_per_case": dist([float(r["seconds"]) for r in rows if r.get("seconds") is not None]),
            "stage_cpu_s_median": {k: round(float(np.median(v)), 3) for k, v in stages.items()},
            "note": "CPU seconds of the process that planned the case, all its threads (on a study worker: one "
                    "numba and one HiGHS thread, kernels loaded before the first case)"}

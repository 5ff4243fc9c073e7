"""The dwell-optimiser seam: what a dwell optimiser is given, what it returns, and how one is chosen by name.

An optimiser loads dwell columns with times: given each structure's dose-rate rows (target sample points with the
dose each should reach; each organ's representative points with the volume each stands for and the organ's D2cm³
limit), the modulation rules and, optionally, which channels are needles (with their template hole and cost) and a
needle budget, it returns the dwell time of every column, a status, the objective and, where it has one, a lower
bound. The implant planner asks it twice (:mod:`reachplan.planner.implant.plan`): to select at most K needles among
the candidates (with ``budget``), and for the dwell times of the chosen channels (without).

Optimisers register under the entry-point group ``reachplan.optimisers`` (the built-in ``"lp"``:
:data:`reachplan.planner.implant.selection.LP`) and are chosen by name with
:attr:`reachplan.planner.implant.settings.ImplantSettings.optimiser`. A new optimiser is one module holding an
object with a ``name`` and an ``optimise`` method (:class:`DwellOptimiser`), plus its entry point.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast, runtime_checkable

import numpy as np

from reachplan.planner import lookup

#: key of :attr:`DwellProblem.cache` under which a caller may leave a similar problem solved before (the last round
#: of a robust loading: the same columns and target rows, a subset of its row sets); an optimiser may start from
#: what it found there (the built-in ``"lp"``: its last basis) and should not keep the reference
WARM_START = "warm_start"
#: key of :attr:`DwellProblem.cache` whose dict every restriction of the problem (:func:`restricted`) shares: a
#: selection has the same LP in each, so an optimiser may keep there what holds for a needle set in all of them
#: (the built-in ``"lp"``: each enumerated selection's LP, by its channels)
SHARED = "shared"


@dataclass(frozen=True, eq=False)
class OrganRows:
    """One structure's tail rows: the mean dose over its hottest ``volume_cc`` within a limit.

    An organ's D2cm³ rows (nominal, or with one needle displaced: a robustness scenario), or the HR-CTV's V200 rows
    (its hottest ``v200_max_pct`` of volume under twice the prescription).

    Parameters
    ----------
    rates : (p, D) float, Gy s⁻¹ per fraction
        Dose per second of dwell at each representative point from each dwell column.
    weight_cc : (p,) float, cm³
        Volume each point stands for.
    limit_gy : float, Gy per fraction
        D2cm³ limit (physical).
    volume_cc : float, cm³
        The hottest volume whose mean dose is held within the limit (2 for D2cm³).
    name : str
        What the rows stand for (e.g. ``"Bladder"``, ``"Bladder, needle 3 +x"``, ``"HR-CTV V200"``).
    """

    rates: np.ndarray
    weight_cc: np.ndarray
    limit_gy: float
    volume_cc: float = 2.0
    name: str = ""


@dataclass(frozen=True)
class Modulation:
    """How dwell times may be modulated, and the objective's weights.

    Parameters
    ----------
    max_dwell_share : float, in (0, 1]
        No dwell carries more than this share of the total time.
    neighbour_ratio : float
        Neighbouring dwell times on a channel differ by at most this factor (>= 1).
    time_weight : float
        Weight of the mean target dose (shorter plans) in the objective.
    invasiveness_weight : float
        Weight of each used needle's cost (its invasiveness) in the objective.
    smoothness_weight : float
        Weight of the dwell-time gradient term in the objective (0: none).
    """

    max_dwell_share: float
    neighbour_ratio: float
    time_weight: float
    invasiveness_weight: float
    smoothness_weight: float = 0.0


@dataclass(frozen=True, eq=False)
class NeedleChoice:
    """The channels that are needles (a binary each: used or not), their template holes and costs.

    Parameters
    ----------
    channels : tuple of int
        Channel numbers (values of :attr:`DwellProblem.channel`) that are needles; the other channels
        (intracavitary) are always available.
    holes : tuple of str
        Template hole of each needle (a hole takes one needle).
    cost : (n,) float, unitless
        Invasiveness of each needle (normalised hole distance and tissue length).

    Raises
    ------
    ValueError
        Channels, holes and costs of different lengths.
    """

    channels: tuple[int, ...]
    holes: tuple[str, ...]
    cost: np.ndarray

    def __post_init__(self) -> None:
        if not len(self.channels) == len(self.holes) == len(self.cost):
            raise ValueError("needle choice: channels, holes and costs must have one entry per needle")


@dataclass(frozen=True, eq=False)
class DwellProblem:
    """What a dwell optimiser loads: dose-rate rows per structure, the rules, and optionally the needle binaries.

    Columns are dwell positions (``D`` of them). The problem object is built once and handed to the optimiser
    for every solve (a selection solves many); an optimiser may keep what it builds from it in :attr:`cache`.

    Parameters
    ----------
    target_rates : (m, D) float, Gy s⁻¹ per fraction
        Dose per second of dwell at the target (and GTV) sample points.
    target_dose_gy : (m,) float, Gy per fraction
        The dose each target point should reach.
    reference_dose_gy : float, Gy per fraction
        The prescription the objective is normalised by.
    organs : tuple of OrganRows
        The D2cm³ rows of each organ with a limit.
    channel : (D,) int
        Channel of each column.
    modulation : Modulation
        Dwell-share and neighbour rules, the objective's weights.
    units : tuple of (k,) int arrays, optional
        Runs of consecutive columns of one channel that share one time (the selection model's blocks); None: each
        column its own time.
    needles : NeedleChoice, optional
        The needle binaries; None: every channel is loaded as given (no selection).
    swap_pool, swap_passes : int
        Effort of a selecting optimiser's local search (candidates considered, passes), for those that search.
    min_time_s : float, s
        A loaded column carries at least this time (each column 0 or >= ``min_time_s``; 0: no such rule).
    exhaustive_max : int
        A selecting optimiser that can enumerate solves every selection of at most the budget (one needle per hole)
        when there are at most this many (0: never), and so proves its selection optimal.
    cache : dict
        Scratch space for optimisers (e.g. a built LP), keyed by the optimiser's name; its :data:`SHARED` entry is
        shared with the problem's restrictions.
    """

    target_rates: np.ndarray
    target_dose_gy: np.ndarray
    reference_dose_gy: float
    organs: tuple[OrganRows, ...]
    channel: np.ndarray
    modulation: Modulation
    units: tuple[np.ndarray, ...] | None = None
    needles: NeedleChoice | None = None
    swap_pool: int = 8
    swap_passes: int = 3
    min_time_s: float = 0.0
    exhaustive_max: int = 0
    cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def n_columns(self) -> int:
        """Number of dwell columns ``D``."""
        return int(self.target_rates.shape[1])

    @property
    def limits_gy(self) -> np.ndarray:
        """(n_organs,) float, Gy per fraction: each organ's D2cm³ limit."""
        return np.array([o.limit_gy for o in self.organs])

    def tail_means(self, times_s: np.ndarray) -> np.ndarray:
        """Return each row set's mean dose over its hottest ``volume_cc`` of points.

        Parameters
        ----------
        times_s : (D,) float, s
            Dwell time of each column.

        Returns
        -------
        (n_organs,) float, Gy per fraction
        """
        return np.array([float(tail_mean((o.rates @ times_s)[:, None], o.weight_cc, o.volume_cc)[0])
                         for o in self.organs])


@dataclass(frozen=True, eq=False)
class DwellSolution:
    """An optimiser's answer.

    Parameters
    ----------
    times_s : (D,) float, s per fraction, or None
        Dwell time of each column; None when no loading was found (``status`` says why).
    status : str
        How the optimiser ended (reported in plan.json).
    objective : float
        The optimiser's objective at ``times_s`` (inf when there is none); the built-in ``"lp"``'s is unitless
        (doses in units of :attr:`DwellProblem.reference_dose_gy`).
    bound : float or None
        A lower bound of the objective over every loading the problem allows (e.g. an LP relaxation's optimum);
        None when the optimiser has none.
    needles : tuple of int
        The needles used, as indices into :attr:`NeedleChoice.channels` (ascending).
    """

    times_s: np.ndarray | None
    status: str
    objective: float = float("inf")
    bound: float | None = None
    needles: tuple[int, ...] = ()


@runtime_checkable
class DwellOptimiser(Protocol):
    """A dwell optimiser (registered under ``reachplan.optimisers``, chosen by ``ImplantSettings.optimiser``).

    Attributes
    ----------
    name : str
        The name it is registered and chosen by.

    Notes
    -----
    The registry checks the shape only (a str ``name``, a callable ``optimise``); an optional str ``description``
    is what plan.json's ``selection.model`` says of it.
    """

    name: str

    def optimise(self, problem: DwellProblem, *, budget: int | None = None, limit_factor: np.ndarray | None = None,
                 start: Sequence[Sequence[int]] = ()) -> DwellSolution:
        """Load the problem's columns.

        Parameters
        ----------
        problem : DwellProblem
            The rows, rules and (optionally) needle binaries to load.
        budget : int, optional
            At most this many needles (of ``problem.needles``) used; None: no budget (every needle may be used).
        limit_factor : (n_organs,) float, unitless, optional
            Each organ's D2cm³ rows may reach this factor × its limit (the planner calibrates it to the exact
            D2cm³); None: 1.
        start : sequence of sequence of int
            Selections to start from (each indices into ``problem.needles.channels``), e.g. a smaller budget's and
            another arm's at this budget.

        Returns
        -------
        DwellSolution
        """
        ...


def restricted(problem: DwellProblem, allowed: Sequence[int]) -> DwellProblem:
    """Return the selection problem on the channels ``allowed`` alone: the same rows, their units and needles.

    A selection of its needles has the same LP in it as in ``problem`` (the objective's scales are the whole
    problem's), so it gets the same score in either.

    Parameters
    ----------
    problem : DwellProblem
        A selection problem (with ``units`` and ``needles``).
    allowed : sequence of int
        Channels kept (values of :attr:`DwellProblem.channel`).

    Returns
    -------
    DwellProblem
        With an empty cache but for ``problem``'s :data:`SHARED` dict (the same object).
    """
    keep = set(allowed)
    units = tuple(u for u in (problem.units or ()) if int(problem.channel[u[0]]) in keep)
    choice = problem.needles
    assert choice is not None
    on = [i for i, c in enumerate(choice.channels) if c in keep]
    needles = NeedleChoice(tuple(choice.channels[i] for i in on), tuple(choice.holes[i] for i in on),
                           choice.cost[on])
    return dataclasses.replace(problem, units=units, needles=needles,
                               cache={SHARED: problem.cache.setdefault(SHARED, {})})


def tail_mean(rates: np.ndarray, weight_cc: np.ndarray, volume_cc: float) -> np.ndarray:
    """Return the mean of each column over its hottest ``volume_cc`` (rows weighted by the volume each stands for).

    A column whose rows hold less than ``volume_cc`` is averaged over ``volume_cc`` all the same (the mean-tail-dose
    row's value with its threshold at 0).

    Parameters
    ----------
    rates : (p, k) float, Gy or Gy s⁻¹
        Dose (or dose rate) of each row in each column.
    weight_cc : (p,) float, cm³
        Volume each row stands for.
    volume_cc : float, cm³
        The hottest volume averaged over (2 for D2cm³).

    Returns
    -------
    (k,) float
        In the unit of ``rates``.
    """
    if rates.size == 0:
        return np.zeros(rates.shape[1] if rates.ndim == 2 else 0)
    order = np.argsort(-rates, axis=0, kind="stable")
    r = np.take_along_axis(rates, order, axis=0)
    w = weight_cc[order]
    before = np.cumsum(w, axis=0) - w
    part = np.clip(volume_cc - before, 0.0, w)
    out: np.ndarray = (part * r).sum(axis=0) / volume_cc
    return out


def resolve(name: str) -> DwellOptimiser:
    """Return the dwell optimiser registered as ``name``.

    Parameters
    ----------
    name : str
        Its entry-point name in ``reachplan.optimisers`` (e.g. ``"lp"``).

    Returns
    -------
    DwellOptimiser

    Raises
    ------
    reachplan.plugins.errors.PluginError
        No optimiser of that name is installed (the message lists the available ones), or it is unavailable.
    """
    return cast(DwellOptimiser, lookup.optimiser(name))

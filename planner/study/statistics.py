"""Paired statistics for straight-against-steered cohorts: tests, intervals, effect sizes and a power note.

Each case gives one paired difference (steered against straight). What fits depends on the data:

* **Needle counts** (small integers, many ties and zeros): the Wilcoxon signed-rank test (zero differences dropped,
  Wilcoxon's convention; the exact null distribution without ties and n <= 50, else the normal approximation with
  the tie correction; scipy's ``wilcoxon``), the exact sign test beside it (a binomial
  test on the non-zero differences, which assumes nothing about their size), and a percentile bootstrap interval of
  the mean difference (:func:`bootstrap_ci`: resampling cases, no normality assumed; Efron & Tibshirani, *An
  Introduction to the Bootstrap*, 1993, ch. 13). Effect sizes: the matched-pairs rank-biserial correlation
  ``(W+ - W-) / (W+ + W-)`` (Kerby, Comprehensive Psychology 3:11.IT.3.1, 2014) and Cohen's ``d_z`` (mean / SD of
  the differences).
* **Doses** (continuous): the paired t-test and its t-interval (``mean ± t(0.975, n - 1) s / √n``; NIST/SEMATECH
  e-Handbook 1.3.5.2; Rice, *Mathematical Statistics and Data Analysis*, 3rd ed. 2007, 11.3), which assume roughly
  normal differences, and the Wilcoxon signed-rank test beside it, which assumes only a symmetric distribution.

Cases are assumed independent (one per patient anatomy). The **power note** (:func:`cases_for_power`) gives the
smallest cohort in which a two-sided paired t-test at α = 0.05 detects a given mean difference with 80 % power
when the differences have the observed standard deviation (non-central t; Cohen, *Statistical Power Analysis*, 2nd
ed. 1988, ch. 2), and the Wilcoxon test's need from it by its asymptotic relative efficiency 3/π (Lehmann,
*Nonparametrics*, 1975, ch. 4).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.planner.errors import StudyError

#: Resamples of the bootstrap intervals and the seed of their generator (the intervals are reproducible).
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 20261205


@dataclass(frozen=True)
class PairedStat:
    """Mean of a paired difference over the cases and its two-sided t confidence interval (same unit).

    Parameters
    ----------
    mean : float or None, same unit as the differences
        Mean difference; None when no case gives one.
    low, high : float or None
        Interval bounds; None when fewer than two cases give a difference (no spread to estimate).
    n : int
        Cases that give a difference.
    level : float
        The interval's confidence level, in (0, 1).
    """

    mean: float | None
    low: float | None
    high: float | None
    n: int
    level: float


def _diffs(diffs: Sequence[float] | np.ndarray) -> np.ndarray:
    d = np.asarray(diffs, dtype=float).ravel()
    if not np.all(np.isfinite(d)):
        raise StudyError("a paired difference is not finite; check the cases' results")
    return d


def _check_level(level: float) -> None:
    if not 0.0 < level < 1.0:
        raise StudyError(f"confidence level must be in (0, 1), got {level}")


def t_interval(diffs: Sequence[float] | np.ndarray, level: float = 0.95) -> PairedStat:
    """Return the mean of the paired differences ``diffs`` and its Student t confidence interval.

    ``mean ± t(1 - α/2, n - 1) · s / √n`` with ``α = 1 - level`` and ``s`` the sample standard deviation
    (NIST/SEMATECH e-Handbook of Statistical Methods, 1.3.5.2; Rice 2007, 11.3).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences (steered minus straight), in their own unit.
    level : float
        Confidence level, in (0, 1).

    Returns
    -------
    PairedStat
        Mean and interval, in the unit of ``diffs``.

    Raises
    ------
    StudyError
        ``level`` outside (0, 1) or a difference that is not finite.
    """
    from scipy.stats import t as student_t

    _check_level(level)
    d = _diffs(diffs)
    n = len(d)
    if n == 0:
        return PairedStat(None, None, None, 0, level)
    mean = float(d.mean())
    if n == 1:
        return PairedStat(mean, None, None, 1, level)
    half = float(student_t.ppf(0.5 + level / 2.0, n - 1)) * float(d.std(ddof=1)) / np.sqrt(n)
    return PairedStat(mean, mean - half, mean + half, n, level)


def bootstrap_ci(diffs: Sequence[float] | np.ndarray, level: float = 0.95,
                 resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED) -> tuple[float, float] | None:
    """Return the percentile bootstrap interval of the mean of ``diffs`` (cases resampled with replacement).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences, in their own unit.
    level : float
        Confidence level, in (0, 1).
    resamples : int
        Bootstrap resamples (>= 100).
    seed : int
        Seed of the resampling generator.

    Returns
    -------
    (float, float) or None
        The ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles of the resampled means (linear interpolation), in
        the unit of ``diffs``; None with fewer than two differences.

    Raises
    ------
    StudyError
        ``level`` outside (0, 1), fewer than 100 resamples or a difference that is not finite.
    """
    _check_level(level)
    if resamples < 100:
        raise StudyError(f"a bootstrap needs at least 100 resamples, got {resamples}")
    d = _diffs(diffs)
    if len(d) < 2:
        return None
    idx = np.random.default_rng(seed).integers(0, len(d), size=(resamples, len(d)))
    means = d[idx].mean(axis=1)
    lo, hi = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(lo), float(hi)


@dataclass(frozen=True)
class HypothesisTest:
    """One hypothesis test of "no difference" on paired differences.

    Parameters
    ----------
    test : str
        Its name (``Wilcoxon signed-rank``, ``exact sign test``, ``paired t``).
    statistic : float or None
        The test statistic (W+ for Wilcoxon, the number of positive differences for the sign test, t for the
        t-test); None when the test cannot be made.
    p_value : float or None
        Two-sided p-value; None when the test cannot be made (``note`` says why).
    n_used : int
        Differences the test used (the sign and signed-rank tests drop zeros).
    note : str
        How it was computed, or why it was not.
    """

    test: str
    statistic: float | None
    p_value: float | None
    n_used: int
    note: str = ""

    def to_json(self) -> dict[str, object]:
        """Return the test as JSON-ready values (rounded to 1e-6).

        Returns
        -------
        dict
            ``test``, ``statistic``, ``p_value``, ``n_used``, ``note``.
        """
        return {"test": self.test, "statistic": _r(self.statistic, 6), "p_value": _r(self.p_value, 6),
                "n_used": self.n_used, "note": self.note}


def _r(v: float | None, nd: int = 4) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), nd)


def wilcoxon_test(diffs: Sequence[float] | np.ndarray) -> HypothesisTest:
    """Return the two-sided Wilcoxon signed-rank test of ``diffs`` (zero differences dropped).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences.

    Returns
    -------
    HypothesisTest
        ``statistic`` = W+, the sum of the ranks of the positive differences; p from scipy (exact null distribution
        of the non-zero differences without ties and n <= 50, else the normal approximation with the tie
        correction, no continuity correction). No p-value when every difference is zero.
    """
    from scipy.stats import wilcoxon

    d = _diffs(diffs)
    nz = d[d != 0.0]
    if len(nz) == 0:
        return HypothesisTest("Wilcoxon signed-rank", None, None, 0, "every difference is zero: nothing to rank")
    ranks = _ranks(np.abs(nz))
    w_plus = float(ranks[nz > 0].sum())
    exact = len(nz) <= 50 and len(np.unique(np.abs(nz))) == len(nz)
    res = wilcoxon(nz, alternative="two-sided", method="exact" if exact else "approx")
    return HypothesisTest("Wilcoxon signed-rank", w_plus, float(res.pvalue), len(nz),
                      f"{len(d) - len(nz)} zero differences dropped; "
                      + ("exact null distribution" if exact else "normal approximation with tie correction"))


def _ranks(a: np.ndarray) -> np.ndarray:
    from scipy.stats import rankdata

    return np.asarray(rankdata(a, method="average"), dtype=float)


def sign_test(diffs: Sequence[float] | np.ndarray) -> HypothesisTest:
    """Return the two-sided exact sign test of ``diffs``: a binomial test (p = 1/2) on the non-zero differences.

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences.

    Returns
    -------
    HypothesisTest
        ``statistic`` = the number of positive differences; no p-value when every difference is zero.
    """
    from scipy.stats import binomtest

    d = _diffs(diffs)
    nz = d[d != 0.0]
    if len(nz) == 0:
        return HypothesisTest("exact sign test", None, None, 0, "every difference is zero")
    k = int((nz > 0).sum())
    return HypothesisTest("exact sign test", float(k), float(binomtest(k, len(nz), 0.5).pvalue), len(nz),
                      f"{k} of {len(nz)} non-zero differences positive")


def paired_t_test(diffs: Sequence[float] | np.ndarray) -> HypothesisTest:
    """Return the two-sided paired t-test (one-sample t-test of ``diffs`` against 0).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences.

    Returns
    -------
    HypothesisTest
        ``statistic`` = t with n - 1 degrees of freedom; no p-value with fewer than two differences or none spread.
    """
    from scipy.stats import t as student_t

    d = _diffs(diffs)
    n = len(d)
    if n < 2 or float(d.std(ddof=1)) == 0.0:
        return HypothesisTest("paired t", None, None, n, "needs two differences that are not all equal")
    t = float(d.mean() / (d.std(ddof=1) / math.sqrt(n)))
    return HypothesisTest("paired t", t, float(2.0 * student_t.sf(abs(t), n - 1)), n, f"{n - 1} degrees of freedom")


def rank_biserial(diffs: Sequence[float] | np.ndarray) -> float | None:
    """Return the matched-pairs rank-biserial correlation ``(W+ - W-) / (W+ + W-)`` (Kerby 2014), zeros dropped.

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences.

    Returns
    -------
    float or None
        In [-1, 1] (1: every non-zero difference positive); None when every difference is zero.
    """
    d = _diffs(diffs)
    nz = d[d != 0.0]
    if len(nz) == 0:
        return None
    ranks = _ranks(np.abs(nz))
    return float((ranks[nz > 0].sum() - ranks[nz < 0].sum()) / ranks.sum())


def cohens_dz(diffs: Sequence[float] | np.ndarray) -> float | None:
    """Return Cohen's ``d_z``: the mean difference over the differences' standard deviation (ddof 1).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences.

    Returns
    -------
    float or None
        Dimensionless; None with fewer than two differences or none spread.
    """
    d = _diffs(diffs)
    if len(d) < 2 or float(d.std(ddof=1)) == 0.0:
        return None
    return float(d.mean() / d.std(ddof=1))


def t_test_power(n: int, effect: float, sd: float, alpha: float = 0.05) -> float:
    """Return the power of the two-sided paired t-test with ``n`` cases to detect a mean difference ``effect``.

    Parameters
    ----------
    n : int
        Cases (>= 2).
    effect : float
        The true mean difference (unit of the differences).
    sd : float
        The differences' standard deviation (same unit, > 0).
    alpha : float
        Significance level.

    Returns
    -------
    float
        ``P(|T| > t(1 - α/2, n - 1))`` with T non-central t, ``n - 1`` degrees of freedom, non-centrality
        ``effect √n / sd`` (its normal limit where scipy's series fails far in the tail).
    """
    from scipy.stats import nct, norm
    from scipy.stats import t as student_t

    crit = float(student_t.ppf(1.0 - alpha / 2.0, n - 1))
    nc = effect * math.sqrt(n) / sd
    power = float(nct.sf(crit, n - 1, nc) + nct.cdf(-crit, n - 1, nc))
    # far in the tail the non-central t's series can fail (nan): the normal limit is exact to many digits there
    return power if math.isfinite(power) else float(norm.sf(crit - nc) + norm.cdf(-crit - nc))


def cases_for_power(effect: float, sd: float, power: float = 0.8, alpha: float = 0.05,
                    max_n: int = 100_000) -> int | None:
    """Return the fewest cases with which the paired t-test reaches ``power`` for a mean difference ``effect``.

    Parameters
    ----------
    effect : float
        The mean difference to detect (> 0, unit of the differences).
    sd : float
        The differences' standard deviation (same unit).
    power : float
        Wanted power, in (alpha, 1).
    alpha : float
        Two-sided significance level.
    max_n : int
        Largest cohort searched.

    Returns
    -------
    int or None
        The cohort size (>= 2); None when ``sd`` is not positive (no spread observed) or more than ``max_n`` are
        needed.
    """
    if not (sd > 0 and math.isfinite(sd)) or effect <= 0:
        return None
    lo, hi = 2, 2
    while t_test_power(hi, effect, sd, alpha) < power:
        lo, hi = hi, 2 * hi
        if hi > max_n:
            return None
    while lo < hi:  # power rises with n: bisect for the first n that reaches it
        mid = (lo + hi) // 2
        if t_test_power(mid, effect, sd, alpha) >= power:
            hi = mid
        else:
            lo = mid + 1
    return hi


@dataclass(frozen=True)
class PairedSummary:
    """A paired difference over a cohort: mean, interval, the primary test and those beside it, effect sizes.

    Parameters
    ----------
    n : int
        Cases with a difference.
    mean, median, sd : float or None
        Of the differences (sd with ddof 1).
    ci95 : (float, float) or None
        The 95 % interval of the mean difference.
    ci_method : str
        How it was computed.
    primary : HypothesisTest
        The test ``summary.json`` reports as ``test`` and ``p_value``.
    others : tuple of HypothesisTest
        Further tests of the same differences.
    effect_sizes : tuple of (str, float or None)
        Named effect sizes.
    """

    n: int
    mean: float | None
    median: float | None
    sd: float | None
    ci95: tuple[float, float] | None
    ci_method: str
    primary: HypothesisTest
    others: tuple[HypothesisTest, ...]
    effect_sizes: tuple[tuple[str, float | None], ...]

    def to_json(self) -> dict[str, object]:
        """Return the summary for ``summary.json`` (``mean``, ``ci95``, ``test``, ``p_value`` and the rest).

        Returns
        -------
        dict
            Numbers rounded to 1e-4 (p-values 1e-6).
        """
        return {"n": self.n, "mean": _r(self.mean), "median": _r(self.median), "sd": _r(self.sd),
                "ci95": None if self.ci95 is None else [_r(self.ci95[0]), _r(self.ci95[1])],
                "ci_method": self.ci_method, "test": self.primary.test, "statistic": _r(self.primary.statistic, 6),
                "p_value": _r(self.primary.p_value, 6), "test_note": self.primary.note,
                "other_tests": [t.to_json() for t in self.others],
                "effect_sizes": {k: _r(v) for k, v in self.effect_sizes}}


def _moments(d: np.ndarray) -> tuple[float | None, float | None, float | None]:
    if not len(d):
        return None, None, None
    return float(d.mean()), float(np.median(d)), float(d.std(ddof=1)) if len(d) > 1 else None


def count_summary(diffs: Sequence[float] | np.ndarray) -> PairedSummary:
    """Summarise paired count differences (needles): bootstrap CI, Wilcoxon signed-rank, sign test, effect sizes.

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences (e.g. straight minus steered needles).

    Returns
    -------
    PairedSummary
        Primary test Wilcoxon signed-rank; the exact sign test beside it; rank-biserial and Cohen's d_z.
    """
    d = _diffs(diffs)
    mean, median, sd = _moments(d)
    return PairedSummary(len(d), mean, median, sd, bootstrap_ci(d),
                         f"percentile bootstrap of the mean, {BOOTSTRAP_RESAMPLES} resamples of the cases",
                         wilcoxon_test(d), (sign_test(d),),
                         (("rank_biserial", rank_biserial(d)), ("cohens_dz", cohens_dz(d))))


def continuous_summary(diffs: Sequence[float] | np.ndarray) -> PairedSummary:
    """Summarise paired continuous differences (doses): t-interval, paired t-test, Wilcoxon, effect sizes.

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences (e.g. steered minus straight D90, Gy).

    Returns
    -------
    PairedSummary
        Primary test paired t; Wilcoxon signed-rank beside it; Cohen's d_z and rank-biserial.
    """
    d = _diffs(diffs)
    mean, median, sd = _moments(d)
    ti = t_interval(d)
    return PairedSummary(len(d), mean, median, sd, None if ti.low is None or ti.high is None else (ti.low, ti.high),
                         "paired Student t-interval", paired_t_test(d), (wilcoxon_test(d),),
                         (("cohens_dz", cohens_dz(d)), ("rank_biserial", rank_biserial(d))))


def power_note(diffs: Sequence[float] | np.ndarray, effect: float, unit: str = "needle",
               power: float = 0.8) -> dict[str, object]:
    """Return how many cases detect a mean difference ``effect`` at ``power`` given the observed spread.

    Parameters
    ----------
    diffs : (n,) float
        The observed per-case differences (their SD is the assumed spread).
    effect : float
        The mean difference to detect (> 0).
    unit : str
        Its unit, for the sentence.
    power : float
        The wanted power.

    Returns
    -------
    dict
        ``effect``, ``power``, ``alpha``, ``observed_sd``, ``cases_paired_t``, ``cases_wilcoxon`` (the t-test's
        count over the ARE 3/π, rounded up) and ``text``.
    """
    d = _diffs(diffs)
    sd = float(d.std(ddof=1)) if len(d) > 1 else float("nan")
    n_t = cases_for_power(effect, sd, power) if math.isfinite(sd) else None
    n_w = None if n_t is None else math.ceil(n_t / (3.0 / math.pi))
    text = (f"with the observed SD of {sd:.2f} {unit}s per case, a two-sided paired t-test at alpha 0.05 detects a "
            f"mean saving of {effect:g} {unit} with {100 * power:.0f} % power in {n_t} cases (Wilcoxon signed-rank, "
            f"asymptotic relative efficiency 3/pi: about {n_w})") if n_t is not None else (
            "no spread observed (or fewer than two cases): a power estimate needs a standard deviation")
    return {"effect": effect, "power": power, "alpha": 0.05, "observed_sd": _r(sd), "cases_paired_t": n_t,
            "cases_wilcoxon": n_w, "text": text}

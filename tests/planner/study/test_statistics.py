"""The cohort statistics against scipy's own routines and closed forms, on planted paired data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from reachplan.planner.errors import StudyError
from reachplan.planner.study.statistics import (
    bootstrap_ci,
    cases_for_power,
    cohens_dz,
    continuous_summary,
    count_summary,
    paired_t_test,
    power_note,
    rank_biserial,
    sign_test,
    t_test_power,
    wilcoxon_test,
)

#: A planted cohort of 20 paired needle counts: steering saves 0, 1 or 2 needles, once costs one.
STRAIGHT = np.array([6, 5, 7, 6, 8, 5, 6, 7, 9, 6, 5, 6, 7, 8, 6, 5, 7, 6, 6, 8])
STEERED = np.array([6, 4, 7, 5, 6, 5, 6, 6, 8, 6, 6, 5, 7, 7, 6, 5, 6, 6, 5, 7])
#: Planted D90s (Gy): steered higher by about 1 Gy with noise.
D90_STRAIGHT = np.array([86.1, 88.4, 84.9, 90.2, 87.7, 85.5, 89.0, 86.8, 88.1, 87.3])
D90_STEERED = np.array([87.0, 89.9, 85.1, 91.0, 89.2, 85.9, 89.8, 88.5, 88.0, 88.6])


def test_needle_statistics_match_scipy_and_closed_forms() -> None:
    saved = STRAIGHT - STEERED
    nz = saved[saved != 0]
    w = wilcoxon_test(saved)
    ranks = stats.rankdata(np.abs(nz))
    assert w.statistic == pytest.approx(ranks[nz > 0].sum()) and w.n_used == len(nz) == 11
    # ties: the normal approximation with the tie correction, by hand (Lehmann 1975, ch. 3), then scipy's
    n = len(nz)
    _, counts = np.unique(np.abs(nz), return_counts=True)
    var = n * (n + 1) * (2 * n + 1) / 24 - (counts**3 - counts).sum() / 48
    z = (ranks[nz > 0].sum() - n * (n + 1) / 4) / math.sqrt(var)
    assert w.p_value == pytest.approx(2 * stats.norm.sf(abs(z)), rel=1e-9)
    assert w.p_value == pytest.approx(stats.wilcoxon(nz, method="approx").pvalue, rel=1e-12)
    # no ties, no zeros: the exact null distribution, counted by hand over all 2^n sign patterns
    untied = np.array([1.0, 2.5, -0.5, 4.0, 3.0, 6.0, 5.5])
    r = stats.rankdata(np.abs(untied))
    w_obs = r[untied > 0].sum()
    sums = np.array([sum(r[i] for i in range(7) if m >> i & 1) for m in range(2**7)])
    mean = r.sum() / 2
    assert wilcoxon_test(untied).p_value == pytest.approx(np.mean(np.abs(sums - mean) >= abs(w_obs - mean)), rel=1e-9)
    # exact sign test: 10 of 11 non-zero differences positive; two-sided binomial tail summed by hand
    k, n = int((nz > 0).sum()), len(nz)
    tail = sum(math.comb(n, i) for i in range(k, n + 1)) / 2**n
    s = sign_test(saved)
    assert (s.statistic, s.n_used) == (10.0, 11) and s.p_value == pytest.approx(min(1.0, 2 * tail), rel=1e-12)
    assert rank_biserial(saved) == pytest.approx((ranks[nz > 0].sum() - ranks[nz < 0].sum()) / ranks.sum())
    assert cohens_dz(saved) == pytest.approx(saved.mean() / saved.std(ddof=1))
    summary = count_summary(saved)
    assert summary.primary.test == "Wilcoxon signed-rank" and summary.mean == pytest.approx(saved.mean())
    assert summary.ci95 is not None and summary.ci95[0] < saved.mean() < summary.ci95[1]
    doc = summary.to_json()
    assert {"mean", "ci95", "test", "p_value"} <= set(doc) and doc["p_value"] == pytest.approx(w.p_value, abs=1e-6)


def test_bootstrap_interval_agrees_with_scipy() -> None:
    """Our percentile bootstrap against scipy's (different generators: equal within resampling noise)."""
    saved = (STRAIGHT - STEERED).astype(float)
    ours = bootstrap_ci(saved)
    ref = stats.bootstrap((saved,), np.mean, n_resamples=20_000, method="percentile",
                          rng=np.random.default_rng(5)).confidence_interval
    assert ours is not None
    assert ours[0] == pytest.approx(ref.low, abs=0.06) and ours[1] == pytest.approx(ref.high, abs=0.06)
    assert bootstrap_ci(saved) == ours  # seeded: reproducible
    assert bootstrap_ci([1.0]) is None and bootstrap_ci([2.0, 2.0, 2.0]) == (2.0, 2.0)
    with pytest.raises(StudyError):
        bootstrap_ci(saved, resamples=10)


def test_dose_statistics_match_scipy() -> None:
    gain = np.round(D90_STEERED - D90_STRAIGHT, 3)  # as cases.csv rounds them
    t = paired_t_test(gain)
    ref = stats.ttest_rel(D90_STEERED, D90_STRAIGHT)
    assert t.statistic == pytest.approx(ref.statistic, rel=1e-10) and t.p_value == pytest.approx(ref.pvalue, rel=1e-10)
    summary = continuous_summary(gain)
    ci = ref.confidence_interval(0.95)
    assert summary.ci95 == pytest.approx((ci.low, ci.high), rel=1e-10)
    (w,) = summary.others
    tied = len(np.unique(np.abs(gain))) < len(gain)  # 1.5 and 0.8 Gy occur twice
    assert tied and "tie correction" in w.note
    assert w.p_value == pytest.approx(stats.wilcoxon(gain, method="approx").pvalue, rel=1e-12)


def test_degenerate_cohorts_say_why() -> None:
    zeros = [0.0, 0.0, 0.0]
    assert wilcoxon_test(zeros).p_value is None and "zero" in wilcoxon_test(zeros).note
    assert sign_test(zeros).p_value is None and rank_biserial(zeros) is None
    assert paired_t_test([1.0, 1.0]).p_value is None and cohens_dz([1.0]) is None
    assert power_note(zeros, 0.5)["cases_paired_t"] is None
    with pytest.raises(StudyError):
        wilcoxon_test([1.0, float("inf")])


def test_power_matches_the_published_sample_size() -> None:
    """d_z = 0.5, alpha 0.05 two-sided, 80 % power: 34 pairs (Cohen 1988 / G*Power's paired t-test); the power at
    the returned size reaches 0.8 and one case fewer does not; power follows the normal approximation for large n."""
    assert cases_for_power(0.5, 1.0) == 34
    n = cases_for_power(0.5, 1.3)
    assert n is not None and t_test_power(n, 0.5, 1.3) >= 0.8 > t_test_power(n - 1, 0.5, 1.3)
    nc, crit = 0.2 * math.sqrt(200), stats.norm.ppf(0.975)
    assert t_test_power(200, 0.2, 1.0) == pytest.approx(stats.norm.sf(crit - nc) + stats.norm.cdf(-crit - nc), abs=5e-3)
    assert t_test_power(400, 0.5, 1.0) == pytest.approx(1.0)
    note = power_note(STRAIGHT - STEERED, 0.5)
    assert note["cases_wilcoxon"] == math.ceil(note["cases_paired_t"] * math.pi / 3)
    assert cases_for_power(0.5, 0.0) is None

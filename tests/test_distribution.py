"""The smoothed-indicator MLMC distribution function and its quantiles on known answers.

Statistical checks are seeded; each states where its slack comes from.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from moment_problems import PerturbedLimit, RareJumps, RoundedLimit
from scipy import integrate, stats
from scipy.optimize import isotonic_regression

from rough_uq.errors import EstimationError, EstimationWarning, InvalidParameterError
from rough_uq.multilevel.distribution import (
    cdf_from_samples,
    cdf_level_term,
    isotonic,
    level_bandwidth,
    mlmc_cdf,
    UNSEEN_CHANGE,
    quantiles,
    smoothed_step,
)

THETA = 0.5
BANDWIDTH = 0.5
PROBABILITIES = (0.05, 0.5, 0.95)


def rms_slack(n_repeats: int) -> float:
    # The mean of n squared errors has relative sd <= sqrt(2/n) for Gaussian errors; three of those.
    return math.sqrt(1.0 + 3.0 * math.sqrt(2.0 / n_repeats))


def grid(problem: PerturbedLimit, n_thresholds: int = 41) -> np.ndarray:
    # Half a unit beyond the 0.5% and 99.5% quantiles: the estimated CDF must cross 5% and 95%
    # inside the grid even in runs whose error at the ends is twice the tolerance.
    return np.linspace(problem.limit.ppf(0.005) - 0.5, problem.limit.ppf(0.995) + 0.5, n_thresholds)


# --------------------------------------------------------------------------
# The smooth step and the projection
# --------------------------------------------------------------------------


def test_the_smooth_step_is_a_symmetric_twice_differentiable_monotone_step():
    x = np.linspace(-1.5, 1.5, 3001)
    g = smoothed_step(x)
    assert np.all(np.diff(g) >= 0)
    assert np.all(g[x <= -1] == 0) and np.all(g[x >= 1] == 1) and smoothed_step(0.0) == 0.5
    np.testing.assert_allclose(smoothed_step(-x), 1 - g, atol=1e-15)
    # g' = 15/16 (1 - t^2)^2 vanishes to second order at 1: 1 - g(1 - h) = 5/4 h^3 + O(h^4).
    h = 1e-3
    assert (1 - smoothed_step(1 - h)) / h**3 == pytest.approx(1.25, rel=1e-2)


def test_the_smoothing_bias_is_the_documented_second_order_term():
    # E[g((s - Z)/delta)] - F(s) = delta^2 f'(s) / 14 + O(delta^4) for Z ~ N(0, 1).
    s = 0.7
    residuals = []
    deltas = np.array([0.4, 0.2, 0.1])
    for delta in deltas:
        smoothed, _ = integrate.quad(
            lambda z, d=delta: smoothed_step((s - z) / d) * stats.norm.pdf(z), -12, 12, points=[s - delta, s + delta],
            epsabs=1e-14, epsrel=1e-14,
        )
        slope = -s * stats.norm.pdf(s)
        residuals.append(abs(smoothed - stats.norm.cdf(s) - delta**2 * slope / 14))
    rate = np.polyfit(np.log2(deltas), np.log2(residuals), 1)[0]
    assert rate == pytest.approx(4.0, abs=0.3)


def test_isotonic_is_the_least_squares_projection_and_a_sup_norm_contraction():
    rng = np.random.default_rng(4)
    for _ in range(50):
        m = int(rng.integers(1, 60))
        truth = np.sort(rng.uniform(size=m))
        noisy = truth + rng.normal(scale=rng.uniform(0.01, 0.3), size=m)
        projected = isotonic(noisy)
        np.testing.assert_allclose(projected, isotonic_regression(noisy).x, atol=1e-12)
        assert np.all(np.diff(projected) >= 0)
        assert np.max(np.abs(projected - truth)) <= np.max(np.abs(noisy - truth)) + 1e-12


def test_level_terms_telescope_to_the_smoothed_cdf_of_the_finest_level():
    rng = np.random.default_rng(8)
    z, w = rng.normal(size=500), rng.normal(size=500)
    values = [z + 2.0**-level * w for level in range(4)]
    s = np.linspace(-2, 2, 9)
    coarse = [None] + values[:-1]
    total = sum(cdf_level_term(values[k], coarse[k], k, thresholds=s, bandwidth=0.3).mean for k in range(4))
    delta = level_bandwidth(3, bandwidth=0.3)
    np.testing.assert_allclose(total, np.mean(smoothed_step((s - values[3][:, None]) / delta), axis=0), atol=1e-13)
    term = cdf_level_term(values[2], values[1], 2, thresholds=s, bandwidth=0.3)
    direct = smoothed_step((s - values[2][:, None]) / 0.075) - smoothed_step((s - values[1][:, None]) / 0.15)
    np.testing.assert_allclose(term.variance, np.var(direct, axis=0, ddof=1) / 500, rtol=1e-10)
    assert term.groups.tolist() == [0] * 9


# --------------------------------------------------------------------------
# Known answers
# --------------------------------------------------------------------------


def cdf_runs(kind: str, tol: float, n_repeats: int, n_thresholds: int = 41):
    s = grid(PerturbedLimit(kind=kind), n_thresholds)
    runs = []
    for seed in range(n_repeats):
        problem = PerturbedLimit(kind=kind, seed=seed)
        runs.append((problem, mlmc_cdf(problem, thresholds=s, tol=tol, bandwidth=BANDWIDTH)))
    return s, runs


def sup_pointwise_rmse(s: np.ndarray, runs) -> float:
    errors = np.array([result.cdf - problem.limit.cdf(s) for problem, result in runs])
    return float(np.max(np.sqrt(np.mean(errors**2, axis=0))))


@pytest.mark.parametrize(("kind", "tol", "n_repeats"), [("gaussian", 0.03, 60), ("gamma", 0.03, 40)])
def test_mlmc_cdf_and_quantiles_are_within_tolerance(kind, tol, n_repeats):
    s, runs = cdf_runs(kind, tol, n_repeats)
    assert sup_pointwise_rmse(s, runs) <= tol * rms_slack(n_repeats)
    limit = runs[0][0].limit
    q_errors, half_widths = [], []
    for problem, result in runs:
        assert result.stop_reason == "tol_met" and result.tol_met and result.rmse <= tol
        assert result.bias <= math.sqrt(THETA) * tol
        assert np.all(np.diff(result.cdf) >= 0) and result.cdf[0] >= 0 and result.cdf[-1] <= 1
        truth = limit.cdf(s)
        # The projection never increases the sup-norm error (module docstring).
        assert np.max(np.abs(result.cdf - truth)) <= np.max(np.abs(result.cdf_raw - truth)) + 1e-12
        found = quantiles(result, probabilities=PROBABILITIES)
        assert np.all(found.lower <= found.values) and np.all(found.values <= found.upper)
        q_errors.append(found.values - limit.ppf(PROBABILITIES))
        half_widths.append(found.half_width)
    q_rmse = np.sqrt(np.mean(np.square(q_errors), axis=0))
    # The quantile tolerance implied by the CDF's: tol / f(q_p) (delta method), and the
    # reported error bars are at least as wide as the errors on average.
    density = limit.pdf(limit.ppf(PROBABILITIES))
    assert np.all(q_rmse <= tol / density * rms_slack(n_repeats))
    assert np.all(q_rmse <= np.mean(half_widths, axis=0) * rms_slack(n_repeats))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["gaussian", "gamma"])
def test_mlmc_cdf_error_and_cost_follow_the_tolerance(kind):
    # Sup-norm RMSE ~ tol; with beta = 1 = gamma the cost grows like tol^-2 log(tol)^2 (SPEC section 5).
    tols = np.array([0.04, 0.02, 0.01])
    n_repeats = 30
    rmse, cost = [], []
    for tol in tols:
        s, runs = cdf_runs(kind, float(tol), n_repeats)
        rmse.append(sup_pointwise_rmse(s, runs))
        cost.append(np.mean([result.target.cost for _, result in runs]))
        assert rmse[-1] <= tol * rms_slack(n_repeats)
    error_rate = np.polyfit(np.log2(tols), np.log2(rmse), 1)[0]
    cost_rate = np.polyfit(np.log2(tols), np.log2(cost), 1)[0]
    # log2 of an RMSE over 30 runs has sd ~ 0.19; the slope over two octaves ~ 0.13: four of those.
    assert abs(error_rate - 1.0) < 0.55
    # -2 for the tol^-2 part, the log(tol)^2 factor adds about -0.6 over these octaves; discrete
    # levels add up to a factor 2 at either end (0.5 on the slope).
    assert -3.1 < cost_rate < -1.5


def test_quantile_error_bars_follow_the_delta_method():
    # One level, many samples: no bias, and the band cdf +- rmse crosses p at q_p -+ rmse / f(q_p).
    problem = PerturbedLimit(seed=3, scale=0.0)
    fine, _, _ = problem(0, np.arange(200_000))
    s = np.linspace(-3, 3, 241)
    result = cdf_from_samples(fine=[fine], coarse=[np.zeros_like(fine)], thresholds=s, bandwidth=0.01)
    assert result.bias == 0 and result.rmse == pytest.approx(np.max(result.stat_error))
    found = quantiles(result, probabilities=PROBABILITIES)
    density = stats.norm.pdf(found.values)
    np.testing.assert_allclose(found.half_width * density / result.rmse, 1.0, rtol=0.05)
    assert np.all(np.abs(found.values - stats.norm.ppf(PROBABILITIES)) < 4 * found.half_width)


# --------------------------------------------------------------------------
# Thresholds that miss the samples
# --------------------------------------------------------------------------


def level_ranges(problem: PerturbedLimit, n_samples: np.ndarray) -> list[tuple[float, float]]:
    """Smallest and largest value (``Q_l``, and ``Q_{l-1}`` on ``l >= 1``) of the samples a run used, per level."""
    ranges = []
    for level, n in enumerate(n_samples):
        fine, coarse, _ = problem(level, np.arange(n))
        values = fine if level == 0 else np.concatenate([fine, coarse])
        ranges.append((float(values.min()), float(values.max())))
    return ranges


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("side", ["below", "above"])
def test_thresholds_beyond_every_sample_do_not_claim_the_tolerance(seed, side):
    # Every threshold 8 to 12 standard deviations from the mean: the indicators are 0 (or 1) on every sample,
    # the sample variances 0, and the run reported a sup-norm RMSE 0 and "tol_met".
    problem = PerturbedLimit(seed=seed)
    s = np.linspace(-12.0, -8.0, 9) if side == "below" else np.linspace(8.0, 12.0, 9)
    with pytest.warns(EstimationWarning) as caught:
        result = mlmc_cdf(problem, thresholds=s, tol=0.05, bandwidth=BANDWIDTH)
    assert np.all(result.cdf == (1.0 if side == "above" else 0.0)) and result.rmse == 0.0
    assert not result.tol_met and not result.target.tol_met
    assert result.stop_reason == result.target.stop_reason == "thresholds_miss_samples"
    assert result.missed_levels.tolist() == result.levels.tolist()
    (message,) = [str(w.message) for w in caught]
    ranges = ", ".join(f"level {level} (values {low:.4g} .. {high:.4g})"
                       for level, (low, high) in enumerate(level_ranges(problem, result.n_samples)))
    assert message.startswith(f"cdf: the thresholds [{s[0]:g}, {s[-1]:g}] miss the samples of {ranges}: ")
    assert "the tolerance is not met" in message


@pytest.mark.parametrize("seed", range(4))
def test_thresholds_over_part_of_the_distribution_still_meet_the_tolerance(seed):
    # The lower half only: levels have values on both sides of the thresholds near the median.
    problem = PerturbedLimit(seed=seed)
    s = np.linspace(problem.limit.ppf(0.005) - 0.5, 0.0, 21)
    result = mlmc_cdf(problem, thresholds=s, tol=0.05, bandwidth=BANDWIDTH)  # warnings are errors
    assert result.missed_levels.size == 0
    assert result.stop_reason == "tol_met" and result.tol_met and 0 < result.rmse <= 0.05


@pytest.mark.parametrize(
    ("level_1", "is_missed_1"),
    [
        (([5.0, 6.0], [5.5, 7.0]), True),  # every value above the grid, beyond the bandwidths 0.5 and 1
        (([5.0, 6.0], [2.9, 7.0]), False),  # a coarse value within delta_0 = 1 of the last threshold
        (([2.4, 6.0], [5.5, 7.0]), False),  # a fine value within delta_1 = 0.5 of it
        (([-5.0, 6.0], [5.5, 7.0]), False),  # fine values on both sides of every threshold
        (([5.0, 6.0], [-5.0, -6.0]), True),  # every fine value above, every coarse one below: the term is -1 on all
    ],
)
@pytest.mark.parametrize(("level_0", "is_missed_0"), [([4.0, 9.0, 6.5], True), ([2.5, 9.0, 6.5], False)])
def test_a_level_is_missed_where_its_values_lie_beyond_the_bandwidth_on_one_side_of_every_threshold(
    level_0, is_missed_0, level_1, is_missed_1
):
    fine = [np.array(level_0), np.array(level_1[0])]
    coarse = [np.zeros(3), np.array(level_1[1])]
    missed = [level for level, is_missed in enumerate([is_missed_0, is_missed_1]) if is_missed]
    options = {"thresholds": [0.0, 1.0, 2.0], "bandwidth": 1.0, "tol": 0.5}
    if not missed:
        result = cdf_from_samples(fine=fine, coarse=coarse, **options)  # warnings are errors
        assert result.missed_levels.size == 0 and result.stop_reason == "given"
        return
    values = [fine[0], np.concatenate([fine[1], coarse[1]])]
    named = ", ".join(f"level {level} (values {values[level].min():g} .. {values[level].max():g})" for level in missed)
    expected = f"cdf: the thresholds [0, 2] miss the samples of {named}: "
    with pytest.warns(EstimationWarning, match="^" + re.escape(expected)):
        result = cdf_from_samples(fine=fine, coarse=coarse, **options)
    assert result.missed_levels.tolist() == missed
    assert not result.tol_met and result.stop_reason == "thresholds_miss_samples"


@pytest.mark.parametrize("bandwidth", [1e3, 1e4, 1e12])
def test_a_bandwidth_far_wider_than_the_values_does_not_claim_the_tolerance(bandwidth):
    # Every value in the linear part of the smoothed step: the smoothed CDF was about 1/2 at every threshold and
    # changed little between levels, so the decay of the level terms put the bias near 0 and the run reported
    # its tolerance met for a CDF some 0.45 off the truth. At 1e12 every value was within TIE_TOLERANCE
    # bandwidths of every threshold, on it: F = 1 everywhere, "thresholds_miss_samples" (an API audit).
    problem = PerturbedLimit(seed=1)
    s = grid(problem, 21)
    with pytest.warns(EstimationWarning) as caught:
        result = mlmc_cdf(problem, thresholds=s, tol=0.05, bandwidth=bandwidth)
    assert np.max(np.abs(result.cdf - problem.limit.cdf(s))) > 0.3  # what was reported as within 0.05
    assert result.stop_reason == result.target.stop_reason == "bandwidth_too_wide"
    assert not result.tol_met and not result.is_bias_estimated and result.bias == 0.0
    # Its quantiles' error bars were the statistical error's band alone (an audit: [0.8969, 2.072] % about a
    # q(0.05) of 1.804 % where the truth was 18.6 %): open now.
    bars = quantiles(result, probabilities=[0.5])
    assert not result.has_error_band and np.isneginf(bars.lower[0]) and np.isposinf(bars.upper[0])
    finest = level_bandwidth(int(result.levels[-1]), bandwidth=bandwidth)
    (message,) = [str(w.message) for w in caught]
    assert message.startswith(f"cdf: the smoothing bandwidth on the finest level {result.levels[-1]}, {finest:.4g}, "
                              "exceeds 2 standard deviations of the values (")
    assert "give a bandwidth below twice the spread of the values" in message
    # Some 30 times the standard deviation is fine: the run refines until its bias estimate is within its share.
    wide = mlmc_cdf(problem, thresholds=s, tol=0.05, bandwidth=30.0)  # warnings are errors
    assert wide.tol_met and wide.bandwidths[-1] < 1.0 and np.max(np.abs(wide.cdf - problem.limit.cdf(s))) < 0.05
    bars = quantiles(wide, probabilities=[0.5])
    assert wide.has_error_band and bars.lower[0] < bars.values[0] < bars.upper[0] < bars.lower[0] + 10


@pytest.mark.parametrize(("bandwidth", "is_too_wide"), [(7.3, False), (7.31, True)])
def test_the_finest_bandwidth_is_compared_with_twice_the_telescoped_standard_deviation(bandwidth, is_too_wide):
    # Var(Q_1) = Var(Q_0) + (Var(Q_1) - Var(Q_0)) from each level's own pairs: 5/3 + (5/3 - 0) = 10/3, sd 1.826 (the
    # finest level's own sample variance, 5/3, is smaller),
    # limit 3.651; delta_1 = bandwidth / 2. (Raw moments telescoped, E[Q_1^2] - E[Q_1]^2, gave 2.5.)
    fine, coarse = [np.arange(4.0), np.arange(4.0)], [np.zeros(4), np.full(4, 1.5)]
    options = {"thresholds": [0.0, 1.0, 2.0, 3.0], "bandwidth": bandwidth, "tol": 0.9}
    if not is_too_wide:
        result = cdf_from_samples(fine=fine, coarse=coarse, **options)  # warnings are errors
        assert result.stop_reason == "given" and result.is_bias_estimated
        return
    expected = (r"^cdf: the smoothing bandwidth on the finest level 1, 3\.655, exceeds 2 standard deviations of the "
                r"values \(standard deviation 1\.826\): ")
    with pytest.warns(EstimationWarning, match=expected):
        result = cdf_from_samples(fine=fine, coarse=coarse, **options)
    assert result.stop_reason == "bandwidth_too_wide" and not result.tol_met


def test_the_spread_is_telescoped_on_each_levels_own_means_or_the_finest_levels_where_larger():
    # The quickstart's --tol-cdf run of an audit (contact areas in %, 10 samples per level, rounded here): raw
    # moments telescoped gave a standard deviation of 0.16 where the finest values' is 1.08, and the run ended
    # "bandwidth_too_wide" at a finest bandwidth of 0.5. The levels' means differ between their sample sets
    # (20.9 / 20.3 / 20.0), and raw moments carried that into the spread.
    fine = [np.array([21.8795, 21.8533, 20.0047, 21.2382, 21.6611, 20.8299, 19.9241, 21.2989, 20.4092, 20.1393]),
            np.array([20.8299, 19.7052, 21.0792, 20.2713, 19.6138, 21.5885, 19.2055, 20.7753, 21.5775, 19.3095]),
            np.array([21.8146, 20.0053, 20.5728, 19.0474, 20.2194, 19.9893, 19.6298, 19.6263, 18.1127, 21.4243])]
    coarse = [np.zeros(10),
              np.array([19.6026, 19.6987, 20.9882, 20.663, 18.9336, 21.3666, 18.8183, 21.1766, 22.0078, 20.097]),
              np.array([21.5958, 19.7986, 20.6263, 19.054, 19.8824, 20.064, 19.6365, 19.5973, 17.9989, 21.327])]
    raw = sum(np.mean(f * f - c * c) for f, c in zip(fine, coarse))
    raw -= sum(np.mean(f - c) for f, c in zip(fine, coarse)) ** 2
    assert raw < (0.5 / 2) ** 2  # the old spread failed the check
    result = cdf_from_samples(fine=fine, coarse=coarse, thresholds=np.linspace(10.0, 30.0, 21), bandwidth=2.0,
                              tol=0.9)  # warnings are errors: delta_2 = 0.5
    assert result.stop_reason == "given" and result.is_bias_estimated
    # Telescoped on each level's own pairs, sqrt(0.588 - 0.339 + 0.054) = 0.55, half the finest values' 1.08 (noise
    # of 10 samples a level): a finest bandwidth of 1.125 ended "bandwidth_too_wide" too. The larger spread counts.
    centred = np.var(fine[0], ddof=1) + sum(np.var(f, ddof=1) - np.var(c, ddof=1) for f, c in zip(fine[1:], coarse[1:]))
    finest = np.std(fine[2], ddof=1)
    assert 2 * math.sqrt(centred) < 1.125 < 2 * finest < 0.25 * 10.0  # delta_2 of bandwidths 4.5 and 10
    moderate = cdf_from_samples(fine=fine, coarse=coarse, thresholds=np.linspace(10.0, 30.0, 21), bandwidth=4.5,
                                tol=0.9)  # delta_2 = 1.125
    assert moderate.stop_reason != "bandwidth_too_wide" and moderate.is_bias_estimated
    with pytest.warns(EstimationWarning, match=rf"values \(standard deviation {finest:.4g}\)"):
        wide = cdf_from_samples(fine=fine, coarse=coarse, thresholds=np.linspace(10.0, 30.0, 21), bandwidth=10.0,
                                tol=0.9)  # delta_2 = 2.5 > 2 x 1.08
    assert wide.stop_reason == "bandwidth_too_wide"


def test_the_spread_is_the_finest_levels_not_the_coarsest_ones():
    # Spreads 6.8 / 1.67 on levels 0 / 1 (as a stored contact area had): pooled by sample count, the spread was
    # about level 0's, and a finest bandwidth of 4 finest standard deviations passed the check.
    rng = np.random.default_rng(11)
    coarse_values = 6.8 * rng.standard_normal(400)
    fine = [6.8 * rng.standard_normal(4000), 1.67 * rng.standard_normal(400)]
    thresholds = np.linspace(-5.0, 5.0, 21)
    with pytest.warns(EstimationWarning, match="exceeds 2 standard deviations of the values"):
        result = cdf_from_samples(fine=fine, coarse=[np.zeros(4000), coarse_values], thresholds=thresholds,
                                  bandwidth=2 * 4 * 1.67, tol=0.9)
    assert result.stop_reason == "bandwidth_too_wide"


def test_a_wide_bandwidth_is_left_alone_where_it_is_the_target_or_exact():
    # bandwidth_rate 0 estimates the smoothed CDF itself (its smoothing bias is documented as not reported); a
    # discrete Q whose values lie a bandwidth or more from every threshold has exact smoothed indicators.
    fine, coarse = [np.arange(4.0), np.arange(4.0)], [np.zeros(4), np.full(4, 1.5)]
    fixed = cdf_from_samples(fine=fine, coarse=coarse, thresholds=[0.0, 1.0, 2.0, 3.0], bandwidth=9.0,
                             bandwidth_rate=0.0, tol=0.9)  # warnings are errors
    assert fixed.stop_reason == "given"
    atoms = [np.array([1.0, 2.0, 1.0, 2.0, 1.0]), np.array([1.0, 2.0, 2.0, 1.0, 2.0])]
    between = cdf_from_samples(fine=atoms, coarse=[np.zeros(5), atoms[1]], thresholds=[0.5, 1.5, 2.5, 3.5],
                               bandwidth=1.0, tol=0.9)  # delta_1 = 0.5: every value 0.5 from its thresholds
    assert between.stop_reason == "given" and between.is_bias_estimated
    constant = [np.full(4, 2.2), np.full(4, 2.2)]
    with pytest.warns(EstimationWarning, match=r"^cdf: the values of the finest level 1 do not vary, and lie within "
                                                r"its smoothing bandwidth, 0\.5, of a threshold: "):
        near_step = cdf_from_samples(fine=constant, coarse=[np.zeros(4), constant[1]], thresholds=[1.0, 2.0, 3.0],
                                     bandwidth=1.0, tol=0.9)
    assert near_step.stop_reason == "bandwidth_too_wide"
    # On the threshold the constant's step is exact (a tie counts whole), but its samples bound nothing else.
    on_step = [np.full(4, 2.0), np.full(4, 2.0)]
    with pytest.warns(EstimationWarning, match=r"^cdf: the thresholds \[1, 3\] miss the samples of level 0 "):
        exact = cdf_from_samples(fine=on_step, coarse=[np.zeros(4), on_step[1]], thresholds=[1.0, 2.0, 3.0],
                                 bandwidth=1.0, tol=0.9)
    assert exact.cdf.tolist() == [0.0, 1.0, 1.0] and exact.stop_reason == "thresholds_miss_samples"


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------


@pytest.mark.parametrize("thresholds", [[0.0, 1.0, 1.0], [1.0, 0.0], [0.5], [[0.0, 1.0]], [0.0, np.nan]])
def test_thresholds_must_increase(thresholds):
    with pytest.raises(InvalidParameterError, match="thresholds"):
        mlmc_cdf(PerturbedLimit(), thresholds=thresholds, tol=0.1, bandwidth=0.5)


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"tol": 0.0}, "tol"),
        ({"tol": -0.1}, "tol"),
        ({"tol": [0.1, 0.1]}, "tol"),
        ({"bandwidth": 0.0}, "bandwidth"),
        ({"bandwidth_rate": -1.0}, "bandwidth_rate"),
        ({"qoi": 1}, "qoi"),
    ],
)
def test_bad_options_are_refused(options, field):
    arguments = {"thresholds": [0.0, 1.0], "tol": 0.1, "bandwidth": 0.5, **options}
    with pytest.raises(InvalidParameterError, match=field):
        mlmc_cdf(PerturbedLimit(), **arguments)


def test_a_budget_stop_on_level_0_does_not_claim_the_tolerance():
    # The 32 initial samples of level 0 are drawn before any cost is known; their sup-norm error is below 0.3,
    # and with "bias 0" the run claimed the tolerance met.
    problem = PerturbedLimit()
    result = mlmc_cdf(problem, thresholds=grid(problem, 9), tol=0.3, bandwidth=BANDWIDTH, max_cost=1e-9)
    assert result.stop_reason == "max_cost" and result.levels.tolist() == [0] and result.rmse < 0.3
    assert not result.is_bias_estimated and result.bias == 0.0 and not result.tol_met


def test_too_few_samples_and_unbracketed_quantiles_are_refused():
    with pytest.raises(InvalidParameterError, match="at least 2 samples"):
        cdf_level_term(np.zeros(1), None, 0, thresholds=[0.0, 1.0], bandwidth=0.5)
    with pytest.raises(InvalidParameterError, match="finite"):
        cdf_level_term(np.array([0.0, np.nan]), None, 0, thresholds=[0.0, 1.0], bandwidth=0.5)
    fine = PerturbedLimit(scale=0.0)(0, np.arange(1000))[0]
    result = cdf_from_samples(fine=[fine], coarse=[fine], thresholds=[-0.5, 0.0, 0.5], bandwidth=0.1)
    with pytest.raises(EstimationError, match="do not bracket"):
        quantiles(result, probabilities=[0.05])
    with pytest.raises(InvalidParameterError, match="probabilities"):
        quantiles(result, probabilities=[0.0, 0.5])
    middle = quantiles(result, probabilities=[0.5])
    # The band cdf +- rmse stays inside the grid here; a band leaving the grid is reported as infinite.
    assert np.isfinite(middle.lower[0]) and np.isfinite(middle.upper[0])


@pytest.mark.parametrize(
    "probabilities",
    ["0.5", "abc", ["0.5", 0.9], np.array(["0.5"]), [0.5, True], 0.5j, [[0.1], [0.2, 0.3]], None, [], [0.5, 0.5]],
)
def test_quantiles_refuse_probabilities_that_are_not_numbers_by_name(probabilities):
    # "abc" and the ragged list gave bare ValueErrors, 0.5j a TypeError; "0.5" and ["0.5", 0.9] were converted;
    # [] gave no quantiles and [0.5, 0.5] one twice, where --probabilities refuses both.
    fine = np.linspace(-2.0, 2.0, 200)
    result = cdf_from_samples(fine=[fine], coarse=[fine], thresholds=np.linspace(-3.0, 3.0, 25), bandwidth=0.1)
    allowed = "allowed: a number or a non-empty 1-d sequence of distinct numbers strictly between 0 and 1$"
    with pytest.raises(InvalidParameterError, match=r"^probabilities: got .*; " + allowed):
        quantiles(result, probabilities=probabilities)
    np.testing.assert_array_equal(quantiles(result, probabilities=0.5).values, [0.0])


def test_a_fixed_bandwidth_converges_to_the_smoothed_cdf():
    # bandwidth_rate = 0: the telescoped sum is E[g((s - Q_L)/delta)], the smoothed CDF of Q_L,
    # here Q_3 ~ N(0, 1 + 4^-3), computed by quadrature.
    problem = PerturbedLimit(seed=9)
    s = np.linspace(-2.0, 2.0, 9)
    drawn = [problem(level, np.arange(40_000)) for level in range(4)]
    result = cdf_from_samples(
        fine=[d[0] for d in drawn], coarse=[d[1] for d in drawn], thresholds=s, bandwidth=1.0, bandwidth_rate=0.0
    )
    assert np.all(result.bandwidths == 1.0)
    spread = math.sqrt(1.0 + 4.0**-3)
    smoothed = [
        integrate.quad(lambda q, t=t: smoothed_step((t - q) / 1.0) * stats.norm.pdf(q, scale=spread), -10, 10)[0]
        for t in s
    ]
    assert np.all(np.abs(result.cdf_raw - smoothed) < 4.0 * result.stat_error)
    # ... which differs from F itself by about delta^2 f'(s) / 14 = 0.017, beyond the statistical error.
    assert np.max(np.abs(smoothed - stats.norm.cdf(s, scale=spread))) > 4 * np.max(result.stat_error)


def test_a_cdf_run_reports_the_checks_of_its_qoi_column_by_name():
    # SPEC section 5 asks every multilevel run for the consistency and kurtosis checks; the variance and CDF
    # runs reported none. Column "b" has rare jumps between levels (kurtosis 213 on level 1, none drawn on
    # level 2); column "a" (constant) is not the CDF's and is not checked.
    jumps = RareJumps(p0=0.01, seed=0)

    def two_columns(level, indices):
        fine, coarse, cost = jumps(level, indices)
        return np.column_stack([np.zeros_like(fine), fine]), np.column_stack([np.zeros_like(coarse), coarse]), cost

    with pytest.warns(EstimationWarning) as caught:
        mlmc_cdf(two_columns, thresholds=np.linspace(-2, 2, 9), tol=0.02, bandwidth=0.5, qoi=1, qoi_names=("a", "b"))
    messages = [str(warning.message) for warning in caught]
    assert any(re.match(r"^cdf: level 1: kurtosis \d+ of Q_l - Q_l-1 for b exceeds 100", m) for m in messages)
    assert any(re.match(r"^cdf: level 2: Q_l - Q_l-1 is the same in all \d+ samples for b", m) for m in messages)
    assert not any(" for a " in m for m in messages)


def test_a_discrete_qoi_counts_its_atoms_on_the_thresholds_whole():
    # Integer thresholds under an integer Q (an atom of 0.2 at 0): g(0) = 1/2 made every level's smoothed CDF
    # F(s-) + P(Q = s) / 2, a bias no level term shows. 10 runs had an RMS error of 0.1 at s = 0 (5 tol) and
    # all claimed tol 0.02.
    thresholds = np.arange(-5.0, 6.0)
    exact = stats.norm.cdf((thresholds + 0.5) / 2.0)  # P(round(2 X) <= s) for integer s
    errors = []
    for seed in range(10):
        result = mlmc_cdf(RoundedLimit(rate=1.0, seed=seed), thresholds=thresholds, tol=0.02, bandwidth=0.3)
        assert result.tol_met
        errors.append(result.cdf - exact)
    assert np.max(np.sqrt(np.mean(np.square(errors), axis=0))) < 0.02


def test_a_level_whose_pairs_change_no_indicator_is_not_taken_as_exact():
    # A tail grid: the 32 pairs of levels 1 and 2 (seed 25) lie on both sides of the grid, none within a
    # bandwidth of a threshold and none crossing one, so every difference and its variance was 0: the levels
    # were never sampled again and the run claimed tol 0.01 at an error of 0.058 (11 RMSE).
    thresholds = np.linspace(2.0, 3.0, 11)
    result = mlmc_cdf(PerturbedLimit(seed=25), thresholds=thresholds, tol=0.01, bandwidth=0.2)
    assert result.target.n_samples[1] > 32 and result.target.n_samples[2] > 32
    assert np.max(np.abs(result.cdf - stats.norm.cdf(thresholds))) < 3 * result.rmse


def test_unchanged_pairs_bound_the_variance_of_their_level_by_the_rule_of_three():
    # Values on both sides of the thresholds, every one a bandwidth or more from both, on both levels.
    values = np.r_[np.linspace(-1.0, 1.0, 38), 10.0, 11.0][:, None]
    far = np.array([5.0, 6.0])
    term = cdf_level_term(values, values, 1, thresholds=far, bandwidth=0.5)
    assert np.all(term.mean == 0) and np.allclose(term.variance, UNSEEN_CHANGE / 40**2)
    below = values[:38]  # all below both: the thresholds miss the level (missed_levels), no bound
    assert np.all(cdf_level_term(below, below, 1, thresholds=far, bandwidth=0.5).variance == 0)
    moved = values.copy()
    moved[0] = 5.5  # one pair crosses s = 5: measured, not bounded
    term = cdf_level_term(moved, values, 1, thresholds=far, bandwidth=0.5)
    assert term.variance[0] == pytest.approx(np.var(np.r_[-1.0, np.zeros(39)], ddof=1) / 40)
    assert term.variance[1] == 0  # a level that changed an indicator is measured, at every threshold


def test_a_value_within_rounding_of_a_threshold_counts_as_on_it():
    # 3 clusters in a box of 0.1 are 299.99999999999994 per unit area, not 300: halved as g(0) = 1/2 they kept
    # the bias of an atom on the threshold (an RMS error of 0.09 against tol 0.02 on such a grid).
    density = np.full(8, 3 / 0.1**2)
    term = cdf_level_term(density, None, 0, thresholds=np.array([300.0, 400.0]), bandwidth=50.0)
    assert term.mean.tolist() == [1.0, 1.0]
    assert cdf_level_term(density + 1e-6, None, 0, thresholds=np.array([300.0, 400.0]), bandwidth=50.0).mean[0] < 1


def test_a_value_on_a_threshold_to_rounding_counts_whole_whatever_the_bandwidth_and_the_span():
    # 3 clusters in a box of 0.1: 3 / 0.1**2 = 299.99999999999994 on the threshold 300. The tie width was
    # TIE_TOLERANCE bandwidths (bandwidth 1e12: every value on every threshold), then of the thresholds' span
    # (1e-5 here: below the rounding of 300, the atom halved again).
    from rough_uq.multilevel.distribution import _indicator

    value = np.array([[3 / 0.1**2]])
    for thresholds, bandwidth in (([300.0, 300.00001], 1.0), ([300.0, 1000.0], 1e12), ([300.0, 400.0], 0.5)):
        assert _indicator(np.array(thresholds), value, bandwidth)[0, 0] == 1.0
    assert _indicator(np.array([10.0, 40.0]), np.array([[20.0]]), 1e12)[0, 0] == pytest.approx(0.5, abs=1e-9)

"""h-statistics, the variance of h2 level terms, and the MLMC variance estimator on known answers.

Exactness is checked by enumerating every sample of a small discrete
distribution; statistical checks are seeded and their slack is a stated
number of standard errors.
"""

from __future__ import annotations

import functools
import itertools
import math
import warnings

import numpy as np
import pytest
from moment_problems import PerturbedLimit, RareJumps, RoundedLimit

from rough_uq.errors import EstimationError, InvalidParameterError
from rough_uq.multilevel.statistics import EstimationWarning
from rough_uq.multilevel.allocation import optimal_samples
from rough_uq.multilevel.moments import (
    central_moment_level_term,
    h2,
    h2_difference_variance,
    h3,
    h4,
    mlmc_central_moment,
    mlmc_variance,
    variance_from_samples,
    variance_level_term,
)
from rough_uq.multilevel.targets import LevelTerm, adaptive_mlmc, sample_plan, telescope

THETA = 0.5


def enumerate_samples(support: np.ndarray, probabilities: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Every sample of size ``n`` (as columns, shape (n, n_support^n, ...)) and its probability."""
    rows = np.array(list(itertools.product(range(len(support)), repeat=n)))
    return np.moveaxis(support[rows], 0, 1), np.prod(probabilities[rows], axis=1)


def rms_slack(n_repeats: int) -> float:
    # The mean of n squared errors has relative sd <= sqrt(2/n) for Gaussian errors; three of those.
    return math.sqrt(1.0 + 3.0 * math.sqrt(2.0 / n_repeats))


# --------------------------------------------------------------------------
# Exactness
# --------------------------------------------------------------------------


@pytest.mark.parametrize("n", [4, 5, 7])
def test_h_statistics_are_unbiased_over_all_samples(n):
    support = np.array([0.0, 1.0, 3.0, -2.5])
    probabilities = np.array([0.4, 0.3, 0.2, 0.1])
    samples, weights = enumerate_samples(support, probabilities, n)
    mean = probabilities @ support
    for statistic, order in ((h2, 2), (h3, 3), (h4, 4)):
        expectation = weights @ statistic(samples)
        exact = probabilities @ (support - mean) ** order
        assert expectation == pytest.approx(exact, rel=1e-12), statistic.__name__


def test_h_statistics_of_a_column_and_of_a_1d_sample_agree():
    sample = np.random.default_rng(3).gamma(2.0, size=50)
    for statistic in (h2, h3, h4):
        assert isinstance(statistic(sample), float)
        assert statistic(sample) == pytest.approx(statistic(np.stack([sample, 2 * sample], axis=1))[0], rel=1e-14)
    assert h2(sample) == pytest.approx(np.var(sample, ddof=1), rel=1e-14)


BIVARIATE = (np.array([[0.0, 1.0], [1.0, 0.0], [2.0, 3.0], [-1.0, 1.5]]), np.array([0.25, 0.25, 1 / 3, 1 / 6]))


@pytest.mark.parametrize("n", [4, 5, 6])
def test_variance_of_the_h2_difference_is_estimated_without_bias(n):
    support, probabilities = BIVARIATE
    samples, weights = enumerate_samples(support, probabilities, n)
    fine, coarse = samples[..., 0], samples[..., 1]
    term = h2(fine) - h2(coarse)
    exact = weights @ term**2 - (weights @ term) ** 2
    assert weights @ h2_difference_variance(fine, coarse) == pytest.approx(exact, rel=1e-12)
    # The closed form of the module docstring, from the moments of D = X - Y, S = X + Y.
    d, s = support[:, 0] - support[:, 1], support[:, 0] + support[:, 1]
    d, s = d - probabilities @ d, s - probabilities @ s
    mu22, cov, var_d, var_s = (probabilities @ v for v in (d**2 * s**2, d * s, d**2, s**2))
    closed = mu22 / n - (n - 2) / (n * (n - 1)) * cov**2 + var_d * var_s / (n * (n - 1))
    assert exact == pytest.approx(closed, rel=1e-12)


def test_variance_of_h2_alone_is_estimated_without_bias():
    support, probabilities = BIVARIATE[0][:, 0], BIVARIATE[1]
    samples, weights = enumerate_samples(support, probabilities, 5)
    exact = weights @ h2(samples) ** 2 - (weights @ h2(samples)) ** 2
    assert weights @ h2_difference_variance(samples) == pytest.approx(exact, rel=1e-12)


def test_the_variance_level_term_is_the_h2_difference():
    rng = np.random.default_rng(11)
    fine = rng.normal(size=(30, 2))
    coarse = fine + 0.1 * rng.normal(size=(30, 2))
    term = variance_level_term(fine, coarse, 3)
    np.testing.assert_allclose(term.mean, h2(fine) - h2(coarse), rtol=1e-12)
    plug_in = plug_in_variance(fine - coarse, fine + coarse)
    np.testing.assert_allclose(term.variance, np.maximum(h2_difference_variance(fine, coarse), plug_in), rtol=1e-12)
    assert term.n_samples == 30 and term.groups.tolist() == [0, 1]
    base = variance_level_term(fine, None)
    np.testing.assert_allclose(base.mean, h2(fine), rtol=1e-12)


def plug_in_variance(d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The sample variance of ``(d - mean d)(s - mean s)`` over ``n``, per column."""
    products = (d - d.mean(axis=0)) * (s - s.mean(axis=0))
    return products.var(axis=0, ddof=1) / len(d)


def test_a_level_whose_unbiased_variance_is_negative_gets_the_plug_in_one():
    # The first 32 pairs of level 1 of a discrete QoI: two differ, (0, 1) and (1, 0), so T = 0 and T^2 - U4 is
    # negative. Clipped at 0, the level looked exact (no samples beyond its first, nothing added to the error).
    fine, coarse, _ = RoundedLimit(seed=36)(1, np.arange(32))
    fine, coarse = fine[:, None], coarse[:, None]
    assert np.count_nonzero(fine != coarse) == 2
    assert h2_difference_variance(fine, coarse) < 0
    term = variance_level_term(fine, coarse, 1)
    plug_in = plug_in_variance(fine - coarse, fine + coarse)
    assert plug_in > 0 and term.variance == pytest.approx(plug_in, rel=1e-12)


def test_a_discrete_qoi_whose_level_terms_come_out_negative_keeps_an_honest_error():
    # Seed 36 of this hierarchy gave level 1 a clipped variance of 0 at its 32 samples: the run claimed
    # tol 0.05 with an RMSE of 0.041 at an error of 0.52 (12.7 RMSE). (The plug-in variance or the floor from
    # the level above each mends it alone; the unit test above pins the plug-in.)
    problem = RoundedLimit(seed=36)
    result = mlmc_variance(problem, tol=0.05)
    assert result.tol_met and result.n_samples[1] > 1000
    assert abs(result.estimate[0] - problem.variance()) < 3 * result.rmse[0]


def test_a_level_that_missed_its_rare_jumps_is_floored_by_the_level_above():
    # Level 1's 32 samples of seed 5 saw none of its jumps (probability 0.1 each): V_1 = 0 kept them at 32,
    # and the run claimed tol 0.05 with an RMSE of 0.034 at an error of 0.46. Half the V of level 2 as its
    # planning floor draws the jumps; the kurtosis check of the final levels now warns (SPEC section 5).
    problem = RareJumps(seed=5)
    with pytest.warns(EstimationWarning, match=r"^variance: level \d: kurtosis \d+ of Q_l - Q_l-1 for QoI \[0\]"):
        result = mlmc_variance(problem, tol=0.05)
    assert result.n_samples[1] > 1000
    assert abs(result.estimate[0] - problem.variance()) < 3 * result.rmse[0]


# --------------------------------------------------------------------------
# Brute-force repetitions
# --------------------------------------------------------------------------


def coupled_pairs(rng: np.random.Generator, n: int, repeats: int) -> tuple[np.ndarray, np.ndarray]:
    """``repeats`` samples (columns) of ``n`` skewed, coupled pairs ``X = Z + W/4``, ``Y = Z + W/2``."""
    z = rng.gamma(2.0, size=(n, repeats))
    w = rng.normal(size=(n, repeats))
    return z + 0.25 * w, z + 0.5 * w


@pytest.mark.parametrize("n", [6, 40])
def test_estimated_variance_of_the_h2_difference_matches_repetitions(n):
    repeats = 40_000
    fine, coarse = coupled_pairs(np.random.default_rng(n), n, repeats)
    term = h2(fine) - h2(coarse)
    estimated = h2_difference_variance(fine, coarse)
    empirical = np.var(term, ddof=1)
    # Standard errors: of the mean of the estimates, and of a sample variance (fourth moment).
    se_estimated = np.std(estimated, ddof=1) / math.sqrt(repeats)
    centred = term - term.mean()
    se_empirical = math.sqrt((np.mean(centred**4) - empirical**2) / repeats)
    assert abs(np.mean(estimated) - empirical) < 4.0 * math.hypot(se_estimated, se_empirical)


@pytest.mark.parametrize("order", [3, 4])
def test_central_moment_level_terms_are_unbiased_and_their_variance_consistent(order):
    n, repeats = 400, 4000
    fine, coarse = coupled_pairs(np.random.default_rng(order), n, repeats)
    exact = {}  # central moments of Z + c W, Z ~ Gamma(2), W ~ N(0, 1), from the cumulants
    for c in (0.25, 0.5):
        k2, k3, k4 = 2.0 + c**2, 4.0, 12.0  # cumulants of Gamma(2) plus those of N(0, c^2)
        exact[c] = k3 if order == 3 else k4 + 3 * k2**2
    # One column per repetition: the term treats columns as independent QoIs.
    term = central_moment_level_term(fine, coarse, order=order)
    means = term.mean
    assert abs(means.mean() - (exact[0.25] - exact[0.5])) < 4.0 * means.std(ddof=1) / math.sqrt(repeats)
    # The influence-function variance is consistent: at n = 400 its O(1/n) relative bias is
    # below 2%, next to the 4-standard-error band of the ratio (about 9% for 4000 repeats).
    ratio = np.mean(term.variance) / np.var(means, ddof=1)
    assert abs(ratio - 1.0) < 4.0 * math.sqrt(2.0 / (repeats - 1)) + 0.02


# --------------------------------------------------------------------------
# MLMC variance on known answers
# --------------------------------------------------------------------------


def variance_runs(kind: str, tol: float, n_repeats: int):
    problems = [PerturbedLimit(kind=kind, seed=seed) for seed in range(n_repeats)]
    return [(problem, mlmc_variance(problem, tol=tol)) for problem in problems]


@pytest.mark.parametrize(("kind", "tol", "n_repeats"), [("gaussian", 0.05, 100), ("gamma", 0.2, 40)])
def test_mlmc_variance_rms_error_is_within_tolerance(kind, tol, n_repeats):
    runs = variance_runs(kind, tol, n_repeats)
    errors = np.array([result.estimate[0] - problem.variance() for problem, result in runs])
    assert math.sqrt(np.mean(errors**2)) <= tol * rms_slack(n_repeats)
    for problem, result in runs:
        assert result.stop_reason == "tol_met" and result.tol_met
        assert result.rmse[0] <= tol and result.bias[0] <= math.sqrt(THETA) * tol
        assert result.stat_error[0] ** 2 <= (1 - THETA) * tol**2 * 1.01  # within the driver's 1% slack
    # The statistical error is calibrated: z = (estimate - Var(Q_L)) / stat_error has mean square
    # about 1 (chi-square over n_repeats, sd sqrt(2/n); four of those).
    z = np.array([(r.estimate[0] - p.variance(r.finest_level)) / r.stat_error[0] for p, r in runs])
    assert abs(np.mean(z**2) - 1.0) < 4.0 * math.sqrt(2.0 / n_repeats)
    # The true remaining bias c^2 4^-L / 3 meets its share in all but a few runs (noisy bias test).
    too_coarse = sum(p.variance(r.finest_level) - p.variance() > math.sqrt(THETA) * tol for p, r in runs)
    assert too_coarse <= 0.05 * n_repeats


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["gaussian", "gamma"])
def test_mlmc_variance_error_and_cost_follow_the_tolerance(kind):
    # RMSE ~ tol and, with beta = 2 > gamma = 1, cost ~ tol^-2 (SPEC section 5).
    scale = 1.0 if kind == "gaussian" else 4.0
    tols = scale * np.array([0.08, 0.04, 0.02])
    n_repeats = 40
    rmse, cost = [], []
    for tol in tols:
        runs = variance_runs(kind, float(tol), n_repeats)
        errors = [r.estimate[0] - p.variance() for p, r in runs]
        rmse.append(math.sqrt(np.mean(np.square(errors))))
        cost.append(np.mean([r.cost for _, r in runs]))
        assert rmse[-1] <= tol * rms_slack(n_repeats)
    error_rate = np.polyfit(np.log2(tols), np.log2(rmse), 1)[0]
    cost_rate = np.polyfit(np.log2(tols), np.log2(cost), 1)[0]
    # Each RMSE has relative sd ~ 1/sqrt(2 n) = 0.11 (0.16 in log2); the slope over two octaves
    # has sd ~ 0.16 / sqrt(2) = 0.11: four of those. Cost: discrete levels add up to one
    # level's worth (factor 2) at either end, so allow 0.5 on the slope of -2.
    assert abs(error_rate - 1.0) < 0.45
    assert abs(cost_rate + 2.0) < 0.5


def test_mlmc_fourth_central_moment_is_within_tolerance():
    # Gaussian limit: mu4(Q_l) = 3 (1 + 4^-l)^2 -> 3, level terms decay like 4^-l.
    tol, n_repeats = 0.6, 30
    errors = []
    for seed in range(n_repeats):
        result = mlmc_central_moment(PerturbedLimit(seed=seed), order=4, tol=tol)
        assert result.stop_reason == "tol_met" and result.tol_met
        errors.append(result.estimate[0] - 3.0)
    assert math.sqrt(np.mean(np.square(errors))) <= tol * rms_slack(n_repeats)
    with pytest.raises(InvalidParameterError, match="order"):
        mlmc_central_moment(PerturbedLimit(), order=2, tol=tol)


def test_variance_from_given_samples_telescopes_to_var_q_l():
    problem = PerturbedLimit(seed=5)
    n = 20_000
    fine, coarse = [], []
    for level in range(4):
        f, c, _ = problem(level, np.arange(n))
        fine.append(f)
        coarse.append(c)
    result = variance_from_samples(fine=fine, coarse=coarse, tol=0.05)
    assert result.stop_reason == "given" and result.levels.tolist() == [0, 1, 2, 3]
    assert abs(result.estimate[0] - problem.variance(3)) < 4.0 * result.stat_error[0]
    # alpha of Var(Q_l) - Var(Q_l-1) = -3 c^2 4^-l is 2; the fit sees it within noise.
    assert abs(result.alpha[0] - 2.0) < 0.5
    exact_bias = problem.variance(3) - problem.variance()
    assert result.bias[0] == pytest.approx(exact_bias, rel=0.5)


def test_the_sample_plan_is_the_mean_formula_with_the_variance_of_the_h2_terms():
    problem = PerturbedLimit(seed=6)
    terms, costs = [], []
    for level in range(4):
        fine, coarse, cost = problem(level, np.arange(500))
        terms.append(variance_level_term(fine, None if level == 0 else coarse, level))
        costs.append(np.mean(cost))
    costs = np.array(costs)
    tol = 0.05
    n_planned = sample_plan(terms, costs=costs, tol=tol)
    per_sample = np.array([[t.per_sample_variance[0]] for t in terms])
    expected = np.ceil(optimal_samples(per_sample, costs, np.array([0.5 * tol**2])))[:, 0]
    np.testing.assert_array_equal(n_planned, expected)
    # The plan meets the statistical share of the tolerance with the screened W_l.
    assert np.sum(per_sample[:, 0] / n_planned) <= 0.5 * tol**2
    with pytest.raises(EstimationError, match="one value per level"):
        sample_plan(terms, costs=costs[:2], tol=tol)


def test_max_level_and_max_cost_stop_honestly():
    problem = PerturbedLimit(scale=4.0)
    # Var(Q_2) - Var(Q) = 16 / 16 is far above the bias share of 0.3, which level 2 cannot meet.
    result = mlmc_variance(problem, tol=0.3, max_level=2)
    assert result.stop_reason == "max_level" and not result.tol_met and result.finest_level == 2
    capped = mlmc_variance(problem, tol=0.005, max_cost=20_000.0)
    assert capped.stop_reason == "max_cost" and capped.cost <= 20_000.0 and not capped.tol_met


def test_a_max_level_stop_on_terms_within_their_noise_says_so():
    # Var(Q_2) - Var(Q) = 0.09 / 16 is far below the bias share of 0.035, but the level-2 term is noise and the
    # bias estimate (0.086) the level-1 term at the floor rate: the run said only that the bias needs a finer grid.
    with pytest.warns(EstimationWarning, match=r"the bias estimate 0.0855 \(the tolerance's share 0.0354\) rests on "
                      r"level terms within their noise .* more initial samples per level may measure it"):
        noisy = mlmc_variance(PerturbedLimit(scale=0.3), tol=0.05, max_level=2, n_initial=8)
    assert noisy.stop_reason == "max_level" and not noisy.tol_met and noisy.noisy_bias_groups == (0,)
    # A bias the finest level measures (1/16 against the share 0.035) is not put down to noise.
    with warnings.catch_warnings():
        warnings.simplefilter("error", EstimationWarning)
        real = mlmc_variance(PerturbedLimit(scale=1.0), tol=0.05, max_level=2, n_initial=8)
    assert real.stop_reason == "max_level" and real.noisy_bias_groups == ()


def test_terms_of_exactly_zero_on_the_finest_level_are_measured_not_noise():
    # A CDF away from every sample has terms of exactly 0 with no spread: its bias is not the terms' noise.
    groups = np.array([0])

    def term(mean, variance):
        return LevelTerm(mean=np.array([mean]), variance=np.array([variance]), n_samples=10, groups=groups)

    exact = telescope([term(1.0, 0.01), term(0.5, 1e-4), term(0.0, 0.0)], tol=0.05)
    noisy = telescope([term(1.0, 0.01), term(0.5, 1e-4), term(1e-3, 1e-2)], tol=0.05)
    assert exact.bias[0] > 0.05 and noisy.bias[0] > 0.05  # both fail the bias test (the level-1 term, floor rate)
    assert exact.noisy_bias_groups == () and noisy.noisy_bias_groups == (0,)


@pytest.mark.parametrize(("tol", "max_cost", "levels"), [(60.0, 1e-9, [0]), (0.5, 40.0, [0]), (3.0, 100.0, [0, 1])])
def test_a_budget_stop_before_the_bias_is_estimated_does_not_claim_the_tolerance(tol, max_cost, levels):
    # Level 0 costs 32 and level 1 64: the budget stops the run below min_finest_level = 2, before its first
    # bias test. The run claimed the tolerance met: on level 0 with "bias 0" and a statistical error of 0.42,
    # on levels 0..1 with an RMS error of 2.2 from a bias that level 1 alone can only guess.
    result = mlmc_variance(PerturbedLimit(), tol=tol, max_cost=max_cost)
    assert result.stop_reason == "max_cost" and result.levels.tolist() == levels
    assert result.stat_error[0] < tol
    assert not result.is_bias_estimated and result.bias[0] == 0.0 and not result.tol_met


def test_a_budget_stop_after_the_first_bias_test_is_met_only_by_its_rms_error():
    # Levels 0..2 cost 32 * (1 + 2 + 4) = 224; level 3 (32 * 8) does not fit into 300.
    result = mlmc_variance(PerturbedLimit(), tol=2.0, max_cost=300.0)
    assert result.stop_reason == "max_cost" and result.levels.tolist() == [0, 1, 2]
    assert result.is_bias_estimated and result.bias[0] > 0
    assert result.tol_met == bool(result.rmse[0] <= 2.0)
    # One level short of the minimum: not estimated, whatever the error.
    assert not mlmc_variance(PerturbedLimit(), tol=2.0, max_cost=300.0, min_finest_level=3).is_bias_estimated


@pytest.mark.parametrize("max_cost", [1e-9, 32.0])
def test_a_batch_cap_below_n_initial_only_splits_the_initial_samples_within_a_budget(max_cost):
    # A level is started only if the budget pays for its n_initial samples, and then gets all of them:
    # the variance of an h2 term needs four. Capped at 2 per batch, the budget stopped level 0 (first
    # batch always drawn) or level 2 after 2 samples, and the term of that level refused them.
    problem = PerturbedLimit(seed=3)
    capped = mlmc_variance(problem, tol=0.01, n_initial=8, batch_size=2, max_cost=max_cost)
    uncapped = mlmc_variance(problem, tol=0.01, n_initial=8, batch_size=None, max_cost=max_cost)
    assert capped.stop_reason == uncapped.stop_reason == "max_cost"
    assert capped.n_samples.tolist() == uncapped.n_samples.tolist() == [8] * len(capped.levels)
    np.testing.assert_array_equal(capped.estimate, uncapped.estimate)
    assert not capped.tol_met and not capped.is_bias_estimated


def test_given_samples_of_level_0_alone_estimate_no_bias():
    fine, _, _ = PerturbedLimit(seed=5)(0, np.arange(1000))
    result = variance_from_samples(fine=[fine], coarse=[fine], tol=10.0)
    assert result.stat_error[0] < 10.0 and not result.is_bias_estimated and not result.tol_met
    two = [PerturbedLimit(seed=5)(level, np.arange(1000)) for level in range(2)]
    assert variance_from_samples(fine=[d[0] for d in two], coarse=[d[1] for d in two], tol=10.0).tol_met


def test_several_qois_get_one_tolerance_each():
    def two(level, indices):
        fine, coarse, cost = PerturbedLimit(seed=2)(level, indices)
        return np.stack([fine, 3 * fine], axis=1), np.stack([coarse, 3 * coarse], axis=1), cost

    result = mlmc_variance(two, tol=[0.05, 0.45])
    assert result.estimate.shape == (2,) and result.tol.tolist() == [0.05, 0.45]
    assert result.tol_met
    assert result.estimate[1] == pytest.approx(9 * result.estimate[0], rel=1e-12)


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------


@pytest.mark.parametrize("tol", [0.0, -1.0, float("nan"), [0.1, 0.0]])
def test_non_positive_tolerances_are_refused(tol):
    with pytest.raises(InvalidParameterError, match="tol"):
        mlmc_variance(PerturbedLimit(), tol=tol)


@pytest.mark.parametrize("scale", [1e-80, 1e-100])
def test_a_tolerance_whose_squares_underflow_is_refused(scale):
    # The variance of values of about 1e-80 at a relative tolerance of 5 %: the error of the variance (fourth
    # powers) underflowed to 0 and the run reported its tolerance met with an RMS error of exactly 0; at 1e-100
    # it failed with a bare ValueError (NaN sample counts).
    def tiny(level, indices):
        fine, coarse, cost = PerturbedLimit()(level, indices)
        return fine * scale, coarse * scale, cost

    with pytest.raises(InvalidParameterError, match=r"^tol: got .*; allowed: tolerances in \[1e-140, 1e\+140\] "):
        mlmc_variance(tiny, tol=0.05 * scale**2)
    for order in (3, 4):
        with pytest.raises(InvalidParameterError, match=r"allowed: tolerances in \[1e-140, "):
            mlmc_central_moment(tiny, order=order, tol=1e-200)


def test_too_few_samples_and_bad_shapes_are_refused():
    with pytest.raises(InvalidParameterError, match="at least 4 samples"):
        h2_difference_variance(np.arange(3.0), np.arange(3.0))
    with pytest.raises(InvalidParameterError, match="at least 3 samples"):
        h3(np.arange(2.0))
    with pytest.raises(InvalidParameterError, match="coarse"):
        variance_level_term(np.zeros((5, 2)), np.zeros((5, 1)))
    with pytest.raises(InvalidParameterError, match="finite"):
        h2(np.array([1.0, np.inf, 2.0]))
    with pytest.raises(InvalidParameterError, match="order"):
        central_moment_level_term(np.zeros(10), None, order=5)
    with pytest.raises(InvalidParameterError, match="n_initial"):
        mlmc_variance(PerturbedLimit(), tol=0.1, n_initial=3)
    with pytest.raises(InvalidParameterError, match="theta"):
        mlmc_variance(PerturbedLimit(), tol=0.1, theta=1.0)
    with pytest.raises(EstimationError, match="one entry per level"):
        variance_from_samples(fine=[np.zeros(5)], coarse=[])


def test_telescope_refuses_mismatched_terms():
    a = LevelTerm(mean=np.zeros(2), variance=np.zeros(2), n_samples=4, groups=np.arange(2))
    b = LevelTerm(mean=np.zeros(3), variance=np.zeros(3), n_samples=4, groups=np.arange(3))
    with pytest.raises(EstimationError, match=r"different components: term 1 has means of shape \(3,\) and 3 groups, "
                                              r"term 0 \(2,\) and 2$"):
        telescope([a, b])
    c = LevelTerm(mean=np.zeros(300), variance=np.zeros(300), n_samples=4, groups=np.zeros(300, dtype=int))
    d = LevelTerm(mean=np.zeros(300), variance=np.zeros(300), n_samples=4, groups=np.r_[np.zeros(299, dtype=int), 1])
    with pytest.raises(EstimationError, match=r"\(group 1 at component 299 against 0\)$"):
        telescope([c, d])
    with pytest.raises(EstimationError, match="at least one level"):
        telescope([])
    with pytest.raises(InvalidParameterError, match="a scalar or 2 values"):
        telescope([a], tol=[0.1, 0.1, 0.1])
    with pytest.raises(InvalidParameterError, match="batch_size"):
        adaptive_mlmc(PerturbedLimit(), term=variance_level_term, tol=0.1, batch_size=0)
    for name in ("n_initial", "min_finest_level", "max_level", "batch_size", "max_samples"):
        for value in (True, 8.0, "8"):  # errors.checked_integer: nothing is converted
            with pytest.raises(InvalidParameterError, match=rf"^{name}: got .*; allowed: an integer >= \d+$"):
                adaptive_mlmc(PerturbedLimit(), term=variance_level_term, tol=0.1, **{name: value})
    result = adaptive_mlmc(
        PerturbedLimit(), term=variance_level_term, tol=1.0, n_initial=np.int64(8), max_level=np.int32(4)
    )
    assert result.n_samples[0] >= 8  # numpy integers are integers


def test_a_batch_cap_below_n_initial_only_splits_the_initial_samples():
    # A batch cap is not a budget: the initial samples arrive in several batches, and the
    # estimate is the one drawn without a cap (samples are keyed by index, not by batch).
    problem = PerturbedLimit(seed=3)
    capped = mlmc_variance(problem, tol=0.1, n_initial=32, batch_size=10)
    uncapped = mlmc_variance(problem, tol=0.1, n_initial=32, batch_size=None)
    assert capped.stop_reason == "tol_met"
    np.testing.assert_array_equal(capped.n_samples, uncapped.n_samples)
    np.testing.assert_array_equal(capped.estimate, uncapped.estimate)


def test_a_budget_that_pays_a_variance_run_changes_nothing():
    free = mlmc_variance(PerturbedLimit(seed=3), tol=0.05, batch_size=20)
    paid = mlmc_variance(PerturbedLimit(seed=3), tol=0.05, batch_size=20, max_cost=1.01 * free.cost)
    assert paid.tol_met and paid.n_samples.tolist() == free.n_samples.tolist()
    np.testing.assert_array_equal(paid.estimate, free.estimate)


def test_a_variance_run_without_a_budget_draws_whole_batches():
    # Passes in proportion to the missing samples (also without a budget) cut the batches of the finer levels to
    # 2-4 samples: some 1.8 times the sampler calls, each an executor round trip and a store append in a study.
    sizes = []

    def recorded(level, indices):
        sizes.append(len(indices))
        return PerturbedLimit(seed=3)(level, indices)

    mlmc_variance(recorded, tol=0.05, batch_size=10)
    assert np.median(sizes) == 10 and max(sizes) == 10


def test_qoi_names_that_do_not_match_the_columns_are_refused_after_the_first_round():
    # They were checked only after the whole run (22 000 samples), under the name "names".
    drawn = []

    def sampler(level, indices):
        drawn.append(len(indices))
        return PerturbedLimit(seed=1)(level, indices)

    with pytest.raises(InvalidParameterError, match="^qoi_names: "):
        mlmc_variance(sampler, tol=0.05, qoi_names=("a", "b"))
    assert sum(drawn) == 3 * 32  # the first round: the initial samples of levels 0..2
    with pytest.raises(InvalidParameterError, match="^qoi_names: "):
        mlmc_variance(sampler, tol=0.05, qoi_names="a")


def test_a_level_whose_variance_is_a_bound_at_most_doubles_its_samples_per_round():
    # A bound 3 / N^2 (a CDF level whose pairs changed no indicator) planned as a measured W = 3 / N asked for
    # far more samples than the bound needs; the round doubles them at most and looks again.
    from rough_uq.multilevel.targets import _Level, _targets

    levels = [_Level(0), _Level(1)]
    for s in levels:
        s.add(np.zeros((32, 1)), np.zeros((32, 1)), np.full(32, 2.0**s.level))
    measured = LevelTerm(mean=np.array([0.5]), variance=np.array([1e-3]), n_samples=32, groups=np.array([0]))
    bounded = {"mean": np.array([0.0]), "variance": np.array([3 / 32**2]), "n_samples": 32, "groups": np.array([0])}
    plan = functools.partial(_targets, levels, n_initial=32, tol=np.array([0.001]), theta=0.5,
                             beta=np.array([1.0]), gamma=1.0)
    assert plan([measured, LevelTerm(**bounded)])[1] > 1000
    assert plan([measured, LevelTerm(**bounded, is_bound=True)])[1] == 64

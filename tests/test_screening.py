"""Screening table, rate fits and plans against problems with known answers.

Statistical assertions use fixed seeds and tolerances of four standard
errors unless stated otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from mlmc_problems import GbmEuler, Synthetic, sample_levels
from scipy import stats as scipy_stats

from rough_uq.errors import EstimationError, InvalidParameterError
from rough_uq.multilevel.allocation import plan
from rough_uq.multilevel.rates import (
    DROP_MARGIN,
    EXACT_RATE,
    Rates,
    choose_coarsest_level,
    estimated_bias,
    fit_rates,
    remaining_bias,
)
from rough_uq.multilevel.statistics import CONSISTENCY_CHECK_SAMPLES, EstimationWarning, diagnose, level_statistics


@pytest.fixture(scope="module")
def gbm_statistics():
    problem = GbmEuler(r=1.0, sigma=0.5, seed=11)
    return problem, level_statistics(**sample_levels(problem, range(8), 20_000))


# --------------------------------------------------------------------------
# level_statistics
# --------------------------------------------------------------------------


def test_level_statistics_matches_direct_formulas():
    rng = np.random.default_rng(1)
    fine0 = rng.normal(size=(50, 2))
    fine1 = rng.normal(size=(40, 2))
    coarse1 = fine1 + 0.3 * rng.standard_t(5, size=(40, 2))
    cost = [rng.uniform(1, 2, 50), rng.uniform(3, 4, 40)]
    table = level_statistics(fine=[fine0, fine1], coarse=[np.zeros((50, 2)), coarse1], cost=cost)

    diff1 = fine1 - coarse1
    np.testing.assert_allclose(table.mean_fine[1], fine1.mean(0))
    np.testing.assert_allclose(table.var_fine[1], fine1.var(0, ddof=1))
    np.testing.assert_allclose(table.var_coarse[1], coarse1.var(0, ddof=1))
    np.testing.assert_allclose(table.mean_diff[1], diff1.mean(0))
    np.testing.assert_allclose(table.var_diff[1], diff1.var(0, ddof=1))
    np.testing.assert_allclose(table.var_diff[0], fine0.var(0, ddof=1))
    np.testing.assert_allclose(table.kurtosis[1], scipy_stats.kurtosis(diff1, fisher=False, bias=True))
    np.testing.assert_allclose(table.var_delta[1], fine1.var(0, ddof=1) - coarse1.var(0, ddof=1))
    np.testing.assert_allclose(table.var_delta[0], fine0.var(0, ddof=1))
    np.testing.assert_allclose(table.mean_cost, [c.mean() for c in cost])
    assert table.n_samples.tolist() == [50, 40]
    assert table.n_qoi == 2 and table.n_levels == 2


def test_variance_difference_standard_error_matches_its_sampling_spread():
    # 4000 independent screening tables of n = 40 correlated pairs: the spread of
    # var_delta must match the exact formula and the mean reported error^2.
    rng = np.random.default_rng(2)
    n, n_rep = 40, 4000
    x = rng.normal(size=(n_rep, n))
    y = 0.8 * x + 0.5 * rng.exponential(size=(n_rep, n))
    deltas = np.empty(n_rep)
    se2 = np.empty(n_rep)
    for rep in range(n_rep):
        table = level_statistics(fine=[x[rep], x[rep]], coarse=[np.zeros(n), y[rep]], cost=[np.ones(n)] * 2)
        deltas[rep] = table.var_delta[1, 0]
        se2[rep] = table.var_delta_se[1, 0] ** 2
    true_delta = 1.0 - (0.64 + 0.25)  # Var(x) - Var(0.8 x + 0.5 Exp(1))
    empirical = deltas.var(ddof=1)
    # The estimator is unbiased: mean within 4 standard errors of the mean.
    assert abs(deltas.mean() - true_delta) < 4 * math.sqrt(empirical / n_rep)
    # The sample variance of 4000 values has relative sd ~ sqrt((kurt - 1)/4000) < 5%;
    # the plug-in se^2 is biased low by O(1/n); allow 15%.
    assert se2.mean() == pytest.approx(empirical, rel=0.15)


def test_gaussian_level_zero_variance_error_is_textbook():
    # For X = Y (level 0) the formula is Var(s^2) = (mu4 - (n-3)/(n-1) sigma^4)/n, i.e.
    # 2 sigma^4/(n-1) for Gaussian data; with plug-in moments it is close to that.
    sample = np.random.default_rng(3).normal(scale=2.0, size=200_000)
    table = level_statistics(fine=[sample], coarse=[np.zeros_like(sample)], cost=[np.ones_like(sample)])
    assert table.var_delta_se[0, 0] == pytest.approx(math.sqrt(2 * 16.0 / (len(sample) - 1)), rel=0.02)


def test_gbm_level_means_and_variances_match_closed_form(gbm_statistics):
    problem, table = gbm_statistics
    n = table.n_samples[:, None]
    for row, level in enumerate(table.levels):
        expected_q = problem.mean(level)
        se_q = math.sqrt(table.var_fine[row, 0] / n[row, 0])
        assert abs(table.mean_fine[row, 0] - expected_q) < 4 * se_q, level
        expected_y = expected_q - (problem.mean(level - 1) if level else 0.0)
        se_y = math.sqrt(table.var_diff[row, 0] / n[row, 0])
        assert abs(table.mean_diff[row, 0] - expected_y) < 4 * se_y, level
        # se of a sample variance: V sqrt((kurtosis - (n-3)/(n-1)) / n)
        kurt = table.kurtosis[row, 0]
        se_v = problem.var_diff(level) * math.sqrt((kurt - 1) / n[row, 0])
        assert abs(table.var_diff[row, 0] - problem.var_diff(level)) < 4 * se_v, level
    assert np.all(table.is_consistent)
    assert np.all(table.is_coupled)
    assert diagnose(table) == ()


def test_gbm_rates_match_euler_maruyama_theory(gbm_statistics):
    problem, table = gbm_statistics
    rates = fit_rates(table, min_level=3)
    levels = np.array(rates.levels_alpha[0])
    assert levels.tolist() == [3, 4, 5, 6, 7] == list(rates.levels_beta[0])
    # Theory: Euler-Maruyama has weak order 1 (E[S_T^(l)] = S0 (1 + r h)^(1/h) = S0 e^r (1 - r^2 h/2 + ...),
    # so alpha = 1) and strong order 1/2 for multiplicative noise (the missing Milstein term
    # sigma^2 S (dW^2 - h)/2 makes S_fine - S_coarse = O(h^1/2), so V_l ~ h and beta = 1 -- not the
    # beta = 2 of Milstein). The closed-form values confirm it on fine levels...
    deep = np.arange(10, 16)
    exact_mean = [problem.mean(level) - problem.mean(level - 1) for level in deep]
    exact_var = [problem.var_diff(level) for level in deep]
    assert -np.polyfit(deep, np.log2(exact_mean), 1)[0] == pytest.approx(1.0, abs=0.01)
    assert -np.polyfit(deep, np.log2(exact_var), 1)[0] == pytest.approx(1.0, abs=0.01)
    # ... while on the screened levels 3..7 (r h up to 1/8) the closed-form slopes are still
    # pre-asymptotic (0.90 and 1.09). The fit from samples must reproduce those within 4 se,
    fit_alpha = -np.polyfit(levels, np.log2([problem.mean(lv) - problem.mean(lv - 1) for lv in levels]), 1)[0]
    fit_beta = -np.polyfit(levels, np.log2([problem.var_diff(lv) for lv in levels]), 1)[0]
    assert abs(rates.alpha[0] - fit_alpha) < 4 * rates.alpha_se[0]
    assert abs(rates.beta[0] - fit_beta) < 4 * rates.beta_se[0]
    # and so lies within that pre-asymptotic offset (0.11) plus 4 se of the theoretical 1.
    assert abs(rates.alpha[0] - 1.0) < 0.11 + 4 * rates.alpha_se[0]
    assert abs(rates.beta[0] - 1.0) < 0.11 + 4 * rates.beta_se[0]
    assert rates.alpha_se[0] < 0.05 and rates.beta_se[0] < 0.05  # the test has power
    # The cost is 1.5 * 2^l time steps exactly: gamma = 1, c_gamma = 1.5.
    assert rates.gamma == pytest.approx(1.0, abs=1e-12)
    assert rates.c_gamma == pytest.approx(1.5, rel=1e-12)


def test_fit_rates_recovers_prescribed_exponents():
    problem = Synthetic(alpha=1.5, beta=2.5, gamma=1.0, a=2.0, v1=3.0, seed=5)
    table = level_statistics(**sample_levels(problem, range(7), 4000))
    rates = fit_rates(table)
    assert rates.levels_alpha[0] == (1, 2, 3, 4, 5, 6)
    assert abs(rates.alpha[0] - 1.5) < 4 * rates.alpha_se[0]
    assert abs(rates.beta[0] - 2.5) < 4 * rates.beta_se[0]
    # Constants: log2 c has a standard error of roughly se(rate) * mean level.
    assert abs(math.log2(rates.c_alpha[0] / 2.0)) < 4 * rates.alpha_se[0] * 3.5 + 0.05
    assert abs(math.log2(rates.c_beta[0] / 3.0)) < 4 * rates.beta_se[0] * 3.5 + 0.05
    assert rates.gamma == pytest.approx(1.0, abs=1e-12)
    assert 0 < rates.alpha_se[0] < 0.2 and 0 < rates.beta_se[0] < 0.2


def test_rate_standard_errors_are_honest_over_repetitions():
    # z-scores of the fitted rates over independent screenings: mean ~ 0, sd ~ 1 (<= 1.5
    # since the errors are conservative: the larger of two estimates).
    z_alpha, z_beta = [], []
    for seed in range(40):
        problem = Synthetic(alpha=1.0, beta=2.0, seed=100 + seed)
        rates = fit_rates(level_statistics(**sample_levels(problem, range(6), 500)))
        z_alpha.append((rates.alpha[0] - 1.0) / rates.alpha_se[0])
        z_beta.append((rates.beta[0] - 2.0) / rates.beta_se[0])
    for z in (np.array(z_alpha), np.array(z_beta)):
        assert abs(z.mean()) < 4 / math.sqrt(len(z)) * 1.5
        assert 0.4 < z.std() < 1.5


def test_fit_rates_refuses_too_few_usable_levels():
    problem = Synthetic(seed=1)
    table = level_statistics(**sample_levels(problem, range(2), 100))
    with pytest.raises(EstimationError, match="cannot fit alpha .*at least two usable levels"):
        fit_rates(table)
    # A level whose differences are all 0 (mean and variance) shows nothing of the bias: left out, never log(0).
    rng = np.random.default_rng(0)
    q = rng.normal(size=100)
    flat = level_statistics(fine=[q, q, q + rng.normal(size=100)], coarse=[0 * q, q, q], cost=[np.ones(100)] * 3)
    with pytest.raises(EstimationError, match=r"E\[Q_l - Q_l-1\] = 0 and no variance \(unusable\): \[1\]"):
        fit_rates(flat)


def test_level_means_exactly_zero_while_the_differences_vary_are_fitted_at_their_bound():
    """A screening of cluster counts whose level-2 mean came out exactly 0 (half-integer differences that cancel)
    was refused after all its samples: "cannot fit alpha ... levels with E[Q_l - Q_l-1] = 0 (unusable): [2]"."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=100)
    step = np.where(np.arange(100) % 2, 0.5, -0.5)  # +-0.5 in turn: mean exactly 0, variance 0.25
    flat = level_statistics(fine=[q, q + step, q], coarse=[0 * q, q, q + step], cost=[np.ones(100)] * 3)
    assert np.all(flat.mean_diff[1:, 0] == 0.0)
    rates = fit_rates(flat)
    bound = 2.0 * flat.mean_diff_error[1:, 0]  # two standard errors: the largest mean not ruled out
    assert rates.levels_alpha[0] == (1, 2) and np.all(bound > 0)
    np.testing.assert_allclose([rates.bias_model(1)[0], rates.bias_model(2)[0]], bound, rtol=1e-9)


def test_a_column_exact_on_the_fitted_levels_gets_the_exact_rate_and_no_bias():
    # A load curve through full contact (contact area 100 %, one cluster in every sample) made the whole
    # screening fail: "cannot fit alpha for clusters@2.0". Such a column has no bias and no level variance.
    rng = np.random.default_rng(2)
    q = rng.normal(size=(100, 2))
    only_1 = np.array([[0.0, 1.0]])  # column 0: Q_l = Q_l-1 in every sample of levels 1 and 2; column 1 decays
    fine = [q, q + (0.5 + 0.2 * rng.normal(size=(100, 1))) * only_1]
    fine.append(fine[1] + (0.25 + 0.05 * rng.normal(size=(100, 1))) * only_1)
    coarse = [0 * q, q, fine[1]]
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.ones(100), 2 * np.ones(100), 4 * np.ones(100)])
    rates = fit_rates(table, names=("clusters@2.0", "contact_area"))
    assert rates.alpha[0] == rates.beta[0] == EXACT_RATE and rates.c_alpha[0] == rates.c_beta[0] == 0.0
    assert rates.levels_alpha[0] == rates.levels_beta[0] == (1, 2)
    assert 0 < rates.alpha[1] < 10 and 0 < rates.beta[1] < 10  # the other column is fitted as before
    assert rates.bias_model(2)[0] == 0.0 and rates.variance_model(0)[0] == 0.0  # no NaN from inf * 0
    assert remaining_bias(table.mean_diff[-1], rates.alpha)[0] == 0.0
    one_level = level_statistics(fine=fine[:2], coarse=coarse[:2], cost=[np.ones(100)] * 2)
    with pytest.raises(EstimationError, match="cannot fit alpha for QoI 0"):
        fit_rates(one_level)  # one level shows nothing: not called exact


def test_a_level_mean_zero_to_rounding_is_fitted_at_its_bound_not_at_its_rounding():
    # Cluster-count differences whose pooled mean is exactly 0 came out as 1.93e-17: log2(2.06 / 1.93e-17)
    # fitted alpha = 56.6 and every bias term rounded to 0 (a run certified "bias 1.8e-34").
    rng = np.random.default_rng(0)
    n = 30
    start, coarse1, coarse2 = rng.normal(size=(3, n))
    steps = rng.integers(-1, 2, size=n).astype(float)
    table = level_statistics(fine=[start, coarse1 + 2.0 + rng.normal(size=n), coarse2 + steps],
                             coarse=[0 * start, coarse1, coarse2], cost=[np.ones(n)] * 3)
    means = np.array(table.mean_diff)
    means[2, 0] = 1.93e-17
    rounded = fit_rates(dataclasses.replace(table, mean_diff=means))
    bound = 2.0 * table.mean_diff_error[2, 0]
    assert rounded.bias_model(2)[0] == pytest.approx(bound, rel=1e-9)  # not 1.93e-17
    assert rounded.alpha[0] == pytest.approx(math.log2(abs(means[1, 0]) / bound), rel=1e-9)
    means[2, 0] = 1e-6 * math.sqrt(table.var_diff[2, 0])  # small, but resolvable by enough samples: used
    assert fit_rates(dataclasses.replace(table, mean_diff=means)).alpha[0] > 10


def test_fit_rates_names_the_qoi_it_cannot_fit():
    # "cannot fit alpha for QoI 1" named a column index; with the names the error names the QoI.
    rng = np.random.default_rng(1)
    q = rng.normal(size=(100, 2))
    # Column 0's level-1 differences are all 0 (unusable for alpha), its level-2 ones are not; column 1 decays.
    step = np.where(np.arange(100) % 2, 0.5, -0.5)[:, None] * [[1.0, 0.0]]
    fine = [q, q + [[0.0, 0.5]], q + [[0.0, 0.75]] + step + [[0.1, 0.0]]]
    coarse = [0 * q, q, q + [[0.0, 0.5]]]
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.ones(100)] * 3)
    with pytest.raises(EstimationError, match=r"^cannot fit alpha for QoI 0: needs"):
        fit_rates(table)
    with pytest.raises(EstimationError, match=r"^cannot fit alpha for contact_area: needs"):
        fit_rates(table, names=("contact_area", "clusters"))
    with pytest.raises(InvalidParameterError, match="^names"):
        fit_rates(table, names=("contact_area",))


# Pre-asymptotic hierarchy: E[Y_l] = 16 * 8^-l + 2^-l. The fast term dominates levels 1-2,
# the slow one (the asymptotic rate alpha = 1) from level 3 on; V_l tiny, so means are exact
# to about 1e-3 relative.
PRE_ASYMPTOTIC = {"alpha": 3.0, "a": 16.0, "b": 1.0, "alpha2": 1.0, "beta": 2.0, "v1": 1e-4}


def plain_alpha_fit(table):
    """alpha and c_alpha of a least-squares line through every level >= 1 (the old fit)."""
    slope, intercept = np.polyfit(table.levels[1:], np.log2(np.abs(table.mean_diff[1:, 0])), 1)
    return -slope, 2.0**intercept


def test_alpha_is_fitted_on_the_asymptotic_levels_only():
    problem = Synthetic(seed=21, **PRE_ASYMPTOTIC)
    table = level_statistics(**sample_levels(problem, range(5), 50))
    rates = fit_rates(table)
    # Local rates log2 |E[Y_l-1] / E[Y_l]|: 2.3, 1.7, 1.2; the first differs from the window's by > 0.5.
    assert rates.levels_alpha == ((2, 3, 4),)
    old_alpha, _ = plain_alpha_fit(table)
    assert 1.0 < rates.alpha[0] < old_alpha
    # So the predicted tail beyond the finest screened level is nearer the truth than before.
    truth = problem.mean() - problem.mean(4)
    old_prediction = remaining_bias(table.mean_diff[4], np.array([old_alpha]))[0]
    new_prediction = estimated_bias(rates=rates, level=4, mean_diff=table.mean_diff[4])[0]
    assert old_prediction < new_prediction < truth


def test_alpha_is_fitted_on_every_level_without_an_asymptotic_pair():
    # Geometric means: the window spans every level (the rates of test_fit_rates_recovers... too).
    geometric = level_statistics(**sample_levels(Synthetic(seed=22, v1=1e-4), range(5), 50))
    assert fit_rates(geometric).levels_alpha == ((1, 2, 3, 4),)
    # The two finest means change sign (E[Y_l] = 2^-l - 12 * 4^-l: -0.0625 on level 3, +0.0156
    # on level 4, as the classic cluster count's): no window can be anchored, nothing is left out.
    crossing = Synthetic(seed=23, a=1.0, alpha=1.0, b=-12.0, alpha2=2.0, v1=1e-4)
    table = level_statistics(**sample_levels(crossing, range(5), 50))
    assert np.sign(table.mean_diff[3, 0]) != np.sign(table.mean_diff[4, 0])
    rates = fit_rates(table)
    assert rates.levels_alpha == ((1, 2, 3, 4),)
    assert rates.alpha[0] == pytest.approx(plain_alpha_fit(table)[0], rel=1e-9)


def test_estimated_bias_is_the_largest_of_model_and_measured_means():
    rates = Rates(alpha=[1.0, 2.0], beta=2.0, gamma=1.0, c_alpha=[1.0, 8.0], c_beta=1.0, c_gamma=1.0)
    # Level 3: model 1/8 and 8/64; measured -0.5 (QoI 0, above its model) and 0.01 (QoI 1, below).
    bias = estimated_bias(rates=rates, level=3, mean_diff=np.array([-0.5, 0.01]))
    np.testing.assert_allclose(bias, [0.5 / 1.0, 0.125 / 3.0])
    np.testing.assert_allclose(estimated_bias(rates=rates, level=3), [0.125, 0.125 / 3.0])
    # Levels 1 and 2 scaled to level 3 (Giles' rule): QoI 0 by 1/4 and 1/2, QoI 1 by 1/16 and 1/4.
    coarser = np.array([[4.0, 1.0], [0.2, 4.0]])
    bias = estimated_bias(rates=rates, level=3, mean_diff=np.array([-0.5, 0.01]), coarser=coarser)
    np.testing.assert_allclose(bias, [max(0.5, 4.0 / 4, 0.2 / 2) / 1.0, max(0.125, 1.0 / 16, 4.0 / 4) / 3.0])
    # A level not sampled (NaN) adds nothing; a single coarser row is level L - 1.
    bias = estimated_bias(rates=rates, level=3, coarser=np.array([[np.nan, np.nan], [1.5, 0.0]]))
    np.testing.assert_allclose(bias, [0.75, 0.125 / 3.0])


@pytest.mark.parametrize("level", ["2", 2.0, 2.5, -1, True, None, [1, 2]])
def test_rate_models_refuse_a_level_that_is_not_an_integer_from_0_by_name(level):
    # "2" and None gave bare TypeErrors; 2.5, -1, True (level 1) and [1, 2] (a value per entry) a model value.
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0)
    for model in (rates.bias_model, rates.variance_model, rates.cost_model):
        with pytest.raises(InvalidParameterError, match=r"^level: got .*; allowed: an integer >= 0$"):
            model(level)
    with pytest.raises(InvalidParameterError, match="^level: "):
        estimated_bias(rates=rates, level=level)


def test_rate_models_take_python_and_numpy_integer_levels():
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=2.0, c_beta=3.0, c_gamma=4.0)
    for level in (3, np.int64(3)):
        np.testing.assert_allclose(rates.bias_model(level), [0.25])
        np.testing.assert_allclose(rates.variance_model(level), [3.0 / 64])
        assert rates.cost_model(level) == 32.0
    assert rates.cost_model(0) == 4.0


def test_the_classic_cluster_counts_bias_is_not_underestimated_where_its_differences_change_sign():
    # The reference hierarchy of the classic cluster study (mean count, docs/classic): level
    # means 61.2, 13.2, -0.67 on 384^2 ... 1536^2, then -1.26 and -0.46 on 3072^2 and 6144^2.
    data = json.loads((Path(__file__).resolve().parents[1] / "docs/classic/hierarchy_clusters.json").read_text())
    levels = [data["levels"][str(level)] for level in range(7)]
    y = [np.array(row["fine"])[:, 2] - np.array(row["coarse"])[:, 2] for row in levels]
    table = level_statistics(
        fine=[np.array(row["fine"])[:, 2] for row in levels[:5]],
        coarse=[np.array(row["coarse"])[:, 2] for row in levels[:5]],
        cost=[np.array(row["seconds"]) for row in levels[:5]],
    )
    rates = fit_rates(table)
    # E[Q_1536] - E[Q_6144], measured on finer grids than the fit saw (the bias beyond is larger still).
    measured = -(y[5].mean() + y[6].mean())
    error = math.hypot(y[5].std(ddof=1) / math.sqrt(len(y[5])), y[6].std(ddof=1) / math.sqrt(len(y[6])))
    bias = estimated_bias(rates=rates, level=4, mean_diff=table.mean_diff[4], coarser=table.mean_diff[2:4])[0]
    assert bias >= measured - 2 * error
    # The model and the finest mean alone (the earlier rule) fall short by more than the noise.
    assert estimated_bias(rates=rates, level=4, mean_diff=table.mean_diff[4])[0] < measured - 3 * error


def test_plan_on_a_pre_asymptotic_hierarchy_picks_fewer_levels_with_too_much_bias():
    problem = Synthetic(seed=24, **PRE_ASYMPTOTIC)
    table = level_statistics(**sample_levels(problem, range(5), 50))
    old_alpha, old_c = plain_alpha_fit(table)
    old_rates = dataclasses.replace(fit_rates(table), alpha=np.array([old_alpha]), c_alpha=np.array([old_c]))
    rates = fit_rates(table)
    eps_grid = np.geomspace(0.5, 0.02, 12)
    old_misses = new_misses = 0
    for eps in eps_grid:
        limit = math.sqrt(0.5) * eps
        old = plan(tol=eps, rates=old_rates, statistics=table, bias_from="model", max_level=10)
        new = plan(tol=eps, rates=rates, statistics=table, max_level=10)
        assert new.finest_level >= old.finest_level
        # The default plan's bias on a screened level is the estimated_bias of its screened means.
        finest = new.finest_level
        if finest <= 4:
            coarser = table.mean_diff[max(finest - 2, 1) : finest]
            expected = estimated_bias(rates=rates, level=finest, mean_diff=table.mean_diff[finest], coarser=coarser)
            np.testing.assert_allclose(new.bias, expected)
        old_misses += problem.mean() - problem.mean(old.finest_level) > limit
        new_misses += problem.mean() - problem.mean(new.finest_level) > limit
    assert new_misses < old_misses


def test_a_level_below_screened_ones_is_not_planned_more_accurate_than_they_measure():
    # The screening of the quickstart on 32^2-128^2: E[Y_1] = -0.30, E[Y_2] = +0.12 (standard error 0.04), alpha a
    # line through the two (1.33). Level 1's own rate gave it a bias of 0.198 where level 2 had 0.372: plain MC
    # claimed on 64^2 a tolerance that MLMC refused on 256^2.
    rng = np.random.default_rng(39)
    fine, coarse, cost, q = [], [], [], 20.0
    for level, mean in enumerate([0.0, -0.30, 0.12]):
        below = q + rng.normal(0.0, 1.0, 20)
        q += mean
        fine.append(below + mean + rng.normal(0.0, 0.17, 20))
        coarse.append(below if level else np.zeros(20))
        cost.append(np.full(20, 4.0**level))
    table = level_statistics(fine=fine, coarse=coarse, cost=cost)
    rates = fit_rates(table)
    assert rates.levels_alpha == ((1, 2),) and rates.alpha[0] > 1.0
    biases = [plan(tol=1.0, rates=rates, statistics=table, finest_level=level).bias[0] for level in range(3)]
    for level in (0, 1):
        # E[Q] - E[Q_level] = E[Q] - E[Q_2] + sum of the measured E[Y_l] above it: at least what the finer level
        # has left, up to the differences the screening measured between them.
        assert biases[level] >= abs(table.mean_diff[level + 1 :, 0].sum()) + biases[2] - 1e-12
    assert biases[1] > biases[2]


# --------------------------------------------------------------------------
# plan
# --------------------------------------------------------------------------


def test_plan_reproduces_closed_form_with_exact_values():
    problem = Synthetic(alpha=1.0, beta=2.0, gamma=1.0, a=1.0, v1=1.0)
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0)
    eps, theta = 0.01, 0.3
    # Remaining bias 2^-L / (2 - 1) <= sqrt(theta) eps.
    finest = math.ceil(-math.log2(math.sqrt(theta) * eps))
    variances = np.array([problem.var_diff(level) for level in range(finest + 1)])
    costs = np.array([problem.cost(level) for level in range(finest + 1)])
    result = plan(tol=eps, rates=rates, variances=variances, costs=costs, theta=theta)
    assert result.finest_level == finest
    assert result.is_bias_met and not np.any(result.is_extrapolated)
    total = np.sum(np.sqrt(variances * costs))
    expected = [math.ceil(math.sqrt(v / c) * total / ((1 - theta) * eps**2)) for v, c in zip(variances, costs)]
    assert result.n_samples.tolist() == expected
    assert result.cost == pytest.approx(float(np.dot(expected, costs)))
    assert result.bias[0] == pytest.approx(2.0**-finest)
    assert result.stat_variance[0] <= (1 - theta) * eps**2
    # Without explicit values the rate models give the same numbers (V_0 = c_beta = 1 = s0^2).
    assert plan(tol=eps, rates=rates, theta=theta).n_samples.tolist() == expected
    # Plain MC on L: Var(Q_L) ~ V_0 = 1 without screening; fine-solve cost 2^L / (1 + 1/2).
    assert result.mc_n_samples == math.ceil(1.0 / ((1 - theta) * eps**2))
    assert result.mc_cost == pytest.approx(result.mc_n_samples * 2.0**finest / 1.5)


def test_plan_uses_screened_levels_and_extrapolates_beyond():
    problem = Synthetic(seed=3)
    table = level_statistics(**sample_levels(problem, range(4), 2000))
    rates = fit_rates(table)
    result = plan(tol=0.002, rates=rates, statistics=table)
    assert result.finest_level > 3
    assert result.is_extrapolated.tolist() == [False] * 4 + [True] * (result.finest_level - 3)
    np.testing.assert_allclose(result.variances[:4, 0], table.var_diff[:, 0])
    np.testing.assert_allclose(result.variances[5, 0], rates.variance_model(5)[0])
    np.testing.assert_allclose(result.costs[5], rates.cost_model(5))
    # Var(Q_L) for the MC prediction comes from the finest screened level.
    assert result.mc_n_samples == math.ceil(table.var_fine[3, 0] / (0.5 * 0.002**2))
    # bias_from="data" uses the screened mean on screened levels.
    coarse_plan = plan(tol=0.2, rates=rates, statistics=table, bias_from="data", finest_level=2)
    np.testing.assert_allclose(coarse_plan.bias, remaining_bias(table.mean_diff[2], rates.alpha))


def test_plan_reports_a_capped_finest_level():
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0)
    result = plan(tol=1e-4, rates=rates, max_level=5)
    assert result.finest_level == 5 and not result.is_bias_met
    with pytest.raises(EstimationError, match="does not decay"):
        plan(tol=0.1, rates=Rates(alpha=0.0, beta=1.0, gamma=1.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0))
    with pytest.raises(InvalidParameterError):
        plan(tol=-1.0, rates=rates)
    with pytest.raises(InvalidParameterError):
        plan(tol=0.1, rates=rates, theta=1.0)


def test_plan_takes_the_worst_qoi():
    rates = Rates(alpha=[1.0, 2.0], beta=[2.0, 2.0], gamma=1.0, c_alpha=[1.0, 1.0], c_beta=[1.0, 4.0], c_gamma=1.0)
    both = plan(tol=[0.01, 0.01], rates=rates)
    first = plan(tol=0.01, rates=Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0))
    # QoI 0 decides the finest level (slower bias decay), QoI 1 the sample numbers (4x variance).
    assert both.finest_level == first.finest_level
    assert np.all(both.n_samples >= first.n_samples)
    assert np.all(both.stat_variance <= 0.5 * 0.01**2)


@pytest.mark.parametrize(
    ("alpha", "beta", "gamma"),
    [(1.0, 2.0, 1.0), (2.0, 2.0, 1.0), (1.0, 1.0, 2.0), (1.0, 1.0, 1.0)],
)
def test_predicted_costs_follow_the_complexity_theorem(alpha, beta, gamma):
    rates = Rates(alpha=alpha, beta=beta, gamma=gamma, c_alpha=1.0, c_beta=1.0, c_gamma=1.0)
    eps = np.logspace(-2, -5, 13)
    plans = [plan(tol=e, rates=rates, variances=[1.0], costs=[1.0]) for e in eps]
    log_eps = np.log(eps)
    mlmc_cost = np.log([p.cost for p in plans])
    mc_cost = np.log([p.mc_cost for p in plans])
    # MC: eps^(-2 - gamma/alpha) (integer finest levels make the curve a staircase; over three
    # decades its slope is within 0.15 of the exponent).
    assert np.polyfit(log_eps, mc_cost, 1)[0] == pytest.approx(-2 - gamma / alpha, abs=0.15)
    if beta == gamma:
        # eps^-2 log(eps)^2: dividing it out leaves a flat curve.
        flat = mlmc_cost + 2 * log_eps - 2 * np.log(-log_eps)
        assert np.polyfit(log_eps, flat, 1)[0] == pytest.approx(0.0, abs=0.15)
    else:
        exponent = -2 - max(gamma - beta, 0.0) / alpha
        assert np.polyfit(log_eps, mlmc_cost, 1)[0] == pytest.approx(exponent, abs=0.15)
    ratio = np.array([p.work_ratio for p in plans])
    assert ratio[-1] > max(ratio[0], 1.0)  # MLMC's advantage grows as eps shrinks


# --------------------------------------------------------------------------
# Diagnostics and robustness
# --------------------------------------------------------------------------


def test_independent_coarse_samples_are_flagged():
    problem = Synthetic(seed=4, coupled=False)
    table = level_statistics(**sample_levels(problem, range(4), 400))
    # Independent coarse values: V_l ~ Var(Q_l) + Var(Q_l-1) ~ 2 Var(Q_l).
    assert not np.any(table.is_coupled[1:])
    assert np.all(table.coupling_ratio[1:, 0] > 1.5)
    assert any("weakly coupled" in message for message in diagnose(table))


def test_the_coupling_warning_names_the_qoi_and_does_not_claim_a_defect():
    # Reported as "... for QoI [4] (ratio 1.07); the coarse sample is not coupled to the fine one": a ratio
    # a little above 1 on a coarse grid can be the noise of a weakly coupled QoI, and [4] named nothing.
    rng = np.random.default_rng(5)
    fine = rng.normal(size=(20, 3))
    coarse = fine + [0.01, 0.01, 1.5] * rng.normal(size=(20, 3))  # the third column: barely coupled
    table = level_statistics(fine=[rng.normal(size=(20, 3)), fine], coarse=[np.zeros((20, 3)), coarse],
                             cost=[np.ones(20)] * 2)
    assert table.coupling_ratio[1, 2] >= 1.0 and np.all(table.coupling_ratio[1, :2] < 1.0)
    (named,) = diagnose(table, names=("contact_area", "clusters", "area_above"))
    ratio = f"{table.coupling_ratio[1, 2]:.3g}"
    assert named.startswith(f"level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for area_above (ratio {ratio}): ")
    assert "weakly coupled" in named and "noise" in named and "not coupled" not in named
    assert "QoI [" not in named and "contact_area" not in named
    (indexed,) = diagnose(table)
    assert "for QoI [2] (ratio" in indexed and "weakly coupled" in indexed
    for names in (("contact_area", "clusters"), "abc", ("a", "b", 3)):
        with pytest.raises(InvalidParameterError, match="names"):
            diagnose(table, names=names)


def test_coarse_from_the_wrong_distribution_fails_the_consistency_check():
    # A sampler whose coarse value is the fine value of level l (wrong grid) and thus
    # does not have the distribution of Q_{l-1}: E[coarse_l] != E[fine_{l-1}].
    problem = Synthetic(seed=6)

    def broken(level, indices):
        fine, coarse, cost = problem(level, indices)
        if level >= 1:
            coarse = problem(level, indices + 10**6)[0]
        return fine, coarse, cost

    table = level_statistics(**sample_levels(broken, range(4), 4000))
    assert not np.all(table.is_consistent[1:])
    assert np.max(table.consistency[1:]) > 1
    assert any("consistency check failed" in message for message in diagnose(table))
    good = level_statistics(**sample_levels(problem, range(4), 4000))
    assert np.all(good.is_consistent)


def _false_alarms(n: int, seeds: range) -> int:
    """Tables of a consistent hierarchy (``n`` samples on each of 4 levels) whose consistency check fails."""
    alarms = 0
    for seed in seeds:
        table = level_statistics(**sample_levels(Synthetic(seed=seed), range(4), n))
        alarms += int(np.any(table.consistency > 1.0))
    return alarms


def test_few_samples_per_level_give_no_false_consistency_alarms():
    # Estimation runs at loose tolerances have two samples on most levels. With the
    # bound built from standard deviations of two samples a consistent hierarchy failed
    # the check in about 3 % of the level pairs (so in about 10 % of these tables).
    assert CONSISTENCY_CHECK_SAMPLES == 5
    for n in range(2, CONSISTENCY_CHECK_SAMPLES):
        assert _false_alarms(n, range(300)) == 0, n


def test_the_consistency_check_counts_from_the_documented_number_of_samples():
    # A coarse value shifted by five standard deviations of the fine one: fails the
    # check from CONSISTENCY_CHECK_SAMPLES samples on, is not checked below them.
    def shifted(level, indices):
        fine, coarse, cost = Synthetic(seed=4)(level, indices)
        return fine, coarse + (5.0 if level >= 1 else 0.0), cost

    for n in (CONSISTENCY_CHECK_SAMPLES - 1, CONSISTENCY_CHECK_SAMPLES):
        table = level_statistics(**sample_levels(shifted, range(3), n))
        checked = n >= CONSISTENCY_CHECK_SAMPLES
        assert np.all(table.consistency[1:] > 1.0) == checked, n
        assert any("consistency check failed" in message for message in diagnose(table)) == checked, n
    # A gap with no spread at all is broken coupling whatever the sample count.
    fine = [np.full(2, 1.0), np.full(2, 1.5)]
    coarse = [np.zeros(2), np.full(2, 1.2)]
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.ones(2)] * 2)
    assert table.consistency[1, 0] == np.inf


def test_degenerate_levels_give_finite_statistics():
    # Level 0 random; level 1 a deterministic shift (zero variance of Y); level 2 deterministic
    # (all samples identical); level 3 deterministic with a coarse value that is not level 2's.
    rng = np.random.default_rng(7)
    q0 = rng.normal(size=30)
    fine = [q0, q0 + 1.0, np.full(30, 1.5), np.full(30, 2.0)]
    coarse = [np.zeros(30), q0, np.full(30, 1.0), np.full(30, 1.7)]
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.ones(30)] * 4)
    for name in ("var_diff", "kurtosis", "coupling_ratio", "var_delta", "var_delta_se"):
        assert np.all(np.isfinite(getattr(table, name))), name
    assert not np.any(np.isnan(table.consistency))
    # Rounding noise of fine - coarse (q0 + 1 - q0) counts as zero variance.
    assert table.var_diff[1:, 0].tolist() == [0.0, 0.0, 0.0]
    assert table.kurtosis[1:, 0].tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(table.mean_diff[1:, 0], [1.0, 0.5, 0.3], rtol=1e-14)
    # Level 3's coarse value (1.7) is not level 2's fine one (1.5), with no variance to
    # hide behind: an infinite consistency ratio, not a NaN.
    assert table.consistency[3, 0] == np.inf


def test_single_sample_levels_warn_and_stay_finite():
    with pytest.warns(EstimationWarning, match="single sample"):
        table = level_statistics(fine=[[1.0], [2.0]], coarse=[[0.0], [1.5]], cost=[[1.0], [2.0]])
    assert np.all(table.var_diff == 0) and np.all(table.consistency == 0)
    assert any("variance unknown" in message for message in diagnose(table))


def test_integer_valued_heavy_tailed_levels_are_flagged():
    # Counts whose level difference is nonzero for about 1 sample in 1000.
    rng = np.random.default_rng(8)
    fine1 = rng.poisson(20.0, size=5000).astype(float)
    coarse1 = fine1 - (rng.uniform(size=5000) < 1e-3)
    table = level_statistics(
        fine=[rng.poisson(20.0, size=5000), fine1],
        coarse=[np.zeros(5000), coarse1],
        cost=[np.ones(5000)] * 2,
    )
    assert table.kurtosis[1, 0] > 100
    assert np.all(np.isfinite(table.var_delta_se))
    assert any("kurtosis" in message for message in diagnose(table))


def test_invalid_input_is_refused():
    with pytest.raises(EstimationError, match="level 0 must be zero"):
        level_statistics(fine=[[1.0, 2.0]], coarse=[[1.0, 1.0]], cost=[[1.0, 1.0]])
    with pytest.raises(EstimationError, match="do not match"):
        level_statistics(fine=[[1.0, 2.0]], coarse=[[0.0, 0.0]], cost=[[1.0]])
    with pytest.raises(EstimationError, match=r"non-finite values \(the first: nan in sample 1, QoI 0\)"):
        level_statistics(fine=[[1.0, np.nan]], coarse=[[0.0, 0.0]], cost=[[1.0, 1.0]])
    with pytest.raises(EstimationError, match=r"coarse of level 1 contains .* \(the first: -inf in sample 0, QoI 1\)"):
        level_statistics(fine=[np.zeros((2, 2)), np.zeros((2, 2))], coarse=[np.zeros((2, 2)), [[0, -np.inf], [0, 0]]],
                         cost=[[1.0, 1.0], [1.0, 1.0]])
    with pytest.raises(EstimationError, match="no samples"):
        level_statistics(fine=[[]], coarse=[[]], cost=[[]])
    with pytest.raises(EstimationError, match="non-negative, got -1.0 for sample 1"):
        level_statistics(fine=[[1.0, 2.0]], coarse=[[0.0, 0.0]], cost=[[1.0, -1.0]])
    with pytest.raises(EstimationError, match="non-negative, got nan for sample 0"):
        level_statistics(fine=[[1.0, 2.0]], coarse=[[0.0, 0.0]], cost=[[np.nan, 1.0]])


# --------------------------------------------------------------------------
# Coarsest useful level
# --------------------------------------------------------------------------


def test_a_level_without_variance_reduction_drops_the_levels_below():
    loose = Synthetic(seed=5, gamma=2.0, loose_levels=(1,))  # Var(Y_1) = Var(Q_0) + Var(Q_1)
    statistics = level_statistics(**sample_levels(loose, range(4), 200))
    choice = choose_coarsest_level(statistics)
    assert choice.level == 1 and [d.level for d in choice.dropped] == [0]
    assert "Var(Y_1)" in choice.dropped[0].reason and "is not below Var(Q_1)" in choice.dropped[0].reason
    assert choice.cost_factor < 1.0 - DROP_MARGIN
    coupled = level_statistics(**sample_levels(Synthetic(seed=5, gamma=2.0), range(4), 200))
    assert choose_coarsest_level(coupled).level == 0 and choose_coarsest_level(coupled).dropped == ()


def test_plan_starts_on_the_chosen_level_and_costs_less():
    loose = Synthetic(seed=6, gamma=2.0, loose_levels=(1,))
    statistics = level_statistics(**sample_levels(loose, range(4), 200))
    rates = fit_rates(statistics)
    full = plan(tol=0.02, rates=rates, statistics=statistics)
    chosen = plan(tol=0.02, rates=rates, statistics=statistics, coarsest_level=None)
    assert full.coarsest_level == 0 and full.dropped_levels == ()
    assert chosen.coarsest_level == 1 and [d.level for d in chosen.dropped_levels] == [0]
    assert chosen.n_samples[0] == 0 and np.all(chosen.n_samples[1:] >= 1)
    np.testing.assert_array_equal(chosen.variances[1], statistics.var_fine[1])  # the base level is Q_1 itself
    assert chosen.finest_level == full.finest_level
    assert np.all(chosen.stat_variance <= 0.5 * 0.02**2 * (1 + 1e-12))
    assert chosen.cost < (1.0 - DROP_MARGIN) * full.cost
    with pytest.raises(InvalidParameterError):
        plan(tol=0.02, rates=rates, statistics=statistics, coarsest_level=9)

"""The cost of levels finer than the screened ones: ``Rates.gamma_beyond`` and the contact problem's rate."""

from __future__ import annotations

import math

import numpy as np
import pytest

import rough_uq
from rough_uq.errors import InvalidParameterError
from rough_uq.multilevel.drivers import PlanUpdated, iter_mlmc, planning_rates
from rough_uq.multilevel.rates import Rates
from rough_uq.multilevel.statistics import level_statistics
from rough_uq.problem.runs import contact_planning_rates
from rough_uq.problem.sampler import ITERATION_RATE_FLOOR, cost_rate_beyond, modelled_cost


def _rates(**overrides: object) -> Rates:
    options = dict(alpha=1.0, beta=2.0, gamma=1.5, c_alpha=1.0, c_beta=1.0, c_gamma=2.0, levels_gamma=(1, 2))
    return Rates(**(options | overrides))


def test_the_cost_model_goes_on_from_the_finest_fitted_level_at_the_larger_of_both_rates():
    rates = _rates(gamma_beyond=2.25)
    assert rates.cost_model(1) == 2.0 * 2**1.5 and rates.cost_model(2) == 2.0 * 2**3.0
    assert rates.cost_model(4) == pytest.approx(2.0 * 2 ** (3.0 + 2.25 * 2))
    # A rate below the fitted one does not lower the model; without one (or without fitted levels) it is the fit.
    assert _rates(gamma_beyond=1.0).cost_model(4) == pytest.approx(2.0 * 2**6.0)
    assert _rates().cost_model(4) == pytest.approx(2.0 * 2**6.0)
    assert _rates(gamma_beyond=2.25, levels_gamma=()).cost_model(4) == pytest.approx(2.0 * 2**6.0)
    assert rates.gamma_extrapolated == 2.25 and _rates(gamma_beyond=1.0).gamma_extrapolated == 1.5
    assert _rates().gamma_extrapolated == 1.5


@pytest.mark.parametrize("value", [math.nan, math.inf, -0.5, "2", True, [2.0]])
def test_a_cost_rate_beyond_that_is_no_finite_number_from_0_is_refused_by_name(value):
    with pytest.raises(InvalidParameterError, match=r"^Rates.gamma_beyond: got .*; allowed: None or a finite"):
        _rates(gamma_beyond=value)
    with pytest.raises(InvalidParameterError, match=r"^gamma_beyond: got .*; allowed: None or a finite"):
        iter_mlmc(lambda *args: None, tol=1.0, gamma_beyond=value)


def test_planning_rates_carry_the_rate_beyond():
    rng = np.random.default_rng(3)
    levels = [0, 1, 2]
    fine = [rng.normal(1.0, 0.5 * 2.0**-lv, size=(20, 1)) for lv in levels]
    coarse = [np.zeros((20, 1))] + [f + rng.normal(0.1 * 2.0**-lv, 0.01, size=(20, 1)) for f, lv in
                                    zip(fine[1:], levels[1:])]
    statistics = level_statistics(fine=fine, coarse=coarse, cost=[np.full(20, 2.0**lv) for lv in levels])
    assert planning_rates(statistics).gamma_beyond is None
    rates = planning_rates(statistics, gamma_beyond=2.5)
    assert rates.gamma_beyond == 2.5 and rates.cost_model(4) == pytest.approx(rates.cost_model(2) * 2**5)


def _model(coarsest: int = 32):
    spectrum = rough_uq.SurfaceSpectrum(system_size=1, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1)
    return rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=coarsest,
                                   seed=1).model


@pytest.mark.parametrize("coarsest", [16, 32, 128])
@pytest.mark.parametrize("iteration_rate", [0.3, 0.6, 0.9])
def test_the_contact_rate_beyond_predicts_the_modelled_cost_of_iterations_growing_at_a_steady_rate(
    coarsest, iteration_rate
):
    # Modelled costs of coupled samples whose solves take 10 * 2^(r l) iterations (the extra ones included): the
    # cost on max_level is the finest screened one times 2^(rate * levels beyond), whatever the fixed costs.
    model = _model(coarsest)

    def cost(level: int) -> float:
        iterations = 10.0 * 2 ** (iteration_rate * level) - 2
        return float(modelled_cost(model, level, np.array([[iterations] * 2]))[0])

    levels = np.arange(3)
    for max_level in (3, 5, 7):
        rate = cost_rate_beyond(model, levels, np.array([cost(lv) for lv in levels]), max_level)
        assert cost(2) * 2 ** (rate * (max_level - 2)) == pytest.approx(cost(max_level), rel=1e-12)


@pytest.mark.parametrize(("iteration_rate", "counted"), [(0.0, ITERATION_RATE_FLOOR), (-0.4, ITERATION_RATE_FLOOR),
                                                          (1.7, 1.0)])
def test_the_iterations_count_at_least_the_floor_and_at_most_doubling_per_level(iteration_rate, counted):
    model = _model()

    def steady(r: float, level: int) -> float:
        return float(modelled_cost(model, level, np.array([[10.0 * 2 ** (r * level) - 2] * 2]))[0])

    levels = np.arange(3)
    rate = cost_rate_beyond(model, levels, np.array([steady(iteration_rate, lv) for lv in levels]), 5)
    expected = cost_rate_beyond(model, levels, np.array([steady(0.5, lv) for lv in levels]), 5) - 0.5 + counted
    assert rate == pytest.approx(expected, rel=1e-12)


def test_no_rate_beyond_where_nothing_lies_beyond_or_too_few_levels_have_a_cost():
    model = _model()
    levels, costs = np.arange(3), np.array([1e-3, 4e-3, 1.2e-2])
    assert cost_rate_beyond(model, levels, costs, 2) is None
    assert cost_rate_beyond(model, levels, np.array([1e-3, 0.0, 1.2e-2]), 4) is None
    assert cost_rate_beyond(model, levels[:2], costs[:2], 4) is None
    assert cost_rate_beyond(model, levels, costs, 4) > 2.0


def test_the_planned_cost_of_levels_beyond_the_screening_is_that_of_their_samples():
    # The quickstart's surface screened on 32^2..128^2: gamma 1.5 there (the fixed cost of an iteration still
    # weighs), so that the fitted model put a coupled sample of 512^2 at 2.5 times below its cost (0.096 against
    # 0.236 ref-s, 2026-11-29) and a forecast of MLMC beyond the screened levels 4-8 times too low.
    spectrum = rough_uq.SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32,
                                      max_level=4, seed=1)
    screening = rough_uq.screen(problem, levels=3, samples=6)
    rates = contact_planning_rates(problem.model, screening.statistics, problem.max_level)
    assert rates.gamma_beyond > screening.rates.gamma + 0.4
    sampler = problem.sampler(1)
    for level in (3, 4):
        _, _, cost = sampler(level, np.arange(3))
        assert 0.7 < rates.cost_model(level) / np.mean(cost) < 1.5, (level, rates.cost_model(level), cost)


def test_a_run_plans_the_level_it_adds_beyond_its_samples_at_the_rate_beyond():
    # The screening (a hierarchy with a bias 200 times smaller) plans levels 0..3; the run finds its bias larger
    # and adds levels 4 and 5, whose cost its replan extrapolates from level 3: at the fitted gamma (1) before, now
    # at the larger gamma_beyond, which draws fewer samples on the new level and more on the cheaper ones.
    from mlmc_problems import Synthetic, sample_levels

    screening = level_statistics(**sample_levels(Synthetic(a=0.01, seed=2), [0, 1, 2], 40))
    added = {}
    for gamma_beyond in (None, 4.0):
        events = iter_mlmc(Synthetic(a=2.0, seed=1), tol=0.2, screening=screening, max_level=8, coarsest_level=None,
                           gamma_beyond=gamma_beyond)
        added[gamma_beyond] = next(e for e in events if isinstance(e, PlanUpdated) and e.reason == "new level")
    assert added[None].levels.tolist() == added[4.0].levels.tolist() == [0, 1, 2, 3, 4]
    assert added[4.0].n_planned[4] < added[None].n_planned[4]
    assert np.all(added[4.0].n_planned[1:4] >= added[None].n_planned[1:4])


def test_plain_mc_beyond_the_screening_is_priced_at_the_rate_there():
    # mc --tol priced its fine solves at the share 1 / (1 + 2^-gamma) of the screening's gamma (1.54: 0.74) where
    # the cost model beyond runs at gamma_beyond; mc --level took the whole coupled sample. The same MC run was
    # forecast at 7.2 and 9.68 ref-s.
    from rough_uq.multilevel.allocation import fine_cost_share, plan

    rates = _rates(gamma_beyond=2.5)
    assert rates.cost_rate_at(2) == 1.5 and rates.cost_rate_at(3) == 2.5 and _rates().cost_rate_at(3) == 1.5
    rng = np.random.default_rng(5)
    fine = [rng.normal(1.0, 1.0, size=(20, 1))] + [rng.normal(0.0, 1.0, size=(20, 1)) for _ in range(2)]
    coarse = [np.zeros((20, 1))] + [f - rng.normal(0.3 * 4.0**-lv, 0.05, size=(20, 1)) for lv, f in
                                    zip((1, 2), fine[1:])]
    statistics = level_statistics(fine=fine, coarse=coarse, cost=[np.full(20, 2.0 ** (1.5 * lv)) for lv in range(3)])
    planned = planning_rates(statistics, gamma_beyond=2.5)
    prediction = plan(tol=np.array([0.01]), rates=planned, statistics=statistics, max_level=6, coarsest_level=None)
    level = prediction.finest_level
    assert level > 2
    share = fine_cost_share(2.5, level)
    assert prediction.mc_cost == pytest.approx(prediction.mc_n_samples * planned.cost_model(level) * share)


def test_a_floored_cost_rate_goes_on_from_the_fit_at_its_finest_level():
    # Costs that fall with the level (0.01, 0.005, 0.002): gamma is floored at 0.5, but its constant was the
    # fitted line's, which priced level 3 at 59 times level 2's measured cost.
    rng = np.random.default_rng(2)
    fine = [rng.normal(1.0, 1.0, size=(20, 1)) for _ in range(3)]
    coarse = [np.zeros((20, 1))] + [f - rng.normal(0.1, 0.05, size=(20, 1)) for f in fine[1:]]
    statistics = level_statistics(fine=fine, coarse=coarse, cost=[np.full(20, c) for c in (0.01, 0.005, 0.002)])
    rates = planning_rates(statistics)
    assert rates.gamma == 0.5 and rates.levels_gamma == (1, 2)
    assert rates.cost_model(2) == pytest.approx(0.002) and rates.cost_model(3) == pytest.approx(0.002 * 2**0.5)

"""allocation.plan names the QoIs in its Richardson note, as the drivers' messages do."""

from __future__ import annotations

import numpy as np
import pytest

from rough_uq.errors import InvalidParameterError
from rough_uq.multilevel.allocation import plan
from rough_uq.multilevel.rates import fit_rates
from rough_uq.multilevel.statistics import level_statistics

N_SAMPLES = 50


def _screening(level_means: np.ndarray):
    """Statistics of levels 0..3 whose ``E[Y_l]`` are ``level_means[l - 1]`` (shape (3, n_qoi)) to 1e-4."""
    rng = np.random.default_rng(7)
    n_qoi = level_means.shape[1]
    fine, coarse = [], []
    q0 = 1.0 + 0.1 * rng.standard_normal((N_SAMPLES, n_qoi))
    fine.append(q0)
    coarse.append(np.zeros_like(q0))
    for mean in level_means:
        below = 1.0 + 0.1 * rng.standard_normal((N_SAMPLES, n_qoi))
        difference = mean + 1e-4 * rng.standard_normal((N_SAMPLES, n_qoi))
        fine.append(below + difference)
        coarse.append(below)
    cost = [np.full(N_SAMPLES, 2.0**level) for level in range(4)]
    return level_statistics(fine=fine, coarse=coarse, cost=cost)


def _richardson_note(level_means, **options):
    statistics = _screening(np.asarray(level_means, dtype=float))
    planned = plan(tol=1e-3, rates=fit_rates(statistics), statistics=statistics, richardson=True, **options)
    return planned.richardson_note


# The second QoI's means stop decaying between levels 2 and 3: the extrapolation is refused for it.
NOT_DECAYING = [[0.5, 0.5], [0.25, 0.25], [0.125, 0.3]]


def test_richardson_note_names_the_qoi_that_refused_it():
    indexed = _richardson_note(NOT_DECAYING)
    assert indexed.startswith("Richardson extrapolation refused: the level means do not decay") and "(QoI 1)" in indexed
    named = _richardson_note(NOT_DECAYING, qoi_names=("contact_area", "clusters"))
    assert named == indexed.replace("(QoI 1)", "(clusters)")
    assert "QoI" not in named


@pytest.mark.parametrize("bad", [("contact_area",), "contact_area", [1, 2]])
def test_plan_refuses_qoi_names_that_do_not_match_the_columns(bad):
    with pytest.raises(InvalidParameterError, match="^qoi_names"):
        _richardson_note(NOT_DECAYING, qoi_names=bad)


def test_the_starting_plan_of_a_run_and_its_forecast_name_the_qoi_too():
    # The forecast said "(QoI 0)" where the run's own warning named contact_area@0.05: the run's starting plan
    # (from which forecasts are made) did not pass the names on to plan.
    from rough_uq.multilevel.drivers import planning_rates, starting_plan

    statistics = _screening(np.asarray(NOT_DECAYING, dtype=float))
    options = dict(tol=np.array([1e-3, 1e-3]), rates=planning_rates(statistics), statistics=statistics, theta=0.5,
                   max_level=6, richardson=True)
    named = starting_plan(**options, qoi_names=("contact_area", "clusters")).richardson_note
    assert "(clusters)" in named and "QoI" not in named
    assert "(QoI 1)" in starting_plan(**options).richardson_note

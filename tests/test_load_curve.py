"""Load curves: warm-started sequences of solves equal independent solves; curve configs, problems and reports."""

from __future__ import annotations

import numpy as np
import pytest

from rough_uq.errors import InvalidParameterError
from rough_uq.physics.load_curve import solve_load_curve
from rough_uq.physics.solver import solve_contact
from rough_uq.physics.surface import SurfaceSpectrum, sample_surface

#: Both the sequence and the cold solves go to this tolerance, so that their
#: difference measures the solutions, not the stopping test.
TOL = 1e-10


def random_surface(seed: int, grids=(32, 64, 128)):
    """``(heights, system_size, rms_slope, description)`` of a seeded random surface."""
    rng = np.random.default_rng([18, seed])
    n = int(rng.choice(grids))
    size = float(10 ** rng.uniform(-1, 1))
    k_s = int(rng.integers(2, n // 2 + 1))
    k_r = int(rng.integers(1, k_s + 1))
    k_l = int(rng.integers(0, k_r + 1))
    spectrum = SurfaceSpectrum(
        system_size=size, k_l=k_l, k_r=k_r, k_s=k_s, hurst=float(rng.uniform(0, 1)),
        rms_height=float(10 ** rng.uniform(-2, 2)),
    )
    return sample_surface(spectrum, n, rng), size, spectrum.rms_slope, f"seed {seed}: {n}^2, {spectrum}", rng


def assert_same_solution(solution, cold, description):
    assert solution.converged and cold.converged, f"{description}: {solution.message} / {cold.message}"
    difference = np.linalg.norm(solution.pressure - cold.pressure) / np.linalg.norm(cold.pressure)
    assert difference < 1e-6, f"{description}: pressure differs from the cold solve by {difference:.2e}"
    n_differ = int(np.count_nonzero(solution.contact != cold.contact))
    assert n_differ == 0, f"{description}: {n_differ} nodes differ in the contact set"


@pytest.mark.parametrize("block", range(2))
def test_each_point_equals_an_independent_cold_solve(block):
    # Relative loads from 1e-3 (a few nodes) to 3 (full contact on most spectra), drawn unsorted.
    fractions = []
    for seed in range(6 * block, 6 * (block + 1)):
        heights, size, slope, description, rng = random_surface(seed)
        relative = 10 ** rng.uniform(-3, np.log10(3), size=int(rng.integers(2, 6)))
        loads = relative * slope
        curve = solve_load_curve(heights, system_size=size, mean_pressures=loads, tol=TOL)
        assert curve.n_loads == loads.size and np.array_equal(curve.mean_pressures, loads)
        for load, solution in zip(loads, curve.solutions):
            cold = solve_contact(heights, system_size=size, mean_pressure=load, tol=TOL)
            assert_same_solution(solution, cold, f"{description}, load {load:.3g}")
            assert solution.pressure.mean() == pytest.approx(load, rel=1e-12)
            fractions.append(solution.contact.mean())
    # The draws span nearly empty to (nearly) full contact sets.
    assert min(fractions) < 0.02 and max(fractions) > 0.9


def test_unsorted_loads_come_back_in_the_callers_order_and_warm_starts_save_iterations():
    heights, size, slope, description, _ = random_surface(100, grids=(128,))
    loads = np.array([0.2, 0.01, 0.05, 0.1, 0.02]) * slope
    curve = solve_load_curve(heights, system_size=size, mean_pressures=loads, tol=TOL)
    areas = np.array([s.contact.mean() for s in curve.solutions])
    order = np.argsort(loads)
    assert np.all(np.diff(areas[order]) > 0), f"{description}: area not increasing with the load"
    cold_iter = [solve_contact(heights, system_size=size, mean_pressure=p, tol=TOL).n_iter for p in loads]
    # The smallest load starts cold in both; every other one starts from a neighbour.
    assert curve.n_iter[order[0]] == cold_iter[order[0]]
    assert curve.total_iter < sum(cold_iter), f"{description}: {curve.n_iter} vs cold {cold_iter}"


def test_duplicate_loads_share_one_solve():
    heights, size, slope, _, _ = random_surface(101, grids=(64,))
    loads = [0.1 * slope, 0.05 * slope, 0.1 * slope]
    curve = solve_load_curve(heights, system_size=size, mean_pressures=loads, tol=TOL)
    assert curve.solutions[0] is curve.solutions[2]
    assert curve.n_iter[0] > 0 and curve.n_iter[2] == 0
    assert np.array_equal(curve.converged, [True, True, True])


@pytest.mark.parametrize("seed", range(3))
def test_a_single_load_is_solve_contact(seed):
    heights, size, slope, _, rng = random_surface(200 + seed)
    load = float(10 ** rng.uniform(-2, 0)) * slope
    guess = np.abs(heights) + 0.0  # any non-negative field is a valid warm start
    for initial in (None, guess):
        curve = solve_load_curve(heights, system_size=size, mean_pressures=[load], initial_pressure=initial)
        single = solve_contact(heights, system_size=size, mean_pressure=load, initial_pressure=initial)
        assert np.array_equal(curve.solutions[0].pressure, single.pressure)
        assert curve.n_iter[0] == single.n_iter and curve.is_converged == single.converged


def test_a_solve_that_stops_early_is_flagged_and_continued_with_retry_iter():
    heights, size, slope, _, _ = random_surface(300, grids=(64,))
    loads = [0.05 * slope, 0.2 * slope]
    short = solve_load_curve(heights, system_size=size, mean_pressures=loads, tol=TOL, max_iter=2)
    assert not short.converged.any() and not short.is_converged
    assert np.array_equal(short.n_iter, [2, 2])
    retried = solve_load_curve(heights, system_size=size, mean_pressures=loads, tol=TOL, max_iter=2, retry_iter=500)
    assert retried.is_converged and np.all(retried.n_iter > 2)


@pytest.mark.parametrize("bad", [[], [0.1, 0.0], [0.1, -1.0], [0.1, float("nan")], "0.1", [True], None])
def test_bad_mean_pressures_name_the_field(bad):
    heights, size, _, _, _ = random_surface(0, grids=(32,))
    with pytest.raises(InvalidParameterError, match="mean_pressures"):
        solve_load_curve(heights, system_size=size, mean_pressures=bad)


def test_bad_retry_iter_names_the_field():
    heights, size, _, _, _ = random_surface(0, grids=(32,))
    with pytest.raises(InvalidParameterError, match="retry_iter"):
        solve_load_curve(heights, system_size=size, mean_pressures=[0.1], retry_iter=-1)

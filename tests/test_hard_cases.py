"""Numerical hard cases of the core library: extreme loads, spectra, scales, grids and samples.

Every case asks the same of the code: a converged answer that is right, or a
clear report (``converged=False``, an :class:`InvalidParameterError` naming the
argument, an :class:`EstimationError` or an :class:`EstimationWarning`), never
a NaN, an infinity or a stray ``RuntimeWarning`` (warnings are errors here).
Grids are small (4 to 64 nodes per side) so that the whole file runs in seconds.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections import deque

import numpy as np
import pytest

from rough_uq.errors import EstimationError, InvalidParameterError
from rough_uq.multilevel.drivers import EstimationWarning, mc, mlmc
from rough_uq.physics.qoi import contact_area, count_clusters, evaluate_qoi, label_clusters
from rough_uq.physics.reference import full_contact_pressure, westergaard_full_contact_pressure
from rough_uq.multilevel.allocation import optimal_samples, plan
from rough_uq.multilevel.rates import Rates, fit_rates, remaining_bias
from rough_uq.multilevel.statistics import diagnose, level_statistics
from rough_uq.physics.solver import resample_pressure, solve_contact
from rough_uq.physics.surface import SurfaceSpectrum, project_surface, sample_coupled, sample_surface

L = 1.0
N = 64
#: Band 1..16 periods per box: resolved by every grid from 34 nodes on.
SPECTRUM = SurfaceSpectrum(system_size=L, k_l=1, k_r=2, k_s=16, hurst=0.8, rms_height=1.0)


def surface(seed: int = 0, n: int = N, spectrum: SurfaceSpectrum = SPECTRUM) -> np.ndarray:
    return sample_surface(spectrum, n, np.random.default_rng(seed))


def assert_valid_solution(sol, heights: np.ndarray, load: float, *, tol: float = 1e-8) -> None:
    """Finite fields, the load carried exactly, p >= 0, and the returned fields meet ``tol``.

    The convergence measure of :mod:`rough_uq.physics.solver` is recomputed from the
    returned pressure and gap (complementarity plus interpenetration, relative
    to ``load * s_rms``), in units of ``load`` and ``s_rms`` so that products
    of tiny or huge numbers neither underflow nor overflow.
    """
    assert sol.converged, sol.message
    assert sol.error < tol
    for field in (sol.pressure, sol.displacement, sol.gap):
        assert np.all(np.isfinite(field))
    assert math.isfinite(sol.approach)
    assert sol.pressure.mean() == pytest.approx(load, rel=1e-12)
    assert sol.pressure.min() >= 0.0
    peak = float(np.max(np.abs(heights)))
    # RMS about the mean without squaring heights of 1e+-300 (np.std would over/underflow).
    scale = peak * float(np.std(heights / peak)) if peak > 0 else 1.0
    pressure, gap = sol.pressure / load, sol.gap / scale
    measure = (np.sum(pressure * np.abs(gap)) + np.sum(np.maximum(-gap[~sol.contact], 0.0))) / gap.size
    assert measure < tol * (1 + 1e-9)
    np.testing.assert_allclose(gap, (sol.displacement - heights + sol.approach) / scale, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------
# Loads: from one node to beyond full contact, and zero
# --------------------------------------------------------------------------


def full_contact_threshold(heights: np.ndarray, e_star: float = 1.0) -> float:
    """Smallest mean pressure at which every node is in contact.

    The full-contact pressure is ``load + (a field independent of the load)``,
    so the threshold is where its minimum reaches zero.
    """
    return 1.0 - float(full_contact_pressure(heights, system_size=L, mean_pressure=1.0, e_star=e_star).min())


@pytest.mark.parametrize("relative_load", [1e-300, 1e-100, 1e-12, 1e-6])
def test_vanishing_load_rests_on_the_highest_node(relative_load):
    s = surface(seed=1)
    load = relative_load * SPECTRUM.rms_slope
    sol = solve_contact(s, system_size=L, mean_pressure=load)
    assert_valid_solution(sol, s, load)
    top = np.unravel_index(np.argmax(s), s.shape)
    assert sol.contact.sum() == 1 and sol.contact[top]
    # The single node carries the whole force.
    assert sol.pressure[top] == pytest.approx(N * N * load, rel=1e-12)
    assert count_clusters(sol.contact) == 1
    assert contact_area(sol.pressure, estimator="nodes") == 1.0 / (N * N)


def _spike_problem(seed: int) -> tuple[np.ndarray, list[tuple[int, int]], float]:
    """A tall spike (or two) on a flat surface or 1e4 above white noise, at a dimensionless load 0.1-0.8."""
    rng = np.random.default_rng([34, seed])
    n = int(rng.choice([32, 64, 128, 256]))
    kind = ("spike", "two_spikes", "spike_on_noise")[seed % 3]
    s = rng.standard_normal((n, n)) if kind == "spike_on_noise" else np.zeros((n, n))
    tops = [tuple(int(i) for i in rng.integers(0, n, 2))]
    if kind == "two_spikes":
        tops.append(((tops[0][0] + n // 2) % n, (tops[0][1] + n // 3) % n))
    for top in tops:
        s[top] = 1e4 if kind == "spike_on_noise" else 1.0
    return s, tops, float(rng.uniform(0.1, 0.8)) * float(np.std(s)) / L  # p L / (E* s_rms) in [0.1, 0.8]


@pytest.mark.parametrize("precondition", [True, False])
@pytest.mark.parametrize("seed", range(15))
def test_a_tall_spike_converges_at_the_loads_just_before_the_rest_touches(seed, precondition):
    # At these loads the preconditioned iteration cycled between contact sets of thousands of nodes, and so did
    # plain Polonsky-Keer, from its start or handed the stalled pressure (error 7-33 after 10 000 iterations;
    # the answer is the load on the spikes): the factor that restores the mean pressure after each step took
    # most of the spike's increase back. The hand-over now starts plain afresh, and plain shifts after a stall.
    s, tops, load = _spike_problem(seed)
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-9, max_iter=1000, precondition=precondition)
    assert_valid_solution(sol, s, load, tol=1e-9)
    assert all(sol.contact[top] for top in tops)


@pytest.fixture
def estimated_plans():
    """FFTW_ESTIMATE plans, as a fresh process has them: a test before may have left measured plans (the
    pipeline's), whose rounding moves where an iteration at the rounding floor stalls."""
    from rough_uq.physics import fft

    previous = fft._PLANNER.wisdom
    fft.use_wisdom(None)
    yield
    fft.use_wisdom(previous)


@pytest.mark.parametrize(("seed", "n"), [(1, 64), (3, 128)])
def test_a_solve_stalled_at_the_rounding_floor_keeps_its_answer_through_the_hand_over(seed, n, estimated_plans):
    # tol 1e-17 is below what rounding allows: the preconditioned iteration stalls at an error of 1e-15. Handed
    # over to a plain start from uniform pressure, the same 100 iterations ended at an error of 6.5e-6 or 4e-4.
    # With the pipeline's measured plans the same surfaces went on halving their error past 100 iterations (no
    # stall to test): the test failed after tests/test_pipeline.py in one process.
    s = sample_surface(SPECTRUM, n, np.random.default_rng(seed))
    sol = solve_contact(s, system_size=L, mean_pressure=0.05 * SPECTRUM.rms_slope, tol=1e-17, max_iter=100)
    assert sol.path == "preconditioned+plain" and not sol.converged
    assert sol.error < 1e-13


@pytest.mark.parametrize(("n", "relative_load"), [(8, 1.0), (32, 1.0), (64, 2.0), (128, 1.0)])
def test_plain_polonsky_keer_converges_on_a_spike_in_a_sea_of_contact(n, relative_load):
    # Plain Polonsky-Keer never converged here (error about 5 after 10 000 iterations), or on 8^2 stopped at
    # once with "no descent" and all the load on the spike while other nodes interpenetrated.
    s = np.zeros((n, n))
    s[n // 3, n // 5] = 1.0
    load = relative_load * float(np.std(s)) / L
    plain = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10, precondition=False, max_iter=2000)
    assert_valid_solution(plain, s, load, tol=1e-10)
    preconditioned = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
    np.testing.assert_array_equal(plain.contact, preconditioned.contact)
    difference = np.linalg.norm(plain.pressure - preconditioned.pressure) / np.linalg.norm(plain.pressure)
    assert difference < 1e-6


@pytest.mark.parametrize("seed", range(20))
def test_the_shift_to_the_force_is_the_projection_on_pressures_of_that_force(seed):
    from rough_uq.physics.solver import _shift_to_force

    rng = np.random.default_rng([35, seed])
    x = rng.exponential(size=(16, 16)) * (rng.random((16, 16)) < 0.7) * 10.0 ** rng.uniform(-200, 200)
    force = float(x.sum()) * rng.uniform(1e-6, 0.999)
    p = x.copy()
    assert _shift_to_force(p, force) == pytest.approx(force, rel=1e-12)
    # max(x - lam, 0) with one lam >= 0: every pressure kept drops by the same amount.
    kept = p > 0
    assert p.min() >= 0.0 and kept.any()
    shifts = (x - p)[kept]
    np.testing.assert_allclose(shifts, shifts[0], rtol=1e-9, atol=1e-12 * float(x.max()))
    assert np.all(x[~kept] <= shifts[0] * (1 + 1e-9))
    tiny = np.array([1e20, 1.0])  # a force below the rounding of the largest pressure
    assert _shift_to_force(tiny, 1.0) == 1.0 and tiny.tolist() == [1.0, 0.0]


def test_the_shift_to_the_force_makes_no_grid_sized_temporaries():
    """Sorting the pressures peaked at 3.6 MB here (230 MB at 4096^2) in every plain step after a stall."""
    import tracemalloc

    from rough_uq.physics.solver import _shift_to_force

    rng = np.random.default_rng(36)
    p = rng.exponential(size=(512, 512)) * (rng.random((512, 512)) < 0.5)
    force = 0.3 * float(p.sum())
    _shift_to_force(p.copy(), force)  # compiled before measuring
    tracemalloc.start()
    try:
        _shift_to_force(p, force)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 1024, peak  # the grid is 2 MiB
    assert float(p.sum()) == pytest.approx(force, rel=1e-12)


@pytest.mark.parametrize("seed", range(10))
def test_the_shift_to_the_force_finishes_by_sorting_after_its_rounds(seed, monkeypatch):
    import rough_uq.physics.solver as solver

    rng = np.random.default_rng([37, seed])
    x = rng.pareto(1.5, size=(32, 32)) * (rng.random((32, 32)) < 0.6)
    force = float(x.sum()) * rng.uniform(1e-4, 0.99)
    michelot = x.copy()
    solver._shift_to_force(michelot, force)
    sorted_shift = solver._sorted_shift
    # The solver's pressure is the FFT plan's padded buffer, a strided view: the passes write into it.
    padded = np.zeros((32, 34))
    strided = padded[:, :32]
    strided[...] = x
    solver._shift_to_force(strided, force)
    np.testing.assert_allclose(strided, michelot, rtol=0, atol=1e-12 * float(x.max()))  # sums in another order
    assert not padded[:, 32:].any()
    monkeypatch.setattr(solver, "_MAX_SHIFT_ROUNDS", 1)
    sorts = []
    monkeypatch.setattr(solver, "_sorted_shift", lambda *args: sorts.append(1) or sorted_shift(*args))
    sorted_ = x.copy()
    assert solver._shift_to_force(sorted_, force) == pytest.approx(force, rel=1e-12)
    assert sorts == [1]  # one round was not enough: the sort finished it
    np.testing.assert_allclose(sorted_, michelot, rtol=0, atol=1e-12 * float(x.max()))
    np.testing.assert_array_equal(sorted_ > 0, michelot > 0)
    tiny = np.array([1e20, 1.0])  # a force below the rounding of the largest pressure
    assert solver._shift_to_force(tiny, 1.0) == 1.0 and tiny.tolist() == [1.0, 0.0]


@pytest.mark.parametrize("relative_load", [0.00537, 0.008])
def test_plain_polonsky_keer_converges_on_integer_terraces(relative_load):
    # Many tied heights on 7 levels: plain Polonsky-Keer ended at error 0.076 after 10 000 iterations.
    n = 128
    x = np.arange(n) / n
    s = np.floor(7 * (np.cos(2 * np.pi * x)[:, None] + np.cos(2 * np.pi * x)[None, :] + 2) / 4)
    load = relative_load * float(np.std(s)) / L
    plain = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10, precondition=False, max_iter=2000)
    assert_valid_solution(plain, s, load, tol=1e-10)
    preconditioned = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
    np.testing.assert_array_equal(plain.contact, preconditioned.contact)


def test_contact_grows_monotonically_from_a_handful_of_nodes_to_full_contact():
    # Frictionless contact on a half-space: the contact set grows with the load
    # (Barber 2003), here from a handful of nodes to every node.
    s = surface(seed=0)
    loads = SPECTRUM.rms_slope * np.geomspace(3e-4, 3.0, 9)
    previous = np.zeros(s.shape, dtype=bool)
    counts = []
    for load in loads:
        sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
        assert_valid_solution(sol, s, load, tol=1e-10)
        assert not np.any(previous & ~sol.contact), "a node left the contact as the load grew"
        previous = sol.contact
        counts.append(int(sol.contact.sum()))
    assert 2 <= counts[0] <= 20  # a handful of nodes
    assert counts[-1] == N * N
    assert counts == sorted(counts)


@pytest.mark.parametrize("factor", [1.5, 1e4])
def test_beyond_full_contact_is_the_analytic_full_contact_solution(factor):
    s = surface(seed=2)
    threshold = full_contact_threshold(s)
    load = factor * threshold
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
    assert_valid_solution(sol, s, load, tol=1e-10)
    assert sol.contact.all()
    exact = full_contact_pressure(s, system_size=L, mean_pressure=load)
    np.testing.assert_allclose(sol.pressure, exact, rtol=0, atol=1e-8 * threshold)
    np.testing.assert_array_equal(evaluate_qoi(["contact_area", "clusters"], pressure=sol.pressure), [1.0, 1.0])
    assert count_clusters(sol.contact, connectivity=8) == 1


def test_just_below_the_full_contact_load_some_node_is_free():
    s = surface(seed=2)
    load = 0.9 * full_contact_threshold(s)
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
    assert_valid_solution(sol, s, load, tol=1e-10)
    assert 0 < np.count_nonzero(~sol.contact) < N * N // 10


def test_far_beyond_full_contact_reports_non_convergence_not_nan():
    # At 1e12 times the full-contact load, rounding of p = load + O(1) keeps the error
    # far above tol: the solver must say so, and keep its fields finite.
    s = surface(seed=2)
    load = 1e12 * full_contact_threshold(s)
    sol = solve_contact(s, system_size=L, mean_pressure=load, max_iter=200)
    assert not sol.converged
    assert sol.n_iter == 200 and "max_iter" in sol.message
    assert math.isfinite(sol.error) and sol.error > 1e-8
    for field in (sol.pressure, sol.displacement, sol.gap):
        assert np.all(np.isfinite(field))
    assert sol.pressure.mean() == pytest.approx(load, rel=1e-12)


@pytest.mark.parametrize("zero", [0, 0.0, -0.0, np.float64(0.0)])
def test_zero_load_is_rejected_naming_mean_pressure(zero):
    with pytest.raises(InvalidParameterError) as info:
        solve_contact(surface(), system_size=L, mean_pressure=zero)
    assert info.value.name == "mean_pressure"
    # The choice is documented where users look for it.
    assert "Zero" in solve_contact.__doc__ and "load itself is rejected" in solve_contact.__doc__


@pytest.mark.parametrize(
    ("load", "e_star"),
    [
        (5e-324, 1.0),  # used to raise ZeroDivisionError
        (1e-310, 1.0),  # subnormal dimensionless load: precision lost, slow arithmetic
        (1e305, 1.0),  # 4096 * 1e305 overflows the total force
        (1e120, 1.0),  # 1e120 E* s_rms / L: used to iterate 10_000 times to an error of 0.84
        (1.0, 1e-300),  # the same from a modulus of 1e-300
    ],
)
def test_loads_outside_the_range_of_the_dimensionless_load_are_rejected(load, e_star):
    with pytest.raises(InvalidParameterError) as info:
        solve_contact(surface(), system_size=L, mean_pressure=load, e_star=e_star)
    assert info.value.name == "mean_pressure"


# --------------------------------------------------------------------------
# Spectra: Hurst exponents at the ends, one ring, very wide, unresolved bands
# --------------------------------------------------------------------------


def spectrum_with(**changes) -> SurfaceSpectrum:
    parameters = {"system_size": L, "k_l": 2, "k_r": 4, "k_s": 24, "hurst": 0.8, "rms_height": 1.0}
    parameters.update(changes)
    return SurfaceSpectrum(**parameters)


@pytest.mark.parametrize(("hurst", "neighbour"), [(0.0, 1e-6), (1.0, 1.0 - 1e-6)])
def test_hurst_exponents_at_and_next_to_the_ends(hurst, neighbour):
    at_end = spectrum_with(hurst=hurst)
    near_end = spectrum_with(hurst=neighbour)
    for spectrum in (at_end, near_end):
        assert 0 < spectrum.C < math.inf and 0 < spectrum.m2 < math.inf
    # Phi depends smoothly on H: a change of 1e-6 moves C and m2 by O(1e-6 log(k_s/k_r)).
    assert near_end.C == pytest.approx(at_end.C, rel=1e-5)
    assert near_end.m2 == pytest.approx(at_end.m2, rel=1e-5)
    s_end = surface(seed=3, spectrum=at_end)
    s_near = surface(seed=3, spectrum=near_end)
    assert np.all(np.isfinite(s_end))
    np.testing.assert_allclose(s_near, s_end, rtol=0, atol=1e-5)
    load = 0.1 * at_end.rms_slope
    sol = solve_contact(s_end, system_size=L, mean_pressure=load)
    assert_valid_solution(sol, s_end, load)
    assert 0.0 < contact_area(sol.pressure) < 1.0


@pytest.mark.parametrize("hurst", [-1e-12, 1.0 + 1e-12, math.nan])
def test_hurst_outside_the_unit_interval_is_rejected(hurst):
    with pytest.raises(InvalidParameterError) as info:
        spectrum_with(hurst=hurst)
    assert info.value.name == "hurst"


@pytest.mark.parametrize(("radius", "n_modes"), [(5.0, 12), (math.sqrt(50.0), 12), (1.0, 4)])
def test_a_single_ring_of_modes(radius, n_modes):
    # k_l = k_r = k_s: only the integer wave vectors with |k| = radius (5: (3, 4)-type
    # and (5, 0)-type; sqrt(50): (5, 5) and (1, 7)-type), all with the same PSD value.
    spectrum = SurfaceSpectrum(system_size=L, k_l=radius, k_r=radius, k_s=radius, hurst=0.8, rms_height=1.0)
    assert spectrum.n_modes == n_modes
    assert spectrum.C == pytest.approx(1.0 / n_modes, rel=1e-14)
    assert spectrum.m2 == pytest.approx((2 * math.pi * radius / L) ** 2, rel=1e-12)
    n = 32
    s = surface(seed=4, n=n, spectrum=spectrum)
    amplitudes = np.abs(np.fft.fft2(s))
    k = np.fft.fftfreq(n, 1.0 / n)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    on_ring = np.isclose(k2, radius**2)
    assert amplitudes[~on_ring].max() <= 1e-12 * amplitudes.max()
    assert np.count_nonzero(amplitudes[on_ring] > 1e-12 * amplitudes.max()) == n_modes
    load = 0.1 * spectrum.rms_slope
    sol = solve_contact(s, system_size=L, mean_pressure=load)
    assert_valid_solution(sol, s, load)


@pytest.mark.parametrize("radius", [1.5, 3.5])
def test_a_ring_without_integer_wave_vectors_is_rejected(radius):
    with pytest.raises(InvalidParameterError) as info:
        SurfaceSpectrum(system_size=L, k_l=radius, k_r=radius, k_s=radius, hurst=0.8, rms_height=1.0)
    assert info.value.name == "k_l, k_s"


def test_a_very_wide_spectrum_on_a_small_grid_is_its_truncation():
    # k_s / k_l = 1000 on grids of 8..64 nodes: the grids see only the longest waves.
    wide = SurfaceSpectrum(system_size=L, k_l=1, k_r=1, k_s=1000, hurst=0.8, rms_height=1.0)
    assert wide.n_modes > 3_000_000
    fine = surface(seed=5, n=64, spectrum=wide)
    for n in (8, 16, 32, 64):
        assert not wide.resolves(n)
        assert 0 < wide.grid_variance(n) < wide.rms_height**2
        s = surface(seed=5, n=n, spectrum=wide)
        assert np.all(np.isfinite(s))
        # The draws of a coarse grid are the first draws of a finer one.
        np.testing.assert_allclose(s, project_surface(fine, n), rtol=0, atol=1e-12)
        # Heights have the PSD's partial variance only; the load stays the one of the full band.
        load = 0.1 * wide.rms_slope
        sol = solve_contact(s, system_size=L, mean_pressure=load)
        assert_valid_solution(sol, s, load)


@pytest.mark.parametrize("n", [8, 16, 32])
def test_short_wavelength_below_the_grid_spacing_is_truncated(n):
    # The classic band (k_s = 128) on grids that are 4 to 16 times too coarse.
    classic = SurfaceSpectrum(system_size=2.0, k_l=2, k_r=2, k_s=128, hurst=0.8, rms_height=1.0)
    assert not classic.resolves(n) and classic.resolves(258)
    direct = surface(seed=6, n=n, spectrum=classic)
    finer = surface(seed=6, n=4 * n, spectrum=classic)
    np.testing.assert_allclose(direct, project_surface(finer, n), rtol=0, atol=1e-12)
    _, coarse = sample_coupled(classic, 2 * n, np.random.default_rng(6))
    np.testing.assert_allclose(coarse, direct, rtol=0, atol=1e-12)
    assert "truncation" in sample_surface.__doc__


def test_a_grid_that_represents_none_of_the_band_gives_a_flat_surface():
    # k_l = 2 on a 4 x 4 grid (|k0|, |k1| <= 1), and a ring on the Nyquist wave number of 8.
    classic = SurfaceSpectrum(system_size=2.0, k_l=2, k_r=2, k_s=128, hurst=0.8, rms_height=1.0)
    nyquist_ring = SurfaceSpectrum(system_size=L, k_l=4, k_r=4, k_s=4, hurst=0.8, rms_height=1.0)
    for spectrum, n in ((classic, 4), (nyquist_ring, 8)):
        assert spectrum.grid_variance(n) == 0.0
        s = surface(seed=7, n=n, spectrum=spectrum)
        np.testing.assert_array_equal(s, np.zeros((n, n)))
        sol = solve_contact(s, system_size=spectrum.system_size, mean_pressure=0.3)
        assert sol.converged and sol.n_iter == 0 and sol.contact.all()
        np.testing.assert_allclose(sol.pressure, 0.3, rtol=1e-15)
    assert nyquist_ring.resolves(10) and nyquist_ring.grid_variance(10) == pytest.approx(1.0, rel=1e-14)
    _, coarse = sample_coupled(classic, 8, np.random.default_rng(7))
    np.testing.assert_array_equal(coarse, np.zeros((4, 4)))


# --------------------------------------------------------------------------
# Scales: heights and loads together, E* far from 1, extreme spectra
# --------------------------------------------------------------------------


@pytest.mark.parametrize("factor", [1e-300, 1e-150, 1e-9, 1e9, 1e150, 1e300])
def test_heights_and_load_scaled_together_give_the_scaled_solution(factor):
    # Heights of 1e-300 used to be treated as flat (their squares underflow): full
    # contact, "converged" at iteration 0.
    s = surface(seed=8)
    load = 0.1 * SPECTRUM.rms_slope
    reference = solve_contact(s, system_size=L, mean_pressure=load)
    scaled = solve_contact(factor * s, system_size=L, mean_pressure=factor * load)
    assert_valid_solution(scaled, factor * s, factor * load)
    np.testing.assert_array_equal(scaled.contact, reference.contact)
    # To about 1e-10 of the largest pressure, not to rounding: the preconditioned iteration's
    # single-precision displacement increments round differently in the two problems (solver
    # docstring, "Scaled units"; measured here: at most 1.3e-11 of the largest pressure and 6e-12
    # RMS heights in the gap).
    peak = reference.pressure.max()
    np.testing.assert_allclose(scaled.pressure / factor, reference.pressure, rtol=0, atol=1e-10 * peak)
    np.testing.assert_allclose(scaled.gap / factor, reference.gap, rtol=0, atol=1e-10)
    assert scaled.approach / factor == pytest.approx(reference.approach, rel=1e-10)


@pytest.mark.parametrize("factor", [1e-200, 1e-9, 1e9, 1e200])
def test_scaling_every_length_leaves_the_pressure_unchanged(factor):
    # Box, heights (and so displacements and gaps) times c, the same pressure. Boxes of
    # 1e-200 used to end in "converged" interpenetration or a ZeroDivisionError (no node
    # left in contact), boxes of 1e200 in an overflow.
    s = surface(seed=8)
    load = 0.1 * SPECTRUM.rms_slope
    reference = solve_contact(s, system_size=L, mean_pressure=load)
    scaled = solve_contact(factor * s, system_size=factor * L, mean_pressure=load)
    assert_valid_solution(scaled, factor * s, load)
    np.testing.assert_array_equal(scaled.contact, reference.contact)
    # To about 1e-10 of the largest pressure (see the test above; measured: at most 1.3e-11 of it).
    peak = reference.pressure.max()
    np.testing.assert_allclose(scaled.pressure, reference.pressure, rtol=0, atol=1e-10 * peak)
    np.testing.assert_allclose(scaled.displacement / factor, reference.displacement, rtol=0, atol=1e-10)


@pytest.mark.parametrize("rms_height", [1e-9, 1e9])
def test_spectrum_scaled_heights_give_scaled_samples_and_loads(rms_height):
    # The study's view of the same invariance: RMS height and paper-style load.
    scaled_spectrum = SurfaceSpectrum(system_size=L, k_l=1, k_r=2, k_s=16, hurst=0.8, rms_height=rms_height)
    s = surface(seed=9)
    s_scaled = surface(seed=9, spectrum=scaled_spectrum)
    np.testing.assert_allclose(s_scaled, rms_height * s, rtol=1e-13, atol=1e-14 * rms_height)
    assert scaled_spectrum.rms_slope == pytest.approx(rms_height * SPECTRUM.rms_slope, rel=1e-14)
    reference = solve_contact(s, system_size=L, mean_pressure=0.1 * SPECTRUM.rms_slope)
    scaled = solve_contact(s_scaled, system_size=L, mean_pressure=0.1 * scaled_spectrum.rms_slope)
    np.testing.assert_array_equal(scaled.contact, reference.contact)


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        ({"rms_height": 1e-300}, "rms_height"),  # C underflowed to 0: a flat surface, zero load
        ({"rms_height": 1e300}, "rms_height"),  # OverflowError from rms_height ** 2
        ({"system_size": 1e-300}, "rms_height, system_size"),  # OverflowError in (2 pi / L) ** 2
        ({"system_size": 1e300}, "rms_height, system_size"),  # m2 underflowed to 0
    ],
)
def test_spectra_outside_the_float_range_are_rejected(changes, name):
    with pytest.raises(InvalidParameterError) as info:
        spectrum_with(**changes)
    assert info.value.name == name


@pytest.mark.parametrize("e_star", [1e-6, 1e9])
def test_modulus_far_from_one(e_star):
    s = surface(seed=10)
    load = 0.1 * SPECTRUM.rms_slope
    reference = solve_contact(s, system_size=L, mean_pressure=load)
    # Pressure in the unit of E*: the same dimensionless load gives the same contact.
    scaled = solve_contact(s, system_size=L, mean_pressure=load * e_star, e_star=e_star)
    assert_valid_solution(scaled, s, load * e_star)
    np.testing.assert_array_equal(scaled.contact, reference.contact)
    np.testing.assert_allclose(scaled.pressure / e_star, reference.pressure, rtol=1e-10, atol=1e-12 * load)
    np.testing.assert_allclose(scaled.gap, reference.gap, rtol=0, atol=1e-12)
    # The same load on a soft solid is beyond full contact, on a stiff one it rests on one node.
    fixed = solve_contact(s, system_size=L, mean_pressure=load, e_star=e_star)
    assert_valid_solution(fixed, s, load)
    if e_star < 1:
        assert load > full_contact_threshold(s, e_star) and fixed.contact.all()
    else:
        assert fixed.contact.sum() == 1 and fixed.contact.flat[np.argmax(s)]


# --------------------------------------------------------------------------
# Grids: 4 x 4 upward; odd and non-square inputs
# --------------------------------------------------------------------------


@pytest.mark.parametrize("n", [4, 6, 8, 16])
def test_small_grids_solve_the_sinusoid_exactly_in_full_contact(n):
    amplitude = 0.01
    x = np.arange(n) * L / n
    s = np.tile((amplitude * np.cos(2 * np.pi * x / L))[:, None], (1, n))
    p_star = westergaard_full_contact_pressure(amplitude=amplitude, wavelength=L)
    # One mode is represented exactly by any grid from 3 nodes on: so is its contact.
    sol = solve_contact(s, system_size=L, mean_pressure=1.5 * p_star, tol=1e-12)
    assert_valid_solution(sol, s, 1.5 * p_star, tol=1e-12)
    assert sol.contact.all()
    np.testing.assert_allclose(sol.pressure[:, 0], 1.5 * p_star + p_star * np.cos(2 * np.pi * x / L), rtol=1e-10)
    partial = solve_contact(s, system_size=L, mean_pressure=0.3 * p_star, tol=1e-12)
    assert_valid_solution(partial, s, 0.3 * p_star, tol=1e-12)
    assert 0 < partial.contact.sum() < n * n


@pytest.mark.parametrize("n", [4, 6, 8, 16])
def test_small_grids_solve_random_surfaces(n):
    small = SurfaceSpectrum(system_size=L, k_l=1, k_r=1, k_s=3, hurst=0.8, rms_height=1.0)
    s = surface(seed=11, n=n, spectrum=small)
    assert np.std(s) > 0
    for relative_load in (1e-3, 0.1, 1.0, 100.0):
        load = relative_load * small.rms_slope
        sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
        assert_valid_solution(sol, s, load, tol=1e-10)
    assert sol.contact.all()  # the largest load


@pytest.mark.parametrize("shape", [(7, 7), (5, 5), (3, 3), (1, 1), (0, 0), (8, 6), (6, 8), (8,), (2, 8, 8)])
def test_solver_rejects_odd_and_non_square_heights_naming_them(shape):
    with pytest.raises(InvalidParameterError) as info:
        solve_contact(np.zeros(shape), system_size=L, mean_pressure=0.1)
    assert info.value.name == "heights"


@pytest.mark.parametrize("n", [7, 5, 3, 1, 0, -4, 6.0, True])
def test_sampling_rejects_odd_grid_sizes_naming_n(n):
    with pytest.raises(InvalidParameterError) as info:
        sample_surface(SPECTRUM, n, np.random.default_rng(0))
    assert info.value.name == "n"
    with pytest.raises(InvalidParameterError) as info:
        SPECTRUM.grid_psd(n)
    assert info.value.name == "n"


@pytest.mark.parametrize("n", [6, 10, 2])
def test_coupled_sampling_needs_an_even_coarse_grid(n):
    with pytest.raises(InvalidParameterError) as info:
        sample_coupled(SPECTRUM, n, np.random.default_rng(0))
    assert info.value.name == "n"


def test_projections_reject_odd_and_non_square_inputs_naming_them():
    cases = [
        (lambda: project_surface(np.zeros((8, 6)), 4), "fine"),
        (lambda: project_surface(np.zeros((7, 7)), 7), "fine.shape[0]"),
        (lambda: project_surface(np.zeros((8, 8)), 3), "n_coarse"),
        (lambda: project_surface(np.zeros((6, 6)), 4), "n_coarse"),
        (lambda: resample_pressure(np.ones((8, 6)), 8), "pressure"),
        (lambda: resample_pressure(np.ones((0, 0)), 8), "pressure"),
        (lambda: resample_pressure(np.ones((8, 8)), 6), "pressure"),
        (lambda: resample_pressure(np.ones((8, 8)), 0), "n"),  # used to raise ZeroDivisionError
        (lambda: resample_pressure(np.ones((8, 8)), 4.0), "n"),
    ]
    for call, name in cases:
        with pytest.raises(InvalidParameterError) as info:
            call()
        assert info.value.name == name


# --------------------------------------------------------------------------
# Poor warm starts
# --------------------------------------------------------------------------


def _one_node(n: int, node: tuple[int, int], value: float = 1.0) -> np.ndarray:
    guess = np.zeros((n, n))
    guess[node] = value
    return guess


WARM_STARTS = {
    "all on the lowest node": lambda s: _one_node(N, np.unravel_index(np.argmin(s), s.shape)),
    "all on the highest node": lambda s: _one_node(N, np.unravel_index(np.argmax(s), s.shape)),
    "unrelated surface": lambda s: solve_contact(surface(seed=99), system_size=L, mean_pressure=0.5).pressure,
    "4x coarser grid": lambda s: solve_contact(surface(seed=98, n=N // 4), system_size=L, mean_pressure=0.5).pressure,
    "2x finer unrelated grid": lambda s: solve_contact(
        surface(seed=97, n=2 * N), system_size=L, mean_pressure=5.0
    ).pressure,
    "one node of a 2 x 2 grid": lambda s: np.array([[0.0, 0.0], [0.0, 3.0]]),
    "near overflow": lambda s: np.full((N, N), 1e308),  # used to raise an overflow RuntimeWarning
    "subnormal": lambda s: _one_node(N, (5, 5), 5e-324),  # used to raise an overflow RuntimeWarning
}


@pytest.mark.parametrize("kind", sorted(WARM_STARTS))
def test_poor_warm_starts_converge_to_the_cold_solution(kind):
    s = surface(seed=12)
    load = 0.1 * SPECTRUM.rms_slope
    cold = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11)
    warm = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11, initial_pressure=WARM_STARTS[kind](s))
    assert_valid_solution(warm, s, load, tol=1e-11)
    np.testing.assert_array_equal(warm.contact, cold.contact)
    np.testing.assert_allclose(warm.pressure, cold.pressure, rtol=0, atol=1e-6 * load)


@pytest.mark.parametrize(
    "guess",
    [
        np.ones((6, 6)),
        np.ones((N, N // 2)),
        np.ones(N * N),
        np.float64(1.0),
        -np.ones((N, N)),
        np.zeros((2 * N, 2 * N)),
    ],
    ids=["non-nested grid", "non-square", "flat", "scalar", "negative", "all zero"],
)
def test_unusable_warm_starts_are_rejected_naming_initial_pressure(guess):
    # A scalar guess used to raise IndexError.
    with pytest.raises(InvalidParameterError) as info:
        solve_contact(surface(), system_size=L, mean_pressure=0.5, initial_pressure=guess)
    assert info.value.name == "initial_pressure"


# --------------------------------------------------------------------------
# Cluster counting on the periodic grid
# --------------------------------------------------------------------------


def flood_fill_count(contact: np.ndarray, connectivity: int) -> int:
    """Periodic connected components by breadth-first search (written independently of qoi)."""
    n0, n1 = contact.shape
    steps = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    if connectivity == 8:
        steps += [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    seen = np.zeros(contact.shape, dtype=bool)
    count = 0
    for start in zip(*np.nonzero(contact)):
        if seen[start]:
            continue
        count += 1
        seen[start] = True
        queue = deque([start])
        while queue:
            a, b = queue.popleft()
            for d0, d1 in steps:
                neighbour = ((a + d0) % n0, (b + d1) % n1)
                if contact[neighbour] and not seen[neighbour]:
                    seen[neighbour] = True
                    queue.append(neighbour)
    return count


def test_a_cross_wrapping_both_boundaries_is_one_cluster():
    n = 9
    contact = np.zeros((n, n), dtype=bool)
    contact[0, :] = contact[:, n - 1] = True
    contact[4, 2:7] = True  # separate bar, 3 rows from the cross
    for connectivity in (4, 8):
        assert count_clusters(contact, connectivity=connectivity) == 2
        labels = label_clusters(contact, connectivity=connectivity)
        assert len(np.unique(labels[0, :])) == 1 and len(np.unique(labels[:, n - 1])) == 1


@pytest.mark.parametrize("shift", [0, 3])
def test_a_diagonal_wrapping_both_boundaries(shift):
    # Nodes (i, i + shift): only corners touch, and the last one touches the first across
    # both boundaries at once; one closed cluster with diagonals, n singletons without.
    n = 8
    contact = np.zeros((n, n), dtype=bool)
    contact[np.arange(n), (np.arange(n) + shift) % n] = True
    assert count_clusters(contact, connectivity=4) == n
    assert count_clusters(contact, connectivity=8) == 1
    anti = np.fliplr(contact)
    assert count_clusters(anti, connectivity=4) == n
    assert count_clusters(anti, connectivity=8) == 1


def test_the_four_corner_nodes_are_one_cluster_on_the_torus():
    contact = np.zeros((6, 10), dtype=bool)
    contact[np.ix_([0, 5], [0, 9])] = True  # edge neighbours across both boundaries
    for connectivity in (4, 8):
        assert count_clusters(contact, connectivity=connectivity) == 1
        assert len(np.unique(label_clusters(contact, connectivity=connectivity)[contact])) == 1


@pytest.mark.parametrize("shape", [(1, 1), (1, 2), (2, 1), (1, 5), (2, 2), (2, 3), (2, 4), (3, 3)])
def test_every_map_on_tiny_grids_matches_a_flood_fill(shape):
    # On grids of 1 to 3 nodes per side the periodic neighbours coincide with each other
    # or with the node itself; every map is checked.
    size = shape[0] * shape[1]
    for bits in itertools.product((False, True), repeat=size):
        contact = np.array(bits).reshape(shape)
        for connectivity in (4, 8):
            assert count_clusters(contact, connectivity=connectivity) == flood_fill_count(contact, connectivity)


@pytest.mark.parametrize("shape", [(1, 1), (4, 4), (6, 10)])
def test_full_empty_and_single_node_maps(shape):
    full = np.ones(shape, dtype=bool)
    empty = np.zeros(shape, dtype=bool)
    single = empty.copy()
    single[-1, -1] = True
    for connectivity in (4, 8):
        assert count_clusters(full, connectivity=connectivity) == 1
        assert count_clusters(empty, connectivity=connectivity) == 0
        assert count_clusters(single, connectivity=connectivity) == 1
        np.testing.assert_array_equal(label_clusters(full, connectivity=connectivity), np.ones(shape, dtype=int))
        np.testing.assert_array_equal(label_clusters(empty, connectivity=connectivity), np.zeros(shape, dtype=int))
    assert contact_area(full.astype(float)) == 1.0 and contact_area(empty.astype(float)) == 0.0
    values = evaluate_qoi(
        ["contact_area", "clusters"], pressure=single.astype(float), connectivity=8, area_estimator="nodes"
    )
    np.testing.assert_array_equal(values, [1.0 / single.size, 1.0])


# --------------------------------------------------------------------------
# Estimators: degenerate levels, single samples, heavy-tailed integer QoIs
# --------------------------------------------------------------------------


def record_warnings(function, *args, **kwargs):
    """Call ``function``; return its result and the messages of the EstimationWarnings raised."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EstimationWarning)
        result = function(*args, **kwargs)
    # Anything else (a RuntimeWarning above all) stays an error.
    others = [w for w in caught if not issubclass(w.category, EstimationWarning)]
    assert not others, [str(w.message) for w in others]
    return result, [str(w.message) for w in caught]


def assert_finite_table(table) -> None:
    for name in (
        "mean_fine", "var_fine", "mean_coarse", "var_coarse", "mean_diff", "var_diff",
        "kurtosis", "var_delta", "var_delta_se", "mean_cost", "var_cost",
    ):  # fmt: skip
        assert np.all(np.isfinite(getattr(table, name))), name
    assert not np.any(np.isnan(table.consistency)) and not np.any(np.isnan(table.coupling_ratio))


def test_one_sample_per_level_warns_per_level_and_cannot_fit_rates():
    table, messages = record_warnings(
        level_statistics, fine=[[1.0], [2.0], [2.5]], coarse=[[0.0], [1.0], [2.0]], cost=[[1.0], [2.0], [4.0]]
    )
    assert sum("single sample" in m for m in messages) == 3
    assert_finite_table(table)
    assert np.all(table.var_diff == 0) and np.all(table.kurtosis == 0) and np.all(table.consistency == 0)
    assert sum("variance unknown" in m for m in diagnose(table)) == 3
    with pytest.raises(EstimationError, match="at least two usable levels"):
        fit_rates(table)
    # A plan from prescribed rates does not trust single-sample levels: it extrapolates.
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=0.5, c_beta=1.0, c_gamma=1.0)
    schedule = plan(tol=0.1, rates=rates, statistics=table)
    assert np.all(schedule.is_extrapolated) and np.all(schedule.n_samples >= 1)
    assert math.isfinite(schedule.cost) and math.isfinite(schedule.mc_cost)


def test_levels_with_identical_samples_give_finite_statistics():
    rng = np.random.default_rng(13)
    q0 = rng.normal(size=40)
    q1 = q0 + 0.1 * rng.normal(size=40)
    # QoI 0: level 2 has identical fine and identical coarse samples; QoI 1 never varies.
    fine = [np.c_[q0, np.full(40, 7.0)], np.c_[q1, np.full(40, 7.0)], np.c_[np.full(40, 0.75), np.full(40, 7.0)]]
    coarse = [np.zeros((40, 2)), np.c_[q0, np.full(40, 7.0)], np.c_[np.full(40, 0.5), np.full(40, 7.0)]]
    table, messages = record_warnings(level_statistics, fine=fine, coarse=coarse, cost=[np.ones(40)] * 3)
    assert messages == []
    assert_finite_table(table)
    assert table.var_fine[2].tolist() == [0.0, 0.0] and table.var_diff[2].tolist() == [0.0, 0.0]
    assert table.kurtosis[2].tolist() == [0.0, 0.0]
    assert table.mean_diff[2, 0] == 0.25 and table.mean_diff[1:, 1].tolist() == [0.0, 0.0]
    # Nothing varies on level 2: nothing to reduce, so a coupling ratio of 0, not NaN.
    assert table.coupling_ratio[2].tolist() == [0.0, 0.0]
    assert np.all(table.is_coupled)


def test_a_constant_fine_value_over_a_varying_coarse_one_is_not_coupled():
    # E.g. full contact on the fine grid in every sample, partial contact on the coarse one.
    # V_l > 0 = Var(Q_l) used to be reported as a coupling ratio of 0 (perfect coupling).
    rng = np.random.default_rng(14)
    coarse_area = 1.0 - 0.01 * (rng.random(50) < 0.3)
    table = level_statistics(
        fine=[rng.random(50), np.ones(50)], coarse=[np.zeros(50), coarse_area], cost=[np.ones(50)] * 2
    )
    assert table.var_fine[1, 0] == 0.0 and table.var_diff[1, 0] > 0.0
    assert table.coupling_ratio[1, 0] == math.inf
    assert not table.is_coupled[1, 0]
    assert any("weakly coupled" in m for m in diagnose(table))


def test_mlmc_with_deterministic_level_differences_is_exact_and_warns():
    # Q_0 random, Y_l = 2^-l in every sample: V_l = 0 for l >= 1 (zero-variance levels).
    def sampler(level, indices):
        q0 = np.array([np.random.default_rng([15, int(i)]).normal() for i in indices])
        fine = q0 + (1.0 - 2.0**-level)
        coarse = np.zeros_like(q0) if level == 0 else q0 + (1.0 - 2.0 ** -(level - 1))
        return fine, coarse, np.full(len(indices), 2.0**level)

    result, messages = record_warnings(mlmc, sampler, tol=0.05)
    finest = result.finest_level
    n0 = int(result.n_samples[0])
    q0 = sampler(0, np.arange(n0))[0]
    assert result.estimate == pytest.approx(q0.mean() + 1.0 - 2.0**-finest, rel=1e-12)
    assert result.stat_error == pytest.approx(q0.std(ddof=1) / math.sqrt(n0), rel=1e-12)
    # E[Y_l] = 2^-l exactly: alpha = 1, remaining bias 2^-L / (2 - 1).
    assert result.bias_estimate == pytest.approx(2.0**-finest, rel=1e-12)
    assert np.all(result.statistics.var_diff[1:] == 0)
    assert result.tol_met and result.stop_reason == "tol_met"
    for value in (result.estimate, result.stat_error, result.variance, result.variance_error, result.mc_cost):
        assert math.isfinite(value)
    # Rare-event levels would look just like this: the user is told.
    assert sum("same in all" in m for m in messages) == finest


def test_constant_qoi_through_plain_mc_needs_only_the_initial_samples():
    def constant(level, indices):
        return np.full(len(indices), 7.0), np.zeros(len(indices)), np.full(len(indices), 3.0)

    result, messages = record_warnings(mc, constant, tol=1e-6, level=2, n_initial=2)
    assert messages == []
    assert result.estimate == 7.0 and result.stat_error == 0.0 and result.variance == 0.0
    assert result.n_samples.tolist() == [2] and result.tol_met
    assert result.cost == 6.0 and math.isfinite(result.mc_cost)


def test_plan_with_zero_variances_and_the_zero_cost_guard():
    rates = Rates(alpha=1.0, beta=2.0, gamma=1.0, c_alpha=1.0, c_beta=0.0, c_gamma=1.0)
    schedule = plan(tol=0.1, rates=rates, variances=np.zeros(4), costs=[1.0, 2.0, 4.0, 8.0], finest_level=3)
    assert schedule.n_samples.tolist() == [1, 1, 1, 1]
    assert schedule.stat_variance.tolist() == [0.0] and schedule.cost == 15.0
    np.testing.assert_array_equal(optimal_samples(np.zeros((3, 1)), np.ones(3), np.ones(1)), np.zeros((3, 1)))
    # A zero cost used to divide by zero in sqrt(V_l / C_l).
    with pytest.raises(InvalidParameterError) as info:
        optimal_samples(np.ones((3, 1)), np.array([1.0, 0.0, 4.0]), np.ones(1))
    assert info.value.name == "costs"


def _jump_table(n: int, jumps: list[int]):
    """Two levels of an integer QoI (a cluster count) whose level difference is 1 in the samples ``jumps``."""
    base = np.arange(n) % 7 + 20.0
    jump = np.zeros(n)
    jump[jumps] = 1.0
    return level_statistics(fine=[base, base + jump], coarse=[np.zeros(n), base], cost=[np.ones(n)] * 2)


def test_bernoulli_level_difference_has_the_exact_heavy_kurtosis():
    # Integer QoI (a cluster count) whose level difference is 1 in one sample of n.
    n = 1000
    table = _jump_table(n, [123])
    p = 1.0 / n
    # Population kurtosis of a Bernoulli(p) variable.
    assert table.kurtosis[1, 0] == pytest.approx((1.0 - 3.0 * p * (1.0 - p)) / (p * (1.0 - p)), rel=1e-12)
    assert table.var_diff[1, 0] == pytest.approx(p * (1.0 - p) * n / (n - 1), rel=1e-12)
    assert_finite_table(table)
    assert any("kurtosis" in m for m in diagnose(table))


def test_a_screening_sized_level_whose_variance_rests_on_one_sample_is_flagged():
    # The sample kurtosis of n values is at most n - 2 + 1 / (n - 1) (one value apart): with the limit of 100
    # alone a default screening (20 samples per level) could never flag a level, however few samples its V_l
    # rests on. A cluster-count difference of 1 in one sample of 20 now is.
    n = 20
    table = _jump_table(n, [5])
    assert table.kurtosis[1, 0] == pytest.approx(n - 2 + 1 / (n - 1), rel=1e-12)
    (message,) = [m for m in diagnose(table, names=["clusters"]) if "kurtosis" in m]
    assert message == ("level 1: kurtosis 18.1 of Q_l - Q_l-1 for clusters exceeds 10 = 20 samples / 2: the "
                       "variance rests on 20 / 18.1 = 1.11 of them, fewer than 2; its variance estimate is unreliable")
    # On the base level the samples are Q_0 alone, as the message says (it said "of Q_l - Q_l-1" there too).
    spike = np.zeros(n)
    spike[5] = 1.0
    base = level_statistics(fine=[spike, spike], coarse=[np.zeros(n), spike], cost=[np.ones(n)] * 2)
    (message,) = [m for m in diagnose(base) if "kurtosis" in m]
    assert message.startswith("level 0: kurtosis 18.1 of Q_l for QoI [0] exceeds 10")
    # Two jumps of 20: the variance rests on about 2.5 samples, not flagged; nor one jump in 19 samples.
    assert not [m for m in diagnose(_jump_table(n, [5, 11])) if "kurtosis" in m]
    assert not [m for m in diagnose(_jump_table(19, [3])) if "kurtosis" in m]


@pytest.mark.parametrize("seed", range(20))
def test_gaussian_levels_of_screening_size_pass_the_kurtosis_check(seed):
    # Randomised: Gaussian fine values and coupled coarse ones, 20-60 samples per level, four QoIs.
    rng = np.random.default_rng([2026, 11, 27, seed])
    n = int(rng.integers(20, 61))
    coarse = [np.zeros((n, 4))] + [rng.standard_normal((n, 4)) for _ in range(3)]
    fine = [c + rng.standard_normal((n, 4)) * 2.0 ** -level for level, c in enumerate(coarse)]
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.ones(n)] * 4)
    assert not [m for m in diagnose(table) if "kurtosis" in m]


class _FixedValues:
    """A level sampler whose sample ``i`` is row ``i`` of ``values`` on every level (coarse values 0), cost 1."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = values

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fine = self.values[np.asarray(indices) % len(self.values)]
        return fine, np.zeros_like(fine), np.ones(len(fine))


def test_mc_flags_a_qoi_whose_variance_rests_on_one_of_its_samples():
    values = np.zeros((30, 2))
    values[:, 0] = np.linspace(0.0, 1.0, 30)
    values[7, 1] = 1.0  # a rare event: the only sample that differs
    problem = _FixedValues(values)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mc(problem, tol=10.0, level=0, n_initial=30, qoi_names=["smooth", "rare"])
    messages = [str(w.message) for w in caught if "kurtosis" in str(w.message)]
    assert messages == ["mc: kurtosis 28 of Q on level 0 for rare exceeds 15 = 30 samples / 2: the variance rests "
                        "on 30 / 28 = 1.07 of them, fewer than 2; the variance and error estimates are unreliable"]
    # kurtosis_limit = inf turns the check off, as documented ("never").
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mc(problem, tol=10.0, level=0, n_initial=30, qoi_names=["smooth", "rare"], kurtosis_limit=math.inf)
    assert not [w for w in caught if "kurtosis" in str(w.message)]


def test_heavy_tailed_integer_levels_fit_rates_with_finite_errors():
    # Y_l = 1 in one sample of 250 * 2^l (l = 1, 2, 3): bias and variance rates 1.
    n = 4000
    fine, coarse = [np.arange(n) % 5.0], [np.zeros(n)]
    for level in (1, 2, 3):
        jumps = (np.arange(n) % (250 * 2**level) == 0).astype(float)
        coarse.append(np.arange(n) % 5.0)
        fine.append(coarse[-1] + jumps)
    table = level_statistics(fine=fine, coarse=coarse, cost=[np.full(n, 2.0**level) for level in range(4)])
    assert np.all(table.kurtosis[1:, 0] > 100)
    rates = fit_rates(table)
    for value in (rates.alpha[0], rates.beta[0], rates.alpha_se[0], rates.beta_se[0], rates.gamma):
        assert math.isfinite(value)
    assert rates.alpha[0] == pytest.approx(1.0, abs=0.05) and rates.gamma == pytest.approx(1.0, rel=1e-12)
    # Sampling error of a mean over a handful of ones: the fit says it is uncertain.
    assert rates.alpha_se[0] > 0.1


def test_plain_mc_on_a_rare_integer_event_warns_about_kurtosis():
    def rare(level, indices):
        return (np.asarray(indices) % 1000 == 3).astype(float), np.zeros(len(indices)), np.ones(len(indices))

    result, messages = record_warnings(mc, rare, tol=0.01, level=0)
    assert any("kurtosis" in m for m in messages)
    for value in (result.estimate, result.stat_error, result.variance, result.variance_error, result.mc_cost):
        assert math.isfinite(value)
    n = int(result.n_samples[0])
    assert result.estimate == np.count_nonzero(np.arange(n) % 1000 == 3) / n
    assert result.statistics.kurtosis[0, 0] > 100


@pytest.mark.parametrize("alpha", [1e-300, 1e-17, 1e-10])
def test_remaining_bias_for_tiny_positive_rates_is_finite(alpha):
    # 2.0**alpha - 1 rounds to 0 for alpha < 1.6e-16: 0/0 and 1/0 used to be computed.
    bias = remaining_bias(np.array([0.0, 1e-3]), np.array([alpha, alpha]))
    assert bias[0] == 0.0
    assert bias[1] == pytest.approx(1e-3 / (alpha * math.log(2.0)), rel=1e-9)


def test_remaining_bias_overflow_is_infinite_and_non_decaying_rates_are_errors():
    assert remaining_bias(np.array([1.0]), np.array([1e-310]))[0] == math.inf
    for alpha in (0.0, -0.5, math.nan):
        with pytest.raises(EstimationError, match="does not decay"):
            remaining_bias(np.array([1.0]), np.array([alpha]))


def test_the_coupling_check_needs_enough_samples():
    # Two well-coupled samples can show Var(Y_l) > Var(Q_l) by chance (q1 ~ q2): no alarm;
    # ten samples with an independent coarse value still raise it.
    two = level_statistics(fine=[np.array([1.0, 2.0]), np.array([5.0, 5.01])],
                           coarse=[np.zeros(2), np.array([4.9, 5.2])], cost=[np.ones(2)] * 2)
    assert two.coupling_ratio[1, 0] > 1.0
    assert not any("weakly coupled" in m for m in diagnose(two))
    rng = np.random.default_rng(16)
    ten = level_statistics(fine=[rng.normal(size=10), rng.normal(size=10)],
                           coarse=[np.zeros(10), rng.normal(size=10)], cost=[np.ones(10)] * 2)
    assert ten.coupling_ratio[1, 0] > 1.0
    assert any("weakly coupled" in m for m in diagnose(ten))

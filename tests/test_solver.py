"""Contact solver: analytic references, invariants, warm starts, failure modes."""

from __future__ import annotations

import numpy as np
import pytest

from rough_uq.physics.elastic import HalfSpace, westergaard_kernel
from rough_uq.errors import InvalidParameterError
from rough_uq.physics.reference import (
    full_contact_pressure,
    westergaard_contact_half_width,
    westergaard_full_contact_pressure,
    westergaard_pressure,
)
from rough_uq.physics import solver as solver_module
from rough_uq.physics.solver import resample_pressure, solve_contact

L = 1.0
AMPLITUDE = 0.01


def random_surface(n: int, *, seed: int = 0, k_s: int = 16, hurst: float = 0.8) -> np.ndarray:
    """A self-affine random surface built independently of rough_uq.physics.surface."""
    rng = np.random.default_rng(seed)
    k0 = np.fft.fftfreq(n, 1.0 / n)[:, None]
    k1 = np.fft.fftfreq(n, 1.0 / n)[None, :]
    k = np.hypot(k0, k1)
    band = (k >= 1) & (k <= k_s)
    phi = np.zeros_like(k)
    phi[band] = k[band] ** (-2 - 2 * hurst)
    coefficients = np.sqrt(phi) * (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n)))
    heights = np.real(np.fft.ifft2(coefficients)) * n * n
    return heights / heights.std()


def sinusoid(n: int) -> tuple[np.ndarray, np.ndarray]:
    x = np.arange(n) * L / n
    return x, np.tile((AMPLITUDE * np.cos(2 * np.pi * x / L))[:, None], (1, n))


def test_half_space_matches_numpy_fft_and_single_mode():
    n = 32
    rng = np.random.default_rng(1)
    p = rng.random((n, n))
    op = HalfSpace(n, system_size=2.0, e_star=3.0)
    expected = np.fft.irfft2(np.fft.rfft2(p) * westergaard_kernel(n, system_size=2.0, e_star=3.0), s=(n, n))
    np.testing.assert_allclose(op.displacement(p), expected, rtol=1e-12, atol=1e-14)
    # A single mode p0 cos(q x) gives u = 2 p0 / (E* q) cos(q x).
    x = np.arange(n) * 2.0 / n
    q = 2 * np.pi * 3 / 2.0
    mode = np.tile(np.cos(q * x)[:, None], (1, n))
    np.testing.assert_allclose(op.displacement(0.5 * mode), 2 * 0.5 / (3.0 * q) * mode, atol=1e-14)


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.8])
def test_westergaard_partial_contact(fraction):
    n = 256
    x, s = sinusoid(n)
    p_star = westergaard_full_contact_pressure(amplitude=AMPLITUDE, wavelength=L)
    load = fraction * p_star
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
    assert sol.converged
    a = westergaard_contact_half_width(amplitude=AMPLITUDE, wavelength=L, mean_pressure=load)
    h = L / n
    # The contact width is resolved to about one grid spacing on each side.
    assert abs(sol.contact[:, 0].sum() * h - 2 * a) <= 2 * h + 1e-12
    exact = westergaard_pressure(x, amplitude=AMPLITUDE, wavelength=L, mean_pressure=load)
    error = np.linalg.norm(sol.pressure[:, 0] - exact) / np.linalg.norm(exact)
    assert error < 0.02
    # Uniform in y.
    assert np.ptp(sol.pressure, axis=1).max() < 1e-9 * load


def test_westergaard_pressure_converges_with_grid():
    # The L2 error is dominated by the few nodes at the contact edge, where the
    # exact pressure has a square-root profile: it oscillates with the position
    # of the edge between two nodes, so it is bounded here, not fitted. Away from
    # the edge the discrete solution converges fast; that rate is fitted.
    sizes = [64, 96, 128, 192, 256, 384, 512]
    p_star = westergaard_full_contact_pressure(amplitude=AMPLITUDE, wavelength=L)
    load = 0.3 * p_star
    a = westergaard_contact_half_width(amplitude=AMPLITUDE, wavelength=L, mean_pressure=load)
    interior_errors = []
    for n in sizes:
        x, s = sinusoid(n)
        sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-10)
        assert sol.converged
        exact = westergaard_pressure(x, amplitude=AMPLITUDE, wavelength=L, mean_pressure=load)
        error = sol.pressure[:, 0] - exact
        assert np.linalg.norm(error) / np.linalg.norm(exact) < 0.01
        interior = np.minimum(x, L - x) < a - 0.05 * L
        interior_errors.append(np.abs(error[interior]).max() / exact.max())
    slope = np.polyfit(np.log(sizes), np.log(interior_errors), 1)[0]
    assert slope < -1.5, (slope, interior_errors)


def test_westergaard_full_contact_is_exact():
    n = 64
    x, s = sinusoid(n)
    p_star = westergaard_full_contact_pressure(amplitude=AMPLITUDE, wavelength=L)
    load = 1.5 * p_star
    sol = solve_contact(s, system_size=L, mean_pressure=load)
    assert sol.converged and sol.contact.all()
    exact = load + p_star * np.cos(2 * np.pi * x / L)
    np.testing.assert_allclose(sol.pressure[:, 0], exact, rtol=1e-10)
    np.testing.assert_allclose(full_contact_pressure(s, system_size=L, mean_pressure=load)[:, 0], exact, rtol=1e-12)


def test_force_balance_signs_and_complementarity():
    n = 128
    s = random_surface(n)
    load = 0.5
    sol = solve_contact(s, system_size=L, mean_pressure=load, e_star=2.0, tol=1e-10)
    assert sol.converged and sol.error < 1e-10
    assert sol.pressure.mean() == pytest.approx(load, rel=1e-13)
    assert sol.pressure.min() >= 0
    scale = s.std()
    assert sol.gap.min() >= -1e-8 * scale
    assert np.abs(sol.gap[sol.contact]).max() < 1e-6 * scale
    assert np.mean(sol.pressure * np.abs(sol.gap)) < 1e-10 * load * scale
    # gap = u - s + d and u has zero mean.
    np.testing.assert_allclose(sol.gap, sol.displacement - s + sol.approach, atol=1e-12 * scale)
    assert abs(sol.displacement.mean()) < 1e-12 * scale
    for field in (sol.pressure, sol.displacement, sol.gap):
        assert np.all(np.isfinite(field))


@pytest.mark.parametrize("factor", [1e-9, 1e-3, 1e3, 1e9])
def test_scaling_heights_and_load_keeps_contact_set(factor):
    n = 64
    s = random_surface(n, seed=3)
    reference = solve_contact(s, system_size=L, mean_pressure=0.3, tol=1e-10)
    scaled = solve_contact(factor * s, system_size=L, mean_pressure=0.3 * factor, tol=1e-10)
    assert scaled.converged
    np.testing.assert_array_equal(scaled.contact, reference.contact)
    np.testing.assert_allclose(scaled.pressure / factor, reference.pressure, rtol=1e-6, atol=1e-9 * 0.3)


def test_periodic_shift_and_rotation_move_the_solution():
    n = 64
    s = random_surface(n, seed=4)
    sol = solve_contact(s, system_size=L, mean_pressure=0.4, tol=1e-11)
    shifted = solve_contact(np.roll(s, (5, -13), axis=(0, 1)), system_size=L, mean_pressure=0.4, tol=1e-11)
    np.testing.assert_allclose(shifted.pressure, np.roll(sol.pressure, (5, -13), axis=(0, 1)), atol=1e-7)
    rotated = solve_contact(np.rot90(s), system_size=L, mean_pressure=0.4, tol=1e-11)
    np.testing.assert_allclose(rotated.pressure, np.rot90(sol.pressure), atol=1e-7)


def test_max_iter_reports_non_convergence_without_nan():
    s = random_surface(128, seed=5)
    sol = solve_contact(s, system_size=L, mean_pressure=0.2, tol=1e-12, max_iter=3)
    assert not sol.converged
    assert sol.n_iter == 3
    assert "max_iter" in sol.message
    assert np.isfinite(sol.error) and sol.error > 1e-12
    for field in (sol.pressure, sol.displacement, sol.gap):
        assert np.all(np.isfinite(field))


def test_warm_start_from_coarser_grid_cuts_iterations_and_agrees():
    n = 256
    fine = random_surface(n, seed=6, k_s=32)
    coarse = fine[::2, ::2]  # k_s = 32 < 64 = coarse Nyquist: injection is exact
    load = 0.1
    coarse_sol = solve_contact(coarse, system_size=L, mean_pressure=load, tol=1e-10)
    cold = solve_contact(fine, system_size=L, mean_pressure=load, tol=1e-10)
    warm = solve_contact(fine, system_size=L, mean_pressure=load, tol=1e-10, initial_pressure=coarse_sol.pressure)
    assert warm.converged and cold.converged
    assert warm.n_iter < cold.n_iter
    np.testing.assert_allclose(warm.pressure, cold.pressure, atol=1e-6 * load * 10)


@pytest.mark.parametrize("n", [64, 256])
def test_preconditioner_cuts_iterations_and_reaches_the_plain_solution(n):
    # The preconditioned and the plain Polonsky-Keer iterations solve the same
    # problem: same pressure to the tolerance, far fewer iterations on a rough
    # surface resolved down to the grid (here 25 against 53 at 64^2 and 55
    # against 193 at 256^2, about 18% contact), a gap that widens with the grid.
    s = random_surface(n, seed=11, k_s=n // 2)
    rms_slope = np.sqrt(2 * np.mean(np.gradient(s, L / n, axis=0) ** 2))
    load = 0.1 * rms_slope
    plain = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11, precondition=False)
    fast = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11)
    assert plain.converged and fast.converged
    assert fast.n_iter < plain.n_iter / (1.5 if n == 64 else 2.5)
    assert np.linalg.norm(fast.pressure - plain.pressure) / np.linalg.norm(plain.pressure) < 1e-8
    assert np.array_equal(fast.contact, plain.contact)
    assert fast.pressure.mean() == pytest.approx(load, rel=1e-12)


@pytest.mark.parametrize("precondition", [True, False])
def test_solutions_own_their_arrays(precondition):
    # The solver iterates in the buffers of cached FFT plans (the pressure in
    # the input, the gap over the displacement): a returned solution must not
    # change when the next solve on the same grid reuses them.
    # The fields are written into the solve's own work arrays (the reference
    # pressure and displacement, the scaled heights): they must not share
    # memory with each other or with the caller's heights, which stay as given.
    n = 32
    heights = random_surface(n, seed=1)
    given = heights.copy()
    first = solve_contact(heights, system_size=L, mean_pressure=0.5, precondition=precondition)
    names = ("pressure", "displacement", "gap")
    kept = {name: getattr(first, name).copy() for name in names}
    solve_contact(random_surface(n, seed=2), system_size=L, mean_pressure=2.0, precondition=precondition)
    for name, value in kept.items():
        np.testing.assert_array_equal(getattr(first, name), value, err_msg=name)
    np.testing.assert_array_equal(heights, given)
    arrays = [heights] + [getattr(first, name) for name in names]
    assert not any(np.shares_memory(a, b) for i, a in enumerate(arrays) for b in arrays[i + 1 :])


@pytest.mark.parametrize("n", [2, 8, 64, 130])
def test_single_precision_kernels_round_the_double_ones(n):
    # The solver's kernels of K and M = K^-1, divided by N and rounded to single
    # precision in one compiled pass, must be the numpy expressions' numbers, bit for bit.
    kernel = westergaard_kernel(n, system_size=1.0)
    single = np.empty(kernel.shape, dtype=np.float32)
    inverse = np.empty_like(single)
    solver_module._single_kernels(kernel, float(n * n), single, inverse)
    expected_inverse = np.divide(1.0, kernel, out=np.zeros_like(kernel), where=kernel > 0)
    np.testing.assert_array_equal(single, (kernel / (n * n)).astype(np.float32))
    np.testing.assert_array_equal(inverse, (expected_inverse / (n * n)).astype(np.float32))
    assert inverse[0, 0] == 0.0 and np.all(inverse.ravel()[1:] > 0)


@pytest.mark.parametrize("precondition", [True, False])
def test_the_uniform_start_is_displaced_without_a_transform(monkeypatch, precondition):
    # A cold start (uniform pressure) has zero displacement, which the solver writes
    # without a double-precision FFT pair. The pair would return exact zeros too, so
    # the solutions must be the same bits as with the transform: on estimated and on
    # measured plans (grids 32-128; 256 is estimated in both), random surfaces, loads, units.
    from rough_uq.physics import fft

    apply = HalfSpace.apply
    applied = []

    def counted(half_space, scale=1.0):
        applied.append(scale)
        return apply(half_space, scale)

    def transformed(state, ops, scale, *, uniform):
        ops.half_space.apply(scale)

    rng = np.random.default_rng(11)
    problems = []
    for n in (32, 64, 128, 256):
        for _ in range(2):
            heights = float(10 ** rng.uniform(-3, 3)) * random_surface(n, seed=int(rng.integers(1000)))
            size = float(10 ** rng.uniform(-1, 1))
            slope = float(np.std(np.gradient(heights, size / n, axis=0)))
            problems.append((heights, size, float(10 ** rng.uniform(-2, 0.5)) * slope))
    try:
        for wisdom in (None, fft.measure_plans([32, 64, 128])):
            fft.use_wisdom(wisdom)
            for heights, size, pressure in problems:
                options = dict(system_size=size, mean_pressure=pressure, precondition=precondition)
                applied.clear()
                with monkeypatch.context() as patch:
                    patch.setattr(HalfSpace, "apply", counted)
                    solve_contact(heights, max_iter=1, **options)
                assert len(applied) == 1, "one exact displacement: the stop's, none at the start"
                skipped = solve_contact(heights, **options)
                with monkeypatch.context() as patch:
                    patch.setattr(solver_module._State, "_displace", transformed)
                    reference = solve_contact(heights, **options)
                assert skipped.converged and skipped.n_iter == reference.n_iter
                for name in ("pressure", "displacement", "gap"):
                    np.testing.assert_array_equal(getattr(skipped, name), getattr(reference, name), err_msg=name)
    finally:
        fft.use_wisdom(None)


@pytest.mark.parametrize("n", [64, 256, 512])
def test_small_grids_run_their_passes_on_one_thread(monkeypatch, n):
    # Waking a second numba thread costs more than a pass on grids below
    # PARALLEL_PASS_MIN_NODES: their passes run on one thread whatever `threads`
    # says; larger grids use the threads asked for (as many as numba has), and
    # the caller's numba thread count is restored afterwards.
    import numba

    seen = []
    gap_pass = solver_module._gap_pass

    def recorded(*args):
        seen.append(numba.get_num_threads())
        return gap_pass(*args)

    monkeypatch.setattr(solver_module, "_gap_pass", recorded)
    before = numba.get_num_threads()
    solution = solve_contact(random_surface(n, seed=3), system_size=L, mean_pressure=1.0, threads=2)
    assert solution.converged
    expected = 1 if n * n < solver_module.PARALLEL_PASS_MIN_NODES else min(2, numba.config.NUMBA_NUM_THREADS)
    assert set(seen) == {expected}
    assert numba.get_num_threads() == before


@pytest.mark.parametrize("kind", ["single_node", "unrelated_surface", "finer_grid"])
def test_poor_warm_starts_still_converge_to_the_same_solution(kind):
    n = 64
    s = random_surface(n, seed=7)
    load = 0.3
    reference = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11)
    if kind == "single_node":
        guess = np.zeros((n, n))
        guess[3, 4] = 1.0
    elif kind == "unrelated_surface":
        guess = solve_contact(random_surface(n, seed=99), system_size=L, mean_pressure=load).pressure
    else:
        guess = solve_contact(random_surface(2 * n, seed=8), system_size=L, mean_pressure=load).pressure
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-11, initial_pressure=guess)
    assert sol.converged
    np.testing.assert_allclose(sol.pressure, reference.pressure, atol=1e-6 * load * 10)


def test_resample_pressure_restricts_and_prolongs():
    rng = np.random.default_rng(2)
    p = rng.random((16, 16))
    up = resample_pressure(p, 32)
    np.testing.assert_array_equal(up[::2, ::2], p)
    assert up.min() >= 0 and up.mean() == pytest.approx(p.mean())
    down = resample_pressure(up, 16)
    assert down.shape == (16, 16) and down.mean() == pytest.approx(p.mean())
    constant = np.full((32, 32), 2.0)
    np.testing.assert_allclose(resample_pressure(constant, 8), 2.0)
    with pytest.raises(InvalidParameterError, match="power of two"):
        resample_pressure(p, 24)
    with pytest.raises(InvalidParameterError, match="^pressure"):
        resample_pressure(np.ones(4), 8)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"heights": np.zeros((8, 6))}, "heights"),
        ({"heights": np.zeros((7, 7))}, "heights"),
        ({"heights": np.full((8, 8), np.nan)}, "heights"),
        ({"mean_pressure": 0.0}, "mean_pressure"),
        ({"mean_pressure": -1.0}, "mean_pressure"),
        ({"e_star": 0.0}, "e_star"),
        ({"system_size": -2.0}, "system_size"),
        ({"tol": 0.0}, "tol"),
        ({"max_iter": 0}, "max_iter"),
        ({"initial_pressure": -np.ones((8, 8))}, "initial_pressure"),
        ({"initial_pressure": np.zeros((8, 8))}, "initial_pressure"),
        ({"initial_pressure": np.ones((6, 6))}, "initial_pressure"),
        ({"initial_pressure": np.ones((8, 4))}, "initial_pressure"),
        ({"threads": 0}, "threads"),
        ({"threads": 1.5}, "threads"),
        ({"threads": True}, "threads"),
        # Booleans and strings are not numbers (True would pass for 1).
        ({"system_size": True}, "system_size"),
        ({"mean_pressure": "0.1"}, "mean_pressure"),
        ({"max_iter": True}, "max_iter"),
        ({"tol": "1e-7"}, "tol"),
    ],
)
def test_invalid_input_names_the_parameter(kwargs, name):
    arguments = {"heights": random_surface(8, k_s=3), "system_size": 1.0, "mean_pressure": 0.1}
    arguments.update(kwargs)
    heights = arguments.pop("heights")
    with pytest.raises(InvalidParameterError, match=name):
        solve_contact(heights, **arguments)


@pytest.mark.parametrize("name", ["heights", "initial_pressure"])
@pytest.mark.parametrize(
    "values, held",
    [
        ("abc", "text"),
        (np.full((8, 8), "1.0"), "text"),
        (np.ones((8, 8), dtype=complex), "complex numbers"),
        (np.ones((8, 8), dtype=bool), "booleans"),
        (np.full((8, 8), None), "Python objects"),
        (np.ones((8, 8), dtype="timedelta64[s]"), "time differences"),  # a subtype of np.integer
    ],
)
def test_arrays_that_are_not_real_numbers_are_refused_by_name(name, values, held):
    # The initial pressure was converted to float first: a string gave numpy's own ValueError, a complex
    # guess only a ComplexWarning (its imaginary part dropped), booleans ran as 0/1.
    arguments = {"heights": random_surface(8, k_s=3), "initial_pressure": None, name: values}
    expected = rf"^{name}: got 'an array of {held}'; allowed: real numbers \(float or integer\)$"
    with pytest.raises(InvalidParameterError, match=expected):
        solve_contact(arguments.pop("heights"), system_size=1.0, mean_pressure=0.1, **arguments)


def test_no_heights_are_refused_as_none():
    # They were "an array of Python objects".
    with pytest.raises(InvalidParameterError, match="^heights: got None; allowed: a square 2-D array of real numbers$"):
        solve_contact(None, system_size=1.0, mean_pressure=0.1)


@pytest.mark.parametrize("name", ["heights", "initial_pressure"])
def test_a_ragged_list_is_refused_by_name(name):
    # numpy's own ValueError ("inhomogeneous shape") came through before.
    ragged = [[0.0] * 8 for _ in range(7)] + [[0.0] * 7]
    arguments = {"heights": random_surface(8, k_s=3), "initial_pressure": None, name: ragged}
    expected = rf"^{name}: got 'a ragged sequence \(rows of different lengths\)'; allowed: a square 2-D array$"
    with pytest.raises(InvalidParameterError, match=expected):
        solve_contact(arguments.pop("heights"), system_size=1.0, mean_pressure=0.1, **arguments)


def test_approach_is_the_highest_height_at_first_contact_and_falls_with_the_load():
    heights = random_surface(64, k_s=8)
    approaches = [solve_contact(heights, system_size=1.0, mean_pressure=load).approach
                  for load in (1e-7, 1e-3, 1e-1, 1.0)]
    assert approaches[0] == pytest.approx(heights.max(), rel=1e-3)
    assert np.all(np.diff(approaches) < 0)


def test_integer_initial_pressure_is_a_guess():
    heights = random_surface(8, k_s=3)
    guess = np.ones((8, 8), dtype=np.int64)
    solution = solve_contact(heights, system_size=1.0, mean_pressure=0.1, initial_pressure=guess)
    assert solution.converged


@pytest.mark.parametrize("flag", ["no", "False", 0, 1, None, [False]])
def test_precondition_that_is_not_a_bool_is_refused_by_name(flag):
    # "no" (any non-empty string) ran preconditioned, 0 and None ran plain: read by their truth value.
    with pytest.raises(InvalidParameterError, match=r"^precondition: got .*; allowed: True or False$"):
        solve_contact(random_surface(8, k_s=3), system_size=1.0, mean_pressure=0.1, precondition=flag)


def test_precondition_takes_numpy_booleans():
    heights = random_surface(8, k_s=3)
    for flag, path in ((np.True_, "preconditioned"), (np.False_, "plain")):
        assert solve_contact(heights, system_size=1.0, mean_pressure=0.1, precondition=flag).path == path


def test_flat_surface_is_uniform_pressure():
    sol = solve_contact(np.zeros((16, 16)), system_size=1.0, mean_pressure=0.7)
    assert sol.converged and sol.n_iter == 0
    np.testing.assert_allclose(sol.pressure, 0.7)


def test_agrees_with_tamaas():
    tamaas = pytest.importorskip("tamaas")
    n = 128
    s = random_surface(n, seed=9, k_s=32)
    load = 0.2
    model = tamaas.ModelFactory.createModel(tamaas.model_type.basic_2d, [L, L], [n, n])
    model.E = 1.0
    model.nu = 0.0
    peer = tamaas.PolonskyKeerRey(model, s, 1e-12, tamaas.PolonskyKeerRey.pressure, tamaas.PolonskyKeerRey.pressure)
    peer.max_iter = 10_000
    tamaas.set_log_level(tamaas.LogLevel.warning)
    peer.solve(load)
    peer_pressure = np.array(model.traction).reshape(n, n)
    sol = solve_contact(s, system_size=L, mean_pressure=load, tol=1e-12)
    assert sol.converged
    assert np.linalg.norm(sol.pressure - peer_pressure) / np.linalg.norm(peer_pressure) < 1e-6

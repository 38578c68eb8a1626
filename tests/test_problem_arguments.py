"""Arguments of the contact problem, its sampler and the physics functions behind it: refused by name."""

from __future__ import annotations

import re

import numpy as np
import pytest

import rough_uq
from rough_uq.errors import ConfigError, InvalidParameterError
from rough_uq.problem.contact import MAX_SOLVER_TOL, MIN_SOLVER_TOL
from rough_uq.study import config as config_module


def _problem(**changes) -> rough_uq.ContactProblem:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    settings = dict(load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"], coarsest=8, max_level=2, solver_tol=1e-8,
                    seed=2026)
    return rough_uq.ContactProblem(spectrum, **{**settings, **changes})


@pytest.mark.parametrize("tol", [1e-17, 1e-16, 1e-15, 0.99e-14])
def test_a_solver_tolerance_below_what_rounding_allows_is_refused(tol) -> None:
    # 1e-17 was accepted, and every solve ran 10,000 iterations and a 100,000-iteration retry without converging.
    refusal = r"^solver_tol: got .*allowed: a number in \[1e-14, 1\)"
    with pytest.raises(InvalidParameterError, match=refusal) as caught:
        _problem(solver_tol=tol)
    assert "rounding" in caught.value.allowed


@pytest.mark.parametrize("tol", [MIN_SOLVER_TOL, 1e-13, 1e-12, 1e-7])
def test_solver_tolerances_the_solver_reaches_are_accepted(tol) -> None:
    assert _problem(solver_tol=tol).model.tol == tol


def test_the_config_takes_the_same_smallest_solver_tolerance() -> None:
    from tests.test_config import _base

    assert config_module.MIN_SOLVER_TOL == MIN_SOLVER_TOL
    data = _base()
    data["solver"] = {"tol": MIN_SOLVER_TOL}
    assert config_module.config_from_dict(data).solver.tol == MIN_SOLVER_TOL
    data["solver"] = {"tol": 1e-17}
    with pytest.raises(ConfigError, match=r"solver\.tol.*1e-14, 0.01\]"):
        config_module.config_from_dict(data)


@pytest.mark.parametrize("tol", [0.011, 0.2, 0.9, 1.0])
def test_a_solver_tolerance_that_gives_no_contact_solution_is_refused_by_a_config_and_warned_of(tol) -> None:
    # 0.9 was accepted: contact area 100 % after no iteration, reported as converged (0.5 gave 57.5 % against
    # 19.55 % at the default): a QoI tolerance written under solver by mistake.
    from tests.test_config import _base

    assert config_module.MAX_SOLVER_TOL == MAX_SOLVER_TOL
    if tol < 1:  # a problem warns (a study's stored config from before the bound must still be read)
        with pytest.warns(rough_uq.EstimationWarning, match=r"^solver_tol .* above MAX_SOLVER_TOL = 0.01: .*no "
                          "contact solution"):
            _problem(solver_tol=tol)
    else:
        with pytest.raises(InvalidParameterError, match=r"^solver_tol: .*1e-14, 1\)"):
            _problem(solver_tol=tol)
    data = _base()
    data["solver"] = {"tol": tol}
    with pytest.raises(ConfigError, match=r"solver\.tol.*1e-14, 0.01\].*no contact solution"):
        config_module.config_from_dict(data)
    data["solver"] = {"tol": MAX_SOLVER_TOL}
    assert config_module.config_from_dict(data).solver.tol == _problem(solver_tol=MAX_SOLVER_TOL).solver_tol
    # A study file's stored config from before the bound is read as written (its report and samples stay readable).
    stored = config_module.resolved_yaml(config_module.config_from_dict(data)).replace("tol: 0.01", f"tol: {tol}")
    if tol < 1:
        assert config_module.config_from_stored_text(stored).solver.tol == tol
    else:
        with pytest.raises(ConfigError, match=r"solver\.tol: must be less than 1"):
            config_module.config_from_stored_text(stored)


@pytest.mark.parametrize(
    ("level", "indices", "name"),
    [
        (99, [0], "level"),  # OverflowError deep in surface.py
        (3, [0], "level"),  # beyond max_level = 2: silently sampled a 64^2 grid
        (-1, [0], "level"),
        (2.0, [0], "level"),  # the error named n
        (True, [0], "level"),
        (0, [-1], "indices"),
        (0, [0.5], "indices"),  # silently sampled index 0
        (0, np.array([1.0]), "indices"),
        (0, [True], "indices"),
        (0, ["1"], "indices"),
        (0, np.array([2**63], dtype=np.uint64), "indices"),
    ],
)
def test_a_sampler_refuses_a_level_or_indices_it_has_not_by_name(level, indices, name) -> None:
    sampler = _problem().sampler(1)
    for ask in (sampler, sampler.batch):
        with pytest.raises(InvalidParameterError, match=f"^{name}: ") as caught:
            ask(level, indices)
        assert ("max_level = 2" in caught.value.allowed) == (name == "level")
    assert sampler.n_samples == 0


def test_a_sampler_takes_integer_indices_of_any_dtype_with_the_same_samples() -> None:
    sampler = _problem().sampler(1)
    reference = sampler.batch(1, np.array([0, 3], dtype=np.int64))
    for indices in ([0, 3], np.array([0, 3], dtype=np.uint8), np.array([[0], [3]], dtype=np.int32)):
        batch = sampler.batch(np.int64(1), indices)
        assert batch.indices.dtype == np.int64
        np.testing.assert_array_equal(batch.fine, reference.fine)
        np.testing.assert_array_equal(batch.coarse, reference.coarse)
    fine, coarse, cost = sampler(2, np.arange(1))
    assert fine.shape == (1, 1) and cost.shape == (1,)
    assert sampler.batch(0, np.zeros(0, dtype=np.int64)).n_samples == 0


@pytest.mark.parametrize("k_s", [32768.5, 3e4 * 2, 1e12, 1e200])
def test_a_short_cut_off_no_grid_resolves_is_refused_by_name(k_s) -> None:
    # k_s = 1e4 took seconds, 1e12 ended in a MemoryError, 1e200 in an OverflowError.
    with pytest.raises(InvalidParameterError, match=r"^k_s: .*<= 32768 \(MAX_K_S: half the largest grid"):
        rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=k_s, hurst=0.8, rms_height=1.0)
    with pytest.raises(InvalidParameterError, match=r"^lambda_s: got 1e-300; allowed: a wavelength >= system_size"):
        rough_uq.SurfaceSpectrum.from_wavelengths(
            system_size=1, lambda_l=1, lambda_r=0.5, lambda_s=1e-300, hurst=0.8, rms_height=1
        )


def test_the_largest_short_cut_off_is_half_the_largest_grid_in_every_layer() -> None:
    from rough_uq.physics.surface import MAX_K_S
    from rough_uq.problem.contact import MAX_GRID
    from tests.test_config import _base

    assert MAX_K_S == config_module.MAX_K_S == MAX_GRID // 2
    data = _base()
    data["surface"]["wavelengths"]["lambda_s"] = data["surface"]["system_size"] / MAX_K_S
    assert config_module.config_from_dict(data).surface.k_s == MAX_K_S
    data["surface"]["wavelengths"]["lambda_s"] = 1e-300
    with pytest.raises(ConfigError, match=r"surface\.wavelengths\.lambda_s: .*got 1e-300; allowed: number >= system"):
        config_module.config_from_dict(data)
    data["surface"].pop("wavelengths")
    data["surface"]["wavenumbers"] = {"k_l": 2, "k_r": 2, "k_s": 1e12}
    with pytest.raises(ConfigError, match=r"surface\.wavenumbers\.k_s: .*got 1000000000000.0; allowed: .*<= 32768"):
        config_module.config_from_dict(data)


@pytest.mark.parametrize("system_size", [3.0, 0.7, 1e-3])
def test_the_smallest_wavelength_a_refusal_names_is_accepted(system_size) -> None:
    # The refusal printed system_size / 32768 to six digits: 3 / 32768 as 9.15527e-05, whose k_s, 32768.0098, was
    # refused in turn. (Only checked, not built: a spectrum with k_s = 32768 takes minutes to set up.)
    from tests.test_config import _base

    def named_bound(text: str) -> float:
        return float(re.search(r"system_size / 32768 = ([0-9.e+-]+)", text).group(1))

    with pytest.raises(InvalidParameterError) as info:
        rough_uq.SurfaceSpectrum.from_wavelengths(
            system_size=system_size, lambda_l=system_size, lambda_r=system_size / 2, lambda_s=system_size / 4e4,
            hurst=0.8, rms_height=1,
        )
    assert system_size / named_bound(str(info.value)) <= 32768
    data = _base()
    data["surface"]["system_size"] = system_size
    data["surface"]["wavelengths"] = {"lambda_l": system_size, "lambda_r": system_size / 2, "lambda_s": 1e-9}
    with pytest.raises(ConfigError) as refusal:
        config_module.config_from_dict(data)
    data["surface"]["wavelengths"]["lambda_s"] = named_bound(str(refusal.value))
    assert config_module.config_from_dict(data).surface.k_s <= 32768


def _surface(n: int = 32) -> np.ndarray:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    return rough_uq.sample_surface(spectrum, n, np.random.default_rng(3))


def test_load_curve_warm_starts_may_be_a_stack_of_fields_one_per_load() -> None:
    # A stacked array was refused as "got '2 fields'; allowed: a sequence of 2 fields".
    heights, loads = _surface(), [0.1, 0.2]
    guesses = [np.ones((32, 32)), np.ones((16, 16))]
    stacked = rough_uq.solve_load_curve(heights, system_size=1.0, mean_pressures=loads,
                                        initial_pressures=np.stack([np.ones((32, 32))] * 2))
    listed = rough_uq.solve_load_curve(heights, system_size=1.0, mean_pressures=loads,
                                       initial_pressures=[np.ones((32, 32))] * 2)
    for a, b in zip(stacked.solutions, listed.solutions):
        np.testing.assert_array_equal(a.pressure, b.pressure)
    assert rough_uq.solve_load_curve(heights, system_size=1.0, mean_pressures=loads, initial_pressures=guesses)


@pytest.mark.parametrize(
    ("guesses", "got"),
    [
        (np.ones((2, 32)), "an array of shape (2, 32)"),  # a single field would be taken row by row
        (np.ones((3, 32, 32)), "an array of shape (3, 32, 32)"),
        (np.array(1.0), "an array of shape ()"),
        (5, "an object of type int"),
        ((np.ones((32, 32)) for _ in range(2)), "an object of type generator"),
        ("ab", "an object of type str"),
        ([np.ones((32, 32))], "a sequence of 1 fields"),
    ],
)
def test_load_curve_warm_starts_that_are_not_one_field_per_load_are_refused_by_name(guesses, got) -> None:
    with pytest.raises(InvalidParameterError) as caught:
        rough_uq.solve_load_curve(_surface(), system_size=1.0, mean_pressures=[0.1, 0.2], initial_pressures=guesses)
    assert caught.value.name == "initial_pressures" and caught.value.value == got
    assert caught.value.allowed.startswith("a sequence of 2 fields (2-D arrays), one per load, or an array of shape")


@pytest.mark.parametrize("names", [None, 5, 0.5])
def test_qoi_names_that_are_not_names_are_refused_by_name(names) -> None:
    # A bare TypeError: 'NoneType' object is not iterable.
    with pytest.raises(InvalidParameterError, match=r"^names: got .*allowed: a name or a list of names"):
        rough_uq.evaluate_qoi(names, pressure=np.ones((4, 4)))


@pytest.mark.parametrize("names", [b"contact_area", [1], ("contact_area", None)])
def test_qoi_names_that_are_not_strings_are_refused_as_given(names) -> None:
    # The message showed the tuple made of them: got (99, 111, 110, ...) for b"contact_area".
    with pytest.raises(InvalidParameterError) as caught:
        _problem(qoi=names)
    assert caught.value.name == "qoi" and caught.value.value is names


@pytest.mark.parametrize("kind", [set, frozenset])
def test_qoi_names_in_a_set_are_refused_since_their_order_changes_between_processes(kind) -> None:
    # A set's order follows string hashing, randomised per process: the columns (and a list of tolerances meant for
    # them, and the samples' random stage) changed from one process to the next.
    names = kind(["contact_area", "clusters", "max_pressure"])
    with pytest.raises(InvalidParameterError, match=r"^qoi: got .*in a list or tuple \(a set has no fixed order\)"):
        _problem(qoi=names)
    with pytest.raises(InvalidParameterError, match=r"^names: got .*a set has no fixed order"):
        rough_uq.evaluate_qoi(names, pressure=np.ones((4, 4)))


def test_qoi_names_from_a_numpy_array_are_plain_strings() -> None:
    # np.str_ names ended up in the columns (and their repr in messages) as np.str_('contact_area').
    problem = _problem(qoi=np.array(["contact_area", "clusters"]))
    assert problem.qoi == ("contact_area", "clusters") and all(type(name) is str for name in problem.qoi)


@pytest.mark.parametrize("connectivity", [8.0, 4.0, np.float64(8.0)])
def test_a_connectivity_given_as_a_float_is_refused_like_other_integer_settings(connectivity) -> None:
    # 8.0 == 8 passed the membership test, where max_iter=2.0 and the grids refuse floats.
    with pytest.raises(InvalidParameterError) as caught:
        _problem(qoi=["clusters"], connectivity=connectivity)
    assert caught.value.name == "connectivity"
    contact = np.eye(4, dtype=bool)
    for call in (lambda: rough_uq.count_clusters(contact, connectivity=connectivity),
                 lambda: rough_uq.evaluate_qoi(["clusters"], pressure=np.ones((4, 4)), connectivity=connectivity)):
        with pytest.raises(InvalidParameterError) as caught:
            call()
        assert caught.value.name == "connectivity"
    assert _problem(qoi=["clusters"], connectivity=np.int64(8)).connectivity == 8


def test_a_gap_of_another_shape_than_the_pressure_is_refused_by_name() -> None:
    # The mean of gap[:3] was returned as the mean gap.
    pressure, gap = np.zeros((4, 4)), np.arange(16.0).reshape(4, 4)
    pressure[0, 0] = 1.0
    with pytest.raises(InvalidParameterError, match=r"^gap: got 'an array of shape \(3, 4\)'; allowed: .*\(4, 4\)"):
        rough_uq.evaluate_qoi(["mean_gap"], pressure=pressure, gap=gap[:3])
    assert rough_uq.evaluate_qoi(("mean_gap",), pressure=pressure, gap=gap)[0] == np.mean(gap)


_HUGE = 10**400  # an integer no float holds: float(_HUGE) raises OverflowError
_SPECTRUM = dict(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        *[(field, lambda field=field: rough_uq.SurfaceSpectrum(**{**_SPECTRUM, field: _HUGE})) for field in _SPECTRUM],
        ("load.relative", lambda: rough_uq.RelativeLoad(_HUGE)),
        ("load.absolute", lambda: rough_uq.AbsoluteLoad(-_HUGE)),
        ("mean_pressure", lambda: rough_uq.solve_contact(np.eye(8), system_size=1.0, mean_pressure=_HUGE)),
        ("e_star", lambda: rough_uq.solve_contact(np.eye(8), system_size=1.0, mean_pressure=0.1, e_star=_HUGE)),
        ("mean_pressures", lambda: rough_uq.solve_load_curve(np.eye(8), system_size=1.0, mean_pressures=[0.1, _HUGE])),
        ("critical_pressure", lambda: rough_uq.evaluate_qoi(["area_above"], pressure=np.ones((4, 4)),
                                                             critical_pressure=_HUGE)),
        ("e_star", lambda: _problem(e_star=_HUGE)),
        ("critical_pressure", lambda: _problem(qoi=["area_above"], critical_pressure=_HUGE)),
        ("coarsest", lambda: _problem(coarsest=_HUGE)),
    ],
)
def test_an_integer_beyond_the_float_range_is_refused_by_name_not_with_an_overflow(name, call) -> None:
    # A bare OverflowError ("int too large to convert to float") came out of each of these.
    with pytest.raises(InvalidParameterError) as caught:
        call()
    assert caught.value.name == name
    assert "integer of 401 digits" in str(caught.value) and len(str(caught.value)) < 400


def test_an_integer_of_more_digits_than_python_prints_is_shown_by_its_size() -> None:
    # str() of an integer beyond 4300 digits raises ValueError: the error's own message failed to build.
    with pytest.raises(InvalidParameterError, match=r"^load\.relative: got an integer of 5001 digits; allowed: "):
        rough_uq.RelativeLoad(10**5000)
    with pytest.raises(InvalidParameterError, match=r"^e_star: got a negative integer of 5001 digits; allowed: "):
        _problem(e_star=-(10**5000))


def test_a_two_dimensional_array_of_loads_is_refused_not_flattened() -> None:
    # np.array([[0.1, 0.2], [0.3, 0.4]]) was solved as four loads.
    with pytest.raises(InvalidParameterError) as caught:
        rough_uq.solve_load_curve(np.eye(8), system_size=1.0, mean_pressures=np.array([[0.1, 0.2], [0.3, 0.4]]))
    assert caught.value.name == "mean_pressures"
    assert rough_uq.solve_load_curve(np.eye(8), system_size=1.0, mean_pressures=np.array([0.1, 0.2])).n_loads == 2


@pytest.mark.parametrize("flag", [True, np.bool_(True)])
def test_a_boolean_load_is_refused_not_read_as_1(flag) -> None:
    with pytest.raises(InvalidParameterError) as caught:
        rough_uq.solve_load_curve(np.eye(8), system_size=1.0, mean_pressures=[0.1, flag])
    assert caught.value.name == "mean_pressures"


@pytest.mark.parametrize("threads", [2**31, 2**64, 10**100])
def test_a_thread_count_beyond_what_any_layer_takes_is_refused_by_name(threads) -> None:
    # Each was an OverflowError from deep inside pyFFTW's planner (`roughuq screen` with solver.threads: 1e100
    # written as an integer printed a traceback).
    from rough_uq.physics.solver import MAX_THREADS
    from rough_uq.problem.contact import MAX_THREADS as problem_max_threads
    from tests.test_config import _base

    assert MAX_THREADS == problem_max_threads == config_module.MAX_THREADS
    with pytest.raises(InvalidParameterError, match=r"^threads: got [^;]+; allowed: an integer in 1\.\.1024"):
        _problem(threads=threads)
    with pytest.raises(InvalidParameterError, match=r"^threads: got .*allowed: an integer in 1\.\.1024"):
        rough_uq.solve_contact(np.zeros((8, 8)), system_size=1.0, mean_pressure=0.1, threads=threads)
    data = _base()
    data["solver"] = {"threads": threads}
    with pytest.raises(ConfigError, match=r"solver\.threads: .*allowed: integer in 1\.\.1024"):
        config_module.config_from_dict(data)
    data["solver"] = {"threads": MAX_THREADS}
    assert config_module.config_from_dict(data).solver.threads == _problem(threads=MAX_THREADS).threads


@pytest.mark.parametrize("max_level", [17, 2**63, 10**100])
def test_a_huge_max_level_is_refused_at_once(max_level) -> None:
    # 32 * 2**max_level was computed before the comparison: 2**63 never finished (`roughuq validate` hung).
    from tests.test_config import _base

    with pytest.raises(InvalidParameterError, match=r"^max_level: got [^;]+; allowed: a finest grid"):
        _problem(coarsest=32, max_level=max_level)
    data = _base()
    data["grid"] = {"coarsest": 32, "max_level": max_level}
    with pytest.raises(ConfigError, match=rf"grid\.max_level: makes the finest grid 32 \* 2\*\*{max_level} larger"):
        config_module.config_from_dict(data)
    assert _problem(coarsest=32, max_level=11).max_level == 11


def test_numpy_choices_are_kept_as_plain_values() -> None:
    # np.int64(8) was kept as given: the problem's repr read connectivity=np.int64(8), and the problem differed in
    # type from one built with 8.
    problem = _problem(
        connectivity=np.int64(8), area_estimator=np.str_("nodes"), projection=np.str_("injection"), coarsest=32
    )
    assert type(problem.connectivity) is int and type(problem.area_estimator) is str
    assert type(problem.projection) is str and "connectivity=8," in repr(problem)
    assert problem == _problem(connectivity=8, area_estimator="nodes", projection="injection", coarsest=32)

"""The error classes: each pickles with its fields, so a worker's error reaches the caller as itself."""

from __future__ import annotations

import inspect
import pickle
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

import rough_uq.errors as errors

#: One instance of every error class of rough_uq.errors, built as the code builds them.
INSTANCES = [
    errors.RoughUQError("plain"),
    errors.ConfigError("config.yaml: bad"),
    errors.InvalidParameterError("load.relative", -1.0, "a number > 0"),
    errors.MisplacedOptionError("--shards", 3, context="without --plan", allowed="only with --plan"),
    errors.ConvergenceError("no convergence", solution=None),
    errors.StudyFileError("locked", "results.h5"),
    errors.EstimationError("too few levels"),
    errors.PlanTooLargeError(n_planned=[10, 2], total=12.0, max_samples=5, tol=[0.1], advice="loosen it"),
    errors.ExecutorError("worker died"),
]


def test_every_error_class_is_covered():
    defined = {cls for _, cls in inspect.getmembers(errors, inspect.isclass)
               if issubclass(cls, errors.RoughUQError) and cls.__module__ == errors.__name__}
    assert defined == {type(error) for error in INSTANCES}


@pytest.mark.parametrize("error", INSTANCES, ids=lambda error: type(error).__name__)
def test_an_error_pickles_with_its_message_and_fields(error):
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is type(error) and copy.args == error.args and str(copy) == str(error)
    assert vars(copy) == vars(error)


def _refuse(value: float) -> None:
    raise errors.InvalidParameterError("load.relative", value, "a number > 0")


def test_an_error_raised_in_a_pool_worker_reaches_the_caller_as_itself():
    """It did not unpickle, and the pool said a worker had been "terminated abruptly"."""
    with ProcessPoolExecutor(1) as pool:
        with pytest.raises(errors.InvalidParameterError, match="load.relative: got -1.0") as caught:
            pool.submit(_refuse, -1.0).result()
    assert caught.value.name == "load.relative" and caught.value.value == -1.0


def test_checked_bool_takes_python_and_numpy_booleans_and_nothing_else():
    assert errors.checked_bool("flag", np.True_) is True and errors.checked_bool("flag", False) is False
    for value in ("no", "True", 0, 1, None, 1.0):
        with pytest.raises(errors.InvalidParameterError, match=r"^flag: got .*; allowed: True or False$"):
            errors.checked_bool("flag", value)


def test_checked_real_array_converts_real_numbers_and_refuses_what_it_would_have_to_guess():
    for value in (2, np.float32(2.5), [1, 2.5], np.arange(3, dtype=np.int8), ((1, 2), (3, 4))):
        converted = errors.checked_real_array("x", value, "numbers")
        assert converted.dtype == np.float64 and np.array_equal(converted, np.asarray(value, dtype=np.float64))
    for value in ("0.5", b"1", True, np.bool_(True), [1, "2"], [1, None], 1j, np.array([1j]), [[1], [2, 3]], 10**400):
        with pytest.raises(errors.InvalidParameterError, match="^x: got .*; allowed: numbers$"):
            errors.checked_real_array("x", value, "numbers")


@pytest.mark.parametrize(("value", "shown"), [
    (np.linspace(10, 40, 121).reshape(11, 11), "an array of shape (11, 11) (float64)"),
    (np.zeros(13, dtype=np.int32), "an array of shape (13,) (int32)"),
    (np.zeros((1, 2)), "an array of shape (1, 2) (float64)"),
    (np.array([1.0, 2.0]), "array([1., 2.])"),
    ([1, 2], "[1, 2]"),
])
def test_a_refused_array_is_shown_by_its_shape_where_its_values_would_take_lines(value, shown):
    # An 11 x 11 array of thresholds made a message of 22 lines.
    text = str(errors.InvalidParameterError("thresholds", value, "a 1-d array"))
    assert text == f"thresholds: got {shown}; allowed: a 1-d array"


def test_a_scalar_parameter_given_a_0d_array_says_that_a_number_is_meant():
    # "rms_height: got array(1.); allowed: a finite number > 0" read as a contradiction.
    from rough_uq.physics.solver import solve_contact
    from rough_uq.physics.surface import SurfaceSpectrum
    from rough_uq.problem.loads import RelativeLoad

    hint = "(a number, not a 0-d array: x.item() is one)"
    calls = {
        "rms_height": lambda: SurfaceSpectrum(system_size=1, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=np.array(1.0)),
        "system_size": lambda: solve_contact(np.zeros((8, 8)), system_size=np.array(2.0), mean_pressure=1.0),
        "tol": lambda: solve_contact(np.zeros((8, 8)), system_size=2.0, mean_pressure=1.0, tol=np.array(1e-8)),
        "load.relative": lambda: RelativeLoad(np.array(0.1)),
    }
    for name, call in calls.items():
        with pytest.raises(errors.InvalidParameterError) as info:
            call()
        assert info.value.name == name and str(info.value).endswith(hint), str(info.value)
    with pytest.raises(errors.InvalidParameterError) as info:  # a number out of range: no hint
        SurfaceSpectrum(system_size=1, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=-1.0)
    assert "0-d" not in str(info.value)


def test_a_warning_of_a_dataclass_post_init_points_at_the_users_line():
    # The warning pointed at "<string>:19", the __init__ dataclasses generate: one location for every caller, so
    # that Python's default filter showed it once for all of them.
    import rough_uq

    spectrum = rough_uq.SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32,
                                solver_tol=0.05)
    (warning,) = [w for w in caught if "MAX_SOLVER_TOL" in str(w.message)]
    assert warning.filename == __file__
    # Through dataclasses.replace (which the README suggests for a deeper max_level) it pointed at dataclasses.py.
    import dataclasses

    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataclasses.replace(problem, solver_tol=0.05)
    (warning,) = [w for w in caught if "MAX_SOLVER_TOL" in str(w.message)]
    assert warning.filename == __file__

"""The public Python API (``rough_uq.__all__``): names, light import, tiny runs, equality with the CLI pipeline."""

from __future__ import annotations

import ast
import builtins
import dataclasses
import functools
import math
import os
import re
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

import rough_uq
from rough_uq.multilevel.rates import fit_rates
from rough_uq.multilevel.statistics import level_statistics
from tests.mlmc_problems import shifted_screening
from rough_uq.problem.batch import STAGE_SCREENING
from rough_uq.problem.runs import contact_planning_rates, run_id
from rough_uq.problem.sampler import run_stage
from rough_uq.study.config import config_from_dict
from rough_uq.study.executors import Executor, SerialExecutor
from rough_uq.study.pipeline import Study, build_model, run_estimation, run_screening
from rough_uq.study.progress import Progress
from rough_uq.study.store import MemoryStore
from tests.study_configs import tiny_config, write_config

ROOT = Path(__file__).resolve().parent.parent

PUBLIC = [
    "__version__",
    "ContactProblem",
    "RelativeLoad",
    "AbsoluteLoad",
    "RunForecast",
    "ScreeningResult",
    "mlmc",
    "mc",
    "screen",
    "variance",
    "distribution",
    "DistributionResult",
    "EstimationResult",
    "TargetEstimate",
    "CdfEstimate",
    "Quantiles",
    "LevelStatistics",
    "Rates",
    "SurfaceSpectrum",
    "sample_surface",
    "sample_coupled",
    "solve_contact",
    "ContactSolution",
    "solve_load_curve",
    "LoadCurveSolution",
    "QOI_NAMES",
    "evaluate_qoi",
    "contact_area",
    "count_clusters",
    "label_clusters",
    "mean_gap",
    "max_pressure",
    "area_above",
    "RoughUQError",
    "InvalidParameterError",
    "ConvergenceError",
    "EstimationError",
    "PlanTooLargeError",
    "ExecutorError",  # the README's PoolExecutor example names it; it was only in rough_uq.study.executors
    "EstimationWarning",
]


def _problem(**overrides: object) -> rough_uq.ContactProblem:
    """A problem on grids 16, 32, 64 whose MLMC runs take about a second."""
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    options = dict(load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"], coarsest=16, max_level=2, seed=7)
    return rough_uq.ContactProblem(spectrum, **(options | overrides))


def _quickstart_problem(**overrides: object) -> rough_uq.ContactProblem:
    """The quickstart's surface and load in a box of 2 (k = 2/2/16), coarsest grid 32."""
    spectrum = rough_uq.SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1)
    options = dict(load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32, max_level=3, seed=1)
    return rough_uq.ContactProblem(spectrum, **(options | overrides))


def _tiny_problem(config: dict) -> rough_uq.ContactProblem:
    """The ContactProblem of ``tests.study_configs.tiny_config()`` (relative load, contact area in percent)."""
    surface = config["surface"]
    spectrum = rough_uq.SurfaceSpectrum(
        system_size=surface["system_size"], hurst=surface["hurst"], rms_height=surface["rms_height"],
        **surface["wavenumbers"],
    )
    return rough_uq.ContactProblem(
        spectrum,
        load=rough_uq.RelativeLoad(config["load"]["relative"]),
        qoi=list(config["qoi"]),
        coarsest=config["grid"]["coarsest"],
        max_level=config["grid"]["max_level"],
        seed=config["seed"],
        solver_tol=config["solver"]["tol"],
    )


# --------------------------------------------------------------------------
# Names and imports
# --------------------------------------------------------------------------


def test_public_names_are_pinned_and_resolve():
    assert rough_uq.__all__ == PUBLIC
    for name in PUBLIC:
        assert getattr(rough_uq, name) is not None, name
    assert set(PUBLIC) <= set(dir(rough_uq))
    # the package's own imports are not names a notebook's completion offers (``rough_uq.version`` was
    # importlib's function, not the version)
    assert not {"version", "importlib", "PackageNotFoundError", "TYPE_CHECKING", "annotations"} & set(dir(rough_uq))
    assert not hasattr(rough_uq, "version")
    assert rough_uq.mlmc is rough_uq.problem.runs.mlmc
    assert rough_uq.EstimationResult is rough_uq.multilevel.drivers.EstimationResult
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        rough_uq.not_a_name  # noqa: B018


def _modules_after(code: str) -> list[str]:
    probe = "import sys; " + code + "; print(sorted(m for m in {} if m in sys.modules))"
    heavy = ("pydantic", "h5py", "click", "rich", "yaml", "numba", "pyfftw")
    out = subprocess.run(
        [sys.executable, "-c", probe.format(heavy)], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return eval(out.stdout.strip())  # a printed list of str


def test_import_is_light_and_the_api_needs_no_edge_library():
    assert _modules_after("import rough_uq") == []
    # Using every public name loads the solver (numba; numba imports PyYAML itself), pyFFTW only at the first
    # transform, never pydantic, h5py, click or rich.
    used = _modules_after("import rough_uq; [getattr(rough_uq, n) for n in rough_uq.__all__]")
    assert "numba" in used and "pyfftw" not in used
    assert not {"pydantic", "h5py", "click", "rich"} & set(used)
    assert "pyfftw" in _modules_after("import rough_uq, numpy; rough_uq.sample_surface(rough_uq.SurfaceSpectrum("
                                      "system_size=1, k_l=1, k_r=1, k_s=4, hurst=0.8, rms_height=1), 16, "
                                      "numpy.random.default_rng(0))")


def test_the_loads_and_the_spectrum_need_no_numba():
    # The load range checks moved to rough_uq.problem.loads import the solver's limits where they run: a module
    # import of them loaded numba with every RelativeLoad.
    names = "rough_uq.RelativeLoad, rough_uq.AbsoluteLoad, rough_uq.SurfaceSpectrum"
    used = _modules_after(f"import rough_uq; {names}")
    assert "numba" not in used and "pyfftw" not in used  # pyFFTW at the first transform


def test_init_imports_no_edge_module():
    # The problem package is checked by tests/test_layering.py; __init__ only names modules lazily.
    tree = ast.parse((ROOT / "rough_uq" / "__init__.py").read_text())
    guarded = {
        id(child)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING"
        for child in ast.walk(node)
    }
    imported = [
        alias.name if isinstance(node, ast.Import) else node.module
        for node in ast.walk(tree)
        if id(node) not in guarded and isinstance(node, (ast.Import, ast.ImportFrom))
        for alias in node.names
    ]
    assert all(not (name or "").startswith("rough_uq") for name in imported), imported
    edge = ("rough_uq.study", "rough_uq.report", "rough_uq.cli")
    module_of = ast.literal_eval(next(
        node.value for node in tree.body
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "_EXPORTS"
        or isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "_EXPORTS"
    ))
    assert not [m for m in module_of.values() if m.startswith(edge)]


# --------------------------------------------------------------------------
# The problem
# --------------------------------------------------------------------------


def test_relative_load_conversion_and_model_match_the_pipeline():
    config = tiny_config(
        material={"e_star": 3.0},
        qoi={"contact_area": {"unit": "percent"}, "clusters": {"unit": "per_area", "connectivity": 8},
             "mean_gap": {}},
    )
    problem = dataclasses.replace(
        _tiny_problem(config), e_star=3.0, connectivity=8, qoi=("contact_area", "clusters", "mean_gap")
    )
    model = build_model(config_from_dict(config))
    assert problem.mean_pressure == model.mean_pressure
    assert problem.mean_pressure == pytest.approx(0.2 * 3.0 * np.sqrt(problem.spectrum.m2), rel=1e-14)
    assert problem.model == model  # every field, FFT wisdom aside
    absolute = build_model(config_from_dict(tiny_config(load={"absolute": 0.05})))
    assert absolute.mean_pressure == rough_uq.AbsoluteLoad(0.05).mean_pressure(spectrum=problem.spectrum, e_star=3.0)


def test_units_scale_the_quantities():
    spectrum = _problem().spectrum
    percent = _problem()
    fraction = _problem(units={"contact_area": "fraction"})
    assert fraction.units == (("contact_area", "fraction"),)
    assert percent.model.qoi_scales == (100.0,) and fraction.model.qoi_scales == (1.0,)
    clusters = _problem(qoi="clusters")
    assert clusters.qoi == ("clusters",) and clusters.qoi_units == ("per_area",)
    assert clusters.model.qoi_scales == (1.0 / spectrum.system_size**2,)


def test_max_pressure_is_in_the_unit_e_star_is_given_in_and_not_labelled_as_a_multiple_of_e_star():
    problem = _problem(qoi=["max_pressure"], e_star=210.0)
    assert problem.qoi_units == ("pressure",) and problem.model.qoi_scales == (1.0,)
    config = config_from_dict(tiny_config(qoi={"max_pressure": {}}, material={"e_star": 210.0}))
    assert config.qoi["max_pressure"].unit_label == "pressure"
    with pytest.raises(rough_uq.InvalidParameterError, match="pressure"):
        _problem(qoi=["max_pressure"], units={"max_pressure": "E*"})


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"load": 0.1}, "load"),
        ({"load": rough_uq.AbsoluteLoad}, "load"),
        ({"qoi": []}, "qoi"),
        ({"qoi": ["contact_area", "contact_area"]}, "qoi"),
        ({"qoi": ["area"]}, "qoi"),
        ({"coarsest": 15}, "coarsest"),
        ({"coarsest": 4}, "coarsest"),  # 4 / 2 = 2 does not resolve k_r = 2
        ({"units": {"contact_area": "per_area"}}, "units.contact_area"),
        ({"units": {"clusters": "absolute"}}, "units"),
        ({"e_star": 0}, "e_star"),
        ({"max_level": -1}, "max_level"),
        ({"max_level": 13}, "max_level"),  # 16 * 2**13 = 131072 > MAX_GRID; 2**1000 overflowed later
        ({"projection": "injection"}, "projection"),  # k_s = 8 is not below 16 / 2
        ({"connectivity": 6}, "connectivity"),
        ({"area_estimator": "perimeter"}, "area_estimator"),
        ({"qoi": ["area_above"]}, "critical_pressure"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"solver_tol": 1.0}, "solver_tol"),
        ({"max_iter": 0}, "max_iter"),
        ({"warm_start": "yes"}, "warm_start"),
        ({"threads": 0}, "threads"),
    ],
)
def test_invalid_settings_name_the_field(overrides, field):
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        _problem(**overrides)
    assert caught.value.name == field


def test_invalid_loads_and_arguments_name_the_field():
    for load, field in ((rough_uq.RelativeLoad, "load.relative"), (rough_uq.AbsoluteLoad, "load.absolute")):
        for value in (0.0, -1.0, float("nan"), "0.1"):
            with pytest.raises(rough_uq.InvalidParameterError) as caught:
                load(value)
            assert caught.value.name == field
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.ContactProblem("spectrum", load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=16)
    assert caught.value.name == "spectrum"
    problem = _problem()
    for call, field in (
        (lambda: rough_uq.mlmc(problem, tol=[0.5, 0.5]), "tol"),
        (lambda: rough_uq.mlmc(problem, tol=-1.0), "tol"),
        (lambda: rough_uq.mlmc("problem", tol=1.0), "problem"),
        (lambda: rough_uq.mc(problem, tol=1.0), "level"),
        (lambda: rough_uq.mc(problem, tol=1.0, level=3), "level"),
        (lambda: rough_uq.screen(problem, levels=2), "levels"),
        (lambda: rough_uq.screen(problem, levels=problem.max_level + 2), "levels"),
        (lambda: rough_uq.mlmc(problem, tol=1.0, screening="table"), "screening"),
    ):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == field


def test_screening_needs_three_levels_and_says_why_as_the_config_does():
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.screen(_problem(), levels=2)
    assert caught.value.name == "levels" and "fitted on levels >= 1, two of them at least" in str(caught.value)
    with pytest.raises(rough_uq.InvalidParameterError) as caught:  # said "at most max_level + 1 = 2", then ">= 3"
        rough_uq.screen(_problem(max_level=1), levels=2)
    # Named by the problem's max_level, not by a levels argument the caller may not have given.
    assert caught.value.name == "max_level" and caught.value.value == 1
    assert "a screening needs levels 0..2" in str(caught.value) and "mc(level=...), variance" in str(caught.value)
    with pytest.raises(rough_uq.InvalidParameterError, match="^max_level: got 1;"):
        rough_uq.screen(_problem(max_level=1))


#: Loads whose problem was built although every solve of it refuses the load (L = E* = rms_height = 1 in
#: _problem, so an absolute load is the dimensionless load; a relative one times sqrt(m2) = 18).
LOADS_NO_SOLVE_TAKES = {
    "dimensionless load 1.8e201": (rough_uq.RelativeLoad(1e200), "load.relative", "a dimensionless load"),
    "dimensionless load 1e300": (rough_uq.AbsoluteLoad(1e300), "load.absolute", "a dimensionless load"),
    "dimensionless load 1e60": (rough_uq.AbsoluteLoad(1e60), "load.absolute", "a dimensionless load"),  # a 'bug'
    "subnormal dimensionless load": (rough_uq.RelativeLoad(1e-310), "load.relative", "a dimensionless load"),
    "second load of a curve": (
        [rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(1e200)], "load.relative.1", "a dimensionless load"
    ),
    "infinite pressure": (rough_uq.RelativeLoad(1e308), "load.relative", "here inf"),  # was accepted as inf
    "total force overflows on 64^2 nodes": (rough_uq.AbsoluteLoad(1e305), "load.absolute", "64^2 nodes"),
}


@pytest.mark.parametrize("load, field, text", LOADS_NO_SOLVE_TAKES.values(), ids=LOADS_NO_SOLVE_TAKES.keys())
def test_a_load_no_solve_takes_is_refused_when_the_problem_is_built(load, field, text):
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        _problem(load=load)
    assert caught.value.name == field and text in caught.value.allowed


def test_the_load_range_is_the_solvers_less_the_margin_and_a_load_at_its_ends_is_solved():
    from rough_uq.physics.solver import MAX_DIMENSIONLESS_LOAD, MIN_DIMENSIONLESS_LOAD
    from rough_uq.problem.loads import LOAD_MARGIN

    lowest, highest = MIN_DIMENSIONLESS_LOAD * LOAD_MARGIN, MAX_DIMENSIONLESS_LOAD / LOAD_MARGIN
    for outside in (lowest / 1.001, highest * 1.001):
        with pytest.raises(rough_uq.InvalidParameterError, match=r"in \[2.2e-298, 1e\+15\]"):
            _problem(load=rough_uq.AbsoluteLoad(outside))
    # A sample's own RMS height leaves them inside the solver's range. The high end is taken at a loose solver
    # tolerance: at a tight one rounding keeps solves from it, and the problem is refused
    # (test_a_load_beyond_what_rounding_allows_...).
    for end, solver_tol in ((lowest, 1e-7), (highest, 1e-2)):
        problem = _problem(load=rough_uq.AbsoluteLoad(end), max_iter=2, solver_tol=solver_tol)
        for level in range(problem.max_level + 1):
            fine, coarse, _ = problem.sampler(STAGE_SCREENING)(level, np.arange(2))
            assert np.all(np.isfinite(fine)) and np.all(np.isfinite(coarse))


def test_a_load_beyond_what_rounding_allows_is_refused_when_the_problem_is_built_and_named_by_the_solver():
    # relative: 1e9 passed `roughuq validate`; every solve then ran max_iter (110 000 iterations with its retry)
    # and was stored as not converged.
    from rough_uq.physics.solver import max_convergent_load

    limit = max_convergent_load(1e-8)
    problem = _problem(solver_tol=1e-8)
    spectrum = problem.spectrum
    # The premise: solves at 10 times the limit stop above the tolerance, at a hundredth of it they converge.
    heights = rough_uq.sample_surface(spectrum, 64, np.random.default_rng(5))
    rms = float(np.std(heights))
    far = rough_uq.solve_contact(heights, system_size=1.0, mean_pressure=10 * limit * rms, tol=1e-8, max_iter=300)
    assert not far.converged and f"above {limit:.3g}" in far.message
    near = rough_uq.solve_contact(heights, system_size=1.0, mean_pressure=limit / 100 * rms, tol=1e-8)
    assert near.converged and "rounding of the pressures" not in near.message
    pressure = 2 * limit * spectrum.rms_height / spectrum.system_size
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        _problem(load=[rough_uq.AbsoluteLoad(1.0), rough_uq.AbsoluteLoad(pressure)], solver_tol=1e-8)
    assert caught.value.name == "load.absolute.1" and caught.value.value == pressure
    assert caught.value.allowed.startswith("a dimensionless load mean_pressure * system_size / (e_star * rms_height) "
                                           "at most 2.3e+9 at solver tol 1e-08; here it is 4.5e+9")
    _problem(load=rough_uq.AbsoluteLoad(pressure), solver_tol=1e-7)  # twice the limit of 1e-8, within that of 1e-7


@pytest.mark.parametrize("n", [16, 256])
def test_a_solve_takes_every_load_of_its_range_and_refuses_the_rest_by_name(n):
    """Loads from about 1e52 on 16^2 nodes (1e44 on 1024^2) to the old ceiling 1e100 ended in a ConvergenceError."""
    from rough_uq.physics.solver import MAX_DIMENSIONLESS_LOAD, MIN_DIMENSIONLESS_LOAD

    heights = rough_uq.sample_surface(_problem().spectrum, n, np.random.default_rng(3))
    rms = float(np.std(heights))
    for load in (MIN_DIMENSIONLESS_LOAD * 1.01, MAX_DIMENSIONLESS_LOAD / 1.01):
        solution = rough_uq.solve_contact(heights, mean_pressure=load * rms, system_size=1.0, max_iter=5)
        assert np.all(np.isfinite(solution.pressure)) and math.isfinite(solution.error)
    for load in (1e46, 1e60, 1e99):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            rough_uq.solve_contact(heights, mean_pressure=load * rms, system_size=1.0, max_iter=5)
        assert caught.value.name == "mean_pressure" and "1e+25]" in caught.value.allowed


def test_validate_refuses_the_loads_the_problem_refuses_with_the_same_message(tmp_path):
    from click.testing import CliRunner

    from rough_uq.cli import main

    problem = _tiny_problem(tiny_config())
    for value in (1e200, 1e-310, 1e308, [0.2, 1e200]):
        loads = [rough_uq.RelativeLoad(v) for v in value] if isinstance(value, list) else rough_uq.RelativeLoad(value)
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            dataclasses.replace(problem, load=loads)
        config = write_config(tmp_path / "load.yaml", tiny_config(load={"relative": value}))
        result = CliRunner().invoke(main, ["validate", str(config)])
        # The same message, after the name of the file (validate names the file of every refusal).
        assert result.exit_code == 2 and result.stderr == f"error: {config}: {caught.value}\n"


@pytest.mark.parametrize("run", ["mlmc", "mc", "variance", "distribution"])
@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("theta", "0.5"),
        ("theta", None),
        ("theta", [0.5]),
        ("theta", 1.0),
        ("max_cost", "10"),
        ("max_cost", True),
        ("max_cost", [1.0]),
        ("max_cost", 0.0),
        ("max_cost", float("nan")),
    ],
)
def test_settings_that_are_not_numbers_are_refused_by_name(run, field, value):
    # Strings and booleans are not converted; a list or None is an error naming the field, not a TypeError.
    arguments = {"tol": 50.0, "level": 0} if run == "mc" else {"tol": 50.0 if run != "distribution" else 0.5}
    if run == "distribution":
        arguments["thresholds"] = [10.0, 20.0]
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        getattr(rough_uq, run)(_problem(), **arguments, **{field: value})
    assert caught.value.name == field


def test_mlmc_options_are_checked_and_an_infinite_budget_is_no_budget():
    problem = _problem()
    for field, value in (("kurtosis_limit", -1.0), ("kurtosis_limit", "5"), ("kurtosis_limit", float("nan")),
                         ("kurtosis_limit", 0.5), ("richardson", "yes"), ("richardson", 1)):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            rough_uq.mlmc(problem, tol=5.0, **{field: value})
        assert caught.value.name == field
    # A kurtosis is at least 1: a limit of 0.5 (taken before) flagged every level.
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^kurtosis_limit: got 0.99; allowed: a number >= 1 "):
        rough_uq.mc(problem, tol=5.0, level=0, kurtosis_limit=0.99)
    unlimited = rough_uq.variance(problem, tol=50.0, max_cost=None)
    infinite = rough_uq.variance(problem, tol=50.0, max_cost=math.inf)  # was an OverflowError
    np.testing.assert_array_equal(infinite.estimate, unlimited.estimate)
    assert rough_uq.mlmc(problem, tol=5.0, max_cost=math.inf).estimate == rough_uq.mlmc(problem, tol=5.0).estimate
    # A finite budget too large to count samples in (1e308 / a cost of 1e-3 is inf) was an OverflowError.
    assert rough_uq.mlmc(problem, tol=5.0, max_cost=1e308).estimate == rough_uq.mlmc(problem, tol=5.0).estimate
    huge = rough_uq.variance(problem, tol=50.0, max_cost=1e308)
    np.testing.assert_array_equal(huge.estimate, unlimited.estimate)


def test_wrong_kinds_of_argument_are_refused_by_name_not_by_a_type_error():
    problem = _problem()
    for call, field in (
        (lambda: rough_uq.mlmc(problem, tol=2.0, executor="pool"), "executor"),  # was an AttributeError
        (lambda: rough_uq.distribution(problem, tol=0.3, thresholds="abc"), "thresholds"),  # a ValueError
        (lambda: rough_uq.distribution(problem, tol=2.0, thresholds=[10.0, 20.0]), "tol"),  # F is a probability
        (lambda: rough_uq.sample_surface(problem.spectrum, 16, None), "rng"),  # a TypeError
    ):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == field


def test_problem_is_frozen_and_hashable():
    problem = _problem()
    with pytest.raises(dataclasses.FrozenInstanceError):
        problem.seed = 3
    assert problem == _problem() and hash(problem) == hash(_problem())
    assert problem != _problem(seed=8)
    assert problem.grid(2) == 64


# --------------------------------------------------------------------------
# Tiny runs
# --------------------------------------------------------------------------


def test_mlmc_mc_screen_on_small_grids():
    problem = _problem()
    result = rough_uq.mlmc(problem, tol=2.0)
    assert result.method == "mlmc"
    assert result.estimate.shape == result.rmse.shape == (1,)
    assert result.levels.shape == result.n_samples.shape and result.levels[0] == 0
    assert 0 < result.estimate[0] < 100  # percent of the nominal area
    if result.tol_met:
        assert result.rmse[0] <= 2.0
    else:
        assert result.stop_reason in ("max_level", "max_cost")

    mc = rough_uq.mc(problem, tol=2.0, level=1)
    assert mc.levels.tolist() == [1] and mc.n_samples[0] >= 10
    assert mc.estimate.shape == (1,) and not mc.is_bias_estimated

    screening = rough_uq.screen(problem, levels=3, samples=6)
    assert screening.levels.tolist() == [0, 1, 2] and screening.n_samples.tolist() == [6, 6, 6]
    assert screening.statistics.mean_fine.shape == (3, 1)
    assert screening.rates.alpha.shape == (1,) and screening.n_not_converged == 0
    planned = rough_uq.mc(problem, tol=2.0, screening=screening)
    assert planned.is_bias_estimated and 0 <= planned.levels[0] <= problem.max_level


def test_screen_names_the_qois_in_its_diagnostics(monkeypatch):
    # The checks gave column indices ("for QoI [1]"); screen knows the names of its columns.
    from rough_uq.problem import runs

    seen = []
    real = runs.diagnose

    def spy(statistics, **options):
        seen.append(options)
        return real(statistics, **options)

    monkeypatch.setattr(runs, "diagnose", spy)
    problem = _problem(qoi=["contact_area", "mean_gap"])
    rough_uq.screen(problem, levels=3, samples=3)
    assert seen == [{"names": ("contact_area", "mean_gap")}] and problem.columns == ("contact_area", "mean_gap")


def test_the_warnings_of_runs_name_the_problems_columns():
    # The runs warned "for QoI [0] (ratio 1.82)" although the problem knows its columns.
    problem = _problem(qoi=["contact_area", "mean_gap"], coarsest=8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", rough_uq.EstimationWarning)
        rough_uq.mlmc(problem, tol=[2.0, 0.1])
        rough_uq.mc(problem, tol=[2.0, 0.1], level=1, kurtosis_limit=2.0)
    messages = [str(w.message) for w in caught]
    assert any(m.startswith("mlmc: level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for contact_area (ratio ") for m in messages)
    assert any(m.startswith("mc: kurtosis ") and " on level 1 for mean_gap exceeds 2; " in m for m in messages)
    assert not any("QoI [" in m for m in messages), messages


def test_a_column_past_full_contact_is_exact_and_the_others_are_screened():
    # Far past full contact the area is 100 % on every level, the gap is not: the screening failed with "cannot
    # fit alpha for contact_area"; the area is exact (no bias, no level variance) and the gap is fitted.
    from rough_uq.multilevel.rates import EXACT_RATE

    problem = _problem(qoi=["mean_gap", "contact_area"], coarsest=8, load=rough_uq.RelativeLoad(1e6))
    screening = rough_uq.screen(problem, levels=3, samples=3)
    assert screening.rates.alpha[1] == screening.rates.beta[1] == EXACT_RATE
    assert screening.rates.alpha[0] < EXACT_RATE
    alone = _problem(qoi=["contact_area"], coarsest=8, load=rough_uq.RelativeLoad(1e6))
    with pytest.raises(rough_uq.EstimationError, match="^contact_area took one value in every sample"):
        rough_uq.screen(alone, levels=3, samples=3)  # nothing at all to estimate


def test_same_seed_same_estimate_other_seed_other_estimate():
    first = rough_uq.mlmc(_problem(), tol=2.0)
    again = rough_uq.mlmc(_problem(), tol=2.0)
    np.testing.assert_array_equal(again.estimate, first.estimate)
    np.testing.assert_array_equal(again.n_samples, first.n_samples)
    other = rough_uq.mlmc(_problem(seed=8), tol=2.0)
    assert not np.array_equal(other.estimate, first.estimate)


class _Reversed(Executor):
    """Computes the items serially but yields them last first (as a pool may)."""

    def run(self, model, items):
        return reversed(list(SerialExecutor().run(model, items)))


def test_an_executor_computes_the_same_samples():
    problem = _problem()
    default = problem.sampler(STAGE_SCREENING)(1, np.arange(4))
    # Equal problems, not the same one: a problem gives back the samples it computed before (rough_uq.problem.kept).
    reordered = _problem().sampler(STAGE_SCREENING, executor=_Reversed())(1, np.arange(4))
    for mine, theirs in zip(default, reordered):
        np.testing.assert_array_equal(theirs, mine)
    mc = rough_uq.mc(problem, tol=2.0, level=0)
    assert rough_uq.mc(_problem(), tol=2.0, level=0, executor=_Reversed()).estimate == mc.estimate


def test_a_sampler_warms_the_kernels_before_its_first_sample_in_this_process(monkeypatch):
    # Loading numba's kernels (about 0.3 s in a fresh process) must not be timed as a sample.
    import rough_uq.problem.contact as contact_module

    calls = []
    monkeypatch.setattr(contact_module, "warm_up", lambda model: calls.append(model))
    problem = _problem()
    sampler = problem.sampler(STAGE_SCREENING)
    sampler(1, np.arange(2))
    assert calls == [problem.model]
    sampler(0, np.arange(3))
    assert len(calls) == 1  # once per sampler
    on_executor = _problem().sampler(STAGE_SCREENING, executor=_Reversed())  # samples not kept from above
    on_executor(1, np.arange(3))  # the executor's workers warm up themselves
    assert len(calls) == 1


@pytest.mark.slow
def test_a_process_pool_computes_the_same_estimate():
    from rough_uq.study.executors import PoolExecutor

    problem = _problem()
    serial = rough_uq.mlmc(problem, tol=2.0)
    with PoolExecutor(2) as pool:
        pooled = rough_uq.mlmc(problem, tol=2.0, executor=pool)
    np.testing.assert_array_equal(pooled.estimate, serial.estimate)
    np.testing.assert_array_equal(pooled.n_samples, serial.n_samples)


def test_non_converged_samples_are_reported():
    # In the results too: a notebook that filters warnings saw tol_met True and nothing of the unconverged solves.
    problem = _problem(max_iter=1, solver_tol=1e-12)
    with pytest.warns(rough_uq.EstimationWarning, match="did not converge"):
        result = rough_uq.mc(problem, tol=100.0, level=0, n_initial=2)
    assert result.n_not_converged == int(result.n_samples.sum()) == 2
    runs = [lambda: rough_uq.mlmc(problem, tol=100.0), lambda: rough_uq.variance(problem, tol=1e6, n_initial=4),
            lambda: rough_uq.distribution(problem, tol=0.5, thresholds=[0.0, 50.0, 100.0], n_initial=4)]
    for run in runs:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rough_uq.EstimationWarning)
            estimate = run()
        n_samples = getattr(estimate, "cdf", estimate).n_samples
        assert 0 < estimate.n_not_converged <= int(np.sum(n_samples))
    assert rough_uq.mc(_problem(), tol=100.0, level=0, n_initial=2).n_not_converged == 0


# --------------------------------------------------------------------------
# Equal to the CLI pipeline
# --------------------------------------------------------------------------


def test_api_computes_what_the_pipeline_computes(monkeypatch):
    # Both plan FFTs the same way (the pipeline otherwise measures plans per machine).
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", "estimate")
    config = tiny_config()
    study = Study(config_from_dict(config), MemoryStore(qoi_names=("contact_area",)))
    quiet = Progress()
    outcome = run_screening(study, executor=SerialExecutor(), progress=quiet)
    problem = _tiny_problem(config)
    screening = rough_uq.screen(problem, levels=config["screening"]["levels"], samples=config["screening"]["samples"])
    np.testing.assert_array_equal(screening.statistics.mean_diff, outcome.statistics.mean_diff)
    np.testing.assert_array_equal(screening.statistics.var_diff, outcome.statistics.var_diff)
    np.testing.assert_array_equal(screening.statistics.mean_cost, outcome.statistics.mean_cost)

    options = dict(n_initial=config["estimation"]["initial_samples"], batch_size=config["estimation"]["batch_size"])
    for method, level in (("mlmc", None), ("mc", None), ("mc", 1)):
        record = run_estimation(
            study, method=method, tol=np.array([2.0]), executor=SerialExecutor(), progress=quiet, level=level
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", rough_uq.EstimationWarning)
            if method == "mlmc":
                result = rough_uq.mlmc(problem, tol=2.0, screening=screening, **options)
            elif level is None:
                result = rough_uq.mc(problem, tol=2.0, screening=screening, **options)
            else:
                result = rough_uq.mc(problem, tol=2.0, level=level, **options)
        # The same diagnostics, as warnings here and in the run record there.
        outcome = record.outcome
        assert list(dict.fromkeys(str(w.message) for w in caught)) == [d.message for d in outcome.diagnostics], (
            method, level)
        assert tuple(result.levels.tolist()) == outcome.levels, (method, level)
        assert tuple(result.n_samples.tolist()) == outcome.n_samples, (method, level)
        assert tuple(result.estimate.tolist()) == outcome.estimate, (method, level)
        assert tuple(result.rmse.tolist()) == outcome.rmse, (method, level)
        # Plain MC's predicted cost: MLMC's was priced on the run's finest level in Python, on the level the
        # screening needs by roughuq (0.0347 against 0.0202 on the quickstart at tol 0.5).
        assert result.mc_cost == pytest.approx(outcome.mc_cost, rel=1e-12), (method, level)
        name = run_id(method, ("contact_area",), [2.0], 0.5, level)
        assert run_stage(method, name) == record.stage


# --------------------------------------------------------------------------
# The README's example
# --------------------------------------------------------------------------


def _readme_python_blocks() -> list[str]:
    """The Python code blocks of the README's section "From Python", in order."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## From Python\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_from_python_example_runs(capsys):
    block = _readme_python_blocks()[0]
    namespace: dict[str, object] = {}
    exec(compile(block, "README.md (From Python)", "exec"), namespace)
    result = namespace["result"]
    assert isinstance(result, rough_uq.EstimationResult)
    assert result.tol_met and result.rmse[0] <= 0.5
    assert str(result.stop_reason) in capsys.readouterr().out


def test_every_readme_from_python_block_runs_in_order(capsys):
    # The section's later blocks use the first one's problem, as a notebook would run them; the worker-pool
    # block runs nothing here (its `if __name__ == "__main__":` guard; tests/test_executors.py runs pools).
    namespace: dict[str, object] = {"__name__": "readme"}
    blocks = _readme_python_blocks()
    assert len(blocks) >= 5
    for block in blocks:
        exec(compile(block, "README.md (From Python)", "exec"), namespace)
    assert isinstance(namespace["screening"], rough_uq.ScreeningResult)
    assert isinstance(namespace["forecast"], rough_uq.RunForecast)
    assert isinstance(namespace["var"], rough_uq.TargetEstimate) and namespace["var"].tol_met
    law = namespace["law"]
    assert isinstance(law, rough_uq.DistributionResult) and law.cdf.tol_met
    assert np.all(np.isfinite(law.quantiles().values))
    assert "[mlmc contact_area=0.5] done" in capsys.readouterr().err


def test_the_package_docstring_example_imports_every_name_it_uses():
    # The example called numpy.linspace without `import numpy`.
    example = rough_uq.__doc__.split("::\n", 1)[1].split("\n\n", 1)[0]
    tree = ast.parse(textwrap.dedent(example))
    bound = {alias.asname or alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
             for alias in node.names}
    bound |= {node.id for node in ast.walk(tree) if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store)}
    used = {node.id for node in ast.walk(tree) if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load)}
    assert {"numpy", "rough_uq"} <= used
    assert used - bound - set(dir(builtins)) == set()


def test_readme_pool_example_runs_as_a_script(tmp_path):
    # The recipe had no `if __name__ == "__main__":`; as a script, every spawned worker re-ran it and it failed.
    (block,) = [block for block in _readme_python_blocks() if "PoolExecutor" in block]
    assert 'if __name__ == "__main__":' in block and "PoolExecutor(2)" in block
    script = tmp_path / "pool.py"
    script.write_text(block)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                            timeout=300, env=env)
    assert result.returncode == 0, result.stderr
    estimate, rmse = (float(text.strip("[]")) for text in result.stdout.split())
    assert 0 < estimate < 100 and 0 < rmse <= 0.5


def test_a_screening_forecasts_what_mlmc_draws_first_and_what_it_costs():
    """Python runs started without a word of what they would take (a variance run took 11 minutes)."""
    from rough_uq.multilevel.drivers import PlanUpdated, iter_mlmc

    problem = _problem(max_level=3)
    screening = rough_uq.screen(problem, levels=3, samples=10)
    assert screening.seconds_per_cost > 0
    forecast = screening.forecast(tol=1.0)
    assert forecast.is_bias_met and forecast.levels.tolist() == list(range(len(forecast.n_samples)))
    assert forecast.cpu_seconds == pytest.approx(forecast.cost * screening.seconds_per_cost)
    assert forecast.mc_cost > 0 and forecast.mc_cpu_seconds == pytest.approx(forecast.mc_cost *
                                                                             screening.seconds_per_cost)
    # The plan the run starts from (its first PlanUpdated, with the problem's cost rate beyond the screened levels
    # that mlmc passes), and the costs of those samples.
    planned = contact_planning_rates(problem.model, screening.statistics, 3)
    assert planned.gamma_beyond > planned.gamma
    events = iter_mlmc(problem.sampler(1), tol=np.array([1.0]), screening=screening.statistics, max_level=3,
                       coarsest_level=None, gamma_beyond=planned.gamma_beyond)
    first = next(event for event in events if isinstance(event, PlanUpdated))
    events.close()
    assert first.n_planned.tolist() == forecast.n_samples.tolist()
    levels = np.arange(len(forecast.n_samples))
    model = np.where(levels < 3, 0.0, planned.cost_model(3))
    costs = np.where(levels < 3, screening.statistics.mean_cost[np.minimum(levels, 2)], model)
    assert forecast.cost == pytest.approx(float(np.dot(forecast.n_samples, costs)))
    with pytest.raises(rough_uq.InvalidParameterError, match="^theta: "):
        screening.forecast(tol=1.0, theta=1.5)
    # Printed, it names the levels with their counts (the repr showed n_samples=array([...]) and 16-digit costs).
    assert repr(forecast).startswith(f"RunForecast(levels={forecast.levels.tolist()}, "
                                     f"n_samples={forecast.n_samples.tolist()}, cost={forecast.cost:.3g}, ")
    assert repr(forecast).endswith(f"is_bias_met={forecast.is_bias_met})") and "array(" not in repr(forecast)


def test_a_forecast_previews_the_run_of_a_deeper_max_level_the_refusal_suggests():
    # "or raise the problem's max_level (the same screening serves it)", but the forecast knew only the screened
    # problem's max_level. Synthetic screening: level means 0.3 / 0.15 on levels 1 / 2, max_level 2 misses tol 0.2.
    problem = _problem(max_level=2)
    statistics = level_statistics(**shifted_screening((0.0, 0.3, 0.15), seed=5))
    screening = dataclasses.replace(rough_uq.screen(problem, levels=3, samples=4), statistics=statistics,
                                    rates=fit_rates(statistics))
    shallow, deep = screening.forecast(tol=0.2), screening.forecast(tol=0.2, max_level=5)
    assert not shallow.is_bias_met and deep.is_bias_met and len(deep.n_samples) > len(shallow.n_samples)
    served = dataclasses.replace(screening, problem=dataclasses.replace(problem, max_level=5))
    assert repr(served.forecast(tol=0.2)) == repr(deep)
    previews = r"its forecast\(tol, max_level=...\) previews the run"
    with pytest.raises(rough_uq.EstimationError, match=previews) as caught:
        rough_uq.mlmc(problem, tol=0.2, screening=screening)
    # The forecast of the refused tolerance said is_bias_met=False and nothing of why or what would do: it names the
    # bias and the smallest reachable tolerance, the numbers of mlmc's refusal.
    bias, reachable = shallow.bias[0], shallow.reachable_tol[0]
    assert f"bias of contact_area={bias:.3g};" in str(caught.value)
    assert f"about contact_area={reachable:.3g}," in str(caught.value)
    assert repr(shallow).endswith(f"is_bias_met=False, bias=[{bias:.3g}], reachable_tol=[{reachable:.3g}])")
    assert deep.reachable_tol.tolist() == [0.2] and "reachable_tol" not in repr(deep)
    assert screening.forecast(tol=reachable).is_bias_met
    with pytest.raises(rough_uq.InvalidParameterError, match="^max_level: got 1; allowed: an integer >= 2"):
        screening.forecast(tol=0.2, max_level=1)


def test_mc_from_a_screening_with_a_flat_bias_plans_with_the_rate_mlmc_runs_use():
    # Level means -0.09, +0.084 (alpha 0.1): the bias |E[Y_2]| / (2^0.1 - 1) = 1.2 sent MC to max_level with a
    # bias too large for tol 1 ("bias" stop); MLMC runs floor alpha at 0.5 (bias 0.2) and so does MC's plan now.
    statistics = level_statistics(**shifted_screening((0.0, -0.09, 0.085), seed=3))
    assert 0 < fit_rates(statistics).alpha[0] < 0.5
    result = rough_uq.mc(_problem(), tol=1.0, screening=statistics)
    assert 0.084 / (2**0.5 - 1) <= result.bias_estimate[0] < 0.3  # at least the data's tail sum with alpha 0.5
    assert result.stop_reason == "tol_met" and result.tol_met


def test_a_distribution_stopped_on_terms_within_their_noise_advises_more_samples():
    # The quickstart problem on levels 0..3: the level-3 terms are noise and the bias the level-1 term at the
    # floor rate; the not-met warning said "the bias needs a grid finer than the problem's max_level" only.
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=0.004)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32,
                                      max_level=3, seed=12345)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", rough_uq.EstimationWarning)
        law = rough_uq.distribution(problem, tol=0.1, thresholds=np.linspace(17, 24, 29), n_initial=10)
    assert law.cdf.stop_reason == "max_level" and law.cdf.noisy_bias_groups == (0,)
    messages = [str(w.message) for w in caught]
    assert any("rests on level terms within their noise" in m for m in messages)
    assert any(m.startswith("distribution of contact_area: tolerance not met (max_level)") and m.endswith(
        "the bias estimate rests on level terms within their noise (see the warning): raise n_initial to measure "
        "it, loosen tol or raise max_level") for m in messages), messages


def test_mc_from_a_screening_whose_bias_grows_says_to_pass_a_level():
    # |E[Y_l]| grows with l (alpha < 0): no level meets a bias tolerance, so MC cannot choose one.
    statistics = level_statistics(**shifted_screening((0.0, 0.1, 0.4), seed=3))
    with pytest.raises(rough_uq.EstimationError, match=r"alpha = -[0-9.]+\) does not decrease .*; pass level="):
        rough_uq.mc(_problem(), tol=0.5, screening=statistics)
    # MLMC too, as roughuq mlmc (it ran at the floor rate 0.5 and reported its tolerance met).
    with pytest.raises(rough_uq.EstimationError, match=r"alpha = -[0-9.]+\) does not decrease .*mc\(level=\.\.\.\)"):
        rough_uq.mlmc(_problem(), tol=0.5, screening=statistics)


def test_a_tolerance_out_of_reach_is_refused_before_its_samples_are_drawn():
    # 1e-6 percentage points of contact area need some 1e11 samples: the first plan says so, and the run stops
    # there instead of computing for days (roughuq refuses such a forecast too).
    problem = _problem()
    mlmc_run = functools.partial(rough_uq.mlmc, problem, tol=1e-6)
    mc_run = functools.partial(rough_uq.mc, problem, tol=1e-6, level=0)
    for run in (mlmc_run, mc_run):
        with pytest.raises(rough_uq.PlanTooLargeError, match=r"needs about [0-9.e+]+ samples .*max_samples = 10000000"):
            run()
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            run(max_samples=0)
        assert caught.value.name == "max_samples"
    with pytest.warns(rough_uq.EstimationWarning, match=r"^mlmc: from the samples so far the bias on max_level"), \
            pytest.warns(rough_uq.EstimationWarning, match=r"^mlmc: tolerance not met \(max_cost\): RMSE "):
        result = rough_uq.mlmc(problem, tol=1e-6, max_samples=None, max_cost=0.5)  # a budget instead
    assert result.stop_reason == "max_cost"


def test_a_bias_the_screening_predicts_beyond_max_level_is_refused_as_roughuq_refuses_it():
    # Level means 0.4, 0.2 (alpha 1): the bias on level 2 is 0.2, out of reach of tol 0.1 (share 0.071). MLMC
    # and MC from such a screening planned millions of samples for the statistical error, and ran for hours.
    statistics = level_statistics(**shifted_screening((0.0, 0.4, 0.2), seed=5))
    refusal = (r"^tol contact_area=0.1 cannot be reached: on the finest grid allowed \(max_level = 2, 64\^2\) the "
               r"screening predicts a bias of contact_area=(0.2\d*); the smallest reachable tolerance is about "
               r"contact_area=([0-9.]+), a prediction from 20 screened samples per level"
               r".*raise the problem's max_level")
    for run in (rough_uq.mlmc, rough_uq.mc):
        with pytest.raises(rough_uq.EstimationError, match=refusal) as caught:
            run(_problem(), tol=0.1, screening=statistics)
        bias, reachable = map(float, re.match(refusal, str(caught.value)).groups())
        assert ("plain MC takes as its bias" in str(caught.value)) == (run is rough_uq.mc)
        assert bias / math.sqrt(0.5) <= reachable <= 1.05 * bias / math.sqrt(0.5)  # rounded up to 2 digits
    result = rough_uq.mc(_problem(), tol=0.1, screening=statistics, level=2)  # a level of one's choice: no bias model
    assert not result.is_bias_estimated


def test_the_reachable_tolerance_of_a_column_without_bias_is_the_one_asked():
    # A load curve's full-contact column has no bias (100 % on every level): the refusal proposed
    # "contact_area@5.0=0", a tolerance no run takes. It now keeps the tolerance asked there.
    biased = shifted_screening((0.0, 0.4, 0.2), seed=5)
    unbiased = shifted_screening((0.0, 0.0, 0.0), seed=6, noise=0.0)
    columns = {key: [np.column_stack(pair) for pair in zip(biased[key], unbiased[key])] for key in ("fine", "coarse")}
    statistics = level_statistics(**columns, cost=biased["cost"])
    problem = _problem(load=[rough_uq.RelativeLoad(0.2), rough_uq.RelativeLoad(5.0)])
    with pytest.raises(rough_uq.EstimationError) as caught:
        rough_uq.mlmc(problem, tol=0.1, screening=statistics)
    proposed = re.search(r"the smallest reachable tolerance is about (.*), a prediction", str(caught.value)).group(1)
    # (grouped as --tol takes it: the QoI's first value, then the column set apart)
    assert re.fullmatch(r"contact_area=0\.[0-9]+, contact_area@5\.0=0\.1", proposed), proposed
    # The column that blocks is named: the proposal alone did not say which one it was.
    assert "tol contact_area=0.1 cannot be reached for contact_area@0.2: on the finest grid" in str(caught.value)


def test_the_proposed_tolerance_keeps_the_columns_that_do_not_block():
    # The refusal proposed every column's bias floor: a mean gap asked at 2.2e-06 came back as 7.8e-09, and the
    # proposal was then refused as a plan of 2.8e7 samples (config fuzz, 2026-11-28).
    from types import SimpleNamespace

    from rough_uq.multilevel.allocation import reachable_tolerance

    prediction = SimpleNamespace(bias=np.array([0.024, 5.5e-9, 0.0]), theta=0.5)
    proposed = reachable_tolerance(prediction, np.array([0.02, 2.2e-6, 0.3]))
    np.testing.assert_allclose(proposed, [0.034, 2.2e-6, 0.3])  # 0.024 / sqrt(0.5) = 0.0339, rounded up
    np.testing.assert_allclose(reachable_tolerance(prediction), [0.034, 7.8e-9, 0.0])  # without a request: floors


def test_the_blocking_columns_are_named_only_where_a_bias_exceeds_its_share():
    from types import SimpleNamespace

    from rough_uq.problem.runs import blocking_text

    def text(bias, tol):
        return blocking_text(["a", "b", "c"], SimpleNamespace(bias=np.array(bias), theta=0.5), np.array(tol))

    assert text([1.0, 0.01, 0.5], [1.0, 1.0, 0.5]) == " for a, c"  # 1 > sqrt(0.5), 0.5 > sqrt(0.5) / 2
    assert text([1.0, 1.0, 1.0], [1.0, 1.0, 1.0]) == ""  # every column: the tolerance as a whole
    assert text([np.nan, 0.01, 0.01], [1.0, 1.0, 1.0]) == ""  # no column named: no dangling " for "


def test_a_run_without_a_screening_warns_of_a_bias_out_of_reach_before_drawing_its_plan():
    # tol 0.001 on max_level 2: the first samples put the bias far above its share, and the plan that follows
    # asked for millions of samples for the statistical error, in silence (a notebook cell just hung).
    class StopAtSecondPlan(Progress):
        def plan(self, levels, n_planned, n_done):
            self.is_replanned = sum(n_done) > 0

        def advance(self, level, n):
            if self.is_replanned:
                raise KeyboardInterrupt

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", rough_uq.EstimationWarning)
        with pytest.raises(KeyboardInterrupt):
            rough_uq.mlmc(_quickstart_problem(max_level=2), tol=0.001, progress=StopAtSecondPlan())
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1 and re.match(
        r"mlmc: from the samples so far the bias on max_level = 2 is about contact_area=[0-9.]+, above its share "
        r"sqrt\(theta\) tol = contact_area=0.000707: the run will likely stop at max_level with its tolerance not "
        r"met, after the \d{5,} samples it now plans", messages[0]), messages


def test_a_finest_mean_that_changes_sign_does_not_make_a_fast_decay():
    # The quickstart surface on grids 32, 64, 128 (seed 2): level means -0.237, +0.050 fitted alpha 2.26 and the
    # run reported a bias of 0.013 and its tolerance met; the finer grids' means (+0.115, +0.080, +0.045 on
    # 128^2-512^2, a reference of 10 000 samples per level) put the bias of 128^2 at 0.125 or more.
    problem = _quickstart_problem(max_level=2, seed=2)
    with pytest.warns(rough_uq.EstimationWarning, match=r"^mlmc: tolerance not met \(max_level\)"):
        result = rough_uq.mlmc(problem, tol=0.2)
    assert result.levels.tolist() == [0, 1, 2] and result.rates.levels_alpha == ((1, 2),)
    assert result.bias_estimate[0] > 0.125 and not result.tol_met


def test_printed_solutions_summarise_instead_of_dumping_their_fields():
    # repr(ContactSolution) printed its three (n, n) arrays: some 30 lines of numbers in a notebook.
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    heights = rough_uq.sample_surface(spectrum, 32, np.random.default_rng(1))
    solution = rough_uq.solve_contact(heights, system_size=1.0, mean_pressure=0.1 * spectrum.rms_slope)
    text = repr(solution)
    assert re.fullmatch(r"ContactSolution\(grid=32\^2, converged=True, n_iter=\d+, error=[0-9.e-]+, "
                        r"path='preconditioned', contact_fraction=0\.\d+, approach=[0-9.e-]+\)", text), text
    assert f"contact_fraction={np.mean(solution.pressure > 0):.4g}" in text
    stopped = rough_uq.solve_contact(heights, system_size=1.0, mean_pressure=0.1 * spectrum.rms_slope, max_iter=2)
    assert repr(stopped).endswith(f", n_restarts={stopped.n_restarts}, message={stopped.message!r})")
    curve = rough_uq.solve_load_curve(heights, system_size=1.0, mean_pressures=[0.05, 0.1])
    assert repr(curve) == (f"LoadCurveSolution(mean_pressures=[0.05, 0.1], n_iter={curve.n_iter.tolist()}, "
                           "converged=[True, True])")


def test_a_printed_result_shows_the_estimate_not_the_statistics_arrays():
    result = rough_uq.mlmc(_problem(), tol=2.0)
    text = repr(result)
    # Four significant digits: 20.148 +- 0.30 printed estimate=[20.1], a digit short of what its error supports.
    assert f"estimate=[{result.estimate[0]:.4g}]" in text and "stop_reason=" in text
    assert f"rmse=[{result.rmse[0]:.3g}]" in text and f"tol_met={result.tol_met}" in text  # the RMSE was left out
    assert "statistics=" not in text and "rates=" not in text and len(text) < 360
    # It printed bias=[..], which is no attribute of the result (bias_estimate is).
    assert f"stat_error=[{result.stat_error[0]:.3g}], bias_estimate=[{result.bias_estimate[0]:.3g}]" in text
    assert "units=('percent',)" in text and result.units == ("percent",)


def test_a_printed_mc_result_on_a_given_level_says_its_bias_is_not_estimated():
    # It printed rmse=[0.398] next to tol_met=True on 16^2, whose estimate (32.9 %) was 12 points above 256^2's.
    result = rough_uq.mc(_problem(), tol=2.0, level=0)
    text = repr(result)
    assert not result.is_bias_estimated and result.tol_met
    assert f"stat_error=[{result.stat_error[0]:.3g}], bias_estimate='not estimated'" in text and "rmse=" not in text


def test_results_name_their_columns_and_units():
    problem = _problem(load=[rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(0.2)], qoi=["contact_area", "clusters"],
                       units={"clusters": "absolute"})
    assert problem.column_units == ("percent", "percent", "absolute", "absolute")
    result = rough_uq.variance(problem, tol=50.0)  # printed four unlabelled numbers
    squares = ("percent^2", "percent^2", "absolute^2", "absolute^2")  # a variance is in its QoI's unit squared
    assert result.qoi_names == problem.columns and result.units == squares
    assert repr(result).startswith(f"TargetEstimate(qoi_names={problem.columns!r}, units={squares!r}, ")


@pytest.mark.filterwarnings("ignore::rough_uq.errors.EstimationWarning")  # weakly coupled clusters: beside the point
def test_a_printed_result_of_many_columns_shows_numbers():
    # Eight columns (two QoIs at four loads) printed estimate=<8 values>, rmse=<8 values>: no number at all.
    loads = [rough_uq.RelativeLoad(r) for r in (0.05, 0.1, 0.2, 0.4)]
    result = rough_uq.variance(_problem(load=loads, qoi=["contact_area", "clusters"]), tol=50.0)
    text = repr(result)
    assert "values>" not in text and "columns>" not in text
    assert f"estimate=[{', '.join(f'{value:.4g}' for value in result.estimate)}]" in text
    assert f"qoi_names={result.qoi_names!r}" in text
    # Beyond twelve, the first and last three with their count (a CDF of 121 thresholds).
    from rough_uq.multilevel.statistics import names_summary, values_summary

    assert values_summary(np.arange(13.0)) == "[0, 1, 2, ..., 10, 11, 12 (13 values)]"
    assert names_summary(tuple("abcdefghijklm")) == "('a', 'b', 'c', ..., 'k', 'l', 'm' (13 columns))"
    assert values_summary(np.arange(12.0)).count(",") == 11 and names_summary(("a",)) == "('a',)"


def test_the_default_units_given_or_not_make_the_same_problem():
    # units={"contact_area": "percent"} (the default) made a problem unequal to the one without units.
    assert _problem(units={"contact_area": "percent"}) == _problem()
    both = _problem(qoi=["clusters", "contact_area"], units={"clusters": "absolute", "contact_area": "percent"})
    assert both.units == (("clusters", "absolute"),) and both.qoi_units == ("absolute", "percent")
    # A QoI dropped by dataclasses.replace leaves no unit behind (with every unit stored, its default was refused).
    assert dataclasses.replace(_problem(qoi=["clusters", "contact_area"]), qoi=["contact_area"]) == _problem()


def test_a_unit_given_twice_is_refused():
    # [("contact_area", "fraction"), ("contact_area", "percent")]: the last pair won, silently.
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^units: .*given twice: contact_area"):
        _problem(units=[("contact_area", "fraction"), ("contact_area", "percent")])


def test_a_qoi_mapping_of_settings_is_refused_pointing_to_the_arguments():
    # qoi={"contact_area": {"unit": "fraction", ...}} as in the config file was read as its keys, settings lost.
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^qoi: .*not a mapping of settings.*units=") as caught:
        _problem(qoi={"contact_area": {"unit": "fraction", "tol": 0.005}})
    assert caught.value.name == "qoi"


#: The refusal of a plan beyond the sample limit.
TOO_MANY_SAMPLES = r"needs about [0-9.e+]+ samples .*max_samples = 10000000"


def test_variance_and_distribution_refuse_a_tolerance_out_of_reach_before_drawing_its_samples():
    problem = _problem()
    thresholds = np.linspace(20, 60, 41)
    for run in (
        functools.partial(rough_uq.variance, problem, tol=1e-4),
        functools.partial(rough_uq.distribution, problem, tol=1e-5, thresholds=thresholds),
    ):
        with pytest.raises(rough_uq.PlanTooLargeError, match=TOO_MANY_SAMPLES) as caught:
            run()
        assert str(caught.value).startswith("tol ") and "--tol" not in str(caught.value)  # the argument's name
        assert caught.value.total > caught.value.max_samples == 10_000_000
        assert caught.value.total == sum(caught.value.n_planned) and caught.value.tol[0] == run.keywords["tol"]
        with pytest.raises(rough_uq.InvalidParameterError, match="max_samples"):
            run(max_samples=0)


def test_the_api_warns_before_solves_that_exceed_the_machines_memory(monkeypatch):
    # The CLI warned before a level whose solves exceed physical memory; rough_uq.mc on 8192^2 (10.7 GB a solve)
    # went on silently until the machine swapped or the solve died.
    import rough_uq.problem.contact as contact_module
    from rough_uq.problem.memory import solver_memory_bytes

    monkeypatch.setattr(contact_module, "physical_memory_bytes", lambda: solver_memory_bytes(32) - 1)
    with pytest.warns(rough_uq.EstimationWarning) as caught:
        rough_uq.mc(_problem(), tol=2.0, level=1)
    (text,) = [str(w.message) for w in caught if "memory" in str(w.message)]  # once, not per batch
    assert text.startswith("level 1 (grid 32 x 32) needs about 0.156 MiB per solve (20 float64 arrays of n^2), "
                           "but this machine has 0.156 MiB: stay at level <= 0 "
                           "(a smaller max_level, or mc's level=)"), text
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rough_uq.mc(_problem(), tol=2.0, level=0)  # 16^2 fits
    # A screening samples levels 0..2 whatever: "stay at level <= 0" was advice it could not take.
    with pytest.warns(rough_uq.EstimationWarning) as caught:
        rough_uq.screen(_problem(), levels=3, samples=2)
    texts = [str(w.message) for w in caught if "memory" in str(w.message)]
    assert texts and all("use a smaller coarsest" in text for text in texts), texts

    class TwoWorkers(_Reversed):
        n_workers = 2

    monkeypatch.setattr(contact_module, "physical_memory_bytes", lambda: solver_memory_bytes(32) * 3 // 2)
    with pytest.warns(rough_uq.EstimationWarning, match=r"x 2 workers = .*: use an executor with n_workers = 1"):
        rough_uq.mc(_problem(), tol=2.0, level=1, executor=TwoWorkers())

    class Remote(TwoWorkers):
        runs_here = False  # a dask cluster's workers run on other machines

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rough_uq.mc(_problem(), tol=2.0, level=1, executor=Remote())

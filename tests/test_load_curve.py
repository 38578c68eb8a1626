"""Load curves: warm-started sequences of solves equal independent solves; curve configs, problems and reports."""

from __future__ import annotations

import dataclasses

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


def test_guesses_per_load_replace_the_sequence():
    # Each load starts from its own guess (e.g. the coarse solution): exactly the independent warm solve.
    from rough_uq.physics.surface import sample_coupled

    _, size, slope, _, rng = random_surface(400, grids=(64,))
    spectrum = SurfaceSpectrum(system_size=size, k_l=1, k_r=2, k_s=40, hurst=0.7, rms_height=1.0)
    heights, coarse_heights = sample_coupled(spectrum, 64, rng, projection="truncation")
    loads = np.array([0.1, 0.02, 0.3]) * spectrum.rms_slope
    coarse = solve_load_curve(coarse_heights, system_size=size, mean_pressures=loads)
    guesses = [solution.pressure for solution in coarse.solutions]
    curve = solve_load_curve(heights, system_size=size, mean_pressures=loads, initial_pressures=guesses)
    for load, guess, solution, n_iter in zip(loads, guesses, curve.solutions, curve.n_iter):
        alone = solve_contact(heights, system_size=size, mean_pressure=load, initial_pressure=guess)
        assert np.array_equal(solution.pressure, alone.pressure) and n_iter == alone.n_iter
    with pytest.raises(InvalidParameterError, match="initial_pressures"):
        solve_load_curve(heights, system_size=size, mean_pressures=loads, initial_pressures=guesses[:2])
    with pytest.raises(InvalidParameterError, match="initial_pressure"):
        solve_load_curve(heights, system_size=size, mean_pressures=loads, initial_pressures=guesses,
                         initial_pressure=guesses[0])


def test_a_bad_guess_per_load_is_named_by_its_index():
    # A bad second field was refused as "initial_pressure: got 'grid 24 x 24'", a parameter not given, and no index.
    heights, size, slope, _, _ = random_surface(401, grids=(32,))
    loads = [0.2 * slope, 0.05 * slope]  # the bad field is the first load's, which is solved second
    for bad, said in ((np.ones((24, 24)), "grid 24 x 24"), (-np.ones((32, 32)), "minimum -1")):
        with pytest.raises(InvalidParameterError, match=f"^initial_pressures\\[0\\]: got '{said}'") as caught:
            solve_load_curve(heights, system_size=size, mean_pressures=loads,
                             initial_pressures=[bad, np.ones((16, 16))])
        assert caught.value.name == "initial_pressures[0]"
    with pytest.raises(InvalidParameterError, match="^initial_pressure: got 'grid 24 x 24'"):
        solve_load_curve(heights, system_size=size, mean_pressures=loads, initial_pressure=np.ones((24, 24)))


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


# --------------------------------------------------------------------------
# Config, problem and pipeline
# --------------------------------------------------------------------------

CURVE = [0.2, 0.02, 0.1]  # relative loads, unsorted on purpose


def _spectrum():
    return SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)


def _curve_problem(**overrides):
    import rough_uq

    loads = [rough_uq.RelativeLoad(v) for v in CURVE]
    options = dict(load=loads, qoi=["contact_area", "clusters"], coarsest=16, max_level=2, seed=7, solver_tol=1e-10)
    return rough_uq.ContactProblem(_spectrum(), **(options | overrides))


@pytest.mark.parametrize(
    ("load", "field", "what"),
    [
        ({"relative": []}, "load.relative", "at least one load"),
        ({"relative": [0.1, 0.0]}, "load.relative.1", "> 0"),
        ({"absolute": [-1.0, 0.1]}, "load.absolute.0", "> 0"),
        ({"relative": [0.1, "x"]}, "load.relative.1", "> 0"),
        ({"relative": [0.05, 0.1, 0.05]}, "load.relative", "given once; repeated: 0.05"),
        ({"relative": [0.1], "absolute": [0.2]}, "load.relative", "exactly once"),
        ({"relative": {"a": 0.1}}, "load.relative", "a number or a list"),
        # An integer beyond the floats was an OverflowError traceback from math.isfinite:
        ({"relative": 10**400}, "load.relative", "finite number > 0"),
        ({"absolute": [0.1, 10**400]}, "load.absolute.1", "finite number > 0"),
    ],
)
def test_bad_load_lists_name_the_field(load, field, what):
    from rough_uq.errors import ConfigError
    from rough_uq.study.config import config_from_dict
    from tests.study_configs import tiny_config

    with pytest.raises(ConfigError) as caught:
        config_from_dict(tiny_config(load=load))
    line = str(caught.value)
    assert line.startswith(field + ":") and what in line, line


def test_config_curve_columns_and_a_one_element_list_is_the_single_load():
    from rough_uq.study.config import config_from_dict, config_from_yaml_text, config_hash, resolved_yaml
    from tests.study_configs import tiny_config

    qoi = {"contact_area": {"tol": 1.0}, "clusters": {"tol": 5.0}}
    curve = config_from_dict(tiny_config(load={"relative": CURVE}, qoi=qoi))
    assert curve.load.values == tuple(CURVE) and curve.load.n_loads == 3
    assert curve.qoi_names == (
        "contact_area@0.2", "contact_area@0.02", "contact_area@0.1", "clusters@0.2", "clusters@0.02", "clusters@0.1",
    )
    assert config_from_yaml_text(resolved_yaml(curve)) == curve
    single, listed = (config_from_dict(tiny_config(load={"relative": v})) for v in (0.2, [0.2]))
    assert listed == single and config_hash(listed) == config_hash(single) and single.qoi_names == ("contact_area",)


@pytest.mark.parametrize("seed", range(4))
def test_a_column_name_splits_back_into_its_qoi_and_load(seed):
    from rough_uq.problem.columns import column_name, split_column

    rng = np.random.default_rng([26, seed])
    loads = np.concatenate([10 ** rng.uniform(-12, 12, 50), rng.uniform(0, 3, 50), rng.integers(1, 100, 5)])
    for qoi in ("contact_area", "clusters", "area_above"):
        for load in loads:
            name, value = split_column(column_name(qoi, load))
            assert (name, value) == (qoi, float(load))
    assert split_column("mean_gap") == ("mean_gap", None)


def test_problem_columns_and_model_match_the_pipeline():
    import rough_uq
    from rough_uq.study.config import config_from_dict
    from rough_uq.study.pipeline import build_model
    from tests.study_configs import tiny_config

    config = config_from_dict(
        tiny_config(load={"relative": CURVE}, qoi={"contact_area": {}, "clusters": {}}, solver={"tol": 1e-10},
                    seed=7, grid={"coarsest": 16, "max_level": 2})
    )
    problem = _curve_problem()
    assert problem.columns == config.qoi_names and problem.n_qoi == 6 and problem.n_loads == 3
    assert problem.model == build_model(config)
    assert problem.model.loads == tuple(v * _spectrum().rms_slope for v in CURVE)
    with pytest.raises(InvalidParameterError, match="load"):
        _curve_problem(load=[])
    with pytest.raises(InvalidParameterError, match="distinct"):
        _curve_problem(load=[rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(0.1)])
    with pytest.raises(InvalidParameterError, match="load"):
        _curve_problem(load=[rough_uq.RelativeLoad(0.1), rough_uq.AbsoluteLoad(0.2)])


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_single_precision_loads_are_taken_at_their_shortest_decimal(dtype):
    import rough_uq
    from rough_uq.problem.runs import checked_tolerances

    values = np.array(CURVE, dtype=dtype)
    for kind in (rough_uq.RelativeLoad, rough_uq.AbsoluteLoad):
        problem = _curve_problem(load=[kind(v) for v in values])
        assert problem.columns == _curve_problem(load=[kind(v) for v in CURVE]).columns
        assert "contact_area@0.02" in problem.columns
        tol = checked_tolerances({"contact_area@0.02": 3.0, "contact_area": 1.0, "clusters": 50.0}, problem.n_qoi,
                          problem.columns)
        np.testing.assert_array_equal(tol, [1.0, 3.0, 1.0, 50.0, 50.0, 50.0])
    assert rough_uq.RelativeLoad(np.float64(0.05000000074505806)).value == 0.05000000074505806
    with pytest.raises(InvalidParameterError, match="load.relative"):
        rough_uq.RelativeLoad(dtype(-0.1))
    with pytest.raises(InvalidParameterError, match="load.absolute"):
        rough_uq.AbsoluteLoad(dtype("nan"))


@pytest.mark.parametrize("stage_kind", ["mlmc", "mc"])
def test_curve_columns_equal_single_load_samples(stage_kind):
    # Each load column of a curve sample is the sample of a single-load problem at that load
    # (same surface; the warm starts change the path of the solver only).
    import rough_uq
    from rough_uq.problem.sampler import compute_batch, run_stage

    stage = run_stage(stage_kind, "curve-test")
    curve = _curve_problem()
    batch = compute_batch(curve.model, stage=stage, level=1, indices=np.arange(3))
    assert batch.fine.shape == (3, 6) and batch.is_converged.all()
    for j, value in enumerate(CURVE):
        single = _curve_problem(load=rough_uq.RelativeLoad(value))
        alone = compute_batch(single.model, stage=stage, level=1, indices=np.arange(3))
        for part in ("fine", "coarse"):
            columns = getattr(batch, part)[:, [j, 3 + j]]
            np.testing.assert_allclose(columns, getattr(alone, part), rtol=1e-9, atol=1e-9, err_msg=f"{part} {value}")
    order = np.argsort(CURVE)
    assert np.all(np.diff(batch.fine[:, order], axis=1) > 0)  # the area grows with the load


def test_tiny_mlmc_and_mc_give_curves():
    import rough_uq

    problem = _curve_problem(qoi=["contact_area"])
    result = rough_uq.mlmc(problem, tol=3.0)
    assert result.estimate.shape == result.rmse.shape == (3,)
    order = np.argsort(CURVE)
    assert np.all(np.diff(result.estimate[order]) > 0)
    mc = rough_uq.mc(problem, tol=3.0, level=0)
    assert mc.estimate.shape == (3,) and np.all(np.diff(mc.estimate[order]) > 0)


def test_tolerances_apply_per_column_unless_a_column_is_named():
    from rough_uq.study.config import config_from_dict
    from rough_uq.study.pipeline import parse_tolerances
    from tests.study_configs import tiny_config

    qoi = {"contact_area": {"tol": 2.0}, "mean_gap": {"tol": 0.05}}
    config = config_from_dict(tiny_config(load={"relative": CURVE}, qoi=qoi))
    tol = parse_tolerances(None, config)
    np.testing.assert_array_equal(tol, [2.0] * 3 + [0.05] * 3)
    tol = parse_tolerances(["contact_area=1.5", "contact_area@0.02=3"], config)
    np.testing.assert_array_equal(tol, [1.5, 3.0, 1.5, 0.05, 0.05, 0.05])
    # A load is a number, as show --load reads it: @0.020 and @2e-2 name the column @0.02 ("not a QoI" before).
    for spelled in ("0.020", "2e-2", "2.0E-02"):
        np.testing.assert_array_equal(parse_tolerances([f"contact_area@{spelled}=3"], config),
                                      [2.0, 3.0, 2.0, 0.05, 0.05, 0.05])
    with pytest.raises(InvalidParameterError, match="one tolerance per QoI; contact_area@0.02 was already given 3"):
        parse_tolerances(["contact_area@0.02=3,contact_area@0.020=4"], config)
    with pytest.raises(InvalidParameterError, match="contact_area@0.3"):
        parse_tolerances(["contact_area@0.3=1"], config)
    with pytest.raises(InvalidParameterError, match="NAME=EPS"):
        parse_tolerances(["0.7"], config)
    single_qoi = config_from_dict(tiny_config(load={"relative": CURVE}))
    np.testing.assert_array_equal(parse_tolerances(["0.7"], single_qoi), [0.7] * 3)


# --------------------------------------------------------------------------
# Report: slope fit, tables, figure
# --------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_slope_fit_recovers_a_linear_area_and_bounds_the_error(seed):
    from rough_uq.report.summary import fit_area_slope

    rng = np.random.default_rng([18, 5, seed])
    kappa = rng.uniform(1, 3)
    loads = np.sort(rng.uniform(0.001, 0.2, size=int(rng.integers(3, 8))))
    exact = kappa * loads
    # Above 10 % area the curve bends: such points must not enter the fit.
    area = np.where(exact < 0.1, exact, 0.1 + 0.3 * (exact - 0.1))
    errors = rng.uniform(1e-5, 1e-4, size=loads.size)  # small enough that no point crosses 10 %
    fit = fit_area_slope(relative_loads=loads, area=area, area_error=errors)
    if np.all(exact >= 0.1):
        assert fit is None
        return
    small = exact < 0.1
    assert fit.kappa == pytest.approx(kappa, rel=1e-12) and fit.n_points == int(small.sum())
    # Fully correlated errors (every estimate off by +e_i) move kappa by exactly the bound.
    shifted = fit_area_slope(relative_loads=loads, area=area + errors * small, area_error=errors)
    assert shifted.n_points == fit.n_points
    assert shifted.kappa - fit.kappa == pytest.approx(fit.error, rel=1e-9)


@pytest.fixture(scope="module")
def curve_study(tmp_path_factory):
    """A tiny curve study screened and estimated through the real CLI; the path of its study file."""
    import os

    from click.testing import CliRunner

    from rough_uq.cli import main
    from tests.study_configs import tiny_config, write_config

    directory = tmp_path_factory.mktemp("curve")
    # contact_area 3: the screening of grids 8^2-32^2 reaches about 2.2 at load 0.1
    qoi = {"contact_area": {"tol": 3.0}, "mean_gap": {"tol": 0.05}}
    config = tiny_config(load={"relative": CURVE}, qoi=qoi, output={"path": str(directory / "curve.h5")})
    path = write_config(directory / "curve.yaml", config)
    previous = os.getcwd()
    os.chdir(directory)
    try:
        study = str(directory / "curve.h5")
        for args in (["screen", str(path)], ["mlmc", "--study", study, "--tol", "mean_gap@0.02=0.1"],
                     ["mc", "--study", study]):
            result = CliRunner().invoke(main, [*args, "--workers", "1", "--quiet"])
            assert result.exit_code == 0, (args, result.output, result.exception)
    finally:
        os.chdir(previous)
    return directory / "curve.h5"


def test_cli_study_stores_one_column_per_qoi_and_load(curve_study):
    from rough_uq.study.store import open_study_readonly

    with open_study_readonly(curve_study) as store:
        names = store.qoi_names
        screening = store.read_screening()
        runs = store.read_runs()
    expected = tuple(f"{q}@{v!r}" for q in ("contact_area", "mean_gap") for v in CURVE)
    assert names == expected and screening["qoi_names"] == list(expected)
    assert np.shape(screening["statistics"]["mean_fine"]) == (3, 6)
    assert [run["qoi_names"] for run in runs] == [list(expected)] * 2


def test_report_shows_the_load_curve_table_and_kappa(curve_study, tmp_path):
    from click.testing import CliRunner

    from rough_uq.cli import main
    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.report.summary import study_report

    with open_existing_study(curve_study, writable=False) as study:
        report = study_report(study.store, study.config)
    curves = report["load_curves"]
    assert [entry["method"] for entry in curves] == ["mlmc", "mc"]
    for entry, run in zip(curves, report["runs"]):
        assert entry["loads"] == sorted(CURVE) and entry["relative_loads"] == sorted(CURVE)
        for j, load in enumerate(entry["loads"]):
            column = report["qoi_names"].index(f"contact_area@{load!r}")
            assert entry["curves"]["contact_area"]["estimate"][j] == run["estimate"][column]
        assert np.all(np.diff(entry["curves"]["contact_area"]["estimate"]) > 0)
        # The smallest load has less than 10 % contact: kappa is fitted on it.
        assert entry["kappa"]["n_points"] >= 1 and entry["kappa"]["kappa"] > 0 and entry["kappa"]["error"] > 0
    mlmc = report["runs"][0]
    assert mlmc["tol"] == [3.0] * 3 + [0.05, 0.1, 0.05]  # per QoI, one column apart

    output = CliRunner().invoke(main, ["report", str(curve_study), "--plots", str(tmp_path)]).output
    assert "Load curve of" in output and "kappa =" in output and "contact_area@0.02" in output
    # Relative loads once: a "load" column repeated the p/(E* sqrt(m2)) one.
    headers = [line.split() for line in output.splitlines() if "p/(E* sqrt(m2))" in line and "kappa" not in line]
    assert headers and all(header[0] == "p/(E*" for header in headers), headers
    # One small load gives no fit, only the line through it (the report said "fitted ... on the 1 load(s)").
    for entry in curves:
        n_points = entry["kappa"]["n_points"]
        assert (f"fitted through 0\n  on the {n_points} loads with A/A0 < 0.1;" in output) == (n_points > 1)
        # ("no fit: the line through 0 and that load; smaller loads in the curve make it one" was hard to parse)
        assert ("the slope of the line through 0 and the only load with A/A0 < 0.1\n  (more loads below that area "
                "in the curve give a least-squares fit);" in output) == (n_points == 1)
    assert (tmp_path / "load_curve.png").read_bytes().startswith(b"\x89PNG")


def test_cli_progress_names_a_curve_runs_tolerances_by_qoi(curve_study, tmp_path):
    """The progress of a curve run listed one ``mean_gap@LOAD=EPS`` per column (every load of every QoI)."""
    import shutil

    from click.testing import CliRunner

    from rough_uq.cli import main

    study = shutil.copy(curve_study, tmp_path / "curve.h5")
    result = CliRunner().invoke(main, ["mlmc", "--study", str(study), "--tol", "mean_gap@0.02=0.1", "--workers", "1"])
    assert result.exit_code == 0, result.output
    assert "[mlmc contact_area=3, mean_gap=0.05, mean_gap@0.02=0.1] done in " in result.stderr


def test_a_load_curve_through_full_contact_is_screened_and_estimated():
    # At full contact the area is 100 % and there is one cluster in every sample: the screening refused the
    # whole curve ("cannot fit alpha for clusters@3.0"), though its other loads have everything to estimate.
    import rough_uq
    from rough_uq.multilevel.rates import EXACT_RATE
    from rough_uq.problem.runs import exact_column_caveats

    loads = [rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(3.0)]
    problem = _curve_problem(load=loads, qoi=["clusters"], solver_tol=1e-8)
    screening = rough_uq.screen(problem, levels=3, samples=6)
    exact = problem.columns.index("clusters@3.0")
    assert screening.statistics.var_fine[:, exact].tolist() == [0.0, 0.0, 0.0]  # one cluster: full contact
    assert screening.rates.alpha[exact] == screening.rates.beta[exact] == EXACT_RATE
    assert screening.rates.alpha[1 - exact] < EXACT_RATE  # the partial contact of 0.1 is fitted
    result = rough_uq.mlmc(problem, tol={"clusters": 20.0}, screening=screening)
    assert result.estimate[exact] == 1.0 and result.rmse[exact] == 0.0  # per unit area of a box of 1
    assert np.isfinite(result.rmse).all() and result.tol_met
    # Grids 16-64 resolve k_s = 8: no caveat. Grids that truncate the spectrum see a smoother surface, which
    # reaches full contact sooner: the screening says that a finer grid may differ.
    assert not [d for d in screening.diagnostics if "do not resolve the surface" in d]
    coarse = dataclasses.replace(problem.model, coarsest=4)  # screened grids 4, 8, 16: 16 <= 2 k_s
    (caveat,) = exact_column_caveats(coarse, problem.columns, screening.rates, screening.statistics)
    assert caveat.startswith("clusters@3.0: every level difference is 0 on the screened grids up to 16^2")
    assert "k_s = 8 needs a grid above 16" in caveat


def test_solutions_compare_by_identity_like_every_result():
    """``==``, ``in`` and ``hash`` raised numpy's "truth value of an array is ambiguous" and "unhashable"."""
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=2, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    heights = sample_surface(spectrum, 16, np.random.default_rng(0))
    solutions = [solve_contact(heights, system_size=2.0, mean_pressure=1.0) for _ in range(2)]
    curves = [solve_load_curve(heights, system_size=2.0, mean_pressures=[0.5, 1.0]) for _ in range(2)]
    for first, second in (solutions, curves):
        assert first == first and first != second and first in [first] and second not in [first]
        assert len({first, second, first}) == 2

"""The Python API on the CLI's files: ``load_problem`` (config or study file) and ``read_report`` (study file)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import rough_uq
from rough_uq.cli import main
from rough_uq.errors import ConfigError, InvalidParameterError, StudyFileError
from rough_uq.report.summary import read_report
from rough_uq.study.config import load_config
from rough_uq.study.pipeline import build_model, load_problem, load_screening, problem_of_config
from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config


def _random_config(rng: np.random.Generator) -> dict:
    """A valid config with every sample-deciding field drawn: QoIs, units, loads, grids, solver, seed."""
    pick = lambda options: options[int(rng.integers(len(options)))]  # noqa: E731 - plain Python values for YAML
    k_l = int(rng.integers(1, 3))
    k_r = k_l + int(rng.integers(0, 2))
    surface = {"system_size": float(pick([0.5, 1.0, 2.0])), "hurst": float(rng.uniform(0.1, 1.0)),
               "rms_height": float(rng.uniform(0.5, 2.0)),
               "wavenumbers": {"k_l": k_l, "k_r": k_r, "k_s": int(rng.integers(k_r + 2, 12))}}
    choices = {
        "contact_area": {"unit": pick(["percent", "fraction"]), "estimator": pick(["corrected", "nodes"])},
        "clusters": {"unit": pick(["absolute", "per_area"]), "connectivity": pick([4, 8, "mean"])},
        "mean_gap": {},
        "max_pressure": {},
        "area_above": {"critical_pressure": float(rng.uniform(0.1, 1.0)), "unit": pick(["fraction", "percent"])},
    }
    names = [str(name) for name in rng.permutation(list(choices))[: int(rng.integers(1, 6))]]
    qoi = {name: choices[name] for name in names}
    kind = pick(["relative", "absolute"])
    values = sorted(float(v) for v in rng.uniform(0.02, 0.5, size=int(rng.integers(1, 4))))
    coarsest = pick([16, 32])
    return tiny_config(
        seed=int(rng.integers(0, 2**31)),
        surface=surface,
        material={"e_star": float(rng.uniform(0.5, 3.0))},
        load={kind: values[0] if len(values) == 1 else values},
        solver={"tol": float(10.0 ** rng.uniform(-10, -5)), "max_iter": int(rng.integers(50, 5000)),
                "warm_start": bool(rng.integers(2)), "threads": int(rng.integers(1, 3))},
        qoi=qoi,
        grid={"coarsest": coarsest, "max_level": int(rng.integers(0, 4)),
              "projection": "injection" if surface["wavenumbers"]["k_s"] < coarsest / 2 and pick([True, False])
              else "truncation"},
    )


@pytest.mark.parametrize("seed", range(40))
def test_the_problem_of_a_random_config_computes_the_samples_the_cli_computes(tmp_path, seed):
    config = _random_config(np.random.default_rng([2026, 11, 27, seed]))
    path = write_config(tmp_path / "config.yaml", config)
    problem = load_problem(path)
    assert problem.model == build_model(load_config(path))  # every field of a sample, FFT wisdom aside
    assert problem.max_level == config["grid"]["max_level"] and problem.seed == config["seed"]
    assert problem.columns == load_config(path).qoi_names  # the study file's result columns


def test_the_problem_of_a_study_file_is_its_stored_configs(tmp_path):
    config = write_config(tmp_path / "config.yaml", tiny_config(grid={"coarsest": 16, "max_level": 2}))
    study = tmp_path / "study.h5"
    result = CliRunner().invoke(main, ["screen", str(config), "--out", str(study)])
    assert result.exit_code == 0, result.output
    assert load_problem(study) == load_problem(config) == problem_of_config(load_config(config))
    # A field changed with dataclasses.replace (max_level decides which levels, not what a sample is).
    finer = dataclasses.replace(load_problem(study), max_level=3)
    assert finer.max_level == 3 and finer != load_problem(study) and finer.model == load_problem(study).model


@pytest.mark.parametrize("method", ["mlmc", "mc"])
def test_a_run_on_the_files_problem_and_screening_estimates_what_roughuq_estimates(tmp_path, monkeypatch, method):
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", "estimate")  # both plan FFTs alike
    config = tiny_config(grid={"coarsest": 16, "max_level": 3}, qoi={"contact_area": {"unit": "percent", "tol": 3}})
    path = write_config(tmp_path / "config.yaml", config)
    study = tmp_path / "study.h5"
    runner = CliRunner()
    assert runner.invoke(main, ["screen", str(path), "--out", str(study)]).exit_code == 0
    level = ["--level", "1"] if method == "mc" else []
    result = runner.invoke(main, [method, "--study", str(study), "--tol", "3", *level])
    assert result.exit_code in (0, 3), result.output
    record = read_report(study)["runs"][-1]
    options = dict(n_initial=config["estimation"]["initial_samples"], batch_size=config["estimation"]["batch_size"])
    problem = load_problem(study)
    expect_warning = pytest.warns(rough_uq.EstimationWarning) if not record["tol_met"] else contextlib.nullcontext()
    with expect_warning:
        if method == "mc":
            estimate = rough_uq.mc(problem, tol=3, level=1, **options)
        else:
            estimate = rough_uq.mlmc(problem, tol=3, screening=load_screening(study), **options)
    assert estimate.estimate.tolist() == record["estimate"]
    assert estimate.levels.tolist() == record["levels"] and estimate.n_samples.tolist() == record["n_samples"]


def test_the_screening_of_a_study_file_is_the_screening_of_its_samples(tmp_path, monkeypatch):
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", "estimate")
    config = tiny_config(grid={"coarsest": 16, "max_level": 3})
    path = write_config(tmp_path / "config.yaml", config)
    study = tmp_path / "study.h5"
    assert CliRunner().invoke(main, ["screen", str(path), "--out", str(study)]).exit_code == 0
    read = load_screening(study)
    drawn = rough_uq.screen(load_problem(path), levels=config["screening"]["levels"],
                            samples=config["screening"]["samples"])
    np.testing.assert_array_equal(read.statistics.mean_diff, drawn.statistics.mean_diff)
    np.testing.assert_array_equal(read.statistics.var_fine, drawn.statistics.var_fine)
    np.testing.assert_array_equal(read.rates.alpha, drawn.rates.alpha)
    assert read.problem == drawn.problem and read.diagnostics == drawn.diagnostics
    stored = read_report(study)["screening"]["statistics"]
    assert read.statistics.mean_diff.tolist() == stored["mean_diff"]
    unscreened = tmp_path / "unscreened.h5"
    assert CliRunner().invoke(main, ["mc", "--config", str(path), "--study", str(unscreened), "--level", "0",
                                     "--tol", "50"]).exit_code in (0, 3)
    with pytest.raises(StudyFileError, match="no complete screening yet"):
        load_screening(unscreened)


def test_read_report_is_what_report_json_prints(tmp_path):
    config = write_config(tmp_path / "config.yaml", tiny_config(grid={"coarsest": 16, "max_level": 2}))
    study = tmp_path / "study.h5"
    runner = CliRunner()
    assert runner.invoke(main, ["screen", str(config), "--out", str(study)]).exit_code == 0
    printed = runner.invoke(main, ["report", str(study), "--json"])
    assert printed.exit_code == 0, printed.output
    read = read_report(study)
    assert json.loads(json.dumps(read, default=str)) == json.loads(printed.output)
    assert read["screening"]["statistics"]["levels"] == [0, 1, 2]


def test_files_that_hold_no_problem_are_refused_by_name(tmp_path):
    for missing in ("", tmp_path / "missing.yaml", tmp_path / "missing.h5"):
        with pytest.raises(InvalidParameterError, match="^path: .*an existing config file .* or study file"):
            load_problem(missing)
    bad = write_config(tmp_path / "bad.yaml", tiny_config(grid={"coarsest": 15, "max_level": 2}))
    with pytest.raises(ConfigError, match="bad.yaml: grid.coarsest"):
        load_problem(bad)
    # A setting that the config's schema takes and the problem refuses: named with the file, a ConfigError too.
    heavy = write_config(tmp_path / "heavy.yaml", tiny_config(load={"relative": 1e30}))
    with pytest.raises(ConfigError, match="heavy.yaml: load.relative: got 1e[+]30"):
        load_problem(heavy)
    not_hdf5 = tmp_path / "junk.h5"
    not_hdf5.write_text("not hdf5 at all")
    with pytest.raises(StudyFileError, match="junk.h5 is not an HDF5 file"):
        load_problem(not_hdf5)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["format"] = "something else"
    with pytest.raises(StudyFileError, match="not a roughuq study file"):
        load_problem(other)
    with pytest.raises(StudyFileError, match="not a roughuq study file"):
        read_report(other)
    for read in (open_study_readonly, read_report, load_screening):
        with pytest.raises(StudyFileError, match="empty path"):  # read_report("") said ". is not a file"
            read("")
    with pytest.raises(StudyFileError, match=r"is a directory \(got .*; allowed: a study file\)"):
        load_screening(tmp_path)  # a directory: it said "is a directory ... allowed: a YAML file"
    # A missing file: the message advised the CLI's options "--study or --config" in a Python call.
    with pytest.raises(StudyFileError, match=r"missing.h5' does not exist: load_screening reads the file") as caught:
        load_screening(tmp_path / "missing.h5")
    assert "--" not in str(caught.value)
    if Path("/dev/null").exists():  # it said "/dev/null is not a file"
        with pytest.raises(StudyFileError, match=r"^/dev/null is not a regular file \(a device or a pipe\?\)"):
            load_screening("/dev/null")



@pytest.mark.parametrize("path", [None, 5, b"results.h5"])
def test_a_path_that_is_no_path_is_refused_by_name(path):
    # os.fspath raised a bare TypeError ("expected str, bytes or os.PathLike object, not NoneType").
    for read in (load_problem, load_screening, read_report, open_study_readonly):
        with pytest.raises(InvalidParameterError, match=r"^path: got .*; allowed: a file path \(a str or pathlib"):
            read(path)


def test_a_screening_the_cli_refused_is_refused_naming_the_file(tmp_path):
    config = write_config(tmp_path / "full.yaml", tiny_config(load={"relative": 1e6}))  # 100 % in every sample
    study = tmp_path / "full.h5"
    result = CliRunner().invoke(main, ["screen", str(config), "--out", str(study)])
    assert result.exit_code == 2 and "took one value in every sample" in result.output
    with pytest.raises(rough_uq.EstimationError, match=r"full\.h5: the stored screening gives no rates: contact_area "
                                                       "took one value in every sample"):
        load_screening(study)

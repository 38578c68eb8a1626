"""Beyond the mean through the real CLI: `roughuq mlmc --tol-var / --tol-cdf`, their records and the report."""

from __future__ import annotations

import io
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from rough_uq.cli import main
from rough_uq.multilevel.distribution import level_bandwidth, smoothed_step
from rough_uq.multilevel.moments import variance_level_term
from rough_uq.study.records import RunRecord
from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config

#: Thresholds that bracket the tiny study's contact area (about 35-55 % on its grids), in percent.
TINY_THRESHOLDS = "25:60:36"


def run(*args: str, expect: int | tuple[int, ...] = 0) -> object:
    result = CliRunner().invoke(main, list(args))
    allowed = (expect,) if isinstance(expect, int) else expect
    assert result.exit_code in allowed, (result.output, result.stderr, result.exception)
    return result


def stored_runs(path: Path) -> dict[str, RunRecord]:
    with open_study_readonly(path) as store:
        return {data["run_id"]: RunRecord.from_json(data) for data in store.read_runs()}


def stage_samples(path: Path, *, stage: int, level: int) -> object:
    with open_study_readonly(path) as store:
        return store.read_samples(level=level, stage=stage)


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """A tiny study config in a fresh working directory (target runs need no screening)."""
    monkeypatch.chdir(tmp_path)
    return write_config(tmp_path / "tiny.yaml", tiny_config())


# ---------------------------------------------------------------------------
# The classic setting (slow): variance and 5 % / 95 % quantiles against plain MC
# ---------------------------------------------------------------------------


def _classic_config(tmp_path: Path) -> Path:
    """The shipped classic-area config on its three coarsest grids (256^2 ... 1024^2).

    On these grids the CDF's discretisation bias (the area shifts by about
    0.1 % per level, a quarter of its standard deviation) is estimated at
    about 0.12 in the sup norm, so the CDF tolerance is 0.25: a tighter one
    stops at grid.max_level (status 3).
    """
    run("init", "classic-area")
    config = yaml.safe_load((tmp_path / "classic-area.yaml").read_text())
    config["grid"]["max_level"] = 2
    config["estimation"]["initial_samples"] = 20
    # The area is about 19.3 +- 0.4 %: the grid brackets its 5 % and 95 % quantiles with a spacing of 0.1 %.
    config["estimation"]["distribution"] = {"contact_area": {"thresholds": {"start": 17.5, "stop": 21.5, "count": 41},
                                                             "probabilities": [0.05, 0.5, 0.95]}}
    config["output"]["path"] = "classic.h5"
    return write_config(tmp_path / "classic.yaml", config)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_classic_area_variance_and_quantiles_agree_with_plain_mc_on_the_finest_level(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = _classic_config(tmp_path)
    variance = json.loads(run("mlmc", "--config", str(config), "--study", "classic.h5", "--tol-var", "0.03",
                              "--json", "-q", expect=(0, 3)).stdout)
    cdf = json.loads(run("mlmc", "--study", "classic.h5", "--tol-cdf", "0.25", "--json", "-q",
                         expect=(0, 3)).stdout)
    assert variance["tol_met"] and cdf["tol_met"], (variance["rmse"], variance["stop_reason"], cdf["rmse"])
    finest = variance["levels"][-1]
    assert cdf["levels"][-1] == finest

    # Plain MC on that level, samples of another stage (an MC run's), about 100 of them.
    mc = json.loads(run("mc", "--study", "classic.h5", "--level", str(finest), "--tol", "0.06", "--json",
                        "-q").stdout)
    samples = stage_samples(tmp_path / "classic.h5", stage=mc["stage"], level=finest).fine[:, 0]
    assert samples.size == mc["n_samples"][0] >= 40

    # Var(Q_L): the MLMC telescoping sum against the unbiased sample variance, within 3 combined standard errors.
    term = variance_level_term(samples[:, None], None)
    combined = math.hypot(variance["stat_error"][0], math.sqrt(term.variance[0]))
    assert abs(variance["estimate"][0] - term.mean[0]) <= 3 * combined

    # The quantiles: at q_p the MC estimate of the same smoothed CDF (bandwidth of level L) is p, within
    # 3 combined standard errors (the MLMC's largest statistical error over the grid, the MC's binomial one).
    distribution = cdf["distribution"]
    delta = distribution["bandwidths"][-1]
    assert delta == pytest.approx(level_bandwidth(finest, bandwidth=distribution["bandwidths"][0]))
    for quantile in distribution["quantiles"]:
        if quantile["probability"] not in (0.05, 0.95):
            continue
        smoothed = smoothed_step((quantile["value"] - samples) / delta)
        mc_se = np.std(smoothed, ddof=1) / math.sqrt(samples.size)
        combined = math.hypot(max(cdf["stat_error"]), mc_se)
        assert abs(np.mean(smoothed) - quantile["probability"]) <= 3 * combined, quantile
        assert (quantile["lower"] or -math.inf) < quantile["value"] < (quantile["upper"] or math.inf)
    print(f"\nclassic (levels 0..{finest}): Var = {variance['estimate'][0]:.4f} ± {variance['stat_error'][0]:.4f} "
          f"(RMSE {variance['rmse'][0]:.3g}, N_l {variance['n_samples']}), MC {term.mean[0]:.4f} ± "
          f"{math.sqrt(term.variance[0]):.4f} (N {samples.size}); quantiles "
          + "; ".join(f"q({q['probability']}) = {q['value']:.3f} [{q['lower']}, {q['upper']}]"
                      for q in distribution["quantiles"])
          + f" (sup RMSE {cdf['rmse'][0]:.3g}, N_l {cdf['n_samples']})")


# ---------------------------------------------------------------------------
# Tiny studies (fast)
# ---------------------------------------------------------------------------


def _exit_status(record: dict) -> int:
    return 0 if record["tol_met"] else 3


def _levels(path: Path, record: RunRecord) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The fine and coarse values a finished run used, read back from the study file."""
    fine, coarse = [], []
    for level, n in zip(record.outcome.levels, record.outcome.n_samples):
        batch = stage_samples(path, stage=record.stage, level=level)
        order = np.argsort(batch.indices)[:n]
        assert np.array_equal(batch.indices[order], np.arange(n))
        fine.append(batch.fine[order])
        coarse.append(batch.coarse[order])
    return fine, coarse


def test_variance_run_stores_the_telescoped_h_statistics_of_its_own_samples(tiny):
    from rough_uq.multilevel.moments import variance_from_samples
    from rough_uq.problem.runs import run_id
    from rough_uq.problem.sampler import run_stage

    result = run("mlmc", "--config", str(tiny), "--tol-var", "contact_area=60", "--workers", "1", "--json",
                 expect=(0, 3))
    shown = json.loads(result.stdout)
    assert result.exit_code == _exit_status(shown)
    key = run_id("variance", ["contact_area"], np.array([60.0]), 0.5)
    assert shown["run_id"] == key and shown["method"] == "variance"
    record = stored_runs(tiny.parent / "results.h5")[key]
    assert record.stage == run_stage("mlmc", key) == shown["stage"]  # the stage rough_uq.variance draws from
    fine, coarse = _levels(tiny.parent / "results.h5", record)
    expected = variance_from_samples(fine=fine, coarse=coarse, tol=60.0)
    outcome = record.outcome
    np.testing.assert_allclose(outcome.estimate, expected.estimate, rtol=1e-12)
    np.testing.assert_allclose(outcome.stat_error, expected.stat_error, rtol=1e-12)
    assert outcome.tol_met == (outcome.rmse[0] <= 60.0) and outcome.variance is None and outcome.statistics is None
    assert outcome.cost > 0 and outcome.mc_cost > 0 and outcome.n_computed == sum(outcome.n_samples)


def test_cdf_run_stores_cdf_band_and_quantiles_of_its_own_samples(tiny):
    from rough_uq.multilevel.distribution import cdf_from_samples, quantiles

    result = run("mlmc", "--config", str(tiny), "--tol-cdf", "0.3", "--thresholds", TINY_THRESHOLDS,
                 "--probabilities", "0.05,0.5", "--workers", "1", "--json", expect=(0, 3))
    shown = json.loads(result.stdout)
    assert result.exit_code == _exit_status(shown)
    record = stored_runs(tiny.parent / "results.h5")[shown["run_id"]]
    assert record.method == "cdf" and record.qoi_names == ("contact_area",) and record.tol == (0.3,)
    distribution = record.outcome.distribution
    s = np.linspace(25, 60, 36)
    np.testing.assert_allclose(distribution.thresholds, s)
    fine, coarse = _levels(tiny.parent / "results.h5", record)
    expected = cdf_from_samples(fine=fine, coarse=coarse, thresholds=s, bandwidth=2.0, tol=0.3)
    np.testing.assert_allclose(distribution.cdf, expected.cdf, atol=1e-12)
    np.testing.assert_allclose(record.outcome.estimate, expected.cdf_raw, atol=1e-12)
    np.testing.assert_allclose(distribution.cdf_upper, np.clip(expected.cdf + expected.rmse, 0, 1), atol=1e-12)
    np.testing.assert_allclose(distribution.cdf_lower, np.clip(expected.cdf - expected.rmse, 0, 1), atol=1e-12)
    assert record.outcome.rmse == pytest.approx((expected.rmse,))
    wanted = quantiles(expected, probabilities=[0.05, 0.5])
    assert [q.probability for q in distribution.quantiles] == [0.05, 0.5]
    np.testing.assert_allclose([q.value for q in distribution.quantiles], wanted.values)
    for q, lower, upper in zip(distribution.quantiles, wanted.lower, wanted.upper):
        assert q.lower == (lower if np.isfinite(lower) else None) and q.upper == (upper if np.isfinite(upper) else None)


def test_cdf_runs_with_other_thresholds_or_probabilities_keep_their_own_records(tiny):
    args = ("mlmc", "--config", str(tiny), "--tol-cdf", "0.3", "--workers", "1", "--json", "-q")
    first = json.loads(run(*args, "--thresholds", TINY_THRESHOLDS, expect=(0, 3)).stdout)
    other = json.loads(run(*args, "--thresholds", "30:50:21", expect=(0, 3)).stdout)
    quantiles = json.loads(run(*args, "--thresholds", TINY_THRESHOLDS, "--probabilities", "0.5", expect=(0, 3)).stdout)
    again = json.loads(run(*args, "--thresholds", TINY_THRESHOLDS, expect=(0, 3)).stdout)
    ids = [record["run_id"] for record in (first, other, quantiles)]
    assert len(set(ids)) == 3 and all(key.startswith("cdf_contact_area-0.3_theta-0.5_request-") for key in ids)
    assert again["run_id"] == first["run_id"] and again["n_computed"] == 0  # the same command resumes its run
    assert first["stage"] == other["stage"] == quantiles["stage"]  # one stage: the samples are shared
    runs = stored_runs(tiny.parent / "results.h5")
    assert sorted(runs) == sorted(ids) and all(run.status == "finished" for run in runs.values())
    np.testing.assert_allclose(runs[ids[0]].outcome.distribution.thresholds, np.linspace(25, 60, 36))
    np.testing.assert_allclose(runs[ids[1]].outcome.distribution.thresholds, np.linspace(30, 50, 21))
    assert [q.probability for q in runs[ids[2]].outcome.distribution.quantiles] == [0.5]


def _interrupt_after(monkeypatch, n_batches: int) -> None:
    """Make the study sampler raise KeyboardInterrupt (as Ctrl-C would) after ``n_batches`` computed batches."""
    from rough_uq.study import pipeline

    original = pipeline.StudySampler.compute
    calls = {"n": 0}

    def compute(self, level, indices):
        if self.missing(level, indices).size:
            calls["n"] += 1
            if calls["n"] > n_batches:
                raise KeyboardInterrupt
        return original(self, level, indices)

    monkeypatch.setattr(pipeline.StudySampler, "compute", compute)


_VOLATILE = ("finished", "started", "elapsed", "stopped_elapsed", "seconds", "mc_seconds_predicted", "n_computed")


@pytest.mark.parametrize("target", [("--tol-var", "60"), ("--tol-cdf", "0.3", "--thresholds", TINY_THRESHOLDS)],
                         ids=["variance", "cdf"])
def test_an_interrupted_run_resumes_to_the_record_of_an_uninterrupted_one(tiny, monkeypatch, target):
    whole = run("mlmc", "--config", str(tiny), *target, "--study", "whole.h5", "--workers", "1", "--json", "-q",
                expect=(0, 3))
    with monkeypatch.context() as patch:
        _interrupt_after(patch, 3)
        stopped = run("mlmc", "--config", str(tiny), *target, "--study", "resumed.h5", "--workers", "1", "-q",
                      expect=130)
        assert "every completed sample is saved" in stopped.stderr
    partial = stored_runs(tiny.parent / "resumed.h5")
    assert [r.status for r in partial.values()] == ["interrupted"]
    resumed = run("mlmc", *target, "--study", "resumed.h5", "--workers", "1", "--json", "-q",
                  expect=whole.exit_code)
    first, second = json.loads(whole.stdout), json.loads(resumed.stdout)
    assert 0 < second["n_computed"] < first["n_computed"]
    assert second["stopped_elapsed"] > 0 and "stopped_elapsed" not in first  # the stopped command's wall time
    assert {k: v for k, v in first.items() if k not in _VOLATILE} == {
        k: v for k, v in second.items() if k not in _VOLATILE}


def test_two_workers_give_the_numbers_of_one(tiny):
    args = ("mlmc", "--config", str(tiny), "--tol-var", "60", "--json", "-q")
    one = json.loads(run(*args, "--study", "one.h5", "--workers", "1", expect=(0, 3)).stdout)
    two = json.loads(run(*args, "--study", "two.h5", "--workers", "2", expect=(0, 3)).stdout)
    for key in ("estimate", "stat_error", "bias_estimate", "rmse", "n_samples", "cost", "stage"):
        assert one[key] == two[key], key


def test_report_shows_variance_and_distribution_tables_json_and_the_cdf_figure(tiny):
    run("mlmc", "--config", str(tiny), "--tol-var", "60", "--workers", "1", "-q", expect=(0, 3))
    run("mlmc", "--tol-cdf", "0.3", "--thresholds", TINY_THRESHOLDS, "--workers", "1", "-q", expect=(0, 3))
    runs = stored_runs(tiny.parent / "results.h5")
    cdf = next(r for r in runs.values() if r.method == "cdf")
    text = run("report", "results.h5").output
    assert "Variance" in text and "Distribution" in text
    # The unit of a table row in brackets (report.summary's docstring).
    variance_rows = text.split("Variance")[1].split("Distribution")[0]
    distribution_rows = text.split("Distribution")[1]
    # The unit under the QoI's name (a narrow column keeps both; a load curve's load gets a line between them).
    assert "\n [%^2] " in variance_rows and "\n [%] " in distribution_rows
    assert re.search(r"^ contact_area ", variance_rows, re.M) and re.search(r"^ contact_area ", distribution_rows, re.M)
    q05 = cdf.outcome.distribution.quantiles[0]
    assert f"q(0.05) = {q05.value:#.4g}" in text
    report = json.loads(run("report", "results.h5", "--json").stdout)
    by_method = {entry["method"]: entry for entry in report["runs"]}
    assert by_method["cdf"]["distribution"]["cdf"] == list(cdf.outcome.distribution.cdf)
    assert by_method["variance"]["estimate"] == list(next(
        r for r in runs.values() if r.method == "variance").outcome.estimate)
    assert RunRecord.from_json(by_method["cdf"]) == cdf
    written = json.loads(run("report", "results.h5", "--json", "--plots", "figures").stdout)["plots"]
    figure = tiny.parent / "figures" / "cdf_contact_area.png"
    assert str(figure) in written or "figures/cdf_contact_area.png" in written
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cdf_thresholds_and_probabilities_come_from_the_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    estimation = {"initial_samples": 4, "batch_size": 4, "distribution": {"contact_area": {
        "thresholds": {"start": 25, "stop": 60, "count": 36}, "probabilities": [0.25, 0.75]}}}
    config = write_config(tmp_path / "tiny.yaml", tiny_config(estimation=estimation))
    shown = json.loads(run("mlmc", "--config", str(config), "--tol-cdf", "0.3", "--workers", "1", "--json", "-q",
                           expect=(0, 3)).stdout)
    assert shown["distribution"]["thresholds"] == pytest.approx(np.linspace(25, 60, 36).tolist())
    assert [q["probability"] for q in shown["distribution"]["quantiles"]] == [0.25, 0.75]


BAD_OPTIONS = [
    (("--tol", "5", "--tol-var", "1"), "exactly one of --tol"),
    (("--tol-var", "1", "--tol-cdf", "0.1", "--thresholds", "1:2:3"), "exactly one of --tol"),
    (("--tol-cdf", "0.1"), "--thresholds START:STOP:COUNT"),
    (("--tol-cdf", "0.1", "--thresholds", "60:25:36"), "START < STOP"),
    (("--tol-cdf", "0.1", "--thresholds", "25:60:1"), "COUNT in 2..10000"),
    (("--tol-cdf", "0.1", "--thresholds", "25:60:10001"), "COUNT in 2..10000"),
    (("--tol-cdf", "0.1", "--thresholds", "10:30:99999999999"), "COUNT in 2..10000"),  # not a MemoryError
    (("--tol-cdf", "0.1", "--thresholds", "25:60"), "START:STOP:COUNT"),
    (("--tol-cdf", "0.1", "--thresholds", "a:b:c"), "START:STOP:COUNT"),
    (("--tol-cdf", "0.1", "--thresholds", "25:60:2.5"), "START:STOP:COUNT"),
    (("--tol-cdf", "1.5", "--thresholds", TINY_THRESHOLDS), "one number in [1e-140, 1)"),
    (("--tol-cdf", "0.1", "--thresholds", TINY_THRESHOLDS, "--qoi", "clusters"), "one result column"),
    (("--tol-cdf", "0.1", "--thresholds", TINY_THRESHOLDS, "--probabilities", "0.5,1"), "in (0, 1)"),
    (("--tol-cdf", "0.1", "--thresholds", TINY_THRESHOLDS, "--probabilities", "0.5,0.5"), "distinct numbers"),
    (("--tol-cdf", "0.1", "--thresholds", TINY_THRESHOLDS, "--probabilities", "0.5,5e-1"), "distinct numbers"),
    (("--tol", "5", "--thresholds", TINY_THRESHOLDS), "only with --tol-cdf"),
    (("--tol-var", "-1"), "positive"),
    (("--tol-var", "area=1"), "a QoI of this study"),
    (("--tol-var", "1", "--plan"), "--plan was given with --tol-var; --method, --plan"),
    (("--tol-cdf", "0.1", "--thresholds", TINY_THRESHOLDS, "--method", "auto"),
     "--method auto was given with --tol-cdf; --method, --plan"),
]


@pytest.mark.parametrize("options, text", BAD_OPTIONS, ids=[" ".join(o) for o, _ in BAD_OPTIONS])
def test_bad_options_are_one_line_status_2_and_compute_nothing(tiny, options, text):
    result = run("mlmc", "--config", str(tiny), *options, "--workers", "1", expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and text in lines[0], result.stderr
    if (tiny.parent / "results.h5").exists():
        assert stored_runs(tiny.parent / "results.h5") == {}


def test_a_cdf_of_a_study_of_several_columns_without_qoi_names_the_columns(tmp_path, monkeypatch):
    """It said "--qoi: got None"."""
    monkeypatch.chdir(tmp_path)
    qoi = {"contact_area": {"unit": "percent"}, "mean_gap": {}}
    config = write_config(tmp_path / "two.yaml", tiny_config(qoi=qoi))
    result = run("mlmc", "--config", str(config), "--tol-cdf", "0.2", "--thresholds", TINY_THRESHOLDS,
                 "--workers", "1", expect=2)
    assert result.stderr.strip() == "error: --qoi: this study has several result columns; name one of contact_area, " \
                                    "mean_gap"


def test_a_variance_run_missing_tolerances_names_every_one_at_once(tmp_path, monkeypatch):
    # A study of three QoIs named one missing tolerance per attempt ("got 'clusters'", then "got 'mean_gap'").
    monkeypatch.chdir(tmp_path)
    qoi = {"contact_area": {"unit": "percent"}, "clusters": {}, "mean_gap": {}}
    config = write_config(tmp_path / "three.yaml", tiny_config(qoi=qoi))
    result = run("mlmc", "--config", str(config), "--tol-var", "contact_area=60", "--workers", "1", expect=2)
    assert result.stderr.strip() == ("error: --tol-var: no tolerance for clusters, mean_gap; give --tol-var "
                                     "clusters=EPS --tol-var mean_gap=EPS")
    assert not (tmp_path / "results.h5").exists()


def test_a_run_refused_on_the_way_is_recorded_as_refused_with_the_reason(tiny):
    result = run("mlmc", "--config", str(tiny), "--tol-var", "1e-6", "--workers", "1", "-q", expect=2)
    (line,) = result.stderr.strip().splitlines()
    limit = "more than the 1e+07 samples a roughuq run may plan"  # (max_samples is the Python API's argument)
    assert line.startswith("error: ") and limit in line
    (record,) = stored_runs(tiny.parent / "results.h5").values()
    assert record.status == "refused" and record.reason == line.removeprefix("error: ") and record.outcome is None
    text = run("report", "results.h5").output
    assert "variance contact_area=1e-06: refused" in text and limit in " ".join(text.split())
    assert "interrupted" not in text and "running" not in text
    (shown,) = json.loads(run("report", "results.h5", "--json").stdout)["runs"]
    assert shown["status"] == "refused" and limit in shown["reason"]


def test_too_few_initial_samples_for_a_target_run_name_the_config_field(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config(estimation={"initial_samples": 3}))
    result = run("mlmc", "--config", str(config), "--tol-var", "1", "--workers", "1", expect=2)
    assert "estimation.initial_samples" in result.stderr and ">= 4" in result.stderr


@pytest.mark.parametrize("budget, option", [({}, "--max-cost"), ({"max_cost": 1e-9}, "estimation.max_cost")])
def test_a_budget_below_the_initial_samples_is_refused_before_the_study_file_is_created(tmp_path, monkeypatch,
                                                                                        budget, option):
    """The file was created from --config, then run_target refused the budget: an empty study stayed behind."""
    monkeypatch.chdir(tmp_path)
    estimation = {"initial_samples": 4, "batch_size": 4, **budget}
    config = write_config(tmp_path / "tiny.yaml", tiny_config(estimation=estimation))
    given = () if budget else ("--max-cost", "1e-9")
    result = run("mlmc", "--config", str(config), "--study", "new.h5", "--tol-var", "contact_area=60", *given,
                 "--workers", "1", expect=2)
    (line,) = result.stderr.strip().splitlines()
    where = "" if option == "--max-cost" else f"{config}: "  # a field of the config names its file first
    assert line.startswith(f"error: {where}{option} 1e-09 is too small for the initial samples"), line
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tiny.yaml"]


@pytest.mark.parametrize("target", [("--tol-var", "contact_area=60"), ("--tol-cdf", "0.3", "--thresholds",
                                                                      TINY_THRESHOLDS)], ids=["variance", "cdf"])
def test_a_run_its_budget_stops_before_its_bias_is_estimated_is_told_to_raise_the_budget_not_loosen(tiny, target):
    """Its last line said 'raise --max-cost ... or loosen --tol-var', but a looser tolerance needs the same samples."""
    refused = run("mlmc", "--config", str(tiny), *target, "--max-cost", "1e-9", "--workers", "1", expect=2).stderr
    least = float(re.search(r"which cost at least ([0-9.e+-]+) reference seconds", refused).group(1))
    # Just above the least cost of the initial samples: level 0 (drawn first, whatever it costs) takes the budget.
    result = run("mlmc", "--config", str(tiny), *target, "--max-cost", f"{1.01 * least:.6g}", "--workers", "1",
                 expect=3)
    assert "bias not estimated" in result.stdout
    # "MC/MLMC 26 predicted" compared MC to the tolerance with a run that stopped short of it.
    assert "  plain MC: " in result.stdout and not re.search(r"MC/MLMC [0-9]", result.stdout), result.stdout
    assert "ref-s predicted (no MC/MLMC ratio: the run stopped at --max-cost)" in result.stdout
    stored = json.loads(run("report", str(tiny.parent / "results.h5"), "--json").stdout)["runs"]
    assert [entry["work_ratio"] for entry in stored if entry["stop_reason"] == "max_cost"] == [None], stored
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("tolerance not met (max_cost): the run reached --max-cost before its bias was estimated; "
                           "raise --max-cost (or estimation.max_cost) or lower estimation.initial_samples"), last
    assert "loosen" not in last


def test_a_cdf_record_round_trips_and_a_malformed_quantile_is_refused_by_its_path():
    from rough_uq.errors import InvalidParameterError

    data = {
        "method": "cdf", "status": "finished", "tol": [0.1], "qoi_names": ["contact_area"], "finished": "now",
        "estimate": [0.1, 0.6, 1.02], "stat_error": [0.01, 0.02, 0.01], "bias_estimate": [0.01],
        "is_bias_estimated": True, "rmse": [0.03], "levels": [0, 1], "n_samples": [8, 4], "cost": 1.5,
        "seconds": 2, "mc_cost": 3.0, "mc_seconds_predicted": 6.0, "n_computed": 12, "n_not_converged": 0,
        "tol_met": True, "stop_reason": "tol_met",
        "distribution": {"column": "contact_area", "thresholds": [1, 2, 3], "cdf": [0.1, 0.6, 1.0],
                         "cdf_lower": [0.07, 0.57, 0.97], "cdf_upper": [0.13, 0.63, 1.0], "bandwidths": [2, 1],
                         "quantiles": [{"probability": 0.5, "value": 1.8, "lower": 1.74, "upper": None}]},
    }
    record = RunRecord.from_json(data, run_id="cdf_x")
    assert record.outcome.variance is None and record.outcome.statistics is None
    assert record.outcome.distribution.quantiles[0].upper is None
    assert record.to_json() == {**data, "max_cost": None, "forecast": None,
                                "rates": None, "warnings": []}
    data["distribution"]["quantiles"][0]["lower"] = "low"
    with pytest.raises(InvalidParameterError) as info:
        RunRecord.from_json(data, run_id="cdf_x")
    assert info.value.name == "run cdf_x.distribution.quantiles[0].lower"


@pytest.mark.parametrize("distribution, field", [
    ({"contact_area": {"thresholds": {"start": 60, "stop": 25, "count": 36}}},
     "estimation.distribution.contact_area.thresholds.stop"),
    ({"contact_area": {"thresholds": {"start": 25, "stop": 60, "count": 1}}},
     "estimation.distribution.contact_area.thresholds.count"),
    ({"contact_area": {"thresholds": {"start": 25, "stop": 60, "count": 10**8}}},  # as --thresholds: 10 000 at most
     "estimation.distribution.contact_area.thresholds.count"),
    ({"contact_area": {"probabilities": [0.5, 1.0]}}, "estimation.distribution.contact_area.probabilities"),
    ({"clusters": {}}, "estimation.distribution.clusters"),
], ids=["decreasing", "one threshold", "too many thresholds", "probability 1", "not a QoI"])
def test_bad_distribution_settings_in_the_config_name_the_field(tmp_path, distribution, field):
    config = write_config(tmp_path / "bad.yaml", tiny_config(estimation={"distribution": distribution}))
    result = run("validate", str(config), expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {config}: {field}: "), result.stderr


def test_the_cli_and_the_python_front_door_draw_the_same_samples_and_agree(tiny, monkeypatch):
    import rough_uq

    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", "estimate")  # the Python API plans FFTs with FFTW_ESTIMATE
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"], coarsest=8,
                                      max_level=2, seed=2026, solver_tol=1e-8)
    result = run("mlmc", "--config", str(tiny), "--tol-var", "60", "--workers", "1", "--json", "-q", expect=(0, 3))
    cli = json.loads(result.stdout)
    python, messages = _with_warnings(lambda: rough_uq.variance(problem, tol=60, n_initial=4, batch_size=4))
    assert any("the estimate -23.6 is negative" in m for m in messages)  # four samples a level
    # Not met for both or for neither (the CLI's status 3, the Python API's warning).
    assert any(m.startswith("variance: tolerance not met") for m in messages) == (result.exit_code == 3)
    assert cli["n_samples"] == python.n_samples.tolist()
    np.testing.assert_allclose(cli["estimate"], python.estimate, rtol=1e-9)
    result = run("mlmc", "--tol-cdf", "0.3", "--thresholds", TINY_THRESHOLDS, "--workers", "1", "--json", "-q",
                 expect=(0, 3))
    cli = json.loads(result.stdout)
    python, messages = _with_warnings(lambda: rough_uq.distribution(
        problem, tol=0.3, thresholds=np.linspace(25, 60, 36), n_initial=4, batch_size=4))
    assert any(m.startswith("distribution of contact_area: tolerance not met") for m in messages) == (
        result.exit_code == 3)
    assert cli["n_samples"] == python.cdf.n_samples.tolist()
    np.testing.assert_allclose(cli["distribution"]["cdf"], python.cdf.cdf, atol=1e-9)


def _with_warnings(call):
    """``call()``'s result and the texts of the EstimationWarnings it raised."""
    import warnings

    import rough_uq

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", rough_uq.EstimationWarning)
        value = call()
    return value, [str(w.message) for w in caught if issubclass(w.category, rough_uq.EstimationWarning)]


def test_the_variance_table_shows_no_bias_or_rmse_for_a_run_that_did_not_estimate_its_bias(tiny):
    # A run --max-cost stopped before its bias was estimated says "bias not estimated" in its lines; the table
    # showed "bias 0" and an RMSE equal to the statistical error.
    from dataclasses import replace

    from rich.console import Console

    from rough_uq.report.summary import _variance_table

    run("mlmc", "--config", str(tiny), "--tol-var", "60", "--workers", "1", "-q", expect=(0, 3))
    variance = next(r for r in stored_runs(tiny.parent / "results.h5").values() if r.method == "variance")
    units = {"contact_area": "%"}

    def row(record):
        console = Console(width=200, record=True, file=io.StringIO())
        console.print(_variance_table([record], units))
        return next(line for line in console.export_text().splitlines() if "contact_area" in line)

    # Columns: QoI, Var(Q) ± stat., sd(Q), RMSE, tol, bias, N_l (from level 0), met (at least two spaces apart).
    estimated = re.split(r"\s{2,}", row(variance).strip())
    stopped = re.split(r"\s{2,}", row(replace(variance, outcome=replace(variance.outcome,
                                                                         is_bias_estimated=False))).strip())
    assert variance.outcome.is_bias_estimated and len(estimated) == len(stopped) == 8
    assert estimated[3] != "-" and estimated[5] != "-" and stopped[3] == stopped[5] == "-"
    assert [cell for k, cell in enumerate(stopped) if k not in (3, 5)] == \
        [cell for k, cell in enumerate(estimated) if k not in (3, 5)]


def test_the_report_of_a_variance_study_says_which_runs_lack_a_screening_and_that_no_figure_was_written(tiny):
    # It said "no screening yet: run `roughuq screen ...`" (the variance run needed none), and `--plots` left an
    # empty folder without a word.
    run("mlmc", "--config", str(tiny), "--tol-var", "60", "--workers", "1", "-q", expect=(0, 3))
    result = run("report", "results.h5", "--plots", "figures")
    text = " ".join(result.stdout.split())
    assert ("no screening yet (mlmc and mc --tol need one: run `roughuq screen CONFIG --out results.h5`; --tol-var, "
            "--tol-cdf and mc --level do not)") in text
    assert text.endswith("wrote no figure (and made no folder figures): the figures draw a screening, finished mlmc "
                         "and mc --tol runs, load curves and cdf runs, and this study has none of them yet (an mc "
                         "--level run has no figure of its own: its estimate is in the report above)")
    assert not Path("figures").exists()  # was an empty folder
    Path("mine").mkdir()  # a folder of the user's stays
    mine = " ".join(run("report", "results.h5", "--plots", "mine").stdout.split())
    assert "wrote no figure to mine: the figures draw" in mine and Path("mine").is_dir()
    run("report", "results.h5", "--plots", "a/b/c")
    assert not Path("a").exists()  # nor the folders made on the way


def test_a_load_curve_variance_table_at_80_columns_keeps_the_loads_apart(tmp_path, monkeypatch):
    # Both rows of a QoI read "clusters…" (the load, which tells them apart, was cut) and "met" fell off the edge.
    from rich.console import Console

    from rough_uq.report.summary import _variance_table

    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "lc.yaml", tiny_config(load={"relative": [0.1, 0.02]},
                                                            qoi={"contact_area": {"unit": "percent"}, "clusters": {}}))
    run("mlmc", "--config", str(config), "--tol-var", "contact_area=60", "--tol-var", "clusters=1e4", "--workers",
        "1", "-q", expect=(0, 3))
    (variance,) = stored_runs(tmp_path / "results.h5").values()
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(_variance_table([variance], {"contact_area": "%", "clusters": "clusters per unit area"}))
    text = console.export_text()
    assert all(len(line) <= 80 for line in text.splitlines())
    lines = [line.split() for line in text.splitlines()]
    assert [cells[0] for cells in lines if cells and cells[0].startswith("@")] == ["@0.1", "@0.02"] * 2, text
    met = [cells[-1] for cells in lines if cells and cells[0] in ("clusters", "contact_area")]
    assert len(met) == 4 and set(met) <= {"yes", "no"}, text  # the last column, whole
    assert "…" not in text


def test_a_variance_or_cdf_run_at_max_level_is_not_told_to_screen():
    # "screen a new study with a larger grid.max_level" after --tol-var: variance and cdf runs need no screening.
    from types import SimpleNamespace

    from rough_uq.cli import _what_to_change

    outcome = SimpleNamespace(stop_reason="max_level", is_bias_estimated=True, diagnostics=())
    assert _what_to_change(outcome, "--tol").endswith("or screen a new study with a larger grid.max_level")
    for option in ("--tol-var", "--tol-cdf"):
        expected = (f"the bias needs a grid finer than grid.max_level; loosen {option}, or run it on a new study (no "
                    "screening needed) with a larger ")
        assert _what_to_change(outcome, option) == expected + "grid.max_level"

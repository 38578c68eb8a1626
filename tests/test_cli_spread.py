"""Beyond the mean through the real CLI: `roughuq mlmc --tol-var / --tol-cdf`, their records and the report."""

from __future__ import annotations

import json
import math
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
    """The shipped classic-area config on its three coarsest grids (256^2 ... 1024^2)."""
    run("init", "classic-area")
    config = yaml.safe_load((tmp_path / "classic-area.yaml").read_text())
    config["grid"]["max_level"] = 2
    config["estimation"]["initial_samples"] = 20
    # The area is about 19.3 +- 0.4 %: the grid brackets its 5 % and 95 % quantiles with a spacing of 0.05 %.
    config["estimation"]["distribution"] = {"contact_area": {"thresholds": {"start": 17.5, "stop": 21.5, "count": 81},
                                                             "probabilities": [0.05, 0.5, 0.95]}}
    config["output"]["path"] = "classic.h5"
    return write_config(tmp_path / "classic.yaml", config)


@pytest.mark.slow
def test_classic_area_variance_and_quantiles_agree_with_plain_mc_on_the_finest_level(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = _classic_config(tmp_path)
    variance = json.loads(run("mlmc", "--config", str(config), "--study", "classic.h5", "--tol-var", "0.03",
                              "--json", "-q", expect=(0, 3)).output)
    cdf = json.loads(run("mlmc", "--study", "classic.h5", "--tol-cdf", "0.05", "--json", "-q",
                         expect=(0, 3)).output)
    assert variance["tol_met"] and cdf["tol_met"], (variance["rmse"], variance["stop_reason"], cdf["rmse"])
    finest = variance["levels"][-1]
    assert cdf["levels"][-1] == finest

    # Plain MC on that level, samples of another stage (an MC run's), about 100 of them.
    mc = json.loads(run("mc", "--study", "classic.h5", "--level", str(finest), "--tol", "0.06", "--json",
                        "-q").output)
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
        assert quantile["lower"] is not None and quantile["upper"] is not None
        assert quantile["lower"] < quantile["value"] < quantile["upper"]
    print(f"\nclassic (levels 0..{finest}): Var = {variance['estimate'][0]:.4f} ± {variance['stat_error'][0]:.4f} "
          f"(RMSE {variance['rmse'][0]:.3g}, N_l {variance['n_samples']}), MC {term.mean[0]:.4f} ± "
          f"{math.sqrt(term.variance[0]):.4f} (N {samples.size}); quantiles "
          + "; ".join(f"q({q['probability']}) = {q['value']:.3f} [{q['lower']:.3f}, {q['upper']:.3f}]"
                      for q in distribution["quantiles"])
          + f" (sup RMSE {cdf['rmse'][0]:.3g}, N_l {cdf['n_samples']})")

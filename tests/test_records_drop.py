"""A run brought back after `roughuq drop`: its new record owes nothing to the dropped one."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner

from rough_uq.cli import main
from rough_uq.study.pipeline import open_existing_study
from rough_uq.study.records import read_run_records
from tests.study_configs import tiny_config, write_config

KEY = "mlmc_contact_area-5_theta-0.5"
# Far beyond the few seconds any command on the tiny study takes: a time only a stored record can give.
LONG_AGO = 1.0e6


def run(*args: str) -> object:
    result = CliRunner().invoke(main, list(args))
    assert result.exit_code == 0, (result.output, result.exception)
    return result


@pytest.fixture
def finished(tmp_path, monkeypatch) -> Path:
    """A screened tiny study with the finished run ``KEY``; the working directory."""
    monkeypatch.chdir(tmp_path)
    qoi = {"contact_area": {"unit": "percent", "tol": 2.0, "estimator": "nodes"}}
    run("screen", str(write_config(tmp_path / "tiny.yaml", tiny_config(qoi=qoi))), "--workers", "1", "--quiet")
    run("mlmc", "--tol", "5", "--workers", "1", "--quiet")
    return tmp_path


def _set_elapsed(path: Path, seconds: float) -> None:
    """Store ``seconds`` as the elapsed time of run ``KEY`` (as a long first run would have left it)."""
    with open_existing_study(path) as study:
        record = next(r for r in read_run_records(study.store) if r.run_id == KEY)
        study.store.write_run(KEY, replace(record, outcome=replace(record.outcome, elapsed=seconds)).to_json())


def _rerun() -> tuple[dict, float]:
    """Run the same mlmc command again: its JSON record and the wall seconds the command took."""
    start = time.monotonic()
    record = json.loads(run("mlmc", "--tol", "5", "--workers", "1", "--json").output)
    return record, time.monotonic() - start


def test_a_rerun_after_drop_is_timed_afresh(finished):
    run("drop", KEY)
    _set_elapsed(finished / "results.h5", LONG_AGO)
    record, seconds = _rerun()
    assert record["status"] == "finished" and record["n_computed"] == 0  # the kept samples, reused
    assert 0 < record["elapsed"] <= seconds  # this command's time, not the dropped record's
    stored = json.loads(run("report", "results.h5", "--json").output)
    assert [r["elapsed"] for r in stored["runs"] if r["run_id"] == KEY] == [record["elapsed"]]
    assert stored["dropped_runs"] == []


def test_a_rerun_of_a_finished_run_keeps_its_time(finished):
    # The contrast: a finished run that a rerun finds complete keeps the time its samples took.
    _set_elapsed(finished / "results.h5", LONG_AGO)
    record, _ = _rerun()
    assert record["n_computed"] == 0 and record["elapsed"] == LONG_AGO

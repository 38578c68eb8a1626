"""The report names every setting that defines a QoI's numbers, in its text and its JSON."""

from __future__ import annotations

import json

from click.testing import CliRunner

from rough_uq.cli import main
from tests.study_configs import tiny_config, write_config

QOI = {
    "contact_area": {"unit": "percent", "estimator": "nodes", "tol": 2.0},
    "clusters": {"connectivity": 8, "tol": 5.0},
    "area_above": {"critical_pressure": 0.5, "tol": 2.0},
}


def test_the_report_names_the_area_estimator_the_connectivity_and_the_critical_pressure(tmp_path, monkeypatch):
    # Two studies that differed in the area estimator alone (20.64 % against 25.24 %) gave reports that differed
    # in their numbers alone, and the JSON had no estimator, connectivity or critical pressure.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "study.yaml", tiny_config(qoi=QOI))
    runner = CliRunner()
    assert runner.invoke(main, ["screen", str(config), "-q"]).exit_code == 0
    text = runner.invoke(main, ["report", "results.h5"])
    assert text.exit_code == 0
    (line,) = [line for line in text.output.splitlines() if line.startswith("QoIs: ")]
    assert "contact_area [%] (estimator nodes)" in line
    assert "clusters [" in line and "] (connectivity 8)" in line
    assert "area_above [%] (critical pressure 0.5)" in line
    report = json.loads(runner.invoke(main, ["report", "--json", "results.h5"]).output)
    assert report["config"]["qoi_settings"] == {
        "contact_area": {"estimator": "nodes"}, "clusters": {"connectivity": 8},
        "area_above": {"critical_pressure": 0.5},
    }

"""`roughuq mlmc --tol-cdf` through the real CLI on thresholds that miss the samples (fast, tiny study)."""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from rough_uq.cli import main
from rough_uq.report.summary import read_report, run_label
from rough_uq.study.records import read_run_records
from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config


@pytest.mark.parametrize("thresholds", ["1:10:10", "80:99:20"])
def test_a_cdf_run_whose_thresholds_miss_the_samples_is_not_met_and_says_why(tmp_path, monkeypatch, thresholds):
    # The tiny study's contact area is about 35-55 %: every indicator was 0 (or 1) on every sample, and the run
    # printed "sup-norm RMSE 0 <= tol 0.1" and "tolerance met" (exit 0) next to warnings on the quantiles.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.1", "--thresholds",
                                       thresholds, "--workers", "1", "--json", "-q"])
    assert result.exit_code == 3, (result.output, result.exception)
    shown = json.loads(result.stdout)
    # Its RMSE rests on variances of 0: not an error (was [0.0]).
    assert not shown["tol_met"] and shown["stop_reason"] == "thresholds_miss_samples" and shown["rmse"] is None
    assert "tolerance not met (thresholds_miss_samples)" in result.stderr
    assert "put thresholds among the values" in result.stderr  # not "loosen --tol-cdf, raise --max-cost"
    # Terms of exactly 0 with no spread are not noise: no advice to draw more samples for the bias.
    assert not any("within their noise" in text for text in shown["warnings"])
    # The stored warning names the thresholds and, per level, the range of the values the run used.
    start, stop, _ = (float(text) for text in thresholds.split(":"))
    (message,) = [text for text in shown["warnings"] if text.startswith("cdf: ")]
    assert message.startswith(f"cdf: the thresholds [{start:g}, {stop:g}] miss the samples of level 0 (values ")
    with open_study_readonly(tmp_path / "results.h5") as store:
        for level, n in zip(shown["levels"], shown["n_samples"]):
            batch = store.read_samples(level=level, stage=shown["stage"])
            used = np.argsort(batch.indices)[:n]
            values = batch.fine[used, 0] if level == 0 else np.concatenate([batch.fine[used, 0], batch.coarse[used, 0]])
            assert f"level {level} (values {values.min():.4g} .. {values.max():.4g})" in message
            assert np.all(values > stop) or np.all(values < start)


def test_the_report_of_such_a_run_shows_no_error_it_did_not_measure(tmp_path, monkeypatch):
    # The report printed "sup-norm RMSE 0 <= tol 0.1" under NOT MET, and the raw reason.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.1", "--thresholds", "1:10:10",
                                    "--workers", "1", "-q"])
    assert run.exit_code == 3, (run.output, run.exception)
    report = CliRunner().invoke(main, ["report", str(tmp_path / "results.h5")], terminal_width=200)
    assert report.exit_code == 0, (report.output, report.exception)
    assert "sup-norm RMSE not measured (the thresholds miss a level's samples), tol 0.1" in report.stdout
    assert "RMSE 0 <=" not in report.stdout
    assert "the thresholds miss the samples of a level, whose variance they do not measure" in report.stdout
    # The Distribution table showed "sup RMSE 0", the figure a band of width 0 labelled "sup RMSE 0".
    # (The run's cells are on its first row, the first quantile's.)
    (row,) = [line.split() for line in report.stdout.splitlines() if line.split()[:2] == ["contact_area", "0.05"]]
    assert row[4:6] == ["-", "0.1"], row
    assert json.loads(CliRunner().invoke(main, ["report", "results.h5", "--json"]).stdout)["runs"][0]["rmse"] is None
    from rough_uq.report.figures import _cdf_figure
    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.study.records import read_run_records

    with open_existing_study(tmp_path / "results.h5", writable=False) as study:
        (record,) = read_run_records(study.store)
    captured = {}
    monkeypatch.setattr("rough_uq.report.figures._save", lambda figure, path: captured.setdefault("figure", figure))
    _cdf_figure([record], "contact_area", "%", tmp_path / "cdf.png")
    (ax,) = captured["figure"].axes
    assert [text.get_text() for text in ax.get_legend().get_texts()] == [
        "MLMC, tol 0.1: RMSE not measured (thresholds miss samples)"]
    assert not ax.collections  # no band
    # A quantile such a run brackets got the error bar of the band of its unmeasured RMSE ([v, v]).
    from dataclasses import replace

    from rich.console import Console

    from rough_uq.report.summary import _cdf_lines, _distribution_table
    from rough_uq.study.records import QuantileRecord

    bracketed = QuantileRecord(probability=0.5, value=5.0, lower=5.0, upper=5.0)
    distribution = replace(record.outcome.distribution, quantiles=(bracketed,))
    shown = replace(record, outcome=replace(record.outcome, distribution=distribution))
    assert "  q(0.5) = 5.000 % (error not measured)" in _cdf_lines(shown.outcome, 0.1, {"contact_area": "%"})
    console = Console(width=120, record=True)
    console.print(_distribution_table([shown], {"contact_area": "%"}))
    lines = console.export_text().splitlines()
    (row,) = [line.split() for line in lines if line.split()[:2] == ["contact_area", "0.5"]]
    assert row[2:5] == ["5.000", "-", "-"], row
    captured.clear()
    _cdf_figure([shown], "contact_area", "%", tmp_path / "cdf.png")
    (ax,) = captured["figure"].axes
    assert not ax.containers  # the quantile as a point, without an error bar


def test_quantiles_are_printed_to_four_significant_digits_trailing_zeros_kept():
    # q(0.05) = 18.6 beside q(0.5) = 20.45: the trailing zero was dropped, the first read as less precise.
    from rough_uq.report.summary import _quantile_text
    from rough_uq.study.records import QuantileRecord

    for value, lower, upper, text in [
        (18.6, 18.25, None, "18.60 [18.25, inf]"),
        (1000.0, None, 1003.0, "1000 [-inf, 1003]"),
        (2.5e-7, 2.0e-7, 3.0e-7, "2.500e-07 [2.000e-07, 3.000e-07]"),
    ]:
        quantile = QuantileRecord(probability=0.05, value=value, lower=lower, upper=upper)
        outcome = SimpleNamespace(stop_reason="tol_met", is_bias_estimated=True)
        assert _quantile_text(quantile, "%", outcome) == f"q(0.05) = {text} %"


def test_a_cdf_run_on_thresholds_far_coarser_than_the_spread_is_not_met_and_says_to_refine_them(tmp_path, monkeypatch):
    # --thresholds 0:100:3 (spacing 50, the default bandwidth 100, 25 on level 2) against contact areas within a
    # few percent of each other: the smoothed CDF was about 1/2 everywhere and the run exited 0, "tolerance met".
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.1", "--thresholds", "0:100:3",
                                       "--workers", "1", "--json", "-q"])
    assert result.exit_code == 3, (result.output, result.exception)
    shown = json.loads(result.stdout)
    assert not shown["tol_met"] and shown["stop_reason"] == "bandwidth_too_wide"
    assert "give finer thresholds (--thresholds or the config's thresholds)" in result.stderr
    (message,) = [text for text in shown["warnings"] if text.startswith("cdf: ")]
    assert message.startswith(f"cdf: the smoothing bandwidth on the finest level {shown['levels'][-1]}, ")
    # "the bias estimate 0.184 ... rests on level terms within their noise" beside "the bias is not estimated".
    assert not [text for text in shown["warnings"] if "within their noise" in text], shown["warnings"]
    report = CliRunner().invoke(main, ["report", str(tmp_path / "results.h5")], terminal_width=200)
    assert report.exit_code == 0, (report.output, report.exception)
    assert "the smoothing bandwidth exceeds twice the spread of the values; the bias is not estimated" in report.stdout
    # Its Distribution table showed the statistical error alone as its "sup RMSE" (0.05): "-", as for variance;
    # and its quantiles' error bars, that band's (q(0.05) = 1.804 [0.8969, 2.072] % where the truth was 18.6).
    (row,) = [line.split() for line in report.stdout.splitlines() if line.split()[:2] == ["contact_area", "0.05"]]
    assert row[3:6] == ["-", "-", "0.1"], row
    # and its JSON, from a file written before as now: no band, open bars.
    (stored,) = json.loads(CliRunner().invoke(main, ["report", "results.h5", "--json"]).stdout)["runs"]
    band = stored["distribution"]
    assert set(band["cdf_lower"]) == {0.0} and set(band["cdf_upper"]) == {1.0}
    assert all(q["lower"] is None and q["upper"] is None for q in band["quantiles"])
    assert all(q["lower"] is None and q["upper"] is None for q in shown["distribution"]["quantiles"]), shown
    run = CliRunner().invoke(main, ["mlmc", "--study", "results.h5", "--tol-cdf", "0.1", "--thresholds", "0:100:3",
                                    "--workers", "1"])
    assert run.exit_code == 3, (run.output, run.exception)
    lines = [line for line in run.stdout.splitlines() if line.startswith("  q(")]
    assert len(lines) == 3, lines
    assert all(line.endswith(" % (no error bar: smoothing bias not estimated)") for line in lines), lines


def test_the_distribution_table_has_one_line_per_quantile_at_80_columns(tmp_path, monkeypatch):
    # At 80 columns every row wrapped over two lines: error bars split ("[-inf," / "19.85]"), N_l too, and the
    # run's RMSE, tol, N_l and met were repeated on every quantile's row.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.2", "--thresholds", "20:70:51",
                                    "--workers", "1", "-q"])
    assert run.exit_code in (0, 3), (run.output, run.exception)
    report = CliRunner().invoke(main, ["report", "results.h5"], terminal_width=80)
    lines = report.stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("Distribution"))
    # Under the QoI its unit and its thresholds, which tell apart the runs of one column and tolerance.
    assert [line.strip() for line in lines[start + 5:start + 8]] == ["[%]", "s 20 .. 70", "(51 values)"], lines
    rows = [line for line in lines[start + 4:] if line.strip() not in ("", "[%]", "s 20 .. 70", "(51 values)")][:3]
    assert [line.split()[0] for line in rows] == ["contact_area", "0.5", "0.95"], rows  # one line each
    assert all(line.count("[") == line.count("]") == 1 for line in rows), rows  # whole error bars
    assert len(rows[0].split()) > len(rows[1].split()) == len(rows[2].split()) == 4, rows  # p, q_p, error bar


def test_the_cdf_figure_says_which_run_missed_its_tolerance(tmp_path, monkeypatch):
    # A run NOT MET with an error band (at grid.max_level, at --max-cost) was drawn and labelled as a met one.
    import dataclasses

    from rough_uq.report.figures import _cdf_figure
    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.study.records import read_run_records

    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.5", "--thresholds", "0:100:51",
                                    "--workers", "1", "-q"])
    assert run.exit_code == 3, (run.output, run.exception)  # NOT MET (max_level), with its error band
    with open_existing_study(tmp_path / "results.h5", writable=False) as study:
        (missed,) = read_run_records(study.store)
    met = dataclasses.replace(missed, outcome=dataclasses.replace(missed.outcome, tol_met=True))
    captured = []
    monkeypatch.setattr("rough_uq.report.figures._save", lambda figure, path: captured.append(figure))
    _cdf_figure([met, missed], "contact_area", "%", tmp_path / "cdf.png")
    (ax,) = captured[0].axes
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert labels[0].endswith("(band)") and labels[1] == labels[0] + ", NOT MET", labels


def test_a_cdf_run_whose_bandwidth_withdraws_its_bias_does_not_also_warn_of_a_noisy_bias(tmp_path, monkeypatch):
    # The quickstart at max_level 2 with --thresholds 0:40:3 (an audit): the run warned "the bias estimate 0.184
    # ... rests on level terms within their noise" beside "so the bias is not estimated" (bandwidth too wide).
    monkeypatch.chdir(tmp_path)
    assert CliRunner().invoke(main, ["init", "quickstart", "-q"]).exit_code == 0
    config = yaml.safe_load((tmp_path / "quickstart.yaml").read_text())
    config["grid"]["max_level"] = 2
    write_config(tmp_path / "quickstart.yaml", config)
    result = CliRunner().invoke(main, ["mlmc", "--config", "quickstart.yaml", "--tol-cdf", "0.1", "--thresholds",
                                       "0:40:3", "--workers", "1", "--json", "-q"])
    assert result.exit_code == 3, (result.output, result.exception)
    shown = json.loads(result.stdout)
    assert shown["stop_reason"] == "bandwidth_too_wide" and shown["levels"][-1] == 2, shown
    assert [text[:40] for text in shown["warnings"]] == ["cdf: the smoothing bandwidth on the fine"], shown


def test_the_cdf_column_of_a_load_curve_takes_the_load_written_as_tol_takes_it(tmp_path, monkeypatch):
    # `--tol contact_area@5=0.5` was taken, `--tol-cdf 0.2 --qoi contact_area@5` refused ("allowed: ...@5.0").
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "curve.yaml", tiny_config(load={"relative": [0.2, 5]}))
    for column in ("contact_area@5", "contact_area@5.0"):
        result = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.3", "--qoi", column,
                                           "--thresholds", "99:101:5", "--workers", "1", "--json", "-q"])
        assert result.exit_code in (0, 3), (result.output, result.exception)
        assert json.loads(result.stdout)["distribution"]["column"] == "contact_area@5.0"
    assert len(read_report("results.h5")["runs"]) == 1  # one run: the second command found the first one's
    refused = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.3", "--qoi",
                                        "contact_area@6", "--thresholds", "99:101:5"])
    assert refused.exit_code == 2 and "--qoi: got 'contact_area@6'; allowed: one result column" in refused.stderr


def test_cdf_runs_of_one_tolerance_with_other_thresholds_read_apart_in_the_report(tmp_path, monkeypatch):
    # Three runs at tol 0.1 with other thresholds: every row of the Distribution table and every warning read
    # "contact_area ... 0.1" / "cdf, tol contact_area=0.1, theta 0.5", whichever run it was.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    for thresholds, probabilities in (("0:100:3", []), ("20:70:51", ["--probabilities", "0.1,0.9"])):
        run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.2", "--thresholds",
                                        thresholds, *probabilities, "--workers", "1", "-q"])
        assert run.exit_code in (0, 3), (run.output, run.exception)
    report = CliRunner().invoke(main, ["report", "results.h5"], terminal_width=200)
    warned = {line.split(": ")[1] for line in report.stdout.splitlines() if line.startswith("warning: cdf")}
    assert "cdf, tol contact_area=0.2, theta 0.5, thresholds 0 .. 100 (3)" in warned, warned
    with open_study_readonly("results.h5") as stored:
        labels = sorted(run_label(record, ["contact_area"]) for record in read_run_records(stored))
    assert labels == ["cdf, tol contact_area=0.2, theta 0.5, thresholds 0 .. 100 (3)",
                      "cdf, tol contact_area=0.2, theta 0.5, thresholds 20 .. 70 (51), p 0.1, 0.9"], labels
    assert all(label.startswith("cdf, tol contact_area=0.2, theta 0.5, thresholds ") for label in warned), warned
    cells = [line.strip() for line in report.stdout.splitlines() if line.strip().startswith("s ")]
    assert cells == ["s 0 .. 100", "s 20 .. 70"], cells


def test_interrupted_cdf_runs_of_one_tolerance_read_apart(tmp_path, monkeypatch, ctrl_c_after_one_sample):
    # Both read "cdf contact_area=0.2: interrupted; rerun the same command to resume": which command?
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    for thresholds in ("0:100:3", "20:70:51"):
        run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.2", "--thresholds",
                                        thresholds, "--workers", "1", "-q"])
        assert run.exit_code == 130, (run.output, run.exception)
    report = CliRunner().invoke(main, ["report", "results.h5"], terminal_width=200).stdout
    heads = sorted(line for line in report.splitlines() if line.endswith("interrupted; rerun the same command to "
                                                                           "resume"))
    assert len(heads) == 2 and heads[0] != heads[1], heads
    assert all(re.fullmatch(r"cdf contact_area=0\.2, request [0-9a-f]{8}: interrupted; .*", head) for head in heads)


def test_a_cdf_runs_stored_bias_is_at_most_one_as_the_apis(tmp_path, monkeypatch):
    # Thresholds that miss two of three levels' samples: the level terms extrapolated a bias of 1.9 for a CDF, which
    # the API's CdfEstimate caps at 1 and the study file stored as it was.
    monkeypatch.chdir(tmp_path)
    surface = {"system_size": 2.0, "wavenumbers": {"k_l": 2, "k_r": 2, "k_s": 16}, "hurst": 0.8, "rms_height": 1.0}
    config = write_config(tmp_path / "tiny.yaml", tiny_config(surface=surface, load={"relative": 1e-5}, seed=1,
                                                              grid={"coarsest": 32, "max_level": 2},
                                                              estimation={"initial_samples": 32}))
    run = CliRunner().invoke(main, ["mlmc", "--config", str(config), "--tol-cdf", "0.3", "--thresholds", "0:0.01:21",
                                    "--workers", "1", "-q"])
    assert run.exit_code == 3, (run.output, run.exception)
    (record,) = json.loads(CliRunner().invoke(main, ["report", "results.h5", "--json"]).stdout)["runs"]
    assert record["stop_reason"] == "thresholds_miss_samples" and record["bias_estimate"] == [1.0]

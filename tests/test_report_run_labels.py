"""A load-curve run is named in the report by a short label, not by its run id of hundreds of characters."""

from __future__ import annotations

import io
import itertools
import json
import os
import re
from dataclasses import replace

import pytest

from rough_uq.problem.runs import run_id
from rough_uq.report.summary import render_report
from rough_uq.study.records import RatesRecord, RunRecord

CURVE = [0.2, 0.02, 0.1, 0.05, 0.3]  # relative loads
COLUMNS = ("contact_area@0.02", "contact_area@0.2", "mean_gap@0.02", "mean_gap@0.2")


def _rates(n_qoi: int) -> RatesRecord:
    per_qoi = (1.0,) * n_qoi
    return RatesRecord(alpha=per_qoi, alpha_se=per_qoi, beta=per_qoi, beta_se=per_qoi, gamma=2.0, gamma_se=0.1,
                       c_alpha=per_qoi, c_beta=per_qoi, c_gamma=1.0, levels_alpha=((1, 2),) * n_qoi,
                       levels_beta=((1, 2),) * n_qoi, levels_gamma=(1, 2))


def _record(kind: str, tol: tuple[float, ...], theta: float) -> RunRecord:
    """A run of ``kind``: mlmc, mlmc-richardson, mc-tol (the screening chose level 1) or mc-level-<l>."""
    method = kind.split("-")[0]
    level = int(kind.rsplit("-", 1)[1]) if kind.startswith("mc-level") else None
    key = run_id(method, COLUMNS, tol, theta, level, richardson=kind == "mlmc-richardson")
    return RunRecord(run_id=key, method=method, status="running", tol=tol, qoi_names=COLUMNS, theta=theta,
                     level=1 if kind == "mc-tol" else level,
                     screening_rates=None if level is not None else _rates(len(COLUMNS)))


def test_labels_tell_apart_every_run_the_run_ids_tell_apart():
    from rough_uq.report.summary import run_label

    kinds = ("mlmc", "mlmc-richardson", "mc-tol", "mc-level-1", "mc-level-2")
    runs = [_record(kind, tol, theta) for kind in kinds for tol in itertools.product((1.0, 2.5), repeat=4)
            for theta in (0.5, 0.25)]
    labels = {run.run_id: run_label(run, COLUMNS) for run in runs}
    assert len(set(labels)) == len(runs) and len(set(labels.values())) == len(runs)
    # mc on a given level is named by it; mc --tol (which chose level 1) is not.
    assert labels[run_id("mc", COLUMNS, (1.0,) * 4, 0.5, 1)].startswith("mc on level 1, tol ")
    assert labels[run_id("mc", COLUMNS, (1.0,) * 4, 0.5)].startswith("mc, tol ")
    # A QoI whose loads share a tolerance is written once.
    assert labels[run_id("mlmc", COLUMNS, (2.5, 2.5, 1.0, 2.5), 0.5)] == (
        "mlmc, tol contact_area=2.5, mean_gap=1, mean_gap@0.2=2.5, theta 0.5"
    )


@pytest.fixture(scope="module")
def curve_report(tmp_path_factory):
    """The ``report --json`` of a 5-load study with two MLMC runs at different tolerances (real CLI)."""
    from click.testing import CliRunner

    from rough_uq.cli import main
    from tests.study_configs import tiny_config, write_config

    directory = tmp_path_factory.mktemp("labels")
    qoi = {"contact_area": {"tol": 4.0}, "mean_gap": {"tol": 0.1}}
    study = str(directory / "curve.h5")
    path = write_config(directory / "curve.yaml", tiny_config(load={"relative": CURVE}, qoi=qoi,
                                                                output={"path": study}))
    previous = os.getcwd()
    os.chdir(directory)
    try:
        for args in (["screen", str(path)], ["mlmc", "--study", study], ["mlmc", "--study", study, "--tol",
                                                                         "mean_gap@0.02=0.2"]):
            result = CliRunner().invoke(main, [*args, "--workers", "1", "--quiet"])
            assert result.exit_code == 0, (args, result.output, result.exception)
        result = CliRunner().invoke(main, ["report", study, "--json"])
        assert result.exit_code == 0, result.output
    finally:
        os.chdir(previous)
    return json.loads(result.output)


def _rendered(report: dict) -> str:
    from rich.console import Console

    out = io.StringIO()
    render_report(report, Console(file=out, width=1000))  # no line but a table title wraps
    return out.getvalue()


def test_load_curve_tables_are_headed_by_labels_and_the_ids_stay_findable(curve_report):
    ids = [run["run_id"] for run in curve_report["runs"]]
    assert len(ids) == 2 and all(len(key) > 200 for key in ids)
    text = _rendered(curve_report)
    # A table's title wraps at the table's width: read it across its lines.
    headings = re.findall(r"Load curve of (.*?) \(estimate ± RMSE\)", " ".join(text.split()))
    assert len(headings) == 2 and len(set(headings)) == 2
    for heading in headings:
        assert len(heading) <= 80 and not any(key in heading for key in ids), heading
        assert heading.startswith("mlmc, tol contact_area=4, mean_gap=0.1") and heading.endswith(", theta 0.5")
    assert "mean_gap@0.02=0.2" in headings[1] and "mean_gap@0.02" not in headings[0]
    # The runs' own headings give the tolerances the same way (they listed all ten columns).
    heads = [line.split(": ")[0] for line in text.splitlines() if line.startswith("mlmc ")]
    assert heads == ["mlmc contact_area=4, mean_gap=0.1", "mlmc contact_area=4, mean_gap=0.1, mean_gap@0.02=0.2"]
    # The ids, which `roughuq drop` and `roughuq show --stage` take, are in the text and in the JSON.
    samples_line = next(line for line in text.splitlines() if line.startswith("samples stored"))
    assert all(key in samples_line for key in ids)
    assert [entry["run_id"] for entry in curve_report["load_curves"]] == ids


@pytest.fixture(scope="module")
def memory_curve():
    """A screened 3-load study of two QoIs in memory, with MLMC at the config's tolerances and one column apart."""
    import numpy as np

    from rough_uq.study.executors import SerialExecutor
    from rough_uq.study.pipeline import run_estimation, run_screening
    from rough_uq.study.progress import Progress
    from tests.test_plots import _study

    study = _study(load={"relative": [0.1, 0.2, 0.3]}, qoi={"contact_area": {"tol": 4.0}, "mean_gap": {"tol": 0.1}})
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    for tol in ([4.0, 4.0, 4.0, 0.1, 0.1, 0.1], [4.0, 4.0, 4.0, 0.2, 0.1, 0.1]):
        run_estimation(study, method="mlmc", tol=np.array(tol), executor=SerialExecutor(), progress=Progress())
    return study


def test_run_warnings_start_with_the_label_and_the_drop_hint_keeps_the_id(memory_curve):
    from rough_uq.report.summary import study_report
    from rough_uq.study.store import MemoryStore

    source = memory_curve.store
    store = MemoryStore(qoi_names=source.qoi_names)
    finished = source.read_runs()[0]
    names = finished["qoi_names"]
    store.write_run(finished["run_id"], {**finished, "warnings": ["the kurtosis of level 2 is large"]})
    loose = run_id("mlmc", names, (8.0,) * 6, 0.5)  # a run whose process died: its record says "running"
    store.write_run(loose, {"method": "mlmc", "stage": 7, "status": "running", "tol": [8.0] * 6,
                            "qoi_names": names, "theta": 0.5})
    report = study_report(store, memory_curve.config)
    ids = [finished["run_id"], loose]
    assert all(len(key) > 100 for key in ids)
    (diagnostic,) = [text for text in report["warnings"] if "kurtosis" in text]
    assert diagnostic == "mlmc, tol contact_area=4, mean_gap=0.1, theta 0.5: the kurtosis of level 2 is large"
    (interrupted,) = [text for text in report["warnings"] if "interrupted" in text]
    assert interrupted.startswith("mlmc, tol contact_area=8, mean_gap=8, theta 0.5: interrupted; ")
    assert interrupted.count(loose) == 1 and interrupted.endswith(f"`roughuq drop {loose}` to forget it")
    assert finished["run_id"] not in " ".join(report["warnings"])
    # The JSON keeps each run's warnings by id, for a consumer that read the id off the text.
    assert report["run_warnings"] == [
        {"run_id": ids[0], "label": diagnostic.split(": ")[0], "message": "the kurtosis of level 2 is large"},
        {"run_id": loose, "label": interrupted.split(": ")[0], "message": interrupted.split(": ", 1)[1]},
    ]


def test_screening_predictions_name_the_tolerances_grouped_by_qoi(memory_curve):
    from rich.console import Console

    from rough_uq.report.summary import render_screening
    from rough_uq.study.records import read_screening_record

    screening = read_screening_record(memory_curve.store)
    names = screening.qoi_names
    assert len(names) == 6 and screening.predictions
    out = io.StringIO()
    render_screening(Console(file=out, width=1000), screening, names)
    text = out.getvalue()
    table = text[text.index("Predicted from the screening"):]
    for plan in screening.predictions:
        contact, gap = plan.tol[0], plan.tol[3]
        assert plan.tol == (contact,) * 3 + (gap,) * 3
        assert re.search(rf"contact_area={contact:.3g} .*\n *mean_gap={gap:.3g} ", table), table
    assert "@" not in table


def test_a_run_heading_names_a_theta_other_than_the_default():
    # Two runs that differ in theta alone were both headed "mlmc contact_area=0.7: ...".
    from rough_uq.report.summary import format_run

    usual, other = _record("mlmc", (1.0,) * 4, 0.5), _record("mlmc", (1.0,) * 4, 0.3)
    assert format_run(usual, COLUMNS, {}) == ["mlmc contact_area=1, mean_gap=1: running (another process is "
                                              "computing it)"]
    assert format_run(other, COLUMNS, {})[0].startswith("mlmc contact_area=1, mean_gap=1, theta 0.3: running")


def test_the_heading_of_mc_on_a_given_level_names_the_level():
    # `mc --tol 1` and `mc --level 1 --tol 1` were both headed "mc contact_area=1, ...: interrupted; rerun the same
    # command to resume", which did not say which command.
    from rough_uq.report.summary import format_run

    chosen, given = _record("mc-tol", (1.0,) * 4, 0.5), _record("mc-level-1", (1.0,) * 4, 0.5)
    interrupted = [replace(run, status="interrupted") for run in (chosen, given)]
    assert format_run(interrupted[0], COLUMNS, {})[0].startswith("mc contact_area=1, mean_gap=1: interrupted")
    assert format_run(interrupted[1], COLUMNS, {})[0].startswith("mc on level 1, contact_area=1, mean_gap=1: interr")


def test_a_table_is_printed_wider_than_the_terminal_only_where_squeezing_would_cut_a_word():
    from rich.console import Console

    from rough_uq.report.summary import _print_table, _table

    def printed(cells: list[str], width: int) -> list[str]:
        table = _table("t")
        for j in range(len(cells)):
            table.add_column(f"c{j}", justify="right")
        table.add_row(*cells)
        out = io.StringIO()
        _print_table(Console(file=out, width=width, color_system=None), table)
        return out.getvalue().splitlines()

    # Cells that wrap at their spaces (a load curve's values) fit a narrow terminal as before.
    lines = printed(["20.15 ± 0.30"] * 4, 40)  # 56 characters wide unsqueezed
    assert max(map(len, lines)) <= 40 and "…" not in "".join(lines)
    # A word rich would cut ("0.02…") or fold ("contact_" / "area=0.2" / "5"): the table keeps its natural width.
    words = ["contact_area=0.25", "0.029912", "0.0044721", "12345.678", "0.08445"]
    lines = printed(words, 30)
    assert max(map(len, lines)) > 30 and all(word in "".join(lines).split() for word in words)


def test_an_error_beside_its_tolerance_never_reads_as_equal_to_it():
    # An audit's cdf run printed "sup-norm RMSE 0.1 > tol 0.1" (RMSE 0.10364) and its table RMSE 0.1, tol 0.1, met no.
    from types import SimpleNamespace

    from rough_uq.report.summary import _error_text

    estimated = SimpleNamespace(is_bias_estimated=True)
    assert _error_text(estimated, 0.10364, 0.1, "sup-norm ") == "sup-norm RMSE 0.104 > tol 0.1"
    assert _error_text(estimated, 0.0999, 0.1) == "RMSE 0.0999 <= tol 0.1"
    assert _error_text(estimated, 0.39, 0.5) == "RMSE 0.39 <= tol 0.5"  # two digits where they tell apart
    assert _error_text(estimated, 0.1, 0.1) == "RMSE 0.1 <= tol 0.1"
    assert _error_text(estimated, 0.1234, 0.123) == "RMSE 0.1234 > tol 0.123"  # it read "RMSE 0.12 > tol 0.123"
    # The share of an mc --level run: the bound printed as finely as the error.
    assert _error_text(SimpleNamespace(is_bias_estimated=False), 0.1801, 0.18 / 0.9, share=0.9) == (
        "stat. error 0.1801 > 0.18, its share of tol 0.2")


def test_a_tiny_value_is_printed_to_its_errors_second_digit_too():
    # A variance of a mean gap printed "2.13623e-07 ± 3.8e-08": four digits its error does not support.
    from rough_uq.report.summary import value_error_text

    assert value_error_text(2.13623e-07, 3.8e-08) == "2.14e-07 ± 3.8e-08"
    assert value_error_text(9.96e-08, 3.8e-08) == "1.0e-07 ± 3.8e-08"  # its zeros kept (it read 1e-07)
    assert value_error_text(2e-07, 9.96e-09) == "2.000e-07 ± 1.0e-08"
    assert value_error_text(20.148, 0.30) == "20.15 ± 0.30"  # fixed decimals, as before
    assert value_error_text(0.0, 3e-10) == "0 ± 3.0e-10"

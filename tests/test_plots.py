"""Figures of a study report and of one sample: files written, data missing, sample recomputed exactly."""

from __future__ import annotations

import copy
import io
import re
import sys

import numpy as np
import pytest
from rich.console import Console

from rough_uq.report import figures as plots
from rough_uq.study.config import config_from_dict
from rough_uq.errors import RoughUQError
from rough_uq.study.executors import SerialExecutor
from rough_uq.study.pipeline import Study, build_model, run_estimation, run_screening
from rough_uq.study.progress import Progress
from rough_uq.multilevel.rates import EXACT_RATE
from rough_uq.physics.qoi import evaluate_qoi, label_clusters
from rough_uq.report.summary import render_load_curves, study_report
from rough_uq.problem.sampler import STAGE_SCREENING, compute_batch, is_coupled_stage, run_stage, solve_sample
from rough_uq.study.store import MemoryStore
from tests.study_configs import tiny_config

pytest.importorskip("matplotlib")

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
ALL_FIGURES = ["rates.png", "cost_vs_tol.png", "samples_per_level.png"]


def _study(**overrides: object) -> Study:
    config = config_from_dict(tiny_config(**overrides))
    return Study(config, MemoryStore(qoi_names=config.qoi_names))


@pytest.fixture(scope="module")
def report() -> dict:
    """Screening, MLMC at two tolerances and MC at the looser one, on grids 8..32."""
    study = _study()
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    for method, tol in (("mlmc", 4.0), ("mlmc", 2.0), ("mc", 4.0)):
        run_estimation(study, method=method, tol=np.array([tol]), executor=SerialExecutor(), progress=Progress())
    return study_report(study.store, study.config)


@pytest.fixture
def figures(monkeypatch) -> dict:
    """The matplotlib figures the next calls save, by file name."""
    drawn = {}
    save = plots._save

    def keep(figure, path):
        drawn[path.name] = figure
        return save(figure, path)

    monkeypatch.setattr(plots, "_save", keep)
    return drawn


def _lines(ax) -> dict:
    """The lines of ``ax`` by legend label (those without a label left out)."""
    return {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}


def _legend_texts(ax) -> list[str]:
    return [text.get_text() for text in ax.get_legend().get_texts()]


def _assert_pngs(paths: list, names: list[str]) -> None:
    assert [path.name for path in paths] == names
    for path in paths:
        data = path.read_bytes()
        assert data.startswith(PNG_MAGIC), path
        assert len(data) > len(PNG_MAGIC)


def test_report_figures_are_written(tmp_path, report):
    directory = tmp_path / "not" / "there"
    paths = plots.write_report_plots(report, directory)
    _assert_pngs(paths, ALL_FIGURES)
    assert all(path.parent == directory for path in paths)
    assert sorted(p.name for p in directory.iterdir()) == sorted(ALL_FIGURES)


def test_nothing_to_draw_writes_nothing(tmp_path, report):
    empty = _study()
    assert plots.write_report_plots(study_report(empty.store, empty.config), tmp_path / "empty") == []
    assert not (tmp_path / "empty").exists()  # no empty folder made
    (tmp_path / "mine").mkdir()
    assert plots.write_report_plots(study_report(empty.store, empty.config), tmp_path / "mine") == []
    assert (tmp_path / "mine").is_dir()  # the caller's folder stays
    # Interrupted runs and no screening: nothing either.
    interrupted = dict(report, screening=None, runs=[dict(run, status="running") for run in report["runs"]])
    assert plots.write_report_plots(interrupted, tmp_path / "interrupted") == []


def test_screening_only_skips_the_run_figures(tmp_path, report):
    paths = plots.write_report_plots(dict(report, runs=[]), tmp_path)
    _assert_pngs(paths, ["rates.png", "cost_vs_tol.png"])


def test_runs_without_screening_skip_the_rates(tmp_path, report):
    # One MLMC run and no MC run: the samples figure has one panel and MLMC bars only.
    first_mlmc = next(run for run in report["runs"] if run["method"] == "mlmc")
    paths = plots.write_report_plots(dict(report, screening=None, runs=[first_mlmc]), tmp_path)
    _assert_pngs(paths, ["cost_vs_tol.png", "samples_per_level.png"])


def test_missing_matplotlib_is_a_user_error(tmp_path, report, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(RoughUQError, match=r"pip install 'roughuq\[plot\]'"):
        plots.write_report_plots(report, tmp_path)
    model = build_model(config_from_dict(tiny_config()))
    with pytest.raises(RoughUQError, match="matplotlib"):
        plots.write_sample_figure(model=model, stage=STAGE_SCREENING, level=0, index=0, path=tmp_path / "s.png")


SAMPLE_QOI = {"contact_area": {"unit": "percent"}, "clusters": {"connectivity": 8}, "mean_gap": {}}


@pytest.mark.parametrize(
    "stage, level",
    [
        (STAGE_SCREENING, 2),  # coupled, fine solve warm-started from the coarse one
        (run_stage("mlmc", "plots"), 0),  # coupled stage, level 0: no coarse solve
        (run_stage("mc", "plots"), 1),  # MC stage: fine grid only
    ],
)
def test_recomputed_sample_is_the_stored_one(stage, level):
    model = build_model(config_from_dict(tiny_config(qoi=SAMPLE_QOI)))
    index = 3
    batch = compute_batch(model, stage=stage, level=level, indices=[index])
    sample = solve_sample(model, stage=stage, level=level, index=index)
    heights, solution = sample.heights, sample.fine
    assert heights.shape == (model.grid(level),) * 2
    assert (sample.coarse is not None) == (is_coupled_stage(stage) and level > 0)
    values = evaluate_qoi(model.qoi_names, pressure=solution.pressure, gap=solution.gap,
                          connectivity=model.connectivity) * np.asarray(model.qoi_scales)
    # Bit for bit, the mean gap included: it would change in its last digits without the warm start.
    np.testing.assert_array_equal(values, batch.fine[0])
    assert int(label_clusters(solution.contact, connectivity=8).max()) == batch.fine[0, 1]


def test_sample_figure_shows_the_stored_contact_area(tmp_path, monkeypatch):
    model = build_model(config_from_dict(tiny_config(qoi=SAMPLE_QOI)))
    stage, level, index = run_stage("mlmc", "plots"), 2, 1
    drawn = []
    save = plots._save

    def keep(figure, path):
        drawn.append(figure)
        return save(figure, path)

    monkeypatch.setattr(plots, "_save", keep)
    path = plots.write_sample_figure(model=model, stage=stage, level=level, index=index, path=tmp_path / "one.png")
    assert path == tmp_path / "one.png"
    _assert_pngs([path], ["one.png"])

    fine = compute_batch(model, stage=stage, level=level, indices=[index]).fine[0]
    titles = [ax.get_title() for ax in drawn[0].axes if ax.get_title()]
    assert f"contact {fine[0]:.2f} %, {int(fine[1])} clusters (8-connected)" in titles


def test_cost_against_tolerance_leaves_out_mc_on_a_chosen_level(tmp_path, report, figures):
    # `mc --level L` samples a level the user chose: no measure of plain MC to a tolerance (as derive_runs).
    planned = next(run for run in report["runs"] if run["method"] == "mc")
    chosen = {key: value for key, value in copy.deepcopy(planned).items() if key != "screening_rates"}
    chosen.update(run_id=planned["run_id"] + "_level-1", tol=[2.0])  # the tightest MLMC run's tolerance
    plots.write_report_plots(dict(report, runs=[*report["runs"], chosen]), tmp_path)
    (ax,) = figures["cost_vs_tol.png"].axes
    assert list(_lines(ax)["MC measured CPU-s"].get_xdata()) == [4.0]
    loosest, tightest = (ax for ax in figures["samples_per_level.png"].axes if ax.get_legend() is not None)
    assert _legend_texts(loosest) == ["MLMC $N_l$", "MC $N$"] and _legend_texts(tightest) == ["MLMC $N_l$"]


def test_richardson_runs_are_drawn_apart_from_plain_mlmc(tmp_path, report, figures):
    # Both were "MLMC measured CPU-s" and "MLMC $N_l$": a Richardson run read as plain MLMC's cost and samples.
    plain = [run for run in report["runs"] if run["method"] == "mlmc"]
    extrapolated = copy.deepcopy(plain[0])
    extrapolated["run_id"] += "_richardson"
    extrapolated["richardson"] = "applied"
    extrapolated["tol"] = [min(run["tol"][0] for run in plain) / 2]  # the tightest: the samples figure's right panel
    plots.write_report_plots(dict(report, runs=[*report["runs"], extrapolated]), tmp_path)
    lines = _lines(figures["cost_vs_tol.png"].axes[0])
    assert sorted(lines["MLMC measured CPU-s"].get_xdata()) == sorted(run["tol"][0] for run in plain)
    assert list(lines["Richardson MLMC measured CPU-s"].get_xdata()) == [extrapolated["tol"][0]]
    legends = [_legend_texts(ax) for ax in figures["samples_per_level.png"].axes if ax.get_legend() is not None]
    assert legends[0][0] == "MLMC $N_l$" and legends[-1][0] == "Richardson MLMC $N_l$"


def test_cost_against_tolerance_states_the_slope_of_the_lines_it_draws(tmp_path, report, figures):
    # A fitted alpha of 0.3 and gamma 2: the legend said MC eps^-8.67 beside a line planned at alpha 0.5 (eps^-6).
    changed = copy.deepcopy(report)
    changed["screening"]["rates"].update(alpha=[0.3], gamma=2.0)
    plots.write_report_plots(changed, tmp_path)
    (mc_label,) = [label for label in _lines(figures["cost_vs_tol.png"].axes[0]) if label.startswith("MC predicted")]
    assert mc_label == "MC predicted CPU-s (eps^-6.00)"


def test_cost_against_tolerance_sets_the_refused_tolerances_apart(tmp_path, report, figures):
    # The predicted lines ran through tolerances the screening marks "*" (mlmc refuses them).
    changed = copy.deepcopy(report)
    predictions = sorted(changed["screening"]["predictions"], key=lambda p: p["tol"][0])
    for prediction in predictions:  # the tightest refused, the others not (whatever the screening predicts)
        prediction["is_bias_met"] = prediction is not predictions[0]
    changed["screening"]["predictions"] = predictions
    plots.write_report_plots(changed, tmp_path)
    lines = _lines(figures["cost_vs_tol.png"].axes[0])
    tols = [p["tol"][0] for p in predictions]
    assert list(lines["MLMC predicted at tol whose bias grid.max_level cannot reach"].get_xdata()) == tols[:1]
    (mlmc,) = [line for label, line in lines.items() if label.startswith("MLMC predicted CPU-s")]
    assert list(mlmc.get_xdata()) == tols[1:]


def test_a_prediction_of_one_reachable_tolerance_is_drawn_as_a_mark(tmp_path, report, figures):
    # Only the loosest screened tolerance reachable: each predicted "line" had one point, drew nothing, and the
    # legend listed the MLMC and MC predictions all the same.
    changed = copy.deepcopy(report)
    predictions = sorted(changed["screening"]["predictions"], key=lambda p: p["tol"][0])
    for prediction in predictions:
        prediction["is_bias_met"] = prediction is predictions[-1]
    changed["screening"]["predictions"] = predictions
    plots.write_report_plots(changed, tmp_path)
    lines = _lines(figures["cost_vs_tol.png"].axes[0])
    predicted = [line for label, line in lines.items() if " predicted CPU-s" in label]
    assert len(predicted) == 2
    for line in predicted:
        assert list(line.get_xdata()) == [predictions[-1]["tol"][0]] and line.get_marker() == "_"


@pytest.fixture(scope="module")
def two_qoi_report() -> dict:
    """Two QoIs screened with tolerances 2 % and 0.05 (ratio 0.025); MLMC at that ratio and at another."""
    study = _study(qoi={"contact_area": {"unit": "percent", "tol": 2.0}, "mean_gap": {"tol": 0.05}})
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    for tol in ((4.0, 0.1), (2.0, 0.5)):
        run_estimation(study, method="mlmc", tol=np.array(tol), executor=SerialExecutor(), progress=Progress())
    return study_report(study.store, study.config)


def test_cost_against_tolerance_of_two_qois_states_the_ratio_and_marks_runs_off_it(tmp_path, two_qoi_report,
                                                                                    figures):
    plots.write_report_plots(two_qoi_report, tmp_path)
    (ax,) = figures["cost_vs_tol.png"].axes
    assert ax.get_xlabel() == "tolerance on contact_area [%]\n(lines: mean_gap at 0.025 × this tolerance)"
    lines = _lines(ax)
    on, off = lines["MLMC measured CPU-s"], lines["MLMC measured CPU-s, other tol ratio than the lines"]
    assert list(on.get_xdata()) == [4.0] and list(off.get_xdata()) == [2.0]
    assert off.get_markerfacecolor() == "none" and on.get_markerfacecolor() != "none"
    # The predicted costs' exponents of both QoIs, not only the first's.
    (mc_label,) = [label for label in lines if label.startswith("MC predicted")]
    assert "contact_area eps^-" in mc_label and "mean_gap " in mc_label


def test_load_curve_legend_names_method_level_and_grid(tmp_path, figures):
    study = _study(load={"relative": [0.1, 0.2]})
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    run_estimation(study, method="mlmc", tol=np.full(2, 4.0), executor=SerialExecutor(), progress=Progress())
    for level in (1, 2):
        run_estimation(study, method="mc", tol=np.full(2, 4.0), level=level, executor=SerialExecutor(),
                       progress=Progress())
    plots.write_report_plots(study_report(study.store, study.config), tmp_path)
    (ax,) = figures["load_curve.png"].axes
    mlmc, *mc = _legend_texts(ax)
    # MC on a given level estimates no bias: its band is the statistical error (it said "± RMSE").
    assert mc == ["MC, level 1 (16²) (± stat. error)", "MC, level 2 (32²) (± stat. error)"]
    assert mlmc.startswith("MLMC, levels 0..") and mlmc.endswith("²) (± RMSE)")
    # The samples' panel names its tolerance by QoI (it read "tol 4, 4", one number per load column).
    assert [ax.get_title() for ax in figures["samples_per_level.png"].axes] == ["tol contact_area=4"]
    text = io.StringIO()
    render_load_curves(Console(file=text, width=300), study_report(study.store, study.config)["load_curves"])
    titles = re.findall(r"\((estimate ± [a-zA-Z. ]+)\)", " ".join(text.getvalue().split()))
    assert titles == ["estimate ± RMSE", "estimate ± stat. error", "estimate ± stat. error"], text.getvalue()



def test_load_curve_legend_tells_runs_of_one_name_apart_by_what_differs(tmp_path, figures):
    # Two runs on one grid were "MC, level 1 (16²), run 1" and "..., run 2": which was which?
    study = _study(load={"relative": [0.1, 0.2]}, qoi={"contact_area": {"tol": 4.0}, "mean_gap": {"tol": 1.0}})
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    for tol in ([4.0, 4.0, 1.0, 1.0], [4.0, 4.0, 1.0, 0.5]):
        run_estimation(study, method="mc", tol=np.array(tol), level=1, executor=SerialExecutor(), progress=Progress())
    plots.write_report_plots(study_report(study.store, study.config), tmp_path)
    legends = [_legend_texts(ax) for ax in figures["load_curve.png"].axes]
    assert legends[0] == legends[1] == ["MC, level 1 (16²)\ntol mean_gap@0.2=1 (± stat. error)",
                                        "MC, level 1 (16²)\ntol mean_gap@0.2=0.5 (± stat. error)"]


def test_load_curve_kappa_line_stops_where_its_fit_stops(tmp_path, figures):
    # Drawn over every load, the small-load line rose to 1100 % at a relative load of 5 and squashed the curve.
    loads = [0.01, 0.1, 0.5, 1.0, 5.0]
    area = [2.0, 18.0, 60.0, 85.0, 100.0]
    fit = {"kappa": 1.8, "error": 0.1, "max_area": 0.2, "n_points": 2}
    entry = {"run_id": "r", "method": "mlmc", "label": "r", "relative_loads": loads, "kappa": fit,
             "curves": {"contact_area": {"estimate": area, "rmse": [0.5] * 5}}}
    plots._load_curve_figure(plots._Drawn(None, (), ("contact_area",), {"contact_area": "%"}, (), (entry,)),
                             tmp_path / "load_curve.png")
    (ax,) = figures["load_curve.png"].axes
    (line,) = [line for label, line in _lines(ax).items() if label.startswith("kappa")]
    np.testing.assert_allclose(line.get_xdata(), [0.0, 0.2 / 1.8])
    assert max(line.get_ydata()) == pytest.approx(20.0) and ax.get_ylim()[1] < 110.0
    # Its label reads as the report's text (value to the error's second digit): "kappa = 2.2 ± 0.049" stood beside
    # the report's 2.203 ± 0.049.
    fit.update(kappa=2.2034, error=0.0491)
    plots._load_curve_figure(plots._Drawn(None, (), ("contact_area",), {"contact_area": "%"}, (), (entry,)),
                             tmp_path / "load_curve.png")
    (label,) = [label for label in _lines(figures["load_curve.png"].axes[0]) if label.startswith("kappa")]
    assert label.startswith("kappa = 2.203 ± 0.049 (fit on 2 loads")


def test_load_curve_names_of_many_runs_stay_distinct_and_short():
    import itertools

    from rough_uq.problem.runs import run_id
    from rough_uq.study.records import RunRecord

    columns = tuple(f"{qoi}@{load}" for qoi in ("contact_area", "mean_gap", "clusters") for load in (0.01, 0.02, 0.05))

    def record(tol: tuple[float, ...], theta: float, richardson: bool) -> RunRecord:
        key = run_id("mlmc", columns, tol, theta, richardson=richardson)
        return RunRecord(run_id=key, method="mlmc", status="finished", tol=tol, qoi_names=columns, theta=theta)

    def names_of(runs: list[RunRecord]) -> list[str]:
        entries = tuple({"run_id": run.run_id, "method": run.method, "label": run.run_id} for run in runs)
        return plots._load_curve_names(plots._Drawn(None, tuple(runs), columns, {}, (), entries))

    runs = [record(tuple(scale * (1.0 + ((k + j) % 7) / 10) for j in range(len(columns))), theta, richardson)
            for k, (richardson, theta, scale) in enumerate(itertools.product((False, True), (0.5, 0.25), (1.0, 3.0)))]
    # Two runs that differ only in the last of many differing columns, past what a legend shows.
    runs += [record(runs[0].tol[:-1] + (9.0,), 0.5, False), record(runs[0].tol[:-1] + (8.0,), 0.5, False)]
    names = names_of(runs)  # every column has its own tolerance, in every run another
    assert len(set(names)) == len(runs)
    for name in names:
        lines = name.split("\n")
        assert lines[0] == "MLMC" and len(lines) <= 1 + plots.LEGEND_LINES, name
        assert all(len(line) <= plots.LEGEND_WIDTH for line in lines), name
    # Runs that differ only in the extrapolation are told apart by it.
    pair = names_of([record(runs[0].tol, 0.5, False), record(runs[0].tol, 0.5, True)])
    assert pair == ["MLMC\nno Richardson", "MLMC\nRichardson"]


def test_rates_draw_no_bias_line_where_the_text_says_not_fitted(tmp_path, report, figures):
    screening = copy.deepcopy(report["screening"])
    screening["rates"]["alpha"] = [0.04]  # <= MIN_ALPHA: the report prints "not fitted"
    plots.write_report_plots(dict(report, screening=screening), tmp_path)
    bias = figures["rates.png"].axes[0]
    assert bias.get_title().endswith(": bias")
    assert [len(line.get_xdata()) > 0 for line in bias.get_lines()] == [True, False]  # data; a legend entry only
    assert _legend_texts(bias)[1] == r"$\alpha$ = 0.04: not fitted, the bias does not decay"


def test_an_exact_column_is_said_so_in_the_rates_and_cost_figures(tmp_path, two_qoi_report, figures):
    # A column past full contact (rates EXACT_RATE, constants 0) left its rate panels blank and its cost slope
    # read "eps^-2.25" (the stand-in rate capped like a fit).
    screening = copy.deepcopy(two_qoi_report["screening"])
    rates = screening["rates"]
    for key, value in (("alpha", EXACT_RATE), ("beta", EXACT_RATE), ("c_alpha", 0.0), ("c_beta", 0.0)):
        rates[key] = [rates[key][0], value]
    plots.write_report_plots(dict(two_qoi_report, screening=screening), tmp_path)
    rates_axes = figures["rates.png"].axes
    assert "exact: every level difference is 0 (no bias)" in _legend_texts(rates_axes[3])
    assert "exact: every level difference is 0 (no level variance)" in _legend_texts(rates_axes[4])
    labels = [label for label in _lines(figures["cost_vs_tol.png"].axes[0]) if "predicted CPU-s" in label]
    assert labels and all("mean_gap exact" in label for label in labels), labels


def test_sample_figure_titles_fit_and_name_the_load_drawn(tmp_path, figures):
    qoi = {"contact_area": {"unit": "percent"}, "clusters": {"connectivity": "mean"}}
    model = build_model(config_from_dict(tiny_config(qoi=qoi, load={"relative": [0.1, 0.2]})))
    plots.write_sample_figure(model=model, stage=STAGE_SCREENING, level=1, index=0, path=tmp_path / "s.png")
    figure = figures["s.png"]
    renderer = figure.canvas.get_renderer()
    figure.draw(renderer)
    box = figure.bbox
    (suptitle,) = figure.texts
    for text in [ax.title for ax in figure.axes if ax.get_title()] + [suptitle]:
        extent = text.get_window_extent(renderer)
        assert box.x0 <= extent.x0 and extent.x1 <= box.x1 and extent.y1 <= box.y1, text.get_text()
    assert "mean of 4- and 8-connected" in figure.axes[2].get_title()
    assert "load 1 of 2: $p / (E^* \\sqrt{m_2})$ = 0.1 " in suptitle.get_text()
    assert suptitle.get_text().startswith("sample of stage 0, level 1 (grid 16), index 0 [coupled draw]")


def test_a_sample_figure_names_its_stage_as_given(tmp_path, figures):
    # `roughuq show --stage <run id>` titled the figure "sample stage 65290023461150223": a run's stage is a hash.
    model = build_model(config_from_dict(tiny_config()))
    plots.write_sample_figure(model=model, stage=STAGE_SCREENING, level=0, index=0, path=tmp_path / "s.png",
                              stage_name="run mlmc_contact_area-2_theta-0.5")
    (suptitle,) = figures["s.png"].texts
    assert suptitle.get_text().startswith("sample of run mlmc_contact_area-2_theta-0.5, level 0 (grid 8), index 0")


def test_the_cost_legend_counts_the_exponents_of_many_columns():
    # Ten columns of a load curve, each named with its exponent, took more lines than the axes had room for.
    from types import SimpleNamespace

    def complexity(mc: float, regime: str = "eps^-2 (beta > gamma)"):
        return SimpleNamespace(mc_exponent=mc, mlmc_regime=regime, mlmc_exponent=2.0)

    columns = tuple(f"contact_area@{load}" for load in (0.01, 0.02, 0.05, 0.1, 0.2))
    drawn = plots._Drawn(None, (), columns, {}, ())
    many = [complexity(3.0)] * 3 + [complexity(3.5)] * 2
    assert plots._exponent_note(drawn, many, is_mc=True) == (
        "\neps^-3.00 (3 columns), eps^-3.50 (2 columns); per\ncolumn in the report")
    assert plots._exponent_note(drawn, many, is_mc=False) == "\neps^-2 (5 columns); per column in the report"
    assert " ".join(plots._exponent_note(drawn, many[:4] + [complexity(4.0)], is_mc=True).split()).startswith(
        "eps^-3.00 (3 columns), eps^-3.50 (1 column), eps^-4.00 (1 column);")
    few = plots._exponent_note(plots._Drawn(None, (), columns[:2], {}, ()), many[3:], is_mc=True)
    assert few == "\ncontact_area@0.01 eps^-3.50;\ncontact_area@0.02 eps^-3.50"  # named, as before

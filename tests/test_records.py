"""Typed study records: JSON round trips, records written before they existed, malformed records, derived numbers."""

from __future__ import annotations

import copy
import json
import math
import re
from dataclasses import replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from rough_uq.errors import InvalidParameterError, RoughUQError
from rough_uq.multilevel.rates import BIAS_RATE_CAP, EXACT_RATE, RATE_FLOOR
from rough_uq.problem.batch import LevelBatch
from rough_uq.report.summary import ReportedRun, derive_runs
from rough_uq.study.records import (
    MIN_ALPHA,
    RATE_TIE,
    Diagnostic,
    DroppedLevel,
    Forecast,
    LevelTable,
    PlanRecord,
    RatesRecord,
    RunRecord,
    ScreeningRecord,
    complexity,
    count_not_converged,
    read_run_records,
    read_screening_record,
    utc_timestamp,
)
from rough_uq.study.store import MemoryStore, open_study_readonly

DATA = Path(__file__).resolve().parent / "data"
#: Record texts written by the code before typed records (see its "source").
STORED = json.loads((DATA / "records_v2.json").read_text())
MLMC = "mlmc_contact_area-2_clusters-5_theta-0.5"
MC_DROPPED = "mc_contact_area-2_clusters-5_theta-0.5"
MC_LEVEL = "mc_contact_area-4_clusters-20_theta-0.5_level-1"
RICHARDSON = "mlmc_contact_area-3_clusters-8_theta-0.5_richardson"
RUNNING = "mlmc_contact_area-1_clusters-3_theta-0.5"


def _screening_data() -> dict:
    return json.loads(STORED["screening"])


def _run_data(run_id: str) -> dict:
    return json.loads(STORED["runs"][run_id])


def _screening() -> ScreeningRecord:
    return ScreeningRecord.from_json(_screening_data())


def _run(run_id: str) -> RunRecord:
    return RunRecord.from_json(_run_data(run_id), run_id=run_id)


# ---------------------------------------------------------------------------
# Records written by the code before typed records
# ---------------------------------------------------------------------------


def test_stored_screening_reads_and_writes_back_the_same_text():
    record = _screening()
    assert json.dumps(record.to_json()) == STORED["screening"]
    assert record.qoi_names == ("contact_area", "clusters")
    assert record.statistics.levels == (0, 1, 2) and record.statistics.n_qoi == 2
    assert record.n_screened == 8 and record.coarsest_level is not None
    assert len(record.predictions) == 5 and all(isinstance(p, PlanRecord) for p in record.predictions)


@pytest.mark.parametrize("run_id", sorted(STORED["runs"]))
def test_stored_runs_read_and_write_back_the_same_text(run_id):
    record = _run(run_id)
    assert json.dumps(record.to_json()) == STORED["runs"][run_id]
    assert record.run_id == run_id and record.method == run_id.split("_")[0]


def test_stored_runs_have_the_fields_of_their_kind():
    running, mlmc, mc_level, richardson = _run(RUNNING), _run(MLMC), _run(MC_LEVEL), _run(RICHARDSON)
    assert running.status == "running" and running.outcome is None and running.forecast is None
    assert mlmc.is_finished and mlmc.level is None and isinstance(mlmc.forecast, Forecast)
    assert isinstance(mlmc.screening_rates, RatesRecord) and isinstance(mlmc.predicted, PlanRecord)
    assert mc_level.level == 1 and mc_level.screening_rates is None and mc_level.predicted is None
    assert mc_level.outcome.rates is None and not mc_level.outcome.is_bias_estimated
    assert _run(MC_DROPPED).status == "dropped" and _run(MC_DROPPED).outcome is not None
    assert richardson.outcome.richardson == "refused" and richardson.outcome.richardson_reason
    assert [d.kind for d in richardson.outcome.diagnostics] == ["coupling", "richardson"]


def test_the_store_gives_typed_records():
    store = MemoryStore(qoi_names=("contact_area", "clusters"))
    assert read_screening_record(store) is None and read_run_records(store) == []
    store.write_screening(_screening_data())
    for run_id in STORED["runs"]:
        store.write_run(run_id, _run_data(run_id))
    assert read_screening_record(store) == _screening()
    assert [run.run_id for run in read_run_records(store)] == list(STORED["runs"])
    assert read_run_records(store)[0] == _run(MLMC)


#: Keys the first study files (commit 2261a0b) did not have yet.
NEWER_RUN_KEYS = ("stage", "initial_samples", "elapsed", "forecast", "richardson", "richardson_reason",
                  "dropped_levels", "stopped_elapsed")
NEWER_SCREENING_KEYS = ("coarsest_level", "dropped_levels")


def test_the_first_layout_reads_with_the_newer_fields_unset():
    data = {k: v for k, v in _run_data(MLMC).items() if k not in NEWER_RUN_KEYS}
    record = RunRecord.from_json(data, run_id=MLMC)
    assert record.stage is None and record.initial_samples is None and record.forecast is None
    assert record.outcome.elapsed is None and record.outcome.richardson is None
    assert record.outcome.dropped_levels is None
    assert record.outcome.estimate == _run(MLMC).outcome.estimate
    # Written back: the same keys, plus the forecast the pipeline has always written as null.
    assert record.to_json() == data | {"forecast": None}
    old = {k: v for k, v in _screening_data().items() if k not in NEWER_SCREENING_KEYS}
    screening = ScreeningRecord.from_json(old)
    assert screening.coarsest_level is None and screening.dropped_levels is None
    assert screening.to_json() == old


def test_a_minimal_run_record_derives_what_it_lacks():
    assert RunRecord.from_json({"method": "mlmc", "stage": 7, "status": "running", "tol": [9.0]},
                               run_id="r").to_json() == {"method": "mlmc", "stage": 7, "status": "running",
                                                         "tol": [9.0], "max_cost": None, "forecast": None}
    data = {k: v for k, v in _run_data(MLMC).items() if k not in ("rmse", "tol_met", "is_bias_estimated")}
    outcome = RunRecord.from_json(data, run_id=MLMC).outcome
    assert outcome.rmse == tuple(math.hypot(s, b) for s, b in zip(outcome.stat_error, outcome.bias_estimate))
    assert outcome.tol_met == (outcome.stop_reason == "tol_met") and outcome.is_bias_estimated


def test_report_keys_are_ignored_and_run_id_is_read():
    data = {"run_id": MLMC, **_run_data(MLMC), "work_ratio": 0.1, "measured_ratio": 2.0}
    assert RunRecord.from_json(data) == _run(MLMC)
    report_screening = {**_screening_data(), "complexity": [], "grids": [8, 16, 32]}
    assert ScreeningRecord.from_json(report_screening) == _screening()


# ---------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------


def _parts() -> list[object]:
    screening, mlmc = _screening(), _run(MLMC)
    return [screening, screening.statistics, screening.rates, screening.predictions[0], mlmc, mlmc.forecast,
            DroppedLevel(level=0, reason="its V_0 costs more than it saves"), mlmc.outcome.diagnostics[0]]


@pytest.mark.parametrize("record", _parts(), ids=lambda record: type(record).__name__)
def test_every_record_type_round_trips_through_json_text(record):
    text = json.dumps(record.to_json())
    if isinstance(record, RunRecord):
        again = RunRecord.from_json(json.loads(text), run_id=record.run_id)
    else:
        again = type(record).from_json(json.loads(text))
    assert again == record
    assert json.dumps(again.to_json()) == text


def _random_rates(rng: np.random.Generator, n_qoi: int) -> RatesRecord:
    per_qoi = {key: tuple(rng.normal(size=n_qoi).tolist()) for key in
               ("alpha", "alpha_se", "beta", "beta_se", "c_alpha", "c_beta")}
    spans = tuple(tuple(range(int(rng.integers(0, 2)), int(rng.integers(2, 5)))) for _ in range(n_qoi))
    return RatesRecord(**per_qoi, gamma=float(rng.normal()), gamma_se=float(rng.random()), c_gamma=float(rng.random()),
                       levels_alpha=spans, levels_beta=spans[::-1], levels_gamma=(1, 2))


def _random_table(rng: np.random.Generator, n_levels: int, n_qoi: int) -> LevelTable:
    def table() -> tuple:
        values = rng.normal(size=(n_levels, n_qoi)) * 10.0 ** rng.integers(-300, 300)
        return tuple(tuple(row) for row in values.tolist())

    return LevelTable(levels=tuple(range(n_levels)), n_samples=tuple(rng.integers(2, 10**6, n_levels).tolist()),
                      mean_fine=table(), var_fine=table(), mean_diff=table(), var_diff=table(), kurtosis=table(),
                      consistency=table(), mean_cost=tuple(rng.random(n_levels).tolist()),
                      mean_seconds=tuple(rng.random(n_levels).tolist()))


@pytest.mark.parametrize("seed", range(5))
def test_random_records_round_trip_exactly(seed):
    rng = np.random.default_rng(seed)
    n_qoi, n_levels = int(rng.integers(1, 4)), int(rng.integers(1, 7))
    screening = replace(_screening(), qoi_names=tuple(f"q{q}" for q in range(n_qoi)),
                        statistics=_random_table(rng, n_levels, n_qoi), rates=_random_rates(rng, n_qoi),
                        seconds_per_cost=float(rng.random()), diagnostics=(Diagnostic("level 1: 1 sample(s)"),))
    text = json.dumps(screening.to_json())
    assert ScreeningRecord.from_json(json.loads(text)) == screening
    per_qoi = {key: tuple(rng.normal(size=n_qoi).tolist())
               for key in ("estimate", "stat_error", "bias_estimate", "rmse", "variance", "variance_error")}
    outcome = replace(_run(MLMC).outcome, **per_qoi, statistics=_random_table(rng, n_levels, n_qoi),
                      rates=_random_rates(rng, n_qoi))
    run = replace(_run(MLMC), tol=tuple(rng.random(n_qoi).tolist()), qoi_names=screening.qoi_names, outcome=outcome)
    assert RunRecord.from_json(json.loads(json.dumps(run.to_json())), run_id=MLMC) == run


def test_infinite_and_nan_values_survive_the_text():
    outcome = replace(_run(MLMC).outcome, cost=0.0, mc_cost=math.inf, variance=(math.nan, -1.5))
    run = replace(_run(MLMC), outcome=outcome)
    again = RunRecord.from_json(json.loads(json.dumps(run.to_json())), run_id=MLMC)
    assert again.outcome.mc_cost == math.inf and math.isnan(again.outcome.variance[0])
    assert again.outcome.work_ratio == math.inf  # a run that cost nothing


# ---------------------------------------------------------------------------
# Malformed records
# ---------------------------------------------------------------------------


def _broken(data: dict, path: tuple, value: object) -> dict:
    data = copy.deepcopy(data)
    target = data
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return data


SCREENING_DEFECTS = [
    (("rates",), KeyError, "screening.rates"),
    (("statistics", "levels"), "0 1 2", "screening.statistics.levels"),
    (("statistics", "mean_fine", 1, 0), "40.2", "screening.statistics.mean_fine[1][0]"),
    (("statistics", "n_samples", 0), 8.0, "screening.statistics.n_samples[0]"),
    (("rates", "gamma"), [0.4], "screening.rates.gamma"),
    (("predictions", 0, "is_bias_met"), "yes", "screening.predictions[0].is_bias_met"),
    (("predictions", 2, "mc_cost"), True, "screening.predictions[2].mc_cost"),
    (("dropped_levels",), [{"level": 0}], "screening.dropped_levels[0].reason"),
    (("warnings",), [3], "screening.warnings[0]"),
]


@pytest.mark.parametrize("path, value, field", SCREENING_DEFECTS, ids=[d[2] for d in SCREENING_DEFECTS])
def test_a_malformed_screening_is_refused_naming_the_field(path, value, field):
    with pytest.raises(InvalidParameterError) as info:
        ScreeningRecord.from_json(_broken(_screening_data(), path, value))
    assert isinstance(info.value, RoughUQError) and info.value.name == field
    assert field in str(info.value)


RUN_DEFECTS = [
    (("status",), "paused", "status", "running, finished, refused, dropped, interrupted"),
    (("method",), "qmc", "method", "mlmc, mc, variance, cdf"),
    (("tol",), KeyError, "tol", "missing"),
    (("estimate", 1), None, "estimate[1]", "a number"),
    (("n_samples",), 57, "n_samples", "a list"),
    (("stop_reason",), KeyError, "stop_reason", "missing"),
    (("forecast", "memory_bytes"), 1.5, "forecast.memory_bytes", "an integer"),
    (("statistics", "consistency"), [0.1], "statistics.consistency[0]", "a list"),
    (("rates", "levels_alpha", 0), [1, "2"], "rates.levels_alpha[0][1]", "an integer"),
    # lengths that disagree: the report indexed past their ends (a traceback)
    (("tol",), [], "tol", "one tolerance per QoI (2: contact_area, clusters)"),
    (("tol",), [0.5], "tol", "one tolerance per QoI (2: contact_area, clusters)"),
    (("estimate",), [20.0], "estimate", "2 values, one per QoI as in tol"),
    (("variance_error",), [1.0, 2.0, 3.0], "variance_error", "2 values, one per QoI as in tol"),
    (("n_samples",), [57], "n_samples", "counts, one per level"),
]


@pytest.mark.parametrize("path, value, field, allowed", RUN_DEFECTS, ids=[d[2] for d in RUN_DEFECTS])
def test_a_malformed_run_is_refused_naming_the_field(path, value, field, allowed):
    data = _broken(_run_data(MLMC), path, value)
    with pytest.raises(InvalidParameterError) as info:
        RunRecord.from_json(data, run_id=MLMC)
    assert info.value.name == f"run {MLMC}.{field}"
    assert allowed in info.value.allowed


def test_records_that_are_not_objects_or_lack_a_name_are_refused():
    with pytest.raises(InvalidParameterError, match="screening: .*JSON object"):
        ScreeningRecord.from_json([1, 2])
    with pytest.raises(InvalidParameterError, match=r"run\.run_id"):
        RunRecord.from_json(_run_data(MLMC))


def test_a_study_file_with_foreign_records_is_refused_by_field():
    # The version-1 file of the store tests holds stand-in records, not screenings.
    with open_study_readonly(DATA / "study_v1.h5") as store:
        with pytest.raises(InvalidParameterError, match=r"screening\.created"):
            read_screening_record(store)
        with pytest.raises(InvalidParameterError, match=r"run r1\.method"):
            read_run_records(store)


# ---------------------------------------------------------------------------
# Derived numbers, each defined once
# ---------------------------------------------------------------------------


def test_complexity_regimes():
    assert complexity(MIN_ALPHA, 2.0, 1.0).mc_exponent is None
    assert complexity(None, 2.0, 1.0).mlmc_exponent is None
    assert complexity(1.0, 2.0, None).mc_exponent is None
    assert complexity(1.0, None, 1.0) == complexity(1.0, math.nan, 1.0)
    assert complexity(1.0, None, 1.0).mlmc_exponent is None and complexity(1.0, None, 1.0).mc_exponent == 3.0
    assert "log" in complexity(1.0, 1.0 + RATE_TIE / 2, 1.0).mlmc_regime


@pytest.mark.parametrize("seed", range(3))
def test_complexity_exponents_follow_the_theorem(seed):
    rng = np.random.default_rng(seed)
    for alpha, beta, gamma in rng.uniform([0.1, 0.0, 0.0], [3.0, 4.0, 4.0], size=(50, 3)):
        result = complexity(alpha, beta, gamma)
        assert result.mc_exponent == pytest.approx(2.0 + gamma / alpha, rel=1e-14)
        if abs(beta - gamma) < RATE_TIE or beta > gamma:
            assert result.mlmc_exponent == 2.0
        else:
            assert result.mlmc_exponent == pytest.approx(2.0 + (gamma - beta) / alpha, rel=1e-14)
        assert result.mlmc_exponent <= result.mc_exponent + 1e-12  # MLMC is never worse


def test_screening_complexity_is_that_of_its_rates():
    screening = _screening()
    rates = screening.rates
    assert screening.complexity == tuple(complexity(a, b, rates.gamma) for a, b in zip(rates.alpha, rates.beta))


def test_planned_complexity_takes_the_rates_as_plans_take_them():
    # Floored at RATE_FLOOR, and alpha capped at BIAS_RATE_CAP as the bias's tail is summed: a fitted alpha of
    # 4.6 (a coarsest grid that truncates the spectrum) gave the predicted costs a slope of 2 + 1/4.6.
    rates = replace(_screening().rates, alpha=(4.6, 0.2), beta=(2.0, 0.1), gamma=1.0)
    planned = rates.planned_complexity
    assert planned[0] == complexity(BIAS_RATE_CAP, 2.0, 1.0) and planned[0].mc_exponent == 2.5
    assert planned[1] == complexity(RATE_FLOOR, RATE_FLOOR, 1.0)
    assert rates.complexity[0] == complexity(4.6, 2.0, 1.0)  # the report lists the fitted rates
    # A column exact on the screened levels keeps its regime: capped to 2, EXACT_RATE read as a fit of eps^-2.25.
    exact = replace(rates, alpha=(EXACT_RATE, 0.2), beta=(EXACT_RATE, 0.1)).planned_complexity[0]
    assert exact.mc_exponent is None and exact.mlmc_regime.startswith("exact")


@pytest.mark.parametrize("seed", range(3))
def test_count_not_converged_counts_samples_with_any_failed_solve(seed):
    rng = np.random.default_rng(seed)
    batches, expected = [], 0
    for level in range(3):
        n = int(rng.integers(0, 20))
        converged = rng.random((n, 2)) > 0.3
        expected += int(np.sum(~converged[:, 0] | ~converged[:, 1]))
        batches.append(LevelBatch(level=level, stage=0, indices=np.arange(n), fine=np.zeros((n, 1)),
                                  coarse=np.zeros((n, 1)), cost=np.ones(n), n_iter=np.ones((n, 2), dtype=np.int64),
                                  converged=converged))
    assert count_not_converged(batches) == expected
    assert count_not_converged(iter(batches)) == expected


def test_timestamps_are_utc_seconds():
    before = datetime.now(timezone.utc).replace(microsecond=0)
    stamp = datetime.fromisoformat(utc_timestamp())
    assert stamp.utcoffset() == timedelta(0) and stamp.microsecond == 0
    assert before <= stamp <= datetime.now(timezone.utc)


def test_work_ratio_and_measured_ratio():
    mlmc, mc = _run(MLMC), replace(_run(MC_DROPPED), status="finished")
    assert mlmc.outcome.work_ratio == mlmc.outcome.mc_cost / mlmc.outcome.cost
    (shown_mlmc, shown_mc) = derive_runs([mlmc, mc])
    assert shown_mlmc.mc_seconds_measured == mc.outcome.seconds and shown_mlmc.mc_cost_measured == mc.outcome.cost
    # In modelled cost, as the predicted ratio (CPU-seconds depend on the machine's load during each run).
    assert shown_mlmc.measured_ratio == mc.outcome.cost / mlmc.outcome.cost
    assert shown_mc.measured_ratio is None and shown_mc.to_json()["work_ratio"] == mc.outcome.work_ratio
    assert ReportedRun.from_json(shown_mlmc.to_json()) == shown_mlmc
    # MC on a level of the user's choosing (no screening's plan) measures nothing for MLMC at that tolerance.
    on_level = replace(mc, run_id=MC_LEVEL, screening_rates=None, level=0)
    assert derive_runs([mlmc, on_level])[0].measured_ratio is None
    # A dropped MC run is neither shown nor measured against.
    assert [run.record.run_id for run in derive_runs([mlmc, _run(MC_DROPPED)])] == [MLMC]
    assert derive_runs([mlmc, _run(MC_DROPPED)])[0].measured_ratio is None


def test_the_measured_ratio_pairs_runs_of_the_same_theta():
    # Keyed on the tolerances alone, an mc run at theta 0.25 stood in for the theta-0.5 one (0.09 against 0.13).
    mlmc, mc = _run(MLMC), replace(_run(MC_DROPPED), status="finished")
    other_theta = replace(mc, run_id=MC_LEVEL, theta=mlmc.theta / 2, outcome=replace(mc.outcome, cost=1e-3))
    assert mlmc.theta == mc.theta and other_theta.tol == mlmc.tol
    for order in ([mlmc, mc, other_theta], [mlmc, other_theta, mc]):
        assert derive_runs(order)[0].measured_ratio == mc.outcome.cost / mlmc.outcome.cost
    assert derive_runs([mlmc, other_theta])[0].measured_ratio is None


def test_a_richardson_run_is_told_apart_from_plain_mlmc_at_the_same_tolerance():
    # Both runs were headed "mlmc contact_area=3, clusters=8: tolerance met"; only a warning named the run.
    from rough_uq.report.summary import format_run

    refused = _run(RICHARDSON)
    plain = replace(refused, run_id=RICHARDSON.removesuffix("_richardson"),
                    outcome=replace(refused.outcome, richardson="off", richardson_reason=""))
    applied = replace(refused, outcome=replace(refused.outcome, richardson="applied", richardson_reason=""))
    running = replace(refused, status="running", outcome=None)
    units = {"contact_area": "%", "clusters": "clusters per unit area"}
    names = refused.qoi_names
    heads = {name: format_run(run, names, units)[0] for name, run in
             [("plain", plain), ("refused", refused), ("applied", applied), ("running", running)]}
    assert heads["plain"].startswith("mlmc contact_area=3, clusters=8: ")
    for name in ("refused", "applied", "running"):
        assert heads[name].startswith("mlmc (Richardson) contact_area=3, clusters=8: "), heads[name]
    assert not plain.is_richardson and refused.is_richardson and not _run(MC_LEVEL).is_richardson
    refusal = "  Richardson extrapolation refused: the estimate is plain MLMC (see warning)"
    assert refusal in format_run(refused, names, units) and refusal not in format_run(applied, names, units)
    assert all(len(line) <= 80 for line in format_run(refused, names, units))


def test_diagnostic_kinds():
    kinds = {
        "level 2: consistency check failed for QoI [0] (...)": "consistency",
        "level 1: kurtosis 412 of Q_l - Q_l-1 for QoI [0] exceeds 100; ...": "kurtosis",
        "mlmc: level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for QoI [0] (ratio 2.67); ...": "coupling",
        "level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for area_above (ratio 1.07): the levels are weakly ...": "coupling",
        "level 0: 1 sample(s), variance unknown": "few_samples",
        "no cost prediction: the bias of contact_area (alpha = -0.9) does not decrease ...": "prediction",
        "something new": "other",
    }
    assert {message: Diagnostic(message).kind for message in kinds} == kinds
    assert Diagnostic.from_json("x").to_json() == "x"


def test_the_prediction_table_marks_tolerances_whose_bias_the_finest_grid_cannot_reach():
    # The screening planned tol 1 on the finest allowed grid although its bias stays above sqrt(theta) tol there,
    # and `mlmc --tol 1` then refused it: the table must say so, not list it like a reachable one.
    from types import SimpleNamespace

    from rich.console import Console

    from rough_uq.report.summary import _predictions_table

    def row(tol: float, is_bias_met: bool) -> PlanRecord:
        return PlanRecord(tol=(tol,), finest_level=2, n_samples=(0, 4, 1), mlmc_cost=1.0, mc_cost=1.0,
                          mlmc_seconds=1.0, mc_seconds=1.0, work_ratio=1.0, is_bias_met=is_bias_met)

    console = Console(width=120, record=True)
    names = ("contact_area",)
    rates = SimpleNamespace(alpha=(1.0,), beta=(2.0,), gamma=1.5)
    console.print(_predictions_table(SimpleNamespace(qoi_names=names, predictions=(row(2.0, True), row(1.0, False)),
                                                     rates=rates)))
    text = console.export_text()
    assert "contact_area=1 *" in text and "contact_area=2 *" not in text and "mlmc refuses it" in text
    console.print(_predictions_table(SimpleNamespace(qoi_names=names, predictions=(row(2.0, True),), rates=rates)))
    text = console.export_text()  # (export_text clears the record)
    assert text.count("mlmc refuses") == 0 and "contact_area=2" in text
    assert "raised to at least" not in text
    # A fitted rate below the floor is planned at the floor, as runs plan: the table says so.
    low = SimpleNamespace(alpha=(0.05,), beta=(2.0,), gamma=1.5)
    console.print(_predictions_table(SimpleNamespace(qoi_names=names, predictions=(row(2.0, True),), rates=low)))
    assert "planned, as runs plan, with every rate raised to at least 0.5" in " ".join(console.export_text().split())


def test_the_prediction_table_marks_the_qoi_whose_bias_the_finest_grid_misses():
    # The mark ended the cell, next to its last QoI: "contact_area=0.25 / clusters=2.5 *", where contact_area's
    # bias was the one that `mlmc --tol` refused.
    from types import SimpleNamespace

    from rich.console import Console

    from rough_uq.report.summary import _predictions_table

    names = ("contact_area", "clusters", "mean_gap@0.1", "mean_gap@0.2")

    def row(unmet: tuple[int, ...] | None) -> PlanRecord:
        return PlanRecord(tol=(0.25, 2.5, 0.01, 0.02), finest_level=3, n_samples=(9, 4, 2, 1), mlmc_cost=1.0,
                          mc_cost=1.0, mlmc_seconds=1.0, mc_seconds=1.0, work_ratio=1.0, is_bias_met=False,
                          unmet_columns=unmet)

    rates = SimpleNamespace(alpha=(1.0,) * 4, beta=(2.0,) * 4, gamma=1.5)
    # A load curve's column set apart is marked alone; its group line where a column it stands for misses.
    for unmet, marked in (((0,), ["contact_area=0.25 *"]), ((3,), ["mean_gap@0.2=0.02 *"]),
                          ((2,), ["mean_gap=0.01 *"]), ((1, 2), ["clusters=2.5 *", "mean_gap=0.01 *"]),
                          (None, ["mean_gap@0.2=0.02 *"]), ((), ["mean_gap@0.2=0.02 *"])):  # no columns: at its end
        record = PlanRecord.from_json(row(unmet).to_json())  # as a file keeps it
        assert record.unmet_columns == unmet
        console = Console(width=120, record=True)
        console.print(_predictions_table(SimpleNamespace(qoi_names=names, predictions=(record,), rates=rates)))
        assert re.findall(r"\S+=\S+ \*", console.export_text()) == marked, unmet


def test_the_prediction_table_of_many_qois_shows_every_tolerance_whole_at_80_columns():
    # Five QoIs at 80 columns: rich cut "mean_gap=4.93058e-05" to "mean_gap=4.93058e…" and "max_pressure=0.00…",
    # and the tolerances of the QoIs without a configured tol came with no word of where they came from.
    from types import SimpleNamespace

    from rich.console import Console

    from rough_uq.report.summary import _predictions_table

    names = ("contact_area", "clusters", "mean_gap", "max_pressure", "area_above")
    base = (1.0, 0.43900001, 4.93058e-05, 0.00339897, 0.346711)
    plans = tuple(PlanRecord(tol=tuple(v * f for v in base), finest_level=3, n_samples=(143353, 42231, 18533, 8133),
                             mlmc_cost=1.0, mc_cost=1.0, mlmc_seconds=1140.0, mc_seconds=1524.0, work_ratio=1.33,
                             is_bias_met=f > 0.3) for f in (2.0, 1.0, 0.5, 0.25, 0.125))
    console = Console(width=80, record=True)
    rates = SimpleNamespace(alpha=(1.0,) * 5, beta=(2.0,) * 5, gamma=1.5)
    console.print(_predictions_table(SimpleNamespace(qoi_names=names, predictions=plans, rates=rates)))
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    lines = [line.strip() for line in re.sub(r"=\s*\n\s*", "=", text).splitlines()]  # a long line breaks at "="
    for plan in plans:
        for name, value in zip(names, plan.tol):
            assert any(line.startswith(f"{name}={value:.3g}") for line in lines), (name, value, text)
    assert "1 % of the QoI's finest screened mean" in " ".join(text.split())
    # A load curve's long column names: the table was 81 wide and rich cropped its last column ("1.3", "MC/MLM").
    curve = tuple(f"{qoi}@{load}" for qoi in ("contact_area", "max_pressure") for load in (0.0123456, 0.05, 0.1))
    console.print(_predictions_table(SimpleNamespace(
        qoi_names=curve, rates=SimpleNamespace(alpha=(1.0,) * 6, beta=(2.0,) * 6, gamma=1.5),
        predictions=tuple(replace(plan, tol=tuple(0.0123 * k * plan.tol[0] for k in range(1, 7)))
                          for plan in plans))))
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    assert "MC/MLMC" in text and text.count(" 1.33") == len(plans)
    assert re.search(r"max_pressure@0\.05= *\n *0\.\d+", text), text  # broken after its "=", not mid-number


def test_the_rates_say_no_decay_only_for_a_bias_that_does_not_decay():
    # Without a cost rate gamma there is no complexity exponent, and the alpha of a decaying bias was printed
    # "(no decay)" all the same.
    import io

    from rich.console import Console

    from rough_uq.report.summary import _print_rates

    screening = _screening()
    no_gamma = replace(screening, rates=replace(screening.rates, gamma=math.nan))

    def printed(record):
        console = Console(width=200, file=io.StringIO(), record=True)
        _print_rates(console, record, ("contact_area", "clusters"))
        return console.export_text()

    assert screening.rates.alpha[0] > MIN_ALPHA and no_gamma.complexity[0].mc_exponent is None
    assert "(no decay)" not in printed(screening).splitlines()[2] and "(no decay)" not in printed(no_gamma)
    assert "not fitted: no cost rate gamma" in printed(no_gamma)

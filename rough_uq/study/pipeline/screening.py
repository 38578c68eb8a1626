"""Screening: the level statistics of a few samples per level, the fitted rates and what accuracy will cost.

:func:`run_screening` computes (or reads back) the screening samples and stores a
:class:`~rough_uq.study.records.ScreeningRecord` with the cost predictions for the multiples
:data:`PREDICTION_FACTORS` of the base tolerance; :func:`screening_statistics` recomputes the statistics from the
stored samples and :func:`load_screening` gives a study file's screening to the Python API.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from rough_uq import __version__
from rough_uq.study.config import StudyConfig
from rough_uq.errors import EstimationError, InvalidParameterError, RoughUQError, StudyFileError
from rough_uq.multilevel.drivers import starting_plan
from rough_uq.study.executors import Executor, SerialExecutor
from rough_uq.study.progress import Progress
from rough_uq.study.records import (
    Diagnostic, DroppedLevel, LevelTable, PlanRecord, RatesRecord, ScreeningRecord, count_not_converged,
    read_screening_record, utc_timestamp,
)
from rough_uq.problem.runs import (
    MIN_SCREENED_LEVELS, ScreeningResult, contact_planning_rates, exact_column_caveats, screening_of_batches,
)
from rough_uq.problem.sampler import STAGE_SCREENING, LevelBatch, measured_seconds_per_cost, modelled_cost
from rough_uq.multilevel.allocation import MAX_TOL, MIN_TOL, Plan, plan
from rough_uq.multilevel.rates import (
    Rates, choose_coarsest_level, fit_rates, refuse_constant_columns, stalled_bias, stalled_text,
)
from rough_uq.multilevel.statistics import LevelStatistics, diagnose, level_statistics
from rough_uq.study.store import shard_refusal
from rough_uq.study.pipeline.diagnostics import collecting_diagnostics, unique_diagnostics
from rough_uq.study.pipeline.sampling import StudySampler
from rough_uq.study.pipeline.studies import Study, naming_source, open_existing_study, problem_of_config


#: Tolerances of the screening's cost predictions, as multiples of the base tolerance.
PREDICTION_FACTORS = (2.0, 1.0, 0.5, 0.25, 0.125)


@dataclass(frozen=True)
class ScreeningOutcome:
    """What screening measured: per-level statistics, rates, and what accuracy will cost."""

    statistics: LevelStatistics
    rates: Rates
    record: ScreeningRecord


def screening_statistics(study: Study, sampler: StudySampler | None = None) -> tuple[LevelStatistics, list[LevelBatch]]:
    """Level statistics of the screening samples (computing missing ones if ``sampler`` is given).

    The statistics are recomputed from the stored samples, so every command
    sees the same numbers whatever process ran the screening. Without a
    sampler (estimation runs), the levels and sample count are those of the
    last completed screening (a study may be screened again with more levels
    or samples than its config first said).
    """
    config = study.config
    levels = list(range(config.screening.levels))
    indices = np.arange(config.screening.samples)
    if sampler is None:
        record = read_screening_record(study.store)
        if record is not None:
            levels = list(record.statistics.levels)
            indices = np.arange(record.n_screened)
        sampler = StudySampler(study, stage=STAGE_SCREENING, executor=SerialExecutor(), progress=Progress())
        for level in levels:
            if sampler.missing(level, indices).size:
                path = getattr(study.store, "path", None)
                if study.store.role == "shard":  # its screening is in its study: screening it would be refused
                    raise shard_refusal(path)
                out = "" if path is None else f" --out {path}"
                raise StudyFileError(f"the study has no complete screening yet: run `roughuq screen CONFIG{out}` first",
                                     path)
    batches = [sampler.samples(level, indices) for level in levels]
    statistics = level_statistics(
        fine=[b.fine for b in batches],
        coarse=[b.coarse for b in batches],
        cost=[modelled_cost(study.model, b.level, b.n_iter) for b in batches],
        levels=levels,
    )
    return statistics, batches


def _base_tolerance(config: StudyConfig, statistics: LevelStatistics) -> np.ndarray:
    """Per column: its QoI's configured tol, or 1% of the finest screened mean (its standard deviation if that is 0)."""
    base = []
    for q, (_, _, settings) in enumerate(config.qoi_columns):
        tol = getattr(settings, "tol", None)
        if tol is None:
            mean = abs(float(statistics.mean_fine[-1, q]))
            spread = math.sqrt(max(float(statistics.var_fine[-1, q]), 0.0))
            tol = 0.01 * mean if mean > 0 else spread
            tol = tol if tol > 0 else 1.0
        base.append(tol)
    return np.array(base)


def _marked_as_runs_refuse(prediction: Plan, config: StudyConfig, rates: Rates, statistics: LevelStatistics) -> Plan:
    """The table's optimal plan, unreachable (with the bias that decides it) where ``roughuq mlmc`` refuses it.

    The run starts from :func:`~rough_uq.multilevel.drivers.adaptive.starting_plan` (its coarsest level may differ)
    and samples levels its bias test needs beyond a plan's finest
    (:func:`~rough_uq.multilevel.drivers.adaptive.with_run_bias`).
    """
    start = starting_plan(tol=prediction.tol, rates=rates, statistics=statistics, theta=prediction.theta,
                          max_level=config.grid.max_level, qoi_names=config.qoi_names)
    if start.is_bias_met or not prediction.is_bias_met:
        return prediction
    return replace(prediction, bias=start.bias, is_bias_met=False)


def _no_prediction(names: Sequence[str], rates: Rates, statistics: LevelStatistics, exc: Exception | None) -> str:
    """Why the screening predicts no cost, in words (the QoIs whose bias does not decay, by name)."""
    stalled = stalled_bias(names, rates, statistics)
    if stalled:
        return (f"no cost prediction: {stalled_text(stalled)}, so no finest grid can be chosen; screen finer "
                "grids (screening.levels, grid.coarsest)")
    return f"no cost prediction: {exc}; screen more levels (screening.levels)"


def run_screening(study: Study, *, executor: Executor, progress: Progress) -> ScreeningOutcome:
    """Compute (or complete) the screening samples, fit the rates, predict costs, store the record.

    A study with ``grid.max_level < 2`` (a valid config for the runs that
    need no screening) is refused before any sample is computed
    (:class:`~rough_uq.errors.InvalidParameterError` naming ``grid.max_level``,
    or :class:`~rough_uq.errors.ConfigError` naming the study's ``source`` first):
    a screening needs levels ``0..2`` (:data:`~rough_uq.problem.runs.MIN_SCREENED_LEVELS`).
    """
    config = study.config
    with naming_source(study.source):
        _check_screenable(config)
    levels = list(range(config.screening.levels))
    n = config.screening.samples
    smaller = _smaller_screening_text(read_screening_record(study.store), levels, n)
    sampler = StudySampler(study, stage=STAGE_SCREENING, executor=executor, progress=progress)
    progress.start("screening")
    try:
        progress.plan(levels, [n] * len(levels), [n - sampler.missing(level, np.arange(n)).size for level in levels])
        with collecting_diagnostics() as caught:
            statistics, batches = screening_statistics(study, sampler)
            rates = _screening_rates(statistics, config.qoi_names)
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop()
    seconds_per_cost = measured_seconds_per_cost(batches, study.model)
    predictions, problems = _predictions(study, statistics, rates, seconds_per_cost)
    caveats = exact_column_caveats(study.model, config.qoi_names, rates, statistics)
    texts = (*diagnose(statistics, names=config.qoi_names), *problems, *caveats, *smaller)
    checks = [Diagnostic(text) for text in texts]
    coarsest = choose_coarsest_level(statistics)
    record = ScreeningRecord(
        created=utc_timestamp(),
        code_version=__version__,
        qoi_names=tuple(config.qoi_names),
        statistics=LevelTable.from_statistics(statistics, [float(np.mean(b.cost)) for b in batches]),
        rates=RatesRecord.from_rates(rates),
        predictions=predictions,
        seconds_per_cost=seconds_per_cost,
        n_not_converged=count_not_converged(batches),
        n_computed=sampler.n_computed,
        diagnostics=unique_diagnostics(caught + checks),
        coarsest_level=int(coarsest.level),
        dropped_levels=tuple(DroppedLevel(int(d.level), d.reason) for d in coarsest.dropped),
    )
    study.store.write_screening(record.to_json())
    return ScreeningOutcome(statistics, rates, record)


def _smaller_screening_text(previous: ScreeningRecord | None, levels: Sequence[int], n: int) -> tuple[str, ...]:
    """A notice where this screening uses fewer levels or samples than the study's last one (its samples stay).

    A config with ``screening.samples: 10`` replaced a 20-sample screening and its rates without a word.
    """
    if previous is None:
        return ()
    n_before, levels_before = previous.n_screened, len(previous.statistics.levels)
    if n >= n_before and len(levels) >= levels_before:
        return ()
    return (f"this screening uses {n} samples on levels 0..{len(levels) - 1} (screening.samples, screening.levels) "
            f"where the study's last one used {n_before} on levels 0..{levels_before - 1}; its rates and plans "
            "replace that one's (the samples stay in the file: the config's earlier values screen with them again)",)


def _check_screenable(config: StudyConfig) -> None:
    """Refuse a config too shallow to screen (:func:`run_screening`), naming ``grid.max_level``."""
    if config.grid.max_level + 1 < MIN_SCREENED_LEVELS:
        raise InvalidParameterError(
            "grid.max_level", config.grid.max_level,
            f"an integer >= {MIN_SCREENED_LEVELS - 1} to screen: a screening needs levels 0..{MIN_SCREENED_LEVELS - 1} "
            "(the rates are fitted on levels >= 1, two of them at least); runs without a screening need none "
            "(mc --level; mlmc --tol-var / --tol-cdf from grid.max_level 1)",
        )


def _screening_rates(statistics: LevelStatistics, qoi_names: Sequence[str]) -> Rates:
    advice = "screen more levels (screening.levels) or more samples (screening.samples)"
    # Nothing to estimate at all (more levels or samples would not help), or no variance on the screened grids.
    refuse_constant_columns(statistics, qoi_names, advice=f"{advice}, or change the load")
    try:
        return fit_rates(statistics, names=qoi_names)
    except EstimationError as exc:
        raise EstimationError(f"screening cannot fit the rates: {exc}; {advice}") from None


def study_planning_rates(study: Study, statistics: LevelStatistics) -> Rates:
    """The rates a run of ``study`` plans with from its screening's ``statistics``
    (:func:`~rough_uq.problem.runs.contact_planning_rates`, up to ``grid.max_level``)."""
    return contact_planning_rates(study.model, statistics, study.config.grid.max_level)


def _predictions(
    study: Study, statistics: LevelStatistics, rates: Rates, seconds_per_cost: float
) -> tuple[tuple[PlanRecord, ...], list[str]]:
    """Plans for the multiples :data:`PREDICTION_FACTORS` of the base tolerance, and why any is missing."""
    config = study.config
    base = _base_tolerance(config, statistics)
    predictions = []
    if stalled_bias(config.qoi_names, rates, statistics):
        return (), [_no_prediction(config.qoi_names, rates, statistics, None)]
    planned = study_planning_rates(study, statistics)  # floored, as the runs plan (the record keeps the fits)
    # A tol within a factor 8 of the range's edge dropped the rows after it, advising more levels.
    factors = [f for f in PREDICTION_FACTORS if np.all((base * f >= MIN_TOL) & (base * f <= MAX_TOL))]
    notes = [] if len(factors) == len(PREDICTION_FACTORS) else [_beyond_tolerances(PREDICTION_FACTORS, factors)]
    for factor in factors:
        try:
            prediction = plan(
                tol=base * factor,
                rates=planned,
                statistics=statistics,
                theta=config.estimation.theta,
                max_level=config.grid.max_level,
                coarsest_level=None,
            )
        except RoughUQError as exc:
            # E.g. a bias that does not decay yet (alpha <= 0 on pre-asymptotic
            # levels): keep the table and rates, say why nothing can be predicted.
            return tuple(predictions), [*notes, _no_prediction(config.qoi_names, rates, statistics, exc)]
        predictions.append(PlanRecord.from_plan(_marked_as_runs_refuse(prediction, config, planned, statistics),
                                                seconds_per_cost))
    return tuple(predictions), notes


def _beyond_tolerances(all_factors: Sequence[float], kept: Sequence[float]) -> str:
    """Which multiples of the base tolerance the table leaves out, and why."""
    left_out = ", ".join(f"{f:g}" for f in all_factors if f not in kept)
    return (f"no cost prediction for {left_out} times the tolerance: a tolerance beyond [{MIN_TOL:g}, {MAX_TOL:g}] "
            "(the QoI's unit) is refused by every run; express the QoI in another unit")


def load_screening(path: str | os.PathLike[str]) -> ScreeningResult:
    """The screening a study file holds, as :func:`rough_uq.screen` returns it, for the Python API.

    Recomputed from the stored screening samples, as ``roughuq mlmc`` recomputes it, with the problem of
    :func:`~rough_uq.study.pipeline.studies.load_problem`: ``rough_uq.mlmc(load_problem(path), tol=...,
    screening=load_screening(path))`` plans as ``roughuq mlmc --study path --tol ...`` does, without solving the
    screening again.

    Raises
    ------
    StudyFileError
        For an empty path and a file that is not a readable study file, or a study without a complete screening.
    EstimationError
        Where the rates cannot be fitted on the stored samples (``roughuq screen`` refused them), naming the file.
    """
    missing = ": load_screening reads the file `roughuq screen` wrote (its config's output.path)"
    with open_existing_study(path, writable=False, missing=missing) as study:
        with naming_source(f"{os.fspath(path)} (stored config)"):
            problem = problem_of_config(study.config)
        _, batches = screening_statistics(study)  # its table is computed again with the problem's model
    try:
        return screening_of_batches(problem, batches, n_not_converged=count_not_converged(batches))
    except EstimationError as error:
        raise EstimationError(f"{os.fspath(path)}: the stored screening gives no rates: {error}") from None

"""Runs of targets beyond the mean: the variance and the distribution function with quantiles.

:func:`run_target` drives the targets of :mod:`rough_uq.multilevel.targets` (through
:func:`rough_uq.problem.distribution.estimate_target`) on the study's samples and records them;
:func:`cdf_request` checks the column, thresholds and probabilities of a cdf run, :func:`target_run_id` names a run.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rough_uq import __version__
from rough_uq.study.config import DistributionConfig, StudyConfig
from rough_uq.errors import EstimationError, InvalidParameterError, PlanTooLargeError, is_real_number
from rough_uq.study.executors import Executor
from rough_uq.study.progress import Progress
from rough_uq.study.records import (
    Diagnostic, DistributionRecord, QuantileRecord, RunOutcome, RunRecord, count_not_converged, read_screening_record,
    utc_timestamp,
)
from rough_uq.problem.columns import column_of_load, tol_number, tol_text
from rough_uq.multilevel.distribution import cdf_level_term, quantiles
from rough_uq.multilevel.moments import variance_level_term
from rough_uq.problem.distribution import DEFAULT_PROBABILITIES, TARGETS, estimate_target, initial_finest_level
from rough_uq.problem.runs import run_id
from rough_uq.problem.sampler import ContactModel, LevelBatch, modelled_cost, run_stage
from rough_uq.study.pipeline.diagnostics import collecting_diagnostics, unique_diagnostics
from rough_uq.study.pipeline.estimation import _RunClock, _earlier_run, _run_recorded
from rough_uq.study.pipeline.planning import RUN_PLAN_LIMIT, _check_initial_budget, check_initial_samples
from rough_uq.study.pipeline.sampling import StudySampler
from rough_uq.study.pipeline.studies import Study, naming_source


#: Fewest initial samples per level of a target run: the variance of a level's variance term needs four.
MIN_TARGET_SAMPLES = 4


@dataclass(frozen=True)
class CdfRequest:
    """What a ``cdf`` run estimates: one column's distribution function on a grid, and which quantiles.

    Attributes
    ----------
    column : str
        A result column of the study (``config.qoi_names``).
    thresholds : ndarray, shape (m,)
        Strictly increasing ``s_j``, the column's unit.
    probabilities : tuple of float
        ``p`` of the quantiles reported: distinct, in (0, 1), in the order
        given (:func:`cdf_request`).
    """

    column: str
    thresholds: np.ndarray
    probabilities: tuple[float, ...]


def cdf_request(
    config: StudyConfig,
    *,
    column: str | None,
    thresholds: Sequence[float] | None = None,
    probabilities: Sequence[float] | None = None,
) -> CdfRequest:
    """The column, thresholds and probabilities of a ``cdf`` run: as given, else from ``estimation.distribution``.

    Raises :class:`~rough_uq.errors.InvalidParameterError` naming ``--qoi`` or
    ``--thresholds`` when the column is unknown or no thresholds are given
    (saying how to give them), and ``--probabilities`` unless they are
    distinct real numbers in (0, 1) (``0.5`` and ``5e-1`` are the same).

    Probabilities are kept in the order given, not sorted, as the CLI and the
    config keep them: each quantile is computed on its own, the record and
    the report list them in the user's order, and the run's name hashes them
    in that order (:func:`target_run_id`), so sorting would rename runs
    stored before. Two orders of the same probabilities are therefore two
    records of one run's samples (same stage), not one.
    """
    names = config.qoi_names
    if column is None and len(names) == 1:
        column = names[0]
    given, column = column, None if column is None else column_of_load(column, names)
    if column is None:  # it read "--qoi: got None"
        columns = ", ".join(names)
        raise InvalidParameterError("--qoi", None, f"one result column of this study: {columns}",
                                    text=f"--qoi: this study has several result columns; name one of {columns}")
    if column not in names:  # as typed: "contact_area@6", not the "contact_area@6.0" it was compared as
        raise InvalidParameterError("--qoi", given, f"one result column of this study: {', '.join(names)}")
    entries = _distribution_entries(config, column)
    key, grid = next(((key, entry.thresholds) for key, entry in entries if entry.thresholds is not None),
                     (_qoi_of(config, column), None))
    if thresholds is None and grid is None:
        raise InvalidParameterError(
            "--thresholds", "none (neither the option nor the config gives them)",
            f"the values s where F(s) = P({column} <= s) is estimated: give --thresholds "
            f"START:STOP:COUNT (the QoI's unit) or set estimation.distribution.{key}.thresholds in the config",
        )
    values = np.asarray(grid.values() if thresholds is None else thresholds, dtype=float)
    if values.ndim != 1 or values.size < 2 or not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0):
        # The config's grid is checked when it is loaded; name it, not the --thresholds nobody gave, if not.
        field = "--thresholds" if thresholds is not None else f"estimation.distribution.{key}.thresholds"
        raise InvalidParameterError(field, values, "at least two finite, strictly increasing values")
    if probabilities is None:
        given = (entry.probabilities for _, entry in entries if "probabilities" in entry.model_fields_set)
        probabilities = next(given, DEFAULT_PROBABILITIES)
    return CdfRequest(column=column, thresholds=values, probabilities=_probabilities(probabilities))


def _distribution_entries(config: StudyConfig, column: str) -> list[tuple[str, DistributionConfig]]:
    """The ``estimation.distribution`` entries of a result ``column`` with their keys, the column's own first (a
    load curve's ``contact_area@0.1``, however its load is written), then its QoI's: each setting comes from the
    first entry that gives it."""
    qoi, names = _qoi_of(config, column), config.qoi_names
    entries = config.estimation.distribution
    own = [(key, entry) for key, entry in entries.items() if key != qoi and column_of_load(key, names) == column]
    return own + ([(qoi, entries[qoi])] if qoi in entries else [])


def _probabilities(probabilities: object) -> tuple[float, ...]:
    """``probabilities`` as a tuple of floats, or InvalidParameterError naming ``--probabilities``."""
    allowed = "distinct numbers strictly between 0 and 1, at least one"
    items = (probabilities,) if isinstance(probabilities, (str, bytes)) else probabilities
    try:
        items = tuple(items)
    except TypeError:
        raise InvalidParameterError("--probabilities", probabilities, allowed) from None
    if not items or not all(is_real_number(x) and 0 < x < 1 for x in items):
        raise InvalidParameterError("--probabilities", probabilities, allowed)
    p = tuple(float(x) for x in items)
    if len(set(p)) != len(p):
        repeated = next(x for x in p if p.count(x) > 1)
        raise InvalidParameterError("--probabilities", probabilities, f"{allowed} ({repeated:g} is given twice)")
    return p


def _qoi_of(config: StudyConfig, column: str) -> str:
    """The QoI name of a result column (a load-curve column ``qoi@load`` belongs to ``qoi``)."""
    return next(name for col, name, _ in config.qoi_columns if col == column)


def target_run_id(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None = None) -> str:
    """Name of a variance or cdf run (its record in the study).

    A variance run is named by its columns, ``tol`` and ``theta``
    (:func:`~rough_uq.problem.runs.run_id`). A ``cdf`` run's name adds
    ``_request-<8 hex digits>``, a hash of its thresholds and probabilities
    (:func:`_request_digest`): the same command gives the same name and
    resumes its run, while a run of the same column and tolerance with other
    thresholds or quantiles gets a record of its own instead of replacing the
    first one. Either way the run draws the samples of the name without that
    suffix (:func:`_target_stage`), the stage :func:`rough_uq.variance` /
    :func:`rough_uq.distribution` use: the CLI and the Python API draw the
    same samples, and cdf runs that differ only in thresholds share them.
    """
    base = _target_base_id(study, target=target, tol=tol, request=request)
    return base if target == "variance" else f"{base}_request-{_request_digest(request)}"


def _target_base_id(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None) -> str:
    """The run id of a target without the cdf request's suffix: the name its random stage derives from."""
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
    columns = study.config.qoi_names if target == "variance" else [request.column]
    return run_id(target, columns, np.asarray(tol, dtype=float), study.config.estimation.theta)


def _target_stage(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None) -> int:
    """Random stage of a variance or cdf run (the same for every thresholds and probabilities of a cdf run)."""
    return run_stage("mlmc", _target_base_id(study, target=target, tol=tol, request=request))


def _request_digest(request: CdfRequest) -> str:
    """8 hex digits of SHA-256 of the thresholds and probabilities (12 significant digits: stable to rounding)."""
    values = [[f"{float(s):.12g}" for s in request.thresholds], [f"{float(p):.12g}" for p in request.probabilities]]
    return hashlib.sha256(json.dumps(values, separators=(",", ":")).encode("ascii")).hexdigest()[:8]


class _PlannedSampler:
    """A sampler that announces every batch to the progress before the study sampler computes it.

    The targets' adaptive driver does not publish its plan, so the progress
    shows per level the samples asked for so far (bars that grow as the run
    adapts), which is also what the CLI's memory warning watches.
    """

    def __init__(self, sampler: StudySampler, progress: Progress) -> None:
        self.sampler = sampler
        self.progress = progress
        self.asked: dict[int, int] = {}

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        done = dict(self.asked)  # every earlier batch is complete
        # Samples of this batch already stored (a resumed run) count as done.
        done[level] = done.get(level, 0) + int(indices.size - self.sampler.missing(level, indices).size)
        self.asked[level] = self.asked.get(level, 0) + int(indices.size)
        levels = sorted(self.asked)
        self.progress.plan(levels, [self.asked[lv] for lv in levels], [done.get(lv, 0) for lv in levels])
        return self.sampler(level, indices)


def run_target(
    study: Study,
    *,
    target: str,
    tol: np.ndarray,
    executor: Executor,
    progress: Progress,
    max_cost: float | None = None,
    request: CdfRequest | None = None,
) -> RunRecord:
    """Run MLMC for the variance of every column (``target="variance"``) or one column's CDF (``"cdf"``).

    The adaptive driver of :mod:`rough_uq.multilevel.targets` runs on levels
    ``0..min(2, grid.max_level)`` first with ``estimation.initial_samples``
    samples each (at least :data:`MIN_TARGET_SAMPLES`), adding levels up to
    ``grid.max_level``; no screening is needed. Samples come through a
    :class:`StudySampler` of the run's stage, so an interrupted run resumes
    and the same config gives the same numbers with any number of workers.

    Parameters
    ----------
    target : {"variance", "cdf"}
    tol : ndarray
        ``variance``: RMS tolerance per column, the QoI's unit squared;
        ``cdf``: shape (1,), tolerance on the largest RMS error of ``F`` over
        the thresholds (dimensionless).
    max_cost : float, optional
        Modelled reference seconds; default ``estimation.max_cost``.
    request : CdfRequest
        ``cdf`` only (:func:`cdf_request`).

    Returns
    -------
    RunRecord
        Named by :func:`target_run_id` (a cdf run by its thresholds and
        probabilities too), method ``target``; stored as ``running`` when it
        starts and ``finished`` when it ends (``refused`` with the reason where the
        driver raises :class:`~rough_uq.errors.EstimationError`, e.g. for a
        plan of more than ``MAX_PLANNED_SAMPLES`` samples; the reason, raised
        on, names the options of ``roughuq mlmc``, ``--tol-var NAME=EPS`` or
        ``--tol-cdf EPS``, where the driver says ``tol``). A rerun of a
        finished run keeps the finished record until it finishes itself. A
        run that ``max_cost`` stops before its bias is estimated does not
        meet its tolerance (:mod:`rough_uq.multilevel.targets`).

    Raises
    ------
    InvalidParameterError, EstimationError
        Before any sample and any record, what :func:`check_target_run`
        refuses: a config without the levels or samples such a run needs, or
        a ``max_cost`` below the least cost of the run's initial samples,
        naming ``--max-cost X`` or ``estimation.max_cost X``.
    """
    tol = np.asarray(tol, dtype=float)
    if target == "cdf" and (request is None or tol.shape != (1,)):
        raise InvalidParameterError("--tol-cdf", tol.tolist(), "one number, with the column and thresholds")
    check_target_run(study.config, max_cost=max_cost, model=study.model, source=study.source)
    estimation = study.config.estimation
    max_cost = estimation.max_cost if max_cost is None else max_cost
    key = target_run_id(study, target=target, tol=tol, request=request)
    earlier = _earlier_run(study, key)
    clock = _RunClock.start(earlier)
    stage = _target_stage(study, target=target, tol=tol, request=request)
    sampler = StudySampler(study, stage=stage, executor=executor, progress=progress)
    names = study.config.qoi_names if target == "variance" else (request.column,)
    record = RunRecord(
        run_id=key, method=target, status="running", tol=tuple(tol.tolist()), started=utc_timestamp(),
        code_version=__version__, qoi_names=tuple(names), theta=estimation.theta, max_cost=max_cost,
        stage=sampler.stage, initial_samples=estimation.initial_samples,
    )
    title = f"{target} {tol_text(names, tol)}"
    option = _TARGET_OPTIONS[target]
    given = tol_text(names, tol) if target == "variance" else tol_number(tol[0])
    with _run_recorded(study, record, earlier, clock) as record, _naming_options(f"{option} {given}", option):
        result, diagnostics = _follow_target(study, target, tol, sampler, progress, title, max_cost, request)
    outcome = _target_outcome(study, target=target, sampler=sampler, result=result, request=request,
                              diagnostics=diagnostics, clock=clock)
    record = replace(record, status="finished", outcome=outcome)
    study.store.write_run(key, record.to_json())
    return record


#: The option of ``roughuq mlmc`` that asks for a target run, and gives its tolerance.
_TARGET_OPTIONS = {"variance": "--tol-var", "cdf": "--tol-cdf"}


def check_target_run(
    config: StudyConfig, *, max_cost: float | None = None, model: ContactModel | None = None,
    source: str | None = None,
) -> None:
    """Refuse, before any sample, a variance or cdf run that ``config`` cannot give.

    What :func:`run_target` checks before it opens a record, for callers that
    check before a study file exists (``roughuq mlmc --config``, which would
    otherwise leave an empty study file behind): ``grid.max_level`` at least
    1, ``estimation.initial_samples`` at least :data:`MIN_TARGET_SAMPLES` and
    within :func:`check_initial_samples`, and the budget
    (:func:`check_target_budget`; ``model`` and ``source`` as there).

    Raises
    ------
    InvalidParameterError
        Naming ``grid.max_level`` or ``estimation.initial_samples``.
    ConfigError
        The same, with ``source`` (the config's file) named first (:func:`naming_source`).
    EstimationError
        A budget below the least cost of the initial samples.
    """
    with naming_source(source):
        _check_target_fields(config)
    check_target_budget(config, max_cost=max_cost, model=model, source=source)


def _check_target_fields(config: StudyConfig) -> None:
    """The levels and initial samples a variance or cdf run needs (:func:`check_target_run`)."""
    if config.grid.max_level < 1:
        raise InvalidParameterError("grid.max_level", config.grid.max_level,
                                    "an integer >= 1 for variance and cdf runs (they estimate level differences)")
    if config.estimation.initial_samples < MIN_TARGET_SAMPLES:
        raise InvalidParameterError(
            "estimation.initial_samples", config.estimation.initial_samples,
            f"an integer >= {MIN_TARGET_SAMPLES} for variance and cdf runs (the variance of a level's "
            "variance term needs four samples)",
        )
    check_initial_samples(config, n_levels=initial_finest_level(config.grid.max_level) + 1,
                          run="variance and cdf runs")


def check_target_budget(
    config: StudyConfig, *, max_cost: float | None = None, model: ContactModel | None = None,
    source: str | None = None,
) -> None:
    """Refuse, before any sample, a variance or cdf run whose budget cannot pay for its initial samples.

    The run estimates its bias only once it has ``estimation.initial_samples``
    samples on each of levels ``0..min(2, grid.max_level)``
    (:mod:`rough_uq.multilevel.targets`); their modelled cost is at least that
    of solves that need no iteration at all. A budget below that bound could
    only stop the run before its bias is estimated, a result that cannot meet
    its tolerance (the mean's forecast refuses a predicted overrun alike,
    :func:`~rough_uq.study.pipeline.planning.forecast_run`). ``max_cost`` is ``--max-cost`` (reference seconds);
    None takes ``estimation.max_cost``, named so in the message; no budget at
    all passes. ``model`` is the config's (:func:`~rough_uq.study.pipeline.studies.build_model`), built here if
    not given. ``source`` (the config's file) is named first in a refusal of
    ``estimation.max_cost``.

    Raises
    ------
    EstimationError
        ``--max-cost X is too small for the initial samples of levels 0..2
        (N each), which cost at least ...: raise --max-cost (or lower
        estimation.initial_samples)`` (``estimation.max_cost X`` where that is
        the budget).
    """
    finest = initial_finest_level(config.grid.max_level)
    _check_initial_budget(config, list(range(finest + 1)), max_cost=max_cost, model=model,
                          without="no bias is estimated", source=source)


@contextmanager
def _naming_options(tolerance: str, option: str) -> Iterator[None]:
    """Re-raise the driver's refusal of a tolerance naming what the user gave instead of the driver's ``tol``.

    The multilevel core (and the Python API, :func:`rough_uq.variance` and
    :func:`rough_uq.distribution`, which keep its words) says ``tol 1e-06
    needs about ...: loosen the tolerance``; a run of ``roughuq mlmc`` says
    ``--tol-var contact_area=1e-06 needs about ..., more than the 1e+07 samples a roughuq run may plan: loosen
    --tol-var``
    (``tolerance`` is the option with its value, ``option`` the bare option),
    the same :class:`~rough_uq.errors.PlanTooLargeError` with the same numbers.
    Other errors pass as they are.
    """
    try:
        yield
    except PlanTooLargeError as exc:
        raise exc.named(tolerance=tolerance, advice=f"loosen {option}", limit=RUN_PLAN_LIMIT) from None


def _follow_target(
    study: Study, target: str, tol: np.ndarray, sampler: StudySampler, progress: Progress, title: str,
    max_cost: float | None, request: CdfRequest | None,
) -> tuple[Any, list[Diagnostic]]:
    """Run the targets' adaptive driver with progress; its estimate and the diagnostics it raised."""
    config = study.config
    per_target = dict(qoi_names=config.qoi_names) if target == "variance" else dict(
        thresholds=request.thresholds, qoi=config.qoi_names.index(request.column), qoi_names=config.qoi_names
    )
    planned = _PlannedSampler(sampler, progress)
    progress.start(title)
    try:
        with collecting_diagnostics() as diagnostics:
            result = estimate_target(
                planned, target=target, tol=tol, max_level=config.grid.max_level, theta=config.estimation.theta,
                n_initial=config.estimation.initial_samples, max_cost=max_cost,
                batch_size=config.estimation.batch_size, **per_target,
            )
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop(is_complete=getattr(result, "stop_reason", None) != "max_cost")  # as _follow
    return result, diagnostics


def _target_outcome(
    study: Study, *, target: str, sampler: StudySampler, result: Any, request: CdfRequest | None,
    diagnostics: Sequence[Diagnostic], clock: _RunClock,
) -> RunOutcome:
    """The outcome of a variance run (a :class:`TargetEstimate`) or a cdf run (a :class:`CdfEstimate`)."""
    estimate = result if target == "variance" else result.target
    used = [sampler.samples(int(level), np.arange(int(n))) for level, n in zip(estimate.levels, estimate.n_samples)]
    seconds = float(sum(float(np.sum(batch.cost)) for batch in used))
    seconds_per_cost = seconds / estimate.cost if estimate.cost > 0 else 1.0
    screening = read_screening_record(study.store)
    if screening is not None and screening.seconds_per_cost:
        seconds_per_cost = float(screening.seconds_per_cost)
    mc_cost = _target_mc_cost(study, estimate, used[-1], result if target == "cdf" else None, request)
    extra: list[Diagnostic] = []
    distribution = None if target == "variance" else _distribution_record(result, request, extra)
    # A cdf run's bias and RMSE as its CdfEstimate gives them: at most 1, the largest error of a CDF.
    bias, rmse = (estimate.bias, estimate.rmse) if target == "variance" else (result.bias, result.rmse)
    return RunOutcome(
        finished=utc_timestamp(),
        estimate=_floats(estimate.estimate), stat_error=_floats(estimate.stat_error),
        bias_estimate=_floats(bias), is_bias_estimated=estimate.is_bias_estimated,
        rmse=_floats(rmse), levels=tuple(int(level) for level in estimate.levels),
        n_samples=tuple(int(n) for n in estimate.n_samples), cost=float(estimate.cost), seconds=seconds,
        mc_cost=mc_cost, mc_seconds_predicted=mc_cost * seconds_per_cost, n_computed=sampler.n_computed,
        n_not_converged=count_not_converged(used), tol_met=bool(estimate.tol_met), stop_reason=estimate.stop_reason,
        elapsed=clock.elapsed(sampler),
        diagnostics=unique_diagnostics([*diagnostics, *extra]), distribution=distribution,
    )


def _floats(values: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in np.atleast_1d(values))


def _target_mc_cost(
    study: Study, estimate: Any, finest: LevelBatch, cdf: Any, request: CdfRequest | None
) -> float:
    """Modelled cost of plain MC on the run's finest level to the run's tolerance.

    ``N = max (per-sample variance of the single-level term) / ((1 - theta) tol^2)``,
    the per-sample variance from the run's own ``Q_L`` values (the level-0
    term of the target computed on level ``L``'s values, with ``L``'s
    bandwidth for a CDF), times the mean modelled cost of one uncoupled
    level-``L`` solve.
    """
    level = int(estimate.levels[-1])
    if cdf is None:
        term = variance_level_term(finest.fine, None)
    else:
        index = study.config.qoi_names.index(request.column)
        term = cdf_level_term(finest.fine, None, level, thresholds=request.thresholds,
                              bandwidth=float(cdf.bandwidths[0]), qoi=index)
    budget = (1.0 - estimate.theta) * np.asarray(estimate.tol, dtype=float)[term.groups] ** 2
    n_mc = max(float(np.max(np.ceil(term.per_sample_variance / budget))), 1.0)
    per_sample = float(np.mean(modelled_cost(study.model, level, finest.n_iter, is_coupled=False)))
    return n_mc * per_sample


def _bound(value: float) -> float | None:
    """A quantile's error-bar end, None where it is beyond the thresholds (infinite)."""
    return float(value) if math.isfinite(value) else None


def _distribution_record(cdf: Any, request: CdfRequest, diagnostics: list[Diagnostic]) -> DistributionRecord:
    """Thresholds, monotone CDF with its band and the quantiles.

    A quantile the grid of thresholds does not bracket is a diagnostic.
    """
    rows = []
    for p in request.probabilities:
        try:
            q = quantiles(cdf, probabilities=[p])
        except EstimationError as exc:
            diagnostics.append(Diagnostic(f"quantile p = {p:g} of {request.column}: {exc}"))
            rows.append(QuantileRecord(probability=p, value=None, lower=None, upper=None))
            continue
        rows.append(QuantileRecord(probability=p, value=float(q.values[0]), lower=_bound(q.lower[0]),
                                   upper=_bound(q.upper[0])))
    return DistributionRecord(
        column=request.column,
        thresholds=_floats(cdf.thresholds),
        cdf=_floats(cdf.cdf),
        cdf_lower=_floats(np.clip(cdf.cdf - cdf.rmse, 0.0, 1.0)),
        cdf_upper=_floats(np.clip(cdf.cdf + cdf.rmse, 0.0, 1.0)),
        bandwidths=_floats(cdf.bandwidths),
        quantiles=tuple(rows),
    )

"""Estimation runs of the mean: MLMC and plain MC to a tolerance, recorded in the study file.

:func:`run_estimation` drives the estimators of :mod:`rough_uq.multilevel.drivers` on a
:class:`~rough_uq.study.pipeline.sampling.StudySampler` and stores the run's record as it starts and when it ends
(a rerun of an interrupted run resumes from its stored samples); :func:`missing_samples` replays a run on the
stored samples to list the samples its next round needs (cluster jobs compute them with ``roughuq sample``).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rough_uq import __version__
from rough_uq.errors import EstimationError, RoughUQError
from rough_uq.multilevel.drivers import BatchDone, Finished, PlanUpdated, RichardsonRefused, iter_mc, iter_mlmc
from rough_uq.study.executors import Executor, SerialExecutor
from rough_uq.study.progress import Progress
from rough_uq.study.records import (
    Diagnostic, Forecast, PlanRecord, RatesRecord, RunOutcome, RunRecord, count_not_converged, read_run_records,
    read_screening_record, utc_timestamp,
)
from rough_uq.problem.columns import tol_text
from rough_uq.problem.runs import contact_gamma_beyond, run_id
from rough_uq.problem.sampler import run_stage
from rough_uq.multilevel.statistics import EstimationWarning
from rough_uq.study.pipeline.diagnostics import collecting_diagnostics, unique_diagnostics
from rough_uq.study.pipeline.planning import (
    _check_initial_budget, _check_run_arguments, _estimation_plan, _planned_samples, _refusing_large_plans,
    _screened_seconds_per_cost,
)
from rough_uq.study.pipeline.sampling import StudySampler
from rough_uq.study.pipeline.studies import Study


class _SamplesMissing(Exception):
    """Raised by the replay sampler of :func:`missing_samples` at the first sample not stored."""


@dataclass(frozen=True)
class WorkPlan:
    """Samples an estimation run still needs (:func:`missing_samples`).

    Attributes
    ----------
    run_id : str
        Name of the run.
    stage : int
        Its random stage (the ``--stage`` of ``roughuq sample``).
    missing : dict of int to ndarray of int64
        Per level, the sorted sample indices not stored yet.
    """

    run_id: str
    stage: int
    missing: dict[int, np.ndarray]

    @property
    def n_missing(self) -> int:
        """Total samples missing (0: the stored samples complete the run)."""
        return int(sum(indices.size for indices in self.missing.values()))

    def shards(self, size: int) -> list[tuple[int, int, int]]:
        """The missing samples as shards ``(level, start, stop)`` of at most ``size`` contiguous indices each.

        Level by level, each contiguous run of missing indices (:func:`index_ranges`) cut into pieces of
        ``size`` from its start: what one ``roughuq sample --stage STAGE --level LEVEL --indices START:STOP``
        computes.
        """
        return [(int(level), first, min(first + size, stop))
                for level, indices in self.missing.items()
                for start, stop in index_ranges(indices)
                for first in range(start, stop, size)]


def index_ranges(indices: Sequence[int] | np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of sorted ``indices`` as half-open ``(start, stop)`` pairs (``roughuq sample --indices``)."""
    values = np.asarray(indices, dtype=np.int64).ravel()
    if values.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(values) != 1) + 1
    starts = values[np.concatenate(([0], breaks))]
    lasts = values[np.concatenate((breaks - 1, [values.size - 1]))]
    return [(int(start), int(last) + 1) for start, last in zip(starts, lasts)]  # + 1 in Python: no int64 overflow


def missing_samples(
    study: Study, *, method: str, tol: np.ndarray, max_cost: float | None = None, level: int | None = None
) -> WorkPlan:
    """The sample indices the next round of a run needs that are not stored, per level.

    The run is replayed on the stored samples (exactly the decisions
    ``run_estimation`` would take) until it asks for a sample that is not
    stored; the missing indices of its current plan are returned. No missing
    index means the stored samples complete the run. An adaptive MLMC run may
    plan more samples once these are stored: ask again after merging them.
    Nothing is computed or written.
    """
    _check_run_arguments(study, method, level)
    estimation = study.config.estimation
    key = run_id(method, study.config.qoi_names, tol, estimation.theta, level, richardson=estimation.richardson)
    stage = run_stage(method, key)
    stored = StudySampler(study, stage=stage, executor=SerialExecutor(), progress=Progress())

    def replay(level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if stored.missing(level, indices).size:
            raise _SamplesMissing
        return stored(level, indices)

    max_cost = study.config.estimation.max_cost if max_cost is None else max_cost
    events, _ = _events(
        study, method=method, tol=np.asarray(tol, dtype=float), sampler=replay, max_cost=max_cost, level=level
    )
    planned: dict[int, int] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", EstimationWarning)
            for event in events:
                if isinstance(event, PlanUpdated):
                    planned = {int(level): int(n) for level, n in zip(event.levels, event.n_planned)}
    except _SamplesMissing:
        missing = {level: stored.missing(level, np.arange(n)) for level, n in planned.items()}
        return WorkPlan(key, stage, {level: indices for level, indices in missing.items() if indices.size})
    return WorkPlan(key, stage, {})


def _events(
    study: Study,
    *,
    method: str,
    tol: np.ndarray,
    sampler: StudySampler,
    max_cost: float | None,
    level: int | None = None,
) -> tuple[Iterator[object], dict[str, Any]]:
    """The estimator's event stream and the run's context (``level``, ``screening_rates``, ``predicted``)."""
    config = study.config
    estimation = config.estimation
    options = dict(
        tol=tol,
        theta=estimation.theta,
        n_initial=estimation.initial_samples,
        max_cost=max_cost,
        batch_size=estimation.batch_size,
        qoi_names=config.qoi_names,
    )
    if method == "mc" and level is not None:
        # An explicit level needs no screening (and so no forecast); the bias of that level is then unknown.
        return _refusing_large_plans(iter_mc(sampler, level=level, **options), config.qoi_names, tol), {"level": level}
    events, context = _screened_events(study, method=method, sampler=sampler, options=options)
    return _refusing_large_plans(events, config.qoi_names, tol), context


def _screened_events(
    study: Study, *, method: str, sampler: StudySampler, options: dict[str, Any]
) -> tuple[Iterator[object], dict[str, Any]]:
    """The events of an ``mlmc`` or ``mc --tol`` run from the screening's plan, and the run's context."""
    config, estimation, tol = study.config, study.config.estimation, options["tol"]
    statistics, rates, prediction = _estimation_plan(study, tol, method=method)
    predicted = PlanRecord.from_plan(prediction, _screened_seconds_per_cost(read_screening_record(study.store)))
    context: dict[str, Any] = {"screening_rates": RatesRecord.from_rates(rates), "predicted": predicted}
    if method == "mlmc":
        events = iter_mlmc(
            sampler, max_level=config.grid.max_level, screening=statistics, richardson=estimation.richardson,
            coarsest_level=None, **options,
            gamma_beyond=contact_gamma_beyond(study.model, statistics, config.grid.max_level),
        )
    else:
        context["level"] = int(prediction.finest_level)
        events = iter_mc(
            sampler, level=prediction.finest_level, bias=prediction.bias, screening=statistics, **options
        )
    return events, context


def _earlier_run(study: Study, key: str) -> RunRecord | None:
    """The stored record of run ``key`` (read before this command rewrites it), or None."""
    return next((run for run in read_run_records(study.store) if run.run_id == key), None)


@dataclass(frozen=True)
class _RunClock:
    """When this command started a run, the wall seconds of the run's earlier finish, if any, and of its
    commands stopped before it finished (:attr:`~rough_uq.study.records.RunRecord.stopped_elapsed`)."""

    started: float
    earlier_elapsed: float | None
    stopped: float = 0.0

    @classmethod
    def start(cls, earlier: RunRecord | None) -> _RunClock:
        """Start now; ``earlier`` is the run's stored record (:func:`_earlier_run`), if any.

        Only a finished record's outcome counts: a dropped one keeps the outcome it had, which is not this
        run's. The stopped commands of a record that is not finished count too (not a dropped one's, for the
        same reason).
        """
        outcome = earlier.outcome if earlier is not None and earlier.is_finished else None
        elapsed = None if outcome is None or outcome.elapsed is None else float(outcome.elapsed)
        is_resumed = earlier is not None and not earlier.is_finished and earlier.status != "dropped"
        stopped = float(earlier.stopped_elapsed or 0.0) if is_resumed else 0.0
        return cls(started=time.monotonic(), earlier_elapsed=elapsed, stopped=stopped)

    def so_far(self) -> float:
        """Wall seconds of the run's stopped commands and of this one so far."""
        return self.stopped + time.monotonic() - self.started

    def elapsed(self, sampler: StudySampler) -> float:
        """Wall seconds of the run: its commands', the earlier finish's among them; the earlier finish's
        alone when this rerun computed nothing.

        A finished run that a rerun extends (e.g. one stopped by ``--max-cost``, run again without it) counted
        the rerun alone: 5.05 s against 21.6 CPU-seconds of samples on two workers, the first command's 8.68 s
        lost.
        """
        if sampler.n_computed == 0 and self.earlier_elapsed is not None:
            return self.earlier_elapsed
        return (self.earlier_elapsed or 0.0) + self.so_far()


def _screened_mc_cost(study: Study, tol: np.ndarray) -> float:
    """Modelled cost of plain MC to ``tol`` as the screening predicts it: ``roughuq mc --tol``'s forecast.

    On the level the screening's bias model needs for ``tol``, with its
    ``Var(Q)`` there. Not on the MLMC run's finest level: the levels a run
    starts with and its own bias test (two samples on its finest levels) can
    take it beyond, and plain MC priced there came out some 20 times dearer
    than the MC run at the same tolerance.
    """
    _, rates, prediction = _estimation_plan(study, np.asarray(tol, dtype=float), method="mc")
    _, counts, costs = _planned_samples("mc", None, prediction, rates,
                                        n_initial=study.config.estimation.initial_samples)
    return counts[0] * costs[0]


def run_estimation(
    study: Study,
    *,
    method: str,
    tol: np.ndarray,
    executor: Executor,
    progress: Progress,
    max_cost: float | None = None,
    level: int | None = None,
    forecast: Forecast | None = None,
) -> RunRecord:
    """Run MLMC (``method="mlmc"``) or plain MC (``"mc"``) to ``tol`` and store its record.

    ``forecast`` (:func:`~rough_uq.study.pipeline.planning.forecast_run`, which the CLI calls first to refuse
    hopeless tolerances) is stored in the record as ``forecast``.

    MC runs on the finest level the screening's plan needs for ``tol``, or on
    ``level`` if given (no screening needed; its bias is then not estimated).

    ``max_cost`` (reference seconds of modelled cost; default the config's
    ``estimation.max_cost``) bounds the run. The record is written when the
    run starts (``status = "running"``) and when it ends (``"finished"``, or
    ``"refused"`` with the reason when the estimator raises
    :class:`~rough_uq.errors.EstimationError`, which is raised on); an
    interrupted run (Ctrl-C, SIGTERM) keeps its samples, its record says
    ``interrupted``, and the same command resumes it. A rerun of a finished
    run leaves the finished record in place until it finishes itself, so a
    rerun that is refused, interrupted or fails keeps the earlier result.

    Returns
    -------
    RunRecord
        The finished run (``roughuq report --json`` shows its ``to_json``).
    """
    _check_run_arguments(study, method, level)
    if level is not None:  # no screening's forecast checks its budget: at least its initial samples
        _check_initial_budget(study.config, [level], max_cost=max_cost, model=study.model,
                              without="the run has no variance estimate", source=study.source)
    tol = np.asarray(tol, dtype=float)
    max_cost = study.config.estimation.max_cost if max_cost is None else max_cost
    estimation = study.config.estimation
    key = run_id(method, study.config.qoi_names, tol, estimation.theta, level, richardson=estimation.richardson)
    earlier = _earlier_run(study, key)
    clock = _RunClock.start(earlier)
    sampler = StudySampler(study, stage=run_stage(method, key), executor=executor, progress=progress,
                           advance_served=True)
    events, context = _events(study, method=method, tol=tol, sampler=sampler, max_cost=max_cost, level=level)
    record = _started_record(study, key=key, method=method, tol=tol, stage=sampler.stage, max_cost=max_cost,
                             context=context, forecast=forecast)
    title = f"{method} {tol_text(study.config.qoi_names, tol)}"
    with _run_recorded(study, record, earlier, clock) as record:
        result, diagnostics = _follow(events, progress, title)
    outcome = _outcome(study, method=method, sampler=sampler, result=result, diagnostics=diagnostics, clock=clock)
    record = replace(record, status="finished", outcome=outcome)
    study.store.write_run(key, record.to_json())
    return record


@contextmanager
def _run_recorded(
    study: Study, record: RunRecord, earlier: RunRecord | None, clock: _RunClock
) -> Iterator[RunRecord]:
    """Store ``record`` as ``running`` for the block, then ``refused`` (EstimationError) or ``interrupted`` (else).

    Yields ``record`` with the wall time of the run's stopped commands (``clock``), which the stored records
    keep: the running one too, for a command killed outright.

    ``refused`` comes with the error's message; ``interrupted`` follows
    anything else that stops the block: Ctrl-C, SIGTERM (which raises
    KeyboardInterrupt too), a failing worker or disk.

    A refused run is not an interrupted one: rerunning it as it is would be
    refused again, so its record must not stay ``running`` (which the report
    shows as "interrupted; rerun the same command to resume"). The error is
    raised on. A rerun of a finished run (``earlier``) leaves its record
    as it is until the caller stores the new outcome: a rerun that is
    refused, interrupted or fails never downgrades a finished result.
    """
    record = replace(record, stopped_elapsed=clock.stopped or None)
    is_kept = earlier is not None and earlier.is_finished
    if not is_kept:
        study.store.write_run(record.run_id, record.to_json())
    try:
        yield record
    except EstimationError as exc:
        if not is_kept:
            refused = replace(record, status="refused", reason=str(exc), stopped_elapsed=clock.so_far())
            study.store.write_run(record.run_id, refused.to_json())
        raise
    except BaseException:
        # Ctrl-C, SIGTERM, a worker or the disk failing: the run stopped, and the same command resumes it. Recorded
        # so, that a report while another run holds the study does not show it as running (a process killed
        # outright leaves "running", which the report reads by the lock). Best effort: the record must not replace
        # the error or the interrupt that stopped the run.
        if not is_kept:
            with suppress(Exception):
                stopped = replace(record, status="interrupted", stopped_elapsed=clock.so_far())
                study.store.write_run(record.run_id, stopped.to_json())
        raise


def _started_record(
    study: Study, *, key: str, method: str, tol: np.ndarray, stage: int, max_cost: float | None,
    context: Mapping[str, Any], forecast: Forecast | None,
) -> RunRecord:
    """The record of a run that starts: its settings and context, no outcome."""
    config = study.config
    return RunRecord(
        run_id=key,
        method=method,
        status="running",
        tol=tuple(tol.tolist()),
        started=utc_timestamp(),
        code_version=__version__,
        qoi_names=tuple(config.qoi_names),
        theta=config.estimation.theta,
        max_cost=max_cost,
        stage=stage,
        initial_samples=config.estimation.initial_samples,
        forecast=forecast,
        **context,
    )


def _follow(events: Iterator[object], progress: Progress, title: str) -> tuple[Any, list[Diagnostic]]:
    """Drive the estimator's events with progress; its result and the diagnostics it raised."""
    progress.start(title)
    result = None
    try:
        with collecting_diagnostics() as diagnostics:
            for event in events:
                if isinstance(event, (PlanUpdated, BatchDone)):
                    # A batch's counts include samples served from the store (an earlier run's, merged shards'),
                    # which no sample computed here advanced: a rerun's progress ended at "7/11 samples", "done".
                    progress.plan(event.levels, event.n_planned, event.n_done)
                elif isinstance(event, Finished):
                    result = event.result
                elif not isinstance(event, RichardsonRefused):  # pragma: no cover - the contract
                    raise RoughUQError(f"unexpected estimator event {event!r}")
    except BaseException:
        progress.stop(is_complete=False)
        raise
    # A run its budget stopped did not draw what it planned: "stopped after", not "done in".
    progress.stop(is_complete=getattr(result, "stop_reason", None) != "max_cost")
    if result is None:  # pragma: no cover - the event stream always ends with Finished
        raise RoughUQError("the estimator stopped without a result")
    return result, diagnostics


def _outcome(
    study: Study, *, method: str, sampler: StudySampler, result: Any, diagnostics: Sequence[Diagnostic],
    clock: _RunClock,
) -> RunOutcome:
    """What the finished run found, with the seconds and non-converged solves of the samples it used."""
    used = [sampler.samples(int(level), np.arange(int(n))) for level, n in zip(result.levels, result.n_samples)]
    seconds = 0.0
    for batch in used:  # summed level by level, as the records always have been
        seconds += float(np.sum(batch.cost))
    seconds_per_cost = seconds / result.cost if result.cost > 0 else 1.0
    screening = read_screening_record(study.store)
    if screening is not None and screening.seconds_per_cost:
        seconds_per_cost = float(screening.seconds_per_cost)  # robust to the pool's start-up
    mc_cost = _screened_mc_cost(study, result.tol) if method == "mlmc" else result.mc_cost
    return RunOutcome.from_result(
        result,
        mean_seconds=[float(np.mean(batch.cost)) for batch in used],
        seconds=seconds,
        elapsed=clock.elapsed(sampler),
        mc_cost=mc_cost,
        seconds_per_cost=seconds_per_cost,
        n_computed=sampler.n_computed,
        n_not_converged=count_not_converged(used),
        diagnostics=unique_diagnostics(diagnostics),
    )

"""The driver loop shared by MC and MLMC: a run's state, its rounds of batches and their events."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import PLANNED_COUNT_CAP, EstimationError, warn_at_caller
from rough_uq.multilevel.allocation import check_tol
from rough_uq.multilevel.drivers.events import BatchDone, Event
from rough_uq.multilevel.drivers.hierarchy import _Hierarchy, _batch_size, _per_sample_cost
from rough_uq.multilevel.drivers.samples import _Batch, _LevelSamples, Sampler, call_sampler
from rough_uq.multilevel.rates import RATE_FLOOR
from rough_uq.multilevel.statistics import EstimationWarning, LevelStatistics, checked_names, readonly_array

_MAX_COUNT = float(PLANNED_COUNT_CAP)


@dataclass(frozen=True, eq=False)
class _Options:
    """The checked arguments every run takes (:func:`~rough_uq.multilevel.drivers.adaptive.iter_mlmc`,
    :func:`~rough_uq.multilevel.drivers.plain_mc.iter_mc`).

    ``tol`` has shape (n_qoi,), or (1,) while the number of QoIs is unknown;
    ``qoi_names`` is checked against the number of QoIs once it is known.
    """

    tol: np.ndarray
    theta: float
    n_initial: int
    screening: LevelStatistics | None
    kurtosis_limit: float
    qoi_names: tuple[str, ...] | None


class _Run:
    """What MC and MLMC runs share: the hierarchy, the tolerance, the QoI count, the stop reason.

    :func:`_drive` runs the loop; a subclass decides the plan (:meth:`replan`),
    what happens once a round of samples is (nearly) complete
    (:meth:`after_round`) and the result (:meth:`finish`). MC is the
    one-level hierarchy at its level.
    """

    def __init__(self, hierarchy: _Hierarchy, options: _Options) -> None:
        self.hierarchy = hierarchy
        self.options = options
        self.tol = options.tol
        self.n_qoi: int | None = None
        self.is_scalar = False
        self.stop_reason = ""

    @property
    def cost_rate(self) -> float:
        """``gamma`` for predicting the cost of a level from the nearest sampled one.

        Any value serves a run that samples one level only (``2^(gamma 0) = 1``).
        """
        return RATE_FLOOR

    def accept(self, batch: _Batch, level: int) -> None:
        """Check a batch's number of QoIs; the first batch fixes it."""
        if self.n_qoi is None:
            self.n_qoi, self.is_scalar = batch.fine.shape[1], batch.is_scalar
            self.tol = check_tol(self.tol, self.n_qoi)
            _check_qoi_names(self.options.qoi_names, self.n_qoi)
            self.on_qoi_count(self.n_qoi)
        elif batch.fine.shape[1] != self.n_qoi:
            raise EstimationError(f"sampler returned {batch.fine.shape[1]} QoIs on level {level}, earlier {self.n_qoi}")

    def on_qoi_count(self, n_qoi: int) -> None:
        """Check what depends on the number of QoIs, once it is known."""

    def start(self) -> Iterator[Event]:
        """Events right after the initial plan."""
        return iter(())

    def check_reach(self) -> None:
        """Warn of a tolerance the run cannot meet, before the new plan's samples are drawn (MLMC only)."""

    def replan(self) -> None:
        raise NotImplementedError

    def after_round(self) -> Iterator[Event]:
        raise NotImplementedError

    def finish(self) -> Iterator[Event]:
        raise NotImplementedError


def checked_batch_cap(batch_size: int | None) -> float:
    """The most samples one sampler call draws: ``batch_size`` (checked by the caller), ``inf`` for None or for a
    size beyond any plan (``10**400`` has no float, and no plan asks for more than :data:`PLANNED_COUNT_CAP`)."""
    return math.inf if batch_size is None or batch_size > _MAX_COUNT else float(batch_size)


def round_counts(missing: Sequence[int], batch_cap: float, share: float | None) -> list[float]:
    """Per level, the most samples one pass draws, for levels still ``missing`` that many samples.

    ``share`` None (no budget, or one that pays what the plan misses): ``batch_cap`` each. Otherwise ``share``
    is the fraction of the missing samples' predicted cost that the budget left pays, and every level draws that
    fraction of its missing samples (at least one), scaled down together where the level missing most would
    draw more than ``batch_cap``: a run the budget stops has then drawn its levels in about the ratio of its
    plan, not in equal batches (or level after level) that leave the finer levels short.
    """
    largest = max(missing, default=0)
    if share is None or largest <= 0:
        return [batch_cap] * len(missing)
    scale = min(share, batch_cap / largest)
    return [max(1, math.ceil(scale * count)) for count in missing]


def budget_share(missing: Sequence[int], unit_costs: Sequence[float], budget_left: float) -> float | None:
    """The fraction of the missing samples' predicted cost that ``budget_left`` pays, or None where it pays all
    of it, or where some level's cost is not known yet (then a run draws as without a budget)."""
    if any(not unit > 0 for unit in unit_costs):
        return None
    needed = sum(count * unit for count, unit in zip(missing, unit_costs))
    return None if needed <= budget_left else max(budget_left, 0.0) / needed


def _round_share(run: _Run, pending: Sequence[_LevelSamples], missing: Sequence[int],
                 max_cost: float | None) -> float | None:
    """:func:`budget_share` of a round of the mean driver (None without ``max_cost``)."""
    if max_cost is None:
        return None
    hierarchy = run.hierarchy
    units = [_per_sample_cost(hierarchy, s.level, run.cost_rate) for s in pending]
    return budget_share(missing, units, max_cost - hierarchy.spent)


def _draw(
    run: _Run, sampler: Sampler, samples: _LevelSamples, batch_cap: float, max_cost: float | None
) -> tuple[list[_Batch], bool]:
    """Draw and store the next samples of one level; the batches, and whether ``max_cost`` stops the run.

    The run stops when the budget affords no sample, or when it cannot pay
    the rest of a batch whose cost a probe had to tell first (:data:`_PROBE`).
    """
    hierarchy = run.hierarchy
    level = samples.level
    wanted = int(min(hierarchy.targets[level] - samples.n, batch_cap))
    batches = []
    is_probed = max_cost is not None and wanted > _PROBE and _per_sample_cost(hierarchy, level, run.cost_rate) <= 0
    if is_probed:
        batches.append(_draw_batch(run, sampler, samples, _PROBE))
        wanted -= _PROBE
    n = _batch_size(hierarchy, level, wanted, max_cost, run.cost_rate)
    if n:
        batches.append(_draw_batch(run, sampler, samples, n))
    is_over_budget = n < wanted if is_probed else n == 0
    return batches, is_over_budget


#: Samples drawn first, alone, where a run with a budget knows no cost yet (its first batch): a budget below
#: the cost of the first batch (``n_initial`` samples) paid all of it before, e.g. 1300 times
#: ``--max-cost 1e-5`` for an MC run on one level; now the run stops once the probe shows the rest unaffordable.
_PROBE = 2


def _draw_batch(run: _Run, sampler: Sampler, samples: _LevelSamples, n: int) -> _Batch:
    """Draw ``n`` samples of ``samples``' level and store them."""
    hierarchy = run.hierarchy
    batch = call_sampler(sampler, samples.level, samples.n, n)
    run.accept(batch, samples.level)
    # The base level is sampled as Q_base: its coarse values are not part of the sum.
    coarse = np.zeros_like(batch.fine) if samples.level == hierarchy.base else batch.coarse
    samples.add(batch.fine, coarse, batch.cost)
    hierarchy.add_cost(batch.cost)
    return batch


def _batch_event(hierarchy: _Hierarchy, level: int, batch: _Batch) -> BatchDone:
    return BatchDone(
        level=level,
        indices=readonly_array(batch.indices),
        fine=readonly_array(batch.fine),
        coarse=readonly_array(batch.coarse),
        cost=readonly_array(batch.cost),
        levels=hierarchy.levels(),
        n_done=hierarchy.n_done(),
        n_planned=hierarchy.n_planned(),
    )


def _drive(
    make_run: Callable[[], _Run], sampler: Sampler, *, batch_cap: float, max_cost: float | None
) -> Iterator[Event]:
    """The run's events: rounds of batches, each followed by a new plan, until a stop reason is set.

    ``make_run`` is called on the first event, so that errors in the run's
    set-up surface where the events are consumed. Warnings of
    :meth:`_Run.finish` name the consumer's line (:func:`~rough_uq.errors.warn_at_caller`).
    """
    run = make_run()
    hierarchy = run.hierarchy
    yield hierarchy.plan_event("initial")
    yield from run.start()
    while not run.stop_reason:
        pending = hierarchy.pending()
        missing = [hierarchy.targets[samples.level] - samples.n for samples in pending]
        share = _round_share(run, pending, missing, max_cost)
        counts = round_counts(missing, batch_cap, share)
        for samples, count in zip(pending, counts):
            is_over_budget = False
            while not is_over_budget:
                # A level needs two samples for a variance (_batch_size refuses to start it with fewer).
                batches, is_over_budget = _draw(run, sampler, samples, max(count, 2 - samples.n), max_cost)
                for batch in batches:
                    yield _batch_event(hierarchy, samples.level, batch)
                # Without a budget that cuts the round, a level gets all it misses before the next plan, in
                # batches of batch_size: the plans, and so the result, do not depend on the batch size.
                if share is not None or samples.n >= hierarchy.targets[samples.level]:
                    break
            if is_over_budget:
                run.stop_reason = "max_cost"
                break
        if run.stop_reason:
            break
        if pending:
            before = list(hierarchy.targets)
            run.replan()
            if hierarchy.targets != before:
                yield hierarchy.plan_event("variance")
                run.check_reach()  # after the plan's event: a consumer that refuses the plan never draws it
            if not hierarchy.is_nearly_complete():
                continue
        yield from run.after_round()
    yield from run.finish()


def _per_qoi(names: Sequence[str], values: np.ndarray, columns: np.ndarray) -> str:
    """``values`` of ``columns`` in a message, ``name=value`` with three significant digits."""
    return ", ".join(f"{names[column]}={float(values[column]):.3g}" for column in columns)


def _check_qoi_names(qoi_names: object, n_qoi: int | None) -> tuple[str, ...] | None:
    """``qoi_names`` as a tuple of ``n_qoi`` strings (any number while ``n_qoi`` is None), or None."""
    names = checked_names(qoi_names, n_qoi, argument="qoi_names")
    return None if names is None else tuple(names)


def _warn_zero_cost(statistics: LevelStatistics) -> None:
    if np.any(statistics.mean_cost <= 0):
        warn_at_caller(
            f"the sampler reported zero cost on levels {statistics.levels[statistics.mean_cost <= 0].tolist()}; "
            "the sample allocation uses costs extrapolated with the cost rate instead",
            EstimationWarning,
        )

"""Plain Monte Carlo (:func:`iter_mc`, :func:`mc`): the one-level hierarchy at its level."""

from __future__ import annotations

import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import (
    InvalidParameterError, checked_integer, checked_real_array, warn_at_caller,
)
from rough_uq.multilevel.allocation import check_fraction, check_tol
from rough_uq.multilevel.drivers.adaptive import MIN_LEVEL_SAMPLES, _final
from rough_uq.multilevel.drivers.events import EstimationResult, Event, Finished
from rough_uq.multilevel.drivers.hierarchy import _Hierarchy
from rough_uq.multilevel.drivers.loop import _MAX_COUNT, _Options, _Run, _check_qoi_names, _drive, checked_batch_cap
from rough_uq.multilevel.drivers.samples import (
    _LevelSamples,
    Sampler,
    check_initial_count,
    check_kurtosis_limit,
    _shape_out,
    check_optional_positive,
)
from rough_uq.multilevel.statistics import (
    KURTOSIS_LIMIT,
    EstimationWarning,
    LevelStatistics,
    assemble_statistics,
    kurtosis_text,
    kurtosis_threshold,
    qoi_text,
    readonly_array,
)


def iter_mc(
    sampler: Sampler,
    *,
    tol: float | np.ndarray,
    level: int,
    theta: float = 0.5,
    bias: float | np.ndarray | None = None,
    n_initial: int = 10,
    max_cost: float | None = None,
    batch_size: int | None = 1000,
    screening: LevelStatistics | None = None,
    kurtosis_limit: float = KURTOSIS_LIMIT,
    qoi_names: Sequence[str] | None = None,
) -> Iterator[Event]:
    """Plain MC on one level to a tolerance, as a generator of events.

    Draws ``N = ceil((1-theta)^-1 eps^-2 Var(Q_level))`` samples (at least
    ``n_initial``; maximum over QoIs), re-estimating ``Var(Q_level)`` after
    every batch. Only the ``fine`` values are used; a sampler for MC may
    return zeros as ``coarse``.

    With a ``screening`` the run is treated as MLMC's (:func:`~rough_uq.multilevel.drivers.adaptive.iter_mlmc`):
    it starts from the ``N`` the screening's ``Var(Q)`` implies, needs at
    least 2 samples, and ``Var(Q_level)`` is pooled with the screening's if
    the screening sampled ``level``; otherwise the variance used to plan is
    floored at half the screening's ``Var(Q)`` on its finest level.

    Parameters
    ----------
    sampler : callable
        ``sampler(level, sample_indices) -> (fine, coarse, cost)``.
    tol : float or ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error.
    level : int
        The level (grid) to sample.
    theta : float
        Bias share of ``eps^2``; the statistical target is ``(1-theta) eps^2``,
        as in :func:`~rough_uq.multilevel.allocation.plan`'s MC prediction.
    bias : float or ndarray, optional
        Estimated bias of level ``level`` (e.g. ``Plan.bias`` from the
        screening). MC cannot estimate it from one level; without it the
        result has ``bias_estimate = 0`` and ``is_bias_estimated = False``.
    n_initial : int
        Samples before the variance is trusted (>= 2), without a screening.
    max_cost : float, optional
        Budget in the sampler's cost unit (as in :func:`~rough_uq.multilevel.drivers.adaptive.iter_mlmc`); a run it
        stops before its first ``n_initial`` samples (2 from a screening) does
        not meet ``tol``.
    batch_size : int or None
        Largest batch per sampler call; the result does not depend on it (as for
        :func:`~rough_uq.multilevel.drivers.adaptive.iter_mlmc`).
    screening : LevelStatistics, optional
        Screening table (independent samples) of the same hierarchy.
    kurtosis_limit : float
        Kurtosis of ``Q`` above which a warning is issued, as for
        :func:`~rough_uq.multilevel.drivers.adaptive.iter_mlmc`.
    qoi_names : sequence of str, optional
        Names of the QoI columns, one per QoI: the kurtosis warning names the
        QoIs it concerns (``for clusters``); without them it names none.

    Yields
    ------
    PlanUpdated, BatchDone, Finished
    """
    theta = check_fraction("theta", theta)
    level = checked_integer("level", level, 0)
    n_initial = check_initial_count(n_initial)
    batch_size = None if batch_size is None else checked_integer("batch_size", batch_size, 1)
    max_cost = check_optional_positive("max_cost", max_cost)
    n_qoi = screening.n_qoi if screening is not None else None
    tol = check_tol(tol, n_qoi)
    options = _McOptions(
        tol=tol,
        qoi_names=_check_qoi_names(qoi_names, n_qoi),
        level=level,
        theta=theta,
        bias=None if bias is None else _checked_bias(bias),
        n_initial=n_initial,
        screening=screening,
        kurtosis_limit=check_kurtosis_limit(kurtosis_limit),
    )
    batch_cap = checked_batch_cap(batch_size)
    return _drive(functools.partial(_McRun, options), sampler, batch_cap=batch_cap, max_cost=max_cost)


def _checked_bias(bias: object) -> np.ndarray:
    """``|bias|`` as a 1-d float array; strings, booleans and non-finite values are refused naming ``bias``."""
    allowed = "a finite number or a 1-d array of them (one per QoI)"
    values = checked_real_array("bias", bias, allowed)
    if values.ndim > 1 or not np.all(np.isfinite(values)):
        raise InvalidParameterError("bias", bias, allowed)
    return np.atleast_1d(np.abs(values))


def _mc_screened_variance(screening: LevelStatistics, level: int) -> tuple[np.ndarray, float | np.ndarray]:
    """``Var(Q_level)`` the screening predicts, and the floor of the run's planning variance.

    The level's own screened variance (no floor: the run pools it instead);
    else that of the finest screened level, half of which floors the run's;
    zeros without a level screened with two or more samples.
    """
    usable = np.flatnonzero(screening.n_samples >= 2)
    same = usable[screening.levels[usable] == level]
    if same.size:
        return screening.var_fine[same[0]], 0.0
    if usable.size:
        return screening.var_fine[usable[-1]], 0.5 * screening.var_fine[usable[-1]]
    return np.zeros(screening.n_qoi), 0.0


@dataclass(frozen=True, eq=False)
class _McOptions(_Options):
    """The checked arguments of :func:`iter_mc` that shape the run (see there)."""

    level: int
    bias: np.ndarray | None


class _McRun(_Run):
    """Plain MC on ``level``: a hierarchy whose base is ``level``, so its samples are ``Q_level`` alone.

    ``bias`` is the bias given to :func:`iter_mc` (None if unknown), one per
    QoI once their number is known.
    """

    def __init__(self, options: _McOptions) -> None:
        screening, level, tol = options.screening, options.level, options.tol
        floor = options.n_initial if screening is None else MIN_LEVEL_SAMPLES
        # The hierarchy pools the screening's Var(Q_level), if it sampled the level, as MLMC's base level.
        hierarchy = _Hierarchy(level + 1, floor, screening, base=level, reported_from=level)
        super().__init__(hierarchy, options)
        self.level, self.bias = level, options.bias
        self.var_floor: float | np.ndarray = 0.0
        if screening is not None:
            first_var, self.var_floor = _mc_screened_variance(screening, level)
            first = np.max(np.ceil(first_var / ((1.0 - options.theta) * tol**2)))
            hierarchy.targets[level] = max(int(min(first, _MAX_COUNT)), floor)

    @property
    def samples(self) -> _LevelSamples:
        return self.hierarchy.samples[self.level]

    def on_qoi_count(self, n_qoi: int) -> None:
        if self.bias is not None:
            self.bias = _check_bias(self.bias, n_qoi)

    def variance(self) -> np.ndarray:
        """``Var(Q_level)``: the run's, pooled with the screening's where it sampled the level."""
        return self.hierarchy.variances(self.level, self.samples.moments().var_fine, self.samples.n)

    def replan(self) -> None:
        """``N = ceil((1-theta)^-1 eps^-2 Var(Q_level))``, maximum over QoIs, never below the drawn or the floor."""
        budget = (1.0 - self.options.theta) * self.tol**2
        wanted = np.max(np.ceil(np.maximum(self.variance(), self.var_floor) / budget))
        n = max(self.samples.n, int(min(wanted, _MAX_COUNT)), self.hierarchy.floor)
        self.hierarchy.targets[self.level] = n

    def bias_values(self) -> np.ndarray:
        return self.bias if self.bias is not None else np.zeros(self.n_qoi)

    def is_tol_met(self) -> bool:
        """``Var / N + bias^2 <= eps^2`` with a given bias, ``Var / N <= (1 - theta) eps^2`` without one (the
        statistical error's share, which the plan aims at), once the run has the samples it starts with.

        Fewer than the first plan's samples (``n_initial``, or 2 from a
        screening) give no variance estimate to trust: a budget that stopped
        the run after a probe of two (:data:`~rough_uq.multilevel.drivers.loop._PROBE`) claimed the tolerance met.
        Without a bias, ``max_cost`` stopped runs between the two errors and
        called them met, while the same run without the budget drew on.
        """
        if self.samples.n < self.hierarchy.floor:
            return False
        stat_variance = self.variance() / self.samples.n
        if self.bias is None:
            return bool(np.all(stat_variance <= (1.0 - self.options.theta) * self.tol**2 * (1 + 1e-12)))
        return bool(np.all(stat_variance + self.bias_values() ** 2 <= self.tol**2 * (1 + 1e-12)))

    def after_round(self) -> Iterator[Event]:
        # MC has no level to add: once the samples are drawn, only the given bias can fail.
        if self.hierarchy.is_complete():
            self.stop_reason = "tol_met" if self.is_tol_met() else "bias"
        yield from ()

    def finish(self) -> Iterator[Event]:
        moments = self.samples.moments()
        result = _mc_result(self)
        limit, names = self.options.kurtosis_limit, self.options.qoi_names
        heavy = np.flatnonzero(moments.kurtosis > kurtosis_threshold(moments.n, limit))
        if heavy.size:
            which = "" if names is None else f" for {qoi_text(heavy, names)}"
            worst = float(np.max(moments.kurtosis))
            warn_at_caller(
                f"mc: kurtosis {worst:.3g} of Q on level {self.level}{which} {kurtosis_text(worst, moments.n, limit)}; "
                "the variance and error estimates are unreliable",
                EstimationWarning,
            )
        yield Finished(result=result)


def _mc_result(run: _McRun) -> EstimationResult:
    moments = run.samples.moments()
    # A table of Q alone (coarse values stored as zeros), with base level 0 as MC tables always had.
    statistics = assemble_statistics([run.level], [moments])
    is_scalar = run.is_scalar
    budget = (1.0 - run.options.theta) * run.tol**2
    mc_n = float(np.max(np.minimum(np.ceil(run.variance() / budget), _MAX_COUNT)))
    return EstimationResult(
        method="mc",
        estimate=_shape_out(moments.mean_fine, is_scalar),
        stat_error=_shape_out(np.sqrt(run.variance() / run.samples.n), is_scalar),
        bias_estimate=_shape_out(run.bias_values(), is_scalar),
        variance=_shape_out(moments.var_fine, is_scalar),
        variance_error=_shape_out(moments.var_delta_se, is_scalar),
        n_samples=statistics.n_samples,
        levels=statistics.levels,
        cost=run.hierarchy.spent,
        mc_cost=float(mc_n * moments.mean_cost),
        statistics=statistics,
        rates=None,
        tol=readonly_array(run.tol),
        theta=run.options.theta,
        tol_met=run.is_tol_met(),
        stop_reason=run.stop_reason,
        is_bias_estimated=run.bias is not None,
        qoi_names=run.options.qoi_names,
    )


def _check_bias(bias: np.ndarray, n_qoi: int) -> np.ndarray:
    """Bias as an array of shape (n_qoi,) (a single value is broadcast)."""
    if bias.size == 1:
        return np.repeat(bias, n_qoi)
    if bias.size != n_qoi:
        raise InvalidParameterError("bias", bias, f"a scalar or {n_qoi} values (one per QoI)")
    return bias


def mc(
    sampler: Sampler, *, tol: float | np.ndarray, level: int, qoi_names: Sequence[str] | None = None,
    **options: object,
) -> EstimationResult:
    """Plain Monte Carlo estimate of ``E[Q_level]`` to RMS tolerance ``tol``.

    Runs :func:`iter_mc` to the end; ``qoi_names`` (names of the QoI
    columns, for the warnings) and ``options`` are its keyword arguments
    (``theta``, ``bias``, ``n_initial``, ``max_cost``, ``batch_size``,
    ``screening``, ``kurtosis_limit``).

    Returns
    -------
    EstimationResult
    """
    return _final(iter_mc(sampler, tol=tol, level=level, qoi_names=qoi_names, **options))

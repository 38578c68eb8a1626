"""Beyond the mean on a :class:`~rough_uq.problem.contact.ContactProblem`: variance, CDF and quantiles.

:func:`variance` and :func:`distribution` run the adaptive MLMC driver of
:mod:`rough_uq.multilevel.targets` on a contact problem, with the level terms
of :mod:`rough_uq.multilevel.moments` (unbiased ``h2`` differences) and
:mod:`rough_uq.multilevel.distribution` (smoothed indicators), in this process
or on an executor; nothing is written to disk.

Random streams
--------------
As for :func:`rough_uq.mlmc` (:mod:`rough_uq.problem.runs`): every sample
comes from ``SeedSequence(seed, spawn_key=(stage, level, index))``, with a
coupled stage named after the target, the columns, the tolerance and
``theta`` (``run_id("variance", ...)``, ``run_id("cdf", ...)``). The same
problem and settings draw the same samples; a variance run and a mean run
never share samples.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import dataclasses
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import EstimationWarning, InvalidParameterError, is_one_of, warn_at_caller
from rough_uq.multilevel.distribution import (
    DEFAULT_PROBABILITIES, CdfEstimate, Quantiles, check_cdf_tol, checked_thresholds, mlmc_cdf, quantiles,
)
from rough_uq.multilevel.moments import mlmc_variance
from rough_uq.multilevel.drivers import MAX_PLANNED_SAMPLES, Sampler
from rough_uq.multilevel.statistics import checked_names, qoi_text
from rough_uq.multilevel.targets import TargetEstimate
from rough_uq.problem.contact import BatchExecutor, ContactProblem, ProgressReporter
from rough_uq.problem.columns import column_of_load, tol_text
from rough_uq.problem.runs import (
    checked_problem, checked_tolerances, reporting_progress, run_id, warn_not_converged, warn_not_met,
)
from rough_uq.problem.sampler import run_stage

__all__ = ["DistributionResult", "distribution", "estimate_target", "initial_finest_level", "variance"]


#: The targets :func:`estimate_target` runs.
TARGETS = ("variance", "cdf")

#: The finest level a run starts on by default (two levels >= 1 to fit the rates from), if the problem has it.
MIN_FINEST_LEVEL = 2


def initial_finest_level(max_level: int, min_finest_level: int | None = None) -> int:
    """The finest level a target run starts on: ``min_finest_level``, by default ``min(MIN_FINEST_LEVEL, max_level)``.

    The run samples levels ``0..`` this one first, ``n_initial`` samples
    each; its bias is estimated once they are drawn.
    """
    return min(MIN_FINEST_LEVEL, max_level) if min_finest_level is None else min_finest_level


def estimate_target(
    sampler: Sampler,
    *,
    target: str,
    tol: np.ndarray,
    max_level: int,
    thresholds: Sequence[float] | np.ndarray | None = None,
    qoi: int = 0,
    bandwidth: float | None = None,
    theta: float = 0.5,
    n_initial: int = 32,
    min_finest_level: int | None = None,
    max_cost: float | None = None,
    batch_size: int | None = 10,
    max_samples: int | None = MAX_PLANNED_SAMPLES,
    qoi_names: Sequence[str] | None = None,
) -> TargetEstimate | CdfEstimate:
    """The adaptive driver of ``target`` on a level sampler, with the defaults of this module.

    The one place the front door (:func:`variance`, :func:`distribution`)
    and the study pipeline (``roughuq mlmc --tol-var / --tol-cdf``) run a
    target from, so that both make the same decisions on the same samples.

    Parameters
    ----------
    sampler : callable
        ``sampler(level, indices) -> (fine, coarse, cost)``.
    target : str
        ``"variance"`` (every column) or ``"cdf"`` (column ``qoi`` on ``thresholds``).
    tol : ndarray
        Tolerances: one per column (variance) or one (cdf, dimensionless).
    max_level : int
        Finest level allowed, >= 1 (the targets telescope level differences).
    thresholds, qoi, bandwidth
        For ``"cdf"``: as in :func:`distribution` (``bandwidth`` default twice
        the mean threshold spacing).
    theta, n_initial, min_finest_level, max_cost, batch_size, max_samples
        As for :func:`variance` (``min_finest_level`` default ``min(2, max_level)``).
    qoi_names : sequence of str, optional
        Names of the columns, one per QoI, for the warnings: about a negative
        variance (``variance of contact_area``) and those of the checks of the
        final samples (SPEC section 5; ``for contact_area``); without them
        they give the column index (``QoI [0]``).
    """
    if max_level < 1:
        # The driver would name its min_finest_level (min(2, 0) = 0), which the caller never gave.
        raise InvalidParameterError("max_level", max_level, "an integer >= 1: variance and distribution runs "
                                    "estimate level differences")
    checked_names(qoi_names, None, argument="qoi_names")
    options = dict(
        theta=theta,
        n_initial=n_initial,
        min_finest_level=initial_finest_level(max_level, min_finest_level),
        max_level=max_level,
        max_cost=max_cost,
        batch_size=batch_size,
        max_samples=max_samples,
        qoi_names=qoi_names,
    )
    if target == "variance":
        result = mlmc_variance(sampler, tol=tol, **options)
        _warn_negative_variance(result, checked_names(qoi_names, result.estimate.size, argument="qoi_names"))
        return result
    if target != "cdf":
        raise InvalidParameterError("target", target, f"one of {', '.join(TARGETS)}")
    s = checked_thresholds(thresholds)
    width = _default_bandwidth(s) if bandwidth is None else bandwidth
    tol_value = float(np.asarray(tol).reshape(-1)[0])
    return mlmc_cdf(sampler, thresholds=s, tol=tol_value, bandwidth=width, qoi=qoi, **options)


def variance(
    problem: ContactProblem,
    *,
    tol: float | Sequence[float] | Mapping[str, float] | np.ndarray,
    theta: float = 0.5,
    n_initial: int = 32,
    min_finest_level: int | None = None,
    max_cost: float | None = None,
    batch_size: int | None = 10,
    max_samples: int | None = MAX_PLANNED_SAMPLES,
    executor: BatchExecutor | None = None,
    progress: ProgressReporter | None = None,
) -> TargetEstimate:
    """Adaptive MLMC estimate of ``Var(Q)`` of every column of a contact problem to RMS tolerance ``tol``.

    Parameters
    ----------
    problem : ContactProblem
    tol : float, sequence of float or mapping of str to float
        Tolerance on the RMS error of the variance, one for all columns or
        one per column (in column order or by column name), in the square of
        each QoI's unit (e.g. percent^2 for the contact area).
    theta : float
        Bias share of ``tol^2``, in (0, 1).
    n_initial, min_finest_level, max_cost, batch_size
        As in :func:`rough_uq.multilevel.targets.adaptive_mlmc`; costs are
        modelled reference seconds. ``n_initial`` is at least 4;
        ``min_finest_level`` defaults to 2, or ``problem.max_level`` if smaller.
    max_samples : int or None
        A plan of more samples in all (default 10^7, as for
        :func:`~rough_uq.problem.runs.mlmc`) raises
        :class:`~rough_uq.errors.EstimationError` before its samples are
        drawn: the tolerance is out of reach. None: no limit.
    executor : BatchExecutor, optional
        Where samples are computed; default in this process.
    progress : ProgressReporter, optional
        Told of the run's start, plan, every sample done and its end, e.g.
        :class:`rough_uq.study.progress.PlainProgress` (a line per level every
        10 s, for a notebook or a log) or ``RichProgress`` (bars on a
        terminal); default: silent.

    Returns
    -------
    TargetEstimate
        ``estimate``, ``stat_error``, ``bias``, ``rmse`` of shape ``(n_qoi,)``
        (the variances, in the QoIs' units squared); ``levels`` and
        ``n_samples`` of shape ``(n_levels,)``.
    """
    problem = checked_problem(problem)
    tol = checked_tolerances(tol, problem.n_qoi, problem.columns)
    stage = run_stage("mlmc", run_id("variance", problem.columns, tol, theta))
    sampler = problem.sampler(stage, executor=executor, progress=progress, plans_asked=True,
                              least_level=initial_finest_level(problem.max_level))
    with reporting_progress(sampler, f"variance {tol_text(problem.columns, tol)}"):
        result = estimate_target(
            sampler, target="variance", tol=tol, max_level=problem.max_level, theta=theta, n_initial=n_initial,
            min_finest_level=min_finest_level, max_cost=max_cost, batch_size=batch_size, max_samples=max_samples,
            qoi_names=problem.columns,
        )
    result = dataclasses.replace(result, n_not_converged=warn_not_converged(sampler, "variance"),
                                 qoi_names=problem.columns, units=tuple(f"{unit}^2" for unit in problem.column_units))
    warn_not_met("variance", problem.columns, result, tol)
    return result


def _warn_negative_variance(result: TargetEstimate, names: Sequence[str] | None) -> None:
    """An :class:`~rough_uq.errors.EstimationWarning` for each variance estimated below zero.

    The multilevel estimator is unbiased, not positive: with few samples a
    small variance can come out negative, within its error. It is returned
    as estimated (clipping it would bias it); the warning says so (a study
    run stores it with its diagnostics, which the report shows), naming the
    column by its name in ``names``, else by its index.
    """
    for column, (value, rmse) in enumerate(zip(result.estimate, result.rmse)):
        if value < 0:
            warn_at_caller(
                EstimationWarning(
                    f"variance of {qoi_text(np.array([column]), names)}: the estimate {value:.3g} is negative "
                    f"(RMSE {rmse:.3g}); the unbiased multilevel estimator can be, with few samples: a tighter tol "
                    "takes more"
                ),
            )


@dataclass(frozen=True, eq=False)
class DistributionResult:
    """What :func:`distribution` estimated for one column.

    Attributes
    ----------
    column : str
        The QoI column (e.g. ``"contact_area"``).
    cdf : CdfEstimate
        ``thresholds`` and the monotone ``cdf`` (shape ``(n_thresholds,)``),
        its sup-norm ``rmse`` and the levels and samples used.
    n_not_converged : int
        Samples with a solve that did not converge, kept with the QoIs of their last iterate (also warned).
    """

    column: str
    cdf: CdfEstimate
    n_not_converged: int = 0

    def quantiles(self, probabilities: Sequence[float] = DEFAULT_PROBABILITIES) -> Quantiles:
        """Quantiles at ``probabilities`` (default 5 %, 50 %, 95 %) with error bars, in the column's unit.

        Raises
        ------
        InvalidParameterError
            If ``probabilities`` is not a number or a non-empty 1-d sequence of
            distinct numbers strictly between 0 and 1 (strings and booleans are refused, not
            converted), naming ``probabilities``.
        EstimationError
            If the estimated CDF does not cross a probability inside the
            thresholds (the message names it; the CDF itself stays usable).
        """
        return quantiles(self.cdf, probabilities=probabilities)


def _column_index(problem: ContactProblem, column: str | None) -> int:
    """The index of ``column`` (``QOI@LOAD`` with the load written any way, :func:`column_of_load`); None names
    the one column of a problem that has one (with several it picked the first, where ``--qoi`` is required)."""
    columns = problem.columns
    if column is None and len(columns) > 1:
        raise InvalidParameterError("column", None, f"one of {', '.join(columns)}",
                                    text=f"column: this problem has several columns; name one of {', '.join(columns)}")
    if column is None:
        return 0
    name = column_of_load(column, columns) if isinstance(column, str) else column
    if not is_one_of(name, columns):
        raise InvalidParameterError("column", column, f"one of {', '.join(columns)}")
    return columns.index(name)


def _default_bandwidth(thresholds: np.ndarray) -> float:
    """Twice the mean spacing of the thresholds: the level-0 smoothing width when none is given."""
    if thresholds.ndim != 1 or thresholds.size < 2:
        raise InvalidParameterError("thresholds", thresholds, "at least two increasing values")
    return 2.0 * float(thresholds[-1] - thresholds[0]) / (thresholds.size - 1)


def distribution(
    problem: ContactProblem,
    *,
    tol: float,
    thresholds: Sequence[float] | np.ndarray,
    column: str | None = None,
    bandwidth: float | None = None,
    theta: float = 0.5,
    n_initial: int = 32,
    min_finest_level: int | None = None,
    max_cost: float | None = None,
    batch_size: int | None = 10,
    max_samples: int | None = MAX_PLANNED_SAMPLES,
    executor: BatchExecutor | None = None,
    progress: ProgressReporter | None = None,
) -> DistributionResult:
    """Adaptive MLMC estimate of the distribution function ``F(s) = P(Q <= s)`` and quantiles of one column.

    Parameters
    ----------
    problem : ContactProblem
    tol : float
        Tolerance on the largest RMS error of ``F`` over the thresholds (dimensionless, in (0, 1)).
    thresholds : sequence of float
        Strictly increasing values ``s_j`` in the column's unit; they must
        bracket the quantiles asked for, with a spacing well below the
        quantiles' error bars (:mod:`rough_uq.multilevel.distribution`).
        Thresholds that miss the samples of a level (every value of the
        level a bandwidth or more on one side of each threshold, e.g. all
        thresholds below the smallest contact area) leave its variance
        unmeasured: the run then warns and does not meet ``tol``.
    column : str, optional
        Column of ``problem.columns`` (a load curve's ``QOI@LOAD`` may write the load any way: ``@5`` is
        ``@5.0``); required where the problem has several columns.
    bandwidth : float, optional
        Smoothing width on level 0, halved per level (the column's unit);
        default twice the mean threshold spacing.
    theta, n_initial, min_finest_level, max_cost, batch_size, max_samples, executor, progress
        As for :func:`variance`.

    Returns
    -------
    DistributionResult
        ``cdf`` and, by :meth:`DistributionResult.quantiles`, the quantiles.

    Warns
    -----
    EstimationWarning
        Where the thresholds miss the samples of a level, naming the
        thresholds and the range of the level's values; ``cdf.tol_met`` is
        then False, ``cdf.stop_reason`` ``"thresholds_miss_samples"`` and
        ``cdf.missed_levels`` lists the levels. Where the finest bandwidth
        exceeds twice the spread of the values (a bandwidth, or thresholds,
        far coarser than the values vary): ``cdf.stop_reason``
        ``"bandwidth_too_wide"``, the bias not estimated, ``tol_met`` False
        (:mod:`rough_uq.multilevel.distribution`).
    """
    problem = checked_problem(problem)
    index = _column_index(problem, column)
    tol_array = np.array([check_cdf_tol(tol)])
    name = problem.columns[index]
    stage = run_stage("mlmc", run_id("cdf", [name], tol_array, theta))
    sampler = problem.sampler(stage, executor=executor, progress=progress, plans_asked=True,
                              least_level=initial_finest_level(problem.max_level))
    with reporting_progress(sampler, f"cdf {tol_text([name], tol_array)}"):
        estimate = estimate_target(
            sampler, target="cdf", tol=tol_array, max_level=problem.max_level, thresholds=thresholds, qoi=index,
            bandwidth=bandwidth, theta=theta, n_initial=n_initial, min_finest_level=min_finest_level,
            max_cost=max_cost, batch_size=batch_size, max_samples=max_samples, qoi_names=problem.columns,
        )
    n_not_converged = warn_not_converged(sampler, "distribution")
    warn_not_met(f"distribution of {name}", None, estimate, tol_array)
    return DistributionResult(column=name, cdf=estimate, n_not_converged=n_not_converged)

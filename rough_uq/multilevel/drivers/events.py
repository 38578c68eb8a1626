"""The events a driver yields, and the outcome of a run (:class:`EstimationResult`).

"The module docstring" below is the package's, :mod:`rough_uq.multilevel.drivers`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rough_uq.multilevel.rates import DroppedLevel, Rates
from rough_uq.multilevel.statistics import (
    ESTIMATE_DIGITS, LevelStatistics, errors_summary, names_summary, units_summary, values_summary,
)


@dataclass(frozen=True, eq=False)
class PlanUpdated:
    """The plan changed: a new level, new ``N_l``, or the initial plan.

    Attributes
    ----------
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy.
    n_planned, n_done : ndarray of int, shape (n_levels,)
        Samples planned and drawn so far, per level.
    reason : str
        ``"initial"``, ``"variance"`` (re-estimated ``V_l``/``C_l``) or
        ``"new level"``.
    """

    levels: np.ndarray
    n_planned: np.ndarray
    n_done: np.ndarray
    reason: str


@dataclass(frozen=True, eq=False)
class RichardsonRefused:
    """Richardson extrapolation was refused; the run continues as plain MLMC.

    Attributes
    ----------
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy when it was refused.
    reason : str
        Which check failed (:func:`~rough_uq.multilevel.richardson.ratio_instability`).
    """

    levels: np.ndarray
    reason: str


@dataclass(frozen=True, eq=False)
class BatchDone:
    """One batch of samples was drawn.

    Attributes
    ----------
    level : int
        Level of the batch.
    indices : ndarray of int64, shape (n,)
        Sample indices (contiguous, continuing the previous batch of the level).
    fine, coarse : ndarray, shape (n, n_qoi)
        QoIs returned by the sampler (always 2-d here).
    cost : ndarray, shape (n,)
        Per-sample cost returned by the sampler.
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy.
    n_done, n_planned : ndarray of int, shape (n_levels,)
        Progress per level after this batch.
    """

    level: int
    indices: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray
    cost: np.ndarray
    levels: np.ndarray
    n_done: np.ndarray
    n_planned: np.ndarray


@dataclass(frozen=True, eq=False)
class EstimationResult:
    """Outcome of an MC or MLMC run.

    Per-QoI fields are floats when the sampler returned 1-d arrays (one QoI)
    and arrays of shape (n_qoi,) otherwise (``rough_uq.mlmc`` / ``rough_uq.mc``
    on a contact problem always give arrays).

    Attributes
    ----------
    method : str
        ``"mlmc"`` or ``"mc"``.
    estimate : float or ndarray
        Estimate of ``E[Q]``.
    stat_error : float or ndarray
        Statistical (standard) error, ``sqrt(sum_l V_l / N_l)``, with ``V_l`` pooled from the run's samples and
        the screening's where the screening sampled level ``l`` (so for MC not always ``sqrt(variance / N)``).
    bias_estimate : float or ndarray
        Estimated bias: the remaining bias of the finest level (MLMC), the
        ``bias`` given to :func:`~rough_uq.multilevel.drivers.plain_mc.mc`, or 0 if unknown (``is_bias_estimated``).
    variance : float or ndarray
        Estimate of ``Var(Q)`` from the run's own samples: for MLMC the telescoped sum of the levels' terms
        (unbiased, but not bounded below: with few samples per level it can be negative), for MC the sample
        variance. :func:`rough_uq.variance` estimates ``Var(Q)`` to a tolerance.
    variance_error : float or ndarray
        Standard error of ``variance``.
    n_samples : ndarray of int, shape (n_levels,)
        ``N_l`` drawn.
    levels : ndarray of int, shape (n_levels,)
        Levels used (``[level]`` for MC).
    cost : float
        Total cost of the samples (sum of the sampler's costs).
    mc_cost : float
        Predicted cost of plain MC for the same tolerance (fine solves only),
        on the level the bias model needs for ``tol``
        (:func:`~rough_uq.multilevel.allocation.mc_run_cost`): for MLMC the
        run's own statistics and rates (:func:`rough_uq.mlmc` with a screening:
        the screening's, as ``roughuq mlmc`` reports it); for :func:`~rough_uq.multilevel.drivers.plain_mc.mc`, the
        cost its own estimates predict.
    statistics : LevelStatistics
        Per-level statistics (for MC: of ``Q`` alone, coarse values ignored).
    rates : Rates or None
        Rates the MLMC driver used last (None for MC): the given ``rates``, or
        fitted on the run's levels ``>= 1`` and floored at 0.5; a rate that could
        not be fitted keeps the screening value or the floor (empty ``levels_*``).
    tol : ndarray, shape (n_qoi,)
        Tolerance per QoI.
    theta : float
        Bias share of ``eps^2``.
    tol_met : bool
        ``stat_error^2 + bias_estimate^2 <= tol^2`` for every QoI, with an
        estimated bias (MC without a ``bias``: the statistical error alone,
        ``stat_error <= sqrt(1 - theta) tol``, the share it plans for);
        False for MC stopped by ``max_cost`` before it drew the samples it
        starts with (``n_initial``, 2 from a screening).
    stop_reason : str
        ``"tol_met"``, ``"max_cost"``, ``"max_level"`` (MLMC: the bias test
        asked for a level beyond ``max_level``; ``tol_met`` may still be True
        where the bias then estimated on ``max_level`` and the statistical
        error together meet ``tol``, since the bias test checks the stricter
        share ``sqrt(theta) tol``) or ``"bias"`` (MC: the statistical target
        is met but the given bias is too large).
    is_bias_estimated : bool
        False for MC without a ``bias`` (``bias_estimate`` is then 0 and
        ``tol_met`` concerns the statistical error only, within its share), and for MLMC
        stopped by ``max_cost`` before the levels its bias test needs were
        sampled (module docstring, step 4: ``bias_estimate`` 0, ``tol_met``
        False).
    richardson : str
        ``"off"`` (not asked for), ``"applied"`` (``estimate``, ``stat_error``
        and ``bias_estimate`` are those of the extrapolated estimate) or
        ``"refused"`` (plain MLMC; ``richardson_reason`` says why).
    richardson_reason : str
        Why the extrapolation was refused ("" otherwise).
    dropped_levels : tuple of DroppedLevel
        MLMC: coarse levels left out (``levels`` then starts above 0) and why.
    qoi_names : tuple of str or None
        Names of the QoI columns of the per-QoI fields, in order (the run's
        ``qoi_names``; a contact problem's columns), None if not given.
    n_not_converged : int
        Samples of the run with a solve that did not converge, kept with the
        QoIs of their last iterate (:func:`rough_uq.mlmc` and :func:`rough_uq.mc`
        count them and warn; 0 from a level sampler, which has no solves).
    units : tuple of str or None
        Unit of each QoI column (:func:`rough_uq.mlmc` and :func:`rough_uq.mc`: the problem's
        ``column_units``, e.g. ``"percent"``), None if not known (a level sampler's run).
    """

    method: str
    estimate: float | np.ndarray
    stat_error: float | np.ndarray
    bias_estimate: float | np.ndarray
    variance: float | np.ndarray
    variance_error: float | np.ndarray
    n_samples: np.ndarray
    levels: np.ndarray
    cost: float
    mc_cost: float
    statistics: LevelStatistics = field(repr=False)  # long arrays: printing a result shows the estimate
    rates: Rates | None = field(repr=False)
    tol: np.ndarray
    theta: float
    tol_met: bool
    stop_reason: str
    is_bias_estimated: bool
    richardson: str = "off"
    richardson_reason: str = ""
    dropped_levels: tuple[DroppedLevel, ...] = ()
    qoi_names: tuple[str, ...] | None = None
    n_not_converged: int = 0
    units: tuple[str, ...] | None = None

    def __repr__(self) -> str:
        # One line for notebooks and print(), with the RMSE (a property the dataclass repr left out); the
        # per-QoI arrays of a load curve's columns (944 characters for 6) summarised as TargetEstimate's are.
        # Without an estimated bias the RMSE is unknown: the repr says so rather than show the statistical error
        # as the RMSE next to tol_met=True (mc on a given level).
        errors = errors_summary(self.rmse, self.stat_error, self.bias_estimate, self.is_bias_estimated,
                                 bias_name="bias_estimate")
        return (
            f"EstimationResult(method={self.method!r}, qoi_names={names_summary(self.qoi_names)}, "
            f"{units_summary(self.units)}estimate={values_summary(self.estimate, ESTIMATE_DIGITS)}, {errors}, "
            f"tol={values_summary(self.tol)}, tol_met={self.tol_met}, "
            f"stop_reason={self.stop_reason!r}, levels={np.asarray(self.levels).tolist()}, "
            f"n_samples={np.asarray(self.n_samples).tolist()}, n_not_converged={self.n_not_converged})"
        )

    @property
    def rmse(self) -> float | np.ndarray:
        """Estimated root-mean-square error ``sqrt(stat_error^2 + bias_estimate^2)``.

        Where the bias is not estimated (``is_bias_estimated`` False, ``bias_estimate`` 0) the statistical error
        alone: a lower bound of the error, not an estimate of it. (``hypot``: no squares that under- or overflow.)
        """
        return np.hypot(self.stat_error, self.bias_estimate)

    @property
    def finest_level(self) -> int:
        """Finest level used."""
        return int(self.levels[-1])


@dataclass(frozen=True, eq=False)
class Finished:
    """The run ended; ``result`` is its :class:`EstimationResult`."""

    result: EstimationResult


Event = PlanUpdated | BatchDone | RichardsonRefused | Finished

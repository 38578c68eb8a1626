"""MLMC sample allocation: the optimal ``N_l`` and the plan for a tolerance (SPEC section 5).

This module turns rate models and a screening table into a plan: the finest
level, the number of samples per level and the predicted costs of MLMC and of
plain MC. It needs only numpy and the standard library and has no state.

Conventions
-----------
Levels ``l = 0, 1, 2, ...``, ``Q_l``, ``Y_l = Q_l - Q_{l-1}``, ``V_l =
Var(Y_l)`` and the cost ``C_l`` of one level-``l`` sample are those of
:mod:`~rough_uq.multilevel.statistics`; the rates ``alpha``, ``beta``,
``gamma``, their models and the remaining bias those of
:mod:`~rough_uq.multilevel.rates`; the Richardson weight ``w`` that of
:mod:`~rough_uq.multilevel.richardson`.

Symbols (SPEC section 5):

``eps``
    Tolerance on the root-mean-square error, ``MSE <= eps^2``.
``theta``
    Bias share of ``eps^2``: the bias must stay below ``sqrt(theta) eps`` and
    the estimator variance below ``(1 - theta) eps^2`` (default 1/2).
``N_l``
    The number of samples of level ``l``.

The plan
--------
:func:`plan` checks its arguments and goes in steps, one function each: the
finest level (``_plan_finest``) is the first whose remaining bias
(``_BiasModel``, as ``bias_from`` says) is within ``sqrt(theta) eps``
(``_finest_level``); with ``richardson`` the extrapolated estimate may need
fewer levels (``_richardson_level``); the base level is given or chosen
(``_plan_base``, :func:`~rough_uq.multilevel.rates.choose_coarsest_level`);
``V_l`` and ``C_l`` come from the explicit arguments, the screening or the
rate models (``_level_inputs``); then the allocation (``_allocate``,
:func:`optimal_samples`) and the prediction for plain MC (``_mc_samples``)
make the :class:`Plan` (``_allocated_plan``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import PLANNED_COUNT_CAP, EstimationError, InvalidParameterError, is_real_number
from rough_uq.multilevel.rates import (
    CoarsestLevel,
    DroppedLevel,
    Rates,
    choose_coarsest_level,
    confirmed_tail,
    estimated_bias,
    remaining_bias,
    tail_rate,
)
from rough_uq.multilevel.richardson import (
    RICHARDSON_MIN_LEVELS,
    ratio_instability,
    richardson_bias,
    richardson_weight,
)
from rough_uq.multilevel.statistics import LevelStatistics, checked_names, readonly_array

__all__ = [
    "Plan",
    "fine_cost_share",
    "mc_run_cost",
    "optimal_samples",
    "plan",
    "reachable_tolerance",
]
# Also imported by the drivers and targets and by rough_uq.problem.runs, not part of the API: check_tol,
# check_fraction.

_MAX_COUNT = float(PLANNED_COUNT_CAP)


def optimal_samples(variances: np.ndarray, costs: np.ndarray, budget: np.ndarray) -> np.ndarray:
    """Real-valued optimal ``N_l`` per QoI for a variance budget.

    ``N_l = sqrt(V_l / C_l) * sum_k sqrt(V_k C_k) / budget`` (SPEC section 5
    with ``budget = (1 - theta) eps^2``).

    Parameters
    ----------
    variances : ndarray, shape (n_levels, n_qoi)
        ``V_l`` (>= 0).
    costs : ndarray, shape (n_levels,)
        ``C_l`` (> 0).
    budget : ndarray, shape (n_qoi,)
        Allowed estimator variance per QoI (> 0).

    Returns
    -------
    ndarray, shape (n_levels, n_qoi)
    """
    if np.any(~(np.asarray(costs) > 0)):
        # C_l = 0 would divide by zero in sqrt(V_l / C_l).
        raise InvalidParameterError("costs", costs, "positive costs C_l")
    costs = costs[:, None]
    total = np.sum(np.sqrt(variances * costs), axis=0)
    return np.minimum(np.sqrt(variances / costs) * total / budget, _MAX_COUNT)


@dataclass(frozen=True, eq=False)
class Plan:
    """Finest level, optimal sample numbers and predicted costs for a tolerance.

    Attributes
    ----------
    tol : ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error, per QoI.
    theta : float
        Bias share of ``eps^2``.
    finest_level : int
        ``L``; the plan covers levels ``0..L``.
    n_samples : ndarray of int, shape (L+1,)
        ``N_l`` (maximum over the QoIs; at least 1).
    variances : ndarray, shape (L+1, n_qoi)
        ``V_l`` the plan used.
    costs : ndarray, shape (L+1,)
        ``C_l`` the plan used.
    is_extrapolated : ndarray of bool, shape (L+1,)
        True where ``V_l`` or ``C_l`` came from the rate models.
    bias : ndarray, shape (n_qoi,)
        Predicted remaining bias on level ``L``; where the levels a run samples
        beyond ``L`` miss the bias (:func:`~rough_uq.multilevel.drivers.adaptive.with_run_bias`),
        the bias ``max_level`` predicts.
    is_bias_met : bool
        Whether ``bias <= sqrt(theta) eps`` for every QoI (False when
        ``max_level`` capped the finest level, or where the levels a run
        samples miss the bias: ``with_run_bias``).
    stat_variance : ndarray, shape (n_qoi,)
        Predicted estimator variance ``sum_l V_l / N_l``.
    cost : float
        Predicted MLMC cost ``sum_l N_l C_l``.
    mc_n_samples : int
        Samples plain MC on level ``L`` needs: ``(1-theta)^-1 eps^-2 Var(Q_L)``.
    mc_cost : float
        Predicted cost of plain MC, ``mc_n_samples`` times the cost of one fine
        solve on level ``L``.
    is_richardson : bool
        The plan is for the Richardson-extrapolated estimate (``richardson=True``
        and it needs fewer levels than plain MLMC): ``bias`` is its remaining
        bias, ``n_samples`` and ``stat_variance`` weight ``V_L`` by ``w^2``.
    richardson_note : str
        Why a requested extrapolation was not planned ("" otherwise), naming the QoI by :func:`plan`'s
        ``qoi_names`` where given.
    coarsest_level : int
        ``b``, the level the hierarchy starts on (its ``V_b`` is ``Var(Q_b)``;
        ``n_samples`` and ``variances`` are 0 below it).
    dropped_levels : tuple of DroppedLevel
        The levels below ``b`` and why they were dropped.
    """

    tol: np.ndarray
    theta: float
    finest_level: int
    n_samples: np.ndarray
    variances: np.ndarray
    costs: np.ndarray
    is_extrapolated: np.ndarray
    bias: np.ndarray
    is_bias_met: bool
    stat_variance: np.ndarray
    cost: float
    mc_n_samples: int
    mc_cost: float
    is_richardson: bool = False
    richardson_note: str = ""
    coarsest_level: int = 0
    dropped_levels: tuple[DroppedLevel, ...] = ()

    @property
    def levels(self) -> np.ndarray:
        """Level indices ``0..L``."""
        return np.arange(self.finest_level + 1)

    @property
    def work_ratio(self) -> float:
        """Predicted cost of plain MC over that of MLMC."""
        return self.mc_cost / self.cost if self.cost > 0 else math.inf


def mc_run_cost(prediction: Plan) -> float:
    """Modelled cost of the plain MC run a plan predicts: ``mc_n_samples`` fine solves on its level, at least 2.

    (A run needs two samples for a variance.) What ``roughuq mc --tol`` forecasts and what an MLMC run's
    ``mc_cost`` compares with.
    """
    return max(prediction.mc_n_samples, 2) * prediction.mc_cost / max(prediction.mc_n_samples, 1)


def reachable_tolerance(prediction: Plan, tol: np.ndarray | None = None) -> np.ndarray:
    """The smallest tolerance per QoI whose bias share ``sqrt(theta) eps`` the plan's predicted bias meets, rounded
    up to two significant digits (a tolerance the refusals of an unreachable one can propose).

    Shape ``(n_qoi,)``. With ``tol``, the tolerance asked stands where its share already covers the bias: only
    the columns that block are raised (the refusal proposed every column's bias floor, and a mean gap asked at
    2.2e-06 came back as 7.8e-09, a plan of 2.8e7 samples). Where the predicted bias is 0 (e.g. the contact area
    of a load curve's full-contact column) every tolerance is reachable and there is no smallest: the requested
    ``tol`` stands there too; 0 without ``tol``.
    """
    bias = np.asarray(prediction.bias, dtype=float) / math.sqrt(prediction.theta)
    if tol is None:
        return np.array([_round_up(float(value)) for value in bias])
    asked = np.broadcast_to(np.asarray(tol, dtype=float), bias.shape)
    blocked = unreachable_columns(prediction, asked)
    return np.array([_round_up(float(value)) if block else float(wanted)
                     for value, wanted, block in zip(bias, asked, blocked)])


def unreachable_columns(prediction: Plan, tol: np.ndarray) -> np.ndarray:
    """Where the plan's predicted bias exceeds the bias share ``sqrt(theta) tol``: the columns that make ``tol``
    unreachable (shape ``(n_qoi,)``, bool)."""
    bias = np.asarray(prediction.bias, dtype=float)
    return bias > math.sqrt(prediction.theta) * np.broadcast_to(np.asarray(tol, dtype=float), bias.shape)


def _round_up(value: float) -> float:
    """``value`` rounded up to two significant digits."""
    if not (math.isfinite(value) and value > 0):
        return value
    scale = 10.0 ** (math.floor(math.log10(value)) - 1)
    return math.ceil(value / scale * (1 - 1e-12)) * scale


def check_fraction(name: str, value: object) -> float:
    if not (is_real_number(value) and 0.0 < value < 1.0):
        raise InvalidParameterError(name, value, "a number strictly between 0 and 1")
    return float(value)


#: The smallest tolerance a run takes. Errors are compared with ``tol`` in squares, and the error of a variance
#: (of a fourth moment) in squares of squared (fourth-power) values: with a variance of some 1e-160 a variance
#: run reported an RMS error of exactly 0 and its tolerance met, with one of 1e-200 it failed with a bare
#: ``ValueError`` (NaN sample counts). Down to this tolerance the squares are normal floats with a margin.
MIN_TOL = 1e-140

#: The largest tolerance a run takes: the squares of larger ones overflowed (``--tol 1e300`` printed numpy's
#: "overflow encountered in square" and a plain MC cost of 0).
MAX_TOL = 1e140

#: What :func:`check_tol` allows, in words (for the messages of the layers that check tolerances first).
TOL_RANGE_TEXT = (f"in [{MIN_TOL:g}, {MAX_TOL:g}] (errors are compared in squares, which underflow or overflow "
                  "beyond; express the QoI in another unit)")


def check_tol(tol: object, n_qoi: int | None) -> np.ndarray:
    """Tolerance as a positive array of shape (n_qoi,) (a scalar is broadcast), each in [``MIN_TOL``, ``MAX_TOL``]."""
    array = np.atleast_1d(np.asarray(tol, dtype=float))
    if array.ndim != 1 or not np.all(np.isfinite(array)) or np.any(array <= 0):
        raise InvalidParameterError("tol", tol, "a positive number or a 1-d array of positive numbers")
    if np.any((array < MIN_TOL) | (array > MAX_TOL)):
        raise InvalidParameterError("tol", tol, f"tolerances {TOL_RANGE_TEXT}")
    if n_qoi is not None:
        if array.size == 1:
            array = np.repeat(array, n_qoi)
        elif array.size != n_qoi:
            raise InvalidParameterError("tol", tol, f"a scalar or {n_qoi} values (one per QoI)")
    return array


def fine_cost_share(gamma: float, level: int) -> float:
    """Fraction of a level-``level`` sample's cost spent on the fine solve.

    A sample on ``l >= 1`` solves on ``h_l`` and ``h_{l-1}``; under the cost
    model the coarse solve costs ``2^-gamma`` of the fine one, so plain MC
    (fine solve only) pays ``1 / (1 + 2^-gamma)`` of ``C_l``.
    """
    return 1.0 if level == 0 else 1.0 / (1.0 + 2.0 ** (-gamma))


def plan(
    *,
    tol: float | np.ndarray,
    rates: Rates,
    statistics: LevelStatistics | None = None,
    variances: np.ndarray | None = None,
    costs: np.ndarray | None = None,
    theta: float = 0.5,
    finest_level: int | None = None,
    max_level: int | None = None,
    bias_from: str = "both",
    richardson: bool = False,
    coarsest_level: int | None = 0,
    qoi_names: Sequence[str] | None = None,
) -> Plan:
    """Finest level and optimal ``N_l`` for a tolerance (SPEC section 5).

    Parameters
    ----------
    tol : float or ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error (one per QoI, or one for all).
    rates : Rates
        Rate models, used for the bias and to extrapolate ``V_l``, ``C_l``
        beyond the data.
    statistics : LevelStatistics, optional
        Screening table; ``V_l``, ``C_l`` of screened levels (with two or more
        samples) come from it, and ``Var(Q_L)`` for the MC prediction.
    variances : ndarray, shape (n_levels,) or (n_levels, n_qoi), optional
        Explicit ``V_0, V_1, ...`` (override ``statistics``).
    costs : ndarray, shape (n_levels,), optional
        Explicit ``C_0, C_1, ...`` (override ``statistics``).
    theta : float
        Bias share of ``eps^2``, in (0, 1).
    finest_level : int, optional
        Use this ``L`` instead of choosing it from the bias.
    max_level : int, optional
        Largest admissible ``L``; if the bias needs a finer level, the plan
        stops there with ``is_bias_met = False``.
    bias_from : {"both", "model", "data"}
        ``|E[Y_L]|`` from the largest of the fitted model ``c_alpha
        2^(-alpha L)`` and the screened means of levels ``L``, ``L - 1`` and
        ``L - 2`` (levels ``>= 1``, scaled to level ``L``) where screened
        (default, :func:`~rough_uq.multilevel.rates.estimated_bias`), from the
        model alone, or from the screened mean of level ``L`` where available
        (the model elsewhere).
    richardson : bool
        Plan the Richardson-extrapolated estimate
        (:mod:`~rough_uq.multilevel.richardson`) if the screened means allow
        it and it needs fewer levels than plain MLMC; otherwise plan plain
        MLMC and say why in ``richardson_note``.
    coarsest_level : int or None
        Level the hierarchy starts on (default 0); None chooses it with
        :func:`~rough_uq.multilevel.rates.choose_coarsest_level` from
        ``statistics`` (0 without). It is capped at the finest level.
    qoi_names : sequence of str, optional
        Names of the QoI columns, length ``n_qoi``: ``richardson_note`` names
        the QoI whose screened means refused the extrapolation
        (``(contact_area)``); without them it gives its column index
        (``(QoI 0)``), and nothing for a single QoI.

    Returns
    -------
    Plan

    Notes
    -----
    ``L`` is the smallest level whose remaining bias
    ``|E[Y_L]| / (2^alpha - 1)`` is at most ``sqrt(theta) eps``, maximised
    over the QoIs (``|E[Y_L]|`` as ``bias_from`` says). ``N_l =
    ceil((1-theta)^-1 eps^-2 sqrt(V_l/C_l) sum_k sqrt(V_k C_k))``, maximised
    over the QoIs, at least 1. Plain MC needs
    ``(1-theta)^-1 eps^-2 Var(Q_L)`` samples of cost ``C_L / (1 + 2^-gamma)``
    (the fine solve only, see :func:`fine_cost_share`); ``Var(Q_L)`` comes
    from the screening at ``L`` or, beyond it, from the finest screened level
    (``Var(Q_l)`` converges), or is ``V_0 = Var(Q_0)`` without screening.
    """
    theta = check_fraction("theta", theta)
    if bias_from not in ("both", "model", "data"):
        raise InvalidParameterError("bias_from", bias_from, '"both", "model" or "data"')
    if statistics is not None and statistics.n_qoi != rates.n_qoi:
        raise EstimationError(f"rates have {rates.n_qoi} QoIs, the statistics {statistics.n_qoi}")
    tol = check_tol(tol, rates.n_qoi)
    names = checked_names(qoi_names, rates.n_qoi, argument="qoi_names")
    variances = _explicit_variances(variances, rates.n_qoi)
    costs = _explicit_costs(costs)
    bias_model = _BiasModel(rates=rates, statistics=statistics, bias_from=bias_from)
    finest = _plan_finest(
        bias_model, math.sqrt(theta) * tol, finest_level=finest_level, max_level=max_level, richardson=richardson,
        names=names,
    )
    base, dropped = _plan_base(statistics, coarsest_level, finest.level)
    inputs = _level_inputs(
        statistics=statistics, rates=rates, variances=variances, costs=costs, finest_level=finest.level, base=base
    )
    return _allocated_plan(
        finest, inputs, base=base, dropped=dropped, tol=tol, theta=theta, rates=rates, statistics=statistics
    )


def _explicit_variances(variances: np.ndarray | None, n_qoi: int) -> np.ndarray | None:
    """``variances`` given to :func:`plan` as shape (n_levels, n_qoi), checked."""
    if variances is None:
        return None
    variances = np.asarray(variances, dtype=float)
    variances = variances[:, None] if variances.ndim == 1 else variances
    if variances.ndim != 2 or variances.shape[1] != n_qoi or np.any(variances < 0):
        raise InvalidParameterError("variances", variances, f"non-negative values of shape (n_levels, {n_qoi})")
    return variances


def _explicit_costs(costs: np.ndarray | None) -> np.ndarray | None:
    """``costs`` given to :func:`plan`, checked."""
    if costs is None:
        return None
    costs = np.asarray(costs, dtype=float)
    if costs.ndim != 1 or np.any(costs <= 0):
        raise InvalidParameterError("costs", costs, "positive values of shape (n_levels,)")
    return costs


def _screened_row(statistics: LevelStatistics | None, level: int) -> int | None:
    """Row of ``level`` in the screening if it was screened with two or more samples, else None."""
    if statistics is None:
        return None
    row = statistics.index(level)
    return row if row is not None and statistics.n_samples[row] >= 2 else None


@dataclass(frozen=True, eq=False)
class _BiasModel:
    """The remaining bias :func:`plan` predicts for a finest level (``bias_from``: see :func:`plan`)."""

    rates: Rates
    statistics: LevelStatistics | None
    bias_from: str

    def at(self, level: int) -> np.ndarray:
        """Remaining bias, shape (n_qoi,), of an estimator whose finest level is ``level``.

        Below screened levels (``bias_from="both"``) at least what they measured (:meth:`_through_finer`).
        """
        own = self._own(level)
        through_finer = self._through_finer(level)
        return own if through_finer is None else np.fmax(own, through_finer)

    def _through_finer(self, level: int) -> np.ndarray | None:
        """``|sum_{l=level+1..top} E[Y_l]| + bias(top)``: the bias of ``level`` as the screened levels above it
        measure it, ``top`` the finest of the consecutive screened levels above ``level`` (None if there is none).

        Without it a level below the screened ones had only its own rate to go by, and a rate fitted as a line
        through two means of opposite sign (alpha 1.33 where those means confirm 0.61) gave 64^2 a bias of 0.198
        where 128^2, one level finer, had 0.372: plain MC claimed a tolerance on 64^2 that MLMC refused on 256^2.
        For means that decay geometrically at the fitted rate both are the same sum.
        """
        if self.statistics is None or self.bias_from != "both":
            return None
        rows = []
        while (row := _screened_row(self.statistics, level + len(rows) + 1)) is not None:
            rows.append(row)
        if not rows:
            return None
        measured = np.abs(np.sum(self.statistics.mean_diff[rows], axis=0))
        return measured + self._own(level + len(rows))

    def _own(self, level: int) -> np.ndarray:
        """The remaining bias of ``level`` from its own mean, the two below it and the rates."""
        row = _screened_row(self.statistics, level) if level >= 1 else None
        if self.bias_from == "data" and row is not None:
            return remaining_bias(self.statistics.mean_diff[row], tail_rate(self.rates.alpha))
        if self.bias_from != "both":
            return estimated_bias(rates=self.rates, level=level)
        measured = error = None
        if row is not None:
            measured, error = self.statistics.mean_diff[row], self.statistics.mean_diff_error[row]
        bias = estimated_bias(rates=self.rates, level=level, mean_diff=measured, coarser=self._coarser(level),
                              mean_error=error)
        finest = self._finest_pair()
        if row is not None or finest is None or level <= finest:
            return bias
        # Beyond the screened levels, as the run will sum it: from the finest screened level at the tail rate its
        # two finest means confirm, where that bound binds (the fitted alpha promised tolerances the runs missed).
        alpha, binding = confirmed_tail(self.rates, *self._pair_inputs(finest))
        return np.where(binding, np.fmax(bias, self._own(finest) * 2.0 ** (-alpha * (level - finest))), bias)

    def _finest_pair(self) -> int | None:
        """The finest screened level whose level below is screened too, both differences (None if none is)."""
        if self.statistics is None or self.bias_from != "both":
            return None
        levels = [int(level) for level in self.statistics.levels if level >= 2]
        pairs = [level for level in levels if _screened_row(self.statistics, level - 1) is not None]
        return pairs[-1] if pairs else None

    def _pair_inputs(self, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Means of levels ``level - 1`` and ``level`` and the standard error of the second (screened rows)."""
        row, below = _screened_row(self.statistics, level), _screened_row(self.statistics, level - 1)
        return self.statistics.mean_diff[below], self.statistics.mean_diff[row], self.statistics.mean_diff_error[row]

    def _coarser(self, level: int) -> np.ndarray | None:
        """Screened means of the (up to) two levels ``>= 1`` below ``level``, NaN where not screened."""
        below = range(max(level - 2, 1), level)
        if self.statistics is None or not below:
            return None
        rows = [_screened_row(self.statistics, lower) for lower in below]
        nan = np.full(self.statistics.n_qoi, np.nan)
        return np.array([nan if row is None else self.statistics.mean_diff[row] for row in rows])


def _finest_level(bias_model: _BiasModel, bias_limit: np.ndarray, max_level: int | None) -> int:
    """The smallest level whose remaining bias is within ``bias_limit`` (``max_level`` if none is)."""
    rates, statistics = bias_model.rates, bias_model.statistics
    if np.any(rates.alpha <= 0):
        remaining_bias(rates.c_alpha, rates.alpha)  # raises the explanatory error
    # Beyond the data the model bias halves every 1/alpha levels, so this cap is never binding
    # for sane inputs; it only keeps a runaway search finite.
    top = (0 if statistics is None else int(statistics.levels[-1])) + 200
    cap = top if max_level is None else int(max_level)
    for level in range(cap + 1):
        if np.all(bias_model.at(level) <= bias_limit):
            return level
    return cap


@dataclass(frozen=True, eq=False)
class _FinestLevel:
    """The finest level :func:`plan` chose, its remaining bias (shape (n_qoi,)) and how it was chosen."""

    level: int
    bias: np.ndarray
    is_bias_met: bool
    is_richardson: bool = False
    richardson_note: str = ""


def _plan_finest(
    bias_model: _BiasModel,
    bias_limit: np.ndarray,
    *,
    finest_level: int | None,
    max_level: int | None,
    richardson: bool,
    names: Sequence[str] | None = None,
) -> _FinestLevel:
    """The finest level of :func:`plan`: given or the first to meet the bias, fewer if the extrapolation allows."""
    if finest_level is None:
        finest_level = _finest_level(bias_model, bias_limit, max_level)
    finest_level = int(finest_level)
    if finest_level < 0:
        raise InvalidParameterError("finest_level", finest_level, "a non-negative integer")
    bias = bias_model.at(finest_level)
    is_plain_met = bool(np.all(bias <= bias_limit))
    if not richardson:
        return _FinestLevel(level=finest_level, bias=bias, is_bias_met=is_plain_met)
    extrapolated = _richardson_level(bias_model.statistics, bias_model.rates, bias_limit, finest_level, is_plain_met,
                                     names=names)
    if isinstance(extrapolated, str):
        return _FinestLevel(level=finest_level, bias=bias, is_bias_met=is_plain_met, richardson_note=extrapolated)
    level, bias = extrapolated
    return _FinestLevel(level=level, bias=bias, is_bias_met=bool(np.all(bias <= bias_limit)), is_richardson=True)


def _plan_base(
    statistics: LevelStatistics | None, coarsest_level: int | None, finest_level: int
) -> tuple[int, tuple[DroppedLevel, ...]]:
    """The level :func:`plan`'s hierarchy starts on, and the dropped levels below it."""
    dropped: tuple[DroppedLevel, ...] = ()
    if coarsest_level is None:
        choice = choose_coarsest_level(statistics) if statistics is not None else CoarsestLevel(0, (), 1.0)
        coarsest_level, dropped = choice.level, choice.dropped
    base = min(int(coarsest_level), finest_level)
    if base < 0 or (base > 0 and _screened_row(statistics, base) is None):
        raise InvalidParameterError("coarsest_level", coarsest_level, "0 or a screened level")
    return base, tuple(d for d in dropped if d.level < base)


@dataclass(frozen=True, eq=False)
class _LevelInputs:
    """``V_l`` (shape (L+1, n_qoi)), ``C_l`` (shape (L+1,)) and where they are extrapolated, for :func:`plan`."""

    variances: np.ndarray
    costs: np.ndarray
    is_extrapolated: np.ndarray


def _level_inputs(
    *,
    statistics: LevelStatistics | None,
    rates: Rates,
    variances: np.ndarray | None,
    costs: np.ndarray | None,
    finest_level: int,
    base: int,
) -> _LevelInputs:
    """``V_l`` and ``C_l`` of levels ``0..L``: given, else screened, else from the rate models."""
    level_variances = np.zeros((finest_level + 1, rates.n_qoi))
    level_costs = np.empty(finest_level + 1)
    is_extrapolated = np.zeros(finest_level + 1, dtype=bool)
    for level in range(finest_level + 1):
        row = _screened_row(statistics, level)
        if level < base:
            pass  # below the base level: no samples, V_l stays 0 (the cost is still filled in)
        elif level == base and base > 0:
            level_variances[level] = statistics.var_fine[row]
        elif variances is not None and level < len(variances):
            level_variances[level] = variances[level]
        elif row is not None:
            level_variances[level] = statistics.var_diff[row]
        else:
            level_variances[level] = rates.variance_model(level)
            is_extrapolated[level] = True
        if costs is not None and level < len(costs):
            level_costs[level] = costs[level]
        elif row is not None and statistics.mean_cost[row] > 0:
            level_costs[level] = statistics.mean_cost[row]
        else:
            level_costs[level] = rates.cost_model(level)
            is_extrapolated[level] = True
    if np.any(level_costs <= 0):
        raise EstimationError(
            f"plan needs positive costs; got C_l = {level_costs.tolist()} (check the rates' c_gamma)"
        )
    return _LevelInputs(variances=level_variances, costs=level_costs, is_extrapolated=is_extrapolated)


def _allocated_plan(
    finest: _FinestLevel,
    inputs: _LevelInputs,
    *,
    base: int,
    dropped: tuple[DroppedLevel, ...],
    tol: np.ndarray,
    theta: float,
    rates: Rates,
    statistics: LevelStatistics | None,
) -> Plan:
    """The :class:`Plan` on levels ``0..finest.level``: ``N_l`` from ``base`` on and the prediction for plain MC."""
    level = finest.level
    budget = (1.0 - theta) * tol**2
    weighted = np.array(inputs.variances)
    if finest.is_richardson:
        weighted[-1] *= richardson_weight(rates.alpha) ** 2
    n_samples, stat_variance = _allocate(weighted, inputs.costs, budget, base)
    mc_n = _mc_samples(statistics, inputs.variances, level, budget)
    mc_cost = mc_n * inputs.costs[level] * fine_cost_share(rates.cost_rate_at(level), level)
    return Plan(
        tol=readonly_array(tol),
        theta=theta,
        finest_level=level,
        n_samples=readonly_array(n_samples),
        variances=readonly_array(inputs.variances),
        costs=readonly_array(inputs.costs),
        is_extrapolated=readonly_array(inputs.is_extrapolated),
        bias=readonly_array(finest.bias),
        is_bias_met=finest.is_bias_met,
        stat_variance=readonly_array(stat_variance),
        cost=float(np.sum(n_samples * inputs.costs)),
        mc_n_samples=mc_n,
        mc_cost=float(mc_cost),
        is_richardson=finest.is_richardson,
        richardson_note=finest.richardson_note,
        coarsest_level=base,
        dropped_levels=dropped,
    )


def _allocate(
    variances: np.ndarray, costs: np.ndarray, budget: np.ndarray, base: int
) -> tuple[np.ndarray, np.ndarray]:
    """``N_l`` (maximum over QoIs, at least 1 from ``base`` on, 0 below) and the predicted ``sum_l V_l / N_l``."""
    n_real = np.zeros_like(variances)
    n_real[base:] = optimal_samples(variances[base:], costs[base:], budget)
    n_samples = np.maximum(np.ceil(np.max(n_real, axis=1)), 1.0).astype(np.int64)
    n_samples[:base] = 0
    return n_samples, np.sum(variances[base:] / n_samples[base:, None], axis=0)


def _mc_samples(
    statistics: LevelStatistics | None, variances: np.ndarray, finest_level: int, budget: np.ndarray
) -> int:
    """Samples plain MC on level ``L`` needs (:func:`plan`, Notes).

    ``Var(Q_L)`` is that of the finest level screened up to ``L``, else ``V_0``.
    """
    var_q = variances[0]
    if statistics is not None:
        rows = [row for row in range(statistics.n_levels) if statistics.levels[row] <= finest_level]
        rows = [row for row in rows if statistics.n_samples[row] >= 2]
        if rows:
            var_q = statistics.var_fine[rows[-1]]
    return int(np.max(np.minimum(np.ceil(var_q / budget), _MAX_COUNT)))


def _richardson_level(
    statistics: LevelStatistics | None,
    rates: Rates,
    bias_limit: np.ndarray,
    plain_level: int,
    is_plain_met: bool,
    *,
    names: Sequence[str] | None = None,
) -> tuple[int, np.ndarray] | str:
    """Finest level and remaining bias of the extrapolated estimate, or why there is none (:func:`plan`).

    The reason names the QoI that refused it by ``names`` where given (:func:`plan`'s ``qoi_names``).
    """
    if statistics is None:
        return "Richardson extrapolation needs screened level means"
    rows = [r for r in range(statistics.n_levels) if statistics.levels[r] >= 1 and statistics.n_samples[r] >= 2]
    levels = [int(statistics.levels[r]) for r in rows]
    if len(rows) < 2 or levels != list(range(1, len(rows) + 1)):
        return f"Richardson extrapolation needs the screened means of levels 1 and 2 at least (has {levels})"
    means = statistics.mean_diff[rows]
    errors = np.sqrt(statistics.var_diff[rows] / statistics.n_samples[rows][:, None])
    reason = ratio_instability(means, errors, levels, min_levels=2, names=names)
    if reason:
        return f"Richardson extrapolation refused: {reason}"
    alpha = rates.alpha
    if np.any(alpha <= 0):
        return f"Richardson extrapolation refused: the bias does not decay (alpha = {alpha.tolist()})"
    top = levels[-1]
    # Worth it only with fewer levels than plain MLMC, or on the same levels if plain MLMC
    # cannot meet the bias there (capped by max_level).
    cap = plain_level + 1 if not is_plain_met else plain_level
    for level in range(RICHARDSON_MIN_LEVELS, cap):
        if level <= top:
            bias = richardson_bias(means[:level], alpha, errors[:level])
        else:
            bias = richardson_bias(means, alpha, errors, beyond=level - top)
        if np.all(bias <= bias_limit):
            return level, bias
    return f"Richardson extrapolation needs as many levels as plain MLMC here (L = {plain_level})"

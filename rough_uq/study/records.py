"""Typed records of a study: screening, estimation runs, plans, forecasts, diagnostics.

The pipeline (:mod:`rough_uq.study.pipeline`) produces these frozen
dataclasses, the store keeps them as JSON text (:mod:`rough_uq.study.store`,
``screening/record`` and ``runs/<run_id>/record``), and the report and the
CLI read them back with ``from_json``. ``to_json`` gives exactly the mapping
the store holds; the layout is the one every roughuq so far has written
(format versions 1-3 of the study file differ in their samples only), so
records need no conversion.

Older layouts
-------------
Keys added since the first study files are optional when read: a run's
``stage``, ``initial_samples``, ``elapsed``, ``forecast``, ``richardson``,
``richardson_reason``, ``dropped_levels`` and ``stopped_elapsed``, the screening's
``coarsest_level`` and ``dropped_levels``. Runs of the targets beyond the
mean (``method`` ``variance`` or ``cdf``, :class:`RunOutcome`) add optional
keys and leave out the mean run's ``variance``, ``variance_error`` and
``statistics``, which are therefore optional too; a file with such runs keeps
its format version (an older roughuq refuses the new methods by name when it
reads them, rather than misreading them). A record read without them writes
them back only where a value is known (``None`` keys stay absent), except the
keys the pipeline has always written as ``null`` (``max_cost``, ``forecast``,
a run's ``rates``). Where a run record lacks ``rmse``, ``tol_met`` or
``is_bias_estimated`` (hand-written records), they are derived: ``rmse =
hypot(stat_error, bias_estimate)``, ``tol_met = stop_reason == "tol_met"``,
``is_bias_estimated = True``. Keys a record does not define (e.g. the derived
numbers of ``roughuq report --json``) are ignored when read.

Every malformed field raises :class:`~rough_uq.errors.InvalidParameterError`
naming the field by its path (``run mlmc_x: outcome.estimate``), the value and
what is allowed.

Derived numbers, each defined once here: the complexity exponents of fitted
rates (:func:`complexity`, SPEC section 5), the count of non-converged samples
over batches (:func:`count_not_converged`, the sum of
:attr:`~rough_uq.problem.batch.LevelBatch.n_not_converged`), timestamps
(:func:`utc_timestamp`) and a run's predicted MC/MLMC work ratio
(:attr:`RunOutcome.work_ratio`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, TypeVar

import numpy as np

from rough_uq.errors import InvalidParameterError
from rough_uq.multilevel.allocation import unreachable_columns
from rough_uq.multilevel.drivers import RATE_FLOOR
from rough_uq.multilevel.rates import BIAS_RATE_CAP, EXACT_RATE
from rough_uq.problem.batch import LevelBatch

__all__ = [
    "MIN_ALPHA",
    "RATE_TIE",
    "RUN_STATUSES",
    "Complexity",
    "Diagnostic",
    "DistributionRecord",
    "DroppedLevel",
    "Forecast",
    "LevelTable",
    "PlanRecord",
    "QuantileRecord",
    "RUN_METHODS",
    "RatesRecord",
    "RunOutcome",
    "RunRecord",
    "ScreeningRecord",
    "complexity",
    "is_bias_decaying",
    "count_not_converged",
    "read_run_records",
    "read_screening_record",
    "utc_timestamp",
]

#: ``beta`` and ``gamma`` closer than this count as equal (about the standard error of a screening fit).
RATE_TIE = 0.1
#: Fitted bias rates at or below this are "not fitted": the bias does not decay (measurably).
MIN_ALPHA = 0.05
#: Status of a run: stored ones (``refused``: the estimator stopped it with an error, its ``reason``), and
#: ``interrupted`` (a ``running`` record without a live writer, as reported).
RUN_STATUSES = ("running", "finished", "refused", "dropped", "interrupted")

_T = TypeVar("_T")
Number = int | float


# ---------------------------------------------------------------------------
# Derived numbers
# ---------------------------------------------------------------------------


def utc_timestamp() -> str:
    """The current time as ISO 8601 text in UTC, to the second (``2026-11-24T06:01:47+00:00``)."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def count_not_converged(batches: Iterable[LevelBatch]) -> int:
    """Samples with a solve (fine or coarse) that did not converge, summed over ``batches``."""
    return sum(batch.n_not_converged for batch in batches)


@dataclass(frozen=True)
class Complexity:
    """Cost of an estimator to RMS error ``eps`` as a power of ``1/eps`` (SPEC section 5).

    Attributes
    ----------
    mc_exponent, mlmc_exponent : float or None
        Exponents of plain MC and MLMC; None where a rate is not fitted.
    mlmc_regime : str
        The MLMC regime in words, or why there is no exponent.
    """

    mc_exponent: float | None
    mlmc_exponent: float | None
    mlmc_regime: str

    def to_json(self) -> dict[str, Any]:
        return {"mc_exponent": self.mc_exponent, "mlmc_exponent": self.mlmc_exponent,
                "mlmc_regime": self.mlmc_regime}


def is_bias_decaying(alpha: float | None) -> bool:
    """Whether a fitted bias rate shows a measurable decay: finite and above :data:`MIN_ALPHA`.

    The one rule of the report's "not fitted" (:func:`complexity`, the rates figure).
    """
    return alpha is not None and math.isfinite(alpha) and alpha > MIN_ALPHA


def complexity(alpha: float | None, beta: float | None, gamma: float | None) -> Complexity:
    """Cost exponents of MC and MLMC in ``1/eps`` from the rates of one QoI.

    A column exact on the screened levels (``alpha`` :data:`~rough_uq.multilevel.rates.EXACT_RATE`) has no
    exponents: its regime says "exact". Otherwise MC costs ``eps^-(2 + gamma/alpha)``; MLMC ``eps^-2`` if
    ``beta > gamma``,
    ``eps^-2 log(eps)^2`` if ``|beta - gamma| <`` :data:`RATE_TIE`, else
    ``eps^-(2 + (gamma - beta)/alpha)``. A bias rate at most :data:`MIN_ALPHA`
    (no measurable decay) gives no exponent.
    """
    if alpha == EXACT_RATE:  # the stand-in of rates.fit_rates for a column exact on every fitted level
        return Complexity(None, None, "exact: the same value on every screened grid (no bias, no level variance)")
    if not is_bias_decaying(alpha):
        return Complexity(None, None, "not fitted: the bias does not decay over the screened levels")
    if gamma is None or not math.isfinite(gamma):
        return Complexity(None, None, "not fitted: no cost rate gamma")
    mc = 2.0 + gamma / alpha
    if beta is None or not math.isfinite(beta):
        return Complexity(mc, None, "not fitted: no variance rate beta")
    if abs(beta - gamma) < RATE_TIE:
        return Complexity(mc, 2.0, "eps^-2 log(eps)^2 (beta = gamma)")
    if beta > gamma:
        return Complexity(mc, 2.0, "eps^-2 (beta > gamma)")
    mlmc = 2.0 + (gamma - beta) / alpha
    return Complexity(mc, mlmc, f"eps^-{mlmc:.2f} (beta < gamma)")


# ---------------------------------------------------------------------------
# Reading JSON values
# ---------------------------------------------------------------------------


def _fail(where: str, value: object, allowed: str) -> Any:
    raise InvalidParameterError(where, value, allowed)


def _number(value: object, where: str) -> Number:
    # Kept as given (an int stays an int), so a record rewritten is the record read.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(where, value, "a number")
    return value  # type: ignore[return-value]


def _integer(value: object, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        _fail(where, value, "an integer")
    return value  # type: ignore[return-value]


def _text(value: object, where: str) -> str:
    return value if isinstance(value, str) else _fail(where, value, "a string")


def _flag(value: object, where: str) -> bool:
    return value if isinstance(value, bool) else _fail(where, value, "true or false")


def _list(value: object, where: str) -> list[Any]:
    return value if isinstance(value, list) else _fail(where, value, "a list")


def _each(parse: Callable[[object, str], _T]) -> Callable[[object, str], tuple[_T, ...]]:
    """A parser of a JSON list whose entries ``parse`` reads (``where[i]`` names an entry)."""

    def parse_list(value: object, where: str) -> tuple[_T, ...]:
        return tuple(parse(item, f"{where}[{i}]") for i, item in enumerate(_list(value, where)))

    return parse_list


_numbers = _each(_number)
_integers = _each(_integer)
_table = _each(_numbers)
_texts = _each(_text)


def _lists(value: Any) -> Any:
    """Tuples back to JSON lists (nested)."""
    return [_lists(item) for item in value] if isinstance(value, tuple) else value


class _Fields:
    """The fields of one JSON object, read by name; errors name ``where.key``."""

    def __init__(self, data: object, where: str) -> None:
        if not isinstance(data, Mapping):
            _fail(where, data, "a JSON object (mapping)")
        self.data = data
        self.where = where

    def required(self, key: str, parse: Callable[[object, str], _T]) -> _T:
        if key not in self.data:
            _fail(f"{self.where}.{key}", None, "a value: the field is missing")
        return parse(self.data[key], f"{self.where}.{key}")

    def optional(self, key: str, parse: Callable[[object, str], _T], default: Any = None) -> Any:
        value = self.data.get(key)
        return default if value is None else parse(value, f"{self.where}.{key}")


def _omit_none(pairs: Iterable[tuple[str, Any]], keep: Sequence[str] = ()) -> dict[str, Any]:
    """A JSON object of ``pairs`` without the keys whose value is None (except those in ``keep``)."""
    return {key: _lists(value) for key, value in pairs if value is not None or key in keep}


# ---------------------------------------------------------------------------
# Small records
# ---------------------------------------------------------------------------


_KINDS = (  # (kind, text that identifies it), first match wins
    ("prediction", "no cost prediction"),
    ("richardson", "Richardson extrapolation refused"),
    ("consistency", "consistency check failed"),
    ("kurtosis", "kurtosis"),
    ("coupling", "Var(Q_l - Q_l-1) >= Var(Q_l)"),
    ("rare_differences", "is the same in all"),
    ("few_samples", "variance unknown"),
    ("few_samples", "single sample"),
    ("zero_cost", "zero cost"),
    ("bias_noise", "rests on level terms within their noise"),
)


@dataclass(frozen=True)
class Diagnostic:
    """A failed check or a caveat of a screening or a run, shown to the user as a warning.

    Stored as its message text (the ``warnings`` list of a record), so a
    record's diagnostics read back equal. :attr:`kind` classifies it.

    Attributes
    ----------
    message : str
        What was found and what it means.
    """

    message: str

    @property
    def kind(self) -> str:
        """``consistency``, ``kurtosis``, ``coupling``, ``rare_differences``, ``few_samples``,
        ``richardson``, ``prediction``, ``zero_cost``, ``bias_noise`` or ``other``."""
        return next((kind for kind, text in _KINDS if text in self.message), "other")

    def to_json(self) -> str:
        return self.message

    @classmethod
    def from_json(cls, data: object, where: str = "diagnostic") -> Diagnostic:
        return cls(_text(data, where))


def _diagnostics(value: object, where: str) -> tuple[Diagnostic, ...]:
    return _each(Diagnostic.from_json)(value, where)


@dataclass(frozen=True)
class DroppedLevel:
    """A coarse level left out of an estimator, and why.

    Attributes
    ----------
    level : int
    reason : str
    """

    level: int
    reason: str

    def to_json(self) -> dict[str, Any]:
        return {"level": self.level, "reason": self.reason}

    @classmethod
    def from_json(cls, data: object, where: str = "dropped_level") -> DroppedLevel:
        fields = _Fields(data, where)
        return cls(level=fields.required("level", _integer), reason=fields.required("reason", _text))


_dropped_levels = _each(DroppedLevel.from_json)


# ---------------------------------------------------------------------------
# Level statistics, rates, plans, forecasts
# ---------------------------------------------------------------------------


_TABLE_KEYS = ("mean_fine", "var_fine", "mean_diff", "var_diff", "kurtosis", "consistency")


@dataclass(frozen=True)
class LevelTable:
    """Per-level statistics of a screening or a run (SPEC section 5), as stored.

    Attributes
    ----------
    levels, n_samples : tuple of int, shape (n_levels,)
    mean_fine, var_fine, mean_diff, var_diff, kurtosis, consistency : tuple of tuple of float
        Shape (n_levels, n_qoi): moments of ``Q_l`` and ``Y_l = Q_l - Q_l-1``,
        the kurtosis of ``Y_l`` and the consistency ratio (above 1: failed).
    mean_cost : tuple of float, shape (n_levels,)
        Modelled cost per sample (reference seconds).
    mean_seconds : tuple of float, shape (n_levels,)
        Measured CPU-seconds per sample.
    """

    levels: tuple[int, ...]
    n_samples: tuple[int, ...]
    mean_fine: tuple[tuple[Number, ...], ...]
    var_fine: tuple[tuple[Number, ...], ...]
    mean_diff: tuple[tuple[Number, ...], ...]
    var_diff: tuple[tuple[Number, ...], ...]
    kurtosis: tuple[tuple[Number, ...], ...]
    consistency: tuple[tuple[Number, ...], ...]
    mean_cost: tuple[Number, ...]
    mean_seconds: tuple[Number, ...]

    @property
    def n_qoi(self) -> int:
        return len(self.mean_fine[0]) if self.mean_fine else 0

    @classmethod
    def from_statistics(cls, statistics: Any, seconds: Sequence[float]) -> LevelTable:
        """The table of a :class:`~rough_uq.multilevel.statistics.LevelStatistics` and measured seconds per sample."""
        values = {key: _tuples(getattr(statistics, key)) for key in _TABLE_KEYS}
        return cls(levels=_tuples(statistics.levels), n_samples=_tuples(statistics.n_samples), **values,
                   mean_cost=_tuples(statistics.mean_cost), mean_seconds=tuple(float(s) for s in seconds))

    def to_json(self) -> dict[str, Any]:
        keys = ("levels", "n_samples", *_TABLE_KEYS, "mean_cost", "mean_seconds")
        return {key: _lists(getattr(self, key)) for key in keys}

    @classmethod
    def from_json(cls, data: object, where: str = "statistics") -> LevelTable:
        fields = _Fields(data, where)
        return cls(
            levels=fields.required("levels", _integers),
            n_samples=fields.required("n_samples", _integers),
            **{key: fields.required(key, _table) for key in _TABLE_KEYS},
            mean_cost=fields.required("mean_cost", _numbers),
            mean_seconds=fields.required("mean_seconds", _numbers),
        )


def _tuples(value: Any) -> Any:
    """Arrays, lists and tuples (nested, possibly ragged) as nested tuples of Python numbers."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return tuple(_tuples(item) for item in value)
    return value.item() if isinstance(value, np.generic) else value


_PER_QOI_RATES = ("alpha", "alpha_se", "beta", "beta_se")


@dataclass(frozen=True)
class RatesRecord:
    """Fitted rates (SPEC section 5): ``|E[Y_l]| = c_alpha 2^(-alpha l)``, ``V_l = c_beta 2^(-beta l)``,
    ``C_l = c_gamma 2^(gamma l)`` (levels, not ``h``; the exponents are the same).

    Attributes
    ----------
    alpha, alpha_se, beta, beta_se, c_alpha, c_beta : tuple of float, shape (n_qoi,)
    gamma, gamma_se, c_gamma : float
    levels_alpha, levels_beta : tuple of tuple of int
        Per QoI, the levels each fit used.
    levels_gamma : tuple of int
    """

    alpha: tuple[Number, ...]
    alpha_se: tuple[Number, ...]
    beta: tuple[Number, ...]
    beta_se: tuple[Number, ...]
    gamma: Number
    gamma_se: Number
    c_alpha: tuple[Number, ...]
    c_beta: tuple[Number, ...]
    c_gamma: Number
    levels_alpha: tuple[tuple[int, ...], ...]
    levels_beta: tuple[tuple[int, ...], ...]
    levels_gamma: tuple[int, ...]

    @classmethod
    def from_rates(cls, rates: Any) -> RatesRecord:
        """The record of a :class:`~rough_uq.multilevel.rates.Rates` (per-QoI values as tuples)."""
        return cls(**{key: _tuples(getattr(rates, key)) for key in _RATES_KEYS})

    @property
    def complexity(self) -> tuple[Complexity, ...]:
        """Per QoI, the cost exponents these rates imply (:func:`complexity`)."""
        return tuple(complexity(a, b, self.gamma) for a, b in zip(self.alpha, self.beta))

    @property
    def planned_complexity(self) -> tuple[Complexity, ...]:
        """Per QoI, the cost exponents of these rates raised to the floor the plans use (``RATE_FLOOR``,
        :func:`~rough_uq.multilevel.drivers.planning.planning_rates`), ``alpha`` also capped where the plans cap the
        bias's tail (``BIAS_RATE_CAP``, :func:`~rough_uq.multilevel.rates.tail_rate`): the slopes of the
        predicted costs."""
        def floored(rate: Number | None) -> Number | None:
            return None if rate is None or not math.isfinite(rate) else max(rate, RATE_FLOOR)

        def capped(rate: Number | None) -> Number | None:
            return None if rate is None or not math.isfinite(rate) else min(rate, BIAS_RATE_CAP)

        return tuple(complexity(a, b, self.gamma) if a == EXACT_RATE  # exact: no rate to floor or cap
                     else complexity(capped(floored(a)), floored(b), floored(self.gamma))
                     for a, b in zip(self.alpha, self.beta))

    def to_json(self) -> dict[str, Any]:
        return {key: _lists(getattr(self, key)) for key in _RATES_KEYS}

    @classmethod
    def from_json(cls, data: object, where: str = "rates") -> RatesRecord:
        fields = _Fields(data, where)
        return cls(
            **{key: fields.required(key, _numbers) for key in (*_PER_QOI_RATES, "c_alpha", "c_beta")},
            **{key: fields.required(key, _number) for key in ("gamma", "gamma_se", "c_gamma")},
            levels_alpha=fields.required("levels_alpha", _each(_integers)),
            levels_beta=fields.required("levels_beta", _each(_integers)),
            levels_gamma=fields.required("levels_gamma", _integers),
        )


_RATES_KEYS = (*_PER_QOI_RATES, "gamma", "gamma_se", "c_alpha", "c_beta", "c_gamma",
               "levels_alpha", "levels_beta", "levels_gamma")


@dataclass(frozen=True)
class PlanRecord:
    """An MLMC plan for one tolerance as the screening predicts it.

    Attributes
    ----------
    tol : tuple of float, shape (n_qoi,)
    finest_level : int
    n_samples : tuple of int, shape (finest_level + 1,)
    mlmc_cost, mc_cost : float
        Modelled cost (reference seconds) of MLMC and of plain MC to ``tol``.
    mlmc_seconds, mc_seconds : float
        The same in CPU-seconds (modelled cost times measured seconds per modelled second).
    work_ratio : float
        ``mc_cost / mlmc_cost``.
    is_bias_met : bool
        The finest level allowed reaches the bias ``tol`` needs.
    unmet_columns : tuple of int or None
        The columns whose predicted bias on the plan's finest level is above
        their share ``sqrt(theta) tol`` (None in files before it was recorded).
    """

    tol: tuple[Number, ...]
    finest_level: int
    n_samples: tuple[int, ...]
    mlmc_cost: Number
    mc_cost: Number
    mlmc_seconds: Number
    mc_seconds: Number
    work_ratio: Number
    is_bias_met: bool
    unmet_columns: tuple[int, ...] | None = None

    @classmethod
    def from_plan(cls, plan: Any, seconds_per_cost: float) -> PlanRecord:
        """The record of a :class:`~rough_uq.multilevel.allocation.Plan`; seconds are ``cost * seconds_per_cost``."""
        return cls(
            tol=_tuples(plan.tol), finest_level=int(plan.finest_level), n_samples=_tuples(plan.n_samples),
            mlmc_cost=float(plan.cost), mc_cost=float(plan.mc_cost),
            mlmc_seconds=float(plan.cost * seconds_per_cost), mc_seconds=float(plan.mc_cost * seconds_per_cost),
            work_ratio=float(plan.work_ratio), is_bias_met=bool(plan.is_bias_met),
            unmet_columns=tuple(int(q) for q in np.flatnonzero(unreachable_columns(plan, plan.tol))),
        )

    def to_json(self) -> dict[str, Any]:
        data = {key: _lists(getattr(self, key)) for key in _PLAN_KEYS}
        return data if self.unmet_columns is None else {**data, "unmet_columns": list(self.unmet_columns)}

    @classmethod
    def from_json(cls, data: object, where: str = "plan") -> PlanRecord:
        fields = _Fields(data, where)
        return cls(
            tol=fields.required("tol", _numbers),
            finest_level=fields.required("finest_level", _integer),
            n_samples=fields.required("n_samples", _integers),
            **{key: fields.required(key, _number) for key in _PLAN_COSTS},
            is_bias_met=fields.required("is_bias_met", _flag),
            unmet_columns=fields.optional("unmet_columns", _integers),
        )


_PLAN_COSTS = ("mlmc_cost", "mc_cost", "mlmc_seconds", "mc_seconds", "work_ratio")
_PLAN_KEYS = ("tol", "finest_level", "n_samples", *_PLAN_COSTS, "is_bias_met")


@dataclass(frozen=True)
class Forecast:
    """What a run will need, predicted from the screening before its first sample.

    Attributes
    ----------
    finest_level : int
        Finest level the run samples from the start: MLMC the finest level
        its bias needs, or the level it adds to fit the rates (two above its
        coarsest); MC the level it samples.
    grid : int
        Nodes per side of that level.
    n_samples : tuple of int
        Samples per level ``0..finest_level``, 0 below the coarsest level
        the run uses (MC: one entry, the finest level).
    modelled_cost : float
        Predicted modelled cost (reference seconds).
    cpu_seconds : float
        Predicted CPU-seconds of the samples (modelled cost times the
        screening's measured seconds per modelled second).
    wall_seconds : float
        ``cpu_seconds`` shared by the workers.
    memory_bytes : int
        Memory of the solves running at once (one finest solve per worker).
    is_richardson : bool
        The prediction is for the Richardson-extrapolated estimate (asked for,
        and the screening's level means allow it).
    richardson_note : str
        Why an extrapolation that was asked for is not planned ("" when it is,
        or was not asked for): the run plans plain MLMC.
    n_stored : tuple of int
        Of ``n_samples``, how many are stored already (merged shards, an
        earlier run of the same request), per entry; empty when none is.
        ``modelled_cost``, ``cpu_seconds`` and ``wall_seconds`` count them too.
    stored_cost : float
        Their modelled cost (reference seconds).
    """

    finest_level: int
    grid: int
    n_samples: tuple[int, ...]
    modelled_cost: float
    cpu_seconds: float
    wall_seconds: float
    memory_bytes: int
    is_richardson: bool = False
    richardson_note: str = ""
    n_stored: tuple[int, ...] = ()
    stored_cost: float = 0.0

    @property
    def remaining_fraction(self) -> float:
        """The share of the modelled cost still to compute (1 when nothing is stored)."""
        if not self.n_stored or not self.modelled_cost > 0:
            return 1.0
        return min(max(1.0 - self.stored_cost / self.modelled_cost, 0.0), 1.0)

    def to_json(self) -> dict[str, Any]:
        data = {key: _lists(getattr(self, key)) for key in _FORECAST_KEYS}
        # Left out when empty: the records of earlier versions read back to the same text.
        if self.richardson_note:
            data["richardson_note"] = self.richardson_note
        if self.n_stored:
            data.update(n_stored=list(self.n_stored), stored_cost=self.stored_cost)
        return data

    @classmethod
    def from_json(cls, data: object, where: str = "forecast") -> Forecast:
        fields = _Fields(data, where)
        return cls(
            finest_level=fields.required("finest_level", _integer),
            grid=fields.required("grid", _integer),
            n_samples=fields.required("n_samples", _integers),
            **{key: fields.required(key, _number) for key in ("modelled_cost", "cpu_seconds", "wall_seconds")},
            memory_bytes=fields.required("memory_bytes", _integer),
            is_richardson=fields.optional("is_richardson", _flag, False),
            richardson_note=fields.optional("richardson_note", _text, ""),
            n_stored=fields.optional("n_stored", _integers, ()),
            stored_cost=fields.optional("stored_cost", _number, 0.0),
        )


_FORECAST_KEYS = ("finest_level", "grid", "n_samples", "modelled_cost", "cpu_seconds", "wall_seconds",
                  "memory_bytes", "is_richardson")


# ---------------------------------------------------------------------------
# Screening and runs
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ScreeningRecord:
    """What the screening measured and predicts (``roughuq screen``).

    Attributes
    ----------
    created, code_version : str
        When (:func:`utc_timestamp`) and by which roughuq it was computed.
    qoi_names : tuple of str
    statistics : LevelTable
    rates : RatesRecord
    predictions : tuple of PlanRecord
        Plans for multiples of the base tolerance (empty where the bias does not decay).
    seconds_per_cost : float
        Measured CPU-seconds per modelled reference second.
    n_not_converged, n_computed : int
        Samples with a non-converged solve; samples this screening computed.
    diagnostics : tuple of Diagnostic
        Failed checks and caveats (stored as ``warnings``).
    coarsest_level : int or None
        Coarsest level worth sampling (None in files before it was recorded).
    dropped_levels : tuple of DroppedLevel or None
        Coarse levels left out, and why (None in files before it was recorded).
    """

    created: str
    code_version: str
    qoi_names: tuple[str, ...]
    statistics: LevelTable
    rates: RatesRecord
    predictions: tuple[PlanRecord, ...]
    seconds_per_cost: Number
    n_not_converged: int
    n_computed: int
    diagnostics: tuple[Diagnostic, ...] = ()
    coarsest_level: int | None = None
    dropped_levels: tuple[DroppedLevel, ...] | None = None

    @property
    def complexity(self) -> tuple[Complexity, ...]:
        """Per QoI, the cost exponents of the fitted rates."""
        return self.rates.complexity

    @property
    def n_screened(self) -> int:
        """Samples on every screened level (the fewest of any level)."""
        return int(min(self.statistics.n_samples))

    def to_json(self) -> dict[str, Any]:
        dropped = None if self.dropped_levels is None else [d.to_json() for d in self.dropped_levels]
        return _omit_none([
            ("created", self.created), ("code_version", self.code_version), ("qoi_names", self.qoi_names),
            ("statistics", self.statistics.to_json()), ("rates", self.rates.to_json()),
            ("predictions", [p.to_json() for p in self.predictions]),
            ("coarsest_level", self.coarsest_level), ("dropped_levels", dropped),
            ("seconds_per_cost", self.seconds_per_cost), ("n_not_converged", self.n_not_converged),
            ("n_computed", self.n_computed), ("warnings", [d.to_json() for d in self.diagnostics]),
        ])

    @classmethod
    def from_json(cls, data: object, where: str = "screening") -> ScreeningRecord:
        fields = _Fields(data, where)
        return cls(
            created=fields.required("created", _text),
            code_version=fields.required("code_version", _text),
            qoi_names=fields.required("qoi_names", _texts),
            statistics=fields.required("statistics", LevelTable.from_json),
            rates=fields.required("rates", RatesRecord.from_json),
            predictions=fields.required("predictions", _each(PlanRecord.from_json)),
            seconds_per_cost=fields.required("seconds_per_cost", _number),
            n_not_converged=fields.required("n_not_converged", _integer),
            n_computed=fields.required("n_computed", _integer),
            diagnostics=fields.optional("warnings", _diagnostics, ()),
            coarsest_level=fields.optional("coarsest_level", _integer),
            dropped_levels=fields.optional("dropped_levels", _dropped_levels),
        )


def _optional_number(value: object, where: str) -> Number | None:
    """A number or JSON null (an unbounded end of an error bar)."""
    return None if value is None else _number(value, where)


@dataclass(frozen=True)
class QuantileRecord:
    """A quantile ``q_p`` of a ``cdf`` run with its error bar (:mod:`rough_uq.multilevel.distribution`).

    Attributes
    ----------
    probability : float
        ``p`` in (0, 1).
    value : float or None
        ``q_p`` in the QoI's unit; None when the CDF does not reach ``p`` on
        the thresholds (a diagnostic of the run says so).
    lower, upper : float or None
        Where the band ``cdf +- rmse`` reaches ``p``; None where that is
        beyond the thresholds (the error bar is open on that side).
    """

    probability: Number
    value: Number | None
    lower: Number | None
    upper: Number | None

    def to_json(self) -> dict[str, Any]:
        return {"probability": self.probability, "value": self.value, "lower": self.lower, "upper": self.upper}

    @classmethod
    def from_json(cls, data: object, where: str = "quantile") -> QuantileRecord:
        fields = _Fields(data, where)
        return cls(
            probability=fields.required("probability", _number),
            **{key: _optional_number(fields.data.get(key), f"{where}.{key}") for key in ("value", "lower", "upper")},
        )


@dataclass(frozen=True)
class DistributionRecord:
    """The distribution function of one QoI column estimated by a ``cdf`` run.

    Attributes
    ----------
    column : str
        The QoI column.
    thresholds : tuple of float, shape (m,)
        ``s_j``, the column's unit.
    cdf : tuple of float, shape (m,)
        The monotone estimate of ``F(s_j) = P(Q <= s_j)`` in [0, 1].
    cdf_lower, cdf_upper : tuple of float, shape (m,)
        The band ``cdf -+ rmse`` (the run's sup-norm RMS error), clipped to [0, 1].
    bandwidths : tuple of float, shape (n_levels,)
        Smoothing width ``delta_l`` per level, the column's unit.
    quantiles : tuple of QuantileRecord
    """

    column: str
    thresholds: tuple[Number, ...]
    cdf: tuple[Number, ...]
    cdf_lower: tuple[Number, ...]
    cdf_upper: tuple[Number, ...]
    bandwidths: tuple[Number, ...]
    quantiles: tuple[QuantileRecord, ...] = ()

    def to_json(self) -> dict[str, Any]:
        keys = ("column", "thresholds", "cdf", "cdf_lower", "cdf_upper", "bandwidths")
        return {**{key: _lists(getattr(self, key)) for key in keys},
                "quantiles": [q.to_json() for q in self.quantiles]}

    @classmethod
    def from_json(cls, data: object, where: str = "distribution") -> DistributionRecord:
        fields = _Fields(data, where)
        return cls(
            column=fields.required("column", _text),
            **{key: fields.required(key, _numbers)
               for key in ("thresholds", "cdf", "cdf_lower", "cdf_upper", "bandwidths")},
            quantiles=fields.optional("quantiles", _each(QuantileRecord.from_json), ()),
        )


#: Keys of a finished run's outcome, in the order they are stored.
_OUTCOME_VECTORS = ("estimate", "stat_error", "bias_estimate")
_OUTCOME_MOMENTS = ("variance", "variance_error")


@dataclass(frozen=True)
class RunOutcome:
    """What a finished run found and spent (SPEC section 5: estimate, errors, bias, cost, MC cost).

    What ``estimate`` means depends on the run's method: ``E[Q]`` (``mlmc``,
    ``mc``), ``Var(Q)`` in the QoI's unit squared (``variance``), or the
    telescoped CDF ``F(s_j)`` before its monotone projection (``cdf``, one
    value per threshold; :attr:`distribution` holds the thresholds, the
    monotone CDF, its band and the quantiles).

    Attributes
    ----------
    finished : str
        When it finished (:func:`utc_timestamp`).
    estimate, stat_error : tuple of float
        Shape (n_qoi,); for a ``cdf`` run (n_thresholds,).
    bias_estimate, rmse : tuple of float, shape (n_qoi,)
        For a ``cdf`` run shape (1,): the sup-norm over the thresholds.
    is_bias_estimated : bool
    variance, variance_error : tuple of float, shape (n_qoi,), or None
        Mean runs: MLMC estimate of ``Var(Q)`` and its standard error (None
        for ``variance`` and ``cdf`` runs, whose estimate it is or replaces).
    levels, n_samples : tuple of int
    cost : float
        Modelled cost (reference seconds).
    seconds : float
        CPU-seconds of the samples.
    elapsed : float or None
        Wall seconds of the commands that computed the run: the one that finished it, plus those stopped before
        it (Ctrl-C, SIGTERM, a failure; :attr:`RunRecord.stopped_elapsed`) (None in files before it was
        recorded).
    mc_cost, mc_seconds_predicted : float
        Predicted plain MC to the same tolerance: modelled cost, CPU-seconds.
    n_computed, n_not_converged : int
    tol_met : bool
    stop_reason : str
    richardson, richardson_reason : str or None
    dropped_levels : tuple of DroppedLevel or None
    rates : RatesRecord or None
        Rates refitted on the run's levels (MLMC only).
    statistics : LevelTable or None
        Mean runs: the per-level statistics (None for ``variance`` and ``cdf`` runs).
    diagnostics : tuple of Diagnostic
    distribution : DistributionRecord or None
        ``cdf`` runs: thresholds, monotone CDF with its band, quantiles.
    """

    finished: str
    estimate: tuple[Number, ...]
    stat_error: tuple[Number, ...]
    bias_estimate: tuple[Number, ...]
    is_bias_estimated: bool
    rmse: tuple[Number, ...]
    levels: tuple[int, ...]
    n_samples: tuple[int, ...]
    cost: Number
    seconds: Number
    mc_cost: Number
    mc_seconds_predicted: Number
    n_computed: int
    n_not_converged: int
    tol_met: bool
    stop_reason: str
    variance: tuple[Number, ...] | None = None
    variance_error: tuple[Number, ...] | None = None
    statistics: LevelTable | None = None
    rates: RatesRecord | None = None
    elapsed: Number | None = None
    richardson: str | None = None
    richardson_reason: str | None = None
    dropped_levels: tuple[DroppedLevel, ...] | None = None
    diagnostics: tuple[Diagnostic, ...] = ()
    distribution: DistributionRecord | None = None

    @classmethod
    def from_result(
        cls, result: Any, *, mean_seconds: Sequence[float], seconds: float, elapsed: float, mc_cost: float,
        seconds_per_cost: float, n_computed: int, n_not_converged: int, diagnostics: Sequence[Diagnostic],
    ) -> RunOutcome:
        """The outcome of an :class:`~rough_uq.multilevel.drivers.events.EstimationResult` and what the pipeline
        measured.

        ``mean_seconds`` are the CPU-seconds per sample of each level, ``seconds``
        their total over the run's samples; ``mc_cost`` (modelled) is converted
        to CPU-seconds with ``seconds_per_cost``.
        """
        vectors = {key: _tuples(np.atleast_1d(getattr(result, key)))
                   for key in (*_OUTCOME_VECTORS, "rmse", *_OUTCOME_MOMENTS)}
        return cls(
            finished=utc_timestamp(), **vectors, is_bias_estimated=_tuples(result.is_bias_estimated),
            levels=_tuples(result.levels), n_samples=_tuples(result.n_samples), cost=_tuples(result.cost),
            seconds=seconds, elapsed=elapsed, mc_cost=_tuples(mc_cost),
            mc_seconds_predicted=_tuples(mc_cost * seconds_per_cost),
            n_computed=n_computed, n_not_converged=n_not_converged, tol_met=_tuples(result.tol_met),
            stop_reason=result.stop_reason, richardson=result.richardson, richardson_reason=result.richardson_reason,
            dropped_levels=tuple(DroppedLevel(int(d.level), d.reason) for d in result.dropped_levels),
            rates=None if result.rates is None else RatesRecord.from_rates(result.rates),
            statistics=LevelTable.from_statistics(result.statistics, mean_seconds),
            diagnostics=tuple(diagnostics),
        )

    @property
    def work_ratio(self) -> float:
        """Predicted plain-MC modelled cost over the run's (inf for a run that cost nothing)."""
        return self.mc_cost / self.cost if self.cost > 0 else math.inf

    def json_items(self) -> list[tuple[str, Any]]:
        """The outcome's keys and JSON values, in stored order (``status`` excluded: it belongs to the run)."""
        dropped = None if self.dropped_levels is None else [d.to_json() for d in self.dropped_levels]
        return [
            ("finished", self.finished),
            *((key, getattr(self, key)) for key in (*_OUTCOME_VECTORS, "is_bias_estimated", "rmse",
                                                    *_OUTCOME_MOMENTS, "levels", "n_samples", "cost", "seconds",
                                                    "elapsed", "mc_cost", "mc_seconds_predicted", "n_computed",
                                                    "n_not_converged", "tol_met", "stop_reason", "richardson",
                                                    "richardson_reason")),
            ("dropped_levels", dropped),
            ("rates", None if self.rates is None else self.rates.to_json()),
            ("statistics", None if self.statistics is None else self.statistics.to_json()),
            ("distribution", None if self.distribution is None else self.distribution.to_json()),
            ("warnings", [d.to_json() for d in self.diagnostics]),
        ]

    @classmethod
    def from_json(cls, data: object, where: str = "run") -> RunOutcome:
        fields = _Fields(data, where)
        vectors = {key: fields.required(key, _numbers) for key in _OUTCOME_VECTORS}
        moments = {key: fields.optional(key, _numbers) for key in _OUTCOME_MOMENTS}
        stop_reason = fields.required("stop_reason", _text)
        rmse = tuple(math.hypot(s, b) for s, b in zip(vectors["stat_error"], vectors["bias_estimate"]))
        return cls(
            finished=fields.required("finished", _text),
            **vectors,
            **moments,
            is_bias_estimated=fields.optional("is_bias_estimated", _flag, True),
            rmse=fields.optional("rmse", _numbers, rmse),
            levels=fields.required("levels", _integers),
            n_samples=fields.required("n_samples", _integers),
            **{key: fields.required(key, _number) for key in ("cost", "seconds", "mc_cost", "mc_seconds_predicted")},
            n_computed=fields.required("n_computed", _integer),
            n_not_converged=fields.required("n_not_converged", _integer),
            tol_met=fields.optional("tol_met", _flag, stop_reason == "tol_met"),
            stop_reason=stop_reason,
            statistics=fields.optional("statistics", LevelTable.from_json),
            rates=fields.optional("rates", RatesRecord.from_json),
            distribution=fields.optional("distribution", DistributionRecord.from_json),
            elapsed=fields.optional("elapsed", _number),
            richardson=fields.optional("richardson", _text),
            richardson_reason=fields.optional("richardson_reason", _text),
            dropped_levels=fields.optional("dropped_levels", _dropped_levels),
            diagnostics=fields.optional("warnings", _diagnostics, ()),
        )


def _status(value: object, where: str) -> str:
    return value if value in RUN_STATUSES else _fail(where, value, ", ".join(RUN_STATUSES))


#: Estimators of a run: the mean (``mlmc``, ``mc``) and the targets beyond it (``variance``, ``cdf``).
RUN_METHODS = ("mlmc", "mc", "variance", "cdf")


def _method(value: object, where: str) -> str:
    return value if value in RUN_METHODS else _fail(where, value, ", ".join(RUN_METHODS))


@dataclass(frozen=True)
class RunRecord:
    """An estimation run (MLMC, MC, or an MLMC variance or CDF run): its settings, and its outcome once finished.

    The record is stored when the run starts (``status = "running"``, no
    outcome) and again when it ends (``"finished"``, or ``"refused"`` with
    the ``reason`` when the estimator refused to go on, e.g. a plan beyond
    ``max_samples``, or ``"interrupted"`` after Ctrl-C or SIGTERM); ``roughuq
    drop`` marks it ``"dropped"``. A ``"running"`` record whose process is
    gone (killed outright) is an interrupted run too.

    Attributes
    ----------
    run_id : str
        Its name in the study (:func:`~rough_uq.problem.runs.run_id`); not part of the stored text.
    method : {"mlmc", "mc", "variance", "cdf"}
        ``variance`` and ``cdf`` are the MLMC targets beyond the mean
        (:class:`RunOutcome` says what their outcome holds).
    status : {"running", "finished", "refused", "dropped", "interrupted"}
    tol : tuple of float, shape (n_qoi,)
    started, code_version : str or None
        When it started (:func:`utc_timestamp`) and by which roughuq (the
        pipeline always records them; None only in hand-made records).
    qoi_names : tuple of str or None
    theta : float or None
        Bias share of ``tol**2``.
    max_cost : float or None
        Budget (modelled reference seconds).
    stage : int or None
        Random stage of its samples (None in files before runs had their own).
    initial_samples : int or None
    level : int or None
        MC only: the level sampled.
    screening_rates : RatesRecord or None
        The screening's fitted rates (None for MC on a given level); the run planned with them floored at 0.5
        (:func:`~rough_uq.multilevel.drivers.planning.planning_rates`).
    predicted : PlanRecord or None
        The screening's plan for ``tol`` (seconds are modelled cost: ``seconds_per_cost = 1``).
    forecast : Forecast or None
    outcome : RunOutcome or None
        None until the run finished.
    reason : str or None
        Why the run was refused (the error's message; status ``refused`` only).
    stopped_elapsed : float or None
        Wall seconds of the commands of this run that were stopped before it finished (None where none was): a
        resumed run's ``elapsed`` adds them, as it took them (a process killed outright records none).
    """

    run_id: str
    method: str
    status: str
    tol: tuple[Number, ...]
    started: str | None = None
    code_version: str | None = None
    qoi_names: tuple[str, ...] | None = None
    theta: Number | None = None
    max_cost: Number | None = None
    stage: int | None = None
    initial_samples: int | None = None
    level: int | None = None
    screening_rates: RatesRecord | None = None
    predicted: PlanRecord | None = None
    forecast: Forecast | None = None
    outcome: RunOutcome | None = field(default=None)
    reason: str | None = None
    stopped_elapsed: Number | None = None

    @property
    def is_finished(self) -> bool:
        return self.status == "finished" and self.outcome is not None

    @property
    def measures_plain_mc(self) -> bool:
        """An MC run the screening planned (``mc --tol``): a measure of plain MC to its tolerance.

        ``mc --level`` runs (no ``screening_rates``) sample a level the user
        chose, with a bias of their own: the report's measured MC/MLMC ratio
        and its figures leave them out.
        """
        return self.method == "mc" and self.screening_rates is not None

    @property
    def comparison_key(self) -> tuple[tuple[Number, ...], Number | None]:
        """What a plain MC run and an MLMC run share to be compared: the tolerances and ``theta``.

        ``theta`` splits the tolerance between bias and statistical error, so MC runs at another
        ``theta`` are other problems: keyed on the tolerances alone, an ``mc`` run at theta 0.25 took
        the place of the theta-0.5 one in the measured MC/MLMC ratio of a theta-0.5 MLMC run.
        """
        return self.tol, self.theta

    @property
    def is_richardson(self) -> bool:
        """An MLMC run that asked for Richardson extrapolation, applied or refused.

        Its name ends in ``_richardson`` (:func:`~rough_uq.problem.runs.run_id`);
        a finished run also says so in ``outcome.richardson``.
        """
        if self.method != "mlmc":
            return False
        asked = self.outcome is not None and self.outcome.richardson in ("applied", "refused")
        return asked or self.run_id.endswith("_richardson")

    def to_json(self) -> dict[str, Any]:
        """The stored mapping (without ``run_id``, which names the record in the store)."""
        head = [
            ("method", self.method), ("stage", self.stage), ("status", self.status), ("reason", self.reason),
            ("started", self.started), ("code_version", self.code_version), ("qoi_names", self.qoi_names),
            ("tol", self.tol), ("theta", self.theta), ("initial_samples", self.initial_samples),
            ("max_cost", self.max_cost), ("stopped_elapsed", self.stopped_elapsed),
        ]
        context = [
            ("screening_rates", None if self.screening_rates is None else self.screening_rates.to_json()),
            ("predicted", None if self.predicted is None else self.predicted.to_json()),
            ("level", self.level),
        ]
        forecast = [("forecast", None if self.forecast is None else self.forecast.to_json())]
        outcome = [] if self.outcome is None else self.outcome.json_items()
        return _omit_none(head + context + forecast + outcome, keep=("max_cost", "forecast", "rates"))

    @classmethod
    def from_json(cls, data: object, *, run_id: str | None = None) -> RunRecord:
        """Read a stored run; ``run_id`` defaults to the ``run_id`` key (:meth:`StudyStore.read_runs` adds it)."""
        if run_id is None:
            run_id = _Fields(data, "run").required("run_id", _text)
        where = f"run {run_id}"
        fields = _Fields(data, where)
        has_outcome = "finished" in fields.data
        record = cls(
            run_id=run_id,
            method=fields.required("method", _method),
            status=fields.required("status", _status),
            tol=fields.required("tol", _numbers),
            started=fields.optional("started", _text),
            code_version=fields.optional("code_version", _text),
            qoi_names=fields.optional("qoi_names", _texts),
            theta=fields.optional("theta", _number),
            max_cost=fields.optional("max_cost", _number),
            stage=fields.optional("stage", _integer),
            initial_samples=fields.optional("initial_samples", _integer),
            level=fields.optional("level", _integer),
            screening_rates=fields.optional("screening_rates", RatesRecord.from_json),
            predicted=fields.optional("predicted", PlanRecord.from_json),
            forecast=fields.optional("forecast", Forecast.from_json),
            outcome=RunOutcome.from_json(fields.data, where) if has_outcome else None,
            reason=fields.optional("reason", _text),
            stopped_elapsed=fields.optional("stopped_elapsed", _number),
        )
        _check_lengths(record, where)
        return record


def _check_lengths(record: RunRecord, where: str) -> None:
    """Refuse a record whose per-QoI fields disagree in length (a hand-edited or damaged record: the report indexed
    past their ends)."""
    n = len(record.tol)
    if n == 0 or (record.qoi_names is not None and len(record.qoi_names) != n):
        names = "" if record.qoi_names is None else f" ({len(record.qoi_names)}: {', '.join(record.qoi_names)})"
        _fail(f"{where}.tol", list(record.tol), f"one tolerance per QoI{names}")
    outcome = record.outcome
    if outcome is None:
        return
    per_qoi = ["bias_estimate", "rmse"]
    if record.method != "cdf":  # a CDF run's estimate and statistical error have one value per threshold
        per_qoi += ["estimate", "stat_error", *(key for key in _OUTCOME_MOMENTS if getattr(outcome, key) is not None)]
    elif len(outcome.stat_error) != len(outcome.estimate):
        _fail(f"{where}.stat_error", list(outcome.stat_error), f"{len(outcome.estimate)} values, one per threshold")
    for key in per_qoi:
        if len(getattr(outcome, key)) != n:
            _fail(f"{where}.{key}", list(getattr(outcome, key)), f"{n} values, one per QoI as in tol")
    if len(outcome.n_samples) != len(outcome.levels):
        _fail(f"{where}.n_samples", list(outcome.n_samples), f"{len(outcome.levels)} counts, one per level")


# ---------------------------------------------------------------------------
# Reading a store
# ---------------------------------------------------------------------------


def read_screening_record(store: Any) -> ScreeningRecord | None:
    """The screening of a study store (:class:`~rough_uq.study.store.StudyStore`), or None."""
    data = store.read_screening()
    return None if data is None else ScreeningRecord.from_json(data)


def read_run_records(store: Any) -> list[RunRecord]:
    """Every run of a study store, in creation order."""
    return [RunRecord.from_json(data) for data in store.read_runs()]

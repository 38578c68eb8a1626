"""Screening, MLMC and plain MC on a :class:`~rough_uq.problem.contact.ContactProblem`: the Python front door.

:func:`screen`, :func:`mlmc` and :func:`mc` run the statistics and drivers of
:mod:`rough_uq.multilevel` on a contact problem, in this process by default
or on an executor (e.g. :mod:`rough_uq.study.executors`); nothing is written
to disk.

Random streams
--------------
Every sample is computed from ``SeedSequence(seed, spawn_key=(stage, level,
index))`` (SPEC section 7, :func:`~rough_uq.problem.sampler.sample_rng`).
Screening samples have stage :data:`~rough_uq.problem.batch.STAGE_SCREENING`;
an MLMC or MC run has the stage of its name (:func:`run_id`,
:func:`~rough_uq.problem.sampler.run_stage`), which depends on the method, the
QoI names, the tolerances, ``theta``, the MC level and Richardson
extrapolation, exactly as for ``roughuq mlmc`` / ``roughuq mc``. The same
problem and settings therefore draw the same samples here and in the CLI. (The
CLI measures FFT plans per machine, this module plans with ``FFTW_ESTIMATE``:
the numbers agree to rounding, not bit for bit.)
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import (
    EstimationError, InvalidParameterError, checked_bool, checked_integer, checked_real_array, is_integer,
    is_real_number, warn_at_caller,
)
from rough_uq.multilevel import drivers
from rough_uq.multilevel.allocation import (
    Plan, check_fraction, mc_run_cost, plan, reachable_tolerance, unreachable_columns,
)
from rough_uq.multilevel.distribution import BANDWIDTH_TOO_WIDE, THRESHOLDS_MISS_SAMPLES
from rough_uq.multilevel.drivers import MAX_PLANNED_SAMPLES, EstimationResult
from rough_uq.multilevel.rates import EXACT_RATE, Rates, fit_rates, stalled_bias, stalled_text
from rough_uq.multilevel.statistics import (
    KURTOSIS_LIMIT,
    EstimationWarning,
    LevelStatistics,
    diagnose,
    level_statistics,
    values_summary,
)
from rough_uq.problem.batch import STAGE_SCREENING, LevelBatch
from rough_uq.problem.contact import BatchExecutor, ContactProblem, ContactSampler, ProgressReporter
from rough_uq.problem.columns import column_of_load, split_column, tol_number, tol_text, values_text
from rough_uq.problem.sampler import (
    ContactModel, cost_rate_beyond, measured_seconds_per_cost, modelled_cost, run_stage,
)

__all__ = [
    "MIN_SCREENED_LEVELS", "RunForecast", "ScreeningResult", "contact_gamma_beyond", "contact_planning_rates",
    "exact_column_caveats", "mc", "mlmc", "run_id", "screen",
    "screening_of_batches", "unreachable_text",
]
# Also imported by rough_uq.problem.distribution (variance and distribution runs), not part of the API:
# checked_problem, checked_tolerances, reporting_progress, warn_not_converged, warn_not_met.

#: Fewest levels a screening covers, ``0..2``: the rates are fitted on levels >= 1 (level 0's ``Y_0 = Q_0``
#: follows none of their models) and a line needs two of them. The config's ``screening.levels`` says the same.
MIN_SCREENED_LEVELS = 3


def run_id(
    method: str,
    names: Sequence[str],
    tol: np.ndarray,
    theta: float,
    level: int | None = None,
    *,
    richardson: bool = False,
) -> str:
    """Name of the run of ``method`` at tolerances ``tol`` and bias share ``theta`` (MC: on ``level``, if given).

    The same settings give the same name, hence the same random stage
    (:func:`~rough_uq.problem.sampler.run_stage`): the CLI resumes a run by
    rerunning its command, and :func:`mlmc` / :func:`mc` draw the samples the
    CLI draws. A Richardson-extrapolated MLMC run ends in ``_richardson``.
    """
    theta = check_fraction("theta", theta)  # the first use of a caller's theta: refuse a bad one by name
    # A load-curve column "contact_area@0.05" appears as "contact_area-at-0.05" (and "@1e+16" as "-at-1e16"):
    # run names are file-safe.
    names = [name.replace("@", "-at-").replace("+", "") for name in names]
    parts = [method] + [f"{name}-{_tag(eps)}" for name, eps in zip(names, tol)] + [f"theta-{_tag(theta)}"]
    if level is not None:
        parts.append(f"level-{level}")
    if richardson and method == "mlmc":
        parts.append("richardson")
    return "_".join(parts)


def _tag(value: float) -> str:
    """``value`` in a run name: ``%.6g`` without the ``+`` of a large exponent (``1e+06`` -> ``1e06``), or
    ``%.12g`` where six digits do not give it back (:func:`~rough_uq.problem.columns.tol_number`).

    Every name that had no ``+`` stays as it was, and with it its random stage; ``%.6g`` alone named
    ``--tol 0.25`` and ``--tol 0.2500001`` alike: two runs, one name, one record, one stream of samples.
    """
    return tol_number(value).replace("+", "")


@dataclass(frozen=True, eq=False)
class ScreeningResult:
    """What a screening measured (:func:`screen`).

    Attributes
    ----------
    statistics : LevelStatistics
        Per-level statistics; QoI arrays of shape ``(n_levels, n_qoi)``, costs
        in reference seconds (modelled).
    rates : Rates
        ``alpha``, ``beta`` (shape ``(n_qoi,)``) and ``gamma`` fitted on levels >= 1.
    n_not_converged : int
        Samples with a solve that did not converge (kept).
    diagnostics : tuple of str
        Failed checks of :func:`~rough_uq.multilevel.statistics.diagnose`
        (consistency, kurtosis, coupling), in words; empty when all pass.
    problem : ContactProblem or None
        The problem screened; :func:`mlmc` and :func:`mc` refuse the
        screening for a problem that differs in more than
        :data:`SCREENING_FREE_FIELDS`.
    seconds_per_cost : float or None
        Measured CPU-seconds per reference second of modelled cost, the median over the samples (as ``roughuq
        screen`` measures it); None where not measured. :meth:`forecast` converts with it.
    """

    statistics: LevelStatistics
    rates: Rates
    n_not_converged: int
    diagnostics: tuple[str, ...]
    problem: ContactProblem | None = None
    seconds_per_cost: float | None = None

    def forecast(self, tol: object, *, theta: float = 0.5, richardson: bool = False,
                 max_level: int | None = None) -> RunForecast:
        """What :func:`mlmc` with this screening will draw first and cost, before any sample (as ``roughuq mlmc``
        forecasts).

        ``tol``, ``theta`` and ``richardson`` as in :func:`mlmc`. The plan is the one the run starts from (the
        rates floored as it floors them, with the problem's cost rate beyond the screened levels:
        :func:`contact_planning_rates`); the run then
        adapts it to its own samples. ``max_level`` (default the screened problem's) forecasts the run of the
        problem with that ``max_level`` (``dataclasses.replace(problem, max_level=...)``, which the same
        screening serves, as the refusal of an unreachable tolerance suggests). Raises
        :class:`~rough_uq.errors.EstimationError` where the screening's bias does not decay (:func:`mlmc`
        cannot choose a finest level then).
        """
        problem = self.problem
        if problem is None:
            raise InvalidParameterError("problem", None, "the screening's ContactProblem (a result of screen())")
        if max_level is not None:
            problem = dataclasses.replace(problem, max_level=max_level)  # checked as the problem checks it
            drivers.check_finest_levels(2, problem.max_level, least_max_level=2)
        tol = checked_tolerances(tol, problem.n_qoi, problem.columns)
        theta = check_fraction("theta", theta)
        richardson = checked_bool("richardson", richardson)  # bool("no") is True
        _refuse_stalled_bias(problem.columns, self.rates, self.statistics)
        planned = contact_planning_rates(problem.model, self.statistics, problem.max_level)
        initial = drivers.starting_plan(tol=tol, rates=planned, statistics=self.statistics, theta=theta,
                                        max_level=problem.max_level, richardson=richardson, qoi_names=problem.columns)
        counts, costs = drivers.starting_forecast(initial, planned)
        cost = float(np.dot(counts, costs))
        mc_cost = mc_run_cost(_screened_mc_plan(problem, self, self.statistics, tol, theta))
        per_cost = self.seconds_per_cost
        return RunForecast(
            n_samples=np.array(counts), cost=cost, mc_cost=mc_cost, is_bias_met=bool(initial.is_bias_met),
            bias=np.asarray(initial.bias, dtype=float), reachable_tol=reachable_tolerance(initial, tol),
            cpu_seconds=None if per_cost is None else cost * per_cost,
            mc_cpu_seconds=None if per_cost is None else mc_cost * per_cost,
        )

    @property
    def levels(self) -> np.ndarray:
        """Screened levels, shape ``(n_levels,)``."""
        return self.statistics.levels

    @property
    def n_samples(self) -> np.ndarray:
        """Samples per screened level, shape ``(n_levels,)``."""
        return self.statistics.n_samples

    def __repr__(self) -> str:
        # A summary for notebooks and print(): the per-level arrays (some 40 lines) stay in ``statistics``.
        rates = self.rates
        return (
            f"ScreeningResult(levels={self.levels.tolist()}, n_samples={self.n_samples.tolist()}, "
            f"alpha={_rounded(rates.alpha)}, beta={_rounded(rates.beta)}, gamma={rates.gamma:.3g}, "
            f"n_not_converged={self.n_not_converged}, diagnostics={self.diagnostics!r})"
        )


@dataclass(frozen=True, eq=False)
class RunForecast:
    """What an MLMC run from a screening will draw first and cost (:meth:`ScreeningResult.forecast`).

    Attributes
    ----------
    n_samples : ndarray of int, shape (n_levels,)
        Samples per level ``0..L`` the run asks for first: 0 on the coarse levels the screening drops, 2 on the
        levels it adds to fit its rates.
    cost, mc_cost : float
        Modelled cost of those samples, and of plain MC to the same tolerance (reference seconds).
    cpu_seconds, mc_cpu_seconds : float or None
        The same in CPU-seconds at the screening's measured CPU-seconds per reference second (None for a
        screening that did not measure them).
    is_bias_met : bool
        False where the screening predicts a bias above ``sqrt(theta) tol`` on the problem's ``max_level``:
        :func:`mlmc` refuses such a tolerance (as ``roughuq mlmc`` does), with the smallest reachable one.
    bias : ndarray, shape (n_qoi,)
        The bias the screening predicts on the plan's finest level (on ``max_level`` where not ``is_bias_met``).
    reachable_tol : ndarray, shape (n_qoi,)
        The smallest tolerance whose bias share that bias meets where ``tol`` does not (two significant digits,
        rounded up), ``tol`` where it does: what :func:`mlmc`'s refusal proposes.
    """

    n_samples: np.ndarray
    cost: float
    mc_cost: float
    cpu_seconds: float | None
    mc_cpu_seconds: float | None
    is_bias_met: bool
    bias: np.ndarray
    reachable_tol: np.ndarray

    @property
    def levels(self) -> np.ndarray:
        """Levels ``0..L`` of :attr:`n_samples`."""
        return np.arange(len(self.n_samples))

    def __repr__(self) -> str:
        # The levels with their counts, and the costs to three digits, as `roughuq mlmc --plan` prints a plan.
        def seconds(value: float | None) -> str:
            return "None" if value is None else f"{value:.3g}"

        # An unreachable tolerance: the bias that blocks it and the smallest reachable one, as mlmc refuses it.
        unreachable = "" if self.is_bias_met else (
            f", bias={values_summary(self.bias)}, reachable_tol={values_summary(self.reachable_tol)}"
        )
        return (
            f"RunForecast(levels={self.levels.tolist()}, n_samples={self.n_samples.tolist()}, "
            f"cost={self.cost:.3g}, mc_cost={self.mc_cost:.3g}, cpu_seconds={seconds(self.cpu_seconds)}, "
            f"mc_cpu_seconds={seconds(self.mc_cpu_seconds)}, is_bias_met={self.is_bias_met}{unreachable})"
        )


def _rounded(values: np.ndarray) -> list[float]:
    """Three significant digits of each value, for a summary."""
    return [float(f"{value:.3g}") + 0.0 for value in np.asarray(values, dtype=float)]  # + 0.0: no -0.0


def checked_problem(problem: object) -> ContactProblem:
    if not isinstance(problem, ContactProblem):
        raise InvalidParameterError("problem", problem, "a rough_uq.ContactProblem")
    return problem


def screen(
    problem: ContactProblem, *, levels: int = 3, samples: int = 20, executor: BatchExecutor | None = None,
    progress: ProgressReporter | None = None,
) -> ScreeningResult:
    """Screening: ``samples`` coupled samples on each of levels ``0..levels-1``, per-level statistics and rates.

    The samples are those of ``roughuq screen`` with the same settings
    (stage :data:`~rough_uq.problem.batch.STAGE_SCREENING`, indices ``0..samples-1``).

    Parameters
    ----------
    problem : ContactProblem
    levels : int
        Number of levels screened, >= :data:`MIN_SCREENED_LEVELS` = 3
        (default 3, as the config's) and at most ``problem.max_level + 1``:
        the rates are fitted on levels >= 1, two of them at least. A problem
        with ``max_level < 2`` cannot be screened (:func:`mc` on a given
        ``level``, :func:`~rough_uq.variance` and :func:`~rough_uq.distribution`
        need no screening).
    samples : int
        Samples per level, >= 2 (default 20).
    executor : BatchExecutor, optional
        Where samples are computed; default in this process.
    progress : ProgressReporter, optional
        As in :func:`mlmc`.

    Returns
    -------
    ScreeningResult

    Raises
    ------
    InvalidParameterError
        ``levels`` or ``samples`` out of range.
    EstimationError
        The rates cannot be fitted (e.g. every ``E[Y_l]`` is 0).
    """
    problem = checked_problem(problem)
    why = "the rates are fitted on levels >= 1, two of them at least"
    if problem.max_level + 1 < MIN_SCREENED_LEVELS:
        raise InvalidParameterError(
            "max_level", problem.max_level, f"an integer >= {MIN_SCREENED_LEVELS - 1} to screen: a screening needs "
            f"levels 0..{MIN_SCREENED_LEVELS - 1} ({why}); without a screening use mc(level=...), variance or "
            "distribution",
        )
    if not (is_integer(levels) and levels >= MIN_SCREENED_LEVELS):
        raise InvalidParameterError("levels", levels, f"an integer >= {MIN_SCREENED_LEVELS} ({why})")
    levels = int(levels)
    if levels > problem.max_level + 1:
        raise InvalidParameterError(
            "levels", levels, f"at most max_level + 1 = {problem.max_level + 1} (levels 0..{problem.max_level} exist)"
        )
    samples = checked_integer("samples", samples, 2)
    if samples * levels > drivers.MAX_PLANNED_SAMPLES:  # samples=10**11 allocated their indices first
        raise InvalidParameterError(
            "samples", samples, f"an integer in 2..{drivers.MAX_PLANNED_SAMPLES // levels} (a screening of {levels} "
            f"levels; at most {drivers.MAX_PLANNED_SAMPLES:,} samples in all, as any run plans)",
        )
    sampler = problem.sampler(STAGE_SCREENING, executor=executor, progress=progress, least_level=2)
    indices = np.arange(samples, dtype=np.int64)
    with reporting_progress(sampler, "screening"):
        if sampler.progress is not None:
            sampler.progress.plan(list(range(levels)), [samples] * levels, [0] * levels)
        batches = [sampler.batch(level, indices) for level in range(levels)]
    return screening_of_batches(problem, batches, n_not_converged=sampler.n_not_converged)


def screening_of_batches(
    problem: ContactProblem, batches: Sequence[LevelBatch], *, n_not_converged: int
) -> ScreeningResult:
    """The :class:`ScreeningResult` of screening samples: one batch per level ``0, 1, ...``, the same indices.

    What :func:`screen` returns for the samples it drew; also how a study file's screening is read
    (:func:`rough_uq.study.pipeline.load_screening`).
    """
    statistics = level_statistics(
        fine=[b.fine for b in batches],
        coarse=[b.coarse for b in batches],
        cost=[modelled_cost(problem.model, b.level, b.n_iter) for b in batches],
        levels=[b.level for b in batches],
    )
    rates = fit_rates(statistics, names=problem.columns)
    return ScreeningResult(
        statistics=statistics,
        rates=rates,
        n_not_converged=n_not_converged,
        diagnostics=(
            *diagnose(statistics, names=problem.columns), *_stalled_bias(problem.columns, rates, statistics),
            *exact_column_caveats(problem.model, problem.columns, rates, statistics),
        ),
        problem=problem,
        seconds_per_cost=measured_seconds_per_cost(batches, problem.model),
    )


def exact_column_caveats(
    model: ContactModel, names: Sequence[str], rates: Rates, statistics: LevelStatistics
) -> list[str]:
    """The caveat of columns exact on the screened levels (rates :data:`~rough_uq.multilevel.rates.EXACT_RATE`)
    whose grids do not resolve the surface: a grid that truncates the spectrum sees a smoother surface, which
    reaches full contact at a lower load, so a finer grid may differ where these did not ([] otherwise)."""
    exact = [name for name, alpha in zip(names, rates.alpha) if alpha == EXACT_RATE]
    n = model.grid(int(statistics.levels[-1]))
    k_s = model.spectrum.k_s
    if not exact or n > 2 * k_s:
        return []
    return [
        f"{', '.join(exact)}: every level difference is 0 on the screened grids up to {n}^2, so they are planned "
        f"with no bias and no level variance; these grids do not resolve the surface (k_s = {k_s:g} needs a grid "
        f"above {2 * k_s:g}), and a finer grid may differ: screen finer levels to check"
    ]


#: What a refusal of a bias that does not decay advises (the forecast gave none, mlmc this).
_STALLED_ADVICE = "; screen finer grids (a larger coarsest), or use mc(level=...) (bias not estimated)"


def _refuse_stalled_bias(
    columns: Sequence[str], rates: Rates, statistics: LevelStatistics, advice: str = _STALLED_ADVICE
) -> None:
    """Raise :class:`~rough_uq.errors.EstimationError` if the screening's bias of a column does not decay.

    ``advice`` ends the message (``"; ..."``).
    """
    stalled = stalled_bias(columns, rates, statistics)
    if stalled:
        raise EstimationError(f"{stalled_text(stalled)}, so no level can be chosen for a tolerance{advice}")


def _fitted_rates(problem: ContactProblem, screening, statistics: LevelStatistics) -> Rates:
    """The screening's fitted rates: a :class:`ScreeningResult`'s, or fitted on ``statistics`` (warnings hushed:
    the screening reported them)."""
    if isinstance(screening, ScreeningResult):
        return screening.rates
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EstimationWarning)
        return fit_rates(statistics, names=problem.columns)


def _stalled_bias(columns: Sequence[str], rates: Rates, statistics: LevelStatistics) -> tuple[str, ...]:
    """The screening's diagnostic for QoIs whose bias does not decay (``roughuq screen`` warns, ``mlmc`` refuses)."""
    stalled = stalled_bias(columns, rates, statistics)
    if not stalled:
        return ()
    return (f"{stalled_text(stalled)}, so "
            "no finest level can be chosen from this screening (roughuq mlmc refuses it); screen finer grids "
            "(a larger coarsest), or use mc(level=...) (bias not estimated)",)


def checked_tolerances(tol: object, n_qoi: int, columns: Sequence[str] | None = None) -> np.ndarray:
    """``tol`` as one tolerance per QoI: a number (for all), a sequence of ``n_qoi`` numbers, or (``columns``
    given) a mapping by column.

    A sequence of another length is refused, one number in a list too: ``[0.5]`` for two QoIs read as one per
    QoI in column order and was applied to both.
    """
    if columns is not None and isinstance(tol, Mapping):
        tol = _values_by_name("tol", tol, columns, noun="tolerance", positive=True)
    per_qoi = "one per QoI" if columns is None else f"one per QoI column: {', '.join(columns)}"
    sequence = f"a sequence of {n_qoi} ({per_qoi}, in its unit)" if n_qoi > 1 else f"a sequence of one ({per_qoi})"
    by_name = "" if columns is None else ", or a mapping of every QoI column to one"
    allowed = f"a number > 0 (for every QoI), {sequence}{by_name}"
    values = checked_real_array("tol", tol, allowed)  # numbers only: ["0.5"] and [True] were converted
    if values.ndim == 0 or values.shape == (n_qoi,):
        values = np.broadcast_to(values.reshape(-1), (n_qoi,)).copy()
        bad = np.flatnonzero(~(np.isfinite(values) & (values > 0)))
        if bad.size == 0:
            return values
        if values.size > 1 and np.ndim(tol) == 1:  # "a sequence of 4" said nothing of which one of the 4 is bad
            i = int(bad[0])
            column = "" if columns is None else f" (column {columns[i]})"
            raise InvalidParameterError(f"tol[{i}]", float(values[i]), f"a finite number > 0{column}")
    raise InvalidParameterError("tol", tol, allowed)


def _values_by_name(name: str, values: Mapping, columns: Sequence[str], *, noun: str, positive: bool) -> list:
    """The values of the mapping ``values`` (parameter ``name``) in column order, by column or by QoI (as
    ``--tol NAME=EPS``).

    A QoI's name gives all its columns of a load curve (``contact_area`` for
    ``contact_area@0.1`` and ``contact_area@0.2``); a column's own name takes
    precedence. Every column must get one, and no other key may be there.
    Each value is a finite number, ``> 0`` if ``positive``; ``noun`` names one in messages ("tolerance"). A
    column's load may be written as ``column=`` takes it (``contact_area@0.10`` for ``contact_area@0.1``).
    """
    values = _keys_as_columns(name, values, columns)
    qois = {column: split_column(column)[0] for column in columns}
    known = set(columns) | set(qois.values())
    unknown = [key for key in values if key not in known]
    if unknown:
        raise InvalidParameterError(name, f"key {unknown[0]!r}", f"QoI or column names: {', '.join(sorted(known))}")
    keys = [column if column in values else qois[column] for column in columns]
    missing = [column for column, key in zip(columns, keys) if key not in values]
    if missing:
        every = f"one {noun} for every QoI column ({', '.join(columns)})"
        raise InvalidParameterError(name, f"no {noun} for {', '.join(missing)}", every)
    allowed = f"a finite number{' > 0' if positive else ''} for every key"
    for key in keys:
        value = values[key]
        if not (is_real_number(value) and math.isfinite(value) and (value > 0 or not positive)):
            raise InvalidParameterError(name, f"{key}: {value!r}", allowed)
    return [values[key] for key in keys]


def _keys_as_columns(name: str, values: Mapping, columns: Sequence[str]) -> dict:
    """``values`` with each key that names a load column written as the column is (:func:`column_of_load`); two keys
    of one column are refused (``contact_area@0.1`` and ``contact_area@0.10``)."""
    spelled: dict = {}
    for key, value in values.items():
        column = column_of_load(key, columns) if isinstance(key, str) else key
        column = column if column in columns else key  # an unknown key is refused as typed
        if column in spelled:
            raise InvalidParameterError(name, f"keys {spelled[column][0]!r} and {key!r}", f"one key for {column}")
        spelled[column] = (key, value)
    return {column: value for column, (_, value) in spelled.items()}


#: The fields of a :class:`ContactProblem` in which a run's problem may differ from the problem its screening
#: screened: they do not change the distribution of a level's samples. Any other difference that changes the
#: samples (grids, load, surface, QoIs and units, solver) makes the screening's level statistics, which a run
#: pools and plans with, another problem's; settings no QoI uses (``connectivity`` without ``clusters``, ...)
#: and spellings of the same problem (a load or a list of one, a default unit written out) do not count.
SCREENING_FREE_FIELDS = ("seed", "max_level", "threads")

#: The :class:`ContactProblem` field that sets each field of its sample model, where the names differ.
_PROBLEM_FIELD = {"mean_pressure": "load", "mean_pressures": "load", "qoi_names": "qoi", "qoi_scales": "units",
                  "tol": "solver_tol"}


def _screening_of(problem: ContactProblem, screening: object) -> LevelStatistics | None:
    """The statistics of ``screening`` (None without one); refused if of another number of QoIs or another problem."""
    statistics = _screening_statistics(screening)
    if statistics is None:
        return None
    _check_qoi_count(problem, "screening", statistics.n_qoi)
    screened = getattr(screening, "problem", None)
    if screened is None:
        return statistics
    ours, theirs = _sample_identity(problem), _sample_identity(screened)
    differing = dict.fromkeys(_PROBLEM_FIELD.get(f.name, f.name) for f in dataclasses.fields(ours)
                              if f.compare and getattr(ours, f.name) != getattr(theirs, f.name))
    if differing:
        raise InvalidParameterError(
            "screening", f"a screening of another problem (it differs in {', '.join(differing)})",
            f"a screening of this problem, rough_uq.screen(problem) (it may differ in "
            f"{', '.join(SCREENING_FREE_FIELDS)} only)",
        )
    return statistics


def _sample_identity(problem: ContactProblem):
    """What decides the distribution of ``problem``'s samples: its sample model without seed and threads, and
    without the settings of QoIs it does not compute."""
    model = problem.model
    qoi = set(model.qoi_names)
    return dataclasses.replace(
        model, seed=0, threads=1,
        connectivity=model.connectivity if "clusters" in qoi else 4,
        critical_pressure=model.critical_pressure if "area_above" in qoi else None,
        area_estimator=model.area_estimator if "contact_area" in qoi else "corrected",
    )


def _screening_statistics(screening: object) -> LevelStatistics | None:
    if screening is None or isinstance(screening, LevelStatistics):
        return screening
    if isinstance(screening, ScreeningResult):
        return screening.statistics
    raise InvalidParameterError("screening", screening, "a ScreeningResult (rough_uq.screen), LevelStatistics or None")


def _check_qoi_count(problem: ContactProblem, name: str, n_qoi: int) -> None:
    """Refuse a screening or rates (``name``) of another number of QoIs than ``problem``'s, before any sample."""
    if n_qoi != problem.n_qoi:
        raise InvalidParameterError(
            name, f"{name} of {n_qoi} QoIs", f"{name} of the problem's QoIs: it has {n_qoi} QoIs, the problem "
            f"{problem.n_qoi}",
        )


def warn_not_converged(sampler: ContactSampler, method: str) -> int:
    """Warn of the run's samples whose solve did not converge; returns their number (for the result)."""
    if sampler.n_not_converged:
        warn_at_caller(
            f"{method}: {sampler.n_not_converged} of {sampler.n_samples} samples had a solve that did not converge "
            "(kept with the QoIs of the last iterate); raise max_iter or solver_tol",
            EstimationWarning,
        )
    return int(sampler.n_not_converged)


#: What to change when a run stops with this ``stop_reason`` and its tolerance not met (the CLI's advice, in
#: the Python API's arguments).
_NOT_MET_ADVICE = {
    "max_level": "the bias needs a grid finer than the problem's max_level: loosen tol or raise max_level",
    "max_cost": "the run reached max_cost: raise max_cost or loosen tol",
    "bias": "the bias on this level exceeds the tolerance's share: loosen tol, sample a finer level or use mlmc",
    THRESHOLDS_MISS_SAMPLES: ("the thresholds miss the samples of a level (see the warning): put thresholds "
                                "among the values or raise n_initial"),
    BANDWIDTH_TOO_WIDE: ("the smoothing bandwidth exceeds twice the spread of the values (see the warning): give a "
                         "smaller bandwidth, or finer thresholds (the default bandwidth is twice their spacing)"),
}


def warn_not_met(method: str, names: Sequence[str] | None, result, tol, *, advice: str | None = None) -> None:
    """An :class:`EstimationWarning` when a run ended with its tolerance not met (``roughuq`` exits 3 then).

    A notebook user reading ``estimate`` and ``rmse`` was not told (only ``tol_met`` said so). ``result``: an
    :class:`EstimationResult`, ``TargetEstimate`` or ``CdfEstimate`` (its ``tol_met``, ``stop_reason``,
    ``rmse``, ``is_bias_estimated``). ``names``: of the columns of ``rmse`` and ``tol``; None for one error
    without a column (a distribution function's). ``advice`` replaces the advice of the stop reason
    (:data:`_NOT_MET_ADVICE`).
    """
    if result.tol_met:
        return
    stop_reason, is_bias_estimated = result.stop_reason, result.is_bias_estimated
    # Plain MC on a given level never estimates its bias: its statistical error must be within its share.
    is_level_mc = getattr(result, "method", None) == "mc" and not is_bias_estimated
    if advice is None and stop_reason == "max_cost" and not is_bias_estimated and not is_level_mc:
        advice = "the run reached max_cost before its bias was estimated: raise max_cost or lower n_initial"
    if advice is None and stop_reason == "max_level" and getattr(result, "noisy_bias_groups", ()):
        advice = ("the bias estimate rests on level terms within their noise (see the warning): raise n_initial "
                  "to measure it, loosen tol or raise max_level")
    if advice is None:
        advice = _NOT_MET_ADVICE.get(stop_reason, "loosen tol, or raise max_cost or max_level")
    rmse, tol = np.atleast_1d(result.rmse), np.atleast_1d(tol)
    if names is None:
        errors, tolerances = ", ".join(f"{e:.3g}" for e in rmse), ", ".join(f"{e:g}" for e in tol)
    else:
        errors, tolerances = values_text(names, rmse), tol_text(names, tol)
    if stop_reason == THRESHOLDS_MISS_SAMPLES:
        errors = "not measured"  # from variances of 0 (rough_uq.multilevel.distribution)
    unestimated = "" if is_bias_estimated else " (bias not estimated)"
    if is_level_mc:
        share = math.sqrt(1.0 - result.theta)
        shares = values_text(names, share * tol) if names is not None else ", ".join(f"{e:.3g}" for e in share * tol)
        text = f"statistical error {errors} against its share sqrt(1 - theta) tol = {shares} of tol {tolerances}"
    else:
        text = f"RMSE {errors}{unestimated} against tol {tolerances}"
    warn_at_caller(f"{method}: tolerance not met ({stop_reason}): {text}; {advice}", EstimationWarning)


def mlmc(
    problem: ContactProblem,
    *,
    tol: float | Sequence[float] | Mapping[str, float] | np.ndarray,
    theta: float = 0.5,
    screening: ScreeningResult | LevelStatistics | None = None,
    richardson: bool = False,
    n_initial: int = 10,
    min_finest_level: int = 2,
    max_cost: float | None = None,
    max_samples: int | None = MAX_PLANNED_SAMPLES,
    batch_size: int | None = 10,
    rates: Rates | None = None,
    kurtosis_limit: float = KURTOSIS_LIMIT,
    executor: BatchExecutor | None = None,
    progress: ProgressReporter | None = None,
) -> EstimationResult:
    """Adaptive MLMC estimate of ``E[Q]`` of a contact problem to RMS tolerance ``tol``.

    Giles' algorithm (:func:`rough_uq.multilevel.drivers.adaptive.iter_mlmc`) on levels
    up to ``problem.max_level``. Without ``screening`` it starts on levels
    ``0..min_finest_level`` with ``n_initial`` samples each; with one (what
    ``roughuq mlmc`` does) it starts from the screening's plan, pools its
    variances and drops coarse levels that do not pay
    (:func:`~rough_uq.multilevel.rates.choose_coarsest_level`). The random
    stage is that of ``roughuq mlmc`` with the same QoIs, ``tol``, ``theta``
    and ``richardson`` (module docstring).

    Parameters
    ----------
    problem : ContactProblem
    tol : float, sequence of float or mapping of str to float
        Tolerance ``eps`` on the root-mean-square error, one for all QoIs or
        one per QoI (in column order, or by column name, e.g.
        ``{"contact_area": 0.5, "clusters": 50}``), in the QoIs' units (e.g.
        percent of contact area).
    theta : float
        Bias share of ``eps^2``, in (0, 1).
    screening : ScreeningResult or LevelStatistics, optional
        A screening of the same problem (:func:`screen`); a ScreeningResult of another problem is refused, a
        LevelStatistics (no problem to compare) is taken on the caller's word.
    richardson : bool
        Richardson-extrapolate the finest level where the level means allow
        it (refused with a reason in the result otherwise).
    n_initial, min_finest_level, max_cost, batch_size, rates, kurtosis_limit
        As in :func:`rough_uq.multilevel.drivers.adaptive.iter_mlmc`; ``max_cost`` and
        costs are modelled reference seconds. Defaults are the config's.
    max_samples : int or None
        A plan with more samples in all (default
        :data:`~rough_uq.multilevel.drivers.adaptive.MAX_PLANNED_SAMPLES`, as ``roughuq``
        refuses) raises :class:`~rough_uq.errors.EstimationError` before its
        samples are drawn: the tolerance is out of reach. None: no limit.
    executor : BatchExecutor, optional
        Where samples are computed; default in this process.
    progress : ProgressReporter, optional
        Told of the run's start, plan, every sample done and its end, e.g.
        :class:`rough_uq.study.progress.PlainProgress` (a line per level every
        10 s, for a notebook or a log) or ``RichProgress`` (bars on a
        terminal); default: silent.

    Returns
    -------
    EstimationResult
        ``estimate``, ``stat_error``, ``bias_estimate``, ``rmse`` of shape
        ``(n_qoi,)`` in the QoIs' units; ``levels`` and ``n_samples`` of shape
        ``(n_levels,)``; ``cost`` in reference seconds.

    Raises
    ------
    EstimationError
        A plan of more than ``max_samples`` samples (see above); with a ``screening``, a tolerance whose bias it
        predicts above ``sqrt(theta) tol`` on ``max_level`` (the message gives the smallest reachable one), or a
        bias that does not decay, before any sample (as ``roughuq mlmc`` refuses them).

    Warns
    -----
    EstimationWarning
        For failed diagnostics of the run, for samples whose solve did not converge, for a tolerance not met
        (its RMSE, the stop reason and what to change, as ``roughuq`` exits 3) and for a Richardson
        extrapolation refused (the run is then plain MLMC; ``richardson_reason`` says why).
    """
    problem = checked_problem(problem)
    tol = checked_tolerances(tol, problem.n_qoi, problem.columns)
    richardson = checked_bool("richardson", richardson)
    max_samples = _max_samples(max_samples)
    # Before the screening's plan, which reads them (iter_mlmc checks them again).
    drivers.check_finest_levels(min_finest_level, problem.max_level, least_max_level=2)
    statistics = _screening_of(problem, screening)
    if isinstance(rates, Rates):
        _check_qoi_count(problem, "rates", rates.n_qoi)
    elif statistics is not None:  # as roughuq mlmc: no finest level can be planned from a bias that grows
        _refuse_stalled_bias(problem.columns, _fitted_rates(problem, screening, statistics), statistics)
    if statistics is not None:  # as roughuq mlmc: a bias the screening predicts beyond max_level is refused
        starting_rates = rates if isinstance(rates, Rates) else contact_planning_rates(
            problem.model, statistics, problem.max_level)
        _refuse_unreachable(problem, tol, drivers.starting_plan(
            tol=tol, rates=starting_rates, statistics=statistics, theta=theta, max_level=problem.max_level,
            richardson=richardson, min_finest_level=min_finest_level, qoi_names=problem.columns), statistics,
            method="mlmc")
    stage = run_stage("mlmc", run_id("mlmc", problem.columns, tol, theta, richardson=richardson))
    sampler = problem.sampler(stage, executor=executor, progress=progress, least_level=min_finest_level)
    events = drivers.iter_mlmc(
        sampler,
        tol=tol,
        theta=theta,
        n_initial=n_initial,
        min_finest_level=min_finest_level,
        max_level=problem.max_level,
        max_cost=max_cost,
        batch_size=batch_size,
        screening=statistics,
        rates=rates,
        kurtosis_limit=kurtosis_limit,
        richardson=richardson,
        coarsest_level=None if statistics is not None else 0,
        qoi_names=problem.columns,
        gamma_beyond=None if statistics is None else contact_gamma_beyond(problem.model, statistics, problem.max_level),
    )
    with reporting_progress(sampler, f"mlmc {tol_text(problem.columns, tol)}"):
        result = _run_to_end(events, max_samples=max_samples, tol=tol,
                             n_initial=n_initial if statistics is None else None, progress=sampler.progress)
    result = dataclasses.replace(result, n_not_converged=warn_not_converged(sampler, "mlmc"),
                                 units=problem.column_units)
    warn_not_met("mlmc", problem.columns, result, tol)
    screened = None if statistics is None else _screened_mc_cost(problem, screening, statistics, tol, theta)
    return result if screened is None else dataclasses.replace(result, mc_cost=screened)


def _refuse_unreachable(problem: ContactProblem, tol: np.ndarray, prediction: Plan,
                        statistics: LevelStatistics, *, method: str) -> None:
    """Raise :class:`~rough_uq.errors.EstimationError` where the screening predicts a bias above the tolerance's
    share on ``max_level`` (``prediction``: the run's first plan), before any sample, as ``roughuq mlmc`` / ``mc``
    refuse: such a run planned millions of samples to bring its statistical error within a tolerance its bias
    already missed."""
    if prediction.is_bias_met:
        return
    finest = problem.max_level
    raise EstimationError(unreachable_text(
        problem.columns, tol, prediction, tol_name="tol", level_name="max_level", max_level=finest,
        grid=problem.grid(finest), n_screened=int(np.min(statistics.n_samples)),
        advice=f"{_UNREACHABLE_ADVICE[method]}; or raise the problem's max_level (the same screening serves it; "
        "its forecast(tol, max_level=...) previews the run)",
    ))


def unreachable_text(names: Sequence[str], tol: np.ndarray, prediction: Plan, *, tol_name: str, level_name: str,
                     max_level: int, grid: int, n_screened: int, advice: str) -> str:
    """The refusal of a tolerance whose bias the finest allowed grid cannot reach, with the smallest reachable one
    (the Python API's and ``roughuq``'s, which name the tolerance and the finest level as each spells them)."""
    reachable = reachable_tolerance(prediction, tol)
    return (
        f"{tol_name} {tol_text(names, tol, digits=3)} cannot be reached{blocking_text(names, prediction, tol)}: on "
        f"the finest grid allowed ({level_name} = {max_level}, {grid}^2) the screening predicts a bias of "
        f"{values_text(names, np.asarray(prediction.bias, dtype=float))}; the smallest reachable tolerance is about "
        f"{tol_text(names, reachable, digits=3)}, a prediction from {n_screened} screened samples per level{advice}"
    )


def blocking_text(names: Sequence[str], prediction: Plan, tol: np.ndarray) -> str:
    """`` for clusters@0.1``: the columns whose predicted bias exceeds their share of ``tol``, where not all do
    (a load curve's refusal listed a reachable tolerance for every column and did not say which one blocked)."""
    blocked = unreachable_columns(prediction, tol)
    named = [name for name, is_blocked in zip(names, blocked) if is_blocked]
    return "" if np.all(blocked) or not named else " for " + ", ".join(named)


#: How :func:`_refuse_unreachable` goes on, by method.
_UNREACHABLE_ADVICE = {
    "mlmc": " (a run estimates the bias from its own samples and may find it larger)",
    "mc": ", which plain MC takes as its bias; or sample a level of your choice with level= (and bias=)",
}


def _screened_mc_cost(problem: ContactProblem, screening, statistics: LevelStatistics, tol: np.ndarray,
                      theta: float) -> float | None:
    """Plain MC's cost for ``tol`` as the screening predicts it, as ``roughuq mlmc`` reports it.

    None where the screening's bias model cannot choose a level (``roughuq mlmc`` refuses such a run; the
    result keeps the run's own prediction).
    """
    try:
        return mc_run_cost(_screened_mc_plan(problem, screening, statistics, tol, theta))
    except EstimationError:
        return None


def contact_gamma_beyond(model: ContactModel, statistics: LevelStatistics, max_level: int) -> float | None:
    """The contact problem's cost rate beyond the screened levels of ``statistics``, up to ``max_level``
    (:func:`~rough_uq.problem.sampler.cost_rate_beyond`; ``iter_mlmc``'s ``gamma_beyond``)."""
    return cost_rate_beyond(model, statistics.levels, statistics.mean_cost, max_level)


def contact_planning_rates(model: ContactModel, statistics: LevelStatistics, max_level: int) -> Rates:
    """The rates a run of a contact problem plans with from a screening: those of
    :func:`~rough_uq.multilevel.drivers.planning.planning_rates` with the problem's cost rate beyond the screened
    levels (:func:`~rough_uq.problem.sampler.cost_rate_beyond`) up to ``max_level``."""
    return drivers.planning_rates(statistics, gamma_beyond=contact_gamma_beyond(model, statistics, max_level))


def _screened_mc_plan(problem: ContactProblem, screening, statistics: LevelStatistics, tol: np.ndarray,
                      theta: float) -> Plan:
    """The plain MC run the screening plans for ``tol``: its level, bias and cost (``EstimationError`` where the
    screening's bias does not decay). Planned with the rates floored as MLMC runs plan
    (:func:`contact_planning_rates`), as ``roughuq mc`` does."""
    _refuse_stalled_bias(problem.columns, _fitted_rates(problem, screening, statistics), statistics)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EstimationWarning)  # the screening reported them
        planned = contact_planning_rates(problem.model, statistics, problem.max_level)
    return plan(tol=tol, rates=planned, statistics=statistics, theta=theta, max_level=problem.max_level,
                coarsest_level=None)


def _mc_level(problem: ContactProblem, tol: np.ndarray, theta: float, level, screening, bias):
    """The level plain MC samples and its bias: ``level`` if given, else the finest level of the screening's plan."""
    statistics = _screening_statistics(screening)
    if level is not None:
        level = checked_integer("level", level, 0)
        if level > problem.max_level:
            raise InvalidParameterError("level", level, f"an integer in 0..max_level = {problem.max_level}")
        return level, bias
    if statistics is None:
        raise InvalidParameterError("level", None, "a level to sample, or a screening to choose it from")
    try:
        prediction = _screened_mc_plan(problem, screening, statistics, tol, theta)
    except EstimationError as error:
        raise EstimationError(f"{error}; pass level= to sample a level of your choice") from error
    if bias is None:
        _refuse_unreachable(problem, tol, prediction, statistics, method="mc")
        return prediction.finest_level, prediction.bias
    return prediction.finest_level, bias


def _refuse_given_bias(columns: tuple[str, ...], tol: np.ndarray, theta: float, bias: np.ndarray) -> None:
    """Raise :class:`~rough_uq.errors.EstimationError` for a given bias above its share ``sqrt(theta) tol``.

    MC draws samples for the statistical share ``(1 - theta) tol^2`` of the tolerance and leaves ``theta tol^2``
    to the bias: with a larger bias the run ended ``"bias"``, not met, after drawing all of them in vain.
    """
    bias = np.broadcast_to(bias.reshape(-1), tol.shape)
    with np.errstate(over="ignore"):  # a bias of 1e300 squares to inf, which is compared as such (no warning)
        over = bias**2 > theta * tol**2 * (1 + 1e-12)
        if not np.any(over):
            return
        needed = float(np.max(bias[over] ** 2 / tol[over] ** 2))
    remedy = (f"raise theta (the bias's share of tol^2) to at least {needed:.3g}, or loosen tol" if needed < 1
              else "no theta does: loosen tol above the bias, or sample a finer level")
    raise EstimationError(
        f"mc: the given bias {values_text(columns, bias)} is above its share of the tolerance, sqrt(theta) tol = "
        f"{values_text(columns, np.sqrt(theta) * tol)} (theta = {theta:g}): the run would draw its samples and end "
        f"with tol {tol_text(columns, tol, digits=3)} not met; {remedy}"
    )


def _mc_advice(result: EstimationResult, n_initial: int) -> str | None:
    """What to change for an MC run that ``max_cost`` stopped (None otherwise: the advice of its stop reason).

    Plain MC estimates no bias, so not "before its bias was estimated"; before its first ``n_initial`` samples,
    a looser tolerance changes nothing.
    """
    if result.stop_reason != "max_cost":
        return None
    if int(np.sum(result.n_samples)) < n_initial:
        return "the run reached max_cost before its first n_initial samples: raise max_cost or lower n_initial"
    return _NOT_MET_ADVICE["max_cost"]


def mc(
    problem: ContactProblem,
    *,
    tol: float | Sequence[float] | Mapping[str, float] | np.ndarray,
    level: int | None = None,
    theta: float = 0.5,
    screening: ScreeningResult | LevelStatistics | None = None,
    bias: float | Sequence[float] | np.ndarray | Mapping[str, float] | None = None,
    n_initial: int = 10,
    max_cost: float | None = None,
    max_samples: int | None = MAX_PLANNED_SAMPLES,
    batch_size: int | None = 10,
    kurtosis_limit: float = KURTOSIS_LIMIT,
    executor: BatchExecutor | None = None,
    progress: ProgressReporter | None = None,
) -> EstimationResult:
    """Plain Monte Carlo estimate of ``E[Q_level]`` of a contact problem to RMS tolerance ``tol``.

    On ``level`` if given (``roughuq mc --level``: its bias is unknown unless
    ``bias`` is given; a ``screening`` given too has its variance of ``level``
    pooled in, which the CLI does not do); otherwise on the finest level the
    ``screening``'s plan needs for ``tol``, with the plan's bias (``roughuq
    mc``). The random stage is that of the same CLI command (module docstring).

    Parameters
    ----------
    problem : ContactProblem
    tol : float, sequence of float or mapping of str to float
        Tolerance ``eps`` on the root-mean-square error, one for all QoIs or
        one per QoI (in column order or by column name, as in :func:`mlmc`),
        in the QoIs' units.
    level : int, optional
        Level to sample, ``0..problem.max_level``; required without ``screening``.
    theta : float
        Bias share of ``eps^2``, in (0, 1).
    screening : ScreeningResult or LevelStatistics, optional
        A screening of the same problem (:func:`screen`); a ScreeningResult of another problem is refused, a
        LevelStatistics (no problem to compare) is taken on the caller's word.
    bias : float, sequence of float or mapping of str to float, optional
        Known bias of ``level`` (overrides the plan's), one for all QoIs or one per QoI (in column order or by
        column name, as ``tol``; its sign does not count), at most ``sqrt(theta) tol`` per column: the run draws
        samples for the statistical share ``(1 - theta) tol^2``, so a larger bias is refused before any sample
        (:class:`~rough_uq.errors.EstimationError`, with the ``theta`` that would take it).
    n_initial, max_cost, batch_size, kurtosis_limit
        As in :func:`rough_uq.multilevel.drivers.plain_mc.iter_mc`. Defaults are the config's.
    max_samples : int or None
        As in :func:`mlmc`.
    executor : BatchExecutor, optional
        Where samples are computed; default in this process.
    progress : ProgressReporter, optional
        As in :func:`mlmc`.

    Returns
    -------
    EstimationResult
        As :func:`mlmc`'s, with ``levels == [level]``.

    Raises
    ------
    EstimationError
        A plan of more than ``max_samples`` samples; without ``level``, a screening whose bias does not decay,
        and without ``bias`` too, a tolerance whose bias the screening predicts above ``sqrt(theta) tol`` on
        ``max_level`` (as ``roughuq mc`` refuses them).
    """
    problem = checked_problem(problem)
    tol = checked_tolerances(tol, problem.n_qoi, problem.columns)
    max_samples = _max_samples(max_samples)
    statistics = _screening_of(problem, screening)
    if isinstance(bias, Mapping):
        bias = _values_by_name("bias", bias, problem.columns, noun="bias", positive=False)
    given_bias = bias
    mc_level, bias = _mc_level(problem, tol, theta, level, screening, bias)
    stage = run_stage("mc", run_id("mc", problem.columns, tol, theta, level))
    sampler = problem.sampler(stage, executor=executor, progress=progress)
    events = drivers.iter_mc(
        sampler,
        tol=tol,
        level=mc_level,
        theta=theta,
        bias=bias,
        n_initial=n_initial,
        max_cost=max_cost,
        batch_size=batch_size,
        screening=statistics,
        kurtosis_limit=kurtosis_limit,
        qoi_names=problem.columns,
    )
    if given_bias is not None:  # checked by iter_mc: finite numbers
        values = np.abs(np.asarray(given_bias, dtype=float))
        # iter_mc would refuse another length only after its first batch; one number in a list is refused as for
        # tol ([1.0] for two QoIs read as one per QoI in column order and was applied to both)
        if not (values.ndim == 0 or values.shape == (problem.n_qoi,)):
            raise InvalidParameterError("bias", given_bias, f"a number (for every QoI) or {problem.n_qoi} values "
                                        f"(one per QoI column: {', '.join(problem.columns)})")
        _refuse_given_bias(problem.columns, tol, float(theta), values)
    with reporting_progress(sampler, f"mc {tol_text(problem.columns, tol)}"):
        result = _run_to_end(events, max_samples=max_samples, tol=tol,
                             n_initial=n_initial if statistics is None else None, progress=sampler.progress)
    result = dataclasses.replace(result, n_not_converged=warn_not_converged(sampler, "mc"),
                                 units=problem.column_units)
    warn_not_met("mc", problem.columns, result, tol, advice=_mc_advice(result, n_initial))
    return result


@contextlib.contextmanager
def reporting_progress(sampler: ContactSampler, title: str) -> Iterator[None]:
    """Start and stop the sampler's progress (if any) around a run: ``stop(is_complete=False)`` if the run raises.

    An interrupted run (Ctrl-C: :class:`KeyboardInterrupt`) gets a note that its samples are kept with the
    problem (:mod:`rough_uq.problem.kept`) and the same call goes on from them.
    """
    progress = sampler.progress
    try:
        if progress is not None:
            progress.start(title)  # inside: a Ctrl-C while it starts stops it too (rich's display kept running)
        yield
    except BaseException as error:
        if isinstance(error, KeyboardInterrupt):
            error.add_note(
                f"rough_uq: {title} interrupted; the {sampler.n_kept} samples it computed are kept with the problem "
                "(in memory): the same call on the same problem goes on from them"
            )
        if progress is not None:
            try:
                progress.stop(is_complete=False)
            except Exception as failed:  # the run's own error (a Ctrl-C) is what the caller must see
                error.add_note(f"rough_uq: the progress reporter's stop(is_complete=False) failed too: {failed!r}")
        raise
    if progress is not None:
        progress.stop()


def _max_samples(max_samples: object) -> int | None:
    return None if max_samples is None else checked_integer("max_samples", max_samples, 1)


def _run_to_end(
    events, *, max_samples: int | None, tol: np.ndarray, n_initial: int | None, progress: ProgressReporter | None
) -> EstimationResult:
    """The result of a run's events; refuses a plan of more than ``max_samples`` samples before drawing them.

    ``n_initial``: a run without a screening, whose initial plan is
    ``n_initial`` samples on each of its levels; if they alone are too many,
    the refusal names ``n_initial``, not the tolerance. None: the initial
    plan follows from the tolerance (a screening's). Each plan goes to ``progress``.
    """
    for event in events:
        if isinstance(event, drivers.PlanUpdated):
            if progress is not None:
                progress.plan(event.levels.tolist(), event.n_planned.tolist(), event.n_done.tolist())
            if event.reason == "initial" and n_initial is not None:
                levels = event.levels[event.n_planned > 0].tolist()
                drivers.refuse_large_start(n_initial, levels, max_samples=max_samples)
            drivers.refuse_large_plan(
                event.n_planned, max_samples=max_samples, tol=tol,
                advice="loosen tol, or pass max_cost (a budget) with max_samples=None",
            )
        if isinstance(event, drivers.Finished):
            return event.result
    raise EstimationError("the estimator stopped without a result")  # pragma: no cover - generator bug

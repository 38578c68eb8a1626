"""What a study file holds, as a dict (``roughuq report --json``) and as text that fits 80 columns.

:func:`study_report` gathers the config summary, the sample counts, the
screening table and rates with the complexity they imply, and every run with
its measured and predicted costs; :func:`render_report` prints it.

Three kinds of time, each with one name and unit everywhere:

* **elapsed** (s): wall-clock time of the commands that ran the run (JSON
  ``elapsed``; a run stopped and resumed before it finished adds its stopped
  commands', ``stopped_elapsed``; a finished run extended by a rerun adds
  the rerun's);
* **CPU-seconds** (CPU-s): the wall times of the samples, each measured in the
  process that computed it, summed (JSON keys with ``seconds``: ``seconds``,
  ``mean_seconds``, ``mlmc_seconds``, ``mc_seconds``,
  ``mc_seconds_predicted``); with 2 workers a run's CPU-seconds are about
  twice its elapsed time;
* **modelled cost** (ref-s, reference seconds): the cost model the estimators
  plan with (JSON keys with ``cost``: ``cost``, ``mean_cost``, ``mc_cost``,
  ``mlmc_cost``), independent of the machine's load.

Units. A line of text puts the unit after the value, ``20.15 ± 0.30 %``,
``Var(contact_area) = 1.10 ± 0.28 %^2``. A table names each QoI with the
unit of its row's estimate in brackets, the one convention of every table:
``contact_area [%]`` (screening, distribution quantiles, load curves),
``contact_area [%^2]`` (the variance table, whose ``Var(Q)``, ``RMSE``,
``tol`` and ``bias`` are in the QoI's unit squared; ``sd(Q)`` is in its
unit), ``clusters [(clusters per unit area)^2]``. The variance and
distribution tables, whose rows are result columns, put the unit (and a
load-curve column's ``@load``) on lines of their own under the QoI, so that
a narrow terminal folds none of them away. A dimensionless fraction
has no unit, in lines and tables alike; the report's ``QoIs:`` line names
every QoI's unit, ``fraction`` included.

Complexity (SPEC section 5): plain MC to RMS error ``eps`` costs
``eps^-(2 + gamma/alpha)``; MLMC costs ``eps^-2`` if ``beta > gamma``,
``eps^-2 log(eps)^2`` if ``beta == gamma`` and ``eps^-(2 + (gamma - beta)/alpha)``
if ``beta < gamma``. The exponents are computed per QoI from the fitted rates
(:func:`~rough_uq.study.records.complexity`, defined once with the records);
``beta`` and ``gamma`` are called equal when they differ by less than
:data:`RATE_TIE` (about the standard error of a screening fit). A bias that
does not decay (``alpha`` at most :data:`MIN_ALPHA`) has no exponent: the
report says so instead of printing a meaningless number.

The report reads the typed records of :mod:`rough_uq.study.records`; its
JSON form (:func:`study_report`) is the records' ``to_json`` with the derived
numbers added (the screening's ``complexity``, a run's ``work_ratio``,
``mc_seconds_measured``, ``mc_cost_measured`` and ``measured_ratio``). The
MC/MLMC ratios, predicted and measured, and the predicted plain MC beside
them are in modelled cost.

Load curves
-----------
A study with several loads has one column per QoI and load
(``contact_area@0.05``, :mod:`rough_uq.problem.loads`). :func:`load_curves`
regroups every finished run's columns into curves over the increasing load,
with the estimates' RMS errors, and :func:`fit_area_slope` fits the slope
``kappa`` of ``A / A0 = kappa p / (E* sqrt(m2))`` at small loads (see there
for the choice of loads and the error).
"""

from __future__ import annotations

import math
import os
import shlex
import textwrap
from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from rich.markup import escape

from rough_uq.errors import PLANNED_COUNT_CAP
from rough_uq.multilevel.distribution import (
    BANDWIDTH_TOO_WIDE, DEFAULT_PROBABILITIES, NO_ERROR_BAND, THRESHOLDS_MISS_SAMPLES,
)
from rough_uq.multilevel.rates import EXACT_RATE, RATE_FLOOR
from rough_uq.multilevel.statistics import (
    CONSISTENCY_CHECK_SAMPLES, FEWEST_VARIANCE_SAMPLES, KURTOSIS_LIMIT, SAMPLE_KURTOSIS_CHECK_SAMPLES,
)
from rough_uq.problem.batch import STAGE_SCREENING
from rough_uq.problem.columns import split_column, tol_text
from rough_uq.study.progress import format_duration
from rough_uq.study.records import (
    MIN_ALPHA,
    RATE_TIE,
    RunRecord,
    ScreeningRecord,
    complexity,
    count_not_converged,
    is_bias_decaying,
    read_run_records,
    read_screening_record,
)
from rough_uq.study.store import FORMAT_VERSION, StudyStore, incomplete_shard_name, is_locked_by_running_process

__all__ = [
    "MIN_ALPHA",
    "RATE_TIE",
    "ReportedRun",
    "SLOPE_MAX_AREA",
    "SlopeFit",
    "complexity",
    "fit_area_slope",
    "load_curves",
    "render_load_curves",
    "derive_runs",
    "format_run",
    "load_text",
    "value_error_text",
    "render_report",
    "render_runs",
    "render_sweep",
    "render_targets",
    "run_label",
    "tol_text",
    "TARGET_METHODS",
    "render_screening",
    "screening_json",
    "study_report",
]

#: Run methods whose estimate is not the mean (their outcome is read differently).
TARGET_METHODS = ("variance", "cdf")

_STOP_REASONS = {
    "max_level": "the bias needs a grid finer than grid.max_level",
    "max_cost": "stopped at --max-cost",
    "bias": "the bias of this level is larger than the tolerance allows",
    THRESHOLDS_MISS_SAMPLES: "the thresholds miss the samples of a level, whose variance they do not measure",
    BANDWIDTH_TOO_WIDE: "the smoothing bandwidth exceeds twice the spread of the values; the bias is not estimated",
}


def load_text(load: dict[str, Any]) -> str:
    """The load as it is written in a config, e.g. ``relative: 0.1`` or ``relative: [0.01, 0.1]``."""
    def text(value: Any) -> str:
        return "[" + ", ".join(f"{v:g}" for v in value) + "]" if isinstance(value, (list, tuple)) else f"{value:g}"

    return ", ".join(f"{kind}: {text(value)}" for kind, value in load.items())


def _config_summary(config: Any) -> dict[str, Any]:
    surface = config.surface
    return {
        "seed": config.seed,
        "system_size": surface.system_size,
        "k_l": surface.k_l,
        "k_r": surface.k_r,
        "k_s": surface.k_s,
        "hurst": surface.hurst,
        "rms_height": surface.rms_height,
        "e_star": config.material.e_star,
        "load": {config.load.kind: config.load.value},
        "grids": [config.grid.n_at(level) for level in range(config.grid.max_level + 1)],
        "qoi": {name: settings.unit_label for name, settings in config.qoi.items()},
        # What else defines a QoI's numbers (the area estimator, cluster connectivity, critical pressure): two
        # studies that differ in it alone gave reports that differed in their numbers alone.
        "qoi_settings": {
            name: settings.model_dump(mode="json", exclude={"unit", "tol"}) for name, settings in config.qoi.items()
        },
        "solver_tol": config.solver.tol,
        "theta": config.estimation.theta,
    }


def _sample_counts(store: StudyStore, runs: Sequence[RunRecord]) -> dict[str, dict[str, int]]:
    """Stored samples per stage (named by its run) and level."""
    names = {run.stage: run.run_id for run in runs if run.stage is not None}
    names[STAGE_SCREENING] = "screening"
    counts: dict[str, dict[str, int]] = {}
    for level in store.levels():
        for stage in store.stages(level=level):
            n = int(store.sample_indices(level=level, stage=stage).size)
            counts.setdefault(names.get(stage, f"stage {stage}"), {})[str(level)] = n
    return counts


def _not_converged(store: StudyStore) -> int:
    return count_not_converged(store.read_samples(level=level) for level in store.levels())


@dataclass(frozen=True)
class ReportedRun:
    """A run as the report shows it: its record, and the measured plain MC at its tolerances if any.

    Attributes
    ----------
    record : RunRecord
        Its status is as seen now (a ``running`` record is ``running`` or ``interrupted``).
    mc_seconds_measured, mc_cost_measured : float or None
        CPU-seconds and modelled cost of a finished plain MC run at the same
        tolerances and ``theta`` on the level the screening picks (``roughuq mc --tol``;
        MLMC runs only).
    """

    record: RunRecord
    mc_seconds_measured: float | None = None
    mc_cost_measured: float | None = None

    @property
    def measured_ratio(self) -> float | None:
        """Measured MC over MLMC modelled cost (None without a measured MC run).

        In modelled cost, as the predicted ratio: CPU-seconds depend on the
        load of the machine while each run ran.
        """
        if self.mc_cost_measured is None or self.record.outcome is None:
            return None
        cost = self.record.outcome.cost
        return self.mc_cost_measured / cost if cost > 0 else math.inf

    def to_json(self) -> dict[str, Any]:
        """The run as ``roughuq report --json`` lists it: ``run_id``, the stored record, the derived ratios."""
        data = {"run_id": self.record.run_id, **self.record.to_json()}
        if self.record.is_finished:
            outcome = self.record.outcome
            # A run that --max-cost stopped short of its tolerance is no measure of MLMC against MC (format_run).
            data["work_ratio"] = None if outcome.stop_reason == "max_cost" else outcome.work_ratio
            if not is_rmse_measured(outcome):
                data["rmse"] = None  # the stored value rests on variances of 0: not an error
            if data.get("distribution") is not None and not has_error_band(outcome):
                _open_band(data["distribution"])
        if self.mc_cost_measured is not None:
            data["mc_seconds_measured"] = self.mc_seconds_measured
            data["mc_cost_measured"] = self.mc_cost_measured
            data["measured_ratio"] = self.measured_ratio
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ReportedRun:
        """Read an entry of the report's ``runs`` (the derived ratios are recomputed, not read)."""
        seconds, cost = data.get("mc_seconds_measured"), data.get("mc_cost_measured")
        return cls(RunRecord.from_json(data), None if seconds is None else float(seconds),
                   None if cost is None else float(cost))


def derive_runs(runs: Sequence[RunRecord]) -> list[ReportedRun]:
    """The runs a report shows, with what is derived from them: MC/MLMC ratios, predicted and measured.

    ``work_ratio`` (:attr:`~rough_uq.study.records.RunOutcome.work_ratio`):
    predicted plain-MC modelled cost over the run's modelled cost. Where a
    finished plain MC run at the same tolerances and ``theta`` exists on the level the
    screening picks (``roughuq mc --tol``; not ``mc --level``, another
    level's bias), ``mc_seconds_measured`` and ``mc_cost_measured`` (its
    CPU-seconds and modelled cost) and ``measured_ratio`` (over the MLMC
    run's modelled cost). Dropped runs (``roughuq drop``) are left out.
    """
    kept = [run for run in runs if run.status != "dropped"]
    measured_mc = {run.comparison_key: run.outcome for run in kept if run.measures_plain_mc and run.is_finished}
    shown = []
    for run in kept:
        mc = measured_mc.get(run.comparison_key) if run.method == "mlmc" and run.is_finished else None
        shown.append(ReportedRun(run) if mc is None else ReportedRun(run, float(mc.seconds), float(mc.cost)))
    return shown


def _seen_status(run: ReportedRun, is_running: bool) -> ReportedRun:
    """A ``running`` record is a run a live process holds the study for, else an ``interrupted`` one."""
    if run.record.status != "running":
        return run
    return replace(run, record=replace(run.record, status="running" if is_running else "interrupted"))


def _run_warnings(runs: Sequence[ReportedRun], qoi_names: Sequence[str]) -> list[dict[str, str]]:
    """Each run's warnings as ``{"run_id", "label", "message"}``: its diagnostics, and that it was interrupted.

    The text names a run by its label (:func:`run_label`); its id, hundreds
    of characters for a load curve, only where the user types it (``roughuq drop``).
    """
    warnings = []
    for run in runs:
        record = run.record
        diagnostics = record.outcome.diagnostics if record.outcome is not None else ()
        messages = [d.message for d in diagnostics]
        if record.status == "interrupted":
            messages.append(f"interrupted; rerun the same command to resume, or `roughuq drop {record.run_id}` "
                            "to forget it")
        label = run_label(record, qoi_names)
        warnings += [{"run_id": record.run_id, "label": label, "message": message} for message in messages]
    return warnings


def _report_warnings(screening: ScreeningRecord | None, run_warnings: Sequence[dict[str, str]],
                     n_not_converged: int) -> list[str]:
    warnings = [d.message for d in screening.diagnostics] if screening is not None else []
    warnings += [f"{warning['label']}: {warning['message']}" for warning in run_warnings]
    if n_not_converged:
        warnings.append(
            f"{n_not_converged} stored samples have a solve that did not converge even after the retry; "
            "their QoIs (from the last iterate) are included"
        )
    return warnings


def _unrecorded_screening(screening: ScreeningRecord | None, samples: dict[str, dict[str, int]], is_running: bool,
                          path: str) -> list[str]:
    """A warning where the study holds screening samples beyond its screening record (else none).

    A ``roughuq screen`` that extends a screening (more levels or samples) and is stopped before its record leaves
    them so: the report showed the old screening's table next to the larger sample counts without a word.
    """
    stored = samples.get("screening", {})
    if screening is None or is_running:
        return []
    recorded = dict(zip(screening.statistics.levels, screening.statistics.n_samples))
    extra = [(int(level), n) for level, n in stored.items() if n > recorded.get(int(level), 0)]
    if not extra:
        return []
    counts = ", ".join(f"L{level} {n} (recorded {recorded.get(level, 0)})" for level, n in sorted(extra))
    return [f"the study holds screening samples its screening record does not use: {counts}; a `roughuq screen` "
            f"stopped before its record leaves them (rerun it, `roughuq screen CONFIG{_out_option(path)}` with its "
            "config, to take them in), and so do screening shards merged beyond screening.samples (a screening with "
            "that many samples takes them in); the rates shown are the recorded screening's"]


def screening_json(screening: ScreeningRecord | None) -> dict[str, Any] | None:
    """The screening as ``roughuq screen --json`` and ``report --json`` show it: the record and its complexity."""
    if screening is None:
        return None
    return {**screening.to_json(), "complexity": [c.to_json() for c in screening.complexity]}


def read_report(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What ``roughuq report --json`` prints for the study file ``path``, as a dict (for notebooks and scripts).

    ``runs`` lists every run with its stored record (``estimate``, ``rmse``,
    ``levels``, ``n_samples``, ... per QoI in ``qoi_names`` order) and
    ``screening`` the screening's per-level table and rates; see
    :func:`study_report`. Raises :class:`~rough_uq.errors.StudyFileError` for
    a file that is not a readable study file.
    """
    from rough_uq.study.pipeline import open_existing_study

    missing = "; name one that `roughuq screen` or a run wrote (its config's output.path, results.h5 by default)"
    with open_existing_study(path, writable=False, missing=missing) as study:
        return study_report(study.store, study.config)


def study_report(store: StudyStore, config: Any) -> dict[str, Any]:
    """Everything ``roughuq report`` shows, as a JSON-able dict (see :func:`derive_runs` for the ratios).

    ``warnings`` are the texts printed; ``run_warnings`` those of the runs
    with their ids (:func:`_run_warnings`), which the texts leave out.
    """
    screening = read_screening_record(store)
    stored_runs = read_run_records(store)
    path = getattr(store, "path", "")
    is_running = bool(path) and is_locked_by_running_process(path)
    runs = [_seen_status(run, is_running) for run in derive_runs(stored_runs)]
    n_not_converged = _not_converged(store)
    run_warnings = _run_warnings(runs, store.qoi_names)
    samples = _sample_counts(store, stored_runs)
    return {
        "path": str(path),
        "format_version": FORMAT_VERSION,
        "code_version": store.code_version,
        "created": store.created,
        "role": store.role,
        "config_hash": store.config_hash,
        "config": _config_summary(config),
        "qoi_names": list(store.qoi_names),
        "samples": samples,
        "screening": screening_json(screening),
        "runs": [run.to_json() for run in runs],
        "dropped_runs": [run.run_id for run in stored_runs if run.status == "dropped"],
        "is_running": is_running,
        "n_not_converged": n_not_converged,
        "warnings": _report_warnings(screening, run_warnings, n_not_converged)
        + _unrecorded_screening(screening, samples, is_running, str(path)),
        "run_warnings": run_warnings,
        "load_curves": load_curves(list(store.qoi_names), [run.record for run in runs], config),
    }


# ---------------------------------------------------------------------------
# Text
# ---------------------------------------------------------------------------


def _g(value: float | None, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return f"{value + 0.0:.{digits}g}"  # + 0.0: a fitted -0.0 reads "0", not "-0"


def _beside(value: float, bound: float, digits: int = 2, bound_digits: int = 3) -> tuple[str, str]:
    """``value`` and ``bound`` to ``digits`` and ``bound_digits`` significant digits, both to more (up to 6)
    where they would read alike without being equal: an RMSE of 0.10364 beside its tolerance 0.1 printed
    "RMSE 0.1 > tol 0.1"."""
    while True:
        text, bound_text = _g(value, digits), _g(bound, bound_digits)
        # Read as the numbers compare: not alike where they differ, nor the other way round ("0.12 > 0.123").
        is_ordered = (float(text) > float(bound_text)) == (value > bound)
        is_read_right = is_ordered and (text != bound_text) == (value != bound)
        if is_read_right or max(digits, bound_digits) >= 6:
            return text, bound_text
        digits, bound_digits = digits + 1, max(bound_digits, digits + 1)


def _digits(value: float, digits: int) -> str:
    """``value`` to ``digits`` significant digits, trailing zeros kept (``18.60`` beside ``20.45``; ``:.4g``
    printed ``18.6``), without a bare trailing point (``1000``, not ``1000.``)."""
    mantissa, mark, exponent = f"{value + 0.0:#.{digits}g}".partition("e")
    return mantissa.rstrip(".") + mark + exponent


def _quantile_values(quantile: Any) -> tuple[str, str, str]:
    """A quantile's value and the ends of its error bar, four significant digits each (open ends ``-inf``/``inf``)."""
    lower = "-inf" if quantile.lower is None else _digits(quantile.lower, 4)
    upper = "inf" if quantile.upper is None else _digits(quantile.upper, 4)
    return _digits(quantile.value, 4), lower, upper


#: Planned counts from here on are shown in three digits (``1.97e+15``; sixteen digits said nothing more).
_COUNT_DIGITS_LIMIT = 10**7


def _planned_count(n: int) -> str:
    """A level's planned sample count; a count at the plan's cap as ``>=`` the cap (the plan needs more)."""
    if n >= PLANNED_COUNT_CAP:
        return f">={PLANNED_COUNT_CAP:.2g}"
    return str(n) if n < _COUNT_DIGITS_LIMIT else f"{n:.3g}"


def _pm(value: float, error: float) -> str:
    return f"{_g(value, 3)} ± {_g(error, 2)}"


def value_error_text(value: float, error: float) -> str:
    """``value ± error`` with the error to two significant digits and the value to the same decimal."""
    if not (math.isfinite(value) and math.isfinite(error)) or error <= 0:
        return f"{_g(value, 5)} ± {_g(error, 2)}"
    decimals = max(0, 1 - math.floor(math.log10(error)))
    if decimals > 8:  # in exponent form, the value to the error's second digit too (it printed 2.13623e-07 ± 3.8e-08)
        if value == 0:
            return f"0 ± {error:.1e}"
        digits = max(1, math.floor(math.log10(abs(value))) - math.floor(math.log10(error)) + 2)
        return f"{value:.{min(digits, 6) - 1}e} ± {error:.1e}"  # e, not g: the zeros kept (9.96e-08 read 1e-07)
    return f"{value:.{decimals}f} ± {error:.{decimals}f}"


def _power(label: str, power: int = 1) -> str:
    """``label`` to ``power``: ``%``, ``%^2``, ``(clusters per unit area)^2``; empty for a dimensionless fraction."""
    if label in ("fraction", ""):
        return ""
    if power == 1:
        return label
    return f"{label}^{power}" if " " not in label else f"({label})^{power}"


def _unit(label: str, power: int = 1) -> str:
    """The unit after a value in a line of text: `` %``, `` %^2``; empty for a dimensionless fraction."""
    text = _power(label, power)
    return f" {text}" if text else ""


def _labelled(name: str, label: str, power: int = 1) -> str:
    """A QoI as a table names it, with the unit of the row's estimate: ``contact_area [%^2]`` (module docstring)."""
    text = _power(label, power)
    return f"{name} [{text}]" if text else name


def _column_unit(units: dict[str, str], column: str) -> str:
    """Unit label of a result column: its QoI's (a load-curve column ``qoi@load`` has the unit of ``qoi``)."""
    return units.get(column, units.get(split_column(column)[0], ""))


def run_label(run: RunRecord, qoi_names: Sequence[str]) -> str:
    """A run in a few words: ``mlmc, tol contact_area=2, mean_gap=0.05, theta 0.5``; ``mc on level 1, ...``.

    Method (``mlmc (Richardson)`` for an extrapolated run), the level of an
    ``mc --level`` run (not that an ``mc --tol`` run chose), tolerances
    (:func:`tol_text`), ``theta`` and, for a cdf run, its thresholds (and
    probabilities other than the default; :func:`_cdf_request_text`): what
    its run id is made of (:func:`~rough_uq.problem.runs.run_id`), so
    distinct runs have distinct labels, in a fraction of the id's length. The id itself is in ``roughuq
    report``'s ``samples stored`` line and in its ``--json`` (``run_id``),
    for ``roughuq drop`` and ``roughuq show --stage``.
    """
    theta = "" if run.theta is None else f", theta {run.theta:g}"
    tol = tol_text(run.qoi_names or qoi_names, run.tol)
    return f"{_method_text(run)}{_given_level(run)}, tol {tol}{theta}{_cdf_request_text(run)}"


def _cdf_request_text(run: RunRecord) -> str:
    """``, thresholds 0 .. 40 (3)`` (and ``, p 0.1, 0.9`` where not the default probabilities) for a finished
    cdf run, ``, request 1a2b3c4d`` (its id's suffix) for another: the runs of one column and tolerance with other
    thresholds, which their ids tell apart, read alike in the report's warnings and tables; ``""`` for other
    methods."""
    if run.method != "cdf":
        return ""
    distribution = None if run.outcome is None else run.outcome.distribution
    if distribution is None:
        _, separator, digest = run.run_id.partition("_request-")
        return f", request {digest}" if separator else ""
    s = distribution.thresholds
    probabilities = tuple(q.probability for q in distribution.quantiles)
    shown = "" if probabilities == DEFAULT_PROBABILITIES else f", p {', '.join(f'{p:g}' for p in probabilities)}"
    return f", {_thresholds_text(s)}{shown}"


def _thresholds_text(s: Sequence[float]) -> str:
    """``thresholds 0 .. 40 (3)``."""
    return f"thresholds {_g(s[0], 4)} .. {_g(s[-1], 4)} ({len(s)})"


def _given_level(run: RunRecord) -> str:
    """`` on level L`` for an ``mc --level`` run (not the level an ``mc --tol`` run chose), else ``""``."""
    is_given_level = run.method == "mc" and run.level is not None and not run.measures_plain_mc
    return f" on level {run.level}" if is_given_level else ""


#: The default ``estimation.theta`` (and of the Python runs); a run's heading names any other.
_USUAL_THETA = 0.5


def format_run(run: RunRecord, qoi_names: Sequence[str], units: dict[str, str], *,
               measured_ratio: float | None = None) -> list[str]:
    """A run as a few lines of at most about 80 characters (one summary line per QoI).

    ``measured_ratio`` is the measured MC/MLMC ratio (:attr:`ReportedRun.measured_ratio`) where known.
    """
    if run.method in TARGET_METHODS and run.qoi_names:
        qoi_names = run.qoi_names  # a cdf run has one column, whatever the study's
    # theta is part of a run's identity: two runs that differ in it alone had the same heading.
    theta = "" if run.theta is None or run.theta == _USUAL_THETA else f", theta {run.theta:g}"
    # So is an `mc --level` run's level: `mc --tol 0.3` and `mc --level 1 --tol 0.3` were both "mc contact_area=0.3".
    level = _given_level(run)
    head = f"{_method_text(run)}{level + ',' if level else ''} {tol_text(qoi_names, run.tol)}{theta}"
    outcome = run.outcome
    if run.status != "finished" or outcome is None:
        head += _cdf_request_text(run)  # cdf runs of one tolerance with other thresholds (finished: their F line)
        if run.status == "running":
            return [f"{head}: running (another process is computing it)"]
        if run.status == "refused":
            return [f"{head}: refused", *textwrap.wrap(run.reason or "", 78, initial_indent="  ",
                                                       subsequent_indent="  ")]
        return [f"{head}: interrupted; rerun the same command to resume"]
    levels = outcome.levels
    if run.method == "mc":
        where = f"level {levels[-1]}, N {outcome.n_samples[-1]}"
    else:
        where = f"levels {levels[0]}..{levels[-1]}, N_l {' '.join(str(n) for n in outcome.n_samples)}"
    reason = outcome.stop_reason
    if outcome.tol_met and not outcome.is_bias_estimated:
        # `mc --level`: its statistical error is within the tolerance, its bias unknown (the RMSE may not be).
        lines = [f"{head}: statistical error within tolerance, bias not estimated", f"  {where}"]
    elif outcome.tol_met:
        lines = [f"{head}: tolerance met", f"  {where}"]
    else:
        lines = [f"{head}: NOT MET ({reason})", f"  {_stop_text(outcome, run.method)}; {where}"]
    if outcome.richardson == "refused":
        lines.append("  Richardson extrapolation refused: the estimate is plain MLMC (see warning)")
    if run.method == "variance":
        lines += [_variance_line(outcome, q, name, run.tol[q], units) for q, name in enumerate(qoi_names)]
    elif run.method == "cdf":
        lines += _cdf_lines(outcome, run.tol[0], units)
    else:
        share = _stat_share(run)
        lines += [_qoi_line(outcome, q, name, run.tol[q], units, share) for q, name in enumerate(qoi_names)]
    lines.append(
        f"  time: elapsed {format_duration(outcome.elapsed)}; samples {format_duration(outcome.seconds)} CPU; "
        f"modelled cost {_g(outcome.cost)} ref-s"
    )
    if run.method != "mc":
        lines.append(_mc_comparison(outcome, measured_ratio))
    return lines


def _mc_comparison(outcome: Any, measured_ratio: float | None) -> str:
    """``  plain MC: 1.31 ref-s predicted; MC/MLMC 26 predicted, 24 measured`` for an MLMC run; without the
    ratios for a run that ``--max-cost`` stopped (its cost is not that of its tolerance: "MC/MLMC 26" compared
    MC to the tolerance with a run that stopped short of it)."""
    # Modelled cost, as the ratios: CPU-seconds converted at the screening's rate contradicted them.
    text = f"  plain MC: {_g(outcome.mc_cost)} ref-s predicted"
    if outcome.stop_reason == "max_cost":
        return f"{text} (no MC/MLMC ratio: the run stopped at --max-cost)"
    text += f"; MC/MLMC {_g(outcome.work_ratio, 2)} predicted"
    return text if measured_ratio is None else f"{text}, {_g(measured_ratio, 2)} measured"


def _method_text(run: RunRecord) -> str:
    """The method in a run's heading: ``mlmc``, or ``mlmc (Richardson)`` for a Richardson-extrapolated run.

    A run that asked for the extrapolation is named so even where it was
    refused: it is another run, with its own samples, than plain MLMC at the
    same tolerance.
    """
    return f"{run.method} (Richardson)" if run.is_richardson else run.method


def _stop_text(outcome: Any, method: str) -> str:
    """Why a run of ``method`` that missed its tolerance stopped, in words (plain MC never estimates a bias)."""
    reason = outcome.stop_reason
    if reason == "max_cost" and not outcome.is_bias_estimated and method != "mc":
        return "stopped at --max-cost before the levels its bias estimate needs were sampled"
    if reason == "max_level" and is_bias_in_noise(outcome):
        return "the bias test failed on terms within their noise (see the warning)"
    return _STOP_REASONS.get(reason, reason)


def _stat_share(run: RunRecord) -> float | None:
    """``sqrt(1 - theta)``, the statistical error's share of the tolerance that an ``mc --level`` run (no bias
    estimate) must meet (:class:`~rough_uq.multilevel.drivers.plain_mc._McRun`); None for the other runs."""
    if run.method != "mc" or run.outcome is None or run.outcome.is_bias_estimated:
        return None
    return math.sqrt(1.0 - (_USUAL_THETA if run.theta is None else run.theta))


def _error_text(outcome: Any, rmse: float, tol: float, what: str = "", share: float | None = None) -> str:
    """``RMSE r <= tol t``, or ``stat. error e <= tol t`` where the bias is not estimated (the RMSE is unknown);
    with a ``share`` of the tolerance that the statistical error must meet, ``stat. error e <= s, its share of
    tol t`` (a run at 0.0355 stopped by its budget read "0.0355 <= tol 0.043" beside NOT MET: its share was 0.0304)."""
    bound = tol if share is None else share * tol
    relation = "<=" if rmse <= bound * (1 + 1e-12) else ">"
    label = f"{what}RMSE" if outcome.is_bias_estimated else f"{what}stat. error"
    if share is not None:
        shown, bound_shown = _beside(rmse, bound, bound_digits=2)
        return f"{label} {shown} {relation} {bound_shown}, its share of tol {_g(tol)}"
    shown, tol_shown = _beside(rmse, tol)
    return f"{label} {shown} {relation} tol {tol_shown}"


def _estimate_line(outcome: Any, q: int, label: str, unit: str, tol: float, share: float | None = None) -> str:
    """``  label = value ± error unit (RMSE r <= tol t, bias b)`` for column ``q`` of a finished run.

    Without a bias estimate: ``(stat. error e <= tol t, bias not estimated)``; ``share``: :func:`_error_text`.
    """
    bias = f"bias {_g(outcome.bias_estimate[q], 2)}" if outcome.is_bias_estimated else "bias not estimated"
    return (f"  {label} = {value_error_text(outcome.estimate[q], outcome.stat_error[q])}{unit} "
            f"({_error_text(outcome, outcome.rmse[q], tol, share=share)}, {bias})")


def _qoi_line(outcome: Any, q: int, name: str, tol: float, units: dict[str, str], share: float | None = None) -> str:
    """``  name = value ± error unit (RMSE r <= tol t, bias b)`` for QoI ``q`` of a finished run."""
    return _estimate_line(outcome, q, name, _unit(_column_unit(units, name)), tol, share)


def _variance_line(outcome: Any, q: int, name: str, tol: float, units: dict[str, str]) -> str:
    """``  Var(name) = value ± error unit^2 (RMSE r <= tol t, bias b)`` for column ``q`` of a variance run."""
    return _estimate_line(outcome, q, f"Var({name})", _unit(_column_unit(units, name), 2), tol)


def _quantile_text(quantile: Any, unit: str, outcome: Any) -> str:
    """``q(0.05) = 17.9 [17.5, 18.3] %``; an open end of the error bar is ``-inf`` / ``inf``.

    No error bar where the run has no error band (:func:`has_error_band`).
    """
    if quantile.value is None:
        return f"q({quantile.probability:g}) not bracketed by the thresholds"
    value, lower, upper = _quantile_values(quantile)
    if not is_rmse_measured(outcome):
        return f"q({quantile.probability:g}) = {value}{_unit(unit)} (error not measured)"
    if not has_error_band(outcome):
        return f"q({quantile.probability:g}) = {value}{_unit(unit)} (no error bar: smoothing bias not estimated)"
    return f"q({quantile.probability:g}) = {value} [{lower}, {upper}]{_unit(unit)}"


def is_bias_in_noise(outcome: Any) -> bool:
    """Whether a run's bias estimate rests on level terms within their noise (its ``bias_noise`` warning)."""
    return any(d.kind == "bias_noise" for d in outcome.diagnostics)


def is_rmse_measured(outcome: Any) -> bool:
    """False for a cdf run whose thresholds miss a level's samples: its stored RMSE (from variances of 0) means
    nothing (:mod:`rough_uq.multilevel.distribution`)."""
    return outcome.stop_reason != THRESHOLDS_MISS_SAMPLES


def has_error_band(outcome: Any) -> bool:
    """Whether a cdf run's band ``cdf +- rmse`` and its quantiles' error bars are shown
    (:attr:`~rough_uq.multilevel.distribution.CdfEstimate.has_error_band`): not where the thresholds miss a
    level's samples or the bandwidth is too wide (its band, the statistical error's, ignores a smoothing bias
    known to be large; files written before 2026-11-28 stored finite quantile bars from it)."""
    return outcome.stop_reason not in NO_ERROR_BAND


def _cdf_lines(outcome: Any, tol: float, units: dict[str, str]) -> list[str]:
    """The thresholds, the sup-norm error and the quantiles of a cdf run."""
    distribution = outcome.distribution
    if distribution is None:  # pragma: no cover - the pipeline always stores it
        return []
    unit = _column_unit(units, distribution.column)
    s = distribution.thresholds
    error = _error_text(outcome, outcome.rmse[0], tol, "sup-norm ")
    if not is_rmse_measured(outcome):
        # A zero variance estimate there says nothing (rough_uq.multilevel.distribution): no error to show.
        error = f"sup-norm RMSE not measured (the thresholds miss a level's samples), tol {_g(tol)}"
    elif outcome.is_bias_estimated:
        error += f" (stat. {_g(max(outcome.stat_error), 2)}, bias {_g(outcome.bias_estimate[0], 2)})"
    else:
        error += " (bias not estimated)"
    lines = [
        f"  F(s) = P({distribution.column} <= s) at {len(s)} thresholds {_g(s[0], 4)} .. {_g(s[-1], 4)}{_unit(unit)}",
        f"  {error}",
    ]
    return lines + [f"  {_quantile_text(q, unit, outcome)}" for q in distribution.quantiles]


def _print_table(console: Any, table: Any) -> None:
    """Print ``table``; where the terminal is too narrow for it without cutting or folding a word of a cell, at its
    natural width (the terminal then wraps its lines).

    Squeezed into a narrow terminal rich cut numbers to "..." and folded tolerances mid-number (at 60 columns
    "0.0299" read "0.02...", "contact_area=0.25" read "contact_" / "area=0.2" / "5"), and giving every
    column its longest word as a minimum made rich leave out whole columns. A table rich can fit by wrapping
    cells at their spaces (a load curve's "20.15 ± 0.30") is printed so, as before.
    """
    from rich.measure import Measurement

    natural = max(Measurement.get(console, console.options.update_width(_WIDEST_TABLE), table).maximum, console.width)
    if _words(_rendered(console, table, natural)) <= _words(_rendered(console, table, console.width)):
        natural = console.width
    width = console.width
    console.width = natural
    try:
        console.print(table)
    finally:
        console.width = width


def _words(text: str) -> set[str]:
    """The words of a rendered table, its rules (which change with the width) left out."""
    return {word for word in text.split() if any(character.isalnum() for character in word)}


def _rendered(console: Any, table: Any, width: int) -> str:
    """The text of ``table`` printed ``width`` characters wide (styles left out)."""
    from rich.text import Text

    width, console.width = console.width, width
    try:
        with console.capture() as capture:
            console.print(table)
    finally:
        console.width = width
    return Text.from_ansi(capture.get()).plain


#: Widest table :func:`_print_table` prints without folding (characters).
_WIDEST_TABLE = 10_000


def _table(title: str) -> Any:
    from rich import box
    from rich.table import Table

    return Table(title=title, box=box.SIMPLE_HEAD, title_justify="left", pad_edge=False)


def render_screening(console: Any, screening: ScreeningRecord, qoi_names: Sequence[str],
                     units: dict[str, str] | None = None, *, grids: Sequence[int] = ()) -> None:
    """The per-level screening tables, the rates with their complexity, and the cost predictions.

    ``grids`` are the nodes per side of each level (``-`` where not given).
    """
    units = units or {}
    stats = screening.statistics
    console.print(f"screened levels {stats.levels[0]}..{stats.levels[-1]}, {screening.n_screened} samples each",
                  highlight=False)
    for q, name in enumerate(qoi_names):
        # The legend once, under the last table: a load curve of 20 columns printed it 20 times (100 lines).
        table = _screening_table(stats, q, name, _column_unit(units, name), legend=q == len(qoi_names) - 1)
        _print_table(console, table)
    table = _table("Time per sample")
    for column in ("level", "grid", "modelled cost", "measured"):
        table.add_column(column, justify="right")
    for i, level in enumerate(stats.levels):
        grid = str(grids[level]) if level < len(grids) else "-"
        measured = f"{format_duration(stats.mean_seconds[i])} CPU"
        table.add_row(str(level), grid, f"{_g(stats.mean_cost[i])} ref-s", measured)
    _print_table(console, table)
    _print_rates(console, screening, qoi_names)
    if screening.predictions:
        _print_table(console, _predictions_table(screening))


def _screening_table(stats: Any, q: int, name: str, unit: str | None, *, legend: bool = True) -> Any:
    table = _table(escape(f"Screening of {_labelled(name, unit or '')} per level"))
    if legend:
        table.caption = _SCREENING_LEGEND
        table.caption_justify = "left"
    for column in ("level", "N", "mean Q", "var Q", "mean Y", "var Y", "kurt", "check"):
        table.add_column(column, justify="right")
    for i, level in enumerate(stats.levels):
        table.add_row(
            str(level), str(stats.n_samples[i]),
            _g(stats.mean_fine[i][q], 4), _g(stats.var_fine[i][q]),
            _g(stats.mean_diff[i][q]), _g(stats.var_diff[i][q]),
            _g(stats.kurtosis[i][q]), _check_cell(stats, i, q),
        )
    return table


def _open_band(distribution: dict[str, Any]) -> None:
    """The JSON of a CDF without an error band (:func:`has_error_band`): the band ``[0, 1]`` at every threshold
    and open quantile bars, as :func:`~rough_uq.multilevel.distribution.quantiles` gives them now (files written
    before 2026-11-28 stored the statistical error's band)."""
    size = len(distribution["thresholds"])
    distribution["cdf_lower"], distribution["cdf_upper"] = [0.0] * size, [1.0] * size
    for quantile in distribution["quantiles"]:
        quantile["lower"] = quantile["upper"] = None


def _shard_text(path: str, *, is_running: bool) -> str:
    """What a shard file is and what to do with it; a ``.partial-PID`` one is a shard not yet complete (it read
    "add them to their study", as if whole)."""
    incomplete = incomplete_shard_name(path)
    if incomplete is None:
        return ("a shard of samples (written by `roughuq sample`): add them to their study with `roughuq merge "
                f"--into STUDY {escape(shlex.quote(path))}`")
    name, pid = incomplete
    if is_running:
        return (f"an incomplete shard (being written by process {pid}): `roughuq sample` renames it {escape(name)} "
                "once complete; merge that file")
    return (f"an incomplete shard, left by process {pid}, which was stopped before it finished: run its `roughuq "
            f"sample ... --out {escape(name)}` again (which removes this file), then merge {escape(name)}")


def _check_cell(stats: Any, i: int, q: int) -> str:
    """The consistency ratio of row ``i``, QoI ``q``; ``-`` where it was not checked (level 0, a level below
    missing, fewer than :data:`CONSISTENCY_CHECK_SAMPLES` samples on either level), where it read 0, as a pass."""
    value = stats.consistency[i][q]
    levels, n = stats.levels, stats.n_samples
    unchecked = i == 0 or levels[i - 1] != levels[i] - 1 or min(n[i], n[i - 1]) < CONSISTENCY_CHECK_SAMPLES
    return "-" if unchecked and value == 0 else _g(value, 2)


#: What a reader of the screening tables cannot guess from their headers (the rest is the usual MLMC notation).
_SCREENING_LEGEND = ("Y = Q_l - Q_(l-1) on coupled grids; kurt: kurtosis of Y (3 for Gaussian Y; var Y rests on "
                     f"about N / kurt samples: flagged above {KURTOSIS_LIMIT:g}, and from "
                     f"{SAMPLE_KURTOSIS_CHECK_SAMPLES} samples above N / {FEWEST_VARIANCE_SAMPLES:g}); "
                     "check: |mean Y - (mean Q_l - mean Q_(l-1))| "
                     "over 3 times the sum of the three means' standard errors; above 1 the levels do not telescope; "
                     f"- where not checked (level 0, fewer than {CONSISTENCY_CHECK_SAMPLES} samples)")


def _print_rates(console: Any, screening: ScreeningRecord, qoi_names: Sequence[str]) -> None:
    rates = screening.rates
    console.print("Rates: |E[Y_l]| ~ 2^(-alpha l), Var(Y_l) ~ 2^(-beta l), cost ~ 2^(gamma l)")
    console.print(f"  gamma = {_pm(rates.gamma, rates.gamma_se)} (cost)")
    for q, name in enumerate(qoi_names):
        c = screening.complexity[q]
        alpha, beta = rates.alpha[q], rates.beta[q]
        alpha_text = _pm(alpha, rates.alpha_se[q]) if is_bias_decaying(alpha) else f"{_g(alpha, 2)} (no decay)"
        if alpha == EXACT_RATE:  # a stand-in, not a fit: the column is exact on the screened levels
            console.print(f"  {name}: alpha, beta: none (every level difference is 0)")
        else:
            console.print(f"  {name}: alpha = {alpha_text}, beta = {_pm(beta, rates.beta_se[q])}")
        if c.mc_exponent is None:
            console.print(f"    {c.mlmc_regime}")
        else:
            console.print(f"    cost to RMSE eps: MC eps^-{c.mc_exponent:.2f}, MLMC {c.mlmc_regime}")


def _predictions_table(screening: ScreeningRecord) -> Any:
    """Cost of MLMC and MC at each planned tolerance; a load curve's tolerances grouped by QoI (:func:`tol_text`)."""
    # A tolerance whose bias the finest allowed grid cannot reach is planned on that grid all the same
    # (the rows stay comparable); the mark says that `mlmc` refuses it.
    unreachable = any(not p.is_bias_met for p in screening.predictions)
    captions = ["tol: qoi.<name>.tol, or 1 % of the QoI's finest screened mean where the config sets none, times "
                "2, 1, 1/2, 1/4 and 1/8",
                "levels, N_l: the optimal plan (0: a level it leaves out); a run takes at least two levels above the "
                "plan's coarsest for its bias test, so its own levels and N_l differ"]
    if unreachable:
        captions.append("* bias above sqrt(theta) tol on the finest allowed grid: mlmc refuses it")
    rates = screening.rates
    if min(np.min(rates.alpha), np.min(rates.beta), rates.gamma) < RATE_FLOOR:
        captions.append(f"planned, as runs plan, with every rate raised to at least {RATE_FLOOR:g}")
    table = _table("Predicted from the screening (CPU time of the samples)")
    table.caption, table.caption_justify = "\n".join(captions), "left"
    # One column's tolerance per line, folded rather than cut: at 80 columns rich cut "mean_gap=4.93058e-05"
    # to "mean_gap=4.93058e…" and "max_pressure=0.00339897" to "max_pressure=0.00…".
    cells = [_marked_tol_cell(screening.qoi_names, p) for p in screening.predictions]
    # Several columns: rich gave the tolerances 17 characters at 80 columns and folded "max_pressure=0.0034"
    # mid-number; N_l, wrapping between its counts, leaves them their width.
    several = any("\n" in cell for cell in cells)
    widest = max((len(line) for cell in cells for line in cell.splitlines()), default=0)
    table.add_column("tol", justify="right", overflow="fold", min_width=min(widest, _TOL_LINE) if several else None)
    table.add_column("levels", justify="right")
    table.add_column("N_l", justify="right", max_width=14 if several else None)
    for column in ("MLMC", "MC", "MC/MLMC"):
        table.add_column(column, justify="right")
    for p, cell in zip(screening.predictions, cells):
        table.add_row(
            cell,
            f"0..{p.finest_level}",
            " ".join(_planned_count(n) for n in p.n_samples),
            format_duration(p.mlmc_seconds),
            format_duration(p.mc_seconds),
            _g(p.work_ratio),
        )
    return table


#: Longest line of a tolerance cell of the prediction table: longer ones break after their "=".
_TOL_LINE = 20


def _tol_cell(names: Sequence[str], tol: Sequence[float], marked: Collection[str] = ()) -> str:
    """The tolerances of a prediction, one column (or group of a load curve's) per line, a long line broken
    after its ``=`` (``contact_area@0.01=`` / ``0.0492``) rather than folded mid-number; the lines of the
    columns ``marked`` end in `` *`` (a load curve's group line where a column it stands for is marked)."""
    parts = tol_text(names, tol, digits=3).split(", ")
    keys = [part.split("=", 1)[0] for part in parts]
    grouped = {split_column(name)[0] for name in marked if name not in keys}  # columns a group line stands for
    parts = [part + " *" if key in marked or key in grouped else part for part, key in zip(parts, keys)]
    return "\n".join(part.replace("=", "=\n", 1) if len(part) > _TOL_LINE else part for part in parts)


def _marked_tol_cell(names: Sequence[str], plan: Any) -> str:
    """:func:`_tol_cell` of a prediction whose bias the finest allowed grid misses, marked at the columns that
    miss it (the mark ended the cell, next to the last QoI: ``clusters=2.5 *`` where contact_area's bias missed).
    A plan without the columns (older files), or whose columns all meet their share, is marked at its end."""
    if plan.is_bias_met:
        return _tol_cell(names, plan.tol)
    unmet = {names[q] for q in plan.unmet_columns or () if 0 <= q < len(names)}
    return _tol_cell(names, plan.tol, unmet) if unmet else _tol_cell(names, plan.tol) + " *"


def render_runs(console: Any, runs: Sequence[ReportedRun], qoi_names: Sequence[str],
                units: dict[str, str] | None = None) -> None:
    """Every run as a block of lines (:func:`format_run`)."""
    console.print("[bold]Estimation runs[/bold]")
    for run in runs:
        for line in format_run(run.record, qoi_names, units or {}, measured_ratio=run.measured_ratio):
            console.print(escape(line), highlight=False)


def _add_qoi_column(table: Any) -> None:
    """The QoI column of a table of result columns (cells of :func:`_qoi_cell`), folded rather than cut.

    At 80 columns rich cut ``clusters@0.1 [...]`` and ``clusters@0.02 [...]`` alike to ``clusters…``: the load,
    which tells the rows apart, was lost.
    """
    table.add_column("QoI", justify="left", overflow="fold")
    table.caption, table.caption_justify = "N_l: samples per level, from level 0", "left"


def _qoi_cell(name: str, unit: str, power: int = 1) -> str:
    """A QoI cell on lines of their own: the QoI, a load-curve column's load, the unit (``contact_area`` /
    ``@0.02`` / ``[%^2]``), so that a narrow column keeps them all."""
    text = _power(unit, power)
    lines = [*name.replace("@", "\n@").splitlines(), *([f"[{text}]"] if text else [])]
    return escape("\n".join(lines))


def _variance_table(runs: Sequence[RunRecord], units: dict[str, str]) -> Any:
    """Every finished variance run, one row per QoI column."""
    table = _table("Variance (MLMC, RMSE on Var(Q))")
    _add_qoi_column(table)
    for column in ("Var(Q) ± stat.", "sd(Q)", "RMSE", "tol", "bias", "N_l", "met"):
        table.add_column(column, justify="right")
    for run in runs:
        outcome = run.outcome
        for q, name in enumerate(run.qoi_names or ()):
            variance = outcome.estimate[q]
            # A run stopped before its bias was estimated has no RMSE, only a statistical error (its line says
            # "bias not estimated"): "-" rather than a bias of 0 and an RMSE equal to the statistical error.
            is_estimated = outcome.is_bias_estimated
            table.add_row(
                _qoi_cell(name, _column_unit(units, name), 2),
                value_error_text(variance, outcome.stat_error[q]),
                _g(math.sqrt(variance)) if variance >= 0 else "-",
                *(_beside(outcome.rmse[q], run.tol[q]) if is_estimated else ("-", _g(run.tol[q]))),
                _g(outcome.bias_estimate[q], 2) if is_estimated else "-",
                " ".join(str(n) for n in outcome.n_samples),
                "yes" if outcome.tol_met else "no",
            )
    return table


def _distribution_table(runs: Sequence[RunRecord], units: dict[str, str]) -> Any:
    """Every finished cdf run, one row per quantile (its error bar from the sup-norm RMSE band).

    The run's own cells (RMSE, tol, N_l, met) are on its first row only: repeated on every quantile they wrapped
    each row over two lines at 80 columns. Its RMSE is "-" where the bias was not estimated (the statistical error
    alone is no RMSE), as in the variance table.
    """
    table = _table("Distribution (MLMC CDF, its RMSE in the sup norm; quantiles with error bars)")
    _add_qoi_column(table)
    for column in ("p", "q_p", "error bar", "RMSE", "tol", "N_l", "met"):
        # An error bar is read whole; N_l (one line per run now) may wrap instead.
        table.add_column(column, justify="right", no_wrap=column == "error bar")
    for run in runs:
        outcome, distribution = run.outcome, run.outcome.distribution
        unit = _column_unit(units, distribution.column)
        is_rmse = is_rmse_measured(outcome) and bool(outcome.is_bias_estimated)
        run_cells = (*(_beside(outcome.rmse[0], run.tol[0]) if is_rmse else ("-", _g(run.tol[0]))),
                     " ".join(str(n) for n in outcome.n_samples), "yes" if outcome.tol_met else "no")
        for row, quantile in enumerate(distribution.quantiles or (None,)):
            value, bar = "-", "-"
            is_bracketed = quantile is not None and quantile.value is not None
            if is_bracketed:
                value, lower, upper = _quantile_values(quantile)
                if has_error_band(outcome):  # else the band of an unmeasured RMSE or beside a large bias
                    bar = f"[{lower}, {upper}]"
            # The thresholds on the QoI's lines: runs of one column and tolerance read alike without them.
            s = distribution.thresholds
            qoi = f"{_qoi_cell(distribution.column, unit)}\ns {_g(s[0], 4)} .. {_g(s[-1], 4)}\n({len(s)} values)"
            table.add_row(
                qoi if row == 0 else "",
                "-" if quantile is None else _g(quantile.probability), value, bar,
                *(run_cells if row == 0 else ("",) * len(run_cells)),
            )
    return table


def render_targets(console: Any, runs: Sequence[RunRecord], units: dict[str, str] | None = None) -> None:
    """The "Variance" and "Distribution" tables of the finished variance and cdf runs (nothing without any)."""
    units = units or {}
    finished = [run for run in runs if run.is_finished]
    variance = [run for run in finished if run.method == "variance"]
    cdf = [run for run in finished if run.method == "cdf" and run.outcome.distribution is not None]
    if variance:
        _print_table(console, _variance_table(variance, units))
    if cdf:
        _print_table(console, _distribution_table(cdf, units))


def render_sweep(console: Any, rows: Sequence[Any], *, key: str, level: int,
                 units: Sequence[dict[str, str]]) -> None:
    """The table of ``roughuq sweep``: each value's MC estimate per QoI, written as the report writes one.

    ``units`` has one mapping per row, QoI names to their unit labels (``%``, ...), as the report's config
    summary has (a sweep of ``qoi.NAME.unit`` gives each row its own).
    """
    table = _table(escape(f"Sweep of {key} (plain MC on level {level}; bias not estimated)"))
    for column in ("value", "grid", "QoI", "estimate ± stat. error", "N", "CPU time"):
        table.add_column(column, justify="right")
    for row, row_units in zip(rows, units, strict=True):
        outcome = row.run.outcome
        for q, name in enumerate(row.run.qoi_names):
            table.add_row(
                escape(row.value), str(row.grid), escape(_labelled(name, _column_unit(row_units, name))),
                value_error_text(outcome.estimate[q], outcome.stat_error[q]), str(outcome.n_samples[0]),
                format_duration(outcome.seconds),
            )
    _print_table(console, table)


def _out_option(path: str) -> str:
    """`` --out PATH`` for a study file ``roughuq screen`` would not find by the config's default ``output.path``."""
    return f" --out {escape(path)}" if path else ""


def _settings_text(settings: dict[str, Any] | None) -> str:
    """`` (estimator corrected)``: a QoI's settings beyond its unit and tolerance, or nothing."""
    if not settings:
        return ""
    return " (" + ", ".join(f"{key.replace('_', ' ')} {value:g}" if isinstance(value, float) else
                            f"{key.replace('_', ' ')} {value}" for key, value in settings.items()) + ")"


def render_report(report: dict[str, Any], console: Any) -> None:
    """Print a :func:`study_report` (or its JSON round trip) with rich."""
    config = report["config"]
    grids = config["grids"]
    units = config["qoi"]
    kind = "Shard" if report.get("role") == "shard" else "Study"
    console.print(f"[bold]{kind}[/bold] {escape(report['path'])} (created {report['created']}, "
                  f"roughuq {report['code_version']})")
    console.print(
        f"surface L={config['system_size']:g}, k = {config['k_l']:g}/{config['k_r']:g}/{config['k_s']:g}, "
        f"H={config['hurst']:g}, rms height {config['rms_height']:g}; E*={config['e_star']:g}; "
        f"load {load_text(config['load'])}; grids {', '.join(str(n) for n in grids)}; seed {config['seed']}",
        highlight=False,
    )
    settings = config.get("qoi_settings", {})  # absent from the JSON of earlier versions
    console.print(escape("QoIs: " + ", ".join(f"{name} [{unit}]{_settings_text(settings.get(name))}"
                                              for name, unit in units.items())), highlight=False)
    counts = "; ".join(
        f"{stage}: " + ", ".join(f"L{level} {n}" for level, n in levels.items())
        for stage, levels in report["samples"].items()
    )
    console.print(f"samples stored: {counts or 'none'}", highlight=False)
    if report.get("role") == "shard":
        console.print(_shard_text(report["path"], is_running=bool(report.get("is_running"))), highlight=False)
    elif report["screening"] is not None:
        screening = ScreeningRecord.from_json(report["screening"])
        render_screening(console, screening, report["qoi_names"], units, grids=grids)
    elif "screening" in report["samples"] and report.get("is_running"):
        console.print("screening in progress (another process holds the study)")
    elif "screening" in report["samples"]:  # samples but no record: stopped, or refused, before it finished
        console.print(f"screening not finished (stopped or refused before its record): run `roughuq screen CONFIG"
                      f"{_out_option(report['path'])}` to complete it (its stored samples are kept; one it "
                      "refused, e.g. with nothing to estimate, says why again)")
    else:
        # Runs of variance, cdf and mc --level need none: say for which runs it is missing.
        console.print(f"no screening yet (mlmc and mc --tol need one: run `roughuq screen CONFIG"
                      f"{_out_option(report['path'])}`; --tol-var, --tol-cdf and mc --level do not)")
    if report["runs"]:
        reported = [ReportedRun.from_json(run) for run in report["runs"]]
        render_runs(console, reported, report["qoi_names"], units)
        render_targets(console, [run.record for run in reported], units)
    if report.get("load_curves"):
        render_load_curves(console, report["load_curves"], units)
    if report.get("dropped_runs"):
        console.print(f"dropped runs (their samples stay): {', '.join(report['dropped_runs'])}", highlight=False)
    for text in report["warnings"]:
        console.print(f"[yellow]warning:[/yellow] {escape(text)}", highlight=False)


# ---------------------------------------------------------------------------
# Load curves
# ---------------------------------------------------------------------------

#: Loads whose contact area is below this fraction of the nominal area enter the slope fit.
SLOPE_MAX_AREA = 0.1


@dataclass(frozen=True)
class SlopeFit:
    """The slope ``kappa`` of ``A / A0 = kappa * p / (E* sqrt(m2))`` at small loads (:func:`fit_area_slope`).

    Attributes
    ----------
    kappa : float
        Fitted slope (dimensionless).
    error : float
        Bound on its RMS error from the estimates' RMS errors (dimensionless).
    n_points : int
        Loads used.
    max_area : float
        Area fraction below which loads were used.
    """

    kappa: float
    error: float
    n_points: int
    max_area: float


def fit_area_slope(
    *, relative_loads: np.ndarray, area: np.ndarray, area_error: np.ndarray, max_area: float = SLOPE_MAX_AREA
) -> SlopeFit | None:
    """Least-squares slope through the origin of the area fraction against the relative load, at small loads.

    Fits ``a_i = kappa r_i`` on the loads with ``a_i < max_area``:
    ``kappa = sum(r_i a_i) / sum(r_i^2)``. Through the origin because
    ``A = 0`` at zero load; on small loads only because the relation is the
    small-load asymptote (the area grows more slowly than linearly as the
    contact spreads). The estimates of one run share their surfaces, so their
    errors are correlated in an unknown way; the error of ``kappa`` is the
    bound that holds for any correlation, ``sum(r_i e_i) / sum(r_i^2)``
    (``e_i`` the estimates' RMS errors; equal to the exact error if they are
    fully correlated, at most ``sqrt(n)`` times it if independent).

    Parameters
    ----------
    relative_loads : ndarray, shape (n_loads,)
        ``r = p / (E* sqrt(m2))``, dimensionless, > 0.
    area, area_error : ndarray, shape (n_loads,)
        Estimated contact-area fraction ``A / A0`` (dimensionless) and its RMS error.
    max_area : float
        Largest area fraction used.

    Returns
    -------
    SlopeFit or None
        None when no load has ``area < max_area``.
    """
    r, a, e = (np.asarray(x, dtype=float) for x in (relative_loads, area, area_error))
    small = a < max_area
    if not np.any(small):
        return None
    r, a, e = r[small], a[small], e[small]
    denominator = float(np.sum(r * r))
    return SlopeFit(
        kappa=float(np.sum(r * a)) / denominator,
        error=float(np.sum(r * np.abs(e))) / denominator,
        n_points=int(small.sum()),
        max_area=max_area,
    )


def _relative_loads(config: Any, loads: np.ndarray) -> np.ndarray:
    """The loads as ``p / (E* sqrt(m2))`` (converting absolute pressures with the spectrum's ``m2``)."""
    if config.load.kind == "relative":
        return loads
    # Here only: the spectrum pulls in the FFTs, which the report otherwise does not need.
    from rough_uq.physics.surface import SurfaceSpectrum

    surface = config.surface
    spectrum = SurfaceSpectrum(system_size=surface.system_size, k_l=surface.k_l, k_r=surface.k_r, k_s=surface.k_s,
                               hurst=surface.hurst, rms_height=surface.rms_height)
    return loads / (config.material.e_star * spectrum.rms_slope)


def _area_fraction_scale(config: Any) -> float:
    """Factor from the stored contact area to a fraction (percent: 1/100)."""
    settings = config.qoi.get("contact_area")
    return 0.01 if settings is not None and settings.unit == "percent" else 1.0


def error_name(outcome: Any) -> str:
    """``RMSE``, or ``stat. error`` for a run whose bias is not estimated (``mc --level``: its RMSE is unknown)."""
    return "RMSE" if outcome.is_bias_estimated else "stat. error"


def load_curves(qoi_names: Sequence[str], runs: Sequence[RunRecord], config: Any) -> list[dict[str, Any]]:
    """Every finished run's estimates as curves over the increasing load (empty for a single-load study).

    Returns
    -------
    list of dict
        Per finished run: ``run_id``, ``label`` (:func:`run_label`, the
        table's heading), ``method``, ``loads`` (as given in the
        config, increasing), ``relative_loads`` (``p / (E* sqrt(m2))``),
        ``curves`` (QoI name -> ``{"estimate", "rmse", "stat_error"}``, lists
        over the loads; ``rmse`` is the statistical error where the bias is not
        estimated), ``error`` (:func:`error_name`: what ``rmse`` is), and
        ``kappa`` (:class:`SlopeFit` as a dict, or None without
        ``contact_area`` or without a load of area below
        :data:`SLOPE_MAX_AREA`).
    """
    if not any(split_column(name)[1] is not None for name in qoi_names):
        return []
    loads = np.array(sorted({split_column(name)[1] for name in qoi_names}))
    relative = _relative_loads(config, loads)
    out = []
    for run in runs:
        if not run.is_finished or run.method in TARGET_METHODS:
            continue
        outcome = run.outcome
        curves: dict[str, dict[str, list[float]]] = {}
        for q, name in enumerate(qoi_names):
            qoi, load = split_column(name)
            curve = curves.setdefault(qoi, {key: [math.nan] * loads.size for key in ("estimate", "rmse", "stat_error")})
            j = int(np.searchsorted(loads, load))
            curve["estimate"][j], curve["rmse"][j] = outcome.estimate[q], outcome.rmse[q]
            curve["stat_error"][j] = outcome.stat_error[q]
        kappa = None
        if "contact_area" in curves:
            scale = _area_fraction_scale(config)
            area = curves["contact_area"]
            fit = fit_area_slope(relative_loads=relative, area=np.array(area["estimate"]) * scale,
                                 area_error=np.array(area["rmse"]) * scale)
            kappa = None if fit is None else dict(vars(fit))
        out.append({"run_id": run.run_id, "label": run_label(run, qoi_names), "method": run.method,
                    "error": error_name(outcome), "loads": loads.tolist(),
                    "relative_loads": relative.tolist(), "curves": curves, "kappa": kappa})
    return out


def render_load_curves(console: Any, curves: Sequence[dict[str, Any]], units: dict[str, str] | None = None) -> None:
    """One table per finished run: each QoI's estimate ± RMSE against the load, and the fitted ``kappa``.

    A table is headed by the run's label (:func:`run_label`), not by its id:
    a curve's id names every column's tolerance and runs to hundreds of characters.
    """
    units = units or {}
    for entry in curves:
        table = _table(escape(f"Load curve of {entry['label']} (estimate ± {entry['error']})"))
        # Relative loads are the second column already: a first column repeating them made the table wider than
        # most terminals for two QoIs.
        is_absolute = entry["loads"] != entry["relative_loads"]
        if is_absolute:
            table.add_column("load", justify="right")
        table.add_column("p/(E* sqrt(m2))", justify="right")
        names = list(entry["curves"])
        for name in names:
            table.add_column(escape(_labelled(name, units.get(name, ""))), justify="right")
        for j, load in enumerate(entry["loads"]):
            cells = [value_error_text(entry["curves"][n]["estimate"][j], entry["curves"][n]["rmse"][j]) for n in names]
            table.add_row(*([_g(load, 4)] if is_absolute else []), _g(entry["relative_loads"][j], 4), *cells)
        _print_table(console, table)
        fit = entry.get("kappa")
        if fit is not None:
            console.print(
                f"  kappa = {value_error_text(fit['kappa'], fit['error'])} in A/A0 = kappa p/(E* sqrt(m2)), "
                f"{_slope_source(fit)}; Persson's theory: sqrt(8/pi) = {math.sqrt(8 / math.pi):.3f}, numerical "
                "studies: about 2",
                highlight=False,
            )


def _slope_source(fit: dict[str, Any]) -> str:
    """Where ``kappa`` comes from: a fit through 0 on several small loads, or the ratio at the only one."""
    if fit["n_points"] == 1:
        return (f"the slope of the line through 0 and the only load with A/A0 < {fit['max_area']:g}\n  (more loads "
                "below that area in the curve give a least-squares fit)")
    return f"fitted through 0\n  on the {fit['n_points']} loads with A/A0 < {fit['max_area']:g}"

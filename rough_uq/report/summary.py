"""What a study file holds, as a dict (``roughuq report --json``) and as text that fits 80 columns.

:func:`study_report` gathers the config summary, the sample counts, the
screening table and rates with the complexity they imply, and every run with
its measured and predicted costs; :func:`render_report` prints it.

Three kinds of time, each with one name and unit everywhere:

* **elapsed** (s): wall-clock time of the command that ran the run
  (JSON ``elapsed``);
* **CPU-seconds** (CPU-s): the wall times of the samples, each measured in the
  process that computed it, summed (JSON keys with ``seconds``: ``seconds``,
  ``mean_seconds``, ``mlmc_seconds``, ``mc_seconds``,
  ``mc_seconds_predicted``); with 2 workers a run's CPU-seconds are about
  twice its elapsed time;
* **modelled cost** (ref-s, reference seconds): the cost model the estimators
  plan with (JSON keys with ``cost``: ``cost``, ``mean_cost``, ``mc_cost``,
  ``mlmc_cost``), independent of the machine's load.

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
``mc_seconds_measured`` and ``measured_ratio``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich.markup import escape

from rough_uq.problem.batch import STAGE_SCREENING
from rough_uq.study.records import (
    MIN_ALPHA,
    RATE_TIE,
    RunRecord,
    ScreeningRecord,
    complexity,
    count_not_converged,
    read_run_records,
    read_screening_record,
)
from rough_uq.study.store import FORMAT_VERSION, StudyStore

__all__ = [
    "MIN_ALPHA",
    "RATE_TIE",
    "ReportedRun",
    "complexity",
    "derive_runs",
    "format_run",
    "is_locked_by_running_process",
    "load_text",
    "render_report",
    "render_runs",
    "render_screening",
    "screening_json",
    "study_report",
]

_STOP_REASONS = {
    "max_level": "the bias needs a grid finer than grid.max_level",
    "max_cost": "stopped at --max-cost",
    "bias": "the bias of this level is larger than the tolerance allows",
}


def load_text(load: dict[str, float]) -> str:
    """The load as it is written in a config, e.g. ``relative: 0.1``."""
    return ", ".join(f"{kind}: {value:g}" for kind, value in load.items())


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


def is_locked_by_running_process(path: str | Path) -> bool:
    """Whether a live process holds the study's lock (``<file>.lock`` names its pid, see :mod:`rough_uq.study.store`)."""
    lock = Path(str(path) + ".lock")
    try:
        pid = int(lock.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass(frozen=True)
class ReportedRun:
    """A run as the report shows it: its record, and the measured plain MC at its tolerances if any.

    Attributes
    ----------
    record : RunRecord
        Its status is as seen now (``running`` / ``interrupted`` for an unfinished run).
    mc_seconds_measured : float or None
        CPU-seconds of a finished MC run at the same tolerances (MLMC runs only).
    """

    record: RunRecord
    mc_seconds_measured: float | None = None

    @property
    def measured_ratio(self) -> float | None:
        """Measured MC over MLMC CPU-seconds (None without a measured MC run)."""
        if self.mc_seconds_measured is None or self.record.outcome is None:
            return None
        seconds = self.record.outcome.seconds
        return self.mc_seconds_measured / seconds if seconds > 0 else math.inf

    def to_json(self) -> dict[str, Any]:
        """The run as ``roughuq report --json`` lists it: ``run_id``, the stored record, the derived ratios."""
        data = {"run_id": self.record.run_id, **self.record.to_json()}
        if self.record.is_finished:
            data["work_ratio"] = self.record.outcome.work_ratio
        if self.mc_seconds_measured is not None:
            data["mc_seconds_measured"] = self.mc_seconds_measured
            data["measured_ratio"] = self.measured_ratio
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ReportedRun:
        """Read an entry of the report's ``runs`` (the derived ratios are recomputed, not read)."""
        measured = data.get("mc_seconds_measured")
        return cls(RunRecord.from_json(data), None if measured is None else float(measured))


def derive_runs(runs: Sequence[RunRecord]) -> list[ReportedRun]:
    """The runs a report shows, with what is derived from them: MC/MLMC ratios, predicted and measured.

    ``work_ratio`` (:attr:`~rough_uq.study.records.RunOutcome.work_ratio`):
    predicted plain-MC modelled cost over the run's modelled cost. Where a
    finished MC run at the same tolerances exists, ``mc_seconds_measured``
    (its CPU-seconds) and ``measured_ratio`` (over the MLMC run's
    CPU-seconds). Dropped runs (``roughuq drop``) are left out.
    """
    kept = [run for run in runs if run.status != "dropped"]
    measured_mc = {run.tol: run.outcome.seconds for run in kept if run.method == "mc" and run.is_finished}
    return [
        ReportedRun(run, measured_mc.get(run.tol) if run.method == "mlmc" and run.is_finished else None)
        for run in kept
    ]


def _seen_status(run: ReportedRun, is_running: bool) -> ReportedRun:
    """An unfinished run is ``running`` while a live process holds the study, else ``interrupted``."""
    if run.record.status == "finished":
        return run
    return replace(run, record=replace(run.record, status="running" if is_running else "interrupted"))


def _report_warnings(screening: ScreeningRecord | None, runs: Sequence[ReportedRun], n_not_converged: int) -> list[str]:
    warnings = [d.message for d in screening.diagnostics] if screening is not None else []
    for run in runs:
        record = run.record
        diagnostics = record.outcome.diagnostics if record.outcome is not None else ()
        warnings += [f"{record.run_id}: {d.message}" for d in diagnostics]
        if record.status == "interrupted":
            warnings.append(
                f"{record.run_id}: interrupted; rerun the same command to resume, or "
                f"`roughuq drop {record.run_id}` to forget it"
            )
    if n_not_converged:
        warnings.append(
            f"{n_not_converged} stored samples have a solve that did not converge even after the retry; "
            "their QoIs (from the last iterate) are included"
        )
    return warnings


def screening_json(screening: ScreeningRecord | None) -> dict[str, Any] | None:
    """The screening as ``roughuq screen --json`` and ``report --json`` show it: the record and its complexity."""
    if screening is None:
        return None
    return {**screening.to_json(), "complexity": [c.to_json() for c in screening.complexity]}


def study_report(store: StudyStore, config: Any) -> dict[str, Any]:
    """Everything ``roughuq report`` shows, as a JSON-able dict (see :func:`derive_runs` for the ratios)."""
    screening = read_screening_record(store)
    stored_runs = read_run_records(store)
    path = getattr(store, "path", "")
    is_running = bool(path) and is_locked_by_running_process(path)
    runs = [_seen_status(run, is_running) for run in derive_runs(stored_runs)]
    n_not_converged = _not_converged(store)
    return {
        "path": str(path),
        "format_version": FORMAT_VERSION,
        "code_version": store.code_version,
        "created": store.created,
        "config_hash": store.config_hash,
        "config": _config_summary(config),
        "qoi_names": list(store.qoi_names),
        "samples": _sample_counts(store, stored_runs),
        "screening": screening_json(screening),
        "runs": [run.to_json() for run in runs],
        "dropped_runs": [run.run_id for run in stored_runs if run.status == "dropped"],
        "is_running": is_running,
        "n_not_converged": n_not_converged,
        "warnings": _report_warnings(screening, runs, n_not_converged),
    }


# ---------------------------------------------------------------------------
# Text
# ---------------------------------------------------------------------------


def _g(value: float | None, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}g}"


def _pm(value: float, error: float) -> str:
    return f"{_g(value, 3)} ± {_g(error, 2)}"


def _value_error(value: float, error: float) -> str:
    """``value ± error`` with the error to two significant digits and the value to the same decimal."""
    if not (math.isfinite(value) and math.isfinite(error)) or error <= 0:
        return f"{_g(value, 5)} ± {_g(error, 2)}"
    decimals = max(0, 1 - math.floor(math.log10(error)))
    if decimals > 8:
        return f"{value:.6g} ± {error:.2g}"
    return f"{value:.{decimals}f} ± {error:.{decimals}f}"


def _seconds(value: float | None, unit: str = "s") -> str:
    """A duration with its unit: ``12.3 s``, ``4.5 min CPU``, ..."""
    if value is None:
        return "-"
    suffix = "" if unit == "s" else f" {unit}"
    if value < 120:
        return f"{value:.3g} s{suffix}"
    if value < 7200:
        return f"{value / 60:.3g} min{suffix}"
    return f"{value / 3600:.3g} h{suffix}"


def _unit(label: str) -> str:
    return "" if label in ("fraction", "") else f" {label}"


def _tol_text(names: Sequence[str], tol: Sequence[float]) -> str:
    return ", ".join(f"{name}={eps:g}" for name, eps in zip(names, tol))


def format_run(run: RunRecord, qoi_names: Sequence[str], units: dict[str, str], *,
               measured_ratio: float | None = None) -> list[str]:
    """A run as a few lines of at most about 80 characters (one summary line per QoI).

    ``measured_ratio`` is the measured MC/MLMC ratio (:attr:`ReportedRun.measured_ratio`) where known.
    """
    head = f"{run.method} {_tol_text(qoi_names, run.tol)}"
    outcome = run.outcome
    if run.status != "finished" or outcome is None:
        if run.status == "running":
            return [f"{head}: running (another process is computing it)"]
        return [f"{head}: interrupted; rerun the same command to resume"]
    levels = outcome.levels
    if run.method == "mc":
        where = f"level {levels[-1]}, N {outcome.n_samples[-1]}"
    else:
        where = f"levels {levels[0]}..{levels[-1]}, N_l {' '.join(str(n) for n in outcome.n_samples)}"
    reason = outcome.stop_reason
    if outcome.tol_met:
        lines = [f"{head}: tolerance met", f"  {where}"]
    else:
        lines = [f"{head}: NOT MET ({reason})", f"  {_STOP_REASONS.get(reason, reason)}; {where}"]
    lines += [_qoi_line(outcome, q, name, run.tol[q], units) for q, name in enumerate(qoi_names)]
    lines.append(
        f"  time: elapsed {_seconds(outcome.elapsed)}; samples {_seconds(outcome.seconds, 'CPU')}; "
        f"modelled cost {_g(outcome.cost)} ref-s"
    )
    if run.method == "mlmc":
        text = (f"  plain MC: {_seconds(outcome.mc_seconds_predicted, 'CPU')} predicted; "
                f"MC/MLMC {_g(outcome.work_ratio, 2)} predicted")
        if measured_ratio is not None:
            text += f", {_g(measured_ratio, 2)} measured"
        lines.append(text)
    return lines


def _qoi_line(outcome: Any, q: int, name: str, tol: float, units: dict[str, str]) -> str:
    """``  name = value ± error unit (RMSE r <= tol t, bias b)`` for QoI ``q`` of a finished run."""
    rmse = outcome.rmse[q]
    relation = "<=" if rmse <= tol * (1 + 1e-12) else ">"
    bias = f"bias {_g(outcome.bias_estimate[q], 2)}" if outcome.is_bias_estimated else "bias not estimated"
    return (f"  {name} = {_value_error(outcome.estimate[q], outcome.stat_error[q])}{_unit(units.get(name, ''))} "
            f"(RMSE {_g(rmse, 2)} {relation} tol {_g(tol)}, {bias})")


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
        console.print(_screening_table(stats, q, name, units.get(name)))
    table = _table("Time per sample")
    for column in ("level", "grid", "modelled cost", "measured"):
        table.add_column(column, justify="right")
    for i, level in enumerate(stats.levels):
        grid = str(grids[level]) if level < len(grids) else "-"
        table.add_row(str(level), grid, f"{_g(stats.mean_cost[i])} ref-s", _seconds(stats.mean_seconds[i], "CPU"))
    console.print(table)
    _print_rates(console, screening, qoi_names)
    if screening.predictions:
        console.print(_predictions_table(screening))


def _screening_table(stats: Any, q: int, name: str, unit: str | None) -> Any:
    table = _table(escape(f"Screening of {name}" + (f" [{unit}]" if unit else "") + " per level"))
    for column in ("level", "N", "mean Q", "var Q", "mean Y", "var Y", "kurt", "check"):
        table.add_column(column, justify="right")
    for i, level in enumerate(stats.levels):
        table.add_row(
            str(level), str(stats.n_samples[i]),
            _g(stats.mean_fine[i][q], 4), _g(stats.var_fine[i][q]),
            _g(stats.mean_diff[i][q]), _g(stats.var_diff[i][q]),
            _g(stats.kurtosis[i][q]), _g(stats.consistency[i][q], 2),
        )
    return table


def _print_rates(console: Any, screening: ScreeningRecord, qoi_names: Sequence[str]) -> None:
    rates = screening.rates
    console.print("Rates: |E[Y_l]| ~ 2^(-alpha l), Var(Y_l) ~ 2^(-beta l), cost ~ 2^(gamma l)")
    console.print(f"  gamma = {_pm(rates.gamma, rates.gamma_se)} (cost)")
    for q, name in enumerate(qoi_names):
        c = screening.complexity[q]
        alpha, beta = rates.alpha[q], rates.beta[q]
        alpha_text = _pm(alpha, rates.alpha_se[q]) if c.mc_exponent is not None else f"{_g(alpha, 2)} (no decay)"
        console.print(f"  {name}: alpha = {alpha_text}, beta = {_pm(beta, rates.beta_se[q])}")
        if c.mc_exponent is None:
            console.print(f"    {c.mlmc_regime}")
        else:
            console.print(f"    cost to RMSE eps: MC eps^-{c.mc_exponent:.2f}, MLMC {c.mlmc_regime}")


def _predictions_table(screening: ScreeningRecord) -> Any:
    table = _table("Predicted from the screening (CPU time of the samples)")
    for column in ("tol", "levels", "N_l", "MLMC", "MC", "MC/MLMC"):
        table.add_column(column, justify="right")
    for p in screening.predictions:
        table.add_row(
            ", ".join(_g(t) for t in p.tol),
            f"0..{p.finest_level}",
            " ".join(str(n) for n in p.n_samples),
            _seconds(p.mlmc_seconds),
            _seconds(p.mc_seconds),
            _g(p.work_ratio),
        )
    return table


def render_runs(console: Any, runs: Sequence[ReportedRun], qoi_names: Sequence[str],
                units: dict[str, str] | None = None) -> None:
    """Every run as a block of lines (:func:`format_run`)."""
    console.print("[bold]Estimation runs[/bold]")
    for run in runs:
        for line in format_run(run.record, qoi_names, units or {}, measured_ratio=run.measured_ratio):
            console.print(escape(line), highlight=False, soft_wrap=False)


def render_report(report: dict[str, Any], console: Any) -> None:
    """Print a :func:`study_report` (or its JSON round trip) with rich."""
    config = report["config"]
    grids = config["grids"]
    units = config["qoi"]
    console.print(f"[bold]Study[/bold] {escape(report['path'])} (created {report['created']}, "
                  f"roughuq {report['code_version']})")
    console.print(
        f"surface L={config['system_size']:g}, k = {config['k_l']:g}/{config['k_r']:g}/{config['k_s']:g}, "
        f"H={config['hurst']:g}, rms height {config['rms_height']:g}; E*={config['e_star']:g}; "
        f"load {load_text(config['load'])}; grids {', '.join(str(n) for n in grids)}; seed {config['seed']}",
        highlight=False,
    )
    console.print(escape("QoIs: " + ", ".join(f"{name} [{unit}]" for name, unit in units.items())), highlight=False)
    counts = "; ".join(
        f"{stage}: " + ", ".join(f"L{level} {n}" for level, n in levels.items())
        for stage, levels in report["samples"].items()
    )
    console.print(f"samples stored: {counts or 'none'}", highlight=False)
    if report["screening"] is not None:
        screening = ScreeningRecord.from_json(report["screening"])
        render_screening(console, screening, report["qoi_names"], units, grids=grids)
    else:
        console.print("no screening yet: run `roughuq screen CONFIG`")
    if report["runs"]:
        render_runs(console, [ReportedRun.from_json(run) for run in report["runs"]], report["qoi_names"], units)
    if report.get("dropped_runs"):
        console.print(f"dropped runs (their samples stay): {', '.join(report['dropped_runs'])}", highlight=False)
    for text in report["warnings"]:
        console.print(f"[yellow]warning:[/yellow] {escape(text)}", highlight=False)

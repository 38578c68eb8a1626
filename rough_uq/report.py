"""What a study file holds, as a dict (``roughuq report --json``) and as rich tables.

:func:`study_report` gathers the config summary, the sample counts, the
screening table and rates with the complexity they imply, and every run with
its measured and predicted costs; :func:`render_report` prints it.

Complexity (SPEC section 5): plain MC to RMS error ``eps`` costs
``eps^-(2 + gamma/alpha)``; MLMC costs ``eps^-2`` if ``beta > gamma``,
``eps^-2 log(eps)^2`` if ``beta == gamma`` and ``eps^-(2 + (gamma - beta)/alpha)``
if ``beta < gamma``. The exponents are computed per QoI from the fitted rates;
``beta`` and ``gamma`` are called equal when they differ by less than
:data:`RATE_TIE` (about the standard error of a screening fit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from rough_uq.batch import STAGE_SCREENING
from rough_uq.store import StudyStore

__all__ = ["RATE_TIE", "complexity", "study_report", "render_report"]

RATE_TIE = 0.1


def complexity(alpha: float, beta: float, gamma: float) -> dict[str, Any]:
    """Cost exponents of MC and MLMC in ``1/eps`` (and whether MLMC has the ``log^2`` factor)."""
    alpha = max(alpha, 1e-12)
    mc = 2.0 + gamma / alpha
    if abs(beta - gamma) < RATE_TIE:
        mlmc, regime = 2.0, "beta = gamma: eps^-2 log(eps)^2"
    elif beta > gamma:
        mlmc, regime = 2.0, "beta > gamma: eps^-2"
    else:
        mlmc = 2.0 + (gamma - beta) / alpha
        regime = f"beta < gamma: eps^-{mlmc:.2f}"
    return {"mc_exponent": mc, "mlmc_exponent": mlmc, "mlmc_regime": regime}


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


def _sample_counts(store: StudyStore, runs: Sequence[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Stored samples per stage (named by its run) and level."""
    names = {run["stage"]: run["run_id"] for run in runs if "stage" in run}
    names[STAGE_SCREENING] = "screening"
    counts: dict[str, dict[str, int]] = {}
    for level in store.levels():
        for stage in store.stages(level=level):
            n = int(store.sample_indices(level=level, stage=stage).size)
            counts.setdefault(names.get(stage, f"stage {stage}"), {})[str(level)] = n
    return counts


def _not_converged(store: StudyStore) -> int:
    return int(sum(np.count_nonzero(~store.read_samples(level=level).is_converged) for level in store.levels()))


def study_report(store: StudyStore, config: Any) -> dict[str, Any]:
    """Everything ``roughuq report`` shows, as a JSON-able dict.

    Each run gets ``work_ratio`` = predicted MC cost / MLMC cost (both
    modelled), and, where an MC run at the same tolerances exists in the file,
    ``mc_seconds_measured`` and ``measured_ratio``.
    """
    screening = store.read_screening()
    if screening is not None:
        rates = screening["rates"]
        screening = dict(screening)
        screening["complexity"] = [
            complexity(a, b, rates["gamma"]) for a, b in zip(rates["alpha"], rates["beta"])
        ]
    runs = [dict(run) for run in store.read_runs()]
    measured_mc = {
        tuple(run["tol"]): run["seconds"] for run in runs if run["method"] == "mc" and run.get("status") == "finished"
    }
    for run in runs:
        if run.get("status") != "finished":
            continue
        run["work_ratio"] = run["mc_cost"] / run["cost"] if run["cost"] > 0 else math.inf
        if run["method"] == "mlmc" and tuple(run["tol"]) in measured_mc:
            run["mc_seconds_measured"] = measured_mc[tuple(run["tol"])]
            run["measured_ratio"] = run["mc_seconds_measured"] / run["seconds"] if run["seconds"] > 0 else math.inf
    warnings = list(screening.get("warnings", [])) if screening else []
    for run in runs:
        warnings += [f"{run['run_id']}: {text}" for text in run.get("warnings", [])]
        if run.get("status") != "finished":
            warnings.append(f"{run['run_id']}: did not finish (interrupted?); rerun the same command to resume")
    n_not_converged = _not_converged(store)
    if n_not_converged:
        warnings.append(
            f"{n_not_converged} stored samples have a solve that did not converge even after the retry; "
            "their QoIs (from the last iterate) are included"
        )
    return {
        "path": str(getattr(store, "path", "")),
        "format_version": getattr(store, "format_version", None),
        "code_version": store.code_version,
        "created": store.created,
        "config_hash": store.config_hash,
        "config": _config_summary(config),
        "qoi_names": list(store.qoi_names),
        "samples": _sample_counts(store, runs),
        "screening": screening,
        "runs": runs,
        "n_not_converged": n_not_converged,
        "warnings": warnings,
    }


def _g(value: float, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}g}"


def _pm(value: float, error: float) -> str:
    return f"{_g(value, 5)} ± {_g(error, 2)}"


def _seconds(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.3g} s" if value < 120 else f"{value / 60:.3g} min"


def render_screening(console: Any, screening: dict[str, Any], qoi_names: Sequence[str]) -> None:
    """The per-level screening table, the rates with their complexity, and the cost predictions."""
    from rich.table import Table

    stats = screening["statistics"]
    table = Table(title="Screening (per level)")
    for column in ("level", "N"):
        table.add_column(column, justify="right")
    for name in qoi_names:
        for column in ("mean Q", "var Q", "mean Y", "var Y", "kurt", "check"):
            table.add_column(f"{column}\n{name}" if len(qoi_names) > 1 else column, justify="right")
    table.add_column("cost/sample\n(model)", justify="right")
    table.add_column("wall/sample", justify="right")
    for i, level in enumerate(stats["levels"]):
        row = [str(level), str(stats["n_samples"][i])]
        for q in range(len(qoi_names)):
            row += [
                _g(stats["mean_fine"][i][q], 4),
                _g(stats["var_fine"][i][q]),
                _g(stats["mean_diff"][i][q]),
                _g(stats["var_diff"][i][q]),
                _g(stats["kurtosis"][i][q]),
                _g(stats["consistency"][i][q], 2),
            ]
        row += [_seconds(stats["mean_cost"][i]), _seconds(stats["mean_seconds"][i])]
        table.add_row(*row)
    console.print(table)

    rates = screening["rates"]
    table = Table(title="Rates (|E[Y_l]| ~ 2^-alpha l, V_l ~ 2^-beta l, C_l ~ 2^gamma l)")
    for column in ("QoI", "alpha", "beta", "gamma", "MC cost", "MLMC cost"):
        table.add_column(column, justify="right")
    for q, name in enumerate(qoi_names):
        c = screening["complexity"][q]
        table.add_row(
            name,
            _pm(rates["alpha"][q], rates["alpha_se"][q]),
            _pm(rates["beta"][q], rates["beta_se"][q]),
            _pm(rates["gamma"], rates["gamma_se"]),
            f"eps^-{c['mc_exponent']:.2f}",
            c["mlmc_regime"],
        )
    console.print(table)

    table = Table(title="What accuracy will cost (predicted from the screening)")
    for column in ("tol", "levels", "N_l", "MLMC", "MC", "MC/MLMC"):
        table.add_column(column, justify="right")
    for p in screening["predictions"]:
        table.add_row(
            ", ".join(_g(t) for t in p["tol"]),
            f"0..{p['finest_level']}",
            " ".join(str(n) for n in p["n_samples"]),
            _seconds(p["mlmc_seconds"]),
            _seconds(p["mc_seconds"]),
            _g(p["work_ratio"]),
        )
    console.print(table)


def render_runs(console: Any, runs: Sequence[dict[str, Any]], qoi_names: Sequence[str]) -> None:
    """One row per run (and per QoI): tolerance, estimate ± error, bias, N_l, costs."""
    from rich.table import Table

    table = Table(title="Estimation runs")
    for column in ("run", "QoI", "tol", "estimate ± stat. error", "bias", "N_l", "cost (wall)",
                   "cost (model)", "MC predicted", "MC/MLMC", "stop"):
        table.add_column(column, justify="right")
    for run in runs:
        if run.get("status") != "finished":
            table.add_row(run["run_id"], "", ", ".join(_g(t) for t in run["tol"]), "(interrupted)")
            continue
        for q, name in enumerate(qoi_names):
            first = q == 0
            ratio = run.get("measured_ratio", run.get("work_ratio"))
            table.add_row(
                run["method"] if first else "",
                name,
                _g(run["tol"][q]),
                _pm(run["estimate"][q], run["stat_error"][q]),
                _g(run["bias_estimate"][q], 2) if run.get("is_bias_estimated", True) else "-",
                " ".join(str(n) for n in run["n_samples"]) + f" (L{run['levels'][0]}..{run['levels'][-1]})"
                if first else "",
                _seconds(run["seconds"]) if first else "",
                _seconds(run["cost"]) if first else "",
                _seconds(run["mc_seconds_predicted"]) if first else "",
                (_g(ratio) + (" measured" if "measured_ratio" in run else "")) if first and run["method"] == "mlmc" else "",
                ("" if run["tol_met"] else "NOT MET: ") + run["stop_reason"] if first else "",
            )
    console.print(table)


def render_report(report: dict[str, Any], console: Any) -> None:
    """Print a :func:`study_report` with rich."""
    config = report["config"]
    console.print(f"[bold]Study[/bold] {report['path']}  (created {report['created']}, roughuq {report['code_version']})")
    console.print(
        f"surface L={config['system_size']:g}, k = {config['k_l']:g}/{config['k_r']:g}/{config['k_s']:g}, "
        f"H={config['hurst']:g}, rms height {config['rms_height']:g}; E*={config['e_star']:g}; load {config['load']}; "
        f"grids {config['grids']}; seed {config['seed']}"
    )
    console.print("QoIs: " + ", ".join(f"{name} [{unit}]" for name, unit in config["qoi"].items()))
    counts = "; ".join(
        f"{stage}: " + ", ".join(f"L{level} {n}" for level, n in levels.items())
        for stage, levels in report["samples"].items()
    )
    console.print(f"samples stored: {counts or 'none'}")
    if report["screening"] is not None:
        render_screening(console, report["screening"], report["qoi_names"])
    else:
        console.print("no screening yet: run `roughuq screen CONFIG`")
    if report["runs"]:
        render_runs(console, report["runs"], report["qoi_names"])
    for text in report["warnings"]:
        console.print(f"[yellow]warning:[/yellow] {text}")

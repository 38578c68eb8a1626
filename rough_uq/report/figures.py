"""Figures of a study: MLMC rates, cost against tolerance, samples per level, load curves, CDFs, one contact sample.

An edge module like :mod:`rough_uq.report.summary`: it reads the JSON-able dict of
:func:`~rough_uq.report.summary.study_report` (never the store), as the typed
records of :mod:`rough_uq.study.records`, and writes PNG files.
matplotlib (the ``plot`` extra) is imported only when a figure is drawn, and
only its object-oriented API is used (``Figure`` on an Agg canvas): no
pyplot, no global state, no display needed.

Conventions
-----------
* Rates are drawn the way :mod:`rough_uq.multilevel.rates` fits them: ``log2`` of the
  per-level statistic against the level ``l``, with the fitted models
  ``|E[Y_l]| = c_alpha 2^(-alpha l)``, ``V_l = c_beta 2^(-beta l)`` and
  ``C_l = c_gamma 2^(gamma l)`` (:class:`~rough_uq.multilevel.rates.Rates`) as
  straight lines. The top axis names the grid ``n_l`` of each level.
* Several QoIs share one tolerance axis: cost against tolerance and the
  choice of the loosest / tightest run use the first QoI's tolerance. The
  screening predicts costs for one ratio of the QoIs' tolerances (its base
  tolerances, scaled); the axis label states it, and runs at another ratio
  are drawn hollow, labelled as such: their cost belongs to other lines.
* Plain MC is measured by ``mc --tol`` runs only, as in the text report
  (:func:`~rough_uq.report.summary.derive_runs`): ``mc --level`` runs sample
  a level the user chose, with another bias.
* A bias rate the text report calls not fitted (``alpha`` at most
  :data:`~rough_uq.study.records.MIN_ALPHA`) gets no fitted line, only a
  legend entry saying so.
* Missing data (no screening, no finished run) skips a figure; it is never
  an error.
"""

from __future__ import annotations

import math
import textwrap
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rough_uq.errors import InvalidParameterError, RoughUQError, is_integer
from rough_uq.physics.qoi import cluster_count, contact_area, label_clusters
from rough_uq.physics.solver import ContactSolution
from rough_uq.problem.sampler import ContactModel, is_coupled_stage, solve_sample
from rough_uq.problem.columns import split_column, tol_number
from rough_uq.report.summary import has_error_band, is_rmse_measured, run_label, tol_text, value_error_text
from rough_uq.multilevel.rates import EXACT_RATE
from rough_uq.study.records import RunRecord, ScreeningRecord, is_bias_decaying

__all__ = ["write_report_plots", "write_sample_figure"]

_DPI = 120
_MISSING = "plots need matplotlib: pip install 'roughuq[plot]'"


def _matplotlib() -> tuple[Any, Any]:
    """``(Figure, FigureCanvasAgg)``, or :class:`RoughUQError` if matplotlib is not installed."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise RoughUQError(_MISSING) from None
    return Figure, FigureCanvasAgg


def _new_figure(width: float, height: float) -> Any:
    figure_class, canvas_class = _matplotlib()
    figure = figure_class(figsize=(width, height), layout="constrained")
    canvas_class(figure)
    return figure


def _save(figure: Any, path: Path) -> Path:
    figure.savefig(path, dpi=_DPI, format="png")
    return path


def _log2_points(levels: Sequence[int], values: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Levels and ``log2(value)`` where the value is positive and finite (a log of 0 is not drawn)."""
    levels = np.asarray(levels, dtype=float)
    values = np.asarray(values, dtype=float)
    keep = np.isfinite(values) & (values > 0)
    return levels[keep], np.log2(values[keep])


def _label_grids(ax: Any, levels: Sequence[int], grids: Sequence[int]) -> None:
    """Integer level ticks below, the grid size ``n_l`` of each level above."""
    levels = [int(level) for level in levels if 0 <= int(level) < len(grids)]
    if not levels:
        return
    ax.set_xticks(levels)
    top = ax.secondary_xaxis("top")
    top.set_xticks(levels, labels=[str(grids[level]) for level in levels])
    top.set_xlabel("grid $n_l$")


def _fit_line(ax: Any, levels: Sequence[int], constant: float, rate: float, label: str, color: str) -> None:
    """``log2(constant 2^(rate l))`` over the levels of the fit, wide and pale so the data stays visible on top."""
    levels = np.asarray(levels, dtype=float)
    if levels.size and np.isfinite(constant) and constant > 0 and np.isfinite(rate):
        span = np.array([levels.min(), levels.max()])
        ax.plot(span, np.log2(constant) + rate * span, "--", color=color, linewidth=4, alpha=0.4, zorder=1,
                label=label)


# ---------------------------------------------------------------------------
# Report figures
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Drawn:
    """What the report figures draw: the typed records and the labels of a report.

    ``load_curves`` are the report's ``load_curves`` entries as they are
    (numbers derived from the finished runs, not records).
    """

    screening: ScreeningRecord | None
    runs: tuple[RunRecord, ...]
    qoi_names: tuple[str, ...]
    units: dict[str, str]
    grids: tuple[int, ...]
    load_curves: tuple[dict[str, Any], ...] = ()

    @classmethod
    def of(cls, report: dict[str, Any]) -> _Drawn:
        data = report.get("screening")
        screening = ScreeningRecord.from_json(data) if data else None
        config = report.get("config", {})
        names = report.get("qoi_names") or (screening.qoi_names if screening is not None else ())
        return cls(screening, tuple(RunRecord.from_json(run) for run in report.get("runs") or []), tuple(names),
                   dict(config.get("qoi", {})), tuple(config.get("grids", [])),
                   tuple(report.get("load_curves") or ()))

    def finished(self, method: str) -> list[RunRecord]:
        return [run for run in self.runs if run.is_finished and run.method == method]


def _rates_figure(drawn: _Drawn, path: Path) -> Path | None:
    screening = drawn.screening
    if screening is None or not screening.statistics.levels:
        return None
    stats, rates = screening.statistics, screening.rates
    levels = np.asarray(stats.levels, dtype=int)
    n_qoi = stats.n_qoi
    names = list(drawn.qoi_names) + [f"QoI {q}" for q in range(len(drawn.qoi_names), n_qoi)]
    upper = levels >= 1
    # Each line spans the levels its fit used (recorded by the screening), else the levels >= 1.
    default_span = levels[upper] if np.any(upper) else levels
    span_alpha = rates.levels_alpha or [default_span] * n_qoi
    span_beta = rates.levels_beta or [default_span] * n_qoi
    span_gamma = rates.levels_gamma or default_span

    figure = _new_figure(13.0, 3.6 * n_qoi)
    axes = figure.subplots(n_qoi, 3, squeeze=False)
    for q, name in enumerate(names[:n_qoi]):
        unit = drawn.units.get(name, drawn.units.get(split_column(name)[0]))  # a load-curve column: its QoI's
        title = f"{name} [{unit}]" if unit else name
        _bias_panel(axes[q, 0], stats, rates, q, span_alpha[q], upper, title)
        _variance_panel(axes[q, 1], stats, rates, q, span_beta[q], upper, title)
        for ax in (axes[q, 0], axes[q, 1]):
            ax.set_xlabel("level $l$")
            _label_grids(ax, levels, drawn.grids)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize="small")
    _cost_panel(axes[0, 2], stats, rates, span_gamma, drawn.grids)
    for q in range(1, n_qoi):
        axes[q, 2].set_visible(False)
    return _save(figure, path)


def _bias_panel(ax: Any, stats: Any, rates: Any, q: int, span: Sequence[int], upper: np.ndarray, title: str) -> None:
    levels = np.asarray(stats.levels, dtype=int)
    x, y = _log2_points(levels[upper], np.abs(np.asarray(stats.mean_diff, float))[upper, q])
    ax.plot(x, y, "o-", color="C0", label="$|E[Y_l]|$")
    alpha = rates.alpha[q]
    if alpha == EXACT_RATE:  # nothing to draw on a log axis: say why the panel is empty
        ax.plot([], [], " ", label="exact: every level difference is 0 (no bias)")
    elif is_bias_decaying(alpha):
        _fit_line(ax, span, rates.c_alpha[q], -alpha,
                  rf"$c_\alpha 2^{{-\alpha l}}$, $\alpha$ = {alpha:.2f} ± {rates.alpha_se[q]:.2f}", "C0")
    else:  # as the text report: a legend entry without a line
        ax.plot([], [], " ", label=rf"$\alpha$ = {alpha:.2f}: not fitted, the bias does not decay")
    ax.set_title(f"{title}: bias")
    ax.set_ylabel(r"$\log_2 |E[Y_l]|$")


def _variance_panel(ax: Any, stats: Any, rates: Any, q: int, span: Sequence[int], upper: np.ndarray,
                    title: str) -> None:
    levels = np.asarray(stats.levels, dtype=int)
    x, y = _log2_points(levels[upper], np.asarray(stats.var_diff, float)[upper, q])
    ax.plot(x, y, "o-", color="C1", label=r"$V_l = \mathrm{Var}(Y_l)$")
    x, y = _log2_points(levels, np.asarray(stats.var_fine, float)[:, q])
    ax.plot(x, y, "s:", color="C2", label=r"$\mathrm{Var}(Q_l)$")
    beta = rates.beta[q]
    if beta == EXACT_RATE:
        ax.plot([], [], " ", label="exact: every level difference is 0 (no level variance)")
    else:
        _fit_line(ax, span, rates.c_beta[q], -beta,
                  rf"$c_\beta 2^{{-\beta l}}$, $\beta$ = {beta:.2f} ± {rates.beta_se[q]:.2f}", "C1")
    ax.set_title(f"{title}: variance")
    ax.set_ylabel(r"$\log_2$ variance")


def _cost_panel(ax: Any, stats: Any, rates: Any, span: Sequence[int], grids: Sequence[int]) -> None:
    levels = np.asarray(stats.levels, dtype=int)
    x, y = _log2_points(levels, stats.mean_cost)
    ax.plot(x, y, "o-", color="C3", label="$C_l$ modelled cost (ref-s)")
    if len(stats.mean_seconds) == levels.size:
        x, y = _log2_points(levels, stats.mean_seconds)
        ax.plot(x, y, "s:", color="C4", label="CPU-s per sample (measured)")
    _fit_line(ax, span, rates.c_gamma, rates.gamma,
              rf"$c_\gamma 2^{{\gamma l}}$, $\gamma$ = {rates.gamma:.2f} ± {rates.gamma_se:.2f}", "C3")
    ax.set_title("cost per sample")
    ax.set_xlabel("level $l$")
    ax.set_ylabel(r"$\log_2$ ref-s or CPU-s")
    _label_grids(ax, levels, grids)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")


def _tol_ratio(tol: Sequence[float]) -> np.ndarray:
    """Each QoI's tolerance over the first QoI's."""
    return np.asarray(tol, dtype=float) / float(tol[0])


def _is_on_curve(run: RunRecord, ratio: np.ndarray | None) -> bool:
    """Whether ``run`` used the tolerance ratio of the predicted lines (always, with one QoI or no lines)."""
    if ratio is None:
        return True
    return len(run.tol) == ratio.size and bool(np.allclose(_tol_ratio(run.tol), ratio, rtol=1e-6))


def _no_break(text: str) -> str:
    """``text`` with no-break spaces, which :func:`_fill` never breaks at."""
    return text.replace(" ", "\u00a0")


def _fill(text: str, width: int) -> str:
    """``text`` wrapped to ``width`` characters (textwrap breaks only at ASCII white space)."""
    return textwrap.fill(text, width).replace("\u00a0", " ")


def _tol_label(drawn: _Drawn, ratio: np.ndarray | None) -> str:
    """The first QoI's tolerance; with several QoIs, the others' tolerances of the predicted lines as multiples."""
    if not drawn.qoi_names:
        return "tolerance"
    name = drawn.qoi_names[0]
    unit = drawn.units.get(name, drawn.units.get(split_column(name)[0]))
    label = f"tolerance on {name}" + (f" [{unit}]" if unit else "")
    if ratio is None or ratio.size < 2:
        return label
    others = [f"{other} at {r:.3g} ×" for other, r in zip(drawn.qoi_names[1:], ratio[1:])]
    return label + "\n" + _fill(f"(lines: {', '.join(map(_no_break, others))} this tolerance)", 72)


def _exponent_note(drawn: _Drawn, complexities: Sequence[Any], *, is_mc: bool) -> str:
    """The predicted cost's power of ``1/eps``, for the legend: per QoI when there are several."""
    if not complexities:
        return ""
    if len(complexities) == 1:
        (c,) = complexities
        if is_mc:
            return f" (eps^-{c.mc_exponent:.2f})" if _positive(c.mc_exponent) else ""
        return f" ({c.mlmc_regime})"
    notes = []
    for c in complexities:
        if c.mlmc_regime.startswith("exact"):  # no rates to speak of (records.complexity)
            notes.append("exact")
        elif is_mc:
            notes.append(f"eps^-{c.mc_exponent:.2f}" if _positive(c.mc_exponent) else "not fitted")
        else:
            notes.append(c.mlmc_regime.split(" (")[0] if c.mlmc_exponent is not None else "not fitted")
    if len(notes) > _NAMED_EXPONENTS:
        # Each column named, ten columns of a load curve took more lines than the axes (an audit's figure).
        counts = Counter(notes)
        text = ", ".join(f"{note} ({counts[note]} column{'s' if counts[note] > 1 else ''})"
                         for note in dict.fromkeys(notes))
        return "\n" + _fill(f"{text}; per column in the report", 50)
    named = [f"{name} {note}" for name, note in zip(drawn.qoi_names, notes)]
    return "\n" + _fill("; ".join(map(_no_break, named)), 50)


#: Up to this many columns the legend names each column's cost exponent; more are counted by exponent.
_NAMED_EXPONENTS = 3


def _positive(value: object) -> bool:
    """A positive, finite number (a log axis shows nothing else; JSON may carry None or inf)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def _cost_vs_tol_figure(drawn: _Drawn, path: Path) -> Path | None:
    screening = drawn.screening
    predictions = sorted(screening.predictions if screening else (), key=lambda p: p.tol[0])
    # The slopes of the lines drawn: the rates as the plans floor them (the report lists the fitted ones).
    complexities = screening.rates.planned_complexity if screening is not None else ()
    ratio = _tol_ratio(predictions[0].tol) if predictions else None
    # Tolerances whose bias the finest allowed grid cannot reach (the table's "*": mlmc refuses them) get
    # markers of their own, off the lines of what a run can do.
    reachable = [p for p in predictions if p.is_bias_met]
    refused = [p for p in predictions if not p.is_bias_met]
    series = [  # (points, format, keywords of Axes.plot)
        ([(p.tol[0], p.mlmc_seconds) for p in reachable if _positive(p.mlmc_seconds)], "-",
         {"color": "C0", "label": "MLMC predicted CPU-s" + _exponent_note(drawn, complexities, is_mc=False)}),
        ([(p.tol[0], p.mc_seconds) for p in reachable if _positive(p.mc_seconds)], "--",
         {"color": "C3", "label": "MC predicted CPU-s" + _exponent_note(drawn, complexities, is_mc=True)}),
        ([(p.tol[0], p.mlmc_seconds) for p in refused if _positive(p.mlmc_seconds)], "x",
         {"color": "0.5", "label": "MLMC predicted at tol whose bias grid.max_level cannot reach"}),
    ]
    # Richardson-extrapolated runs apart: drawn as "MLMC" they read as plain MLMC's cost at their tolerance.
    mlmc = drawn.finished("mlmc")
    measured = {"MLMC": [run for run in mlmc if not run.is_richardson],
                "Richardson MLMC": [run for run in mlmc if run.is_richardson],
                "MC": [run for run in drawn.finished("mc") if run.measures_plain_mc]}
    for (method, runs), marker, colour in zip(measured.items(), ("o", "D", "s"), ("C0", "C2", "C3")):
        runs = [run for run in runs if _positive(run.outcome.seconds)]
        for is_on_curve in (True, False):
            points = sorted((run.tol[0], run.outcome.seconds) for run in runs
                            if _is_on_curve(run, ratio) == is_on_curve)
            label = f"{method} measured CPU-s" + ("" if is_on_curve else ", other tol ratio than the lines")
            face = colour if is_on_curve else "none"
            series.append((points, marker, {"color": colour, "markerfacecolor": face, "label": label}))
    if not any(points for points, *_ in series):
        return None

    from matplotlib.ticker import NullFormatter

    figure = _new_figure(6.4, 4.8)
    ax = figure.subplots()
    for points, style, keywords in series:
        if points:
            x, y = np.array(points, dtype=float).T
            if len(points) == 1 and style in ("-", "--"):
                # A line of one point draws nothing: a short dash marks it (e.g. one screened tolerance reachable).
                keywords = {**keywords, "marker": "_", "markersize": 14, "markeredgewidth": 2}
            ax.plot(x, y, style, **keywords)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(_tol_label(drawn, ratio))
    ax.set_ylabel("CPU-seconds of the samples")
    ax.set_title("CPU time against tolerance")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    return _save(figure, path)


def _samples_figure(drawn: _Drawn, path: Path) -> Path | None:
    mlmc = sorted(drawn.finished("mlmc"), key=lambda run: run.tol[0], reverse=True)
    if not mlmc:
        return None
    shown = [mlmc[0]] if len(mlmc) == 1 else [mlmc[0], mlmc[-1]]
    mc_by_key = {run.comparison_key: run.outcome for run in drawn.finished("mc") if run.measures_plain_mc}

    from matplotlib.ticker import FuncFormatter, NullFormatter

    figure = _new_figure(5.5 * len(shown), 4.5)
    axes = figure.subplots(1, len(shown), squeeze=False, sharey=True)[0]
    for ax, run in zip(axes, shown):
        mc = mc_by_key.get(run.comparison_key)
        width = 0.4 if mc is not None else 0.8
        shift = -0.2 if mc is not None else 0.0
        levels = np.asarray(run.outcome.levels, dtype=float)
        method = "Richardson MLMC" if run.is_richardson else "MLMC"
        bars = ax.bar(levels + shift, run.outcome.n_samples, width=width, color="C0", label=f"{method} $N_l$")
        ax.bar_label(bars, fontsize="small")
        if mc is not None:
            bars = ax.bar(np.asarray(mc.levels, dtype=float) + 0.2, mc.n_samples, width=width, color="C3",
                          label="MC $N$")
            ax.bar_label(bars, fontsize="small")
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("level $l$")
        all_levels = sorted(set(run.outcome.levels) | set(mc.levels if mc is not None else []))
        _label_grids(ax, all_levels, drawn.grids)
        # By name, grouped by QoI as --tol takes them (a load curve's read "tol 1, 4, 1, 20, 20, ...").
        ax.set_title("\n".join(textwrap.wrap("tol " + tol_text(drawn.qoi_names, run.tol), 60)), fontsize="medium")
        ax.grid(True, axis="y", which="both", alpha=0.3)
        ax.legend(fontsize="small")
    axes[0].set_ylabel("samples per level")
    # Shared by the panels; from below 1 so that a bar of N = 1 shows, with room for the bar labels on top.
    counts = [n for run in shown for n in run.outcome.n_samples]
    counts += [n for run in shown if run.comparison_key in mc_by_key for n in mc_by_key[run.comparison_key].n_samples]
    axes[0].set_ylim(0.7, 2.0 * max(counts))
    return _save(figure, path)


def _grid_text(grids: Sequence[int], level: int) -> str:
    return f"{grids[level]}²" if 0 <= level < len(grids) else "grid ?"


def _run_name(run: RunRecord | None, method: str, grids: Sequence[int]) -> str:
    """``MC, level 2 (128²)`` or ``MLMC, levels 0..2 (32²..128²)``: the method and the grids it sampled."""
    if run is None or run.outcome is None or not run.outcome.levels:
        return method.upper()
    levels = run.outcome.levels
    if len(levels) == 1:
        return f"{method.upper()}, level {levels[0]} ({_grid_text(grids, levels[0])})"
    return (f"{method.upper()}, levels {levels[0]}..{levels[-1]} "
            f"({_grid_text(grids, levels[0])}..{_grid_text(grids, levels[-1])})")


#: A load curve's legend name sets a run apart from others of the same method and grids in at most
#: ``LEGEND_LINES`` lines of ``LEGEND_WIDTH`` characters (more would crowd out the curves).
LEGEND_WIDTH = 48
LEGEND_LINES = 2


def _differences(runs: Sequence[RunRecord], qoi_names: Sequence[str]) -> list[str]:
    """What sets each run apart from the others: the tolerances that differ (:func:`tol_text`), theta, Richardson.

    Every run's label (:func:`run_label`) where the runs have different
    columns; a run id tells runs apart by these and by an ``mc --level``.
    """
    columns = {run.qoi_names or tuple(qoi_names) for run in runs}
    if len(columns) > 1 or len({len(run.tol) for run in runs}) > 1:
        return [run_label(run, qoi_names) for run in runs]
    (names,) = columns
    differing = [j for j in range(len(names)) if len({run.tol[j] for run in runs}) > 1]
    texts = []
    for run in runs:  # the short differences first: a long list of tolerances may be cut
        parts = []
        if len({r.is_richardson for r in runs}) > 1:
            parts.append("Richardson" if run.is_richardson else "no Richardson")
        if len({r.theta for r in runs}) > 1:
            parts.append("no theta" if run.theta is None else f"theta {run.theta:g}")
        if differing:
            parts.append(f"tol {tol_text([names[j] for j in differing], [run.tol[j] for j in differing])}")
        texts.append(", ".join(parts))
    return texts if len(set(texts)) == len(texts) else [run_label(run, qoi_names) for run in runs]


def _shortened(text: str) -> str:
    """``text`` in at most :data:`LEGEND_LINES` lines of :data:`LEGEND_WIDTH` characters, cut with ``...``."""
    lines = textwrap.wrap(text, LEGEND_WIDTH, max_lines=LEGEND_LINES, placeholder=" ...")
    return "\n".join(lines)


def _told_apart(runs: Sequence[RunRecord | None], qoi_names: Sequence[str]) -> list[str]:
    """Last lines of legend names that would clash: :func:`_differences`, shortened; ``run k: `` where still equal."""
    if any(run is None for run in runs):
        return [f"run {k + 1}" for k in range(len(runs))]
    texts = _differences(runs, qoi_names)
    short = [_shortened(text) for text in texts]
    return [_shortened(f"run {k + 1}: {text}") if short.count(cut) > 1 else cut
            for k, (text, cut) in enumerate(zip(texts, short))]


def _load_curve_names(drawn: _Drawn) -> list[str]:
    """A legend name per load curve (:func:`_run_name`); runs sharing one say how they differ on a second line."""
    by_id = {run.run_id: run for run in drawn.runs}
    runs = [by_id.get(entry.get("run_id")) for entry in drawn.load_curves]
    names = [_run_name(run, entry["method"], drawn.grids) for run, entry in zip(runs, drawn.load_curves)]
    out = list(names)
    for name in set(names):
        group = [k for k, other in enumerate(names) if other == name]
        if len(group) > 1:
            for k, text in zip(group, _told_apart([runs[k] for k in group], drawn.qoi_names)):
                out[k] = f"{name}\n{text}"
    return out


def _load_curve_figure(drawn: _Drawn, path: Path) -> Path | None:
    """Each QoI of a load-curve study against the relative load, one line with an error band per finished run."""
    curves = drawn.load_curves
    if not curves:
        return None
    names = list(curves[0]["curves"])
    units = drawn.units
    figure = _new_figure(5.5 * len(names), 4.5)
    axes = figure.subplots(1, len(names), squeeze=False)[0]
    run_names = _load_curve_names(drawn)
    for ax, name in zip(axes, names):
        for k, (entry, run_name) in enumerate(zip(curves, run_names)):
            load = np.asarray(entry["relative_loads"], dtype=float)
            value = np.asarray(entry["curves"][name]["estimate"], dtype=float)
            error = np.asarray(entry["curves"][name]["rmse"], dtype=float)
            colour = f"C{k % 10}"
            ax.fill_between(load, value - error, value + error, color=colour, alpha=0.25, linewidth=0)
            ax.plot(load, value, "o-", color=colour, label=f"{run_name} (± {entry.get('error', 'RMSE')})")
            fit = entry.get("kappa")
            if name == "contact_area" and fit is not None:
                scale = 100.0 if units.get(name) == "%" else 1.0
                # Up to the area the fit is valid for: drawn over every load it rose to 1100 % at a load of 5.
                reach = fit["max_area"] / fit["kappa"] if fit["kappa"] > 0 else math.inf
                span = np.array([0.0, min(load.max(), reach)])
                source = "one load" if fit["n_points"] == 1 else f"fit on {fit['n_points']} loads"
                # As the text prints it: "kappa = 2.2 ± 0.049" read beside the report's 2.203 ± 0.049.
                kappa = value_error_text(fit["kappa"], fit["error"])
                label = f"kappa = {kappa} ({source}, A/A0 < {fit['max_area']:g})"
                ax.plot(span, fit["kappa"] * span * scale, ":", color=colour, label=label)
        unit = units.get(name)
        ax.set_xlabel("load $p / (E^* \\sqrt{m_2})$")
        ax.set_ylabel(f"E[{name}]" + (f" [{unit}]" if unit else ""))
        ax.set_title(f"E[{name}] against the load")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="x-small")
    return _save(figure, path)


def _cdf_figure(runs: Sequence[RunRecord], column: str, unit: str | None, path: Path) -> Path:
    """The CDF of ``column`` from every finished cdf run: the monotone estimate, its RMSE band, the quantiles."""
    figure = _new_figure(6.4, 4.8)
    ax = figure.subplots()
    for k, run in enumerate(runs):
        distribution = run.outcome.distribution
        colour = f"C{k % 10}"
        s = np.asarray(distribution.thresholds, dtype=float)
        is_band = has_error_band(run.outcome)
        if is_band:
            ax.fill_between(s, distribution.cdf_lower, distribution.cdf_upper, color=colour, alpha=0.25,
                            linewidth=0, step=None)
            label = f"MLMC, tol {tol_number(run.tol[0])}: sup RMSE {run.outcome.rmse[0]:.2g} (band)"
            label += "" if run.outcome.tol_met else ", NOT MET"  # its band is drawn as a met run's is
        elif not is_rmse_measured(run.outcome):  # the thresholds miss a level's samples: variance not measured
            label = f"MLMC, tol {tol_number(run.tol[0])}: RMSE not measured (thresholds miss samples)"
        else:  # the bandwidth is too wide: the band, the statistical error's, ignores a large smoothing bias
            label = f"MLMC, tol {tol_number(run.tol[0])}: no band (smoothing bias not estimated)"
        ax.plot(s, distribution.cdf, "-", color=colour, label=label)
        for quantile in distribution.quantiles:
            if quantile.value is None:
                continue
            if not is_band:  # no error bar: it would be the band of an unmeasured RMSE or beside a large bias
                ax.plot([quantile.value], [quantile.probability], "o", color=colour)
                continue
            # The error bar reaches the grid's end where the band does not cross p inside it.
            low = s[0] if quantile.lower is None else quantile.lower
            high = s[-1] if quantile.upper is None else quantile.upper
            ax.errorbar([quantile.value], [quantile.probability],
                        xerr=[[quantile.value - low], [high - quantile.value]], fmt="o", color=colour, capsize=3)
    ax.set_xlabel(f"s [{unit}]" if unit else "s")
    ax.set_ylabel(f"F(s) = P({column} <= s)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"distribution of {column}, quantiles with error bars")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    return _save(figure, path)


def _cdf_figures(drawn: _Drawn, directory: Path) -> list[Path]:
    """One ``cdf_<column>.png`` per column with finished cdf runs (``@`` of a load column as ``-at-``)."""
    by_column: dict[str, list[RunRecord]] = {}
    for run in drawn.finished("cdf"):
        if run.outcome.distribution is not None:
            by_column.setdefault(run.outcome.distribution.column, []).append(run)
    written = []
    for column, runs in by_column.items():
        unit = drawn.units.get(column, drawn.units.get(split_column(column)[0]))
        name = "cdf_" + column.replace("@", "-at-") + ".png"
        written.append(_cdf_figure(runs, column, unit, directory / name))
    return written


def write_report_plots(report: dict[str, Any], directory: str | Path) -> list[Path]:
    """Write the figures of a study report as PNG files.

    Parameters
    ----------
    report : dict
        A :func:`~rough_uq.report.summary.study_report` (or its JSON round trip).
    directory : str or Path
        Where the files go; created if missing.

    Returns
    -------
    list of Path
        The files written, among:

        ``rates.png``
            Per QoI, ``log2 |E[Y_l]|`` (levels >= 1), ``log2 Var(Y_l)`` and
            ``log2 Var(Q_l)`` against the level, with the screening's fitted
            ``alpha`` (unless not fitted) and ``beta`` lines; and the cost per
            sample (modelled ``C_l`` and measured wall seconds) with the
            ``gamma`` line. Needs a screening.
        ``cost_vs_tol.png``
            Log-log CPU-seconds of the samples against the first QoI's
            tolerance: the screening's predicted MLMC and MC costs as lines
            (with each QoI's exponent; the other QoIs' tolerances as
            multiples of the first's in the axis label; a tolerance whose
            bias ``grid.max_level`` cannot reach as a grey cross, off the
            lines), the measured CPU time of finished MLMC and ``mc --tol``
            runs as points, hollow for a run at another ratio of tolerances.
            Needs a screening or a finished run.
        ``samples_per_level.png``
            ``N_l`` per level (log scale) of the loosest and the tightest
            finished MLMC run, beside the sample count of a finished MC run
            at the same tolerance where there is one. Needs a finished MLMC run.
        ``load_curve.png``
            Per QoI, the estimates of every finished run (named by method,
            levels and grids; runs of one such name on a second line by
            what differs: tolerances, ``theta``, Richardson, cut to
            :data:`LEGEND_LINES` lines) against the relative load
            ``p / (E* sqrt(m2))`` with a band of one RMSE, and for the
            contact area the fitted small-load line ``kappa r``
            (:func:`~rough_uq.report.summary.fit_area_slope`). Needs a study
            with several loads and a finished run.
        ``cdf_<column>.png``
            Per column with finished ``cdf`` runs (``roughuq mlmc
            --tol-cdf``): the monotone CDF estimate against the thresholds
            with its band ``cdf +- sup-norm RMSE``, and the quantiles with
            their error bars (cut at the grid where the band leaves it).

        A figure without its data is skipped; the folders this call made are removed again if no figure was drawn.

    Raises
    ------
    RoughUQError
        If matplotlib is not installed.
    """
    _matplotlib()
    drawn = _Drawn.of(report)
    directory = Path(directory)
    made = [folder for folder in (directory, *directory.parents) if not folder.exists()]  # deepest first
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, draw in (
        ("rates.png", _rates_figure),
        ("cost_vs_tol.png", _cost_vs_tol_figure),
        ("samples_per_level.png", _samples_figure),
        ("load_curve.png", _load_curve_figure),
    ):
        path = draw(drawn, directory / name)
        if path is not None:
            written.append(path)
    written += _cdf_figures(drawn, directory)
    if not written:
        for folder in made:  # no empty folders for a study without figures
            folder.rmdir()
    return written


# ---------------------------------------------------------------------------
# One sample
# ---------------------------------------------------------------------------


def _map_panel(figure: Any, ax: Any, values: np.ndarray, extent: tuple[float, ...], *, cmap: str, label: str,
               title: str) -> None:
    """A map of nodal ``values``, shape (n, n), with its colour bar."""
    # Node (i, j) sits at (x, y) = (i h, j h): transpose so that i runs along x.
    image = ax.imshow(values.T, origin="lower", extent=extent, cmap=cmap)
    figure.colorbar(image, ax=ax, shrink=0.8, label=label)
    ax.set_title(title)


def _cluster_colours(contact: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """RGB image, shape (n, n, 3): white out of contact, each contact cluster one colour of ``tab20``."""
    import matplotlib

    palette = matplotlib.colormaps["tab20"](np.arange(20))[:, :3]
    colours = np.ones((*contact.shape, 3))
    colours[contact] = palette[(labels[contact] - 1) % len(palette)]
    return colours


def _clusters_panel(ax: Any, model: ContactModel, solution: ContactSolution, extent: tuple[float, ...]) -> None:
    """The contact clusters in colour, titled with the contact area and the cluster count."""
    contact = solution.contact
    # "mean" counts both ways; the map shows the 8-connected clusters and the title the mean.
    labels = label_clusters(contact, connectivity=8 if model.connectivity == "mean" else model.connectivity)
    n_clusters = cluster_count(contact, model.connectivity)
    area = 100.0 * contact_area(solution.pressure, estimator=model.area_estimator)
    colours = _cluster_colours(contact, labels)
    # Transposed like the maps of _map_panel.
    ax.imshow(np.transpose(colours, (1, 0, 2)), origin="lower", extent=extent, interpolation="nearest")
    if model.connectivity == "mean":  # on one line, the title is wider than the panel
        ax.set_title(f"contact {area:.2f} %, {n_clusters:g} clusters\nmean of 4- and 8-connected\n(map: 8-connected)")
    else:
        ax.set_title(f"contact {area:.2f} %, {n_clusters:g} clusters ({model.connectivity}-connected)")


def _load_text(model: ContactModel, load_index: int) -> str:
    """Of a load curve, which load the figure draws: empty for one load."""
    if model.n_loads == 1:
        return ""
    pressure = model.loads[load_index]
    relative = pressure / (model.e_star * model.spectrum.rms_slope)
    return (f"\nload {load_index + 1} of {model.n_loads}: $p / (E^* \\sqrt{{m_2}})$ = {relative:.3g} "
            f"(mean pressure {pressure:.3g} $E^*$)")


def _checked_load_index(model: ContactModel, load_index: object) -> int:
    if not (is_integer(load_index) and 0 <= load_index < model.n_loads):
        raise InvalidParameterError("load_index", load_index, f"an integer in 0..{model.n_loads - 1}")
    return int(load_index)


def write_sample_figure(*, model: ContactModel, stage: int, level: int, index: int, path: str | Path,
                        load_index: int = 0, stage_name: str | None = None) -> Path:
    """Draw one sample: its heights, its contact pressure and its contact clusters.

    Of a load curve, the pressure and the clusters are those at the load
    ``load_index`` (in the config's order; default the first); the title
    says which.

    The sample is recomputed from its random stream exactly as
    :func:`~rough_uq.problem.sampler.compute_batch` computes its fine grid (coupled
    stages on ``level >= 1`` draw the coupled pair and warm-start from the
    coarse solve).

    Parameters
    ----------
    model : ContactModel
        The study's model (:func:`~rough_uq.study.pipeline.build_model`).
    stage, level, index : int
        The sample's key (:mod:`rough_uq.problem.sampler`).
    path : str or Path
        PNG file to write; its folder must exist.
    load_index : int
        Which of ``model.loads`` to draw, ``0..n_loads - 1`` (0 for a single load).
    stage_name : str, optional
        What the title calls the sample's stage, e.g. ``"the screening"`` or
        ``"run mlmc_contact_area-0.5_theta-0.5"`` (the stage numbers of runs are
        17-digit hashes); default ``"stage <stage>"``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    RoughUQError
        If matplotlib is not installed.
    InvalidParameterError
        If ``load_index`` is not one of the model's loads.
    """
    _matplotlib()
    load_index = _checked_load_index(model, load_index)
    path = Path(path)
    sample = solve_sample(model, stage=stage, level=level, index=index)
    heights, solution = sample.heights, sample.fine_curve.solutions[load_index]
    n = heights.shape[0]
    size = model.spectrum.system_size
    extent = (0.0, size, 0.0, size)

    figure = _new_figure(15.0, 4.8)
    axes = figure.subplots(1, 3)
    _map_panel(figure, axes[0], heights, extent, cmap="viridis", label="height (length unit)",
               title=f"heights, rms {np.std(heights):.3g}")
    unconverged = "" if solution.converged else " (not converged)"
    pressure_title = f"pressure, mean {model.loads[load_index]:.3g}{unconverged}"
    _map_panel(figure, axes[1], solution.pressure, extent, cmap="magma", label="pressure (unit of $E^*$)",
               title=pressure_title)
    _clusters_panel(axes[2], model, solution, extent)
    for ax in axes:
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    kind = "coupled" if is_coupled_stage(stage) and level > 0 else "single"
    name = f"stage {stage}" if stage_name is None else stage_name
    figure.suptitle(f"sample of {name}, level {level} (grid {n}), index {index} [{kind} draw]"
                    + _load_text(model, load_index))
    return _save(figure, path)

"""The hierarchy of a run: its samples, plan and spent cost; what one sample costs and a budget affords.

"The module docstring" below is the package's, :mod:`rough_uq.multilevel.drivers`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from rough_uq.multilevel.drivers.events import PlanUpdated
from rough_uq.multilevel.drivers.planning import _pooled_variance
from rough_uq.multilevel.drivers.samples import _LevelSamples
from rough_uq.multilevel.statistics import ExactTotal, LevelStatistics, assemble_statistics, readonly_array


class _Hierarchy:
    """Mutable state of one run: the samples of levels ``0..L``, the plan, the spent cost.

    ``base`` is the level the telescoping sum starts on (sampled as ``Q_base``;
    levels below it get no samples); ``floor`` is the fewest samples any level
    from ``base`` on gets; ``prior_var``, ``prior_mean`` and ``prior_n``
    (keyed by level) are the screening's ``V_l``, ``E[Y_l]`` and sample
    counts, pooled with the run's samples in :meth:`variances` (allocation and
    statistical error) and :meth:`bias_means` (bias estimate and rate
    ``alpha``; module docstring). Events report the levels from
    ``reported_from`` on (MC: its one level; MLMC: all, from 0).
    """

    def __init__(
        self, n_levels: int, floor: int, prior: LevelStatistics | None = None, base: int = 0, reported_from: int = 0
    ) -> None:
        self.samples = [_LevelSamples(level) for level in range(n_levels)]
        self.base = base
        self.targets = [floor if level >= base else 0 for level in range(n_levels)]
        self.floor = floor
        self._spent = ExactTotal()
        self.reported_from = reported_from
        self.prior_var: dict[int, np.ndarray] = {}
        self.prior_mean: dict[int, np.ndarray] = {}
        self.prior_n: dict[int, int] = {}
        if prior is not None:
            for row, level in enumerate(prior.levels):
                if prior.n_samples[row] >= 2 and level >= base:
                    # The base level is sampled as Q_base: its prior is the screening's Q, not Y.
                    is_base = level == base
                    self.prior_var[int(level)] = prior.var_fine[row] if is_base else prior.var_diff[row]
                    self.prior_mean[int(level)] = prior.mean_fine[row] if is_base else prior.mean_diff[row]
                    self.prior_n[int(level)] = int(prior.n_samples[row])

    @property
    def spent(self) -> float:
        """Modelled cost of the samples drawn so far (exactly summed: the same whatever the batches)."""
        return self._spent.value

    def add_cost(self, costs: np.ndarray) -> None:
        self._spent.add(costs)

    def add_level(self) -> None:
        self.samples.append(_LevelSamples(self.n_levels))
        self.targets.append(0)

    def variances(self, level: int, run_var: np.ndarray, n_run: int) -> np.ndarray:
        """``V_level``: the run's sample variance, pooled with the screening's where it has the level."""
        if level not in self.prior_var:
            return run_var
        return _pooled_variance(run_var, n_run, self.prior_var[level], self.prior_n[level])

    def bias_means(self, n_qoi: int) -> tuple[np.ndarray, np.ndarray]:
        """Pooled ``E[Y_l]`` of levels ``0..L`` and their standard errors, shapes (n_levels, n_qoi).

        Where the screening sampled a level, its samples and the run's are
        independent draws of the same ``Y_l``: the mean is their
        count-weighted mean, its error ``sqrt(V_l / (N_run + N_screening))``
        with the pooled ``V_l``. Elsewhere the run's own (zeros, error inf,
        on a level without samples).
        """
        means = np.zeros((self.n_levels, n_qoi))
        errors = np.full((self.n_levels, n_qoi), np.inf)
        for s in self.samples:
            n_prior = self.prior_n.get(s.level, 0)
            n_total = s.n + n_prior
            if n_total == 0:
                continue
            run_mean = s.moments().mean_diff if s.n else np.zeros(n_qoi)
            means[s.level] = (s.n * run_mean + n_prior * self.prior_mean.get(s.level, 0.0)) / n_total
            if s.n >= 2 or n_prior:
                run_var = s.moments().var_diff if s.n else np.zeros(n_qoi)
                errors[s.level] = np.sqrt(self.variances(s.level, run_var, s.n) / n_total)
        return means, errors

    def bias_statistics(self, statistics: LevelStatistics) -> LevelStatistics:
        """``statistics`` (the run's) with ``mean_diff``, ``var_diff`` and ``n_samples`` pooled, for ``alpha``."""
        if not self.prior_n:
            return statistics
        n_qoi = statistics.n_qoi
        means, _ = self.bias_means(n_qoi)
        var_diff = np.array(statistics.var_diff)
        n_samples = np.array(statistics.n_samples)
        for row, level in enumerate(statistics.levels):
            level = int(level)
            var_diff[row] = self.variances(level, statistics.var_diff[row], int(statistics.n_samples[row]))
            n_samples[row] += self.prior_n.get(level, 0)
        return dataclasses.replace(
            statistics,
            mean_diff=readonly_array(means[statistics.levels]),
            var_diff=readonly_array(var_diff),
            n_samples=readonly_array(n_samples),
        )

    def planning_inputs(self, n_qoi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pooled ``V_l`` (shape (n_levels, n_qoi)), which levels have one, and mean costs ``C_l`` (0 if unsampled)."""
        has_data = np.array([self.has_variance(s.level) for s in self.samples])
        var_diff = np.zeros((self.n_levels, n_qoi))
        mean_cost = np.zeros(self.n_levels)
        for s in self.samples:
            run_var = s.moments().var_diff if s.n > 0 else np.zeros(n_qoi)
            if has_data[s.level]:
                var_diff[s.level] = self.variances(s.level, run_var, s.n)
            if s.n > 0:
                mean_cost[s.level] = s.moments().mean_cost
        return var_diff, has_data, mean_cost

    def has_variance(self, level: int) -> bool:
        return level >= self.base and (self.samples[level].n >= 2 or level in self.prior_var)

    @property
    def n_levels(self) -> int:
        return len(self.samples)

    def levels(self) -> np.ndarray:
        return readonly_array(np.arange(self.reported_from, self.n_levels))

    def n_done(self) -> np.ndarray:
        return readonly_array(np.array([s.n for s in self.samples[self.reported_from :]], dtype=np.int64))

    def n_planned(self) -> np.ndarray:
        return readonly_array(np.array(self.targets[self.reported_from :], dtype=np.int64))

    def plan_event(self, reason: str) -> PlanUpdated:
        return PlanUpdated(levels=self.levels(), n_planned=self.n_planned(), n_done=self.n_done(), reason=reason)

    def pending(self) -> list[_LevelSamples]:
        """Levels with fewer samples than planned, coarsest first."""
        return [s for s in self.samples if s.n < self.targets[s.level]]

    def is_nearly_complete(self) -> bool:
        """Every level within 1 % of its planned samples (Giles' test before the bias check)."""
        return not any(self.targets[s.level] - s.n > 0.01 * s.n for s in self.samples)

    def is_complete(self) -> bool:
        return all(s.n >= self.targets[s.level] for s in self.samples)

    def sampled(self) -> list[_LevelSamples]:
        return [s for s in self.samples if s.n > 0]

    def statistics(self) -> LevelStatistics:
        sampled = self.sampled()
        return assemble_statistics([s.level for s in sampled], [s.moments() for s in sampled], base_level=self.base)


def _per_sample_cost(hierarchy: _Hierarchy, level: int, gamma: float) -> float:
    """Predicted cost of one sample on ``level`` (0 when nothing is known yet)."""
    known = [s for s in hierarchy.samples if s.n > 0 and s.moments().mean_cost > 0]
    if not known:
        return 0.0
    nearest = min(known, key=lambda s: abs(s.level - level))
    return nearest.moments().mean_cost * 2.0 ** (gamma * (level - nearest.level))


def affordable_count(budget_left: float, unit: float, wanted: int) -> int:
    """``min(wanted, floor(budget_left / unit))``, at least 0, for any finite budget.

    A budget as large as ``1e308`` over a small ``unit`` is an infinite
    count in floating point, which ``math.floor`` cannot make an integer;
    such a budget affords ``wanted``.
    """
    count = budget_left / unit
    return wanted if count >= wanted else max(math.floor(count), 0)


def _batch_size(hierarchy: _Hierarchy, level: int, wanted: int, max_cost: float | None, gamma: float) -> int:
    """Samples to draw now on ``level``: ``wanted`` unless ``max_cost`` forbids (then maybe 0)."""
    if max_cost is None:
        return wanted
    unit = _per_sample_cost(hierarchy, level, gamma)
    if unit <= 0:
        return wanted
    n = affordable_count(max_cost - hierarchy.spent, unit, wanted)
    # A level with a single sample has no variance; do not start one that cannot get two.
    return n if hierarchy.samples[level].n + n >= 2 else 0

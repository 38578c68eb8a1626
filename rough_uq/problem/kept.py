"""Samples a contact problem keeps in memory, so that a run interrupted from Python loses none of them.

A sample is determined by its ``(stage, level, index)`` (:func:`~rough_uq.problem.sampler.sample_rng`): the
same call of :func:`rough_uq.mlmc` (or ``mc``, ``screen``, ``variance``, ``distribution``) on the same problem
asks for the same samples in the same order (:mod:`rough_uq.multilevel.drivers`, "the engine asks for
contiguous new indices per level"). :class:`KeptSamples` holds every sample a problem's samplers computed, by
``(stage, level)`` in arrays addressed by the sample index, and gives them back instead of solving again: a
call interrupted by Ctrl-C and made again goes on where it stopped, with the numbers it would have had. A
sample takes some 60 bytes here (one QoI; 16 more per further column), a million of them 60 MB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rough_uq.problem.batch import LevelBatch

__all__ = ["KeptSamples"]

#: The per-sample arrays of a :class:`LevelBatch`, in its field order.
_FIELDS = ("fine", "coarse", "cost", "n_iter", "converged")


@dataclass
class _Level:
    """The samples of one ``(stage, level)``: row ``i`` of each array is sample ``i`` where ``is_kept[i]``."""

    is_kept: np.ndarray
    arrays: dict[str, np.ndarray]

    @classmethod
    def empty(cls, batch: LevelBatch) -> _Level:
        arrays = {name: np.zeros((0, *np.shape(getattr(batch, name))[1:]), getattr(batch, name).dtype)
                  for name in _FIELDS}
        return cls(np.zeros(0, dtype=bool), arrays)

    def grow(self, size: int) -> None:
        """Room for sample indices below ``size`` (the capacity at least doubles: adding is amortised O(n))."""
        if size <= self.is_kept.size:
            return
        capacity = max(size, 2 * self.is_kept.size)
        self.is_kept = np.concatenate([self.is_kept, np.zeros(capacity - self.is_kept.size, dtype=bool)])
        for name, array in self.arrays.items():
            extra = np.zeros((capacity - array.shape[0], *array.shape[1:]), dtype=array.dtype)
            self.arrays[name] = np.concatenate([array, extra])


class KeptSamples:
    """Every sample computed for one problem, by stage and level (module docstring)."""

    def __init__(self) -> None:
        self._levels: dict[tuple[int, int], _Level] = {}

    def __len__(self) -> int:
        return sum(int(np.count_nonzero(kept.is_kept)) for kept in self._levels.values())

    def add(self, batch: LevelBatch) -> None:
        """Keep the samples of ``batch``."""
        if batch.n_samples == 0:
            return
        kept = self._levels.setdefault((batch.stage, batch.level), _Level.empty(batch))
        kept.grow(int(np.max(batch.indices)) + 1)
        kept.is_kept[batch.indices] = True
        for name in _FIELDS:
            kept.arrays[name][batch.indices] = getattr(batch, name)

    def split(self, stage: int, level: int, indices: np.ndarray) -> tuple[LevelBatch | None, np.ndarray]:
        """The kept samples among ``indices`` (in their order; None if none is kept) and the indices still to
        compute (in their order)."""
        kept = self._levels.get((stage, level))
        if kept is None:
            return None, indices
        inside = indices < kept.is_kept.size
        is_kept = np.zeros(indices.size, dtype=bool)
        is_kept[inside] = kept.is_kept[indices[inside]]
        if not is_kept.any():
            return None, indices
        rows = indices[is_kept]
        batch = LevelBatch(level=level, stage=stage, indices=rows.copy(),
                           **{name: kept.arrays[name][rows].copy() for name in _FIELDS})
        return batch, indices[~is_kept]

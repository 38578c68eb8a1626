"""Samples a contact problem keeps in memory, so that a run interrupted from Python loses none of them.

A sample is determined by its ``(stage, level, index)`` (:func:`~rough_uq.problem.sampler.sample_rng`): the
same call of :func:`rough_uq.mlmc` (or ``mc``, ``screen``, ``variance``, ``distribution``) on the same problem
asks for the same samples in the same order (:mod:`rough_uq.multilevel.drivers`, "the engine asks for
contiguous new indices per level"). :class:`KeptSamples` holds every sample a problem's samplers computed, by
``(stage, level)`` in arrays addressed by the sample index, and gives them back instead of solving again: a
call interrupted by Ctrl-C and made again goes on from its last completed batch (from its last sample with a
progress reporter or an executor, which compute one sample at a time), with the numbers it would have had. A
sample takes some 60 bytes here (one QoI; 16 more per further column), a million of them 60 MB. A sample whose
index lies far beyond those kept (more than :data:`MAX_GAP` past four times their number; the drivers never
ask for one) is not kept: arrays addressed by the index would need a row for every index below it.

Every sample is written before it is marked kept, so an interrupt (or another thread) never finds a row
marked kept but not yet written; a lock serialises threads that run on one problem.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from rough_uq.problem.batch import LevelBatch

__all__ = ["MAX_GAP", "KeptSamples"]

#: Indices up to ``4 * (samples kept + batch) + MAX_GAP`` of a stage and level are kept (module docstring).
MAX_GAP = 4096

#: The per-sample arrays of a :class:`LevelBatch`, in its field order.
_FIELDS = ("fine", "coarse", "cost", "n_iter", "converged")


@dataclass
class _Level:
    """The samples of one ``(stage, level)``: row ``i`` of each array is sample ``i`` where ``is_kept[i]``."""

    is_kept: np.ndarray
    arrays: dict[str, np.ndarray]
    n_kept: int = 0

    @classmethod
    def empty(cls, batch: LevelBatch) -> _Level:
        arrays = {name: np.zeros((0, *np.shape(getattr(batch, name))[1:]), getattr(batch, name).dtype)
                  for name in _FIELDS}
        return cls(np.zeros(0, dtype=bool), arrays)

    def grow(self, size: int) -> None:
        """Room for sample indices below ``size`` (the capacity at least doubles: adding is amortised O(n)).

        The new arrays are complete before they replace the old ones, ``is_kept`` last.
        """
        if size <= self.is_kept.size:
            return
        capacity = max(size, 2 * self.is_kept.size)
        grown = {name: np.concatenate([array, np.zeros((capacity - array.shape[0], *array.shape[1:]), array.dtype)])
                 for name, array in self.arrays.items()}
        is_kept = np.concatenate([self.is_kept, np.zeros(capacity - self.is_kept.size, dtype=bool)])
        self.arrays = grown
        self.is_kept = is_kept

    def add(self, batch: LevelBatch) -> None:
        """Write the rows of ``batch`` whose index is within reach (module docstring), then mark them kept."""
        within = batch.indices < 4 * (self.n_kept + batch.n_samples) + MAX_GAP
        indices = batch.indices[within]
        if indices.size == 0:
            return
        self.grow(int(np.max(indices)) + 1)
        for name in _FIELDS:
            self.arrays[name][indices] = getattr(batch, name)[within]
        self.n_kept += int(np.count_nonzero(~self.is_kept[np.unique(indices)]))
        self.is_kept[indices] = True


class KeptSamples:
    """Every sample computed for one problem, by stage and level (module docstring)."""

    def __init__(self) -> None:
        self._levels: dict[tuple[int, int], _Level] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return sum(kept.n_kept for kept in self._levels.values())

    def add(self, batch: LevelBatch) -> None:
        """Keep the samples of ``batch``."""
        if batch.n_samples == 0:
            return
        with self._lock:
            self._levels.setdefault((batch.stage, batch.level), _Level.empty(batch)).add(batch)

    def split(self, stage: int, level: int, indices: np.ndarray) -> tuple[LevelBatch | None, np.ndarray]:
        """The kept samples among ``indices`` (in their order; None if none is kept) and the indices still to
        compute (in their order)."""
        with self._lock:
            kept = self._levels.get((stage, level))
            if kept is None:
                return None, indices
            inside = indices < kept.is_kept.size
            is_kept = np.zeros(indices.size, dtype=bool)
            is_kept[inside] = kept.is_kept[indices[inside]]
            if not is_kept.any():
                return None, indices
            rows = indices[is_kept]
            columns = {name: kept.arrays[name][rows].copy() for name in _FIELDS}
        return LevelBatch(level=level, stage=stage, indices=rows.copy(), **columns), indices[~is_kept]

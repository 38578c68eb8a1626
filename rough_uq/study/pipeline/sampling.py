"""The store-backed sampler: stored samples are read back, missing ones computed and appended.

:class:`StudySampler` serves the estimators: samples already stored are read back, missing ones are computed by
the executor and written as they arrive (at least every :data:`FLUSH_SECONDS`, and at the end of each batch the
estimator asks for), so an interrupted run loses at most a few seconds of work and its rerun replays the same
decisions from the stored samples.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from rough_uq.study.executors import Executor
from rough_uq.study.progress import Progress
from rough_uq.problem.sampler import LevelBatch, is_coupled_stage, modelled_cost
from rough_uq.study.pipeline.studies import Study


#: Longest time computed samples wait in memory before they are written.
FLUSH_SECONDS = 2.0


class StudySampler:
    """A level sampler (estimator contract) serving stored samples and computing missing ones.

    Parameters
    ----------
    study : Study
    stage : int
        Stage of the samples (:mod:`rough_uq.problem.sampler`).
    executor : Executor
    progress : Progress
    chunk : int
        Samples per work item sent to the executor.
    advance_served : bool
        Advance ``progress`` by the stored samples of a batch that also computes some (an estimation run's,
        whose progress counts a batch's stored samples only once the batch is done: a resumed run's progress
        started below what was stored, "411/827" of 416). Not where the plan counted them first (screening).
    """

    def __init__(
        self, study: Study, *, stage: int, executor: Executor, progress: Progress, chunk: int = 1,
        advance_served: bool = False,
    ) -> None:
        self.study = study
        self.stage = stage
        self.executor = executor
        self.progress = progress
        self.chunk = max(1, int(chunk))
        self.advance_served = advance_served
        self._cache: dict[int, dict[int, int]] = {}
        self._batches: dict[int, LevelBatch] = {}
        self.n_computed = 0

    def stored(self, level: int) -> LevelBatch:
        """All stored samples of ``(stage, level)``."""
        if level not in self._batches:
            self._batches[level] = self.study.store.read_samples(level=level, stage=self.stage)
            self._cache[level] = {int(i): row for row, i in enumerate(self._batches[level].indices)}
        return self._batches[level]

    def _forget(self, level: int) -> None:
        self._batches.pop(level, None)
        self._cache.pop(level, None)

    def missing(self, level: int, indices: np.ndarray) -> np.ndarray:
        """The ``indices`` of ``level`` not stored yet."""
        self.stored(level)
        rows = self._cache[level]
        return np.array([i for i in np.asarray(indices, dtype=np.int64) if int(i) not in rows], dtype=np.int64)

    def compute(self, level: int, indices: np.ndarray) -> None:
        """Compute and store the missing samples among ``indices`` of ``level``."""
        missing = self.missing(level, indices)
        if missing.size == 0:
            return
        if self.advance_served and missing.size < np.size(indices):
            self.progress.advance(level, np.size(indices) - missing.size)
        items = [(self.stage, level, missing[i : i + self.chunk]) for i in range(0, missing.size, self.chunk)]
        pending: list[LevelBatch] = []
        last_flush = time.monotonic()
        try:
            for batch in self.executor.run(self.study.model_for(level, note=self.progress.note), items):
                pending.append(batch)
                self.progress.advance(level, batch.n_samples)
                if time.monotonic() - last_flush >= FLUSH_SECONDS:
                    self._flush(level, pending)
                    last_flush = time.monotonic()
        finally:
            self._flush(level, pending)

    def _flush(self, level: int, pending: list[LevelBatch]) -> None:
        if not pending:
            return
        batch = _concatenate(pending)
        pending.clear()
        self.study.store.append_samples(batch)
        self.n_computed += batch.n_samples
        self._forget(level)

    def samples(self, level: int, indices: np.ndarray) -> LevelBatch:
        """Samples ``indices`` of ``level`` (computing the missing ones), in the order asked."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        self.compute(level, indices)
        stored = self.stored(level)
        rows = np.array([self._cache[level][int(i)] for i in indices], dtype=np.int64)
        return _take(stored, rows)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        batch = self.samples(level, indices)
        cost = modelled_cost(self.study.model, level, batch.n_iter, is_coupled=is_coupled_stage(self.stage))
        return batch.fine, batch.coarse, cost


def _take(batch: LevelBatch, rows: np.ndarray) -> LevelBatch:
    return LevelBatch(
        level=batch.level,
        stage=batch.stage,
        indices=batch.indices[rows],
        fine=batch.fine[rows],
        coarse=batch.coarse[rows],
        cost=batch.cost[rows],
        n_iter=batch.n_iter[rows],
        converged=batch.converged[rows],
    )


def _concatenate(batches: Sequence[LevelBatch]) -> LevelBatch:
    first = batches[0]
    return LevelBatch(
        level=first.level,
        stage=first.stage,
        indices=np.concatenate([b.indices for b in batches]),
        fine=np.concatenate([b.fine for b in batches]),
        coarse=np.concatenate([b.coarse for b in batches]),
        cost=np.concatenate([b.cost for b in batches]),
        n_iter=np.concatenate([b.n_iter for b in batches]),
        converged=np.concatenate([b.converged for b in batches]),
    )

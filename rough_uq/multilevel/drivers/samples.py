"""Sample storage per level and the calls of a level sampler, checked against its contract.

The contract is in the package docstring (:mod:`rough_uq.multilevel.drivers`); :data:`Sampler` is its type.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import PLANNED_COUNT_CAP, EstimationError, InvalidParameterError, checked_integer, is_real_number
from rough_uq.multilevel.statistics import LevelMoments, level_moments, readonly_array

Sampler = Callable[[int, np.ndarray], tuple[object, object, object]]


class _LevelSamples:
    """All samples of one level, with their statistics cached until the next batch."""

    def __init__(self, level: int) -> None:
        self.level = level
        self.n = 0
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._moments: LevelMoments | None = None

    def add(self, fine: np.ndarray, coarse: np.ndarray, cost: np.ndarray) -> None:
        self._chunks.append((fine, coarse, cost))
        self.n += len(cost)
        self._moments = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self._chunks) > 1:
            # Merge once so that later concatenations do not redo the work.
            self._chunks = [tuple(np.concatenate(part) for part in zip(*self._chunks))]
        return self._chunks[0]

    def moments(self) -> LevelMoments:
        if self._moments is None:
            self._moments = level_moments(*self.arrays())
        return self._moments


def _qoi_array(values: object, *, name: str, level: int, n: int) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2 or array.shape[0] != n:
        raise EstimationError(
            f"sampler returned {name} of shape {np.shape(values)} for {n} samples on level {level}; "
            "expected (n,) or (n, n_qoi)"
        )
    bad = ~np.all(np.isfinite(array), axis=1)
    if np.any(bad):
        rows = np.flatnonzero(bad)[:10].tolist()
        raise EstimationError(f"sampler returned non-finite {name} values on level {level} (batch rows {rows})")
    return array


@dataclass(frozen=True, eq=False)
class _Batch:
    """One validated sampler answer; ``is_scalar`` records a 1-d (single QoI) return."""

    indices: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray
    cost: np.ndarray
    is_scalar: bool


def call_sampler(sampler: Sampler, level: int, start: int, n: int) -> _Batch:
    indices = np.arange(start, start + n, dtype=np.int64)
    returned = sampler(level, indices.copy())
    try:
        fine, coarse, cost = returned
    except (TypeError, ValueError) as error:
        raise EstimationError("a sampler must return a tuple (fine, coarse, cost)") from error
    is_scalar = np.ndim(fine) == 1
    fine = _qoi_array(fine, name="fine", level=level, n=n)
    coarse = _qoi_array(coarse, name="coarse", level=level, n=n)
    if coarse.shape != fine.shape:
        raise EstimationError(f"sampler returned fine {fine.shape} and coarse {coarse.shape} on level {level}")
    if level == 0 and np.any(coarse != 0):
        raise EstimationError("sampler returned nonzero coarse values on level 0 (there is no coarser level)")
    try:
        cost = np.array(np.broadcast_to(np.asarray(cost, dtype=float), (n,)))
    except ValueError as error:
        raise EstimationError(f"sampler returned cost of shape {np.shape(cost)} for {n} samples") from error
    if not np.all(np.isfinite(cost)) or np.any(cost < 0):
        raise EstimationError(f"sampler returned a negative or non-finite cost on level {level}")
    return _Batch(indices=indices, fine=fine, coarse=coarse, cost=cost, is_scalar=is_scalar)


def check_optional_positive(name: str, value: object) -> float | None:
    """A limit: a number > 0, or None for none (``math.inf`` means none too)."""
    if value is None:
        return None
    if not (is_real_number(value) and value > 0):
        raise InvalidParameterError(name, value, "a number > 0, or None for no limit")
    return None if value == math.inf else float(value)


def check_initial_count(n_initial: object) -> int:
    """``n_initial`` as an int, or :class:`InvalidParameterError` unless an integer from 2 to
    :data:`~rough_uq.errors.PLANNED_COUNT_CAP` (2^52, the largest count a plan gives a level: ``10**20`` was an
    OverflowError from the first plan's int64 counts)."""
    n_initial = checked_integer("n_initial", n_initial, 2)
    if n_initial > PLANNED_COUNT_CAP:
        raise InvalidParameterError("n_initial", n_initial, f"at most 2^52 = {PLANNED_COUNT_CAP}, the largest count "
                                    "a plan gives a level")
    return n_initial


def check_kurtosis_limit(value: object) -> float:
    """``kurtosis_limit`` as a float, or :class:`InvalidParameterError` unless a number >= 1 (``math.inf``: never
    warn): a kurtosis is at least 1, so a limit below it flagged every level (0.5 was taken)."""
    if not (is_real_number(value) and value >= 1):
        raise InvalidParameterError("kurtosis_limit", value, "a number >= 1 (a kurtosis is at least 1; math.inf: "
                                    "never warn)")
    return float(value)


def _shape_out(values: np.ndarray, is_scalar: bool) -> float | np.ndarray:
    return float(values[0]) if is_scalar else readonly_array(values)

"""Memory of contact solves, against this machine's: what to say before solves that would not fit.

A solve on an ``n x n`` grid holds about :data:`SOLVER_ARRAYS_PER_NODE` float64
arrays of ``n x n`` (pressure, gap, displacement, surface, search direction,
residuals, FFT work arrays and the warm-start guess), i.e. ``160 n^2`` bytes.
:func:`memory_warning` compares the solves that run at once (one per worker)
with the physical memory; the CLI prints its text before it computes a
level's samples (:func:`rough_uq.study.config.memory_warning`), the Python API
warns with it (:class:`~rough_uq.problem.contact.ContactSampler`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

__all__ = ["SOLVER_ARRAYS_PER_NODE", "memory_warning", "physical_memory_bytes", "solver_memory_bytes"]

SOLVER_ARRAYS_PER_NODE = 20
"""Estimated number of float64 ``n x n`` arrays alive during one solve."""


def solver_memory_bytes(n: int) -> int:
    """Estimated memory of one contact solve on an ``n x n`` grid, in bytes."""
    return SOLVER_ARRAYS_PER_NODE * 8 * n * n


def physical_memory_bytes() -> int | None:
    """This machine's physical memory in bytes, None where the platform does not tell."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not available on this platform
        return None


def _size(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.1f} GiB" if n_bytes >= 2**30 else f"{n_bytes / 2**20:.3g} MiB"


def memory_warning(
    grids: Sequence[int], level: int, n_workers: int, memory: int | None, *, lower_with: str, workers: str,
    smaller_coarsest: str, least_level: int = 0,
) -> str | None:
    """What to say before solves on ``grids[level]`` (``n_workers`` at once, each of
    :func:`solver_memory_bytes`) that need more than ``memory`` bytes, or None if they fit (or ``memory`` is
    unknown).

    The text names the grid, the estimate, the machine's memory and what to change: fewer workers
    (``workers`` with the number, e.g. ``"--workers {}"``) if one solve fits, else a lower level
    (``lower_with`` says how the caller gets there, down to ``least_level``) or a smaller coarsest grid
    (``smaller_coarsest``).
    """
    n = grids[level]
    per_solve = solver_memory_bytes(n)
    n_workers = max(1, int(n_workers))
    if memory is None or per_solve * n_workers <= memory:
        return None
    at_once = f" x {n_workers} workers = {_size(per_solve * n_workers)}" if n_workers > 1 else ""
    if per_solve <= memory:
        change = f"use {workers.format(memory // per_solve)}, or run on a machine with more memory"
    else:
        fitting = [lv for lv in range(least_level, level) if solver_memory_bytes(grids[lv]) <= memory]
        lower = f"stay at level <= {fitting[-1]} ({lower_with})" if fitting else f"use {smaller_coarsest}"
        change = f"{lower}, or run on a machine with more memory"
    return (
        f"level {level} (grid {n} x {n}) needs about {_size(per_solve)} per solve{at_once} "
        f"({SOLVER_ARRAYS_PER_NODE} float64 arrays of n^2), but this machine has {_size(memory)}: {change}"
    )

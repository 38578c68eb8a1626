"""What a shard will need: wall time and memory of one ``roughuq sample --workers 1`` process.

For batch systems that kill a job at its time or memory limit
(``roughuq mlmc --plan --shards SIZE --resources``, ``scripts/slurm_study.sh``).
The estimates are deliberately simple and on the safe side; the scripts
multiply them by a safety factor.

Time
----
``seconds = STARTUP_SECONDS + (n + WARMUP_SAMPLES) * s_l`` for a shard of
``n`` samples on level ``l``. The per-sample time ``s_l`` is the modelled cost
of :mod:`rough_uq.problem.sampler` (grid size and iteration counts) times the speed of
the machines that computed the stored samples: the largest, over stored
levels, of the median ratio of measured wall time to modelled cost (a median,
so the first sample of a process, which compiles and plans, does not count).
The iteration counts are the 90th percentiles of the stored samples of that
level; on a level without stored samples those of the finest stored level,
times ``ITERATION_GROWTH`` per level beyond it. ``WARMUP_SAMPLES`` covers the
FFT plans and JIT-cache loading of a fresh process.

Memory
------
``BASE_BYTES`` (interpreter and imported libraries) plus
:func:`~rough_uq.study.config.solver_memory_bytes` of the fine grid and, for coupled
samples, of the coarse one. Measured peak RSS of ``roughuq sample --workers
1`` on the reference machine (quickstart surface): 216 MiB at 32^2 to 128^2,
257 MiB at 512^2, 373 MiB at 1024^2; the model gives 257 (32^2), 306 and 456 MiB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rough_uq.study.config import solver_memory_bytes
from rough_uq.problem.sampler import is_coupled_stage, modelled_cost

__all__ = [
    "BASE_BYTES",
    "ITERATION_GROWTH",
    "STARTUP_SECONDS",
    "WARMUP_SAMPLES",
    "ShardResources",
    "shard_resources",
]

#: Interpreter start, imports and JIT-cache loading (1.8 s on the reference machine; more on a shared file system).
STARTUP_SECONDS = 30.0
#: Samples' worth of time added per shard for FFT planning and the first solves of a fresh process.
WARMUP_SAMPLES = 2
#: Peak memory of a ``roughuq sample`` process before any grid is allocated (216 MiB measured).
BASE_BYTES = 256 * 2**20
#: Assumed growth of the iteration count per level beyond the finest stored one.
ITERATION_GROWTH = 1.5
#: Iterations assumed when nothing at all is stored.
DEFAULT_ITERATIONS = 100


@dataclass(frozen=True)
class ShardResources:
    """Per-level estimates for the shards of one stage.

    Attributes
    ----------
    seconds_per_sample : dict of int to float
        Wall seconds per sample, per level.
    memory_bytes : dict of int to int
        Peak memory of one process computing samples of that level.
    """

    seconds_per_sample: dict[int, float]
    memory_bytes: dict[int, int]

    def seconds(self, level: int, n_samples: int) -> float:
        """Wall seconds of a shard of ``n_samples`` samples on ``level`` (module docstring)."""
        return STARTUP_SECONDS + (n_samples + WARMUP_SAMPLES) * self.seconds_per_sample[level]


def _stored_iterations(store: object, level: int) -> np.ndarray | None:
    """90th percentiles of the (fine, coarse) iteration counts stored on ``level``, or None."""
    n_iter = store.read_samples(level=level).n_iter
    return np.percentile(n_iter, 90, axis=0) if len(n_iter) else None


def _speed(store: object, model: object) -> float:
    """Measured wall seconds per modelled reference second (module docstring); 1 if nothing is stored."""
    ratios = []
    for level in store.levels():
        for stage in store.stages(level=level):
            batch = store.read_samples(level=level, stage=stage)
            modelled = modelled_cost(model, level, batch.n_iter, is_coupled=is_coupled_stage(stage))
            ratios.append(float(np.median(batch.cost / modelled)))
    return max(ratios, default=1.0)


def shard_resources(study: object, *, stage: int, levels: list[int]) -> ShardResources:
    """Estimated time per sample and memory of shards of ``stage`` on ``levels`` (module docstring).

    Parameters
    ----------
    study : rough_uq.study.pipeline.Study
        The study (only read).
    stage : int
        Stage of the shards (decides whether samples are coupled).
    levels : list of int
        Levels to estimate.
    """
    store, model = study.store, study.model
    speed = _speed(store, model)
    stored = {level: _stored_iterations(store, level) for level in store.levels()}
    finest = max(stored, default=None)
    seconds, memory = {}, {}
    for level in levels:
        is_coupled = is_coupled_stage(stage) and level > 0
        n_iter = stored.get(level)
        if n_iter is None:
            fine = DEFAULT_ITERATIONS if finest is None else stored[finest][0] * ITERATION_GROWTH ** (level - finest)
            n_iter = np.array([fine, fine / ITERATION_GROWTH])
        cost = modelled_cost(model, level, np.ceil(n_iter)[None, :], is_coupled=is_coupled)
        seconds[level] = speed * float(cost[0])
        n = model.grid(level)
        memory[level] = BASE_BYTES + solver_memory_bytes(n) + (solver_memory_bytes(n // 2) if is_coupled else 0)
    return ShardResources(seconds, memory)

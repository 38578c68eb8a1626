"""What a batch of level samples carries, without the solver that computes it.

:class:`LevelBatch` and the screening stage key live here rather than in
:mod:`rough_uq.problem.sampler` so that the store and the report can use them without
importing the solver (and with it numba and pyFFTW). Samples, levels and
stages are described in :mod:`rough_uq.problem.sampler`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LevelBatch", "STAGE_SCREENING"]

#: Stage key of the screening samples (estimation runs have stages of their own).
STAGE_SCREENING = 0


@dataclass(frozen=True)
class LevelBatch:
    """Samples of one level and one stage, in a fixed order.

    Attributes
    ----------
    level : int
        Level index ``l``.
    stage : int
        Stage key of the random streams (screening or one estimation run).
    indices : ndarray of int64, shape (n,)
        Sample indices within ``(stage, level)``.
    fine : ndarray of float64, shape (n, n_qoi)
        Quantities of interest on grid ``n_l``.
    coarse : ndarray of float64, shape (n, n_qoi)
        Quantities of interest on grid ``n_{l-1}`` (zeros on level 0).
    cost : ndarray of float64, shape (n,)
        Wall time of each sample in seconds (both solves and the QoI).
    n_iter : ndarray of int64, shape (n, 2)
        Solver iterations, fine and coarse (0 for the missing coarse solve on level 0).
    converged : ndarray of bool, shape (n, 2)
        Whether each solve converged (True for the missing coarse solve on level 0).
    """

    level: int
    stage: int
    indices: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray
    cost: np.ndarray
    n_iter: np.ndarray
    converged: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.indices)
        expected = {
            "indices": (n,),
            "cost": (n,),
            "n_iter": (n, 2),
            "converged": (n, 2),
        }
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"LevelBatch.{name} has shape {np.shape(getattr(self, name))}, expected {shape}")
        if np.ndim(self.fine) != 2 or np.shape(self.fine)[0] != n or np.shape(self.coarse) != np.shape(self.fine):
            raise ValueError(
                f"LevelBatch.fine/coarse must both have shape (n, n_qoi) with n={n}, "
                f"got {np.shape(self.fine)} and {np.shape(self.coarse)}"
            )

    @property
    def n_samples(self) -> int:
        """Number of samples in the batch."""
        return len(self.indices)

    @property
    def n_qoi(self) -> int:
        """Number of quantities of interest per sample."""
        return int(np.shape(self.fine)[1])

    @property
    def is_converged(self) -> np.ndarray:
        """Boolean mask, shape (n,): both solves of the sample converged."""
        return np.all(self.converged, axis=1)

    @property
    def n_not_converged(self) -> int:
        """Number of samples with a solve (fine or coarse) that did not converge."""
        return int(np.count_nonzero(~self.is_converged))

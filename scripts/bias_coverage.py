"""Do MLMC runs' reported errors cover their true error? A check of the bias estimate against a reference.

On the quickstart surface (box 1, k = 2/2/16, H = 0.8, relative load 0.1,
perimeter-corrected contact area in percent), a reference hierarchy of
coupled samples (seed 999, which no run uses) gives the level means
``E[Y_l]`` and so ``E[Q]`` on every grid from 16^2 to ``16 * 2^--reference-levels``;
then ``--runs`` independent runs of ``rough_uq.mlmc`` (problem seeds 1, 2, ...)
on grids ``--coarsest`` .. ``--coarsest * 2^--max-level`` at ``--tol``. Printed
per run: its finest grid, estimate, reported bias and RMSE, whether it
claims the tolerance, and its error against the reference value of the
finest reference grid (the limit the runs estimate, short of the reference
grid's own bias, which the last level means bound).

    python scripts/bias_coverage.py --coarsest 16 --max-level 3 --tol 0.2 --runs 8
    python scripts/bias_coverage.py --coarsest 32 --max-level 3 --tol 0.2 --runs 8
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np

import rough_uq
from rough_uq.problem.sampler import compute_batch

SPECTRUM = rough_uq.SurfaceSpectrum(system_size=1, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=0.004)
REFERENCE_SEED = 999


def problem(coarsest: int, max_level: int, seed: int) -> rough_uq.ContactProblem:
    return rough_uq.ContactProblem(SPECTRUM, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"],
                                   coarsest=coarsest, max_level=max_level, seed=seed)


def reference(counts: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``E[Q]`` on grids 16 * 2^l and its standard error, from coupled level samples (levels 0..len(counts)-1)."""
    model = problem(16, len(counts) - 1, REFERENCE_SEED).sampler(1).model
    means, variances = [], []
    for level, n in enumerate(counts):
        start = time.perf_counter()
        batch = compute_batch(model, stage=1, level=level, indices=np.arange(n))
        y = batch.fine[:, 0] - (batch.coarse[:, 0] if level else 0.0)
        means.append(float(np.mean(y)))
        variances.append(float(np.var(y, ddof=1)) / n)
        print(f"reference level {level} ({16 * 2**level}^2): mean Y {means[-1]:+.4f} ± {math.sqrt(variances[-1]):.4f}"
              f" ({n} samples, {time.perf_counter() - start:.0f} s)", flush=True)
    return np.cumsum(means), np.sqrt(np.cumsum(variances))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coarsest", type=int, default=16)
    parser.add_argument("--max-level", type=int, default=3)
    parser.add_argument("--tol", type=float, default=0.2)
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--reference-samples", default="40000,20000,4000,1000,200,50",
                        help="coupled samples per reference level from 16^2 (default up to 512^2)")
    args = parser.parse_args()
    values, errors = reference([int(n) for n in args.reference_samples.split(",")])
    limit = values[-1]
    print(f"reference E[Q] on {16 * 2 ** (len(values) - 1)}^2: {limit:.3f} ± {errors[-1]:.3f}")
    print("seed  finest  estimate  bias   rmse   met    error vs reference  error / rmse")
    for seed in range(1, args.runs + 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rough_uq.EstimationWarning)
            result = rough_uq.mlmc(problem(args.coarsest, args.max_level, seed), tol=args.tol)
        finest = args.coarsest * 2 ** int(result.levels[-1])
        error = float(result.estimate[0]) - limit
        rmse = float(result.rmse[0])
        print(f"{seed:4d}  {finest:5d}^2  {result.estimate[0]:8.3f}  {result.bias_estimate[0]:.3f}  {rmse:.3f}  "
              f"{str(bool(result.tol_met)):5s}  {error:+18.3f}  {abs(error) / rmse:12.2f}", flush=True)


if __name__ == "__main__":
    main()

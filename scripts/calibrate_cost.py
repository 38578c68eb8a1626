"""Fit the constants of roughuq's cost model (rough_uq.problem.sampler.modelled_cost).

The estimators plan with a *modelled* cost so that the plan does not depend on
the speed of the process that drew a sample (see the module docstring of
rough_uq.problem.sampler). One solve is modelled as

    (n_iter + COST_EXTRA_ITERATIONS) * (COST_PER_POINT * n^2 log2(n^2) + COST_PER_ITERATION)

reference seconds. This script times samples of the quickstart spectrum on
grids 32..512 (1 thread), fits the two constants by least squares on the
relative error, and prints them with the measured/modelled ratio per grid.

    python scripts/calibrate_cost.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from rough_uq.problem.sampler import COST_EXTRA_ITERATIONS  # noqa: E402
from rough_uq.physics.solver import solve_contact  # noqa: E402
from rough_uq.physics.surface import SurfaceSpectrum, sample_surface  # noqa: E402

SIZES = (32, 64, 128, 256, 512)


def measure(repeats: int) -> list[tuple[int, int, float]]:
    """(n, iterations, seconds) of solves on each grid, surface synthesis included."""
    spectrum = SurfaceSpectrum(system_size=1.0, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1.0)
    pressure = 0.1 * spectrum.rms_slope
    rows = []
    for n in SIZES:
        for repeat in range(repeats + 1):
            rng = np.random.default_rng(repeat)
            start = time.perf_counter()
            heights = sample_surface(spectrum, n, rng)
            solution = solve_contact(heights, system_size=1.0, mean_pressure=pressure)
            seconds = time.perf_counter() - start
            if repeat:  # the first solve of a size pays for FFT planning
                rows.append((n, solution.n_iter, seconds))
    return rows


def fit(rows: list[tuple[int, int, float]]) -> tuple[float, float]:
    """Least-squares constants (per point-log, per iteration), relative residuals."""
    design = np.array([[(it + COST_EXTRA_ITERATIONS) * n * n * math.log2(n * n), it + COST_EXTRA_ITERATIONS]
                       for n, it, _ in rows])
    seconds = np.array([s for _, _, s in rows])
    weights = 1.0 / seconds
    coefficients, *_ = np.linalg.lstsq(design * weights[:, None], seconds * weights, rcond=None)
    return float(coefficients[0]), float(coefficients[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = measure(args.repeats)
    per_point, per_iteration = fit(rows)
    print(f"COST_PER_POINT = {per_point:.3e}\nCOST_PER_ITERATION = {per_iteration:.3e}")
    print(f"{'n':>6} {'iters':>6} {'seconds':>9} {'model':>9} {'ratio':>6}")
    for n, it, seconds in rows:
        model = (it + COST_EXTRA_ITERATIONS) * (per_point * n * n * math.log2(n * n) + per_iteration)
        print(f"{n:>6} {it:>6} {seconds:>9.4f} {model:>9.4f} {seconds / model:>6.2f}")


if __name__ == "__main__":
    main()

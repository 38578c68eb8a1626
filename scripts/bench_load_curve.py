"""Warm-started load curves against independent solves, on the classic surface.

    python scripts/bench_load_curve.py [--grids 512 1024] [--samples 2] [--loads 0.01 0.02 0.05 0.1 0.2]

For each grid and each of a few surfaces of the classic area study (``L = 2``,
``k_l = k_r = 2``, ``k_s = 128``, ``H = 0.8``, RMS height 1, ``E* = 1``),
solves the relative loads ``p / (E* sqrt(m2))`` once as a warm-started
sequence (:func:`rough_uq.physics.load_curve.solve_load_curve`) and once as
independent cold solves (:func:`rough_uq.physics.solver.solve_contact`), at
the config's default tolerance 1e-7, and prints iterations and seconds per
load side by side, with the largest relative L2 difference of the pressures.
Timing only: nothing is asserted (the tests check the equality).
"""

from __future__ import annotations

import argparse
import os
import time
from datetime import date

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from rough_uq.physics.load_curve import solve_load_curve  # noqa: E402
from rough_uq.physics.solver import solve_contact  # noqa: E402
from rough_uq.physics.surface import SurfaceSpectrum, sample_surface  # noqa: E402

TOL = 1e-7
CLASSIC = SurfaceSpectrum(system_size=2.0, k_l=2, k_r=2, k_s=128, hurst=0.8, rms_height=1.0)


def timed(function, **kwargs):
    """``(result, seconds)`` of one call."""
    start = time.perf_counter()
    result = function(**kwargs)
    return result, time.perf_counter() - start


def bench_surface(heights: np.ndarray, pressures: np.ndarray) -> dict[str, np.ndarray]:
    """Iterations per load and seconds of the whole curve: sequence and independent; pressure differences."""
    curve, curve_seconds = timed(
        solve_load_curve, heights=heights, system_size=CLASSIC.system_size, mean_pressures=pressures, tol=TOL
    )
    cold_iter = np.zeros(pressures.size, dtype=int)
    cold_seconds = 0.0
    difference = np.zeros(pressures.size)
    for j, load in enumerate(pressures):
        cold, seconds = timed(
            solve_contact, heights=heights, system_size=CLASSIC.system_size, mean_pressure=load, tol=TOL
        )
        cold_seconds += seconds
        cold_iter[j] = cold.n_iter
        warm = curve.solutions[j].pressure
        difference[j] = np.linalg.norm(warm - cold.pressure) / np.linalg.norm(cold.pressure)
    if not curve.is_converged:
        print("  (a warm-started solve did not converge)")
    return dict(curve_iter=curve.n_iter, cold_iter=cold_iter, curve_seconds=np.array(curve_seconds),
                cold_seconds=np.array(cold_seconds), difference=difference)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grids", type=int, nargs="+", default=[512, 1024])
    parser.add_argument("--samples", type=int, default=2)
    parser.add_argument("--loads", type=float, nargs="+", default=[0.01, 0.02, 0.05, 0.1, 0.2])
    parser.add_argument("--seed", type=int, default=18)
    args = parser.parse_args()
    relative = np.sort(np.asarray(args.loads, dtype=float))
    pressures = relative * CLASSIC.rms_slope
    print(f"roughuq load curves, {date.today()}, {os.cpu_count()} cores, classic surface, tol {TOL:g}, "
          f"{args.samples} surfaces per grid, relative loads {' '.join(f'{r:g}' for r in relative)}")
    solve_contact(sample_surface(CLASSIC, 256, np.random.default_rng(0)), system_size=2.0, mean_pressure=0.1)  # JIT
    for n in args.grids:
        rng = np.random.default_rng([args.seed, n])
        keys = ("curve_iter", "cold_iter", "curve_seconds", "cold_seconds")
        totals = dict.fromkeys(keys, 0.0)
        worst = np.zeros(relative.size)
        for _ in range(args.samples):
            result = bench_surface(sample_surface(CLASSIC, n, rng), pressures)
            totals = {key: totals[key] + result[key] / args.samples for key in keys}
            worst = np.maximum(worst, result["difference"])
        print(f"\ngrid {n}x{n}, iterations per load (mean over surfaces)")
        print(f"{'load':>6} {'sequence':>9} {'cold':>9} {'max rel L2 diff':>16}")
        for j, r in enumerate(relative):
            print(f"{r:6g} {totals['curve_iter'][j]:9.1f} {totals['cold_iter'][j]:9.1f} {worst[j]:16.2e}")
        seq_iter, cold_iter = float(np.sum(totals["curve_iter"])), float(np.sum(totals["cold_iter"]))
        seq_s, cold_s = float(totals["curve_seconds"]), float(totals["cold_seconds"])
        print(f"{'curve':>6} {seq_iter:9.1f} {cold_iter:9.1f}   seconds: sequence {seq_s:.2f}, cold {cold_s:.2f}; "
              f"saving {1 - seq_iter / cold_iter:.0%} of the iterations, {1 - seq_s / cold_s:.0%} of the time")


if __name__ == "__main__":
    main()

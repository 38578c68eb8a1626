"""How much the solver tolerance moves the quantities of interest (issue: solve only as accurately as needed).

For classic surfaces (SPEC section 6) at several grids, every sample is solved
at each tolerance of ``--tols`` and its quantities of interest are compared
with those of the tightest tolerance: the contact area in percent (node count
and perimeter-corrected) on the contact-area setting, and the cluster density
per unit area with 4- and 8-connectivity on the cluster setting. Printed per
grid and tolerance: the mean over samples of the change (the solver's bias on
the estimate) and the largest change of one sample, next to 1 % of the tightest
tolerance of the classic studies (0.2 % for the area, 2 per unit area for the
clusters): the budget the solver may spend of the error.

    python scripts/tolerance_study.py --grids 256,512,1024,2048 --samples 16,8,4,2
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from rough_uq.physics.qoi import contact_area, count_clusters
from rough_uq.physics.solver import solve_contact
from rough_uq.physics.surface import SurfaceSpectrum, sample_surface

#: 1 % of the tightest tolerances of SPEC section 6.
BUDGET = {"area_nodes": 0.002, "area_corrected": 0.002, "clusters4": 0.02, "clusters8": 0.02}


def quantities(pressure: np.ndarray, size: float, setting: str) -> dict[str, float]:
    if setting == "area":
        return {f"area_{e}": 100.0 * contact_area(pressure, estimator=e) for e in ("nodes", "corrected")}
    return {f"clusters{c}": count_clusters(pressure > 0, connectivity=c) / size**2 for c in (4, 8)}


def study(setting: str, n: int, n_samples: int, tols: list[float], threads: int) -> None:
    size = 2.0 if setting == "area" else 3.0
    spectrum = SurfaceSpectrum(system_size=size, k_l=size, k_r=size, k_s=64 * size, hurst=0.8, rms_height=1)
    load = 0.1 * spectrum.rms_slope
    changes: dict[float, list[dict[str, float]]] = {tol: [] for tol in tols}
    iterations = {tol: [] for tol in tols}
    start = time.perf_counter()
    for sample in range(n_samples):
        heights = sample_surface(spectrum, n, np.random.default_rng([2026, n, sample]))
        values = {}
        for tol in tols:
            solution = solve_contact(heights, system_size=size, mean_pressure=load, tol=tol, threads=threads)
            if not solution.converged:
                sys.exit(f"{setting} {n}^2 sample {sample} tol {tol:g}: {solution.message}")
            values[tol] = quantities(solution.pressure, size, setting)
            iterations[tol].append(solution.n_iter)
        reference = values[min(tols)]
        for tol in tols:
            changes[tol].append({k: v - reference[k] for k, v in values[tol].items()})
    print(f"\n{setting} setting (L = {size:g}), {n}^2, {n_samples} samples, {time.perf_counter() - start:.0f} s")
    names = list(changes[tols[0]][0])
    print(f"{'tol':>8} {'iter':>5}  " + "  ".join(f"{name + ' mean':>20} {'max':>8}" for name in names))
    for tol in tols:
        cells = []
        for name in names:
            column = np.array([change[name] for change in changes[tol]])
            cells.append(f"{column.mean():>+20.5f} {np.abs(column).max():>8.5f}")
        print(f"{tol:>8.0e} {np.mean(iterations[tol]):>5.0f}  " + "  ".join(cells))
    print("budget (1 % of the tightest classic tolerance): " + ", ".join(f"{k} {BUDGET[k]}" for k in names))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grids", default="256,512,1024,2048")
    parser.add_argument("--samples", default="16,8,4,2", help="samples per grid, one per entry of --grids")
    parser.add_argument("--tols", default="1e-4,1e-5,1e-6,1e-7,1e-8,1e-9,1e-10")
    parser.add_argument("--settings", default="area,clusters")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    grids = [int(g) for g in args.grids.split(",")]
    samples = [int(s) for s in args.samples.split(",")]
    tols = sorted((float(t) for t in args.tols.split(",")), reverse=True)
    print(f"command: python scripts/tolerance_study.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    for setting in args.settings.split(","):
        for n, n_samples in zip(grids, samples):
            # The cluster setting's grids are 1.5 times finer per box (L = 3, same spacing ladder from 128^2 x 1.5).
            grid = n if setting == "area" else 3 * n // 2
            study(setting, grid, n_samples, tols, args.threads)


if __name__ == "__main__":
    main()

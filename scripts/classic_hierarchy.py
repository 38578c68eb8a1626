"""Level hierarchies of the classic settings: estimator variants and high-resolution references (issue 16).

Coupled samples of a classic setting (SPEC section 6) on a hierarchy of grids,
each solved once; from every contact map the script evaluates several
variants of the quantity:

* ``--setting area`` (L = 2, k = 2/2/128): the contact area in percent, node
  count (``nodes``) and perimeter-corrected (``corrected``);
* ``--setting clusters`` (L = 3, k = 3/3/192): clusters per unit area with
  4-connectivity, 8-connectivity and their mean (``mixed``: the two approach
  the limit from opposite sides).

Per variant it prints the level means ``Q_l`` and ``Y_l = Q_l - Q_{l-1}``, the
telescoping (MLMC) estimate of ``E[Q]`` on the finest grid with its standard
error (the reference: every level has its own independent samples), the rates
fitted on the first ``--fit-levels`` levels and the MLMC plan for ``--tol``
(``rough_uq.multilevel.allocation.plan``) with level 0 as coarsest, level 1
as coarsest, and the coarsest useful level chosen from the data. Levels
beyond ``--fit-levels`` check the limit at a resolution finer than any level
the plan uses.

    python scripts/classic_hierarchy.py --setting clusters --coarsest 96 \
        --samples 40,40,40,30,12,4 --fit-levels 5 --tol 2

Samples use their own stage of the study seed (``STAGE``), so they are
independent of any study's screening and runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import time
from pathlib import Path

import numpy as np

from rough_uq.errors import EstimationError
from rough_uq.multilevel.allocation import plan
from rough_uq.multilevel.rates import fit_rates
from rough_uq.multilevel.statistics import level_statistics
from rough_uq.physics.qoi import contact_area, count_clusters
from rough_uq.problem.sampler import solve_sample
from rough_uq.study.config import load_config
from rough_uq.study.pipeline import build_model

#: Coupled (odd) stage not used by any study run of the shipped configs' seed.
STAGE = 2_000_001
CONFIGS = Path(__file__).resolve().parent.parent / "rough_uq" / "study" / "configs"
SETTINGS = {"area": "classic-area.yaml", "clusters": "classic-clusters.yaml"}
VARIANTS = {"area": ("nodes", "corrected"), "clusters": ("4", "8", "mixed")}


def _values(setting: str, pressure: np.ndarray, box: float) -> np.ndarray:
    if setting == "area":
        return 100.0 * np.array([contact_area(pressure, estimator="nodes"), contact_area(pressure)])
    contact = pressure > 0
    four = count_clusters(contact, connectivity=4) / box**2
    eight = count_clusters(contact, connectivity=8) / box**2
    return np.array([four, eight, 0.5 * (four + eight)])


def _sample(args: tuple) -> tuple[int, int, np.ndarray, np.ndarray, float]:
    setting, model, level, index = args
    start = time.perf_counter()
    sample = solve_sample(model, stage=STAGE, level=level, index=index)
    box = model.spectrum.system_size
    fine = _values(setting, sample.fine.pressure, box)
    coarse = _values(setting, sample.coarse.pressure, box) if sample.coarse is not None else np.zeros_like(fine)
    return level, index, fine, coarse, time.perf_counter() - start


def compute(setting: str, model, samples: list[int], workers: int, known: dict | None = None) -> dict:
    """``{level: {"fine", "coarse", "seconds"}}`` for ``samples[l]`` coupled samples per level.

    ``known`` (the ``levels`` of an earlier run's JSON, same setting and grids)
    supplies samples already computed: only the missing indices are solved.
    """
    results: dict[int, list] = {level: [] for level in range(len(samples))}
    for level, rows in (known or {}).items():
        level = int(level)
        if level < len(samples):
            n = min(samples[level], len(rows["seconds"]))
            results[level] = [
                (i, np.array(rows["fine"][i]), np.array(rows["coarse"][i]), rows["seconds"][i]) for i in range(n)
            ]
    tasks = [
        (setting, model, level, index)
        for level, n in enumerate(samples)
        for index in range(len(results[level]), n)
    ]
    tasks.sort(key=lambda task: -task[2])  # the expensive levels first, for load balance
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        for level, index, fine, coarse, seconds in pool.imap_unordered(_sample, tasks):
            results[level].append((index, fine, coarse, seconds))
            print(f"  level {level} sample {index}: {np.round(fine, 2)} ({seconds:.1f} s)", flush=True)
    out = {}
    for level, rows in results.items():
        rows.sort(key=lambda row: row[0])
        out[level] = {
            "fine": np.array([row[1] for row in rows]),
            "coarse": np.array([row[2] for row in rows]),
            "seconds": np.array([row[3] for row in rows]),
        }
    return out


def analyse(data: dict, variants: tuple[str, ...], *, coarsest: int | None, tol: float, n_fit: int) -> dict:
    """Statistics of levels ``0..n_fit-1``, rates and the MLMC plan at ``tol`` starting on level ``coarsest``.

    ``coarsest=None`` lets :func:`~rough_uq.multilevel.rates.choose_coarsest_level` decide.
    The plan may extrapolate beyond ``n_fit - 1`` with the fitted rates.
    """
    report = {}
    for v, name in enumerate(variants):
        levels = range(n_fit)
        statistics = level_statistics(
            fine=[data[level]["fine"][:, v] for level in levels],
            coarse=[data[level]["coarse"][:, v] for level in levels],
            cost=[data[level]["seconds"] for level in levels],
        )
        rates = fit_rates(statistics)
        entry = {
            "mean_Q": statistics.mean_fine[:, 0].tolist(),
            "var_Q": statistics.var_fine[:, 0].tolist(),
            "mean_Y": statistics.mean_diff[:, 0].tolist(),
            "var_Y": statistics.var_diff[:, 0].tolist(),
            "alpha": float(rates.alpha[0]),
            "beta": float(rates.beta[0]),
            "gamma": float(rates.gamma),
        }
        try:
            prediction = plan(tol=tol, rates=rates, statistics=statistics, coarsest_level=coarsest)
        except EstimationError as exc:
            report[name] = {**entry, "no_plan": str(exc)}
            continue
        report[name] = {
            **entry,
            "coarsest_level": int(prediction.coarsest_level),
            "finest_level": int(prediction.finest_level),
            "n_samples": [int(n) for n in prediction.n_samples],
            "mlmc_seconds": float(prediction.cost),
            "mc_seconds": float(prediction.mc_cost),
            "bias": float(np.max(prediction.bias)),
        }
    return report


def reference(data: dict, variants: tuple[str, ...]) -> dict:
    """Per variant, the telescoping estimate of ``E[Q]`` on the finest grid and its standard error.

    The estimate is ``sum_l mean(Y_l)``.
    """
    out = {}
    for v, name in enumerate(variants):
        means, variances = [], []
        for level in sorted(data):
            y = data[level]["fine"][:, v] - data[level]["coarse"][:, v]
            means.append(y.mean())
            variances.append(y.var(ddof=1) / len(y) if len(y) > 1 else np.nan)
        out[name] = {"estimate": float(np.sum(means)), "std_error": float(np.sqrt(np.sum(variances)))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", choices=sorted(SETTINGS), required=True)
    parser.add_argument("--samples", required=True, help="coupled samples per level, comma separated")
    parser.add_argument(
        "--fit-levels", type=int, default=None, help="levels used for the fits and plans (default: all)"
    )
    parser.add_argument(
        "--tol", type=float, required=True, help="tolerance of the predicted MLMC plans (unit of the QoI)"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--coarsest", type=int, default=None, help="grid of level 0 (default: the shipped config's)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--resume", type=Path, default=None, help="JSON of an earlier run: reuse its samples")
    args = parser.parse_args()
    samples = [int(n) for n in args.samples.split(",")]
    variants = VARIANTS[args.setting]
    model = build_model(load_config(CONFIGS / SETTINGS[args.setting]))
    if args.coarsest:
        model = dataclasses.replace(model, coarsest=args.coarsest)
    start = time.perf_counter()
    known = None
    if args.resume:
        earlier = json.loads(args.resume.read_text())
        if earlier["setting"] != args.setting or earlier["grids"][0] != model.grid(0):
            parser.error(f"--resume {args.resume}: another setting or coarsest grid")
        known = earlier["levels"]
    data = compute(args.setting, model, samples, args.workers, known)
    n_fit = args.fit_levels or len(samples)
    summary = {
        "setting": args.setting,
        "variants": variants,
        "samples": samples,
        "grids": [model.grid(level) for level in range(len(samples))],
        "tol": args.tol,
        "seconds": time.perf_counter() - start,
        "reference": reference(data, variants),
        "levels": {level: {key: value.tolist() for key, value in data[level].items()} for level in data},
    }
    for coarsest in (0, 1, None):
        key = f"coarsest_{model.grid(coarsest)}" if coarsest is not None else "coarsest_auto"
        summary[key] = analyse(data, variants, coarsest=coarsest, tol=args.tol, n_fit=n_fit)
    _print(summary)
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))


def _print(summary: dict) -> None:
    variants = summary["variants"]
    print(f"computed in {summary['seconds']:.0f} s")
    print("\nlevel means (fine Q_l; Y_l = Q_l - Q_{l-1} on the same surfaces, with its standard error)")
    for level, grid in enumerate(summary["grids"]):
        fine = np.array(summary["levels"][level]["fine"])
        y = fine - np.array(summary["levels"][level]["coarse"])
        se = y.std(axis=0, ddof=1) / np.sqrt(len(y)) if len(y) > 1 else np.full(len(variants), np.nan)
        cells = "  ".join(
            f"{name}: Q {fine[:, v].mean():7.2f}  Y {y[:, v].mean():+7.3f} ± {se[v]:.3f}"
            for v, name in enumerate(variants)
        )
        print(f"  {grid:5d}^2 (N={len(fine):3d})  {cells}")
    print(f"\ntelescoping estimate on {summary['grids'][-1]}^2:")
    for name, r in summary["reference"].items():
        print(f"  {name:>9}: {r['estimate']:.3f} ± {r['std_error']:.3f}")
    fitted = summary["grids"][: len(next(iter(summary["coarsest_auto"].values()))["mean_Q"])]
    for key in [k for k in summary if k.startswith("coarsest_")]:
        print(f"\n{key}: MLMC plan at eps = {summary['tol']} (rates fitted on grids {fitted})")
        for name in variants:
            _print_plan(name, summary[key][name])


def _print_plan(name: str, r: dict) -> None:
    if "no_plan" in r:
        print(f"  {name:>9}: alpha {r['alpha']:.2f} beta {r['beta']:.2f}: no plan ({r['no_plan']})")
        return
    print(
        f"  {name:>9}: alpha {r['alpha']:.2f} beta {r['beta']:.2f} gamma {r['gamma']:.2f}  "
        f"levels {r['coarsest_level']}..{r['finest_level']}  N_l {r['n_samples']}  "
        f"cost {r['mlmc_seconds']:.0f} s (MC {r['mc_seconds']:.0f} s)  bias {r['bias']:.3f}"
    )


if __name__ == "__main__":
    main()

"""Tables of the classic studies: every run of a study file against a reference value (issue 16).

    python scripts/classic_tables.py classic_area.h5 --reference docs/classic/reference.json --qoi contact_area
    python scripts/classic_tables.py classic_area.h5 --reference-value 19.21 --reference-error 0.02

Reads the study file with ``roughuq report --json`` and prints a Markdown table
with, per finished run (MLMC and MC side by side, tightest tolerance last):
the tolerance, the estimate, its statistical error, the estimated bias, the
RMSE, the deviation from the reference in units of ``eps`` (the acceptance
check is ``|estimate - reference| <= 2 eps``), the samples per level, the wall
time of the run and whether the tolerance was met. ``--json`` also writes the
rows. Exit status 1 if any estimate lies farther than ``2 eps`` from the
reference.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def _report(path: Path) -> dict:
    out = subprocess.run(["roughuq", "report", str(path), "--json"], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def _levels(run: dict, grids: list[int]) -> str:
    return " ".join(f"{n}@{grids[level]}" for level, n in zip(run["levels"], run["n_samples"]) if n > 0)


def rows(report: dict, qoi: str, reference: float) -> list[dict]:
    """One row per finished run of ``report`` for QoI ``qoi``."""
    column = report["qoi_names"].index(qoi)
    grids = report["config"]["grids"]
    out = []
    for run in report["runs"]:
        if run.get("status") != "finished":
            continue
        eps = run["tol"][column]
        estimate = run["estimate"][column]
        out.append(
            {
                "method": run["method"] + (" (Richardson)" if run.get("richardson") == "applied" else ""),
                "eps": eps,
                "estimate": estimate,
                "stat_error": run["stat_error"][column],
                "bias": run["bias_estimate"][column] if run.get("is_bias_estimated", True) else None,
                "rmse": run["rmse"][column],
                "deviation": (estimate - reference) / eps,
                "samples": _levels(run, grids),
                "elapsed": run["elapsed"],
                "tol_met": run["tol_met"],
            }
        )
    out.sort(key=lambda row: (-row["eps"], row["method"]))
    return out


def markdown(table: list[dict]) -> str:
    lines = [
        "| method | eps | estimate | stat. error | bias | RMSE | (est. - ref.) / eps | N_l @ grid | wall | met |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in table:
        bias = "n/a" if row["bias"] is None else f"{row['bias']:.3g}"
        lines.append(
            f"| {row['method']} | {row['eps']:g} | {row['estimate']:.3f} | {row['stat_error']:.3f} | {bias} "
            f"| {row['rmse']:.3f} | {row['deviation']:+.2f} | {row['samples']} | {row['elapsed']:.1f} s "
            f"| {'yes' if row['tol_met'] else 'no'} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("--qoi", default=None, help="QoI column (default: the study's first)")
    parser.add_argument("--reference", type=Path, default=None, help="reference JSON (scripts/classic_hierarchy.py)")
    parser.add_argument("--variant", default=None, help="variant of the reference JSON (e.g. corrected, 8)")
    parser.add_argument("--reference-value", type=float, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    report = _report(args.study)
    qoi = args.qoi or report["qoi_names"][0]
    if args.reference is not None:
        entry = json.loads(args.reference.read_text())["reference"]
        value = entry[args.variant or next(iter(entry))]["estimate"]
    elif args.reference_value is not None:
        value = args.reference_value
    else:
        parser.error("give --reference or --reference-value")
    table = rows(report, qoi, value)
    print(f"{qoi}: reference {value:.3f}")
    print(markdown(table))
    if args.json:
        args.json.write_text(json.dumps({"qoi": qoi, "reference": value, "rows": table}, indent=1))
    outside = [row for row in table if abs(row["deviation"]) > 2]
    for row in outside:
        print(f"outside 2 eps: {row['method']} eps {row['eps']:g}: {row['deviation']:+.2f} eps", file=sys.stderr)
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main())

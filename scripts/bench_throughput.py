"""Sample throughput of roughuq's executors: serial against a pool of worker processes.

    python scripts/bench_throughput.py [--config quickstart.yaml] [--level 3] [--samples 24] [--threads 1]

Computes the same samples (stage 0, the given level) in this process and with
pools of 1..--max-workers spawned workers, prints samples per second and the
speed-up over serial, and checks the samples are identical. Pool start-up
(spawning, imports, JIT loading) is timed separately, not in the throughput.
The FFT plans are those a study uses for the level (its grid and the coarse
grid): measured once per machine for the solver threads, from the wisdom
file in the user cache directory (``rough_uq.study.fft_wisdom``); with
``ROUGHUQ_FFTW_WISDOM=estimate`` they are ``FFTW_ESTIMATE`` plans, as in a
study then.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from datetime import date

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from rough_uq.study.config import load_config  # noqa: E402
from rough_uq.study.executors import PoolExecutor, SerialExecutor  # noqa: E402
from rough_uq.study.fft_wisdom import prepare_wisdom  # noqa: E402
from rough_uq.study.pipeline import build_model  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def measure(executor, model, level: int, indices: np.ndarray) -> tuple[float, np.ndarray]:
    """Seconds to compute ``indices`` and the fine QoIs in index order."""
    items = [(0, level, indices[i : i + 1]) for i in range(indices.size)]
    start = time.perf_counter()
    batches = list(executor.run(model, items))
    seconds = time.perf_counter() - start
    order = np.argsort(np.concatenate([b.indices for b in batches]))
    return seconds, np.concatenate([b.fine for b in batches])[order]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=os.path.join(ROOT, "rough_uq", "study", "configs", "quickstart.yaml"))
    parser.add_argument("--level", type=int, default=3)
    parser.add_argument("--samples", type=int, default=24)
    parser.add_argument("--max-workers", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--threads", type=int, default=None, help="solver threads per process (default: the config's)")
    args = parser.parse_args()
    model = build_model(load_config(args.config))
    if args.threads is not None:
        model = dataclasses.replace(model, threads=args.threads)
    grids = sorted({model.grid(args.level), model.grid(max(args.level - 1, 0))})
    model = dataclasses.replace(model, fft_wisdom=prepare_wisdom(grids, threads=model.threads, note=print))
    indices = np.arange(args.samples)
    n = model.grid(args.level)
    plans = "FFTW_ESTIMATE" if model.fft_wisdom is None else "measured"
    print(f"roughuq throughput, {date.today()}, {os.cpu_count()} cores, grid {n}x{n} (level {args.level}), "
          f"{args.samples} samples, solver threads {model.threads}, {plans} FFT plans")
    serial = SerialExecutor()
    measure(serial, model, args.level, indices[:1])  # JIT and FFT plans, as a pool worker's start-up
    base, reference = measure(serial, model, args.level, indices)
    print(f"{'executor':>10} {'start s':>8} {'seconds':>8} {'samples/s':>10} {'speed-up':>9} identical")
    print(f"{'serial':>10} {'-':>8} {base:8.2f} {args.samples / base:10.2f} {1.0:9.2f} yes")
    for workers in range(1, args.max_workers + 1):
        with PoolExecutor(workers, threads=model.threads) as pool:
            start = time.perf_counter()
            measure(pool, model, args.level, indices[:workers])  # start every worker, load JIT caches
            startup = time.perf_counter() - start
            seconds, values = measure(pool, model, args.level, indices)
        same = "yes" if np.array_equal(values, reference) else "NO"
        print(f"{f'pool {workers}':>10} {startup:8.2f} {seconds:8.2f} {args.samples / seconds:10.2f} "
              f"{base / seconds:9.2f} {same}")


if __name__ == "__main__":
    main()

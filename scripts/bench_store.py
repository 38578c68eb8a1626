"""Cost of one flush of the study file: with 1 000 against 1 000 000 samples already stored.

    python scripts/bench_store.py [--small 1000] [--large 1000000] [--batch 100] [--repeats 40] [--dir /tmp]

Builds two study files that differ only in the number of samples already on
level 0, then appends the same batches (``--batch`` new samples, what a flush
of cheap coarse samples holds) to both, alternating between them so that both
see the same machine. A flush is one ``StudyFile.append_samples`` call:
duplicate check, in-place write, two fsyncs. The first append after opening
reads the level's indices once and is timed apart. For scale, it also times
what the version 1 store paid per flush: a copy and fsync of the whole file.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

from rough_uq.problem.batch import LevelBatch
from rough_uq.study.store import StudyFile, open_study

QOI = ("contact_area", "clusters")
FILL_BATCH = 50_000


def batch(rng: np.random.Generator, start: int, n: int) -> LevelBatch:
    """``n`` samples of stage 0, level 0, indices ``start ..``, with random values."""
    return LevelBatch(
        level=0,
        stage=0,
        indices=np.arange(start, start + n, dtype=np.int64),
        fine=rng.random((n, len(QOI))),
        coarse=np.zeros((n, len(QOI))),
        cost=rng.random(n),
        n_iter=rng.integers(10, 100, size=(n, 2)),
        converged=np.ones((n, 2), dtype=bool),
    )


def study(path: Path, n_samples: int, rng: np.random.Generator) -> StudyFile:
    """A study file at ``path`` holding ``n_samples`` samples, open for writing."""
    store = open_study(path, config_text="bench: 1\n", config_hash="0" * 64, qoi_names=QOI, code_version="bench")
    for start in range(0, n_samples, FILL_BATCH):
        store.append_samples(batch(rng, start, min(FILL_BATCH, n_samples - start)))
    store.close()
    return open_study(path, config_text="bench: 1\n", config_hash="0" * 64, qoi_names=QOI, create=False)


def timed_append(store: StudyFile, samples: LevelBatch) -> float:
    start = time.perf_counter()
    assert store.append_samples(samples) == samples.n_samples
    return time.perf_counter() - start


def copy_seconds(path: Path) -> float:
    """A copy of ``path`` with fsync: the version 1 store's cost per flush."""
    target = path.with_name(path.name + ".copy")
    start = time.perf_counter()
    shutil.copyfile(path, target)
    fd = os.open(target, os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    seconds = time.perf_counter() - start
    target.unlink()
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", type=int, default=1_000, help="samples already in the small file")
    parser.add_argument("--large", type=int, default=1_000_000, help="samples already in the large file")
    parser.add_argument("--batch", type=int, default=100, help="samples per flush")
    parser.add_argument("--repeats", type=int, default=40, help="flushes timed per file")
    parser.add_argument("--dir", default=None, help="where the files go (default: a temporary directory)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory(dir=args.dir) as directory:
        sizes = {"small": args.small, "large": args.large}
        start = time.perf_counter()
        stores = {name: study(Path(directory) / f"{name}.h5", n, rng) for name, n in sizes.items()}
        build = time.perf_counter() - start
        next_index = dict(sizes)
        first = {}
        for name, store in stores.items():
            first[name] = timed_append(store, batch(rng, next_index[name], args.batch))
            next_index[name] += args.batch
        seconds: dict[str, list[float]] = {name: [] for name in stores}
        for _ in range(args.repeats):  # side by side: small, large, small, large, ...
            for name, store in stores.items():
                seconds[name].append(timed_append(store, batch(rng, next_index[name], args.batch)))
                next_index[name] += args.batch
        for store in stores.values():
            store.close()
        file_bytes = {name: (Path(directory) / f"{name}.h5").stat().st_size for name in stores}
        copies = {name: np.median([copy_seconds(Path(directory) / f"{name}.h5") for _ in range(3)]) for name in stores}
    print(f"roughuq study file flush, {date.today()}, {os.cpu_count()} cores, {args.batch} samples per flush, "
          f"{args.repeats} flushes per file (files built in {build:.1f} s)")
    print(f"{'file':>6} {'samples':>9} {'MB':>7} {'first ms':>9} {'median ms':>10} {'p90 ms':>7} {'max ms':>7} "
          f"{'v1 copy ms':>11}")
    for name in stores:
        ms = 1e3 * np.asarray(seconds[name])
        print(f"{name:>6} {sizes[name]:>9} {file_bytes[name] / 1e6:7.1f} {1e3 * first[name]:9.1f} "
              f"{np.median(ms):10.2f} {np.percentile(ms, 90):7.2f} {ms.max():7.2f} {1e3 * copies[name]:11.1f}")
    ratio = np.median(seconds["large"]) / np.median(seconds["small"])
    ratio_p90 = np.percentile(seconds["large"], 90) / np.percentile(seconds["small"], 90)
    verdict = "within 2x" if ratio < 2 else "NOT within 2x"
    print(f"flush time, {args.large} / {args.small} samples stored: median ratio {ratio:.2f}, "
          f"p90 ratio {ratio_p90:.2f} ({verdict})")


if __name__ == "__main__":
    main()

"""Where one iteration of the contact solver spends its time.

Solves the benchmark surface of ``scripts/bench_solver.py`` (classic setting,
SPEC section 6, load 0.1 E* sqrt(m2), tol 1e-8, one thread unless
``--threads`` says otherwise, measured FFT plans) with every FFT call and
every fused pass of :mod:`rough_uq.physics.solver` wrapped in a timer, and
prints milliseconds per iteration by component, next to a hot-cache
double-precision FFT pair of the same plan (the unit of the per-iteration target of ``bench_solver.py``).

The point: the preconditioned iteration needs five half transforms in
single precision (the preconditioner ``M r``, the transform of the search
direction, the displacement of the pressure increment ``K e``),
plus a double-precision pair for the exact displacement whenever the error
has fallen a hundredfold. Timed inside the solve, where the arrays of the
iteration do not fit in the cache together, the transforms alone cost about
two hot-cache double pairs at 1024^2 (their floor in the benchmark).

    python scripts/profile_solver.py [--sizes 1024,2048] [--threads 1]

With ``--threads 2`` every component runs on two FFTW and numba threads (the
hot-cache pair too), which shows where a second thread per solve pays and
where it costs more than it saves.

Timers add a few microseconds per call; the total is printed beside the
untimed solve for comparison.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_solver  # noqa: E402  (the reference surface and load of the benchmark)

import rough_uq.physics.solver as solver  # noqa: E402
from rough_uq.physics.fft import RealFFT, get_fft, measure_plans  # noqa: E402
from rough_uq.physics.surface import sample_surface  # noqa: E402

_PASSES = (
    "_gap_pass", "_residual_pass", "_active_sum", "_direction",
    "_energy", "_multiply_energy", "_step", "multiply_spectrum",
)


class _Timers:
    """Seconds and calls per label, collected by wrappers around solver internals."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.calls: collections.Counter[str] = collections.Counter()

    def wrap(self, function, label):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            result = function(*args, **kwargs)
            self.seconds[label(args)] += time.perf_counter() - start
            self.calls[label(args)] += 1
            return result

        return timed


@contextlib.contextmanager
def _instrumented(timers: _Timers):
    """The solver's passes and the FFT methods replaced by timed wrappers while the block runs."""
    originals = [(solver, name, getattr(solver, name)) for name in _PASSES]
    originals += [(RealFFT, name, getattr(RealFFT, name)) for name in ("forward", "inverse")]
    precision = {np.dtype("float32"): "single", np.dtype("float64"): "double"}
    for owner, name, function in originals:
        if owner is solver:
            label = lambda args, name=name: name  # noqa: E731
        else:
            label = lambda args, name=name: f"FFT {name} ({precision[args[0].real.dtype]})"  # noqa: E731
        setattr(owner, name, timers.wrap(function, label))
    try:
        yield
    finally:
        for owner, name, function in originals:
            setattr(owner, name, function)


def _hot_pair(n: int, threads: int) -> float:
    """Best of 20 forward + inverse pairs of the solver's double-precision plan, data in cache."""
    plan = get_fft(n, threads=threads, separate_output=True)
    plan.real[...] = np.random.default_rng(0).standard_normal((n, n))
    best = np.inf
    for _ in range(20):
        start = time.perf_counter()
        plan.forward()
        plan.inverse()
        best = min(best, time.perf_counter() - start)
    return best


def profile(n: int, threads: int = 1) -> str:
    """The per-iteration table of one grid, as text."""
    spectrum = bench_solver.reference_spectrum()
    pressure = bench_solver.mean_pressure(spectrum)
    heights = sample_surface(spectrum, n, np.random.default_rng(1))
    measure_plans([n], threads=threads)
    pair = _hot_pair(n, threads)
    solve = dict(system_size=bench_solver.SYSTEM_SIZE, mean_pressure=pressure, tol=1e-8, threads=threads)
    start = time.perf_counter()
    untimed = solver.solve_contact(heights, **solve)
    untimed_seconds = time.perf_counter() - start
    timers = _Timers()
    with _instrumented(timers):
        start = time.perf_counter()
        solution = solver.solve_contact(heights, **solve)
        total = time.perf_counter() - start
    iters = solution.n_iter
    lines = [
        f"{n}^2, {threads} thread(s): {iters} iterations; "
        f"untimed solve {1e3 * untimed_seconds / untimed.n_iter:.2f} ms/iteration, "
        f"instrumented {1e3 * total / iters:.2f} ms/iteration; hot-cache double FFT pair {1e3 * pair:.2f} ms",
        f"  {'component':<26} {'ms/iter':>8} {'pairs':>6} {'calls':>6}",
    ]
    for label in sorted(timers.seconds, key=lambda k: -timers.seconds[k]):
        per_iter = timers.seconds[label] / iters
        lines.append(f"  {label:<26} {1e3 * per_iter:8.2f} {per_iter / pair:6.2f} {timers.calls[label]:6d}")
    ffts = sum(v for k, v in timers.seconds.items() if k.startswith("FFT")) / iters
    other = total / iters - sum(timers.seconds.values()) / iters
    lines.append(f"  {'all FFTs':<26} {1e3 * ffts:8.2f} {ffts / pair:6.2f}")
    lines.append(f"  {'Python and the rest':<26} {1e3 * other:8.2f} {other / pair:6.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1024,2048", help="comma-separated grid sizes")
    parser.add_argument("--threads", type=int, default=1, help="FFTW and numba threads of every component")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    # Compile the passes outside the timings.
    bench_solver.warm_up(args.threads)
    for n in (int(s) for s in args.sizes.split(",")):
        print(profile(n, args.threads), flush=True)


if __name__ == "__main__":
    main()

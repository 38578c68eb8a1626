"""Benchmark the contact solver on the reference surface of SPEC section 6.

For each grid ``n`` one surface of the classic study (``L = 2``,
``lambda_l = lambda_r = 1``, ``lambda_s = 1/64``, ``H = 0.8``, RMS height 1,
``E* = 1``) is drawn with a seeded generator and solved at the paper load
``p_mean = 0.1 E* sqrt(m2)``. Everything below is measured side by side in one
run, so the ratios are meaningful even where the absolute times are not:

* FFT floor: the time of one double-precision real FFT pair (rfft2 + irfft2,
  median over batches) of every implementation at hand on the same grid and
  threads: pyFFTW with estimated, measured and patient plans (patient up to
  2048^2), each out of place and in place (FFTW's padded layout: half the
  memory traffic, the faster from 1024^2 on; at 256^2 the slower),
  ``scipy.fft`` and ``numpy.fft``, each measured twice, before and
  after the solver's timed solve, and planned afresh each time (a patient
  plan is only as good as the timings it was chosen by); the fastest of all
  is the floor, and the solver's time per iteration is printed over it
  (target: at most 2.0 at 1024^2 and 2048^2). The solver is timed with
  measured plans from wisdom, as studies use it
  (``rough_uq.study.fft_wisdom``), and once with ``FFTW_ESTIMATE``
  plans for comparison; the process's peak resident memory is printed after
  each grid;
* solver: iterations, seconds per solve and per iteration, the time of one real
  FFT pair (forward + inverse, double precision, the same cached plan and
  threads the solver uses, median over batches) and the ratios (s/iteration) /
  (FFT pair) and (s/solve) / (FFT pair), for the preconditioned solver (the
  default) and for plain Polonsky-Keer (``precondition=False``, up to
  ``--plain-max``) on the same surface. A plain iteration costs one double FFT pair and a single-precision
  forward transform plus fused passes; a preconditioned one does two and a
  half single-precision pairs (a single pair takes 0.55-0.7 of the time of a
  double pair at 1024^2-2048^2), plus a double pair whenever its error has
  fallen a hundredfold (the exact displacement, :mod:`rough_uq.physics.solver`),
  and needs about a third of the iterations. ``iter/transf`` divides the time
  of an iteration by the time of the transforms it must do (1 double and 0.5
  single pair for plain Polonsky-Keer, 2.5 single pairs preconditioned, each
  timed with the plan that solver uses: out-of-place, or in place with an
  unnormalised inverse): what the elementwise passes, the exact displacements
  and the Python loop add;
* warm start: the coupled coarse surface (grid ``n/2``, spectral truncation) is
  solved first and its pressure passed as ``initial_pressure`` to the fine
  solve; cold vs warm iterations and time;
* peer (if ``import tamaas`` works): Tamaas's PolonskyKeerRey on the same
  heights and mean pressure (``E = E*``, ``nu = 0``, model ``basic_2d``), the
  contact areas, the relative L2 difference of the pressure fields and the time
  ratio tamaas/roughuq. roughuq is solved once more at ``--tight-tol`` so that
  the field comparison is not dominated by roughuq's own tolerance. The height
  orientation and pressure scale of Tamaas are checked once on a small grid
  (both signs of the heights are tried; the one matching roughuq's contact
  area is used).

Timings exclude one-off costs: numba compilation (a small warm-up solve) and
FFT planning (the plan is built by the FFT timing before the first solve).

    python scripts/bench_solver.py [--sizes 256,512,1024] [--threads 1] [--tol 1e-8]
                                   [--seed 1] [--repeats 1] [--no-tamaas] [--tamaas-max 2048]
                                   [--plain-max 2048] [--json FILE]

2048 and 4096 are opt-in (``--sizes 256,512,1024,2048,4096``); with Tamaas
(up to ``--tamaas-max``) it takes many minutes.
"""

from __future__ import annotations

import os

# FFTW's threads and numba's OpenMP threads spin-wait for each other otherwise.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import resource  # noqa: E402
import shlex  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import pyfftw  # noqa: E402
import scipy.fft  # noqa: E402

from rough_uq.physics.fft import RealFFT, get_fft, measure_plans, use_wisdom  # noqa: E402
from rough_uq.physics.solver import ContactSolution, solve_contact  # noqa: E402
from rough_uq.physics.surface import SurfaceSpectrum, sample_coupled, sample_surface  # noqa: E402

#: SPEC section 6: box side, cut-off wavelengths (unit of L), Hurst exponent, RMS height.
SYSTEM_SIZE = 2.0
LAMBDA_L = 1.0
LAMBDA_R = 1.0
LAMBDA_S = 1.0 / 64.0
HURST = 0.8
RMS_HEIGHT = 1.0
E_STAR = 1.0
#: Dimensionless load p_mean / (E* sqrt(m2)).
RELATIVE_LOAD = 0.1

#: Minimum wall time of one batch of FFT pairs, and the number of batches (median taken).
FFT_BATCH_SECONDS = 0.05
FFT_BATCHES = 7

#: Tamaas: iteration budget (its default is 1000), tolerances below / from TAMAAS_FINE_GRID.
TAMAAS_MAX_ITER = 100_000
TAMAAS_TOL_COARSE = 1e-12
TAMAAS_TOL_FINE = 1e-10
TAMAAS_FINE_GRID = 1024
#: Grid of the one-off orientation check of Tamaas's height convention.
CONVENTION_GRID = 128


@dataclass
class SolveTiming:
    """One timed roughuq solve (median seconds over the repeats, and the first of them)."""

    n: int
    tol: float
    n_iter: int
    seconds: float
    first_seconds: float
    error: float
    converged: bool
    area_fraction: float


@dataclass
class GridRow:
    """The solver line of the main table."""

    n: int
    n_iter: int
    seconds_per_solve: float
    seconds_per_iteration: float
    fft_pair_seconds: float
    iteration_over_fft: float
    single_pair_seconds: float
    iteration_over_transforms: float
    solve_over_fft: float
    area_fraction: float
    error: float
    converged: bool
    plain_iter: int
    plain_seconds_per_solve: float
    plain_iteration_over_fft: float
    plain_iteration_over_transforms: float
    plain_solve_over_fft: float
    plain_converged: bool
    floor: dict[str, float]  # the faster of the two measurements of each implementation
    floor_before: dict[str, float]  # measured before the solve
    floor_after: dict[str, float]  # and after it
    floor_name: str
    floor_seconds: float
    iteration_over_floor: float
    first_iteration_over_floor: float
    estimate_iter: int
    estimate_seconds_per_solve: float
    peak_rss_mib: float


@dataclass
class WarmRow:
    """Cold vs warm-started solve of one fine grid."""

    n: int
    cold_iter: int
    cold_seconds: float
    coarse_iter: int
    coarse_seconds: float
    warm_iter: int
    warm_seconds: float
    iteration_reduction_percent: float
    time_reduction_percent: float
    time_reduction_with_coarse_percent: float


@dataclass
class PeerRow:
    """roughuq (at --tol and at --tight-tol) against Tamaas on one grid."""

    n: int
    tamaas_tol: float
    tamaas_iter: int | None
    tamaas_seconds: float
    tamaas_area_fraction: float
    tamaas_mean_pressure: float
    roughuq_iter: int
    roughuq_seconds: float
    roughuq_area_fraction: float
    roughuq_rel_l2: float
    tight_tol: float
    tight_iter: int
    tight_seconds: float
    tight_area_fraction: float
    tight_rel_l2: float
    time_ratio: float
    time_ratio_tight: float


def reference_spectrum() -> SurfaceSpectrum:
    """The PSD of SPEC section 6."""
    return SurfaceSpectrum.from_wavelengths(
        system_size=SYSTEM_SIZE,
        lambda_l=LAMBDA_L,
        lambda_r=LAMBDA_R,
        lambda_s=LAMBDA_S,
        hurst=HURST,
        rms_height=RMS_HEIGHT,
    )


def mean_pressure(spectrum: SurfaceSpectrum) -> float:
    """The paper load ``RELATIVE_LOAD * E* * sqrt(m2)`` (unit of E*), from the spectral model."""
    return RELATIVE_LOAD * E_STAR * spectrum.rms_slope


def environment(argv: list[str]) -> dict[str, object]:
    """Date, machine and library versions, and the exact command line."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    info: dict[str, object] = {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "machine": f"{platform.node()} {platform.machine()} {platform.processor() or ''}".strip(),
        "cores": f"{os.cpu_count()} logical, {usable} usable",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "pyfftw": pyfftw.__version__,
        "numba": f"{numba.__version__} (threading layer {numba.config.THREADING_LAYER}, "
        f"NUMBA_NUM_THREADS {numba.config.NUMBA_NUM_THREADS})",
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "command": shlex.join([os.path.basename(sys.executable)] + argv),
    }
    tamaas = import_tamaas()
    if tamaas is None:
        info["tamaas"] = "not installed"
    else:
        info["tamaas"] = f"{tamaas.__version__} (backend {tamaas.TamaasInfo.backend})"
    return info


def import_tamaas():
    """The ``tamaas`` module, or None when it is not installed."""
    try:
        import tamaas
    except ImportError:
        return None
    return tamaas


def warm_up(threads: int) -> None:
    """Load or compile the solver's numba kernels (and start its thread pool) outside the timings."""
    spectrum = reference_spectrum()
    heights = sample_surface(spectrum, 32, np.random.default_rng(0))
    for precondition in (True, False):
        solve_contact(
            heights,
            system_size=SYSTEM_SIZE,
            mean_pressure=mean_pressure(spectrum),
            threads=threads,
            precondition=precondition,
        )


def time_pair(pair) -> float:
    """Median seconds of one call of ``pair`` (a forward + inverse transform), over batches."""
    pair()
    start = time.perf_counter()
    n_pairs = 0
    while time.perf_counter() - start < FFT_BATCH_SECONDS:
        pair()
        n_pairs += 1
    batch = max(n_pairs, 1)
    samples = []
    for _ in range(FFT_BATCHES):
        start = time.perf_counter()
        for _ in range(batch):
            pair()
        samples.append((time.perf_counter() - start) / batch)
    return statistics.median(samples)


@contextlib.contextmanager
def _wisdom_kept():
    """FFTW's wisdom as it was before the block: plans measured inside leave no trace.

    FFTW serves later requests for the same transform (even ``FFTW_ESTIMATE``
    ones) from the wisdom of any plan it has made, so the floor's patient
    plans would otherwise become the solver's and the surfaces' plans.
    """
    saved = pyfftw.export_wisdom()
    try:
        yield
    finally:
        pyfftw.forget_wisdom()
        pyfftw.import_wisdom(saved)


def fft_floor(n: int, threads: int) -> dict[str, float]:
    """Seconds of one double-precision real FFT pair (rfft2 + irfft2) of every implementation at hand.

    pyFFTW with a freshly measured plan (FFTW_MEASURE, then FFTW_PATIENT) and an
    estimated one, each out of place (separate real and spectral arrays) and
    in place (one padded array, FFTW's layout for in-place real transforms:
    half the memory traffic, 0.73-0.84 of the time of the out-of-place pair at
    1024^2-2048^2 on the development machine), ``scipy.fft`` (pocketfft,
    ``workers=threads``) and ``numpy.fft`` (one thread); the floor of the
    per-iteration target is the fastest of them. Every pair normalises its
    inverse (irfft2). Every call plans afresh: FFTW's wisdom is forgotten
    inside (and restored after), so that no earlier plan, the solver's or the
    floor's own, stands in for an estimated or measured one.
    """
    x = np.random.default_rng(0).standard_normal((n, n))
    times = {}
    with _wisdom_kept():
        pyfftw.forget_wisdom()
        for effort in ("FFTW_ESTIMATE", "FFTW_MEASURE", "FFTW_PATIENT"):
            if effort == "FFTW_PATIENT" and n > 2048:
                continue  # planning alone would take many minutes
            for in_place in (False, True):
                plan = RealFFT((n, n), threads=threads, flags=(effort,), in_place=in_place)
                plan.real[...] = x
                name = f"pyfftw {effort[5:].lower()}{' in-place' if in_place else ''}"
                times[name] = time_pair(lambda plan=plan: (plan.forward(), plan.inverse()))
    times["scipy.fft"] = time_pair(
        lambda: scipy.fft.irfft2(scipy.fft.rfft2(x, workers=threads), s=(n, n), workers=threads)
    )
    times["numpy.fft"] = time_pair(lambda: np.fft.irfft2(np.fft.rfft2(x), s=(n, n)))
    return times


def time_fft_pair(n: int, threads: int, *, single: bool = False, in_place: bool = False) -> float:
    """Median seconds of one forward + inverse real FFT with the solver's cached plan of that kind.

    Double precision: the solver's plan of ``K p``, with a separate output
    buffer. Single precision: plain Polonsky-Keer's plan, or with
    ``in_place`` that of the preconditioned iteration (one padded buffer,
    inverse unnormalised, as the solver runs it).
    """
    plan = get_fft(n, threads=threads, single=single, separate_output=not single, in_place=in_place)
    plan.real[...] = np.random.default_rng(0).standard_normal((n, n))
    return time_pair(lambda: (plan.forward(), plan.inverse(normalise=not in_place)))


def warn_estimated_plans(n: int, threads: int) -> None:
    """Say so on stderr where one of the solver's plans (just timed) is estimated: the wisdom lacks it."""
    kinds = {"double": {}, "single": {"single": True}, "single in place": {"single": True, "in_place": True}}
    for name, layout in kinds.items():
        plan = get_fft(n, threads=threads, separate_output=not layout, **layout)
        if "FFTW_ESTIMATE" in plan.flags:
            print(f"warning: the solver's {name} plan of {n}^2 is estimated (not in the measured wisdom)",
                  file=sys.stderr)


def timed_solve(
    heights: np.ndarray,
    *,
    pressure: float,
    tol: float,
    threads: int,
    repeats: int,
    initial_pressure: np.ndarray | None = None,
    precondition: bool = True,
) -> tuple[ContactSolution, SolveTiming]:
    """Solve ``repeats`` times; the last solution, the median and the first wall time."""
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        solution = solve_contact(
            heights,
            system_size=SYSTEM_SIZE,
            mean_pressure=pressure,
            e_star=E_STAR,
            tol=tol,
            threads=threads,
            initial_pressure=initial_pressure,
            precondition=precondition,
        )
        seconds.append(time.perf_counter() - start)
    timing = SolveTiming(
        n=heights.shape[0],
        tol=tol,
        n_iter=solution.n_iter,
        seconds=statistics.median(seconds),
        first_seconds=seconds[0],
        error=solution.error,
        converged=solution.converged,
        area_fraction=float(solution.contact.mean()),
    )
    return solution, timing


@contextlib.contextmanager
def captured_stderr_fd():
    """Redirect file descriptor 2 (where Tamaas's C++ logger writes) to a temp file; yields a getter."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 2)
        text: list[str] = []
        try:
            yield lambda: "".join(text)
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text.append(sink.read().decode(errors="replace"))


def tamaas_solve(tamaas, heights: np.ndarray, pressure: float, tol: float) -> tuple[np.ndarray, float, int | None]:
    """Tamaas PolonskyKeerRey on ``heights``: (pressure field, seconds, iterations or None).

    ``E = E*`` with ``nu = 0`` gives Tamaas the same effective modulus. Tamaas
    logs its iterations to stderr at the info level; the log is captured (so it
    does not flood the table) and the last iteration number is read from it.
    """
    n = heights.shape[0]
    model = tamaas.ModelFactory.createModel(tamaas.model_type.basic_2d, [SYSTEM_SIZE, SYSTEM_SIZE], [n, n])
    model.E = E_STAR
    model.nu = 0.0
    surface = np.ascontiguousarray(heights, dtype=np.float64)
    solver = tamaas.PolonskyKeerRey(model, surface, tol)
    solver.max_iter = TAMAAS_MAX_ITER
    with captured_stderr_fd() as log:
        start = time.perf_counter()
        solver.solve(pressure)
        seconds = time.perf_counter() - start
    iterations = [int(m.group(1)) for m in re.finditer(r"^\s*(\d+)\s+\S+\s+\S+\s*$", log(), flags=re.MULTILINE)]
    traction = np.array(model.traction, dtype=np.float64, copy=True).reshape(n, n)
    return traction, seconds, (iterations[-1] if iterations else None)


def check_tamaas_convention(tamaas, pressure: float, seed: int, threads: int) -> tuple[int, list[str]]:
    """Which sign of the heights Tamaas needs to match roughuq (larger = touches first); report lines.

    Both orientations are solved on a small grid; the one whose contact area
    and pressure field are closer to roughuq's is returned (+1 or -1).
    """
    spectrum = reference_spectrum()
    heights = sample_surface(spectrum, CONVENTION_GRID, np.random.default_rng(seed))
    reference, _ = timed_solve(heights, pressure=pressure, tol=1e-10, threads=threads, repeats=1)
    area = float(reference.contact.mean())
    lines = [f"Tamaas convention check on {CONVENTION_GRID}^2: roughuq area {100 * area:.3f}%"]
    best_sign, best_difference = 1, np.inf
    for sign in (1, -1):
        traction, _, _ = tamaas_solve(tamaas, sign * heights, pressure, TAMAAS_TOL_COARSE)
        difference = relative_l2(traction, reference.pressure)
        lines.append(
            f"  heights x {sign:+d}: area {100 * float((traction > 0).mean()):.3f}%, "
            f"mean pressure {traction.mean() / pressure:.6f} x p_mean, rel. L2 vs roughuq {difference:.2e}"
        )
        if difference < best_difference:
            best_sign, best_difference = sign, difference
    lines.append(f"  -> Tamaas gets heights x {best_sign:+d}")
    return best_sign, lines


def relative_l2(field: np.ndarray, reference: np.ndarray) -> float:
    """``||field - reference|| / ||reference||`` (Frobenius norms)."""
    return float(np.linalg.norm(field - reference) / np.linalg.norm(reference))


def percent_less(new: float, old: float) -> float:
    """Reduction from ``old`` to ``new`` in percent of ``old``."""
    return 100.0 * (old - new) / old if old else float("nan")


def format_table(headers: list[str], rows: list[list[str]]) -> str:
    """A plain right-aligned text table."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in rows]
    return "\n".join(lines)


def run_grid(
    n: int, args: argparse.Namespace, pressure: float, tamaas, tamaas_sign: int
) -> tuple[GridRow, WarmRow, PeerRow | None]:
    """All measurements of one grid."""
    spectrum = reference_spectrum()
    floor_before = fft_floor(n, args.threads)
    # Measured plans, as a study uses them (rough_uq.study.fft_wisdom); planning outside the timings.
    # The surfaces are drawn with them too, so that sample_coupled (below) draws the same bits.
    wisdom = measure_plans([n, n // 2], threads=args.threads)
    heights = sample_surface(spectrum, n, np.random.default_rng(args.seed))
    fft_pair = time_fft_pair(n, args.threads)
    single_pair = time_fft_pair(n, args.threads, single=True, in_place=True)
    plain_single_pair = time_fft_pair(n, args.threads, single=True)
    warn_estimated_plans(n, args.threads)
    cold, cold_timing = timed_solve(
        heights, pressure=pressure, tol=args.tol, threads=args.threads, repeats=args.repeats
    )
    peak_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    per_iteration = cold_timing.seconds / max(cold_timing.n_iter, 1)
    # The floor again, on the other side of the solve: the machine's speed drifts within minutes.
    floor_after = fft_floor(n, args.threads)
    floor = {name: min(seconds, floor_after[name]) for name, seconds in floor_before.items()}
    floor_name = min(floor, key=floor.get)
    if n <= args.plain_max:
        _, plain_timing = timed_solve(
            heights, pressure=pressure, tol=args.tol, threads=args.threads, repeats=args.repeats, precondition=False
        )
    else:  # plain Polonsky-Keer would take some 1000 iterations here
        plain_timing = SolveTiming(n=n, tol=args.tol, n_iter=0, seconds=math.nan, first_seconds=math.nan,
                                   error=math.nan, converged=False, area_fraction=math.nan)
    # FFTW_ESTIMATE plans for comparison: what a process without wisdom uses (use_wisdom(None) forgets it).
    use_wisdom(None)
    time_fft_pair(n, args.threads)
    time_fft_pair(n, args.threads, single=True)
    time_fft_pair(n, args.threads, single=True, in_place=True)
    _, estimate_timing = timed_solve(heights, pressure=pressure, tol=args.tol, threads=args.threads, repeats=1)
    use_wisdom(wisdom)
    grid_row = GridRow(
        n=n,
        n_iter=cold_timing.n_iter,
        seconds_per_solve=cold_timing.seconds,
        seconds_per_iteration=per_iteration,
        fft_pair_seconds=fft_pair,
        iteration_over_fft=per_iteration / fft_pair,
        single_pair_seconds=single_pair,
        iteration_over_transforms=per_iteration / (2.5 * single_pair),
        solve_over_fft=cold_timing.seconds / fft_pair,
        area_fraction=cold_timing.area_fraction,
        error=cold_timing.error,
        converged=cold_timing.converged,
        plain_iter=plain_timing.n_iter,
        plain_seconds_per_solve=plain_timing.seconds,
        plain_iteration_over_fft=plain_timing.seconds / max(plain_timing.n_iter, 1) / fft_pair,
        plain_iteration_over_transforms=plain_timing.seconds
        / max(plain_timing.n_iter, 1)
        / (0.5 * plain_single_pair + fft_pair),
        plain_solve_over_fft=plain_timing.seconds / fft_pair,
        plain_converged=plain_timing.converged,
        floor=floor,
        floor_before=floor_before,
        floor_after=floor_after,
        floor_name=floor_name,
        floor_seconds=floor[floor_name],
        iteration_over_floor=per_iteration / floor[floor_name],
        first_iteration_over_floor=cold_timing.first_seconds / max(cold_timing.n_iter, 1) / floor[floor_name],
        estimate_iter=estimate_timing.n_iter,
        estimate_seconds_per_solve=estimate_timing.seconds,
        peak_rss_mib=peak_rss_mib,
    )

    fine, coarse = sample_coupled(spectrum, n, np.random.default_rng(args.seed))
    if not np.array_equal(fine, heights):
        raise RuntimeError(f"sample_coupled's fine surface differs from sample_surface's on grid {n}")
    time_fft_pair(n // 2, args.threads)  # plan for the coarse grid, outside the timings
    get_fft(n // 2, threads=args.threads, single=True)  # and its single-precision plan
    coarse_solution, coarse_timing = timed_solve(
        coarse, pressure=pressure, tol=args.tol, threads=args.threads, repeats=args.repeats
    )
    _, warm_timing = timed_solve(
        fine,
        pressure=pressure,
        tol=args.tol,
        threads=args.threads,
        repeats=args.repeats,
        initial_pressure=coarse_solution.pressure,
    )
    warm_row = WarmRow(
        n=n,
        cold_iter=cold_timing.n_iter,
        cold_seconds=cold_timing.seconds,
        coarse_iter=coarse_timing.n_iter,
        coarse_seconds=coarse_timing.seconds,
        warm_iter=warm_timing.n_iter,
        warm_seconds=warm_timing.seconds,
        iteration_reduction_percent=percent_less(warm_timing.n_iter, cold_timing.n_iter),
        time_reduction_percent=percent_less(warm_timing.seconds, cold_timing.seconds),
        time_reduction_with_coarse_percent=percent_less(
            warm_timing.seconds + coarse_timing.seconds, cold_timing.seconds
        ),
    )

    if tamaas is None or n > args.tamaas_max:
        return grid_row, warm_row, None
    tight, tight_timing = timed_solve(
        heights, pressure=pressure, tol=args.tight_tol, threads=args.threads, repeats=args.repeats
    )
    tamaas_tol = TAMAAS_TOL_FINE if n >= TAMAAS_FINE_GRID else TAMAAS_TOL_COARSE
    traction, tamaas_seconds, tamaas_iter = tamaas_solve(tamaas, tamaas_sign * heights, pressure, tamaas_tol)
    peer_row = PeerRow(
        n=n,
        tamaas_tol=tamaas_tol,
        tamaas_iter=tamaas_iter,
        tamaas_seconds=tamaas_seconds,
        tamaas_area_fraction=float((traction > 0).mean()),
        tamaas_mean_pressure=float(traction.mean()),
        roughuq_iter=cold_timing.n_iter,
        roughuq_seconds=cold_timing.seconds,
        roughuq_area_fraction=cold_timing.area_fraction,
        roughuq_rel_l2=relative_l2(cold.pressure, traction),
        tight_tol=args.tight_tol,
        tight_iter=tight_timing.n_iter,
        tight_seconds=tight_timing.seconds,
        tight_area_fraction=tight_timing.area_fraction,
        tight_rel_l2=relative_l2(tight.pressure, traction),
        time_ratio=tamaas_seconds / cold_timing.seconds,
        time_ratio_tight=tamaas_seconds / tight_timing.seconds,
    )
    return grid_row, warm_row, peer_row


def render(grid_rows: list[GridRow], warm_rows: list[WarmRow], peer_rows: list[PeerRow], args) -> str:
    """The three result tables as text."""
    parts = [
        f"Solver (tol {args.tol:g}, {args.threads} thread(s), median of {args.repeats} solve(s))",
        format_table(
            ["n", "solver", "iters", "s/solve", "s/iter", "FFT pair s", "iter/FFT", "iter/transf", "solve/FFT",
             "area %", "error", "conv"],
            [
                row
                for r in grid_rows
                for row in (
                    [
                        str(r.n),
                        "precond.",
                        str(r.n_iter),
                        f"{r.seconds_per_solve:.3f}",
                        f"{r.seconds_per_iteration:.3e}",
                        f"{r.fft_pair_seconds:.3e}",
                        f"{r.iteration_over_fft:.2f}",
                        f"{r.iteration_over_transforms:.2f}",
                        f"{r.solve_over_fft:.0f}",
                        f"{100 * r.area_fraction:.3f}",
                        f"{r.error:.1e}",
                        "yes" if r.converged else "NO",
                    ],
                    [
                        str(r.n),
                        "plain PK",
                        str(r.plain_iter),
                        f"{r.plain_seconds_per_solve:.3f}",
                        f"{r.plain_seconds_per_solve / max(r.plain_iter, 1):.3e}",
                        f"{r.fft_pair_seconds:.3e}",
                        f"{r.plain_iteration_over_fft:.2f}",
                        f"{r.plain_iteration_over_transforms:.2f}",
                        f"{r.plain_solve_over_fft:.0f}",
                        "-",
                        "-",
                        "yes" if r.plain_converged else "NO",
                    ],
                )
            ],
        ),
        "",
        "Warm start from the coupled coarse solution (grid n/2, spectral truncation)",
        format_table(
            ["n", "cold it", "cold s", "n/2 it", "n/2 s", "warm it", "warm s", "it -%", "time -%", "time+n/2 -%"],
            [
                [
                    str(r.n),
                    str(r.cold_iter),
                    f"{r.cold_seconds:.3f}",
                    str(r.coarse_iter),
                    f"{r.coarse_seconds:.3f}",
                    str(r.warm_iter),
                    f"{r.warm_seconds:.3f}",
                    f"{r.iteration_reduction_percent:.1f}",
                    f"{r.time_reduction_percent:.1f}",
                    f"{r.time_reduction_with_coarse_percent:.1f}",
                ]
                for r in warm_rows
            ],
        ),
    ]
    floor_names = list(dict.fromkeys(k for r in grid_rows for k in r.floor))
    parts += [
        "",
        "FFT floor: one double-precision real FFT pair (rfft2 + irfft2), seconds, same grid and threads",
        format_table(
            ["n", *floor_names, "fastest", "solver s/iter", "iter/fastest", "1st solve", "solve est. s",
             "solve meas. s", "peak RSS MiB"],
            [
                [str(r.n), *(f"{r.floor[k]:.3e}" if k in r.floor else "-" for k in floor_names), r.floor_name,
                 f"{r.seconds_per_iteration:.3e}", f"{r.iteration_over_floor:.2f}",
                 f"{r.first_iteration_over_floor:.2f}",
                 f"{r.estimate_seconds_per_solve:.3f} ({r.estimate_iter} it)",
                 f"{r.seconds_per_solve:.3f} ({r.n_iter} it)", f"{r.peak_rss_mib:.0f}"]
                for r in grid_rows
            ],
        ),
        "(each implementation: the faster of its measurements before and after the timed solve, below;"
        " iter/fastest: median over the repeats; 1st solve: the same for the first of them, which also pays a"
        " process's one-off costs, e.g. the first touch of fresh memory; solve est./meas.: the preconditioned solve"
        " with FFTW_ESTIMATE plans and with measured plans, as studies use them; peak RSS: the process's peak so"
        " far, grids in increasing order)",
        *(floor_drift(r) for r in grid_rows),
    ]
    if peer_rows:
        rows = []
        for r in peer_rows:
            iters = "?" if r.tamaas_iter is None else str(r.tamaas_iter)
            rows.append([str(r.n), "tamaas", f"{r.tamaas_tol:g}", iters, f"{r.tamaas_seconds:.3f}",
                         f"{100 * r.tamaas_area_fraction:.3f}", "-", "-"])
            rows.append([str(r.n), "roughuq", f"{args.tol:g}", str(r.roughuq_iter),
                         f"{r.roughuq_seconds:.3f}", f"{100 * r.roughuq_area_fraction:.3f}",
                         f"{r.roughuq_rel_l2:.2e}", f"{r.time_ratio:.2f}"])
            rows.append([str(r.n), "roughuq", f"{r.tight_tol:g}", str(r.tight_iter), f"{r.tight_seconds:.3f}",
                         f"{100 * r.tight_area_fraction:.3f}", f"{r.tight_rel_l2:.2e}", f"{r.time_ratio_tight:.2f}"])
        parts += [
            "",
            "Peer: Tamaas PolonskyKeerRey (E = E*, nu = 0), same heights and mean pressure",
            format_table(["n", "solver", "tol", "iters", "seconds", "area %", "rel L2 vs tamaas", "tamaas/this"], rows),
            "(tol is each solver's own error measure; Tamaas runs serially whatever --threads says)",
        ]
    parts += ["", "Targets (issue 14)", *targets(grid_rows, peer_rows)]
    return "\n".join(parts)


def floor_drift(row: GridRow) -> str:
    """The fastest pair of each of the two floor measurements of a grid, as one line."""
    before = min(row.floor_before, key=row.floor_before.get)
    after = min(row.floor_after, key=row.floor_after.get)
    return (
        f"  {row.n}^2: fastest before the solve {row.floor_before[before]:.3e} s ({before}), "
        f"after it {row.floor_after[after]:.3e} s ({after})"
    )


def targets(grid_rows: list[GridRow], peer_rows: list[PeerRow]) -> list[str]:
    """The issue's targets against this run's ratios."""
    lines = []
    for r in grid_rows:
        if r.n in (1024, 2048):
            verdict = "met" if r.iteration_over_floor <= 2.0 else "NOT met"
            lines.append(
                f"  s/iteration <= 2.0 fastest FFT pairs at {r.n}^2: {r.iteration_over_floor:.2f} ({verdict}; "
                f"the first solve alone {r.first_iteration_over_floor:.2f})"
            )
    for r in peer_rows:
        if r.n in (1024, 2048):
            verdict = "met" if r.time_ratio >= 20 else "NOT met"
            lines.append(f"  whole solve >= 20x faster than Tamaas at {r.n}^2: {r.time_ratio:.1f}x ({verdict})")
    return lines or ["  (none of the target grids 1024, 2048 in this run)"]


def parse_args(argv: list[str]) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="256,512,1024", help="comma-separated grid sizes (2048 is slow)")
    parser.add_argument("--threads", type=int, default=1, help="FFTW and numba threads of roughuq")
    parser.add_argument("--tol", type=float, default=1e-8, help="roughuq tolerance of the timed solves")
    parser.add_argument("--tight-tol", type=float, default=1e-10, help="roughuq tolerance for the field comparison")
    parser.add_argument("--seed", type=int, default=1, help="seed of numpy.random.default_rng for the surfaces")
    parser.add_argument("--repeats", type=int, default=1, help="timed roughuq solves per measurement (median)")
    parser.add_argument("--no-tamaas", action="store_true", help="skip the peer comparison")
    parser.add_argument("--tamaas-max", type=int, default=2048, help="largest grid solved with Tamaas too")
    parser.add_argument("--plain-max", type=int, default=2048, help="largest grid solved with plain PK too")
    parser.add_argument("--json", metavar="FILE", help="also write the numbers to FILE")
    args = parser.parse_args(argv)
    try:
        args.sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    except ValueError:
        parser.error(f"--sizes must be comma-separated integers, got {args.sizes!r}")
    if not args.sizes or any(n < 8 or n % 4 for n in args.sizes):
        parser.error("--sizes must be multiples of 4, >= 8 (the warm start solves on n/2)")
    if args.threads < 1 or args.repeats < 1:
        parser.error("--threads and --repeats must be >= 1")
    return args


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark and print (and optionally save) the tables."""
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    info = environment([sys.argv[0]] + argv)
    for key, value in info.items():
        print(f"{key + ':':<17}{value}")
    spectrum = reference_spectrum()
    pressure = mean_pressure(spectrum)
    print(f"{'surface:':<17}SPEC 6, L={SYSTEM_SIZE:g}, k_l=k_r={spectrum.k_r:g}, k_s={spectrum.k_s:g}, H={HURST:g}, "
          f"rms height {RMS_HEIGHT:g}, rms slope {spectrum.rms_slope:.4f}, seed {args.seed}")
    print(f"{'load:':<17}p_mean = {RELATIVE_LOAD:g} E* sqrt(m2) = {pressure:.6f} E*")
    print(flush=True)

    warm_up(args.threads)
    tamaas = None if args.no_tamaas else import_tamaas()
    tamaas_sign = 1
    convention_lines: list[str] = []
    if tamaas is not None:
        tamaas.set_log_level(tamaas.LogLevel.info)  # the iteration log is captured and parsed
        tamaas_sign, convention_lines = check_tamaas_convention(tamaas, pressure, args.seed, args.threads)
        print("\n".join(convention_lines) + "\n", flush=True)

    grid_rows, warm_rows, peer_rows = [], [], []
    for n in args.sizes:
        grid_row, warm_row, peer_row = run_grid(n, args, pressure, tamaas, tamaas_sign)
        grid_rows.append(grid_row)
        warm_rows.append(warm_row)
        if peer_row is not None:
            peer_rows.append(peer_row)
        print(f"[grid {n} done]", file=sys.stderr, flush=True)

    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(
                {
                    "environment": info,
                    "options": {k: v for k, v in vars(args).items() if k != "json"},
                    "mean_pressure": pressure,
                    "tamaas_convention": convention_lines,
                    "solver": [asdict(r) for r in grid_rows],
                    "warm_start": [asdict(r) for r in warm_rows],
                    "peer": [asdict(r) for r in peer_rows],
                },
                handle,
                indent=2,
            )
    print(render(grid_rows, warm_rows, peer_rows, args))


if __name__ == "__main__":
    main()

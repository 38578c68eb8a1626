"""Real two-dimensional FFTs behind one small interface, with cached pyFFTW plans.

Conventions (used by every module of roughuq)
---------------------------------------------
* Arrays are indexed ``[i, j]`` with ``x = i * h``, ``y = j * h``, ``h = L / n``.
* :meth:`RealFFT.forward` is the unnormalised real-to-complex DFT,
  ``X[k1, k2] = sum_{i,j} x[i, j] exp(-2 pi i (k1 i + k2 j) / n)``, of shape
  ``(n, n // 2 + 1)`` (numpy's ``rfft2`` layout).
* :meth:`RealFFT.inverse` is its exact inverse (it carries the ``1 / n**2``
  factor), so ``inverse(forward(x)) == x`` up to rounding, as with numpy's
  ``irfft2(rfft2(x))``.
* Wave numbers are integers counted in periods per box (``k = L / lambda``); the
  angular wave number is ``q = 2 pi k / L``. :func:`rfft_wavenumbers` gives them.

Plans are built once per shape, thread count, precision and output layout in
each process and reused (:func:`get_fft`). Nothing happens at import time and
this module reads and writes no file.

Planning and reproducibility
----------------------------
FFTW's algorithm choice changes the rounding of a transform, so a sample is
reproducible to the bit only where every process uses the same plan. Two
ways are offered:

* ``FFTW_ESTIMATE`` (the default of a fresh process): the plan follows from
  the shape alone.
* Measured plans from shared wisdom: one process measures the plans it needs
  (:func:`measure_plans`, ``FFTW_MEASURE``) and exports the wisdom
  (:func:`export_wisdom`); every process that calls :func:`use_wisdom` with
  those bytes then plans from the wisdom only (``FFTW_WISDOM_ONLY``), and so
  uses the very same plans. A plan missing from the wisdom is estimated,
  never measured, so that it too is the same in every such process.
  The study pipeline measures the grids of each level before it computes
  samples there, keeps the wisdom on disk (user cache directory) and ships it
  with the contact model to every worker. Measured plans were 1.1-1.5x faster
  than estimated ones here (``scripts/bench_solver.py`` prints both).
  The in-place single-precision plans of the preconditioned solver (every
  transform of an iteration but the occasional exact displacement) are planned with
  ``FFTW_PATIENT`` on grids up to :data:`PATIENT_MAX_GRID`, where it pays:
  a pair took 0.965 / 0.91 / 0.93 of the time of the ``FFTW_MEASURE`` plan at
  256^2 / 512^2 / 1024^2 (one core), for 4 / 7 / 16 s of planning, once per
  machine; at 2048^2 it gained 1-6 % for 54 s, so larger grids are measured.
  FFTW uses wisdom of a more patient plan for a less patient request, so the
  processes that plan from the wisdom get the patient plans too. A search
  that runs out of time (FFTW's limit: 30 s patient, 5 s measured) leaves no
  wisdom; such a plan is measured instead (:func:`measure_plans`), so that
  no solve runs with estimated transforms: with two threads the patient
  search of 1024^2 took longer than its limit, and until 2026-11-28 every
  such solve ran estimated, its in-place single-precision pair 2.5 ms
  against 1.7 ms measured.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterable

import numpy as np


def _import_pyfftw():
    """``import pyfftw`` without the optional imports of its ``interfaces`` subpackage.

    ``pyfftw/__init__.py`` imports ``pyfftw.interfaces``, which imports
    ``scipy.fftpack`` and ``dask.array`` (if installed) to offer drop-in
    replacements for them. roughuq uses neither replacement, and the two
    imports took 0.4-0.8 s of the 3-4 s that every ``roughuq`` command spends
    starting (most of its time in shell loops over shards). Modules not yet
    imported are marked absent while pyFFTW imports (its ``interfaces`` then
    skip them, as when they are not installed) and unmarked at once, so that
    the caller can import them later as usual. A process that imported them
    before gets pyFFTW's full interfaces. First :func:`prefer_sleeping_threads`.
    """
    prefer_sleeping_threads()
    hidden = [name for name in ("dask", "scipy.fftpack") if name not in sys.modules]
    for name in hidden:
        sys.modules[name] = None  # ``import name`` raises ImportError
    try:
        import pyfftw
    finally:
        for name in hidden:
            if sys.modules.get(name, False) is None:
                del sys.modules[name]
    return pyfftw


def prefer_sleeping_threads() -> None:
    """Let idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE``) unless the environment sets a policy.

    pyFFTW's threaded transforms (the OpenMP runtime its wheels bundle reads the setting when it is loaded,
    with pyFFTW) and numba's parallel passes (another runtime, loaded at the first parallel kernel) otherwise
    busy-wait against each other: a 512^2 solve with ``threads=2`` took 4.1 s instead of 0.17 s from Python on
    two cores (2026-11-29); the CLI and the pool's workers set it before, the Python API did not. Called when
    pyFFTW is first used (a solve makes its transforms before its first parallel pass), never at import.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class _LazyPyFFTW:
    """pyFFTW, imported (:func:`_import_pyfftw`) at the first use of one of its names, not with this module."""

    _module = None

    def __getattr__(self, name: str):
        if _LazyPyFFTW._module is None:
            _LazyPyFFTW._module = _import_pyfftw()
        return getattr(_LazyPyFFTW._module, name)


pyfftw = _LazyPyFFTW()

__all__ = [
    "RealFFT",
    "get_fft",
    "rfft_wavenumbers",
    "clear_plan_cache",
    "measure_plans",
    "use_wisdom",
    "export_wisdom",
]

#: Upper bound on planning time per plan, in seconds (measured planning only).
_PLANNING_TIMELIMIT = 5.0

#: The same for ``FFTW_PATIENT`` plans: 5 s stops the search at 1024^2 before
#: it finds the faster plan (it needs about 8 s per plan here).
_PATIENT_TIMELIMIT = 30.0

#: The largest grid whose in-place single-precision plans (the preconditioned
#: solver's) :func:`measure_plans` plans with ``FFTW_PATIENT`` (module docstring).
PATIENT_MAX_GRID = 1024


class _Planner:
    """The process's planning mode (module docstring): flags and the wisdom it came from."""

    flags: tuple[str, ...] = ("FFTW_ESTIMATE",)
    wisdom: tuple[bytes, ...] | None = None


_PLANNER = _Planner()


class RealFFT:
    """A pair of FFTW plans (forward r2c, inverse c2r) on aligned work buffers.

    The forward plan reads :attr:`real` (shape ``shape``, float64) and writes
    :attr:`spectral` (shape ``(shape[0], shape[1] // 2 + 1)``, complex128);
    the inverse reads :attr:`spectral` and writes :attr:`output`, which is
    :attr:`real` itself unless ``separate_output``: fill one, call the
    transform, read the other. The buffers belong to the plan: copy results
    that must outlive the next transform. :attr:`padded` is a C-contiguous
    array whose first ``shape[1]`` columns are :attr:`real` (:attr:`real`
    itself unless ``in_place``), for compiled loops that index ``[i, j]``
    with ``j < shape[1]``: they vectorise over contiguous rows only.

    Parameters
    ----------
    shape : tuple of int
        Real-space grid shape ``(n0, n1)``; ``n1`` must be even.
    threads : int
        Number of FFTW threads.
    single : bool
        Single precision (float32 / complex64 buffers), for uses that tolerate
        a relative rounding error of about 1e-7 (the solver's preconditioner).
        With FFTW_ESTIMATE plans a pair takes 0.6 of the time of a
        double-precision pair at 1024^2, 0.7-0.8 at 256^2 and 512^2, 0.9 at
        2048^2 (``scripts/bench_solver.py``).
    separate_output : bool
        Give the inverse its own output buffer, so that :attr:`real` keeps its
        content across a round trip (the solver stores the pressure there and
        saves a copy per iteration).
    in_place : bool
        One buffer for both sides (FFTW's in-place layout): :attr:`padded` has
        ``shape[1] + 2`` columns, :attr:`real` is its first ``shape[1]``
        columns and :attr:`spectral` the same memory read as complex numbers,
        so the forward transform destroys :attr:`real`. Half the memory of
        separate buffers, and faster where the transforms are limited by
        memory traffic (the solver's preconditioned iteration,
        :mod:`rough_uq.physics.solver`). Not with ``separate_output``.
    flags : tuple of str, optional
        FFTW planner flags; by default the process's planning mode (module
        docstring). :attr:`flags` holds the flags the plans were made with.
    unlimited_planning : bool, optional
        Plan without FFTW's time limit (by default 5 s, and 30 s for
        ``FFTW_PATIENT``), for :func:`measure_plans` where a search ran out
        of time.
    """

    def __init__(
        self,
        shape: tuple[int, int],
        *,
        threads: int = 1,
        single: bool = False,
        separate_output: bool = False,
        in_place: bool = False,
        flags: tuple[str, ...] | None = None,
        unlimited_planning: bool = False,
    ) -> None:
        n0, n1 = (int(s) for s in shape)
        if n0 < 2 or n1 < 2 or n1 % 2:
            raise ValueError(f"FFT grid shape must be at least 2 x 2 with an even last axis, got {shape}")
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        if in_place and separate_output:
            raise ValueError("an in-place plan has no separate output")
        self.shape = (n0, n1)
        self.threads = int(threads)
        self.single = bool(single)
        real_type, complex_type = ("float32", "complex64") if self.single else ("float64", "complex128")
        self.in_place = bool(in_place)
        if self.in_place:
            # Rows of n1 + 2 reals, read as n1 // 2 + 1 complex numbers.
            self.padded = pyfftw.empty_aligned((n0, n1 + 2), dtype=real_type)
            self.real = self.padded[:, :n1]
            self.spectral = self.padded.view(complex_type)
        else:
            self.real = pyfftw.empty_aligned(self.shape, dtype=real_type)
            self.padded = self.real
            self.spectral = pyfftw.empty_aligned((n0, n1 // 2 + 1), dtype=complex_type)
        self.output = pyfftw.empty_aligned(self.shape, dtype=real_type) if separate_output else self.real
        flags = _PLANNER.flags if flags is None else tuple(flags)
        try:
            self._plan(flags, unlimited_planning)
        except RuntimeError:
            if "FFTW_WISDOM_ONLY" not in flags:
                raise
            # Not in the wisdom: estimate, never measure, so that every process
            # holding the same wisdom still makes the same plan.
            flags = ("FFTW_ESTIMATE",)
            self._plan(flags)
        self.flags = flags
        # Planning may scribble on the buffers.
        self.real[...] = 0.0
        self.output[...] = 0.0
        self.spectral[...] = 0.0

    def _plan(self, flags: tuple[str, ...], unlimited: bool = False) -> None:
        timelimit = _PATIENT_TIMELIMIT if "FFTW_PATIENT" in flags else _PLANNING_TIMELIMIT
        if unlimited:
            timelimit = None
        self._forward = pyfftw.FFTW(
            self.real,
            self.spectral,
            axes=(0, 1),
            direction="FFTW_FORWARD",
            threads=self.threads,
            flags=flags,
            planning_timelimit=timelimit,
        )
        self._inverse = pyfftw.FFTW(
            self.spectral,
            self.output,
            axes=(0, 1),
            direction="FFTW_BACKWARD",
            threads=self.threads,
            flags=flags + ("FFTW_DESTROY_INPUT",),
            planning_timelimit=timelimit,
        )

    def forward(self, x: np.ndarray | None = None) -> np.ndarray:
        """Transform :attr:`real` (after copying ``x`` into it, if given) into :attr:`spectral`."""
        if x is not None:
            np.copyto(self.real, x)
        self._forward.execute()
        return self.spectral

    def inverse(self, x_hat: np.ndarray | None = None, *, normalise: bool = True) -> np.ndarray:
        """Transform :attr:`spectral` (after copying ``x_hat`` into it) into :attr:`output`.

        The input buffer is destroyed (FFTW's c2r transforms overwrite it).
        ``normalise=False`` leaves out the factor ``1 / n**2`` (the result is
        ``n**2`` times the inverse), for callers that fold it into a spectral
        multiply: pyFFTW applies it in a separate pass over the output.
        """
        if x_hat is not None:
            np.copyto(self.spectral, x_hat)
        if normalise:
            self._inverse(normalise_idft=True)
        else:
            self._inverse.execute()
        return self.output


_PLANS: dict[tuple[tuple[int, int], int, bool, bool, bool, int], RealFFT] = {}
_PLANS_LOCK = threading.RLock()  # re-entrant: use_wisdom clears the cache while holding it


def get_fft(
    shape: tuple[int, int] | int,
    *,
    threads: int = 1,
    single: bool = False,
    separate_output: bool = False,
    in_place: bool = False,
) -> RealFFT:
    """The cached :class:`RealFFT` for ``shape``, ``threads``, precision and buffer layout in this process and thread.

    Plans own their work buffers, so each Python thread gets its own plans.
    """
    if isinstance(shape, (int, np.integer)):
        shape = (int(shape), int(shape))
    key = (
        tuple(int(s) for s in shape),
        int(threads),
        bool(single),
        bool(separate_output),
        bool(in_place),
        threading.get_ident(),
    )
    with _PLANS_LOCK:
        plan = _PLANS.get(key)
        if plan is None:
            plan = RealFFT(key[0], threads=threads, single=single, separate_output=separate_output, in_place=in_place)
            _PLANS[key] = plan
    return plan


def clear_plan_cache() -> None:
    """Forget all cached plans (frees their buffers)."""
    with _PLANS_LOCK:
        _PLANS.clear()


#: The plan variants roughuq uses per grid: the surface synthesis and
#: projection (double, one thread), the solver's ``K`` (double, separate
#: output), the single-precision transforms of plain Polonsky-Keer and those
#: of the preconditioned iteration (in-place buffer), all three with the
#: solver's threads. Keys: (threads, single, separate_output, in_place).
def _variants(threads: int) -> tuple[tuple[int, bool, bool, bool], ...]:
    return (
        (1, False, False, False),
        (threads, False, True, False),
        (threads, True, False, False),
        (threads, True, False, True),
    )


def _plan_variant(
    n: int, variant: tuple[int, bool, bool, bool], flags: tuple[str, ...], *, unlimited_planning: bool = False
) -> RealFFT:
    plan_threads, single, separate_output, in_place = variant
    return RealFFT(
        (n, n), threads=plan_threads, single=single, separate_output=separate_output, in_place=in_place, flags=flags,
        unlimited_planning=unlimited_planning,
    )


def _default_effort(n: int, variant: tuple[int, bool, bool, bool]) -> str:
    in_place = variant[3]
    return "FFTW_PATIENT" if in_place and n <= PATIENT_MAX_GRID else "FFTW_MEASURE"


def _in_wisdom(n: int, variant: tuple[int, bool, bool, bool], effort: str) -> bool:
    # Planning from the wisdom only succeeds where it holds a plan of at least
    # this rigour (RealFFT falls back to an estimated plan otherwise).
    flags = (effort, "FFTW_WISDOM_ONLY")
    return _plan_variant(n, variant, flags).flags == flags


def _measure_variant(n: int, variant: tuple[int, bool, bool, bool], effort: str) -> None:
    """Plan ``variant`` at ``effort`` so that the wisdom holds it; less patiently where the search runs out of time.

    A search that reaches its time limit leaves FFTW's wisdom without a plan of
    that rigour, so that planning from the wisdom only would estimate: the
    in-place single-precision plan of 1024^2 with two threads took more than
    the 30 s of ``FFTW_PATIENT`` here, and solves ran with estimated
    transforms (a pair 2.5 ms instead of 1.7 ms measured). Such a plan is
    measured instead (``FFTW_MEASURE``, within its own time limit), and where
    even that search runs out of time, measured without a limit: planning
    happens once per machine and grid, and every later process plans from the
    wisdom. (Should that too leave no wisdom, every process estimates the plan:
    slower, but the same plan everywhere.)
    """
    attempts = [(effort, False), ("FFTW_MEASURE", False), ("FFTW_MEASURE", True)]
    for attempt_effort, unlimited in attempts[1:] if effort == "FFTW_MEASURE" else attempts:
        before = tuple(pyfftw.export_wisdom())
        _plan_variant(n, variant, (attempt_effort,), unlimited_planning=unlimited)
        if _in_wisdom(n, variant, attempt_effort):
            return
        # The search that ran out of time left solutions in FFTW's planner that are
        # not wisdom but serve every later search of the problem at once: forget them.
        with _PLANS_LOCK:
            pyfftw.forget_wisdom()
            pyfftw.import_wisdom(before)


def measure_plans(
    grids: Iterable[int],
    *,
    threads: int = 1,
    wisdom: tuple[bytes, ...] | None = None,
    effort: str | None = None,
    before_measuring: Callable[[list[int]], None] | None = None,
) -> tuple[bytes, ...]:
    """Measure the plans roughuq needs on ``grids`` and return the accumulated wisdom.

    Wisdom from an earlier call (e.g. read from disk) is imported first, so
    plans it already holds are not measured again. Afterwards this process
    plans from the returned wisdom only (:func:`use_wisdom`).

    Parameters
    ----------
    grids : iterable of int
        Grid sizes ``n`` (plans for ``n x n``).
    threads : int
        The solver's FFTW threads.
    wisdom : tuple of bytes, optional
        Wisdom to start from (:func:`export_wisdom` of this or another process).
    effort : {"FFTW_MEASURE", "FFTW_PATIENT"}, optional
        Planner effort for plans not in the wisdom yet (a plan the wisdom
        holds at ``FFTW_MEASURE`` rigour or more counts as in it). By default
        ``FFTW_MEASURE``, and ``FFTW_PATIENT`` for the preconditioned solver's
        in-place single-precision plans on grids up to :data:`PATIENT_MAX_GRID`
        (module docstring).
    before_measuring : callable, optional
        Called with the grids whose plans the wisdom lacks, before they are
        measured (not called when it holds them all): measuring takes seconds
        per grid, up to about 20 s at 1024^2.

    Returns
    -------
    tuple of bytes
        The wisdom after planning (:func:`pyfftw.export_wisdom`).
    """
    if effort not in (None, "FFTW_MEASURE", "FFTW_PATIENT"):
        raise ValueError(f"effort must be FFTW_MEASURE, FFTW_PATIENT or None (the default policy), got {effort!r}")
    if wisdom is not None:
        pyfftw.import_wisdom(wisdom)
    plans = [
        (n, variant, effort or _default_effort(n, variant))
        for n in sorted({int(n) for n in grids})
        for variant in _variants(int(threads))
    ]
    # A plan counts as known once the wisdom serves the solver's request (measured):
    # a patient search that ran out of time is not searched again in every run.
    missing = [(n, variant, plan_effort) for n, variant, plan_effort in plans
               if not _in_wisdom(n, variant, "FFTW_MEASURE")]
    if missing and before_measuring is not None:
        before_measuring(sorted({n for n, _, _ in missing}))
    for n, variant, plan_effort in missing:
        _measure_variant(n, variant, plan_effort)
    measured = tuple(pyfftw.export_wisdom())
    use_wisdom(measured)
    return measured


def use_wisdom(wisdom: tuple[bytes, ...] | None) -> None:
    """Plan from ``wisdom`` only from now on in this process (``None``: back to ``FFTW_ESTIMATE``).

    Calling it again with the same wisdom does nothing; a change forgets the
    cached plans, so that no plan of the old mode is reused. ``None`` also
    forgets FFTW's wisdom (measured here or imported before): FFTW serves an
    ``FFTW_ESTIMATE`` request from any wisdom it holds for the same problem,
    and the plans would then differ from those of a fresh process. FFTW's
    wisdom changes under the lock of :func:`get_fft`, so never while another
    thread of the process plans there.
    """
    wisdom = None if wisdom is None else tuple(bytes(part) for part in wisdom)
    with _PLANS_LOCK:
        if wisdom is None:
            pyfftw.forget_wisdom()
        if wisdom == _PLANNER.wisdom:
            return
        if wisdom is not None:
            pyfftw.forget_wisdom()
            pyfftw.import_wisdom(wisdom)
        _PLANNER.wisdom = wisdom
        _PLANNER.flags = ("FFTW_ESTIMATE",) if wisdom is None else ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
        clear_plan_cache()


def export_wisdom() -> tuple[bytes, ...]:
    """FFTW's accumulated wisdom in this process (:func:`pyfftw.export_wisdom`)."""
    return tuple(pyfftw.export_wisdom())


def rfft_wavenumbers(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer wave numbers of the ``(n, n // 2 + 1)`` rfft layout, broadcastable.

    Returns
    -------
    k0 : ndarray, shape (n, 1)
        Wave numbers along axis 0, in ``[-n/2, n/2)`` (periods per box).
    k1 : ndarray, shape (1, n // 2 + 1)
        Wave numbers along axis 1, in ``[0, n/2]``.
    """
    k0 = np.fft.fftfreq(n, d=1.0 / n).reshape(-1, 1)
    k1 = np.fft.rfftfreq(n, d=1.0 / n).reshape(1, -1)
    return k0, k1

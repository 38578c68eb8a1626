"""Where samples are computed: in this process, in a local process pool, or on a dask cluster.

An executor takes work items ``(stage, level, indices)`` of a
:class:`~rough_uq.problem.sampler.ContactModel` and yields the computed
:class:`~rough_uq.problem.sampler.LevelBatch` es *as they complete*, in any order.
Every sample depends only on the model and its ``(stage, level, index)``
(:mod:`rough_uq.problem.sampler`), so the executor cannot change a number: serial,
pooled and distributed runs store identical samples.

Threads
-------
Each solve uses the config's ``solver.threads`` FFTW/numba threads in every
executor (changing the thread count may change the rounding of FFTs and of
parallel reductions: keep it fixed for bit-identical reruns). The pool defaults to
``cores // threads`` worker processes, so workers do not oversubscribe the
cores; workers are told ``OMP_NUM_THREADS`` (and the BLAS equivalents) =
``threads`` and ``OMP_WAIT_POLICY=PASSIVE`` (FFTW's threads and numba's
OpenMP threads otherwise spin against each other).

A pool has at most :data:`MAX_WORKERS_PER_CORE` workers per available core
(:func:`max_workers`): the solves are CPU-bound, so workers beyond the cores
only share them (a modest surplus is allowed, e.g. to keep cores busy while
some workers write or wait), while a mistyped ``--workers 100000`` would try
to start that many interpreters and exhaust memory and the process table.

Workers are started with ``spawn``: forking a process that has already run
OpenMP threads is unsafe, and a forked child would inherit the study file's
lock. Each worker builds its FFT plans once and reuses them for all its
samples. Workers ignore Ctrl-C; the parent stops them. A worker imports numpy,
numba and roughuq for seconds before it can say so, and Ctrl-C reaches the
whole process group: workers are therefore started with SIGINT blocked
(:func:`_sigint_held_back`), and one that arrives while they import waits
until they ignore it, instead of ending the import with a traceback.

A spawned worker imports the main module of its parent again (as
``__mp_main__``). A script that starts a pool outside ``if __name__ ==
"__main__":`` would thus start one in every worker while it starts;
multiprocessing refuses that with a RuntimeError. A worker that finds itself
starting a pool while it is being spawned ends at once with the exit status
:data:`UNGUARDED_MAIN_STATUS`, and the parent's :class:`ExecutorError` names
the cause (:func:`_broken_pool_message`).
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager

import numpy as np

from rough_uq.errors import ExecutorError, InvalidParameterError, RoughUQError, is_integer
from rough_uq.problem.sampler import ContactModel, LevelBatch, compute_batch, warm_up

__all__ = [
    "Executor",
    "ExecutorError",
    "SerialExecutor",
    "PoolExecutor",
    "DaskExecutor",
    "MAX_WORKERS_PER_CORE",
    "UNGUARDED_MAIN_STATUS",
    "available_cores",
    "default_workers",
    "max_workers",
    "check_workers",
    "check_scheduler_address",
    "make_executor",
    "thread_environment",
    "freeze_garbage",
]

WorkItem = tuple[int, int, np.ndarray]
"""``(stage, level, indices)``."""


#: Most local worker processes per available core (:func:`max_workers`, module docstring).
MAX_WORKERS_PER_CORE = 4

#: Exit status of a worker that was asked to start a pool while it was being spawned (module docstring):
#: its parent's script starts a :class:`PoolExecutor` outside ``if __name__ == "__main__":``.
UNGUARDED_MAIN_STATUS = 86


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity on Linux, else ``os.cpu_count()``), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_workers(threads: int = 1) -> int:
    """Worker processes that fill the cores available to this process without oversubscription."""
    return max(1, available_cores() // max(1, threads))


def max_workers() -> int:
    """Most worker processes a local pool may have: :data:`MAX_WORKERS_PER_CORE` per available core."""
    return MAX_WORKERS_PER_CORE * available_cores()


def _workers_allowed() -> str:
    """What a worker count may be, in the words of an :class:`InvalidParameterError`."""
    cores = available_cores()
    return (f"an integer in 1..{max_workers()} (at most {MAX_WORKERS_PER_CORE} per core; "
            f"this process may use {cores} core{'s' if cores != 1 else ''})")


def check_workers(workers: object, name: str = "workers") -> int:
    """``workers`` as an int, or :class:`InvalidParameterError` naming ``name`` unless in ``1..max_workers()``.

    Booleans and non-integral numbers are refused, never rounded.
    """
    if not (is_integer(workers) and 1 <= workers <= max_workers()):
        raise InvalidParameterError(name, workers, _workers_allowed())
    return int(workers)


def check_threads(threads: object, name: str = "threads") -> int:
    """``threads`` per worker as an int, or :class:`InvalidParameterError` naming ``name`` unless in
    ``1..max_workers()`` (at most 4 per core, as for workers): with ``solver.threads: 10000`` two workers
    died creating their OpenMP threads, and a rerun failed the same way."""
    if not (is_integer(threads) and 1 <= threads <= max_workers()):
        raise InvalidParameterError(name, threads, _workers_allowed())
    return int(threads)


def thread_environment(threads: int) -> dict[str, str]:
    """Environment variables that pin a worker's native thread pools to ``threads``."""
    value = str(int(threads))
    return {
        "OMP_NUM_THREADS": value,
        "OPENBLAS_NUM_THREADS": value,
        "MKL_NUM_THREADS": value,
        "NUMBA_NUM_THREADS": value,
        "OMP_WAIT_POLICY": "PASSIVE",
    }


class Executor(ABC):
    """Computes work items and yields their batches as they complete."""

    #: Number of samples computed at once.
    n_workers: int = 1

    #: Whether the samples are computed on this machine (its memory is what the solves need; not a cluster's).
    runs_here: bool = True

    @abstractmethod
    def run(self, model: ContactModel, items: Sequence[WorkItem]) -> Iterator[LevelBatch]:
        """Compute ``items``; yield one :class:`LevelBatch` per item, in completion order.

        Closing the iterator early (e.g. on Ctrl-C) cancels what has not started (a
        :class:`PoolExecutor` before Python 3.12 leaves that to :meth:`close`: :func:`_abandon`).
        """

    def close(self) -> None:
        """Release workers (idempotent)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class SerialExecutor(Executor):
    """Computes every item in this process, in order (after a warm-up of the kernels, once per process)."""

    def run(self, model: ContactModel, items: Sequence[WorkItem]) -> Iterator[LevelBatch]:
        for stage, level, indices in items:
            yield _compute(model, stage, level, indices)


#: Whether this process (a worker, or the one a SerialExecutor computes in) has run
#: :func:`~rough_uq.problem.sampler.warm_up`.
_is_warm = False
#: Whether this process is a worker of a :class:`PoolExecutor` (ours to tune: :func:`freeze_garbage`).
_is_pool_worker = False


def _init_worker(parent: int) -> None:
    global _is_pool_worker
    _is_pool_worker = True
    # Ctrl-C goes to the whole process group; the parent decides what stops. The
    # parent started this worker with SIGINT blocked (_sigint_held_back): ignoring it
    # discards a Ctrl-C held back during the imports; the mask is then the usual one.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # Die with the parent (Linux), even when it is killed without cleaning up
    # (SIGTERM, SIGKILL); otherwise idle workers would linger forever.
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux
        pass
    # The parent may have died while this worker was still importing, before
    # the death signal was armed.
    if os.getppid() != parent:
        os._exit(1)


def freeze_garbage() -> None:
    """Collect garbage, then exempt every surviving object from later collections (:func:`gc.freeze`).

    Loading numba's kernels leaves some 160 000 objects; the next full
    collection walks them all (60-80 ms here) and fell into the measured cost
    of one sample (a 64^2 sample takes 4 ms). Called once per process, after
    the warm-up and before any sample is timed.
    """
    gc.collect()
    gc.freeze()


def _compute(model: ContactModel, stage: int, level: int, indices: np.ndarray) -> LevelBatch:
    global _is_warm
    if not _is_warm:
        # A worker's first task: load the kernels before the first timed sample.
        warm_up(model)
        if _is_pool_worker:  # not in a dask worker, which may be someone's own process
            freeze_garbage()
        _is_warm = True
    return compute_batch(model, stage=stage, level=level, indices=indices)


def _start_quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker with its stderr on /dev/null.

    The tracker frees the pool's semaphores when this process is killed
    (kill -9), correctly, and then warns about each "leaked" one on the
    user's terminal, after the fact and with nothing left to do. It inherits
    file descriptor 2 when it starts; a tracker already running is kept.
    """
    from multiprocessing import resource_tracker

    try:
        sys.stderr.flush()
    except (AttributeError, ValueError, OSError):
        pass
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        resource_tracker.ensure_running()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


@contextmanager
def _sigint_held_back() -> Iterator[None]:
    """Block SIGINT in this thread while it starts worker processes; a Ctrl-C meanwhile comes after.

    A spawned child inherits the signal mask across fork and exec
    (multiprocessing starts its resource tracker so, for the same reason): a
    worker keeps a Ctrl-C pending from its first instruction, through its
    imports, until :func:`_init_worker` ignores SIGINT, which discards it.
    Python installs its KeyboardInterrupt handler in the worker, but it never runs.

    This process does not ignore SIGINT meanwhile (a Ctrl-C of that moment
    would be lost): this thread only defers it until the mask is restored.
    Another thread of the process may take the signal, and Python would then
    raise KeyboardInterrupt in the main thread at once, possibly between a
    worker's start and its registration in the pool (which would neither stop
    nor join a worker it does not know). On the main thread, Python's
    handler is therefore replaced, for the milliseconds of the spawning, by
    one that records the signal, and a recorded Ctrl-C is raised again once
    the handler is back. Handlers can be changed only on the main thread
    (:func:`signal.signal`); elsewhere only the mask is.
    """
    if not hasattr(signal, "pthread_sigmask"):  # Windows: children inherit no signal state
        yield
        return
    received: list[int] = []
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.getsignal(signal.SIGINT)  # None: installed outside Python, left alone
        if previous is not None:
            signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        # The mask first: pthread_sigmask runs the pending Python handlers before it
        # returns, so a held-back Ctrl-C reaches the recorder, and no KeyboardInterrupt
        # leaves the mask or the handler half restored.
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            if received:
                signal.raise_signal(signal.SIGINT)


def _is_being_spawned() -> bool:
    """Whether this process is a spawned worker still importing its parent's main module.

    ``multiprocessing`` marks the process so while it prepares it, and refuses to
    start a child then (its RuntimeError about the bootstrapping phase).
    """
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def _pool_processes(pool: ProcessPoolExecutor) -> list[multiprocessing.Process]:
    """The worker processes of ``pool`` (none where it does not list them)."""
    # ProcessPoolExecutor keeps its workers in the private _processes.
    return list((getattr(pool, "_processes", None) or {}).values())


def _exit_statuses(processes: Sequence[multiprocessing.Process], timeout: float = 2.0) -> list[int]:
    """Exit statuses of the worker ``processes`` of a broken pool.

    The pool is broken as soon as a worker's end is seen, a moment before its
    status can be read, and it terminates the other workers: each is given
    until ``timeout`` seconds in all to end. The processes are those listed
    when the workers started: a broken pool empties its own list. The pool's
    own thread reaps the workers too, and a join that loses that race returns
    before the status is recorded: the status is polled until it is (with one
    worker, half the runs lost the advice for a script without ``if __name__ ==
    '__main__':`` to one or the other).
    """
    deadline = time.monotonic() + timeout
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        while process.exitcode is None and time.monotonic() < deadline:
            time.sleep(0.01)
    return [process.exitcode for process in processes if process.exitcode is not None]


def _broken_pool_message(statuses: Sequence[int], *, is_starting: bool) -> str:
    """What an :class:`ExecutorError` says about a pool whose worker died, given the workers' exit statuses."""
    if UNGUARDED_MAIN_STATUS in statuses:
        return (
            "a worker process failed while starting: each worker imports the main script again, and this "
            "script starts a PoolExecutor when imported; scripts that start a PoolExecutor need "
            "`if __name__ == '__main__':` around the code that does"
        )
    if is_starting:
        # Other statuses do not tell the cause: the pool terminates the other workers once one has died.
        return ("a worker process failed while starting, before it computed any sample (killed, out of memory, "
                "or an error in the worker, printed above)")
    return (
        "a worker process died while computing samples (killed, or out of memory); a study file keeps the "
        "samples already stored: the same roughuq command run again computes the rest"
    )


#: Whether a future of a process pool may be cancelled while the pool can break. Before Python 3.12 the pool's
#: thread that marks the pending futures failed when a worker dies raised InvalidStateError on a cancelled one
#: (CPython gh-107219): it printed a traceback and died before terminating the other workers and closing the
#: pool's queues. A group SIGTERM (a scheduler's), which ends the workers while the run cancels its futures,
#: printed that traceback about one time in ten.
_CAN_CANCEL_POOL_FUTURES = sys.version_info >= (3, 12)


def _abandon(pending: Iterable[Future]) -> None:
    """Cancel the ``pending`` futures of a run closed early, where that is safe (:data:`_CAN_CANCEL_POOL_FUTURES`).

    Where it is not, they are left to the pool: an aborted run closes it (``shutdown(cancel_futures=True)``
    cancels them in the pool's own thread), and a pool used again first finishes the at most ``2 n_workers``
    items a run keeps in flight.
    """
    if _CAN_CANCEL_POOL_FUTURES:
        for future in pending:
            future.cancel()


class PoolExecutor(Executor):
    """A local pool of ``n_workers`` spawned processes (module docstring).

    Parameters
    ----------
    n_workers : int
        Number of worker processes, 1 to :func:`max_workers` (:data:`MAX_WORKERS_PER_CORE` per core).
    threads : int
        Native threads per worker (the study's ``solver.threads``).
    """

    def __init__(self, n_workers: int, *, threads: int = 1) -> None:
        self.n_workers = check_workers(n_workers, name="n_workers")
        self.threads = check_threads(threads)
        self._pool: ProcessPoolExecutor | None = None
        self._workers: list[multiprocessing.Process] = []

    def _start(self) -> ProcessPoolExecutor:
        if self._pool is None:
            if _is_being_spawned():
                # Our parent's script started a pool at import (module docstring): starting one here
                # would fail with multiprocessing's RuntimeError; end with a status the parent recognises.
                raise SystemExit(UNGUARDED_MAIN_STATUS)
            _start_quiet_resource_tracker()
            self._pool = ProcessPoolExecutor(
                max_workers=self.n_workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker,
                initargs=(os.getpid(),),
            )
            # Start every worker now, in this thread: with the spawn context, submit()
            # starts a process whenever no worker is idle (Python 3.11:
            # _adjust_process_count), and none is idle before its start-up (seconds) is
            # over. Spawned children copy os.environ when they start; set it for them
            # and restore ours right after.
            saved = dict(os.environ)
            os.environ.update(thread_environment(self.threads))
            try:
                with _sigint_held_back():
                    started = [self._pool.submit(int, index) for index in range(self.n_workers)]
                self._workers = _pool_processes(self._pool)
            finally:
                os.environ.clear()
                os.environ.update(saved)
            self._wait_for_start(started)
        return self._pool

    def _wait_for_start(self, started: Sequence[Future]) -> None:
        """Wait until every worker has run a first (trivial) task; an :class:`ExecutorError` if one died first."""
        try:
            for future in started:
                future.result()
        except BrokenProcessPool as exc:
            statuses = _exit_statuses(self._workers)
            self._pool, self._workers = None, []
            raise ExecutorError(_broken_pool_message(statuses, is_starting=True)) from exc

    def run(self, model: ContactModel, items: Sequence[WorkItem]) -> Iterator[LevelBatch]:
        queue = list(items)
        pending: set[Future] = set()
        is_done = False
        try:
            pool = self._start()
            # Keep a bounded number of items in flight so cancelling is cheap.
            while queue or pending:
                while queue and len(pending) < 2 * self.n_workers:
                    stage, level, indices = queue.pop(0)
                    pending.add(pool.submit(_compute, model, stage, level, indices))
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    yield future.result()
            is_done = True
        except BrokenProcessPool as exc:
            statuses = [] if self._pool is None else _exit_statuses(self._workers)
            self._pool, self._workers = None, []
            raise ExecutorError(_broken_pool_message(statuses, is_starting=False)) from exc
        finally:
            if not is_done:
                _abandon(pending)

    def close(self, *, is_abort: bool = False) -> None:
        """Stop the workers; with ``is_abort`` (an error or Ctrl-C) without waiting for running samples."""
        if self._pool is None:
            return
        if is_abort:
            # A running sample may take a minute on a fine grid; its result is not
            # wanted any more. ProcessPoolExecutor has no public way to stop a
            # running task before Python 3.14 (terminate_workers), hence _processes.
            for process in _pool_processes(self._pool):
                process.terminate()
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._pool, self._workers = None, []

    def __exit__(self, exc_type: object, *exc_info: object) -> None:
        self.close(is_abort=exc_type is not None)


class DaskExecutor(Executor):
    """Sends work items to a ``dask.distributed`` cluster (optional extra ``dask``).

    Parameters
    ----------
    scheduler : str or distributed.Client
        Address of a running scheduler (``tcp://host:8786``) or a client.

    The model is scattered to the workers once; each item is one task.
    The cluster's workers should run one thread each per ``solver.threads``
    (e.g. ``dask worker --nthreads 1``); roughuq does not manage them.
    """

    runs_here = False

    def __init__(self, scheduler: object) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise ExecutorError(
                "the dask executor needs the optional extra: pip install 'roughuq[dask]'"
            ) from None
        if isinstance(scheduler, Client):
            self._client = scheduler
            self._owns_client = False
        else:
            scheduler = check_scheduler_address(scheduler)
            _check_handshake(scheduler)
            try:
                self._client = Client(scheduler, timeout="10s", set_as_default=False)
            except (OSError, TypeError, ValueError) as exc:  # a TLS address without certificates was a TypeError
                raise ExecutorError(f"cannot reach the dask scheduler at {scheduler!r}: {_one_line(exc)}") from None
            self._owns_client = True
        self.n_workers = max(1, sum(self._client.nthreads().values()))
        self._scattered: tuple[ContactModel, object] | None = None

    def _scatter(self, model: ContactModel) -> object:
        # Scatter once and keep the future: scattering the same data again gives the
        # same key, which the release of an earlier run's future would take away.
        if self._scattered is None or self._scattered[0] != model:
            try:
                _check_worker_versions(self._client.run(_installed_version))
                future = self._client.scatter(model, broadcast=True)
            except RoughUQError:  # workers of another version
                raise
            except Exception as exc:  # noqa: BLE001 - distributed re-raises the workers' errors as they are
                # A scheduler without workers ("No valid workers found") or workers that cannot import roughuq
                # were tracebacks, status 1.
                raise ExecutorError(
                    f"cannot send the problem to the dask cluster's workers ({_one_line(exc)}): start workers "
                    "(`dask worker ADDRESS --nthreads 1`) in an environment where roughuq is installed, the same "
                    "version as here"
                ) from None
            self._scattered = (model, future)
        return self._scattered[1]

    def run(self, model: ContactModel, items: Sequence[WorkItem]) -> Iterator[LevelBatch]:
        from distributed import as_completed

        model_future = self._scatter(model)
        futures = [
            self._client.submit(_compute, model_future, stage, level, indices, pure=False)
            for stage, level, indices in items
        ]
        is_done = False
        try:
            for future in as_completed(futures, loop=self._client.loop):
                try:
                    yield future.result()
                except Exception as exc:
                    if isinstance(exc, RoughUQError):
                        raise
                    self._scattered = None  # its workers may be gone with it: the next run scatters again
                    raise ExecutorError(dask_failure_text(exc)) from exc
            is_done = True
        finally:
            if not is_done:
                self._client.cancel(futures)

    def close(self) -> None:
        self._scattered = None
        if self._owns_client:
            self._client.close()
            self._owns_client = False


def _installed_version() -> str:
    """The roughuq version of the process that runs it (a dask worker's)."""
    from rough_uq import __version__

    return __version__


def _check_worker_versions(versions: dict[str, str]) -> None:
    """Refuse dask workers (address -> roughuq version) whose roughuq is not this one's: a worker of another
    version stored its own numbers as the study's, status 0 (every sample of the run differed from a serial run)."""
    here = _installed_version()
    other = {address: version for address, version in versions.items() if version != here}
    if other:
        shown = ", ".join(f"{address} has {version}" for address, version in sorted(other.items())[:3])
        raise ExecutorError(f"dask workers run another roughuq than this one ({here}): {shown}; install roughuq "
                            f"{here} on the workers (same config and seed give the same numbers only on one version)")


def dask_failure_text(error: Exception) -> str:
    """What an :class:`ExecutorError` says about a dask task that raised ``error`` (not a roughuq error).

    A task whose workers died or left the cluster (``KilledWorker``; a cancelled future, "already forgotten" once
    the scattered model was lost with them; a closed connection) is lost, not wrong: the same command run again
    computes the rest, as after a local worker's death.
    """
    from concurrent.futures import CancelledError

    from distributed import KilledWorker

    cause = _one_line(error)
    if isinstance(error, (KilledWorker, CancelledError, OSError)):
        return (f"a dask task was lost ({cause}): its workers died (killed, or out of memory) or left the cluster, "
                "or the scheduler went away; "
                "a study file keeps the samples already stored: the same roughuq command run again, on a cluster "
                "with workers, computes the rest")
    return f"a dask task failed: {cause}"


def _one_line(error: BaseException) -> str:
    """``Type: message`` on one line (distributed's reasons hold newlines: an ``error:`` line became two)."""
    return " ".join(f"{type(error).__name__}: {error}".split())


#: Schemes of a scheduler address whose location is ``host:port``.
_HOST_PORT_SCHEMES = ("tcp", "tls", "ws", "wss")

#: Schemes roughuq's client connects by: tls and wss need certificates it has no option for (a TypeError after
#: 20 s), ucx a UCX build, inproc a scheduler in this process (tracebacks, status 1).
_CONNECTABLE_SCHEMES = ("tcp", "ws")


#: Seconds a tcp address has to send the first bytes of a dask handshake (:func:`_check_handshake`).
HANDSHAKE_SECONDS = 10.0


def _check_handshake(scheduler: str) -> None:
    """Refuse (:class:`ExecutorError`) a tcp address that accepts a connection but sends no handshake.

    A dask scheduler (its listener) sends its handshake as soon as a connection opens. distributed's
    ``Client`` waits for it without end: an address where something else listens (an HTTP server) or a frozen
    scheduler held a command silently until Ctrl-C, whose exit then waited 20 s more and printed the client's
    traceback. A refused connection is left to the Client, which says so. ws addresses speak HTTP first and
    are not probed.
    """
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    scheme, location = parse_address(scheduler)
    if scheme != "tcp":
        return
    host, port = parse_host_port(location)
    try:
        connection = socket.create_connection((host, int(port)), timeout=HANDSHAKE_SECONDS)
    except OSError:
        return  # refused or unreachable: the Client's own message names it
    with connection:
        try:
            is_answered = bool(connection.recv(1))
        except OSError:  # timed out, reset
            is_answered = False
    if not is_answered:
        raise ExecutorError(
            f"{scheduler!r} accepts connections but is no dask scheduler (no handshake within "
            f"{HANDSHAKE_SECONDS:g} s; a scheduler stopped or frozen does the same): give the address that "
            "`dask scheduler` prints"
        )


def check_scheduler_address(scheduler: object, name: str = "scheduler") -> str:
    """``scheduler`` as an address distributed can connect to, ``[scheme://]host:port``; otherwise
    :class:`InvalidParameterError` naming ``name``.

    distributed's ``Client`` raised a bare ValueError for an address such as ``localhost:abc`` or ``notaurl`` (no
    port), and its finaliser then waited 20 s and printed a traceback of its own.
    """
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    schemes = [scheme for scheme in _CONNECTABLE_SCHEMES if scheme in backends]
    allowed = f"the address of a dask scheduler, [scheme://]host:port with a scheme of {', '.join(schemes)} "
    allowed += "(e.g. tcp://127.0.0.1:8786)"
    try:
        scheme, location = parse_address(str(scheduler))
        if scheme not in schemes:
            raise ValueError(scheme)
        if scheme in _HOST_PORT_SCHEMES:
            host, port = parse_host_port(location)
            if not host or not 0 < int(port) < 65536:
                raise ValueError(location)
    except (ValueError, TypeError):
        raise InvalidParameterError(name, scheduler, allowed) from None
    return str(scheduler)


def make_executor(kind: str, *, workers: int | None = None, threads: int = 1, scheduler: str | None = None) -> Executor:
    """The executor the CLI's ``--executor``/``--workers``/``--scheduler`` ask for.

    ``kind`` is ``"local"`` (serial when ``workers == 1``, else a pool of
    ``workers``, default :func:`default_workers`) or ``"dask"`` (needs ``scheduler``).
    ``workers`` may be at most :func:`max_workers`, i.e. :data:`MAX_WORKERS_PER_CORE`
    (4) per core available to this process: the solves are CPU-bound, so more
    processes than cores only share them; a few per core are allowed, a number
    that would exhaust memory or the process table is refused
    (:class:`InvalidParameterError` naming ``workers``).
    """
    if kind == "dask":
        if not scheduler:
            raise InvalidParameterError("scheduler", scheduler, "the address of a dask scheduler, e.g. tcp://host:8786")
        return DaskExecutor(scheduler)
    if kind != "local":
        raise InvalidParameterError("executor", kind, "'local' or 'dask'")
    threads = check_threads(threads, name="solver.threads")
    n_workers = default_workers(threads) if workers is None else check_workers(workers)
    return SerialExecutor() if n_workers == 1 else PoolExecutor(n_workers, threads=threads)

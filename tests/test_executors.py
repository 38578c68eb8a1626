"""Every executor stores the same samples and gives the same estimate, bit for bit."""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import types
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rough_uq.cli import main
from rough_uq.study.config import config_from_dict
from rough_uq.errors import ExecutorError, InvalidParameterError
from rough_uq.study import executors
from rough_uq.study.executors import SerialExecutor, default_workers, make_executor, PoolExecutor
from rough_uq.study.pipeline import Study, run_estimation, run_screening
from rough_uq.study.progress import Progress
from rough_uq.study.store import MemoryStore
from tests.study_configs import tiny_config, write_config


def _run(executor) -> Study:
    config = config_from_dict(tiny_config())
    study = Study(config, MemoryStore(qoi_names=config.qoi_names))
    run_screening(study, executor=executor, progress=Progress())
    run_estimation(study, method="mlmc", tol=np.array([5.0]), executor=executor, progress=Progress())
    return study


def _assert_same_samples(a: Study, b: Study) -> None:
    assert a.store.levels() == b.store.levels()
    for level in a.store.levels():
        assert a.store.stages(level=level) == b.store.stages(level=level)
        for stage in a.store.stages(level=level):
            x = a.store.read_samples(level=level, stage=stage)
            y = b.store.read_samples(level=level, stage=stage)
            for name in ("indices", "fine", "coarse", "n_iter", "converged"):
                np.testing.assert_array_equal(getattr(x, name), getattr(y, name))
    assert [r["estimate"] for r in a.store.read_runs()] == [r["estimate"] for r in b.store.read_runs()]


def test_make_executor_choices():
    assert isinstance(make_executor("local", workers=1), SerialExecutor)
    pool = make_executor("local", workers=2)
    assert isinstance(pool, PoolExecutor) and pool.n_workers == 2
    pool.close()
    assert default_workers(threads=1) >= 1
    assert default_workers(threads=10_000) == 1
    with pytest.raises(InvalidParameterError, match="scheduler"):
        make_executor("dask")
    with pytest.raises(InvalidParameterError, match="executor"):
        make_executor("mpi")


def test_a_local_pool_has_at_most_four_workers_per_core(monkeypatch):
    monkeypatch.setattr(executors, "available_cores", lambda: 3)
    assert executors.max_workers() == 3 * executors.MAX_WORKERS_PER_CORE == 12
    pool = make_executor("local", workers=12)  # modest oversubscription is allowed (no process is started yet)
    assert isinstance(pool, PoolExecutor) and pool.n_workers == 12
    pool.close()
    for workers in (13, 100_000, 0, 2.5, True):
        with pytest.raises(InvalidParameterError) as info:
            make_executor("local", workers=workers)
        assert info.value.name == "workers" and info.value.value == workers
        assert str(info.value).endswith("allowed: an integer in 1..12 (at most 4 per core; this process may use "
                                        "3 cores)")
    with pytest.raises(InvalidParameterError, match="^n_workers: got 13;"):  # its parameter, not the CLI's name
        PoolExecutor(13)
    pool = make_executor("local", workers=np.int64(3))
    assert pool.n_workers == 3
    pool.close()
    # solver.threads: 10000 passed, and two workers died creating their OpenMP threads (a rerun did the same).
    for threads in (13, 10_000, 0, 1.5):
        with pytest.raises(InvalidParameterError) as info:
            make_executor("local", workers=2, threads=threads)
        assert info.value.name == "solver.threads" and info.value.value == threads
        assert str(info.value).endswith("allowed: an integer in 1..12 (at most 4 per core; this process may use "
                                        "3 cores)")
        with pytest.raises(InvalidParameterError, match=rf"^threads: got {threads};"):
            PoolExecutor(2, threads=threads)


def test_dask_cluster_matches_serial(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    serial = _run(SerialExecutor())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            executor = make_executor("dask", scheduler=client)
            _assert_same_samples(serial, _run(executor))
            executor.close()
        # The CLI path: --executor dask --scheduler ADDRESS, results gathered into the study file.
        monkeypatch.chdir(tmp_path)
        config = write_config(tmp_path / "tiny.yaml", tiny_config())
        runner = CliRunner()
        args = ["--executor", "dask", "--scheduler", cluster.scheduler_address, "-q"]
        result = runner.invoke(main, ["screen", str(config), *args])
        assert result.exit_code == 0, (result.output, result.stderr)
        result = runner.invoke(main, ["mlmc", "--tol", "5", "--json", *args])
        assert result.exit_code == 0, (result.output, result.stderr)
    (expected,) = serial.store.read_runs()
    assert json.loads(result.output)["estimate"] == expected["estimate"]


def test_unreachable_scheduler_is_a_clear_error(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = CliRunner().invoke(main, ["screen", str(config), "--executor", "dask", "--scheduler",
                                       "tcp://127.0.0.1:1", "-q"])
    assert result.exit_code == 2 and "dask scheduler" in result.stderr


def test_an_address_that_listens_but_is_no_scheduler_is_refused_not_waited_on(tmp_path, monkeypatch):
    # Something else listening there (an HTTP server, a frozen scheduler): distributed's Client waited without
    # end, and after a Ctrl-C its finaliser another 20 s, printing its traceback.
    import socket

    pytest.importorskip("distributed")
    monkeypatch.setattr(executors, "HANDSHAKE_SECONDS", 0.5)
    with socket.create_server(("127.0.0.1", 0)) as silent:
        port = silent.getsockname()[1]
        with pytest.raises(ExecutorError, match=f"^'tcp://127.0.0.1:{port}' accepts connections but is no dask "
                                                r"scheduler \(no handshake within 0.5 s;"):
            executors.DaskExecutor(f"tcp://127.0.0.1:{port}")
        monkeypatch.chdir(tmp_path)
        config = write_config(tmp_path / "tiny.yaml", tiny_config())
        result = CliRunner().invoke(main, ["screen", str(config), "--executor", "dask", "--scheduler",
                                           f"tcp://127.0.0.1:{port}", "-q"])
        assert result.exit_code == 2 and "is no dask scheduler" in result.stderr


@pytest.mark.parametrize("address", ["notaurl", "localhost:abc", "tcp://", "foo://bar:1", "tcp://host:0", "h:99999",
                                     # schemes the client cannot connect by: tracebacks, status 1, after 20 s
                                     "tls://127.0.0.1:9999", "ucx://127.0.0.1:9999", "inproc://x"])
def test_a_malformed_scheduler_address_is_refused_by_name_before_any_connection(tmp_path, monkeypatch, address):
    # distributed's Client raised a bare ValueError (a traceback, status 1), and its finaliser then waited 20 s.
    pytest.importorskip("distributed")
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = CliRunner().invoke(main, ["screen", str(config), "--executor", "dask", "--scheduler", address, "-q"])
    assert result.exit_code == 2 and result.stderr.startswith(f"error: --scheduler: got {address!r}; allowed: the "
                                                              "address of a dask scheduler, [scheme://]host:port")
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert not (tmp_path / "results.h5").exists()  # refused with the other options, before the study file


@pytest.mark.parametrize("raised", [TimeoutError("No valid workers found"),
                                    Exception("ModuleNotFoundError(\"No module named 'rough_uq'\")")])
def test_a_cluster_whose_workers_cannot_take_the_problem_is_one_error(raised):
    # A scheduler without workers, or workers without roughuq: the scatter's error was a traceback, status 1.
    from rough_uq.errors import ExecutorError

    class Client:
        def run(self, function):
            return {"tcp://127.0.0.1:1": function()}

        def scatter(self, data, broadcast):
            raise raised

    executor = executors.DaskExecutor.__new__(executors.DaskExecutor)
    executor._client, executor._scattered = Client(), None
    with pytest.raises(ExecutorError, match=r"^cannot send the problem to the dask cluster's workers \(") as info:
        executor._scatter("model")
    assert type(raised).__name__ in str(info.value) and "\n" not in str(info.value)
    assert "start workers" in str(info.value) and "where roughuq is installed" in str(info.value)


def test_dask_workers_of_another_roughuq_are_refused():
    # A worker of another version stored its own numbers as the study's, status 0.
    from rough_uq import __version__
    from rough_uq.errors import ExecutorError

    class Client:
        def run(self, function):
            return {"tcp://10.0.0.2:4000": function(), "tcp://10.0.0.3:4000": "0.0.9"}

        def scatter(self, data, broadcast):
            raise AssertionError("scattered to workers of another version")

    executor = executors.DaskExecutor.__new__(executors.DaskExecutor)
    executor._client, executor._scattered = Client(), None
    refusal = rf"^dask workers run another roughuq than this one \({re.escape(__version__)}\): tcp://10.0.0.3:4000 has "
    with pytest.raises(ExecutorError, match=refusal + "0.0.9; install roughuq"):
        executor._scatter("model")


def test_a_lost_task_s_reason_is_one_line():
    # distributed's reason for a cancelled future holds a newline: the error: line became two.
    from concurrent.futures import CancelledError

    text = executors.dask_failure_text(CancelledError("cancelled for reason: scheduler-connection-lost.\nClient "
                                                      "lost the connection to the scheduler."))
    assert "\n" not in text and "scheduler-connection-lost. Client lost" in text and "scheduler went away" in text


@pytest.mark.parametrize("is_pool_worker", [True, False])
def test_a_worker_warms_the_kernels_once_before_its_first_sample(monkeypatch, is_pool_worker):
    calls: list[str] = []
    monkeypatch.setattr(executors, "_is_warm", False)
    monkeypatch.setattr(executors, "_is_pool_worker", is_pool_worker)
    monkeypatch.setattr(executors, "warm_up", lambda model: calls.append(f"warm {model}"))
    monkeypatch.setattr(executors, "freeze_garbage", lambda: calls.append("freeze"))
    monkeypatch.setattr(executors, "compute_batch", lambda model, **item: calls.append(f"sample {item['level']}"))
    for level in (0, 1):
        executors._compute("model", 5, level, np.arange(2))
    # The garbage collector is tuned only in the pool's own processes (a dask worker may be the user's).
    expected = ["warm model", "freeze", "sample 0", "sample 1"]
    assert calls == (expected if is_pool_worker else [call for call in expected if call != "freeze"])


def test_the_serial_executor_warms_the_kernels_once_per_process_without_freezing(monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(executors, "_is_warm", False)
    monkeypatch.setattr(executors, "warm_up", lambda model: calls.append(f"warm {model}"))
    monkeypatch.setattr(executors, "freeze_garbage", lambda: calls.append("freeze"))
    monkeypatch.setattr(executors, "compute_batch", lambda model, **item: calls.append(f"sample {item['level']}"))
    items = [(5, 0, np.arange(2)), (5, 1, np.arange(2))]
    list(SerialExecutor().run("model", items))
    list(SerialExecutor().run("model", items[:1]))
    assert calls == ["warm model", "sample 0", "sample 1", "sample 0"]


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="needs POSIX signal masks")
def test_a_ctrl_c_while_workers_are_spawned_comes_after_the_spawning_once():
    # Spawned workers inherit the blocked mask (tests/test_faults.py runs the real thing). Here: the Ctrl-C of
    # the spawning's few milliseconds reaches the handler once the spawning is over, never during it, whether
    # this thread holds it back or another thread takes it; afterwards, handler and mask are as before.
    calls: list[str] = []

    def handler(signum: int, frame: object) -> None:
        calls.append("handler")

    # Thread-directed signals: a process-directed one (os.kill) went to whichever thread of the test process did
    # not block it (an OpenMP thread of an earlier test), whose handler could run after this test under load; the
    # suite then stopped with KeyboardInterrupt (2026-11-29).
    def held_back_here() -> None:
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    def taken_by_another_thread() -> None:
        def take() -> None:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # it inherited the block
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # handled (flagged) before this returns

        thread = threading.Thread(target=take)
        thread.start()
        thread.join()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        for ctrl_c in (held_back_here, taken_by_another_thread):
            calls.clear()
            with executors._sigint_held_back():
                ctrl_c()
                sum(range(100_000))  # room for Python to run signal handlers
                calls.append("spawned")
            assert calls == ["spawned", "handler"]
            assert signal.getsignal(signal.SIGINT) is handler
            assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
        # Off the main thread only the mask changes (signal.signal would raise there).
        seen: list[object] = []

        def spawn_off_the_main_thread() -> None:
            with executors._sigint_held_back():
                seen.append(signal.getsignal(signal.SIGINT))
                seen.append(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
            seen.append(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))

        thread = threading.Thread(target=spawn_off_the_main_thread)
        thread.start()
        thread.join()
        assert seen == [handler, True, False]
    finally:
        signal.signal(signal.SIGINT, previous)


ROOT = Path(__file__).resolve().parent.parent

#: A script that starts a pool without `if __name__ == "__main__":` (as the README's recipe once read).
UNGUARDED_SCRIPT = textwrap.dedent("""
    import rough_uq
    from rough_uq.study.executors import PoolExecutor

    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"],
                                      coarsest=16, max_level=2, seed=7)
    with PoolExecutor(N_WORKERS) as pool:
        rough_uq.mlmc(problem, tol=2.0, executor=pool)
""")


# One worker: the broken pool had emptied its list of workers before their status was read, in most runs, and
# the message said "an error in the worker, printed above" (nothing was printed).
@pytest.mark.parametrize("n_workers", [1, 2])
def test_a_script_that_starts_a_pool_unguarded_is_told_to_add_the_main_guard(tmp_path, n_workers):
    # Each spawned worker re-ran the script, failed with multiprocessing's RuntimeError, and the script ended
    # in "a worker process died while computing samples ...: run the command again" (there was no command).
    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED_SCRIPT.replace("N_WORKERS", str(n_workers)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                            timeout=300, env=env)
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("rough_uq.errors.ExecutorError: a worker process failed while starting: "), last
    assert "`if __name__ == '__main__':`" in last and "run the command again" not in last
    assert "freeze_support" not in result.stderr  # the workers ended before multiprocessing's RuntimeError


def _exit_86() -> None:
    raise SystemExit(executors.UNGUARDED_MAIN_STATUS)


def test_a_broken_pool_reads_the_statuses_of_the_workers_it_started_with():
    # A broken pool empties its own list of workers, with one worker often before their status was read:
    # the statuses come from the processes listed when the workers started.
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    worker = multiprocessing.get_context("spawn").Process(target=_exit_86)
    worker.start()
    worker.join(60)
    pool = executors.PoolExecutor(1)
    pool._pool, pool._workers = types.SimpleNamespace(_processes={}), [worker]
    broken = Future()
    broken.set_exception(BrokenProcessPool("a child process terminated abruptly"))
    with pytest.raises(executors.ExecutorError, match=r"`if __name__ == '__main__':`"):
        pool._wait_for_start([broken])


def test_a_broken_pool_is_explained_by_when_it_broke():
    unguarded = executors._broken_pool_message([executors.UNGUARDED_MAIN_STATUS, -15], is_starting=True)
    assert "`if __name__ == '__main__':`" in unguarded
    starting = executors._broken_pool_message([1, -15], is_starting=True)
    assert starting.startswith("a worker process failed while starting, before it computed any sample (")
    computing = executors._broken_pool_message([-9], is_starting=False)
    assert computing.startswith("a worker process died while computing samples (killed, or out of memory)")
    for message in (unguarded, starting, computing):
        assert "run the command again" not in message  # a Python script has no command to run again


def test_a_dask_task_lost_with_its_workers_says_that_a_rerun_computes_the_rest():
    # Killing the dask workers said "a dask task failed: FutureCancelledError: ... already forgotten", with no way
    # forward, although the stored samples were kept (as a local pool's dead worker says).
    pytest.importorskip("distributed")
    from distributed import KilledWorker
    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError

    from rough_uq.study.executors import dask_failure_text

    from types import SimpleNamespace

    killed = KilledWorker("_compute-1", SimpleNamespace(address="tcp://10.0.0.2:40001"), 3)
    for lost in (killed, FutureCancelledError("_compute-1", "already forgotten"),
                 CommClosedError("in <TCP>: Stream is closed")):
        text = dask_failure_text(lost)
        assert text.startswith(f"a dask task was lost ({type(lost).__name__}: ")
        assert text.endswith("the same roughuq command run again, on a cluster with workers, computes the rest")
    assert dask_failure_text(ZeroDivisionError("x")) == "a dask task failed: ZeroDivisionError: x"


def test_a_run_closed_early_cancels_pool_futures_only_from_python_3_12():
    # A SIGTERM to the process group (a scheduler's) ends the workers while the run cancels its futures. Before
    # Python 3.12 the pool's thread then raised InvalidStateError on a cancelled future ("Exception in thread
    # Thread-1: ... CANCELLED", 2 of 20 group SIGTERMs of `roughuq mlmc`) and died before terminating the workers
    # and closing the pool's queues; there the run leaves them to close(), whose shutdown cancels them in that thread.
    from concurrent.futures import Future

    futures = [Future(), Future()]
    executors._abandon(futures)
    assert [future.cancelled() for future in futures] == [sys.version_info >= (3, 12)] * 2

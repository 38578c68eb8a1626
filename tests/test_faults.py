"""Faults: a run killed at random moments (Ctrl-C, kill -9) or losing a worker resumes to the same result."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config

TOL = "0.001"  # mean gap (length unit); reachable on these grids, about 20 s of MLMC on an idle 2-core machine
ROOT = Path(__file__).resolve().parent.parent


def _env() -> dict[str, str]:
    """The subprocesses' environment: this checkout's roughuq, whatever is installed, and the session's settings.

    Built when a subprocess starts, not at import: the session fixture of
    conftest.py sets ``ROUGHUQ_FFTW_WISDOM`` after this module is collected, and
    an environment copied before would send the subprocesses' FFTW wisdom to the
    user's cache.
    """
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}


def _config(directory: Path) -> Path:
    # Grids 32..128: an MLMC run to TOL takes about 20 s here (idle), long enough to interrupt after 3 s.
    # The mean gap, not the contact area: its bias is small enough that grid.max_level reaches TOL (the
    # CLI refuses an unreachable tolerance before the first sample). Not from 16: that grid truncates the
    # spectrum (k_s = 16), and the bias fitted across it (alpha 7) is no longer trusted.
    config = tiny_config(
        surface={"system_size": 1.0, "wavenumbers": {"k_l": 1, "k_r": 2, "k_s": 16}, "hurst": 0.8, "rms_height": 1.0},
        grid={"coarsest": 32, "max_level": 2},
        qoi={"mean_gap": {}},
    )
    return write_config(directory / "study.yaml", config)


def _roughuq(*args: str, cwd: Path, **kwargs: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rough_uq.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env=_env(), **kwargs)


def _default_sigint() -> None:
    # A pytest run started in the background (``cmd &`` in a script) ignores SIGINT, and a child
    # inherits that: Python then installs no KeyboardInterrupt handler and the Ctrl-C tests fail.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(*args: str, cwd: Path, **popen: object) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rough_uq.cli", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), preexec_fn=_default_sigint, **popen)


def _wait_until_running(process: subprocess.Popen, study: Path, timeout: float = 60.0) -> None:
    """Return once ``process`` holds the lock of ``study`` (its run has begun), or has exited.

    Python's start-up and imports take about 2 s idle and several times that on
    a loaded machine; a signal before the CLI runs would test Python's default
    handling, not the store's. Read from ``/proc`` (Linux); elsewhere return at once.
    """
    lock = str(study.with_name(study.name + ".lock"))
    descriptors = Path(f"/proc/{process.pid}/fd")
    if not descriptors.parent.exists():
        return
    deadline = time.monotonic() + timeout
    while process.poll() is None and time.monotonic() < deadline:
        try:
            if any(os.readlink(fd) == lock for fd in descriptors.iterdir()):
                return
        except OSError:  # a descriptor closed while listed, or the process exited
            pass
        time.sleep(0.05)


def _screened(directory: Path) -> Path:
    directory.mkdir()
    result = _roughuq("screen", str(_config(directory)), "-q", "--workers", "1", cwd=directory)
    assert result.returncode == 0, result.stderr
    return directory


def _finish(directory: Path, *options: str) -> dict:
    result = _roughuq("mlmc", "--tol", TOL, "-q", "--json", *options, cwd=directory)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def _stored(directory: Path) -> dict[int, np.ndarray]:
    """Indices per level of the estimation samples (every stage but the screening)."""
    with open_study_readonly(directory / "results.h5") as store:
        return {
            level: np.concatenate([store.sample_indices(level=level, stage=stage)
                                   for stage in store.stages(level=level) if stage != 0] or [np.zeros(0, int)])
            for level in store.levels()
        }


def test_the_subprocesses_keep_their_fftw_wisdom_where_the_test_session_says(tmp_path, monkeypatch):
    """Their environment was copied at import, before conftest set ROUGHUQ_FFTW_WISDOM: the user's cache got it."""
    wisdom = tmp_path / "wisdom.json"
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", str(wisdom))
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = _roughuq("screen", str(config), "-q", "--workers", "1", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert json.loads(wisdom.read_text())["format"] == "roughuq-fftw-wisdom"


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict:
    return _finish(_screened(tmp_path_factory.mktemp("reference") / "study"), "--workers", "1")


def test_killed_runs_lose_nothing_and_resume_to_the_same_estimate(tmp_path, reference):
    directory = _screened(tmp_path / "study")
    rng = np.random.default_rng(5)
    previous = {}
    for attempt, sig in enumerate([signal.SIGINT, signal.SIGKILL, signal.SIGTERM, signal.SIGKILL]):
        process = _start("mlmc", "--tol", TOL, "-q", "--workers", "1", cwd=directory)
        _wait_until_running(process, directory / "results.h5")
        time.sleep(rng.uniform(0.5, 5.0))
        process.send_signal(sig)
        _, stderr = process.communicate(timeout=60)
        if process.returncode == 0:
            break  # finished before the signal: nothing left to interrupt
        expected = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -signal.SIGKILL}[sig]
        assert process.returncode == expected, stderr
        if sig != signal.SIGKILL:  # a clean stop, with its message
            word = "interrupted" if sig == signal.SIGINT else "terminated"
            assert word in stderr and "Traceback" not in stderr, stderr
            # The command that continues, as it was called (`roughuq` may not be on PATH).
            assert f"run the same command to continue: python -m rough_uq.cli mlmc --tol {TOL} -q --workers 1" in stderr
        stored = _stored(directory)  # the file opens after every interruption
        for level, indices in stored.items():
            assert np.unique(indices).size == indices.size, "a sample was stored twice"
            assert set(previous.get(level, [])) <= set(indices.tolist()), "a stored sample was lost"
        previous = {level: indices.tolist() for level, indices in stored.items()}
    final = _finish(directory, "--workers", "1")
    for key in ("estimate", "stat_error", "bias_estimate", "n_samples", "cost"):
        assert final[key] == reference[key], key
    stored = _stored(directory)
    assert sum(indices.size for indices in stored.values()) == sum(final["n_samples"])


def _pool_workers(pid: int) -> list[int]:
    """Pids of the spawned pool workers of process ``pid`` (not the resource tracker).

    Recognised by their command line, which a child has only once it has run
    the interpreter: a child between fork and exec still shows its parent's.
    """
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except FileNotFoundError:  # exited
        return []
    workers = []
    for child in children:
        try:
            command = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except FileNotFoundError:
            continue
        if b"--multiprocessing-fork" in command:
            workers.append(int(child))
    return workers


def _start_with_pool(directory: Path) -> tuple[subprocess.Popen, list[int]]:
    """Start an MLMC run with 2 pool workers; return it once both workers exist."""
    process = _start("mlmc", "--tol", TOL, "-q", "--workers", "2", cwd=directory)
    deadline = time.monotonic() + 60
    workers: list[int] = []
    while time.monotonic() < deadline and len(workers) < 2:
        time.sleep(0.2)
        workers = _pool_workers(process.pid)
    assert len(workers) == 2, "the pool did not start"
    return process, workers


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_a_dead_worker_loses_only_its_samples(tmp_path, reference):
    directory = _screened(tmp_path / "study")
    process, workers = _start_with_pool(directory)
    time.sleep(3.0)
    os.kill(workers[0], signal.SIGKILL)
    _, stderr = process.communicate(timeout=120)
    if process.returncode != 0:  # the run may have finished before the kill
        assert process.returncode == 2, stderr
        # Killed while computing, or (a slow start, e.g. beside other tests) before its first sample.
        assert ("worker process died" in stderr or "worker process failed while starting" in stderr), stderr
        assert "Traceback" not in stderr
    final = _finish(directory, "--workers", "2")
    for key in ("estimate", "stat_error", "bias_estimate", "n_samples", "cost"):
        assert final[key] == reference[key], key
    stored = _stored(directory)
    assert sum(indices.size for indices in stored.values()) == sum(final["n_samples"])


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_pool_workers_do_not_outlive_their_run(tmp_path, sig):
    directory = _screened(tmp_path / "study")
    process, workers = _start_with_pool(directory)
    time.sleep(1.0)
    start = time.monotonic()
    process.send_signal(sig)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -signal.SIGKILL}[sig], stderr
    # Ctrl-C stops running samples instead of waiting for them; kill -9 takes the workers along.
    while time.monotonic() - start < 10 and any(Path(f"/proc/{pid}").exists() for pid in workers):
        time.sleep(0.1)
    alive = [pid for pid in workers if Path(f"/proc/{pid}/status").exists()
             and "zombie" not in Path(f"/proc/{pid}/status").read_text()]
    assert not alive, f"workers {alive} outlived their run"


def _sigint_masks(pid: int) -> set[str] | None:
    """Which signal masks of process ``pid`` hold SIGINT (blocked, ignored, caught); None once it has exited."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except FileNotFoundError:
        return None
    status = {key: value.strip() for key, _, value in (line.partition(":") for line in lines)}
    if status["State"].startswith(("Z", "X")):
        return None
    return {key for key in ("SigBlk", "SigIgn", "SigCgt") if int(status[key], 16) >> (signal.SIGINT - 1) & 1}


def _poll(condition: Callable[[], object], timeout: float) -> object:
    """The first true value of ``condition()``, polled every 10 ms, or its last value after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not (value := condition()) and time.monotonic() < deadline:
        time.sleep(0.01)
    return value


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("is_command_held", [True, False], ids=["command-held", "at-once"])
def test_ctrl_c_while_pool_workers_import_prints_no_worker_traceback(tmp_path, is_command_held):
    # Ctrl-C reaches the whole foreground process group: the command and the workers it has just spawned, which
    # import numpy, numba and roughuq for seconds before they can ignore it. It is sent once Python runs in both
    # workers (SIGINT caught or ignored: a signal before that kills a process without a word). Held: sent at once,
    # with the command stopped from just before the Ctrl-C until each worker has ignored it or died of it;
    # otherwise, in most runs, the command kills a worker that did not ignore it before its traceback is out. At
    # once: sent 0.3 s later, amid the imports, and the command stops workers still importing.
    config = write_config(tmp_path / "study.yaml", tiny_config())
    process = _start("screen", str(config), "-q", "--workers", "2", cwd=tmp_path, start_new_session=True)
    try:
        def started() -> list[int]:
            workers = _pool_workers(process.pid)
            is_running = len(workers) == 2 and all((_sigint_masks(pid) or set()) & {"SigIgn", "SigCgt"}
                                                   for pid in workers)
            return workers if is_running or process.poll() is not None else []

        workers = _poll(started, timeout=60)
        assert len(workers) == 2, "the pool did not start"
        if is_command_held:
            os.kill(process.pid, signal.SIGSTOP)
        else:
            time.sleep(0.3)
        os.killpg(process.pid, signal.SIGINT)
        if is_command_held:
            _poll(lambda: all(_sigint_masks(pid) in (None, {"SigIgn"}) for pid in workers), timeout=20)
            os.kill(process.pid, signal.SIGCONT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            os.kill(process.pid, signal.SIGCONT)
            process.communicate()
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert process.returncode == 130 and "interrupted" in stderr, stderr
    _poll(lambda: all(_sigint_masks(pid) is None for pid in workers), timeout=10)
    alive = [pid for pid in workers if _sigint_masks(pid) is not None]
    assert not alive, f"workers {alive} outlived their run"


# Slow: test_cluster_scripts.test_loop_study_survives_a_killed_shard_and_matches_serial runs the same script
# to the serial result with a shard killed on the way (the default suite's loop-script test); this one adds
# only the default worker pool, whose samples equal the serial ones (test_pipeline, test_cli_spread).
@pytest.mark.slow
def test_bash_loop_script_completes_a_study_like_an_uninterrupted_run(tmp_path):
    """scripts/loop_study.sh (plan, shards, merge, repeat) ends with the estimate of a plain `roughuq mlmc`."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "roughuq"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m rough_uq.cli "$@"\n')
    shim.chmod(0o755)
    env = {**_env(), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    directory = tmp_path / "loop"
    directory.mkdir()
    config = _config(directory)
    subprocess.run(["bash", str(ROOT / "scripts" / "loop_study.sh"), str(config), "0.01", "study.h5", "500"],
                   cwd=directory, env=env, check=True, capture_output=True, timeout=600)
    plain = tmp_path / "plain"
    plain.mkdir()
    assert _roughuq("screen", str(_config(plain)), "-q", "--workers", "1", cwd=plain).returncode == 0
    expected = json.loads(_roughuq("mlmc", "--tol", "0.01", "--json", "-q", "--workers", "1", cwd=plain).stdout)
    result = _roughuq("mlmc", "--study", "study.h5", "--tol", "0.01", "--json", "-q", cwd=directory)
    final = json.loads(result.stdout)
    assert final["n_computed"] == 0
    for key in ("estimate", "stat_error", "n_samples", "cost"):
        assert final[key] == expected[key], key


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_swallowed_by_a_callback_is_raised_at_the_next_batch(sig, monkeypatch):
    # A signal that lands in a weakref callback or __del__ has its exception printed as
    # "Exception ignored" and dropped (seen: SIGTERM during a pool run, which then finished
    # with status 0). The request is recorded; the command's progress raises it again at
    # its next batch, and the command ends with the signal's status.
    from click.testing import CliRunner

    import rough_uq.cli as cli

    class Referent:
        pass

    def command() -> None:
        progress = cli._progress(quiet=True)
        referent = Referent()
        reference = weakref.ref(referent, lambda _: cli._raise_terminated(sig, None))
        del referent  # the callback raises the stop; Python reports the exception and drops it
        assert reference() is None
        progress.advance(0, 1)
        raise AssertionError("the recorded stop was not raised")

    # Python's own hook, which prints the traceback to stderr (pytest's would keep it as a warning).
    monkeypatch.setattr(sys, "unraisablehook", sys.__unraisablehook__)
    wrapped = cli._user_errors(command)
    result = CliRunner().invoke(cli.click.command()(wrapped))
    assert result.exit_code == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig], result.output
    assert "every completed sample is saved" in result.stderr
    # One line, no traceback of the swallowed first raise ("Exception ignored in ...").
    assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr, result.stderr
    assert sys.unraisablehook is sys.__unraisablehook__
    # The next command starts with no stop request.
    assert cli._user_errors(lambda: "ran")() == "ran"

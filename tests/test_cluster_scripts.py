"""The cluster scripts end to end, against a serial run of the same study.

``scripts/slurm_study.sh`` runs against the SLURM stand-ins of
``tests/fake_slurm`` (sbatch queues, a runner plays the scheduler, one array
task is killed as by a lost node) and ``scripts/loop_study.sh`` in plain bash
(one ``roughuq sample`` killed). Both must end with the serial run's estimate
and samples, bit for bit. ``roughuq`` in the scripts is this checkout's CLI.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rough_uq.cli import main
from rough_uq.study.resources import BASE_BYTES, STARTUP_SECONDS
from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config

ROOT = Path(__file__).resolve().parent.parent
FAKE_SLURM = ROOT / "tests" / "fake_slurm"
TOL = "2.5"   # two rounds of three shards without faults (2.0 needs five rounds, each a few processes more)
CHUNK = "50"   # one shard per level in the first round: few processes, the test stays short
#: Run-record fields that are wall-clock times or dates (everything else must match bit for bit).
TIMING = {"started", "finished", "seconds", "elapsed", "stopped_elapsed", "forecast", "mc_seconds_predicted",
          "n_computed"}

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def run_cli(*args: str) -> str:
    result = CliRunner().invoke(main, list(args))
    assert result.exit_code == 0, (result.output, result.exception)
    return result.output


def comparable(record: dict) -> dict:
    record = {key: value for key, value in record.items() if key not in TIMING}
    record["statistics"] = {k: v for k, v in record["statistics"].items() if k != "mean_seconds"}
    # The predicted seconds are the screening's measured time per modelled cost times the modelled cost.
    record["predicted"] = {k: v for k, v in record["predicted"].items() if not k.endswith("_seconds")}
    return record


def final_run(study: Path) -> tuple[dict, dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """The study's only run record and the samples it used per level (indices, fine, coarse).

    Shards may hold a few samples more than the run uses: a round computes
    all its plan asked for, and the plan may shrink once they are in.
    """
    with open_study_readonly(study) as store:
        (record,) = store.read_runs()
        samples = {}
        for level, n in zip(record["levels"], record["n_samples"]):
            batch = store.read_samples(level=level, stage=record["stage"])
            used = batch.indices < n
            samples[level] = (batch.indices[used], batch.fine[used], batch.coarse[used])
    return record, samples


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """The tiny study screened and estimated in one process: the reference."""
    directory = tmp_path_factory.mktemp("serial")
    config = write_config(directory / "tiny.yaml", tiny_config())
    study = directory / "serial.h5"
    run_cli("screen", str(config), "--out", str(study), "--workers", "1", "--quiet")
    run_cli("mlmc", "--study", str(study), "--tol", TOL, "--workers", "1", "--quiet")
    return config, study


def environment(tmp_path: Path, **extra: str) -> dict[str, str]:
    """PATH with the SLURM stand-ins and a ``roughuq`` of this checkout that can be told to die."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "roughuq"
    shim.write_text(
        "#!/usr/bin/env bash\n"
        "# This checkout's roughuq. KILL_SAMPLES=2,5 kills the 2nd and 5th `roughuq sample` (all: every one);\n"
        "# INTERRUPT_SAMPLE=2 sends SIGINT to the process group a second into the 2nd (a terminal's Ctrl-C);\n"
        "# NOT_MET=1: a run (`mlmc` without --plan) ends with status 3, as one that missed its tolerance;\n"
        "# SLOW_SAMPLES=1: every `roughuq sample` is a process that sleeps for a minute.\n"
        'if [ "$1" = sample ] && [ -n "${SLOW_SAMPLES:-}" ]; then exec sleep 60; fi\n'
        'if [ "$1" = mlmc ] && [ -n "${NOT_MET:-}" ] && [[ " $* " != *" --plan "* ]]; then\n'
        f'    {sys.executable} -m rough_uq.cli "$@" && exit 3\n'
        "fi\n"
        'if [ "$1" = sample ] && [ -n "${KILL_SAMPLES:-}${INTERRUPT_SAMPLE:-}" ]; then\n'
        '    n=$(( $(cat "$SAMPLE_COUNT" 2> /dev/null || echo 0) + 1 )); echo "$n" > "$SAMPLE_COUNT"\n'
        '    if [ "${KILL_SAMPLES:-}" = all ] || [[ ",${KILL_SAMPLES:-}," == *",$n,"* ]]; then kill -9 $$; fi\n'
        '    echo "sample $n started" >> "$SAMPLE_COUNT.log"\n'
        '    if [ "${INTERRUPT_SAMPLE:-}" = "$n" ]; then\n'
        '        (sleep 1; kill -INT 0; echo "SIGINT sent to the group, status $?" >> "$SAMPLE_COUNT.log") &\n'
        '    fi\n'
        "fi\n"
        f'exec {sys.executable} -m rough_uq.cli "$@"\n'
    )
    shim.chmod(0o755)
    # The caller's settings of the cluster scripts (ROUGHUQ would bypass the shim) are not the tests'.
    env = {name: value for name, value in os.environ.items() if name != "ROUGHUQ" and not name.startswith("RUQ_")}
    env.update(
        PATH=f"{FAKE_SLURM}{os.pathsep}{bin_dir}{os.pathsep}{env['PATH']}",
        PYTHONPATH=str(ROOT),
        NUMBA_NUM_THREADS="1",
        FAKE_SLURM_DIR=str(tmp_path / "spool"),
        FAKE_SLURM_PYTHON=sys.executable,
        SAMPLE_COUNT=str(tmp_path / "sample-count"),
        COLUMNS="160",
    )
    env.update(extra)
    return env


def bash(script: str, *args: str, cwd: Path, env: dict[str, str], expect: int = 0) -> subprocess.CompletedProcess:
    done = subprocess.run(["bash", str(ROOT / "scripts" / script), *args], cwd=cwd, env=env,
                          capture_output=True, text=True)
    assert done.returncode == expect, (done.stdout, done.stderr)
    return done


def run_queue(env: dict[str, str], cwd: Path) -> None:
    done = subprocess.run([sys.executable, str(FAKE_SLURM / "fake_slurm.py"), "run"], cwd=cwd, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, (done.stdout, done.stderr)


def assert_same_as_serial(study: Path, serial_study: Path) -> None:
    record, samples = final_run(study)
    expected, expected_samples = final_run(serial_study)
    assert comparable(record) == comparable(expected)
    assert samples.keys() == expected_samples.keys()
    for level, arrays in samples.items():
        for got, want in zip(arrays, expected_samples[level]):
            np.testing.assert_array_equal(got, want)


def test_slurm_study_survives_a_lost_task_and_matches_serial(serial, tmp_path):
    config, serial_study = serial
    # A one-core node whose partition allows 4 minutes: the screening must ask
    # for one core (the stand-in refuses more) and no shard for more than 4 minutes.
    env = environment(tmp_path, FAKE_SLURM_CPUS="1", FAKE_SLURM_TIMELIMIT="00:04:00", FAKE_SLURM_KILL="2")
    out = bash("slurm_study.sh", str(config), TOL, "study.h5", CHUNK, cwd=tmp_path, env=env).stdout
    assert "submitted the screening" in out and not (tmp_path / "study.h5").exists()  # nothing runs yet
    run_queue(env, tmp_path)

    assert_same_as_serial(tmp_path / "study.h5", serial_study)
    logs = tmp_path / "logs"
    assert any("node lost" in p.read_text() for p in logs.glob("shard-*.out"))
    assert any(re.search(r"1 of \d+ shards failed", p.read_text()) for p in logs.glob("next-*.out"))
    assert "tolerance met" in max(logs.glob("next-*.out"), key=lambda p: int(p.stem[5:])).read_text()
    assert not list((tmp_path / "study.shards").glob("shard-*"))

    jobs = [json.loads(line)["options"] for line in (tmp_path / "spool" / "submitted.jsonl").read_text().splitlines()]
    (screening,) = [job for job in jobs if job.get("job-name") == "roughuq-screen"]
    assert screening["cpus-per-task"] == "1"
    arrays = [job for job in jobs if "array" in job]
    assert len(arrays) >= 4   # three levels in the first round, the lost shard and more in the next
    for job in arrays:
        assert job["time"] == "4"   # 5-minute floor capped at the partition's limit
        assert job["mem"].endswith("M") and 256 < int(job["mem"][:-1]) < 1024


def test_slurm_study_gives_up_after_failed_rounds(serial, tmp_path):
    config, serial_study = serial
    shutil.copy(serial_study, tmp_path / "study.h5")   # screened (and estimated at TOL: plan another tol)
    env = environment(tmp_path, FAKE_SLURM_CPUS="1", FAKE_SLURM_KILL=",".join(str(n) for n in range(1, 40)))
    bash("slurm_study.sh", "--retries", "2", str(config), "1.5", "study.h5", "1000", cwd=tmp_path, env=env)
    run_queue(env, tmp_path)
    texts = [p.read_text() for p in sorted((tmp_path / "logs").glob("next-*.out"))]
    assert len(texts) == 2
    assert "2 rounds in a row had failed jobs" in texts[-1]


def test_loop_study_survives_a_killed_shard_and_matches_serial(serial, tmp_path):
    config, serial_study = serial
    env = environment(tmp_path, KILL_SAMPLES="2")
    done = bash("loop_study.sh", "--workers", "1", str(config), TOL, "study.h5", CHUNK, cwd=tmp_path, env=env)
    assert "planned again next round" in done.stderr
    assert_same_as_serial(tmp_path / "study.h5", serial_study)
    assert not list((tmp_path / "study.shards").glob("shard-*"))


@pytest.mark.slow
def test_quickstart_on_slurm_and_loop_matches_serial(tmp_path):
    """The issue's case: the quickstart at tol 0.3, a lost task, 2-core nodes (minutes)."""
    config = ROOT / "rough_uq" / "study" / "configs" / "quickstart.yaml"
    serial_study = tmp_path / "serial.h5"
    run_cli("screen", str(config), "--out", str(serial_study), "--workers", "1", "--quiet")
    run_cli("mlmc", "--study", str(serial_study), "--tol", "0.3", "--workers", "1", "--quiet")
    env = environment(tmp_path, FAKE_SLURM_CPUS="2", FAKE_SLURM_KILL="3")
    bash("slurm_study.sh", str(config), "0.3", "slurm.h5", "20", cwd=tmp_path, env=env)
    run_queue(env, tmp_path)
    assert_same_as_serial(tmp_path / "slurm.h5", serial_study)
    bash("loop_study.sh", "--jobs", "2", str(config), "0.3", "loop.h5", "20", cwd=tmp_path, env=env)
    assert_same_as_serial(tmp_path / "loop.h5", serial_study)


def test_plan_resources_columns(serial, tmp_path):
    config, serial_study = serial
    study = tmp_path / "study.h5"
    shutil.copy(serial_study, study)
    # 1.5: the smallest tolerance the screening reaches on these grids is about 1.2
    lines = run_cli("mlmc", "--study", str(study), "--tol", "1.5", "--plan", "--shards", "50", "--resources")
    rows = [line.split() for line in lines.splitlines()]
    assert rows and all(len(row) == 5 for row in rows)
    seconds = {int(row[1]): int(row[3]) for row in rows}
    memory = {int(row[1]): int(row[4]) for row in rows}
    assert all(s >= STARTUP_SECONDS for s in seconds.values())
    assert sorted(memory) == [0, 1, 2] and memory[0] <= memory[1] <= memory[2]
    assert memory[0] * 2**20 > BASE_BYTES
    result = CliRunner().invoke(main, ["mlmc", "--study", str(study), "--tol", "1.5", "--plan", "--resources"])
    assert result.exit_code == 2 and "--resources" in result.output


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_stops_loop_study(serial, tmp_path, jobs):
    """Ctrl-C stopped the running shard (status 130), which the loop took for a failed shard: it went on to the end.

    The shim sends SIGINT to the whole process group, as a terminal's Ctrl-C does, while the second shard runs.
    """
    config, _ = serial
    env = environment(tmp_path, INTERRUPT_SAMPLE="2")
    args = ["bash", str(ROOT / "scripts" / "loop_study.sh"), "--jobs", jobs, "--workers", "1", str(config), TOL,
            "study.h5", CHUNK]
    # A session of its own: the group's SIGINT must not reach pytest.
    done = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, start_new_session=True)
    shim_log = (tmp_path / "sample-count.log").read_text()  # which samples ran, whether the SIGINT was sent
    assert done.returncode == 130, (done.stdout, done.stderr, shim_log)
    assert "loop_study.sh: stopped; run the same command to continue" in done.stderr
    assert "planned again" not in done.stderr
    with open_study_readonly(tmp_path / "study.h5") as store:
        assert store.read_runs() == []  # the loop did not go on to the estimate
    # The same command then continues as after a killed shard (test_loop_study_survives_a_killed_shard_...).


def test_slurm_study_checks_the_config_before_submitting(tmp_path):
    """A typo in the config name was submitted (exit 0) and failed in three screening jobs, one queue wait each."""
    env = environment(tmp_path)
    done = bash("slurm_study.sh", "nope.yaml", "0.3", "study.h5", cwd=tmp_path, env=env, expect=1)
    assert "nope.yaml is not a valid config (see above); nothing was submitted" in done.stderr
    assert "nope.yaml" in done.stderr.splitlines()[0]  # roughuq validate's own line first
    assert not (tmp_path / "spool").exists() or not any((tmp_path / "spool").iterdir())


def test_loop_study_ends_with_the_status_of_its_run(serial, tmp_path):
    """A run that missed its tolerance (status 3) ended the loop with status 0: a shell caller could not tell."""
    config, _ = serial
    env = environment(tmp_path, NOT_MET="1")
    done = bash("loop_study.sh", "--workers", "1", str(config), TOL, "study.h5", CHUNK, cwd=tmp_path, env=env,
                expect=3)
    assert "loop_study.sh" not in done.stderr  # not an error of the script's own


def _session_processes(sid: int) -> list[str]:
    """The live processes of session ``sid`` (not zombies, which a container's init may never reap)."""
    listing = subprocess.run(["ps", "-o", "sid=,stat=,args=", "-e"], capture_output=True, text=True).stdout
    rows = [line.split(None, 2) for line in listing.splitlines()]
    return [row[2] for row in rows if len(row) == 3 and row[0] == str(sid) and not row[1].startswith("Z")]


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_sigterm_to_loop_study_alone_stops_its_running_shards(serial, tmp_path, jobs):
    """`kill PID` (or `timeout`) on the script: with --jobs 1 the shard ran to its end before the loop stopped."""
    config, _ = serial
    env = environment(tmp_path, SLOW_SAMPLES="1")
    args = ["bash", str(ROOT / "scripts" / "loop_study.sh"), "--jobs", jobs, "--workers", "1", str(config), TOL,
            "study.h5", CHUNK]
    process = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not any(p.startswith("sleep 60") for p in _session_processes(process.pid)):
            assert time.monotonic() < deadline and process.poll() is None, process.communicate()
            time.sleep(0.2)
        start = time.monotonic()
        process.send_signal(signal.SIGTERM)  # to the script only, not to its process group
        _, stderr = process.communicate(timeout=30)
        assert process.returncode == 143 and time.monotonic() - start < 10, stderr
        assert "loop_study.sh: stopped; run the same command to continue" in stderr
        assert _session_processes(process.pid) == []
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()

"""FFTW wisdom on disk: measured once per machine and grid, and said so when it is measured."""

from __future__ import annotations

import json
import os

import pyfftw
import pytest

from rough_uq.physics import fft as fft_module
from rough_uq.study.executors import SerialExecutor
from rough_uq.study.fft_wisdom import _save, load_wisdom, prepare_wisdom, wisdom_entries
from rough_uq.study.pipeline import Study, run_screening
from rough_uq.study.config import config_from_dict
from rough_uq.study.progress import Progress
from rough_uq.study.store import MemoryStore
from tests.study_configs import tiny_config


@pytest.fixture
def fresh_wisdom(tmp_path, monkeypatch):
    # A machine that has measured nothing yet: no file, nothing in this process.
    path = tmp_path / "wisdom.json"
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", str(path))
    pyfftw.forget_wisdom()
    yield path
    fft_module.use_wisdom(None)


def test_plans_are_measured_once_per_grid_and_the_measuring_is_announced(fresh_wisdom):
    notes: list[str] = []
    first = prepare_wisdom([16], threads=1, note=notes.append)
    assert notes == [f"measuring FFT plans for 16x16 (once per machine, kept in {fresh_wisdom})"]
    assert load_wisdom(fresh_wisdom) == first
    # Another process of the machine (nothing in memory) finds them on disk: nothing to measure, say or write.
    pyfftw.forget_wisdom()
    written = fresh_wisdom.stat().st_ino  # a rewrite replaces the file
    assert wisdom_entries(prepare_wisdom([16], threads=1, note=notes.append)) == wisdom_entries(first)
    assert len(notes) == 1
    assert fresh_wisdom.stat().st_ino == written
    # Only the grid it lacks is measured and named.
    pyfftw.forget_wisdom()
    prepare_wisdom([16, 24], threads=1, note=notes.append)
    assert notes[1:] == [f"measuring FFT plans for 24x24 (once per machine, kept in {fresh_wisdom})"]


@pytest.mark.parametrize("where", ["a directory", "under a file"])
def test_a_wisdom_file_that_cannot_be_written_is_said_once_measured(fresh_wisdom, monkeypatch, where):
    # ROUGHUQ_FFTW_WISDOM=/proc/nope/w.json: "measuring FFT plans ... kept in /proc/nope/w.json" on every command,
    # nothing kept and nothing said.
    if where == "a directory":
        unwritable = fresh_wisdom.parent
    else:
        fresh_wisdom.write_text("not a directory")
        unwritable = fresh_wisdom / "w.json"
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", str(unwritable))
    notes: list[str] = []
    prepare_wisdom([16], threads=1, note=notes.append)
    assert len(notes) == 2 and notes[0].startswith("measuring FFT plans for 16x16")
    assert notes[1].startswith(f"warning: the measured FFT plans could not be kept in {unwritable} (")
    assert notes[1].endswith("every command measures them again; set ROUGHUQ_FFTW_WISDOM to a writable file (or to "
                             "'estimate': no measured plans)")


@pytest.mark.parametrize("setting", ["ESTIMATE", "Estimate", " estimate"])
def test_estimate_in_any_case_turns_measured_planning_off(fresh_wisdom, monkeypatch, setting):
    # "ESTIMATE" measured plans and wrote them to a file of that name in the working directory.
    monkeypatch.chdir(fresh_wisdom.parent)
    monkeypatch.setenv("ROUGHUQ_FFTW_WISDOM", setting)
    assert prepare_wisdom([16], threads=1, note=None) is None
    assert os.listdir(fresh_wisdom.parent) == []


def test_plans_measured_before_a_ctrl_c_are_kept_on_disk(fresh_wisdom, monkeypatch):
    # Ctrl-C while "measuring FFT plans" threw every measured plan away: each rerun measured them all again.
    measure = fft_module._plan_variant
    grids: list[int] = []

    def interrupted_at_24(n, variant, flags, **options):
        if "FFTW_WISDOM_ONLY" not in flags:  # measuring, not looking up
            if n == 24:
                raise KeyboardInterrupt
            grids.append(n)
        return measure(n, variant, flags, **options)

    monkeypatch.setattr(fft_module, "_plan_variant", interrupted_at_24)
    with pytest.raises(KeyboardInterrupt):
        prepare_wisdom([16, 24], threads=1)
    assert set(grids) == {16}
    monkeypatch.setattr(fft_module, "_plan_variant", measure)
    pyfftw.forget_wisdom()  # the next process
    notes: list[str] = []
    prepare_wisdom([16, 24], threads=1, note=notes.append)
    assert notes == [f"measuring FFT plans for 24x24 (once per machine, kept in {fresh_wisdom})"]


def test_measure_plans_names_the_missing_grids_before_measuring(fresh_wisdom):
    calls: list[list[int]] = []
    wisdom = fft_module.measure_plans([24, 16], threads=1, before_measuring=calls.append)
    assert calls == [[16, 24]]
    fft_module.measure_plans([16, 24], threads=1, wisdom=wisdom, before_measuring=calls.append)
    assert calls == [[16, 24]]


class _Notes(Progress):
    def __init__(self) -> None:
        self.notes: list[str] = []

    def note(self, text: str) -> None:
        self.notes.append(text)


def test_a_screening_says_when_it_measures_plans_and_not_when_they_are_known(fresh_wisdom):
    config = config_from_dict(tiny_config())
    progress = _Notes()
    run_screening(Study(config, MemoryStore(qoi_names=config.qoi_names)), executor=SerialExecutor(), progress=progress)
    measuring = [text for text in progress.notes if text.startswith("measuring FFT plans")]
    assert measuring and all(str(fresh_wisdom) in text for text in measuring)
    again = _Notes()
    pyfftw.forget_wisdom()
    run_screening(Study(config, MemoryStore(qoi_names=config.qoi_names)), executor=SerialExecutor(), progress=again)
    assert not [text for text in again.notes if text.startswith("measuring FFT plans")]


@pytest.mark.parametrize(
    "content",
    [
        b"\x80\x04\x95 not json",  # e.g. the pickle of earlier versions
        b"{\"format\": \"roughuq-fftw-wisdom\", \"version\": 2, \"wisdom\": []}",
        b"{\"format\": \"roughuq-fftw-wisdom\", \"version\": 1, \"wisdom\": [1, 2]}",
        b"[]",
        b"\xff\xfe",
        pytest.param(b"[" * 100000 + b"]" * 100000, id="deep"),  # json recursed per level: a RecursionError
    ],
)
def test_a_file_that_is_not_wisdom_of_this_version_is_ignored_and_replaced(fresh_wisdom, content):
    fresh_wisdom.write_bytes(content)
    assert load_wisdom(fresh_wisdom) is None
    notes: list[str] = []
    wisdom = prepare_wisdom([16], threads=1, note=notes.append)
    assert len(notes) == 1 and load_wisdom(fresh_wisdom) == wisdom


def test_the_wisdom_file_is_json_and_round_trips_every_byte(fresh_wisdom):
    wisdom = (b"(fftw-3.3.10 fftw_wisdom)\n", bytes(range(256)), b"")
    _save(fresh_wisdom, wisdom)
    assert json.loads(fresh_wisdom.read_text())["format"] == "roughuq-fftw-wisdom"
    assert load_wisdom(fresh_wisdom) == wisdom


def test_a_failed_write_leaves_no_temporary_file(tmp_path):
    target = tmp_path / "wisdom.json"
    target.mkdir()  # os.replace cannot put a file there
    _save(target, (b"(fftw-3.3.10 fftw_wisdom)\n",))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["wisdom.json"]


def test_a_process_waits_for_another_measuring_and_plans_from_its_wisdom(tmp_path):
    """Two processes measuring one grid at once (the shards of `loop_study.sh --jobs 2` on a machine without
    wisdom) could choose different plans, which round differently. Process A holds the lock, measures and writes;
    process B, started meanwhile, waits, says so, and measures nothing: it plans from A's wisdom."""
    import subprocess
    import sys
    import time

    path = tmp_path / "wisdom.json"
    locked, go = tmp_path / "locked", tmp_path / "go"
    holder = ("import fcntl, sys, time\n"
              "from pathlib import Path\n"
              "from rough_uq.physics.fft import measure_plans\n"
              "from rough_uq.study.fft_wisdom import _save\n"
              f"path, locked, go = Path({str(path)!r}), Path({str(locked)!r}), Path({str(go)!r})\n"
              "with open(str(path) + '.lock', 'a') as handle:\n"
              "    fcntl.flock(handle, fcntl.LOCK_EX)\n"
              "    locked.touch()\n"
              "    while not go.exists():\n"
              "        time.sleep(0.02)\n"
              "    _save(path, measure_plans([16], threads=1))\n")
    waiter = ("import sys\n"
              "from rough_uq.study.fft_wisdom import load_wisdom, prepare_wisdom, wisdom_entries\n"
              "def note(text):\n"
              "    print(text, flush=True)\n"
              "wisdom = prepare_wisdom([16], threads=1, note=note)\n"
              f"print(wisdom_entries(wisdom) == wisdom_entries(load_wisdom({str(path)!r})), flush=True)\n")
    env = {**os.environ, "ROUGHUQ_FFTW_WISDOM": str(path)}
    a = subprocess.Popen([sys.executable, "-c", holder], env=env)
    try:
        deadline = time.monotonic() + 60
        while not locked.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        b = subprocess.Popen([sys.executable, "-c", waiter], env=env, stdout=subprocess.PIPE, text=True)
        first = b.stdout.readline()
        go.touch()
        rest = b.communicate(timeout=120)[0]
    finally:
        a.wait(timeout=120)
    assert first == f"waiting for another roughuq process measuring FFT plans (kept in {path})\n"
    assert rest == "True\n"  # no "measuring FFT plans": A's plans, read under the lock
    assert a.returncode == 0 and b.returncode == 0

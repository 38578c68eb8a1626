"""The real CLI through click's CliRunner, on a tiny study: the commands users run."""

from __future__ import annotations

import errno
import filecmp
import json
import math
import os
import re
import shutil
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rough_uq import __version__
from rough_uq.cli import main
from rough_uq.errors import StudyFileError
from rough_uq.study.store import FORMAT_VERSION, open_study_readonly
from tests.study_configs import tiny_config, write_config

ROOT = Path(__file__).resolve().parent.parent
BAD = sorted((ROOT / "tests" / "data" / "bad_configs").glob("*.yaml"))


def run(*args: str, expect: int = 0) -> object:
    result = CliRunner().invoke(main, list(args))
    assert result.exit_code == expect, (result.output, result.stderr, result.exception)
    return result


@pytest.fixture
def screened(tmp_path, monkeypatch):
    """A tiny study screened into results.h5 in a fresh working directory."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    run("screen", str(config), "--workers", "1", "--quiet")
    return tmp_path


def test_a_solve_beyond_the_memory_is_one_line_and_the_run_resumes(screened, monkeypatch):
    # A grid the machine could not hold (after the forecast's warning) ended in numpy's _ArrayMemoryError
    # traceback, status 1, which the CLI reserves for bugs.
    import rough_uq.problem.sampler as sampler_module

    solve = sampler_module._solve

    def out_of_memory(model, heights, initial):
        if heights.shape[0] >= 32:
            raise MemoryError("Unable to allocate 2.00 GiB for an array with shape (16384, 16384) and data type "
                              "float64")
        return solve(model, heights, initial)

    monkeypatch.setattr(sampler_module, "_solve", out_of_memory)
    result = run("mc", "--level", "2", "--tol", "0.5", "--workers", "1", "--quiet", expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    line = lines[0]
    assert line.startswith("error: Unable to allocate 2.00 GiB for an array with shape (16384, 16384)"), line
    assert "allowed: grids whose solves fit the machine's memory" in line and "completed samples are saved" in line
    monkeypatch.setattr(sampler_module, "_solve", solve)
    report = json.loads(run("report", "results.h5", "--json").output)
    assert [r["status"] for r in report["runs"]] == ["interrupted"]
    run("mc", "--level", "2", "--tol", "0.5", "--workers", "1", "--quiet")


def test_version_and_help():
    assert __version__ in run("--version").output
    output = run("--help").output
    for command in ("screen", "mlmc", "mc", "report", "validate", "solve"):
        assert command in output


def test_validate_and_solve_demo(tmp_path):
    config = write_config(tmp_path / "tiny.yaml", tiny_config(qoi={"contact_area": {}, "clusters": {}}))
    assert "valid" in run("validate", str(config)).output
    output = run("solve", str(config), "--level", "1").output
    assert "grid 16 x 16" in output and "contact_area" in output and "clusters" in output
    assert "converged" in output and "NOT" not in output


def test_screen_prints_table_rates_and_predictions(screened):
    result = run("report", "results.h5")
    for text in ("Screening", "alpha", "beta", "gamma", "Predicted from the screening"):
        assert text in result.output
    with open_study_readonly(screened / "results.h5") as store:
        assert [store.sample_indices(level=level, stage=0).size for level in range(3)] == [8, 8, 8]


def test_mlmc_mc_and_report_json_agree_with_the_file(screened):
    run("mlmc", "--tol", "5", "--workers", "1", "--quiet")
    run("mlmc", "--tol", "contact_area=4", "--workers", "1", "--quiet")
    mc = json.loads(run("mc", "--tol", "5", "--workers", "1", "--json").output)
    report = json.loads(run("report", "results.h5", "--json").output)
    runs = {run_["run_id"]: run_ for run_ in report["runs"]}
    assert set(runs) == {"mlmc_contact_area-5_theta-0.5", "mlmc_contact_area-4_theta-0.5",
                         "mc_contact_area-5_theta-0.5"}
    assert runs["mc_contact_area-5_theta-0.5"]["estimate"] == mc["estimate"]
    with open_study_readonly(screened / "results.h5") as store:
        for run_ in store.read_runs():
            assert runs[run_["run_id"]]["estimate"] == run_["estimate"]
            assert runs[run_["run_id"]]["n_samples"] == run_["n_samples"]
        for run_ in runs.values():
            stored = sum(store.sample_indices(level=level, stage=run_["stage"]).size for level in store.levels())
            assert stored == sum(run_["n_samples"])
    assert "measured_ratio" in runs["mlmc_contact_area-5_theta-0.5"]
    assert report["screening"]["complexity"][0]["mc_exponent"] > 2
    text = run("report", "results.h5").output
    assert "Estimation runs" in text and "mlmc" in text


def test_rerunning_a_finished_run_computes_nothing(screened):
    first = json.loads(run("mlmc", "--tol", "5", "--workers", "1", "--json").output)
    again = json.loads(run("mlmc", "--tol", "5", "--workers", "1", "--json").output)
    assert again["n_computed"] == 0
    assert again["estimate"] == first["estimate"]


def test_plan_lists_missing_samples_without_computing(screened):
    before = (screened / "results.h5").read_bytes()
    plan = json.loads(run("mlmc", "--tol", "5", "--plan", "--json").output)
    assert plan["run_id"] == "mlmc_contact_area-5_theta-0.5" and plan["stage"] % 2 == 1
    rows = plan["levels"]
    assert [row["level"] for row in rows] == [0, 1, 2]
    assert all(row["n_missing"] > 0 and row["indices"] == [f"0:{row['n_missing']}"] for row in rows)
    assert (screened / "results.h5").read_bytes() == before
    assert "level 0:" in run("mlmc", "--tol", "5", "--plan").output


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_config_is_one_line_and_status_2(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for command in ("validate", "screen"):
        result = run(command, str(path), expect=2)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
        assert result.exception is None or isinstance(result.exception, SystemExit)
    assert not (tmp_path / "results.h5").exists()


def test_user_errors_are_one_line_and_status_2(screened):
    cases = [
        ("mlmc", "--tol", "5", "--study", "missing.h5"),
        ("mlmc", "--tol", "-1"),
        ("mlmc", "--tol", "area=1"),
        ("report", "missing.h5"),
    ]
    (screened / "not_hdf5.h5").write_text("hello")
    cases.append(("report", "not_hdf5.h5"))
    for args in cases:
        result = run(*args, expect=2)
        assert len(result.stderr.strip().splitlines()) == 1 and result.stderr.startswith("error: "), args
    # report takes the file as its argument: the remedy named --study and --config, which it does not have.
    line = run("report", "missing.h5", expect=2).stderr.strip()
    assert line.startswith("error: study file 'missing.h5' does not exist; name one that `roughuq screen` or a run")
    assert "--study" not in line and "--config" not in line


def test_study_from_another_config_is_refused_and_untouched(screened):
    before = (screened / "results.h5").read_bytes()
    other = write_config(screened / "other.yaml", tiny_config(seed=1))
    result = run("screen", str(other), expect=2)
    assert "another config" in result.stderr or "different config" in result.stderr
    result = run("mlmc", "--tol", "1", "--config", str(other), expect=2)
    assert "another config" in result.stderr and "differs in seed: 2026 in the file, 1 in this config" in result.stderr
    assert (screened / "results.h5").read_bytes() == before


def test_estimation_before_screening_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config(screening={"levels": 3, "samples": 4}))
    from rough_uq.study.config import load_config
    from rough_uq.study.pipeline import create_study

    create_study(load_config(config)).close()
    result = run("mlmc", "--tol", "1", expect=2)
    assert "roughuq screen" in result.stderr


def test_stored_samples_are_what_the_cli_reports(screened):
    record = json.loads(run("mlmc", "--tol", "5", "--workers", "1", "--json").output)
    with h5py.File(screened / "results.h5", "r") as f:
        fine = [f[f"samples/level_{level}/fine"][:] for level in record["levels"]]
        stage = [f[f"samples/level_{level}/stage"][:] for level in record["levels"]]
        coarse = [f[f"samples/level_{level}/coarse"][:] for level in record["levels"]]
    own = [s == record["stage"] for s in stage]
    estimate = sum(np.mean(f_[k, 0] - c[k, 0]) for f_, c, k in zip(fine, coarse, own))
    assert estimate == pytest.approx(record["estimate"][0], rel=1e-12)


def test_piped_report_keeps_each_line_of_text_whole(screened, monkeypatch):
    # Piped (not a terminal, no COLUMNS), lines of text are not broken at the console's width: the sample counts of
    # many runs stay on one line, whole, for grep and copy-paste.
    monkeypatch.delenv("COLUMNS", raising=False)
    for tol in ("5", "4", "3", "2.5", "2"):
        assert CliRunner().invoke(main, ["mlmc", "--tol", tol, "--workers", "1", "--quiet"]).exit_code in (0, 3)
    output = run("report", "results.h5").output
    (line,) = [line for line in output.splitlines() if line.startswith("samples stored:")]
    run_ids = [entry["run_id"] for entry in json.loads(run("report", "results.h5", "--json").output)["runs"]]
    assert len(line) > 160 and len(run_ids) == 5
    for run_id in run_ids:
        assert f"{run_id}: L" in line


def test_shards_in_any_order_merge_to_the_serial_result(screened, tmp_path):
    """The cluster workflow: plan, compute shards (out of order), merge, repeat; then mlmc computes nothing."""
    reference = json.loads(run("mlmc", "--tol", "5", "--study", "results.h5", "--workers", "1", "--json").output)
    copy = screened / "cluster.h5"
    config = write_config(screened / "tiny2.yaml", tiny_config())
    run("screen", str(config), "--out", str(copy), "--workers", "1", "--quiet")
    n_rounds = 0
    while True:
        plan = json.loads(run("mlmc", "--tol", "5", "--study", str(copy), "--plan", "--json").output)
        if plan["n_missing"] == 0:
            break
        n_rounds += 1
        shards = []
        for row in plan["levels"]:
            indices = [i for part in row["indices"] for i in range(*map(int, part.split(":")))]
            thirds = [indices[k::3] for k in range(3)]
            for k in (2, 0, 1):  # in a different order than the indices
                if not thirds[k]:
                    continue
                shard = screened / f"shard-{n_rounds}-{row['level']}-{k}.h5"
                text = ",".join(str(i) for i in thirds[k])
                run("sample", "--study", str(copy), "--stage", str(plan["stage"]), "--level", str(row["level"]),
                    "--indices", text, "--out", str(shard), "--workers", "1", "--quiet")
                shards.append(str(shard))
        result = run("merge", *reversed(shards), "--into", str(copy))
        assert "added" in result.output
        assert n_rounds < 10
    # Merging a shard twice never double-counts.
    result = run("merge", shards[0], "--into", str(copy))
    assert "skipped" in result.stderr and "added 0 samples from 1 shard\n" in result.output
    final = json.loads(run("mlmc", "--tol", "5", "--study", str(copy), "--workers", "1", "--json").output)
    assert final["n_computed"] == 0
    for key in ("estimate", "stat_error", "bias_estimate", "n_samples", "cost"):
        assert final[key] == reference[key], key
    assert not list(screened.glob("*.partial-*"))


def _sample(*extra: str, out: str = "shard.h5", expect: int = 0) -> object:
    return run("sample", "--study", "results.h5", "--stage", "screening", "--level", "0", "--indices", "100:103",
               "--out", out, "--workers", "1", *extra, expect=expect)


def test_a_stopped_shard_says_that_nothing_was_written(screened, ctrl_c_after_one_sample):
    """Ctrl-C on `sample` said 'every completed sample is saved' and deleted them: a shard is written whole or not."""
    result = _sample("--quiet", expect=130)
    last = result.stderr.strip().splitlines()[-1]
    assert last == ("interrupted: nothing was written (a shard is written whole or not at all); run the same "
                    "command to compute it: roughuq sample --study results.h5 --stage screening --level 0 --indices "
                    "100:103 --out shard.h5 --workers 1 --quiet")
    assert not list(screened.glob("shard.h5*"))


def test_a_stopped_run_spells_the_command_that_continues_it(screened, ctrl_c_after_one_sample):
    # "run the same command to continue" left the command to memory: the same command without its --config (another
    # theta) started another run, and the stopped run's samples went unused.
    (screened / "my config.yaml").write_text((screened / "tiny.yaml").read_text())
    result = run("mlmc", "--config", "my config.yaml", "--tol", "5", "--study", "results.h5", "-q", expect=130)
    assert result.stderr.strip().splitlines()[-1] == ("interrupted: every completed sample is saved; run the same "
                                                      "command to continue: roughuq mlmc --config 'my config.yaml' "
                                                      "--tol 5 --study results.h5 -q")


def test_an_existing_out_file_is_refused_with_advice_that_fits_what_it_is(screened):
    # Every existing --out read "shard ... already exists; merge or remove it first": for a study with a screening
    # or runs, that advised deleting its results.
    shutil.copy("results.h5", "other study.h5")
    Path("junk.h5").write_text("not a study")
    _sample(out="shard.h5")
    outs = ("other study.h5", "junk.h5", "shard.h5")
    lines = {out: _sample(out=out, expect=2).stderr.strip() for out in outs}
    assert lines["other study.h5"] == ("error: --out 'other study.h5' is a study file with results (a screening or "
                                       "runs), not a shard; choose another --out")
    assert lines["junk.h5"] == ("error: --out 'junk.h5' exists and is not a shard (not a study file); choose another "
                                "--out")
    assert lines["shard.h5"] == ("error: shard 'shard.h5' already exists; merge it (roughuq merge shard.h5 --into "
                                 "STUDY) or remove it first")


def test_an_existing_out_study_without_records_is_not_called_a_shard(screened, ctrl_c_after_one_sample):
    # A study whose first screening was stopped has samples but no record: it read "shard 'stopped.h5' already
    # exists; merge it ... or remove it first".
    write_config(screened / "stopped.yaml", tiny_config(output={"path": "stopped.h5"}))
    run("screen", "stopped.yaml", "--workers", "1", "-q", expect=130)
    assert _sample(out="stopped.h5", expect=2).stderr.strip() == (
        "error: --out 'stopped.h5' is a study file, not a shard; choose another --out")


def test_sample_refuses_to_write_into_the_study_itself(screened):
    """`--out` = `--study` read "shard 'results.h5' already exists; merge or remove it first": remove the study."""
    os.link("results.h5", "linked.h5")  # the same file under another name
    for out in ("results.h5", "./results.h5", str(screened / "results.h5"), "linked.h5"):
        line = _sample(out=out, expect=2).stderr.strip()
        assert line == f"error: --out: got {out!r}; allowed: a new shard file, not the study file (--study) itself"


def test_a_shard_removes_what_a_killed_run_of_it_left_and_nothing_another_process_holds(screened):
    """`kill -9` left shard.h5.partial-PID and its .lock; reruns wrote new ones beside them; `merge dir/*` failed."""
    from rough_uq.study.store import _acquire_lock, _release_lock

    hour_ago = time.time() - 3600
    for name in ("shard.h5.partial-999999", "shard.h5.partial-999999.lock", "shard.h5.partial-999998.lock"):
        (screened / name).write_text("left by a killed process\n")
        os.utime(screened / name, (hour_ago, hour_ago))
    held = screened / "shard.h5.partial-1"
    held.write_text("being written\n")
    os.utime(held, (hour_ago, hour_ago))
    # Closed (its lock free) a moment ago and about to be renamed by its writer: not abandoned.
    (screened / "shard.h5.partial-2").write_text("just closed\n")
    fd = _acquire_lock(held)  # as a running process holds it
    try:
        result = _sample()
    finally:
        _release_lock(held, fd)
    removed = [line for line in result.stderr.splitlines() if " removed " in line]
    assert len(removed) == 1 and removed[0].endswith(
        "removed shard.h5.partial-999999, left by a run of this shard that was killed")
    assert sorted(p.name for p in screened.glob("shard.h5*")) == ["shard.h5", "shard.h5.partial-1",
                                                                  "shard.h5.partial-2"]


def test_a_shard_written_meanwhile_under_the_same_out_is_not_replaced(screened, monkeypatch):
    # Two jobs with the same --out: both exit 0 and say "3 samples written"; the second rename replaced the first
    # one's shard, whose samples were gone.
    import rough_uq.cli as cli
    from rough_uq.study.executors import SerialExecutor

    _sample(out="other job.h5")

    class OtherJobFinishesFirst(SerialExecutor):
        n_workers = 1

        def run(self, model, items):
            shutil.copy("other job.h5", "shard.h5")  # another job with the same --out finishes now
            yield from super().run(model, items)

    monkeypatch.setattr(cli, "_executor", lambda *args: OtherJobFinishesFirst())
    kept = f"shard.{os.getpid()}.h5"
    assert _sample("--quiet", expect=2).stderr.strip() == (
        "error: shard 'shard.h5' was written by another process while this one computed its samples (two jobs with "
        f"the same --out?); this job's shard is kept as '{kept}': merge both (roughuq merge shard.h5 {kept} --into "
        "STUDY)")
    assert filecmp.cmp("shard.h5", "other job.h5", shallow=False)
    assert sorted(p.name for p in screened.glob("shard*")) == sorted(["shard.h5", kept])
    assert run("merge", kept, "--into", "results.h5").exit_code == 0


def test_a_clashing_shard_is_kept_without_replacing_a_file_and_without_hard_links_too(screened):
    # The kept name was written with os.replace, over a file of that name; and every OSError of os.link fell
    # back to a rename (an EIO or a vanished file became a traceback or a silent replace).
    from rough_uq.study.pipeline.shards import _publish_shard

    for name, content in (("out.h5", "another job's"), (f"out.{os.getpid()}.h5", "the user's")):
        Path(name).write_text(content)
    Path("a.partial-1").write_text("this job's")
    with pytest.raises(StudyFileError, match=f"is kept as 'out.{os.getpid()}-1.h5'"):
        _publish_shard(Path("a.partial-1"), Path("out.h5"))
    assert [Path(name).read_text() for name in ("out.h5", f"out.{os.getpid()}.h5", f"out.{os.getpid()}-1.h5")] == [
        "another job's", "the user's", "this job's"]
    assert not Path("a.partial-1").exists()

    def no_hard_links(source, target):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    Path("b.partial-1").write_text("shard b")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(os, "link", no_hard_links)
        _publish_shard(Path("b.partial-1"), Path("b.h5"))
        assert Path("b.h5").read_text() == "shard b" and not Path("b.partial-1").exists()
        Path("c.partial-1").write_text("shard c")
        with pytest.raises(StudyFileError, match=f"is kept as 'b.{os.getpid()}.h5'"):
            _publish_shard(Path("c.partial-1"), Path("b.h5"))
        assert Path("b.h5").read_text() == "shard b"

        def broken(source, target):
            raise OSError(errno.EIO, "Input/output error")

        patch.setattr(os, "link", broken)
        with pytest.raises(OSError, match="Input/output error"):
            _publish_shard(Path(f"b.{os.getpid()}.h5"), Path("d.h5"))
        assert not Path("d.h5").exists()


def test_a_shard_still_under_its_temporary_name_says_it_is_incomplete(screened):
    # `report shard.h5.partial-PID` said "a shard of samples ...: add them to their study with roughuq merge".
    from rough_uq.study.store import _acquire_lock, _release_lock

    _sample(out="shard.h5")
    shutil.copy("shard.h5", "shard.h5.partial-4242")
    left = [line for line in run("report", "shard.h5.partial-4242").stdout.splitlines() if "incomplete" in line]
    assert left == ["an incomplete shard, left by process 4242, which was stopped before it finished: run its "
                    "`roughuq sample ... --out shard.h5` again (which removes this file), then merge shard.h5"]
    fd = _acquire_lock(screened / "shard.h5.partial-4242")  # as its writer holds it
    try:
        text = run("report", "shard.h5.partial-4242").stdout
    finally:
        _release_lock(screened / "shard.h5.partial-4242", fd)
    assert "an incomplete shard (being written by process 4242): `roughuq sample` renames it shard.h5" in text
    assert "add them to their study with `roughuq merge --into STUDY shard.h5`" in run("report", "shard.h5").stdout


def test_a_shard_says_it_is_one_and_is_refused_as_a_study(screened):
    """`report shard.h5` said "screening not finished: run `roughuq screen CONFIG --out shard.h5`" (not a study)."""
    _sample("--quiet")
    text = run("report", "shard.h5").output
    assert text.startswith("Shard shard.h5 (created ")
    assert ("a shard of samples (written by `roughuq sample`): add them to their study with "
            "`roughuq merge --into STUDY shard.h5`") in text
    assert "roughuq screen" not in text and "screening not finished" not in text
    assert json.loads(run("report", "shard.h5", "--json").output)["role"] == "shard"
    assert json.loads(run("report", "results.h5", "--json").output)["role"] == "study"
    before = (screened / "shard.h5").read_bytes()
    refusal = ("error: shard.h5 is a shard of samples (written by `roughuq sample`), not a study: add its samples "
               "to their study with `roughuq merge --into STUDY shard.h5` and run there")
    for command in (("mlmc", "--tol", "5", "--study", "shard.h5", "--workers", "1"),
                    ("screen", "tiny.yaml", "--out", "shard.h5", "--workers", "1"),
                    ("merge", "--into", "shard.h5", "shard.h5"),
                    # Read only, they told to finish the shard's screening with `screen --out shard.h5`.
                    ("mlmc", "--tol", "5", "--study", "shard.h5", "--plan"),
                    ("mc", "--tol", "5", "--study", "shard.h5", "--plan")):
        assert run(*command, expect=2).stderr.strip().splitlines()[-1] == refusal, command
    assert (screened / "shard.h5").read_bytes() == before
    stored = json.loads(run("report", "results.h5", "--json").output)["samples"]["screening"]
    run("merge", "shard.h5")
    merged = json.loads(run("report", "results.h5", "--json").output)["samples"]["screening"]
    assert merged == {**stored, "0": stored["0"] + 3}


def test_a_screening_extension_stopped_before_its_record_is_reported(screened, ctrl_c_after_one_sample):
    # The report showed the old screening (8 samples per level) next to "samples stored: screening: L0 9 ..." and
    # no warning; mlmc --plan planned from the old screening without a word.
    write_config(screened / "more.yaml", tiny_config(screening={"levels": 3, "samples": 16}))
    run("screen", "more.yaml", "--out", "results.h5", "--workers", "1", "-q", expect=130)
    shown = json.loads(run("report", "results.h5", "--json").output)
    (warning,) = [text for text in shown["warnings"] if "screening record does not use" in text]
    assert warning.startswith("the study holds screening samples its screening record does not use: L0 9 (recorded "
                              "8); a `roughuq screen` stopped before its record leaves them")
    assert "(rerun it, `roughuq screen CONFIG --out results.h5` with its config, to take them in)" in warning


def test_report_on_a_config_says_it_is_one(screened):
    """`roughuq report tiny.yaml` said only "not an HDF5 file"."""
    line = run("report", "tiny.yaml", expect=2).stderr.strip()
    hint = ("it looks like a config: a study file is the HDF5 file `roughuq screen CONFIG` writes (the config's "
            "output.path, or --out)")
    assert line == f"error: tiny.yaml is not an HDF5 file (so not a roughuq study file); {hint}"
    # Where the config was given as the study to write, the same words hold.
    before = (screened / "tiny.yaml").read_text()
    line = run("screen", "tiny.yaml", "--out", "tiny.yaml", expect=2).stderr.strip()
    assert line == f"error: tiny.yaml is not an HDF5 file (so not a roughuq study file); {hint}"
    assert (screened / "tiny.yaml").read_text() == before
    (screened / "notes.txt").write_text("a text file\n")
    assert run("report", "notes.txt", expect=2).stderr.strip() == (
        "error: notes.txt is not an HDF5 file (so not a roughuq study file)")


def test_the_forecast_counts_the_samples_merged_shards_already_stored(screened):
    """After the shards were merged, the finishing run forecast the whole plan's time though it computed nothing."""
    plan = json.loads(run("mlmc", "--tol", "5", "--plan", "--json").output)
    for row in plan["levels"]:
        run("sample", "--study", "results.h5", "--stage", str(plan["stage"]), "--level", str(row["level"]),
            "--indices", ",".join(row["indices"]), "--out", f"shard-{row['level']}.h5", "--workers", "1", "--quiet")
        run("merge", f"shard-{row['level']}.h5")
    result = run("mlmc", "--tol", "5", "--workers", "1")
    counts = re.search(r"forecast: levels 0\.\.2 \(finest \d+\^2\), N_l ([\d ]+)\n", result.stderr).group(1)
    # The plan's first round is the samples the run asks for first: all of them are stored.
    assert [int(n) for n in counts.split()] == [row["n_missing"] for row in plan["levels"]]
    assert (f"forecast: {plan['n_missing']} samples of these are stored already (merged shards or an earlier run); "
            "about 0 s elapsed for the rest") in result.stderr.splitlines()
    record = json.loads(run("report", "results.h5", "--json").output)["runs"][0]
    assert record["forecast"]["n_stored"] == [row["n_missing"] for row in plan["levels"]]


def test_merge_refuses_a_shard_of_another_config(screened):
    other = write_config(screened / "other.yaml", tiny_config(seed=99))
    run("screen", str(other), "--out", "other.h5", "--workers", "1", "--quiet")
    run("sample", "--study", "other.h5", "--stage", "screening", "--level", "0", "--indices", "100:102",
        "--out", "foreign.h5", "--workers", "1", "--quiet")
    before = (screened / "results.h5").read_bytes()
    result = run("merge", "foreign.h5", "--into", "results.h5", expect=2)
    assert "another study" in result.stderr and "differs in seed: 99 in the shard, " in result.stderr
    assert (screened / "results.h5").read_bytes() == before
    result = run("sample", "--study", "results.h5", "--stage", "screening", "--level", "0", "--indices", "5:2",
                 "--out", "x.h5", expect=2)
    assert "--indices" in result.stderr


def test_merge_refuses_an_incomplete_shard(screened):
    # A `sample` killed mid-run leaves <shard>.partial-PID, which `report` calls incomplete; merge took it silently.
    run("sample", "--study", "results.h5", "--stage", "screening", "--level", "0", "--indices", "100:102",
        "--out", "b.h5", "--workers", "1", "--quiet")
    (screened / "b.h5").rename(screened / "b.h5.partial-4242")
    before = (screened / "results.h5").read_bytes()
    result = run("merge", "b.h5.partial-4242", "--into", "results.h5", expect=2)
    assert result.stderr.strip() == ("error: b.h5.partial-4242 is an incomplete shard (process 4242 had not finished "
                                     "it; got 'b.h5.partial-4242'; allowed: complete shards): run its `roughuq sample "
                                     "... --out b.h5` again, then merge b.h5; nothing was merged")
    assert (screened / "results.h5").read_bytes() == before


def test_sweep_box_size_at_fixed_spacing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # The spectrum in wavelengths, which stay fixed as the box grows (in wave numbers it would scale with it).
    surface = {**tiny_config()["surface"], "wavelengths": {"lambda_l": 1.0, "lambda_r": 0.5, "lambda_s": 0.125}}
    del surface["wavenumbers"]
    config = write_config(tmp_path / "tiny.yaml", tiny_config(surface=surface))
    rows = json.loads(run("sweep", str(config), "--set", "surface.system_size=1,2", "--fixed-spacing",
                          "--tol", "5", "--workers", "1", "--json").output)
    assert [row["value"] for row in rows] == ["1", "2"]
    assert [row["grid"] for row in rows] == [8, 16]  # n_0 scales with the box: same spacing
    for row in rows:
        assert row["method"] == "mc" and row["levels"] == [0] and not row["is_bias_estimated"]
        assert Path(row["study"]).exists() and Path(row["config"]).exists()
    again = json.loads(run("sweep", str(config), "--set", "surface.system_size=1,2", "--fixed-spacing",
                           "--tol", "5", "--workers", "1", "--json").output)
    assert [row["estimate"] for row in again] == [row["estimate"] for row in rows]
    assert all(row["n_computed"] == 0 for row in again)
    # The table, as the report writes a run: the QoI's unit, the estimate to the error's second digit.
    table = run("sweep", str(config), "--set", "surface.system_size=1,2", "--fixed-spacing", "--tol", "5",
                "--workers", "1", "--quiet").output
    assert "Sweep of surface.system_size (plain MC on level 0; bias not estimated)" in table
    for row in rows:
        error = row["stat_error"][0]
        decimals = max(0, 1 - math.floor(math.log10(error)))
        cell = re.escape(f"{row['estimate'][0]:.{decimals}f} ± {error:.2g}")
        assert re.search(rf"contact_area \[%\]\s+{cell}\s", table), table
    result = run("sweep", str(config), "--set", "surface.system_size=1.1", "--fixed-spacing", expect=2)
    assert "even integer" in result.stderr
    for value in ("nan", "abc", "1e400", "-2", "null"):  # the first three were tracebacks (float(), round())
        result = run("sweep", str(config), "--set", f"surface.system_size=1,{value}", "--fixed-spacing", expect=2)
        assert result.stderr.startswith(f"error: --set surface.system_size={value}: --fixed-spacing needs a box "
                                        "size (got "), result.stderr
        assert result.stderr.rstrip().endswith("allowed: a finite number > 0)") and result.stderr.count("\n") == 1
    result = run("sweep", str(config), "--set", "surface.system_size=1,1e308", "--fixed-spacing", expect=2)
    assert result.stderr.startswith("error: --fixed-spacing: box 1e+308 needs grid.coarsest = inf"), result.stderr
    result = run("sweep", str(config), "--set", "surface.colour=1", expect=2)
    assert "not a field" in result.stderr


def test_sweep_at_fixed_spacing_refuses_a_spectrum_that_grows_with_the_box(tmp_path, monkeypatch):
    """In wave numbers (periods per box) every box was the same surface magnified and resolved more finely: the
    quickstart's areas for boxes 1 and 2 (20.51, 20.34 %) differed by discretisation bias, not box size."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())  # k_l 1, k_r 2, k_s 8 at L = 1
    result = run("sweep", str(config), "--set", "surface.system_size=1,2", "--fixed-spacing", "--tol", "5",
                 expect=2)
    assert result.stderr.startswith("error: --fixed-spacing: the spectrum is given as surface.wavenumbers")
    assert "here lambda_l: 1, lambda_r: 0.5, lambda_s: 0.125)" in result.stderr
    assert not list(tmp_path.glob("sweep-*/*.h5"))  # refused before any study


def test_a_sweeps_progress_names_the_value_of_each_study(tmp_path, monkeypatch):
    # Every study's progress read "[mc contact_area=5] ...": which value was running could not be told.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = run("sweep", str(config), "--set", "load.relative=0.1,0.2", "--tol", "5", "--workers", "1")
    for value in ("0.1", "0.2"):
        assert f"[load.relative={value}: mc contact_area=5] started" in result.stderr, result.stderr


def test_a_sweep_of_a_unit_labels_its_rows_in_their_own_unit(tmp_path, monkeypatch):
    # The table took the base config's unit (%) for a row computed in fraction.
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())  # contact_area in percent
    table = run("sweep", str(config), "--set", "qoi.contact_area.unit=fraction", "--tol", "0.05", "--workers", "1",
                "--quiet").output
    assert re.search(r"fraction\s+8\s+contact_area\s+0\.\d+ ± ", table), table
    assert "[%]" not in table


def test_sweeps_of_two_fields_with_the_same_last_name_go_to_two_folders(tmp_path, monkeypatch):
    """solver.tol and qoi.contact_area.tol both went to sweep-tol/, the second refused as another study's file."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    folders = []
    for key, value, tol in (("solver.tol", "0.001", ("--tol", "5")), ("qoi.contact_area.tol", "5", ())):
        rows = json.loads(run("sweep", str(config), "--set", f"{key}={value}", *tol, "--workers", "1",
                              "--json").output)
        folders.append(Path(rows[0]["study"]).parent)
    assert folders == [Path("sweep-solver.tol"), Path("sweep-qoi.contact_area.tol")]


@pytest.mark.parametrize("options, text", [
    (("--set", "load.relative=0.1", "--set", "surface.hurst=0.7"), "one --set KEY=V1,V2,..."),
    (("--set", "load.relative=0.1,0.2,0.1"), "distinct values: 0.1 is the same as 0.1"),
    (("--set", "load.relative=0.1,1e-1"), "distinct values: 1e-1 is the same as 0.1"),
    (("--set", "output.path=a.h5,b.h5"), "a field outside output.*: the sweep names"),
    (("--set", "screening.samples=4,5"), "a field outside screening.*: a sweep runs plain MC"),
    (("--set", "qoi.contact_area.unit=fraction,percent"),
     "values that keep each QoI's unit: contact_area would be in fraction (value fraction) and in % (value percent)"),
], ids=["two --set", "a value twice", "one value written twice", "output", "screening", "a unit"])
def test_sweep_refuses_what_would_run_a_study_twice_or_sweep_nothing(tmp_path, monkeypatch, options, text):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = run("sweep", str(config), *options, "--tol", "5", "--workers", "1", expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --set: got") and text in lines[0], result.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tiny.yaml"]  # nothing computed, no folder


@pytest.mark.parametrize("tol, column", [("5", "contact_area"), ("contact_area=5", "contact_area"),
                                         ("contact_area@0.2=5", "contact_area@0.2")],
                         ids=["bare", "by name", "one column of a load curve"])
def test_sweep_refuses_a_tol_that_overrides_the_swept_qoi_tolerance(tmp_path, monkeypatch, tol, column):
    """--tol took precedence over each value of qoi.contact_area.tol: every study of the sweep ran tolerance 5."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config(load={"relative": [0.2, 0.3]}))
    result = run("sweep", str(config), "--set", "qoi.contact_area.tol=1,2", "--tol", tol, "--workers", "1", expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: --tol: got {tol!r}; allowed: no tolerance for "
                                                   f"contact_area in a sweep of qoi.contact_area.tol"), result.stderr
    assert f"every study would run {column}=5 " in lines[0]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tiny.yaml"]  # nothing computed, no folder


@pytest.mark.parametrize("options", [("--set", "seed=1,2", "--level", "3"),
                                     ("--set", "grid.max_level=2,3", "--level", "3"),
                                     ("--set", "seed=1", "--level", "99999999999999999999")])
def test_sweep_refuses_a_level_beyond_grid_max_level_before_creating_any_study(tmp_path, monkeypatch, options):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    result = run("sweep", str(config), *options, "--tol", "5", "--workers", "1", expect=2)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --level: got") and "grid.max_level" in lines[0]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tiny.yaml"]  # was a folder with a study


def test_a_sweep_folder_that_cannot_be_made_is_one_error_line(tmp_path, monkeypatch):
    # --dir below a file gave a NotADirectoryError traceback (exit 1), where the other outputs say "cannot write".
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    (tmp_path / "afile").write_text("")
    result = run("sweep", str(config), "--set", "seed=1,2", "--tol", "5", "--workers", "1", "--dir", "afile/sub",
                 expect=2)
    assert result.stderr.strip() == "error: cannot write afile/sub: Not a directory; choose another --dir"


def test_mc_on_a_given_level_needs_no_screening(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    record = json.loads(run("mc", "--config", str(config), "--level", "1", "--tol", "5", "--workers", "1",
                            "--json").output)
    assert record["levels"] == [1] and record["run_id"] if "run_id" in record else True
    assert record["stat_error"][0] <= 3 and not record["is_bias_estimated"]
    result = run("mlmc", "--level", "1", "--tol", "5", expect=2)
    assert "--level" in result.stderr


def test_mc_on_a_given_level_forecasts_the_initial_samples_it_draws(tmp_path, monkeypatch):
    """On a screened study ``mc --level`` forecast the N the screening's variance implies (3) and drew
    ``estimation.initial_samples`` (10): a ``--max-cost`` set on that forecast stopped the run short of them."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config(estimation={"initial_samples": 10, "batch_size": 4}))
    run("screen", str(config), "--workers", "1", "--quiet")
    record = json.loads(run("mc", "--level", "2", "--tol", "5", "--workers", "1", "--json").output)
    assert record["n_samples"] == [10]  # the tolerance is loose: the initial samples are the run
    assert record["forecast"]["n_samples"] == [10]


def test_the_two_forecasts_of_one_mc_run_price_its_samples_alike(screened):
    # mc --tol priced a sample at the fine solve's share of the coupled cost, mc --level at the whole coupled cost:
    # the same run (level, N) was forecast at 7.2 and 9.68 ref-s on the quickstart.
    from rough_uq.study.pipeline import forecast_run, open_existing_study

    with open_existing_study("results.h5", writable=False) as study:
        planned = forecast_run(study, method="mc", tol=np.array([5.0]))
        given = forecast_run(study, method="mc", tol=np.array([5.0]), level=planned.finest_level)
    per_sample = [f.modelled_cost / f.n_samples[0] for f in (planned, given)]
    assert per_sample[0] == pytest.approx(per_sample[1], rel=1e-12)


def test_mc_refuses_a_level_beyond_the_grids_before_forecasting_or_planning(screened):
    for extra in ([], ["--plan"]):
        result = run("mc", "--tol", "5", "--level", "99", *extra, expect=2)
        assert result.stderr.startswith("error: --level: got 99; allowed: an integer in 0..")
        assert "forecast" not in result.stderr


def test_report_plots_and_show_write_figures(screened):
    pytest.importorskip("matplotlib")
    run("mlmc", "--tol", "5", "--workers", "1", "--quiet")
    run("mc", "--tol", "5", "--workers", "1", "--quiet")
    result = run("report", "results.h5", "--plots", "figures")
    for name in ("rates.png", "cost_vs_tol.png", "samples_per_level.png"):
        path = screened / "figures" / name
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 1000
        assert name in result.output
    (screened / "sample").mkdir()  # show does not create missing directories (as init and sample)
    result = run("show", "--level", "2", "--index", "3", "--out", "sample/fig.png")
    assert (screened / "sample" / "fig.png").stat().st_size > 1000
    result = run("show", "--level", "9", "--index", "0", "--out", "x.png", expect=2)
    assert "--level" in result.stderr
    for out in ("x.pdf", "x", "x.png.svg"):  # PNG bytes were written into these
        line = run("show", "--level", "2", "--index", "3", "--out", out, expect=2).stderr.strip()
        assert line == f"error: --out: got {out!r}; allowed: a file name ending in .png (the figure is written as PNG)"
        assert not (screened / out).exists()
    run("show", "--level", "2", "--index", "3", "--out", "upper.PNG")
    assert (screened / "upper.PNG").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_show_names_the_stage_as_typed(screened, monkeypatch):
    # A run's sample was titled "sample stage 65290023461150223", its stage's hash.
    run("mlmc", "--tol", "5", "--workers", "1", "--quiet")
    (run_id,) = [entry["run_id"] for entry in json.loads(run("report", "results.h5", "--json").stdout)["runs"]]
    names = []
    monkeypatch.setattr("rough_uq.report.figures.write_sample_figure",
                        lambda **arguments: names.append(arguments["stage_name"]) or Path(arguments["path"]))
    for stage in ("screening", run_id, "0"):
        run("show", "--stage", stage, "--level", "1", "--index", "0", "--out", "s.png")
    assert names == ["the screening", f"run {run_id}", "stage 0"]


def test_show_draws_the_load_of_a_curve_that_load_names(tmp_path, monkeypatch):
    # show drew a load curve's first load only.
    pytest.importorskip("matplotlib")
    from rough_uq.report import figures

    monkeypatch.chdir(tmp_path)
    curve = [0.2, 0.02, 0.1, 0.05, 0.3]
    config = write_config(tmp_path / "curve.yaml", tiny_config(load={"relative": curve}))
    run("screen", str(config), "--workers", "1", "--quiet")
    drawn = {}
    save = figures._save
    monkeypatch.setattr(figures, "_save", lambda figure, path: drawn.setdefault(Path(path).name, figure) and
                        save(figure, path))

    def shown(out: str, *load: str) -> tuple[float, str]:
        """The mean of the drawn pressure map and the figure's title."""
        run("show", "--level", "1", "--index", "2", *load, "--out", out)
        figure = drawn[out]
        panel = next(ax for ax in figure.axes if ax.get_title().startswith("pressure"))
        return float(panel.images[0].get_array().mean()), figure.texts[0].get_text()

    first, title = shown("default.png")
    assert "load 1 of 5" in title
    for k, load in enumerate(curve):
        pressure, title = shown(f"load{k}.png", "--load", str(load))
        # The solver imposes the mean pressure: the maps scale as the relative loads.
        assert pressure / first == pytest.approx(load / curve[0], rel=1e-9)
        assert f"load {k + 1} of 5" in title and f"= {load:.3g}" in title
    for bad in ("0.5", "small"):
        line = run("show", "--level", "1", "--index", "2", "--load", bad, "--out", "x.png", expect=2).stderr.strip()
        assert line == f"error: --load: got '{bad}'; allowed: one of the study's relative loads (0.2, 0.02, 0.1, " \
                       "0.05, 0.3)"
    from rough_uq.errors import InvalidParameterError
    from rough_uq.study.pipeline import open_existing_study

    with open_existing_study(tmp_path / "results.h5", writable=False) as study:
        model = study.model_for(1)
    for bad in (5, -1, 1.0):
        with pytest.raises(InvalidParameterError, match=r"^load_index: .* an integer in 0\.\.4"):
            figures.write_sample_figure(model=model, stage=0, level=1, index=2, path="x.png", load_index=bad)


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _other_version(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1


def _garbage(path: Path) -> None:
    path.write_text("not a study")


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_truncate, "truncated or damaged"),
        (_other_version, f"format version {FORMAT_VERSION + 1}"),
        (_garbage, "not an HDF5 file"),
    ],
    ids=["truncated", "other-version", "not-hdf5"],
)
def test_bad_study_files_get_one_line_and_stay_unchanged(screened, damage, message):
    path = screened / "results.h5"
    damage(path)
    before = path.read_bytes()
    for args in (("mlmc", "--tol", "1"), ("mc", "--tol", "1"), ("report", "results.h5"),
                 ("screen", str(screened / "tiny.yaml"))):
        result = run(*args, expect=2)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (args, result.stderr)
    assert path.read_bytes() == before


def test_locked_study_is_refused_and_unchanged(screened):
    from rough_uq.study.config import load_config
    from rough_uq.study.pipeline import create_study

    before = (screened / "results.h5").read_bytes()
    with create_study(load_config(screened / "tiny.yaml")):  # another writer holds the lock
        result = run("mlmc", "--tol", "1", expect=2)
        assert "locked by a running process" in result.stderr
        assert "Screening" in run("report", "results.h5").output  # readers are never blocked
    assert (screened / "results.h5").read_bytes() == before


@pytest.mark.parametrize("kind", ["read-only directory", "file in the way"])
def test_unwritable_output_is_refused_before_any_work(tmp_path, monkeypatch, kind):
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "tiny.yaml", tiny_config())
    if kind == "read-only directory":
        if os.geteuid() == 0:
            pytest.skip("root ignores directory permissions")
        parent = tmp_path / "locked"
        parent.mkdir(mode=0o500)
    else:
        parent = tmp_path / "a-file"
        parent.write_text("")
    result = run("screen", str(config), "--out", str(parent / "study.h5"), expect=2)
    assert "study.h5" in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_a_stopped_report_says_that_it_stored_nothing(screened, monkeypatch):
    # It said "every completed sample is saved; run the same command to continue" of a report.
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("rough_uq.report.summary.read_report", interrupted)
    assert run("report", "results.h5", expect=130).stderr.strip() == "interrupted: nothing was stored"


def test_a_resumed_run_counts_the_wall_time_of_its_stopped_commands(screened, ctrl_c_after_one_sample, monkeypatch):
    # `elapsed` of a run stopped and resumed was the last command's alone (3.6 s of a run that took 7.6 s), beside
    # the CPU seconds of all its samples.
    import dataclasses

    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.study.records import read_run_records

    study_path = screened / "results.h5"
    run("mlmc", "--tol", "5", "--study", str(study_path), "-q", expect=130)
    with open_existing_study(study_path) as study:
        (stopped,) = read_run_records(study.store)
        assert stopped.status == "interrupted" and 0 < stopped.stopped_elapsed < 60
        # As if the stopped command had run for 1000 s.
        study.store.write_run(stopped.run_id, dataclasses.replace(stopped, stopped_elapsed=1000.0).to_json())
    monkeypatch.undo()  # the executor computes whole batches again
    finished = json.loads(run("mlmc", "--tol", "5", "--study", str(study_path), "--workers", "1", "--json",
                              "-q").output)
    assert 1000.0 < finished["elapsed"] < 1060.0

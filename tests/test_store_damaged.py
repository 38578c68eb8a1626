"""Damaged study files are refused within seconds, through the real CLI; a reader beside a live writer still reads.

HDF5 retries a SWMR reader's metadata read that fails (a writer may be
halfway through it) with a doubling sleep; unbounded, a damaged file held
``roughuq report`` for hours. Each command here runs in a subprocess with a
timeout, so a hang fails the test instead of hanging it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from rough_uq.study.config import load_config
from rough_uq.study.pipeline import create_study
from rough_uq.errors import StudyFileError
from rough_uq.study.store import open_study_readonly
from tests.study_configs import tiny_config, write_config
from tests.test_store import _WRITER_KEYS, _child, _writer_code, assert_same_batch, make_batch

ROOT = Path(__file__).resolve().parent.parent
# Seconds a refusal may take: it takes a few (a second per failed metadata read); a hang takes hours.
TIMEOUT = 30
# The superblock of the HDF5 1.10 file format (version 3, 8-byte addresses): signature, version, sizes, flags,
# four addresses, checksum. Byte 11 holds the flags, which mark a file held by a writer.
SUPERBLOCK_BYTES = 48
FLAGS_BYTE = 11


def _study_bytes(directory: Path) -> tuple[bytes, bytes]:
    """A tiny study file as a writer that died while appending left it (its mark set), and as it is once closed."""
    config = load_config(write_config(directory / "tiny.yaml", tiny_config()))
    path = directory / "source.h5"
    with create_study(config, path) as study:
        n_qoi = len(config.qoi_names)
        for start in (0, 5):  # the second batch is appended in place, through the writer's SWMR handle
            study.store.append_samples(make_batch(0, 0, range(start, start + 5), n_qoi=n_qoi))
        held = path.read_bytes()
    closed = path.read_bytes()
    path.unlink()
    assert held[FLAGS_BYTE] != 0 and closed[FLAGS_BYTE] == 0  # what the kinds of damage below start from
    return held, closed


def _noise(n: int) -> bytes:
    return np.random.default_rng(2026).integers(0, 256, size=n, dtype=np.uint8).tobytes()


def _marked_by_hand(closed: bytes) -> bytes:
    """The flags of a writer set in the superblock without its checksum (a file edited or damaged there)."""
    return closed[:FLAGS_BYTE] + b"\x05" + closed[FLAGS_BYTE + 1:]


DAMAGES: dict[str, Callable[[bytes, bytes], bytes]] = {
    "held-truncated": lambda held, closed: held[: len(held) // 2],
    "held-noise-after-superblock": lambda held, closed: held[:SUPERBLOCK_BYTES] + _noise(len(held) - SUPERBLOCK_BYTES),
    "marked-by-hand": lambda held, closed: _marked_by_hand(closed),
    "noise-after-signature": lambda held, closed: held[:8] + _noise(len(held) - 8),
}


@pytest.fixture(scope="module")
def study_bytes(tmp_path_factory) -> tuple[bytes, bytes]:
    return _study_bytes(tmp_path_factory.mktemp("source"))


def _roughuq(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run the CLI in a subprocess; a command still running after TIMEOUT seconds fails the test."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        return subprocess.run([sys.executable, "-m", "rough_uq.cli", *args], cwd=cwd, env=env, capture_output=True,
                              text=True, timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        pytest.fail(f"roughuq {' '.join(args)} still running after {TIMEOUT} s")


def _assert_refused_as_damaged(result: subprocess.CompletedProcess, name: str) -> None:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"error: {name} cannot be read: truncated or damaged study file")
    assert "restore the file from a copy or start a new study file" in lines[0]


def test_a_file_a_dead_writer_left_undamaged_is_read(tmp_path, study_bytes):
    # The case the retries exist for, and the control of the tests below: only the damage makes them fail.
    (tmp_path / "study.h5").write_bytes(study_bytes[0])
    result = _roughuq("report", "study.h5", cwd=tmp_path)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("damage", DAMAGES)
def test_report_refuses_a_damaged_file_quickly(tmp_path, study_bytes, damage):
    (tmp_path / "study.h5").write_bytes(DAMAGES[damage](*study_bytes))
    _assert_refused_as_damaged(_roughuq("report", "study.h5", cwd=tmp_path), "study.h5")


@pytest.mark.parametrize("damage", ["held-truncated", "marked-by-hand"])
def test_a_writing_command_refuses_a_damaged_file_quickly(tmp_path, study_bytes, damage):
    data = DAMAGES[damage](*study_bytes)
    (tmp_path / "study.h5").write_bytes(data)
    _assert_refused_as_damaged(_roughuq("drop", "some-run", "--study", "study.h5", cwd=tmp_path), "study.h5")
    assert (tmp_path / "study.h5").read_bytes() == data


def _read_while_writing(path: Path, seconds: float) -> list[int]:
    """Open ``path`` read-only again and again for ``seconds``, checking every row; the row counts seen."""
    counts = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        with open_study_readonly(path) as reader:
            n_rows = 0
            for level, stage in _WRITER_KEYS:
                stored = reader.read_samples(level=level, stage=stage)
                assert_same_batch(stored, make_batch(level, stage, range(stored.n_samples)))
                n_rows += stored.n_samples
            reader.read_runs()
        counts.append(n_rows)
    return counts


def test_a_reader_reads_while_a_writer_appends(tmp_path):
    path = tmp_path / "study.h5"
    with _child(_writer_code(path, None)) as writer:
        try:
            assert writer.stdout.readline() == "opening\n", writer.stderr.read()
            for _ in range(len(_WRITER_KEYS) + 1):  # every level exists: later batches are appended in place
                assert writer.stdout.readline(), writer.stderr.read()
            counts = _read_while_writing(path, seconds=3.0)
            assert writer.poll() is None, writer.stderr.read()  # the writer appended all along
        finally:
            writer.kill()
            writer.wait()
    assert len(counts) >= 3 and counts == sorted(counts) and counts[-1] > counts[0]



def _damage_first_chunk(path: Path, dataset: str, change: Callable[[bytes], bytes]) -> None:
    """Replace the first stored chunk of ``dataset`` by ``change`` of it, as a bad disk block or a stray write."""
    import h5py

    with h5py.File(path, "r", swmr=True, locking=False) as f:  # SWMR: a dead writer's mark may be set
        chunk = f[dataset].id.get_chunk_info(0)
    with open(path, "r+b") as file:
        file.seek(chunk.byte_offset)
        data = file.read(chunk.size)
        file.seek(chunk.byte_offset)
        file.write(change(data))


def _tiny_study(directory: Path) -> Path:
    config = load_config(write_config(directory / "tiny.yaml", tiny_config()))
    path = directory / "study.h5"
    with create_study(config, path) as study:
        n_qoi = len(config.qoi_names)
        for start in (0, 5):  # the second batch in place, through the writer's SWMR handle
            study.store.append_samples(make_batch(0, 3, range(start, start + 5), n_qoi=n_qoi))
        study.store.write_run("r", {"tol": 0.125})
    return path


@pytest.mark.parametrize("dataset", ["fine", "index", "stage", "checksum"])
@pytest.mark.parametrize("damage", ["zeroed", "one byte"])
def test_damaged_sample_rows_are_refused_not_read(tmp_path, dataset, damage):
    # HDF5 checksums its metadata only: zeroed QoI values were read as zeros (a rerun then stored a contact area
    # of 0.039 % over the good record of 19.65 %), a zeroed index column sent the user to screen again.
    path = _tiny_study(tmp_path)
    change = (lambda data: bytes(len(data))) if damage == "zeroed" else (lambda data: b"\x5a" + data[1:])
    _damage_first_chunk(path, f"samples/level_0/{dataset}", change)
    with open_study_readonly(path) as reader:
        with pytest.raises(StudyFileError, match=r"study.h5 cannot be read: truncated or damaged study file "
                           r"\(samples/level_0: \d+ of 10 rows differ from their checksums \(rows \d"):
            reader.read_samples(level=0, stage=3)


def _replaced(name: str, data: object) -> Callable[[object], None]:
    """A change of a tiny study file: the dataset ``samples/level_0/<name>`` replaced by ``data``."""
    def change(f) -> None:
        del f[f"samples/level_0/{name}"]
        f[f"samples/level_0/{name}"] = data
    return change


def _level_attribute(value: object) -> Callable[[object], None]:
    def change(f) -> None:
        f["samples/level_0"].attrs["level"] = value
    return change


def _level_as_dataset(f) -> None:
    del f["samples/level_0"]
    f["samples/level_0"] = np.arange(3)


# Files whose structure was edited by hand or damaged (a study file's checksums cover its rows' bits, not its
# layout): each crashed `report`, `mlmc` and `mc` with a traceback before, at the place the layout was relied on.
MALFORMED = {
    "level-not-a-number": (_level_attribute("abc"), "samples/level_0: its 'level' attribute is 'abc', not a non-"),
    "level-an-array": (_level_attribute(np.array([1, 2])), "samples/level_0: its 'level' attribute is array"),
    "level-of-another-group": (_level_attribute(3), "samples/level_0: its 'level' attribute is 3"),
    "level-a-dataset": (_level_as_dataset, "samples/level_0: a dataset of shape (3,) and dtype int64, not a group"),
    "index-a-string": (_replaced("index", np.bytes_(b"text")), "samples/level_0/index: a dataset of shape () and "
                       "dtype |S4, not integer values of shape (rows)"),
    "stage-float32": (_replaced("stage", np.full(10, 3, dtype=np.float32)), "samples/level_0/stage: a dataset of "
                      "shape (10,) and dtype float32, not integer values of shape (rows)"),
    "stage-too-short": (_replaced("stage", np.full(4, 3)), "samples/level_0/stage: 4 rows, fewer than the 10"),
    "fine-a-column-too-many": (_replaced("fine", np.zeros((10, 9))), "samples/level_0/fine: a dataset of shape "
                               "(10, 9) and dtype float64, not float values of shape (rows, 1)"),
    "converged-a-group": (lambda f: (f["samples/level_0"].__delitem__("converged"),
                                     f["samples/level_0"].create_group("converged")),
                          "samples/level_0/converged: a group, not boolean values of shape (rows, 2)"),
    "n_committed-a-list": (_replaced("n_committed", [10, 10]), "samples/level_0/n_committed: a dataset of shape (2,)"),
    "n_committed-negative": (_replaced("n_committed", -1), "samples/level_0/n_committed is -1, not a non-negative"),
}


@pytest.mark.parametrize("change, message", MALFORMED.values(), ids=list(MALFORMED))
def test_a_study_file_of_a_malformed_layout_is_refused_as_damaged(tmp_path, change, message):
    import h5py

    path = _tiny_study(tmp_path)
    with h5py.File(path, "r+") as f:
        change(f)
    with open_study_readonly(path) as reader:
        with pytest.raises(StudyFileError, match="study.h5 cannot be read: truncated or damaged study file") as info:
            reader.read_samples(level=0, stage=3)
    assert message in str(info.value)


def test_report_refuses_a_study_file_of_a_malformed_layout_in_one_line(tmp_path):
    import h5py

    config = load_config(write_config(tmp_path / "tiny.yaml", tiny_config()))
    with create_study(config, tmp_path / "study.h5") as study:
        study.store.append_samples(make_batch(0, 0, range(10), n_qoi=len(config.qoi_names)))
    with h5py.File(tmp_path / "study.h5", "r+") as f:
        _replaced("stage", np.full(10, 3, dtype=np.float32))(f)
    _assert_refused_as_damaged(_roughuq("report", "study.h5", cwd=tmp_path), "study.h5")


def test_a_changed_byte_of_a_record_is_refused(tmp_path):
    path = _tiny_study(tmp_path)
    _damage_first_chunk(path, "runs/r/record", lambda data: data.replace(b"0.125", b"0.725"))  # still JSON
    with open_study_readonly(path) as reader:
        with pytest.raises(StudyFileError, match="study.h5 cannot be read: truncated or damaged study file"):
            reader.read_runs()


def test_damaged_rows_in_a_file_a_dead_writer_left_are_refused_as_damaged(tmp_path, study_bytes):
    # Opened for writing, such a file is rewritten first; its rows are read for the copy, and a row that differs
    # from its checksum was reported as a failed write ("could not write ...; the study file is unchanged").
    path = tmp_path / "study.h5"
    path.write_bytes(study_bytes[0])
    _damage_first_chunk(path, "samples/level_0/cost", lambda data: data[:8] + b"\x01" + data[9:])
    damaged = path.read_bytes()
    result = _roughuq("drop", "some-run", "--study", "study.h5", cwd=tmp_path)
    _assert_refused_as_damaged(result, "study.h5")
    assert "samples/level_0: 1 of 10 rows differ from their checksums (rows 1)" in result.stderr
    assert path.read_bytes() == damaged


@pytest.mark.parametrize("altered", [(b"relative: 0.2", b"relative: 0.3"), (b"contact_area", b"contact_arex")])
def test_a_stored_config_or_qoi_name_altered_in_the_file_is_refused_as_damage(tmp_path, altered):
    # One byte of the stored config (in HDF5's global heap, which has no checksum) changed the load: a resumed run
    # mixed samples of the two loads into one estimate, and the report showed the altered load.
    config = load_config(write_config(tmp_path / "tiny.yaml", tiny_config()))
    path = tmp_path / "results.h5"
    with create_study(config, path) as study:
        study.store.append_samples(make_batch(0, 0, range(5), n_qoi=len(config.qoi_names)))
    data = path.read_bytes()
    old, new = altered
    assert data.count(old) >= 1
    path.write_bytes(data.replace(old, new))
    with pytest.raises(StudyFileError, match="damaged study file .its stored config or QoI names do not match"):
        open_study_readonly(path)
    report = subprocess.run([sys.executable, "-m", "rough_uq", "report", str(path)], capture_output=True,
                            text=True, timeout=TIMEOUT, cwd=tmp_path)
    assert report.returncode == 2 and report.stderr.startswith(f"error: {path} cannot be read: damaged study file")


def test_a_study_file_without_a_header_checksum_is_read_and_gets_one_when_rewritten(tmp_path):
    import h5py

    from rough_uq.study.store import header_checksum, open_study

    config = load_config(write_config(tmp_path / "tiny.yaml", tiny_config()))
    path = tmp_path / "results.h5"
    with create_study(config, path) as study:
        study.store.append_samples(make_batch(0, 0, range(5), n_qoi=len(config.qoi_names)))
        text, names, digest = study.store.config_text, study.store.qoi_names, study.store.config_hash
    with h5py.File(path, "r+") as f:  # as written before the checksum existed
        del f.attrs["header_checksum"]
        f.attrs["format_version"] = 2  # a version this roughuq converts when it writes
        del f["samples/level_0/checksum"]
    with open_study_readonly(path) as store:
        assert store.read_samples(level=0).indices.size == 5
    with open_study(path, config_text=text, config_hash=digest, qoi_names=names, create=False) as store:
        assert store.read_samples(level=0).indices.size == 5
    with h5py.File(path, "r") as f:
        assert f.attrs["header_checksum"] == header_checksum(text, names)

"""Study stores: HDF5 file and in-memory twin behave alike; files are refused safely."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from rough_uq.study import store as store_module
from rough_uq.errors import StudyFileError
from rough_uq.problem.batch import LevelBatch
from rough_uq.study.store import (
    ALL_STAGES,
    FORMAT,
    FORMAT_VERSION,
    DuplicateSampleWarning,
    MemoryStore,
    StudyFile,
    open_study,
    open_study_readonly,
)

ROOT = Path(__file__).resolve().parent.parent
QOI = ("contact_area", "clusters")
HASH = "a" * 64
OTHER_HASH = "b" * 64
CONFIG_TEXT = "schema_version: 1\nseed: 7\n"


def make_batch(level: int, stage: int, indices, *, n_qoi: int = 2) -> LevelBatch:
    indices = np.asarray(indices, dtype=np.int64)
    n = len(indices)
    base = indices[:, None] + 10.0 * level + 100.0 * stage
    fine = base + np.arange(n_qoi) / 10
    converged = np.ones((n, 2), dtype=bool)
    converged[indices % 3 == 0, 1] = False
    return LevelBatch(
        level=level,
        stage=stage,
        indices=indices,
        fine=fine,
        coarse=np.zeros_like(fine) if level == 0 else fine - 0.5,
        cost=0.01 * (indices + 1),
        n_iter=np.stack([indices + 5, np.full(n, 0 if level == 0 else 3)], axis=1),
        converged=converged,
    )


def new_study(path: Path, **kwargs) -> StudyFile:
    options = {"config_text": CONFIG_TEXT, "config_hash": HASH, "qoi_names": QOI, "code_version": "test"}
    options.update(kwargs)
    return open_study(path, **options)


def fingerprint(path: Path) -> tuple[str, int]:
    return hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns


def assert_same_batch(a: LevelBatch, b: LevelBatch) -> None:
    assert (a.level, a.stage) == (b.level, b.stage)
    for name in ("indices", "fine", "coarse", "cost", "n_iter", "converged"):
        left, right = getattr(a, name), getattr(b, name)
        assert left.dtype == right.dtype, name
        np.testing.assert_array_equal(left, right, err_msg=name)


@pytest.fixture(params=["hdf5", "memory"])
def store(request, tmp_path: Path):
    if request.param == "memory":
        yield MemoryStore(qoi_names=QOI, config_text=CONFIG_TEXT, config_hash=HASH)
    else:
        with new_study(tmp_path / "study.h5") as study:
            yield study


# ---------------------------------------------------------------------------
# Semantics shared by both stores
# ---------------------------------------------------------------------------


def test_roundtrip_orders_by_index(store) -> None:
    written = make_batch(1, 4, [5, 2, 9])
    assert store.append_samples(written) == 3
    read = store.read_samples(level=1, stage=4)
    order = np.argsort(written.indices)
    expected = LevelBatch(
        level=1,
        stage=4,
        indices=written.indices[order],
        fine=written.fine[order],
        coarse=written.coarse[order],
        cost=written.cost[order],
        n_iter=written.n_iter[order],
        converged=written.converged[order],
    )
    assert_same_batch(read, expected)
    assert read.n_qoi == 2 and not read.is_converged.all()


def test_duplicates_are_skipped_with_a_warning(store) -> None:
    assert store.append_samples(make_batch(0, 0, [0, 1, 2])) == 3
    with pytest.warns(DuplicateSampleWarning, match="3 sample"):  # 2, the second 3, 1
        assert store.append_samples(make_batch(0, 0, [2, 3, 3, 1])) == 1
    with pytest.warns(DuplicateSampleWarning):
        assert store.append_samples(make_batch(0, 0, [0])) == 0
    # The same index in another stage or level is another sample.
    assert store.append_samples(make_batch(0, 1, [0, 1])) == 2
    assert store.append_samples(make_batch(1, 0, [0])) == 1
    np.testing.assert_array_equal(store.sample_indices(level=0, stage=0), [0, 1, 2, 3])
    assert store.read_samples(level=0, stage=0).n_samples == 4
    assert store.read_samples(level=0).n_samples == 6


def test_all_stages_and_empty_levels(store) -> None:
    store.append_samples(make_batch(2, 3, [1, 0]))
    store.append_samples(make_batch(2, 1, [4]))
    both = store.read_samples(level=2)
    assert both.stage == ALL_STAGES
    np.testing.assert_array_equal(both.indices, [4, 0, 1])  # stage 1 first, then stage 3 by index
    assert store.levels() == [2]
    assert store.stages(level=2) == [1, 3]
    empty = store.read_samples(level=0, stage=0)
    assert empty.n_samples == 0 and empty.fine.shape == (0, 2) and empty.converged.dtype == bool
    assert store.sample_indices(level=5, stage=0).size == 0


def test_batch_with_wrong_qoi_count_is_a_bug(store) -> None:
    with pytest.raises(ValueError, match="QoI columns"):
        store.append_samples(make_batch(0, 0, [0], n_qoi=3))


def test_runs_and_screening_roundtrip(store) -> None:
    assert store.read_screening() is None and store.read_runs() == []
    screening = {"alpha": 1.5, "V": np.array([1e-2, 1e-3]), "n": np.int64(20), "kurtosis": [float("nan")]}
    store.write_screening(screening)
    read = store.read_screening()
    assert read["alpha"] == 1.5 and read["V"] == [1e-2, 1e-3] and read["n"] == 20
    assert math.isnan(read["kurtosis"][0])

    store.write_run("run-2", {"kind": "mlmc", "tol": 0.5, "N_l": [10, 0]})
    store.write_run("run-1", {"kind": "mc", "tol": 1.0})
    store.write_run("run-2", {"kind": "mlmc", "tol": 0.5, "N_l": [40, 12], "done": True})
    runs = store.read_runs()
    assert [r["run_id"] for r in runs] == ["run-2", "run-1"]  # creation order survives a rewrite
    assert runs[0] == {"run_id": "run-2", "kind": "mlmc", "tol": 0.5, "N_l": [40, 12], "done": True}


def test_bad_records_are_refused(store) -> None:
    with pytest.raises(TypeError, match="JSON"):
        store.write_run("r", {"x": object()})
    with pytest.raises(TypeError, match="mapping"):
        store.write_screening([1, 2])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="run_id"):
        store.write_run("a/b", {})
    with pytest.raises(ValueError, match="run_id"):
        store.write_run("x", {"run_id": "y"})
    assert store.read_runs() == []


def test_file_and_memory_store_are_equivalent(tmp_path: Path) -> None:
    memory = MemoryStore(qoi_names=QOI)
    operations = [
        make_batch(0, 0, range(12)),
        make_batch(1, 0, [3, 1, 2]),
        make_batch(0, 1, [7, 0]),
        make_batch(1, 0, [2, 5]),  # one duplicate
        make_batch(2, 2, []),
    ]
    with new_study(tmp_path / "study.h5") as study:
        for batch in operations:
            with pytest.warns(DuplicateSampleWarning) if batch.level == 1 and 5 in batch.indices else _no_warning():
                assert study.append_samples(batch) == memory.append_samples(batch)
        for s in (study, memory):
            s.write_run("r", {"estimate": np.float64(0.25)})
    assert study.levels() == memory.levels() == [0, 1]
    reopened = open_study_readonly(tmp_path / "study.h5")
    for level in (0, 1, 2):
        for stage in (None, 0, 1, 2):
            assert_same_batch(
                reopened.read_samples(level=level, stage=stage), memory.read_samples(level=level, stage=stage)
            )
    assert reopened.read_runs() == memory.read_runs()


class _no_warning:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *args) -> None:
        return None


# ---------------------------------------------------------------------------
# The file: header, resume, refusal
# ---------------------------------------------------------------------------


def test_header_and_layout(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(1, 0, [0, 1]))
        study.write_run("r1", {"tol": 0.1})
        study.write_screening({"alpha": 1.0})
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == FORMAT and f.attrs["format_version"] == FORMAT_VERSION
        assert f.attrs["config_hash"] == HASH and f.attrs["code_version"] == "test"
        assert "T" in f.attrs["created"] and f.attrs["role"] == "study"
        assert f["config_yaml"].asstr()[()] == CONFIG_TEXT
        assert tuple(f["qoi_names"].asstr()[()]) == QOI
        level = f["samples/level_1"]
        assert level["fine"].shape == (2, 2) and level["fine"].maxshape == (None, 2)
        assert level["n_committed"][()] == 2 and level["n_committed"].dtype == np.int64
        assert level["stage"].dtype == np.int64 and level["converged"].dtype == bool
        assert json.loads(f["runs/r1/record"][()].tobytes()) == {"tol": 0.1}
        assert json.loads(f["screening/record"][()].tobytes()) == {"alpha": 1.0}
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]  # no lock or temporary file left


def test_a_shard_keeps_its_role_and_is_not_written_as_a_study(tmp_path: Path) -> None:
    """A shard is marked as one (the report told it to finish its screening), through rewrites too."""
    path = tmp_path / "shard.h5"
    with new_study(path, role="shard") as shard:
        shard.append_samples(make_batch(0, 0, [0, 1]))
    store_module._rewrite(path)  # as after a writer killed outright
    with open_study_readonly(path) as reader:
        assert reader.role == "shard"
        assert_same_batch(reader.read_samples(level=0, stage=0), make_batch(0, 0, [0, 1]))
    before = fingerprint(path)
    with pytest.raises(StudyFileError, match=r"shard\.h5 is a shard of samples .* `roughuq merge --into STUDY "):
        new_study(path, create=False)
    assert fingerprint(path) == before
    with new_study(path, create=False, role="shard") as shard:
        assert shard.role == "shard" and shard.levels() == [0]
    with pytest.raises(ValueError, match="role must be one of study, shard, got 'Shard'"):
        new_study(tmp_path / "other.h5", role="Shard")
    assert not (tmp_path / "other.h5").exists()
    version_1 = tmp_path / "v1.h5"  # written before the attribute: a study
    version_1.write_bytes(VERSION_1.read_bytes())
    with open_study_readonly(version_1) as reader:
        assert reader.role == "study"
    assert MemoryStore(qoi_names=QOI).role == "study"


def test_index_set_is_a_set(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    stored = store_module._IndexSet()
    expected: set[int] = set()
    for _ in range(200):
        start = int(rng.integers(0, 300))
        added = rng.integers(start, start + rng.integers(1, 20), size=int(rng.integers(0, 8)))
        stored.add(added)
        expected.update(int(i) for i in added)
        probe = rng.integers(-5, 330, size=50)
        np.testing.assert_array_equal(stored.contains(probe), [int(i) in expected for i in probe])
    assert np.all(stored.starts[1:] > stored.stops[:-1])  # disjoint, not touching, sorted
    assert int(np.sum(stored.stops - stored.starts)) == len(expected)


def test_rows_beyond_the_committed_count_are_invisible_and_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1]))
        study.append_samples(make_batch(0, 0, [2]))
    with h5py.File(path, "r+") as f:  # what an append killed before its count leaves
        level = f["samples/level_0"]
        for name in ("stage", "index", "fine", "coarse", "cost", "n_iter", "converged"):
            level[name].resize(5, axis=0)
        level["index"][3:] = [7, 8]
        level["fine"][3:] = -1.0
    with open_study_readonly(path) as reader:
        assert_same_batch(reader.read_samples(level=0, stage=0), make_batch(0, 0, [0, 1, 2]))
        assert reader.levels() == [0] and reader.stages(level=0) == [0]
    with new_study(path, create=False) as study:
        assert study.append_samples(make_batch(0, 0, [8])) == 1  # 8 was never committed
        assert_same_batch(study.read_samples(level=0, stage=0), make_batch(0, 0, [0, 1, 2, 8]))
    with h5py.File(path, "r") as f:
        assert f["samples/level_0/n_committed"][()] == 4
        np.testing.assert_array_equal(f["samples/level_0/index"][:4], [0, 1, 2, 8])


VERSION_1 = ROOT / "tests" / "data" / "study_v1.h5"


def _check_version_1_content(study: StudyFile) -> None:
    # tests/data/study_v1.h5 was written by the version-1 store (before in-place appends) with
    # make_batch: level 0 stage 0 [3, 1, 0] then [2, 5, 4]; level 1 stage 0 [0, 1], stage 7 [2, 0];
    # screening {"alpha": 1.5, "levels": [0, 1]}; runs r1 (written twice) and r0.
    assert (study.config_hash, study.config_text, study.qoi_names, study.code_version) == (
        HASH, CONFIG_TEXT, QOI, "test"
    )
    assert study.levels() == [0, 1] and study.stages(level=1) == [0, 7]
    assert_same_batch(study.read_samples(level=0, stage=0), make_batch(0, 0, range(6)))
    assert_same_batch(study.read_samples(level=1, stage=7), make_batch(1, 7, [0, 2]))
    np.testing.assert_array_equal(study.read_samples(level=1).indices, [0, 1, 0, 2])
    assert study.read_screening() == {"alpha": 1.5, "levels": [0, 1]}
    assert study.read_runs() == [
        {"run_id": "r1", "tol": 0.1, "status": "finished"},
        {"run_id": "r0", "tol": 0.2},
    ]


def test_version_1_file_is_read(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    path.write_bytes(VERSION_1.read_bytes())
    before = fingerprint(path)
    with open_study_readonly(path) as reader:
        assert reader.format_version == 1
        _check_version_1_content(reader)
    assert fingerprint(path) == before


def test_version_1_file_is_converted_when_opened_for_writing(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    path.write_bytes(VERSION_1.read_bytes())
    with new_study(path, create=False) as study:
        assert study.format_version == FORMAT_VERSION
        _check_version_1_content(study)
        assert study.append_samples(make_batch(0, 0, [6, 7])) == 2
        with pytest.warns(DuplicateSampleWarning):
            assert study.append_samples(make_batch(1, 7, [2, 3])) == 1
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == FORMAT_VERSION and f.attrs["created"] == "2026-11-23T20:54:25+00:00"
        assert f["samples/level_0/n_committed"][()] == 8
    with open_study_readonly(path) as reader:
        assert_same_batch(reader.read_samples(level=0, stage=0), make_batch(0, 0, range(8)))
        assert_same_batch(reader.read_samples(level=1, stage=7), make_batch(1, 7, [0, 2, 3]))
        assert [run["run_id"] for run in reader.read_runs()] == ["r1", "r0"]
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]


def _as_version_2(path: Path) -> None:
    """Make ``path`` (written by this store) a version-2 file: no checksums of its rows."""
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 2
        for level in f["samples"].values():
            del level["checksum"]


def test_version_2_file_is_read_unchecked_and_converted_when_opened_for_writing(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1]))
        study.append_samples(make_batch(0, 0, [2]))
    _as_version_2(path)
    with open_study_readonly(path) as reader:
        assert reader.format_version == 2
        assert_same_batch(reader.read_samples(level=0, stage=0), make_batch(0, 0, range(3)))
    with new_study(path, create=False) as study:
        assert study.format_version == FORMAT_VERSION == 3
        assert study.append_samples(make_batch(0, 0, [3])) == 1
    with h5py.File(path, "r+") as f:  # every row has its checksum now, the converted ones too
        assert f["samples/level_0/checksum"].shape == (4,)
        f["samples/level_0/fine"][1, 0] += 1.0
    with open_study_readonly(path) as reader:
        damaged = r"samples/level_0: 1 of 4 rows differ from their checksums \(rows 1\)"
        with pytest.raises(StudyFileError, match=damaged):
            reader.read_samples(level=0, stage=0)


def test_converted_files_get_checksums_on_their_old_records(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    path.write_bytes(VERSION_1.read_bytes())
    with new_study(path, create=False):
        pass
    with h5py.File(path, "r") as f:
        records = [f["screening/record"], *(group["record"] for group in f["runs"].values())]
        assert len(records) == 3 and all(record.fletcher32 for record in records)
    with open_study_readonly(path) as reader:
        _check_version_1_content(reader)


def test_rows_stored_big_endian_are_checked_by_value(tmp_path: Path) -> None:
    # h5py reads a big-endian column as it is stored; its bits viewed as native words differed from the checksum.
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1, 2]))
    with h5py.File(path, "r+") as f:
        group = f["samples/level_0"]
        values = group["fine"][()]
        del group["fine"]
        group.create_dataset("fine", data=values.astype(">f8"), maxshape=(None, 2), chunks=(512, 2))
    with open_study_readonly(path) as reader:
        np.testing.assert_array_equal(reader.read_samples(level=0, stage=0).fine, make_batch(0, 0, [0, 1, 2]).fine)


@pytest.mark.parametrize("damage", ["no checksum", "a boolean byte"])
def test_version_3_rows_without_their_checksum_or_with_a_changed_byte_are_refused(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1, 2]))
    with h5py.File(path, "r+") as f:
        group = f["samples/level_0"]
        if damage == "no checksum":
            del group["checksum"]
        else:  # a byte of True changed from 1 to 2: h5py still reads True
            raw = group["converged"][()].view(np.uint8).copy()
            raw[1, 0] = 2
            group["converged"][1] = raw[1].view(bool)
    expected = "no checksum dataset"
    if damage != "no checksum":
        expected = r"1 of 3 rows differ from their checksums \(rows 1\)"
    with open_study_readonly(path) as reader:
        with pytest.raises(StudyFileError, match=f"damaged study file \\(samples/level_0: {expected}"):
            reader.read_samples(level=0, stage=0)


def test_read_only_file_is_opened_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        for level in range(3):
            study.append_samples(make_batch(level, 0, range(4)))
            study.append_samples(make_batch(level, 5, [1]))
        study.write_run("r", {"tol": 0.1})
        study.write_screening({"alpha": 1.0})
    opened = []
    real_file = h5py.File

    def counting_file(*args, **kwargs):
        opened.append(args[0])
        return real_file(*args, **kwargs)

    monkeypatch.setattr(store_module.h5py, "File", counting_file)
    with open_study_readonly(path) as reader:
        n_header = len(opened)  # the header check
        for _ in range(2):
            for level in reader.levels():
                reader.read_samples(level=level)
                for stage in reader.stages(level=level):
                    reader.sample_indices(level=level, stage=stage)
                    reader.read_samples(level=level, stage=stage)
            reader.read_runs(), reader.read_screening(), reader.qoi_names, reader.config_hash
        assert len(opened) == n_header + 1
    assert n_header == 1


def test_resume_with_matching_hash(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1]))
    with new_study(path, create=False, config_text="ignored: 1\n", code_version="later") as study:
        assert study.config_text == CONFIG_TEXT and study.code_version == "test"
        np.testing.assert_array_equal(study.sample_indices(level=0, stage=0), [0, 1])
        assert study.append_samples(make_batch(0, 0, [2])) == 1
    assert open_study_readonly(path).read_samples(level=0, stage=0).n_samples == 3


def test_mismatched_hash_is_refused_and_file_unchanged(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0]))
    before = fingerprint(path)
    time.sleep(0.01)
    with pytest.raises(StudyFileError, match="written by another config") as info:
        new_study(path, config_hash=OTHER_HASH)
    assert "aaaaaaaaaaaa" in str(info.value) and "bbbbbbbbbbbb" in str(info.value)
    assert "another study file" in str(info.value) and "--" not in str(info.value)  # the store knows no options
    assert fingerprint(path) == before
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]


def _valid_bytes(tmp_path: Path) -> bytes:
    path = tmp_path / "valid.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, range(50)))
    data = path.read_bytes()
    path.unlink()
    return data


def _not_hdf5(path: Path, tmp_path: Path) -> None:
    path.write_text("this is not HDF5\n")


def _truncated(path: Path, tmp_path: Path) -> None:
    data = _valid_bytes(tmp_path)
    path.write_bytes(data[: len(data) // 2])


def _empty(path: Path, tmp_path: Path) -> None:
    path.write_bytes(b"")


def _wrong_version(path: Path, tmp_path: Path) -> None:
    path.write_bytes(_valid_bytes(tmp_path))
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1


def _foreign_hdf5(path: Path, tmp_path: Path) -> None:
    with h5py.File(path, "w") as f:
        f["data"] = np.arange(3)


def _other_format_hdf5(path: Path, tmp_path: Path) -> None:
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "netcdf4"


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (_not_hdf5, "not an HDF5 file"),
        (_truncated, "truncated or damaged"),
        (_empty, "is empty"),
        (_wrong_version, "format version 4; this roughuq reads versions 1, 2 and 3"),
        (_foreign_hdf5, r"not a roughuq study file \(no 'format' attribute; a study file's is 'roughuq-study'\)"),
        (_other_format_hdf5, r"not a roughuq study file \(its 'format' attribute is 'netcdf4'; a study file's is "),
    ],
    ids=["not-hdf5", "truncated", "empty", "wrong-version", "foreign-hdf5", "other-format-hdf5"],
)
@pytest.mark.parametrize("opener", ["create", "resume", "readonly"])
def test_bad_files_are_refused_and_unchanged(tmp_path: Path, make, message: str, opener: str) -> None:
    path = tmp_path / "study.h5"
    make(path, tmp_path)
    before = fingerprint(path)
    with pytest.raises(StudyFileError, match=message) as info:
        if opener == "readonly":
            open_study_readonly(path)
        else:
            new_study(path, create=opener == "create")
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert fingerprint(path) == before
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]


@pytest.mark.parametrize("mode", ["r", "a"])
def test_a_file_the_caller_holds_open_is_not_called_damaged(tmp_path: Path, mode: str) -> None:
    # An h5py.File of the user's own (HDF5's default locking) made a sound study "truncated or damaged", with the
    # advice to restore it from a copy or start a new one.
    path = tmp_path / "study.h5"
    path.write_bytes(_valid_bytes(tmp_path))
    with h5py.File(path, mode):
        with pytest.raises(StudyFileError, match="already open in this process .* close it and read again") as info:
            open_study_readonly(path).read_samples(level=0)
        assert "damaged" not in str(info.value)
    with open_study_readonly(path) as study:
        assert study.read_samples(level=0).indices.size == 50  # closed, it reads


def _replace_record(path: Path, name: str, value: object) -> None:
    with h5py.File(path, "r+") as f:
        del f[name]
        f[name] = value


DAMAGED_RECORDS = [
    ("screening/record", np.frombuffer(b'{"a": "\xcc\xcc"}', dtype=np.uint8), "not UTF-8 text"),
    ("screening/record", np.frombuffer(b"{not json", dtype=np.uint8), "not JSON text"),
    ("screening/record", np.array(b'{"a": 1}', dtype=h5py.string_dtype()), "a string dataset"),
    ("runs/r1/record", np.frombuffer(b"[1, 2]", dtype=np.uint8), "JSON list, not an object"),
    # json recursed per level: a RecursionError traceback.
    ("runs/r1/record", np.frombuffer(b"[" * 100000 + b"]" * 100000, dtype=np.uint8), "JSON nested too deeply"),
]


@pytest.mark.parametrize(("name", "value", "message"), DAMAGED_RECORDS, ids=["utf8", "json", "string", "list", "deep"])
@pytest.mark.parametrize("opener", ["readonly", "writable"])
def test_a_damaged_record_is_a_study_file_error_naming_file_and_record(
    tmp_path: Path, name: str, value: object, message: str, opener: str
) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.write_screening({"alpha": 1.0})
        study.write_run("r1", {"tol": 1.0})
    _replace_record(path, name, value)
    with open_study_readonly(path) if opener == "readonly" else new_study(path) as study:
        with pytest.raises(StudyFileError, match=message) as info:
            study.read_screening() if name.startswith("screening") else study.read_runs()
    assert str(path) in str(info.value) and name in str(info.value) and "damaged" in str(info.value)
    assert info.value.path == path


def test_missing_file_is_refused_when_not_creating(tmp_path: Path) -> None:
    with pytest.raises(StudyFileError, match="no such study file"):
        new_study(tmp_path / "missing.h5", create=False)
    with pytest.raises(StudyFileError, match="no such study file"):
        open_study_readonly(tmp_path / "missing.h5")
    assert os.listdir(tmp_path) == []


def test_create_makes_parent_directories(tmp_path: Path) -> None:
    with new_study(tmp_path / "a" / "b" / "study.h5") as study:
        assert study.path.exists()


@pytest.mark.parametrize("below", [(), ("sub",)], ids=["parent", "grandparent"])
def test_unusable_directory_is_refused_before_any_work(tmp_path: Path, below: tuple[str, ...]) -> None:
    # It said "cannot create the directory file (File exists)": the file in the way is named as such.
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StudyFileError, match=f": {re.escape(str(blocker))} is a file, not a directory$"):
        new_study(blocker.joinpath(*below, "study.h5"))


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write to read-only directories")
def test_read_only_directory_is_refused(tmp_path: Path) -> None:
    directory = tmp_path / "ro"
    directory.mkdir()
    directory.chmod(0o555)
    try:
        with pytest.raises(StudyFileError, match="not writable"):
            new_study(directory / "study.h5")
    finally:
        directory.chmod(0o755)


def _disk_full(*args, **kwargs):
    raise OSError(28, "No space left on device")


def test_failed_copy_on_write_leaves_file_unchanged(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0]))
        before = fingerprint(path)
        monkeypatch.setattr(store_module, "_fsync_path", _disk_full)
        with pytest.raises(StudyFileError, match="No space left on device.*unchanged"):
            study.append_samples(make_batch(1, 0, [0]))  # a new level: written by copy-on-write
        with pytest.raises(StudyFileError, match="No space left on device.*unchanged"):
            study.write_run("r", {"tol": 0.1})
        monkeypatch.undo()
        assert fingerprint(path) == before
        assert sorted(os.listdir(tmp_path)) == ["study.h5", "study.h5.lock"]
        assert study.levels() == [0] and study.read_runs() == []
        assert study.append_samples(make_batch(1, 0, [0])) == 1  # the sample was not counted


def test_failed_append_keeps_the_committed_samples(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, [0, 1]))
        study.append_samples(make_batch(0, 0, [2]))  # in place
        monkeypatch.setattr(store_module, "_fsync_path", _disk_full)  # fails before the count is written
        with pytest.raises(StudyFileError, match="No space left on device.*committed samples are intact"):
            study.append_samples(make_batch(0, 0, [3, 4]))
        monkeypatch.undo()
        assert sorted(os.listdir(tmp_path)) == ["study.h5", "study.h5.lock"]
        with open_study_readonly(path) as reader:
            assert_same_batch(reader.read_samples(level=0, stage=0), make_batch(0, 0, [0, 1, 2]))
        np.testing.assert_array_equal(study.sample_indices(level=0, stage=0), [0, 1, 2])
        assert study.append_samples(make_batch(0, 0, [4, 3])) == 2  # the samples were not counted
        assert_same_batch(study.read_samples(level=0, stage=0), make_batch(0, 0, range(5)))


def _ctrl_c_once(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Send this process a Ctrl-C from the first fsync of the next write (in its middle), once."""
    sent: list[int] = []
    fsync = store_module._fsync_path

    def interrupted_fsync(*args, **kwargs):
        if not sent:
            sent.append(signal.SIGINT)
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)  # this thread's, not another's
            time.sleep(0.05)  # Python runs the handler at the next instruction: it would land here
        return fsync(*args, **kwargs)

    monkeypatch.setattr(store_module, "_fsync_path", interrupted_fsync)
    return sent


@pytest.mark.parametrize("new_level", [False, True], ids=["in place", "copy-on-write"])
def test_ctrl_c_during_an_append_stops_after_the_rows_are_stored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, new_level: bool
) -> None:
    # A second Ctrl-C landed in the final save that the first one started and lost the batch (3 of 19 double
    # Ctrl-Cs in an audit), while roughuq said every completed sample was saved.
    path = tmp_path / "study.h5"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with new_study(path) as study:
            study.append_samples(make_batch(0, 0, [0, 1]))
            sent = _ctrl_c_once(monkeypatch)
            with pytest.raises(KeyboardInterrupt):
                study.append_samples(make_batch(1 if new_level else 0, 0, [2, 3]))
            assert sent
            monkeypatch.undo()
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
            with pytest.warns(DuplicateSampleWarning):
                assert study.append_samples(make_batch(1 if new_level else 0, 0, [2, 3])) == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    with open_study_readonly(path) as reader:
        stored = reader.sample_indices(level=1 if new_level else 0, stage=0)
    np.testing.assert_array_equal(stored, [2, 3] if new_level else [0, 1, 2, 3])


def test_ctrl_c_while_a_new_study_file_is_written_stops_once_it_is_in_place(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Raised inside h5py's conversion of a text attribute of the header, a KeyboardInterrupt came out as
    # "TypeError: Operation not defined for data type class" (a traceback, 1 of 100 interrupted sweeps).
    path = tmp_path / "study.h5"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        sent = _ctrl_c_once(monkeypatch)
        with pytest.raises(KeyboardInterrupt):
            new_study(path).close()
        assert sent
        monkeypatch.undo()
    finally:
        signal.signal(signal.SIGINT, previous)
    with open_study_readonly(path) as reader:
        assert reader.qoi_names == tuple(QOI) and reader.read_runs() == []


def test_ctrl_c_during_a_record_stops_after_it_is_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "study.h5"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with new_study(path) as study:
            _ctrl_c_once(monkeypatch)
            with pytest.raises(KeyboardInterrupt):
                study.write_run("r", {"tol": 0.1})
            monkeypatch.undo()
    finally:
        signal.signal(signal.SIGINT, previous)
    with open_study_readonly(path) as reader:
        assert [run["run_id"] for run in reader.read_runs()] == ["r"]


def test_read_only_and_closed_files_refuse_writes(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    study = new_study(path)
    study.close()
    with pytest.raises(StudyFileError, match="closed"):
        study.append_samples(make_batch(0, 0, [0]))
    reader = open_study_readonly(path)
    assert reader.config_hash == HASH and reader.config_text == CONFIG_TEXT and reader.qoi_names == QOI
    with pytest.raises(StudyFileError, match="read-only"):
        reader.write_run("r", {})


# ---------------------------------------------------------------------------
# Locking and crash safety
# ---------------------------------------------------------------------------


def test_second_writer_is_refused_while_locked(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path):
        with pytest.raises(StudyFileError, match=f"locked by a running process \\(pid {os.getpid()}\\)"):
            new_study(path).close()
        assert open_study_readonly(path).config_hash == HASH  # readers need no lock
    with new_study(path, create=False):
        pass


def test_a_study_reached_through_a_symlink_is_written_and_locked_as_the_file_it_names(tmp_path: Path) -> None:
    # Through work/results.h5 -> ../store/study.h5 a run's copy-on-write replaced the link by a file of its own
    # (the study never got the run's samples), and the lock was the link's: both names could be written at once.
    target = tmp_path / "store" / "study.h5"
    target.parent.mkdir()
    new_study(target).close()
    link = tmp_path / "work" / "results.h5"
    link.parent.mkdir()
    link.symlink_to(Path("..") / "store" / "study.h5")
    with new_study(link, create=False) as study:
        study.append_samples(make_batch(1, 0, range(3)))  # a new level: a copy-on-write transaction
        with pytest.raises(StudyFileError, match="locked by a running process"):
            new_study(target, create=False)
    assert link.is_symlink()
    with open_study_readonly(target) as reader:
        assert reader.read_samples(level=1).indices.tolist() == [0, 1, 2]


def _child(code: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


_CHILD_PRELUDE = f"""
import sys, numpy as np
sys.path.insert(0, {str(ROOT / 'tests')!r})
from test_store import make_batch, new_study
from pathlib import Path

def say(*words):  # one write per line: a kill never leaves half a line (print writes word by word unbuffered)
    sys.stdout.write(" ".join(map(str, words)) + "\\n")
    sys.stdout.flush()
"""


def _complete_lines(output: str) -> list[str]:
    """Lines of a killed child's output, without a last line it may not have finished."""
    return [line for line in output.splitlines(keepends=True) if line.endswith("\n")]


def test_lock_of_a_killed_process_is_released(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    code = _CHILD_PRELUDE + (
        f"study = new_study(Path({str(path)!r}))\nprint('ready', flush=True)\nimport time\ntime.sleep(60)\n"
    )
    with _child(code) as child:
        try:
            assert child.stdout.readline().strip() == "ready", child.stderr.read()
            with pytest.raises(StudyFileError, match=f"pid {child.pid}"):
                new_study(path)
        finally:
            child.kill()
            child.wait()
    with new_study(path, create=False) as study:
        assert study.read_samples(level=0).n_samples == 0


def test_kill_during_appends_loses_nothing_acknowledged(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    code = _CHILD_PRELUDE + (
        f"study = new_study(Path({str(path)!r}))\n"
        "for start in range(0, 10**6, 5):\n"
        "    study.append_samples(make_batch(0, 0, range(start, start + 5)))\n"
        "    say(start + 5)\n"
    )
    acknowledged = 0
    with _child(code) as child:
        try:
            while acknowledged < 40:
                line = child.stdout.readline()
                assert line, child.stderr.read()
                acknowledged = int(line)
        finally:
            child.kill()  # SIGKILL, at whatever point the writer is
            child.wait()
        for line in _complete_lines(child.stdout.read()):
            acknowledged = int(line)
    with new_study(path, create=False) as study:
        stored = study.sample_indices(level=0, stage=0)
        assert acknowledged <= stored.size <= acknowledged + 5
        np.testing.assert_array_equal(stored, np.arange(stored.size))
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]  # the temporary copy is gone


_WRITER_KEYS = ((0, 0), (1, 0), (0, 3), (2, 3))  # (level, stage) appended in turn
_MAX_BATCH = 13


def _writer_code(path: Path, n_batches: int | None) -> str:
    """A writer that resumes the study at ``path`` and appends batches (forever, or ``n_batches``)."""
    return _CHILD_PRELUDE + f"""
say("opening")
study = new_study(Path({str(path)!r}), create=True)
keys = {_WRITER_KEYS!r}
next_index = {{key: int(study.sample_indices(level=key[0], stage=key[1]).size) for key in keys}}
k = 0
while {n_batches!r} is None or k < {n_batches!r}:
    level, stage = keys[k % len(keys)]
    start, size = next_index[(level, stage)], 1 + (7 * k) % {_MAX_BATCH}
    study.append_samples(make_batch(level, stage, range(start, start + size)))
    next_index[(level, stage)] = start + size
    say(level, stage, start + size)
    if k % 10 == 9:
        study.write_run("r", {{"n_samples": sum(next_index.values())}})  # copy-on-write, killed too
    k += 1
study.close()
"""


def _check_committed(path: Path, acknowledged: dict[tuple[int, int], int]) -> int:
    """Every committed row reads back as written, with no gap and no partial row; return the row count."""
    n_total = 0
    with open_study_readonly(path) as reader:
        for level, stage in _WRITER_KEYS:
            stored = reader.read_samples(level=level, stage=stage)
            n_acknowledged = acknowledged.get((level, stage), 0)
            assert n_acknowledged <= stored.n_samples <= n_acknowledged + _MAX_BATCH, (
                level, stage, n_acknowledged, stored.n_samples, reader._committed_counts()
            )
            assert_same_batch(stored, make_batch(level, stage, range(stored.n_samples)))
            n_total += stored.n_samples
        runs = reader.read_runs()
        assert runs == [] or (runs[0]["run_id"] == "r" and runs[0]["n_samples"] <= n_total)
    return n_total


@pytest.mark.parametrize(
    "n_kills", [6, pytest.param(60, marks=pytest.mark.slow)], ids=["6-kills", "60-kills"]
)
def test_writer_killed_at_random_moments_keeps_every_committed_row(tmp_path: Path, n_kills: int) -> None:
    path = tmp_path / "study.h5"
    rng = np.random.default_rng(2026 + n_kills)
    acknowledged: dict[tuple[int, int], int] = {}
    n_before = 0
    n_crashed_writers = 0
    for attempt, delay in enumerate(rng.uniform(0.0, 0.6, size=n_kills)):
        with _child(_writer_code(path, None)) as child:
            assert child.stdout.readline() == "opening\n", child.stderr.read()
            # Every other writer is killed while appending; the others possibly in the open (and its rewrite).
            output = child.stdout.readline() if attempt % 2 else ""
            time.sleep(delay)
            child.kill()
            child.wait()
            output, errors = output + child.stdout.read(), child.stderr.read()
        assert "Traceback" not in errors, errors
        for line in _complete_lines(output):
            level, stage, n = map(int, line.split())
            acknowledged[(level, stage)] = max(acknowledged.get((level, stage), 0), n)
        if path.exists():
            n_crashed_writers += store_module._is_marked_open(path)
            n_rows = _check_committed(path, acknowledged)  # readable before any writer cleans up
            assert n_rows >= n_before  # nothing committed is ever lost
            n_before = n_rows
    assert n_crashed_writers >= 1  # a kill hit a writer with the file open (in SWMR mode)
    with _child(_writer_code(path, 12)) as child:  # the resume continues where the last writer stopped
        output, errors = child.communicate(timeout=60)
    assert child.returncode == 0, errors
    for line in output.splitlines()[1:]:
        level, stage, n = map(int, line.split())
        acknowledged[(level, stage)] = n
    assert _check_committed(path, acknowledged) == sum(acknowledged.values()) > n_before
    with h5py.File(path, "r") as f:  # the resume dropped what the killed writers left beyond their counts
        assert f.attrs["format_version"] == FORMAT_VERSION
        for group in f["samples"].values():
            assert group["index"].shape[0] == group["n_committed"][()]
    assert sorted(os.listdir(tmp_path)) == ["study.h5"]


def test_stale_temporary_file_is_removed(tmp_path: Path) -> None:
    path = tmp_path / "study.h5"
    with new_study(path):
        pass
    stale = tmp_path / "study.h5.tmp-999999"
    stale.write_bytes(b"half a file")
    unrelated = tmp_path / "other.h5.tmp-1"
    unrelated.write_bytes(b"")
    assert open_study_readonly(path).qoi_names == QOI  # readers ignore it
    with new_study(path, create=False):
        assert not stale.exists()
    assert unrelated.exists()


# ---------------------------------------------------------------------------
# Imports
# ---------------------------------------------------------------------------


def test_store_and_report_do_not_import_the_solver() -> None:
    heavy = ("numba", "pyfftw", "rough_uq.physics.solver", "rough_uq.problem.sampler", "rough_uq.physics.fft")
    imports = "import sys, rough_uq.study.store, rough_uq.report.summary"
    code = f"{imports}; print(sorted(m for m in {heavy!r} if m in sys.modules))"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.strip() == "[]"


#: What h5py raises for a write that a full disk failed (HDF5's error stack, shortened).
_FULL_DISK = RuntimeError(
    "Unable to synchronously flush file (file write failed: time = Sat Nov 28 04:21:31 2026\n, filename = "
    "'results.h5', file descriptor = 14, errno = 28, error message = 'No space left on device', buf = 0x5558, "
    "total write size = 2120, bytes this sub-write = 2120, offset = 188416)"
)


def test_a_full_disk_in_an_append_or_a_transaction_is_a_study_file_error(tmp_path: Path, monkeypatch) -> None:
    # HDF5 reports a failed write as a RuntimeError, which escaped as a traceback (status 1, then a crash).
    path = tmp_path / "study.h5"
    with new_study(path) as study:
        study.append_samples(make_batch(0, 0, range(3)))

        def full(*args, **kwargs):
            raise _FULL_DISK

        with monkeypatch.context() as patch:
            patch.setattr(h5py.File, "flush", full)
            with pytest.raises(StudyFileError, match=r"could not write \(No space left on device\); the committed "
                                                     r"samples are intact, this batch may be missing$"):
                study.append_samples(make_batch(0, 0, range(3, 6)))
        with monkeypatch.context() as patch:
            patch.setattr(store_module, "_create_level", full)
            with pytest.raises(StudyFileError, match=r"could not write \(No space left on device\); the study file "
                                                     r"is unchanged by this write, and what it held before is kept: "
                                                     r"rerun the command once it can write$"):
                study.append_samples(make_batch(1, 0, range(3)))
        assert study.read_samples(level=0).indices.tolist() == [0, 1, 2]
        study.append_samples(make_batch(0, 0, range(3, 6)))  # with room again, the same batch is stored
    with open_study_readonly(path) as reader:
        assert reader.read_samples(level=0).indices.tolist() == list(range(6)) and reader.levels() == [0]


def test_a_writer_is_not_refused_for_a_reader_probing_the_lock(tmp_path, monkeypatch):
    # is_lock_held (report's "running") takes a shared lock for an instant: a writer starting then was refused,
    # "locked by a running process (pid unknown)", in 2-3 of 25 reruns beside a loop of probes.
    import fcntl

    path = tmp_path / "s.h5"
    store_module._release_lock(path, store_module._acquire_lock(path))
    lock_path = tmp_path / "s.h5.lock"
    lock_path.touch()
    monkeypatch.setattr(store_module, "_LOCK_RETRY_SECONDS", 0.05)  # a window of 1 s: no flake on busy cores
    probe = os.open(lock_path, os.O_RDONLY)
    fcntl.flock(probe, fcntl.LOCK_SH)
    timer = threading.Timer(0.05, os.close, args=(probe,))  # the probe lets go after 50 ms
    timer.start()
    try:
        fd = store_module._acquire_lock(path)
    finally:
        timer.join()
    store_module._release_lock(path, fd)
    held = os.open(lock_path, os.O_RDWR | os.O_CREAT)
    fcntl.flock(held, fcntl.LOCK_EX)  # a real writer keeps it: refused as before
    try:
        with pytest.raises(StudyFileError, match="is locked by a running process"):
            store_module._acquire_lock(path)
    finally:
        os.close(held)


def test_a_lock_file_the_directory_no_longer_lets_go_of_is_released_without_a_traceback(tmp_path, monkeypatch):
    # A directory made read-only under a left-over .lock: unlink raised PermissionError, a traceback (status 1)
    # that hid the command's own one-line error, and the lock's descriptor stayed open.
    path = tmp_path / "s.h5"
    fd = store_module._acquire_lock(path)
    lock_path = tmp_path / "s.h5.lock"
    real_unlink = Path.unlink

    def refused(self, missing_ok=False):
        if self == lock_path:
            raise PermissionError(13, "Permission denied", str(self))
        real_unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", refused)
    store_module._release_lock(path, fd)
    with pytest.raises(OSError):
        os.fstat(fd)  # closed
    monkeypatch.setattr(Path, "unlink", real_unlink)
    store_module._release_lock(path, store_module._acquire_lock(path))  # and free


def test_running_is_a_live_lock_holder_and_nothing_else(tmp_path: Path) -> None:
    from rough_uq.study.store import is_locked_by_running_process

    path = tmp_path / "study.h5"
    assert not is_locked_by_running_process(path)  # no lock file
    with new_study(path):
        assert is_locked_by_running_process(path) and is_locked_by_running_process(str(path))
    (tmp_path / "study.h5.lock").write_text("not a pid\n")
    assert not is_locked_by_running_process(path)
    for odd in (".", "/", ""):  # no file name to put ".lock" after: not a running study
        assert not is_locked_by_running_process(odd)

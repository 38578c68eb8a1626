"""Study files: the samples, screening results and estimation runs of a study.

This is the only module that uses h5py. A study lives in one HDF5 file with
this layout (format ``roughuq-study``, version 3)::

    /                              attrs: format = "roughuq-study"
    |                                     format_version = 3
    |                                     config_hash   (sha256 hex, see rough_uq.study.config.config_hash)
    |                                     code_version  (roughuq version that created the file)
    |                                     created       (ISO 8601 time, UTC)
    |                                     header_checksum (sha256 hex of config_yaml and qoi_names)
    |-- config_yaml                scalar string: the resolved config (YAML text)
    |-- qoi_names                  (n_qoi,) string: names of the QoI columns, in order
    |-- samples/
    |   `-- level_<l>/             attrs: level = l; one row per sample, rows in append order
    |       |-- n_committed        scalar int64: rows 0 .. n_committed-1 are the samples
    |       |-- stage              (n,) int64     stage key (screening / estimation run)
    |       |-- index              (n,) int64     sample index within (stage, level)
    |       |-- fine               (n, n_qoi) float64  QoI on grid n_l
    |       |-- coarse             (n, n_qoi) float64  QoI on grid n_{l-1} (0 on level 0)
    |       |-- cost               (n,) float64   wall time of the sample (s)
    |       |-- n_iter             (n, 2) int64   solver iterations (fine, coarse)
    |       |-- converged          (n, 2) bool    solver converged (fine, coarse)
    |       `-- checksum           (n,) uint64    hash of the row's bits (version 3)
    |-- screening/                 (present once written)
    |   `-- record                 (m,) uint8: UTF-8 JSON text of the screening dict
    `-- runs/
        `-- <run_id>/              attrs: order = creation rank (0, 1, ...)
            `-- record             (m,) uint8: UTF-8 JSON text of the run dict

The sample datasets are chunked and resizable along the first axis; they may
hold rows beyond ``n_committed`` (left by a writer that died in an append),
which are not part of the study and are never read. Version 2 and 3 files
use the HDF5 1.10 file format (``libver="v110"``), which any HDF5 >= 1.10
reads. Version 1 (written by roughuq before the in-place appends) had no
``n_committed`` (every row counted) and the HDF5 1.8 file format; version 2
no ``checksum``. Both are read as they are (without checks of their rows)
and converted to version 3 when opened for writing. ``header_checksum``
covers the two variable-length strings, which HDF5 keeps in its global heap
without a checksum (one altered byte of the stored config changed the load
of every later sample); files written before it have none and get it when
they are rewritten (converted, or mended after a writer's death). JSON
records are byte arrays rather than string attributes because HDF5 never
reuses the space of a rewritten attribute or string.

HDF5 checksums its own metadata, not the data. Version 3 stores a 64-bit hash
of every sample row (``checksum``; :func:`_row_checksums`) and checks every
row it reads against it: a damaged row makes the file unreadable, with the
level and rows named, instead of entering an estimate (zeroed QoI values were
read as contact areas of 0). Records carry HDF5's Fletcher-32 checksum per
chunk, which catches changed bytes, though not a chunk zeroed whole with its
checksum (HDF5 skips a checksum of 0); a zeroed record is no JSON text.

Writing and crash safety
------------------------
A writable :class:`StudyFile` holds an exclusive advisory lock
(``fcntl.flock``, non-blocking) on the sidecar ``<path>.lock`` for as long as
it is open; a second writer is refused with the pid of the holder. The OS
releases the lock when the process dies, even on ``kill -9``.

Samples are appended in place, so the cost of an append does not depend on
the size of the file. The writer keeps the file open in HDF5's
single-writer/multiple-reader (SWMR) mode, in which the library orders its
metadata writes so that the file on disk is a valid HDF5 file at every
moment, and a reader, or a writer that died, never leaves pointers to
unwritten data. An append (:meth:`~StudyStore.append_samples`)

1. grows the level's datasets and writes the new rows after the last
   committed one (overwriting any uncommitted leftovers),
2. flushes the file and ``fsync``\\ s it,
3. writes the new ``n_committed`` (8 bytes written in place),
4. flushes and ``fsync``\\ s again.

A process killed at any moment therefore leaves every committed row
readable, and rows of a half-done append invisible: readers take the first
``n_committed`` rows, never the dataset length. A writer that dies leaves
HDF5's "open for writing" mark in the superblock; readers open the file in
SWMR mode, which ignores the mark, and the next writer (holding the lock, so
no writer is alive) rewrites the file with its committed rows only, which
also drops the leftovers.

Everything else (creating the file, the first batch of a level, the
screening and run records, converting a version 1 or 2 file, the rewrite after a
crash) is a copy-on-write transaction: close the file, copy ``<path>`` to
``<path>.tmp-<pid>``, change the copy, ``fsync`` it, ``os.replace`` it onto
``<path>`` and ``fsync`` the directory, so ``<path>`` is always either the
old or the new complete file. These cost a copy of the file but happen a few
times per command (run records are written when a run starts and ends).
Temporary files left by a killed writer are removed when the study is next
opened for writing. Ctrl-C and SIGTERM are held back while an append or a
transaction writes (:mod:`rough_uq.study.signals`): the command stops once
the write is done, so a second Ctrl-C in the final save loses no batch.

Reading
-------
A read-only :class:`StudyFile` (:func:`open_study_readonly`) takes no lock.
It reads the header when opened, then opens the HDF5 file once, at its first
read of samples or records, and keeps it open until :meth:`~StudyFile.close`:
it sees the study as it was at that moment (the committed row counts are read
once), even while a writer appends. Reading during appends relies on SWMR,
which needs POSIX write semantics: on a network file system (NFS) a reader
may fail while a writer is active on another machine, and succeeds once it
stops. A writable one reads its own file through its writing handle and keeps
what it has read in memory.

A SWMR reader retries a metadata read that fails (a writer may be halfway
through writing it) with a doubling sleep; HDF5's default number of attempts
makes that hours on a damaged file, so the store allows about a second
(``_SWMR_READ_ATTEMPTS``). A file HDF5 cannot read (truncated, overwritten,
marked as held by a writer in a superblock that does not match its checksum)
raises :class:`~rough_uq.errors.StudyFileError` naming the file, saying it
is truncated or damaged and what to do.

Choices where the specification is silent
-----------------------------------------
* ``read_samples(level=l)`` without a stage returns all rows of the level
  ordered by (stage, index), with ``stage = ALL_STAGES`` (-1) on the batch.
* ``sample_indices`` returns a sorted int64 array.
* Records (screening, runs) must be JSON-able mappings; numpy scalars and
  arrays are accepted and come back as Python numbers and lists, NaN and
  infinities survive. ``read_runs`` adds the ``run_id`` key. The store does
  not interpret them: the pipeline writes the ``to_json`` of the typed
  records of :mod:`rough_uq.study.records` and reads them back with
  :func:`~rough_uq.study.records.read_screening_record` and
  :func:`~rough_uq.study.records.read_run_records`. A stored record that
  is not a byte array of UTF-8 JSON text of an object (a damaged or
  hand-edited file) raises :class:`~rough_uq.errors.StudyFileError` naming
  the file and the record (``runs/<run_id>/record``).
* Opening for writing with ``create=True`` creates missing parent
  directories.
* HDF5's own file locking is switched off (``locking=False``): the sidecar
  lock serialises writers, readers need no lock (SWMR), and the store works
  on file systems without locks.
* A closed store can still be read (each read opens and closes the file);
  only writes are refused.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import functools
import hashlib
import json
import math
import os
import re
import shutil
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import h5py
import numpy as np

from rough_uq.problem.batch import LevelBatch
from rough_uq.errors import DuplicateSampleWarning, StudyFileError, checked_path, warn_at_caller
from rough_uq.study.records import utc_timestamp
from rough_uq.study.signals import signals_held

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "READABLE_VERSIONS",
    "ROLES",
    "ALL_STAGES",
    "DuplicateSampleWarning",
    "StudyStore",
    "StudyFile",
    "MemoryStore",
    "open_study",
    "open_study_readonly",
    "is_hdf5_file",
    "checked_study_path",
    "remove_abandoned",
    "is_lock_held",
    "is_locked_by_running_process",
    "lock_if_free",
    "PARTIAL_SUFFIX",
    "incomplete_shard_name",
    "shard_refusal",
]

FORMAT = "roughuq-study"
"""Value of the root attribute ``format``."""

FORMAT_VERSION = 3
"""Version of the layout this code writes."""

READABLE_VERSIONS = (1, 2, 3)
"""Versions of the layout this code reads (older ones are converted when opened for writing)."""

ROLES = ("study", "shard")
"""Values of the root attribute ``role``: a study, or a shard of samples written by ``roughuq sample``.

A file without the attribute (written before it existed) is a study.
"""

ALL_STAGES = -1
"""``LevelBatch.stage`` of a batch read across all stages."""

_COLUMNS = ("stage", "index", "fine", "coarse", "cost", "n_iter", "converged")
_COMMITTED = "n_committed"
_CHECKSUM = "checksum"  # version 3: one per row (_row_checksums)
_CHUNK_ROWS = 512
_RECORD_CHUNK = 4096
_RUN_ID = re.compile(r"^[A-Za-z0-9_.\-]+$")
# The HDF5 1.10 file format: the oldest that supports SWMR, pinned so that
# files stay readable by HDF5 1.10 to 1.14 whatever library writes them.
_LIBVER = ("v110", "v110")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
# A SWMR reader retries a metadata read that fails its checksum or ends past the end of the file (a writer
# may be halfway through writing it), sleeping 1, 2, 4, ... ns in between. HDF5's default of 100 attempts
# makes that hours on a damaged file; 31 attempts give a writer about a second (2**30 ns).
_SWMR_READ_ATTEMPTS = 31

_T = TypeVar("_T")


# ---------------------------------------------------------------------------
# Helpers shared by both stores
# ---------------------------------------------------------------------------


def _batch_columns(batch: LevelBatch) -> dict[str, np.ndarray]:
    n = batch.n_samples
    return {
        "stage": np.full(n, batch.stage, dtype=np.int64),
        "index": np.asarray(batch.indices, dtype=np.int64),
        "fine": np.asarray(batch.fine, dtype=np.float64),
        "coarse": np.asarray(batch.coarse, dtype=np.float64),
        "cost": np.asarray(batch.cost, dtype=np.float64),
        "n_iter": np.asarray(batch.n_iter, dtype=np.int64),
        "converged": np.asarray(batch.converged, dtype=bool),
    }


#: The 64-bit FNV-1a constants; the hash of a row runs over its 8-byte words, column by column.
_FNV_OFFSET = np.uint64(0xCBF29CE484222325)
_FNV_PRIME = np.uint64(0x100000001B3)


def _row_checksums(columns: Mapping[str, np.ndarray]) -> np.ndarray:
    """A 64-bit hash of each row's stored bits (shape ``(n,)``, uint64), never 0 for a row of zeros.

    HDF5 checksums its metadata only; a sample column damaged on disk was read as it was (zeroed QoI values
    became contact areas of 0, a zeroed index column a study without screening). The hash of every row is
    stored beside it and compared on every read.
    """
    n = len(columns["index"])
    digest = np.full(n, _FNV_OFFSET, dtype=np.uint64)
    for name in _COLUMNS:
        values = columns[name]  # in native byte order: h5py reads a big-endian file's columns as they are
        words = np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("="))
        words = words.reshape(n, math.prod(values.shape[1:]))
        words = words.view(np.uint8).astype(np.uint64) if words.dtype == bool else words.view(np.uint64)
        for k in range(words.shape[1]):
            digest ^= words[:, k]
            digest *= _FNV_PRIME
    return digest


def _empty_columns(n_qoi: int) -> dict[str, np.ndarray]:
    return {
        "stage": np.zeros(0, dtype=np.int64),
        "index": np.zeros(0, dtype=np.int64),
        "fine": np.zeros((0, n_qoi), dtype=np.float64),
        "coarse": np.zeros((0, n_qoi), dtype=np.float64),
        "cost": np.zeros(0, dtype=np.float64),
        "n_iter": np.zeros((0, 2), dtype=np.int64),
        "converged": np.zeros((0, 2), dtype=bool),
    }


def _concatenated(blocks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The rows of ``blocks`` as one block; ``blocks`` is collapsed to it (appends stay O(batch))."""
    if len(blocks) > 1:
        blocks[:] = [{name: np.concatenate([block[name] for block in blocks]) for name in _COLUMNS}]
    return blocks[0]


class _IndexSet:
    """A set of sample indices, held as sorted disjoint ranges ``[start, stop)``.

    Indices arrive in runs (a plan asks for ``N_old .. N_new - 1``), so a
    study of a million samples per level usually needs one range per stage:
    membership and insertion cost ``O(batch log n_ranges)``, not ``O(n)``.
    """

    def __init__(self, indices: np.ndarray | None = None) -> None:
        self.starts = np.zeros(0, dtype=np.int64)
        self.stops = np.zeros(0, dtype=np.int64)
        if indices is not None:
            self.add(indices)

    def contains(self, indices: np.ndarray) -> np.ndarray:
        """Boolean mask: which of ``indices`` are in the set."""
        indices = np.asarray(indices, dtype=np.int64)
        if self.starts.size == 0:
            return np.zeros(indices.shape, dtype=bool)
        where = np.searchsorted(self.starts, indices, side="right") - 1
        return (where >= 0) & (indices < self.stops[np.maximum(where, 0)])

    def add(self, indices: np.ndarray) -> None:
        """Add ``indices`` (any order, repeats allowed)."""
        values = np.unique(np.asarray(indices, dtype=np.int64))
        if values.size == 0:
            return
        breaks = np.flatnonzero(np.diff(values) != 1) + 1
        starts = np.concatenate([self.starts, values[np.r_[0, breaks]]])
        stops = np.concatenate([self.stops, values[np.r_[breaks - 1, values.size - 1]] + 1])
        order = np.argsort(starts, kind="stable")
        starts, stops = starts[order], np.maximum.accumulate(stops[order])
        # A range opens where it starts past the furthest stop so far (touching ranges merge).
        opens = np.r_[True, starts[1:] > stops[:-1]]
        closes = np.r_[np.flatnonzero(opens)[1:] - 1, starts.size - 1]
        self.starts, self.stops = starts[opens], stops[closes]


def _fresh_rows(stored: _IndexSet | None, batch: LevelBatch) -> np.ndarray:
    """Mask of the batch rows not yet stored (first occurrence within the batch wins)."""
    indices = np.asarray(batch.indices, dtype=np.int64)
    is_new = np.ones(len(indices), dtype=bool) if stored is None else ~stored.contains(indices)
    is_first = np.zeros(len(indices), dtype=bool)
    is_first[np.unique(indices, return_index=True)[1]] = True
    return is_new & is_first


def _warn_duplicates(batch: LevelBatch, keep: np.ndarray) -> None:
    n_dup = int(np.count_nonzero(~keep))
    if n_dup:
        shown = ", ".join(str(i) for i in np.asarray(batch.indices)[~keep][:10])
        more = ", ..." if n_dup > 10 else ""
        warn_at_caller(
            f"{n_dup} sample(s) of stage {batch.stage}, level {batch.level} already stored and skipped "
            f"(indices {shown}{more})",
            DuplicateSampleWarning,
        )


def _json_default(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON-able")


def _encode_record(record: Mapping[str, Any], what: str) -> str:
    if not isinstance(record, Mapping):
        raise TypeError(f"{what} must be a mapping, got {type(record).__name__}")
    try:
        return json.dumps(dict(record), default=_json_default)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{what} is not JSON-able: {exc}") from None


def _record_name(key: tuple[str, ...]) -> str:
    """HDF5 path of the record dataset under ``key`` (``screening/record``, ``runs/<run_id>/record``)."""
    return "/".join((*key, "record"))


def _check_run_id(run_id: str) -> None:
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id) or run_id in (".", ".."):
        raise ValueError(f"run_id must be a non-empty name of letters, digits, '_', '-', '.', got {run_id!r}")



# ---------------------------------------------------------------------------
# The interface
# ---------------------------------------------------------------------------


class StudyStore(ABC):
    """What the pipeline needs from a study store; see :class:`StudyFile`, :class:`MemoryStore`.

    Attributes
    ----------
    config_text : str
        The resolved config (YAML) the study was created with.
    config_hash : str
        Its hash (:func:`rough_uq.study.config.config_hash`).
    qoi_names : tuple of str
        Names of the QoI columns of ``fine`` and ``coarse``.
    code_version : str
        roughuq version that created the study.
    created : str
        Creation time, ISO 8601 (UTC).
    role : str
        ``"study"``, or ``"shard"`` for a file of samples to merge into a study (:data:`ROLES`).
    """

    config_text: str
    config_hash: str
    qoi_names: tuple[str, ...]
    code_version: str
    created: str
    role: str = "study"

    def __init__(self) -> None:
        # Stored indices per level and stage, built from the rows at the first
        # append to a level, then kept up to date: duplicates are found without
        # reading the level again.
        self._stored_indices: dict[int, dict[int, _IndexSet]] = {}

    @property
    def n_qoi(self) -> int:
        """Number of QoI columns."""
        return len(self.qoi_names)

    # -- storage primitives ------------------------------------------------

    @abstractmethod
    def _columns(self, level: int) -> dict[str, np.ndarray]:
        """All stored rows of ``level`` (empty columns if none), in append order."""

    @abstractmethod
    def _append_rows(self, level: int, rows: dict[str, np.ndarray]) -> None:
        """Append rows (already free of duplicates) to ``level``."""

    @abstractmethod
    def _stored_levels(self) -> list[int]:
        """Levels with a sample group."""

    def _n_rows(self, level: int) -> int:
        """Number of stored rows of ``level``."""
        return len(self._columns(level)["index"])

    @abstractmethod
    def _write_record(self, key: tuple[str, ...], text: str) -> None:
        """Store JSON text under ``("screening",)`` or ``("runs", run_id)``."""

    @abstractmethod
    def _read_record(self, key: tuple[str, ...]) -> str | None:
        """JSON text under ``key``, or None."""

    @abstractmethod
    def _run_ids(self) -> list[str]:
        """Run ids in creation order."""

    # -- samples -------------------------------------------------------------

    def append_samples(self, batch: LevelBatch) -> int:
        """Store the samples of ``batch`` that are not stored yet.

        Samples whose (stage, level, index) is already stored, or repeated
        within the batch, are skipped with a :class:`DuplicateSampleWarning`.

        Returns
        -------
        int
            Number of samples added.
        """
        self._check_writable()
        if batch.n_qoi != self.n_qoi:
            raise ValueError(f"batch has {batch.n_qoi} QoI columns, the study has {self.n_qoi} ({self.qoi_names})")
        if batch.level < 0:
            raise ValueError(f"level must be >= 0, got {batch.level}")
        stored = self._indices_by_stage(batch.level)
        keep = _fresh_rows(stored.get(batch.stage), batch)
        _warn_duplicates(batch, keep)
        n_new = int(np.count_nonzero(keep))
        if n_new:
            rows = {name: values[keep] for name, values in _batch_columns(batch).items()}
            with signals_held():  # a Ctrl-C meanwhile stops the command once the rows are stored
                self._append_rows(batch.level, rows)
                stored.setdefault(batch.stage, _IndexSet()).add(rows["index"])
        return n_new

    def _indices_by_stage(self, level: int) -> dict[int, _IndexSet]:
        if level not in self._stored_indices:
            columns = self._columns(level)
            self._stored_indices[level] = {
                int(stage): _IndexSet(columns["index"][columns["stage"] == stage])
                for stage in np.unique(columns["stage"])
            }
        return self._stored_indices[level]

    def read_samples(self, *, level: int, stage: int | None = None) -> LevelBatch:
        """The stored samples of one level, of one stage or of all stages.

        Rows are ordered by index (one stage) or by (stage, index) (all
        stages, returned with ``stage = ALL_STAGES``). A level without
        samples gives an empty batch.
        """
        columns = self._columns(level)
        if stage is not None:
            selected = columns["stage"] == stage
            columns = {name: values[selected] for name, values in columns.items()}
        order = np.lexsort((columns["index"], columns["stage"]))
        columns = {name: values[order] for name, values in columns.items()}
        return LevelBatch(
            level=level,
            stage=ALL_STAGES if stage is None else stage,
            indices=columns["index"],
            fine=columns["fine"],
            coarse=columns["coarse"],
            cost=columns["cost"],
            n_iter=columns["n_iter"],
            converged=columns["converged"],
        )

    def sample_indices(self, *, level: int, stage: int) -> np.ndarray:
        """Sorted indices (int64) of the stored samples of (stage, level)."""
        columns = self._columns(level)
        return np.sort(columns["index"][columns["stage"] == stage])

    def levels(self) -> list[int]:
        """Levels that have stored samples, ascending."""
        return sorted(level for level in self._stored_levels() if self._n_rows(level))

    def stages(self, *, level: int) -> list[int]:
        """Stages that have stored samples on ``level``, ascending."""
        return [int(s) for s in np.unique(self._columns(level)["stage"])]

    # -- screening and runs --------------------------------------------------

    def write_screening(self, record: Mapping[str, Any]) -> None:
        """Store (replace) the screening results, a JSON-able mapping."""
        self._check_writable()
        self._write_record(("screening",), _encode_record(record, "screening record"))

    def read_screening(self) -> dict[str, Any] | None:
        """The screening results, or None if none were written."""
        return self._record(("screening",))

    def write_run(self, run_id: str, record: Mapping[str, Any]) -> None:
        """Store (create or replace) the record of an estimation run, a JSON-able mapping.

        A replaced run keeps its place in the creation order.
        """
        self._check_writable()
        _check_run_id(run_id)
        text = _encode_record(record, f"run {run_id!r}")
        if "run_id" in record and record["run_id"] != run_id:
            raise ValueError(f"record has run_id {record['run_id']!r}, written as {run_id!r}")
        self._write_record(("runs", run_id), text)

    def read_runs(self) -> list[dict[str, Any]]:
        """All run records in creation order, each with its ``run_id``."""
        runs = []
        for run_id in self._run_ids():
            data = self._record(("runs", run_id))
            if data is not None:
                runs.append({"run_id": run_id, **data})
        return runs

    def _record(self, key: tuple[str, ...]) -> dict[str, Any] | None:
        """The JSON object stored under ``key``, or None; anything else is a damaged file."""
        text = self._read_record(key)
        if text is None:
            return None
        try:
            data = json.loads(text)
        except ValueError as exc:  # json.JSONDecodeError
            raise self._damaged(_record_name(key), f"not JSON text ({exc})") from None
        except RecursionError:
            raise self._damaged(_record_name(key), "JSON nested too deeply") from None
        if not isinstance(data, dict):
            raise self._damaged(_record_name(key), f"JSON {type(data).__name__}, not an object")
        return data

    def _damaged(self, where: str, reason: str) -> StudyFileError:
        """The error for damaged content at ``where`` (an HDF5 path in the file): names the file and the place."""
        path = getattr(self, "path", None)
        place = "the study" if path is None else str(path)
        return StudyFileError(f"{place} cannot be read: damaged study file ({where}: {reason})", path)

    # -- life cycle ----------------------------------------------------------

    def _check_writable(self) -> None:
        """Raise if this store cannot be written."""

    def close(self) -> None:
        """Release the store (the lock of a study file)."""

    def __enter__(self: _T) -> _T:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()



# ---------------------------------------------------------------------------
# In memory
# ---------------------------------------------------------------------------


class MemoryStore(StudyStore):
    """A study store in memory, with the semantics of :class:`StudyFile`.

    Parameters
    ----------
    qoi_names : sequence of str
        Names of the QoI columns.
    config_text, config_hash, code_version : str, optional
        Recorded as given.
    """

    def __init__(
        self,
        *,
        qoi_names: Sequence[str],
        config_text: str = "",
        config_hash: str = "",
        code_version: str = "",
    ) -> None:
        super().__init__()
        self.qoi_names = tuple(qoi_names)
        self.config_text = config_text
        self.config_hash = config_hash
        self.code_version = code_version
        self.created = utc_timestamp()
        self._samples: dict[int, list[dict[str, np.ndarray]]] = {}
        self._records: dict[tuple[str, ...], str] = {}

    def __repr__(self) -> str:
        return f"MemoryStore(qoi_names={self.qoi_names!r}, levels={self.levels()!r})"

    def _columns(self, level: int) -> dict[str, np.ndarray]:
        if level not in self._samples:
            return _empty_columns(self.n_qoi)
        return _concatenated(self._samples[level])

    def _append_rows(self, level: int, rows: dict[str, np.ndarray]) -> None:
        self._samples.setdefault(level, []).append(rows)

    def _stored_levels(self) -> list[int]:
        return list(self._samples)

    def _n_rows(self, level: int) -> int:
        return sum(len(block["index"]) for block in self._samples.get(level, []))

    def _write_record(self, key: tuple[str, ...], text: str) -> None:
        self._records[key] = text  # dicts keep insertion order: a rewrite keeps its place

    def _read_record(self, key: tuple[str, ...]) -> str | None:
        return self._records.get(key)

    def _run_ids(self) -> list[str]:
        return [key[1] for key in self._records if key[0] == "runs"]


# ---------------------------------------------------------------------------
# HDF5 file
# ---------------------------------------------------------------------------


def _fsync_path(path: Path, *, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        # A file's data and size, not its times: what reading it back after a crash needs.
        (os.fsync if directory else getattr(os, "fdatasync", os.fsync))(fd)  # no fdatasync on macOS
    finally:
        os.close(fd)


def _lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".lock")


def _tmp_path(path: Path) -> Path:
    return path.with_name(f"{path.name}.tmp-{os.getpid()}")


def _remove_stale_tmp(path: Path) -> None:
    pattern = re.compile(re.escape(path.name) + r"\.tmp-\d+$")
    try:
        candidates = list(path.parent.iterdir())
    except OSError:
        return
    for candidate in candidates:
        if pattern.match(candidate.name):
            try:
                candidate.unlink()
            except OSError:
                pass  # not ours to fight over; it is ignored either way


#: Seconds since its last change before a temporary file whose lock is free counts as abandoned.
ABANDONED_AFTER_SECONDS = 60.0


def remove_abandoned(path: Path, suffix: str, *, min_age: float = ABANDONED_AFTER_SECONDS) -> list[Path]:
    """Remove the files ``<path><suffix><pid>`` (and their locks) whose writer has died; the files removed.

    A study file written under a temporary name (a shard's ``.partial-PID``)
    is left behind, with its ``.lock``, by a process killed outright
    (``kill -9``, a lost node). Its writer held the lock while alive
    (:func:`_acquire_lock`; the system releases it when the process dies),
    so a file whose lock can be taken is abandoned; one still locked is
    another process's work and is left alone, and so is one changed in the
    last ``min_age`` seconds: its writer may have closed it (releasing the
    lock) and be about to rename it. A lock file without its file is removed
    too, but not listed.
    """
    pattern = re.compile(re.escape(path.name + suffix) + r"\d+(\.lock)?$")
    try:
        names = {candidate.name.removesuffix(".lock") for candidate in path.parent.iterdir()
                 if pattern.match(candidate.name)}
    except OSError:
        return []
    removed = []
    for name in sorted(names):
        abandoned = path.with_name(name)
        if _age(abandoned) < min_age or _age(_lock_path(abandoned)) < min_age:
            continue
        try:
            fd = _acquire_lock(abandoned)
        except StudyFileError:
            continue  # held: a running process writes it
        try:
            if abandoned.exists():
                abandoned.unlink()
                removed.append(abandoned)
        except OSError:
            pass  # not ours to fight over
        finally:
            _release_lock(abandoned, fd)
    return removed


def _age(path: Path) -> float:
    """Seconds since ``path`` last changed; infinite for a missing file."""
    try:
        return time.time() - path.stat().st_mtime
    except OSError:
        return math.inf


def is_lock_held(path: str | Path) -> bool:
    """Whether a process holds the lock of the study file ``path`` now (False where it has no lock file).

    Probed with a shared non-blocking ``flock``, released at once: the pid a lock file names outlives its
    process (``kill -9``) and may be another process's later, so only the lock itself says "running".
    """
    try:
        fd = os.open(_lock_path(Path(path)), os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)
    finally:
        os.close(fd)  # closing releases a lock taken
    return False


def is_locked_by_running_process(path: str | Path) -> bool:
    """Whether a live process holds the study's lock.

    ``<file>.lock`` names its holder's pid (:func:`_acquire_lock`); a live pid counts only while the lock is held
    (:func:`is_lock_held`): after a ``kill -9`` its pid may be another process's, and a dead
    run read "running" for as long as that process lived.
    """
    try:
        pid = int(_lock_path(Path(path)).read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return is_lock_held(path)


#: Tries, :data:`_LOCK_RETRY_SECONDS` apart, of a writer's exclusive lock before the file counts as locked.
_LOCK_TRIES = 20
_LOCK_RETRY_SECONDS = 0.01


def _flock_exclusive(fd: int) -> None:
    """The exclusive ``flock`` of ``fd``, tried for some 0.2 s before the ``OSError`` of a held lock is raised.

    :func:`is_lock_held` (``roughuq report``'s "running") holds a shared lock for microseconds: a writer that
    started then was refused as "locked by a running process (pid unknown)" (2-3 of 25 reruns beside a loop of
    probes), though readers need no lock.
    """
    for attempt in range(_LOCK_TRIES):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES) or attempt == _LOCK_TRIES - 1:
                raise
        time.sleep(_LOCK_RETRY_SECONDS)


def _acquire_lock(path: Path) -> int:
    """Take the exclusive lock of ``path``; return the lock file descriptor."""
    lock_path = _lock_path(path)
    for _ in range(100):
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise StudyFileError(
                f"{path}: cannot create the lock file {lock_path.name} in {path.parent} ({exc.strerror})", path
            ) from None
        try:
            _flock_exclusive(fd)
        except OSError as exc:
            holder = os.read(fd, 64).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise StudyFileError(
                    f"{path} is locked by a running process (pid {holder}); wait for it to finish or use another file",
                    path,
                ) from None
            raise StudyFileError(f"{path}: cannot lock {lock_path.name} ({exc.strerror})", path) from None
        # The previous holder may have removed the lock file between our open
        # and our flock; then we hold a lock nobody else can see. Start over.
        try:
            is_current = os.fstat(fd).st_ino == os.stat(lock_path).st_ino
        except FileNotFoundError:
            is_current = False
        if is_current:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode("ascii"))
            return fd
        os.close(fd)
    raise StudyFileError(f"{path}: could not take the lock {lock_path.name}", path)


#: What ``roughuq sample`` appends to a shard's name, with its pid, until the shard is complete.
PARTIAL_SUFFIX = ".partial-"


def incomplete_shard_name(path: str | os.PathLike[str]) -> tuple[str, str] | None:
    """``(name, pid)`` of a shard file named ``<name>.partial-<pid>`` (not yet complete), None for any other."""
    name, separator, pid = Path(path).name.rpartition(PARTIAL_SUFFIX)
    return (name, pid) if separator and pid.isdigit() else None


@contextmanager
def lock_if_free(path: str | os.PathLike[str]) -> Iterator[bool]:
    """Hold the lock of the study file ``path`` for the block if no other process holds it; yields whether held.

    For removing a file only its creator may remove: a command refused on a study another process had just
    created (and held) removed that file as "unused", and the other command failed on a file gone.
    """
    try:
        fd = _acquire_lock(Path(path))
    except StudyFileError:
        yield False
        return
    try:
        yield True
    finally:
        _release_lock(Path(path), fd)


def _release_lock(path: Path, fd: int) -> None:
    try:
        _lock_path(path).unlink()  # while still holding the lock, see _acquire_lock
    except OSError:
        # Gone, or a directory made read-only since (a PermissionError here was a traceback that hid the
        # command's own error): the lock file stays, and the closing below releases the lock all the same.
        pass
    finally:
        os.close(fd)


#: What to do with a study file HDF5 cannot read (a reader on NFS may fail while another machine writes).
_UNREADABLE_REMEDY = (
    "if a roughuq command on another machine is writing it, try again once it has finished; "
    "otherwise restore the file from a copy or start a new study file"
)

# What h5py raises for a file it cannot read: OSError, and RuntimeError or KeyError for some damaged metadata.
_HDF5_READ_ERRORS = (OSError, RuntimeError, KeyError)


def _unreadable(path: Path, exc: BaseException) -> StudyFileError:
    """The error for a study file HDF5 cannot read: names the file, says it is damaged, says what to do."""
    reason = exc.args[0] if len(exc.args) == 1 and isinstance(exc.args[0], str) else str(exc)
    if any(clash in reason for clash in _OPEN_IN_THIS_PROCESS):
        return StudyFileError(
            f"{path} is already open in this process with other settings (an h5py.File of your own?), which HDF5 "
            f"refuses ({reason}): close it and read again; roughuq opens study files itself, read-only with HDF5 "
            "file locking off", path)
    return StudyFileError(f"{path} cannot be read: truncated or damaged study file ({reason}); {_UNREADABLE_REMEDY}",
                          path)


#: HDF5's refusals to open a file that this process holds open with other flags: the file is sound.
_OPEN_IN_THIS_PROCESS = ("file locking flag values don't match", "not the same for file that is already open")


def _read_text(dataset: Any) -> str:
    value = dataset[()]
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


@functools.cache
def _read_attempts_setter() -> Callable[[int, int], int] | None:
    """HDF5's ``H5Pset_metadata_read_attempts`` (h5py does not wrap it), from the library h5py uses; None if absent."""
    try:
        setter = ctypes.CDLL(h5py.h5p.__file__).H5Pset_metadata_read_attempts  # searches h5p's libhdf5 too
    except (OSError, AttributeError):
        return None
    setter.argtypes = [ctypes.c_int64, ctypes.c_uint]  # hid_t is 64 bits since HDF5 1.10
    setter.restype = ctypes.c_int
    return setter


def _swmr_access() -> h5py.h5p.PropFAID:
    """File access for a SWMR open: HDF5's file locking off (module docstring), bounded metadata read retries."""
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    fapl.set_file_locking(False, True)
    setter = _read_attempts_setter()
    if setter is not None and setter(fapl.id, _SWMR_READ_ATTEMPTS) < 0:  # pragma: no cover - HDF5 refused
        raise RuntimeError(f"H5Pset_metadata_read_attempts refused {_SWMR_READ_ATTEMPTS}")
    return fapl


def _open_for_reading(path: Path) -> h5py.File:
    """Open ``path`` read-only in SWMR mode: works while a writer appends, and after one died.

    A read that finds damaged metadata fails after :data:`_SWMR_READ_ATTEMPTS`
    attempts (about a second) instead of retrying for hours.
    """
    fapl = _swmr_access()
    fapl.set_libver_bounds(h5py.h5f.LIBVER_EARLIEST, h5py.h5f.LIBVER_LATEST)  # h5py's default for reading
    flags = h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ
    return h5py.File(h5py.h5f.open(os.fsencode(path), flags, fapl=fapl))


def _open_checked(path: Path) -> h5py.File:
    """Open ``path`` read-only with HDF5's checks (a truncated file is refused) unless a writer has it.

    SWMR readers skip the end-of-file check (a live writer may have reserved
    space it has not written yet), so a file nobody writes is opened without.
    """
    if not _is_marked_open(path):
        try:
            return h5py.File(path, "r", locking=False)
        except OSError:
            if not _is_marked_open(path):  # not a writer that arrived meanwhile
                raise
    return _open_for_reading(path)


def _is_marked_open(path: Path) -> bool:
    """Whether the superblock says a writer has the file open (HDF5 file format, superblock v2+).

    The flag byte follows the signature, the superblock version and two size
    bytes. Once we hold the lock, no roughuq writer is alive, so a set flag
    was left by one that died.
    """
    with open(path, "rb") as stream:
        head = stream.read(12)
    return len(head) == 12 and head[:8] == _HDF5_SIGNATURE and head[8] >= 2 and head[11] != 0


def checked_study_path(path: str | os.PathLike[str]) -> Path:
    """``path`` as a :class:`~pathlib.Path`, refusing an empty one (``Path("")`` is the working directory) and one
    that is no path (``None``, a number: :class:`~rough_uq.errors.InvalidParameterError`)."""
    text = checked_path("path", path)
    if not text:
        raise StudyFileError("no study file named (got an empty path; allowed: the HDF5 file `roughuq screen` wrote)",
                             Path())
    return Path(text)


def is_hdf5_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is an existing, readable HDF5 file (a study file or another); False for anything else."""
    try:
        return Path(path).is_file() and h5py.is_hdf5(path)
    except OSError:
        return False


def _read_header(path: Path) -> dict[str, Any]:
    """Check that ``path`` is a readable study file of this format; return its header."""
    if not path.exists():
        raise StudyFileError(f"{path}: no such study file", path)
    if not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file (a device or a pipe?)"
        raise StudyFileError(f"{path} is {kind} (got {os.fspath(path)!r}; allowed: a study file)", path)
    if path.stat().st_size == 0:
        raise StudyFileError(f"{path} is empty, not a study file", path)
    try:
        is_hdf5 = h5py.is_hdf5(path)
    except OSError as exc:
        raise StudyFileError(f"{path} cannot be read ({exc})", path) from None
    if not is_hdf5:
        hint = ("; it looks like a config: a study file is the HDF5 file `roughuq screen CONFIG` writes (the "
                "config's output.path, or --out)" if path.suffix.lower() in (".yaml", ".yml") else "")
        raise StudyFileError(f"{path} is not an HDF5 file (so not a roughuq study file){hint}", path)
    try:
        with _open_checked(path) as f:
            found = f.attrs.get("format")
            found = None if found is None else _text_attribute(found)
            if found != FORMAT:
                attribute = "no 'format' attribute" if found is None else f"its 'format' attribute is {found!r}"
                raise StudyFileError(
                    f"{path} is an HDF5 file but not a roughuq study file ({attribute}; a study file's is {FORMAT!r})",
                    path,
                )
            version = f.attrs.get("format_version")
            if version is None or int(version) not in READABLE_VERSIONS:
                readable = ", ".join(str(v) for v in READABLE_VERSIONS[:-1]) + f" and {READABLE_VERSIONS[-1]}"
                raise StudyFileError(
                    f"{path} has study format version {version}; this roughuq reads versions {readable}",
                    path,
                )
            header = {
                "format_version": int(version),
                "config_hash": str(f.attrs["config_hash"]),
                "code_version": str(f.attrs["code_version"]),
                "created": str(f.attrs["created"]),
                "role": _text_attribute(f.attrs.get("role", ROLES[0])),
                "config_text": _read_text(f["config_yaml"]),
                "qoi_names": tuple(f["qoi_names"].asstr()[()]),
                "has_samples": isinstance(f.get("samples"), h5py.Group),
            }
            stored = f.attrs.get(_HEADER_CHECKSUM)
            if stored is not None and _text_attribute(stored) != header_checksum(
                header["config_text"], header["qoi_names"]
            ):
                raise StudyFileError(
                    f"{path} cannot be read: damaged study file (its stored config or QoI names do not match their "
                    "checksum); restore it from a copy, or start a new study file",
                    path,
                )
            return header
    except StudyFileError:
        raise
    except (*_HDF5_READ_ERRORS, ValueError, TypeError) as exc:
        raise _unreadable(path, exc) from None


#: Root attribute: :func:`header_checksum` of the stored config text and QoI names.
_HEADER_CHECKSUM = "header_checksum"


def header_checksum(config_text: str, qoi_names: Sequence[str]) -> str:
    """SHA-256 (hex) of a study file's config text and QoI names (``header_checksum``, module docstring)."""
    return hashlib.sha256("\0".join((config_text, *qoi_names)).encode("utf-8")).hexdigest()


def _text_attribute(value: Any) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _write_header(
    f: h5py.File, *, config_text: str, config_hash: str, qoi_names: Sequence[str], code_version: str, role: str
) -> None:
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = np.int64(FORMAT_VERSION)
    f.attrs["role"] = role
    f.attrs["config_hash"] = config_hash
    f.attrs["code_version"] = code_version
    f.attrs["created"] = utc_timestamp()
    f.attrs[_HEADER_CHECKSUM] = header_checksum(config_text, qoi_names)
    f.create_dataset("config_yaml", data=config_text, dtype=h5py.string_dtype())
    f.create_dataset("qoi_names", data=list(qoi_names), dtype=h5py.string_dtype())
    f.create_group("samples")
    f.create_group("runs")


def _create_level(f: h5py.File, level: int, columns: Mapping[str, np.ndarray]) -> None:
    """Create ``samples/level_<level>`` holding ``columns`` (all committed)."""
    group = f["samples"].create_group(f"level_{level}")
    group.attrs["level"] = np.int64(level)
    stored = {**{name: columns[name] for name in _COLUMNS}, _CHECKSUM: _row_checksums(columns)}
    for name, values in stored.items():
        tail = values.shape[1:]
        group.create_dataset(name, data=values, maxshape=(None, *tail), chunks=(_CHUNK_ROWS, *tail))
    group.create_dataset(_COMMITTED, data=np.int64(len(columns["index"])))


def _committed_rows(f: h5py.File, version: int) -> dict[int, int]:
    """Committed row count of every level group (version 1: every row); a malformed group is :class:`_DamagedRows`."""
    counts = {}
    samples = f["samples"]
    for name in samples:
        group = samples[name]  # not values(), which gives None for a group HDF5 cannot read (a damaged file)
        where = f"samples/{name}"
        if not isinstance(group, h5py.Group):
            raise _DamagedRows(f"{where}: {_describe_node(group)}, not a group of sample columns")
        level = _stored_integer(group.attrs.get("level"), f"{where}: its 'level' attribute")
        if name != f"level_{level}":
            raise _DamagedRows(f"{where}: its 'level' attribute is {level}")
        if version >= 2:
            counts[level] = _stored_integer(_scalar(group, _COMMITTED), f"{where}/{_COMMITTED}")
        else:
            counts[level] = _column(group, where, "index", 0).shape[0]
    return counts


#: What each sample column holds: the kinds of dtype allowed (numpy's ``dtype.kind``) and its shape after the rows
#: (``None``: one value per QoI).
_COLUMN_LAYOUT: dict[str, tuple[str, tuple[int | None, ...]]] = {
    "stage": ("iu", ()),
    "index": ("iu", ()),
    "fine": ("f", (None,)),
    "coarse": ("f", (None,)),
    "cost": ("f", ()),
    "n_iter": ("iu", (2,)),
    "converged": ("b", (2,)),
    _CHECKSUM: ("u", ()),
}
_KIND_WORDS = {"iu": "integer", "f": "float", "b": "boolean", "u": "unsigned integer"}


def _describe_node(node: Any) -> str:
    """``a dataset of shape (3,) and dtype float32``, ``a group``, ``nothing``: what a damaged file holds there."""
    if node is None:
        return "nothing"
    if isinstance(node, h5py.Dataset):
        return f"a dataset of shape {node.shape} and dtype {node.dtype}"
    return "a group" if isinstance(node, h5py.Group) else f"a {type(node).__name__}"


def _scalar(group: h5py.Group, name: str) -> Any:
    """The value of the scalar dataset ``name`` of ``group`` (:class:`_DamagedRows` for anything else)."""
    node = group.get(name)
    if not isinstance(node, h5py.Dataset) or node.shape != ():
        raise _DamagedRows(f"{group.name.lstrip('/')}/{name}: {_describe_node(node)}, not a count")
    return node[()]


def _stored_integer(value: Any, what: str) -> int:
    """``value`` (read from the file) as a non-negative int; :class:`_DamagedRows` naming ``what`` otherwise."""
    array = np.asarray(value) if value is not None else None
    if array is None or array.shape != () or array.dtype.kind not in "iu" or int(array) < 0:
        shown = array.item() if array is not None and array.shape == () and array.dtype.kind != "O" else value
        raise _DamagedRows(f"{what} is {shown!r}, not a non-negative integer")
    return int(array)


def _column(group: h5py.Group, where: str, name: str, n_rows: int, n_qoi: int | None = None) -> h5py.Dataset:
    """The dataset of column ``name``, checked against :data:`_COLUMN_LAYOUT` and for at least ``n_rows`` rows."""
    dataset = group.get(name)
    kinds, tail = _COLUMN_LAYOUT[name]
    expected = tuple(n_qoi if size is None else size for size in tail)
    if (
        not isinstance(dataset, h5py.Dataset)
        or dataset.dtype.kind not in kinds
        or len(dataset.shape) != 1 + len(tail)
        or (n_qoi is not None and dataset.shape[1:] != expected)
    ):
        shape = ", ".join(["rows", *(("QoIs" if size is None else str(size)) for size in expected)])
        raise _DamagedRows(f"{where}/{name}: {_describe_node(dataset)}, not {_KIND_WORDS[kinds]} values of shape "
                           f"({shape})")
    if dataset.shape[0] < n_rows:  # a SWMR reader's cached extent; ask the file again
        dataset.refresh()
        if dataset.shape[0] < n_rows:
            raise _DamagedRows(f"{where}/{name}: {dataset.shape[0]} rows, fewer than the {n_rows} committed")
    return dataset


def _read_columns(f: h5py.File, level: int, n_rows: int, version: int, n_qoi: int) -> dict[str, np.ndarray]:
    """The first ``n_rows`` rows of ``level`` of a file of format ``version`` with ``n_qoi`` QoIs, checked against
    their layout and from version 3 on their checksums (:class:`_DamagedRows`)."""
    where = f"samples/level_{level}"
    group = f[where]
    is_checked = version >= 3
    if is_checked and _CHECKSUM not in group:
        raise _DamagedRows(f"{where}: no {_CHECKSUM} dataset")
    columns = {}
    for name in (*_COLUMNS, _CHECKSUM) if is_checked else _COLUMNS:
        columns[name] = _column(group, where, name, n_rows, n_qoi)[:n_rows]
    if is_checked:
        _check_rows(level, columns.pop(_CHECKSUM), columns)
    return columns


class _DamagedRows(RuntimeError):
    """Sample columns of the wrong layout, or rows that differ from their checksums: reported as a damaged file
    (one of :data:`_HDF5_READ_ERRORS`, and not an OSError, which a copy-on-write transaction would report as a
    failed write)."""


def _check_rows(level: int, checksums: np.ndarray, columns: Mapping[str, np.ndarray]) -> None:
    """Raise :class:`_DamagedRows` where rows of ``level`` differ from their stored checksums."""
    bad = np.flatnonzero(_row_checksums(columns) != checksums)
    if bad.size:
        rows = ", ".join(str(row) for row in bad[:3]) + (", ..." if bad.size > 3 else "")
        raise _DamagedRows(f"samples/level_{level}: {bad.size} of {len(checksums)} rows differ from their checksums "
                      f"(rows {rows})")


class StudyFile(StudyStore):
    """A study stored in an HDF5 file (see the module docstring for layout and crash safety).

    Create with :func:`open_study` (writable, locked) or
    :func:`open_study_readonly`. Use as a context manager; the lock is
    released and the file closed on exit.

    Attributes
    ----------
    path : pathlib.Path
        The study file.
    read_only : bool
        Whether writes are refused.
    format_version : int
        Layout version of the file (a writable file is always the current one).
    """

    def __init__(self, path: Path, header: Mapping[str, Any], *, lock_fd: int | None) -> None:
        super().__init__()
        self.path = path
        self.read_only = lock_fd is None
        self.format_version = int(header["format_version"])
        self.config_text = header["config_text"]
        self.config_hash = header["config_hash"]
        self.qoi_names = tuple(header["qoi_names"])
        self.code_version = header["code_version"]
        self.created = header["created"]
        self.role = header["role"]
        self._lock_fd = lock_fd
        self._is_closed = False
        self._h5: h5py.File | None = None
        # Committed rows per level and the rows read so far. A reader's are a
        # snapshot; a writer's stay valid because nobody else writes the file.
        self._committed: dict[int, int] | None = None
        self._cache: dict[int, list[dict[str, np.ndarray]]] = {}
        self._datasets: dict[int, dict[str, h5py.Dataset]] = {}  # a writer's open datasets per level

    def __repr__(self) -> str:
        mode = "read-only" if self.read_only else "writable"
        return f"StudyFile({str(self.path)!r}, {mode}{', closed' if self._is_closed else ''})"

    # -- life cycle ----------------------------------------------------------

    def close(self) -> None:
        """Close the file and release the lock; further writes are refused. Safe to call twice."""
        if not self._is_closed:
            self._is_closed = True
            self._forget()
            if self._lock_fd is not None:
                _release_lock(self.path, self._lock_fd)
                self._lock_fd = None

    def _check_writable(self) -> None:
        if self.read_only:
            raise StudyFileError(f"{self.path} was opened read-only", self.path)
        if self._is_closed:
            raise StudyFileError(f"{self.path} is closed", self.path)

    # -- file access ----------------------------------------------------------

    def _handle(self) -> h5py.File:
        """The open HDF5 file: SWMR reading for a reader, SWMR writing for a writer."""
        if self._h5 is None:
            if not self.read_only and _is_marked_open(self.path):
                # Our own handle failed to close after a write error; we hold the lock.
                with signals_held():
                    _rewrite(self.path)
            try:
                self._h5 = _open_for_reading(self.path) if self.read_only else _open_for_writing(self.path)
            except _HDF5_READ_ERRORS as exc:
                if self.read_only:
                    raise _unreadable(self.path, exc) from None
                raise StudyFileError(f"{self.path} cannot be opened ({exc})", self.path) from None
        return self._h5

    def _close_handle(self) -> None:
        self._datasets.clear()
        if self._h5 is not None:
            h5, self._h5 = self._h5, None
            try:
                h5.close()
            except (OSError, RuntimeError):  # HDF5 reports a failed flush (a full disk) as a RuntimeError
                pass  # a writer's mark may stay in the superblock; the next writer rewrites the file

    def _forget(self) -> None:
        """Close the file and drop everything read from it."""
        self._close_handle()
        self._committed = None
        self._cache.clear()
        self._stored_indices.clear()

    @contextmanager
    def _reading(self) -> Iterator[h5py.File]:
        """The file to read: the cached handle, or (closed store) a handle for this read only."""
        try:
            if self._is_closed:
                with _open_for_reading(self.path) as f:
                    yield f
            else:
                yield self._handle()
        except _HDF5_READ_ERRORS as exc:
            raise _unreadable(self.path, exc) from None

    def _committed_counts(self) -> dict[int, int]:
        if self._is_closed:
            with self._reading() as f:
                return _committed_rows(f, self.format_version)
        if self._committed is None:
            with self._reading() as f:
                self._committed = _committed_rows(f, self.format_version)
        return self._committed

    def _transaction(self, action: Callable[[h5py.File], None]) -> None:
        """Apply ``action`` to a copy of the file, then atomically replace the file by the copy."""
        self._check_writable()
        self._close_handle()  # a complete file on disk, without the writer's mark, to copy
        with signals_held():  # a Ctrl-C meanwhile stops the command once the file is replaced
            _replace_atomically(self.path, action, copy_from=self.path)

    # -- storage primitives ----------------------------------------------------

    def _columns(self, level: int) -> dict[str, np.ndarray]:
        if level in self._cache:
            return _concatenated(self._cache[level])
        n_rows = self._committed_counts().get(level, 0)
        if n_rows == 0:
            return _empty_columns(self.n_qoi)
        with self._reading() as f:
            columns = _read_columns(f, level, n_rows, self.format_version, self.n_qoi)
        if not self._is_closed:
            self._cache[level] = [columns]
        return columns

    def _n_rows(self, level: int) -> int:
        return self._committed_counts().get(level, 0)

    def _stored_levels(self) -> list[int]:
        return list(self._committed_counts())

    def _append_rows(self, level: int, rows: dict[str, np.ndarray]) -> None:
        committed = self._committed_counts()
        n_rows = len(rows["index"])
        if level not in committed:
            self._transaction(lambda f: _create_level(f, level, rows))
            committed[level] = n_rows
            return
        n_old = committed[level]
        n_new = n_old + n_rows
        try:
            f = self._handle()
            if level not in self._datasets:
                group = f[f"samples/level_{level}"]
                self._datasets[level] = {name: group[name] for name in (*_COLUMNS, _CHECKSUM, _COMMITTED)}
            datasets = self._datasets[level]
            for name, values in {**rows, _CHECKSUM: _row_checksums(rows)}.items():
                if datasets[name].shape[0] < n_new:
                    datasets[name].resize(n_new, axis=0)
                datasets[name][n_old:n_new] = values
            f.flush()
            _fsync_path(self.path)  # the rows are on disk before the count that makes them visible
            datasets[_COMMITTED][()] = n_new
            f.flush()
            _fsync_path(self.path)
        except BaseException as exc:
            # Whether the count reached the file is unknown: read everything again from the file.
            self._forget()
            if isinstance(exc, (OSError, RuntimeError)):  # HDF5's failed flush (a full disk): a RuntimeError
                raise StudyFileError(
                    f"{self.path}: could not write ({_write_failure(exc)}); the committed samples are intact, "
                    "this batch may be missing",
                    self.path,
                ) from None
            raise
        committed[level] = n_new
        if level in self._cache:
            self._cache[level].append(rows)

    def _write_record(self, key: tuple[str, ...], text: str) -> None:
        data = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)

        def write(f: h5py.File) -> None:
            group = f.get("/".join(key))
            if group is None:
                group = f.create_group("/".join(key))
                if key[0] == "runs":
                    group.attrs["order"] = np.int64(len(f["runs"]) - 1)
            if "record" not in group:
                _new_record(group, np.zeros(0, dtype=np.uint8))
            record = group["record"]
            record.resize(len(data), axis=0)
            if len(data):
                record[:] = data

        self._transaction(write)

    def _read_record(self, key: tuple[str, ...]) -> str | None:
        name = _record_name(key)
        with self._reading() as f:
            record = f.get(name)
            if record is None:
                return None
            if not (isinstance(record, h5py.Dataset) and record.dtype == np.uint8 and record.ndim == 1):
                raise self._damaged(name, f"{_describe(record)}, not a byte array (uint8)")
            data = record[()]
        try:
            return data.tobytes().decode("utf-8")
        except UnicodeDecodeError as exc:
            raise self._damaged(name, f"not UTF-8 text (byte {exc.start}: {exc.reason})") from None

    def _run_ids(self) -> list[str]:
        with self._reading() as f:
            try:
                runs = f["runs"]
                return sorted(runs, key=lambda run_id: int(runs[run_id].attrs["order"]))
            except (KeyError, TypeError, ValueError) as exc:
                raise self._damaged("runs", f"no readable creation order ({exc})") from None


def _describe(item: h5py.Group | h5py.Dataset) -> str:
    """What an HDF5 object is, in words (``a string dataset``, ``a float64 dataset of shape (3,)``, ``a group``)."""
    if not isinstance(item, h5py.Dataset):
        return "a group"
    if h5py.check_string_dtype(item.dtype) is not None:
        return "a string dataset"
    return f"a {item.dtype} dataset of shape {item.shape}"


def _open_for_writing(path: Path) -> h5py.File:
    """Open ``path`` (a file of this version without a writer's mark) for appending in SWMR mode.

    One open marks the superblock "SWMR writer" at once. (h5py's ``"r+"``
    followed by ``swmr_mode = True`` marks it "writer" first: a kill in
    between leaves a file that neither a SWMR nor a plain reader opens.)
    """
    fapl = _swmr_access()
    fapl.set_libver_bounds(h5py.h5f.LIBVER_V110, h5py.h5f.LIBVER_V110)
    flags = h5py.h5f.ACC_RDWR | h5py.h5f.ACC_SWMR_WRITE
    return h5py.File(h5py.h5f.open(os.fsencode(path), flags, fapl=fapl))


def _replace_atomically(
    path: Path, action: Callable[[h5py.File], None], *, copy_from: Path | None
) -> None:
    """Write ``path`` through a temporary file: copy (or create), change, fsync, rename."""
    tmp = _tmp_path(path)
    try:
        if copy_from is not None:
            shutil.copyfile(copy_from, tmp)
            shutil.copymode(copy_from, tmp)
        with h5py.File(tmp, "r+" if copy_from is not None else "w", libver=_LIBVER, locking=False) as f:
            action(f)
        _fsync_path(tmp)
        os.replace(tmp, path)
        _fsync_path(path.parent, directory=True)
    except _DamagedRows:  # read from the file copied (a rewrite): damage, reported as such by the caller
        tmp.unlink(missing_ok=True)
        raise
    except (OSError, RuntimeError) as exc:  # HDF5 reports a failed flush or close (a full disk) as a RuntimeError
        tmp.unlink(missing_ok=True)
        # "the study file is unchanged" read as if a run's earlier samples were lost with it: they are not.
        raise StudyFileError(f"{path}: could not write ({_write_failure(exc)}); the study file is unchanged by "
                             "this write, and what it held before is kept: rerun the command once it can write",
                             path) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_failure(error: OSError | RuntimeError) -> str:
    """Why a write failed, in a few words: the system's reason (``No space left on device``) where there is one.

    HDF5's errors are RuntimeErrors whose text is its whole error stack; the system's reason is in it.
    """
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    text = str(error)
    match = re.search(r"error message = '([^']+)'", text)
    return match.group(1) if match else text.splitlines()[0][:200]


def _rewrite(path: Path) -> None:
    """Rewrite ``path`` as a fresh file of this version holding its committed rows only (atomically).

    Converts a version 1 or 2 file, and cleans up after a writer that died: drops
    rows beyond ``n_committed`` and the writer's mark in the superblock.
    """
    try:
        src = _open_for_reading(path)
    except _HDF5_READ_ERRORS as exc:
        raise _unreadable(path, exc) from None
    with src:
        try:
            version = int(src.attrs["format_version"])
            committed = _committed_rows(src, version)
            _replace_atomically(path, lambda dst: _copy_committed(src, dst, committed, version), copy_from=None)
        except _HDF5_READ_ERRORS as exc:  # reading ``src`` failed (_replace_atomically reports its writing)
            raise _unreadable(path, exc) from None


def _copy_committed(src: h5py.File, dst: h5py.File, committed: Mapping[int, int], version: int) -> None:
    """Copy the header, records and ``committed`` rows per level of ``src`` (of format ``version``) into the new file
    ``dst`` (of :data:`FORMAT_VERSION`, with the checksums of rows and records)."""
    for name in ("format", "config_hash", "code_version", "created"):
        dst.attrs[name] = src.attrs[name]
    if "role" in src.attrs:
        dst.attrs["role"] = src.attrs["role"]
    # Kept as it is (the caller read the header, which checked it), or first computed for a file without one.
    dst.attrs[_HEADER_CHECKSUM] = src.attrs[_HEADER_CHECKSUM] if _HEADER_CHECKSUM in src.attrs else header_checksum(
        _read_text(src["config_yaml"]), tuple(src["qoi_names"].asstr()[()])
    )
    dst.attrs["format_version"] = np.int64(FORMAT_VERSION)
    for name in ("config_yaml", "qoi_names", "runs", "screening"):
        if name in src:
            src.copy(src[name], dst, name)
    for record in _record_datasets(dst):
        _with_checksums(record)
    dst.create_group("samples")
    n_qoi = len(src["qoi_names"])
    for level, n_rows in sorted(committed.items()):
        _create_level(dst, level, _read_columns(src, level, n_rows, version, n_qoi))


def _record_datasets(f: h5py.File) -> list[h5py.Dataset]:
    """The record datasets of ``f``: the screening's and every run's."""
    groups = [f["screening"]] if "screening" in f else []
    groups += list(f["runs"].values()) if "runs" in f else []
    return [group["record"] for group in groups if isinstance(group.get("record"), h5py.Dataset)]


def _with_checksums(record: h5py.Dataset) -> None:
    """Re-create ``record`` (a copy's, in a transaction) with HDF5's Fletcher-32 checksum, where it has none."""
    if record.fletcher32:
        return
    group, data = record.parent, record[()]
    del group["record"]
    _new_record(group, data)


def _new_record(group: h5py.Group, data: np.ndarray) -> None:
    """Create ``group/record`` holding ``data``: uint8, resizable, with HDF5's Fletcher-32 checksum per chunk."""
    group.create_dataset("record", data=data, maxshape=(None,), chunks=(_RECORD_CHUNK,), dtype=np.uint8,
                         fletcher32=True)

def _installed_version() -> str:
    """The installed roughuq version (imported late: the package imports this module)."""
    from rough_uq import __version__

    return __version__


def _check_before_lock(path: Path, *, create: bool) -> None:
    """Refuse a missing (``create=False``) or foreign file, or make sure a new one's directory is writable."""
    if path.exists():
        _read_header(path)  # refuse foreign files before touching their directory
    elif not create:
        raise StudyFileError(f"{path}: no such study file", path)
    else:
        _make_directory(path)


def _make_directory(path: Path) -> None:
    """Create the missing parent directories of ``path``; refuse a directory this process cannot write in."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as exc:
        # It said "cannot create the directory afile (File exists)" of a file in the way.
        blocking = [parent for parent in reversed(path.parents) if parent.exists() and not parent.is_dir()]
        what = (f"{blocking[0]} is a file, not a directory" if blocking
                else f"cannot create the directory {path.parent} ({exc.strerror})")
        raise StudyFileError(f"{path}: {what}", path) from None
    except OSError as exc:
        raise StudyFileError(f"{path}: cannot create the directory {path.parent} ({exc.strerror})", path) from None
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise StudyFileError(f"{path}: the directory {path.parent} is not writable", path)


def _prepare_locked(
    path: Path, *, config_text: str, config_hash: str, qoi_names: Sequence[str], code_version: str, role: str
) -> dict[str, Any]:
    """With the lock held: create the file if missing, check it, bring it to this version; its header.

    A Ctrl-C or SIGTERM while the file is written takes effect once it is in place: raised inside h5py's
    conversion of a text attribute, a KeyboardInterrupt came out as "TypeError: Operation not defined for data
    type class" (a traceback, status 1).
    """
    if not path.exists():
        with signals_held():
            _replace_atomically(
                path,
                lambda f: _write_header(
                    f,
                    config_text=config_text,
                    config_hash=config_hash,
                    qoi_names=qoi_names,
                    code_version=str(code_version),
                    role=role,
                ),
                copy_from=None,
            )
    header = _read_header(path)
    _check_header(path, header, config_hash=config_hash, qoi_names=qoi_names)
    _check_role(path, header["role"], role)
    _remove_stale_tmp(path)  # left by a killed writer; we hold the lock, so none is live
    if header["format_version"] != FORMAT_VERSION or _is_marked_open(path):
        with signals_held():
            _rewrite(path)
        header = _read_header(path)
    return header


def _check_role(path: Path, found: str, wanted: str) -> None:
    """Refuse to write a shard as a study (or the other way round): its records would never reach the study."""
    if found == wanted:
        return
    if found == "shard":
        raise shard_refusal(path)
    raise StudyFileError(f"{path} is a {found} file, not a {wanted} file", path)


def shard_refusal(path: Path) -> StudyFileError:
    """The refusal of a shard file where a study is needed, with what to do instead."""
    return StudyFileError(
        f"{path} is a shard of samples (written by `roughuq sample`), not a study: add its samples to their "
        f"study with `roughuq merge --into STUDY {path}` and run there",
        path,
    )


def _check_header(path: Path, header: Mapping[str, Any], *, config_hash: str, qoi_names: Sequence[str]) -> None:
    """Refuse a file without a samples group, written by another config, or whose QoI columns are not the config's."""
    if not header["has_samples"]:
        raise StudyFileError(f"{path} cannot be read: damaged study file (no samples group)", path)
    if header["config_hash"] != config_hash:
        raise StudyFileError(
            f"{path} was written by another config "
            f"(hash {header['config_hash'][:12]}… ≠ {config_hash[:12]}…); "
            "use another study file or the config it was written with",
            path,
        )
    if tuple(header["qoi_names"]) != tuple(qoi_names):
        # The hash covers the QoI columns: equal hashes with other names mean the stored names were altered.
        raise StudyFileError(
            f"{path} cannot be read: damaged study file (qoi_names {list(header['qoi_names'])} are not the "
            f"result columns of its config, {list(qoi_names)})",
            path,
        )


def open_study(
    path: str | os.PathLike[str],
    *,
    config_text: str,
    config_hash: str,
    qoi_names: Sequence[str],
    create: bool = True,
    code_version: str | None = None,
    role: str = "study",
) -> StudyFile:
    """Open a study file for writing, creating it if asked; takes the file's lock.

    A version 1 or 2 file, and a file whose last writer died, are first
    rewritten as a file of version :data:`FORMAT_VERSION` holding the
    committed samples, with their checksums (module docstring).

    Parameters
    ----------
    path : str or path-like
        The study file.
    config_text : str
        The resolved config (YAML); stored when the file is created.
    config_hash : str
        Hash of the config; must equal the stored one of an existing file.
    qoi_names : sequence of str
        QoI column names; stored when the file is created.
    create : bool
        Create the file (and missing parent directories) if it does not
        exist. If False, a missing file is an error.
    code_version : str, optional
        Recorded when creating; defaults to the installed roughuq version.
    role : str
        Recorded when creating: ``"study"``, or ``"shard"`` for a file of
        samples to merge into a study (:data:`ROLES`).

    Returns
    -------
    StudyFile
        Writable; close it (or use ``with``) to release the lock.

    Raises
    ------
    StudyFileError
        Missing file (``create=False``), unwritable directory, file locked by
        another process, not HDF5, truncated or damaged, another format or
        format version, written by another config, or (same config) storing
        other ``qoi_names`` than given. A refused file is not modified.
    """
    path = Path(os.fspath(path))
    if path.is_symlink():
        # Written through a link, the copy-on-write writes replaced the link by a file of their own (the study
        # behind it never got the samples), under a lock of the link's name: write to the file it names.
        path = Path(os.path.realpath(path))
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    if code_version is None:
        code_version = _installed_version()
    _check_before_lock(path, create=create)
    lock_fd = _acquire_lock(path)
    try:
        header = _prepare_locked(
            path,
            config_text=config_text,
            config_hash=config_hash,
            qoi_names=qoi_names,
            code_version=code_version,
            role=role,
        )
    except BaseException:
        _release_lock(path, lock_fd)
        raise
    return StudyFile(path, header, lock_fd=lock_fd)


def open_study_readonly(path: str | os.PathLike[str]) -> StudyFile:
    """Open an existing study file for reading (no lock, no config needed).

    The stored config is in ``config_text`` and ``config_hash``. The HDF5
    file is opened at the first read and stays open until
    :meth:`StudyFile.close`. Raises :class:`StudyFileError` like
    :func:`open_study`.
    """
    path = checked_study_path(path)
    header = _read_header(path)
    return StudyFile(path, header, lock_fd=None)

"""Shards: samples computed elsewhere (cluster jobs) and merged into the study.

:func:`compute_shard` writes a given range of samples to a shard file of its own (published under its name only
when complete, never over another file); :func:`merge_shards` checks shards against the study (same config and
columns, not the study file itself) and adds the samples it does not hold yet.
"""

from __future__ import annotations

import errno
import os
import shlex
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

from rough_uq import __version__
from rough_uq.errors import InvalidParameterError, RoughUQError, StudyFileError, checked_path
from rough_uq.study.executors import Executor
from rough_uq.study.progress import Progress
from rough_uq.study.records import read_run_records, read_screening_record
from rough_uq.problem.sampler import LevelBatch
from rough_uq.study.store import (
    PARTIAL_SUFFIX,
    StudyFile,
    StudyStore,
    incomplete_shard_name,
    open_study,
    open_study_readonly,
    remove_abandoned,
)
from rough_uq.study.pipeline.sampling import StudySampler
from rough_uq.study.pipeline.studies import Study, _differences_text, _readable_config


def _refuse_existing_shard(out: Path) -> None:
    """The refusal of an ``--out`` that exists: a shard to merge or remove, a study to keep, or another file.

    "merge or remove it first" of a study with a screening or runs advised deleting its results.
    """
    try:
        with open_study_readonly(out) as stored:
            role = stored.role
            has_results = read_screening_record(stored) is not None or bool(read_run_records(stored))
    except (RoughUQError, OSError):
        raise StudyFileError(f"--out {str(out)!r} exists and is not a shard (not a study file); choose another "
                             "--out", out) from None
    if role == "shard":
        raise StudyFileError(f"shard {str(out)!r} already exists; merge it (roughuq merge {shlex.quote(str(out))} "
                             "--into STUDY) or remove it first", out)
    what = " with results (a screening or runs)" if has_results else ""
    raise StudyFileError(f"--out {str(out)!r} is a study file{what}, not a shard; choose another --out", out)


def compute_shard(
    study: Study,
    *,
    stage: int,
    level: int,
    indices: np.ndarray,
    out: str | Path,
    executor: Executor,
    progress: Progress,
) -> Path:
    """Compute samples ``(stage, level, indices)`` of a study into the shard file ``out``.

    The shard is a study file with the study's config and hash holding just
    these samples. It is written under a temporary name and renamed to
    ``out`` only when complete, so a killed job never leaves a partial shard
    under the final name; what a job killed outright left under the
    temporary name (``out.partial-PID`` and its lock) is removed by the next
    run of the shard. The study itself is only read.
    """
    _refuse_writing_the_study(study, out)
    out = Path(out)
    if out.exists():
        _refuse_existing_shard(out)
    if not 0 <= level <= study.config.grid.max_level:
        allowed = f"an integer in 0..{study.config.grid.max_level} (grid.max_level)"
        raise InvalidParameterError("--level", level, allowed)
    abandoned = remove_abandoned(out, PARTIAL_SUFFIX)  # of this shard, by a run killed outright
    partial = out.with_name(f"{out.name}{PARTIAL_SUFFIX}{os.getpid()}")
    indices = np.unique(np.asarray(indices, dtype=np.int64))
    shard_store = open_study(
        partial,
        config_text=study.store.config_text,
        config_hash=study.store.config_hash,
        qoi_names=study.store.qoi_names,
        create=True,
        code_version=__version__,
        role="shard",
    )
    shard = Study(study.config, shard_store)
    progress.start(f"shard stage {stage} level {level}")
    for path in abandoned:
        progress.note(f"removed {path.name}, left by a run of this shard that was killed")
    try:
        with shard:
            progress.plan([level], [indices.size], [0])
            StudySampler(shard, stage=stage, executor=executor, progress=progress).compute(level, indices)
    except BaseException:
        partial.unlink(missing_ok=True)
        progress.stop(is_complete=False)
        raise
    try:
        _publish_shard(partial, out)  # a shard that cannot take its name is kept under another, never removed
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop()
    return out


def _publish_shard(partial: Path, out: Path) -> None:
    """Rename the complete shard ``partial`` to ``out``, never over a file that appeared there meanwhile.

    Two jobs given the same ``--out`` both passed the check at their start, and the second rename replaced the
    first one's shard: both said "130 samples written", one shard's samples were gone. A hard link fails where
    ``out`` exists; the shard is then kept under a name of its own, which the error names (status 2). Where the
    file system has no hard links, a last check and a rename (a window of microseconds instead of the job's run).
    """
    if not _rename_new(partial, out):
        _keep_clashing_shard(partial, out)


def _rename_new(partial: Path, target: Path) -> bool:
    """Rename ``partial`` to ``target`` unless a file has that name (False, ``partial`` left as it is): a hard
    link, which fails where ``target`` exists, then the old name removed; on a file system without hard links
    a check and a rename."""
    try:
        os.link(partial, target)
    except FileExistsError:
        return False
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        if target.exists():
            return False
        os.replace(partial, target)
        return True
    partial.unlink()
    return True


#: What ``os.link`` raises on a file system without hard links (and across devices).
_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS}


def _keep_clashing_shard(partial: Path, out: Path) -> NoReturn:
    """Keep ``partial`` as ``<stem>.<pid><suffix>`` beside ``out``, which another process wrote (or
    ``<stem>.<pid>-<k><suffix>`` where that name is taken too: never over a file), and say so."""
    names = (out.with_name(f"{out.stem}.{os.getpid()}{'' if k == 0 else f'-{k}'}{out.suffix}") for k in range(100))
    kept = next((name for name in names if _rename_new(partial, name)), partial)
    raise StudyFileError(
        f"shard {str(out)!r} was written by another process while this one computed its samples (two jobs with "
        f"the same --out?); this job's shard is kept as {str(kept)!r}: merge both (roughuq merge "
        f"{shlex.quote(str(out))} {shlex.quote(str(kept))} --into STUDY)", out)


def merge_shards(study: Study, shards: Sequence[str | Path]) -> dict[str, int]:
    """Add the samples of shard files to the study.

    Every shard is checked first: the study file itself (also through
    another path or a link), a shard of another config (hash) or with other
    QoI columns is refused before anything is written. Samples already in
    the study are skipped, never counted twice.

    Returns
    -------
    dict
        ``{"added": n, "duplicates": n, "studies": [paths]}``, ``studies`` the inputs that are study files, not
        shards (their samples are added; their screening and run records are not).
    """
    from rough_uq.study.store import DuplicateSampleWarning

    try:
        batches, studies = _read_shards(study, shards)
    except StudyFileError as exc:
        # Damaged rows read "... or start a new study file" (a study's remedy) and not what became of the others.
        text = str(exc).replace("or start a new study file", _SHARD_REMEDY)
        text = text if text.endswith("; nothing was merged") else f"{text}; nothing was merged"
        raise StudyFileError(text, exc.path) from None
    added = duplicates = 0
    for batch in batches:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DuplicateSampleWarning)
            n = study.store.append_samples(batch)
        added += n
        duplicates += batch.n_samples - n
    return {"added": added, "duplicates": duplicates, "studies": studies}


def _refuse_an_incomplete_shard(path: str | Path) -> None:
    """Refuse ``<shard>.partial-PID``, the name a shard has until `roughuq sample` completes it (it was merged
    without a word, although a shard is written whole or not at all)."""
    incomplete = incomplete_shard_name(path)
    if incomplete is not None:
        name, pid = incomplete
        raise StudyFileError(
            f"{path} is an incomplete shard (process {pid} had not finished it; got {str(path)!r}; allowed: "
            f"complete shards): run its `roughuq sample ... --out {name}` again, then merge {name}; nothing was "
            "merged", Path(path))


def _read_shards(study: Study, shards: Sequence[str | Path]) -> tuple[list[LevelBatch], list[str]]:
    """Every sample of ``shards``, each checked (:func:`merge_shards`), and the inputs that are study files."""
    batches: list[LevelBatch] = []
    studies = []
    for path in shards:
        _refuse_the_study_itself(study, path)
        _refuse_an_incomplete_shard(path)
        with _open_shard(path) as shard:
            _check_shard(study, path, shard)
            if shard.role != "shard":
                studies.append(str(path))
            for level in shard.levels():
                for stage in shard.stages(level=level):
                    batches.append(shard.read_samples(level=level, stage=stage))
    return batches, studies


def _open_shard(path: str | Path) -> StudyFile:
    """A shard for reading; a missing one refused as a shard (it was called a study file)."""
    if not Path(checked_path("shard", path)).exists():
        raise StudyFileError(f"{path}: no such shard file (`roughuq sample --out` writes one)", Path(path))
    return open_study_readonly(path)  # a damaged shard's remedy: merge_shards


#: What to do with a damaged shard, where a study's remedy says "start a new study file".
_SHARD_REMEDY = "or compute the shard again (`roughuq sample`)"


def _is_the_study_file(study: Study, path: str | Path) -> bool:
    """Whether ``path`` is the study's file (same device and inode: another path or a link too)."""
    target = getattr(study.store, "path", None)
    try:
        return target is not None and os.path.samefile(path, target)
    except OSError:  # a missing file
        return False


def _refuse_writing_the_study(study: Study, out: str | Path) -> None:
    """Refuse a shard ``out`` that is the study file (its refusal would otherwise say "remove it first")."""
    if _is_the_study_file(study, out):
        raise InvalidParameterError("--out", str(out), "a new shard file, not the study file (--study) itself")


def _refuse_the_study_itself(study: Study, path: str | Path) -> None:
    """Refuse a shard that is the study file (same file by device and inode: another path or a link too)."""
    target = getattr(study.store, "path", None)
    if _is_the_study_file(study, path):
        raise StudyFileError(
            f"shard {str(path)!r} is the study file {str(target)!r} itself (a file cannot be merged into "
            "itself); nothing was merged",
            path,
        )


def _check_shard(study: Study, path: str | Path, shard: StudyStore) -> None:
    """Refuse a shard of another config, or with other QoI columns than the study's (one of them is damaged)."""
    here = study.store
    if shard.config_hash != here.config_hash:
        shard_config = _readable_config(shard.config_text, source=f"{path} (stored config)")
        differences = _differences_text(shard_config, study.config, there="in the shard", here="in this study")
        raise StudyFileError(
            f"shard {str(path)!r} belongs to another study (config hash {shard.config_hash[:12]}, "
            f"this study {here.config_hash[:12]}{differences}); nothing was merged",
            path,
        )
    if tuple(shard.qoi_names) != tuple(here.qoi_names):
        raise StudyFileError(
            f"shard {str(path)!r} has the study's config hash but other QoI columns ({', '.join(shard.qoi_names)}; "
            f"this study: {', '.join(here.qoi_names)}), so it is damaged; nothing was merged",
            path,
        )

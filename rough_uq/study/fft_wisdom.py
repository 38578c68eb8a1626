"""FFTW wisdom kept on disk, so that measured plans are measured once per machine.

The core (:mod:`rough_uq.physics.fft`) measures plans and plans from wisdom; this edge
module reads and writes the wisdom file. The pipeline calls
:func:`prepare_wisdom` with the grids of a level before it computes samples
there and hands the returned bytes to every worker with the contact model, so
that all processes of a study use the same plans (bit-identical samples).

Where the file lives: ``$ROUGHUQ_FFTW_WISDOM`` if set, else
``$XDG_CACHE_HOME/roughuq/fftw-wisdom-<host>.json`` (``~/.cache`` when
``XDG_CACHE_HOME`` is unset); one file per host name, since wisdom describes one
machine. The file is JSON (``format``, ``version`` and FFTW's own text export
of the double, single and long-double wisdom): reading it runs no code, unlike
a pickle a stranger could have put in the cache directory.
``ROUGHUQ_FFTW_WISDOM=estimate`` (in any case) turns measured planning off
(``FFTW_ESTIMATE`` plans, nothing measured or written). An unreadable or
corrupt file is ignored and replaced; a file that cannot be written is said
(a warning among the progress notes: every command then measures again).
The file is written only when it gains plans, also when Ctrl-C or SIGTERM
stops the measuring (the plans measured by then are kept, and a rerun
measures only the rest), and the study's progress says when plans are being
measured (seconds per grid the first time, about 20 s at 1024^2). Processes of one machine read, measure
and write the file one at a time (a lock file beside it), so that two that
start at once do not measure the same grid twice and choose different plans.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rough_uq.physics.fft import export_wisdom, measure_plans

__all__ = ["wisdom_path", "load_wisdom", "prepare_wisdom", "wisdom_entries", "ESTIMATE"]

#: Value of ``ROUGHUQ_FFTW_WISDOM`` that turns measured planning off.
ESTIMATE = "estimate"


def wisdom_path() -> Path | None:
    """The wisdom file of this machine, or ``None`` when measured planning is off."""
    setting = os.environ.get("ROUGHUQ_FFTW_WISDOM", "")
    if setting.strip().lower() == ESTIMATE:  # "ESTIMATE" named a file of that name
        return None
    if setting:
        return Path(setting)
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    host = "".join(c if c.isalnum() or c in "-_." else "_" for c in platform.node()) or "host"
    return cache / "roughuq" / f"fftw-wisdom-{host}.json"


#: ``format`` and ``version`` of the wisdom file; a file with others is ignored (and replaced).
_FORMAT, _VERSION = "roughuq-fftw-wisdom", 1


def load_wisdom(path: Path) -> tuple[bytes, ...] | None:
    """The wisdom stored at ``path``; ``None`` if missing, unreadable or not a wisdom file of this version."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # JSON and Unicode errors are ValueErrors; deep nesting recurses
        return None
    if not (isinstance(data, dict) and data.get("format") == _FORMAT and data.get("version") == _VERSION):
        return None
    parts = data.get("wisdom")
    if not (isinstance(parts, list) and all(isinstance(part, str) for part in parts)):
        return None
    try:
        # FFTW exports wisdom as text; latin-1 maps every byte to one character and back.
        return tuple(part.encode("latin-1") for part in parts)
    except UnicodeEncodeError:
        return None


def _save(path: Path, wisdom: tuple[bytes, ...]) -> str | None:
    """Write ``wisdom`` to ``path``; returns why it could not (None once written)."""
    # Atomic replacement: concurrent studies on one machine never read half a file.
    text = json.dumps({"format": _FORMAT, "version": _VERSION, "wisdom": [part.decode("latin-1") for part in wisdom]})
    temporary = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
        os.replace(temporary, path)
    except OSError as error:
        # A read-only cache costs only the measuring time of the next run (which says so: prepare_wisdom).
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)
        return error.strerror or type(error).__name__
    return None


def prepare_wisdom(
    grids: Iterable[int], *, threads: int, note: Callable[[str], None] | None = None
) -> tuple[bytes, ...] | None:
    """Measured plans for ``grids`` (from the disk cache where it has them); the wisdom to ship to workers.

    Returns ``None`` when measured planning is off (``ROUGHUQ_FFTW_WISDOM=estimate``).
    ``note`` is told, in one line, when plans are about to be measured (the
    first use of a grid on this machine takes seconds, about 20 s at 1024^2).
    """
    path = wisdom_path()
    if path is None:
        return None

    def announce(missing: list[int]) -> None:
        grids_text = ", ".join(f"{n}x{n}" for n in missing)
        note(f"measuring FFT plans for {grids_text} (once per machine, kept in {path})")

    with _measuring_lock(path, note):
        stored = load_wisdom(path)  # read under the lock: what another process measured meanwhile is used
        try:
            wisdom = measure_plans(grids, threads=threads, wisdom=stored,
                                   before_measuring=None if note is None else announce)
        except KeyboardInterrupt:
            # Ctrl-C (or SIGTERM) lands between two plans: keep those measured, which a rerun would measure again
            # (tens of seconds at 1024^2-4096^2).
            _save_gained(path, stored, export_wisdom())
            raise
        failure = _save_gained(path, stored, wisdom)
    if failure is not None and note is not None:
        note(f"warning: the measured FFT plans could not be kept in {path} ({failure}): every command measures them "
             f"again; set ROUGHUQ_FFTW_WISDOM to a writable file (or to '{ESTIMATE}': no measured plans)")
    return wisdom


@contextmanager
def _measuring_lock(path: Path, note: Callable[[str], None] | None) -> Iterator[None]:
    """Hold an exclusive lock on ``<path>.lock`` while this process reads, measures and writes the wisdom.

    Two processes that measured the same grid at once (the shards of ``loop_study.sh --jobs 2`` on a machine
    without wisdom yet) could choose different plans, which round differently: the shards' samples were then not
    bit-identical to a serial run's. With the lock the second process waits (and says so) and plans from the
    first one's wisdom. Without ``fcntl`` (not POSIX) or where the lock file cannot be opened (a read-only
    cache) nothing is locked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - POSIX here
        yield
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path.with_name(path.name + ".lock"), "a")  # noqa: SIM115 - closed below
    except OSError:
        yield
        return
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if note is not None:
                note(f"waiting for another roughuq process measuring FFT plans (kept in {path})")
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _save_gained(path: Path, stored: tuple[bytes, ...] | None, wisdom: tuple[bytes, ...]) -> str | None:
    """Write ``wisdom`` to ``path`` if it holds plans ``stored`` (the file's) does not; why it could not, or None."""
    if stored is None or wisdom_entries(wisdom) != wisdom_entries(stored):
        return _save(path, wisdom)
    return None


def wisdom_entries(wisdom: tuple[bytes, ...]) -> list[list[bytes]]:
    """The plans ``wisdom`` holds, in a fixed order (FFTW exports the same wisdom in varying order)."""
    return [sorted(part.splitlines()) for part in wisdom]

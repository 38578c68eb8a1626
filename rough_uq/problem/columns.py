"""Names of result columns: a QoI's name, or ``<qoi>@<load>`` on a load curve.

No solver import (and no numpy), so that the config, the store and the report
name and split columns with the same functions as the contact problem
(:mod:`rough_uq.problem.loads` explains the naming).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

__all__ = ["LOAD_SEPARATOR", "load_label", "column_name", "column_of_load", "split_column", "tol_number", "tol_text",
           "values_text"]

#: Separates the QoI name from the load in the name of a load-curve column.
LOAD_SEPARATOR = "@"


def load_label(value: float) -> str:
    """The load ``value`` as written in column names: the shortest float repr (``0.05``, ``1e-05``)."""
    return repr(float(value))


def column_name(qoi: str, load: float) -> str:
    """The column of ``qoi`` at ``load`` on a load curve: ``<qoi>@<load>``."""
    return f"{qoi}{LOAD_SEPARATOR}{load_label(load)}"


def column_of_load(name: str, names: Sequence[str]) -> str:
    """``name``, or ``QOI@LOAD`` with the load written as column names write it (:func:`column_name`):
    ``@5``, ``@5.00`` and ``@5e0`` name ``@5.0`` (and are returned unchanged when not a load at all).

    ``show --load`` compared loads as numbers, ``--tol QOI@LOAD=EPS`` as text: ``@0.050`` was "not a QoI"; the
    column of a cdf run (``--qoi``, ``column=``) did not take ``@5`` for ``@5.0`` where ``--tol`` did.
    """
    qoi, at, load = name.partition(LOAD_SEPARATOR)
    if name in names or not at:
        return name
    try:
        return column_name(qoi, float(load))
    except ValueError:
        return name


def split_column(column: str) -> tuple[str, float | None]:
    """``(qoi, load)`` of a result column name; ``load`` is None for a single-load column."""
    name, separator, label = column.partition(LOAD_SEPARATOR)
    return (name, float(label)) if separator else (name, None)


def tol_text(names: Sequence[str], values: Iterable[float], *, digits: int | None = None) -> str:
    """Tolerances per column as ``--tol`` takes them: ``contact_area=2, clusters=0.5``.

    The columns of a load curve are grouped by QoI: the value most of its
    loads share, then the columns set apart, ``mean_gap=0.05,
    mean_gap@0.02=0.1`` (not one ``name@load=eps`` per column, which made a
    line of hundreds of characters). Values are written by :func:`tol_number`
    (``%g``, or ``digits`` significant digits), and grouped as written.
    """
    columns: dict[str, list[tuple[str, float]]] = {}
    for name, value in zip(names, values):
        columns.setdefault(split_column(name)[0], []).append((name, float(value)))
    parts = []
    for qoi, pairs in columns.items():
        if len(pairs) == 1:
            parts.append(f"{pairs[0][0]}={tol_number(pairs[0][1], digits)}")
            continue
        shown = [tol_number(value, digits) for _, value in pairs]
        common = max(shown, key=shown.count)
        parts += [f"{qoi}={common}"] + [f"{name}={text}" for (name, _), text in zip(pairs, shown) if text != common]
    return ", ".join(parts)


def tol_number(value: float, digits: int | None = None) -> str:
    """A tolerance as :func:`tol_text` and run names write it: ``%g``, or ``%.12g`` where six digits do not give
    it back (0.2500001 read 0.25; twelve, not all seventeen, so that ``0.1 * 3`` is written 0.3, as typed);
    with ``digits``, that many significant digits."""
    if digits is not None:
        return format(value, f".{digits}g")
    text = format(value, "g")
    return text if float(text) == value else format(value, ".12g")


def values_text(names: Sequence[str], values: Iterable[float], *, digits: int = 3) -> str:
    """Values that are not tolerances (errors, biases) per column, each under its own name: ``contact_area@0.1=1.2,
    contact_area@0.2=0.8`` (grouped as :func:`tol_text` does, one of them would read as the QoI's)."""
    return ", ".join(f"{name}={float(value):.{digits}g}" for name, value in zip(names, values))

"""Names of result columns: a QoI's name, or ``<qoi>@<load>`` on a load curve.

No solver import (and no numpy), so that the config, the store and the report
name and split columns with the same functions as the contact problem
(:mod:`rough_uq.problem.loads` explains the naming).
"""

from __future__ import annotations

__all__ = ["LOAD_SEPARATOR", "load_label", "column_name", "split_column"]

#: Separates the QoI name from the load in the name of a load-curve column.
LOAD_SEPARATOR = "@"


def load_label(value: float) -> str:
    """The load ``value`` as written in column names: the shortest float repr (``0.05``, ``1e-05``)."""
    return repr(float(value))


def column_name(qoi: str, load: float) -> str:
    """The column of ``qoi`` at ``load`` on a load curve: ``<qoi>@<load>``."""
    return f"{qoi}{LOAD_SEPARATOR}{load_label(load)}"


def split_column(column: str) -> tuple[str, float | None]:
    """``(qoi, load)`` of a result column name; ``load`` is None for a single-load column."""
    name, separator, label = column.partition(LOAD_SEPARATOR)
    return (name, float(label)) if separator else (name, None)

"""The multilevel core's warnings as typed entries of the records.

The core reports its checks as ``EstimationWarning``; the pipeline collects them here into the
:class:`~rough_uq.study.records.Diagnostic` entries of its records, never passed on as warnings.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from rough_uq.multilevel.statistics import EstimationWarning
from rough_uq.study.records import Diagnostic


@contextmanager
def collecting_diagnostics() -> Iterator[list[Diagnostic]]:
    """Collect the warnings raised inside (the core's ``EstimationWarning``) as :class:`Diagnostic` entries.

    The multilevel core reports its checks as warnings; records carry them as
    fields, so they are caught here, at the pipeline boundary, and never
    reach the user's warning filters. The list fills when the block ends.
    """
    diagnostics: list[Diagnostic] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EstimationWarning)
        yield diagnostics
    diagnostics.extend(Diagnostic(str(w.message)) for w in caught)


def unique_diagnostics(diagnostics: Sequence[Diagnostic]) -> tuple[Diagnostic, ...]:
    """``diagnostics`` without repeats, in first-seen order."""
    return tuple(dict.fromkeys(diagnostics))

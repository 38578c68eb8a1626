"""``python -m rough_uq``: the ``roughuq`` command line (:func:`rough_uq.console.run`), where the console script
is not on ``PATH``."""

from __future__ import annotations

if __name__ == "__main__":  # not when a spawned worker process imports the main module again
    from rough_uq.console import run

    run()

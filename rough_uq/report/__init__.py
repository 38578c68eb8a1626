"""What a study computed, for people: summary tables (:mod:`~rough_uq.report.summary`) and figures
(:mod:`~rough_uq.report.figures`, needs matplotlib)."""

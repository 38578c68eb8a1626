"""The contact problem as a level sampler: where physics meets MLMC.

* :mod:`~rough_uq.problem.batch`: :class:`LevelBatch`, what a batch of level samples carries
  (no solver import, so that the store and the report can use it).
* :mod:`~rough_uq.problem.sampler`: :class:`ContactModel` and how one coupled sample is
  computed from its seed (SPEC sections 3 and 7).
* :mod:`~rough_uq.problem.loads`: relative and absolute loads, the units of the quantities.
* :mod:`~rough_uq.problem.columns`: names of the result columns (``<qoi>@<load>`` on a load
  curve), without the solver, for the config, the store and the report.
* :mod:`~rough_uq.problem.contact`: :class:`ContactProblem` (a study in Python, no config
  file) and its level sampler.
* :mod:`~rough_uq.problem.kept`: the samples a problem keeps in memory (an interrupted run loses none).
* :mod:`~rough_uq.problem.memory`: a solve's memory against the machine's.
* :mod:`~rough_uq.problem.runs`: :func:`screen`, :func:`mlmc` and :func:`mc` on a problem,
  the functions ``rough_uq`` exports.
* :mod:`~rough_uq.problem.distribution`: :func:`variance` and :func:`distribution` on a problem.
"""

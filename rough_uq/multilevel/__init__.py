"""Multilevel Monte Carlo, independent of what is sampled (SPEC section 5).

Pure numpy/scipy; no I/O, never imports :mod:`rough_uq.physics`.

* :mod:`~rough_uq.multilevel.statistics`: level statistics, rate fits, the coarsest useful level,
  sample allocation (plans) and diagnostics.
* :mod:`~rough_uq.multilevel.drivers`: the adaptive MC and MLMC drivers (with Richardson
  extrapolation) as generators of events over a level sampler.
"""

"""Multilevel Monte Carlo, independent of what is sampled (SPEC section 5).

Pure numpy/scipy; no I/O, never imports :mod:`rough_uq.physics`.

* :mod:`~rough_uq.multilevel.statistics`: level statistics and diagnostics.
* :mod:`~rough_uq.multilevel.rates`: rate fits, the remaining bias and the coarsest useful level.
* :mod:`~rough_uq.multilevel.richardson`: Richardson extrapolation (weight, remaining bias, stability).
* :mod:`~rough_uq.multilevel.allocation`: sample allocation (plans).
* :mod:`~rough_uq.multilevel.drivers`: the adaptive MC and MLMC drivers (with Richardson
  extrapolation) as generators of events over a level sampler, a package: the events and result
  (``events``), sample storage and sampler calls (``samples``), the rates and allocation of a run
  (``planning``), its hierarchy (``hierarchy``), the loop MC and MLMC share (``loop``), adaptive MLMC
  (``adaptive``) and plain MC (``plain_mc``).
* :mod:`~rough_uq.multilevel.moments`: h-statistics, the variance and central moments.
* :mod:`~rough_uq.multilevel.distribution`: the smoothed-indicator CDF and its quantiles.
* :mod:`~rough_uq.multilevel.targets`: the adaptive driver of those targets (variance, CDF).
"""

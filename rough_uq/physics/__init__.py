"""The physics core: FFTs, rough surfaces, the elastic half-space, the contact solver, quantities of interest.

Pure numpy/scipy/pyFFTW/numba (SPEC sections 1-4); no I/O, never imports
:mod:`rough_uq.multilevel`.

* :mod:`~rough_uq.physics.fft`: cached real FFT plans, one normalisation, FFTW wisdom.
* :mod:`~rough_uq.physics.surface`: the power spectrum and Gaussian random surfaces, coupled across grids.
* :mod:`~rough_uq.physics.elastic`: the Westergaard kernel of the periodic half-space.
* :mod:`~rough_uq.physics.solver`: the preconditioned Polonsky-Keer contact solver.
* :mod:`~rough_uq.physics.load_curve`: one surface at several loads, each solve warm-started from the last.
* :mod:`~rough_uq.physics.qoi`: contact area (perimeter-corrected), clusters and other quantities.
* :mod:`~rough_uq.physics.reference`: analytic reference solutions.
"""

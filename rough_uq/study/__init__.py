"""The edges of a study: config, study file, executors, progress, and the pipeline that joins them.

* :mod:`~rough_uq.study.config`: the versioned YAML schema (pydantic), the only YAML reader.
* :mod:`~rough_uq.study.store`: the HDF5 study file (and its in-memory twin), the only h5py importer.
* :mod:`~rough_uq.study.records`: typed screening, run and plan records, to and from JSON.
* :mod:`~rough_uq.study.signals`: Ctrl-C and SIGTERM held back while the study file is written.
* :mod:`~rough_uq.study.executors`: serial, process pool and dask execution of sample batches.
* :mod:`~rough_uq.study.pipeline`: screening and estimation runs from a config into a store (a package of
  modules, one per step: studies, sampling, screening, planning, estimation, target runs, shards, sweeps).
* :mod:`~rough_uq.study.progress`: progress reporting passed into the pipeline.
* :mod:`~rough_uq.study.fft_wisdom`: measured FFT plans kept on disk per machine.
* :mod:`~rough_uq.study.resources`: time and memory a shard of samples needs (batch systems).
"""

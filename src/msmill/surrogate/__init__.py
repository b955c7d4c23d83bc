"""Training pipeline above the DEM: SQL store of run statistics, campaigns, Gaussian-process surrogate.

Sub-modules are imported on use (``import msmill.surrogate`` stays light):

* :mod:`msmill.surrogate.store` -- SQL store (SQLAlchemy + Alembic) of machines,
  design points, DEM runs, per-stage statistics, raw files and trained surrogates;
  ingest and export of run folders.
* :mod:`msmill.surrogate.campaign` -- campaigns of DEM runs executed on Dask.
* ``space`` (the 4-D design space and its input scaling), ``targets``
  (stage statistics <-> GP-regressable target vectors), ``gp`` (the estimator),
  ``stage_model`` (targets + GP: a surrogate of whole runs), ``accuracy``
  (leave-one-out figures), ``active`` (space-filling and batch acquisition),
  ``persist`` (versioned JSON), ``provider`` (stage-parameter provider for the
  mill model). See ``docs/surrogate.md`` and ``docs/campaign.md``.
"""

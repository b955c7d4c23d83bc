"""Training pipeline above the DEM: SQL store of run statistics, campaigns, surrogate.

Sub-modules are imported on use (``import msmill.surrogate`` stays light):

* :mod:`msmill.surrogate.store` -- SQL store (SQLAlchemy + Alembic) of machines,
  design points, DEM runs, per-stage statistics, raw files and trained surrogates;
  ingest and export of run folders.
* :mod:`msmill.surrogate.campaign` -- campaigns of DEM runs executed on Dask.
"""

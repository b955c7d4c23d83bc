"""The training pipeline: DEM runs planned, executed and stored, for the surrogate to learn from.

Imports core, :mod:`msmill.dem` and :mod:`msmill.surrogate` (never :mod:`msmill.model`); sub-modules
are imported on use:

* :mod:`msmill.pipeline.store` -- SQL store (SQLAlchemy + Alembic) of machines, design points, DEM
  runs, per-stage statistics, raw files and trained surrogates; ingest and export of run folders.
* :mod:`msmill.pipeline.campaign` -- campaigns of DEM runs executed on Dask, planned by active learning.
* :mod:`msmill.pipeline.export` -- a campaign as small JSON documents in git, and back.

See ``docs/campaign.md``.
"""

"""Training pipeline above the DEM: Gaussian-process surrogate of the stage statistics.

Modules: ``space`` (the 4-D design space and its input scaling), ``targets``
(stage statistics <-> GP-regressable target vectors), ``gp`` (the estimator),
``stage_model`` (targets + GP: a surrogate of whole runs), ``accuracy``
(leave-one-out figures), ``active`` (space-filling and batch acquisition),
``persist`` (versioned JSON), ``provider`` (stage-parameter provider for the
mill model). See ``docs/surrogate.md``. Nothing is imported eagerly.
"""

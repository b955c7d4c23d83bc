"""The Gaussian-process surrogate of per-stage DEM statistics, and what is fitted on DEM runs.

Imports only core (``import msmill.surrogate`` stays light; sub-modules are imported on use):
``space`` (the 4-D design space and its input scaling), ``targets`` (stage statistics <-> GP-regressable
target vectors), ``gp`` (the estimator), ``stage_model`` (targets + GP: a surrogate of whole runs),
``accuracy`` (leave-one-out figures), ``active`` (space-filling and batch acquisition), ``fidelity``
(slice-to-full-mill correction), ``persist`` (versioned JSON), ``provider`` (stage-parameter provider for
the mill model) and ``capacity`` (the DEM operating envelope's classifier). The store and campaigns that
produce the runs are :mod:`msmill.pipeline`. See ``docs/surrogate.md``.
"""

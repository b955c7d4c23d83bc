"""DEM of the multi-shaft mill: scene builder, run driver and per-stage statistics.

* :mod:`msmill.dem.mill.scene` builds the engine scene from a
  :class:`msmill.machine.Machine` and a design point (full mill or a periodic
  slice one flinger row long).
* :mod:`msmill.dem.mill.run` runs it to steady state, records a measurement
  window and writes raw events, snapshots and statistics.
* :mod:`msmill.dem.mill.stats` turns the raw tables into
  :class:`msmill.stageparams.RunStatistics`.
"""

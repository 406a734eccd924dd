"""Support for the tests and the benchmarks, kept out of the ground station's own package.

- :mod:`benchkit.synthetic`: closed-loop flights of our own linear eq.-8 model with known truth
  (checks the estimator against its own model; the independent truth is ``hil_replay.sim``);
- :mod:`benchkit.reference`: the plain multi-start least-squares output-error fit, the floor an
  identification must beat on held-out data (``groundstation bench heldout``);
- :mod:`benchkit.rerun_inspect`: a saved .rrd read back as a user sees it (tabs, views, entity
  tree, Rerun's chunk check), for the tests and ``groundstation bench rerun``;
- :mod:`benchkit.telemetry`: synthetic MAVLink telemetry logs (.tlog) for throughput benchmarks;
- :mod:`benchkit.onboard_logs`: large dataflash (.bin) and ULog (.ulg) logs for the log-reading and
  log-download benchmarks.

Installed beside ``groundstation`` so that ``groundstation bench`` finds it; the ground station
itself (everything but its ``bench`` commands) never imports it. The scenario sets of the blind
diagnosis test live with the simulator, in :mod:`hil_replay.scenarios`.
"""

"""The batch study behind ``scara-compare``: fuzzy against conventional coordination over many
generated scenarios, one module per job.

- :mod:`sim.study.variants`: the settings compared (the baseline, and each value a ``--sweep``
  gives a gain, a fuzzy input's term or the output peaks);
- :mod:`sim.study.jobs`: the scenarios generated, and the runs cut into batches of even cost
  for the batch simulator;
- :mod:`sim.study.pool`: where the batches run, a pool of worker processes or a Dask cluster;
- :mod:`sim.study.results`: the table, the jerk comparison, the CSV and the figures.

Split by job because each changes for its own reason (a parameter to sweep, the cost model of
a batch, an executor, a measure to report), and because ``benchmarks/bench_study.py`` runs the
jobs on the pool without the command line (:mod:`sim.compare`) or the reports.
"""

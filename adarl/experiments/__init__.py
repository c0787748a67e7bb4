"""The experiment tooling: many runs of recipes, where they run, and what they add up to.

* :mod:`~adarl.experiments.spec` - experiment specs (axes x seeds x budgets) and the runs they plan;
* :mod:`~adarl.experiments.execute` - one run, wherever it lands (``adarl run``/``resume`` in a child process);
* :mod:`~adarl.experiments.launchers` - local processes, Ray tasks, SLURM jobs;
* :mod:`~adarl.experiments.orchestrate` - :func:`~adarl.experiments.orchestrate.run_experiment`;
* :mod:`~adarl.experiments.progress` - the live progress board;
* :mod:`~adarl.experiments.sweep` - robustness sweeps of a trained run (Fig. 8);
* :mod:`~adarl.experiments.report` - reports across seeds (a hub over private modules), with the estimators in
  :mod:`~adarl.experiments.report.stats` (IQM, bootstrap intervals, probability of improvement);
* :mod:`~adarl.experiments.tune` - ``adarl tune``: the spec, the Optuna study and the command (a hub);
* :mod:`~adarl.experiments.bench` - ``adarl bench``: the side-by-side speed benchmark and, with ``--whole-run``,
  whole runs (process start to finished run folder) against SB3, with ``--pack`` packed seeds against solo seeds
  (a hub).
"""

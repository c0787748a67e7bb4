"""The experiment tooling: many runs of recipes, where they run, and what they add up to.

* :mod:`~adarl.experiments.spec` - experiment specs (axes x seeds x budgets) and the runs they plan;
* :mod:`~adarl.experiments.execute` - one run, wherever it lands (``adarl run``/``resume`` in a child process);
* :mod:`~adarl.experiments.launchers` - local processes, Ray tasks, SLURM jobs;
* :mod:`~adarl.experiments.orchestrate` - :func:`~adarl.experiments.orchestrate.run_experiment`;
* :mod:`~adarl.experiments.progress` - the live progress board;
* :mod:`~adarl.experiments.sweep` - robustness sweeps of a trained run (Fig. 8);
* :mod:`~adarl.experiments.aggregate` and :mod:`~adarl.experiments.stats` - reports across seeds, IQM and
  bootstrap intervals;
* :mod:`~adarl.experiments.bench` - ``adarl bench``, the side-by-side speed benchmark.
* :mod:`~adarl.experiments.bench_whole_run` - ``adarl bench --whole-run``: whole runs, process start to finished
  run folder, against SB3.
"""
